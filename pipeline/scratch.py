"""Run one stage over plain folders, outside a workspace: for benchmarks and stage tests.

The runner is the only thing that commits objects; this builds a ``StageContext`` over a
scratch folder, with the runner's own progress lines and executor, and writes the stage's
``metrics.json`` as the runner does, so a stage's algorithm can be run and measured alone::

    out = run_stage_in_folder(SEQUENCE_STAGE, scratch, inputs={}, params={"fps": 24})
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Mapping

from pipeline.executors import LocalExecutor
from pipeline.metrics import clean_metrics
from pipeline.progress import progress_factory
from pipeline.stage import Stage, StageContext


def run_stage_in_folder(stage: Stage, workdir: Path, inputs: Mapping[str, Path] | None = None,
                        params: Mapping[str, Any] | None = None, *, subject: str = "test",
                        workers: int = 1) -> Path:
    """Run ``stage`` with ``params`` over ``inputs``; returns its output folder.

    Output goes to ``workdir/<stage.name>`` (extra outputs to ``workdir/<stage.name>.<extra>``),
    metrics to ``metrics.json`` in it, exactly as the runner writes them; per-item caches to
    ``workdir/.cache/<stage.name>``. ``workers > 1`` runs ``ctx.executor.map`` on a process
    pool as the runner would.
    """
    workdir = Path(workdir)
    out = workdir / stage.name
    out.mkdir(parents=True, exist_ok=False)
    extra = {name: workdir / f"{stage.name}.{name}" for name in stage.extra_outputs}
    for path in extra.values():
        path.mkdir(parents=True, exist_ok=False)
    log = logging.getLogger(f"stage.{stage.name}")
    metrics: dict[str, float] = {}
    factory = progress_factory(stage.name, log, tty=False)
    with LocalExecutor(workers=workers, progress_factory=factory) as executor:
        ctx = StageContext(
            stage=stage.name, subject=subject, params=stage.params(**dict(params or {})),
            inputs=dict(inputs or {}), out=out, extra_outputs=extra, log=log, metrics=metrics,
            cache_dir=workdir / ".cache" / stage.name, shared_cache_dir=workdir / ".shared_cache",
            executor=executor, progress_factory=factory,
        )
        ctx.cache_dir.mkdir(parents=True, exist_ok=True)
        ctx.shared_cache_dir.mkdir(parents=True, exist_ok=True)
        stage.run(ctx)
    clean = clean_metrics(stage.name, metrics)
    metrics_file = out / "metrics.json"
    if metrics_file.is_file():
        clean = {**json.loads(metrics_file.read_text(encoding="utf-8")), **clean}
    metrics_file.write_text(json.dumps(clean, indent=1, sort_keys=True) + "\n", encoding="utf-8")
    return out
