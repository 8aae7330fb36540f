"""Matting training frames rendered by the virtual studio, for subjects other than the target.

Each sample is what the matte stage sees at run time: a target frame t (OLAT, one bar, or
F) from one camera with its exact alpha, and the F frame of frame t-1 or t+1 of the same
camera as its guide (the head has moved by 1/24 s). Identities and performances come from
their own seeds (``identity_seeds``, default 1000 and up, far from subjects' seeds), so
the model never sees the person it mattes. Rendering shares each frame's geometry across
several cameras, and identities are rendered in parallel through the stage's executor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from scene.rig import RigConfig

from stages.matte.training import TrainingSet


class StudioDataConfig(BaseModel):
    """Which studio renders make up the matting training set."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    identity_seeds: tuple[int, ...] = Field((1001, 1002, 1003, 1004), description="Identity seeds of the training subjects (never a subject's own seed).")
    performance_seed_offset: int = Field(500, description="Each training subject performs the performance of seed identity_seed + this offset.")
    frames_per_take: int = Field(48, ge=4, description="Frames per take of each training performance.")
    frame_pairs_per_identity: int = Field(10, ge=1, description="Frames (each with a neighbouring F guide frame) drawn per identity.")
    cameras_per_frame: int = Field(3, ge=1, description="Cameras rendered per drawn frame (they share the frame's geometry).")
    olat_fraction: float = Field(0.7, ge=0, le=1, description="Fraction of samples whose target is an OLAT frame (the rest are F).")
    empty_fraction: float = Field(0.15, ge=0, le=1, description="Fraction of extra samples with no person (backdrop and sensor noise only).")
    render_seed: int = Field(7, description="Seed of frame, camera and bar choice and of the studio's sensor noise.")


@dataclass(frozen=True)
class IdentityJob:
    """The renders of one training identity (a picklable unit of work for the executor)."""

    identity_seed: int
    config: StudioDataConfig
    image_scale: float
    rig: RigConfig | None = None  # the studio filmed in (the subject's rig); None: configs/rig.yaml


@dataclass(frozen=True)
class Sample:
    """One rendered training sample."""

    image: np.ndarray  # [H, W, 3] linear
    guide: np.ndarray  # [H, W, 3] linear
    alpha: np.ndarray  # [H, W]
    is_olat: bool


def render_identity(job: IdentityJob) -> list[Sample]:
    """Render one identity's samples (top-level so a process pool can run it)."""
    from hardware.studio import RenderSettings, VirtualStudio, make_performance, make_subject
    from scene.rig import default_rig

    config = job.config
    # The subject's own studio: its cameras frame the training heads as the capture's frame the subject.
    rig = job.rig if job.rig is not None else default_rig()
    cameras = rig.cameras_at(job.image_scale)
    rng = np.random.default_rng([config.render_seed, job.identity_seed])
    subject = make_subject(f"matte-train-{job.identity_seed}", seed=job.identity_seed)
    frames = make_performance(seed=job.identity_seed + config.performance_seed_offset,
                              frames_per_take=config.frames_per_take)
    studio = VirtualStudio(rig, subject, RenderSettings(seed=config.render_seed + job.identity_seed))
    bar_count = len(rig.light_bars())
    samples: list[Sample] = []
    for _ in range(config.frame_pairs_per_identity):
        t = int(rng.integers(1, len(frames) - 1))
        guide_t = t + (1 if rng.uniform() < 0.5 else -1)
        chosen = rng.choice(len(cameras), size=min(config.cameras_per_frame, len(cameras)), replace=False)
        targets = []
        for cam_index in chosen:  # frame t first, so its geometry is built once
            is_olat = bool(rng.uniform() < config.olat_fraction)
            light = int(rng.integers(bar_count)) if is_olat else "F"
            targets.append((cam_index, is_olat, studio.render(frames[t], cameras[cam_index], light)))
        for cam_index, is_olat, target in targets:
            if is_olat:
                guide = studio.render(frames[guide_t], cameras[cam_index], "F").rgb
                samples.append(Sample(target.rgb, guide, target.alpha, True))
            else:
                samples.append(Sample(target.rgb, target.rgb, target.alpha, False))
    # At least one per identity when asked for: an empty studio must be seen in training, or
    # the instance-normalised half of IBNorm stretches pure sensor noise into false contrast.
    empty_count = int(round(config.empty_fraction * len(samples)))
    if config.empty_fraction > 0:
        empty_count = max(empty_count, 1)
    settings = studio.settings
    for _ in range(empty_count):
        shape = (cameras[0].height, cameras[0].width, 3)
        # The studio's sensor on a black backdrop: read noise only, clipped at 0 like its renders.
        noise = np.maximum(rng.normal(0.0, settings.read_noise, shape), 0.0).astype(np.float32)
        guide = np.maximum(rng.normal(0.0, settings.read_noise, shape), 0.0).astype(np.float32)
        samples.append(Sample(noise, guide, np.zeros(shape[:2], np.float32), bool(rng.uniform() < 0.5)))
    return samples


def identity_jobs(config: StudioDataConfig, image_scale: float, rig: RigConfig | None = None) -> list[IdentityJob]:
    """One job per training identity, filmed with ``rig`` (None: configs/rig.yaml)."""
    return [IdentityJob(seed, config, image_scale, rig) for seed in config.identity_seeds]


def collect(sample_lists: list[list[Sample]]) -> TrainingSet:
    """A training set from the identities' samples."""
    train_set = TrainingSet()
    for samples in sample_lists:
        for sample in samples:
            train_set.add(sample.image, sample.guide, sample.alpha, sample.is_olat)
    return train_set.finish()
