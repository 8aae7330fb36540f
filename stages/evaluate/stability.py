"""The stability sweeps over loaded data: renders of the model and the studio, their PSNR and the limits.

``measure_stability`` is pure over an ``EvaluationInputs`` and the params (it reads and writes
no files); ``stages.evaluate.stage`` describes the two sweeps.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from pipeline.errors import InputError
from pipeline.stage import Progress
from stages.evaluate.inputs import EvaluationInputs
from stages.evaluate.measure import sweep_psnr
from stages.evaluate.params import EvaluateParams
from stages.evaluate.sweeps import (Crossing, angle_to_nearest_deg, azimuth_limit_deg, extrapolation_limit_deg,
                                    orbit_directions, scale_limits, unit)

#: One sample's renders, per camera: (model rgb, truth rgb, truth alpha), [H, W, 3] / [H, W] linear.
SampleRenders = list[tuple[np.ndarray, np.ndarray, np.ndarray]]


@dataclass
class OrbitSweep:
    """The light orbit's result.

    Attributes:
        curves: per plane, (orbit angles, angles from the nearest training light, PSNR), degrees / dB.
        limit: where PSNR first falls under ``threshold_db`` going away from the training lights.
        azimuth: how far round from the front (the worse side) the horizontal orbit stays above it.
        threshold_db: the threshold; ``reference_db`` the in-distribution PSNR it may be relative to.
        samples: every light position's record (``sweeps.json``).
        strip_truth, strip_pred: truth and exposure-matched model images of the first camera every
            ``strip_every_deg`` of the horizontal orbit.
    """

    curves: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]
    limit: Crossing
    azimuth: Crossing
    threshold_db: float
    reference_db: float
    samples: list[dict[str, Any]]
    strip_truth: list[np.ndarray]
    strip_pred: list[np.ndarray]

    @property
    def all_from_training_deg(self) -> np.ndarray:
        return np.concatenate([c[1] for c in self.curves.values()])

    @property
    def all_psnr_db(self) -> np.ndarray:
        return np.concatenate([c[2] for c in self.curves.values()])


@dataclass
class ExpressionSweep:
    """The expression magnitude sweep's result: PSNR per weight scale and the scales where it breaks."""

    scales: np.ndarray
    psnr_db: np.ndarray
    threshold_db: float
    reference_db: float
    low: Crossing
    high: Crossing

    def samples(self) -> list[dict[str, float]]:
        return [{"scale": float(s), "psnr_db": float(v)} for s, v in zip(self.scales, self.psnr_db)]


@dataclass
class StabilityResults:
    """Both sweeps, the head's centre and the training light directions they were measured against."""

    centre: np.ndarray
    train_dirs: np.ndarray
    orbit: OrbitSweep
    expression: ExpressionSweep
    model_seconds: float
    truth_seconds: float

    def samples(self) -> dict[str, Any]:
        """Every sample of both sweeps (``sweeps.json``)."""
        return {"light_orbit": self.orbit.samples, "expression_scale": self.expression.samples(),
                "light_orbit_azimuth_limit_deg": self.orbit.azimuth.x}

    def metrics(self) -> dict[str, float]:
        orbit, expr = self.orbit, self.expression
        all_from, all_psnr = orbit.all_from_training_deg, orbit.all_psnr_db
        return {
            "light_extrapolation_limit_deg": orbit.limit.x,
            "light_extrapolation_censored": float(orbit.limit.censored),
            "light_orbit_azimuth_limit_deg": orbit.azimuth.x,  # how far round from the front, the worse side
            "light_threshold_db": orbit.threshold_db,
            "light_orbit_psnr_mean": float(np.mean(all_psnr)),
            "light_orbit_psnr_min": float(np.min(all_psnr)),
            "light_orbit_psnr_near_training": orbit.reference_db,
            "light_orbit_max_from_training_deg": float(np.max(all_from)),
            "light_orbit_points": int(all_psnr.size),
            "expression_scale_limit_low": expr.low.x,
            "expression_scale_limit_high": expr.high.x,
            "expression_scale_censored_low": float(expr.low.censored),
            "expression_scale_censored_high": float(expr.high.censored),
            "expression_threshold_db": expr.threshold_db,
            "expression_psnr_at_scale_1": expr.reference_db,
            "expression_psnr_min": float(np.min(expr.psnr_db)),
            "model_render_seconds": self.model_seconds,
            "truth_render_seconds": self.truth_seconds,
        }


