"""One sRGB PNG writer and one contact-sheet helper: every caller writes the bytes it wrote before.

Each ``_old_*`` function is the caller's implementation from before the unification, kept
verbatim (minus its file writing where the bytes are compared through the new writer), as the
oracle: capture's contact sheet and strip, track's overlay sheet, matte's matte sheet and
``write_png_srgb``.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from scene.colour import srgb8, srgb_encode
from scene.contact_sheet import tile_grid
from scene.image_io import write_png16, write_png8, write_png_srgb


# ---- the implementations before (oracles) ----------------------------------------------------

def _old_write_png_srgb(path, linear_rgb, exposure=1.0):
    img = srgb_encode(np.asarray(linear_rgb, dtype=np.float32) * exposure)
    img8 = np.round(img * 255.0).astype(np.uint8)
    if img8.ndim == 3 and img8.shape[2] == 3:
        img8 = img8[..., ::-1]
    assert cv2.imwrite(str(path), np.ascontiguousarray(img8))


def _old_capture_to_srgb8(img, exposure, text):
    out = np.ascontiguousarray(np.round(srgb_encode(img * exposure) * 255).astype(np.uint8))
    scale = max(0.3, img.shape[0] / 700)
    cv2.putText(out, text, (3, int(18 * scale) + 2), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1,
                cv2.LINE_AA)
    return out


def _old_capture_write(path, rgb8):
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb8[..., ::-1]))


def _old_capture_contact_sheet(path, images, names, columns=5, exposure=1.0):
    h, w = images[0].shape[:2]
    rows = (len(images) + columns - 1) // columns
    sheet = np.zeros((rows * h, columns * w, 3), np.uint8)
    for k, (img, name) in enumerate(zip(images, names)):
        r, c = divmod(k, columns)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = _old_capture_to_srgb8(img, exposure, name)
    _old_capture_write(path, sheet)


def _old_capture_strip(path, images, labels, full_on_exposure=1.0, olat_exposure=8.0):
    tiles = [_old_capture_to_srgb8(img, full_on_exposure if label.startswith("F") else olat_exposure, label)
             for img, label in zip(images, labels)]
    _old_capture_write(path, np.concatenate(tiles, axis=1))


def _old_track_contact_sheet(tiles, columns, tile_width=320):
    if not tiles:
        return np.zeros((8, 8, 3), np.uint8)
    resized = []
    for tile in tiles:
        h, w = tile.shape[:2]
        resized.append(cv2.resize(tile, (tile_width, max(1, int(round(h * tile_width / w)))),
                                  interpolation=cv2.INTER_AREA))
    tile_h = max(t.shape[0] for t in resized)
    rows = (len(resized) + columns - 1) // columns
    sheet = np.zeros((rows * tile_h, columns * tile_width, 3), np.uint8)
    for k, tile in enumerate(resized):
        r, c = divmod(k, columns)
        sheet[r * tile_h: r * tile_h + tile.shape[0], c * tile_width: (c + 1) * tile_width] = tile
    return sheet


def _old_track_label(canvas_rgb, label):
    canvas = np.ascontiguousarray(canvas_rgb[..., ::-1])
    cv2.putText(canvas, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return canvas[..., ::-1]


def _old_track_write(path, image_rgb):
    assert cv2.imwrite(str(path), np.ascontiguousarray(image_rgb[..., ::-1]))


def _old_matte_sheet(path, manifest, mattes, rows):
    from scene.image_io import read_png16
    from stages.matte.contact_sheet import TILE_HEIGHT_PX, pick_frames

    cams = [cam for cam in manifest["cameras"] if mattes.get(cam)]
    if not cams:
        return
    available = set.intersection(*(set(mattes[cam]) for cam in cams))
    indices = pick_frames(manifest, available, rows)
    width = int(round(TILE_HEIGHT_PX * float(manifest["width"]) / float(manifest["height"])))
    grid = np.zeros((max(len(indices), 1) * TILE_HEIGHT_PX, len(cams) * width), np.uint8)
    for row, index in enumerate(indices):
        for col, cam in enumerate(cams):
            alpha = read_png16(mattes[cam][index])
            tile = cv2.resize(alpha, (width, TILE_HEIGHT_PX), interpolation=cv2.INTER_AREA)
            grid[row * TILE_HEIGHT_PX:(row + 1) * TILE_HEIGHT_PX, col * width:(col + 1) * width] = \
                np.round(np.clip(tile, 0, 1) * 255).astype(np.uint8)
    grid[:, ::width] = 64
    grid[::TILE_HEIGHT_PX, :] = 64
    cv2.imwrite(str(path), grid)


# ---- sample inputs ---------------------------------------------------------------------------

def _linear(rng, h, w, scale=1.0, dtype=np.float32):
    # HDR-ish: a few values above 1 and below 0, as renders with noise have.
    return (rng.gamma(0.8, 0.4, size=(h, w, 3)) * scale - 0.01).astype(dtype)


@pytest.mark.parametrize("exposure", [1.0, 0.37, np.float64(2.5)])
@pytest.mark.parametrize("shape", [(17, 23, 3), (9, 11)])
def test_write_png_srgb_bytes_unchanged(tmp_path: Path, exposure, shape) -> None:
    rng = np.random.default_rng(1)
    img = (rng.gamma(0.8, 0.4, size=shape) - 0.01).astype(np.float32)
    _old_write_png_srgb(tmp_path / "old.png", img, exposure)
    write_png_srgb(tmp_path / "new.png", img, exposure)
    assert (tmp_path / "old.png").read_bytes() == (tmp_path / "new.png").read_bytes()
    # float64 input, as train's preview rows are after .numpy() on float64 tensors
    _old_write_png_srgb(tmp_path / "old64.png", img.astype(np.float64), exposure)
    write_png_srgb(tmp_path / "new64.png", img.astype(np.float64), exposure)
    assert (tmp_path / "old64.png").read_bytes() == (tmp_path / "new64.png").read_bytes()


def test_srgb8_matches_the_old_inline_quantisers() -> None:
    rng = np.random.default_rng(2)
    img = _linear(rng, 31, 29)
    for exposure in (1.0, 0.6 / 0.83, 8.0):
        old = np.round(srgb_encode(img * exposure) * 255).astype(np.uint8)
        assert np.array_equal(srgb8(img, exposure), old)


def test_track_detector_image_unchanged() -> None:
    from stages.track.landmarks import DetectorParams, to_detector_image

    rng = np.random.default_rng(7)
    linear = _linear(rng, 40, 30, scale=0.2)
    linear[3, 4, 1] = np.nan
    params = DetectorParams()
    rgb = np.nan_to_num(linear, nan=0.0, posinf=0.0, neginf=0.0)
    from scene.colour import luminance

    level = float(np.percentile(luminance(np.maximum(rgb, 0.0)), params.exposure_percentile))
    old = np.round(srgb_encode(rgb * (params.exposure_target / level)) * 255.0).astype(np.uint8)
    assert np.array_equal(to_detector_image(linear, params), old)


@pytest.mark.parametrize("size,columns,count", [((64, 48), 5, 7), ((256, 192), 5, 5), ((40, 30), 3, 2)])
def test_capture_contact_sheet_and_strip_bytes_unchanged(tmp_path: Path, size, columns, count) -> None:
    from stages.capture.previews import contact_sheet, strip

    rng = np.random.default_rng(3)
    images = [_linear(rng, *size) for _ in range(count)]
    names = [f"cam{k:02d} #12 F" for k in range(count)]
    exposure = 0.6 / max(float(np.percentile(np.concatenate([i.reshape(-1, 3) for i in images]), 99)), 1e-6)
    _old_capture_contact_sheet(tmp_path / "old_sheet.png", images, names, columns=columns, exposure=exposure)
    contact_sheet(tmp_path / "new_sheet.png", images, names, columns=columns, exposure=exposure)
    assert (tmp_path / "old_sheet.png").read_bytes() == (tmp_path / "new_sheet.png").read_bytes()

    labels = [("F" if k % 3 == 0 else f"L{k}") + f" #{k}" for k in range(count)]
    _old_capture_strip(tmp_path / "old_strip.png", images, labels, exposure, exposure * 10)
    strip(tmp_path / "new_strip.png", images, labels, full_on_exposure=exposure, olat_exposure=exposure * 10)
    assert (tmp_path / "old_strip.png").read_bytes() == (tmp_path / "new_strip.png").read_bytes()


@pytest.mark.parametrize("tile_width,columns", [(320, 3), (61, 2), (100, 4)])
def test_track_overlay_sheet_bytes_unchanged(tmp_path: Path, tile_width, columns) -> None:
    from stages.track.overlay import contact_sheet

    rng = np.random.default_rng(4)
    shapes = [(80, 60), (80, 60), (120, 90), (70, 100), (80, 60)]
    tiles = [rng.integers(0, 256, size=(*s, 3), dtype=np.uint8) for s in shapes]
    old = _old_track_contact_sheet(tiles, columns, tile_width)
    new = contact_sheet(tiles, columns, tile_width)
    assert new.dtype == old.dtype and np.array_equal(new, old)
    assert np.array_equal(contact_sheet([], columns, tile_width), _old_track_contact_sheet([], columns, tile_width))
    _old_track_write(tmp_path / "old.png", old)
    write_png8(tmp_path / "new.png", new)
    assert (tmp_path / "old.png").read_bytes() == (tmp_path / "new.png").read_bytes()


def test_track_view_label_unchanged() -> None:
    from scene.contact_sheet import label_tile

    rng = np.random.default_rng(5)
    image = rng.integers(0, 256, size=(60, 80, 3), dtype=np.uint8)
    old = _old_track_label(image, "cam01 frame 12")
    canvas = np.ascontiguousarray(image[..., ::-1])
    label_tile(canvas, "cam01 frame 12", scale=0.4, origin=(4, 14))
    assert np.array_equal(canvas[..., ::-1], old)


@pytest.mark.parametrize("rows", [0, 3, 4])
def test_matte_contact_sheet_bytes_unchanged(tmp_path: Path, rows) -> None:
    from stages.matte.contact_sheet import write_contact_sheet

    rng = np.random.default_rng(6)
    cams, frames = ["cam00", "cam01", "cam02"], list(range(6))
    manifest = {"cameras": cams, "width": 60, "height": 80,
                "frames": [{"index": i, "light": "F" if i % 2 == 0 else i} for i in frames]}
    mattes: dict[str, dict[int, Path]] = {}
    for cam in cams:
        mattes[cam] = {}
        for i in frames:
            path = tmp_path / f"{cam}_{i}.png"
            write_png16(path, rng.random((80, 60)))
            mattes[cam][i] = path
    _old_matte_sheet(tmp_path / "old.png", manifest, mattes, rows)
    write_contact_sheet(tmp_path / "new.png", manifest, mattes, rows)
    assert (tmp_path / "old.png").read_bytes() == (tmp_path / "new.png").read_bytes()


def test_tile_grid_layout() -> None:
    a = np.full((2, 3), 10, np.uint8)
    b = np.full((1, 2), 20, np.uint8)
    sheet = tile_grid([a, b, a], 2, fill=5)
    assert sheet.shape == (4, 6)
    assert (sheet[:2, :3] == 10).all() and (sheet[0, 3:5] == 20).all() and sheet[1, 3] == 5
    assert (sheet[2:, :3] == 10).all() and (sheet[2:, 3:] == 5).all()
    empty = tile_grid([], 3, rows=1, cell=(4, 5), separator=64)
    assert empty.shape == (4, 15) and empty[0, 7] == 64 and empty[1, 5] == 64 and empty[1, 6] == 0
    with pytest.raises(ValueError):
        tile_grid([], 2)
    with pytest.raises(ValueError, match="uint8"):
        write_png8("unused.png", np.zeros((2, 2), np.float32))
