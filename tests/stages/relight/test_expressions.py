"""Blendshape CSVs: ARKit names map to the ICT rig; unknown names and bad numbers are clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from stages.relight.expressions import arkit_to_ict, meshes_from_weights, read_weights_csv

ICT = ("jawOpen", "eyeBlink_L", "eyeBlink_R", "mouthSmile_L")


def test_arkit_names_map_to_ict():
    assert arkit_to_ict("eyeBlinkLeft") == "eyeBlink_L" and arkit_to_ict("jawOpen") == "jawOpen"


def test_csv_reads_weights(tmp_path):
    path = tmp_path / "w.csv"
    path.write_text("Timecode,jawOpen,eyeBlinkLeft\n0,0.5,1.0\n1,0.25,0\n")
    w = read_weights_csv(path, ICT)
    assert w.shape == (2, 4) and w[0, 0] == 0.5 and w[0, 1] == 1.0 and w[1, 0] == 0.25


def test_unknown_names_are_listed(tmp_path):
    path = tmp_path / "w.csv"
    path.write_text("jawOpen,mouthFrownSideways\n0.5,1\n")
    with pytest.raises(ValueError, match=r"w.csv.*mouthFrownSideways"):
        read_weights_csv(path, ICT)


def test_bad_number_names_row_and_column(tmp_path):
    path = tmp_path / "w.csv"
    path.write_text("jawOpen\n0.5\nabc\n")
    with pytest.raises(ValueError, match=r"row 3, column 'jawOpen'"):
        read_weights_csv(path, ICT)


def test_projection_onto_the_actor_rig_reproduces_its_poses():
    rng = np.random.default_rng(0)
    neutral = rng.normal(size=(10, 3))
    offsets = rng.normal(size=(2, 10, 3))  # the actor's two scanned poses
    ict = np.stack([offsets[0], offsets[1], np.zeros((10, 3)), np.zeros((10, 3))])  # generic shapes
    meshes = meshes_from_weights(np.array([[0.5, 1.0, 0, 0]]), ict, neutral, offsets)
    assert np.allclose(meshes[0], neutral + 0.5 * offsets[0] + offsets[1], atol=1e-5)
