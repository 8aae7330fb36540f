"""Head-stabilised cameras: per frame, every camera's extrinsics relative to the head.

The network trains in head space, so the head's motion is folded into the cameras:
``cam_from_head = cam_from_world @ world_from_head`` (the inverse head pose applied to the
cameras). The file format (``cameras_head.json``)::

    {"frames": {"<index>": [Camera.to_dict(), ...]}, "space": "head"}

Each camera dict is ``scene.camera.Camera.to_dict`` of a camera posed in the head frame: its
pose is under ``cam_from_head`` (metres). Files written before poses named their frame hold
it under ``cam_from_world``; they are read as head-frame poses too.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import numpy as np

from scene.camera import Camera, Rigid


def cameras_in_head_space(cameras: Sequence[Camera], world_from_head: Rigid) -> list[Camera]:
    """The world-posed cameras posed in the head frame (``cam_from_head``) for one head pose."""
    return [cam.with_pose(cam.cam_from_world @ world_from_head, "head") for cam in cameras]


def write_cameras_head(path: Path, index: Sequence[int], world_from_head_R: np.ndarray,
                       world_from_head_t: np.ndarray, cameras: Sequence[Camera]) -> None:
    """Write ``cameras_head.json`` for frames ``index`` [T] with head poses R [T, 3, 3], t [T, 3]."""
    frames = {}
    for i, R, t in zip(index, world_from_head_R, world_from_head_t):
        frames[str(int(i))] = [c.to_dict() for c in cameras_in_head_space(cameras, Rigid(np.asarray(R), np.asarray(t)))]
    Path(path).write_text(json.dumps({"space": "head", "frames": frames}))


def read_cameras_head(path: Path) -> dict[int, list[Camera]]:
    """Read ``cameras_head.json``: frame index -> cameras posed in the head frame (``cam_from_head``).

    Raises ``ValueError`` naming the file when it is not such a file.
    """
    try:
        data = json.loads(Path(path).read_text())
        return parse_cameras_head(data)
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
        raise ValueError(f"{path}: not a valid head-space camera file ({err}); re-run the stabilize stage") from err


def parse_cameras_head(data: dict) -> dict[int, list[Camera]]:
    """The cameras of a parsed ``cameras_head.json``.

    Besides the format above, reads the frames as a list (``[{"index", "cameras"}]``), the
    cameras of a frame as a dict, and a camera's pose under ``cam_from_world`` (files written
    before poses named their frame), read as ``cam_from_head``.
    """
    frames = data["frames"]
    if isinstance(frames, dict):
        frames = [{"index": k, "cameras": v} for k, v in frames.items()]
    result: dict[int, list[Camera]] = {}
    for entry in frames:
        cams = entry["cameras"]
        per_frame = [Camera.from_dict(d, "head") for d in (cams.values() if isinstance(cams, dict) else cams)]
        result[int(entry["index"])] = per_frame
    return result
