"""The bar's line from the rays reflected along highlight streaks: exact synthetic streaks, known bar."""

from __future__ import annotations

import numpy as np
import pytest

from scene.camera import Camera, look_at
from stages.lightcal.highlights import Highlight, reflect_ray
from stages.lightcal.solve import ray_line_distances
from stages.lightcal.stage import LightcalParams, _fit_bar_line, _incidence_weights

RADIUS_M = 0.035
BALLS = (np.array([-0.1, -0.05, 0.05]), np.array([0.1, -0.05, 0.05]), np.array([0.0, 0.12, 0.0]))
BAR_CENTRE = np.array([-0.9, 0.5, 0.8])
BAR_AXIS = np.array([0.3, 0.1, -0.95]) / np.linalg.norm([0.3, 0.1, -0.95])
BAR_LENGTH_M = 0.4


def _cameras() -> list[Camera]:
    eyes = ((0.0, 0.05, 1.2), (-0.6, 0.1, 1.0), (0.6, -0.1, 1.0), (0.1, 0.6, 1.0))
    return [Camera(f"cam{i:02d}", 768, 1024, 2400.0, 2400.0, 383.5, 511.5, (0.0,) * 5,
                   look_at(np.array(e), np.zeros(3))) for i, e in enumerate(eyes)]


def _mirror_points(cam: Camera, ball: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Where on the ball ``cam`` sees each of ``targets`` [N, 3] reflected: the normal bisects the
    directions to the camera and to the target (fixed-point iteration) -> [N, 3]."""
    n = np.tile((cam.center_world - ball) / np.linalg.norm(cam.center_world - ball), (len(targets), 1))
    for _ in range(200):
        p = ball + RADIUS_M * n
        to_cam = cam.center_world - p
        to_target = targets - p
        h = (to_cam / np.linalg.norm(to_cam, axis=1, keepdims=True)
             + to_target / np.linalg.norm(to_target, axis=1, keepdims=True))
        n = h / np.linalg.norm(h, axis=1, keepdims=True)
    return ball + RADIUS_M * n


def _streak_rays(noise_px: float = 0.0, seed: int = 0) -> list[tuple]:
    """The rays tuple lightcal builds per highlight, from exact ridge pixels of the bar's reflection."""
    rng = np.random.default_rng(seed)
    rays = []
    for cam in _cameras():
        for k, ball in enumerate(BALLS):
            s = np.linspace(-0.5, 0.5, 41) * BAR_LENGTH_M
            uv, _ = cam.project(_mirror_points(cam, ball, BAR_CENTRE + s[:, None] * BAR_AXIS))
            uv = uv + rng.normal(0.0, noise_px, uv.shape)
            mid = uv[len(uv) // 2]
            ends = uv[[0, -1]]
            major = (ends[1] - ends[0]) / np.linalg.norm(ends[1] - ends[0])
            hl = Highlight(cam.name, k, uv.mean(0), major, 10.0, 0.5, 1.0, False, ends, uv[1:-1], mid)
            hit = reflect_ray(cam, mid, ball, RADIUS_M)
            assert hit is not None
            rays.append((hit[0], hit[1], hl, cam, ball, hit[2]))
    return rays


def _off_line(p: np.ndarray, a: np.ndarray) -> tuple[float, float]:
    """(largest distance of the true bar's ends from the line p + s a, in mm; angle to the true axis, deg)."""
    ends = BAR_CENTRE + np.outer([-0.5, 0.5], BAR_AXIS * BAR_LENGTH_M)
    v = ends - p
    dist = np.linalg.norm(v - (v @ a)[:, None] * a, axis=1)
    return 1e3 * float(dist.max()), float(np.degrees(np.arccos(min(abs(a @ BAR_AXIS), 1.0))))


def test_mid_streak_rays_pass_the_true_bar():
    # the synthetic streaks are right: every mid-streak ray meets the true bar's line
    rays = _streak_rays()
    d = ray_line_distances(np.stack([r[0] for r in rays]), np.stack([r[1] for r in rays]), BAR_CENTRE, BAR_AXIS)
    assert d.max() < 1e-4


@pytest.mark.parametrize("free_axis", [False, True])
def test_line_fit_recovers_the_bar_from_an_offset_start(free_axis):
    rays = _streak_rays()
    across = np.cross(BAR_AXIS, [0.0, 1.0, 0.0])
    across /= np.linalg.norm(across)
    start = BAR_CENTRE + 0.03 * across + 0.02 * BAR_AXIS  # 3 cm off the line, 2 cm along it
    tilt = np.cross(BAR_AXIS, across)
    axis0 = BAR_AXIS + (np.radians(2.0) * tilt if free_axis else 0.0)
    axis0 /= np.linalg.norm(axis0)
    fitted = _fit_bar_line(rays, start, axis0, RADIUS_M, free_axis, LightcalParams())
    assert fitted is not None
    p, a, dist, _ = fitted
    off_mm, angle_deg = _off_line(p, a)
    if free_axis:
        assert off_mm < 0.5 and angle_deg < 0.05
    else:  # the axis stays as given, exact here: the line moves onto the bar
        assert off_mm < 0.5
    # the centre keeps its place along the bar (the ends' middle decides it, not the line fit)
    assert abs((p - BAR_CENTRE) @ BAR_AXIS - 0.02) < 1e-3
    assert dist.max() < 1e-3


def test_line_fit_with_noisy_ridges_stays_within_a_few_millimetres():
    # 0.05 px of independent noise on every ridge point (the balls are ~70 px in radius): the
    # rays leave a 0.2 m cluster of balls for a bar 1.3 m away, so depth is the weak direction
    rays = _streak_rays(noise_px=0.05, seed=4)
    start = BAR_CENTRE + np.array([0.0, 0.02, 0.0])
    off_mm, _ = _off_line(*_fit_bar_line(rays, start, BAR_AXIS, RADIUS_M, False, LightcalParams())[:2])
    assert off_mm < 3.0
    off_mm, angle_deg = _off_line(*_fit_bar_line(rays, start, BAR_AXIS, RADIUS_M, True, LightcalParams())[:2])
    assert off_mm < 8.0 and angle_deg < 1.5


def test_grazing_rays_weigh_less():
    w = _incidence_weights(np.array([0.0, 45.0, 60.0, 80.0]), 2.0)
    assert np.allclose(w, [1.0, 0.5, 0.25, np.cos(np.radians(80.0)) ** 2])
    assert np.allclose(_incidence_weights(np.array([70.0]), 0.0), 1.0)
