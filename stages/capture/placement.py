"""Labelling the frames a capture received and placing them under ``frames/<cam>/<index>.exr``.

Shared by the virtual studio (``stages.capture.stage``) and the importer of real captures
(``stages.capture.importer``): both hand over images in arrival order and the controller's
log; this module labels each image with its trigger from the log and writes the manifest's
frame list.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Callable

from pipeline.errors import InputError
from pipeline.stage import StageContext
from stages.capture.labelling import label_frames
from stages.capture.output import CaptureOutput


def label_and_place(ctx: StageContext, fps: float, cam_names: list[str], n_bars: int, takes: tuple[str, ...],
                     take_of_trigger: list[str], log_json: list[dict], brightness: list[list[float]],
                     n_triggers: int, received: Callable[[str, int], Path] | None = None,
                     place: Callable[[Path, Path], None] = os.replace,
                     frame_times: list[list[float]] | None = None) -> tuple[dict, dict]:
    """Label received frames from the controller log, move them to ``frames/<cam>/<index>.exr``.

    Images arrive in ``received(cam, k)`` (default ``_received/<cam>/<k>.exr``, arrival order)
    and are moved (``place``: a rename; the importer hard-links). Each log entry carries its
    trigger's time stamp, which gives the frame index; a trigger the controller did not act
    on has no log entry and is listed as dropped (``reason: "no light"``).
    """
    log_lights = [e["light"] for e in log_json]
    trigger_of_entry = [int(round(e["time_us"] * 1e-6 * fps)) for e in log_json]
    try:
        result = label_frames(log_lights, brightness, camera_names=cam_names, frame_times_s=frame_times,
                              log_times_s=[e["time_us"] * 1e-6 for e in log_json] if frame_times else None)
    except ValueError as err:
        raise InputError(f"capture: frames cannot be matched to the controller log ({err})") from err
    for line in result.warnings:
        ctx.log.warning(line)
    out = CaptureOutput(ctx.out)
    received = received or out.received_path
    for c, cam in enumerate(cam_names):
        out.frames_dir(cam).mkdir(parents=True, exist_ok=True)
        labels = result.cameras[c]
        for r, (k, status) in enumerate(zip(labels.pulse, labels.status)):
            if status == "ok":
                place(received(cam, r), out.frame_path(cam, trigger_of_entry[k]))
    shutil.rmtree(out.received_dir, ignore_errors=True)

    by_trigger = {t: k for k, t in enumerate(trigger_of_entry)}
    frames = []
    n_total = max(n_triggers, max(trigger_of_entry, default=-1) + 1)
    for index in range(n_total):
        take = take_of_trigger[index] if index < len(take_of_trigger) else takes[-1]
        entry = {"index": index, "take": take, "time_s": round(index / fps, 9)}
        k = by_trigger.get(index)
        if k is None:
            entry.update(light=None, status="dropped", reason="no light")
        else:
            missing = [cam_names[c] for c in range(len(cam_names)) if result.pulse_frame[c, k] < 0]
            entry.update(light=log_lights[k], status="ok" if not missing else "dropped")
            if missing:
                entry.update(reason="no image", missing_cameras=missing)
        frames.append(entry)
    manifest = {"subject": ctx.subject, "fps": fps, "width": None, "height": None, "cameras": cam_names,
                "bars": n_bars, "takes": list(takes), "frames": frames}
    metrics = {"repeated_frames": result.count("repeated"), "unexpected_frames": result.count("unexpected"),
               "shifted_frames": result.shifted_frames(), "labelling_warnings": len(result.warnings)}
    return manifest, metrics
