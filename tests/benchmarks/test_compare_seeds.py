"""Comparing two seed benches: paired on the same inputs, Welch's interval on other inputs."""

from __future__ import annotations

import json

import pytest

from benchmarks.bench_seeds import SPLITS
from benchmarks.compare_seeds import compare, welch_difference


def _write(path, digest, values, params=None):
    runs = {str(seed): {f"ours_{s}": v for s in SPLITS} for seed, v in values.items()}
    path.write_text(json.dumps({"inputs_digest": digest, "models": ["ours"], "params": params or {"lr": 0.003},
                                "runs": runs}))
    return str(path)


def test_welch_interval_matches_the_textbook_case():
    # Two samples of 5 with variances 1 and 4: Welch-Satterthwaite dof = (0.2 + 0.8)^2 / (0.04/4 + 0.64/4) = 5.88.
    a, b = [1.0, 2.0, 3.0, 2.0, 2.0], [0.0, 2.0, 4.0, -2.0, 1.0]
    r = welch_difference(a, b)
    va, vb = 0.5 / 5, 5.0 / 5  # sample variances 0.5 and 5.0
    assert r["dof"] == pytest.approx((va + vb) ** 2 / (va ** 2 / 4 + vb ** 2 / 4))
    assert r["diff_mean"] == pytest.approx(1.0) and r["verdict"] == "not resolved"
    assert welch_difference([10.0, 10.1, 9.9], [8.0, 8.2, 7.9])["verdict"] == "variant ahead"


def test_same_inputs_pair_by_seed_and_other_inputs_do_not(tmp_path):
    base = _write(tmp_path / "base.json", "aaa", {0: 29.0, 1: 30.0, 2: 29.5})
    # Each seed 0.2 dB up: paired, a tight interval around +0.2.
    same = _write(tmp_path / "same.json", "aaa", {0: 29.2, 1: 30.2, 2: 29.7, 7: 35.0})
    r = compare(same, base)
    assert r["paired"] and r["seeds"] == [0, 1, 2]
    assert r["ours_val_light"]["diff_mean"] == pytest.approx(0.2) and r["ours_val_light"]["verdict"] == "variant ahead"
    # The same figures on other inputs: independent samples, the seeds' spread stays in the interval.
    other = _write(tmp_path / "other.json", "bbb", {0: 29.2, 1: 30.2, 2: 29.7})
    r = compare(other, base)
    assert not r["paired"] and r["ours_val_perf"]["verdict"] == "not resolved"
    assert r["ours_val_perf"]["diff_mean"] == pytest.approx(0.2)


def test_a_side_merges_files_of_one_bench_and_refuses_others(tmp_path):
    base = _write(tmp_path / "base.json", "aaa", {0: 29.0, 1: 30.0, 2: 29.5, 3: 29.1})
    first = _write(tmp_path / "a.json", "bbb", {0: 30.0, 1: 30.1})
    second = _write(tmp_path / "b.json", "bbb", {2: 30.2, 3: 30.0})
    r = compare(f"{first}+{second}", base)
    assert r["seeds"]["variant"] == [0, 1, 2, 3]
    assert r["ours_train"]["variant_mean"] == pytest.approx(30.075)
    settings = _write(tmp_path / "c.json", "bbb", {4: 30.0}, params={"lr": 0.005})
    with pytest.raises(SystemExit, match="other inputs or settings"):
        compare(f"{first}+{settings}", base)
    with pytest.raises(SystemExit, match="not a bench_seeds results file"):
        compare(str(tmp_path / "missing.json"), base)
