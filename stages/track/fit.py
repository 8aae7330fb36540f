"""Per-frame fit of head pose and blendweights to multi-view 2D landmarks.

Model: head-space landmarks ``L(w) = L0 + sum_k w_k B_k`` (``LandmarkModel``), world
points ``X = R L(w) + t`` with ``(R, t) = world_from_head``, projected by every camera's
pinhole (observations were undistorted into ideal pixels beforehand). The rotation is
parameterised as ``R = exp(omega) R0`` around the warm start ``R0``, so the solver sees a
small, well-scaled rotation vector and the Jacobian is analytic (SO(3) left Jacobian).

Cost (``scipy.optimize.least_squares``, robust loss on all terms, bounded weights):
reprojection residuals in pixels, weighted by detection confidence; a light temporal term
pulling weights and pose towards the previous full-on frame; a small ridge on weights.
The fit runs rigid-only first (weights held), then jointly, then drops views whose
residuals are implausible (a wrong face, a head leaving the frustum) and refits.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from stages.track.geometry import PinholeArrays, robust_kabsch, skew, so3_exp, so3_left_jacobian, triangulate


class FitParams(BaseModel):
    """Weights and thresholds of the per-frame fit."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    loss: Literal["soft_l1", "cauchy", "huber", "arctan", "linear"] = Field(
        "soft_l1", description="Robust loss of scipy's least_squares: 'soft_l1', 'cauchy', 'huber', 'arctan' or "
        "'linear' (plain least squares). Try 'cauchy' if outlier landmarks still pull the fit.")
    loss_scale_px: float = Field(1.5, gt=0, description="Residual (pixels) where the robust loss starts to flatten.")
    temporal_weights_px: float = Field(3.0, ge=0, description="Pixel-equivalent cost of a unit blendweight change between consecutive full-on frames.")
    temporal_rotation_px_per_deg: float = Field(0.5, ge=0, description="Pixel-equivalent cost of one degree of head rotation between consecutive full-on frames.")
    temporal_translation_px_per_mm: float = Field(0.1, ge=0, description="Pixel-equivalent cost of one millimetre of head translation between consecutive full-on frames.")
    ridge_weights_px: float = Field(0.5, ge=0, description="Pixel-equivalent cost of a unit blendweight (pulls unobserved shapes to zero).")
    weight_min: float = Field(0.0, description="Lower bound of every blendweight.")
    weight_max: float = Field(1.0, description="Upper bound of every blendweight.")
    max_iterations: int = Field(60, ge=1, description="Maximum least-squares iterations per solve.")
    view_reject_px: float = Field(8.0, gt=0, description="A view whose median landmark residual exceeds this (and 3x the frame's median) is dropped and the frame refitted.")
    min_views: int = Field(2, ge=1, description="A frame needs at least this many usable views to be fitted.")
    min_landmarks_per_view: int = Field(20, ge=3, description="A view with fewer valid landmarks than this is not used.")


@dataclass(frozen=True)
class LandmarkModel:
    """Linear model of the tracked landmarks in head space.

    Attributes:
        mean_m: landmark positions with all weights zero (neutral) [N, 3], metres.
        basis_m: landmark offsets per blendshape [K, N, 3], metres.
    """

    mean_m: np.ndarray
    basis_m: np.ndarray

    @property
    def num_shapes(self) -> int:
        return int(self.basis_m.shape[0])

    def points(self, weights: np.ndarray) -> np.ndarray:
        """Head-space landmarks for weights [K] -> [N, 3]."""
        return self.mean_m + np.tensordot(np.asarray(weights, float), self.basis_m, axes=(0, 0))


@dataclass
class FramePose:
    """A head pose and weights: ``world_from_head`` = (R, t) and blendweights [K]."""

    R: np.ndarray  # [3, 3]
    t: np.ndarray  # [3] metres
    weights: np.ndarray  # [K]

    def copy(self) -> "FramePose":
        return FramePose(self.R.copy(), self.t.copy(), self.weights.copy())


