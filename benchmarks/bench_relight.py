"""Relighting benchmark: voxel-space light sum vs naive, adaptive directions, PSNR vs render time.

1. Seconds per frame for a 256-direction environment map: the voxel-space sum (decode the
   per-light RGB grids in batches, sum, raymarch once) against the naive render-each-light-
   and-sum, same output to within 1e-4; tiny configuration on the CPU (random weights: the
   timing does not depend on training), paper configuration when CUDA is present.
2. Per shipped map: directions, selection time and error of the adaptive selection against
   the paper's uniform 256 (error = PSNR against a 4096-direction reference render of the
   studio's true subject, ray traced with shadows, each of its lights at its cell's energy
   centroid: the light-sampling error alone).
3. Chart ``bench-results/relight_psnr_vs_time.png``: that PSNR against our render time per
   frame as the number of directions grows (64..1024), per map, for the paper's lights (at
   the Fibonacci cell centres) and with each light at its cell's energy centroid (the
   render time depends on the number of lights only, so it is measured once per count).

4. The light-transfer bake (``avatar.bake``) against the voxel-space sum, side by side in this
   process, on the stage's default view (96 x 128, 0.9 m, 24 degrees) of ``BAKE_SUBJECT``'s
   trained head (default alice; its first tracked mesh) or, without one, the random tiny head:
   one bake (256 uniform directions), then for every shipped map at several rotations the
   voxel-space sum's frame and the bake's (projection of the turned map onto the directions
   plus the weighted sum) at every rank, image-space and voxel-space kinds; PSNR against the
   sum (white = its 99th-percentile head pixel). Charts ``bench-results/relight_bake_rank.png``
   (error vs rank, time vs rank, error vs bytes) and the figures at the relight stage's rank
   (``bake_seconds``, ``bake_frame_seconds``, ``envmap_seconds_per_frame``,
   ``bake_psnr_vs_sum_db`` over the stage's default maps), and what reusing a voxel bake from a
   moved camera would cost in accuracy.

CPU timings are this process's CPU time with one torch thread (a shared machine's wall
clock is meaningless); GPU timings are synchronised wall clock. Writes ``bench-results/relight.json``.
"""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench-results"
MAPS = sorted((ROOT / "assets" / "envmaps").glob("*/*.exr"))
CHART_MAPS = ("courtyard", "studio", "sunrise", "StageEnvLatLong")
REFERENCE_DIRECTIONS = 4096


def _model(config):
    import trimesh

    from avatar.layout import build_layout
    from avatar.model import RelightableMVP

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    torch.manual_seed(0)
    layout = build_layout(np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces), config.prims_per_side)
    return RelightableMVP(config, layout, num_bars=32).eval(), np.asarray(mesh.vertices, np.float32)


def _camera(width: int, height: int):
    from scene.view import ViewSpec

    view = ViewSpec(width, height, 0.6, 30.0)
    return view.camera(view.front_eye())


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def _clock(device: str) -> float:
    """Seconds: wall clock on a GPU (synchronised); this process's CPU time on the CPU.

    Benchmarks run with one torch thread on the CPU, so CPU time is what an idle machine's
    wall clock would show, and other jobs on a shared machine do not inflate it.
    """
    return time.perf_counter() if device == "cuda" else time.process_time()


def time_fast_vs_naive(config, device: str, width: int, height: int, repeats: int = 2) -> dict:
    from avatar.render import DirectionalLights, decode, render
    from scene.envmap import read_envmap, select_uniform

    model, verts = _model(config)
    model = model.to(device)
    light_batch = 16 if device == "cpu" else 32
    geometry = decode(model, verts)
    lights = select_uniform(read_envmap(ROOT / "assets/envmaps/blender-cc0/courtyard.exr"), 256)
    sky = DirectionalLights(lights.directions_world, lights.irradiance_rgb / lights.irradiance_rgb.sum(0).max(), 50.0)
    cam = _camera(width, height)

    def frame(lights, method="voxel_sum"):
        return render(model, geometry, cam, lights, light_batch=light_batch, method=method).numpy()[0]

    frame(DirectionalLights(sky.directions[:4], sky.rgb[:4], 50.0))  # warm-up
    fast_s = []
    for _ in range(repeats):
        _sync(device)
        start = _clock(device)
        fast = frame(sky)
        _sync(device)
        fast_s.append(_clock(device) - start)
    _sync(device)
    start = _clock(device)
    naive = frame(sky, "per_light")
    _sync(device)
    naive_s = _clock(device) - start
    return {"directions": len(lights), "image": f"{width}x{height}", "device": device,
            "envmap_seconds_per_frame": min(fast_s), "naive_envmap_seconds_per_frame": naive_s,
            "speedup": naive_s / min(fast_s), "max_abs_diff": float(np.abs(fast - naive).max()),
            "image_peak": float(fast.max())}


