"""Render a relight job: every sequence of ``RelightParams`` from a trained head, into a folder.

``render_all`` takes the input folders, the params and where to write; the relight stage's
``run`` and ``pipeline render`` are thin adapters over it. How the frames are rendered, cached
and timed is described in ``stages.relight.stage``.
"""

from __future__ import annotations

import logging
import math
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np
import torch

from avatar.bake import ImageBake, bake_images, psnr_db
from avatar.render import PointLights, RenderMethod, decode, render
from pipeline.devices import resolve_device
from pipeline.errors import ConfigError, InputError
from pipeline.hashing import hash_path
from pipeline.itemcache import stage_item_cache
from pipeline.stage import Executor
from scene.envmap import BackMask, EnvMapError, RotatingProjection, fibonacci_sphere
from stages.relight import sequences as seq
from stages.relight.bake import BAKE_CODE, BakeItem, bake_item, bake_key, choose_paths, render_from_bake, view_key
from stages.relight.inputs import load_inputs, read_map
from stages.relight.output import RelightOutput
from stages.relight.outputs import SequenceWriter
from stages.relight.params import RelightParams, check_maps
from stages.relight.render import FrameItem, frame_key, render_frame
from stages.train.output import TrainOutput


@dataclass
class RenderTarget:
    """Where a render writes and how it fans out: what ``render_all``'s steps share.

    Attributes:
        out: the output folder (``stages.relight.output.RelightOutput``).
        cache_dir: the persistent folder of the per-frame and per-bake caches (``items/``).
        executor: fans frames and bakes out to workers.
        log: progress, warnings and the summary line.
        metrics: the run's figures, filled as it goes; ``ItemCache.report`` reads ``log`` from here.
    """

    out: Path
    cache_dir: Path
    executor: Executor
    log: logging.Logger
    metrics: dict[str, float] = field(default_factory=dict)


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


def render_sequence(target: RenderTarget, fps: float, source: FrameSource, name: str, frames: list[seq.FrameSpec],
                    meshes: np.ndarray, mesh_array: str, manifest: dict) -> list[float]:
    """Render and write one sequence; returns seconds per frame.

    Frames fan out through ``target.executor`` (GPU items on CUDA) and are cached per frame in
    ``target.cache_dir`` (``render.frame_key``): a rerun renders only frames it has not
    rendered before. Each frame is written as soon as it (and every frame before it) exists,
    and stored in the cache by the worker that rendered it, so an error keeps every frame done.
    """
    out = RelightOutput(target.out)
    writer = SequenceWriter(out, name, fps, target.log)
    seconds, records = [], []
    manifest[name] = records
    cache = stage_item_cache(target)

    def write(i: int, result: dict) -> None:
        seconds.append(float(result["seconds"]))
        writer.write(i, np.asarray(result["rgb"], np.float32), np.asarray(result["alpha"], np.float32))
        records.append(_record(i, frames[i], "voxel_sum"))

    try:
        cache.map(target.executor, render_frame, source.items(frames, meshes, mesh_array), frame_key,
                  desc=f"{name} frames", gpu=source.device.startswith("cuda"), consume=write)
    finally:
        writer.finish()
        out.write_renders(manifest)
    cache.report(target, f"{name} frames")
    target.metrics["frames_reused"] = target.metrics.get("frames_reused", 0) + cache.hits
    target.metrics["frames_computed"] = target.metrics.get("frames_computed", 0) + cache.misses
    return seconds


def _record(index: int, spec: seq.FrameSpec, path: str) -> dict:
    """A frame's entry in ``renders.json``: what it shows and which path rendered it."""
    return {"index": index, "camera": spec.camera.to_dict(), "light_pos": spec.light_pos.tolist(),
            "light_rgb": spec.light_rgb.tolist(), "mesh_index": spec.mesh_index, "path": path, **spec.info}


def fetch_bakes(target: RenderTarget, items: list[BakeItem]) -> list[ImageBake]:
    """The bakes of ``items``: from the per-item cache, the missing ones baked through the executor."""
    cache = stage_item_cache(target, code=BAKE_CODE)
    results = cache.map(target.executor, bake_item, items, bake_key, desc="light-transfer bakes",
                        gpu=items[0].device.startswith("cuda") if items else False)
    cache.report(target, "light-transfer bakes")
    target.metrics["bakes_reused"] = target.metrics.get("bakes_reused", 0) + cache.hits
    target.metrics["bakes_computed"] = target.metrics.get("bakes_computed", 0) + cache.misses
    return [ImageBake.from_arrays(r) for r in results]


def render_bake_sequence(target: RenderTarget, fps: float, baked: ImageBake, name: str, frames: list[seq.FrameSpec],
                         image_scale: float, manifest: dict) -> list[float]:
    """Write one envmap sequence from its view's bake (every frame a weighted sum of the basis); seconds per frame."""
    out = RelightOutput(target.out)
    writer = SequenceWriter(out, name, fps, target.log)
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


