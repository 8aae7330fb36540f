"""Held-out splits: interior bars, held-out segment of the last take, disjoint masks."""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull

from avatar.travatar import direction_uv
from stages.train.splits import interior_bars, make_splits, nearest_training_distance_mm


def _bar_dirs() -> dict[int, np.ndarray]:
    az = np.deg2rad(np.tile(np.linspace(-80, 80, 8), 4))
    el = np.deg2rad(np.repeat([-30, 0, 28, 56], 8))
    return {i: np.array([np.cos(e) * np.sin(a), np.sin(e), np.cos(e) * np.cos(a)]) for i, (a, e) in enumerate(zip(az, el))}


def test_interior_bars_are_inside_the_hull_of_the_rest():
    dirs = _bar_dirs()
    held = interior_bars(dirs, 3)
    assert len(held) == 3
    rest = np.stack([dirs[b] for b in dirs if b not in held])
    hull = ConvexHull(direction_uv(rest))
    for b in held:
        uv = direction_uv(dirs[b][None])[0]
        assert (hull.equations[:, :2] @ uv + hull.equations[:, 2]).max() < 0  # strictly inside


def test_held_out_segment_of_the_last_take():
    dirs = _bar_dirs()
    take = np.array(["rom"] * 32 + ["speech"] * 32)
    bar = np.concatenate([np.arange(32), np.arange(32)])
    s = make_splits(take, bar, dirs, 3, "", 0.5)
    assert s.novel_perf.sum() + s.novel_both.sum() == 16
    assert np.all(np.flatnonzero(s.novel_perf | s.novel_both) >= 48)
    assert s.novel_both.any() and s.novel_light.any()
    masks = np.stack([s.train, s.novel_light, s.novel_perf, s.novel_both])
    assert np.all(masks.sum(0) == 1)
    assert not np.isin(bar[s.train], s.held_out_bars).any()


def test_nearest_training_distance_is_to_the_closest_other_training_mesh():
    rng = np.random.default_rng(0)
    base = rng.normal(size=(50, 3)) * 0.05  # [V, 3] metres
    shift_mm = np.array([0.0, 1.0, 3.0, 10.0, 2.5])  # each frame's mesh moved along x by this
    vertices = base[None] + np.stack([[s / 1000.0, 0.0, 0.0] for s in shift_mm])[:, None]
    train = np.array([True, True, True, False, False])
    query = np.array([False, False, False, True, True])
    # Held out: 10 mm -> nearest training 3 mm (7 mm away); 2.5 mm -> 3 mm (0.5 mm away).
    np.testing.assert_allclose(nearest_training_distance_mm(vertices, train, query), [7.0, 0.5], atol=1e-4)
    # RMS over vertices: half the vertices moved by 2 mm, half not at all is sqrt(2) mm (the mean would say 1).
    pair = np.stack([base, base])
    pair[1, :25, 0] += 0.002
    np.testing.assert_allclose(nearest_training_distance_mm(pair, np.array([True, False]), np.array([False, True])),
                               [np.sqrt(2.0)], atol=1e-4)
    # Training frames never count themselves: 0 -> 1, 1 -> 0, 3 -> 1 mm. Chunking changes nothing.
    np.testing.assert_allclose(nearest_training_distance_mm(vertices, train, train, chunk=2), [1.0, 1.0, 2.0],
                               atol=1e-4)
