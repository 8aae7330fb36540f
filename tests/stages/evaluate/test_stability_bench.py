"""Pieces of ``benchmarks.stability`` on synthetic data: blur kernel, labelling score, crossings."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.stability import crossing_record, label_errors, motion_blur


def test_motion_blur_spreads_a_point_over_its_length_and_keeps_energy():
    img = np.zeros((5, 21, 3), np.float32)
    img[2, 10] = 1.0
    out = motion_blur(img, 4)
    assert out[2, :, 0].sum() == pytest.approx(1.0)
    assert np.count_nonzero(out[2, :, 0]) == 4 and np.count_nonzero(out[[0, 1, 3, 4]]) == 0
    np.testing.assert_array_equal(motion_blur(img, 0), img)


def _synthetic_capture(cycles: int = 3, cameras: int = 5, bars: int = 12, seed: int = 0):
    rng = np.random.default_rng(seed)
    pattern = [x for i in range(0, bars, 2) for x in ("F", i, i + 1)]
    log = pattern * cycles
    per_bar = rng.uniform(0.02, 0.1, (cameras, bars))  # each camera sees each bar differently
    base = np.array([[per_bar[c].sum() if l == "F" else per_bar[c, l] for l in log] for c in range(cameras)])
    return log, base * np.exp(rng.normal(0.0, 0.01, base.shape))


def test_labelling_score_is_perfect_without_drops_and_counts_lost_pulses():
    log, brightness = _synthetic_capture()
    clean = label_errors(log, brightness, 0.0, seed=0)
    assert clean == {"wrong_ok_rate": 0.0, "missed_drops": 0, "usable_pulses": 1.0, "failed": False}
    dropped = label_errors(log, brightness, 0.05, seed=3)
    assert 0.0 < 1.0 - dropped["usable_pulses"] < 0.6  # some pulse lost its frame in some camera
    assert dropped["wrong_ok_rate"] <= 0.05


def test_walking_from_the_most_cameras_down():
    # Error rises as cameras are removed: the crossing is between 4 and 3 cameras.
    c = crossing_record([10, 6, 4, 3, 2], [0.2, 0.3, 0.8, 1.6, np.nan], 1.0)
    assert not c["censored"] and 3.0 < c["x"] < 4.0 and c["threshold"] == 1.0