def measure_stability(data: EvaluationInputs, params: EvaluateParams,
                      progress: Callable[[int, str], Progress]) -> StabilityResults:
    """Both sweeps: the light orbit on a training frame's mesh, the expression scales on a held-out frame's."""
    from avatar.render import decode
    from scene.view import ViewSpec

    mesh_index, truth_row, splits = data.mesh_index, data.truth_row, data.splits
    common = [i for i in mesh_index if i in truth_row]
    if not common:
        raise InputError("evaluate: no frame is both in track/meshes.npz and capture.truth/frames.npz; "
                         "re-run track on this capture")
    orbit_frame = next((i for i in splits.get("train", []) if i in truth_row and i in mesh_index), common[0])
    held_out = next((i for s in ("novel_perf", "novel_both") for i in splits.get(s, [])
                     if i in truth_row and i in mesh_index), common[-1])
    tracked = data.vertices[mesh_index.index(held_out)]
    if tracked.shape != data.neutral_scan.shape:
        raise InputError(f"evaluate: tracked meshes have {tracked.shape[0]} vertices but the neutral scan has "
                         f"{data.neutral_scan.shape[0]}; re-run track on this capture")
    orbit_mesh = data.vertices[mesh_index.index(orbit_frame)]
    centre = orbit_mesh.mean(0).astype(float)  # [3] head space
    train_dirs = unit(data.training_lights_head - centre)

    view = ViewSpec(params.width_px, params.height_px, params.camera_distance_m, params.fov_deg, tuple(centre))
    cameras = []
    for az in params.camera_azimuths_deg:
        a = math.radians(az)
        cameras.append(view.camera(centre + params.camera_distance_m * np.array([math.sin(a), 0.0, math.cos(a)]),
                                   name=f"eval_az{az:g}"))
    model = data.model
    sweeper = _Sweeper(model, params.steps_per_ray or model.config.steps_per_ray, data.subject, cameras)
    orbit_weights = np.asarray(data.truth_weights[truth_row[orbit_frame]], np.float32)
    orbit = _sweep_orbit(sweeper, orbit_mesh, orbit_weights, decode(model, orbit_mesh), centre, train_dirs,
                         params, progress)
    held_weights = np.asarray(data.truth_weights[truth_row[held_out]], np.float32)
    front = train_dirs[int(np.argmax(train_dirs @ np.array([0.0, 0.0, 1.0])))]
    expression = _sweep_expression(sweeper, data.neutral_scan, tracked, held_weights,
                                   centre + params.orbit_radius_m * front, params, progress)
    return StabilityResults(centre=centre, train_dirs=train_dirs, orbit=orbit, expression=expression,
                            model_seconds=sweeper.model_seconds, truth_seconds=sweeper.truth_seconds)


def _sweep_orbit(sweeper: "_Sweeper", mesh: np.ndarray, weights: np.ndarray, geometry: Any, centre: np.ndarray,
                 train_dirs: np.ndarray, params: EvaluateParams, progress: Callable[[int, str], Progress]
                 ) -> OrbitSweep:
    """A point light circling the head at ``orbit_radius_m`` in each plane, the expression fixed."""
    planes = ("horizontal", "vertical") if params.vertical_orbit else ("horizontal",)
    samples: list[dict[str, Any]] = []
    curves, strip_truth, strip_pred = {}, [], []
    with progress(params.orbit_points * len(planes), "orbit lights") as bar:
        for plane in planes:
            angles, dirs = orbit_directions(params.orbit_points, plane)
            from_train = angle_to_nearest_deg(dirs, train_dirs)
            lights = centre + params.orbit_radius_m * dirs  # [N, 3] head space
            renders = []
            for light in lights:
                renders.append(sweeper.render(mesh, weights, light, geometry))
                bar.advance(1)
            values, exposure = score_sweep(renders, params.white_floor_fraction)
            for angle, ft, light, value, sample in zip(angles, from_train, lights, values, renders):
                samples.append({"plane": plane, "orbit_deg": float(angle), "from_training_deg": float(ft),
                                "light_head": light.tolist(), "psnr_db": float(value)})
                if plane == "horizontal" and (angle + 1e-6) % params.strip_every_deg < 1e-3:
                    strip_truth.append(sample[0][1])
                    strip_pred.append(sample[0][0] * exposure[0])
            curves[plane] = (angles, from_train, values)
    all_from = np.concatenate([c[1] for c in curves.values()])
    all_psnr = np.concatenate([c[2] for c in curves.values()])
    near = all_from <= max(np.min(all_from) + 1e-6, 10.0)  # the in-distribution end of the curve
    reference_db = float(np.median(all_psnr[near]))
    threshold = _threshold(params, reference_db)
    return OrbitSweep(curves=curves, limit=extrapolation_limit_deg(all_from, all_psnr, threshold),
                      azimuth=azimuth_limit_deg(curves["horizontal"][0], curves["horizontal"][2], threshold),
                      threshold_db=threshold, reference_db=reference_db, samples=samples,
                      strip_truth=strip_truth, strip_pred=strip_pred)


