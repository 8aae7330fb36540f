"""Per-item functions for the streaming item-cache tests (top level, so workers can import them)."""

from __future__ import annotations

from pathlib import Path


def square_unless_poisoned(job: tuple[int, str]) -> dict:
    """``{"square": n * n}``; raises on an item named in the ``poison`` file of the job's folder."""
    value, folder = job
    (Path(folder) / "calls" / f"{value}.{id(job)}").touch()
    poison = Path(folder) / "poison"
    if poison.is_file() and str(value) in poison.read_text().split():
        raise ValueError(f"item {value} is poisoned")
    return {"square": value * value}


def job_key(job: tuple[int, str]) -> str:
    """The cache key of a job: its value only (not the folder)."""
    from pipeline.itemcache import content_key

    return content_key(job[0])
