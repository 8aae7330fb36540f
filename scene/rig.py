"""The capture rig: cameras and LED bars, validated from ``configs/rig.yaml``.

The YAML holds the reference (paper) resolution; ``RigConfig.cameras(scale)`` returns the
``scene.camera.Camera`` list at any preset's resolution (``scale=0.3125`` gives the tiny
preset's 240x320). Images are portrait: ``width_px x height_px = 768 x 1024`` at scale 1
(the paper's 1024x768 images, turned so that a head fills the frame).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from scene.camera import Camera, look_at
from scene.lights import LightBar

# The default rig file (declared so the code digest of every module using ``default_rig`` covers it).
CODE_FILES = ("../configs/rig.yaml",)
DEFAULT_RIG = (Path(__file__).parent / CODE_FILES[0]).resolve()


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class CameraSpec(_Frozen):
    """One camera of the rig at the reference resolution."""

    name: str = Field(description="Camera id used in folder names (cam00 ...).")
    position_m: tuple[float, float, float] = Field(description="Camera centre in world space, metres.")
    look_at_m: tuple[float, float, float] = Field(description="World point on the optical axis, metres.")
    up: tuple[float, float, float] = Field((0.0, 1.0, 0.0), description="World up direction for the camera's roll.")
    focal_px: float = Field(gt=0, description="Focal length in pixels at the reference resolution (fx = fy).")
    principal_offset_px: tuple[float, float] = Field(
        (0.0, 0.0), description="Principal point offset from the image centre, pixels at reference resolution.")
    dist: tuple[float, float, float, float, float] = Field(
        (0.0, 0.0, 0.0, 0.0, 0.0), description="OpenCV distortion (k1, k2, p1, p2, k3).")


class BarSpec(_Frozen):
    """One LED bar (a line light)."""

    id: int = Field(ge=0, description="Bar index as used by the OLAT sequence and the controller.")
    center_m: tuple[float, float, float] = Field(description="Bar centre in world space, metres.")
    axis: tuple[float, float, float] = Field(description="Direction along the bar (normalised on load).")
    length_m: float = Field(gt=0, description="Length of the emitting segment, metres.")
    intensity: float = Field(gt=0, description="Relative radiant intensity of the bar (about 1; bars differ slightly).")


class RigConfig(_Frozen):
    """The studio: cameras, LED bars and calibration targets."""

    width_px: int = Field(gt=0, description="Image width at the reference (paper) resolution, pixels.")
    height_px: int = Field(gt=0, description="Image height at the reference (paper) resolution, pixels.")
    fps: float = Field(24.0, gt=0, description="Camera frame rate, frames per second.")
    head_center_m: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="Where the subject's head stands in world space (bars aim at it), metres.")
    cameras: tuple[CameraSpec, ...] = Field(description="The cameras, in camera-id order.")
    bars: tuple[BarSpec, ...] = Field(description="The LED bars, ids 0..N-1 in order.")
    calibration: dict[str, Any] = Field(
        default_factory=dict,
        description="Calibration targets (ChArUco board, mirror spheres); read by hardware.studio.calibration_takes.")

    @field_validator("bars")
    @classmethod
    def _bar_ids_in_order(cls, bars: tuple[BarSpec, ...]) -> tuple[BarSpec, ...]:
        for i, bar in enumerate(bars):
            if bar.id != i:
                raise ValueError(f"bars[{i}] has id {bar.id}; bar ids must be 0..N-1 in order")
        return bars

    @field_validator("cameras")
    @classmethod
    def _unique_names(cls, cams: tuple[CameraSpec, ...]) -> tuple[CameraSpec, ...]:
        names = [c.name for c in cams]
        if len(set(names)) != len(names):
            raise ValueError(f"camera names must be unique, got {names}")
        return cams

    # ---- derived objects -------------------------------------------------------------
    def cameras_at(self, scale: float = 1.0) -> list[Camera]:
        """The rig's cameras as ``Camera`` objects at ``scale`` times the reference resolution."""
        out = []
        for spec in self.cameras:
            cam = Camera(
                name=spec.name, width=self.width_px, height=self.height_px,
                fx=spec.focal_px, fy=spec.focal_px,
                cx=(self.width_px - 1) / 2 + spec.principal_offset_px[0],
                cy=(self.height_px - 1) / 2 + spec.principal_offset_px[1],
                dist=tuple(spec.dist),  # type: ignore[arg-type]
                pose=look_at(np.array(spec.position_m), np.array(spec.look_at_m), np.array(spec.up)),
            )
            out.append(cam if scale == 1.0 else cam.scaled(scale))
        return out

    def light_bars(self) -> list[LightBar]:
        """The rig's LED bars; each emits towards ``head_center_m``."""
        head = np.asarray(self.head_center_m, dtype=np.float64)
        return [LightBar(b.id, np.asarray(b.center_m, float), np.asarray(b.axis, float), b.length_m,
                         b.intensity, head - np.asarray(b.center_m, float)) for b in self.bars]

    @property
    def camera_names(self) -> list[str]:
        return [c.name for c in self.cameras]


def load_rig(path: str | Path = DEFAULT_RIG) -> RigConfig:
    """Read and validate a rig file; ``ValueError`` naming the file and key on a bad value."""
    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        raise ValueError(f"{path}: cannot read rig file ({err})") from err
    try:
        return RigConfig.model_validate(raw)
    except ValidationError as err:
        first = err.errors()[0]
        key = ".".join(str(p) for p in first["loc"])
        raise ValueError(f"{path}: bad rig value at '{key}': {first['msg']} "
                         f"({len(err.errors())} error(s) in total)") from err


@lru_cache(maxsize=4)
def default_rig() -> RigConfig:
    """The studio rig of ``configs/rig.yaml`` (cached)."""
    return load_rig(DEFAULT_RIG)
