"""The capacity a capture needs: primitives, voxels, channel widths, raymarch steps and latent size.

The model's resolution on the head is the decoder's UV image: N*M texels per side, N
primitives of M voxels each, laid over the head's outer surface (``avatar.layout``: a
latitude-longitude grid over +-theta of azimuth). Along a row the layout spans an arc of
``2 theta R`` around a head whose width in the images is ``2 R`` pixels, i.e.
``theta * footprint_px`` pixels, so one UV texel covers::

    texel_px = theta * footprint_px / (N * M)

pixels of the images, and a voxel projects to ``voxel_px = prim_overlap * texel_px``.

The rule (``choose_capacity``, constants in ``CapacityRule``):

- N*M is the largest power of two whose texels stay at least ``min_texel_px`` pixels wide:
  texels much finer than a pixel are capacity the images cannot supervise. It is split into N
  primitives of M voxels with N = 2^k M (``prims_over_voxels_log2``; the paper's N = 4 M).
- Raymarch steps: about one sample per texel across the head (N*M / theta, rounded to a power
  of two within ``[min_steps, max_steps]``).
- Decoder width: ``width_per_cbrt_frame`` times the cube root of the number of training
  frames, within bounds: more frames hold more appearance variation and get more channels;
  few frames get a narrow decoder that cannot memorise them.
- Latent size: ``latent_per_mode`` dimensions per expression mode of the (head-space) training
  meshes (``count_expression_modes``: the principal components that hold
  ``expression_variance`` of their variance about the mean), rounded up to a power of two
  within ``[min_latent, max_latent]``.

``choose_capacity`` is pure (numbers in, an ``AvatarConfig`` out); ``footprint_from_mattes``
measures the footprint from the training mattes; ``find_knee`` locates the knee of a measured
capacity curve (Kneedle, Satopaa et al. 2011), which ``benchmarks/bench_capacity.py`` uses to
check that the rule's default sits at the knee. How the defaults were chosen, with the
measurements behind them: ``docs/experiments.md``, section 2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from avatar.config import AvatarConfig


class CapacityRule(BaseModel):
    """Constants of the capacity rule (see the module docstring)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    min_texel_px: float = Field(
        2.0, gt=0, description="Smallest UV texel pitch on the head, in image pixels, the rule allows: it picks "
        "the largest power-of-two N*M whose texels stay at least this wide (1 = texels no finer than pixels). "
        "Lower it for a finer, slower model when quality matters more than time (the tiny preset uses 1); "
        "docs/experiments.md, section 2, has the measured curve behind the default.")
    prims_over_voxels_log2: int = Field(
        2, ge=0, le=6, description="log2(N / M) of the split of N*M into N primitives of M voxels per side "
        "(2: N = 4 M, as the paper's 64 x 16 and tiny's 16 x 4).")
    min_prims_per_side: int = Field(8, ge=8, description="Smallest N (a power of two >= 8).")
    max_prims_per_side: int = Field(128, ge=8, description="Largest N (a power of two).")
    min_voxels_per_side: int = Field(2, ge=2, description="Smallest M (a power of two >= 2).")
    max_voxels_per_side: int = Field(32, ge=2, description="Largest M (a power of two).")
    width_per_cbrt_frame: float = Field(
        16.0, gt=0, description="Decoder width (channels of the 8 x 8 feature map and first transposed conv) "
        "per cube root of the number of training frames.")
    min_width: int = Field(32, ge=8, description="Smallest decoder width (channels).")
    max_width: int = Field(256, ge=8, description="Largest decoder width (channels; the paper's 256).")
    min_steps: int = Field(16, ge=2, description="Fewest raymarch steps per ray.")
    max_steps: int = Field(128, ge=2, description="Most raymarch steps per ray (the paper's 128).")
    expression_variance: float = Field(
        0.999, gt=0, lt=1, description="Fraction of the training meshes' variance about their mean that the "
        "counted expression modes hold (see count_expression_modes).")
    latent_per_mode: float = Field(
        2.0, ge=0, description="Latent size per expression mode, rounded up to a power of two within "
        "[min_latent, max_latent]; 0 = keep the latent size of the train stage's avatar section. Fewer "
        "dimensions per mode leave the encoder less room to give a training frame a code of its own: new "
        "expressions render better and held-out lights on the training expressions worse. Lower it where the "
        "training frames are few (tiny: 1, for 34 frames; docs/experiments.md, section 43).")
    min_latent: int = Field(8, ge=1, description="Smallest latent size.")
    max_latent: int = Field(256, ge=1, description="Largest latent size (the paper's 256).")

    @model_validator(mode="after")
    def _check(self) -> "CapacityRule":
        for key in ("min_prims_per_side", "max_prims_per_side", "min_voxels_per_side", "max_voxels_per_side"):
            value = getattr(self, key)
            if value & (value - 1):
                raise ValueError(f"{key}={value}: must be a power of two")
        for lo, hi in (("min_prims_per_side", "max_prims_per_side"), ("min_voxels_per_side", "max_voxels_per_side"),
                       ("min_width", "max_width"), ("min_steps", "max_steps"), ("min_latent", "max_latent")):
            if getattr(self, lo) > getattr(self, hi):
                raise ValueError(f"{lo}={getattr(self, lo)} > {hi}={getattr(self, hi)}")
        return self


