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
import pickle
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from typing import Any, Callable, Iterator, Sequence, TypeVar

from pipeline.errors import ConfigError, PipelineError
from pipeline.executor_base import BaseExecutor, ProgressFactory, apply_chunk, chunk_bounds, ordered

T = TypeVar("T")
R = TypeVar("R")


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
        return ordered(self.imap(fn, items, desc=desc, gpu=gpu), len(items))

    def imap(self, fn: Callable[[T], R], items: Sequence[T], *, desc: str = "items",
             gpu: bool = False) -> Iterator[tuple[int, R]]:
        """``(position, result)`` as chunks finish (each item as it finishes when run in this process)."""
        items = list(items)
        if gpu or self.workers == 1 or len(items) <= 1:
            return self._serial(fn, items, desc)
        try:
            pickle.dumps(fn)
        except (pickle.PicklingError, AttributeError, TypeError) as err:
            raise PipelineError(f"executor.map({getattr(fn, '__qualname__', fn)!r}): the function must "
                                f"be a top-level function of an importable module so worker "
                                f"processes can import it ({err})") from None
        n_chunks = min(len(items), self.workers * 4)
        bounds = chunk_bounds(len(items), n_chunks)
        pool = self._get_pool()
        futures: dict[Future, int] = {pool.submit(apply_chunk, fn, items[bounds[i]:bounds[i + 1]]): i
                                      for i in range(n_chunks)}
        return self._drain(futures, bounds, desc)

    def _serial(self, fn: Callable[[T], R], items: list[T], desc: str) -> Iterator[tuple[int, R]]:
        progress = self._progress(len(items), desc)
        try:
            for position, item in enumerate(items):
                yield position, fn(item)
                if progress:
                    progress.advance()
        finally:
            if progress:
                progress.close()

    def _drain(self, futures: dict[Future, int], bounds: list[int], desc: str) -> Iterator[tuple[int, Any]]:
        progress = self._progress(bounds[-1], desc)
        pending = set(futures)
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for future in sorted(done, key=futures.__getitem__):
                    index = futures[future]
                    chunk_results = future.result()  # re-raises the worker's exception
                    if progress:
                        progress.advance(len(chunk_results))
                    for offset, value in enumerate(chunk_results):
                        yield bounds[index] + offset, value
        finally:
            for other in pending:  # an error, or the caller stopped early: start nothing new
                other.cancel()
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
