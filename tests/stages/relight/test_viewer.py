"""``pipeline view`` as a user runs it: the server in its own process, a client and a real browser.

The head is ``lambertian_head`` (its bright side faces the light), served from a workspace
laid out as the pipeline writes one, with a good map, a damaged one and one that is not 2:1
on the command line, and a readable map outside them that no request may reach.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from urllib.parse import quote

import numpy as np
import pytest

from scene.envmap import synthetic_sky, write_envmap
from scene.image_io import write_exr
from tests.stages.relight.conftest import lambertian_head

REPO = Path(__file__).resolve().parents[3]


def _write_workspace(root: Path, subject: str) -> None:
    from avatar.io import save_trained

    model, verts = lambertian_head()
    ws = root / subject
    save_trained(ws / "objects" / "digest_train" / "models" / "ours", model, "ours")
    (ws / "objects" / "digest_track").mkdir(parents=True)
    np.savez(ws / "objects" / "digest_track" / "meshes.npz", vertices=np.stack([verts, verts * 1.04, verts * 0.97]))
    (ws / "refs").mkdir()
    for stage in ("train", "track"):
        (ws / "refs" / f"{stage}.json").write_text(json.dumps(
            {"stage": stage, "action": "a", "outputs": {"out": f"digest_{stage}"}, "updated": ""}))


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    root = tmp_path_factory.mktemp("viewer")
    _write_workspace(root / "ws", "alice")
    maps = root / "maps"
    maps.mkdir()
    write_envmap(maps / "sky.exr", synthetic_sky(16, np.array([0.3, 0.8, 0.5]), 0.5, 8.0))
    (maps / "damaged.exr").write_bytes(b"\x76\x2f\x31\x01 and then nothing")
    write_exr(maps / "square.exr", np.ones((16, 16, 3), np.float32))
    secret = root / "secret.exr"  # readable, but never offered: no request may open it
    write_envmap(secret, synthetic_sky(16))
    log_path = root / "view.log"
    command = [sys.executable, "-m", "stages.relight.view_cli", "-S", "alice", "--workspaces", str(root / "ws"),
               "--no-shipped-maps", "--port", "0", "--width", "32", "--height", "40", "--directions", "48",
               "--bake-rank", "8", "--threads", "1", "--device", "cpu",
               *[a for m in ("sky.exr", "damaged.exr", "square.exr") for a in ("--envmap", str(maps / m))]]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    with open(log_path, "w") as log:
        proc = subprocess.Popen(command, cwd=REPO, stdout=log, stderr=subprocess.STDOUT, env=env,
                                start_new_session=True)
    url = None
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline and url is None and proc.poll() is None:
        time.sleep(0.2)
        for line in log_path.read_text().splitlines():
            if line.startswith("pipeline view: alice at "):
                url = line.split(" at ")[1].split()[0]
    if url is None:
        proc.kill()
        pytest.fail(f"pipeline view did not start:\n{log_path.read_text()}")
    yield {"url": url, "secret": secret, "log": log_path, "proc": proc}
    os.killpg(proc.pid, signal.SIGTERM)
    proc.wait(timeout=30)


def test_it_listens_on_localhost_and_lists_every_map(server):
    import urllib.request

    assert server["url"].startswith("http://127.0.0.1:")
    info = json.loads(urllib.request.urlopen(server["url"] + "api/info", timeout=30).read())
    maps = {m["id"]: m for m in info["maps"]}
    assert set(maps) == {"sky", "damaged", "square"}
    assert maps["sky"]["ok"] and not maps["damaged"]["ok"] and not maps["square"]["ok"]
    assert "2:1" in maps["square"]["error"] and "damaged.exr" in maps["damaged"]["error"]
    assert info["expressions"] == 3 and info["default_state"]["map"] == "sky"
    assert "square.exr" in server["log"].read_text()  # the operator is told at start-up too


def test_paths_in_requests_are_refused(server):
    import urllib.error
    import urllib.request

    secret = str(server["secret"])
    for path in (f"api/map/{quote(secret, safe='')}.jpg", "api/map/..%2Fsecret.jpg",
                 f"api/map/{quote('../../secret', safe='')}.jpg", "../secret.exr", "static/../../secret.exr"):
        with pytest.raises(urllib.error.HTTPError) as caught:
            urllib.request.urlopen(server["url"] + path, timeout=30)
        assert caught.value.code == 404, path
    thumb = urllib.request.urlopen(server["url"] + "api/map/sky.jpg", timeout=30)
    assert thumb.headers["Content-Type"] == "image/jpeg"


async def _frames(url: str, states: list[dict], timeout: float = 120.0) -> list[dict]:
    """Send each state and wait for its answer; returns the answers (frame info or error)."""
    import aiohttp

    answers = []
    async with aiohttp.ClientSession() as http, http.ws_connect(url.replace("http", "ws") + "ws") as ws:
        for seq, state in enumerate(states, 1):
            await ws.send_json({"type": "state", "seq": seq, "state": state})
            while True:
                msg = await ws.receive_json(timeout=timeout)
                if msg["type"] == "error":
                    answers.append(msg)
                    break
                if msg["type"] == "frame":
                    data = await ws.receive_bytes(timeout=timeout)
                    assert data[:2] == b"\xff\xd8", "a frame is a JPEG"
                    answers.append(msg)
                    break
    return answers


def test_bad_requests_get_an_error_and_the_server_keeps_serving(server):
    import aiohttp

    async def dropped() -> None:  # a page that goes away mid-frame
        async with aiohttp.ClientSession() as http:
            ws = await http.ws_connect(server["url"].replace("http", "ws") + "ws")
            await ws.send_json({"type": "state", "seq": 1, "state": {"map": "sky", "azimuth_deg": 33}})
            await ws.close()

    asyncio.run(dropped())
    answers = asyncio.run(_frames(server["url"], [
        {"map": str(server["secret"])}, {"map": "damaged"}, {"expression": 7}, {"distance_m": "far"},
        {"map": "sky"}]))
    assert [a["type"] for a in answers] == ["error"] * 4 + ["frame"]
    assert "unknown environment map" in answers[0]["message"]
    assert "could not be read" in answers[1]["message"]
    assert "unknown expression 7" in answers[2]["message"]
    assert "distance_m" in answers[3]["message"]
    assert server["proc"].poll() is None


def test_a_held_view_bakes_and_turning_the_map_reuses_it(server):
    answers = asyncio.run(_frames(server["url"], [
        {"map": "sky", "azimuth_deg": 50}, {"map": "sky", "azimuth_deg": 50},
        {"map": "sky", "azimuth_deg": 50, "rotation_deg": 90}, {"map": "sky", "azimuth_deg": 60}]))
    paths = [a["info"]["path"] for a in answers]
    assert paths == ["voxel_sum", "bake", "bake", "voxel_sum"], paths
    assert answers[1]["info"]["baked_now"] and not answers[2]["info"]["baked_now"]


# ---- in a real browser ---------------------------------------------------------------------------

def _browser():
    """(chromium, chromedriver) or a skip with its reason."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if chromium is None or driver is None:
        pytest.skip("Debian's chromium and chromium-driver are not installed (.ci/run installs them)")
    pytest.importorskip("selenium", reason="selenium (a test dependency) is not installed")
    return chromium, driver


