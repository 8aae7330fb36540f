"""How much of the code the decoder trains on is noise (``avatar.model.latent_noise_to_code_spread``), and what sets it."""

from __future__ import annotations

import logging
import math

import numpy as np
import torch

from avatar.model import latent_noise_to_code_spread
from stages.train import trainer as trainer_mod


def test_the_ratio_is_the_mean_noise_over_the_mean_spread_of_the_codes(tensors_and_renderer):
    tensors, renderer = tensors_and_renderer
    model = renderer.model
    state = {k: v.clone() for k, v in model.state_dict().items()}
    meshes = tensors.guide_vertices
    try:
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
    finally:
        model.load_state_dict(state)


def _trained_ratio(tensors, renderer, tmp_path, kld: float) -> float:
    state = {k: v.clone() for k, v in renderer.model.state_dict().items()}
    try:
        tr = trainer_mod.ModelTrainer(renderer, tensors, np.arange(6), iterations=60, batch_size=2,
                                      rays_per_image=16, lr=3e-3, weights=trainer_mod.LossWeights(kld=kld),
                                      seed=0, ckpt_path=tmp_path / f"k{kld}.pt", checkpoint_every=100,
                                      spike_factor=1e9, log=logging.getLogger("test"))
        for _ in range(60):
            tr.step()
        return latent_noise_to_code_spread(tr.model, tensors.guide_vertices[:6])
    finally:
        renderer.model.load_state_dict(state)


def test_a_heavier_kl_weight_trains_a_noisier_code(tensors_and_renderer, tmp_path):
    # The KL pulls every log-variance towards 0 (sigma 1) and every code towards 0: the heavier it
    # weighs against the other terms, the more of a training code is the noise draw (at tiny's
    # learning rate; this small model's codes run away at a much larger one).
    tensors, renderer = tensors_and_renderer
    light, heavy = (_trained_ratio(tensors, renderer, tmp_path, kld) for kld in (0.0, 1.0))
    assert heavy > 10.0 * light
