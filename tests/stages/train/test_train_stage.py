"""The train stage on a tiny synthetic capture: outputs and metrics, loss decrease, resume, rollback."""

from __future__ import annotations

import json
import logging
import shutil
import threading
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from pipeline.testing import run_stage_for_test
from stages.train import trainer as trainer_mod
from stages.train.splits import ALL_SPLITS, HELD_OUT_SPLITS, SPLITS, VAL_SPLITS
from stages.train.stage import STAGE
from tests.stages.train.train_synth import SMALL_AVATAR, small_model

BASE = {"avatar": SMALL_AVATAR, "image_width_px": 24, "batch_size": 2, "rays_per_image": 64, "eval_images": 2,
        "curve_every": 6, "curve_images": 1, "checkpoint_every": 4, "previews": 1, "threads": 1,
        "held_out_fraction": 1.0}  # the whole short "speech" take: every split gets frames


def assert_same_models(a: Path, b: Path, kinds: tuple[str, ...] = ("ours", "travatar")) -> None:
    """The stage outputs ``a`` and ``b`` hold bit-identical weights for every model in ``kinds``."""
    for kind in kinds:
        first = load_file(str(a / "models" / kind / "model.safetensors"))
        second = load_file(str(b / "models" / kind / "model.safetensors"))
        assert first.keys() == second.keys(), kind
        for key in first:
            assert torch.equal(first[key], second[key]), (kind, key)


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> dict[str, Path]:
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from train_synth import make_capture

    return make_capture(tmp_path_factory.mktemp("synth"), width_px=32, cameras=4, frames_per_take=(27, 9))


def test_stage_outputs_metrics_table_and_models(capture, tmp_path):
    out = run_stage_for_test(STAGE, tmp_path, capture, {**BASE, "iterations": 8, "baseline_iterations": 6})
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("iterations", "seconds", "iterations_per_second", "peak_memory_mb"):
        assert metrics[key] > 0
    for model in ("ours", "travatar"):
        for split in HELD_OUT_SPLITS:  # validation figures beside the test ones
            for name in ("psnr", "mae", "ssim", "lpips"):
                assert np.isfinite(metrics[f"{model}_{split}_{name}"]), (model, split, name)
    assert metrics["iterations"] == 8 and metrics["travatar_iterations"] == 6
    table = (out / "table.md").read_text()
    assert "novel light" in table and "TRAvatar*" in table
    for split, title in (("val_light", "validation light"), ("val_perf", "validation performance")):
        row = next(line for line in table.splitlines() if line.startswith(f"| {title} |"))
        assert f"{metrics[f'ours_{split}_psnr']:.2f}" in row
    fit_row = next(line for line in table.splitlines() if line.startswith("| training images (fit)"))
    assert f"{metrics['ours_train_psnr']:.2f}" in fit_row and f"{metrics['travatar_train_psnr']:.2f}" in fit_row
    # Expression distances: held-out frames of another take lie further from training than its own spacing.
    assert metrics["train_expression_spacing_mm"] > 0
    assert metrics["novel_perf_expression_distance_mm"] > metrics["train_expression_spacing_mm"]
    assert f"novel performance {metrics['novel_perf_expression_distance_mm']:.2f} mm" in table
    assert metrics["train_expression_reach_sd"] > 0 and metrics["novel_perf_expression_reach_sd"] >= 0
    assert f"novel performance {metrics['novel_perf_expression_reach_sd']:.1f}" in table
    for model in ("ours", "travatar"):
        for split in SPLITS:
            assert 0.0 <= metrics[f"{model}_{split}_uncovered_fraction"] <= 1.0
            assert 0.0 <= metrics[f"{model}_{split}_uncovered_error_share"] <= 1.0
    assert f"ours novel light {100 * metrics['ours_novel_light_uncovered_fraction']:.1f}%" in table
    for model in ("ours", "travatar"):  # the encoder's noise over its codes' spread, on the fitted frames
        assert 0.0 < metrics[f"{model}_latent_noise_to_code_spread"] < np.inf
    assert (out / "learning_curve.png").stat().st_size > 0
    curve = json.loads((out / "curve.json").read_text())
    assert [p[0] for p in curve["ours"]] == [0, 6] and [p[0] for p in curve["travatar"]] == [0, 6]
    splits = json.loads((out / "splits.json").read_text())
    manifest = json.loads((capture["capture"] / "manifest.json").read_text())
    takes = {f["index"]: f["take"] for f in manifest["frames"]}
    assert len(splits["held_out_bars"]) == 3
    assert all(takes[i] == "speech" for i in splits["novel_perf"] + splits["novel_both"])
    assert not set(splits["train"]) & set(splits["novel_light"] + splits["novel_perf"])
    # Validation: its own bars and frames (here the end of "rom": the test holds out all of "speech"), in no
    # other split, and none of them trains.
    assert len(splits["val_bars"]) == 2 and set(splits["val_bars"]).isdisjoint(splits["held_out_bars"])
    assert splits["val_segment"].startswith("rom[")
    frames = [i for name in ALL_SPLITS for i in splits[name]]
    assert len(frames) == len(set(frames))
    val = {i for name in VAL_SPLITS for i in splits[name]}
    assert val and val.isdisjoint(i for name in ("train",) + SPLITS for i in splits[name])
    lights = {f["index"]: f["light"] for f in manifest["frames"]}
    assert {lights[i] for i in splits["train"]}.isdisjoint(splits["val_bars"] + splits["held_out_bars"])
    from avatar.io import load_trained

    model, meta = load_trained(out / "models" / "travatar")
    assert meta["kind"] == "travatar" and set(meta["held_out_bars"]).isdisjoint(meta["basis_bars"])
    assert set(meta["val_bars"]) == set(splits["val_bars"]) and set(meta["val_bars"]).isdisjoint(meta["basis_bars"])
    # Novel light per held-out bar: one figure per bar among the split's evaluated images, in the table too.
    for model, name in (("ours", "ours"), ("travatar", "TRAvatar*")):
        by_bar = {int(k.rsplit("_bar", 1)[1]): v for k, v in metrics.items()
                  if k.startswith(f"{model}_novel_light_psnr_bar")}
        assert by_bar and set(by_bar) <= set(splits["held_out_bars"])
        bar_line = next(line for line in table.splitlines() if line.startswith("Novel light per held-out bar"))
        assert all(f"bar {b} {v:.2f}" in bar_line for b, v in by_bar.items()) and f"{name} bar" in bar_line


