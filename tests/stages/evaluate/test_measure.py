"""Sweep PSNR: one exposure per sweep, white level floored for black (back-lit) references."""

from __future__ import annotations

import numpy as np

from stages.evaluate.measure import sweep_psnr


def _truths(rng):
    alpha = np.zeros((12, 10))
    alpha[2:10, 2:8] = 1.0
    lit = rng.uniform(0.2, 1.0, (12, 10, 3)) * alpha[..., None]
    dim = lit * 0.3
    black = np.zeros_like(lit)
    return [lit, dim, black], [alpha] * 3


def test_a_correct_model_in_other_units_scores_high_everywhere():
    truths, alphas = _truths(np.random.default_rng(0))
    psnr, scale = sweep_psnr([t * 7.0 for t in truths], truths, alphas)
    assert np.all(psnr > 100) and abs(scale - 1 / 7.0) < 1e-9


def test_lighting_a_black_reference_is_punished_not_scaled_away():
    rng = np.random.default_rng(1)
    truths, alphas = _truths(rng)
    preds = [truths[0], truths[1], truths[0]]  # lit where the truth is black (light behind the head)
    psnr, _ = sweep_psnr(preds, truths, alphas)
    # The one exposure is pulled down by the wrong image, so the others lose a little too,
    # but the back-lit one is far worse (and finite: the white level is floored).
    assert np.isfinite(psnr[2]) and psnr[2] < 5 and psnr[2] < min(psnr[0], psnr[1]) - 5
