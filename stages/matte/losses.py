"""MODNet's losses: supervised (semantic, detail, fusion) and SOC (sub-objectives consistency).

Supervised, per MODNet:
- semantic: L2 between the predicted coarse foreground and the ground-truth alpha
  downsampled to 1/16 and Gaussian-blurred;
- detail: L1 between the predicted detail and the ground-truth alpha, inside the transition
  region of a trimap derived from the ground truth (by erosion and dilation);
- fusion: L1 on alpha plus a compositional L1 (alpha times image), each over the whole
  image and, weighted more, over the transition region.

SOC (on unlabelled frames): the semantic output must agree with the blurred, downsampled
fused matte, and the detail output with the fused matte inside the transition region that
the semantic output implies; an L1 to a frozen copy's detail and matte keeps the adapted
model from drifting to the trivial solutions (all-zero or all-one mattes agree with
themselves too).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F


def gaussian_kernel(sigma_px: float, radius_px: int | None = None) -> torch.Tensor:
    """A normalised 1-D Gaussian kernel [2r+1]."""
    radius_px = radius_px if radius_px is not None else max(int(round(3.0 * sigma_px)), 1)
    x = torch.arange(-radius_px, radius_px + 1, dtype=torch.float32)
    kernel = torch.exp(-0.5 * (x / sigma_px) ** 2)
    return kernel / kernel.sum()


def gaussian_blur(x: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """Separable Gaussian blur of [B, C, H, W] with replicate padding."""
    kernel = gaussian_kernel(sigma_px).to(x)
    r, channels = kernel.numel() // 2, x.shape[1]
    kx = kernel.view(1, 1, 1, -1).repeat(channels, 1, 1, 1)
    ky = kernel.view(1, 1, -1, 1).repeat(channels, 1, 1, 1)
    x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="replicate"), kx, groups=channels)
    return F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), ky, groups=channels)


def semantic_target(alpha: torch.Tensor) -> torch.Tensor:
    """Ground truth of the semantic branch: alpha [B,1,H,W] area-downsampled to 1/16, then blurred."""
    small = F.interpolate(alpha, scale_factor=1.0 / 16.0, mode="area")
    return gaussian_blur(small, 1.0)


def transition_region(alpha: torch.Tensor, radius_px: int) -> torch.Tensor:
    """Boolean [B,1,H,W]: pixels within ``radius_px`` of a fractional alpha value (dilated minus eroded foreground)."""
    size = 2 * radius_px + 1
    fg = (alpha > 0.01).float()
    definite_fg = (alpha > 0.99).float()
    dilated = F.max_pool2d(fg, size, stride=1, padding=radius_px)
    eroded = -F.max_pool2d(-definite_fg, size, stride=1, padding=radius_px)
    return (dilated - eroded) > 0.5


@dataclass(frozen=True)
class LossWeights:
    """MODNet's loss scales."""

    semantic: float = 10.0
    detail: float = 10.0
    # MODNet uses 1; a larger weight makes the small network's fused matte converge to
    # confident 0/1 values in a few hundred CPU steps instead of tens of epochs.
    matte: float = 10.0
    boundary: float = 4.0


def supervised_loss(semantic: torch.Tensor, detail: torch.Tensor, matte: torch.Tensor, alpha: torch.Tensor,
                    image: torch.Tensor, transition_radius_px: int = 3,
                    weights: LossWeights = LossWeights()) -> tuple[torch.Tensor, dict[str, float]]:
    """Total MODNet loss and its parts.

    Args:
        semantic: [B,1,H/16,W/16]; detail, matte, alpha: [B,1,H,W]; image: [B,3,H,W] in [0, 1]
            (the compositional term's colour).
    """
    boundary = transition_region(alpha, transition_radius_px)  # [B,1,H,W] bool
    semantic_loss = F.mse_loss(semantic, semantic_target(alpha))
    boundary_count = boundary.float().sum().clamp_min(1.0)
    detail_loss = (detail - alpha).abs().mul(boundary).sum() / boundary_count
    # Outside the transition region the boundary copy equals the truth, so these terms only
    # count transition pixels, averaged over the whole image as in MODNet.
    boundary_matte = torch.where(boundary, matte, alpha)
    l1 = (matte - alpha).abs().mean() + weights.boundary * (boundary_matte - alpha).abs().mean()
    comp = ((matte - alpha) * image).abs().mean() + weights.boundary * ((boundary_matte - alpha) * image).abs().mean()
    total = weights.semantic * semantic_loss + weights.detail * detail_loss + weights.matte * (l1 + comp)
    parts = {"semantic": float(semantic_loss.detach()), "detail": float(detail_loss.detach()), "matte_l1": float(l1.detach()),
             "compositional": float(comp.detach())}
    return total, parts


def soc_loss(semantic: torch.Tensor, detail: torch.Tensor, matte: torch.Tensor,
             frozen_detail: torch.Tensor, frozen_matte: torch.Tensor,
             weights: LossWeights = LossWeights(), anchor_weight: float = 1.0) -> tuple[torch.Tensor, dict[str, float]]:
    """SOC adaptation loss on unlabelled images; ``frozen_*`` come from a frozen copy of the model."""
    semantic_consistency = F.mse_loss(semantic, semantic_target(matte))
    # The transition region from the semantic prediction: neither clearly in nor clearly out.
    semantic_up = F.interpolate(semantic, size=matte.shape[-2:], mode="bilinear", align_corners=False)
    boundary = ((semantic_up > 0.05) & (semantic_up < 0.95)).float()
    count = boundary.sum().clamp_min(1.0)
    detail_consistency = ((detail - matte.detach()).abs() * boundary).sum() / count
    anchor = (detail - frozen_detail).abs().mean() + (matte - frozen_matte).abs().mean()
    total = weights.semantic * semantic_consistency + weights.detail * detail_consistency + anchor_weight * anchor
    parts = {"soc_semantic": float(semantic_consistency.detach()), "soc_detail": float(detail_consistency.detach()),
             "soc_anchor": float(anchor.detach())}
    return total, parts
