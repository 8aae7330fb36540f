"""Where one training run loses against another of the same inputs: per image, per pixel, per opacity.

Two seeds of the same settings can end a dB or more apart (docs/experiments.md, sections 19-34).
This renders both runs' heads for the same images (a sample of the training images and both
validation splits; never a test split) and says whether the gap is spread over the image or sits
in a few pixels, and there whether the losing head is transparent where the capture's head is
solid (a hole) or opaque with the wrong colour:

    PIPELINE_WORKSPACES=<root> python -m benchmarks.where_runs_differ RUN_A RUN_B [-S bob] [--png out.png]

``RUN_A`` and ``RUN_B`` are train-stage output folders (``models/ours``, ``metrics.json``; the
seed bench's ``bench-seeds-*`` scratch folders are removed, so train them with
``pipeline.scratch.run_stage_in_folder`` or take two workspaces' ``train`` outputs). Both must
have been trained on the subject's current train inputs (the same digest).
"""

from __future__ import annotations

import argparse
import logging
import tempfile
from pathlib import Path

import numpy as np
import torch

from avatar.io import load_trained
from avatar.metrics import exposure_scale, psnr
from avatar.model import share_below_floor
from stages.train.evaluate import SCALED_SPLITS, eval_pairs
from stages.train.output import TrainOutput
from stages.train.setup import TrainingSetup
from stages.train.trainer import Renderer

log = logging.getLogger("bench.where_runs_differ")

#: The sets compared: a sample of the training images and the validation splits (the test splits choose nothing).
SETS = ("train", "val_light", "val_perf")


def _renders(run: Path, kind: str, setup: TrainingSetup, pairs: dict[str, list], kernel) -> tuple[dict, float]:
    """Each set's (prediction, opacity) of ``run``'s ``kind`` head, and its share of opacity logits under the floor."""
    model, _ = TrainOutput(run).model(lambda folder: load_trained(folder, "cpu"), kind)
    renderer = Renderer(model, kind, setup.basis if kind == "travatar" else None, setup.basis_bars, kernel)
    out = {name: setup.assess.render(renderer, p) for name, p in pairs.items()}
    return out, share_below_floor(model)


