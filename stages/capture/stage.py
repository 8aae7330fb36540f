"""Stage ``capture``: film the subject (virtual studio) or import a real capture folder.

Output (the ``capture`` contract, docs/design.md)::

    manifest.json                 subject, fps, width, height, cameras, bars, takes, frames[]
    frames/<cam>/<index:06d>.exr  received images labelled with their trigger index
    calib/...                     calibration takes (ChArUco board, mirror spheres)
    scans/scans.npz               the actor's scan session (names, vertices, faces)
    controller_log.json           the LED controller's log (which light at which pulse)
    contact_sheet.png, strip.png  previews
Ground truth (``capture.truth``, evaluation stages only): ``cameras.json``, ``bars.json``,
``frames.npz``, ``meshes.npz``, ``mattes/<cam>/<index:06d>.png``, ``studio.json``,
``lights_per_pulse.json`` and the calibration takes' board poses and sphere centres.

Frames are labelled (light per frame, dropped/repeated frames) from the controller log and
the images' brightness by ``stages.capture.labelling``; the virtual studio never tells the
labeller what it knows.

The virtual studio renders trigger pulses through ``ctx.executor``, one cached item per pulse
(``stages.capture.virtual``, ``pipeline.itemcache``): a longer take renders only its new pulses
(metrics ``render_pulses_reused``, ``render_pulses_computed``), the rest are copied byte for byte.
The calibration takes are cached per camera and take likewise (``calibration_items_reused``,
``calibration_items_computed``; per take ``calibration_board_items_computed``,
``calibration_mirror_items_computed``).

``realism: real`` (the default) films through a real camera (``hardware.studio.camera_effects``):
sensor noise in electrons and DN, vignetting, thin-lens defocus, motion blur, and a ChArUco
board printed off nominal and bowed; the metrics state the model (``realism_real``,
``sensor_gain_e_per_dn``, ``read_noise_e``, ``sensor_full_well_e``, ``exposure_s``, ...).
``realism: ideal`` renders the clean studio of before bit for bit. The mirror-sphere take keeps
its own ideal sensor either way.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from hardware.studio.camera_effects import CameraEffects
from hardware.studio.renderer import RenderSettings
from pipeline.errors import ConfigError
from pipeline.stage import Stage, StageContext, StageParams
from scene.rig import RigConfig, default_rig
from stages.capture.output import CaptureOutput, CaptureTruth
from stages.sequence.output import SequenceOutput


class CaptureParams(StageParams):
    """Params of the capture stage."""

    rig: RigConfig = Field(default_factory=default_rig,
                           description="The studio rig (injected from configs/rig.yaml): cameras and LED bars.")
    source: str | None = Field(
        None, description="A real capture folder to import (layout: stages/capture/README.md); "
                          "None renders one with the virtual studio.")
    identity_seed: int = Field(0, description="Seed of the virtual subject's identity and materials.")
    performance_seed: int | None = Field(None, description="Seed of the performance; None uses identity_seed.")
    takes: tuple[str, ...] = Field(("rom", "speech"), min_length=1,
                                   description="Takes in order (rom = range of motion, speech); frames split evenly.")
    max_frames: int | None = Field(None, ge=1, description="Film at most this many frames of the schedule (None = all).")
    image_scale: float = Field(1.0, gt=0, le=2,
                               description="Image size relative to the rig's reference 768x1024 (0.3125 = 240x320).")
    texture_size: int = Field(1024, ge=64, description="Height of the subject's UV material tiles, pixels.")
    render: RenderSettings = Field(
        default_factory=RenderSettings,
        description="How the virtual studio renders (antialiasing and light samples, sensor noise, their seed); "
        "see hardware.studio.RenderSettings. Ignored when source imports a real capture.")
    realism: Literal["real", "ideal"] = Field(
        "real", description="real: the virtual cameras film like real ones (camera_effects: photon and read noise "
        "in electrons, vignetting, thin-lens defocus, motion blur over the exposure; the ChArUco board printed off "
        "nominal and bowed), so calibration and the later stages see realistic residuals (ChArUco RMS ~0.05-0.3 "
        "px). ideal: today's clean studio bit for bit (render.shot_noise_gain / read_noise, a perfect board); set "
        "it for tests and studies that need clean images. Ignored when source imports a real capture.")
    camera_effects: CameraEffects = Field(
        default_factory=CameraEffects,
        description="The camera, lens, exposure and board print of realism: real (hardware.studio.camera_effects); "
        "ignored when realism is ideal.")
    head_motion_deg: float = Field(4.0, ge=0, description="Amplitude of the subject's natural head yaw, degrees.")
    rom_pose_seconds: float = Field(0.6, gt=0, description="Duration of one range-of-motion pose, seconds.")
    drop_frames: tuple[int, ...] = Field((), description="Trigger indices whose images every camera loses (simulated drops).")
    camera_drop_frames: dict[str, tuple[int, ...]] = Field(
        default_factory=dict, description="Per camera name, trigger indices that camera alone loses.")
    repeat_frames: dict[str, tuple[int, ...]] = Field(
        default_factory=dict, description="Per camera name, trigger indices that camera delivers twice.")
    controller_missed_pulses: tuple[int, ...] = Field(
        (), description="Trigger pulses the LED controller misses (dark frame, later lights shift).")
    camera_timestamp_jitter_s: float | None = Field(
        None, ge=0, description="Cameras stamp each image with its trigger time plus this jitter (seconds); "
                                "the labeller then also uses time. None = no time stamps (brightness only).")
    half_float: bool = Field(True, description="Store EXR images as float16 (else float32).")
    calibration_takes: bool = Field(True, description="Also film the ChArUco board and mirror-sphere takes.")
    calibration_poses: int = Field(24, ge=2, description="Board poses in the ChArUco take.")
    calibration_image_scale: float = Field(
        1.0, gt=0, le=2, description="Resolution of the ChArUco take, times the rig's reference resolution "
        "(1.0 = the sensors' native 768x1024, as a studio calibrates whatever image_scale the performance uses).")
    calibration_mirror_scale: float | None = Field(
        None, gt=0, le=2, description="Resolution of the mirror-sphere take, times the rig's reference resolution; "
        "None = the performance's image_scale. 1.0 places the bars to a few mm but renders ~10x slower.")
    calibration_mirror_windows: bool = Field(
        True, description="Re-render small windows around each mirror-sphere highlight at the cameras' native "
        "resolution (region-of-interest readout), which light calibration uses to place the bars to a few mm; "
        "False = the low-resolution mirror images only (bars ~20 mm off).")
    strip_camera: str = Field("cam00", description="Camera whose consecutive frames make strip.png.")
    strip_frames: int = Field(12, ge=1, description="Frames in strip.png.")

    @field_validator("source")
    @classmethod
    def _source_exists(cls, value: str | None) -> str | None:
        if value is not None and not Path(value).is_dir():
            raise ValueError(f"capture source '{value}' is not a folder; give a capture folder "
                             "(layout in stages/capture/README.md) or leave source unset to render one")
        return value


def _external(params: CaptureParams) -> list[Path]:
    return [Path(params.source)] if params.source else []


def run(ctx: StageContext) -> None:
    """Capture (render or import), label frames, write previews and metrics."""
    params: CaptureParams = ctx.params
    start = time.perf_counter()
    if params.source:
        from stages.capture.importer import import_capture

        summary = import_capture(ctx, Path(params.source))
    else:
        summary = _virtual_capture(ctx, params)
    _write_previews(ctx, params, summary["manifest"])
    frames = summary["manifest"]["frames"]
    ok = [f for f in frames if f["status"] == "ok"]
    ctx.metrics.update({
        "cameras": len(summary["manifest"]["cameras"]),
        "frames": len(frames),
        "full_on_frames": sum(f["light"] == "F" for f in ok),
        "olat_frames": sum(isinstance(f["light"], int) for f in ok),
        "dropped_frames": sum(f["status"] == "dropped" for f in frames),
        "seconds": time.perf_counter() - start,
        **summary.get("metrics", {}),
    })


def _split_takes(n: int, takes: tuple[str, ...], cycle: int) -> list[int]:
    """Frames per take: whole pattern cycles where possible, the rest to the last take."""
    cycles = n // cycle if cycle else 0
    if cycles >= len(takes):
        counts = [(cycles * (k + 1) // len(takes) - cycles * k // len(takes)) * cycle for k in range(len(takes))]
    else:
        counts = [n * (k + 1) // len(takes) - n * k // len(takes) for k in range(len(takes))]
    counts[-1] += n - sum(counts)
    return counts


def _virtual_capture(ctx: StageContext, params: CaptureParams) -> dict:
    from hardware.led import Faults, run_emulated_session
    from hardware.studio import make_performance, make_subject, scan_session
    from pipeline.itemcache import stage_item_cache
    from stages.capture.placement import label_and_place
    from stages.capture.virtual import RenderTask, place_pulse, pulse_key, render_task

    rig = params.rig
    upstream = SequenceOutput(ctx.input("sequence"))
    sequence = upstream.sequence(keys=("pattern", "fps", "frames"))
    try:
        pattern = sequence["pattern"]
        fps = float(sequence["fps"])
        n_frames = int(sequence["frames"])
    except (ValueError, TypeError) as err:
        raise upstream.malformed(upstream.sequence_path, err) from err
    out = CaptureOutput(ctx.out)
    if params.max_frames is not None:
        n_frames = min(n_frames, params.max_frames)
    cameras = rig.cameras_at(params.image_scale)
    cam_names = [c.name for c in cameras]
    streams = _camera_streams(params, cam_names, n_frames)

    # The controller runs the program; its log (read back over serial) is all a real rig knows.
    trigger_times = [i / fps for i in range(n_frames)]
    session = run_emulated_session(
        pattern=pattern, n_frames=n_frames, n_bars=len(rig.bars), trigger_times_s=trigger_times,
        faults=Faults(drop_pulses=frozenset(params.controller_missed_pulses)))
    log_json = [entry.to_json() for entry in session.log]
    out.write_controller_log({"program_crc32": session.program_crc32, "fps": fps, "entries": log_json})

    counts = _split_takes(n_frames, params.takes, len(pattern))
    seed = params.identity_seed if params.performance_seed is None else params.performance_seed
    performance = make_performance(seed, params.takes, counts, fps, params.rom_pose_seconds,
                                   np.asarray(rig.head_center_m), head_motion_deg=params.head_motion_deg)
    settings = params.render
    truth = ctx.extra_outputs["truth"]
    true_out = CaptureTruth(truth)
    arrivals: list[list[tuple[int, ...]]] = [[() for _ in streams] for _ in range(n_frames)]
    for c, stream in enumerate(streams):  # [F][C] arrival indices of each trigger per camera
        for k, index in enumerate(stream):
            arrivals[index][c] += (k,)
    pulses = [i for i in range(n_frames) if any(arrivals[i])]
    effects = params.camera_effects if params.realism == "real" else None
    real = {} if effects is None else {"effects": effects, "image_scale": params.image_scale,
                                       "volume_center_m": tuple(rig.head_center_m)}

    def motion_partner(i: int):
        """The frame the head's motion over frame i's exposure is taken from: the previous one of the same take
        (so a longer take leaves every earlier pulse's images, and cache keys, as they were), the next one for
        a take's first frame; None without a neighbour in the take."""
        if effects is None:
            return None
        for j in (i - 1, i + 1):
            if 0 <= j < len(performance) and performance[j].take == performance[i].take:
                return performance[j]
        return None

    tasks = [RenderTask(rig=rig, subject_name=ctx.subject, identity_seed=params.identity_seed,
                        texture_size=params.texture_size, settings=settings,
                        cameras=tuple(cam for cam, got in zip(cameras, arrivals[i]) if got),
                        frame=performance[i], light=session.lit_per_pulse[i], half=params.half_float,
                        motion_frame=motion_partner(i), **real)
             for i in pulses]
    arrivals_of = [{cam.name: got for cam, got in zip(cameras, arrivals[i]) if got} for i in pulses]
    ctx.log.info("filming %d trigger pulses x %d cameras at %dx%d (%d images lost by the cameras, "
                 "%d pulses missed by the controller)", n_frames, len(cameras), cameras[0].width,
                 cameras[0].height, n_frames * len(cameras) - sum(len(set(s)) for s in streams),
                 len(params.controller_missed_pulses))
    render_start = time.perf_counter()
    # One cache entry per pulse: frames added to a take render alone, the rest come from the cache.
    cache = stage_item_cache(ctx)
    results = cache.map(ctx.executor, render_task, tasks, pulse_key, desc="frames",
                        consume=lambda k, rendered: place_pulse(rendered, arrivals_of[k], out.received_dir,
                                                                true_out.mattes_dir, cam_names))
    cache.report(ctx, "frames", metrics_prefix="render_pulses")
    rendered_now = [results[k] for k in cache.computed]
    render_s = time.perf_counter() - render_start
    bright_of = {r["index"]: r["brightness"] for r in results}
    brightness = [[bright_of[i][c] for i in stream] for c, stream in enumerate(streams)]  # C x [R_c]

    frame_times = None
    if params.camera_timestamp_jitter_s is not None:
        rng = np.random.default_rng([params.render.seed, 7])
        frame_times = [[i / fps + params.camera_timestamp_jitter_s * rng.standard_normal() for i in stream]
                       for stream in streams]
    manifest, label_metrics = label_and_place(out, ctx.log, ctx.subject, fps, cam_names, len(rig.bars),
                                               params.takes, [f.take for f in performance], log_json,
                                               brightness, n_frames, frame_times=frame_times)
    manifest.update(width=cameras[0].width, height=cameras[0].height)
    out.write_manifest(manifest)
    lost_images = n_frames * len(cameras) - sum(r["images"] for r in results)

    subject = make_subject(ctx.subject, params.identity_seed, texture_size=params.texture_size)
    names, scan_verts, faces = scan_session(subject)
    out.write_scans(names, scan_verts, faces)

    calibration_metrics = _calibration_takes(ctx, params, cameras, truth) if params.calibration_takes else {}

    _write_truth(truth, rig, cameras, subject, performance, session.lit_per_pulse, streams, settings, params)
    total_rays = sum(r["rays"] for r in results)
    return {"manifest": manifest, "metrics": {
        **label_metrics, "lost_images": lost_images,
        "render_seconds": render_s,
        "rays_per_second": total_rays / max(sum(r["seconds"] for r in results), 1e-9),
        # Images rendered by this run (pulses reused from the per-item cache took no time now).
        "images_per_second": sum(r["images"] for r in rendered_now) / max(render_s, 1e-9),
        "image_width_px": cameras[0].width, "image_height_px": cameras[0].height,
        "controller_log_entries": len(log_json), **calibration_metrics,
        "realism_real": int(params.realism == "real"), **params.camera_effects.metrics(),
    }}


def _camera_streams(params: CaptureParams, cam_names: list[str], n_frames: int) -> list[list[int]]:
    """Per camera, the trigger index of each image in arrival order (drops and repeats applied)."""
    for key, mapping in (("camera_drop_frames", params.camera_drop_frames), ("repeat_frames", params.repeat_frames)):
        for cam, ids in mapping.items():
            if cam not in cam_names:
                raise ConfigError(f"capture.{key}: unknown camera '{cam}'; cameras: {', '.join(cam_names)}")
            bad = [i for i in ids if not 0 <= i < n_frames]
            if bad:
                raise ConfigError(f"capture.{key}.{cam}: trigger indices {bad} outside 0..{n_frames - 1}")
    for key, ids in (("drop_frames", params.drop_frames), ("controller_missed_pulses", params.controller_missed_pulses)):
        bad = [i for i in ids if not 0 <= i < n_frames]
        if bad:
            raise ConfigError(f"capture.{key}: trigger indices {bad} outside 0..{n_frames - 1}")
    streams = []
    for cam in cam_names:
        lost = set(params.drop_frames) | set(params.camera_drop_frames.get(cam, ()))
        twice = set(params.repeat_frames.get(cam, ()))
        stream = []
        for i in range(n_frames):
            if i in lost:
                continue
            stream.append(i)
            if i in twice:
                stream.append(i)
        streams.append(stream)
    return streams


def _calibration_takes(ctx: StageContext, params: CaptureParams, cameras, truth: Path) -> dict:
    """Film the board and mirror takes, one cached item per camera and take; returns their metrics."""
    from hardware.studio.calibration_takes import (BarLight, CalibrationTakeParams, CharucoBoardConfig,
                                                   MirrorSpheresConfig, TakeWriter, plan_calibration_takes,
                                                   render_take_item, write_take_specs)
    from pipeline.itemcache import stage_item_cache
    from stages.capture.virtual import calibration_item_key

    rig = params.rig
    try:
        board = CharucoBoardConfig(**rig.calibration.get("board", {}))
        spheres = MirrorSpheresConfig(**rig.calibration.get("mirror_spheres", {}))
    except (TypeError, ValueError) as err:
        raise ConfigError(f"configs/rig.yaml: bad 'calibration' section ({err})") from err
    bars = [BarLight(b.id, b.center_world, b.axis_world, b.length_m, b.intensity) for b in rig.light_bars()]
    take_params = CalibrationTakeParams(poses=params.calibration_poses, seed=params.render.seed,
                                        volume_center_m=tuple(rig.head_center_m),
                                        mirror_roi=params.calibration_mirror_windows,
                                        effects=params.camera_effects if params.realism == "real" else None,
                                        board_scale=params.calibration_image_scale)
    board_cameras = {c.name: c for c in rig.cameras_at(params.calibration_image_scale)}
    mirror_cameras = None
    if params.calibration_mirror_scale is not None:
        by_name = {c.name: c for c in rig.cameras_at(params.calibration_mirror_scale)}
        mirror_cameras = [by_name[c.name] for c in cameras]
    start = time.perf_counter()
    plan = plan_calibration_takes(cameras, bars, take_params, board, spheres,
                                  board_cameras=[board_cameras[c.name] for c in cameras], mirror_cameras=mirror_cameras)
    write_take_specs(plan, ctx.out, truth)
    writer = TakeWriter(CaptureOutput(ctx.out).calib_dir)
    # One entry per camera and take: a rerun (more frames, another performance) renders none of them again.
    cache = stage_item_cache(ctx)
    cache.map(ctx.executor, render_take_item, plan.items, calibration_item_key, desc="calibration takes",
              consume=writer.write)
    writer.finish()
    cache.report(ctx, "calibration takes", metrics_prefix="calibration_items")
    computed = [plan.items[i].kind for i in cache.computed]
    return {"calibration_board_items_computed": computed.count("board"),
            "calibration_mirror_items_computed": computed.count("mirror"),
            "calibration_seconds": time.perf_counter() - start}


def _write_truth(truth: Path, rig: RigConfig, cameras, subject, performance, lit_per_pulse, streams,
                 settings, params: CaptureParams) -> None:
    from dataclasses import asdict

    from stages.capture.virtual import frame_state_arrays

    out = CaptureTruth(truth)
    out.write_cameras(cameras)
    bars = []
    for bar in rig.light_bars():
        entry = bar.to_dict()
        entry["radiant_intensity"] = bar.intensity * settings.bar_intensity_scale
        bars.append(entry)
    out.write_bars({"bars": bars, "intensity_scale": settings.bar_intensity_scale}, indent=1)
    arrays = frame_state_arrays(performance)
    received = np.zeros((len(cameras), len(performance)), np.int32)  # [C, F] images delivered per trigger
    for c, stream in enumerate(streams):
        np.add.at(received[c], np.asarray(stream, int), 1)
    out.write_frames(**arrays, expression_names=np.array(subject.rig.expression_names),
                        received=received,
                        lit=np.array(["none" if x is None else str(x) for x in lit_per_pulse]))
    verts = np.stack([subject.vertices(f.expression_weights) for f in performance]).astype(np.float32)
    out.write_meshes(verts, subject.rig.triangles)
    out.write_lights_per_pulse(list(lit_per_pulse))
    out.write_studio({
        "subject": subject.name, "identity_seed": subject.seed, "texture_size": params.texture_size,
        "performance_seed": params.identity_seed if params.performance_seed is None else params.performance_seed,
        "identity_coeffs": subject.identity_coeffs.tolist(), "skin_albedo": subject.skin_albedo.tolist(),
        "iris_albedo": subject.iris_albedo.tolist(), "render_settings": asdict(settings),
        "realism": params.realism, "camera_effects": params.camera_effects.model_dump(mode="json"),
        "drop_frames": list(params.drop_frames), "controller_missed_pulses": list(params.controller_missed_pulses),
    })


def _write_previews(ctx: StageContext, params: CaptureParams, manifest: dict) -> None:
    from stages.capture.previews import contact_sheet, strip

    ok = [f for f in manifest["frames"] if f["status"] == "ok"]
    full_on = [f for f in ok if f["light"] == "F"] or ok
    if not full_on:
        ctx.log.warning("no frame was received: no contact sheet or strip")
        return
    cams = manifest["cameras"]
    pick = full_on[0]["index"]
    out = CaptureOutput(ctx.out)
    images = [out.frame(cam, pick)[..., :3] for cam in cams]
    exposure = 0.6 / max(float(np.percentile(np.concatenate([i.reshape(-1, 3) for i in images]), 99)), 1e-6)
    contact_sheet(out.contact_sheet_path, images, [f"{c} #{pick} F" for c in cams], exposure=exposure)
    cam = params.strip_camera if params.strip_camera in cams else cams[0]
    chosen = ok[:params.strip_frames]
    strip_images = [out.frame(cam, f["index"])[..., :3] for f in chosen]
    labels = [f"{'F' if f['light'] == 'F' else 'bar ' + str(f['light'])} #{f['index']}" for f in chosen]
    strip(out.strip_path, strip_images, labels, full_on_exposure=exposure, olat_exposure=exposure * 10)


STAGE = Stage(
    name="capture",
    inputs=("sequence",),
    params=CaptureParams,
    run=run,
    extra_outputs=("truth",),
    external_inputs=_external,
    doc="Film the subject in the virtual studio (or import a real capture), label frames by their light.",
)
