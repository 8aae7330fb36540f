"""A per-frame function for the item cache tests (top level, so a process pool can pickle it)."""

from __future__ import annotations

import os
import uuid
from pathlib import Path


def frame_sum(job: tuple[str, str]) -> float:
    """Sum of the numbers in a frame file; leaves a marker per call in the calls folder."""
    path, calls = job
    (Path(calls) / f"{Path(path).stem}.{os.getpid()}.{uuid.uuid4().hex}").touch()
    return float(sum(float(x) for x in Path(path).read_text().split()))
