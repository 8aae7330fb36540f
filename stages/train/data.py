"""The training data of the train stage, read from the upstream stages' outputs.

Per OLAT frame: the camera images (full-on frames are only for tracking and are dropped),
the stabilised per-frame cameras (``stabilize/cameras_head.json``, cam_from_head), the
tracked head-space mesh (``track/meshes.npz``), the mattes (``matte/mattes``) and the lit
bar's centre (``lightcal/bars.json``, world space) moved into head space with the tracked
pose (``track/tracking.npz``, world_from_head). Images are resized to the training width.

Memory: per-pixel rays are not stored (a camera's pixel directions are the same in every
frame; only its pose in head space changes), and when the images and mattes would take more
than ``resident_limit_gb`` they are written to memory-mapped files in ``spill_dir`` instead of
RAM (the paper preset: thousands of 1024x768 images), so the trainer gathers the pixels of a
batch from disk pages rather than holding the capture in memory.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from pipeline.errors import InputError
from scene.camera import Camera, Rigid
from stages.capture.output import CaptureOutput
from stages.lightcal.output import LightcalOutput
from stages.matte.output import MatteOutput
from stages.stabilize.output import StabilizeOutput
from stages.track.output import TrackOutput


@dataclass
class TrainData:
    """Every usable OLAT frame of every camera, at training resolution.

    Attributes:
        frame_index: [F] capture frame indices.
        take: [F] take name of each frame.
        bar: [F] lit bar id of each frame.
        camera_names: [C] camera ids.
        images: [F, C, H, W, 3] linear RGB float32 (an ``np.memmap`` when spilled to disk).
        mattes: [F, C, H, W] alpha float32 (an ``np.memmap`` when spilled to disk).
        pixel_dirs_cam: [C, H*W, 3] unit ray direction of every pixel in its camera's frame
            (lens distortion undone), float32.
        head_from_cam_rot: [F, C, 3, 3] camera rotations in head space: a pixel's head-space
            direction is ``head_from_cam_rot @ pixel_dirs_cam``, its origin ``cam_pos_head``.
        cam_pos_head: [F, C, 3] camera centres in head space, metres.
        light_pos_head: [F, 3] lit bar centre in head space, metres.
        light_pos_world: [B, 3] every bar's centre in world space (row = bar id).
        head_t_world: [F, 3] head origin in world space.
        vertices: [F, V, 3] tracked head-space meshes, metres.
        triangles: [T, 3] mesh triangles.
    """

    frame_index: np.ndarray
    take: np.ndarray
    bar: np.ndarray
    camera_names: list[str]
    images: np.ndarray
    mattes: np.ndarray
    pixel_dirs_cam: np.ndarray
    head_from_cam_rot: np.ndarray
    cam_pos_head: np.ndarray
    light_pos_head: np.ndarray
    light_pos_world: np.ndarray
    head_t_world: np.ndarray
    vertices: np.ndarray
    triangles: np.ndarray

    @property
    def num_bars(self) -> int:
        return int(self.light_pos_world.shape[0])

    @property
    def spilled(self) -> bool:
        """Whether the images and mattes live in memory-mapped files rather than RAM."""
        return isinstance(self.images, np.memmap)

    def rays(self, frame: int, camera: int) -> tuple[np.ndarray, np.ndarray]:
        """Head-space origins and unit directions [H*W, 3] of every pixel of one (frame, camera) image."""
        dirs = self.pixel_dirs_cam[camera] @ self.head_from_cam_rot[frame, camera].T  # [H*W, 3]
        return np.broadcast_to(self.cam_pos_head[frame, camera], dirs.shape).copy(), dirs


def resize_area(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """``img`` [H, W(, C)] area-averaged to ``width`` x ``height`` (what a coarser sensor would record)."""
    import cv2

    if img.shape[1] == width and img.shape[0] == height:
        return img
    return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)


def _image_array(shape: tuple[int, ...], spill_dir: Path | None, name: str) -> np.ndarray:
    """A zeroed float32 array in RAM, or a memory-mapped ``.npy`` file in ``spill_dir``."""
    if spill_dir is None:
        return np.zeros(shape, np.float32)
    spill_dir.mkdir(parents=True, exist_ok=True)
    # A fresh file each time: a spilled array is scratch space, rebuilt from the inputs.
    return np.lib.format.open_memmap(spill_dir / f"{name}.npy", mode="w+", dtype=np.float32, shape=shape)


def _pixel_directions(cam: Camera) -> np.ndarray:
    """Unit directions [H*W, 3] of ``cam``'s pixel centres in its own frame."""
    at_origin = replace(cam, pose=Rigid(np.eye(3), np.zeros(3)))
    _, dirs = at_origin.image_rays()
    return dirs.reshape(-1, 3)


def _intrinsics(cam: Camera) -> tuple:
    return (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, tuple(cam.dist))