def compare_runs(run_a: Path, run_b: Path, setup: TrainingSetup, kernel, kind: str = "ours",
                 train_images: int = 48) -> dict:
    """Per set: both runs' mean PSNR, B - A per image, where A's excess error sits, and A's and B's opacity there.

    ``a_excess_top1pct_share``: the part of A's excess squared error (A's minus B's, summed over
    the set) held by the 1% of pixels where that excess is largest; near or above 1 means the gap
    is a few pixels' (a hole, a misplaced patch), near 0.01 that it is spread evenly.
    ``a_alpha_top1pct`` / ``b_alpha_top1pct``: each head's mean opacity over those pixels.
    """
    pairs = {"train": eval_pairs(setup.fitted_frames, setup.num_cams, train_images),
             "val_light": setup.pairs["val_light"], "val_perf": setup.pairs["val_perf"]}
    pairs = {k: v for k, v in pairs.items() if v}
    renders_a, floor_a = _renders(run_a, kind, setup, pairs, kernel)
    renders_b, floor_b = _renders(run_b, kind, setup, pairs, kernel)
    result: dict = {"a_opacity_logits_below_floor": floor_a, "b_opacity_logits_below_floor": floor_b, "sets": {}}
    for name, set_pairs in pairs.items():
        target = setup.assess.targets(set_pairs)
        (pred_a, alpha_a), (pred_b, alpha_b) = renders_a[name], renders_b[name]
        if name in SCALED_SPLITS:  # as the train stage measures a held-out light: at the image's exposure
            pred_a = pred_a * exposure_scale(pred_a, target)[:, None, None, None]
            pred_b = pred_b * exposure_scale(pred_b, target)[:, None, None, None]
        psnr_a, psnr_b = psnr(pred_a, target).numpy(), psnr(pred_b, target).numpy()
        excess = (((pred_a - target) ** 2).sum(-1) - ((pred_b - target) ** 2).sum(-1)).flatten()
        top = torch.topk(excess, max(1, excess.numel() // 100)).indices
        total = float(excess.sum())
        diff = psnr_b - psnr_a
        result["sets"][name] = {
            "images": len(set_pairs), "a_psnr": float(psnr_a.mean()), "b_psnr": float(psnr_b.mean()),
            "b_minus_a_mean": float(diff.mean()), "b_minus_a_min": float(diff.min()),
            "b_minus_a_max": float(diff.max()),
            "a_excess_top1pct_share": float(excess[top].sum()) / total if total > 0 else float("nan"),
            "a_alpha_top1pct": float(alpha_a.flatten()[top].mean()),
            "b_alpha_top1pct": float(alpha_b.flatten()[top].mean()),
            "worst_image_for_a": int(np.argmax(diff)),
            "_images": (target, pred_a, pred_b)}
    return result


def mosaic(target: torch.Tensor, pred_a: torch.Tensor, pred_b: torch.Tensor, index: int) -> np.ndarray:
    """One row, 8-bit sRGB-ish: target | A | B | where A's squared error exceeds B's (red) or falls short (blue)."""
    peak = max(float(torch.quantile(target.flatten(), 0.995)), 1e-6)

    def tone(image: torch.Tensor) -> np.ndarray:
        return (np.clip(image.numpy() / peak, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)

    t, a, b = target[index], pred_a[index], pred_b[index]
    excess = (((a - t) ** 2).sum(-1) - ((b - t) ** 2).sum(-1)).numpy()
    scale = max(float(np.abs(excess).max()), 1e-12)
    e = excess / scale
    heat = (np.stack([np.clip(e, 0, 1), np.zeros_like(e), np.clip(-e, 0, 1)], -1) * 255).astype(np.uint8)
    return np.concatenate([tone(t), tone(a), tone(b), heat], 1)


def main(argv: list[str] | None = None) -> dict:
    from benchmarks.cross_build import _check_same_frames
    from benchmarks.train_runs import tiny_train_params, train_inputs
    from stages.train.data import load_train_data
    from stages.train.setup import prepare_training
    from stages.train.stage import STAGE

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_a", type=Path, help="a train-stage output folder")
    parser.add_argument("run_b", type=Path, help="another, trained on the same inputs")
    parser.add_argument("-S", "--subject", default="alice", help="the subject whose train inputs both runs used")
    parser.add_argument("--kind", default="ours", choices=("ours", "travatar"), help="which head to compare")
    parser.add_argument("--png", type=Path, help="write target | A | B | excess error of each set's most different image")
    args = parser.parse_args(argv)
    # The benches' settings: the tiny preset's (the splits and image size follow from them).
    params = STAGE.params(**{**tiny_train_params(), "lpips": False})
    with tempfile.TemporaryDirectory(prefix="where-runs-differ-") as scratch:
        inputs, source = train_inputs(args.subject, Path(scratch))
        data = load_train_data({k: Path(v) for k, v in inputs.items()}, params.image_width_px, log,
                               params.max_frames, resident_limit_gb=params.resident_limit_gb)
    setup = prepare_training(data, params, torch.device("cpu"), log)
    for run in (args.run_a, args.run_b):  # both runs must have been asked the same questions
        _check_same_frames(TrainOutput(run).splits(), setup, data.frame_index)
    result = compare_runs(args.run_a, args.run_b, setup, params.raymarch_kernel, args.kind)
    print(f"{args.kind}, {source}: opacity logits under the floor: A {result['a_opacity_logits_below_floor']:.3f}, "
          f"B {result['b_opacity_logits_below_floor']:.3f}")
    rows = []
    for name, r in result["sets"].items():
        print(f"{name:<10} {r['images']:3d} images  A {r['a_psnr']:.2f}  B {r['b_psnr']:.2f}  B - A per image "
              f"{r['b_minus_a_mean']:+.2f} [{r['b_minus_a_min']:+.2f}, {r['b_minus_a_max']:+.2f}]  top 1% of pixels "
              f"hold {r['a_excess_top1pct_share']:.2f} of A's excess error; opacity there A "
              f"{r['a_alpha_top1pct']:.2f}, B {r['b_alpha_top1pct']:.2f}")
        rows.append(mosaic(*r.pop("_images"), r["worst_image_for_a"]))
    if args.png:
        from PIL import Image

        Image.fromarray(np.concatenate(rows, 0)).save(args.png)
        print(f"wrote {args.png}")
    return result


if __name__ == "__main__":
    main()
