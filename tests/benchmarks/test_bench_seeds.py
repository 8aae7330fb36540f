"""The seed bench's statistics: paired differences and their 95% interval decide a split only when it excludes 0."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from benchmarks.bench_seeds import paired_summary, uncovered_spread


def test_a_consistent_lead_is_called_and_a_tie_is_not():
    lead = paired_summary([24.0, 25.0, 24.5], [23.0, 24.0, 23.4])  # differences 1.0, 1.0, 1.1
    assert lead["diff_mean"] == pytest.approx(31 / 30)
    # t(0.975, 2) = 4.3027; sample std of the differences 0.057735; n = 3.
    half = 4.302653 * 0.0577350 / 3 ** 0.5
    assert lead["diff_ci95"] == pytest.approx([31 / 30 - half, 31 / 30 + half], abs=1e-5)
    assert lead["verdict"] == "ours ahead" and lead["ours_std"] == pytest.approx(0.5)
    # The same means apart, but the seeds disagree on the sign: not resolved.
    assert paired_summary([24.0, 25.0, 24.5], [24.2, 24.6, 24.7])["verdict"] == "not resolved"
    assert paired_summary([23.0, 23.1, 23.3], [24.0, 24.3, 24.2])["verdict"] == "TRAvatar* ahead"


def test_earlier_runs_are_reused_only_with_the_same_settings_and_data(tmp_path):
    import json

    from benchmarks.bench_seeds import MODELS, SPLITS, _earlier_runs

    def run(value: float) -> dict:
        return {f"{m}_{s}": value for m in MODELS for s in SPLITS}

    path = tmp_path / "seeds_alice.json"
    assert _earlier_runs(path, {"lr": 0.003}, "workspace alice") == {}  # no file yet
    # Seed 3 has no validation figures: trained before the validation split, on more frames; not reused.
    path.write_text(json.dumps({"params": {"lr": 0.003}, "source": "workspace alice",
                                "runs": {"0": run(27.0), "2": run(26.0), "3": {"ours_novel_light": 25.0}}}))
    assert _earlier_runs(path, {"lr": 0.003}, "workspace alice") == {0: run(27.0), 2: run(26.0)}
    assert _earlier_runs(path, {"lr": 0.001}, "workspace alice") == {}  # other settings: train again
    assert _earlier_runs(path, {"lr": 0.003}, "synthetic capture") == {}  # other data: train again


def test_overrides_merge_into_nested_sections_and_bad_ones_are_named(monkeypatch):
    from benchmarks.bench_seeds import _overrides, merge_params

    base = {"lr": 0.003, "capacity_rule": {"min_texel_px": 2.0, "latent_per_mode": 2.0}, "avatar": None}
    merged = merge_params(base, {"capacity_rule": {"latent_per_mode": 0}, "avatar": {"latent_dim": 64}, "seed": 3})
    assert merged == {"lr": 0.003, "capacity_rule": {"min_texel_px": 2.0, "latent_per_mode": 0},
                      "avatar": {"latent_dim": 64}, "seed": 3}
    assert base["capacity_rule"]["latent_per_mode"] == 2.0  # the preset is not changed in place
    monkeypatch.setenv("SEEDS_SET", '{"lr": 0.001}')
    assert _overrides() == {"lr": 0.001}
    monkeypatch.setenv("SEEDS_SET", "{lr: 0.001")
    with pytest.raises(SystemExit, match="SEEDS_SET.*not JSON"):
        _overrides()
    monkeypatch.setenv("SEEDS_SET", "[1, 2]")
    with pytest.raises(SystemExit, match="JSON object"):
        _overrides()


def test_a_variant_is_compared_with_the_default_on_the_seeds_both_hold(tmp_path):
    import json

    from benchmarks.bench_seeds import MODELS, SPLITS, _default_runs, against_default

    def run(offset: float) -> dict:
        return {f"{m}_{s}": 24.0 + offset for m in MODELS for s in SPLITS}

    default = {0: run(0.0), 1: run(0.5), 2: run(1.0)}
    variant = {0: run(-1.0), 2: run(0.1), 5: run(3.0)}
    compared = against_default(variant, default, [0, 2, 5])
    assert compared["seeds"] == [0, 2]  # seed 5 has no default to pair with
    assert compared["ours_novel_perf"]["diff_mean"] == pytest.approx(-0.95)  # (-1.0 - 0.9) / 2
    assert compared["travatar_train"]["verdict"] == "default ahead"  # differences -1.0 and -0.9
    assert against_default(variant, default, [5]) == {}
    path = tmp_path / "seeds_bob.json"
    path.write_text(json.dumps({"source": "workspace bob", "iterations": 2500, "runs": {"0": run(0.0)}}))
    assert _default_runs(path, "workspace bob") == (2500, {0: run(0.0)})  # its iterations, to print beside
    assert _default_runs(path, "synthetic capture") == (None, {})  # other data: not comparable
    assert _default_runs(tmp_path / "none.json", "workspace bob") == (None, {})


def _bench_in(tmp_path, monkeypatch):
    """The bench module writing under ``tmp_path``, with a 10-iteration preset and a named workspace as data."""
    import benchmarks.bench_seeds as bench

    (tmp_path / "bench-results").mkdir()
    monkeypatch.setattr(bench, "ROOT", tmp_path)
    monkeypatch.setattr(bench, "tiny_train_params", lambda: {"iterations": 10, "lr": 0.003})
    monkeypatch.setattr(bench, "train_inputs", lambda subject, scratch: ({}, f"workspace {subject}"))
    return bench


def test_a_stopped_run_keeps_its_finished_seeds_and_compares_with_a_named_baseline(tmp_path, monkeypatch):
    """Each seed is written as soon as it is trained; a rerun trains only the missing ones."""
    import json

    bench = _bench_in(tmp_path, monkeypatch)
    trained: list[int] = []
    stop_at = {1}  # the user stops the first bench during seed 1

    def fake_train(inputs, params, scratch, name):
        # Stands in for a real training run (minutes each): only the bench's bookkeeping is tested here.
        seed = params["seed"]
        if seed in stop_at:
            stop_at.discard(seed)
            raise KeyboardInterrupt
        trained.append(seed)
        return {"metrics": {"seconds": 1.0, "pruned_primitives": 3 * seed, "ours_clipped_steps": 10 * seed,
                            "travatar_clipped_steps": 0, "ours_opacity_logits_below_floor": 0.1 * seed,
                            "ours_val_light_uncovered_error_share": 0.2, "ours_novel_light_uncovered_error_share": 0.3,
                            **{f"{m}_{s}_psnr": 25.0 + seed + (m == "ours") for m in bench.MODELS for s in bench.SPLITS}}}

    monkeypatch.setattr(bench, "run_train", fake_train)
    monkeypatch.setenv("SEEDS_SUBJECT", "bob")
    monkeypatch.setenv("SEEDS", "0,1,2")
    monkeypatch.setenv("SEEDS_TAG", "x")
    with pytest.raises(KeyboardInterrupt):
        bench.main()
    kept = json.loads((tmp_path / "bench-results" / "seeds_bob_x.json").read_text())
    assert kept["runs"].keys() == {"0"} and kept["complete"] is False
    assert kept["summary"]["train"]["ours_mean"] == 26.0
    assert not list((tmp_path / "bench-results").glob("*.part"))  # written whole, no leftovers

    # The baseline: a named tag's file holding seeds 0 and 2, one dB under the variant for ours.
    base_runs = {str(x): {f"{m}_{s}": 24.0 + x + (m == "ours") for m in bench.MODELS for s in bench.SPLITS}
                 for x in (0, 2)}
    (tmp_path / "bench-results" / "seeds_bob_it5k.json").write_text(json.dumps(
        {"source": "workspace bob", "iterations": 5000, "runs": base_runs}))
    monkeypatch.setenv("SEEDS_BASELINE", "it5k")
    trained.clear()
    results = bench.main()
    assert trained == [1, 2]  # seed 0 came from the file
    assert results["complete"] is True and results["seeds"] == [0, 1, 2]
    assert results["runs"]["2"]["ours_pruned_primitives"] == 6  # kept per seed, from the stage's metrics
    assert (results["runs"]["2"]["ours_clipped_steps"], results["runs"]["2"]["travatar_clipped_steps"]) == (20, 0)
    # How holes show, kept per seed where the stage reported it; never a test split's.
    assert results["runs"]["2"]["ours_opacity_logits_below_floor"] == pytest.approx(0.2)
    assert results["runs"]["2"]["ours_val_light_uncovered_error_share"] == 0.2
    assert "ours_novel_light_uncovered_error_share" not in results["runs"]["2"]
    compared = results["against_default"]
    assert compared["seeds"] == [0, 2] and compared["baseline_file"] == "seeds_bob_it5k.json"
    assert compared["ours_novel_light"]["diff_mean"] == pytest.approx(1.0)
    monkeypatch.setenv("SEEDS_BASELINE", "../x")
    with pytest.raises(SystemExit, match="SEEDS_BASELINE"):
        bench.main()


def test_learning_curves_are_kept_per_seed_when_asked(tmp_path, monkeypatch):
    """SEEDS_CURVE_EVERY: the runs train with that curve period and keep both models' curves."""
    bench = _bench_in(tmp_path, monkeypatch)
    periods: list[int] = []

    def fake_train(inputs, params, scratch, name):
        # Stands in for a real training run: only what the bench keeps of it is tested here.
        periods.append(params["curve_every"])
        curve = [[0, 0.0, 10.0], [5, 1.0, 20.0 + params["seed"]]] if params["curve_every"] else []
        return {"metrics": {"seconds": 1.0, **{f"{m}_{s}_psnr": 25.0 for m in bench.MODELS for s in bench.SPLITS}},
                "curve": {"ours": curve, "travatar": curve}}

    monkeypatch.setattr(bench, "run_train", fake_train)
    monkeypatch.setenv("SEEDS_SUBJECT", "bob")
    monkeypatch.setenv("SEEDS", "0,1")
    monkeypatch.setenv("SEEDS_TAG", "curves")
    monkeypatch.setenv("SEEDS_CURVE_EVERY", "5")
    results = bench.main()
    assert periods == [5, 5]
    assert results["runs"]["1"]["curve_ours"] == [[0, 0.0, 10.0], [5, 1.0, 21.0]]
    assert results["runs"]["0"]["curve_travatar"][-1][2] == 20.0
    monkeypatch.setenv("SEEDS_TAG", "nocurves")
    monkeypatch.delenv("SEEDS_CURVE_EVERY")
    results = bench.main()
    assert periods[2:] == [0, 0] and "curve_ours" not in results["runs"]["0"]


