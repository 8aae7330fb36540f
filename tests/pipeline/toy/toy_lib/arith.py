"""Arithmetic used by the toy ``double`` stage (imported by it, so part of its code digest)."""


def apply(item: tuple[float, int, str]) -> float:
    """Scale or shift one number: ``(value, factor, mode)``."""
    value, factor, mode = item
    return value * factor if mode == "mul" else value + factor
