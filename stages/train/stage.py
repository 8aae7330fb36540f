"""Train stage: the relightable MVP head (ours) and the TRAvatar* baseline, then held-out metrics.

Inputs: ``capture`` (OLAT images, manifest), ``stabilize`` (per-frame cam_from_head),
``track`` (head-space meshes, world_from_head poses), ``matte`` (alpha mattes) and
``lightcal`` (bar centres). Never ``capture.truth``.

Output:
    models/ours/, models/travatar/   ``model.safetensors`` + ``model.json`` (``avatar.io.load_trained``)
    splits.json                      held-out bars / take and the frames of every split
    learning_curve.png, curve.json   held-out (novel light) PSNR against training time
    tradeoffs/learning_curve.json    the same as a report trade-off series, the chosen configuration marked
    capacity.json                    the capacity rule's inputs (image size, head footprint, frames, expression modes) and choice
    table.md                         the paper's table (rows: splits; PSNR, MAE, SSIM, LPIPS per model)
    previews/<split>_<k>.png         ground truth | ours | TRAvatar*, sRGB
    tensorboard/                     loss terms and held-out PSNR
    metrics.json                     the required train keys are listed in docs/design.md (metrics)

The two models train one after another, or side by side in two threads of this process
(``parallel_models: 2``, ``stages.train.side_by_side``), to the same weights either way.

The learning curves and TensorBoard files hold wall-clock times: they are the stage's run
records (``Stage.run_records``), left out of the key relight and evaluate see, so a rerun
that trains the same models leaves them fresh.
"""

from __future__ import annotations

import hashlib
import json
import resource
import shutil
import sys
import time
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from pydantic import Field

from avatar.capacity import Capacity, CapacityInputError, CapacityRule, CaptureStats, choose_capacity, \
    count_expression_modes, footprint_from_mattes
from avatar.config import AvatarConfig
from avatar.layout import layout_for
from avatar.io import save_trained
from avatar.model import RelightableMVP, count_parameters
from avatar.raymarch import RaymarchKernel, resolve_kernel
from avatar.raymarch_fused import FusedKernelUnavailable
from avatar.travatar import LightBasis
from pipeline.devices import DeviceChoice, resolve_device
from pipeline.codedigest import modules_code_version
from pipeline.errors import ConfigError, InputError
from pipeline.stage import Stage, StageContext, StageParams
from stages.train.data import TrainData, load_train_data
from stages.train.evaluate import (SCALED_SPLITS, coverage_metrics, curve_png, eval_pairs, image_metrics,
                                   psnr_by_bar, results_table)
from stages.train.output import RUN_RECORDS, TrainOutput
from stages.train.splits import SPLITS, Splits, make_splits, nearest_training_distance_mm
from stages.train.side_by_side import train_models
from stages.train.trainer import LossWeights, ModelTrainer, Pruning, Renderer, TrainTensors


