"""The actor-specific blendshape rig, built from the actor's scan session.

A studio scans the actor first in a neutral pose and a few FACS poses (``scans/scans.npz``
of the capture: ``names`` [S], ``vertices`` [S, V, 3] in head space, metres, ``faces``
[T, 3], neutral first). The rig is linear: ``mesh(w) = neutral + sum_k w_k (scan_k - neutral)``,
with ``w_k`` in ``[0, 1]`` (a scan is a full activation of its pose). Everything here is in
head space; the head pose is fitted separately.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.errors import InputError
from stages.capture.output import CaptureOutput


@dataclass(frozen=True)
class ActorRig:
    """A linear blendshape rig in head space.

    Attributes:
        names: blendshape names [K] (the scan session's pose names, neutral excluded).
        neutral_m: neutral vertices [V, 3], head space, metres.
        basis_m: per-blendshape vertex offsets from neutral [K, V, 3], metres.
        faces: triangles [T, 3] (vertex indices).
    """

    names: tuple[str, ...]
    neutral_m: np.ndarray  # [V, 3]
    basis_m: np.ndarray  # [K, V, 3]
    faces: np.ndarray  # [T, 3]

    @property
    def num_shapes(self) -> int:
        """Number of blendshapes K."""
        return len(self.names)

    @property
    def num_vertices(self) -> int:
        """Number of vertices V."""
        return int(self.neutral_m.shape[0])

    def mesh(self, weights: np.ndarray) -> np.ndarray:
        """Head-space vertices for blendweights [K] -> [V, 3], or [F, K] -> [F, V, 3]."""
        w = np.asarray(weights, dtype=np.float64)
        offsets = np.tensordot(w, self.basis_m, axes=([-1], [0]))  # [..., V, 3]
        return self.neutral_m + offsets


def load_scan_rig(capture: CaptureOutput) -> ActorRig:
    """Build the actor rig from a capture's scan session (``CaptureOutput.scans``).

    Raises ``InputError`` naming the file when it is missing, lacks a key, or its arrays
    disagree in shape (the neutral scan must come first).
    """
    scans_path = capture.scans_path
    data = capture.scans(keys=("names", "vertices", "faces"))
    names = [str(n) for n in data["names"]]
    vertices = np.asarray(data["vertices"], dtype=np.float64)  # [S, V, 3]
    faces = np.asarray(data["faces"], dtype=np.int64)  # [T, 3]
    if vertices.ndim != 3 or vertices.shape[2] != 3 or vertices.shape[0] != len(names):
        raise InputError(f"{scans_path}: 'vertices' has shape {vertices.shape}, expected "
                         f"[S={len(names)}, V, 3] matching 'names'")
    if vertices.shape[0] < 1:
        raise InputError(f"{scans_path}: the scan session is empty; it needs at least a neutral scan")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.min() < 0 or faces.max() >= vertices.shape[1]:
        raise InputError(f"{scans_path}: 'faces' must be [T, 3] triangle indices into {vertices.shape[1]} "
                         f"vertices, got shape {faces.shape}")
    if not np.all(np.isfinite(vertices)):
        raise InputError(f"{scans_path}: 'vertices' holds NaN or inf values; re-run the capture stage")
    neutral = vertices[0]
    basis = vertices[1:] - neutral[None]
    return ActorRig(names=tuple(names[1:]), neutral_m=neutral, basis_m=basis, faces=faces)
