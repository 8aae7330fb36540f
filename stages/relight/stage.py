"""Relight stage: renders of the trained head under environment maps, point lights, new views and expressions.

Inputs: ``train`` (``models/ours``, loaded with ``avatar.io.load_trained``), ``track``
(``meshes.npz``: the tracked head-space meshes; the first is the default expression) and
``capture`` (``scans/scans.npz``: the actor rig that drives novel expressions).

Output (every sequence in its own folder)::

    <sequence>/frames/<i:06d>.exr     linear RGBA (float16), head at the origin, black backdrop
    <sequence>/previews/<i:06d>.png   sRGB preview (exposure fixed from the first frame)
    <sequence>/<sequence>.mp4         the previews as a video
    renders.json                      per sequence and frame: camera, lights, mesh index, map, path
    paths.json                        per sequence: the path its frames took ("bake" or "voxel_sum") and why
    meshes.npz                        the driving meshes used ("default": [1, V, 3], "expressions")
    metrics.json                      envmap_seconds_per_frame, naive_envmap_seconds_per_frame, bake_*, ...

Environment maps render with the voxel-space light sum (decode every light, one raymarch per
frame) or from a light-transfer bake of the view and expression (``avatar.bake``: a weighted
sum of basis images per frame, no network). ``envmap_path`` "auto" bakes a (view, expression)
once ``bake_min_frames`` envmap frames share it (one bake serves every map and rotation; it
costs about as much as a few sum frames), which needs the paper's uniform cell-centre lights;
point lights, turntables, dolly zooms and new views or expressions stay on the network.
``paths.json`` and each frame's ``path`` in ``renders.json`` say which path was taken.

Timings measured in this process, one after the other (the workers' own timings overlap each
other and any other job): the naive render-each-light path against the voxel-space sum on
``naive_timing_frames`` frames (checked to agree), and, with ``bake_check``, one bake
(``bake_seconds``), then its frames (``bake_frame_seconds``: projecting the turned map onto the
baked directions plus the weighted sum) against the voxel-space sum of the same frames on
``bake_check_envmaps`` at ``bake_check_rotations_deg`` (``bake_psnr_vs_sum_db``, the mean;
``bake_speedup_vs_sum``). ``envmap_seconds_per_frame`` is the mean of this process's
voxel-space-sum timings (the workers', ``envmap_worker_seconds_per_frame``, without any).

Frames fan out through ``ctx.executor`` (GPU items on CUDA) and are cached per frame in the
stage's ``cache_dir`` (key: checkpoint digest, driving mesh, camera, lights, settings), so a
rerun renders only frames it has not rendered before (metrics ``frames_reused``,
``frames_computed``); seconds per frame are those measured when each frame was rendered.
Bakes are kept in the same cache (``stages.relight.bake.bake_key``: checkpoint digest, driving
mesh, camera, baked directions, rank and settings, code version; ``bakes_reused``,
``bakes_computed``); frames from a bake are not cached (a weighted sum is cheaper than a read).
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

from avatar.bake import ImageBake, bake_images, psnr_db
from avatar.render import PointLights, RenderMethod, decode, render
from pipeline.devices import DeviceChoice, resolve_device
from pipeline.errors import ConfigError, InputError
from pipeline.hashing import hash_path
from pipeline.itemcache import stage_item_cache
from pipeline.stage import Stage, StageContext, StageParams
from scene.envmap import (AdaptiveParams, BackMask, EnvMapError, EnvMapWarning, RotatingProjection, fibonacci_sphere,
                          read_envmap)
from stages.capture.output import CaptureOutput
from stages.relight import sequences as seq
from stages.relight.bake import BAKE_CODE, BakeItem, bake_item, bake_key, choose_paths, render_from_bake, view_key
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
    envmap_path: Literal["auto", "bake", "sum"] = Field("auto", description="How envmap sequences render: 'auto' (from a light-transfer bake of their view and expression where one bake serves at least bake_min_frames envmap frames, else the voxel-space sum), 'bake' (always bake; needs uniform cell-centre lights) or 'sum' (never).")
    bake_rank: int = Field(32, ge=0, description="Images in the bake's basis (0 = one per direction, exact). Raise it when bake frames drift from the voxel-space sum (bake_psnr_vs_sum_db); each doubling costs about 1.3x the frame time (docs/experiments.md, section 8).")
    bake_min_frames: int = Field(4, ge=1, description="'auto': bake a view and expression once this many envmap frames (over all maps and rotations) share it; lower it when bakes are cheap against frames (a GPU), raise it for short sequences (docs/experiments.md, section 8).")
    bake_check: bool = Field(True, description="Time one bake, its frames and the voxel-space sum of the same frames side by side in this process, and compare them (metrics bake_*), on bake_check_envmaps at bake_check_rotations_deg. Off for quick renders.")
    bake_check_envmaps: tuple[str, ...] = Field((), description="Maps the bake is checked on, as envmaps; empty = the envmaps rendered (the shipped defaults unless changed).")
    bake_check_rotations_deg: tuple[float, ...] = Field((0.0, 90.0, 200.0), description="Rotations about +y at which each checked map is compared, degrees.")
    device: DeviceChoice = Field("auto", description="'auto' (CUDA if present), 'cpu' or 'cuda'.")


def resolve_envmap(name: str) -> Path:
    """A map path as given, or relative to the shipped ``assets/envmaps``."""
    p = Path(name)
    return p if p.is_absolute() or p.exists() else ASSETS / name


def _external(params: RelightParams) -> list[Path]:
    files = [resolve_envmap(m) for m in dict.fromkeys(params.envmaps + _check_maps(params))]
    files += [Path(p) for p in (params.expressions_csv, params.expressions_obj_dir) if p]
    return files


def _check_maps(params: RelightParams) -> tuple[str, ...]:
    """The maps the bake is checked on (``bake_check_envmaps``, or the envmaps rendered); none when the check is off."""
    if not params.bake_check:
        return ()
    return tuple(params.bake_check_envmaps or params.envmaps)


def _read_map(name: str, log):
    """An envmap by its param name; repairs are logged, a bad file is an InputError naming it."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", EnvMapWarning)
        try:
            envmap = read_envmap(resolve_envmap(name))
        except EnvMapError as err:
            raise InputError(f"relight.envmaps: {err}") from err
    for w in caught:
        log.warning("%s", w.message)
    return envmap


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
        digests: dict[int, str] = {}
        items = []
        for spec in frames:
            if spec.mesh_index not in digests:
                digests[spec.mesh_index] = _mesh_digest(meshes, spec.mesh_index)
            items.append(FrameItem(
                model_dir=str(self.model_dir), model_digest=self.model_digest, meshes_path=str(self.meshes_path),
                mesh_array=mesh_array, mesh_index=spec.mesh_index, mesh_digest=digests[spec.mesh_index],
                camera=spec.camera, light_pos=np.asarray(spec.light_pos), light_rgb=np.asarray(spec.light_rgb),
                steps=self.steps, light_batch=self.light_batch, image_scale=self.image_scale,
                device=self.device))
        return items

    def bake(self, spec: seq.FrameSpec, meshes: np.ndarray, mesh_array: str, params: "RelightParams",
             centre_head) -> BakeItem:
        """The bake item of a frame's view and expression (the uniform directions the envmap frames use)."""
        return BakeItem(
            model_dir=str(self.model_dir), model_digest=self.model_digest, meshes_path=str(self.meshes_path),
            mesh_array=mesh_array, mesh_index=spec.mesh_index, mesh_digest=_mesh_digest(meshes, spec.mesh_index),
            camera=spec.camera, directions=params.directions, distance_m=params.light_distance_m,
            centre_head=tuple(float(v) for v in centre_head), rank=params.bake_rank, steps=self.steps,
            light_batch=self.light_batch, device=self.device)


