"""MODNet losses: transition region, supervised loss, SOC loss."""

import torch

from stages.matte.losses import semantic_target, soc_loss, supervised_loss, transition_region


def _disc(size: int = 64) -> torch.Tensor:
    ys, xs = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    r = ((xs - size / 2) ** 2 + (ys - size / 2) ** 2).float().sqrt()
    return (size / 4 + 0.5 - r).clamp(0, 1)[None, None]  # [1, 1, H, W] anti-aliased disc


def test_transition_region_hugs_the_edge():
    alpha = _disc()
    region = transition_region(alpha, 3)
    assert region[0, 0, 32, 32].item() is False  # deep inside
    assert region[0, 0, 0, 0].item() is False  # far outside
    assert region[0, 0, 32, 32 + 16].item() is True  # on the edge (radius 16)
    assert region.float().mean() < 0.25


def test_supervised_loss_is_small_for_the_truth_and_large_for_its_inverse():
    alpha = _disc()
    image = alpha.expand(1, 3, 64, 64)
    good, parts = supervised_loss(semantic_target(alpha), alpha, alpha, alpha, image)
    bad, _ = supervised_loss(1 - semantic_target(alpha), 1 - alpha, 1 - alpha, alpha, image)
    assert good.item() < 1e-6 and parts["matte_l1"] < 1e-6
    assert bad.item() > 1.0


def test_soc_loss_zero_when_consistent_and_anchored():
    alpha = _disc()
    loss, parts = soc_loss(semantic_target(alpha), alpha, alpha, alpha, alpha)
    assert loss.item() < 1e-6
    drift, _ = soc_loss(semantic_target(alpha), alpha * 0.5, alpha, alpha, alpha)
    assert drift.item() > 0.01
