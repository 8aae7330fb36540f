"""Render a trained relightable head under many lights: the fast voxel-space sum and the naive reference.

Volume rendering is linear in colour once opacity is fixed, and opacity does not depend on
the light (``RelightableMVP.decode_geometry`` holds it). So the image under K lights with
colours ``c_k`` is ``raymarch(sum_k c_k * rgb_k)``: decode the per-light RGB voxel grids in
batches, sum them with the light colours in voxel space, raymarch once (``render_lights``).
``render_lights_naive`` raymarches every light and sums the images; the two agree to float
rounding (tests/stages/relight/test_render.py).

Everything here is in head space: cameras (``cam_from_head`` as the camera's extrinsics)
and light positions are head-space points, as the network was trained on.

``render_frame`` renders one ``FrameItem`` (paths and numbers) in a worker: the stage fans
frames out through its executor (as GPU items on CUDA) and caches each by ``frame_key``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from avatar.model import DecodedGeometry, RelightableMVP
from avatar.raymarch import raymarch
from scene.camera import Camera


@dataclass
class Image:
    """A rendered image: linear RGB [H, W, 3] and accumulated opacity [H, W] (float32 numpy)."""

    rgb: np.ndarray
    alpha: np.ndarray


def camera_rays(camera: Camera, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Head-space rays of every pixel: origins and directions [1, H*W, 3] (camera extrinsics = cam_from_head)."""
    origins, dirs = camera.image_rays()  # [H, W, 3]
    o = torch.as_tensor(origins.reshape(1, -1, 3), dtype=torch.float32, device=device)
    d = torch.as_tensor(dirs.reshape(1, -1, 3), dtype=torch.float32, device=device)
    return o, d


def _expand(geometry: DecodedGeometry, n: int) -> DecodedGeometry:
    """The batch-1 geometry repeated ``n`` times (views, no copies)."""
    return DecodedGeometry(*(t.expand(n, *t.shape[1:]) for t in (
        geometry.centre, geometry.rotation, geometry.half_extent, geometry.density,
        geometry.guide_vertices, geometry.feature)))


class HeadRenderer:
    """A trained model plus what rendering needs (raymarch steps, light batch size, device)."""

    def __init__(self, model: RelightableMVP, steps: int, light_batch: int = 16,
                 device: str | torch.device = "cpu", rgb_scale: float = 1.0) -> None:
        """``rgb_scale`` multiplies rendered RGB: ``1 / meta["image_scale"]`` of the trained model
        turns the network's training units back into the capture's linear units."""
        self.model = model.eval().to(device)
        self.rgb_scale = float(rgb_scale)
        self.steps = int(steps)
        self.light_batch = max(1, int(light_batch))
        self.device = torch.device(device)

    @torch.no_grad()
    def geometry(self, mesh_vertices_head: np.ndarray) -> DecodedGeometry:
        """Decode a tracked / driven mesh [V, 3] (head space, metres): boxes and opacity (batch 1).

        Uses the encoder's mean code (no sampling), as at test time.
        """
        verts = torch.as_tensor(np.asarray(mesh_vertices_head, np.float32)[None], device=self.device)
        mu, _ = self.model.encode(verts)
        return self.model.decode_geometry(mu)

    @torch.no_grad()
    def summed_rgb(self, geometry: DecodedGeometry, cam_pos: np.ndarray, light_pos: np.ndarray,
                   light_rgb: np.ndarray) -> torch.Tensor:
        """Sum over lights of ``light_rgb[k] * rgb_voxels(light k)``, [1, P, M, M, M, 3].

        ``light_pos`` [K, 3] head-space positions, ``light_rgb`` [K, 3] colours/intensities.
        Light decodes run ``light_batch`` at a time.
        """
        pos = torch.as_tensor(np.asarray(light_pos, np.float32).reshape(-1, 3), device=self.device)
        col = torch.as_tensor(np.asarray(light_rgb, np.float32).reshape(-1, 3), device=self.device)
        cam = torch.as_tensor(np.asarray(cam_pos, np.float32).reshape(1, 3), device=self.device)
        total = None
        for start in range(0, len(pos), self.light_batch):
            p, c = pos[start:start + self.light_batch], col[start:start + self.light_batch]
            rgb = self.model.decode_rgb(_expand(geometry, len(p)), cam.expand(len(p), 3), p)  # [b, P, M, M, M, 3]
            part = torch.einsum("bpzyxc,bc->pzyxc", rgb, c)[None]
            total = part if total is None else total + part
        if total is None:
            raise ValueError("render: no lights given")
        return total

    @torch.no_grad()
    def render_lights(self, geometry: DecodedGeometry, camera: Camera, light_pos: np.ndarray,
                      light_rgb: np.ndarray) -> Image:
        """The fast path: one raymarch of the light-summed voxel grids."""
        rays_o, rays_d = camera_rays(camera, self.device)
        rgb = self.summed_rgb(geometry, camera.center_world, light_pos, light_rgb)
        res = raymarch(geometry.primitives(rgb), rays_o, rays_d, self.steps)
        return _image(res.rgb[0] * self.rgb_scale, res.alpha[0], camera)

    @torch.no_grad()
    def render_lights_naive(self, geometry: DecodedGeometry, camera: Camera, light_pos: np.ndarray,
                            light_rgb: np.ndarray) -> Image:
        """The reference: decode and raymarch every light on its own, then sum the images."""
        rays_o, rays_d = camera_rays(camera, self.device)
        pos = np.asarray(light_pos, np.float32).reshape(-1, 3)
        col = np.asarray(light_rgb, np.float32).reshape(-1, 3)
        total = torch.zeros(rays_o.shape[1], 3, dtype=torch.float64, device=self.device)
        alpha = None
        for k in range(len(pos)):
            rgb = self.summed_rgb(geometry, camera.center_world, pos[k:k + 1], col[k:k + 1])
            res = raymarch(geometry.primitives(rgb), rays_o, rays_d, self.steps)
            total += res.rgb[0].double()
            alpha = res.alpha[0]
        if alpha is None:
            raise ValueError("render: no lights given")
        return _image(total.float() * self.rgb_scale, alpha, camera)


