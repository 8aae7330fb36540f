"""Calibration stability sweep: camera calibration error against image noise and board poses.

Renders the studio rig's board take once without noise at the cameras' native resolution
(768x1024, as the capture stage shoots it; the mirror take at the tiny preset's 240x320),
then calibrates (stage ``calibrate``, evaluated by ``calibrate_eval``) on
- the first N board poses, N in POSES (at the take's default noise), and
- every pose with sensor noise sigma in NOISES added to the clean images,
so a user sees how many poses are enough and how much noise the calibration tolerates.
Errors are those of ``calibrate/cameras.json`` at the performance resolution (240x320);
``principal_err_px_max_native`` is at 768x1024.
The 24-pose run also places all 32 LED bars (stage ``lightcal`` on the mirror-ball take,
evaluated by ``lightcal_eval``) with the calibrated cameras: the rig's headline figures.
Prints a table, writes ``bench-results/calibration.json`` and ``bench-results/calibration.png``.
Timings on a shared 2-core machine are noisy; the errors are deterministic for a seed.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

POSES = (8, 12, 16, 24, 36)
NOISES = (0.001, 0.003, 0.01, 0.03)
DEFAULT_NOISE = 0.003
LIGHTCAL_POSES = 24
KEYS = ("reproj_rms_px", "focal_err_pct_max", "principal_err_px_max", "center_err_mm_max", "rotation_err_deg_max")


def _noisy_copy(clean: Path, dst: Path, noise: float, keep_poses: int | None, seed: int,
                mirror: bool = False) -> None:
    """Copy a capture, adding sensor noise to the board (and mirror) images, keeping only the first poses."""
    from scene.image_io import read_exr, write_exr
    from stages.capture.output import CaptureOutput

    copy = CaptureOutput(dst)
    shutil.copytree(clean, dst, ignore=None if mirror else shutil.ignore_patterns(copy.mirror_dir.name))
    rng = np.random.default_rng(seed)
    if mirror:
        for path in copy.mirror_images():
            img = read_exr(path)
            noisy = np.clip(img[..., :1] + rng.normal(0.0, noise, size=img.shape[:2] + (1,)), 0.0, 1.0)
            write_exr(path, np.repeat(noisy, 3, axis=-1))
    for path in sorted(p for cam in copy.charuco_cameras() for p in copy.charuco_images(cam)):
        if keep_poses is not None and int(path.stem) >= keep_poses:
            path.unlink()
            continue
        img = read_exr(path)
        noisy = np.clip(img[..., :1] + rng.normal(0.0, noise, size=img.shape[:2] + (1,)), 0.0, 1.0)
        write_exr(path, np.repeat(noisy, 3, axis=-1))


def _place_bars(capture: Path, calibrate: Path, truth: Path, work: Path) -> dict:
    from pipeline.scratch import run_stage_in_folder
    from stages.lightcal.eval_stage import STAGE as EVAL
    from stages.lightcal.stage import STAGE

    out = run_stage_in_folder(STAGE, work, inputs={"capture": capture, "calibrate": calibrate})
    ev = run_stage_in_folder(EVAL, work, inputs={"lightcal": out, "capture.truth": truth})
    return {**json.loads((out / "metrics.json").read_text()), **json.loads((ev / "metrics.json").read_text())}


def _calibrate(capture: Path, truth: Path, work: Path) -> dict:
    from pipeline.errors import PipelineError
    from pipeline.scratch import run_stage_in_folder
    from stages.calibrate.eval_stage import STAGE as EVAL
    from stages.calibrate.stage import STAGE

    try:
        out = run_stage_in_folder(STAGE, work, inputs={"capture": capture})
    except PipelineError as err:  # too few poses for some camera: that is a result too
        return {"failed": str(err)[:160]}
    ev = run_stage_in_folder(EVAL, work, inputs={"calibrate": out, "capture.truth": truth})
    m = {**json.loads((out / "metrics.json").read_text()), **json.loads((ev / "metrics.json").read_text())}
    return {k: m[k] for k in KEYS + ("board_frames", "corners_used", "volume_reproj_err_px_max",
                                      "volume_reproj_err_px_mean", "principal_err_px_max_native")}


def _plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(13, 7))
    for row, (sweep, xs, xlabel) in enumerate((("poses", POSES, "board poses"),
                                                ("noise", NOISES, "noise sigma (linear)"))):
        runs = results[sweep]
        for col, (key, target) in enumerate((("focal_err_pct_max", 0.2), ("center_err_mm_max", 1.0),
                                             ("rotation_err_deg_max", 0.05))):
            ax = axes[row, col]
            ok = [(x, r[key]) for x, r in zip(xs, runs) if key in r]
            if ok:
                ax.plot([o[0] for o in ok], [o[1] for o in ok], "o-")
            ax.axhline(target, color="red", ls="--", lw=1, label="target")
            ax.set_xlabel(xlabel)
            ax.set_ylabel(key)
            if sweep == "noise":
                ax.set_xscale("log")
            ax.set_yscale("log")
            ax.legend()
    fig.suptitle("Camera calibration error vs board poses (noise 0.003) and vs noise (36 poses); 10 cameras, "
                 "board take at 768x1024, errors at 240x320")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> None:
    """Run the sweep; print the table; write the JSON and the chart."""
    from hardware.studio.calibration_takes import CalibrationTakeParams, render_rig_takes

    out_dir = Path("bench-results")
    out_dir.mkdir(exist_ok=True)
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        render_rig_takes(root / "clean", root / "truth", CalibrationTakeParams(poses=max(POSES), noise=0.0))
        render_s = time.perf_counter() - start
        results: dict = {"poses": [], "noise": []}
        for i, n in enumerate(POSES):
            _noisy_copy(root / "clean", root / f"p{n}", DEFAULT_NOISE, n, seed=i, mirror=n == LIGHTCAL_POSES)
            results["poses"].append(_calibrate(root / f"p{n}", root / "truth", root / f"wp{n}"))
            if n == LIGHTCAL_POSES and "failed" not in results["poses"][-1]:
                results["lightcal"] = _place_bars(root / f"p{n}", root / f"wp{n}" / "calibrate", root / "truth",
                                                  root / "wl")
            shutil.rmtree(root / f"p{n}")
        for i, s in enumerate(NOISES):
            _noisy_copy(root / "clean", root / f"n{i}", s, None, seed=100 + i)
            results["noise"].append(_calibrate(root / f"n{i}", root / "truth", root / f"wn{i}"))
            shutil.rmtree(root / f"n{i}")
    keys = KEYS + ("volume_reproj_err_px_max",)
    header = f"{'setting':>14} " + " ".join(f"{k:>24}" for k in keys)
    print(header)
    for sweep, xs, fmt in (("poses", POSES, "poses={}"), ("noise", NOISES, "noise={}")):
        for x, r in zip(xs, results[sweep]):
            cells = " ".join(f"{r[k]:>24.4f}" if k in r else f"{'failed':>24}" for k in keys)
            print(f"{fmt.format(x):>14} {cells}")
    if "lightcal" in results:
        lc = results["lightcal"]
        print(f"lightcal (32 bars, {LIGHTCAL_POSES}-pose calibration): bar centre error mean "
              f"{lc['bar_center_err_mm_mean']:.1f} mm, median {lc['bar_center_err_mm_median']:.1f} mm, max "
              f"{lc['bar_center_err_mm_max']:.1f} mm; axis error mean {lc.get('bar_axis_err_deg_mean', float('nan')):.2f}"
              f" deg; ray residual mean {lc['residual_mm_mean']:.1f} mm")
    _plot(results, out_dir / "calibration.png")
    summary = {"poses": list(POSES), "noises": list(NOISES), "default_noise": DEFAULT_NOISE,
               "resolution": "board take 768x1024 (native), errors at 240x320 (tiny preset)", "cameras": 10, "render_seconds": render_s,
               "seconds": time.perf_counter() - start, **results}
    (out_dir / "calibration.json").write_text(json.dumps(summary, indent=1))
    print(f"wrote {out_dir / 'calibration.json'} and {out_dir / 'calibration.png'} "
          f"({summary['seconds']:.0f} s, timings noisy on a shared machine)")


if __name__ == "__main__":
    main()
