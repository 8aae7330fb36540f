"""The matte stage's output folder: the one place that spells its file names.

Files::

    mattes/<cam>/<index:06d>.png   16-bit alpha, one per received image
    contact_sheet.png              mattes of a few frames from every camera
    model.json                     which model was used and its training and SOC records

``matte_eval`` writes ``per_image.json`` (every image's measures).

A missing or unreadable matte raises one ``InputError`` naming it and saying to rerun matte.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.stage_output import StageOutput

_MATTES = "mattes"
_CONTACT_SHEET = "contact_sheet.png"
_MODEL = "model.json"
_PER_IMAGE = "per_image.json"  # matte_eval's output

#: The names no module outside ``stages/matte`` may spell (``tests/test_output_contracts.py``);
#: ``model.json`` is also the name of ``avatar.io``'s model record, so it is not one of them.
CONTRACT_NAMES = (_MATTES, _CONTACT_SHEET, _PER_IMAGE)


def write_per_image(folder: Path, records: list[dict[str, Any]]) -> None:
    """``matte_eval``'s output: ``per_image.json``, every image's measures."""
    (Path(folder) / _PER_IMAGE).write_text(json.dumps(records, indent=0))


class MatteOutput(StageOutput):
    """The ``matte`` object: an alpha matte for every captured image."""

    stage = "matte"

    def mattes_dir(self, cam: str) -> Path:
        """``mattes/<cam>/`` (not created)."""
        return self.file(_MATTES, cam)

    def matte_path(self, cam: str, index: int) -> Path:
        return self.file(_MATTES, cam, f"{int(index):06d}.png")

    def has_matte(self, cam: str, index: int) -> bool:
        return self.matte_path(cam, index).is_file()

    def matte(self, cam: str, index: int) -> np.ndarray:
        """The alpha [H, W] float (0..1) of camera ``cam`` at frame ``index``."""
        from scene.image_io import read_png16

        return self.load(self.matte_path(cam, index), read_png16)

    @property
    def contact_sheet_path(self) -> Path:
        return self.file(_CONTACT_SHEET)

    def model_record(self) -> dict[str, Any]:
        return self.read_json(_MODEL)

    def write_model_record(self, record: dict[str, Any]) -> None:
        self.file(_MODEL).write_text(json.dumps(record, indent=1, sort_keys=True, default=str))
