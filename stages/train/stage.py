"""Train stage: the relightable MVP head (ours) and the TRAvatar* baseline, then held-out metrics.

Inputs: ``capture`` (OLAT images, manifest), ``stabilize`` (per-frame cam_from_head),
``track`` (head-space meshes, world_from_head poses), ``matte`` (alpha mattes) and
``lightcal`` (bar centres). Never ``capture.truth``.

Output:
    models/ours/, models/travatar/   ``model.safetensors`` + ``model.json`` (``avatar.io.load_trained``)
    splits.json                      test and validation bars / segments, the frames of every split
    learning_curve.png, curve.json   validation-light PSNR against training time
    tradeoffs/learning_curve.json    the same as a report trade-off series, the chosen configuration marked
    capacity.json                    the capacity rule's inputs (image size, head footprint, frames, expression modes) and choice
    table.md                         the paper's table (rows: splits; PSNR, MAE, SSIM, LPIPS per model)
    previews/<split>_<k>.png         ground truth | ours | TRAvatar*, sRGB
    tensorboard/                     loss terms and validation-light PSNR
    metrics.json                     the required train keys are listed in docs/design.md (metrics)

The two models train one after another, or side by side in two threads of this process
(``parallel_models: 2``, ``stages.train.side_by_side``), to the same weights either way.

The learning curves and TensorBoard files hold wall-clock times: they are the stage's run
records (``Stage.run_records``), left out of the key relight and evaluate see, so a rerun
that trains the same models leaves them fresh.
"""

from __future__ import annotations

import hashlib
import logging
import resource
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

import torch

from avatar.raymarch import RaymarchKernel, resolve_kernel
from avatar.raymarch_fused import FusedKernelUnavailable
from pipeline.codedigest import modules_code_version
from pipeline.devices import resolve_device
from pipeline.errors import ConfigError
from pipeline.stage import Progress, Stage, StageContext
from stages.train.assess import assess_heads, run_metrics
from stages.train.data import load_train_data
from stages.train.fit import fit_heads
from stages.train.output import RUN_RECORDS, TrainOutput
from stages.train.params import TrainParams
from stages.train.setup import prepare_training
from stages.train.write import write_train_outputs

#: The upstream outputs training reads (never ``capture.truth``).
TRAIN_INPUTS = ("capture", "stabilize", "track", "matte", "lightcal")


@dataclass(frozen=True)
class TrainFolders:
    """Where one run reads and writes.

    Attributes:
        inputs: the upstream output folders by stage name (``TRAIN_INPUTS``).
        out: the stage's output folder (rank 0 writes it).
        cache_dir: the stage's persistent scratch folder: checkpoints (``<run key>/<kind>.pt``)
            and each rank's memory-mapped images (``spill-rank<r>``).
    """

    inputs: Mapping[str, Path]
    out: Path
    cache_dir: Path

    def spill_dir(self, rank: int) -> Path:
        return self.cache_dir / f"spill-rank{rank}"


def _raymarch_kernel(name: RaymarchKernel, device: torch.device) -> RaymarchKernel:
    """The raymarcher this run uses, built now (not in the first iteration, whose time it would skew)."""
    try:
        return resolve_kernel(name, device, torch.float32)
    except (ValueError, FusedKernelUnavailable) as error:
        raise ConfigError(f"train.raymarch_kernel={name}: {error}") from error


def _run_key(params: TrainParams, inputs: dict[str, Path]) -> str:
    """Checkpoint folder key: params, input objects and the training code (so stale checkpoints are never resumed)."""
    # The process count is left out: every rank draws the same global batch, so a checkpoint
    # resumes with any number of processes.
    # Nor does training side by side change a model's iterations.
    # How the work is spread, and which raymarcher does it, change no more than float rounding.
    h = hashlib.sha256(params.model_dump_json(exclude={"processes", "parallel_models", "raymarch_kernel"}).encode())
    for name in sorted(inputs):
        h.update(f"{name}={Path(inputs[name]).resolve()}".encode())
    # The training code: this package and everything it imports (the same closure as the stage's digest).
    h.update(modules_code_version(("stages.train",)).digest.encode())
    return h.hexdigest()[:20]


