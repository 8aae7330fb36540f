"""The ChArUco board spec (``calib/board.json``) and corner detection with frame quality checks."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.errors import InputError
from scene.camera import Rigid
from stages.capture.output import CaptureOutput


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board as written in ``calib/board.json`` (metres)."""

    squares_x: int
    squares_y: int
    square_m: float
    marker_m: float
    dictionary: str
    reference_pose_index: int
    world_from_board_reference: Rigid

    def cv_board(self):
        """The OpenCV ``CharucoBoard``."""
        import cv2

        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_m, self.marker_m, dictionary)

    def corners_board(self) -> np.ndarray:
        """Inner chessboard corners in the board frame, metres [N, 3], indexed by ChArUco id."""
        return np.asarray(self.cv_board().getChessboardCorners(), dtype=np.float64)


def load_board_spec(capture: CaptureOutput, log=None) -> BoardSpec:
    """Read the capture's board spec (``CaptureOutput.board_spec``); errors name the file and the key.

    ``world_from_board_reference`` is the board's known fixture pose in the studio world at
    ``reference_pose_index``; without it the board is assumed upright at the origin, facing +z.
    """
    import cv2

    path = capture.board_spec_path
    d = capture.board_spec()
    for key in ("squares_x", "squares_y", "square_m", "marker_m", "dictionary"):
        if key not in d:
            raise InputError(f"{path}: board spec lacks '{key}'; it needs squares_x, squares_y, square_m, "
                             "marker_m, dictionary")
    if not hasattr(cv2.aruco, str(d["dictionary"])):
        raise InputError(f"{path}: unknown ArUco dictionary '{d['dictionary']}' (use an OpenCV name like DICT_4X4_50)")
    if "world_from_board_reference" in d:
        ref = Rigid(np.asarray(d["world_from_board_reference"]["R"], float),
                    np.asarray(d["world_from_board_reference"]["t"], float))
    else:
        if log is not None:
            log.warning("%s: no 'world_from_board_reference'; the world frame is the first board pose, "
                        "centred at the origin, printed side facing +z", path)
        R = np.diag([1.0, -1.0, -1.0])
        half = np.array([d["squares_x"] * d["square_m"] / 2, d["squares_y"] * d["square_m"] / 2, 0.0])
        ref = Rigid(R, -R @ half)
    return BoardSpec(int(d["squares_x"]), int(d["squares_y"]), float(d["square_m"]), float(d["marker_m"]),
                     str(d["dictionary"]), int(d.get("reference_pose_index", 0)), ref)


@dataclass(frozen=True)
class Detection:
    """ChArUco corners found in one image."""

    frame: int
    ids: np.ndarray  # [N] int, ChArUco corner ids
    corners_px: np.ndarray  # [N, 2] float64, sub-pixel image positions


@dataclass(frozen=True)
class FrameVerdict:
    """Why a frame was or was not used (for the per-camera report)."""

    frame: int
    used: bool
    reason: str
    corners: int = 0
    edge_width_px: float = float("nan")


def _to_uint8(grey: np.ndarray) -> np.ndarray:
    """Linear grey -> 8-bit, normalised by a high percentile and gamma-encoded (what the detector expects)."""
    scale = max(float(np.percentile(grey, 99.5)), 1e-6)
    return np.clip(np.sqrt(np.clip(grey / scale, 0, 1)) * 255 + 0.5, 0, 255).astype(np.uint8)


def saturated_fraction(grey: np.ndarray) -> float:
    """Fraction of pixels at the image's maximum value (a clipped sensor piles values there)."""
    top = float(grey.max())
    if top <= 0:
        return 0.0
    return float(np.mean(grey >= top * (1 - 1e-3)))


def edge_width_px(grey: np.ndarray, corners_px: np.ndarray, radius: int) -> float:
    """Median edge width (contrast / steepest gradient) around the corners, pixels; ~1-2 when sharp."""
    import cv2

    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    mag = np.hypot(gx, gy)
    widths = []
    h, w = grey.shape
    for x, y in np.round(corners_px).astype(int):
        x0, x1, y0, y1 = max(x - radius, 0), min(x + radius + 1, w), max(y - radius, 0), min(y + radius + 1, h)
        patch = grey[y0:y1, x0:x1]
        if patch.size < 9:
            continue
        contrast = float(np.percentile(patch, 95) - np.percentile(patch, 5))
        steepest = float(mag[y0:y1, x0:x1].max())
        if steepest > 0 and contrast > 0:
            widths.append(contrast / steepest)
    return float(np.median(widths)) if widths else float("inf")


def global_edge_width_px(grey: np.ndarray) -> float:
    """Image contrast over its steepest gradients, pixels: ~1-2 for a sharp print, large when blurred.

    Zero for an image without content (contrast under 20 noise sigmas).
    """
    import cv2

    lo, hi = np.percentile(grey, [0.5, 99.5])
    # noise from neighbour differences: robust to a board covering most of the image
    sigma = 1.4826 * float(np.median(np.abs(np.diff(grey, axis=1)))) / np.sqrt(2.0)
    if hi - lo < 20 * max(sigma, 1e-6):
        return 0.0

    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    steep = float(np.percentile(np.hypot(gx, gy), 99.9))
    return float(hi - lo) / max(steep, 1e-12)


