"""``lightcal``: the 3D position (and axis) of every LED bar from mirror-sphere takes.

Images come from ``calib/mirror/<cam>/`` or, where the capture has them, from its native-
resolution windows (``calib/mirror_roi.json``; ``mirror_take.MirrorTake`` serves both alike).

1. Ball silhouettes in ``calib/mirror/<cam>/<silhouette image>`` (room light, bars off) give,
   with the calibrated cameras and the known radius, every ball's centre (tangent-cone fit
   per camera, then a joint least-squares fit over all cameras).
2. In ``calib/mirror/<cam>/bar<b>.exr`` the bar's highlight on each ball is found (a streak:
   its ends and its ridge, the centre line); the viewing ray through the ridge's middle is
   reflected off the ball. Highlights near the rim (grazing) are dropped past
   ``max_incidence_deg`` and weighted down by cos(incidence)^power before it.
3. The bar's centre is the point closest to all its reflected rays (robustly reweighted),
   slid along the bar to the middle of its triangulated ends; its axis comes from the
   streaks' ends. With balls large enough in the images, the line through it is refined so
   that the rays reflected all along every streak's ridge meet it (least squares).

Outputs ``bars.json`` (the truth schema: id, center_world, axis_world, length_m, intensity,
normal_world, plus per-bar fit statistics), ``spheres.json`` and ``report.json``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext, StageParams
from scene.camera import Camera
from stages.calibrate.output import CalibrateOutput
from stages.capture.output import CaptureOutput
from stages.lightcal.highlights import Highlight, find_highlight, reflect_ray, reflect_rays
from stages.lightcal.mirror_take import MirrorTake, read_grey
from stages.lightcal.output import LightcalOutput
from stages.lightcal.solve import conditioning, ray_distances, ray_line_distances, robust_closest_point
from stages.lightcal.spheres import (Silhouette, cone_centre, find_silhouettes,
                                     group_estimates, refine_centre)


class LightcalParams(StageParams):
    """Light calibration settings."""

    min_snr: float = Field(12.0, gt=0, description="A highlight must rise this many noise sigmas above the background.")
    max_incidence_deg: float = Field(
        50.0, gt=0, lt=90, description="Highlights (and ridge points) nearer the ball's rim than this incidence angle are ignored.")
    incidence_weight_power: float = Field(
        2.0, ge=0, description="Rays reflected near a ball's rim (grazing) are weighted by cos(incidence)^power in "
        "the fits: there the ball's image is compressed, so a pixel of error turns the reflected ray by 1/cos "
        "times more (power 2 = inverse variance; 0 = equal weights).")
    min_rays: int = Field(3, ge=2, description="Fewest highlights (ball x camera) needed to place a bar.")
    min_elongation: float = Field(1.5, ge=1, description="Long/short axis ratio above which a highlight gives the bar's axis.")
    per_camera_centres: bool = Field(
        True, description="Move each ball's centre onto the camera's own silhouette axis before reflecting its "
        "highlights (cancels that camera's small pose error).")
    centre_from: Literal["ends", "midpoints"] = Field(
        "midpoints", description="Bar centre as the middle of its two triangulated ends, or the point nearest the "
        "mid-streak rays slid along the bar to the ends' middle.")
    line_fit: Literal["auto", "off", "offset", "line"] = Field(
        "auto", description="Refine the bar so that the rays reflected at points all along every streak's ridge "
        "meet its line: 'offset' moves it across its axis, 'line' also tilts the axis, 'off' keeps the mid-streak "
        "estimate; the centre along the bar stays the ends' middle. 'auto': 'offset' when the balls are at least "
        "line_fit_min_ball_px in radius in the images (native resolution), else 'off' (short noisy ridges).")
    line_fit_min_ball_px: float = Field(
        50.0, gt=0, description="Median ball radius in pixels from which line_fit 'auto' refines the bar's line.")
    use_windows: bool = Field(
        True, description="Use the mirror take's native-resolution windows (calib/mirror_roi.json) where the "
        "capture has them; False: the full images only.")
    allow_missing_bars: bool = Field(
        False, description="Leave out (with a warning) bars that cannot be placed instead of failing.")


def _load_mirror_spec(capture: CaptureOutput) -> dict:
    spec = capture.mirror_spec()
    try:
        float(spec["radius_m"])
    except (KeyError, ValueError, TypeError) as err:
        raise capture.malformed(capture.mirror_spec_path, f"no mirror-sphere radius_m ({err!r})") from err
    return spec


def _grey(path: Path) -> np.ndarray:
    return read_grey(path)


def _at_mirror_resolution(cams: dict[str, Camera], capture: CaptureOutput, image_name: str) -> dict[str, Camera]:
    """The calibrated cameras at the resolution of their mirror take (it may be shot at native resolution).

    ``Camera.scaled`` keeps the pixel-centre convention, so this is exact, not an approximation.
    """
    out = {}
    for name, cam in cams.items():
        path = capture.mirror_image_path(name, image_name)
        if not path.is_file():
            out[name] = cam
            continue
        h, w = _grey(path).shape
        if (w, h) == (cam.width, cam.height):
            out[name] = cam
            continue
        scaled = cam.scaled(w / cam.width)
        if (scaled.width, scaled.height) != (w, h):
            raise InputError(f"{path}: {w}x{h} mirror image, but camera {name} is calibrated at "
                             f"{cam.width}x{cam.height} (another aspect ratio); the take does not match the camera")
        out[name] = scaled
    return out


def locate_spheres(cams: dict[str, Camera], capture: CaptureOutput, image_name: str, radius_m: float, count: int, log,
                   take: MirrorTake | None = None
                   ) -> tuple[list[np.ndarray], dict[tuple[str, int], Silhouette], list[float]]:
    """Ball centres in world space and, per (camera, ball), the silhouette seen.

    ``take`` serves the images (native windows where the capture has them); default: the full images.
    """
    take = MirrorTake(capture, use_windows=False) if take is None else take
    per_cam: list[tuple[str, Silhouette, np.ndarray]] = []
    for name, cam in cams.items():
        loaded = take.image(name, Path(image_name).stem)
        if loaded is None:
            log.warning("%s: no silhouette image %s; camera not used for the balls", name,
                        capture.mirror_image_path(name, image_name))
            continue
        grey, bg, sigma = loaded
        sils, notes = find_silhouettes(grey, name, noise=(bg, sigma))
        for note in notes:
            log.info("%s %s: %s", name, image_name, note)
        for s in sils:
            centre, _ = cone_centre(cam, s.outline_px, radius_m)
            per_cam.append((name, s, centre))
    groups = group_estimates([(i, c) for i, (_, _, c) in enumerate(per_cam)], radius_m)
    groups = [g for g in groups if len({per_cam[i][0] for i in g}) >= 2]
    if not groups:
        raise InputError(f"no mirror ball was found in two or more cameras (calib/mirror/<cam>/{image_name}); "
                         "check that the balls are in view and lit by the room light")
    if count and len(groups) != count:
        log.warning("found %d mirror balls seen by two or more cameras, calib/mirror.json says %d",
                    len(groups), count)
    centres, sil_of, rms = [], {}, []
    for k, g in enumerate(sorted(groups, key=lambda g: -len(g))):
        init = np.mean([per_cam[i][2] for i in g], axis=0)
        c, r = refine_centre([cams[per_cam[i][0]] for i in g], [per_cam[i][1].outline_px for i in g], radius_m, init)
        centres.append(c)
        rms.append(r)
        for i in g:
            sil_of[(per_cam[i][0], k)] = per_cam[i][1]
        log.info("ball %d: centre %s m, seen by %d cameras, outline RMS %.3f mm", k, np.round(c, 4), len(g), 1e3 * r)
    return centres, sil_of, rms


def run(ctx: StageContext) -> None:
    """Place every LED bar (see the module docstring)."""
    params: LightcalParams = ctx.params  # type: ignore[assignment]
    capture = CaptureOutput(ctx.input("capture"))
    cams = {c.name: c for c in CalibrateOutput(ctx.input("calibrate")).cameras()}
    spec = _load_mirror_spec(capture)
    radius = float(spec["radius_m"])
    image_name = str(spec.get("silhouette_image", "room.exr"))
    take = MirrorTake(capture, params.use_windows)
    cams = take.cameras(cams, _at_mirror_resolution(cams, capture, image_name))
    windowed = sum(take.has_windows(n) for n in cams)
    if windowed:
        ctx.log.info("mirror take: native %dx%d windows for %d of %d cameras", *take.native_size, windowed, len(cams))
    centres, sil_of, sphere_rms = locate_spheres(cams, capture, image_name, radius, int(spec.get("count", 0)), ctx.log,
                                                 take)
    bar_ids = [int(b) for b in spec.get("bars", [])] or capture.mirror_bar_ids()
    if not bar_ids:
        raise InputError(f"{capture.mirror_dir}: no bar images (bar<b:02d>.exr); the mirror take is missing")

    # per camera and ball: the centre used to reflect (optionally on the camera's own silhouette axis)
    centre_for: dict[tuple[str, int], np.ndarray] = {}
    for (name, k), sil in sil_of.items():
        c = centres[k]
        if params.per_camera_centres:
            _, axis = cone_centre(cams[name], sil.outline_px, radius)
            c = cams[name].center_world + ((c - cams[name].center_world) @ axis) * axis
        centre_for[(name, k)] = c

    bars_out, report, failures = [], {}, []
    with ctx.progress(len(bar_ids), "bars") as progress:
        for b in bar_ids:
            entry, info = _solve_bar(b, cams, take, sil_of, centre_for, radius, params, ctx.log)
            report[f"bar{b:02d}"] = info
            if entry is None:
                failures.append(f"bar {b}: {info['error']}")
            else:
                bars_out.append(entry)
            progress.advance(1)
    if failures:
        message = "; ".join(failures)
        if not params.allow_missing_bars:
            raise InputError(f"cannot place {len(failures)} bar(s): {message}. Check the mirror take "
                             "(calib/mirror/<cam>/bar<b>.exr), or set lightcal.allow_missing_bars to leave them out")
        ctx.log.warning("bars left out: %s", message)

    head = np.mean(centres, axis=0)
    for entry in bars_out:
        n = head - np.asarray(entry["center_world"])
        entry["normal_world"] = (n / np.linalg.norm(n)).tolist()
    out = LightcalOutput(ctx.out)
    out.write_bars(bars_out, [int(f.split(":")[0][4:]) for f in failures])
    out.write_spheres({"radius_m": radius, "centers_world": [c.tolist() for c in centres], "outline_rms_m": sphere_rms})
    out.write_report(report)
    residuals = [e["residual_mm"] for e in bars_out]
    ctx.metrics["residual_mm_mean"] = float(np.mean(residuals)) if residuals else float("nan")
    ctx.metrics["residual_mm_max"] = float(np.max(residuals)) if residuals else float("nan")
    ctx.metrics["bars"] = len(bars_out)
    ctx.metrics["bars_missing"] = len(failures)
    ctx.metrics["spheres"] = len(centres)
    ctx.metrics["cameras_with_windows"] = windowed
    ctx.metrics["sphere_outline_rms_mm_max"] = 1e3 * float(max(sphere_rms))
    ctx.metrics["highlights_used_mean"] = float(np.mean([e["rays"] for e in bars_out])) if bars_out else 0.0


def _solve_bar(b: int, cams: dict[str, Camera], take: MirrorTake, sil_of: dict[tuple[str, int], Silhouette],
               centre_for: dict[tuple[str, int], np.ndarray], radius: float, params: LightcalParams, log
               ) -> tuple[dict | None, dict]:
    """Find bar ``b``'s highlights, reflect them, and place the bar; (bars.json entry or None, report)."""
    rays: list[tuple[np.ndarray, np.ndarray, Highlight, Camera, np.ndarray, float]] = []  # (point, dir, hl, cam, ball, incidence deg)
    seen_saturated, saturated_in_windows, images = 0, 0, 0
    for name, cam in cams.items():
        loaded = take.image(name, f"bar{b:02d}")
        if loaded is None:
            continue
        images += 1
        grey, bg, sigma = loaded
        white = float(grey.max()) if np.mean(grey >= grey.max() * (1 - 1e-4)) * grey.size >= 4 else None
        for (cname, k), sil in sil_of.items():
            if cname != name:
                continue
            uv_c, _ = cam.project(centre_for[(name, k)])
            hl = find_highlight(grey, uv_c, sil.radius_px, bg, sigma, params.min_snr, white, name, k)
            if hl is None:
                continue
            # the ridge midpoint lies on the streak; the centroid of a curved streak does not
            hit = reflect_ray(cam, hl.mid_px if hl.mid_px is not None else hl.centroid_px, centre_for[(name, k)],
                              radius)
            if hit is None or hit[2] > params.max_incidence_deg:
                continue
            if hl.saturated and take.has_windows(name):
                saturated_in_windows += 1
            elif hl.saturated:
                seen_saturated += 1
            rays.append((hit[0], hit[1], hl, cam, centre_for[(name, k)], hit[2]))
    info: dict = {"images": images, "highlights": len(rays), "saturated": seen_saturated + saturated_in_windows}
    if saturated_in_windows:
        # at native resolution the sub-pixel streak fills more of a pixel and may clip; clipping is
        # symmetric across the streak, so its ridge (which places the bar) is unbiased
        log.info("bar %d: %d highlight(s) clipped at the white level in the native windows", b, saturated_in_windows)
    if seen_saturated:
        log.warning("bar %d: %d highlight(s) over-exposed (clipped at the white level); centroids are less "
                    "accurate: lower the exposure of the mirror take", b, seen_saturated)
    if images == 0:
        info["error"] = "no mirror images (calib/mirror/<cam>/bar%02d.exr)" % b
        return None, info
    if len(rays) < params.min_rays:
        info["error"] = (f"highlight found in only {len(rays)} ball view(s) of {images} camera images "
                         f"(needs {params.min_rays}); is the bar lit in calib/mirror/<cam>/bar{b:02d}.exr?")
        return None, info
    points = np.stack([r[0] for r in rays])
    dirs = np.stack([r[1] for r in rays])
    if conditioning(dirs) < 1e-4:
        info["error"] = "its reflected rays are nearly parallel (cannot triangulate)"
        return None, info
    prior = _incidence_weights(np.array([r[5] for r in rays]), params.incidence_weight_power)
    centre, weights = robust_closest_point(points, dirs, prior=prior)
    dist = ray_distances(centre, points, dirs)
    axis, length, elongated = _axis_and_length(rays, centre, radius, params.min_elongation)
    method = "centroids"
    if elongated >= params.min_rays:
        refined = _refine_with_endpoints(rays, centre, axis, radius, params)
        if refined is not None:
            centre, axis, length, dist, weights = refined
            method = "streak ends"
            mode = params.line_fit
            if mode == "auto":
                ball_px = float(np.median([sil.radius_px for sil in sil_of.values()]))
                mode = "offset" if ball_px >= params.line_fit_min_ball_px else "off"
            if mode != "off":
                fitted = _fit_bar_line(rays, centre, axis, radius, mode == "line", params)
                if fitted is not None:
                    centre, axis, dist, weights = fitted
                    method = "ridge line fit"
    info.update({"residual_mm": 1e3 * float(np.average(dist, weights=weights)), "elongated": elongated,
                 "rays_downweighted": int(np.sum(weights < 0.5)), "method": method})
    entry = {"id": b, "center_world": centre.tolist(), "axis_world": axis.tolist(), "length_m": length,
             "intensity": 1.0, "residual_mm": info["residual_mm"], "rays": len(rays),
             "axis_from_highlights": elongated > 0}
    log.info("bar %d: centre %s m from %d highlights, residual %.1f mm", b, np.round(centre, 4), len(rays),
             info["residual_mm"])
    return entry, info


