"""The lens and the exposure of ``realism: real``: vignetting, thin-lens defocus, motion blur.

All are per-image approximations: the defocus is one Gaussian per image, its sigma from the
depth of what the image is of (the board's centre, the head's centre) -- the board is small
against its distance, so its depth varies little across it; the motion blur smears the
whole image along one projected velocity (the head moves rigidly and slowly, so sub-frame
re-renders, ~5x the render cost, would buy little).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter, shift

from hardware.studio.camera_effects import LensModel
from scene.camera import Camera


_VIGNETTING_CACHE: dict[tuple, np.ndarray] = {}


def vignetting_gain(camera: Camera, cos_power: float) -> np.ndarray:
    """Relative illumination [H, W] of every pixel: cos^p of its ray's angle to the optical axis (1 on axis).

    The angle depends on the intrinsics alone, so the map is cached per intrinsics (a board take
    reuses it for every pose).
    """
    if cos_power == 0:
        return np.ones((camera.height, camera.width))
    key = (camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy, tuple(camera.dist), cos_power)
    if key not in _VIGNETTING_CACHE:
        _, dirs = camera.image_rays()  # [H, W, 3] unit, world frame (lens distortion included)
        cos_field = np.clip(dirs @ camera.forward_world, 0.0, 1.0)
        if len(_VIGNETTING_CACHE) > 32:
            _VIGNETTING_CACHE.pop(next(iter(_VIGNETTING_CACHE)))
        _VIGNETTING_CACHE[key] = cos_field ** cos_power
    return _VIGNETTING_CACHE[key]


def focus_distance_m(camera: Camera, lens: LensModel, volume_center_world: np.ndarray) -> float:
    """Where ``camera`` is focused: ``lens.focus_distance_m``, else the depth of the capture volume's centre."""
    if lens.focus_distance_m is not None:
        return float(lens.focus_distance_m)
    return float(camera.cam_from_world.apply(np.asarray(volume_center_world, float)[None])[0, 2])


def defocus_sigma_px(camera: Camera, lens: LensModel, depth_m: float, focus_m: float) -> float:
    """Gaussian sigma (pixels of ``camera``) of the thin lens's blur disc for a point at ``depth_m``.

    Circle of confusion on the sensor c = A f |s - s_f| / (s (s_f - f)) with the aperture
    A = f / N; in pixels c / pitch with pitch = f / fx (the camera's focal length in pixels
    at its current resolution). A uniform disc of diameter c has a per-axis sigma of c / 4.
    """
    f = lens.focal_length_mm * 1e-3
    s, s_f = max(float(depth_m), 2 * f), max(float(focus_m), 2 * f)
    coc_m = (f / lens.f_number) * f * abs(s - s_f) / (s * (s_f - f))
    return coc_m * camera.fx / f / 4.0


def gaussian_blur(img: np.ndarray, sigma_px: float) -> np.ndarray:
    """``img`` [H, W] or [H, W, C] blurred by a Gaussian of ``sigma_px`` over the two image axes."""
    if sigma_px <= 0:
        return img
    sigma = (sigma_px, sigma_px) + (0,) * (img.ndim - 2)
    return gaussian_filter(img, sigma, mode="nearest")


def motion_blur(img: np.ndarray, travel_px: np.ndarray, min_travel_px: float = 0.05) -> np.ndarray:
    """``img`` [H, W] or [H, W, C] averaged along the segment ``travel_px`` (dx, dy) the image moves over the exposure.

    The segment (centred on the frame's instant) is sampled every half pixel or finer, each
    copy shifted with bilinear interpolation; below ``min_travel_px`` the image is returned as is.
    """
    travel = np.asarray(travel_px, float)
    length = float(np.hypot(*travel))
    if length < min_travel_px:
        return img
    steps = max(2, int(np.ceil(2 * length)) + 1)
    out = np.zeros(img.shape, np.float64)
    for t in np.linspace(-0.5, 0.5, steps):
        offset = (t * travel[1], t * travel[0]) + (0.0,) * (img.ndim - 2)  # (rows, cols, channels)
        out += shift(img, offset, order=1, mode="nearest")
    return out / steps