class TrainParams(StageParams):
    """Parameters of the train stage (defaults: the tiny, CPU-sized run)."""

    avatar: AvatarConfig = Field(default_factory=AvatarConfig.tiny,
                                 description="Model sizes (N, M, latent, channels, raymarch steps); see avatar.config. "
                                 "With capacity 'auto' the rule replaces N, M, the channel widths, the steps and the "
                                 "latent size.")
    capacity: Literal["auto", "fixed"] = Field(
        "fixed", description="'auto': primitives, voxels per primitive, channel widths, raymarch steps and latent "
        "size chosen from the capture (training image size, the head's footprint in the mattes, training frames, "
        "expression modes of the training meshes) by avatar.capacity; 'fixed': the avatar section as given.")
    capacity_rule: CapacityRule = Field(default_factory=CapacityRule,
                                        description="Constants of the capacity rule (capacity 'auto').")
    pruning: Pruning = Field(default_factory=Pruning,
                             description="When and how empty primitives are pruned; see stages.train.trainer.Pruning.")
    image_width_px: int = Field(64, ge=0, description="Training/evaluation image width in pixels (0 = the capture's).")
    max_frames: int = Field(0, ge=0, description="Use at most this many OLAT frames, evenly spread (0 = all).")
    resident_limit_gb: float = Field(8.0, ge=0, description="Training images and mattes larger than this (GB, "
                                     "float32) are memory-mapped from the stage's cache folder and gathered per "
                                     "batch instead of being held in RAM or on the GPU.")
    iterations: int = Field(2000, ge=1, description="Training iterations of our model.")
    baseline: bool = Field(True, description="Also train the TRAvatar* baseline on the same data.")
    baseline_iterations: int = Field(0, ge=0, description="Training iterations of TRAvatar* (0 = same as ours).")
    batch_size: int = Field(4, ge=1, description="Images per iteration (the paper: 12).")
    rays_per_image: int = Field(256, ge=1, description="Rays sampled per image per iteration (foreground-weighted).")
    lr: float = Field(1e-3, gt=0, description="Adam learning rate (the paper: 1e-4).")
    lr_decay_to: float = Field(0.1, gt=0, le=1, description="Final learning rate as a fraction of lr "
                               "(exponential decay over the run; 1 = constant, as the paper).")
    weight_average: float = Field(0.0, ge=0, lt=1, description="Decay per iteration of an exponential moving "
                                  "average of the weights, evaluated and saved instead of the last iterate (0 = "
                                  "the last iterate, as the paper; 0.998 averages over roughly the last 500 "
                                  "iterations). Both models alike. Leave it at 0 unless you are experimenting: on the "
                                  "tiny preset it cost ours on alice, whose encoder and decoders still move together "
                                  "late in training and no longer match once averaged apart (docs/experiments.md, "
                                  "section 1).")
    loss_weights: LossWeights = Field(default_factory=LossWeights,
                                      description="Weights of the loss terms (photometric, guide mesh, volume, KL, "
                                      "matte); see stages.train.trainer.LossWeights.")
    held_out_bars: int = Field(3, ge=1, description="Interior bars held out for the novel-light split.")
    held_out_take: str = Field("", description="Take whose final segment is the novel performance ('' = the last take).")
    held_out_fraction: float = Field(0.5, gt=0, le=1, description="Final fraction of that take held out (1 = all of it).")
    fit_frames: int = Field(0, ge=0, description="Diagnostic: optimise on only the first K training frames (all "
                            "their cameras; 0 = every training frame). With 1 it measures how well the model's "
                            "capacity can fit one frame in the iteration budget (train_psnr), an upper bound for "
                            "the held-out figures; the layout, light basis and capacity still come from every "
                            "training frame.")
    eval_images: int = Field(12, ge=1, description="Held-out images rendered per split for the metrics.")
    lpips: bool = Field(True, description="Compute LPIPS (AlexNet weights from assets/lpips).")
    curve_every: int = Field(100, ge=0, description="Iterations between learning-curve points (0 = none).")
    curve_images: int = Field(3, ge=1, description="Novel-light images per learning-curve point.")
    checkpoint_every: int = Field(50, ge=1, description="Iterations between checkpoints (resume after a kill).")
    spike_factor: float = Field(10.0, gt=1, description="A loss above this multiple of its running mean rolls back.")
    seed: int = Field(0, description="Seed of initialisation and sampling.")
    threads: int = Field(0, ge=0, description="torch CPU threads (0 = torch's default).")
    device: DeviceChoice = Field("auto", description="'auto' (CUDA if present), 'cpu' or 'cuda'.")
    raymarch_kernel: RaymarchKernel = Field(
        "auto", description="'fused': the C++ CPU raymarcher (avatar.raymarch_fused, built on first use, needs a C++ "
        "compiler; several times the training iterations/s of 'torch' on the CPU, docs/experiments.md, section 4); "
        "'torch': tensor ops (CPU or GPU); 'auto': fused on the CPU where a C++ compiler builds it, else torch with "
        "a warning. The same images either way, up to float rounding. Set 'fused' to fail instead of falling back.")
    previews: int = Field(2, ge=0, description="Preview images written per split.")
    parallel_models: int = Field(1, ge=1, description="Models (ours, TRAvatar*) trained at the same time, each in its "
                                 "own thread of this process: 2 trains both side by side, in about the time of one "
                                 "on a CPU with threads: 1 (stages.train.side_by_side); the same numbers as 1, which "
                                 "trains them one after another. Needs processes: 1.")
    processes: int = Field(1, ge=1, description="Data-parallel training processes (torch.distributed DDP, launched "
                           "with torchrun; gloo on CPU, nccl with one GPU per process). batch_size is the global "
                           "batch and must divide by it; 1 = train in the stage's own process.")


