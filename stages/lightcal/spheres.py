"""Mirror-sphere silhouettes -> sphere centres in world space (known radius, calibrated cameras).

Each camera's silhouette outline is a set of rays tangent to the sphere. A single camera
fixes the cone around the sphere (axis and half-angle: a linear fit), hence a centre; all
cameras together refine it by least squares on ``distance(centre, ray) = radius``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import map_coordinates
from scipy.optimize import least_squares

from scene.camera import Camera


@dataclass(frozen=True)
class Silhouette:
    """One ball's outline in one camera."""

    camera: str
    outline_px: np.ndarray  # [N, 2] sub-pixel edge points
    centre_px: np.ndarray  # [2] blob centroid
    radius_px: float


def background_and_noise(grey: np.ndarray) -> tuple[float, float]:
    """Background level (median) and noise sigma (MAD) of a mostly-dark image."""
    bg = float(np.median(grey))
    sigma = float(1.4826 * np.median(np.abs(grey - bg)))
    return bg, max(sigma, 1e-6)


def find_silhouettes(grey: np.ndarray, camera: str, min_radius_px: float = 4.0, angles: int = 180,
                     noise: tuple[float, float] | None = None) -> tuple[list[Silhouette], list[str]]:
    """Bright round blobs (the balls under room light) and their sub-pixel outlines.

    ``noise``: (background, sigma) when known from elsewhere (an image of windows pasted on a
    flat background has no noise to measure); default: measured in ``grey``.
    Returns the silhouettes and notes on blobs that were rejected (cut by the image border,
    not round: two balls overlapping in this view).
    """
    import cv2

    bg, sigma = background_and_noise(grey) if noise is None else noise
    mask = grey > bg + 8 * sigma
    if not mask.any():
        return [], ["no bright blob"]
    body = float(np.median(grey[mask]))
    level = 0.5 * (bg + body)  # the anti-aliased edge crosses half way
    n, labels, stats, cents = cv2.connectedComponentsWithStats((grey > level).astype(np.uint8), connectivity=8)
    h, w = grey.shape
    found, notes = [], []
    for i in range(1, n):
        x, y, bw, bh, area = stats[i]
        radius = float(np.sqrt(area / np.pi))
        if radius < min_radius_px:
            continue
        if x <= 1 or y <= 1 or x + bw >= w - 1 or y + bh >= h - 1:
            notes.append(f"ball at ({cents[i][0]:.0f}, {cents[i][1]:.0f}) cut by the image border")
            continue
        if abs(bw - bh) > 0.25 * max(bw, bh) or area < 0.6 * np.pi * (0.5 * max(bw, bh)) ** 2:
            notes.append(f"blob at ({cents[i][0]:.0f}, {cents[i][1]:.0f}) is not round (balls overlap?)")
            continue
        centre = np.asarray(cents[i], float)
        # radial profiles from outside inwards: the first crossing of the edge level is the outline
        theta = np.linspace(0, 2 * np.pi, angles, endpoint=False)
        steps = np.arange(1.5 * radius + 3, 0.5 * radius, -0.1)
        xs = centre[0] + np.cos(theta)[:, None] * steps
        ys = centre[1] + np.sin(theta)[:, None] * steps
        prof = map_coordinates(grey, [ys, xs], order=1, mode="nearest")  # [A, S]
        above = prof > level
        pts = []
        for a in range(angles):
            idx = np.argmax(above[a])
            if not above[a, idx] or idx == 0:
                continue
            v0, v1 = prof[a, idx - 1], prof[a, idx]
            frac = (level - v0) / (v1 - v0)
            r_edge = steps[idx - 1] + frac * (steps[idx] - steps[idx - 1])
            pts.append(centre + r_edge * np.array([np.cos(theta[a]), np.sin(theta[a])]))
        if len(pts) >= angles // 2:
            found.append(Silhouette(camera, np.asarray(pts), centre, radius))
    return found, notes


def cone_centre(cam: Camera, outline_px: np.ndarray, radius_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Centre of a sphere of known radius from one camera's outline: the tangent cone's apex fit.

    Unit rays ``d_i`` along the outline satisfy ``a . d_i = cos(alpha)``; solving
    ``w . d_i = 1`` linearly gives ``a = w / |w|``, ``cos(alpha) = 1 / |w|``.
    Returns the centre [3] and the cone axis [3].
    """
    _, dirs = cam.pixel_rays(outline_px)
    w, *_ = np.linalg.lstsq(dirs, np.ones(len(dirs)), rcond=None)
    axis = w / np.linalg.norm(w)
    cos_a = min(1.0 / np.linalg.norm(w), 1 - 1e-9)
    sin_a = np.sqrt(1 - cos_a ** 2)
    return cam.center_world + radius_m / sin_a * axis, axis


def refine_centre(cams: list[Camera], outlines: list[np.ndarray], radius_m: float, init: np.ndarray
                  ) -> tuple[np.ndarray, float]:
    """Least-squares centre from all cameras' outline rays (soft L1); returns centre [3] and RMS (m)."""
    origins, dirs = [], []
    for cam, pts in zip(cams, outlines):
        o, d = cam.pixel_rays(pts)
        origins.append(o)
        dirs.append(d)
    o = np.concatenate(origins)
    d = np.concatenate(dirs)

    def residual(x: np.ndarray) -> np.ndarray:
        v = x - o
        return np.linalg.norm(v - (v * d).sum(-1, keepdims=True) * d, axis=-1) - radius_m

    fit = least_squares(residual, init, loss="soft_l1", f_scale=radius_m * 0.01, x_scale=radius_m)
    return fit.x, float(np.sqrt(np.mean(residual(fit.x) ** 2)))


def group_estimates(estimates: list[tuple[int, np.ndarray]], radius_m: float) -> list[list[int]]:
    """Cluster per-camera centre estimates (index, centre) of the same ball (closer than a radius)."""
    groups: list[list[int]] = []
    centres: list[np.ndarray] = []
    for i, c in estimates:
        for g, gc in zip(groups, centres):
            if np.linalg.norm(gc - c) < radius_m:
                g.append(i)
                break
        else:
            groups.append([i])
            centres.append(c)
    return groups
