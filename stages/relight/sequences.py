"""What to render, frame by frame: cameras, lights and expressions of each render sequence.

A sequence is a list of ``FrameSpec`` (head-space camera, lights as head-space positions
with RGB intensities, the mesh to drive the head with). Builders here make the artist's
requests: an environment map rotating over time, a point light anywhere or orbiting the
head, a turntable, a dolly zoom, novel expressions from blendshape curves or meshes.

Head space: +y up, +z out of the face, +x the subject's left, metres (the world frame of
``scene``, with the head at the origin). Environment-map directions are taken in this frame.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from scene.camera import Camera
from scene.envmap import AdaptiveParams, BackMask, EnvMap, select_lights
from scene.view import ViewSpec  # the sequences' default camera (re-exported: seq.ViewSpec)


class LightRangeWarning(UserWarning):
    """A requested light lies far behind the head, outside what the model saw in training."""


@dataclass
class FrameSpec:
    """One frame to render.

    Attributes:
        camera: camera posed in the head frame (``cam_from_head``).
        light_pos: [K, 3] head-space light positions (distant lights: far along their direction).
        light_rgb: [K, 3] light colours/intensities multiplying the network's unit-light output.
        mesh_index: which driving mesh (row of the sequence's mesh array) to decode.
        info: what a person or the eval stage needs to redo this frame (map, rotation, light).
    """

    camera: Camera
    light_pos: np.ndarray
    light_rgb: np.ndarray
    mesh_index: int = 0
    info: dict = field(default_factory=dict)


def warn_if_behind(position: np.ndarray, centre: np.ndarray, mask: BackMask, what: str) -> bool:
    """Warn (once per call) when a light is inside the back cone the model never saw lit."""
    d = np.asarray(position, float) - np.asarray(centre, float)
    d = d / max(float(np.linalg.norm(d)), 1e-12)
    if -d[2] > math.cos(math.radians(mask.cone_half_angle_deg)):
        warnings.warn(f"{what}: light at {np.round(position, 3).tolist()} is {math.degrees(math.acos(-d[2])):.0f} "
                      f"degrees from straight behind the head; the model was trained with lights in front "
                      "(the capture rig), so expect an unreliable render there", LightRangeWarning, stacklevel=2)
        return True
    return False


def envmap_sequence(envmap: EnvMap, frames: int, rotate_deg_per_frame: float, view: ViewSpec, *,
                    method: str = "uniform", directions: int = 256, drop_fraction: float = 0.1,
                    adaptive: AdaptiveParams = AdaptiveParams(), mask: BackMask = BackMask(),
                    light_distance_m: float = 50.0, scale: float = 1.0, centroid: bool = False) -> list[FrameSpec]:
    """An environment map turning about +y by ``rotate_deg_per_frame`` each frame, front camera."""
    out = []
    camera = view.camera(view.front_eye())
    for i in range(frames):
        angle = math.radians(rotate_deg_per_frame * i)
        lights = select_lights(envmap.rotated_about_y(angle), method, directions, drop_fraction, adaptive, mask,
                               centroid)
        out.append(FrameSpec(camera, lights.positions_world(light_distance_m, np.asarray(view.target_head)),
                             scale * lights.irradiance_rgb, 0,
                             {"kind": "envmap", "envmap": envmap.source, "rotation_deg": rotate_deg_per_frame * i,
                              "directions": len(lights), "method": method}))
    return out


def point_light_gain(position: np.ndarray, centre: np.ndarray, intensity: float = 1.0,
                     falloff_reference_m: float = 1.0) -> float:
    """A point light's gain on the network's unit light: inverse-square from ``falloff_reference_m``."""
    r = float(np.linalg.norm(np.asarray(position, float) - np.asarray(centre, float)))
    return intensity * (falloff_reference_m / max(r, 1e-3)) ** 2


def point_light_sequence(positions: np.ndarray, view: ViewSpec, *, intensity: float = 1.0,
                         falloff_reference_m: float = 1.0, mask: BackMask = BackMask(),
                         what: str = "point light") -> list[FrameSpec]:
    """One frame per head-space light position [F, 3], front camera.

    The network's output is for a light at the training bars' distance (``falloff_reference_m``);
    a point light elsewhere is scaled by the inverse-square law relative to it.
    """
    camera = view.camera(view.front_eye())
    centre = np.asarray(view.target_head, float)
    out, warned = [], False
    for i, p in enumerate(np.asarray(positions, float).reshape(-1, 3)):
        if not warned:
            warned = warn_if_behind(p, centre, mask, f"{what} frame {i}")
        gain = point_light_gain(p, centre, intensity, falloff_reference_m)
        out.append(FrameSpec(camera, p[None], np.full((1, 3), gain), 0,
                             {"kind": "point", "position": p.tolist(), "intensity": gain}))
    return out


def orbit_positions(radius_m: float, frames: int, height_m: float = 0.0,
                    centre: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Light positions [F, 3] on a horizontal circle around the head, starting in front (+z)."""
    a = 2 * math.pi * np.arange(frames) / frames
    return np.asarray(centre) + np.stack([radius_m * np.sin(a), np.full(frames, height_m), radius_m * np.cos(a)], -1)


def turntable_sequence(frames: int, view: ViewSpec, light_pos: np.ndarray, light_rgb: np.ndarray,
                       sweep_deg: float = 180.0) -> list[FrameSpec]:
    """The camera swings ``sweep_deg`` around the head (centred on the front) at constant distance.

    The model covers the front of the head (its primitives span about +-105 degrees around
    +z), so the default sweep goes from the left profile to the right one.
    """
    out = []
    for i in range(frames):
        a = math.radians(-sweep_deg / 2 + sweep_deg * i / max(frames - 1, 1))
        eye = np.asarray(view.target_head) + view.distance_m * np.array([math.sin(a), 0.0, math.cos(a)])
        out.append(FrameSpec(view.camera(eye), light_pos, light_rgb, 0, {"kind": "turntable",
                                                                       "azimuth_deg": math.degrees(a)}))
    return out


def views_sequence(eyes: np.ndarray, view: ViewSpec, light_pos: np.ndarray, light_rgb: np.ndarray) -> list[FrameSpec]:
    """One frame per camera position [F, 3] (head space), each looking at the head centre."""
    return [FrameSpec(view.camera(eye), light_pos, light_rgb, 0, {"kind": "view", "eye": np.asarray(eye).tolist()})
            for eye in np.asarray(eyes, float).reshape(-1, 3)]


def dolly_zoom_sequence(frames: int, view: ViewSpec, light_pos: np.ndarray, light_rgb: np.ndarray,
                        near_m: float = 0.35, far_m: float = 1.6) -> list[FrameSpec]:
    """Push in from ``far_m`` to ``near_m`` while widening the field of view (head size kept).

    The focal length scales with the distance so the head keeps its size in the image while
    the perspective changes: the near-field effect the paper shows.
    """
    out = []
    f0 = view.focal_px()
    for i in range(frames):
        d = far_m + (near_m - far_m) * i / max(frames - 1, 1)
        eye = np.asarray(view.target_head) + np.array([0.0, 0.0, d])
        out.append(FrameSpec(view.camera(eye, f0 * d / view.distance_m), light_pos, light_rgb, 0,
                             {"kind": "dolly_zoom", "distance_m": d}))
    return out


def expression_sequence(meshes: np.ndarray, view: ViewSpec, light_pos: np.ndarray,
                        light_rgb: np.ndarray) -> list[FrameSpec]:
    """One frame per driving mesh (rows of ``meshes`` [F, V, 3]), front camera, fixed light."""
    camera = view.camera(view.front_eye())
    return [FrameSpec(camera, light_pos, light_rgb, i, {"kind": "expression", "mesh": i}) for i in range(len(meshes))]


def key_light(view: ViewSpec, intensity: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A default light for view and expression renders: upper front-left, 1.2 m from the head."""
    pos = np.asarray(view.target_head) + 1.2 * np.array([0.45, 0.35, 0.82]) / np.linalg.norm([0.45, 0.35, 0.82])
    return pos[None], np.full((1, 3), intensity * (1.0 / 1.2) ** 2)


def read_light_position(text: str) -> np.ndarray:
    """Parse ``x,y,z`` (metres, head space) into [3]; ``ValueError`` with the text otherwise."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError as err:
        raise ValueError(f"point light '{text}': expected x,y,z in metres, e.g. 0.5,0.3,1.0") from err
    if len(values) != 3:
        raise ValueError(f"point light '{text}': expected three numbers x,y,z in metres, got {len(values)}")
    return np.array(values)


__all__ = ["FrameSpec", "ViewSpec", "LightRangeWarning", "dolly_zoom_sequence", "envmap_sequence",
           "expression_sequence", "key_light", "orbit_positions", "point_light_sequence", "read_light_position",
           "turntable_sequence", "views_sequence", "warn_if_behind"]
