"""A MODNet-style matting network (Ke et al., "MODNet: Real-Time Trimap-Free Portrait Matting").

Three branches share one small encoder:

- semantic (low resolution): the encoder's 1/32 features, re-weighted by an SE block,
  upsampled to 1/8 and predicting a coarse foreground probability at 1/16 of the input;
- detail (high resolution): the image at 1/2 and 1/4 plus the encoder's 1/2 and 1/4
  features and the semantic features, predicting the matte's boundary detail at full size;
- fusion: semantic features upsampled and merged with the detail features, predicting the
  final alpha at full size.

Normalisation in the decoder is IBNorm: half the channels batch-normalised (statistics of
the data set, good for semantics), half instance-normalised (per-image contrast, good for
detail under strongly varying exposure such as OLAT frames).

The encoder is a small MobileNetV2-like stack of inverted-residual depthwise blocks,
written here (no pretrained weights can be downloaded). Input height and width must be
multiples of 32 (``pad_to_multiple`` in ``stages.matte.inputs`` pads).
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from pydantic import BaseModel, ConfigDict, Field
from torch import nn


class MattingNetConfig(BaseModel):
    """Sizes of the matting network."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    in_channels: int = Field(6, description="Input channels: RGB of the image, then RGB of the guide full-on frame.")
    encoder_channels: tuple[int, int, int, int, int] = Field(
        (8, 12, 16, 24, 32), description="Encoder feature channels at 1/2, 1/4, 1/8, 1/16, 1/32 of the input.")
    encoder_blocks: tuple[int, int, int, int] = Field(
        (1, 1, 1, 1), description="Inverted-residual blocks at 1/4, 1/8, 1/16 and 1/32 (the first of each strides).")
    expand_ratio: int = Field(3, description="Channel expansion inside an inverted-residual block.")
    hr_channels: int = Field(8, description="Channels of the high-resolution (detail) branch.")
    se_reduction: int = Field(4, description="Squeeze-and-excitation channel reduction factor.")
    logit_gain: float = Field(6.0, description="Constant gain on the detail and matte logits before the sigmoid.")


SIZES: dict[str, MattingNetConfig] = {
    # Trains on a 2-core CPU in minutes at 64-128 px.
    "tiny": MattingNetConfig(),
    # A GPU-sized network close to MODNet's proportions (MobileNetV2 widths).
    "large": MattingNetConfig(encoder_channels=(16, 24, 32, 96, 160), encoder_blocks=(2, 3, 4, 3),
                              expand_ratio=6, hr_channels=32, se_reduction=4),
}

NetSize = Literal["tiny", "large"]