def load_train_data(inputs: dict[str, Path], image_width_px: int, log, max_frames: int = 0,
                    resident_limit_gb: float = 8.0, spill_dir: Path | None = None) -> TrainData:
    """Read the training data from the upstream folders (never from ``capture.truth``).

    ``resident_limit_gb``: images and mattes larger than this go to memory-mapped files in
    ``spill_dir`` (required then) instead of RAM.
    """
    capture, stabilize, track = (CaptureOutput(inputs["capture"]), StabilizeOutput(inputs["stabilize"]),
                                 TrackOutput(inputs["track"]))
    matte, lightcal = MatteOutput(inputs["matte"]), LightcalOutput(inputs["lightcal"])
    manifest = capture.manifest(keys=("cameras", "frames", "width", "height"))
    bars = {int(b["id"]): np.asarray(b["center_world"], np.float64) for b in lightcal.bars()}
    num_bars = max(int(manifest.get("bars", 0)), max(bars) + 1 if bars else 0)
    light_world = np.full((num_bars, 3), np.nan)
    for bar_id, centre in bars.items():
        light_world[bar_id] = centre
    tracking = track.tracking(("index", "world_from_head_R", "world_from_head_t"))
    meshes = track.meshes(("vertices",))
    mesh_index = meshes.get("index", tracking["index"])
    if len(mesh_index) != len(meshes["vertices"]):
        raise track.malformed(track.meshes_path, f"{len(meshes['vertices'])} meshes but {len(mesh_index)} frame "
                                                 "indices")
    if "faces" in meshes:
        faces = meshes["faces"]
    else:
        faces = capture.scans(keys=("faces",))["faces"]
    from avatar.layout import triangulate

    triangles = triangulate(faces)
    mesh_row = {int(i): r for r, i in enumerate(mesh_index)}
    pose_row = {int(i): r for r, i in enumerate(tracking["index"])}
    cams_head = stabilize.cameras_head_by_name()
    camera_names = [str(c) for c in manifest["cameras"]]
    frames = []
    for f in manifest["frames"]:
        light = f.get("light")
        if light == "F" or light is None or f.get("status", "ok") != "ok":
            continue
        idx = int(f["index"])
        bar = int(light)
        if idx not in mesh_row or idx not in pose_row or idx not in cams_head:
            log.warning("frame %d: no tracked mesh, pose or stabilised camera; skipped", idx)
            continue
        if bar >= num_bars or not np.isfinite(light_world[bar]).all():
            log.warning("frame %d: bar %d has no calibrated position in %s; skipped", idx, bar, lightcal.bars_path)
            continue
        frames.append((idx, str(f.get("take", "")), bar))
    if max_frames and len(frames) > max_frames:
        pick = np.linspace(0, len(frames) - 1, max_frames).round().astype(int)
        frames = [frames[i] for i in pick]
    if not frames:
        raise InputError(f"{capture.manifest_path}: no usable OLAT frames (status ok, tracked, "
                         "with a calibrated bar); check the capture and the track stage")
    width0, height0 = int(manifest["width"]), int(manifest["height"])
    scale = image_width_px / width0 if image_width_px else 1.0
    width, height = int(round(width0 * scale)), int(round(height0 * scale))
    nf, nc = len(frames), len(camera_names)
    image_gb = nf * nc * height * width * 4 * 4 / 1e9  # RGB + alpha, float32
    spill = image_gb > resident_limit_gb
    if spill and spill_dir is None:
        raise ValueError("load_train_data: spill_dir is required when the images exceed resident_limit_gb")
    images = _image_array((nf, nc, height, width, 3), spill_dir if spill else None, "images")
    mattes = _image_array((nf, nc, height, width), spill_dir if spill else None, "mattes")
    if spill:
        log.info("train data: %.1f GB of images and mattes > train.resident_limit_gb=%.1f; memory-mapped "
                 "from %s", image_gb, resident_limit_gb, spill_dir)
    pixel_dirs = np.zeros((nc, height * width, 3), np.float32)
    cam_intrinsics: list[tuple | None] = [None] * nc
    head_from_cam = np.zeros((nf, nc, 3, 3), np.float32)
    cam_pos = np.zeros((nf, nc, 3), np.float32)
    light_head = np.zeros((nf, 3), np.float32)
    head_t = np.zeros((nf, 3), np.float32)
    verts = np.zeros((nf,) + meshes["vertices"].shape[1:], np.float32)
    for i, (idx, _take, bar) in enumerate(frames):
        row = pose_row[idx]
        world_from_head = Rigid(np.asarray(tracking["world_from_head_R"][row], np.float64),
                                np.asarray(tracking["world_from_head_t"][row], np.float64))
        light_head[i] = world_from_head.inverse().apply(light_world[bar])
        head_t[i] = world_from_head.t
        verts[i] = meshes["vertices"][mesh_row[idx]]
        for j, name in enumerate(camera_names):
            cam = cams_head[idx].get(name)
            if cam is None:
                raise stabilize.malformed(stabilize.cameras_head_path, f"frame {idx} has no camera '{name}'")
            img = capture.frame(name, idx)[..., :3]
            alpha = matte.matte(name, idx)
            images[i, j] = resize_area(img, width, height)
            mattes[i, j] = resize_area(alpha, width, height)
            cam_small = cam.scaled(width / cam.width)
            if cam_intrinsics[j] is None:
                cam_intrinsics[j] = _intrinsics(cam_small)
                pixel_dirs[j] = _pixel_directions(cam_small)
            elif _intrinsics(cam_small) != cam_intrinsics[j]:
                raise InputError(f"{stabilize.cameras_head_path}: camera '{name}' has other intrinsics in frame "
                                 f"{idx} than in frame {frames[0][0]}; a camera's lens must be the same in every "
                                 "frame (re-run calibrate and stabilize)")
            head_from_cam[i, j] = cam_small.cam_from_head.R.T
            cam_pos[i, j] = cam_small.center
    log.info("train data: %d OLAT frames x %d cameras at %dx%d px", nf, nc, width, height)
    return TrainData(
        frame_index=np.array([f[0] for f in frames]), take=np.array([f[1] for f in frames]),
        bar=np.array([f[2] for f in frames]), camera_names=camera_names, images=images, mattes=mattes,
        pixel_dirs_cam=pixel_dirs, head_from_cam_rot=head_from_cam, cam_pos_head=cam_pos, light_pos_head=light_head,
        light_pos_world=light_world.astype(np.float32), head_t_world=head_t, vertices=verts, triangles=triangles)
