"""lightcal / lightcal_eval on a small virtual-studio take: accuracy, geometry helpers, bad input."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.testing import run_stage_for_test
from scene.camera import Camera, look_at
from scene.image_io import read_exr, write_exr
from stages.lightcal.eval_stage import STAGE as EVAL_STAGE
from stages.lightcal.solve import closest_point, robust_closest_point
from stages.lightcal.spheres import cone_centre
from stages.lightcal.stage import STAGE


def _run(capture: Path, calibrate: Path, truth: Path, work: Path, **params) -> dict:
    out = run_stage_for_test(STAGE, work, inputs={"capture": capture, "calibrate": calibrate}, params=params)
    ev = run_stage_for_test(EVAL_STAGE, work, inputs={"lightcal": out, "capture.truth": truth})
    return {**json.loads((out / "metrics.json").read_text()), **json.loads((ev / "metrics.json").read_text()),
            "_out": out}


@pytest.fixture(scope="module")
def placed(calib_capture, tmp_path_factory):
    capture, truth = calib_capture
    # the true cameras isolate the light calibration from the camera calibration's error
    return _run(capture, truth, truth, tmp_path_factory.mktemp("lightcal"))


def test_accuracy_against_ground_truth(placed):
    # 5 cameras at 240x320 with 384x512 windows give ~18 highlights per bar (~22 mm mean, ~39 mm max);
    # native windows do much better (test_windows.py, bench_lightcal.py)
    assert placed["bars"] == 3 and placed["spheres"] == 4
    assert placed["cameras_with_windows"] == 5
    assert placed["bar_center_err_mm_mean"] <= 35.0
    assert placed["bar_center_err_mm_max"] <= 60.0
    assert placed["bar_axis_err_deg_max"] <= 5.0
    assert placed["residual_mm_mean"] <= 25.0


def test_bars_json_has_the_truth_schema(placed, calib_capture):
    ours = json.loads((placed["_out"] / "bars.json").read_text())["bars"]
    truth = json.loads((calib_capture[1] / "bars.json").read_text())["bars"]
    assert [b["id"] for b in ours] == [b["id"] for b in truth]
    for b in ours:
        for key in ("id", "center_world", "axis_world", "length_m", "intensity", "normal_world"):
            assert key in b
        assert abs(np.linalg.norm(b["axis_world"]) - 1) < 1e-9


def test_spheres_are_located_to_a_fraction_of_a_millimetre(placed, calib_capture):
    found = np.asarray(json.loads((placed["_out"] / "spheres.json").read_text())["centers_world"])
    true = np.asarray(json.loads((calib_capture[1] / "mirror_spheres.json").read_text())["centers_world"])
    err = [np.min(np.linalg.norm(true - c, axis=1)) for c in found]
    assert max(err) < 0.5e-3


def _mirror_images(capture: Path, name: str) -> list[Path]:
    """The full images ``calib/mirror/*/<name>.exr`` and their native windows (``calib/mirror_roi``)."""
    return (sorted((capture / "calib" / "mirror").glob(f"*/{name}.exr"))
            + sorted((capture / "calib" / "mirror_roi").glob(f"*/{name}_*.exr")))


def test_bar_never_lit_fails_naming_it_or_is_left_out(calib_capture, tmp_path):
    capture, truth = calib_capture
    capture = Path(shutil.copytree(capture, tmp_path / "capture"))
    for path in _mirror_images(capture, "bar09"):
        img = read_exr(path)
        write_exr(path, np.full_like(img, float(np.median(img))))
    with pytest.raises(InputError, match="bar 9: highlight found in only 0"):
        run_stage_for_test(STAGE, tmp_path / "w1", inputs={"capture": capture, "calibrate": truth})
    m = _run(capture, truth, truth, tmp_path / "w2", allow_missing_bars=True)
    assert m["bars"] == 2 and m["bars_missing"] == 1


def test_overexposed_highlights_warn_and_still_place_the_bar(calib_capture, tmp_path, caplog):
    capture, truth = calib_capture
    capture = Path(shutil.copytree(capture, tmp_path / "capture"))
    for path in (capture / "calib" / "mirror").glob("*/bar20.exr"):
        write_exr(path, np.minimum(read_exr(path) * 6.0, 1.0))  # clipped at the sensor's white level
    with caplog.at_level(logging.WARNING):
        m = _run(capture, truth, truth, tmp_path / "w", use_windows=False)
    assert "bar 20:" in caplog.text and "over-exposed" in caplog.text
    assert m["bars"] == 3 and m["bar_center_err_mm_max"] <= 150.0


def test_no_balls_in_view_fails_clearly(calib_capture, tmp_path):
    capture, truth = calib_capture
    capture = Path(shutil.copytree(capture, tmp_path / "capture"))
    for path in _mirror_images(capture, "room"):
        write_exr(path, np.full_like(read_exr(path), 0.01))
    with pytest.raises(InputError, match="no mirror ball was found"):
        run_stage_for_test(STAGE, tmp_path / "w", inputs={"capture": capture, "calibrate": truth})


def test_closest_point_is_exact_for_rays_through_a_point():
    rng = np.random.default_rng(1)
    target = np.array([0.3, -0.2, 1.1])
    origins = rng.normal(size=(7, 3))
    dirs = target - origins
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    assert np.allclose(closest_point(origins, dirs), target)
    dirs[0] = np.array([1.0, 0.0, 0.0])  # one wild ray barely moves the robust estimate
    assert np.linalg.norm(robust_closest_point(origins, dirs)[0] - target) < 1e-3


def test_cone_centre_recovers_a_sphere_from_its_exact_outline():
    cam = Camera("c", 320, 240, 500.0, 500.0, 160.0, 120.0, (-0.05, 0.01, 0.0, 0.0, 0.0),
                 look_at(np.array([0.1, 0.2, 1.0]), np.zeros(3)))
    centre, radius = np.array([0.05, -0.03, 0.02]), 0.04
    # tangent rays: directions at the cone's half-angle around the axis to the centre
    to_c = centre - cam.center_world
    dist = np.linalg.norm(to_c)
    axis = to_c / dist
    alpha = np.arcsin(radius / dist)
    e1 = np.cross(axis, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    th = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    dirs = np.cos(alpha) * axis + np.sin(alpha) * (np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2)
    uv, _ = cam.project(cam.center_world + dirs)
    est, est_axis = cone_centre(cam, uv, radius)
    assert np.linalg.norm(est - centre) < 1e-6 and np.allclose(est_axis, axis, atol=1e-8)


def test_cameras_are_rescaled_to_the_mirror_take_resolution(calib_capture):
    from scene.camera import load_cameras
    from stages.capture.output import CaptureOutput
    from stages.lightcal.stage import _at_mirror_resolution

    capture, truth = calib_capture
    true = {c.name: c for c in load_cameras(truth / "cameras.json")}  # 240x320, as the mirror take
    native = {n: c.scaled(3.2) for n, c in true.items()}  # calibrated at 768x1024
    back = _at_mirror_resolution(native, CaptureOutput(capture), "room.exr")
    for n, c in back.items():
        assert (c.width, c.height) == (240, 320)
        assert abs(c.cx - true[n].cx) < 1e-9 and abs(c.fy - true[n].fy) < 1e-9