@pytest.fixture(scope="module")
def page(server):
    chromium, chromedriver = _browser()
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--no-first-run",
                 "--window-size=1200,900"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(chromedriver), options=options)
    driver.set_script_timeout(120)
    try:
        driver.get(server["url"])
        yield driver
    finally:
        driver.quit()


def _wait(driver, condition: str, timeout: float = 120.0):
    """Wait until the JavaScript expression ``condition`` is truthy; returns its value."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = driver.execute_script(f"return ({condition});")
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {condition}; page error: "
                         f"{driver.execute_script('return window.viewer && window.viewer.error')}")


def _settled(driver) -> None:
    """Wait until no change is queued and the page shows the frame of the last state it sent.

    Without the queue check a change whose send waits on the next animation frame (late under
    load) passed as settled on the previous state's frame.
    """
    _wait(driver, "!window.viewer.queued && window.viewer.seq > 0 && window.viewer.shownSeq === window.viewer.seq")


_HIGHLIGHT_X = """
const img = document.getElementById('frame');
const c = document.createElement('canvas'); c.width = img.naturalWidth; c.height = img.naturalHeight;
const g = c.getContext('2d'); g.drawImage(img, 0, 0);
const d = g.getImageData(0, 0, c.width, c.height).data, lum = [];
for (let i = 0; i < d.length; i += 4) lum.push(d[i] + d[i + 1] + d[i + 2]);
const cut = [...lum].sort((a, b) => a - b)[Math.floor(0.9 * lum.length)];
let sx = 0, n = 0;
lum.forEach((v, i) => { if (v >= cut) { sx += i % c.width; n += 1; } });
return sx / n;
"""


def _set(driver, element_id: str, value) -> None:
    driver.execute_script(
        "const e = document.getElementById(arguments[0]);"
        "if (e.type === 'checkbox') e.checked = arguments[1]; else e.value = arguments[1];"
        "e.dispatchEvent(new Event(e.tagName === 'SELECT' || e.type === 'checkbox' ? 'change' : 'input'));",
        element_id, value)


def test_page_loads_and_shows_a_frame_rate(page):
    _settled(page)
    assert page.find_element("id", "path").text in ("bake", "voxel_sum")
    page.find_element("id", "frame")
    listed = page.find_element("id", "map-errors").text
    assert "square.exr" in listed and "damaged.exr" in listed


def test_dragging_rotates_the_map_and_changes_the_image(page):
    from selenium.webdriver import ActionChains

    _settled(page)
    before = page.execute_script("return window.viewer.digest")
    frame = page.find_element("id", "frame")
    chain = ActionChains(page).click_and_hold(frame)
    for _ in range(6):
        chain.move_by_offset(25, 0).pause(0.05)
    chain.release().perform()
    _settled(page)
    assert float(page.find_element("id", "rotation_deg").get_attribute("value")) != 0.0
    assert page.execute_script("return window.viewer.digest") != before
    fps = float(page.find_element("id", "fps").text)  # "the frame rate shown is a number"
    assert fps >= 0.0 and np.isfinite(fps)
    assert page.find_element("id", "path").text == "bake"  # the map turned over a held view


def test_moving_the_point_light_moves_the_highlight(page):
    from selenium.webdriver import ActionChains

    _set(page, "map", "")
    _set(page, "light_on", True)
    _set(page, "light_x", -1.0)
    _settled(page)
    assert page.find_element("id", "path").text == "network"
    left = page.execute_script(_HIGHLIGHT_X)
    page.find_element("css selector", "input[name=drag][value=light]").click()
    chain = ActionChains(page).click_and_hold(page.find_element("id", "frame"))
    for _ in range(8):
        chain.move_by_offset(50, 0).pause(0.05)  # 400 px at 5 mm a pixel: the light to x = +1 m
    chain.release().perform()
    _settled(page)
    assert float(page.find_element("id", "light_x").get_attribute("value")) == pytest.approx(1.0, abs=0.05)
    right = page.execute_script(_HIGHLIGHT_X)
    # The head's bright side follows the light: image right is head +x.
    assert right - left > 4.0, (left, right)


def test_a_map_outside_the_given_ones_is_refused_in_the_page(page, server):
    secret = str(server["secret"])
    status = page.execute_async_script(
        "const done = arguments[arguments.length - 1];"
        "fetch('/api/map/' + encodeURIComponent(arguments[0]) + '.jpg').then(r => done(r.status));", secret)
    assert status == 404
    page.execute_script("const s = document.getElementById('map'); s.add(new Option('x', arguments[0]));", secret)
    _set(page, "map", secret)
    _wait(page, "window.viewer.error.includes('unknown environment map')")
    assert "unknown environment map" in page.find_element("id", "error").text
    _set(page, "map", "damaged")
    _wait(page, "window.viewer.error.includes('could not be read')")
    _set(page, "map", "sky")  # and the server keeps serving
    _settled(page)
    assert page.find_element("id", "error").text == ""