@dataclass
class FrameFit:
    """Result of fitting one frame.

    Attributes:
        pose: the fitted pose and weights.
        residual_px: per-observation reprojection error [C, N] (nan where unobserved or dropped).
        used_views: which views took part in the final solve [C].
        dropped_views: names of views rejected by the residual check.
        iterations: least-squares function evaluations over all solves.
        outline_pairs: model/image outline pairs of the silhouette refinement (0 = not used).
    """

    pose: FramePose
    residual_px: np.ndarray
    used_views: np.ndarray
    dropped_views: list[str] = field(default_factory=list)
    iterations: int = 0
    outline_pairs: int = 0

    @property
    def mean_residual_px(self) -> float:
        """Mean reprojection error over used observations (pixels)."""
        r = self.residual_px[self.used_views]
        r = r[np.isfinite(r)]
        return float(r.mean()) if r.size else float("nan")


class _Problem:
    """Residuals and analytic Jacobian for one frame; ``x = [omega(3), t(3), w(K)]`` or rigid only."""

    def __init__(self, model: LandmarkModel, cams: PinholeArrays, uv: np.ndarray, conf: np.ndarray,
                 R0: np.ndarray, prev: FramePose | None, params: FitParams, rigid_weights: np.ndarray | None):
        self.model, self.cams, self.params, self.R0, self.prev = model, cams, params, R0, prev
        self.rigid_weights = rigid_weights  # weights held fixed in a rigid-only solve, else None
        self.cam_idx, self.lm_idx = np.nonzero(conf > 0)  # observed (view, landmark) pairs
        self.obs = uv[self.cam_idx, self.lm_idx]  # [M, 2]
        self.sqrt_w = np.sqrt(conf[self.cam_idx, self.lm_idx])[:, None]  # [M, 1]
        K = model.num_shapes
        self.n_params = 6 + (0 if rigid_weights is not None else K)
        # Temporal / ridge rows: stiffness per parameter, in "pixels per unit".
        stiff = []
        if prev is not None:
            stiff += [np.full(3, params.temporal_rotation_px_per_deg * 180.0 / np.pi),
                      np.full(3, params.temporal_translation_px_per_mm * 1000.0)]
            if rigid_weights is None:
                stiff.append(np.full(K, params.temporal_weights_px))
        self.temporal_stiff = np.concatenate(stiff) if stiff else np.zeros(0)
        self.ridge = params.ridge_weights_px if (rigid_weights is None and K) else 0.0

    def unpack(self, x: np.ndarray) -> FramePose:
        R = so3_exp(x[:3]) @ self.R0
        w = self.rigid_weights if self.rigid_weights is not None else x[6:]
        return FramePose(R, x[3:6].copy(), np.array(w, dtype=np.float64))

    def _prior_target(self) -> np.ndarray:
        prev = self.prev
        if prev is None:
            return np.zeros(0)
        # Rotation of prev relative to R0, as a rotation vector.
        omega_prev = Rotation.from_matrix(prev.R @ self.R0.T).as_rotvec()
        target = [omega_prev, prev.t]
        if self.rigid_weights is None:
            target.append(prev.weights)
        return np.concatenate(target)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        pose = self.unpack(x)
        L = self.model.points(pose.weights)  # [N, 3]
        Xw = L @ pose.R.T + pose.t  # [N, 3]
        Xc = np.einsum("mij,mj->mi", self.cams.R[self.cam_idx], Xw[self.lm_idx]) + self.cams.t[self.cam_idx]
        z = np.maximum(Xc[:, 2:3], 1e-6)
        proj = Xc[:, :2] / z * self.cams.f_px[self.cam_idx] + self.cams.c_px[self.cam_idx]
        parts = [((proj - self.obs) * self.sqrt_w).ravel()]
        if self.temporal_stiff.size:
            parts.append(self.temporal_stiff * (x[: self.temporal_stiff.size] - self._prior_target()))
        if self.ridge:
            parts.append(self.ridge * x[6:])
        return np.concatenate(parts)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        pose = self.unpack(x)
        L = self.model.points(pose.weights)
        RL = L @ pose.R.T  # [N, 3]
        Xw = RL + pose.t
        Rc = self.cams.R[self.cam_idx]  # [M, 3, 3]
        Xc = np.einsum("mij,mj->mi", Rc, Xw[self.lm_idx]) + self.cams.t[self.cam_idx]
        z = np.maximum(Xc[:, 2], 1e-6)
        f = self.cams.f_px[self.cam_idx]  # [M, 2]
        # d(proj)/d(Xc) [M, 2, 3]
        dp = np.zeros((len(z), 2, 3))
        dp[:, 0, 0] = f[:, 0] / z
        dp[:, 0, 2] = -f[:, 0] * Xc[:, 0] / z**2
        dp[:, 1, 1] = f[:, 1] / z
        dp[:, 1, 2] = -f[:, 1] * Xc[:, 1] / z**2
        dpw = np.einsum("mab,mbc->mac", dp, Rc) * self.sqrt_w[:, :, None]  # d(proj)/d(Xw) [M, 2, 3]
        # d(Xw)/d(omega) = -[R L]_x J_l(omega)
        dX_domega = -skew(RL) @ so3_left_jacobian(x[:3])  # [N, 3, 3]
        cols = [np.einsum("mab,mbc->mac", dpw, dX_domega[self.lm_idx]), dpw]
        if self.rigid_weights is None and self.model.num_shapes:
            RB = np.einsum("ij,knj->nik", pose.R, self.model.basis_m)  # d(Xw)/d(w) [N, 3, K]
            cols.append(np.einsum("mab,mbk->mak", dpw, RB[self.lm_idx]))
        J_obs = np.concatenate(cols, axis=2).reshape(-1, self.n_params)  # [2M, P]
        rows = [J_obs]
        if self.temporal_stiff.size:
            J_t = np.zeros((self.temporal_stiff.size, self.n_params))
            # The prior is linear in x (its target omega_prev is fixed during the solve).
            J_t[np.arange(self.temporal_stiff.size), np.arange(self.temporal_stiff.size)] = self.temporal_stiff
            rows.append(J_t)
        if self.ridge:
            J_r = np.zeros((self.n_params - 6, self.n_params))
            J_r[:, 6:] = np.eye(self.n_params - 6) * self.ridge
            rows.append(J_r)
        return np.concatenate(rows, axis=0)


