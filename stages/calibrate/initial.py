"""First estimates: per-camera intrinsics (OpenCV) and all poses chained through shared board frames."""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from pipeline.errors import InputError
from scene.camera import Rigid
from stages.calibrate.board import Detection


@dataclass
class Intrinsics:
    """One camera's intrinsics and its board poses from ``cv2.calibrateCamera``."""

    K: np.ndarray  # [3, 3]
    dist: np.ndarray  # [5] k1, k2, p1, p2, k3
    cam_from_board: dict[int, Rigid]  # frame -> pose
    rms_px: float
    frame_rms_px: dict[int, float]


@contextmanager
def single_threaded_opencv() -> Iterator[None]:
    """Run OpenCV on one thread inside the block, restoring its thread count after.

    ``cv2.calibrateCamera`` accumulates its normal equations across threads in whatever order
    they finish, so on a multi-core machine two calls on the same detections differ in the
    last bits (1e-11 px). That is harmless as a number but changes the calibration's content
    digest, so every downstream stage would rerun and training, which amplifies such
    differences, would give other figures for the same seed. One thread costs little here:
    corner detection dominates the stage's time (docs/experiments.md, section 7).
    """
    import cv2

    previous = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(previous)


def calibrate_intrinsics(name: str, detections: list[Detection], corners_board: np.ndarray,
                         size: tuple[int, int], model: str, outlier_px: float, max_view_angle_deg: float,
                         log) -> Intrinsics:
    """``cv2.calibrateCamera`` on one camera's detections; frames whose RMS is an outlier are dropped.

    A frame counts as an outlier when its RMS exceeds ``outlier_px`` and three times the
    median frame RMS (a mis-detected corner or a moving board), or when the board is seen
    more obliquely than ``max_view_angle_deg`` (foreshortened corners pull the sub-pixel
    refinement towards the markers); the camera is then recalibrated.
    """
    import cv2

    # the same parameter set as the COLMAP model the bundle adjustment refines
    flags = {"SIMPLE_RADIAL": cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K2
             | cv2.CALIB_FIX_K3,
             "RADIAL": cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3,
             "OPENCV": cv2.CALIB_FIX_K3, "FULL_OPENCV": 0}[model]
    dets = list(detections)
    for _ in range(3):
        obj = [corners_board[d.ids].astype(np.float32).reshape(-1, 1, 3) for d in dets]
        img = [d.corners_px.astype(np.float32).reshape(-1, 1, 2) for d in dets]
        with single_threaded_opencv():  # bit-identical results run to run
            rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
                obj, img, size, np.eye(3), None, flags=flags,
                criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12))
        dist = np.zeros(5) + np.concatenate([dist.ravel()[:5], np.zeros(5)])[:5]
        frame_rms = {}
        poses = {}
        for d, o, i, rv, tv in zip(dets, obj, img, rvecs, tvecs):
            proj, _ = cv2.projectPoints(o, rv, tv, K, dist)
            frame_rms[d.frame] = float(np.sqrt(np.mean(np.sum((proj - i) ** 2, axis=-1))))
            poses[d.frame] = Rigid.from_rotvec(rv.ravel(), tv.ravel())
        med = float(np.median(list(frame_rms.values())))
        bad = [f for f, r in frame_rms.items() if r > max(outlier_px, 3 * med)]
        oblique = {d.frame: view_angle_deg(poses[d.frame], corners_board[d.ids].mean(axis=0)) for d in dets}
        oblique = {f: a for f, a in oblique.items() if a > max_view_angle_deg and f not in bad}
        if (not bad and not oblique) or len(dets) - len(bad) - len(oblique) < 3:
            break
        for f in bad:
            log.warning("%s frame %04d: reprojection RMS %.2f px (median %.2f): dropped as an outlier",
                        name, f, frame_rms[f], med)
        for f, a in oblique.items():
            log.info("%s frame %04d: board seen at %.0f deg (> %.0f): dropped as too oblique", name, f, a,
                     max_view_angle_deg)
        bad += list(oblique)
        dets = [d for d in dets if d.frame not in bad]
    return Intrinsics(K, dist, poses, float(rms), frame_rms)


def view_angle_deg(cam_from_board: Rigid, point_board: np.ndarray) -> float:
    """Angle between the board's normal and the line of sight to ``point_board``, degrees."""
    to_point = cam_from_board.apply(point_board)
    normal = cam_from_board.R[:, 2]
    return float(np.degrees(np.arccos(min(abs(normal @ to_point) / np.linalg.norm(to_point), 1.0))))


def _average_rigid(estimates: list[tuple[Rigid, float]]) -> Rigid:
    """Weighted mean of nearby rigid transforms (chordal rotation mean, projected back onto SO(3))."""
    w = np.array([e[1] for e in estimates], float)
    M = sum(wi * e[0].R for wi, e in zip(w, estimates))
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    t = sum(wi * e[0].t for wi, e in zip(w, estimates)) / w.sum()
    return Rigid(R, t)


def chain_poses(names: list[str], intr: dict[str, Intrinsics], counts: dict[tuple[str, int], int],
                reference_frame: int) -> tuple[str, dict[str, Rigid], dict[int, Rigid]]:
    """Put every camera and board pose in one frame: the rig frame of a reference camera.

    The reference camera is one that saw the reference board pose (most corners). Poses are
    propagated breadth-first: a board pose seen by a placed camera is placed, a camera that
    sees a placed board pose is placed; several estimates are averaged, weighted by corners.

    Returns the reference camera, ``cam_from_rig`` per camera and ``rig_from_board`` per frame.
    """
    seen_ref = [(counts.get((n, reference_frame), 0), n) for n in names if reference_frame in intr[n].cam_from_board]
    if not seen_ref:
        raise InputError(f"board pose {reference_frame:04d} (the fixture pose that defines the world frame) was "
                         "not detected in any camera; re-shoot it with the board fully in view of at least one "
                         "camera, or set calibrate.reference_frame to another fixture frame")
    ref = max(seen_ref)[1]
    cam_from_rig: dict[str, Rigid] = {ref: Rigid.identity()}
    rig_from_board: dict[int, Rigid] = {}
    all_frames = sorted({f for n in names for f in intr[n].cam_from_board})
    changed = True
    while changed:
        changed = False
        for f in all_frames:
            if f in rig_from_board:
                continue
            est = [(cam_from_rig[n].inverse() @ intr[n].cam_from_board[f], counts[(n, f)])
                   for n in cam_from_rig if f in intr[n].cam_from_board]
            if est:
                rig_from_board[f] = _average_rigid(est)
                changed = True
        for n in names:
            if n in cam_from_rig:
                continue
            est = [(intr[n].cam_from_board[f] @ rig_from_board[f].inverse(), counts[(n, f)])
                   for f in intr[n].cam_from_board if f in rig_from_board]
            if est:
                cam_from_rig[n] = _average_rigid(est)
                changed = True
    missing = [n for n in names if n not in cam_from_rig]
    if missing:
        raise InputError(f"cameras {', '.join(missing)} share no board frame with the others (no chain of "
                         "frames links them to the reference camera); re-shoot the board take with poses "
                         "seen by these cameras and a neighbour at the same time")
    return ref, cam_from_rig, rig_from_board
