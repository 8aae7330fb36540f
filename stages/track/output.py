"""The track stage's output folder: the one place that spells its file names.

Files::

    tracking.npz     index [T], time_s [T], full_on [T], fitted [T], weights [T, K],
                     expression_names [K], world_from_head_R [T, 3, 3], world_from_head_t [T, 3],
                     landmark_reproj_px [T]
    meshes.npz       index [T], vertices [T, V, 3] float32 head space (metres), faces [F, 3]
    embedding.npz    landmark_ids [N], triangles [N], barycentric [N, 3]
    landmarks.npz    the detections (index, cameras, uv_px, score, status, contour_px, contour_count)
    cameras.json     the calibrated cameras the fit used (``scene.camera.save_cameras``)
    obj/<index:06d>.obj   a few frames' meshes
    overlay.png      detected and fitted landmarks over a few frames

A missing or malformed file raises one ``InputError`` naming it and saying to rerun track.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.stage_output import StageOutput
from scene.camera import Camera, load_cameras, save_cameras

_TRACKING = "tracking.npz"
_MESHES = "meshes.npz"
_EMBEDDING = "embedding.npz"
_LANDMARKS = "landmarks.npz"
_CAMERAS = "cameras.json"
_OBJ = "obj"
_OVERLAY = "overlay.png"

#: The names no module outside ``stages/track`` may spell (``tests/test_output_contracts.py``).
CONTRACT_NAMES = (_TRACKING, _MESHES, _EMBEDDING, _LANDMARKS, _CAMERAS, _OVERLAY)


class TrackOutput(StageOutput):
    """The ``track`` object: per-frame head pose and expression, the head-space meshes."""

    stage = "track"

    @property
    def tracking_path(self) -> Path:
        return self.file(_TRACKING)

    def tracking(self, keys: tuple[str, ...] = ("index", "world_from_head_R", "world_from_head_t")
                 ) -> dict[str, np.ndarray]:
        """``tracking.npz``: every array; it must hold ``keys``."""
        return self.read_npz(_TRACKING, keys=keys)

    def write_tracking(self, **arrays: np.ndarray) -> None:
        np.savez_compressed(self.tracking_path, **arrays)

    @property
    def meshes_path(self) -> Path:
        return self.file(_MESHES)

    def meshes(self, keys: tuple[str, ...] = ("vertices",)) -> dict[str, np.ndarray]:
        """``meshes.npz``: ``index`` [T], ``vertices`` [T, V, 3] head space, ``faces``."""
        return self.read_npz(_MESHES, keys=keys)

    def write_meshes(self, index: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> None:
        np.savez(self.meshes_path, index=index, vertices=vertices, faces=faces)

    def embedding(self) -> dict[str, np.ndarray]:
        return self.read_npz(_EMBEDDING, keys=("landmark_ids", "triangles", "barycentric"))

    def write_embedding(self, landmark_ids: np.ndarray, triangles: np.ndarray, barycentric: np.ndarray) -> None:
        np.savez(self.file(_EMBEDDING), landmark_ids=landmark_ids, triangles=triangles, barycentric=barycentric)

    def landmarks(self) -> dict[str, np.ndarray]:
        return self.read_npz(_LANDMARKS, keys=("index", "cameras", "uv_px"))

    def write_landmarks(self, **arrays: np.ndarray) -> None:
        np.savez_compressed(self.file(_LANDMARKS), **arrays)

    @property
    def cameras_path(self) -> Path:
        return self.file(_CAMERAS)

    def cameras(self) -> list[Camera]:
        """The calibrated cameras the fit used."""
        return self.load(self.cameras_path, lambda path: load_cameras(path, "world"))

    def write_cameras(self, cameras: list[Camera]) -> None:
        save_cameras(self.cameras_path, cameras)

    def make_obj_dir(self) -> None:
        self.file(_OBJ).mkdir()

    def obj_path(self, index: int) -> Path:
        return self.file(_OBJ, f"{int(index):06d}.obj")

    @property
    def overlay_path(self) -> Path:
        return self.file(_OVERLAY)
