"""``stages.capture.export`` / ``pipeline hw export-capture``: a virtual capture in the import layout
passes ``check-capture`` and imports through the capture stage to the same labelled manifest."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from pipeline.errors import InputError
from pipeline.testing import run_stage_for_test
from scene.rig import default_rig, load_rig
from stages.capture.check import check_capture
from stages.capture.check_cli import main as check_main
from stages.capture.export import export_capture
from stages.capture.stage import STAGE as CAPTURE
from stages.sequence.stage import STAGE as SEQUENCE

ROOT = Path(__file__).resolve().parents[3]
# Three cameras, 61x82 images, 12 frames, the smallest calibration takes: a few seconds.
SMALL = {"image_scale": 0.08, "texture_size": 64, "render": {"edge_samples": 2, "bar_samples": 1},
         "max_frames": 12, "identity_seed": 4, "calibration_poses": 2, "calibration_image_scale": 0.15,
         "calibration_mirror_windows": False}
MANIFEST_KEYS = ("subject", "fps", "width", "height", "cameras", "bars", "takes", "frames")


@pytest.fixture(scope="module")
def virtual_capture(tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("virtual")
    sequence = run_stage_for_test(SEQUENCE, work, params={"cycles": 1, "restarts": 1, "random_baseline_samples": 4})
    rig = default_rig()
    return run_stage_for_test(CAPTURE, work, inputs={"sequence": sequence},
                              params={**SMALL, "rig": rig.model_copy(update={"cameras": rig.cameras[:3]})},
                              subject="alice")


def test_the_export_checks_clean_and_imports_to_the_same_manifest(virtual_capture: Path, tmp_path: Path) -> None:
    summary = export_capture(virtual_capture, tmp_path / "export")
    assert (summary.cameras, summary.images, summary.log_entries) == (3, 36, 12)
    assert summary.calibration_files > 0
    assert check_capture(tmp_path / "export") == []
    imported = run_stage_for_test(CAPTURE, tmp_path / "w", params={"source": str(tmp_path / "export")},
                                  subject="someone-else")
    original = json.loads((virtual_capture / "manifest.json").read_text())
    again = json.loads((imported / "manifest.json").read_text())
    assert {k: again[k] for k in MANIFEST_KEYS} == {k: original[k] for k in MANIFEST_KEYS}
    # The images are the studio's own files (hard links), the calibration takes and scans came along.
    first = tmp_path / "export" / "cameras" / "cam02" / "000005.exr"
    assert first.stat().st_ino == (virtual_capture / "frames" / "cam02" / "000005.exr").stat().st_ino
    assert (imported / "frames" / "cam02" / "000005.exr").stat().st_ino == first.stat().st_ino
    calib = sorted(p.relative_to(virtual_capture).as_posix() for p in (virtual_capture / "calib").rglob("*")
                   if p.is_file())
    assert calib == sorted(p.relative_to(imported).as_posix() for p in (imported / "calib").rglob("*")
                           if p.is_file())
    assert (imported / "scans" / "scans.npz").is_file()


def test_a_deleted_image_and_a_link_outside_are_reported(virtual_capture: Path, tmp_path: Path, capsys) -> None:
    folder = tmp_path / "export"
    export_capture(virtual_capture, folder)
    (folder / "cameras" / "cam01" / "000007.exr").unlink()
    outside = tmp_path / "notes.json"
    outside.write_text("{}")
    os.symlink(outside, folder / "calib" / "notes.json")
    assert check_main([str(folder)]) == 1
    lines = capsys.readouterr().out.splitlines()
    assert any(line.startswith("cameras/cam01: 11 images, cam00 has 12: missing 000007.exr (index 7)")
               for line in lines), lines
    assert any(line.startswith("calib/notes.json: leads outside the capture folder") for line in lines), lines
    with pytest.raises(InputError, match="not an empty folder"):
        export_capture(virtual_capture, folder)


def _export_command(tmp_path: Path, subject: str, *extra: str, image_scale: float = 0.08) -> subprocess.CompletedProcess:
    """``pipeline hw export-capture`` at test size in a workspace root of its own."""
    small = {**SMALL, "image_scale": image_scale}
    sets = [f"capture.{key}={json.dumps(value)}" for key, value in small.items() if key != "render"]
    sets += ["capture.render.edge_samples=2", "capture.render.bar_samples=1", "sequence.cycles=1",
             "sequence.restarts=1", "sequence.random_baseline_samples=4"]
    env = dict(os.environ, PIPELINE_WORKSPACES=str(tmp_path / "ws"), PIPELINE_PROJECT_ROOT=str(ROOT))
    command = [sys.executable, "-m", "pipeline.cli", "hw", "export-capture", "-S", subject, "--out",
               str(tmp_path / "export"), "--workers", "1", *extra]
    return subprocess.run([*command, *(a for s in sets for a in ("--set", s))], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)


def test_a_subject_with_its_own_rig_exports_checks_and_imports(tmp_path: Path) -> None:
    """configs/subjects/studio6.yaml: 6 cameras, 20 bars, 30 fps, landscape, an F frame every 4th frame."""
    done = _export_command(tmp_path, "studio6", image_scale=0.25)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "6 cameras, 72 images, 12 controller log entries" in done.stdout
    folder = tmp_path / "export"
    info = json.loads((folder / "capture.json").read_text())
    assert (info["fps"], info["bars"], len(info["cameras"])) == (30.0, 20, 6)
    lights = [e["light"] for e in json.loads((folder / "controller_log.json").read_text())["entries"]]
    assert [i for i, light in enumerate(lights) if light == "F"] == [0, 4, 8]
    # The rig travels with the capture, in the form a subject's rig: line reads.
    assert load_rig(folder / "rig.yaml") == load_rig(ROOT / "configs" / "rigs" / "six_landscape.yaml")
    assert check_main([str(folder)]) == 0
    imported = run_stage_for_test(CAPTURE, tmp_path / "w", params={"source": str(folder)})
    manifest = json.loads((imported / "manifest.json").read_text())
    assert (manifest["width"], manifest["height"]) == (80, 60)  # landscape, as the rig's 320 x 240
    assert [f["light"] for f in manifest["frames"]] == lights and {f["status"] for f in manifest["frames"]} == {"ok"}


def test_the_command_films_with_another_rig_and_exports(tmp_path: Path) -> None:
    rig = yaml.safe_load((ROOT / "configs" / "rig.yaml").read_text())
    rig["cameras"] = rig["cameras"][1:3]
    (tmp_path / "two_cameras.yaml").write_text(yaml.safe_dump(rig))
    done = _export_command(tmp_path, "ci", "--rig", str(tmp_path / "two_cameras.yaml"))
    assert done.returncode == 0, done.stderr[-3000:]
    assert "2 cameras, 24 images, 12 controller log entries" in done.stdout
    info = json.loads((tmp_path / "export" / "capture.json").read_text())
    assert info["cameras"] == ["cam01", "cam02"] and info["subject"] == "ci" and info["fps"] == 24.0
    assert check_main([str(tmp_path / "export")]) == 0
    again = _export_command(tmp_path, "ci", "--rig", str(tmp_path / "two_cameras.yaml"))
    assert again.returncode == 1 and "not an empty folder" in again.stderr and "capture" not in again.stdout
