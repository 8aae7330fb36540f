"""One rank of a small DDP run with a poisoned loss on rank 1, for the rollback test (top level for ``spawn``)."""

from __future__ import annotations

import gc
import json
import logging
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist

from pipeline.progress import SilentProgress
from train_synth import small_model


def _params_digest(model: torch.nn.Module) -> str:
    import hashlib

    hasher = hashlib.sha256()
    for name, tensor in sorted(model.state_dict().items()):
        hasher.update(name.encode())
        hasher.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return hasher.hexdigest()


def rollback_rank(rank: int, world_size: int, init_file: str, capture: dict[str, Path], workdir: Path,
                  iterations: int, nan_at: int, spike_at: int, grad_clip_factor: float = 0.0) -> None:
    """Train ``iterations`` steps (checkpoint every 2) with rank 1's loss made NaN at ``nan_at`` and
    1000x at ``spike_at`` (-1: never); writes, per iteration, the model digest, rollbacks, lr and
    clipped steps (``grad_clip_factor``) to ``rank<r>.json``."""
    from stages.train import trainer as trainer_mod
    from stages.train.data import load_train_data

    real_losses = trainer_mod.ModelTrainer.losses

    def poisoned(self, frames, cams, pix, eps):
        total, terms = real_losses(self, frames, cams, pix, eps)
        if self.rank == 1 and self.state.iteration == nan_at:  # one rank alone sees the NaN
            return total * float("nan"), {**terms, "loss": float("nan")}
        if self.rank == 1 and self.state.iteration == spike_at:
            return total * 1000.0, {**terms, "loss": terms["loss"] * 1000.0}
        return total, terms

    # Patched before the trainer exists: DistributedDataParallel wraps the bound method.
    trainer_mod.ModelTrainer.losses = poisoned
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world_size)
    try:
        log = logging.getLogger(f"rollback.rank{rank}")
        data = load_train_data(capture, 24, log)
        _, tensors, model, renderer = small_model(data)
        record: list[dict] = []
        trainer = None

        def after_iteration() -> float:  # the trainer's curve hook, called after every iteration
            record.append({"digest": _params_digest(model), "rollbacks": trainer.state.rollbacks,
                           "lr": trainer.state.lr, "clipped_steps": trainer.state.clipped_steps})
            return 0.0

        trainer = trainer_mod.ModelTrainer(
            renderer, tensors, np.arange(len(data.bar)), iterations=iterations, batch_size=4, rays_per_image=32,
            lr=3e-3, weights=trainer_mod.LossWeights(), seed=0, ckpt_path=workdir / f"ckpt{rank}.pt",
            checkpoint_every=2, spike_factor=10.0, log=log, rank=rank, world_size=world_size, curve_every=1,
            curve_fn=after_iteration, grad_clip_factor=grad_clip_factor)

        trainer.run(SilentProgress())
        (workdir / f"rank{rank}.json").write_text(json.dumps(record[1:]))  # record[0]: before training
        trainer = None  # its curve hook closes over it: a cycle only a collection frees
        gc.collect()
        dist.barrier()
    finally:
        dist.destroy_process_group()