def _studio_psnr(subject, frame, cam, envmap, lights, reference) -> float:
    from hardware.studio.envmap_truth import studio_camera, truth_studio
    from scene.lights import DirectionalLight

    img = truth_studio(subject).render_lights(
        frame, studio_camera(cam), [DirectionalLight(d, e) for d, e in zip(lights.directions_world, lights.irradiance_rgb)],
        noise=False).rgb
    white = max(float(np.percentile(reference, 99.5)), 1e-8)
    mse = float(np.mean((img / white - reference / white) ** 2))
    return 10 * np.log10(1.0 / max(mse, 1e-12))


def adaptive_and_chart(width: int = 48, height: int = 64) -> dict:
    from hardware.studio.envmap_truth import frame_from_weights, studio_camera, truth_studio
    from hardware.studio.subject import make_subject
    from avatar.config import AvatarConfig
    from avatar.render import DirectionalLights, decode, render
    from scene.envmap import BackMask, read_envmap, select_adaptive, select_uniform
    from scene.lights import DirectionalLight

    subject = make_subject("alice", 1)
    frame = frame_from_weights(np.zeros(57))
    cam = _camera(width, height)
    model, verts = _model(AvatarConfig.tiny())
    geometry = decode(model, verts)

    def ours(lights) -> None:
        render(model, geometry, cam, DirectionalLights(lights.directions_world, lights.irradiance_rgb)).numpy()
    per_map, chart, render_seconds = {}, {}, {}
    for path in MAPS:
        env = read_envmap(path)
        mask = BackMask()
        ref_lights = select_uniform(env, REFERENCE_DIRECTIONS, 0.0, mask, centroid=True)
        reference = truth_studio(subject).render_lights(
            frame, studio_camera(cam), [DirectionalLight(d, e) for d, e in zip(ref_lights.directions_world, ref_lights.irradiance_rgb)],
            noise=False).rgb
        start = _clock("cpu")
        adaptive = select_adaptive(env, mask=mask)
        select_s = _clock("cpu") - start
        uniform = select_uniform(env, 256, 0.0, mask)
        entry = {"adaptive_directions": len(adaptive), "adaptive_select_seconds": select_s,
                 "adaptive_estimated_error": adaptive.estimated_error,
                 "adaptive_psnr_db": _studio_psnr(subject, frame, cam, env, adaptive, reference),
                 "uniform256_directions": len(uniform),
                 "uniform256_psnr_db": _studio_psnr(subject, frame, cam, env, uniform, reference),
                 "uniform256_centroid_psnr_db": _studio_psnr(subject, frame, cam, env,
                                                             select_uniform(env, 256, 0.0, mask, centroid=True),
                                                             reference)}
        runs = []
        for _ in range(2):
            start = _clock("cpu")
            ours(adaptive)
            runs.append(_clock("cpu") - start)
        entry["adaptive_render_seconds"] = min(runs)
        per_map[env.name] = entry
        print(f"{env.name:20s} adaptive {len(adaptive):4d} dirs {entry['adaptive_psnr_db']:6.2f} dB "
              f"(select {select_s:.2f} s, render {entry['adaptive_render_seconds']:.2f} s) | "
              f"uniform {len(uniform)} dirs {entry['uniform256_psnr_db']:6.2f} dB "
              f"(centroids {entry['uniform256_centroid_psnr_db']:6.2f} dB)", flush=True)
        if env.name in CHART_MAPS:
            points = []
            for count in (64, 128, 256, 512, 1024):
                lights = select_uniform(env, count, 0.0, mask)
                if count not in render_seconds:  # render time depends on the light count, not the map
                    runs = []
                    for _ in range(2):
                        start = _clock("cpu")
                        ours(lights)
                        runs.append(_clock("cpu") - start)
                    render_seconds[count] = min(runs)
                centred = select_uniform(env, count, 0.0, mask, centroid=True)
                points.append({"directions": len(lights), "render_seconds": render_seconds[count],
                               "psnr_db": _studio_psnr(subject, frame, cam, env, lights, reference),
                               "centroid_psnr_db": _studio_psnr(subject, frame, cam, env, centred, reference)})
            chart[env.name] = points
    _plot(chart, per_map)
    return {"maps": per_map, "chart": chart}


