"""A camera's pose names its frame: strict accessors, serialisation per frame, numerics unchanged."""

from __future__ import annotations

import json

import numpy as np
import pytest

from scene.camera import FRAMES, Camera, Rigid, load_cameras, look_at, save_cameras


def _camera(frame: str = "world") -> Camera:
    pose = look_at(np.array([0.3, 0.1, 1.2]), np.array([0.01, -0.02, 0.0]))
    return Camera("cam03", 40, 30, 52.0, 51.0, 19.3, 14.6, (-0.08, 0.02, 0.001, -0.002, 0.003), pose, frame)


def test_a_head_frame_camera_refuses_cam_from_world():
    cam = _camera("head")
    assert cam.cam_from_head is cam.pose
    with pytest.raises(ValueError, match=r"'cam03'.*head frame.*cam_from_world"):
        cam.cam_from_world
    with pytest.raises(ValueError, match=r"cam03.*cam_from_rig"):
        cam.cam_from_rig
    with pytest.raises(ValueError, match="cam03"):
        cam.center_world
    with pytest.raises(ValueError, match="cam03"):
        cam.forward_world


def test_each_frame_answers_only_its_own_accessor():
    for frame in FRAMES:
        cam = _camera(frame)
        for other in FRAMES:
            if other == frame:
                assert getattr(cam, f"cam_from_{other}") is cam.pose
            else:
                with pytest.raises(ValueError):
                    getattr(cam, f"cam_from_{other}")


def test_an_unknown_frame_is_refused():
    with pytest.raises(ValueError, match="frame 'studio'"):
        _camera("studio")


def test_with_pose_names_the_new_frame_and_keeps_the_lens():
    world = _camera()
    world_from_head = Rigid.from_rotvec(np.array([0.1, -0.2, 0.05]), np.array([0.01, -0.02, 0.03]))
    head = world.with_pose(world.cam_from_world @ world_from_head, "head")
    assert head.frame == "head" and head.K.tolist() == world.K.tolist() and head.dist == world.dist
    np.testing.assert_array_equal(head.cam_from_head.R, world.pose.R @ world_from_head.R)
    assert head.scaled(0.5).frame == "head"


@pytest.mark.parametrize("frame", FRAMES)
def test_to_dict_from_dict_round_trip_per_frame(frame, tmp_path):
    cam = _camera(frame)
    d = cam.to_dict()
    assert [k for k in d if k.startswith("cam_from_")] == [f"cam_from_{frame}"]
    back = Camera.from_dict(json.loads(json.dumps(d)))
    assert back.frame == frame and back.to_dict() == d
    np.testing.assert_array_equal(back.pose.matrix(), cam.pose.matrix())
    assert Camera.from_dict(d, frame).frame == frame
    save_cameras(tmp_path / "cameras.json", [cam])
    assert load_cameras(tmp_path / "cameras.json")[0].frame == frame


def test_a_world_camera_dict_is_byte_identical_to_the_earlier_format():
    cam = _camera("world")
    old = {"name": cam.name, "width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy,
           "cx": cam.cx, "cy": cam.cy, "dist": list(cam.dist),
           "cam_from_world": {"R": cam.pose.R.tolist(), "t": cam.pose.t.tolist()}}
    assert json.dumps(cam.to_dict(), indent=1) == json.dumps(old, indent=1)


@pytest.mark.parametrize("frame", FRAMES)
def test_a_legacy_cam_from_world_dict_is_read_as_the_callers_frame(frame):
    legacy = _camera("world").to_dict()  # earlier versions wrote every pose under cam_from_world
    cam = Camera.from_dict(legacy, frame)
    assert cam.frame == frame
    np.testing.assert_array_equal(getattr(cam, f"cam_from_{frame}").matrix(), _camera().pose.matrix())


def test_a_pose_named_for_another_frame_is_refused():
    with pytest.raises(ValueError, match=r"cam_from_rig, expected cam_from_head"):
        Camera.from_dict(_camera("rig").to_dict(), "head")


def test_no_pose_or_two_poses_are_refused_and_the_file_named(tmp_path):
    d = _camera("head").to_dict()
    two = dict(d, cam_from_world=d["cam_from_head"])
    with pytest.raises(ValueError, match="exactly one pose.*cam_from_world, cam_from_head"):
        Camera.from_dict(two)
    none = {k: v for k, v in d.items() if k != "cam_from_head"}
    with pytest.raises(ValueError, match="found none"):
        Camera.from_dict(none)
    (tmp_path / "two.json").write_text(json.dumps({"cameras": [two]}))
    with pytest.raises(ValueError, match="two.json"):
        load_cameras(tmp_path / "two.json")


def _reference_project(cam: Camera, X: np.ndarray):
    """Projection as written before poses named their frame (cam_from_world = pose)."""
    pc = cam.pose.apply(np.asarray(X, dtype=np.float64))
    z = pc[..., 2]
    safe_z = np.where(np.abs(z) < 1e-12, 1e-12, z)
    xy = cam.distort(pc[..., :2] / safe_z[..., None])
    return np.stack([cam.fx * xy[..., 0] + cam.cx, cam.fy * xy[..., 1] + cam.cy], -1), z


def _reference_rays(cam: Camera, uv: np.ndarray):
    uv = np.asarray(uv, dtype=np.float64)
    xy = cam.undistort(np.stack([(uv[..., 0] - cam.cx) / cam.fx, (uv[..., 1] - cam.cy) / cam.fy], -1))
    d_cam = np.concatenate([xy, np.ones_like(xy[..., :1])], -1)
    d = d_cam @ cam.pose.R
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    centre = -cam.pose.R.T @ cam.pose.t
    return np.broadcast_to(centre, d.shape).copy(), d


@pytest.mark.parametrize("frame", FRAMES)
def test_projection_and_rays_are_unchanged_in_every_frame(frame):
    cam = _camera(frame)
    X = np.random.default_rng(0).normal(0, 0.1, (50, 3))
    uv, z = cam.project(X)
    uv_ref, z_ref = _reference_project(cam, X)
    np.testing.assert_array_equal(uv, uv_ref)
    np.testing.assert_array_equal(z, z_ref)
    o, d = cam.image_rays()
    jj, ii = np.meshgrid(np.arange(cam.width, dtype=np.float64), np.arange(cam.height, dtype=np.float64))
    o_ref, d_ref = _reference_rays(cam, np.stack([jj, ii], -1))
    np.testing.assert_array_equal(o, o_ref)
    np.testing.assert_array_equal(d, d_ref)
    np.testing.assert_array_equal(cam.center, -cam.pose.R.T @ cam.pose.t)
    np.testing.assert_array_equal(cam.forward, cam.pose.R[2])
    if frame == "world":
        np.testing.assert_array_equal(cam.center_world, cam.center)
