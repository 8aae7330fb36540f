"""Executors: fan independent per-item work out to workers.

``LocalExecutor`` uses a spawn-based process pool (``workers`` processes; serial in this
process when ``workers == 1`` or there is a single item). ``ray`` (``pipeline.ray_executor``)
fans out over a Ray cluster. Other executors subclass ``BaseExecutor`` and register with
``register_executor`` (or are named as ``"module:Class"``). Choose with ``executor.kind`` in
``configs/pipeline.yaml`` or ``pipeline run --executor``.
"""

from __future__ import annotations

import importlib
import multiprocessing
import os
import pickle
from abc import ABC, abstractmethod
from concurrent.futures import FIRST_EXCEPTION, Future, ProcessPoolExecutor, wait
from typing import Any, Callable, Sequence, TypeVar

from pipeline.errors import ConfigError, PipelineError
from pipeline.progress import ProgressLine

T = TypeVar("T")
R = TypeVar("R")
ProgressFactory = Callable[[int, str], ProgressLine]


def _apply_chunk(fn: Callable[[Any], Any], chunk: Sequence[Any]) -> list[Any]:
    return [fn(item) for item in chunk]


class BaseExecutor(ABC):
    """What the runner hands stages as ``ctx.executor``; a context manager owning its workers."""

    def __init__(self, workers: int | None = None, progress_factory: ProgressFactory | None = None) -> None:
        self.workers = max(1, int(workers or os.cpu_count() or 1))
        self.progress_factory = progress_factory

    @abstractmethod
    def map(self, fn: Callable[[T], R], items: Sequence[T], *, desc: str = "items", gpu: bool = False) -> list[R]:
        """Apply a picklable top-level ``fn`` to every item; results in input order."""

    def close(self) -> None:
        """Release workers (idempotent)."""

    def __enter__(self) -> "BaseExecutor":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _progress(self, total: int, desc: str) -> ProgressLine | None:
        return self.progress_factory(total, desc) if self.progress_factory else None


class LocalExecutor(BaseExecutor):
    """A process pool on this machine (``spawn`` start method: safe with threads and torch).

    Work flagged ``gpu=True`` runs in this process, one item after another, so a single process
    owns the device. The pool is created on first use and kept for the stage's lifetime.
    """

    def __init__(self, workers: int | None = None, progress_factory: ProgressFactory | None = None) -> None:
        super().__init__(workers, progress_factory)
        self._pool: ProcessPoolExecutor | None = None

    def _get_pool(self) -> ProcessPoolExecutor:
        if self._pool is None:
            self._pool = ProcessPoolExecutor(max_workers=self.workers,
                                             mp_context=multiprocessing.get_context("spawn"))
        return self._pool

    def map(self, fn: Callable[[T], R], items: Sequence[T], *, desc: str = "items", gpu: bool = False) -> list[R]:
        """Apply ``fn`` to every item on the pool (in chunks); results in input order."""
        items = list(items)
        progress = self._progress(len(items), desc)
        try:
            if gpu or self.workers == 1 or len(items) <= 1:
                results = []
                for item in items:
                    results.append(fn(item))
                    if progress:
                        progress.advance()
                return results
            try:
                pickle.dumps(fn)
            except (pickle.PicklingError, AttributeError, TypeError) as err:
                raise PipelineError(f"executor.map({getattr(fn, '__qualname__', fn)!r}): the function must "
                                    f"be a top-level function of an importable module so worker "
                                    f"processes can import it ({err})") from None
            n_chunks = min(len(items), self.workers * 4)
            bounds = [round(i * len(items) / n_chunks) for i in range(n_chunks + 1)]
            chunks = [items[bounds[i]:bounds[i + 1]] for i in range(n_chunks)]
            pool = self._get_pool()
            futures: dict[Future, int] = {pool.submit(_apply_chunk, fn, chunk): i for i, chunk in enumerate(chunks)}
            results_by_chunk: dict[int, list[R]] = {}
            pending = set(futures)
            while pending:
                done, pending = wait(pending, return_when=FIRST_EXCEPTION)
                for future in done:
                    index = futures[future]
                    error = future.exception()
                    if error is not None:
                        for other in pending:
                            other.cancel()
                        raise error
                    results_by_chunk[index] = future.result()
                    if progress:
                        progress.advance(len(chunks[index]))
            return [r for i in range(n_chunks) for r in results_by_chunk[i]]
        finally:
            if progress:
                progress.close()

    def close(self) -> None:
        """Shut the pool down (pending work is cancelled)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


def _ray_executor(**kwargs: Any) -> BaseExecutor:
    # Imported only when asked for: Ray is an optional dependency (``pip install .[ray]``).
    from pipeline.ray_executor import RayExecutor

    return RayExecutor(**kwargs)


_EXECUTORS: dict[str, Callable[..., BaseExecutor]] = {"local": LocalExecutor, "ray": _ray_executor}


def register_executor(kind: str, factory: Callable[..., BaseExecutor]) -> None:
    """Make ``kind`` (e.g. ``"ray"``) available to ``make_executor``."""
    _EXECUTORS[kind] = factory


def check_executor_kind(kind: str) -> None:
    """Raise ``ConfigError`` early for an executor kind that ``make_executor`` cannot build."""
    if kind not in _EXECUTORS and ":" not in kind:
        raise ConfigError(f"executor '{kind}': unknown; available: {', '.join(sorted(_EXECUTORS))} "
                          f"or 'module:Class'")


def make_executor(kind: str, workers: int | None, progress_factory: ProgressFactory | None = None) -> BaseExecutor:
    """An executor by kind: a registered name, or ``"module:Class"`` imported lazily."""
    factory = _EXECUTORS.get(kind)
    if factory is None and ":" in kind:
        module_name, attr = kind.split(":", 1)
        try:
            factory = getattr(importlib.import_module(module_name), attr)
        except (ImportError, AttributeError) as err:
            raise ConfigError(f"executor '{kind}': cannot import it ({err})") from None
    if factory is None:
        raise ConfigError(f"executor '{kind}': unknown; available: {', '.join(sorted(_EXECUTORS))} "
                          f"or 'module:Class'")
    return factory(workers=workers, progress_factory=progress_factory)
