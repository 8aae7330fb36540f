"""A small virtual-studio calibration take shared by the calibrate and lightcal tests (rendered once)."""

from __future__ import annotations

import fcntl
import json
from pathlib import Path

import pytest

SMALL_CAMERAS = ("cam00", "cam01", "cam02", "cam05", "cam07")
SMALL_BARS = (2, 9, 20)
BOARD_SCALE = 0.5


def small_capture(base: Path) -> tuple[Path, Path]:
    """Render (once per test session) 5 cameras, 14 board poses, 3 bars; (capture, truth).

    The mirror take is at the tiny preset's 240x320; the board take at half the rig's native
    resolution (384x512), a cheaper stand-in for the capture's native-resolution board take.
    """
    from hardware.studio.calibration_takes import CalibrationTakeParams, render_rig_takes

    root = base / "small_calib_capture"
    root.mkdir(parents=True, exist_ok=True)
    with open(root / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (root / "done").exists():
            render_rig_takes(root / "capture", root / "truth", CalibrationTakeParams(poses=14, seed=3),
                             camera_names=SMALL_CAMERAS, bar_ids=SMALL_BARS, board_scale=BOARD_SCALE)
            # the capture stage's manifest lists every camera, also one whose takes are missing
            (root / "capture" / "manifest.json").write_text(json.dumps(
                {"cameras": list(SMALL_CAMERAS), "width": 240, "height": 320}))
            (root / "done").write_text("ok")
    return root / "capture", root / "truth"


@pytest.fixture(scope="session")
def calib_capture(tmp_path_factory) -> tuple[Path, Path]:
    """(capture folder, truth folder) of the small calibration take."""
    return small_capture(tmp_path_factory.getbasetemp())
