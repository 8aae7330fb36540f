"""Pinhole camera with OpenCV distortion; a pose that names the frame it maps from.

Conventions (docs/design.md, section 6): metres, right-handed frames, OpenCV camera frame
(x right, y down, z forward). A camera's ``pose`` maps a point ``X`` of its ``frame`` to
camera coordinates ``R @ X + t``. The frames:

- ``"world"``: the studio's world (the virtual studio's truth, capture, calibrate's output,
  track, lightcal);
- ``"rig"``: calibrate's recovered rig frame (the reference camera's), before the board's
  fixture pose places it in the world;
- ``"head"``: the tracked head's frame (stabilize's per-frame cameras, train, relight,
  evaluate, the avatar's rays).

``cam.cam_from_world``, ``cam.cam_from_rig`` and ``cam.cam_from_head`` return the pose only
when the camera is in that frame and raise ``ValueError`` otherwise, so a frame mix-up is an
error rather than a wrong image. Projection and rays (``project``, ``pixel_rays``,
``image_rays``, ``center``, ``forward``) work in the camera's own frame. Camera files store
the pose under ``cam_from_<frame>`` (``Camera.to_dict``).

Distortion follows OpenCV's 5-parameter model ``(k1, k2, p1, p2, k3)``. Pixel centres are at
integer coordinates (OpenCV's convention), so the ray through pixel (i, j) passes through
image point (j, i).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterable, Literal, get_args

import numpy as np

#: The frames a camera's pose can map from (module docstring).
Frame = Literal["world", "rig", "head"]
FRAMES: tuple[str, ...] = get_args(Frame)


@dataclass(frozen=True)
class Rigid:
    """A rigid transform ``y = R @ x + t``; name instances by their frames (``head_from_world``)."""

    R: np.ndarray  # [3, 3]
    t: np.ndarray  # [3]

    @staticmethod
    def identity() -> "Rigid":
        return Rigid(np.eye(3), np.zeros(3))

    @staticmethod
    def from_matrix(m: np.ndarray) -> "Rigid":
        """From a [4, 4] or [3, 4] matrix."""
        m = np.asarray(m, dtype=np.float64)
        return Rigid(m[:3, :3].copy(), m[:3, 3].copy())

    @staticmethod
    def from_rotvec(rotvec: np.ndarray, t: np.ndarray) -> "Rigid":
        """From an axis-angle vector (radians) and a translation."""
        from scipy.spatial.transform import Rotation

        return Rigid(Rotation.from_rotvec(np.asarray(rotvec, float)).as_matrix(), np.asarray(t, float))

    def matrix(self) -> np.ndarray:
        """The [4, 4] homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3] = self.R
        m[:3, 3] = self.t
        return m

    def inverse(self) -> "Rigid":
        return Rigid(self.R.T, -self.R.T @ self.t)

    def __matmul__(self, other: "Rigid") -> "Rigid":
        """Composition: ``(a @ b)(x) = a(b(x))``, so ``cam_from_head = cam_from_world @ world_from_head``."""
        return Rigid(self.R @ other.R, self.R @ other.t + self.t)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform points [..., 3]."""
        return points @ self.R.T + self.t

    def rotvec(self) -> np.ndarray:
        from scipy.spatial.transform import Rotation

        return Rotation.from_matrix(self.R).as_rotvec()


@dataclass(frozen=True)
class Camera:
    """One calibrated camera.

    Attributes:
        name: camera id (``cam00`` ...), used in folder names and messages.
        width, height: image size in pixels.
        fx, fy, cx, cy: intrinsics in pixels.
        dist: OpenCV distortion ``(k1, k2, p1, p2, k3)``.
        pose: extrinsics ``cam_from_<frame>`` (``frame`` to camera).
        frame: the frame ``pose`` maps from: ``"world"``, ``"rig"`` or ``"head"``.
    """

    name: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    pose: Rigid = field(default_factory=Rigid.identity)
    frame: Frame = "world"

    def __post_init__(self) -> None:
        if self.frame not in FRAMES:
            raise ValueError(f"camera {self.name!r}: frame {self.frame!r} is not one of {', '.join(FRAMES)}")

    # ---- the pose, by frame ----------------------------------------------------------
    def cam_from(self, frame: Frame) -> Rigid:
        """The pose, when the camera is posed in ``frame``; ``ValueError`` naming both frames otherwise."""
        if frame != self.frame:
            raise ValueError(f"camera {self.name!r} is posed in the {self.frame} frame (cam_from_{self.frame}), "
                             f"not the {frame} frame: cam_from_{frame} asked for")
        return self.pose

    @property
    def cam_from_world(self) -> Rigid:
        """Extrinsics world to camera; only for a camera posed in the world."""
        return self.cam_from("world")

    @property
    def cam_from_rig(self) -> Rigid:
        """Extrinsics rig to camera; only for a camera posed in calibrate's rig frame."""
        return self.cam_from("rig")

    @property
    def cam_from_head(self) -> Rigid:
        """Extrinsics head to camera; only for a camera posed in the head frame."""
        return self.cam_from("head")

    # ---- derived -------------------------------------------------------------------
    @property
    def K(self) -> np.ndarray:
        """The [3, 3] intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def center(self) -> np.ndarray:
        """Camera centre in the camera's own frame (``self.frame``), metres [3]."""
        return -self.pose.R.T @ self.pose.t

    @property
    def forward(self) -> np.ndarray:
        """Optical axis (+z of the camera) in the camera's own frame [3]."""
        return self.pose.R[2].copy()

    @property
    def center_world(self) -> np.ndarray:
        """Camera centre in world coordinates, metres [3]; only for a camera posed in the world."""
        self.cam_from("world")
        return self.center

    @property
    def forward_world(self) -> np.ndarray:
        """Optical axis in world coordinates [3]; only for a camera posed in the world."""
        self.cam_from("world")
        return self.forward

    def with_pose(self, pose: Rigid, frame: Frame) -> "Camera":
        """The same lens posed by ``pose`` = ``cam_from_<frame>``."""
        return replace(self, pose=pose, frame=frame)

    def in_frame(self, frame: Frame, current_from_frame: Rigid) -> "Camera":
        """The same camera posed in ``frame``: ``cam_from_frame = pose @ current_from_frame``.

        ``current_from_frame`` maps ``frame`` into the camera's current frame, e.g.
        ``cam.in_frame("head", world_from_head)`` for a world camera.
        """
        return self.with_pose(self.pose @ current_from_frame, frame)

    def scaled(self, factor: float) -> "Camera":
        """The same camera at ``factor`` times the resolution (pixel-centre convention kept)."""
        w, h = int(round(self.width * factor)), int(round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return replace(self, width=w, height=h, fx=self.fx * sx, fy=self.fy * sy,
                       cx=(self.cx + 0.5) * sx - 0.5, cy=(self.cy + 0.5) * sy - 0.5)

    # ---- projection ------------------------------------------------------------------
    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Apply the distortion model to normalised image points [..., 2]."""
        k1, k2, p1, p2, k3 = self.dist
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def undistort(self, xy_distorted: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Invert ``distort`` by fixed-point iteration (as OpenCV's undistortPoints) [..., 2]."""
        if not any(self.dist):
            return xy_distorted.copy()
        k1, k2, p1, p2, k3 = self.dist
        xy = xy_distorted.copy()
        for _ in range(iterations):
            x, y = xy[..., 0], xy[..., 1]
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
            dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            xy = np.stack([(xy_distorted[..., 0] - dx) / radial, (xy_distorted[..., 1] - dy) / radial], -1)
        return xy

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project points [..., 3] of the camera's frame to pixels [..., 2]; also returns depth [...] (camera z, m)."""
        pc = self.pose.apply(np.asarray(points, dtype=np.float64))
        z = pc[..., 2]
        safe_z = np.where(np.abs(z) < 1e-12, 1e-12, z)
        xy = self.distort(pc[..., :2] / safe_z[..., None])
        uv = np.stack([self.fx * xy[..., 0] + self.cx, self.fy * xy[..., 1] + self.cy], -1)
        return uv, z

    def pixel_rays(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rays through pixels [..., 2] in the camera's frame: origins [..., 3] and unit directions [..., 3]."""
        uv = np.asarray(uv, dtype=np.float64)
        xy_d = np.stack([(uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy], -1)
        xy = self.undistort(xy_d)
        d_cam = np.concatenate([xy, np.ones_like(xy[..., :1])], -1)
        d_frame = d_cam @ self.pose.R  # R^T @ d, batched
        d_frame /= np.linalg.norm(d_frame, axis=-1, keepdims=True)
        origins = np.broadcast_to(self.center, d_frame.shape).copy()
        return origins, d_frame

    def image_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Rays for every pixel centre in the camera's frame: origins and directions [H, W, 3]."""
        jj, ii = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        return self.pixel_rays(np.stack([jj, ii], -1))

    # ---- I/O ---------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """JSON-ready dict; the pose is stored under ``cam_from_<frame>``."""
        return {
            "name": self.name, "width": self.width, "height": self.height,
            "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
            "dist": list(self.dist),
            f"cam_from_{self.frame}": {"R": self.pose.R.tolist(), "t": self.pose.t.tolist()},
        }

    @staticmethod
    def from_dict(d: dict, frame: Frame | None = None) -> "Camera":
        """Read a ``to_dict`` dict; its one pose key (``cam_from_world|rig|head``) gives the frame.

        ``frame``: the frame the producer of the dict means. A pose named for another frame is
        then an error, except ``cam_from_world``, which files written before poses named their
        frame used for every frame: it is read as ``frame``. Raises ``ValueError`` (or
        ``KeyError``/``TypeError`` for a malformed dict); file readers add the file's name.
        """
        keys = [f for f in FRAMES if f"cam_from_{f}" in d]
        name = d.get("name") if isinstance(d, dict) else None
        if len(keys) != 1:
            raise ValueError(f"camera {name!r}: needs exactly one pose (cam_from_world, cam_from_rig or "
                             f"cam_from_head), found {', '.join(f'cam_from_{k}' for k in keys) or 'none'}")
        stored = keys[0]
        if frame is not None and stored != frame and stored != "world":
            raise ValueError(f"camera {name!r}: pose is cam_from_{stored}, expected cam_from_{frame}")
        pose = d[f"cam_from_{stored}"]
        return Camera(
            name=str(d["name"]), width=int(d["width"]), height=int(d["height"]),
            fx=float(d["fx"]), fy=float(d["fy"]), cx=float(d["cx"]), cy=float(d["cy"]),
            dist=tuple(float(v) for v in d.get("dist", (0, 0, 0, 0, 0))),  # type: ignore[arg-type]
            pose=Rigid(np.asarray(pose["R"], float), np.asarray(pose["t"], float)),
            frame=frame if frame is not None else stored,  # type: ignore[arg-type]
        )


def save_cameras(path: Path, cameras: Iterable[Camera]) -> None:
    """Write cameras to a JSON file (``{"cameras": [...]}``), our own camera file format."""
    path.write_text(json.dumps({"cameras": [c.to_dict() for c in cameras]}, indent=1))


def load_cameras(path: Path, frame: Frame | None = None) -> list[Camera]:
    """Read a camera file written by ``save_cameras``; errors name the file.

    ``frame``: the frame the file's producer means (``Camera.from_dict``); None takes each
    camera's stored pose key as it is.
    """
    try:
        data = json.loads(Path(path).read_text())
        return [Camera.from_dict(d, frame) for d in data["cameras"]]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{path}: not a valid camera file ({err}); re-run the stage that wrote it") from err


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 1.0, 0.0])) -> Rigid:
    """``cam_from_<frame>`` for a camera at ``eye`` looking at ``target`` (points of one frame).

    ``up`` is the frame's up direction (+y in the world and in head space); the OpenCV camera's y axis
    points down, so image right is ``forward x up`` and image down is ``forward x right``.
    """
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return Rigid(R, -R @ eye)
