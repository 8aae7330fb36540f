"""The paper preset's train and relight code paths run on a CPU, reduced (benchmarks/smoke_paper.py, make smoke-paper)."""

from __future__ import annotations

import pytest

from benchmarks.smoke_paper import CPU_REDUCTIONS, paper_params, run

pytestmark = pytest.mark.slow


def test_the_reductions_leave_the_papers_sizes():
    train = paper_params("train")
    assert train["image_width_px"] == 0  # the capture's 768 px
    assert train["avatar"]["prims_per_side"] == 64 and train["avatar"]["voxels_per_side"] == 16
    assert train["avatar"]["latent_dim"] == 256 and train["held_out_fraction"] == 1.0
    assert paper_params("relight")["width_px"] == 768 and paper_params("relight")["height_px"] == 1024
    assert set(CPU_REDUCTIONS) == {"train", "relight"}


def test_the_paper_preset_trains_and_relights_at_768_by_1024(tmp_path):
    result = run(tmp_path)
    assert result["problems"] == []
    memory = result["projected_paper_training_memory_batch12"]
    # The RGB voxels alone: 12 images x 4096 primitives x 16^3 voxels x 3 colours x 4 bytes = 2.4 GB.
    assert memory["batch"] == 12 and 2.4 < memory["decoder_activations_gb"] < memory["projected_peak_gb"] < 139.0
