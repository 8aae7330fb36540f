"""A bar's highlight on a mirror ball: find it, and turn it into reflected world rays."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scene.camera import Camera


@dataclass(frozen=True)
class Highlight:
    """One bar's highlight on one ball in one camera."""

    camera: str
    sphere: int
    centroid_px: np.ndarray  # [2] intensity-weighted centre
    major_px: np.ndarray  # [2] unit direction of the long axis in the image
    sigma_major_px: float  # spread along the long axis
    sigma_minor_px: float
    peak: float
    saturated: bool
    endpoints_px: np.ndarray | None = None  # [2, 2] the streak's two ends (half-maximum), None if too short
    ridge_px: np.ndarray | None = None  # [K, 2] points on the streak's centre line, between its ends
    mid_px: np.ndarray | None = None  # [2] the ridge point halfway between the ends


def streak_ridge(grey: np.ndarray, bg: float, ends_px: np.ndarray, step_px: float = 0.5,
                 half_width_px: float = 2.5) -> np.ndarray:
    """Points on a streak's centre line between its ends [K, 2] (the middle one first).

    A line reflected in a ball images as a curve; its intensity centroid lies off the curve
    (on the concave side) and its viewing ray misses the bar. Cross-sections are symmetric
    about the curve, so each cross-section's centroid is on it.
    """
    from scipy.ndimage import map_coordinates

    axis = ends_px[1] - ends_px[0]
    length = float(np.linalg.norm(axis))
    axis = axis / max(length, 1e-9)
    perp = np.array([-axis[1], axis[0]])
    n_half = max(int(0.4 * length / step_px), 0)
    t = 0.5 * length + step_px * np.concatenate([[0], np.arange(1, n_half + 1), -np.arange(1, n_half + 1)])
    u = np.arange(-half_width_px, half_width_px + 1e-9, 0.1)
    pts = ends_px[0] + t[:, None, None] * axis + u[None, :, None] * perp  # [T, U, 2]
    vals = map_coordinates(grey, [pts[..., 1].ravel(), pts[..., 0].ravel()], order=1, mode="nearest"
                           ).reshape(len(t), len(u)) - bg
    w = np.maximum(vals - 0.2 * vals.max(axis=1, keepdims=True), 0.0)  # the core only: noise tails bias it
    ok = w.sum(axis=1) > 0
    u_c = (w * u).sum(axis=1) / np.maximum(w.sum(axis=1), 1e-12)
    ridge = ends_px[0] + t[:, None] * axis + u_c[:, None] * perp
    return ridge[ok]


def streak_endpoints(grey: np.ndarray, bg: float, centroid_px: np.ndarray, major_px: np.ndarray,
                     sigma_major_px: float, half_width_px: float = 2.0) -> np.ndarray | None:
    """The two ends of an elongated highlight, at half its plateau, along its long axis [2, 2].

    A bar has the same radiance along its length, so its highlight is a uniform streak and
    its half-maximum ends are the images of the bar's ends, whatever the (non-linear)
    mirror mapping in between does; the centroid is not (it is pulled towards the end
    the mirror compresses). The profile is summed across the streak so a slight bend or
    an off-axis centroid does not cut it.
    """
    from scipy.ndimage import map_coordinates

    reach = 3.0 * sigma_major_px + 4.0
    t = np.arange(-reach, reach + 1e-9, 0.05)  # along the axis, px
    u = np.arange(-half_width_px, half_width_px + 1e-9, 0.25)  # across
    perp = np.array([-major_px[1], major_px[0]])
    pts = centroid_px + t[:, None, None] * major_px + u[None, :, None] * perp  # [T, U, 2]
    prof = map_coordinates(grey, [pts[..., 1].ravel(), pts[..., 0].ravel()], order=1, mode="constant",
                           cval=bg).reshape(len(t), len(u)).sum(axis=1) - bg * len(u)  # [T]
    plateau = float(np.max(prof))
    if plateau <= 0:
        return None
    above = prof >= 0.5 * plateau
    idx = np.nonzero(above)[0]
    if len(idx) < 2 or idx[0] == 0 or idx[-1] == len(t) - 1:
        return None
    i0, i1 = idx[0], idx[-1]
    # linear interpolation of the half-maximum crossing on each side
    t0 = t[i0 - 1] + (0.5 * plateau - prof[i0 - 1]) / (prof[i0] - prof[i0 - 1]) * (t[i0] - t[i0 - 1])
    t1 = t[i1] + (prof[i1] - 0.5 * plateau) / (prof[i1] - prof[i1 + 1]) * (t[i1 + 1] - t[i1])
    return np.stack([centroid_px + t0 * major_px, centroid_px + t1 * major_px])


