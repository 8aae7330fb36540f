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


def test_native_box_maps_coarse_pixels_onto_the_native_grid():
    from hardware.studio.calibration_takes import native_box

    # coarse pixel 10 spans [9.5, 10.5], at 3.2x native [31.5, 34.7] (pixel centres): native pixels 32..35
    box = native_box((10, 20, 11, 21), 3.2, 0, 1000, 1000)
    assert box == (32, 64, 36, 68)
    assert native_box((0, 0, 5, 5), 3.2, 4, 12, 12) == (0, 0, 12, 12)  # clipped to the image


def test_window_render_matches_the_full_render_and_holds_the_highlight():
    from hardware.studio.calibration_takes import detect_windows, render_mirror_rois, render_mirror_window

    cam = _camera(dist=(0.0, 0.0, 0.0, 0.0, 0.0))
    spheres = MirrorSpheresConfig(radius_m=0.04, offsets_m=((0.0, 0.0, 0.0),))
    bar = BarLight(0, np.array([0.2, 0.3, 1.2]), np.array([1.0, 0.0, 0.0]), 0.3)
    # the same sub-pixel rays in both paths: the window is exactly that part of the full image
    params = CalibrationTakeParams(noise=0.0, blur_px=0.0, mirror_supersample=3, roi_coarse_supersample=3,
                                   highlight_supersample=8, roi_highlight_supersample=8)
    full = render_mirror_images(cam, np.zeros((1, 3)), spheres, [bar], params, np.random.default_rng(0))
    boxes = detect_windows(full["bar00"].mean(-1) + np.random.default_rng(1).normal(0, 1e-3, (240, 320)), 6.0)
    assert len(boxes) == 1
    x0, y0, x1, y1 = boxes[0]
    box = (x0 - 3, y0 - 3, x1 + 3, y1 + 3)
    window = render_mirror_window(cam, box, np.zeros((1, 3)), spheres, bar, params)
    np.testing.assert_allclose(window, full["bar00"][box[1]:box[3], box[0]:box[2], 0], atol=1e-6)
    room = render_mirror_window(cam, box, np.zeros((1, 3)), spheres, None, params)
    np.testing.assert_allclose(room, full["room"][box[1]:box[3], box[0]:box[2], 0], atol=1e-6)
    # at twice the resolution the windows hold all of the highlight's light and the whole ball
    native = cam.scaled(2.0)
    coarse = {k: v + np.random.default_rng(2).normal(0, 1e-3, v.shape).astype(np.float32) for k, v in full.items()}
    rois = render_mirror_rois(native, coarse, np.zeros((1, 3)), spheres, [bar], params, np.random.default_rng(3))
    assert len(rois["bar00"]) == 1 and len(rois["room"]) == 1
    hi = render_mirror_images(native, np.zeros((1, 3)), spheres, [bar], params, np.random.default_rng(0))
    (bx0, by0, bx1, by1), img = rois["bar00"][0]
    np.testing.assert_allclose(img, hi["bar00"][by0:by1, bx0:bx1], atol=1e-6)
    outside = hi["bar00"][..., 0].copy()
    outside[by0:by1, bx0:bx1] = 0.0
    assert outside.max() <= params.background + 1e-6  # no highlight light outside the window
    (rx0, ry0, rx1, ry1), _ = rois["room"][0]
    lit = np.argwhere(hi["room"][..., 0] > params.background + 1e-6)
    assert lit[:, 0].min() >= ry0 and lit[:, 0].max() < ry1 and lit[:, 1].min() >= rx0 and lit[:, 1].max() < rx1


