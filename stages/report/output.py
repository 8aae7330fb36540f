"""The report stage's output folder: the one place that spells its file names.

Files::

    report.html    self-contained (images inlined), opens offline
    charts/*.png   the charts, also inlined in the page
    summary.json   every stage's merged metrics and every target's verdict
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pipeline.stage_output import StageOutput

_HTML = "report.html"
_SUMMARY = "summary.json"
_CHARTS = "charts"

#: The names no module outside ``stages/report`` may spell (``tests/test_output_contracts.py``).
CONTRACT_NAMES = (_HTML, _SUMMARY)


class ReportOutput(StageOutput):
    """The ``report`` object: the HTML page, its charts and the merged figures."""

    stage = "report"

    @property
    def html_path(self) -> Path:
        return self.file(_HTML)

    def write_html(self, page: str) -> None:
        self.html_path.write_text(page, encoding="utf-8")

    @property
    def summary_path(self) -> Path:
        return self.file(_SUMMARY)

    def write_summary(self, summary: dict[str, Any]) -> None:
        self.summary_path.write_text(json.dumps(summary, indent=1), encoding="utf-8")

    def summary(self) -> dict[str, Any]:
        return self.read_json(_SUMMARY, keys=("metrics", "targets"))

    @property
    def charts_dir(self) -> Path:
        return self.file(_CHARTS)
