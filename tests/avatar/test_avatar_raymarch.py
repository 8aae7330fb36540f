"""The raymarcher: both fast paths (tensor ops, fused C++) vs the reference, gradients vs finite
differences, an opaque primitive, and the fused kernel's fallback when it cannot be built."""

from __future__ import annotations

import pytest
import torch
from scipy.spatial.transform import Rotation

import avatar.raymarch_fused as fused
from avatar.raymarch import Primitives, local_frames, raymarch, raymarch_reference


def _scene(b: int = 2, p: int = 6, m: int = 4, r: int = 40, density: float = 3.0, seed: int = 0,
           dtype=torch.float64) -> tuple[Primitives, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    centre = torch.randn(b, p, 3, generator=g, dtype=dtype) * 0.3
    rot = torch.tensor(Rotation.random(b * p, random_state=seed).as_matrix(), dtype=dtype).view(b, p, 3, 3)
    half = torch.rand(b, p, 3, generator=g, dtype=dtype) * 0.3 + 0.2
    rgb = torch.rand(b, p, m, m, m, 3, generator=g, dtype=dtype)
    den = torch.rand(b, p, m, m, m, generator=g, dtype=dtype) * density
    origins = torch.zeros(b, r, 3, dtype=dtype)
    origins[..., 2] = -3.0
    dirs = torch.randn(b, r, 3, generator=g, dtype=dtype) * 0.15
    dirs[..., 2] = 1.0
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    return Primitives(centre, rot, half, rgb, den), origins, dirs


def _gradients(res, weights: torch.Tensor, leaves: list[torch.Tensor]) -> tuple[torch.Tensor, ...]:
    """Gradients of a weighted sum of a render's colour, plus its opacity, with respect to ``leaves``."""
    return torch.autograd.grad((res.rgb * weights).sum() + res.alpha.sum(), leaves)


def test_fast_path_matches_reference_forward_and_backward(kernel):
    prims, o, d = _scene(density=6.0)  # dense enough that many rays saturate (early termination)
    leaves = [prims.rgb.requires_grad_(), prims.density.requires_grad_(), prims.centre.requires_grad_(),
              prims.half_extent.requires_grad_(), prims.rotation.requires_grad_()]
    fast = raymarch(prims, o, d, steps=24, kernel=kernel)
    ref = raymarch_reference(prims, o, d, steps=24)
    assert (ref.alpha > 0.999).any() and (ref.alpha < 0.5).any()
    torch.testing.assert_close(fast.rgb, ref.rgb, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(fast.alpha, ref.alpha, rtol=1e-9, atol=1e-10)
    w = torch.rand_like(fast.rgb)
    for a, b in zip(_gradients(fast, w, leaves), _gradients(ref, w, leaves)):
        torch.testing.assert_close(a, b, rtol=1e-7, atol=1e-9)


def test_chunked_rays_match_unchunked(kernel):
    prims, o, d = _scene()
    whole = raymarch(prims, o, d, steps=16, kernel=kernel)
    chunked = raymarch(prims, o, d, steps=16, max_pairs=2 * 6 * 7, kernel=kernel)  # 7 rays per chunk
    torch.testing.assert_close(whole.rgb, chunked.rgb)


def test_gradients_match_finite_differences(kernel):
    # Low density: no ray saturates, so the image is smooth in every input.
    prims, o, d = _scene(b=1, p=3, m=3, r=12, density=0.5, seed=3)

    def render(rgb, density):
        res = raymarch(Primitives(prims.centre, prims.rotation, prims.half_extent, rgb, density), o, d, steps=10,
                       kernel=kernel)
        return torch.cat([res.rgb.flatten(), res.alpha.flatten()])

    inputs = (prims.rgb.clone().requires_grad_(), prims.density.clone().requires_grad_())
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_geometry_gradients_match_finite_differences(kernel):
    # Sample placement is not differentiated (as in MVP): the ray's span comes from the boxes
    # it hits. Add a large empty box around everything so the span, and hence the samples,
    # stay fixed while the small boxes move; then the image is smooth in their pose.
    prims, o, d = _scene(b=1, p=3, m=3, r=12, density=0.5, seed=3)
    m = 3
    big = Primitives(torch.zeros(1, 1, 3, dtype=torch.float64), torch.eye(3, dtype=torch.float64).expand(1, 1, 3, 3),
                     torch.full((1, 1, 3), 2.0, dtype=torch.float64), torch.zeros(1, 1, m, m, m, 3, dtype=torch.float64),
                     torch.zeros(1, 1, m, m, m, dtype=torch.float64))

    def render(centre, half):
        cat = [torch.cat([a, b], 1) for a, b in zip(
            (centre, prims.rotation, half, prims.rgb, prims.density),
            (big.centre, big.rotation, big.half_extent, big.rgb, big.density))]
        res = raymarch(Primitives(*cat), o, d, steps=24, kernel=kernel)
        return torch.cat([res.rgb.flatten(), res.alpha.flatten()])

    inputs = (prims.centre.clone().requires_grad_(), prims.half_extent.clone().requires_grad_())
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_constant_opaque_primitive_renders_its_colour(kernel):
    m = 4
    colour = torch.tensor([0.2, 0.5, 0.9])
    prims = Primitives(centre=torch.zeros(1, 1, 3), rotation=torch.eye(3).expand(1, 1, 3, 3).clone(),
                       half_extent=torch.full((1, 1, 3), 0.1), rgb=colour.expand(1, 1, m, m, m, 3).clone(),
                       density=torch.full((1, 1, m, m, m), 1e4))
    origins = torch.tensor([[[0.0, 0.0, -1.0], [0.05, -0.03, -1.0], [0.3, 0.0, -1.0]]])
    dirs = torch.tensor([[[0.0, 0.0, 1.0]] * 3])
    for res in (raymarch(prims, origins, dirs, steps=16, kernel=kernel), raymarch_reference(prims, origins, dirs, 16)):
        torch.testing.assert_close(res.rgb[0, :2], colour.expand(2, 3), rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(res.alpha[0, :2], torch.ones(2))
        assert float(res.alpha[0, 2]) == 0.0 and float(res.rgb[0, 2].abs().sum()) == 0.0  # misses the box


def test_a_batch_in_which_no_ray_hits_a_box_renders_empty_with_gradients(kernel):
    # No (sample, box) pair at all: the lookups run on empty tensors (the trainer's reach term renders such rays).
    prims, o, d = _scene(b=1, p=3, r=5)
    o = o + torch.tensor([50.0, 0.0, 0.0], dtype=o.dtype)  # every ray passes far to the side of every box
    prims.centre.requires_grad_()
    res = raymarch(prims, o, d, steps=8, kernel=kernel)
    assert float(res.alpha.detach().abs().max()) == 0.0 and float(res.rgb.detach().abs().max()) == 0.0
    (res.rgb.sum() + res.alpha.sum()).backward()
    assert prims.centre.grad is None or float(prims.centre.grad.abs().max()) == 0.0


def test_colour_is_linear_for_fixed_opacity(kernel):
    """The basis of the voxel-space light sum: render(rgb1 + rgb2) = render(rgb1) + render(rgb2)."""
    prims, o, d = _scene(density=6.0)
    rgb2 = torch.rand_like(prims.rgb)
    both = raymarch(prims.with_rgb(prims.rgb + 0.5 * rgb2), o, d, steps=16, kernel=kernel).rgb
    apart = (raymarch(prims, o, d, steps=16, kernel=kernel).rgb
             + 0.5 * raymarch(prims.with_rgb(rgb2), o, d, steps=16, kernel=kernel).rgb)
    torch.testing.assert_close(both, apart)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_gpu_fast_path_matches_cpu_reference():
    prims, o, d = _scene(density=6.0, dtype=torch.float32)
    ref = raymarch_reference(prims, o, d, steps=24)
    cuda = Primitives(*(t.cuda() for t in (prims.centre, prims.rotation, prims.half_extent, prims.rgb, prims.density)))
    fast = raymarch(cuda, o.cuda(), d.cuda(), steps=24)
    torch.testing.assert_close(fast.rgb.cpu(), ref.rgb, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(fast.alpha.cpu(), ref.alpha, rtol=1e-4, atol=1e-5)


def test_fused_and_tensor_paths_agree_in_float32_and_on_misses_and_empty_rays(fused_kernel):
    prims, o, d = _scene(b=3, p=20, m=5, r=200, density=8.0, seed=5, dtype=torch.float32)
    o[1, :50] = torch.tensor([0.0, 5.0, -3.0])  # these rays miss every box: black, transparent, no gradient
    leaves = [x.requires_grad_() for x in (prims.rgb, prims.density, prims.centre, prims.half_extent)]
    a = raymarch(prims, o, d, steps=32, kernel=fused_kernel)
    b = raymarch(prims, o, d, steps=32, kernel="torch")
    assert float(a.alpha.detach()[1, :50].abs().max()) == 0.0 and float(a.rgb.detach()[1, :50].abs().max()) == 0.0
    torch.testing.assert_close(a.rgb, b.rgb, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(a.alpha, b.alpha, rtol=1e-5, atol=1e-5)
    w = torch.rand_like(a.rgb)
    for x, y in zip(_gradients(a, w, leaves), _gradients(b, w, leaves)):
        torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-4 * float(y.abs().max()))


def test_fused_prim_stats_match_the_tensor_path(fused_kernel):
    prims, o, d = _scene(density=6.0)
    a = raymarch(prims, o, d, steps=24, kernel=fused_kernel, prim_stats=True)
    b = raymarch(prims, o, d, steps=24, kernel="torch", prim_stats=True)
    assert (b.prim_alpha > 0.999).any() and (b.prim_alpha == 0).any()
    torch.testing.assert_close(a.prim_alpha, b.prim_alpha, rtol=1e-9, atol=1e-12)


def test_auto_falls_back_to_tensor_ops_when_the_kernel_cannot_be_built(monkeypatch, caplog):
    def no_compiler():
        raise RuntimeError("Error building extension: c++: command not found")

    monkeypatch.setattr(fused, "_module", None)
    monkeypatch.setattr(fused, "_build_error", None)
    monkeypatch.setattr(fused, "_build", no_compiler)
    prims, o, d = _scene()
    with caplog.at_level("WARNING"):
        res = raymarch(prims, o, d, steps=16, kernel="auto")
        raymarch(prims, o, d, steps=16, kernel="auto")
    warnings = [r for r in caplog.records if "fused raymarcher unavailable" in r.getMessage()]
    assert len(warnings) == 1 and "c++: command not found" in warnings[0].getMessage()  # once per process
    torch.testing.assert_close(res.rgb, raymarch(prims, o, d, steps=16, kernel="torch").rgb)
    with pytest.raises(fused.FusedKernelUnavailable, match="apt-get install g\\+\\+"):
        raymarch(prims, o, d, steps=16, kernel="fused")


def test_unknown_kernel_is_refused():
    prims, o, d = _scene()
    with pytest.raises(ValueError, match="'cuda' is not one of auto, fused, torch"):
        raymarch(prims, o, d, steps=16, kernel="cuda")


def test_fused_kernel_stops_each_ray_once_it_is_opaque(fused_kernel):
    """Samples past opacity 1 are never read: NaN voxels hidden behind an opaque box change no output or gradient.

    The tensor path reads them (and turns NaN); the fused kernel stops each ray at its first
    sample past opacity 1, which skips work without changing a bit of what it computes.
    """
    dtype = torch.float64
    centre = torch.tensor([[[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]], dtype=dtype)  # front box, then one behind it
    rotation = torch.eye(3, dtype=dtype).expand(1, 2, 3, 3).clone()
    half = torch.full((1, 2, 3), 0.4, dtype=dtype)
    g = torch.Generator().manual_seed(0)
    rgb = torch.rand(1, 2, 4, 4, 4, 3, generator=g, dtype=dtype)
    density = torch.rand(1, 2, 4, 4, 4, generator=g, dtype=dtype) + 20.0  # ~8 of opacity through the front box
    origins = torch.zeros(1, 16, 3, dtype=dtype)
    origins[..., 2] = -3.0
    origins[..., :2] = torch.rand(1, 16, 2, generator=g, dtype=dtype) * 0.4 - 0.2
    dirs = torch.tensor([0.0, 0.0, 1.0], dtype=dtype).expand(1, 16, 3)

    def render(hidden: float, kernel: str):
        colour, sigma = rgb.clone(), density.clone()
        colour[:, 1], sigma[:, 1] = hidden, hidden
        leaves = [colour.requires_grad_(), sigma.requires_grad_()]
        res = raymarch(Primitives(centre, rotation, half, colour, sigma), origins, dirs, steps=16, kernel=kernel)
        return res, _gradients(res, torch.ones_like(res.rgb), leaves)

    nan_img, nan_grads = render(float("nan"), fused_kernel)
    img, grads = render(0.7, fused_kernel)
    assert bool((img.alpha == 1.0).all())
    for a, b in zip((nan_img.rgb, nan_img.alpha, *nan_grads), (img.rgb, img.alpha, *grads)):
        assert bool(torch.isfinite(a).all())
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert float(grads[0][:, 0].abs().sum()) > 0 and float(grads[0][:, 1].abs().sum()) == 0
    tensor_img, _ = render(float("nan"), "torch")  # control: the hidden voxels do lie on the rays' samples
    assert bool(torch.isnan(tensor_img.rgb).any())


def test_fused_kernel_keeps_rays_that_only_clip_a_box_corner(fused_kernel):
    """The kernel culls boxes by their bounding sphere before the slab test; a ray through a corner is kept."""
    dtype = torch.float64
    rot = torch.tensor(Rotation.from_euler("xyz", [30, 40, 50], degrees=True).as_matrix(), dtype=dtype)
    half = torch.tensor([0.3, 0.2, 0.1], dtype=dtype)
    signs = torch.tensor([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=dtype)
    corners = (signs * half * 0.98) @ rot.T  # [8, 3] just inside each corner, head space
    g = torch.Generator().manual_seed(1)
    dirs = torch.nn.functional.normalize(torch.randn(8, 3, generator=g, dtype=dtype), dim=-1)
    # Rays through those points along random directions, from 3 m back: each passes close to |half| from the centre.
    origins = corners - 3.0 * dirs
    prims = Primitives(torch.zeros(1, 1, 3, dtype=dtype), rot[None, None], half[None, None],
                       torch.rand(1, 1, 2, 2, 2, 3, generator=g, dtype=dtype),
                       torch.full((1, 1, 2, 2, 2), 5.0, dtype=dtype))
    fused_res = raymarch(prims, origins[None], dirs[None], steps=8, kernel=fused_kernel)
    tensor_res = raymarch(prims, origins[None], dirs[None], steps=8, kernel="torch")
    assert bool((tensor_res.alpha > 0).all())  # every ray does cross the box
    torch.testing.assert_close(fused_res.alpha, tensor_res.alpha, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(fused_res.rgb, tensor_res.rgb, rtol=1e-9, atol=1e-12)


def test_fused_kernel_keeps_every_box_of_a_ray_that_crosses_more_than_its_first_guess(fused_kernel):
    """The candidate search first keeps 64 boxes a ray; a ray through 100 stacked boxes must keep all 100."""
    dtype = torch.float64
    p = 100
    g = torch.Generator().manual_seed(2)
    centre = torch.zeros(1, p, 3, dtype=dtype)
    centre[0, :, 2] = torch.linspace(-1.0, 1.0, p, dtype=dtype)  # a column of thin boxes along z
    half = torch.tensor([0.2, 0.2, 0.01], dtype=dtype).expand(1, p, 3).contiguous()
    rot = torch.eye(3, dtype=dtype).expand(1, p, 3, 3).contiguous()
    prims = Primitives(centre, rot, half, torch.rand(1, p, 2, 2, 2, 3, generator=g, dtype=dtype),
                       torch.rand(1, p, 2, 2, 2, generator=g, dtype=dtype) * 0.5)
    origins = torch.tensor([[[0.0, 0.0, -3.0], [0.05, -0.05, -3.0], [3.0, 0.0, -3.0]]], dtype=dtype)
    dirs = torch.tensor([[[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]], dtype=dtype)  # the last misses
    module = fused.fused_module(required=True)
    local_from_head, centre_local = (x.contiguous() for x in local_frames(prims))
    cand, *_ = module.candidates(origins, dirs, local_from_head, centre_local, centre, half.norm(dim=-1))
    assert cand.shape == (3, p) and bool((cand[:2] == torch.arange(p)).all()) and bool((cand[2] == -1).all())
    leaves = [prims.rgb.requires_grad_(), prims.density.requires_grad_()]
    a = raymarch(prims, origins, dirs, steps=256, kernel=fused_kernel)
    b = raymarch(prims, origins, dirs, steps=256, kernel="torch")
    torch.testing.assert_close(a.rgb, b.rgb, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(a.alpha, b.alpha, rtol=1e-9, atol=1e-12)
    w = torch.rand_like(a.rgb)
    for x, y in zip(_gradients(a, w, leaves), _gradients(b, w, leaves)):
        torch.testing.assert_close(x, y, rtol=1e-7, atol=1e-10)


def test_a_lock_file_left_by_a_killed_build_is_cleared_not_waited_on(tmp_path, caplog):
    build_dir = tmp_path / "ext"
    build_dir.mkdir()
    (build_dir / "lock").touch()  # what torch's file lock leaves when its build is killed
    with caplog.at_level("WARNING", logger="avatar.raymarch_fused"):
        with fused._exclusive_build(build_dir):
            assert not (build_dir / "lock").exists()
    assert any("killed" in r.getMessage() and "lock" in r.getMessage() for r in caplog.records)
    caplog.clear()
    with fused._exclusive_build(build_dir):  # nothing stale: nothing said
        pass
    assert not caplog.records
