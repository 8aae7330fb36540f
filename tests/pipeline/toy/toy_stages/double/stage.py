"""Toy double: scales every number (through the executor, with progress)."""

import json
import os
import time
from pathlib import Path
from typing import Literal

from pydantic import Field

from pipeline.stage import Stage, StageContext, StageParams
from toy_lib.arith import apply


class DoubleParams(StageParams):
    factor: int = Field(2, description="Multiplier (or addend).")
    mode: Literal["mul", "add"] = Field("mul", description="Multiply or add.")


def run(ctx: StageContext) -> None:
    params: DoubleParams = ctx.params
    numbers = json.loads((ctx.input("source") / "numbers.json").read_text())
    # Tests hold the stage mid-write through this file to kill it or to race a second run.
    hold = os.environ.get("TOY_HOLD_FILE")
    (ctx.out / "partial.bin").write_bytes(b"x" * 1000)
    if hold:
        Path(hold + ".started").write_text(str(os.getpid()))
        deadline = time.monotonic() + 60
        while not Path(hold).exists() and time.monotonic() < deadline:
            time.sleep(0.05)
    (ctx.out / "partial.bin").unlink()
    results = ctx.executor.map(apply, [(n, params.factor, params.mode) for n in numbers], desc="numbers")
    (ctx.out / "numbers.json").write_text(json.dumps(results))
    ctx.log.info("doubled %d numbers", len(results))
    ctx.metrics["max_value"] = max(results)

# Tests check which stage modules a command imports (the declaration cache spares the rest).
if os.environ.get("TOY_IMPORT_LOG"):
    with open(os.environ["TOY_IMPORT_LOG"], "a") as _log:
        _log.write(__name__ + "\n")


STAGE = Stage(name="double", inputs=("source",), params=DoubleParams, run=run)
