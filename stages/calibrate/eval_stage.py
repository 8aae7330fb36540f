"""``calibrate_eval``: the calibrated cameras against the virtual studio's true cameras.

Intrinsics are compared at the performance resolution (``calibrate/cameras.json`` and the
truth's ``cameras.json``, e.g. 240x320 at the tiny preset); ``principal_err_px_max_native``
repeats the principal point comparison at the board images' (native) resolution, with the
true cameras scaled there. Both are in the studio world (the calibration fixes its world by the board's fixture pose),
so the errors are taken directly. ``volume_reproj_err_px_*`` is the pixel distance
between the true and calibrated projections of points filling the capture volume: the
error downstream stages see. A similarity fit (Umeyama, camera centres) is reported
beside them: ``world_alignment_mm`` (how far the calibrated world is from the true one)
and the errors after that fit, which isolate the rig's internal accuracy.
"""

from __future__ import annotations

import numpy as np

from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext, StageParams
from scene.camera import Camera
from stages.calibrate.output import CalibrateOutput
from stages.capture.output import CaptureTruth


class CalibrateEvalParams(StageParams):
    """No settings: the comparison is fixed."""


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity ``dst ~ s * R @ src + t`` (least squares) for points [N, 3]; returns s, R [3, 3], t [3]."""
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    xs, xd = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(xd.T @ xs / len(src))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    var = (xs ** 2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var) if var > 0 else 1.0
    return s, R, mu_d - s * R @ mu_s


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle of the rotation taking ``Rb`` to ``Ra``, degrees."""
    c = (np.trace(Ra @ Rb.T) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def volume_reprojection_px(est: dict[str, Camera], true: dict[str, Camera], half_size_m: float = 0.15,
                           steps: int = 7) -> dict[str, float]:
    """Pixel distance between true and calibrated projections of a grid filling the capture volume.

    What downstream stages feel: a camera whose principal point and rotation err together
    (nearly interchangeable for narrow lenses, and both trade with tangential distortion)
    can still project every point of the volume where it belongs. The volume is centred
    where the true optical axes pass closest (the head).
    """
    names = [n for n in true if n in est]
    origins = np.stack([true[n].center_world for n in names])
    dirs = np.stack([true[n].forward_world for n in names])
    proj = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]
    centre = np.linalg.solve(proj.sum(0), (proj @ origins[:, :, None]).sum(0)[:, 0])
    axis = np.linspace(-half_size_m, half_size_m, steps)
    grid = centre + np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    errs = []
    for n in names:
        uv_t, _ = true[n].project(grid)
        uv_e, _ = est[n].project(grid)
        errs.append(float(np.linalg.norm(uv_e - uv_t, axis=1).max()))
    return {"volume_reproj_err_px_max": max(errs), "volume_reproj_err_px_mean": float(np.mean(errs))}


def camera_errors(est: dict[str, Camera], true: dict[str, Camera]) -> dict[str, float]:
    """Worst-camera errors of intrinsics and poses, direct and after a similarity fit of centres."""
    names = [n for n in true if n in est]
    focal = [100 * max(abs(est[n].fx / true[n].fx - 1), abs(est[n].fy / true[n].fy - 1)) for n in names]
    principal = [float(np.hypot(est[n].cx - true[n].cx, est[n].cy - true[n].cy)) for n in names]
    centre = [1000 * float(np.linalg.norm(est[n].center_world - true[n].center_world)) for n in names]
    rot = [rotation_angle_deg(est[n].cam_from_world.R, true[n].cam_from_world.R) for n in names]
    metrics = {"focal_err_pct_max": max(focal), "focal_err_pct_mean": float(np.mean(focal)),
               "principal_err_px_max": max(principal), "center_err_mm_max": max(centre),
               "center_err_mm_mean": float(np.mean(centre)), "rotation_err_deg_max": max(rot),
               "cameras_compared": len(names)}
    if len(names) >= 3:
        src = np.stack([est[n].center_world for n in names])
        dst = np.stack([true[n].center_world for n in names])
        s, R, t = umeyama(src, dst)
        aligned = s * src @ R.T + t
        metrics["center_err_mm_max_aligned"] = 1000 * float(np.linalg.norm(aligned - dst, axis=1).max())
        metrics["rotation_err_deg_max_aligned"] = max(
            rotation_angle_deg(est[n].cam_from_world.R @ R.T, true[n].cam_from_world.R) for n in names)
        metrics["world_alignment_mm"] = 1000 * float(np.linalg.norm(src - aligned, axis=1).max())
        metrics["world_alignment_scale_err_pct"] = 100 * abs(s - 1)
    metrics.update(volume_reprojection_px(est, true))
    return metrics


def run(ctx: StageContext) -> None:
    """Compare ``calibrate/cameras.json`` with ``capture.truth/cameras.json``."""
    calibrated, truth = CalibrateOutput(ctx.input("calibrate")), CaptureTruth(ctx.input("capture.truth"))
    est_path, true_path = calibrated.cameras_path, truth.cameras_path
    est = {c.name: c for c in calibrated.cameras()}
    true = {c.name: c for c in truth.cameras()}
    missing = sorted(set(true) - set(est))
    if missing:
        ctx.log.warning("cameras %s are not in the calibration (dropped); compared the rest", ", ".join(missing))
    if not set(true) & set(est):
        raise InputError(f"{est_path}: no camera in common with the ground truth {true_path}")
    metrics = camera_errors(est, true)
    metrics["cameras_missing"] = len(missing)
    if calibrated.has_cameras_native():
        native = {c.name: c for c in calibrated.cameras_native()}
        metrics["principal_err_px_max_native"] = max(
            float(np.hypot(c.cx - t.cx, c.cy - t.cy))
            for n, c in native.items() if n in true
            for t in [true[n].scaled(c.width / true[n].width)])
        metrics["calibration_width_px"] = next(iter(native.values())).width
    metrics["compared_width_px"] = next(iter(true.values())).width
    ctx.metrics.update(metrics)
    for key, value in metrics.items():
        ctx.log.info("%s = %.4g", key, value)


STAGE = Stage(name="calibrate_eval", inputs=("calibrate", "capture.truth"), params=CalibrateEvalParams, run=run,
              evaluates="calibrate", doc="Camera calibration accuracy against ground truth.")
