"""relight_eval renders the studio's truth for the relit frames and scores them."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.testing import run_stage_for_test
from stages.relight.eval_stage import STAGE as EVAL_STAGE, compare_images
from stages.relight.stage import STAGE
from tests.stages.relight.test_stage import FAST, inputs  # noqa: F401  (fixture)


def test_compare_images_is_exposure_invariant():
    rng = np.random.default_rng(0)
    truth = rng.uniform(0, 2, (24, 20, 3))
    alpha = np.ones((24, 20))
    p_same, s_same, scale = compare_images(truth * 0.25, truth, alpha)
    assert p_same > 100 and s_same > 0.999 and scale == pytest.approx(4.0)
    p_noisy, _, _ = compare_images(truth + rng.normal(0, 0.1, truth.shape), truth, alpha)
    assert 10 < p_noisy < p_same


@pytest.mark.slow
def test_eval_scores_envmap_and_point_frames(inputs, tmp_path):  # noqa: F811
    relight = run_stage_for_test(STAGE, tmp_path, inputs, {**FAST, "turntable_frames": 0, "dolly_zoom_frames": 0,
                                                            "orbit_frames": 2})
    truth = tmp_path / "capture.truth"
    truth.mkdir()
    (truth / "studio.json").write_text(json.dumps({"subject": "alice", "identity_seed": 1, "texture_size": 128}))
    np.savez(truth / "frames.npz", weights=np.zeros((1, 57), np.float32))
    out = run_stage_for_test(EVAL_STAGE, tmp_path, {"relight": relight, "capture.truth": truth},
                             {"truth_directions": 64})
    metrics = json.loads((out / "metrics.json").read_text())
    assert np.isfinite(metrics["envmap_psnr_mean"]) and np.isfinite(metrics["pointlight_psnr_mean"])
    assert metrics["envmap_frames_checked"] == 1 and metrics["pointlight_frames_checked"] == 1
    assert (out / "truth" / "envmap_studio" / "000000.exr").exists()
