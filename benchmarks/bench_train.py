"""Training speed and memory of the relightable MVP head, tiny and paper configurations.

Figures: training iterations per second and peak memory (tiny preset's batch, and the
paper's configuration: on a GPU at batch 12, on a CPU a few iterations at batch 1), the
time to render one image, and on a CPU ours and TRAvatar* trained side by side against one
after another (``train.parallel_models``). The data are the rig's cameras around the ICT head
with random targets: speed does not depend on image content. Writes ``bench-results/train.json``.
Timings on a shared CPU are noisy.
"""

from __future__ import annotations

import json
import logging
import resource
import time
from pathlib import Path

import numpy as np
import torch

from avatar import render as avatar_render
from avatar.config import AvatarConfig
from avatar.layout import layout_for
from avatar.model import RelightableMVP
from scene.camera import Camera, look_at
from scene.face_rig import load_face_rig
from scene.rig import default_rig
from stages.train.trainer import LossWeights, ModelTrainer, Renderer, TrainTensors


def _tensors(width_px: int, frames: int, device: torch.device) -> tuple[TrainTensors, np.ndarray, np.ndarray]:
    rig, face = default_rig(), load_face_rig()
    verts = face.vertices()
    cams = []
    for spec in rig.cameras:
        cam = Camera(spec.name, rig.width_px, rig.height_px, spec.focal_px, spec.focal_px,
                     rig.width_px / 2 - 0.5, rig.height_px / 2 - 0.5,
                     pose=look_at(np.array(spec.position_m), np.array(spec.look_at_m)))
        cams.append(cam.scaled(width_px / rig.width_px))
    h, w = cams[0].height, cams[0].width
    # Pixel directions in each camera's frame, and the cameras' head_from_cam rotations.
    dirs = np.stack([c.pixel_rays(np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 2))[1]
                     @ c.cam_from_world.R.T for c in cams])  # [C, H*W, 3]
    rot = np.stack([c.cam_from_world.R.T for c in cams])[None].repeat(frames, 0)  # [F, C, 3, 3]
    g = torch.Generator().manual_seed(0)
    t = TrainTensors(
        images=torch.rand(frames, len(cams), h * w, 3, generator=g).to(device),
        mattes=torch.ones(frames, len(cams), h * w).to(device),
        pixel_dirs=torch.as_tensor(dirs, dtype=torch.float32, device=device),
        head_from_cam=torch.as_tensor(rot, dtype=torch.float32, device=device),
        cam_pos=torch.as_tensor(np.stack([c.center_world for c in cams]), dtype=torch.float32)[None]
        .expand(frames, -1, -1).contiguous().to(device),
        light_pos=torch.tensor([[0.5, 0.3, 1.0]]).expand(frames, -1).contiguous().to(device),
        bar=torch.zeros(frames, dtype=torch.long, device=device),
        guide_vertices=torch.zeros(0), height=h, width=w, device=device)
    return t, verts, face.triangles


def _trainer(renderer: Renderer, t: TrainTensors, iterations: int, batch: int, rays: int,
             ckpt_path: Path) -> ModelTrainer:
    """A trainer for speed runs: every frame of ``t``, no rollback, no checkpoint until the end."""
    return ModelTrainer(renderer, t, np.arange(int(t.bar.shape[0])), iterations=iterations, batch_size=batch,
                        rays_per_image=rays, lr=1e-4, weights=LossWeights(), seed=0, ckpt_path=ckpt_path,
                        checkpoint_every=10 ** 9, spike_factor=1e9, log=logging.getLogger("bench"))


def _measure(config: AvatarConfig, width_px: int, batch: int, rays: int, iterations: int,
             device: torch.device, render: bool = True) -> dict[str, float]:
    t, verts, tris = _tensors(width_px, 2, device)
    layout = layout_for(config, verts, tris)
    t.guide_vertices = torch.as_tensor(verts[layout.guide_vertex_ids])[None].expand(2, -1, -1).contiguous().to(device)
    torch.manual_seed(0)
    model = RelightableMVP(config, layout, num_bars=1).to(device)
    renderer = Renderer(model, "ours", None, [0])
    tr = _trainer(renderer, t, iterations, batch, rays, Path("/nonexistent"))
    tr.step()  # warm-up
    if device.type == "cuda":
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    start = time.perf_counter()
    for _ in range(iterations):
        tr.step()
    if device.type == "cuda":
        torch.cuda.synchronize()
    seconds = time.perf_counter() - start
    out = {"iterations_per_second": iterations / seconds, "batch": batch, "rays_per_image": rays,
           "peak_memory_mb": (torch.cuda.max_memory_allocated() / 2 ** 20 if device.type == "cuda"
                              else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)}
    if render:
        with torch.no_grad():
            start = time.perf_counter()
            image_rays = avatar_render.Rays(*t.image_rays(0, 0), t.cam_pos[0, 0], t.height, t.width)
            avatar_render.render(model, t.guide_vertices[:1], image_rays, avatar_render.PointLights(t.light_pos[:1]))
            if device.type == "cuda":
                torch.cuda.synchronize()
            out["render_seconds_per_image"] = time.perf_counter() - start
            out["render_width_px"], out["render_height_px"] = t.width, t.height
    return out


