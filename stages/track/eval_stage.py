"""Stage ``track_eval``: tracking accuracy against the virtual studio's ground truth.

Inputs: ``track`` and ``capture.truth`` (``frames.npz`` poses, ``meshes.npz`` head-space
vertices, ``cameras.json``). Vertex errors are measured in head space on the face region
(the ICT ``face`` vertices when the mesh has ICT topology), for full-on (fitted) and OLAT
(interpolated) frames separately. Poses are compared in the truth's world frame: the
calibration may have chosen another world frame (another origin or orientation), so the
estimated world is first mapped onto the true one through the cameras the tracker used
(``track/cameras.json`` against ``truth/cameras.json``, matched by name).
"""

from __future__ import annotations

import numpy as np

from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext, StageParams
from scene.camera import Rigid
from stages.capture.output import CaptureTruth
from stages.track import topology
from stages.track.geometry import rotation_angle_deg
from stages.track.output import TrackOutput


class TrackEvalParams(StageParams):
    """Params of the track evaluation (none)."""


def truth_world_from_estimated_world(track: TrackOutput, truth_out: CaptureTruth) -> Rigid:
    """The rigid map from the calibration's world frame to the truth's, through shared cameras.

    For every camera, ``truth_world_from_cam @ cam_from_est_world`` is an estimate of the
    map; rotations are averaged (chordal mean), translations averaged.
    """
    est = {c.name: c for c in track.cameras()}
    truth = {c.name: c for c in truth_out.cameras()}
    shared = sorted(set(est) & set(truth))
    if not shared:
        raise InputError(f"{track.cameras_path}: no camera name in common with {truth_out.cameras_path}")
    maps = [truth[n].cam_from_world.inverse() @ est[n].cam_from_world for n in shared]
    U, _, Vt = np.linalg.svd(sum(m.R for m in maps))
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    t = np.mean([m.t for m in maps], axis=0)
    return Rigid(R, t)


def run(ctx: StageContext) -> None:
    """Compare the tracked meshes and poses with the truth; see the module docstring."""
    track, truth = TrackOutput(ctx.input("track")), CaptureTruth(ctx.input("capture.truth"))
    tracking = track.tracking(("index", "full_on", "world_from_head_R", "world_from_head_t"))
    meshes = track.meshes(("index", "vertices"))
    true_frames = truth.frames(("index", "world_from_head_R", "world_from_head_t"))
    true_meshes = truth.meshes(("vertices",))

    true_row = {int(i): k for k, i in enumerate(true_frames["index"])}
    rows = [(k, true_row[int(i)]) for k, i in enumerate(tracking["index"]) if int(i) in true_row]
    if not rows:
        raise InputError(f"{track.tracking_path}: no frame index in common with {truth.frames_path}")
    est_idx = np.array([r[0] for r in rows])
    true_idx = np.array([r[1] for r in rows])
    est_v = meshes["vertices"][est_idx].astype(np.float64)
    true_v = true_meshes["vertices"][true_idx].astype(np.float64)
    if est_v.shape[1:] != true_v.shape[1:]:
        raise InputError(f"{track.meshes_path}: meshes have {est_v.shape[1]} vertices, the truth "
                         f"{true_v.shape[1]}; the scan session must share the truth's topology")
    face = topology.face_vertex_mask(est_v.shape[1])
    vertex_err_mm = np.linalg.norm(est_v[:, face] - true_v[:, face], axis=-1) * 1000.0  # [T, Vf]
    full = tracking["full_on"][est_idx].astype(bool)

    world = truth_world_from_estimated_world(track, truth)
    R_est = np.einsum("ij,tjk->tik", world.R, tracking["world_from_head_R"][est_idx])
    t_est = tracking["world_from_head_t"][est_idx] @ world.R.T + world.t
    rot_err = rotation_angle_deg(R_est, true_frames["world_from_head_R"][true_idx])
    trans_err_mm = np.linalg.norm(t_est - true_frames["world_from_head_t"][true_idx], axis=1) * 1000.0

    def mean_or_nan(x: np.ndarray) -> float:
        return float(np.mean(x)) if x.size else float("nan")

    ctx.metrics.update({
        "vertex_err_mm_mean_full": mean_or_nan(vertex_err_mm[full]),
        "vertex_err_mm_p95_full": float(np.percentile(vertex_err_mm[full], 95)) if full.any() else float("nan"),
        "vertex_err_mm_mean_olat": mean_or_nan(vertex_err_mm[~full]),
        "vertex_err_mm_p95_olat": float(np.percentile(vertex_err_mm[~full], 95)) if (~full).any() else float("nan"),
        "vertex_err_mm_max": float(vertex_err_mm.max()),
        "rotation_err_deg_mean": float(rot_err.mean()),
        "rotation_err_deg_max": float(rot_err.max()),
        "translation_err_mm_mean": float(trans_err_mm.mean()),
        "translation_err_mm_max": float(trans_err_mm.max()),
        "evaluated_frames": len(rows),
    })
    ctx.log.info("vertex error %.2f mm (full-on), %.2f mm (OLAT); rotation %.3f deg, translation %.2f mm",
                 ctx.metrics["vertex_err_mm_mean_full"], ctx.metrics["vertex_err_mm_mean_olat"],
                 ctx.metrics["rotation_err_deg_mean"], ctx.metrics["translation_err_mm_mean"])


STAGE = Stage(name="track_eval", inputs=("track", "capture.truth"), params=TrackEvalParams, run=run,
              evaluates="track", doc="Tracking accuracy against ground truth.")
