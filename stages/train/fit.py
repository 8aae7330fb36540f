"""Train the heads (ours, TRAvatar*) on a ``TrainingSetup``: models, trainers, and the training itself.

Reads nothing but the setup and the params; writes only the trainers' checkpoints (into the
folder it is given, so a killed run resumes) and, where a writer is given, TensorBoard events.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from avatar.capacity import latent_size
from avatar.config import AvatarConfig
from avatar.model import (RelightableMVP, count_parameters, latent_noise_to_code_spread, share_below_floor,
                          share_of_boxes_at_smallest)
from avatar.raymarch import RaymarchKernel
from pipeline.stage import Progress
from stages.train.assess_images import AssessImages
from stages.train.evaluate import image_metrics
from stages.train.params import TrainParams
from stages.train.setup import TrainingSetup
from stages.train.side_by_side import train_models
from stages.train.trainer import ModelTrainer, Renderer, TrainState


@dataclass
class TrainedHeads:
    """The trained models of a run.

    Attributes:
        kinds: the model kinds in training order (``"ours"``, then ``"travatar"`` with a baseline).
        renderers: each kind's renderer (its ``model`` in eval mode).
        states: each kind's final training state (iterations, times, rollbacks, learning curve).
        parameters: each kind's parameter count.
        training_seconds: wall-clock time of the training; the kinds' own ``train_seconds``
            overlap when they train side by side.
        latent_noise_to_code_spread: each kind's encoder noise over its codes' spread on the fitted
            frames at the end of training (``avatar.model.latent_noise_to_code_spread``).
    """

    kinds: list[str]
    renderers: dict[str, Renderer]
    states: dict[str, TrainState]
    parameters: dict[str, int]
    training_seconds: float
    latent_noise_to_code_spread: dict[str, float]

    def metrics(self) -> dict[str, float]:
        """Each kind's parameters, iterations, training time, rollbacks, primitives and latent noise."""
        out: dict[str, float] = {f"{kind}_parameters": self.parameters[kind] for kind in self.kinds}
        for kind in self.kinds:
            model, state = self.renderers[kind].model, self.states[kind]
            out[f"{kind}_iterations"] = state.iteration
            out[f"{kind}_seconds"] = state.train_seconds
            out[f"{kind}_rollbacks"] = state.rollbacks
            out[f"{kind}_clipped_steps"] = state.clipped_steps
            out[f"{kind}_pruned_primitives"] = model.num_pruned
            out[f"{kind}_primitives"] = model.config.num_prims
            out[f"{kind}_opacity_logits_below_floor"] = share_below_floor(model)
            out[f"{kind}_boxes_at_smallest_size"] = share_of_boxes_at_smallest(model)
            out[f"{kind}_latent_noise_to_code_spread"] = self.latent_noise_to_code_spread[kind]
            out[f"{kind}_latent_dim"] = model.config.latent_dim
        return out


def fit_heads(setup: TrainingSetup, num_bars: int, params: TrainParams, device: torch.device,
              kernel: RaymarchKernel, checkpoints: Path, log: logging.Logger,
              progress: Callable[[int, str], Progress], writer: Any = None, rank: int = 0,
              world_size: int = 1) -> TrainedHeads:
    """Build and train every model kind of ``params``; ``checkpoints`` holds ``<kind>.pt`` (resumed if there).

    Each model is initialised from ``params.seed`` (or ``init_seed``) right before it is built, so its weights do
    not depend on what was built before it. Only rank 0 records the learning curve (``writer``
    too, where given).
    """
    avatar, tensors, lead = setup.avatar, setup.tensors, rank == 0
    kinds = ["ours"] + (["travatar"] if params.baseline else [])
    renderers: dict[str, Renderer] = {}
    trainers: dict[str, ModelTrainer] = {}
    parameters: dict[str, int] = {}
    for kind in kinds:
        config = avatar if kind == "ours" else baseline_config(setup, params)
        torch.manual_seed(params.seed if params.init_seed is None else params.init_seed)
        model = RelightableMVP(config, setup.layout, num_bars).to(device)
        renderer = renderers[kind] = Renderer(model, kind, setup.basis if kind == "travatar" else None,
                                              setup.basis_bars, kernel=kernel)
        iterations = params.iterations if kind == "ours" else (params.baseline_iterations or params.iterations)
        trainers[kind] = ModelTrainer(
            renderer, tensors, setup.fitted_frames, iterations=iterations, batch_size=params.batch_size,
            rays_per_image=params.rays_per_image, lr=params.lr, weights=params.loss_weights,
            seed=params.seed if params.sampling_seed is None else params.sampling_seed,
            ckpt_path=checkpoints / f"{kind}.pt", checkpoint_every=params.checkpoint_every,
            spike_factor=params.spike_factor, log=log, curve_every=params.curve_every,
            curve_fn=_curve_psnr(renderer, setup.assess, setup.curve_pairs) if lead else None, writer=writer,
            lr_decay_to=params.lr_decay_to, rank=rank, world_size=world_size,
            prune=params.pruning.schedule(iterations), weight_average=params.weight_average,
            image_order=params.image_order, lr_warmup_iterations=params.lr_warmup_iterations,
            grad_clip_factor=params.grad_clip_factor)
        parameters[kind] = count_parameters(model)
        log.info("%s: %d parameters, %d primitives of %d^3 voxels", kind, parameters[kind],
                 config.num_prims, config.voxels_per_side)
    total = sum(t.iterations for t in trainers.values())
    if params.parallel_models > 1 and len(kinds) > 1:
        log.info("training %s side by side (train.parallel_models=%d)", " and ".join(kinds), params.parallel_models)
    started = time.perf_counter()
    with progress(total, "it") as bar:
        states = train_models(trainers, bar, params.parallel_models)
    training_seconds = time.perf_counter() - started
    for renderer in renderers.values():
        renderer.model.eval()
    fitted_meshes = tensors.guide_vertices[torch.as_tensor(setup.fitted_frames, device=tensors.guide_vertices.device)]
    return TrainedHeads(kinds=kinds, renderers=renderers, states=states, parameters=parameters,
                        training_seconds=training_seconds,
                        latent_noise_to_code_spread={kind: latent_noise_to_code_spread(renderers[kind].model, fitted_meshes)
                                                     for kind in kinds})


def baseline_config(setup: TrainingSetup, params: TrainParams) -> AvatarConfig:
    """TRAvatar*'s configuration: ours' with its light basis, and its own latent size where
    ``params.baseline_latent_per_mode`` gives one (``capacity: auto`` and moving meshes only)."""
    update: dict = {"light_basis": len(setup.basis_bars)}
    modes = setup.capacity.stats.expression_modes
    if params.baseline_latent_per_mode is not None and params.capacity == "auto" and modes > 0:
        rule = params.capacity_rule.model_copy(update={"latent_per_mode": params.baseline_latent_per_mode})
        if rule.latent_per_mode > 0:
            update["latent_dim"] = latent_size(modes, rule)
    return setup.avatar.model_copy(update=update)


def _curve_psnr(renderer: Renderer, images: AssessImages, pairs: list[tuple[int, int]]) -> Callable[[], float]:
    """The learning curve's measure: the validation-light PSNR of ``pairs`` (NaN without any)."""

    def psnr() -> float:
        if not pairs:
            return float("nan")
        pred, _ = images.render(renderer, pairs)
        return image_metrics(pred, images.targets(pairs), scale=True)["psnr"]

    return psnr
