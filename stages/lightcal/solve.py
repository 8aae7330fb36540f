"""Bar centre and axis from reflected rays (closest point to a set of lines, robustly)."""

from __future__ import annotations

import numpy as np


def closest_point(points: np.ndarray, dirs: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """The point nearest (least squares) to lines ``points + t dirs`` [N, 3] (dirs unit)."""
    w = np.ones(len(points)) if weights is None else weights
    proj = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]  # [N, 3, 3]
    A = (w[:, None, None] * proj).sum(0)
    b = (w[:, None, None] * proj @ points[:, :, None]).sum(0)[:, 0]
    return np.linalg.solve(A, b)


def ray_distances(x: np.ndarray, points: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Distance of ``x`` [3] from each ray [N]."""
    v = x - points
    return np.linalg.norm(v - (v * dirs).sum(-1, keepdims=True) * dirs, axis=-1)


def robust_closest_point(points: np.ndarray, dirs: np.ndarray, iterations: int = 5,
                         prior: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Closest point with iterative reweighting (Cauchy-like): a wrong highlight cannot drag it far.

    ``prior`` [N]: per-ray weights known beforehand (inverse variances, say), multiplied in.
    Returns the point [3] and the final weights [N] (robust times prior).
    """
    prior = np.ones(len(points)) if prior is None else np.asarray(prior, float)
    x = closest_point(points, dirs, prior)
    w = prior
    for _ in range(iterations):
        r = ray_distances(x, points, dirs)
        scale = max(1.4826 * float(np.median(r)), 1e-4)
        w = prior / (1.0 + (r / (2 * scale)) ** 2)
        x = closest_point(points, dirs, w)
    return x, w


def conditioning(dirs: np.ndarray) -> float:
    """Smallest eigenvalue of sum(I - d d^T) / N: 0 when all rays are parallel (no triangulation)."""
    proj = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]
    return float(np.linalg.eigvalsh(proj.mean(0))[0])


def ray_line_distances(origins: np.ndarray, dirs: np.ndarray, p: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Distance between each ray (line) [N, 3] and the line ``p + s a`` (a unit) [N]."""
    cross = np.cross(dirs, a)
    norm = np.linalg.norm(cross, axis=-1)
    par = norm < 1e-9  # parallel: point-to-line distance
    v = origins - p
    d_skew = np.abs((v * cross).sum(-1)) / np.where(par, 1.0, norm)
    d_par = np.linalg.norm(v - (v @ a)[:, None] * a, axis=-1)
    return np.where(par, d_par, d_skew)


def closest_param_on_line(origins: np.ndarray, dirs: np.ndarray, p: np.ndarray, a: np.ndarray) -> np.ndarray:
    """For each ray [N, 3], the parameter s of the line point ``p + s a`` nearest to it [N]."""
    w0 = p - origins
    b = dirs @ a
    d = (dirs * w0).sum(-1)
    e = w0 @ a
    denom = np.maximum(1.0 - b * b, 1e-12)
    return (b * d - e) / denom