def _sweep_expression(sweeper: "_Sweeper", neutral: np.ndarray, tracked: np.ndarray, weights: np.ndarray,
                      key_light: np.ndarray, params: EvaluateParams, progress: Callable[[int, str], Progress]
                      ) -> ExpressionSweep:
    """The held-out frame's expression scaled by each of ``expression_scales``, under ``key_light``.

    The actor rig is linear, so the driving mesh is ``neutral + s (tracked - neutral)``; the
    studio's truth takes the true weights scaled by the same ``s``.
    """
    scales = np.asarray(sorted(params.expression_scales), float)
    renders = []
    with progress(len(scales), "expression scales") as bar:
        for s in scales:
            mesh = neutral + float(s) * (tracked - neutral)
            renders.append(sweeper.render(mesh, float(s) * weights, key_light))
            bar.advance(1)
    psnr_db, _ = score_sweep(renders, params.white_floor_fraction)
    reference_db = float(psnr_db[int(np.argmin(np.abs(scales - 1.0)))])
    threshold = _threshold(params, reference_db)
    low, high = scale_limits(scales, psnr_db, threshold)
    return ExpressionSweep(scales=scales, psnr_db=psnr_db, threshold_db=threshold, reference_db=reference_db,
                           low=low, high=high)


def _threshold(params: EvaluateParams, reference_db: float) -> float:
    return reference_db - params.relative_drop_db if params.relative_drop_db > 0 else params.psnr_threshold_db


class _Sweeper:
    """Renders (mesh, true weights, light) with the model and the studio from every camera."""

    def __init__(self, model, steps: int, subject, cameras) -> None:
        from hardware.studio.envmap_truth import truth_studio

        self.model, self.steps, self.cameras = model, steps, cameras
        # One noiseless studio for the whole sweep, so the subject's geometry is built once per
        # expression, not once per light.
        self.studio = truth_studio(subject)
        self.model_seconds = 0.0
        self.truth_seconds = 0.0

    def render(self, mesh_head: np.ndarray, truth_weights: np.ndarray, light_head: np.ndarray,
               geometry=None) -> SampleRenders:
        """Per camera: (model rgb, truth rgb, truth alpha), [H, W, 3] / [H, W] linear."""
        from avatar.render import PointLights, decode, render
        from hardware.studio.envmap_truth import frame_from_weights, studio_camera
        from scene.lights import PointLight

        if geometry is None:
            geometry = decode(self.model, mesh_head)
        frame = frame_from_weights(truth_weights)
        out = []
        for camera in self.cameras:
            start = time.perf_counter()
            pred_rgb, _ = render(self.model, geometry, camera, PointLights(light_head[None], np.ones((1, 3))),
                                 steps=self.steps).numpy()
            self.model_seconds += time.perf_counter() - start
            start = time.perf_counter()
            truth = self.studio.render_lights(frame, studio_camera(camera),
                                              [PointLight(np.asarray(light_head, float), np.ones(3))], noise=False)
            self.truth_seconds += time.perf_counter() - start
            out.append((pred_rgb, truth.rgb, truth.alpha))
        return out


def score_sweep(renders: list[SampleRenders], floor_fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean PSNR over cameras [N] of a sweep's N samples, and each camera's exposure scale [cameras]."""
    values, scales = [], []
    for c in range(len(renders[0])):
        v, s = sweep_psnr(*zip(*(sample[c] for sample in renders)), floor_fraction=floor_fraction)
        values.append(v)
        scales.append(s)
    return np.mean(values, axis=0), np.asarray(scales)
