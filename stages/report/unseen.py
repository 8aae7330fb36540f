"""The report's unseen-subjects section: every stage on fresh subjects nothing was tuned on (``make evaluate-subjects``).

Drawn from ``bench-results/unseen_subjects.json`` (``benchmarks/evaluate_subjects.py``): each
stage's figures as mean and worst over the subjects, and ours against TRAvatar* per subject on
the test splits. The figures are those of the subjects' first runs, reported as they fell.
"""

from __future__ import annotations

import json
from pathlib import Path

from stages.report.html import Section, Table

TEST_SPLITS = {"novel_light": "novel light", "novel_perf": "novel performance", "novel_both": "both"}


def studio_of(figures: object, subjects: list[str]) -> str:
    """Which virtual studio filmed the subjects, in words, from their capture figures' ``realism_real``.

    A run made before the studio recorded it (no ``realism_real``) was filmed by the ideal
    studio, the only one there was then; a mixed run says so.
    """
    kinds = set()
    for subject in subjects:
        capture = figures.get(subject, {}).get("capture", {}) if isinstance(figures, dict) else {}
        kinds.add(capture.get("realism_real", 0) if isinstance(capture, dict) else None)
    if kinds == {1}:
        return "filmed by the realistic studio (capture.realism: real)"
    if kinds == {0}:
        return "filmed by the ideal studio (capture.realism: ideal, or a run from before the realistic one)"
    return "filmed by a mix of studios or by one not recorded: compare the subjects with care"


def unseen_subjects_section(bench_folder: Path) -> Section | None:
    """The section, or None when ``unseen_subjects.json`` is missing or unreadable."""
    path = Path(bench_folder) / "unseen_subjects.json"
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        summary = doc["summary"]
        subjects = [str(s) for s in summary["subjects"]]
        stages, pairs = dict(summary["stages"]), dict(summary["ours_vs_travatar"])
    except (ValueError, KeyError, TypeError):
        return None
    section = Section(f"Unseen subjects ({len(subjects)})", "unseen-subjects")
    section.paragraph(f"Subjects {', '.join(subjects)}: identity, performance and noise seeds from a range that no "
                      "test, tuning run or setting ever used, each run through train once with the shipped settings "
                      f"(make evaluate-subjects), {studio_of(doc.get('figures'), subjects)}. Each stage's figure is "
                      "given as the mean and the worst over them.")
    figures = Table(["stage", "figure", "mean", "worst"], table_id="unseen-stages-table")
    for stage, measures in stages.items():
        for key, value in measures.items():
            figures.add([stage, key, f"{value['mean']:.4g}", f"{value['worst']:.4g}"])
    section.table(figures)
    per_subject = Table(["subject"] + [f"{title}: ours / TRAvatar* (ours - TRAvatar*)" for title in TEST_SPLITS.values()],
                        table_id="unseen-models-table")
    for subject in subjects:
        row = [subject]
        for split in TEST_SPLITS:
            cell = pairs.get(subject, {}).get(split)
            complete = cell and all(isinstance(cell.get(k), (int, float))
                                    for k in ("ours", "travatar", "ours_minus_travatar"))
            row.append(f"{cell['ours']:.2f} / {cell['travatar']:.2f} ({cell['ours_minus_travatar']:+.2f})"
                       if complete else "n/a")
        per_subject.add(row)
    section.paragraph("Ours against TRAvatar* per subject, PSNR dB on the test splits (one seed a subject: each "
                      "row is one draw, not a mean over seeds).")
    section.table(per_subject)
    return section
