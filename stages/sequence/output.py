"""The sequence stage's output folder: the one place that spells its file names.

Files::

    sequence.json  olat_order, pattern (one cycle), fps, cycles, frames, duration_s, program,
                   program_crc32, head_center_m, bars, schedule (see ``stages.sequence.stage``)
    order.png      the OLAT order drawn on a sphere projection
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pipeline.stage_output import StageOutput

_SEQUENCE = "sequence.json"
_ORDER_PNG = "order.png"

#: The names no module outside ``stages/sequence`` may spell (``tests/test_output_contracts.py``).
CONTRACT_NAMES = (_SEQUENCE, _ORDER_PNG)


class SequenceOutput(StageOutput):
    """The ``sequence`` object: the capture pattern, schedule and controller program."""

    stage = "sequence"

    @property
    def sequence_path(self) -> Path:
        return self.file(_SEQUENCE)

    def sequence(self, keys: tuple[str, ...] = ("pattern", "fps", "frames")) -> dict[str, Any]:
        """The parsed ``sequence.json``; it must hold ``keys``."""
        return self.read_json(_SEQUENCE, keys=keys)

    def write_sequence(self, sequence: dict[str, Any]) -> None:
        self.write_json(sequence, _SEQUENCE, indent=1)

    @property
    def order_png_path(self) -> Path:
        return self.file(_ORDER_PNG)
