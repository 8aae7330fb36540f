"""Studio rendering is cached per trigger pulse: a longer take renders only its new pulses, and the
capture it gives is byte for byte the one a run without a cache gives."""

import json
from pathlib import Path

from pipeline.testing import run_stage_for_test
from scene.rig import default_rig
from stages.capture.stage import STAGE as CAPTURE
from stages.sequence.stage import STAGE as SEQUENCE

SMALL = {"image_scale": 0.08, "texture_size": 64, "edge_samples": 2, "bar_samples": 1, "calibration_takes": False,
         "takes": ["rom"], "identity_seed": 3, "repeat_frames": {"cam01": [2]}, "camera_drop_frames": {"cam00": [3]}}


def _files(root: Path, folders: tuple[str, ...]) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for folder in folders for p in sorted((root / folder).rglob("*"))
            if p.is_file() and p.name != "metrics.json"}


def test_more_frames_render_only_the_new_pulses_and_equal_an_uncached_capture(tmp_path):
    rig = default_rig()
    rig = rig.model_copy(update={"cameras": rig.cameras[:2]})
    seq = run_stage_for_test(SEQUENCE, tmp_path / "seq", params={"cycles": 1, "restarts": 1,
                                                                 "random_baseline_samples": 4})
    first = run_stage_for_test(CAPTURE, tmp_path / "a", inputs={"sequence": seq},
                               params={**SMALL, "rig": rig, "max_frames": 5})
    metrics = json.loads((first / "metrics.json").read_text())
    assert (metrics["render_pulses_reused"], metrics["render_pulses_computed"]) == (0, 5)

    (tmp_path / "b").mkdir()
    (tmp_path / "b" / ".cache").symlink_to(tmp_path / "a" / ".cache")  # the same subject's cache
    longer = run_stage_for_test(CAPTURE, tmp_path / "b", inputs={"sequence": seq},
                                params={**SMALL, "rig": rig, "max_frames": 8})
    metrics = json.loads((longer / "metrics.json").read_text())
    assert (metrics["render_pulses_reused"], metrics["render_pulses_computed"]) == (5, 3)
    assert metrics["frames"] == 8

    uncached = run_stage_for_test(CAPTURE, tmp_path / "c", inputs={"sequence": seq},
                                  params={**SMALL, "rig": rig, "max_frames": 8})
    assert json.loads((uncached / "metrics.json").read_text())["render_pulses_computed"] == 8
    cached_files = _files(tmp_path / "b", ("capture", "capture.truth"))
    assert cached_files == _files(tmp_path / "c", ("capture", "capture.truth"))
    assert "capture/frames/cam01/000002.exr" in cached_files and "capture.truth/mattes/cam01/000003.png" in cached_files
