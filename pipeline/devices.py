"""Where a stage's tensors go: the one resolver of a ``device`` setting (``auto``, ``cpu``, ``cuda``).

torch is imported only when a setting is resolved, so importing this module costs nothing.
"""

from __future__ import annotations

from typing import Literal

from pipeline.errors import ConfigError

# The values a stage's ``device`` param takes.
DeviceChoice = Literal["auto", "cpu", "cuda"]


def resolve_device(choice: str, setting: str) -> str:
    """``"cuda"`` or ``"cpu"`` for a ``device`` setting; ``setting`` names it in errors (``train.device``).

    ``auto`` takes CUDA when torch sees a device; ``cuda`` without one is an error rather than a
    silent fall-back to a CPU run many times slower.
    """
    import torch

    if choice == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if choice not in ("cpu", "cuda"):
        raise ConfigError(f"{setting}={choice!r}: use 'auto', 'cpu' or 'cuda'")
    if choice == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"{setting}: 'cuda' asked for but no CUDA device is available; use 'auto' or 'cpu'")
    return choice
