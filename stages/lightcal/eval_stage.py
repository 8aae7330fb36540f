"""``lightcal_eval``: the placed LED bars against the virtual studio's true bars."""

from __future__ import annotations

import numpy as np

from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext, StageParams
from stages.capture.output import CaptureTruth
from stages.lightcal.output import LightcalOutput


class LightcalEvalParams(StageParams):
    """No settings: the comparison is fixed."""


def bar_errors(est: list[dict], true: list[dict]) -> dict[str, float]:
    """Centre error (mm) per bar, axis error (deg, where the axis was measured), bars missing."""
    by_id = {int(b["id"]): b for b in est}
    centre, axis, length = [], [], []
    for t in true:
        e = by_id.get(int(t["id"]))
        if e is None:
            continue
        centre.append(1e3 * float(np.linalg.norm(np.asarray(e["center_world"]) - np.asarray(t["center_world"]))))
        if e.get("axis_from_highlights", True):
            c = abs(float(np.dot(e["axis_world"], t["axis_world"])))
            axis.append(float(np.degrees(np.arccos(min(c, 1.0)))))
            if np.isfinite(e.get("length_m", float("nan"))):
                length.append(1e3 * abs(float(e["length_m"]) - float(t["length_m"])))
    out = {"bars_compared": len(centre), "bars_missing": len(true) - len(centre)}
    if centre:
        out.update({"bar_center_err_mm_mean": float(np.mean(centre)), "bar_center_err_mm_max": float(np.max(centre)),
                    "bar_center_err_mm_median": float(np.median(centre))})
    if axis:
        out.update({"bar_axis_err_deg_mean": float(np.mean(axis)), "bar_axis_err_deg_max": float(np.max(axis))})
    if length:
        out["bar_length_err_mm_mean"] = float(np.mean(length))
    return out


def run(ctx: StageContext) -> None:
    """Compare ``lightcal/bars.json`` with ``capture.truth/bars.json``."""
    placed, truth = LightcalOutput(ctx.input("lightcal")), CaptureTruth(ctx.input("capture.truth"))
    paths = (placed.bars_path, truth.bars_path)
    est, true = placed.bars(), truth.bars()
    metrics = bar_errors(est, true)
    if metrics["bars_compared"] == 0:
        raise InputError(f"{paths[0]}: no bar in common with the ground truth {paths[1]}")
    ctx.metrics.update(metrics)
    for key, value in metrics.items():
        ctx.log.info("%s = %.4g", key, value)


STAGE = Stage(name="lightcal_eval", inputs=("lightcal", "capture.truth"), params=LightcalEvalParams, run=run,
              evaluates="lightcal", doc="LED bar placement accuracy against ground truth.")
