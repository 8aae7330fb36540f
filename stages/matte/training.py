"""Supervised training and SOC adaptation of the matting network (inference: ``stages.matte.inference``)."""

from __future__ import annotations

import copy
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field

from stages.matte.augment import AugmentConfig, augment, random_crop
from stages.matte.inputs import bright_level, network_input, olat_scale
from stages.matte.losses import soc_loss, supervised_loss
from stages.matte.modnet import SIZES, MODNet, NetSize


class InputConfig(BaseModel):
    """Input normalisation (the same in training and inference)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    exposure_floor: float = Field(
        0.2, description="Smallest F exposure reference (linear luminance; a well exposed F frame's 99th "
                         "percentile is ~0.3-1), so the sensor noise of an empty studio is not stretched to white.")
    olat_floor_ratio: float = Field(0.02, description="An OLAT frame's scale is at least this x its camera's F reference.")


class TrainConfig(BaseModel):
    """Supervised training of the matting network."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    net_size: NetSize = Field("tiny", description="Network size: 'tiny' (2-core CPU) or 'large' (GPU).")
    iterations: int = Field(1500, ge=1, description="Optimiser steps.")
    batch_size: int = Field(8, ge=1, description="Crops per step.")
    crop_px: int = Field(96, ge=32, multiple_of=32, description="Square training crop size in pixels (multiple of 32).")
    learning_rate: float = Field(2e-3, gt=0, description="Adam learning rate at the start (cosine decay to 1/20).")
    transition_radius_px: int = Field(3, ge=1, description="Half-width of the trimap transition region for the detail and boundary losses.")
    seed: int = Field(0, description="Random seed of initialisation, batches and augmentation.")
    augment: AugmentConfig = Field(AugmentConfig(), description="Augmentation strengths.")
    inputs: InputConfig = Field(InputConfig(), description="Input normalisation.")


class SocConfig(BaseModel):
    """SOC adaptation on unlabelled frames of the capture being matted."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    iterations: int = Field(60, ge=0, description="SOC steps (0 disables the adaptation).")
    batch_size: int = Field(4, ge=1, description="Frames per SOC step.")
    crop_px: int = Field(96, ge=32, multiple_of=32, description="Square crop size of SOC frames (multiple of 32).")
    learning_rate: float = Field(1e-4, gt=0, description="Adam learning rate (small: adaptation, not retraining).")
    anchor_weight: float = Field(1.0, ge=0, description="Weight of the L1 to the frozen model's detail and matte.")
    seed: int = Field(0, description="Random seed of frame and crop choice.")


@dataclass
class TrainingSet:
    """Labelled samples, linear float32, each image with its guide F frame.

    ``references`` are the F exposure references (the clean guide's bright level; for an
    empty frame a typical level of the set).
    """

    images: list[np.ndarray] = field(default_factory=list)  # each [H, W, 3]
    guides: list[np.ndarray] = field(default_factory=list)  # each [H, W, 3]
    alphas: list[np.ndarray] = field(default_factory=list)  # each [H, W]
    is_olat: list[bool] = field(default_factory=list)
    references: list[float] = field(default_factory=list)

    def add(self, image: np.ndarray, guide: np.ndarray, alpha: np.ndarray, is_olat: bool) -> None:
        """Append one sample; its reference is its guide's bright level (0 = empty, fixed by ``finish``)."""
        self.images.append(image.astype(np.float32))
        self.guides.append(guide.astype(np.float32))
        self.alphas.append(alpha.astype(np.float32))
        self.is_olat.append(bool(is_olat))
        self.references.append(bright_level(guide) if alpha.max() > 0 else 0.0)

    def finish(self) -> "TrainingSet":
        """Set the references of empty frames.

        Every other empty frame gets the median reference of the others (one empty frame in a
        capture of a person: its camera's reference comes from the person's F frames); the
        rest get 0, i.e. the exposure floor (a capture of an empty studio).
        """
        levels = [r for r in self.references if r > 0]
        typical = float(np.median(levels)) if levels else 1.0
        empty = 0
        references = []
        for r in self.references:
            if r <= 0:
                r = typical if empty % 2 == 0 else 0.0
                empty += 1
            references.append(r)
        self.references = references
        return self

    def __len__(self) -> int:
        return len(self.images)


def make_model(config: TrainConfig) -> MODNet:
    """A freshly initialised network of the configured size."""
    torch.manual_seed(config.seed)
    return MODNet(SIZES[config.net_size])


