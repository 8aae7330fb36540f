"""The real camera of ``capture.realism: real``: the sensor's noise law, vignetting, defocus, motion blur, the print."""

import numpy as np
import pytest

from hardware.studio.camera_effects import BoardPrint, CameraEffects, LensModel, SensorModel
from hardware.studio.optics import defocus_sigma_px, focus_distance_m, motion_blur, vignetting_gain
from hardware.studio.printed_board import print_board
from hardware.studio.real_camera import film_performance_image
from hardware.studio.sensor import expose, linear_variance
from scene.rig import default_rig


def test_noise_variance_follows_the_gain_model():
    sensor = SensorModel()
    rng = np.random.default_rng(0)
    per_linear = sensor.full_well_e / sensor.white_level_linear
    for level in (0.002, 0.02, 0.2, 1.0, 1.8):  # dark OLAT pixel .. near saturation, linear units
        img = expose(np.full((300, 300), level), sensor, rng)
        assert img.mean() == pytest.approx(level, rel=0.01, abs=2e-5)
        # in electrons: variance = mean (Poisson) + read noise^2 (+ the DN step^2 / 12)
        var_e = img.var() * per_linear ** 2
        expected_e = level * per_linear + sensor.read_noise_e ** 2 + sensor.gain_e_per_dn ** 2 / 12
        assert var_e == pytest.approx(expected_e, rel=0.03)
        assert img.var() == pytest.approx(linear_variance(level, sensor), rel=0.03)
    # DN steps of gain / electrons-per-linear, and saturation at the white level
    img = expose(np.full((50, 50), 0.3), sensor, rng)
    steps = np.unique(img) / (sensor.gain_e_per_dn / per_linear)
    np.testing.assert_allclose(steps, np.rint(steps), atol=1e-6)
    assert expose(np.full((10, 10), 5.0), sensor, rng).max() == pytest.approx(sensor.white_level_linear)
    assert sensor.full_well_e == pytest.approx(2.5 * 4095)


def test_read_noise_alone_sets_the_dark_floor():
    sensor = SensorModel(read_noise_e=3.0, black_level_dn=64)  # a pedestal: the dark noise is not clipped
    img = expose(np.zeros((400, 400)), sensor, np.random.default_rng(1))
    per_linear = sensor.full_well_e / sensor.white_level_linear
    assert img.std() * per_linear == pytest.approx(np.sqrt(3.0 ** 2 + sensor.gain_e_per_dn ** 2 / 12), rel=0.03)
    assert abs(img.mean()) * per_linear < 0.05


def test_vignetting_is_cos4_of_the_field_angle_and_falls_towards_the_corners():
    cam = default_rig().cameras_at(0.25)[0]
    gain = vignetting_gain(cam, 4.0)
    assert gain.shape == (cam.height, cam.width)
    centre = gain[int(round(cam.cy)), int(round(cam.cx))]
    assert centre == pytest.approx(1.0, abs=1e-4)
    for y, x in ((0, 0), (0, cam.width - 1), (cam.height - 1, 0), (cam.height - 1, cam.width - 1)):
        xn, yn = (x - cam.cx) / cam.fx, (y - cam.cy) / cam.fy  # pinhole angle (the rig's distortion is small)
        assert gain[y, x] == pytest.approx(1.0 / (1.0 + xn * xn + yn * yn) ** 2, rel=0.01)
        assert 0.80 < gain[y, x] < 0.95  # the rig's ~8 deg half-diagonal: ~10% at the corners
    diagonal = gain[np.linspace(int(cam.cy), cam.height - 1, 20).astype(int),
                    np.linspace(int(cam.cx), cam.width - 1, 20).astype(int)]
    assert np.all(np.diff(diagonal) <= 1e-9)
    np.testing.assert_array_equal(vignetting_gain(cam, 0.0), 1.0)


