"""The reach term (``avatar.reach``): how far the nearest box misses a foreground ray no box reaches."""

from __future__ import annotations

import math

import pytest
import torch
from scipy.spatial.transform import Rotation

from avatar.raymarch import Primitives, raymarch
from avatar.reach import missed_rays, reach_penalty


def _boxes(centres: list[list[float]], half: list[list[float]], rotations: torch.Tensor | None = None) -> Primitives:
    p = len(centres)
    centre = torch.tensor([centres], dtype=torch.float64)
    half_extent = torch.tensor([half], dtype=torch.float64)
    rotation = torch.eye(3, dtype=torch.float64).expand(1, p, 3, 3).clone() if rotations is None else rotations
    density = torch.full((1, p, 2, 2, 2), 5.0, dtype=torch.float64)
    return Primitives(centre, rotation, half_extent, torch.rand(1, p, 2, 2, 2, 3, dtype=torch.float64), density)


def _rays(origins: list[list[float]], directions: list[list[float]]) -> tuple[torch.Tensor, torch.Tensor]:
    o = torch.tensor([origins], dtype=torch.float64)
    d = torch.tensor([directions], dtype=torch.float64)
    return o, d / d.norm(dim=-1, keepdim=True)


def _penalty(prims: Primitives, o: torch.Tensor, d: torch.Tensor, wanted: torch.Tensor) -> tuple[torch.Tensor, int]:
    """The reach term as the trainer takes it, with the rays' rendered opacity."""
    with torch.no_grad():
        alpha = raymarch(prims, o, d, steps=8, kernel="torch").alpha
    return reach_penalty(prims, o, d, wanted, alpha)


