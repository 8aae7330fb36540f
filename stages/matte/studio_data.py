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
from stages.matte.conditions import IdentityConditions, TrainingConditions, film
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
    conditions: TrainingConditions = Field(
        default_factory=TrainingConditions,
        description="The training studio's own backdrop, exposure, lens blur and sensor noise, drawn per identity "
        "so that the network crosses a domain gap to the subject's capture (stages.matte.conditions). "
        "TrainingConditions.same_as_capture() removes the gap, for studies of it.")


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
    from hardware.studio import (
        RenderSettings,
        VirtualStudio,
        make_performance,
        make_subject,
    )
    from scene.rig import default_rig

    config = job.config
    # The subject's own studio: its cameras frame the training heads as the capture's frame the subject.
    rig = job.rig if job.rig is not None else default_rig()
    cameras = rig.cameras_at(job.image_scale)
    rng = np.random.default_rng([config.render_seed, job.identity_seed])
    subject = make_subject(f"matte-train-{job.identity_seed}", seed=job.identity_seed)
    frames = make_performance(seed=job.identity_seed + config.performance_seed_offset,
                              frames_per_take=config.frames_per_take)
    studio_default = RenderSettings(seed=config.render_seed + job.identity_seed)
    conditions = IdentityConditions.draw(config.conditions,
                                         np.random.default_rng([config.render_seed, job.identity_seed, 31]))
    studio = VirtualStudio(rig, subject, RenderSettings(
        seed=studio_default.seed, bar_intensity_scale=studio_default.bar_intensity_scale * conditions.exposure_scale))
    # Noise levels scale as sigmas: the shot-noise variance per unit of signal by the factor squared.
    shot_gain = studio_default.shot_noise_gain * conditions.sensor_noise_scale ** 2
    read_noise = studio_default.read_noise * conditions.sensor_noise_scale
    sensor_rng = np.random.default_rng([config.render_seed, job.identity_seed, 37])
    blur_px = conditions.lens_blur_sigma_px * job.image_scale  # given at the capture's reference size

    def filmed(render, backdrop: float) -> tuple[np.ndarray, np.ndarray]:
        return film(render.rgb, render.alpha, backdrop, blur_px, shot_gain, read_noise, sensor_rng)

    bar_count = len(rig.light_bars())
    samples: list[Sample] = []
    full_on_levels: list[float] = []
    for _ in range(config.frame_pairs_per_identity):
        t = int(rng.integers(1, len(frames) - 1))
        guide_t = t + (1 if rng.uniform() < 0.5 else -1)
        chosen = rng.choice(len(cameras), size=min(config.cameras_per_frame, len(cameras)), replace=False)
        targets = []
        for cam_index in chosen:  # frame t first, so its geometry is built once
            is_olat = bool(rng.uniform() < config.olat_fraction)
            light = int(rng.integers(bar_count)) if is_olat else "F"
            targets.append((cam_index, is_olat, studio.render(frames[t], cameras[cam_index], light, noise=False)))
        for cam_index, is_olat, target in targets:
            full_on = studio.render(frames[guide_t], cameras[cam_index], "F", noise=False) if is_olat else target
            # The backdrop is lit like the head: at the drawn fraction of this F frame's skin level,
            # and by one bar's share of it under one bar.
            backdrop_full_on = conditions.backdrop_level * _skin_level(full_on.rgb, full_on.alpha)
            full_on_levels.append(backdrop_full_on)
            if is_olat:
                guide, _ = filmed(full_on, backdrop_full_on)
                image, alpha = filmed(target, backdrop_full_on / bar_count)
                samples.append(Sample(image, guide, alpha, True))
            else:
                image, alpha = filmed(target, backdrop_full_on)
                samples.append(Sample(image, image, alpha, False))
    # At least one per identity when asked for: an empty studio must be seen in training, or
    # the instance-normalised half of IBNorm stretches pure sensor noise into false contrast.
    empty_count = int(round(config.empty_fraction * len(samples)))
    if config.empty_fraction > 0:
        empty_count = max(empty_count, 1)
    backdrop = float(np.mean(full_on_levels)) if full_on_levels else 0.0
    for _ in range(empty_count):
        shape = (cameras[0].height, cameras[0].width)
        # The training studio's sensor on its backdrop alone, clipped at 0 like its renders.
        empty = np.zeros(shape + (3,), np.float32)
        is_olat = bool(rng.uniform() < 0.5)
        guide, _ = film(empty, np.zeros(shape, np.float32), backdrop, 0.0, shot_gain, read_noise, sensor_rng)
        image, _ = film(empty, np.zeros(shape, np.float32), backdrop / bar_count if is_olat else backdrop, 0.0,
                        shot_gain, read_noise, sensor_rng)
        samples.append(Sample(image, guide, np.zeros(shape, np.float32), is_olat))
    return samples


def _skin_level(rgb: np.ndarray, alpha: np.ndarray) -> float:
    """The 99th percentile of a render's foreground luminance (0 when no pixel is foreground)."""
    foreground = rgb.mean(-1)[alpha > 0.5]
    return float(np.percentile(foreground, 99)) if foreground.size else 0.0


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
