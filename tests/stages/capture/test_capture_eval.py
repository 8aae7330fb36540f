"""capture_eval: counts wrong lights, missed drops and false drops against the truth."""

import json

import numpy as np

from pipeline.testing import run_stage_for_test
from stages.capture.eval_stage import STAGE as CAPTURE_EVAL


def test_capture_eval_counts_each_kind_of_mistake(tmp_path):
    cap, truth = tmp_path / "cap", tmp_path / "truth"
    cap.mkdir(), truth.mkdir()
    lit = ["F", 3, 7, "F", None, 9]
    received = np.array([[1, 1, 1, 1, 1, 1], [1, 0, 1, 1, 1, 2]])  # cam1 lost frame 1, repeated frame 5
    frames = [{"index": 0, "light": "F", "status": "ok"},       # right
              {"index": 1, "light": 3, "status": "ok"},         # missed drop (cam1 lost it)
              {"index": 2, "light": 3, "status": "ok"},         # wrong light
              {"index": 3, "light": "F", "status": "dropped"},  # false drop
              {"index": 4, "light": None, "status": "dropped"},  # right: nothing was lit
              {"index": 5, "light": 9, "status": "ok"}]         # right: a repeat is still a delivered image
    (cap / "manifest.json").write_text(json.dumps({"frames": frames}))
    (truth / "lights_per_pulse.json").write_text(json.dumps(lit))
    np.savez(truth / "frames.npz", received=received)
    out = run_stage_for_test(CAPTURE_EVAL, tmp_path, inputs={"capture": cap, "capture.truth": truth})
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics == {"label_errors": 1, "missed_drops": 1, "false_drops": 1, "label_accuracy": 0.5}
