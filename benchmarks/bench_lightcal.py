"""Light calibration: LED bar placement from the mirror take, coarse images vs native windows.

Renders the studio rig's mirror-sphere take alone (10 cameras, 32 bars, no board) as the
tiny preset's capture shoots it: full images at 240x320 plus native (768x1024) windows
around the balls and highlights (``CalibrationTakeParams.mirror_roi``). Then places every
bar (stage ``lightcal`` with the true cameras, so only the light calibration's error shows;
``lightcal_eval``) twice: from the native windows, and from the full images alone.
Prints mean / median / max centre error, the side bars' (more than SIDE_DEG from the
cameras' axis: grazing highlights) separately, a per-bar table (error, ray residual,
highlights used), the render seconds of both parts of the take and lightcal's seconds.
Writes ``bench-results/lightcal.json``. Timings on a shared 2-core machine are noisy; the
errors are deterministic for the seed.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np

SIDE_DEG = 60.0
TARGET_MM = 10.0


def _place(capture: Path, truth: Path, work: Path, **params) -> tuple[dict, dict, dict, float]:
    from pipeline.scratch import run_stage_in_folder
    from stages.lightcal.eval_stage import STAGE as EVAL
    from stages.lightcal.output import LightcalOutput
    from stages.lightcal.stage import STAGE

    start = time.perf_counter()
    out = run_stage_in_folder(STAGE, work, inputs={"capture": capture, "calibrate": truth}, params=params)
    seconds = time.perf_counter() - start
    ev = run_stage_in_folder(EVAL, work, inputs={"lightcal": out, "capture.truth": truth})
    metrics = {**json.loads((out / "metrics.json").read_text()), **json.loads((ev / "metrics.json").read_text())}
    placed = LightcalOutput(out)
    bars = {int(b["id"]): b for b in placed.bars()}
    return metrics, bars, placed.report(), seconds


def _per_bar(bars: dict, report: dict, truth_bars: list[dict], side: set[int]) -> list[dict]:
    rows = []
    for t in truth_bars:
        b = bars.get(int(t["id"]))
        row = {"id": int(t["id"]), "side": int(t["id"]) in side}
        if b is not None:
            row.update(err_mm=1e3 * float(np.linalg.norm(np.subtract(b["center_world"], t["center_world"]))),
                       residual_mm=float(b["residual_mm"]), rays=int(b["rays"]),
                       method=report.get(f"bar{int(t['id']):02d}", {}).get("method"))
        rows.append(row)
    return rows


def _summary(rows: list[dict]) -> dict:
    out = {}
    for name, sel in (("all", rows), ("side", [r for r in rows if r["side"]]),
                      ("front", [r for r in rows if not r["side"]])):
        errs = [r["err_mm"] for r in sel if "err_mm" in r]
        if errs:
            out[name] = {"bars": len(errs), "err_mm_mean": float(np.mean(errs)),
                         "err_mm_median": float(np.median(errs)), "err_mm_max": float(np.max(errs))}
    return out


def main() -> None:
    """Render the take, place the bars both ways, print and write the figures."""
    from hardware.studio.calibration_takes import BarLight, CalibrationTakeParams, render_mirror_take, takes_from_rig
    from scene.rig import default_rig
    from stages.capture.output import CaptureOutput, CaptureTruth

    out_dir = Path("bench-results")
    out_dir.mkdir(exist_ok=True)
    rig = default_rig()
    coarse, native = rig.cameras_at(0.3125), rig.cameras_at(1.0)
    light_bars = rig.light_bars()
    bars = [BarLight(b.id, b.center_world, b.axis_world, b.length_m, b.intensity, b.normal_world) for b in light_bars]
    _, spheres = takes_from_rig(rig)
    head = np.asarray(rig.head_center_m, float)
    cam_axis = np.mean([c.center_world - head for c in coarse], axis=0)
    cam_axis /= np.linalg.norm(cam_axis)
    side = {int(b.id) for b in light_bars
            if np.degrees(np.arccos((b.center_world - head) @ cam_axis / np.linalg.norm(b.center_world - head)))
            > SIDE_DEG}
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        params = CalibrationTakeParams(volume_center_m=tuple(head))
        take_s = render_mirror_take(coarse, bars, root / "capture", root / "truth", params, spheres,
                                    roi_cameras=native)
        truth, capture = CaptureTruth(root / "truth"), CaptureOutput(root / "capture")
        truth.write_cameras(coarse)
        truth_bars = [b.to_dict() for b in light_bars]
        truth.write_bars({"bars": truth_bars})
        windows_bytes = sum(p.stat().st_size for p in capture.mirror_roi_images())
        full_bytes = sum(p.stat().st_size for p in capture.mirror_images())
        runs = {}
        for name, use_windows in (("windows", True), ("full_images", False)):
            metrics, placed, report, seconds = _place(root / "capture", root / "truth", root / name,
                                                      use_windows=use_windows)
            rows = _per_bar(placed, report, truth_bars, side)
            runs[name] = {"metrics": metrics, "lightcal_seconds": seconds, "summary": _summary(rows), "bars": rows}
    print(f"mirror take (10 cameras, 32 bars): full 240x320 images {take_s['full_s']:.1f} s, native windows "
          f"{take_s['windows_s']:.1f} s ({windows_bytes / 1e6:.1f} MB of windows, {full_bytes / 1e6:.1f} MB of "
          "full images)")
    print(f"{'path':>12} {'lightcal_s':>10} {'mean_mm':>8} {'median_mm':>9} {'max_mm':>7} {'side_mean':>9} "
          f"{'side_max':>8} {'front_mean':>10} {'residual_mm':>11}")
    for name, r in runs.items():
        s = r["summary"]
        print(f"{name:>12} {r['lightcal_seconds']:>10.1f} {s['all']['err_mm_mean']:>8.2f} "
              f"{s['all']['err_mm_median']:>9.2f} {s['all']['err_mm_max']:>7.2f} {s['side']['err_mm_mean']:>9.2f} "
              f"{s['side']['err_mm_max']:>8.2f} {s['front']['err_mm_mean']:>10.2f} "
              f"{r['metrics']['residual_mm_mean']:>11.2f}")
    print(f"side bars (> {SIDE_DEG:.0f} deg from the cameras' axis): {sorted(side)}")
    print("per bar, native windows:  id  err_mm  residual_mm  rays  method")
    for row in runs["windows"]["bars"]:
        if "err_mm" in row:
            print(f"{'':>24}{row['id']:>4} {row['err_mm']:>7.2f} {row['residual_mm']:>12.2f} {row['rays']:>5}  "
                  f"{row['method']}{'  (side)' if row['side'] else ''}")
    summary = {"cameras": len(coarse), "bars": len(bars), "coarse_resolution": "240x320",
               "native_resolution": "768x1024", "target_mm": TARGET_MM, "side_deg": SIDE_DEG,
               "side_bars": sorted(side), "take_seconds": take_s, "windows_bytes": windows_bytes,
               "full_bytes": full_bytes, "seconds": time.perf_counter() - start, **runs}
    (out_dir / "lightcal.json").write_text(json.dumps(summary, indent=1))
    print(f"wrote {out_dir / 'lightcal.json'} ({summary['seconds']:.0f} s, timings noisy on a shared machine)")


if __name__ == "__main__":
    main()