def _raymarch_kernel(name: RaymarchKernel, device: torch.device) -> RaymarchKernel:
    """The raymarcher this run uses, built now (not in the first iteration, whose time it would skew)."""
    try:
        return resolve_kernel(name, device, torch.float32)
    except (ValueError, FusedKernelUnavailable) as error:
        raise ConfigError(f"train.raymarch_kernel={name}: {error}") from error


def _run_key(params: TrainParams, inputs: dict[str, Path]) -> str:
    """Checkpoint folder key: params, input objects and the training code (so stale checkpoints are never resumed)."""
    # The process count is left out: every rank draws the same global batch, so a checkpoint
    # resumes with any number of processes.
    # Nor does training side by side change a model's iterations.
    # How the work is spread, and which raymarcher does it, change no more than float rounding.
    h = hashlib.sha256(params.model_dump_json(exclude={"processes", "parallel_models", "raymarch_kernel"}).encode())
    for name in sorted(inputs):
        h.update(f"{name}={Path(inputs[name]).resolve()}".encode())
    # The training code: this package and everything it imports (the same closure as the stage's digest).
    h.update(modules_code_version(("stages.train",)).digest.encode())
    return h.hexdigest()[:20]


def _tensors(data: TrainData, guide_ids: np.ndarray, device: torch.device) -> TrainTensors:
    """The training tensors; spilled (memory-mapped) images and mattes stay on the CPU and are gathered per batch."""
    f, c, h, w = data.mattes.shape

    def dev(x: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(x)).to(device)

    if data.spilled:
        images = torch.from_numpy(data.images.reshape(f, c, h * w, 3))  # no copy: pages read on demand
        mattes = torch.from_numpy(data.mattes.reshape(f, c, h * w))
    else:
        images, mattes = dev(data.images.reshape(f, c, h * w, 3)), dev(data.mattes.reshape(f, c, h * w))
    return TrainTensors(
        images=images, mattes=mattes, pixel_dirs=dev(data.pixel_dirs_cam), head_from_cam=dev(data.head_from_cam_rot),
        cam_pos=dev(data.cam_pos_head), light_pos=dev(data.light_pos_head), bar=dev(data.bar.astype(np.int64)),
        guide_vertices=dev(data.vertices[:, guide_ids]), height=h, width=w, device=device)


def _statistics_frames(train_frames: np.ndarray, limit: int = 64) -> np.ndarray:
    """At most ``limit`` training frames, evenly spread, for image statistics (all of them on small captures)."""
    if len(train_frames) <= limit:
        return train_frames
    return train_frames[np.linspace(0, len(train_frames) - 1, limit).round().astype(int)]


def _foreground_percentile(data: TrainData, frames: np.ndarray, q: float) -> float:
    """The ``q``-th percentile of the foreground (matte > 0.5) pixel values of ``frames``, one frame in memory at a time."""
    values = [np.asarray(data.images[i])[np.asarray(data.mattes[i]) > 0.5] for i in frames]
    foreground = np.concatenate(values) if values else np.zeros(0, np.float32)
    return float(np.percentile(foreground, q)) if foreground.size else 1.0


