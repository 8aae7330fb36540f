"""Capture with the virtual studio: the controller drives the bars, the cameras film.

Per trigger pulse the emulated LED controller (``hardware.led``) says which light was on;
the studio renders that light for every camera. Frames listed in ``drop_frames`` are lost
by the cameras (no image arrives), as a real rig drops frames; the received images are
written in arrival order and labelled afterwards from the controller log and their
brightness, exactly as a real capture is.

Every pulse is one per-item cache entry (``pipeline.itemcache``): ``render_task`` returns the
encoded files (EXR and true-matte PNG bytes, exactly what is written) and ``pulse_key``
digests all they depend on (rig, subject, render settings, the cameras that receive the
pulse, the subject's state at that frame, the light). A longer take or more frames therefore
renders only the new pulses; the others are copied from the cache byte for byte.

The calibration takes are cached the same way, one entry per camera and take
(``hardware.studio.calibration_takes.render_take_item``, keyed by ``calibration_item_key``):
a capture rerun with more frames renders no calibration image again.
"""

from __future__ import annotations

import os
import tempfile
import time
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from hardware.studio import FrameState, RenderSettings, VirtualStudio, make_subject
from hardware.studio.camera_effects import CameraEffects
from hardware.studio.optics import focus_distance_m
from hardware.studio.real_camera import film_performance_image, head_travel_px
from pipeline.itemcache import content_key
from scene.camera import Camera
from scene.colour import luminance
from scene.image_io import write_exr, write_png16
from scene.rig import RigConfig


_STUDIO_CACHE: dict[tuple, VirtualStudio] = {}


@dataclass(frozen=True)
class RenderTask:
    """One trigger pulse to film with the cameras that receive it (picklable, for the executor)."""

    rig: RigConfig
    subject_name: str
    identity_seed: int
    texture_size: int
    settings: RenderSettings
    cameras: tuple[Camera, ...]  # the cameras that receive this pulse (a lost image is not rendered)
    frame: FrameState
    light: str | int | None  # what the bars showed: "F", a bar id, None = dark
    half: bool
    # realism "real": the camera model, a neighbouring frame (the head's motion over the exposure), the
    # cameras' resolution over the native one and the capture volume's centre (the focus); None = ideal.
    effects: CameraEffects | None = None
    motion_frame: FrameState | None = None
    image_scale: float = 1.0
    volume_center_m: tuple[float, float, float] = (0.0, 0.0, 0.0)


def pulse_key(task: RenderTask) -> str:
    """Content digest of everything a pulse's images depend on (the renderer's code aside)."""
    frame = task.frame
    real = {} if task.effects is None else {"real": {  # absent when ideal: ideal pulses keep their keys
        "effects": task.effects.model_dump(mode="json"), "image_scale": task.image_scale,
        "volume_center_m": list(task.volume_center_m),
        "motion_frame": None if task.motion_frame is None else _frame_json(task.motion_frame)}}
    return content_key({
        "rig": task.rig.model_dump(mode="json"),
        "subject": [task.subject_name, task.identity_seed, task.texture_size],
        "settings": asdict(task.settings),
        "cameras": [cam.to_dict() for cam in task.cameras],
        "frame": _frame_json(frame),
        "light": task.light,
        "half": task.half,
        **real,
    })


def _frame_json(frame: FrameState) -> dict:
    return {"index": frame.index, "take": frame.take, "time_s": frame.time_s,
            "expression_weights": np.asarray(frame.expression_weights).tolist(),
            "world_from_head_R": np.asarray(frame.world_from_head.R).tolist(),
            "world_from_head_t": np.asarray(frame.world_from_head.t).tolist()}


def calibration_item_key(item) -> str:
    """Content digest of a calibration take item (``BoardTakeItem`` / ``MirrorTakeItem``): what its files depend on.

    The board item counts the camera, its noise seed, the board print, every pose and the board's
    render settings; the mirror item the camera (and its native one for the windows), the balls,
    the bars, the mirror's render settings and the board noise drawn before it (see
    ``hardware.studio.calibration_takes``).
    """
    return content_key(item.kind, item.dependencies())


def _studio(task: RenderTask) -> VirtualStudio:
    key = (task.subject_name, task.identity_seed, task.texture_size, task.settings, task.rig.model_dump_json())
    if key not in _STUDIO_CACHE:
        _STUDIO_CACHE.clear()
        subject = make_subject(task.subject_name, task.identity_seed, texture_size=task.texture_size)
        _STUDIO_CACHE[key] = VirtualStudio(task.rig, subject, task.settings)
    return _STUDIO_CACHE[key]