@dataclass(frozen=True)
class CaptureStats:
    """What the rule reads from a capture (at training resolution).

    Attributes:
        image_width_px, image_height_px: training image size.
        footprint_px: the head's width in the images, pixels (median over training images).
        frames: number of training frames (each with every camera).
        expression_modes: principal components of the training meshes that hold
            ``CapacityRule.expression_variance`` of their variance (``count_expression_modes``);
            0 = not measured (the latent size is left as given).
    """

    image_width_px: int
    image_height_px: int
    footprint_px: float
    frames: int
    expression_modes: int = 0


@dataclass(frozen=True)
class Capacity:
    """The rule's choice and the figures behind it."""

    config: AvatarConfig
    stats: CaptureStats
    texels_per_side: int  # N * M
    texel_px: float  # UV texel pitch of the choice on the head, image pixels
    voxel_px: float  # projected voxel edge of the choice, pixels (prim_overlap * texel_px)
    layout_span_px: float  # pixels the layout's row spans (theta * footprint)
    width: int  # decoder width

    def as_metrics(self) -> dict[str, float]:
        """Flat metrics (``capacity_*``): the choice and the rule's inputs."""
        c = self.config
        return {
            "capacity_primitives": c.num_prims, "capacity_prims_per_side": c.prims_per_side,
            "capacity_voxel_res": c.voxels_per_side, "capacity_texels_per_side": self.texels_per_side,
            "capacity_width": self.width, "capacity_steps_per_ray": c.steps_per_ray,
            "capacity_latent_dim": c.latent_dim, "capacity_expression_modes": self.stats.expression_modes,
            "capacity_texel_px": self.texel_px, "capacity_voxel_px": self.voxel_px,
            "capacity_layout_span_px": self.layout_span_px,
            "capacity_image_width_px": self.stats.image_width_px,
            "capacity_image_height_px": self.stats.image_height_px,
            "capacity_footprint_px": self.stats.footprint_px, "capacity_frames": self.stats.frames,
        }


def _pow2_floor(x: float) -> int:
    return 1 << max(0, int(math.floor(math.log2(max(x, 1.0)) + 1e-9)))


def _pow2_ceil(x: float) -> int:
    return 1 << max(0, int(math.ceil(math.log2(max(x, 1.0)) - 1e-9)))


def _pow2_round(x: float) -> int:
    return 1 << max(0, int(round(math.log2(max(x, 1.0)))))


def _round8(x: float) -> int:
    return max(8, int(round(x / 8.0)) * 8)


class CapacityInputError(ValueError):
    """Capture figures the rule cannot use (the train stage reports it as a ConfigError)."""


def _check_stats(stats: CaptureStats) -> None:
    for key in ("image_width_px", "image_height_px", "footprint_px", "frames"):
        value = getattr(stats, key)
        if not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise CapacityInputError(f"capacity rule: {key}={value!r} must be a positive finite number; check the "
                              "training images and mattes (an empty matte gives a zero footprint) or use "
                              "train.capacity: fixed")
    modes = stats.expression_modes
    if isinstance(modes, bool) or not isinstance(modes, (int, np.integer)) or modes < 0:
        raise CapacityInputError(f"capacity rule: expression_modes={modes!r} must be an integer >= 0 (0 = not "
                                 "measured); count it with count_expression_modes on the training meshes")
    if stats.footprint_px > 2.0 * math.hypot(stats.image_width_px, stats.image_height_px):
        raise CapacityInputError(f"capacity rule: footprint_px={stats.footprint_px:.1f} is more than twice the image "
                          f"diagonal ({stats.image_width_px}x{stats.image_height_px} px); the footprint must be "
                          "measured at the training resolution")


