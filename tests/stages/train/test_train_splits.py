"""Held-out splits: interior bars, held-out segment of the last take, disjoint masks."""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull

from avatar.travatar import direction_uv
from stages.train.splits import interior_bars, make_splits


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
