"""The matting network trains in a studio of its own: backdrop, exposure, lens blur and sensor drawn per identity."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from stages.matte.conditions import IdentityConditions, TrainingConditions, film
from stages.matte.studio_data import IdentityJob, StudioDataConfig, render_identity


def test_film_composites_the_backdrop_then_blurs_then_adds_the_sensors_noise():
    rng = np.random.default_rng(0)
    rgb = np.zeros((64, 64, 3), np.float32)
    alpha = np.zeros((64, 64), np.float32)
    rgb[:, 32:] = 0.5
    alpha[:, 32:] = 1.0
    image, blurred = film(rgb, alpha, 0.1, 0.0, 0.0, 0.0, rng)
    assert np.allclose(image[:, :32], 0.1) and np.allclose(image[:, 32:], 0.5)  # backdrop behind the head only
    assert np.array_equal(blurred, alpha)
    image, blurred = film(rgb, alpha, 0.1, 2.0, 0.0, 0.0, rng)
    assert 0.0 < blurred[0, 31] < 1.0 and 0.1 < image[0, 31, 0] < 0.5  # the edge is soft in both alike
    assert np.allclose(image[:, :32, 0], 0.1 + 0.4 * blurred[:, :32], atol=1e-5)
    flat = np.full((200, 200, 3), 0.25, np.float32)
    noisy, _ = film(flat, np.ones((200, 200), np.float32), 0.0, 0.0, 4e-4, 0.01, rng)
    assert np.var(noisy) == pytest.approx(4e-4 * 0.25 + 0.01 ** 2, rel=0.05)  # shot + read variance


def test_each_identity_draws_its_own_conditions_within_the_ranges():
    ranges = TrainingConditions()
    draws = [IdentityConditions.draw(ranges, np.random.default_rng(seed)) for seed in range(50)]
    for name in ("backdrop_level", "exposure_scale", "sensor_noise_scale", "lens_blur_sigma_px"):
        values = [getattr(d, name) for d in draws]
        low, high = getattr(ranges, name)
        assert low <= min(values) < max(values) <= high, name
    same = TrainingConditions.same_as_capture()
    assert IdentityConditions.draw(same, np.random.default_rng(0)) == IdentityConditions(0.0, 1.0, 1.0, 0.0)
    with pytest.raises(ValidationError, match="backdrop_level"):
        TrainingConditions(backdrop_level=(0.1, 0.0))


def test_training_renders_differ_from_the_subjects_studio_in_backdrop():
    base = dict(identity_seeds=(1001,), frame_pairs_per_identity=2, cameras_per_frame=1, olat_fraction=0.0,
                empty_fraction=0.0, frames_per_take=4)
    grey = TrainingConditions(backdrop_level=(0.05, 0.05), exposure_scale=(1.0, 1.0),
                              sensor_noise_scale=(1.0, 1.0), lens_blur_sigma_px=(0.0, 0.0))

    def backdrop_over_skin(conditions: TrainingConditions) -> float:
        samples = render_identity(IdentityJob(1001, StudioDataConfig(**base, conditions=conditions), 0.0625))
        sample = samples[0]
        luminance = sample.image.mean(-1)
        return float(luminance[sample.alpha == 0].mean() / np.percentile(luminance[sample.alpha > 0.5], 99))

    assert backdrop_over_skin(grey) == pytest.approx(0.05, abs=0.01)
    assert backdrop_over_skin(TrainingConditions.same_as_capture()) < 0.01  # black, as the subject's studio
