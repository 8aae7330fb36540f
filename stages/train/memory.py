"""Projected peak training memory of a configuration at a batch size, without the device it is meant for.

A training step holds the model (parameters, gradients and Adam's two moments: 16 bytes a
parameter) and what autograd saves for the backward pass. The saved tensors are counted with
``torch.autograd.graph.saved_tensors_hooks``:

- **the decoders** (encoder, geometry, the RGB voxel grids of N^2 primitives of M^3 voxels)
  run on PyTorch's ``meta`` device: shapes without storage or arithmetic, so the paper's
  configuration at any batch is counted in seconds on a CPU; the count is exact and linear
  in the batch, so two batch sizes give the cost of one more image;
- **the raymarch** depends on how many primitives each ray crosses, so it is measured by
  running it (tensor ops, as on a GPU) on ``sample_rays`` rays of one image of the actual
  geometry at its initialisation, then scaled to ``rays_per_image`` rays per image.

The projection leaves out the allocator's caching and fragmentation and the transient
buffers of single operations (typically 10-30 % on CUDA), so read it as a lower bound.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from avatar.config import AvatarConfig
from avatar.layout import GuideLayout
from avatar.model import RelightableMVP


@dataclass(frozen=True)
class MemoryProjection:
    """Bytes of one training step's resident state at ``batch`` images of ``rays_per_image`` rays."""

    batch: int
    rays_per_image: int
    model_bytes: int  # parameters, gradients, Adam moments
    decoder_bytes: int  # saved by the decoders for the backward pass
    raymarch_bytes: int  # saved by the raymarch

    @property
    def total_gb(self) -> float:
        return (self.model_bytes + self.decoder_bytes + self.raymarch_bytes) / 1e9

    def as_dict(self) -> dict[str, float]:
        return {"batch": self.batch, "rays_per_image": self.rays_per_image, "model_gb": self.model_bytes / 1e9,
                "decoder_activations_gb": self.decoder_bytes / 1e9,
                "raymarch_activations_gb": self.raymarch_bytes / 1e9, "projected_peak_gb": self.total_gb}


def _saved_bytes(run) -> int:
    total = [0]

    def pack(tensor: torch.Tensor) -> torch.Tensor:
        total[0] += tensor.numel() * tensor.element_size()
        return tensor

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda tensor: tensor):
        run()
    return total[0]


def decoder_saved_bytes(config: AvatarConfig, layout: GuideLayout, batch: int, num_bars: int = 32) -> int:
    """Bytes the encoder and decoders save for backward at ``batch`` images (counted on the meta device)."""
    with torch.device("meta"):
        model = RelightableMVP(config, layout, num_bars)
    model.kept_index = lambda: None  # pruning state is data; nothing is pruned at the start

    def run() -> None:
        with torch.device("meta"):
            vertices = torch.zeros(batch, model.num_guide_vertices, 3)
            mu, _ = model.encode(vertices)
            geometry = model.decode_geometry(mu)
            model.decode_rgb(geometry, torch.zeros(batch, 3), torch.ones(batch, 3))

    return _saved_bytes(run)


def raymarch_saved_bytes_per_ray(config: AvatarConfig, layout: GuideLayout, camera, sample_rays: int = 2048,
                                 seed: int = 0) -> float:
    """Bytes the tensor-op raymarch saves per ray, measured on ``sample_rays`` pixels of ``camera``.

    The geometry is a model of ``config``'s primitive layout at its initialisation, with its
    channels narrowed to keep the decode cheap: the raymarch's cost depends on the boxes, not
    on the channel widths.
    """
    from avatar.raymarch import raymarch
    from avatar.render import Rays

    narrow = config.model_copy(update={"encoder_hidden": 16, "base_channels": 16, "geometry_channels": 8,
                                       # the last layer's width is the voxels' (3 M colours, M densities)
                                       "rgb_channels": tuple(min(c, 8) for c in config.rgb_channels[:-1])
                                       + tuple(config.rgb_channels[-1:]),
                                       "alpha_channels": tuple(min(c, 8) for c in config.alpha_channels[:-1])
                                       + tuple(config.alpha_channels[-1:]),
                                       "latent_dim": min(config.latent_dim, 16)})
    torch.manual_seed(seed)
    model = RelightableMVP(narrow, layout, num_bars=32)
    rays = Rays.of_camera(camera)
    pick = torch.as_tensor(np.random.default_rng(seed).choice(rays.origins.shape[0], sample_rays, replace=False))
    mu, _ = model.encode(model.mean_guide_vertices.reshape(1, -1, 3))
    geometry = model.decode_geometry(mu)
    rgb = model.decode_rgb(geometry, rays.position[None], torch.ones(1, 3))
    prims = geometry.primitives(rgb)
    saved = _saved_bytes(lambda: raymarch(prims, rays.origins[pick][None], rays.directions[pick][None],
                                          config.steps_per_ray, kernel="torch"))
    return saved / sample_rays


def project_training_memory(config: AvatarConfig, layout: GuideLayout, camera, batch: int, rays_per_image: int,
                            sample_rays: int = 2048) -> MemoryProjection:
    """The projection at ``batch`` (see the module docstring); the decoders counted at batch 1 and 2."""
    one, two = decoder_saved_bytes(config, layout, 1), decoder_saved_bytes(config, layout, 2)
    decoder = one + (two - one) * (batch - 1)
    with torch.device("meta"):
        parameters = sum(p.numel() for p in RelightableMVP(config, layout, 32).parameters())
    per_ray = raymarch_saved_bytes_per_ray(config, layout, camera, sample_rays)
    return MemoryProjection(batch, rays_per_image, int(16 * parameters), int(decoder),
                            int(per_ray * rays_per_image * batch))


__all__ = ["MemoryProjection", "decoder_saved_bytes", "project_training_memory", "raymarch_saved_bytes_per_ray"]
