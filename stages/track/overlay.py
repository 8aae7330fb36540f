"""Overlay pictures: detected landmarks, fitted landmarks and the mesh wireframe on images."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from scene.camera import Camera
from scene.contact_sheet import label_tile, resize_to_width, tile_grid


def mesh_edges(faces: np.ndarray, vertex_mask: np.ndarray, max_edges: int) -> np.ndarray:
    """Unique edges [E, 2] of triangles whose vertices are all in ``vertex_mask`` (subsampled)."""
    tri = faces[np.all(vertex_mask[faces], axis=1)]
    edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    if len(edges) > max_edges:
        edges = edges[np.linspace(0, len(edges) - 1, max_edges).astype(int)]
    return edges


def draw_view(image_srgb: np.ndarray, camera: Camera, vertices_world: np.ndarray, edges: np.ndarray,
              detected_px: np.ndarray | None, fitted_world: np.ndarray | None, label: str) -> np.ndarray:
    """One annotated view: wireframe (blue), detected landmarks (green), fitted landmarks (red).

    Args:
        image_srgb: the image, uint8 [H, W, 3] RGB.
        camera: its camera.
        vertices_world: mesh vertices [V, 3] in world space.
        edges: edges [E, 2] to draw.
        detected_px: detector pixels [N, 2] (nan = missing), or None.
        fitted_world: fitted landmark positions [N, 3] (world), or None.
        label: text in the corner.
    """
    import cv2

    canvas = np.ascontiguousarray(image_srgb[..., ::-1])  # BGR for OpenCV
    uv, z = camera.project(vertices_world)
    ok = (z[edges[:, 0]] > 0) & (z[edges[:, 1]] > 0)
    segs = np.round(uv[edges[ok]] * 4).astype(np.int32)  # 2 fractional bits
    cv2.polylines(canvas, list(segs), False, (200, 120, 40), 1, lineType=cv2.LINE_AA, shift=2)
    if detected_px is not None:
        for u, v in detected_px[np.all(np.isfinite(detected_px), axis=1)]:
            cv2.circle(canvas, (int(round(u * 4)), int(round(v * 4))), 8, (60, 220, 60), -1, lineType=cv2.LINE_AA, shift=2)
    if fitted_world is not None:
        puv, pz = camera.project(fitted_world)
        for u, v in puv[pz > 0]:
            cv2.circle(canvas, (int(round(u * 4)), int(round(v * 4))), 6, (40, 40, 230), -1, lineType=cv2.LINE_AA, shift=2)
    label_tile(canvas, label, scale=0.4, origin=(4, 14))
    return canvas[..., ::-1]


def contact_sheet(tiles: Sequence[np.ndarray], columns: int, tile_width: int = 320) -> np.ndarray:
    """Tiles (uint8 RGB, any size) resized to ``tile_width`` and laid out in a grid."""
    if not tiles:
        return np.zeros((8, 8, 3), np.uint8)
    return tile_grid([resize_to_width(tile, tile_width) for tile in tiles], columns)
