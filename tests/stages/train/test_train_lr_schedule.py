"""The learning-rate schedule: an optional linear warm-up (``train.lr_warmup_iterations``), then the decay."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from pipeline.testing import run_stage_for_test
from stages.train import trainer as trainer_mod
from stages.train.stage import STAGE
from tests.stages.train.test_train_stage import BASE
from tests.stages.train.train_synth import make_capture


def _trainer(tensors_and_renderer, tmp_path, warmup: int, lr_decay_to: float = 0.1):
    tensors, renderer = tensors_and_renderer
    return trainer_mod.ModelTrainer(renderer, tensors, np.arange(4), iterations=10, batch_size=2,
                                    rays_per_image=16, lr=1e-3, weights=trainer_mod.LossWeights(), seed=0,
                                    ckpt_path=tmp_path / "m.pt", checkpoint_every=100, spike_factor=10.0,
                                    log=logging.getLogger("test"), lr_decay_to=lr_decay_to,
                                    lr_warmup_iterations=warmup)


def test_warm_up_ramps_linearly_then_the_decay_takes_over(tensors_and_renderer, tmp_path):
    tr = _trainer(tensors_and_renderer, tmp_path, warmup=4)
    decay = [1e-3 * 0.1 ** (i / 10) for i in range(10)]
    assert [tr.lr_at(i) for i in range(10)] == pytest.approx(
        [decay[0] / 4, decay[1] * 2 / 4, decay[2] * 3 / 4] + decay[3:], rel=1e-12)
    tr.state.lr = 5e-4  # a rollback halves the base rate: the schedule scales with it
    assert tr.lr_at(1) == pytest.approx(5e-4 * 0.5 * 0.1 ** 0.1, rel=1e-12)


def test_without_warm_up_the_schedule_is_the_decay_alone(tensors_and_renderer, tmp_path):
    tr = _trainer(tensors_and_renderer, tmp_path, warmup=0)
    assert [tr.lr_at(i) for i in range(10)] == pytest.approx([1e-3 * 0.1 ** (i / 10) for i in range(10)], rel=1e-12)
    constant = _trainer(tensors_and_renderer, tmp_path, warmup=0, lr_decay_to=1.0)
    assert {constant.lr_at(i) for i in range(10)} == {1e-3}


def test_a_negative_warm_up_is_refused(tensors_and_renderer, tmp_path):
    with pytest.raises(ValueError, match="lr_warmup_iterations"):
        _trainer(tensors_and_renderer, tmp_path, warmup=-1)


def test_the_stage_steps_with_the_warm_up_rates(tmp_path, monkeypatch):
    capture = make_capture(tmp_path / "synth", width_px=24, cameras=3, frames_per_take=(9, 6))
    used: list[float] = []
    real_step = trainer_mod.ModelTrainer.step

    def recording_step(self):
        used.append(self.optim.param_groups[0]["lr"])
        return real_step(self)

    monkeypatch.setattr(trainer_mod.ModelTrainer, "step", recording_step)
    params = {**BASE, "iterations": 6, "baseline": False, "lpips": False, "curve_every": 0, "previews": 0,
              "lr": 2e-3, "lr_decay_to": 0.5, "lr_warmup_iterations": 3}
    run_stage_for_test(STAGE, tmp_path / "ws", capture, params)
    expected = [2e-3 * min(1.0, (i + 1) / 3) * 0.5 ** (i / 6) for i in range(6)]
    assert used == pytest.approx(expected, rel=1e-9)
