"""The voxel-space light sum equals raymarching every light and summing the images."""

from __future__ import annotations

import numpy as np

from scene.camera import Camera, look_at
from scene.envmap import select_uniform, synthetic_sky
from stages.relight.render import HeadRenderer


def _camera(width: int = 24, height: int = 32) -> Camera:
    cam = Camera("test", width, height, fx=60.0, fy=60.0, cx=width / 2 - 0.5, cy=height / 2 - 0.5)
    return cam.with_pose(look_at(np.array([0.1, 0.05, 0.6]), np.zeros(3)))


def test_fast_voxel_sum_matches_naive_per_light_render(random_head):
    model, verts = random_head
    renderer = HeadRenderer(model, steps=24, light_batch=5)
    geometry = renderer.geometry(verts)
    lights = select_uniform(synthetic_sky(32, np.array([0.4, 0.5, 0.7]), 0.5), count=24, drop_fraction=0.1)
    pos = lights.positions_world(50.0)
    rgb = lights.irradiance_rgb / lights.irradiance_rgb.sum(0).max()  # image values O(0.1..1)
    fast = renderer.render_lights(geometry, _camera(), pos, rgb)
    naive = renderer.render_lights_naive(geometry, _camera(), pos, rgb)
    assert fast.rgb.max() > 0.05  # the head is in view and lit
    assert np.abs(fast.rgb - naive.rgb).max() < 1e-4
    assert np.array_equal(fast.alpha, naive.alpha)
    # Lights matter: a single light from the other side gives a different image.
    one = renderer.render_lights(geometry, _camera(), pos[:1], rgb[:1])
    assert np.abs(one.rgb - fast.rgb).max() > 1e-3
