"""Differentiable raymarching of a mixture of volumetric primitives (MVP).

Each primitive k is a box (centre ``c_k``, rotation ``R_k`` whose columns are its local
axes, half extents ``h_k``) holding an M^3 grid of RGB and density voxels. A point x has
local coordinates ``y = R_k^T (x - c_k) / h_k`` in [-1, 1]^3 inside the box, where the
voxels are looked up trilinearly (voxel centres at ``(i + 0.5) / M * 2 - 1``, values
clamped at the border, as ``grid_sample(align_corners=False, padding_mode="border")``).

A ray is sampled at ``steps`` evenly spaced points over its span through the union of the
boxes it hits (a precomputed ray-box intersection, so the number of steps is fixed and no
sample is spent in empty space). Every primitive containing a sample adds its density
``sigma_k`` and colour; opacity accumulates additively as in MVP,
``A(t) = min(1, integral of sum_k sigma_k dt)``, and a sample's colour counts only with the
share of its opacity that still fits below 1 (MVP's early termination: past saturation
a sample contributes nothing and gets no gradient).

Three implementations give the same images:
- ``raymarch_reference``: obvious and slow; loops over primitives (``grid_sample`` on every
  sample) and over steps, stopping when every ray is opaque. For tests.
- ``raymarch(kernel="fused")``: the fused C++ CPU kernel (``avatar.raymarch_fused``), one
  pass per ray over its samples and boxes, nothing per (sample, box) pair kept, each ray
  taken into its candidate boxes' frames in the kernel, and each ray stopped at its first
  sample past opacity 1 (bit for bit the same result: later samples have a share of 0); what
  ``kernel="auto"`` runs on the CPU. Several times faster than the tensor path, with much less
  memory kept for backward (``python -m benchmarks.bench_raymarch``; the figures are in
  docs/experiments.md, section 4). In float64 both paths agree to ~1e-14; in float32, a
  sample within rounding of a box face can fall on either side, so a few rays in 10^4 differ
  by up to ~3e-3.
- ``raymarch(kernel="torch")``: the tensor-op fast path, CPU or GPU; keeps per ray only the
  primitives its ray hits, keeps only (sample, primitive) pairs that lie inside the box (from the entry/exit
  distances, no per-sample test), does the trilinear lookup with 8 gathers on those pairs
  only and scatters the results back with ``index_add``. Boxes go to local coordinates by
  one matrix per box with the half extents folded in, and the every-ray-against-every-box
  slab test is two batched matmuls and a single reciprocal (faster than per-pair einsums and
  divisions; docs/experiments.md, section 4).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import torch
import torch.nn.functional as F

from avatar.raymarch_fused import fused_module, fused_raymarch


@dataclass
class Primitives:
    """A batch of B sets of P primitives with M^3 voxels each.

    Attributes:
        centre: [B, P, 3] box centres, head space, metres.
        rotation: [B, P, 3, 3] head_from_local rotations (columns are the box's local axes).
        half_extent: [B, P, 3] half edge lengths, metres.
        rgb: [B, P, M, M, M, 3] linear RGB voxels, indexed [z, y, x] in local coordinates.
        density: [B, P, M, M, M] non-negative density voxels, per metre.
    """

    centre: torch.Tensor
    rotation: torch.Tensor
    half_extent: torch.Tensor
    rgb: torch.Tensor
    density: torch.Tensor

    @property
    def voxels_per_side(self) -> int:
        return int(self.density.shape[-1])

    def with_rgb(self, rgb: torch.Tensor) -> "Primitives":
        """The same geometry and opacity with other colours (light sums reuse one opacity)."""
        return Primitives(self.centre, self.rotation, self.half_extent, rgb, self.density)


@dataclass
class RenderResult:
    """Raymarched colour [B, R, 3] and accumulated opacity [B, R] of each ray.

    ``prim_alpha`` [B, P] (only when asked for): the largest opacity any of the rays gave
    to each primitive, i.e. the most a primitive ever added to a pixel's alpha (the share
    of the ray it filled before saturation). Primitives whose ``prim_alpha`` stays near 0
    over the training set can be pruned without changing the images.
    """

    rgb: torch.Tensor
    alpha: torch.Tensor
    prim_alpha: torch.Tensor | None = None


def local_frames(prims: Primitives) -> tuple[torch.Tensor, torch.Tensor]:
    """``local_from_head`` [B, P, 3, 3] and ``centre_local`` [B, P, 3]: y = x @ local_from_head - centre_local.

    ``y = R^T (x - c) / h`` with the division by the half extents folded into the matrix, so a
    ray-box pair costs one small matmul and no per-pair division.
    """
    local_from_head = prims.rotation / prims.half_extent[:, :, None, :]  # [B, P, 3, 3] (R_ij / h_j)
    centre_local = (prims.centre[..., None] * local_from_head).sum(-2)  # [B, P, 3]
    return local_from_head, centre_local


@torch.no_grad()
def box_intervals(prims: Primitives, rays_o: torch.Tensor, rays_d: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Entry and exit distances of every ray [B, R] in every box [B, P] (slab test).

    Returns ``hit`` [B, R, P] (bool), ``t_near`` [B, R, P] (clamped at 0) and ``t_far`` [B, R, P].
    """
    b, p = prims.centre.shape[:2]
    local_from_head, centre_local = local_frames(prims)
    flat = local_from_head.detach().transpose(1, 2).reshape(b, 3, p * 3)  # [B, 3, P*3]
    # Every ray against every box as two batched matmuls [B, R, 3] x [B, 3, P*3].
    o_local = (rays_o @ flat).view(b, -1, p, 3) - centre_local.detach()[:, None]  # [B, R, P, 3]
    d_local = (rays_d @ flat).view(b, -1, p, 3)  # [B, R, P, 3]
    return slab_test(o_local, d_local)


