"""A trained run scored on another build's images (benchmarks/cross_build.py)."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks.cross_build import BuildMismatch, score_on_build
from pipeline.testing import run_stage_for_test
from scene.image_io import read_exr, write_exr
from stages.train.evaluate import SCALED_SPLITS
from stages.train.splits import HELD_OUT_SPLITS
from stages.train.stage import STAGE

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "stages" / "train"))
from train_synth import SMALL_AVATAR, make_capture  # noqa: E402

PARAMS = {"avatar": SMALL_AVATAR, "image_width_px": 24, "batch_size": 2, "rays_per_image": 64, "eval_images": 2,
          "curve_every": 0, "previews": 0, "threads": 1, "lpips": False, "held_out_fraction": 1.0,
          "iterations": 6, "baseline_iterations": 6}


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("cross")
    capture = make_capture(root / "synth", width_px=32, cameras=4, frames_per_take=(27, 9))
    out = run_stage_for_test(STAGE, root / "run", capture, PARAMS)
    return capture, out


def _rebuilt(capture: dict[str, Path], dest: Path, change) -> dict[str, Path]:
    """A copy of the train inputs whose capture images are ``change(image, index)``."""
    copy = {k: dest / k for k in capture}
    for k, folder in capture.items():
        shutil.copytree(folder, copy[k])
    for i, path in enumerate(sorted((copy["capture"] / "frames").rglob("*.exr"))):
        write_exr(path, change(read_exr(path), i).astype(np.float32))
    return copy


def test_scored_on_its_own_build_a_run_gives_the_stage_figures(trained):
    capture, out = trained
    metrics = json.loads((out / "metrics.json").read_text())
    scores = score_on_build(out, capture, STAGE.params(**PARAMS))
    for kind in ("ours", "travatar"):
        assert scores[f"{kind}_train"] == pytest.approx(metrics[f"{kind}_train_psnr"], abs=1e-4)
        for split in HELD_OUT_SPLITS:
            assert scores[f"{kind}_{split}"] == pytest.approx(metrics[f"{kind}_{split}_psnr"], abs=1e-4), (kind, split)


def test_the_reference_is_put_in_the_runs_units_and_other_images_score_otherwise(trained, tmp_path):
    capture, out = trained
    params = STAGE.params(**PARAMS)
    own = score_on_build(out, capture, params)
    # The builds share the studio's units: twice the light in the reference's images is twice the target,
    # not another exposure to normalise away. The held-out-light splits match each image's exposure, as the
    # train stage does, so their error doubles with the target (PSNR's peak stays 1): exactly 20 log10(2) dB
    # lower. The others now miss by a factor of 2.
    brighter = score_on_build(out, _rebuilt(capture, tmp_path / "x2", lambda img, i: img * 2.0), params)
    for kind in ("ours", "travatar"):
        for split in SCALED_SPLITS:
            assert brighter[f"{kind}_{split}"] == pytest.approx(own[f"{kind}_{split}"] - 20 * np.log10(2), abs=1e-3)
        for split in ("train", "val_perf", "novel_perf"):
            assert brighter[f"{kind}_{split}"] < own[f"{kind}_{split}"] - 1.0, (kind, split)
    # Much noisier images of the same frames: the same models score lower on every split.
    rng = np.random.default_rng(0)
    noisy = score_on_build(out, _rebuilt(capture, tmp_path / "noisy",
                                         lambda img, i: np.abs(img + rng.normal(0, 0.5, img.shape))), params)
    for split in HELD_OUT_SPLITS:
        assert noisy[f"ours_{split}"] < own[f"ours_{split}"] - 0.5, split


def test_a_build_of_other_frames_is_refused(trained, tmp_path):
    capture, out = trained
    other = make_capture(tmp_path / "other", width_px=32, cameras=4, frames_per_take=(30, 9))
    with pytest.raises(BuildMismatch, match="other frames|holds out bars"):
        score_on_build(out, other, STAGE.params(**PARAMS))
