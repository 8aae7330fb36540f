"""2D face landmarks with MediaPipe FaceMesh (``mediapipe==0.10.14``, whose wheel ships its
TFLite models), on linear HDR images, with per-view confidence and rejection.

The detector sees an sRGB uint8 image: the linear EXR is exposure-normalised (a high
percentile of luminance mapped to ``exposure_target``) and sRGB-encoded, so a dim OLAT-like
or a hot image both reach the network in its usual range. MediaPipe reports normalised
coordinates over the continuous image ``[0, W] x [0, H]``; our cameras put pixel centres at
integer coordinates, so ``u = x * W - 0.5``.

A view is rejected (status other than ``"ok"``) when no face is found, when the face
detector's score is below threshold, or when the landmark spread is implausible (too
small, too large, mostly outside the image, degenerate shape).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from pipeline.itemcache import touch_entry
from scene.colour import luminance, srgb8

NUM_FACEMESH_LANDMARKS = 468

# Index groups of the 468 FaceMesh landmarks (from the FaceMesh topology's named contours).
LANDMARK_GROUPS: dict[str, tuple[int, ...]] = {
    "contour": (10, 21, 54, 58, 67, 93, 103, 109, 127, 132, 136, 148, 149, 150, 152, 162, 172, 176,
                234, 251, 284, 288, 297, 323, 332, 338, 356, 361, 365, 377, 378, 379, 389, 397, 400, 454),
    "eyes": (7, 33, 133, 144, 145, 153, 154, 155, 157, 158, 159, 160, 161, 163, 173, 246,
             249, 263, 362, 373, 374, 380, 381, 382, 384, 385, 386, 387, 388, 390, 398, 466),
    "brows": (46, 52, 53, 55, 63, 65, 66, 70, 105, 107, 276, 282, 283, 285, 293, 295, 296, 300, 334, 336),
    "nose": (1, 2, 4, 5, 6, 19, 45, 48, 64, 94, 97, 98, 115, 168, 195, 197, 220, 275, 278, 294, 326, 327,
             344, 440),
    "lips_outer": (0, 17, 37, 39, 40, 61, 84, 91, 146, 181, 185, 267, 269, 270, 291, 314, 321, 375, 405, 409),
    "lips_inner": (13, 14, 78, 80, 81, 82, 87, 88, 95, 178, 191, 308, 310, 311, 312, 317, 318, 324, 402, 415),
    "all": tuple(range(NUM_FACEMESH_LANDMARKS)),
}


def landmark_subset(groups: tuple[str, ...]) -> np.ndarray:
    """Sorted unique FaceMesh indices of the named groups (see ``LANDMARK_GROUPS``)."""
    unknown = [g for g in groups if g not in LANDMARK_GROUPS]
    if unknown:
        raise ValueError(f"unknown landmark group(s) {unknown}; allowed: {sorted(LANDMARK_GROUPS)}")
    return np.array(sorted({i for g in groups for i in LANDMARK_GROUPS[g]}), dtype=np.int64)


class DetectorParams(BaseModel):
    """Settings of the MediaPipe landmark detector and its per-view rejection."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    exposure_percentile: float = Field(99.0, gt=0, le=100, description="Luminance percentile mapped to exposure_target before sRGB encoding.")
    exposure_target: float = Field(0.8, gt=0, le=1, description="Linear value the exposure percentile is mapped to.")
    min_detection_score: float = Field(0.5, ge=0, le=1, description="Views whose MediaPipe face-detection score is below this are rejected.")
    min_face_fraction: float = Field(0.05, gt=0, description="Reject a view whose landmark box is smaller than this fraction of the image's shorter side.")
    max_face_fraction: float = Field(1.5, gt=0, description="Reject a view whose landmark box is larger than this fraction of the image's shorter side.")
    min_inside_fraction: float = Field(0.6, gt=0, le=1, description="Reject a view with fewer than this fraction of landmarks inside the image.")
    refine_landmarks: bool = Field(False, description="Use FaceMesh's attention model (refined eyes and lips, 478 points; slower).")


@dataclass(frozen=True)
class ViewLandmarks:
    """Landmarks detected in one image.

    Attributes:
        uv_px: landmark pixels [468, 2] (our pixel-centre convention); nan when rejected.
        score: the face detector's confidence in [0, 1] (0 when no face).
        status: ``"ok"`` or why the view was rejected.
        contour_px: the foreground's outer contour [M, 2] (image pixels), for the
            silhouette term of the pose (``stages.track.silhouette``); empty when none.
    """

    uv_px: np.ndarray
    score: float
    status: str
    contour_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def to_detector_image(linear_rgb: np.ndarray, params: DetectorParams) -> np.ndarray | None:
    """Linear RGB [H, W, 3] -> exposure-normalised sRGB uint8 [H, W, 3]; None when black."""
    rgb = np.nan_to_num(np.asarray(linear_rgb, dtype=np.float32)[..., :3], nan=0.0, posinf=0.0, neginf=0.0)
    lum = luminance(np.maximum(rgb, 0.0))
    level = float(np.percentile(lum, params.exposure_percentile))
    if level <= 1e-8:
        return None
    return srgb8(rgb, params.exposure_target / level)


