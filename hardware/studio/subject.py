"""A virtual subject: ICT identity from a seed plus procedural skin, eye and mouth materials.

Materials live in UV space (the ICT layout: face tile u in [0, 1], head/neck tile [1, 2]):
an albedo atlas [H, 2H, 3] and a roughness atlas [H, 2H] painted from the subject's own
landmarks (lips, brows), with low-frequency skin-tone variation and a hair cap on the
scalp. Eyes (sclera, iris, pupil) are shaded from the hit point's angle to the eyeball's
gaze axis, so they stay sharp at any resolution; teeth and the mouth interior are
constant materials.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from scene.face_rig import FaceRig, load_face_rig

# Regions the renderer draws (the ICT pack's transparent overlays, lashes and lacrimal
# pieces are left out: they need alpha blending that a matte ground truth cannot express).
RENDER_REGIONS: tuple[str, ...] = (
    "face", "head_neck", "mouth_socket", "eye_socket_left", "eye_socket_right",
    "gums_tongue", "teeth", "eyeball_left", "eyeball_right",
)

# Material ids per region (index into the per-material constant tables below).
MAT_SKIN, MAT_MOUTH, MAT_TEETH, MAT_EYE, MAT_SOCKET = 0, 1, 2, 3, 4
_REGION_MATERIAL = {
    "face": MAT_SKIN, "head_neck": MAT_SKIN, "mouth_socket": MAT_MOUTH, "gums_tongue": MAT_MOUTH,
    "teeth": MAT_TEETH, "eyeball_left": MAT_EYE, "eyeball_right": MAT_EYE,
    "eye_socket_left": MAT_SOCKET, "eye_socket_right": MAT_SOCKET,
}

IRIS_COLOURS = np.array([[0.10, 0.05, 0.02], [0.12, 0.20, 0.30], [0.10, 0.16, 0.06], [0.18, 0.10, 0.04]])


@dataclass(frozen=True)
class Subject:
    """A subject of the virtual studio.

    Attributes:
        name: subject name (``alice``).
        seed: the identity seed everything below derives from.
        identity_coeffs: [20] ICT identity PCA coefficients.
        skin_albedo: [3] linear base skin albedo.
        iris_albedo: [3] linear iris albedo.
        albedo_atlas: [Ht, 2 Ht, 3] linear albedo over UV u in [0, 2], v in [0, 1].
        roughness_atlas: [Ht, 2 Ht] GGX roughness (perceptual, alpha = r^2) over the same UV.
        specular_atlas: [Ht, 2 Ht] normal-incidence Fresnel reflectance F0 over the same UV.
    """

    name: str
    seed: int
    identity_coeffs: np.ndarray
    skin_albedo: np.ndarray
    iris_albedo: np.ndarray
    albedo_atlas: np.ndarray
    roughness_atlas: np.ndarray
    specular_atlas: np.ndarray
    rig: FaceRig = field(repr=False, compare=False, default_factory=load_face_rig)

    @cached_property
    def neutral_m(self) -> np.ndarray:
        """The subject's neutral head-space vertices [V, 3], metres."""
        return self.rig.identity_mesh(self.identity_coeffs)

    def vertices(self, expression_weights: np.ndarray | None = None) -> np.ndarray:
        """Head-space vertices [V, 3] (metres) of this subject with blendshape weights [57]."""
        verts = self.neutral_m.copy()
        if expression_weights is not None:
            w = np.asarray(expression_weights, dtype=np.float32)
            nz = np.nonzero(w)[0]
            if len(nz):
                verts += np.tensordot(w[nz], self.rig.expression_deltas_m[nz], axes=1)
        return verts

    @cached_property
    def render_triangles(self) -> np.ndarray:
        """Indices [K] of the rig triangles the renderer draws (``RENDER_REGIONS``)."""
        return self.rig.region_triangles(RENDER_REGIONS)

    @cached_property
    def triangle_material(self) -> np.ndarray:
        """Material id [T] of every rig triangle (-1 for regions not drawn)."""
        mat = np.full(len(self.rig.triangles), -1, dtype=np.int8)
        for name, mid in _REGION_MATERIAL.items():
            mat[self.rig.regions[name].triangle_slice] = mid
        return mat

    @cached_property
    def eye_pupil_vertices(self) -> tuple[int, int]:
        """Vertex ids of the front-most (pupil-centre) vertex of the left and right eyeball."""
        ids = []
        for name in ("eyeball_left", "eyeball_right"):
            sl = self.rig.regions[name].vertex_slice
            ids.append(int(sl.start + np.argmax(self.neutral_m[sl, 2])))
        return ids[0], ids[1]


