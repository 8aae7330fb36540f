"""Tracking a sequence of full-on frames: landmark embedding, then pose + weights per frame.

Per key frame: the landmark fit (``stages.track.fit``), then, where the images gave the
head's outline, a refinement of the rigid pose with that outline and a re-fit of the
weights at the refined pose (``stages.track.silhouette``). Input is detector output only
(landmark pixels and outline points per key frame and camera), so the whole algorithm
runs without images (tests feed it projected synthetic landmarks).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from scene.camera import Camera
from stages.track.embedding import (LandmarkEmbedding, SkinSurface, embed_points, icp_to_surface,
                                    initial_alignment)
from stages.track.fit import (FitParams, FrameFit, FramePose, LandmarkModel, fit_frame, refine_pose_with_silhouette,
                              refit_weights, residuals_px)
from stages.track.geometry import PinholeArrays, ideal_pixels, triangulate, triangulate_general
from stages.track.rig import ActorRig
from stages.track.silhouette import ImageSilhouette, outline_edges
from stages.track.topology import outline_geometry


class TrackerParams(BaseModel):
    """Settings of the landmark embedding and the sequential fit."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    embed_frames: int = Field(6, ge=1, description="Full-on frames (from the first, where the actor is neutral) used to estimate and refine the landmark embedding.")
    embed_refine_rounds: int = Field(2, ge=0, description="Rounds of re-triangulating the landmarks in head space with fitted poses and expressions.")
    triangulation_reject_px: float = Field(8.0, gt=0, description="Triangulation drops a view whose reprojection error exceeds this (pixels).")
    min_facing_cos: float = Field(0.15, ge=-1, le=1, description="A landmark counts in a view only when its surface normal faces the camera by at least this cosine (drops hallucinated far-side points).")
    silhouette_weight: float = Field(20.0, ge=0, description="Weight of the head-outline term (per outline point, against 1 per landmark coordinate) that refines each frame's pose after the landmark fit; the outline is rigid and unbiased, so it dominates (0 = landmarks only; needs a dark backdrop).")
    outline_defines_head_frame: bool = Field(True, description="With outlines, keep the head frame of the outline-refined poses when re-embedding (no landmark-to-scan re-alignment).")
    silhouette_max_px: float = Field(6.0, gt=0, description="Model and image outline points farther apart than this (pixels) are not paired.")
    fit: FitParams = Field(default_factory=FitParams, description="Per-frame fit settings.")


@dataclass
class KeyFrameObservations:
    """Detector output over the full-on (key) frames.

    Attributes:
        uv_px: landmark pixels [F, C, N, 2] in image (distorted) coordinates; nan = missing.
        score: per-view detection confidence [F, C] in [0, 1]; 0 = view rejected.
        landmark_ids: detector landmark id of each of the N columns [N].
        contours_px: optional foreground outlines per key frame and camera ([F][C] arrays
            [M, 2], image pixels) for the silhouette term; None = landmarks only.
    """

    uv_px: np.ndarray
    score: np.ndarray
    landmark_ids: np.ndarray
    contours_px: list[list[np.ndarray]] | None = None


@dataclass
class TrackResult:
    """Per-key-frame fits and what was learnt on the way.

    Attributes:
        embedding: the landmark embedding on the rig (of the fitted landmarks).
        fits: one ``FrameFit`` per key frame (None where the frame could not be fitted).
        warnings: messages for a person (dropped views, unfitted frames).
        fit_seconds: wall time of the final sequential fit.
    """

    embedding: LandmarkEmbedding
    fits: list[FrameFit | None]
    warnings: list[str] = field(default_factory=list)
    fit_seconds: float = 0.0