class FaceMeshDetector:
    """MediaPipe FaceDetection (for a score) + FaceMesh (468 landmarks), single images."""

    def __init__(self, params: DetectorParams):
        import warnings

        import mediapipe as mp  # heavy import, only where detection actually runs

        # mediapipe 0.10.14 calls a protobuf API that protobuf 4.25 marks deprecated.
        warnings.filterwarnings("ignore", message="SymbolDatabase.GetPrototype", category=UserWarning)
        self.params = params
        self._mesh = mp.solutions.face_mesh.FaceMesh(
            static_image_mode=True, max_num_faces=1, refine_landmarks=params.refine_landmarks,
            min_detection_confidence=min(params.min_detection_score, 0.5))
        self._faces = mp.solutions.face_detection.FaceDetection(model_selection=0, min_detection_confidence=0.05)

    def close(self) -> None:
        self._mesh.close()
        self._faces.close()

    def __enter__(self) -> "FaceMeshDetector":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def detect(self, linear_rgb: np.ndarray) -> ViewLandmarks:
        """Landmarks of the (single) face in a linear RGB image [H, W, 3]."""
        from stages.track.silhouette import image_contour

        nan = np.full((NUM_FACEMESH_LANDMARKS, 2), np.nan)
        contour = image_contour(linear_rgb)
        image = to_detector_image(linear_rgb, self.params)
        if image is None:
            return ViewLandmarks(nan, 0.0, "black image")
        H, W = image.shape[:2]
        faces = self._faces.process(image)
        score = max((float(d.score[0]) for d in (faces.detections or [])), default=0.0)
        mesh = self._mesh.process(image)
        if not mesh.multi_face_landmarks:
            return ViewLandmarks(nan, score, "no face", contour)
        pts = mesh.multi_face_landmarks[0].landmark
        uv = np.array([[p.x * W - 0.5, p.y * H - 0.5] for p in pts[:NUM_FACEMESH_LANDMARKS]], dtype=np.float64)
        status = check_spread(uv, W, H, self.params)
        if status == "ok" and score < self.params.min_detection_score:
            status = f"low score {score:.2f}"
        return ViewLandmarks(uv if status == "ok" else nan, score, status, contour)


def check_spread(uv_px: np.ndarray, width: int, height: int, params: DetectorParams) -> str:
    """``"ok"`` when a landmark set [N, 2] has a plausible size, shape and visibility, else why not."""
    lo, hi = np.nanmin(uv_px, axis=0), np.nanmax(uv_px, axis=0)
    box_w, box_h = hi - lo
    short = float(min(width, height))
    size = max(box_w, box_h) / short
    if size < params.min_face_fraction:
        return f"face too small ({size:.3f} of the image)"
    if size > params.max_face_fraction:
        return f"face too large ({size:.2f} of the image)"
    aspect = box_h / max(box_w, 1e-6)
    if not 0.25 <= aspect <= 4.0:
        return f"degenerate landmark spread (aspect {aspect:.2f})"
    inside = np.mean((uv_px[:, 0] >= 0) & (uv_px[:, 0] <= width - 1) & (uv_px[:, 1] >= 0) & (uv_px[:, 1] <= height - 1))
    if inside < params.min_inside_fraction:
        return f"face mostly outside the image ({inside:.0%} of landmarks inside)"
    return "ok"


def _cache_key(path: Path, params: DetectorParams) -> str:
    """Content hash of an image file and the detector settings (BLAKE3)."""
    import blake3

    digest = blake3.blake3(Path(path).read_bytes())
    digest.update(params.model_dump_json().encode())
    digest.update(b"facemesh-0.10.14+contour-v1")  # bump when detection or outline code changes
    return digest.hexdigest()


def _load_cached(cache_file: Path) -> ViewLandmarks | None:
    try:
        with np.load(cache_file, allow_pickle=False) as data:
            return ViewLandmarks(np.asarray(data["uv_px"]), float(data["score"]), str(data["status"]),
                                 np.asarray(data["contour_px"]))
    except (OSError, ValueError, KeyError):  # a corrupt cache entry is a miss
        return None


def _store_cached(cache_file: Path, result: ViewLandmarks) -> None:
    tmp = cache_file.with_name(cache_file.name + ".tmp.npz")
    np.savez(tmp, uv_px=result.uv_px, score=result.score, status=result.status, contour_px=result.contour_px)
    tmp.replace(cache_file)  # atomic: a killed run never leaves half an entry


def detect_files(job: tuple[list[Path], DetectorParams, Path | None]) -> list[ViewLandmarks]:
    """Detect landmarks in a list of EXR files with one detector (a picklable executor job).

    ``job`` = (paths, params, cache folder or None). With a cache folder, results are kept
    per image content and settings, so re-running the stage with other fit settings does
    not run the detector again.
    """
    from scene.image_io import read_exr

    paths, params, cache_dir = job
    results: list[ViewLandmarks] = []
    detector: FaceMeshDetector | None = None
    try:
        for path in paths:
            cache_file = None
            if cache_dir is not None and Path(path).is_file():
                cache_file = Path(cache_dir) / f"{_cache_key(path, params)}.npz"
                cached = _load_cached(cache_file) if cache_file.is_file() else None
                if cached is not None:
                    touch_entry(cache_file)
                    results.append(cached)
                    continue
            try:
                image = read_exr(path)
            except ValueError as err:  # a corrupt frame loses one view, not the whole capture
                results.append(ViewLandmarks(np.full((NUM_FACEMESH_LANDMARKS, 2), np.nan), 0.0,
                                             f"unreadable image ({err})"))
                continue
            if detector is None:
                detector = FaceMeshDetector(params)
            result = detector.detect(image)
            if cache_file is not None:
                _store_cached(cache_file, result)
            results.append(result)
    finally:
        if detector is not None:
            detector.close()
    return results