def _mesh_digest(meshes: np.ndarray, index: int) -> str:
    from pipeline.hashing import hash_bytes

    return hash_bytes(np.ascontiguousarray(meshes[index], np.float32).tobytes())


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
        seconds.append(float(result["seconds"]))
        writer.write(i, np.asarray(result["rgb"], np.float32), np.asarray(result["alpha"], np.float32))
        records.append(_record(i, frames[i], "voxel_sum"))

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


def _record(index: int, spec: seq.FrameSpec, path: str) -> dict:
    """A frame's entry in ``renders.json``: what it shows and which path rendered it."""
    return {"index": index, "camera": spec.camera.to_dict(), "light_pos": spec.light_pos.tolist(),
            "light_rgb": spec.light_rgb.tolist(), "mesh_index": spec.mesh_index, "path": path, **spec.info}


def fetch_bakes(ctx: StageContext, items: list[BakeItem]) -> list[ImageBake]:
    """The bakes of ``items``: from the stage's per-item cache, the missing ones baked through the executor."""
    cache = stage_item_cache(ctx, code=BAKE_CODE)
    results = cache.map(ctx.executor, bake_item, items, bake_key, desc="light-transfer bakes",
                        gpu=items[0].device.startswith("cuda") if items else False)
    cache.report(ctx, "light-transfer bakes")
    ctx.metrics["bakes_reused"] = ctx.metrics.get("bakes_reused", 0) + cache.hits
    ctx.metrics["bakes_computed"] = ctx.metrics.get("bakes_computed", 0) + cache.misses
    return [ImageBake.from_arrays(r) for r in results]


