"""Previews a person can look at: a contact sheet (one frame, every camera) and a strip."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from scene.colour import srgb_encode


def _to_srgb8(img: np.ndarray, exposure: float, text: str) -> np.ndarray:
    """Linear [H, W, 3] -> labelled 8-bit sRGB (RGB order)."""
    import cv2

    out = np.ascontiguousarray(np.round(srgb_encode(img * exposure) * 255).astype(np.uint8))
    scale = max(0.3, img.shape[0] / 700)
    cv2.putText(out, text, (3, int(18 * scale) + 2), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1,
                cv2.LINE_AA)
    return out


def _write(path: Path, rgb8: np.ndarray) -> None:
    import cv2

    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb8[..., ::-1])):
        raise ValueError(f"{path}: could not write PNG")


def contact_sheet(path: Path, images: Sequence[np.ndarray], names: Sequence[str], columns: int = 5,
                  exposure: float = 1.0) -> None:
    """Tile linear images [H, W, 3] (one per camera) into an sRGB PNG, each labelled with its name."""
    h, w = images[0].shape[:2]
    rows = (len(images) + columns - 1) // columns
    sheet = np.zeros((rows * h, columns * w, 3), np.uint8)
    for k, (img, name) in enumerate(zip(images, names)):
        r, c = divmod(k, columns)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = _to_srgb8(img, exposure, name)
    _write(path, sheet)


def strip(path: Path, images: Sequence[np.ndarray], labels: Sequence[str], full_on_exposure: float = 1.0,
          olat_exposure: float = 8.0) -> None:
    """A row of consecutive frames of one camera; OLAT frames shown with ``olat_exposure``."""
    tiles = [_to_srgb8(img, full_on_exposure if label.startswith("F") else olat_exposure, label)
             for img, label in zip(images, labels)]
    _write(path, np.concatenate(tiles, axis=1))
