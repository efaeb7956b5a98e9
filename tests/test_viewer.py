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

from baseline.cli import main  # noqa: E402
from baseline.data.images import read_png_u8  # noqa: E402
from baseline.eval.evaluate import view_file_names  # noqa: E402
from baseline.run import Renderable  # noqa: E402
from baseline.viewer import ModelViewer, camera_from_state, camera_state_of  # noqa: E402

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
        p.send_signal(signal.SIGINT)
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


@pytest.mark.skipif(not Path(CHROMIUM).exists(), reason="no headless Chromium (apt-get install chromium)")
def test_a_headless_browser_loads_the_viewer(viewer, tmp_path):
    """Chromium from the distribution loads the page, connects to the server and draws a
    frame the toolkit rendered: the screenshot is not one flat colour."""
    shot = tmp_path / "viewer.png"
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           "--no-first-run", f"--user-data-dir={tmp_path / 'profile'}",
           "--enable-unsafe-swiftshader", "--window-size=960,640",
           "--virtual-time-budget=20000", f"--screenshot={shot}", viewer.url]
    subprocess.run(cmd, capture_output=True, timeout=180)
    assert shot.is_file() and shot.stat().st_size > 0
    img = read_png_u8(shot)
    assert img.shape[:2] == (640, 960)
    assert img.reshape(-1, img.shape[-1])[:, :3].std(axis=0).max() > 5
    shutil.rmtree(tmp_path / "profile", ignore_errors=True)
