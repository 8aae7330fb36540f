"""The virtual studio's calibration takes: a ChArUco board and mirror spheres.

Both are ray-cast through ``scene.camera.Camera.pixel_rays``, so lens distortion in the
images is exactly the camera model's. Output layout (within the capture's output, docs/design.md)::

    calib/board.json                     board spec + the reference (fixture) pose of frame 0
    calib/charuco/<cam>/<k:04d>.exr      board pose k as seen by <cam> (absent: board not in view)
    calib/mirror.json                    sphere spec {"radius_m", "count", ...}
    calib/mirror/<cam>/room.exr          spheres under the room light, bars off (silhouettes)
    calib/mirror/<cam>/bar<b:02d>.exr    spheres lit by bar b alone
    calib/mirror_roi.json                native-resolution windows of the mirror take (when the
    calib/mirror_roi/<cam>/<name>_<k>.exr  take is coarser than the sensor): boxes + images

The mirror take is shot coarse-to-fine, as a studio with region-of-interest readout would:
full images at the take's resolution, then, found in them, small windows around the balls
and each bar's highlights read out at the sensor's native resolution (``render_mirror_rois``).

Ground truth (the board poses, the sphere centres) goes to ``truth_dir`` as
``calib_board_poses.json`` and ``mirror_spheres.json``.

The work is planned as independent items, one per camera and take (``plan_calibration_takes``:
``BoardTakeItem``, ``MirrorTakeItem``), each rendered by ``render_take_item`` into the bytes of
its files and written by ``TakeWriter``; the capture stage fans the items out and caches them
one by one, ``render_calibration_takes`` runs them here. Either way the files are the same bytes.

Board frame (OpenCV's ChArUco convention): origin at the chessboard's top-left corner,
x along the squares to the right, y down the printed page, z into the board; a camera
looking at the printed side sees the board's +z pointing away from it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.ndimage import gaussian_filter
from scipy.spatial.transform import Rotation

from hardware.studio.camera_effects import CameraEffects
from hardware.studio.printed_board import PrintedBoard, print_board
from scene.camera import Camera, Rigid
from scene.image_io import write_exr


class CharucoBoardConfig(BaseModel):
    """The printed ChArUco board (OpenCV ``cv2.aruco.CharucoBoard``)."""

    model_config = ConfigDict(frozen=True, extra="forbid")
    squares_x: int = Field(8, ge=3, description="Chessboard squares along the board's x axis.")
    squares_y: int = Field(6, ge=3, description="Chessboard squares along the board's y axis.")
    square_m: float = Field(0.04, gt=0, description="Side of one chessboard square in metres.")
    marker_m: float = Field(0.029, gt=0, description="Side of one ArUco marker in metres (< square_m).")
    dictionary: str = Field("DICT_4X4_50", description="OpenCV ArUco dictionary name (cv2.aruco.<name>).")

    def spec(self) -> dict:
        """The ``calib/board.json`` fields."""
        return {"squares_x": self.squares_x, "squares_y": self.squares_y, "square_m": self.square_m,
                "marker_m": self.marker_m, "dictionary": self.dictionary}


class MirrorSpheresConfig(BaseModel):
    """Chrome balls placed around the head position for the light calibration take."""

    model_config = ConfigDict(frozen=True, extra="forbid")
    radius_m: float = Field(0.035, gt=0, description="Radius of every chrome ball in metres.")
    offsets_m: tuple[tuple[float, float, float], ...] = Field(
        ((-0.11, -0.06, 0.05), (0.11, -0.06, 0.05), (0.0, 0.14, -0.02), (0.0, 0.0, 0.13)),
        description="Ball centres relative to the capture volume centre, metres (world axes).")
    reflectance: float = Field(0.6, gt=0, le=1, description="Mirror reflectance of the chrome.")


class CalibrationTakeParams(BaseModel):
    """How the calibration takes are shot."""

    model_config = ConfigDict(frozen=True, extra="forbid")
    poses: int = Field(24, ge=2, description="Board poses in the ChArUco take (pose 0 is the fixture pose).")
    noise: float = Field(0.003, ge=0, description="Sensor noise, standard deviation in linear units.")
    blur_px: float = Field(0.5, ge=0, description="Optical blur, Gaussian sigma in pixels.")
    seed: int = Field(0, description="Random seed for board poses and noise.")
    supersample: int = Field(
        2, ge=1, le=8, description="Rays per pixel per axis for board images (2 suffices at native resolution: "
        "the calibration's saddle-point corner fit leaves ~0.01 px there).")
    mirror_supersample: int = Field(4, ge=1, le=12, description="Rays per pixel per axis on the spheres.")
    highlight_supersample: int = Field(
        24, ge=1, le=64, description="Rays per pixel per axis where a bar's highlight falls (a sub-pixel streak).")
    volume_center_m: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="Centre of the capture volume (the head position), world metres.")
    volume_half_extent_m: tuple[float, float, float] = Field(
        (0.1, 0.12, 0.15), description="Half size of the box the board centre moves in, metres.")
    max_tilt_deg: float = Field(35.0, ge=0, le=70, description="Largest board tilt away from its facing direction.")
    board_albedo_white: float = Field(0.75, gt=0, le=1, description="Linear albedo of the white print.")
    board_albedo_black: float = Field(0.03, ge=0, lt=1, description="Linear albedo of the black print.")
    exposure: float = Field(1.0, gt=0, description="Full-on irradiance scale for the board take.")
    bar_radiance: float = Field(4.0, gt=0, description="Radiance of a lit bar (times its intensity).")
    bar_width_m: float = Field(0.03, gt=0, description="Width of a bar's diffuser, metres.")
    room_radiance: float = Field(0.15, ge=0, description="Room light seen in the spheres in the silhouette take.")
    background: float = Field(0.01, ge=0, description="Radiance of the black backdrop.")
    white_level: float = Field(1.0, gt=0, description="Sensor saturation level (linear); images are clipped to it.")
    mirror_roi: bool = Field(
        True, description="Coarse-to-fine mirror take: find the balls and highlights in the full (performance-"
        "resolution) mirror images, then read out small windows around them at the sensor's native resolution "
        "(calib/mirror_roi/, as a region-of-interest readout); only when the native resolution is finer.")
    roi_threshold_sigma: float = Field(
        6.0, gt=0, description="A pixel of the coarse mirror image belongs to a highlight or ball window when it "
        "rises this many noise sigmas above the background.")
    roi_pad_px: int = Field(6, ge=2, description="Margin around a detected highlight or ball, native pixels.")
    roi_coarse_supersample: int = Field(
        2, ge=1, le=8, description="Rays per native pixel per axis in a window's first pass (finds the lit pixels).")
    roi_highlight_supersample: int = Field(
        8, ge=1, le=64, description="Rays per native pixel per axis on a window's lit pixels (the streak is about "
        "half a native pixel wide).")
    effects: CameraEffects | None = Field(
        None, description="The real camera and print (capture.realism: real): the board is printed off nominal "
        "and bowed, and its images go through the lens and sensor model instead of blur_px, noise and "
        "white_level; None = the ideal board take. The mirror take is not affected.")
    board_scale: float = Field(
        1.0, gt=0, description="Resolution of the board take over the sensors' native one (the real lens's "
        "residual blur is stated in native pixels); only read with effects.")


@dataclass(frozen=True)
class BarLight:
    """One LED bar as the calibration take needs it (world metres)."""

    id: int
    center_world: np.ndarray  # [3]
    axis_world: np.ndarray  # [3] unit
    length_m: float
    intensity: float = 1.0
    normal_world: np.ndarray | None = None  # [3] emission direction; None: lit on both sides


# ---- board -----------------------------------------------------------------------------

def make_board(cfg: CharucoBoardConfig):
    """The OpenCV board object for a board spec."""
    import cv2

    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, cfg.dictionary))
    return cv2.aruco.CharucoBoard((cfg.squares_x, cfg.squares_y), cfg.square_m, cfg.marker_m, dictionary)


def board_texture(cfg: CharucoBoardConfig, px_per_square: int = 48) -> tuple[np.ndarray, int]:
    """The printed board as a float albedo mask in [0, 1] [Ht, Wt] (1 = white) and its margin in pixels.

    The margin is white paper around the chessboard (half a square), as on a real print.
    """
    margin = px_per_square // 2
    size = (cfg.squares_x * px_per_square + 2 * margin, cfg.squares_y * px_per_square + 2 * margin)
    img = make_board(cfg).generateImage(size, marginSize=margin, borderBits=1)
    return img.astype(np.float32) / 255.0, margin


def reference_world_from_board(cfg: CharucoBoardConfig, center_world: np.ndarray) -> Rigid:
    """The fixture pose: board upright, printed side facing +z (towards the cameras), centred at ``center_world``.

    Board x = world +x, board y = world -y (down the page), board z = world -z.
    """
    R = np.diag([1.0, -1.0, -1.0])
    half = np.array([cfg.squares_x * cfg.square_m / 2, cfg.squares_y * cfg.square_m / 2, 0.0])
    return Rigid(R, np.asarray(center_world, float) - R @ half)


def sample_board_poses(cfg: CharucoBoardConfig, cameras: Sequence[Camera], params: CalibrationTakeParams,
                       rng: np.random.Generator) -> list[Rigid]:
    """Board poses ``world_from_board``: pose 0 at the fixture, each other one facing a random camera.

    The facing direction points at a randomly chosen camera (seen from the volume centre,
    jittered by about 20 degrees, so its neighbours see the board too), is tilted by up to
    ``max_tilt_deg`` and spun in plane: every camera sees the board often and at varied
    angles (what makes focal length observable) and neighbours share frames (which chains
    the extrinsics).
    """
    centre = np.asarray(params.volume_center_m, float)
    half_ext = np.asarray(params.volume_half_extent_m, float)
    to_cams = np.stack([c.center_world - centre for c in cameras])
    az = np.arctan2(to_cams[:, 0], to_cams[:, 2])
    el = np.arctan2(to_cams[:, 1], np.linalg.norm(to_cams[:, [0, 2]], axis=1))
    poses = [reference_world_from_board(cfg, centre)]
    half = np.array([cfg.squares_x * cfg.square_m / 2, cfg.squares_y * cfg.square_m / 2, 0.0])
    while len(poses) < params.poses:
        i = rng.integers(len(cameras))  # face one camera, jittered: covers every camera evenly
        yaw = az[i] + rng.uniform(-0.35, 0.35)
        pitch = el[i] + rng.uniform(-0.3, 0.3)
        facing = np.array([np.sin(yaw) * np.cos(pitch), np.sin(pitch), np.cos(yaw) * np.cos(pitch)])
        tilt_axis = np.cross(facing, rng.normal(size=3))
        tilt_axis /= np.linalg.norm(tilt_axis)
        tilt = np.deg2rad(rng.uniform(0.3, 1.0) * params.max_tilt_deg)
        facing = Rotation.from_rotvec(tilt_axis * tilt).apply(facing)
        # board z points away from the viewer: -facing; board y down the page ~ world -y
        z = -facing
        x = np.cross(np.array([0.0, -1.0, 0.0]), z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z], axis=1)
        spin = Rotation.from_rotvec(z * np.deg2rad(rng.uniform(-25, 25))).as_matrix()
        R = spin @ R
        c = centre + rng.uniform(-1, 1, size=3) * half_ext
        poses.append(Rigid(R, c - R @ half))
    return poses


def _supersampled_rays(cam: Camera, ss: int, box: tuple[int, int, int, int] | None = None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Rays at ``ss x ss`` sub-pixel positions of every pixel in ``box`` (x0, y0, x1, y1, exclusive ends).

    Returns origins [3] and directions [h, w, ss*ss, 3] (float64).
    """
    x0, y0, x1, y1 = box if box is not None else (0, 0, cam.width, cam.height)
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    jj, ii = np.meshgrid(np.arange(x0, x1, dtype=np.float64), np.arange(y0, y1, dtype=np.float64))
    oy, ox = np.meshgrid(offs, offs, indexing="ij")
    uv = np.stack([jj[..., None] + ox.ravel(), ii[..., None] + oy.ravel()], axis=-1)  # [h, w, S, 2]
    _, dirs = cam.pixel_rays(uv)
    return cam.center_world, dirs


