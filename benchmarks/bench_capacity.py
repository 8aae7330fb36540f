"""Capacity against held-out PSNR and cost: the curve that justifies the capacity rule.

Trains the relightable head (ours only, the tiny preset's train settings) at a sweep of
capacities around the rule's choice (``avatar.capacity``): N*M texels per UV side from a
quarter to four times the rule's, the same decoder width, the same short training for every
size. Records held-out PSNR (``heldout_psnr``: the mean of the validation-light and
validation-performance splits, so that the rule's constant is chosen on validation only; the
test splits' figures are recorded beside it, never used), iterations per second, peak memory,
parameters and primitives pruned, finds the knee of validation PSNR against log2(N*M)
(Kneedle) and says whether the rule's choice sits at it (and, if not, which
``capacity_rule.min_texel_px`` would put it there).

Data: the train inputs of an existing workspace (``CAPACITY_SUBJECT``, default alice; run
``make subject S=alice`` first), else a small synthetic capture rendered like the train
tests' (``tests/stages/train/train_synth.py``). Each size trains in its own process, so
peak memory (RSS on a CPU) is that size's own. Knobs: ``CAPACITY_ITERATIONS`` (default: the
tiny preset's training iterations, so the knee is the one of the budget the default trains
with; fewer iterations favour smaller sizes), ``CAPACITY_SCALES`` (default ``0.25,0.5,1,2,4``; multiples of the rule's N*M; sizes
outside the rule's bounds are skipped), ``CAPACITY_OUT`` (default ``bench-results``). Writes
``capacity.json`` and ``capacity.png`` there. About 15 minutes on 2 CPU cores at the defaults.
Timings on a shared 2-core CPU are noisy.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.train_runs import ROOT, run_train, tiny_train_params, train_inputs


def _point(name: str, result: dict, texels: int, chosen: bool) -> dict:
    m = result["metrics"]
    # Validation only: the knee (and with it the rule's constant) must not be chosen on the test splits.
    psnrs = [m[f"ours_{s}_psnr"] for s in ("val_light", "val_perf") if f"ours_{s}_psnr" in m]
    return {
        "name": name, "texels_per_side": texels, "prims_per_side": m["capacity_prims_per_side"],
        "voxels_per_side": m["capacity_voxel_res"], "primitives": m["capacity_primitives"],
        "width": m["capacity_width"], "steps_per_ray": m["capacity_steps_per_ray"],
        "texel_px": m.get("capacity_texel_px"), "voxel_px": m.get("capacity_voxel_px"),
        "parameters": m.get("ours_parameters"),
        "heldout_psnr": float(np.mean(psnrs)), "val_light_psnr": m.get("ours_val_light_psnr"),
        "val_perf_psnr": m.get("ours_val_perf_psnr"), "novel_light_psnr": m.get("ours_novel_light_psnr"),
        "novel_perf_psnr": m.get("ours_novel_perf_psnr"), "novel_both_psnr": m.get("ours_novel_both_psnr"),
        "iterations": m["ours_iterations"], "train_seconds": m["ours_seconds"],
        "iterations_per_second": m["iterations_per_second"], "peak_memory_mb": m["peak_memory_mb"],
        "pruned_primitives": m.get("pruned_primitives"),
        "render_seconds_per_image": m.get("render_seconds_per_image"),
        "prune_render_speedup": m.get("prune_render_speedup"), "rule_choice": chosen,
    }


def main() -> dict:
    from avatar.capacity import CapacityRule, config_for, find_knee, texel_px
    from avatar.config import AvatarConfig

    subject = os.environ.get("CAPACITY_SUBJECT", "alice")
    iterations = int(os.environ.get("CAPACITY_ITERATIONS", "0")) or int(tiny_train_params()["iterations"])
    scales = [float(s) for s in os.environ.get("CAPACITY_SCALES", "0.25,0.5,1,2,4").split(",")]
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_capacity_") as tmp:
        scratch = Path(tmp)
        inputs, source = train_inputs(subject, scratch)
        base = {**tiny_train_params(), "iterations": iterations, "baseline": False, "lpips": False,
                "curve_every": 0, "previews": 0, "threads": 1, "checkpoint_every": 10 ** 6}
        auto = run_train(inputs, {**base, "capacity": "auto"}, scratch, "auto")
        cap = auto["capacity"]
        rule = CapacityRule(**cap["rule"])
        used = AvatarConfig(**cap["used"])
        chosen_texels = int(cap["rule_choice"]["texels_per_side"])
        width = int(cap["rule_choice"]["width"])
        points = [_point("auto", auto, chosen_texels, True)]
        print(f"rule's choice: N={used.prims_per_side} M={used.voxels_per_side} (N*M={chosen_texels}), width {width}: "
              f"{points[0]['heldout_psnr']:.2f} dB, {points[0]['iterations_per_second']:.2f} it/s", flush=True)
        min_texels = rule.min_prims_per_side * rule.min_voxels_per_side
        for scale in scales:
            texels = int(round(chosen_texels * scale))
            if texels == chosen_texels or texels < min_texels or texels & (texels - 1):
                continue
            config = config_for(texels, width, rule, used)
            params = {**base, "capacity": "fixed", "avatar": config.model_dump(mode="json")}
            result = run_train(inputs, params, scratch, f"t{texels}")
            points.append(_point(f"x{scale:g}", result, texels, False))
            p = points[-1]
            print(f"N={p['prims_per_side']} M={p['voxels_per_side']} (N*M={texels}): {p['heldout_psnr']:.2f} dB, "
                  f"{p['iterations_per_second']:.2f} it/s, {p['peak_memory_mb']:.0f} MB, {p['parameters']} params",
                  flush=True)
    points.sort(key=lambda p: p["texels_per_side"])
    knee_index = find_knee(np.log2([p["texels_per_side"] for p in points]), [p["heldout_psnr"] for p in points])
    knee = points[knee_index] if knee_index is not None else None
    at_knee = knee is not None and knee["texels_per_side"] == chosen_texels
    inputs_used = cap["inputs"]
    suggestion = None
    if knee is not None and not at_knee:
        # The rule picks the largest N*M with texel_px >= min_texel_px: a threshold between the
        # knee's texel pitch and the next size up's (geometric middle) picks the knee.
        suggestion = texel_px(knee["texels_per_side"], inputs_used["footprint_px"], used) / math.sqrt(2.0)
    verdict = ("the rule's default sits at the knee" if at_knee else
               "the rule's default is NOT at the knee" + (
                   f" (knee at N*M={knee['texels_per_side']}; capacity_rule.min_texel_px={suggestion:.2f} "
                   "would choose it)" if knee is not None else " (no knee: fewer than 3 sizes)"))
    print(verdict, flush=True)
    results = {
        "source": source, "iterations_per_size": iterations, "rule_inputs": inputs_used, "rule": cap["rule"],
        "rule_texels_per_side": chosen_texels, "rule_primitives": used.num_prims,
        "rule_voxels_per_side": used.voxels_per_side, "rule_width": width,
        "knee_texels_per_side": knee["texels_per_side"] if knee else None,
        "default_at_knee": bool(at_knee), "verdict": verdict, "suggested_min_texel_px": suggestion,
        "seconds": time.perf_counter() - start, "points": points,
        "note": "ours only, tiny preset's train settings, the same short training for every size; held-out PSNR = "
                "mean of validation light / validation performance (the test splits recorded, not used); shared 2-core CPU, timings noisy",
    }
    out = ROOT / os.environ.get("CAPACITY_OUT", "bench-results")
    out.mkdir(parents=True, exist_ok=True)
    (out / "capacity.json").write_text(json.dumps(results, indent=1))
    from stages.report.charts import capacity_chart

    capacity_chart([{**p, "knee": p is knee} for p in points], out / "capacity.png",
                   f"{source}, {iterations} it/size; knee N*M={results['knee_texels_per_side']}, "
                   f"rule N*M={chosen_texels}")
    print(f"{'N*M':>5} {'N':>4} {'M':>3} {'params':>8} {'PSNR dB':>8} {'it/s':>6} {'MB':>6} {'pruned':>6}")
    for p in points:
        print(f"{p['texels_per_side']:>5} {p['prims_per_side']:>4} {p['voxels_per_side']:>3} {p['parameters']:>8} "
              f"{p['heldout_psnr']:>8.2f} {p['iterations_per_second']:>6.2f} {p['peak_memory_mb']:>6.0f} "
              f"{p['pruned_primitives']:>6}" + ("  <- rule" if p["rule_choice"] else "")
              + ("  <- knee" if knee is p else ""))
    return results


if __name__ == "__main__":
    main()
