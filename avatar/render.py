"""The public render API: a trained head, a driving mesh, a camera and lights -> an image.

``render(model, mesh, camera, lights)`` decodes the mesh (or takes an already decoded
``DecodedGeometry``), decodes the RGB voxels of every light and raymarches. Lights are

- ``PointLights``: head-space positions [K, 3] with RGB intensities [K, 3];
- ``DirectionalLights``: unit directions [K, 3] with RGB weights [K, 3] (an environment
  map's lights), placed as point lights far away along their direction (the network takes
  a light position: ``DirectionalLights.as_points``);
- ``BasisLights``: TRAvatar* only, weights [K, L] over its training-light basis fed to the
  network as they are (a one-hot row is one training light, as in training).

The voxel-space sum (``method="voxel_sum"``, the default): volume rendering is linear in
colour once opacity is fixed, and opacity does not depend on the light
(``RelightableMVP.decode_geometry`` holds it). So the image under K lights with colours
``c_k`` is ``raymarch(sum_k c_k * rgb_k)``: decode the per-light RGB voxel grids
``light_batch`` at a time, sum them with the light colours in voxel space, raymarch once.
``method="per_light"`` is the slow reference: decode and raymarch every light on its own
and sum the images (in float64); the two agree to float rounding.

The TRAvatar* baseline (``model.config.light_basis > 0``) needs its ``LightBasis``
(``LightBasis(meta["basis_directions"])`` of the saved model): point and directional lights
are blended barycentrically over the basis (``avatar.travatar.interpolated_rgb``).

Everything is in head space, metres: cameras are posed in the head frame (``cam_from_head``), light
positions are head-space points. Images are linear RGB in the network's training units;
``image_scale`` (the trained model's ``meta["image_scale"]``) divides them back into the
capture's units.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Sequence, Union

import numpy as np
import torch

from avatar.model import DecodedGeometry, RelightableMVP
from avatar.raymarch import RaymarchKernel, raymarch
from avatar.travatar import LightBasis, interpolated_rgb

ArrayLike = Union[np.ndarray, torch.Tensor, Sequence]

RenderMethod = Literal["voxel_sum", "per_light"]


def _tensor(x: ArrayLike, columns: int, device: torch.device) -> torch.Tensor:
    """``x`` as a tensor [K, columns] on ``device``: a tensor keeps its dtype, anything else becomes float32."""
    if isinstance(x, torch.Tensor):
        return x.to(device=device).reshape(-1, columns)
    return torch.as_tensor(np.asarray(x, np.float32).reshape(-1, columns), device=device)


def _rows(x, index: slice):
    return None if x is None else x[index]


def _table(x: ArrayLike | None, columns: int):
    """``x`` as rows [K, columns]: a tensor stays a tensor (a view), anything else becomes a float64 array."""
    if x is None:
        return None
    if isinstance(x, torch.Tensor):
        return x.reshape(-1, columns)
    return np.asarray(x, float).reshape(-1, columns)


def _gains(x: ArrayLike | None):
    """Per-light gains as [K]: a tensor stays a tensor (a view), anything else becomes a float32 array."""
    if x is None:
        return None
    if isinstance(x, torch.Tensor):
        return x.reshape(-1)
    return np.asarray(x, np.float32).reshape(-1)


def _check_rows(lights, table) -> None:
    """Every per-light table of ``lights`` has one row per light."""
    k = int(table.shape[0])
    for name in ("rgb", "intensity"):
        value = getattr(lights, name)
        if value is not None and int(value.shape[0]) != k:
            raise ValueError(f"{type(lights).__name__}: {name} has {int(value.shape[0])} rows for {k} lights")


@dataclass(frozen=True)
class PointLights:
    """K point lights.

    Attributes:
        positions: [K, 3] head-space positions, metres.
        rgb: [K, 3] RGB intensities multiplying the network's unit light (a training bar at
            its own distance); None: unit white lights, each light's voxels summed as decoded.
        intensity: [K] or None: a gain per light applied inside the decoder
            (``RelightableMVP.decode_rgb``'s ``intensity``, e.g. the learnt bar intensities).
    """

    positions: ArrayLike
    rgb: ArrayLike | None = None
    intensity: ArrayLike | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "positions", _table(self.positions, 3))
        object.__setattr__(self, "rgb", _table(self.rgb, 3))
        object.__setattr__(self, "intensity", _gains(self.intensity))
        _check_rows(self, self.positions)

    def __len__(self) -> int:
        return int(self.positions.shape[0])

    def __getitem__(self, index: slice) -> "PointLights":
        return PointLights(self.positions[index], _rows(self.rgb, index), _rows(self.intensity, index))


@dataclass(frozen=True)
class DirectionalLights:
    """K distant lights: unit directions [K, 3] towards each light (head space) and RGB weights [K, 3].

    The network takes light positions, so a directional light is rendered as a point light
    ``distance_m`` from ``centre`` along its direction (as ``scene.envmap``'s
    ``positions_world`` places them). The network was trained on bars 1-1.5 m away, so very
    distant lights extrapolate.
    """

    directions: ArrayLike
    rgb: ArrayLike
    distance_m: float = 50.0
    centre: ArrayLike = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        d = self.directions
        d = d.detach().cpu().numpy() if isinstance(d, torch.Tensor) else d
        object.__setattr__(self, "directions", np.asarray(d, float).reshape(-1, 3))
        object.__setattr__(self, "rgb", _table(self.rgb, 3))

    def as_points(self) -> PointLights:
        """The same lights as far point lights."""
        positions = np.asarray(self.centre, float) + self.distance_m * self.directions
        return PointLights(positions, self.rgb)

    def __len__(self) -> int:
        return int(self.directions.shape[0])


@dataclass(frozen=True)
class BasisLights:
    """TRAvatar* only: K lights as weights [K, L] over the model's light basis, fed to the network as they are.

    A one-hot row is a training light, decoded exactly as in training. ``rgb`` and
    ``intensity`` as in ``PointLights``.
    """

    weights: ArrayLike
    rgb: ArrayLike | None = None
    intensity: ArrayLike | None = None

    def __post_init__(self) -> None:
        w = self.weights
        object.__setattr__(self, "weights", w if isinstance(w, torch.Tensor) else np.asarray(w, float))
        object.__setattr__(self, "rgb", _table(self.rgb, 3))
        object.__setattr__(self, "intensity", _gains(self.intensity))
        if self.weights.ndim != 2:
            raise ValueError(f"BasisLights: weights must be [K, L], got shape {tuple(self.weights.shape)}")
        _check_rows(self, self.weights)

    def __len__(self) -> int:
        return int(self.weights.shape[0])

    def __getitem__(self, index: slice) -> "BasisLights":
        return BasisLights(self.weights[index], _rows(self.rgb, index), _rows(self.intensity, index))


Lights = Union[PointLights, DirectionalLights, BasisLights]


@dataclass(frozen=True)
class Rays:
    """The head-space rays of an image: origins and directions [H*W, 3], the camera centre [3], the image size."""

    origins: torch.Tensor
    directions: torch.Tensor
    position: torch.Tensor
    height: int
    width: int

    @staticmethod
    def of_camera(camera, device: str | torch.device = "cpu") -> "Rays":
        """Every pixel's ray of a ``scene.camera.Camera`` posed in the head frame (``cam_from_head``).

        A camera posed in another frame raises ``ValueError`` (the avatar lives in head space).
        """
        camera.cam_from("head")  # refuses a camera posed in another frame
        origins, dirs = camera.image_rays()  # [H, W, 3], head space
        o = torch.as_tensor(origins.reshape(-1, 3), dtype=torch.float32, device=device)
        d = torch.as_tensor(dirs.reshape(-1, 3), dtype=torch.float32, device=device)
        position = torch.as_tensor(np.asarray(camera.center, np.float32).reshape(3), device=device)
        return Rays(o, d, position, int(camera.height), int(camera.width))


@dataclass
class Image:
    """A rendered image: linear RGB [H, W, 3] and accumulated opacity [H, W] (float32 tensors on the model's device)."""

    rgb: torch.Tensor
    alpha: torch.Tensor

    def numpy(self) -> tuple[np.ndarray, np.ndarray]:
        """``(rgb [H, W, 3], alpha [H, W])`` as float32 numpy arrays."""
        return (self.rgb.cpu().numpy().astype(np.float32), self.alpha.cpu().numpy().astype(np.float32))


def _device(model: RelightableMVP) -> torch.device:
    return next(model.parameters()).device


@torch.no_grad()
def decode(model: RelightableMVP, mesh_head: ArrayLike) -> DecodedGeometry:
    """Boxes and opacity (batch 1) of a tracked / driven mesh [V, 3] (head space, metres; or guide vertices).

    Uses the encoder's mean code (no sampling), as at test time.
    """
    device = _device(model)
    if isinstance(mesh_head, torch.Tensor):
        verts = mesh_head.to(device=device, dtype=torch.float32)
    else:
        verts = torch.as_tensor(np.asarray(mesh_head, np.float32), device=device)
    if verts.dim() == 2:
        verts = verts[None]
    mu, _ = model.encode(verts)
    return model.decode_geometry(mu)


def decode_lights(model: RelightableMVP, geometry: DecodedGeometry, cam_pos: torch.Tensor,
                  lights: PointLights | BasisLights, basis: LightBasis | None = None) -> torch.Tensor:
    """RGB voxels [B, P, M, M, M, 3] of one light per batch item (``len(lights)`` = B, ``cam_pos`` [B, 3]).

    Ours: from the light positions. TRAvatar*: ``BasisLights`` decoded with their weights as
    given; point lights blended over ``basis``. ``lights.rgb`` is not applied here (see
    ``summed_voxels``); ``lights.intensity`` is.
    """
    if isinstance(lights, DirectionalLights):
        lights = lights.as_points()
    device, intensity = cam_pos.device, lights.intensity
    if intensity is not None and not isinstance(intensity, torch.Tensor):
        intensity = torch.as_tensor(intensity, device=device)
    if model.config.light_basis == 0:
        if not isinstance(lights, PointLights):
            raise ValueError("render: the relightable model (ours) takes point or directional lights, not BasisLights")
        return model.decode_rgb(geometry, cam_pos, _tensor(lights.positions, 3, device), intensity=intensity)
    if isinstance(lights, BasisLights):
        w = lights.weights
        weights = (w.to(device=device, dtype=cam_pos.dtype) if isinstance(w, torch.Tensor)
                   else torch.as_tensor(np.asarray(w), dtype=cam_pos.dtype, device=device))
        return model.decode_rgb(geometry, cam_pos, light_weights=weights, intensity=intensity)
    if basis is None:
        raise ValueError("render: a TRAvatar* model needs its light basis: basis=LightBasis(meta['basis_directions'])")
    w = basis.weights(_tensor(lights.positions, 3, device).detach().cpu().numpy())
    weights = torch.as_tensor(w, dtype=cam_pos.dtype, device=device)
    return interpolated_rgb(model, geometry, cam_pos, weights, intensity)


@torch.no_grad()
def summed_voxels(model: RelightableMVP, geometry: DecodedGeometry, cam_pos: torch.Tensor, lights: Lights,
                  basis: LightBasis | None = None, light_batch: int = 16) -> torch.Tensor:
    """Sum over lights of ``rgb[k] * rgb_voxels(light k)``, [1, P, M, M, M, 3], for a batch-1 ``geometry``.

    Lights decode ``light_batch`` at a time; ``cam_pos`` [3] (or [1, 3]) is the camera centre.
    """
    if isinstance(lights, DirectionalLights):
        lights = lights.as_points()
    cam = cam_pos.reshape(1, 3)
    light_batch = max(1, int(light_batch))
    total = None
    for start in range(0, len(lights), light_batch):
        part = lights[start:start + light_batch]
        k = len(part)
        rgb = decode_lights(model, geometry.expand(k), cam.expand(k, 3), part, basis)  # [k, P, M, M, M, 3]
        if part.rgb is None:
            summed = rgb.sum(0, keepdim=True)
        else:
            summed = torch.einsum("bpzyxc,bc->pzyxc", rgb, _tensor(part.rgb, 3, cam.device).to(rgb.dtype))[None]
        total = summed if total is None else total + summed
    if total is None:
        raise ValueError("render: no lights given")
    return total


@torch.no_grad()
def render(model: RelightableMVP, mesh: ArrayLike | DecodedGeometry, camera, lights: Lights, *,
           basis: LightBasis | None = None, steps: int | None = None, image_scale: float = 1.0,
           light_batch: int = 16, kernel: RaymarchKernel = "auto", method: RenderMethod = "voxel_sum") -> Image:
    """Render ``model`` driven by ``mesh`` from ``camera`` under ``lights``.

    Args:
        model: a trained ``RelightableMVP`` (ours or TRAvatar*), on the device to render on.
        mesh: the driving mesh [V, 3] (head space, metres), or its ``decode(model, mesh)``.
        camera: a ``scene.camera.Camera`` posed in the head frame (``cam_from_head``) or ``Rays``.
        lights: ``PointLights``, ``DirectionalLights`` or (TRAvatar*) ``BasisLights``.
        basis: TRAvatar*'s light basis (needed for point and directional lights).
        steps: raymarch steps per ray (None: ``model.config.steps_per_ray``).
        image_scale: the model's ``meta["image_scale"]``; rendered RGB is multiplied by its inverse.
        light_batch: lights decoded at once.
        kernel: the raymarcher (``avatar.raymarch.raymarch``'s ``kernel``).
        method: ``"voxel_sum"`` (one raymarch) or ``"per_light"`` (the slow reference).
    """
    if method not in ("voxel_sum", "per_light"):
        raise ValueError(f"render: method '{method}' is not one of 'voxel_sum', 'per_light'")
    geometry = mesh if isinstance(mesh, DecodedGeometry) else decode(model, mesh)
    rays = camera if isinstance(camera, Rays) else Rays.of_camera(camera, _device(model))
    steps = int(steps or model.config.steps_per_ray)
    scale = 1.0 / float(image_scale)
    rays_o, rays_d = rays.origins[None], rays.directions[None]
    if method == "voxel_sum":
        rgb = summed_voxels(model, geometry, rays.position, lights, basis, light_batch)
        res = raymarch(geometry.primitives(rgb), rays_o, rays_d, steps, kernel=kernel)
        return _image(res.rgb[0] * scale, res.alpha[0], rays)
    if isinstance(lights, DirectionalLights):
        lights = lights.as_points()
    total = torch.zeros(rays_o.shape[1], 3, dtype=torch.float64, device=rays_o.device)
    alpha = None
    for k in range(len(lights)):
        rgb = summed_voxels(model, geometry, rays.position, lights[k:k + 1], basis, light_batch)
        res = raymarch(geometry.primitives(rgb), rays_o, rays_d, steps, kernel=kernel)
        total += res.rgb[0].double()
        alpha = res.alpha[0]
    if alpha is None:
        raise ValueError("render: no lights given")
    return _image(total.float() * scale, alpha, rays)


def _image(rgb: torch.Tensor, alpha: torch.Tensor, rays: Rays) -> Image:
    return Image(rgb.reshape(rays.height, rays.width, 3), alpha.reshape(rays.height, rays.width))


__all__ = ["BasisLights", "DirectionalLights", "Image", "Lights", "PointLights", "Rays", "RenderMethod", "decode",
           "decode_lights", "render", "summed_voxels"]
