"""Matte error measures against ground-truth alpha.

- MAE, MSE: mean over all pixels of |a - a*| and (a - a*)^2.
- Gradient error (Rhemann et al., 2009): the difference of gradient magnitudes, both
  computed with first-order Gaussian derivative filters (sigma 1.4 px), squared and
  averaged over pixels (the original sums and divides by 1000; a per-pixel mean is
  comparable across image sizes).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_gradient_magnitude

GRADIENT_SIGMA_PX = 1.4


def mae(alpha: np.ndarray, truth: np.ndarray) -> float:
    """Mean absolute error of two [H, W] mattes in [0, 1]."""
    return float(np.mean(np.abs(alpha.astype(np.float64) - truth)))


def mse(alpha: np.ndarray, truth: np.ndarray) -> float:
    """Mean squared error of two [H, W] mattes in [0, 1]."""
    return float(np.mean((alpha.astype(np.float64) - truth) ** 2))


def gradient_error(alpha: np.ndarray, truth: np.ndarray, sigma_px: float = GRADIENT_SIGMA_PX) -> float:
    """Mean squared difference of Gaussian-derivative gradient magnitudes of two [H, W] mattes."""
    grad_alpha = gaussian_gradient_magnitude(alpha.astype(np.float64), sigma_px)
    grad_truth = gaussian_gradient_magnitude(truth.astype(np.float64), sigma_px)
    return float(np.mean((grad_alpha - grad_truth) ** 2))


def all_measures(alpha: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """``{"mae", "mse", "grad_err"}`` of one matte."""
    return {"mae": mae(alpha, truth), "mse": mse(alpha, truth), "grad_err": gradient_error(alpha, truth)}