def bar_directions(data: TrainData) -> dict[int, np.ndarray]:
    """Each lit bar's mean head-space direction over its frames (the splits' and TRAvatar*'s light directions)."""
    dirs = {}
    for b in np.unique(data.bar):
        d = data.light_pos_head[data.bar == b]
        dirs[int(b)] = (d / np.linalg.norm(d, axis=-1, keepdims=True)).mean(0)
    return dirs


def exposure_of(data: TrainData, train_frames: np.ndarray) -> float:
    """The factor every image is scaled by: the 99.5th percentile of training foreground pixels goes to 1.

    OLAT images are dark (a single bar): scaled, losses are in a sane range and PSNR's peak (1)
    is the subject's brightest pixels, not an arbitrary unit.
    """
    return 1.0 / max(_foreground_percentile(data, _statistics_frames(train_frames), 99.5), 1e-12)


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
    if params.processes > 1 and params.parallel_models > 1:
        raise ConfigError(f"train.parallel_models={params.parallel_models} with train.processes={params.processes}: "
                          "a DDP run trains its models one after another; set train.parallel_models: 1")
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
    device = device or torch.device(resolve_device(params.device, "train.device"))
    kernel = _raymarch_kernel(params.raymarch_kernel, device)
    lead = rank == 0
    if lead:
        ctx.log.info("raymarcher: %s (train.raymarch_kernel=%s)", kernel, params.raymarch_kernel)
    inputs = {k: ctx.input(k) for k in ("capture", "stabilize", "track", "matte", "lightcal")}
    data = load_train_data(inputs, params.image_width_px, ctx.log, params.max_frames,
                           resident_limit_gb=params.resident_limit_gb, spill_dir=ctx.cache_dir / f"spill-rank{rank}")
    bar_dirs = bar_directions(data)
    splits = make_splits(data.take, data.bar, bar_dirs, params.held_out_bars, params.held_out_take,
                         params.held_out_fraction)
    train_frames = np.flatnonzero(splits.train)
    if len(train_frames) == 0:
        raise InputError("train: no training frames left after holding out "
                         f"bars {splits.held_out_bars} and take '{splits.held_out_take}'; capture more OLAT frames")
    if lead:
        _write_splits(TrainOutput(ctx.out).splits_path, data, splits)
    image_scale = exposure_of(data, train_frames)
    data.images *= image_scale  # in place (a spilled array is rescaled on disk, page by page)
    metrics_scale = {"image_scale": image_scale}
    ctx.log.info("splits: %s", {k: int(splits.mask(k).sum()) for k in ("train",) + SPLITS})
    capacity = capacity_of(data, train_frames, params)
    avatar = capacity.config if params.capacity == "auto" else params.avatar
    ctx.log.info("capacity (%s): %d primitives (N=%d) of %d^3 voxels, width %d, %d steps, latent %d; rule inputs: "
                 "%dx%d px, head %.1f px wide, %d training frames, %d expression modes", params.capacity,
                 avatar.num_prims, avatar.prims_per_side, avatar.voxels_per_side, avatar.base_channels,
                 avatar.steps_per_ray, avatar.latent_dim, capacity.stats.image_width_px,
                 capacity.stats.image_height_px, capacity.stats.footprint_px, capacity.stats.frames,
                 capacity.stats.expression_modes)
    if lead:
        _write_capacity(TrainOutput(ctx.out).capacity_path, params, capacity, avatar)
    mean_mesh = data.vertices[train_frames].mean(0)
    layout = layout_for(avatar, mean_mesh, data.triangles)
    tensors = _tensors(data, layout.guide_vertex_ids, device)
    basis_bars = sorted(int(b) for b in np.unique(data.bar[train_frames]))
    fitted_frames = train_frames[:params.fit_frames] if params.fit_frames else train_frames
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
    weights = params.loss_weights
    kinds = ["ours"] + (["travatar"] if params.baseline else [])
    curves, renders, metrics = {}, {}, ctx.metrics
    renderers, trainers = {}, {}
    for kind in kinds:
        config = avatar if kind == "ours" else avatar.model_copy(update={"light_basis": len(basis_bars)})
        torch.manual_seed(params.seed)
        model = RelightableMVP(config, layout, data.num_bars).to(device)
        renderer = renderers[kind] = Renderer(model, kind, basis if kind == "travatar" else None, basis_bars,
                                              kernel=kernel)

        def curve_fn(renderer: Renderer = renderer) -> float:
            if not curve_pairs:
                return float("nan")
            pred, _ = renderer.render_images(tensors, curve_pairs)
            return image_metrics(pred, _targets(tensors, curve_pairs), scale=True)["psnr"]

        iterations = params.iterations if kind == "ours" else (params.baseline_iterations or params.iterations)
        trainers[kind] = ModelTrainer(
            renderer, tensors, fitted_frames, iterations=iterations, batch_size=params.batch_size,
            rays_per_image=params.rays_per_image, lr=params.lr, weights=weights, seed=params.seed,
            ckpt_path=ckpt_dir / f"{kind}.pt", checkpoint_every=params.checkpoint_every,
            spike_factor=params.spike_factor, log=ctx.log, curve_every=params.curve_every,
            curve_fn=curve_fn if lead else None, writer=writer, lr_decay_to=params.lr_decay_to, rank=rank,
            world_size=world_size, prune=params.pruning.schedule(iterations),
            weight_average=params.weight_average)
        ctx.log.info("%s: %d parameters, %d primitives of %d^3 voxels", kind, count_parameters(model),
                     config.num_prims, config.voxels_per_side)
        metrics[f"{kind}_parameters"] = count_parameters(model)
    total = sum(t.iterations for t in trainers.values())
    if params.parallel_models > 1 and len(kinds) > 1:
        ctx.log.info("training %s side by side (train.parallel_models=%d)", " and ".join(kinds),
                     params.parallel_models)
    started = time.perf_counter()
    with ctx.progress(total, "it") as progress:
        states = train_models(trainers, progress, params.parallel_models)
    # Wall-clock time of the training: the models' own ``{kind}_seconds`` overlap when they train side by side.
    training_seconds = time.perf_counter() - started
    for kind in kinds:
        renderer, state = renderers[kind], states[kind]
        model, config = renderer.model, renderer.model.config
        curves[kind] = state.curve
        metrics[f"{kind}_iterations"] = state.iteration
        metrics[f"{kind}_seconds"] = state.train_seconds
        metrics[f"{kind}_rollbacks"] = state.rollbacks
        metrics[f"{kind}_pruned_primitives"] = model.num_pruned
        metrics[f"{kind}_primitives"] = config.num_prims
        model.eval()
        if not lead:
            continue  # the other ranks only train
        if kind == "ours":
            metrics.update(_prune_render_figures(renderer, tensors, pairs["novel_light"] or pairs["novel_perf"]))
        extra = {"image_scale": image_scale, "basis_bars": basis_bars, "basis_directions": np.stack([bar_dirs[b] for b in basis_bars]).tolist(),
                 "held_out_bars": list(splits.held_out_bars),
                 "bar_intensity": {int(b): float(torch.exp(model.log_bar_intensity[b]).detach()) for b in basis_bars}}
        save_trained(TrainOutput(ctx.out).model_dir(kind), model, kind, extra)
        # The fit on training images (seen frames, cameras and lights): next to the held-out
        # figures it tells underfitting (both low) from overfitting (a large gap).
        fit_pairs = eval_pairs(fitted_frames, num_cams, params.eval_images)
        pred, _ = renderer.render_images(tensors, fit_pairs)
        metrics[f"{kind}_train_psnr"] = image_metrics(pred, _targets(tensors, fit_pairs), scale=False)["psnr"]
        renders[kind] = {}
        for split in SPLITS:
            if not pairs[split]:
                ctx.log.warning("split %s is empty; no metrics for it", split)
                continue
            pred, alpha = renderer.render_images(tensors, pairs[split])
            target = _targets(tensors, pairs[split])
            scale = split in SCALED_SPLITS
            for name, value in image_metrics(pred, target, scale, lpips).items():
                metrics[f"{kind}_{split}_{name}"] = value
            if scale:
                bars = [int(tensors.bar[f]) for f, _ in pairs[split]]
                for bar, value in psnr_by_bar(pred, target, bars, scale).items():
                    metrics[f"{kind}_{split}_psnr_bar{bar}"] = value
            # The same PSNR with the capture's own units as peak (EXR value 1), for comparison
            # with figures computed on unnormalised linear images.
            metrics[f"{kind}_{split}_psnr_capture_units"] = (metrics[f"{kind}_{split}_psnr"]
                                                             + 20.0 * float(np.log10(image_scale)))
            if scale:
                pred = pred * _scales(pred, target)
            for name, value in coverage_metrics(pred, alpha, target, _mattes(tensors, pairs[split])).items():
                metrics[f"{kind}_{split}_{name}"] = value
            renders[kind][split] = pred
    if not lead:
        _drop_spill(ctx, rank, data)
        return
    metrics["iterations"] = metrics["ours_iterations"]
    metrics["seconds"] = training_seconds
    metrics["iterations_per_second"] = metrics["ours_iterations"] / max(metrics["ours_seconds"], 1e-9)
    metrics["peak_memory_mb"] = _peak_memory_mb(device)
    metrics["train_frames"] = int(len(train_frames))
    metrics["fitted_frames"] = int(len(fitted_frames))
    metrics.update(metrics_scale)
    metrics.update(expression_spread_metrics(data.vertices[:, layout.guide_vertex_ids], splits))
    metrics["image_width_px"] = int(tensors.width)
    metrics["pruned_primitives"] = metrics["ours_pruned_primitives"]
    metrics.update(capacity.as_metrics() if params.capacity == "auto" else _fixed_capacity_metrics(capacity, avatar))
    metrics["capacity_auto"] = int(params.capacity == "auto")
    metrics["capacity_parameters"] = metrics.get("ours_parameters", 0)
    if writer is not None:
        writer.close()
    out = TrainOutput(ctx.out)
    curve_png(out.curve_png_path, {("TRAvatar*" if k == "travatar" else k): v for k, v in curves.items()},
              f"held-out bars {list(splits.held_out_bars)}")
    out.curve_path.write_text(json.dumps(curves))
    _write_curve_tradeoff(out.curve_tradeoff_path, curves, avatar, params.capacity)
    table = results_table(metrics, kinds)
    out.table_path.write_text(table)
    ctx.log.info("results (linear RGB; novel-light predictions exposure-matched):\n%s", table)
    _write_previews(out.previews_dir, tensors, pairs, renders, params.previews)
    _drop_spill(ctx, rank, data)


