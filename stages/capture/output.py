"""The capture stage's output folders: the one place that spells their file names.

``CaptureOutput`` (the ``capture`` object)::

    manifest.json                 subject, fps, width, height, cameras, bars, takes, frames[]
    frames/<cam>/<index:06d>.exr  received images labelled with their trigger index
    calib/board.json, calib/charuco/<cam>/<k:04d>.exr           the ChArUco board take
    calib/mirror.json, calib/mirror/<cam>/<name>.exr            the mirror-sphere take
    calib/mirror_roi.json, calib/mirror_roi/<cam>/<file>.exr    its native-resolution windows
    scans/scans.npz               the actor's scan session (names, vertices, faces)
    controller_log.json           the LED controller's log (which light at which pulse)
    contact_sheet.png, strip.png  previews

``CaptureTruth`` (``capture.truth``, evaluation stages only)::

    cameras.json, bars.json, frames.npz, meshes.npz, mattes/<cam>/<index:06d>.png,
    studio.json, lights_per_pulse.json, calib_board_poses.json, mirror_spheres.json

The calibration takes (``calib/``) are written by the virtual studio
(``hardware.studio.calibration_takes``) or copied from a real capture folder.

A missing or malformed file raises one ``InputError`` naming the file and saying to rerun
the capture stage.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pipeline.stage_output import StageOutput
from scene.camera import Camera, load_cameras, save_cameras

_MANIFEST = "manifest.json"
_FRAMES = "frames"
_FRAME_SUFFIX = ".exr"
_SCANS_DIR = "scans"
_SCANS = "scans.npz"
_CONTROLLER_LOG = "controller_log.json"
_CONTACT_SHEET = "contact_sheet.png"
_STRIP = "strip.png"
_RECEIVED = "_received"  # images in arrival order, before labelling (removed before the stage ends)
_CALIB = "calib"
_BOARD_SPEC = "board.json"
_CHARUCO = "charuco"
_MIRROR_SPEC = "mirror.json"
_MIRROR = "mirror"
_MIRROR_ROI = "mirror_roi"
_MIRROR_ROI_INDEX = "mirror_roi.json"

_TRUTH_CAMERAS = "cameras.json"
_TRUTH_BARS = "bars.json"
_TRUTH_FRAMES = "frames.npz"
_TRUTH_MESHES = "meshes.npz"
_TRUTH_MATTES = "mattes"
_TRUTH_STUDIO = "studio.json"
_TRUTH_LIGHTS = "lights_per_pulse.json"
_TRUTH_BOARD_POSES = "calib_board_poses.json"
_TRUTH_MIRROR_SPHERES = "mirror_spheres.json"

#: The names no module outside ``stages/capture`` may spell (``tests/test_output_contracts.py``).
CONTRACT_NAMES = (
    _MANIFEST, _FRAMES, _SCANS_DIR, _SCANS, _CONTROLLER_LOG, _CONTACT_SHEET, _STRIP, _CALIB, _BOARD_SPEC,
    _CHARUCO, _MIRROR_SPEC, _MIRROR, _MIRROR_ROI, _MIRROR_ROI_INDEX, _RECEIVED,
    _TRUTH_CAMERAS, _TRUTH_BARS, _TRUTH_FRAMES, _TRUTH_MESHES, _TRUTH_MATTES, _TRUTH_STUDIO, _TRUTH_LIGHTS,
    _TRUTH_BOARD_POSES, _TRUTH_MIRROR_SPHERES,
)


def frame_name(index: int) -> str:
    """The file name of frame ``index`` in ``frames/<cam>/`` (and of a truth matte, with ``.png``)."""
    return f"{int(index):06d}{_FRAME_SUFFIX}"


class CaptureOutput(StageOutput):
    """The ``capture`` object: manifest, labelled frames, calibration takes, scans, log, previews."""

    stage = "capture"

    # --- manifest -------------------------------------------------------------------------
    @property
    def manifest_path(self) -> Path:
        return self.file(_MANIFEST)

    def has_manifest(self) -> bool:
        """Whether the folder has a manifest (a calibration-only capture may not)."""
        return self.manifest_path.is_file()

    def manifest(self, keys: tuple[str, ...] = ()) -> dict[str, Any]:
        """The parsed ``manifest.json``; it must hold ``keys`` (e.g. ``("cameras", "frames")``)."""
        return self.read_json(_MANIFEST, keys=keys)

    def manifest_bytes(self) -> bytes:
        """The manifest file's bytes (``OSError`` when absent: the caller decides)."""
        return self.manifest_path.read_bytes()

    def write_manifest(self, manifest: dict[str, Any]) -> None:
        self.write_json(manifest, _MANIFEST, indent=1)

    def frames_of(self, manifest: dict[str, Any]) -> list[dict[str, Any]]:
        """The manifest's ``frames`` list; a clear error when it has none."""
        frames = manifest.get("frames")
        if not isinstance(frames, list) or not frames:
            raise self.malformed(self.manifest_path, "no 'frames' list")
        return frames

    # --- frames ---------------------------------------------------------------------------
    def frames_dir(self, cam: str) -> Path:
        """``frames/<cam>/`` (not created)."""
        return self.file(_FRAMES, cam)

    def frame_path(self, cam: str, index: int) -> Path:
        """``frames/<cam>/<index:06d>.exr``."""
        return self.file(_FRAMES, cam, frame_name(index))

    def has_frame(self, cam: str, index: int) -> bool:
        return self.frame_path(cam, index).is_file()

    def frame(self, cam: str, index: int) -> np.ndarray:
        """The linear image [H, W, C] float32 of camera ``cam`` at trigger ``index``."""
        from scene.image_io import read_exr

        return self.load(self.frame_path(cam, index), read_exr)

    def frame_cameras(self) -> list[Path]:
        """The cameras' frame folders that exist, sorted by name."""
        return sorted(p for p in self.file(_FRAMES).glob("*") if p.is_dir())

    @property
    def received_dir(self) -> Path:
        """Scratch folder of the images in arrival order, before labelling (capture stage only)."""
        return self.file(_RECEIVED)

    def received_path(self, cam: str, arrival: int) -> Path:
        return self.file(_RECEIVED, cam, frame_name(arrival))

    # --- scans, controller log, previews --------------------------------------------------
    @property
    def scans_dir(self) -> Path:
        return self.file(_SCANS_DIR)

    @property
    def scans_path(self) -> Path:
        return self.file(_SCANS_DIR, _SCANS)

    def scans(self, keys: tuple[str, ...] = ("vertices",)) -> dict[str, np.ndarray]:
        """The actor's scan session: ``names`` [S], ``vertices`` [S, V, 3] metres (neutral first), ``faces``."""
        return self.read_npz(_SCANS_DIR, _SCANS, keys=keys)

    def write_scans(self, names: list[str], vertices: np.ndarray, faces: np.ndarray) -> None:
        self.scans_dir.mkdir()
        np.savez_compressed(self.scans_path, names=np.array(names), vertices=vertices, faces=faces)

    def controller_log(self) -> dict[str, Any]:
        return self.read_json(_CONTROLLER_LOG, keys=("entries",))

    def write_controller_log(self, log: dict[str, Any]) -> None:
        self.write_json(log, _CONTROLLER_LOG, indent=1)

    @property
    def contact_sheet_path(self) -> Path:
        return self.file(_CONTACT_SHEET)

    @property
    def strip_path(self) -> Path:
        return self.file(_STRIP)

    def previews(self) -> list[tuple[str, Path]]:
        """(name, path) of the preview images, in reading order (the contact sheet, then the strip)."""
        return [(_CONTACT_SHEET, self.contact_sheet_path), (_STRIP, self.strip_path)]

    # --- calibration takes ----------------------------------------------------------------
    @property
    def calib_dir(self) -> Path:
        """``calib/``: the calibration takes (``hardware.studio.calibration_takes`` writes them)."""
        return self.file(_CALIB)

    @property
    def board_spec_path(self) -> Path:
        return self.file(_CALIB, _BOARD_SPEC)

    def board_spec(self) -> dict[str, Any]:
        """``calib/board.json``: the ChArUco board's print and its fixture (reference) pose."""
        return self.read_json(_CALIB, _BOARD_SPEC)

    @property
    def charuco_dir(self) -> Path:
        """``calib/charuco/``: one folder of board images per camera."""
        return self.file(_CALIB, _CHARUCO)

    def charuco_cameras(self) -> list[str]:
        """The cameras with a board-take folder, sorted; a clear error when there is no board take."""
        root = self.charuco_dir
        if not root.is_dir():
            raise self.error(root, "no board takes in the capture (the capture must hold calib/charuco/<cam>/)",
                             state="is missing")
        return sorted(p.name for p in root.iterdir() if p.is_dir())

    def charuco_images(self, cam: str) -> list[Path]:
        """Camera ``cam``'s board images (``<k:04d>.exr``), sorted; empty when it has none."""
        folder = self.charuco_dir / cam
        return sorted(folder.glob(f"*{_FRAME_SUFFIX}")) if folder.is_dir() else []

    @property
    def mirror_spec_path(self) -> Path:
        return self.file(_CALIB, _MIRROR_SPEC)

    def mirror_spec(self) -> dict[str, Any]:
        """``calib/mirror.json``: the mirror spheres' ``radius_m``, ``count``, silhouette image, bars."""
        return self.read_json(_CALIB, _MIRROR_SPEC)

    @property
    def mirror_dir(self) -> Path:
        """``calib/mirror/``: one folder of mirror-sphere images per camera."""
        return self.file(_CALIB, _MIRROR)

    def mirror_image_path(self, cam: str, name: str) -> Path:
        """``calib/mirror/<cam>/<name>`` (``name`` with its suffix, e.g. ``room.exr``)."""
        return self.file(_CALIB, _MIRROR, cam, name)

    def mirror_bar_ids(self) -> list[int]:
        """The bars with an image in the mirror take (``calib/mirror/<cam>/bar<b:02d>.exr``), sorted."""
        return sorted({int(p.stem[3:]) for p in self.mirror_dir.glob(f"*/bar*{_FRAME_SUFFIX}")})

    def mirror_images(self, pattern: str = "*") -> list[Path]:
        """The mirror take's full images matching ``<cam>/<pattern>.exr``, sorted."""
        return sorted(self.mirror_dir.glob(f"*/{pattern}{_FRAME_SUFFIX}"))

    @property
    def mirror_roi_index_path(self) -> Path:
        return self.file(_CALIB, _MIRROR_ROI_INDEX)

    def has_mirror_roi_index(self) -> bool:
        return self.mirror_roi_index_path.is_file()

    @property
    def mirror_roi_dir(self) -> Path:
        """``calib/mirror_roi/``: the windows' images, one folder per camera."""
        return self.file(_CALIB, _MIRROR_ROI)

    def mirror_roi_image_path(self, cam: str, file: str) -> Path:
        return self.file(_CALIB, _MIRROR_ROI, cam, file)

    def mirror_roi_images(self, pattern: str = "*") -> list[Path]:
        """The windows' images matching ``<cam>/<pattern>.exr``, sorted."""
        return sorted(self.mirror_roi_dir.glob(f"*/{pattern}{_FRAME_SUFFIX}"))