def split_texels(texels_per_side: int, rule: CapacityRule) -> tuple[int, int]:
    """N * M texels per side -> (N, M): N = 2^k M as far as the bounds allow."""
    k = int(round(math.log2(texels_per_side)))
    log_n = math.ceil((k + rule.prims_over_voxels_log2) / 2)
    lo_n, hi_n = int(math.log2(rule.min_prims_per_side)), int(math.log2(rule.max_prims_per_side))
    lo_m, hi_m = int(math.log2(rule.min_voxels_per_side)), int(math.log2(rule.max_voxels_per_side))
    log_n = min(max(log_n, lo_n, k - hi_m), hi_n, k - lo_m)
    log_m = min(max(k - log_n, lo_m), hi_m)
    return 1 << log_n, 1 << log_m


def config_for(texels_per_side: int, width: int, rule: CapacityRule, base: AvatarConfig) -> AvatarConfig:
    """The model with ``texels_per_side`` = N*M and decoder ``width``; other fields from ``base``.

    Transposed-conv widths follow the paper's pattern: w, w/2, w/2, w/4, w/4, ... (the paper's
    256, 128, 128, 64, 64, 32 for w = 256), the last layer 3 M (RGB) or M (opacity).
    """
    n, m = split_texels(texels_per_side, rule)
    layers = int(round(math.log2(n * m / 8)))
    hidden = tuple(max(8, _round8(width / 2 ** math.ceil(i / 2))) for i in range(layers - 1))
    theta = math.radians(base.layout_theta_deg)
    steps = min(max(_pow2_round(n * m / theta), rule.min_steps), rule.max_steps)
    return base.model_copy(update={
        "prims_per_side": n, "voxels_per_side": m, "base_channels": width,
        "rgb_channels": hidden + (3 * m,), "alpha_channels": hidden + (m,),
        "geometry_channels": min(max(_round8(width / 4), 16), 64), "steps_per_ray": steps})


def decoder_width(frames: int, rule: CapacityRule) -> int:
    """Decoder width for ``frames`` training frames: ``width_per_cbrt_frame * frames^(1/3)``, bounded, multiple of 8."""
    raw = rule.width_per_cbrt_frame * float(frames) ** (1.0 / 3.0)
    return min(max(_round8(raw), rule.min_width), rule.max_width)


def latent_size(expression_modes: int, rule: CapacityRule) -> int:
    """Latent size for ``expression_modes`` modes: ``latent_per_mode`` each, up to a power of two, bounded."""
    return min(max(_pow2_ceil(rule.latent_per_mode * expression_modes), rule.min_latent), rule.max_latent)


def count_expression_modes(vertices: np.ndarray, variance: float, max_frames: int = 512,
                           max_points: int = 2048) -> int:
    """Principal components of the meshes ``vertices`` [F, V, 3] that hold ``variance`` of their spread.

    The spread is about the mean mesh, so with head-space (stabilised) meshes it is the
    expression's. Evenly spread subsets of at most ``max_frames`` frames and ``max_points``
    vertices keep the cost bounded at the paper's thousands of frames and tens of thousands
    of vertices (expression modes are smooth over the face, so a vertex subset spans them);
    the eigenvalues come from the [F, F] Gram matrix in float64. 0 for fewer than 2 frames or
    meshes that never move.
    """
    v = np.asarray(vertices)
    if v.ndim != 3 or v.shape[-1] != 3:
        raise ValueError(f"count_expression_modes: vertices must be [F, V, 3], got {v.shape}")
    if v.shape[0] < 2:
        return 0
    frames = np.unique(np.linspace(0, v.shape[0] - 1, min(max_frames, v.shape[0])).round().astype(int))
    points = np.unique(np.linspace(0, v.shape[1] - 1, min(max_points, v.shape[1])).round().astype(int))
    x = v[frames][:, points].reshape(len(frames), -1).astype(np.float64)
    if not np.any(x != x[0]):
        return 0  # exactly still (the mean's rounding would otherwise leave a spurious mode)
    x -= x.mean(0)
    eig = np.clip(np.linalg.eigvalsh(x @ x.T)[::-1], 0.0, None)  # descending
    total = eig.sum()
    if not np.isfinite(total) or total <= 0:
        return 0
    return int(np.searchsorted(np.cumsum(eig) / total, variance - 1e-12) + 1)