def test_rerun_differs_only_in_its_declared_run_records(capture, tmp_path):
    """Two runs of the same training write the same files but for ``metrics.json`` and the
    stage's run records, so the content key downstream stages see is the same."""
    from pipeline.hashing import hash_tree
    from pipeline.workspace import is_run_record

    params = {**BASE, "iterations": 8, "baseline_iterations": 6}
    outs = [run_stage_for_test(STAGE, tmp_path / f"run{i}", capture, params) for i in range(2)]

    def data_files(folder: Path) -> dict[str, str]:
        """The manifest the workspace would store, without what the content key leaves out."""
        return {e.relpath: e.digest for e in hash_tree(folder)[1] if not is_run_record(e.relpath, STAGE.run_records)}

    first, second = (data_files(out) for out in outs)
    assert "models/ours/model.safetensors" in first and "table.md" in first
    assert first == second
    # The records themselves do change between runs (wall-clock times), or declaring them would be moot.
    assert (outs[0] / "curve.json").read_bytes() != (outs[1] / "curve.json").read_bytes()


@pytest.mark.parametrize(("weight_average", "warmup"), [(0.0, 0), (0.9, 0), (0.0, 8)])
def test_resume_after_kill_continues_the_same_run(capture, tmp_path, monkeypatch, caplog, weight_average, warmup):
    # warmup 8: the kill and the resume (at iteration 4) fall inside the warm-up.
    params = {**BASE, "iterations": 10, "baseline": False, "lpips": False, "curve_every": 0,
              "weight_average": weight_average, "lr_warmup_iterations": warmup}
    whole = run_stage_for_test(STAGE, tmp_path / "a", capture, params)

    calls = {"n": 0}
    real_step = trainer_mod.ModelTrainer.step

    def dying_step(self):
        calls["n"] += 1
        if calls["n"] == 7:
            raise KeyboardInterrupt("killed")
        return real_step(self)

    monkeypatch.setattr(trainer_mod.ModelTrainer, "step", dying_step)
    with pytest.raises(KeyboardInterrupt):
        run_stage_for_test(STAGE, tmp_path / "b", capture, params)
    monkeypatch.setattr(trainer_mod.ModelTrainer, "step", real_step)
    shutil.rmtree(tmp_path / "b" / "train")  # the runner never commits a failed stage's output
    with caplog.at_level(logging.INFO):
        resumed = run_stage_for_test(STAGE, tmp_path / "b", capture, params)
    assert "resumed at iteration 4" in caplog.text
    assert_same_models(whole, resumed, ("ours",))


