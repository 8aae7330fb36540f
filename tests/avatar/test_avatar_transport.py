"""The colour transport (``avatar.transport``): its weights times any colour grid are the raymarch of that grid."""

from __future__ import annotations

import pytest
import torch

from avatar.raymarch import Primitives, raymarch
from avatar.transport import colour_transport
from tests.avatar.test_avatar_raymarch import _scene


def _first(prims: Primitives) -> Primitives:
    return Primitives(*(x[:1] for x in (prims.centre, prims.rotation, prims.half_extent, prims.rgb, prims.density)))


def test_colour_transport_renders_any_colours_as_the_raymarch_does(kernel):
    """The recorded weights times a colour grid are the raymarch of that grid (same opacity), for several grids at once."""
    prims, o, d = _scene(density=6.0)  # many rays saturate: the weights carry the early termination
    prims, o, d = _first(prims), o[:1], d[:1]
    transport = colour_transport(prims, o, d, steps=24, kernel=kernel)
    assert transport.matrix.layout == torch.sparse_csr and transport.nnz > 0
    g = torch.Generator().manual_seed(5)
    grids = [prims.rgb] + [torch.rand(prims.rgb.shape, generator=g, dtype=prims.rgb.dtype) for _ in range(2)]
    stacked = torch.cat([x[0] for x in grids], -1)  # [P, M, M, M, 9]: three grids in one product
    pixels = transport.apply(stacked)  # [R, 9]
    for i, rgb in enumerate(grids):
        res = raymarch(prims.with_rgb(rgb), o, d, steps=24, kernel=kernel)
        torch.testing.assert_close(pixels[:, 3 * i:3 * i + 3], res.rgb[0], rtol=1e-9, atol=1e-11)
        torch.testing.assert_close(transport.alpha, res.alpha[0], rtol=1e-9, atol=1e-11)
    assert (res.alpha > 0.999).any() and (res.alpha < 0.5).any()


def test_colour_transport_is_the_same_in_chunks():
    prims, o, d = _scene(r=60)
    prims, o, d = _first(prims), o[:1], d[:1]
    whole = colour_transport(prims, o, d, steps=16, kernel="torch")
    # Tiny budgets: several ray chunks, and several accumulation blocks within each.
    for budget in (60, 7):
        parts = colour_transport(prims, o, d, steps=16, max_pairs=budget, kernel="torch")
        torch.testing.assert_close(parts.matrix.to_dense(), whole.matrix.to_dense(), rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(parts.alpha, whole.alpha, rtol=1e-12, atol=1e-14)


def test_colour_transport_takes_one_geometry():
    prims, o, d = _scene()
    with pytest.raises(ValueError, match="batch 1"):
        colour_transport(prims, o, d, steps=8)
