"""Spline and Slerp interpolation of the full-on fits to every frame."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stages.track.geometry import rotation_angle_deg
from stages.track.interpolate import interpolate_track


def _keys():
    key_t = np.array([0.0, 0.125, 0.25, 0.375])
    key_R = Rotation.from_euler("y", [[0.0], [10.0], [20.0], [30.0]], degrees=True).as_matrix()
    key_tr = np.array([[0.0, 0, 0], [0.01, 0, 0], [0.02, 0, 0], [0.03, 0, 0]])
    key_w = np.array([[0.0, 1.0], [0.5, 1.0], [1.0, 1.0], [0.5, 1.0]])
    return key_t, key_R, key_tr, key_w


def test_interpolation_passes_through_the_key_frames():
    key_t, key_R, key_tr, key_w = _keys()
    R, t, w = interpolate_track(key_t, key_R, key_tr, key_w, key_t, 0.0, 1.0)
    assert np.allclose(R, key_R, atol=1e-9)
    assert np.allclose(t, key_tr)
    assert np.allclose(w, key_w)


def test_slerp_halfway_and_linear_motion_is_kept():
    key_t, key_R, key_tr, key_w = _keys()
    R, t, _ = interpolate_track(key_t, key_R, key_tr, key_w, np.array([0.0625, 0.3]), 0.0, 1.0)
    expected = Rotation.from_euler("y", [[5.0], [24.0]], degrees=True).as_matrix()
    assert rotation_angle_deg(R, expected).max() < 1e-6
    # A natural cubic spline through collinear keys is that line.
    assert np.allclose(t[:, 0], [0.005, 0.024], atol=1e-9)


def test_spline_overshoot_is_clipped_and_ends_are_held():
    key_t, key_R, key_tr, key_w = _keys()
    times = np.linspace(-0.1, 0.5, 61)
    R, t, w = interpolate_track(key_t, key_R, key_tr, key_w, times, 0.0, 1.0)
    assert w.min() >= 0.0 and w.max() <= 1.0
    assert np.allclose(w[:, 1], 1.0)  # constant weight stays constant
    assert np.allclose(t[times < 0], key_tr[0]) and np.allclose(t[times > 0.375], key_tr[-1])
    assert rotation_angle_deg(R[times > 0.375], key_R[-1]).max() < 1e-6


def test_single_key_frame_is_constant_and_bad_times_raise():
    key_t, key_R, key_tr, key_w = _keys()
    R, t, w = interpolate_track(key_t[:1], key_R[:1], key_tr[:1], key_w[:1], np.array([0.0, 1.0]), 0.0, 1.0)
    assert np.allclose(w, key_w[0]) and np.allclose(t, key_tr[0])
    with pytest.raises(ValueError):
        interpolate_track(key_t[::-1], key_R, key_tr, key_w, key_t, 0.0, 1.0)
