"""Run one stage's ``run`` function outside a workspace, for unit tests of stages.

The runner is the only thing that commits objects; this helper just builds a
``StageContext`` over plain folders so a stage's algorithm can be tested in isolation::

    out = run_stage_for_test(SEQUENCE_STAGE, tmp_path, inputs={}, params={"fps": 24})
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from pipeline.stage import Stage, StageContext


class SerialExecutor:
    """Runs items one after another in this process (tests, debugging)."""

    def map(self, fn: Callable, items: Sequence, *, desc: str = "items", gpu: bool = False) -> list:
        return [fn(item) for item in items]


class _LogProgress:
    def __init__(self, log: logging.Logger, total: int, unit: str) -> None:
        self.log, self.total, self.unit, self.done = log, total, unit, 0

    def advance(self, n: int = 1, **fields: Any) -> None:
        self.done += n

    def close(self) -> None:
        self.log.debug("%d/%d %s", self.done, self.total, self.unit)

    def __enter__(self) -> "_LogProgress":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def run_stage_for_test(stage: Stage, workdir: Path, inputs: Mapping[str, Path] | None = None,
                       params: Mapping[str, Any] | None = None) -> Path:
    """Run ``stage`` with ``params`` over ``inputs``; returns its output folder.

    Output goes to ``workdir/<stage.name>`` (extra outputs to ``workdir/<stage.name>.<extra>``),
    metrics to ``metrics.json`` in it, exactly as the runner writes them.
    """
    workdir = Path(workdir)
    out = workdir / stage.name
    out.mkdir(parents=True, exist_ok=False)
    extra = {name: workdir / f"{stage.name}.{name}" for name in stage.extra_outputs}
    for path in extra.values():
        path.mkdir(parents=True, exist_ok=False)
    log = logging.getLogger(f"stage.{stage.name}")
    metrics: dict[str, float] = {}
    ctx = StageContext(
        stage=stage.name, subject="test", params=stage.params(**dict(params or {})),
        inputs=dict(inputs or {}), out=out, extra_outputs=extra, log=log, metrics=metrics,
        cache_dir=workdir / ".cache" / stage.name, shared_cache_dir=workdir / ".shared_cache",
        executor=SerialExecutor(), progress_factory=lambda total, unit: _LogProgress(log, total, unit),
    )
    ctx.cache_dir.mkdir(parents=True, exist_ok=True)
    ctx.shared_cache_dir.mkdir(parents=True, exist_ok=True)
    stage.run(ctx)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1, sort_keys=True))
    return out
