"""Pruning empty primitives: the raymarcher's per-primitive opacity and the model's pruned rendering."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatar.config import AvatarConfig
from avatar.io import load_trained, save_trained
from avatar.layout import build_layout
from avatar.model import RelightableMVP
from avatar.raymarch import Primitives, raymarch

SMALL = AvatarConfig(prims_per_side=8, voxels_per_side=4, latent_dim=8, encoder_hidden=32, base_channels=16,
                     rgb_channels=(16, 12), alpha_channels=(8, 4), geometry_channels=8, steps_per_ray=32)


def _row_of_boxes(densities: list[float], m: int = 3) -> Primitives:
    """Boxes of half size 0.1 at x = 0, 0.5, 1.0, ... (one per density), seen along -z."""
    p = len(densities)
    centre = torch.zeros(1, p, 3, dtype=torch.float64)
    centre[0, :, 0] = torch.arange(p, dtype=torch.float64) * 0.5
    rot = torch.eye(3, dtype=torch.float64).expand(1, p, 3, 3).clone()
    half = torch.full((1, p, 3), 0.1, dtype=torch.float64)
    rgb = torch.rand(1, p, m, m, m, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    density = torch.tensor(densities, dtype=torch.float64).view(1, p, 1, 1, 1).expand(1, p, m, m, m).clone()
    return Primitives(centre, rot, half, rgb, density)


def _rays_at(xs: list[float], y: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    o = torch.tensor([[[x, y, 2.0] for x in xs]], dtype=torch.float64)
    d = torch.tensor([[[0.0, 0.0, -1.0]] * len(xs)], dtype=torch.float64)
    return o, d


def test_prim_alpha_is_the_opacity_a_primitive_adds(kernel):
    prims = _row_of_boxes([2.0, 0.0, 2.0])  # the middle box is empty
    o, d = _rays_at([0.0, 0.5, 1.0, 0.05])
    res = raymarch(prims, o, d, steps=32, prim_stats=True, kernel=kernel)
    plain = raymarch(prims, o, d, steps=32, kernel=kernel)
    torch.testing.assert_close(res.rgb, plain.rgb)  # the statistics change nothing
    # One box per ray: the opacity it adds is the ray's alpha (1 - nothing before it).
    assert float(res.prim_alpha[0, 1]) == 0.0
    torch.testing.assert_close(res.prim_alpha[0, 0], res.alpha[0, [0, 3]].max())
    torch.testing.assert_close(res.prim_alpha[0, 2], res.alpha[0, 2])
    assert float(res.prim_alpha[0, 0]) > 0.3


def test_prim_alpha_ignores_boxes_behind_an_opaque_one_and_survives_chunking(kernel):
    prims = _row_of_boxes([200.0, 1.0])
    prims.centre[0, 1] = torch.tensor([0.0, 0.0, -0.5], dtype=torch.float64)  # behind box 0 along the rays
    o, d = _rays_at([0.0, 0.02, -0.03])
    res = raymarch(prims, o, d, steps=64, prim_stats=True, kernel=kernel)
    assert float(res.alpha.min()) == 1.0
    assert float(res.prim_alpha[0, 0]) == 1.0 and float(res.prim_alpha[0, 1]) == 0.0
    chunked = raymarch(prims, o, d, steps=64, max_pairs=2, prim_stats=True, kernel=kernel)  # one ray per chunk
    torch.testing.assert_close(chunked.prim_alpha, res.prim_alpha)


def _sphere(radius: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    mesh = trimesh.creation.uv_sphere(radius=radius, count=(24, 48))
    return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int64)


def test_pruned_model_renders_the_same_images_with_fewer_boxes(tmp_path):
    verts, faces = _sphere()
    torch.manual_seed(0)
    model = RelightableMVP(SMALL, build_layout(verts, faces, SMALL.prims_per_side), num_bars=2).eval()
    mesh = torch.as_tensor(verts)[None]
    cam = torch.tensor([[0.0, 0.0, 0.6]])
    light = torch.tensor([[0.3, 0.3, 0.6]])
    # A narrow cone of rays from the front: it sees only the front primitives.
    g = torch.Generator().manual_seed(1)
    d = torch.nn.functional.normalize(torch.randn(1, 400, 3, generator=g) * 0.05
                                      + torch.tensor([0.0, 0.0, -1.0]), dim=-1)
    o = cam.expand(1, 400, 3).contiguous()
    with torch.no_grad():
        geo = model.decode_geometry(model.encode(mesh)[0])
        assert geo.keep is None
        rgb = model.decode_rgb(geo, cam, light)
        before = raymarch(geo.primitives(rgb), o, d, SMALL.steps_per_ray, prim_stats=True)
        keep = before.prim_alpha[0] >= 0.01
        visible = int(before.prim_alpha[0].argmax())
        empty = int(before.prim_alpha[0].argmin())
        assert float(before.prim_alpha[0, empty]) == 0.0  # a primitive on the far side: no ray reaches it
        pruned = model.prune(keep)
        assert pruned == int((~keep).sum()) and 0 < pruned < model.prim_keep.numel()
        assert not bool(model.prim_keep[empty]) and bool(model.prim_keep[visible])
        geo2 = model.decode_geometry(model.encode(mesh)[0])
        prims2 = geo2.primitives(model.decode_rgb(geo2, cam, light))
        assert prims2.centre.shape[1] == SMALL.num_prims - pruned
        after = raymarch(prims2, o, d, SMALL.steps_per_ray)
    # Dropping boxes that add < 1% opacity to any ray changes a pixel's opacity by about that
    # much at most; its colour changes a little more because the ray's span through the
    # remaining boxes, hence the sample positions, shrinks (resampling, not lost content).
    assert float((after.alpha - before.alpha).abs().max()) < 0.02
    peak = float(before.rgb.max())
    psnr_db = float(-10.0 * torch.log10(((after.rgb - before.rgb) ** 2).mean() / peak ** 2))
    assert psnr_db > 40.0
    # Pruning only accumulates, and survives save / load.
    assert model.prune(torch.ones_like(keep)) == pruned
    save_trained(tmp_path / "m", model, "ours")
    loaded, _ = load_trained(tmp_path / "m")
    assert torch.equal(loaded.prim_keep, model.prim_keep)


def test_heads_saved_before_pruning_still_load():
    verts, faces = _sphere()
    model = RelightableMVP(SMALL, build_layout(verts, faces, SMALL.prims_per_side), num_bars=2)
    state = {k: v for k, v in model.state_dict().items() if k != "prim_keep"}
    model.prune(torch.zeros(SMALL.num_prims, dtype=torch.bool))
    model.load_state_dict(state)
    assert bool(model.prim_keep.all()) and model.kept_index() is None
