"""A picture of the OLAT order: bar directions on a sphere projection, arrows in capture order."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np


def azimuth_elevation_deg(directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth (about +y, 0 towards +z, positive towards +x) and elevation of unit directions [B, 3]."""
    azimuth = np.degrees(np.arctan2(directions[:, 0], directions[:, 2]))  # [B]
    elevation = np.degrees(np.arcsin(np.clip(directions[:, 1], -1.0, 1.0)))  # [B]
    return azimuth, elevation


def plot_order(path: Path, directions: np.ndarray, olat_order: Sequence[int], bar_ids: Sequence[int],
               across_full_on: Sequence[bool], title: str) -> None:
    """Write a PNG: each bar at its (azimuth, elevation) as seen from the head, arrows from each
    OLAT light to the next (solid: adjacent frames, dashed: across a full-on frame)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    azimuth, elevation = azimuth_elevation_deg(directions)
    fig, ax = plt.subplots(figsize=(7.0, 4.2), dpi=110)
    ax.scatter(azimuth, elevation, s=60, c="#f2c14e", edgecolors="k", zorder=3)
    for index, bar in enumerate(bar_ids):
        ax.annotate(str(bar), (azimuth[index], elevation[index]), fontsize=7, ha="center", va="center", zorder=4)
    n = len(olat_order)
    colours = plt.get_cmap("viridis")(np.linspace(0, 1, n))
    for k in range(n):
        a, b = olat_order[k], olat_order[(k + 1) % n]
        style = "--" if across_full_on[k] else "-"
        ax.annotate("", xy=(azimuth[b], elevation[b]), xytext=(azimuth[a], elevation[a]),
                    arrowprops=dict(arrowstyle="->", color=colours[k], lw=1.0, linestyle=style,
                                    shrinkA=6, shrinkB=6), zorder=2)
    ax.set_xlabel("azimuth seen from the head (deg, + = subject's left)")
    ax.set_ylabel("elevation (deg)")
    ax.set_title(title, fontsize=9)
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
