"""The look-development session behind ``pipeline view``: one preview image per viewer state.

A viewer state (``LookState``) names an environment map from the session's catalogue (never a
path), its rotation and exposure, an optional point light, an orbit camera and a tracked
expression. ``LookDevSession.render`` turns it into an 8-bit sRGB preview by the cheapest path
that is exact enough, and says which path it took:

- **bake**: the map part of the frame from a light-transfer bake (``avatar.bake.ImageBake``)
  of the current view and expression: project the turned map onto the baked directions
  (``scene.envmap.RotatingProjection``, microseconds), then a weighted sum of basis images.
  A view and expression are baked the second time a frame asks for them in a row, that is
  once the camera and the expression hold still, so a drag of the camera never waits for
  a bake while a drag of the map rotation (or the exposure, or the light) runs on it.
- **voxel_sum**: the map's lights and the point light decoded and summed in voxel space,
  one raymarch (``avatar.render.render``); what a moving camera or a new expression gets.
- **network** (point light only): a near-field light is never a mix of baked directions
  (the network is conditioned on the light's position), so with a bake in hand the point
  light is rendered on its own (one light, one raymarch) and added: light adds linearly and
  opacity does not depend on it.

Bakes and decoded expressions are kept in small LRU caches. Everything is in head space,
metres; the orbit camera looks at the tracked head's centre.
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from avatar.bake import ImageBake, bake_images
from avatar.render import PointLights, decode, render
from scene.colour import srgb8
from scene.envmap import (
    BackMask,
    EnvMap,
    EnvMapError,
    RotatingProjection,
    fibonacci_sphere,
    read_envmap,
)
from scene.view import ViewSpec
from stages.relight.sequences import point_light_gain

RenderPath = Literal["bake", "voxel_sum", "network", "none"]


class RequestError(ValueError):
    """A viewer request that cannot be served (unknown map or expression, a value out of range); the page shows it."""


@dataclass
class MapEntry:
    """One environment map the session may use: loaded at start-up, or the reason it could not be."""

    map_id: str
    label: str
    envmap: EnvMap | None
    error: str = ""
    projection: RotatingProjection | None = None  # built on first use (tens of ms to seconds per map)

    def describe(self) -> dict:
        return {"id": self.map_id, "label": self.label, "ok": self.envmap is not None, "error": self.error}


class MapCatalogue:
    """The maps a viewer may pick, by id. Requests name an id; a path in a request is never opened.

    Maps are read once, when the catalogue is built, from the files the operator listed (the
    command line) and the project's shipped maps. A map that cannot be read (damaged, not 2:1)
    stays listed with its error, so the page can say why it cannot be picked.
    """

    def __init__(self, files: list[tuple[str, Path]]) -> None:
        self.entries: OrderedDict[str, MapEntry] = OrderedDict()
        for label, path in files:
            map_id = _unique_id(_slug(label), self.entries)
            try:
                envmap, error = read_envmap(path), ""
            except EnvMapError as err:
                envmap, error = None, str(err)
            self.entries[map_id] = MapEntry(map_id, label, envmap, error)

    def describe(self) -> list[dict]:
        return [entry.describe() for entry in self.entries.values()]

    def get(self, map_id: str) -> MapEntry:
        entry = self.entries.get(map_id)
        if entry is None:
            known = ", ".join(self.entries) or "none"
            raise RequestError(f"unknown environment map '{map_id}' (this viewer serves only: {known})")
        if entry.envmap is None:
            raise RequestError(f"environment map '{entry.label}' could not be read: {entry.error}")
        return entry

    def preview(self, map_id: str, height: int = 64) -> np.ndarray:
        """An 8-bit sRGB thumbnail [height, 2 height, 3] of a map, exposed so its mean is mid-grey."""
        import cv2

        radiance = self.get(map_id).envmap.radiance
        small = cv2.resize(radiance, (2 * height, height), interpolation=cv2.INTER_AREA)
        mean = float(np.mean(small)) or 1.0
        return srgb8(np.clip(small * (0.18 / mean), 0.0, None))


def _slug(label: str) -> str:
    keep = "".join(c if c.isalnum() else "-" for c in Path(label).stem.lower())
    return "-".join(part for part in keep.split("-") if part) or "map"


def _unique_id(base: str, taken) -> str:
    candidate, n = base, 2
    while candidate in taken:
        candidate, n = f"{base}-{n}", n + 1
    return candidate


@dataclass(frozen=True)
class LookState:
    """What the viewer shows: map, light, camera and expression (head space, metres and degrees)."""

    map_id: str = ""  # "" = no environment map
    rotation_deg: float = 0.0
    exposure_stops: float = 0.0  # display exposure, 2 ** stops
    map_intensity: float = 1.0  # multiplier of the map's light
    light_on: bool = False
    light_head_m: tuple[float, float, float] = (0.5, 0.3, 1.0)
    light_intensity: float = 1.0  # the network's unit light at falloff_reference_m
    azimuth_deg: float = 0.0  # camera orbit about +y, 0 = in front (+z)
    elevation_deg: float = 0.0
    distance_m: float = 0.9
    expression: int = 0

    @staticmethod
    def from_request(message: dict, num_expressions: int) -> LookState:
        """A state from a page's JSON message; ``RequestError`` naming the bad field."""
        if not isinstance(message, dict):
            raise RequestError("a viewer message must be a JSON object")

        def number(key: str, default: float, low: float, high: float) -> float:
            value = message.get(key, default)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise RequestError(f"'{key}' must be a number, got {value!r}")
            if not low <= value <= high:
                raise RequestError(f"'{key}' = {value} is outside [{low}, {high}]")
            return float(value)

        map_id = message.get("map", "")
        if not isinstance(map_id, str):
            raise RequestError(f"'map' must be a map id (a string), got {map_id!r}")
        light = message.get("light_head_m", LookState.light_head_m)
        if (not isinstance(light, (list, tuple)) or len(light) != 3
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                           for v in light)):
            raise RequestError(f"'light_head_m' must be [x, y, z] in metres, got {light!r}")
        if max(abs(float(v)) for v in light) > 20.0:
            raise RequestError(f"'light_head_m' {list(light)} is more than 20 m from the head")
        expression = message.get("expression", 0)
        if isinstance(expression, bool) or not isinstance(expression, int):
            raise RequestError(f"'expression' must be a whole number, got {expression!r}")
        if not 0 <= expression < num_expressions:
            raise RequestError(f"unknown expression {expression}: this subject has tracked expressions "
                               f"0 to {num_expressions - 1}")
        return LookState(
            map_id=map_id, rotation_deg=number("rotation_deg", 0.0, -1e6, 1e6),
            exposure_stops=number("exposure_stops", 0.0, -20.0, 20.0),
            map_intensity=number("map_intensity", 1.0, 0.0, 1e4), light_on=bool(message.get("light_on", False)),
            light_head_m=tuple(float(v) for v in light), light_intensity=number("light_intensity", 1.0, 0.0, 1e4),
            azimuth_deg=number("azimuth_deg", 0.0, -1e6, 1e6), elevation_deg=number("elevation_deg", 0.0, -85.0, 85.0),
            distance_m=number("distance_m", 0.9, 0.2, 10.0), expression=expression)


