"""The stabilize stage's output folder: the one place that spells its file names.

Files::

    cameras_head.json  per frame, every camera with its pose relative to the head
                       (format: ``stages.stabilize.cameras_head``)

A missing or malformed file raises one ``InputError`` naming it and saying to rerun stabilize.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from pipeline.stage_output import StageOutput
from scene.camera import Camera
from stages.stabilize.cameras_head import read_cameras_head, write_cameras_head

_CAMERAS_HEAD = "cameras_head.json"

#: The names no module outside ``stages/stabilize`` may spell (``tests/test_output_contracts.py``).
CONTRACT_NAMES = (_CAMERAS_HEAD,)


class StabilizeOutput(StageOutput):
    """The ``stabilize`` object: per-frame cameras in head space."""

    stage = "stabilize"

    @property
    def cameras_head_path(self) -> Path:
        return self.file(_CAMERAS_HEAD)

    def cameras_head(self) -> dict[int, list[Camera]]:
        """Frame index -> cameras posed in the head frame (``cam_from_head``)."""
        return self.load(self.cameras_head_path, read_cameras_head)

    def cameras_head_by_name(self) -> dict[int, dict[str, Camera]]:
        """Frame index -> camera name -> camera posed in the head frame."""
        return {index: {cam.name: cam for cam in cams} for index, cams in self.cameras_head().items()}

    def write_cameras_head(self, index: Sequence[int], world_from_head_R: np.ndarray,
                           world_from_head_t: np.ndarray, cameras: Sequence[Camera]) -> None:
        write_cameras_head(self.cameras_head_path, index, world_from_head_R, world_from_head_t, cameras)
