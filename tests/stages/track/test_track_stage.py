"""The track stage and its evaluation on small virtual-studio captures."""

from __future__ import annotations

import json

import numpy as np
import pytest

from track_synthetic import write_capture
from pipeline.errors import InputError
from pipeline.testing import run_stage_for_test
from stages.track.eval_stage import STAGE as TRACK_EVAL
from stages.track.stage import STAGE as TRACK


def test_capture_without_full_on_frames_is_a_clear_error(tmp_path):
    capture, calibrate, _ = write_capture(tmp_path, frames=4, render=False, full_on_every=1000)
    manifest = json.loads((capture / "manifest.json").read_text())
    for frame in manifest["frames"]:
        frame["light"] = 5
    (capture / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="no usable full-on"):
        run_stage_for_test(TRACK, tmp_path / "work", inputs={"capture": capture, "calibrate": calibrate})


def test_mediapipe_finds_the_face_in_a_rendered_frame(tmp_path):
    from scene.image_io import read_exr
    from stages.track.landmarks import DetectorParams, FaceMeshDetector

    capture, calibrate, _ = write_capture(tmp_path, frames=1, cameras=(0, 1))
    with FaceMeshDetector(DetectorParams()) as detector:
        for cam in ("cam00", "cam01"):
            image = read_exr(capture / "frames" / cam / "000000.exr")
            found = detector.detect(image)
            assert found.ok, found.status
            assert found.score > 0.5
            # The landmarks cover the middle of the image, where the studio frames the head.
            centre = np.nanmean(found.uv_px, axis=0)
            assert abs(centre[0] - image.shape[1] / 2) < image.shape[1] / 4
            missed = detector.detect(np.zeros_like(image))
            assert not missed.ok
    # Through the executor job with a cache: the second pass reads the cache, a corrupt entry is a miss.
    from stages.track.landmarks import detect_files

    paths = [capture / "frames" / "cam00" / "000000.exr", capture / "frames" / "cam00" / "missing.exr"]
    cache = tmp_path / "cache"
    cache.mkdir()
    first = detect_files((paths, DetectorParams(), cache))
    assert first[0].ok and first[1].status.startswith("unreadable")
    entries = list(cache.glob("*.npz"))
    assert len(entries) == 1
    again = detect_files((paths, DetectorParams(), cache))
    assert np.array_equal(again[0].uv_px, first[0].uv_px) and np.array_equal(again[0].contour_px, first[0].contour_px)
    entries[0].write_bytes(b"not an npz")
    rebuilt = detect_files((paths, DetectorParams(), cache))
    assert rebuilt[0].ok and np.allclose(rebuilt[0].uv_px, first[0].uv_px)


@pytest.mark.slow
def test_track_stage_end_to_end(tmp_path, small_capture):
    capture, calibrate, truth = small_capture
    out = run_stage_for_test(TRACK, tmp_path, inputs={"capture": capture, "calibrate": calibrate})
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["landmark_reproj_px_mean"] < 3.0
    assert metrics["fit_frames_per_second"] > 0
    tracking = np.load(out / "tracking.npz")
    assert tracking["weights"].shape == (13, 9)
    meshes = np.load(out / "meshes.npz")
    assert meshes["vertices"].shape[0] == 13 and meshes["vertices"].dtype == np.float32
    assert (out / "overlay.png").is_file() and list((out / "obj").glob("*.obj"))
    ev = run_stage_for_test(TRACK_EVAL, tmp_path, inputs={"track": out, "capture.truth": truth})
    acc = json.loads((ev / "metrics.json").read_text())
    print("track on a 13-frame, 5-camera capture:", metrics, acc)
    assert acc["vertex_err_mm_mean_full"] < 1.5
    assert acc["vertex_err_mm_mean_olat"] < 2.0
    assert acc["rotation_err_deg_mean"] < 0.3
    assert acc["translation_err_mm_mean"] < 1.0
    # Stabilised cameras from the track: every frame, every camera.
    from stages.stabilize.eval_stage import STAGE as STABILIZE_EVAL
    from stages.stabilize.stage import STAGE as STABILIZE

    stab = run_stage_for_test(STABILIZE, tmp_path, inputs={"track": out, "calibrate": calibrate})
    head = json.loads((stab / "cameras_head.json").read_text())
    assert len(head["frames"]) == 13 and all(len(cams) == 5 for cams in head["frames"].values())
    stab_eval = run_stage_for_test(STABILIZE_EVAL, tmp_path, inputs={"stabilize": stab, "capture.truth": truth})
    assert json.loads((stab_eval / "metrics.json").read_text())["head_pose_residual_deg_max"] < 1.0