def _bilinear(tex: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Sample ``tex`` [Ht, Wt] at continuous pixel-centre coordinates (u along x); clamps at the border."""
    h, w = tex.shape
    u = np.clip(u, 0, w - 1.001)
    v = np.clip(v, 0, h - 1.001)
    u0 = np.floor(u).astype(np.int64)
    v0 = np.floor(v).astype(np.int64)
    fu, fv = u - u0, v - v0
    return ((tex[v0, u0] * (1 - fu) + tex[v0, u0 + 1] * fu) * (1 - fv)
            + (tex[v0 + 1, u0] * (1 - fu) + tex[v0 + 1, u0 + 1] * fu) * fv)


def _sensor(img: np.ndarray, params: CalibrationTakeParams, rng: np.random.Generator) -> np.ndarray:
    """Optics and sensor: blur, noise, clip at the white level; grey -> RGB [H, W, 3]."""
    if params.blur_px > 0:
        img = gaussian_filter(img, params.blur_px, mode="nearest")
    img = img + rng.normal(0.0, params.noise, size=img.shape) if params.noise > 0 else img
    img = np.clip(img, 0.0, params.white_level)
    return np.repeat(img[..., None], 3, axis=-1).astype(np.float32)


def render_board_image(cam: Camera, world_from_board: Rigid, cfg: CharucoBoardConfig, tex: np.ndarray,
                       margin_px: int, params: CalibrationTakeParams, rng: np.random.Generator,
                       rays: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """One board image [H, W, 3] (linear), anti-aliased by supersampling, then blurred and noised."""
    return _sensor(board_radiance(cam, world_from_board, cfg, tex, margin_px, params, rays), params, rng)


def board_radiance(cam: Camera, world_from_board: Rigid, cfg: CharucoBoardConfig, tex: np.ndarray,
                   margin_px: int, params: CalibrationTakeParams, rays: tuple[np.ndarray, np.ndarray] | None = None,
                   printed: PrintedBoard | None = None) -> np.ndarray:
    """The clean radiance [H, W] of one board image, anti-aliased by supersampling (no blur, no noise).

    ``printed``: the physical print (scale error, corner jitter, bow) to render instead of the
    nominal flat board; ``world_from_board`` stays the nominal board's pose.
    """
    origin, all_dirs = rays if rays is not None else _supersampled_rays(cam, params.supersample)
    R, t = world_from_board.R, world_from_board.t
    # only the pixels the board (with its white margin) can cover need ray casting
    pad = 0.5 * cfg.square_m
    outline = np.array([[-pad, -pad, 0], [cfg.squares_x * cfg.square_m + pad, -pad, 0],
                        [cfg.squares_x * cfg.square_m + pad, cfg.squares_y * cfg.square_m + pad, 0],
                        [-pad, cfg.squares_y * cfg.square_m + pad, 0]])
    uv, z = cam.project(world_from_board.apply(outline))
    x0, y0, x1, y1 = 0, 0, cam.width, cam.height
    if np.all(z > 0):
        x0, y0 = np.maximum(np.floor(uv.min(axis=0)).astype(int) - 4, 0)
        x1, y1 = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + 5, [cam.width, cam.height])
    clean = np.full((cam.height, cam.width), params.background, np.float64)
    if x1 > x0 and y1 > y0:
        dirs = all_dirs[y0:y1, x0:x1]
        normal = R[:, 2]  # board +z, into the board
        denom = dirs @ normal  # [h, w, S]; > 0: the ray meets the printed side
        safe_denom = np.where(np.abs(denom) < 1e-12, 1e-12, denom)
        dist = ((t - origin) @ normal) / safe_denom
        hit = origin + dist[..., None] * dirs
        p_board = (hit - t) @ R  # [h, w, S, 3]
        artwork_xy = p_board[..., :2]
        if printed is not None:
            # The bowed surface z = h(x, y): intersect the plane z = h at the last hit (h is < 1 mm and
            # smooth, so two steps converge to ~1e-8 m), then look the artwork up where it was printed.
            for _ in range(2):
                lift = printed.surface_z(p_board[..., :2])
                dist = ((t - origin) @ normal + lift) / safe_denom
                hit = origin + dist[..., None] * dirs
                p_board = (hit - t) @ R
            artwork_xy = printed.nominal_xy(p_board[..., :2])
        px_per_square = (tex.shape[1] - 2 * margin_px) / cfg.squares_x
        u = margin_px + artwork_xy[..., 0] / cfg.square_m * px_per_square - 0.5
        v = margin_px + artwork_xy[..., 1] / cfg.square_m * px_per_square - 0.5
        inside = (dist > 0) & (u >= -0.5) & (v >= -0.5) & (u <= tex.shape[1] - 0.5) & (v <= tex.shape[0] - 0.5)
        albedo = (params.board_albedo_black
                  + (params.board_albedo_white - params.board_albedo_black) * _bilinear(tex, u, v))
        shading = params.exposure * (0.75 + 0.25 * np.abs(denom))  # soft full-on light, a little Lambert
        radiance = np.where(inside & (denom > 0), albedo * shading, np.where(inside, 0.05, params.background))
        clean[y0:y1, x0:x1] = radiance.mean(axis=-1)
    return clean


def board_visible(cam: Camera, world_from_board: Rigid, cfg: CharucoBoardConfig, min_corners: int = 6) -> bool:
    """Whether the printed side faces ``cam`` and at least ``min_corners`` inner corners fall in its image."""
    board = make_board(cfg)
    corners_world = world_from_board.apply(np.asarray(board.getChessboardCorners(), float))
    to_cam = cam.center_world - corners_world.mean(axis=0)
    if to_cam @ world_from_board.R[:, 2] >= 0:  # looking at the back of the board
        return False
    uv, z = cam.project(corners_world)
    ok = (z > 0) & (uv[:, 0] >= 2) & (uv[:, 1] >= 2) & (uv[:, 0] < cam.width - 3) & (uv[:, 1] < cam.height - 3)
    return int(ok.sum()) >= min_corners


# ---- mirror spheres -----------------------------------------------------------------------

def _ray_segment_distance(origins: np.ndarray, dirs: np.ndarray, a: np.ndarray, b: np.ndarray
                          ) -> np.ndarray:
    """Closest distance between rays ``origins + t dirs`` (t >= 0, dirs unit) [N, 3] and segment a-b; [N]."""
    seg = b - a
    seg_len2 = float(seg @ seg)
    w0 = origins - a  # [N, 3]
    bb = dirs @ seg  # [N]
    dd = (dirs * w0).sum(-1)
    ee = w0 @ seg
    denom = np.maximum(seg_len2 - bb * bb, 1e-12)
    s = np.clip((ee - bb * dd) / denom, 0.0, 1.0)
    t = np.maximum(s * bb - dd, 0.0)  # the ray point closest to a + s*seg
    s = np.clip(((origins + t[:, None] * dirs - a) @ seg) / seg_len2, 0.0, 1.0)  # re-clamp the segment side
    t = np.maximum(s * bb - dd, 0.0)
    return np.linalg.norm(origins + t[:, None] * dirs - (a + s[:, None] * seg), axis=-1)


def sphere_pixel_box(cam: Camera, center_world: np.ndarray, radius_m: float, pad_px: int = 3
                     ) -> tuple[int, int, int, int] | None:
    """Pixel box (x0, y0, x1, y1) that holds the sphere's image, or None if it is not in view."""
    golden = np.pi * (3.0 - np.sqrt(5.0))
    k = np.arange(400)
    zs = 1 - 2 * (k + 0.5) / 400
    rs = np.sqrt(1 - zs * zs)
    pts = np.stack([rs * np.cos(golden * k), zs, rs * np.sin(golden * k)], -1) * radius_m + center_world
    uv, z = cam.project(pts)
    if np.any(z <= radius_m * 0.1):
        return None
    x0, y0 = np.floor(uv.min(axis=0)).astype(int) - pad_px
    x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + pad_px + 1
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, cam.width), min(y1, cam.height)
    if x1 <= x0 or y1 <= y0:
        return None
    return int(x0), int(y0), int(x1), int(y1)


