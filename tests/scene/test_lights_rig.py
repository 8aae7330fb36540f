"""scene.lights and scene.rig: the LED bars, near-field irradiance, the studio's cameras."""

import numpy as np

from scene.lights import LightBar, bar_irradiance, bar_sample_points, point_irradiance
from scene.rig import default_rig


def test_rig_has_ten_cameras_and_32_frontal_bars():
    rig = default_rig()
    cams = rig.cameras_at(0.3125)
    assert len(cams) == 10 and (cams[0].width, cams[0].height) == (240, 320)
    for cam in cams:
        uv, z = cam.project(np.array([rig.head_center_m]))
        assert z[0] > 0.8  # in front of the camera, about a metre away
        assert 0.3 * cam.width < uv[0, 0] < 0.7 * cam.width and 0.3 * cam.height < uv[0, 1] < 0.7 * cam.height
        assert cam.center_world[2] > 0  # frontal hemisphere
    bars = rig.light_bars()
    assert len(bars) == 32 and [b.id for b in bars] == list(range(32))
    for bar in bars:
        dist = np.linalg.norm(bar.center_world - np.asarray(rig.head_center_m))
        assert 1.0 < dist < 1.5 and bar.center_world[2] > 0
        assert 0.2 < bar.length_m < 0.6 and 0.8 < bar.intensity < 1.2
        assert abs(bar.axis_world @ bar.normal_world) < 1e-3  # bars lie tangent to the dome
    assert len({round(b.intensity, 4) for b in bars}) > 20  # intensities differ slightly


def test_bar_samples_lie_on_the_segment():
    bar = LightBar(0, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), 0.4, 1.0, np.array([0.0, 0.0, -1.0]))
    pts = bar_sample_points(bar, 8, np.random.default_rng(0).uniform(size=(5, 8)))
    assert pts.shape == (5, 8, 3)
    assert np.all(np.abs(pts[..., 0]) <= 0.2) and np.allclose(pts[..., 2], 1.0)
    # Stratified: one sample per eighth of the bar.
    strata = np.floor((pts[..., 0] + 0.2) / 0.05).astype(int)
    assert (np.sort(strata, axis=1) == np.arange(8)).all()


def test_near_field_falloff_and_cosines():
    pts = np.zeros((1, 3))
    n = np.array([[0.0, 0.0, 1.0]])
    e1 = point_irradiance(pts, n, np.array([0.0, 0.0, 1.0]), 1.0)
    e2 = point_irradiance(pts, n, np.array([0.0, 0.0, 2.0]), 1.0)
    assert np.isclose(e1[0] / e2[0], 4.0)  # 1 / r^2
    oblique = point_irradiance(pts, n, np.array([1.0, 0.0, 1.0]) / np.sqrt(2), 1.0)
    assert np.isclose(oblique[0], np.cos(np.pi / 4))  # receiver cosine
    assert point_irradiance(pts, n, np.array([0.0, 0.0, -1.0]), 1.0)[0] == 0.0  # behind the surface
    # A short bar far away acts like a point; a long bar close by gives less than a point would.
    far = LightBar(0, np.array([0.0, 0.0, 5.0]), np.array([1.0, 0.0, 0.0]), 0.1, 1.0, np.array([0.0, 0.0, -1.0]))
    assert np.isclose(bar_irradiance(pts, n, far)[0], 1 / 25, rtol=1e-3)
    near = LightBar(0, np.array([0.0, 0.0, 0.3]), np.array([1.0, 0.0, 0.0]), 0.6, 1.0, np.array([0.0, 0.0, -1.0]))
    assert bar_irradiance(pts, n, near)[0] < 1 / 0.09


def test_bad_rig_file_names_file_and_key(tmp_path):
    import pytest
    import yaml

    from scene.rig import DEFAULT_RIG, load_rig

    raw = yaml.safe_load(DEFAULT_RIG.read_text())
    raw["bars"][3]["length_m"] = -1.0
    bad = tmp_path / "rig.yaml"
    bad.write_text(yaml.safe_dump(raw))
    with pytest.raises(ValueError, match=r"rig.yaml.*bars\.3\.length_m"):
        load_rig(bad)
