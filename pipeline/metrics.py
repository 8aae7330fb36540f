"""Stage metrics: flat ``key -> JSON number`` dicts, units in the key (required keys: docs/design.md)."""

from __future__ import annotations

import logging
import math
from typing import Any

from pipeline.errors import InputError

log = logging.getLogger("pipeline.metrics")


def clean_metrics(stage: str, metrics: dict[str, Any]) -> dict[str, Any]:
    """Plain JSON values (numpy scalars -> Python numbers, NaN/inf -> null with a warning)."""
    cleaned: dict[str, Any] = {}
    for key, value in metrics.items():
        if hasattr(value, "item") and callable(value.item):
            try:
                value = value.item()
            except (ValueError, TypeError):
                pass
        if isinstance(value, float) and not math.isfinite(value):
            log.warning("stage %s: metric %s is %s; written as null", stage, key, value)
            value = None
        if value is not None and not isinstance(value, (int, float, str, bool)):
            raise InputError(f"stage '{stage}': metric '{key}' is a {type(value).__name__}; metrics must "
                             f"be flat JSON numbers (units in the key)")
        cleaned[str(key)] = value
    return cleaned
