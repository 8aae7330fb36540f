"""The report's charts (matplotlib, Agg backend, PNG files)."""

from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (backend chosen first, on purpose)


def stage_timings_chart(seconds_by_stage: Mapping[str, float], path: Path) -> None:
    """Horizontal bars: wall-clock seconds of every stage's last run."""
    names = list(seconds_by_stage)
    fig, ax = plt.subplots(figsize=(7, 0.35 * len(names) + 1.2))
    ax.barh(names, [seconds_by_stage[n] for n in names], color="#4a7fb5")
    ax.invert_yaxis()
    ax.set_xlabel("seconds (last run)")
    ax.set_title("Stage timings")
    for i, name in enumerate(names):
        ax.text(seconds_by_stage[name], i, f" {seconds_by_stage[name]:.1f}", va="center", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def target_ratio_chart(rows: Sequence[tuple[str, float, bool]], path: Path) -> None:
    """Bars of value / bound per target, coloured by pass/fail; the target is the line at 1.

    ``rows``: (label, ratio normalised so that < 1 passes, passed).
    """
    labels = [r[0] for r in rows]
    ratios = [r[1] for r in rows]
    colours = ["#4caf50" if r[2] else "#e57373" for r in rows]
    fig, ax = plt.subplots(figsize=(8, 0.35 * len(rows) + 1.4))
    ax.barh(labels, ratios, color=colours)
    ax.axvline(1.0, color="k", lw=1, ls="--")
    ax.invert_yaxis()
    ax.set_xscale("log")
    ax.set_xlabel("measured / target (left of the dashed line passes)")
    ax.set_title("Accuracy against the targets")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def tradeoff_chart(title: str, x_label: str, y_label: str, points: Sequence[Mapping], path: Path) -> None:
    """Speed against accuracy: one point per configuration, the chosen one marked.

    ``points``: mappings with ``x``, ``y``, optional ``label``, ``series`` and ``chosen``.
    """
    fig, ax = plt.subplots(figsize=(6, 4))
    series: dict[str, list[Mapping]] = {}
    for p in points:
        series.setdefault(str(p.get("series", "")), []).append(p)
    for name, pts in series.items():
        pts = sorted(pts, key=lambda p: p["x"])
        ax.plot([p["x"] for p in pts], [p["y"] for p in pts], "o-", label=name or None)
        for p in pts:
            if p.get("label"):
                ax.annotate(str(p["label"]), (p["x"], p["y"]), fontsize=7, xytext=(3, 3),
                            textcoords="offset points")
    chosen = [p for p in points if p.get("chosen")]
    if chosen:
        ax.scatter([p["x"] for p in chosen], [p["y"] for p in chosen], s=160, facecolors="none",
                   edgecolors="red", linewidths=2, label="chosen", zorder=5)
    ax.set_xlabel(x_label)
    ax.set_ylabel(y_label)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if any(series) or chosen:
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def capacity_chart(points: Sequence[Mapping], path: Path, title: str) -> None:
    """Capacity against held-out PSNR (left) and cost (right), the rule's choice and the knee marked.

    ``points``: mappings with ``texels_per_side``, ``heldout_psnr``, ``iterations_per_second``,
    ``peak_memory_mb``, ``prims_per_side``, ``voxels_per_side`` and optional ``rule_choice``
    and ``knee`` flags.
    """
    pts = sorted(points, key=lambda p: p["texels_per_side"])
    x = [p["texels_per_side"] for p in pts]
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    ax.plot(x, [p["heldout_psnr"] for p in pts], "o-", label="held-out PSNR")
    for p in pts:
        ax.annotate(f"N={p['prims_per_side']} M={p['voxels_per_side']}", (p["texels_per_side"], p["heldout_psnr"]),
                    fontsize=7, xytext=(3, -10), textcoords="offset points")
    chosen = [p for p in pts if p.get("rule_choice")]
    if chosen:
        ax.scatter([p["texels_per_side"] for p in chosen], [p["heldout_psnr"] for p in chosen], s=220,
                   facecolors="none", edgecolors="red", linewidths=2, label="rule's choice", zorder=5)
    knee = [p for p in pts if p.get("knee")]
    if knee:
        ax.scatter([p["texels_per_side"] for p in knee], [p["heldout_psnr"] for p in knee], marker="x", s=120,
                   color="green", linewidths=2.5, label="knee (Kneedle)", zorder=6)
    ax.set_xscale("log", base=2)
    ax.set_xlabel("capacity: texels per UV side, N x M")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax2.plot(x, [1.0 / p["iterations_per_second"] for p in pts], "s-", color="#d62728", label="s / iteration")
    ax2.set_xscale("log", base=2)
    ax2.set_xlabel("capacity: texels per UV side, N x M")
    ax2.set_ylabel("training seconds per iteration")
    ax3 = ax2.twinx()
    ax3.plot(x, [p["peak_memory_mb"] for p in pts], "^--", color="#2ca02c", label="peak memory (MB)")
    ax3.set_ylabel("peak memory (MB)")
    if chosen:
        ax2.axvline(chosen[0]["texels_per_side"], color="red", ls=":", lw=1.5, label="rule's choice")
    handles, labels = ax2.get_legend_handles_labels()
    more_handles, more_labels = ax3.get_legend_handles_labels()
    ax2.legend(handles + more_handles, labels + more_labels, fontsize=8, loc="upper left")
    ax2.set_title("cost of each capacity", fontsize=9)
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
