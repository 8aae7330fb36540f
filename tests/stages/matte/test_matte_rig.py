"""The matting network's training data is filmed in the subject's own studio (its rig), not configs/rig.yaml's."""

from __future__ import annotations

from pathlib import Path

from scene.rig import default_rig, load_rig
from stages.matte.stage import MatteParams, _image_scale
from stages.matte.studio_data import IdentityJob, StudioDataConfig, render_identity

ROOT = Path(__file__).resolve().parents[3]


def test_training_samples_are_framed_by_the_subjects_rig():
    landscape = load_rig(ROOT / "configs" / "rigs" / "six_landscape.yaml")  # 320 x 240
    config = StudioDataConfig(identity_seeds=(1001,), frame_pairs_per_identity=1, cameras_per_frame=1,
                              olat_fraction=1.0, empty_fraction=0.0, frames_per_take=4)
    samples = render_identity(IdentityJob(1001, config, 0.25, landscape))
    assert samples and samples[0].image.shape[:2] == (60, 80)  # landscape, as the rig's cameras
    portrait = render_identity(IdentityJob(1001, config, 0.0625))  # configs/rig.yaml: 768 x 1024
    assert portrait[0].image.shape[:2] == (64, 48)


def test_the_capture_scale_is_relative_to_the_subjects_rig():
    landscape = load_rig(ROOT / "configs" / "rigs" / "six_landscape.yaml")
    assert _image_scale({"width": 320}, landscape) == 1.0
    assert _image_scale({"width": 240}, default_rig()) == 0.3125
    assert MatteParams(rig=landscape).rig.width_px == 320
