"""The virtual studio's renderer: determinism, lighting geometry, coverage alpha, shadows."""


import numpy as np
import pytest

from hardware.studio import RenderSettings, VirtualStudio, make_performance, make_subject, scan_session
from hardware.studio.performance import FrameState
from scene.camera import Rigid
from scene.lights import DirectionalLight, LightBar, PointLight
from scene.rig import default_rig

SCALE = 0.125  # 96 x 128 images: fast, still a recognisable head


@pytest.fixture(scope="module")
def setup():
    rig = default_rig()
    subject = make_subject("test", seed=3, texture_size=128)
    frames = make_performance(seed=3, frames_per_take=6)
    cams = rig.cameras_at(SCALE)
    return rig, subject, frames, cams


def _still_frame(rig) -> FrameState:
    return FrameState(0, "still", 0.0, np.zeros(57, np.float32), Rigid(np.eye(3), np.asarray(rig.head_center_m)))


def test_same_frame_twice_is_identical_and_noise_is_seeded(setup):
    rig, subject, frames, cams = setup
    a = VirtualStudio(rig, subject, RenderSettings(seed=5)).render(frames[2], cams[1], 7)
    b = VirtualStudio(rig, subject, RenderSettings(seed=5)).render(frames[2], cams[1], 7)
    np.testing.assert_array_equal(a.rgb, b.rgb)
    np.testing.assert_array_equal(a.alpha, b.alpha)
    c = VirtualStudio(rig, subject, RenderSettings(seed=6)).render(frames[2], cams[1], 7)
    assert not np.array_equal(a.rgb, c.rgb)  # another seed: other noise
    assert a.rgb.dtype == np.float32 and a.rgb.shape == (cams[1].height, cams[1].width, 3)


def test_light_on_the_subjects_left_brightens_the_image_right(setup):
    rig, subject, _, cams = setup
    studio = VirtualStudio(rig, subject, RenderSettings(shot_noise_gain=0, read_noise=0))
    bars = rig.light_bars()
    left_bar = max(bars, key=lambda b: b.center_world[0] - abs(b.center_world[1]))  # +x: subject's left
    right_bar = min(bars, key=lambda b: b.center_world[0] + abs(b.center_world[1]))
    frame = _still_frame(rig)
    front = cams[0]  # looking along -z: the subject's left (+x) is the image's right
    img = studio.render(frame, front, left_bar.id).rgb.sum(-1)
    half = front.width // 2
    assert img[:, half:].sum() > 3 * img[:, :half].sum()
    img = studio.render(frame, front, right_bar.id).rgb.sum(-1)
    assert img[:, :half].sum() > 3 * img[:, half:].sum()


def test_alpha_is_pixel_coverage(setup):
    rig, subject, _, cams = setup
    studio = VirtualStudio(rig, subject, RenderSettings(edge_samples=4, shot_noise_gain=0, read_noise=0))
    frame = _still_frame(rig)
    cam = cams[3]
    res = studio.render(frame, cam, "F")
    # Reference coverage: 10 x 10 regular samples per pixel.
    n = 10
    offs = (np.arange(n) + 0.5) / n - 0.5
    jj, ii = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    ox, oy = np.meshgrid(offs, offs)
    sub = np.stack([jj[..., None] + ox.ravel(), ii[..., None] + oy.ravel()], -1)  # [H, W, n*n, 2]
    o, d = cam.pixel_rays(sub.reshape(-1, 2))
    hit = studio.geometry(frame).trace(o, d)["primID"] >= 0
    coverage = hit.reshape(cam.height, cam.width, n * n).mean(-1)
    assert np.abs(res.alpha - coverage).mean() < 0.01
    edge = (coverage > 0.05) & (coverage < 0.95)
    assert edge.sum() > 50 and np.abs(res.alpha - coverage)[edge].mean() < 0.15
    assert ((res.alpha > 0) & (res.alpha < 1)).sum() > 50  # antialiased silhouette
    assert (res.rgb.sum(-1)[res.alpha == 0] == 0).all()  # black backdrop (no noise here)


