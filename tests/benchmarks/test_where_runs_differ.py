"""``benchmarks/where_runs_differ.py``: two runs of the same inputs compared image by image."""

from __future__ import annotations

import json
import logging

import pytest
import torch

from benchmarks.where_runs_differ import compare_runs, mosaic
from pipeline.testing import run_stage_for_test
from stages.train.data import load_train_data
from stages.train.setup import prepare_training
from stages.train.stage import STAGE
from tests.stages.train.test_train_stage import BASE
from tests.stages.train.train_synth import make_capture


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("differ")
    capture = make_capture(root / "synth", width_px=24, cameras=3, frames_per_take=(9, 6))
    params = {**BASE, "iterations": 40, "lpips": False, "curve_every": 0, "previews": 0, "checkpoint_every": 100,
              "baseline": False}
    runs = [run_stage_for_test(STAGE, root / f"ws{seed}", capture, {**params, "seed": seed}) for seed in (0, 1)]
    stage_params = STAGE.params(**params)
    data = load_train_data(capture, stage_params.image_width_px, logging.getLogger("test"))
    setup = prepare_training(data, stage_params, torch.device("cpu"), logging.getLogger("test"))
    return runs, setup, stage_params


def test_a_run_against_itself_differs_nowhere_and_scores_as_the_stage(two_runs):
    (a, _), setup, params = two_runs
    result = compare_runs(a, a, setup, params.raymarch_kernel, train_images=params.eval_images)
    own = json.loads((a / "metrics.json").read_text())
    for name, r in result["sets"].items():
        assert r["b_minus_a_mean"] == 0.0 and r["b_minus_a_min"] == 0.0 and r["b_minus_a_max"] == 0.0
        assert r["a_alpha_top1pct"] == r["b_alpha_top1pct"]
        # The same images and scoring as the train stage's own figures.
        key = "ours_train_psnr" if name == "train" else f"ours_{name}_psnr"
        assert r["a_psnr"] == pytest.approx(own[key], abs=1e-4)
    assert result["a_opacity_logits_below_floor"] == pytest.approx(own["ours_opacity_logits_below_floor"])


def test_swapping_the_runs_negates_the_gap(two_runs):
    (a, b), setup, params = two_runs
    ab = compare_runs(a, b, setup, params.raymarch_kernel)["sets"]
    ba = compare_runs(b, a, setup, params.raymarch_kernel)["sets"]
    for name in ab:
        assert ab[name]["b_minus_a_mean"] == pytest.approx(-ba[name]["b_minus_a_mean"], abs=1e-5)
        assert ab[name]["b_minus_a_mean"] != 0.0  # two seeds are two runs
        assert ab[name]["a_psnr"] == pytest.approx(ba[name]["b_psnr"])
    target, pred_a, pred_b = ab["train"].pop("_images")
    row = mosaic(target, pred_a, pred_b, ab["train"]["worst_image_for_a"])
    assert row.shape == (target.shape[1], 4 * target.shape[2], 3) and row.dtype.name == "uint8"
