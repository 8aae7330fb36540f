"""The public render API (``avatar.render``): light types, the voxel-space sum against the per-light
reference, linearity in the lights' RGB weights, and the TRAvatar* path."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatar.raymarch import raymarch
from avatar.render import BasisLights, DirectionalLights, PointLights, Rays, decode, render
from avatar.travatar import LightBasis, interpolated_rgb
from scene.camera import Camera, look_at
from scene.envmap import select_uniform, synthetic_sky
from tests.stages.relight.conftest import tiny_model

BASIS_DIRECTIONS = np.array([[0.0, 0.0, 1.0], [0.7, 0.0, 0.7], [-0.7, 0.0, 0.7], [0.0, 0.7, 0.7], [0.0, -0.7, 0.7]])


@pytest.fixture(scope="module")
def ours():
    torch.set_num_threads(1)
    return tiny_model()


@pytest.fixture(scope="module")
def travatar():
    return tiny_model(seed=1, light_basis=len(BASIS_DIRECTIONS))


def _camera(width: int = 16, height: int = 20) -> Camera:
    cam = Camera("test", width, height, fx=40.0, fy=40.0, cx=width / 2 - 0.5, cy=height / 2 - 0.5)
    return cam.with_pose(look_at(np.array([0.1, 0.05, 0.6]), np.zeros(3)), "head")


def _sky(count: int = 20):
    lights = select_uniform(synthetic_sky(32, np.array([0.4, 0.5, 0.7]), 0.5), count=count, drop_fraction=0.1)
    return lights.directions_world, lights.irradiance_rgb / lights.irradiance_rgb.sum(0).max()


def test_voxel_sum_equals_the_per_light_sum(ours):
    model, verts = ours
    directions, rgb = _sky()
    lights = PointLights(50.0 * directions, rgb)
    geometry = decode(model, verts)
    fast = render(model, geometry, _camera(), lights, light_batch=6)
    naive = render(model, geometry, _camera(), lights, light_batch=6, method="per_light")
    assert float(fast.rgb.max()) > 0.05  # the head is in view and lit
    assert float((fast.rgb - naive.rgb).abs().max()) < 1e-4
    assert torch.equal(fast.alpha, naive.alpha)
    # The batch size changes nothing but rounding; lights matter (one light gives another image).
    assert float((render(model, geometry, _camera(), lights, light_batch=64).rgb - fast.rgb).abs().max()) < 1e-5
    assert float((render(model, geometry, _camera(), lights[:1]).rgb - fast.rgb).abs().max()) > 1e-3


def test_directional_lights_are_far_point_lights(ours):
    model, verts = ours
    directions, rgb = _sky(8)
    centre = np.array([0.0, 0.01, 0.0])
    directional = render(model, verts, _camera(), DirectionalLights(directions, rgb, distance_m=40.0, centre=centre))
    point = render(model, verts, _camera(), PointLights(centre + 40.0 * directions, rgb))
    assert torch.equal(directional.rgb, point.rgb) and torch.equal(directional.alpha, point.alpha)
    # A near point light along the same direction lights the head differently (near field).
    near = render(model, verts, _camera(), PointLights(centre + 1.0 * directions, rgb))
    assert float((near.rgb - point.rgb).abs().max()) > 1e-3


def test_rgb_weights_scale_the_image_linearly(ours):
    model, verts = ours
    directions, rgb = _sky(6)
    geometry = decode(model, verts)
    one = render(model, geometry, _camera(), DirectionalLights(directions, rgb))
    two = render(model, geometry, _camera(), DirectionalLights(directions, 2.0 * rgb))
    # Doubling every weight is exact in binary floating point (each product and sum doubles).
    assert torch.equal(two.rgb, 2.0 * one.rgb) and torch.equal(two.alpha, one.alpha)
    # Per channel: a weight in red only leaves green and blue black.
    red = render(model, geometry, _camera(), DirectionalLights(directions, rgb * np.array([1.0, 0.0, 0.0])))
    assert float(red.rgb[..., 1:].abs().max()) == 0.0 and float(red.rgb[..., 0].max()) > 0.0
    # Unit lights (rgb=None) are weights of one; image_scale divides.
    unit = render(model, geometry, _camera(), PointLights(50.0 * directions[:1]))
    white = render(model, geometry, _camera(), PointLights(50.0 * directions[:1], np.ones((1, 3))), image_scale=0.5)
    assert float((white.rgb - 2.0 * unit.rgb).abs().max()) < 1e-6
    # A decoder gain per light (the train stage's learnt bar intensities) scales the same way.
    gained = render(model, geometry, _camera(), PointLights(50.0 * directions[:1], intensity=[2.0]))
    assert torch.equal(gained.rgb, 2.0 * unit.rgb)


def test_one_light_equals_decode_and_raymarch(ours):
    """The API computes what the documented building blocks do: decode_rgb, then raymarch."""
    model, verts = ours
    camera = _camera()
    rays = Rays.of_camera(camera)
    position = torch.tensor([[0.3, 0.2, 0.9]])
    image = render(model, verts, rays, PointLights(position))
    with torch.no_grad():
        geometry = decode(model, verts)
        rgb = model.decode_rgb(geometry, rays.position[None], position)
        res = raymarch(geometry.primitives(rgb), rays.origins[None], rays.directions[None], model.config.steps_per_ray)
    assert torch.equal(image.rgb, res.rgb.view(camera.height, camera.width, 3))
    assert torch.equal(image.alpha, res.alpha.view(camera.height, camera.width))
    assert torch.equal(render(model, verts, camera, PointLights(position)).rgb, image.rgb)


def test_travatar_interpolates_point_lights_over_its_basis(travatar):
    model, verts = travatar
    basis = LightBasis(BASIS_DIRECTIONS)
    camera = _camera()
    position = np.array([[0.4, 0.2, 1.0]])
    image = render(model, verts, camera, PointLights(position), basis=basis)
    rays = Rays.of_camera(camera)
    with torch.no_grad():
        geometry = decode(model, verts)
        weights = torch.as_tensor(basis.weights(position.astype(np.float32)), dtype=torch.float32)
        rgb = interpolated_rgb(model, geometry, rays.position[None], weights)
        res = raymarch(geometry.primitives(rgb), rays.origins[None], rays.directions[None], model.config.steps_per_ray)
    assert float(image.rgb.max()) > 0.01
    assert torch.equal(image.rgb, res.rgb.view(camera.height, camera.width, 3))
    # A training light's one-hot weights are fed as they are; the image is the network's for that light.
    one_hot = BasisLights(basis.one_hot(np.array([1])))
    at_bar = render(model, verts, camera, one_hot, basis=basis)
    with torch.no_grad():
        rgb = model.decode_rgb(geometry, rays.position[None], light_weights=torch.as_tensor(
            basis.one_hot(np.array([1])), dtype=torch.float32))
        res = raymarch(geometry.primitives(rgb), rays.origins[None], rays.directions[None], model.config.steps_per_ray)
    assert torch.equal(at_bar.rgb, res.rgb.view(camera.height, camera.width, 3))
    # Many lights: the voxel sum holds for the baseline too.
    directions, rgb = _sky(5)
    lights = DirectionalLights(directions, rgb, distance_m=1.5)
    fast = render(model, geometry, camera, lights, basis=basis, light_batch=2)
    naive = render(model, geometry, camera, lights, basis=basis, method="per_light")
    assert float((fast.rgb - naive.rgb).abs().max()) < 1e-4


def test_clear_errors(ours, travatar):
    model, verts = ours
    with pytest.raises(ValueError, match="no lights"):
        render(model, verts, _camera(), PointLights(np.zeros((0, 3))))
    with pytest.raises(ValueError, match="BasisLights"):
        render(model, verts, _camera(), BasisLights(np.eye(3)))
    with pytest.raises(ValueError, match="rows"):
        PointLights(np.zeros((2, 3)), np.ones((3, 3)))
    with pytest.raises(ValueError, match="method"):
        render(model, verts, _camera(), PointLights(np.ones((1, 3))), method="fastest")  # type: ignore[arg-type]
    world_camera = _camera().with_pose(_camera().cam_from_head, "world")  # a frame mix-up
    with pytest.raises(ValueError, match="world frame.*cam_from_head"):
        render(model, verts, world_camera, PointLights(np.ones((1, 3))))
    trav, trav_verts = travatar
    with pytest.raises(ValueError, match="light basis"):
        render(trav, trav_verts, _camera(), PointLights(np.ones((1, 3))))
