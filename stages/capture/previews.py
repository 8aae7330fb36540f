"""Previews a person can look at: a contact sheet (one frame, every camera) and a strip."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from scene.colour import srgb8
from scene.contact_sheet import label_tile, tile_grid
from scene.image_io import write_png8


def _to_srgb8(img: np.ndarray, exposure: float, text: str) -> np.ndarray:
    """Linear [H, W, 3] -> labelled 8-bit sRGB (RGB order)."""
    return label_tile(np.ascontiguousarray(srgb8(img, exposure)), text)


def contact_sheet(path: Path, images: Sequence[np.ndarray], names: Sequence[str], columns: int = 5,
                  exposure: float = 1.0) -> None:
    """Tile linear images [H, W, 3] (one per camera) into an sRGB PNG, each labelled with its name."""
    tiles = [_to_srgb8(img, exposure, name) for img, name in zip(images, names)]
    write_png8(path, tile_grid(tiles, columns, cell=images[0].shape[:2]))


def strip(path: Path, images: Sequence[np.ndarray], labels: Sequence[str], full_on_exposure: float = 1.0,
          olat_exposure: float = 8.0) -> None:
    """A row of consecutive frames of one camera; OLAT frames shown with ``olat_exposure``."""
    tiles = [_to_srgb8(img, full_on_exposure if label.startswith("F") else olat_exposure, label)
             for img, label in zip(images, labels)]
    write_png8(path, tile_grid(tiles, len(tiles)))
