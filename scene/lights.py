"""Light sources in world space: LED bars (line lights), point lights, directional lights.

Radiometric conventions (linear, arbitrary but consistent units):

- A ``PointLight`` has a radiant intensity ``intensity_rgb`` (per steradian). With an
  emitter normal it is a Lambertian emitter (intensity times ``cos`` of the angle off the
  normal), without one it is isotropic. The irradiance it gives a surface point ``x`` with
  normal ``n`` is ``I * cos_emit * max(0, n . l) / r^2`` (near-field: the ``1/r^2`` and both
  cosines are evaluated per point, never approximated by a distant light).
- A ``LightBar`` is a line light: the segment ``center +- axis * length / 2`` emitting the
  total intensity ``intensity`` (scalar, white) in the direction ``normal``. It is
  integrated by sampling points along the segment (``bar_sample_points``), each carrying
  ``intensity / samples``.
- A ``DirectionalLight`` gives the irradiance ``irradiance_rgb * max(0, n . l)`` with ``l``
  pointing from the surface towards the light (an environment-map direction).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Union

import numpy as np


def _unit(v: np.ndarray, what: str) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    n = float(np.linalg.norm(v))
    if n < 1e-12:
        raise ValueError(f"{what}: zero-length direction")
    return v / n


@dataclass(frozen=True)
class LightBar:
    """One LED bar of the rig (a line light).

    Attributes:
        id: bar index (0 ... 31), as in the OLAT sequence and ``bars.json``.
        center_world: [3] centre of the bar, metres.
        axis_world: [3] unit direction along the bar.
        length_m: length of the emitting segment.
        intensity: total radiant intensity along ``normal_world`` (white, linear units).
        normal_world: [3] unit emission direction (towards the head).
    """

    id: int
    center_world: np.ndarray
    axis_world: np.ndarray
    length_m: float
    intensity: float
    normal_world: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "center_world", np.asarray(self.center_world, dtype=np.float64))
        object.__setattr__(self, "axis_world", _unit(self.axis_world, f"bar {self.id} axis"))
        object.__setattr__(self, "normal_world", _unit(self.normal_world, f"bar {self.id} normal"))

    @property
    def endpoints_world(self) -> np.ndarray:
        """The two ends of the bar [2, 3]."""
        half = 0.5 * self.length_m * self.axis_world
        return np.stack([self.center_world - half, self.center_world + half])

    def to_dict(self) -> dict:
        """The ``bars.json`` entry of this bar (ground-truth / lightcal schema)."""
        return {"id": int(self.id), "center_world": self.center_world.tolist(),
                "axis_world": self.axis_world.tolist(), "length_m": float(self.length_m),
                "intensity": float(self.intensity), "normal_world": self.normal_world.tolist()}

    @staticmethod
    def from_dict(d: dict) -> "LightBar":
        centre = np.asarray(d["center_world"], float)
        normal = d.get("normal_world", (-centre / max(np.linalg.norm(centre), 1e-9)).tolist())
        return LightBar(int(d["id"]), centre, np.asarray(d["axis_world"], float), float(d["length_m"]),
                        float(d["intensity"]), np.asarray(normal, float))


def bar_sample_points(bar: LightBar, samples: int, jitter: np.ndarray | None = None) -> np.ndarray:
    """Stratified points along a bar.

    Args:
        samples: K strata along the bar.
        jitter: offsets in [0, 1) within each stratum, [..., K]; None = stratum midpoints.
    Returns:
        points [..., K, 3] in world space; each carries ``bar.intensity / K``.
    """
    k = np.arange(samples, dtype=np.float64)
    offs = 0.5 if jitter is None else np.asarray(jitter, dtype=np.float64)
    s = (k + offs) / samples - 0.5  # [..., K] in [-0.5, 0.5)
    return bar.center_world + s[..., None] * bar.length_m * bar.axis_world


@dataclass(frozen=True)
class PointLight:
    """A point light: ``intensity_rgb`` [3] radiant intensity; optional Lambertian emitter normal."""

    position_world: np.ndarray
    intensity_rgb: np.ndarray
    normal_world: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "position_world", np.asarray(self.position_world, dtype=np.float64))
        object.__setattr__(self, "intensity_rgb", np.broadcast_to(
            np.asarray(self.intensity_rgb, dtype=np.float64), (3,)).copy())
        if self.normal_world is not None:
            object.__setattr__(self, "normal_world", _unit(self.normal_world, "point light normal"))


@dataclass(frozen=True)
class DirectionalLight:
    """A distant light: ``direction_world`` [3] points from the surface towards the light."""

    direction_world: np.ndarray
    irradiance_rgb: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "direction_world", _unit(self.direction_world, "directional light"))
        object.__setattr__(self, "irradiance_rgb", np.broadcast_to(
            np.asarray(self.irradiance_rgb, dtype=np.float64), (3,)).copy())


Light = Union[LightBar, PointLight, DirectionalLight]


def point_irradiance(points: np.ndarray, normals: np.ndarray, light_pos: np.ndarray,
                     intensity: float | np.ndarray = 1.0,
                     emitter_normal: np.ndarray | None = None) -> np.ndarray:
    """Unshadowed near-field irradiance from point light(s) at surface points.

    Args:
        points, normals: [N, 3] surface positions and unit normals.
        light_pos: [3] or [N, 3] light position(s).
        intensity: scalar or [N] radiant intensity.
        emitter_normal: [3] Lambertian emitter direction, None = isotropic.
    Returns:
        irradiance [N]: ``I * cos_emit * max(0, n . l) / r^2``.
    """
    to_light = np.asarray(light_pos, dtype=np.float64) - points  # [N, 3]
    r2 = np.maximum(np.einsum("ij,ij->i", to_light, to_light), 1e-12)
    l = to_light / np.sqrt(r2)[:, None]
    cos_i = np.maximum(np.einsum("ij,ij->i", normals, l), 0.0)
    cos_e = 1.0 if emitter_normal is None else np.maximum(-(l @ np.asarray(emitter_normal, float)), 0.0)
    return np.asarray(intensity) * cos_e * cos_i / r2


def bar_irradiance(points: np.ndarray, normals: np.ndarray, bar: LightBar, samples: int = 64) -> np.ndarray:
    """Unshadowed irradiance [N] from a bar, integrated with ``samples`` midpoints (a reference)."""
    total = np.zeros(len(points))
    for p in bar_sample_points(bar, samples):
        total += point_irradiance(points, normals, p, bar.intensity / samples, bar.normal_world)
    return total
