"""Train stage: the relightable MVP head (ours) and the TRAvatar* baseline, then held-out metrics.

Inputs: ``capture`` (OLAT images, manifest), ``stabilize`` (per-frame cam_from_head),
``track`` (head-space meshes, world_from_head poses), ``matte`` (alpha mattes) and
``lightcal`` (bar centres). Never ``capture.truth``.

Output:
    models/ours/, models/travatar/   ``model.safetensors`` + ``model.json`` (``avatar.io.load_trained``)
    splits.json                      held-out bars / take and the frames of every split
    learning_curve.png, curve.json   held-out (novel light) PSNR against training time
    table.md                         the paper's table (rows: splits; PSNR, MAE, SSIM, LPIPS per model)
    previews/<split>_<k>.png         ground truth | ours | TRAvatar*, sRGB
    tensorboard/                     loss terms and held-out PSNR
    metrics.json                     see METRICS.md (train)
"""

from __future__ import annotations

import hashlib
import json
import resource
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import Field

from avatar.config import AvatarConfig
from avatar.layout import build_layout
from avatar.io import save_trained
from avatar.model import RelightableMVP, count_parameters
from avatar.travatar import LightBasis
from pipeline.errors import ConfigError, InputError
from pipeline.stage import Stage, StageContext, StageParams
from stages.train.data import TrainData, load_train_data
from stages.train.evaluate import SCALED_SPLITS, curve_png, eval_pairs, image_metrics, results_table
from stages.train.splits import SPLITS, Splits, make_splits
from stages.train.trainer import LossWeights, ModelTrainer, Renderer, TrainTensors


class TrainParams(StageParams):
    """Parameters of the train stage (defaults: the tiny, CPU-sized run)."""

    avatar: AvatarConfig = Field(default_factory=AvatarConfig.tiny,
                                 description="Model sizes (N, M, latent, channels, raymarch steps); see avatar.config.")
    image_width_px: int = Field(64, ge=0, description="Training/evaluation image width in pixels (0 = the capture's).")
    max_frames: int = Field(0, ge=0, description="Use at most this many OLAT frames, evenly spread (0 = all).")
    iterations: int = Field(2000, ge=1, description="Training iterations of our model.")
    baseline: bool = Field(True, description="Also train the TRAvatar* baseline on the same data.")
    baseline_iterations: int = Field(0, ge=0, description="Training iterations of TRAvatar* (0 = same as ours).")
    batch_size: int = Field(4, ge=1, description="Images per iteration (the paper: 12).")
    rays_per_image: int = Field(256, ge=1, description="Rays sampled per image per iteration (foreground-weighted).")
    lr: float = Field(1e-3, gt=0, description="Adam learning rate (the paper: 1e-4).")
    lr_decay_to: float = Field(0.1, gt=0, le=1, description="Final learning rate as a fraction of lr "
                               "(exponential decay over the run; 1 = constant, as the paper).")
    pho_weight: float = Field(1.0, ge=0, description="Weight of the photometric (MSE) loss.")
    geo_weight: float = Field(0.1, ge=0, description="Weight of the guide-mesh loss (MSE, cm^2).")
    vol_weight: float = Field(0.01, ge=0, description="Weight of MVP's primitive volume prior.")
    kld_weight: float = Field(0.001, ge=0, description="Weight of the encoder's KL divergence.")
    mat_weight: float = Field(0.1, ge=0, description="Weight of the matte loss (L1, matte vs accumulated opacity).")
    held_out_bars: int = Field(3, ge=1, description="Interior bars held out for the novel-light split.")
    held_out_take: str = Field("", description="Take whose final segment is the novel performance ('' = the last take).")
    held_out_fraction: float = Field(0.5, gt=0, le=1, description="Final fraction of that take held out (1 = all of it).")
    eval_images: int = Field(12, ge=1, description="Held-out images rendered per split for the metrics.")
    lpips: bool = Field(True, description="Compute LPIPS (AlexNet weights from assets/lpips).")
    curve_every: int = Field(100, ge=0, description="Iterations between learning-curve points (0 = none).")
    curve_images: int = Field(3, ge=1, description="Novel-light images per learning-curve point.")
    checkpoint_every: int = Field(50, ge=1, description="Iterations between checkpoints (resume after a kill).")
    spike_factor: float = Field(10.0, gt=1, description="A loss above this multiple of its running mean rolls back.")
    seed: int = Field(0, description="Seed of initialisation and sampling.")
    threads: int = Field(0, ge=0, description="torch CPU threads (0 = torch's default).")
    device: str = Field("auto", description="'auto' (CUDA if present), 'cpu' or 'cuda'.")
    previews: int = Field(2, ge=0, description="Preview images written per split.")
    processes: int = Field(1, ge=1, description="Data-parallel training processes (torch.distributed DDP, launched "
                           "with torchrun; gloo on CPU, nccl with one GPU per process). batch_size is the global "
                           "batch and must divide by it; 1 = train in the stage's own process.")


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name not in ("cpu", "cuda") or (name == "cuda" and not torch.cuda.is_available()):
        raise ConfigError(f"train.device={name!r}: use 'auto', 'cpu' or 'cuda' (CUDA must be available)")
    return torch.device(name)