def _incidence_weights(incidence_deg: np.ndarray, power: float) -> np.ndarray:
    """Per-ray weights cos(incidence)^power [N]: grazing reflections are the least certain."""
    return np.cos(np.radians(np.asarray(incidence_deg, float))) ** power


def _fit_bar_line(rays, centre: np.ndarray, axis: np.ndarray, radius: float, free_axis: bool,
                  params: LightcalParams):
    """Least-squares bar line from the rays reflected at points along every highlight's ridge.

    Each ridge point's reflected ray meets the bar's axis line somewhere along it; the mid-streak
    rays alone meet it at different points, so the point nearest to them sits off the line
    (across the bar, by centimetres for side bars). Here the line (2 offsets across it, 2 axis
    tilts) minimises the ray-to-line distances (soft L1); the ridge spans most of the bar, which
    pins the line's direction (a line along the ray bundle would not meet them all). The
    centre keeps its position along the line. Returns (centre, axis, mid-ray distances, weights) or None.
    """
    from scipy.optimize import least_squares

    from stages.lightcal.solve import ray_line_distances

    origins, dirs, incidence = [], [], []
    for _, _, hl, cam, ball, _ in rays:
        if hl.ridge_px is None or len(hl.ridge_px) < 3:
            continue
        hit, p, refl, inc = reflect_rays(cam, hl.ridge_px, ball, radius)
        keep = hit & (np.nan_to_num(inc, nan=90.0) <= params.max_incidence_deg)
        origins.append(p[keep])
        dirs.append(refl[keep])
        incidence.append(inc[keep])
    if sum(len(o) for o in origins) < 12:
        return None
    o, d = np.concatenate(origins), np.concatenate(dirs)  # [M, 3]
    # residuals scaled by sqrt(weight): least squares with cos^power weights
    sqrt_w = np.sqrt(_incidence_weights(np.concatenate(incidence), params.incidence_weight_power))  # [M]
    # a frame around the current line: u, v across it
    u = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)

    def line(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if len(x) == 2:
            return centre + x[0] * u + x[1] * v, axis
        a = axis + x[2] * u + x[3] * v
        return centre + x[0] * u + x[1] * v, a / np.linalg.norm(a)

    def residual(x: np.ndarray) -> np.ndarray:
        p, a = line(x)
        return sqrt_w * ray_line_distances(o, d, p, a)

    n_free = 4 if free_axis else 2
    fit = least_squares(residual, np.zeros(n_free), loss="soft_l1", f_scale=0.003, x_scale=0.01)
    p, a = line(fit.x)
    # keep the centre's place along the bar: the point of the new line nearest the old centre
    p = p + ((centre - p) @ a) * a
    if a[np.argmax(np.abs(a))] < 0:
        a = -a
    points = np.stack([r[0] for r in rays])
    dirs_mid = np.stack([r[1] for r in rays])
    dist = ray_line_distances(points, dirs_mid, p, a)
    w = 1.0 / (1.0 + (dist / (2 * 1.4826 * max(float(np.median(dist)), 1e-6))) ** 2)
    w = w * _incidence_weights(np.array([r[5] for r in rays]), params.incidence_weight_power)
    return p, a, dist, w


def _refine_with_endpoints(rays, centre: np.ndarray, axis: np.ndarray, radius: float, params: LightcalParams):
    """Slide the centre along the bar to halfway between the images of its ends; axis from the ends.

    The point nearest the mid-streak rays is right across the bar but may sit off its middle
    along it (the mirror maps the bar non-linearly); each view's two end rays pass the bar's
    two ends, so halfway between them is the middle. A free 3D line fit is avoided on
    purpose: the rays leave a few small balls in similar directions, and a line along
    them fits them all. Returns (centre, axis, length_m, ray distances, ray weights) or None.
    """
    from stages.lightcal.solve import closest_param_on_line

    centre_from = params.centre_from
    ends, end_weights = [], []
    for p, d, hl, cam, ball, _ in rays:
        if hl.endpoints_px is None:
            continue
        hits = [reflect_ray(cam, e, ball, radius) for e in hl.endpoints_px]
        if all(h is not None for h in hits):
            ends.append((np.stack([h[0] for h in hits]), np.stack([h[1] for h in hits])))
            end_weights.append(_incidence_weights(np.array([h[2] for h in hits]), params.incidence_weight_power))
    if len(ends) < 2:
        return None
    # axis: the scatter of end-to-end directions (sign-free), through the current centre
    vecs = []
    for pts, dirs in ends:
        near = pts + np.maximum(((centre - pts) * dirs).sum(-1), 0.0)[:, None] * dirs
        v = near[1] - near[0]
        if np.linalg.norm(v) > 1e-6:
            vecs.append(v / np.linalg.norm(v))
    if vecs:
        scatter = sum(np.outer(v, v) for v in vecs)
        axis = np.linalg.eigh(scatter)[1][:, -1]
    # triangulate the bar's two ends: label each view's end rays by the side of the centre they meet
    end_rays: dict[int, list[tuple[np.ndarray, np.ndarray, float]]] = {0: [], 1: []}
    for (pts, dirs), ew in zip(ends, end_weights):
        sp = closest_param_on_line(pts, dirs, centre, axis)
        order = (0, 1) if sp[0] < sp[1] else (1, 0)
        for side, k in zip(order, (0, 1)):
            end_rays[side].append((pts[k], dirs[k], float(ew[k])))
    end_points = [robust_closest_point(np.stack([e[0] for e in end_rays[side]]),
                                       np.stack([e[1] for e in end_rays[side]]),
                                       prior=np.array([e[2] for e in end_rays[side]]))[0] for side in (0, 1)]
    v = end_points[1] - end_points[0]
    length = float(np.linalg.norm(v))
    if centre_from == "ends":
        axis = v / max(length, 1e-9)
        centre_new = 0.5 * (end_points[0] + end_points[1])
    else:  # "midpoints": keep the mid-streak point across the bar, take the ends' middle along it
        mids = [0.5 * sum(closest_param_on_line(pts, dirs, centre, axis)) for pts, dirs in ends]
        centre_new = centre + float(np.median(mids)) * axis
    points = np.stack([r[0] for r in rays])
    dirs_all = np.stack([r[1] for r in rays])
    dist = ray_line_distances(points, dirs_all, centre_new, axis)
    w = 1.0 / (1.0 + (dist / (2 * 1.4826 * max(float(np.median(dist)), 1e-6))) ** 2)
    w = w * _incidence_weights(np.array([r[5] for r in rays]), params.incidence_weight_power)
    if axis[np.argmax(np.abs(axis))] < 0:
        axis = -axis
    return centre_new, axis, length, dist, w


def _axis_and_length(rays, centre: np.ndarray, radius: float, min_elongation: float
                     ) -> tuple[np.ndarray, float, int]:
    """Bar axis (unit [3]) and length from the elongated highlights; (axis, length_m, highlights used).

    The highlight's long axis, at +-sigma around its centroid, reflects into two rays; their
    points nearest the bar centre span the bar's sigma along its axis (a uniform segment of
    length L has sigma L / sqrt(12)).
    """
    dirs, sigmas, weights = [], [], []
    for _, _, hl, cam, ball, _ in rays:
        if hl.sigma_major_px < min_elongation * max(hl.sigma_minor_px, 1e-6):
            continue
        ends = []
        for sgn in (-1.0, 1.0):
            hit = reflect_ray(cam, hl.centroid_px + sgn * hl.sigma_major_px * hl.major_px, ball, radius)
            if hit is None:
                break
            p, d, _ = hit
            ends.append(p + max((centre - p) @ d, 0.0) * d)
        if len(ends) < 2:
            continue
        v = ends[1] - ends[0]
        if np.linalg.norm(v) < 1e-6:
            continue
        dirs.append(v / np.linalg.norm(v))
        sigmas.append(0.5 * np.linalg.norm(v))
        weights.append(hl.sigma_major_px / max(hl.sigma_minor_px, 1e-6))
    if not dirs:
        return np.array([0.0, 1.0, 0.0]), float("nan"), 0
    dirs_a = np.stack(dirs)
    w = np.asarray(weights)
    # sign-free average: the principal eigenvector of the weighted scatter of directions
    scatter = (w[:, None, None] * dirs_a[:, :, None] * dirs_a[:, None, :]).sum(0)
    axis = np.linalg.eigh(scatter)[1][:, -1]
    if axis[np.argmax(np.abs(axis))] < 0:
        axis = -axis
    return axis, float(np.sqrt(12.0) * np.median(sigmas)), len(dirs)


STAGE = Stage(name="lightcal", inputs=("capture", "calibrate"), params=LightcalParams, run=run,
              doc="LED bar positions from their highlights in mirror spheres.")
