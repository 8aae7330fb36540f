"""How far the volume prior presses the boxes (``train.loss_weights.vol``), seen through ``share_of_boxes_at_smallest``."""

from __future__ import annotations

import pytest
import torch

from avatar.model import share_of_boxes_at_smallest
from stages.train import trainer as trainer_mod
from tests.stages.train.train_synth import train_steps, weights_restored


def test_a_fresh_head_has_room_to_shrink_and_a_pressed_one_none(tensors_and_renderer):
    _, renderer = tensors_and_renderer
    model = renderer.model
    state = {k: v.clone() for k, v in model.state_dict().items()}
    try:
        # Initial boxes are 1.1 x their base size per axis (1.33 x the volume): none at the smallest.
        assert share_of_boxes_at_smallest(model) == 0.0
        with torch.no_grad():
            model.geometry_head.bias[6:9] = -40.0  # sigmoid(-40) ~ 0: every box at its base size
        assert share_of_boxes_at_smallest(model) == 1.0
        with torch.no_grad():
            model.geometry_head.bias[6] = 0.0  # one axis half-way to 2x: every box grown again
        assert share_of_boxes_at_smallest(model) == 0.0
        # After pruning half the boxes, the share is taken over the kept ones (all pressed again here).
        with torch.no_grad():
            model.geometry_head.bias[6] = -40.0
        keep = torch.ones(model.config.num_prims, dtype=torch.bool)
        keep[: model.config.num_prims // 2] = False
        model.prune(keep)
        assert share_of_boxes_at_smallest(model) == 1.0
    finally:
        model.load_state_dict(state)

@pytest.mark.parametrize("vol", [0.0, 10.0])
def test_the_volume_prior_presses_boxes_to_their_smallest_size(tensors_and_renderer, tmp_path, vol):
    tensors, renderer = tensors_and_renderer
    with weights_restored(renderer.model):
        tr, _ = train_steps(renderer, tensors, tmp_path / f"v{vol}.pt", trainer_mod.LossWeights(vol=vol), steps=60,
                            lr=5e-2)
        share = share_of_boxes_at_smallest(tr.model)
        if vol:
            # A heavy prior drives the boxes' scale sigmoids onto their flat tail: within 60 steps a third or more
            # of the boxes sit at their base size (0.45 on this head).
            assert share > 0.3, share
        else:
            assert share < 0.1, share  # without it nothing asks the boxes to shrink that far
