"""capture.realism: ``ideal`` films today's clean studio bit for bit, ``real`` films through the camera model."""

import json

import numpy as np
import pytest

from hardware.studio import RenderSettings, VirtualStudio, make_subject
from hardware.studio.performance import FrameState
from pipeline.testing import run_stage_for_test
from scene.camera import Rigid, load_cameras
from scene.image_io import read_exr, read_png16
from scene.rig import default_rig
from stages.capture.stage import STAGE as CAPTURE
from stages.sequence.stage import STAGE as SEQUENCE

RENDER = {"edge_samples": 2, "bar_samples": 1}
SMALL = {"image_scale": 0.08, "texture_size": 64, "render": RENDER, "calibration_takes": False,
         "max_frames": 3, "identity_seed": 4}


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    rig = default_rig()
    rig = rig.model_copy(update={"cameras": rig.cameras[:2]})
    out = {}
    for realism in ("ideal", "real"):
        tmp = tmp_path_factory.mktemp(realism)
        seq = run_stage_for_test(SEQUENCE, tmp, params={"cycles": 1, "restarts": 1, "random_baseline_samples": 4})
        cap = run_stage_for_test(CAPTURE, tmp, inputs={"sequence": seq},
                                 params={**SMALL, "rig": rig, "realism": realism})
        out[realism] = (cap, tmp / "capture.truth", rig)
    return out


def _frames(truth) -> list[FrameState]:
    f = np.load(truth / "frames.npz")
    return [FrameState(int(i), str(take), float(t), w, Rigid(R, p))
            for i, take, t, w, R, p in zip(f["index"], f["take"], f["time_s"], f["weights"],
                                           f["world_from_head_R"], f["world_from_head_t"])]


def test_ideal_is_the_renderers_clean_image_with_its_own_noise_bit_for_bit(captures):
    cap, truth, rig = captures["ideal"]
    studio = VirtualStudio(rig, make_subject("test", 4, texture_size=64), RenderSettings(**RENDER))
    lit = json.loads((truth / "lights_per_pulse.json").read_text())
    for cam in load_cameras(truth / "cameras.json"):
        for frame in _frames(truth):
            expected = studio.render(frame, cam, [] if lit[frame.index] is None else lit[frame.index])
            got = read_exr(cap / "frames" / cam.name / f"{frame.index:06d}.exr")
            np.testing.assert_array_equal(got, expected.rgb.astype(np.float16).astype(got.dtype))
            np.testing.assert_array_equal(read_png16(truth / "mattes" / cam.name / f"{frame.index:06d}.png"),
                                          np.round(expected.alpha * 65535) / 65535)
    assert json.loads((cap / "metrics.json").read_text())["realism_real"] == 0


def test_real_states_its_noise_model_and_films_other_images(captures):
    ideal, real = captures["ideal"][0], captures["real"][0]
    metrics = json.loads((real / "metrics.json").read_text())
    assert metrics["realism_real"] == 1
    assert (metrics["sensor_gain_e_per_dn"], metrics["read_noise_e"], metrics["exposure_s"]) == (2.5, 2.5, 0.008)
    assert metrics["sensor_full_well_e"] == pytest.approx(2.5 * 4095)
    a = read_exr(ideal / "frames" / "cam00" / "000000.exr")
    b = read_exr(real / "frames" / "cam00" / "000000.exr")
    assert a.shape == b.shape and not np.array_equal(a, b)
    # same exposure: the vignetting (~10% at the corners, less on the head) and blur leave the mean within a few %
    assert b.mean() == pytest.approx(a.mean(), rel=0.08)
    assert b.max() <= 2.0  # the sensor saturates at white_level_linear
