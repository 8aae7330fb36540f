"""Benchmark of the sequencing and LED controller pieces.

Figures: the OLAT order's angles against naive and random orders and the solver's time
(exact integer program vs local search); the emulated controller's round trip, upload and
session rates through the real pyserial client on a pty; and the frame labeller's
throughput and accuracy on synthetic brightness with dropped, repeated and dark frames
(image means and 2x2 quadrant means). Writes ``bench-results/sequence.json``.
"""

from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

import numpy as np

from hardware.led import LedController, LedEmulator, run_emulated_session
from scene.rig import default_rig
from stages.capture.labelling import label_frames
from stages.sequence.order import (angle_matrix_deg, bar_directions, cycle_angles_deg, olat_upper_bounds,
                                   random_baseline_mean_deg, solve_olat_order)
from stages.sequence.schedule import build_pattern


def _order_figures() -> tuple[dict, list]:
    rig = default_rig()
    centres = np.array([b.center_m for b in rig.bars])
    angles = angle_matrix_deg(bar_directions(centres, np.array(rig.head_center_m)))
    start = time.perf_counter()
    exact = solve_olat_order(angles, method="exact")
    exact_s = time.perf_counter() - start
    start = time.perf_counter()
    local = solve_olat_order(angles, method="local")
    local_s = time.perf_counter() - start
    naive = cycle_angles_deg(angles, np.arange(len(centres)))
    min_bound, mean_bound = olat_upper_bounds(angles)
    figures = {
        "bars": len(centres),
        "olat_angle_mean_deg": exact.mean_deg, "olat_angle_min_deg": exact.min_deg,
        "local_search_angle_mean_deg": local.mean_deg, "local_search_angle_min_deg": local.min_deg,
        "naive_olat_angle_mean_deg": float(naive.mean()), "naive_olat_angle_min_deg": float(naive.min()),
        "random_olat_angle_mean_deg": random_baseline_mean_deg(angles, seed=0),
        "olat_angle_min_upper_bound_deg": min_bound, "olat_angle_mean_upper_bound_deg": mean_bound,
        "exact_solve_seconds": exact_s, "local_search_seconds": local_s,
    }
    return figures, build_pattern(list(exact.olat_order), 2)


def _controller_figures(pattern: list) -> dict:
    with LedEmulator(n_bars=32) as emulator, LedController(emulator.port) as controller:
        controller.ping()
        pings_ms = [controller.ping() * 1e3 for _ in range(200)]
        start = time.perf_counter()
        for _ in range(10):
            controller.upload(pattern, 4)
        upload_s = (time.perf_counter() - start) / 10
        start = time.perf_counter()
        controller.verify_program(pattern, 4)
        readback_s = time.perf_counter() - start
    n_frames = 24 * 60  # one minute of capture
    start = time.perf_counter()
    session = run_emulated_session(pattern, n_frames, trigger_times_s=[i / 24 for i in range(n_frames)])
    session_s = time.perf_counter() - start
    if len(session.log) != n_frames:
        raise RuntimeError(f"session logged {len(session.log)} of {n_frames} pulses")
    return {
        "ping_round_trip_ms_median": statistics.median(pings_ms),
        "ping_round_trip_ms_p95": float(np.percentile(pings_ms, 95)),
        "upload_seconds_48_steps": upload_s, "readback_seconds_48_steps": readback_s,
        "session_seconds_1440_frames": session_s,
        "log_entries_per_second": n_frames / session_s,
    }


def _synthetic_capture(pattern: list, cycles: int, n_cameras: int, seed: int, quadrants: bool):
    """Brightness of received frames from the rig's geometry (a bar lights the quadrants that face it)."""
    rig = default_rig()
    rng = np.random.default_rng(seed)
    bars = bar_directions(np.array([b.center_m for b in rig.bars]), np.array(rig.head_center_m))  # [B, 3]
    cams = bar_directions(np.array([c.position_m for c in rig.cameras]), np.array(rig.head_center_m))[:n_cameras]
    offsets = np.radians([[-35, 25], [35, 25], [-35, -25], [35, -25]])
    profiles = np.zeros((n_cameras, len(bars), 4))
    for c, cam in enumerate(cams):
        az, el = np.arctan2(cam[0], cam[2]), np.arcsin(cam[1])
        for d, (da, de) in enumerate(offsets):
            normal = np.array([np.sin(az + da) * np.cos(el + de), np.sin(el + de), np.cos(az + da) * np.cos(el + de)])
            profiles[c, :, d] = np.clip(bars @ normal, 0, None) ** 2 + 0.02
    log = [pattern[i % len(pattern)] for i in range(cycles * len(pattern))]
    n = len(log)
    drops = {(int(rng.integers(n_cameras)), int(rng.integers(n))) for _ in range(n // 40)}
    repeats = {(int(rng.integers(n_cameras)), int(rng.integers(n))) for _ in range(n // 200 + 1)}
    brightness, truth = [], []
    for c in range(n_cameras):
        values, labels = [], []
        for k, light in enumerate(log):
            if (c, k) in drops:
                continue
            value = profiles[c].sum(axis=0) if light == "F" else profiles[c, light]
            value = value * np.exp(rng.normal(0, 0.04, 4))
            values.append(value if quadrants else value.mean())
            labels.append(k)
            if (c, k) in repeats:
                values.append(values[-1])
                labels.append(-1)
        brightness.append(np.array(values))
        truth.append(np.array(labels))
    return log, brightness, truth, len(drops)


def _labelling_figures(pattern: list) -> dict:
    figures = {}
    for quadrants, name in ((False, "image_mean"), (True, "quadrants")):
        log, brightness, truth, n_drops = _synthetic_capture(pattern, cycles=20, n_cameras=10, seed=1,
                                                            quadrants=quadrants)
        start = time.perf_counter()
        result = label_frames(log, brightness)
        seconds = time.perf_counter() - start
        frames = sum(len(b) for b in brightness)
        wrong = sum(int(((np.array(cam.status) == "ok") & (cam.pulse != t)).sum())
                    for cam, t in zip(result.cameras, truth))
        figures.update({
            f"labelling_{name}_frames_per_second": frames / seconds,
            f"labelling_{name}_wrong_ok_labels": wrong,
            f"labelling_{name}_ambiguous_frames": result.count("ambiguous"),
            f"labelling_{name}_frames": frames,
            f"labelling_{name}_dropped_found": result.dropped_frames(),
            f"labelling_{name}_dropped_true": n_drops,
        })
    return figures


def main() -> None:
    """Print the figures and write ``bench-results/sequence.json``."""
    figures, pattern = _order_figures()
    figures.update(_controller_figures(pattern))
    figures.update(_labelling_figures(pattern))
    for key, value in figures.items():
        print(f"{key:45s} {value:.4g}" if isinstance(value, float) else f"{key:45s} {value}")
    out = Path("bench-results")
    out.mkdir(exist_ok=True)
    (out / "sequence.json").write_text(json.dumps(figures, indent=1))


if __name__ == "__main__":
    main()
