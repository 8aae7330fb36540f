"""Stability sweeps: where each method of the pipeline breaks, and the threshold crossing of each.

``make bench-stability`` (``python -m benchmarks.stability [sweep ...]``) runs, on the tiny
preset's sizes, sweeps named:

- ``track``: tracking vertex / rotation error against landmark noise, outlier rate and
  number of cameras (``benchmarks.bench_track.stability``; synthetic landmarks, exact truth).
  Thresholds: the report's targets, 1.0 mm mean vertex error and 0.2 deg head rotation error.
- ``calibration``: camera calibration error against image noise and number of board poses
  (``benchmarks.bench_calibration.main``, which writes its own ``calibration.json``).
  Thresholds: focal error 0.2 %, camera centre error 1.0 mm, rotation error 0.05 deg.
- ``dropped``: frame labelling (``stages.capture.labelling.label_frames``) against the rate of
  frames a camera drops: the studio films two OLAT pattern cycles with the rig's 10 cameras
  (the tiny capture's brightness, sensor noise included), frames are then dropped at random;
  the error is the share of frames labelled ``ok`` with the wrong light (which would train
  the model on a wrong light). Threshold: 1 %.
- ``blur``: motion blur of the full-on frames (a horizontal box kernel of L pixels, applied to
  the image and to the true matte alike, as a moving head blurs both) against the classical
  matte's MAE (``stages.matte.baseline``; needs no trained network) and the landmark
  detector's (MediaPipe, ``stages.track.landmarks``) displacement from its sharp-image
  detection plus its failures. Thresholds: matte MAE 0.01 (the report's target), landmark
  displacement 1.0 px (median over landmarks, 240x320 images).

Each sweep's crossing is found by ``stages.evaluate.sweeps.first_crossing`` walking from the
benign end (no noise, all cameras, no drops, no blur). Prints a table of the crossings,
writes ``bench-results/stability.json`` (top-level scalars: the crossings) and
``bench-results/stability_*.png``. Timings on a shared 2-core CPU are noisy; errors are
deterministic for the seeds used.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

OUT = Path("bench-results")
DROP_RATES = (0.0, 0.01, 0.02, 0.05, 0.1, 0.2, 0.3)
DROP_SEEDS = (0, 1, 2)
BLUR_PX = (0, 2, 4, 8, 16, 32)
LABEL_ERROR_MAX = 0.01
MATTE_MAE_MAX = 0.01
LANDMARK_SHIFT_MAX_PX = 1.0
TRACK_VERTEX_MAX_MM = 1.0
TRACK_ROTATION_MAX_DEG = 0.2
CALIBRATION_TARGETS = {"focal_err_pct_max": 0.2, "center_err_mm_max": 1.0, "rotation_err_deg_max": 0.05}
CAPTURE_SCALE = 0.3125  # the tiny preset's 240x320 images


def crossing_record(x, values, threshold: float, higher_is_better: bool = False) -> dict:
    """The break point of one curve (walked in the order given) as a JSON record."""
    from stages.evaluate.sweeps import first_crossing

    c = first_crossing(np.asarray(x, float), np.asarray(values, float), threshold, higher_is_better=higher_is_better)
    return {"x": c.x, "censored": c.censored, "failed_at_start": c.failed_at_start, "threshold": threshold}


def describe(c: dict, unit: str) -> str:
    """One phrase for a crossing record."""
    if c["censored"]:
        return f"holds over the whole sweep (to {c['x']:g}{unit})"
    if c["failed_at_start"]:
        return f"already past the threshold at {c['x']:g}{unit}"
    return f"breaks at {c['x']:.3g}{unit}"


# --- tracking --------------------------------------------------------------------------------------

def track_sweep() -> dict:
    """Tracking error sweeps (benchmarks.bench_track) and their crossings."""
    from benchmarks import bench_track

    sweeps = bench_track.stability()
    bench_track.plot(sweeps, OUT / "stability_track.png")
    axes = {"noise_px": (bench_track.NOISE_PX, False), "outlier_rate": (bench_track.OUTLIER_RATES, False),
            "cameras": (bench_track.CAMERAS, True)}  # cameras: walk from the most cameras down
    result: dict = {"points": {}, "crossings": {}}
    for key, (xs, reverse) in axes.items():
        points = sweeps[key]
        order = list(range(len(xs)))[::-1] if reverse else list(range(len(xs)))
        xs_walk = [xs[i] for i in order]
        result["points"][key] = [dict(points[i], value=xs[i]) for i in range(len(xs))]
        # A failed fit (NaN) counts as past the threshold.
        result["crossings"][f"{key}_vertex"] = crossing_record(
            xs_walk, [points[i]["vertex_err_mm"] for i in order], TRACK_VERTEX_MAX_MM)
        result["crossings"][f"{key}_rotation"] = crossing_record(
            xs_walk, [points[i]["rotation_err_deg"] for i in order], TRACK_ROTATION_MAX_DEG)
    return result


# --- calibration -----------------------------------------------------------------------------------

def calibration_sweep(reuse: bool = False) -> dict:
    """Calibration error sweeps (benchmarks.bench_calibration.main) and their crossings.

    ``reuse``: read the ``bench-results/calibration.json`` an earlier ``make bench`` wrote
    instead of running the calibration benchmark again (it is the slowest sweep).
    """
    from benchmarks import bench_calibration

    if not (reuse and (OUT / "calibration.json").is_file()):
        bench_calibration.main()  # writes bench-results/calibration.json and calibration.png
    data = json.loads((OUT / "calibration.json").read_text())
    result: dict = {"crossings": {}, "bench_seconds": data.get("seconds"), "reused": bool(reuse)}
    # Poses: walk from the most poses down; noise: from the least noise up. The x values are
    # bench_calibration's constants (its JSON's "poses" key holds the per-run results).
    for sweep, xs, reverse in (("poses", bench_calibration.POSES, True), ("noise", bench_calibration.NOISES, False)):
        runs = data[sweep]
        if len(runs) != len(xs):
            raise ValueError(f"{OUT / 'calibration.json'}: {len(runs)} '{sweep}' runs for {len(xs)} settings; it comes "
                             "from another version of bench_calibration, run without --reuse-calibration")
        order = list(range(len(xs)))[::-1] if reverse else list(range(len(xs)))
        for key, bound in CALIBRATION_TARGETS.items():
            values = [runs[i].get(key, float("nan")) for i in order]  # a failed calibration is NaN
            result["crossings"][f"{sweep}_{key}"] = crossing_record([xs[i] for i in order], values, bound)
    return result


# --- dropped frames --------------------------------------------------------------------------------

def _film_pattern(cycles: int = 2) -> tuple[list, np.ndarray]:
    """The controller log's lights [K] and every camera's mean luminance per pulse [C, K] (no drops)."""
    from hardware.studio import RenderSettings, VirtualStudio, make_performance, make_subject
    from scene.colour import luminance
    from scene.rig import default_rig
    from stages.sequence.order import angle_matrix_deg, bar_directions, solve_olat_order
    from stages.sequence.schedule import build_pattern

    rig = default_rig()
    bars = rig.light_bars()
    centres = np.stack([b.center_world for b in bars])
    order = solve_olat_order(angle_matrix_deg(bar_directions(centres, np.asarray(rig.head_center_m))),
                             method="local", restarts=2)
    pattern = build_pattern(order.olat_order, 2)
    log = [pattern[k % len(pattern)] for k in range(cycles * len(pattern))]
    frames = make_performance(seed=1, frames_per_take=len(log) // 2)
    cameras = rig.cameras_at(0.125)  # brightness only: a coarse image has the same mean
    studio = VirtualStudio(rig, make_subject("alice", 1, texture_size=256), RenderSettings(seed=1))
    brightness = np.zeros((len(cameras), len(log)))
    for k, light in enumerate(log):
        for c, cam in enumerate(cameras):
            brightness[c, k] = float(luminance(studio.render(frames[k], cam, light).rgb).mean())
    return log, brightness


def label_errors(log: list, brightness: np.ndarray, drop_rate: float, seed: int) -> dict:
    """Drop each (camera, pulse) with ``drop_rate``, label, and score against the truth."""
    from stages.capture.labelling import label_frames

    rng = np.random.default_rng(seed)
    keep = rng.random(brightness.shape) >= drop_rate  # [C, K]
    streams = [brightness[c, keep[c]] for c in range(len(brightness))]
    truth = [np.flatnonzero(keep[c]) for c in range(len(brightness))]
    try:
        result = label_frames(log, streams)
    except ValueError:  # too far out of step to align at all
        return {"wrong_ok_rate": 1.0, "missed_drops": int((~keep).sum()), "usable_pulses": 0.0, "failed": True}
    wrong = ok = 0
    for cam, expected in zip(result.cameras, truth):
        for pulse, status, true_pulse in zip(cam.pulse, cam.status, expected):
            if status == "ok":
                ok += 1
                wrong += int(pulse != true_pulse)
    # A dropped (camera, pulse) that labelling still fills with some frame is a missed drop.
    missed = int(((result.pulse_frame >= 0) & ~keep).sum())
    usable = float(np.mean([s == "ok" for s in result.pulse_status]))
    return {"wrong_ok_rate": wrong / max(ok, 1), "missed_drops": missed, "usable_pulses": usable, "failed": False}


def dropped_sweep() -> dict:
    """Labelling errors against the drop rate (mean over seeds) and the crossing."""
    start = time.perf_counter()
    log, brightness = _film_pattern()
    film_s = time.perf_counter() - start
    points = []
    for rate in DROP_RATES:
        runs = [label_errors(log, brightness, rate, seed) for seed in DROP_SEEDS]
        points.append({"drop_rate": rate, **{k: float(np.mean([r[k] for r in runs]))
                                             for k in ("wrong_ok_rate", "missed_drops", "usable_pulses")},
                       "failures": int(sum(r["failed"] for r in runs))})
    crossing = crossing_record(DROP_RATES, [p["wrong_ok_rate"] for p in points], LABEL_ERROR_MAX)
    _plot_dropped(points, crossing)
    return {"points": points, "crossings": {"wrong_ok_rate": crossing}, "pulses": len(log),
            "cameras": int(brightness.shape[0]), "film_seconds": film_s}


def _plot_dropped(points: list[dict], crossing: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rates = [p["drop_rate"] for p in points]
    fig, ax = plt.subplots(figsize=(6.5, 4))
    ax.plot(rates, [100 * p["wrong_ok_rate"] for p in points], "o-", label="frames labelled ok with the wrong light (%)")
    ax.plot(rates, [100 * (1 - p["usable_pulses"]) for p in points], "s--", label="pulses lost for training (%)")
    ax.axhline(100 * LABEL_ERROR_MAX, color="k", ls=":", lw=1, label=f"threshold {100 * LABEL_ERROR_MAX:g} %")
    ax.axvline(crossing["x"], color="#c0392b", lw=1.2, label=describe(crossing, ""))
    ax.set_xlabel("per-camera frame drop rate")
    ax.set_ylabel("%")
    ax.set_title("Frame labelling against dropped frames (10 cameras, 2 OLAT cycles)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "stability_dropped_frames.png", dpi=100)
    plt.close(fig)


# --- motion blur -----------------------------------------------------------------------------------

def motion_blur(image: np.ndarray, length_px: int) -> np.ndarray:
    """Horizontal box blur of ``length_px`` pixels (a head moving sideways during the exposure), centred."""
    import cv2

    if length_px <= 1:
        return np.asarray(image, np.float32).copy()
    kernel = np.full((1, int(length_px)), 1.0 / int(length_px), np.float32)
    return cv2.filter2D(np.asarray(image, np.float32), -1, kernel, borderType=cv2.BORDER_CONSTANT)


def blur_sweep(cameras_used: tuple[int, ...] = (2, 4, 5, 7), frames_used: int = 2) -> dict:
    """Matte MAE and landmark displacement against motion blur length (full-on frames, 240x320)."""
    from hardware.studio import RenderSettings, VirtualStudio, make_performance, make_subject
    from scene.rig import default_rig
    from stages.matte.baseline import baseline_matte
    from stages.track.landmarks import DetectorParams, FaceMeshDetector

    rig = default_rig()
    cameras = [rig.cameras_at(CAPTURE_SCALE)[i] for i in cameras_used]
    studio = VirtualStudio(rig, make_subject("alice", 1, texture_size=512), RenderSettings(seed=1))
    frames = make_performance(seed=1, frames_per_take=12)[::6][:frames_used]
    views = [studio.render(f, cam, "F") for f in frames for cam in cameras]
    mae = {L: [] for L in BLUR_PX}
    shift = {L: [] for L in BLUR_PX}
    failures = {L: 0 for L in BLUR_PX}
    with FaceMeshDetector(DetectorParams()) as detector:
        for view in views:
            sharp = detector.detect(view.rgb)
            for L in BLUR_PX:
                rgb, alpha = motion_blur(view.rgb, L), motion_blur(view.alpha, L)
                mae[L].append(float(np.abs(baseline_matte(rgb) - alpha).mean()))
                found = detector.detect(rgb) if L else sharp
                if not (sharp.ok and found.ok):
                    failures[L] += 1
                    continue
                shift[L].append(float(np.median(np.linalg.norm(found.uv_px - sharp.uv_px, axis=1))))
    points = [{"blur_px": L, "matte_mae": float(np.mean(mae[L])),
               "landmark_shift_px": float(np.mean(shift[L])) if shift[L] else float("nan"),
               "landmark_failures": failures[L], "views": len(views)} for L in BLUR_PX]
    crossings = {"matte_mae": crossing_record(BLUR_PX, [p["matte_mae"] for p in points], MATTE_MAE_MAX),
                 "landmark_shift_px": crossing_record(BLUR_PX, [p["landmark_shift_px"] for p in points],
                                                      LANDMARK_SHIFT_MAX_PX)}
    _plot_blur(points, crossings)
    return {"points": points, "crossings": crossings}


def _plot_blur(points: list[dict], crossings: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    blur = [p["blur_px"] for p in points]
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(10, 3.8))
    ax0.plot(blur, [p["matte_mae"] for p in points], "o-")
    ax0.axhline(MATTE_MAE_MAX, color="k", ls=":", lw=1, label=f"target {MATTE_MAE_MAX:g}")
    ax0.axvline(crossings["matte_mae"]["x"], color="#c0392b", lw=1.2, label=describe(crossings["matte_mae"], " px"))
    ax0.set_ylabel("classical matte MAE vs blurred true matte")
    ax1.plot(blur, [p["landmark_shift_px"] for p in points], "o-")
    ax1.axhline(LANDMARK_SHIFT_MAX_PX, color="k", ls=":", lw=1, label=f"threshold {LANDMARK_SHIFT_MAX_PX:g} px")
    ax1.axvline(crossings["landmark_shift_px"]["x"], color="#c0392b", lw=1.2,
                label=describe(crossings["landmark_shift_px"], " px"))
    ax1.set_ylabel("landmark shift from sharp (px, median)")
    for ax in (ax0, ax1):
        ax.set_xlabel("horizontal motion blur (px, 240x320 image)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("Motion blur: matting and landmark detection (full-on frames, 4 cameras)")
    fig.tight_layout()
    fig.savefig(OUT / "stability_motion_blur.png", dpi=100)
    plt.close(fig)


# --- driver ----------------------------------------------------------------------------------------

SWEEPS = {"track": (track_sweep, {"noise_px": " px", "outlier_rate": "", "cameras": " cameras"}),
          "calibration": (calibration_sweep, {"poses": " poses", "noise": ""}),
          "dropped": (dropped_sweep, {"wrong_ok_rate": ""}),
          "blur": (blur_sweep, {"matte_mae": " px", "landmark_shift_px": " px"})}


def _unit(units: dict, key: str) -> str:
    return next((u for prefix, u in units.items() if key.startswith(prefix)), "")


def main(argv: list[str] | None = None) -> int:
    """Run the named sweeps (default: all), print every crossing, write the JSON and charts.

    ``--reuse-calibration``: take the calibration sweep from an existing ``calibration.json``.
    A sweep that fails is reported and the others still run (exit code 1).
    """
    import torch

    torch.set_num_threads(1)
    args = list(argv if argv is not None else sys.argv[1:])
    reuse = "--reuse-calibration" in args
    names = [a for a in args if a != "--reuse-calibration"] or list(SWEEPS)
    unknown = [n for n in names if n not in SWEEPS]
    if unknown:
        print(f"unknown sweep(s) {unknown}; known: {', '.join(SWEEPS)}", file=sys.stderr)
        return 2
    OUT.mkdir(exist_ok=True)
    path = OUT / "stability.json"
    summary: dict = json.loads(path.read_text()) if path.is_file() else {}
    failed: list[str] = []
    for name in names:
        fn, units = SWEEPS[name]
        print(f"\n=== stability: {name} ===", flush=True)
        start = time.perf_counter()
        try:
            result = fn(reuse) if name == "calibration" else fn()
        except Exception as err:  # one broken sweep must not hide the others' crossings
            failed.append(name)
            print(f"  {name} FAILED: {type(err).__name__}: {err}", flush=True)
            continue
        result["seconds"] = time.perf_counter() - start
        summary[name] = result
        for key, c in result["crossings"].items():
            summary[f"{name}_{key}_limit"] = c["x"]  # the report shows top-level scalars
            summary[f"{name}_{key}_censored"] = int(c["censored"])  # 1: never crossed, the limit is a bound
            print(f"  {name:<12} {key:<32} threshold {c['threshold']:<6g} {describe(c, _unit(units, key))}", flush=True)
        summary[f"{name}_seconds"] = result["seconds"]
        print(f"  ({result['seconds']:.0f} s; timings noisy on a shared CPU)", flush=True)
        path.write_text(json.dumps(summary, indent=1) + "\n")
    print(f"\nwrote {path} and {OUT}/stability_*.png")
    if failed:
        print(f"failed sweeps: {', '.join(failed)}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
