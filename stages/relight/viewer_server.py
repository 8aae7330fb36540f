"""The web side of ``pipeline view``: an aiohttp server streaming ``LookDevSession`` frames to a page.

Why aiohttp: one well-kept library gives both the HTTP routes and the WebSocket (framing,
ping/pong, close handshake) on asyncio, with no separate ASGI server; the frames are rendered
in a worker thread so the event loop keeps answering while the network runs.

Routes (nothing else is served; no route maps a request onto the file system):

- ``GET /``: the page (``viewer_page.html``, read once at start-up);
- ``GET /api/info``: the subject, the map catalogue (with each unreadable map's error), the
  number of tracked expressions, the render size and the default state;
- ``GET /api/map/{id}.jpg``: a thumbnail of a catalogue map, looked up by id; any other id
  (a path included) is a 404 with a JSON error;
- ``GET /ws``: the page sends ``{"type": "state", "seq": n, "state": {...}}`` (``LookState``
  fields); the server answers with ``{"type": "frame", "seq", "info", "fps"}`` then the JPEG
  as a binary message, or ``{"type": "error", "seq", "message"}``. Only the newest state is
  rendered: states that arrive during a render replace each other, so a drag never queues up.

A dropped connection ends its handler; the server keeps serving every other page.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from aiohttp import WSMsgType, web

from stages.relight.lookdev import LookDevSession, LookState, RequestError

CODE_FILES = ("viewer_page.html",)  # read at start-up; part of the code, like a module
PAGE = Path(__file__).with_name(CODE_FILES[0])
log = logging.getLogger("pipeline.view")


def encode_jpeg(image_srgb8: np.ndarray, quality: int = 92) -> bytes:
    """An RGB uint8 image as JPEG bytes."""
    import cv2

    ok, data = cv2.imencode(".jpg", np.ascontiguousarray(image_srgb8[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError("could not encode a preview frame as JPEG")
    return data.tobytes()


class FrameRate:
    """Frames per second over the last ``window_s`` seconds."""

    def __init__(self, window_s: float = 2.0) -> None:
        self.window_s, self.times = window_s, deque()

    def tick(self, now: float) -> float:
        self.times.append(now)
        while self.times and now - self.times[0] > self.window_s:
            self.times.popleft()
        if len(self.times) < 2:
            return 0.0
        return (len(self.times) - 1) / max(self.times[-1] - self.times[0], 1e-6)


def build_app(session: LookDevSession, subject: str) -> web.Application:
    """The viewer's aiohttp application for ``session``."""
    page = PAGE.read_text()
    renderer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="lookdev")
    app = web.Application()

    async def index(request: web.Request) -> web.Response:
        return web.Response(text=page, content_type="text/html")

    async def info(request: web.Request) -> web.Response:
        s = session.settings
        return web.json_response({
            "subject": subject, "maps": session.maps.describe(), "expressions": session.num_expressions,
            "width": s.width_px, "height": s.height_px, "bake_rank": s.bake_rank, "directions": s.directions,
            "default_state": {"map": next((m["id"] for m in session.maps.describe() if m["ok"]), ""),
                              "distance_m": LookState().distance_m, "light_head_m": list(LookState().light_head_m)}})

    async def map_thumbnail(request: web.Request) -> web.Response:
        map_id = request.match_info["map_id"]
        try:
            image = await asyncio.get_running_loop().run_in_executor(renderer, session.maps.preview, map_id)
        except RequestError as err:
            return web.json_response({"error": str(err)}, status=404)
        return web.Response(body=encode_jpeg(image), content_type="image/jpeg")

    async def websocket(request: web.Request) -> web.WebSocketResponse:
        ws = web.WebSocketResponse(heartbeat=20.0, max_msg_size=1 << 16)
        await ws.prepare(request)
        latest: dict = {}
        wake = asyncio.Event()
        rate = FrameRate()

        async def render_loop() -> None:
            loop = asyncio.get_running_loop()
            while not ws.closed:
                await wake.wait()
                wake.clear()
                seq, message = latest.pop("seq", None), latest.pop("state", None)
                if message is None:
                    continue
                try:
                    state = LookState.from_request(message, session.num_expressions)
                    frame = await loop.run_in_executor(renderer, session.render, state)
                    jpeg = await loop.run_in_executor(renderer, encode_jpeg, frame.image_srgb8)
                except RequestError as err:
                    await ws.send_json({"type": "error", "seq": seq, "message": str(err)})
                    continue
                except Exception as err:  # a render failing must not take the page (or the server) down
                    log.exception("view: frame %s failed", seq)
                    await ws.send_json({"type": "error", "seq": seq, "message": f"render failed: {err}"})
                    continue
                await ws.send_json({"type": "frame", "seq": seq, "info": frame.info(),
                                    "fps": rate.tick(time.perf_counter())})
                await ws.send_bytes(jpeg)

        task = asyncio.create_task(render_loop())
        try:
            async for msg in ws:
                if msg.type != WSMsgType.TEXT:
                    continue
                try:
                    data = json.loads(msg.data)
                except ValueError:
                    await ws.send_json({"type": "error", "seq": None, "message": "a viewer message must be JSON"})
                    continue
                if not isinstance(data, dict) or data.get("type") != "state":
                    await ws.send_json({"type": "error", "seq": None,
                                        "message": "unknown message; send {\"type\": \"state\", \"state\": {...}}"})
                    continue
                latest["seq"], latest["state"] = data.get("seq"), data.get("state")
                wake.set()
        except (ConnectionResetError, asyncio.CancelledError):
            pass
        finally:
            task.cancel()
            try:
                await task
            except (asyncio.CancelledError, ConnectionResetError, RuntimeError):
                pass  # the page went away mid-frame: nothing to send it
            except Exception:
                log.exception("view: connection ended with an error")
        return ws

    async def shutdown(app: web.Application) -> None:
        renderer.shutdown(wait=False, cancel_futures=True)

    app.router.add_get("/", index)
    app.router.add_get("/api/info", info)
    app.router.add_get("/api/map/{map_id}.jpg", map_thumbnail)
    app.router.add_get("/ws", websocket)
    app.on_cleanup.append(shutdown)
    return app


async def serve(app: web.Application, host: str, port: int, ready=None) -> None:
    """Serve ``app`` on ``host:port`` (0: any free port) until cancelled; ``ready(url)`` once listening."""
    runner = web.AppRunner(app, handle_signals=False)
    await runner.setup()
    site = web.TCPSite(runner, host, port)
    await site.start()
    bound = runner.addresses[0]
    url = f"http://{'[' + host + ']' if ':' in host else host}:{bound[1]}/"
    if ready is not None:
        ready(url)
    try:
        while True:
            await asyncio.sleep(3600)
    finally:
        await runner.cleanup()


__all__ = ["FrameRate", "build_app", "encode_jpeg", "serve"]
