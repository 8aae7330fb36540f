"""Tracked meshes from elsewhere (``track.source``) instead of landmark tracking.

A studio that already tracks its performances hands over one mesh per frame, in world space
(metres, or ``source_units_m``) and in the actor rig's topology (the scan session's):

- a folder of OBJ files named by frame index (``000012.obj``, ``12.obj``); frames without a
  mesh are interpolated, as the landmark tracker interpolates its OLAT frames;
- or an ``.npz`` with ``vertices`` [N, V, 3] and optionally ``index`` [N] (the frames they
  belong to; without it, one mesh per capture frame in index order).

Head pose comes from a rigid fit (no scale) of the neutral scan's **stable vertices** to each
mesh: the vertices that none of the actor's scanned expressions moves by more than
``stable_motion_mm`` (skull, forehead, ears; the neutral is in head space, so the fit gives
``world_from_head``). The head-space mesh is the given mesh brought back by that pose, kept
exactly; the blendshape weights are its bounded least-squares fit to the rig (what
``tracking.npz`` reports), and frames between meshes interpolate pose (spline and Slerp),
weights, and head-space vertices (linearly). ``stabilize`` and everything downstream then
work unchanged.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from pipeline.errors import InputError
from scene.camera import Rigid
from stages.track.interpolate import interpolate_track
from stages.track.rig import ActorRig


class MeshSourceParams(BaseModel):
    """Reading tracked meshes from elsewhere (``track.source``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    units_m: float = Field(1.0, gt=0, description="Metres per unit of the meshes' coordinates: 0.001 for "
                           "millimetres, 0.01 for centimetres.")
    stable_motion_mm: float = Field(1.0, gt=0, description="A vertex is stable (used for the head pose) when no "
                                    "scanned expression moves it further than this. Raise it for a rig whose scans "
                                    "all move the skull a little (then fewer than 100 vertices qualify).")
    min_stable_vertices: int = Field(100, ge=3, description="Fewest stable vertices for the pose fit; with fewer, "
                                     "the stage says so and asks for a larger stable_motion_mm.")


@dataclass(frozen=True)
class SourceMeshes:
    """World-space meshes [N, V, 3] (metres) and the capture frames they belong to [N]."""

    path: Path
    index: np.ndarray
    vertices_world: np.ndarray


_INDEX_NAME = re.compile(r"^(?:frame_?)?(\d+)$")


def _read_obj(path: Path) -> np.ndarray:
    verts = []
    try:
        for line in path.read_text().splitlines():
            if line.startswith("v "):
                verts.append([float(v) for v in line.split()[1:4]])
    except (OSError, ValueError) as err:
        raise InputError(f"{path}: cannot read the OBJ's vertices ({err})") from err
    return np.asarray(verts, np.float64).reshape(-1, 3)


def read_mesh_source(path: str | Path, num_vertices: int, frame_indices: np.ndarray, units_m: float = 1.0
                     ) -> SourceMeshes:
    """The meshes at ``path`` (see the module docstring), checked against the rig's vertex count and the frames."""
    path = Path(path).expanduser()
    known = {int(i) for i in frame_indices}
    if path.is_dir():
        files = sorted(path.glob("*.obj"))
        if not files:
            raise InputError(f"track.source {path}: no .obj files in this folder")
        index, meshes = [], []
        for file in files:
            match = _INDEX_NAME.match(file.stem)
            if match is None:
                raise InputError(f"{file}: name the OBJ files by their frame index (000012.obj); '{file.stem}' is not "
                                 "a frame index")
            mesh = _read_obj(file)
            if len(mesh) != num_vertices:
                raise InputError(f"{file}: has {len(mesh)} vertices, the actor rig (the capture's scan session) has "
                                 f"{num_vertices}; the meshes must use the rig's topology")
            index.append(int(match.group(1)))
            meshes.append(mesh)
        index_arr, vertices = np.asarray(index), np.stack(meshes)
    elif path.suffix.lower() == ".npz":
        try:
            with np.load(path, allow_pickle=False) as data:
                vertices = np.asarray(data["vertices"], np.float64)
                index_arr = np.asarray(data["index"]) if "index" in data.files else None
        except (OSError, ValueError, KeyError) as err:
            raise InputError(f"{path}: not an .npz with 'vertices' [N, V, 3] ({err})") from err
        if vertices.ndim != 3 or vertices.shape[2] != 3:
            raise InputError(f"{path}: 'vertices' has shape {vertices.shape}, expected [N, V, 3]")
        if vertices.shape[1] != num_vertices:
            raise InputError(f"{path}: meshes have {vertices.shape[1]} vertices, the actor rig (the capture's scan "
                             f"session) has {num_vertices}; the meshes must use the rig's topology")
        if index_arr is None:
            if len(vertices) != len(frame_indices):
                raise InputError(f"{path}: {len(vertices)} meshes and no 'index', but the capture has "
                                 f"{len(frame_indices)} frames; add 'index' [N] naming each mesh's frame")
            index_arr = np.sort(np.asarray(frame_indices))
        elif index_arr.shape != (len(vertices),):
            raise InputError(f"{path}: 'index' has shape {index_arr.shape}, expected [{len(vertices)}]")
    else:
        raise InputError(f"track.source {path}: give a folder of OBJ files or an .npz of vertices")
    index_arr = index_arr.astype(np.int64)
    unknown = sorted(set(index_arr.tolist()) - known)
    if unknown:
        raise InputError(f"track.source {path}: frame {unknown[0]} is not a frame of the capture"
                         f"{f' (nor {len(unknown) - 1} more)' if len(unknown) > 1 else ''}; its frames are "
                         f"{min(known)}..{max(known)}")
    if len(set(index_arr.tolist())) != len(index_arr):
        raise InputError(f"track.source {path}: a frame has two meshes")
    if not np.all(np.isfinite(vertices)):
        raise InputError(f"track.source {path}: the meshes hold NaN or inf")
    order = np.argsort(index_arr)
    return SourceMeshes(path, index_arr[order], vertices[order] * units_m)


def stable_vertices(rig: ActorRig, motion_mm: float, minimum: int) -> np.ndarray:
    """Vertex ids [S] that no scanned expression moves further than ``motion_mm``."""
    if rig.num_shapes == 0:
        return np.arange(rig.num_vertices)  # a neutral scan only: every vertex is as stable as any
    motion_mm_per_vertex = np.linalg.norm(rig.basis_m, axis=-1).max(axis=0) * 1000.0  # [V]
    ids = np.flatnonzero(motion_mm_per_vertex <= motion_mm)
    if len(ids) < minimum:
        raise InputError(f"track.source: only {len(ids)} vertices move less than track.mesh_source.stable_motion_mm = "
                         f"{motion_mm} mm under the actor's scans (needs {minimum}); raise stable_motion_mm")
    return ids


def rigid_fit(source: np.ndarray, target: np.ndarray) -> Rigid:
    """The rotation and translation taking points ``source`` [N, 3] onto ``target`` [N, 3] (least squares, Kabsch)."""
    mu_s, mu_t = source.mean(0), target.mean(0)
    u, _, vt = np.linalg.svd((target - mu_t).T @ (source - mu_s))
    d = np.sign(np.linalg.det(u @ vt))
    R = u @ np.diag([1.0, 1.0, d]) @ vt
    return Rigid(R, mu_t - R @ mu_s)


def fit_weights(rig: ActorRig, vertices_head: np.ndarray, weight_min: float, weight_max: float) -> np.ndarray:
    """Bounded least-squares blendweights [K] of a head-space mesh [V, 3] on the rig."""
    from scipy.optimize import lsq_linear

    if rig.num_shapes == 0:
        return np.zeros(0)
    basis = rig.basis_m.reshape(rig.num_shapes, -1).T  # [3V, K]
    target = (vertices_head - rig.neutral_m).reshape(-1)
    return lsq_linear(basis, target, bounds=(weight_min, weight_max)).x


@dataclass(frozen=True)
class MeshTrack:
    """Pose, weights and head-space meshes of every capture frame from the given meshes."""

    index: np.ndarray  # [T]
    world_from_head_R: np.ndarray  # [T, 3, 3]
    world_from_head_t: np.ndarray  # [T, 3]
    weights: np.ndarray  # [T, K]
    vertices_head: np.ndarray  # [T, V, 3] float32
    given: np.ndarray  # [T] bool: the frame had a mesh
    stable_residual_mm: np.ndarray  # [N] RMS of the stable vertices after the pose fit, per given mesh
    rig_residual_mm: np.ndarray  # [N] RMS of the rig's fit of each given mesh (how far it is from the rig)


def track_from_meshes(rig: ActorRig, source: SourceMeshes, frame_index: np.ndarray, frame_time_s: np.ndarray,
                      params: MeshSourceParams, weight_min: float, weight_max: float,
                      log: logging.Logger | None = None) -> MeshTrack:
    """Poses by rigid fits of the stable vertices, weights by the rig's fit; every frame (see the module docstring)."""
    stable = stable_vertices(rig, params.stable_motion_mm, params.min_stable_vertices)
    poses, head, weights, stable_res, rig_res = [], [], [], [], []
    for world in source.vertices_world:
        pose = rigid_fit(rig.neutral_m[stable], world[stable])
        in_head = (world - pose.t) @ pose.R  # R^T (x - t), row vectors
        w = fit_weights(rig, in_head, weight_min, weight_max)
        poses.append(pose)
        head.append(in_head)
        weights.append(w)
        stable_res.append(np.sqrt(np.mean(np.sum((in_head[stable] - rig.neutral_m[stable]) ** 2, -1))) * 1000.0)
        rig_res.append(np.sqrt(np.mean(np.sum((rig.mesh(w) - in_head) ** 2, -1))) * 1000.0)
    time_of = dict(zip(np.asarray(frame_index).tolist(), np.asarray(frame_time_s, float).tolist()))
    key_t = np.array([time_of[int(i)] for i in source.index])
    order = np.argsort(key_t, kind="stable")
    if np.any(np.diff(key_t[order]) <= 0):
        raise InputError(f"track.source {source.path}: two meshes belong to frames with the same time stamp")
    key_t = key_t[order]
    key_R = np.stack([poses[k].R for k in order])
    key_tr = np.stack([poses[k].t for k in order])
    key_w = np.stack([weights[k] for k in order]).reshape(len(order), rig.num_shapes)
    key_head = np.stack([head[k] for k in order])
    times = np.asarray(frame_time_s, float)
    R, t, w = interpolate_track(key_t, key_R, key_tr, key_w, times, weight_min, weight_max)
    vertices = _interpolate_meshes(key_t, key_head, times)
    given_index = set(source.index.tolist())
    given = np.array([int(i) in given_index for i in frame_index])
    vertices[given] = key_head[np.searchsorted(key_t, times[given])]  # given frames keep their mesh exactly
    if log is not None:
        log.info("track.source: %d meshes for %d frames; pose from %d stable vertices (RMS %.3f mm after the fit); "
                 "the rig fits them to %.3f mm RMS", len(source.index), len(frame_index), len(stable),
                 float(np.mean(stable_res)), float(np.mean(rig_res)))
    return MeshTrack(np.asarray(frame_index), R, t, w, vertices.astype(np.float32), given, np.asarray(stable_res),
                     np.asarray(rig_res))


def _interpolate_meshes(key_t: np.ndarray, key_head: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Head-space vertices at ``times`` [T]: linear between the key meshes, held beyond the ends."""
    if len(key_t) == 1:
        return np.repeat(key_head, len(times), axis=0).astype(np.float64)
    flat = key_head.reshape(len(key_t), -1)
    hi = np.clip(np.searchsorted(key_t, times), 1, len(key_t) - 1)
    lo = hi - 1
    a = np.clip((times - key_t[lo]) / (key_t[hi] - key_t[lo]), 0.0, 1.0)[:, None]
    return ((1.0 - a) * flat[lo] + a * flat[hi]).reshape(len(times), *key_head.shape[1:])


__all__ = ["MeshSourceParams", "MeshTrack", "SourceMeshes", "fit_weights", "read_mesh_source", "rigid_fit",
           "stable_vertices", "track_from_meshes"]
