"""`pgs view`: the web viewer serves its page, renders the browser's camera through the toolkit
exactly as `pgs render` renders that view, prints its URL; a headless browser loads it."""
from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("viser", reason="the viewer extra is not installed (pip install -e .[viewer])")
pytest.importorskip("nerfview", reason="the viewer extra is not installed (pip install -e .[viewer])")

from baseline.cli import main
from baseline.data.images import read_png_u8
from baseline.eval.evaluate import view_file_names
from baseline.run import Renderable
from baseline.viewer import ModelViewer, camera_from_state, camera_state_of

CHROMIUM = "/usr/bin/chromium"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def fetch(url: str, tries: int = 50) -> str:
    for _ in range(tries):
        try:
            with urllib.request.urlopen(url, timeout=5) as r:
                return r.read().decode("utf-8", "replace")
        except OSError:
            time.sleep(0.2)
    raise AssertionError(f"{url}: no answer")


@pytest.fixture(scope="module")
def viewer(decoded_files):
    """The viewer of a decoded Predict-GS file (its f_c cache on) on a free localhost port."""
    v = ModelViewer(Renderable(decoded_files["predict-gs"] / "model.pgs"), host="127.0.0.1",
                    port=free_port())
    v.start()
    yield v
    v.stop()


def test_the_camera_round_trip_is_exact(decoded_files):
    r = Renderable(decoded_files["baseline"] / "model.pgs")
    for cam in r.scene.test_cameras:
        back = camera_from_state(camera_state_of(cam), cam.width, cam.height, cam.near)
        np.testing.assert_allclose(back.viewmat.numpy(), cam.viewmat.numpy(), rtol=0, atol=1e-6)
        assert (back.fx, back.fy, back.cx, back.cy) == pytest.approx(
            (cam.fx, cam.fy, cam.cx, cam.cy), rel=1e-12)


def test_viewer_serves_its_page_and_renders_as_pgs_render(viewer, decoded_files, tmp_path):
    page = fetch(viewer.url)
    assert viewer.url == f"http://localhost:{viewer.port}"
    assert "<html" in page.lower()
    pgs = decoded_files["predict-gs"] / "model.pgs"
    out = tmp_path / "views"
    assert main(["render", str(pgs), "-o", str(out)]) == 0
    cams = viewer.r.scene.test_cameras
    for cam, name in list(zip(cams, view_file_names(cams)))[:2]:
        frame = viewer.render(camera_state_of(cam), (cam.width, cam.height))
        assert frame.dtype == np.uint8 and frame.shape == (cam.height, cam.width, 3)
        assert np.array_equal(frame, read_png_u8(out / "renders" / name))
    # nerfview's current API hands the render-tab state instead of a size
    state = type("Tab", (), {"viewer_width": 40, "viewer_height": 30})()
    assert viewer.render(camera_state_of(cams[0]), state).shape == (30, 40, 3)
    # the scene's cameras are drawn as frustums, a still frame is at most the training size
    assert viewer.viewer.render_tab_state.viewer_res == max(
        max(c.width, c.height) for c in viewer.r.scene.train_cameras)


def test_pgs_view_prints_its_url_and_serves(decoded_files):
    port = free_port()
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parent.parent))
    p = subprocess.Popen([sys.executable, "-m", "baseline.cli", "view",
                          str(decoded_files["baseline"] / "model.pgs"), "--host", "127.0.0.1",
                          "--port", str(port)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, env=env)
    try:
        seen = []
        for _ in range(60):               # viser prints its own banner first
            seen.append(p.stdout.readline())
            if "viewer of" in seen[-1] or not seen[-1]:
                break
        assert f"viewer of {decoded_files['baseline'] / 'model.pgs'}: http://localhost:{port}" \
            in seen[-1], (seen, p.stderr.read() if p.poll() is not None else "")
        assert "<html" in fetch(f"http://127.0.0.1:{port}").lower()
    finally:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
    assert p.returncode == 0 and "viewer stopped" in p.stdout.read()


def _screenshots(url: str, profile: Path, seconds: float):
    """Headless Chromium (the distribution's) on ``url``, driven over its DevTools protocol
    (websockets comes with viser): a PNG screenshot every second for ``seconds``, yielded as
    bytes, so the caller waits for the server's frame in real time."""
    import asyncio
    import base64
    import json

    import websockets

    port = free_port()
    p = subprocess.Popen([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu",
                          "--disable-background-networking", "--disable-component-update",
                          "--disable-sync", "--no-first-run", f"--user-data-dir={profile}",
                          "--enable-unsafe-swiftshader", "--window-size=960,640",
                          f"--remote-debugging-port={port}", "about:blank"],
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        tabs = json.loads(fetch(f"http://127.0.0.1:{port}/json", tries=100))
        ws_url = next(t for t in tabs if t["type"] == "page")["webSocketDebuggerUrl"]

        async def shots():
            out = []
            async with websockets.connect(ws_url, max_size=None) as ws:
                n = 0

                async def call(method, **params):
                    nonlocal n
                    n += 1
                    await ws.send(json.dumps({"id": n, "method": method, "params": params}))
                    while True:
                        m = json.loads(await ws.recv())
                        if m.get("id") == n:
                            return m

                await call("Page.enable")
                await call("Page.navigate", url=url)
                for _ in range(int(seconds)):
                    await asyncio.sleep(1.0)
                    r = await call("Page.captureScreenshot", format="png")
                    out.append(base64.b64decode(r["result"]["data"]))
                    if _frame_shown(out[-1], profile):
                        break
            return out

        return asyncio.run(shots())
    finally:
        p.terminate()
        p.wait(timeout=30)


def _frame_shown(png: bytes, folder: Path) -> bool:
    """Whether a screenshot shows a rendered frame in the viewer's canvas (the left part of
    the window; the control panel is on the right): viser's empty canvas is near black, the
    synthetic scene's render is mostly light (its sky and floor); before the page connects its
    panel is light (viser's default theme), after it nerfview's dark one."""
    f = folder.parent / "shot.png"
    f.write_bytes(png)
    grey = read_png_u8(f)[..., :3].astype(float).mean(axis=-1)
    h, w = grey.shape
    panel = grey[:, 3 * w // 4:]                 # connected: nerfview's dark control panel
    canvas = grey[h // 4:, : w // 2]
    return float(np.median(panel)) < 80 and float(np.median(canvas)) > 60


@pytest.mark.skipif(not Path(CHROMIUM).exists(), reason="no headless Chromium (apt-get install chromium)")
def test_a_headless_browser_loads_the_viewer(viewer, tmp_path):
    """Chromium from the distribution loads the page, connects to the server and shows a frame
    the toolkit rendered for its camera (the canvas turns from viser's near-black to the
    scene); the last screenshot is kept as shot.png."""
    shots = _screenshots(viewer.url, tmp_path / "profile", seconds=90)
    assert shots and _frame_shown(shots[-1], tmp_path / "profile")
    img = read_png_u8(tmp_path / "shot.png")
    assert img.shape[1] == 960
    shutil.rmtree(tmp_path / "profile", ignore_errors=True)
