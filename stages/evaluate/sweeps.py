"""Sweep geometry and break points: where a quality curve falls under a threshold.

Pure numpy, no rendering: the evaluate stage and ``benchmarks.stability`` feed measured
curves in, these functions say where they break.

A break point is found by walking the curve outward from its trusted end (the training
lights, scale 1, zero noise) and stopping at the first sample under the threshold; the
crossing is linearly interpolated between that sample and the previous one. Walking from
the trusted end, not taking the global minimum, is deliberate: a curve that dips and
recovers further out is still broken from the first dip on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Crossing:
    """Where a curve crosses its threshold going outward.

    Attributes:
        x: the interpolated crossing; when the curve never crosses, the last x tested
            (a lower bound: ``censored`` is then True); when the first sample already fails,
            that sample's x (``failed_at_start`` True).
        censored: no sample fell under the threshold; ``x`` is only a bound.
        failed_at_start: the trusted end itself is under the threshold.
    """

    x: float
    censored: bool
    failed_at_start: bool


def first_crossing(x: np.ndarray, quality: np.ndarray, threshold: float, *, higher_is_better: bool = True) -> Crossing:
    """The first x, walking in the order given, where ``quality`` falls past ``threshold``.

    ``x`` [N] and ``quality`` [N] in walking order (trusted end first). ``higher_is_better``
    False for error curves (fails when the error rises above the threshold). Non-finite
    quality counts as failing.
    """
    x = np.asarray(x, float).reshape(-1)
    q = np.asarray(quality, float).reshape(-1)
    if x.size == 0 or x.size != q.size:
        raise ValueError(f"first_crossing: need as many x as quality values, got {x.size} and {q.size}")
    margin = (q - threshold) if higher_is_better else (threshold - q)  # >= 0 passes
    margin = np.where(np.isfinite(margin), margin, -np.inf)
    failing = np.flatnonzero(margin < 0)
    if failing.size == 0:
        return Crossing(float(x[-1]), censored=True, failed_at_start=False)
    k = int(failing[0])
    if k == 0:
        return Crossing(float(x[0]), censored=False, failed_at_start=True)
    m0, m1 = margin[k - 1], margin[k]
    t = 1.0 if not np.isfinite(m1) else m0 / max(m0 - m1, 1e-12)  # fraction of the step to the zero
    return Crossing(float(x[k - 1] + t * (x[k] - x[k - 1])), censored=False, failed_at_start=False)


def unit(v: np.ndarray) -> np.ndarray:
    """Rows of ``v`` [..., 3] scaled to unit length."""
    v = np.asarray(v, float)
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def orbit_directions(count: int, plane: str = "horizontal") -> tuple[np.ndarray, np.ndarray]:
    """``count`` directions evenly around a circle: (angles_deg [N], unit directions [N, 3]).

    ``horizontal``: azimuth about +y, 0 = straight in front (+z), 90 = the subject's left (+x),
    180 = straight behind. ``vertical``: elevation in the y-z plane, 0 = front, 90 = above,
    180 = behind, 270 = below.
    """
    if count < 1:
        raise ValueError(f"orbit_directions: count={count} must be at least 1")
    angles = np.arange(count) * 360.0 / count
    a = np.radians(angles)
    if plane == "horizontal":
        dirs = np.stack([np.sin(a), np.zeros_like(a), np.cos(a)], -1)
    elif plane == "vertical":
        dirs = np.stack([np.zeros_like(a), np.sin(a), np.cos(a)], -1)
    else:
        raise ValueError(f"orbit_directions: plane '{plane}' is not 'horizontal' or 'vertical'")
    return angles, dirs


def angle_to_nearest_deg(directions: np.ndarray, reference_directions: np.ndarray) -> np.ndarray:
    """Angle in degrees [N] from each of ``directions`` [N, 3] to the nearest of ``reference_directions`` [R, 3]."""
    d = unit(np.asarray(directions, float).reshape(-1, 3))
    r = unit(np.asarray(reference_directions, float).reshape(-1, 3))
    if r.shape[0] == 0:
        raise ValueError("angle_to_nearest_deg: no reference directions")
    cos = np.clip(d @ r.T, -1.0, 1.0).max(-1)  # [N]
    return np.degrees(np.arccos(cos))


def extrapolation_limit_deg(angle_from_training_deg: np.ndarray, psnr_db: np.ndarray, threshold_db: float) -> Crossing:
    """The angle from the nearest training light where PSNR first falls under ``threshold_db``.

    Samples are walked by increasing angle (nearest the training lights first); samples at
    equal angles are taken worst first, so a failure on either side of the rig counts.
    """
    a = np.asarray(angle_from_training_deg, float).reshape(-1)
    p = np.asarray(psnr_db, float).reshape(-1)
    order = np.lexsort((np.where(np.isfinite(p), p, -np.inf), a))
    return first_crossing(a[order], p[order], threshold_db)


def azimuth_limit_deg(orbit_deg: np.ndarray, psnr_db: np.ndarray, threshold_db: float) -> Crossing:
    """How far from the front (orbit angle 0) a horizontal orbit holds, the worse of both sides.

    ``orbit_deg`` [N] in [0, 360); walks 0 -> 180 on one side and 0 -> -180 on the other
    (angles folded to 0..180) and returns the smaller crossing.
    """
    a = np.mod(np.asarray(orbit_deg, float).reshape(-1), 360.0)
    p = np.asarray(psnr_db, float).reshape(-1)
    eps = 1e-9
    right = a <= 180.0 + eps                  # 0 -> 180 through the subject's left (+x)
    left = (a <= eps) | (a >= 180.0 - eps)    # 0 -> 360 = -180 through the subject's right
    sides = []
    for mask, folded in ((right, a), (left, np.where(a <= eps, 0.0, 360.0 - a))):
        order = np.argsort(folded[mask], kind="stable")
        sides.append(first_crossing(folded[mask][order], p[mask][order], threshold_db))
    return min(sides, key=lambda c: c.x)


def scale_limits(scales: np.ndarray, psnr_db: np.ndarray, threshold_db: float) -> tuple[Crossing, Crossing]:
    """Expression-magnitude break points (low, high): walking down and up from the scale nearest 1."""
    s = np.asarray(scales, float).reshape(-1)
    p = np.asarray(psnr_db, float).reshape(-1)
    order = np.argsort(s)
    s, p = s[order], p[order]
    start = int(np.argmin(np.abs(s - 1.0)))
    down = first_crossing(s[:start + 1][::-1], p[:start + 1][::-1], threshold_db)
    up = first_crossing(s[start:], p[start:], threshold_db)
    return down, up


def angle_between_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle in degrees between two 3-vectors."""
    ua, ub = unit(np.asarray(a, float)), unit(np.asarray(b, float))
    return math.degrees(math.acos(float(np.clip(ua @ ub, -1.0, 1.0))))
