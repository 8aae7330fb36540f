"""The light-transfer bake (``avatar.bake``) against the renders it stands for: per-direction images
against one raymarch per direction, the full-rank frame against the exact weighted sum, a (rotated)
map against the voxel-space sum of its lights, truncation, pruning and the saved file."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from avatar.bake import ImageBake, bake_images, bake_voxels, direction_images, direction_lights, psnr_db
from avatar.render import PointLights, decode, render
from scene.camera import Camera, look_at
from scene.envmap import BackMask, RotatingProjection, fibonacci_sphere, select_uniform, synthetic_sky
from tests.stages.relight.conftest import tiny_model

COUNT = 48  # baked directions
CENTRE = np.array([0.0, 0.01, 0.0])


@pytest.fixture(scope="module")
def head():
    torch.set_num_threads(1)
    model, verts = tiny_model()
    return model, decode(model, verts)


def _camera(width: int = 16, height: int = 20) -> Camera:
    cam = Camera("test", width, height, fx=40.0, fy=40.0, cx=width / 2 - 0.5, cy=height / 2 - 0.5)
    return cam.with_pose(look_at(np.array([0.1, 0.05, 0.6]), np.zeros(3)), "head")


@pytest.fixture(scope="module")
def full(head):
    model, geometry = head
    return bake_images(model, geometry, _camera(), fibonacci_sphere(COUNT), centre=CENTRE)


@pytest.fixture(scope="module")
def sunny():
    return RotatingProjection(synthetic_sky(32, np.array([0.5, 0.4, 0.75]), 0.6, sun_radius_deg=4.0), COUNT, 0.1,
                              BackMask())


def _sum_frame(model, geometry, lights, camera=None):
    """The voxel-space sum of a map's lights (what the relight stage renders today)."""
    positions = CENTRE + 50.0 * lights.directions_world
    return render(model, geometry, camera or _camera(), PointLights(positions, lights.irradiance_rgb)).numpy()


def test_transport_images_are_one_raymarch_per_direction(head):
    model, geometry = head
    dirs = fibonacci_sphere(12)
    fast = direction_images(model, geometry, _camera(), dirs, centre=CENTRE, light_batch=5)
    slow = direction_images(model, geometry, _camera(), dirs, centre=CENTRE, method="raymarch")
    assert fast.rgb.shape == (12, 20, 16, 3) and float(slow.rgb.max()) > 0.05
    torch.testing.assert_close(fast.rgb, slow.rgb, rtol=0.0, atol=2e-5 * float(slow.rgb.max()))
    torch.testing.assert_close(fast.alpha, slow.alpha, rtol=0.0, atol=1e-5)
    # Lights differ: the images of two directions are not alike.
    assert float((slow.rgb[0] - slow.rgb[6]).abs().max()) > 1e-3


def test_full_rank_frame_is_the_exact_weighted_sum_of_the_direction_renders(head, full):
    model, geometry = head
    assert full.rank == COUNT and full.seconds > 0
    slow = direction_images(model, geometry, _camera(), fibonacci_sphere(COUNT), centre=CENTRE, method="raymarch")
    rng = np.random.default_rng(0)
    for weights in (rng.uniform(0.0, 1.0, (COUNT, 3)), np.eye(COUNT)[:, :3] * 2.0):
        exact = np.einsum("dc,dhwc->hwc", weights, slow.rgb.double().numpy())
        rgb, alpha = full.frame(weights)
        assert rgb.shape == (20, 16, 3) and rgb.dtype == np.float32
        np.testing.assert_allclose(rgb, exact, rtol=0.0, atol=5e-5 * float(np.abs(exact).max()))
        np.testing.assert_array_equal(alpha, full.alpha)
    np.testing.assert_allclose(full.alpha, slow.alpha.numpy(), atol=1e-5)
    # image_scale divides, as render's does.
    np.testing.assert_allclose(full.frame(weights, image_scale=4.0)[0], full.frame(weights)[0] / 4.0, rtol=1e-6)


@pytest.mark.parametrize("angle_deg", [0.0, 33.3, 200.0])
def test_a_rotated_map_through_the_bake_is_the_voxel_space_sum_of_the_rotated_map(head, full, sunny, angle_deg):
    """Full rank: the same image as the voxel-space sum of select_uniform's lights of the rotated map
    (>= 60 dB; float32 rounding only). Turning the map the wrong way is far off (< 40 dB)."""
    model, geometry = head
    angle = math.radians(angle_deg)
    envmap = synthetic_sky(32, np.array([0.5, 0.4, 0.75]), 0.6, sun_radius_deg=4.0)
    lights = select_uniform(envmap.rotated_about_y(angle), COUNT, 0.1, BackMask())
    reference, alpha = _sum_frame(model, geometry, lights)
    baked, _ = full.frame(sunny.weights(angle))
    assert psnr_db(baked, reference, alpha) >= 60.0
    # The lights as the relight stage stores them (directions and RGB) map onto the same weights.
    np.testing.assert_allclose(full.weights_of(lights.directions_world, lights.irradiance_rgb), sunny.weights(angle),
                               rtol=1e-6, atol=1e-12)
    if angle_deg:
        wrong, _ = full.frame(sunny.weights(-angle))
        assert psnr_db(wrong, reference, alpha) < 40.0


