"""Capture with the virtual studio: the controller drives the bars, the cameras film.

Per trigger pulse the emulated LED controller (``hardware.led``) says which light was on;
the studio renders that light for every camera. Frames listed in ``drop_frames`` are lost
by the cameras (no image arrives), as a real rig drops frames; the received images are
written in arrival order and labelled afterwards from the controller log and their
brightness, exactly as a real capture is.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hardware.studio import FrameState, RenderSettings, VirtualStudio, make_subject
from scene.camera import Camera
from scene.colour import luminance
from scene.image_io import write_exr, write_png16
from scene.rig import RigConfig

_STUDIO_CACHE: dict[tuple, VirtualStudio] = {}


@dataclass(frozen=True)
class RenderTask:
    """One trigger pulse to film with every camera (picklable, for ``ctx.executor.map``)."""

    rig: RigConfig
    subject_name: str
    identity_seed: int
    texture_size: int
    settings: RenderSettings
    cameras: tuple[Camera, ...]
    frame: FrameState
    light: str | int | None  # what the bars showed: "F", a bar id, None = dark
    received: tuple[tuple[int, ...], ...]  # per camera: arrival indices of this frame (empty = lost)
    received_dir: Path  # images go to <received_dir>/<cam>/<k:06d>.exr
    matte_dir: Path  # true mattes go to <matte_dir>/<cam>/<index:06d>.png
    half: bool


def _studio(task: RenderTask) -> VirtualStudio:
    key = (task.subject_name, task.identity_seed, task.texture_size, task.settings, task.rig.model_dump_json())
    if key not in _STUDIO_CACHE:
        _STUDIO_CACHE.clear()
        subject = make_subject(task.subject_name, task.identity_seed, texture_size=task.texture_size)
        _STUDIO_CACHE[key] = VirtualStudio(task.rig, subject, task.settings)
    return _STUDIO_CACHE[key]


def render_task(task: RenderTask) -> dict:
    """Render one pulse for every camera that receives it; write its EXRs and true mattes.

    A camera that delivers the frame twice (a repeat) gets a hard link under the second
    arrival index. Returns ``{"index", "brightness": [C] mean luminance per camera (nan when
    lost), "rays", "images", "seconds"}``.
    """
    start = time.perf_counter()
    studio = _studio(task)
    rays = 0
    images = 0
    brightness = []
    for cam, arrivals in zip(task.cameras, task.received):
        if not arrivals:
            brightness.append(float("nan"))
            continue
        lit = [] if task.light is None else task.light
        result = studio.render(task.frame, cam, lit)
        rays += result.rays
        images += 1
        cam_dir = task.received_dir / cam.name
        cam_dir.mkdir(parents=True, exist_ok=True)
        first = cam_dir / f"{arrivals[0]:06d}.exr"
        write_exr(first, result.rgb, half=task.half)
        for k in arrivals[1:]:
            os.link(first, cam_dir / f"{k:06d}.exr")
        matte_dir = task.matte_dir / cam.name
        matte_dir.mkdir(parents=True, exist_ok=True)
        write_png16(matte_dir / f"{task.frame.index:06d}.png", result.alpha)
        brightness.append(float(luminance(result.rgb).mean()))
    return {"index": task.frame.index, "brightness": brightness, "rays": rays, "images": images,
            "seconds": time.perf_counter() - start}


def frame_state_arrays(frames: list[FrameState]) -> dict[str, np.ndarray]:
    """Ground-truth arrays of a performance (``frames.npz`` keys)."""
    return {
        "index": np.array([f.index for f in frames], np.int64),
        "time_s": np.array([f.time_s for f in frames], np.float64),
        "take": np.array([f.take for f in frames]),
        "world_from_head_R": np.stack([f.world_from_head.R for f in frames]) if frames else np.zeros((0, 3, 3)),
        "world_from_head_t": np.stack([f.world_from_head.t for f in frames]) if frames else np.zeros((0, 3)),
        "weights": np.stack([f.expression_weights for f in frames]).astype(np.float32) if frames else np.zeros((0, 57)),
    }


