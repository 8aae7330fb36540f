"""sRGB transfer functions (IEC 61966-2-1) between linear RGB and display-encoded values."""

from __future__ import annotations

import numpy as np


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear RGB in [0, 1] (clipped) -> sRGB-encoded values in [0, 1], same shape."""
    x = np.clip(np.asarray(linear, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055).astype(np.float32)


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear RGB, same shape."""
    x = np.clip(np.asarray(encoded, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4)).astype(np.float32)


def luminance(linear_rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 relative luminance of linear RGB [..., 3] -> [...]."""
    rgb = np.asarray(linear_rgb, dtype=np.float32)
    return rgb[..., 0] * 0.2126 + rgb[..., 1] * 0.7152 + rgb[..., 2] * 0.0722


def srgb8(linear: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Linear RGB (or grey) times ``exposure`` -> 8-bit sRGB, same shape, uint8.

    The one linear-to-display quantiser of the project's PNGs: float32, ``srgb_encode``,
    ``round(x * 255)``.
    """
    return np.round(srgb_encode(np.asarray(linear, dtype=np.float32) * exposure) * 255.0).astype(np.uint8)
