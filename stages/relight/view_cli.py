"""``pipeline view``: an interactive look-development viewer of a trained head, in the browser.

Examples::

    pipeline view -S alice
    pipeline view -S alice --envmap ~/maps/stage.exr --port 9000
    pipeline view -S alice --width 144 --height 192 --host 0.0.0.0   # reachable from other machines

It reads the subject's current ``train`` and ``track`` outputs, serves the viewer on
127.0.0.1 (``--host`` to change) and prints the URL. In the page: drag to rotate the
environment map (or, by the mode chosen, orbit the camera or move the point light), pick a
map, scrub the tracked expressions; the page shows the frame rate and the path each frame
took (``bake``, ``voxel_sum`` or ``network``; see ``stages.relight.lookdev``).

The server serves only the maps given with ``--envmap`` and those shipped under
``assets/envmaps``: requests name a map by its id, and no path from a request is opened. A
map that cannot be read is listed in the page with its error; the rest still serve.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
from pathlib import Path

from pipeline.errors import ConfigError, PipelineError


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="pipeline view", description="Interactive look-development viewer of a "
                                "trained head in the browser: environment maps, a point light, camera, expressions.")
    p.add_argument("-S", "--subject", required=True, help="subject (workspace) name, e.g. alice")
    p.add_argument("--workspaces", default=None, help="workspace root (default: $PIPELINE_WORKSPACES or ./workspaces)")
    p.add_argument("--envmap", action="append", default=[], help="lat-long EXR map to offer, besides the shipped "
                   "ones (repeatable)")
    p.add_argument("--no-shipped-maps", action="store_true", help="offer only the --envmap maps")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, default=8765, help="port (0: any free one)")
    p.add_argument("--width", type=int, default=96, help="render width, pixels (the page scales it up)")
    p.add_argument("--height", type=int, default=128, help="render height, pixels")
    p.add_argument("--bake-rank", type=int, default=32, help="images in each bake's basis (0: one per direction)")
    p.add_argument("--directions", type=int, default=256, help="uniform directions a map is projected onto")
    p.add_argument("--device", default="auto", help="auto, cpu or cuda")
    p.add_argument("--threads", type=int, default=0, help="CPU threads for rendering (0: torch's default)")
    return p


def map_files(given: list[str], shipped: bool) -> list[tuple[str, Path]]:
    """(label, file) of every map the viewer may serve: the given ones first, then the shipped ones."""
    from stages.relight.params import ASSETS

    files = [(Path(g).name, Path(g).expanduser()) for g in given]
    if shipped:
        files += [(p.relative_to(ASSETS).as_posix(), p) for p in sorted(ASSETS.rglob("*.exr"))]
    return files


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``pipeline view``; serves until interrupted. Exit code 0, 1 bad input, 2 usage."""
    try:
        args = _parser().parse_args(argv)
    except SystemExit as exit_:
        return int(exit_.code or 0)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        return _view(args)
    except PipelineError as err:
        print(f"error: {err}", file=sys.stderr)
        return err.exit_code
    except KeyboardInterrupt:
        return 0


def _view(args: argparse.Namespace) -> int:
    import torch

    from pipeline.devices import resolve_device
    from pipeline.project import find_project_root
    from pipeline.workspace import Workspace, workspace_root
    from stages.relight.cli import stage_folder
    from stages.relight.lookdev import LookSettings, load_session
    from stages.relight.viewer_server import build_app, serve

    if not 0 <= args.port <= 65535:
        raise ConfigError(f"--port {args.port}: give a port between 0 and 65535")
    if args.width < 8 or args.height < 8:
        raise ConfigError(f"--width {args.width} --height {args.height}: at least 8 pixels each")
    if args.directions < 1 or args.bake_rank < 0:
        raise ConfigError("--directions must be at least 1 and --bake-rank at least 0")
    files = map_files(args.envmap, not args.no_shipped_maps)
    if not files:
        raise ConfigError("no environment maps: give --envmap, or drop --no-shipped-maps")
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    device = resolve_device(args.device, "--device")
    workspace = Workspace(workspace_root(find_project_root(), args.workspaces), args.subject)
    inputs = {s: stage_folder(workspace, s) for s in ("train", "track")}
    settings = LookSettings(width_px=args.width, height_px=args.height, directions=args.directions,
                            bake_rank=args.bake_rank)
    session = load_session(inputs, files, settings, device)
    for entry in session.maps.describe():
        if not entry["ok"]:
            logging.getLogger("pipeline.view").warning("map %s is listed but cannot be used: %s", entry["label"],
                                                       entry["error"])

    def ready(url: str) -> None:
        print(f"pipeline view: {args.subject} at {url} (Ctrl-C to stop)", flush=True)

    try:
        asyncio.run(serve(build_app(session, args.subject), args.host, args.port, ready))
    except OSError as err:
        raise ConfigError(f"--host {args.host} --port {args.port}: cannot listen there ({err}); pick another "
                          "port, or 0 for any free one") from None
    return 0


if __name__ == "__main__":
    sys.exit(main())
