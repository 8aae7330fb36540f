"""The comparison figure: ground truth | each prediction | each prediction's per-pixel error, with a colour bar.

The paper's comparison figure, as a PNG a report embeds: one row per example, the images in
sRGB at one exposure per row, the errors as heat maps on one shared scale (so the models can
be compared cell by cell) with the colour bar beside them. An error is the per-pixel mean over
RGB of ``|prediction - truth|``, as a fraction of the truth's white (its 99th-percentile
foreground pixel), the normalisation the PSNR figures use.

Rows smaller than ``min_height_px`` are drawn larger (bilinear), so that every picture is
at least that tall on the page; callers that can render larger (the volumetric head renders
at any resolution) should, and say so.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scene.colour import srgb_encode


@dataclass
class ComparisonRow:
    """One example: the truth and the predictions (linear RGB [H, W, 3], same size), and its label in words."""

    label: str
    truth: np.ndarray
    predictions: dict[str, np.ndarray]
    truth_alpha: np.ndarray | None = None  # [H, W]: where the white is measured (all pixels when None)
    notes: dict[str, str] = field(default_factory=dict)  # per prediction, e.g. its PSNR, shown under its image


def white_level(truth: np.ndarray, alpha: np.ndarray | None = None) -> float:
    """The truth's 99th-percentile luminance over its foreground (all pixels without ``alpha``)."""
    lum = np.asarray(truth, np.float64).mean(-1)
    values = lum[alpha > 0.5] if alpha is not None and (alpha > 0.5).any() else lum.reshape(-1)
    return max(float(np.percentile(values, 99)), 1e-8)


def error_map(prediction: np.ndarray, truth: np.ndarray, white: float) -> np.ndarray:
    """Per-pixel mean over RGB of ``|prediction - truth|`` / ``white``, [H, W]."""
    return np.abs(np.asarray(prediction, np.float64) - np.asarray(truth, np.float64)).mean(-1) / white


def write_comparison_figure(path: str | Path, rows: list[ComparisonRow], title: str, min_height_px: int = 256,
                            dpi: int = 100) -> float:
    """Write the figure; returns the error scale's top (the colour bar's maximum)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not rows:
        raise ValueError(f"{path}: a comparison figure needs at least one row")
    names = list(rows[0].predictions)
    whites = [white_level(r.truth, r.truth_alpha) for r in rows]
    errors = [[error_map(r.predictions[n], r.truth, w) for n in names] for r, w in zip(rows, whites)]
    every = np.concatenate([e.reshape(-1) for row in errors for e in row])
    top = max(float(np.percentile(every, 99.5)), 1e-3)
    h, w = rows[0].truth.shape[:2]
    cell_h = max(min_height_px, h) / dpi  # inches
    cell_w = cell_h * w / h
    columns = 1 + 2 * len(names)
    fig, axes = plt.subplots(len(rows), columns, squeeze=False, dpi=dpi, layout="constrained",
                             figsize=(columns * cell_w + 1.2, len(rows) * (cell_h + 0.45) + 0.5))
    heat = None
    for i, (row, white, row_errors) in enumerate(zip(rows, whites, errors)):
        exposure = 0.8 / white

        def shown(image: np.ndarray, exposure: float = exposure) -> np.ndarray:
            return srgb_encode(np.clip(np.asarray(image, np.float32) * exposure, 0.0, 1.0))

        cells = [("ground truth", shown(row.truth), None)]
        cells += [(n, shown(row.predictions[n]), row.notes.get(n)) for n in names]
        for ax, (label, image, note) in zip(axes[i], cells):
            ax.imshow(image, interpolation="bilinear")
            ax.set_title(label if note is None else f"{label}\n{note}", fontsize=8)
        for ax, n, err in zip(axes[i][1 + len(names):], names, row_errors):
            heat = ax.imshow(err, cmap="inferno", vmin=0.0, vmax=top, interpolation="bilinear")
            ax.set_title(f"{n}: error", fontsize=8)
        axes[i][0].set_ylabel(row.label, fontsize=8)
        for ax in axes[i]:
            ax.set_xticks([])
            ax.set_yticks([])
    bar = fig.colorbar(heat, ax=axes.ravel().tolist(), fraction=0.025, pad=0.01)
    bar.set_label("|error| / white (mean over RGB)", fontsize=8)
    bar.ax.tick_params(labelsize=7)
    fig.suptitle(title, fontsize=9)
    # Titles and the colour bar take room from the cells: grow the figure until a cell is tall enough.
    for _ in range(3):
        fig.canvas.draw()
        shown_px = axes[0][0].get_window_extent().height
        if shown_px >= min_height_px:
            break
        fig.set_size_inches(*(fig.get_size_inches() * (1.02 * min_height_px / shown_px)))
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return top


__all__ = ["ComparisonRow", "error_map", "white_level", "write_comparison_figure"]