def _drop_spill(ctx: StageContext, rank: int, data: TrainData) -> None:
    """Delete this rank's memory-mapped scratch copy of the images (rebuilt from the inputs by every run)."""
    if data.spilled:
        # Unlinking a mapped file is safe on POSIX; the pages go when the last mapping does.
        shutil.rmtree(ctx.cache_dir / f"spill-rank{rank}", ignore_errors=True)


def capacity_of(data: TrainData, train_frames: np.ndarray, params: TrainParams) -> Capacity:
    """The capacity rule applied to the training data (training resolution, training frames' mattes)."""
    _, _, height, width = data.mattes.shape
    modes = count_expression_modes(data.vertices[train_frames], params.capacity_rule.expression_variance)
    stats = CaptureStats(image_width_px=int(width), image_height_px=int(height),
                         footprint_px=footprint_from_mattes(data.mattes[_statistics_frames(train_frames)]),
                         frames=int(len(train_frames)), expression_modes=modes)
    try:
        return choose_capacity(stats, params.capacity_rule, params.avatar)
    except CapacityInputError as err:
        if params.capacity == "fixed":
            # The rule only reports in this mode; a capture it cannot read must not stop training.
            avatar = params.avatar
            return Capacity(config=avatar, stats=stats, texels_per_side=avatar.prims_per_side * avatar.voxels_per_side,
                            texel_px=float("nan"), voxel_px=float("nan"), layout_span_px=float("nan"),
                            width=avatar.base_channels)
        raise ConfigError(f"train.capacity=auto: {err}") from err


