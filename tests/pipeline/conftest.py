"""Fixtures of the orchestrator tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline_toy_support import ToyProject


@pytest.fixture
def toy(tmp_path: Path) -> ToyProject:
    return ToyProject(tmp_path)