def _encoded(write, suffix: str, *args) -> np.ndarray:
    """The bytes ``write(path, *args)`` puts in a file, as a uint8 array (so cached files are byte-exact)."""
    handle, name = tempfile.mkstemp(suffix=suffix)
    os.close(handle)
    try:
        write(name, *args)
        return np.frombuffer(Path(name).read_bytes(), np.uint8)
    finally:
        os.unlink(name)


def render_task(task: RenderTask) -> dict:
    """Render one pulse for every camera of the task; returns the files to write.

    Returns ``{"index", "cameras": [C'] names, "exr": [C'] EXR file bytes (uint8), "matte_png":
    [C'] true-matte PNG bytes, "brightness": [C'] mean luminance, "rays", "images", "seconds"}``.
    """
    start = time.perf_counter()
    studio = _studio(task)
    lit = [] if task.light is None else task.light
    rays = 0
    exr, mattes, brightness = [], [], []
    for cam in task.cameras:
        result = studio.render(task.frame, cam, lit, noise=task.effects is None)
        rays += result.rays
        rgb, alpha = result.rgb, result.alpha
        if task.effects is not None:
            rgb, alpha = _film(task, studio, cam, rgb, alpha)
        exr.append(_encoded(write_exr, ".exr", rgb, task.half))
        mattes.append(_encoded(write_png16, ".png", alpha))
        brightness.append(float(luminance(rgb).mean()))
    return {"index": task.frame.index, "cameras": [cam.name for cam in task.cameras], "exr": exr,
            "matte_png": mattes, "brightness": brightness, "rays": rays, "images": len(task.cameras),
            "seconds": time.perf_counter() - start}


def _film(task: RenderTask, studio: VirtualStudio, cam: Camera, rgb: np.ndarray, alpha: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray]:
    """The clean render of ``cam`` as the real camera records it (``task.effects``).

    The sensor noise is seeded like the ideal model's, by (render seed, frame, camera), with its own stream.
    """
    effects, frame = task.effects, task.frame
    travel = np.zeros(2)
    if task.motion_frame is not None:
        travel = head_travel_px(cam, studio.geometry(frame).vertices_head, frame, task.motion_frame,
                                effects.motion.exposure_s)
    head_depth = float(cam.cam_from_world.apply(np.asarray(frame.world_from_head.t, float)[None])[0, 2])
    focus = focus_distance_m(cam, effects.lens, np.asarray(task.volume_center_m, float))
    rng = np.random.default_rng([task.settings.seed, frame.index, zlib.crc32(cam.name.encode()), 98])
    return film_performance_image(rgb, alpha, cam, effects, task.image_scale, head_depth, focus, travel, rng)


def place_pulse(result: dict, arrivals: dict[str, tuple[int, ...]], received_dir: Path, matte_dir: Path,
                camera_names: list[str]) -> dict:
    """Write a rendered pulse: ``<received_dir>/<cam>/<k:06d>.exr`` per arrival, true mattes.

    A camera that delivers the frame twice (a repeat) gets a hard link under the second
    arrival index. Returns the pulse's summary ``{"index", "brightness": [C] (nan when lost),
    "rays", "images", "seconds"}``.
    """
    index = int(result["index"])
    bright_of = dict(zip(result["cameras"], result["brightness"]))
    for name, exr, png in zip(result["cameras"], result["exr"], result["matte_png"]):
        cam_dir = received_dir / name
        cam_dir.mkdir(parents=True, exist_ok=True)
        first = cam_dir / f"{arrivals[name][0]:06d}.exr"
        first.write_bytes(np.asarray(exr, np.uint8).tobytes())
        for k in arrivals[name][1:]:
            os.link(first, cam_dir / f"{k:06d}.exr")
        (matte_dir / name).mkdir(parents=True, exist_ok=True)
        (matte_dir / name / f"{index:06d}.png").write_bytes(np.asarray(png, np.uint8).tobytes())
    return {"index": index, "brightness": [float(bright_of.get(name, float("nan"))) for name in camera_names],
            "rays": int(result["rays"]), "images": int(result["images"]), "seconds": float(result["seconds"])}


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


