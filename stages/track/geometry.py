"""Small geometric helpers for tracking: SO(3) maps, camera arrays, triangulation, Kabsch.

Observations are handled as *ideal* pinhole pixels: detections are undistorted once with
the camera's distortion model (``Camera.undistort``) and re-expressed with its ``K``, so
the fit projects with a plain pinhole and its Jacobian stays analytic.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from scene.camera import Camera


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices of vectors [..., 3] -> [..., 3, 3]."""
    v = np.asarray(v, dtype=np.float64)
    z = np.zeros(v.shape[:-1])
    return np.stack([
        np.stack([z, -v[..., 2], v[..., 1]], -1),
        np.stack([v[..., 2], z, -v[..., 0]], -1),
        np.stack([-v[..., 1], v[..., 0], z], -1),
    ], -2)


def so3_exp(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: axis-angle [3] (radians) -> rotation matrix [3, 3]."""
    w = np.asarray(rotvec, dtype=np.float64)
    theta = float(np.linalg.norm(w))
    k = skew(w)
    if theta < 1e-8:
        return np.eye(3) + k + 0.5 * k @ k
    return np.eye(3) + np.sin(theta) / theta * k + (1 - np.cos(theta)) / theta**2 * k @ k


def so3_left_jacobian(rotvec: np.ndarray) -> np.ndarray:
    """Left Jacobian of SO(3) at ``rotvec`` [3] -> [3, 3]: ``exp(w + d) ~ exp(J d) exp(w)``."""
    w = np.asarray(rotvec, dtype=np.float64)
    theta = float(np.linalg.norm(w))
    k = skew(w)
    if theta < 1e-6:
        return np.eye(3) + 0.5 * k + k @ k / 6.0
    return (np.eye(3) + (1 - np.cos(theta)) / theta**2 * k
            + (theta - np.sin(theta)) / theta**3 * k @ k)


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Angle of ``R_a @ R_b^T`` in degrees, for rotations [..., 3, 3] -> [...]."""
    rel = np.einsum("...ij,...kj->...ik", R_a, R_b)
    cos = (np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


@dataclass(frozen=True)
class PinholeArrays:
    """The cameras of a rig as stacked arrays for vectorised pinhole projection.

    Attributes:
        names: camera names [C].
        R: cam_from_world rotations [C, 3, 3].
        t: cam_from_world translations [C, 3], metres.
        f_px: focal lengths (fx, fy) [C, 2], pixels.
        c_px: principal points (cx, cy) [C, 2], pixels.
        size_px: image (width, height) [C, 2].
    """

    names: tuple[str, ...]
    R: np.ndarray
    t: np.ndarray
    f_px: np.ndarray
    c_px: np.ndarray
    size_px: np.ndarray

    @staticmethod
    def from_cameras(cameras: Sequence[Camera]) -> "PinholeArrays":
        """Stack ``Camera`` objects (their distortion is handled by ``ideal_pixels``)."""
        return PinholeArrays(
            names=tuple(c.name for c in cameras),
            R=np.stack([c.cam_from_world.R for c in cameras]),
            t=np.stack([c.cam_from_world.t for c in cameras]),
            f_px=np.array([[c.fx, c.fy] for c in cameras], dtype=np.float64),
            c_px=np.array([[c.cx, c.cy] for c in cameras], dtype=np.float64),
            size_px=np.array([[c.width, c.height] for c in cameras], dtype=np.float64),
        )

    def subset(self, keep: np.ndarray) -> "PinholeArrays":
        """The cameras where ``keep`` [C] (bool) is true."""
        idx = np.flatnonzero(keep)
        return PinholeArrays(tuple(self.names[i] for i in idx), self.R[idx], self.t[idx],
                             self.f_px[idx], self.c_px[idx], self.size_px[idx])

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points [N, 3] into every camera: ideal pixels [C, N, 2], depth [C, N]."""
        pc = np.einsum("cij,nj->cni", self.R, points_world) + self.t[:, None, :]  # [C, N, 3]
        z = pc[..., 2]
        safe = np.where(np.abs(z) < 1e-9, 1e-9, z)
        uv = pc[..., :2] / safe[..., None] * self.f_px[:, None, :] + self.c_px[:, None, :]
        return uv, z


def ideal_pixels(camera: Camera, uv_px: np.ndarray) -> np.ndarray:
    """Undistort detected pixels [..., 2] of ``camera`` into ideal pinhole pixels [..., 2]."""
    uv = np.asarray(uv_px, dtype=np.float64)
    xy_d = np.stack([(uv[..., 0] - camera.cx) / camera.fx, (uv[..., 1] - camera.cy) / camera.fy], -1)
    xy = camera.undistort(xy_d)
    return np.stack([xy[..., 0] * camera.fx + camera.cx, xy[..., 1] * camera.fy + camera.cy], -1)


def distorted_pixels(camera: Camera, uv_ideal: np.ndarray) -> np.ndarray:
    """Inverse of ``ideal_pixels``: ideal pinhole pixels [..., 2] -> image pixels [..., 2]."""
    uv = np.asarray(uv_ideal, dtype=np.float64)
    xy = np.stack([(uv[..., 0] - camera.cx) / camera.fx, (uv[..., 1] - camera.cy) / camera.fy], -1)
    xy_d = camera.distort(xy)
    return np.stack([xy_d[..., 0] * camera.fx + camera.cx, xy_d[..., 1] * camera.fy + camera.cy], -1)


def triangulate(cams: PinholeArrays, uv_ideal: np.ndarray, weight: np.ndarray,
                reject_px: float = 6.0, rounds: int = 6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangulate N points seen in C views (batched DLT, reweighted by depth, view rejection).

    Args:
        cams: the C cameras.
        uv_ideal: ideal pixel observations [C, N, 2].
        weight: per-observation weight [C, N]; 0 means not observed.
        reject_px: observations whose reprojection error exceeds this are dropped and the
            point re-solved (a wrong detection in one view must not drag the point).
        rounds: at most this many reweighting / rejection rounds (one view dropped per point
            per round).

    Returns:
        points [N, 3], valid [N] (seen by >= 2 views in front of them, all within
        ``reject_px`` after rejection), reprojection error [C, N] in pixels (inf where
        unobserved).
    """
    t_per_point = np.broadcast_to(cams.t[:, None, :], uv_ideal.shape[:2] + (3,))
    return triangulate_general(cams.R, t_per_point, cams.f_px, cams.c_px, uv_ideal, weight, reject_px, rounds)


def triangulate_general(R: np.ndarray, t: np.ndarray, f_px: np.ndarray, c_px: np.ndarray, uv_ideal: np.ndarray,
                        weight: np.ndarray, reject_px: float = 6.0, rounds: int = 6
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``triangulate`` with a per-point camera translation ``t`` [C, N, 3] (R [C, 3, 3]).

    A per-point translation expresses a known per-observation offset of the point: a view
    of ``p + d`` through ``[R | t]`` is a view of ``p`` through ``[R | t + R d]``.
    """
    C, N = weight.shape
    weight = np.where(np.all(np.isfinite(uv_ideal), axis=-1), weight, 0.0)
    uv_ideal = np.nan_to_num(uv_ideal)
    xy = (uv_ideal - c_px[:, None, :]) / f_px[:, None, :]  # [C, N, 2] normalised coordinates
    P = np.concatenate([np.broadcast_to(R[:, None], (C, N, 3, 3)), t[..., None]], axis=3)  # [C, N, 3, 4]
    w = (np.asarray(weight, dtype=np.float64) > 0).astype(np.float64)  # [C, N]
    depth_scale = np.ones((C, N))
    points = np.zeros((N, 3))
    err = np.full((C, N), np.inf)
    z = np.ones((C, N))

    def project(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pc = np.einsum("cnij,nj->cni", P[..., :3], X) + P[..., 3]
        depth = pc[..., 2]
        safe = np.where(np.abs(depth) < 1e-9, 1e-9, depth)
        return pc[..., :2] / safe[..., None] * f_px[:, None, :] + c_px[:, None, :], depth

    for _ in range(max(1, rounds)):
        # DLT rows x * P3 - P1, y * P3 - P2; scaling them by 1/depth turns the algebraic
        # error into (nearly) the image error.
        rows_x = xy[..., 0:1] * P[:, :, 2, :] - P[:, :, 0, :]  # [C, N, 4]
        rows_y = xy[..., 1:2] * P[:, :, 2, :] - P[:, :, 1, :]
        scale = (w / depth_scale)[..., None]
        A = np.concatenate([rows_x * scale, rows_y * scale], axis=0).transpose(1, 0, 2)  # [N, 2C, 4]
        _, _, vt = np.linalg.svd(A)
        X = vt[:, -1, :]  # [N, 4]
        hom = np.where(np.abs(X[:, 3:4]) < 1e-12, 1e-12, X[:, 3:4])
        points = X[:, :3] / hom
        proj, z = project(points)
        err = np.where(w > 0, np.linalg.norm(proj - uv_ideal, axis=-1), np.inf)
        depth_scale = np.where(z > 1e-6, z / max(float(np.median(np.abs(z))), 1e-6), 1.0)
        # Drop only the worst view of each point per round: one wrong detection inflates
        # every view's error, and dropping all of them at once would lose good views.
        masked = np.where(w > 0, err, -1.0)
        worst = np.argmax(masked, axis=0)  # [N]
        worst_err = masked[worst, np.arange(N)]
        drop = (worst_err > reject_px) & (w.sum(0) > 2)
        w[worst[drop], np.flatnonzero(drop)] = 0.0
        # Gross outliers (far beyond the threshold) go all at once while enough views remain.
        gross = (w > 0) & (err > 4.0 * reject_px) & (w.sum(0) > 3)[None, :]
        w[gross] = 0.0
        if not drop.any() and not gross.any():
            break
    kept_err = np.where(w > 0, err, 0.0).max(axis=0)
    valid = (w.sum(0) >= 2) & np.all((z > 0) | (w == 0), axis=0) & (kept_err <= reject_px)
    return points, valid, err


def kabsch(src: np.ndarray, dst: np.ndarray, weight: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rigid (R, t) minimising ``sum w |R src + t - dst|^2`` for points [N, 3]."""
    w = np.ones(len(src)) if weight is None else np.asarray(weight, dtype=np.float64)
    w = w / w.sum()
    mu_s = (w[:, None] * src).sum(0)
    mu_d = (w[:, None] * dst).sum(0)
    H = ((src - mu_s) * w[:, None]).T @ (dst - mu_d)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, mu_d - R @ mu_s


def robust_kabsch(src: np.ndarray, dst: np.ndarray, trim_fraction: float = 0.2,
                  rounds: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kabsch with iterative trimming of the worst matches; returns R, t, inlier mask [N]."""
    keep = np.ones(len(src), dtype=bool)
    R, t = kabsch(src, dst)
    for _ in range(rounds):
        resid = np.linalg.norm(src @ R.T + t - dst, axis=1)
        cut = np.quantile(resid, 1.0 - trim_fraction)
        keep = resid <= max(cut, 1e-9)
        if keep.sum() < 3:
            break
        R, t = kabsch(src[keep], dst[keep])
    return R, t, keep
