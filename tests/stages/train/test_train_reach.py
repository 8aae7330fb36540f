"""The reach term in training (``train.loss_weights.reach``): boxes that leave foreground uncovered grow over it."""

from __future__ import annotations


import numpy as np
import torch

from stages.train import trainer as trainer_mod
from tests.stages.train.train_synth import train_steps, weights_restored


def _train(tensors, renderer, tmp_path, weights: trainer_mod.LossWeights, steps: int = 60) -> list[dict]:
    """Every step's loss terms, the boxes at 0.4 x their base size (a grid with gaps: many foreground rays
    cross no box); the iteration advances with each step, as ``ModelTrainer.run`` steps."""
    with weights_restored(renderer.model) as model:
        with torch.no_grad():
            model.half_extent_m.mul_(0.4)
        _, terms = train_steps(renderer, tensors, tmp_path / f"r{weights.reach}_{weights.reach_until}.pt", weights,
                               steps=steps, lr=1e-2, rays_per_image=64)
        return terms


def _last_missed(terms: list[dict]) -> float:
    """The share of foreground rays that crossed no box, over the last 20 steps."""
    return float(np.mean([t["missed"] for t in terms[-20:]]))


def test_the_reach_term_closes_the_gaps_the_other_terms_cannot(tensors_and_renderer, tmp_path):
    tensors, renderer = tensors_and_renderer
    off = _train(tensors, renderer, tmp_path, trainer_mod.LossWeights(reach=0.0), steps=2)
    assert all("reach" not in t and "missed" not in t for t in off)  # off = the paper's loss, nothing reported
    # A weight too small to move anything measures the gaps the paper's terms leave: they stay open.
    plain = _train(tensors, renderer, tmp_path, trainer_mod.LossWeights(reach=1e-9))
    on = _train(tensors, renderer, tmp_path, trainer_mod.LossWeights(reach=1.0))
    last_plain, last = _last_missed(plain), _last_missed(on)
    assert plain[0]["missed"] > 0.1 and on[0]["missed"] == plain[0]["missed"]  # same draw, same start
    assert last_plain > 0.2, last_plain
    assert last < 0.5 * last_plain, (last, last_plain)
    assert all(t["reach"] >= 0 for t in on) and on[-1]["reach"] < on[0]["reach"] + 0.05


def test_the_reach_term_stops_at_its_fraction_of_the_run(tensors_and_renderer, tmp_path):
    """``reach_until``: the term is in the loss for that fraction of the iterations and out of it after."""
    tensors, renderer = tensors_and_renderer
    terms = _train(tensors, renderer, tmp_path, trainer_mod.LossWeights(reach=1.0, reach_until=0.5), steps=8)
    assert all("reach" in t for t in terms[:4]) and terms[0]["reach"] > 0
    assert not any("reach" in t or "missed" in t for t in terms[4:])


def test_reach_until_must_be_a_fraction_of_the_run():
    import pydantic
    import pytest

    for bad in (0.0, 1.5):
        with pytest.raises(pydantic.ValidationError, match="reach_until"):
            trainer_mod.LossWeights(reach=0.1, reach_until=bad)
