"""Evaluate stage: stability sweeps of the trained head against the studio's ground truth.

Two sweeps, each a curve with the point where quality falls under a PSNR threshold:

- Light orbit: a point light circles the head at ``orbit_radius_m`` (3 m) in the horizontal
  plane (and, optionally, the vertical y-z plane). Each position is rendered by the trained
  model and by the studio's ray tracer (same head-space camera, expression, light) from
  ``camera_azimuths_deg``; PSNR is exposure fitted as in the paper
  (``stages.evaluate.measure``). Plotted against the angle between the light
  and the nearest training light direction (the lit bars of the training split, moved into
  head space with the true head pose, seen from the head's centre), the first angle where PSNR
  drops under the threshold is ``light_extrapolation_limit_deg`` (the paper reports ~20 degrees
  behind the training lights).
- Expression magnitude: a held-out frame's tracked blendshape weights scaled by
  ``expression_scales`` (the actor rig is linear, so the driving mesh is
  ``neutral + s (tracked - neutral)``), against the studio's truth with its true ICT weights
  scaled by the same ``s``, under the training light nearest the front. The scales where PSNR
  falls under the threshold below and above 1 are ``expression_scale_limit_low/high``.

Output::

    limits.json                     the warning zone (``stages.evaluate.limits``)
    tradeoffs/light_orbit.json      PSNR vs angle from the nearest training light (report chart)
    tradeoffs/expression_scale.json PSNR vs weight scale
    light_orbit.png, expression_scale.png, orbit_strip.png (truth over model, every 45 degrees)
    sweeps.json                     every sample of both sweeps
    metrics.json

Reads ground truth (``capture.truth``); nothing reads its output back into a product stage.
"""

from __future__ import annotations

import math
import time

import numpy as np
from pydantic import Field

from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext, StageParams
from stages.capture.output import CaptureOutput, CaptureTruth
from stages.evaluate import charts
from stages.evaluate.measure import sweep_psnr
from stages.evaluate.limits import LightLimits, write_limits
from stages.evaluate.output import EvaluateOutput
from stages.evaluate.sweeps import (Crossing, angle_to_nearest_deg, azimuth_limit_deg, extrapolation_limit_deg,
                                    orbit_directions, scale_limits, unit)
from stages.track.output import TrackOutput
from stages.train.output import TrainOutput


class EvaluateParams(StageParams):
    """Sizes of the sweeps (defaults: a couple of CPU minutes on the tiny preset)."""

    psnr_threshold_db: float = Field(25.0, description="PSNR under which a render counts as broken (dB).")
    relative_drop_db: float = Field(0.0, ge=0.0, description="If > 0, the threshold is instead this many dB under "
                                    "the sweep's own in-distribution PSNR (orbit: the lights nearest the training "
                                    "lights; expression: scale 1), for models too small to reach the absolute one.")
    orbit_radius_m: float = Field(3.0, gt=0.2, description="Distance of the orbiting point light from the head's centre.")
    orbit_points: int = Field(24, ge=4, description="Light positions per orbit circle (24 = every 15 degrees).")
    vertical_orbit: bool = Field(True, description="Also orbit in the vertical (y-z) plane (over the head and under the chin).")
    camera_azimuths_deg: tuple[float, ...] = Field((0.0, 40.0), description="Cameras around +y looking at the head "
                                                   "(0 = front, positive = the subject's left).")
    camera_distance_m: float = Field(0.9, gt=0.1, description="Camera distance from the head's centre.")
    fov_deg: float = Field(24.0, gt=1.0, lt=170.0, description="Horizontal field of view of the cameras.")
    width_px: int = Field(48, ge=8, description="Render width in pixels.")
    height_px: int = Field(60, ge=8, description="Render height in pixels.")
    expression_scales: tuple[float, ...] = Field((0.5, 0.75, 1.0, 1.25, 1.5, 1.75, 2.0),
                                                 description="Scales of the held-out frame's blendshape weights.")
    strip_every_deg: float = Field(45.0, gt=0.0, description="Orbit angles shown in orbit_strip.png.")
    white_floor_fraction: float = Field(0.05, gt=0.0, le=1.0, description="PSNR white level floor, as a fraction "
                                        "of the sweep's brightest truth (keeps a black back-lit truth from "
                                        "blowing errors up).")
    steps_per_ray: int = Field(0, ge=0, description="Raymarch steps per ray (0 = the model's own).")


