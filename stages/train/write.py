"""Write a finished run into the train stage's output folder (``stages.train.output.TrainOutput``)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import torch

from avatar.capacity import Capacity
from avatar.config import AvatarConfig
from avatar.io import save_trained
from stages.train.assess import HeldOutResults
from stages.train.assess_images import AssessImages
from stages.train.data import TrainData
from stages.train.evaluate import curve_png, results_table
from stages.train.fit import TrainedHeads
from stages.train.output import TrainOutput
from stages.train.params import TrainParams
from stages.train.setup import TrainingSetup
from stages.train.splits import ALL_SPLITS, SPLITS, Splits


def write_train_outputs(out: TrainOutput, data: TrainData, setup: TrainingSetup, heads: TrainedHeads,
                        results: HeldOutResults, metrics: dict[str, float], params: TrainParams,
                        log: logging.Logger, inputs: dict[str, Path] | None = None) -> None:
    """The splits, capacity report, models, learning curves, results table and previews of a run."""
    splits, avatar = setup.splits, setup.avatar
    _write_splits(out.splits_path, data, splits)
    _write_capacity(out.capacity_path, params, setup.capacity, avatar)
    for kind in heads.kinds:
        model = heads.renderers[kind].model
        extra = {"image_scale": setup.image_scale, "basis_bars": setup.basis_bars,
                 "basis_directions": np.stack([setup.bar_dirs[b] for b in setup.basis_bars]).tolist(),
                 "held_out_bars": list(splits.held_out_bars), "val_bars": list(splits.val_bars),
                 "bar_intensity": {int(b): float(torch.exp(model.log_bar_intensity[b]).detach())
                                   for b in setup.basis_bars}}
        save_trained(out.model_dir(kind), model, kind, extra)
    curves = {kind: heads.states[kind].curve for kind in heads.kinds}
    curve_png(out.curve_png_path, {("TRAvatar*" if k == "travatar" else k): v for k, v in curves.items()},
              f"validation bars {list(splits.val_bars)}")
    out.curve_path.write_text(json.dumps(curves))
    _write_curve_tradeoff(out.curve_tradeoff_path, curves, avatar, params.capacity)
    table = results_table(metrics, heads.kinds)
    out.table_path.write_text(table)
    log.info("results (linear RGB; predictions under held-out lights exposure-matched):\n%s", table)
    # Previews of the test splits only, as before the validation split (the report shows them).
    test_pairs = {split: setup.pairs[split] for split in SPLITS}
    _write_previews(out.previews_dir, setup.assess, test_pairs, results.renders, params.previews)
    if inputs is not None:  # the capture's full-size images, for the comparison figures
        from stages.train.comparisons import write_comparisons

        write_comparisons(out.comparisons_dir, inputs, data, setup, heads, params.previews, log,
                          height_px=params.figure_height_px)


def _write_splits(path: Path, data: TrainData, splits: Splits) -> None:
    """The test's and validation's bars and segments, and the frame indices of every split (``ALL_SPLITS``)."""
    path.write_text(json.dumps({
        "held_out_bars": list(splits.held_out_bars), "held_out_take": splits.held_out_take,
        "val_bars": list(splits.val_bars), "val_segment": splits.val_segment,
        **{name: data.frame_index[splits.mask(name)].tolist() for name in ALL_SPLITS}}, indent=1))


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
    path.write_text(json.dumps({"title": "Validation PSNR (held-out light) against training time",
                                "x_label": "training time (s)", "y_label": "validation PSNR (dB)",
                                "points": points}, indent=1))


def _write_previews(folder: Path, images: AssessImages, pairs: dict[str, list[tuple[int, int]]],
                    renders: dict[str, dict[str, torch.Tensor]], count: int) -> None:
    from scene.image_io import write_png_srgb

    folder.mkdir(parents=True, exist_ok=True)
    for split, split_pairs in pairs.items():
        for k in range(min(count, len(split_pairs))):
            row = [images.targets([split_pairs[k]])[0]]
            row += [renders[m][split][k] for m in renders if split in renders[m]]
            write_png_srgb(folder / f"{split}_{k}.png", torch.cat(row, 1).clamp(min=0).cpu().numpy())
