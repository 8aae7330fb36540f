"""Helpers for unit tests of stages.

``run_stage_for_test`` runs one stage's ``run`` function outside a workspace
(``pipeline.scratch.run_stage_in_folder``, named for tests)::

    out = run_stage_for_test(SEQUENCE_STAGE, tmp_path, inputs={}, params={"fps": 24})
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from pipeline.executors import LocalExecutor
from pipeline.scratch import run_stage_in_folder
from pipeline.stage import Stage


class SerialExecutor(LocalExecutor):
    """Runs items one after another in this process (tests, debugging)."""

    def __init__(self, workers: int | None = 1, progress_factory=None) -> None:
        super().__init__(workers=1, progress_factory=progress_factory)


def run_stage_for_test(stage: Stage, workdir: Path, inputs: Mapping[str, Path] | None = None,
                       params: Mapping[str, Any] | None = None, *, subject: str = "test",
                       workers: int = 1) -> Path:
    """``run_stage_in_folder``: ``stage`` over ``inputs`` in ``workdir/<stage.name>``; returns that folder."""
    return run_stage_in_folder(stage, workdir, inputs, params, subject=subject, workers=workers)