def _solve(model: LandmarkModel, cams: PinholeArrays, uv: np.ndarray, conf: np.ndarray,
           init: FramePose, prev: FramePose | None, params: FitParams, rigid: bool) -> tuple[FramePose, int]:
    """One least-squares solve from ``init``; returns the pose and the number of evaluations."""
    problem = _Problem(model, cams, uv, conf, init.R, prev, params, init.weights if rigid else None)
    x0 = np.concatenate([np.zeros(3), init.t] + ([] if rigid else [init.weights]))
    lo = np.full(problem.n_params, -np.inf)
    hi = np.full(problem.n_params, np.inf)
    if not rigid:
        lo[6:], hi[6:] = params.weight_min, params.weight_max
        x0[6:] = np.clip(x0[6:], params.weight_min, params.weight_max)
    result = least_squares(problem.residuals, x0, jac=problem.jacobian, bounds=(lo, hi), method="trf",
                           loss=params.loss, f_scale=params.loss_scale_px, max_nfev=params.max_iterations,
                           x_scale="jac")
    return problem.unpack(result.x), int(result.nfev)


def residuals_px(model: LandmarkModel, cams: PinholeArrays, uv: np.ndarray, conf: np.ndarray,
                 pose: FramePose) -> np.ndarray:
    """Reprojection error [C, N] in pixels of ``pose`` (nan where unobserved)."""
    X = model.points(pose.weights) @ pose.R.T + pose.t
    proj, z = cams.project(X)
    err = np.linalg.norm(proj - uv, axis=-1)
    return np.where((conf > 0) & (z > 0), err, np.nan)


def initial_pose(model: LandmarkModel, cams: PinholeArrays, uv: np.ndarray, conf: np.ndarray,
                 weights: np.ndarray) -> FramePose | None:
    """A pose from scratch: triangulate landmarks and align the model's landmarks (Kabsch).

    Returns None when fewer than 6 landmarks could be triangulated.
    """
    points, valid, _ = triangulate(cams, uv, conf)
    if valid.sum() < 6:
        return None
    head = model.points(weights)
    R, t, _ = robust_kabsch(head[valid], points[valid])
    return FramePose(R, t, np.asarray(weights, dtype=np.float64).copy())


