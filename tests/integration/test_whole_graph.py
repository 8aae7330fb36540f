"""The whole graph on the smallest real configuration (subject `ci`, preset `smoke`).

Every stage runs for real (virtual studio, controller emulator, calibration, MediaPipe
tracking, matting, training, relighting, evaluation, report) through the `pipeline`
command, as a user runs it. Accuracy figures at this size are not meaningful; the test
checks that the graph completes, that every stage reports the metric keys that
docs/design.md requires (``REQUIRED``), that a second run does nothing and that the report
is written.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]

REQUIRED = {
    "sequence": ["olat_angle_mean_deg", "olat_angle_min_deg", "naive_olat_angle_mean_deg",
                 "random_olat_angle_mean_deg"],
    "capture": ["cameras", "frames", "full_on_frames", "olat_frames", "dropped_frames", "seconds",
                "realism_real", "sensor_gain_e_per_dn", "read_noise_e", "sensor_full_well_e", "exposure_s"],
    "calibrate": ["reproj_rms_px", "focal_err_pct_max", "principal_err_px_max", "center_err_mm_max",
                  "rotation_err_deg_max"],
    "lightcal": ["residual_mm_mean", "bar_center_err_mm_mean", "bar_center_err_mm_max"],
    "track": ["landmark_reproj_px_mean", "fit_frames_per_second", "vertex_err_mm_mean_full",
              "vertex_err_mm_p95_full", "vertex_err_mm_mean_olat", "rotation_err_deg_mean",
              "translation_err_mm_mean"],
    "stabilize": ["head_pose_residual_deg_max"],
    "matte": ["images_per_second", "mae_full", "mae_olat", "grad_err_olat", "baseline_mae_full",
              "baseline_mae_olat", "baseline_grad_err_olat"],
    "train": ["iterations", "seconds", "iterations_per_second", "peak_memory_mb"]
    + [f"{model}_{split}_{measure}" for model in ("ours", "travatar")
       for split in ("val_light", "val_perf", "novel_light", "novel_perf", "novel_both")
       for measure in ("psnr", "mae", "ssim", "lpips")],
    "relight": ["envmap_seconds_per_frame", "naive_envmap_seconds_per_frame", "envmap_directions",
                "envmap_psnr_mean", "pointlight_psnr_mean", "bake_seconds", "bake_frame_seconds",
                "bake_psnr_vs_sum_db"],
}


def _pipeline(*args: str, workspaces: Path, timeout: int = 1500) -> subprocess.CompletedProcess:
    env = dict(os.environ, PIPELINE_WORKSPACES=str(workspaces), PIPELINE_PROJECT_ROOT=str(ROOT))
    return subprocess.run([sys.executable, "-m", "pipeline.cli", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=timeout, check=False)


@pytest.fixture(scope="module")
def workspaces(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("workspaces")
    done = _pipeline("run", "-S", "ci", "--workers", "2", workspaces=root)
    assert done.returncode == 0, f"pipeline run failed:\n{done.stdout[-3000:]}\n{done.stderr[-6000:]}"
    return root


def test_every_stage_reports_the_metrics_contract(workspaces: Path) -> None:
    for stage, keys in REQUIRED.items():
        shown = _pipeline("show", "-S", "ci", stage, "--json", workspaces=workspaces)
        assert shown.returncode == 0, shown.stderr
        metrics = json.loads(shown.stdout)
        missing = [k for k in keys if k not in metrics]
        assert not missing, f"{stage}: missing metrics {missing}"
        assert all(isinstance(metrics[k], (int, float)) for k in keys)


def test_second_run_does_nothing_and_status_is_fresh(workspaces: Path) -> None:
    again = _pipeline("run", "-S", "ci", workspaces=workspaces)
    assert again.returncode == 0, again.stderr
    assert "0 stage(s) ran" in again.stdout
    status = _pipeline("status", "-S", "ci", "--json", workspaces=workspaces)
    assert status.returncode == 0, status.stderr
    assert all(entry["state"] == "fresh" for entry in json.loads(status.stdout))


def test_report_is_written(workspaces: Path) -> None:
    shown = _pipeline("show", "-S", "ci", "report", "--json", "--full", workspaces=workspaces)
    page = Path(json.loads(shown.stdout)["path"]) / "report.html"
    text = page.read_text()
    assert 'id="paper-table"' in text and 'id="targets-table"' in text


def test_retraining_the_same_models_leaves_relight_and_evaluate_fresh(workspaces: Path) -> None:
    """A forced train writes the same models with new wall-clock curves (its run records): only
    the report, which shows the curves and timings, runs after it."""
    forced = _pipeline("run", "-S", "ci", "--force", "train", workspaces=workspaces)
    assert forced.returncode == 0, forced.stderr
    ran = {line.split()[1] for line in forced.stdout.splitlines() if line.startswith("ran ")}
    assert ran == {"train", "report"}, forced.stdout
