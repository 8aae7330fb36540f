"""Save and load trained heads: ``model.safetensors`` (weights + layout buffers) and ``model.json``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from avatar.config import AvatarConfig
from avatar.layout import GuideLayout
from avatar.model import RelightableMVP

_LAYOUT_KEYS = ("guide_vertex_ids", "anchor_tris", "anchor_bary", "normal_sign", "half_extent_m", "mean_guide_vertices")
#: Layout arrays only some heads have (heads saved before them load without).
_OPTIONAL_LAYOUT_KEYS = ("expression_basis",)


def save_trained(folder: Path, model: RelightableMVP, kind: str, extra: dict[str, Any] | None = None) -> None:
    """Write ``folder/model.safetensors`` and ``folder/model.json`` (kind, config, bars, ``extra``)."""
    from safetensors.torch import save_file

    folder.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    save_file(state, str(folder / "model.safetensors"))
    meta = {"kind": kind, "config": model.config.model_dump(mode="json"),
            "num_bars": int(model.log_bar_intensity.numel()), **(extra or {})}
    (folder / "model.json").write_text(json.dumps(meta, indent=1))


def load_trained(folder: Path, device: str | torch.device = "cpu") -> tuple[RelightableMVP, dict[str, Any]]:
    """Rebuild a head saved by ``save_trained``; returns the model (eval mode) and its ``model.json``."""
    from safetensors.torch import load_file

    meta = json.loads((Path(folder) / "model.json").read_text())
    state = load_file(str(Path(folder) / "model.safetensors"))
    layout = GuideLayout(**{k: state[k].numpy() for k in _LAYOUT_KEYS + _OPTIONAL_LAYOUT_KEYS if k in state})
    model = RelightableMVP(AvatarConfig(**meta["config"]), layout, int(meta["num_bars"]))
    model.load_state_dict(state)
    return model.to(device).eval(), meta
