"""Image metrics in linear RGB (PSNR, MAE, SSIM) and the exposure fit used for novel lights."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def exposure_scale(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Least-squares scale s minimising ||s * pred - target||^2 per image; pred/target [B, H, W, 3] -> [B]."""
    num = (pred * target).flatten(1).sum(-1)
    den = (pred * pred).flatten(1).sum(-1).clamp(min=1e-12)
    return num / den


def psnr(pred: torch.Tensor, target: torch.Tensor, peak: float = 1.0) -> torch.Tensor:
    """PSNR in dB per image [B] of linear images [B, H, W, C] (peak 1 = the exposure's white)."""
    mse = (pred - target).pow(2).flatten(1).mean(-1).clamp(min=1e-12)
    return 10.0 * torch.log10(peak * peak / mse)


def mae(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean absolute error per image [B]."""
    return (pred - target).abs().flatten(1).mean(-1)


def ssim(pred: torch.Tensor, target: torch.Tensor, data_range: float = 1.0, window: int = 11,
         sigma: float = 1.5) -> torch.Tensor:
    """SSIM (Wang et al. 2004, Gaussian window) per image [B] of [B, H, W, C] images, channels averaged."""
    x = pred.permute(0, 3, 1, 2)
    y = target.permute(0, 3, 1, 2)
    c = x.shape[1]
    coords = torch.arange(window, dtype=x.dtype, device=x.device) - (window - 1) / 2
    g = torch.exp(-coords ** 2 / (2 * sigma ** 2))
    g = g / g.sum()
    kernel = (g[:, None] * g[None, :]).expand(c, 1, window, window).contiguous()

    def blur(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(t, kernel, groups=c)

    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    mu_x, mu_y = blur(x), blur(y)
    var_x = blur(x * x) - mu_x ** 2
    var_y = blur(y * y) - mu_y ** 2
    cov = blur(x * y) - mu_x * mu_y
    value = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x ** 2 + mu_y ** 2 + c1) * (var_x + var_y + c2))
    return value.flatten(1).mean(-1)
