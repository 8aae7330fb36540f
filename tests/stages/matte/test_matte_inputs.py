"""Input normalisation and F-frame guides."""

import numpy as np

from stages.matte.inputs import camera_reference, nearest_full_on, network_input, olat_scale


def test_nearest_full_on_follows_the_pattern_and_skips_dropped_frames():
    lights = ["F", 3, 9, "F", 4, 10, "F"]
    frames = [{"index": i, "time_s": i / 24, "light": light, "status": "ok"} for i, light in enumerate(lights)]
    guides = nearest_full_on(frames)
    assert guides == {0: 0, 1: 0, 2: 3, 3: 3, 4: 3, 5: 6, 6: 6}
    frames[3]["status"] = "dropped"
    guides = nearest_full_on(frames)
    assert guides[2] == 0 and guides[4] == 6


def test_olat_scale_is_floored_by_the_camera_reference():
    reference = camera_reference([0.5, 0.4, 0.6], floor=1e-3)
    assert reference == 0.5
    dark = np.zeros((8, 8, 3), np.float32)
    assert olat_scale(dark, reference, 0.02) == 0.5 * 0.02
    assert camera_reference([], floor=1e-3) == 1e-3


def test_network_input_channels_and_range():
    rng = np.random.default_rng(0)
    image = rng.uniform(0, 2, (10, 12, 3)).astype(np.float32)
    x = network_input(image, 1.0, image * 0, 1.0)
    assert x.shape == (6, 10, 12) and x.dtype == np.float32
    assert x.min() >= -1 and x.max() <= 1
    assert np.all(x[3:] == -1)  # a black guide is the backdrop value
