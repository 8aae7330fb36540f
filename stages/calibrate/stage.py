"""``calibrate``: ChArUco board takes -> intrinsics, distortion and extrinsics of every camera.

Steps: detect corners in every board image (frames that are over-exposed, blurred or
without a board are skipped with a reason), calibrate each camera with OpenCV, chain
all cameras and board poses into one frame through shared board frames, refine
everything jointly in pycolmap (robust BA; the board's corners refined with two held at
their printed places, which fixes metric scale, or all held there: ``board_shape``), and
express the result in the studio world: the board's fixture pose (``calib/board.json``) at the reference frame defines it.

The board take is shot at the cameras' native resolution (as a studio calibrates, whatever
resolution the performance is later used at); the cameras are calibrated there and
``cameras.json`` holds them scaled to the performance images' resolution (``manifest.json``
width/height; pixel-centre convention, ``Camera.scaled``), ``cameras_native.json`` at the
board images' resolution.

Outputs: ``cameras.json``, ``cameras_native.json`` (``scene.camera.save_cameras``),
``colmap/text`` and ``colmap/binary`` (COLMAP model at the board images' resolution, whose
keypoints it holds), ``board_poses.json``, ``report.json`` and ``residuals/<cam>.png``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext, StageParams
from scene.camera import Camera
from stages.calibrate.board import (
    CharucoFinder,
    Detection,
    FrameVerdict,
    load_board_spec,
)
from stages.calibrate.board_shape import bow_m as board_bow_m
from stages.calibrate.board_shape import scale_err_pct as board_scale_err_pct
from stages.calibrate.board_shape import shift_m_max as board_shift_m_max
from stages.calibrate.bundle import bundle_adjust, export_colmap
from stages.calibrate.initial import calibrate_intrinsics, chain_poses
from stages.calibrate.output import CalibrateOutput
from stages.calibrate.report import plot_residuals, residuals_px
from stages.calibrate.resolution import (
    capture_cameras,
    performance_size,
    to_performance_resolution,
)
from stages.capture.output import CaptureOutput


class CalibrateParams(StageParams):
    """Camera calibration settings."""

    min_corners: int = Field(8, ge=4, description="Fewest ChArUco corners for a board image to be used.")
    min_frames: int = Field(4, ge=3, description="Fewest usable board images per camera.")
    camera_model: Literal["SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV"] = Field(
        "OPENCV", description="Lens model (COLMAP names): OPENCV = fx, fy, cx, cy, k1, k2, p1, p2; RADIAL = square "
        "pixels, k1, k2 only. Real lenses are slightly decentred: without p1, p2 the principal point and the "
        "rotation absorb the tangential terms (0.1 deg off on the studio's narrow lenses).")
    max_saturated_fraction: float = Field(
        0.02, gt=0, le=1, description="A board image with more pixels at the white level than this is over-exposed.")
    max_edge_width_px: float = Field(3.5, gt=0, description="A board image whose edges are wider than this is blurred.")
    outlier_frame_px: float = Field(1.0, gt=0, description="A frame whose RMS exceeds this (and 3x the median) is dropped.")
    max_view_angle_deg: float = Field(
        50.0, gt=0, lt=90, description="Board images seen more obliquely than this are dropped (biased corners).")
    board_shape: Literal["nominal", "refined"] = Field(
        "refined", description="The board's corners in the bundle adjustment: 'refined' moves them (one board shared "
        "by every pose, as cv2.calibrateCameraRO does), holding the first row's two ends at nominal (their distance "
        "sets the scale, which the cameras cannot observe); 'nominal' "
        "holds every corner at its printed nominal place. A real print is a little off scale and bows, and with "
        "'nominal' the intrinsics absorb that; choose 'nominal' only for a board whose flatness and print are known "
        "to be much better than the corner detection (then 'refined' adds unknowns for nothing).")
    loss_scale_px: float = Field(1.0, gt=0, description="Soft-L1 loss scale of the bundle adjustment, pixels.")
    max_iterations: int = Field(100, ge=1, description="Bundle adjustment iterations.")
    reference_frame: int | None = Field(
        None, description="Board frame shot in the fixture (defines the world); default: calib/board.json's.")
    allow_missing_cameras: bool = Field(
        False, description="Drop (with a warning) cameras that cannot be calibrated instead of failing.")
    source: str | None = Field(
        None, description="An existing calibration to use instead of the board takes: a COLMAP model folder (text or "
        "binary) or OpenCV-style camera files (a folder of <camera>.yaml/.json, or one JSON with 'cameras'; fields in "
        "stages/calibrate/sources.py). Every capture camera must be in it; it is scaled to the performance images. "
        "Leave unset to calibrate from the capture's ChArUco takes.")
    source_units_m: float = Field(
        1.0, gt=0, description="Metres per unit of the source's world coordinates: 0.001 for millimetres. A COLMAP "
        "model from structure from motion has no metric scale; set this from a distance you know.")
    max_source_reproj_px: float = Field(
        1.0, gt=0, description="Refuse a source whose reprojection RMS for any camera (from its own points, where it "
        "has them; board-image pixels) is above this: it does not describe this rig well.")


def _detect_camera(capture: CaptureOutput, name: str, finder: CharucoFinder, log
                   ) -> tuple[list[Detection], list[FrameVerdict], tuple[int, int] | None]:
    from scene.image_io import read_exr

    files = capture.charuco_images(name)
    detections, verdicts, size = [], [], None
    for path in files:
        try:
            frame = int(path.stem)
        except ValueError:
            log.warning("%s: not a board frame name (expected <k:04d>.exr); skipped", path)
            continue
        try:
            image = read_exr(path)
        except ValueError as err:
            raise InputError(str(err)) from err
        if size is None:
            size = (image.shape[1], image.shape[0])
        elif size != (image.shape[1], image.shape[0]):
            raise InputError(f"{path}: image size {image.shape[1]}x{image.shape[0]} differs from the camera's "
                             f"other board images ({size[0]}x{size[1]}); the take is mixed up")
        det, verdict = finder.find(image, frame)
        verdicts.append(verdict)
        if det is not None:
            detections.append(det)
        elif not verdict.reason.startswith("board not found"):
            log.warning("%s frame %04d: %s; frame skipped", name, frame, verdict.reason)
    return detections, verdicts, size


def run(ctx: StageContext) -> None:
    """Calibrate every camera from the capture's board takes, or take an existing calibration (``source``)."""
    params: CalibrateParams = ctx.params  # type: ignore[assignment]
    capture = CaptureOutput(ctx.input("capture"))
    out = CalibrateOutput(ctx.out)
    if params.source:
        from stages.calibrate.from_source import calibrate_from_source

        calibrate_from_source(capture, out, params, ctx.metrics, ctx.log)
        return
    spec = load_board_spec(capture, ctx.log)
    reference_frame = spec.reference_pose_index if params.reference_frame is None else params.reference_frame
    corners_board = spec.corners_board()
    finder = CharucoFinder(spec, params.min_corners, params.max_saturated_fraction, params.max_edge_width_px)
    names = capture_cameras(capture)

    detections: dict[str, list[Detection]] = {}
    verdicts: dict[str, list[FrameVerdict]] = {}
    sizes: dict[str, tuple[int, int]] = {}
    problems: dict[str, str] = {}
    with ctx.progress(len(names), "cameras") as progress:
        for name in names:
            dets, verd, size = _detect_camera(capture, name, finder, ctx.log)
            detections[name], verdicts[name] = dets, verd
            if size is not None:
                sizes[name] = size
            if not verd:
                problems[name] = (f"camera {name} has no board images in calib/charuco/{name}; "
                                  "re-shoot the board take with this camera recording")
            elif not dets:
                problems[name] = (f"camera {name} never saw the board ({len(verd)} images, none usable: "
                                  f"{_reason_summary(verd)}); re-shoot the board take with poses facing {name}")
            elif len(dets) < params.min_frames:
                problems[name] = (f"camera {name} has only {len(dets)} usable board images "
                                  f"(frames {', '.join(f'{d.frame:04d}' for d in dets)}), needs at least "
                                  f"{params.min_frames}; re-shoot the board take with more poses facing {name}")
            progress.advance(1, detections=len(dets))
    for name, message in problems.items():
        if not params.allow_missing_cameras:
            raise InputError(message + " (or set calibrate.allow_missing_cameras to drop it)")
        ctx.log.warning("%s: camera dropped from the calibration", message)
    names = [n for n in names if n not in problems]
    if not names:
        raise InputError("no camera could be calibrated; check calib/charuco in the capture")

    intr = {}
    for name in names:
        intr[name] = calibrate_intrinsics(name, detections[name], corners_board, sizes[name], params.camera_model,
                                          params.outlier_frame_px, params.max_view_angle_deg, ctx.log)
        ctx.log.info("%s: %d board images, OpenCV RMS %.3f px", name, len(intr[name].cam_from_board),
                     intr[name].rms_px)
        detections[name] = [d for d in detections[name] if d.frame in intr[name].cam_from_board]
    counts = {(n, d.frame): len(d.ids) for n in names for d in detections[n]}
    ref, cam_from_rig, rig_from_board = chain_poses(names, intr, counts, reference_frame)

    initial = {n: Camera(name=n, width=sizes[n][0], height=sizes[n][1], fx=float(intr[n].K[0, 0]),
                         fy=float(intr[n].K[1, 1]), cx=float(intr[n].K[0, 2]), cy=float(intr[n].K[1, 2]),
                         dist=tuple(float(v) for v in intr[n].dist), pose=cam_from_rig[n], frame="rig")  # type: ignore[arg-type]
               for n in names}
    ba = bundle_adjust(initial, rig_from_board, detections, corners_board, ref, params.loss_scale_px,
                       params.max_iterations, params.camera_model, params.board_shape)
    ctx.log.info("bundle adjustment: %s", ba.summary)
    nominal_corners_board, corners_board = corners_board, ba.corners_board

    # the studio world: the fixture frame's board pose is known in it
    rig_from_world = ba.rig_from_board[reference_frame] @ spec.world_from_board_reference.inverse()
    cameras = [ba.cameras[n].with_pose(ba.cameras[n].cam_from_rig @ rig_from_world, "world") for n in names]
    world_from_board = {f: rig_from_world.inverse() @ p for f, p in ba.rig_from_board.items()}

    out.write_cameras_native(cameras)
    perf_size = performance_size(capture)
    out.write_cameras([to_performance_resolution(c, perf_size) for c in cameras])
    export_colmap(out.colmap_dir, {c.name: c for c in cameras}, detections, world_from_board, corners_board, ref,
                  params.camera_model)
    out.write_board_poses({"world_from_board": {f"{f:04d}": {"R": p.R.tolist(), "t": p.t.tolist()}
                                                for f, p in sorted(world_from_board.items())}})
    out.make_residuals_dir()
    report, all_res = {}, []
    for cam in cameras:
        res, obs = residuals_px(cam, detections[cam.name], world_from_board, corners_board)
        all_res.append(res)
        rms = float(np.sqrt(np.mean(np.sum(res ** 2, axis=1))))
        plot_residuals(out.residuals_path(cam.name), cam, res, obs)
        report[cam.name] = {
            "frames_used": len(detections[cam.name]), "corners_used": len(res), "reproj_rms_px": rms,
            "opencv_rms_px": intr[cam.name].rms_px,
            "frames": [_frame_entry(v, intr[cam.name].cam_from_board) for v in verdicts[cam.name]],
            "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "dist": list(cam.dist)}
        ctx.log.info("%s: %d frames, %d corners, RMS %.3f px", cam.name, len(detections[cam.name]), len(res), rms)
    out.write_report(
        {"reference_camera": ref, "reference_frame": reference_frame, "dropped_cameras": sorted(problems),
         "calibration_size": list(sizes[names[0]]), "performance_size": list(perf_size) if perf_size else None,
         "bundle_adjustment": ba.summary, "board_shape": params.board_shape,
         "board_corners_board_m": corners_board.tolist(), "cameras": report})
    res = np.concatenate(all_res)
    # pixels of the board images (the native resolution); cameras.json may be at another
    ctx.metrics["reproj_rms_px"] = float(np.sqrt(np.mean(np.sum(res ** 2, axis=1))))
    ctx.metrics["calibration_width_px"] = sizes[names[0]][0]
    ctx.metrics["reproj_rms_px_max_camera"] = max(r["reproj_rms_px"] for r in report.values())
    ctx.metrics["cameras"] = len(cameras)
    ctx.metrics["cameras_dropped"] = len(problems)
    ctx.metrics["board_frames"] = len(world_from_board)
    ctx.metrics["corners_used"] = len(res)
    ctx.metrics["frames_rejected_quality"] = sum(
        1 for v in verdicts.values() for x in v if not x.used and not x.reason.startswith("board not found"))
    ctx.metrics.update(_board_shape_metrics(corners_board, nominal_corners_board, params.board_shape))


def _board_shape_metrics(corners_board: np.ndarray, nominal_corners_board: np.ndarray, board_shape: str) -> dict:
    """The refined board against nominal (all 0 under ``board_shape: nominal``); mm and percent."""
    return {"board_shape_refined": int(board_shape == "refined"),
            "board_refined_bow_mm": 1000 * board_bow_m(corners_board, nominal_corners_board),
            "board_refined_shift_mm_max": 1000 * board_shift_m_max(corners_board, nominal_corners_board),
            "board_refined_scale_err_pct_x": board_scale_err_pct(corners_board, nominal_corners_board, 0),
            "board_refined_scale_err_pct_y": board_scale_err_pct(corners_board, nominal_corners_board, 1)}


def _frame_entry(verdict: FrameVerdict, kept: dict) -> dict:
    """A frame's line in the report: used or why not."""
    used = verdict.used and verdict.frame in kept
    reason = verdict.reason if not verdict.used else ("ok" if used else "dropped: outlier RMS or too oblique")
    return {"frame": verdict.frame, "used": used, "reason": reason, "corners": verdict.corners}


def _reason_summary(verdicts: list[FrameVerdict]) -> str:
    reasons: dict[str, int] = {}
    for v in verdicts:
        key = v.reason.split(" (")[0]
        reasons[key] = reasons.get(key, 0) + 1
    return ", ".join(f"{k}: {n}" for k, n in sorted(reasons.items()))


def _external(params: CalibrateParams) -> list[Path]:
    return [Path(params.source).expanduser()] if params.source else []


STAGE = Stage(name="calibrate", inputs=("capture",), params=CalibrateParams, run=run, external_inputs=_external,
              doc="ChArUco board takes -> intrinsics, distortion, extrinsics (pycolmap BA), COLMAP export.")