def bake_check(log: logging.Logger, model, geometry, baked: ImageBake, camera, params: RelightParams,
               mask: BackMask, centre_head, image_scale: float, steps: int) -> dict[str, list[float]]:
    """The bake against the voxel-space sum on the same frames, timed one after the other in this process.

    For every map of ``check_maps`` at every ``bake_check_rotations_deg``: the bake frame
    (projection of the turned map onto the baked directions, then the weighted sum) and the
    voxel-space sum of the same lights (the select_uniform lights of the turned map), their
    seconds and the bake's PSNR against the sum.
    """
    found: dict[str, list[float]] = {"bake_s": [], "sum_s": [], "psnr": [], "setup_s": []}
    warm = False
    for name in check_maps(params):
        envmap = read_map(name, log)
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
            log.info("bake check %s at %.0f deg: %.1f dB against the voxel-space sum; %.2f ms against %.0f ms",
                         envmap.name, deg, found["psnr"][-1], 1e3 * found["bake_s"][-1], 1e3 * found["sum_s"][-1])
    return found


def render_all(inputs: Mapping[str, Path], params: RelightParams, out_dir: Path, cache_dir: Path,
               log: logging.Logger, executor: Executor) -> dict[str, float]:
    """Render every sequence ``params`` asks for from the ``train``, ``track`` and ``capture`` folders in
    ``inputs`` into ``out_dir``; returns the metrics.

    Frames and bakes are cached in ``cache_dir`` (``items/``), so a rerun into the same folder renders
    only what it has not rendered before. The stage's ``run`` and ``pipeline render`` both call this.
    """
    target = RenderTarget(out=out_dir, cache_dir=cache_dir, executor=executor, log=log)
    bakeable = _bakeable(params)
    if params.envmap_path == "bake" and bakeable is not None:
        raise ConfigError(f"relight.envmap_path 'bake': {bakeable}; or set envmap_path to 'auto' or 'sum'")
    device = resolve_device(params.device, "relight.device")
    model, meta, default_mesh, expressions = load_inputs(inputs, params, device)
    steps = params.steps_per_ray or model.config.steps_per_ray
    # The network learnt normalised images; EXR outputs are in the capture's linear units.
    image_scale = float(meta.get("image_scale", 1.0))
    model_dir = TrainOutput(inputs["train"]).model_dir()
    out = RelightOutput(out_dir)
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
    metrics = target.metrics

    # Every sequence first (what each frame shows), so that a path can be chosen for each.
    sequences: dict[str, tuple[list[seq.FrameSpec], np.ndarray, str]] = {}
    for map_name in params.envmaps:
        envmap = read_map(map_name, log)
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
            target.log.warning("%s", w.message)
        sequences["point_orbit"] = (frames, default, "default")
    if params.point_lights:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", seq.LightRangeWarning)
            frames = seq.point_light_sequence(np.asarray(params.point_lights, float), view,
                                              falloff_reference_m=params.falloff_reference_m, mask=mask)
        for w in caught:
            target.log.warning("%s", w.message)
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
    if params.bake_check and check_maps(params) and bakeable is None:
        # One bake of the default view and expression, in this process and timed, then its frames
        # against the voxel-space sum's; kept in the cache, where the envmap sequences find it.
        item = source.bake(seq.FrameSpec(front, key_pos, key_rgb, 0), default, "default", params, view.target_head)
        start = time.perf_counter()
        baked = bake_images(model, geometry, front, fibonacci_sphere(params.directions), rank=params.bake_rank,
                            distance_m=params.light_distance_m, centre=view.target_head, steps=steps,
                            light_batch=params.light_batch)
        bake_seconds = time.perf_counter() - start
        cache = stage_item_cache(target, code=BAKE_CODE)
        entry = cache.path(bake_item, bake_key(item))
        if not entry.is_file():
            cache.store(entry, baked.to_arrays())
        check = bake_check(log, model, geometry, baked, front, params, mask, view.target_head, image_scale, steps)

    # The bakes the sequences need, one per view and expression (from the cache where made before).
    bakes: dict[tuple, ImageBake] = {}
    wanted: dict[tuple, BakeItem] = {}
    for name, (frames, meshes, mesh_array) in sequences.items():
        if paths[name].path == "bake":
            for spec in frames:
                wanted.setdefault(view_key(spec), source.bake(spec, meshes, mesh_array, params, view.target_head))
    if wanted:
        bakes = dict(zip(wanted, fetch_bakes(target, list(wanted.values()))))

    manifest: dict = {}
    envmap_seconds, bake_frame_seconds, directions = [], [], []
    naive_seconds, fast_seconds, max_diff = [], [], 0.0
    for name, (frames, meshes, mesh_array) in sequences.items():
        if paths[name].path == "bake":
            bake_frame_seconds += render_bake_sequence(target, params.fps, bakes[view_key(frames[0])], name, frames, image_scale,
                                                       manifest)
        else:
            seconds = render_sequence(target, params.fps, source, name, frames, meshes, mesh_array, manifest)
            if name.startswith("envmap_"):
                envmap_seconds += seconds
        log.info("%s: %d frames by %s (%s)", name, len(frames), paths[name].path, paths[name].reason)
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
    log.info("relight: %d frames (%d from bakes); envmap %.3f s/frame (naive %.3f, bake %.4f), %.0f directions",
                 metrics["frames_rendered"], len(bake_frame_seconds), metrics.get("envmap_seconds_per_frame", math.nan),
                 metrics.get("naive_envmap_seconds_per_frame", math.nan), metrics.get("bake_frame_seconds", math.nan),
                 metrics.get("envmap_directions", math.nan))
    return metrics