def _side_by_side(config: AvatarConfig, width_px: int, batch: int, rays: int, iterations: int) -> dict:
    """Ours and TRAvatar* trained one after another, then side by side (``train.parallel_models: 2``).

    Model iterations per second of each way, the speed-up, and whether both ways end with the
    same parameters (they must: each model has its own generator and optimiser).
    """
    import tempfile

    from avatar.travatar import LightBasis
    from pipeline.progress import SilentProgress
    from stages.train.side_by_side import train_models

    t, verts, tris = _tensors(width_px, 3, torch.device("cpu"))
    lights = np.array([[0.5, 0.3, 1.0], [-0.5, 0.3, 1.0], [0.0, -0.4, 1.0]], np.float32)
    t.light_pos, t.bar = torch.as_tensor(lights), torch.arange(3)
    layout = layout_for(config, verts, tris)
    t.guide_vertices = torch.as_tensor(verts[layout.guide_vertex_ids])[None].expand(3, -1, -1).contiguous()
    basis = LightBasis(lights / np.linalg.norm(lights, axis=1, keepdims=True))

    def run(parallel: int, folder: Path) -> tuple[float, list[torch.Tensor]]:
        trainers = {}
        for kind in ("ours", "travatar"):
            torch.manual_seed(0)
            model = RelightableMVP(config.model_copy(update={"light_basis": 3 if kind == "travatar" else 0}),
                                   layout, num_bars=3)
            renderer = Renderer(model, kind, basis if kind == "travatar" else None, [0, 1, 2])
            trainers[kind] = _trainer(renderer, t, iterations, batch, rays, folder / f"{kind}.pt")
        start = time.perf_counter()
        train_models(trainers, SilentProgress(), parallel)
        seconds = time.perf_counter() - start
        return seconds, [p.detach().clone() for tr in trainers.values() for p in tr.model.parameters()]

    with tempfile.TemporaryDirectory(prefix="bench-side-by-side-") as tmp:
        (Path(tmp) / "a").mkdir()
        (Path(tmp) / "b").mkdir()
        one_s, one_params = run(1, Path(tmp) / "a")
        two_s, two_params = run(2, Path(tmp) / "b")
    return {"iterations_per_model": iterations, "one_after_another_model_it_per_s": 2 * iterations / one_s,
            "side_by_side_model_it_per_s": 2 * iterations / two_s, "speedup": one_s / two_s,
            "same_parameters": all(torch.equal(a, b) for a, b in zip(one_params, two_params))}


def main() -> dict:
    cuda = torch.cuda.is_available()
    device = torch.device("cuda" if cuda else "cpu")
    if not cuda:
        # One intra-op thread: on a shared 2-core machine, OpenMP threads spinning at barriers
        # make multi-threaded small-tensor work many times slower, not faster.
        torch.set_num_threads(1)
    results: dict = {"device": torch.cuda.get_device_name() if cuda else "cpu",
                     "threads": torch.get_num_threads()}
    from benchmarks.train_runs import tiny_train_params

    preset = tiny_train_params()
    batch, rays = int(preset["batch_size"]), int(preset["rays_per_image"])
    tiny = _measure(AvatarConfig.tiny(), 64, batch=batch, rays=rays, iterations=10, device=device)
    results["tiny"] = tiny
    print(f"tiny  (N=16, M=4, the tiny preset's batch {batch} x {rays} rays, "
          f"{tiny['render_width_px']}x{tiny['render_height_px']} px): "
          f"{tiny['iterations_per_second']:.2f} it/s, peak {tiny['peak_memory_mb']:.0f} MB, "
          f"render {tiny['render_seconds_per_image'] * 1000:.0f} ms/image")
    if not cuda:
        both = _side_by_side(AvatarConfig.tiny(), 64, batch, rays, iterations=60)
        results["tiny_side_by_side"] = both
        print(f"tiny, ours and TRAvatar* ({both['iterations_per_model']} iterations each): "
              f"{both['one_after_another_model_it_per_s']:.2f} model-it/s one after another, "
              f"{both['side_by_side_model_it_per_s']:.2f} side by side (x{both['speedup']:.2f}), "
              f"same parameters: {both['same_parameters']}")
    if cuda:
        paper = _measure(AvatarConfig.paper(), 768, batch=12, rays=4096, iterations=10, device=device)
        note = "GPU, batch 12 (the paper: ~1.2 it/s on an A6000)"
    else:
        paper = _measure(AvatarConfig.paper(), 96, batch=1, rays=512, iterations=2, device=device, render=False)
        note = "CPU, batch 1 x 512 rays, 2 iterations only (the paper's batch 12 needs a GPU)"
    paper["note"] = note
    results["paper"] = paper
    print(f"paper (N=64, M=16, {note}): {paper['iterations_per_second']:.3f} it/s, "
          f"peak {paper['peak_memory_mb']:.0f} MB"
          + (f", render {paper['render_seconds_per_image']:.2f} s/image" if "render_seconds_per_image" in paper else ""))
    out = Path("bench-results")
    out.mkdir(exist_ok=True)
    (out / "train.json").write_text(json.dumps(results, indent=1))
    return results


if __name__ == "__main__":
    main()