def _run_key(params: TrainParams, inputs: dict[str, Path]) -> str:
    """Checkpoint folder key: params, input objects and the training code (so stale checkpoints are never resumed)."""
    # The process count is left out: every rank draws the same global batch, so a checkpoint
    # resumes with any number of processes.
    h = hashlib.sha256(params.model_dump_json(exclude={"processes"}).encode())
    for name in sorted(inputs):
        h.update(f"{name}={Path(inputs[name]).resolve()}".encode())
    root = Path(__file__).resolve().parents[2]
    for path in sorted(list((root / "avatar").glob("*.py")) + list((root / "stages" / "train").glob("*.py"))):
        h.update(path.read_bytes())
    return h.hexdigest()[:20]


def _tensors(data: TrainData, guide_ids: np.ndarray, device: torch.device) -> TrainTensors:
    f, c, h, w = data.mattes.shape
    mattes = torch.from_numpy(data.mattes)
    dilated = F.max_pool2d(mattes.view(f * c, 1, h, w), 7, 1, 3).view(f, c, h * w)

    def dev(x: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(x)).to(device)

    return TrainTensors(
        images=dev(data.images.reshape(f, c, h * w, 3)), mattes=dev(data.mattes.reshape(f, c, h * w)),
        rays_o=dev(data.rays_o.reshape(f, c, h * w, 3)), rays_d=dev(data.rays_d.reshape(f, c, h * w, 3)),
        pixel_weights=(dilated + 0.1).contiguous(), cam_pos=dev(data.cam_pos_head),
        light_pos=dev(data.light_pos_head), bar=dev(data.bar.astype(np.int64)),
        guide_vertices=dev(data.vertices[:, guide_ids]), height=h, width=w)


def _peak_memory_mb(device: torch.device) -> float:
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2 ** 20
    rss_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss_kb / 1024.0 if sys.platform != "darwin" else rss_kb / 2 ** 20


def run(ctx: StageContext) -> None:
    params: TrainParams = ctx.params  # type: ignore[assignment]
    if params.batch_size % params.processes:
        raise ConfigError(f"train.batch_size={params.batch_size} does not divide by train.processes="
                          f"{params.processes}; every process takes an equal share of the global batch")
    if params.processes > 1:
        from stages.train.launch import launch_ddp

        launch_ddp(ctx)
        return
    train(ctx)


