"""One relight frame as an executor item: what a worker needs to render it, its cache key, the render.

Rendering itself is ``avatar.render.render`` (the voxel-space light sum; see there). Everything
here is in head space: cameras posed in the head frame (``cam_from_head``) and light
positions are head-space points, as the network was trained on.

``render_frame`` renders one ``FrameItem`` (paths and numbers) in a worker: the stage fans
frames out through its executor (as GPU items on CUDA) and caches each by ``frame_key``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from avatar.render import PointLights, decode, render
from scene.camera import Camera


# --- One frame as an executor item (cached per frame by the stage) -----------------------------

@dataclass(frozen=True)
class FrameItem:
    """One frame to render, picklable and small: the model and meshes travel as paths.

    ``model_digest`` (the checkpoint folder's content digest) and ``mesh_digest`` (the
    driving mesh's bytes) stand for them in the cache key; a worker loads each once.
    """

    model_dir: str  # a ``save_trained`` folder
    model_digest: str
    meshes_path: str  # an .npz of driving meshes
    mesh_array: str  # its array ("default", "expressions")
    mesh_index: int
    mesh_digest: str
    camera: Camera  # posed in the head frame
    light_pos: np.ndarray  # [K, 3] head space
    light_rgb: np.ndarray  # [K, 3]
    steps: int
    light_batch: int
    image_scale: float  # the model's meta["image_scale"]: renders are divided by it
    device: str


def frame_key(item: FrameItem) -> str:
    """Content digest of what a frame's image depends on (checkpoint, mesh, camera, lights, settings)."""
    from pipeline.itemcache import content_key

    return content_key({"model": item.model_digest, "mesh": item.mesh_digest, "camera": item.camera.to_dict(),
                        "light_pos": np.asarray(item.light_pos, np.float64).tolist(),
                        "light_rgb": np.asarray(item.light_rgb, np.float64).tolist(), "steps": item.steps,
                        "light_batch": item.light_batch, "image_scale": item.image_scale,
                        "device": torch.device(item.device).type})


_WORKER: dict[str, object] = {}  # this process's model and last decoded geometry


def worker_model(item):
    """This worker's copy of ``item``'s model (``model_dir``, ``model_digest``, ``device``), loaded once."""
    from avatar.io import load_trained

    key = (item.model_digest, item.device)
    if _WORKER.get("model_key") != key:
        model, _ = load_trained(Path(item.model_dir), item.device)
        _WORKER.update(model_key=key, model=model, geometry_key=None)
    return _WORKER["model"]


def worker_geometry(model, item):
    """The decoded geometry of ``item``'s driving mesh (``meshes_path``, ``mesh_array``, ``mesh_index``), kept for the next item."""
    geometry_key = (item.mesh_digest, item.meshes_path, item.mesh_array, item.mesh_index)
    if _WORKER.get("geometry_key") != geometry_key:
        if _WORKER.get("meshes_key") != (item.meshes_path, item.mesh_array):
            with np.load(item.meshes_path) as meshes:  # the whole array once, not once per frame
                _WORKER.update(meshes_key=(item.meshes_path, item.mesh_array), meshes=meshes[item.mesh_array])
        vertices = np.asarray(_WORKER["meshes"][item.mesh_index], np.float32)  # type: ignore[index]
        _WORKER.update(geometry_key=geometry_key, geometry=decode(model, vertices))
    return _WORKER["geometry"]


def render_frame(item: FrameItem) -> dict:
    """Render one frame with the voxel-space sum: ``{"rgb": [H, W, 3], "alpha": [H, W] float32, "seconds"}``.

    ``seconds`` is the render alone (geometry decoding and model loading excluded, as the
    stage's per-frame timings always were).
    """
    model = worker_model(item)
    geometry = worker_geometry(model, item)
    start = time.perf_counter()
    rgb, alpha = render(model, geometry, item.camera, PointLights(item.light_pos, item.light_rgb),
                        steps=item.steps, image_scale=item.image_scale, light_batch=item.light_batch).numpy()
    if torch.device(item.device).type == "cuda":
        torch.cuda.synchronize()
    return {"rgb": rgb, "alpha": alpha, "seconds": time.perf_counter() - start}