def training_light_dirs(capture: CaptureOutput, truth: CaptureTruth, train: TrainOutput,
                        centre_head: np.ndarray) -> np.ndarray:
    """Unit head-space directions [L, 3] from ``centre_head`` to the lit bar of every training frame.

    Training frames come from the train stage's splits (all OLAT frames if it has none); bar
    centres and head poses are the studio's true ones, so the directions are what the
    model was actually shown.
    """
    manifest = capture.manifest(keys=("frames",))
    frames = {int(f["index"]): f for f in manifest["frames"]}
    splits_path = train.splits_path
    if train.has_splits():
        train_index = [int(i) for i in train.splits()["train"]]
    else:
        train_index = sorted(i for i, f in frames.items() if f.get("light") not in ("F", None)
                             and f.get("status", "ok") == "ok")
    bars = {int(b["id"]): np.asarray(b["center_world"], float) for b in truth.bars()}
    poses = truth.frames(keys=("index", "world_from_head_R", "world_from_head_t"))
    row = {int(i): k for k, i in enumerate(poses["index"])}
    dirs = []
    for i in train_index:
        light = frames.get(i, {}).get("light")
        if light in ("F", None) or i not in row or int(light) not in bars:
            continue
        R, t = poses["world_from_head_R"][row[i]], poses["world_from_head_t"][row[i]]
        light_head = R.T @ (bars[int(light)] - t)  # head_from_world applied to the bar centre
        dirs.append(light_head - centre_head)
    if not dirs:
        raise InputError(f"evaluate: no training OLAT frames with a lit bar in {splits_path} / "
                         f"{capture.manifest_path}; re-run capture and train")
    return unit(np.asarray(dirs))


def _threshold(params: EvaluateParams, reference_db: float) -> float:
    return reference_db - params.relative_drop_db if params.relative_drop_db > 0 else params.psnr_threshold_db


class _Sweeper:
    """Renders (mesh, true weights, light) with the model and the studio from every camera."""

    def __init__(self, model, steps: int, subject, cameras) -> None:
        from hardware.studio import RenderSettings, VirtualStudio
        from scene.rig import load_rig

        self.model, self.steps, self.cameras = model, steps, cameras
        # One noiseless studio for the whole sweep (as hardware.studio.envmap_truth builds it),
        # so the subject's geometry is built once per expression, not once per light.
        self.studio = VirtualStudio(load_rig(), subject, RenderSettings(shot_noise_gain=0.0, read_noise=0.0))
        self.model_seconds = 0.0
        self.truth_seconds = 0.0

    def render(self, mesh_head: np.ndarray, truth_weights: np.ndarray, light_head: np.ndarray,
               geometry=None) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
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


