"""Stage ``track``: landmark blendshape tracking on full-on frames, interpolated to every frame.

Inputs: ``capture`` (manifest, frames, scan session) and ``calibrate`` (``cameras.json``).

Output::

    tracking.npz     index [T], time_s [T], full_on [T] (bool), fitted [T] (bool: a full-on
                     frame fitted directly), weights [T, K], expression_names [K],
                     world_from_head_R [T, 3, 3], world_from_head_t [T, 3] (metres),
                     landmark_reproj_px [T] (nan where not fitted)
    meshes.npz       index [T], vertices [T, V, 3] float32 head space (metres), faces [F, 3]
    embedding.npz    landmark_ids [N] (FaceMesh), triangles [N], barycentric [N, 3]
    landmarks.npz    detections: index [F], cameras [C], uv_px [F, C, 468, 2], score [F, C], status [F, C],
                     foreground outlines contour_px [sum M, 2] with contour_count [F, C] points each
    cameras.json     the calibrated cameras the fit used (save_cameras)
    obj/<index:06d>.obj   a few frames' meshes to open in a viewer
    overlay.png      detected (green) and fitted (red) landmarks and the mesh wireframe
    metrics.json     landmark_reproj_px_mean, fit_frames_per_second, ...

Method: MediaPipe FaceMesh landmarks on every full-on frame and camera (per-view rejection:
no face, low score, implausible spread); the actor rig from the scan session (scan poses
minus neutral); a barycentric landmark embedding on the neutral scan (``embedding``);
per frame a robust multi-view fit of head pose and bounded weights (rigid first, warm
started, light temporal term), its pose refined with the head's outline against the dark
backdrop (``silhouette``). Every frame of the manifest then gets a pose and weights (OLAT
frames by cubic spline and Slerp, ``interpolate``); the meshes are expression only, in
head space. Warnings name the frame and camera of every rejected view and unfitted frame.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from pydantic import Field

from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext, StageParams
from scene.camera import Camera
from scene.image_io import write_png8
from stages.calibrate.output import CalibrateOutput
from stages.capture.output import CaptureOutput
from stages.track import topology
from stages.track.from_meshes import MeshSourceParams
from stages.track.interpolate import interpolate_track
from stages.track.landmarks import (NUM_FACEMESH_LANDMARKS, DetectorParams, detect_files, landmark_subset,
                                    to_detector_image)
from stages.track.output import TrackOutput
from stages.track.overlay import contact_sheet, draw_view, mesh_edges
from stages.track.rig import ActorRig, load_scan_rig
from stages.track.tracker import KeyFrameObservations, Tracker, TrackerParams, TrackResult


class TrackParams(StageParams):
    """Params of the track stage."""

    landmark_groups: tuple[str, ...] = Field(
        ("eyes", "brows", "nose", "lips_outer"),
        description="FaceMesh landmark groups to fit (contour, eyes, brows, nose, lips_outer, lips_inner, all); "
                    "the face contour and inner lips slide over the skin and are left out by default.")
    align_groups: tuple[str, ...] = Field(
        ("all",), description="FaceMesh landmark groups whose triangulation is aligned to the neutral scan to "
                              "fix the head frame (a dense set pins the head's pitch; see Tracker).")
    detector: DetectorParams = Field(default_factory=DetectorParams, description="Landmark detector settings.")
    tracker: TrackerParams = Field(default_factory=TrackerParams, description="Embedding and fit settings.")
    obj_frames: int = Field(3, ge=0, description="Number of frames (evenly spread) also written as OBJ.")
    overlay_frames: int = Field(2, ge=0, description="Full-on frames drawn in overlay.png (one row of cameras each).")
    source: str | None = Field(
        None, description="Tracked meshes from elsewhere instead of landmark tracking: a folder of OBJ files named by "
        "frame index, or an .npz with 'vertices' [N, V, 3] (and 'index' [N]); world space, the actor rig's topology. "
        "Leave unset to track the capture's full-on frames.")
    mesh_source: MeshSourceParams = Field(default_factory=MeshSourceParams,
                                          description="How source meshes are read and posed; see "
                                          "stages.track.from_meshes.MeshSourceParams.")


def _full_on_frames(manifest: dict, capture: CaptureOutput) -> list[dict]:
    frames = capture.frames_of(manifest)
    manifest_path = capture.manifest_path
    full_on = [f for f in frames if f.get("light") == "F" and f.get("status", "ok") == "ok"]
    if not full_on:
        raise InputError(f"{manifest_path}: the capture has no usable full-on ('F') frames, so there is "
                         "nothing to track landmarks on; capture with the F,O,O,... pattern (the sequence "
                         "stage's default) or check the capture's frame labels")
    return sorted(full_on, key=lambda f: float(f["time_s"]))


def _cameras(ctx: StageContext, manifest: dict) -> list[Camera]:
    calibrate = CalibrateOutput(ctx.input("calibrate"))
    path = calibrate.cameras_path
    calibrated = {c.name: c for c in calibrate.cameras()}
    names = [str(n) for n in manifest.get("cameras", [])]
    missing = [n for n in names if n not in calibrated]
    if missing:
        ctx.log.warning("cameras %s of the capture are not calibrated (%s); tracking without them",
                        ", ".join(missing), path)
    cams = [calibrated[n] for n in names if n in calibrated]
    if len(cams) < 2:
        raise InputError(f"{path}: only {len(cams)} of the capture's cameras {names} are calibrated; "
                         "tracking needs at least two; re-run calibrate")
    return cams


def _detect(ctx: StageContext, params: TrackParams, capture: CaptureOutput, cams: list[Camera],
            key_frames: list[dict]) -> tuple[np.ndarray, np.ndarray, list[list[str]], list[list[np.ndarray]]]:
    """Detections [F, C, 468, 2], scores [F, C] (0 = rejected), statuses [F][C], outlines [F][C]."""
    cache = ctx.cache_dir / "landmarks"
    cache.mkdir(parents=True, exist_ok=True)
    jobs = []
    for cam in cams:
        paths = [capture.frame_path(cam.name, int(f["index"])) for f in key_frames]
        jobs.append((paths, params.detector, cache))
    ctx.log.info("detecting landmarks in %d full-on frames x %d cameras", len(key_frames), len(cams))
    per_camera = ctx.executor.map(detect_files, jobs, desc="cameras")
    F, C = len(key_frames), len(cams)
    uv = np.full((F, C, NUM_FACEMESH_LANDMARKS, 2), np.nan)
    score = np.zeros((F, C))
    status = [["" for _ in range(C)] for _ in range(F)]
    contours: list[list[np.ndarray]] = [[np.zeros((0, 2)) for _ in range(C)] for _ in range(F)]
    for c, results in enumerate(per_camera):
        for f, res in enumerate(results):
            status[f][c] = res.status
            contours[f][c] = res.contour_px
            if res.ok:
                uv[f, c] = res.uv_px
                score[f, c] = res.score
    for c, cam in enumerate(cams):
        bad = [(key_frames[f]["index"], status[f][c]) for f in range(F) if status[f][c] != "ok"]
        if bad:
            shown = "; ".join(f"frame {i}: {s}" for i, s in bad[:3])
            ctx.log.warning("camera %s: %d of %d full-on views rejected (%s%s)", cam.name, len(bad), F, shown,
                            " ..." if len(bad) > 3 else "")
    return uv, score, status, contours


def _write_outputs(ctx: StageContext, params: TrackParams, rig: ActorRig, cams: list[Camera], manifest: dict,
                   key_frames: list[dict], result: TrackResult) -> dict[str, float]:
    fitted = [k for k, fit in enumerate(result.fits) if fit is not None]
    if not fitted:
        raise InputError("no full-on frame could be fitted (too few views with a face in every frame); "
                         "check the overlay of detections in landmarks.npz and the camera calibration")
    key_t = np.array([float(key_frames[k]["time_s"]) for k in fitted])
    # Frames sharing a time stamp (a repeated frame) keep only their first fit.
    _, first = np.unique(key_t, return_index=True)
    fitted = [fitted[i] for i in sorted(first)]
    key_t = key_t[sorted(first)]
    key_R = np.stack([result.fits[k].pose.R for k in fitted])
    key_tr = np.stack([result.fits[k].pose.t for k in fitted])
    key_w = np.stack([result.fits[k].pose.weights for k in fitted]).reshape(len(fitted), rig.num_shapes)

    frames = sorted(manifest["frames"], key=lambda f: int(f["index"]))
    index = np.array([int(f["index"]) for f in frames])
    times = np.array([float(f["time_s"]) for f in frames])
    fit_params = params.tracker.fit
    R, t, w = interpolate_track(key_t, key_R, key_tr, key_w, times, fit_params.weight_min, fit_params.weight_max)
    fitted_index = {int(key_frames[k]["index"]): result.fits[k] for k in fitted}
    reproj = np.array([fitted_index[i].mean_residual_px if i in fitted_index else np.nan for i in index])
    out = TrackOutput(ctx.out)
    out.write_tracking(
        index=index, time_s=times,
        full_on=np.array([f.get("light") == "F" for f in frames]),
        fitted=np.array([int(i) in fitted_index for i in index]),
        weights=w.astype(np.float32), expression_names=np.array(rig.names, dtype=str),
        world_from_head_R=R, world_from_head_t=t, landmark_reproj_px=reproj)
    vertices = rig.mesh(w).astype(np.float32)  # [T, V, 3]
    out.write_meshes(index, vertices, rig.faces.astype(np.int32))
    emb = result.embedding
    out.write_embedding(emb.landmark_ids, emb.triangles, emb.barycentric)
    out.write_cameras(cams)
    if params.obj_frames:
        out.make_obj_dir()
        for k in np.unique(np.linspace(0, len(index) - 1, params.obj_frames).round().astype(int)):
            _write_obj(out.obj_path(index[k]), vertices[k], rig.faces)
    residuals = np.array([fitted_index[i].mean_residual_px for i in fitted_index])
    dropped = sum(len(fit.dropped_views) for fit in fitted_index.values())
    return {
        "landmark_reproj_px_mean": float(np.nanmean(residuals)),
        "landmark_reproj_px_max": float(np.nanmax(residuals)),
        "frames": len(index), "full_on_frames": len(key_frames), "fitted_frames": len(fitted),
        "unfitted_full_on_frames": len(key_frames) - len(fitted), "views_dropped_by_fit": dropped,
        "landmarks_tracked": len(emb.landmark_ids), "blendshapes": rig.num_shapes,
        "outline_frames": sum(1 for fit in fitted_index.values() if fit.outline_pairs),
    }


def _write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def _write_overlay(ctx: StageContext, params: TrackParams, capture: CaptureOutput, rig: ActorRig, cams: list[Camera],
                   key_frames: list[dict], uv_all: np.ndarray, result: TrackResult) -> None:
    from scene.image_io import read_exr

    fitted = [k for k, fit in enumerate(result.fits) if fit is not None]
    if not params.overlay_frames or not fitted:
        return
    chosen = [fitted[i] for i in np.unique(np.linspace(0, len(fitted) - 1, params.overlay_frames).round().astype(int))]
    edges = mesh_edges(rig.faces, topology.face_vertex_mask(rig.num_vertices), max_edges=6000)
    ids = result.embedding.landmark_ids
    tiles = []
    for k in chosen:
        pose = result.fits[k].pose
        verts_world = rig.mesh(pose.weights) @ pose.R.T + pose.t
        lm_world = result.embedding.points(rig.faces, rig.mesh(pose.weights)) @ pose.R.T + pose.t
        for c, cam in enumerate(cams):
            path = capture.frame_path(cam.name, int(key_frames[k]["index"]))
            try:
                image = to_detector_image(read_exr(path), params.detector)
            except ValueError:
                image = None
            if image is None:
                image = np.zeros((cam.height, cam.width, 3), np.uint8)
            label = f"{cam.name} frame {key_frames[k]['index']}"
            tiles.append(draw_view(image, cam, verts_world, edges, uv_all[k, c, ids], lm_world, label))
    sheet = contact_sheet(tiles, columns=len(cams), tile_width=min(320, cams[0].width))
    write_png8(TrackOutput(ctx.out).overlay_path, sheet)


def _run_from_meshes(ctx: StageContext, params: TrackParams, capture: CaptureOutput, manifest: dict,
                     cams: list[Camera], rig: ActorRig) -> None:
    """``track.source``: poses and weights from given meshes (``stages.track.from_meshes``), the same outputs."""
    from stages.track.from_meshes import read_mesh_source, track_from_meshes

    frames = sorted(manifest["frames"], key=lambda f: int(f["index"]))
    index = np.array([int(f["index"]) for f in frames])
    times = np.array([float(f["time_s"]) for f in frames])
    source = read_mesh_source(params.source, rig.num_vertices, index, params.mesh_source.units_m)
    fit = params.tracker.fit
    track = track_from_meshes(rig, source, index, times, params.mesh_source, fit.weight_min, fit.weight_max, ctx.log)
    out = TrackOutput(ctx.out)
    out.write_tracking(
        index=index, time_s=times, full_on=np.array([f.get("light") == "F" for f in frames]), fitted=track.given,
        weights=track.weights.astype(np.float32), expression_names=np.array(rig.names, dtype=str),
        world_from_head_R=track.world_from_head_R, world_from_head_t=track.world_from_head_t,
        landmark_reproj_px=np.full(len(index), np.nan))
    out.write_meshes(index, track.vertices_head, rig.faces.astype(np.int32))
    # No landmarks were detected or embedded: empty tables keep the output's layout.
    out.write_embedding(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)))
    out.write_landmarks(index=np.zeros(0, np.int64), cameras=np.array([c.name for c in cams]),
                        uv_px=np.zeros((0, len(cams), NUM_FACEMESH_LANDMARKS, 2), np.float32),
                        score=np.zeros((0, len(cams))), status=np.zeros((0, len(cams)), dtype=str),
                        contour_px=np.zeros((0, 2), np.float32), contour_count=np.zeros((0, len(cams)), np.int64))
    out.write_cameras(cams)
    if params.obj_frames:
        out.make_obj_dir()
        for k in np.unique(np.linspace(0, len(index) - 1, params.obj_frames).round().astype(int)):
            _write_obj(out.obj_path(index[k]), track.vertices_head[k], rig.faces)
    ctx.metrics.update({
        "frames": len(index), "full_on_frames": int(sum(f.get("light") == "F" for f in frames)),
        "source_meshes": len(source.index), "interpolated_frames": int((~track.given).sum()),
        "source_stable_residual_mm_mean": float(track.stable_residual_mm.mean()),
        "source_rig_fit_residual_mm_mean": float(track.rig_residual_mm.mean()),
        "blendshapes": rig.num_shapes,
    })


def run(ctx: StageContext) -> None:
    """Detect, embed, fit, interpolate, write (see the module docstring); or pose given meshes (``source``)."""
    params: TrackParams = ctx.params  # type: ignore[assignment]
    capture = CaptureOutput(ctx.input("capture"))
    manifest = capture.manifest()
    rig = load_scan_rig(capture)
    if params.source:
        _run_from_meshes(ctx, params, capture, manifest, _cameras(ctx, manifest), rig)
        return
    key_frames = _full_on_frames(manifest, capture)
    cams = _cameras(ctx, manifest)
    try:
        ids = landmark_subset(params.landmark_groups)
        align_ids = landmark_subset(params.align_groups)
    except ValueError as err:
        raise InputError(f"track.landmark_groups / align_groups: {err}") from err

    start = time.perf_counter()
    uv_all, score, status, contours = _detect(ctx, params, capture, cams, key_frames)
    detect_s = time.perf_counter() - start
    flat = [c for per_view in contours for c in per_view]
    TrackOutput(ctx.out).write_landmarks(index=np.array([int(f["index"]) for f in key_frames]),
                        cameras=np.array([c.name for c in cams]), uv_px=uv_all.astype(np.float32), score=score,
                        status=np.array(status, dtype=str),
                        contour_px=np.concatenate(flat).astype(np.float32) if flat else np.zeros((0, 2), np.float32),
                        contour_count=np.array([[len(c) for c in per_view] for per_view in contours]))
    usable = (score > 0).sum(1)
    if usable.max(initial=0) < 2:
        raise InputError(f"{capture.path}: no full-on frame has a face detected in two or more cameras "
                         f"(views rejected: {sorted({s for row in status for s in row if s != 'ok'})}); "
                         "check the images (exposure, framing) in the capture's contact sheet")

    used = np.union1d(ids, align_ids)
    tracker = Tracker(rig, cams, topology.skin_triangles(rig.faces, rig.num_vertices),
                      topology.head_reference(rig.neutral_m, used), params.tracker, ctx.log,
                      fit_ids=ids, align_ids=align_ids)
    names = [str(f["index"]) for f in key_frames]
    observations = KeyFrameObservations(uv_all[:, :, used], score, used, contours)
    with ctx.progress(len(key_frames), "frames") as progress:
        try:
            result = tracker.run(observations, names, on_frame=progress.advance)
        except ValueError as err:
            raise InputError(f"{capture.path}: {err}") from err
    for message in result.warnings:
        ctx.log.warning(message)
    metrics = _write_outputs(ctx, params, rig, cams, manifest, key_frames, result)
    _write_overlay(ctx, params, capture, rig, cams, key_frames, uv_all, result)
    metrics.update({
        "fit_frames_per_second": len(key_frames) / max(result.fit_seconds, 1e-9),
        "detect_seconds": detect_s,
        "detect_views_per_second": uv_all.shape[0] * uv_all.shape[1] / max(detect_s, 1e-9),
        "views_rejected_by_detector": int((score == 0).sum()),
    })
    ctx.metrics.update(metrics)


def _external(params: TrackParams) -> list[Path]:
    return [Path(params.source).expanduser()] if params.source else []


STAGE = Stage(name="track", inputs=("capture", "calibrate"), params=TrackParams, run=run, external_inputs=_external,
              doc="Landmark blendshape tracking on full-on frames; pose and weights for every frame.")
