"""Two sets of ``bench_seeds`` runs compared split by split: paired by seed where that means something, else not.

``bench_seeds`` pairs a tagged run with its baseline only on the same train inputs (the same
``inputs_digest``): the same seed on the same files is the same draw but for the setting. A
capture setting that films other frames (``sequence.cycles``, say) builds other inputs, and its
validation splits hold other images; its runs can only be compared with the baseline's as two
independent samples. This tool does either:

- **paired** (both sides on the same inputs digest): the mean of the per-seed differences over the
  seeds both hold, with a Student's t 95% interval, as ``bench_seeds`` does;
- **unpaired** (other inputs): the difference of the means with Welch's 95% interval over all seeds
  of each side.

A side may be several result files of the same inputs and settings (``A.json+A2.json``: a bench split
over two processes); their seeds are merged. Usage::

    python -m benchmarks.compare_seeds bench-results/seeds_alice_ours_c4.json+bench-results/seeds_alice_ours_c4b.json \\
        bench-results/seeds_alice_ours_shipped.json

prints variant - baseline per model and split, with the spread of each side.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from benchmarks.bench_seeds import MODELS, SPLITS, paired_difference


def load_side(spec: str) -> tuple[str | None, dict[int, dict], tuple[str, ...]]:
    """The inputs digest, per-seed runs and models of ``spec`` (result files joined by ``+``).

    Raises ``SystemExit`` naming the file when the files of one side differ in inputs or settings.
    """
    digest, params, runs, models = None, None, {}, None
    for i, name in enumerate(spec.split("+")):
        path = Path(name)
        try:
            results = json.loads(path.read_text())
        except (OSError, ValueError) as err:
            raise SystemExit(f"{path}: not a bench_seeds results file ({err})") from err
        file_models = tuple(results.get("models") or MODELS)
        if i and (results.get("inputs_digest") != digest or _without_seed(results.get("params")) != params):
            raise SystemExit(f"{path}: other inputs or settings than {spec.split('+')[0]}; a side merges only "
                             "runs of one bench split over several files")
        digest, params = results.get("inputs_digest"), _without_seed(results.get("params"))
        models = file_models if models is None else tuple(m for m in models if m in file_models)
        for seed, run in results.get("runs", {}).items():
            runs[int(seed)] = run
    return digest, runs, models or ()


def _without_seed(params: dict | None) -> dict:
    return {k: v for k, v in (params or {}).items() if k != "seed"}


def welch_difference(a: list[float], b: list[float]) -> dict:
    """mean(a) - mean(b) with Welch's 95% interval (two independent samples, unequal variances)."""
    from scipy.stats import t as student_t

    a_, b_ = np.asarray(a, float), np.asarray(b, float)
    va, vb = a_.var(ddof=1) / len(a_), b_.var(ddof=1) / len(b_)
    dof = (va + vb) ** 2 / (va ** 2 / (len(a_) - 1) + vb ** 2 / (len(b_) - 1))
    half = float(student_t.ppf(0.975, dof) * np.sqrt(va + vb))
    diff = float(a_.mean() - b_.mean())
    verdict = "variant ahead" if diff - half > 0 else "baseline ahead" if diff + half < 0 else "not resolved"
    return {"diff_mean": diff, "diff_ci95": [diff - half, diff + half], "verdict": verdict, "dof": float(dof)}


def compare(variant: str, baseline: str) -> dict:
    """Variant - baseline per ``<model>_<split>``: paired on the same inputs digest, else Welch."""
    v_digest, v_runs, v_models = load_side(variant)
    b_digest, b_runs, b_models = load_side(baseline)
    models = tuple(m for m in v_models if m in b_models)
    paired = v_digest is not None and v_digest == b_digest
    seeds = sorted(set(v_runs) & set(b_runs)) if paired else []
    if paired and len(seeds) < 2:
        raise SystemExit("the two sides share the inputs but fewer than 2 seeds: nothing to pair")
    if not paired and (len(v_runs) < 2 or len(b_runs) < 2):
        raise SystemExit("an unpaired comparison needs at least 2 seeds on each side")
    out: dict = {"paired": paired, "seeds": seeds if paired else {"variant": sorted(v_runs), "baseline": sorted(b_runs)}}
    for m in models:
        for s in SPLITS:
            key = f"{m}_{s}"
            if paired:
                entry = paired_difference([v_runs[x][key] for x in seeds], [b_runs[x][key] for x in seeds],
                                          ("variant", "baseline"))
                v_vals, b_vals = [v_runs[x][key] for x in seeds], [b_runs[x][key] for x in seeds]
            else:
                v_vals, b_vals = [r[key] for r in v_runs.values()], [r[key] for r in b_runs.values()]
                entry = welch_difference(v_vals, b_vals)
            entry.update(variant_mean=float(np.mean(v_vals)), variant_std=float(np.std(v_vals, ddof=1)),
                         baseline_mean=float(np.mean(b_vals)), baseline_std=float(np.std(b_vals, ddof=1)))
            out[key] = entry
    return out


def main(argv: list[str]) -> dict:
    if len(argv) != 2:
        raise SystemExit("usage: python -m benchmarks.compare_seeds VARIANT.json[+MORE.json] BASELINE.json[+MORE.json]")
    result = compare(*argv)
    how = (f"paired by seed over {result['seeds']}" if result["paired"] else
           f"unpaired (other inputs), Welch, seeds {result['seeds']['variant']} against {result['seeds']['baseline']}")
    print(f"variant - baseline, {how} (95% CI):")
    for key, r in result.items():
        if isinstance(r, dict) and "diff_mean" in r:
            print(f"  {key:<22} {r['variant_mean']:6.2f} ± {r['variant_std']:4.2f} against {r['baseline_mean']:6.2f} ± "
                  f"{r['baseline_std']:4.2f}: {r['diff_mean']:+.2f} [{r['diff_ci95'][0]:+.2f}, {r['diff_ci95'][1]:+.2f}]"
                  f"  {r['verdict']}")
    return result


if __name__ == "__main__":
    main(sys.argv[1:])
