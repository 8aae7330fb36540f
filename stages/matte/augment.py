"""Training augmentation of linear images: flips, exposure, sensor noise, defocus blur, crops.

Everything happens in linear light before the input normalisation, so the network sees
the same kind of exposure and noise variation a real camera gives. The guide F frame and
the target frame get independent exposure and noise (they are different exposures), the
same flip and crop (they are the same camera).
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.ndimage import gaussian_filter



class AugmentConfig(BaseModel):
    """How strongly to augment a training sample."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    exposure_stops: float = Field(1.5, description="Exposure jitter, +- this many stops, drawn per image.")
    noise_max: float = Field(0.01, description="Largest Gaussian read-noise sigma, as a fraction of the F frame's bright level.")
    shot_noise_max: float = Field(0.02, description="Largest shot-noise factor (sigma = factor * sqrt(value * bright level)).")
    blur_probability: float = Field(0.3, description="Probability of a defocus blur on the target image.")
    blur_sigma_max_px: float = Field(1.0, description="Largest Gaussian blur sigma in pixels.")
    flip_probability: float = Field(0.5, description="Probability of a horizontal flip.")


def _noisy(image: np.ndarray, level: float, rng: np.random.Generator, config: AugmentConfig) -> np.ndarray:
    read_sigma = rng.uniform(0.0, config.noise_max) * level
    shot = rng.uniform(0.0, config.shot_noise_max)
    sigma = np.sqrt(read_sigma ** 2 + shot ** 2 * level * np.clip(image, 0.0, None))
    return np.clip(image + rng.normal(0.0, 1.0, image.shape).astype(np.float32) * sigma, 0.0, None)


def augment(image: np.ndarray, guide: np.ndarray, alpha: np.ndarray, reference: float, is_olat: bool,
            rng: np.random.Generator, config: AugmentConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Augmented copies of (image [H,W,3], guide [H,W,3], alpha [H,W]) and the guide's new reference level.

    ``reference`` is the camera's F exposure reference for this sample (the clean guide's
    bright level; a typical level for an empty frame); noise is relative to it because an
    OLAT frame's own level can be tiny. An F target is its own guide and stays identical to it.
    """
    if rng.uniform() < config.flip_probability:
        image, guide, alpha = image[:, ::-1], guide[:, ::-1], alpha[:, ::-1]
    gain = 2.0 ** rng.uniform(-config.exposure_stops, config.exposure_stops)
    reference = reference * gain
    guide = _noisy(guide * np.float32(gain), reference, rng, config)
    if is_olat:
        image = image * np.float32(gain * 2.0 ** rng.uniform(-config.exposure_stops, config.exposure_stops))
        if rng.uniform() < config.blur_probability:
            sigma = rng.uniform(0.2, config.blur_sigma_max_px)
            image = gaussian_filter(image, (sigma, sigma, 0))
        image = _noisy(image, reference, rng, config)
    else:
        if rng.uniform() < config.blur_probability:
            sigma = rng.uniform(0.2, config.blur_sigma_max_px)
            guide = gaussian_filter(guide, (sigma, sigma, 0))
        image = guide
    return (np.ascontiguousarray(image, dtype=np.float32), np.ascontiguousarray(guide, dtype=np.float32),
            np.ascontiguousarray(alpha, dtype=np.float32), float(reference))


def random_crop(arrays: tuple[np.ndarray, ...], size_px: int, rng: np.random.Generator,
                fill: float = 0.0) -> tuple[np.ndarray, ...]:
    """The same random ``size_px`` square crop of every [H, W, ...] array, padded with ``fill`` if smaller.

    The default fill 0 is the black backdrop of a linear image (and alpha 0).
    """
    height, width = arrays[0].shape[:2]
    pad_h, pad_w = max(size_px - height, 0), max(size_px - width, 0)
    top = int(rng.integers(0, height + pad_h - size_px + 1))
    left = int(rng.integers(0, width + pad_w - size_px + 1))
    out = []
    for array in arrays:
        padding = [(pad_h // 2, pad_h - pad_h // 2), (pad_w // 2, pad_w - pad_w // 2)] + [(0, 0)] * (array.ndim - 2)
        padded = np.pad(array, padding, constant_values=fill) if pad_h or pad_w else array
        out.append(np.ascontiguousarray(padded[top:top + size_px, left:left + size_px]))
    return tuple(out)
