"""TRAvatar* (the paper's re-implementation of the baseline): a fixed basis of training lights.

The network (``RelightableMVP`` with ``config.light_basis = L``) is conditioned on the view
directions and on L weights over the training lights: one-hot while training. A novel light
is rendered by barycentric interpolation over the Delaunay triangulation of the training
light directions: the three basis lights of the triangle holding the novel direction are
decoded separately and their RGB voxels blended with the barycentric weights (opacity does
not depend on light, so the blend is exact for the rendered image as well).

Directions are parameterised in 2D by azimuth ``atan2(x, z)`` and elevation ``asin(y)``
seen from the head origin (the rig's bars cover the frontal hemisphere, so there is no seam).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import Delaunay

from avatar.model import DecodedGeometry, RelightableMVP


def direction_uv(directions: np.ndarray) -> np.ndarray:
    """Unit directions [..., 3] (head space) -> (azimuth, elevation) radians [..., 2]."""
    d = np.asarray(directions, np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return np.stack([np.arctan2(d[..., 0], d[..., 2]), np.arcsin(np.clip(d[..., 1], -1.0, 1.0))], -1)


class LightBasis:
    """Barycentric interpolation weights over the Delaunay triangulation of basis light directions [L, 3]."""

    def __init__(self, directions: np.ndarray) -> None:
        self.directions = np.asarray(directions, np.float64)
        self.uv = direction_uv(self.directions)  # [L, 2]
        if len(self.uv) < 3:
            raise ValueError(f"TRAvatar* needs at least 3 training lights, got {len(self.uv)}")
        self.triangulation = Delaunay(self.uv)

    def weights(self, query_directions: np.ndarray) -> np.ndarray:
        """Weights [K, L] (three non-zero, summing to 1) for query directions [K, 3].

        A direction outside the basis' convex hull takes the triangle it is closest to (its
        barycentric coordinates clamped to the triangle and renormalised).
        """
        q = direction_uv(np.atleast_2d(query_directions))  # [K, 2]
        tri = self.triangulation
        out = np.zeros((len(q), len(self.uv)))
        for i, point in enumerate(q):
            # Barycentric coordinates of the point in every triangle; the containing one has all >= 0.
            t = tri.transform  # [S, 3, 2]
            b2 = np.einsum("sij,sj->si", t[:, :2], point[None] - t[:, 2])  # [S, 2]
            bary = np.concatenate([b2, 1.0 - b2.sum(-1, keepdims=True)], -1)  # [S, 3]
            s = int(np.argmax(bary.min(-1)))
            w = np.clip(bary[s], 0.0, None)
            out[i, tri.simplices[s]] = w / w.sum()
        return out

    def one_hot(self, basis_index: np.ndarray) -> np.ndarray:
        """Training weights [K, L] for basis lights ``basis_index`` [K]."""
        out = np.zeros((len(basis_index), len(self.uv)))
        out[np.arange(len(basis_index)), basis_index] = 1.0
        return out


def interpolated_rgb(model: RelightableMVP, geometry: DecodedGeometry, cam_pos: torch.Tensor,
                     weights: torch.Tensor, intensity: torch.Tensor | None = None) -> torch.Tensor:
    """RGB voxels [B, P, M, M, M, 3] for light weights [B, L] with at most 3 non-zeros: blend of one-hot decodes."""
    b, num_lights = weights.shape
    top_w, top_i = torch.topk(weights, min(3, num_lights), dim=-1)  # [B, 3]
    k = top_i.shape[1]
    one_hot = torch.zeros(b * k, num_lights, dtype=weights.dtype, device=weights.device)
    one_hot[torch.arange(b * k), top_i.reshape(-1)] = 1.0
    rgb = model.decode_rgb(geometry.repeat(k), cam_pos.repeat_interleave(k, 0), light_weights=one_hot)
    rgb = rgb.view(b, k, *rgb.shape[1:])
    blended = (rgb * top_w.view(b, k, 1, 1, 1, 1, 1)).sum(1)
    if intensity is not None:
        blended = blended * intensity.view(b, 1, 1, 1, 1, 1)
    return blended