def render_bake_sequence(ctx: StageContext, baked: ImageBake, name: str, frames: list[seq.FrameSpec],
                         image_scale: float, manifest: dict) -> list[float]:
    """Write one envmap sequence from its view's bake (every frame a weighted sum of the basis); seconds per frame."""
    out = RelightOutput(ctx.out)
    writer = SequenceWriter(out, name, ctx.params.fps, ctx.log)
    seconds, records = [], []
    manifest[name] = records
    try:
        for i, spec in enumerate(frames):
            try:
                result = render_from_bake(baked, spec, image_scale)
            except ValueError as err:  # a light off the baked directions: a bug in choosing the path
                raise InputError(f"relight: sequence {name} frame {i}: {err}") from err
            seconds.append(result["seconds"])
            writer.write(i, result["rgb"], result["alpha"])
            records.append(_record(i, spec, "bake"))
    finally:
        writer.finish()
        out.write_renders(manifest)
    return seconds


def _bakeable(params: RelightParams) -> str | None:
    """None when envmap frames use the bake's fixed directions; else why they cannot."""
    if params.light_method != "uniform":
        return (f"light_method '{params.light_method}' picks directions per map and rotation; a bake holds fixed "
                "ones (use 'uniform')")
    if params.light_centroid:
        return "light_centroid moves each light to its cell's centroid of the map; a bake holds the cell centres"
    return None


def bake_check(ctx: StageContext, model, geometry, baked: ImageBake, camera, params: RelightParams,
               mask: BackMask, centre_head, image_scale: float, steps: int) -> dict[str, list[float]]:
    """The bake against the voxel-space sum on the same frames, timed one after the other in this process.

    For every map of ``_check_maps`` at every ``bake_check_rotations_deg``: the bake frame
    (projection of the turned map onto the baked directions, then the weighted sum) and the
    voxel-space sum of the same lights (the select_uniform lights of the turned map), their
    seconds and the bake's PSNR against the sum.
    """
    found: dict[str, list[float]] = {"bake_s": [], "sum_s": [], "psnr": [], "setup_s": []}
    warm = False
    for name in _check_maps(params):
        envmap = _read_map(name, ctx.log)
        start = time.perf_counter()
        projection = RotatingProjection(envmap, params.directions, params.drop_fraction, mask)
        found["setup_s"].append(time.perf_counter() - start)
        for deg in params.bake_check_rotations_deg:
            angle = math.radians(deg)
            start = time.perf_counter()
            rgb_bake, _ = baked.frame(params.envmap_scale * projection.weights(angle), image_scale)
            found["bake_s"].append(time.perf_counter() - start)
            lights = projection.lights(angle)
            points = PointLights(lights.positions_world(params.light_distance_m, np.asarray(centre_head)),
                                 params.envmap_scale * lights.irradiance_rgb)

            def sum_frame():
                return render(model, geometry, camera, points, steps=steps, image_scale=image_scale,
                              light_batch=params.light_batch).numpy()
            if not warm:
                sum_frame()  # one-off costs (kernel load, allocator) out of the timing
                warm = True
            start = time.perf_counter()
            rgb_sum, alpha = sum_frame()
            if torch.cuda.is_available():
                torch.cuda.synchronize()
            found["sum_s"].append(time.perf_counter() - start)
            found["psnr"].append(psnr_db(rgb_bake, rgb_sum, alpha))
            ctx.log.info("bake check %s at %.0f deg: %.1f dB against the voxel-space sum; %.2f ms against %.0f ms",
                         envmap.name, deg, found["psnr"][-1], 1e3 * found["bake_s"][-1], 1e3 * found["sum_s"][-1])
    return found


