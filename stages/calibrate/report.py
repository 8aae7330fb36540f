"""Per-camera residuals and plots for the calibration report."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scene.camera import Camera, Rigid
from stages.calibrate.board import Detection


def residuals_px(cam: Camera, detections: list[Detection], world_from_board: dict[int, Rigid],
                 corners_board: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Observed minus projected corner positions [N, 2] and the observed positions [N, 2], over used frames."""
    res, obs = [], []
    for d in detections:
        if d.frame not in world_from_board:
            continue
        uv, _ = cam.project(world_from_board[d.frame].apply(corners_board[d.ids]))
        res.append(d.corners_px - uv)
        obs.append(d.corners_px)
    if not res:
        return np.zeros((0, 2)), np.zeros((0, 2))
    return np.concatenate(res), np.concatenate(obs)


def plot_residuals(path: Path, cam: Camera, residual_px: np.ndarray, observed_px: np.ndarray) -> None:
    """A PNG with the residual vectors over the image (exaggerated) and their scatter."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rms = float(np.sqrt(np.mean(np.sum(residual_px ** 2, axis=1)))) if len(residual_px) else float("nan")
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    scale = 0.1 * cam.width / max(float(np.abs(residual_px).max()) if len(residual_px) else 1.0, 1e-6)
    a.quiver(observed_px[:, 0], observed_px[:, 1], residual_px[:, 0] * scale, residual_px[:, 1] * scale,
             angles="xy", scale_units="xy", scale=1, width=0.003)
    a.set_xlim(0, cam.width)
    a.set_ylim(cam.height, 0)
    a.set_aspect("equal")
    a.set_title(f"{cam.name}: residuals x{scale:.0f}")
    b.scatter(residual_px[:, 0], residual_px[:, 1], s=3)
    lim = max(float(np.abs(residual_px).max()) if len(residual_px) else 1.0, 0.1) * 1.1
    b.set_xlim(-lim, lim)
    b.set_ylim(-lim, lim)
    b.set_aspect("equal")
    b.axhline(0, color="grey", lw=0.5)
    b.axvline(0, color="grey", lw=0.5)
    b.set_title(f"residual (px), RMS {rms:.3f}, {len(residual_px)} corners")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
