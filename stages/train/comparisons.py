"""The train stage's comparison figures: per held-out split, ground truth | ours | TRAvatar* | their errors.

The paper's comparison figure for every split the stage measures, at the **capture's**
resolution rather than the training images' (the volumetric head renders at any resolution,
and the capture holds the full-size ground truth): the first ``count`` evaluation images of
the split (the same (frame, camera) pairs the table's figures start from), each model
rendered through the frame's stabilised head-space camera under the frame's light. As for
the table, predictions under novel lights are scaled to the ground truth's exposure (least
squares: the network's light units are its own). Errors share one scale per figure
(``scene.comparison_figure``).

Writes ``comparisons/<split>.png`` and ``comparisons/captions.json`` (split -> caption in
words, for the report).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import torch

from avatar.metrics import exposure_scale
from avatar.render import Rays
from scene.comparison_figure import ComparisonRow, write_comparison_figure
from stages.capture.output import CaptureOutput
from stages.matte.output import MatteOutput
from stages.stabilize.output import StabilizeOutput
from stages.train.data import TrainData, resize_area
from stages.train.evaluate import SCALED_SPLITS
from stages.train.fit import TrainedHeads
from stages.train.setup import TrainingSetup
from stages.train.splits import SPLITS, VAL_SPLITS

MODEL_LABELS = {"ours": "ours", "travatar": "TRAvatar*"}


def split_caption(split: str, setup: TrainingSetup) -> str:
    """What a split holds, in words."""
    splits = setup.splits
    bars = ", ".join(str(b) for b in splits.held_out_bars)
    take = splits.held_out_take
    val_bars = ", ".join(str(b) for b in splits.val_bars)
    captions = {
        "val_light": f"Validation light (chooses settings, never reported as a result): LED bars {val_bars}, never "
                     "lit in training, on frames of the training performance",
        "val_perf": f"Validation performance (chooses settings, never reported as a result): {splits.val_segment}, "
                    "never seen in training, under training lights",
        "novel_light": f"Test, novel light: LED bars {bars}, never lit in training, on frames of the training "
                       "performance",
        "novel_perf": f"Test, novel performance: {take} of the capture, never seen in training, under training lights",
        "novel_both": f"Test, novel light and performance: bars {bars} on {take}",
    }
    return captions.get(split, split.replace("_", " "))


def write_comparisons(folder: Path, inputs: dict[str, Path], data: TrainData, setup: TrainingSetup,
                      heads: TrainedHeads, count: int, log: logging.Logger, height_px: int = 0) -> dict[str, str]:
    """Write one comparison figure per split with evaluation images; returns split -> caption.

    ``height_px`` > 0 and under the capture's height renders and shows the images at that height
    (ground truth and matte area-averaged to it); 0 keeps the capture's size.
    """
    if count <= 0:
        return {}
    capture, matte = CaptureOutput(inputs["capture"]), MatteOutput(inputs["matte"])
    cams_head = StabilizeOutput(inputs["stabilize"]).cameras_head_by_name()
    tensors = setup.tensors
    folder.mkdir(parents=True, exist_ok=True)
    captions: dict[str, str] = {}
    for split in SPLITS + VAL_SPLITS:  # the test splits first: what a user will get
        pairs = setup.pairs.get(split, [])
        if not pairs:
            continue
        rows = []
        for f, c in pairs[:count]:
            index, name = int(data.frame_index[f]), data.camera_names[c]
            camera = cams_head[index][name]  # the capture's resolution
            truth = capture.frame(name, index)[..., :3].astype(np.float32) * np.float32(setup.image_scale)
            truth_alpha = matte.matte(name, index)
            reduced = 0 < height_px < camera.height
            if reduced:
                camera = camera.scaled(height_px / camera.height)
                truth, truth_alpha = (resize_area(np.ascontiguousarray(x, np.float32), camera.width, camera.height)
                                      for x in (truth, truth_alpha))
            rays = Rays.of_camera(camera, tensors.device)
            predictions = {}
            for kind in heads.kinds:
                rgb, _ = heads.renderers[kind].render_rays(tensors, [f], [rays])
                pred = rgb[0].float().cpu()
                if split in SCALED_SPLITS:  # the table's least-squares exposure match
                    pred = pred * exposure_scale(pred[None], torch.as_tensor(truth)[None])[0]
                predictions[MODEL_LABELS.get(kind, kind)] = pred.numpy()
            rows.append(ComparisonRow(f"frame {index}, {name}, bar {int(data.bar[f])}", truth, predictions,
                                      truth_alpha=truth_alpha))
        caption = split_caption(split, setup)
        h, w = rows[0].truth.shape[:2]
        size = "reduced from the capture's size" if reduced else "the capture's size"
        write_comparison_figure(folder / f"{split}.png", rows, f"{caption} ({w} x {h} px, {size})")
        captions[split] = (f"{caption}. Ground truth, each model's render at {w} x {h} px ({size}), and each "
                           "model's per-pixel error (mean over RGB, as a fraction of the ground truth's white; one "
                           "colour scale per figure)"
                           + (". Predictions scaled to the ground truth's exposure, as in the table" if split in
                              SCALED_SPLITS else ""))
        log.info("comparison figure %s: %d images", split, len(rows))
    (folder / "captions.json").write_text(json.dumps(captions, indent=1))
    return captions


__all__ = ["split_caption", "write_comparisons"]