def test_ours_alone_trains_without_the_baseline_and_pairs_with_a_file_of_both(tmp_path, monkeypatch):
    """SEEDS_MODELS=ours: no TRAvatar* run, ours' figures only, paired on ours with a baseline of both models."""
    import json

    bench = _bench_in(tmp_path, monkeypatch)
    baselines: list[bool] = []

    def fake_train(inputs, params, scratch, name):
        # Stands in for a real training run: what the bench asks of the stage and keeps of it is tested here.
        baselines.append(params["baseline"])
        kinds = ("ours", "travatar") if params["baseline"] else ("ours",)
        return {"metrics": {"seconds": 2.0, "ours_clipped_steps": 0,
                            **{f"{m}_{s}_psnr": 26.0 + params["seed"] for m in kinds for s in bench.SPLITS}}}

    monkeypatch.setattr(bench, "run_train", fake_train)
    monkeypatch.setenv("SEEDS_SUBJECT", "bob")
    monkeypatch.setenv("SEEDS", "0,1")
    monkeypatch.setenv("SEEDS_MODELS", "ours")
    with pytest.raises(SystemExit, match="SEEDS_MODELS=ours needs a SEEDS_TAG"):
        bench.main()  # the untagged file is the report's: both models or nothing
    assert baselines == []
    # The shipped settings' file of both models, ours half a dB under the variant on seed 0 and 1 dB on seed 1.
    both = {str(x): {f"{m}_{s}": 25.5 + x / 2 for m in bench.MODELS for s in bench.SPLITS} for x in (0, 1)}
    (tmp_path / "bench-results" / "seeds_bob.json").write_text(json.dumps(
        {"source": "workspace bob", "iterations": 10, "runs": both}))
    monkeypatch.setenv("SEEDS_TAG", "alone")
    results = bench.main()
    assert baselines == [False, False]  # train.baseline off: ours alone
    assert results["models"] == ["ours"] and set(results["runs"]["1"]) == (
        {f"ours_{s}" for s in bench.SPLITS} | {"seconds", "ours_pruned_primitives", "ours_clipped_steps"})
    assert results["summary"]["val_light"] == {"ours_mean": 26.5, "ours_std": pytest.approx(0.5 ** 0.5)}
    compared = results["against_default"]
    assert compared["seeds"] == [0, 1] and not any(k.startswith("travatar") for k in compared)
    assert compared["ours_val_perf"]["diff_mean"] == pytest.approx(0.75)  # (0.5 + 1.0) / 2
    # A rerun reuses the ours-only seeds it holds.
    baselines.clear()
    assert bench.main()["seeds"] == [0, 1] and baselines == []
    monkeypatch.setenv("SEEDS_MODELS", "travatar")
    with pytest.raises(SystemExit, match="SEEDS_MODELS='travatar'"):
        bench.main()


