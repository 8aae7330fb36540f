"""Interpolation of the full-on fits to every frame: cubic splines and Slerp.

Blendweights and head translation follow a natural cubic spline through the full-on
frames (weights clipped back to their bounds, as a spline overshoots); head rotation
follows Slerp between neighbouring full-on frames. Times outside the first and last
full-on frame hold the nearest fit (no extrapolation: a spline's ends run away).
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, Slerp


def _held(times_s: np.ndarray, key_times_s: np.ndarray) -> np.ndarray:
    return np.clip(times_s, key_times_s[0], key_times_s[-1])


def interpolate_vectors(key_times_s: np.ndarray, key_values: np.ndarray, times_s: np.ndarray) -> np.ndarray:
    """Natural cubic spline through ``key_values`` [F, D] at ``key_times_s`` [F] -> [T, D].

    One key frame gives a constant; two give a straight line (a natural spline's degree).
    """
    key_times_s = np.asarray(key_times_s, dtype=np.float64)
    key_values = np.asarray(key_values, dtype=np.float64)
    times_s = np.asarray(times_s, dtype=np.float64)
    if len(key_times_s) == 1 or key_values.shape[1] == 0:
        return np.repeat(key_values[:1], len(times_s), axis=0)
    spline = CubicSpline(key_times_s, key_values, axis=0, bc_type="natural")
    return spline(_held(times_s, key_times_s))


def interpolate_rotations(key_times_s: np.ndarray, key_R: np.ndarray, times_s: np.ndarray) -> np.ndarray:
    """Slerp between rotations ``key_R`` [F, 3, 3] at ``key_times_s`` [F] -> [T, 3, 3]."""
    key_times_s = np.asarray(key_times_s, dtype=np.float64)
    times_s = np.asarray(times_s, dtype=np.float64)
    if len(key_times_s) == 1:
        return np.repeat(np.asarray(key_R)[:1], len(times_s), axis=0)
    slerp = Slerp(key_times_s, Rotation.from_matrix(key_R))
    return slerp(_held(times_s, key_times_s)).as_matrix()


def interpolate_track(key_times_s: np.ndarray, key_R: np.ndarray, key_t: np.ndarray, key_weights: np.ndarray,
                      times_s: np.ndarray, weight_min: float, weight_max: float
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pose and weights of the full-on key frames at every time in ``times_s`` [T].

    Args:
        key_times_s: times of the fitted full-on frames [F], strictly increasing.
        key_R, key_t: their world_from_head rotations [F, 3, 3] and translations [F, 3].
        key_weights: their blendweights [F, K].
        times_s: the times to evaluate [T].
        weight_min, weight_max: the weights' bounds (the spline's overshoot is clipped).

    Returns:
        R [T, 3, 3], t [T, 3], weights [T, K].
    """
    key_times_s = np.asarray(key_times_s, dtype=np.float64)
    if key_times_s.ndim != 1 or len(key_times_s) == 0 or np.any(np.diff(key_times_s) <= 0):
        raise ValueError("key frame times must be a non-empty, strictly increasing 1-D array")
    R = interpolate_rotations(key_times_s, key_R, times_s)
    t = interpolate_vectors(key_times_s, key_t, times_s)
    w = np.clip(interpolate_vectors(key_times_s, key_weights, times_s), weight_min, weight_max)
    return R, t, w
