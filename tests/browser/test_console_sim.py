"""``trackmeter console``'s default: the tumbling satellite of the ``estec`` scenario, in Chromium.

Automatic selection on, then the 3D view: both camera frustums, the point cloud, the estimated
body frame with the mock-up mesh and the true pose as a ghost. The screenshots
(``test-artifacts/browser/10_sim_image.png``, ``11_sim_both.png``) are the README's.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest

from tests.browser.conftest import free_port, open_page, wait_for

pytestmark = [pytest.mark.browser, pytest.mark.slow]


@pytest.fixture(scope="module")
def sim_console() -> Any:
    pytest.importorskip("viser")
    pytest.importorskip("trackmeter.sources.sim.simulator", reason="the simulator has not landed")
    from benchmarks.pipeline import make_engine
    from console.server import start_console
    from trackmeter.sources import open_source

    source = open_source("sim", realtime=True, loop=True)
    running = start_console(source, make_engine(source), port=free_port())
    try:
        wait_for(lambda: running.console.images_pushed > 0, 60, "the first image")
        yield running
    finally:
        running.stop()


def test_default_console_shows_the_satellite_in_image_and_3d(browser: Any, sim_console: Any, artifacts: Path) -> None:
    from trackmeter.pipeline.snapshot import SetAuto

    running = sim_console
    con = running.console
    assert con.mockup_mesh is not None, "the simulator's mock-up mesh reaches the 3D view"
    page, client = open_page(browser, running)
    try:
        assert running.pipeline.call(SetAuto(True, 16, "gabor"), 60).ok
        snap = wait_for(lambda: (s := running.pipeline.latest()).pose.valid and sum(t.measured for t in s.targets) >= 6 and s,
                        240, "a valid pose on the tumbling satellite", poll_s=0.5)
        assert snap.frame is not None and snap.frame.truth is not None
        wait_for(lambda: con.body.visible and con.truth.visible, 10, "estimated and true body frames in 3D")
        time.sleep(2.0)
        page.screenshot(path=str(artifacts / "10_sim_image.png"))
        page.get_by_role("button", name="both").click()
        time.sleep(4.0)
        page.screenshot(path=str(artifacts / "11_sim_both.png"))
        assert sum(1 for _ in con.server.scene._handle_from_node_name if _.startswith("/scene3d/body/mockup")) >= 1
    finally:
        page.context.close()
