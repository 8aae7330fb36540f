"""What every executor shares: the ``BaseExecutor`` interface and the chunking helpers.

Kept apart from ``pipeline.executors`` (the local pool and the registry of kinds) so that
executors defined elsewhere (``pipeline.ray_executor``) build on it without importing the
registry that names them.
"""

from __future__ import annotations

import os
from abc import ABC, abstractmethod
from typing import Any, Callable, Iterator, Sequence, TypeVar

from pipeline.progress import ProgressLine

T = TypeVar("T")
R = TypeVar("R")
ProgressFactory = Callable[[int, str], ProgressLine]


def apply_chunk(fn: Callable[[Any], Any], chunk: Sequence[Any]) -> list[Any]:
    """Run ``fn`` over one chunk of items on a worker (one task per chunk, not per item)."""
    return [fn(item) for item in chunk]


def chunk_bounds(n_items: int, n_chunks: int) -> list[int]:
    """Start positions of ``n_chunks`` contiguous, near-equal chunks of ``n_items``, plus the end."""
    return [round(i * n_items / n_chunks) for i in range(n_chunks + 1)]


def ordered(pairs: Iterator[tuple[int, R]], n_items: int) -> list[R]:
    """The results of an ``imap`` stream, in input order."""
    results: list[Any] = [None] * n_items
    for position, value in pairs:
        results[position] = value
    return results


class BaseExecutor(ABC):
    """What the runner hands stages as ``ctx.executor``; a context manager owning its workers."""

    def __init__(self, workers: int | None = None, progress_factory: ProgressFactory | None = None) -> None:
        self.workers = max(1, int(workers or os.cpu_count() or 1))
        self.progress_factory = progress_factory

    @abstractmethod
    def map(self, fn: Callable[[T], R], items: Sequence[T], *, desc: str = "items", gpu: bool = False) -> list[R]:
        """Apply a picklable top-level ``fn`` to every item; results in input order."""

    def imap(self, fn: Callable[[T], R], items: Sequence[T], *, desc: str = "items",
             gpu: bool = False) -> Iterator[tuple[int, R]]:
        """``(position, fn(item))`` pairs as items finish, in any order; the work is handed out at the call.

        Lets a caller store or write each result as soon as it exists (a failure later in the
        run then loses nothing already done) and keeps only a few results in memory. Closing
        the iterator early cancels what has not started. This default runs ``map`` first.
        """
        return iter(enumerate(self.map(fn, items, desc=desc, gpu=gpu)))

    def close(self) -> None:
        """Release workers (idempotent)."""

    def __enter__(self) -> "BaseExecutor":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _progress(self, total: int, desc: str) -> ProgressLine | None:
        return self.progress_factory(total, desc) if self.progress_factory else None