def test_defocus_is_the_thin_lens_circle_of_confusion():
    cam = default_rig().cameras_at(1.0)[0]
    lens = LensModel(focal_length_mm=50, f_number=8)
    assert defocus_sigma_px(cam, lens, 1.1, 1.1) == 0.0
    # c = (f / N) f |s - s_f| / (s (s_f - f)), in pixels c fx / f, sigma = c / 4
    f, n, s, s_f = 0.05, 8.0, 1.25, 1.1
    coc_px = (f / n) * f * (s - s_f) / (s * (s_f - f)) * cam.fx / f
    assert defocus_sigma_px(cam, lens, s, s_f) == pytest.approx(coc_px / 4)
    assert 0.3 < coc_px / 4 < 1.0  # the board 15 cm behind the head: half a native pixel or so
    # a wider aperture blurs more, a nearer point too
    assert defocus_sigma_px(cam, LensModel(f_number=4), s, s_f) == pytest.approx(2 * coc_px / 4)
    assert defocus_sigma_px(cam, lens, 0.95, s_f) > 0
    # half the resolution: half the pixels of blur
    assert defocus_sigma_px(cam.scaled(0.5), lens, s, s_f) == pytest.approx(coc_px / 8, rel=1e-3)
    rig = default_rig()
    assert focus_distance_m(cam, lens, np.asarray(rig.head_center_m)) == pytest.approx(
        float(np.linalg.norm(cam.center_world - np.asarray(rig.head_center_m))), rel=0.01)


def test_motion_blur_smears_along_the_travel_and_keeps_the_energy():
    img = np.zeros((41, 41))
    img[20, 20] = 1.0
    out = motion_blur(img, np.array([8.0, 0.0]))
    assert out.sum() == pytest.approx(1.0)
    row = out[20]
    assert np.count_nonzero(row > 1e-6) >= 8 and np.all(out[[19, 21]] < 1e-9)  # a horizontal streak only
    assert np.flatnonzero(row > 1e-6).min() == 16 and np.flatnonzero(row > 1e-6).max() == 24
    np.testing.assert_array_equal(motion_blur(img, np.array([0.01, 0.0])), img)  # below min travel: untouched


def test_printed_board_differs_from_nominal_by_the_stated_amounts():
    spec = BoardPrint(scale_error=(0.0015, 0.0025), corner_jitter_m=3e-5, bow_m=8e-4, seed=5)
    sx, sy, sq = 12, 9, 0.04  # more corners than the rig's board: tighter statistics
    board = print_board(sx, sy, sq, spec)
    gx, gy = np.meshgrid(np.arange(sx + 1) * sq, np.arange(sy + 1) * sq)
    nominal = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], -1)
    printed = board.printed_points(nominal)
    centred = nominal[:, :2] - board.center_m
    scale = [(centred[:, a] @ (printed[:, a] - board.center_m[a])) / (centred[:, a] @ centred[:, a]) for a in (0, 1)]
    assert scale[0] - 1 == pytest.approx(0.0015, abs=2e-4)
    assert scale[1] - 1 == pytest.approx(0.0025, abs=2e-4)
    residual = printed[:, :2] - board.center_m - centred * np.array(scale)
    assert residual.std() == pytest.approx(3e-5, rel=0.2)
    # the bow: the centre 0.8 mm towards the camera (-z), the outer corners in the plane
    corners = (nominal[:, 0] % (sx * sq) == 0) & (nominal[:, 1] % (sy * sq) == 0)
    # (the print's +0.25% puts them ~0.5% beyond the nominal corner radius: ~4 um behind the plane)
    np.testing.assert_allclose(printed[corners, 2], 0.0, atol=1e-5)
    assert board.surface_z(board.center_m[None])[0] == pytest.approx(-8e-4)
    # the artwork lookup inverts the print (to 0.2 um: ~1/2000 of a native pixel on the board)
    xy = np.random.default_rng(0).uniform(0, [sx * sq, sy * sq], size=(500, 2))
    np.testing.assert_allclose(board.nominal_xy(board.printed_xy(xy)), xy, rtol=0, atol=2e-7)


