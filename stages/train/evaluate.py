"""Held-out evaluation: metrics per split and model, the learning curve and the results table."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from avatar.metrics import exposure_scale, mae, psnr, ssim

SPLIT_TITLES = {"novel_light": "novel light", "novel_perf": "novel performance", "novel_both": "both"}
#: The validation splits' rows of the results table, above the test splits'.
VAL_SPLIT_TITLES = {"val_light": "validation light", "val_perf": "validation performance"}
#: Splits with held-out lights, whose predictions are scaled to the ground truth's exposure.
SCALED_SPLITS = ("val_light", "novel_light", "novel_both")


def eval_pairs(frames: np.ndarray, num_cameras: int, count: int) -> list[tuple[int, int]]:
    """Up to ``count`` (frame, camera) pairs spread over a split's frames, cycling the cameras."""
    frames = np.asarray(frames)
    if len(frames) == 0 or count <= 0:
        return []
    pairs = [(int(f), int(c)) for f in frames for c in range(num_cameras)]
    pick = np.linspace(0, len(pairs) - 1, min(count, len(pairs))).round().astype(int)
    # Shift the camera of every pick so that the cameras vary even when frames are few.
    return [(pairs[i][0], (pairs[i][1] + k) % num_cameras) for k, i in enumerate(pick)]


def image_metrics(pred: torch.Tensor, target: torch.Tensor, scale: bool, lpips=None) -> dict[str, float]:
    """Mean PSNR / MAE / SSIM / LPIPS over images [K, H, W, 3] (linear RGB)."""
    if scale:
        pred = pred * exposure_scale(pred, target)[:, None, None, None]
    out = {"psnr": float(psnr(pred, target).mean()), "mae": float(mae(pred, target).mean()),
           "ssim": float(ssim(pred, target).mean())}
    if lpips is not None:
        out["lpips"] = float(lpips(pred, target).mean())
    return out


def psnr_by_bar(pred: torch.Tensor, target: torch.Tensor, bars: list[int], scale: bool) -> dict[int, float]:
    """Mean PSNR of each bar's images [K, H, W, 3] (``bars`` [K]: the bar that lit each image).

    On a held-out-light split this says which of the held-out lights the split's mean comes
    from: a bar whose images are brighter gives larger absolute errors for the same relative
    error, so the split's PSNR depends on which bars were held out, not only on the model.
    """
    if scale:
        pred = pred * exposure_scale(pred, target)[:, None, None, None]
    per_image = psnr(pred, target)
    ids = torch.as_tensor(bars)
    return {int(b): float(per_image[ids == b].mean()) for b in sorted(set(bars))}


def coverage_metrics(pred: torch.Tensor, alpha: torch.Tensor, target: torch.Tensor,
                     matte: torch.Tensor) -> dict[str, float]:
    """Where the head is in the capture but not in the render, over images [K, H, W(, 3)].

    ``pred`` and ``target`` are the linear RGB images (``pred`` at the target's exposure where
    the split scales), ``alpha`` the render's opacity and ``matte`` the capture's matte.
    ``uncovered_fraction``: share of the capture's foreground pixels (matte >= 0.5) that the
    model leaves transparent (opacity < 0.5), i.e. parts of the head the primitives' layout
    does not reach; ``uncovered_error_share``: share of the images' squared error on them.
    Together they tell how much of a split's PSNR the layout costs: what a better appearance
    model cannot win back.
    """
    foreground = matte >= 0.5
    uncovered = foreground & (alpha < 0.5)
    sq_error = ((pred - target) ** 2).sum(-1)
    total = float(sq_error.sum())
    return {"uncovered_fraction": float(uncovered.sum()) / max(int(foreground.sum()), 1),
            "uncovered_error_share": float(sq_error[uncovered].sum()) / total if total > 0 else 0.0}