@dataclass(frozen=True)
class LookSettings:
    """How the session renders (``pipeline view``'s options)."""

    width_px: int = 96
    height_px: int = 128
    fov_deg: float = 24.0
    directions: int = 256  # the bake's uniform directions (the paper's 256)
    drop_fraction: float = 0.1
    bake_rank: int = 32
    light_distance_m: float = 50.0  # where distant (map) lights are placed
    falloff_reference_m: float = 1.0  # the network's unit light holds at this distance (the bars')
    light_batch: int = 16
    bake_cache: int = 8  # bakes kept (views x expressions)
    backdrop: float = 0.03  # linear grey behind the head
    back_mask: BackMask = field(default_factory=BackMask)


@dataclass(frozen=True)
class LookFrame:
    """One preview: the sRGB image, the path that made it and how long it took."""

    image_srgb8: np.ndarray  # [H, W, 3] uint8
    path: RenderPath
    seconds: float
    baked_now: bool = False  # this frame waited for a bake
    bake_seconds: float = 0.0
    note: str = ""

    def info(self) -> dict[str, Any]:
        return {"path": self.path, "ms": 1e3 * self.seconds, "baked_now": self.baked_now,
                "bake_ms": 1e3 * self.bake_seconds, "note": self.note,
                "width": int(self.image_srgb8.shape[1]), "height": int(self.image_srgb8.shape[0])}


