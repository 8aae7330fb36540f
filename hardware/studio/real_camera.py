"""A real camera filming the studio: the clean renders through ``hardware.studio.camera_effects``.

Order is the light's: the scene moves during the exposure (motion blur), the lens blurs
(defocus and its residual blur) and dims the corners (vignetting), the sensor counts photons
(shot and read noise, DN, saturation). The true matte goes through the same motion and
lens blur (a blurred edge covers its pixels partially), not through the sensor.
"""

from __future__ import annotations

import numpy as np

from hardware.studio.camera_effects import CameraEffects
from hardware.studio.optics import defocus_sigma_px, gaussian_blur, motion_blur, vignetting_gain
from hardware.studio.performance import FrameState
from hardware.studio.sensor import expose
from scene.camera import Camera


def head_travel_px(camera: Camera, vertices_head: np.ndarray, frame: FrameState, other_frame: FrameState,
                   exposure_s: float) -> np.ndarray:
    """How far (dx, dy) pixels the head's visible side moves in ``camera`` over the exposure at ``frame``.

    The velocity is the finite difference to ``other_frame`` (a neighbouring frame, before or after).

    The head's vertices ``vertices_head`` [V, 3] are posed rigidly at both frames (the expression's
    own motion is local and left out: one smear for the whole image would misplace it); the
    mean displacement of the half nearer the camera, scaled from the frame interval to the
    exposure, is the travel.
    """
    dt = float(other_frame.time_s - frame.time_s)
    if exposure_s <= 0 or dt == 0:
        return np.zeros(2)
    now = frame.world_from_head.apply(np.asarray(vertices_head, np.float64))
    later = other_frame.world_from_head.apply(np.asarray(vertices_head, np.float64))
    uv_now, depth = camera.project(now)
    uv_later, _ = camera.project(later)
    front = depth <= np.median(depth)
    return (uv_later[front] - uv_now[front]).mean(axis=0) * (exposure_s / dt)


def lens_sigma_px(camera: Camera, effects: CameraEffects, image_scale: float, depth_m: float, focus_m: float,
                  extra_sigma_px: float = 0.0) -> float:
    """The one Gaussian sigma (pixels of ``camera``) of the lens at ``depth_m``: defocus, residual and extra blurs
    added in quadrature (``image_scale`` = the camera's resolution over the native one)."""
    defocus = defocus_sigma_px(camera, effects.lens, depth_m, focus_m)
    residual = effects.lens.residual_blur_px * image_scale
    return float(np.sqrt(defocus ** 2 + residual ** 2 + extra_sigma_px ** 2))


def film_performance_image(rgb: np.ndarray, alpha: np.ndarray, camera: Camera, effects: CameraEffects,
                           image_scale: float, head_depth_m: float, focus_m: float, travel_px: np.ndarray,
                           rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A performance image as the real camera records it: (rgb [H, W, 3], alpha [H, W]) float32.

    Args:
        rgb, alpha: the clean render (no sensor noise) and its coverage.
        image_scale: the camera's resolution over the sensor's native one (scales the residual blur).
        head_depth_m, focus_m: depth of the head's centre and of the focus plane along the optical axis.
        travel_px: the head's image motion over the exposure (``head_travel_px``).
    """
    sigma = lens_sigma_px(camera, effects, image_scale, head_depth_m, focus_m)
    both = np.concatenate([np.asarray(rgb, np.float64), np.asarray(alpha, np.float64)[..., None]], axis=-1)
    both = gaussian_blur(motion_blur(both, travel_px), sigma)
    radiance = both[..., :3] * vignetting_gain(camera, effects.lens.vignetting_cos_power)[..., None]
    recorded = expose(radiance, effects.sensor, rng)
    return recorded.astype(np.float32), np.clip(both[..., 3], 0.0, 1.0).astype(np.float32)


def film_board_image(clean: np.ndarray, camera: Camera, effects: CameraEffects, image_scale: float,
                     board_depth_m: float, focus_m: float, rng: np.random.Generator) -> np.ndarray:
    """A ChArUco image [H, W, 3] float32 as the real camera records the clean grey radiance ``clean`` [H, W].

    The lens model stands in for the ideal take's ``CalibrationTakeParams.blur_px`` (which is then
    not applied); the board is held still for each image: no motion blur.
    """
    sigma = lens_sigma_px(camera, effects, image_scale, board_depth_m, focus_m)
    radiance = gaussian_blur(np.asarray(clean, np.float64), sigma) * vignetting_gain(
        camera, effects.lens.vignetting_cos_power)
    grey = expose(radiance, effects.sensor, rng)
    return np.repeat(grey[..., None], 3, axis=-1).astype(np.float32)