def test_weight_average_saves_the_moving_average_of_the_iterates(capture, tmp_path, monkeypatch):
    keep_at_most = 0.6
    params = {**BASE, "iterations": 6, "baseline": False, "lpips": False, "curve_every": 0,
              "weight_average": keep_at_most}
    start: dict[str, torch.Tensor] = {}
    iterates: list[tuple[int, dict[str, torch.Tensor]]] = []
    real_fresh, real_update = trainer_mod.ModelTrainer._fresh_average, trainer_mod.ModelTrainer._update_average

    def recording_fresh(self):
        average = real_fresh(self)
        start.update({k: v.clone() for k, v in average.items()})
        return average

    def recording_update(self):
        iterates.append((self.state.iteration, {k: p.detach().clone() for k, p in self.model.named_parameters()}))
        real_update(self)

    monkeypatch.setattr(trainer_mod.ModelTrainer, "_fresh_average", recording_fresh)
    monkeypatch.setattr(trainer_mod.ModelTrainer, "_update_average", recording_update)
    out = run_stage_for_test(STAGE, tmp_path, capture, params)
    assert [i for i, _ in iterates] == list(range(6))
    expected = {k: v.double() for k, v in start.items()}
    for i, weights in iterates:
        keep = min(keep_at_most, (1 + i) / (10 + i))
        expected = {k: keep * v + (1 - keep) * weights[k].double() for k, v in expected.items()}
    saved = load_file(str(out / "models" / "ours" / "model.safetensors"))
    last = iterates[-1][1]
    moved = [k for k in expected if not torch.allclose(last[k], expected[k].float(), atol=1e-6)]
    assert moved, "the average should differ from the last iterate"
    for key, value in expected.items():
        torch.testing.assert_close(saved[key], value.float(), atol=1e-6, rtol=1e-5, msg=key)


def test_models_trained_side_by_side_are_the_models_trained_one_after_another(capture, tmp_path):
    params = {**BASE, "iterations": 8, "baseline_iterations": 6, "lpips": False}
    one = run_stage_for_test(STAGE, tmp_path / "one", capture, {**params, "parallel_models": 1})
    two = run_stage_for_test(STAGE, tmp_path / "two", capture, {**params, "parallel_models": 2})
    assert_same_models(one, two)
    m1, m2 = (json.loads((out / "metrics.json").read_text()) for out in (one, two))
    assert m2["ours_iterations"] == 8 and m2["travatar_iterations"] == 6
    for split in SPLITS:
        assert m1[f"travatar_{split}_psnr"] == m2[f"travatar_{split}_psnr"], split


def test_ours_trained_alone_is_ours_trained_beside_the_baseline(capture, tmp_path):
    """benchmarks/bench_seeds.py's SEEDS_MODELS=ours pairs ours-alone runs with runs of both models, seed for seed."""
    params = {**BASE, "iterations": 8, "lpips": False, "curve_every": 4}
    alone = run_stage_for_test(STAGE, tmp_path / "alone", capture, {**params, "baseline": False})
    beside = run_stage_for_test(STAGE, tmp_path / "beside", capture, {**params, "parallel_models": 2})
    assert_same_models(alone, beside, ("ours",))
    m1, m2 = (json.loads((out / "metrics.json").read_text()) for out in (alone, beside))
    assert "travatar_val_light_psnr" not in m1
    for split in SPLITS:
        assert m1[f"ours_{split}_psnr"] == m2[f"ours_{split}_psnr"], split


def test_init_and_sampling_seeds_each_take_over_their_part_of_seed(capture, tmp_path):
    params = {**BASE, "iterations": 3, "baseline": False, "lpips": False, "previews": 0, "curve_every": 0}
    seed0 = run_stage_for_test(STAGE, tmp_path / "a", capture, {**params, "seed": 0})
    overridden = run_stage_for_test(STAGE, tmp_path / "b", capture,
                                    {**params, "seed": 5, "init_seed": 0, "sampling_seed": 0})
    assert_same_models(seed0, overridden, ("ours",))  # both parts of seed 5 replaced: seed 0's run
    other_sampling = run_stage_for_test(STAGE, tmp_path / "c", capture, {**params, "seed": 0, "sampling_seed": 5})
    with pytest.raises(AssertionError):
        assert_same_models(seed0, other_sampling, ("ours",))


