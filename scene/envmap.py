"""Lat-long HDR environment maps: reading, orientation, rotation and light-direction selection.

Orientation (checked by ``tests/scene/test_envmap.py`` against the markings of
``assets/envmaps/openexr-images/OrientationLatLong.exr``). A map of ``H`` rows and
``W = 2 H`` columns covers the sphere of directions in our world frame (+y up, +z out of
the face towards the cameras, +x to the subject's left). Pixel ``(row i, column j)`` has
its centre at ``u = (j + 0.5) / W``, ``v = (i + 0.5) / H`` and looks along::

    longitude phi = 2 pi (0.5 - u)        latitude theta = pi (0.5 - v)
    direction = (sin(phi) cos(theta), sin(theta), cos(phi) cos(theta))

so that

- the centre column (``u = 0.5``) is **+z**: what the face looks at (the cameras);
- the column a quarter of the way in from the left (``u = 0.25``) is **+x**, the
  subject's left; three quarters (``u = 0.75``) is **-x**, the subject's right;
- the left and right edges (``u = 0`` and ``u = 1``, the seam) are **-z**, behind the head;
- the top row is **+y** (up), the bottom row **-y**.

This is OpenEXR's own lat-long convention (``ImfEnvmap.h``: ``direction = (sin lon cos lat,
sin lat, cos lon cos lat)`` with ``lon = +pi`` at the left edge, ``lat = +pi/2`` at the top)
mapped one to one onto our world axes, except that we put directions at pixel centres
(OpenEXR puts the first and last column exactly on the seam, half a pixel off ours).
Seen from inside the sphere, panning right in the image turns right: looking at +z with +y
up, +x appears on the left, as in the test image.

Radiometry: a map holds radiance ``L`` (linear RGB). A set of distant lights chosen from it
(``DirectionalLights``) carries, per direction, the integral of ``L`` times the pixel solid
angle over the directions it stands for (``irradiance_rgb``, the irradiance the light gives
a surface facing it), so the lights' sum is the map's integral (times any attenuation).

Rotation: ``select_uniform`` of a map turned about +y integrates the whole map again;
``RotatingProjection`` precomputes every whole-column shift of one map once and then gives
the same lights for any rotation in microseconds (the light-transfer bake's projection).
"""

from __future__ import annotations

import functools
import heapq
import math
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from pydantic import ConfigDict, Field
from pydantic.dataclasses import dataclass as pydantic_dataclass

from scene.colour import luminance


class EnvMapError(ValueError):
    """An environment map file that cannot be used (missing, corrupt, truncated, not 2:1)."""


class EnvMapWarning(UserWarning):
    """An environment map was usable only after a repair (NaN or clearly negative pixels)."""