def train(ctx: StageContext, rank: int = 0, world_size: int = 1, device: torch.device | None = None) -> None:
    """The whole stage in this process; with ``world_size > 1`` one rank of a DDP run (rank 0 writes)."""
    params: TrainParams = ctx.params  # type: ignore[assignment]
    if params.threads:
        torch.set_num_threads(params.threads)
    device = device or _device(params.device)
    lead = rank == 0
    inputs = {k: ctx.input(k) for k in ("capture", "stabilize", "track", "matte", "lightcal")}
    data = load_train_data(inputs, params.image_width_px, ctx.log, params.max_frames)
    bar_dirs = {}
    for b in np.unique(data.bar):
        d = data.light_pos_head[data.bar == b]
        bar_dirs[int(b)] = (d / np.linalg.norm(d, axis=-1, keepdims=True)).mean(0)
    splits = make_splits(data.take, data.bar, bar_dirs, params.held_out_bars, params.held_out_take,
                         params.held_out_fraction)
    train_frames = np.flatnonzero(splits.train)
    if len(train_frames) == 0:
        raise InputError("train: no training frames left after holding out "
                         f"bars {splits.held_out_bars} and take '{splits.held_out_take}'; capture more OLAT frames")
    if lead:
        _write_splits(ctx.out / "splits.json", data, splits)
    # One global exposure for the data: OLAT images are dark (a single bar), so they are
    # scaled to put the 99.5th percentile of training foreground pixels at 1. Losses are in a
    # sane range and PSNR's peak (1) is the subject's brightest pixels, not an arbitrary unit.
    foreground = data.images[train_frames][data.mattes[train_frames] > 0.5]
    image_scale = 1.0 / max(float(np.percentile(foreground, 99.5)) if foreground.size else 1.0, 1e-12)
    data.images *= image_scale
    metrics_scale = {"image_scale": image_scale}
    ctx.log.info("splits: %s", {k: int(splits.mask(k).sum()) for k in ("train",) + SPLITS})
    mean_mesh = data.vertices[train_frames].mean(0)
    layout = build_layout(mean_mesh, data.triangles, params.avatar.prims_per_side,
                          params.avatar.layout_theta_deg, params.avatar.prim_overlap)
    tensors = _tensors(data, layout.guide_vertex_ids, device)
    basis_bars = sorted(int(b) for b in np.unique(data.bar[train_frames]))
    basis = LightBasis(np.stack([bar_dirs[b] for b in basis_bars]))
    num_cams = len(data.camera_names)
    pairs = {s: eval_pairs(np.flatnonzero(splits.mask(s)), num_cams, params.eval_images) for s in SPLITS}
    curve_pairs = pairs["novel_light"][:params.curve_images]
    lpips = None
    if params.lpips and lead:
        from avatar.lpips import LPIPS

        lpips = LPIPS().to(device)
    key = _run_key(params, inputs)
    ckpt_dir = ctx.cache_dir / key
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    writer = _tensorboard_writer(ctx) if lead else None
    weights = LossWeights(params.pho_weight, params.geo_weight, params.vol_weight, params.kld_weight, params.mat_weight)
    kinds = ["ours"] + (["travatar"] if params.baseline else [])
    curves, renders, metrics = {}, {}, ctx.metrics
    for kind in kinds:
        config = params.avatar if kind == "ours" else params.avatar.model_copy(update={"light_basis": len(basis_bars)})
        torch.manual_seed(params.seed)
        model = RelightableMVP(config, layout, data.num_bars).to(device)
        renderer = Renderer(model, kind, basis if kind == "travatar" else None, basis_bars)

        def curve_fn(renderer: Renderer = renderer) -> float:
            if not curve_pairs:
                return float("nan")
            pred, _ = renderer.render_images(tensors, curve_pairs)
            return image_metrics(pred, _targets(tensors, curve_pairs), scale=True)["psnr"]

        iterations = params.iterations if kind == "ours" else (params.baseline_iterations or params.iterations)
        trainer = ModelTrainer(renderer, tensors, train_frames, iterations=iterations, batch_size=params.batch_size,
                               rays_per_image=params.rays_per_image, lr=params.lr, weights=weights,
                               seed=params.seed, ckpt_path=ckpt_dir / f"{kind}.pt",
                               checkpoint_every=params.checkpoint_every, spike_factor=params.spike_factor,
                               log=ctx.log, curve_every=params.curve_every, curve_fn=curve_fn if lead else None,
                               writer=writer, lr_decay_to=params.lr_decay_to, rank=rank, world_size=world_size)
        ctx.log.info("%s: %d parameters, %d primitives of %d^3 voxels", kind, count_parameters(model),
                     config.num_prims, config.voxels_per_side)
        with ctx.progress(iterations, f"{kind} it") as progress:
            state = trainer.run(progress)
        curves[kind] = state.curve
        metrics[f"{kind}_iterations"] = state.iteration
        metrics[f"{kind}_seconds"] = state.train_seconds
        metrics[f"{kind}_rollbacks"] = state.rollbacks
        model.eval()
        if not lead:
            continue  # the other ranks only train
        extra = {"image_scale": image_scale, "basis_bars": basis_bars, "basis_directions": np.stack([bar_dirs[b] for b in basis_bars]).tolist(),
                 "held_out_bars": list(splits.held_out_bars),
                 "bar_intensity": {int(b): float(torch.exp(model.log_bar_intensity[b]).detach()) for b in basis_bars}}
        save_trained(ctx.out / "models" / kind, model, kind, extra)
        renders[kind] = {}
        for split in SPLITS:
            if not pairs[split]:
                ctx.log.warning("split %s is empty; no metrics for it", split)
                continue
            pred, _ = renderer.render_images(tensors, pairs[split])
            target = _targets(tensors, pairs[split])
            scale = split in SCALED_SPLITS
            for name, value in image_metrics(pred, target, scale, lpips).items():
                metrics[f"{kind}_{split}_{name}"] = value
            # The same PSNR with the capture's own units as peak (EXR value 1), for comparison
            # with figures computed on unnormalised linear images.
            metrics[f"{kind}_{split}_psnr_capture_units"] = (metrics[f"{kind}_{split}_psnr"]
                                                             + 20.0 * float(np.log10(image_scale)))
            if scale:
                pred = pred * _scales(pred, target)
            renders[kind][split] = pred
    if not lead:
        return
    metrics["iterations"] = metrics["ours_iterations"]
    metrics["seconds"] = sum(metrics[f"{k}_seconds"] for k in kinds)
    metrics["iterations_per_second"] = metrics["ours_iterations"] / max(metrics["ours_seconds"], 1e-9)
    metrics["peak_memory_mb"] = _peak_memory_mb(device)
    metrics["train_frames"] = int(len(train_frames))
    metrics.update(metrics_scale)
    metrics["image_width_px"] = int(tensors.width)
    if writer is not None:
        writer.close()
    curve_png(ctx.out / "learning_curve.png", {("TRAvatar*" if k == "travatar" else k): v for k, v in curves.items()},
              f"held-out bars {list(splits.held_out_bars)}")
    (ctx.out / "curve.json").write_text(json.dumps(curves))
    table = results_table(metrics, kinds)
    (ctx.out / "table.md").write_text(table)
    ctx.log.info("results (linear RGB; novel-light predictions exposure-matched):\n%s", table)
    _write_previews(ctx.out / "previews", tensors, pairs, renders, params.previews)


