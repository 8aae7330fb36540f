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

CPU timings are this process's CPU time with one torch thread (a shared machine's wall
clock is meaningless); GPU timings are synchronised wall clock. Writes ``bench-results/relight.json``.
"""

from __future__ import annotations

import json
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
    from hardware.studio.envmap_truth import _studio, studio_camera
    from scene.lights import DirectionalLight

    img = _studio(subject, None).render_lights(
        frame, studio_camera(cam), [DirectionalLight(d, e) for d, e in zip(lights.directions_world, lights.irradiance_rgb)],
        noise=False).rgb
    white = max(float(np.percentile(reference, 99.5)), 1e-8)
    mse = float(np.mean((img / white - reference / white) ** 2))
    return 10 * np.log10(1.0 / max(mse, 1e-12))


def adaptive_and_chart(width: int = 48, height: int = 64) -> dict:
    from hardware.studio.envmap_truth import _studio, frame_from_weights, studio_camera
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
        reference = _studio(subject, None).render_lights(
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
    else:
        results["paper"] = {"note": "no CUDA device here: the paper configuration (N=64, M=16, 1024x768) is "
                                    "timed only on a GPU"}
        print("paper: skipped (no CUDA device)", flush=True)
    results.update(adaptive_and_chart())
    (OUT / "relight.json").write_text(json.dumps(results, indent=1))
    print(f"wrote {OUT / 'relight.json'} and {OUT / 'relight_psnr_vs_time.png'}")


if __name__ == "__main__":
    main()
