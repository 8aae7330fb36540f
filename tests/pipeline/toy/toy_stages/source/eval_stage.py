"""Toy evaluation of ``source``: compares its numbers with the ground-truth sum."""

import json

from pipeline.stage import Stage, StageContext, StageParams


class SourceEvalParams(StageParams):
    pass


def run(ctx: StageContext) -> None:
    numbers = json.loads((ctx.input("source") / "numbers.json").read_text())
    truth = json.loads((ctx.input("source.truth") / "sum.json").read_text())
    ctx.metrics["sum_abs_err"] = abs(sum(numbers) - truth["sum"])


STAGE = Stage(name="source_eval", inputs=("source", "source.truth"), params=SourceEvalParams, run=run,
              evaluates="source")
