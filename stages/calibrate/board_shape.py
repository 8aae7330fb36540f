"""The board's shape as the bundle adjustment refines it: which corners fix the gauge, and how far off nominal it is.

A print is never exactly nominal (a little off scale, corners tens of microns off, the mounted
board bowed). With ``calibrate.board_shape: refined`` the bundle adjustment moves the board's
corners (one board, shared by every pose), as ``cv2.calibrateCameraRO`` does. The cameras
cannot tell a uniformly larger board from a rig that stands farther away, nor a moved board
frame from moved board poses, so three corners stay at their nominal places: two at the ends
of the first row (their distance sets the scale) and the corner diagonally opposite the first
(with them it fixes the board frame's origin and orientation, and the board's plane through
its outermost corners, which is where the mount holds a bowed board).
"""

from __future__ import annotations

import numpy as np


def gauge_corner_ids(corners_board: np.ndarray) -> list[int]:
    """Ids of the corners held at nominal: the first row's two ends and the corner opposite the first.

    ``corners_board`` [N, 3] in the board frame (z = 0). The first corner is the one with the
    smallest x + y; the first row is the corners at its y (to 1 um).
    """
    xy = corners_board[:, :2]
    first = int(np.argmin(xy.sum(axis=1)))
    row = np.flatnonzero(np.abs(xy[:, 1] - xy[first, 1]) < 1e-6)
    row_end = int(row[np.argmax(xy[row, 0])])
    opposite = int(np.argmax(xy.sum(axis=1)))
    return [first, row_end, opposite]


def bow_m(points_board: np.ndarray, nominal_board: np.ndarray) -> float:
    """How far the board's centre stands out of its rim, towards the camera (board -z), metres.

    Fits z = a + b x + c y + d r^2 over the points [N, 3] (r from the nominal corners' centre,
    so a tilt of the fitted plane does not count as bow) and returns the paraboloid's depth at
    the outermost nominal corner, d r_max^2: positive when the centre is nearer the camera.
    """
    centre_xy = 0.5 * (nominal_board[:, :2].min(axis=0) + nominal_board[:, :2].max(axis=0))
    d_xy = nominal_board[:, :2] - centre_xy
    r2 = np.sum(d_xy ** 2, axis=1)
    design = np.column_stack([np.ones(len(r2)), d_xy, r2])
    coeff, *_ = np.linalg.lstsq(design, points_board[:, 2], rcond=None)
    return float(coeff[3] * r2.max())


def shift_m_max(points_board: np.ndarray, nominal_board: np.ndarray) -> float:
    """Largest distance of a refined corner from its nominal place [N, 3] -> metres."""
    return float(np.linalg.norm(points_board - nominal_board, axis=1).max())


def scale_err_pct(points_board: np.ndarray, nominal_board: np.ndarray, axis: int) -> float:
    """Refined board's scale along a board axis (0 = x, 1 = y) against nominal, percent: the slope of refined on nominal."""
    nominal = nominal_board[:, axis] - nominal_board[:, axis].mean()
    refined = points_board[:, axis] - points_board[:, axis].mean()
    return float(100.0 * (np.dot(nominal, refined) / np.dot(nominal, nominal) - 1.0))
