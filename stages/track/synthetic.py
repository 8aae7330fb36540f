"""Synthetic tracking scenes with known answers, for tests and the stability benchmark.

An actor rig from the ICT model (a few expression shapes), a known landmark embedding on
the front of the face, a ring of cameras, and landmark pixels projected from known head
poses and weights, with Gaussian noise and far-off outliers. No images are involved.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scene.camera import Camera, look_at
from scene.face_rig import load_face_rig
from stages.track.embedding import LandmarkEmbedding
from stages.track.geometry import so3_exp
from stages.track.rig import ActorRig

SHAPES = ("jawOpen", "mouthSmile_L", "mouthSmile_R", "browInnerUp_L", "eyeBlink_L", "mouthPucker")


@dataclass
class SyntheticScene:
    """Ground truth of a synthetic scene: rig, embedding, cameras, per-frame pose and weights."""

    rig: ActorRig
    skin_triangles: np.ndarray
    embedding: LandmarkEmbedding
    cameras: list[Camera]
    times_s: np.ndarray  # [F]
    R: np.ndarray  # [F, 3, 3] world_from_head
    t: np.ndarray  # [F, 3]
    weights: np.ndarray  # [F, K]

    def landmarks_world(self, f: int) -> np.ndarray:
        verts = self.rig.mesh(self.weights[f])
        return self.embedding.points(self.rig.faces, verts) @ self.R[f].T + self.t[f]

    def project(self, noise_px: float = 0.0, outlier_rate: float = 0.0, seed: int = 0) -> np.ndarray:
        """Landmark pixels [F, C, N, 2] with Gaussian noise and uniform far-off (+-40 px) outliers."""
        rng = np.random.default_rng(seed)
        F, C, N = len(self.times_s), len(self.cameras), len(self.embedding.landmark_ids)
        uv = np.zeros((F, C, N, 2))
        for f in range(F):
            X = self.landmarks_world(f)
            for c, cam in enumerate(self.cameras):
                uv[f, c], _ = cam.project(X)
        uv += rng.normal(0.0, noise_px, uv.shape)
        out = rng.random((F, C, N)) < outlier_rate
        uv[out] += rng.uniform(-40.0, 40.0, (int(out.sum()), 2))
        return uv


def make_scene(frames: int = 8, landmarks: int = 100, cameras: int = 6, seed: int = 1) -> SyntheticScene:
    """A scene of ``frames`` frames (neutral first, smooth motion at 8 key frames per second),
    ``landmarks`` random skin points on the front of the face, ``cameras`` cameras 1 m away
    spread over 100 degrees of azimuth."""
    rng = np.random.default_rng(seed)
    ict = load_face_rig()
    basis = np.stack([ict.expression_deltas_m[ict.expression_index(n)] for n in SHAPES]).astype(np.float64)
    rig = ActorRig(SHAPES, ict.neutral_m.astype(np.float64), basis, ict.triangles.astype(np.int64))
    skin = ict.region_triangles(["face"])
    centres = rig.neutral_m[rig.faces[skin]].mean(1)
    front = skin[centres[:, 2] > 0.05]
    tri = rng.choice(front, landmarks, replace=False)
    emb = LandmarkEmbedding(np.arange(landmarks), tri, rng.dirichlet([2.0, 2.0, 2.0], landmarks))
    target = np.array([0.0, 0.0, 0.05])
    cams = []
    for k in range(cameras):
        az = np.radians(-50 + 100 * k / max(cameras - 1, 1))
        el = np.radians(12 * ((k % 3) - 1))
        eye = target + np.array([np.sin(az) * np.cos(el), np.sin(el), np.cos(az) * np.cos(el)])
        cams.append(Camera(f"cam{k:02d}", 400, 300, 700.0, 700.0, 199.5, 149.5, dist=(-0.05, 0.01, 0, 0, 0),
                           pose=look_at(eye, target)))
    times = np.arange(frames) / 8.0
    weights = np.clip(0.5 + 0.5 * np.sin(times[:, None] * np.arange(1, 7)[None] + np.arange(6)[None]), 0, 1)
    weights[0] = 0.0  # the actor starts neutral
    R = np.stack([so3_exp(np.radians([3 * np.sin(s), 4 * np.sin(0.7 * s), np.cos(s)])) for s in times])
    t = np.stack([[0.003 * np.sin(s), 0.002, 0.004 * np.cos(s)] for s in times])
    return SyntheticScene(rig, skin, emb, cams, times, R, t, weights)
