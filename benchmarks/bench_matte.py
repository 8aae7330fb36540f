"""Matting benchmark: CPU inference images/s and training time of the tiny network.

Prints and writes ``bench-results/matte.json``:
- ``inference_images_per_second_<H>x<W>``: batched tiny-network inference on CPU (network
  inputs prepared in advance), at the tiny preset's image size 240x320 and at 96x128.
- ``train_seconds_per_iteration`` and ``train_seconds_<N>_iterations``: supervised
  training steps (the tiny preset's batch 6, 96 px crops) on procedural figures (``stages.matte.synthetic``),
  so the figure does not depend on the studio's render speed;
  ``studio_render_seconds_per_sample`` times one studio training sample (target + guide).
Timings on a shared CPU are noisy. ``MATTE_BENCH_THREADS`` sets torch's thread count (default 1).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from stages.matte.modnet import SIZES, MODNet
from stages.matte.synthetic import random_pair
from stages.matte.inference import predict
from stages.matte.training import TrainConfig, TrainingSet, train_supervised

RESULTS = Path("bench-results")


def inference_rate(height: int, width: int, images: int = 16, batch_size: int = 8) -> float:
    """Images per second of tiny-network inference on CPU."""
    model = MODNet(SIZES["tiny"]).eval()
    inputs = np.random.default_rng(0).uniform(-1, 1, (images, 6, height, width)).astype(np.float32)
    predict(model, inputs[:batch_size], batch_size)  # warm-up
    start = time.perf_counter()
    predict(model, inputs, batch_size)
    return images / (time.perf_counter() - start)


def training_time(iterations: int = 40) -> tuple[float, float]:
    """(seconds per iteration, total seconds) of tiny-network training on procedural figures."""
    rng = np.random.default_rng(0)
    train_set = TrainingSet()
    for _ in range(16):
        pair = random_pair(rng, 96, 96)
        train_set.add(pair.image, pair.guide, pair.alpha, pair.is_olat)
    train_set.finish()
    _, record = train_supervised(train_set, TrainConfig(iterations=iterations, batch_size=6, crop_px=96))
    return record["seconds"] / iterations, record["seconds"]


def studio_sample_seconds(image_scale: float = 0.3125) -> float:
    """Seconds to render one OLAT training sample (target frame + guide F frame) in the studio."""
    from stages.matte.studio_data import IdentityJob, StudioDataConfig, render_identity

    config = StudioDataConfig(identity_seeds=(1001,), frame_pairs_per_identity=1, cameras_per_frame=1,
                              olat_fraction=1.0, empty_fraction=0.0)
    start = time.perf_counter()
    render_identity(IdentityJob(1001, config, image_scale))
    return time.perf_counter() - start


def main() -> None:
    # One thread: on the shared 2-core development machine two torch threads per process
    # thrash (5x slower); on dedicated cores MATTE_BENCH_THREADS=2 may be faster.
    threads = int(os.environ.get("MATTE_BENCH_THREADS", "1"))
    torch.set_num_threads(threads)
    results: dict[str, float] = {"threads": threads}
    for height, width in ((320, 240), (128, 96)):
        results[f"inference_images_per_second_{height}x{width}"] = inference_rate(height, width)
    per_iteration, total = training_time()
    results["train_seconds_per_iteration"] = per_iteration
    results["train_seconds_40_iterations"] = total
    results["train_seconds_600_iterations_estimate"] = per_iteration * 600  # the tiny preset
    results["studio_render_seconds_per_sample"] = studio_sample_seconds()
    for key, value in results.items():
        print(f"{key}: {value:.4g}")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "matte.json").write_text(json.dumps(results, indent=1, sort_keys=True))


if __name__ == "__main__":
    main()
