"""The viewer's render session: paths, the bake against the voxel-space sum, requests by id only."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from scene.envmap import synthetic_sky, write_envmap
from scene.image_io import write_exr
from stages.relight.lookdev import (
    LookDevSession,
    LookSettings,
    LookState,
    MapCatalogue,
    RequestError,
)
from tests.stages.relight.conftest import tiny_model


@pytest.fixture(scope="module")
def maps(tmp_path_factory) -> list[tuple[str, Path]]:
    root = tmp_path_factory.mktemp("maps")
    write_envmap(root / "sky.exr", synthetic_sky(16, np.array([0.3, 0.8, 0.5]), 0.5, 8.0))
    (root / "damaged.exr").write_bytes(b"\x76\x2f\x31\x01 not the rest of an EXR")
    write_exr(root / "square.exr", np.ones((16, 16, 3), np.float32))
    return [(p, root / p) for p in ("sky.exr", "damaged.exr", "square.exr")]


@pytest.fixture(scope="module")
def session(maps, random_head) -> LookDevSession:
    model, verts = random_head
    meshes = np.stack([verts, verts * 1.03])
    # Rank 0: the full basis, so a bake frame equals the voxel-space sum up to float rounding.
    settings = LookSettings(width_px=20, height_px=24, directions=48, bake_rank=0)
    return LookDevSession(model, 1.0, meshes, MapCatalogue(maps), settings)


def test_unreadable_maps_stay_listed_with_their_error(session):
    listed = {m["id"]: m for m in session.maps.describe()}
    assert listed["sky"]["ok"]
    assert not listed["damaged"]["ok"] and "damaged.exr" in listed["damaged"]["error"]
    assert not listed["square"]["ok"] and "2:1" in listed["square"]["error"]
    with pytest.raises(RequestError, match="could not be read"):
        session.render(LookState(map_id="square"))


def test_a_path_is_never_a_map(session, maps):
    for name in (str(maps[0][1]), "sky.exr", "../sky", "/etc/passwd"):
        with pytest.raises(RequestError, match="unknown environment map"):
            session.render(LookState(map_id=name))
        with pytest.raises(RequestError, match="unknown environment map"):
            session.maps.preview(name)


def test_requests_are_validated_field_by_field():
    with pytest.raises(RequestError, match="expression"):
        LookState.from_request({"expression": 2}, num_expressions=2)
    with pytest.raises(RequestError, match="light_head_m"):
        LookState.from_request({"light_head_m": [0, "x", 1]}, num_expressions=2)
    with pytest.raises(RequestError, match="distance_m"):
        LookState.from_request({"distance_m": 0.0}, num_expressions=2)
    state = LookState.from_request({"map": "sky", "rotation_deg": 30, "expression": 1}, num_expressions=2)
    assert (state.map_id, state.rotation_deg, state.expression) == ("sky", 30.0, 1)


def test_camera_moves_take_the_sum_and_held_views_bake_once(session):
    moving = [LookState(map_id="sky", azimuth_deg=a) for a in (10.0, 20.0)]
    assert [session.render(s).path for s in moving] == ["voxel_sum", "voxel_sum"]
    held = session.render(LookState(map_id="sky", azimuth_deg=20.0))
    assert held.path == "bake" and held.baked_now
    turned = session.render(LookState(map_id="sky", azimuth_deg=20.0, rotation_deg=75.0))
    assert turned.path == "bake" and not turned.baked_now
    assert not np.array_equal(turned.image_srgb8, held.image_srgb8), "turning the map changed nothing"
    lit = session.render(LookState(map_id="sky", azimuth_deg=20.0, rotation_deg=75.0, light_on=True))
    assert lit.path == "bake" and "point light" in lit.note
    assert lit.image_srgb8.astype(int).sum() > turned.image_srgb8.astype(int).sum()  # light only adds


def test_bake_frames_match_the_voxel_space_sum(session):
    """Full rank: the bake's frame of a turned map (and a point light) is the sum's frame to a grey level."""
    state = LookState(map_id="sky", rotation_deg=140.0, expression=1, light_on=True, light_head_m=(0.4, 0.2, 1.2))
    fresh = LookDevSession(session.model, 1.0, session.meshes_head, session.maps, session.settings)
    summed = fresh.render(state)
    baked = fresh.render(state)
    assert (summed.path, baked.path) == ("voxel_sum", "bake")
    assert np.abs(summed.image_srgb8.astype(int) - baked.image_srgb8.astype(int)).max() <= 1


def test_expression_scrub_changes_the_head(session):
    a = session.render(LookState(light_on=True, expression=0))
    b = session.render(LookState(light_on=True, expression=1))
    assert a.path == b.path == "network"
    assert not np.array_equal(a.image_srgb8, b.image_srgb8)
    with pytest.raises(RequestError, match="unknown expression 2"):
        session.render(LookState(expression=2))


def test_a_subject_without_tracked_meshes_is_refused(maps):
    model, verts = tiny_model()
    with pytest.raises(ValueError, match="at least one tracked expression"):
        LookDevSession(model, 1.0, verts[None][:0], MapCatalogue(maps))
