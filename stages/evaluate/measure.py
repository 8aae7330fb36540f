"""Exposure-fitted PSNR of relit renders against truth, robust to nearly black references.

As in the paper (and ``relight_eval``), the prediction is scaled by the least-squares
exposure to the truth (the network's light units are its own). Along a sweep the light keeps
its intensity and distance, so one exposure is fitted per camera over the whole sweep, not
per image: a per-image fit would scale a wrongly lit render of a back-lit (nearly black)
truth down to black and call it perfect. Both are then divided by a white level before PSNR: the truth's 99th-percentile head pixel, so a dim (side- or back-lit)
image is judged relative to its own brightness. A light straight behind the head leaves the
truth almost black, and that white level would then be ~0 and blow any error up to -50 dB;
so the white level is floored at ``floor_fraction`` of the brightest truth of the same camera
in the sweep.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from avatar.metrics import exposure_scale, psnr


def head_white(truth_rgb: np.ndarray, truth_alpha: np.ndarray) -> float:
    """99th-percentile value of the head's pixels in ``truth_rgb`` [H, W, 3] (whole image if no head)."""
    head = truth_rgb[truth_alpha > 0.5]
    return float(np.percentile(head, 99)) if head.size else float(np.max(truth_rgb, initial=0.0))


def sweep_psnr(preds: Sequence[np.ndarray], truths: Sequence[np.ndarray], alphas: Sequence[np.ndarray],
               floor_fraction: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """PSNR [N] of one camera's renders along a sweep and the sweep's one exposure scale (see module doc)."""
    p = torch.as_tensor(np.stack(preds), dtype=torch.float64)  # [N, H, W, 3]
    t = torch.as_tensor(np.stack(truths), dtype=torch.float64)
    scale = float(exposure_scale(p.reshape(1, -1), t.reshape(1, -1))[0])
    whites = np.array([head_white(ti, a) for ti, a in zip(truths, alphas)])
    floor = floor_fraction * float(whites.max(initial=0.0))
    white = torch.as_tensor(np.maximum(np.maximum(whites, floor), 1e-12))[:, None, None, None]
    return psnr(p * scale / white, t / white).numpy(), scale
