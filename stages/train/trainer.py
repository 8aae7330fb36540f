"""The optimisation loop of one model (ours or TRAvatar*): sampling, losses, checkpoints, rollback.

Randomness comes from one ``torch.Generator`` whose state is checkpointed with the model and
the optimiser, so a killed run resumes from its last checkpoint and replays exactly the
iterations an uninterrupted run would have done. A NaN or a loss spike restores the last
good state (model and optimiser) with a warning and halves the learning rate; the sampler
goes on, so the offending batch is not replayed.

Data-parallel training (``world_size > 1``, inside an initialised ``torch.distributed``
process group): every rank draws the same global batch from the same generator and keeps
its contiguous share of it, the model is wrapped in ``DistributedDataParallel`` (gradients
averaged over ranks, so the step equals the single-process step on the whole batch), the
loss terms are averaged over ranks (so rollback decisions agree) and only rank 0 writes
checkpoints, logs and the learning curve. The generator state is the same on every rank,
so a checkpoint resumes with any number of processes.
"""

from __future__ import annotations

import copy
import json
import logging
import math
import threading
import time
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Literal, get_args

import numpy as np
import torch
from pydantic import ConfigDict, Field
from pydantic.dataclasses import dataclass as pydantic_dataclass
import torch.nn.functional as F
from torch import nn

from avatar.model import OPACITY_FLOOR_LOGIT, RelightableMVP, kl_divergence, opacity_floor_penalty
from avatar.raymarch import RaymarchKernel, raymarch
from avatar.reach import reach_penalty
from avatar.render import BasisLights, PointLights, Rays, decode, decode_lights, render
from avatar.travatar import LightBasis
from pipeline.workspace import atomic_path

#: How a batch's training images are drawn (``TrainParams.image_order``).
ImageOrder = Literal["random", "balanced"]

#: Steps before a running mean (of the loss, of the gradient norm) is trusted: the loss-spike
#: rollback and the gradient clip only record until then.
WARM_UP_STEPS = 50


class TrainingStopped(RuntimeError):
    """A trainer stopped early because a trainer beside it failed (``ModelTrainer.stop_event``)."""


@pydantic_dataclass(frozen=True, config=ConfigDict(extra="forbid"))
class LossWeights:
    """The loss terms' weights, the matte term's shape and the opacity's gradient on its flat tail (the one
    declaration: the train stage nests it as ``train.loss_weights``). The defaults are the paper's."""

    pho: float = Field(1.0, ge=0, description="Weight of the photometric (MSE) loss.")
    geo: float = Field(0.1, ge=0, description="Weight of the guide-mesh loss (MSE, cm^2); raise it if the "
                       "primitives drift off the tracked mesh.")
    vol: float = Field(0.01, ge=0, description="Weight of MVP's primitive volume prior; raise it if primitives "
                       "grow into large, blurry slabs, lower it if the train stage's `<model>_boxes_at_smallest_size` "
                       "is near 1 and renders leave the shoulders or the back of the head transparent (the tiny "
                       "preset uses 0.001; docs/experiments.md, section 37).")
    kld: float = Field(0.001, ge=0, description="Weight of the encoder's KL divergence (averaged over the code's "
                       "dimensions). It sets how much of the code the decoder trains on is noise (the train stage's "
                       "`<model>_latent_noise_to_code_spread`), and that noise keeps the decoder from overfitting the "
                       "training expressions: with far less of it the tiny preset fit the training images better and new "
                       "expressions worse (docs/experiments.md, section 41). Heavier, the seeds agree more and the "
                       "training performance is fitted less (section 42): raise it (3e-3) when one run must stand "
                       "for any. Change it only with the validation splits to judge by.")
    mat: float = Field(0.1, ge=0, description="Weight of the matte loss (L1, matte vs accumulated opacity); raise "
                       "it if the avatar leaks opacity outside the head.")
    mat_delta: float = Field(0.0, ge=0, lt=1, description="Opacity error under which the matte loss turns "
                             "quadratic (a Huber loss; 0 = the paper's L1 throughout). Above it the loss is the L1 "
                             "less a constant; under it the pull fades with the error instead of driving opacity "
                             "logits ever lower outside the head. Set it near the matte's own error (e.g. 0.01); "
                             "docs/experiments.md, section 34 measures it.")
    floor: float = Field(0.0, ge=0, description="Weight of the opacity floor (not the paper's): a squared penalty on "
                         "opacity logits below -8, where the softplus stops learning and holes stay open. 0 = off; "
                         "turn it on if renders show transparent patches where the matte is solid (docs/experiments.md, "
                         "section 34: it closed such a hole, and cost accuracy where none formed).")
    lift: bool = Field(False, description="Surrogate gradient on the opacity's flat tail (not the paper's): opacity "
                       "logits below -8 answer pulls towards more opacity with the softplus' slope at -8 instead of "
                       "their own vanishing one, so a transparent patch where the matte is solid can refill; pulls "
                       "towards less opacity, and every render, are unchanged. Off = the paper's softplus (on tiny it neither "
                       "narrowed the spread nor raised validation PSNR, not adopted); "
                       "docs/experiments.md, section 36 measures it.")
    reach: float = Field(0.0, ge=0, description="Weight of the reach term (not the paper's): for each training ray "
                         "the matte calls foreground (>= 0.5) that crosses no box, the distance, in the nearest box's "
                         "half extents, by which that box misses it, summed and divided by the batch's rays "
                         "(avatar.reach). Such a ray renders transparent and no other term has a gradient there; this "
                         "one moves and grows the nearest box towards it. 0 = off (the paper's); at 0.1 a missed ray "
                         "gets the pull the matte term gives a covered one. Turn it on if the train stage's "
                         "`<model>_val_*_uncovered_fraction` is high and renders leave shoulders or the back of the "
                         "head transparent. The tiny preset uses 0.1 for the first half of the run (reach_until 0.5): "
                         "it narrowed ours' spread over seeds on alice's and bob's validation splits with the means "
                         "unchanged (docs/experiments.md, sections 39 and 40).")
    reach_until: float = Field(1.0, gt=0, le=1, description="Fraction of the run during which the reach term is "
                               "on (1 = the whole run; 0.5 = until empty boxes are pruned at train.pruning.at_fraction's "
                               "default). "
                               "The term is for the foreground the grid of boxes leaves uncovered as the boxes settle; "
                               "late in the run the boxes are fitted, and pulling one towards a stray foreground ray "
                               "(a matte's false positive, say) moves a box that is already doing its job. Lower it if "
                               "the reach term closes holes but costs PSNR where there were none; "
                               "docs/experiments.md, section 40 measures it; tiny uses 0.5.")