def curve_png(path: Path, curves: dict[str, list], title: str) -> None:
    """Validation-light PSNR against training wall-clock time, one line per model."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    for name, points in curves.items():
        if points:
            pts = np.asarray(points, float)
            ax.plot(pts[:, 1], pts[:, 2], marker="o", ms=3, label=name)
    ax.set_xlabel("training time (s)")
    ax.set_ylabel("validation PSNR, held-out light (dB)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def results_table(metrics: dict[str, float], models: list[str]) -> str:
    """The paper's table: rows = splits (validation, then test), columns = PSNR / MAE / SSIM / LPIPS per model (Markdown)."""
    names = {"ours": "ours", "travatar": "TRAvatar*"}
    cols = ["psnr", "mae", "ssim", "lpips"]
    header = "| split | " + " | ".join(f"{names[m]} {c.upper()}" for m in models for c in cols) + " |"
    lines = [header, "|" + " --- |" * (1 + len(models) * len(cols))]
    for split, title in {**VAL_SPLIT_TITLES, **SPLIT_TITLES}.items():
        cells = []
        for m in models:
            for c in cols:
                v = metrics.get(f"{m}_{split}_{c}")
                cells.append("n/a" if v is None else (f"{v:.2f}" if c == "psnr" else f"{v:.4f}"))
        lines.append(f"| {title} | " + " | ".join(cells) + " |")
    if any(f"{m}_train_psnr" in metrics for m in models):
        # PSNR on training images: how well the run fits what it saw (the other columns are not computed).
        cells = []
        for m in models:
            v = metrics.get(f"{m}_train_psnr")
            cells += ["n/a" if v is None else f"{v:.2f}"] + ["-"] * (len(cols) - 1)
        lines.append("| training images (fit) | " + " | ".join(cells) + " |")
    lines += _expression_lines(metrics)
    by_bar = {m: sorted((int(k.rsplit("_bar", 1)[1]), v) for k, v in metrics.items()
                        if k.startswith(f"{m}_novel_light_psnr_bar")) for m in models}
    if all(by_bar.values()):
        # Which held-out lights the novel-light mean comes from (the bars differ by several dB).
        parts = "; ".join(f"{names[m]} " + ", ".join(f"bar {b} {v:.2f}" for b, v in by_bar[m]) for m in models)
        lines.append(f"\nNovel light per held-out bar (PSNR dB): {parts}.")
    coverage = [(names[m], title, metrics.get(f"{m}_{split}_uncovered_fraction"),
                 metrics.get(f"{m}_{split}_uncovered_error_share"))
                for m in models for split, title in SPLIT_TITLES.items()]
    if all(f is not None and e is not None for *_, f, e in coverage):
        # What the layout misses (the capture's foreground rendered transparent): no appearance model wins that back.
        parts = "; ".join(f"{name} {title} {100 * f:.1f}% ({100 * e:.0f}% of the error)"
                          for name, title, f, e in coverage)
        lines.append(f"\nForeground the model leaves transparent (share of the error there): {parts}.")
    return "\n".join(lines) + "\n"


def _per_split(metrics: dict, key: str) -> list[tuple[str, float]] | None:
    """``(title, metrics[f"{split}_{key}"])`` for every split, or None when a split lacks it."""
    values = [(title, metrics.get(f"{split}_{key}")) for split, title in SPLIT_TITLES.items()]
    return values if all(v is not None for _, v in values) else None


def _expression_lines(metrics: dict) -> list[str]:
    """The table's lines on how far the held-out expressions lie from the training ones."""
    lines = []
    spacing, distances = metrics.get("train_expression_spacing_mm"), _per_split(metrics, "expression_distance_mm")
    if spacing is not None and distances:
        # How far each split extrapolates in expression: a model that generalises poorly loses most where this is high.
        parts = ", ".join(f"{title} {d:.2f} mm ({d / max(spacing, 1e-12):.1f}x)" for title, d in distances)
        lines.append(f"\nHeld-out guide meshes to the nearest training mesh (RMS vertex distance): {parts}; "
                     f"training meshes are {spacing:.2f} mm from each other.")
    train_reach, reaches = metrics.get("train_expression_reach_sd"), _per_split(metrics, "expression_reach_sd")
    if train_reach is not None and reaches:
        # Near is not inside: a split beyond the training range asks the model to extrapolate.
        parts = ", ".join(f"{title} {r:.1f}" for title, r in reaches)
        lines.append(f"Along their most extreme expression mode, held-out meshes reach (median, training standard "
                     f"deviations from the training mean): {parts}; training meshes reach at most {train_reach:.1f}.")
    return lines
