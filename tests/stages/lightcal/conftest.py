"""The small calibration take (same files as tests/stages/calibrate use: rendered once per session)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location(
    "calibrate_test_support", Path(__file__).resolve().parents[1] / "calibrate" / "conftest.py")
_support = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_support)


@pytest.fixture(scope="session")
def calib_capture(tmp_path_factory) -> tuple[Path, Path]:
    """(capture folder, truth folder) of the small calibration take."""
    return _support.small_capture(tmp_path_factory.getbasetemp())
