"""Procedural head-and-shoulders shapes with exact alpha, for tests and development.

A figure is a union of ellipses (head, ears, neck, shoulders) plus a bumpy hair cap and
thin hair strands, rasterised at ``supersample`` x the resolution and box-filtered, so the
alpha is exact coverage (fractional on edges and strands). Shading treats each ellipse as a
half-ellipsoid (normals from its height field), Lambertian: a full-on frame is lit from
many directions, an OLAT frame by one direction (often from the side or behind, leaving
half the head black). The backdrop is black, as in the studio.

A ``SyntheticPair`` is one training sample as the matte stage sees it: the target frame
(OLAT or F) with its alpha, and the guide F frame a frame-time earlier or later, in which
the figure has moved by a pixel or two.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter


@dataclass(frozen=True)
class Figure:
    """Ellipses (centre x, y, radii x, y, angle rad, height scale) in pixels, strands, albedo seed."""

    ellipses: np.ndarray  # [E, 6]
    hair_bumps: np.ndarray  # [K, 2] amplitude (fraction of radius), phase; on the head ellipse
    strands: np.ndarray  # [S, 5] x0, y0, x1, y1, width (pixels)
    skin_rgb: np.ndarray  # [3]
    hair_rgb: np.ndarray  # [3]
    seed: int


@dataclass(frozen=True)
class SyntheticPair:
    """A target frame, its alpha, and its guide F frame (linear RGB float32)."""

    image: np.ndarray  # [H, W, 3]
    alpha: np.ndarray  # [H, W]
    guide: np.ndarray  # [H, W, 3]
    is_olat: bool


def random_figure(rng: np.random.Generator, height: int, width: int) -> Figure:
    """A random head-and-shoulders figure roughly centred in an image of the given size."""
    s = min(height, width)
    cx = width * rng.uniform(0.4, 0.6)
    cy = height * rng.uniform(0.38, 0.5)
    rx, ry = s * rng.uniform(0.17, 0.24), s * rng.uniform(0.23, 0.3)
    angle = rng.uniform(-0.25, 0.25)
    ellipses = [[cx, cy, rx, ry, angle, 1.0],
                [cx - rx * 0.98, cy + ry * 0.05, rx * 0.16, ry * 0.22, 0.0, 0.3],  # ears
                [cx + rx * 0.98, cy + ry * 0.05, rx * 0.16, ry * 0.22, 0.0, 0.3],
                [cx, cy + ry * 1.05, rx * 0.55, ry * 0.6, 0.0, 0.6],  # neck
                [cx + rng.uniform(-0.1, 0.1) * s, cy + ry * 1.9, s * rng.uniform(0.45, 0.6), ry * 0.75, 0.0, 0.8]]
    if rng.uniform() < 0.3:  # a bun or a big hair volume at the back of the head
        ellipses.append([cx + rng.uniform(-0.4, 0.4) * rx, cy - ry * 0.75, rx * 0.5, ry * 0.4, 0.0, 0.5])
    bumps = np.stack([rng.uniform(0.0, 0.06, 6), rng.uniform(0, 2 * np.pi, 6)], axis=1)
    strand_count = int(rng.integers(0, 12))
    strands = []
    for _ in range(strand_count):
        theta = rng.uniform(-np.pi * 0.95, -np.pi * 0.05)  # upper half of the head
        x0, y0 = cx + rx * 0.95 * np.cos(theta), cy + ry * 0.95 * np.sin(theta)
        length = s * rng.uniform(0.03, 0.1)
        direction = theta + rng.uniform(-0.6, 0.6)
        strands.append([x0, y0, x0 + length * np.cos(direction), y0 + length * np.sin(direction),
                        rng.uniform(0.3, 1.2)])
    skin = np.array([0.6, 0.42, 0.33]) * rng.uniform(0.3, 1.2) * rng.uniform(0.85, 1.15, 3)
    hair = np.array([0.2, 0.13, 0.08]) * rng.uniform(0.2, 2.5) * rng.uniform(0.8, 1.2, 3)
    return Figure(np.array(ellipses, float), bumps, np.array(strands, float).reshape(-1, 5),
                  skin.astype(np.float32), hair.astype(np.float32), int(rng.integers(1 << 30)))


def moved(figure: Figure, rng: np.random.Generator, max_shift_px: float) -> Figure:
    """The figure a frame-time later: shifted and turned a little."""
    shift = rng.uniform(-max_shift_px, max_shift_px, 2)
    turn = rng.uniform(-0.02, 0.02)
    ellipses = figure.ellipses.copy()
    ellipses[:, :2] += shift
    ellipses[:, 4] += turn
    strands = figure.strands.copy()
    strands[:, [0, 2]] += shift[0]
    strands[:, [1, 3]] += shift[1]
    return Figure(ellipses, figure.hair_bumps, strands, figure.skin_rgb, figure.hair_rgb, figure.seed)


def _rasterise(figure: Figure, height: int, width: int, supersample: int):
    """Coverage, normals and hair mask at ``supersample`` x resolution."""
    hs, ws = height * supersample, width * supersample
    ys, xs = np.mgrid[0:hs, 0:ws].astype(np.float32)
    xs = (xs + 0.5) / supersample - 0.5
    ys = (ys + 0.5) / supersample - 0.5
    inside = np.zeros((hs, ws), bool)
    height_field = np.full((hs, ws), -np.inf, np.float32)
    normal = np.zeros((hs, ws, 3), np.float32)
    hair = np.zeros((hs, ws), bool)
    for k, (cx, cy, rx, ry, angle, z_scale) in enumerate(figure.ellipses):
        c, s = np.cos(angle), np.sin(angle)
        u = ((xs - cx) * c + (ys - cy) * s) / rx
        v = (-(xs - cx) * s + (ys - cy) * c) / ry
        radius2 = u * u + v * v
        if k == 0:  # the head: a bumpy outline (hair volume), hair on its upper part
            polar = np.arctan2(v, u)
            bump = sum(a * np.sin((i + 3) * polar + p) for i, (a, p) in enumerate(figure.hair_bumps))
            upper = np.clip(-v, 0.0, 1.0)  # bumps only on the upper half
            limit = (1.0 + bump * upper) ** 2
        else:
            limit = np.ones_like(radius2)
        part = radius2 < limit
        z = np.sqrt(np.clip(1.0 - radius2 / limit, 0.0, 1.0)) * z_scale * max(rx, ry)
        front = part & (z > height_field)
        height_field = np.where(front, z, height_field)
        # Ellipsoid normal in image axes (x right, y down, z towards the camera).
        nu, nv = u / rx, v / ry
        nx, ny = nu * c - nv * s, nu * s + nv * c
        nz = np.sqrt(np.clip(1.0 - radius2 / limit, 1e-4, 1.0)) / max(rx, ry) * 1.5
        n = np.stack([nx, ny, nz], -1)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        normal = np.where(front[..., None], n, normal)
        if k == 0:
            hair |= part & (v < -0.35 + 0.1 * np.sin(4 * u))
        inside |= part
    for x0, y0, x1, y1, width_px in figure.strands:
        dx, dy = x1 - x0, y1 - y0
        t = np.clip(((xs - x0) * dx + (ys - y0) * dy) / (dx * dx + dy * dy + 1e-9), 0.0, 1.0)
        dist = np.hypot(xs - (x0 + t * dx), ys - (y0 + t * dy))
        strand = dist < width_px / 2
        hair |= strand & ~inside
        normal = np.where((strand & ~inside)[..., None], np.array([0.0, -0.3, 0.95], np.float32), normal)
        inside |= strand
    return inside, normal, hair


def render(figure: Figure, height: int, width: int, light_dirs: np.ndarray, light_rgb: np.ndarray,
           ambient: float, supersample: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Linear RGB [H, W, 3] and alpha [H, W] of the figure lit by directional lights.

    ``light_dirs`` [L, 3] point from the figure towards each light (image axes, z to camera);
    ``light_rgb`` [L, 3] their radiance.
    """
    inside, normal, hair = _rasterise(figure, height, width, supersample)
    hs, ws = inside.shape
    rng = np.random.default_rng(figure.seed)
    texture = gaussian_filter(rng.normal(0.0, 1.0, (hs // 4 + 1, ws // 4 + 1)), 2.0)
    texture = np.kron(texture, np.ones((4, 4)))[:hs, :ws]
    texture = 1.0 + 0.25 * texture / (texture.std() + 1e-6)
    albedo = np.where(hair[..., None], figure.hair_rgb, figure.skin_rgb) * texture[..., None]  # [hs, ws, 3]
    irradiance = np.full((hs, ws, 3), ambient, np.float32)
    for direction, rgb in zip(light_dirs, light_rgb):
        direction = direction / np.linalg.norm(direction)
        irradiance += np.clip(normal @ direction, 0.0, None)[..., None] * rgb
    radiance = albedo * irradiance * inside[..., None]
    image = radiance.reshape(height, supersample, width, supersample, 3).mean(axis=(1, 3))
    alpha = inside.reshape(height, supersample, width, supersample).mean(axis=(1, 3))
    return image.astype(np.float32), alpha.astype(np.float32)


def full_on_lights(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Many lights around the front hemisphere (the studio's F frame)."""
    count = 12
    theta = rng.uniform(-np.pi * 0.6, np.pi * 0.6, count)
    phi = rng.uniform(-0.6, 0.6, count)
    dirs = np.stack([np.sin(theta) * np.cos(phi), np.sin(phi), np.cos(theta) * np.cos(phi)], 1)
    return dirs, np.full((count, 3), 1.0 / count * 1.6)


def olat_light(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One light somewhere on the sphere around the head, biased to the sides (the studio's OLAT frame)."""
    theta = rng.uniform(-np.pi * 0.85, np.pi * 0.85)
    phi = rng.uniform(-0.9, 0.9)
    direction = np.array([[np.sin(theta) * np.cos(phi), np.sin(phi), np.cos(theta) * np.cos(phi)]])
    return direction, np.full((1, 3), rng.uniform(0.02, 0.2))


def random_pair(rng: np.random.Generator, height: int, width: int, olat_probability: float = 0.6,
                empty_probability: float = 0.05, max_shift_px: float = 1.5, supersample: int = 4) -> SyntheticPair:
    """One training sample: target (OLAT or F) frame, its alpha, its guide F frame."""
    if rng.uniform() < empty_probability:
        black = np.zeros((height, width, 3), np.float32)
        return SyntheticPair(black, np.zeros((height, width), np.float32), black, bool(rng.uniform() < 0.5))
    figure = random_figure(rng, height, width)
    guide_figure = moved(figure, rng, max_shift_px)
    f_dirs, f_rgb = full_on_lights(rng)
    guide, _ = render(guide_figure, height, width, f_dirs, f_rgb, 0.05, supersample)
    if rng.uniform() < olat_probability:
        dirs, rgb = olat_light(rng)
        image, alpha = render(figure, height, width, dirs, rgb, 0.0, supersample)
        return SyntheticPair(image, alpha, guide, True)
    image, alpha = render(figure, height, width, f_dirs, f_rgb, 0.05, supersample)
    return SyntheticPair(image, alpha, image, False)
