"""The calibrate stage from an existing calibration (``calibrate.source``) instead of board takes.

Reads the source (``stages.calibrate.sources``), checks it against the capture (every camera
the capture recorded must be in it; cameras it has beyond those are left out and logged),
validates it by its own reprojection error where it has points, and writes what the board
path writes for downstream stages: ``cameras_native.json`` at the source's resolution,
``cameras.json`` at the performance images', and ``report.json`` (with ``source``). There are
no board poses, residual plots or COLMAP export: the source is the studio's own record.
"""

from __future__ import annotations

import logging

import numpy as np

from pipeline.errors import InputError
from stages.calibrate.output import CalibrateOutput
from stages.calibrate.resolution import (
    capture_cameras,
    performance_size,
    to_performance_resolution,
)
from stages.calibrate.sources import read_calibration_source
from stages.capture.output import CaptureOutput


def calibrate_from_source(capture: CaptureOutput, out: CalibrateOutput, params, metrics: dict,
                          log: logging.Logger) -> None:
    """Write the calibrate stage's outputs from ``params.source`` (see the module docstring)."""
    source = read_calibration_source(params.source, params.source_units_m)
    wanted = capture_cameras(capture)
    missing = [n for n in wanted if n not in source.cameras]
    if missing:
        raise InputError(f"calibrate.source {source.path}: camera {missing[0]} of the capture is not in it"
                         + (f" (nor {', '.join(missing[1:])})" if len(missing) > 1 else "")
                         + f"; it holds {', '.join(sorted(source.cameras))}. Calibrate every camera the capture "
                         "recorded, or unset calibrate.source to use the capture's board takes")
    extra = sorted(set(source.cameras) - set(wanted))
    if extra:
        log.info("calibrate.source: %d cameras not in the capture left out: %s", len(extra), ", ".join(extra))
    cameras = [source.cameras[n] for n in wanted]
    report = {}
    for cam in cameras:
        rms = source.reproj_rms_px(cam.name)
        if rms is not None and rms > params.max_source_reproj_px:
            raise InputError(f"calibrate.source {source.path}: camera {cam.name} reprojects its own points with an "
                             f"RMS of {rms:.3f} px (more than calibrate.max_source_reproj_px = "
                             f"{params.max_source_reproj_px}); check the model's units and camera names, or re-run "
                             "its bundle adjustment")
        report[cam.name] = {"reproj_rms_px": rms, "points": len(source.residuals_px.get(cam.name, ())),
                            "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "dist": list(cam.dist)}
        log.info("%s: from %s, %s", cam.name, source.kind,
                 f"RMS {rms:.3f} px over {report[cam.name]['points']} points" if rms is not None else "no points")
    perf_size = performance_size(capture)
    out.write_cameras_native(cameras)
    out.write_cameras([to_performance_resolution(c, perf_size) for c in cameras])
    out.write_report({"source": str(source.path), "source_kind": source.kind, "units_m": params.source_units_m,
                      "cameras_left_out": extra, "calibration_size": [cameras[0].width, cameras[0].height],
                      "performance_size": list(perf_size) if perf_size else None, "cameras": report})
    residuals = [r for r in source.residuals_px.values() if len(r)]
    if residuals:
        res = np.concatenate(residuals)
        metrics["reproj_rms_px"] = float(np.sqrt(np.mean(np.sum(res ** 2, axis=1))))
        metrics["reproj_rms_px_max_camera"] = max(v["reproj_rms_px"] for v in report.values()
                                                  if v["reproj_rms_px"] is not None)
        metrics["corners_used"] = len(res)
    metrics["cameras"] = len(cameras)
    metrics["cameras_dropped"] = 0
    metrics["calibration_width_px"] = cameras[0].width
    metrics["calibration_from_source"] = 1  # the kind is in report.json
