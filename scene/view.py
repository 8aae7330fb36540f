"""A render's default camera: a pinhole at a distance in front of the head, looking at it.

Head space (+y up, +z out of the face, metres), the frame relight and evaluate render in:
the cameras ``ViewSpec`` makes are posed in the head frame (``cam_from_head``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from scene.camera import Camera, look_at


@dataclass(frozen=True)
class ViewSpec:
    """The default camera: ``distance_m`` in front of the head (+z), ``fov_deg`` horizontal."""

    width_px: int = 96
    height_px: int = 128
    distance_m: float = 0.9
    fov_deg: float = 24.0
    target_head: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def focal_px(self) -> float:
        return 0.5 * self.width_px / math.tan(math.radians(self.fov_deg) / 2)

    def camera(self, eye: np.ndarray, focal_px: float | None = None, name: str = "relight") -> Camera:
        f = self.focal_px() if focal_px is None else focal_px
        cam = Camera(name, self.width_px, self.height_px, f, f, self.width_px / 2 - 0.5, self.height_px / 2 - 0.5)
        return cam.with_pose(look_at(np.asarray(eye, float), np.asarray(self.target_head, float)), "head")

    def front_eye(self) -> np.ndarray:
        return np.asarray(self.target_head, float) + np.array([0.0, 0.0, self.distance_m])


__all__ = ["ViewSpec"]