def fit_frame(model: LandmarkModel, cams: PinholeArrays, uv: np.ndarray, conf: np.ndarray,
              init: FramePose | None, prev: FramePose | None, params: FitParams) -> FrameFit | None:
    """Fit pose and weights of one frame to ideal-pixel landmarks ``uv`` [C, N, 2].

    Args:
        model: head-space landmark model.
        cams: the C cameras.
        uv: ideal-pixel observations [C, N, 2].
        conf: per-observation confidence [C, N]; 0 = not observed (missing or rejected).
        init: warm start (the previous full-on frame's result), or None to start from a
            triangulation.
        prev: the previous frame's result for the temporal term, or None.
        params: fit weights and thresholds.

    Returns:
        The fit, or None when too few views or landmarks are usable.
    """
    conf = np.asarray(conf, dtype=np.float64).copy()
    per_view = (conf > 0).sum(1)
    conf[per_view < params.min_landmarks_per_view] = 0.0
    used = (conf > 0).any(1)
    if used.sum() < params.min_views:
        return None
    K = model.num_shapes

    def rigid_from(start: FramePose) -> tuple[float, FramePose, int]:
        # Rigid only first: a wrong pose would otherwise be absorbed by the weights.
        rigid_pose, n = _solve(model, cams, uv, conf, start, prev, params, rigid=True)
        resid = residuals_px(model, cams, uv, conf, rigid_pose)
        cost = float(np.nanmedian(resid)) if np.isfinite(resid).any() else np.inf
        return cost, rigid_pose, n

    evaluations = 0
    rigid_fits = []
    if init is not None:
        rigid_fits.append(rigid_from(init.copy()))
    if not rigid_fits or rigid_fits[0][0] > params.view_reject_px:
        # No warm start, or it landed far off (a fast head turn, a bad previous frame):
        # start again from a triangulation of this frame's landmarks.
        scratch = initial_pose(model, cams, uv, conf, init.weights if init is not None else np.zeros(K))
        if scratch is not None:
            rigid_fits.append(rigid_from(scratch))
    if not rigid_fits:
        return None
    evaluations += sum(item[2] for item in rigid_fits)
    pose = min(rigid_fits, key=lambda item: item[0])[1]
    dropped: list[str] = []
    for _ in range(3):
        if K:
            pose, n = _solve(model, cams, uv, conf, pose, prev, params, rigid=False)
            evaluations += n
        else:
            pose, n = _solve(model, cams, uv, conf, pose, prev, params, rigid=True)
            evaluations += n
        resid = residuals_px(model, cams, uv, conf, pose)
        view_median = np.array([np.nanmedian(r) if np.isfinite(r).any() else np.nan for r in resid])
        frame_median = float(np.nanmedian(resid)) if np.isfinite(resid).any() else np.inf
        bad = (conf > 0).any(1) & (view_median > max(params.view_reject_px, 3.0 * frame_median))
        if not bad.any() or ((conf > 0).any(1) & ~bad).sum() < params.min_views:
            break
        # Drop only the worst view per round: one bad view inflates every view's residuals.
        worst = int(np.nanargmax(np.where(bad, view_median, -np.inf)))
        dropped.append(cams.names[worst])
        conf[worst] = 0.0
        pose, n = _solve(model, cams, uv, conf, pose, prev, params, rigid=True)
        evaluations += n
    resid = residuals_px(model, cams, uv, conf, pose)
    return FrameFit(pose=pose, residual_px=resid, used_views=(conf > 0).any(1), dropped_views=dropped,
                    iterations=evaluations)


