"""Stage ``stabilize_eval``: head-space cameras against the truth.

``head_pose_residual_deg_max``: over all frames and cameras, the largest rotation angle
between the estimated ``cam_from_head`` and the true one (true ``cam_from_world`` composed
with the true ``world_from_head``). ``cam_from_head`` does not depend on the world frame
the calibration chose, so no alignment is needed; it carries both calibration and tracking
error. Also the mean, and the camera-centre error in head space (mm).
"""

from __future__ import annotations

import numpy as np

from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext, StageParams
from scene.camera import Rigid
from stages.capture.output import CaptureTruth
from stages.stabilize.output import StabilizeOutput


class StabilizeEvalParams(StageParams):
    """Params of the stabilize evaluation (none)."""


def run(ctx: StageContext) -> None:
    """Compare every frame's head-space cameras with the truth's."""
    truth = CaptureTruth(ctx.input("capture.truth"))
    head_cams = StabilizeOutput(ctx.input("stabilize")).cameras_head()
    true_cams = {c.name: c for c in truth.cameras()}
    data = truth.frames(keys=("index", "world_from_head_R", "world_from_head_t"))
    true_pose = {int(i): Rigid(np.asarray(R), np.asarray(t)) for i, R, t in
                 zip(data["index"], data["world_from_head_R"], data["world_from_head_t"])}
    angles, centres_mm = [], []
    for index, cams in head_cams.items():
        if index not in true_pose:
            continue
        for cam in cams:
            if cam.name not in true_cams:
                continue
            true_cam_from_head = true_cams[cam.name].cam_from_world @ true_pose[index]
            rel = cam.cam_from_head.R @ true_cam_from_head.R.T
            angles.append(np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1))))
            centre_est = cam.cam_from_head.inverse().t
            centre_true = true_cam_from_head.inverse().t
            centres_mm.append(np.linalg.norm(centre_est - centre_true) * 1000)
    if not angles:
        raise InputError("stabilize_eval: no frame index and camera name in common with the truth")
    ctx.metrics.update({
        "head_pose_residual_deg_max": float(np.max(angles)),
        "head_pose_residual_deg_mean": float(np.mean(angles)),
        "head_camera_center_err_mm_mean": float(np.mean(centres_mm)),
        "head_camera_center_err_mm_max": float(np.max(centres_mm)),
    })


STAGE = Stage(name="stabilize_eval", inputs=("stabilize", "capture.truth"), params=StabilizeEvalParams, run=run,
              evaluates="stabilize", doc="Head-space cameras against ground truth.")