def _bar_profile(dist_m: np.ndarray, width_m: float) -> np.ndarray:
    """Diffuser profile across a bar: 1 on its axis, falling smoothly to 0 at half its width."""
    return np.clip(1.0 - (dist_m / (0.5 * width_m)) ** 2, 0.0, None)


def _sphere_hits(origin: np.ndarray, d: np.ndarray, centres: np.ndarray, r: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest ball hit of rays ``d`` [N, 3] (another ball may be in front of this one).

    Returns the hit mask [N], hit points [M, 3] and reflected directions [M, 3].
    """
    best_t = np.full(d.shape[0], np.inf)
    best_c = np.zeros((d.shape[0], 3))
    for other in centres:
        oc = origin - other
        b = d @ oc
        disc = b * b - (oc @ oc - r * r)
        t = np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        t = np.where(t > 0, t, np.inf)
        closer = t < best_t
        best_t = np.where(closer, t, best_t)
        best_c[closer] = other
    hit = np.isfinite(best_t)
    p = origin + best_t[hit, None] * d[hit]
    n = (p - best_c[hit]) / r
    refl = d[hit] - 2 * (d[hit] * n).sum(-1, keepdims=True) * n
    return hit, p, refl


def _bar_radiance(bar: BarLight, p: np.ndarray, refl: np.ndarray, params: CalibrationTakeParams) -> np.ndarray:
    """Radiance of ``bar`` seen along reflected rays ``p + t refl`` [M, 3] -> [M]."""
    half = 0.5 * bar.length_m * np.asarray(bar.axis_world, float)
    c = np.asarray(bar.center_world, float)
    dist = _ray_segment_distance(p, refl, c - half, c + half)
    light = params.bar_radiance * bar.intensity * _bar_profile(dist, params.bar_width_m)
    normal = getattr(bar, "normal_world", None)
    if normal is not None:  # a bar's diffuser is dark from behind
        light = light * (refl @ np.asarray(normal, float) < 0)
    return light


def _pixel_rays_at(cam: Camera, pixels: np.ndarray, ss: int) -> np.ndarray:
    """Directions of ``ss x ss`` sub-pixel rays for pixels [M, 2] (x, y) -> [M, ss*ss, 3]."""
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    oy, ox = np.meshgrid(offs, offs, indexing="ij")
    uv = pixels[:, None, :].astype(np.float64) + np.stack([ox.ravel(), oy.ravel()], -1)[None]
    return cam.pixel_rays(uv)[1]


def render_mirror_images(cam: Camera, sphere_centers_world: np.ndarray, spheres: MirrorSpheresConfig,
                         bars: Sequence[BarLight], params: CalibrationTakeParams, rng: np.random.Generator
                         ) -> dict[str, np.ndarray]:
    """The mirror-sphere take for one camera: ``{"room": img, "bar00": img, ...}``, each [H, W, 3] linear.

    A sphere reflects the bar (a diffuser of ``bar_width_m`` around its segment); ``room``
    is the balls under uniform room light with the bars off, so their silhouettes show.
    Inter-reflections are ignored. A bar's highlight is a thin streak (a fraction of a
    pixel wide), so its pixels are rendered again with ``highlight_supersample`` rays per
    axis: with too few sub-pixel rays its position snaps to the sub-pixel grid.
    """
    ss = params.mirror_supersample
    r = spheres.radius_m
    names = ["room"] + [f"bar{b.id:02d}" for b in bars]
    clean = {n: np.full((cam.height, cam.width), params.background, np.float64) for n in names}
    for centre in sphere_centers_world:
        box = sphere_pixel_box(cam, centre, r)
        if box is None:
            continue
        x0, y0, x1, y1 = box
        origin, dirs = _supersampled_rays(cam, ss, box)
        shape = dirs.shape[:-1]  # [h, w, S]
        hit, p, refl = _sphere_hits(origin, dirs.reshape(-1, 3), sphere_centers_world, r)
        room = np.full(hit.shape, params.background)
        room[hit] = spheres.reflectance * params.room_radiance
        clean["room"][y0:y1, x0:x1] = room.reshape(shape).mean(axis=-1)
        for bar in bars:
            clean[f"bar{bar.id:02d}"][y0:y1, x0:x1] = _bar_highlight(
                cam, origin, (hit, p, refl), shape, (x0, y0), bar, spheres, sphere_centers_world, params,
                params.highlight_supersample)
    return {n: _sensor(img, params, rng) for n, img in clean.items()}


# ---- native-resolution windows (region-of-interest readout) -------------------------------

def detect_windows(grey: np.ndarray, threshold_sigma: float, min_pixels: int = 1) -> list[tuple[int, int, int, int]]:
    """Boxes (x0, y0, x1, y1, exclusive ends) of the bright blobs in a mostly dark image [H, W].

    What the studio does on its coarse image before the region-of-interest readout: pixels
    ``threshold_sigma`` noise sigmas (median / MAD) above the background, grown by a pixel
    (the blurred tails), grouped into connected blobs.
    """
    import cv2

    bg = float(np.median(grey))
    sigma = max(float(1.4826 * np.median(np.abs(grey - bg))), 1e-6)
    mask = (grey > bg + threshold_sigma * sigma).astype(np.uint8)
    mask = cv2.dilate(mask, np.ones((3, 3), np.uint8))
    n, _, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    return [(int(x), int(y), int(x + w), int(y + h)) for x, y, w, h, area in stats[1:] if area >= min_pixels]


def native_box(box: tuple[int, int, int, int], scale: float, pad_px: int, width: int, height: int
               ) -> tuple[int, int, int, int] | None:
    """A coarse-image pixel box in the native image (``scale`` = native / coarse), padded and clipped.

    Coarse pixel i covers [i - 0.5, i + 0.5] in pixel-centre coordinates and native u = (u_c + 0.5) s - 0.5,
    so coarse pixels [x0, x1) span native [x0 s - 0.5, x1 s - 0.5]: native pixels floor(x0 s) to
    floor(x1 s) (pixel j spans [j - 0.5, j + 0.5]).
    """
    x0, y0, x1, y1 = box
    nx0 = int(np.floor(x0 * scale)) - pad_px
    ny0 = int(np.floor(y0 * scale)) - pad_px
    nx1 = int(np.floor(x1 * scale)) + 1 + pad_px
    ny1 = int(np.floor(y1 * scale)) + 1 + pad_px
    nx0, ny0, nx1, ny1 = max(nx0, 0), max(ny0, 0), min(nx1, width), min(ny1, height)
    if nx1 <= nx0 or ny1 <= ny0:
        return None
    return nx0, ny0, nx1, ny1


def render_mirror_window(cam: Camera, box: tuple[int, int, int, int], sphere_centers_world: np.ndarray,
                         spheres: MirrorSpheresConfig, bar: BarLight | None, params: CalibrationTakeParams
                         ) -> np.ndarray:
    """Clean radiance [h, w] of the pixels in ``box`` of the mirror take: the balls lit by ``bar`` (None: room light).

    Rendered like ``render_mirror_images`` but only for the window's pixel rays: a first pass
    with ``roi_coarse_supersample`` rays per pixel, then the lit pixels (and their neighbours)
    again with ``roi_highlight_supersample``; the room light's balls with one ray per pixel,
    then ``mirror_supersample`` on the pixels along their outlines.
    """
    import cv2

    x0, y0, x1, y1 = box
    r = spheres.radius_m
    if bar is None:
        # uniform inside a ball: one ray per pixel, then ``mirror_supersample`` on the outline's pixels
        origin, dirs = _supersampled_rays(cam, 1, box)
        hit = _sphere_hits(origin, dirs.reshape(-1, 3), sphere_centers_world, r)[0].reshape(dirs.shape[:2])
        img = np.where(hit, spheres.reflectance * params.room_radiance, params.background)
        kernel = np.ones((3, 3), np.uint8)
        u8 = hit.astype(np.uint8)
        edge = cv2.dilate(u8, kernel) != cv2.erode(u8, kernel)
        ys, xs = np.nonzero(edge)
        if len(ys):
            fine = _pixel_rays_at(cam, np.stack([xs + x0, ys + y0], -1), params.mirror_supersample)
            fhit = _sphere_hits(origin, fine.reshape(-1, 3), sphere_centers_world, r)[0].reshape(len(ys), -1)
            img[ys, xs] = np.where(fhit, spheres.reflectance * params.room_radiance, params.background).mean(-1)
        return img
    origin, dirs = _supersampled_rays(cam, params.roi_coarse_supersample, box)
    shape = dirs.shape[:-1]  # [h, w, S]
    hits = _sphere_hits(origin, dirs.reshape(-1, 3), sphere_centers_world, r)
    return _bar_highlight(cam, origin, hits, shape, (x0, y0), bar, spheres, sphere_centers_world, params,
                          params.roi_highlight_supersample)


def _bar_highlight(cam: Camera, origin: np.ndarray, hits: tuple, shape: tuple, corner: tuple[int, int], bar,
                   spheres, sphere_centers_world: np.ndarray, params, fine_supersample: int) -> np.ndarray:
    """One bar's reflection in a window [h, w]: the supersampled render ``hits`` (hit, point,
    reflected direction of every ray, rays shaped ``shape`` = [h, w, S]), re-rendered with
    ``fine_supersample`` rays per pixel where the bar's highlight (grown by a pixel) lies.
    ``corner``: the window's top-left pixel (x0, y0) in the camera's image."""
    import cv2

    hit, p, refl = hits
    x0, y0 = corner
    radiance = np.full(hit.shape, params.background)
    radiance[hit] = spheres.reflectance * _bar_radiance(bar, p, refl, params)
    radiance = radiance.reshape(shape)
    img = radiance.mean(axis=-1)
    lit = (radiance > params.background).any(axis=-1).astype(np.uint8)
    lit = cv2.dilate(lit, np.ones((3, 3), np.uint8)).astype(bool)
    if lit.any():
        ys, xs = np.nonzero(lit)
        fine = _pixel_rays_at(cam, np.stack([xs + x0, ys + y0], -1), fine_supersample)
        fhit, fp, frefl = _sphere_hits(origin, fine.reshape(-1, 3), sphere_centers_world, spheres.radius_m)
        fr = np.full(fhit.shape, params.background)
        fr[fhit] = spheres.reflectance * _bar_radiance(bar, fp, frefl, params)
        img[ys, xs] = fr.reshape(len(ys), -1).mean(axis=-1)
    return img


def render_mirror_rois(native_cam: Camera, coarse_images: dict[str, np.ndarray], sphere_centers_world: np.ndarray,
                       spheres: MirrorSpheresConfig, bars: Sequence[BarLight], params: CalibrationTakeParams,
                       rng: np.random.Generator) -> dict[str, list[tuple[tuple[int, int, int, int], np.ndarray]]]:
    """Native-resolution windows around what the coarse mirror take shows, per image name.

    ``coarse_images`` is ``render_mirror_images``' output for the same camera at a coarser
    resolution. For ``room`` the windows hold the balls, for ``bar<b>`` the highlights; each
    is found in the coarse image (``detect_windows``) and read out at ``native_cam``'s
    resolution. Returns ``{name: [(box (x0, y0, x1, y1) native px, image [h, w, 3]), ...]}``.
    """
    by_name = {f"bar{b.id:02d}": b for b in bars}
    out: dict[str, list] = {}
    for name, coarse in coarse_images.items():
        grey = coarse[..., :3].mean(axis=-1)
        scale = native_cam.width / grey.shape[1]
        bar = by_name.get(name)
        windows = []
        for box in detect_windows(grey, params.roi_threshold_sigma, min_pixels=1 if bar is not None else 9):
            nbox = native_box(box, scale, params.roi_pad_px, native_cam.width, native_cam.height)
            if nbox is None:
                continue
            clean = render_mirror_window(native_cam, nbox, sphere_centers_world, spheres, bar, params)
            windows.append((nbox, _sensor(clean, params, rng)))
        out[name] = windows
    return out


# ---- the take, one item per camera and take -----------------------------------------------
#
# Camera ``i`` draws all its sensor noise from one generator seeded ``[seed, i]``: first its
# board images (in pose order), then its mirror images. Each camera's board take and mirror
# take are separate items (``BoardTakeItem``, ``MirrorTakeItem``) so they can run on different
# workers and be cached apart; the mirror item replays the board take's noise draws
# (``skip_board_noise``: cheap, no rendering) to start from the same generator state, which
# keeps the images bit for bit those of one sequential pass.

# Fields of ``CalibrationTakeParams`` that only one of the two takes reads (the rest count for both).
BOARD_ONLY_FIELDS = frozenset({"poses", "supersample", "volume_half_extent_m", "max_tilt_deg", "board_albedo_white",
                               "board_albedo_black", "exposure", "effects", "board_scale"})
MIRROR_ONLY_FIELDS = frozenset({"mirror_supersample", "highlight_supersample", "bar_radiance", "bar_width_m",
                                "room_radiance", "mirror_roi", "roi_threshold_sigma", "roi_pad_px",
                                "roi_coarse_supersample", "roi_highlight_supersample"})


def _rigid_dict(x: Rigid) -> dict:
    return {"R": x.R.tolist(), "t": x.t.tolist()}


def _bar_dict(bar: BarLight) -> dict:
    normal = getattr(bar, "normal_world", None)
    return {"id": int(bar.id), "center_world": np.asarray(bar.center_world, float).tolist(),
            "axis_world": np.asarray(bar.axis_world, float).tolist(), "length_m": float(bar.length_m),
            "intensity": float(bar.intensity),
            "normal_world": None if normal is None else np.asarray(normal, float).tolist()}


@dataclass(frozen=True)
class BoardTakeItem:
    """One camera's ChArUco take (picklable, for an executor): the poses it sees, at the board resolution."""

    camera_index: int  # position in the rig's camera list: seeds the camera's noise ``[seed, camera_index]``
    camera: Camera  # at the board take's resolution
    poses: tuple[Rigid, ...]  # every pose of the take, world_from_board; file k = pose k
    board: CharucoBoardConfig
    params: CalibrationTakeParams
    kind: str = "board"

    def dependencies(self) -> dict:
        """Everything the item's files depend on, as JSON values (the render code aside)."""
        return {"camera_index": self.camera_index, "camera": self.camera.to_dict(),
                "poses": [_rigid_dict(p) for p in self.poses], "board": self.board.model_dump(mode="json"),
                "params": self.params.model_dump(mode="json", exclude=set(MIRROR_ONLY_FIELDS))}


