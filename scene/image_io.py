"""Image files: linear float EXR (OpenEXR 3.x), sRGB PNG previews, 16-bit PNG mattes.

OpenCV's wheel cannot read or write EXR, so EXR goes through the ``OpenEXR`` package.
Every reader raises ``ValueError`` naming the file when it is missing, truncated or not an
image of the expected kind (stages wrap it into ``InputError``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scene.colour import srgb8, srgb_decode

_CHANNEL_SETS = {1: ("Y",), 2: ("Y", "A"), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}


def write_exr(path: str | Path, img: np.ndarray, half: bool = True) -> None:
    """Write a linear image [H, W] or [H, W, C] (C in 1..4) as a ZIP-compressed EXR.

    ``half=True`` stores float16 (what a camera pipeline keeps), else float32. Values above
    the float16 range are clipped to its maximum, so a hot pixel never becomes ``inf``.
    """
    import OpenEXR

    arr = np.asarray(img, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3 or arr.shape[2] not in _CHANNEL_SETS:
        raise ValueError(f"{path}: cannot write an image of shape {arr.shape} as EXR; "
                         "expected [H, W] or [H, W, C] with C in 1..4")
    if half:
        arr = np.clip(arr, -65504.0, 65504.0).astype(np.float16)
    names = _CHANNEL_SETS[arr.shape[2]]
    channels = {name: np.ascontiguousarray(arr[..., i]) for i, name in enumerate(names)}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, channels) as exr:
        exr.write(str(path))


def read_exr_channels(path: str | Path, fix: str = "re-run the stage that writes it") -> dict[str, np.ndarray]:
    """Every channel of an EXR, name -> pixels [H, W] in the file's own type; ``ValueError`` naming the file.

    ``fix`` says what to do about a missing, truncated or corrupt file.
    """
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such EXR file; check the path or {fix}")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            channels = {name: np.asarray(ch.pixels) for name, ch in exr.channels().items()}
    except Exception as err:  # OpenEXR raises several exception types for bad files
        raise ValueError(f"{path}: not a readable EXR image ({err}); the file is corrupt or truncated, {fix}") from err
    if not channels:
        raise ValueError(f"{path}: EXR has no channels; {fix}")
    return channels


def stack_channels(path: str | Path, channels: dict[str, np.ndarray]) -> np.ndarray:
    """float32 [H, W, C] of R, G, B(, A) in that order, or Y(, A); other channel sets in sorted name order."""
    if {"R", "G", "B"} <= set(channels):
        order = ["R", "G", "B"] + (["A"] if "A" in channels else [])
    elif "Y" in channels:
        order = ["Y"] + (["A"] if "A" in channels else [])
    else:
        order = sorted(channels)
    if len({channels[n].shape for n in order}) != 1:
        raise ValueError(f"{path}: EXR channels have different sizes")
    return np.stack([channels[n].astype(np.float32) for n in order], axis=-1)


def read_exr(path: str | Path) -> np.ndarray:
    """Read an EXR into float32 [H, W, C]: channels R, G, B(, A) in that order, or Y(, A).

    Other channel sets come in sorted name order. Raises ``ValueError`` naming the file
    when it is missing, truncated or not an EXR.
    """
    return stack_channels(path, read_exr_channels(path))


def write_png8(path: str | Path, image: np.ndarray) -> None:
    """Write a uint8 image, RGB [H, W, 3] or grey [H, W], as a PNG (OpenCV's default compression).

    The one PNG writer of the project's 8-bit images; raises ``ValueError`` naming the file.
    """
    import cv2

    img8 = np.asarray(image)
    if img8.dtype != np.uint8:
        raise ValueError(f"{path}: write_png8 takes uint8 images, got {img8.dtype}")
    if img8.ndim == 3 and img8.shape[2] == 3:
        img8 = img8[..., ::-1]  # OpenCV writes BGR
    if not cv2.imwrite(str(path), np.ascontiguousarray(img8)):
        raise ValueError(f"{path}: could not write PNG (does the folder exist?)")


def write_png_srgb(path: str | Path, linear_rgb: np.ndarray, exposure: float = 1.0) -> None:
    """Write linear RGB [H, W, 3] (or grey [H, W]) times ``exposure`` as an 8-bit sRGB PNG."""
    write_png8(path, srgb8(linear_rgb, exposure))


def read_png(path: str | Path, linear: bool = False) -> np.ndarray:
    """Read an 8- or 16-bit PNG as float32 in [0, 1]: [H, W, 3] RGB or [H, W] grey.

    ``linear=True`` decodes sRGB to linear RGB. Raises ``ValueError`` naming the file.
    """
    import cv2

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such PNG file; check the path or re-run the stage that writes it")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ValueError(f"{path}: not a readable PNG image (corrupt or truncated); re-run the stage that writes it")
    scale = 65535.0 if raw.dtype == np.uint16 else 255.0
    img = raw.astype(np.float32) / scale
    if img.ndim == 3:
        img = img[..., :3][..., ::-1].copy()  # BGR(A) -> RGB
    return srgb_decode(img) if linear else img


def write_png16(path: str | Path, alpha: np.ndarray) -> None:
    """Write a matte [H, W] in [0, 1] (clipped) as a 16-bit grey PNG."""
    import cv2

    a = np.asarray(alpha, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError(f"{path}: a matte must be [H, W], got shape {a.shape}")
    a16 = np.round(np.clip(a, 0.0, 1.0) * 65535.0).astype(np.uint16)
    if not cv2.imwrite(str(path), a16):
        raise ValueError(f"{path}: could not write PNG (does the folder exist?)")


def read_png16(path: str | Path) -> np.ndarray:
    """Read a 16-bit (or 8-bit) grey matte PNG as float32 [H, W] in [0, 1]."""
    img = read_png(path)
    if img.ndim == 3:
        raise ValueError(f"{path}: expected a single-channel matte PNG, found {img.shape[2]} channels")
    return img
