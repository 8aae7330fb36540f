"""Head-space cameras: the algebra, the file round trip, the stage and its evaluation."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.testing import run_stage_for_test
from scene.camera import Camera, Rigid, look_at, save_cameras
from stages.stabilize.cameras_head import cameras_in_head_space, read_cameras_head, write_cameras_head
from stages.stabilize.eval_stage import STAGE as STABILIZE_EVAL
from stages.stabilize.stage import STAGE as STABILIZE


def _cameras() -> list[Camera]:
    return [Camera(f"cam{k:02d}", 240, 320, 860.0, 860.0, 119.5, 159.5, dist=(0.01, 0, 0, 0, 0),
                   pose=look_at(np.array([np.sin(a), 0.1, np.cos(a)]), np.zeros(3)))
            for k, a in enumerate(np.radians([-40.0, 0.0, 35.0]))]


def _poses(n: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    R = np.stack([Rigid.from_rotvec(rng.normal(0, 0.05, 3), np.zeros(3)).R for _ in range(n)])
    t = rng.normal(0, 0.01, (n, 3))
    return R, t


def test_head_space_camera_sees_the_head_point_where_the_world_camera_sees_the_world_point():
    cams = _cameras()
    world_from_head = Rigid.from_rotvec(np.array([0.1, -0.2, 0.05]), np.array([0.01, -0.02, 0.03]))
    points_head = np.random.default_rng(1).normal(0, 0.05, (20, 3))
    for cam, head_cam in zip(cams, cameras_in_head_space(cams, world_from_head)):
        uv_world, z_world = cam.project(world_from_head.apply(points_head))
        uv_head, z_head = head_cam.project(points_head)
        assert np.allclose(uv_world, uv_head) and np.allclose(z_world, z_head)
        # The head-space camera centre is the world centre brought into head space.
        assert np.allclose(head_cam.center, world_from_head.inverse().apply(cam.center_world))


def test_cameras_head_file_round_trip(tmp_path):
    cams = _cameras()
    R, t = _poses(4)
    write_cameras_head(tmp_path / "cameras_head.json", [0, 3, 6, 9], R, t, cams)
    back = read_cameras_head(tmp_path / "cameras_head.json")
    assert sorted(back) == [0, 3, 6, 9] and len(back[6]) == 3
    expected = cams[1].cam_from_world @ Rigid(R[2], t[2])
    assert np.allclose(back[6][1].cam_from_head.matrix(), expected.matrix())
    assert back[6][1].dist == cams[1].dist
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(ValueError, match="bad.json"):
        read_cameras_head(tmp_path / "bad.json")


def _workspace(tmp_path, R_est, t_est, R_true, t_true):
    cams = _cameras()
    track, calibrate, truth = tmp_path / "track", tmp_path / "calibrate", tmp_path / "truth"
    for folder in (track, calibrate, truth):
        folder.mkdir()
    index = np.arange(len(R_est))
    np.savez(track / "tracking.npz", index=index, world_from_head_R=R_est, world_from_head_t=t_est)
    save_cameras(calibrate / "cameras.json", cams)
    save_cameras(truth / "cameras.json", cams)
    np.savez(truth / "frames.npz", index=index, world_from_head_R=R_true, world_from_head_t=t_true)
    return track, calibrate, truth


def test_stage_and_eval_measure_the_head_pose_residual(tmp_path):
    R, t = _poses(5)
    tilt = Rigid.from_rotvec(np.radians([0.0, 0.3, 0.0]), np.zeros(3)).R
    R_est = R.copy()
    R_est[3] = tilt @ R[3]  # one frame off by 0.3 degrees
    track, calibrate, truth = _workspace(tmp_path, R_est, t, R, t)
    out = run_stage_for_test(STABILIZE, tmp_path / "work", inputs={"track": track, "calibrate": calibrate})
    data = json.loads((out / "cameras_head.json").read_text())
    assert data["space"] == "head" and len(data["frames"]) == 5 and len(data["frames"]["0"]) == 3
    ev = run_stage_for_test(STABILIZE_EVAL, tmp_path / "work",
                            inputs={"stabilize": out, "capture.truth": truth})
    metrics = json.loads((ev / "metrics.json").read_text())
    assert metrics["head_pose_residual_deg_max"] == pytest.approx(0.3, abs=1e-6)
    assert metrics["head_pose_residual_deg_mean"] < 0.3


def test_stage_rejects_a_broken_tracking_file(tmp_path):
    R, t = _poses(3)
    track, calibrate, _ = _workspace(tmp_path, R, t, R, t)
    np.savez(track / "tracking.npz", index=np.arange(3), world_from_head_R=R)
    with pytest.raises(InputError, match="world_from_head_t"):
        run_stage_for_test(STABILIZE, tmp_path / "work", inputs={"track": track, "calibrate": calibrate})


def test_cameras_head_file_names_the_head_frame_and_reads_the_earlier_key(tmp_path):
    cams = _cameras()
    R, t = _poses(2)
    path = tmp_path / "cameras_head.json"
    write_cameras_head(path, [0, 1], R, t, cams)
    text = path.read_text()
    assert '"cam_from_head"' in text and '"cam_from_world"' not in text
    new = read_cameras_head(path)
    # A file written before poses named their frame: the same poses under cam_from_world.
    path.write_text(text.replace('"cam_from_head"', '"cam_from_world"'))
    old = read_cameras_head(path)
    for index in (0, 1):
        for a, b in zip(new[index], old[index]):
            assert a.frame == b.frame == "head"
            assert np.array_equal(a.cam_from_head.matrix(), b.cam_from_head.matrix())
            with pytest.raises(ValueError, match="head frame"):
                b.cam_from_world
