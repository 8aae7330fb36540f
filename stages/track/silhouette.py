"""Silhouette term for the head pose: the head's outline against a dark backdrop.

Landmarks pin the expression, but their detector biases change with the expression and
leak into the head's pitch (a raised brow reads partly as a nod). The outline of the whole
head (skull, ears, jaw, neck) is rigid and seen by every camera, so after the landmark fit
each frame's pose is refined with it: an ICP in the image between the model's occluding
contour and the image's foreground contour (point-to-line distances), together with the
landmark term.

Image side: the foreground is everything brighter than a fraction of the image's bright
level (the studio's backdrop is black); its outer contour, off the image border, in
ideal pixels. Model side: mesh vertices at grazing angles to the camera that lie on the
boundary of the projected mesh.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from scene.colour import luminance
from stages.track.geometry import PinholeArrays


def image_contour(linear_rgb: np.ndarray, threshold_fraction: float = 0.03, percentile: float = 99.0,
                  max_points: int = 1500) -> np.ndarray:
    """Outer contour pixels [M, 2] (image pixels, ordered along the contour) of the foreground.

    Points on the image border are dropped (the head leaving the frame is no silhouette).
    Empty [0, 2] when there is no foreground.
    """
    import cv2

    rgb = np.nan_to_num(np.asarray(linear_rgb, dtype=np.float32)[..., :3])
    lum = luminance(np.maximum(rgb, 0.0))
    level = float(np.percentile(lum, percentile))
    if level <= 1e-8:
        return np.zeros((0, 2))
    mask = (lum > threshold_fraction * level).astype(np.uint8)
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))  # sensor-noise specks
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return np.zeros((0, 2))
    pts = max(contours, key=cv2.contourArea)[:, 0, :].astype(np.float64)  # [M, 2] (x, y)
    H, W = mask.shape
    inside = (pts[:, 0] > 2) & (pts[:, 0] < W - 3) & (pts[:, 1] > 2) & (pts[:, 1] < H - 3)
    step = max(1, int(np.ceil(len(pts) / max_points)))
    keep = np.zeros(len(pts), dtype=bool)
    keep[::step] = True
    normals = contour_normals(pts)
    pts, normals = pts[keep & inside], normals[keep & inside]
    return _subpixel_edge(lum, mask, pts, normals)


def _bilinear(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    H, W = img.shape
    x = np.clip(xy[:, 0], 0, W - 1.001)
    y = np.clip(xy[:, 1], 0, H - 1.001)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    return ((1 - fx) * (1 - fy) * img[y0, x0] + fx * (1 - fy) * img[y0, x0 + 1]
            + (1 - fx) * fy * img[y0 + 1, x0] + fx * fy * img[y0 + 1, x0 + 1])


def _subpixel_edge(lum: np.ndarray, mask: np.ndarray, pts: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Move contour pixels (the foreground's outermost pixel centres) to the 50 % coverage edge.

    Along the outward normal, the edge lies where the luminance falls to half of the
    surface's value just inside (an anti-aliased edge pixel's value is its coverage times
    the surface's); without this the outline sits about half a pixel inside the head.
    """
    if not len(pts):
        return pts
    # Orient the normals outwards: a step along an outward normal leaves the mask.
    probe = np.round(pts + 1.5 * normals).astype(int)
    probe[:, 0] = np.clip(probe[:, 0], 0, mask.shape[1] - 1)
    probe[:, 1] = np.clip(probe[:, 1], 0, mask.shape[0] - 1)
    flip = mask[probe[:, 1], probe[:, 0]] > 0
    normals = np.where(flip[:, None], -normals, normals)
    surface = _bilinear(lum, pts - 1.5 * normals)  # fully covered, just inside
    here = _bilinear(lum, pts)
    out = _bilinear(lum, pts + normals)
    half = 0.5 * surface
    # Linear interpolation of the half-level crossing between this pixel and the next one out
    # (or the previous one in, when this pixel is already below half).
    step_out = np.clip((here - half) / np.maximum(here - out, 1e-9), 0.0, 1.0)
    inner = _bilinear(lum, pts - normals)
    step_in = -np.clip((half - here) / np.maximum(inner - here, 1e-9), 0.0, 1.0)
    offset = np.where(here >= half, step_out, step_in)
    return pts + offset[:, None] * normals


def contour_normals(points: np.ndarray) -> np.ndarray:
    """Unit normals [M, 2] of an ordered contour [M, 2] (from the neighbours' chord)."""
    if len(points) < 3:
        return np.tile([1.0, 0.0], (len(points), 1))
    tangent = np.roll(points, -1, axis=0) - np.roll(points, 1, axis=0)
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    return normal / np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-9)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals [V, 3]."""
    tri = vertices[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vn = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)


class ImageSilhouette:
    """One view's foreground contour in ideal pixels, with a KD-tree and normals."""

    def __init__(self, contour_ideal_px: np.ndarray):
        self.points = np.asarray(contour_ideal_px, dtype=np.float64)
        self.normals = contour_normals(self.points)
        self.tree = cKDTree(self.points) if len(self.points) else None


