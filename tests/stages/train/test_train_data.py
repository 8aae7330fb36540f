"""The train stage's data layer: rays computed from per-camera directions, spilling to disk."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from pipeline.errors import InputError
from scene.camera import Camera, look_at
from stages.stabilize.output import StabilizeOutput
from stages.train.data import _pixel_directions, load_train_data
from tests.stages.train.train_synth import make_capture


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return make_capture(tmp_path_factory.mktemp("synth"), width_px=32, cameras=3, frames_per_take=(6, 4))


def test_pixel_directions_rotated_into_head_space_equal_the_cameras_rays():
    # A distorted, off-centre camera in a general pose: the per-camera directions, rotated by
    # the pose, must be the rays the camera model itself gives for every pixel.
    cam = Camera(name="c", width=20, height=14, fx=30.0, fy=31.0, cx=9.3, cy=7.1,
                 dist=(-0.21, 0.08, 0.004, -0.003, -0.01),
                 pose=look_at(np.array([0.3, 0.1, 1.2]), np.zeros(3), np.array([0.0, 1.0, 0.0])))
    origins, dirs = cam.image_rays()
    rotated = _pixel_directions(cam) @ cam.cam_from_world.R  # (R^T d) for every row d
    np.testing.assert_allclose(rotated, dirs.reshape(-1, 3), atol=1e-9)
    np.testing.assert_allclose(origins.reshape(-1, 3)[0], cam.center_world, atol=1e-12)


def test_rays_of_an_image_match_the_stabilised_camera(capture):
    data = load_train_data(capture, 24, logging.getLogger("test"))
    cams = StabilizeOutput(capture["stabilize"]).cameras_head_by_name()
    cam = cams[int(data.frame_index[1])][data.camera_names[2]]
    cam = cam.scaled(24 / cam.width)
    want_o, want_d = cam.image_rays()
    got_o, got_d = data.rays(1, 2)
    np.testing.assert_allclose(got_d, want_d.reshape(-1, 3), atol=2e-6)
    np.testing.assert_allclose(got_o, want_o.reshape(-1, 3), atol=2e-6)


def test_spilled_images_are_memory_mapped_and_equal_the_resident_ones(capture, tmp_path):
    resident = load_train_data(capture, 24, logging.getLogger("test"))
    spilled = load_train_data(capture, 24, logging.getLogger("test"), resident_limit_gb=0.0,
                              spill_dir=tmp_path / "spill")
    assert not resident.spilled and spilled.spilled
    assert (tmp_path / "spill" / "images.npy").is_file()
    np.testing.assert_array_equal(np.asarray(spilled.images), resident.images)
    np.testing.assert_array_equal(np.asarray(spilled.mattes), resident.mattes)


def test_a_camera_whose_lens_changes_between_frames_is_refused(capture, tmp_path):
    import shutil

    inputs = {k: tmp_path / k for k in capture}
    for k, src in capture.items():
        shutil.copytree(src, inputs[k])
    data = load_train_data(capture, 24, logging.getLogger("test"))
    path = inputs["stabilize"] / "cameras_head.json"
    doc = json.loads(path.read_text())  # {"frames": {"<index>": [camera dicts]}}
    doc["frames"][str(int(data.frame_index[-1]))][0]["fx"] *= 1.1  # one camera, last used frame only
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="other intrinsics"):
        load_train_data(inputs, 24, logging.getLogger("test"))


def test_training_on_spilled_images_takes_the_same_steps_as_on_resident_ones(capture, tmp_path):
    """The memory-mapped path (paper-size captures) gathers the same pixels and rays as the in-memory one."""
    import torch

    from stages.train import trainer as trainer_mod
    from tests.stages.train.train_synth import small_model

    def losses(spill: bool) -> list[float]:
        data = load_train_data(capture, 24, logging.getLogger("test"), resident_limit_gb=0.0 if spill else 8.0,
                               spill_dir=tmp_path / f"spill{int(spill)}")
        assert data.spilled == spill
        _, tensors, model, renderer = small_model(data)
        tr = trainer_mod.ModelTrainer(renderer, tensors, np.arange(len(data.bar)), iterations=4, batch_size=2,
                                      rays_per_image=64, lr=3e-3, weights=trainer_mod.LossWeights(), seed=0,
                                      ckpt_path=tmp_path / f"c{int(spill)}.pt", checkpoint_every=100,
                                      spike_factor=10.0, log=logging.getLogger("test"))
        return [tr.step()["loss"] for _ in range(4)]

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # multi-threaded scatter-adds are not bit-reproducible from run to run
    try:
        assert losses(spill=True) == losses(spill=False)
    finally:
        torch.set_num_threads(threads)

