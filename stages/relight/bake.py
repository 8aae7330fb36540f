"""The relight stage's light-transfer bakes: one per (view, expression), an executor item, cached.

A bake (``avatar.bake.ImageBake``) renders any environment map, at any rotation, from one
view of one expression with a weighted sum of its basis images. The stage bakes where that
pays (``choose_paths``) and keeps each bake in its per-item cache like every cached result:
``<cache_dir>/items/stages.relight.bake.bake_item/<key[:2]>/<key>.npz``, keyed by
``bake_key`` (the checkpoint's content digest, the driving mesh's bytes, the camera, the
baked directions and where their lights sit, the rank, steps, light batch and device type)
mixed with the code digest of this module and of ``avatar`` and ``scene`` (so a change to
the renderer re-bakes, a comment edit does not).

``render_from_bake`` turns frame specs (the same ``FrameSpec`` the voxel-space sum renders)
into images: each light of a frame must be one of the baked directions (the paper's uniform
directions, ``scene.envmap.fibonacci_sphere``), and its RGB becomes that direction's weight.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from avatar.bake import ImageBake, bake_images
from scene.camera import Camera
from scene.envmap import fibonacci_sphere
from stages.relight import sequences as seq
from stages.relight.render import worker_geometry, worker_model

# What a bake depends on besides this module (its cache entries' code version).
BAKE_CODE = ("avatar", "scene.camera", "scene.envmap")


@dataclass(frozen=True)
class BakeItem:
    """One bake to make, picklable and small (the model and meshes travel as paths, as ``FrameItem``'s)."""

    model_dir: str
    model_digest: str
    meshes_path: str
    mesh_array: str
    mesh_index: int
    mesh_digest: str
    camera: Camera  # cam_from_head extrinsics
    directions: int  # the uniform directions baked (fibonacci_sphere(directions))
    distance_m: float  # lights at centre_head + distance_m * direction
    centre_head: tuple[float, float, float]
    rank: int  # 0 = full (exact)
    steps: int
    light_batch: int
    device: str


def bake_key(item: BakeItem) -> str:
    """Content digest of what a bake depends on (checkpoint, mesh, camera, directions, settings)."""
    from pipeline.itemcache import content_key

    return content_key({"kind": "image", "model": item.model_digest, "mesh": item.mesh_digest,
                        "camera": item.camera.to_dict(), "directions": item.directions, "distance_m": item.distance_m,
                        "centre_head": [float(v) for v in item.centre_head], "rank": item.rank, "steps": item.steps,
                        "light_batch": item.light_batch, "device": torch.device(item.device).type})


def bake_item(item: BakeItem) -> dict:
    """Bake one (view, expression) in a worker: ``ImageBake.to_arrays()`` (``seconds``: the bake alone)."""
    model = worker_model(item)
    geometry = worker_geometry(model, item)
    baked = bake_images(model, geometry, item.camera, fibonacci_sphere(item.directions), rank=item.rank,
                        distance_m=item.distance_m, centre=item.centre_head, steps=item.steps,
                        light_batch=item.light_batch)
    return baked.to_arrays()


def frame_weights(baked: ImageBake, spec: seq.FrameSpec) -> np.ndarray:
    """The weights [D, 3] of a frame's lights over the baked directions (``ValueError`` for a light that is not one)."""
    offsets = np.asarray(spec.light_pos, float) - baked.centre
    return baked.weights_of(offsets, spec.light_rgb)


def render_from_bake(baked: ImageBake, spec: seq.FrameSpec, image_scale: float) -> dict:
    """One frame from the bake, as ``render.render_frame`` returns it: ``{"rgb", "alpha", "seconds"}``."""
    start = time.perf_counter()
    rgb, alpha = baked.frame(frame_weights(baked, spec), image_scale)
    return {"rgb": rgb, "alpha": alpha, "seconds": time.perf_counter() - start}


@dataclass(frozen=True)
class PathChoice:
    """How one sequence renders: ``path`` ``"bake"`` or ``"voxel_sum"`` (the network, every frame), and why."""

    path: str
    reason: str


def choose_paths(sequences: dict[str, list[seq.FrameSpec]], mode: str, min_frames: int,
                 bakeable: str | None) -> dict[str, PathChoice]:
    """The path of every sequence.

    A sequence is baked when it is made of environment-map frames, the light selection is
    bakeable (``bakeable`` None; else the reason it is not) and, in ``mode`` ``"auto"``, at
    least ``min_frames`` environment-map frames of the whole run share its views and
    expressions (one bake serves every map and rotation of a (view, expression); a bake
    costs about as much as a few voxel-space-sum frames). ``"bake"`` bakes every such
    sequence, ``"sum"`` none. Point lights, turntables, dolly zooms, views and expressions
    light the head with a near-field point light: always the network (``voxel_sum``).
    """
    shared: dict[tuple, int] = {}
    for frames in sequences.values():
        for spec in frames:
            if spec.info.get("kind") == "envmap":
                key = view_key(spec)
                shared[key] = shared.get(key, 0) + 1
    out = {}
    for name, frames in sequences.items():
        if not frames or any(f.info.get("kind") != "envmap" for f in frames):
            out[name] = PathChoice("voxel_sum", "near-field point light: the network, every frame")
        elif mode == "sum":
            out[name] = PathChoice("voxel_sum", "relight.envmap_path is 'sum'")
        elif bakeable is not None:
            out[name] = PathChoice("voxel_sum", bakeable)
        elif mode == "bake":
            out[name] = PathChoice("bake", "relight.envmap_path is 'bake'")
        else:
            least = min(shared[view_key(f)] for f in frames)
            if least >= min_frames:
                out[name] = PathChoice("bake", f"{least} envmap frames share its view and expression "
                                               f"(bake_min_frames {min_frames}): one bake serves them all")
            else:
                out[name] = PathChoice("voxel_sum", f"only {least} envmap frames share its view and expression "
                                                    f"(fewer than bake_min_frames {min_frames}): a bake would not pay")
    return out


def view_key(spec: seq.FrameSpec) -> tuple:
    """What a bake is made for: the camera and the driving mesh."""
    cam = spec.camera.to_dict()
    return (repr(sorted(cam.items())), spec.mesh_index)


__all__ = ["BAKE_CODE", "BakeItem", "PathChoice", "bake_item", "bake_key", "choose_paths", "frame_weights",
           "render_from_bake", "view_key"]
