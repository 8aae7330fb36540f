"""A small randomly initialised relightable head on a sphere, for render tests."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatar.config import AvatarConfig
from avatar.layout import build_layout
from avatar.model import RelightableMVP


def sphere_head(radius_m: float = 0.1):
    """Vertices [V, 3] and triangles [T, 3] of a head-sized sphere at the origin."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=2, radius=radius_m)
    return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int64)


def tiny_model(seed: int = 0, light_basis: int = 0) -> tuple[RelightableMVP, np.ndarray]:
    """A random 8x8-primitive, 4^3-voxel model and the mesh it is anchored on (``light_basis`` > 0: TRAvatar*'s)."""
    torch.manual_seed(seed)
    verts, tris = sphere_head()
    config = AvatarConfig(prims_per_side=8, voxels_per_side=4, latent_dim=16, encoder_hidden=32,
                          base_channels=16, rgb_channels=(16, 12), alpha_channels=(8, 4),
                          geometry_channels=8, steps_per_ray=24, light_basis=light_basis)
    layout = build_layout(verts, tris, config.prims_per_side)
    model = RelightableMVP(config, layout, num_bars=4)
    with torch.no_grad():  # a visibly non-trivial, light-dependent appearance
        for p in model.rgb_branch.parameters():
            p.mul_(3.0)
    return model.eval(), verts


@pytest.fixture(scope="session")
def random_head():
    torch.set_num_threads(1)
    return tiny_model()


def write_relight_inputs(root, expressions: int = 1) -> dict:
    """The relight stage's input folders under ``root`` for ``tiny_model``: the trained model, one
    tracked mesh and a scan set of ``expressions`` poses (neutral, then slightly scaled copies)."""
    from avatar.io import save_trained

    model, verts = tiny_model()
    save_trained(root / "train" / "models" / "ours", model, "ours")
    (root / "track").mkdir()
    np.savez(root / "track" / "meshes.npz", vertices=verts[None])
    (root / "capture" / "scans").mkdir(parents=True)
    names = ["neutral", "smile", "frown", "blink"][:expressions]
    np.savez(root / "capture" / "scans" / "scans.npz", names=np.array(names),
             vertices=np.stack([verts * (1.0 + 0.01 * k) for k in range(expressions)]), faces=np.zeros((1, 3), int))
    return {k: root / k for k in ("train", "track", "capture")}


def fail_on_call(monkeypatch, n: int):
    """Make the ``n``-th frame render (``avatar.render.render`` as the relight worker calls it) raise (a GPU
    failing mid-sequence); returns the original, to put back with ``restore_render`` when the test needs it."""
    from stages.relight import render as relight_render

    original = relight_render.render
    calls = {"n": 0}

    def flaky(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == n:
            raise RuntimeError("GPU fell off the bus")
        return original(*args, **kwargs)

    monkeypatch.setattr(relight_render, "render", flaky)
    return original


def restore_render(monkeypatch, original) -> None:
    """Undo ``fail_on_call``."""
    from stages.relight import render as relight_render

    monkeypatch.setattr(relight_render, "render", original)


def lambertian_head(steps: int = 300, seed: int = 0) -> tuple[RelightableMVP, np.ndarray]:
    """``tiny_model`` with its appearance fitted to a diffuse sphere: 0.05 + max(0, n . l) per primitive.

    A random head's response to a light's position is arbitrary; this one's bright side faces
    the light, so a test can check that moving a light moves the highlight. The fit regresses
    the decoded RGB voxels directly (no raymarch): about 7 s on one core.
    """
    import torch.nn.functional as F

    from avatar.render import decode

    model, verts = tiny_model(seed)
    generator = torch.Generator().manual_seed(seed)
    optimiser = torch.optim.Adam(model.rgb_branch.parameters(), lr=3e-3)
    with torch.no_grad():
        normal = F.normalize(decode(model, verts).centre, dim=-1)  # [1, P, 3]: a sphere's normals
    for _ in range(steps):
        lights = F.normalize(torch.randn(8, 3, generator=generator), dim=-1) * 1.5
        cameras = F.normalize(torch.randn(8, 3, generator=generator), dim=-1) * 0.9
        geometry = decode(model, verts).expand(8)
        rgb = model.decode_rgb(geometry, cameras, lights)  # [8, P, M, M, M, 3]
        to_light = F.normalize(lights[:, None] - geometry.centre, dim=-1)
        target = 0.05 + (normal * to_light).sum(-1).clamp(min=0.0)  # [8, P]
        loss = ((rgb - target[:, :, None, None, None, None]) ** 2).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    return model.eval(), verts
