"""The evaluate stage's figures: sweep curves (PNG) and the report's trade-off series (JSON)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (backend chosen first, on purpose)
import numpy as np  # noqa: E402

from stages.evaluate.sweeps import Crossing  # noqa: E402


def write_series(path: Path, title: str, x_label: str, y_label: str, points: Sequence[dict]) -> None:
    """A ``tradeoffs/<name>.json`` series the report draws as a chart (``chosen`` points marked)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    clean = [{k: (float(v) if k in ("x", "y") else v) for k, v in p.items()} for p in points]
    path.write_text(json.dumps({"title": title, "x_label": x_label, "y_label": y_label, "points": clean},
                               indent=1) + "\n", encoding="utf-8")


def _limit_label(c: Crossing, unit: str) -> str:
    if c.censored:
        return f"holds to {c.x:.3g}{unit} (end of sweep)"
    if c.failed_at_start:
        return f"under threshold already at {c.x:.3g}{unit}"
    return f"breaks at {c.x:.3g}{unit}"


def light_orbit_png(path: Path, orbits: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]],
                    threshold_db: float, limit: Crossing) -> None:
    """Two panels: PSNR around each orbit, and PSNR against the angle from the nearest training light.

    ``orbits``: plane -> (orbit angle deg [N], angle from training deg [N], PSNR dB [N]).
    """
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(10, 3.8))
    for plane, (orbit_deg, from_train_deg, psnr_db) in orbits.items():
        ax0.plot(orbit_deg, psnr_db, "o-", ms=3, label=plane)
        ax1.plot(from_train_deg, psnr_db, "o", ms=4, label=plane)
    for ax in (ax0, ax1):
        ax.axhline(threshold_db, color="k", ls="--", lw=1, label=f"threshold {threshold_db:.1f} dB")
        ax.set_ylabel("PSNR (dB, exposure fitted)")
        ax.grid(alpha=0.3)
    ax0.set_xlabel("orbit angle (deg; 0 = front, 180 = behind)")
    ax0.set_title("Point light orbiting at 3 m")
    ax1.axvline(limit.x, color="#c0392b", lw=1.5, label=_limit_label(limit, " deg"))
    ax1.set_xlabel("angle from the nearest training light (deg)")
    ax1.set_title("Light extrapolation limit")
    ax1.legend(fontsize=8)
    ax0.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def expression_png(path: Path, scales: np.ndarray, psnr_db: np.ndarray, threshold_db: float,
                   low: Crossing, high: Crossing) -> None:
    """PSNR against the blendshape-weight scale, the threshold and both break points."""
    fig, ax = plt.subplots(figsize=(6, 3.8))
    ax.plot(scales, psnr_db, "o-", ms=4)
    ax.axhline(threshold_db, color="k", ls="--", lw=1, label=f"threshold {threshold_db:.1f} dB")
    ax.axvspan(min(scales), 1.0, color="#eeeeee", zorder=0, label="up to the captured magnitude")
    for c, side in ((low, "low"), (high, "high")):
        ax.axvline(c.x, color="#c0392b", lw=1.2, ls=":" if c.censored else "-",
                   label=f"{side}: {_limit_label(c, 'x')}")
    ax.set_xlabel("scale of the tracked blendshape weights (1 = as captured)")
    ax.set_ylabel("PSNR (dB, exposure fitted)")
    ax.set_title("Expression magnitude beyond the training range")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def strip_png(path: Path, truth: Sequence[np.ndarray], pred: Sequence[np.ndarray]) -> None:
    """Truth (top row) over prediction (bottom row), each column normalised to its truth's 99.5th percentile.

    The white level is floored at 5% of the brightest column's, so a black back-lit truth does
    not turn its column's prediction into a white blob.
    """
    from scene.image_io import write_png_srgb

    whites = [float(np.percentile(t, 99.5)) for t in truth]
    floor = 0.05 * max(whites, default=1.0)
    cols = []
    for t, p, w in zip(truth, pred, whites):
        white = max(w, floor, 1e-8)
        cols.append(np.concatenate([t / white, p / white], axis=0) * 0.8)
    write_png_srgb(path, np.clip(np.concatenate(cols, axis=1), 0.0, None).astype(np.float32))
