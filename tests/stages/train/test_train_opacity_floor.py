"""The opacity floor (``train.loss_weights.floor``) and the lifted gradient (``lift``): logits that can still learn."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from avatar.model import OPACITY_FLOOR_LOGIT, lifted_softplus, opacity_floor_penalty
from stages.train import trainer as trainer_mod


def test_the_penalty_is_zero_above_the_floor_and_squared_below():
    raw = torch.tensor([0.0, -5.0, OPACITY_FLOOR_LOGIT, OPACITY_FLOOR_LOGIT - 2.0, OPACITY_FLOOR_LOGIT - 4.0],
                       requires_grad=True)
    penalty = opacity_floor_penalty(raw)
    assert float(penalty.detach()) == pytest.approx((4.0 + 16.0) / 5)
    penalty.backward()
    # Only the logits below the floor are pushed, and upwards (a descent step raises them).
    assert raw.grad[:3].abs().max() == 0.0
    assert raw.grad[3] == pytest.approx(-2 * 2.0 / 5) and raw.grad[4] == pytest.approx(-2 * 4.0 / 5)


def test_the_lifted_softplus_changes_only_upward_pulls_under_the_floor():
    raw = torch.tensor([2.0, -5.0, -20.0, -20.0, -48.0], dtype=torch.float64)
    pull = torch.tensor([1.0, -1.0, 1.0, -1.0, -1.0], dtype=torch.float64)  # d loss / d softplus
    plain, lifted = raw.clone().requires_grad_(), raw.clone().requires_grad_()
    (F.softplus(plain) * pull).sum().backward()
    value = lifted_softplus(lifted)
    (value * pull).sum().backward()
    torch.testing.assert_close(value.detach(), F.softplus(raw))  # the forward pass is the softplus itself
    # Above the floor, and a downward pull under it: the true slope.
    torch.testing.assert_close(lifted.grad[:3], plain.grad[:3])
    # An upward pull under the floor: the slope at the floor, not the vanishing one.
    at_floor = torch.sigmoid(torch.tensor(OPACITY_FLOOR_LOGIT, dtype=torch.float64))
    torch.testing.assert_close(lifted.grad[3:], -at_floor.expand(2))
    assert float(plain.grad[4].abs()) < 1e-20


def test_the_floor_is_where_a_box_is_still_empty():
    # A box whose every voxel sits at the floor stays under the pruning's 0.01 of opacity on a ray through it,
    # while the softplus' slope there is 20 000 times its slope at -18.
    density_times_length = F.softplus(torch.tensor(OPACITY_FLOOR_LOGIT)) * 2.0  # density_scale x a box's length
    assert 1.0 - torch.exp(-density_times_length) < 1e-3
    assert torch.sigmoid(torch.tensor(OPACITY_FLOOR_LOGIT)) / torch.sigmoid(torch.tensor(-18.0)) > 2e4


def test_decoded_geometry_keeps_the_logits_the_density_comes_from(tensors_and_renderer):
    _, renderer = tensors_and_renderer
    model = renderer.model
    with torch.no_grad():
        geo = model.decode_geometry(torch.zeros(2, model.config.latent_dim))
    b, n, m = 2, model.n, model.m
    density = (F.softplus(geo.raw_alpha) * model.density_scale).view(b, m, n, m, n, m)
    density = density.permute(0, 2, 4, 1, 3, 5).reshape(b, n * n, m, m, m)
    torch.testing.assert_close(density, geo.density)
    one = model.decode_geometry(torch.zeros(1, model.config.latent_dim))
    assert one.expand(3).raw_alpha is None and geo.repeat(2).raw_alpha is None  # rendering copies leave it out


def _raw_mean(trainer) -> float:
    with torch.no_grad():
        return float(trainer.model.decode_geometry(torch.zeros(1, trainer.model.config.latent_dim)).raw_alpha.mean())


@pytest.mark.parametrize("floor, lift", [(0.0, False), (1.0, False), (0.0, True)])
def test_a_head_gone_transparent_revives_only_with_the_floor_or_the_lift(tensors_and_renderer, tmp_path, floor,
                                                                          lift):
    """Every opacity logit at -40: the softplus is flat there, so without the floor or the lift nothing moves them."""
    tensors, renderer = tensors_and_renderer
    state = {k: v.clone() for k, v in renderer.model.state_dict().items()}
    try:
        last = renderer.model.alpha_branch.layers[-1]
        with torch.no_grad():
            last.weight.zero_()
            last.bias.fill_(-40.0)
        tr = trainer_mod.ModelTrainer(renderer, tensors, np.arange(4), iterations=20, batch_size=2,
                                      rays_per_image=16, lr=1e-2,
                                      weights=trainer_mod.LossWeights(floor=floor, lift=lift),
                                      seed=0, ckpt_path=tmp_path / f"m{floor}.pt", checkpoint_every=100,
                                      spike_factor=1e9, log=logging.getLogger("test"))
        before = _raw_mean(tr)
        terms = [tr.step() for _ in range(20)]
        rise = _raw_mean(tr) - before
        if floor:
            assert all("floor" in t for t in terms) and terms[-1]["floor"] < terms[0]["floor"]
            assert rise > 0.1, rise  # Adam's steps of about lr x 20 on the bias alone give 0.2
        elif lift:
            assert all("floor" not in t for t in terms)
            assert tr.model.lift_below_logit == OPACITY_FLOOR_LOGIT
            assert rise > 0.1, rise  # the matte loss's pull on the foreground now reaches the logits
        else:
            assert all("floor" not in t for t in terms)
            assert abs(rise) < 1e-3, rise  # the photometric and matte losses have no grip on a flat softplus
    finally:
        renderer.model.load_state_dict(state)
        renderer.model.lift_below_logit = None


def test_the_huber_matte_loss_is_the_l1_over_delta_and_quadratic_under_it(tensors_and_renderer, tmp_path):
    """``train.loss_weights.mat_delta``: the same batch's matte term as an L1 and as a Huber loss."""
    tensors, renderer = tensors_and_renderer

    def matte_term(delta: float) -> float:
        tr = trainer_mod.ModelTrainer(renderer, tensors, np.arange(4), iterations=1, batch_size=2,
                                      rays_per_image=32, lr=1e-3,
                                      weights=trainer_mod.LossWeights(mat_delta=delta), seed=0,
                                      ckpt_path=tmp_path / f"h{delta}.pt", checkpoint_every=100,
                                      spike_factor=1e9, log=logging.getLogger("test"))
        frames, cams, pix = tr.sample_batch()
        eps = torch.zeros(2, tr.model.config.latent_dim)
        with torch.no_grad():
            return tr.losses(frames, cams, pix, eps)[1]["mat"]

    l1, tiny, whole = matte_term(0.0), matte_term(1e-6), matte_term(0.999)
    assert l1 > 0.01  # a fresh head's opacity is far from the matte
    assert tiny == pytest.approx(l1 - 0.5e-6, abs=1e-6)  # every error over delta: the L1 less delta / 2
    assert 0.0 < whole < 0.5 * l1  # every error under delta: 0.5 e^2 / delta <= 0.5 |e|
