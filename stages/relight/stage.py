"""Relight stage: renders of the trained head under environment maps, point lights, new views and expressions.

Inputs: ``train`` (``models/ours``, loaded with ``avatar.io.load_trained``), ``track``
(``meshes.npz``: the tracked head-space meshes; the first is the default expression) and
``capture`` (``scans/scans.npz``: the actor rig that drives novel expressions).

Output (every sequence in its own folder)::

    <sequence>/frames/<i:06d>.exr     linear RGBA (float16), head at the origin, black backdrop
    <sequence>/previews/<i:06d>.png   sRGB preview (exposure fixed from the first frame)
    <sequence>/<sequence>.mp4         the previews as a video
    renders.json                      per sequence and frame: camera, lights, mesh index, map, path
    paths.json                        per sequence: the path its frames took ("bake" or "voxel_sum") and why
    meshes.npz                        the driving meshes used ("default": [1, V, 3], "expressions")
    metrics.json                      envmap_seconds_per_frame, naive_envmap_seconds_per_frame, bake_*, ...

Environment maps render with the voxel-space light sum (decode every light, one raymarch per
frame) or from a light-transfer bake of the view and expression (``avatar.bake``: a weighted
sum of basis images per frame, no network). ``envmap_path`` "auto" bakes a (view, expression)
once ``bake_min_frames`` envmap frames share it (one bake serves every map and rotation; it
costs about as much as a few sum frames), which needs the paper's uniform cell-centre lights;
point lights, turntables, dolly zooms and new views or expressions stay on the network.
``paths.json`` and each frame's ``path`` in ``renders.json`` say which path was taken.

Timings measured in this process, one after the other (the workers' own timings overlap each
other and any other job): the naive render-each-light path against the voxel-space sum on
``naive_timing_frames`` frames (checked to agree), and, with ``bake_check``, one bake
(``bake_seconds``), then its frames (``bake_frame_seconds``: projecting the turned map onto the
baked directions plus the weighted sum) against the voxel-space sum of the same frames on
``bake_check_envmaps`` at ``bake_check_rotations_deg`` (``bake_psnr_vs_sum_db``, the mean;
``bake_speedup_vs_sum``). ``envmap_seconds_per_frame`` is the mean of this process's
voxel-space-sum timings (the workers', ``envmap_worker_seconds_per_frame``, without any).

Frames fan out through ``ctx.executor`` (GPU items on CUDA) and are cached per frame in the
stage's ``cache_dir`` (key: checkpoint digest, driving mesh, camera, lights, settings), so a
rerun renders only frames it has not rendered before (metrics ``frames_reused``,
``frames_computed``); seconds per frame are those measured when each frame was rendered.
Bakes are kept in the same cache (``stages.relight.bake.bake_key``: checkpoint digest, driving
mesh, camera, baked directions, rank and settings, code version; ``bakes_reused``,
``bakes_computed``); frames from a bake are not cached (a weighted sum is cheaper than a read).
"""

from __future__ import annotations

from pathlib import Path

from pipeline.stage import Stage, StageContext
from stages.relight.params import RelightParams, check_maps, resolve_envmap
from stages.relight.render_all import render_all


def run(ctx: StageContext) -> None:
    """``render_all`` over the stage's folders, executor and log."""
    ctx.metrics.update(render_all(ctx.inputs, ctx.params, ctx.out, ctx.cache_dir, ctx.log,  # type: ignore[arg-type]
                                  ctx.executor))


def _external(params: RelightParams) -> list[Path]:
    files = [resolve_envmap(m) for m in dict.fromkeys(params.envmaps + check_maps(params))]
    files += [Path(p) for p in (params.expressions_csv, params.expressions_obj_dir) if p]
    return files


STAGE = Stage(
    name="relight",
    inputs=("train", "track", "capture"),
    params=RelightParams,
    run=run,
    external_inputs=_external,
    doc="Render the trained head under environment maps, point lights, new views and expressions (EXR, PNG, MP4).",
)