def score_sweep(renders: list[list[tuple[np.ndarray, np.ndarray, np.ndarray]]], floor_fraction: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Mean PSNR over cameras [N] of a sweep's N samples, and each camera's exposure scale [cameras]."""
    values, scales = [], []
    for c in range(len(renders[0])):
        v, s = sweep_psnr(*zip(*(sample[c] for sample in renders)), floor_fraction=floor_fraction)
        values.append(v)
        scales.append(s)
    return np.mean(values, axis=0), np.asarray(scales)


def run(ctx: StageContext) -> None:
    from avatar.io import load_trained
    from avatar.render import decode
    from hardware.studio.envmap_truth import subject_from_truth
    from scene.view import ViewSpec

    params: EvaluateParams = ctx.params
    capture, truth = CaptureOutput(ctx.input("capture")), CaptureTruth(ctx.input("capture.truth"))
    train, track = TrainOutput(ctx.input("train")), TrackOutput(ctx.input("track"))
    model, _meta = train.model(load_trained)
    try:
        subject = subject_from_truth(truth.path)
    except ValueError as err:
        raise InputError(f"evaluate: {err}") from err
    meshes = track.meshes(keys=("vertices",))
    mesh_index = [int(i) for i in meshes["index"]] if "index" in meshes else list(range(len(meshes["vertices"])))
    truth_frames = truth.frames(keys=("weights",))
    truth_row = {int(i): k for k, i in enumerate(truth_frames["index"])} if "index" in truth_frames else \
        {k: k for k in range(len(truth_frames["weights"]))}
    splits = train.splits() if train.has_splits() else {}
    common = [i for i in mesh_index if i in truth_row]
    if not common:
        raise InputError("evaluate: no frame is both in track/meshes.npz and capture.truth/frames.npz; "
                         "re-run track on this capture")
    orbit_frame = next((i for i in splits.get("train", []) if i in truth_row and i in mesh_index), common[0])
    held_out = next((i for s in ("novel_perf", "novel_both") for i in splits.get(s, [])
                     if i in truth_row and i in mesh_index), common[-1])
    vertices = np.asarray(meshes["vertices"], np.float32)
    orbit_mesh = vertices[mesh_index.index(orbit_frame)]
    centre = orbit_mesh.mean(0).astype(float)  # [3] head space
    train_dirs = training_light_dirs(capture, truth, train, centre)

    view = ViewSpec(params.width_px, params.height_px, params.camera_distance_m, params.fov_deg, tuple(centre))
    cameras = []
    for az in params.camera_azimuths_deg:
        a = math.radians(az)
        cameras.append(view.camera(centre + params.camera_distance_m * np.array([math.sin(a), 0.0, math.cos(a)]),
                                   name=f"eval_az{az:g}"))
    sweeper = _Sweeper(model, params.steps_per_ray or model.config.steps_per_ray, subject, cameras)

    # Light orbit.
    planes = ("horizontal", "vertical") if params.vertical_orbit else ("horizontal",)
    orbit_weights = np.asarray(truth_frames["weights"][truth_row[orbit_frame]], np.float32)
    geometry = decode(model, orbit_mesh)
    samples: dict[str, list[dict]] = {"light_orbit": [], "expression_scale": []}
    orbits, strip_truth, strip_pred = {}, [], []
    with ctx.progress(params.orbit_points * len(planes), "orbit lights") as progress:
        for plane in planes:
            angles, dirs = orbit_directions(params.orbit_points, plane)
            from_train = angle_to_nearest_deg(dirs, train_dirs)
            lights = centre + params.orbit_radius_m * dirs  # [N, 3] head space
            renders = []
            for light in lights:
                renders.append(sweeper.render(orbit_mesh, orbit_weights, light, geometry))
                progress.advance(1)
            values, exposure = score_sweep(renders, params.white_floor_fraction)
            for angle, ft, light, value, sample in zip(angles, from_train, lights, values, renders):
                samples["light_orbit"].append({"plane": plane, "orbit_deg": float(angle),
                                               "from_training_deg": float(ft), "light_head": light.tolist(),
                                               "psnr_db": float(value)})
                if plane == "horizontal" and (angle + 1e-6) % params.strip_every_deg < 1e-3:
                    strip_truth.append(sample[0][1])
                    strip_pred.append(sample[0][0] * exposure[0])
            orbits[plane] = (angles, from_train, values)
    all_from = np.concatenate([o[1] for o in orbits.values()])
    all_psnr = np.concatenate([o[2] for o in orbits.values()])
    near = all_from <= max(np.min(all_from) + 1e-6, 10.0)  # the in-distribution end of the curve
    light_reference_db = float(np.median(all_psnr[near]))
    light_threshold = _threshold(params, light_reference_db)
    limit = extrapolation_limit_deg(all_from, all_psnr, light_threshold)
    azimuth = azimuth_limit_deg(orbits["horizontal"][0], orbits["horizontal"][2], light_threshold)

    # Expression magnitude.
    scans = capture.scans(keys=("vertices",))
    neutral = np.asarray(scans["vertices"][0], np.float32)
    tracked = vertices[mesh_index.index(held_out)]
    if tracked.shape != neutral.shape:
        raise InputError(f"evaluate: tracked meshes have {tracked.shape[0]} vertices but the neutral scan has "
                         f"{neutral.shape[0]}; re-run track on this capture")
    held_weights = np.asarray(truth_frames["weights"][truth_row[held_out]], np.float32)
    front = train_dirs[int(np.argmax(train_dirs @ np.array([0.0, 0.0, 1.0])))]
    key_light = centre + params.orbit_radius_m * front
    scales = np.asarray(sorted(params.expression_scales), float)
    renders = []
    with ctx.progress(len(scales), "expression scales") as progress:
        for s in scales:
            mesh = neutral + float(s) * (tracked - neutral)
            renders.append(sweeper.render(mesh, float(s) * held_weights, key_light))
            progress.advance(1)
    expr_psnr, _ = score_sweep(renders, params.white_floor_fraction)
    samples["expression_scale"] = [{"scale": float(s), "psnr_db": float(v)} for s, v in zip(scales, expr_psnr)]
    expr_reference_db = float(expr_psnr[int(np.argmin(np.abs(scales - 1.0)))])
    expr_threshold = _threshold(params, expr_reference_db)
    low, high = scale_limits(scales, expr_psnr, expr_threshold)

    samples["light_orbit_azimuth_limit_deg"] = azimuth.x
    _write_outputs(ctx, params, orbits, limit, light_threshold, centre, train_dirs, scales, expr_psnr,
                   expr_threshold, low, high, samples, strip_truth, strip_pred)
    m = ctx.metrics
    m["light_extrapolation_limit_deg"] = limit.x
    m["light_extrapolation_censored"] = float(limit.censored)
    m["light_orbit_azimuth_limit_deg"] = azimuth.x  # how far round from the front, the worse side
    m["light_threshold_db"] = light_threshold
    m["light_orbit_psnr_mean"] = float(np.mean(all_psnr))
    m["light_orbit_psnr_min"] = float(np.min(all_psnr))
    m["light_orbit_psnr_near_training"] = light_reference_db
    m["light_orbit_max_from_training_deg"] = float(np.max(all_from))
    m["light_orbit_points"] = int(all_psnr.size)
    m["expression_scale_limit_low"] = low.x
    m["expression_scale_limit_high"] = high.x
    m["expression_scale_censored_low"] = float(low.censored)
    m["expression_scale_censored_high"] = float(high.censored)
    m["expression_threshold_db"] = expr_threshold
    m["expression_psnr_at_scale_1"] = expr_reference_db
    m["expression_psnr_min"] = float(np.min(expr_psnr))
    m["model_render_seconds"] = sweeper.model_seconds
    m["truth_render_seconds"] = sweeper.truth_seconds
    ctx.log.info("evaluate: light extrapolation limit %.1f deg from the training lights (threshold %.1f dB%s); "
                 "expression scale limits %.2f / %.2f (threshold %.1f dB)", limit.x, light_threshold,
                 ", not reached" if limit.censored else "", low.x, high.x, expr_threshold)


def _write_outputs(ctx: StageContext, params: EvaluateParams, orbits: dict, limit: Crossing, light_threshold: float,
                   centre: np.ndarray, train_dirs: np.ndarray, scales: np.ndarray, expr_psnr: np.ndarray,
                   expr_threshold: float, low: Crossing, high: Crossing, samples: dict, strip_truth: list,
                   strip_pred: list) -> None:
    out = EvaluateOutput(ctx.out)
    limits = LightLimits(limit.x, limit.censored, light_threshold, tuple(float(v) for v in centre),
                         tuple(tuple(float(v) for v in d) for d in train_dirs))
    write_limits(out.limits_path, limits, {
        "failed_at_start": limit.failed_at_start,
        "light_orbit_azimuth_limit_deg": samples["light_orbit_azimuth_limit_deg"],
        "expression_scale_limit_low": low.x, "expression_scale_limit_high": high.x,
        "expression_scale_censored_low": low.censored, "expression_scale_censored_high": high.censored,
        "expression_threshold_db": expr_threshold})
    out.write_sweeps(samples)
    # No per-point labels: the report annotates every labelled point and an orbit has dozens.
    points = [{"x": ft, "y": p, "series": f"{plane} orbit"}
              for plane, (_angles, from_train, psnr_db) in orbits.items()
              for ft, p in zip(from_train, psnr_db)]
    points.append({"x": limit.x, "y": light_threshold, "series": "limit", "chosen": True,
                   "label": f"limit {limit.x:.0f} deg" + (" (not reached)" if limit.censored else "")})
    charts.write_series(out.light_orbit_series_path,
                        f"Point light orbit at {params.orbit_radius_m:g} m: PSNR vs angle from the training lights",
                        "angle from the nearest training light (deg)", "PSNR (dB)", points)
    points = [{"x": s, "y": p, "series": "held-out frame", "label": f"x{s:g}"} for s, p in zip(scales, expr_psnr)]
    points += [{"x": c.x, "y": expr_threshold, "series": "limit", "chosen": True, "label": f"{side} limit x{c.x:.2f}"}
               for side, c in (("low", low), ("high", high))]
    charts.write_series(out.expression_series_path, "Expression magnitude: PSNR vs weight scale",
                        "blendshape weight scale", "PSNR (dB)", points)
    charts.light_orbit_png(out.light_orbit_png_path, orbits, light_threshold, limit)
    charts.expression_png(out.expression_png_path, scales, expr_psnr, expr_threshold, low, high)
    if strip_truth:
        charts.strip_png(out.orbit_strip_path, strip_truth, strip_pred)


STAGE = Stage(
    name="evaluate",
    inputs=("train", "track", "capture", "capture.truth"),
    params=EvaluateParams,
    run=run,
    reads_truth=True,
    doc="Stability sweeps against ground truth: light orbit (extrapolation limit) and expression magnitude.",
)
