"""Relight stage: renders of the trained head under environment maps, point lights, new views and expressions.

Inputs: ``train`` (``models/ours``, loaded with ``avatar.io.load_trained``), ``track``
(``meshes.npz``: the tracked head-space meshes; the first is the default expression) and
``capture`` (``scans/scans.npz``: the actor rig that drives novel expressions).

Output (every sequence in its own folder)::

    <sequence>/frames/<i:06d>.exr     linear RGBA (float16), head at the origin, black backdrop
    <sequence>/previews/<i:06d>.png   sRGB preview (exposure fixed from the first frame)
    <sequence>/<sequence>.mp4         the previews as a video
    renders.json                      per sequence and frame: camera, lights, mesh index, map
    meshes.npz                        the driving meshes used ("default": [1, V, 3], "expressions")
    metrics.json                      envmap_seconds_per_frame, naive_envmap_seconds_per_frame, ...

Environment maps render with the voxel-space light sum (one raymarch per frame); the naive
render-each-light path is timed on ``naive_timing_frames`` frames and checked to agree; on those
frames the fast path is timed too, in the same process one after the other, and that is
``envmap_seconds_per_frame`` (the workers' own timings, which overlap, are
``envmap_worker_seconds_per_frame``).

Frames fan out through ``ctx.executor`` (GPU items on CUDA) and are cached per frame in the
stage's ``cache_dir`` (key: checkpoint digest, driving mesh, camera, lights, settings), so a
rerun renders only frames it has not rendered before (metrics ``frames_reused``,
``frames_computed``); seconds per frame are those measured when each frame was rendered.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from pydantic import Field

from avatar.render import PointLights, RenderMethod, decode, render
from pipeline.devices import DeviceChoice, resolve_device
from pipeline.errors import InputError
from pipeline.hashing import hash_path
from pipeline.itemcache import stage_item_cache
from pipeline.stage import Stage, StageContext, StageParams
from scene.envmap import AdaptiveParams, BackMask, EnvMapError, EnvMapWarning, read_envmap
from stages.capture.output import CaptureOutput
from stages.relight import sequences as seq
from stages.relight.output import RelightOutput
from stages.relight.outputs import SequenceWriter
from stages.relight.render import FrameItem, frame_key, render_frame
from stages.track.output import TrackOutput
from stages.train.output import TrainOutput


ASSETS = Path(__file__).resolve().parents[2] / "assets" / "envmaps"
DEFAULT_ENVMAPS = ("blender-cc0/courtyard.exr", "blender-cc0/studio.exr", "blender-cc0/sunrise.exr")


class RelightParams(StageParams):
    """What to render and how."""

    envmaps: tuple[str, ...] = Field(DEFAULT_ENVMAPS, description="Lat-long EXR maps, paths relative to assets/envmaps or absolute.")
    envmap_frames: int = Field(4, ge=0, description="Frames per environment map sequence.")
    rotate_deg_per_frame: float = Field(30.0, description="Rotation of the map about +y per frame, degrees.")
    light_method: Literal["uniform", "adaptive"] = Field(
        "uniform", description="'uniform' (the paper's ~256 directions) or 'adaptive' (importance sampled; see adaptive).")
    directions: int = Field(256, ge=1, description="Uniform directions before masking and dropping.")
    light_centroid: bool = Field(False, description="Uniform: place each light at its cell's energy centroid (a sun exactly where it is) instead of the paper's cell centre.")
    drop_fraction: float = Field(0.1, ge=0.0, lt=1.0, description="Fraction of the dimmest directions dropped (paper: 0.1).")
    back_mask: BackMask = Field(default_factory=BackMask,
                                description="Light from behind the head (never seen in training): the dropped cone "
                                "and the attenuation of the rest of the back hemisphere; see scene.envmap.BackMask.")
    adaptive: AdaptiveParams = Field(default_factory=AdaptiveParams,
                                     description="Adaptive light selection (light_method 'adaptive'): tolerance and "
                                     "bounds; see scene.envmap.AdaptiveParams.")
    light_distance_m: float = Field(50.0, gt=1.0, description="Distance at which distant (envmap) lights are placed as point lights.")
    envmap_scale: float = Field(1.0, gt=0.0, description="Multiplier of envmap light intensities (exposure of the renders).")
    orbit_radius_m: float = Field(3.0, ge=0.0, description="Point light orbiting the head at this radius (0 = no orbit).")
    orbit_frames: int = Field(8, ge=0, description="Frames of the point-light orbit.")
    falloff_reference_m: float = Field(1.0, gt=0.0, description="Distance at which the network's unit light holds (the rig's bars); point lights fall off as 1/r^2 from it.")
    point_lights: tuple[tuple[float, float, float], ...] = Field((), description="Extra fixed point lights, head space metres, one frame each.")
    camera_eyes: tuple[tuple[float, float, float], ...] = Field((), description="Extra camera positions, head space metres, each a frame looking at the head (key light).")
    turntable_frames: int = Field(6, ge=0, description="Frames of the camera turntable (0 = none).")
    dolly_zoom_frames: int = Field(6, ge=0, description="Frames of the dolly zoom (0 = none).")
    expressions_csv: str = Field("", description="ARKit-named blendshape weight CSV to drive the head with ('' = none).")
    expressions_obj_dir: str = Field("", description="Folder of OBJ meshes (tracked topology) to drive the head with.")
    width_px: int = Field(96, ge=8, description="Render width in pixels.")
    height_px: int = Field(128, ge=8, description="Render height in pixels.")
    distance_m: float = Field(0.9, gt=0.05, description="Camera distance from the head for the default view.")
    fov_deg: float = Field(24.0, gt=1.0, lt=170.0, description="Horizontal field of view of the default view, degrees.")
    fps: float = Field(24.0, gt=0.0, description="Frame rate of the MP4s.")
    light_batch: int = Field(16, ge=1, description="Lights decoded per batch in the voxel-space sum.")
    steps_per_ray: int = Field(0, ge=0, description="Raymarch steps per ray (0 = the model's own setting).")
    naive_timing_frames: int = Field(1, ge=0, description="Envmap frames (the first ones, over all maps) timed in this process with the fast and the naive path (timing and agreement check); 0 = report the workers' timings.")
    device: DeviceChoice = Field("auto", description="'auto' (CUDA if present), 'cpu' or 'cuda'.")


def resolve_envmap(name: str) -> Path:
    """A map path as given, or relative to the shipped ``assets/envmaps``."""
    p = Path(name)
    return p if p.is_absolute() or p.exists() else ASSETS / name


def _external(params: RelightParams) -> list[Path]:
    files = [resolve_envmap(m) for m in params.envmaps]
    files += [Path(p) for p in (params.expressions_csv, params.expressions_obj_dir) if p]
    return files


def load_inputs(ctx_inputs: dict[str, Path], params: RelightParams, device: str):
    """The trained model and its metadata, the default (first tracked) mesh and the driving meshes of novel expressions."""
    from avatar.io import load_trained

    model, meta = TrainOutput(ctx_inputs["train"]).model(lambda folder: load_trained(folder, device))
    track = TrackOutput(ctx_inputs["track"])
    vertices = track.meshes(keys=("vertices",))["vertices"]
    if len(vertices) == 0:
        raise track.malformed(track.meshes_path, "no tracked meshes")
    default_mesh = np.asarray(vertices[0], np.float32)
    expressions = None
    if params.expressions_csv or params.expressions_obj_dir:
        expressions = _expression_meshes(ctx_inputs, params, default_mesh.shape[0])
    return model, meta, default_mesh, expressions


def _expression_meshes(ctx_inputs: dict[str, Path], params: RelightParams, num_vertices: int) -> np.ndarray:
    from scene.face_rig import load_face_rig
    from stages.relight.expressions import (load_actor_rig, meshes_from_weights, read_obj_sequence,
                                            read_weights_csv)

    try:
        if params.expressions_obj_dir:
            return read_obj_sequence(Path(params.expressions_obj_dir), num_vertices)
        names, neutral, offsets = load_actor_rig(CaptureOutput(ctx_inputs["capture"]))
        rig = load_face_rig()
        weights = read_weights_csv(Path(params.expressions_csv), rig.expression_names)
        return meshes_from_weights(weights, rig.expression_deltas_m, neutral, offsets)
    except ValueError as err:
        raise InputError(str(err)) from err


@dataclass(frozen=True)
class FrameSource:
    """What every frame item of this run shares: the checkpoint and render settings (see ``render.FrameItem``)."""

    model_dir: Path
    model_digest: str
    meshes_path: Path  # the stage's own meshes.npz ("default", "expressions")
    steps: int
    light_batch: int
    image_scale: float
    device: str

    def items(self, frames: list[seq.FrameSpec], meshes: np.ndarray, mesh_array: str) -> list[FrameItem]:
        """One picklable item per frame; the driving mesh is named by its array, row and content digest."""
        from pipeline.hashing import hash_bytes

        digests: dict[int, str] = {}
        items = []
        for spec in frames:
            if spec.mesh_index not in digests:
                row = np.ascontiguousarray(meshes[spec.mesh_index], np.float32)
                digests[spec.mesh_index] = hash_bytes(row.tobytes())
            items.append(FrameItem(
                model_dir=str(self.model_dir), model_digest=self.model_digest, meshes_path=str(self.meshes_path),
                mesh_array=mesh_array, mesh_index=spec.mesh_index, mesh_digest=digests[spec.mesh_index],
                camera=spec.camera, light_pos=np.asarray(spec.light_pos), light_rgb=np.asarray(spec.light_rgb),
                steps=self.steps, light_batch=self.light_batch, image_scale=self.image_scale,
                device=self.device))
        return items


def _timed(render, geometry, spec: seq.FrameSpec) -> float:
    """Seconds of one ``render(geometry, spec)`` (CUDA work waited for)."""
    start = time.perf_counter()
    render(geometry, spec)
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    return time.perf_counter() - start


def render_sequence(ctx: StageContext, source: FrameSource, name: str, frames: list[seq.FrameSpec],
                    meshes: np.ndarray, mesh_array: str, manifest: dict) -> list[float]:
    """Render and write one sequence; returns seconds per frame.

    Frames fan out through ``ctx.executor`` (GPU items on CUDA) and are cached per frame in the
    stage's ``cache_dir`` (``render.frame_key``): a rerun renders only frames it has not
    rendered before. Each frame is written as soon as it (and every frame before it) exists,
    and stored in the cache by the worker that rendered it, so an error keeps every frame done.
    """
    out = RelightOutput(ctx.out)
    writer = SequenceWriter(out, name, ctx.params.fps, ctx.log)
    seconds, records = [], []
    manifest[name] = records
    cache = stage_item_cache(ctx)

    def write(i: int, result: dict) -> None:
        spec = frames[i]
        seconds.append(float(result["seconds"]))
        writer.write(i, np.asarray(result["rgb"], np.float32), np.asarray(result["alpha"], np.float32))
        records.append({"index": i, "camera": spec.camera.to_dict(), "light_pos": spec.light_pos.tolist(),
                        "light_rgb": spec.light_rgb.tolist(), "mesh_index": spec.mesh_index, **spec.info})

    try:
        cache.map(ctx.executor, render_frame, source.items(frames, meshes, mesh_array), frame_key,
                  desc=f"{name} frames", gpu=source.device.startswith("cuda"), consume=write)
    finally:
        writer.finish()
        out.write_renders(manifest)
    cache.report(ctx, f"{name} frames")
    ctx.metrics["frames_reused"] = ctx.metrics.get("frames_reused", 0) + cache.hits
    ctx.metrics["frames_computed"] = ctx.metrics.get("frames_computed", 0) + cache.misses
    return seconds


def run(ctx: StageContext) -> None:
    params: RelightParams = ctx.params
    device = resolve_device(params.device, "relight.device")
    model, meta, default_mesh, expressions = load_inputs(dict(ctx.inputs), params, device)
    steps = params.steps_per_ray or model.config.steps_per_ray
    # The network learnt normalised images; EXR outputs are in the capture's linear units.
    image_scale = float(meta.get("image_scale", 1.0))
    model_dir = TrainOutput(ctx.inputs["train"]).model_dir()
    out = RelightOutput(ctx.out)
    source = FrameSource(model_dir, hash_path(model_dir), out.meshes_path, steps, params.light_batch,
                         image_scale, device)

    def render_spec(geometry, spec: seq.FrameSpec, method: RenderMethod = "voxel_sum"):
        return render(model, geometry, spec.camera, PointLights(spec.light_pos, spec.light_rgb), steps=steps,
                      image_scale=image_scale, light_batch=params.light_batch, method=method).numpy()
    view = seq.ViewSpec(params.width_px, params.height_px, params.distance_m, params.fov_deg,
                        tuple(float(v) for v in default_mesh.mean(0)))
    mask = params.back_mask
    default = default_mesh[None]
    out.write_meshes(default, expressions if expressions is not None else np.zeros((0, *default_mesh.shape)))
    manifest: dict = {}
    metrics = ctx.metrics
    envmap_seconds, directions, naive_seconds, fast_seconds, max_diff = [], [], [], [], 0.0

    for map_name in params.envmaps:
        path = resolve_envmap(map_name)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", EnvMapWarning)
            try:
                envmap = read_envmap(path)
            except EnvMapError as err:
                raise InputError(f"relight.envmaps: {err}") from err
        for w in caught:
            ctx.log.warning("%s", w.message)
        try:
            frames = seq.envmap_sequence(envmap, params.envmap_frames, params.rotate_deg_per_frame, view,
                                         method=params.light_method, directions=params.directions,
                                         drop_fraction=params.drop_fraction,
                                         adaptive=params.adaptive, mask=mask,
                                         light_distance_m=params.light_distance_m, scale=params.envmap_scale,
                                         centroid=params.light_centroid)
        except EnvMapError as err:
            raise InputError(f"relight.envmaps: {err}") from err
        envmap_seconds += render_sequence(ctx, source, f"envmap_{envmap.name}", frames, default, "default", manifest)
        directions += [f.info["directions"] for f in frames]
        geometry = decode(model, default_mesh)
        for spec in frames[:max(0, params.naive_timing_frames - len(naive_seconds))]:
            # Both paths timed here, one after the other in this one process: the workers'
            # own timings overlap each other (and any other job), so they measure contention.
            fast_rgb, _ = render_spec(geometry, spec)  # also a warm-up
            fast_seconds.append(_timed(render_spec, geometry, spec))
            start = time.perf_counter()
            naive_rgb, _ = render_spec(geometry, spec, "per_light")
            naive_seconds.append(time.perf_counter() - start)
            max_diff = max(max_diff, float(np.abs(fast_rgb - naive_rgb).max()))

    key_pos, key_rgb = seq.key_light(view)
    if params.orbit_radius_m > 0 and params.orbit_frames > 0:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", seq.LightRangeWarning)
            frames = seq.point_light_sequence(
                seq.orbit_positions(params.orbit_radius_m, params.orbit_frames, 0.0, view.target_head), view,
                falloff_reference_m=params.falloff_reference_m, mask=mask, what="orbit")
        for w in caught:
            ctx.log.warning("%s", w.message)
        render_sequence(ctx, source, "point_orbit", frames, default, "default", manifest)
    if params.point_lights:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", seq.LightRangeWarning)
            frames = seq.point_light_sequence(np.asarray(params.point_lights, float), view,
                                              falloff_reference_m=params.falloff_reference_m, mask=mask)
        for w in caught:
            ctx.log.warning("%s", w.message)
        render_sequence(ctx, source, "point_lights", frames, default, "default", manifest)
    if params.camera_eyes:
        render_sequence(ctx, source, "views", seq.views_sequence(np.asarray(params.camera_eyes, float), view, key_pos,
                                                                key_rgb), default, "default", manifest)
    if params.turntable_frames:
        render_sequence(ctx, source, "turntable", seq.turntable_sequence(params.turntable_frames, view, key_pos,
                                                                        key_rgb), default, "default", manifest)
    if params.dolly_zoom_frames:
        render_sequence(ctx, source, "dolly_zoom", seq.dolly_zoom_sequence(params.dolly_zoom_frames, view, key_pos,
                                                                          key_rgb), default, "default", manifest)
    if expressions is not None:
        render_sequence(ctx, source, "expressions", seq.expression_sequence(expressions, view, key_pos, key_rgb),
                        expressions, "expressions", manifest)

    if envmap_seconds:
        # Single-process timing when there is one (comparable with the naive path's), else the workers'.
        metrics["envmap_seconds_per_frame"] = float(np.mean(fast_seconds or envmap_seconds))
        metrics["envmap_worker_seconds_per_frame"] = float(np.mean(envmap_seconds))
        metrics["envmap_directions"] = float(np.mean(directions))
        metrics["envmap_frames"] = len(envmap_seconds)
    if naive_seconds:
        metrics["naive_envmap_seconds_per_frame"] = float(np.mean(naive_seconds))
        metrics["envmap_fast_naive_max_abs_diff"] = max_diff
    metrics["frames_rendered"] = sum(len(v) for v in manifest.values())
    ctx.log.info("relight: %d frames; envmap %.3f s/frame (naive %.3f), %.0f directions",
                 metrics["frames_rendered"], metrics.get("envmap_seconds_per_frame", math.nan),
                 metrics.get("naive_envmap_seconds_per_frame", math.nan), metrics.get("envmap_directions", math.nan))


STAGE = Stage(
    name="relight",
    inputs=("train", "track", "capture"),
    params=RelightParams,
    run=run,
    external_inputs=_external,
    doc="Render the trained head under environment maps, point lights, new views and expressions (EXR, PNG, MP4).",
)
