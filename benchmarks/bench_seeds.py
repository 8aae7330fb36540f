"""Ours against TRAvatar* over several seeds: is the difference larger than the seed-to-seed spread?

One training run gives one draw: on the tiny preset, changing only the seed (initialisation
and ray sampling) moves held-out PSNR by up to about 1 dB, as much as the gap between the two
models. This bench trains both models with the tiny preset's settings on a subject's train
inputs once per seed and reports, per split (validation: ``val_light``, ``val_perf``, what a
setting is adopted by; test: ``novel_*``, the claim; and the training images), each model's mean and standard deviation and the
paired difference ours - TRAvatar* (same seed, same data) with its 95% confidence interval
(Student's t over the seeds). A split is called for a model only when the interval excludes 0.

Knobs: ``SEEDS_SUBJECT`` (default alice; a synthetic capture when the subject has no train
inputs), ``SEEDS`` (default ``0,1,2``), ``SEEDS_ITERATIONS`` (default: the preset's),
``SEEDS_SET`` (a JSON object of train params laid over the preset's, nested sections merged
key by key, e.g. ``'{"capacity_rule": {"latent_per_mode": 0}}'`` to train both models at the
avatar section's latent size instead of the rule's; ``'{"init_seed": 0}'`` holds the initial weights and
varies only the ray sampling and latent noise with the seed, ``'{"sampling_seed": 0}'`` the reverse) and
``SEEDS_TAG`` (a name for that variant) and ``SEEDS_CURVE_EVERY`` (default 0: no curve; N: each
run keeps both models' learning curves, the validation-light PSNR of 3 images every N iterations,
as ``curve_ours`` and ``curve_travatar``: [iteration, seconds, PSNR] points, to see where in
training the seeds part; each point renders 3 images, so the training time grows a little). Writes ``bench-results/seeds_<subject>.json`` (``seeds_<subject>_<tag>.json`` with a
tag) after every seed, so a stopped run keeps the seeds it finished; a later run with the same
settings reuses the seeds that file already holds and trains only the new ones. A tagged run
also compares itself with a baseline file's runs of the same seeds and data (the same digest of
the input files: another build of a subject can differ in its images and draw other runs for a
seed) where there are any (at the iterations each was run with; both are printed): variant -
baseline per model and split, paired by seed, with the same 95% interval (``against_default`` in its results). The
baseline is the untagged file, or ``seeds_<subject>_<SEEDS_BASELINE>.json`` when
``SEEDS_BASELINE`` names a tag (e.g. ``it5k``, the preset's 5000 iterations on bob). Each run
records its training wall time (``seconds``, printed as a mean per seed), how many primitives
ours pruned (``ours_pruned_primitives``), each model's clipped steps (``<model>_clipped_steps``,
``train.grad_clip_factor``), the share of its opacity logits on the softplus' flat tail
(``<model>_opacity_logits_below_floor``), the share of its boxes pressed to their smallest size
(``<model>_boxes_at_smallest_size``), its encoder's noise over its codes' spread
(``<model>_latent_noise_to_code_spread``, set by the KL weight) and the share of its validation error where it leaves the
head transparent (``<model>_val_light_uncovered_error_share``, ``..._val_perf_...``): how a run
that left holes shows. ``SEEDS_MODELS=ours`` trains ours alone (``train.baseline`` off; a
tag is then required, so the untagged file the report reads always holds both models): a setting
is adopted by what it does to ours, and ours alone takes one core, so two such benches run side
by side on a 2-core CPU and screen two settings in the time of one. Ours' figures are the same,
seed for seed, as when it trains beside TRAvatar*, and an ours-only run pairs with a baseline file
of either kind on ours. ``SEEDS_REFERENCE`` (a workspaces root holding another build of the same
subject, the same frames: a capture setting changed, say ``capture.render.bar_samples``) also scores
each run on that build's images (``ref_<model>_<split>``, ``benchmarks/cross_build.py``): a capture
setting changes the targets as well as the training images, and one build's targets judge both.
Where the baseline file is that build's, or was itself scored on this one, the tagged run's
``across_builds`` pairs the two builds' models on one build's images. PSNR only (no LPIPS). About 6 to 8 minutes a seed run alone on a
2-core CPU with the tiny preset (both models side by side, 5000 iterations each: 324 to 348 s of
training a seed on alice in the realistic studio, plus 1 to 2 minutes of loading; a slower
machine took 479 to 570 s).
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.train_runs import ROOT, inputs_digest, run_train, tiny_train_params, train_inputs
from pipeline.workspace import write_json_atomic

#: Validation first: a setting is adopted by what it does to ours there, over seeds (docs/experiments.md,
#: "The validation split"); the test splits are the claim, measured as they fall.
SPLITS = ("val_light", "val_perf", "novel_light", "novel_perf", "novel_both", "train")
MODELS = ("ours", "travatar")


def paired_difference(a: list[float], b: list[float], names: tuple[str, str] = ("ours", "TRAvatar*")) -> dict:
    """The paired difference a - b: its mean, 95% interval (Student's t) and verdict.

    The verdict names the side ahead (``names``) only when the interval excludes 0.
    """
    from scipy.stats import t as student_t

    diff = np.asarray(a, float) - np.asarray(b, float)
    n = len(diff)
    half = float(student_t.ppf(0.975, n - 1) * diff.std(ddof=1) / np.sqrt(n)) if n > 1 else float("inf")
    lo, hi = float(diff.mean()) - half, float(diff.mean()) + half
    verdict = f"{names[0]} ahead" if lo > 0 else f"{names[1]} ahead" if hi < 0 else "not resolved"
    return {"diff_mean": float(diff.mean()), "diff_ci95": [lo, hi], "verdict": verdict}


def mean_std(values: list[float], name: str) -> dict:
    """``{name}_mean`` and ``{name}_std`` (sample std; NaN with one value) of ``values``."""
    a = np.asarray(values, float)
    return {f"{name}_mean": float(a.mean()), f"{name}_std": float(a.std(ddof=1)) if len(a) > 1 else float("nan")}


def paired_summary(ours: list[float], baseline: list[float]) -> dict:
    """Mean and sample std of each list, and the paired difference ours - baseline with its 95% interval."""
    return {**mean_std(ours, "ours"), **mean_std(baseline, "travatar"), **paired_difference(ours, baseline)}


def uncovered_spread(runs: dict[int, dict], seeds: list[int], models: tuple[str, ...] = MODELS) -> dict:
    """How much of each model's spread over ``seeds`` sits where it leaves the capture's head transparent.

    Per model and validation split: the PSNR's mean and sample std; the correlation over seeds of
    the PSNR with the uncovered error share (the share of the split's squared error on foreground
    pixels the render leaves transparent, ``stages.train.evaluate.coverage_metrics``); and the
    mean and std of the PSNR the rest of the error alone would give, PSNR - 10 log10(1 - share).
    A narrow spread there with a wide one in the PSNR says that the runs differ in their holes and
    silhouettes rather than in the head they do cover. Seeds without the share are left out; a
    split with fewer than 3 such seeds is left out.
    """
    out: dict = {}
    for m in models:
        for split in ("val_light", "val_perf"):
            key = f"{m}_{split}_uncovered_error_share"
            held = [x for x in seeds if x in runs and key in runs[x]]
            if len(held) < 3:
                continue
            psnr = np.asarray([runs[x][f"{m}_{split}"] for x in held], float)
            share = np.asarray([runs[x][key] for x in held], float)
            rest = psnr - 10.0 * np.log10(np.clip(1.0 - share, 1e-12, None))
            flat = float(share.std()) == 0.0 or float(psnr.std()) == 0.0
            out[f"{m}_{split}"] = {"seeds": held, **mean_std(list(psnr), "psnr"), **mean_std(list(rest), "covered_psnr"),
                                   "share_min": float(share.min()), "share_max": float(share.max()),
                                   "correlation": float("nan") if flat else float(np.corrcoef(psnr, share)[0, 1])}
    return out


def against_default(runs: dict[int, dict], default: dict[int, dict], seeds: list[int],
                    models: tuple[str, ...] = MODELS) -> dict:
    """Variant - default per ``<model>_<split>`` of ``models`` over the ``seeds`` both hold (paired by seed); {} if none."""
    shared = [x for x in seeds if x in runs and x in default]
    if not shared:
        return {}
    return {"seeds": shared, **{f"{m}_{s}": paired_difference([runs[x][f"{m}_{s}"] for x in shared],
                                                           [default[x][f"{m}_{s}"] for x in shared],
                                                           ("variant", "default"))
                                for m in models for s in SPLITS}}


def merge_params(base: dict, overrides: dict) -> dict:
    """``base`` with ``overrides`` laid over it; a nested section (a dict in both) is merged key by key."""
    out = dict(base)
    for key, value in overrides.items():
        out[key] = merge_params(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) \
            else value
    return out


def _overrides() -> dict:
    text = os.environ.get("SEEDS_SET", "").strip()
    try:
        value = json.loads(text) if text else {}
    except ValueError as err:
        raise SystemExit(f"SEEDS_SET={text!r} is not JSON ({err}); give an object of train params, "
                         "e.g. '{\"capacity_rule\": {\"latent_per_mode\": 0}}'") from err
    if not isinstance(value, dict):
        raise SystemExit(f"SEEDS_SET={text!r} must be a JSON object of train params")
    return value


def _models(tag: str) -> tuple[str, ...]:
    """The models ``SEEDS_MODELS`` names: both (the default, or ``ours,travatar``) or ``ours`` alone, with a tag."""
    text = os.environ.get("SEEDS_MODELS", "").strip().replace(" ", "")
    if text in ("", "ours,travatar", "travatar,ours"):
        return MODELS
    if text != "ours":
        raise SystemExit(f"SEEDS_MODELS={text!r}: give 'ours' (ours alone) or 'ours,travatar' (both, the default)")
    if not tag:
        # The untagged file is the report's headline comparison: it must hold both models.
        raise SystemExit("SEEDS_MODELS=ours needs a SEEDS_TAG: the untagged results file holds both models")
    return ("ours",)


def main() -> dict:
    subject = os.environ.get("SEEDS_SUBJECT", "alice")
    seeds = [int(s) for s in os.environ.get("SEEDS", "0,1,2").split(",")]
    tag = _tag("SEEDS_TAG")
    baseline = _tag("SEEDS_BASELINE")
    models = _models(tag)
    preset = tiny_train_params()
    iterations = int(os.environ.get("SEEDS_ITERATIONS", "0")) or int(preset["iterations"])
    curve_every = int(os.environ.get("SEEDS_CURVE_EVERY", "0"))
    base = merge_params({**preset, "iterations": iterations, "baseline": "travatar" in models, "baseline_iterations": 0,
                         "lpips": False, "curve_every": curve_every, "previews": 0}, _overrides())
    out = ROOT / "bench-results"
    path = out / (f"seeds_{subject}_{tag}.json" if tag else f"seeds_{subject}.json")
    with tempfile.TemporaryDirectory(prefix="bench-seeds-") as tmp:
        scratch = Path(tmp)
        inputs, source = train_inputs(subject, scratch)
        digest = inputs_digest(inputs)
        reference = _reference_inputs(subject)
        reference_digest = inputs_digest(reference) if reference else None
        runs = _earlier_runs(path, base, source, models, digest)
        if reference:
            # Reuse only seeds already scored on this reference.
            runs = {x: r for x, r in runs.items() if r.get("reference_digest") == reference_digest}
            print(f"seeds: each run also scored on {os.environ['SEEDS_REFERENCE']}'s {subject} "
                  f"(inputs {reference_digest})", flush=True)
        print(f"seeds: {source} (inputs {digest}), {iterations} iterations per model, seeds {seeds}"
              + (f" (seeds {sorted(set(runs) & set(seeds))} from {path.name})" if set(runs) & set(seeds) else ""),
              flush=True)
        for seed in seeds:
            if seed in runs:
                continue
            trained = run_train(inputs, {**base, "seed": seed}, scratch, f"seed{seed}",
                                **({"reference_inputs": reference} if reference else {}))
            m = trained["metrics"]
            runs[seed] = {f"{k}_{s}": m[f"{k}_{s}_psnr"] for k in models for s in SPLITS}
            if reference:
                runs[seed].update({f"ref_{k}": v for k, v in trained["reference"].items()})
                runs[seed]["reference_digest"] = reference_digest
            runs[seed]["seconds"] = m["seconds"]  # training wall time, every model trained
            # Whether the pruning dropped anything (docs/experiments.md, section 22, had to infer it).
            runs[seed]["ours_pruned_primitives"] = m.get("pruned_primitives")
            for kind in models:  # how often train.grad_clip_factor bound the step (0 when it is off)
                runs[seed][f"{kind}_clipped_steps"] = m.get(f"{kind}_clipped_steps")
            # How a run with holes shows (docs/experiments.md, section 34): flat opacity logits, and
            # the validation error where the capture's head is rendered transparent.
            for key in [f"{k}_opacity_logits_below_floor" for k in models] + [
                    f"{k}_boxes_at_smallest_size" for k in models] + [
                    f"{k}_latent_noise_to_code_spread" for k in models] + [
                    f"{k}_{s}_uncovered_error_share" for k in models for s in ("val_light", "val_perf")]:
                if key in m:
                    runs[seed][key] = m[key]
            for kind, curve in trained.get("curve", {}).items():
                if curve:
                    runs[seed][f"curve_{kind}"] = curve
            print(f"seed {seed}: " + ", ".join(f"{s} " + "/".join(f"{runs[seed][f'{k}_{s}']:.2f}" for k in models)
                                                for s in SPLITS)
                  + (" (ours/TRAvatar*)" if len(models) > 1 else " (ours)"), flush=True)
            # Each seed costs minutes: keep it at once, so a stopped run resumes from here.
            write_json_atomic(path, {"subject": subject, "source": source, "inputs_digest": digest,
                                  "iterations": iterations,
                                  "seeds": sorted(runs), "params": base, "complete": False,
                                  "runs": {str(k): v for k, v in sorted(runs.items())},
                                  "models": list(models), "summary": _summary(runs, sorted(runs), models)})
    summary = _summary(runs, seeds, models)
    if len(models) > 1:
        print(f"{'split':<12} {'ours':>13} {'TRAvatar*':>13} {'ours - TRAvatar* (95% CI)':>30}  verdict")
        for s, r in summary.items():
            print(f"{s:<12} {r['ours_mean']:6.2f} ± {r['ours_std']:4.2f} {r['travatar_mean']:6.2f} ± "
                  f"{r['travatar_std']:4.2f} {r['diff_mean']:+6.2f} [{r['diff_ci95'][0]:+.2f}, "
                  f"{r['diff_ci95'][1]:+.2f}]{'':>8}  {r['verdict']}")
    else:
        print(f"{'split':<12} {'ours':>13}")
        for s, r in summary.items():
            print(f"{s:<12} {r['ours_mean']:6.2f} ± {r['ours_std']:4.2f}")
    uncovered = uncovered_spread(runs, seeds, models)
    if uncovered:
        print("where the spread sits: PSNR, and the PSNR of the error off the pixels the head leaves transparent")
        for key, r in uncovered.items():
            print(f"  {key:<18} {r['psnr_mean']:6.2f} ± {r['psnr_std']:4.2f}   without them {r['covered_psnr_mean']:6.2f} ± "
                  f"{r['covered_psnr_std']:4.2f}   uncovered error share {r['share_min']:.2f}-{r['share_max']:.2f}, "
                  f"correlation with PSNR {r['correlation']:+.2f}")
    timed = [runs[x]["seconds"] for x in seeds if "seconds" in runs[x]]
    if timed:
        print(f"training wall time per seed ({'both models' if len(models) > 1 else 'ours alone'}): "
              f"{np.mean(timed):.0f} s (min {min(timed):.0f}, max {max(timed):.0f}, {len(timed)} seeds)")
    results = {"subject": subject, "source": source, "inputs_digest": digest, "iterations": iterations,
               "reference_digest": reference_digest,
               "seeds": seeds, "params": base,
               "models": list(models), "complete": True, "runs": {str(k): v for k, v in sorted(runs.items())}, "summary": summary,
               "uncovered_spread": uncovered}
    if tag and tag != baseline:
        baseline_name = f"seeds_{subject}_{baseline}.json" if baseline else f"seeds_{subject}.json"
        default_iterations, default = _default_runs(out / baseline_name, source, models, digest)
        compared = against_default(runs, default, seeds, models)
        if compared:
            compared["default_iterations"] = default_iterations
            compared["baseline_file"] = baseline_name
            print(f"{tag} ({iterations} iterations) - {baseline or 'default'} ({default_iterations} iterations, "
                  f"{baseline_name}), paired over seeds {compared['seeds']} (95% CI):")
            for m in models:
                print(f"  {'ours' if m == 'ours' else 'TRAvatar*':<9} " + ", ".join(
                    f"{s} {compared[f'{m}_{s}']['diff_mean']:+.2f} [{compared[f'{m}_{s}']['diff_ci95'][0]:+.2f}, "
                    f"{compared[f'{m}_{s}']['diff_ci95'][1]:+.2f}]" for s in SPLITS))
            results["against_default"] = compared
        across = _across_builds(runs, digest, reference_digest, out / baseline_name, seeds, models)
        if across:
            results["across_builds"] = across
        elif baseline and not (out / baseline_name).exists():
            print(f"SEEDS_BASELINE={baseline!r}: no {baseline_name} in {out}; nothing to compare with")
    write_json_atomic(path, results)
    return results


def _reference_inputs(subject: str) -> dict[str, str] | None:
    """``SEEDS_REFERENCE``'s train inputs for ``subject`` (a workspaces root holding another build), or None."""
    root = os.environ.get("SEEDS_REFERENCE", "").strip()
    if not root:
        return None
    from benchmarks.train_runs import INPUT_STAGES
    from pipeline.errors import PipelineError
    from pipeline.workspace import Workspace

    try:
        ws = Workspace(Path(root).expanduser().resolve(), subject)
        return {k: str(ws.output_path(k)) for k in INPUT_STAGES}
    except (PipelineError, OSError) as err:
        raise SystemExit(f"SEEDS_REFERENCE={root}: no train inputs of subject '{subject}' there ({err}); build them "
                         f"with `PIPELINE_WORKSPACES={root} pipeline run -S {subject} --until matte`") from err


def _across_builds(runs: dict[int, dict], digest: str, reference_digest: str | None, baseline_path: Path,
                   seeds: list[int], models: tuple[str, ...]) -> dict:
    """This build's models against the baseline file's, both scored on one build's images, paired by seed.

    ``on_baseline_build``: this run's models on the baseline's images (``SEEDS_REFERENCE`` is the baseline's
    build) minus the baseline's own figures. ``on_this_build``: this run's own figures minus the baseline's
    models scored on this build's images (the baseline ran with ``SEEDS_REFERENCE`` set to this build).
    Either is left out where the files do not hold it.
    """
    try:
        base = json.loads(baseline_path.read_text())
    except (OSError, ValueError):
        return {}
    base_runs = {int(k): v for k, v in base.get("runs", {}).items()}
    out: dict = {}
    for name, mine, theirs, wanted in (
            ("on_baseline_build", "ref_", "", reference_digest is not None and base.get("inputs_digest") == reference_digest),
            ("on_this_build", "", "ref_", True)):
        if not wanted:
            continue
        shared = [x for x in seeds if x in runs and x in base_runs
                  and (name == "on_baseline_build" or base_runs[x].get("reference_digest") == digest)
                  and all(f"{mine}{m}_{s}" in runs[x] and f"{theirs}{m}_{s}" in base_runs[x]
                          for m in models for s in SPLITS)]
        if not shared:
            continue
        out[name] = {"seeds": shared, **{f"{m}_{s}": paired_difference(
            [runs[x][f"{mine}{m}_{s}"] for x in shared], [base_runs[x][f"{theirs}{m}_{s}"] for x in shared],
            ("variant", "baseline")) for m in models for s in SPLITS}}
        print(f"{name.replace('_', ' ')}: variant - baseline, one build's images, seeds {shared} (95% CI):")
        for m in models:
            print(f"  {'ours' if m == 'ours' else 'TRAvatar*':<9} " + ", ".join(
                f"{s} {out[name][f'{m}_{s}']['diff_mean']:+.2f} [{out[name][f'{m}_{s}']['diff_ci95'][0]:+.2f}, "
                f"{out[name][f'{m}_{s}']['diff_ci95'][1]:+.2f}]" for s in SPLITS))
    return out


def _summary(runs: dict[int, dict], seeds: list[int], models: tuple[str, ...] = MODELS) -> dict:
    """Per split: each model's mean and spread over ``seeds``, and with both the paired difference ours - TRAvatar*."""
    if "travatar" in models:
        return {s: paired_summary([runs[x][f"ours_{s}"] for x in seeds], [runs[x][f"travatar_{s}"] for x in seeds])
                for s in SPLITS}
    return {s: mean_std([runs[x][f"ours_{s}"] for x in seeds], "ours") for s in SPLITS}


def _tag(variable: str) -> str:
    """The tag in environment ``variable`` ('' if unset); it names a results file, so only [A-Za-z0-9_-]."""
    tag = os.environ.get(variable, "").strip()
    if tag and not tag.replace("-", "").replace("_", "").isalnum():
        raise SystemExit(f"{variable}={tag!r}: use letters, digits, '-' and '_' (it names a results file)")
    return tag


def _runs_matching(path: Path, models: tuple[str, ...] = MODELS, digest: str | None = None,
                   **expected: object) -> dict[int, dict]:
    """Per-seed figures of the results file ``path`` if its fields equal ``expected``, else none.

    With ``digest``, a file of other inputs (``inputs_digest``) gives none either; a file written
    before the bench kept the digest is matched on the rest alone.

    A seed without every split's figures for each of ``models`` is left out: it was trained before
    the validation split existed, on frames that are now held out, so it is neither reused nor
    paired. A file of both models pairs with an ours-only run on ours.
    """
    try:
        results = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    if any(results.get(key) != value for key, value in expected.items()):
        return {}
    if digest is not None and results.get("inputs_digest", digest) != digest:
        return {}  # another build of the inputs: its seeds draw other runs (train_runs.inputs_digest)
    keys = {f"{m}_{s}" for m in models for s in SPLITS}
    return {int(k): v for k, v in results.get("runs", {}).items() if keys <= set(v)}


def _default_runs(path: Path, source: str, models: tuple[str, ...] = MODELS,
                  digest: str | None = None) -> tuple[int | None, dict[int, dict]]:
    """Iterations and per-seed figures of the untagged run on the same data, else (None, {}).

    Its iterations may differ from the variant's: a variant may spend a different budget
    (``SEEDS_ITERATIONS``), and the comparison says so.
    """
    runs = _runs_matching(path, models, digest, source=source)
    if not runs:
        return None, {}
    return int(json.loads(path.read_text())["iterations"]), runs


def _earlier_runs(path: Path, params: dict, source: str, models: tuple[str, ...] = MODELS,
                  digest: str | None = None) -> dict[int, dict]:
    """Per-seed figures of an earlier run of this bench with the same train params and data, else none.

    Training is deterministic for a seed, so adding seeds (``SEEDS=0,1,2,3,4`` after ``0,1,2``)
    trains only the new ones. The data is identified by its source and the digest of the input
    files (``train_runs.inputs_digest``), so a rebuilt subject whose files differ trains again.
    """
    return _runs_matching(path, models, digest, params=params, source=source)


if __name__ == "__main__":
    main()
