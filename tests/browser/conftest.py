"""Harness of the browser tests: a console on a free port, a headless Chromium (Debian's), helpers.

The scene is a textured plate on black space (``trackmeter.sources.plane``), rendered once
and replayed at 25 Hz, so clicks can land on texture or on black space at known pixels and
the machine's two cores go to the tracker, the console and the browser rather than the renderer.
Screenshots go to ``test-artifacts/browser/`` (git-ignored).
"""

from __future__ import annotations

import shutil
import socket
import time
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
ARTIFACTS = REPO / "test-artifacts" / "browser"
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]
VIEWPORT = {"width": 1400, "height": 900}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for(predicate: Callable[[], Any], timeout_s: float, what: str, poll_s: float = 0.05) -> Any:
    """Poll ``predicate`` until it returns something truthy; fail naming ``what`` on timeout."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(poll_s)


class LoopedFrame:
    """A live-looking source: one pre-rendered stereo frame delivered at ``rate_hz`` forever."""

    def __init__(self, frame: Any, rig: Any, rate_hz: float = 25.0) -> None:
        from trackmeter.sources.base import StereoFrame

        self._StereoFrame = StereoFrame
        self.frame0 = frame
        self.rig = rig
        self.rate_hz = rate_hz
        self.restart()

    def read(self) -> Any:
        due = self._t0 + self._i / self.rate_hz
        delay = due - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        f = self._StereoFrame(self._i, self._i / self.rate_hz, self.frame0.left, self.frame0.right, self.frame0.truth)
        self._i += 1
        return f

    def restart(self) -> None:
        self._i = 0
        self._t0 = time.monotonic()

    def close(self) -> None:
        pass


def plate_source(rate_hz: float = 25.0) -> LoopedFrame:
    """The textured plate 3.5 m in front of the paper's rig, tilted a little, as a looped source."""
    from scipy.spatial.transform import Rotation

    from trackmeter.data.rigfile import load_rig
    from trackmeter.sources import plane

    rig = load_rig(REPO / "config" / "rigs" / "estec_12mm.yaml")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.2, -0.25, 0.05]).as_matrix()
    T[:3, 3] = (0.0, 0.0, 3.5)
    scene = plane.PlaneScene(rig, lambda t: T, n_frames=1)
    return LoopedFrame(scene.frame(0), rig, rate_hz)


def make_engine(rig: Any) -> Any:
    from trackmeter.data.config import load_config
    from trackmeter.pipeline.engine import Engine

    return Engine(load_config(), rig, case="a", rate_hz=25.0)


@pytest.fixture(scope="session")
def chromium_path() -> str:
    pytest.importorskip("playwright.sync_api", reason="playwright (python) is not installed")
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path is None:
        pytest.skip("Debian chromium is not installed (apt-get install chromium); never `playwright install`")
    return path


@pytest.fixture(scope="session")
def browser(chromium_path: str) -> Iterator[Any]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=chromium_path, args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture(scope="module")
def running_console() -> Iterator[Any]:
    pytest.importorskip("viser")
    from console.server import start_console

    source = plate_source()
    engine = make_engine(source.rig)
    running = start_console(source, engine, port=free_port(), publish_hz=12.0)  # type: ignore[arg-type]
    try:
        wait_for(lambda: running.console.images_pushed > 0, 30, "the first image")
        yield running
    finally:
        running.stop()


@pytest.fixture
def artifacts() -> Path:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    return ARTIFACTS


def open_page(browser: Any, running: Any, viewport: dict[str, int] | None = None) -> tuple[Any, Any]:
    """A new browser page on the console (``viewport`` CSS px, :data:`VIEWPORT` by default),
    connected; returns (page, viser client handle)."""
    before = set(running.server.get_clients())
    page = browser.new_context(viewport=viewport or VIEWPORT).new_page()
    # Playwright's 30 s default bounds waits given no timeout, screenshots among them, which wait
    # for a frame of software WebGL: with the other core running another test worker, a second
    # browser's screenshot took over 30 s once (the README's parallel test command).
    page.set_default_timeout(120_000)
    page.goto(running.url)
    (client_id,) = wait_for(lambda: tuple(set(running.server.get_clients()) - before)[:1], 30,
                            "the browser's websocket connection")
    client = running.server.get_clients()[client_id]
    # The browser reports its camera once it rendered; the console then set the image preset.
    wait_for(lambda: page.locator("canvas").count() > 0, 30, "the 3D canvas")
    time.sleep(1.0)
    return page, client


def main_canvas_box(page: Any) -> dict[str, float]:
    """The largest canvas's box on the page (CSS px). One question to the page for all its
    canvases (the plots have theirs): each waits for a frame of software WebGL, seconds on a
    busy host, where a locator's box per canvas took 10-20 s."""
    boxes = page.evaluate("() => Array.from(document.querySelectorAll('canvas'), (c) => {"
                          " const r = c.getBoundingClientRect();"
                          " return {x: r.x, y: r.y, width: r.width, height: r.height}; })")
    boxes = [b for b in boxes if b["width"] > 0 and b["height"] > 0]  # hidden ones have no box
    return max(boxes, key=lambda b: b["width"] * b["height"])


def pixel_to_screen(running: Any, client: Any, page: Any, uv: tuple[float, float],
                    box: dict[str, float] | None = None) -> tuple[float, float]:
    """Where image pixel ``uv`` of the left image is on the page, from the browser's own camera
    (``box``: the main canvas's :func:`main_canvas_box`, asked of the page when not given; each
    ask is a round trip per canvas to a page that may be busy drawing)."""
    from scipy.spatial.transform import Rotation

    from console.overlay import pixel_to_plane

    con = running.console
    xy = pixel_to_plane([uv], con._image_size, con.render_size)[0]
    R_plane = Rotation.from_quat(np.asarray(con.left_image.wxyz), scalar_first=True)
    p_world = R_plane.apply([xy[0], xy[1], 0.0]) + np.asarray(con.left_image.position)
    cam = client.camera
    R = Rotation.from_quat(np.asarray(cam.wxyz), scalar_first=True).as_matrix()  # OpenCV camera in world
    pc = R.T @ (p_world - np.asarray(cam.position))
    tan_half = np.tan(cam.fov / 2.0)
    box = box or main_canvas_box(page)
    x_ndc = pc[0] / pc[2] / (tan_half * box["width"] / box["height"])
    y_ndc = pc[1] / pc[2] / tan_half
    return box["x"] + (x_ndc + 1.0) / 2.0 * box["width"], box["y"] + (y_ndc + 1.0) / 2.0 * box["height"]