@dataclass(frozen=True)
class EnvMap:
    """A lat-long environment map in the world frame (see the module docstring).

    Attributes:
        radiance: [H, W, 3] float32 linear RGB radiance, W = 2 H, no NaN, no negatives.
        source: where it came from (file path or a description), for messages and file names.
    """

    radiance: np.ndarray
    source: str = "envmap"

    def __post_init__(self) -> None:
        rad = np.asarray(self.radiance, dtype=np.float32)
        if rad.ndim != 3 or rad.shape[2] != 3:
            raise EnvMapError(f"{self.source}: environment map must be [H, W, 3], got {rad.shape}")
        if rad.shape[1] != 2 * rad.shape[0]:
            raise EnvMapError(
                f"{self.source}: environment map is {rad.shape[1]}x{rad.shape[0]} pixels; a lat-long "
                "map must be exactly twice as wide as it is tall (2:1). Convert it to lat-long "
                "(equirectangular) first")
        object.__setattr__(self, "radiance", rad)

    @property
    def height(self) -> int:
        return int(self.radiance.shape[0])

    @property
    def width(self) -> int:
        return int(self.radiance.shape[1])

    @property
    def name(self) -> str:
        """A short name for output folders: the file stem."""
        return Path(self.source).stem

    def integral_rgb(self) -> np.ndarray:
        """The integral of radiance over the sphere, [3] (sum of radiance times solid angle)."""
        return np.einsum("hwc,h->c", self.radiance.astype(np.float64), pixel_solid_angles_sr(self.height))

    def sample(self, directions_world: np.ndarray) -> np.ndarray:
        """Bilinear radiance lookup for unit directions [..., 3] -> [..., 3] (wraps at the seam)."""
        col, row = direction_to_pixel(directions_world, self.height, self.width)
        c0 = np.floor(col).astype(np.int64)
        r0 = np.floor(row).astype(np.int64)
        fc, fr = (col - c0)[..., None], (row - r0)[..., None]
        # Columns wrap around the seam; rows clamp at the poles.
        c0w, c1w = c0 % self.width, (c0 + 1) % self.width
        r0c, r1c = np.clip(r0, 0, self.height - 1), np.clip(r0 + 1, 0, self.height - 1)
        img = self.radiance
        top = img[r0c, c0w] * (1 - fc) + img[r0c, c1w] * fc
        bottom = img[r1c, c0w] * (1 - fc) + img[r1c, c1w] * fc
        return (top * (1 - fr) + bottom * fr).astype(np.float32)

    def rotated_about_y(self, angle_rad: float) -> "EnvMap":
        """The environment turned by ``angle_rad`` about world +y (right-handed: +z towards +x).

        A light that was at +z is at ``(sin a, 0, cos a)`` afterwards. Lat-long rotation about
        the pole is a horizontal shift; fractional shifts interpolate linearly between columns
        (exact, energy-preserving, for whole-pixel shifts).
        """
        shift_px = angle_rad / (2.0 * math.pi) * self.width
        whole = math.floor(shift_px)
        frac = shift_px - whole
        # New column j shows longitude phi_j - a, i.e. old column j + shift.
        a = np.roll(self.radiance, -whole, axis=1)
        b = np.roll(self.radiance, -(whole + 1), axis=1)
        return replace(self, radiance=((1.0 - frac) * a + frac * b).astype(np.float32))


# ---- geometry of the lat-long grid -------------------------------------------------------------

def pixel_directions(height: int, width: int) -> np.ndarray:
    """Unit world direction of every pixel centre, [H, W, 3] (module docstring convention)."""
    u = (np.arange(width, dtype=np.float64) + 0.5) / width
    v = (np.arange(height, dtype=np.float64) + 0.5) / height
    phi = 2.0 * math.pi * (0.5 - u)  # [W] longitude
    theta = math.pi * (0.5 - v)  # [H] latitude
    cos_t, sin_t = np.cos(theta)[:, None], np.sin(theta)[:, None]
    return np.stack([np.sin(phi)[None, :] * cos_t, np.broadcast_to(sin_t, (height, width)),
                     np.cos(phi)[None, :] * cos_t], axis=-1)


def pixel_solid_angles_sr(height: int) -> np.ndarray:
    """Solid angle of one pixel of each row, [H] steradians (rows sum, times W, to 4 pi)."""
    width = 2 * height
    edges = math.pi * (0.5 - np.arange(height + 1, dtype=np.float64) / height)  # latitude of row edges
    return (2.0 * math.pi / width) * (np.sin(edges[:-1]) - np.sin(edges[1:]))


