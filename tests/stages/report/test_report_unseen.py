"""The report's unseen-subjects section, drawn from bench-results/unseen_subjects.json when it exists."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.evaluate_subjects import summarise
from stages.report.unseen import unseen_subjects_section


def test_the_section_shows_each_stage_mean_and_worst_and_each_subject(tmp_path: Path) -> None:
    assert unseen_subjects_section(tmp_path) is None  # no run yet: no section
    train = {"ours_novel_light_psnr": 29.0, "travatar_novel_light_psnr": 27.5, "ours_novel_perf_psnr": 28.0,
             "travatar_novel_perf_psnr": 28.25, "ours_novel_both_psnr": 28.5}  # TRAvatar* both missing
    per_subject = {7001: {"calibrate": {"reproj_rms_px": 0.2}, "train": train},
                   7002: {"calibrate": {"reproj_rms_px": 0.4}, "train": {**train, "ours_novel_light_psnr": 30.0}}}
    (tmp_path / "unseen_subjects.json").write_text(json.dumps({"summary": summarise(per_subject)}))
    section = unseen_subjects_section(tmp_path)
    html = "".join(section.parts)
    assert section.title == "Unseen subjects (2)" and "Subjects 7001, 7002:" in html
    assert "<td>reproj_rms_px</td><td>0.3</td><td>0.4</td>" in html  # mean, worst (larger is worse)
    assert "29.00 / 27.50 (+1.50)" in html and "30.00 / 27.50 (+2.50)" in html
    assert "28.00 / 28.25 (-0.25)" in html and "n/a" in html  # a split without TRAvatar*'s figure
    assert "filmed by the ideal studio" in html  # no capture figures: a run from before the realistic studio
    figures = {str(k): {**v, "capture": {"realism_real": 1}} for k, v in per_subject.items()}
    (tmp_path / "unseen_subjects.json").write_text(json.dumps({"summary": summarise(per_subject), "figures": figures}))
    assert "filmed by the realistic studio" in "".join(unseen_subjects_section(tmp_path).parts)
    figures["7002"]["capture"]["realism_real"] = 0
    (tmp_path / "unseen_subjects.json").write_text(json.dumps({"summary": summarise(per_subject), "figures": figures}))
    assert "a mix of studios" in "".join(unseen_subjects_section(tmp_path).parts)
    (tmp_path / "unseen_subjects.json").write_text("{not json")
    assert unseen_subjects_section(tmp_path) is None

