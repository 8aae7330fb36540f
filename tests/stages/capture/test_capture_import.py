"""Importing a real capture folder: labelling, hard links instead of copies, refusing escapes."""

import json
import os

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.testing import run_stage_for_test
from scene.image_io import write_exr
from stages.capture.stage import STAGE as CAPTURE

PATTERN = ["F", 3, 7, "F", 1, 9, "F", 4, 2]
BRIGHTNESS = {"F": 1.0, 3: 0.05, 7: 0.11, 1: 0.03, 9: 0.08, 4: 0.14, 2: 0.06}


def _make_source(root, drop=None, cycles=3):
    """A capture folder: 2 cameras, constant images whose brightness tells their light."""
    root.mkdir(parents=True)
    rng = np.random.default_rng(0)
    lights = PATTERN * cycles
    fps = 24.0
    (root / "capture.json").write_text(json.dumps({"subject": "real", "fps": fps, "bars": 10,
                                                   "takes": [{"name": "rom", "frames": len(lights)}]}))
    entries = [{"pulse": i, "cycle": i // len(PATTERN), "step": i % len(PATTERN), "light": light,
                "time_us": int(round(i / fps * 1e6))} for i, light in enumerate(lights)]
    (root / "controller_log.json").write_text(json.dumps({"entries": entries}))
    for c, cam in enumerate(("camA", "camB")):
        folder = root / "cameras" / cam
        folder.mkdir(parents=True)
        k = 0
        for i, light in enumerate(lights):
            if drop and drop == (cam, i):
                continue
            value = BRIGHTNESS[light] * (1 + 0.2 * c) * (1 + 0.003 * rng.standard_normal())
            write_exr(folder / f"{k:06d}.exr", np.full((6, 5, 3), value, np.float32), half=False)
            k += 1
    return lights


def test_import_labels_and_links(tmp_path):
    src = tmp_path / "src"
    lights = _make_source(src, drop=("camB", 13))
    out = run_stage_for_test(CAPTURE, tmp_path / "w", params={"source": str(src)})
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["subject"] == "real" and manifest["cameras"] == ["camA", "camB"]
    assert (manifest["width"], manifest["height"]) == (5, 6)
    frames = manifest["frames"]
    assert [f["light"] for f in frames] == lights
    assert [f["index"] for f in frames if f["status"] == "dropped"] == [13]
    assert frames[13]["missing_cameras"] == ["camB"]
    # camB's frame 14 arrived as its 13th image: relabelled, and hard-linked (not copied).
    linked = out / "frames" / "camB" / "000014.exr"
    assert linked.stat().st_ino == (src / "cameras" / "camB" / "000013.exr").stat().st_ino
    assert not (out / "frames" / "camB" / "000013.exr").exists()
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == len(lights) and metrics["dropped_frames"] == 1 and metrics["cameras"] == 2


def test_import_refuses_links_outside_the_folder(tmp_path):
    src = tmp_path / "src"
    _make_source(src)
    outside = tmp_path / "secret.exr"
    write_exr(outside, np.ones((6, 5, 3), np.float32))
    first = src / "cameras" / "camA" / "000000.exr"
    first.unlink()
    os.symlink(outside, first)
    with pytest.raises(InputError, match="outside the capture folder"):
        run_stage_for_test(CAPTURE, tmp_path / "w", params={"source": str(src)})


def test_import_reports_bad_files(tmp_path):
    src = tmp_path / "src"
    _make_source(src)
    (src / "cameras" / "camA" / "000004.exr").write_bytes(b"broken")
    with pytest.raises(InputError, match="000004.exr"):
        run_stage_for_test(CAPTURE, tmp_path / "w", params={"source": str(src)})
    with pytest.raises(ValueError, match="not a folder"):
        run_stage_for_test(CAPTURE, tmp_path / "w2", params={"source": str(tmp_path / "nope")})