@pydantic_dataclass(frozen=True, config=ConfigDict(extra="forbid"))
class Pruning:
    """When and how empty primitives are pruned, as fractions of the run (the train stage nests it as
    ``train.pruning``; ``schedule`` turns it into the trainer's ``PruneSchedule``)."""

    at_fraction: float = Field(0.5, ge=0, le=1, description="Prune empty primitives after this fraction of the "
                               "iterations (0 = never prune).")
    window_fraction: float = Field(0.2, gt=0, le=1, description="Fraction of the iterations, just before pruning, "
                                   "over which each primitive's opacity on training rays is recorded.")
    max_alpha: float = Field(0.01, ge=0, lt=1, description="A primitive that never added this much opacity to any "
                             "recorded training ray is pruned (dropped from the raymarch); raise it to prune more.")

    def schedule(self, iterations: int) -> PruneSchedule | None:
        """The schedule of a run of ``iterations`` (None when pruning is off)."""
        if self.at_fraction <= 0:
            return None
        at = max(1, int(round(self.at_fraction * iterations)))
        window = max(1, int(round(self.window_fraction * iterations)))
        return PruneSchedule(at_iteration=at, window=window, max_alpha=self.max_alpha)


@dataclass(frozen=True)
class PruneSchedule:
    """When and how empty primitives are pruned.

    Over the ``window`` iterations before ``at_iteration`` the trainer records, for every
    primitive, the largest opacity it added to any training ray (``RenderResult.prim_alpha``);
    at ``at_iteration`` the primitives whose record stays below ``max_alpha`` are dropped
    from the raymarch (``RelightableMVP.prune``).
    """

    at_iteration: int
    window: int
    max_alpha: float = 0.01

    @property
    def start(self) -> int:
        """First iteration whose rays are recorded."""
        return max(0, self.at_iteration - self.window)


