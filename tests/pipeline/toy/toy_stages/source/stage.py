"""Toy source: imports numbers from a folder of .txt files, or generates them from a seed."""

import json
import random
import time
from pathlib import Path

from pydantic import Field

from pipeline.stage import Stage, StageContext, StageParams


class RigParams(StageParams):
    name: str = Field("none", description="Rig name.")
    bars: int = Field(0, ge=0, description="Number of light bars.")


class SourceParams(StageParams):
    import_dir: str = Field("", description="Folder of .txt files (one number each) to import; empty: generate.")
    count: int = Field(3, ge=1, description="How many numbers to generate.")
    seed: int = Field(0, description="Seed of the generated numbers.")
    rig: RigParams = Field(default_factory=RigParams, description="The rig (configs/rig.yaml).")


def _external(params: SourceParams) -> list[Path]:
    return [Path(params.import_dir)] if params.import_dir else []


def run(ctx: StageContext) -> None:
    params: SourceParams = ctx.params
    started = time.perf_counter()
    if params.import_dir:
        files = sorted(Path(params.import_dir).rglob("*.txt"))
        numbers = [float(f.read_text().split()[0]) for f in files]
    else:
        rng = random.Random(params.seed)
        numbers = [rng.randint(1, 9) for _ in range(params.count)]
    (ctx.out / "numbers.json").write_text(json.dumps(numbers))
    (ctx.extra_outputs["truth"] / "sum.json").write_text(json.dumps({"sum": sum(numbers)}))
    ctx.metrics["numbers"] = len(numbers)
    ctx.metrics["rig_bars"] = params.rig.bars
    # A timing, as every real stage reports: differs between two runs of identical work.
    ctx.metrics["source_seconds"] = time.perf_counter() - started
    # A run record (as train's wall-clock learning curve): declared below, left out of the content key.
    (ctx.out / "log").mkdir()
    (ctx.out / "log" / "run.txt").write_text(f"generated {len(numbers)} numbers in {time.perf_counter() - started!r} s\n")


STAGE = Stage(name="source", inputs=(), params=SourceParams, run=run, extra_outputs=("truth",),
              external_inputs=_external, run_records=("log/*",))