def direction_to_pixel(directions_world: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Continuous pixel coordinates (column, row) of unit directions [..., 3].

    Integer values are pixel centres (column ``j`` is the centre of pixel column ``j``), so
    +z maps to column ``W/2 - 0.5`` and the seam (-z) to column ``-0.5 == W - 0.5``.
    """
    d = np.asarray(directions_world, dtype=np.float64)
    d = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
    phi = np.arctan2(d[..., 0], d[..., 2])
    theta = np.arcsin(np.clip(d[..., 1], -1.0, 1.0))
    u = 0.5 - phi / (2.0 * math.pi)
    v = 0.5 - theta / math.pi
    return u * width - 0.5, v * height - 0.5


# ---- reading -----------------------------------------------------------------------------------

def read_envmap(path: str | Path, negative_tolerance: float = 0.01) -> EnvMap:
    """Read a lat-long HDR map from an OpenEXR file.

    Args:
        path: the ``.exr`` file (RGB, RGBA or Y channels; alpha is ignored).
        negative_tolerance: negatives down to ``-negative_tolerance`` (lossy DWA compression
            rings around bright pixels) are clamped to 0 silently.
    Returns:
        the map. Clearly negative pixels and NaN/inf are set to 0 with an ``EnvMapWarning``.
    Raises:
        EnvMapError: missing, truncated or corrupt file, or not 2:1; the message names the file.
    """
    from scene.image_io import read_exr

    path = Path(path)
    try:
        img = read_exr(path)
    except ValueError as err:
        raise EnvMapError(f"environment map {path}: {err}") from err
    if img.shape[2] >= 3:
        rgb = img[..., :3]
    else:
        rgb = np.repeat(img[..., :1], 3, axis=2)  # Y (luminance-only) map
    rgb = np.array(rgb, dtype=np.float32)
    if rgb.shape[1] != 2 * rgb.shape[0]:
        raise EnvMapError(
            f"environment map {path}: is {rgb.shape[1]}x{rgb.shape[0]} pixels; a lat-long map must be "
            "exactly twice as wide as it is tall (2:1). Convert it to lat-long (equirectangular) first")
    bad = ~np.isfinite(rgb)
    if bad.any():
        warnings.warn(f"environment map {path}: {int(bad.any(-1).sum())} pixels are NaN or infinite; "
                      "set to 0 (the map may be damaged; check it in an image viewer)", EnvMapWarning,
                      stacklevel=2)
        rgb[bad] = 0.0
    negative = rgb < -negative_tolerance
    if negative.any():
        warnings.warn(f"environment map {path}: {int(negative.any(-1).sum())} pixels are clearly negative "
                      f"(down to {float(rgb.min()):.4g}); clamped to 0. Radiance cannot be negative: "
                      "check how the map was made", EnvMapWarning, stacklevel=2)
    np.maximum(rgb, 0.0, out=rgb)
    return EnvMap(rgb, str(path))


def write_envmap(path: str | Path, envmap: EnvMap) -> None:
    """Write a map as a float32 EXR (lossless, so a re-read map is identical)."""
    from scene.image_io import write_exr

    write_exr(path, envmap.radiance, half=False)


# ---- lights from a map -------------------------------------------------------------------------

@dataclass(frozen=True)
class DirectionalLights:
    """Distant lights standing for an environment map.

    Attributes:
        directions_world: [K, 3] unit vectors from the head towards each light.
        irradiance_rgb: [K, 3] integral of radiance (times attenuation) over the directions the
            light stands for: the irradiance it gives a surface facing it.
        method: how they were chosen (``uniform`` or ``adaptive``), for logs and metrics.
        estimated_error: the selection's own error estimate (adaptive), NaN otherwise.
    """

    directions_world: np.ndarray
    irradiance_rgb: np.ndarray
    method: str = "uniform"
    estimated_error: float = float("nan")

    def __len__(self) -> int:
        return int(self.directions_world.shape[0])

    def positions_world(self, distance_m: float = 50.0,
                        center_world: np.ndarray = np.zeros(3)) -> np.ndarray:
        """Far point-light positions [K, 3]: each direction at ``distance_m`` from the head centre.

        The network takes a light *position* (it computes per-primitive light directions from
        it), so a distant light becomes a point light far away along its direction, as the paper
        does. At 50 m the direction changes by under 0.3 degrees across a 25 cm head, below what
        the model resolves; give a point light of intensity ``irradiance * distance^2`` if the
        renderer applies the inverse-square law.
        """
        return np.asarray(center_world, float) + distance_m * self.directions_world

    def total_rgb(self) -> np.ndarray:
        """Sum of the lights' irradiance [3]."""
        return self.irradiance_rgb.sum(axis=0)


@pydantic_dataclass(frozen=True, config=ConfigDict(extra="forbid"))
class BackMask:
    """The paper's treatment of light from behind the head (never seen in training).

    The one declaration of the back mask: relight nests it as ``relight.back_mask``.
    """

    cone_half_angle_deg: float = Field(
        45.0, ge=0.0, le=180.0, description="Directions within this angle of the back direction (-z) are "
        "dropped. Widen it if relit heads show light bleeding in from behind; 0 keeps the whole back hemisphere "
        "(attenuated).")
    attenuation_power: float = Field(
        4.0, ge=0.0, description="The rest of the back hemisphere is scaled by cos(theta)**power, theta the angle "
        "below the side plane (z = 0): 1 at the side, 0 straight behind. Higher darkens back light faster.")
    enabled: bool = Field(
        True, description="False keeps the whole sphere unattenuated (ground-truth renders, tests).")

    def weights(self, directions_world: np.ndarray) -> np.ndarray:
        """Attenuation in [0, 1] of unit directions [..., 3] -> [...]."""
        d = np.asarray(directions_world, dtype=np.float64)
        if not self.enabled:
            return np.ones(d.shape[:-1])
        back = np.clip(-d[..., 2], 0.0, 1.0)  # sin of the angle behind the side plane
        theta = np.arcsin(back)
        w = np.cos(theta) ** self.attenuation_power
        in_cone = -d[..., 2] > math.cos(math.radians(self.cone_half_angle_deg))
        return np.where(in_cone, 0.0, w)


def fibonacci_sphere(n: int) -> np.ndarray:
    """``n`` nearly uniformly spread unit directions [n, 3] (golden-angle spiral)."""
    if n < 1:
        raise ValueError(f"fibonacci_sphere: need at least one direction, got {n}")
    k = np.arange(n, dtype=np.float64) + 0.5
    y = 1.0 - 2.0 * k / n
    r = np.sqrt(np.maximum(0.0, 1.0 - y * y))
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.sin(phi), y, r * np.cos(phi)], axis=-1)


