"""The relight stage's params (what to render and how) and where its environment maps are found."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field

from pipeline.devices import DeviceChoice
from pipeline.stage import StageParams
from scene.envmap import AdaptiveParams, BackMask

ASSETS = Path(__file__).resolve().parents[2] / "assets" / "envmaps"
DEFAULT_ENVMAPS = ("blender-cc0/courtyard.exr", "blender-cc0/studio.exr", "blender-cc0/sunrise.exr")


class RelightParams(StageParams):
    """What to render and how."""

    envmaps: tuple[str, ...] = Field(DEFAULT_ENVMAPS, description="Lat-long EXR maps, paths relative to assets/envmaps or absolute.")
    envmap_frames: int = Field(4, ge=0, description="Frames per environment map sequence.")
    rotate_deg_per_frame: float = Field(30.0, description="Rotation of the map about +y per frame, degrees.")
    light_method: Literal["uniform", "adaptive"] = Field(
        "uniform", description="'uniform' (the paper's ~256 directions) or 'adaptive' (importance sampled; see adaptive).")
    directions: int = Field(256, ge=1, description="Uniform directions before masking and dropping.")
    light_centroid: bool = Field(False, description="Uniform: place each light at its cell's energy centroid (a sun exactly where it is) instead of the paper's cell centre.")
    drop_fraction: float = Field(0.1, ge=0.0, lt=1.0, description="Fraction of the dimmest directions dropped (paper: 0.1).")
    back_mask: BackMask = Field(default_factory=BackMask,
                                description="Light from behind the head (never seen in training): the dropped cone "
                                "and the attenuation of the rest of the back hemisphere; see scene.envmap.BackMask.")
    adaptive: AdaptiveParams = Field(default_factory=AdaptiveParams,
                                     description="Adaptive light selection (light_method 'adaptive'): tolerance and "
                                     "bounds; see scene.envmap.AdaptiveParams.")
    light_distance_m: float = Field(50.0, gt=1.0, description="Distance at which distant (envmap) lights are placed as point lights.")
    envmap_scale: float = Field(1.0, gt=0.0, description="Multiplier of envmap light intensities (exposure of the renders).")
    orbit_radius_m: float = Field(3.0, ge=0.0, description="Point light orbiting the head at this radius (0 = no orbit).")
    orbit_frames: int = Field(8, ge=0, description="Frames of the point-light orbit.")
    falloff_reference_m: float = Field(1.0, gt=0.0, description="Distance at which the network's unit light holds (the rig's bars); point lights fall off as 1/r^2 from it.")
    point_lights: tuple[tuple[float, float, float], ...] = Field((), description="Extra fixed point lights, head space metres, one frame each.")
    camera_eyes: tuple[tuple[float, float, float], ...] = Field((), description="Extra camera positions, head space metres, each a frame looking at the head (key light).")
    turntable_frames: int = Field(6, ge=0, description="Frames of the camera turntable (0 = none).")
    dolly_zoom_frames: int = Field(6, ge=0, description="Frames of the dolly zoom (0 = none).")
    expressions_csv: str = Field("", description="ARKit-named blendshape weight CSV to drive the head with ('' = none).")
    expressions_obj_dir: str = Field("", description="Folder of OBJ meshes (tracked topology) to drive the head with.")
    width_px: int = Field(96, ge=8, description="Render width in pixels.")
    height_px: int = Field(128, ge=8, description="Render height in pixels.")
    distance_m: float = Field(0.9, gt=0.05, description="Camera distance from the head for the default view.")
    fov_deg: float = Field(24.0, gt=1.0, lt=170.0, description="Horizontal field of view of the default view, degrees.")
    fps: float = Field(24.0, gt=0.0, description="Frame rate of the MP4s.")
    light_batch: int = Field(16, ge=1, description="Lights decoded per batch in the voxel-space sum.")
    steps_per_ray: int = Field(0, ge=0, description="Raymarch steps per ray (0 = the model's own setting).")
    naive_timing_frames: int = Field(1, ge=0, description="Envmap frames (the first ones, over all maps) timed in this process with the fast and the naive path (timing and agreement check); 0 = report the workers' timings.")
    envmap_path: Literal["auto", "bake", "sum"] = Field("auto", description="How envmap sequences render: 'auto' (from a light-transfer bake of their view and expression where one bake serves at least bake_min_frames envmap frames, else the voxel-space sum), 'bake' (always bake; needs uniform cell-centre lights) or 'sum' (never).")
    bake_rank: int = Field(32, ge=0, description="Images in the bake's basis (0 = one per direction, exact). Raise it when bake frames drift from the voxel-space sum (bake_psnr_vs_sum_db); each doubling costs about 1.3x the frame time (docs/experiments.md, section 8).")
    bake_min_frames: int = Field(4, ge=1, description="'auto': bake a view and expression once this many envmap frames (over all maps and rotations) share it; lower it when bakes are cheap against frames (a GPU), raise it for short sequences (docs/experiments.md, section 8).")
    bake_check: bool = Field(True, description="Time one bake, its frames and the voxel-space sum of the same frames side by side in this process, and compare them (metrics bake_*), on bake_check_envmaps at bake_check_rotations_deg. Off for quick renders.")
    bake_check_envmaps: tuple[str, ...] = Field((), description="Maps the bake is checked on, as envmaps; empty = the envmaps rendered (the shipped defaults unless changed).")
    bake_check_rotations_deg: tuple[float, ...] = Field((0.0, 90.0, 200.0), description="Rotations about +y at which each checked map is compared, degrees.")
    device: DeviceChoice = Field("auto", description="'auto' (CUDA if present), 'cpu' or 'cuda'.")


def resolve_envmap(name: str) -> Path:
    """A map path as given, or relative to the shipped ``assets/envmaps``."""
    p = Path(name)
    return p if p.is_absolute() or p.exists() else ASSETS / name


def check_maps(params: RelightParams) -> tuple[str, ...]:
    """The maps the bake is checked on (``bake_check_envmaps``, or the envmaps rendered); none when the check is off."""
    if not params.bake_check:
        return ()
    return tuple(params.bake_check_envmaps or params.envmaps)