class LookDevSession:
    """Renders ``LookState``s of one trained head (``model``) driven by its tracked meshes.

    Thread-safe: ``render`` holds a lock (one render at a time; the network and the caches are shared).
    """

    def __init__(self, model, image_scale: float, meshes_head: np.ndarray, maps: MapCatalogue,
                 settings: LookSettings = LookSettings(), steps: int | None = None) -> None:
        if len(meshes_head) == 0:
            raise ValueError("the viewer needs at least one tracked expression")
        self.model, self.image_scale, self.maps, self.settings = model, float(image_scale), maps, settings
        self.meshes_head = np.asarray(meshes_head, np.float32)
        self.steps = int(steps or model.config.steps_per_ray)
        self.target_head = tuple(float(v) for v in self.meshes_head[0].mean(0))
        self.directions = fibonacci_sphere(settings.directions)
        self._geometry: OrderedDict[int, Any] = OrderedDict()
        self._bakes: OrderedDict[tuple, ImageBake] = OrderedDict()
        self._last_view: tuple | None = None
        self._lock = threading.Lock()

    @property
    def num_expressions(self) -> int:
        return len(self.meshes_head)

    def view(self, state: LookState) -> ViewSpec:
        return ViewSpec(self.settings.width_px, self.settings.height_px, state.distance_m, self.settings.fov_deg,
                        self.target_head)

    def camera(self, state: LookState):
        """The orbit camera: ``distance_m`` from the head's centre at the state's azimuth and elevation."""
        az, el = math.radians(state.azimuth_deg), math.radians(state.elevation_deg)
        offset = state.distance_m * np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
        return self.view(state).camera(np.asarray(self.target_head) + offset)

    def _geometry_of(self, expression: int):
        if expression in self._geometry:
            self._geometry.move_to_end(expression)
            return self._geometry[expression]
        geometry = decode(self.model, self.meshes_head[expression])
        self._geometry[expression] = geometry
        while len(self._geometry) > 16:
            self._geometry.popitem(last=False)
        return geometry

    def _projection(self, entry: MapEntry) -> RotatingProjection:
        if entry.projection is None:
            s = self.settings
            entry.projection = RotatingProjection(entry.envmap, s.directions, s.drop_fraction, s.back_mask)
        return entry.projection

    def _point_light(self, state: LookState) -> PointLights:
        position = np.asarray(state.light_head_m, float)
        gain = point_light_gain(position, self.target_head, state.light_intensity, self.settings.falloff_reference_m)
        return PointLights(position[None], np.full((1, 3), gain))

    def _map_lights(self, state: LookState, projection: RotatingProjection) -> PointLights:
        lights = projection.lights(math.radians(state.rotation_deg))
        return PointLights(lights.positions_world(self.settings.light_distance_m, np.asarray(self.target_head)),
                           state.map_intensity * lights.irradiance_rgb)

    def render(self, state: LookState) -> LookFrame:
        """The preview of ``state``; ``RequestError`` for an unknown map or expression."""
        if not 0 <= state.expression < self.num_expressions:
            raise RequestError(f"unknown expression {state.expression}: this subject has tracked expressions "
                               f"0 to {self.num_expressions - 1}")
        entry = self.maps.get(state.map_id) if state.map_id else None
        with self._lock, torch.no_grad():
            return self._render_locked(state, entry, time.perf_counter())

    def _render_locked(self, state: LookState, entry: MapEntry | None, start: float) -> LookFrame:
        s = self.settings
        camera = self.camera(state)
        view_key = (state.expression, tuple(np.round(camera.cam_from_head.matrix().ravel(), 9)))
        held = view_key == self._last_view
        self._last_view = view_key
        geometry = self._geometry_of(state.expression)
        h, w = s.height_px, s.width_px
        rgb = np.zeros((h, w, 3), np.float32)
        alpha = np.zeros((h, w), np.float32)
        path: RenderPath = "none"
        baked_now, bake_seconds, note = False, 0.0, ""

        def network(lights: PointLights):
            image = render(self.model, geometry, camera, lights, steps=self.steps, image_scale=self.image_scale,
                           light_batch=s.light_batch).numpy()
            return image[0], image[1]

        if entry is not None:
            projection = self._projection(entry)
            baked = self._bakes.get(view_key)
            if baked is None and held:
                bake_start = time.perf_counter()
                baked = bake_images(self.model, geometry, camera, self.directions, rank=s.bake_rank,
                                    distance_m=s.light_distance_m, centre=self.target_head, steps=self.steps,
                                    light_batch=s.light_batch)
                bake_seconds, baked_now = time.perf_counter() - bake_start, True
                self._bakes[view_key] = baked
                while len(self._bakes) > s.bake_cache:
                    self._bakes.popitem(last=False)
            if baked is not None:
                self._bakes.move_to_end(view_key)
                weights = state.map_intensity * projection.weights(math.radians(state.rotation_deg))
                rgb, alpha = baked.frame(weights, self.image_scale)
                rgb = rgb.copy()
                path = "bake"
                if state.light_on:
                    light_rgb, _ = network(self._point_light(state))
                    rgb += light_rgb
                    note = "point light on the network path"
            else:
                lights = self._map_lights(state, projection)
                if state.light_on:
                    point = self._point_light(state)
                    lights = PointLights(np.concatenate([lights.positions, point.positions]),
                                         np.concatenate([lights.rgb, point.rgb]))
                rgb, alpha = network(lights)
                path = "voxel_sum"
                note = "camera or expression moved: bakes once they hold still"
        elif state.light_on:
            rgb, alpha = network(self._point_light(state))
            path = "network"
        else:
            note = "no light: pick a map or switch the point light on"
        if path == "none":
            # Opacity does not depend on light: the silhouette still shows against the backdrop.
            alpha = network(self._point_light(state))[1]
        exposure = 2.0 ** state.exposure_stops
        composite = rgb * exposure + (1.0 - alpha[..., None]) * s.backdrop
        return LookFrame(srgb8(np.clip(composite, 0.0, None)), path, time.perf_counter() - start, baked_now,
                         bake_seconds, note)


def load_session(inputs: dict[str, Path], map_files: list[tuple[str, Path]], settings: LookSettings,
                 device: str, load_model: Callable | None = None) -> LookDevSession:
    """A session for a subject's ``train`` and ``track`` outputs (folders) and the maps it may serve."""
    from avatar.io import load_trained
    from stages.track.output import TrackOutput
    from stages.train.output import TrainOutput

    model, meta = TrainOutput(inputs["train"]).model(load_model or (lambda folder: load_trained(folder, device)))
    track = TrackOutput(inputs["track"])
    vertices = np.asarray(track.meshes(keys=("vertices",))["vertices"], np.float32)
    if len(vertices) == 0:
        raise track.malformed(track.meshes_path, "no tracked meshes")
    return LookDevSession(model, float(meta.get("image_scale", 1.0)), vertices, MapCatalogue(map_files), settings)


__all__ = ["LookDevSession", "LookFrame", "LookSettings", "LookState", "MapCatalogue", "MapEntry", "RequestError",
           "load_session"]
