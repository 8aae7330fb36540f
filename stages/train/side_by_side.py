"""Train several models in one process: one after another, or side by side, one Python thread each.

Why threads work here: torch releases the GIL inside its kernels and autograd's backward, and
with one intra-op thread (``train.threads: 1``) a model's ops run on the thread that calls
them. So ours and TRAvatar* train on a 2-core CPU in about the time of one, with the same
numbers as one after another: each model has its own sampling generator, optimiser and
checkpoint, and its ops do not depend on what the other thread does; the parameters come
out bit-identical (timings: docs/experiments.md, section 5). Processes would gain nothing over
this and would have to copy the data and forward the stage's log, progress line and
TensorBoard writer.

On a GPU the two models would share one device's kernels and memory, so the default stays
one after another (``train.parallel_models: 1``).
"""

from __future__ import annotations

import threading
from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait
from typing import Any

from stages.train.trainer import ModelTrainer, TrainState, TrainingStopped


class SharedProgress:
    """One progress line for several trainers: their iterations add up, the latest fields show.

    ``advance`` takes a lock, so trainers on different threads may call it at any time.
    """

    def __init__(self, progress: Any) -> None:
        self._progress = progress
        self._lock = threading.Lock()

    def advance(self, n: int = 1, **fields: Any) -> None:
        with self._lock:
            self._progress.advance(n, **fields)


def train_models(trainers: dict[str, ModelTrainer], progress: Any, parallel: int = 1) -> dict[str, TrainState]:
    """Run every trainer to its iteration count; their final states by name.

    ``parallel``: how many train at once (1 = one after another, in this thread). Side by
    side, the first error (or a KeyboardInterrupt in this thread) stops the other trainers at
    their next iteration and is raised here once they have stopped; every trainer keeps its
    last checkpoint, so a rerun resumes where each one was.
    """
    shared = SharedProgress(progress)
    if parallel <= 1 or len(trainers) <= 1:
        return {name: trainer.run(shared) for name, trainer in trainers.items()}
    stop = threading.Event()
    for trainer in trainers.values():
        trainer.stop_event = stop
    pool = ThreadPoolExecutor(max_workers=min(parallel, len(trainers)), thread_name_prefix="train")
    futures = {name: pool.submit(trainer.run, shared) for name, trainer in trainers.items()}
    try:
        wait(futures.values(), return_when=FIRST_EXCEPTION)
    finally:
        # A trainer failed, or this thread was interrupted: the others stop at their next
        # iteration (when all have finished, nobody reads the flag any more).
        stop.set()
        pool.shutdown(wait=True)
        for trainer in trainers.values():
            trainer.stop_event = None
    errors = [f.exception() for f in futures.values() if f.exception() is not None]
    if errors:
        # The error that stopped the others, not their TrainingStopped.
        raise next((e for e in errors if not isinstance(e, TrainingStopped)), errors[0])
    return {name: future.result() for name, future in futures.items()}
