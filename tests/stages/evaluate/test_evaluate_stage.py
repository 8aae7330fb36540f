"""The evaluate stage end to end on a random tiny head and the studio's subject (tiny renders)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from avatar.io import save_trained
from pipeline.errors import InputError
from pipeline.testing import run_stage_for_test
from stages.evaluate.limits import light_warning, read_limits
from stages.evaluate.stage import STAGE
from tests.stages.relight.conftest import tiny_model

FAST = {"orbit_points": 8, "camera_azimuths_deg": [0.0], "width_px": 16, "height_px": 20,
        "expression_scales": [0.5, 1.0, 2.0], "steps_per_ray": 12, "relative_drop_db": 3.0, "vertical_orbit": False}
BAR_AZIMUTHS_DEG = (-40.0, 0.0, 70.0)


def _bar(i: int, az_deg: float) -> dict:
    a = math.radians(az_deg)
    return {"id": i, "center_world": [1.2 * math.sin(a), 0.0, 1.2 * math.cos(a)], "axis_world": [0, 1, 0],
            "length_m": 0.3, "intensity": 1.0}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    root = tmp_path_factory.mktemp("evaluate_inputs")
    model, verts = tiny_model()
    save_trained(root / "train" / "models" / "ours", model, "ours")
    # Frames: 0 full-on, 1-2 trained (bars 0 and 1), 3 held out (bar 2: never a training light).
    (root / "train" / "splits.json").write_text(json.dumps({"train": [1, 2], "novel_perf": [3], "novel_light": [],
                                                            "novel_both": []}))
    (root / "track").mkdir()
    meshes = np.stack([verts * (1.0 + 0.01 * k) for k in range(4)]).astype(np.float32)
    np.savez(root / "track" / "meshes.npz", index=np.arange(4), vertices=meshes)
    (root / "capture" / "scans").mkdir(parents=True)
    (root / "capture" / "manifest.json").write_text(json.dumps({"frames": [
        {"index": i, "light": light, "status": "ok"} for i, light in enumerate(["F", 0, 1, 2])]}))
    np.savez(root / "capture" / "scans" / "scans.npz", vertices=np.stack([verts, verts * 1.02]))
    truth = root / "capture.truth"
    truth.mkdir()
    (truth / "studio.json").write_text(json.dumps({"subject": "alice", "identity_seed": 1, "texture_size": 64}))
    (truth / "bars.json").write_text(json.dumps({"bars": [_bar(i, a) for i, a in enumerate(BAR_AZIMUTHS_DEG)]}))
    np.savez(truth / "frames.npz", index=np.arange(4), world_from_head_R=np.tile(np.eye(3), (4, 1, 1)),
             world_from_head_t=np.zeros((4, 3)), weights=np.zeros((4, 57), np.float32))
    return {"train": root / "train", "track": root / "track", "capture": root / "capture", "capture.truth": truth}


def test_sweeps_write_limits_charts_and_metrics(inputs, tmp_path):
    out = run_stage_for_test(STAGE, tmp_path, inputs, FAST)
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("light_extrapolation_limit_deg", "light_orbit_psnr_mean", "expression_scale_limit_low",
                "expression_scale_limit_high", "expression_psnr_at_scale_1"):
        assert np.isfinite(metrics[key]), key
    assert metrics["light_orbit_points"] == 8
    # Only the training split's bars (-40 and 0 degrees) count: straight behind is 140 degrees
    # from the -40 degree bar (it would be 110 had the held-out +70 degree bar been counted).
    assert metrics["light_orbit_max_from_training_deg"] == pytest.approx(140.0, abs=0.5)
    assert 0.0 <= metrics["light_extrapolation_limit_deg"] <= 140.0 + 1e-6
    assert metrics["light_threshold_db"] == pytest.approx(metrics["light_orbit_psnr_near_training"] - 3.0)
    limits = read_limits(out / "limits.json")
    assert len(limits.training_light_dirs_head) == 2
    assert limits.light_extrapolation_limit_deg == pytest.approx(metrics["light_extrapolation_limit_deg"])
    if not limits.censored:
        assert light_warning(np.array(limits.centre_head) + [0.0, 0.0, -3.0], limits) is not None
    sweeps = json.loads((out / "sweeps.json").read_text())
    assert [s["scale"] for s in sweeps["expression_scale"]] == [0.5, 1.0, 2.0]
    for name in ("light_orbit.png", "expression_scale.png", "orbit_strip.png"):
        assert (out / name).stat().st_size > 0
    from stages.report.charts import tradeoff_chart  # the report must be able to draw both series

    for name in ("light_orbit", "expression_scale"):
        spec = json.loads((out / "tradeoffs" / f"{name}.json").read_text())
        assert sum(bool(p.get("chosen")) for p in spec["points"]) >= 1
        tradeoff_chart(spec["title"], spec["x_label"], spec["y_label"], spec["points"], tmp_path / f"{name}.png")
        assert (tmp_path / f"{name}.png").stat().st_size > 0


def test_meshes_that_do_not_match_the_scans_are_a_clear_error(inputs, tmp_path):
    bad = tmp_path / "capture"
    (bad / "scans").mkdir(parents=True)
    (bad / "manifest.json").write_text((inputs["capture"] / "manifest.json").read_text())
    np.savez(bad / "scans" / "scans.npz", vertices=np.zeros((2, 5, 3)))
    with pytest.raises(InputError, match="neutral scan"):
        run_stage_for_test(STAGE, tmp_path / "w", {**inputs, "capture": bad}, {**FAST, "orbit_points": 4})