def _paint_uv_polygon(canvas: np.ndarray, uv: np.ndarray, value: float, size: int, thickness: int = 0) -> None:
    """Fill (or stroke, with ``thickness``) a polygon given in face-tile UV into a [H, 2H] canvas."""
    import cv2

    pts = np.stack([uv[:, 0] * size, (1.0 - uv[:, 1]) * size], -1)
    pts = np.round(pts * 16).astype(np.int32)[None]  # 4 fractional bits for smooth edges
    if thickness:
        cv2.polylines(canvas, pts, False, value, thickness=thickness, lineType=cv2.LINE_AA, shift=4)
    else:
        cv2.fillPoly(canvas, pts, value, lineType=cv2.LINE_AA, shift=4)


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], cells: int) -> np.ndarray:
    """Band-limited noise in [-1, 1]: a coarse random grid, bicubically upsampled."""
    import cv2

    coarse = rng.uniform(-1, 1, size=(cells, cells * shape[1] // shape[0])).astype(np.float32)
    return cv2.resize(coarse, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC).clip(-1, 1)


def make_subject(name: str, seed: int, texture_size: int = 512, rig: FaceRig | None = None) -> Subject:
    """Build a subject deterministically from ``seed``: identity shape, skin tone, eye colour, maps.

    Args:
        name: subject name (metadata only).
        seed: identity seed (``configs/subjects/<name>.yaml: capture.identity_seed``).
        texture_size: height of each UV tile of the material atlases, pixels.
    """
    import cv2

    rig = rig or load_face_rig()
    rng = np.random.default_rng(np.random.SeedSequence([0x5EED, int(seed)]))
    identity = np.clip(rng.normal(0.0, 0.8, size=rig.num_identity), -2.0, 2.0).astype(np.float32)
    # Skin tone: interpolate between light and dark linear albedos.
    tone = rng.uniform(0.0, 1.0)
    skin = (1 - tone) * np.array([0.62, 0.42, 0.33]) + tone * np.array([0.22, 0.12, 0.07])
    iris = IRIS_COLOURS[rng.integers(len(IRIS_COLOURS))] * rng.uniform(0.8, 1.2)
    hair = np.array([0.05, 0.03, 0.015]) * rng.uniform(0.4, 2.5)

    size = int(texture_size)
    shape = (size, 2 * size)
    neutral = rig.identity_mesh(identity)
    lm_uv = _landmark_uv(rig)

    lips = np.zeros(shape, np.float32)
    _paint_uv_polygon(lips, lm_uv[48:60], 1.0, size)
    lips = cv2.GaussianBlur(lips, (0, 0), size / 400)
    brows = np.zeros(shape, np.float32)
    thick = max(2, size // 36)
    _paint_uv_polygon(brows, lm_uv[17:22], 1.0, size, thickness=thick)
    _paint_uv_polygon(brows, lm_uv[22:27], 1.0, size, thickness=thick)
    brows = cv2.GaussianBlur(brows, (0, 0), size / 300) * 0.85

    # Low-frequency tone variation plus fine mottling.
    variation = 0.08 * _smooth_noise(rng, shape, 8) + 0.04 * _smooth_noise(rng, shape, 64)
    albedo = np.broadcast_to(skin, shape + (3,)).astype(np.float32) * (1 + variation[..., None])
    redness = np.clip(_smooth_noise(rng, shape, 6), 0, 1)[..., None] * np.array([0.05, -0.02, -0.02], np.float32)
    albedo = albedo + redness * (1 - tone)
    lip_colour = skin * np.array([1.05, 0.55, 0.6]) * 0.9
    albedo = albedo * (1 - lips[..., None]) + lip_colour * lips[..., None]
    albedo = albedo * (1 - brows[..., None]) + hair * brows[..., None]

    hair_cap = _hair_cap_mask(rig, neutral, size)
    albedo = albedo * (1 - hair_cap[..., None]) + hair * hair_cap[..., None]

    roughness = (0.5 + 0.05 * _smooth_noise(rng, shape, 16)) * (1 - lips) + 0.32 * lips
    roughness = roughness * (1 - brows) + 0.75 * brows
    roughness = roughness * (1 - hair_cap) + 0.7 * hair_cap
    specular = np.full(shape, 0.028, np.float32) * (1 - 0.6 * hair_cap)

    return Subject(name=name, seed=int(seed), identity_coeffs=identity, skin_albedo=skin.astype(np.float32),
                   iris_albedo=iris.astype(np.float32), albedo_atlas=np.clip(albedo, 0.01, 0.95).astype(np.float32),
                   roughness_atlas=np.clip(roughness, 0.05, 1.0).astype(np.float32),
                   specular_atlas=specular.astype(np.float32), rig=rig)


def _landmark_uv(rig: FaceRig) -> np.ndarray:
    """UV [68, 2] of each landmark vertex (first UV found for it among face-tile triangles)."""
    face = rig.regions["face"].triangle_slice
    tris = rig.triangles[face].reshape(-1)
    tuv = rig.triangles_uv[face].reshape(-1)
    first = {}
    for v, t in zip(tris.tolist(), tuv.tolist()):
        first.setdefault(v, t)
    return np.stack([rig.uv[first[int(v)]] for v in rig.landmark_vertex_ids])


def _hair_cap_mask(rig: FaceRig, neutral: np.ndarray, size: int) -> np.ndarray:
    """Hair coverage [H, 2H] in UV: scalp above a hairline plane, painted per triangle."""
    import cv2

    lm = neutral[rig.landmark_vertex_ids]
    brow_y = lm[17:27, 1].max()
    # Hairline: ~6 cm above the brows at the front, sloping down towards the back and sides.
    canvas = np.zeros((size, 2 * size), np.float32)
    for region in ("face", "head_neck"):
        sl = rig.regions[region].triangle_slice
        centre = neutral[rig.triangles[sl]].mean(1)  # [K, 3]
        hairline_y = brow_y + 0.055 - 0.35 * np.clip(0.09 - centre[:, 2], 0, None) - 0.25 * np.abs(centre[:, 0])
        is_hair = (centre[:, 1] > hairline_y) & (centre[:, 1] > -0.02)
        for tri_uv in rig.uv[rig.triangles_uv[sl][is_hair]]:
            pts = np.round(np.stack([tri_uv[:, 0] * size, (1 - tri_uv[:, 1]) * size], -1) * 16).astype(np.int32)
            cv2.fillPoly(canvas, pts[None], 1.0, lineType=cv2.LINE_AA, shift=4)
    # Grow the mask a little: triangles along UV-island borders are only partly covered by
    # anti-aliased filling, which would leave a skin-coloured seam across the scalp.
    grow = max(1, size // 64)
    canvas = cv2.dilate(canvas, np.ones((2 * grow + 1, 2 * grow + 1), np.uint8))
    return cv2.GaussianBlur(canvas, (0, 0), size / 150)
