"""The calibrate stage's output folder: the one place that spells its file names.

Files::

    cameras.json         the calibrated cameras at the performance images' resolution
    cameras_native.json  the same at the board images' (native) resolution
    colmap/text, colmap/binary   COLMAP model at the board images' resolution
    board_poses.json     world_from_board of every board frame used
    report.json          per camera: frames and corners used, reprojection RMS, intrinsics
    residuals/<cam>.png  reprojection residuals drawn over the image

Camera files are ``scene.camera.save_cameras`` files; a missing or malformed file raises one
``InputError`` naming it and saying to rerun the calibrate stage.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pipeline.stage_output import StageOutput
from scene.camera import Camera, load_cameras, save_cameras

_CAMERAS = "cameras.json"
_CAMERAS_NATIVE = "cameras_native.json"
_COLMAP = "colmap"
_BOARD_POSES = "board_poses.json"
_REPORT = "report.json"
_RESIDUALS = "residuals"

#: The names no module outside ``stages/calibrate`` may spell (``tests/test_output_contracts.py``).
CONTRACT_NAMES = (_CAMERAS, _CAMERAS_NATIVE, _COLMAP, _BOARD_POSES, _REPORT, _RESIDUALS)


class CalibrateOutput(StageOutput):
    """The ``calibrate`` object: calibrated cameras, COLMAP export, board poses, report."""

    stage = "calibrate"

    @property
    def cameras_path(self) -> Path:
        return self.file(_CAMERAS)

    def cameras(self) -> list[Camera]:
        """The calibrated cameras at the performance resolution (``cam_from_world``: the studio world)."""
        return self.load(self.cameras_path, lambda path: load_cameras(path, "world"))

    def write_cameras(self, cameras: list[Camera]) -> None:
        save_cameras(self.cameras_path, cameras)

    @property
    def cameras_native_path(self) -> Path:
        return self.file(_CAMERAS_NATIVE)

    def has_cameras_native(self) -> bool:
        return self.cameras_native_path.is_file()

    def cameras_native(self) -> list[Camera]:
        """The calibrated cameras at the board images' resolution (``cam_from_world``)."""
        return self.load(self.cameras_native_path, lambda path: load_cameras(path, "world"))

    def write_cameras_native(self, cameras: list[Camera]) -> None:
        save_cameras(self.cameras_native_path, cameras)

    @property
    def colmap_dir(self) -> Path:
        return self.file(_COLMAP)

    def write_board_poses(self, data: dict[str, Any]) -> None:
        self.write_json(data, _BOARD_POSES, indent=1)

    def board_poses(self) -> dict[str, Any]:
        return self.read_json(_BOARD_POSES, keys=("world_from_board",))

    def write_report(self, report: dict[str, Any]) -> None:
        self.write_json(report, _REPORT, indent=1)

    def report(self) -> dict[str, Any]:
        return self.read_json(_REPORT, keys=("cameras",))

    def residuals_path(self, cam: str) -> Path:
        """``residuals/<cam>.png`` (the folder is made by ``make_residuals_dir``)."""
        return self.file(_RESIDUALS, f"{cam}.png")

    def make_residuals_dir(self) -> None:
        self.file(_RESIDUALS).mkdir()