def test_cast_shadows(setup):
    rig, subject, _, cams = setup
    frame = _still_frame(rig)
    side = [b.id for b in rig.light_bars() if abs(b.center_world[0]) > 0.9][0]
    quiet = dict(shot_noise_gain=0, read_noise=0)
    lit = VirtualStudio(rig, subject, RenderSettings(**quiet)).render(frame, cams[0], side).rgb.sum(-1)
    ref = VirtualStudio(rig, subject, RenderSettings(shadows=False, **quiet)).render(frame, cams[0], side).rgb.sum(-1)
    assert (lit <= ref + 1e-6).all()  # shadows only remove light
    darker = (ref > 1e-3) & (lit < 0.5 * ref)
    assert darker.sum() > 0.03 * (ref > 1e-3).sum()  # the nose and head cast visible shadows


def test_light_list_point_and_directional(setup):
    rig, subject, _, cams = setup
    studio = VirtualStudio(rig, subject, RenderSettings(shot_noise_gain=0, read_noise=0))
    frame = _still_frame(rig)
    bar = rig.light_bars()[12]
    # A very short bar equals a Lambertian point light of the same (scaled) intensity.
    short = LightBar(99, bar.center_world, bar.axis_world, 1e-6, bar.intensity, bar.normal_world)
    point = PointLight(bar.center_world, [bar.intensity * studio.settings.bar_intensity_scale] * 3, bar.normal_world)
    a = studio.render_lights(frame, cams[0], [short], noise=False).rgb
    b = studio.render_lights(frame, cams[0], [point], noise=False).rgb
    np.testing.assert_allclose(a, b, atol=1e-5)
    # Light adds up: two lights render as the sum of each.
    sun = DirectionalLight([0.0, 1.0, 1.0], [0.5, 0.5, 0.5])
    both = studio.render_lights(frame, cams[0], [point, sun], noise=False).rgb
    alone = studio.render_lights(frame, cams[0], [sun], noise=False).rgb
    np.testing.assert_allclose(both, b + alone, atol=1e-5)


def test_scans_and_performance(setup):
    rig, subject, frames, _ = setup
    names, verts, faces = scan_session(subject)
    assert names[0] == "neutral" and verts.shape == (len(names), 26719, 3) and faces.shape[1] == 3
    assert 6 <= len(names) - 1 <= 10
    assert np.abs(verts).max() < 0.3  # metres, head space
    assert [f.take for f in frames] == ["rom"] * 6 + ["speech"] * 6
    again = make_performance(seed=3, frames_per_take=6)
    for f, g in zip(frames, again):
        np.testing.assert_array_equal(f.expression_weights, g.expression_weights)
    w = np.stack([f.expression_weights for f in frames])
    assert w.min() >= 0 and w.max() <= 1.0 + 1e-6 and w.max() > 0.05
    angles = [np.degrees(np.linalg.norm(f.world_from_head.rotvec())) for f in frames]
    assert 0 < max(angles) < 10  # small natural head motion


def test_batched_lighting_matches_the_reference(setup):
    from hardware.studio.renderer import reference_local_lights

    rig, subject, frames, cams = setup
    studio = VirtualStudio(rig, subject, RenderSettings(bar_samples=2))
    cam = cams[2].scaled(0.3)  # ~29 x 38: the reference is a slow per-sample loop
    geom = studio.geometry(frames[1])
    hits, _, _ = studio._primary(geom, cam)
    bars = rig.light_bars()
    lights = [bars[3], bars[20], PointLight([0.3, 0.4, 0.9], [0.2, 0.3, 0.4]),
              PointLight([-0.5, 0.0, 0.8], [0.1, 0.1, 0.1], normal_world=[0.5, 0.0, -0.8])]
    fast, rays = studio._local_lights(geom, hits, lights, 2, (1, 2, 3), chunk=97)  # odd chunks on purpose
    slow = reference_local_lights(studio, geom, hits, lights, 2, (1, 2, 3))
    assert rays > 0 and np.abs(slow).max() > 0
    np.testing.assert_allclose(fast, slow, rtol=1e-9, atol=1e-12)
