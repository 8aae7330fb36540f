"""How a batch's training images are drawn (``train.image_order``): random by default, or balanced passes."""

from __future__ import annotations

import logging
from collections import Counter

import numpy as np
import pytest
import torch

from stages.train import trainer as trainer_mod


def _trainer(tensors_and_renderer, tmp_path, order: str, train_frames: np.ndarray, batch: int = 4, seed: int = 3):
    tensors, renderer = tensors_and_renderer
    return trainer_mod.ModelTrainer(renderer, tensors, train_frames, iterations=50, batch_size=batch,
                                    rays_per_image=16, lr=1e-3, weights=trainer_mod.LossWeights(), seed=seed,
                                    ckpt_path=tmp_path / f"{order}.pt", checkpoint_every=100, spike_factor=10.0,
                                    log=logging.getLogger("test"), image_order=order)


def _images(tr, iterations: int) -> list[tuple[int, int]]:
    seen = []
    for i in range(iterations):
        tr.state.iteration = i  # what step() advances; the batch depends on it alone
        frames, cams = tr.batch_images()
        seen += list(zip(frames.tolist(), cams.tolist()))
    return seen


def test_balanced_order_sees_every_training_image_equally_often(tensors_and_renderer, tmp_path):
    train_frames = np.array([0, 2, 3, 5, 6])  # not every frame trains: others are held out
    tr = _trainer(tensors_and_renderer, tmp_path, "balanced", train_frames, batch=4)
    cameras = tensors_and_renderer[0].num_cameras
    count = len(train_frames) * cameras  # 15 images: a batch of 4 straddles the passes' ends
    seen = _images(tr, iterations=11)  # 44 draws: two whole passes and 14 images of the third
    per_image = Counter(seen)
    assert set(per_image) <= {(int(f), c) for f in train_frames for c in range(cameras)}
    first_two = Counter(seen[:2 * count])
    assert set(first_two.values()) == {2} and len(first_two) == count  # each image exactly twice in 2 passes
    assert max(per_image.values()) - min(per_image.values()) <= 1
    assert seen[:count] != seen[count:2 * count]  # a fresh shuffle every pass
    # the order follows from the seed and the iteration alone: a resumed trainer draws the same images
    again = _trainer(tensors_and_renderer, tmp_path, "balanced", train_frames, batch=4)
    assert _images(again, iterations=11) == seen
    other_seed = _trainer(tensors_and_renderer, tmp_path, "balanced", train_frames, batch=4, seed=4)
    assert _images(other_seed, iterations=11) != seen


def test_random_order_draws_from_the_checkpointed_generator_as_before(tensors_and_renderer, tmp_path):
    train_frames = np.array([0, 2, 3, 5, 6])
    tr = _trainer(tensors_and_renderer, tmp_path, "random", train_frames, batch=4)
    frames, cams, _ = tr.sample_batch()
    g = torch.Generator(device="cpu")
    g.manual_seed(3)
    pick = torch.randint(len(train_frames), (4,), generator=g)
    assert frames.tolist() == train_frames[pick.numpy()].tolist()
    assert cams.tolist() == torch.randint(tensors_and_renderer[0].num_cameras, (4,), generator=g).tolist()


def test_an_unknown_order_is_refused(tensors_and_renderer, tmp_path):
    with pytest.raises(ValueError, match="image_order"):
        _trainer(tensors_and_renderer, tmp_path, "sorted", np.arange(3))
