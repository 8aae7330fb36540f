"""The ICT-FaceKit face model as a blendshape rig in head space (metres).

Head space is the ICT model's own frame converted from centimetres to metres: +x to the
subject's left, +y up, +z out of the face (the nose tip is at z ~ +0.13 m), origin near the
centre of the skull. ``FaceRig.vertices(identity, weights)`` evaluates

    vertices = neutral + sum_i identity[i] * identity_deltas[i] + sum_j weights[j] * expression_deltas[j]

Quads are split into triangles ``(a, b, c), (a, c, d)`` so every consumer shares one
triangle list; ``triangle_polygon`` maps a triangle back to its source polygon.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

# The shipped face model (declared so the code digest of every module using the rig covers it).
CODE_FILES = ("../assets/ict-facekit/ict_face_light.npz",)
DEFAULT_FACE_MODEL = (Path(__file__).parent / CODE_FILES[0]).resolve()
CM_TO_M = 0.01

# Multi-PIE 68 landmark groups (0-based indices into ``landmark_vertex_ids``).
LANDMARK_GROUPS: dict[str, tuple[int, int]] = {
    "jaw": (0, 17), "brow_right": (17, 22), "brow_left": (22, 27), "nose_bridge": (27, 31),
    "nose_base": (31, 36), "eye_right": (36, 42), "eye_left": (42, 48),
    "lips_outer": (48, 60), "lips_inner": (60, 68),
}


@dataclass(frozen=True)
class Region:
    """A named part of the model: vertex range and triangle range (half-open)."""

    name: str
    vertex_start: int
    vertex_stop: int
    triangle_start: int
    triangle_stop: int

    @property
    def vertex_slice(self) -> slice:
        return slice(self.vertex_start, self.vertex_stop)

    @property
    def triangle_slice(self) -> slice:
        return slice(self.triangle_start, self.triangle_stop)


class FaceRig:
    """The ICT face model: neutral, identity PCA modes and expression blendshapes, in metres.

    Attributes:
        neutral_m: [V, 3] neutral vertices, head space, metres.
        identity_deltas_m: [I, V, 3] identity modes (I = 20), roughly one standard deviation each.
        expression_deltas_m: [E, V, 3] expression blendshapes (E = 57), ARKit-style names.
        expression_names: E names (``jawOpen``, ``eyeBlink_L`` ...).
        triangles: [T, 3] int32 vertex indices.
        triangles_uv: [T, 3] int32 indices into ``uv``.
        uv: [U, 2] texture coordinates; UDIM-like tiles (face in u in [0, 1], head/neck in
            [1, 2], gums/tongue [2, 3], teeth [3, 4]; the eyeballs reuse tile [0, 1]).
        triangle_polygon: [T] source polygon index.
        triangle_region: [T] index into ``region_names``.
        regions: name -> ``Region`` (vertex and triangle ranges).
        landmark_vertex_ids: [68] vertex index of each Multi-PIE 68 landmark.
    """

    def __init__(self, path: str | Path = DEFAULT_FACE_MODEL) -> None:
        path = Path(path)
        try:
            data = np.load(path)
            neutral = data["neutral"].astype(np.float32)
            faces = data["faces"].astype(np.int64)
            faces_uv = data["faces_uv"].astype(np.int64)
            self.uv = data["uv"].astype(np.float32)
            self.expression_names: tuple[str, ...] = tuple(str(n) for n in data["expression_names"])
            self.expression_deltas_m = data["expression_deltas"].astype(np.float32) * CM_TO_M
            self.identity_deltas_m = data["identity_deltas"].astype(np.float32) * CM_TO_M
            self.landmark_vertex_ids = data["landmarks_multipie68"].astype(np.int64)
            regions_raw = json.loads(str(data["regions_json"]))
        except (OSError, KeyError, ValueError) as err:
            raise ValueError(f"{path}: not a valid ICT face model pack ({err}); see assets/README.md") from err
        self.path = path
        self.neutral_m = neutral * CM_TO_M

        is_quad = faces[:, 3] >= 0
        poly_ids = np.arange(len(faces))
        first = faces[:, [0, 1, 2]]
        second = faces[is_quad][:, [0, 2, 3]]
        first_uv = faces_uv[:, [0, 1, 2]]
        second_uv = faces_uv[is_quad][:, [0, 2, 3]]
        # Interleave so a polygon's triangles are adjacent and regions stay contiguous.
        tri_poly = np.concatenate([poly_ids, poly_ids[is_quad]])
        tri_order = np.argsort(np.concatenate([poly_ids * 2, poly_ids[is_quad] * 2 + 1]), kind="stable")
        self.triangles = np.concatenate([first, second])[tri_order].astype(np.int32)
        self.triangles_uv = np.concatenate([first_uv, second_uv])[tri_order].astype(np.int32)
        self.triangle_polygon = tri_poly[tri_order].astype(np.int32)

        self.regions: dict[str, Region] = {}
        self.region_names: tuple[str, ...] = tuple(regions_raw)
        self.triangle_region = np.full(len(self.triangles), -1, dtype=np.int32)
        for rid, (name, ((v0, v1), (f0, f1))) in enumerate(regions_raw.items()):
            tris = np.nonzero((self.triangle_polygon >= f0) & (self.triangle_polygon <= f1))[0]
            self.regions[name] = Region(name, int(v0), int(v1) + 1, int(tris.min()), int(tris.max()) + 1)
            self.triangle_region[tris] = rid

    # ---- sizes -------------------------------------------------------------------------
    @property
    def num_vertices(self) -> int:
        return int(self.neutral_m.shape[0])

    @property
    def num_identity(self) -> int:
        return int(self.identity_deltas_m.shape[0])

    @property
    def num_expressions(self) -> int:
        return int(self.expression_deltas_m.shape[0])

    def expression_index(self, name: str) -> int:
        """Index of blendshape ``name``; ``KeyError`` listing the valid names otherwise."""
        try:
            return self.expression_names.index(name)
        except ValueError:
            raise KeyError(f"unknown expression '{name}'; valid: {', '.join(self.expression_names)}") from None

    # ---- evaluation --------------------------------------------------------------------
    def identity_mesh(self, identity_coeffs: np.ndarray | None = None) -> np.ndarray:
        """Neutral-expression vertices [V, 3] (metres) of an identity (coefficients [I], None = mean)."""
        verts = self.neutral_m.copy()
        if identity_coeffs is not None:
            c = np.asarray(identity_coeffs, dtype=np.float32)
            if c.shape != (self.num_identity,):
                raise ValueError(f"identity_coeffs must have shape ({self.num_identity},), got {c.shape}")
            verts += np.tensordot(c, self.identity_deltas_m, axes=1)
        return verts

    def vertices(self, identity_coeffs: np.ndarray | None = None,
                 expression_weights: np.ndarray | None = None) -> np.ndarray:
        """Head-space vertices [V, 3] float32 (metres) for an identity and blendshape weights [E]."""
        verts = self.identity_mesh(identity_coeffs)
        if expression_weights is not None:
            w = np.asarray(expression_weights, dtype=np.float32)
            if w.shape != (self.num_expressions,):
                raise ValueError(f"expression_weights must have shape ({self.num_expressions},), got {w.shape}")
            nz = np.nonzero(w)[0]
            if len(nz):
                verts += np.tensordot(w[nz], self.expression_deltas_m[nz], axes=1)
        return verts

    def region_triangles(self, names: tuple[str, ...] | list[str]) -> np.ndarray:
        """Indices [K] of the triangles in the given regions (``KeyError`` names an unknown one)."""
        ids = []
        for name in names:
            if name not in self.regions:
                raise KeyError(f"unknown face-model region '{name}'; valid: {', '.join(self.regions)}")
            r = self.regions[name]
            ids.append(np.arange(r.triangle_start, r.triangle_stop))
        return np.concatenate(ids) if ids else np.zeros(0, dtype=np.int64)

    def landmarks(self, vertices: np.ndarray) -> np.ndarray:
        """The 68 Multi-PIE landmark positions [..., 68, 3] of vertices [..., V, 3]."""
        return np.asarray(vertices)[..., self.landmark_vertex_ids, :]


@lru_cache(maxsize=2)
def load_face_rig(path: str | Path = DEFAULT_FACE_MODEL) -> FaceRig:
    """A cached ``FaceRig`` (loading takes ~0.3 s; the arrays are shared, do not modify them)."""
    return FaceRig(path)
