"""What the calibrate stage needs to know of the capture: its cameras and the performance images' size."""

from __future__ import annotations

from pipeline.errors import InputError
from scene.camera import Camera
from stages.capture.output import CaptureOutput


def performance_size(capture: CaptureOutput) -> tuple[int, int] | None:
    """(width, height) of the performance images from the capture's manifest; None when it does not say."""
    if not capture.has_manifest():
        return None
    d = capture.manifest()
    try:
        return (int(d["width"]), int(d["height"])) if "width" in d and "height" in d else None
    except (ValueError, TypeError) as err:
        raise capture.malformed(capture.manifest_path, f"bad width/height ({err})") from err


def to_performance_resolution(cam: Camera, size: tuple[int, int] | None) -> Camera:
    """``cam`` (calibrated at its board images' resolution) at the performance resolution ``size``."""
    if size is None or size == (cam.width, cam.height):
        return cam
    factor = size[0] / cam.width
    scaled = cam.scaled(factor)
    if (scaled.width, scaled.height) != size:
        raise InputError(f"camera {cam.name}: board images are {cam.width}x{cam.height} but the performance images "
                         f"are {size[0]}x{size[1]} (the capture manifest), not the same aspect ratio; the calibration "
                         "take must be shot with the performance's sensor crop")
    return scaled


def capture_cameras(capture: CaptureOutput) -> list[str]:
    """The cameras the capture recorded (its manifest), else those with board takes."""
    if capture.has_manifest():
        return [str(c) for c in capture.manifest(keys=("cameras",))["cameras"]]
    return capture.charuco_cameras()
