"""Evaluate stage: stability sweeps of the trained head against the studio's ground truth.

Two sweeps, each a curve with the point where quality falls under a PSNR threshold:

- Light orbit: a point light circles the head at ``orbit_radius_m`` (3 m) in the horizontal
  plane (and, optionally, the vertical y-z plane). Each position is rendered by the trained
  model and by the studio's ray tracer (same head-space camera, expression, light) from
  ``camera_azimuths_deg``; PSNR is exposure fitted as in the paper
  (``stages.evaluate.measure``). Plotted against the angle between the light
  and the nearest training light direction (the lit bars of the training split, moved into
  head space with the true head pose, seen from the head's centre), the first angle where PSNR
  drops under the threshold is ``light_extrapolation_limit_deg`` (the paper reports ~20 degrees
  behind the training lights).
- Expression magnitude: a held-out frame's tracked blendshape weights scaled by
  ``expression_scales`` (the actor rig is linear, so the driving mesh is
  ``neutral + s (tracked - neutral)``), against the studio's truth with its true ICT weights
  scaled by the same ``s``, under the training light nearest the front. The scales where PSNR
  falls under the threshold below and above 1 are ``expression_scale_limit_low/high``.

Output::

    limits.json                     the warning zone (``stages.evaluate.limits``)
    tradeoffs/light_orbit.json      PSNR vs angle from the nearest training light (report chart)
    tradeoffs/expression_scale.json PSNR vs weight scale
    light_orbit.png, expression_scale.png, orbit_strip.png (truth over model, every 45 degrees)
    sweeps.json                     every sample of both sweeps
    metrics.json

Reads ground truth (``capture.truth``); nothing reads its output back into a product stage.
"""

from __future__ import annotations

from pipeline.stage import Stage, StageContext
from stages.evaluate.inputs import load_evaluation_inputs
from stages.evaluate.output import EvaluateOutput
from stages.evaluate.params import EvaluateParams
from stages.evaluate.stability import measure_stability
from stages.evaluate.write import write_evaluate_outputs

#: The folders the sweeps read; ``capture.truth`` is the studio's ground truth.
EVALUATE_INPUTS = ("train", "track", "capture", "capture.truth")


def run(ctx: StageContext) -> None:
    """Read the inputs, run both sweeps (``stages.evaluate.stability``), write the outputs."""
    params: EvaluateParams = ctx.params  # type: ignore[assignment]
    data = load_evaluation_inputs({name: ctx.input(name) for name in EVALUATE_INPUTS})
    results = measure_stability(data, params, ctx.progress)
    write_evaluate_outputs(EvaluateOutput(ctx.out), params, results)
    ctx.metrics.update(results.metrics())
    orbit, expr = results.orbit, results.expression
    ctx.log.info("evaluate: light extrapolation limit %.1f deg from the training lights (threshold %.1f dB%s); "
                 "expression scale limits %.2f / %.2f (threshold %.1f dB)", orbit.limit.x, orbit.threshold_db,
                 ", not reached" if orbit.limit.censored else "", expr.low.x, expr.high.x, expr.threshold_db)


STAGE = Stage(
    name="evaluate",
    inputs=EVALUATE_INPUTS,
    params=EvaluateParams,
    run=run,
    reads_truth=True,
    doc="Stability sweeps against ground truth: light orbit (extrapolation limit) and expression magnitude.",
)
