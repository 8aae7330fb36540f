"""The relight stage's light-transfer bake: which sequences take it, its frames against the voxel-space
sum's, the side-by-side metrics, the bake kept in the per-item cache and what its key covers."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from pydantic import ValidationError

from avatar.bake import psnr_db
from pipeline.errors import ConfigError
from pipeline.testing import run_stage_for_test
from scene.camera import look_at
from scene.image_io import read_exr
from stages.relight import sequences as seq
from stages.relight.bake import BakeItem, bake_key, choose_paths
from stages.relight.stage import STAGE
from tests.stages.relight.conftest import write_relight_inputs

ENVMAPS = {"envmaps": ["blender-cc0/studio.exr", "blender-cc0/sunrise.exr"], "envmap_frames": 2,
           "rotate_deg_per_frame": 47.5, "directions": 24, "orbit_frames": 0, "turntable_frames": 0,
           "dolly_zoom_frames": 0, "width_px": 12, "height_px": 16, "steps_per_ray": 8, "naive_timing_frames": 0,
           "bake_check_rotations_deg": [0.0, 130.0]}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    return write_relight_inputs(tmp_path_factory.mktemp("relight_bake_inputs"), expressions=1)


def _run(inputs, root, params):
    out = run_stage_for_test(STAGE, root, inputs, params)
    return out, json.loads((out / "metrics.json").read_text())


def test_envmap_sequences_from_the_bake_match_the_voxel_space_sum(inputs, tmp_path):
    baked_out, metrics = _run(inputs, tmp_path / "bake", {**ENVMAPS, "envmap_path": "bake", "point_lights": [(0.4, 0.2, 1.0)]})
    summed_out, _ = _run(inputs, tmp_path / "sum", {**ENVMAPS, "envmap_path": "sum", "bake_check": False})
    paths = json.loads((baked_out / "paths.json").read_text())
    assert {k: v["path"] for k, v in paths.items()} == {"envmap_studio": "bake", "envmap_sunrise": "bake",
                                                         "point_lights": "voxel_sum"}
    manifest = json.loads((baked_out / "renders.json").read_text())
    assert {r["path"] for r in manifest["envmap_studio"]} == {"bake"}
    assert manifest["point_lights"][0]["path"] == "voxel_sum"
    for name in ("envmap_studio", "envmap_sunrise"):
        for i in range(2):
            baked = read_exr(baked_out / name / "frames" / f"{i:06d}.exr")
            summed = read_exr(summed_out / name / "frames" / f"{i:06d}.exr")
            # Rank 32 >= 24 directions: the exact sum, up to the EXRs' float16 rounding (2^-11).
            assert psnr_db(baked[..., :3], summed[..., :3], summed[..., 3]) >= 55.0
            np.testing.assert_allclose(baked[..., 3], summed[..., 3], atol=2e-3)
    # The side-by-side figures: one bake, its frames and the sum's of the same frames (2 maps x 2 rotations).
    assert metrics["bake_check_frames"] == 4 and metrics["bake_psnr_vs_sum_db"] >= 60.0
    assert metrics["bake_seconds"] > 0 and 0 < metrics["bake_frame_seconds"] < metrics["envmap_seconds_per_frame"]
    assert metrics["bake_speedup_vs_sum"] > 1.0
    assert (metrics["envmap_frames_from_bake"], metrics["envmap_frames_from_sum"]) == (4, 0)
    assert (metrics["bakes_reused"], metrics["bakes_computed"]) == (1, 0)  # the check's bake, found in the cache


def test_auto_bakes_only_where_enough_frames_share_a_view(inputs, tmp_path):
    params = {**ENVMAPS, "bake_check": False, "bake_min_frames": 5}  # 2 maps x 2 frames = 4 < 5
    out, metrics = _run(inputs, tmp_path / "few", params)
    assert json.loads((out / "paths.json").read_text())["envmap_studio"]["path"] == "voxel_sum"
    assert metrics["envmap_frames_from_sum"] == 4 and "bake_seconds" not in metrics
    out, metrics = _run(inputs, tmp_path / "enough", {**params, "bake_min_frames": 4})
    assert json.loads((out / "paths.json").read_text())["envmap_studio"]["path"] == "bake"
    assert (metrics["bakes_reused"], metrics["bakes_computed"]) == (0, 1)
    assert "bake_frame_seconds" not in metrics  # no check asked for


def test_the_bake_is_kept_in_the_cache_and_rebaked_for_another_view(inputs, tmp_path):
    params = {**ENVMAPS, "envmap_path": "bake", "bake_check": False}
    (tmp_path / "a").mkdir()
    _run(inputs, tmp_path / "a", params)
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / ".cache").symlink_to(tmp_path / "a" / ".cache", target_is_directory=True)
    _, again = _run(inputs, tmp_path / "b", params)
    assert (again["bakes_reused"], again["bakes_computed"]) == (1, 0)
    entries = list((tmp_path / "a" / ".cache").rglob("stages.relight.bake.bake_item/*/*.npz"))
    assert len(entries) == 1
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / ".cache").symlink_to(tmp_path / "a" / ".cache", target_is_directory=True)
    _, moved = _run(inputs, tmp_path / "c", {**params, "distance_m": 1.1})  # the camera moves back
    assert (moved["bakes_reused"], moved["bakes_computed"]) == (0, 1)


def test_the_bake_key_covers_model_expression_camera_and_settings():
    view = seq.ViewSpec(12, 16)
    camera = view.camera(view.front_eye())
    item = BakeItem(model_dir="m", model_digest="model-a", meshes_path="meshes.npz", mesh_array="default",
                    mesh_index=0, mesh_digest="mesh-a", camera=camera, directions=256, distance_m=50.0,
                    centre_head=(0.0, 0.0, 0.0), rank=32, steps=24, light_batch=16, device="cpu")
    moved = camera.with_pose(look_at(np.array([0.01, 0.0, 0.9]), np.zeros(3)), "head")
    changes = {"model_digest": "model-b", "mesh_digest": "mesh-b", "camera": moved, "directions": 128,
               "distance_m": 40.0, "centre_head": (0.0, 0.01, 0.0), "rank": 16, "steps": 32, "light_batch": 8,
               "device": "cuda"}
    keys = {bake_key(item)}
    for field, value in changes.items():
        keys.add(bake_key(dataclasses.replace(item, **{field: value})))
    assert len(keys) == 1 + len(changes)
    # Where the model and meshes lie is not what the bake depends on (their digests are).
    assert bake_key(dataclasses.replace(item, model_dir="elsewhere", meshes_path="x.npz")) == bake_key(item)
    wider = dataclasses.replace(camera, fx=camera.fx * 1.01)
    assert bake_key(dataclasses.replace(item, camera=wider)) != bake_key(item)


def test_choose_paths_explains_itself():
    view = seq.ViewSpec(12, 16)
    front, side = view.camera(view.front_eye()), view.camera(np.array([0.5, 0.0, 0.7]))
    env = [seq.FrameSpec(front, np.zeros((1, 3)), np.ones((1, 3)), 0, {"kind": "envmap"}) for _ in range(3)]
    env_side = [seq.FrameSpec(side, np.zeros((1, 3)), np.ones((1, 3)), 0, {"kind": "envmap"})]
    point = [seq.FrameSpec(front, np.zeros((1, 3)), np.ones((1, 3)), 0, {"kind": "point"})]
    paths = choose_paths({"a": env, "b": env_side, "p": point}, "auto", 3, None)
    assert (paths["a"].path, paths["b"].path, paths["p"].path) == ("bake", "voxel_sum", "voxel_sum")
    assert "only 1 envmap frames" in paths["b"].reason and "point light" in paths["p"].reason
    refused = choose_paths({"a": env}, "auto", 1, "light_method 'adaptive' picks directions")
    assert refused["a"].path == "voxel_sum" and "adaptive" in refused["a"].reason


def test_bad_path_settings_are_config_errors(inputs, tmp_path):
    with pytest.raises(ValidationError, match="envmap_path"):  # a Literal: refused when the params are read
        run_stage_for_test(STAGE, tmp_path / "a", inputs, {**ENVMAPS, "envmap_path": "fast"})
    with pytest.raises(ConfigError, match="adaptive"):
        run_stage_for_test(STAGE, tmp_path / "b", inputs, {**ENVMAPS, "envmap_path": "bake",
                                                           "light_method": "adaptive"})
