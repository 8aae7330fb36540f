"""The trained matting model as a cached object shared by all subjects of a workspace root.

Key: BLAKE3 of the canonical JSON of everything that determines the trained weights (the
training config, the training-data spec) and of the source of the modules that produce
them (network, losses, augmentation, input normalisation, data generation, the studio).
Ten subjects matted with the same config reuse one training run.

Layout: ``<shared_cache_dir>/matte_models/<key>/{model.safetensors, meta.json}``. Written
into a temporary sibling folder and renamed into place, so a crash never leaves half an
entry; an entry that fails to load is treated as a miss (with a warning) and rebuilt.
Weights are read with safetensors (no pickle).
"""

from __future__ import annotations

import json
import logging
import shutil
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterable

import blake3
import torch
from safetensors.torch import load_file, save_file

from pipeline.codedigest import modules_code_version
from pipeline.errors import PipelineError
from stages.matte.modnet import MODNet, MattingNetConfig

MODEL_FILE = "model.safetensors"
META_FILE = "meta.json"


def training_code_digest(modules: Iterable[str]) -> str:
    """The digest of the code that determines trained weights: the import closure of the
    modules that render the training data and train (network, losses, augmentation, the virtual
    studio, the rig file), as a stage's code digest; a comment-only edit does not retrain."""
    version = modules_code_version(tuple(modules))
    if version is None:
        raise PipelineError(f"matting training modules {list(modules)} cannot be found")
    return version.digest


def cache_key(payload: dict[str, Any], code_digest: str) -> str:
    """The cache key of a training run: its canonical JSON payload and its code digest."""
    canonical = json.dumps(payload, sort_keys=True, separators=(",", ":"), default=str)
    return blake3.blake3(f"{canonical}\n{code_digest}".encode()).hexdigest()[:32]


def save_model(folder: Path, model: MODNet, meta: dict[str, Any]) -> None:
    """Write weights (safetensors) and metadata (JSON, with the network config) into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    state = {name: tensor.detach().cpu().contiguous() for name, tensor in model.state_dict().items()}
    save_file(state, str(folder / MODEL_FILE))
    meta = {**meta, "net_config": model.config.model_dump(mode="json")}
    (folder / META_FILE).write_text(json.dumps(meta, indent=1, sort_keys=True, default=str))


def load_model(folder: Path) -> tuple[MODNet, dict[str, Any]]:
    """The network and metadata saved by ``save_model``."""
    meta = json.loads((folder / META_FILE).read_text())
    model = MODNet(MattingNetConfig(**meta["net_config"]))
    model.load_state_dict(load_file(str(folder / MODEL_FILE)), strict=True)
    return model.eval(), meta


def load_or_train(cache_root: Path, key: str, train: Callable[[], tuple[MODNet, dict[str, Any]]],
                  log: logging.Logger) -> tuple[MODNet, dict[str, Any], bool]:
    """The cached model under ``key``, or a newly trained one stored there; returns (model, meta, was_cached)."""
    folder = Path(cache_root) / "matte_models" / key
    if folder.is_dir():
        try:
            model, meta = load_model(folder)
            log.info("matting model %s loaded from the shared cache %s", key, folder)
            return model, meta, True
        except Exception as err:  # a corrupt entry is a miss: retrain and replace it
            log.warning("matting model cache entry %s is unreadable (%s: %s); retraining", folder,
                        type(err).__name__, err)
            shutil.rmtree(folder, ignore_errors=True)
    model, meta = train()
    folder.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{key}.", dir=folder.parent))
    save_model(staging, model, {**meta, "key": key})
    try:
        staging.rename(folder)
    except OSError:  # another run stored the same key meanwhile: keep theirs
        shutil.rmtree(staging, ignore_errors=True)
    model, meta = load_model(folder)
    return model, meta, False


def state_equal(a: MODNet, b: MODNet) -> bool:
    """Whether two networks hold identical parameters and buffers."""
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
