"""One rank of a data-parallel train run; started by ``torchrun`` (see ``stages.train.launch``).

Usage (what the launcher runs)::

    python -m torch.distributed.run --standalone --nproc_per_node N -m stages.train.ddp_worker JOB.json

Reads the job file, joins the process group (nccl with one GPU per rank, gloo on CPU), and
runs ``stages.train.stage.train_in_folders`` as rank ``RANK`` of ``WORLD_SIZE``. Rank 0 writes the
outputs, checkpoints and the metrics file named in the job.
"""

from __future__ import annotations

import gc
import json
import logging
import os
import sys
from datetime import timedelta
from pathlib import Path

import torch
import torch.distributed as dist

from pipeline.devices import resolve_device
from pipeline.progress import SilentProgress, progress_factory
from stages.train.stage import TRAIN_INPUTS, TrainFolders, TrainParams, train_in_folders


def main(argv: list[str] | None = None) -> int:
    """Run one rank of the job named by ``argv[0]``; returns the exit status."""
    args = sys.argv[1:] if argv is None else argv
    job = json.loads(Path(args[0]).read_text())
    rank, world = int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])
    local_rank = int(os.environ.get("LOCAL_RANK", rank))
    params = TrainParams(**job["params"])
    device = torch.device(resolve_device(params.device, "train.device"))
    if device.type == "cuda":
        device = torch.device("cuda", local_rank)
        torch.cuda.set_device(device)
    logging.basicConfig(level=logging.INFO if rank == 0 else logging.WARNING, stream=sys.stderr,
                        format=f"[rank {rank}/{world}] %(levelname)s %(message)s")
    log = logging.getLogger(f"stage.{job['stage']}")
    dist.init_process_group("nccl" if device.type == "cuda" else "gloo", timeout=timedelta(minutes=30))
    try:
        factory = progress_factory(job["stage"], log, tty=False) if rank == 0 else (lambda total, unit: SilentProgress())
        folders = TrainFolders(inputs={k: Path(job["inputs"][k]) for k in TRAIN_INPUTS}, out=Path(job["out"]),
                               cache_dir=Path(job["cache_dir"]))
        metrics = train_in_folders(folders, params, log, factory, rank=rank, world_size=world, device=device)
        if rank == 0:
            Path(job["metrics"]).write_text(json.dumps(metrics))
        # Release every DDP wrapper (and its reference to the process group) before the group is
        # torn down, and let no rank tear it down while another still talks to it.
        gc.collect()
        dist.barrier()
    finally:
        dist.destroy_process_group()
    return 0


if __name__ == "__main__":
    sys.exit(main())