def observation_confidence(cameras: Sequence[Camera], uv_px: np.ndarray, score: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ideal pixels [F, C, N, 2] and confidences [F, C, N] from detections.

    A landmark counts with its view's score when it is finite and inside the image.
    """
    uv_ideal = np.zeros_like(uv_px, dtype=np.float64)
    conf = np.zeros(uv_px.shape[:3])
    for c, cam in enumerate(cameras):
        obs = uv_px[:, c]  # [F, N, 2]
        finite = np.all(np.isfinite(obs), axis=-1)
        inside = finite & (obs[..., 0] >= 0) & (obs[..., 0] <= cam.width - 1) & (obs[..., 1] >= 0) & (obs[..., 1] <= cam.height - 1)
        uv_ideal[:, c] = np.where(finite[..., None], ideal_pixels(cam, np.nan_to_num(obs)), np.nan)
        conf[:, c] = np.where(inside, score[:, c, None], 0.0)
    return uv_ideal, conf


class Tracker:
    """Embeds the landmarks on the rig and fits every key frame.

    Args:
        rig: the actor rig.
        cameras: calibrated cameras [C] (``cam_from_world``).
        fit_ids: detector landmarks the per-frame fit uses (None = all observed).
        align_ids: detector landmarks whose triangulation is aligned to the scan surface to
            fix the head frame (None = all observed). A dense set (FaceMesh's 468 points,
            face contour included) pins the head's pitch far better than the fitted subset:
            a shallow patch of eyes, brows, nose and lips can tilt by degrees under ICP.
        skin_triangles: rig triangles a landmark may sit on (None = all).
        head_reference: optional head-space positions [N, 3] (nan where unknown) of the
            observed landmarks, for the initial alignment (e.g. known correspondences).
        params: tracker settings.
        log: where warnings go as they happen.
    """

    def __init__(self, rig: ActorRig, cameras: Sequence[Camera], skin_triangles: np.ndarray | None,
                 head_reference: np.ndarray | None, params: TrackerParams,
                 log: logging.Logger | None = None, fit_ids: np.ndarray | None = None,
                 align_ids: np.ndarray | None = None):
        self.rig, self.cameras, self.params = rig, list(cameras), params
        self.fit_ids = None if fit_ids is None else np.asarray(fit_ids)
        self.align_ids = None if align_ids is None else np.asarray(align_ids)
        self.pinhole = PinholeArrays.from_cameras(self.cameras)
        self.surface = SkinSurface(rig, skin_triangles)
        self.head_reference = head_reference
        self.log = log or logging.getLogger(__name__)
        self.outline_faces, self.outline_candidates = outline_geometry(rig.faces, rig.num_vertices)
        self.outline_edges = outline_edges(self.outline_faces)
        self.silhouettes: list[list[ImageSilhouette | None]] | None = None

    def set_contours(self, contours_px: list[list[np.ndarray]] | None) -> None:
        """Image outlines per key frame and camera (image pixels); None disables the term."""
        if contours_px is None or self.params.silhouette_weight <= 0:
            self.silhouettes = None
            return
        self.silhouettes = [[ImageSilhouette(ideal_pixels(cam, c)) if len(c) >= 10 else None
                             for cam, c in zip(self.cameras, per_view)] for per_view in contours_px]

    # ---- embedding -----------------------------------------------------------------------
    def initial_embedding(self, landmark_ids: np.ndarray, uv: np.ndarray, conf: np.ndarray) -> LandmarkEmbedding | None:
        """Embedding from one (neutral) frame: triangulate, align to the surface, snap."""
        points, valid, _ = triangulate(self.pinhole, uv, conf, reject_px=self.params.triangulation_reject_px)
        if valid.sum() < 10:
            return None
        pts = np.where(valid[:, None], points, np.nan)
        ref = self.head_reference
        if ref is None or np.isfinite(ref[valid]).all(axis=1).sum() < 6:
            # No correspondences: world and head share their axis convention, so only the
            # centroids need matching before ICP.
            front = self.rig.neutral_m[np.unique(self.rig.faces[self.surface.triangle_ids])]
            front = front[front[:, 2] > np.quantile(front[:, 2], 0.5)]
            R0, t0 = np.eye(3), front.mean(0) - np.nanmean(pts, axis=0)
        else:
            R0, t0 = initial_alignment(pts, ref)
        align = valid & self._is_align(landmark_ids)
        R, t, _ = icp_to_surface(self.surface, points[align if align.sum() >= 10 else valid], R0, t0)
        head = points @ R.T + t
        emb = embed_points(self.surface, landmark_ids[valid], head[valid])
        return emb

    def _is_align(self, landmark_ids: np.ndarray) -> np.ndarray:
        if self.align_ids is None:
            return np.ones(len(landmark_ids), dtype=bool)
        return np.isin(landmark_ids, self.align_ids)

    def refine_embedding(self, emb: LandmarkEmbedding, landmark_ids: np.ndarray, uv: np.ndarray, conf: np.ndarray,
                         fits: Sequence[FrameFit | None]) -> LandmarkEmbedding:
        """Re-triangulate every landmark in head space over several fitted frames, then snap.

        Each frame's expression offset at the landmark (rig basis times fitted weights) is
        removed through a per-point camera translation, so non-neutral frames count too.
        """
        column = {int(i): k for k, i in enumerate(landmark_ids)}
        cols = np.array([column[int(i)] for i in emb.landmark_ids])
        model = emb.model(self.rig)
        Rs, ts, uvs, ws = [], [], [], []
        for f, fit in enumerate(fits):
            if fit is None:
                continue
            offsets = model.points(fit.pose.weights) - model.mean_m  # [N, 3] head space
            cam_from_head_R = self.pinhole.R @ fit.pose.R  # [C, 3, 3]
            cam_from_head_t = self.pinhole.R @ fit.pose.t + self.pinhole.t  # [C, 3]
            Rs.append(cam_from_head_R)
            ts.append(cam_from_head_t[:, None, :] + np.einsum("cij,nj->cni", cam_from_head_R, offsets))
            uvs.append(uv[f][:, cols])
            ws.append(conf[f][:, cols] * fit.used_views[:, None])
        if not Rs:
            return emb
        R = np.concatenate(Rs)
        t = np.concatenate(ts)
        f_px = np.tile(self.pinhole.f_px, (len(Rs), 1))
        c_px = np.tile(self.pinhole.c_px, (len(Rs), 1))
        points, valid, _ = triangulate_general(R, t, f_px, c_px, np.concatenate(uvs), np.concatenate(ws),
                                               reject_px=self.params.triangulation_reject_px,
                                               rounds=max(6, len(R)))
        old = model.mean_m
        if valid.sum() < 10:
            self.log.warning("embedding not refined: only %d landmarks could be re-triangulated "
                             "consistently over %d frames", int(valid.sum()), len(Rs))
            return emb
        # Re-anchor the head frame: the re-triangulated points, aligned to the surface, define it.
        align = valid & self._is_align(emb.landmark_ids)
        if self.silhouettes is None or not self.params.outline_defines_head_frame:
            R_fix, t_fix, _ = icp_to_surface(self.surface, points[align if align.sum() >= 10 else valid],
                                             np.eye(3), np.zeros(3))
        else:
            # The fitted poses followed the head's outline, which the scan matches exactly;
            # re-aligning the landmark cloud would bring back the detector's bias.
            R_fix, t_fix = np.eye(3), np.zeros(3)
        head = np.where(valid[:, None], points @ R_fix.T + t_fix, old)
        refined = embed_points(self.surface, emb.landmark_ids, head)
        moved_mm = np.linalg.norm(refined.points(self.rig.faces, self.rig.neutral_m) - old, axis=1) * 1000
        self.log.info("embedding refined over %d frames: %d/%d landmarks re-triangulated, moved %.2f mm median",
                      len(Rs), int(valid.sum()), len(valid), float(np.median(moved_mm)))
        return refined

    # ---- fitting ---------------------------------------------------------------------------
    def fit_sequence(self, emb: LandmarkEmbedding, landmark_ids: np.ndarray, uv: np.ndarray, conf: np.ndarray,
                     frame_names: Sequence[str], warnings: list[str] | None = None,
                     on_frame: Callable[[], None] | None = None, frame_offset: int = 0) -> list[FrameFit | None]:
        """Fit the key frames in order, each warm-started from the previous fit.

        ``frame_offset`` is the position of ``uv[0]`` among the key frames (for the outlines).
        """
        if self.fit_ids is not None:
            emb = emb.subset(self.fit_ids)
        column = {int(i): k for k, i in enumerate(landmark_ids)}
        cols = np.array([column[int(i)] for i in emb.landmark_ids])
        model = emb.model(self.rig)
        normals_head = emb.normals(self.rig)
        centres = np.stack([c.center_world for c in self.cameras])  # [C, 3]
        fits: list[FrameFit | None] = []
        prev: FramePose | None = None
        for f in range(uv.shape[0]):
            obs, obs_conf = uv[f][:, cols], conf[f][:, cols].copy()
            if prev is not None:
                # Landmarks on surface facing away from a camera are the detector's guesses.
                X = model.points(prev.weights) @ prev.R.T + prev.t  # [N, 3]
                n = normals_head @ prev.R.T
                to_cam = centres[:, None, :] - X[None]  # [C, N, 3]
                cos = np.einsum("cnd,nd->cn", to_cam, n) / np.linalg.norm(to_cam, axis=-1)
                obs_conf[cos < self.params.min_facing_cos] = 0.0
            fit = fit_frame(model, self.pinhole, obs, obs_conf, prev, prev, self.params.fit)
            if fit is not None and self.silhouettes is not None and frame_offset + f < len(self.silhouettes):
                fit = self._with_outline(model, obs, obs_conf, fit, self.silhouettes[frame_offset + f])
            if fit is None:
                msg = (f"frame {frame_names[f]}: too few usable views or landmarks to fit "
                       f"(views with a face: {int((obs_conf > 0).any(1).sum())}); it is interpolated instead")
                self.log.warning(msg)
                if warnings is not None:
                    warnings.append(msg)
            else:
                if fit.dropped_views and warnings is not None:
                    msg = (f"frame {frame_names[f]}: dropped view(s) {', '.join(fit.dropped_views)} "
                           "(landmarks inconsistent with the other cameras)")
                    self.log.warning(msg)
                    warnings.append(msg)
                prev = fit.pose
            fits.append(fit)
            if on_frame is not None:
                on_frame()
        return fits

    def _with_outline(self, model: LandmarkModel, obs: np.ndarray, obs_conf: np.ndarray, fit: FrameFit,
                      silhouettes: list[ImageSilhouette | None]) -> FrameFit:
        """Refine the fitted pose with the head's outline, then the weights at that pose."""
        conf = obs_conf * fit.used_views[:, None]
        vertices = self.rig.mesh(fit.pose.weights)
        pose, pairs = refine_pose_with_silhouette(
            model, self.pinhole, obs, conf, fit.pose, silhouettes, vertices, self.outline_faces,
            self.outline_edges, self.outline_candidates, self.params.fit, self.params.silhouette_weight, self.params.silhouette_max_px)
        if not pairs:
            return fit
        pose = refit_weights(model, self.pinhole, obs, conf, pose, self.params.fit)
        return FrameFit(pose=pose, residual_px=residuals_px(model, self.pinhole, obs, conf, pose),
                        used_views=fit.used_views, dropped_views=fit.dropped_views,
                        iterations=fit.iterations, outline_pairs=pairs)

    def run(self, observations: KeyFrameObservations, frame_names: Sequence[str],
            on_frame: Callable[[], None] | None = None) -> TrackResult:
        """Embedding (initial + refinement) then the sequential fit over all key frames.

        Raises ``ValueError`` when no key frame has enough views to embed the landmarks.
        """
        from threadpoolctl import threadpool_limits

        # Small dense problems: BLAS threads only add contention on a shared CPU.
        with threadpool_limits(limits=1):
            return self._run(observations, frame_names, on_frame)

    def _run(self, observations: KeyFrameObservations, frame_names: Sequence[str],
             on_frame: Callable[[], None] | None) -> TrackResult:
        uv, conf = observation_confidence(self.cameras, observations.uv_px, observations.score)
        ids = observations.landmark_ids
        self.set_contours(observations.contours_px)
        warnings: list[str] = []
        emb, start = None, 0
        for start in range(uv.shape[0]):
            emb = self.initial_embedding(ids, uv[start], conf[start])
            if emb is not None:
                break
        if emb is None:
            raise ValueError("no full-on frame has the face in at least two views with consistent "
                             "landmarks; check the capture's cameras and exposure")
        if start > 0:
            warnings.append(f"landmark embedding from frame {frame_names[start]}: the earlier full-on "
                            "frames lack usable views")
        last = min(uv.shape[0], start + self.params.embed_frames)
        for _ in range(self.params.embed_refine_rounds):
            fits = self.fit_sequence(emb, ids, uv[start:last], conf[start:last], frame_names[start:last],
                                     frame_offset=start)
            emb = self.refine_embedding(emb, ids, uv[start:last], conf[start:last], fits)
        t0 = time.perf_counter()
        fits = self.fit_sequence(emb, ids, uv, conf, frame_names, warnings, on_frame)
        fitted_emb = emb if self.fit_ids is None else emb.subset(self.fit_ids)
        return TrackResult(fitted_emb, fits, warnings, time.perf_counter() - t0)
