"""The head-outline term: sub-pixel image contours and the smooth occluding contour of a mesh."""

from __future__ import annotations

import numpy as np
import trimesh

from scene.camera import Camera, look_at
from stages.track.geometry import PinholeArrays
from stages.track.silhouette import (ImageSilhouette, image_contour, model_contour_correspondences, outline_edges,
                                     vertex_normals)


def _disk_image(radius_px: float, centre: tuple[float, float], size: int = 120, samples: int = 8) -> np.ndarray:
    """An anti-aliased bright disk on black (coverage by supersampling), linear RGB."""
    offsets = (np.arange(samples) + 0.5) / samples - 0.5
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    coverage = np.zeros((size, size))
    for dy in offsets:
        for dx in offsets:
            coverage += (xx + dx - centre[0]) ** 2 + (yy + dy - centre[1]) ** 2 <= radius_px**2
    coverage /= samples**2
    return np.repeat((0.6 * coverage)[..., None], 3, axis=2).astype(np.float32)


def test_image_contour_finds_the_edge_to_a_tenth_of_a_pixel():
    centre, radius = (60.3, 58.7), 31.4
    pts = image_contour(_disk_image(radius, centre))
    assert len(pts) > 100
    r = np.linalg.norm(pts - np.array(centre), axis=1)
    assert abs(np.mean(r) - radius) < 0.1
    assert np.abs(r - radius).max() < 0.35
    assert len(image_contour(np.zeros((40, 40, 3), np.float32))) == 0


def test_occluding_contour_of_a_sphere_matches_its_image_outline():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    verts, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    cam = Camera("cam00", 160, 160, 400.0, 400.0, 79.5, 79.5, pose=look_at(np.array([0, 0, 1.0]), np.zeros(3)))
    cams = PinholeArrays.from_cameras([cam])
    # The true outline of a sphere of radius r at distance d: a circle of radius f r / sqrt(d^2 - r^2).
    radius_px = 400.0 * 0.1 / np.sqrt(1.0 - 0.01)
    angles = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    outline = np.stack([79.5 + radius_px * np.cos(angles), 79.5 + radius_px * np.sin(angles)], axis=1)
    sil = ImageSilhouette(outline)
    candidate = np.ones(len(verts), dtype=bool)
    views, points, targets, normals = model_contour_correspondences(
        cams, [sil], verts, vertex_normals(verts, faces), faces, outline_edges(faces), candidate,
        np.eye(3), np.zeros(3), max_distance_px=3.0)
    assert len(views) > 50
    uv, _ = cams.project(points)
    r = np.linalg.norm(uv[0] - 79.5, axis=1)
    # Points on the smooth occluding contour, not on the inside: within a small fraction of a pixel.
    assert abs(np.mean(r) - radius_px) < 0.15
