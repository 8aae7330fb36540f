"""The sensor of ``realism: real``: photons to electrons to DN and back to linear radiance.

Model (per pixel and channel, ``hardware.studio.camera_effects.SensorModel``):

    electrons = Poisson(radiance x electrons_per_linear) + Normal(0, read_noise_e)
    DN        = clip(round(electrons / gain_e_per_dn + black_level_dn), 0, 2^bits - 1)
    linear    = (DN - black_level_dn) x gain_e_per_dn / electrons_per_linear

so in linear units the variance is ``mean / electrons_per_linear + (read_noise_e /
electrons_per_linear)^2`` (plus the DN step^2 / 12), and values saturate at
``white_level_linear``. The images stay linear floats (what the pipeline reads); only their
statistics and their clipping are a real sensor's.
"""

from __future__ import annotations

import numpy as np

from hardware.studio.camera_effects import SensorModel


def expose(radiance: np.ndarray, sensor: SensorModel, rng: np.random.Generator) -> np.ndarray:
    """The linear image [...] a sensor records of the clean ``radiance`` [...] (float64)."""
    per_linear = sensor.electrons_per_linear
    mean_e = np.maximum(np.asarray(radiance, np.float64), 0.0) * per_linear
    # Photon counts are Poisson; beyond full well the pixel saturates anyway, so cap the mean there
    # (keeps the Poisson draw finite for a bright backdrop or a specular spike).
    electrons = rng.poisson(np.minimum(mean_e, 4.0 * sensor.full_well_e)).astype(np.float64)
    if sensor.read_noise_e > 0:
        electrons += rng.normal(0.0, sensor.read_noise_e, size=electrons.shape)
    dn = np.clip(np.rint(electrons / sensor.gain_e_per_dn + sensor.black_level_dn), 0, sensor.white_level_dn)
    return (dn - sensor.black_level_dn) * sensor.gain_e_per_dn / per_linear


def linear_variance(mean_linear: np.ndarray, sensor: SensorModel) -> np.ndarray:
    """The model's predicted variance of a linear pixel value of mean ``mean_linear`` (below saturation)."""
    per_linear = sensor.electrons_per_linear
    step = sensor.gain_e_per_dn / per_linear  # one DN in linear units
    return (np.asarray(mean_linear, np.float64) / per_linear + (sensor.read_noise_e / per_linear) ** 2
            + step ** 2 / 12.0)
