"""The stage API: what a stage declares and what the runner hands it.

A stage module (``stages/<name>/stage.py``) exposes one module-level ``STAGE``::

    class SequenceParams(StageParams):
        fps: float = Field(24.0, description="Frame rate of the capture in frames per second.")

    def run(ctx: StageContext) -> None:
        params: SequenceParams = ctx.params
        ...write files under ctx.out ...
        ctx.metrics["olat_angle_mean_deg"] = 61.2

    STAGE = Stage(name="sequence", inputs=(), params=SequenceParams, run=run)

The stage's code digest covers its own package and every project module it imports,
transitively (``pipeline.codedigest``); ``code`` names only what imports cannot show.

Rules (docs/design.md, stage contracts and house rules 1-3):
- ``run`` reads only ``ctx.inputs[...]`` (read-only folders of upstream outputs), its
  params and files it declares through ``external_inputs``; it writes only under
  ``ctx.out`` (and ``ctx.extra_outputs[...]`` for declared extra outputs).
- Params are frozen pydantic models; every field has a ``description`` (the CLI help).
- An extra output named ``truth`` is committed as its own object, referenced as
  ``<stage>.truth``; only evaluation stages (name ending ``_eval``, or declared with
  ``reads_truth=True``) may take it as an input. The DAG refuses anything else.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Protocol, Sequence, TypeVar

from pydantic import BaseModel, ConfigDict

T = TypeVar("T")
R = TypeVar("R")


class StageParams(BaseModel):
    """Base class of every stage's params: frozen, unknown keys rejected."""

    model_config = ConfigDict(frozen=True, extra="forbid")


class Progress(Protocol):
    """A progress counter for one loop of work (frames, iterations, images)."""

    def advance(self, n: int = 1, **fields: Any) -> None:
        """Mark ``n`` more items done; ``fields`` (loss=..., psnr=...) are shown beside the rate."""

    def close(self) -> None:
        """Finish the display line (also done by leaving a ``with`` block)."""

    def __enter__(self) -> "Progress": ...

    def __exit__(self, *exc: object) -> None: ...


class Executor(Protocol):
    """Fans independent per-item work out to workers (process pool, Ray)."""

    def map(self, fn: Callable[[T], R], items: Sequence[T], *, desc: str = "items",
            gpu: bool = False) -> list[R]:
        """Apply a picklable top-level ``fn`` to every item, results in input order."""


@dataclass
class StageContext:
    """Everything a stage's ``run`` may touch.

    Attributes:
        stage: the stage's name.
        subject: the subject being processed (workspace name).
        params: the validated, frozen params object of this stage.
        inputs: upstream output folders by stage name (``"capture"``, ``"capture.truth"``);
            read-only, never write into them.
        out: a fresh, empty output folder; everything the stage produces goes here.
        extra_outputs: fresh folders for declared extra outputs (``"truth"``).
        log: the stage's logger (also written to the workspace's log file).
        metrics: flat ``key -> number`` dict; units in the key. Written to
            ``out/metrics.json`` by the runner after ``run`` returns.
        cache_dir: a persistent per-subject, per-stage scratch folder for per-item caches
            (e.g. per-frame results keyed by content hash) that survive reruns.
        shared_cache_dir: a persistent folder shared by all subjects of a workspace root
            (e.g. a matting model trained once and reused across subjects).
        executor: fan-out for per-frame work.
        progress_factory: use ``ctx.progress(total, "frames")``.
    """

    stage: str
    subject: str
    params: StageParams
    inputs: Mapping[str, Path]
    out: Path
    extra_outputs: Mapping[str, Path]
    log: logging.Logger
    metrics: dict[str, float]
    cache_dir: Path
    shared_cache_dir: Path
    executor: Executor
    progress_factory: Callable[[int, str], Progress]

    def progress(self, total: int, unit: str = "items") -> Progress:
        """A progress counter for ``total`` items, shown live on a terminal, as log lines otherwise."""
        return self.progress_factory(total, unit)

    def input(self, name: str) -> Path:
        """The folder of upstream output ``name``; a clear error if the stage did not declare it."""
        from pipeline.errors import PipelineError

        if name not in self.inputs:
            raise PipelineError(
                f"stage '{self.stage}' asked for input '{name}' but declares only "
                f"{sorted(self.inputs)}; add it to the stage's inputs")
        return self.inputs[name]


@dataclass(frozen=True)
class Stage:
    """A stage's declaration.

    Attributes:
        name: unique stage name, as used on the command line and in ``configs/pipeline.yaml``.
        inputs: upstream outputs by name (``"calibrate"``, or ``"capture.truth"`` for eval stages).
        params: the params class (a ``StageParams`` subclass).
        run: the function that does the work.
        code: project modules or packages (dotted names) whose source counts toward this stage's
            code digest although no import reaches them (a module run by name in a subprocess,
            outside the stage's package). Everything the stage's package imports, transitively,
            counts already, and so do the non-Python files those modules declare in ``CODE_FILES``.
        extra_outputs: names of extra output objects (e.g. ``("truth",)``).
        reads_truth: may take ``*.truth`` inputs; defaults to names ending in ``_eval``.
        external_inputs: maps params to files/folders outside the workspace that the stage reads
            (e.g. an imported capture folder); their content digest counts toward staleness.
        evaluates: for an evaluation stage, the stage whose metrics it completes in ``pipeline show``.
        reads_metrics: reads its inputs' ``metrics.json`` and run records (e.g. the report). Such a
            stage is keyed on its inputs' full digests; every other stage only on their data
            (``Workspace.content_key``), so a rerun upstream that changes nothing but its timings
            does not make it stale.
        run_records: patterns (``fnmatch``, relative to an output folder, ``*`` crossing folders) of
            the output files that record how the run went rather than what it made: wall-clock
            learning curves, TensorBoard event files. Like ``metrics.json`` they are left out of the
            content key, so only stages with ``reads_metrics`` see them change; no other stage may
            read them.
    """

    name: str
    inputs: tuple[str, ...]
    params: type[StageParams]
    run: Callable[[StageContext], None]
    code: tuple[str, ...] = ()
    extra_outputs: tuple[str, ...] = ()
    reads_truth: bool | None = None
    external_inputs: Callable[[StageParams], Iterable[Path]] | None = None
    evaluates: str | None = None
    reads_metrics: bool = False
    run_records: tuple[str, ...] = ()
    doc: str = field(default="")

    @property
    def may_read_truth(self) -> bool:
        """Whether this stage may consume ground-truth objects."""
        if self.reads_truth is not None:
            return self.reads_truth
        return self.name.endswith("_eval")