def uniform_solid_angles_sr(n: int) -> np.ndarray:
    """Solid angle [n] (steradians, summing to 4 pi) of each ``fibonacci_sphere(n)`` direction's Voronoi cell.

    Exact spherical cells (``scipy.spatial.SphericalVoronoi``); a map's lights integrate the
    pixels whose centres fall in them (``select_uniform``), which approaches these areas as
    the map's resolution grows.
    """
    from scipy.spatial import SphericalVoronoi

    if n < 4:
        return np.full(n, 4.0 * math.pi / n)
    return np.asarray(SphericalVoronoi(fibonacci_sphere(n)).calculate_areas(), float)


@functools.lru_cache(maxsize=16)
def _voronoi_cells(height: int, width: int, n: int) -> np.ndarray:
    """Index [H * W] of the nearest of ``fibonacci_sphere(n)`` for every pixel (its Voronoi cell)."""
    from scipy.spatial import cKDTree

    tree = cKDTree(fibonacci_sphere(n))
    _, idx = tree.query(pixel_directions(height, width).reshape(-1, 3))
    return idx.astype(np.int64)


def weighted_radiance(envmap: EnvMap, mask: BackMask) -> np.ndarray:
    """Per-pixel radiance times solid angle times the back attenuation, [H, W, 3] float64."""
    weights = mask.weights(pixel_directions(envmap.height, envmap.width))  # [H, W]
    solid = pixel_solid_angles_sr(envmap.height)[:, None]  # [H, 1]
    return envmap.radiance.astype(np.float64) * (weights * solid)[..., None]


def select_uniform(envmap: EnvMap, count: int = 256, drop_fraction: float = 0.1,
                   mask: BackMask = BackMask(), centroid: bool = False) -> DirectionalLights:
    """The paper's lights: ``count`` uniform directions, each integrating its Voronoi cell.

    Every pixel's radiance (times solid angle and the back attenuation) goes to its nearest
    Fibonacci direction, so the lights sum to the attenuated integral of the map. Directions
    with nothing left (the masked back cone) are removed, then the ``drop_fraction`` dimmest
    of the remaining ones (by luminance) are dropped, as in the paper.

    ``centroid=False`` puts each light at its cell's Fibonacci direction (the paper's uniform
    directions); ``True`` at the cell's luminance-weighted mean direction, which puts a sun
    exactly where it is (used for ground truth and references).
    """
    energy = weighted_radiance(envmap, mask).reshape(-1, 3)  # [H*W, 3]
    cells = _voronoi_cells(envmap.height, envmap.width, count)
    irradiance = np.stack([np.bincount(cells, energy[:, c], minlength=count) for c in range(3)], -1)
    directions = fibonacci_sphere(count)
    if centroid:
        pixel_lum = luminance(energy).astype(np.float64)  # [H*W]
        dirs = pixel_directions(envmap.height, envmap.width).reshape(-1, 3)
        mean = np.stack([np.bincount(cells, pixel_lum * dirs[:, c], minlength=count) for c in range(3)], -1)
        norm = np.linalg.norm(mean, axis=1, keepdims=True)
        directions = np.where(norm > 1e-30, mean / np.maximum(norm, 1e-30), directions)
    keep = kept_directions(irradiance, drop_fraction, envmap.source)
    return DirectionalLights(directions[keep], irradiance[keep], "uniform")


