"""A contact sheet of mattes: rows are frames (full-on and OLAT alternating), columns cameras."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from scene.contact_sheet import tile_grid

TILE_HEIGHT_PX = 96


def pick_frames(manifest: dict[str, Any], available: set[int], count: int) -> list[int]:
    """Up to ``count`` frame indices spread over the capture, alternating F and OLAT frames."""
    frames = [f for f in manifest["frames"] if int(f["index"]) in available]
    full_on = [int(f["index"]) for f in frames if f.get("light") == "F"]
    olat = [int(f["index"]) for f in frames if f.get("light") != "F"]
    picks: list[int] = []
    for k in range(count):
        pool = full_on if (k % 2 == 0 and full_on) or not olat else olat
        position = (k // 2 + 0.5) / max((count + 1) // 2, 1)
        choice = pool[min(int(position * len(pool)), len(pool) - 1)]
        if choice not in picks:
            picks.append(choice)
    return sorted(picks)


def write_contact_sheet(path: Path, manifest: dict[str, Any], mattes: dict[str, dict[int, Path]], rows: int) -> None:
    """Write an 8-bit grid of the mattes in ``mattes[cam][index]`` (paths of 16-bit PNGs)."""
    from scene.image_io import read_png16, write_png8

    cams = [cam for cam in manifest["cameras"] if mattes.get(cam)]
    if not cams:
        return
    available = set.intersection(*(set(mattes[cam]) for cam in cams))
    indices = pick_frames(manifest, available, rows)
    width = int(round(TILE_HEIGHT_PX * float(manifest["width"]) / float(manifest["height"])))
    tiles = []
    for index in indices:
        for cam in cams:
            alpha = read_png16(mattes[cam][index])
            tile = cv2.resize(alpha, (width, TILE_HEIGHT_PX), interpolation=cv2.INTER_AREA)
            tiles.append(np.round(np.clip(tile, 0, 1) * 255).astype(np.uint8))
    # Thin separators so the tiles of a black backdrop stay readable.
    grid = tile_grid(tiles, len(cams), rows=max(len(indices), 1), cell=(TILE_HEIGHT_PX, width), separator=64)
    write_png8(path, grid)
