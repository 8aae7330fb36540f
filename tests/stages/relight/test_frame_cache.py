"""Relight frames are cached per frame: more frames render only the new ones, the output equals an
uncached run's, and frames rendered before a failure are reused by the rerun."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipeline.testing import run_stage_for_test
from stages.relight.stage import STAGE
from tests.stages.relight.conftest import fail_on_call, restore_render, write_relight_inputs

ONLY = {"envmaps": ["blender-cc0/studio.exr"], "directions": 16, "orbit_frames": 0, "turntable_frames": 0,
        "dolly_zoom_frames": 0, "naive_timing_frames": 0, "width_px": 12, "height_px": 16, "steps_per_ray": 8}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    return write_relight_inputs(tmp_path_factory.mktemp("relight_cache_inputs"), expressions=1)


def _run(inputs, root: Path, work: str, params: dict, share_cache_of: str | None = None) -> tuple[Path, dict]:
    (root / work).mkdir()
    if share_cache_of:
        (root / work / ".cache").symlink_to(root / share_cache_of / ".cache", target_is_directory=True)
    out = run_stage_for_test(STAGE, root / work, inputs, params)
    return out, json.loads((out / "metrics.json").read_text())


def _files(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*"))
            if p.is_file() and p.suffix in (".exr", ".png", ".npz") or p.name == "renders.json"}


def test_more_frames_render_only_the_new_ones_and_equal_an_uncached_run(inputs, tmp_path):
    lights = [(0.4, 0.2, 1.0), (-0.5, 0.1, 0.9)]
    _, first = _run(inputs, tmp_path, "a", {**ONLY, "envmap_frames": 2, "point_lights": lights})
    assert (first["frames_reused"], first["frames_computed"]) == (0, 4)
    more = {**ONLY, "envmap_frames": 3, "point_lights": lights + [(0.0, 0.6, 0.8)]}
    out, second = _run(inputs, tmp_path, "b", more, share_cache_of="a")
    assert (second["frames_reused"], second["frames_computed"]) == (4, 2)
    fresh, third = _run(inputs, tmp_path, "c", more)
    assert third["frames_computed"] == 6
    assert _files(out) == _files(fresh) and len(_files(out)) == 2 * 6 + 2  # EXR + PNG per frame, meshes, manifest


def test_frames_rendered_before_a_failure_are_reused(inputs, tmp_path, monkeypatch):
    params = {**ONLY, "envmaps": [], "point_lights": [(0.4, 0.2, 1.0), (-0.5, 0.1, 0.9), (0.0, 0.6, 0.8),
                                                      (0.3, -0.2, 1.1)]}
    original = fail_on_call(monkeypatch, 3)
    with pytest.raises(RuntimeError, match="fell off"):
        _run(inputs, tmp_path, "a", params)
    restore_render(monkeypatch, original)
    _, rerun = _run(inputs, tmp_path, "b", params, share_cache_of="a")
    assert (rerun["frames_reused"], rerun["frames_computed"]) == (2, 2)