class IBNorm(nn.Module):
    """Instance-batch normalisation: the first half of the channels batch-normalised, the rest instance-normalised."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.batch_channels = max(channels // 2, 1)
        self.instance_channels = channels - self.batch_channels
        self.bnorm = nn.BatchNorm2d(self.batch_channels, affine=True)
        # affine=False as in MODNet: the following conv re-scales; instance statistics are per image.
        self.inorm = nn.InstanceNorm2d(self.instance_channels, affine=False) if self.instance_channels else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # [B, C, H, W] -> [B, C, H, W]
        bn_x = self.bnorm(x[:, : self.batch_channels].contiguous())
        if self.inorm is None:
            return bn_x
        in_x = self.inorm(x[:, self.batch_channels:].contiguous())
        return torch.cat((bn_x, in_x), dim=1)


class ConvIBNormRelu(nn.Sequential):
    """Conv2d, then optionally IBNorm, then optionally ReLU."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, stride: int = 1,
                 with_ibn: bool = True, with_relu: bool = True) -> None:
        layers: list[nn.Module] = [nn.Conv2d(in_channels, out_channels, kernel_size, stride=stride,
                                             padding=kernel_size // 2, bias=not with_ibn)]
        if with_ibn:
            layers.append(IBNorm(out_channels))
        if with_relu:
            layers.append(nn.ReLU(inplace=True))
        super().__init__(*layers)


class SEBlock(nn.Module):
    """Squeeze-and-excitation: per-channel weights from globally pooled features."""

    def __init__(self, channels: int, reduction: int = 4) -> None:
        super().__init__()
        hidden = max(channels // reduction, 1)
        self.fc = nn.Sequential(nn.Linear(channels, hidden, bias=False), nn.ReLU(inplace=True),
                                nn.Linear(hidden, channels, bias=False), nn.Sigmoid())

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # [B, C, H, W] -> [B, C, H, W]
        weights = self.fc(x.mean(dim=(2, 3)))  # [B, C]
        return x * weights[:, :, None, None]


class InvertedResidual(nn.Module):
    """MobileNetV2 block: 1x1 expand, 3x3 depthwise (maybe strided), 1x1 project; residual when shapes match."""

    def __init__(self, in_channels: int, out_channels: int, stride: int, expand_ratio: int) -> None:
        super().__init__()
        hidden = in_channels * expand_ratio
        self.use_residual = stride == 1 and in_channels == out_channels
        layers: list[nn.Module] = []
        if expand_ratio != 1:
            layers += [nn.Conv2d(in_channels, hidden, 1, bias=False), nn.BatchNorm2d(hidden), nn.ReLU6(inplace=True)]
        layers += [nn.Conv2d(hidden, hidden, 3, stride=stride, padding=1, groups=hidden, bias=False),
                   nn.BatchNorm2d(hidden), nn.ReLU6(inplace=True),
                   nn.Conv2d(hidden, out_channels, 1, bias=False), nn.BatchNorm2d(out_channels)]
        self.block = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.block(x)
        return x + out if self.use_residual else out


class Encoder(nn.Module):
    """Five feature maps at 1/2 ... 1/32 of the input."""

    def __init__(self, config: MattingNetConfig) -> None:
        super().__init__()
        c = config.encoder_channels
        self.stem = nn.Sequential(nn.Conv2d(config.in_channels, c[0], 3, stride=2, padding=1, bias=False),
                                  nn.BatchNorm2d(c[0]), nn.ReLU6(inplace=True),
                                  InvertedResidual(c[0], c[0], 1, 1))
        stages = []
        for level, blocks in enumerate(config.encoder_blocks):
            layers = [InvertedResidual(c[level], c[level + 1], 2, config.expand_ratio)]
            layers += [InvertedResidual(c[level + 1], c[level + 1], 1, config.expand_ratio) for _ in range(blocks - 1)]
            stages.append(nn.Sequential(*layers))
        self.stages = nn.ModuleList(stages)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        features = [self.stem(x)]
        for stage in self.stages:
            features.append(stage(features[-1]))
        return features  # [B, c0, H/2, W/2], ..., [B, c4, H/32, W/32]


def _head(in_channels: int, gain: float) -> nn.Module:
    """A 1x1 conv to one logit channel, times a constant gain.

    The head follows a normalised, ReLU'd layer (activations of order 1), so without the
    gain its weights must grow several-fold before the sigmoid can reach confident 0/1
    values, which Adam does only over thousands of steps; the gain gets there in hundreds.
    """
    return _Scaled(nn.Conv2d(in_channels, 1, 1), gain)


class _Scaled(nn.Module):
    def __init__(self, inner: nn.Module, gain: float) -> None:
        super().__init__()
        self.inner, self.gain = inner, gain

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.inner(x) * self.gain


def _resize(x: torch.Tensor, scale: float) -> torch.Tensor:
    return F.interpolate(x, scale_factor=scale, mode="bilinear", align_corners=False)


class SemanticBranch(nn.Module):
    """Low-resolution branch: coarse foreground probability at 1/16 and features at 1/8."""

    def __init__(self, config: MattingNetConfig) -> None:
        super().__init__()
        c = config.encoder_channels
        self.se = SEBlock(c[4], config.se_reduction)
        self.conv_lr16x = ConvIBNormRelu(c[4], c[3], 5)
        self.conv_lr8x = ConvIBNormRelu(c[3], c[2], 5)
        self.conv_lr = ConvIBNormRelu(c[2], 1, 3, stride=2, with_ibn=False, with_relu=False)

    def forward(self, enc32x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        lr16x = self.conv_lr16x(_resize(self.se(enc32x), 2.0))
        lr8x = self.conv_lr8x(_resize(lr16x, 2.0))  # [B, c2, H/8, W/8]
        semantic = torch.sigmoid(self.conv_lr(lr8x))  # [B, 1, H/16, W/16]
        return semantic, lr8x


class DetailBranch(nn.Module):
    """High-resolution branch: boundary detail at full size and features at 1/2."""

    def __init__(self, config: MattingNetConfig) -> None:
        super().__init__()
        c, hr, cin = config.encoder_channels, config.hr_channels, config.in_channels
        self.tohr_enc2x = ConvIBNormRelu(c[0], hr, 1)
        self.conv_enc2x = ConvIBNormRelu(hr + cin, hr, 3, stride=2)
        self.tohr_enc4x = ConvIBNormRelu(c[1], hr, 1)
        self.conv_enc4x = ConvIBNormRelu(2 * hr, 2 * hr, 3)
        self.conv_hr4x = nn.Sequential(ConvIBNormRelu(2 * hr + c[2] + cin, 2 * hr, 3),
                                       ConvIBNormRelu(2 * hr, 2 * hr, 3), ConvIBNormRelu(2 * hr, hr, 3))
        self.conv_hr2x = nn.Sequential(ConvIBNormRelu(2 * hr, 2 * hr, 3), ConvIBNormRelu(2 * hr, hr, 3),
                                       ConvIBNormRelu(hr, hr, 3), ConvIBNormRelu(hr, hr, 3))
        self.conv_hr = nn.Sequential(ConvIBNormRelu(hr + cin, hr, 3),
                                     _head(hr, config.logit_gain))

    def forward(self, image: torch.Tensor, enc2x: torch.Tensor, enc4x: torch.Tensor,
                lr8x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        image2x, image4x = _resize(image, 0.5), _resize(image, 0.25)
        enc2x = self.tohr_enc2x(enc2x)  # [B, hr, H/2, W/2]
        hr4x = self.conv_enc2x(torch.cat((image2x, enc2x), dim=1))  # [B, hr, H/4, W/4]
        hr4x = self.conv_enc4x(torch.cat((hr4x, self.tohr_enc4x(enc4x)), dim=1))  # [B, 2hr, H/4, W/4]
        hr4x = self.conv_hr4x(torch.cat((hr4x, _resize(lr8x, 2.0), image4x), dim=1))  # [B, hr, H/4, W/4]
        hr2x = self.conv_hr2x(torch.cat((_resize(hr4x, 2.0), enc2x), dim=1))  # [B, hr, H/2, W/2]
        detail = torch.sigmoid(self.conv_hr(torch.cat((_resize(hr2x, 2.0), image), dim=1)))  # [B, 1, H, W]
        return detail, hr2x


class FusionBranch(nn.Module):
    """Merges semantic and detail features into the final alpha matte."""

    def __init__(self, config: MattingNetConfig) -> None:
        super().__init__()
        c, hr, cin = config.encoder_channels, config.hr_channels, config.in_channels
        self.conv_lr4x = ConvIBNormRelu(c[2], hr, 5)
        self.conv_f2x = ConvIBNormRelu(2 * hr, hr, 3)
        self.conv_f = nn.Sequential(ConvIBNormRelu(hr + cin, max(hr // 2, 4), 3),
                                    _head(max(hr // 2, 4), config.logit_gain))

    def forward(self, image: torch.Tensor, lr8x: torch.Tensor, hr2x: torch.Tensor) -> torch.Tensor:
        lr4x = self.conv_lr4x(_resize(lr8x, 2.0))  # [B, hr, H/4, W/4]
        f2x = self.conv_f2x(torch.cat((_resize(lr4x, 2.0), hr2x), dim=1))  # [B, hr, H/2, W/2]
        return torch.sigmoid(self.conv_f(torch.cat((_resize(f2x, 2.0), image), dim=1)))  # [B, 1, H, W]


class MODNet(nn.Module):
    """The matting network; ``forward`` returns (semantic [B,1,H/16,W/16], detail [B,1,H,W], matte [B,1,H,W])."""

    def __init__(self, config: MattingNetConfig) -> None:
        super().__init__()
        self.config = config
        self.encoder = Encoder(config)
        self.semantic = SemanticBranch(config)
        self.detail = DetailBranch(config)
        self.fusion = FusionBranch(config)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``image`` [B, in_channels, H, W] with H and W multiples of 32, values about in [-1, 1]."""
        enc2x, enc4x, _, _, enc32x = self.encoder(image)
        semantic, lr8x = self.semantic(enc32x)
        detail, hr2x = self.detail(image, enc2x, enc4x, lr8x)
        matte = self.fusion(image, lr8x, hr2x)
        return semantic, detail, matte

    def freeze_batch_norm(self) -> None:
        """Put every BatchNorm in eval mode (SOC adaptation on a few unlabelled frames must not move the statistics)."""
        for module in self.modules():
            if isinstance(module, nn.BatchNorm2d):
                module.eval()
