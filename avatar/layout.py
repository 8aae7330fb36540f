"""Where the N x N primitives sit on the guide mesh (MVP's UV layout, built once).

The tracked mesh (ICT topology, ~26k vertices) has UV islands for the eyeballs, teeth,
mouth socket and so on, most of them never visible. Rather than spread the primitives
over all islands we give the outer surface of the head its own UV layout: a
latitude-longitude grid around the head centre, restricted to the front
(``|azimuth| <= theta_max``), each grid point mapped onto the outermost surface by casting
a ray from outside towards the centre. A grid point is then (triangle, barycentric
coordinates) on the mesh, so it follows the mesh as it deforms. Only the vertices of those
anchor triangles are kept as the guide mesh ("decimation" to <= 3 N^2 vertices); the
encoder reads them and the decoder predicts them.

What the grid misses: the crown above the top row (70 degrees of elevation by default). In
views from above it is most of the foreground a trained model leaves transparent (the train
stage's ``*_uncovered_fraction``). Stretching the rows higher does not pay: it coarsens every
row and crowds the top rows near the pole; covering it needs a grid whose pole is not on the
head. The ``azimuthal`` projection is such a grid (an equidistant map centred in front,
reaching over the crown), but its corners wrap round behind the ears and lengthen the rays'
spans through the boxes, which thins the samples where the face is. ``latlong`` stays the
default; docs/experiments.md, section 3, has the measurements.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from avatar.config import AvatarConfig


@dataclass(frozen=True)
class GuideLayout:
    """Anchors of the N^2 primitives on the guide mesh.

    Attributes:
        guide_vertex_ids: [U] indices of the guide vertices in the full tracked mesh.
        anchor_tris: [P, 3] anchor triangle of each primitive, as indices into the guide vertices.
        anchor_bary: [P, 3] barycentric coordinates of the primitive centre in its triangle.
        normal_sign: [P] +1 or -1 so that the triangle normal points out of the head.
        half_extent_m: [P] base half edge length of each primitive box, metres.
        mean_guide_vertices: [U, 3] guide vertices of the mean mesh (head space, metres).
        expression_basis: [K, 3U] orthonormal directions of the training expressions, over the
            guide vertices' flattened offsets from ``mean_guide_vertices``; where given, the
            encoder reads only the offsets' part along them (``RelightableMVP.encode``), so a
            direction the training meshes hold only as the tracker's jitter cannot reach the
            code. None: the encoder reads the whole offset.
    """

    guide_vertex_ids: np.ndarray
    anchor_tris: np.ndarray
    anchor_bary: np.ndarray
    normal_sign: np.ndarray
    half_extent_m: np.ndarray
    mean_guide_vertices: np.ndarray
    expression_basis: np.ndarray | None = None

    def as_arrays(self) -> dict[str, np.ndarray]:
        """The layout as named arrays (for checkpoints); an absent expression basis is left out."""
        return {k: np.asarray(getattr(self, k)) for k in self.__dataclass_fields__ if getattr(self, k) is not None}


def _barycentric(points: np.ndarray, tri_xyz: np.ndarray) -> np.ndarray:
    """Barycentric coordinates [K, 3] of points [K, 3] in triangles [K, 3, 3], clamped to the triangle."""
    a, b, c = tri_xyz[:, 0], tri_xyz[:, 1], tri_xyz[:, 2]
    v0, v1, v2 = b - a, c - a, points - a
    d00, d01, d11 = (v0 * v0).sum(-1), (v0 * v1).sum(-1), (v1 * v1).sum(-1)
    d20, d21 = (v2 * v0).sum(-1), (v2 * v1).sum(-1)
    denom = np.where(np.abs(d00 * d11 - d01 * d01) < 1e-20, 1e-20, d00 * d11 - d01 * d01)
    v = (d11 * d20 - d01 * d21) / denom
    w = (d00 * d21 - d01 * d20) / denom
    bary = np.clip(np.stack([1 - v - w, v, w], -1), 0.0, 1.0)
    return bary / bary.sum(-1, keepdims=True)


def grid_directions(n: int, projection: str = "latlong", theta_max_deg: float = 105.0,
                    elevation_range_deg: tuple[float, float] = (-75.0, 70.0),
                    centre_elevation_deg: float = 0.0) -> np.ndarray:
    """Unit directions [N*N, 3] (head space: +x actor's left, +y up, +z front) of the grid points.

    Row 0 is the top, columns go from -x to +x. ``latlong``: rows at equal steps of elevation
    over ``elevation_range_deg``, columns at equal steps of azimuth over +-``theta_max_deg``;
    its pole is straight up, so the crown above the top row is left out and the top rows'
    columns crowd together. ``azimuthal``: an azimuthal equidistant map centred on the
    direction at ``centre_elevation_deg`` in front; a grid point (x, y) lies at angular
    distance hypot(x, y) from the centre in the direction (x, y), with x over
    +-``theta_max_deg`` and y from ``elevation_range_deg[1]`` down to ``[0]`` measured along the
    central meridian (a top above 90 degrees reaches over the crown). Its only singular
    point is the centre's antipode, behind the head; its corners reach round to the back.
    """
    if projection == "latlong":
        az = np.deg2rad(np.linspace(-theta_max_deg, theta_max_deg, n))  # [N] columns
        el = np.deg2rad(np.linspace(elevation_range_deg[1], elevation_range_deg[0], n))  # [N] rows
        el_g, az_g = np.meshgrid(el, az, indexing="ij")  # [N, N]
        return np.stack([np.cos(el_g) * np.sin(az_g), np.sin(el_g), np.cos(el_g) * np.cos(az_g)], -1).reshape(-1, 3)
    if projection == "azimuthal":
        e0 = np.deg2rad(centre_elevation_deg)
        front = np.array([0.0, np.sin(e0), np.cos(e0)])
        right = np.array([1.0, 0.0, 0.0])
        up = np.array([0.0, np.cos(e0), -np.sin(e0)])
        x = np.deg2rad(np.linspace(-theta_max_deg, theta_max_deg, n))
        y = np.deg2rad(np.linspace(elevation_range_deg[1], elevation_range_deg[0], n)) - e0
        y_g, x_g = np.meshgrid(y, x, indexing="ij")  # [N, N]
        dist = np.hypot(x_g, y_g)
        if dist.max() >= np.pi:
            raise ValueError(f"azimuthal layout reaches {np.rad2deg(dist.max()):.0f} deg from its centre; "
                             "narrow layout_theta_deg or layout_elevation_deg to stay under 180")
        safe = np.where(dist > 0, dist, 1.0)
        dirs = (np.cos(dist)[..., None] * front
                + (np.sin(dist) / safe)[..., None] * (x_g[..., None] * right + y_g[..., None] * up))
        return dirs.reshape(-1, 3)
    raise ValueError(f"unknown layout projection {projection!r}: use 'latlong' or 'azimuthal'")


def build_layout(mean_vertices: np.ndarray, triangles: np.ndarray, prims_per_side: int,
                 theta_max_deg: float = 105.0, overlap: float = 1.4,
                 elevation_range_deg: tuple[float, float] = (-75.0, 70.0), projection: str = "latlong",
                 centre_elevation_deg: float = 0.0) -> GuideLayout:
    """Place N x N primitive anchors on the outer surface of ``mean_vertices`` [V, 3].

    ``triangles`` [T, 3] are the mesh's triangles (quads split beforehand). Rows of the
    grid go from the top of the head (row 0) to the chin/neck, columns from the actor's
    right to left as seen by a frontal camera; ``grid_directions`` says where the grid
    points look from the head's centre for each ``projection``.
    """
    import trimesh

    verts = np.asarray(mean_vertices, np.float64)
    tris = np.asarray(triangles, np.int64)
    mesh = trimesh.Trimesh(verts, tris, process=False)
    lo, hi = verts.min(0), verts.max(0)
    centre = 0.5 * (lo + hi)
    radius = float(np.linalg.norm(hi - lo))
    n = prims_per_side
    dirs = grid_directions(n, projection, theta_max_deg, elevation_range_deg, centre_elevation_deg)
    origins = centre + dirs * radius * 2.0
    locs, ray_ids, tri_ids = mesh.ray.intersects_location(origins, -dirs, multiple_hits=True)
    num = n * n
    best_tri = np.full(num, -1, np.int64)
    best_pt = np.zeros((num, 3))
    best_dist = np.full(num, np.inf)
    for loc, r, t in zip(locs, ray_ids, tri_ids):
        dist = np.linalg.norm(loc - origins[r])
        if dist < best_dist[r]:
            best_dist[r], best_tri[r], best_pt[r] = dist, t, loc
    missed = best_tri < 0
    if missed.any():
        # Grid points beyond the silhouette (below the neck, past the ears): nearest surface
        # point to where the ray passes closest to the centre.
        probe = centre + dirs[missed] * radius * 0.35
        pts, _, tids = trimesh.proximity.closest_point(mesh, probe)
        best_pt[missed], best_tri[missed] = pts, tids
    bary = _barycentric(best_pt, verts[tris[best_tri]])  # [P, 3]
    used = np.unique(tris[best_tri].reshape(-1))
    remap = -np.ones(len(verts), np.int64)
    remap[used] = np.arange(len(used))
    anchor_tris = remap[tris[best_tri]]  # [P, 3]
    # Outward normal sign from the neutral mesh.
    tri_xyz = verts[tris[best_tri]]
    normal = np.cross(tri_xyz[:, 1] - tri_xyz[:, 0], tri_xyz[:, 2] - tri_xyz[:, 0])
    outward = best_pt - centre
    sign = np.where((normal * outward).sum(-1) >= 0, 1.0, -1.0)
    # Base size from the spacing of neighbouring anchors on the grid.
    grid = best_pt.reshape(n, n, 3)
    spacing = np.zeros((n, n))
    count = np.zeros((n, n))
    for axis in (0, 1):
        d = np.linalg.norm(np.diff(grid, axis=axis), axis=-1)
        pad_lo = [(0, 0), (0, 0)]
        pad_hi = [(0, 0), (0, 0)]
        pad_lo[axis], pad_hi[axis] = (1, 0), (0, 1)
        spacing += np.pad(d, pad_lo) + np.pad(d, pad_hi)
        count += np.pad(np.ones_like(d), pad_lo) + np.pad(np.ones_like(d), pad_hi)
    spacing = (spacing / np.maximum(count, 1)).reshape(-1)
    median = float(np.median(spacing))
    half = 0.5 * overlap * np.clip(spacing, 0.5 * median, 2.0 * median)
    return GuideLayout(
        guide_vertex_ids=used.astype(np.int64), anchor_tris=anchor_tris.astype(np.int64),
        anchor_bary=bary.astype(np.float32), normal_sign=sign.astype(np.float32),
        half_extent_m=half.astype(np.float32), mean_guide_vertices=verts[used].astype(np.float32))


def layout_for(config: "AvatarConfig", mean_vertices: np.ndarray, triangles: np.ndarray) -> GuideLayout:
    """``build_layout`` with the grid, projection and overlap an ``AvatarConfig`` names."""
    return build_layout(mean_vertices, triangles, config.prims_per_side, config.layout_theta_deg,
                        config.prim_overlap, tuple(config.layout_elevation_deg), config.layout_projection,
                        config.layout_centre_elevation_deg)


def expression_basis(guide_offsets: np.ndarray, modes: int) -> np.ndarray:
    """The ``modes`` principal directions [modes, 3U] (orthonormal rows, float64) of vertex offsets [F, U, 3].

    The offsets are taken about their own mean, so the directions are the expression's spread
    whatever mean they were measured from. Computed from the [F, F] Gram matrix (F training
    frames is far below 3U coordinates).
    """
    x = np.asarray(guide_offsets, np.float64).reshape(len(guide_offsets), -1)
    if modes < 1 or len(x) < 2:
        raise ValueError(f"expression_basis: needs at least 1 mode and 2 frames, got {modes} and {len(x)}")
    x = x - x.mean(0)
    eig, vec = np.linalg.eigh(x @ x.T)
    order = np.argsort(eig)[::-1][:modes]
    if eig[order[-1]] <= 1e-12 * max(eig[order[0]], 1e-300):
        raise ValueError(f"expression_basis: the offsets span fewer than {modes} directions")
    return (vec[:, order].T @ x) / np.sqrt(eig[order])[:, None]  # x = U S Vt: the rows of Vt


def triangulate(faces: np.ndarray) -> np.ndarray:
    """Split polygons [F, 4] (triangles padded with -1) or triangles [F, 3] into triangles [T, 3]."""
    faces = np.asarray(faces, np.int64)
    if faces.shape[1] == 3:
        return faces
    tri_a = faces[:, [0, 1, 2]]
    quad = faces[:, 3] >= 0
    tri_b = faces[quad][:, [0, 2, 3]]
    return np.concatenate([tri_a, tri_b], 0)
