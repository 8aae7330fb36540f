"""A trained run scored on another build's images: one fixed set of targets for two captures.

A capture setting (say ``capture.render.bar_samples``) changes the images a model trains on and
also the images its validation and test figures are measured against. Two builds' own figures
then differ by the targets as well as by the models. Scoring both builds' models on one build's
targets separates the two: the model of build A rendered for build B's validation and test
pairs, with B's cameras, head poses, meshes and light positions, against B's images.

This holds only where the builds film the same frames of the same performance (same
identity, sequence and splits); ``score_on_build`` checks that the reference's splits are the
run's, frame for frame, and refuses otherwise (another ``sequence.cycles``, say, films other
frames: compare those builds on their own validation splits instead).

Both builds film in the studio's units (the same exposure), so the reference's images are
scaled by the run's own exposure factor (``image_scale``, from its training images), not by
the one the reference's images would give: on the unscaled splits (``val_perf``,
``novel_perf``, the training images) a model is asked for the light it was trained to
predict. The held-out-light splits match each image's exposure, as the train stage does.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import torch

from avatar.io import load_trained
from stages.train.data import load_train_data
from stages.train.evaluate import SCALED_SPLITS, eval_pairs, image_metrics
from stages.train.output import TrainOutput
from stages.train.params import TrainParams
from stages.train.setup import prepare_training
from stages.train.splits import HELD_OUT_SPLITS
from stages.train.trainer import Renderer

log = logging.getLogger("bench.cross_build")


class BuildMismatch(ValueError):
    """The reference build does not film the run's frames, so its targets are not the same questions."""


def score_on_build(train_out: Path, reference_inputs: dict[str, Path], params: TrainParams,
                   spill_dir: Path | None = None) -> dict[str, float]:
    """PSNR of each model saved in ``train_out`` on the reference build's splits and training images.

    Returns ``{kind}_{split}`` for every held-out split and ``{kind}_train`` (the training images, the
    run's ``eval_images`` of them, as the train stage picks them), the same figures the train stage
    reports as ``{kind}_{split}_psnr`` and ``{kind}_train_psnr``. With ``reference_inputs`` the run's own
    inputs it returns the stage's own figures (the test of this module checks that).

    Raises ``BuildMismatch`` when the reference's splits are not the run's frame for frame.
    """
    output = TrainOutput(train_out)
    own_metrics = json.loads((train_out / "metrics.json").read_text())
    own_splits = output.splits()
    data = load_train_data(dict(reference_inputs), params.image_width_px, log, params.max_frames,
                           resident_limit_gb=params.resident_limit_gb, spill_dir=spill_dir)
    setup = prepare_training(data, params, torch.device("cpu"), log)
    _check_same_frames(own_splits, setup, data.frame_index)
    # prepare_training scaled the reference's images by their own exposure factor: use the run's instead.
    setup.tensors.images.mul_(float(own_metrics["image_scale"]) / setup.image_scale)
    kinds = ["ours"] + (["travatar"] if output.model_dir("travatar").is_dir() else [])
    scores: dict[str, float] = {}
    for kind in kinds:
        model, _meta = output.model(lambda folder: load_trained(folder, "cpu"), kind)
        renderer = Renderer(model, kind, setup.basis if kind == "travatar" else None, setup.basis_bars,
                            params.raymarch_kernel)
        fit_pairs = eval_pairs(setup.fitted_frames, setup.num_cams, params.eval_images)
        pred, _ = setup.assess.render(renderer, fit_pairs)
        scores[f"{kind}_train"] = image_metrics(pred, setup.assess.targets(fit_pairs), scale=False)["psnr"]
        for split in HELD_OUT_SPLITS:
            pairs = setup.pairs[split]
            if pairs:
                pred, _ = setup.assess.render(renderer, pairs)
                scores[f"{kind}_{split}"] = image_metrics(pred, setup.assess.targets(pairs),
                                                          split in SCALED_SPLITS)["psnr"]
    return scores


def _check_same_frames(own_splits: dict, setup, frame_index: np.ndarray) -> None:
    """Refuse a reference whose splits hold other frames or bars than the run's (``splits.json``)."""
    for key in ("held_out_bars", "val_bars"):
        mine, theirs = sorted(own_splits.get(key, [])), sorted(int(b) for b in getattr(setup.splits, key))
        if mine != theirs:
            raise BuildMismatch(f"the reference build holds out bars {theirs} as {key}, the run {mine}: the builds "
                                "light other frames, so one's images do not score the other's model on the same "
                                "questions; compare them on their own validation splits")
    for split in ("train",) + HELD_OUT_SPLITS:
        mine, theirs = list(own_splits.get(split, [])), frame_index[setup.splits.mask(split)].tolist()
        if mine != theirs:
            raise BuildMismatch(f"split {split}: the reference build's frames {theirs[:6]}... are not the run's "
                                f"{mine[:6]}...: the builds film other frames (another sequence or frame "
                                "count); compare them on their own validation splits")
