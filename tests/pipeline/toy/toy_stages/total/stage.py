"""Toy total: sums the doubled numbers."""

import json

from pydantic import Field

from pipeline.stage import Stage, StageContext, StageParams


class TotalParams(StageParams):
    offset: float = Field(0.0, description="Added to the sum.")


def run(ctx: StageContext) -> None:
    numbers = json.loads((ctx.input("double") / "numbers.json").read_text())
    total = sum(numbers) + ctx.params.offset
    (ctx.out / "total.json").write_text(json.dumps({"total": total}))
    ctx.metrics["total"] = total


STAGE = Stage(name="total", inputs=("double",), params=TotalParams, run=run)
