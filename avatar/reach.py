"""How far the boxes miss foreground rays that none of them reaches (the trainer's reach term).

A training ray whose pixel the matte calls foreground, but that crosses no box, renders
transparent, and neither the photometric nor the matte loss can do anything about it: no
voxel lies on the ray, so no parameter has a gradient there. The grid of boxes at its base
size leaves such rays at the layout's edges (shoulders, the back of the neck, the crown);
which of them a run still reaches through its boxes' offsets and scales is otherwise left to
the draw of the seed.

``reach_penalty`` gives those rays a grip: for each, the distance by which the nearest box
misses it, measured in that box's own local coordinates (``y = R^T (x - c) / h``, where the
box is ``|y|_inf <= 1``). The distance is the Euclidean distance from the box centre to the
ray in those coordinates, less 1: positive for every ray that misses the box (a ray that
misses the cube misses its inscribed unit ball), and its gradient moves the nearest box's
centre towards the ray, turns it and grows its half extents along the gap. Only the nearest
box is pulled (the minimum over boxes), so one stray ray does not drag the whole grid.
"""

from __future__ import annotations

import torch

from avatar.raymarch import Primitives, box_intervals, local_frames, slab_test


def missed_rays(prims: Primitives, rays_o: torch.Tensor, rays_d: torch.Tensor, wanted: torch.Tensor) -> torch.Tensor:
    """[B, R] bool: the ``wanted`` rays (e.g. foreground pixels) that cross no box (every ray against every box)."""
    hit, _, _ = box_intervals(prims, rays_o, rays_d)
    return wanted & ~hit.any(-1)


def _local_rays(prims: Primitives, rays_o: torch.Tensor, rays_d: torch.Tensor, item: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """N rays [N, 3] of batch items ``item`` [N] in every box's local coordinates: origins and directions [N, P, 3]."""
    local_from_head, centre_local = local_frames(prims)  # [B, P, 3, 3], [B, P, 3], with gradients
    frames = local_from_head[item]  # [N, P, 3, 3]
    o = torch.einsum("nc,npcj->npj", rays_o, frames) - centre_local[item]
    d = torch.einsum("nc,npcj->npj", rays_d, frames)
    return o, d


def reach_penalty(prims: Primitives, rays_o: torch.Tensor, rays_d: torch.Tensor, wanted: torch.Tensor,
                  alpha: torch.Tensor) -> tuple[torch.Tensor, int]:
    """The reach term and how many ``wanted`` rays no box reaches.

    Args:
        prims: the boxes of B frames ([B, P] each), as raymarched (pruned boxes left out).
        rays_o, rays_d: [B, R, 3] ray origins and unit directions, head space.
        wanted: [B, R] bool, the rays that should reach a box (foreground under the matte).
        alpha: [B, R] the rays' rendered opacity. A ray that crosses a box gathers some opacity
            (the density is a softplus, positive), so only rays with none can have missed every
            box: the every-ray-against-every-box test (as costly as half a training step's
            raymarch) is left out, and the slab test runs on those few rays alone.

    Returns:
        The sum over the missed rays of the nearest box's gap (in its half extents), divided by
        all B x R rays: a mean over the batch, so its weight compares with the matte term's
        (an L1 mean over the same rays), and a scalar 0 with a graph when no ray is missed.
    """
    item, ray = (wanted & (alpha.detach() <= 0)).nonzero(as_tuple=True)  # [N] each
    o, d = _local_rays(prims, rays_o[item, ray], rays_d[item, ray], item)  # [N, P, 3] each
    # A density underflowed to 0 can leave a ray that crosses a box without opacity: the slab test drops it.
    missed = ~slab_test(o, d)[0].any(-1)  # [N]
    o, d = o[missed], d[missed]
    if o.shape[0] == 0:
        return prims.centre.sum() * 0.0, 0
    # The ray's point nearest the box centre (only ahead of the origin: the camera sees nothing behind it).
    t = (-(o * d).sum(-1) / (d * d).sum(-1).clamp(min=1e-12)).clamp(min=0.0)  # [N, P]
    gap = (o + t[..., None] * d).norm(dim=-1) - 1.0  # [N, P]
    nearest = gap.clamp(min=0.0).amin(-1)  # [N]
    return nearest.sum() / wanted.numel(), int(o.shape[0])
