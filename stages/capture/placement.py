"""Labelling the frames a capture received and placing them under ``frames/<cam>/<index>.exr``.

Shared by the virtual studio (``stages.capture.stage``) and the importer of real captures
(``stages.capture.importer``): both hand over images in arrival order and the controller's
log. ``label_capture`` labels each image with its trigger from the log and builds the
manifest's frame list (pure: data in, labels out); ``place_frames`` moves the images; and
``label_and_place`` does both for a capture's output folder.
"""

from __future__ import annotations

import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from pipeline.errors import InputError
from stages.capture.labelling import LabelResult, label_frames
from stages.capture.output import CaptureOutput


@dataclass(frozen=True)
class LabelledCapture:
    """A capture's received frames labelled from the controller log.

    Attributes:
        labels: per camera and received frame, its log entry and status (``labelling.LabelResult``).
        trigger_of_entry: the trigger (frame index) of every log entry, from its time stamp.
        frames: the manifest's frame list: every trigger with its take, time, light and status.
    """

    labels: LabelResult
    trigger_of_entry: list[int]
    frames: list[dict[str, Any]]

    def metrics(self) -> dict[str, float]:
        return {"repeated_frames": self.labels.count("repeated"), "unexpected_frames": self.labels.count("unexpected"),
                "shifted_frames": self.labels.shifted_frames(), "labelling_warnings": len(self.labels.warnings)}


def label_capture(log_json: list[dict], brightness: list[list[float]], cam_names: list[str], fps: float,
                  n_triggers: int, takes: tuple[str, ...], take_of_trigger: list[str],
                  frame_times: list[list[float]] | None = None) -> LabelledCapture:
    """Label every camera's received frames (``brightness[c]``, arrival order) against the log.

    Each log entry carries its trigger's time stamp, which gives the frame index; a trigger
    the controller did not act on has no log entry and is listed as dropped (``reason: "no
    light"``); one that some camera has no image of as dropped with ``reason: "no image"``.
    """
    log_lights = [e["light"] for e in log_json]
    trigger_of_entry = [int(round(e["time_us"] * 1e-6 * fps)) for e in log_json]
    try:
        labels = label_frames(log_lights, brightness, camera_names=cam_names, frame_times_s=frame_times,
                              log_times_s=[e["time_us"] * 1e-6 for e in log_json] if frame_times else None)
    except ValueError as err:
        raise InputError(f"capture: frames cannot be matched to the controller log ({err})") from err
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
            missing = [cam_names[c] for c in range(len(cam_names)) if labels.pulse_frame[c, k] < 0]
            entry.update(light=log_lights[k], status="ok" if not missing else "dropped")
            if missing:
                entry.update(reason="no image", missing_cameras=missing)
        frames.append(entry)
    return LabelledCapture(labels=labels, trigger_of_entry=trigger_of_entry, frames=frames)


def place_frames(out: CaptureOutput, labelled: LabelledCapture, cam_names: list[str],
                 received: Callable[[str, int], Path], place: Callable[[Path, Path], None]) -> None:
    """Move (``place``) each camera's ``"ok"`` images from ``received(cam, k)`` to ``frames/<cam>/<index>.exr``."""
    for c, cam in enumerate(cam_names):
        out.frames_dir(cam).mkdir(parents=True, exist_ok=True)
        labels = labelled.labels.cameras[c]
        for r, (k, status) in enumerate(zip(labels.pulse, labels.status)):
            if status == "ok":
                place(received(cam, r), out.frame_path(cam, labelled.trigger_of_entry[k]))
    shutil.rmtree(out.received_dir, ignore_errors=True)


def label_and_place(out: CaptureOutput, log: logging.Logger, subject: str, fps: float, cam_names: list[str],
                    n_bars: int, takes: tuple[str, ...], take_of_trigger: list[str], log_json: list[dict],
                    brightness: list[list[float]], n_triggers: int, received: Callable[[str, int], Path] | None = None,
                    place: Callable[[Path, Path], None] = os.replace,
                    frame_times: list[list[float]] | None = None) -> tuple[dict, dict]:
    """Label the received frames, place them in ``out``; the manifest (no image size yet) and the metrics.

    Images arrive in ``received(cam, k)`` (default ``_received/<cam>/<k>.exr``, arrival order)
    and are moved (``place``: a rename; the importer hard-links).
    """
    labelled = label_capture(log_json, brightness, cam_names, fps, n_triggers, takes, take_of_trigger, frame_times)
    for line in labelled.labels.warnings:
        log.warning(line)
    place_frames(out, labelled, cam_names, received or out.received_path, place)
    manifest = {"subject": subject, "fps": fps, "width": None, "height": None, "cameras": cam_names,
                "bars": n_bars, "takes": list(takes), "frames": labelled.frames}
    return manifest, labelled.metrics()