def test_takes_write_native_windows_with_their_index(tmp_path):
    from hardware.studio.calibration_takes import render_mirror_take

    cam = _camera()
    bars = [BarLight(3, np.array([0.3, 0.5, 1.0]), np.array([1.0, 0.0, 0.0]), 0.3)]
    params = CalibrationTakeParams(mirror_supersample=2, highlight_supersample=4, roi_highlight_supersample=4)
    seconds = render_mirror_take([cam], bars, tmp_path / "cap", tmp_path / "truth", params, roi_cameras=[cam.scaled(2)])
    assert seconds["windows_s"] > 0
    index = json.loads((tmp_path / "cap" / "calib" / "mirror_roi.json").read_text())
    assert (index["width"], index["height"]) == (640, 480)
    assert len(index["cameras"]["cam00"]["room"]) == 4 and len(index["cameras"]["cam00"]["bar03"]) >= 3
    for win in index["cameras"]["cam00"]["bar03"]:
        x0, y0, x1, y1 = win["box"]
        assert read_exr(tmp_path / "cap" / "calib" / "mirror_roi" / "cam00" / win["file"]).shape == (y1 - y0, x1 - x0, 3)


def test_items_rendered_apart_equal_one_sequential_pass_per_camera(tmp_path):
    """Board and mirror items of a camera, rendered separately (mirror first), give the bytes of the
    reference: one generator per camera drawing the board images, then the mirror images."""
    from hardware.studio.calibration_takes import (plan_calibration_takes, render_mirror_rois, render_take_item,
                                                   sample_board_poses)
    from scene.image_io import write_exr

    cams = [_camera(), _camera(eye=(-0.3, 0.05, 0.8))]
    cams[1] = Camera("cam01", *[getattr(cams[1], k) for k in ("width", "height", "fx", "fy", "cx", "cy", "dist",
                                                             "cam_from_world")])
    cams = [c.scaled(0.25) for c in cams]
    natives = [c.scaled(2.0) for c in cams]
    bars = [BarLight(3, np.array([0.3, 0.5, 1.0]), np.array([1.0, 0.0, 0.0]), 0.3)]
    board, spheres = CharucoBoardConfig(), MirrorSpheresConfig()
    params = CalibrationTakeParams(poses=4, seed=7, supersample=1, mirror_supersample=2, highlight_supersample=4,
                                   roi_highlight_supersample=4)
    plan = plan_calibration_takes(cams, bars, params, board, spheres, board_cameras=natives)
    assert [item.kind for item in plan.items] == ["board", "mirror", "board", "mirror"]
    results = {(r["kind"], r["camera"]): r for r in (render_take_item(item) for item in reversed(plan.items))}

    def reference_bytes(img) -> bytes:
        write_exr(tmp_path / "ref.exr", img)
        return (tmp_path / "ref.exr").read_bytes()

    poses = sample_board_poses(board, cams, params, np.random.default_rng(params.seed))
    tex, margin = board_texture(board)
    centres = np.asarray(params.volume_center_m) + np.asarray(spheres.offsets_m)
    for ci, (cam, native) in enumerate(zip(cams, natives)):
        rng = np.random.default_rng([params.seed, ci])
        board_files = {f"charuco/{cam.name}/{k:04d}.exr": reference_bytes(
            render_board_image(native, pose, board, tex, margin, params, rng))
            for k, pose in enumerate(poses) if board_visible(native, pose, board)}
        assert board_files and {k: v.tobytes() for k, v in results["board", cam.name]["files"].items()} == board_files
        coarse = render_mirror_images(cam, centres, spheres, bars, params, rng)
        mirror = results["mirror", cam.name]
        for name, img in coarse.items():
            assert mirror["files"][f"mirror/{cam.name}/{name}.exr"].tobytes() == reference_bytes(img)
        rois = render_mirror_rois(native, coarse, centres, spheres, bars, params,
                                  np.random.default_rng([params.seed, ci, 1]))
        assert {name: [w["box"] for w in found] for name, found in mirror["windows"].items()} == \
            {name: [list(box) for box, _ in found] for name, found in rois.items()}
        for name, found in rois.items():
            for k, (_, img) in enumerate(found):
                assert mirror["files"][f"mirror_roi/{cam.name}/{name}_{k:02d}.exr"].tobytes() == reference_bytes(img)
