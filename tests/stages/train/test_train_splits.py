"""Splits: interior bars, held-out segments of the last take, disjoint masks, validation apart from test."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from avatar.travatar import direction_uv
from stages.train.splits import ALL_SPLITS, VAL_SPLITS, SPLITS, ValidationSplit, interior_bars, make_splits, \
    expression_reach_sd, nearest_training_distance_mm


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
    s = make_splits(take, bar, dirs, 3, "", 0.5, ValidationSplit(bars=2, fraction=0.25))
    test_segment = np.flatnonzero(s.novel_perf | s.novel_both | (s.unused & (np.arange(64) >= 48)))
    assert np.array_equal(test_segment, np.arange(48, 64))  # the final half of "speech"
    assert s.novel_both.any() and s.novel_light.any()
    masks = np.stack([s.mask(name) for name in ALL_SPLITS])
    assert np.all(masks.sum(0) == 1)
    assert not np.isin(bar[s.train], s.held_out_bars).any()


def _frames_of(s, names) -> set[int]:
    return set(np.flatnonzero(np.any([s.mask(n) for n in names], axis=0)).tolist())


@pytest.mark.parametrize("held_out_fraction", [0.5, 1.0])
def test_validation_holds_its_own_bars_and_frames_apart_from_the_test(held_out_fraction):
    dirs = _bar_dirs()
    take = np.array(["rom"] * 32 + ["speech"] * 32)
    bar = np.concatenate([np.arange(32), np.arange(32)])
    s = make_splits(take, bar, dirs, 3, "", held_out_fraction, ValidationSplit(bars=2, fraction=0.25))
    # Validation's bars: two interior bars, none of the test's, inside the hull of the other bars (of the
    # training bars where the training performance lights every bar; with the whole take held out for the
    # test, validation's segment takes the last row of bars from training).
    assert len(s.val_bars) == 2 and not set(s.val_bars) & set(s.held_out_bars)
    training_bars = set(bar[s.train].tolist())
    assert not training_bars & (set(s.val_bars) | set(s.held_out_bars))
    others = training_bars if held_out_fraction < 1 else set(dirs) - set(s.val_bars + s.held_out_bars)
    hull = ConvexHull(direction_uv(np.stack([dirs[b] for b in sorted(others)])))
    for b in s.val_bars + s.held_out_bars:
        uv = direction_uv(dirs[b][None])[0]
        assert (hull.equations[:, :2] @ uv + hull.equations[:, 2]).max() < 0
    # Validation's frames: the 8 frames (a quarter of "speech") just before the test segment.
    test_start = 64 - int(round(32 * held_out_fraction))
    val_segment = np.arange(test_start - 8, test_start)
    assert _frames_of(s, ("val_perf",)) <= set(val_segment.tolist())
    assert set(val_segment.tolist()) <= _frames_of(s, ("val_perf", "unused"))
    # Every frame in one split; validation and test share no frame, no bar, and neither trains.
    assert np.all(np.stack([s.mask(name) for name in ALL_SPLITS]).sum(0) == 1)
    val, test, train = _frames_of(s, VAL_SPLITS), _frames_of(s, SPLITS), _frames_of(s, ("train",))
    assert val and test and train and not (val & test) and not (train & (val | test))
    assert set(bar[sorted(val)].tolist()).isdisjoint(s.held_out_bars)
    assert set(bar[sorted(test)].tolist()).isdisjoint(s.val_bars)
    assert not set(range(test_start, 64)) & (val | train)  # the test segment trains nothing, validates nothing
    assert all(s.mask(name).any() for name in ("val_light", "val_perf", "novel_light", "novel_perf"))
    assert np.isin(bar[s.val_light], s.val_bars).all() and not s.val_light[test_start - 8:].any()
    if held_out_fraction == 0.5:
        assert s.val_segment == "speech[8:16]" and s.held_out_take == "speech[16:]"
    else:  # the test holds out all of "speech": validation is the end of "rom"
        assert s.val_segment == "rom[24:32]" and s.held_out_take == "speech"


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


def test_expression_reach_counts_training_deviations_along_the_most_extreme_mode():
    rng = np.random.default_rng(1)
    base = rng.normal(size=(40, 3)) * 0.05  # [V, 3] metres
    smile, blink = rng.normal(size=(2, 40, 3))
    smile /= np.linalg.norm(smile)
    blink -= (blink * smile).sum() * smile  # orthogonal to the smile
    blink /= np.linalg.norm(blink)
    # Training: smile amplitudes +-2 cm and blinks +-0.5 cm, each frame one or the other, so the
    # training std is 2 cm / sqrt(2) along the smile, 0.5 cm / sqrt(2) along the blink.
    amplitudes = np.array([[0.02, 0], [-0.02, 0], [0, 0.005], [0, -0.005]])
    held_out = np.array([[0.04, 0], [0, 0.005], [0.01, 0.0025], [0, 0]])  # 2x the smile; a blink; inside; the mean
    coeffs = np.concatenate([amplitudes, held_out])
    vertices = base[None] + coeffs[:, 0, None, None] * smile + coeffs[:, 1, None, None] * blink
    train = np.arange(8) < 4
    reach = expression_reach_sd(vertices, train, ~train)
    sd = np.sqrt(2.0)  # a training amplitude is sqrt(2) standard deviations out along its mode
    np.testing.assert_allclose(reach, [2 * sd, sd, 0.5 * sd, 0.0], atol=1e-6)
    # Training frames reach the edge of their own range; a blink is as far out as a smile in sd units.
    np.testing.assert_allclose(expression_reach_sd(vertices, train, train), [sd] * 4, atol=1e-6)
    # A mode holding under 1 - variance of the spread is not counted: keep only the smile.
    weak = np.array([[0.02, 0], [-0.02, 0], [0, 1e-5], [0, -1e-5], [0, 0.005]])
    w = base[None] + weak[:, 0, None, None] * smile + weak[:, 1, None, None] * blink
    only_smile = expression_reach_sd(w, np.arange(5) < 4, np.arange(5) == 4, variance=0.99)
    np.testing.assert_allclose(only_smile, [0.0], atol=1e-6)
    # Still meshes: nothing to reach along.
    still = np.repeat(base[None], 3, 0)
    np.testing.assert_array_equal(expression_reach_sd(still, np.array([True, True, False]),
                                                      np.array([False, False, True])), [0.0])
