"""Reading the mirror-sphere take: full images, or native-resolution windows where the capture has them.

A capture may hold, besides ``calib/mirror/<cam>/<name>.exr`` (the contract: full images,
often at the performance resolution), native-resolution windows around the balls and the
highlights (``calib/mirror_roi.json`` + ``calib/mirror_roi/<cam>/<file>.exr``, written by a
region-of-interest readout; layout in ``hardware.studio.calibration_takes``). For a camera
with windows, every image is served at the native resolution: a canvas at the full image's
background level with the windows pasted in, so the detectors need not know about windows.
Background and noise come from the full image (same sensor, same noise per pixel).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline.errors import InputError
from scene.camera import Camera
from scene.image_io import read_exr
from stages.capture.output import CaptureOutput
from stages.lightcal.spheres import background_and_noise


def read_grey(path: Path) -> np.ndarray:
    """An EXR as a float64 grey image [H, W] (mean of RGB); InputError naming the file if unreadable."""
    try:
        img = read_exr(path)
    except ValueError as err:
        raise InputError(str(err)) from err
    return img[..., :3].mean(axis=-1).astype(np.float64) if img.shape[-1] >= 3 else img[..., 0].astype(np.float64)


class MirrorTake:
    """The mirror take of one capture, image by image (``image(cam, "room")``, ``image(cam, "bar07")``)."""

    def __init__(self, capture: CaptureOutput, use_windows: bool = True) -> None:
        self.capture = capture
        self.windows: dict[str, dict[str, list[dict]]] = {}
        self.native_size: tuple[int, int] | None = None
        index_path = capture.mirror_roi_index_path
        if use_windows and capture.has_mirror_roi_index():
            try:
                index = json.loads(index_path.read_text())
                self.native_size = (int(index["width"]), int(index["height"]))
                self.windows = {str(c): {str(n): list(w) for n, w in e.items()} for c, e in index["cameras"].items()}
            except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
                raise InputError(f"{index_path}: cannot read the mirror take's window index ({err}); remove it to "
                                 "use the full images only, or re-run capture") from err

    def has_windows(self, cam_name: str) -> bool:
        """Whether ``cam_name``'s images come from native windows (it has a ball window)."""
        return bool(self.windows.get(cam_name, {}).get("room"))

    def cameras(self, cams: dict[str, Camera], full_cams: dict[str, Camera]) -> dict[str, Camera]:
        """Per camera, the camera model at the resolution ``image`` serves.

        ``full_cams`` are the cameras at the full images' resolution; cameras with windows
        are rescaled to the native size (``Camera.scaled`` keeps the pixel-centre convention).
        """
        out = {}
        for name, cam in full_cams.items():
            if not self.has_windows(name):
                out[name] = cam
                continue
            w, h = self.native_size
            scaled = cams[name].scaled(w / cams[name].width)
            if (scaled.width, scaled.height) != (w, h):
                raise InputError(f"{self.capture.mirror_roi_index_path}: native size {w}x{h}, but camera "
                                 f"{name} is calibrated at {cams[name].width}x{cams[name].height} (another aspect "
                                 "ratio); the windows do not match the camera")
            out[name] = scaled
        return out

    def image(self, cam_name: str, name: str) -> tuple[np.ndarray, float, float] | None:
        """(grey image [H, W], background, noise sigma) of ``calib/mirror/<cam>/<name>.exr``; None if absent."""
        path = self.capture.mirror_image_path(cam_name, f"{name}.exr")
        if not path.is_file():
            return None
        full = read_grey(path)
        bg, sigma = background_and_noise(full)
        if not self.has_windows(cam_name):
            return full, bg, sigma
        w, h = self.native_size
        canvas = np.full((h, w), bg)
        for win in self.windows[cam_name].get(name, []):
            wpath = self.capture.mirror_roi_image_path(cam_name, str(win["file"]))
            x0, y0, x1, y1 = (int(v) for v in win["box"])
            crop = read_grey(wpath)
            if crop.shape != (y1 - y0, x1 - x0) or x0 < 0 or y0 < 0 or x1 > w or y1 > h:
                raise InputError(f"{wpath}: window is {crop.shape[1]}x{crop.shape[0]} px, but mirror_roi.json "
                                 f"gives the box {[x0, y0, x1, y1]} in a {w}x{h} image; re-run capture")
            canvas[y0:y1, x0:x1] = crop
        return canvas, bg, sigma