@dataclass(frozen=True)
class MirrorTakeItem:
    """One camera's mirror-sphere take, all bars, and its native windows (picklable, for an executor)."""

    camera_index: int  # seeds the camera's noise ``[seed, camera_index]`` (and ``[seed, camera_index, 1]``)
    camera: Camera  # at the mirror take's resolution
    roi_camera: Camera | None  # at the sensor's native resolution, for the windows; None: no windows
    sphere_centers_world: np.ndarray  # [K, 3]
    spheres: MirrorSpheresConfig
    bars: tuple[BarLight, ...]
    params: CalibrationTakeParams
    board_noise_draws: tuple[int, int, int] = (0, 0, 0)  # (images, height, width) the board take drew first
    kind: str = "mirror"

    def dependencies(self) -> dict:
        """Everything the item's files depend on, as JSON values (the render code aside)."""
        return {"camera_index": self.camera_index, "camera": self.camera.to_dict(),
                "roi_camera": None if self.roi_camera is None else self.roi_camera.to_dict(),
                "sphere_centers_world": np.asarray(self.sphere_centers_world, float).tolist(),
                "spheres": self.spheres.model_dump(mode="json"), "bars": [_bar_dict(b) for b in self.bars],
                "params": self.params.model_dump(mode="json", exclude=set(BOARD_ONLY_FIELDS)),
                "board_noise_draws": list(self.board_noise_draws)}


