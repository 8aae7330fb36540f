"""Assessment at a whole fraction of the training size (train.assess_width_px, train.figure_height_px)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from pipeline.errors import ConfigError
from pipeline.testing import run_stage_for_test
from stages.train.assess_images import AssessImages, assess_factor
from stages.train.data import load_train_data
from stages.train.output import TrainOutput
from stages.train.stage import STAGE
from tests.stages.train.test_train_stage import BASE
from tests.stages.train.train_synth import small_model


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> dict[str, Path]:
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from train_synth import make_capture

    return make_capture(tmp_path_factory.mktemp("synth"), width_px=32, cameras=4, frames_per_take=(27, 9))


def test_the_assessment_width_divides_the_training_size():
    assert assess_factor(768, 1024, 0) == 1 and assess_factor(768, 1024, 768) == 1
    assert assess_factor(768, 1024, 96) == 8
    with pytest.raises(ConfigError, match=r"train.assess_width_px=100.*768 x 1024.*\[384, 192, 96, 48\]"):
        assess_factor(768, 1024, 100)
    with pytest.raises(ConfigError, match="assess_width_px=1000"):
        assess_factor(768, 1024, 1000)
    with pytest.raises(ConfigError, match="24 x 33"):  # 12 divides the width, not the height
        assess_factor(24, 33, 12)


def test_half_size_images_are_the_area_average_and_rays_through_block_centres(capture):
    data = load_train_data(capture, 24, logging.getLogger("test"))
    _, tensors, _, renderer = small_model(data)
    full, half = AssessImages(tensors, 1), AssessImages(tensors, 2)
    pairs = [(0, 0), (5, 3)]
    h, w = tensors.height, tensors.width
    assert (half.height, half.width) == (h // 2, w // 2)
    target = tensors.target_images(pairs)
    pooled = target.view(2, h // 2, 2, w // 2, 2, 3).mean(dim=(2, 4))
    assert torch.allclose(half.targets(pairs), pooled)
    assert torch.allclose(half.mattes(pairs), tensors.target_mattes(pairs).view(2, h // 2, 2, w // 2, 2).mean((2, 4)))
    assert torch.equal(full.targets(pairs), target)  # factor 1: the training tensors' own values
    # A half-size pixel's ray goes through the centre of the 2 x 2 training pixels it covers.
    rays_full, rays_half = full.rays(5, 3), half.rays(5, 3)
    block_centres = rays_full.directions.view(h // 2, 2, w // 2, 2, 3).mean(dim=(1, 3))
    block_centres = block_centres / block_centres.norm(dim=-1, keepdim=True)
    assert float((rays_half.directions.view(h // 2, w // 2, 3) - block_centres).norm(dim=-1).max()) < 1e-5
    assert torch.allclose(rays_half.origins, rays_full.origins[: h * w // 4])
    assert torch.allclose(half.rays(5, 3).directions.norm(dim=-1), torch.ones(h * w // 4))
    # The same model seen by a camera with 2x larger pixels: close to its full-size render, averaged.
    rgb_full, _ = full.render(renderer, pairs)
    rgb_half, alpha_half = half.render(renderer, pairs)
    assert rgb_half.shape == (2, h // 2, w // 2, 3) and alpha_half.shape == (2, h // 2, w // 2)
    averaged = rgb_full.view(2, h // 2, 2, w // 2, 2, 3).mean(dim=(2, 4))
    mse = float(((rgb_half - averaged) ** 2).mean())
    assert 10 * np.log10(float(averaged.max()) ** 2 / max(mse, 1e-12)) > 20.0


def test_the_stage_measures_previews_and_figures_at_the_reduced_sizes(capture, tmp_path):
    out = run_stage_for_test(STAGE, tmp_path, capture, {**BASE, "iterations": 4, "baseline_iterations": 4,
                                                         "previews": 1, "assess_width_px": 12,
                                                         "figure_height_px": 20})
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["image_width_px"] == 24  # trained at 24 px, assessed at 12
    for split in ("val_light", "novel_light", "novel_perf"):
        assert np.isfinite(metrics[f"ours_{split}_psnr"])
    preview = cv2.imread(str(out / "previews" / "novel_light_0.png"))
    assert preview.shape[0] == 16 and preview.shape[1] == 3 * 12  # ground truth | ours | TRAvatar*
    captions = {p.stem: c for p, c in TrainOutput(out).comparisons()}
    assert "x 20 px (reduced from the capture's size)" in captions["novel_light"]
