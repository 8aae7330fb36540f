"""From linear HDR images to the matting network's input.

Exposure: full-on (F) frames of one camera share a reference scale, the median over those
frames of their 99th luminance percentile (so an empty frame is scaled like its neighbours,
and its backdrop noise stays dark instead of being stretched to white). An OLAT frame is
scaled by its own 99th percentile, floored at a fraction of the camera's F reference (one
bar alone is much dimmer than all of them). The scaled image is sRGB-encoded (its linear toe
lifts the dark, unlit side without amplifying noise like a pure power law) and mapped to
[-1, 1].

Guide: the network sees 6 channels, the image and the nearest full-on frame of the same
camera (an F frame is its own guide). On an OLAT frame the unlit side of the head is black,
but the F frame 1/24 s away shows the whole silhouette, moved by a pixel or two at most;
the network learns to take the silhouette from the guide and the exact edge from the image
where it is lit.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from scene.colour import luminance, srgb_encode


def bright_level(image: np.ndarray, percentile: float = 99.0) -> float:
    """The ``percentile`` of the image's luminance (a robust 'white' of the exposure)."""
    return float(np.percentile(luminance(image), percentile))


def normalise(image: np.ndarray, scale: float) -> np.ndarray:
    """Linear RGB [H, W, 3] divided by ``scale``, sRGB-encoded, mapped to [-1, 1]; float32 [H, W, 3]."""
    return srgb_encode(image[..., :3] / max(scale, 1e-12)) * 2.0 - 1.0


def camera_reference(full_on_levels: Sequence[float], floor: float) -> float:
    """A camera's F exposure reference: the median bright level of its F frames, at least ``floor``."""
    if len(full_on_levels) == 0:
        return floor
    return max(float(np.median(full_on_levels)), floor)


def olat_scale(image: np.ndarray, reference: float, olat_floor_ratio: float) -> float:
    """The scale of an OLAT image: its own bright level, at least ``olat_floor_ratio`` x the F reference."""
    return max(bright_level(image), reference * olat_floor_ratio)


def network_input(image: np.ndarray, image_scale: float, guide: np.ndarray, guide_scale: float) -> np.ndarray:
    """The 6-channel input [6, H, W]: normalised image, then normalised guide F frame."""
    stacked = np.concatenate((normalise(image, image_scale), normalise(guide, guide_scale)), axis=-1)
    return np.ascontiguousarray(stacked.transpose(2, 0, 1))


def pad_to_multiple(batch: torch.Tensor, multiple: int = 32) -> torch.Tensor:
    """Pad [B, C, H, W] on the bottom and right (replicating the border) to multiples of ``multiple``."""
    height, width = batch.shape[-2:]
    pad_h, pad_w = (-height) % multiple, (-width) % multiple
    if pad_h == 0 and pad_w == 0:
        return batch
    return F.pad(batch, (0, pad_w, 0, pad_h), mode="replicate")


def is_full_on(frame: Mapping[str, Any]) -> bool:
    """Whether a manifest frame entry was lit by all bars."""
    return frame.get("light") == "F"


def nearest_full_on(frames: Sequence[Mapping[str, Any]]) -> dict[int, int]:
    """For every frame index, the index of the nearest usable F frame (itself for an F frame).

    Nearest by capture time, ties to the earlier frame; dropped frames are never guides.
    Frames with no usable F frame in the capture map to themselves.
    """
    full_on = sorted((float(f.get("time_s", f["index"])), int(f["index"])) for f in frames
                     if is_full_on(f) and f.get("status", "ok") != "dropped")
    times = np.array([t for t, _ in full_on])
    guides: dict[int, int] = {}
    for frame in frames:
        index = int(frame["index"])
        if is_full_on(frame) or len(full_on) == 0:
            guides[index] = index
            continue
        distance = np.abs(times - float(frame.get("time_s", index)))
        guides[index] = full_on[int(np.argmin(distance))][1]
    return guides