def test_truncation_error_falls_with_rank_and_the_singular_values_bound_it(full, sunny):
    weights = sunny.weights(0.4)
    exact, alpha = full.frame(weights)
    errors = []
    for rank in (1, 2, 4, 8, 16, COUNT):
        part = full.truncated(rank)
        assert part.rank == rank and part.nbytes < full.nbytes or rank == COUNT
        rgb, _ = part.frame(weights)
        err = float(np.linalg.norm((rgb - exact).reshape(-1)))
        # ||w^T (A - U_R U_R^T A)|| <= ||w|| * sigma_{R+1} per channel, so sqrt(3) for three channels.
        tail = full.singular_values[rank] if rank < COUNT else 0.0
        assert err <= math.sqrt(3) * np.linalg.norm(weights, axis=0).max() * tail * 1.001 + 1e-5
        errors.append(err)
    assert errors == sorted(errors, reverse=True) and errors[-1] < 1e-4 * errors[0]


def test_pruned_primitives_are_left_out_as_the_renderer_leaves_them_out():
    model, verts = tiny_model(seed=2)
    keep = torch.ones(model.config.num_prims, dtype=torch.bool)
    keep[::3] = False
    model.prune(keep)
    geometry = decode(model, verts)
    assert geometry.keep is not None
    dirs = fibonacci_sphere(6)
    fast = direction_images(model, geometry, _camera(), dirs, centre=CENTRE)
    slow = direction_images(model, geometry, _camera(), dirs, centre=CENTRE, method="raymarch")
    torch.testing.assert_close(fast.rgb, slow.rgb, rtol=0.0, atol=2e-5 * float(slow.rgb.max()))


def test_voxel_bake_full_rank_is_the_voxel_space_sum(head, sunny):
    model, geometry = head
    voxels = bake_voxels(model, geometry, _camera(), fibonacci_sphere(COUNT), centre=CENTRE)
    lights = sunny.lights(1.0)
    reference, alpha = _sum_frame(model, geometry, lights)
    rgb, a = voxels.frame(sunny.weights(1.0))
    assert psnr_db(rgb, reference, alpha) >= 60.0
    np.testing.assert_allclose(a, alpha, atol=1e-6)
    assert psnr_db(voxels.truncated(4).frame(sunny.weights(1.0))[0], reference, alpha) < psnr_db(rgb, reference, alpha)


def test_saved_bake_round_trips_and_refuses_another_key(full, tmp_path):
    path = tmp_path / "bake.npz"
    full.save(path, key="abc")
    back = ImageBake.load(path, key="abc")
    weights = np.random.default_rng(1).uniform(size=(COUNT, 3))
    np.testing.assert_array_equal(back.frame(weights)[0], full.frame(weights)[0])
    assert back.distance_m == full.distance_m and np.array_equal(back.centre, full.centre)
    with pytest.raises(ValueError, match="another model"):
        ImageBake.load(path, key="other")
    path.write_bytes(b"not a bake")
    with pytest.raises(ValueError, match="bake.npz"):
        ImageBake.load(path)
    # The item cache's JSON + arrays form holds a bake too.
    from pipeline.itemcache import ItemCache

    cache = ItemCache(tmp_path / "items")
    entry = cache.path(ImageBake.to_arrays, "k")
    cache.store(entry, full.to_arrays())
    found, value = cache.load(entry)
    assert found and np.array_equal(ImageBake.from_arrays(value).frame(weights)[0], full.frame(weights)[0])


def test_a_light_that_is_not_a_baked_direction_is_refused(full):
    with pytest.raises(ValueError, match="not one of the 48 baked directions"):
        full.weights_of(np.array([[0.3, 0.3, 0.9]]), np.ones((1, 3)))


def test_direction_lights_sit_far_along_each_direction():
    lights = direction_lights(np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), 50.0, CENTRE)
    np.testing.assert_allclose(lights.positions, CENTRE + np.array([[0, 0, 50.0], [50.0, 0, 0]]))
    assert lights.rgb is None


def test_auto_renders_each_direction_where_the_transport_would_be_too_big(head, monkeypatch):
    import avatar.bake as bake

    model, geometry = head
    dirs = fibonacci_sphere(4)
    small = direction_images(model, geometry, _camera(), dirs, centre=CENTRE)  # transport

    def refuse(*args, **kwargs):
        raise AssertionError("the transport was built above TRANSPORT_MAX_SAMPLES")
    monkeypatch.setattr(bake, "TRANSPORT_MAX_SAMPLES", 100)
    monkeypatch.setattr(bake, "colour_transport", refuse)
    big = direction_images(model, geometry, _camera(), dirs, centre=CENTRE)
    torch.testing.assert_close(big.rgb, small.rgb, rtol=0.0, atol=2e-5 * float(small.rgb.max()))
