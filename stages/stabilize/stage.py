"""Stage ``stabilize``: per-frame camera extrinsics in head space.

Inputs: ``track`` (``tracking.npz``: world_from_head per frame) and ``calibrate``
(``cameras.json``). Output: ``cameras_head.json`` (format in
``stages.stabilize.cameras_head``): for every frame, every camera with
``cam_from_head = cam_from_world @ world_from_head``, so a renderer placing the
expression-only, head-space mesh before these cameras sees exactly the captured image.
"""

from __future__ import annotations

import numpy as np

from pipeline.stage import Stage, StageContext, StageParams
from stages.calibrate.output import CalibrateOutput
from stages.stabilize.output import StabilizeOutput
from stages.track.output import TrackOutput


class StabilizeParams(StageParams):
    """Params of the stabilize stage (none: the algebra has no settings)."""


def run(ctx: StageContext) -> None:
    """Fold each frame's head pose into the calibrated cameras."""
    track = TrackOutput(ctx.input("track"))
    data = track.tracking(keys=("index", "world_from_head_R", "world_from_head_t"))
    index = np.asarray(data["index"])
    R = np.asarray(data["world_from_head_R"], dtype=np.float64)
    t = np.asarray(data["world_from_head_t"], dtype=np.float64)
    if R.shape != (len(index), 3, 3) or t.shape != (len(index), 3):
        raise track.malformed(track.tracking_path, f"world_from_head_R {R.shape} / world_from_head_t {t.shape} "
                                                   f"do not match {len(index)} frames")
    cameras = CalibrateOutput(ctx.input("calibrate")).cameras()
    StabilizeOutput(ctx.out).write_cameras_head(index, R, t, cameras)
    ctx.metrics.update({"frames": int(len(index)), "cameras": len(cameras)})
    ctx.log.info("wrote head-space cameras for %d frames x %d cameras", len(index), len(cameras))


STAGE = Stage(name="stabilize", inputs=("track", "calibrate"), params=StabilizeParams, run=run,
              doc="Per-frame cameras in head space (cam_from_head = cam_from_world @ world_from_head).")