def _plot(chart: dict, per_map: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for name, points in chart.items():
        line, = ax.plot([p["render_seconds"] for p in points], [p["psnr_db"] for p in points], "o-",
                        label=f"{name} (paper: cell centres)")
        ax.plot([p["render_seconds"] for p in points], [p["centroid_psnr_db"] for p in points], "s--",
                color=line.get_color(), alpha=0.6, label=f"{name} (cell centroids)")
        for p in points:
            ax.annotate(str(p["directions"]), (p["render_seconds"], p["psnr_db"]), fontsize=6)
        a = per_map[name]
        ax.plot([a["adaptive_render_seconds"]], [a["adaptive_psnr_db"]], "*", ms=10, color=line.get_color())
    ax.set_xscale("log")
    ax.set_xlabel("render time per frame, CPU s, 1 thread (tiny model, 48x64; voxel-space sum)")
    ax.set_ylabel(f"PSNR vs {REFERENCE_DIRECTIONS} directions, dB (studio truth)")
    ax.set_title("Envmap directions: quality vs time (numbers: lights; stars: adaptive)", fontsize=9)
    ax.legend(fontsize=6, loc="lower right")
    fig.tight_layout()
    fig.savefig(OUT / "relight_psnr_vs_time.png", dpi=120)
    plt.close(fig)


BAKE_DIRECTIONS = 256
BAKE_RANKS = (2, 4, 8, 16, 24, 32, 48, 64, 96, 128, 192, 256)
VOXEL_RANKS = (4, 16, 32, 64, 256)
BAKE_ROTATIONS_DEG = (0.0, 60.0, 135.0, 200.0, 300.0)
CAMERA_MOVES_DEG = (1.0, 3.0, 10.0)


def _bake_head():
    """(model, mesh, image_scale, what): ``BAKE_SUBJECT``'s trained head and first tracked mesh, else the random tiny head."""
    from avatar.config import AvatarConfig
    from avatar.io import load_trained
    from pipeline.workspace import Workspace, workspace_root
    from stages.track.output import TrackOutput
    from stages.train.output import TrainOutput

    subject = os.environ.get("BAKE_SUBJECT", "alice")
    ws = Workspace(workspace_root(ROOT), subject)
    refs = {stage: ws.read_ref(stage) for stage in ("train", "track")}
    if all(r is not None and "out" in r.outputs for r in refs.values()):
        train, track = (ws.object_path(refs[s].outputs["out"]) for s in ("train", "track"))
        try:
            model, meta = load_trained(TrainOutput(train).model_dir("ours"))
            mesh = np.asarray(TrackOutput(track).meshes()["vertices"][0], np.float32)
            return model, mesh, float(meta.get("image_scale", 1.0)), f"{subject}'s trained head ({train.name[:12]})"
        except (OSError, KeyError, ValueError, RuntimeError) as err:
            print(f"bake: {subject}'s head is not loadable ({err}); using the random tiny head", flush=True)
    model, verts = _model(AvatarConfig.tiny())
    return model, verts, 1.0, "the random tiny head (no trained subject in the workspace)"


def bake_figures(width: int = 96, height: int = 128, stage_rank: int = 32) -> dict:
    from dataclasses import replace

    from avatar.bake import ImageBake, bake_voxels, direction_images, psnr_db
    from avatar.render import PointLights, Rays, decode, render
    from scene.envmap import BackMask, RotatingProjection, fibonacci_sphere
    from scene.view import ViewSpec
    from stages.relight.params import DEFAULT_ENVMAPS

    model, mesh, image_scale, what = _bake_head()
    centre = tuple(float(v) for v in mesh.mean(0))
    view = ViewSpec(width, height, 0.9, 24.0, centre)
    cam = view.camera(view.front_eye())
    geometry = decode(model, mesh)
    directions = fibonacci_sphere(BAKE_DIRECTIONS)
    print(f"bake: {what}, {width}x{height}, {BAKE_DIRECTIONS} directions", flush=True)
    render(model, geometry, cam, PointLights(np.asarray(centre) + 50 * directions[:4]))  # warm-up

    start = _clock("cpu")
    images = direction_images(model, geometry, cam, directions, centre=centre)
    images_s = _clock("cpu") - start
    start = _clock("cpu")
    chosen = ImageBake.from_images(images, stage_rank)
    bake_s = images_s + _clock("cpu") - start
    full = ImageBake.from_images(images, BAKE_DIRECTIONS)
    start = _clock("cpu")
    voxels = bake_voxels(model, geometry, cam, directions, centre=centre)
    voxel_bake_s = _clock("cpu") - start

    mask = BackMask()
    image_rows: dict[int, list] = {r: [] for r in BAKE_RANKS}  # (map, psnr, seconds)
    voxel_rows: dict[int, list] = {r: [] for r in VOXEL_RANKS}
    sum_rows, setup_s = [], []
    for path in MAPS:
        name = path.relative_to(ROOT / "assets" / "envmaps").as_posix()
        env = read_map(path)
        start = _clock("cpu")
        projection = RotatingProjection(env, BAKE_DIRECTIONS, 0.1, mask)
        setup_s.append(_clock("cpu") - start)
        for deg in BAKE_ROTATIONS_DEG:
            angle = math.radians(deg)
            lights = projection.lights(angle)
            points = PointLights(lights.positions_world(50.0, np.asarray(centre)), lights.irradiance_rgb)
            start = _clock("cpu")
            reference, alpha = render(model, geometry, cam, points, image_scale=image_scale).numpy()
            sum_rows.append((name, _clock("cpu") - start))
            for rank in BAKE_RANKS:
                part = full.truncated(rank)
                start = _clock("cpu")
                rgb, _ = part.frame(projection.weights(angle), image_scale)
                image_rows[rank].append((name, psnr_db(rgb, reference, alpha), _clock("cpu") - start))
            for rank in VOXEL_RANKS:
                part = voxels.truncated(rank)
                start = _clock("cpu")
                rgb, _ = part.frame(projection.weights(angle), image_scale)
                voxel_rows[rank].append((name, psnr_db(rgb, reference, alpha), _clock("cpu") - start))
        print(f"  {env.name:20s} rank {stage_rank}: "
              + " ".join(f"{r[1]:.1f}" for r in image_rows[stage_rank][-len(BAKE_ROTATIONS_DEG):]) + " dB", flush=True)

    defaults = {m for m in DEFAULT_ENVMAPS}
    sum_s = float(np.median([t for _, t in sum_rows]))

    def summary(rows, rank, nbytes):
        psnrs = [p for _, p, _ in rows]
        default_psnrs = [p for m, p, _ in rows if m in defaults]
        return {"rank": rank, "psnr_mean_db": float(np.mean(default_psnrs)), "psnr_min_db": float(np.min(default_psnrs)),
                "psnr_mean_all_maps_db": float(np.mean(psnrs)), "psnr_min_all_maps_db": float(np.min(psnrs)),
                "frame_seconds": float(np.median([t for *_, t in rows])), "mb": nbytes / 1e6}
    image_curve = [summary(image_rows[r], r, full.truncated(r).nbytes) for r in BAKE_RANKS]
    voxel_curve = [summary(voxel_rows[r], r, voxels.truncated(r).nbytes) for r in VOXEL_RANKS]

    # Reusing a voxel bake from a moved camera (the grids were decoded for the front view).
    env = read_map(ROOT / "assets/envmaps/blender-cc0/courtyard.exr")
    projection = RotatingProjection(env, BAKE_DIRECTIONS, 0.1, mask)
    lights = projection.lights(0.0)
    points = PointLights(lights.positions_world(50.0, np.asarray(centre)), lights.irradiance_rgb)
    moves = []
    for deg in CAMERA_MOVES_DEG:
        a = math.radians(deg)
        eye = np.asarray(centre) + view.distance_m * np.array([math.sin(a), 0.0, math.cos(a)])
        moved = view.camera(eye)
        truth, alpha = render(model, geometry, moved, points, image_scale=image_scale).numpy()
        reused, _ = replace(voxels, rays=Rays.of_camera(moved)).frame(projection.weights(0.0), image_scale)
        moves.append({"camera_move_deg": deg, "voxel_bake_reused_psnr_db": psnr_db(reused, truth, alpha)})

    at = next(c for c in image_curve if c["rank"] == stage_rank)
    figures = {
        "head": what, "image": f"{width}x{height}", "directions": BAKE_DIRECTIONS, "stage_rank": stage_rank,
        "bake_seconds": bake_s, "bake_direction_images_seconds": images_s, "voxel_bake_seconds": voxel_bake_s,
        "bake_frame_seconds": at["frame_seconds"], "envmap_seconds_per_frame": sum_s,
        "bake_speedup_vs_sum": sum_s / max(at["frame_seconds"], 1e-9),
        "bake_psnr_vs_sum_db": at["psnr_mean_db"], "bake_psnr_vs_sum_min_db": at["psnr_min_db"],
        "bake_psnr_vs_sum_all_maps_db": at["psnr_mean_all_maps_db"],
        "bake_psnr_vs_sum_all_maps_min_db": at["psnr_min_all_maps_db"],
        "bake_mb": at["mb"], "bake_break_even_frames": bake_s / max(sum_s - at["frame_seconds"], 1e-9),
        "projection_setup_seconds_per_map": float(np.mean(setup_s)),
        "maps": [p.relative_to(ROOT / "assets" / "envmaps").as_posix() for p in MAPS],
        "default_maps": sorted(defaults), "rotations_deg": list(BAKE_ROTATIONS_DEG),
        "image_curve": image_curve, "voxel_curve": voxel_curve, "camera_moves": moves,
    }
    _plot_bake(figures)
    return figures


def read_map(path):
    from scene.envmap import read_envmap

    return read_envmap(path)


def _plot_bake(figures: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    image, voxel = figures["image_curve"], figures["voxel_curve"]
    fig, (ax_err, ax_time, ax_bytes) = plt.subplots(1, 3, figsize=(13, 4))
    for curve, label, style in ((image, "image-space basis", "o-"), (voxel, "voxel-space basis", "s--")):
        ranks = [c["rank"] for c in curve]
        line, = ax_err.plot(ranks, [c["psnr_mean_db"] for c in curve], style, label=f"{label}: mean, stage's maps")
        ax_err.plot(ranks, [c["psnr_min_all_maps_db"] for c in curve], style, color=line.get_color(), alpha=0.4,
                    label=f"{label}: worst frame, all 9 maps")
        ax_time.plot(ranks, [1e3 * c["frame_seconds"] for c in curve], style, color=line.get_color(), label=label)
        ax_bytes.plot([c["mb"] for c in curve], [c["psnr_min_all_maps_db"] for c in curve], style,
                      color=line.get_color(), label=f"{label} (worst frame)")
        for c in curve:
            ax_bytes.annotate(str(c["rank"]), (c["mb"], c["psnr_min_all_maps_db"]), fontsize=6)
    ax_err.axhline(40.0, color="grey", lw=0.8, ls=":", label="target 40 dB")
    ax_err.set_xscale("log", base=2)
    ax_err.set_xlabel("rank (basis images / grids)")
    ax_err.set_ylabel("PSNR vs the voxel-space sum, dB")
    ax_err.legend(fontsize=6)
    ax_time.axhline(1e3 * figures["envmap_seconds_per_frame"], color="red", lw=0.8,
                    label="voxel-space sum (today), same frames")
    ax_time.axhline(1e3 * figures["envmap_seconds_per_frame"] / 50.0, color="red", lw=0.8, ls=":",
                    label="50x faster than the sum")
    ax_time.set_xscale("log", base=2)
    ax_time.set_yscale("log")
    ax_time.set_xlabel("rank")
    ax_time.set_ylabel("ms per frame, CPU, 1 thread")
    ax_time.set_title("bake frames include projecting the turned map", fontsize=7)
    ax_time.legend(fontsize=6)
    ax_bytes.axhline(40.0, color="grey", lw=0.8, ls=":")
    ax_bytes.set_xscale("log")
    ax_bytes.set_xlabel("MB a frame reads (numbers: rank)")
    ax_bytes.set_ylabel("PSNR of the worst frame, dB")
    ax_bytes.legend(fontsize=6)
    fig.suptitle(f"Light-transfer bake: {figures['head']}, {figures['image']}, {figures['directions']} directions, "
                 f"{len(figures['maps'])} maps x {len(figures['rotations_deg'])} rotations", fontsize=9)
    fig.tight_layout()
    fig.savefig(OUT / "relight_bake_rank.png", dpi=120)
    plt.close(fig)


def paper_bake_figures(device: str = "cuda", width: int = 768, height: int = 1024, rank: int = 32, config=None) -> dict:
    """The bake at the paper's configuration and image size (a random head): one bake, then frames on the device.

    The paper renders an envmap in about 15 s a frame; the aim is real time (under 33 ms). A
    bake frame is the same product as ``ImageBake.frame``, done in torch on the device, and
    once on the CPU (numpy) for comparison.
    """
    from avatar.bake import bake_images
    from avatar.config import AvatarConfig
    from avatar.render import decode
    from scene.envmap import RotatingProjection, fibonacci_sphere, read_envmap

    model, verts = _model(config or AvatarConfig.paper())
    model = model.to(device)
    geometry = decode(model, verts)
    cam = _camera(width, height)
    _sync(device)
    start = _clock(device)
    baked = bake_images(model, geometry, cam, fibonacci_sphere(256), rank=rank, light_batch=32)
    _sync(device)
    bake_s = _clock(device) - start
    coefficients = torch.as_tensor(baked.coefficients, device=device)  # [D, R]
    basis = torch.as_tensor(baked.basis, device=device)  # [3, R, H*W]
    projection = RotatingProjection(read_envmap(ROOT / "assets/envmaps/blender-cc0/courtyard.exr"), 256)
    frame_s = []
    for deg in (0.0, 60.0, 135.0, 200.0, 300.0, 0.0):
        _sync(device)
        start = _clock(device)
        weights = torch.as_tensor(projection.weights(math.radians(deg)), dtype=torch.float32, device=device)
        rgb = torch.einsum("rc,crp->pc", coefficients.T @ weights, basis)  # [H*W, 3]
        _sync(device)
        frame_s.append(_clock(device) - start)
        del rgb
    start = time.perf_counter()
    baked.frame(projection.weights(0.0))
    cpu_frame_s = time.perf_counter() - start
    return {"image": f"{width}x{height}", "rank": rank, "directions": 256, "bake_seconds": bake_s,
            "bake_frame_seconds_device": float(np.median(frame_s[1:])), "bake_frame_seconds_cpu_numpy": cpu_frame_s,
            "bake_mb": baked.nbytes / 1e6,
            "peak_gpu_gb": torch.cuda.max_memory_allocated() / 1e9 if device == "cuda" else None}


def main() -> None:
    from avatar.config import AvatarConfig

    torch.set_num_threads(1)  # CPU timings are process CPU time of one thread (see _clock)
    OUT.mkdir(exist_ok=True)
    results: dict = {}
    results["tiny"] = time_fast_vs_naive(AvatarConfig.tiny(), "cpu", 48, 64, repeats=1)
    print("tiny:", json.dumps(results["tiny"]), flush=True)
    if torch.cuda.is_available():
        results["paper"] = time_fast_vs_naive(AvatarConfig.paper(), "cuda", 768, 1024, repeats=3)
        print("paper:", json.dumps(results["paper"]), flush=True)
        try:
            results["paper_bake"] = paper_bake_figures()
        except RuntimeError as err:  # out of GPU memory, say: report it, keep the other figures
            results["paper_bake"] = {"error": f"{type(err).__name__}: {err}"}
        print("paper bake:", json.dumps(results["paper_bake"]), flush=True)
    else:
        results["paper"] = {"note": "no CUDA device here: the paper configuration (N=64, M=16, 1024x768) is "
                                    "timed only on a GPU"}
        print("paper: skipped (no CUDA device)", flush=True)
    bake = bake_figures()
    results["bake"] = bake
    # The bake's headline figures at the top level too (the report's benchmark table shows those).
    for key in ("bake_seconds", "bake_frame_seconds", "envmap_seconds_per_frame", "bake_speedup_vs_sum",
                "bake_psnr_vs_sum_db", "bake_psnr_vs_sum_min_db", "bake_psnr_vs_sum_all_maps_min_db"):
        results[key] = bake[key]
    print("bake:", json.dumps({k: v for k, v in bake.items() if not isinstance(v, list)}), flush=True)
    results.update(adaptive_and_chart())
    (OUT / "relight.json").write_text(json.dumps(results, indent=1))
    print(f"wrote {OUT / 'relight.json'}, {OUT / 'relight_psnr_vs_time.png'} and {OUT / 'relight_bake_rank.png'}")


if __name__ == "__main__":
    main()
