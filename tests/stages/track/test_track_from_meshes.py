"""``track.source``: tracked meshes from elsewhere (OBJ folder or .npz, world space) instead of landmarks."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.testing import run_stage_for_test
from stages.track.eval_stage import STAGE as TRACK_EVAL
from stages.track.from_meshes import rigid_fit
from stages.track.stage import STAGE as TRACK
from track_synthetic import write_capture


@pytest.fixture(scope="module")
def studio(tmp_path_factory):
    """A 13-frame capture (no images needed), its perfect calibration, the truth and the truth's world meshes."""
    root = tmp_path_factory.mktemp("mesh_source")
    capture, calibrate, truth = write_capture(root, frames=13, render=False)
    frames = np.load(truth / "frames.npz")
    head = np.load(truth / "meshes.npz")["vertices"].astype(np.float64)
    world = np.einsum("tij,tvj->tvi", frames["world_from_head_R"], head) + frames["world_from_head_t"][:, None]
    return {"capture": capture, "calibrate": calibrate, "truth": truth, "index": frames["index"],
            "world": world, "faces": np.load(truth / "meshes.npz")["faces"], "root": root}


def _track(studio, work, params):
    inputs = {"capture": studio["capture"], "calibrate": studio["calibrate"]}
    out = run_stage_for_test(TRACK, work, inputs=inputs, params=params)
    ev = run_stage_for_test(TRACK_EVAL, work, inputs={"track": out, "capture.truth": studio["truth"]})
    return out, {**json.loads((out / "metrics.json").read_text()), **json.loads((ev / "metrics.json").read_text())}


def _write_obj(path, vertices, faces) -> None:
    lines = [f"v {x:.7f} {y:.7f} {z:.7f}" for x, y, z in vertices] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def test_every_frame_from_an_npz_in_millimetres(studio, tmp_path):
    np.savez(tmp_path / "meshes.npz", vertices=studio["world"] * 1000.0)  # no index: one per frame, in order
    out, m = _track(studio, tmp_path / "w", {"source": str(tmp_path / "meshes.npz"), "mesh_source": {"units_m": 0.001}})
    assert m["source_meshes"] == 13 and m["interpolated_frames"] == 0
    # The pose comes from the stable vertices only; what expressions do to them is the error left.
    # Measured: 0.013 deg, 0.011 mm, 0.012 / 0.015 mm.
    assert m["rotation_err_deg_max"] < 0.05, m["rotation_err_deg_max"]
    assert m["translation_err_mm_max"] < 0.05, m["translation_err_mm_max"]
    assert m["vertex_err_mm_mean_full"] < 0.05 and m["vertex_err_mm_mean_olat"] < 0.05
    tracking = np.load(out / "tracking.npz")
    assert tracking["fitted"].all() and np.isnan(tracking["landmark_reproj_px"]).all()
    assert tracking["weights"].shape == (13, len(tracking["expression_names"]))


def test_obj_meshes_of_some_frames_and_the_rest_interpolated(studio, tmp_path):
    folder = tmp_path / "objs"
    folder.mkdir()
    given = [0, 3, 6, 9, 12]  # the full-on frames, as a landmark tracker would give them
    for i in given:
        _write_obj(folder / f"{int(studio['index'][i]):06d}.obj", studio["world"][i], studio["faces"])
    out, m = _track(studio, tmp_path / "w", {"source": str(folder)})
    assert m["source_meshes"] == 5 and m["interpolated_frames"] == 8
    # Measured: 0.012 mm on the given frames, 0.25 mm interpolated, 0.015 deg.
    assert m["vertex_err_mm_mean_full"] < 0.05  # the given frames are kept as they are
    assert m["vertex_err_mm_mean_olat"] < 1.0  # interpolated, as landmark tracking interpolates its OLAT frames
    assert m["rotation_err_deg_max"] < 0.05
    assert len(list((out / "obj").glob("*.obj"))) == 3


def test_topology_mismatch_names_the_file_and_the_counts(studio, tmp_path):
    folder = tmp_path / "objs"
    folder.mkdir()
    _write_obj(folder / "000000.obj", studio["world"][0][:-10], np.zeros((0, 3), int))
    vertices = studio["world"].shape[1]
    with pytest.raises(InputError, match=rf"000000.obj: has {vertices - 10} vertices, the actor rig .* has {vertices}"):
        run_stage_for_test(TRACK, tmp_path / "w", inputs={"capture": studio["capture"], "calibrate": studio["calibrate"]},
                           params={"source": str(folder)})


def test_bad_mesh_sources_say_what_to_fix(studio, tmp_path):
    inputs = {"capture": studio["capture"], "calibrate": studio["calibrate"]}
    np.savez(tmp_path / "few.npz", vertices=studio["world"][:4])
    with pytest.raises(InputError, match="4 meshes and no 'index', but the capture has 13 frames"):
        run_stage_for_test(TRACK, tmp_path / "a", inputs=inputs, params={"source": str(tmp_path / "few.npz")})
    np.savez(tmp_path / "late.npz", vertices=studio["world"][:2], index=np.array([0, 99]))
    with pytest.raises(InputError, match="frame 99 is not a frame of the capture"):
        run_stage_for_test(TRACK, tmp_path / "b", inputs=inputs, params={"source": str(tmp_path / "late.npz")})
    (tmp_path / "named").mkdir()
    _write_obj(tmp_path / "named" / "smile.obj", studio["world"][0], studio["faces"])
    with pytest.raises(InputError, match="name the OBJ files by their frame index"):
        run_stage_for_test(TRACK, tmp_path / "c", inputs=inputs, params={"source": str(tmp_path / "named")})


def test_rigid_fit_recovers_a_pose():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(50, 3))
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    pose = rigid_fit(points, points @ R.T + [0.1, 0.2, -0.3])
    assert np.allclose(pose.R, R) and np.allclose(pose.t, [0.1, 0.2, -0.3])
