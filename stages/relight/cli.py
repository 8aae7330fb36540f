"""``pipeline render``: an artist's render of a trained head, outside the stage graph.

Examples::

    pipeline render -S alice --envmap assets/envmaps/blender-cc0/sunrise.exr --rotate-deg-per-frame 5 --frames 72
    pipeline render -S alice --point-light 0.5,0.3,1.0 --out renders/key
    pipeline render -S alice --orbit 3.0 --frames 48
    pipeline render -S alice --turntable --dolly-zoom --frames 36
    pipeline render -S alice --camera 0.3,0.1,0.5 --camera -0.2,0,0.25
    pipeline render -S alice --expressions weights.csv --envmap studio.exr
    pipeline render -S alice --olat-basis 256

It reads the subject's current ``train``, ``track`` and ``capture`` outputs from its
workspace (run ``pipeline run -S alice --only train`` first) and writes, under ``--out``
(default ``renders/<subject>``), one folder per sequence: linear EXR frames, sRGB PNG
previews and an MP4, plus ``renders.json``. Frames are written as they complete.

``--olat-basis D`` writes the head's virtual one-light-at-a-time renders for the default view
(or each ``--camera``) and the first tracked expression: ``olat/olat_<D>dirs.exr``, a multi-part
EXR with one RGBA part per direction (the paper's D uniform directions), and a JSON of the
directions, their solid angles and how ``--envmap`` weights them (``stages.relight.olat``).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import warnings
from pathlib import Path

from pipeline.errors import ConfigError, InputError, PipelineError


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="pipeline render", description="Render a trained head: environment maps, "
                                "point lights, new views, new expressions (EXR + PNG + MP4).")
    p.add_argument("-S", "--subject", required=True, help="subject (workspace) name, e.g. alice")
    p.add_argument("--workspaces", default=None, help="workspace root (default: $PIPELINE_WORKSPACES or ./workspaces)")
    p.add_argument("--envmap", action="append", default=[], help="lat-long EXR environment map (repeatable)")
    p.add_argument("--rotate-deg-per-frame", type=float, default=0.0, help="turn the map about +y each frame, degrees")
    p.add_argument("--frames", type=int, default=24, help="frames per sequence")
    p.add_argument("--point-light", action="append", default=[], help="x,y,z in metres, head space (+z = in front)")
    p.add_argument("--orbit", type=float, default=0.0, help="point light orbiting the head at this radius, metres")
    p.add_argument("--camera", action="append", default=[], help="camera position x,y,z in metres, head space, "
                   "looking at the head (repeatable; with --olat-basis: the OLAT views)")
    p.add_argument("--turntable", action="store_true", help="swing the camera around the head")
    p.add_argument("--dolly-zoom", action="store_true", help="push in while widening the field of view")
    p.add_argument("--expressions", default="", help="blendshape CSV (ARKit names) or a folder of OBJ meshes")
    p.add_argument("--adaptive", action="store_true", help="choose envmap directions adaptively (fewer for soft maps)")
    p.add_argument("--directions", type=int, default=256, help="uniform envmap directions (the paper's 256)")
    p.add_argument("--olat-basis", type=int, default=0, metavar="DIRS",
                   help="write one-light-at-a-time layers for DIRS uniform directions (multi-part EXR + JSON) for the "
                        "default view (or each --camera) and the first tracked expression")
    p.add_argument("--olat-float", action="store_true", help="OLAT layers as 32-bit float (default: half)")
    p.add_argument("--width", type=int, default=256, help="image width, pixels")
    p.add_argument("--height", type=int, default=320, help="image height, pixels")
    p.add_argument("--device", default="auto", help="auto, cpu or cuda")
    p.add_argument("--out", default="", help="output folder (default renders/<subject>)")
    return p


def stage_folder(workspace, stage: str) -> Path:
    """The object folder of ``stage``'s current output in ``workspace``; ``InputError`` saying what to run if none."""
    ref = workspace.read_ref(stage)
    if ref is None or "out" not in ref.outputs:
        raise InputError(f"subject '{workspace.subject}' has no '{stage}' output yet; run "
                         f"`pipeline run -S {workspace.subject} --only {stage}` (or the whole pipeline) first")
    return workspace.object_path(ref.outputs["out"])


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``pipeline render``; returns the exit code (0 ok, 1 bad input, 2 usage)."""
    try:
        args = _parser().parse_args(argv)
    except SystemExit as exit_:
        return int(exit_.code or 0)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    log = logging.getLogger("render")
    try:
        return _render(args, log)
    except PipelineError as err:
        print(f"error: {err}", file=sys.stderr)
        return err.exit_code


def _render(args: argparse.Namespace, log: logging.Logger) -> int:
    from pipeline.executors import LocalExecutor
    from pipeline.project import find_project_root
    from pipeline.workspace import Workspace, workspace_root
    from stages.evaluate.limits import workspace_light_warnings
    from stages.relight.params import RelightParams
    from stages.relight.render_all import render_all
    from stages.relight.sequences import read_light_position

    if args.frames < 1:
        raise ConfigError(f"--frames {args.frames}: must be at least 1")
    try:
        points = tuple(tuple(read_light_position(t)) for t in args.point_light)
    except ValueError as err:
        raise ConfigError(f"--point-light: {err}") from None
    try:
        eyes = tuple(tuple(read_light_position(t)) for t in args.camera)
    except ValueError as err:
        raise ConfigError(f"--camera: {str(err).replace('point light', 'camera')}") from None
    if args.directions < 1:
        raise ConfigError(f"--directions {args.directions}: must be at least 1")
    if args.olat_basis < 0:
        raise ConfigError(f"--olat-basis {args.olat_basis}: give a number of directions, e.g. 256")
    sequences = bool(args.envmap or points or args.orbit or args.turntable or args.dolly_zoom or args.expressions
                     or (eyes and not args.olat_basis))
    nothing = not (sequences or eyes or args.olat_basis)
    expr = Path(args.expressions) if args.expressions else None
    if expr is not None and not expr.exists():
        raise InputError(f"--expressions {expr}: no such file or folder")
    params = RelightParams(
        envmaps=tuple(args.envmap), envmap_frames=args.frames if args.envmap else 0,
        rotate_deg_per_frame=args.rotate_deg_per_frame, light_method="adaptive" if args.adaptive else "uniform",
        orbit_radius_m=args.orbit, orbit_frames=args.frames if args.orbit > 0 else 0, point_lights=points,
        camera_eyes=() if args.olat_basis else eyes, turntable_frames=args.frames if (args.turntable or nothing) else 0,
        dolly_zoom_frames=args.frames if args.dolly_zoom else 0,
        expressions_csv=str(expr) if expr is not None and expr.is_file() else "",
        expressions_obj_dir=str(expr) if expr is not None and expr.is_dir() else "",
        width_px=args.width, height_px=args.height, device=args.device, naive_timing_frames=0, bake_check=False,
        directions=args.directions)
    root = find_project_root()
    workspace = Workspace(workspace_root(root, args.workspaces), args.subject)
    inputs = {s: stage_folder(workspace, s) for s in ("train", "track", "capture")}
    # The evaluate stage's measured warning zone (nothing when the subject was never evaluated).
    for message in workspace_light_warnings(workspace, points, args.orbit, args.frames if args.orbit > 0 else 0):
        log.warning(message)
    out = Path(args.out) if args.out else root / "renders" / args.subject
    out.mkdir(parents=True, exist_ok=True)
    if args.olat_basis:
        from stages.relight.olat import export_olat_basis

        export_olat_basis(inputs, params, args.olat_basis, out, list(eyes), log, half=not args.olat_float)
        if not sequences:
            print(f"OLAT basis in {out / 'olat'}")
            return 0
    # Frames and bakes are cached beside the renders: rendering more frames into the same folder
    # renders only the new ones.
    (out / ".cache").mkdir(exist_ok=True)
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        logging.captureWarnings(True)
        metrics = render_all(inputs, params, out, out / ".cache", log, LocalExecutor(workers=1))
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1, sort_keys=True))
    print(f"renders in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
