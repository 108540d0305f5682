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


COUNTING_VIEWER = """
import sys
from garo_ns.deformation import DeformationField

calls = open(sys.argv.pop(1), "a", buffering=1)
forward = DeformationField.forward


def counted(self, xyz, time):
    calls.write(f"{xyz.shape[0]}\\n")  # the rows the MLP runs on
    return forward(self, xyz, time)


DeformationField.forward = counted
from nerfstudio.scripts.viewer.run_viewer import entrypoint

sys.argv[0] = "ns-viewer"
entrypoint()
"""


def _move_time_in_the_browser(cmd, tmp_path, name, on_drawn=None):
    """Start the viewer with `cmd` (its port appended), draw a frame in headless Chromium, move the time slider
    to its end and wait for the picture to change; `on_drawn()` runs once the first frame is there. Returns
    whether the picture changed, and the viewer's log."""
    from playwright.sync_api import sync_playwright

    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    port = _free_port()
    log = open(tmp_path / "viewer.log", "w")
    viewer = subprocess.Popen(
        [*cmd, "--viewer.websocket-host", "127.0.0.1", "--viewer.websocket-port", str(port)],
        stdout=log,
        stderr=subprocess.STDOUT,
        env={**os.environ, "TORCHDYNAMO_DISABLE": "1"},
    )  # loopback only: the viewer's own default is 0.0.0.0
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
            empty = _canvas_pixels(page, ARTIFACTS / f"{name}_0_loading.png")

            def drawn():
                img = _canvas_pixels(page, ARTIFACTS / f"{name}_1_time0.png")
                # A rendered frame: many distinct colours, unlike the empty grid/background.
                colours = len(np.unique(img.reshape(-1, 3).astype(np.uint8), axis=0))
                return img if colours > 500 and np.abs(img - empty).mean() > 1.0 else None

            before = _wait_for(drawn, timeout=300)
            assert before is not None, f"no rendered frame arrived (see {name}_1_time0.png)"
            if on_drawn is not None:
                on_drawn()

            # The thumb of the slider labelled "Time" (the control panel also has other 0..1 sliders).
            slider = page.locator("xpath=//*[normalize-space(text())='Time']/following::*[@role='slider'][1]")
            slider.scroll_into_view_if_needed(timeout=30_000)
            assert float(slider.get_attribute("aria-valuenow")) == 0.0
            slider.focus()
            page.keyboard.press("End")  # time 1
            assert float(slider.get_attribute("aria-valuenow")) == 1.0

            def changed():
                img = _canvas_pixels(page, ARTIFACTS / f"{name}_2_time1.png")
                return img if np.abs(img - before).mean() > 1.0 else None

            after = _wait_for(changed, timeout=300)
            browser.close()
        return after is not None, (tmp_path / "viewer.log").read_text()
    finally:
        viewer.terminate()
        try:
            viewer.wait(timeout=30)
        except subprocess.TimeoutExpired:
            viewer.kill()
        log.close()
        shutil.copy(tmp_path / "viewer.log", ARTIFACTS / f"{name}.log")


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="needs Debian's chromium (scripts/test.sh installs it)")
def test_viewer_draws_the_scene_and_the_time_slider_moves_it(garo_run, tmp_path):
    pytest.importorskip("playwright")
    cmd = [str(Path(sys.executable).parent / "ns-viewer"), "--load-config", str(garo_run["config_path"])]
    changed, _ = _move_time_in_the_browser(cmd, tmp_path, "viewer")
    assert changed, "moving the time slider did not change the picture (see viewer_2_time1.png)"


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="needs Debian's chromium (scripts/test.sh installs it)")
def test_with_the_time_table_moving_the_time_slider_does_not_run_the_network(garo_run, tmp_path):
    """The run's config with `time_table: true` (what a model whose table met the bound renders with): loading
    builds the table (the MLP runs on every Gaussian at each key); after the first frame, a change of time renders
    from the table, and the MLP runs on none of the tabled Gaussians (at most on those the table leaves to it).
    The viewer interrupts a render whenever the camera or the time moves: a table built in the first frame was cut
    short and started over, and the MLP ran on every Gaussian after each time change."""
    pytest.importorskip("playwright")
    text = garo_run["config_path"].read_text()
    assert "time_table: null" in text
    config = garo_run["config_path"].with_name("config_table.yml")
    config.write_text(text.replace("time_table: null", "time_table: true"))
    calls = tmp_path / "field_calls.txt"
    calls.write_text("")
    mark = {}

    def on_drawn():  # what the MLP runs on from here on is what the time change costs
        mark["lines"] = len(calls.read_text().split())

    wrapper = tmp_path / "counting_viewer.py"
    wrapper.write_text(COUNTING_VIEWER)
    cmd = [sys.executable, str(wrapper), str(calls), "--load-config", str(config)]
    changed, log = _move_time_in_the_browser(cmd, tmp_path, "viewer_table", on_drawn)
    assert changed, "moving the time slider did not change the picture (see viewer_table_2_time1.png)"
    assert "time_table (" in log, "the load line does not name the time table"
    rows = [int(x) for x in calls.read_text().split()]
    assert rows, "the table was never built"
    gaussians = max(rows)  # the build runs the MLP on every Gaussian
    after = rows[mark["lines"] :]
    assert all(r < gaussians for r in after), f"the MLP ran on every Gaussian after the time change: {after}"
