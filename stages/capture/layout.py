"""The folder layout of a capture to import (``stages/capture/README.md``): the one place that spells its names.

``CaptureFolder(root)``::

    capture.json                    subject, fps, bars, cameras (optional), takes (optional)
    rig.yaml                        optional: the studio's rig (camera names, nominal bar positions, ...)
    controller_log.json             the LED controller's log, {"entries": [...]} or a bare list
    cameras/<cam>/*.exr             each camera's images in arrival order (sorted by file name)
    cameras/<cam>/timestamps.json   optional: the camera's time stamp of each image, seconds
    scans/, calib/                  optional: the actor's scans, the calibration takes

Read by ``stages.capture.check`` (and through it the importer), written by
``stages.capture.export``.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

_INFO = "capture.json"
_RIG = "rig.yaml"
_CONTROLLER_LOG = "controller_log.json"
_CAMERAS = "cameras"
_TIMESTAMPS = "timestamps.json"
_IMAGE_SUFFIX = ".exr"
_SCANS = "scans"
_CALIB = "calib"


class CaptureFolder:
    """Paths of one capture folder in the import layout (nothing is read or created here)."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)

    @property
    def info_path(self) -> Path:
        return self.root / _INFO

    @property
    def rig_path(self) -> Path:
        return self.root / _RIG

    @property
    def log_path(self) -> Path:
        return self.root / _CONTROLLER_LOG

    @property
    def cameras_dir(self) -> Path:
        return self.root / _CAMERAS

    def camera_dir(self, cam: str) -> Path:
        return self.cameras_dir / cam

    def camera_names(self) -> list[str]:
        """The camera folders present, sorted (empty when there is no ``cameras/``)."""
        if not self.cameras_dir.is_dir():
            return []
        return sorted(p.name for p in self.cameras_dir.iterdir() if p.is_dir())

    def images(self, cam: str) -> list[Path]:
        """The camera's images in arrival order: sorted by file name."""
        return sorted(self.camera_dir(cam).glob(f"*{_IMAGE_SUFFIX}"))

    def image_path(self, cam: str, arrival: int) -> Path:
        """The name the exporter gives the camera's ``arrival``-th image (``000000.exr``, ...)."""
        return self.camera_dir(cam) / f"{int(arrival):06d}{_IMAGE_SUFFIX}"

    def timestamps_path(self, cam: str) -> Path:
        return self.camera_dir(cam) / _TIMESTAMPS

    @property
    def scans_dir(self) -> Path:
        return self.root / _SCANS

    @property
    def calib_dir(self) -> Path:
        return self.root / _CALIB

    def relative(self, path: Path) -> str:
        """``path`` as the user sees it under the folder (``cameras/cam03/000017.exr``)."""
        try:
            return Path(path).relative_to(self.root).as_posix() or "."
        except ValueError:
            return str(path)


def link_or_copy(src: Path, dst: Path) -> None:
    """Hard-link ``src`` to ``dst``; copy once when linking is impossible (another file system)."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)
