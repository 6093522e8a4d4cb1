"""The live plots break at a gap, in a real headless Chromium (DESIGN.md section 7).

A plot made as the console makes it (``console.app.add_plot``) gets a window with 3 s without
pose (``console.series``) through the console's own publishing calls. The test reads the plot's
canvas pixels: no line may cross the gap (before the fix uPlot drew one straight line from the
last point before to the first point after), and each line must still span much of the
auto-ranged y axis on both sides (not flat, not empty: a NaN that reaches uPlot can wreck its
y range). Both ways a browser gets the data are checked: an update to an open page, and the
state a page that connects later receives.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any, Iterator

import numpy as np
import pytest

from tests.browser.conftest import free_port, open_page, wait_for

pytestmark = [pytest.mark.browser, pytest.mark.slow]

TITLE = "Gap test [m]"
LABELS = ("x", "y", "z (depth)")
RATE_HZ = 25.0
LOST = (4.0, 7.0)  # the pose is invalid from 4 s to 7 s (frames in between have no values)
END_S = 10.0


def _values(t: float) -> np.ndarray:
    # Three lines of similar amplitude, so each one spans most of the shared y axis.
    return np.array([np.sin(t), np.cos(t), 0.8 * np.sin(2.0 * t + 0.5)])


def _window_with_a_gap() -> Any:
    from console.series import SeriesWindow

    window = SeriesWindow(len(LABELS))
    for i in range(int(END_S * RATE_HZ)):
        t = i / RATE_HZ
        if LOST[0] <= t < LOST[1]:
            window.mark_gap()  # as PlotData.add does for a frame with an invalid pose
        else:
            window.append(t, _values(t))
    return window


@pytest.fixture(scope="module")
def plot_server() -> Iterator[Any]:
    viser = pytest.importorskip("viser")
    from console.app import add_plot

    port = free_port()
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    try:
        handle = add_plot(server.gui, TITLE, LABELS)
        yield SimpleNamespace(server=server, url=f"http://127.0.0.1:{port}", handle=handle)
    finally:
        server.stop()


# Runs in the page: the uPlot chart titled TITLE (viser's test hook), its state, and counts of
# line-coloured pixels of its canvas per series colour, in the gap and on both sides of it.
_INSPECT_JS = """([title, lost, before, after]) => {
  const tps = (window.__viserTestpoints || {}).uplots || {};
  const entry = Object.values(tps).find(
      e => (e.chart.root.querySelector('.u-title') || {}).textContent === title);
  if (!entry) return null;
  const u = entry.chart;
  const ctx = u.ctx, bb = u.bbox;
  const px = v => u.valToPos(v, 'x', true);
  // Strokes are 1.5 CSS px wide with round joins: keep 4 px off the last/first point.
  const regions = {gap: [px(lost[0]) + 4, px(lost[1]) - 4],
                   before: [px(before[0]), px(before[1])], after: [px(after[0]), px(after[1])]};
  const out = {n: u.data[0].length, y: [u.scales.y.min, u.scales.y.max],
               top: bb.top, height: bb.height, regions: {}};
  for (const [name, [x0, x1]] of Object.entries(regions)) {
    const xa = Math.ceil(x0), w = Math.max(1, Math.floor(x1) - xa);
    const img = ctx.getImageData(xa, bb.top, w, bb.height).data;
    // Per series colour (red, green, blue dominant): pixel count and rows it covers.
    const found = [[0, 1e9, -1], [0, 1e9, -1], [0, 1e9, -1]];
    for (let k = 0; k < img.length; k += 4) {
      const r = img[k], g = img[k + 1], b = img[k + 2], a = img[k + 3];
      if (a < 60 || Math.max(r, g, b) - Math.min(r, g, b) < 60) continue;  // grid, text, blank
      const c = r >= g && r >= b ? 0 : (g >= b ? 1 : 2);
      const row = Math.floor(k / 4 / w);
      found[c][0] += 1; found[c][1] = Math.min(found[c][1], row); found[c][2] = Math.max(found[c][2], row);
    }
    out.regions[name] = found;
  }
  return out;
}"""


def _inspect(page: Any, n_expected: int) -> dict[str, Any]:
    """The chart's state and pixels once it holds ``n_expected`` rows and has drawn them."""
    args = [TITLE, list(LOST), [0.5, LOST[0] - 0.5], [LOST[1] + 0.5, END_S - 0.5]]
    wait_for(lambda: (s := page.evaluate(_INSPECT_JS, args)) and s["n"] == n_expected, 30,
             f"the plot with {n_expected} rows in the browser")
    page.wait_for_timeout(300)  # uPlot draws on the next animation frame
    return page.evaluate(_INSPECT_JS, args)


