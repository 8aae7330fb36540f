"""The raymarcher's two CPU fast paths, tensor ops against the fused C++ kernel.

On the tiny head's primitives (N=16, M=4, laid out on the ICT face seen from the rig's
cameras, as at initialisation), for growing ray batches (the tiny preset's 8 x 256 rays,
then 4x and 16x that) and for a whole 64x85 image: forward time, forward + backward time,
and the bytes autograd keeps for the backward pass (every tensor saved for backward,
counted once); the same on an opaque head (the initial head's densities x20, so that rays
saturate as on a trained head and the fused kernel's early termination shows); then
training iterations per second of the whole tiny training step with each kernel. The two paths' images and gradients are compared on the way (max abs
difference). Writes ``bench-results/raymarch.json``. Timings on a shared CPU are noisy:
each is the median of several runs.
"""

from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from avatar.config import AvatarConfig
from avatar.layout import layout_for
from avatar.model import RelightableMVP
from avatar.raymarch import Primitives, raymarch
from avatar.raymarch_fused import fused_module
from benchmarks.bench_train import _tensors, _trainer
from stages.train.trainer import Renderer, TrainTensors

KERNELS = ("torch", "fused")


#: Raises the initial tiny head's densities until about as many rays saturate as in a trained head.
OPAQUE_DENSITY_FACTOR = 20.0


def _saved_bytes(fn) -> int:
    """Bytes of the distinct tensors autograd saves for backward while ``fn()`` runs."""
    seen: dict[tuple[int, int], int] = {}

    def pack(x: torch.Tensor) -> torch.Tensor:
        seen[(x.untyped_storage().data_ptr(), x.untyped_storage().nbytes())] = x.untyped_storage().nbytes()
        return x

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda x: x):
        fn()
    return sum(seen.values())


