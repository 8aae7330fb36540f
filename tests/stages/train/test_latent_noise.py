"""How much of the code the decoder trains on is noise (``avatar.model.latent_noise_to_code_spread``), and what sets it."""

from __future__ import annotations

import math

import torch

from avatar.model import latent_noise_to_code_spread
from stages.train import trainer as trainer_mod
from tests.stages.train.train_synth import train_steps, weights_restored


def test_the_ratio_is_the_mean_noise_over_the_mean_spread_of_the_codes(tensors_and_renderer):
    tensors, renderer = tensors_and_renderer
    model = renderer.model
    meshes = tensors.guide_vertices
    with weights_restored(model):
        with torch.no_grad():
            mu, _ = model.encode(meshes)
        # A fresh encoder's log-variance is -4 for every frame: sigma = exp(-2).
        expected = math.exp(-2.0) / float(mu.std(0).mean())
        assert abs(latent_noise_to_code_spread(model, meshes) - expected) < 1e-6 * expected
        with torch.no_grad():
            model.encoder.logvar.bias += 2.0 * math.log(2.0)  # twice the noise, the same codes
        assert abs(latent_noise_to_code_spread(model, meshes) - 2.0 * expected) < 1e-5 * expected
        # One expression repeated: codes that do not spread at all; fewer than 2 frames: no spread to take.
        assert latent_noise_to_code_spread(model, meshes[:1].expand(4, -1, -1)) > 1e6
        assert math.isnan(latent_noise_to_code_spread(model, meshes[:1]))


def _trained_ratio(tensors, renderer, tmp_path, kld: float) -> float:
    with weights_restored(renderer.model):
        tr, _ = train_steps(renderer, tensors, tmp_path / f"k{kld}.pt", trainer_mod.LossWeights(kld=kld), steps=60,
                            lr=3e-3, frames=6)
        return latent_noise_to_code_spread(tr.model, tensors.guide_vertices[:6])


def test_a_heavier_kl_weight_trains_a_noisier_code(tensors_and_renderer, tmp_path):
    # The KL pulls every log-variance towards 0 (sigma 1) and every code towards 0: the heavier it
    # weighs against the other terms, the more of a training code is the noise draw (at tiny's
    # learning rate; this small model's codes run away at a much larger one).
    tensors, renderer = tensors_and_renderer
    light, heavy = (_trained_ratio(tensors, renderer, tmp_path, kld) for kld in (0.0, 1.0))
    assert heavy > 10.0 * light
