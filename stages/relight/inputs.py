"""What the relight stage reads: the trained head, the tracked default mesh, driving meshes and envmaps."""

from __future__ import annotations

import logging
import warnings
from pathlib import Path
from typing import Mapping

import numpy as np

from pipeline.errors import InputError
from scene.envmap import EnvMap, EnvMapError, EnvMapWarning, read_envmap
from stages.capture.output import CaptureOutput
from stages.relight.params import RelightParams, resolve_envmap
from stages.track.output import TrackOutput
from stages.train.output import TrainOutput


def read_map(name: str, log: logging.Logger) -> EnvMap:
    """An envmap by its param name; repairs are logged, a bad file is an InputError naming it."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", EnvMapWarning)
        try:
            envmap = read_envmap(resolve_envmap(name))
        except EnvMapError as err:
            raise InputError(f"relight.envmaps: {err}") from err
    for w in caught:
        log.warning("%s", w.message)
    return envmap


def load_inputs(inputs: Mapping[str, Path], params: RelightParams, device: str):
    """The trained model and its metadata, the default (first tracked) mesh and the driving meshes of novel expressions."""
    from avatar.io import load_trained

    model, meta = TrainOutput(inputs["train"]).model(lambda folder: load_trained(folder, device))
    track = TrackOutput(inputs["track"])
    vertices = track.meshes(keys=("vertices",))["vertices"]
    if len(vertices) == 0:
        raise track.malformed(track.meshes_path, "no tracked meshes")
    default_mesh = np.asarray(vertices[0], np.float32)
    expressions = None
    if params.expressions_csv or params.expressions_obj_dir:
        expressions = _expression_meshes(inputs, params, default_mesh.shape[0])
    return model, meta, default_mesh, expressions


def _expression_meshes(inputs: Mapping[str, Path], params: RelightParams, num_vertices: int) -> np.ndarray:
    from scene.face_rig import load_face_rig
    from stages.relight.expressions import (load_actor_rig, meshes_from_weights, read_obj_sequence,
                                            read_weights_csv)

    try:
        if params.expressions_obj_dir:
            return read_obj_sequence(Path(params.expressions_obj_dir), num_vertices)
        names, neutral, offsets = load_actor_rig(CaptureOutput(inputs["capture"]))
        rig = load_face_rig()
        weights = read_weights_csv(Path(params.expressions_csv), rig.expression_names)
        return meshes_from_weights(weights, rig.expression_deltas_m, neutral, offsets)
    except ValueError as err:
        raise InputError(str(err)) from err
