"""Write the stability sweeps into the evaluate stage's output folder (``stages.evaluate.output``)."""

from __future__ import annotations

from stages.evaluate import charts
from stages.evaluate.limits import LightLimits, write_limits
from stages.evaluate.output import EvaluateOutput
from stages.evaluate.params import EvaluateParams
from stages.evaluate.stability import StabilityResults


def write_evaluate_outputs(out: EvaluateOutput, params: EvaluateParams, results: StabilityResults) -> None:
    """The warning zone (``limits.json``), every sample, the report's series and the charts."""
    orbit, expr = results.orbit, results.expression
    limit, low, high = orbit.limit, expr.low, expr.high
    limits = LightLimits(limit.x, limit.censored, orbit.threshold_db, tuple(float(v) for v in results.centre),
                         tuple(tuple(float(v) for v in d) for d in results.train_dirs))
    write_limits(out.limits_path, limits, {
        "failed_at_start": limit.failed_at_start,
        "light_orbit_azimuth_limit_deg": orbit.azimuth.x,
        "expression_scale_limit_low": low.x, "expression_scale_limit_high": high.x,
        "expression_scale_censored_low": low.censored, "expression_scale_censored_high": high.censored,
        "expression_threshold_db": expr.threshold_db})
    out.write_sweeps(results.samples())
    # No per-point labels: the report annotates every labelled point and an orbit has dozens.
    points = [{"x": ft, "y": p, "series": f"{plane} orbit"}
              for plane, (_angles, from_train, psnr_db) in orbit.curves.items()
              for ft, p in zip(from_train, psnr_db)]
    points.append({"x": limit.x, "y": orbit.threshold_db, "series": "limit", "chosen": True,
                   "label": f"limit {limit.x:.0f} deg" + (" (not reached)" if limit.censored else "")})
    charts.write_series(out.light_orbit_series_path,
                        f"Point light orbit at {params.orbit_radius_m:g} m: PSNR vs angle from the training lights",
                        "angle from the nearest training light (deg)", "PSNR (dB)", points)
    points = [{"x": s, "y": p, "series": "held-out frame", "label": f"x{s:g}"}
              for s, p in zip(expr.scales, expr.psnr_db)]
    points += [{"x": c.x, "y": expr.threshold_db, "series": "limit", "chosen": True,
                "label": f"{side} limit x{c.x:.2f}"} for side, c in (("low", low), ("high", high))]
    charts.write_series(out.expression_series_path, "Expression magnitude: PSNR vs weight scale",
                        "blendshape weight scale", "PSNR (dB)", points)
    charts.light_orbit_png(out.light_orbit_png_path, orbit.curves, orbit.threshold_db, limit)
    charts.expression_png(out.expression_png_path, expr.scales, expr.psnr_db, expr.threshold_db, low, high)
    if orbit.strip_truth:
        charts.strip_png(out.orbit_strip_path, orbit.strip_truth, orbit.strip_pred)
