"""The trained heads measured: validation and test metrics per split and model, and the run's summary figures.

Pure over the trained models, the setup and the params: renders and numbers, no files.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import torch

from avatar.capacity import Capacity
from avatar.config import AvatarConfig
from stages.train.assess_images import AssessImages
from stages.train.data import TrainData
from stages.train.evaluate import (
    SCALED_SPLITS,
    coverage_metrics,
    eval_pairs,
    image_metrics,
    psnr_by_bar,
)
from stages.train.fit import TrainedHeads
from stages.train.params import TrainParams
from stages.train.setup import TrainingSetup
from stages.train.splits import HELD_OUT_SPLITS, Splits, expression_reach_sd, nearest_training_distance_mm
from stages.train.trainer import Renderer


@dataclass
class HeldOutResults:
    """What the trained heads scored and rendered.

    Attributes:
        metrics: ``{kind}_train_psnr``, ``{kind}_{split}_{measure}`` (validation and test splits) and ours'
            render-time figures.
        renders: each kind's predictions [K, H, W, 3] per split (exposure-matched on the
            scaled splits), in the order of ``TrainingSetup.pairs``; the previews show them.
    """

    metrics: dict[str, float]
    renders: dict[str, dict[str, torch.Tensor]]


def assess_heads(heads: TrainedHeads, setup: TrainingSetup, params: TrainParams, lpips: torch.nn.Module | None,
                 log: logging.Logger) -> HeldOutResults:
    """Every kind's fit on its training images and its metrics on every validation and test split.

    The test splits are only measured here, at the end; nothing reads them to choose anything.
    """
    tensors, pairs, images = setup.tensors, setup.pairs, setup.assess
    metrics: dict[str, float] = {}
    renders: dict[str, dict[str, torch.Tensor]] = {}
    for kind in heads.kinds:
        renderer = heads.renderers[kind]
        if kind == "ours":
            # On validation images: the figures a pruning setting is judged by, never the test's.
            metrics.update(_prune_render_figures(renderer, images, pairs["val_light"] or pairs["val_perf"]))
        # The fit on training images (seen frames, cameras and lights): next to the held-out
        # figures it tells underfitting (both low) from overfitting (a large gap).
        fit_pairs = eval_pairs(setup.fitted_frames, setup.num_cams, params.eval_images)
        pred, _ = images.render(renderer, fit_pairs)
        metrics[f"{kind}_train_psnr"] = image_metrics(pred, images.targets(fit_pairs), scale=False)["psnr"]
        renders[kind] = {}
        for split in HELD_OUT_SPLITS:
            if not pairs[split]:
                log.warning("split %s is empty; no metrics for it", split)
                continue
            pred, alpha = images.render(renderer, pairs[split])
            target = images.targets(pairs[split])
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
                                                             + 20.0 * float(np.log10(setup.image_scale)))
            if scale:
                pred = pred * _scales(pred, target)
            for name, value in coverage_metrics(pred, alpha, target, images.mattes(pairs[split])).items():
                metrics[f"{kind}_{split}_{name}"] = value
            renders[kind][split] = pred
    return HeldOutResults(metrics=metrics, renders=renders)


def run_metrics(heads: TrainedHeads, setup: TrainingSetup, data: TrainData, params: TrainParams) -> dict[str, float]:
    """The run's summary figures: speed, data sizes, expression spread and capacity."""
    ours = heads.states["ours"]
    metrics: dict[str, float] = {
        "iterations": ours.iteration, "seconds": heads.training_seconds,
        "iterations_per_second": ours.iteration / max(ours.train_seconds, 1e-9),
        "train_frames": len(setup.train_frames), "fitted_frames": len(setup.fitted_frames),
        "image_scale": setup.image_scale}
    metrics.update(expression_spread_metrics(data.vertices[:, setup.layout.guide_vertex_ids], setup.splits,
                                             params.capacity_rule.expression_variance))
    metrics["image_width_px"] = int(setup.tensors.width)
    metrics["assess_width_px"] = int(setup.assess.width)
    metrics["images_memory_mapped"] = int(data.spilled)
    metrics["pruned_primitives"] = heads.renderers["ours"].model.num_pruned
    metrics.update(setup.capacity.as_metrics() if params.capacity == "auto"
                   else _fixed_capacity_metrics(setup.capacity, setup.avatar))
    metrics["capacity_auto"] = int(params.capacity == "auto")
    metrics["capacity_parameters"] = heads.parameters.get("ours", 0)
    return metrics


def expression_spread_metrics(guide_vertices: np.ndarray, splits: Splits, variance: float = 0.999) -> dict[str, float]:
    """How far each split's guide meshes lie from the training frames' expressions.

    ``train_expression_spacing_mm`` is the training frames' distance to their nearest other
    training frame; ``{split}_expression_distance_mm`` (RMS vertex distance to the nearest
    training mesh, mean over frames, mm) over it is how far the split lies from the training
    expressions (1 = as close as training frames are to each other).
    ``{split}_expression_reach_sd`` (median over frames of ``expression_reach_sd``, the modes
    holding ``variance``) against ``train_expression_reach_sd`` (the largest over training
    frames: the edge of their range) says whether it lies beyond them: above it, the split
    asks the networks to extrapolate.
    """
    out = {}
    if splits.train.sum() > 1:
        out["train_expression_spacing_mm"] = float(np.mean(nearest_training_distance_mm(
            guide_vertices, splits.train, splits.train)))
        out["train_expression_reach_sd"] = float(np.max(expression_reach_sd(
            guide_vertices, splits.train, splits.train, variance)))
    for split in HELD_OUT_SPLITS:
        if splits.mask(split).any():
            out[f"{split}_expression_distance_mm"] = float(np.mean(nearest_training_distance_mm(
                guide_vertices, splits.train, splits.mask(split))))
            if splits.train.sum() > 1:
                out[f"{split}_expression_reach_sd"] = float(np.median(expression_reach_sd(
                    guide_vertices, splits.train, splits.mask(split), variance)))
    return out


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


def _prune_render_figures(renderer: Renderer, images: AssessImages, pairs: list[tuple[int, int]]) -> dict[str, float]:
    """Render time per image with and without the pruned primitives, and how much the images differ."""
    model = renderer.model
    pairs = pairs[:4]
    if not pairs:
        return {}
    keep = model.prim_keep.clone()

    def timed(pruned: bool) -> tuple[torch.Tensor, float]:
        model.prim_keep.copy_(keep if pruned else torch.ones_like(keep))
        start = time.perf_counter()
        rgb, _ = images.render(renderer, pairs)
        if rgb.is_cuda:
            torch.cuda.synchronize()
        return rgb, (time.perf_counter() - start) / len(pairs)

    try:
        images.render(renderer, pairs[:1])  # warm-up
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


def _scales(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    from avatar.metrics import exposure_scale

    return exposure_scale(pred, target)[:, None, None, None]
