"""Where each detector landmark sits on the actor's surface (barycentric embedding).

Estimated once per capture:
1. triangulate every landmark from all views of the first full-on frame (the actor starts
   neutral), align the triangulated points rigidly to the neutral scan (initialised from
   known landmark correspondences, refined by ICP against the skin surface; all 468
   FaceMesh points take part, which pins the head's pitch), and snap each point to its
   closest point on the surface;
2. refine: fit pose and weights of a few full-on frames with that embedding (the pose
   refined by the head's outline where images give one), move the cameras into head space
   per frame, re-triangulate each landmark in head space with the fitted expression
   offsets removed, snap again. A landmark that the detector places consistently on the
   same skin point converges to it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from stages.track.fit import LandmarkModel
from stages.track.geometry import kabsch, robust_kabsch
from stages.track.rig import ActorRig


@dataclass(frozen=True)
class LandmarkEmbedding:
    """Landmarks as barycentric points on the rig's triangles.

    Attributes:
        landmark_ids: detector landmark indices [N] (FaceMesh numbering).
        triangles: triangle index per landmark [N] (into the rig's ``faces``).
        barycentric: barycentric coordinates per landmark [N, 3].
    """

    landmark_ids: np.ndarray
    triangles: np.ndarray
    barycentric: np.ndarray

    def points(self, faces: np.ndarray, vertices: np.ndarray) -> np.ndarray:
        """Landmark positions for vertices [..., V, 3] -> [..., N, 3]."""
        corners = vertices[..., faces[self.triangles], :]  # [..., N, 3, 3]
        return np.einsum("nk,...nkd->...nd", self.barycentric, corners)

    def subset(self, landmark_ids: np.ndarray) -> "LandmarkEmbedding":
        """The embedding of those of ``landmark_ids`` [M] that it holds, in this embedding's order."""
        keep = np.isin(self.landmark_ids, np.asarray(landmark_ids))
        return LandmarkEmbedding(self.landmark_ids[keep], self.triangles[keep], self.barycentric[keep])

    def model(self, rig: ActorRig) -> LandmarkModel:
        """The linear landmark model of ``rig`` at this embedding."""
        return LandmarkModel(mean_m=self.points(rig.faces, rig.neutral_m),
                             basis_m=self.points(rig.faces, rig.basis_m))

    def normals(self, rig: ActorRig, weights: np.ndarray | None = None) -> np.ndarray:
        """Unit surface normals [N, 3] at the landmarks (head space) for weights [K]."""
        verts = rig.neutral_m if weights is None else rig.mesh(weights)
        tri = verts[rig.faces[self.triangles]]  # [N, 3, 3]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


class SkinSurface:
    """Closest-point queries on a subset of the rig's triangles (the skin)."""

    def __init__(self, rig: ActorRig, triangle_ids: np.ndarray | None = None):
        self.triangle_ids = (np.arange(len(rig.faces)) if triangle_ids is None
                             else np.asarray(triangle_ids, dtype=np.int64))
        self.faces = rig.faces
        self.mesh = trimesh.Trimesh(rig.neutral_m, rig.faces[self.triangle_ids], process=False)

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Closest surface points [N, 3], distances [N], rig triangle ids [N], barycentric [N, 3]."""
        closest, distance, local_tri = self.mesh.nearest.on_surface(np.asarray(points, dtype=np.float64))
        tri_ids = self.triangle_ids[local_tri]
        bary = trimesh.triangles.points_to_barycentric(self.mesh.triangles[local_tri], closest)
        bary = np.clip(bary, 0.0, None)
        bary /= bary.sum(1, keepdims=True)
        return closest, distance, tri_ids, bary


def icp_to_surface(surface: SkinSurface, points_world: np.ndarray, head_from_world_R: np.ndarray,
                   head_from_world_t: np.ndarray, iterations: int = 40, outlier_factor: float = 3.0,
                   min_outlier_m: float = 2e-3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Point-to-point ICP of world points [N, 3] onto the surface, ignoring far points.

    A point counts when its distance is below ``max(outlier_factor * median, min_outlier_m)``:
    a fixed trimming fraction would also cut the far tail of ordinary triangulation noise,
    which lies along the viewing direction and would tilt the fit.

    Returns the refined head_from_world (R, t) and the per-point distance [N] (metres).
    """
    R, t = head_from_world_R.copy(), head_from_world_t.copy()
    dist = np.zeros(len(points_world))
    for _ in range(iterations):
        head = points_world @ R.T + t
        closest, dist, _, _ = surface.closest(head)
        keep = dist <= max(outlier_factor * float(np.median(dist)), min_outlier_m)
        if keep.sum() < 3:
            keep = np.ones(len(dist), dtype=bool)
        dR, dt = kabsch(head[keep], closest[keep])
        R, t = dR @ R, dR @ t + dt
        if np.linalg.norm(dR - np.eye(3)) < 1e-7 and np.linalg.norm(dt) < 1e-8:
            break
    head = points_world @ R.T + t
    _, dist, _, _ = surface.closest(head)
    return R, t, dist


def initial_alignment(points_world: np.ndarray, head_reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A first head_from_world (R, t) for triangulated landmarks [N, 3] (nan = not triangulated).

    ``head_reference`` [N, 3] holds the head-space positions of the landmarks with a known
    correspondence on the scan (nan elsewhere); a trimmed Kabsch over the known pairs. The
    caller needs at least 6 known, triangulated pairs.
    """
    known = np.all(np.isfinite(head_reference), axis=1) & np.all(np.isfinite(points_world), axis=1)
    R, t, _ = robust_kabsch(points_world[known], head_reference[known])
    return R, t


def embed_points(surface: SkinSurface, landmark_ids: np.ndarray, points_head: np.ndarray) -> LandmarkEmbedding:
    """Snap head-space points [N, 3] to the surface: the barycentric embedding."""
    _, _, tri_ids, bary = surface.closest(points_head)
    return LandmarkEmbedding(np.asarray(landmark_ids, dtype=np.int64), tri_ids, bary)