def kept_directions(irradiance: np.ndarray, drop_fraction: float, source: str = "envmap") -> np.ndarray:
    """Indices (ascending) of the uniform directions ``select_uniform`` keeps: lit ones less the dimmest few.

    ``irradiance`` [count, 3] per direction; directions with no light are removed, then the
    ``drop_fraction`` dimmest of the rest (by luminance, ties in index order) are dropped.
    """
    lum = luminance(irradiance).astype(np.float64)
    alive = np.flatnonzero(lum > 0)
    if alive.size == 0:
        raise EnvMapError(f"environment map {source}: no light left (all black, or all behind the head)")
    n_drop = int(math.floor(drop_fraction * len(alive)))
    return np.sort(alive[np.argsort(lum[alive], kind="stable")[n_drop:]])


class RotatingProjection:
    """The paper's uniform lights of every rotation of one map about +y, a few microseconds each.

    ``select_uniform(envmap.rotated_about_y(a), count, drop_fraction, mask)`` integrates the
    whole map per rotation (tens of ms at 512 x 1024). Rotation about +y is a shift of the
    map's columns under fixed Voronoi cells and a fixed back mask (both belong to the head),
    so this precomputes, once per map, every cell's integral of the map shifted by every whole
    number of columns: per row, the cross-correlation of the cell's solid angle times mask
    with the map's row, by FFT (``table`` [count, W, 3]). A rotation by a fractional number of
    columns mixes two whole shifts, as ``rotated_about_y`` does; the dead and dimmest
    directions are then dropped as ``select_uniform`` drops them (``kept_directions``).

    ``lights(a)`` equals ``select_uniform(envmap.rotated_about_y(a), ...)`` to float rounding
    (the FFT's, ~1e-12 of the map's total; a direction lit by less than that counts as dark).
    Only the paper's cell-centre directions (``centroid=False``): centroids move with the map.
    """

    def __init__(self, envmap: EnvMap, count: int = 256, drop_fraction: float = 0.1,
                 mask: BackMask = BackMask()) -> None:
        h, w = envmap.height, envmap.width
        self.source, self.count, self.drop_fraction, self.width = envmap.source, int(count), drop_fraction, w
        self.directions = fibonacci_sphere(count)  # [count, 3]
        cells = _voronoi_cells(h, w, count).reshape(h, w)
        weight = mask.weights(pixel_directions(h, w)) * pixel_solid_angles_sr(h)[:, None]  # [H, W]
        spectrum = np.fft.rfft(envmap.radiance.astype(np.float64), axis=1)  # [H, F, 3]
        acc = np.zeros((count, spectrum.shape[1], 3), np.complex128)  # [count, F, 3]
        columns = np.arange(w)
        for i in range(h):
            row_cells, inverse = np.unique(cells[i], return_inverse=True)
            rows = np.zeros((len(row_cells), w))
            rows[inverse, columns] = weight[i]
            # sum_j m[j] L[j + t] for every t: conj(FFT(m)) * FFT(L), summed over the rows.
            acc[row_cells] += np.conj(np.fft.rfft(rows, axis=1))[:, :, None] * spectrum[i][None]
        table = np.fft.irfft(acc, n=w, axis=1)  # [count, W, 3]: cell integral at each whole shift
        total = float(np.abs(table).max(initial=0.0))
        self.table = np.where(table > 1e-12 * total, table, 0.0)  # FFT round-off is no light
        lit = np.bincount(cells.reshape(-1), weight.reshape(-1), minlength=count) > 0
        self.table[~lit] = 0.0  # cells wholly in the masked cone are dark at every rotation

    def irradiance(self, angle_rad: float) -> np.ndarray:
        """Irradiance [count, 3] of every uniform direction under the map turned by ``angle_rad`` (before dropping)."""
        shift_px = angle_rad / (2.0 * math.pi) * self.width
        whole = math.floor(shift_px)
        frac = shift_px - whole
        a, b = self.table[:, whole % self.width], self.table[:, (whole + 1) % self.width]
        return (1.0 - frac) * a + frac * b

    def weights(self, angle_rad: float) -> np.ndarray:
        """Irradiance [count, 3] of the lights ``select_uniform`` keeps, 0 for the directions it drops."""
        irradiance = self.irradiance(angle_rad)
        out = np.zeros_like(irradiance)
        keep = kept_directions(irradiance, self.drop_fraction, self.source)
        out[keep] = irradiance[keep]
        return out

    def lights(self, angle_rad: float) -> DirectionalLights:
        """``select_uniform(envmap.rotated_about_y(angle_rad), count, drop_fraction, mask)``, fast."""
        irradiance = self.irradiance(angle_rad)
        keep = kept_directions(irradiance, self.drop_fraction, self.source)
        return DirectionalLights(self.directions[keep], irradiance[keep], "uniform")