@torch.no_grad()
def slab_test(o_local: torch.Tensor, d_local: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rays already in a box's local coordinates [..., 3] against the box ``|y|_inf <= 1``.

    Returns ``hit`` (bool), ``t_near`` (clamped at 0: nothing behind the origin) and ``t_far``, each [...].
    """
    tiny = torch.full_like(d_local, 1e-12)
    inv_d = 1.0 / torch.where(d_local.abs() < 1e-12, torch.copysign(tiny, d_local), d_local)
    # The slabs |o + t d| <= 1 per axis: t in (-o/d) -+ 1/|d|.
    mid = -o_local * inv_d
    reach = inv_d.abs()
    t_near = (mid - reach).amax(-1).clamp(min=0.0)
    t_far = (mid + reach).amin(-1)
    return t_far > t_near, t_near, t_far


@torch.no_grad()
def ray_samples(hit: torch.Tensor, t_near: torch.Tensor, t_far: torch.Tensor, steps: int
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample distances [B, R, S] (midpoints of S equal steps over each ray's span) and step length [B, R].

    A ray that hits no box gets step length 0 (it renders black and transparent).
    """
    inf = torch.finfo(t_near.dtype).max
    t_min = torch.where(hit, t_near, torch.full_like(t_near, inf)).amin(-1)  # [B, R]
    t_max = torch.where(hit, t_far, torch.full_like(t_far, -inf)).amax(-1)  # [B, R]
    any_hit = hit.any(-1)
    t_min = torch.where(any_hit, t_min, torch.zeros_like(t_min))
    t_max = torch.where(any_hit, t_max, torch.zeros_like(t_max))
    dt = (t_max - t_min) / steps  # [B, R]
    s = torch.arange(steps, dtype=t_near.dtype, device=t_near.device) + 0.5
    t = t_min[..., None] + s * dt[..., None]  # [B, R, S]
    return t, dt


def composite(sigma: torch.Tensor, sigma_rgb: torch.Tensor, dt: torch.Tensor) -> RenderResult:
    """MVP's additive compositing of per-sample density [B, R, S] and density-weighted colour [B, R, S, 3]."""
    opacity = sigma * dt[..., None]  # [B, R, S]
    acc = torch.cumsum(opacity, -1)
    before = acc - opacity
    # Share of each sample's opacity below saturation: 1 until the ray is opaque, then 0.
    share = ((1.0 - before) / opacity.clamp(min=1e-10)).clamp(0.0, 1.0)  # [B, R, S]
    rgb = (sigma_rgb * (dt[..., None] * share)[..., None]).sum(-2)  # [B, R, 3]
    alpha = acc[..., -1].clamp(max=1.0) if acc.shape[-1] else opacity.sum(-1)
    return RenderResult(rgb=rgb, alpha=alpha)


RaymarchKernel = Literal["auto", "fused", "torch"]
KERNELS: tuple[str, ...] = get_args(RaymarchKernel)


def resolve_kernel(kernel: RaymarchKernel, device: torch.device, dtype: torch.dtype) -> Literal["fused", "torch"]:
    """The raymarcher ``kernel`` runs on tensors of ``device`` and ``dtype`` (building the fused one if needed).

    ``"fused"`` insists: ``ValueError`` where it does not apply, ``FusedKernelUnavailable``
    where it cannot be built. ``"auto"`` picks it where it applies and builds.
    """
    if kernel not in KERNELS:
        raise ValueError(f"raymarch kernel {kernel!r} is not one of {', '.join(KERNELS)}")
    if kernel == "torch":
        return "torch"
    applies = device.type == "cpu" and dtype in (torch.float32, torch.float64)
    if kernel == "fused":
        if not applies:
            raise ValueError("the fused raymarcher takes CPU float32 or float64 tensors; "
                             f"got {device.type} {dtype}: use kernel='auto' or 'torch'")
        fused_module(required=True)
        return "fused"
    return "fused" if applies and fused_module(required=False) is not None else "torch"


_CORNERS = torch.tensor([[dx, dy, dz] for dz in (0, 1) for dy in (0, 1) for dx in (0, 1)])  # [8, 3] (x, y, z)


def trilinear_corners(base: torch.Tensor, local: torch.Tensor, m: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows [Q, 8] of the 8 voxels around local coordinates [Q, 3] and their trilinear weights [Q, 8].

    ``base`` [Q] is the row of each primitive's voxel (0, 0, 0); voxels are stored z-major.
    Shared by the lookup below and the light-transfer bake's transport (``avatar.transport``).
    """
    g = ((local + 1.0) * 0.5 * m - 0.5).clamp(0.0, m - 1.0)  # [Q, 3] voxel coordinates (x, y, z)
    i0 = g.detach().floor().clamp(max=m - 2).long()  # [Q, 3]
    f = g - i0.to(g.dtype)  # [Q, 3] in [0, 1]
    corners = _CORNERS.to(local.device)  # [8, 3]
    idx = i0[:, None, :] + corners  # [Q, 8, 3]
    rows = base[:, None] + (idx[..., 2] * m + idx[..., 1]) * m + idx[..., 0]  # [Q, 8]
    wx = torch.stack([1.0 - f[:, 0], f[:, 0]], -1)  # [Q, 2]
    wy = torch.stack([1.0 - f[:, 1], f[:, 1]], -1)
    wz = torch.stack([1.0 - f[:, 2], f[:, 2]], -1)
    w = (wz[:, :, None, None] * wy[:, None, :, None] * wx[:, None, None, :]).reshape(-1, 8)  # [Q, 8] (z, y, x)
    return rows, w


def _trilinear_gather(table: torch.Tensor, base: torch.Tensor, local: torch.Tensor, m: int) -> torch.Tensor:
    """Trilinear lookup of voxel rows [Q, C] in ``table`` [*, C] at local coordinates [Q, 3].

    One gather of all 8 corners (its backward is a single scatter-add).
    """
    rows, w = trilinear_corners(base, local, m)
    values = table[rows.reshape(-1)].view(rows.shape[0], 8, table.shape[-1])  # [Q, 8, C] (Q may be 0: no ray hits)
    return (values * w[..., None]).sum(1)  # [Q, C]


def _sample_share(sigma: torch.Tensor, dt: torch.Tensor) -> torch.Tensor:
    """Share [B, R, S] of each sample's opacity below saturation (1 until the ray is opaque, then 0)."""
    opacity = sigma * dt[..., None]  # [B, R, S]
    before = torch.cumsum(opacity, -1) - opacity
    return ((1.0 - before) / opacity.clamp(min=1e-10)).clamp(0.0, 1.0)


def raymarch(prims: Primitives, rays_o: torch.Tensor, rays_d: torch.Tensor, steps: int,
             max_pairs: int = 1 << 23, prim_stats: bool = False, kernel: RaymarchKernel = "auto") -> RenderResult:
    """Render rays [B, R, 3] (origins, unit directions; head space) through ``prims``: the fast path.

    Differentiable in the primitives' geometry, colours and densities. Rays are processed in
    chunks so that no [B, R_chunk, P] intermediate exceeds ``max_pairs`` entries.
    ``prim_stats``: also return ``prim_alpha`` [B, P] (see ``RenderResult``; not differentiable).
    ``kernel``: ``"fused"`` the C++ CPU kernel (``avatar.raymarch_fused``; CPU tensors only),
    ``"torch"`` tensor ops (CPU or GPU), ``"auto"`` the fused kernel where it applies and builds
    (CPU float tensors), tensor ops otherwise. All give the same images and gradients.
    """
    b, r, _ = rays_o.shape
    p = prims.centre.shape[1]
    chunk = max(1, min(r, max_pairs // max(1, b * p)))
    if chunk < r:
        parts = [raymarch(prims, rays_o[:, i:i + chunk], rays_d[:, i:i + chunk], steps, max_pairs, prim_stats,
                          kernel)
                 for i in range(0, r, chunk)]
        prim_alpha = torch.stack([x.prim_alpha for x in parts]).amax(0) if prim_stats else None
        return RenderResult(torch.cat([x.rgb for x in parts], 1), torch.cat([x.alpha for x in parts], 1),
                            prim_alpha)
    if resolve_kernel(kernel, prims.density.device, prims.density.dtype) == "fused":
        return _raymarch_fused(prims, rays_o, rays_d, steps, prim_stats)
    m = prims.voxels_per_side
    hit, t_near, t_far = box_intervals(prims, rays_o, rays_d)
    t, dt = ray_samples(hit, t_near, t_far, steps)  # [B, R, S], [B, R]
    with torch.no_grad():
        k = max(1, int(hit.sum(-1).max()))
        cand_hit, cand = torch.topk(hit.to(torch.uint8), k, dim=-1)  # [B, R, K] candidates per ray
        cand_near = torch.gather(t_near, -1, cand)  # [B, R, K]
        cand_far = torch.gather(t_far, -1, cand)
        inside = (cand_hit.bool()[:, :, None, :] & (t[..., None] >= cand_near[:, :, None, :])
                  & (t[..., None] <= cand_far[:, :, None, :]))  # [B, R, S, K]
        bi, ri, si, ki = inside.nonzero(as_tuple=True)  # Q (sample, primitive) pairs inside a box
        pair_ray = (bi * r + ri) * k + ki  # [Q] row of the (ray, candidate)
        t_q = t[bi, ri, si]  # [Q]
    # The ray in each candidate's local frame, y(t) = o_local + t d_local (differentiable).
    flat_p = (torch.arange(b, device=cand.device)[:, None, None] * p + cand).reshape(-1)  # [B*R*K]
    local_from_head, centre_local = local_frames(prims)  # differentiable in the geometry
    mat = local_from_head.reshape(-1, 3, 3)[flat_p].view(b, r, k, 3, 3)
    o_local = (torch.einsum("bri,brkij->brkj", rays_o, mat)
               - centre_local.reshape(-1, 3)[flat_p].view(b, r, k, 3))  # [B, R, K, 3]
    d_local = torch.einsum("bri,brkij->brkj", rays_d, mat)  # [B, R, K, 3]
    local = o_local.reshape(-1, 3)[pair_ray] + t_q[:, None] * d_local.reshape(-1, 3)[pair_ray]  # [Q, 3]
    table = torch.cat([prims.rgb, prims.density[..., None]], -1).reshape(-1, 4)  # [B*P*M^3, 4]
    rgba = _trilinear_gather(table, flat_p[pair_ray] * (m ** 3), local, m)  # [Q, 4]
    sigma_k = rgba[:, 3]
    sample_id = (bi * r + ri) * steps + si  # [Q]
    n_samples = b * r * steps
    sigma = torch.zeros(n_samples, dtype=table.dtype, device=table.device).index_add(0, sample_id, sigma_k)
    sigma_rgb = torch.zeros(n_samples, 3, dtype=table.dtype, device=table.device).index_add(
        0, sample_id, rgba[:, :3] * sigma_k[:, None])
    result = composite(sigma.view(b, r, steps), sigma_rgb.view(b, r, steps, 3), dt)
    if prim_stats:
        with torch.no_grad():
            share = _sample_share(sigma.detach().view(b, r, steps), dt).reshape(-1)  # [B*R*S]
            # Opacity each (sample, primitive) pair adds below saturation, summed per (ray, primitive).
            added = sigma_k.detach() * dt.reshape(-1)[bi * r + ri] * share[sample_id]  # [Q]
            per_ray = torch.zeros(b * r * k, dtype=added.dtype, device=added.device).index_add(0, pair_ray, added)
            prim_alpha = torch.zeros(b * p, dtype=added.dtype, device=added.device).scatter_reduce(
                0, flat_p, per_ray, reduce="amax", include_self=True)
        result.prim_alpha = prim_alpha.view(b, p)
    return result


def _raymarch_fused(prims: Primitives, rays_o: torch.Tensor, rays_d: torch.Tensor, steps: int,
                    prim_stats: bool) -> RenderResult:
    """``raymarch`` by the fused CPU kernel: the slab test and the march run in C++ per ray."""
    b, r, _ = rays_o.shape
    p = prims.centre.shape[1]
    m = prims.voxels_per_side
    local_from_head, centre_local = local_frames(prims)  # differentiable in the geometry
    module = fused_module(required=True)
    with torch.no_grad():
        cand, near, far, t_min, t_max = module.candidates(
            rays_o.detach().contiguous(), rays_d.detach().contiguous(), local_from_head.detach().contiguous(),
            centre_local.detach().contiguous(), prims.centre.detach().contiguous(),
            prims.half_extent.detach().norm(dim=-1).contiguous())  # [B*R, K] x3, [B*R] x2
        k = cand.shape[1]
        dt = (t_max - t_min) / steps  # [B*R]
        t = t_min[:, None] + (torch.arange(steps, dtype=dt.dtype) + 0.5) * dt[:, None]  # [B*R, S]
        batch_of_ray = torch.arange(b).repeat_interleave(r)[:, None]  # [B*R, 1]
        flat_p = batch_of_ray * p + cand.clamp(min=0)  # [B*R, K] primitive row over the batch
        prim = torch.where(cand >= 0, flat_p, -1)  # [B*R, K]
    # The kernel takes each ray into its candidates' frames itself, y(t) = o_local + t d_local, and
    # returns the gradients of the frames (local_from_head, centre_local) per box.
    table = torch.cat([prims.rgb, prims.density[..., None]], -1).reshape(-1, 4)  # [B*P*M^3, 4]
    rgb, alpha, added = fused_raymarch(table, local_from_head.reshape(-1, 3, 3), centre_local.reshape(-1, 3), prim,
                                       rays_o.reshape(-1, 3), rays_d.reshape(-1, 3), near, far, t, dt, m,
                                       with_added=prim_stats)
    prim_alpha = None
    if prim_stats:  # empty slots added 0, so their stand-in row (clamped to the batch item's box 0) is harmless
        prim_alpha = torch.zeros(b * p, dtype=added.dtype).scatter_reduce(
            0, flat_p.reshape(-1), added.reshape(-1), reduce="amax", include_self=True).view(b, p)
    return RenderResult(rgb=rgb.view(b, r, 3), alpha=alpha.view(b, r), prim_alpha=prim_alpha)


def raymarch_reference(prims: Primitives, rays_o: torch.Tensor, rays_d: torch.Tensor, steps: int) -> RenderResult:
    """The slow, obvious raymarcher: every sample against every primitive, then a loop over steps."""
    b, r, _ = rays_o.shape
    p = prims.centre.shape[1]
    hit, t_near, t_far = box_intervals(prims, rays_o, rays_d)
    t, dt = ray_samples(hit, t_near, t_far, steps)
    x = rays_o[:, :, None] + t[..., None] * rays_d[:, :, None]  # [B, R, S, 3]
    sigma = torch.zeros(b, r, steps, dtype=prims.density.dtype, device=x.device)
    sigma_rgb = torch.zeros(b, r, steps, 3, dtype=prims.density.dtype, device=x.device)
    for k in range(p):
        local = torch.einsum("brsi,bij->brsj", x - prims.centre[:, k, None, None], prims.rotation[:, k]) \
            / prims.half_extent[:, k, None, None]  # [B, R, S, 3]
        inside = (local.detach().abs() <= 1.0).all(-1) & hit[:, :, k, None]  # [B, R, S]
        volume = torch.cat([prims.rgb[:, k], prims.density[:, k, ..., None]], -1).permute(0, 4, 1, 2, 3)
        rgba = F.grid_sample(volume, local[:, :, :, None], mode="bilinear", padding_mode="border",
                             align_corners=False)[..., 0].permute(0, 2, 3, 1)  # [B, R, S, 4]
        rgba = rgba * inside[..., None]
        sigma = sigma + rgba[..., 3]
        sigma_rgb = sigma_rgb + rgba[..., :3] * rgba[..., 3:]
    rgb = torch.zeros(b, r, 3, dtype=sigma.dtype, device=sigma.device)
    acc = torch.zeros(b, r, dtype=sigma.dtype, device=sigma.device)
    for s in range(steps):
        if bool((acc >= 1.0).all()):
            break  # early termination: every ray is opaque
        opacity = sigma[..., s] * dt
        share = ((1.0 - acc) / opacity.clamp(min=1e-10)).clamp(0.0, 1.0)
        rgb = rgb + sigma_rgb[..., s, :] * (dt * share)[..., None]
        acc = acc + opacity
    return RenderResult(rgb=rgb, alpha=acc.clamp(max=1.0))