def _tensorboard_writer(ctx: StageContext):
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        ctx.log.warning("tensorboard is not installed; no TensorBoard logs")
        return None
    return SummaryWriter(str(ctx.out / "tensorboard"))


def _targets(t: TrainTensors, pairs: list[tuple[int, int]]) -> torch.Tensor:
    return torch.stack([t.images[f, c].view(t.height, t.width, 3) for f, c in pairs])


def _scales(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    from avatar.metrics import exposure_scale

    return exposure_scale(pred, target)[:, None, None, None]


def _write_splits(path: Path, data: TrainData, splits: Splits) -> None:
    path.write_text(json.dumps({
        "held_out_bars": list(splits.held_out_bars), "held_out_take": splits.held_out_take,
        **{name: data.frame_index[splits.mask(name)].tolist() for name in ("train",) + SPLITS}}, indent=1))


def _write_previews(folder: Path, t: TrainTensors, pairs: dict, renders: dict, count: int) -> None:
    from scene.image_io import write_png_srgb

    folder.mkdir(parents=True, exist_ok=True)
    for split, split_pairs in pairs.items():
        for k in range(min(count, len(split_pairs))):
            row = [_targets(t, [split_pairs[k]])[0]]
            row += [renders[m][split][k] for m in renders if split in renders[m]]
            write_png_srgb(folder / f"{split}_{k}.png", torch.cat(row, 1).clamp(min=0).cpu().numpy())


STAGE = Stage(name="train", inputs=("capture", "stabilize", "track", "matte", "lightcal"), params=TrainParams,
              run=run, code=("avatar",), doc=__doc__ or "")