def test_the_inputs_digest_reads_the_data_and_not_the_run_records(tmp_path):
    from benchmarks.train_runs import inputs_digest

    def build(root, image: bytes, seconds: float):
        (root / "capture" / "frames").mkdir(parents=True)
        (root / "capture" / "frames" / "000.png").write_bytes(image)
        (root / "capture" / "metrics.json").write_text(f'{{"seconds": {seconds}}}')
        (root / "matte").mkdir()
        (root / "matte" / "model.json").write_text("{}")
        return {"capture": str(root / "capture"), "matte": str(root / "matte")}

    first = inputs_digest(build(tmp_path / "a", b"\x01\x02", 250.0))
    assert inputs_digest(build(tmp_path / "b", b"\x01\x02", 411.0)) == first  # the same data, other timings
    assert inputs_digest(build(tmp_path / "c", b"\x01\x03", 250.0)) != first  # one byte of one image
    moved = build(tmp_path / "d", b"\x01\x02", 250.0)
    (Path(moved["capture"]) / "frames" / "000.png").rename(Path(moved["capture"]) / "frames" / "001.png")
    assert inputs_digest(moved) != first  # the same bytes under another name


def test_the_train_inputs_declare_no_run_records_the_digest_would_miss():
    """inputs_digest leaves out only the runner's metrics.json: it relies on this."""
    import importlib

    from benchmarks.train_runs import INPUT_STAGES

    for name in INPUT_STAGES:
        stage = importlib.import_module(f"stages.{name}.stage").STAGE
        assert tuple(stage.run_records) == (), name


