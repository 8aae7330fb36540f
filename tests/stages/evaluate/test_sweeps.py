"""Break points of quality curves: interpolation, censoring, failure at the trusted end, walking order."""

from __future__ import annotations

import numpy as np
import pytest

from stages.evaluate.sweeps import (angle_to_nearest_deg, extrapolation_limit_deg, first_crossing, orbit_directions,
                                    scale_limits)


def test_crossing_is_interpolated_between_the_last_pass_and_the_first_fail():
    c = first_crossing(np.array([0.0, 10.0, 20.0, 30.0]), np.array([30.0, 28.0, 26.0, 22.0]), 25.0)
    assert not c.censored and not c.failed_at_start
    assert c.x == pytest.approx(22.5)  # 26 -> 22 crosses 25 a quarter of the way


def test_a_curve_that_never_fails_is_censored_at_the_last_x():
    c = first_crossing(np.array([1.0, 2.0, 3.0]), np.array([30.0, 29.0, 28.0]), 25.0)
    assert c.censored and c.x == 3.0


def test_failing_at_the_trusted_end_is_reported():
    c = first_crossing(np.array([1.0, 2.0]), np.array([20.0, 30.0]), 25.0)
    assert c.failed_at_start and not c.censored and c.x == 1.0


def test_the_first_dip_counts_even_if_the_curve_recovers():
    c = first_crossing(np.arange(5.0), np.array([30, 24, 30, 30, 10.0]), 25.0)
    assert 0.0 < c.x < 1.0


def test_error_curves_fail_upwards_and_nan_fails():
    c = first_crossing(np.array([0.0, 1.0, 2.0]), np.array([0.5, 1.0, 3.0]), 2.0, higher_is_better=False)
    assert c.x == pytest.approx(1.5)
    assert first_crossing(np.array([0.0, 1.0]), np.array([30.0, np.nan]), 25.0).x == 1.0


def test_mismatched_lengths_are_an_error():
    with pytest.raises(ValueError, match="as many"):
        first_crossing(np.zeros(3), np.zeros(2), 1.0)


def test_orbit_extrapolation_limit_on_a_synthetic_orbit():
    # Training lights: a frontal fan of +-60 degrees in azimuth. PSNR holds at 30 dB up to
    # 20 degrees beyond the fan, then drops 1 dB per degree: the limit is 25 degrees.
    fan = np.radians(np.linspace(-60, 60, 9))
    training = np.stack([np.sin(fan), np.zeros_like(fan), np.cos(fan)], -1)
    angles, dirs = orbit_directions(72)
    away = angle_to_nearest_deg(dirs, training)
    psnr = 30.0 - np.clip(away - 20.0, 0.0, None)
    limit = extrapolation_limit_deg(away, psnr, 25.0)
    assert limit.x == pytest.approx(25.0, abs=1e-6)
    # Straight behind the head is 120 degrees from the fan's edge.
    assert away[np.argmin(np.abs(angles - 180.0))] == pytest.approx(120.0, abs=1e-6)


def test_at_equal_angles_the_worse_side_counts():
    away = np.array([0.0, 10.0, 10.0, 20.0])
    psnr = np.array([30.0, 30.0, 20.0, 30.0])  # one side already fails at 10 degrees
    assert extrapolation_limit_deg(away, psnr, 25.0).x == pytest.approx(5.0)


def test_orbit_planes_and_directions():
    angles, dirs = orbit_directions(4, "vertical")
    np.testing.assert_allclose(dirs, [[0, 0, 1], [0, 1, 0], [0, 0, -1], [0, -1, 0]], atol=1e-12)
    _, dirs = orbit_directions(4)
    np.testing.assert_allclose(dirs[1], [1, 0, 0], atol=1e-12)
    with pytest.raises(ValueError, match="plane"):
        orbit_directions(4, "diagonal")


def test_expression_scale_limits_walk_both_ways_from_one():
    scales = np.array([2.0, 0.5, 1.0, 1.5, 0.75, 1.25, 1.75])
    psnr = 30.0 - 8.0 * np.abs(scales - 1.0)  # 25 dB at 1 +- 0.625
    low, high = scale_limits(scales, psnr, 25.0)
    assert not high.censored and high.x == pytest.approx(1.625)
    assert low.censored and low.x == 0.5  # 0.5 is only 4 dB down: never crosses on the low side


def test_azimuth_limit_takes_the_worse_side():
    from stages.evaluate.sweeps import azimuth_limit_deg

    a = np.arange(24) * 15.0
    front = np.minimum(a, 360.0 - a)
    psnr = 30.0 - 0.2 * np.clip(front - 90.0, 0.0, None)  # symmetric: 25 dB at 115 degrees
    assert azimuth_limit_deg(a, psnr, 25.0).x == pytest.approx(115.0)
    psnr[a == 255.0] = 10.0  # the subject's right breaks between 90 and 105 degrees round
    assert azimuth_limit_deg(a, psnr, 25.0).x == pytest.approx(93.75)