class CaptureTruth(StageOutput):
    """``capture.truth``: what the virtual studio really did (evaluation stages and benches only)."""

    stage = "capture"
    output = "truth"

    @property
    def cameras_path(self) -> Path:
        return self.file(_TRUTH_CAMERAS)

    def cameras(self) -> list[Camera]:
        """The true cameras at the performance resolution."""
        return self.load(self.cameras_path, lambda path: load_cameras(path, "world"))

    def write_cameras(self, cameras: list[Camera]) -> None:
        save_cameras(self.cameras_path, cameras)

    @property
    def bars_path(self) -> Path:
        return self.file(_TRUTH_BARS)

    def bars(self) -> list[dict[str, Any]]:
        """The true LED bars (``bars.json`` entries: id, center_world, axis_world, length_m, ...)."""
        return self.read_json(_TRUTH_BARS, keys=("bars",))["bars"]

    def write_bars(self, data: dict[str, Any], **dumps: Any) -> None:
        self.write_json(data, _TRUTH_BARS, **dumps)

    @property
    def frames_path(self) -> Path:
        return self.file(_TRUTH_FRAMES)

    def frames(self, keys: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
        """``frames.npz``: per trigger the true state (index, weights, world_from_head_R/t, received, lit, ...)."""
        return self.read_npz(_TRUTH_FRAMES, keys=keys)

    def write_frames(self, **arrays: np.ndarray) -> None:
        np.savez_compressed(self.frames_path, **arrays)

    def meshes(self, keys: tuple[str, ...] = ("vertices",)) -> dict[str, np.ndarray]:
        """``meshes.npz``: the true head-space meshes ``vertices`` [F, V, 3] and ``faces``."""
        return self.read_npz(_TRUTH_MESHES, keys=keys)

    def write_meshes(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        np.savez(self.file(_TRUTH_MESHES), vertices=vertices, faces=faces)  # float noise: zlib gains little

    @property
    def mattes_dir(self) -> Path:
        """``mattes/``: the true mattes, ``<cam>/<index:06d>.png``."""
        return self.file(_TRUTH_MATTES)

    def matte_path(self, cam: str, index: int) -> Path:
        return self.file(_TRUTH_MATTES, cam, f"{int(index):06d}.png")

    def matte(self, cam: str, index: int) -> np.ndarray:
        """The true alpha [H, W] float of camera ``cam`` at trigger ``index``."""
        from scene.image_io import read_png16

        return self.load(self.matte_path(cam, index), read_png16)

    @property
    def studio_path(self) -> Path:
        return self.file(_TRUTH_STUDIO)

    def studio(self) -> dict[str, Any]:
        """``studio.json``: the subject, identity seed, texture size, render settings, ..."""
        return self.read_json(_TRUTH_STUDIO)

    def write_studio(self, data: dict[str, Any]) -> None:
        self.write_json(data, _TRUTH_STUDIO, indent=1)

    def lights_per_pulse(self) -> list:
        """What the bars showed at each trigger pulse (``"F"``, a bar id, None = dark)."""
        return self.read_json(_TRUTH_LIGHTS, kind=list)

    def write_lights_per_pulse(self, lights: list) -> None:
        self.write_json(list(lights), _TRUTH_LIGHTS)

    def board_poses(self) -> dict[str, Any]:
        """``calib_board_poses.json``: the board take's true poses."""
        return self.read_json(_TRUTH_BOARD_POSES)

    def mirror_spheres(self) -> dict[str, Any]:
        """``mirror_spheres.json``: the mirror spheres' true radius and centres."""
        return self.read_json(_TRUTH_MIRROR_SPHERES)