@dataclass(frozen=True)
class CalibrationPlan:
    """What the calibration takes shoot: the board poses, the ball centres and the per-camera items."""

    board: CharucoBoardConfig
    spheres: MirrorSpheresConfig
    bars: tuple[BarLight, ...]
    poses: tuple[Rigid, ...]  # world_from_board, pose 0 = the fixture
    sphere_centers_world: np.ndarray  # [K, 3]
    items: tuple[BoardTakeItem | MirrorTakeItem, ...]  # per camera, in camera order: board (if any), mirror


def skip_board_noise(rng: np.random.Generator, draws: tuple[int, int, int], params: CalibrationTakeParams) -> None:
    """Advance ``rng`` past the noise the board take drew: ``draws`` = (images, height, width).

    Exactly ``_sensor``'s draws, without rendering (the normal sampler's bit use varies, so
    the draws are made, not counted).
    """
    images, height, width = draws
    if params.noise > 0:
        for _ in range(images):
            rng.normal(0.0, params.noise, size=(height, width))


def plan_calibration_takes(cameras: Sequence[Camera], bars: Sequence[BarLight], params: CalibrationTakeParams,
                           board: CharucoBoardConfig = CharucoBoardConfig(),
                           spheres: MirrorSpheresConfig = MirrorSpheresConfig(),
                           board_cameras: Sequence[Camera] | None = None,
                           mirror_cameras: Sequence[Camera] | None = None,
                           roi_cameras: Sequence[Camera] | None = None, with_board: bool = True) -> CalibrationPlan:
    """The board poses, ball centres and per-camera items of the takes (arguments as ``render_calibration_takes``).

    ``with_board=False``: the mirror take alone (no board items; the mirror noise then starts
    from the camera's fresh generator).
    """
    mirror_cameras = list(cameras) if mirror_cameras is None else list(mirror_cameras)
    if [c.name for c in mirror_cameras] != [c.name for c in cameras]:
        raise ValueError("mirror_cameras must be the same cameras as cameras, in the same order")
    board_cameras = list(cameras) if board_cameras is None else list(board_cameras)
    if [c.name for c in board_cameras] != [c.name for c in cameras]:
        raise ValueError("board_cameras must be the same cameras as cameras, in the same order")
    roi_cameras = board_cameras if roi_cameras is None else list(roi_cameras)
    if [c.name for c in roi_cameras] != [c.name for c in cameras]:
        raise ValueError("roi_cameras must be the same cameras as cameras, in the same order")
    poses: tuple[Rigid, ...] = ()
    if with_board:
        poses = tuple(sample_board_poses(board, cameras, params, np.random.default_rng(params.seed)))
    sphere_centers = np.asarray(params.volume_center_m, float) + np.asarray(spheres.offsets_m, float)
    items: list[BoardTakeItem | MirrorTakeItem] = []
    for ci, (mirror_cam, board_cam, roi_cam) in enumerate(zip(mirror_cameras, board_cameras, roi_cameras)):
        draws = (0, 0, 0)
        if with_board:
            items.append(BoardTakeItem(ci, board_cam, poses, board, params))
            if params.effects is None:  # the real board take draws from its own generators (render_take_item)
                seen = sum(board_visible(board_cam, pose, board) for pose in poses)
                draws = (int(seen), board_cam.height, board_cam.width)
        windows = params.mirror_roi and roi_cam.width > mirror_cam.width
        items.append(MirrorTakeItem(ci, mirror_cam, roi_cam if windows else None, sphere_centers, spheres,
                                    tuple(bars), params, draws))
    return CalibrationPlan(board, spheres, tuple(bars), poses, sphere_centers, tuple(items))


