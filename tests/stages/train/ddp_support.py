"""One rank of a small DDP training run for the DDP tests (a top-level function, so ``spawn`` can start it)."""

from __future__ import annotations

import gc
import json
import logging
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist

from train_synth import small_model


def loss_curve(capture: dict[str, Path], workdir: Path, steps: int, batch_size: int, rank: int = 0,
               world_size: int = 1) -> list[dict[str, float]]:
    """Loss terms of ``steps`` training iterations (the global batch's, on every rank)."""
    from stages.train import trainer as trainer_mod
    from stages.train.data import load_train_data

    torch.set_num_threads(1)
    log = logging.getLogger("test")
    data = load_train_data(capture, 24, log)
    _, tensors, model, renderer = small_model(data)
    tr = trainer_mod.ModelTrainer(renderer, tensors, np.arange(len(data.bar)), iterations=steps,
                                  batch_size=batch_size, rays_per_image=64, lr=3e-3,
                                  weights=trainer_mod.LossWeights(), seed=0, ckpt_path=workdir / f"c{world_size}.pt",
                                  checkpoint_every=100, spike_factor=10.0, log=log, rank=rank,
                                  world_size=world_size)
    if world_size == 1:
        torch.save(_half_batch_gradient(tr), workdir / "grad_halves.pt")
    curve = [tr.step()]
    torch.save(_flat_grad(model), workdir / f"grad_{world_size}_{rank}.pt")  # after DDP's all-reduce
    return curve + [tr.step() for _ in range(steps - 1)]


def _flat_grad(model: torch.nn.Module) -> torch.Tensor:
    return torch.cat([p.grad.flatten() for p in model.parameters() if p.grad is not None])


def _half_batch_gradient(tr) -> torch.Tensor:
    """The mean of the gradients of the first batch's two halves (what two DDP ranks all-reduce), in one process."""
    state = tr.gen.get_state()
    frames, cams, pix = tr.sample_batch()
    eps = torch.randn(tr.batch_size, tr.model.config.latent_dim, generator=tr.gen)
    tr.gen.set_state(state)  # the real first step draws the same batch
    tr.model.zero_grad(set_to_none=True)
    half = tr.batch_size // 2
    for share in (slice(0, half), slice(half, None)):
        total, _ = tr.losses(frames[share], cams[share], pix[share], eps[share])
        (0.5 * total).backward()
    grad = _flat_grad(tr.model)
    tr.model.zero_grad(set_to_none=True)
    return grad


def rank_main(rank: int, world_size: int, init_file: str, capture: dict[str, Path], workdir: Path, steps: int,
              batch_size: int) -> None:
    """Join a gloo group through ``init_file`` and write rank ``rank``'s loss curve to ``workdir``."""
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world_size)
    try:
        curve = loss_curve(capture, workdir, steps, batch_size, rank, world_size)
        (workdir / f"rank{rank}.json").write_text(json.dumps(curve))
        gc.collect()  # no DDP wrapper outlives the group (see ddp_worker.main)
        dist.barrier()
    finally:
        dist.destroy_process_group()