def _fixed_capacity_metrics(capacity: Capacity, avatar: AvatarConfig) -> dict[str, float]:
    """Metrics of a fixed configuration, beside what the rule would have chosen."""
    from avatar.capacity import texel_px, voxel_px

    texels = avatar.prims_per_side * avatar.voxels_per_side
    out = {"capacity_primitives": avatar.num_prims, "capacity_prims_per_side": avatar.prims_per_side,
           "capacity_voxel_res": avatar.voxels_per_side, "capacity_texels_per_side": texels,
           "capacity_width": avatar.base_channels, "capacity_steps_per_ray": avatar.steps_per_ray,
           "capacity_latent_dim": avatar.latent_dim, "capacity_expression_modes": capacity.stats.expression_modes,
           "capacity_image_width_px": capacity.stats.image_width_px,
           "capacity_image_height_px": capacity.stats.image_height_px,
           "capacity_footprint_px": capacity.stats.footprint_px, "capacity_frames": capacity.stats.frames}
    if capacity.stats.footprint_px > 0:
        out["capacity_texel_px"] = texel_px(texels, capacity.stats.footprint_px, avatar)
        out["capacity_voxel_px"] = voxel_px(texels, capacity.stats.footprint_px, avatar)
    if np.isfinite(capacity.texel_px):  # the rule could read the capture: what it would have chosen
        out["capacity_rule_texels_per_side"] = capacity.texels_per_side
        out["capacity_rule_latent_dim"] = capacity.config.latent_dim
    return out


