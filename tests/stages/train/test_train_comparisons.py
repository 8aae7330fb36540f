"""The train stage's comparison figures: every held-out split, at the capture's size, captions in words."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.testing import run_stage_for_test
from stages.train.output import TrainOutput
from stages.train.splits import HELD_OUT_SPLITS
from stages.train.stage import STAGE
from tests.stages.train.test_train_stage import BASE


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> dict[str, Path]:
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from train_synth import make_capture

    return make_capture(tmp_path_factory.mktemp("synth"), width_px=32, cameras=4, frames_per_take=(27, 9))


def test_every_split_has_a_comparison_figure_at_the_capture_size(capture, tmp_path):
    out = run_stage_for_test(STAGE, tmp_path, capture, {**BASE, "iterations": 4, "baseline_iterations": 4,
                                                         "previews": 2})
    manifest = json.loads((capture["capture"] / "manifest.json").read_text())
    size = f"{manifest['width']} x {manifest['height']} px"
    figures = dict((p.stem, c) for p, c in TrainOutput(out).comparisons())
    assert set(figures) == set(HELD_OUT_SPLITS)
    assert figures["novel_light"].startswith("Test, novel light: LED bars ") and size in figures["novel_light"]
    assert figures["val_light"].startswith("Validation light (chooses settings")
    assert "exposure" in figures["novel_light"] and "exposure" not in figures["novel_perf"]
    for split in HELD_OUT_SPLITS:
        image = cv2.imread(str(out / "comparisons" / f"{split}.png"))
        # Two rows of 256-px cells (the capture is smaller, so they are drawn larger), plus titles.
        assert image.shape[0] >= 2 * 256, (split, image.shape)
        assert np.ptp(image) > 0
