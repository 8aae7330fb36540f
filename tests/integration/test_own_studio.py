"""A studio of its own through train: another rig, imported as a real capture, calibrated two ways.

``configs/subjects/studio6.yaml`` films with ``configs/rigs/six_landscape.yaml`` (6 cameras, 20
bars, 30 fps, landscape 320 x 240, an F frame every 4th frame). The virtual capture is exported
in the import layout (``pipeline hw export-capture``), checked (``pipeline check-capture``) and
imported into another workspace root, where it runs through ``train``:

1. calibrated from the capture's own ChArUco takes;
2. calibrated from a COLMAP model (the first run's export, ``calibrate.source``).

Both calibrations are measured against the virtual studio's truth (which the export leaves
behind, as a real studio has none), and both runs must reach ``train`` with its figures.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]


def _pipeline(*args: str, workspaces: Path, timeout: int = 1500) -> subprocess.CompletedProcess:
    env = dict(os.environ, PIPELINE_WORKSPACES=str(workspaces), PIPELINE_PROJECT_ROOT=str(ROOT))
    return subprocess.run([sys.executable, "-m", "pipeline.cli", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=timeout, check=False)


def _object(workspaces: Path, stage: str, output: str = "out") -> Path:
    from pipeline.workspace import Workspace

    ws = Workspace(workspaces, "studio6")
    return ws.object_path(ws.read_ref(stage).outputs[output])


def _calibration_errors(calibrate: Path, truth: Path) -> dict[str, float]:
    from scene.camera import load_cameras
    from stages.calibrate.eval_stage import camera_errors

    est = {c.name: c for c in load_cameras(calibrate / "cameras.json", "world")}
    true = {c.name: c for c in load_cameras(truth / "cameras.json", "world")}
    return camera_errors(est, true)


@pytest.fixture(scope="module")
def studio(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("own_studio")
    virtual, imported, export = root / "virtual", root / "imported", root / "export"
    done = _pipeline("hw", "export-capture", "-S", "studio6", "--out", str(export), "--workers", "2",
                     workspaces=virtual)
    assert done.returncode == 0, done.stderr[-4000:]
    done = _pipeline("check-capture", str(export), workspaces=virtual)
    assert done.returncode == 0, done.stdout[-4000:]
    return {"virtual": virtual, "imported": imported, "export": export, "root": root,
            "truth": _object(virtual, "capture", "truth")}


def _run_to_train(studio: dict[str, Path], *sets: str) -> dict:
    args = ["run", "-S", "studio6", "--until", "train", "--workers", "2", "--set", f"capture.source={studio['export']}"]
    for s in sets:
        args += ["--set", s]
    done = _pipeline(*args, workspaces=studio["imported"])
    assert done.returncode == 0, f"{done.stdout[-3000:]}\n{done.stderr[-5000:]}"
    train = json.loads((_object(studio["imported"], "train") / "metrics.json").read_text())
    calibrate = _object(studio["imported"], "calibrate")
    return {"train": train, "calibrate": calibrate,
            "calibrate_metrics": json.loads((calibrate / "metrics.json").read_text()),
            "errors": _calibration_errors(calibrate, studio["truth"])}


def test_charuco_then_colmap_calibration_through_train(studio):
    charuco = _run_to_train(studio)
    e = charuco["errors"]
    print("studio6 imported, ChArUco:", json.dumps({k: round(v, 4) for k, v in e.items()}),
          "ours novel light", charuco["train"]["ours_novel_light_psnr"])
    assert e["cameras_compared"] == 6
    # The board is printed 0.15% / 0.25% oversize (capture.realism: real), which no camera can
    # observe: the calibrated world is that much too small, about 2.5 mm at the cameras' distance.
    # So the centres are judged after a similarity fit, and the scale by what the print explains.
    # The board also flexes and twists by 0.3 mm from pose to pose (board_print.flex_m), which no
    # single board shape absorbs: it leaves a real calibration's residuals (0.05-0.5 px) and, with
    # a few poses a camera, tilts the principal points, so the rotations are judged to 0.5 deg
    # (0.1 deg before the flex; measured 0.23 deg).
    assert e["rotation_err_deg_max"] < 0.5 and e["center_err_mm_max_aligned"] < 2.0 and e["focal_err_pct_max"] < 0.2
    assert e["world_alignment_scale_err_pct"] < 0.3
    assert charuco["calibrate_metrics"]["reproj_rms_px"] < 0.5

    model = studio["root"] / "studio_colmap"
    shutil.copytree(charuco["calibrate"] / "colmap" / "binary", model)
    colmap = _run_to_train(studio, f"calibrate.source={model}")
    e2 = colmap["errors"]
    print("studio6 imported, COLMAP:", json.dumps({k: round(v, 4) for k, v in e2.items()}),
          "ours novel light", colmap["train"]["ours_novel_light_psnr"])
    assert colmap["calibrate_metrics"]["calibration_from_source"] == 1
    # The model is the first calibration written in COLMAP's form: read back, it is that calibration.
    for key in ("rotation_err_deg_max", "center_err_mm_max", "focal_err_pct_max", "principal_err_px_max"):
        assert e2[key] == pytest.approx(e[key], rel=1e-6, abs=1e-9), key
    assert colmap["calibrate_metrics"]["reproj_rms_px"] == pytest.approx(
        charuco["calibrate_metrics"]["reproj_rms_px"], rel=1e-3)
    for run in (charuco, colmap):
        assert run["train"]["iterations"] > 0
        assert 5.0 < run["train"]["ours_novel_light_psnr"] < 60.0
