"""The relightable MVP model: sizes, layout, decoding, save/load, metrics, LPIPS, TRAvatar* interpolation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatar.config import AvatarConfig
from avatar.io import load_trained, save_trained
from avatar.layout import build_layout, grid_directions, layout_for
from avatar.metrics import exposure_scale, psnr, ssim
from avatar.model import RelightableMVP
from avatar.raymarch import raymarch
from avatar.travatar import LightBasis, direction_uv

SMALL = AvatarConfig(prims_per_side=8, voxels_per_side=4, latent_dim=8, encoder_hidden=32, base_channels=16,
                     rgb_channels=(16, 12), alpha_channels=(8, 4), geometry_channels=8, steps_per_ray=12)


def _sphere(n_lat: int = 24, n_lon: int = 48, radius: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    mesh = trimesh.creation.uv_sphere(radius=radius, count=(n_lat, n_lon))
    return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int64)


@pytest.fixture(scope="module")
def model() -> RelightableMVP:
    verts, faces = _sphere()
    torch.manual_seed(0)
    return RelightableMVP(SMALL, build_layout(verts, faces, SMALL.prims_per_side), num_bars=4)


def test_paper_config_is_the_papers():
    paper = AvatarConfig.paper()
    assert paper.num_prims == 4096 and paper.voxels_per_side == 16 and paper.latent_dim == 256
    assert paper.appearance_layers == 7 and paper.rgb_channels == (256, 128, 128, 64, 64, 32, 48)
    assert AvatarConfig.tiny().appearance_layers == 3  # N*M = 64
    with pytest.raises(ValueError):
        AvatarConfig(prims_per_side=16, voxels_per_side=8, rgb_channels=(8, 8, 24), alpha_channels=(8, 8, 8))  # 4 needed


def test_layout_anchors_lie_on_the_outer_surface():
    verts, faces = _sphere()
    layout = build_layout(verts, faces, 8)
    tri = layout.mean_guide_vertices[layout.anchor_tris]  # [P, 3, 3]
    points = (tri * layout.anchor_bary[..., None]).sum(1)
    radius = np.linalg.norm(points, axis=-1)
    assert np.all(radius > 0.095) and np.all(radius < 0.1001)
    assert points[:, 2].mean() > 0.0  # the grid faces +z (the cameras)
    assert len(layout.guide_vertex_ids) <= 3 * 64


def test_latlong_grid_rows_are_elevations_and_columns_azimuths():
    d = grid_directions(8, "latlong", 90.0, (-60.0, 60.0)).reshape(8, 8, 3)
    el = np.rad2deg(np.arcsin(d[..., 1]))
    az = np.rad2deg(np.arctan2(d[..., 0], d[..., 2]))
    np.testing.assert_allclose(el[:, 0], np.linspace(60, -60, 8), atol=1e-9)  # row 0 at the top
    np.testing.assert_allclose(az[0], np.linspace(-90, 90, 8), atol=1e-9)  # actor's right to left
    np.testing.assert_allclose(el, el[:, :1].repeat(8, 1), atol=1e-9)


def test_azimuthal_grid_is_equidistant_from_its_centre_and_reaches_over_the_crown():
    n, centre_el = 9, 20.0
    d = grid_directions(n, "azimuthal", 100.0, (-70.0, 110.0), centre_el).reshape(n, n, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    front = np.array([0.0, np.sin(np.deg2rad(centre_el)), np.cos(np.deg2rad(centre_el))])
    x = np.linspace(-100, 100, n)
    y = np.linspace(110, -70, n) - centre_el
    dist = np.rad2deg(np.arccos(np.clip(d @ front, -1, 1)))
    np.testing.assert_allclose(dist, np.hypot(x[None], y[:, None]), atol=1e-6)  # angle from the centre = grid radius
    mid = n // 2
    np.testing.assert_allclose(d[:, mid, 0], 0.0, atol=1e-12)  # the central column is the front meridian ...
    assert d[0, mid, 1] > 0.9 and d[0, mid, 2] < 0.0  # ... whose top is past the vertical, over the crown
    assert np.all(np.diff(d[mid, :, 0]) > 0)  # columns go from -x to +x
    with pytest.raises(ValueError, match="under 180"):
        grid_directions(8, "azimuthal", 150.0, (-90.0, 150.0))
    with pytest.raises(ValueError, match="projection"):
        grid_directions(8, "mercator")


def test_azimuthal_layout_covers_the_top_of_the_head_the_latlong_leaves_out():
    verts, faces = _sphere()

    def closest_to_the_top_deg(config: AvatarConfig) -> float:
        layout = layout_for(config, verts, faces)
        points = (layout.mean_guide_vertices[layout.anchor_tris] * layout.anchor_bary[..., None]).sum(1)
        return float(np.rad2deg(np.arccos(points[:, 1] / np.linalg.norm(points, axis=-1))).min())

    latlong = SMALL.model_copy(update={"prims_per_side": 16})  # only the grid matters here
    assert closest_to_the_top_deg(latlong) > 19.0  # the latlong grid stops at its top row, 70 degrees up
    azimuthal = latlong.model_copy(update={"layout_projection": "azimuthal", "layout_centre_elevation_deg": 20.0,
                                         "layout_elevation_deg": (-75.0, 100.0)})
    assert closest_to_the_top_deg(azimuthal) < 15.0


def test_decoded_primitives_sit_on_the_guide_mesh(model):
    mesh = torch.as_tensor(_sphere()[0])[None]
    mu, logvar = model.encode(mesh)
    geo = model.decode_geometry(mu)
    assert geo.centre.shape == (1, 64, 3) and geo.density.shape == (1, 64, 4, 4, 4)
    # At initialisation the deltas are zero: centres are on the sphere, boxes 1.1 x their base size.
    assert torch.allclose(geo.centre.norm(dim=-1), torch.full((1, 64), 0.1), atol=5e-3)
    torch.testing.assert_close(geo.half_extent[0, :, 0], 1.1 * model.half_extent_m)
    eye = torch.eye(3).expand(1, 64, 3, 3)
    torch.testing.assert_close(geo.rotation.transpose(-1, -2) @ geo.rotation, eye, atol=1e-5, rtol=0)


def test_direction_image_is_constant_per_primitive_tile(model):
    mu, _ = model.encode(torch.as_tensor(_sphere()[0])[None])
    geo = model.decode_geometry(mu)
    cam, light = torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([[0.5, 0.5, 0.5]])
    image = model.direction_image(geo, cam, light)  # [1, 6, 32, 32]
    tile = image[0, :, 4:8, 8:12]  # primitive (row 1, column 2)
    assert torch.allclose(tile, tile[:, :1, :1].expand_as(tile))
    k = 1 * 8 + 2
    expected = torch.nn.functional.normalize(light[0] - geo.centre[0, k], dim=0)
    torch.testing.assert_close(tile[3:, 0, 0], expected)
    rgb = model.decode_rgb(geo, cam, light)
    assert rgb.shape == (1, 64, 4, 4, 4, 3) and bool((rgb >= 0).all())


def test_untied_biases_start_at_zero_and_move_one_texel_each():
    verts, faces = _sphere()
    layout = build_layout(verts, faces, SMALL.prims_per_side)
    heads = {}
    for untied in (False, True):
        torch.manual_seed(0)
        heads[untied] = RelightableMVP(SMALL.model_copy(update={"untied_bias": untied}), layout, num_bars=4)
    # One bias per output pixel of every transposed conv: rgb 16x16 and 32x32, alpha the same (N=8, M=4).
    extra = sum(p.numel() for p in heads[True].parameters()) - sum(p.numel() for p in heads[False].parameters())
    assert extra == 16 * 16 ** 2 + 12 * 32 ** 2 + 8 * 16 ** 2 + 4 * 32 ** 2
    mesh = torch.as_tensor(verts)[None]
    cam, light = torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([[0.5, 0.5, 0.5]])

    def decoded(head: RelightableMVP) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.no_grad():
            geo = head.decode_geometry(head.encode(mesh)[0])
            return geo.density, head.decode_rgb(geo, cam, light)

    tied, untied = decoded(heads[False]), decoded(heads[True])
    torch.testing.assert_close(untied[0], tied[0], rtol=0, atol=0)  # the same head until trained
    torch.testing.assert_close(untied[1], tied[1], rtol=0, atol=0)
    with torch.no_grad():  # texel (row 5, column 9), channel 0 = voxel z 0, red
        heads[True].rgb_branch.untied[-1][0, 0, 5, 9] += 1.0
    rgb = decoded(heads[True])[1]
    changed = torch.nonzero(rgb != untied[1]).tolist()
    assert changed == [[0, 1 * 8 + 2, 0, 1, 1, 0]]  # primitive (1, 2), voxel (z 0, y 1, x 1), red
    assert rgb[0, 10, 0, 1, 1, 0] > untied[1][0, 10, 0, 1, 1, 0]


def test_primitive_frame_directions_carry_the_cosine_to_the_normal():
    """direction_frame='primitive' feeds R_k^T v_k, R_k^T l_k: the same vectors, the normal cosine in channel z."""
    verts, faces = _sphere()
    layout = build_layout(verts, faces, SMALL.prims_per_side)
    torch.manual_seed(0)
    world = RelightableMVP(SMALL, layout, num_bars=4)
    torch.manual_seed(0)
    local = RelightableMVP(SMALL.model_copy(update={"direction_frame": "primitive"}), layout, num_bars=4)
    mu, _ = world.encode(torch.as_tensor(verts)[None])
    geo = world.decode_geometry(mu)
    cam, light = torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([[0.5, 0.5, 0.5]])
    img_w, img_l = world.direction_image(geo, cam, light), local.direction_image(geo, cam, light)
    m = SMALL.voxels_per_side
    per_prim_w = img_w[0, :, ::m, ::m].reshape(6, -1).T.reshape(-1, 2, 3)  # [P, (view, light), 3]
    per_prim_l = img_l[0, :, ::m, ::m].reshape(6, -1).T.reshape(-1, 2, 3)
    rot = geo.rotation[0]  # [P, 3, 3] columns = the primitive's axes
    torch.testing.assert_close(per_prim_l, torch.einsum("pji,pkj->pki", rot, per_prim_w), atol=1e-6, rtol=0)
    # The third axis is the guide triangle's normal: the light's z channel is n.l.
    normal = rot[:, :, 2]  # [P, 3]
    torch.testing.assert_close(per_prim_l[:, 1, 2], (normal * per_prim_w[:, 1]).sum(-1), atol=1e-6, rtol=0)
    assert not torch.allclose(img_w, img_l)
    # Lengths are unchanged (a rotation), so both are unit directions.
    torch.testing.assert_close(per_prim_l.norm(dim=-1), torch.ones(per_prim_l.shape[:2]), atol=1e-5, rtol=0)


def test_light_sum_in_voxel_space_equals_sum_of_renders(model):
    """Opacity does not depend on light: summing RGB voxels of K lights then raymarching once is exact."""
    mu, _ = model.encode(torch.as_tensor(_sphere()[0])[None])
    geo = model.decode_geometry(mu)
    cam = torch.tensor([[0.0, 0.0, 0.6]])
    lights = torch.tensor([[0.5, 0.2, 0.5], [-0.4, 0.0, 0.6], [0.0, 0.6, 0.3]])
    weights = torch.tensor([0.5, 1.5, 0.25])
    o = cam.expand(1, 50, 3).contiguous()
    d = torch.nn.functional.normalize(torch.randn(1, 50, 3) * 0.1 + torch.tensor([0.0, 0.0, -1.0]), dim=-1)
    rgbs = list(model.decode_rgb(geo.expand(3), cam.expand(3, 3), lights)[:, None])  # one batched decode
    torch.testing.assert_close(rgbs[1], model.decode_rgb(geo, cam, lights[1:2]), rtol=1e-5, atol=1e-6)
    summed = raymarch(geo.primitives(sum(w * x for w, x in zip(weights, rgbs))), o, d, 12).rgb
    separate = sum(w * raymarch(geo.primitives(x), o, d, 12).rgb for w, x in zip(weights, rgbs))
    torch.testing.assert_close(summed, separate, rtol=1e-4, atol=1e-6)


def test_save_and_load_round_trip(model, tmp_path):
    with torch.no_grad():
        model.log_bar_intensity[1] = 0.3
    save_trained(tmp_path / "m", model, "ours", {"note": 1})
    loaded, meta = load_trained(tmp_path / "m")
    assert meta["kind"] == "ours" and meta["note"] == 1
    mesh = torch.as_tensor(_sphere()[0])[None]
    a = model.decode_geometry(model.encode(mesh)[0]).centre
    b = loaded.decode_geometry(loaded.encode(mesh)[0]).centre
    torch.testing.assert_close(a, b)
    assert float(loaded.bar_intensity(torch.tensor([1])).detach()) == pytest.approx(np.exp(0.3))


def test_metrics_known_values():
    target = torch.rand(2, 16, 16, 3)
    noisy = target + 0.1
    assert torch.allclose(psnr(noisy, target), torch.full((2,), 20.0), atol=1e-4)
    assert torch.allclose(ssim(target, target), torch.ones(2))
    assert float(ssim(noisy + torch.randn_like(noisy) * 0.2, target).max()) < 0.9
    torch.testing.assert_close(exposure_scale(target * 0.5, target), torch.full((2,), 2.0))


def test_lpips_is_zero_for_identical_and_grows_with_noise():
    from avatar.lpips import DEFAULT_WEIGHTS, LPIPS

    if not DEFAULT_WEIGHTS.exists():
        pytest.skip("assets/lpips/alexnet.safetensors not present")
    lpips = LPIPS()
    g = torch.Generator().manual_seed(0)
    img = torch.rand(1, 64, 64, 3, generator=g)
    small = (img + 0.03 * torch.randn(img.shape, generator=g)).clamp(0, 1)
    large = (img + 0.3 * torch.randn(img.shape, generator=g)).clamp(0, 1)
    assert float(lpips(img, img)) < 1e-6
    assert 0.0 < float(lpips(img, small)) < float(lpips(img, large))


def test_travatar_interpolation_weights():
    az = np.deg2rad([-60, 0, 60, -30, 30, 0])
    el = np.deg2rad([-20, -30, -20, 40, 40, 10])
    dirs = np.stack([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)], -1)
    basis = LightBasis(dirs)
    # A basis light reproduces its one-hot weights.
    np.testing.assert_allclose(basis.weights(dirs[1:2]), basis.one_hot(np.array([1])), atol=1e-9)
    # A direction inside the hull: three non-negative weights summing to one that reproduce it.
    q_az, q_el = np.deg2rad(10.0), np.deg2rad(5.0)
    query = np.array([[np.cos(q_el) * np.sin(q_az), np.sin(q_el), np.cos(q_el) * np.cos(q_az)]])
    w = basis.weights(query)[0]
    assert (w > 0).sum() <= 3 and np.all(w >= 0) and w.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(w @ direction_uv(dirs), direction_uv(query)[0], atol=1e-9)


def test_an_expression_basis_keeps_the_code_blind_to_other_directions(tmp_path):
    import dataclasses

    from avatar.layout import expression_basis

    verts, faces = _sphere()
    layout = build_layout(verts, faces, SMALL.prims_per_side)
    u = layout.mean_guide_vertices.shape[0]
    rng = np.random.default_rng(0)
    # Training offsets (metres) along two directions of the guide vertices, plus jitter far smaller.
    directions = rng.normal(size=(2, u, 3))
    weights = rng.normal(size=(12, 2))
    offsets = np.einsum("fk,kuc->fuc", weights, directions) * 1e-3 + rng.normal(size=(12, u, 3)) * 1e-7
    basis = expression_basis(offsets, 2)
    np.testing.assert_allclose(basis @ basis.T, np.eye(2), atol=1e-5)
    torch.manual_seed(0)
    plain = RelightableMVP(SMALL, layout, num_bars=4)
    torch.manual_seed(0)
    projected = RelightableMVP(SMALL, dataclasses.replace(layout, expression_basis=basis), num_bars=4)

    def encoded(model, offsets_m):
        mesh = torch.as_tensor((layout.mean_guide_vertices + offsets_m).astype(np.float32))[None]
        return model.encode(mesh)[0]

    along = offsets[3]
    across = rng.normal(size=(u, 3)) * 1e-3
    across_flat = across.reshape(-1) - basis.T.astype(np.float64) @ (basis.astype(np.float64) @ across.reshape(-1))
    across = across_flat.reshape(u, 3)
    with torch.no_grad():
        # Along the basis the projection changes (nearly) nothing: the same weights give the same code.
        torch.testing.assert_close(encoded(projected, along), encoded(plain, along), atol=1e-4, rtol=1e-3)
        # Across it, the projected encoder does not see the move; the plain one does.
        torch.testing.assert_close(encoded(projected, along + across), encoded(projected, along), atol=1e-5, rtol=0)
        assert float((encoded(plain, along + across) - encoded(plain, along)).abs().max()) > 1e-3
    # The basis is saved with the head and read back.
    save_trained(tmp_path / "m", projected, "ours")
    loaded, _ = load_trained(tmp_path / "m")
    torch.testing.assert_close(loaded.expression_basis, projected.expression_basis)
    with torch.no_grad():
        torch.testing.assert_close(encoded(loaded, along + across), encoded(projected, along), atol=1e-5, rtol=0)


def test_expression_basis_refuses_more_modes_than_the_offsets_span():
    from avatar.layout import expression_basis

    offsets = np.zeros((5, 10, 3))
    offsets[:, 0, 0] = np.arange(5)
    with pytest.raises(ValueError, match="fewer than 2 directions"):
        expression_basis(offsets, 2)
