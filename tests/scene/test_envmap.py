"""Environment maps: orientation against OrientationLatLong.exr, integrals, masking, selection, bad files."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from scene.envmap import (AdaptiveParams, BackMask, EnvMap, EnvMapError, EnvMapWarning, RotatingProjection,
                          direction_to_pixel,
                          fibonacci_sphere, pixel_directions, pixel_solid_angles_sr, read_envmap, select_adaptive,
                          select_uniform, synthetic_sky, uniform_solid_angles_sr, weighted_radiance,
                          write_envmap, _voronoi_cells)

ROOT = Path(__file__).resolve().parents[2]
ORIENTATION = ROOT / "assets/envmaps/openexr-images/OrientationLatLong.exr"
BLENDER = ROOT / "assets/envmaps/blender-cc0"


# ---- orientation ---------------------------------------------------------------------------------
# What a person sees in OrientationLatLong.exr (1024 x 512): along the equator four views of a
# drawn axis cross, each labelled below in black with the axis it looks along: "+X" near
# column 240, "+Z" near 528, "-X" near 784, "-Z" near 1006. From each view's centre a dark-red
# line runs along the equator towards the +X or +Z view (the world's +x / +z axes, drawn) and a
# vertical dark-red line runs up towards "Y" (+y). The tests below find those markings at the
# pixels our convention assigns to world +x, +z, -x, -z, +y.

@pytest.fixture(scope="module")
def orientation_rgb() -> np.ndarray:
    return read_envmap(ORIENTATION).radiance


def _label_sign(rgb: np.ndarray, col: float) -> str:
    """Read the sign ('+' or '-') of the black axis label printed below the equator near ``col``."""
    h, w, _ = rgb.shape
    cols = np.arange(int(col) - 45, int(col) + 46) % w
    box = rgb[int(0.51 * h):int(0.59 * h)][:, cols].max(-1) < 0.3  # [rows, 91] black ink
    ink = box.sum(0)
    inked = np.flatnonzero(ink)
    assert inked.size, f"no label near column {col}"
    # Glyphs are separated by blank columns; the first glyph is the sign.
    first = [inked[0]]
    for c in inked[1:]:
        if c != first[-1] + 1:
            break
        first.append(c)
    tallest = int(ink[first].max())  # a '+' has a vertical stroke, a '-' is 1-2 rows high
    return "+" if tallest >= 6 else "-"


@pytest.mark.parametrize("axis,sign", [((1, 0, 0), "+"), ((0, 0, 1), "+"), ((-1, 0, 0), "-"), ((0, 0, -1), "-")])
def test_axis_labels_sit_where_our_directions_map(orientation_rgb, axis, sign):
    h, w, _ = orientation_rgb.shape
    col, row = direction_to_pixel(np.array(axis, float), h, w)
    assert abs(float(row) - (h / 2 - 0.5)) < 1e-9  # horizontal directions are on the equator
    assert _label_sign(orientation_rgb, float(col)) == sign


def _dark_red(rgb: np.ndarray) -> np.ndarray:
    return (rgb.max(-1) < 0.45) & (rgb[..., 0] > 2.0 * rgb[..., 1] + 0.03)


@pytest.mark.parametrize("view,towards", [((0, 0, 1), (1, 0, 0)), ((1, 0, 0), (0, 0, 1))])
def test_drawn_axes_point_towards_our_axes(orientation_rgb, view, towards):
    """From the +z view the drawn x axis runs towards our +x column (and vice versa); up is +y."""
    h, w, _ = orientation_rgb.shape
    red = _dark_red(orientation_rgb)
    col_view, row_eq = direction_to_pixel(np.array(view, float), h, w)
    col_to, _ = direction_to_pixel(np.array(towards, float), h, w)
    c, r = int(round(float(col_view))), int(round(float(row_eq)))
    step = 1 if (col_to - col_view) % w < w / 2 else -1
    toward = np.array([red[r - 2:r + 3, (c + step * k) % w].any() for k in range(5, 50)])
    away = np.array([red[r - 2:r + 3, (c - step * k) % w].any() for k in range(5, 50)])
    assert toward.mean() > 0.9 and away.mean() < 0.1
    # The vertical axis goes from the equator towards our +y (row 0 is +y).
    _, row_up = direction_to_pixel(np.array([0.0, 1.0, 0.0]), h, w)
    assert row_up < 0
    up = np.array([red[r - k, c - 2:c + 3].any() for k in range(5, 60)])
    down = np.array([red[r + k, c - 2:c + 3].any() for k in range(5, 60)])
    assert up.mean() > 0.9 and down.mean() < 0.1


def test_pixel_directions_round_trip_and_solid_angles():
    h, w = 16, 32
    dirs = pixel_directions(h, w)
    col, row = direction_to_pixel(dirs, h, w)
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    assert np.allclose(col, jj, atol=1e-9) and np.allclose(row, ii, atol=1e-9)
    assert math.isclose(float(pixel_solid_angles_sr(h).sum() * w), 4 * math.pi, rel_tol=1e-12)
    assert np.allclose(dirs[h // 2 - 1, w // 2 - 1] @ np.array([0, 0, 1.0]), np.cos(np.pi / (2 * h)) * np.cos(np.pi / w),
                       atol=1e-12)


def test_rotation_about_y_turns_plus_z_to_plus_x():
    h = 32
    dirs = pixel_directions(h, 2 * h)
    spot = (dirs @ np.array([0.0, 0.0, 1.0]) > 0.98).astype(np.float32)
    env = EnvMap(np.repeat(spot[..., None], 3, 2), "spot")
    turned = env.rotated_about_y(math.pi / 2)
    assert float(turned.sample(np.array([1.0, 0.0, 0.0]))[0]) == pytest.approx(1.0)
    assert float(turned.sample(np.array([0.0, 0.0, 1.0]))[0]) == pytest.approx(0.0)
    assert np.allclose(turned.integral_rgb(), env.integral_rgb())  # whole-pixel shift keeps energy
    half = env.rotated_about_y(math.pi / 2 + 0.5 * 2 * math.pi / (2 * h))  # fractional shift
    assert np.allclose(half.integral_rgb(), env.integral_rgb(), rtol=1e-5)


# ---- lights from a map -----------------------------------------------------------------------------

def test_back_mask_cone_and_attenuation():
    mask = BackMask()
    back = np.array([0.0, 0.0, -1.0])
    assert mask.weights(back) == 0.0
    tilt = lambda deg: np.array([math.sin(math.radians(deg)), 0.0, -math.cos(math.radians(deg))])
    assert mask.weights(tilt(44.0)) == 0.0  # inside the 45 degree cone
    theta = math.radians(90.0 - 46.0)  # 46 deg from the back = 44 deg below the side plane
    assert mask.weights(tilt(46.0)) == pytest.approx(math.cos(theta) ** 4)
    assert mask.weights(np.array([1.0, 0.0, 0.0])) == pytest.approx(1.0)  # the side
    assert mask.weights(np.array([0.0, 0.0, 1.0])) == 1.0  # front untouched


def test_uniform_lights_sum_to_the_masked_integral():
    env = read_envmap(BLENDER / "courtyard.exr")
    mask = BackMask()
    lights = select_uniform(env, 256, drop_fraction=0.0, mask=mask)
    # Independent integral: radiance * solid angle * attenuation summed over every pixel.
    dirs = pixel_directions(env.height, env.width)
    weights = mask.weights(dirs) * pixel_solid_angles_sr(env.height)[:, None]
    expected = np.einsum("hwc,hw->c", env.radiance.astype(np.float64), weights)
    assert np.allclose(lights.total_rgb(), expected, rtol=1e-9)
    assert expected.sum() < 0.99 * env.integral_rgb().sum()  # the mask did remove light
    # No light survives well inside the back cone (cells reach ~8 degrees past their centre).
    from_back_deg = np.degrees(np.arccos(np.clip(-lights.directions_world[:, 2], -1, 1)))
    assert from_back_deg.min() > 45.0 - 8.0
    # Dropping the 10% dimmest removes exactly those and nothing else.
    dropped = select_uniform(env, 256, drop_fraction=0.1, mask=mask)
    assert len(dropped) == len(lights) - int(0.1 * len(lights))
    from scene.colour import luminance
    assert luminance(dropped.irradiance_rgb).min() >= np.sort(luminance(lights.irradiance_rgb))[int(0.1 * len(lights)) - 1]


def test_unmasked_constant_map_gives_four_pi():
    env = EnvMap(np.ones((32, 64, 3), np.float32), "white")
    lights = select_uniform(env, 64, drop_fraction=0.0, mask=BackMask(enabled=False))
    assert np.allclose(lights.total_rgb(), 4 * math.pi)
    assert len(lights) == 64
    assert np.allclose(np.linalg.norm(fibonacci_sphere(64), axis=1), 1.0)


def _with_lamps(directions, radius_deg=5.0, fraction=0.6) -> EnvMap:
    """The soft synthetic sky plus bright discs (lamps, softboxes, a hazy sun) carrying ``fraction``."""
    soft = synthetic_sky(96)
    rad = soft.radiance.copy()
    for d in directions:
        rad += synthetic_sky(96, np.array(d), fraction / len(directions), radius_deg).radiance - soft.radiance
    return EnvMap(rad, "lamps")


def test_adaptive_soft_map_costs_fewer_directions_than_one_with_bright_sources():
    # A known limit, stated: a single sun is rendered exactly by one light, so under this
    # response-based error estimate a map with one tiny sun does not always cost more than
    # its bare sky; extended bright sources (softboxes, a hazy sun) do.
    n_soft = len(select_adaptive(synthetic_sky(96)))
    for lamps in ([[0.5, 0.6, 0.6], [-0.7, 0.3, 0.4]], [[0.5, 0.6, 0.6], [-0.7, 0.3, 0.4], [0.9, 0.15, -0.2]]):
        n_lamps = len(select_adaptive(_with_lamps(lamps)))
        assert n_soft < n_lamps, (lamps, n_soft, n_lamps)


def test_adaptive_energy_and_error_bound():
    env = synthetic_sky(64, np.array([0.3, 0.5, 0.8]), sun_fraction=0.5)
    params = AdaptiveParams(tolerance=0.05)
    lights = select_adaptive(env, params)
    assert lights.estimated_error <= 0.05
    total = weighted_radiance(env, BackMask()).sum(axis=(0, 1))
    assert np.allclose(lights.total_rgb(), total, rtol=1e-9)  # every bit of light goes to some light
    sun = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
    brightest = lights.directions_world[np.argmax(lights.irradiance_rgb.sum(1))]
    assert math.degrees(math.acos(min(1.0, float(brightest @ sun)))) < 2.0  # the sun gets its own light
    looser = select_adaptive(env, AdaptiveParams(tolerance=0.2))
    assert len(looser) < len(lights)


def test_write_read_round_trip(tmp_path):
    env = synthetic_sky(16, np.array([0.0, 1.0, 0.0]), 0.5)
    write_envmap(tmp_path / "sky.exr", env)
    assert np.array_equal(read_envmap(tmp_path / "sky.exr").radiance, env.radiance)


def test_far_light_positions():
    lights = select_uniform(synthetic_sky(32), 32, 0.0)
    pos = lights.positions_world(50.0, np.array([0.0, 0.1, 0.0]))
    assert np.allclose(np.linalg.norm(pos - [0.0, 0.1, 0.0], axis=1), 50.0)


# ---- bad input ---------------------------------------------------------------------------------

def test_truncated_and_garbage_files_name_the_file(tmp_path):
    data = (BLENDER / "city.exr").read_bytes()
    truncated = tmp_path / "cut.exr"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(EnvMapError, match="cut.exr"):
        read_envmap(truncated)
    garbage = tmp_path / "junk.exr"
    garbage.write_bytes(b"not an exr at all")
    with pytest.raises(EnvMapError, match="junk.exr"):
        read_envmap(garbage)
    with pytest.raises(EnvMapError, match="missing.exr"):
        read_envmap(tmp_path / "missing.exr")


def test_non_2to1_map_is_rejected(tmp_path):
    from scene.image_io import write_exr

    path = tmp_path / "square.exr"
    write_exr(path, np.ones((32, 32, 3), np.float32))
    with pytest.raises(EnvMapError, match=r"square.exr.*2:1"):
        read_envmap(path)


def test_nan_and_negative_pixels_warn_and_clamp(tmp_path):
    rad = np.ones((16, 32, 3), np.float32)
    rad[2, 3] = np.nan
    rad[4, 5] = -2.0
    rad[6, 7] = -0.001  # DWAB ringing: clamped silently
    path = tmp_path / "bad.exr"
    from scene.image_io import write_exr

    write_exr(path, rad, half=False)
    with pytest.warns(EnvMapWarning) as record:
        env = read_envmap(path)
    messages = " ".join(str(r.message) for r in record)
    assert "NaN" in messages and "negative" in messages and "bad.exr" in messages
    assert np.isfinite(env.radiance).all() and env.radiance.min() == 0.0


def test_dwab_ringing_is_clamped_without_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error", EnvMapWarning)
        env = read_envmap(BLENDER / "sunrise.exr")  # has small negatives from DWAB compression
    assert env.radiance.min() >= 0.0


def test_centroid_directions_put_a_sun_where_it_is():
    sun = np.array([0.37, 0.52, 0.77]) / np.linalg.norm([0.37, 0.52, 0.77])
    env = synthetic_sky(128, sun, sun_fraction=0.9, sun_radius_deg=1.0)
    for centroid, worst_deg in ((False, 10.0), (True, 0.5)):
        lights = select_uniform(env, 64, 0.0, BackMask(enabled=False), centroid=centroid)
        brightest = lights.directions_world[np.argmax(lights.irradiance_rgb.sum(1))]
        err = math.degrees(math.acos(min(1.0, float(brightest @ sun))))
        assert err < worst_deg
    assert np.allclose(np.linalg.norm(lights.directions_world, axis=1), 1.0)


def test_black_map_is_a_clear_error():
    black = EnvMap(np.zeros((16, 32, 3), np.float32), "black.exr")
    with pytest.raises(EnvMapError, match="black.exr.*no light"):
        select_uniform(black, 32)
    with pytest.raises(EnvMapError, match="black.exr.*no light"):
        select_adaptive(black)


@pytest.mark.parametrize("angle_deg", [0.0, 17.3, -95.0, 360.0 + 40.0])
def test_rotating_projection_gives_select_uniforms_lights_of_the_rotated_map(angle_deg):
    """Every rotation's lights from the precomputed table equal select_uniform's of the rotated map
    (masked back cone, dropped dimmest, fractional column shifts), on a sunny map and a shipped one."""
    sunny = synthetic_sky(48, np.array([0.6, 0.4, -0.5]), 0.6, sun_radius_deg=3.0)
    shipped = read_envmap(BLENDER / "sunrise.exr")
    for envmap, count in ((sunny, 64), (shipped, 256)):
        projection = _projection(envmap, count)
        angle = math.radians(angle_deg)
        fast = projection.lights(angle)
        reference = select_uniform(envmap.rotated_about_y(angle), count, 0.1, BackMask())
        np.testing.assert_array_equal(fast.directions_world, reference.directions_world)
        np.testing.assert_allclose(fast.irradiance_rgb, reference.irradiance_rgb, rtol=1e-6,
                                   atol=1e-9 * float(reference.irradiance_rgb.max()))
        weights = projection.weights(angle)  # every direction, the dropped ones at 0
        assert weights.shape == (count, 3) and int((weights.sum(1) > 0).sum()) == len(reference)
        np.testing.assert_allclose(weights.sum(0), reference.total_rgb(), rtol=1e-6)


_PROJECTIONS: dict = {}


def _projection(envmap, count):
    key = (envmap.source, count)
    if key not in _PROJECTIONS:
        _PROJECTIONS[key] = RotatingProjection(envmap, count, 0.1, BackMask())
    return _PROJECTIONS[key]


def test_uniform_solid_angles_are_the_cells_the_map_pixels_fall_in():
    solid = uniform_solid_angles_sr(64)
    assert solid.shape == (64,) and abs(solid.sum() - 4 * math.pi) < 1e-9
    # The pixels nearest each direction add up to its cell, up to the cells' ragged pixel edges.
    cells = _voronoi_cells(256, 512, 64)
    pixels = np.bincount(cells, np.repeat(pixel_solid_angles_sr(256), 512), minlength=64)
    np.testing.assert_allclose(pixels, solid, rtol=0.02)
