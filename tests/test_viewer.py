"""ns-viewer in a real browser: the scene is drawn, and the time slider changes the picture.

Starts `ns-viewer` on loopback only, opens it in headless Chromium (software WebGL, since viser
draws the render through WebGL) driven by Playwright, waits for a rendered frame, moves the time
slider to its end and waits for the picture to change. Screenshots are kept under
$GARO_TEST_ARTIFACTS (default: test-artifacts/ in the repository).
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
ARTIFACTS = Path(os.environ.get("GARO_TEST_ARTIFACTS", Path(__file__).resolve().parents[1] / "test-artifacts"))
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-quic",
    "--no-first-run",
    "--enable-unsafe-swiftshader",
    "--use-angle=swiftshader",
]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_port(port: int, proc: subprocess.Popen, timeout: float) -> None:
    end = time.time() + timeout
    while time.time() < end:
        if proc.poll() is not None:
            raise RuntimeError(f"ns-viewer exited with {proc.returncode}")
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.5)
    raise TimeoutError(f"ns-viewer did not open port {port} in {timeout} s")


def _canvas_pixels(page, path: Path) -> np.ndarray:
    """Screenshot of the 3D canvas as an [H, W, 3] array (also written to `path`)."""
    import imageio.v2 as imageio

    page.locator("canvas").first.screenshot(path=str(path))
    # The left part only: the GUI panel floats over the canvas's right side.
    return imageio.imread(path)[:500, :500, :3].astype(np.float32)


def _wait_for(predicate, timeout: float, interval: float = 2.0):
    end = time.time() + timeout
    while True:
        value = predicate()
        if value is not None or time.time() > end:
            return value
        time.sleep(interval)


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="needs Debian's chromium (scripts/test.sh installs it)")
def test_viewer_draws_the_scene_and_the_time_slider_moves_it(garo_run, tmp_path):
    pytest.importorskip("playwright")
    from playwright.sync_api import sync_playwright

    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    port = _free_port()
    log = open(tmp_path / "viewer.log", "w")
    viewer = subprocess.Popen(
        [
            str(Path(sys.executable).parent / "ns-viewer"),
            "--load-config",
            str(garo_run["config_path"]),
            "--viewer.websocket-host",
            "127.0.0.1",  # loopback only: the viewer's own default is 0.0.0.0
            "--viewer.websocket-port",
            str(port),
        ],
        stdout=log,
        stderr=subprocess.STDOUT,
        env={**os.environ, "TORCHDYNAMO_DISABLE": "1"},
    )
    try:
        _wait_port(port, viewer, timeout=240)
        with socket.socket() as s:  # bound to loopback, not to every interface
            host_ip = socket.gethostbyname(socket.gethostname())
            if host_ip != "127.0.0.1" and not host_ip.startswith("127."):
                assert s.connect_ex((host_ip, port)) != 0
        with sync_playwright() as pw:
            browser = pw.chromium.launch_persistent_context(
                str(tmp_path / "chromium-profile"),  # a fresh user-data dir
                executable_path=CHROMIUM,
                args=CHROMIUM_ARGS,
                headless=True,
                viewport={"width": 900, "height": 600},
            )
            page = browser.new_page()
            page.goto(f"http://127.0.0.1:{port}", wait_until="domcontentloaded", timeout=60_000)
            page.wait_for_selector("canvas", timeout=120_000)
            empty = _canvas_pixels(page, ARTIFACTS / "viewer_0_loading.png")

            def drawn():
                img = _canvas_pixels(page, ARTIFACTS / "viewer_1_time0.png")
                # A rendered frame: many distinct colours, unlike the empty grid/background.
                colours = len(np.unique(img.reshape(-1, 3).astype(np.uint8), axis=0))
                return img if colours > 500 and np.abs(img - empty).mean() > 1.0 else None

            before = _wait_for(drawn, timeout=300)
            assert before is not None, "no rendered frame arrived (see viewer_1_time0.png)"

            # The thumb of the slider labelled "Time" (the control panel also has other 0..1 sliders).
            slider = page.locator("xpath=//*[normalize-space(text())='Time']/following::*[@role='slider'][1]")
            slider.scroll_into_view_if_needed(timeout=30_000)
            assert float(slider.get_attribute("aria-valuenow")) == 0.0
            slider.focus()
            page.keyboard.press("End")  # time 1
            assert float(slider.get_attribute("aria-valuenow")) == 1.0

            def changed():
                img = _canvas_pixels(page, ARTIFACTS / "viewer_2_time1.png")
                return img if np.abs(img - before).mean() > 1.0 else None

            after = _wait_for(changed, timeout=300)
            browser.close()
        assert after is not None, "moving the time slider did not change the picture (see viewer_2_time1.png)"
    finally:
        viewer.terminate()
        try:
            viewer.wait(timeout=30)
        except subprocess.TimeoutExpired:
            viewer.kill()
        log.close()
        shutil.copy(tmp_path / "viewer.log", ARTIFACTS / "viewer.log")
