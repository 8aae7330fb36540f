"""Batched inference: the fused matte, gated by the semantic branch's coarse foreground.

The gate: the semantic prediction (1/16 resolution) is max-pooled over 3x3 cells (a margin
of 16-32 px, so hair and ears near the head are never cut), mapped through a ramp from
``gate_low`` to ``gate_high`` and upsampled. Where the semantic branch sees no person
anywhere near, the matte is 0. The fusion branch works on 2-pixel detail, and on a frame of
pure sensor noise its instance-normalised half can stretch the noise into false contrast;
the semantic branch averages over 16x16 cells and is not fooled (it stays below ~0.2 on an
empty studio, near 1 on a head). ``gate_low = 0`` disables the gate.

``matte_item`` mattes one image from its file paths (a ``MatteItem``): the stage fans those
out through the executor and caches each result by ``matte_item_key`` (the adapted model's
weights digest, the image's and its guide's bytes, the settings), so frames added to a
capture are the only ones matted again when the model is unchanged.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from stages.matte.baseline import BaselineConfig, baseline_matte
from stages.matte.inputs import pad_to_multiple
from stages.matte.modnet import MODNet


def semantic_gate(semantic: torch.Tensor, size: tuple[int, int], gate_low: float, gate_high: float) -> torch.Tensor:
    """Gate [B, 1, H, W] in [0, 1] from the semantic prediction [B, 1, H/16, W/16]."""
    dilated = F.max_pool2d(semantic, 3, stride=1, padding=1)
    ramp = ((dilated - gate_low) / max(gate_high - gate_low, 1e-6)).clamp(0.0, 1.0)
    return F.interpolate(ramp, size=size, mode="bilinear", align_corners=False)


@torch.no_grad()
def predict(model: MODNet, inputs: np.ndarray | torch.Tensor, batch_size: int = 8, device: str = "cpu",
            gate_low: float = 0.3, gate_high: float = 0.6) -> np.ndarray:
    """Alpha mattes [N, H, W] float32 of network inputs [N, 6, H, W] (any H, W; padded internally)."""
    model = model.to(device).eval()
    tensor = torch.as_tensor(inputs)
    height, width = tensor.shape[-2:]
    out = []
    for start in range(0, len(tensor), batch_size):
        batch = pad_to_multiple(tensor[start:start + batch_size].to(device), 32)
        semantic, _, matte = model(batch)
        if gate_low > 0:
            matte = matte * semantic_gate(semantic, matte.shape[-2:], gate_low, gate_high)
        out.append(matte[:, 0, :height, :width].float().cpu().numpy())
    return np.concatenate(out) if out else np.zeros((0, height, width), np.float32)


# --- Per-image inference items (fanned out through the executor, cached per image) -------------

@dataclass(frozen=True)
class MatteItem:
    """One image to matte, as paths and numbers (cheap to ship to a worker; picklable).

    The adapted model travels as the folder it is saved in (``stages.matte.model_cache``
    layout) and its weights' digest; a worker loads it once and keeps it.
    """

    image_path: str  # the frame's EXR
    guide_path: str  # the nearest full-on frame's EXR (the frame itself for an F frame)
    olat: bool  # scaled by its own bright level (floored) instead of the camera's F reference
    reference: float  # the camera's F exposure reference (``inputs.camera_reference``)
    olat_floor_ratio: float
    model_dir: str  # "" = the classical baseline matte
    model_digest: str
    gate_low: float
    gate_high: float
    device: str
    threads: int  # torch CPU threads in the worker (0 = torch's default)
    baseline: BaselineConfig | None = None


_MODELS: dict[str, MODNet] = {}


def matte_item_key(item: MatteItem) -> str:
    """Content digest of what an image's matte depends on: model weights, both images' bytes, settings."""
    from pipeline.itemcache import content_key

    settings = {k: v for k, v in asdict(item).items() if k not in ("image_path", "guide_path", "model_dir")}
    if item.baseline is not None:
        settings["baseline"] = item.baseline.model_dump(mode="json")
    return content_key(Path(item.image_path), Path(item.guide_path), settings)


def _model(item: MatteItem) -> MODNet:
    if item.model_digest not in _MODELS:
        from stages.matte.model_cache import load_model

        _MODELS.clear()  # one model per worker at a time
        _MODELS[item.model_digest] = load_model(Path(item.model_dir))[0]
    return _MODELS[item.model_digest]


def matte_item(item: MatteItem) -> dict:
    """The 16-bit matte of one image: ``{"alpha_u16": [H, W] uint16 (what the PNG holds), "seconds"}``."""
    from scene.image_io import read_exr
    from stages.matte.inputs import network_input, olat_scale

    start = time.perf_counter()
    if item.threads:
        torch.set_num_threads(item.threads)
    image = read_exr(item.image_path)[..., :3].astype(np.float32)
    if item.model_dir:
        guide = image if item.guide_path == item.image_path else \
            read_exr(item.guide_path)[..., :3].astype(np.float32)
        scale = olat_scale(image, item.reference, item.olat_floor_ratio) if item.olat else item.reference
        alpha = predict(_model(item), network_input(image, scale, guide, item.reference)[None], 1, item.device,
                        item.gate_low, item.gate_high)[0]
    else:
        alpha = baseline_matte(image, item.baseline or BaselineConfig())
    # Quantised as scene.image_io.write_png16 does, so the cached value is exactly what is written.
    alpha_u16 = np.round(np.clip(np.asarray(alpha, np.float64), 0.0, 1.0) * 65535.0).astype(np.uint16)
    return {"alpha_u16": alpha_u16, "seconds": time.perf_counter() - start}
