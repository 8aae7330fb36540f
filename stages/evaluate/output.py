"""The evaluate stage's output folder: the one place that spells its file names.

Files::

    limits.json                       the warning zone (``stages.evaluate.limits``)
    sweeps.json                       every sample of both sweeps
    tradeoffs/light_orbit.json        PSNR vs angle from the nearest training light (report chart)
    tradeoffs/expression_scale.json   PSNR vs weight scale
    light_orbit.png, expression_scale.png, orbit_strip.png
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pipeline.stage_output import StageOutput

_LIMITS = "limits.json"
_SWEEPS = "sweeps.json"
_TRADEOFFS = "tradeoffs"
_LIGHT_ORBIT = "light_orbit"
_EXPRESSION_SCALE = "expression_scale"
_ORBIT_STRIP = "orbit_strip.png"

#: The file name of the warning zone (``stages.evaluate.limits`` reads and writes its content).
LIMITS_FILE = _LIMITS

#: The names no module outside ``stages/evaluate`` may spell (``tests/test_output_contracts.py``).
CONTRACT_NAMES = (_LIMITS, _SWEEPS, f"{_LIGHT_ORBIT}.png", f"{_EXPRESSION_SCALE}.png", _ORBIT_STRIP)


class EvaluateOutput(StageOutput):
    """The ``evaluate`` object: the stability sweeps and the measured warning zone."""

    stage = "evaluate"

    @property
    def limits_path(self) -> Path:
        return self.file(_LIMITS)

    @property
    def sweeps_path(self) -> Path:
        return self.file(_SWEEPS)

    def write_sweeps(self, samples: dict[str, Any]) -> None:
        self.sweeps_path.write_text(json.dumps(samples, indent=1) + "\n", encoding="utf-8")

    def sweeps(self) -> dict[str, Any]:
        return self.read_json(_SWEEPS)

    @property
    def light_orbit_series_path(self) -> Path:
        return self.file(_TRADEOFFS, f"{_LIGHT_ORBIT}.json")

    @property
    def expression_series_path(self) -> Path:
        return self.file(_TRADEOFFS, f"{_EXPRESSION_SCALE}.json")

    @property
    def light_orbit_png_path(self) -> Path:
        return self.file(f"{_LIGHT_ORBIT}.png")

    @property
    def expression_png_path(self) -> Path:
        return self.file(f"{_EXPRESSION_SCALE}.png")

    @property
    def orbit_strip_path(self) -> Path:
        return self.file(_ORBIT_STRIP)