def _write_capacity(path: Path, params: TrainParams, capacity: Capacity, avatar: AvatarConfig) -> None:
    stats = capacity.stats

    def finite(value: float) -> float | None:
        return float(value) if np.isfinite(value) else None

    path.write_text(json.dumps({
        "mode": params.capacity,
        "inputs": {"image_width_px": stats.image_width_px, "image_height_px": stats.image_height_px,
                   "footprint_px": stats.footprint_px, "frames": stats.frames,
                   "expression_modes": stats.expression_modes},
        "rule": params.capacity_rule.model_dump(mode="json"),
        "rule_choice": {"primitives": capacity.config.num_prims, "prims_per_side": capacity.config.prims_per_side,
                        "voxels_per_side": capacity.config.voxels_per_side,
                        "texels_per_side": capacity.texels_per_side, "texel_px": finite(capacity.texel_px),
                        "voxel_px": finite(capacity.voxel_px),
                        "width": capacity.width, "steps_per_ray": capacity.config.steps_per_ray,
                        "latent_dim": capacity.config.latent_dim},
        "used": avatar.model_dump(mode="json"),
    }, indent=1))


def _prune_render_figures(renderer: Renderer, t: TrainTensors, pairs: list[tuple[int, int]]) -> dict[str, float]:
    """Render time per image with and without the pruned primitives, and how much the images differ."""
    model = renderer.model
    pairs = pairs[:4]
    if not pairs:
        return {}
    keep = model.prim_keep.clone()

    def timed(pruned: bool) -> tuple[torch.Tensor, float]:
        model.prim_keep.copy_(keep if pruned else torch.ones_like(keep))
        start = time.perf_counter()
        images, _ = renderer.render_images(t, pairs)
        if images.is_cuda:
            torch.cuda.synchronize()
        return images, (time.perf_counter() - start) / len(pairs)

    try:
        renderer.render_images(t, pairs[:1])  # warm-up
        # Alternate and keep each one's best time: other load on the machine hits both alike.
        runs = [timed(pruned) for pruned in (True, False, True, False)]
    finally:
        model.prim_keep.copy_(keep)
    pruned_images, full_images = runs[0][0], runs[1][0]
    pruned_s, full_s = min(runs[0][1], runs[2][1]), min(runs[1][1], runs[3][1])
    from avatar.metrics import psnr

    agreement = float(psnr(pruned_images.clamp(0, 1), full_images.clamp(0, 1)).mean().clamp(max=100.0))
    return {"render_seconds_per_image": pruned_s, "render_seconds_per_image_unpruned": full_s,
            "prune_render_speedup": full_s / max(pruned_s, 1e-12), "prune_render_psnr_db": agreement}


