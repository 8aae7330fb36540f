"""The report's seed-spread section: ours against TRAvatar* over several seeds (``benchmarks/bench_seeds.py``).

One training run is one draw; this section shows, for the report's subject, each model's
mean and spread over seeds and whether the paired difference is resolved at 95%.
"""

from __future__ import annotations

import json
from pathlib import Path

from stages.report.html import Section, Table

#: Validation first: settings are chosen there (docs/experiments.md, "The validation split"); the test
#: splits are the claim, measured as they fall.
SPLIT_LABELS = {"val_light": "validation: light", "val_perf": "validation: performance",
                "novel_light": "test: novel light", "novel_perf": "test: novel performance", "novel_both": "test: both",
                "train": "training images (fit)"}


def seeds_section(bench_folder: Path, subject: str) -> Section | None:
    """The section, or None when ``seeds_<subject>.json`` is missing or unreadable."""
    path = Path(bench_folder) / f"seeds_{subject}.json"
    if not path.is_file():
        return None
    try:
        result = json.loads(path.read_text(encoding="utf-8"))
        summary = {split: result["summary"][split] for split in SPLIT_LABELS if split in result["summary"]}
        seeds = list(result["seeds"])
    except (ValueError, KeyError, TypeError):
        return None
    section = Section("Ours vs TRAvatar* over seeds (PSNR, dB)", "seeds")
    order = (result.get("params") or {}).get("image_order", "random")
    section.paragraph(f"{len(seeds)} seeds ({', '.join(map(str, seeds))}), {result.get('iterations')} iterations per "
                      f"model, {order} image order, {result.get('source')}. A split is called for a model only when "
                      "the 95% interval of the paired difference (same seed, same data) excludes 0. Settings are "
                      "chosen on the validation splits; the test splits are measured as they fall.")
    # A single seed has no spread (its std is NaN): say nothing rather than "at most nan".
    widest = max(summary, key=lambda split: summary[split]["ours_std"], default=None) if len(seeds) > 1 else None
    if widest is not None:
        # What one run of `make subject` is worth: how far a single seed strays from the mean.
        section.paragraph(f"One run is one draw of these: ours' standard deviation over the seeds is at most "
                          f"{summary[widest]['ours_std']:.2f} dB ({SPLIT_LABELS[widest]}).")
    table = Table(["split", "ours mean ± std", "TRAvatar* mean ± std", "ours - TRAvatar*", "95% interval", "verdict"],
                  table_id="seeds-table")
    for split, row in summary.items():
        lo, hi = row["diff_ci95"]
        table.add([SPLIT_LABELS[split], f"{row['ours_mean']:.2f} ± {row['ours_std']:.2f}",
                   f"{row['travatar_mean']:.2f} ± {row['travatar_std']:.2f}", f"{row['diff_mean']:+.2f}",
                   f"[{lo:+.2f}, {hi:+.2f}]", str(row["verdict"])])
    section.table(table)
    where = _where_the_spread_sits(result.get("uncovered_spread"))
    if where:
        section.paragraph(where)
    return section


def _where_the_spread_sits(uncovered: object) -> str:
    """A sentence on how much of ours' validation spread is in pixels the head leaves transparent, or ''.

    ``uncovered`` is the bench's ``uncovered_spread`` (``benchmarks.bench_seeds.uncovered_spread``);
    files written before it was kept have none, and say nothing.
    """
    if not isinstance(uncovered, dict):
        return ""
    parts = []
    for split in ("val_light", "val_perf"):
        row = uncovered.get(f"ours_{split}")
        try:
            parts.append(f"{SPLIT_LABELS[split]}: {float(row['psnr_std']):.2f} dB, {float(row['covered_psnr_std']):.2f} "
                         f"dB without them (correlation of the PSNR with their share of the error "
                         f"{float(row['correlation']):+.2f})")
        except (TypeError, KeyError, ValueError):
            continue
    if not parts:
        return ""
    return ("Where ours' spread sits: its standard deviation over the seeds, and that of the PSNR its error off the "
            "foreground pixels it renders transparent would give; " + "; ".join(parts) + ". A much smaller spread "
            "without them, with a negative correlation, says the runs differ in which parts of the head they leave "
            "uncovered more than in the head they cover.")
