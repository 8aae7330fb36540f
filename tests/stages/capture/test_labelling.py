"""Frame labelling: dropped, repeated and dark frames in synthetic per-camera brightness."""

from __future__ import annotations

import numpy as np
import pytest

from stages.capture.labelling import align, label_frames

N_CAMERAS, N_BARS = 6, 12
# Consecutive OLAT bars sit on opposite sides, as the sequence stage orders them.
OLAT_ORDER = [0, 7, 2, 9, 4, 11, 6, 1, 8, 3, 10, 5]
PATTERN = [light for i in range(0, N_BARS, 2) for light in ("F", OLAT_ORDER[i], OLAT_ORDER[i + 1])]


def _unit(azimuth_deg: np.ndarray, elevation_deg: np.ndarray) -> np.ndarray:
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    return np.stack([np.sin(az) * np.cos(el), np.sin(el), np.cos(az) * np.cos(el)], axis=-1)


def _profiles(seed: int = 0) -> np.ndarray:
    """[C, B, 4] brightness of the 2x2 image quadrants of each camera under each bar: a bar
    lights the side of the face it faces, and each quadrant sees a different side."""
    rng = np.random.default_rng(seed)
    bars = _unit(rng.uniform(-90, 90, N_BARS), rng.uniform(-30, 60, N_BARS))  # [B, 3]
    cam_az = np.linspace(-70, 70, N_CAMERAS)
    offsets = [(-35, 25), (35, 25), (-35, -25), (35, -25)]  # quadrant normals (azimuth, elevation)
    normals = np.stack([_unit(cam_az + da, np.full(N_CAMERAS, de)) for da, de in offsets], axis=1)  # [C, 4, 3]
    facing = np.einsum("cdk,bk->cbd", normals, bars)
    return np.clip(facing, 0, None) ** 2 + 0.03


def _simulate(cycles: int, drops: set[tuple[int, int]], repeats: set[tuple[int, int]], dark_pulses: set[int],
              noise: float = 0.03, seed: int = 0, quadrants: bool = True):
    """Per camera brightness of received frames ([R, 4] quadrant means, or [R] image means),
    and the true log entry of each (-1: not in the log)."""
    rng = np.random.default_rng(seed)
    profiles = _profiles()  # [C, B, 4]
    log = [PATTERN[i % len(PATTERN)] for i in range(cycles * len(PATTERN))]
    pulses, entry = [], 0
    for t in range(len(log) + len(dark_pulses)):
        if t in dark_pulses:  # the controller missed this trigger: a dark exposure, no log entry
            pulses.append((None, -1))
        else:
            pulses.append((log[entry], entry))
            entry += 1
    brightness, truth = [], []
    for c in range(N_CAMERAS):
        values, labels = [], []
        for t, (light, k) in enumerate(pulses):
            if (c, t) in drops:
                continue
            if light == "F":
                value = profiles[c].sum(axis=0)
            else:
                value = np.full(4, 1e-3) if light is None else profiles[c, light]
            value = value * np.exp(rng.normal(0.0, noise, size=4))
            values.append(value if quadrants else value.mean())
            labels.append(k)
            if (c, t) in repeats:  # the camera delivered this frame twice
                values.append(values[-1])
                labels.append(-1)
        brightness.append(np.array(values))
        truth.append(np.array(labels))
    return log, brightness, truth


@pytest.mark.parametrize("quadrants", [True, False])
def test_clean_capture_is_labelled_in_order(quadrants: bool) -> None:
    log, brightness, truth = _simulate(2, set(), set(), set(), quadrants=quadrants)
    result = label_frames(log, brightness)
    for cam, expected in zip(result.cameras, truth):
        assert np.array_equal(cam.pulse, expected)
        assert cam.status == ["ok"] * len(expected)
        assert cam.light == log
    assert result.pulse_status == ["ok"] * len(log)
    assert result.dropped_frames() == 0 and result.warnings == []


def test_dropped_repeated_and_dark_frames_are_relabelled() -> None:
    drops = {(1, 5), (1, 40), (3, 17), (4, 0), (5, 70)}
    repeats = {(2, 30), (0, 55)}
    log, brightness, truth = _simulate(4, drops, repeats, dark_pulses={50})
    result = label_frames(log, brightness, camera_names=[f"cam{c:02d}" for c in range(N_CAMERAS)])
    for cam, expected in zip(result.cameras, truth):
        assert np.array_equal(cam.pulse, expected), cam.camera
    # Every frame after a drop was shifted against its naive position, and is now right.
    cam1 = result.cameras[1]
    matched = cam1.pulse >= 0
    assert cam1.shifted[5:][matched[5:]].all() and not cam1.shifted[:5].any()
    assert cam1.light[5] == log[6]
    assert result.cameras[2].status[31] == "repeated" and result.cameras[2].light[31] == result.cameras[2].light[30]
    assert all(cam.status[truth_row.tolist().index(-1)] in ("unexpected", "repeated")
               for cam, truth_row in zip(result.cameras, truth))
    assert result.count("repeated") == 2
    assert result.count("unexpected") == N_CAMERAS  # the dark exposure, in every camera
    assert result.dropped_frames() == len(drops)
    dropped_entries = {k for k, status in enumerate(result.pulse_status) if status == "dropped"}
    assert dropped_entries == {5, 40, 17, 0, 69}  # pulse 70 comes after the dark pulse 50
    assert any("cam01" in line and "missing" in line for line in result.warnings)
    assert any("cam02" in line and "repeated" in line for line in result.warnings)


