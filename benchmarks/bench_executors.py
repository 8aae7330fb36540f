"""Executor throughput: a real per-frame function (the studio rendering one OLAT image at a small
size) with 1 and 2 workers on the local process pool and on a local Ray, and the scheduling
overhead per item (a no-op over many items). Then a per-frame stage's own items: relight frames
(``stages.relight.render.render_frame``, a small random head, 16 point lights per frame)
through the per-item cache (``pipeline.itemcache``) with 1 and 2 workers, and the same frames
again, all reused from the cache.

Writes ``bench-results/executors.json``. The machine's cores are shared with other jobs:
throughputs are noisy, and with 2 cores a 2-worker speed-up below 2x is expected.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

RENDER_ITEMS = 24
NOOP_ITEMS = 4000
RELIGHT_FRAMES = 24
CAMERA_SCALE = 0.15  # 115 x 154 px images
_STUDIO: dict[str, Any] = {}


def render_olat(item: int) -> float:
    """Render OLAT image ``item`` (camera, bar and frame vary with it); returns its mean value."""
    import numpy as np

    from hardware.studio import RenderSettings, VirtualStudio, make_performance, make_subject
    from scene.rig import default_rig

    if "studio" not in _STUDIO:  # once per worker process
        rig = default_rig()
        _STUDIO["rig"] = rig
        _STUDIO["frames"] = make_performance(seed=1, frames_per_take=3)
        _STUDIO["studio"] = VirtualStudio(rig, make_subject("bench", seed=1, texture_size=256),
                                          RenderSettings(edge_samples=2, bar_samples=2, full_on_bar_samples=1))
    rig, frames, studio = _STUDIO["rig"], _STUDIO["frames"], _STUDIO["studio"]
    cams = rig.cameras_at(CAMERA_SCALE)
    image = studio.render(frames[item % len(frames)], cams[item % len(cams)], item % len(rig.bars)).rgb
    return float(np.mean(image))


def noop(item: int) -> int:
    """The scheduling-overhead probe."""
    return item


def _executor(kind: str, workers: int):
    from pipeline.executors import make_executor

    return make_executor(kind, workers)


def _measure(kind: str, workers: int) -> dict[str, float]:
    with _executor(kind, workers) as ex:
        start = time.perf_counter()
        ex.map(render_olat, list(range(2 * workers)), desc="warm-up")  # start workers, build the studio in each
        warm_s = time.perf_counter() - start
        start = time.perf_counter()
        values = ex.map(render_olat, list(range(RENDER_ITEMS)), desc="olat")
        render_s = time.perf_counter() - start
        start = time.perf_counter()
        out = ex.map(noop, list(range(NOOP_ITEMS)), desc="noop")
        noop_s = time.perf_counter() - start
    if out != list(range(NOOP_ITEMS)) or len(values) != RENDER_ITEMS:
        raise RuntimeError(f"{kind} executor returned wrong results")
    return {f"{kind}_{workers}w_olat_images_per_second": RENDER_ITEMS / render_s,
            f"{kind}_{workers}w_startup_seconds": warm_s,
            f"{kind}_{workers}w_overhead_us_per_item": 1e6 * noop_s / NOOP_ITEMS}


def _relight_items(folder: Path) -> list:
    """``RELIGHT_FRAMES`` relight frame items of a small random head saved under ``folder``."""
    import numpy as np
    import torch
    import trimesh

    from avatar.config import AvatarConfig
    from avatar.io import save_trained
    from avatar.layout import build_layout
    from avatar.model import RelightableMVP
    from pipeline.hashing import hash_bytes, hash_path
    from stages.relight.output import RelightOutput
    from stages.relight.render import FrameItem
    from stages.train.output import TrainOutput
    from stages.relight.sequences import ViewSpec, orbit_positions

    torch.set_num_threads(1)  # as the workers (OMP_NUM_THREADS=1)
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    verts = np.asarray(mesh.vertices, np.float32)
    config = AvatarConfig(prims_per_side=8, voxels_per_side=4, latent_dim=16, encoder_hidden=32, base_channels=16,
                          rgb_channels=(16, 12), alpha_channels=(8, 4), geometry_channels=8, steps_per_ray=24)
    torch.manual_seed(0)
    model = RelightableMVP(config, build_layout(verts, np.asarray(mesh.faces), config.prims_per_side), num_bars=4)
    train, relight = TrainOutput(folder), RelightOutput(folder)  # a train and a relight output in one folder
    model_dir, meshes_path = train.model_dir("ours"), relight.meshes_path
    save_trained(model_dir, model, "ours")
    np.savez(meshes_path, default=verts[None])
    view = ViewSpec(48, 64, 0.9, 24.0)
    camera = view.camera(view.front_eye())
    items = []
    for i in range(RELIGHT_FRAMES):  # 16 lights on a ring, turned a little each frame
        lights = orbit_positions(1.5, 16, 0.2 + 0.01 * i)
        items.append(FrameItem(str(model_dir), hash_path(model_dir), str(meshes_path),
                               "default", 0, hash_bytes(verts.tobytes()), camera, lights, np.full((16, 3), 0.1),
                               config.steps_per_ray, 16, 1.0, "cpu"))
    return items


def _measure_relight(kind: str, workers: int, items: list, cache_root: Path) -> dict[str, float]:
    from pipeline.itemcache import ItemCache
    from stages.relight.render import frame_key, render_frame

    with _executor(kind, workers) as ex:
        start = time.perf_counter()
        ex.map(render_frame, items[:2 * workers], desc="warm-up")  # start workers, load the model in each
        warm_s = time.perf_counter() - start
        cache = ItemCache(cache_root / f"{kind}{workers}")
        start = time.perf_counter()
        cache.map(ex, render_frame, items, frame_key, desc="relight frames")
        computed_s = time.perf_counter() - start
        start = time.perf_counter()
        cache.map(ex, render_frame, items, frame_key, desc="relight frames")
        reused_s = time.perf_counter() - start
    if cache.hits != len(items):
        raise RuntimeError(f"{kind}: the second pass over relight frames was not served by the cache")
    return {f"{kind}_{workers}w_relight_frames_per_second": len(items) / computed_s,
            f"{kind}_{workers}w_relight_reused_frames_per_second": len(items) / reused_s,
            f"{kind}_{workers}w_relight_startup_seconds": warm_s}


def main() -> dict:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    serial_start = time.perf_counter()
    render_olat(0)
    build_s = time.perf_counter() - serial_start
    start = time.perf_counter()
    for i in range(RENDER_ITEMS):
        render_olat(i)
    serial_rate = RENDER_ITEMS / (time.perf_counter() - start)
    results: dict[str, Any] = {"in_process_olat_images_per_second": serial_rate, "studio_build_seconds": build_s,
                               "olat_items": RENDER_ITEMS, "noop_items": NOOP_ITEMS, "cpu_count": os.cpu_count() or 1,
                               "load_average_1min_at_start": os.getloadavg()[0],
                               "note": ("2 shared cores (other jobs run beside the benchmark: see the load average): noisy, speed-ups understated. "
                                        "local with 1 worker runs items in-process (no pool); Ray is a local "
                                        "ray.init(num_cpus=workers), items chunked (4 chunks per worker).")}
    print(f"in process: {serial_rate:.2f} OLAT images/s (studio build {build_s:.2f} s)")
    kinds = ["local"]
    try:
        import ray  # noqa: F401

        kinds.append("ray")
    except ImportError:
        print("ray is not installed (`pip install .[ray]`); local executor only")
    for kind in kinds:
        for workers in (1, 2):
            res = _measure(kind, workers)
            results.update(res)
            print(f"{kind} {workers} worker(s): {res[f'{kind}_{workers}w_olat_images_per_second']:.2f} OLAT images/s, "
                  f"overhead {res[f'{kind}_{workers}w_overhead_us_per_item']:.0f} us/item, "
                  f"start + warm-up {res[f'{kind}_{workers}w_startup_seconds']:.1f} s")
        results[f"{kind}_speedup_2w"] = (results[f"{kind}_2w_olat_images_per_second"]
                                         / results[f"{kind}_1w_olat_images_per_second"])
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        items = _relight_items(Path(tmp))
        results["relight_frames"] = RELIGHT_FRAMES
        for kind in kinds:
            for workers in (1, 2):
                res = _measure_relight(kind, workers, items, Path(tmp) / "cache")
                results.update(res)
                print(f"{kind} {workers} worker(s): {res[f'{kind}_{workers}w_relight_frames_per_second']:.2f} relight "
                      f"frames/s rendered, {res[f'{kind}_{workers}w_relight_reused_frames_per_second']:.0f} frames/s "
                      f"reused from the per-item cache")
            results[f"{kind}_relight_speedup_2w"] = (results[f"{kind}_2w_relight_frames_per_second"]
                                                     / results[f"{kind}_1w_relight_frames_per_second"])
    out = Path("bench-results")
    out.mkdir(exist_ok=True)
    (out / "executors.json").write_text(json.dumps(results, indent=1))
    return results


if __name__ == "__main__":
    main()
