"""The evaluate stage's params: the sizes and thresholds of its stability sweeps."""

from __future__ import annotations

from pydantic import Field

from pipeline.stage import StageParams


class EvaluateParams(StageParams):
    """Sizes of the sweeps (defaults: a couple of CPU minutes on the tiny preset)."""

    psnr_threshold_db: float = Field(25.0, description="PSNR under which a render counts as broken (dB).")
    relative_drop_db: float = Field(0.0, ge=0.0, description="If > 0, the threshold is instead this many dB under "
                                    "the sweep's own in-distribution PSNR (orbit: the lights nearest the training "
                                    "lights; expression: scale 1), for models too small to reach the absolute one.")
    orbit_radius_m: float = Field(3.0, gt=0.2, description="Distance of the orbiting point light from the head's centre.")
    orbit_points: int = Field(24, ge=4, description="Light positions per orbit circle (24 = every 15 degrees).")
    vertical_orbit: bool = Field(True, description="Also orbit in the vertical (y-z) plane (over the head and under the chin).")
    camera_azimuths_deg: tuple[float, ...] = Field((0.0, 40.0), description="Cameras around +y looking at the head "
                                                   "(0 = front, positive = the subject's left).")
    camera_distance_m: float = Field(0.9, gt=0.1, description="Camera distance from the head's centre.")
    fov_deg: float = Field(24.0, gt=1.0, lt=170.0, description="Horizontal field of view of the cameras.")
    width_px: int = Field(48, ge=8, description="Render width in pixels.")
    height_px: int = Field(60, ge=8, description="Render height in pixels.")
    expression_scales: tuple[float, ...] = Field((0.5, 0.75, 1.0, 1.25, 1.5, 1.75, 2.0),
                                                 description="Scales of the held-out frame's blendshape weights.")
    strip_every_deg: float = Field(45.0, gt=0.0, description="Orbit angles shown in orbit_strip.png.")
    white_floor_fraction: float = Field(0.05, gt=0.0, le=1.0, description="PSNR white level floor, as a fraction "
                                        "of the sweep's brightest truth (keeps a black back-lit truth from "
                                        "blowing errors up).")
    steps_per_ray: int = Field(0, ge=0, description="Raymarch steps per ray (0 = the model's own).")
