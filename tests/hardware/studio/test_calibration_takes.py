"""The virtual studio's calibration takes: geometry of the rendered board and balls."""

from __future__ import annotations

import json

import numpy as np

from hardware.studio.calibration_takes import (BarLight, CalibrationTakeParams, CharucoBoardConfig,
                                               MirrorSpheresConfig, board_texture, board_visible,
                                               reference_world_from_board, render_board_image,
                                               render_calibration_takes, render_mirror_images)
from scene.camera import Camera, look_at
from scene.image_io import read_exr


def _camera(eye=(0.05, 0.03, 0.9), dist=(-0.08, 0.02, 0.0, 0.0, 0.0)) -> Camera:
    return Camera("cam00", 320, 240, 700.0, 700.0, 161.0, 118.0, dist, look_at(np.array(eye), np.zeros(3)))


def test_rendered_board_corners_match_the_projected_geometry():
    import cv2

    board = CharucoBoardConfig()
    cam = _camera()
    pose = reference_world_from_board(board, np.zeros(3))
    params = CalibrationTakeParams(noise=0.0, blur_px=0.4)
    tex, margin = board_texture(board)
    img = render_board_image(cam, pose, board, tex, margin, params, np.random.default_rng(0))
    from hardware.studio.calibration_takes import make_board

    cv_board = make_board(board)
    grey = img.mean(-1)
    u8 = np.clip(np.sqrt(grey / grey.max()) * 255, 0, 255).astype(np.uint8)
    corners, ids, _, _ = cv2.aruco.CharucoDetector(cv_board).detectBoard(u8)
    assert ids is not None and len(ids) >= 30
    truth, _ = cam.project(pose.apply(np.asarray(cv_board.getChessboardCorners())[ids.ravel()]))
    err = np.linalg.norm(corners.reshape(-1, 2) - truth, axis=1)
    # the print, the distortion and the pixel convention agree to a small fraction of a pixel
    assert np.sqrt(np.mean(err ** 2)) < 0.12


def test_board_seen_from_behind_is_not_visible():
    board = CharucoBoardConfig()
    pose = reference_world_from_board(board, np.zeros(3))
    assert board_visible(_camera(), pose, board)
    assert not board_visible(_camera(eye=(0.0, 0.0, -0.9)), pose, board)


def test_mirror_highlight_appears_where_the_bar_reflects():
    cam = _camera(dist=(0.0, 0.0, 0.0, 0.0, 0.0))
    spheres = MirrorSpheresConfig(radius_m=0.04, offsets_m=((0.0, 0.0, 0.0),))
    bar = BarLight(0, np.array([0.0, 0.0, 1.2]), np.array([1.0, 0.0, 0.0]), 0.3)
    params = CalibrationTakeParams(noise=0.0, blur_px=0.0)
    images = render_mirror_images(cam, np.zeros((1, 3)), spheres, [bar], params, np.random.default_rng(0))
    room, lit = images["room"].mean(-1), images["bar00"].mean(-1)
    # silhouette: a disc of about f r / d pixels around the sphere's image
    area_px = float((room > 0.5 * room.max()).sum())
    expect = np.pi * (700.0 * 0.04 / np.linalg.norm(cam.center_world)) ** 2
    assert abs(area_px / expect - 1) < 0.05
    # highlight: the mirror point of the bar centre (normal halfway between camera and bar directions)
    to_cam = cam.center_world / np.linalg.norm(cam.center_world)
    to_bar = bar.center_world / np.linalg.norm(bar.center_world)
    normal = (to_cam + to_bar) / np.linalg.norm(to_cam + to_bar)
    expected_uv, _ = cam.project(0.04 * normal)
    peak = np.unravel_index(np.argmax(lit), lit.shape)
    assert np.hypot(peak[1] - expected_uv[0], peak[0] - expected_uv[1]) < 1.5


def test_takes_write_the_contracted_files(tmp_path):
    cams = [_camera(), _camera(eye=(-0.4, 0.0, 0.8))]
    cams[1] = Camera("cam01", *[getattr(cams[1], k) for k in ("width", "height", "fx", "fy", "cx", "cy", "dist",
                                                             "cam_from_world")])
    bars = [BarLight(3, np.array([0.3, 0.5, 1.0]), np.array([1.0, 0.0, 0.0]), 0.3)]
    params = CalibrationTakeParams(poses=3, supersample=1, mirror_supersample=2, highlight_supersample=4)
    render_calibration_takes(cams, bars, tmp_path / "cap", tmp_path / "truth", params)
    board = json.loads((tmp_path / "cap" / "calib" / "board.json").read_text())
    assert {"squares_x", "squares_y", "square_m", "marker_m", "dictionary", "world_from_board_reference"} <= set(board)
    mirror = json.loads((tmp_path / "cap" / "calib" / "mirror.json").read_text())
    assert mirror["radius_m"] > 0 and mirror["count"] == 4
    assert (tmp_path / "cap" / "calib" / "charuco" / "cam00" / "0000.exr").is_file()
    assert read_exr(tmp_path / "cap" / "calib" / "mirror" / "cam01" / "bar03.exr").shape == (240, 320, 3)
    poses = json.loads((tmp_path / "truth" / "calib_board_poses.json").read_text())["world_from_board"]
    assert len(poses) == 3
    spheres = json.loads((tmp_path / "truth" / "mirror_spheres.json").read_text())
    assert len(spheres["centers_world"]) == 4
