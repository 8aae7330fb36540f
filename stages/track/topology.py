"""What the tracker knows about the ICT topology the scans share: skin triangles and
landmark correspondences (used only when the scan mesh has the ICT vertex count)."""

from __future__ import annotations

import numpy as np

from scene.face_rig import load_face_rig

# FaceMesh index of Multi-PIE 68 points 17..67 (brows, nose, eyes, lips); the jaw line
# (0..16) is a silhouette in most views and is left out. Only used to start the alignment
# of the first triangulated frame to the scan (a trimmed fit tolerates a few loose pairs).
FACEMESH_OF_MULTIPIE68: dict[int, int] = {
    17: 70, 18: 63, 19: 105, 20: 66, 21: 107, 22: 336, 23: 296, 24: 334, 25: 293, 26: 300,
    27: 168, 28: 197, 29: 5, 30: 4, 31: 98, 32: 97, 33: 2, 34: 326, 35: 327,
    36: 33, 37: 160, 38: 158, 39: 133, 40: 153, 41: 144, 42: 362, 43: 385, 44: 387, 45: 263, 46: 373, 47: 380,
    48: 61, 49: 39, 50: 37, 51: 0, 52: 267, 53: 269, 54: 291, 55: 405, 56: 314, 57: 17, 58: 84, 59: 181,
    60: 78, 61: 82, 62: 13, 63: 312, 64: 308, 65: 317, 66: 14, 67: 87,
}


def is_ict_topology(num_vertices: int) -> bool:
    """Whether a mesh with this many vertices has the ICT face model's topology."""
    return num_vertices == load_face_rig().num_vertices


def skin_triangles(faces: np.ndarray, num_vertices: int, regions: tuple[str, ...] = ("face",)) -> np.ndarray | None:
    """Indices of ``faces`` [T, 3] lying entirely in the ICT vertex ranges of ``regions``.

    None when the mesh is not ICT topology (then every triangle may hold a landmark).
    """
    if not is_ict_topology(num_vertices):
        return None
    ict = load_face_rig()
    mask = np.zeros(num_vertices, dtype=bool)
    for name in regions:
        mask[ict.regions[name].vertex_slice] = True
    return np.flatnonzero(np.all(mask[faces], axis=1))


def face_vertex_mask(num_vertices: int) -> np.ndarray:
    """Vertices [V] of the ICT face region (all vertices when the mesh is not ICT topology)."""
    if not is_ict_topology(num_vertices):
        return np.ones(num_vertices, dtype=bool)
    mask = np.zeros(num_vertices, dtype=bool)
    mask[load_face_rig().regions["face"].vertex_slice] = True
    return mask


def head_reference(neutral_m: np.ndarray, landmark_ids: np.ndarray) -> np.ndarray | None:
    """Head-space positions [N, 3] of FaceMesh landmarks with a known ICT vertex (nan elsewhere)."""
    if not is_ict_topology(len(neutral_m)):
        return None
    vertex_of_68 = load_face_rig().landmark_vertex_ids
    by_facemesh = {fm: int(vertex_of_68[k]) for k, fm in FACEMESH_OF_MULTIPIE68.items()}
    ref = np.full((len(landmark_ids), 3), np.nan)
    for col, lm in enumerate(landmark_ids):
        if int(lm) in by_facemesh:
            ref[col] = neutral_m[by_facemesh[int(lm)]]
    return ref


OUTLINE_REGIONS = ("face", "head_neck")


def outline_geometry(faces: np.ndarray, num_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Triangles [K, 3] that make the head's outline and its candidate vertices [V] (bool).

    With ICT topology: the skin of face and head/neck (eyeballs, teeth and the mouth
    interior never reach the outline); otherwise the whole mesh.
    """
    if not is_ict_topology(num_vertices):
        return faces, np.ones(num_vertices, dtype=bool)
    mask = np.zeros(num_vertices, dtype=bool)
    ict = load_face_rig()
    for name in OUTLINE_REGIONS:
        mask[ict.regions[name].vertex_slice] = True
    return faces[np.all(mask[faces], axis=1)], mask
