"""The matting network's training studio: its own backdrop, sensor, exposure and lens, not the subject's.

A matting network trained on renders made exactly like the capture it mattes has no domain
gap to cross, and its accuracy on the subject says little about a real capture. Each
training identity is therefore filmed under conditions drawn once for it from ranges around
the virtual studio's own (``TrainingConditions``):

- a grey backdrop behind the head at a drawn level (the subject's studio is black), lit like
  the head: an OLAT frame's backdrop gets one bar's share of the F frame's;
- the bars' exposure scaled by a drawn factor;
- a Gaussian lens blur of a drawn width, applied to the image and to its alpha alike (the
  true coverage of a defocused edge is blurred too);
- the sensor's shot and read noise scaled by a drawn factor, added last, after the optics.

Per-sample augmentation (``stages.matte.augment``) then varies exposure, noise and blur
further from image to image. The capture's own camera effects (``capture.realism``) are not
among them, so a real-realism capture differs from every training render in its camera too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.ndimage import gaussian_filter

from hardware.studio.renderer import gaussian_sensor_noise


class TrainingConditions(BaseModel):
    """Ranges the training identities' studio conditions are drawn from, one draw per identity."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    backdrop_level: tuple[float, float] = Field(
        (0.0, 0.04), description="Backdrop radiance behind the head as a fraction of the identity's F-frame skin "
        "level (its 99th percentile), drawn uniformly; the subject's studio backdrop is black (0). A studio with a "
        "lighter backdrop than this range should widen it.")
    exposure_scale: tuple[float, float] = Field(
        (0.5, 2.0), description="Factor on the bars' intensity (the exposure of the whole take), drawn log-uniformly.")
    sensor_noise_scale: tuple[float, float] = Field(
        (0.5, 3.0), description="Factor on the studio's shot- and read-noise levels (capture.render's), drawn "
        "log-uniformly: the training studio's sensor is cleaner or noisier than the subject's.")
    lens_blur_sigma_px: tuple[float, float] = Field(
        (0.0, 0.8), description="Gaussian lens blur of image and alpha, pixels at the capture's size, drawn "
        "uniformly (0 = sharp).")

    @model_validator(mode="after")
    def _ordered(self) -> TrainingConditions:
        for name in ("backdrop_level", "exposure_scale", "sensor_noise_scale", "lens_blur_sigma_px"):
            low, high = getattr(self, name)
            if not 0 <= low <= high:
                raise ValueError(f"matte.data.conditions.{name}: ({low}, {high}) must be 0 <= low <= high")
        if self.exposure_scale[0] <= 0 or self.sensor_noise_scale[0] <= 0:
            raise ValueError("matte.data.conditions: exposure_scale and sensor_noise_scale must be above 0")
        return self

    @staticmethod
    def same_as_capture() -> TrainingConditions:
        """No gap: a black backdrop, the studio's exposure and sensor, no blur (for studies of the gap itself)."""
        return TrainingConditions(backdrop_level=(0.0, 0.0), exposure_scale=(1.0, 1.0),
                                  sensor_noise_scale=(1.0, 1.0), lens_blur_sigma_px=(0.0, 0.0))


@dataclass(frozen=True)
class IdentityConditions:
    """One identity's drawn studio conditions."""

    backdrop_level: float
    exposure_scale: float
    sensor_noise_scale: float
    lens_blur_sigma_px: float

    @staticmethod
    def draw(ranges: TrainingConditions, rng: np.random.Generator) -> IdentityConditions:
        def log_uniform(low: float, high: float) -> float:
            return float(np.exp(rng.uniform(np.log(low), np.log(high))))

        return IdentityConditions(backdrop_level=float(rng.uniform(*ranges.backdrop_level)),
                                  exposure_scale=log_uniform(*ranges.exposure_scale),
                                  sensor_noise_scale=log_uniform(*ranges.sensor_noise_scale),
                                  lens_blur_sigma_px=float(rng.uniform(*ranges.lens_blur_sigma_px)))


def film(rgb: np.ndarray, alpha: np.ndarray, backdrop: float, blur_sigma_px: float, shot_noise_gain: float,
         read_noise: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A noise-free render [H, W, 3] with alpha [H, W] as the training studio's camera records it.

    ``backdrop`` is the backdrop's linear radiance in this frame, composited behind the head;
    then the lens blurs image and alpha alike, and the sensor adds shot noise (variance
    ``shot_noise_gain`` per unit of signal) and read noise (sigma ``read_noise``), clipped at 0.
    """
    image = rgb + np.float32(backdrop) * (1.0 - alpha)[..., None]
    if blur_sigma_px > 0:
        image = gaussian_filter(image, (blur_sigma_px, blur_sigma_px, 0))
        alpha = gaussian_filter(alpha, blur_sigma_px)
    image = gaussian_sensor_noise(image, shot_noise_gain, read_noise, rng)
    return image.astype(np.float32), np.clip(alpha, 0.0, 1.0).astype(np.float32)


__all__ = ["IdentityConditions", "TrainingConditions", "film"]