def _assert_broken_at_the_gap_and_auto_ranged(state: dict[str, Any], data: tuple[np.ndarray, ...]) -> None:
    gap = state["regions"]["gap"]
    assert all(count == 0 for count, _, _ in gap), (
        f"a line crosses the 3 s without pose (line pixels per series in the gap: {[c for c, _, _ in gap]})")
    # The y axis auto-ranged to the data: finite, around it, not wider than a nice rounding.
    values = np.concatenate([v[np.isfinite(v)] for v in data[1:]])
    lo, hi = state["y"]
    assert np.isfinite(lo) and np.isfinite(hi), state["y"]
    assert lo <= values.min() and hi >= values.max() and hi - lo < 2.0 * np.ptp(values), (state["y"], np.ptp(values))
    # Every line is drawn on both sides, spanning much of the plot's height (not flat, not empty).
    for side in ("before", "after"):
        for colour, (count, top, bottom) in zip(("red", "green", "blue"), state["regions"][side]):
            assert count > 50 and bottom - top > 0.3 * state["height"], (side, colour, count, top, bottom, state["height"])


def test_a_plot_draws_no_line_across_a_gap_and_keeps_its_auto_range(browser: Any, plot_server: Any, artifacts: Any) -> None:
    from console.app import set_uplot_data, uplot_data

    window = _window_with_a_gap()
    data = window.arrays()
    assert int(np.isnan(data[1]).sum()) == 1  # one separator row, all the gap needs
    page, _ = open_page(browser, plot_server)
    try:
        # The update path: the page is open when the window is published.
        set_uplot_data(plot_server.handle, uplot_data(data))
        page.get_by_text(TITLE).first.scroll_into_view_if_needed()
        state = _inspect(page, len(data[0]))
        page.locator(".uplot").first.screenshot(path=str(artifacts / "plot_gap.png"))
        _assert_broken_at_the_gap_and_auto_ranged(state, data)
    finally:
        page.context.close()
    # The initial state of a browser that connects after the publish.
    late, _ = open_page(browser, plot_server)
    try:
        _assert_broken_at_the_gap_and_auto_ranged(_inspect(late, len(data[0])), data)
    finally:
        late.context.close()


_LINE_PIXELS_JS = """(title) => {
  const tps = (window.__viserTestpoints || {}).uplots || {};
  const entry = Object.values(tps).find(
      e => (e.chart.root.querySelector('.u-title') || {}).textContent === title);
  if (!entry) return null;
  const u = entry.chart, bb = u.bbox;
  const img = u.ctx.getImageData(bb.left, bb.top, bb.width, bb.height).data;
  let line = 0;
  for (let k = 0; k < img.length; k += 4) {
    const r = img[k], g = img[k + 1], b = img[k + 2], a = img[k + 3];
    if (a >= 60 && Math.max(r, g, b) - Math.min(r, g, b) >= 60) line += 1;  // a series colour
  }
  return {n: u.data[0].length, line: line};
}"""


def test_a_plot_with_no_data_yet_draws_no_line(browser: Any, plot_server: Any) -> None:
    """Before the first valid pose a plot holds only its placeholder row pair; drawn as zeros it
    showed a flat line at 0, read as a measured 0 (an operator probe's finding)."""
    from console.app import add_plot

    title = "Empty test [m]"
    add_plot(plot_server.server.gui, title, LABELS)
    page, _ = open_page(browser, plot_server)
    try:
        page.get_by_text(title).first.scroll_into_view_if_needed()
        wait_for(lambda: page.evaluate(_LINE_PIXELS_JS, title) is not None, 30, "the empty plot in the browser")
        page.wait_for_timeout(300)  # uPlot draws on the next animation frame
        state = page.evaluate(_LINE_PIXELS_JS, title)
        assert state["line"] == 0, state
    finally:
        page.context.close()