def run(ctx: StageContext) -> None:
    params: RelightParams = ctx.params
    bakeable = _bakeable(params)
    if params.envmap_path == "bake" and bakeable is not None:
        raise ConfigError(f"relight.envmap_path 'bake': {bakeable}; or set envmap_path to 'auto' or 'sum'")
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

    # Every sequence first (what each frame shows), so that a path can be chosen for each.
    sequences: dict[str, tuple[list[seq.FrameSpec], np.ndarray, str]] = {}
    for map_name in params.envmaps:
        envmap = _read_map(map_name, ctx.log)
        try:
            frames = seq.envmap_sequence(envmap, params.envmap_frames, params.rotate_deg_per_frame, view,
                                         method=params.light_method, directions=params.directions,
                                         drop_fraction=params.drop_fraction,
                                         adaptive=params.adaptive, mask=mask,
                                         light_distance_m=params.light_distance_m, scale=params.envmap_scale,
                                         centroid=params.light_centroid)
        except EnvMapError as err:
            raise InputError(f"relight.envmaps: {err}") from err
        sequences[f"envmap_{envmap.name}"] = (frames, default, "default")
    key_pos, key_rgb = seq.key_light(view)
    if params.orbit_radius_m > 0 and params.orbit_frames > 0:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", seq.LightRangeWarning)
            frames = seq.point_light_sequence(
                seq.orbit_positions(params.orbit_radius_m, params.orbit_frames, 0.0, view.target_head), view,
                falloff_reference_m=params.falloff_reference_m, mask=mask, what="orbit")
        for w in caught:
            ctx.log.warning("%s", w.message)
        sequences["point_orbit"] = (frames, default, "default")
    if params.point_lights:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", seq.LightRangeWarning)
            frames = seq.point_light_sequence(np.asarray(params.point_lights, float), view,
                                              falloff_reference_m=params.falloff_reference_m, mask=mask)
        for w in caught:
            ctx.log.warning("%s", w.message)
        sequences["point_lights"] = (frames, default, "default")
    if params.camera_eyes:
        sequences["views"] = (seq.views_sequence(np.asarray(params.camera_eyes, float), view, key_pos, key_rgb),
                              default, "default")
    if params.turntable_frames:
        sequences["turntable"] = (seq.turntable_sequence(params.turntable_frames, view, key_pos, key_rgb),
                                  default, "default")
    if params.dolly_zoom_frames:
        sequences["dolly_zoom"] = (seq.dolly_zoom_sequence(params.dolly_zoom_frames, view, key_pos, key_rgb),
                                   default, "default")
    if expressions is not None:
        sequences["expressions"] = (seq.expression_sequence(expressions, view, key_pos, key_rgb), expressions,
                                    "expressions")
    paths = choose_paths({name: frames for name, (frames, _, _) in sequences.items()}, params.envmap_path,
                         params.bake_min_frames, bakeable)
    out.write_paths({name: {"path": c.path, "reason": c.reason, "frames": len(sequences[name][0])}
                     for name, c in paths.items()})

    geometry = decode(model, default_mesh)
    front = view.camera(view.front_eye())
    check: dict[str, list[float]] = {}
    bake_seconds = None
    if params.bake_check and _check_maps(params) and bakeable is None:
        # One bake of the default view and expression, in this process and timed, then its frames
        # against the voxel-space sum's; kept in the cache, where the envmap sequences find it.
        item = source.bake(seq.FrameSpec(front, key_pos, key_rgb, 0), default, "default", params, view.target_head)
        start = time.perf_counter()
        baked = bake_images(model, geometry, front, fibonacci_sphere(params.directions), rank=params.bake_rank,
                            distance_m=params.light_distance_m, centre=view.target_head, steps=steps,
                            light_batch=params.light_batch)
        bake_seconds = time.perf_counter() - start
        cache = stage_item_cache(ctx, code=BAKE_CODE)
        entry = cache.path(bake_item, bake_key(item))
        if not entry.is_file():
            cache.store(entry, baked.to_arrays())
        check = bake_check(ctx, model, geometry, baked, front, params, mask, view.target_head, image_scale, steps)

    # The bakes the sequences need, one per view and expression (from the cache where made before).
    bakes: dict[tuple, ImageBake] = {}
    wanted: dict[tuple, BakeItem] = {}
    for name, (frames, meshes, mesh_array) in sequences.items():
        if paths[name].path == "bake":
            for spec in frames:
                wanted.setdefault(view_key(spec), source.bake(spec, meshes, mesh_array, params, view.target_head))
    if wanted:
        bakes = dict(zip(wanted, fetch_bakes(ctx, list(wanted.values()))))

    manifest: dict = {}
    envmap_seconds, bake_frame_seconds, directions = [], [], []
    naive_seconds, fast_seconds, max_diff = [], [], 0.0
    for name, (frames, meshes, mesh_array) in sequences.items():
        if paths[name].path == "bake":
            bake_frame_seconds += render_bake_sequence(ctx, bakes[view_key(frames[0])], name, frames, image_scale,
                                                       manifest)
        else:
            seconds = render_sequence(ctx, source, name, frames, meshes, mesh_array, manifest)
            if name.startswith("envmap_"):
                envmap_seconds += seconds
        ctx.log.info("%s: %d frames by %s (%s)", name, len(frames), paths[name].path, paths[name].reason)
        if not name.startswith("envmap_"):
            continue
        directions += [f.info["directions"] for f in frames]
        for spec in frames[:max(0, params.naive_timing_frames - len(naive_seconds))]:
            # Both paths timed here, one after the other in this one process: the workers'
            # own timings overlap each other (and any other job), so they measure contention.
            fast_rgb, _ = render_spec(geometry, spec)  # also a warm-up
            fast_seconds.append(_timed(render_spec, geometry, spec))
            start = time.perf_counter()
            naive_rgb, _ = render_spec(geometry, spec, "per_light")
            naive_seconds.append(time.perf_counter() - start)
            max_diff = max(max_diff, float(np.abs(fast_rgb - naive_rgb).max()))

    # Seconds per envmap frame of the voxel-space sum: this process's timings (comparable with the
    # naive path's and the bake's), else the workers'.
    sum_seconds = fast_seconds + check.get("sum_s", [])
    if sum_seconds or envmap_seconds:
        metrics["envmap_seconds_per_frame"] = float(np.mean(sum_seconds or envmap_seconds))
    if envmap_seconds:
        metrics["envmap_worker_seconds_per_frame"] = float(np.mean(envmap_seconds))
    if directions:
        metrics["envmap_directions"] = float(np.mean(directions))
        metrics["envmap_frames"] = len(directions)
    if naive_seconds:
        metrics["naive_envmap_seconds_per_frame"] = float(np.mean(naive_seconds))
        metrics["envmap_fast_naive_max_abs_diff"] = max_diff
    metrics["envmap_frames_from_bake"] = len(bake_frame_seconds)
    metrics["envmap_frames_from_sum"] = len(envmap_seconds)
    metrics["sequences_from_bake"] = sum(c.path == "bake" for c in paths.values())
    metrics["sequences_from_network"] = sum(c.path != "bake" for c in paths.values())
    if bake_frame_seconds:
        metrics["bake_sequence_frame_seconds"] = float(np.mean(bake_frame_seconds))
    if bake_seconds is not None:
        metrics["bake_seconds"] = bake_seconds
        metrics["bake_rank"] = params.bake_rank or params.directions
        metrics["bake_directions"] = params.directions
        metrics["bake_mb"] = baked.nbytes / 1e6
    if check.get("psnr"):
        metrics["bake_frame_seconds"] = float(np.mean(check["bake_s"]))
        metrics["bake_check_sum_seconds_per_frame"] = float(np.mean(check["sum_s"]))
        metrics["bake_speedup_vs_sum"] = float(np.mean(check["sum_s"]) / max(np.mean(check["bake_s"]), 1e-9))
        metrics["bake_psnr_vs_sum_db"] = float(np.mean(check["psnr"]))
        metrics["bake_psnr_vs_sum_min_db"] = float(np.min(check["psnr"]))
        metrics["bake_check_frames"] = len(check["psnr"])
        metrics["bake_projection_setup_seconds"] = float(np.mean(check["setup_s"]))
        metrics["bake_break_even_frames"] = float(
            bake_seconds / max(np.mean(check["sum_s"]) - np.mean(check["bake_s"]), 1e-9))
    metrics["frames_rendered"] = sum(len(v) for v in manifest.values())
    ctx.log.info("relight: %d frames (%d from bakes); envmap %.3f s/frame (naive %.3f, bake %.4f), %.0f directions",
                 metrics["frames_rendered"], len(bake_frame_seconds), metrics.get("envmap_seconds_per_frame", math.nan),
                 metrics.get("naive_envmap_seconds_per_frame", math.nan), metrics.get("bake_frame_seconds", math.nan),
                 metrics.get("envmap_directions", math.nan))


STAGE = Stage(
    name="relight",
    inputs=("train", "track", "capture"),
    params=RelightParams,
    run=run,
    external_inputs=_external,
    doc="Render the trained head under environment maps, point lights, new views and expressions (EXR, PNG, MP4).",
)