def _median_seconds(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _tiny_model() -> tuple[AvatarConfig, TrainTensors, RelightableMVP]:
    """The tiny head at initialisation on the ICT face, and the rig's training tensors (2 frames)."""
    config = AvatarConfig.tiny()
    t, verts, tris = _tensors(64, 2, torch.device("cpu"))
    layout = layout_for(config, verts, tris)
    t.guide_vertices = torch.as_tensor(verts[layout.guide_vertex_ids])[None].expand(2, -1, -1).contiguous()
    torch.manual_seed(0)
    return config, t, RelightableMVP(config, layout, num_bars=1)


def _tiny_scene(batch: int) -> tuple[Primitives, TrainTensors, AvatarConfig]:
    """The tiny head's primitives for ``batch`` frames, the rig's training tensors and the head's config."""
    config, t, model = _tiny_model()
    with torch.no_grad():
        mu, _ = model.encode(t.guide_vertices[:1].expand(batch, -1, -1))
        geo = model.decode_geometry(mu)
        rgb = model.decode_rgb(geo, t.cam_pos[:1, 0].expand(batch, 3), t.light_pos[:1].expand(batch, 3))
    prims = geo.primitives(rgb)
    leaves = Primitives(*(x.detach().clone() for x in (prims.centre, prims.rotation, prims.half_extent,
                                                        prims.rgb, prims.density)))
    return leaves, t, config


def _rays(t, batch: int, rays_per_image: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays of random pixels of the rig's cameras (as a training batch draws them)."""
    g = torch.Generator().manual_seed(seed)
    cams = torch.randint(0, t.cam_pos.shape[1], (batch,), generator=g)
    pix = torch.randint(0, t.height * t.width, (batch, rays_per_image), generator=g)
    return t.rays(torch.zeros(batch, dtype=torch.long), cams, pix)


def _compare_batch(prims: Primitives, ro: torch.Tensor, rd: torch.Tensor, steps: int, repeats: int) -> dict:
    out: dict = {"rays": int(ro.shape[0] * ro.shape[1]), "steps": steps}
    images, grads = {}, {}
    for kernel in KERNELS:
        leaves = [x.requires_grad_() for x in (prims.rgb, prims.density, prims.centre, prims.half_extent)]

        def forward():
            with torch.no_grad():
                return raymarch(prims, ro, rd, steps, kernel=kernel)

        def forward_backward():
            res = raymarch(prims, ro, rd, steps, kernel=kernel)
            g = torch.autograd.grad(res.rgb.sum() + res.alpha.sum(), leaves)
            return res, g

        res, g = forward_backward()
        images[kernel], grads[kernel] = res.rgb.detach(), g
        out[kernel] = {
            "forward_ms": 1000 * _median_seconds(forward, repeats),
            "forward_backward_ms": 1000 * _median_seconds(forward_backward, repeats),
            "saved_for_backward_mb": _saved_bytes(lambda: raymarch(prims, ro, rd, steps, kernel=kernel)) / 2 ** 20,
        }
    out["max_abs_image_difference"] = float((images["fused"] - images["torch"]).abs().max())
    out["max_rel_gradient_difference"] = max(
        float((a - b).abs().max() / b.abs().max().clamp(min=1e-12)) for a, b in zip(grads["fused"], grads["torch"]))
    out["forward_backward_speedup"] = out["torch"]["forward_backward_ms"] / out["fused"]["forward_backward_ms"]
    return out


def _training_rates(batch: int, rays: int, iterations: int) -> dict[str, float]:
    """Tiny training iterations per second, the whole step (encoder, decoders, raymarch, Adam), per kernel."""
    rates = {}
    for kernel in KERNELS:
        _, t, model = _tiny_model()
        tr = _trainer(Renderer(model, "ours", None, [0], kernel=kernel), t, iterations, batch, rays,
                      Path("/nonexistent"))
        rates[kernel] = 1.0 / _median_seconds(tr.step, iterations)
    return rates


def main() -> dict:
    torch.set_num_threads(1)  # as the tiny preset trains (threads: 1), one model per core
    from benchmarks.train_runs import tiny_train_params

    start = time.perf_counter()
    fused_module(required=True)
    results: dict = {"build_or_load_seconds": time.perf_counter() - start, "threads": 1}
    preset = tiny_train_params()
    batch, rays = int(preset["batch_size"]), int(preset["rays_per_image"])
    prims, t, config = _tiny_scene(batch)
    results["batches"] = []
    for scale in (1, 4, 16):
        ro, rd = _rays(t, batch, rays * scale)
        row = _compare_batch(prims, ro, rd, config.steps_per_ray, repeats=5 if scale < 16 else 3)
        results["batches"].append(row)
        print(f"{row['rays']:6d} rays x {row['steps']} steps: forward {row['torch']['forward_ms']:.1f} -> "
              f"{row['fused']['forward_ms']:.1f} ms, forward+backward {row['torch']['forward_backward_ms']:.1f} -> "
              f"{row['fused']['forward_backward_ms']:.1f} ms (x{row['forward_backward_speedup']:.2f}), saved for "
              f"backward {row['torch']['saved_for_backward_mb']:.1f} -> {row['fused']['saved_for_backward_mb']:.1f} "
              f"MB; max |image difference| {row['max_abs_image_difference']:.1e}, "
              f"gradients {row['max_rel_gradient_difference']:.1e}")
    # A trained head is mostly opaque (alice, ours, seed 0 after 5000 iterations: 70% of a training
    # batch's rays reach opacity 1), and the fused kernel stops each ray there. The initial head is
    # semi-transparent, so its densities are raised until the rays that cross it saturate (about 60%
    # of these uniformly drawn pixels; a training batch favours the foreground).
    ro, rd = _rays(t, batch, rays)
    opaque = Primitives(prims.centre, prims.rotation, prims.half_extent, prims.rgb,
                        prims.density.detach() * OPAQUE_DENSITY_FACTOR)
    row = _compare_batch(opaque, ro, rd, config.steps_per_ray, repeats=5)
    with torch.no_grad():
        row["saturated_ray_fraction"] = float((raymarch(opaque, ro, rd, config.steps_per_ray).alpha >= 1).float().mean())
    results["opaque_head"] = {"density_factor": OPAQUE_DENSITY_FACTOR, **row}
    print(f"opaque head (density x{OPAQUE_DENSITY_FACTOR:g}, {row['saturated_ray_fraction']:.0%} of rays saturate): "
          f"forward+backward {row['torch']['forward_backward_ms']:.1f} -> {row['fused']['forward_backward_ms']:.1f} ms "
          f"(x{row['forward_backward_speedup']:.2f}); max |image difference| {row['max_abs_image_difference']:.1e}")
    one = Primitives(*(x.detach()[:1] for x in (prims.centre, prims.rotation, prims.half_extent, prims.rgb,
                                                 prims.density)))
    ro, rd = (x[None] for x in t.image_rays(0, 0))
    image = {k: 1000 * _median_seconds(lambda k=k: raymarch(one, ro, rd, config.steps_per_ray, kernel=k), 5)
             for k in KERNELS}
    results["image"] = {"width_px": t.width, "height_px": t.height, "ms": image}
    print(f"one {t.width}x{t.height} image: {image['torch']:.1f} -> {image['fused']:.1f} ms")
    rates = _training_rates(batch, rays, iterations=15)
    results["training_iterations_per_second"] = rates
    print(f"tiny training step ({batch} x {rays} rays): {rates['torch']:.2f} -> {rates['fused']:.2f} it/s "
          f"(x{rates['fused'] / rates['torch']:.2f})")
    out = Path("bench-results")
    out.mkdir(exist_ok=True)
    (out / "raymarch.json").write_text(json.dumps(results, indent=1))
    return results


if __name__ == "__main__":
    main()
