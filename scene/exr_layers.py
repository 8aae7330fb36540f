"""Multi-part EXR files: several linear images in one file, each part a layer of its own (OpenEXR 3.x).

A module of its own, beside ``scene.image_io``: only what writes layered files imports it, so
it does not join the code digest of every stage that reads or writes an image.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def write_multipart_exr(path: str | Path, parts: list[tuple[str, np.ndarray, dict]], half: bool = True) -> None:
    """Several linear images in one multi-part EXR (ZIP), each part a layer of its own.

    ``parts``: ``(name, image [H, W, 3 or 4], attributes)``; the part is called ``name`` and its
    channels ``name.R``, ``name.G``, ``name.B`` (and ``name.A``), unique across the file as
    compositors flattening parts into layers expect. ``attributes`` go into the part's
    header (str, int, float, or a float32 array of 3 for a V3f). ``half`` as ``write_exr``.
    """
    import OpenEXR

    exr_parts = []
    for name, img, attributes in parts:
        arr = np.asarray(img, dtype=np.float32)
        if arr.ndim != 3 or arr.shape[2] not in (3, 4):
            raise ValueError(f"{path}: part {name}: expected an image [H, W, 3 or 4], got shape {arr.shape}")
        if half:
            arr = np.clip(arr, -65504.0, 65504.0).astype(np.float16)
        channels = {f"{name}.{c}": np.ascontiguousarray(arr[..., i]) for i, c in enumerate("RGBA"[:arr.shape[2]])}
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **attributes}
        exr_parts.append(OpenEXR.Part(header, channels, name=name))
    if not exr_parts:
        raise ValueError(f"{path}: a multi-part EXR needs at least one part")
    OpenEXR.File(exr_parts).write(str(path))


__all__ = ["write_multipart_exr"]