def test_a_model_failing_side_by_side_stops_the_other_and_both_resume(capture, tmp_path, monkeypatch, caplog):
    params = {**BASE, "iterations": 10, "lpips": False, "curve_every": 0, "parallel_models": 2}
    real_step = trainer_mod.ModelTrainer.step
    ours_held = threading.Event()

    def failing_step(self):
        if self.r.kind == "travatar" and self.state.iteration == 6:
            # Fail only once ours is held, so ours is mid-run whichever thread is faster.
            assert ours_held.wait(timeout=60)
            raise RuntimeError("travatar broke")
        if self.r.kind == "ours" and self.state.iteration == 3:
            # Hold ours mid-run until the failure beside it asks it to stop.
            ours_held.set()
            assert self.stop_event is not None and self.stop_event.wait(timeout=60)
        return real_step(self)

    monkeypatch.setattr(trainer_mod.ModelTrainer, "step", failing_step)
    # The baseline's own error reaches the caller, not the stop it caused beside it.
    with pytest.raises(RuntimeError, match="travatar broke"):
        run_stage_for_test(STAGE, tmp_path / "b", capture, params)
    monkeypatch.setattr(trainer_mod.ModelTrainer, "step", real_step)
    shutil.rmtree(tmp_path / "b" / "train")  # the runner never commits a failed stage's output
    with caplog.at_level(logging.INFO):
        resumed = run_stage_for_test(STAGE, tmp_path / "b", capture, params)
    # Each resumes from its last checkpoint (every 4 iterations): ours was stopped after its 4th.
    assert "travatar: resumed at iteration 4" in caplog.text and "ours: resumed at iteration 4" in caplog.text
    whole = run_stage_for_test(STAGE, tmp_path / "a", capture, {**params, "parallel_models": 1})
    assert_same_models(whole, resumed)


def test_side_by_side_needs_one_process(capture, tmp_path):
    from pipeline.errors import ConfigError

    with pytest.raises(ConfigError, match="parallel_models"):
        run_stage_for_test(STAGE, tmp_path, capture, {**BASE, "iterations": 2, "processes": 2, "parallel_models": 2})


def test_the_raymarch_kernels_train_the_same_model(capture, tmp_path, caplog):
    import avatar.raymarch_fused as fused

    if fused.fused_module(required=False) is None:
        pytest.skip("the fused raymarcher cannot be built here (no C++ compiler)")
    runs = {}
    for kernel in ("torch", "fused"):
        params = {**BASE, "iterations": 8, "baseline": False, "raymarch_kernel": kernel}
        with caplog.at_level(logging.INFO):
            runs[kernel] = run_stage_for_test(STAGE, tmp_path / kernel, capture, params)
    assert "raymarcher: torch (train.raymarch_kernel=torch)" in caplog.text
    assert "raymarcher: fused (train.raymarch_kernel=fused)" in caplog.text
    metrics = {k: json.loads((out / "metrics.json").read_text()) for k, out in runs.items()}
    for split in SPLITS:  # the same model up to float rounding: the same held-out figures
        assert metrics["fused"][f"ours_{split}_psnr"] == pytest.approx(metrics["torch"][f"ours_{split}_psnr"], abs=0.02)


def test_fused_kernel_without_a_compiler_is_a_config_error(capture, tmp_path, monkeypatch):
    import avatar.raymarch_fused as fused
    from pipeline.errors import ConfigError

    def no_compiler():
        raise RuntimeError("Error building extension: c++: command not found")

    monkeypatch.setattr(fused, "_module", None)
    monkeypatch.setattr(fused, "_build_error", None)
    monkeypatch.setattr(fused, "_build", no_compiler)
    with pytest.raises(ConfigError, match="train.raymarch_kernel=fused: .*apt-get install g"):
        run_stage_for_test(STAGE, tmp_path, capture, {**BASE, "iterations": 2, "raymarch_kernel": "fused"})


def test_few_iterations_lower_the_loss(capture, tmp_path):
    from stages.train.data import load_train_data

    data = load_train_data(capture, 24, logging.getLogger("test"))
    config, tensors, model, renderer = small_model(data)
    tr = trainer_mod.ModelTrainer(renderer, tensors, np.arange(len(data.bar)), iterations=40, batch_size=2,
                                  rays_per_image=128, lr=3e-3, weights=trainer_mod.LossWeights(), seed=0,
                                  ckpt_path=tmp_path / "c.pt", checkpoint_every=100, spike_factor=10.0,
                                  log=logging.getLogger("test"))
    batch = tr.sample_batch()
    eps = torch.zeros(2, config.latent_dim)
    before = tr.losses(*batch, eps)[1]["loss"]
    for _ in range(40):
        tr.step()
    after = tr.losses(*batch, eps)[1]["loss"]
    assert after < 0.8 * before


