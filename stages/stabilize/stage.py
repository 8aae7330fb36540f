"""Stage ``stabilize``: per-frame camera extrinsics in head space.

Inputs: ``track`` (``tracking.npz``: world_from_head per frame) and ``calibrate``
(``cameras.json``). Output: ``cameras_head.json`` (format in
``stages.stabilize.cameras_head``): for every frame, every camera with
``cam_from_head = cam_from_world @ world_from_head``, so a renderer placing the
expression-only, head-space mesh before these cameras sees exactly the captured image.
"""

from __future__ import annotations

import numpy as np

from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext, StageParams
from scene.camera import load_cameras
from stages.stabilize.cameras_head import write_cameras_head


class StabilizeParams(StageParams):
    """Params of the stabilize stage (none: the algebra has no settings)."""


def run(ctx: StageContext) -> None:
    """Fold each frame's head pose into the calibrated cameras."""
    tracking_path = ctx.input("track") / "tracking.npz"
    try:
        with np.load(tracking_path, allow_pickle=False) as data:
            index = np.asarray(data["index"])
            R = np.asarray(data["world_from_head_R"], dtype=np.float64)
            t = np.asarray(data["world_from_head_t"], dtype=np.float64)
    except KeyError as err:
        raise InputError(f"{tracking_path}: missing key {err}; re-run the track stage") from err
    except (OSError, ValueError) as err:
        raise InputError(f"{tracking_path}: not a readable npz ({err}); re-run the track stage") from err
    if R.shape != (len(index), 3, 3) or t.shape != (len(index), 3):
        raise InputError(f"{tracking_path}: world_from_head_R {R.shape} / world_from_head_t {t.shape} do not "
                         f"match {len(index)} frames; re-run the track stage")
    cams_path = ctx.input("calibrate") / "cameras.json"
    try:
        cameras = load_cameras(cams_path)
    except ValueError as err:
        raise InputError(str(err)) from err
    write_cameras_head(ctx.out / "cameras_head.json", index, R, t, cameras)
    ctx.metrics.update({"frames": int(len(index)), "cameras": len(cameras)})
    ctx.log.info("wrote head-space cameras for %d frames x %d cameras", len(index), len(cameras))


STAGE = Stage(name="stabilize", inputs=("track", "calibrate"), params=StabilizeParams, run=run,
              doc="Per-frame cameras in head space (cam_from_head = cam_from_world @ world_from_head).")