def saddle_refine(grey: np.ndarray, corners_px: np.ndarray, radius_px: float, step_px: float = 0.5,
                  iterations: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel chessboard corners as the saddle points of a local quadratic fit [N, 2], and a keep mask [N].

    A blurred X-junction is point-symmetric about the corner (also under perspective, which
    is locally affine), so it is a critical point of the image; a weighted quadratic fitted on
    a window re-centred at each estimate converges to it. OpenCV's ``cornerSubPix`` (gradient
    orthogonality on the pixel grid) leaves ~0.1 px biases on such corners; this fit leaves
    ~0.02 px. A corner is dropped when the fit is not a saddle, its window has no contrast, or
    it wanders more than 1.5 px away.
    """
    from scipy.ndimage import map_coordinates

    off = np.arange(-radius_px, radius_px + 1e-9, step_px)
    dy, dx = (g.ravel() for g in np.meshgrid(off, off, indexing="ij"))  # [S] sample offsets
    w = np.exp(-(dx ** 2 + dy ** 2) / (2 * (0.6 * radius_px) ** 2))  # [S]
    design = np.stack([dx * dx, dx * dy, dy * dy, dx, dy, np.ones_like(dx)], -1) * w[:, None]  # [S, 6]
    solve = np.linalg.pinv(design)  # [6, S]
    start = np.asarray(corners_px, np.float64).reshape(-1, 2)
    out = start.copy()  # [N, 2]
    det = np.zeros(len(out))
    for _ in range(iterations):
        xs, ys = out[:, :1] + dx[None], out[:, 1:] + dy[None]  # [N, S]
        vals = map_coordinates(grey, [ys.ravel(), xs.ravel()], order=3, mode="nearest").reshape(xs.shape)
        a, b, c, d, e = (solve @ (vals * w[None]).T)[:5]  # each [N]
        det = 4 * a * c - b * b
        safe = np.where(np.abs(det) < 1e-12, -1e-12, det)
        delta = np.stack([(b * e - 2 * c * d) / safe, (b * d - 2 * a * e) / safe], -1)
        out += np.clip(delta, -1.0, 1.0)
    contrast = vals.max(axis=1) - vals.min(axis=1)  # [N] a flat patch fits a noise "saddle"
    ok = (det < 0) & (np.linalg.norm(out - start, axis=1) < 1.5) & (contrast > 0.1 * float(np.ptp(grey)))
    return out, ok


class CharucoFinder:
    """Detects board corners in linear images, refines them, and rejects bad frames."""

    def __init__(self, spec: BoardSpec, min_corners: int, max_saturated_fraction: float,
                 max_edge_width_px: float) -> None:
        import cv2

        self.spec = spec
        self.board = spec.cv_board()
        self.detector = cv2.aruco.CharucoDetector(self.board)
        self.min_corners = min_corners
        self.max_saturated_fraction = max_saturated_fraction
        self.max_edge_width_px = max_edge_width_px

    def find(self, image: np.ndarray, frame: int) -> tuple[Detection | None, FrameVerdict]:
        """Corners in one image [H, W, C] (linear); None with a reason when the frame is unusable."""
        import cv2

        grey = np.ascontiguousarray(image[..., :3].mean(axis=-1) if image.ndim == 3 else image, dtype=np.float32)
        sat = saturated_fraction(grey)
        if sat > self.max_saturated_fraction:
            return None, FrameVerdict(frame, False, f"over-exposed ({100 * sat:.0f}% of pixels at the white level)")
        corners, ids, _, _ = self.detector.detectBoard(_to_uint8(grey))
        if ids is None or len(ids) < self.min_corners:
            n = 0 if ids is None else len(ids)
            # say "blurred" rather than "not found" when the image has contrast but only soft edges
            width = global_edge_width_px(grey)
            if width > self.max_edge_width_px:
                return None, FrameVerdict(frame, False, f"blurred (edge width {width:.1f} px > "
                                          f"{self.max_edge_width_px}; board not found)", n, width)
            return None, FrameVerdict(frame, False, f"board not found ({n} corners < {self.min_corners})", n)
        corners = corners.reshape(-1, 2).astype(np.float64)
        ids = ids.ravel()
        # refine on the linear image: 8-bit quantisation and gamma would bias the saddle point
        square_px = self._square_px(corners, ids)
        # the window must stay inside the white rim around the markers, or marker edges pull the corner
        rim_px = square_px * (self.spec.square_m - self.spec.marker_m) / (2 * self.spec.square_m)
        half = int(np.clip(np.floor(rim_px), 2, 8))
        refined, ok = saddle_refine(grey / max(float(grey.max()), 1e-6), corners, float(np.clip(0.7 * rim_px, 1.5, 6.0)))
        if int(ok.sum()) < self.min_corners:
            return None, FrameVerdict(frame, False, f"board not found ({int(ok.sum())} corners refine to a saddle "
                                      f"< {self.min_corners})", int(ok.sum()))
        corners_px, ids = refined[ok], ids[ok]
        width = edge_width_px(grey, corners_px, max(half, 3))
        if width > self.max_edge_width_px:
            return None, FrameVerdict(frame, False, f"blurred (edge width {width:.1f} px > {self.max_edge_width_px})",
                                      len(ids), width)
        return (Detection(frame, ids.astype(np.int64), corners_px),
                FrameVerdict(frame, True, "ok", len(ids), width))

    def _square_px(self, corners_px: np.ndarray, ids: np.ndarray) -> float:
        """Typical square size in pixels (nearest-corner spacing)."""
        if len(corners_px) < 2:
            return 8.0
        d = np.linalg.norm(corners_px[:, None] - corners_px[None], axis=-1)
        d[d == 0] = np.inf
        return float(np.median(d.min(axis=1)))
