"""The ChArUco board as it was really printed and mounted (``realism: real``).

A print is scaled a little off nominal (differently along x and y), its corners sit a few
tens of microns off their places and the mounted board bows. The calibration only knows the
nominal board (``calib/board.json``), so these errors stay in its reprojection residuals and
its scale, as with a real print.

Board frame as in ``hardware.studio.calibration_takes`` (origin at the chessboard's top-left
corner, x right, y down the page, z into the board, metres). ``printed position`` = where a
point of the nominal artwork ended up on the physical board:

    printed(x) = c + (1 + scale_error) * (x - c) + jitter(x)          (in the board plane)
    z(x)       = -bow * (1 - |x - c|^2 / r_corner^2)                  (towards the camera)
                 - twist * (x - c)_x (x - c)_y / (h_x h_y)

with c the chessboard's centre, jitter bilinear between per-corner offsets, r_corner the
centre-to-corner distance (so the corners lie in z = 0, the centre ``bow`` in front) and h the
half size (so the twist lifts two opposite corners by ``twist`` and lowers the other two).
The print's own bow is one value; in each pose the board flexes a little more or less and
twists (``BoardPrint.flex_m``), the same for every camera that films that pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import map_coordinates

from hardware.studio.camera_effects import BoardPrint


@dataclass(frozen=True)
class PrintedBoard:
    """One physical print of a nominal board."""

    size_m: np.ndarray  # [2] nominal chessboard width, height
    square_m: float
    scale: np.ndarray  # [2] 1 + scale error along x, y
    corner_jitter_m: np.ndarray  # [squares_y + 1, squares_x + 1, 2] print offset of every square corner
    bow_m: float
    twist_m: float = 0.0

    @property
    def center_m(self) -> np.ndarray:
        return 0.5 * self.size_m

    def jitter_at(self, xy_nominal: np.ndarray) -> np.ndarray:
        """Print offset [..., 2] at nominal board points [..., 2]: bilinear between the corners, clamped outside."""
        grid = np.stack([xy_nominal[..., 1] / self.square_m, xy_nominal[..., 0] / self.square_m])  # (row, col)
        return np.stack([map_coordinates(self.corner_jitter_m[..., c], grid, order=1, mode="nearest")
                         for c in range(2)], axis=-1)

    def printed_xy(self, xy_nominal: np.ndarray) -> np.ndarray:
        """Where nominal artwork points [..., 2] lie on the physical board (its plane coordinates)."""
        c = self.center_m
        return c + self.scale * (xy_nominal - c) + self.jitter_at(xy_nominal)

    def nominal_xy(self, xy_printed: np.ndarray) -> np.ndarray:
        """The artwork point [..., 2] printed at physical board points [..., 2] (the texture lookup).

        Inverts ``printed_xy`` by one fixed-point step: the jitter's slope is ~1e-3 (tens of microns
        over a 40 mm square), so the step leaves ~1e-3 of the jitter, < 0.1 um (1/4000 of a native
        pixel on the board).
        """
        c = self.center_m
        xy = c + (xy_printed - c) / self.scale
        return c + (xy_printed - self.jitter_at(xy) - c) / self.scale

    def surface_z(self, xy_printed: np.ndarray) -> np.ndarray:
        """Board-frame z [...] of the bowed surface above physical plane points [..., 2] (negative = towards the camera)."""
        offset = xy_printed - self.center_m
        r2 = np.sum(offset ** 2, axis=-1)
        bowed = -self.bow_m * (1.0 - r2 / float(np.sum(self.center_m ** 2)))
        return bowed - self.twist_m * offset[..., 0] * offset[..., 1] / float(np.prod(self.center_m))

    def printed_points(self, points_nominal: np.ndarray) -> np.ndarray:
        """Nominal board points [N, 3] (z = 0) where they really are [N, 3] on the bowed print."""
        xy = self.printed_xy(np.asarray(points_nominal, float)[:, :2])
        return np.concatenate([xy, self.surface_z(xy)[:, None]], axis=1)


def print_board(squares_x: int, squares_y: int, square_m: float, spec: BoardPrint,
                pose_index: int | None = None) -> PrintedBoard:
    """One print of a ``squares_x`` x ``squares_y`` board of ``square_m`` squares with ``spec``'s errors.

    ``pose_index``: the board as it is in that pose of the take, flexed by its own draw of
    ``spec.flex_m`` (seeded by the print and the pose, so every camera sees the same shape);
    None is the print at rest (no flex).
    """
    rng = np.random.default_rng([spec.seed, 4242])
    jitter = rng.normal(0.0, spec.corner_jitter_m, size=(squares_y + 1, squares_x + 1, 2))
    bow, twist = float(spec.bow_m), 0.0
    if pose_index is not None and spec.flex_m > 0:
        extra_bow, twist = np.random.default_rng([spec.seed, 4243, int(pose_index)]).normal(0.0, spec.flex_m, 2)
        bow += float(extra_bow)
    return PrintedBoard(np.array([squares_x * square_m, squares_y * square_m]), float(square_m),
                        1.0 + np.asarray(spec.scale_error, float), jitter, bow, float(twist))
