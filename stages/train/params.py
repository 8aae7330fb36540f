"""The train stage's params: the model, its capacity rule, the run length and the validation and test splits."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator

from avatar.capacity import CapacityRule
from avatar.config import AvatarConfig
from avatar.raymarch import RaymarchKernel
from pipeline.devices import DeviceChoice
from pipeline.stage import StageParams
from stages.train.splits import ValidationSplit
from stages.train.trainer import ImageOrder, LossWeights, Pruning


class TrainParams(StageParams):
    """Parameters of the train stage (defaults: the tiny, CPU-sized run)."""

    avatar: AvatarConfig = Field(default_factory=AvatarConfig.tiny,
                                 description="Model sizes (N, M, latent, channels, raymarch steps); see avatar.config. "
                                 "With capacity 'auto' the rule replaces N, M, the channel widths, the steps and the "
                                 "latent size.")
    capacity: Literal["auto", "fixed"] = Field(
        "fixed", description="'auto': primitives, voxels per primitive, channel widths, raymarch steps and latent "
        "size chosen from the capture (training image size, the head's footprint in the mattes, training frames, "
        "expression modes of the training meshes) by avatar.capacity; 'fixed': the avatar section as given.")
    capacity_rule: CapacityRule = Field(default_factory=CapacityRule,
                                        description="Constants of the capacity rule (capacity 'auto').")
    pruning: Pruning = Field(default_factory=Pruning,
                             description="When and how empty primitives are pruned; see stages.train.trainer.Pruning.")
    image_width_px: int = Field(64, ge=0, description="Training/evaluation image width in pixels (0 = the capture's).")
    max_frames: int = Field(0, ge=0, description="Use at most this many OLAT frames, evenly spread (0 = all).")
    resident_limit_gb: float = Field(8.0, ge=0, description="Training images and mattes larger than this (GB, "
                                     "float32) are memory-mapped from the stage's cache folder and gathered per "
                                     "batch instead of being held in RAM or on the GPU.")
    iterations: int = Field(2000, ge=1, description="Training iterations of our model.")
    baseline: bool = Field(True, description="Also train the TRAvatar* baseline on the same data.")
    baseline_iterations: int = Field(0, ge=0, description="Training iterations of TRAvatar* (0 = same as ours).")
    baseline_latent_per_mode: float | None = Field(
        None, ge=0, description="TRAvatar*'s latent size per expression mode under `capacity: auto` (None = "
        "capacity_rule.latent_per_mode, the same code size as ours). Set it where the two models are best at "
        "different sizes, so that the baseline stays trained as well as it can be; ignored with `capacity: "
        "fixed` or meshes that never move.")
    encoder_input: Literal["offsets", "expression_modes"] = Field(
        "offsets", description="What both models' encoders read of a tracked mesh. 'offsets': the guide vertices' "
        "whole offsets from the training mean (the paper). 'expression_modes': only their part along the expression "
        "modes the capacity rule counts (capacity_rule.expression_variance of the training meshes' spread), so the "
        "directions the training meshes move along only by the tracker's jitter do not reach the code. Needs meshes "
        "that move (it falls back to 'offsets', with a log line, where they do not).")
    batch_size: int = Field(4, ge=1, description="Images per iteration (the paper: 12).")
    rays_per_image: int = Field(256, ge=1, description="Rays sampled per image per iteration (foreground-weighted).")
    lr: float = Field(1e-3, gt=0, description="Adam learning rate (the paper: 1e-4).")
    lr_decay_to: float = Field(0.1, gt=0, le=1, description="Final learning rate as a fraction of lr "
                               "(exponential decay over the run; 1 = constant, as the paper). Lower it only with "
                               "more iterations: on tiny, 0.01 cost ours 0.6-1.1 dB on validation and on the "
                               "training images, which it still fits at the end (docs/experiments.md, section 23).")
    lr_warmup_iterations: int = Field(
        0, ge=0, description="Iterations over which the learning rate ramps linearly from lr / this up to lr, "
        "before the decay takes over (0 = none, as the paper). Both models alike. Leave it at 0 unless you are "
        "experimenting: on tiny, 500 neither narrowed ours' spread over seeds nor raised its validation PSNR "
        "(docs/experiments.md, section 22).")
    grad_clip_factor: float = Field(
        0.0, ge=0, description="Clip the gradient's norm (over all of a model's parameters) to this multiple of "
        "its running mean before each optimiser step (0 = no clipping, as the paper; otherwise above 1). Both "
        "models alike; each model's metrics count its clipped steps (`{model}_clipped_steps`). Leave it at 0 unless "
        "you are experimenting: on tiny, 2 clipped under 1% of the steps, left ours' validation PSNR unchanged and "
        "narrowed its spread over seeds on one validation split of two (docs/experiments.md, section 26).")
    weight_average: float = Field(0.0, ge=0, lt=1, description="Decay per iteration of an exponential moving "
                                  "average of the weights, evaluated and saved instead of the last iterate (0 = "
                                  "the last iterate, as the paper; 0.998 averages over roughly the last 500 "
                                  "iterations). Both models alike. Set it where training is short and noisy: "
                                  "the tiny preset uses 0.998, which raised ours' validation PSNR on every seed on "
                                  "alice (+0.17 dB) and left bob's unchanged, without narrowing the spread over seeds "
                                  "(docs/experiments.md, section 29). For long runs at the paper's learning rate, 0 "
                                  "keeps the paper's model.")
    image_order: ImageOrder = Field(
        "random", description="How each batch's (frame, camera) images are drawn: 'random', uniformly with "
        "replacement (as before); 'balanced', the next images of a shuffled pass over every training image, so "
        "each is seen equally often. The ray sampling within an image is the same either way. Both models alike. "
        "Leave it at 'random' unless you are experimenting: on tiny, 'balanced' left ours' validation PSNR where it "
        "was on alice and on bob, and narrowed its spread over 5 seeds on alice's validation but widened it on bob's; "
        "TRAvatar* gained on bob, not yet measured on alice (docs/experiments.md, sections 27 and 28).")
    loss_weights: LossWeights = Field(default_factory=LossWeights,
                                      description="Weights of the loss terms (photometric, guide mesh, volume, KL, "
                                      "matte); see stages.train.trainer.LossWeights.")
    held_out_bars: int = Field(3, ge=1, description="Interior bars held out for the novel-light test split.")
    held_out_take: str = Field("", description="Take whose final segment is the novel-performance test split ('' = "
                               "the last take).")
    held_out_fraction: float = Field(0.5, gt=0, le=1, description="Final fraction of that take held out for the "
                                     "test (1 = all of it).")
    validation: ValidationSplit = Field(default_factory=ValidationSplit,
                                        description="The validation split's own held-out bars and frames, disjoint "
                                        "from the test's; the learning curve and the pruning figures are measured "
                                        "on it. See stages.train.splits.ValidationSplit.")
    fit_frames: int = Field(0, ge=0, description="Diagnostic: optimise on only the first K training frames (all "
                            "their cameras; 0 = every training frame). With 1 it measures how well the model's "
                            "capacity can fit one frame in the iteration budget (train_psnr), an upper bound for "
                            "the held-out figures; the layout, light basis and capacity still come from every "
                            "training frame.")
    eval_images: int = Field(12, ge=1, description="Held-out images rendered per split for the metrics.")
    assess_width_px: int = Field(0, ge=0, description="Width of the images the metrics, the learning curve, the "
                                 "pruning figures and the previews are measured on (0 = the training images'). A "
                                 "whole fraction of the training width: each pixel averages a block of training "
                                 "pixels, rays and targets alike (stages.train.assess_images). Set it only to "
                                 "assess a large preset on a CPU (make smoke-paper); figures at another width are "
                                 "not comparable with the training width's.")
    figure_height_px: int = Field(0, ge=0, description="Height of the comparison figures' images (0 = the "
                                  "capture's own size, the most detail). Lower it where rendering at the capture's "
                                  "size is too slow (a 768 x 1024 capture on a CPU); the ground truth is "
                                  "area-averaged to the same size.")
    lpips: bool = Field(True, description="Compute LPIPS (AlexNet weights from assets/lpips).")
    curve_every: int = Field(100, ge=0, description="Iterations between learning-curve points (0 = none).")
    curve_images: int = Field(3, ge=1, description="Validation-light images per learning-curve point.")
    checkpoint_every: int = Field(50, ge=1, description="Iterations between checkpoints (resume after a kill).")
    spike_factor: float = Field(10.0, gt=1, description="A loss above this multiple of its running mean rolls back.")
    seed: int = Field(0, description="Seed of initialisation and sampling.")
    init_seed: int | None = Field(None, description="Seed of the models' initial weights alone (None = seed). With "
                                  "sampling_seed it separates the two sources of the spread over seeds: vary one, "
                                  "hold the other (benchmarks/bench_seeds.py).")
    sampling_seed: int | None = Field(None, description="Seed of the ray sampling and the latent code's noise alone "
                                      "(None = seed); see init_seed.")
    threads: int = Field(0, ge=0, description="torch CPU threads (0 = torch's default).")
    device: DeviceChoice = Field("auto", description="'auto' (CUDA if present), 'cpu' or 'cuda'.")
    raymarch_kernel: RaymarchKernel = Field(
        "auto", description="'fused': the C++ CPU raymarcher (avatar.raymarch_fused, built on first use, needs a C++ "
        "compiler; several times the training iterations/s of 'torch' on the CPU, docs/experiments.md, section 4); "
        "'torch': tensor ops (CPU or GPU); 'auto': fused on the CPU where a C++ compiler builds it, else torch with "
        "a warning. The same images either way, up to float rounding. Set 'fused' to fail instead of falling back.")
    previews: int = Field(2, ge=0, description="Preview images written per split.")
    parallel_models: int = Field(1, ge=1, description="Models (ours, TRAvatar*) trained at the same time, each in its "
                                 "own thread of this process: 2 trains both side by side, in about the time of one "
                                 "on a CPU with threads: 1 (stages.train.side_by_side); the same numbers as 1, which "
                                 "trains them one after another. Needs processes: 1.")
    processes: int = Field(1, ge=1, description="Data-parallel training processes (torch.distributed DDP, launched "
                           "with torchrun; gloo on CPU, nccl with one GPU per process). batch_size is the global "
                           "batch and must divide by it; 1 = train in the stage's own process.")

    @field_validator("grad_clip_factor")
    @classmethod
    def _clip_above_one(cls, value: float) -> float:
        # A bound at or under the running mean would clip nearly every step: that is a smaller
        # learning rate in disguise, not a guard against outliers.
        if 0 < value <= 1:
            raise ValueError(f"train.grad_clip_factor {value} must be 0 (off) or above 1, e.g. 2")
        return value
