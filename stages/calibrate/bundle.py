"""Joint bundle adjustment of every camera and board pose in pycolmap, and the COLMAP export.

The BA model (what pycolmap supports natively): the board is the "world" of the BA, its
corners are 3D points, either all held at their nominal places (``board_shape`` "nominal":
the printed metric geometry fixes scale and shape) or refined, one point per corner shared by
every pose, with two corners held at nominal to fix the gauge (``board_shape`` "refined",
``stages/calibrate/board_shape.py``); every camera is a sensor of one rig (``sensor_from_rig``
= ``cam_from_rig``, the reference camera's is the identity); every board pose is one frame whose
``rig_from_world`` is ``rig_from_board``. Intrinsics (OPENCV model: fx, fy, cx, cy, k1, k2,
p1, p2 for OPENCV), sensor poses and frame poses are refined with a robust (soft L1) loss.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scene.camera import Camera, Rigid
from stages.calibrate.board import Detection
from stages.calibrate.sources import COLMAP_PIXEL_OFFSET, camera_from_colmap


@dataclass
class BundleResult:
    """Refined cameras (in the rig frame) and board poses, with pycolmap's summary."""

    cameras: dict[str, Camera]  # posed in the rig frame (cam_from_rig)
    rig_from_board: dict[int, Rigid]
    corners_board: np.ndarray  # [N, 3] the board's corners as the BA ends with them (nominal unless refined)
    initial_cost: float
    final_cost: float
    summary: str


def _rigid3d(x: Rigid):
    import pycolmap

    return pycolmap.Rigid3d(np.hstack([x.R, x.t[:, None]]))


def _from_rigid3d(x) -> Rigid:
    m = np.asarray(x.matrix())
    return Rigid(m[:3, :3].copy(), m[:3, 3].copy())


#: COLMAP camera models this stage uses, each a subset of our (fx, fy, cx, cy, k1, k2, p1, p2, k3) model.
CAMERA_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")


def _colmap_camera(cam: Camera, camera_id: int, model: str, pixel_offset: float = 0.0):
    import pycolmap

    k1, k2, p1, p2, k3 = cam.dist
    f = 0.5 * (cam.fx + cam.fy)
    cx, cy = cam.cx + pixel_offset, cam.cy + pixel_offset
    params = {"SIMPLE_RADIAL": [f, cx, cy, k1],
              "RADIAL": [f, cx, cy, k1, k2],
              "OPENCV": [cam.fx, cam.fy, cx, cy, k1, k2, p1, p2],
              "FULL_OPENCV": [cam.fx, cam.fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]}[model]
    return pycolmap.Camera(model=model, width=cam.width, height=cam.height, camera_id=camera_id, params=params)


def build_reconstruction(cameras: dict[str, Camera], rig_from_frame: dict[int, Rigid],
                         detections: dict[str, list[Detection]], points_in_frame: dict[int, np.ndarray] | None,
                         corners_board: np.ndarray, ref: str, model: str = "OPENCV", pixel_offset: float = 0.0):
    """A pycolmap reconstruction: one rig of all cameras, one frame per board pose.

    With ``points_in_frame`` None the world is the board (corners shared by all frames, the
    BA model); otherwise each frame has its own 3D points (the studio-world export, where
    every frame has the same rig pose and the board moves). ``pixel_offset`` is added to
    principal points and keypoints: 0 for the BA (OpenCV's pixel centres throughout), 0.5 for
    a model written for COLMAP, whose pixel centres are at +0.5.
    """
    import pycolmap

    rec = pycolmap.Reconstruction()
    names = list(cameras)
    cam_ids = {n: i + 1 for i, n in enumerate(names)}
    rig = pycolmap.Rig(rig_id=1)
    for n in names:
        rec.add_camera(_colmap_camera(cameras[n], cam_ids[n], model, pixel_offset))
    rig.add_ref_sensor(rec.camera(cam_ids[ref]).sensor_id)
    for n in names:
        if n != ref:
            rig.add_sensor(rec.camera(cam_ids[n]).sensor_id, _rigid3d(cameras[n].cam_from_rig))
    rec.add_rig(rig)
    point_ids: dict[tuple[int, int], int] = {}
    if points_in_frame is None:
        for cid, xyz in enumerate(corners_board):
            point_ids[(-1, cid)] = rec.add_point3D(xyz, pycolmap.Track())
    image_id = 0
    for f, rig_from in sorted(rig_from_frame.items()):
        frame = pycolmap.Frame(frame_id=f + 1, rig_id=1, rig_from_world=_rigid3d(rig_from))
        images = []
        for n in names:
            det = next((d for d in detections[n] if d.frame == f), None)
            if det is None:
                continue
            image_id += 1
            image = pycolmap.Image(name=f"{n}/{f:04d}.exr", keypoints=det.corners_px + pixel_offset,
                                   camera_id=cam_ids[n], image_id=image_id)
            image.frame_id = f + 1
            frame.add_data_id(image.data_id)
            images.append((image, det))
        rec.add_frame(frame)
        for image, det in images:
            rec.add_image(image)
        for image, det in images:
            for idx, cid in enumerate(det.ids):
                key = (-1, int(cid)) if points_in_frame is None else (f, int(cid))
                if key not in point_ids:
                    point_ids[key] = rec.add_point3D(points_in_frame[f][cid], pycolmap.Track())
                rec.add_observation(point_ids[key], pycolmap.TrackElement(image.image_id, idx))
    return rec, cam_ids


