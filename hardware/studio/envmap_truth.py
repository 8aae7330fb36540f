"""Ground truth for relighting: the studio's own renderer under an environment map or a point light.

The studio ray traces the true subject (its mesh, albedo, GGX specular) with a shadow ray per
light and pixel, so an environment map rendered as many directional lights (every direction
integrating its Voronoi cell of the map, nothing masked or dropped) is the reference a
learned relight is measured against. The head is posed at the origin with the world axes
(``world_from_head`` = identity), so world and head space coincide and the same cameras and
light positions serve the model (head space) and the studio (world): ``studio_camera`` re-poses a
head-frame camera as the studio's world camera.

Usage::

    subject = subject_from_truth(truth_dir)           # capture.truth/studio.json
    frame = frame_from_weights(weights)                # [57] ICT weights, head at the origin
    img = render_envmap_truth(subject, frame, camera, envmap, directions=1024)
    img = render_point_truth(subject, frame, camera, position_world, intensity_rgb)
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from hardware.studio.performance import FrameState
from hardware.studio.renderer import RenderResult, RenderSettings, VirtualStudio
from hardware.studio.subject import Subject, make_subject
from scene.camera import Camera, Rigid
from scene.envmap import BackMask, EnvMap, select_uniform
from scene.lights import DirectionalLight, PointLight


def subject_from_truth(truth_dir: Path) -> Subject:
    """Rebuild the captured subject from ``capture.truth/studio.json`` (name and identity seed)."""
    path = Path(truth_dir) / "studio.json"
    try:
        spec = json.loads(path.read_text())
        # The albedo atlas resolution, when the capture recorded it (else the studio default).
        extra = {"texture_size": int(spec["texture_size"])} if "texture_size" in spec else {}
        return make_subject(str(spec["subject"]), int(spec["identity_seed"]), **extra)
    except (OSError, ValueError, KeyError) as err:
        raise ValueError(f"{path}: cannot rebuild the subject ({err}); re-run the capture stage") from err


def frame_from_weights(expression_weights: np.ndarray, index: int = 0) -> FrameState:
    """A frame of ``expression_weights`` [57] with the head at the origin (world = head space)."""
    return FrameState(index, "relight", 0.0, np.asarray(expression_weights, np.float32), Rigid.identity())


def studio_camera(camera: Camera) -> Camera:
    """A camera posed in the head frame as the studio's (world) camera, for a head at the origin.

    The frames of ``frame_from_weights`` have ``world_from_head`` = identity, so
    ``cam_from_world = cam_from_head``. A camera already posed in the world is returned as is.
    """
    if camera.frame == "world":
        return camera
    return camera.with_pose(camera.cam_from_head, "world")


def truth_studio(subject: Subject, settings: RenderSettings | None = None) -> VirtualStudio:
    """The studio that renders ground truth under arbitrary lights: noise-free and deterministic
    (``settings`` replaces the noiseless defaults); the rig only matters for its bars, unused here."""
    from scene.rig import load_rig

    return VirtualStudio(load_rig(), subject, settings or RenderSettings(shot_noise_gain=0.0, read_noise=0.0))


def envmap_truth_lights(envmap: EnvMap, directions: int = 1024) -> list[DirectionalLight]:
    """The whole map (no back mask, nothing dropped) as ``directions`` directional lights.

    Each light integrates its Voronoi cell of the map and sits at the cell's luminance-weighted
    mean direction, so a sun is lit from exactly where it is.
    """
    lights = select_uniform(envmap, directions, drop_fraction=0.0, mask=BackMask(enabled=False), centroid=True)
    return [DirectionalLight(d, e) for d, e in zip(lights.directions_world, lights.irradiance_rgb)]


def render_envmap_truth(subject: Subject, frame: FrameState, camera: Camera, envmap: EnvMap,
                        directions: int = 1024, settings: RenderSettings | None = None) -> RenderResult:
    """The studio's render of ``frame`` from ``camera`` (posed in head space = world) lit by ``envmap``."""
    return truth_studio(subject, settings).render_lights(frame, studio_camera(camera),
                                                    envmap_truth_lights(envmap, directions), noise=False)


def render_point_truth(subject: Subject, frame: FrameState, camera: Camera, position_world: np.ndarray,
                       intensity_rgb: np.ndarray, settings: RenderSettings | None = None) -> RenderResult:
    """The studio's render under one isotropic point light (near-field: 1/r^2 and shadows per pixel)."""
    light = PointLight(np.asarray(position_world, float), np.asarray(intensity_rgb, float))
    return truth_studio(subject, settings).render_lights(frame, studio_camera(camera), [light], noise=False)
