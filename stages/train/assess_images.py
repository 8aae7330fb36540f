"""The images the train stage measures itself on: the training images, or a whole fraction of their size.

The volumetric head renders at any resolution, so the metrics need not be taken at the
training images' size. ``train.assess_width_px`` measures them on images ``factor`` times
smaller on each axis: a pixel's ray is the mean of the rays of the ``factor x factor`` training
pixels it covers (for a pinhole camera, the ray through the block's centre, up to
normalisation), and its target and matte are their area average. That is what a camera with
``factor`` times larger pixels would record, so the figures measure the same model at another
resolution; they are not comparable with figures at the training size. At factor 1 every
method returns the training tensors' own values, bit for bit.

The paper preset trains on 768 x 1024 images; on a CPU one render of that size takes about a
minute, and assessment renders a few dozen, which is what this is for (``make smoke-paper``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from avatar.render import Rays
from pipeline.errors import ConfigError
from stages.train.trainer import Renderer, TrainTensors


def assess_factor(width_px: int, height_px: int, assess_width_px: int) -> int:
    """Training pixels per assessment pixel along each axis (1 when ``assess_width_px`` is 0 or the training width)."""
    if assess_width_px in (0, width_px):
        return 1
    factor = width_px // assess_width_px if assess_width_px > 0 else 0
    if assess_width_px > width_px or factor * assess_width_px != width_px or height_px % factor:
        divisors = [width_px // k for k in range(2, 17) if width_px % k == 0 and height_px % k == 0]
        raise ConfigError(f"train.assess_width_px={assess_width_px}: the training images are {width_px} x "
                          f"{height_px} px, and the assessment width must divide both sides by a whole number; "
                          f"use 0 (the training width) or one of {divisors}")
    return factor


@dataclass
class AssessImages:
    """Rays, targets and mattes of (frame, camera) pairs at the assessment resolution."""

    tensors: TrainTensors
    factor: int = 1
    _block_dirs: torch.Tensor | None = field(default=None, repr=False)

    @property
    def height(self) -> int:
        return self.tensors.height // self.factor

    @property
    def width(self) -> int:
        return self.tensors.width // self.factor

    def _pool(self, pixels: torch.Tensor) -> torch.Tensor:
        """Area average of ``pixels`` [..., H*W, D] over ``factor x factor`` blocks -> [..., h*w, D]."""
        k = self.factor
        lead = pixels.shape[:-2]
        x = pixels.reshape(*lead, self.height, k, self.width, k, pixels.shape[-1])
        return x.mean(dim=(-4, -2)).reshape(*lead, self.height * self.width, pixels.shape[-1])

    def _directions(self) -> torch.Tensor:
        """Each camera's unit ray directions [C, h*w, 3] at the assessment resolution (camera frame)."""
        if self._block_dirs is None:
            self._block_dirs = F.normalize(self._pool(self.tensors.pixel_dirs), dim=-1)
        return self._block_dirs

    def rays(self, f: int, c: int) -> Rays:
        """Head-space rays of image (f, c)."""
        t = self.tensors
        if self.factor == 1:
            return Rays(*t.image_rays(f, c), t.cam_pos[f, c], t.height, t.width)
        directions = self._directions()[c] @ t.head_from_cam[f, c].T
        return Rays(t.cam_pos[f, c][None].expand_as(directions), directions, t.cam_pos[f, c], self.height, self.width)

    def targets(self, pairs: list[tuple[int, int]]) -> torch.Tensor:
        """The captured images [K, h, w, 3]."""
        if self.factor == 1:
            return self.tensors.target_images(pairs)
        return torch.stack([self._pool(self.tensors.image(f, c).float()).view(self.height, self.width, 3)
                            for f, c in pairs])

    def mattes(self, pairs: list[tuple[int, int]]) -> torch.Tensor:
        """The mattes [K, h, w] (float)."""
        if self.factor == 1:
            return self.tensors.target_mattes(pairs)
        t = self.tensors
        return torch.stack([self._pool(t.mattes[f, c].float().to(t.device)[:, None]).view(self.height, self.width)
                            for f, c in pairs])

    def render(self, renderer: Renderer, pairs: list[tuple[int, int]]) -> tuple[torch.Tensor, torch.Tensor]:
        """``renderer``'s images [K, h, w, 3] and opacity [K, h, w] of ``pairs`` under each frame's light."""
        if self.factor == 1:
            return renderer.render_images(self.tensors, pairs)
        return renderer.render_rays(self.tensors, [f for f, _ in pairs], [self.rays(f, c) for f, c in pairs])


__all__ = ["AssessImages", "assess_factor"]