def _peak_memory_mb(device: torch.device) -> float:
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2 ** 20
    rss_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss_kb / 1024.0 if sys.platform != "darwin" else rss_kb / 2 ** 20


def run(ctx: StageContext) -> None:
    params: TrainParams = ctx.params  # type: ignore[assignment]
    if params.batch_size % params.processes:
        raise ConfigError(f"train.batch_size={params.batch_size} does not divide by train.processes="
                          f"{params.processes}; every process takes an equal share of the global batch")
    if params.processes > 1 and params.parallel_models > 1:
        raise ConfigError(f"train.parallel_models={params.parallel_models} with train.processes={params.processes}: "
                          "a DDP run trains its models one after another; set train.parallel_models: 1")
    if params.processes > 1:
        from stages.train.launch import launch_ddp

        launch_ddp(ctx)
        return
    train(ctx)


def train(ctx: StageContext) -> None:
    """The stage in this process: ``train_in_folders`` over the context's folders."""
    folders = TrainFolders(inputs={k: ctx.input(k) for k in TRAIN_INPUTS}, out=ctx.out, cache_dir=ctx.cache_dir)
    ctx.metrics.update(train_in_folders(folders, ctx.params, ctx.log, ctx.progress))  # type: ignore[arg-type]


def train_in_folders(folders: TrainFolders, params: TrainParams, log: logging.Logger,
                     progress: Callable[[int, str], Progress], rank: int = 0, world_size: int = 1,
                     device: torch.device | None = None) -> dict[str, float]:
    """Load the data, train, measure and (rank 0) write the outputs; returns the stage's metrics.

    With ``world_size > 1`` this is one rank of a DDP run (``stages.train.ddp_worker``): every
    rank trains, only rank 0 evaluates and writes, and the other ranks return only their
    models' training figures.
    """
    if params.threads:
        torch.set_num_threads(params.threads)
    device = device or torch.device(resolve_device(params.device, "train.device"))
    kernel = _raymarch_kernel(params.raymarch_kernel, device)
    lead = rank == 0
    if lead:
        log.info("raymarcher: %s (train.raymarch_kernel=%s)", kernel, params.raymarch_kernel)
    inputs = dict(folders.inputs)
    data = load_train_data(inputs, params.image_width_px, log, params.max_frames,
                           resident_limit_gb=params.resident_limit_gb, spill_dir=folders.spill_dir(rank))
    setup = prepare_training(data, params, device, log)
    lpips = _lpips(device) if params.lpips and lead else None
    checkpoints = folders.cache_dir / _run_key(params, inputs)
    checkpoints.mkdir(parents=True, exist_ok=True)
    writer = _tensorboard_writer(TrainOutput(folders.out), log) if lead else None
    heads = fit_heads(setup, data.num_bars, params, device, kernel, checkpoints, log, progress, writer=writer,
                      rank=rank, world_size=world_size)
    metrics = heads.metrics()
    if lead:
        results = assess_heads(heads, setup, params, lpips, log)
        metrics.update(results.metrics)
        metrics.update(run_metrics(heads, setup, data, params))
        metrics["peak_memory_mb"] = _peak_memory_mb(device)
        if writer is not None:
            writer.close()
        write_train_outputs(TrainOutput(folders.out), data, setup, heads, results, metrics, params, log,
                            inputs=inputs)
    if data.spilled:
        # Unlinking a mapped file is safe on POSIX; the pages go when the last mapping does.
        shutil.rmtree(folders.spill_dir(rank), ignore_errors=True)
    return metrics


def _lpips(device: torch.device) -> torch.nn.Module:
    from avatar.lpips import LPIPS

    return LPIPS().to(device)


def _tensorboard_writer(out: TrainOutput, log: logging.Logger) -> Any:
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        log.warning("tensorboard is not installed; no TensorBoard logs")
        return None
    return SummaryWriter(str(out.tensorboard_dir))


STAGE = Stage(name="train", inputs=TRAIN_INPUTS, params=TrainParams,
              run=run, doc=__doc__ or "",
              # Wall-clock records: two runs of the same deterministic training differ only here (and in
              # metrics.json), so relight and evaluate, which read the models, need not rerun.
              run_records=RUN_RECORDS)
