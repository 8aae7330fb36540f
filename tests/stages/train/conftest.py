"""Fixtures shared by the trainer's unit tests."""

from __future__ import annotations

import logging

import pytest

from stages.train.data import load_train_data
from tests.stages.train.train_synth import make_capture, small_model


@pytest.fixture(scope="module")
def tensors_and_renderer(tmp_path_factory):
    """A small synthetic capture's training tensors and a small model's renderer (3 cameras, 24 px wide)."""
    capture = make_capture(tmp_path_factory.mktemp("synth"), width_px=24, cameras=3, frames_per_take=(5, 4))
    data = load_train_data(capture, 16, logging.getLogger("test"))
    _, tensors, _, renderer = small_model(data)
    return tensors, renderer