def texel_px(texels_per_side: int, footprint_px: float, base: AvatarConfig) -> float:
    """UV texel pitch on the head (image pixels) of N*M = ``texels_per_side`` on a head ``footprint_px`` wide."""
    return math.radians(base.layout_theta_deg) * footprint_px / texels_per_side


def voxel_px(texels_per_side: int, footprint_px: float, base: AvatarConfig) -> float:
    """Projected voxel edge (pixels) of N*M = ``texels_per_side`` on a head ``footprint_px`` wide."""
    return base.prim_overlap * texel_px(texels_per_side, footprint_px, base)


def choose_capacity(stats: CaptureStats, rule: CapacityRule | None = None,
                    base: AvatarConfig | None = None) -> Capacity:
    """The capacity the capture ``stats`` need (see the module docstring); CapacityInputError on nonsense input.

    ``base`` supplies what the rule does not choose (encoder width, layout; the latent size
    when ``stats.expression_modes`` is 0 or ``rule.latent_per_mode`` is 0); the rule sets N, M,
    the channel widths, the raymarch steps and the latent size.
    """
    rule = rule or CapacityRule()
    base = base or AvatarConfig.tiny()
    _check_stats(stats)
    # The visible head cannot be wider than the image it is seen in.
    footprint = min(float(stats.footprint_px), float(max(stats.image_width_px, stats.image_height_px)))
    span = math.radians(base.layout_theta_deg) * footprint
    finest = span / rule.min_texel_px  # N*M at which a texel is min_texel_px wide
    lo = rule.min_prims_per_side * rule.min_voxels_per_side
    hi = rule.max_prims_per_side * rule.max_voxels_per_side
    texels = min(max(_pow2_floor(finest), lo), hi)
    n, m = split_texels(texels, rule)
    texels = n * m
    width = decoder_width(stats.frames, rule)
    modes = int(stats.expression_modes)
    latent = latent_size(modes, rule) if modes > 0 and rule.latent_per_mode > 0 else base.latent_dim
    config = config_for(texels, width, rule, base.model_copy(update={"latent_dim": latent}))
    return Capacity(config=config, stats=CaptureStats(stats.image_width_px, stats.image_height_px, footprint,
                                                      int(stats.frames), modes),
                    texels_per_side=texels, texel_px=texel_px(texels, footprint, base),
                    voxel_px=voxel_px(texels, footprint, base), layout_span_px=span,
                    width=width)


def footprint_from_mattes(mattes: np.ndarray, threshold: float = 0.5) -> float:
    """The head's width in pixels: median over images of the matte's foreground bounding-box width.

    ``mattes`` [..., H, W] alpha in [0, 1]; images with no foreground are ignored (0 if all are empty).
    """
    fg = np.asarray(mattes) > threshold  # [..., H, W]
    cols = fg.any(-2).reshape(-1, fg.shape[-1])  # [K, W]
    has = cols.any(-1)
    if not has.any():
        return 0.0
    cols = cols[has]
    first = cols.argmax(-1)
    last = cols.shape[-1] - 1 - cols[:, ::-1].argmax(-1)
    return float(np.median(last - first + 1))


def find_knee(x: np.ndarray, y: np.ndarray) -> int | None:
    """Index of the knee of an increasing, concave curve y(x) (Kneedle), or None with < 3 points.

    Both axes are normalised to [0, 1]; the knee is the point farthest above the chord
    from the first to the last point (max of y_n - x_n): where more x stops buying
    proportionally more y. A flat curve (no gain at all) has its knee at the first point.
    """
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    if x.shape != y.shape or x.ndim != 1:
        raise ValueError(f"find_knee: x {x.shape} and y {y.shape} must be 1-D of the same length")
    if len(x) < 3 or not (np.isfinite(x).all() and np.isfinite(y).all()):
        return None
    order = np.argsort(x)
    xs, ys = x[order], y[order]
    span_x = xs[-1] - xs[0]
    span_y = ys.max() - ys.min()
    if span_x <= 0:
        return None
    if span_y <= 0:
        return int(order[0])
    xn = (xs - xs[0]) / span_x
    # y from the first point's value; the last point need not be the highest (noise, overfitting).
    yn = (ys - ys[0]) / span_y
    return int(order[int(np.argmax(yn - xn))])


__all__ = ["CapacityInputError", "CapacityRule", "CaptureStats", "Capacity", "choose_capacity", "config_for",
           "count_expression_modes", "decoder_width", "latent_size", "split_texels", "texel_px", "voxel_px",
           "footprint_from_mattes", "find_knee"]