def _image(rgb: torch.Tensor, alpha: torch.Tensor, camera: Camera) -> Image:
    h, w = camera.height, camera.width
    return Image(rgb.reshape(h, w, 3).cpu().numpy().astype(np.float32),
                 alpha.reshape(h, w).cpu().numpy().astype(np.float32))


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
    camera: Camera  # cam_from_head extrinsics
    light_pos: np.ndarray  # [K, 3] head space
    light_rgb: np.ndarray  # [K, 3]
    steps: int
    light_batch: int
    rgb_scale: float
    device: str


def frame_key(item: FrameItem) -> str:
    """Content digest of what a frame's image depends on (checkpoint, mesh, camera, lights, settings)."""
    from pipeline.itemcache import content_key

    return content_key({"model": item.model_digest, "mesh": item.mesh_digest, "camera": item.camera.to_dict(),
                        "light_pos": np.asarray(item.light_pos, np.float64).tolist(),
                        "light_rgb": np.asarray(item.light_rgb, np.float64).tolist(), "steps": item.steps,
                        "light_batch": item.light_batch, "rgb_scale": item.rgb_scale,
                        "device": torch.device(item.device).type})


_WORKER: dict[str, object] = {}  # this process's renderer and last decoded geometry


def _renderer(item: FrameItem) -> HeadRenderer:
    from avatar.io import load_trained

    key = (item.model_digest, item.steps, item.light_batch, item.rgb_scale, item.device)
    if _WORKER.get("renderer_key") != key:
        model, _ = load_trained(Path(item.model_dir), item.device)
        _WORKER.update(renderer_key=key, renderer=HeadRenderer(model, item.steps, item.light_batch, item.device,
                                                               rgb_scale=item.rgb_scale), geometry_key=None)
    return _WORKER["renderer"]  # type: ignore[return-value]


def render_frame(item: FrameItem) -> dict:
    """Render one frame with the fast path: ``{"rgb": [H, W, 3], "alpha": [H, W] float32, "seconds"}``.

    ``seconds`` is the render alone (geometry decoding and model loading excluded, as the
    stage's per-frame timings always were).
    """
    renderer = _renderer(item)
    geometry_key = (item.mesh_digest, item.meshes_path, item.mesh_array, item.mesh_index)
    if _WORKER.get("geometry_key") != geometry_key:
        if _WORKER.get("meshes_key") != (item.meshes_path, item.mesh_array):
            with np.load(item.meshes_path) as meshes:  # the whole array once, not once per frame
                _WORKER.update(meshes_key=(item.meshes_path, item.mesh_array), meshes=meshes[item.mesh_array])
        vertices = np.asarray(_WORKER["meshes"][item.mesh_index], np.float32)  # type: ignore[index]
        _WORKER.update(geometry_key=geometry_key, geometry=renderer.geometry(vertices))
    start = time.perf_counter()
    image = renderer.render_lights(_WORKER["geometry"], item.camera, item.light_pos, item.light_rgb)  # type: ignore[arg-type]
    if renderer.device.type == "cuda":
        torch.cuda.synchronize()
    return {"rgb": image.rgb, "alpha": image.alpha, "seconds": time.perf_counter() - start}