def test_runs_on_other_inputs_are_neither_reused_nor_paired(tmp_path, monkeypatch):
    import json

    bench = _bench_in(tmp_path, monkeypatch)
    digest = {"value": "aaaa"}
    monkeypatch.setattr(bench, "inputs_digest", lambda inputs: digest["value"])
    trained: list[int] = []

    def fake_train(inputs, params, scratch, name):
        trained.append(params["seed"])
        return {"metrics": {"seconds": 1.0, **{f"{m}_{s}_psnr": 25.0 for m in bench.MODELS for s in bench.SPLITS}}}

    monkeypatch.setattr(bench, "run_train", fake_train)
    monkeypatch.setenv("SEEDS_SUBJECT", "bob")
    monkeypatch.setenv("SEEDS", "0")
    assert bench.main()["inputs_digest"] == "aaaa" and trained == [0]
    assert bench.main() and trained == [0]  # the same inputs: reused
    monkeypatch.setenv("SEEDS_TAG", "v")
    digest["value"] = "bbbb"  # the subject was rebuilt and its images came out different
    results = bench.main()
    assert trained == [0, 0] and "against_default" not in results  # seed 0 of "aaaa" does not pair with "bbbb"
    # A baseline file written before the bench kept the digest pairs on its source alone.
    old = json.loads((tmp_path / "bench-results" / "seeds_bob.json").read_text())
    del old["inputs_digest"]
    (tmp_path / "bench-results" / "seeds_bob.json").write_text(json.dumps(old))
    assert bench.main()["against_default"]["seeds"] == [0] and trained == [0, 0]


