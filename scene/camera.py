"""Pinhole camera with OpenCV distortion; world-to-camera extrinsics.

Conventions (docs/design.md, section 6): metres, right-handed world, OpenCV camera frame
(x right, y down, z forward). ``cam_from_world`` maps a world point ``X`` to camera
coordinates ``R @ X + t``. Distortion follows OpenCV's 5-parameter model
``(k1, k2, p1, p2, k3)``. Pixel centres are at integer coordinates (OpenCV's convention),
so the ray through pixel (i, j) passes through image point (j, i).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterable

import numpy as np


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
        cam_from_world: extrinsics (world to camera).
    """

    name: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    cam_from_world: Rigid = field(default_factory=Rigid.identity)

    # ---- derived -------------------------------------------------------------------
    @property
    def K(self) -> np.ndarray:
        """The [3, 3] intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def center_world(self) -> np.ndarray:
        """Camera centre in world coordinates, metres [3]."""
        return -self.cam_from_world.R.T @ self.cam_from_world.t

    @property
    def forward_world(self) -> np.ndarray:
        """Optical axis (+z of the camera) in world coordinates [3]."""
        return self.cam_from_world.R[2].copy()

    def with_pose(self, cam_from_world: Rigid) -> "Camera":
        return replace(self, cam_from_world=cam_from_world)

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

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points [..., 3] to pixels [..., 2]; also returns depth [...] (camera z, m)."""
        pc = self.cam_from_world.apply(np.asarray(points_world, dtype=np.float64))
        z = pc[..., 2]
        safe_z = np.where(np.abs(z) < 1e-12, 1e-12, z)
        xy = self.distort(pc[..., :2] / safe_z[..., None])
        uv = np.stack([self.fx * xy[..., 0] + self.cx, self.fy * xy[..., 1] + self.cy], -1)
        return uv, z

    def pixel_rays(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World-space rays through pixels [..., 2]: origins [..., 3] and unit directions [..., 3]."""
        uv = np.asarray(uv, dtype=np.float64)
        xy_d = np.stack([(uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy], -1)
        xy = self.undistort(xy_d)
        d_cam = np.concatenate([xy, np.ones_like(xy[..., :1])], -1)
        d_world = d_cam @ self.cam_from_world.R  # R^T @ d, batched
        d_world /= np.linalg.norm(d_world, axis=-1, keepdims=True)
        origins = np.broadcast_to(self.center_world, d_world.shape).copy()
        return origins, d_world

    def image_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Rays for every pixel centre: origins and directions [H, W, 3]."""
        jj, ii = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        return self.pixel_rays(np.stack([jj, ii], -1))

    # ---- I/O ---------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "name": self.name, "width": self.width, "height": self.height,
            "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
            "dist": list(self.dist),
            "cam_from_world": {"R": self.cam_from_world.R.tolist(), "t": self.cam_from_world.t.tolist()},
        }

    @staticmethod
    def from_dict(d: dict) -> "Camera":
        return Camera(
            name=str(d["name"]), width=int(d["width"]), height=int(d["height"]),
            fx=float(d["fx"]), fy=float(d["fy"]), cx=float(d["cx"]), cy=float(d["cy"]),
            dist=tuple(float(v) for v in d.get("dist", (0, 0, 0, 0, 0))),  # type: ignore[arg-type]
            cam_from_world=Rigid(np.asarray(d["cam_from_world"]["R"], float),
                                 np.asarray(d["cam_from_world"]["t"], float)),
        )


def save_cameras(path: Path, cameras: Iterable[Camera]) -> None:
    """Write cameras to a JSON file (``{"cameras": [...]}``), our own camera file format."""
    path.write_text(json.dumps({"cameras": [c.to_dict() for c in cameras]}, indent=1))


def load_cameras(path: Path) -> list[Camera]:
    """Read a camera file written by ``save_cameras``; errors name the file."""
    try:
        data = json.loads(Path(path).read_text())
        return [Camera.from_dict(d) for d in data["cameras"]]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{path}: not a valid camera file ({err}); re-run the stage that wrote it") from err


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 1.0, 0.0])) -> Rigid:
    """``cam_from_world`` for a camera at ``eye`` looking at ``target``.

    ``up`` is the world's up direction (+y in our world); the OpenCV camera's y axis
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