# ---- adaptive selection ------------------------------------------------------------------------

@pydantic_dataclass(frozen=True, config=ConfigDict(extra="forbid"))
class AdaptiveParams:
    """Adaptive (importance-sampled) light selection.

    The one declaration of these settings: relight nests it as ``relight.adaptive``.
    """

    tolerance: float = Field(
        0.1, gt=0.0, description="Stop adding lights when the estimated error (the worst probe's relative error) "
        "is below this. Lower it for more accurate, slower relighting.")
    min_directions: int = Field(8, ge=1, description="Fewest lights the selection returns.")
    max_directions: int = Field(1024, ge=1, description="Most lights the selection returns, whatever the error.")
    working_height: int = Field(
        128, ge=1, description="The map is box-filtered (energy-preserving) to this many rows first; raise it for "
        "maps with very small bright sources.")
    probe_count: int = Field(96, ge=1, description="Surface normals on which the error is estimated.")
    probe_gloss: float = Field(
        8.0, ge=0.0, description="Phong exponent of the glossy half of the probe's reflectance (skin-like sheen); "
        "the other half is Lambertian.")
    probe_floor: float = Field(
        1.0, ge=0.0, description="The error of each probe is relative to its own response plus this many times "
        "the map's background level (its median radiance), so the side of the head in shadow counts as much as "
        "the lit side and a pure black side does not blow up.")


