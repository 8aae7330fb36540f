"""A raymarch as a linear map: the weight of every voxel colour in every pixel, for one geometry and view.

With opacity fixed, ``avatar.raymarch.raymarch`` is linear in the voxel colours: each pixel's
colour is a fixed weighted sum of voxel colours (a sample's share of opacity below
saturation, times its density, times the trilinear weight), the same for every colour
channel. ``colour_transport`` records those weights as a sparse matrix, so any number of
colour grids over the same geometry and rays render as one sparse product each, with no box
test and no compositing: the light-transfer bake (``avatar.bake``) renders all its
directions that way.

It follows the raymarcher's tensor path step by step (samples over each ray's span through
the boxes, the same candidate boxes, additive opacity with MVP's early termination), using
its helpers; ``tests/avatar/test_avatar_transport.py`` checks that the product equals the
raymarch of every grid, with either kernel's box culling, so a change to the raymarcher that
is not mirrored here fails there. A module of its own so that the raymarcher (in the code
digest of training) does not change when this does.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch

from avatar.raymarch import (Primitives, RaymarchKernel, _sample_share, box_intervals, local_frames,
                             ray_samples, resolve_kernel, trilinear_corners)
from avatar.raymarch_fused import fused_module


@dataclass
class ColourTransport:
    """A raymarch as a linear map from voxel colours to pixel colours (one geometry, one set of rays).

    With opacity fixed, every pixel's colour is a fixed weighted sum of voxel colours (the
    sample's share of opacity times its density times the trilinear weight), the same for
    each colour channel. ``matrix`` holds those weights, so ``apply`` renders any number of
    colour grids over the same geometry at the cost of one sparse product each, with no box
    test or compositing: the light-transfer bake (``avatar.bake``) renders all its
    directions that way.

    Attributes:
        matrix: [R, P*M^3] sparse CSR (float): row = ray, column = voxel of the (unpruned
            rows of the) primitives, z-major within each primitive, as ``Primitives.rgb``.
        alpha: [R] the rays' accumulated opacity (as ``raymarch``'s).
    """

    matrix: torch.Tensor
    alpha: torch.Tensor

    def apply(self, rgb: torch.Tensor) -> torch.Tensor:
        """Pixel colours [R, C] of voxel colours [P, M, M, M, C] (any C: e.g. 3 channels times k lights)."""
        channels = int(rgb.shape[-1])
        return self.matrix @ rgb.reshape(-1, channels).to(self.matrix.dtype)

    @property
    def nnz(self) -> int:
        """Stored weights (the transport's size: about 12 bytes each)."""
        return int(self.matrix.values().numel())


def _ray_candidates(prims: Primitives, rays_o: torch.Tensor, rays_d: torch.Tensor, steps: int, fused: bool
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Batch 1: candidate boxes [R, K] (-1 = empty slot), their entry and exit distances [R, K], samples [R, S], step [R].

    ``fused``: the fused kernel's bounding-sphere culling (as ``raymarch(kernel="fused")``
    samples), else the tensor path's slab test (as ``kernel="torch"``).
    """
    if fused:
        local_from_head, centre_local = local_frames(prims)
        cand, near, far, t_min, t_max = fused_module(required=True).candidates(
            rays_o.contiguous(), rays_d.contiguous(), local_from_head.contiguous(), centre_local.contiguous(),
            prims.centre.contiguous(), prims.half_extent.norm(dim=-1).contiguous())  # [R, K] x3, [R] x2
        dt = (t_max - t_min) / steps  # [R]
        t = t_min[:, None] + (torch.arange(steps, dtype=dt.dtype) + 0.5) * dt[:, None]  # [R, S]
        return cand, near, far, t, dt
    hit, t_near, t_far = box_intervals(prims, rays_o, rays_d)  # [1, R, P]
    t, dt = ray_samples(hit, t_near, t_far, steps)  # [1, R, S], [1, R]
    k = max(1, int(hit.sum(-1).max()))
    cand_hit, cand = torch.topk(hit.to(torch.uint8), k, dim=-1)  # [1, R, K]
    near, far = torch.gather(t_near, -1, cand)[0], torch.gather(t_far, -1, cand)[0]
    return torch.where(cand_hit[0].bool(), cand[0], -1), near, far, t[0], dt[0]


@torch.no_grad()
def colour_transport(prims: Primitives, rays_o: torch.Tensor, rays_d: torch.Tensor, steps: int,
                     max_pairs: int = 1 << 23, kernel: RaymarchKernel = "auto") -> ColourTransport:
    """The weights by which ``raymarch(prims, rays_o, rays_d, steps, kernel=kernel)`` mixes voxel colours, batch 1.

    ``prims`` [1, P, ...] (its ``rgb`` is not read), rays [1, R, 3]. The raymarch's sampling
    and compositing, with each (sample, box, voxel) weight recorded instead of summed, so
    ``colour_transport(...).apply(prims.rgb[0])`` equals the raymarch's colour to float
    rounding. ``kernel`` picks whose ray-box culling to use (``"auto"``: the fused kernel's
    on the CPU where it builds, as ``raymarch``); the weights themselves are tensor ops.
    Rays go in chunks so that no intermediate exceeds about ``max_pairs`` entries.
    """
    b, r, _ = rays_o.shape
    if b != 1 or prims.centre.shape[0] != 1:
        raise ValueError(f"colour_transport: one geometry and one set of rays (batch 1), got rays "
                         f"{tuple(rays_o.shape)} and {prims.centre.shape[0]} geometries")
    fused = resolve_kernel(kernel, prims.density.device, prims.density.dtype) == "fused"
    p = prims.centre.shape[1]
    m3 = prims.voxels_per_side ** 3
    density = prims.density.reshape(-1)  # [P*M^3]
    local_from_head, centre_local = local_frames(prims)  # [1, P, 3, 3], [1, P, 3]
    chunk = max(1, min(r, max_pairs // max(1, p)))
    crow, ccol, cval, alphas = [], [], [], []
    for start in range(0, r, chunk):
        o, d = rays_o[:, start:start + chunk], rays_d[:, start:start + chunk]  # [1, Rc, 3]
        rc = o.shape[1]
        cand, near, far, t, dt = _ray_candidates(prims, o, d, steps, fused)  # [Rc, K] x3, [Rc, S], [Rc]
        k = cand.shape[1]
        inside = ((cand >= 0)[:, None, :] & (t[..., None] >= near[:, None, :])
                  & (t[..., None] <= far[:, None, :]))  # [Rc, S, K]
        ri, si, ki = inside.nonzero(as_tuple=True)  # Q (sample, box) pairs, in ray order
        slot = ri * k + ki  # [Q] (ray, candidate)
        box = cand.clamp(min=0).reshape(-1)  # [Rc*K]
        mat = local_from_head.reshape(-1, 3, 3)[box].view(rc, k, 3, 3)
        o_local = torch.einsum("ri,rkij->rkj", o[0], mat) - centre_local.reshape(-1, 3)[box].view(rc, k, 3)
        d_local = torch.einsum("ri,rkij->rkj", d[0], mat)  # [Rc, K, 3]
        local = o_local.reshape(-1, 3)[slot] + t[ri, si][:, None] * d_local.reshape(-1, 3)[slot]  # [Q, 3]
        base = box[slot] * m3  # [Q]
        rows, w = trilinear_corners(base, local, prims.voxels_per_side)  # [Q, 8]
        sigma_k = (density[rows] * w).sum(1)  # [Q]
        sample_id = ri * steps + si  # [Q]
        sigma = torch.zeros(rc * steps, dtype=density.dtype, device=density.device).index_add(0, sample_id, sigma_k)
        share = _sample_share(sigma.view(1, rc, steps), dt[None]).reshape(-1)  # [Rc*S]
        weight = (w * (sigma_k * dt[ri] * share[sample_id])[:, None]).reshape(-1)  # [Q*8]
        # Sum the weights per (ray, box, voxel) in a dense block, in ray order (no sort needed),
        # a block of rays at a time so that no block exceeds max_pairs entries.
        cell = (slot[:, None] * m3 + (rows - base[:, None])).reshape(-1)  # [Q*8], ascending by ray
        per_block = max(1, max_pairs // (k * m3))
        bounds = torch.searchsorted(cell, torch.arange(0, rc + per_block, per_block, device=cell.device) * (k * m3))
        for j in range(0, rc, per_block):
            lo, hi = int(bounds[j // per_block]), int(bounds[j // per_block + 1])
            first = j * k * m3
            block = torch.zeros(min(per_block, rc - j) * k * m3, dtype=density.dtype, device=density.device)
            block.index_add_(0, cell[lo:hi] - first, weight[lo:hi])
            nz = block.nonzero().squeeze(1) + first  # ascending: ray-major
            ray, column = nz // (k * m3) + start, box[nz // m3] * m3 + nz % m3
            order = torch.argsort(ray * (p * m3) + column)  # CSR wants each row's columns sorted
            crow.append(ray[order])
            ccol.append(column[order])
            cval.append(block[nz - first][order])
        alphas.append((sigma.view(rc, steps) * dt[:, None]).sum(-1).clamp(max=1.0))  # [Rc]
    row_index = torch.cat(crow)
    crow_index = torch.zeros(r + 1, dtype=torch.int64, device=row_index.device)
    crow_index[1:] = torch.cumsum(torch.bincount(row_index, minlength=r), 0)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        matrix = torch.sparse_csr_tensor(crow_index, torch.cat(ccol), torch.cat(cval), (r, p * m3),
                                         check_invariants=True)
    return ColourTransport(matrix, torch.cat(alphas))


__all__ = ["ColourTransport", "colour_transport"]
