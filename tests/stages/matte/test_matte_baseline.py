"""The classical threshold + guided-filter matte."""

import numpy as np

from stages.matte.baseline import baseline_matte
from stages.matte.measures import gradient_error, mae
from stages.matte.synthetic import full_on_lights, random_figure, render


def test_baseline_mattes_a_full_on_figure():
    rng = np.random.default_rng(3)
    figure = random_figure(rng, 64, 64)
    dirs, rgb = full_on_lights(rng)
    image, alpha = render(figure, 64, 64, dirs, rgb, 0.05)
    matte = baseline_matte(image)
    assert matte.shape == alpha.shape and matte.dtype == np.float32
    assert mae(matte, alpha) < 0.03
    assert mae(matte, alpha) < mae(np.zeros_like(alpha), alpha) / 5


def test_baseline_empty_frame_is_empty():
    rng = np.random.default_rng(0)
    noise = np.maximum(rng.normal(0, 1e-3, (48, 40, 3)), 0).astype(np.float32)
    assert baseline_matte(noise).max() == 0.0


def test_gradient_error_sees_blur():
    alpha = np.zeros((32, 32), np.float32)
    alpha[8:24, 8:24] = 1
    blurred = np.convolve(alpha.ravel(), np.ones(5) / 5, mode="same").reshape(32, 32)
    assert gradient_error(alpha, alpha) == 0.0
    assert gradient_error(blurred, alpha) > 0.0
