"""What the evaluate stage reads: the trained head, the tracked meshes, the studio's truth and the scans."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from avatar.model import RelightableMVP
from hardware.studio.subject import Subject
from pipeline.errors import InputError
from stages.capture.output import CaptureOutput, CaptureTruth
from stages.track.output import TrackOutput
from stages.train.output import TrainOutput


@dataclass
class EvaluationInputs:
    """The sweeps' data, read from the ``train``, ``track``, ``capture`` and ``capture.truth`` folders.

    Attributes:
        model: the trained head (ours).
        subject: the studio's subject, rebuilt from the truth, that renders the reference images.
        vertices: the tracked head-space meshes [F, V, 3] (float32); ``mesh_index`` their capture frames.
        truth_weights: the true ICT blendshape weights [T, E]; ``truth_row`` maps a capture frame to its row.
        splits: the train stage's splits (``{}`` when it wrote none).
        training_lights_head: head-space positions [L, 3] of the lit bar of every training frame,
            from the studio's true bar centres and head poses: what the model was actually shown.
        neutral_scan: the actor's neutral scan [V', 3] (the expression sweep scales from it).
    """

    model: RelightableMVP
    subject: Subject
    vertices: np.ndarray
    mesh_index: list[int]
    truth_weights: np.ndarray
    truth_row: dict[int, int]
    splits: dict[str, Any]
    training_lights_head: np.ndarray
    neutral_scan: np.ndarray


def load_evaluation_inputs(inputs: Mapping[str, Path]) -> EvaluationInputs:
    """Read the sweeps' data; an ``InputError`` naming what to rerun for anything missing or malformed."""
    from avatar.io import load_trained
    from hardware.studio.envmap_truth import subject_from_truth

    capture, truth = CaptureOutput(inputs["capture"]), CaptureTruth(inputs["capture.truth"])
    train, track = TrainOutput(inputs["train"]), TrackOutput(inputs["track"])
    model, _meta = train.model(load_trained)
    try:
        subject = subject_from_truth(truth.path)
    except ValueError as err:
        raise InputError(f"evaluate: {err}") from err
    meshes = track.meshes(keys=("vertices",))
    mesh_index = [int(i) for i in meshes["index"]] if "index" in meshes else list(range(len(meshes["vertices"])))
    truth_frames = truth.frames(keys=("weights",))
    truth_row = {int(i): k for k, i in enumerate(truth_frames["index"])} if "index" in truth_frames else \
        {k: k for k in range(len(truth_frames["weights"]))}
    scans = capture.scans(keys=("vertices",))
    return EvaluationInputs(
        model=model, subject=subject, vertices=np.asarray(meshes["vertices"], np.float32), mesh_index=mesh_index,
        truth_weights=np.asarray(truth_frames["weights"]), truth_row=truth_row,
        splits=train.splits() if train.has_splits() else {},
        training_lights_head=training_lights_head(capture, truth, train),
        neutral_scan=np.asarray(scans["vertices"][0], np.float32))


def training_lights_head(capture: CaptureOutput, truth: CaptureTruth, train: TrainOutput) -> np.ndarray:
    """Head-space positions [L, 3] of the lit bar of every training frame.

    Training frames come from the train stage's splits (all OLAT frames if it has none); bar
    centres and head poses are the studio's true ones.
    """
    manifest = capture.manifest(keys=("frames",))
    frames = {int(f["index"]): f for f in manifest["frames"]}
    if train.has_splits():
        train_index = [int(i) for i in train.splits()["train"]]
    else:
        train_index = sorted(i for i, f in frames.items() if f.get("light") not in ("F", None)
                             and f.get("status", "ok") == "ok")
    bars = {int(b["id"]): np.asarray(b["center_world"], float) for b in truth.bars()}
    poses = truth.frames(keys=("index", "world_from_head_R", "world_from_head_t"))
    row = {int(i): k for k, i in enumerate(poses["index"])}
    lights = []
    for i in train_index:
        light = frames.get(i, {}).get("light")
        if light in ("F", None) or i not in row or int(light) not in bars:
            continue
        R, t = poses["world_from_head_R"][row[i]], poses["world_from_head_t"][row[i]]
        lights.append(R.T @ (bars[int(light)] - t))  # head_from_world applied to the bar centre
    if not lights:
        raise InputError(f"evaluate: no training OLAT frames with a lit bar in {train.splits_path} / "
                         f"{capture.manifest_path}; re-run capture and train")
    return np.asarray(lights)
