"""The actor's scan session: static 3D scans (neutral first, then FACS poses) in head space."""

from __future__ import annotations

import numpy as np

from hardware.studio.performance import SCAN_POSES, pose_weights
from hardware.studio.subject import Subject


def scan_session(subject: Subject) -> tuple[list[str], np.ndarray, np.ndarray]:
    """The scans a booth would capture of ``subject``.

    Returns:
        names: S pose names, ``"neutral"`` first.
        vertices: [S, V, 3] float32 head-space vertices, metres (full ICT topology).
        faces: [T, 3] int32 triangles (``subject.rig.triangles``).
    """
    names = [name for name, _ in SCAN_POSES]
    verts = np.stack([subject.vertices(pose_weights(subject.rig, pose)) for _, pose in SCAN_POSES])
    return names, verts.astype(np.float32), subject.rig.triangles.copy()


def scan_weights(subject: Subject) -> np.ndarray:
    """The blendshape weights [S, 57] of each scan (ground truth, for evaluation only)."""
    return np.stack([pose_weights(subject.rig, pose) for _, pose in SCAN_POSES])
