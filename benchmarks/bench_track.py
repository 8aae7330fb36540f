"""Tracking benchmark: fit speed on the CPU and the stability chart.

Synthetic scenes (``stages.track.synthetic``: the ICT face with 6 expression shapes, 120
landmarks on the skin, cameras 1 m away) with known poses and weights, so every figure is
an error against exact truth, without a detector in the loop:

- speed: key frames per second of the sequential fit (10 cameras), and of the whole
  tracker including the landmark embedding;
- stability: mean face vertex error (mm) and head rotation error (deg) against landmark
  noise (px), outlier rate (far-off landmarks, +-40 px) and number of cameras, each swept
  with the others at their defaults (1 px noise, 5 % outliers, 10 cameras). The whole
  tracker runs per point (embedding included), so the chart shows where it breaks. These
  scenes have no images, hence no head outline: the pose figures are the landmark term's
  alone (on the tiny rendered capture, landmarks alone gave ~1.1 deg mean rotation error,
  with the outline refinement 0.06 deg).

Writes ``bench-results/track.json`` and ``bench-results/track_stability.png``.
Run: ``python -m benchmarks.run_all track``. Timings on a shared CPU are noisy.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

FACE = slice(0, 9409)  # ICT face-region vertices
NOISE_PX = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0)
OUTLIER_RATES = (0.0, 0.05, 0.1, 0.2, 0.3, 0.4)
CAMERAS = (2, 3, 4, 6, 8, 10)
DEFAULTS = {"noise_px": 1.0, "outlier_rate": 0.05, "cameras": 10}


def _errors(scene, fits) -> tuple[float, float]:
    from stages.track.geometry import rotation_angle_deg

    vert, rot = [], []
    for f, fit in enumerate(fits):
        if fit is None:
            vert.append(np.nan)
            rot.append(np.nan)
            continue
        diff = scene.rig.mesh(fit.pose.weights)[FACE] - scene.rig.mesh(scene.weights[f])[FACE]
        vert.append(float(np.linalg.norm(diff, axis=1).mean() * 1000))
        rot.append(float(rotation_angle_deg(fit.pose.R, scene.R[f])))
    return float(np.nanmean(vert)), float(np.nanmean(rot))


def _run_point(noise_px: float, outlier_rate: float, cameras: int, frames: int = 8) -> dict:
    from stages.track.synthetic import make_scene
    from stages.track.tracker import KeyFrameObservations, Tracker, TrackerParams

    scene = make_scene(frames=frames, landmarks=120, cameras=cameras, seed=2)
    uv = scene.project(noise_px=noise_px, outlier_rate=outlier_rate, seed=3)
    tracker = Tracker(scene.rig, scene.cameras, scene.skin_triangles, None, TrackerParams(embed_frames=frames))
    try:
        result = tracker.run(KeyFrameObservations(uv, np.ones(uv.shape[:2]), scene.embedding.landmark_ids),
                             [str(i) for i in range(frames)])
    except ValueError:  # too few views to even embed: the far end of the chart
        return {"vertex_err_mm": float("nan"), "rotation_err_deg": float("nan"), "failed": True}
    vert, rot = _errors(scene, result.fits)
    return {"vertex_err_mm": vert, "rotation_err_deg": rot, "failed": False}


def speed() -> dict:
    """Key frames per second of the fit alone and of the whole tracker (10 cameras, 120 landmarks)."""
    from threadpoolctl import threadpool_limits

    from stages.track.synthetic import make_scene
    from stages.track.tracker import KeyFrameObservations, Tracker, TrackerParams, observation_confidence

    frames = 24
    scene = make_scene(frames=frames, landmarks=120, cameras=10, seed=4)
    uv = scene.project(noise_px=1.0, outlier_rate=0.05, seed=5)
    score = np.ones(uv.shape[:2])
    tracker = Tracker(scene.rig, scene.cameras, scene.skin_triangles, None, TrackerParams())
    names = [str(i) for i in range(frames)]
    ideal, conf = observation_confidence(scene.cameras, uv, score)
    with threadpool_limits(limits=1):
        start = time.perf_counter()
        tracker.fit_sequence(scene.embedding, scene.embedding.landmark_ids, ideal, conf, names)
        fit_s = time.perf_counter() - start
    start = time.perf_counter()
    tracker.run(KeyFrameObservations(uv, score, scene.embedding.landmark_ids), names)
    total_s = time.perf_counter() - start
    return {"fit_frames_per_second": frames / fit_s, "tracker_frames_per_second": frames / total_s,
            "speed_frames": frames, "speed_cameras": 10, "speed_landmarks": 120, "speed_blendshapes": 6}


def stability() -> dict:
    """The three sweeps; each returns per-point vertex and rotation errors."""
    sweeps = {
        "noise_px": [_run_point(v, DEFAULTS["outlier_rate"], DEFAULTS["cameras"]) for v in NOISE_PX],
        "outlier_rate": [_run_point(DEFAULTS["noise_px"], v, DEFAULTS["cameras"]) for v in OUTLIER_RATES],
        "cameras": [_run_point(DEFAULTS["noise_px"], DEFAULTS["outlier_rate"], v) for v in CAMERAS],
    }
    return sweeps


def plot(sweeps: dict, path: Path) -> None:
    """Three panels: vertex error (left axis) and rotation error (right axis) per sweep."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4.2))
    for ax, (key, xs, label) in zip(axes, (("noise_px", NOISE_PX, "landmark noise (px, sigma)"),
                                           ("outlier_rate", OUTLIER_RATES, "outlier rate (far-off landmarks)"),
                                           ("cameras", CAMERAS, "cameras used"))):
        vert = [p["vertex_err_mm"] for p in sweeps[key]]
        rot = [p["rotation_err_deg"] for p in sweeps[key]]
        ax.plot(xs, vert, "o-", color="tab:blue", label="vertex error (mm)")
        ax.axhline(1.0, color="tab:blue", ls=":", lw=1, label="target 1.0 mm")
        ax.set_xlabel(label)
        ax.set_ylabel("mean face vertex error (mm)", color="tab:blue")
        ax.set_yscale("log")
        twin = ax.twinx()
        twin.plot(xs, rot, "s--", color="tab:red", label="rotation error (deg)")
        twin.axhline(0.2, color="tab:red", ls=":", lw=1)
        twin.set_ylabel("head rotation error (deg)", color="tab:red")
        twin.set_yscale("log")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper left", fontsize=8)
    fig.suptitle("Tracking stability, landmark term alone (synthetic landmarks, exact truth; "
                 "others at 1 px, 5 % outliers, 10 cameras)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    out = Path("bench-results")
    out.mkdir(exist_ok=True)
    results: dict = speed()
    print(f"track fit: {results['fit_frames_per_second']:.1f} key frames/s (fit only), "
          f"{results['tracker_frames_per_second']:.1f} key frames/s (with embedding); 10 cameras, 120 landmarks")
    sweeps = stability()
    for key, xs in (("noise_px", NOISE_PX), ("outlier_rate", OUTLIER_RATES), ("cameras", CAMERAS)):
        for x, point in zip(xs, sweeps[key]):
            print(f"  {key}={x:<5}  vertex {point['vertex_err_mm']:.3f} mm  rotation {point['rotation_err_deg']:.3f} deg")
    plot(sweeps, out / "track_stability.png")
    results["stability"] = {key: [dict(point, value=x) for x, point in zip(xs, sweeps[key])]
                            for key, xs in (("noise_px", NOISE_PX), ("outlier_rate", OUTLIER_RATES),
                                            ("cameras", CAMERAS))}
    (out / "track.json").write_text(json.dumps(results, indent=1))
    print(f"wrote {out / 'track.json'} and {out / 'track_stability.png'}")


if __name__ == "__main__":
    main()
