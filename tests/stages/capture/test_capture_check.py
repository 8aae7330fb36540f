"""``stages.capture.check`` on small hand-made capture folders: one problem per fault, each naming its file."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from pipeline.errors import InputError
from pipeline.testing import run_stage_for_test
from scene.image_io import write_exr
from stages.capture.check import check_capture
from stages.capture.check_cli import main as check_main
from stages.capture.stage import STAGE as CAPTURE

LIGHTS = ["F", 3, 7, "F", 1, 9, "F", 4, 2] * 2
LEVEL = {"F": 1.0, 3: 0.05, 7: 0.11, 1: 0.03, 9: 0.08, 4: 0.14, 2: 0.06}
FPS = 24.0


def _folder(root: Path, cameras: tuple[str, ...] = ("camA", "camB")) -> Path:
    """A complete capture folder: constant images whose brightness tells their light, time stamps."""
    root.mkdir(parents=True)
    (root / "capture.json").write_text(json.dumps({"subject": "real", "fps": FPS, "bars": 10, "cameras": list(cameras),
                                                   "takes": [{"name": "rom", "frames": len(LIGHTS)}]}))
    entries = [{"pulse": i, "light": light, "time_us": int(round(i / FPS * 1e6))} for i, light in enumerate(LIGHTS)]
    (root / "controller_log.json").write_text(json.dumps({"entries": entries}))
    for c, cam in enumerate(cameras):
        folder = root / "cameras" / cam
        folder.mkdir(parents=True)
        for i, light in enumerate(LIGHTS):
            write_exr(folder / f"{i:06d}.exr", np.full((6, 5, 3), LEVEL[light] * (1 + 0.2 * c), np.float32))
        (folder / "timestamps.json").write_text(json.dumps([i / FPS for i in range(len(LIGHTS))]))
    return root


def _lines(root: Path) -> list[str]:
    return [p.line() for p in check_capture(root)]


def test_a_complete_folder_has_no_problem_and_the_command_exits_0(tmp_path: Path, capsys) -> None:
    root = _folder(tmp_path / "cap")
    assert check_capture(root) == []
    assert check_main([str(root)]) == 0
    assert "imports: 2 cameras, 36 images, 18 controller log entries at 24 fps" in capsys.readouterr().out


def test_every_fault_is_one_line_naming_its_file(tmp_path: Path) -> None:
    root = _folder(tmp_path / "cap", cameras=("camA", "camB", "camC"))
    info = json.loads((root / "capture.json").read_text())
    info["cameras"] = ["camA", "camB", "camC", "camD"]  # camD listed, no folder
    (root / "capture.json").write_text(json.dumps(info))
    (root / "cameras" / "camX").mkdir()  # a folder not listed, and empty
    (root / "cameras" / "camA" / "000004.exr").write_bytes(b"broken")
    px = np.zeros((6, 5), np.uint32)
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {"R": px, "G": px, "B": px}) as exr:
        exr.write(str(root / "cameras" / "camB" / "000005.exr"))
    write_exr(root / "cameras" / "camB" / "000006.exr", np.ones((7, 5, 3), np.float32))
    stamps = [i / FPS for i in range(len(LIGHTS))]
    stamps[9], stamps[10] = stamps[10], stamps[9]
    (root / "cameras" / "camC" / "timestamps.json").write_text(json.dumps(stamps))
    log = json.loads((root / "controller_log.json").read_text())
    del log["entries"][12]
    (root / "controller_log.json").write_text(json.dumps(log))
    lines = _lines(root)
    expected = {
        "cameras/camD: missing: capture.json lists this camera",
        "cameras/camX: not a camera of capture.json's 'cameras'",
        "cameras/camX: no .exr images",
        "cameras/camA/000004.exr: not a readable EXR image",
        "cameras/camB/000005.exr: channel(s) B, G, R hold uint32 values, not linear float",
        "cameras/camB/000006.exr: image is 5x7, cameras/camA/000000.exr is 5x6",
        "cameras/camC/timestamps.json: time stamps out of order: image 10",
        "controller_log.json: no entry for frame(s) 12: the controller did not act on those triggers",
    }
    for start in expected:
        assert sum(line.startswith(start) for line in lines) == 1, (start, lines)
    assert len(lines) == len(expected), lines


def test_a_missing_image_names_the_camera_and_the_index(tmp_path: Path, capsys) -> None:
    root = _folder(tmp_path / "cap")
    (root / "cameras" / "camB" / "000013.exr").unlink()
    (root / "cameras" / "camB" / "timestamps.json").unlink()
    lines = _lines(root)
    assert lines == ["cameras/camB: 17 images, camA has 18: missing 000013.exr (index 13), which camA has; restore "
                     "it from the camera, or import without it (it would import with these frames dropped)"]
    assert check_main([str(root)]) == 1
    assert "camB" in capsys.readouterr().out
    # The importer takes it, the frame set aside as dropped; --allow-gaps says so.
    assert check_main([str(root), "--allow-gaps"]) == 0
    out = run_stage_for_test(CAPTURE, tmp_path / "w", params={"source": str(root)})
    frames = json.loads((out / "manifest.json").read_text())["frames"]
    assert [f["index"] for f in frames if f["status"] == "dropped"] == [13]


def test_links_out_of_the_folder_and_bad_json_block_the_import(tmp_path: Path) -> None:
    root = _folder(tmp_path / "cap")
    outside = tmp_path / "elsewhere.exr"
    write_exr(outside, np.ones((6, 5, 3), np.float32))
    first = root / "cameras" / "camA" / "000000.exr"
    first.unlink()
    os.symlink(outside, first)
    (root / "capture.json").write_text("{fps: 24")
    lines = _lines(root)
    assert any(line.startswith("cameras/camA/000000.exr: leads outside the capture folder") for line in lines)
    assert any(line.startswith("capture.json: not valid JSON") for line in lines)
    with pytest.raises(InputError, match=r"(?s)cannot be imported \(2 problem.*capture.json: not valid JSON.*"
                                         r"000000.exr: leads outside"):
        run_stage_for_test(CAPTURE, tmp_path / "w", params={"source": str(root)})


def test_the_rig_file_is_checked_against_the_folder(tmp_path: Path) -> None:
    root = _folder(tmp_path / "cap")
    info = json.loads((root / "capture.json").read_text())
    del info["cameras"], info["bars"]
    (root / "capture.json").write_text(json.dumps(info))
    rig = {"width_px": 5, "height_px": 6, "fps": FPS, "cameras": [{"name": "camA", "focal_px": 9.0}, "camB"],
           "bars": [{"id": i} for i in range(10)]}
    (root / "rig.yaml").write_text(json.dumps(rig))  # JSON is YAML
    assert check_capture(root) == []
    rig.update(cameras=["camA", "camC"], fps=30, width_px=6, height_px=5, bars=[{"id": i} for i in range(5)])
    (root / "rig.yaml").write_text(json.dumps(rig))
    lines = _lines(root)
    expected = {
        "rig.yaml: 'fps' is 30, capture.json says 24: make them agree",
        "cameras/camC: missing: rig.yaml lists this camera",
        "cameras/camB: not a camera of rig.yaml's 'cameras' (camA, camC)",
        "controller_log.json: entry 2: 'light' must be \"F\" or a bar id 0..4, got 7",
        "cameras/camA/000000.exr: image is 5x6, rig.yaml says the sensors are 6x5 (another aspect ratio)",
    }
    for start in expected:
        assert sum(line.startswith(start) for line in lines) == 1, (start, lines)
    assert len(lines) == len(expected), lines
    (root / "rig.yaml").write_text("cameras: camA\n")
    assert [line.split(":")[0] for line in _lines(root)] == ["rig.yaml"]


def test_usage_and_a_missing_folder(tmp_path: Path, capsys) -> None:
    assert check_main([str(tmp_path / "nope")]) == 1
    assert "not a folder" in capsys.readouterr().out
    assert check_main([]) == 2