def test_image_means_alone_find_a_dropped_full_on_frame() -> None:
    log, brightness, truth = _simulate(2, {(2, 9), (4, 30)}, {(1, 3)}, set(), quadrants=False)
    result = label_frames(log, brightness)
    for cam, expected in zip(result.cameras, truth):
        assert np.array_equal(cam.pulse, expected)


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_random_drops_with_noisy_brightness(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 3 * len(PATTERN)
    drops = {(int(rng.integers(N_CAMERAS)), int(rng.integers(n))) for _ in range(8)}
    log, brightness, truth = _simulate(3, drops, set(), set(), noise=0.06, seed=seed)
    result = label_frames(log, brightness)
    for cam, expected in zip(result.cameras, truth):
        ok = np.array(cam.status) == "ok"
        # Never a wrong label on a frame called ok; the rest are excluded, and few.
        assert np.array_equal(cam.pulse[ok], expected[ok]), cam.camera
    assert result.count("ambiguous") <= 2
    assert result.count("ok") >= sum(len(expected) for expected in truth) - 2


def test_single_cycle_uses_time_stamps_when_given() -> None:
    drops = {(0, 4), (2, 10), (3, 13)}
    log, brightness, truth = _simulate(1, drops, set(), set())
    times = []
    for c in range(N_CAMERAS):
        kept = [t for t in range(len(log)) if (c, t) not in drops]
        times.append(np.array(kept) / 24.0)
    result = label_frames(log, brightness, frame_times_s=times, log_times_s=np.arange(len(log)) / 24.0)
    for cam, expected in zip(result.cameras, truth):
        assert np.array_equal(cam.pulse, expected)


def test_bad_input_is_refused() -> None:
    with pytest.raises(ValueError, match="camera cam00"):
        label_frames(["F", 1], [np.array([1.0, -2.0])])
    with pytest.raises(ValueError, match="camera names"):
        label_frames(["F", 1], [np.ones(2)], camera_names=["a", "b"])
    with pytest.raises(ValueError, match="log_times_s"):
        label_frames(["F", 1], [np.ones(2)], frame_times_s=[np.zeros(2)])


def _align_reference(match: np.ndarray, extra: np.ndarray, drop: float) -> float:
    """Plain full-grid edit distance: the optimal total cost."""
    n_frames, n_log = match.shape
    cost = np.full((n_frames + 1, n_log + 1), np.inf)
    cost[0, 0] = 0.0
    for r in range(n_frames + 1):
        for k in range(n_log + 1):
            if r > 0 and k > 0:
                cost[r, k] = min(cost[r, k], cost[r - 1, k - 1] + match[r - 1, k - 1])
            if r > 0:
                cost[r, k] = min(cost[r, k], cost[r - 1, k] + extra[r - 1])
            if k > 0:
                cost[r, k] = min(cost[r, k], cost[r, k - 1] + drop)
    return float(cost[n_frames, n_log])


@pytest.mark.parametrize("shape", [(9, 12), (12, 9), (10, 10)])
def test_banded_alignment_matches_full_reference(shape: tuple[int, int]) -> None:
    rng = np.random.default_rng(sum(shape))
    match = rng.uniform(0, 10, size=shape)
    extra = rng.uniform(2, 8, size=shape[0])
    labels = align(match, extra, drop_cost=5.0, band=20)
    matched = labels >= 0
    assert np.all(np.diff(labels[matched]) > 0)  # order kept, each entry used once
    total = match[np.flatnonzero(matched), labels[matched]].sum() + extra[~matched].sum() \
        + 5.0 * (shape[1] - matched.sum())
    assert total == pytest.approx(_align_reference(match, extra, 5.0))


def test_unlit_log_entries_take_the_dark_frames() -> None:
    # The program ran out: the controller logged three pulses with nothing lit.
    log, brightness, truth = _simulate(2, {(0, 7)}, set(), set())
    log = log + [None] * 3
    rng = np.random.default_rng(0)
    brightness = [np.concatenate([b, rng.uniform(0, 1e-4, (3, 4))]) for b in brightness]  # sensor noise only
    result = label_frames(log, brightness)
    for cam, expected in zip(result.cameras, truth):
        n = len(expected)
        assert np.array_equal(cam.pulse[:n], expected)
        assert cam.pulse[n:].tolist() == [len(log) - 3, len(log) - 2, len(log) - 1]
        assert cam.light[n:] == [None] * 3
