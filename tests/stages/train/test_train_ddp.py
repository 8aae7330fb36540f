"""Data-parallel training (torch.distributed, gloo, 2 CPU processes) against one process.

The same global batch split over two ranks must give the same loss curve as one process
(gradients are averaged over equal shares of batch means), and the train stage launched with
``processes: 2`` (torchrun) must write the same outputs and resume a checkpoint written by a
single-process run.
"""

from __future__ import annotations

import json
import logging
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

dist = pytest.importorskip("torch.distributed")
if not dist.is_available() or not dist.is_gloo_available():
    pytest.skip("torch.distributed with the gloo backend is not available", allow_module_level=True)

sys.path.insert(0, str(Path(__file__).parent))
from ddp_support import loss_curve, rank_main  # noqa: E402
from train_synth import SMALL_AVATAR  # noqa: E402

from pipeline.errors import ConfigError  # noqa: E402
from pipeline.testing import run_stage_for_test  # noqa: E402
from stages.train import trainer as trainer_mod  # noqa: E402
from stages.train.stage import STAGE  # noqa: E402

BASE = {"avatar": SMALL_AVATAR, "image_width_px": 24, "batch_size": 2, "rays_per_image": 64, "eval_images": 2,
        "curve_every": 0, "curve_images": 1, "checkpoint_every": 4, "previews": 1, "threads": 1,
        "held_out_fraction": 1.0, "iterations": 6, "baseline": False, "lpips": False}


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> dict[str, Path]:
    from train_synth import make_capture

    return make_capture(tmp_path_factory.mktemp("synth"), width_px=32, cameras=4, frames_per_take=(27, 9))


def test_two_gloo_ranks_give_the_single_process_loss_curve(capture, tmp_path):
    import torch.multiprocessing as mp

    steps, batch = 5, 4
    mp.spawn(rank_main, args=(2, str(tmp_path / "init"), capture, tmp_path, steps, batch), nprocs=2, join=True)
    ranks = [json.loads((tmp_path / f"rank{r}.json").read_text()) for r in range(2)]
    assert ranks[0] == ranks[1]  # the averaged terms: every rank sees the global batch's loss
    single = loss_curve(capture, tmp_path, steps, batch)
    grad_ddp, grad_halves, grad_one = (torch.load(tmp_path / f"grad_{n}.pt") for n in ("2_0", "halves", "1_0"))
    # DDP's step is exactly the mean of the two shares' gradients ...
    assert float((grad_ddp - grad_halves).norm()) < 1e-5 * float(grad_one.norm())
    # ... which is the whole batch's gradient up to the raymarcher's sensitivity to float
    # rounding: its box gradients are piecewise (sample membership, voxel cells, opacity
    # saturation), and the 1e-16 changes in the decoded boxes that batch-size-dependent BLAS
    # blocking causes move them by ~1% (measured; with equal box values the sum is exact).
    assert float((grad_ddp - grad_one).norm()) < 2e-2 * float(grad_one.norm())
    for key in ("loss", "pho", "geo", "mat"):
        ddp = np.array([t[key] for t in ranks[0]])
        one = np.array([t[key] for t in single])
        np.testing.assert_allclose(ddp[0], one[0], rtol=1e-5, err_msg=key)  # same model, same batch
        # Later steps drift apart by the rounding above, amplified by Adam: measured over seeds
        # 0-2 at 5 steps, the largest term differs by 0.12-0.52% (0.18-0.36% before rays were
        # computed per batch), so the curve is held to 1%; a wrong step itself (a rank training
        # on the wrong share, unsynchronised gradients) is caught exactly by the checks above.
        np.testing.assert_allclose(ddp, one, rtol=1e-2, err_msg=key)
    # The curve moves (the comparison is not between two constant sequences).
    assert len({round(t["loss"], 6) for t in single}) == steps


def test_a_ddp_trainer_is_freed_without_a_garbage_collection(capture, tmp_path):
    """The DDP wrapper must not outlive its trainer: a reference cycle kept it (and the process
    group it holds) alive past destroy_process_group, and a rank aborted at exit in CI."""
    import gc
    import weakref

    from stages.train.data import load_train_data
    from train_synth import small_model

    dist.init_process_group("gloo", init_method=f"file://{tmp_path / 'init'}", rank=0, world_size=1)
    # The first optimizer a process builds imports torch._dynamo, whose import leaves frames
    # (the caller's among them) in cycles; build one first so only the trainer's own references count.
    torch.optim.Adam([torch.zeros(1, requires_grad=True)])
    gc.collect()
    gc.disable()
    try:
        data = load_train_data(capture, 24, logging.getLogger("test"))
        _, tensors, _, renderer = small_model(data)
        tr = trainer_mod.ModelTrainer(renderer, tensors, np.arange(len(data.bar)), iterations=1, batch_size=4,
                                      rays_per_image=16, lr=1e-3, weights=trainer_mod.LossWeights(), seed=0,
                                      ckpt_path=tmp_path / "c.pt", checkpoint_every=100, spike_factor=10.0,
                                      log=logging.getLogger("test"), rank=0, world_size=2)
        wrapper = weakref.ref(tr._ddp_loss)
        assert wrapper() is not None
        del tr
        assert wrapper() is None
    finally:
        gc.enable()
        dist.destroy_process_group()


def test_stage_on_two_processes_resumes_a_single_process_checkpoint(capture, tmp_path, monkeypatch, caplog):
    whole = run_stage_for_test(STAGE, tmp_path / "a", capture, BASE)

    calls = {"n": 0}
    real_step = trainer_mod.ModelTrainer.step

    def dying_step(self):
        calls["n"] += 1
        if calls["n"] == 6:
            raise KeyboardInterrupt("killed")
        return real_step(self)

    monkeypatch.setattr(trainer_mod.ModelTrainer, "step", dying_step)
    with pytest.raises(KeyboardInterrupt):
        run_stage_for_test(STAGE, tmp_path / "b", capture, BASE)  # one process, killed after its checkpoint at 4
    monkeypatch.setattr(trainer_mod.ModelTrainer, "step", real_step)
    shutil.rmtree(tmp_path / "b" / "train")
    with caplog.at_level(logging.INFO):
        ddp = run_stage_for_test(STAGE, tmp_path / "b", capture, {**BASE, "processes": 2})
    assert "DDP training on 2 processes" in caplog.text
    assert "ours: resumed at iteration 4" in caplog.text
    assert not list((tmp_path / "b" / ".cache" / "train" / "ddp_jobs").iterdir())  # job files cleaned up
    a = load_file(str(whole / "models" / "ours" / "model.safetensors"))
    b = load_file(str(ddp / "models" / "ours" / "model.safetensors"))
    for key in a:
        torch.testing.assert_close(b[key], a[key], rtol=0, atol=2e-3, msg=key)
    ma, mb = (json.loads((p / "metrics.json").read_text()) for p in (whole, ddp))
    assert set(ma) == set(mb) and mb["iterations"] == 6
    assert abs(ma["ours_novel_light_psnr"] - mb["ours_novel_light_psnr"]) < 0.05
    assert sorted(p.name for p in whole.iterdir()) == sorted(p.name for p in ddp.iterdir())


def test_batch_that_does_not_split_evenly_is_a_config_error(capture, tmp_path):
    with pytest.raises(ConfigError, match="does not divide by train.processes"):
        run_stage_for_test(STAGE, tmp_path, capture, {**BASE, "batch_size": 3, "processes": 2})
