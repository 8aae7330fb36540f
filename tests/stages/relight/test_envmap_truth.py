"""The studio's envmap ground truth: lit from where the map is bright, and linear in the map."""

from __future__ import annotations

import numpy as np
import pytest

from hardware.studio.envmap_truth import envmap_truth_lights, frame_from_weights, render_envmap_truth
from scene.envmap import EnvMap, pixel_directions
from stages.relight.sequences import ViewSpec


@pytest.fixture(scope="module")
def subject():
    from hardware.studio.subject import make_subject

    return make_subject("alice", 1, texture_size=128)


def _lobe_map(direction) -> EnvMap:
    dirs = pixel_directions(32, 64)
    lobe = np.clip(dirs @ np.asarray(direction, float), 0, 1) ** 8  # a broad light from one side
    return EnvMap(np.repeat(lobe[..., None], 3, 2).astype(np.float32) + 0.01, "lobe")


def test_truth_lights_cover_the_whole_map():
    env = EnvMap(np.ones((16, 32, 3), np.float32), "white")
    lights = envmap_truth_lights(env, 128)
    assert len(lights) == 128  # nothing masked or dropped
    assert np.allclose(sum(l.irradiance_rgb for l in lights), 4 * np.pi)


@pytest.mark.slow
def test_light_from_plus_x_lights_the_subjects_left_the_viewers_right(subject):
    view = ViewSpec(24, 32, 0.9, 24.0, (0.0, 0.0, 0.0))
    cam = view.camera(view.front_eye())
    frame = frame_from_weights(np.zeros(57))
    left = render_envmap_truth(subject, frame, cam, _lobe_map([1.0, 0.0, 0.3]), directions=128)
    right = render_envmap_truth(subject, frame, cam, _lobe_map([-1.0, 0.0, 0.3]), directions=128)
    w = cam.width
    lum_left = left.rgb.sum(-1)
    # +x is the subject's left, which a front camera shows on the image's right half.
    assert lum_left[:, w // 2:].sum() > 1.5 * lum_left[:, :w // 2].sum()
    assert right.rgb.sum(-1)[:, :w // 2].sum() > 1.5 * right.rgb.sum(-1)[:, w // 2:].sum()
    double = render_envmap_truth(subject, frame, cam, EnvMap(2 * _lobe_map([1.0, 0.0, 0.3]).radiance, "x2"),
                                 directions=128)
    assert np.allclose(double.rgb, 2 * left.rgb, rtol=1e-4, atol=1e-6)
