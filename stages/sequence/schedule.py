"""The capture pattern and its frame schedule.

One cycle interleaves full-on frames with the OLAT order: ``F, O1, O2, F, O3, O4, ...``
(``olat_per_full_on`` OLAT frames after each ``F``). The schedule repeats the cycle and
gives every frame its index, its time at the capture's frame rate, and its light.
"""

from __future__ import annotations

from typing import Sequence, Union

Light = Union[str, int]  # "F" (every bar on) or a bar id
FULL_ON = "F"


def build_pattern(olat_order: Sequence[int], olat_per_full_on: int) -> list[Light]:
    """One cycle: an ``F`` before every group of ``olat_per_full_on`` OLAT lights.

    A last group may be shorter when the bar count is not a multiple of the group size.
    """
    if olat_per_full_on < 1:
        raise ValueError(f"olat_per_full_on must be at least 1, got {olat_per_full_on}")
    pattern: list[Light] = []
    for start in range(0, len(olat_order), olat_per_full_on):
        pattern.append(FULL_ON)
        pattern.extend(int(b) for b in olat_order[start:start + olat_per_full_on])
    return pattern


def build_schedule(pattern: Sequence[Light], cycles: int, fps: float) -> list[dict]:
    """Every frame of ``cycles`` repetitions of ``pattern``: ``{"frame", "time_s", "light"}``."""
    if cycles < 1:
        raise ValueError(f"cycles must be at least 1, got {cycles}")
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    frames = []
    for index in range(cycles * len(pattern)):
        frames.append({"frame": index, "time_s": round(index / fps, 9), "light": pattern[index % len(pattern)]})
    return frames


def olat_pairs_across_full_on(pattern: Sequence[Light]) -> list[bool]:
    """For each consecutive OLAT pair of the (cyclic) pattern: whether an ``F`` frame separates them."""
    olat_positions = [i for i, light in enumerate(pattern) if light != FULL_ON]
    across = []
    for k, pos in enumerate(olat_positions):
        nxt = olat_positions[(k + 1) % len(olat_positions)]
        between = [pattern[i % len(pattern)] for i in range(pos + 1, nxt if nxt > pos else nxt + len(pattern))]
        across.append(FULL_ON in between)
    return across
