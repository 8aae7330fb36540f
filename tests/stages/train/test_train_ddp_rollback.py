"""Rollback under data-parallel training: a NaN or a loss spike that only one of two gloo ranks sees
rolls both back to the same last checkpoint, and they go on in step. Gradient clipping keeps them in
step too."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

dist = pytest.importorskip("torch.distributed")
if not dist.is_available() or not dist.is_gloo_available():
    pytest.skip("torch.distributed with the gloo backend is not available", allow_module_level=True)

sys.path.insert(0, str(Path(__file__).parent))
from ddp_rollback_support import rollback_rank  # noqa: E402

ITERATIONS, NAN_AT, SPIKE_AT = 56, 3, 53  # spikes count only after 50 iterations (a warm running mean)


@pytest.mark.slow
def test_both_ranks_roll_back_to_the_same_checkpoint_and_go_on_identically(tmp_path):
    import torch.multiprocessing as mp
    from train_synth import make_capture

    capture = make_capture(tmp_path / "synth", width_px=32, cameras=2, frames_per_take=(9, 3))
    mp.spawn(rollback_rank, args=(2, str(tmp_path / "init"), capture, tmp_path, ITERATIONS, NAN_AT, SPIKE_AT),
             nprocs=2, join=True)
    ranks = [json.loads((tmp_path / f"rank{r}.json").read_text()) for r in range(2)]
    assert len(ranks[0]) == ITERATIONS and ranks[0] == ranks[1]  # same weights, rollbacks, lr at every step
    steps = ranks[0]  # steps[i]: after iteration i + 1; checkpoints after iterations 2, 4, ...
    # The NaN in the 4th iteration (index 3) restores the checkpoint written after iteration 2 ...
    assert steps[NAN_AT]["rollbacks"] == 1 and steps[NAN_AT - 1]["rollbacks"] == 0
    assert steps[NAN_AT]["digest"] == steps[1]["digest"] != steps[NAN_AT - 1]["digest"]
    assert steps[NAN_AT]["lr"] == steps[NAN_AT - 1]["lr"] / 2
    # ... the spike in the 54th (index 53) the one written after iteration 52, not iteration 53's weights.
    assert steps[SPIKE_AT]["rollbacks"] == 2 and steps[SPIKE_AT - 1]["rollbacks"] == 1
    assert steps[SPIKE_AT]["digest"] == steps[SPIKE_AT - 2]["digest"] != steps[SPIKE_AT - 1]["digest"]
    # Training goes on after each rollback (the weights move again), in step on both ranks.
    assert steps[NAN_AT + 1]["digest"] != steps[NAN_AT]["digest"]
    assert steps[-1]["digest"] != steps[SPIKE_AT]["digest"]


@pytest.mark.slow
def test_both_ranks_clip_the_same_steps_and_stay_in_step(tmp_path):
    """``grad_clip_factor`` reads the gradient after DDP's all-reduce, so both ranks bound the same steps."""
    import torch.multiprocessing as mp
    from train_synth import make_capture

    capture = make_capture(tmp_path / "synth", width_px=32, cameras=2, frames_per_take=(9, 3))
    iterations = 70
    mp.spawn(rollback_rank, args=(2, str(tmp_path / "init"), capture, tmp_path, iterations, -1, -1, 1.05),
             nprocs=2, join=True)
    ranks = [json.loads((tmp_path / f"rank{r}.json").read_text()) for r in range(2)]
    assert len(ranks[0]) == iterations and ranks[0] == ranks[1]  # same weights and clipped steps at every step
    assert ranks[0][-1]["rollbacks"] == 0
    # A bound 5% over the running mean catches some of the 19 steps after the first 51, never those.
    assert ranks[0][50]["clipped_steps"] == 0 < ranks[0][-1]["clipped_steps"] <= iterations - 51
