"""The relight stage end to end on a random tiny head: files per frame, MP4s, metrics, bad input."""

from __future__ import annotations

import json

import pytest

from pipeline.errors import InputError
from pipeline.testing import run_stage_for_test
from stages.relight.stage import STAGE
from stages.relight.params import ASSETS as STAGE_ASSETS
from tests.stages.relight.conftest import fail_on_call, write_relight_inputs

FAST = {"envmaps": ["blender-cc0/studio.exr"], "envmap_frames": 2, "directions": 32, "orbit_frames": 3,
        "turntable_frames": 2, "dolly_zoom_frames": 2, "width_px": 16, "height_px": 20, "steps_per_ray": 12}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    return write_relight_inputs(tmp_path_factory.mktemp("relight_inputs"), expressions=2)


def test_stage_writes_every_sequence_and_metrics(inputs, tmp_path):
    out = run_stage_for_test(STAGE, tmp_path, inputs, FAST)
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("envmap_seconds_per_frame", "naive_envmap_seconds_per_frame", "envmap_directions",
                "envmap_worker_seconds_per_frame"):
        assert metrics[key] > 0
    assert metrics["envmap_fast_naive_max_abs_diff"] < 1e-4
    manifest = json.loads((out / "renders.json").read_text())
    assert set(manifest) == {"envmap_studio", "point_orbit", "turntable", "dolly_zoom"}
    for name, frames in manifest.items():
        assert len(list((out / name / "frames").glob("*.exr"))) == len(frames)
        assert len(list((out / name / "previews").glob("*.png"))) == len(frames)
        assert (out / name / f"{name}.mp4").stat().st_size > 0
    # The map turns: consecutive frames differ by the requested rotation.
    assert [f["rotation_deg"] for f in manifest["envmap_studio"]] == [0.0, 30.0]


def test_without_timing_frames_the_workers_timing_is_reported(inputs, tmp_path):
    params = {**FAST, "envmap_frames": 1, "orbit_frames": 0, "turntable_frames": 0, "dolly_zoom_frames": 0,
              "naive_timing_frames": 0, "bake_check": False}
    metrics = json.loads((run_stage_for_test(STAGE, tmp_path, inputs, params) / "metrics.json").read_text())
    assert "naive_envmap_seconds_per_frame" not in metrics
    assert metrics["envmap_seconds_per_frame"] == metrics["envmap_worker_seconds_per_frame"] > 0


def test_orbit_warns_about_lights_behind_the_head(inputs, tmp_path, caplog):
    run_stage_for_test(STAGE, tmp_path, inputs, {**FAST, "envmaps": [], "turntable_frames": 0,
                                                 "dolly_zoom_frames": 0, "orbit_frames": 4})
    assert any("behind the head" in r.getMessage() for r in caplog.records)


def test_bad_envmap_is_a_clear_input_error(inputs, tmp_path):
    bad = tmp_path / "half.exr"
    bad.write_bytes((STAGE_ASSETS / "blender-cc0/city.exr").read_bytes()[:5000])
    with pytest.raises(InputError, match="half.exr"):
        run_stage_for_test(STAGE, tmp_path / "w", inputs, {**FAST, "envmaps": [str(bad)]})




def test_a_failure_mid_sequence_keeps_the_frames_already_rendered(inputs, tmp_path, monkeypatch):
    fail_on_call(monkeypatch, 3)
    params = {**FAST, "envmaps": [], "orbit_frames": 5, "turntable_frames": 0, "dolly_zoom_frames": 0}
    with pytest.raises(RuntimeError, match="fell off"):
        run_stage_for_test(STAGE, tmp_path, inputs, params)
    out = tmp_path / "relight"
    assert sorted(p.name for p in (out / "point_orbit" / "frames").glob("*.exr")) == ["000000.exr", "000001.exr"]
    assert (out / "point_orbit" / "point_orbit.mp4").stat().st_size > 0
    assert len(json.loads((out / "renders.json").read_text())["point_orbit"]) == 2