def sample_batch(train_set: TrainingSet, rng: np.random.Generator, config: TrainConfig
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Inputs [B,6,S,S], alpha [B,1,S,S] and the target's display colour [B,3,S,S] in [0, 1]."""
    inputs, alphas = [], []
    for index in rng.integers(0, len(train_set), config.batch_size):
        image, guide, alpha, reference = augment(
            train_set.images[index], train_set.guides[index], train_set.alphas[index],
            train_set.references[index], train_set.is_olat[index], rng, config.augment)
        image, guide, alpha = random_crop((image, guide, alpha), config.crop_px, rng)
        reference = max(reference, config.inputs.exposure_floor)
        scale = olat_scale(image, reference, config.inputs.olat_floor_ratio) if train_set.is_olat[index] else reference
        inputs.append(network_input(image, scale, guide, reference))
        alphas.append(alpha[None])
    inputs_t = torch.from_numpy(np.stack(inputs))  # [B, 6, S, S]
    return inputs_t, torch.from_numpy(np.stack(alphas)), (inputs_t[:, :3] + 1.0) * 0.5


def _cosine_lr(step: int, total: int, base: float) -> float:
    return base * (0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * step / max(total, 1))))


def train_supervised(train_set: TrainingSet, config: TrainConfig, device: str = "cpu",
                     log: logging.Logger | None = None,
                     on_step: Callable[[int, dict[str, float]], None] | None = None) -> tuple[MODNet, dict]:
    """Train a network from scratch on ``train_set``; returns it (eval mode, on CPU) and a training record."""
    if len(train_set) == 0:
        raise ValueError("the matting training set is empty")
    rng = np.random.default_rng(config.seed)
    model = make_model(config).to(device).train()
    optimiser = torch.optim.Adam(model.parameters(), lr=config.learning_rate)
    start = time.perf_counter()
    history: list[dict[str, float]] = []
    for step in range(config.iterations):
        for group in optimiser.param_groups:
            group["lr"] = _cosine_lr(step, config.iterations, config.learning_rate)
        inputs, alpha, colour = (t.to(device) for t in sample_batch(train_set, rng, config))
        semantic, detail, matte = model(inputs)
        loss, parts = supervised_loss(semantic, detail, matte, alpha, colour, config.transition_radius_px)
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        parts["loss"] = float(loss.detach())
        if step % 50 == 0 or step == config.iterations - 1:
            history.append({"step": step, **parts})
            if log is not None:
                log.info("matte training step %d/%d loss %.4f", step + 1, config.iterations, parts["loss"])
        if on_step is not None:
            on_step(step, parts)
    seconds = time.perf_counter() - start
    record = {"seconds": seconds, "iterations": config.iterations, "samples": len(train_set), "history": history}
    return model.cpu().eval(), record


def soc_adapt(model: MODNet, inputs: np.ndarray, config: SocConfig, device: str = "cpu") -> tuple[MODNet, dict]:
    """A copy of ``model`` adapted by SOC to unlabelled network inputs [N, 6, H, W]; returns it (eval, CPU) and a record."""
    adapted = copy.deepcopy(model).to(device).train()
    adapted.freeze_batch_norm()
    if config.iterations == 0 or len(inputs) == 0:
        return adapted.cpu().eval(), {"iterations": 0, "seconds": 0.0}
    frozen = copy.deepcopy(model).to(device).eval()
    rng = np.random.default_rng(config.seed)
    optimiser = torch.optim.Adam(adapted.parameters(), lr=config.learning_rate)
    start = time.perf_counter()
    losses = []
    for _ in range(config.iterations):
        picks = rng.integers(0, len(inputs), config.batch_size)
        # In normalised units the black backdrop is -1.
        crops = [random_crop((inputs[i].transpose(1, 2, 0),), config.crop_px, rng, fill=-1.0)[0] for i in picks]
        batch = torch.from_numpy(np.stack(crops).transpose(0, 3, 1, 2).copy()).to(device)  # [B, 6, S, S]
        with torch.no_grad():
            _, frozen_detail, frozen_matte = frozen(batch)
        semantic, detail, matte = adapted(batch)
        loss, _ = soc_loss(semantic, detail, matte, frozen_detail, frozen_matte, anchor_weight=config.anchor_weight)
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        losses.append(float(loss.detach()))
    record = {"iterations": config.iterations, "seconds": time.perf_counter() - start,
              "loss_first": losses[0], "loss_last": losses[-1]}
    return adapted.cpu().eval(), record
