"""Shapes and behaviour of the network's building blocks."""

import torch

from stages.matte.inputs import pad_to_multiple
from stages.matte.modnet import SIZES, IBNorm, MODNet, SEBlock


def test_ibnorm_batch_half_and_instance_half():
    torch.manual_seed(0)
    norm = IBNorm(6).train()
    x = torch.randn(4, 6, 8, 8) * 3.0 + 5.0  # [B, C, H, W]
    y = norm(x)
    assert y.shape == x.shape
    assert norm.batch_channels == 3 and norm.instance_channels == 3
    # Instance half: every image's channel has zero mean on its own.
    assert torch.allclose(y[:, 3:].mean(dim=(2, 3)), torch.zeros(4, 3), atol=1e-4)
    # Batch half: zero mean over the batch, but not per image (images differ in offset).
    x[0, :3] += 10.0
    y = norm(x)
    assert torch.allclose(y[:, :3].mean(dim=(0, 2, 3)), torch.zeros(3), atol=1e-4)
    assert y[0, :3].mean() > 0.5


def test_ibnorm_odd_channels():
    assert IBNorm(5)(torch.randn(2, 5, 4, 4)).shape == (2, 5, 4, 4)
    assert IBNorm(1).train()(torch.randn(2, 1, 4, 4)).shape == (2, 1, 4, 4)


def test_se_block_reweights_channels():
    se = SEBlock(8, reduction=4)
    x = torch.rand(2, 8, 5, 7) + 0.1
    y = se(x)
    assert y.shape == x.shape
    ratio = y / x  # per-channel weights in (0, 1), constant over pixels
    assert torch.all(ratio > 0) and torch.all(ratio < 1)
    assert torch.allclose(ratio, ratio[:, :, :1, :1].expand_as(ratio), atol=1e-6)


def test_modnet_output_shapes_and_ranges():
    model = MODNet(SIZES["tiny"]).eval()
    x = pad_to_multiple(torch.randn(2, 6, 70, 50), 32)
    assert x.shape[-2:] == (96, 64)
    semantic, detail, matte = model(x)
    assert semantic.shape == (2, 1, 6, 4)
    assert detail.shape == matte.shape == (2, 1, 96, 64)
    for out in (semantic, detail, matte):
        assert torch.all(out >= 0) and torch.all(out <= 1)


def test_large_size_is_larger():
    tiny = sum(p.numel() for p in MODNet(SIZES["tiny"]).parameters())
    large = sum(p.numel() for p in MODNet(SIZES["large"]).parameters())
    assert 20_000 < tiny < 200_000 and large > 10 * tiny
