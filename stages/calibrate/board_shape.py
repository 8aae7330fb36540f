"""The board's shape as the bundle adjustment refines it: which corners fix the gauge, and how far off nominal it is.

A print is never exactly nominal (a little off scale, corners tens of microns off, the mounted
board bowed). With ``calibrate.board_shape: refined`` the bundle adjustment moves the board's
corners (one board, shared by every pose), as ``cv2.calibrateCameraRO`` does. The cameras
cannot tell a uniformly larger board from a rig that stands farther away, nor a moved board
frame from moved board poses (7 unknowns: scale, rotation, translation). So the two ends of
the first row stay at their nominal places (6 unknowns, their distance the scale), and after
the adjustment the board frame is put back on the nominal board (``board_from_refined``),
which takes the last one, the roll about that row. Holding a third corner too would also
fix the print's y scale and squareness at nominal, which the cameras do see: it left 3.5-7x the
focal error on a misprinted board (smoke preset; the tests' take).
"""

from __future__ import annotations

import numpy as np

from scene.camera import Rigid


def gauge_corner_ids(corners_board: np.ndarray) -> list[int]:
    """Ids of the corners held at nominal: the two ends of the first row.

    ``corners_board`` [N, 3] in the board frame (z = 0). The first corner is the one with the
    smallest x + y; the first row is the corners at its y (to 1 um).
    """
    xy = corners_board[:, :2]
    first = int(np.argmin(xy.sum(axis=1)))
    row = np.flatnonzero(np.abs(xy[:, 1] - xy[first, 1]) < 1e-6)
    row_end = int(row[np.argmax(xy[row, 0])])
    return [first, row_end]


def board_from_refined(points_refined: np.ndarray, nominal_board: np.ndarray) -> Rigid:
    """The rigid motion that puts the refined corners [N, 3] back on the nominal board frame.

    The rotation and translation that best fit them to their nominal places (least squares, no
    scale: the scale is the gauge corners'), then a shift along the board's normal so that the
    fitted bow (``bow_m``'s paraboloid) is at z = 0 at the outermost corners, where the board's
    plane is for a board bowing out of its mount, as the nominal board frame has it.
    """
    centre_refined, centre_nominal = points_refined.mean(axis=0), nominal_board.mean(axis=0)
    cov = (nominal_board - centre_nominal).T @ (points_refined - centre_refined)
    u, _, vt = np.linalg.svd(cov)
    flip = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ flip @ vt
    fitted = Rigid(rotation, centre_nominal - rotation @ centre_refined)
    rim_z = _paraboloid_rim_z(fitted.apply(points_refined), nominal_board)
    return Rigid(rotation, fitted.t - np.array([0.0, 0.0, rim_z]))


def _paraboloid_fit(points_board: np.ndarray, nominal_board: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares z = a + b x + c y + d r^2 over the points (r from the nominal corners' centre): (a, b, c, d), r_max^2."""
    centre_xy = 0.5 * (nominal_board[:, :2].min(axis=0) + nominal_board[:, :2].max(axis=0))
    d_xy = nominal_board[:, :2] - centre_xy
    r2 = np.sum(d_xy ** 2, axis=1)
    design = np.column_stack([np.ones(len(r2)), d_xy, r2])
    coeff, *_ = np.linalg.lstsq(design, points_board[:, 2], rcond=None)
    return coeff, float(r2.max())


def _paraboloid_rim_z(points_board: np.ndarray, nominal_board: np.ndarray) -> float:
    """The fitted paraboloid's z at the outermost corners' radius, over the board's centre."""
    coeff, r2_max = _paraboloid_fit(points_board, nominal_board)
    return float(coeff[0] + coeff[3] * r2_max)


def bow_m(points_board: np.ndarray, nominal_board: np.ndarray) -> float:
    """How far the board's centre stands out of its rim, towards the camera (board -z), metres.

    Fits z = a + b x + c y + d r^2 over the points [N, 3] (r from the nominal corners' centre,
    so a tilt of the fitted plane does not count as bow) and returns the paraboloid's depth at
    the outermost nominal corner, d r_max^2: positive when the centre is nearer the camera.
    """
    coeff, r2_max = _paraboloid_fit(points_board, nominal_board)
    return float(coeff[3] * r2_max)


def shift_m_max(points_board: np.ndarray, nominal_board: np.ndarray) -> float:
    """Largest distance of a refined corner from its nominal place [N, 3] -> metres."""
    return float(np.linalg.norm(points_board - nominal_board, axis=1).max())


def scale_err_pct(points_board: np.ndarray, nominal_board: np.ndarray, axis: int) -> float:
    """Refined board's scale along a board axis (0 = x, 1 = y) against nominal, percent: the slope of refined on nominal."""
    nominal = nominal_board[:, axis] - nominal_board[:, axis].mean()
    refined = points_board[:, axis] - points_board[:, axis].mean()
    return float(100.0 * (np.dot(nominal, refined) / np.dot(nominal, nominal) - 1.0))
