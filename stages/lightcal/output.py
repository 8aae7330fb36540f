"""The lightcal stage's output folder: the one place that spells its file names.

Files::

    bars.json     {"bars": [{id, center_world, axis_world, length_m, intensity, normal_world,
                  fit statistics}], "missing": [bar ids left out]} (the truth's schema)
    spheres.json  the mirror balls: radius_m, centers_world, outline_rms_m
    report.json   per bar (``bar<b:02d>``): the highlights used and the fit

A missing or malformed file raises one ``InputError`` naming it and saying to rerun lightcal.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pipeline.stage_output import StageOutput

_BARS = "bars.json"
_SPHERES = "spheres.json"
_REPORT = "report.json"

#: The names no module outside ``stages/lightcal`` may spell (``tests/test_output_contracts.py``).
CONTRACT_NAMES = (_BARS, _SPHERES, _REPORT)


class LightcalOutput(StageOutput):
    """The ``lightcal`` object: the placed LED bars (world space) and the mirror balls."""

    stage = "lightcal"

    @property
    def bars_path(self) -> Path:
        return self.file(_BARS)

    def bars(self) -> list[dict[str, Any]]:
        """The placed bars (``bars.json`` entries: id, center_world, axis_world, length_m, ...)."""
        return self.read_json(_BARS, keys=("bars",))["bars"]

    def write_bars(self, bars: list[dict[str, Any]], missing: list[int]) -> None:
        self.write_json({"bars": bars, "missing": missing}, _BARS, indent=1)

    def spheres(self) -> dict[str, Any]:
        return self.read_json(_SPHERES, keys=("radius_m", "centers_world"))

    def write_spheres(self, spheres: dict[str, Any]) -> None:
        self.write_json(spheres, _SPHERES, indent=1)

    def report(self) -> dict[str, Any]:
        """Per bar (``bar<b:02d>``): highlights used, residuals or the reason it was not placed."""
        return self.read_json(_REPORT)

    def write_report(self, report: dict[str, Any]) -> None:
        self.write_json(report, _REPORT, indent=1)
