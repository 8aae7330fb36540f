"""Train-stage runs for the training benchmarks: the tiny preset's settings, the inputs, one run per process.

``bench_capacity``, ``bench_headroom`` and ``bench_seeds`` train the head many times with different settings;
each run goes to its own child process (``python -m benchmarks.train_runs SPEC.json``), so
peak memory (RSS on a CPU) is that run's own and one run's threads or caches never slow the
next.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Stages whose outputs the train stage reads.
INPUT_STAGES = ("capture", "stabilize", "track", "matte", "lightcal")


def tiny_train_params() -> dict:
    """The tiny preset's train section (the settings every benchmark run starts from)."""
    from pipeline.yamlio import read_yaml_mapping

    preset = read_yaml_mapping(ROOT / "configs" / "presets" / "tiny.yaml", "configs/presets/tiny.yaml")
    return dict(preset.get("train") or {})


def train_inputs(subject: str, scratch: Path) -> tuple[dict[str, str], str]:
    """Train-stage input folders and where they came from.

    The subject's workspace when it has them (run ``make subject S=<subject>`` first), else a
    small synthetic capture rendered like the train tests' (``tests/stages/train/train_synth.py``)
    under ``scratch``.
    """
    from pipeline.errors import PipelineError
    from pipeline.workspace import Workspace, workspace_root

    try:
        ws = Workspace(workspace_root(ROOT), subject)
        return {k: str(ws.output_path(k)) for k in INPUT_STAGES}, f"workspace {subject}"
    except (PipelineError, OSError) as err:
        print(f"no train inputs for subject '{subject}' ({err}); using a synthetic capture", flush=True)
    sys.path.insert(0, str(ROOT / "tests" / "stages" / "train"))
    from train_synth import make_capture

    folders = make_capture(scratch / "synth", width_px=64, cameras=6, frames_per_take=(60, 24))
    return {k: str(v) for k, v in folders.items()}, "synthetic capture (tests/stages/train/train_synth.py)"


def inputs_digest(inputs: dict[str, str]) -> str:
    """A digest of the train inputs' data: every file of each input folder but its run record.

    The run record is the runner's ``metrics.json`` (``pipeline.workspace.is_run_record``), timings
    included; the input stages declare no run records of their own (``Stage.run_records``), so the
    rest is what the planner's content keys read too.

    Two builds of a subject's upstream stages can give different images (another CPU's float
    rounding in the matting network, say) while every figure they print agrees to the digits
    shown, and training on them then draws different runs for the same seed. The benches pair and
    reuse runs only on the same digest.
    """
    import hashlib

    from pipeline.workspace import is_run_record

    digest = hashlib.sha256()
    for name in sorted(inputs):
        folder = Path(inputs[name])
        files = sorted(p for p in folder.rglob("*")
                       if p.is_file() and not is_run_record(p.relative_to(folder).as_posix()))
        for path in files:
            digest.update(f"{name}/{path.relative_to(folder).as_posix()}\0".encode())
            with path.open("rb") as handle:
                for block in iter(lambda: handle.read(1 << 20), b""):
                    digest.update(block)
    return digest.hexdigest()[:16]


def _train_once(spec: dict) -> dict:
    """In the child: run the train stage once; its metrics and capacity.json."""
    import torch

    torch.set_num_threads(1)
    from pipeline.scratch import run_stage_in_folder
    from stages.train.output import TrainOutput
    from stages.train.stage import STAGE

    workdir = Path(spec["workdir"])
    out = run_stage_in_folder(STAGE, workdir, {k: Path(v) for k, v in spec["inputs"].items()}, spec["params"])
    output = TrainOutput(out)
    result = {"metrics": json.loads((out / "metrics.json").read_text()),
              "capacity": output.capacity(),
              "curve": json.loads(output.curve_path.read_text()) if output.curve_path.exists() else {}}
    if spec.get("reference_inputs"):
        from benchmarks.cross_build import score_on_build

        result["reference"] = score_on_build(out, {k: Path(v) for k, v in spec["reference_inputs"].items()},
                                             STAGE.params(**spec["params"]), spill_dir=workdir / "reference_spill")
    return result


def run_train(inputs: dict[str, str], params: dict, scratch: Path, name: str,
              reference_inputs: dict[str, str] | None = None) -> dict:
    """Run the train stage with ``params`` on ``inputs`` in a child process, working in ``scratch/name``.

    Returns ``{"metrics": metrics.json, "capacity": capacity.json, "curve": curve.json}`` of the run; raises
    ``RuntimeError`` with the end of the child's stderr when it fails. With ``reference_inputs`` (another
    build's train inputs, the same frames) it also holds ``"reference"``: the trained models scored on that
    build's images (``benchmarks.cross_build.score_on_build``).
    """
    spec_path = scratch / f"{name}.json"
    result_path = scratch / f"{name}.result.json"
    spec = {"inputs": inputs, "params": params, "workdir": str(scratch / name), "result": str(result_path),
            "reference_inputs": reference_inputs}
    spec_path.write_text(json.dumps(spec))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-m", "benchmarks.train_runs", str(spec_path)],
                          cwd=ROOT, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"train run '{name}' failed:\n{proc.stderr[-3000:]}")
    return json.loads(result_path.read_text())


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python -m benchmarks.train_runs SPEC.json (written by run_train)")
    child_spec = json.loads(Path(sys.argv[1]).read_text())
    Path(child_spec["result"]).write_text(json.dumps(_train_once(child_spec)))
