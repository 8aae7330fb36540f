"""Toy side branch: counts the source numbers."""

import json
import os

from pydantic import Field

from pipeline.stage import Stage, StageContext, StageParams


class SideParams(StageParams):
    label: str = Field("side", description="A label written into the output.")


def run(ctx: StageContext) -> None:
    numbers = json.loads((ctx.input("source") / "numbers.json").read_text())
    # Reads the source's figures too (declared below), so it reruns when only they change.
    source_metrics = json.loads((ctx.input("source") / "metrics.json").read_text())
    (ctx.out / "count.json").write_text(json.dumps({ctx.params.label: len(numbers),
                                                    "source_seconds": source_metrics["source_seconds"]}))

# Tests check which stage modules a command imports (the declaration cache spares the rest).
if os.environ.get("TOY_IMPORT_LOG"):
    with open(os.environ["TOY_IMPORT_LOG"], "a") as _log:
        _log.write(__name__ + "\n")


STAGE = Stage(name="side", inputs=("source",), params=SideParams, run=run, reads_metrics=True)
