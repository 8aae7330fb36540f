"""The report's seed-spread section, drawn from bench-results/seeds_<subject>.json when it exists."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.bench_seeds import paired_summary
from stages.report.seeds import seeds_section


def test_seeds_section_shows_means_intervals_and_verdicts(tmp_path: Path) -> None:
    assert seeds_section(tmp_path, "alice") is None  # no bench run yet: no section
    ours = {"val_light": [25.0, 25.4, 25.2], "val_perf": [24.0, 24.2, 24.1], "novel_light": [24.0, 25.0, 24.5],
            "novel_perf": [23.0, 23.1, 23.3], "novel_both": [22.6, 24.0, 23.5],
            "train": [27.0, 27.1, 27.2]}
    base = {"val_light": [24.0, 24.4, 24.3], "val_perf": [24.0, 24.1, 24.3], "novel_light": [23.0, 24.0, 23.4],
            "novel_perf": [24.0, 24.3, 24.2], "novel_both": [23.2, 23.6, 23.7],
            "train": [27.0, 27.3, 27.1]}
    result = {"subject": "alice", "source": "test", "iterations": 10, "seeds": [0, 1, 2],
              "params": {"image_order": "balanced"},
              "summary": {s: paired_summary(ours[s], base[s]) for s in ours}}
    (tmp_path / "seeds_alice.json").write_text(json.dumps(result))
    html = "".join(seeds_section(tmp_path, "alice").parts)
    assert 'id="seeds-table"' in html and html.count("<tr>") == 7  # header + 2 validation + 3 test + fit
    assert html.index("validation: light") < html.index("test: novel light")  # validation first: settings are chosen there
    assert "balanced image order" in html
    assert "at most 0.71 dB (test: both)" in html  # the widest spread of ours, the novel-both split's
    assert "ours ahead" in html and "TRAvatar* ahead" in html and "not resolved" in html
    assert "24.50 ± 0.50" in html  # ours, novel light
    assert "spread sits" not in html  # a file from before the bench kept the uncovered shares
    result["uncovered_spread"] = {"ours_val_light": {"psnr_std": 0.67, "covered_psnr_std": 0.2, "correlation": -0.96},
                                  "travatar_val_light": {"psnr_std": 0.26, "covered_psnr_std": 0.04,
                                                         "correlation": -0.99}}
    (tmp_path / "seeds_alice.json").write_text(json.dumps(result))
    html = "".join(seeds_section(tmp_path, "alice").parts)
    assert "spread sits" in html
    assert "validation: light: 0.67 dB, 0.20 dB without them (correlation of the PSNR with their share of the error " \
           "-0.96)" in html
    assert "validation: performance:" not in html  # no figures for that split: nothing claimed
    assert seeds_section(tmp_path, "bob") is None  # another subject's run is not shown
    (tmp_path / "seeds_alice.json").write_text("{not json")
    assert seeds_section(tmp_path, "alice") is None