def _write_curve_tradeoff(path: Path, curves: dict[str, list], avatar: AvatarConfig, mode: str) -> None:
    """The learning curves as a report trade-off series; the chosen configuration's final point is marked."""
    path.parent.mkdir(parents=True, exist_ok=True)
    label = f"N={avatar.prims_per_side} M={avatar.voxels_per_side} w={avatar.base_channels} ({mode})"
    points = []
    for kind, curve in curves.items():
        series = "TRAvatar*" if kind == "travatar" else f"ours, {label}"
        finite = [(p[0], p[1], p[2]) for p in curve if np.isfinite(p[2])]
        for i, (it, seconds, value) in enumerate(finite):
            last = i == len(finite) - 1
            point = {"x": float(seconds), "y": float(value), "series": series}
            if last and kind == "ours":
                point["chosen"] = True
                point["label"] = f"{it} it"
            points.append(point)
    path.write_text(json.dumps({"title": "Held-out PSNR (novel light) against training time",
                                "x_label": "training time (s)", "y_label": "held-out PSNR (dB)",
                                "points": points}, indent=1))


def _tensorboard_writer(ctx: StageContext):
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        ctx.log.warning("tensorboard is not installed; no TensorBoard logs")
        return None
    return SummaryWriter(str(TrainOutput(ctx.out).tensorboard_dir))


def _targets(t: TrainTensors, pairs: list[tuple[int, int]]) -> torch.Tensor:
    return torch.stack([t.image(f, c).view(t.height, t.width, 3) for f, c in pairs])


def _mattes(t: TrainTensors, pairs: list[tuple[int, int]]) -> torch.Tensor:
    return torch.stack([t.mattes[f, c].float().view(t.height, t.width) for f, c in pairs]).to(t.device)


def _scales(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    from avatar.metrics import exposure_scale

    return exposure_scale(pred, target)[:, None, None, None]


def expression_spread_metrics(guide_vertices: np.ndarray, splits: Splits) -> dict[str, float]:
    """How far each split's guide meshes are from the nearest training frame's (RMS vertex distance, mean over frames, mm).

    ``train_expression_spacing_mm`` is the training frames' distance to their nearest other
    training frame; ``{split}_expression_distance_mm`` over it is how far the split
    extrapolates in expression (1 = as close as training frames are to each other).
    """
    out = {"train_expression_spacing_mm": float(np.mean(nearest_training_distance_mm(
        guide_vertices, splits.train, splits.train)))} if splits.train.sum() > 1 else {}
    for split in SPLITS:
        if splits.mask(split).any():
            out[f"{split}_expression_distance_mm"] = float(np.mean(nearest_training_distance_mm(
                guide_vertices, splits.train, splits.mask(split))))
    return out


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
              run=run, doc=__doc__ or "",
              # Wall-clock records: two runs of the same deterministic training differ only here (and in
              # metrics.json), so relight and evaluate, which read the models, need not rerun.
              run_records=RUN_RECORDS)