def _exr_bytes(img: np.ndarray) -> np.ndarray:
    """The bytes ``write_exr`` puts in a file, as uint8 [N] (so a cached image is written byte for byte)."""
    import os
    import tempfile

    handle, name = tempfile.mkstemp(suffix=".exr")
    os.close(handle)
    try:
        write_exr(name, img)
        return np.frombuffer(Path(name).read_bytes(), np.uint8)
    finally:
        os.unlink(name)


def _real_board_image(item: BoardTakeItem, k: int, tex: np.ndarray, margin: int,
                      rays: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Board pose ``k`` of ``item`` as the real camera films the real print (``params.effects``).

    Each image has its own noise generator ``[seed, camera_index, 2, k]``, so no other image's
    draws (nor the mirror take's) depend on it.
    """
    from hardware.studio.optics import focus_distance_m
    from hardware.studio.real_camera import film_board_image

    cam, params, board, effects = item.camera, item.params, item.board, item.params.effects
    pose = item.poses[k]
    printed = print_board(board.squares_x, board.squares_y, board.square_m, effects.board_print, pose_index=k)
    clean = board_radiance(cam, pose, board, tex, margin, params, rays, printed)
    centre_board = np.array([[board.squares_x * board.square_m / 2, board.squares_y * board.square_m / 2, 0.0]])
    depth = float(cam.cam_from_world.apply(pose.apply(centre_board))[0, 2])
    focus = focus_distance_m(cam, effects.lens, np.asarray(params.volume_center_m, float))
    rng = np.random.default_rng([params.seed, item.camera_index, 2, k])
    return film_board_image(clean, cam, effects, params.board_scale, depth, focus, rng)


def render_take_item(item: BoardTakeItem | MirrorTakeItem) -> dict:
    """Render one camera's board or mirror take; returns its files (not written).

    Returns ``{"kind", "camera", "files": {path under calib/: EXR bytes uint8 [N]}, "seconds"}``;
    a mirror item also has ``"windows"``: ``{name: [{"file", "box"}]}`` (None without windows),
    ``"native_size"`` [w, h] and ``"seconds_windows"``.
    """
    import time

    start = time.perf_counter()
    cam, params = item.camera, item.params
    files: dict[str, np.ndarray] = {}
    rng = np.random.default_rng([params.seed, item.camera_index])
    if isinstance(item, BoardTakeItem):
        tex, margin = board_texture(item.board)
        rays = None
        for k, pose in enumerate(item.poses):
            if not board_visible(cam, pose, item.board):
                continue
            if rays is None:  # a camera that sees no pose casts no rays
                rays = _supersampled_rays(cam, params.supersample)
            if params.effects is None:
                img = render_board_image(cam, pose, item.board, tex, margin, params, rng, rays)
            else:
                img = _real_board_image(item, k, tex, margin, rays)
            files[f"charuco/{cam.name}/{k:04d}.exr"] = _exr_bytes(img)
        return {"kind": "board", "camera": cam.name, "files": files, "seconds": time.perf_counter() - start}
    skip_board_noise(rng, item.board_noise_draws, params)
    coarse = render_mirror_images(cam, item.sphere_centers_world, item.spheres, item.bars, params, rng)
    for name, img in coarse.items():
        files[f"mirror/{cam.name}/{name}.exr"] = _exr_bytes(img)
    coarse_s = time.perf_counter() - start
    windows = None
    if item.roi_camera is not None:
        rois = render_mirror_rois(item.roi_camera, coarse, item.sphere_centers_world, item.spheres, item.bars,
                                  params, np.random.default_rng([params.seed, item.camera_index, 1]))
        windows = {}
        for name, found in rois.items():
            windows[name] = []
            for k, (box, img) in enumerate(found):
                file = f"{name}_{k:02d}.exr"
                files[f"mirror_roi/{cam.name}/{file}"] = _exr_bytes(img)
                windows[name].append({"file": file, "box": list(box)})
    native = item.roi_camera or cam
    return {"kind": "mirror", "camera": cam.name, "files": files, "windows": windows,
            "native_size": [native.width, native.height], "seconds": coarse_s,
            "seconds_windows": time.perf_counter() - start - coarse_s}


def write_take_specs(plan: CalibrationPlan, out_dir: Path, truth_dir: Path) -> None:
    """Write the takes' specs (``calib/board.json``, ``calib/mirror.json``) and their truth files.

    Without board poses (a mirror take alone) only the mirror's files are written.
    """
    calib, truth_dir = Path(out_dir) / "calib", Path(truth_dir)
    calib.mkdir(parents=True, exist_ok=True)
    truth_dir.mkdir(parents=True, exist_ok=True)
    if plan.poses:
        (calib / "board.json").write_text(json.dumps({
            **plan.board.spec(), "poses": len(plan.poses), "reference_pose_index": 0,
            "world_from_board_reference": _rigid_dict(plan.poses[0]),
            "note": "pose 0 is shot with the board in its fixture: its known pose defines the world frame",
        }, indent=1))
        (truth_dir / "calib_board_poses.json").write_text(json.dumps(
            {"world_from_board": [_rigid_dict(p) for p in plan.poses]}, indent=1))
    (calib / "mirror.json").write_text(json.dumps({
        "radius_m": plan.spheres.radius_m, "count": len(plan.sphere_centers_world), "silhouette_image": "room.exr",
        "bars": [int(b.id) for b in plan.bars]}, indent=1))
    (truth_dir / "mirror_spheres.json").write_text(json.dumps(
        {"radius_m": plan.spheres.radius_m, "centers_world": plan.sphere_centers_world.tolist()}, indent=1))


class TakeWriter:
    """Writes ``render_take_item`` results under ``calib/`` as they come, then the windows' index.

    Feed it the items' results in plan order (``write``; ``pipeline.itemcache``'s ``consume``
    signature), then call ``finish``.
    """

    def __init__(self, calib: Path) -> None:
        self.calib = Path(calib)
        self.roi_index: dict = {}

    def write(self, position: int, result: dict) -> dict:
        """Write one item's files; returns its summary ``{"kind", "camera", "images", "seconds"}``."""
        cam = result["camera"]
        folder = "charuco" if result["kind"] == "board" else "mirror"
        (self.calib / folder / cam).mkdir(parents=True, exist_ok=True)  # also when the camera saw no board
        if result["kind"] == "mirror" and result["windows"] is not None:
            (self.calib / "mirror_roi" / cam).mkdir(parents=True, exist_ok=True)
            width, height = result["native_size"]
            self.roi_index.setdefault("width", int(width))
            self.roi_index.setdefault("height", int(height))
            self.roi_index.setdefault("cameras", {})[cam] = result["windows"]
        for relative, data in result["files"].items():
            path = self.calib / relative
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(np.asarray(data, np.uint8).tobytes())
        return {"kind": result["kind"], "camera": cam, "images": len(result["files"]),
                "seconds": float(result["seconds"]) + float(result.get("seconds_windows", 0.0))}

    def finish(self) -> None:
        """Write ``calib/mirror_roi.json`` when the mirror take has windows."""
        if self.roi_index:
            self.roi_index["note"] = ("native-resolution windows of the mirror take around the balls (room) and "
                                      "each bar's highlights; box = [x0, y0, x1, y1] native pixels, exclusive ends")
            (self.calib / "mirror_roi.json").write_text(json.dumps(self.roi_index, indent=1))


def render_calibration_takes(cameras: Sequence[Camera], bars: Sequence[BarLight], out_dir: Path,
                             truth_dir: Path, params: CalibrationTakeParams,
                             board: CharucoBoardConfig = CharucoBoardConfig(),
                             spheres: MirrorSpheresConfig = MirrorSpheresConfig(),
                             progress=None, board_cameras: Sequence[Camera] | None = None,
                             mirror_cameras: Sequence[Camera] | None = None,
                             roi_cameras: Sequence[Camera] | None = None) -> None:
    """Render the board and mirror-sphere takes for every camera into ``out_dir/calib`` (in this process).

    Args:
        cameras: the true cameras (the studio's, with distortion) at the performance resolution
            (the mirror take is shot at it).
        bars: the true LED bars.
        out_dir: the capture object's folder; ``calib/`` is written inside it.
        truth_dir: the capture truth folder; board poses and sphere centres go there.
        params: take settings (poses, noise, ...).
        board, spheres: the board print and the chrome balls.
        progress: optional ``Progress`` advanced once per camera and take.
        board_cameras: the same cameras (same order) at the resolution the board take is shot at;
            a real studio calibrates at the sensor's native resolution whatever resolution the
            performance is later used at. Default: ``cameras``.
        mirror_cameras: likewise for the mirror-sphere take. Default: ``cameras``. At native
            resolution the bars are placed to a few millimetres (lightcal's ridge line fit)
            but the take costs ~10x the CPU time.
        roi_cameras: the same cameras at the sensors' native resolution, for the mirror take's
            windows (``params.mirror_roi``). Default: ``board_cameras`` (the board take is shot
            at the native resolution). No windows when they are not finer than ``mirror_cameras``.

    With windows, ``calib/mirror_roi.json`` lists them: ``{"width", "height", "cameras": {cam:
    {"room" | "bar<b:02d>": [{"file", "box": [x0, y0, x1, y1]}, ...]}}}`` (native pixels, exclusive
    ends), the images in ``calib/mirror_roi/<cam>/<file>``. The work is ``plan_calibration_takes``'
    items through ``render_take_item`` and ``TakeWriter``, as the capture stage fans them out.
    """
    plan = plan_calibration_takes(cameras, bars, params, board, spheres, board_cameras=board_cameras,
                                  mirror_cameras=mirror_cameras, roi_cameras=roi_cameras)
    write_take_specs(plan, out_dir, truth_dir)
    writer = TakeWriter(Path(out_dir) / "calib")
    for position, item in enumerate(plan.items):
        writer.write(position, render_take_item(item))
        if progress is not None:
            progress.advance(1)
    writer.finish()


def render_mirror_take(cameras: Sequence[Camera], bars: Sequence[BarLight], out_dir: Path, truth_dir: Path,
                       params: CalibrationTakeParams, spheres: MirrorSpheresConfig = MirrorSpheresConfig(),
                       roi_cameras: Sequence[Camera] | None = None) -> dict[str, float]:
    """The mirror-sphere take alone (no board), as ``render_calibration_takes`` shoots it.

    ``cameras`` at the take's (coarse) resolution, ``roi_cameras`` (same order) at the native
    resolution of the windows (None: no windows). Camera ``i`` draws its noise from the same
    seeds as in ``render_calibration_takes``, but the images differ (there the board take
    draws first). Returns the seconds spent on the full images and on the windows.
    """
    plan = plan_calibration_takes(cameras, bars, params, spheres=spheres, mirror_cameras=cameras,
                                  roi_cameras=list(cameras) if roi_cameras is None else roi_cameras,
                                  with_board=False)
    write_take_specs(plan, out_dir, truth_dir)
    writer = TakeWriter(Path(out_dir) / "calib")
    seconds = {"full_s": 0.0, "windows_s": 0.0}
    for position, item in enumerate(plan.items):
        result = render_take_item(item)
        writer.write(position, result)
        seconds["full_s"] += result["seconds"]
        seconds["windows_s"] += result["seconds_windows"]
    writer.finish()
    return seconds


def takes_from_rig(rig) -> tuple[CharucoBoardConfig, MirrorSpheresConfig]:
    """The board and ball settings of a ``scene.rig.RigConfig`` (its ``calibration`` section)."""
    return (CharucoBoardConfig(**rig.calibration.get("board", {})),
            MirrorSpheresConfig(**rig.calibration.get("mirror_spheres", {})))


def render_rig_takes(out_dir: Path, truth_dir: Path, params: CalibrationTakeParams, scale: float = 0.3125,
                     camera_names: Sequence[str] | None = None, bar_ids: Sequence[int] | None = None,
                     rig=None, board_scale: float = 1.0) -> tuple[list[Camera], list[BarLight]]:
    """Calibration takes of (a subset of) the studio rig, with the truth files the capture stage writes.

    For benchmarks and tests that need a capture's ``calib/`` without the performance:
    writes ``out_dir/calib`` and ``truth_dir`` (``cameras.json``, ``bars.json`` and the
    take's own truth), plus the ``manifest.json`` fields the calibration reads (cameras,
    performance ``width``/``height``). The mirror take is at ``scale`` (the performance
    resolution), the board take at ``board_scale`` (1.0: the rig's native resolution).
    Returns the true cameras (at ``scale``) and bars.
    """
    from scene.camera import save_cameras
    from scene.rig import default_rig

    rig = default_rig() if rig is None else rig
    cameras = [c for c in rig.cameras_at(scale) if camera_names is None or c.name in camera_names]
    light_bars = [b for b in rig.light_bars() if bar_ids is None or b.id in bar_ids]
    bars = [BarLight(b.id, b.center_world, b.axis_world, b.length_m, b.intensity, b.normal_world)
            for b in light_bars]
    board, spheres = takes_from_rig(rig)
    params = params.model_copy(update={"volume_center_m": tuple(rig.head_center_m), "board_scale": board_scale})
    board_cameras = [c for c in rig.cameras_at(board_scale) if camera_names is None or c.name in camera_names]
    render_calibration_takes(cameras, bars, out_dir, truth_dir, params, board, spheres, board_cameras=board_cameras)
    save_cameras(Path(truth_dir) / "cameras.json", cameras)
    (Path(out_dir) / "manifest.json").write_text(json.dumps(
        {"cameras": [c.name for c in cameras], "width": cameras[0].width, "height": cameras[0].height}))
    (Path(truth_dir) / "bars.json").write_text(json.dumps({"bars": [b.to_dict() for b in light_bars]}, indent=1))
    return cameras, bars