def _downsample(energy: np.ndarray, height: int) -> np.ndarray:
    """Sum pixel blocks of an energy map [H, W, C] down to ``height`` rows (integral kept)."""
    h, w, c = energy.shape
    if h <= height:
        return energy
    factor = h // height
    while h % factor:
        factor -= 1
    return energy.reshape(h // factor, factor, w // factor, factor, c).sum(axis=(1, 3))


class _Region:
    """A rectangle of the working map [r0, r1) x [c0, c1) and its summary statistics."""

    __slots__ = ("r0", "r1", "c0", "c1", "energy", "moment_vec", "rgb", "error")

    def __init__(self, tables: "_Tables", r0: int, r1: int, c0: int, c1: int) -> None:
        self.r0, self.r1, self.c0, self.c1 = r0, r1, c0, c1
        s = tables.box(r0, r1, c0, c1)
        self.energy = float(s[0])
        self.moment_vec = s[1:4]  # sum of energy * direction
        self.rgb = s[4:7]
        # Sum of E |d - c|^2 about the unit centroid c = 2 (E - |sum E d|): the leading error of
        # replacing the region by one light at c (the first-order term cancels at the centroid).
        self.error = max(0.0, 2.0 * (self.energy - float(np.linalg.norm(self.moment_vec))))

    @property
    def direction(self) -> np.ndarray:
        n = float(np.linalg.norm(self.moment_vec))
        if n < 1e-30:
            return np.array([0.0, 0.0, 1.0])
        return self.moment_vec / n

    def __lt__(self, other: "_Region") -> bool:  # heap order: largest error first
        return self.error > other.error


class _Tables:
    """Summed-area tables of energy, energy * direction and RGB energy over the working map."""

    def __init__(self, lum: np.ndarray, rgb: np.ndarray, dirs: np.ndarray) -> None:
        stack = np.concatenate([lum[..., None], lum[..., None] * dirs, rgb], axis=-1)  # [h, w, 7]
        self.sat = np.zeros((stack.shape[0] + 1, stack.shape[1] + 1, stack.shape[2]))
        self.sat[1:, 1:] = stack.cumsum(0).cumsum(1)
        self.lum = lum
        self.height, self.width = lum.shape

    def box(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        s = self.sat
        return s[r1, c1] - s[r0, c1] - s[r1, c0] + s[r0, c0]

    def split(self, reg: _Region) -> tuple[_Region, _Region] | None:
        """Cut a region in two halves of equal energy across its longer angular side."""
        rows, cols = reg.r1 - reg.r0, reg.c1 - reg.c0
        if rows * cols <= 1:
            return None
        lat = math.pi * (0.5 - (np.arange(reg.r0, reg.r1) + 0.5) / self.height)
        height_rad = rows * math.pi / self.height
        width_rad = cols * 2.0 * math.pi / self.width * float(np.cos(lat).max())
        block = self.lum[reg.r0:reg.r1, reg.c0:reg.c1]
        along_rows = (height_rad >= width_rad and rows > 1) or cols == 1
        marginal = block.sum(axis=1) if along_rows else block.sum(axis=0)
        cum = np.cumsum(marginal)
        cut = int(np.searchsorted(cum, 0.5 * cum[-1])) + 1 if cum[-1] > 0 else len(marginal) // 2
        cut = min(max(cut, 1), len(marginal) - 1)
        if along_rows:
            return (_Region(self, reg.r0, reg.r0 + cut, reg.c0, reg.c1),
                    _Region(self, reg.r0 + cut, reg.r1, reg.c0, reg.c1))
        return (_Region(self, reg.r0, reg.r1, reg.c0, reg.c0 + cut),
                _Region(self, reg.r0, reg.r1, reg.c0 + cut, reg.c1))


def probe_kernel(cosines: np.ndarray, gloss: float) -> np.ndarray:
    """Reflectance of the error probe for cosines between normal and light: half Lambert, half Phong."""
    c = np.maximum(cosines, 0.0)
    return 0.5 * c / math.pi + 0.5 * (gloss + 2.0) / (2.0 * math.pi) * c ** gloss


def select_adaptive(envmap: EnvMap, params: AdaptiveParams = AdaptiveParams(),
                    mask: BackMask = BackMask()) -> DirectionalLights:
    """Importance-sampled lights: split the brightest, widest regions until the error is small.

    Greedy median cut: every region becomes one light at its energy centroid carrying its
    energy; the region whose replacement by a point costs most (energy times angular
    spread) is cut in two equal-energy halves, until the worst relative error of the lights'
    response on ``probe_count`` probe normals (half Lambert, half glossy), each measured
    against its own response plus the map's background level, falls under ``tolerance``.
    A soft map meets it with a few lights; extended bright sources (softboxes, windows, a
    hazy sun) need more. A single tiny sun is rendered exactly by one light once a chain of
    cuts has isolated it, so it adds only that chain to what its sky needs (and can even
    cost less than the bare sky when it lights most probe normals).
    """
    energy = _downsample(weighted_radiance(envmap, mask), params.working_height)  # [h, w, 3]
    h, w, _ = energy.shape
    dirs = pixel_directions(h, w)  # [h, w, 3]
    lum = luminance(energy).astype(np.float64)
    tables = _Tables(lum, energy, dirs)
    probes = fibonacci_sphere(params.probe_count)  # [P, 3]
    # Exact probe responses of the (working-resolution) map: [P]
    reference = probe_kernel(probes @ dirs.reshape(-1, 3).T, params.probe_gloss) @ lum.reshape(-1)
    if reference.max() <= 0:
        raise EnvMapError(f"environment map {envmap.source}: no light left (all black, or all behind the head)")
    # Each probe's error is relative to its own response plus the map's background level (its
    # median radiance; a uniform map of radiance b gives every probe a response of about b),
    # not to the map's total: the shadowed side of a sunlit head counts as much as the lit one.
    solid = pixel_solid_angles_sr(h)[:, None]  # [h, 1]
    background = max(float(np.median(lum / solid)), 1e-3 * float(lum.sum() / (4.0 * math.pi)))
    scale = reference + params.probe_floor * background

    def response(reg: _Region) -> np.ndarray:
        return reg.energy * probe_kernel(probes @ reg.direction, params.probe_gloss)

    root = _Region(tables, 0, h, 0, w)
    heap = [root]
    approx = response(root)
    error = float(np.max(np.abs(approx - reference) / scale))
    while len(heap) < params.max_directions and (error > params.tolerance or len(heap) < params.min_directions):
        reg = heapq.heappop(heap)
        halves = tables.split(reg) if reg.error > 0 else None
        if halves is None:
            heapq.heappush(heap, reg)
            if all(r.error <= 0 for r in heap):
                break  # nothing left to split: every region is a single point of light
            reg.error = 0.0  # park it; split others
            heapq.heapify(heap)
            continue
        approx = approx - response(reg) + response(halves[0]) + response(halves[1])
        for half in halves:
            heapq.heappush(heap, half)
        error = float(np.max(np.abs(approx - reference) / scale))
    regions = [r for r in heap if r.energy > 0]
    directions = np.stack([r.direction for r in regions])
    irradiance = np.stack([r.rgb for r in regions])
    return DirectionalLights(directions, irradiance, "adaptive", error)


def select_lights(envmap: EnvMap, method: str = "uniform", count: int = 256, drop_fraction: float = 0.1,
                  adaptive: AdaptiveParams = AdaptiveParams(), mask: BackMask = BackMask(),
                  centroid: bool = False) -> DirectionalLights:
    """Choose lights by ``method`` (``uniform``: the paper's; ``adaptive``: importance sampled)."""
    if method == "uniform":
        return select_uniform(envmap, count, drop_fraction, mask, centroid)
    if method == "adaptive":
        return select_adaptive(envmap, adaptive, mask)
    raise ValueError(f"unknown light selection method {method!r}; use 'uniform' or 'adaptive'")


def synthetic_sky(height: int = 64, sun_direction: np.ndarray | None = None, sun_fraction: float = 0.0,
                  sun_radius_deg: float = 1.0) -> EnvMap:
    """A smooth sky (brighter above) with an optional sun carrying ``sun_fraction`` of the energy.

    For tests and benchmarks: the soft version and the sunny version share the same sky.
    """
    dirs = pixel_directions(height, 2 * height)
    sky = 0.3 + 0.7 * np.clip(dirs[..., 1], 0.0, 1.0) + 0.05 * (dirs[..., 2] + 1.0)
    radiance = np.repeat(sky[..., None], 3, axis=2) * np.array([0.8, 0.9, 1.0])
    if sun_direction is not None and sun_fraction > 0:
        sd = np.asarray(sun_direction, float) / np.linalg.norm(sun_direction)
        disc = (dirs @ sd) > math.cos(math.radians(sun_radius_deg))
        if not disc.any():  # a sun smaller than a pixel still lights one pixel
            col, row = direction_to_pixel(sd, height, 2 * height)
            disc = np.zeros(dirs.shape[:2], bool)
            disc[int(np.clip(round(float(row)), 0, height - 1)), int(round(float(col))) % (2 * height)] = True
        solid = np.broadcast_to(pixel_solid_angles_sr(height)[:, None], disc.shape)
        sky_energy = float((sky * solid).sum())
        sun_energy = sky_energy * sun_fraction / (1.0 - sun_fraction)
        radiance[disc] += np.array([1.0, 0.95, 0.85]) * sun_energy / float(solid[disc].sum())
    return EnvMap(radiance.astype(np.float32), "synthetic_sky" if sun_fraction <= 0 else "synthetic_sun")


__all__ = [
    "AdaptiveParams", "BackMask", "DirectionalLights", "EnvMap", "EnvMapError", "EnvMapWarning", "RotatingProjection",
    "direction_to_pixel", "fibonacci_sphere", "kept_directions", "pixel_directions", "pixel_solid_angles_sr", "probe_kernel",
    "read_envmap", "select_adaptive", "select_lights", "select_uniform", "synthetic_sky", "uniform_solid_angles_sr", "weighted_radiance",
    "write_envmap",
]