def test_effects_metrics_are_numbers_with_units_in_the_keys():
    metrics = CameraEffects().metrics()
    assert all(isinstance(v, (int, float)) for v in metrics.values())
    assert metrics["sensor_gain_e_per_dn"] == 2.5 and metrics["read_noise_e"] == 2.5
    assert metrics["exposure_s"] == 0.008 and metrics["board_bow_mm"] == pytest.approx(0.8)
    assert metrics["board_flex_mm"] == pytest.approx(0.3)


def test_the_true_matte_gets_the_images_blur_but_not_its_noise():
    cam = default_rig().cameras_at(0.25)[0]
    alpha = np.zeros((cam.height, cam.width))
    alpha[60:200, 50:140] = 1.0
    rgb = alpha[..., None] * np.array([0.3, 0.2, 0.1])
    effects = CameraEffects(lens=LensModel(f_number=2.0))  # wide open: the head 20 cm off focus is blurred
    head_depth, focus = 1.3, 1.1
    out_rgb, out_alpha = film_performance_image(rgb, alpha, cam, effects, 0.25, head_depth, focus,
                                                np.array([3.0, 0.0]), np.random.default_rng(0))
    assert out_rgb.dtype == np.float32 and out_alpha.dtype == np.float32
    assert out_alpha.sum() == pytest.approx(alpha.sum(), rel=1e-3)  # blur keeps the coverage
    soft = np.count_nonzero((out_alpha > 0.02) & (out_alpha < 0.98))
    assert soft > 2 * (2 * 140 + 2 * 90)  # edges a few pixels wide (sigma 0.6 px, a 3 px smear along x)
    assert np.all(out_alpha[100:160, 70:120] > 0.999)  # the inside is untouched: no noise on the matte
    inside = out_rgb[100:160, 70:120, 0]
    assert inside.std() > 0  # but the image is noisy


def test_the_board_flexes_differently_in_every_pose_and_the_same_for_every_camera():
    spec = BoardPrint(bow_m=8e-4, flex_m=3e-4, seed=5)
    sx, sy, sq = 5, 7, 0.04
    rest = print_board(sx, sy, sq, spec)
    assert rest.bow_m == 8e-4 and rest.twist_m == 0.0  # no pose: the print at rest
    poses = [print_board(sx, sy, sq, spec, pose_index=k) for k in range(400)]
    # one draw per pose, reproducible (every camera filming pose k renders the same board)
    again = print_board(sx, sy, sq, spec, pose_index=7)
    assert (again.bow_m, again.twist_m) == (poses[7].bow_m, poses[7].twist_m)
    np.testing.assert_array_equal(again.corner_jitter_m, rest.corner_jitter_m)  # the same print in every pose
    bows = np.array([b.bow_m for b in poses]) - 8e-4
    twists = np.array([b.twist_m for b in poses])
    assert bows.std() == pytest.approx(3e-4, rel=0.15) and twists.std() == pytest.approx(3e-4, rel=0.15)
    assert abs(np.corrcoef(bows, twists)[0, 1]) < 0.2  # two independent modes
    # the twist lifts two opposite corners and lowers the other two by its amount; the centre stays
    twisted = print_board(sx, sy, sq, BoardPrint(bow_m=0.0, flex_m=3e-4, seed=5), pose_index=3)
    corners = np.array([[0, 0], [sx * sq, sy * sq], [sx * sq, 0], [0, sy * sq]], float)
    z = twisted.surface_z(corners)
    np.testing.assert_allclose(z, [-twisted.twist_m] * 2 + [twisted.twist_m] * 2, atol=1e-12)
    assert twisted.surface_z(twisted.center_m[None])[0] == pytest.approx(-twisted.bow_m)
    # flex 0: every pose is the print at rest
    still = print_board(sx, sy, sq, BoardPrint(flex_m=0.0), pose_index=3)
    assert (still.bow_m, still.twist_m) == (BoardPrint().bow_m, 0.0)