def test_nan_loss_rolls_back_with_a_warning(capture, tmp_path, monkeypatch, caplog):
    real_losses = trainer_mod.ModelTrainer.losses
    calls = {"n": 0}

    def poisoned(self, *args):
        calls["n"] += 1
        total, terms = real_losses(self, *args)
        if calls["n"] == 6:
            return total * float("nan"), {**terms, "loss": float("nan")}
        return total, terms

    monkeypatch.setattr(trainer_mod.ModelTrainer, "losses", poisoned)
    params = {**BASE, "iterations": 8, "baseline": False, "lpips": False, "curve_every": 0}
    with caplog.at_level(logging.WARNING):
        out = run_stage_for_test(STAGE, tmp_path, capture, params)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["ours_rollbacks"] == 1
    assert "rolled back to the last good checkpoint" in caplog.text
    state = load_file(str(out / "models" / "ours" / "model.safetensors"))
    assert all(bool(torch.isfinite(v.float()).all()) for v in state.values())


def test_fit_frames_optimises_on_the_first_training_frames_only(capture, tmp_path, monkeypatch):
    """The capacity diagnostic: fit_frames=1 samples one frame, yet the splits and layout use every frame."""
    seen: set[int] = set()
    real_sample = trainer_mod.ModelTrainer.sample_batch

    def recording_sample(self):
        frames, cams, pix = real_sample(self)
        seen.update(int(f) for f in frames)
        return frames, cams, pix

    monkeypatch.setattr(trainer_mod.ModelTrainer, "sample_batch", recording_sample)
    params = {**BASE, "iterations": 6, "baseline": False, "lpips": False, "curve_every": 0, "fit_frames": 1}
    out = run_stage_for_test(STAGE, tmp_path, capture, params)
    metrics = json.loads((out / "metrics.json").read_text())
    splits = json.loads((out / "splits.json").read_text())
    assert len(seen) == 1  # one frame (data index; splits.json holds capture frame numbers)
    assert metrics["fitted_frames"] == 1 and metrics["train_frames"] == len(splits["train"]) > 1
    assert np.isfinite(metrics["ours_train_psnr"]) and np.isfinite(metrics["ours_novel_light_psnr"])


def test_coverage_metrics_count_the_foreground_left_transparent():
    from stages.train.evaluate import coverage_metrics

    matte = torch.zeros(2, 4, 4)
    matte[:, :2] = 1.0  # 16 foreground pixels
    alpha = torch.ones(2, 4, 4)
    alpha[0, 0, :2] = 0.0  # 2 of them transparent in the render
    target = torch.zeros(2, 4, 4, 3)
    pred = torch.zeros(2, 4, 4, 3)
    pred[0, 0, 0] = 1.0  # error 3 on an uncovered pixel
    pred[1, 3, 3] = 1.0  # error 3 in the background, covered
    out = coverage_metrics(pred, alpha, target, matte)
    assert out == {"uncovered_fraction": 2 / 16, "uncovered_error_share": 0.5}
    assert coverage_metrics(target, alpha, target, matte)["uncovered_error_share"] == 0.0


def test_psnr_by_bar_groups_the_images_by_the_bar_that_lit_them():
    from stages.train.evaluate import psnr_by_bar

    target = torch.rand(4, 6, 6, 3, generator=torch.Generator().manual_seed(0)) * 0.5 + 0.25
    pred = target.clone()
    pred[2:] += 0.1  # bar 5's images off by 0.1 everywhere: 20 dB
    out = psnr_by_bar(pred, target, [3, 3, 5, 5], scale=False)
    assert set(out) == {3, 5} and out[3] > 100 and out[5] == pytest.approx(20.0, abs=1e-3)
    # Held-out lights are compared at the ground truth's exposure: a uniformly brighter render is exact.
    assert psnr_by_bar(1.7 * target, target, [3, 3, 5, 5], scale=True)[5] > 100
    assert psnr_by_bar(1.7 * target, target, [3, 3, 5, 5], scale=False)[5] < 20
