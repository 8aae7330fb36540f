"""Gradient clipping against the norm's running mean (``train.grad_clip_factor``)."""

from __future__ import annotations

import json
import logging
import math

import numpy as np
import pytest
import torch
from pydantic import ValidationError

from pipeline.testing import run_stage_for_test
from stages.train import trainer as trainer_mod
from stages.train.params import TrainParams
from stages.train.stage import STAGE
from tests.stages.train.test_train_stage import BASE
from tests.stages.train.train_synth import make_capture


def _trainer(tensors_and_renderer, tmp_path, factor: float):
    tensors, renderer = tensors_and_renderer
    return trainer_mod.ModelTrainer(renderer, tensors, np.arange(4), iterations=10, batch_size=2,
                                    rays_per_image=16, lr=1e-3, weights=trainer_mod.LossWeights(), seed=0,
                                    ckpt_path=tmp_path / "m.pt", checkpoint_every=100, spike_factor=10.0,
                                    log=logging.getLogger("test"), grad_clip_factor=factor)


def _set_gradient(trainer, norm: float) -> None:
    """Give every parameter the same-signed gradient, scaled so the whole gradient has norm ``norm``."""
    params = list(trainer.model.parameters())
    count = sum(p.numel() for p in params)
    for p in params:
        p.grad = torch.full_like(p, norm / math.sqrt(count))


def _norm(trainer) -> float:
    return float(torch.sqrt(sum((p.grad.double() ** 2).sum() for p in trainer.model.parameters())))


def test_an_outlier_is_clipped_to_the_bound_and_the_mean_takes_the_bound(tensors_and_renderer, tmp_path):
    tr = _trainer(tensors_and_renderer, tmp_path, factor=2.0)
    tr.state.iteration, tr.state.grad_norm_ema = 100, 1.5
    _set_gradient(tr, 30.0)
    before = tr._clip_gradient()
    assert before == pytest.approx(30.0, rel=1e-5)
    assert _norm(tr) == pytest.approx(3.0, rel=1e-5)  # 2 x the running mean 1.5
    assert tr.state.clipped_steps == 1
    assert tr.state.grad_norm_ema == pytest.approx(0.95 * 1.5 + 0.05 * 3.0, rel=1e-5)  # the kept norm, not 30


def test_a_gradient_under_the_bound_is_left_alone(tensors_and_renderer, tmp_path):
    tr = _trainer(tensors_and_renderer, tmp_path, factor=2.0)
    tr.state.iteration, tr.state.grad_norm_ema = 100, 1.5
    _set_gradient(tr, 2.9)
    before = [p.grad.clone() for p in tr.model.parameters()]
    assert tr._clip_gradient() == pytest.approx(2.9, rel=1e-5)
    assert all(torch.equal(a, p.grad) for a, p in zip(before, tr.model.parameters()))
    assert tr.state.clipped_steps == 0


def test_off_or_early_it_only_records(tensors_and_renderer, tmp_path):
    off = _trainer(tensors_and_renderer, tmp_path, factor=0.0)
    off.state.iteration, off.state.grad_norm_ema = 100, 1.0
    _set_gradient(off, 50.0)
    off._clip_gradient()
    assert _norm(off) == pytest.approx(50.0, rel=1e-5) and off.state.clipped_steps == 0
    assert off.state.grad_norm_ema == pytest.approx(0.95 + 0.05 * 50.0, rel=1e-5)
    early = _trainer(tensors_and_renderer, tmp_path, factor=2.0)
    early.state.iteration, early.state.grad_norm_ema = 10, 1.0  # within the first 50 steps
    _set_gradient(early, 50.0)
    early._clip_gradient()
    assert _norm(early) == pytest.approx(50.0, rel=1e-5) and early.state.clipped_steps == 0


@pytest.mark.parametrize("factor", [0.5, 1.0, -1.0])
def test_a_bound_at_or_under_the_mean_is_refused(tensors_and_renderer, tmp_path, factor):
    with pytest.raises(ValueError, match="grad_clip_factor"):
        _trainer(tensors_and_renderer, tmp_path, factor=factor)
    with pytest.raises(ValidationError, match="grad_clip_factor"):
        TrainParams(grad_clip_factor=factor)


def test_the_stage_counts_each_models_clipped_steps(tmp_path):
    capture = make_capture(tmp_path / "synth", width_px=24, cameras=3, frames_per_take=(9, 6))
    params = {**BASE, "iterations": 70, "lpips": False, "curve_every": 0, "previews": 0,
              "checkpoint_every": 100, "grad_clip_factor": 1.05}
    out = run_stage_for_test(STAGE, tmp_path / "ws", capture, params)
    metrics = json.loads((out / "metrics.json").read_text())
    # A bound 5% over the mean catches some of the 19 steps after the first 51, never those.
    for kind in ("ours", "travatar"):
        assert 0 < metrics[f"{kind}_clipped_steps"] <= 19
