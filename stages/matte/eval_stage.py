"""Stage ``matte_eval``: the mattes against the studio's exact alpha, beside the classical baseline.

For every image with a ground-truth matte, the stage's matte and the baseline's (threshold
+ guided filter, computed here from the capture image) are measured (MAE, MSE, gradient
error; ``stages.matte.measures``), then averaged separately over full-on (F) and OLAT
frames. Keys: ``mae_full``, ``mse_full``, ``grad_err_full``, ``mae_olat``, ``mse_olat``,
``grad_err_olat``, and the same with the prefix ``baseline_``; ``*_p95`` and ``*_max`` of the
MAE show the worst images. ``per_image.json`` lists every image's figures.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import Field

from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext, StageParams
from stages.capture.output import CaptureOutput, CaptureTruth
from stages.matte.baseline import BaselineConfig, baseline_matte
from stages.matte.measures import all_measures
from stages.matte.output import MatteOutput, write_per_image


class MatteEvalParams(StageParams):
    """Params of the matte evaluation."""

    baseline: BaselineConfig = Field(BaselineConfig(), description="The classical matte measured beside the stage's.")
    frame_stride: int = Field(1, ge=1, description="Evaluate every n-th frame (1 = all).")


@dataclass(frozen=True)
class CameraJob:
    """The evaluation of one camera's images (a picklable unit of work)."""

    cam: str
    frames: tuple[tuple[int, bool], ...]  # (index, is_olat)
    matte: MatteOutput
    capture: CaptureOutput
    truth: CaptureTruth
    baseline: BaselineConfig


def evaluate_camera(job: CameraJob) -> list[dict[str, Any]]:
    """Per-image measures of the stage's matte and the baseline's for one camera."""
    records = []
    for index, is_olat in job.frames:
        if not (job.truth.matte_path(job.cam, index).is_file() and job.capture.has_frame(job.cam, index)):
            continue  # dropped frame: no image, nothing to matte
        if not job.matte.has_matte(job.cam, index):
            raise job.matte.error(job.matte.matte_path(job.cam, index),
                                  f"camera {job.cam} frame {index} has an image but no matte", state="is missing")
        truth = job.truth.matte(job.cam, index)
        alpha = job.matte.matte(job.cam, index)
        baseline = baseline_matte(job.capture.frame(job.cam, index)[..., :3], job.baseline)
        record = {"cam": job.cam, "index": index, "olat": is_olat, **all_measures(alpha, truth)}
        record.update({f"baseline_{k}": v for k, v in all_measures(baseline, truth).items()})
        records.append(record)
    return records


def summarise(records: list[dict[str, Any]]) -> dict[str, float]:
    """Mean measures over F and OLAT images separately (plus MAE p95/max and counts)."""
    metrics: dict[str, float] = {}
    for split, want_olat in (("full", False), ("olat", True)):
        chosen = [r for r in records if r["olat"] == want_olat]
        metrics[f"images_{split}"] = len(chosen)
        if not chosen:
            continue
        for prefix in ("", "baseline_"):
            for measure in ("mae", "mse", "grad_err"):
                metrics[f"{prefix}{measure}_{split}"] = float(np.mean([r[prefix + measure] for r in chosen]))
            maes = [r[prefix + "mae"] for r in chosen]
            metrics[f"{prefix}mae_{split}_p95"] = float(np.percentile(maes, 95))
            metrics[f"{prefix}mae_{split}_max"] = float(np.max(maes))
    return metrics


def run(ctx: StageContext) -> None:
    """Measure the mattes against ground truth, beside the baseline."""
    params: MatteEvalParams = ctx.params  # type: ignore[assignment]
    capture, truth = CaptureOutput(ctx.input("capture")), CaptureTruth(ctx.input("capture.truth"))
    matte = MatteOutput(ctx.input("matte"))
    manifest = capture.manifest(keys=("frames", "cameras"))
    frames = tuple((int(f["index"]), f.get("light") != "F") for f in manifest["frames"][::params.frame_stride]
                   if f.get("status", "ok") != "dropped")
    jobs = [CameraJob(cam, frames, matte, capture, truth, params.baseline) for cam in manifest["cameras"]]
    records = [r for per_cam in ctx.executor.map(evaluate_camera, jobs, desc="cameras") for r in per_cam]
    if not records:
        raise InputError(f"{truth.mattes_dir}: no ground-truth matte matches a captured image; "
                         "is capture.truth from the same capture?")
    ctx.metrics.update(summarise(records))
    write_per_image(ctx.out, records)


STAGE = Stage(name="matte_eval", inputs=("matte", "capture", "capture.truth"), params=MatteEvalParams, run=run,
              evaluates="matte",
              doc="Matte accuracy (MAE, MSE, gradient error) on F and OLAT frames, beside the classical baseline.")
