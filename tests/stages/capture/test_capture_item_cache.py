"""Studio rendering is cached per trigger pulse: a longer take renders only its new pulses, and the
capture it gives is byte for byte the one a run without a cache gives."""

import json
from pathlib import Path

from pipeline.testing import run_stage_for_test
from scene.rig import default_rig
from stages.capture.stage import STAGE as CAPTURE
from stages.sequence.stage import STAGE as SEQUENCE

SMALL = {"image_scale": 0.08, "texture_size": 64, "render": {"edge_samples": 2, "bar_samples": 1}, "calibration_takes": False,
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


CALIB = {**SMALL, "calibration_takes": True, "calibration_poses": 3, "calibration_image_scale": 0.2,
         "repeat_frames": {}, "camera_drop_frames": {}}


def _capture_sharing_cache(tmp_path, name: str, seq: Path, params: dict) -> tuple[Path, dict]:
    """Capture into ``tmp_path/name`` with the per-item cache of ``tmp_path/a``; (output, metrics)."""
    if name != "a":
        (tmp_path / name).mkdir()
        (tmp_path / name / ".cache").symlink_to(tmp_path / "a" / ".cache")
    out = run_stage_for_test(CAPTURE, tmp_path / name, inputs={"sequence": seq}, params=params)
    return out, json.loads((out / "metrics.json").read_text())


def _calib_counts(metrics: dict) -> tuple[int, int, int, int]:
    return (metrics["calibration_items_reused"], metrics["calibration_items_computed"],
            metrics["calibration_board_items_computed"], metrics["calibration_mirror_items_computed"])


def test_calibration_takes_are_reused_across_reruns_and_recomputed_only_where_they_change(tmp_path):
    rig = default_rig()
    rig = rig.model_copy(update={"cameras": rig.cameras[:2]})
    seq = run_stage_for_test(SEQUENCE, tmp_path / "seq", params={"cycles": 1, "restarts": 1,
                                                                 "random_baseline_samples": 4})
    first, metrics = _capture_sharing_cache(tmp_path, "a", seq, {**CALIB, "rig": rig, "max_frames": 3})
    assert _calib_counts(metrics) == (0, 4, 2, 2)  # per camera: its board take and its mirror take
    calib = _files(tmp_path / "a" / "capture", ("calib",))
    assert {"calib/mirror_roi.json", "calib/mirror/cam01/bar31.exr", "calib/charuco/cam00/0000.exr"} <= set(calib)

    # More performance frames: every calibration item comes from the cache, the files are the same bytes.
    _, metrics = _capture_sharing_cache(tmp_path, "b", seq, {**CALIB, "rig": rig, "max_frames": 5})
    assert _calib_counts(metrics) == (4, 0, 0, 0) and metrics["render_pulses_reused"] == 3
    assert _files(tmp_path / "b" / "capture", ("calib",)) == calib
    for name in ("calib_board_poses.json", "mirror_spheres.json"):
        truth_a, truth_b = tmp_path / "a" / "capture.truth" / name, tmp_path / "b" / "capture.truth" / name
        assert truth_b.read_bytes() == truth_a.read_bytes()

    # Another board print: the board takes change, the mirror takes (drawn after the same board noise) do not.
    board = {**rig.calibration["board"], "marker_m": 0.027}
    reprinted = rig.model_copy(update={"calibration": {**rig.calibration, "board": board}})
    _, metrics = _capture_sharing_cache(tmp_path, "c", seq, {**CALIB, "rig": reprinted, "max_frames": 3})
    assert _calib_counts(metrics) == (2, 2, 2, 0)
    changed = _files(tmp_path / "c" / "capture", ("calib",))
    assert {k: v for k, v in changed.items() if "charuco" not in k and k != "calib/board.json"} == \
        {k: v for k, v in calib.items() if "charuco" not in k and k != "calib/board.json"}
    assert changed["calib/charuco/cam00/0000.exr"] != calib["calib/charuco/cam00/0000.exr"]
    uncached = run_stage_for_test(CAPTURE, tmp_path / "e", inputs={"sequence": seq},
                                  params={**CALIB, "rig": reprinted, "max_frames": 3})
    assert changed == _files(uncached, ("calib",))  # what the reused mirror items give is what a fresh run gives

    # More board poses: every board take changes; under realism real each board image draws its noise from
    # its own generator, so the mirror takes stay as they were.
    more, metrics = _capture_sharing_cache(tmp_path, "d", seq, {**CALIB, "rig": rig, "max_frames": 3,
                                                                "calibration_poses": 4})
    assert _calib_counts(metrics) == (2, 2, 2, 0)
    assert {k: v for k, v in _files(more, ("calib",)).items() if "charuco" not in k and k != "calib/board.json"} == \
        {k: v for k, v in calib.items() if "charuco" not in k and k != "calib/board.json"}


def test_ideal_mirror_takes_follow_the_board_noise_drawn_before_them(tmp_path):
    rig = default_rig()
    rig = rig.model_copy(update={"cameras": rig.cameras[:2]})
    seq = run_stage_for_test(SEQUENCE, tmp_path / "seq", params={"cycles": 1, "restarts": 1,
                                                                 "random_baseline_samples": 4})
    ideal = {**CALIB, "rig": rig, "max_frames": 2, "realism": "ideal"}
    first, metrics = _capture_sharing_cache(tmp_path, "a", seq, ideal)
    assert _calib_counts(metrics) == (0, 4, 2, 2)
    # More board poses: every board take changes, and so does the mirror take of a camera that sees
    # more poses (its noise is drawn after the board's, from the camera's one generator).
    more, metrics = _capture_sharing_cache(tmp_path, "d", seq, {**ideal, "calibration_poses": 4})
    seen_more = sum(len(list((more / "calib" / "charuco" / cam).iterdir())) !=
                    len(list((first / "calib" / "charuco" / cam).iterdir())) for cam in ("cam00", "cam01"))
    assert seen_more > 0 and _calib_counts(metrics) == (2 - seen_more, 2 + seen_more, 2, seen_more)
