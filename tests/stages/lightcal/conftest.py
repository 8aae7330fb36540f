"""The small calibration take (same files as tests/stages/calibrate use: rendered once per session)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location(
    "calibrate_test_support", Path(__file__).resolve().parents[1] / "calibrate" / "conftest.py")
_support = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_support)


@pytest.fixture(scope="session")
def calib_capture(tmp_path_factory) -> tuple[Path, Path]:
    """(capture folder, truth folder) of the small calibration take."""
    return _support.small_capture(tmp_path_factory.getbasetemp())


WINDOW_CAMERAS = ("cam00", "cam01", "cam02", "cam05", "cam07")
WINDOW_BARS = (2, 6, 20)  # bar 6 is the rig's extreme side bar: grazing highlights in the front cameras


@pytest.fixture(scope="session")
def window_capture(tmp_path_factory) -> tuple[Path, Path]:
    """(capture, truth) of a mirror take alone at the tiny preset's 240x320 with native (768x1024) windows.

    5 cameras, 3 bars; about 4 s to render. The truth holds the cameras at 240x320 (lightcal rescales
    them to the windows), the bars and the ball centres.
    """
    import json

    from hardware.studio.calibration_takes import (BarLight, CalibrationTakeParams, render_mirror_take,
                                                   takes_from_rig)
    from scene.camera import save_cameras
    from scene.rig import default_rig

    root = tmp_path_factory.mktemp("window_take")
    rig = default_rig()
    coarse = [c for c in rig.cameras_at(0.3125) if c.name in WINDOW_CAMERAS]
    native = [c for c in rig.cameras_at(1.0) if c.name in WINDOW_CAMERAS]
    light_bars = [b for b in rig.light_bars() if b.id in WINDOW_BARS]
    bars = [BarLight(b.id, b.center_world, b.axis_world, b.length_m, b.intensity, b.normal_world) for b in light_bars]
    _, spheres = takes_from_rig(rig)
    params = CalibrationTakeParams(seed=3, volume_center_m=tuple(rig.head_center_m))
    render_mirror_take(coarse, bars, root / "capture", root / "truth", params, spheres, roi_cameras=native)
    save_cameras(root / "truth" / "cameras.json", coarse)
    (root / "truth" / "bars.json").write_text(json.dumps({"bars": [b.to_dict() for b in light_bars]}))
    return root / "capture", root / "truth"
