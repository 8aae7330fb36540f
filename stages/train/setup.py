"""The training problem made from the loaded data: splits, exposure, capacity, layout and tensors.

``prepare_training`` is pure over the data and the params (it reads and writes no files): the
stage, the DDP worker and the benches build the same setup from the same data.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np
import torch

from avatar.capacity import Capacity, CapacityInputError, CaptureStats, choose_capacity, count_expression_modes, \
    footprint_from_mattes
from avatar.config import AvatarConfig
from avatar.layout import GuideLayout, expression_basis, layout_for
from avatar.travatar import LightBasis
from pipeline.errors import ConfigError, InputError
from stages.train.assess_images import AssessImages, assess_factor
from stages.train.data import TrainData
from stages.train.evaluate import eval_pairs
from stages.train.params import TrainParams
from stages.train.splits import ALL_SPLITS, HELD_OUT_SPLITS, Splits, make_splits
from stages.train.trainer import TrainTensors


@dataclass
class TrainingSetup:
    """What both models train and are evaluated on.

    Attributes:
        splits: the validation and test bars / segments and every frame's split.
        train_frames: indices of the training frames; ``fitted_frames`` the ones optimised on
            (all of them unless ``fit_frames`` is set).
        image_scale: the exposure every image was multiplied by (``exposure_of``).
        bar_dirs: each lit bar's mean head-space direction.
        capacity: the capacity rule's inputs and choice; ``avatar`` the configuration used.
        layout: the primitives' layout on the training frames' mean mesh.
        tensors: the training data as tensors on the training device.
        basis_bars: the bars lit in training frames (TRAvatar*'s light basis, in this order).
        basis: TRAvatar*'s light basis over ``basis_bars``.
        num_cams: cameras per frame.
        pairs: the (frame, camera) pairs evaluated per held-out split (``HELD_OUT_SPLITS``).
        curve_pairs: the validation-light pairs of every learning-curve point (never a test split's).
        assess: the images the metrics, the learning curve and the previews are measured on
            (``train.assess_width_px``).
    """

    splits: Splits
    train_frames: np.ndarray
    fitted_frames: np.ndarray
    image_scale: float
    bar_dirs: dict[int, np.ndarray]
    capacity: Capacity
    avatar: AvatarConfig
    layout: GuideLayout
    tensors: TrainTensors
    basis_bars: list[int]
    basis: LightBasis
    num_cams: int
    pairs: dict[str, list[tuple[int, int]]]
    curve_pairs: list[tuple[int, int]]
    assess: AssessImages


def prepare_training(data: TrainData, params: TrainParams, device: torch.device,
                     log: logging.Logger) -> TrainingSetup:
    """The setup of a run; scales ``data.images`` by the exposure in place (a spilled array on disk)."""
    bar_dirs = bar_directions(data)
    splits = make_splits(data.take, data.bar, bar_dirs, params.held_out_bars, params.held_out_take,
                         params.held_out_fraction, params.validation)
    train_frames = np.flatnonzero(splits.train)
    if len(train_frames) == 0:
        raise InputError("train: no training frames left after holding out test bars "
                         f"{splits.held_out_bars} and take '{splits.held_out_take}', validation bars "
                         f"{splits.val_bars} and frames '{splits.val_segment}'; capture more OLAT frames")
    image_scale = exposure_of(data, train_frames)
    data.images *= image_scale  # in place (a spilled array is rescaled on disk, page by page)
    log.info("splits: %s (validation bars %s, frames %s; test bars %s, frames %s)",
             {k: int(splits.mask(k).sum()) for k in ALL_SPLITS}, list(splits.val_bars), splits.val_segment,
             list(splits.held_out_bars), splits.held_out_take)
    capacity = capacity_of(data, train_frames, params)
    avatar = capacity.config if params.capacity == "auto" else params.avatar
    log.info("capacity (%s): %d primitives (N=%d) of %d^3 voxels, width %d, %d steps, latent %d; rule inputs: "
             "%dx%d px, head %.1f px wide, %d training frames, %d expression modes", params.capacity,
             avatar.num_prims, avatar.prims_per_side, avatar.voxels_per_side, avatar.base_channels,
             avatar.steps_per_ray, avatar.latent_dim, capacity.stats.image_width_px,
             capacity.stats.image_height_px, capacity.stats.footprint_px, capacity.stats.frames,
             capacity.stats.expression_modes)
    mean_mesh = data.vertices[train_frames].mean(0)
    layout = with_encoder_input(layout_for(avatar, mean_mesh, data.triangles), data.vertices[train_frames],
                                params.encoder_input, capacity.stats.expression_modes, log)
    tensors = training_tensors(data, layout.guide_vertex_ids, device)
    assess = AssessImages(tensors, assess_factor(tensors.width, tensors.height, params.assess_width_px))
    basis_bars = sorted(int(b) for b in np.unique(data.bar[train_frames]))
    fitted_frames = train_frames[:params.fit_frames] if params.fit_frames else train_frames
    basis = LightBasis(np.stack([bar_dirs[b] for b in basis_bars]))
    num_cams = len(data.camera_names)
    pairs = {s: eval_pairs(np.flatnonzero(splits.mask(s)), num_cams, params.eval_images) for s in HELD_OUT_SPLITS}
    return TrainingSetup(splits=splits, train_frames=train_frames, fitted_frames=fitted_frames,
                         image_scale=image_scale, bar_dirs=bar_dirs, capacity=capacity, avatar=avatar,
                         layout=layout, tensors=tensors, basis_bars=basis_bars, basis=basis, num_cams=num_cams,
                         pairs=pairs, curve_pairs=pairs["val_light"][:params.curve_images], assess=assess)


def with_encoder_input(layout: GuideLayout, train_vertices: np.ndarray, encoder_input: str, modes: int,
                       log: logging.Logger) -> GuideLayout:
    """``layout`` with the expression basis that ``train.encoder_input`` asks for (none for 'offsets').

    ``modes`` is the capacity rule's count of expression modes in ``train_vertices`` [F, V, 3],
    so the encoder reads the same modes the latent size is sized by.
    """
    if encoder_input == "offsets":
        return layout
    if modes < 1:
        log.info("encoder input: the training meshes do not move; the encoder reads the whole offsets")
        return layout
    offsets = train_vertices[:, layout.guide_vertex_ids] - layout.mean_guide_vertices[None]
    try:
        basis = expression_basis(offsets, modes)
    except ValueError as err:  # a guide mesh too sparse to hold the modes the full meshes have
        raise InputError(f"train.encoder_input 'expression_modes': the {len(layout.guide_vertex_ids)} guide vertices "
                         f"do not span the {modes} expression modes counted on the full tracked meshes ({err}); "
                         "set train.encoder_input: offsets or lower capacity_rule.expression_variance") from err
    log.info("encoder input: the guide offsets' part along the %d expression modes", modes)
    return dataclasses.replace(layout, expression_basis=basis)


def training_tensors(data: TrainData, guide_ids: np.ndarray, device: torch.device) -> TrainTensors:
    """The training tensors; spilled (memory-mapped) images and mattes stay on the CPU and are gathered per batch."""
    f, c, h, w = data.mattes.shape

    def dev(x: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(x)).to(device)

    if data.spilled:
        images = torch.from_numpy(data.images.reshape(f, c, h * w, 3))  # no copy: pages read on demand
        mattes = torch.from_numpy(data.mattes.reshape(f, c, h * w))
    else:
        images, mattes = dev(data.images.reshape(f, c, h * w, 3)), dev(data.mattes.reshape(f, c, h * w))
    return TrainTensors(
        images=images, mattes=mattes, pixel_dirs=dev(data.pixel_dirs_cam), head_from_cam=dev(data.head_from_cam_rot),
        cam_pos=dev(data.cam_pos_head), light_pos=dev(data.light_pos_head), bar=dev(data.bar.astype(np.int64)),
        guide_vertices=dev(data.vertices[:, guide_ids]), height=h, width=w, device=device)


def _statistics_frames(train_frames: np.ndarray, limit: int = 64) -> np.ndarray:
    """At most ``limit`` training frames, evenly spread, for image statistics (all of them on small captures)."""
    if len(train_frames) <= limit:
        return train_frames
    return train_frames[np.linspace(0, len(train_frames) - 1, limit).round().astype(int)]


def _foreground_percentile(data: TrainData, frames: np.ndarray, q: float) -> float:
    """The ``q``-th percentile of the foreground (matte > 0.5) pixel values of ``frames``, one frame in memory at a time."""
    values = [np.asarray(data.images[i])[np.asarray(data.mattes[i]) > 0.5] for i in frames]
    foreground = np.concatenate(values) if values else np.zeros(0, np.float32)
    return float(np.percentile(foreground, q)) if foreground.size else 1.0


def bar_directions(data: TrainData) -> dict[int, np.ndarray]:
    """Each lit bar's mean head-space direction over its frames (the splits' and TRAvatar*'s light directions)."""
    dirs = {}
    for b in np.unique(data.bar):
        d = data.light_pos_head[data.bar == b]
        dirs[int(b)] = (d / np.linalg.norm(d, axis=-1, keepdims=True)).mean(0)
    return dirs


def exposure_of(data: TrainData, train_frames: np.ndarray) -> float:
    """The factor every image is scaled by: the 99.5th percentile of training foreground pixels goes to 1.

    OLAT images are dark (a single bar): scaled, losses are in a sane range and PSNR's peak (1)
    is the subject's brightest pixels, not an arbitrary unit.
    """
    return 1.0 / max(_foreground_percentile(data, _statistics_frames(train_frames), 99.5), 1e-12)


def capacity_of(data: TrainData, train_frames: np.ndarray, params: TrainParams) -> Capacity:
    """The capacity rule applied to the training data (training resolution, training frames' mattes)."""
    _, _, height, width = data.mattes.shape
    modes = count_expression_modes(data.vertices[train_frames], params.capacity_rule.expression_variance)
    stats = CaptureStats(image_width_px=int(width), image_height_px=int(height),
                         footprint_px=footprint_from_mattes(data.mattes[_statistics_frames(train_frames)]),
                         frames=int(len(train_frames)), expression_modes=modes)
    try:
        return choose_capacity(stats, params.capacity_rule, params.avatar)
    except CapacityInputError as err:
        if params.capacity == "fixed":
            # The rule only reports in this mode; a capture it cannot read must not stop training.
            avatar = params.avatar
            return Capacity(config=avatar, stats=stats, texels_per_side=avatar.prims_per_side * avatar.voxels_per_side,
                            texel_px=float("nan"), voxel_px=float("nan"), layout_span_px=float("nan"),
                            width=avatar.base_channels)
        raise ConfigError(f"train.capacity=auto: {err}") from err
