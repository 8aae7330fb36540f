"""The train stage's capacity mode (rule's choice, capacity.json, metrics) and scheduled pruning."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
import torch

from avatar.capacity import CapacityRule, CaptureStats, choose_capacity, latent_size
from avatar.config import AvatarConfig
from pipeline.errors import ConfigError
from pipeline.progress import SilentProgress
from pipeline.testing import run_stage_for_test
from stages.train import trainer as trainer_mod
from stages.train.setup import capacity_of
from stages.train.stage import STAGE, TrainParams
from tests.stages.train.train_synth import SMALL_AVATAR, small_model

BASE = {"avatar": SMALL_AVATAR, "image_width_px": 24, "batch_size": 2, "rays_per_image": 64, "eval_images": 2,
        "curve_every": 4, "curve_images": 1, "checkpoint_every": 100, "previews": 0, "threads": 1,
        "held_out_fraction": 1.0, "baseline": False, "lpips": False}


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> dict[str, Path]:
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from train_synth import make_capture

    return make_capture(tmp_path_factory.mktemp("synth"), width_px=32, cameras=3, frames_per_take=(21, 9))


def test_auto_capacity_is_the_rules_choice_and_is_reported(capture, tmp_path):
    # The avatar section's latent size (32) is the rule's to replace, from the meshes' expression modes.
    base_avatar = {**SMALL_AVATAR, "latent_dim": 32}
    out = run_stage_for_test(STAGE, tmp_path, capture, {**BASE, "avatar": base_avatar, "capacity": "auto",
                                                          "iterations": 8, "rays_per_image": 32})
    metrics = json.loads((out / "metrics.json").read_text())
    report = json.loads((out / "capacity.json").read_text())
    inputs = report["inputs"]
    assert report["mode"] == "auto" and inputs["image_width_px"] == 24 and inputs["image_height_px"] == 32
    assert 5 < inputs["footprint_px"] <= 24 and inputs["frames"] == metrics["train_frames"]
    # The synthetic capture moves the jaw and both smile shapes together: two expression modes.
    assert inputs["expression_modes"] == 2 == metrics["capacity_expression_modes"]
    expected = choose_capacity(CaptureStats(**inputs), base=AvatarConfig(**base_avatar)).config
    used = AvatarConfig(**report["used"])
    assert used == expected
    assert used.latent_dim == latent_size(2, CapacityRule()) == metrics["capacity_latent_dim"]
    from avatar.io import load_trained

    model, _ = load_trained(out / "models" / "ours")
    assert model.config == expected
    assert metrics["capacity_auto"] == 1 and metrics["capacity_primitives"] == expected.num_prims
    assert metrics["capacity_voxel_res"] == expected.voxels_per_side
    assert metrics["capacity_footprint_px"] == pytest.approx(inputs["footprint_px"])
    assert metrics["capacity_texel_px"] >= 1.0 and metrics["capacity_parameters"] > 0
    # Pruning ran at half the iterations; figures for the render speed-up and the image change.
    assert 0 <= metrics["pruned_primitives"] < expected.num_prims
    assert metrics["render_seconds_per_image"] > 0 and metrics["prune_render_speedup"] > 0
    # The report's trade-off series: the learning curve with the chosen configuration marked.
    tradeoff = json.loads((out / "tradeoffs" / "learning_curve.json").read_text())
    chosen = [p for p in tradeoff["points"] if p.get("chosen")]
    assert len(chosen) == 1 and f"N={expected.prims_per_side}" in chosen[0]["series"]


def test_nonsense_capture_gives_a_config_error_in_auto_mode(capture):
    from stages.train.data import load_train_data

    data = load_train_data(capture, 24, logging.getLogger("test"), max_frames=6)
    data.mattes[:] = 0.0  # no foreground anywhere: no footprint
    frames = np.arange(len(data.bar))
    with pytest.raises(ConfigError, match="train.capacity=auto.*footprint_px"):
        capacity_of(data, frames, TrainParams(capacity="auto"))
    fixed = capacity_of(data, frames, TrainParams(capacity="fixed"))  # fixed: reported, never fatal
    assert fixed.config == TrainParams().avatar


def _trainer_with_an_empty_primitive(capture, tmp_path, monkeypatch, checkpoint_every: int):
    """A 12-iteration trainer pruning at iteration 6, whose model has one always-empty primitive.

    Returns the trainer, the model's config, the visible and the empty primitive's indices and
    the list that records how many primitives every raymarch got.
    """
    from avatar.model import RelightableMVP
    from stages.train.data import load_train_data

    data = load_train_data(capture, 24, logging.getLogger("test"))
    config, tensors, model, renderer = small_model(data)
    # The primitive at the centre of the UV grid faces the cameras; make another always empty.
    visible = (config.prims_per_side // 2) * config.prims_per_side + config.prims_per_side // 2
    empty = visible + 1
    real_decode = RelightableMVP.decode_geometry

    def decode_with_an_empty_primitive(self, z):
        geo = real_decode(self, z)
        mask = torch.ones(geo.density.shape[1], 1, 1, 1)
        mask[empty] = 0.0
        geo.density = geo.density * mask
        return geo

    monkeypatch.setattr(RelightableMVP, "decode_geometry", decode_with_an_empty_primitive)
    seen: list[int] = []
    real_raymarch = trainer_mod.raymarch

    def counting_raymarch(prims, *args, **kwargs):
        seen.append(prims.centre.shape[1])
        return real_raymarch(prims, *args, **kwargs)

    monkeypatch.setattr(trainer_mod, "raymarch", counting_raymarch)
    tr = trainer_mod.ModelTrainer(renderer, tensors, np.arange(len(data.bar)), iterations=12, batch_size=2,
                                  rays_per_image=128, lr=1e-3, weights=trainer_mod.LossWeights(), seed=0,
                                  ckpt_path=tmp_path / "c.pt", checkpoint_every=checkpoint_every, spike_factor=10.0,
                                  log=logging.getLogger("test"),
                                  prune=trainer_mod.PruneSchedule(at_iteration=6, window=5, max_alpha=0.01))
    return tr, config, visible, empty, seen


def test_scheduled_pruning_drops_an_always_empty_primitive_and_keeps_a_visible_one(capture, tmp_path, monkeypatch):
    tr, config, visible, empty, seen = _trainer_with_an_empty_primitive(capture, tmp_path, monkeypatch, 100)
    model = tr.model
    state = tr.run(SilentProgress())
    assert state.prune_done and state.pruned == model.num_pruned > 0
    assert float(tr.prim_alpha_max[empty]) == 0.0 and float(tr.prim_alpha_max[visible]) > 0.01
    assert not bool(model.prim_keep[empty]) and bool(model.prim_keep[visible])
    # Iterations 1-6 raymarch every primitive, 7-12 only the kept ones.
    assert seen[:6] == [config.num_prims] * 6
    assert seen[6:] == [config.num_prims - state.pruned] * 6


def test_a_rollback_to_a_state_saved_before_pruning_keeps_the_primitives_pruned(capture, tmp_path, monkeypatch):
    # The last good state is the checkpoint of iteration 5, before pruning at 6; a NaN at
    # iteration 9 restores it, and the primitives pruned at 6 must stay pruned.
    tr, config, visible, empty, seen = _trainer_with_an_empty_primitive(capture, tmp_path, monkeypatch, 5)
    real_losses = trainer_mod.ModelTrainer.losses
    calls = {"n": 0}

    def nan_at_iteration_9(self, *args):
        calls["n"] += 1
        total, terms = real_losses(self, *args)
        if calls["n"] == 9:
            return total * float("nan"), {**terms, "loss": float("nan")}
        return total, terms

    monkeypatch.setattr(trainer_mod.ModelTrainer, "losses", nan_at_iteration_9)
    state = tr.run(SilentProgress())
    assert state.rollbacks == 1 and state.prune_done and state.pruned > 0
    assert not bool(tr.model.prim_keep[empty]) and bool(tr.model.prim_keep[visible])
    assert int((~tr.model.prim_keep).sum()) == state.pruned
    # Every iteration after pruning, the rolled-back one and those after it included, raymarches only the kept ones.
    assert seen[6:] == [config.num_prims - state.pruned] * (len(seen) - 6)


def test_the_baseline_can_keep_a_code_size_of_its_own(capture, tmp_path):
    # Two expression modes: ours at the rule's 2 per mode (4, raised to min_latent 8), TRAvatar* at 8 per mode (16).
    out = run_stage_for_test(STAGE, tmp_path, capture, {**BASE, "capacity": "auto", "baseline": True,
                                                          "baseline_latent_per_mode": 8, "iterations": 4,
                                                          "rays_per_image": 32})
    metrics = json.loads((out / "metrics.json").read_text())
    from avatar.io import load_trained

    ours, _ = load_trained(out / "models" / "ours")
    travatar, _ = load_trained(out / "models" / "travatar")
    assert metrics["capacity_expression_modes"] == 2
    assert ours.config.latent_dim == 8 == metrics["ours_latent_dim"] == metrics["capacity_latent_dim"]
    assert travatar.config.latent_dim == 16 == metrics["travatar_latent_dim"]
    # Everything else of the baseline's size is ours'.
    assert travatar.config.model_copy(update={"latent_dim": 8, "light_basis": 0}) == ours.config


def test_the_baseline_shares_ours_code_size_by_default(capture, tmp_path):
    out = run_stage_for_test(STAGE, tmp_path, capture, {**BASE, "capacity": "auto", "baseline": True,
                                                          "iterations": 2, "rays_per_image": 32})
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["ours_latent_dim"] == metrics["travatar_latent_dim"] == metrics["capacity_latent_dim"]


def test_the_encoder_can_read_only_the_counted_expression_modes(capture, tmp_path):
    out = run_stage_for_test(STAGE, tmp_path, capture, {**BASE, "capacity": "auto", "baseline": True,
                                                          "encoder_input": "expression_modes", "iterations": 2,
                                                          "rays_per_image": 32})
    metrics = json.loads((out / "metrics.json").read_text())
    from avatar.io import load_trained

    for kind in ("ours", "travatar"):
        model, _ = load_trained(out / "models" / kind)
        basis = model.expression_basis.double()
        assert basis.shape == (metrics["capacity_expression_modes"], 3 * model.num_guide_vertices)
        torch.testing.assert_close(basis @ basis.T, torch.eye(len(basis), dtype=torch.float64), atol=1e-5, rtol=0)


def test_the_encoder_reads_the_whole_offsets_by_default(capture, tmp_path):
    out = run_stage_for_test(STAGE, tmp_path, capture, {**BASE, "iterations": 2, "rays_per_image": 32})
    from avatar.io import load_trained

    model, _ = load_trained(out / "models" / "ours")
    assert not hasattr(model, "expression_basis")


def test_a_guide_mesh_that_misses_the_expression_modes_is_a_clear_error():
    import logging

    from avatar.layout import GuideLayout
    from pipeline.errors import InputError
    from stages.train.setup import with_encoder_input

    # Two full-mesh expression modes, but the one guide vertex moves along one direction only.
    frames = np.zeros((6, 3, 3))
    frames[:, 0, 0] = np.arange(6)
    frames[:, 2, 1] = np.arange(6) ** 2
    layout = GuideLayout(guide_vertex_ids=np.array([0]), anchor_tris=np.zeros((1, 3), int),
                         anchor_bary=np.ones((1, 3)) / 3, normal_sign=np.ones(1), half_extent_m=np.ones(1),
                         mean_guide_vertices=frames[:, :1].mean(0))
    with pytest.raises(InputError, match="train.encoder_input.*1 guide vertices.*2 expression modes.*offsets"):
        with_encoder_input(layout, frames, "expression_modes", 2, logging.getLogger("test"))