def find_highlight(grey: np.ndarray, centre_px: np.ndarray, radius_px: float, bg: float, sigma: float,
                   min_snr: float, white_level: float | None, camera: str, sphere: int) -> Highlight | None:
    """The brightest blob inside a ball's disc; None when nothing rises ``min_snr`` sigmas above the background."""
    import cv2

    h, w = grey.shape
    r_in = 0.97 * radius_px  # stay off the anti-aliased rim
    x0, x1 = max(int(centre_px[0] - r_in), 0), min(int(centre_px[0] + r_in) + 2, w)
    y0, y1 = max(int(centre_px[1] - r_in), 0), min(int(centre_px[1] + r_in) + 2, h)
    if x1 <= x0 or y1 <= y0:
        return None
    yy, xx = np.mgrid[y0:y1, x0:x1]
    inside = (xx - centre_px[0]) ** 2 + (yy - centre_px[1]) ** 2 <= r_in ** 2
    patch = np.where(inside, grey[y0:y1, x0:x1] - bg, 0.0)
    peak = float(patch.max())
    if peak < min_snr * sigma:
        return None
    # the connected bright region around the peak
    level = max(0.1 * peak, 4 * sigma)
    n, labels = cv2.connectedComponents((patch > level).astype(np.uint8), connectivity=8)
    py, px = np.unravel_index(np.argmax(patch), patch.shape)
    region = labels == labels[py, px]
    # grow by a pixel so the faint blurred tails count in the centroid
    region = cv2.dilate(region.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & inside
    wgt = np.where(region, np.maximum(patch, 0.0), 0.0)
    total = wgt.sum()
    cx = float((wgt * xx).sum() / total)
    cy = float((wgt * yy).sum() / total)
    dx, dy = xx - cx, yy - cy
    cov = np.array([[(wgt * dx * dx).sum(), (wgt * dx * dy).sum()],
                    [(wgt * dx * dy).sum(), (wgt * dy * dy).sum()]]) / total
    evals, evecs = np.linalg.eigh(cov)
    saturated = white_level is not None and float(grey[y0:y1, x0:x1][region].max()) >= 0.999 * white_level
    centroid, major = np.array([cx, cy]), evecs[:, 1]
    sig_major, sig_minor = float(np.sqrt(max(evals[1], 0))), float(np.sqrt(max(evals[0], 0)))
    ends = streak_endpoints(grey, bg, centroid, major, sig_major)
    ridge = streak_ridge(grey, bg, ends) if ends is not None else None
    mid = ridge[0] if ridge is not None and len(ridge) else None
    return Highlight(camera, sphere, centroid, major, sig_major, sig_minor, peak, bool(saturated), ends, ridge, mid)


def reflect_rays(cam: Camera, uv: np.ndarray, centre: np.ndarray, radius_m: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Reflect the viewing rays through pixels ``uv`` [N, 2] off the ball (batched ``reflect_ray``).

    Returns hit mask [N] (False: the ray misses the ball), points [N, 3], reflected directions
    [N, 3] and incidence angles in degrees [N]; entries where the ray misses are NaN.
    """
    o, d = cam.pixel_rays(np.asarray(uv, float).reshape(-1, 2))  # [N, 3] each
    oc = o - centre
    b = (d * oc).sum(-1)  # [N]
    disc = b * b - ((oc * oc).sum(-1) - radius_m ** 2)
    hit = disc >= 0
    t = np.where(hit, -b - np.sqrt(np.where(hit, disc, 0.0)), np.nan)
    p = o + t[:, None] * d
    n = (p - centre) / radius_m
    dn = (d * n).sum(-1, keepdims=True)
    refl = d - 2 * dn * n
    incidence = np.degrees(np.arccos(np.clip(-dn[:, 0], -1, 1)))
    return hit, p, refl, incidence


def reflect_ray(cam: Camera, uv: np.ndarray, centre: np.ndarray, radius_m: float
                ) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Reflect the viewing ray through pixel ``uv`` [2] off the ball; (point [3], direction [3], incidence deg).

    None when the ray misses the ball.
    """
    hit, p, refl, incidence = reflect_rays(cam, np.asarray(uv, float)[None], centre, radius_m)
    if not hit[0]:
        return None
    return p[0], refl[0], float(incidence[0])
