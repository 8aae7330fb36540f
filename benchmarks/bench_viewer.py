"""``pipeline view``'s frame times per render path, at two resolutions, and end to end over its WebSocket.

The head is ``BAKE_SUBJECT``'s trained one (default alice; the random tiny head when none is
trained), as in ``bench_relight``. Per resolution, in one process, one thread:

- ``bake`` frames: the map turned over a held view (the viewer's common case), against
- ``voxel_sum`` frames of the same states (the reference: what a moving camera gets);
- ``network``: a point light alone; ``bake+light``: a turned map plus a point light;
- the one-off bake of a view, and the JPEG encode of a frame.

Then the server itself (``stages.relight.viewer_server``, in this process on a free port): a
client sends a map rotation, waits for its frame and sends the next, and the frames it gets a
second are timed (render, encode, WebSocket and event loop included).

Cost grows with pixels: a bake frame is R * pixels * 3 multiply-adds, the bake itself is one
decode of D lights plus D transport products over the pixels, a network frame one raymarch.

Writes ``bench-results/viewer.json``.
"""

from __future__ import annotations

import asyncio
import json
import statistics
import threading
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.bench_relight import _bake_head

OUT = Path(__file__).resolve().parents[1] / "bench-results"
SIZES = ((96, 128), (192, 256))
ROTATIONS = tuple(range(0, 360, 36))


def _session(model, mesh, image_scale: float, width: int, height: int):
    from stages.relight.lookdev import LookDevSession, LookSettings, MapCatalogue
    from stages.relight.params import ASSETS

    maps = MapCatalogue([("studio.exr", ASSETS / "blender-cc0" / "studio.exr")])
    return LookDevSession(model, image_scale, mesh[None], maps, LookSettings(width_px=width, height_px=height))


def _ms(session, states) -> tuple[float, list[str]]:
    times, paths = [], []
    for state in states:
        frame = session.render(state)
        times.append(1e3 * frame.seconds)
        paths.append(frame.path)
    return statistics.median(times), sorted(set(paths))


def path_figures(model, mesh, image_scale: float, width: int, height: int) -> dict:
    from stages.relight.lookdev import LookState
    from stages.relight.viewer_server import encode_jpeg

    session = _session(model, mesh, image_scale, width, height)
    held = LookState(map_id="studio")
    session.render(held)  # warm-up, and the first sight of the view
    first = session.render(held)  # the view held: bakes now
    turned = [LookState(map_id="studio", rotation_deg=r) for r in ROTATIONS]
    bake_ms, bake_paths = _ms(session, turned)
    # The reference, same states: a fresh session has no bake, and a camera that moves by a
    # hair each frame never holds still, so every frame takes the voxel-space sum.
    reference = _session(model, mesh, image_scale, width, height)
    moving = [LookState(map_id="studio", rotation_deg=r, azimuth_deg=1e-6 * i) for i, r in enumerate(ROTATIONS)]
    sum_ms, sum_paths = _ms(reference, moving)
    lit = [LookState(map_id="studio", rotation_deg=r, light_on=True) for r in ROTATIONS]
    lit_ms, _ = _ms(session, lit)
    point = [LookState(light_on=True, light_head_m=(float(x), 0.3, 1.0)) for x in np.linspace(-1, 1, len(ROTATIONS))]
    point_ms, _ = _ms(session, point)
    image = session.render(turned[0]).image_srgb8
    encode_jpeg(image)  # warm-up
    start = time.perf_counter()
    for _ in range(20):
        encode_jpeg(image)
    jpeg_ms = 1e3 * (time.perf_counter() - start) / 20
    return {"width": width, "height": height, "bake_seconds": first.bake_seconds,
            "bake_frame_ms": bake_ms, "bake_paths": bake_paths, "voxel_sum_frame_ms": sum_ms, "sum_paths": sum_paths,
            "bake_speedup_vs_sum": sum_ms / max(bake_ms, 1e-9), "bake_plus_point_light_ms": lit_ms,
            "point_light_ms": point_ms, "jpeg_ms": jpeg_ms}


def websocket_fps(model, mesh, image_scale: float, width: int, height: int, frames: int = 60) -> dict:
    """Frames a second a client gets while it turns the map over a held view, one frame in flight."""
    import aiohttp

    from stages.relight.viewer_server import build_app, serve

    session = _session(model, mesh, image_scale, width, height)
    loop = asyncio.new_event_loop()
    ready = threading.Event()
    found: dict = {}

    def on_ready(url: str) -> None:
        found["url"] = url
        ready.set()

    task = loop.create_task(serve(build_app(session, "bench"), "127.0.0.1", 0, on_ready))
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    ready.wait(60)

    async def client() -> list[float]:
        stamps = []
        async with aiohttp.ClientSession() as http, http.ws_connect(found["url"].replace("http", "ws") + "ws") as ws:
            for i in range(frames + 2):
                await ws.send_json({"type": "state", "seq": i, "state": {"map": "studio", "rotation_deg": 6.0 * i}})
                while (await ws.receive()).type != aiohttp.WSMsgType.BINARY:
                    pass
                stamps.append(time.perf_counter())
        return stamps[2:]  # the first two frames see the view and bake it

    stamps = asyncio.run(client())
    loop.call_soon_threadsafe(task.cancel)
    time.sleep(0.2)
    loop.call_soon_threadsafe(loop.stop)
    thread.join(10)
    fps = (len(stamps) - 1) / (stamps[-1] - stamps[0])
    return {"width": width, "height": height, "frames": len(stamps), "fps": fps, "ms_per_frame": 1e3 / fps}


def main() -> None:
    torch.set_num_threads(1)
    OUT.mkdir(exist_ok=True)
    model, mesh, image_scale, what = _bake_head()
    results: dict = {"head": what, "threads": 1, "paths": [], "websocket": []}
    for width, height in SIZES:
        figures = path_figures(model, mesh, image_scale, width, height)
        results["paths"].append(figures)
        print("viewer paths:", json.dumps(figures), flush=True)
        ws = websocket_fps(model, mesh, image_scale, width, height)
        results["websocket"].append(ws)
        print("viewer websocket:", json.dumps(ws), flush=True)
    (OUT / "viewer.json").write_text(json.dumps(results, indent=1))
    print(f"wrote {OUT / 'viewer.json'}")


if __name__ == "__main__":
    main()
