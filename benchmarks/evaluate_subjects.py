"""``make evaluate-subjects``: fresh subjects nobody developed on, through ``train``, every stage's accuracy over them.

Each unseen subject is ``configs/subjects/unseen.yaml`` (the ``tiny`` preset) with its identity,
performance and sensor-noise seeds drawn from ``UNSEEN_SEEDS``, a range that no subject file,
preset, test or tuning run uses (``tests/benchmarks/test_evaluate_subjects.py`` checks the
configuration files). Each runs in a workspace root of its own
(``workspaces/unseen/<identity seed>``), as a user's first run would: ``pipeline run -S unseen
--until train`` plus the evaluation stages.

Reports, in ``bench-results/unseen_subjects.json`` and a table on stdout:

- per stage, each figure's mean and worst over the subjects (worst = the direction that is bad
  for it: the largest error, the smallest PSNR);
- per subject, ours against TRAvatar* on the validation and the test splits.

Usage: ``python -m benchmarks.evaluate_subjects [--subjects 3] [--first 0] [--preset tiny]``.
11 to 13 minutes a subject on a 2-core CPU (``tiny``, the realistic studio).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench-results"
#: Identity seeds reserved for unseen subjects; the performance seed is +1000, the noise seed +2000.
UNSEEN_SEEDS = range(7001, 8000)
STAGES = ("capture", "calibrate", "lightcal", "track", "stabilize", "matte", "train")
#: The figures summarised per stage, and whether larger is worse.
FIGURES: dict[str, dict[str, bool]] = {
    "calibrate": {"reproj_rms_px": True, "focal_err_pct_max": True, "center_err_mm_max": True,
                  "rotation_err_deg_max": True},
    "lightcal": {"bar_center_err_mm_mean": True, "bar_center_err_mm_max": True},
    "track": {"vertex_err_mm_mean_full": True, "vertex_err_mm_mean_olat": True, "rotation_err_deg_mean": True,
              "translation_err_mm_mean": True},
    "stabilize": {"head_pose_residual_deg_max": True},
    "matte": {"mae_full": True, "mae_olat": True, "grad_err_olat": True},
    "train": {f"{model}_{split}_psnr": False for model in ("ours", "travatar")
              for split in ("val_light", "val_perf", "novel_light", "novel_perf", "novel_both")},
}
SPLITS = ("val_light", "val_perf", "novel_light", "novel_perf", "novel_both")


def subject_sets(identity_seed: int) -> list[str]:
    """The ``--set`` overrides of one unseen subject."""
    if identity_seed not in UNSEEN_SEEDS:
        raise ValueError(f"identity seed {identity_seed} is outside the unseen range {UNSEEN_SEEDS}")
    return [f"capture.identity_seed={identity_seed}", f"capture.performance_seed={identity_seed + 1000}",
            f"capture.render.seed={identity_seed + 2000}"]


def _pipeline(args: list[str], workspaces: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PIPELINE_WORKSPACES=str(workspaces), PIPELINE_PROJECT_ROOT=str(ROOT))
    return subprocess.run([sys.executable, "-m", "pipeline.cli", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, check=False)


def run_subject(identity_seed: int, workspaces: Path, preset: str | None, workers: int) -> dict[str, dict]:
    """Run one unseen subject through train (and the evaluation stages); its merged figures per stage."""
    sets = [a for s in subject_sets(identity_seed) for a in ("--set", s)]
    extra = ["--preset", preset] if preset else []
    targets = [s for s in STAGES if s != "train"]
    done = _pipeline(["run", "-S", "unseen", "--until", "train", "--workers", str(workers), *extra, *sets],
                     workspaces)
    if done.returncode != 0:
        raise RuntimeError(f"unseen subject {identity_seed}: pipeline run failed:\n{done.stderr[-4000:]}")
    # The evaluation stages of the stages up to train (they are not upstream of train).
    evals = [f"{s}_eval" for s in targets]
    done = _pipeline(["run", "-S", "unseen", "--only", *evals, "--workers", str(workers), *extra, *sets], workspaces)
    if done.returncode != 0:
        raise RuntimeError(f"unseen subject {identity_seed}: evaluation stages failed:\n{done.stderr[-4000:]}")
    figures = {}
    for stage in STAGES:
        shown = _pipeline(["show", "-S", "unseen", stage, "--json"], workspaces)
        if shown.returncode != 0:
            raise RuntimeError(f"unseen subject {identity_seed}: pipeline show {stage} failed: {shown.stderr[-2000:]}")
        figures[stage] = json.loads(shown.stdout)
    return figures


def summarise(per_subject: dict[int, dict[str, dict]]) -> dict:
    """Mean and worst over subjects of every figure in ``FIGURES``; ours against TRAvatar* per subject."""
    stages: dict[str, dict[str, dict[str, float]]] = {}
    for stage, keys in FIGURES.items():
        for key, larger_is_worse in keys.items():
            values = [float(f[stage][key]) for f in per_subject.values()
                      if isinstance(f.get(stage, {}).get(key), (int, float))]
            if not values:
                continue
            worst = max(values) if larger_is_worse else min(values)
            stages.setdefault(stage, {})[key] = {"mean": float(np.mean(values)), "worst": worst, "n": len(values)}
    versus = {}
    for seed, f in per_subject.items():
        train = f.get("train", {})
        versus[str(seed)] = {split: {"ours": train.get(f"ours_{split}_psnr"),
                                     "travatar": train.get(f"travatar_{split}_psnr"),
                                     "ours_minus_travatar": (train[f"ours_{split}_psnr"] - train[f"travatar_{split}_psnr"]
                                                             if f"ours_{split}_psnr" in train
                                                             and f"travatar_{split}_psnr" in train else None)}
                             for split in SPLITS}
    return {"subjects": sorted(per_subject), "stages": stages, "ours_vs_travatar": versus}


def format_summary(summary: dict) -> str:
    lines = ["| stage | figure | mean | worst |", "| --- | --- | --- | --- |"]
    for stage, keys in summary["stages"].items():
        for key, v in keys.items():
            lines.append(f"| {stage} | {key} | {v['mean']:.4g} | {v['worst']:.4g} |")
    lines += ["", "| subject | " + " | ".join(f"{s} ours - TRAvatar*" for s in SPLITS) + " |",
              "| --- |" + " --- |" * len(SPLITS)]
    for seed, splits in summary["ours_vs_travatar"].items():
        cells = [f"{splits[s]['ours_minus_travatar']:+.2f}" if splits[s]["ours_minus_travatar"] is not None else "-"
                 for s in SPLITS]
        lines.append(f"| {seed} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="evaluate_subjects", description=__doc__.split("\n")[0])
    parser.add_argument("--subjects", type=int, default=3, help="how many unseen subjects")
    parser.add_argument("--first", type=int, default=0, help="index of the first seed in the unseen range")
    parser.add_argument("--preset", default=None, help="preset instead of unseen.yaml's (tiny)")
    parser.add_argument("--workers", type=int, default=2, help="per-item workers of each run")
    parser.add_argument("--workspaces", default=str(ROOT / "workspaces" / "unseen"), help="root of the subjects' "
                        "workspace roots (one per subject)")
    args = parser.parse_args(argv)
    seeds = list(UNSEEN_SEEDS)[args.first:args.first + args.subjects]
    OUT.mkdir(exist_ok=True)
    per_subject: dict[int, dict[str, dict]] = {}
    for seed in seeds:
        start = time.perf_counter()
        per_subject[seed] = run_subject(seed, Path(args.workspaces) / str(seed), args.preset, args.workers)
        print(f"unseen subject {seed}: done in {time.perf_counter() - start:.0f} s", flush=True)
        summary = summarise(per_subject)  # written after every subject: a long run keeps what it has
        (OUT / "unseen_subjects.json").write_text(json.dumps({"summary": summary, "figures": {
            str(s): f for s, f in per_subject.items()}}, indent=1))
    print(format_summary(summarise(per_subject)))
    print(f"wrote {OUT / 'unseen_subjects.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