def outline_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges [E, 2] of a triangle list."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(edges, axis=1), axis=0)


def model_contour_correspondences(cams: PinholeArrays, silhouettes: list[ImageSilhouette | None],
                                  vertices_head: np.ndarray, normals_head: np.ndarray, faces: np.ndarray,
                                  edges: np.ndarray, candidate: np.ndarray, R: np.ndarray, t: np.ndarray,
                                  max_distance_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pairs (view, model contour point) -> (image contour point, its normal) for the current pose.

    Model contour points are the smooth occluding contour: on every mesh edge (``edges``,
    between ``candidate`` vertices) where the vertex normals turn from facing the camera
    to facing away, the zero crossing of ``n . (camera - x)`` (vertices at grazing angles
    would sit a fraction of a pixel inside the outline). Of those, the points on the
    boundary of the projected mesh (its vertices splatted, gaps closed) pair with their
    nearest image contour point when it is within ``max_distance_px``.

    Returns view ids [P], head-space points [P, 3], target points [P, 2], target normals [P, 2].
    """
    import cv2

    world = vertices_head @ R.T + t
    nrm = normals_head @ R.T
    centres = -np.einsum("cji,cj->ci", cams.R, cams.t)  # camera centres in world [C, 3]
    uv_all, z_all = cams.project(world)
    edges = edges[candidate[edges[:, 0]] & candidate[edges[:, 1]]]
    views, points, targets, tnormals = [], [], [], []
    for c, sil in enumerate(silhouettes):
        if sil is None or sil.tree is None:
            continue
        W, H = int(cams.size_px[c, 0]), int(cams.size_px[c, 1])
        uv, z = uv_all[c], z_all[c]
        facing = np.einsum("vd,vd->v", centres[c] - world, nrm)  # [V] > 0: facing the camera
        sa, sb = facing[edges[:, 0]], facing[edges[:, 1]]
        crossing = (sa * sb < 0) & (z[edges[:, 0]] > 0) & (z[edges[:, 1]] > 0)
        if not crossing.any():
            continue
        e = edges[crossing]
        frac = (sa[crossing] / (sa[crossing] - sb[crossing]))[:, None]
        p_head = vertices_head[e[:, 0]] * (1 - frac) + vertices_head[e[:, 1]] * frac  # [K, 3]
        p_uv = uv[e[:, 0]] * (1 - frac) + uv[e[:, 1]] * frac  # [K, 2] (linear in the image: edges are short)
        # Boundary of the projected mesh: splat its vertices and close the gaps between them
        # (rasterising every triangle costs ~50 ms a view; the splat, a millisecond), then
        # keep the contour points near that mask's edge (interior folds, nose, ears' inner rims).
        edge_px = np.linalg.norm(uv[faces[::7, 0]] - uv[faces[::7, 1]], axis=1)
        gap = int(np.clip(np.ceil(2.0 * np.median(edge_px)), 1, 15))
        mask = np.zeros((H + 2, W + 2), np.uint8)  # a one-pixel frame keeps the edge off the border
        pix = np.round(uv[candidate]).astype(int) + 1
        inside_px = (pix[:, 0] >= 1) & (pix[:, 0] <= W) & (pix[:, 1] >= 1) & (pix[:, 1] <= H) & (z[candidate] > 0)
        mask[pix[inside_px, 1], pix[inside_px, 0]] = 1
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * gap + 1, 2 * gap + 1))
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel)
        dist_to_edge = cv2.distanceTransform(mask, cv2.DIST_L2, 3)
        px = np.clip(np.round(p_uv).astype(int) + 1, [0, 0], [W + 1, H + 1])
        on_edge = dist_to_edge[px[:, 1], px[:, 0]] <= max(1.5, 0.5 * gap)
        inside = (p_uv[:, 0] >= 0) & (p_uv[:, 0] <= W - 1) & (p_uv[:, 1] >= 0) & (p_uv[:, 1] <= H - 1)
        keep = on_edge & inside
        if not keep.any():
            continue
        d, nearest = sil.tree.query(p_uv[keep])
        ok = d <= max_distance_px
        views.append(np.full(int(ok.sum()), c))
        points.append(p_head[keep][ok])
        targets.append(sil.points[nearest[ok]])
        tnormals.append(sil.normals[nearest[ok]])
    if not views:
        return np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 2)), np.zeros((0, 2))
    return np.concatenate(views), np.concatenate(points), np.concatenate(targets), np.concatenate(tnormals)
