"""Stage ``capture_eval``: the capture's frame labels against what the studio really did.

Reads the capture's ``manifest.json`` and the truth's ``lights_per_pulse.json`` (what the bars
showed at each trigger) and ``frames.npz["received"]`` ([C, F] images each camera delivered
per trigger). Metrics: ``label_errors`` (frames marked ok whose light is wrong),
``missed_drops`` (frames marked ok although a camera lost or never lit them),
``false_drops`` (frames set aside although every camera delivered one lit image),
``label_accuracy`` (share of frames whose status and light are both right).
"""

from __future__ import annotations

from pipeline.stage import Stage, StageContext, StageParams
from stages.capture.output import CaptureOutput, CaptureTruth


class CaptureEvalParams(StageParams):
    """Params of the capture evaluation (none)."""


def run(ctx: StageContext) -> None:
    """Compare labels with the truth; write the metrics."""
    capture, truth = CaptureOutput(ctx.input("capture")), CaptureTruth(ctx.input("capture.truth"))
    manifest = capture.manifest(keys=("frames",))
    lit = truth.lights_per_pulse()
    received = truth.frames(keys=("received",))["received"]  # [C, F]
    label_errors = missed = false_drops = right = 0
    for frame in manifest["frames"]:
        i = int(frame["index"])
        truly_lit = i < len(lit) and lit[i] is not None
        complete = truly_lit and i < received.shape[1] and bool((received[:, i] >= 1).all())
        if frame["status"] == "ok":
            if not complete:
                missed += 1
            elif frame["light"] != lit[i]:
                label_errors += 1
            else:
                right += 1
        elif complete:
            false_drops += 1
        else:
            right += 1
    n = max(len(manifest["frames"]), 1)
    ctx.metrics.update({"label_errors": label_errors, "missed_drops": missed, "false_drops": false_drops,
                        "label_accuracy": right / n})
    ctx.log.info("labels: %d wrong lights, %d missed drops, %d false drops over %d frames",
                 label_errors, missed, false_drops, len(manifest["frames"]))


STAGE = Stage(
    name="capture_eval",
    inputs=("capture", "capture.truth"),
    params=CaptureEvalParams,
    run=run,
    evaluates="capture",
    doc="Frame labels (lights, dropped frames) of the capture against the studio's truth.",
)