def bundle_adjust(cameras: dict[str, Camera], rig_from_board: dict[int, Rigid],
                  detections: dict[str, list[Detection]], corners_board: np.ndarray, ref: str,
                  loss_scale_px: float, max_iterations: int, model: str,
                  board_shape: str = "nominal") -> BundleResult:
    """Refine intrinsics, camera-in-rig poses and board poses jointly (pycolmap / Ceres, soft L1).

    ``board_shape`` "refined" also refines the board's corners, all but the gauge corners
    (``gauge_corner_ids``), which stay nominal and keep the board's scale; the refined board
    and its poses are then put back on the nominal board's frame (``board_from_refined``).
    """
    import pycolmap

    from stages.calibrate.board_shape import board_from_refined, gauge_corner_ids

    rec, cam_ids = build_reconstruction(cameras, rig_from_board, detections, None, corners_board, ref, model)
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = True
    options.refine_principal_point = True
    options.refine_extra_params = True
    options.refine_sensor_from_rig = True
    options.refine_rig_from_world = True
    options.refine_points3D = board_shape == "refined"
    options.min_track_length = 1
    options.print_summary = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.SOFT_L1
    options.ceres.loss_function_scale = loss_scale_px
    options.ceres.solver_options.max_num_iterations = max_iterations
    options.ceres.solver_options.function_tolerance = 1e-12
    options.ceres.solver_options.gradient_tolerance = 1e-12
    options.ceres.solver_options.parameter_tolerance = 1e-12
    options.ceres.solver_options.num_threads = 1
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.images:
        config.add_image(image_id)
    # build_reconstruction adds the board's corners first, in id order: point ids follow corner ids
    corner_point_ids = sorted(rec.point3D_ids())
    assert len(corner_point_ids) == len(corners_board)
    held = range(len(corner_point_ids)) if board_shape == "nominal" else gauge_corner_ids(corners_board)
    for cid, pid in enumerate(corner_point_ids):
        if cid in held:
            config.add_constant_point(pid)
        else:
            config.add_variable_point(pid)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.UNSPECIFIED)
    adjuster = pycolmap.create_default_bundle_adjuster(options, config, rec)
    summary = adjuster.solve()
    refined = {}
    for n, cid in cam_ids.items():
        rig = rec.rig(1)
        sensor = rec.camera(cid).sensor_id
        cam_from_rig = Rigid.identity() if n == ref else _from_rigid3d(rig.sensor_from_rig(sensor))
        refined[n] = camera_from_colmap(n, rec.camera(cid), cam_from_rig, "rig", pixel_offset=0.0)
    boards = {fid - 1: _from_rigid3d(fr.rig_from_world) for fid, fr in rec.frames.items()}
    refined_corners_board = np.array([rec.point3D(pid).xyz for pid in corner_point_ids], dtype=np.float64)
    if board_shape == "refined":
        # the roll about the gauge corners' row is free in the BA: the board poses hold it, so
        # move them with the board onto the nominal frame, which defines the studio world
        board_from_ba = board_from_refined(refined_corners_board, corners_board)
        refined_corners_board = board_from_ba.apply(refined_corners_board)
        boards = {f: rig_from_ba @ board_from_ba.inverse() for f, rig_from_ba in boards.items()}
    ceres = summary.ceres_summary
    brief = (f"{ceres.termination_type.name.lower()} after {ceres.num_successful_steps} steps, "
             f"cost {ceres.initial_cost:.4g} -> {ceres.final_cost:.4g}, {ceres.num_residuals} residuals")
    return BundleResult(refined, boards, refined_corners_board, float(ceres.initial_cost), float(ceres.final_cost), brief)


def export_colmap(out_dir: Path, cameras_world: dict[str, Camera], detections: dict[str, list[Detection]],
                  world_from_board: dict[int, Rigid], corners_board: np.ndarray, ref: str, model: str) -> None:
    """Write the calibration as a COLMAP model in the studio world, text (``colmap/text``) and binary.

    One rig of all cameras; one frame per board pose, each at the rig's (fixed) world pose;
    the board corners of each pose as 3D points in world metres, observed by the images.
    Pixel coordinates follow COLMAP's convention (pixel centres at +0.5), so COLMAP and
    ``calibrate.source`` read the model as it is.
    """
    ref_from_world = cameras_world[ref].cam_from_world
    in_rig = {n: c.with_pose(c.cam_from_world @ ref_from_world.inverse(), "rig") for n, c in cameras_world.items()}
    frames = {f: ref_from_world for f in world_from_board}
    points = {f: pose.apply(corners_board) for f, pose in world_from_board.items()}
    rec, _ = build_reconstruction(in_rig, frames, detections, points, corners_board, ref, model,
                                  pixel_offset=COLMAP_PIXEL_OFFSET)
    for sub in ("text", "binary"):
        (out_dir / sub).mkdir(parents=True, exist_ok=True)
    rec.write_text(str(out_dir / "text"))
    rec.write_binary(str(out_dir / "binary"))
