"""The light-transfer bake: a head's response to distant light, for one expression and one view.

With the expression (decoded geometry) and the camera fixed, the render is linear in the
light. Opacity does not depend on the light, so under distant lights with RGB weights ``w_i``
along directions ``d_i`` the image is exactly ``sum_i w_i * image_i``, ``image_i`` the render
under a unit light from ``d_i`` (a far point light, as ``avatar.render.DirectionalLights``
places it). An environment map's lights are such weights: ``scene.envmap.select_uniform``
integrates the map over each uniform direction's Voronoi cell (``RotatingProjection`` does so
for any rotation of a map in microseconds).

``bake_images`` (the image-space bake, what the relight stage uses):

1. decode the RGB voxels of every direction (the network, ``light_batch`` lights at a time:
   the decode the voxel-space sum does on every frame, done once);
2. render all of them through the view's colour transport (``avatar.transport.colour_transport``:
   the raymarch's voxel-to-pixel weights, recorded once; each batch of directions is then one
   sparse product instead of a raymarch per direction);
3. compress the D images to rank R: with ``A`` [D, H*W*3] (one image per row), the top R
   eigenvectors ``U`` [D, R] of ``A A^T`` (its left singular vectors) and the basis
   ``B = U^T A`` [R, H*W*3]; ``U U^T A`` is the best rank-R approximation of A, exact at
   R = D. Opacity is one image, the same under every light.

A frame under weights ``w`` [D, 3] is then ``(U^T w)`` [R, 3] times the basis, per channel:
R * H * W * 3 multiply-adds, no network and no raymarch. ``bake_voxels`` compresses the
decoded voxel grids instead (the voxel-space kind): a frame is a weighted sum of R grids and
one raymarch. Which kind and rank pay is measured (``benchmarks/bench_relight.py``,
docs/experiments.md): the image kind, whose frame costs microseconds to milliseconds where
one raymarch costs tens of ms, on every configuration measured.

What invalidates a bake, and what never enters it:

- **a camera move** re-bakes: the network's colours depend on the view direction (the
  appearance branch takes the camera position), and the image basis is in image space. The
  cost is one bake (the decode of D lights, one transport, one product per light batch, one
  eigendecomposition), about what a few voxel-space-sum frames cost (measured in the bench).
  A turntable (a new view every frame) therefore stays on the voxel-space sum.
- **an expression change** re-bakes: geometry, opacity and appearance all change.
- **a map change or rotation** costs nothing but its projection onto the D directions.
- **near-field point lights** stay on the network path (``avatar.render.render`` with
  ``PointLights``): the network is conditioned on the light's position, and a light 1 m
  away is not a distant one, so no mix of baked directions renders it.

The bake is in the network's training units, like ``render``: ``frame(..., image_scale)``
divides by the model's ``meta["image_scale"]``. Everything is in head space, metres.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from avatar.model import DecodedGeometry, RelightableMVP
from avatar.raymarch import RaymarchKernel, raymarch
from avatar.transport import colour_transport
from avatar.render import PointLights, Rays, decode_lights, render

BakeKind = Literal["image", "voxel"]
BAKE_FORMAT = 1  # the layout of saved bakes (``ImageBake.save``); bump when it changes


def direction_lights(directions: np.ndarray, distance_m: float, centre) -> PointLights:
    """Unit lights ``distance_m`` from ``centre`` along each direction [D, 3] (as ``DirectionalLights.as_points``)."""
    return PointLights(np.asarray(centre, float) + distance_m * np.asarray(directions, float).reshape(-1, 3))


def _rays(model: RelightableMVP, camera) -> Rays:
    return camera if isinstance(camera, Rays) else Rays.of_camera(camera, next(model.parameters()).device)


def _voxel_batches(model: RelightableMVP, geometry: DecodedGeometry, cam_pos: torch.Tensor, lights: PointLights,
                   light_batch: int):
    """(start, RGB voxels [k, P', M, M, M, 3]) per batch of ``light_batch`` lights; P' = the kept primitives."""
    cam = cam_pos.reshape(1, 3)
    for start in range(0, len(lights), max(1, int(light_batch))):
        part = lights[start:start + max(1, int(light_batch))]
        rgb = decode_lights(model, geometry.expand(len(part)), cam.expand(len(part), 3), part)
        yield start, (rgb if geometry.keep is None else rgb[:, geometry.keep])


@dataclass
class DirectionImages:
    """Renders under a unit light from each direction (network units).

    Attributes:
        directions: [D, 3] unit head-space directions towards the lights.
        rgb: [D, H, W, 3] float32 tensor, one image per direction.
        alpha: [H, W] float32 tensor (the same under every light).
    """

    directions: np.ndarray
    rgb: torch.Tensor
    alpha: torch.Tensor


# Above this many ray samples (rays x steps) the transport's weights would not fit in memory
# comfortably (~20 bytes per weight, a few hundred weights per ray): render each direction instead.
TRANSPORT_MAX_SAMPLES = 1 << 26


@torch.no_grad()
def direction_images(model: RelightableMVP, geometry: DecodedGeometry, camera, directions: np.ndarray, *,
                     distance_m: float = 50.0, centre=(0.0, 0.0, 0.0), steps: int | None = None,
                     light_batch: int = 16, method: Literal["auto", "transport", "raymarch"] = "auto",
                     kernel: RaymarchKernel = "auto") -> DirectionImages:
    """The render of ``geometry`` from ``camera`` under a unit light from each direction [D, 3].

    ``method="transport"``: every light batch through one colour transport (fast);
    ``"raymarch"``: ``avatar.render.render`` per direction (the slow, obvious reference);
    ``"auto"``: the transport up to ``TRANSPORT_MAX_SAMPLES`` ray samples (e.g. 96 x 128 x 32),
    one raymarch per direction above (the paper's 1024 x 768 x 128, on a GPU).
    """
    rays = _rays(model, camera)
    steps = int(steps or model.config.steps_per_ray)
    directions = np.asarray(directions, float).reshape(-1, 3)
    lights = direction_lights(directions, distance_m, centre)
    if method == "auto":
        method = "transport" if rays.height * rays.width * steps <= TRANSPORT_MAX_SAMPLES else "raymarch"
    if method == "raymarch":
        images = [render(model, geometry, rays, lights[i:i + 1], steps=steps, kernel=kernel) for i in range(len(lights))]
        return DirectionImages(directions, torch.stack([im.rgb for im in images]), images[0].alpha)
    if method != "transport":
        raise ValueError(f"direction_images: method '{method}' is not one of 'transport', 'raymarch'")
    density = geometry.density
    prims = geometry.primitives(torch.zeros(*density.shape, 3, dtype=density.dtype, device=density.device))
    transport = colour_transport(prims, rays.origins[None], rays.directions[None], steps, kernel=kernel)
    out = torch.empty(len(lights), rays.height * rays.width, 3, dtype=torch.float32, device=density.device)
    for start, rgb in _voxel_batches(model, geometry, rays.position, lights, light_batch):
        k = rgb.shape[0]
        stacked = rgb.permute(1, 2, 3, 4, 0, 5).reshape(*rgb.shape[1:5], k * 3)  # [P, M, M, M, k*3]
        out[start:start + k] = transport.apply(stacked).view(-1, k, 3).transpose(0, 1)  # [k, H*W, 3]
    return DirectionImages(directions, out.view(len(lights), rays.height, rays.width, 3),
                           transport.alpha.view(rays.height, rays.width).float())


def _top_eigenvectors(rows: torch.Tensor, rank: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Left singular vectors [D, R] and all singular values [D] (descending) of ``rows`` [D, N], via its Gram matrix.

    ``U U^T rows`` is then exact at full rank whatever the accuracy of the small singular values.
    """
    a = rows.double()
    gram = a @ a.T  # [D, D]
    values, vectors = torch.linalg.eigh(gram)  # ascending
    order = torch.argsort(values, descending=True)
    singular = values[order].clamp(min=0.0).sqrt()
    return vectors[:, order[:rank]], singular


@dataclass
class ImageBake:
    """A rank-R image-space light-transfer bake of one expression and view (see the module docstring).

    Attributes:
        directions: [D, 3] unit head-space directions of the baked lights.
        distance_m, centre: where those lights were placed (``centre + distance_m * direction``).
        coefficients: [D, R] float32, orthonormal columns: a frame's basis weights are
            ``coefficients.T @ weights``.
        basis: [3, R, H*W] float32, channel-major: ``basis[c, r]`` is channel c of basis image r.
        alpha: [H, W] float32, the opacity of every frame.
        singular_values: [D] the singular values of the full per-direction images (descending):
            ``sqrt(sum of the squares past R)`` is the error of the worst unit weight vector.
        height, width: image size.
        seconds: how long the bake took (0 if unknown).
    """

    directions: np.ndarray
    distance_m: float
    centre: np.ndarray
    coefficients: np.ndarray
    basis: np.ndarray
    alpha: np.ndarray
    singular_values: np.ndarray
    height: int
    width: int
    seconds: float = 0.0

    @property
    def rank(self) -> int:
        return int(self.coefficients.shape[1])

    @property
    def num_directions(self) -> int:
        return int(self.directions.shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes of what a frame reads (basis, coefficients, opacity)."""
        return int(self.basis.nbytes + self.coefficients.nbytes + self.alpha.nbytes)

    @staticmethod
    def from_images(images: DirectionImages, rank: int = 0) -> "ImageBake":
        """Compress per-direction images to rank ``rank`` (0 or >= D: full rank, exact)."""
        d, h, w, _ = images.rgb.shape
        rows = images.rgb.reshape(d, -1)  # [D, H*W*3]
        rank = d if rank <= 0 else min(int(rank), d)
        u, singular = _top_eigenvectors(rows, rank)  # [D, R], [D]
        basis = (u.T @ rows.double()).float()  # [R, H*W*3]
        basis = basis.view(rank, h * w, 3).permute(2, 0, 1).contiguous()  # [3, R, H*W]
        return ImageBake(images.directions, 0.0, np.zeros(3), u.float().cpu().numpy(), basis.cpu().numpy(),
                         images.alpha.cpu().numpy().astype(np.float32), singular.cpu().numpy(), h, w)

    def truncated(self, rank: int) -> "ImageBake":
        """The same bake kept to its first ``rank`` components (the best rank-``rank`` one)."""
        rank = max(1, min(int(rank), self.rank))
        return replace(self, coefficients=np.ascontiguousarray(self.coefficients[:, :rank]),
                       basis=np.ascontiguousarray(self.basis[:, :rank]))

    def frame(self, weights: np.ndarray, image_scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """``(rgb [H, W, 3], alpha [H, W])`` float32 under RGB weights [D, 3] of the baked directions."""
        w = np.asarray(weights, np.float32).reshape(self.num_directions, 3)
        # np.einsum's own loops, one thread: BLAS would spawn threads for these small products,
        # which on a loaded machine costs 100x more than the product itself.
        coef = np.einsum("dr,dc->rc", self.coefficients, w)  # [R, 3]
        if image_scale != 1.0:
            coef *= np.float32(1.0 / image_scale)
        rgb = np.einsum("rc,crp->pc", coef, self.basis)  # [H*W, 3]
        return rgb.reshape(self.height, self.width, 3), self.alpha

    def weights_of(self, directions: np.ndarray, rgb: np.ndarray, tolerance: float = 1e-9) -> np.ndarray:
        """Weights [D, 3] of lights given as directions [K, 3] and RGB [K, 3], each one of the baked directions.

        Raises ``ValueError`` naming the first light that is not a baked direction.
        """
        dirs = np.asarray(directions, float).reshape(-1, 3)
        dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        dots = dirs @ self.directions.T  # [K, D]
        nearest = np.argmax(dots, axis=1)
        off = np.flatnonzero(dots[np.arange(len(dirs)), nearest] < 1.0 - tolerance)
        if off.size:
            raise ValueError(f"bake: light {int(off[0])} (direction {np.round(dirs[off[0]], 4).tolist()}) is not one "
                             f"of the {self.num_directions} baked directions; render it with avatar.render.render")
        out = np.zeros((self.num_directions, 3))
        np.add.at(out, nearest, np.asarray(rgb, float).reshape(-1, 3))
        return out

    # -- as a file: JSON values and numpy arrays only (no pickles), like every cached result ----

    def to_arrays(self) -> dict:
        """The bake as JSON values and numpy arrays (``pipeline.itemcache``'s entry format)."""
        return {"format": BAKE_FORMAT, "kind": "image", "directions": self.directions, "distance_m": self.distance_m,
                "centre": np.asarray(self.centre, float), "coefficients": self.coefficients, "basis": self.basis,
                "alpha": self.alpha, "singular_values": self.singular_values, "height": self.height,
                "width": self.width, "seconds": self.seconds}

    @staticmethod
    def from_arrays(entry: dict) -> "ImageBake":
        """Inverse of ``to_arrays``; ``ValueError`` for another format or kind."""
        if entry.get("format") != BAKE_FORMAT or entry.get("kind") != "image":
            raise ValueError(f"not an image bake of format {BAKE_FORMAT} (format {entry.get('format')}, "
                             f"kind {entry.get('kind')}); bake again")
        return ImageBake(np.asarray(entry["directions"], float), float(entry["distance_m"]),
                         np.asarray(entry["centre"], float), np.asarray(entry["coefficients"], np.float32),
                         np.asarray(entry["basis"], np.float32), np.asarray(entry["alpha"], np.float32),
                         np.asarray(entry["singular_values"], float), int(entry["height"]), int(entry["width"]),
                         float(entry["seconds"]))

    def save(self, path: str | Path, key: str = "") -> None:
        """Write the bake as one ``.npz`` (arrays, plus its metadata and content ``key`` as JSON)."""
        arrays = self.to_arrays()
        meta = {k: v for k, v in arrays.items() if not isinstance(v, np.ndarray)}
        meta["key"] = key
        data = {k: v for k, v in arrays.items() if isinstance(v, np.ndarray)}
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as f:
            np.savez(f, __meta__=np.frombuffer(json.dumps(meta).encode(), np.uint8), **data)
        tmp.replace(path)

    @staticmethod
    def load(path: str | Path, key: str | None = None) -> "ImageBake":
        """Read a saved bake; with ``key``, ``ValueError`` unless it was saved under that key."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as f:
                meta = json.loads(f["__meta__"].tobytes().decode())
                arrays = {k: f[k] for k in f.files if k != "__meta__"}
        except (OSError, ValueError, KeyError) as err:
            raise ValueError(f"{path}: not a readable bake ({err}); delete it and bake again") from err
        if key is not None and meta.get("key") != key:
            raise ValueError(f"{path}: baked for another model, expression, camera or setting (key "
                             f"{str(meta.get('key'))[:12]}, wanted {key[:12]}); bake again")
        return ImageBake.from_arrays({**meta, **arrays})


@torch.no_grad()
def bake_images(model: RelightableMVP, geometry: DecodedGeometry, camera, directions: np.ndarray, *,
                rank: int = 0, distance_m: float = 50.0, centre=(0.0, 0.0, 0.0), steps: int | None = None,
                light_batch: int = 16, kernel: RaymarchKernel = "auto") -> ImageBake:
    """The image-space bake of ``geometry`` seen from ``camera`` under lights from ``directions`` [D, 3]."""
    start = time.perf_counter()
    images = direction_images(model, geometry, camera, directions, distance_m=distance_m, centre=centre,
                              steps=steps, light_batch=light_batch, kernel=kernel)
    baked = ImageBake.from_images(images, rank)
    if images.rgb.is_cuda:
        torch.cuda.synchronize()
    return replace(baked, distance_m=float(distance_m), centre=np.asarray(centre, float),
                   seconds=time.perf_counter() - start)


@dataclass
class VoxelBake:
    """A rank-R voxel-space bake: a frame is the weighted sum of R RGB voxel grids and one raymarch.

    Attributes:
        directions: [D, 3]; coefficients: [D, R] (orthonormal columns); basis: [R, P', M, M, M, 3]
        (the kept primitives'); singular_values: [D]; geometry, rays: what the grids are raymarched
        through; steps: raymarch steps.
    """

    directions: np.ndarray
    coefficients: torch.Tensor
    basis: torch.Tensor
    singular_values: np.ndarray
    geometry: DecodedGeometry
    rays: Rays
    steps: int
    seconds: float = 0.0

    @property
    def rank(self) -> int:
        return int(self.coefficients.shape[1])

    @property
    def nbytes(self) -> int:
        return int(self.basis.numel() * self.basis.element_size() + self.coefficients.numel() * 4)

    def truncated(self, rank: int) -> "VoxelBake":
        rank = max(1, min(int(rank), self.rank))
        return replace(self, coefficients=self.coefficients[:, :rank].contiguous(), basis=self.basis[:rank])

    @torch.no_grad()
    def frame(self, weights: np.ndarray, image_scale: float = 1.0,
              kernel: RaymarchKernel = "auto") -> tuple[np.ndarray, np.ndarray]:
        """``(rgb [H, W, 3], alpha [H, W])`` under RGB weights [D, 3]: one weighted grid sum, one raymarch."""
        w = torch.as_tensor(np.asarray(weights, np.float32).reshape(-1, 3), device=self.basis.device)
        coef = self.coefficients.T @ w  # [R, 3]
        rgb = torch.einsum("rc,rpzyxc->pzyxc", coef, self.basis)[None]  # [1, P', M, M, M, 3]
        g = self.geometry
        prims = g.primitives(torch.zeros(*g.density.shape, 3, dtype=rgb.dtype, device=rgb.device)).with_rgb(rgb)
        res = raymarch(prims, self.rays.origins[None], self.rays.directions[None], self.steps, kernel=kernel)
        h, w_ = self.rays.height, self.rays.width
        return ((res.rgb[0] / image_scale).reshape(h, w_, 3).cpu().numpy().astype(np.float32),
                res.alpha[0].reshape(h, w_).cpu().numpy().astype(np.float32))


@torch.no_grad()
def bake_voxels(model: RelightableMVP, geometry: DecodedGeometry, camera, directions: np.ndarray, *,
                rank: int = 0, distance_m: float = 50.0, centre=(0.0, 0.0, 0.0), steps: int | None = None,
                light_batch: int = 16) -> VoxelBake:
    """The voxel-space bake: the decoded RGB grids of every direction, compressed to rank ``rank``."""
    start = time.perf_counter()
    rays = _rays(model, camera)
    directions = np.asarray(directions, float).reshape(-1, 3)
    lights = direction_lights(directions, distance_m, centre)
    grids = None
    for first, rgb in _voxel_batches(model, geometry, rays.position, lights, light_batch):
        if grids is None:
            grids = torch.empty(len(lights), *rgb.shape[1:], dtype=rgb.dtype, device=rgb.device)
        grids[first:first + rgb.shape[0]] = rgb
    d = len(lights)
    rank = d if rank <= 0 else min(int(rank), d)
    rows = grids.reshape(d, -1)
    u, singular = _top_eigenvectors(rows, rank)
    basis = (u.T @ rows.double()).float().view(rank, *grids.shape[1:])
    return VoxelBake(directions, u.float(), basis, singular.cpu().numpy(), geometry, rays,
                     int(steps or model.config.steps_per_ray), time.perf_counter() - start)


def psnr_db(pred: np.ndarray, reference: np.ndarray, alpha: np.ndarray) -> float:
    """PSNR (dB) of ``pred`` against ``reference`` ([H, W, 3] linear), white = the reference's 99th-percentile head pixel.

    The convention of ``relight_eval`` (head pixels: ``alpha > 0.5``; the whole image if none).
    """
    ref = np.asarray(reference, np.float64)
    head = ref[np.asarray(alpha) > 0.5]
    white = max(float(np.percentile(head if head.size else ref, 99)), 1e-12)
    mse = float(np.mean((np.asarray(pred, np.float64) / white - ref / white) ** 2))
    return float(10.0 * np.log10(1.0 / max(mse, 1e-30)))


__all__ = ["BAKE_FORMAT", "TRANSPORT_MAX_SAMPLES", "BakeKind", "DirectionImages", "ImageBake", "VoxelBake", "bake_images", "bake_voxels",
           "direction_images", "direction_lights", "psnr_db"]