def test_the_gap_is_the_distance_in_the_nearest_boxs_half_extents():
    # Two boxes; a ray along +z at x = 3 passes 3 from the first box's centre (half extent 1: gap 2)
    # and 2 from the second's (half extent 0.5 across x: 4 half extents, gap 3). The nearest is the first.
    prims = _boxes([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]], [[1.0, 1.0, 1.0], [0.5, 0.5, 0.5]])
    o, d = _rays([[3.0, 0.0, -5.0], [0.0, 0.0, -5.0]], [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    wanted = torch.tensor([[True, True]])
    assert missed_rays(prims, o, d, wanted).tolist() == [[True, False]]  # the second ray crosses the first box
    penalty, missed = _penalty(prims, o, d, wanted)
    assert missed == 1
    assert float(penalty) == pytest.approx(2.0 / 2)  # summed over missed rays, divided by all 2 rays


def test_rays_that_hit_a_box_or_are_not_wanted_cost_nothing():
    prims = _boxes([[0.0, 0.0, 0.0]], [[1.0, 1.0, 1.0]])
    o, d = _rays([[0.5, 0.5, -5.0], [3.0, 0.0, -5.0]], [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    prims.centre.requires_grad_()
    penalty, missed = _penalty(prims, o, d, torch.tensor([[True, False]]))  # the missing ray is background
    assert missed == 0 and float(penalty.detach()) == 0.0
    penalty.backward()  # still part of the graph, with no pull
    assert float(prims.centre.grad.abs().max()) == 0.0


def test_nothing_behind_the_camera_counts_as_near():
    # The ray's line passes through the box, but the box is behind the ray's origin: the gap is from the origin.
    prims = _boxes([[0.0, 0.0, 0.0]], [[1.0, 1.0, 1.0]])
    o, d = _rays([[0.0, 0.0, 4.0]], [[0.0, 0.0, 1.0]])
    penalty, missed = _penalty(prims, o, d, torch.tensor([[True]]))
    assert missed == 1 and float(penalty) == pytest.approx(3.0)


def test_the_gradient_moves_grows_and_turns_the_nearest_box_towards_the_ray():
    rot = torch.tensor(Rotation.from_euler("z", 30, degrees=True).as_matrix(), dtype=torch.float64)[None, None]
    prims = _boxes([[0.0, 0.0, 0.0], [-4.0, 0.0, 0.0]], [[0.4, 0.6, 0.5], [0.5, 0.5, 0.5]], rot.repeat(1, 2, 1, 1))
    o, d = _rays([[1.5, 0.2, -5.0]], [[0.0, 0.05, 1.0]])
    wanted = torch.tensor([[True]])
    leaves = [prims.centre.requires_grad_(), prims.half_extent.requires_grad_(), prims.rotation.requires_grad_()]
    before, missed = _penalty(prims, o, d, wanted)
    assert missed == 1 and float(before.detach()) > 0
    before.backward()
    assert float(prims.centre.grad[0, 1].abs().max()) == 0.0  # the far box is left where it is
    assert float(prims.centre.grad[0, 0, 0]) < 0  # descent moves the near box towards +x, where the ray is
    assert (prims.half_extent.grad[0, 0] <= 0).all() and float(prims.half_extent.grad[0, 0].min()) < 0  # grow it
    with torch.no_grad():  # small descent steps close the gap until the box reaches the ray
        for _ in range(400):
            prims.centre -= 0.02 * prims.centre.grad
            prims.half_extent -= 0.02 * prims.half_extent.grad
            prims.centre.grad.zero_()
            prims.half_extent.grad.zero_()
            prims.rotation.grad.zero_()
            with torch.enable_grad():
                penalty, missed = _penalty(prims, o, d, wanted)
                if missed == 0:
                    break
                penalty.backward()
    assert missed == 0
    # Once a box reaches it the ray is the raymarcher's: it renders opaque, and the photometric and matte
    # terms take over.
    assert float(raymarch(prims, o, d, steps=8, kernel="torch").alpha.detach()) > 0.5


def test_a_missed_ray_costs_about_its_distance_on_a_realistic_grid():
    # A 4 x 4 grid of 1 cm boxes and foreground rays from a camera 1 m away, half of them past the grid's edge.
    xs = [(i - 1.5) * 0.02 for i in range(4)]
    prims = _boxes([[x, y, 0.0] for y in xs for x in xs], [[0.01, 0.01, 0.01]] * 16)
    targets = [[0.005, 0.005], [0.06, 0.01], [0.01, -0.07], [0.01, 0.01]]
    o, d = _rays([[0.0, 0.0, -1.0]] * 4, [[x, y, 1.0] for x, y in targets])
    penalty, missed = _penalty(prims, o, d, torch.ones(1, 4, dtype=torch.bool))
    assert missed == 2
    # Ray 2 lands 0.03 past the last column's centre (boxes 2 cm wide): about 3 half extents, gap about 2;
    # ray 3 lands 0.04 under the bottom row's centre: gap about 3. Divided by 4 rays.
    assert float(penalty) == pytest.approx((2.0 + 3.0) / 4, rel=0.02)
    assert math.isfinite(float(penalty))


def test_only_rays_without_opacity_are_tested_and_a_crossing_one_is_never_counted():
    # Boxes with empty voxels: every ray renders with no opacity, so every wanted ray is a candidate, and
    # the slab test must drop the ones that cross a box. The count matches the every-ray-against-every-box test.
    g = torch.Generator().manual_seed(1)
    centre = torch.randn(2, 9, 3, generator=g, dtype=torch.float64) * 0.3
    rotation = torch.tensor(Rotation.random(18, random_state=1).as_matrix(), dtype=torch.float64).view(2, 9, 3, 3)
    half = torch.rand(2, 9, 3, generator=g, dtype=torch.float64) * 0.2 + 0.1
    empty = Primitives(centre, rotation, half, torch.rand(2, 9, 2, 2, 2, 3, dtype=torch.float64),
                       torch.zeros(2, 9, 2, 2, 2, dtype=torch.float64))
    o = torch.zeros(2, 300, 3, dtype=torch.float64)
    o[..., 2] = -3.0
    d = torch.randn(2, 300, 3, generator=g, dtype=torch.float64) * 0.2
    d[..., 2] = 1.0
    d = d / d.norm(dim=-1, keepdim=True)
    wanted = torch.rand(2, 300, generator=g) < 0.7
    exact = missed_rays(empty, o, d, wanted)
    assert 0 < int(exact.sum()) < int(wanted.sum())  # some wanted rays cross a box, some do not
    _, count = reach_penalty(empty, o, d, wanted, torch.zeros(2, 300, dtype=torch.float64))
    assert count == int(exact.sum())
    # With opacity where the boxes are, the same rays are found from the render alone.
    solid = Primitives(centre, rotation, half, empty.rgb, torch.full_like(empty.density, 4.0))
    _, rendered = _penalty(solid, o, d, wanted)
    assert rendered == int(exact.sum())
