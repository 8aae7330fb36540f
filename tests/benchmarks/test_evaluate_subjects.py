"""``benchmarks.evaluate_subjects``: the unseen range stays unseen, and the summary's mean and worst."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from benchmarks.evaluate_subjects import UNSEEN_SEEDS, subject_sets, summarise

ROOT = Path(__file__).resolve().parents[2]


def _seeds(node) -> list[int]:
    """Every integer under a key that names a seed, anywhere in a YAML tree."""
    found = []
    if isinstance(node, dict):
        for key, value in node.items():
            if "seed" in str(key):
                found += [v for v in (value if isinstance(value, list) else [value]) if isinstance(v, int)]
            found += _seeds(value)
    elif isinstance(node, list):
        for value in node:
            found += _seeds(value)
    return found


# Identity seeds, their performance seeds (+1000) and their noise seeds (+2000).
RESERVED = range(UNSEEN_SEEDS.start, UNSEEN_SEEDS.stop + 2000)


def test_no_subject_preset_or_test_uses_the_unseen_range():
    for path in sorted((ROOT / "configs").rglob("*.yaml")):
        if path.name == "unseen.yaml":
            continue  # the unseen subject itself: its seeds are set per run from the range
        used = [s for s in _seeds(yaml.safe_load(path.read_text()) or {}) if s in RESERVED]
        assert not used, f"{path} uses seeds {used} of the unseen range"
    pattern = re.compile(r"seed\w*\s*[=:]\s*\(?\s*([789]\d{3})\b")
    for path in sorted((ROOT / "tests").rglob("*.py")):
        if path == Path(__file__).resolve():
            continue  # this file names the range on purpose
        text = path.read_text()
        hits = [int(m) for m in pattern.findall(text) if int(m) in RESERVED]
        assert not hits, f"{path} sets seeds {hits} of the unseen range"


def test_subject_seeds_come_from_the_range_only():
    assert subject_sets(7001) == ["capture.identity_seed=7001", "capture.performance_seed=8001",
                                  "capture.render.seed=9001"]
    with pytest.raises(ValueError, match="outside the unseen range"):
        subject_sets(1)


def test_summary_mean_worst_and_the_paired_difference():
    figures = {7001: {"calibrate": {"reproj_rms_px": 0.1}, "train": {"ours_novel_light_psnr": 27.0,
                                                                    "travatar_novel_light_psnr": 26.0}},
               7002: {"calibrate": {"reproj_rms_px": 0.3}, "train": {"ours_novel_light_psnr": 25.0,
                                                                    "travatar_novel_light_psnr": 25.5}}}
    summary = summarise(figures)
    assert summary["stages"]["calibrate"]["reproj_rms_px"] == {"mean": pytest.approx(0.2), "worst": 0.3, "n": 2}
    psnr = summary["stages"]["train"]["ours_novel_light_psnr"]
    assert psnr["worst"] == 25.0 and psnr["mean"] == pytest.approx(26.0)  # for a PSNR the worst is the smallest
    assert summary["ours_vs_travatar"]["7001"]["novel_light"]["ours_minus_travatar"] == pytest.approx(1.0)
    assert summary["ours_vs_travatar"]["7002"]["novel_light"]["ours_minus_travatar"] == pytest.approx(-0.5)
    assert summary["ours_vs_travatar"]["7002"]["val_light"]["ours_minus_travatar"] is None
