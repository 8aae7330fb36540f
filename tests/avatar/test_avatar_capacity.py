"""The capacity rule (monotone, bounded, pixel-limited, clear errors), the footprint and the knee finder."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from avatar.capacity import (CapacityInputError, CapacityRule, CaptureStats, choose_capacity, config_for,
                             count_expression_modes, decoder_width, find_knee, footprint_from_mattes, latent_size,
                             split_texels, texel_px, voxel_px)
from avatar.config import AvatarConfig


def _texels(width_px: int, footprint_px: float, frames: int = 45, rule: CapacityRule | None = None) -> int:
    stats = CaptureStats(width_px, int(round(width_px * 4 / 3)), footprint_px, frames)
    return choose_capacity(stats, rule).texels_per_side


def test_capacity_grows_with_footprint_and_resolution_and_never_shrinks():
    footprints = np.linspace(4, 700, 120)
    texels = [_texels(768, f) for f in footprints]
    assert all(b >= a for a, b in zip(texels, texels[1:]))
    assert texels[-1] > texels[0]
    # The same framing at a higher resolution: the head covers more pixels, more texels.
    by_res = [_texels(w, 0.8 * w) for w in (32, 64, 128, 256, 512, 1024)]
    assert all(b >= a for a, b in zip(by_res, by_res[1:])) and by_res[-1] >= 8 * by_res[0]


def test_width_grows_with_frames_within_bounds():
    rule = CapacityRule()
    widths = [decoder_width(f, rule) for f in (1, 10, 45, 100, 1000, 10 ** 4, 10 ** 6)]
    assert all(b >= a for a, b in zip(widths, widths[1:]))
    assert widths[0] == rule.min_width and widths[-1] == rule.max_width
    assert all(w % 8 == 0 for w in widths)
    small = choose_capacity(CaptureStats(64, 85, 52, 10)).config
    large = choose_capacity(CaptureStats(64, 85, 52, 5000)).config
    assert large.base_channels > small.base_channels and large.rgb_channels[0] > small.rgb_channels[0]
    assert large.prims_per_side == small.prims_per_side  # frames change widths, not resolution


def test_texels_are_not_finer_than_the_rule_allows():
    base = AvatarConfig.tiny()
    for min_texel_px in (0.5, 1.0, 2.0):
        rule = CapacityRule(min_texel_px=min_texel_px)
        for footprint in (20.0, 52.0, 90.0, 300.0, 624.0):
            cap = choose_capacity(CaptureStats(1024, 1024, footprint, 45), rule)
            assert cap.texel_px >= min_texel_px - 1e-9 or cap.texels_per_side == 16  # 16 = the lower bound
            # Twice the texels would make them finer than allowed.
            assert texel_px(2 * cap.texels_per_side, footprint, base) < min_texel_px
            assert cap.texel_px == pytest.approx(texel_px(cap.texels_per_side, footprint, base))
            assert cap.voxel_px == pytest.approx(base.prim_overlap * cap.texel_px)
            assert voxel_px(cap.texels_per_side, footprint, base) == pytest.approx(cap.voxel_px)


def test_bounds_and_valid_configs():
    rule = CapacityRule()
    tiny = choose_capacity(CaptureStats(16, 16, 1.0, 1))
    assert (tiny.config.prims_per_side, tiny.config.voxels_per_side) == (8, 2)
    huge_rule = CapacityRule(max_prims_per_side=64, max_voxels_per_side=16)
    huge = choose_capacity(CaptureStats(8192, 8192, 8000.0, 10 ** 6), huge_rule)
    assert (huge.config.prims_per_side, huge.config.voxels_per_side) == (64, 16)
    assert huge.config.steps_per_ray == rule.max_steps and huge.config.base_channels == rule.max_width
    for texels in (16, 32, 64, 128, 256, 512, 1024, 2048):
        n, m = split_texels(texels, rule)
        assert n * m == texels and n >= 8 and m >= 2
        config = config_for(texels, 56, rule, AvatarConfig.tiny())  # AvatarConfig validates the layer count
        assert config.rgb_channels[-1] == 3 * m and config.alpha_channels[-1] == m


def test_tiny_capture_and_paper_geometry():
    # Tiny: a 64 px wide training image with the head ~52 px wide (95 px of layout): N*M = 64
    # with texels of a pixel, 32 with texels of 2 px.
    tiny = choose_capacity(CaptureStats(64, 85, 52.0, 45), CapacityRule(min_texel_px=1.0)).config
    assert (tiny.prims_per_side, tiny.voxels_per_side) == (16, 4) and tiny.steps_per_ray == 32
    coarser = choose_capacity(CaptureStats(64, 85, 52.0, 45), CapacityRule(min_texel_px=2.0)).config
    assert (coarser.prims_per_side, coarser.voxels_per_side) == (16, 2) and coarser.steps_per_ray == 16
    # Paper: 768 px images, head ~620 px wide, thousands of frames, texels of a pixel -> exactly
    # the paper's sizes.
    paper = choose_capacity(CaptureStats(768, 1024, 620.0, 5000), CapacityRule(min_texel_px=1.0)).config
    ref = AvatarConfig.paper()
    assert (paper.prims_per_side, paper.voxels_per_side) == (ref.prims_per_side, ref.voxels_per_side)
    assert paper.rgb_channels == ref.rgb_channels and paper.alpha_channels == ref.alpha_channels
    assert paper.base_channels == ref.base_channels and paper.steps_per_ray == ref.steps_per_ray


@pytest.mark.parametrize("stats", [
    CaptureStats(64, 85, 0.0, 45), CaptureStats(64, 85, -3.0, 45), CaptureStats(64, 85, float("nan"), 45),
    CaptureStats(0, 85, 40.0, 45), CaptureStats(64, 85, 40.0, 0), CaptureStats(64, 85, 1000.0, 45),
])
def test_nonsense_inputs_raise_a_clear_error(stats):
    with pytest.raises(CapacityInputError, match="capacity rule"):
        choose_capacity(stats)


def test_rule_constants_are_validated():
    with pytest.raises(ValidationError, match="power of two"):
        CapacityRule(max_prims_per_side=100)
    with pytest.raises(ValidationError, match="min_width"):
        CapacityRule(min_width=300)
    with pytest.raises(ValidationError):
        CapacityRule(min_texel_px=0.0)


def test_footprint_from_mattes_is_the_heads_width():
    mattes = np.zeros((3, 2, 40, 50), np.float32)
    mattes[..., 5:30, 10:32] = 1.0  # 22 px wide
    mattes[0, 0] = 0.0  # an empty matte is ignored
    mattes[1, 1, 5:30, 10:40] = 1.0  # one wider view; the median is robust to it
    assert footprint_from_mattes(mattes) == 22.0
    assert footprint_from_mattes(np.zeros((2, 8, 8))) == 0.0


def test_knee_of_synthetic_curves():
    x = np.linspace(0.0, 3.0, 13)
    assert x[find_knee(x, np.minimum(x, 1.0))] == pytest.approx(1.0)  # a corner at x = 1
    assert x[find_knee(x, np.minimum(2.0 * x, 1.0))] == pytest.approx(0.5)
    sat = 1.0 - np.exp(-x / 0.4)  # saturating: the knee is early, before the curve flattens
    k = x[find_knee(x, sat)]
    assert 0.25 <= k <= 1.0
    # Order of the points does not matter; the index refers to the input order.
    perm = np.random.default_rng(0).permutation(len(x))
    assert x[perm][find_knee(x[perm], np.minimum(x, 1.0)[perm])] == pytest.approx(1.0)
    # A curve that rises then falls (overfitting): the knee is at the corner, not at the end.
    hump = np.minimum(x, 1.0) - 0.2 * np.maximum(x - 2.0, 0.0)
    assert x[find_knee(x, hump)] == pytest.approx(1.0)
    assert find_knee(x, np.zeros_like(x)) == 0  # no gain: the smallest is enough
    assert find_knee(x[:2], x[:2]) is None
    with pytest.raises(ValueError):
        find_knee(x, x[:3])


def test_log2_capacity_curve_knee():
    # PSNR against log2(N*M), gaining 3, 1.5, 0.3 dB per doubling: the knee is the 3rd size.
    texels = np.array([32, 64, 128, 256, 512])
    psnr = np.array([20.0, 23.0, 24.5, 24.8, 24.9])
    assert texels[find_knee(np.log2(texels), psnr)] == 128
    assert math.isclose(np.log2(texels[1]), 6.0)


def _meshes(modes: int, frames: int = 60, vertices: int = 500, noise: float = 0.0, seed: int = 0) -> np.ndarray:
    """Meshes [F, V, 3]: a mean plus ``modes`` independent smooth deformations of equal spread."""
    rng = np.random.default_rng(seed)
    mean = rng.normal(size=(vertices, 3))
    t = np.linspace(0, 1, vertices)[:, None]
    basis = np.stack([np.sin((k + 1) * np.pi * t + rng.uniform(0, 6, size=(1, 3))) for k in range(modes)])  # [K, V, 3]
    weights = rng.normal(size=(frames, modes))
    return mean + np.einsum("fk,kvc->fvc", weights, basis) + noise * rng.normal(size=(frames, vertices, 3))


def test_expression_modes_count_the_meshes_own_dimensions():
    for k in (1, 3, 7, 20):
        assert count_expression_modes(_meshes(k), 0.999) == k
    # A mode too weak to matter is not counted; tracking noise adds modes only at a strict threshold.
    noisy = _meshes(5, noise=1e-2)
    assert count_expression_modes(noisy, 0.99) == 5
    assert count_expression_modes(noisy, 0.99999) > 5
    # Subsampling frames and vertices (the paper's thousands of frames) finds the same count.
    many = _meshes(6, frames=1500, vertices=5000)
    assert count_expression_modes(many, 0.999, max_frames=200, max_points=300) == 6
    assert count_expression_modes(_meshes(4)[:1], 0.999) == 0  # one frame: no spread
    still = np.repeat(_meshes(1)[:1], 10, 0)
    assert count_expression_modes(still, 0.999) == 0
    with pytest.raises(ValueError, match=r"\[F, V, 3\]"):
        count_expression_modes(np.zeros((4, 10)), 0.999)


def test_latent_follows_the_expression_modes_within_bounds():
    rule = CapacityRule()
    sizes = [latent_size(k, rule) for k in range(1, 400)]
    assert all(b >= a for a, b in zip(sizes, sizes[1:]))
    assert sizes[0] == rule.min_latent and sizes[-1] == rule.max_latent
    assert all(s & (s - 1) == 0 for s in sizes)
    assert latent_size(6, rule) == 16 and latent_size(8, rule) == 16 and latent_size(9, rule) == 32
    base = AvatarConfig.tiny()
    stats = dict(image_width_px=64, image_height_px=85, footprint_px=52.0, frames=45)
    chosen = choose_capacity(CaptureStats(**stats, expression_modes=6))
    assert chosen.config.latent_dim == 16
    assert chosen.as_metrics()["capacity_latent_dim"] == 16 and chosen.as_metrics()["capacity_expression_modes"] == 6
    # Not measured, or the rule told to leave it: the base's latent size.
    assert choose_capacity(CaptureStats(**stats)).config.latent_dim == base.latent_dim
    off = CapacityRule(latent_per_mode=0)
    assert choose_capacity(CaptureStats(**stats, expression_modes=6), off).config.latent_dim == base.latent_dim
    # The latent changes nothing else the rule chooses.
    a = choose_capacity(CaptureStats(**stats)).config
    b = choose_capacity(CaptureStats(**stats, expression_modes=40)).config
    assert a.model_copy(update={"latent_dim": b.latent_dim}) == b and b.latent_dim == 128
    with pytest.raises(CapacityInputError, match="expression_modes"):
        choose_capacity(CaptureStats(**stats, expression_modes=-1))
    with pytest.raises(ValidationError):
        CapacityRule(min_latent=64, max_latent=32)