class _SilhouetteTerm:
    """Point-to-line residuals of model contour vertices against image contour points."""

    def __init__(self, cams: PinholeArrays, R0: np.ndarray, points_head: np.ndarray, views: np.ndarray,
                 targets: np.ndarray, normals: np.ndarray, weight: float):
        self.cams, self.R0, self.points_head = cams, R0, points_head  # points [P, 3]
        self.views, self.targets, self.normals = views, targets, normals
        self.sqrt_w = np.sqrt(weight)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        R = so3_exp(x[:3]) @ self.R0
        Xw = self.points_head @ R.T + x[3:6]
        Xc = np.einsum("pij,pj->pi", self.cams.R[self.views], Xw) + self.cams.t[self.views]
        z = np.maximum(Xc[:, 2:3], 1e-6)
        proj = Xc[:, :2] / z * self.cams.f_px[self.views] + self.cams.c_px[self.views]
        return self.sqrt_w * np.einsum("pd,pd->p", proj - self.targets, self.normals)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        R = so3_exp(x[:3]) @ self.R0
        RL = self.points_head @ R.T
        Rc = self.cams.R[self.views]
        Xc = np.einsum("pij,pj->pi", Rc, RL + x[3:6]) + self.cams.t[self.views]
        z = np.maximum(Xc[:, 2], 1e-6)
        f = self.cams.f_px[self.views]
        n = self.normals
        # n^T d(proj)/d(Xc) [P, 3]
        dp = np.stack([n[:, 0] * f[:, 0] / z, n[:, 1] * f[:, 1] / z,
                       -(n[:, 0] * f[:, 0] * Xc[:, 0] + n[:, 1] * f[:, 1] * Xc[:, 1]) / z**2], axis=1)
        dpw = np.einsum("pa,pab->pb", dp, Rc)  # [P, 3] w.r.t. world point
        d_omega = np.einsum("pa,pab->pb", dpw, -skew(RL) @ so3_left_jacobian(x[:3]))
        return self.sqrt_w * np.concatenate([d_omega, dpw], axis=1)


def refine_pose_with_silhouette(model: LandmarkModel, cams: PinholeArrays, uv: np.ndarray, conf: np.ndarray,
                                pose: FramePose, silhouettes: list, vertices_head: np.ndarray,
                                faces: np.ndarray, edges: np.ndarray, candidate: np.ndarray, params: FitParams,
                                weight: float, max_distance_px: float = 6.0, rounds: int = 3) -> tuple[FramePose, int]:
    """Refine the rigid pose (weights held) with landmarks plus the head's outline.

    Each round pairs model contour points with image contour points at the current pose
    (``stages.track.silhouette``) and solves the rigid pose for both terms (robust loss).
    Returns the pose and the number of contour pairs in the last round (0 = no outline used).
    """
    from stages.track.silhouette import model_contour_correspondences, vertex_normals

    normals = vertex_normals(vertices_head, faces)
    pairs = 0
    for _ in range(rounds):
        views, points_head, targets, tnormals = model_contour_correspondences(
            cams, silhouettes, vertices_head, normals, faces, edges, candidate, pose.R, pose.t, max_distance_px)
        pairs = len(views)
        if pairs < 10:
            return pose, 0
        landmarks = _Problem(model, cams, uv, conf, pose.R, None, params, pose.weights)
        outline = _SilhouetteTerm(cams, pose.R, points_head, views, targets, tnormals, weight)

        def residuals(x: np.ndarray) -> np.ndarray:
            return np.concatenate([landmarks.residuals(x), outline.residuals(x)])

        def jacobian(x: np.ndarray) -> np.ndarray:
            return np.concatenate([landmarks.jacobian(x), outline.jacobian(x)])

        x0 = np.concatenate([np.zeros(3), pose.t])
        result = least_squares(residuals, x0, jac=jacobian, method="trf", loss=params.loss,
                               f_scale=params.loss_scale_px, max_nfev=params.max_iterations, x_scale="jac")
        new = landmarks.unpack(result.x)
        moved = np.linalg.norm(new.t - pose.t) + np.linalg.norm(new.R - pose.R)
        pose = new
        if moved < 1e-7:
            break
    return pose, pairs


def refit_weights(model: LandmarkModel, cams: PinholeArrays, uv: np.ndarray, conf: np.ndarray,
                  pose: FramePose, params: FitParams) -> FramePose:
    """Re-fit the weights with the head pose held (after the pose was refined by the outline)."""
    if model.num_shapes == 0:
        return pose
    held = params.model_copy(update={"temporal_rotation_px_per_deg": 1e4, "temporal_translation_px_per_mm": 1e4,
                                     "temporal_weights_px": 0.0})
    # The temporal prior towards ``pose`` itself, made stiff, holds the pose in place.
    refit, _ = _solve(model, cams, uv, conf, pose, pose, held, rigid=False)
    return FramePose(pose.R.copy(), pose.t.copy(), refit.weights)