@dataclass
class TrainTensors:
    """The training data as tensors (flattened pixels), and how a batch is gathered from it.

    Pixels stay where they are cheapest: on the training device when they fit (``images``
    and ``mattes`` on ``device``), else on the CPU over memory-mapped files (the paper
    preset), from which each batch's few pixels are gathered and moved to ``device``. Rays
    are not stored per pixel: a pixel's direction is its camera's fixed direction for that
    pixel rotated by the camera's pose in head space that frame.
    """

    images: torch.Tensor  # [F, C, H*W, 3] on device, or CPU (memory-mapped)
    mattes: torch.Tensor  # [F, C, H*W] same place as images
    pixel_dirs: torch.Tensor  # [C, H*W, 3] unit directions in each camera's frame
    head_from_cam: torch.Tensor  # [F, C, 3, 3] camera rotations in head space
    cam_pos: torch.Tensor  # [F, C, 3]
    light_pos: torch.Tensor  # [F, 3]
    bar: torch.Tensor  # [F] long
    guide_vertices: torch.Tensor  # [F, U, 3]
    height: int
    width: int
    device: torch.device = torch.device("cpu")

    @property
    def num_cameras(self) -> int:
        return int(self.images.shape[1])

    def pixels(self, frames: torch.Tensor, cams: torch.Tensor, pix: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
        """Colours [B, R, 3] and matte [B, R] of pixels ``pix`` [B, R] of images (``frames`` [B], ``cams`` [B]), on ``device``."""
        src = self.images.device
        fi, ci, pi = frames.to(src)[:, None], cams.to(src)[:, None], pix.to(src)
        return self.images[fi, ci, pi].to(self.device), self.mattes[fi, ci, pi].to(self.device)

    def rays(self, frames: torch.Tensor, cams: torch.Tensor, pix: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Head-space origins and unit directions [B, R, 3] of pixels ``pix`` [B, R]."""
        frames, cams, pix = frames.to(self.device), cams.to(self.device), pix.to(self.device)
        dirs = self.pixel_dirs[cams[:, None], pix]  # [B, R, 3]
        # Elementwise, not a batched matmul: each ray's value must not depend on the batch's size
        # (a DDP rank computes half the batch; bmm's blocking would change the rounding).
        rd = (self.head_from_cam[frames, cams][:, None] * dirs[:, :, None, :]).sum(-1)  # [B, R, 3]
        return self.cam_pos[frames, cams][:, None].expand_as(rd), rd

    def image_rays(self, f: int, c: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Origins and directions [H*W, 3] of every pixel of image (f, c)."""
        rd = self.pixel_dirs[c] @ self.head_from_cam[f, c].T  # [H*W, 3]
        return self.cam_pos[f, c][None].expand_as(rd), rd

    def image(self, f: int, c: int) -> torch.Tensor:
        """Image (f, c) [H*W, 3] on ``device``."""
        return self.images[f, c].to(self.device)

    def target_images(self, pairs: list[tuple[int, int]]) -> torch.Tensor:
        """The captured images [K, H, W, 3] of (frame, camera) ``pairs``, on ``device``."""
        return torch.stack([self.image(f, c).view(self.height, self.width, 3) for f, c in pairs])

    def target_mattes(self, pairs: list[tuple[int, int]]) -> torch.Tensor:
        """The mattes [K, H, W] (float) of (frame, camera) ``pairs``, on ``device``."""
        return torch.stack([self.mattes[f, c].float().view(self.height, self.width) for f, c in pairs]).to(self.device)

    def sampling_weights(self, frames: torch.Tensor, cams: torch.Tensor) -> torch.Tensor:
        """Ray sampling weights [B, H*W] on the CPU: foreground, grown by 3 px, weighs 1.1, background 0.1."""
        src = self.mattes.device
        m = self.mattes[frames.to(src), cams.to(src)].float().view(-1, 1, self.height, self.width)
        return (F.max_pool2d(m, 7, 1, 3).view(len(frames), -1) + 0.1).cpu()


@dataclass
class TrainState:
    """Everything a checkpoint holds besides the model and optimiser."""

    iteration: int = 0
    train_seconds: float = 0.0
    loss_ema: float = float("nan")
    lr: float = 0.0
    rollbacks: int = 0
    curve: list = field(default_factory=list)  # [(iteration, train_seconds, validation-light PSNR dB)]
    pruned: int = 0  # primitives pruned (0 until the scheduled iteration)
    prune_done: bool = False
    grad_norm_ema: float = float("nan")  # running mean of the (clipped) gradient norm, over all parameters
    clipped_steps: int = 0  # optimiser steps whose gradient was clipped (``grad_clip_factor``)


class Renderer:
    """One model kind's lights for the training loop's decode, and full images through ``avatar.render``."""

    def __init__(self, model: RelightableMVP, kind: str, basis: LightBasis | None, basis_bars: list[int],
                 kernel: RaymarchKernel = "auto") -> None:
        """``basis_bars``: the training bars (TRAvatar*'s light basis, in order; the bars with a learnt intensity).

        ``kernel``: the raymarcher (``avatar.raymarch.raymarch``'s ``kernel``).
        """
        self.model, self.kind, self.basis, self.kernel = model, kind, basis, kernel
        self.basis_index = {b: i for i, b in enumerate(basis_bars)}

    def lights(self, light_pos: torch.Tensor, bar: torch.Tensor, intensity: torch.Tensor) -> PointLights | BasisLights:
        """One light per batch item: ours at its position; TRAvatar* one-hot over its basis when every bar is
        a training bar, else the positions (interpolated over the basis)."""
        if self.kind == "ours":
            return PointLights(light_pos, intensity=intensity)
        bars = bar.tolist()
        if all(b in self.basis_index for b in bars):
            idx = np.array([self.basis_index[b] for b in bars])
            return BasisLights(self.basis.one_hot(idx), intensity=intensity)
        return PointLights(light_pos, intensity=intensity)

    def rgb(self, geometry, cam_pos: torch.Tensor, light_pos: torch.Tensor, bar: torch.Tensor,
            intensity: torch.Tensor) -> torch.Tensor:
        """RGB voxels for a batch: ours from the light position, TRAvatar* from its basis."""
        return decode_lights(self.model, geometry, cam_pos, self.lights(light_pos, bar, intensity),
                             self.basis)

    @torch.no_grad()
    def render_images(self, t: TrainTensors, pairs: list[tuple[int, int]], light_pos: torch.Tensor | None = None,
                      bar: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Full images [K, H, W, 3] and opacity [K, H, W] for (frame, camera) pairs; deterministic (z = mu)."""
        rays = [Rays(*t.image_rays(f, c), t.cam_pos[f, c], t.height, t.width) for f, c in pairs]
        return self.render_rays(t, [f for f, _ in pairs], rays, light_pos)

    @torch.no_grad()
    def render_rays(self, t: TrainTensors, frames: list[int], rays: list[Rays],
                    light_pos: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Images [K, H, W, 3] and opacity [K, H, W] of frames ``frames`` seen through ``rays`` (any camera, any
        resolution, e.g. a preview larger than the training images), under each frame's light."""
        rgbs, alphas = [], []
        for f, frame_rays in zip(frames, rays):
            geo = decode(self.model, t.guide_vertices[f:f + 1])
            lp = t.light_pos[f:f + 1] if light_pos is None else light_pos[None]
            b = t.bar[f:f + 1]
            # Bars never seen in training (held-out lights) have no learnt intensity: use 1.
            known = torch.as_tensor([int(x) in self.basis_index for x in b.tolist()], device=b.device)
            b_eff = torch.where(known, b, torch.full_like(b, -1))
            intensity = self.model.bar_intensity(b_eff)
            image = render(self.model, geo, frame_rays, self.lights(lp, b_eff, intensity),
                           basis=self.basis, kernel=self.kernel)
            rgbs.append(image.rgb)
            alphas.append(image.alpha)
        return torch.stack(rgbs), torch.stack(alphas)


def _atomic_save(obj: dict, path: Path) -> None:
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


class _BatchLoss(nn.Module):
    """The trainer's loss as a module's forward, so DistributedDataParallel can wrap it."""

    def __init__(self, trainer: "ModelTrainer") -> None:
        super().__init__()
        self.model = trainer.model  # the parameters DDP synchronises
        # A weak reference: the trainer owns the DDP wrapper, so a strong one back would make a
        # cycle that keeps DDP (and through it the process group) alive past
        # destroy_process_group, until a garbage collection or interpreter exit tears gloo down
        # in no particular order (a rank of the two-process test once aborted at exit in CI:
        # "terminate called without an active exception").
        self._losses = weakref.WeakMethod(trainer.losses)

    def forward(self, frames: torch.Tensor, cams: torch.Tensor, pix: torch.Tensor,
                eps: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
        losses = self._losses()
        if losses is None:
            raise RuntimeError("the trainer this DDP loss belongs to has been released")
        return losses(frames, cams, pix, eps)


class ModelTrainer:
    """Trains one model on the training frames; checkpoints under ``ckpt_path``."""

    def __init__(self, renderer: Renderer, tensors: TrainTensors, train_frames: np.ndarray, *, iterations: int,
                 batch_size: int, rays_per_image: int, lr: float, weights: LossWeights, seed: int,
                 ckpt_path: Path, checkpoint_every: int, spike_factor: float, log: logging.Logger,
                 curve_every: int = 0, curve_fn: Callable[[], float] | None = None, writer=None,
                 lr_decay_to: float = 1.0, rank: int = 0, world_size: int = 1,
                 prune: PruneSchedule | None = None, weight_average: float = 0.0,
                 image_order: ImageOrder = "random", lr_warmup_iterations: int = 0,
                 grad_clip_factor: float = 0.0) -> None:
        """``rank``/``world_size``: this process's place in an initialised process group (1 = no DDP).

        ``batch_size`` is the global batch; with DDP it must divide by ``world_size``.
        ``prune``: when to prune empty primitives (None = never).
        ``weight_average``: decay of an exponential moving average of the parameters, which
        replaces the last iterate at the end of ``run`` (0 = keep the last iterate).
        ``image_order``: how a batch's (frame, camera) images are drawn (``TrainParams.image_order``).
        ``lr_warmup_iterations``: the learning rate ramps linearly up to ``lr`` over this many
        first iterations (0 = none); see ``lr_at``.
        ``grad_clip_factor``: clip the gradient's norm (over all parameters) to this multiple of
        its running mean (0 = no clipping); see ``_clip_gradient``.
        """
        if batch_size % world_size:
            raise ValueError(f"batch_size {batch_size} does not divide by {world_size} processes")
        self.rank, self.world_size = rank, world_size
        self.r, self.t = renderer, tensors
        self.model = renderer.model
        self.train_frames = np.asarray(train_frames)
        self.iterations, self.batch_size, self.rays = iterations, batch_size, rays_per_image
        self.weights, self.ckpt_path, self.checkpoint_every = weights, ckpt_path, checkpoint_every
        self.model.lift_below_logit = OPACITY_FLOOR_LOGIT if weights.lift else None
        self.spike_factor, self.log = spike_factor, log
        self.lr_decay_to = lr_decay_to
        if lr_warmup_iterations < 0:
            raise ValueError(f"lr_warmup_iterations {lr_warmup_iterations} must be >= 0")
        self.lr_warmup_iterations = int(lr_warmup_iterations)
        if grad_clip_factor < 0 or 0 < grad_clip_factor <= 1:  # TrainParams checks it too; this is for direct callers
            raise ValueError(f"grad_clip_factor {grad_clip_factor} must be 0 (off) or above 1")
        self.grad_clip_factor = float(grad_clip_factor)
        self.curve_every, self.curve_fn, self.writer = curve_every, curve_fn, writer
        self.optim = torch.optim.Adam(self.model.parameters(), lr=lr)
        self.gen = torch.Generator(device="cpu")
        self.gen.manual_seed(seed)
        if image_order not in get_args(ImageOrder):  # TrainParams checks it too; this is for direct callers
            raise ValueError(f"image_order {image_order!r} must be one of {get_args(ImageOrder)}")
        self.image_order, self.order_seed = image_order, int(seed)
        self._epoch_orders: dict[int, torch.Tensor] = {}
        self.state = TrainState(lr=lr)
        self._good: dict | None = None
        self._ddp_loss: nn.Module | None = None
        self.prune = prune if prune is not None and 0 < prune.at_iteration <= iterations else None
        # [P] largest opacity each primitive added to a training ray in the pruning window.
        self.prim_alpha_max = torch.zeros(self.model.prim_keep.numel(), device=tensors.device)
        if not 0.0 <= weight_average < 1.0:
            raise ValueError(f"weight_average {weight_average} must be in [0, 1)")
        self.weight_average = weight_average
        #: The parameters' moving average (by name), or None when ``weight_average`` is 0.
        self.averaged: dict[str, torch.Tensor] | None = self._fresh_average() if weight_average else None
        #: Set by whoever runs this trainer beside others (``side_by_side.train_models``): when the
        #: event is set, ``run`` stops before its next iteration with ``TrainingStopped``.
        self.stop_event: threading.Event | None = None
        if world_size > 1:
            from torch.nn.parallel import DistributedDataParallel

            dev = tensors.device
            # Both kinds use every parameter in every training iteration (unseen bars'
            # intensities are rows of one indexed tensor), so DDP needs no unused-parameter search.
            self._ddp_loss = DistributedDataParallel(_BatchLoss(self), device_ids=[dev] if dev.type == "cuda" else None)

    # ---- weight averaging ----------------------------------------------------------------------
    def _fresh_average(self) -> dict[str, torch.Tensor]:
        return {name: p.detach().clone() for name, p in self.model.named_parameters()}

    def _update_average(self) -> None:
        """Move the average towards the parameters just stepped to.

        The decay ramps up as (1 + i) / (10 + i) to ``weight_average``, so the first
        iterations' weights (far from the optimum) leave the average quickly.
        """
        i = self.state.iteration
        keep = min(self.weight_average, (1.0 + i) / (10.0 + i))
        with torch.no_grad():
            for name, p in self.model.named_parameters():
                self.averaged[name].lerp_(p.detach(), 1.0 - keep)

    def use_average(self) -> None:
        """Load the averaged parameters into the model (a no-op without weight averaging)."""
        if self.averaged is None:
            return
        with torch.no_grad():
            for name, p in self.model.named_parameters():
                p.copy_(self.averaged[name])

    # ---- checkpoints -------------------------------------------------------------------------
    def _snapshot(self) -> dict:
        snap = {"model": self.model.state_dict(), "optim": self.optim.state_dict(),
                "rng": self.gen.get_state(), "state": json.dumps(self.state.__dict__),
                "prim_alpha_max": self.prim_alpha_max.detach().cpu().clone()}
        if self.averaged is not None:
            snap["averaged"] = self.averaged
        return snap

    def save_checkpoint(self) -> None:
        snap = self._snapshot()
        if self.rank == 0:  # every rank holds the same state; one writer
            _atomic_save(snap, self.ckpt_path)
        self._good = copy.deepcopy({"model": snap["model"], "optim": snap["optim"], "averaged": snap.get("averaged")})

    def try_resume(self) -> bool:
        """Load the checkpoint if there is one; a corrupt one is ignored with a warning."""
        if not self.ckpt_path.exists():
            return False
        try:
            snap = torch.load(self.ckpt_path, map_location="cpu", weights_only=True)
            self.model.load_state_dict(snap["model"])
            self.optim.load_state_dict(snap["optim"])
            self.gen.set_state(snap["rng"])
            self.state = TrainState(**json.loads(snap["state"]))
            if "prim_alpha_max" in snap:
                self.prim_alpha_max = snap["prim_alpha_max"].to(self.prim_alpha_max.device)
            if self.averaged is not None:
                # A checkpoint written without averaging starts the average at its weights.
                saved = snap.get("averaged")
                self.averaged = ({k: v.to(self.averaged[k].device) for k, v in saved.items()} if saved
                                 else self._fresh_average())
        except (OSError, RuntimeError, KeyError, ValueError, TypeError) as err:
            self.log.warning("%s: unreadable checkpoint (%s); starting this model from scratch", self.ckpt_path, err)
            return False
        self._set_lr(self.state.lr)
        self._good = copy.deepcopy({"model": self.model.state_dict(), "optim": self.optim.state_dict(),
                                    "averaged": self.averaged})
        self.log.info("%s: resumed at iteration %d", self.r.kind, self.state.iteration)
        return True

    def lr_at(self, iteration: int) -> float:
        """The learning rate of (0-based) ``iteration``.

        A linear warm-up, (iteration + 1) / ``lr_warmup_iterations`` of the rate, then the
        exponential decay from ``lr`` to ``lr * lr_decay_to`` over the run. A function of the
        iteration and the base rate alone (``state.lr``, halved by a rollback), so a resumed run
        follows the same schedule.
        """
        warm = min(1.0, (iteration + 1) / self.lr_warmup_iterations) if self.lr_warmup_iterations else 1.0
        return self.state.lr * warm * self.lr_decay_to ** (iteration / self.iterations)

    def _set_lr(self, lr: float) -> None:
        for group in self.optim.param_groups:
            group["lr"] = lr

    def _rollback(self, reason: str) -> None:
        self.state.rollbacks += 1
        self.state.lr *= 0.5
        self.log.warning("%s iteration %d: %s; rolled back to the last good checkpoint, lr -> %.3g",
                         self.r.kind, self.state.iteration, reason, self.state.lr)
        if self._good is not None:
            # Pruning only accumulates: a state saved before the scheduled pruning must not bring
            # the pruned primitives back.
            keep = self.model.prim_keep.clone()
            self.model.load_state_dict(self._good["model"])
            self.optim.load_state_dict(self._good["optim"])
            if self._good.get("averaged") is not None:
                self.averaged = copy.deepcopy(self._good["averaged"])
            self.model.prune(keep)
        self._set_lr(self.state.lr)

    # ---- one iteration -------------------------------------------------------------------------
    def epoch_order(self, epoch: int) -> torch.Tensor:
        """The permutation [F * C] of every (training frame, camera) image in ``epoch`` (``balanced`` order).

        Index q stands for frame ``train_frames[q // C]`` and camera ``q % C``. Drawn from its own
        generator seeded by (seed, epoch), so it follows from the iteration alone: a resumed or
        rolled-back run draws the same images without any state in the checkpoint.
        """
        if epoch not in self._epoch_orders:
            if len(self._epoch_orders) > 2:  # a batch spans at most two epochs: keep the few in use
                self._epoch_orders.pop(min(self._epoch_orders))
            g = torch.Generator(device="cpu")
            g.manual_seed(self.order_seed * 1_000_003 + epoch)
            self._epoch_orders[epoch] = torch.randperm(len(self.train_frames) * self.t.num_cameras, generator=g)
        return self._epoch_orders[epoch]

    def batch_images(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Frames [B] and cameras [B] of this iteration's batch.

        ``random``: each drawn uniformly with replacement. ``balanced``: the next B images of a
        shuffled pass over every training image, so that each is seen equally often (to one
        visit) however many iterations run.
        """
        t, g = self.t, self.gen
        if self.image_order == "random":
            pick = torch.randint(len(self.train_frames), (self.batch_size,), generator=g)
            return torch.as_tensor(self.train_frames)[pick], torch.randint(t.num_cameras, (self.batch_size,), generator=g)
        count = len(self.train_frames) * t.num_cameras
        start = self.state.iteration * self.batch_size
        picks = torch.stack([self.epoch_order(q // count)[q % count] for q in range(start, start + self.batch_size)])
        return torch.as_tensor(self.train_frames)[picks // t.num_cameras], picks % t.num_cameras

    def sample_batch(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Frames [B], cameras [B] and pixel indices [B, R], from the checkpointed generator."""
        t, g = self.t, self.gen
        frames, cams = self.batch_images()
        w = t.sampling_weights(frames, cams)  # [B, H*W]
        pix = torch.multinomial(w, self.rays, replacement=True, generator=g)  # [B, R]
        return frames, cams, pix

    def losses(self, frames: torch.Tensor, cams: torch.Tensor, pix: torch.Tensor,
               eps: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
        """Weighted loss and its terms for one batch."""
        t, model = self.t, self.model
        dev = t.device
        gt, matte = t.pixels(frames, cams, pix)  # [B, R, 3], [B, R]
        ro, rd = t.rays(frames, cams, pix)  # [B, R, 3] each
        frames, cams = frames.to(dev), cams.to(dev)
        target_verts = t.guide_vertices[frames]  # [B, U, 3]
        mu, logvar = model.encode(target_verts)
        z = mu + eps.to(dev) * torch.exp(0.5 * logvar)
        geo = model.decode_geometry(z)
        bar = t.bar[frames]
        rgb = self.r.rgb(geo, t.cam_pos[frames, cams], t.light_pos[frames], bar, model.bar_intensity(bar))
        record = self._recording()
        prims = geo.primitives(rgb)
        res = raymarch(prims, ro, rd, model.config.steps_per_ray, prim_stats=record, kernel=self.r.kernel)
        if record:
            self.prim_alpha_max = torch.maximum(self.prim_alpha_max, res.prim_alpha.amax(0))
        pho = F.mse_loss(res.rgb, gt)
        geo_loss = F.mse_loss(geo.guide_vertices, target_verts) / 1e-4  # cm^2
        vol = model.volume_prior(geo)
        kld = kl_divergence(mu, logvar)
        w = self.weights
        if w.mat_delta > 0:  # 0.5 e^2 / delta under delta, |e| - delta / 2 over it: the L1's pull, fading near 0
            mat = F.smooth_l1_loss(res.alpha, matte, beta=w.mat_delta)
        else:
            mat = (res.alpha - matte).abs().mean()
        total = w.pho * pho + w.geo * geo_loss + w.vol * vol + w.kld * kld + w.mat * mat
        terms = {}
        if w.floor > 0:
            floor = opacity_floor_penalty(geo.raw_alpha)
            total = total + w.floor * floor
            terms["floor"] = float(floor.detach())
        if w.reach > 0 and self.state.iteration < w.reach_until * self.iterations:
            foreground = matte >= 0.5
            reach, missed = reach_penalty(prims, ro, rd, foreground, res.alpha)
            total = total + w.reach * reach
            terms["reach"] = float(reach.detach())
            terms["missed"] = missed / max(int(foreground.sum()), 1)
        psnr = float(-10.0 * torch.log10(pho.detach().clamp(min=1e-12)))
        return total, {"loss": float(total.detach()), "pho": float(pho.detach()), "geo": float(geo_loss.detach()),
                       "vol": float(vol.detach()),
                       "kld": float(kld.detach()), "mat": float(mat.detach()), **terms, "psnr": psnr}

    # ---- pruning ---------------------------------------------------------------------------------
    def _recording(self) -> bool:
        """Whether this iteration's rays feed the pruning statistics (the window before pruning)."""
        return (self.prune is not None and not self.state.prune_done and self.model.kept_index() is None
                and self.prune.start <= self.state.iteration < self.prune.at_iteration)

    def prune_now(self) -> int:
        """Prune the primitives whose recorded opacity stayed below the threshold; returns how many."""
        stats = self.prim_alpha_max
        if self.world_size > 1:
            import torch.distributed as dist

            stats = stats.clone()
            if dist.get_backend() != "nccl":
                stats = stats.cpu()
            dist.all_reduce(stats, op=dist.ReduceOp.MAX)  # every rank prunes the same primitives
        keep = stats.to(self.model.prim_keep.device) >= self.prune.max_alpha
        pruned = self.model.prune(keep)
        self.state.pruned, self.state.prune_done = pruned, True
        self.log.info("%s iteration %d: pruned %d of %d primitives (max opacity added to any training ray "
                      "< %.3g over iterations %d-%d)", self.r.kind, self.state.iteration, pruned,
                      keep.numel(), self.prune.max_alpha, self.prune.start, self.prune.at_iteration)
        return pruned

    def _share(self) -> slice:
        """This rank's contiguous part of the global batch."""
        n = self.batch_size // self.world_size
        return slice(self.rank * n, (self.rank + 1) * n)

    def _mean_over_ranks(self, terms: dict[str, float]) -> dict[str, float]:
        """Loss terms of the global batch (every term is a batch mean and shares are equal)."""
        import torch.distributed as dist

        keys = [k for k in terms if k != "psnr"]
        values = torch.tensor([terms[k] for k in keys], dtype=torch.float64)
        if dist.get_backend() == "nccl":
            values = values.to(self.t.device)
        dist.all_reduce(values)
        out = dict(zip(keys, (values.cpu() / self.world_size).tolist()))
        out["psnr"] = -10.0 * math.log10(max(out["pho"], 1e-12)) if math.isfinite(out["pho"]) else float("nan")
        return out

    def step(self) -> dict[str, float]:
        frames, cams, pix = self.sample_batch()
        eps = torch.randn(self.batch_size, self.model.config.latent_dim, generator=self.gen)
        if self.world_size > 1:
            share = self._share()
            total, terms = self._ddp_loss(frames[share], cams[share], pix[share], eps[share])
            # DDP expects a backward after each forward; its all-reduce also keeps the ranks in step.
            self.optim.zero_grad(set_to_none=True)
            total.backward()
            terms = self._mean_over_ranks(terms)
        else:
            total, terms = self.losses(frames, cams, pix, eps)
        bad = not math.isfinite(terms["loss"])
        warm = self.state.iteration > WARM_UP_STEPS and math.isfinite(self.state.loss_ema)
        if not bad and warm and terms["loss"] > self.spike_factor * self.state.loss_ema:
            self._rollback(f"loss spike {terms['loss']:.4g} > {self.spike_factor} x running mean "
                           f"{self.state.loss_ema:.4g}")
            return terms
        if bad:
            self._rollback("loss is not finite")
            return terms
        if self.world_size == 1:
            self.optim.zero_grad(set_to_none=True)
            total.backward()
        grads_ok = all(p.grad is None or bool(torch.isfinite(p.grad).all()) for p in self.model.parameters())
        if not grads_ok:
            self._rollback("gradient is not finite")
            return terms
        terms["grad_norm"] = self._clip_gradient()
        self.optim.step()
        if self.averaged is not None:
            self._update_average()
        ema = self.state.loss_ema
        self.state.loss_ema = terms["loss"] if not math.isfinite(ema) else 0.95 * ema + 0.05 * terms["loss"]
        return terms

    def _clip_gradient(self) -> float:
        """Clip the gradient's norm to ``grad_clip_factor`` x its running mean; returns the norm before.

        The bound follows the norm's own level (an exponential mean over about 20 steps, of the
        norms after clipping, so one outlier does not lift it) rather than a fixed value, because
        the norm's scale differs between models and presets and drifts as training goes on, and no
        fixed value would fit them all. The first ``WARM_UP_STEPS`` steps only record, as the
        loss-spike rollback does. With DDP the gradients are already averaged over the ranks here,
        so every rank clips alike.
        """
        grads = [p.grad for p in self.model.parameters() if p.grad is not None]
        norm = float(torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in grads]))) \
            if grads else 0.0
        ema, kept = self.state.grad_norm_ema, norm
        if self.grad_clip_factor and self.state.iteration > WARM_UP_STEPS and math.isfinite(ema):
            bound = self.grad_clip_factor * ema
            if norm > bound:
                for g in grads:
                    g.mul_(bound / norm)
                self.state.clipped_steps += 1
                kept = bound
        self.state.grad_norm_ema = kept if not math.isfinite(ema) else 0.95 * ema + 0.05 * kept
        return norm

    # ---- the loop ------------------------------------------------------------------------------
    def run(self, progress) -> TrainState:
        """Train to ``iterations`` (resuming if a checkpoint exists); returns the final state."""
        self.try_resume()
        if self.state.iteration == 0 and self.curve_fn is not None:
            self.state.curve.append((0, 0.0, self.curve_fn()))
        progress.advance(self.state.iteration)
        while self.state.iteration < self.iterations:
            if self.stop_event is not None and self.stop_event.is_set():
                raise TrainingStopped(f"{self.r.kind}: stopped at iteration {self.state.iteration} "
                                      f"(last checkpoint at {self.ckpt_path})")
            tick = time.perf_counter()
            self.model.train()
            self._set_lr(self.lr_at(self.state.iteration))
            terms = self.step()
            self.state.iteration += 1
            self.state.train_seconds += time.perf_counter() - tick
            it = self.state.iteration
            if self.writer is not None and it % 10 == 0:
                for key, value in terms.items():
                    self.writer.add_scalar(f"{self.r.kind}/{key}", value, it)
            if self.curve_fn is not None and self.curve_every and it % self.curve_every == 0:
                self.model.eval()
                value = self.curve_fn()
                self.state.curve.append((it, self.state.train_seconds, value))
                if self.writer is not None:
                    self.writer.add_scalar(f"{self.r.kind}/val_light_psnr", value, it)
            if self.prune is not None and not self.state.prune_done and it >= self.prune.at_iteration:
                self.prune_now()
            if it % self.checkpoint_every == 0 or it == self.iterations:
                self.save_checkpoint()
            progress.advance(1, model=self.r.kind, loss=terms["loss"], psnr=terms["psnr"],
                             it_per_s=it / max(self.state.train_seconds, 1e-9))
        # The checkpoint keeps the last iterate and the average apart, so a resumed run (even one
        # resumed after its last iteration) ends with the same averaged model.
        self.use_average()
        self.model.eval()
        return self.state
