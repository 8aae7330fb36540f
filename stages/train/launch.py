"""Launch the train stage as a data-parallel job: ``torchrun`` over ``stages.train.ddp_worker``.

The stage's process writes a job file (params, input folders, output and cache folders) into
the stage's cache folder, runs ``python -m torch.distributed.run --standalone
--nproc_per_node N -m stages.train.ddp_worker <job>`` with this interpreter, forwards the
workers' log lines to the stage's log, and reads back the metrics rank 0 wrote. Rank 0 writes
the outputs straight into ``ctx.out`` and the checkpoints into ``ctx.cache_dir``, exactly where
the single-process path writes them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import uuid
from pathlib import Path
from typing import Protocol

from pipeline.errors import ConfigError, PipelineError
from pipeline.stage import StageContext

PROJECT_ROOT = Path(__file__).resolve().parents[2]


class DdpSettings(Protocol):
    """The train params the launcher reads (``stages.train.params.TrainParams`` has them; the
    launcher does not import it, so the stage and its launcher do not import each other)."""

    device: str
    processes: int
    threads: int

    def model_dump(self, *, mode: str) -> dict: ...


def torchrun_command(processes: int, job: Path) -> list[str]:
    """The launcher command line for ``processes`` ranks on this node."""
    return [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={processes}",
            "-m", "stages.train.ddp_worker", str(job)]


def _check_backend(device: str, processes: int) -> None:
    import torch
    import torch.distributed as dist

    if not dist.is_available():
        raise ConfigError("train.processes > 1 needs torch.distributed, which this torch build lacks; "
                          "set train.processes: 1")
    cuda = device == "cuda" or (device == "auto" and torch.cuda.is_available())
    if cuda and torch.cuda.device_count() < processes:
        raise ConfigError(f"train.processes={processes} but only {torch.cuda.device_count()} CUDA device(s); "
                          "use one process per GPU (or train.device: cpu)")
    if not cuda and not dist.is_gloo_available():
        raise ConfigError("train.processes > 1 on CPU needs the gloo backend, which this torch build lacks")


def _stop(proc: subprocess.Popen) -> None:
    """Terminate the launcher (torchrun passes SIGTERM on to its ranks), then kill it if it lingers."""
    proc.terminate()
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def launch_ddp(ctx: StageContext) -> None:
    """Run the stage on ``ctx.params.processes`` ranks and fill ``ctx.metrics`` from rank 0."""
    params: DdpSettings = ctx.params  # type: ignore[assignment]
    _check_backend(params.device, params.processes)
    jobs = ctx.cache_dir / "ddp_jobs"
    jobs.mkdir(parents=True, exist_ok=True)
    job = jobs / f"{uuid.uuid4().hex}.json"
    metrics_path = job.with_suffix(".metrics.json")
    job.write_text(json.dumps({
        "stage": ctx.stage, "subject": ctx.subject, "params": params.model_dump(mode="json"),
        "inputs": {k: str(Path(v).resolve()) for k, v in ctx.inputs.items()},
        "out": str(Path(ctx.out).resolve()), "cache_dir": str(Path(ctx.cache_dir).resolve()),
        "shared_cache_dir": str(Path(ctx.shared_cache_dir).resolve()), "metrics": str(metrics_path)}))
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(PROJECT_ROOT)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    # torchrun sets OMP_NUM_THREADS=1 itself when unset; keep an explicit thread count.
    if params.threads:
        env["OMP_NUM_THREADS"] = str(params.threads)
    cmd = torchrun_command(params.processes, job)
    ctx.log.info("DDP training on %d processes: %s", params.processes, " ".join(cmd))
    try:
        proc = subprocess.Popen(cmd, cwd=PROJECT_ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True, bufsize=1)
        tail: list[str] = []
        try:
            for line in proc.stdout or ():
                line = line.rstrip()
                ctx.log.info("%s", line)
                tail = (tail + [line])[-20:]
            code = proc.wait()
        except BaseException:
            _stop(proc)  # an interrupted stage must not leave its ranks training
            raise
        if code != 0:
            raise PipelineError(f"train: the DDP job ({' '.join(cmd)}) exited with status {code}; its last lines:\n"
                                + "\n".join(tail) + "\nrerun the stage to resume from its last checkpoint")
        if not metrics_path.is_file():
            raise PipelineError(f"train: DDP rank 0 wrote no metrics ({metrics_path}); see the log above")
        ctx.metrics.update(json.loads(metrics_path.read_text()))
    finally:
        for path in (job, metrics_path):
            path.unlink(missing_ok=True)
