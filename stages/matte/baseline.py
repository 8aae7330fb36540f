"""Classical matte for a black backdrop: luminance threshold, clean-up, guided-filter edges.

The backdrop is black, so a pixel brighter than a small fraction of the image's bright
level is foreground. Small specks (noise) are opened away and holes closed; the binary mask
is then refined by a guided filter (He et al.) with the sRGB-encoded image as the guide,
which snaps the soft edge to image edges. It needs no training, so it is the comparison
for the network and the stage's fallback (``method: baseline``). It cannot see the unlit
side of an OLAT frame; that is what the network's F-frame guide is for.
"""

from __future__ import annotations

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from scene.colour import luminance, srgb_encode


class BaselineConfig(BaseModel):
    """Parameters of the threshold + guided-filter matte."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    threshold_ratio: float = Field(0.03, description="Foreground if luminance > this x the image's 99th percentile luminance.")
    threshold_floor: float = Field(2e-3, description="Absolute luminance floor of the threshold (linear), so an empty noisy frame stays empty.")
    open_radius_px: int = Field(1, description="Radius of the morphological opening that removes noise specks.")
    close_radius_px: int = Field(2, description="Radius of the morphological closing that fills small holes.")
    guided_radius_px: int = Field(1, description="Guided filter window radius in pixels.")
    guided_eps: float = Field(1e-2, description="Guided filter regularisation (edge sensitivity; guide in [0, 1]).")


def _disk(radius_px: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1, 2 * radius_px + 1))


def baseline_matte(image: np.ndarray, config: BaselineConfig = BaselineConfig()) -> np.ndarray:
    """Alpha [H, W] float32 in [0, 1] of a linear RGB image [H, W, 3] on a black backdrop."""
    luma = luminance(image).astype(np.float32)
    level = float(np.percentile(luma, 99.0))
    threshold = max(config.threshold_ratio * level, config.threshold_floor)
    mask = (luma > threshold).astype(np.uint8)
    if config.open_radius_px > 0:
        mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, _disk(config.open_radius_px))
    if config.close_radius_px > 0:
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, _disk(config.close_radius_px))
    guide = srgb_encode(image[..., :3] / max(level, config.threshold_floor)).astype(np.float32)
    alpha = cv2.ximgproc.guidedFilter(guide, mask.astype(np.float32), config.guided_radius_px, config.guided_eps)
    return np.clip(alpha, 0.0, 1.0).astype(np.float32)