def test_two_builds_are_paired_on_one_builds_images(tmp_path):
    """A capture setting: the variant's models on the baseline build's images, and the baseline's on the variant's."""
    import json

    from benchmarks.bench_seeds import SPLITS, _across_builds

    def run(own: float, ref: float | None, ref_digest: str | None = None) -> dict:
        r = {f"ours_{s}": own for s in SPLITS}
        if ref is not None:
            r.update({f"ref_ours_{s}": ref for s in SPLITS}, reference_digest=ref_digest)
        return r

    baseline = tmp_path / "seeds_alice_ours_shipped.json"
    # The baseline build "aaa" (scored on the variant's build "bbb" for seeds 0 and 1 only).
    baseline.write_text(json.dumps({"inputs_digest": "aaa", "runs": {
        "0": run(30.0, 29.0, "bbb"), "1": run(30.5, 29.4, "bbb"), "2": run(29.8, None)}}))
    variant = {0: run(29.0, 30.2, "aaa"), 1: run(29.4, 30.6, "aaa"), 2: run(29.2, 30.1, "aaa")}
    across = _across_builds(variant, "bbb", "aaa", baseline, [0, 1, 2], ("ours",))
    on_base = across["on_baseline_build"]
    assert on_base["seeds"] == [0, 1, 2]
    assert on_base["ours_val_light"]["diff_mean"] == pytest.approx((0.2 + 0.1 + 0.3) / 3)
    on_this = across["on_this_build"]
    assert on_this["seeds"] == [0, 1]  # seed 2 of the baseline was not scored on this build
    assert on_this["ours_val_perf"]["diff_mean"] == pytest.approx(0.0)
    # A reference that is not the baseline's build pairs nothing on the baseline's images.
    assert "on_baseline_build" not in _across_builds(variant, "bbb", "ccc", baseline, [0, 1, 2], ("ours",))
    assert _across_builds(variant, "bbb", "aaa", tmp_path / "none.json", [0, 1, 2], ("ours",)) == {}


def test_a_reference_root_without_the_subject_is_named(tmp_path, monkeypatch):
    from benchmarks.bench_seeds import _reference_inputs

    assert _reference_inputs("alice") is None  # unset: no cross-build scoring
    monkeypatch.setenv("SEEDS_REFERENCE", str(tmp_path / "other-build"))
    with pytest.raises(SystemExit, match=r"SEEDS_REFERENCE=.*other-build.*subject 'alice'.*pipeline run -S alice"):
        _reference_inputs("alice")


def test_the_spread_in_the_uncovered_pixels_is_told_from_the_rest():
    # The same error on the covered pixels every seed, and a hole of another size each: the spread is all
    # in the uncovered pixels, so without them it vanishes, and a bigger hole is a lower PSNR.
    covered = 1e-3
    runs = {}
    for seed, hole in enumerate([0.0, 2e-4, 5e-4, 1e-3]):
        total = covered + hole
        runs[seed] = {"ours_val_light": -10 * math.log10(total), "ours_val_light_uncovered_error_share": hole / total,
                      "ours_val_perf": 30.0 + seed, "ours_val_perf_uncovered_error_share": 0.2}
    runs[4] = {"ours_val_light": 20.0, "ours_val_perf": 20.0}  # a run from before the share was kept: left out
    spread = uncovered_spread(runs, [0, 1, 2, 3, 4], ("ours",))
    light = spread["ours_val_light"]
    assert light["seeds"] == [0, 1, 2, 3]
    assert light["psnr_std"] > 0.5 and light["covered_psnr_std"] < 1e-9
    assert light["covered_psnr_mean"] == pytest.approx(30.0)
    assert light["correlation"] < -0.9 and light["share_max"] == pytest.approx(0.5)
    # The same share every seed: the spread is all off the uncovered pixels, and no correlation is claimed.
    perf = spread["ours_val_perf"]
    assert perf["covered_psnr_std"] == pytest.approx(perf["psnr_std"]) and math.isnan(perf["correlation"])
    assert uncovered_spread(runs, [0, 1], ("ours",)) == {}  # two seeds tell no spread
