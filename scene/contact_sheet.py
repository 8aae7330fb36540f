"""One contact-sheet helper: tile 8-bit images into a grid, and label a tile.

Used by capture's contact sheet and strip, track's overlay sheet and matte's matte sheet.
The layout is plain: cell ``k`` is row ``k // columns``, column ``k % columns``; a tile sits
in the top-left corner of its cell; the rest of the sheet is ``fill``.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np


def label_tile(tile: np.ndarray, text: str, *, scale: float | None = None,
               origin: tuple[int, int] | None = None, colour: tuple[int, int, int] = (255, 255, 255)) -> np.ndarray:
    """Draw ``text`` on a uint8 tile in place (OpenCV Hershey simplex, anti-aliased) and return it.

    ``scale`` defaults to the tile's height / 700 (at least 0.3), ``origin`` (the text's
    bottom-left, pixels) to ``(3, int(18 * scale) + 2)``: readable at any tile size.
    The tile must be C-contiguous.
    """
    import cv2

    if scale is None:
        scale = max(0.3, tile.shape[0] / 700)
    if origin is None:
        origin = (3, int(18 * scale) + 2)
    cv2.putText(tile, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)
    return tile


def resize_to_width(tile: np.ndarray, width: int) -> np.ndarray:
    """A tile resized (area filter) to ``width`` pixels, its aspect kept (height rounded, at least 1)."""
    import cv2

    h, w = tile.shape[:2]
    return cv2.resize(tile, (width, max(1, int(round(h * width / w)))), interpolation=cv2.INTER_AREA)


def tile_grid(tiles: Sequence[np.ndarray], columns: int, *, rows: int | None = None,
              cell: tuple[int, int] | None = None, fill: int = 0, separator: int | None = None) -> np.ndarray:
    """Tiles (uint8, all grey [H, W] or all RGB [H, W, 3], sizes may differ) laid out in a grid.

    Args:
        tiles: in reading order (row by row).
        columns: cells per row.
        rows: rows of the sheet (default: as many as the tiles need); give it to keep an
            empty sheet's size.
        cell: (height, width) of a cell; default the largest tile height and width.
        fill: value of the sheet where no tile lies.
        separator: if set, every cell's first row and first column get this value (thin grid
            lines that keep tiles of a black backdrop apart).
    """
    if cell is None:
        if not tiles:
            raise ValueError("tile_grid: no tiles and no cell size")
        cell = (max(t.shape[0] for t in tiles), max(t.shape[1] for t in tiles))
    cell_h, cell_w = cell
    if rows is None:
        rows = (len(tiles) + columns - 1) // columns
    channels = tiles[0].shape[2:] if tiles else ()
    sheet = np.full((rows * cell_h, columns * cell_w, *channels), fill, np.uint8)
    for k, tile in enumerate(tiles):
        r, c = divmod(k, columns)
        sheet[r * cell_h: r * cell_h + tile.shape[0], c * cell_w: c * cell_w + tile.shape[1]] = tile
    if separator is not None:
        sheet[:, ::cell_w] = separator
        sheet[::cell_h, :] = separator
    return sheet
