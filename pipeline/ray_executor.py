"""``RayExecutor``: per-item work on a Ray cluster (``--executor ray``; ``pip install .[ray]``).

Where it connects, in order: ``address`` given to the constructor, ``$RAY_ADDRESS`` (e.g.
``ray://head-node:10001`` or ``auto`` on a cluster node), else a local Ray started with
``num_cpus=workers``. Items are sent in chunks (scheduling overhead per Ray task is ~1 ms,
larger than a small item's work), each chunk as one task with ``max_retries``: when a worker
process dies (killed, out of memory, node lost) Ray reruns its chunk, so a killed worker
loses no items. GPU items ask for ``num_gpus=1`` per task so Ray places them on GPU nodes.
Application exceptions are not retried: they are bugs or bad input and surface at once.
"""

from __future__ import annotations

import os
import sys
from typing import Any, Callable, Iterator, Sequence, TypeVar

from pipeline.errors import ConfigError, PipelineError
from pipeline.executor_base import BaseExecutor, ProgressFactory, apply_chunk, chunk_bounds, ordered

T = TypeVar("T")
R = TypeVar("R")


class RayExecutor(BaseExecutor):
    """Fans items out as Ray tasks; results in input order.

    Args:
        workers: CPUs for a local Ray (ignored when connecting to a cluster).
        progress_factory: progress display for ``map``.
        address: Ray cluster address; default ``$RAY_ADDRESS`` or a local Ray.
        max_retries: reruns of a chunk whose worker died.
        chunks_per_worker: chunks per worker (more: better balance, more overhead).
    """

    def __init__(self, workers: int | None = None, progress_factory: ProgressFactory | None = None,
                 address: str | None = None, max_retries: int = 3, chunks_per_worker: int = 4) -> None:
        super().__init__(workers, progress_factory)
        try:
            import ray
        except ImportError:
            raise ConfigError("executor 'ray': Ray is not installed; `pip install .[ray]` (or "
                              "`.venv/bin/pip install ray`), or use --executor local") from None
        self._ray = ray
        self.max_retries = max_retries
        self.chunks_per_worker = chunks_per_worker
        self._started_here = False
        if not ray.is_initialized():
            address = address or os.environ.get("RAY_ADDRESS")
            if address:
                ray.init(address=address, log_to_driver=False)
            else:
                # Local workers import what the driver imports: hand them its sys.path.
                driver_path = os.pathsep.join(p for p in sys.path if p and os.path.isdir(p))
                ray.init(num_cpus=self.workers, include_dashboard=False, log_to_driver=False,
                         configure_logging=False, runtime_env={"env_vars": {"PYTHONPATH": driver_path}})
            self._started_here = True
        self._remote_apply = ray.remote(apply_chunk)

    def cluster_cpus(self) -> int:
        """CPUs the cluster offers (for chunking)."""
        return max(1, int(self._ray.cluster_resources().get("CPU", self.workers)))

    def map(self, fn: Callable[[T], R], items: Sequence[T], *, desc: str = "items", gpu: bool = False) -> list[R]:
        """Apply ``fn`` to every item as Ray tasks (in chunks); results in input order."""
        items = list(items)
        return ordered(self.imap(fn, items, desc=desc, gpu=gpu), len(items))

    def imap(self, fn: Callable[[T], R], items: Sequence[T], *, desc: str = "items",
             gpu: bool = False) -> Iterator[tuple[int, R]]:
        """``(position, result)`` as chunks finish; every chunk is submitted at the call."""
        items = list(items)
        if not items:
            return iter(())
        n_chunks = min(len(items), self.cluster_cpus() * self.chunks_per_worker)
        bounds = chunk_bounds(len(items), n_chunks)
        options: dict[str, Any] = {"max_retries": self.max_retries, "retry_exceptions": False}
        if gpu:
            options["num_gpus"] = 1
        fn_ref = self._ray.put(fn)
        refs = [self._remote_apply.options(**options).remote(fn_ref, items[bounds[i]:bounds[i + 1]])
                for i in range(n_chunks)]
        return self._drain(refs, bounds, desc)

    def _drain(self, refs: list[Any], bounds: list[int], desc: str) -> Iterator[tuple[int, Any]]:
        index_of = {ref: i for i, ref in enumerate(refs)}
        progress = self._progress(bounds[-1], desc)
        pending = list(refs)
        try:
            while pending:
                done, pending = self._ray.wait(pending, num_returns=1)
                for ref in done:
                    i = index_of[ref]
                    try:
                        chunk_results = self._ray.get(ref)
                    except self._ray.exceptions.RayTaskError as err:
                        raise err.as_instanceof_cause() from None
                    except self._ray.exceptions.WorkerCrashedError as err:
                        raise PipelineError(f"ray: a worker died {self.max_retries + 1} times on {desc} "
                                            f"{bounds[i]}..{bounds[i + 1] - 1}: {err}") from None
                    if progress:
                        progress.advance(len(chunk_results))
                    for offset, value in enumerate(chunk_results):
                        yield bounds[i] + offset, value
        finally:
            for other in pending:  # an error, or the caller stopped early
                self._ray.cancel(other)
            if progress:
                progress.close()

    def close(self) -> None:
        if self._started_here and self._ray.is_initialized():
            self._ray.shutdown()
            self._started_here = False
