"""``calibrate.board_shape``: refining the board's corners in the bundle adjustment.

A real print is off scale (+0.15 % x, +0.25 % y), its corners 30 um off and the board bows
0.8 mm at its centre; held at nominal, the cameras' intrinsics absorb that. Refined (two
corners held at nominal for the gauge), the board's bow comes out and the intrinsics
errors drop; on an ideal board refining costs nothing.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from hardware.studio.calibration_takes import CalibrationTakeParams, render_rig_takes
from hardware.studio.camera_effects import CameraEffects
from hardware.studio.printed_board import print_board
from pipeline.testing import run_stage_for_test
from scene.camera import Rigid
from stages.calibrate.board import load_board_spec
from stages.calibrate.board_shape import (
    board_from_refined,
    bow_m,
    gauge_corner_ids,
    scale_err_pct,
    shift_m_max,
)
from stages.calibrate.eval_stage import STAGE as EVAL_STAGE
from stages.calibrate.stage import STAGE
from stages.capture.output import CaptureOutput

CAMERAS = ("cam00", "cam01", "cam02")  # neighbours: they share board poses, which chains them


def _grid(nx: int = 7, ny: int = 5, square_m: float = 0.04) -> np.ndarray:
    """Inner corners [ny * nx, 3] of a chessboard, row by row from the origin, z = 0."""
    x, y = np.meshgrid(np.arange(1, nx + 1) * square_m, np.arange(1, ny + 1) * square_m)
    return np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])


def test_gauge_corners_are_the_first_rows_ends():
    nominal_board = _grid()
    assert gauge_corner_ids(nominal_board) == [0, 6]


def test_board_from_refined_puts_a_moved_bowed_board_back_on_the_nominal_frame():
    nominal_board = _grid()
    centre_xy = 0.5 * (nominal_board[:, :2].min(axis=0) + nominal_board[:, :2].max(axis=0))
    r2 = np.sum((nominal_board[:, :2] - centre_xy) ** 2, axis=1)
    bowed_board = nominal_board.copy()
    bowed_board[:, 2] = -0.0005 * (1 - r2 / r2.max())  # the outermost corners at z = 0
    ba_from_board = Rigid.from_rotvec(np.array([0.03, -0.02, 0.5]), np.array([0.1, -0.2, 0.05]))
    board_from_ba = board_from_refined(ba_from_board.apply(bowed_board), nominal_board)
    np.testing.assert_allclose(board_from_ba.apply(ba_from_board.apply(bowed_board)), bowed_board, atol=1e-9)


def test_bow_ignores_a_tilt_and_reads_the_paraboloids_depth():
    nominal_board = _grid()
    centre_xy = nominal_board[:, :2].mean(axis=0)
    r2 = np.sum((nominal_board[:, :2] - centre_xy) ** 2, axis=1)
    bowed_board = nominal_board.copy()
    # centre 0.5 mm nearer the camera (-z) than the outermost corners, on a tilted plane
    bowed_board[:, 2] = -0.0005 * (1 - r2 / r2.max()) + 0.01 * nominal_board[:, 0] - 0.002
    assert bow_m(bowed_board, nominal_board) == pytest.approx(0.0005, rel=1e-9)
    scaled_board = nominal_board * np.array([1.002, 0.999, 1.0])
    assert scale_err_pct(scaled_board, nominal_board, 0) == pytest.approx(0.2, rel=1e-9)
    assert scale_err_pct(scaled_board, nominal_board, 1) == pytest.approx(-0.1, rel=1e-9)
    assert shift_m_max(nominal_board, nominal_board) == 0.0


def _render(tmp_path, effects):
    capture, truth = tmp_path / "capture", tmp_path / "truth"
    render_rig_takes(capture, truth, CalibrationTakeParams(poses=10, seed=3, effects=effects),
                     camera_names=CAMERAS, bar_ids=(), board_scale=0.5)
    (capture / "manifest.json").write_text(json.dumps({"cameras": list(CAMERAS), "width": 240, "height": 320}))
    return capture, truth


def _calibrate(tmp_path, capture, truth, board_shape):
    work = tmp_path / board_shape
    out = run_stage_for_test(STAGE, work, inputs={"capture": capture}, params={"board_shape": board_shape})
    ev = run_stage_for_test(EVAL_STAGE, work, inputs={"calibrate": out, "capture.truth": truth})
    metrics = {**json.loads((out / "metrics.json").read_text()), **json.loads((ev / "metrics.json").read_text())}
    corners_board = np.asarray(json.loads((out / "report.json").read_text())["board_corners_board_m"])
    return metrics, corners_board


def test_refined_board_recovers_the_bow_and_the_intrinsics_on_a_real_print(tmp_path):
    effects = CameraEffects()
    capture, truth = _render(tmp_path, effects)
    nominal, _ = _calibrate(tmp_path, capture, truth, "nominal")
    refined, refined_board = _calibrate(tmp_path, capture, truth, "refined")

    spec = load_board_spec(CaptureOutput(capture))
    nominal_board = spec.corners_board()
    printed = print_board(spec.squares_x, spec.squares_y, spec.square_m, effects.board_print)
    true_bow_mm = 1000 * bow_m(printed.printed_points(nominal_board), nominal_board)
    # the print's bow over the inner corners (0.8 mm at the chessboard's outer corners)
    assert true_bow_mm > 0.3
    assert refined["board_refined_bow_mm"] == pytest.approx(true_bow_mm, rel=0.25)
    assert nominal["board_refined_bow_mm"] == 0.0
    # the print's errors no longer land in the intrinsics
    assert refined["focal_err_pct_max"] < 0.5 * nominal["focal_err_pct_max"]
    assert refined["principal_err_px_max"] < 0.5 * nominal["principal_err_px_max"]
    assert refined["rotation_err_deg_max"] < nominal["rotation_err_deg_max"]
    # modelled, the print leaves less in the residuals (the detection's and the per-pose flex remain)
    assert refined["reproj_rms_px"] < nominal["reproj_rms_px"]

    # the gauge: the first row's ends stay their nominal distance apart (the board's scale)
    first, row_end = gauge_corner_ids(nominal_board)
    assert np.linalg.norm(refined_board[row_end] - refined_board[first]) == pytest.approx(
        np.linalg.norm(nominal_board[row_end] - nominal_board[first]), abs=1e-9)
    assert abs(refined["board_refined_scale_err_pct_x"]) < 0.05
    # only the scale is held: the print's y-over-x stretch (0.1 %) is the cameras' to see
    printed_board = printed.printed_points(nominal_board)
    true_stretch_pct = (scale_err_pct(printed_board, nominal_board, 1) - scale_err_pct(printed_board, nominal_board, 0))
    refined_stretch_pct = refined["board_refined_scale_err_pct_y"] - refined["board_refined_scale_err_pct_x"]
    assert refined_stretch_pct == pytest.approx(true_stretch_pct, abs=0.03)


def test_refined_board_is_no_worse_on_an_ideal_board(tmp_path):
    capture, truth = _render(tmp_path, None)
    nominal, _ = _calibrate(tmp_path, capture, truth, "nominal")
    refined, _ = _calibrate(tmp_path, capture, truth, "refined")
    # a flat, exact board: the refined corners stay within a few microns of nominal
    assert refined["board_refined_shift_mm_max"] < 0.02
    assert abs(refined["board_refined_bow_mm"]) < 0.01
    assert refined["focal_err_pct_max"] <= nominal["focal_err_pct_max"] + 0.01
    assert refined["principal_err_px_max"] <= nominal["principal_err_px_max"] + 0.2
    assert refined["center_err_mm_max"] <= nominal["center_err_mm_max"] + 0.2
    assert refined["rotation_err_deg_max"] <= nominal["rotation_err_deg_max"] + 0.01
    assert refined["reproj_rms_px"] <= nominal["reproj_rms_px"] + 1e-3
