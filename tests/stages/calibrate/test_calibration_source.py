"""``calibrate.source``: an existing COLMAP model or OpenCV-style files instead of the board takes."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.testing import run_stage_for_test
from scene.camera import load_cameras
from stages.calibrate.eval_stage import STAGE as EVAL_STAGE
from stages.calibrate.sources import (
    camera_name_of_image,
    read_calibration_source,
    read_colmap_model,
    write_opencv_cameras,
)
from stages.calibrate.stage import STAGE


@pytest.fixture(scope="module")
def board_run(calib_capture, tmp_path_factory):
    """The board-take calibration (its COLMAP export is the source under test) and its metrics."""
    capture, _ = calib_capture
    work = tmp_path_factory.mktemp("calibrate_board")
    out = run_stage_for_test(STAGE, work, inputs={"capture": capture})
    return out, json.loads((out / "metrics.json").read_text())


def _run(capture, truth, work, params):
    out = run_stage_for_test(STAGE, work, inputs={"capture": capture}, params=params)
    ev = run_stage_for_test(EVAL_STAGE, work, inputs={"calibrate": out, "capture.truth": truth})
    return out, {**json.loads((out / "metrics.json").read_text()), **json.loads((ev / "metrics.json").read_text())}


@pytest.mark.parametrize("kind", ["text", "binary"])
def test_a_colmap_model_gives_the_board_calibration_back(board_run, calib_capture, tmp_path, kind):
    board, board_metrics = board_run
    capture, truth = calib_capture
    out, m = _run(capture, truth, tmp_path, {"source": str(board / "colmap" / kind)})
    native = {c.name: c for c in load_cameras(board / "cameras_native.json")}
    again = {c.name: c for c in load_cameras(out / "cameras_native.json")}
    assert set(again) == set(native)
    for name, cam in again.items():
        # COLMAP's +0.5 pixel centres are undone on the way in: the principal point comes back exactly.
        assert abs(cam.cx - native[name].cx) < 1e-9 and abs(cam.fy - native[name].fy) < 1e-9
        assert np.allclose(cam.cam_from_world.matrix(), native[name].cam_from_world.matrix(), atol=1e-12)
    assert load_cameras(out / "cameras.json")[0].width == 240  # scaled to the performance images
    # The model's own points reproject as the board calibration's corners did.
    assert m["reproj_rms_px"] == pytest.approx(board_metrics["reproj_rms_px"], rel=1e-6)
    assert m["calibration_from_source"] == 1 and m["cameras"] == 5
    assert m["rotation_err_deg_max"] <= 0.08 and m["center_err_mm_max"] <= 0.8  # accuracy against the truth
    report = json.loads((out / "report.json").read_text())
    assert report["source_kind"] == "colmap" and report["cameras"]["cam00"]["points"] > 0


def test_opencv_files_json_and_yaml(board_run, calib_capture, tmp_path):
    import cv2

    board, _ = board_run
    capture, truth = calib_capture
    cameras = load_cameras(board / "cameras_native.json")
    write_opencv_cameras(tmp_path / "rig.json", cameras)
    _, m = _run(capture, truth, tmp_path / "a", {"source": str(tmp_path / "rig.json")})
    assert m["cameras"] == 5 and "reproj_rms_px" not in m  # no points in OpenCV files
    assert m["rotation_err_deg_max"] <= 0.08
    # A folder of cv::FileStorage YAML files, translations in millimetres.
    folder = tmp_path / "yaml"
    folder.mkdir()
    for cam in cameras:
        fs = cv2.FileStorage(str(folder / f"{cam.name}.yaml"), cv2.FILE_STORAGE_WRITE)
        fs.write("camera_matrix", cam.K)
        fs.write("distortion_coefficients", np.asarray(cam.dist)[None])
        fs.write("rvec", cv2.Rodrigues(cam.cam_from_world.R)[0])
        fs.write("tvec", cam.cam_from_world.t * 1000.0)
        fs.write("image_width", cam.width)
        fs.write("image_height", cam.height)
        fs.release()
    read = read_calibration_source(folder, units_m=0.001)
    assert read.kind == "opencv"
    for cam in cameras:
        assert np.allclose(read.cameras[cam.name].cam_from_world.matrix(), cam.cam_from_world.matrix(), atol=1e-9)
        assert np.allclose(read.cameras[cam.name].K, cam.K)


def test_a_camera_missing_from_the_source_is_named(board_run, calib_capture, tmp_path):
    board, _ = board_run
    capture, _ = calib_capture
    cameras = [c for c in load_cameras(board / "cameras_native.json") if c.name != "cam05"]
    write_opencv_cameras(tmp_path / "rig.json", cameras)
    with pytest.raises(InputError, match="camera cam05 of the capture is not in it"):
        run_stage_for_test(STAGE, tmp_path / "w", inputs={"capture": capture}, params={"source": str(tmp_path / "rig.json")})


def test_a_source_that_does_not_fit_its_own_points_is_refused(board_run, calib_capture, tmp_path):
    board, _ = board_run
    capture, _ = calib_capture
    model = tmp_path / "model"
    shutil.copytree(board / "colmap" / "text", model)
    lines = (model / "cameras.txt").read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    fields = lines[first].split()
    fields[4] = repr(float(fields[4]) * 1.02)  # camera 1's fx 2% off: its points land pixels away
    lines[first] = " ".join(fields)
    (model / "cameras.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="camera cam00 reprojects its own points with an RMS"):  # camera 1 is cam00
        run_stage_for_test(STAGE, tmp_path / "w", inputs={"capture": capture}, params={"source": str(model)})


def test_bad_sources_name_what_is_wrong(board_run, tmp_path):
    board, _ = board_run
    with pytest.raises(InputError, match="no such file"):
        read_calibration_source(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no COLMAP model"):
        read_calibration_source(tmp_path / "empty")
    (tmp_path / "rig.json").write_text(json.dumps({"cam00": {}}))
    with pytest.raises(InputError, match="expected 'cameras'"):
        read_calibration_source(tmp_path / "rig.json")
    (tmp_path / "files").mkdir()
    (tmp_path / "files" / "cam00.json").write_text(json.dumps({"K": [[1, 0, 0], [0, 1, 0]], "t": [0, 0, 0]}))
    with pytest.raises(InputError, match=r"cam00.json: 'K' must be 3 x 3"):
        read_calibration_source(tmp_path / "files")
    broken = tmp_path / "broken"
    shutil.copytree(board / "colmap" / "text", broken)
    (broken / "images.txt").write_text("1 not a pose\n")
    with pytest.raises(InputError, match="not a readable COLMAP model"):
        read_colmap_model(broken)


def test_camera_names_of_colmap_images():
    assert camera_name_of_image("cam03/0001.png") == "cam03"
    assert camera_name_of_image("cam03.png") == "cam03"
