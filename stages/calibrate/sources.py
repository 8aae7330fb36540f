"""Existing calibrations as the calibrate stage's input: a COLMAP model or OpenCV-style camera files.

A studio that calibrated its rig already hands its result to ``calibrate.source``; the stage
then writes the same ``cameras.json`` as from its own board takes, so nothing downstream
changes. Two kinds are read:

- **a COLMAP model** (``cameras``, ``images``, ``points3D``; text or binary; ``pycolmap``
  reads both). A camera's name is its images' folder (``cam03/0001.png`` -> ``cam03``) or,
  for images at the top level, the file's stem (``cam03.png``). Every image of one camera
  must share its pose (a fixed rig): several images of one camera that disagree are an
  error naming the camera. COLMAP places pixel centres at +0.5 (the top-left pixel's centre is
  (0.5, 0.5)); the project follows OpenCV (its centre is (0, 0)), so principal points and
  keypoints are shifted by -0.5 on the way in. The model's own points give each camera's
  reprojection error.
- **OpenCV-style camera files**: a folder of ``<camera>.yaml`` / ``.yml`` / ``.json`` files,
  or one ``.json`` whose ``cameras`` maps names to the same fields. Fields: ``K`` (or
  ``camera_matrix``) 3 x 3; ``dist`` (or ``D``, ``distortion_coefficients``) k1, k2, p1, p2[, k3,
  ...]; ``R`` 3 x 3 (or ``rvec``, a Rodrigues vector); ``t`` (or ``T``, ``tvec``), with
  ``x_cam = R x_world + t`` (OpenCV's extrinsics); ``image_size`` [width, height] (or
  ``image_width`` and ``image_height``). YAML is read with OpenCV's ``FileStorage``, so the files
  ``cv::FileStorage`` writes (``!!opencv-matrix``) load as they are.

The world of the source is the studio world, scaled by ``units_m`` (metres per source unit:
structure from motion has no metric scale of its own).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from pipeline.errors import InputError
from scene.camera import Camera, Rigid

SourceKind = Literal["colmap", "opencv"]
#: COLMAP camera models that are a case of the project's (fx, fy, cx, cy, k1, k2, p1, p2, k3).
COLMAP_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
#: COLMAP's pixel centres are at +0.5, OpenCV's (the project's) at 0.
COLMAP_PIXEL_OFFSET = 0.5
_POSE_TOLERANCE_M, _POSE_TOLERANCE_DEG = 1e-4, 0.01


@dataclass
class SourceCalibration:
    """Cameras read from an existing calibration, posed in the (metric) studio world."""

    kind: SourceKind
    path: Path
    cameras: dict[str, Camera]  # cam_from_world, at the source's image resolution
    residuals_px: dict[str, np.ndarray] = field(default_factory=dict)  # [N, 2] per camera with points

    def reproj_rms_px(self, name: str) -> float | None:
        res = self.residuals_px.get(name)
        if res is None or len(res) == 0:
            return None
        return float(np.sqrt(np.mean(np.sum(res ** 2, axis=1))))


def read_calibration_source(path: str | Path, units_m: float = 1.0) -> SourceCalibration:
    """The calibration at ``path``: a COLMAP model folder or OpenCV-style files (see the module docstring)."""
    path = Path(path).expanduser()
    if not path.exists():
        raise InputError(f"calibrate.source {path}: no such file or folder")
    if path.is_dir() and any((path / f"cameras.{ext}").is_file() for ext in ("txt", "bin")):
        return read_colmap_model(path, units_m)
    return read_opencv_cameras(path, units_m)


# ---- COLMAP ----------------------------------------------------------------------------------

def camera_name_of_image(image_name: str) -> str:
    """The camera an image belongs to: its folder (``cam03/0001.png``), else its stem (``cam03.png``)."""
    parts = Path(image_name).parts
    return parts[0] if len(parts) > 1 else Path(image_name).stem


def camera_from_colmap(name: str, colmap_camera, pose: Rigid, frame: str = "world",
                       pixel_offset: float = COLMAP_PIXEL_OFFSET) -> Camera:
    """Our camera (OpenCV pixel convention) from a pycolmap camera; ``InputError`` for a model we cannot hold.

    ``pose`` is ``cam_from_<frame>``; ``pixel_offset`` is subtracted from the principal point
    (0.5 for a model in COLMAP's convention, 0 for one built in the project's, as the BA's).
    """
    model = colmap_camera.model.name
    p = [float(v) for v in colmap_camera.params]
    if model not in COLMAP_MODELS:
        raise InputError(f"COLMAP camera {colmap_camera.camera_id} ({name}): model {model} is not supported; "
                         f"use one of {', '.join(COLMAP_MODELS)} (re-run COLMAP's bundle adjustment with one)")
    if model == "SIMPLE_PINHOLE":
        fx = fy = p[0]
        cx, cy, dist = p[1], p[2], (0.0,) * 5
    elif model == "PINHOLE":
        fx, fy, cx, cy = p[:4]
        dist = (0.0,) * 5
    elif model == "SIMPLE_RADIAL":
        fx = fy = p[0]
        cx, cy, dist = p[1], p[2], (p[3], 0.0, 0.0, 0.0, 0.0)
    elif model == "RADIAL":
        fx = fy = p[0]
        cx, cy, dist = p[1], p[2], (p[3], p[4], 0.0, 0.0, 0.0)
    else:
        fx, fy, cx, cy = p[:4]
        dist = (p[4], p[5], p[6], p[7], p[8] if model == "FULL_OPENCV" else 0.0)
        if model == "FULL_OPENCV" and any(abs(v) > 0 for v in p[9:12]):
            raise InputError(f"COLMAP camera {colmap_camera.camera_id} ({name}): FULL_OPENCV with rational terms "
                             f"k4..k6 = {p[9:12]}; the project's lens model has none (refine with OPENCV instead)")
    return Camera(name=name, width=int(colmap_camera.width), height=int(colmap_camera.height), fx=fx, fy=fy,
                  cx=cx - pixel_offset, cy=cy - pixel_offset, dist=dist,  # type: ignore[arg-type]
                  pose=pose, frame=frame)  # type: ignore[arg-type]


def _same_pose(a: Rigid, b: Rigid) -> bool:
    angle = np.degrees(np.arccos(np.clip((np.trace(a.R.T @ b.R) - 1.0) / 2.0, -1.0, 1.0)))
    centre_a, centre_b = -a.R.T @ a.t, -b.R.T @ b.t
    return angle < _POSE_TOLERANCE_DEG and float(np.linalg.norm(centre_a - centre_b)) < _POSE_TOLERANCE_M


def read_colmap_model(folder: Path, units_m: float = 1.0) -> SourceCalibration:
    """Cameras and reprojection residuals from a COLMAP model (text or binary) in ``folder``."""
    import pycolmap

    try:
        rec = pycolmap.Reconstruction(str(folder))
    except Exception as err:  # pycolmap raises plain RuntimeErrors for unreadable models
        raise InputError(f"calibrate.source {folder}: not a readable COLMAP model ({err}); it needs cameras, "
                         "images and points3D (.txt or .bin)") from err
    poses: dict[str, Rigid] = {}
    camera_ids: dict[str, int] = {}
    images: dict[str, list] = {}
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        if not image.has_pose:
            continue
        name = camera_name_of_image(image.name)
        m = np.asarray(image.cam_from_world().matrix())
        pose = Rigid(m[:3, :3].copy(), m[:3, 3] * units_m)
        if name not in poses:
            poses[name], camera_ids[name] = pose, image.camera_id
        elif not _same_pose(poses[name], pose):
            raise InputError(f"calibrate.source {folder}: camera {name}'s images disagree on its pose ({image.name} "
                             f"against its first image); a rig calibration needs one fixed pose per camera")
        elif image.camera_id != camera_ids[name]:
            raise InputError(f"calibrate.source {folder}: camera {name}'s images use different COLMAP cameras "
                             f"({camera_ids[name]} and {image.camera_id}, at {image.name})")
        images.setdefault(name, []).append(image)
    if not poses:
        raise InputError(f"calibrate.source {folder}: the COLMAP model has no posed images")
    cameras = {n: camera_from_colmap(n, rec.cameras[camera_ids[n]], poses[n]) for n in poses}
    residuals = {}
    for name, group in images.items():
        cam, res = cameras[name], []
        for image in group:
            for point in image.points2D:
                if point.has_point3D():
                    xyz = np.asarray(rec.points3D[point.point3D_id].xyz) * units_m
                    px, depth = cam.project(xyz[None])
                    if depth[0] > 0:
                        res.append(px[0] - (np.asarray(point.xy) - COLMAP_PIXEL_OFFSET))
        if res:
            residuals[name] = np.asarray(res)
    return SourceCalibration("colmap", folder, cameras, residuals)


# ---- OpenCV-style files ----------------------------------------------------------------------

def _first(fields: dict, keys: tuple[str, ...], where: str, required: bool = True):
    for key in keys:
        if key in fields and fields[key] is not None:
            return fields[key]
    if required:
        raise InputError(f"{where}: missing {' or '.join(repr(k) for k in keys)}")
    return None


def _matrix(value, shape: tuple[int, ...], where: str, what: str) -> np.ndarray:
    try:
        array = np.asarray(value, float)
        if array.size != int(np.prod(shape)):
            raise ValueError(f"{array.size} numbers")
        return array.reshape(shape)
    except (TypeError, ValueError) as err:
        raise InputError(f"{where}: '{what}' must be {' x '.join(map(str, shape))} numbers ({err})") from None


def camera_from_opencv(name: str, fields: dict, where: str, units_m: float = 1.0) -> Camera:
    """Our camera from one OpenCV-style record (see the module docstring); ``InputError`` naming ``where``."""
    import cv2

    K = _matrix(_first(fields, ("K", "camera_matrix", "cameraMatrix"), where), (3, 3), where, "K")
    dist_given = _first(fields, ("dist", "D", "distortion_coefficients", "distCoeffs"), where, required=False)
    dist_raw = np.asarray([0.0] * 5 if dist_given is None else dist_given, float).ravel()
    if len(dist_raw) < 4:
        raise InputError(f"{where}: 'dist' needs at least k1, k2, p1, p2 (got {len(dist_raw)} numbers)")
    if np.any(np.abs(dist_raw[5:]) > 0):
        raise InputError(f"{where}: distortion terms beyond k3 ({dist_raw[5:].tolist()}) are not supported; "
                         "the project's lens model is k1, k2, p1, p2, k3")
    dist = tuple(float(v) for v in np.pad(dist_raw[:5], (0, max(0, 5 - len(dist_raw[:5])))))
    rotation = _first(fields, ("R", "rotation"), where, required=False)
    if rotation is not None:
        R = _matrix(rotation, (3, 3), where, "R")
    else:
        R = cv2.Rodrigues(_matrix(_first(fields, ("rvec",), where), (3, 1), where, "rvec"))[0]
    if abs(np.linalg.det(R) - 1.0) > 1e-3 or np.abs(R @ R.T - np.eye(3)).max() > 1e-3:
        raise InputError(f"{where}: 'R' is not a rotation (det {np.linalg.det(R):.4f}); give cam_from_world's rotation")
    t = _matrix(_first(fields, ("t", "T", "tvec", "translation"), where), (3,), where, "t") * units_m
    size = _first(fields, ("image_size", "imageSize"), where, required=False)
    if size is not None:
        width, height = (int(v) for v in _matrix(size, (2,), where, "image_size"))
    else:
        width = int(_first(fields, ("image_width", "width"), where))
        height = int(_first(fields, ("image_height", "height"), where))
    if abs(K[0, 1]) > 1e-9 * max(abs(K[0, 0]), 1.0) or np.abs(K[2] - [0, 0, 1]).max() > 1e-9:
        raise InputError(f"{where}: 'K' must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew)")
    return Camera(name=name, width=width, height=height, fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]),
                  cy=float(K[1, 2]), dist=dist, pose=Rigid(R, t), frame="world")  # type: ignore[arg-type]


def _read_opencv_file(path: Path) -> dict:
    """One file's fields: JSON with ``json``, YAML with OpenCV's ``FileStorage``."""
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as err:
            raise InputError(f"{path}: not valid JSON ({err})") from err
        if not isinstance(data, dict):
            raise InputError(f"{path}: expected a JSON object of camera fields")
        return data
    import cv2

    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not storage.isOpened():
        raise InputError(f"{path}: OpenCV cannot read this YAML file")
    try:
        root = storage.root()
        return {key: _node_value(root.getNode(key)) for key in root.keys()}
    finally:
        storage.release()


def _node_value(node):
    if node.isMap():
        matrix = node.mat()  # an !!opencv-matrix is a map that OpenCV reads as a matrix
        if matrix is not None:
            return matrix
        return {key: _node_value(node.getNode(key)) for key in node.keys()}
    if node.isSeq():
        return [_node_value(node.at(i)) for i in range(node.size())]
    if node.isString():
        return node.string()
    return node.real()


def read_opencv_cameras(path: Path, units_m: float = 1.0) -> SourceCalibration:
    """Cameras from a folder of per-camera files or one JSON with ``cameras`` (see the module docstring)."""
    cameras: dict[str, Camera] = {}
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in (".yaml", ".yml", ".json"))
        if not files:
            raise InputError(f"calibrate.source {path}: no COLMAP model (cameras.txt / cameras.bin) and no "
                             "<camera>.yaml / .json files in this folder")
        for file in files:
            cameras[file.stem] = camera_from_opencv(file.stem, _read_opencv_file(file), str(file), units_m)
    else:
        data = _read_opencv_file(path)
        records = data.get("cameras")
        if not isinstance(records, dict) or not records:
            raise InputError(f"calibrate.source {path}: expected 'cameras': {{name: {{K, dist, R, t, image_size}}}}")
        for name, fields in records.items():
            if not isinstance(fields, dict):
                raise InputError(f"{path}: cameras.{name} must be an object of camera fields")
            cameras[str(name)] = camera_from_opencv(str(name), fields, f"{path}: cameras.{name}", units_m)
    return SourceCalibration("opencv", path, cameras)


def write_opencv_cameras(path: Path, cameras: list[Camera]) -> None:
    """One JSON of OpenCV-style records (``read_opencv_cameras``' format), e.g. to hand a calibration on."""
    records = {c.name: {"K": c.K.tolist(), "dist": list(c.dist), "R": c.cam_from_world.R.tolist(),
                        "t": c.cam_from_world.t.tolist(), "image_size": [c.width, c.height]} for c in cameras}
    Path(path).write_text(json.dumps({"cameras": records}, indent=1))


__all__ = ["COLMAP_MODELS", "COLMAP_PIXEL_OFFSET", "SourceCalibration", "camera_from_colmap", "camera_from_opencv",
           "camera_name_of_image", "read_calibration_source", "read_colmap_model", "read_opencv_cameras",
           "write_opencv_cameras"]
