"""The matting network's domain gap: trained in a studio of its own against one like the subject's.

For a subject whose capture exists (``GAP_SUBJECT``, default alice: run ``pipeline run -S alice
--until capture`` first), trains the matting network twice with the tiny preset's matte section,
once with the shipped training conditions (``matte.data.conditions``: another backdrop,
exposure, lens blur and sensor per training identity) and once with
``TrainingConditions.same_as_capture()`` (the subject's own studio conditions, no gap), mattes
the subject's capture with each and measures both with ``matte_eval`` against the studio's exact
alpha. Each runs in a scratch folder of its own, so the subject's workspace is not touched.

Writes ``bench-results/matte_gap_<subject>.json``: per variant the matte_eval figures and the
matte stage's seconds. About 4 minutes a variant on 2 cores (training 600 iterations, matting 960
images).
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench-results"
FIGURES = ("mae_full", "mae_olat", "grad_err_full", "grad_err_olat", "mae_olat_p95", "mae_olat_max",
           "baseline_mae_olat")


def main() -> int:
    from pipeline.scratch import run_stage_in_folder
    from pipeline.workspace import Workspace, workspace_root
    from pipeline.yamlio import read_yaml_mapping
    from stages.matte.conditions import TrainingConditions
    from stages.matte.eval_stage import STAGE as MATTE_EVAL
    from stages.matte.stage import STAGE as MATTE

    subject = os.environ.get("GAP_SUBJECT", "alice")
    ws = Workspace(workspace_root(ROOT), subject)
    capture, truth = ws.output_path("capture"), ws.output_path("capture", "truth")
    preset = read_yaml_mapping(ROOT / "configs" / "presets" / "tiny.yaml", "configs/presets/tiny.yaml")
    matte_params = dict(preset.get("matte") or {})
    variants = {"own_studio": TrainingConditions(), "same_as_capture": TrainingConditions.same_as_capture()}
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="bench-matte-gap-") as tmp:
        for name, conditions in variants.items():
            scratch = Path(tmp) / name
            data = {**dict(matte_params.get("data") or {}), "conditions": conditions.model_dump()}
            start = time.perf_counter()
            matte = run_stage_in_folder(MATTE, scratch, {"capture": capture}, {**matte_params, "data": data},
                                        subject=subject, workers=2)
            seconds = time.perf_counter() - start
            evaluated = run_stage_in_folder(MATTE_EVAL, scratch, {"matte": matte, "capture": capture,
                                                                   "capture.truth": truth}, {}, subject=subject,
                                            workers=2)
            figures = json.loads((evaluated / "metrics.json").read_text())
            results[name] = {"conditions": conditions.model_dump(), "matte_seconds": seconds,
                             **{k: figures.get(k) for k in FIGURES}}
            print(f"{name}: " + ", ".join(f"{k} {results[name][k]:.5f}" for k in FIGURES
                                          if isinstance(results[name][k], (int, float))), flush=True)
    OUT.mkdir(exist_ok=True)
    (OUT / f"matte_gap_{subject}.json").write_text(json.dumps({"subject": subject, "variants": results}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
