"""The operator console under load (issue 7): tracking rate with a browser connected, image
updates reaching the browser, click-to-target latency.

The console runs in this process on the ``sim`` source (the ``estec`` scenario at 25 Hz) with
16 automatic targets; Debian's Chromium (headless, SwiftShader WebGL) is connected through
Playwright and its websocket frames are counted.

Figures:

- ``tracking_rate_hz``: frames tracked per second over ``MEASURE_S`` s after ``WARMUP_S`` s
  (target 25), and ``dropped_fraction`` (target < 0.01), ``acquisition_hz`` the source's rate;
  ``*_window_median`` and the worst window (``tracking_rate_hz_window_min``,
  ``dropped_fraction_window_max``) over four equal sub-windows of it
  (:class:`benchmarks.pipeline.LiveWindow`).
- ``browser_image_updates_per_s``: websocket frames the browser received that carry a JPEG
  image (the left image with its overlays), per second, same window (target >= 10).
- ``published_images_per_s``: images the console pushed per second (the server side of it),
  and ``publish_ms_median`` the publisher's time per push (overlays, JPEG, scene, numbers, plots).
- ``browser_images_shown_per_s``: images the browser actually put on screen (uploaded as the
  image plane's texture) per second. viser's client starts loading every image it receives
  and drops a load that a newer image overtakes, so under CPU load fewer are shown than
  received. ``browser_renders_per_s``: WebGL frames the page drew (the client renders
  continuously for 250 ms after each scene update, so while images stream in this is as many
  frames as the CPU allows); ``browser_cpu_cores``: CPU of all Chromium processes, cores;
  ``browser_cpu_ms_per_render`` the two divided (the browser's CPU per frame drawn).
- ``paced_*``: the same figures over ``PACED_S`` s with the console's image rate lowered to
  ``PACED_HZ`` (``paced_publish_hz``) in the same run: how many images the same browser
  shows when fewer arrive than it drops.
- ``click_latency_ms``: median over ``N_CLICKS`` clicks on the satellite in the browser: from
  the mouse button going down in the page until the page draws the operator's box around the
  clicked pixel (target < 300). The box is a scene node over the image, in its status colour as
  tone-mapped on screen (:func:`console.overlay.displayed_rgb`); a probe in the page reads the
  drawn pixels of four bands across the box's edges after every frame the page draws, and the
  box counts as drawn when each band holds ``PROBE_MIN_PX`` more pixels of that colour than in
  the first frame probed (page clock at both ends); a target not on screen within 5 s counts as
  infinitely late, a refused click not at all. ``click_latency_from_release_ms``: the same
  from the button going up (the click is sent on release). ``click_latency_received_ms``: until
  the browser received the first image pushed with the target; ``click_to_server_ms``: until
  the tracking thread had created the target.
- ``tracking_rate_hz_without_browser``: the same console with no browser connected, measured
  first in the same run (the browser's rendering competes for the two cores).

Environment: ``TRACKMETER_BENCH_BROWSER_NICE`` (default 0, the issue's conditions: the browser
competes for the cores as it is; N > 0 runs Chromium's processes at nice N, a stand-in for an
operator's browser on another machine, reported as ``browser_nice``), ``TRACKMETER_BENCH_CONSOLE_SOURCE`` (default ``sim``; ``plate`` replays one
pre-rendered frame of a textured plate at 25 Hz, which takes the renderer's CPU out of the
figures), ``TRACKMETER_BENCH_LIVE_S`` (default 30), ``TRACKMETER_BENCH_CPU_NICE`` (default: what
``trackmeter console`` does, ``--cpu-nice``'s default, 0: the priority left alone; -10 runs the
process and its session's autogroup at nice -10, see :mod:`trackmeter.priority`, as in
the README table's run). ``cpu_nice`` is the value asked for and
``cpu_priority_raised`` 1 when the system allowed it.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import statistics
import sys
import time
from typing import TYPE_CHECKING, Any, cast

import numpy as np

if TYPE_CHECKING:
    from playwright.sync_api import ViewportSize

WARMUP_S = 10.0
MEASURE_S = float(os.environ.get("TRACKMETER_BENCH_LIVE_S", "30"))
N_CLICKS = 9
CONNECT_S = 60.0  # how long the page may take to open its websocket
CLICKS_MAX_S = 80.0  # the click phase's share of the 5-minute budget
CLICK_SLACK_PX = 2.0  # a click candidate is accepted by the tracker on a ring this far around it too
CLICK_INSIDE_PX = 15.0  # ... and lies at least this far inside the lit body (from black space)
N_CANDIDATES = 60  # features checked as click candidates (fewer: fresher when clicked)
SOURCE = os.environ.get("TRACKMETER_BENCH_CONSOLE_SOURCE", "sim")
BROWSER_NICE = int(os.environ.get("TRACKMETER_BENCH_BROWSER_NICE", "0"))
PACED_HZ = 6.0  # the paced phase's image rate
PACED_S = 15.0
PROBE_SLACK_PX = 5.0  # screen px either side of the box's edges where its lines may fall (the target moves)
PROBE_MIN_PX = 10  # pixels of the box's colour each edge's band must gain to count as drawn


def _log(msg: str) -> None:
    print(f"[console] {msg}", file=sys.stderr, flush=True)


def console_priority() -> tuple[int, Any]:
    """Raise the CPU priority as ``trackmeter console`` does (before the source opens), or as
    ``TRACKMETER_BENCH_CPU_NICE`` says; returns the nice value asked for and the
    :class:`PriorityChange` (None: left alone) for :func:`~trackmeter.priority.restore_cpu_priority`."""
    from trackmeter.cli.console import DEFAULT_CPU_NICE
    from trackmeter.priority import raise_cpu_priority

    nice = int(os.environ.get("TRACKMETER_BENCH_CPU_NICE", DEFAULT_CPU_NICE))
    if nice == 0:
        return 0, None
    change = raise_cpu_priority(nice)
    _log(change.message)
    return nice, change


def _poll(page: Any, predicate: Any, timeout_s: float) -> Any:
    """Poll while letting Playwright deliver its events (websocket frames)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        page.wait_for_timeout(5)
    return None


#: Page instrumentation (read-only hooks; page clock ``performance.now()``, ms):
#: ``down`` the times of pointerdown; ``renders`` clears of the default framebuffer (three.js
#: clears it once per frame); ``shown`` [time, JPEG size] of every texture upload of an image
#: that came from a blob (viser's image planes load their JPEG through a blob URL).
PAGE_HOOKS = """
(() => {
  const tm = window.__tm = {down: [], up: [], renders: 0, shown: []};
  window.addEventListener('pointerdown', () => tm.down.push(performance.now()), true);
  window.addEventListener('pointerup', () => tm.up.push(performance.now()), true);
  const sizes = new Map();
  const createURL = URL.createObjectURL;
  URL.createObjectURL = function (obj) {
    const url = createURL.call(URL, obj);
    if (obj instanceof Blob && obj.type.startsWith('image/')) sizes.set(url, obj.size);
    return url;
  };
  const src = Object.getOwnPropertyDescriptor(HTMLImageElement.prototype, 'src');
  Object.defineProperty(HTMLImageElement.prototype, 'src', {
    configurable: true,
    get() { return src.get.call(this); },
    set(v) { if (sizes.has(v)) { this.__tmSize = sizes.get(v); sizes.delete(v); } src.set.call(this, v); },
  });
  for (const C of [WebGL2RenderingContext, WebGLRenderingContext]) {
    const P = C.prototype;
    const bind = P.bindFramebuffer;
    P.bindFramebuffer = function (target, fb) { this.__tmFb = fb; return bind.call(this, target, fb); };
    const clear = P.clear;
    P.clear = function (mask) { if (!this.__tmFb) { tm.renders++; tm.gl = this; tm.drew = true; } return clear.call(this, mask); };
    for (const name of ['texImage2D', 'texSubImage2D']) {
      const f = P[name];
      P[name] = function (...args) {
        for (const a of args) if (a instanceof HTMLImageElement && a.__tmSize) { tm.shown.push([performance.now(), a.__tmSize]); a.__tmSize = 0; }
        return f.apply(this, args);
      };
    }
  }
  // The probe: after each animation frame in which the page drew the scene, read the drawn
  // pixels of the armed bands (page CSS px: x0, y0, x1, y1) and count those within ``tol`` of
  // ``rgb``; ``found`` is the page time of the first frame in which every band holds ``min``
  // more of them than in the first frame probed (``base``: what was there before, e.g. an
  // automatic target's thin box drawn into the image).
  tm.probe = null;
  const raf = window.requestAnimationFrame;
  window.requestAnimationFrame = function (cb) {
    return raf.call(window, (t) => {
      tm.drew = false;
      cb(t);
      const p = tm.probe, gl = tm.gl;
      if (!tm.drew || !p || p.found !== null || !gl) return;
      const c = gl.canvas, r = c.getBoundingClientRect();
      const sx = c.width / r.width, sy = c.height / r.height;
      let ok = true;
      const counts = [];
      for (const [bx0, by0, bx1, by1] of p.bands) {
        const x0 = Math.max(0, Math.floor((bx0 - r.left) * sx)), x1 = Math.min(c.width, Math.ceil((bx1 - r.left) * sx));
        const y0 = Math.max(0, Math.floor((by0 - r.top) * sy)), y1 = Math.min(c.height, Math.ceil((by1 - r.top) * sy));
        if (x1 <= x0 || y1 <= y0) { ok = false; break; }
        const buf = new Uint8Array((x1 - x0) * (y1 - y0) * 4);
        gl.readPixels(x0, c.height - y1, x1 - x0, y1 - y0, gl.RGBA, gl.UNSIGNED_BYTE, buf);
        let n = 0;
        for (let i = 0; i < buf.length; i += 4)
          if (Math.abs(buf[i] - p.rgb[0]) <= p.tol && Math.abs(buf[i + 1] - p.rgb[1]) <= p.tol
              && Math.abs(buf[i + 2] - p.rgb[2]) <= p.tol) n++;
        counts.push(n);
      }
      p.frames++;
      if (!ok) return;
      if (p.base === null) { p.base = counts; return; }
      if (counts.every((n, i) => n >= p.base[i] + p.min)) p.found = performance.now();
    });
  };
})();
"""


def box_bands(running: Any, client: Any, page: Any, uv: tuple[float, float], half_px: float,
              slack_px: float, box: dict[str, float]) -> list[list[float]]:
    """Page rectangles (CSS px: x0, y0, x1, y1) around the middle of each edge of the box of
    half-side ``half_px`` (image px) centred on image pixel ``uv``, ``slack_px`` (screen px)
    either side of the edge: where that box's lines fall even when the target has moved a
    little, and where no other box's lines cross all four."""
    from tests.browser.conftest import pixel_to_screen

    corners = [pixel_to_screen(running, client, page, (uv[0] + du, uv[1] + dv), box)
               for du, dv in ((-half_px, -half_px), (half_px, -half_px), (half_px, half_px), (-half_px, half_px))]
    bands = []
    for (xa, ya), (xb, yb) in zip(corners, corners[1:] + corners[:1]):
        # The middle 40 % of the edge, widened across it by the slack.
        mx0, my0 = xa + 0.3 * (xb - xa), ya + 0.3 * (yb - ya)
        mx1, my1 = xa + 0.7 * (xb - xa), ya + 0.7 * (yb - ya)
        bands.append([min(mx0, mx1) - slack_px, min(my0, my1) - slack_px,
                      max(mx0, mx1) + slack_px, max(my0, my1) + slack_px])
    return bands


def _page_offset_s(page: Any) -> float:
    """``time.monotonic() - performance.now() / 1000`` of the page, from the tightest of a few probes."""
    best = (float("inf"), 0.0)
    for _ in range(5):
        t0 = time.monotonic()
        now_ms = page.evaluate("performance.now()")
        t1 = time.monotonic()
        best = min(best, (t1 - t0, (t0 + t1) / 2 - now_ms / 1e3))
    return best[1]


def _chromium_pids() -> list[int]:
    """The Chromium processes this process started (through Playwright's driver)."""
    children: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    children.setdefault(int(f.read().rsplit(")", 1)[1].split()[1]), []).append(int(d))
            except OSError:
                pass
    pids, todo = [], list(children.get(os.getpid(), []))
    while todo:
        pid = todo.pop()
        todo += children.get(pid, [])
        try:
            with open(f"/proc/{pid}/cmdline") as f:
                if "chrom" in f.read().split("\0")[0]:
                    pids.append(pid)
        except OSError:
            pass
    return pids


def _chromium_cpu_s() -> float:
    """CPU seconds used so far by the Chromium processes this process started."""
    total = 0.0
    for pid in _chromium_pids():
        try:
            with open(f"/proc/{pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        except OSError:
            pass
    return total


def _renice_chromium(nice: int) -> None:
    """Every thread of the Chromium processes at ``nice`` (Linux: niceness is per thread)."""
    for pid in _chromium_pids():
        try:
            for tid in os.listdir(f"/proc/{pid}/task"):
                os.setpriority(os.PRIO_PROCESS, int(tid), nice)
        except OSError:
            pass


def _follow(before: Any, after: Any, uv: tuple[float, float], k: int = 3) -> tuple[float, float]:
    """``uv`` of snapshot ``before`` moved to snapshot ``after`` with its ``k`` nearest tracked
    targets (median displacement of the targets in both): the satellite keeps turning while
    the candidates are computed, and a pixel chosen on an older frame lands elsewhere."""
    now = {t.id: np.asarray(t.uv, float) for t in after.targets if t.status != "lost" and np.all(np.isfinite(t.uv))}
    pairs = [(np.asarray(t.uv, float), now[t.id]) for t in before.targets
             if t.id in now and t.status != "lost" and np.all(np.isfinite(t.uv))]
    if not pairs:
        return uv
    p = np.asarray(uv, float)
    pairs.sort(key=lambda ab: float(np.hypot(*(ab[0] - p))))
    shift = np.median([b - a for a, b in pairs[:k]], axis=0)
    return float(p[0] + shift[0]), float(p[1] + shift[1])


def _click_candidates(running: Any) -> tuple[Any, list[tuple[float, float]]]:
    """Pixels an operator would click: the pixels of the targets the tracker is measuring in the
    latest frame (textured points it accepts, at most a frame old: nothing else to compute, so
    the satellite has hardly moved by the time the click lands), at least ``CLICK_INSIDE_PX``
    inside the lit body (a click near the silhouette lands on black space once the body
    turned), the deepest inside first. Else textured points of the satellite that the tracker
    itself accepts (its own measurement parameters and click check) at the point and at 8
    points ``CLICK_SLACK_PX`` around it, deepest inside first; else pixels around the
    projection of the body origin (truth or estimate). Returns the snapshot they belong to and
    the pixels (see :func:`_follow`).

    Measured on the estec scenario: of the features selected with the default
    :class:`MeasureParams` only 4-16 of 24-39 were accepted by the tracker's (mostly "disparity
    too uncertain"), and 2-5 also 2 px around; choosing among them took long enough under load
    that most clicks on them landed on another surface and were refused."""
    import cv2

    from trackmeter.core.features import FeatureParams, select_features
    from trackmeter.core.matching import measure_points

    snap = running.pipeline.latest()
    tracker = running.pipeline.engine.tracker
    if snap.frame is not None:
        left = np.ascontiguousarray(snap.frame.left)
        # Distance of each pixel from black space (grey below the tracker's black-sky level).
        lit = (cv2.blur(left, (5, 5)) >= tracker.measure.min_mean_grey).astype(np.uint8)
        inside = cv2.distanceTransform(lit, cv2.DIST_L2, 5)
        size = [left.shape[1] - 1, left.shape[0] - 1]
        tracked = [t for t in snap.targets if t.status == "tracking" and np.all(np.isfinite(t.uv))]
        if tracked:
            ij = np.clip(np.rint([t.uv for t in tracked]).astype(int), 0, size)
            depth = inside[ij[:, 1], ij[:, 0]]
            good = cast("list[tuple[float, float]]",
                        [tuple(map(float, tracked[i].uv)) for i in np.argsort(-depth) if depth[i] >= CLICK_INSIDE_PX])
            if good:
                return snap, good
        rig = running.pipeline.rig
        pts = select_features(snap.frame.left, snap.frame.right, rig, N_CANDIDATES, "gabor", FeatureParams(),
                              [t.uv for t in snap.targets])
        if len(pts):
            pts = np.asarray(pts, float).reshape(-1, 2)
            ring = [(np.cos(a), np.sin(a)) for a in np.arange(8) * np.pi / 4]
            offsets = np.array([(0.0, 0.0)] + [(CLICK_SLACK_PX * c, CLICK_SLACK_PX * s) for c, s in ring])
            probes = (pts[:, None, :] + offsets[None]).reshape(-1, 2)
            ok = np.array([m.ok for m in measure_points(rig, snap.frame.left, snap.frame.right, probes, tracker.measure)])
            ok &= np.array([tracker._check_click(left, p) is None for p in probes])
            ij = np.clip(np.rint(pts).astype(int), 0, size)
            depth = inside[ij[:, 1], ij[:, 0]]
            keep = ok.reshape(len(pts), len(offsets)).all(axis=1) & (depth >= CLICK_INSIDE_PX)
            good = cast("list[tuple[float, float]]", [tuple(map(float, pts[i])) for i in np.argsort(-depth) if keep[i]])
            if good:
                _log(f"no tracked target inside the body: aiming at {len(good)} selected features")
                return snap, good
        _log("no tracked target or accepted feature inside the body: aiming near the body origin")
    T = None
    if snap.frame is not None and snap.frame.truth is not None:
        T = np.asarray(snap.frame.truth.T_cam_body)
    elif snap.pose.valid:
        T = np.asarray(snap.pose.T_cam_body)
    w, h = running.console._image_size
    centre = np.array([w / 2, h / 2]) if T is None else running.pipeline.rig.left.project(T[:3, 3][None])[0]
    rng = np.random.default_rng(1)
    return snap, cast("list[tuple[float, float]]",
                      [tuple(map(float, np.clip(centre + rng.normal(0, 25, 2), 10, [w - 10, h - 10]))) for _ in range(40)])


def _measure_browser(page: Any, running: Any, window: Any, jpeg_times: list[float], seconds: float) -> dict[str, float]:
    """Tracking and browser figures over the next ``seconds`` (see the module docstring)."""
    page_counts = "[window.__tm.renders, window.__tm.shown.length]"
    window.begin()
    n_jpeg0, pushed0, t0 = len(jpeg_times), running.console.images_pushed, time.monotonic()
    (renders0, shown0), cpu0 = page.evaluate(page_counts), _chromium_cpu_s()
    window.wait(seconds, 4, sleep=lambda s: page.wait_for_timeout(s * 1000))
    live = window.end()
    (renders1, shown1), cpu1 = page.evaluate(page_counts), _chromium_cpu_s()
    dt = time.monotonic() - t0
    renders_per_s = (renders1 - renders0) / dt
    return {
        "tracking_rate_hz": live["rate_hz"],
        "dropped_fraction": live["dropped_fraction"],
        "tracking_rate_hz_window_median": live["rate_hz_window_median"],
        "tracking_rate_hz_window_min": live["rate_hz_window_min"],
        "dropped_fraction_window_median": live["dropped_fraction_window_median"],
        "dropped_fraction_window_max": live["dropped_fraction_window_max"],
        "acquisition_hz": live["acquisition_hz"],
        "latency_ms_median": live["latency_ms_median"],
        "browser_image_updates_per_s": (len(jpeg_times) - n_jpeg0) / dt,
        "browser_images_shown_per_s": (shown1 - shown0) / dt,
        "browser_renders_per_s": renders_per_s,
        "browser_cpu_cores": (cpu1 - cpu0) / dt,
        "browser_cpu_ms_per_render": 1e3 * (cpu1 - cpu0) / dt / renders_per_s if renders_per_s else float("nan"),
        "published_images_per_s": (running.console.images_pushed - pushed0) / dt,
    }


def unmet() -> str | None:
    """What this benchmark needs and this machine lacks (:func:`benchmarks.browser_unmet`)."""
    from benchmarks import browser_unmet

    return browser_unmet()


def run() -> dict[str, float]:
    from playwright.sync_api import sync_playwright

    from benchmarks.pipeline import LiveWindow, make_engine
    from console.overlay import STATUS_RGB, box_half_px, displayed_rgb, node_rgb_for
    from console.server import start_console
    from tests.browser.conftest import CHROMIUM_ARGS, VIEWPORT, free_port, main_canvas_box, pixel_to_screen
    from trackmeter.priority import restore_cpu_priority
    from trackmeter.pipeline.snapshot import RemoveTarget, SetAuto
    from trackmeter.sources import open_source

    chromium = shutil.which("chromium")
    if chromium is None:
        raise RuntimeError(f"needs {unmet()}")
    nice, priority = console_priority()
    if SOURCE == "plate":  # the browser tests' textured plate: no renderer competing for the cores
        from tests.browser.conftest import plate_source

        source: Any = plate_source()
    else:
        source = open_source(SOURCE, realtime=True, loop=True)
    running = start_console(source, make_engine(source), port=free_port())
    out: dict[str, float] = {"cpu_nice": float(nice)}
    try:
        running.pipeline.call(SetAuto(True, 16, "gabor"), 60)
        window = LiveWindow(running.pipeline)
        _log(f"no browser: warm-up {WARMUP_S:.0f} s, measure {MEASURE_S / 2:.0f} s")
        time.sleep(WARMUP_S)
        window.begin()
        time.sleep(MEASURE_S / 2)
        out["tracking_rate_hz_without_browser"] = window.end()["rate_hz"]

        jpeg_times: list[float] = []

        def on_ws(ws: Any) -> None:
            def frame(payload: Any) -> None:
                if isinstance(payload, (bytes, bytearray)) and b"\xff\xd8\xff" in payload:
                    jpeg_times.append(time.monotonic())

            ws.on("framereceived", frame)

        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
            context = browser.new_context(viewport=cast("ViewportSize", VIEWPORT))
            context.add_init_script(PAGE_HOOKS)
            page = context.new_page()
            page.on("websocket", on_ws)
            before = set(running.server.get_clients())
            page.goto(running.url)
            if not _poll(page, lambda: set(running.server.get_clients()) - before, CONNECT_S):
                # A browser starved of CPU may not open its websocket at all: say so, not StopIteration.
                raise RuntimeError(f"the browser did not connect to the console within {CONNECT_S:.0f} s")
            client_id = next(iter(set(running.server.get_clients()) - before))
            client = running.server.get_clients()[client_id]
            _log(f"browser connected: warm-up {WARMUP_S:.0f} s, measure {MEASURE_S:.0f} s")
            if BROWSER_NICE:
                _renice_chromium(BROWSER_NICE)
                out["browser_nice"] = float(BROWSER_NICE)
            page.wait_for_timeout(WARMUP_S * 1000)
            if BROWSER_NICE:
                _renice_chromium(BROWSER_NICE)  # threads started during the warm-up
            out.update(_measure_browser(page, running, window, jpeg_times, MEASURE_S))
            out["publish_ms_median"] = statistics.median(running.console.push_ms)
            # The same browser with images at the rate it can draw (viser's client drops an image
            # still loading when a newer one arrives): what the operator sees at a slower rate.
            default_hz = running.console.publish_hz
            running.console.publish_hz = PACED_HZ
            page.wait_for_timeout(3000)
            paced = _measure_browser(page, running, window, jpeg_times, PACED_S)
            running.console.publish_hz = default_hz
            out["paced_publish_hz"] = PACED_HZ
            for key in ("tracking_rate_hz", "dropped_fraction", "browser_image_updates_per_s",
                        "browser_images_shown_per_s", "browser_renders_per_s", "browser_cpu_cores"):
                out[f"paced_{key}"] = paced[key]
            page.wait_for_timeout(3000)
            _log(f"rates: {out}")

            latencies: list[float]
            latencies, from_release, received, to_server = [], [], [], []
            offset_s = _page_offset_s(page)  # monotonic = page clock / 1000 + offset_s
            skipped: list[str] = []
            clicks_deadline = time.monotonic() + CLICKS_MAX_S
            canvas = main_canvas_box(page)  # asked once: every ask waits for the busy page
            rng = np.random.default_rng(7)
            while len(latencies) < N_CLICKS and time.monotonic() < clicks_deadline:
                # Chosen afresh on the latest frame each time: the satellite turns between clicks.
                snap0, candidates = _click_candidates(running)
                uv = _follow(snap0, running.pipeline.latest(), candidates[int(rng.integers(min(len(candidates), 5)))])
                known = {t.id for t in running.pipeline.latest().targets}
                n_notes = len(running.console.notifications)
                sx, sy = pixel_to_screen(running, client, page, uv, canvas)
                # The operator's box (drawn over the image in its status colour) around the click.
                half = box_half_px(running.console.patch_px, operator=True)
                probe = {"bands": box_bands(running, client, page, uv, half, PROBE_SLACK_PX, canvas),
                         "rgb": displayed_rgb(node_rgb_for(STATUS_RGB["tracking"])).round().tolist(), "tol": 40, "min": PROBE_MIN_PX, "found": None,
                         "frames": 0, "base": None}
                n_down = page.evaluate(f"(window.__tm.probe = {json.dumps(probe)}, window.__tm.down.length)")
                t_click = time.monotonic()
                page.mouse.click(sx, sy)
                downs, ups = page.evaluate(f"[window.__tm.down.slice({n_down}), window.__tm.up.slice({n_down})]")
                if not downs or not ups:
                    skipped.append("no pointerdown and pointerup in the page")
                    continue
                t_down_ms, t_up_ms = downs[0], ups[0]

                def new_target() -> Any:
                    # The click's target in the tracker's latest state, or "refused" once the
                    # console has notified a refusal (an accepted click notifies too: not a refusal).
                    made = next((t for t in running.pipeline.latest().targets
                                 if t.id not in known and t.origin == "operator"), None)
                    refused = any(str(title).endswith("refused") for title, _ in list(running.console.notifications)[n_notes:])
                    return made or (refused and "refused")

                got = _poll(page, new_target, 3)
                if got is None or got == "refused":
                    page.evaluate("window.__tm.probe = null")
                    why = running.console.notifications[-1] if got == "refused" else "no target and no refusal in 3 s"
                    _log(f"click at ({uv[0]:.0f}, {uv[1]:.0f}): {why}")
                    skipped.append(str(why))
                    continue
                t_server = time.monotonic()
                # The first image pushed after the click that shows the target.
                pushed = _poll(page, lambda: next((t for t, ids in list(running.console.image_pushes)
                                                   if t > t_click and got.id in ids), None), 5)
                if not pushed:
                    _log(f"click at ({uv[0]:.0f}, {uv[1]:.0f}): target {got.id} made, but not published in 5 s")
                    skipped.append("not published")
                    latencies.append(math.inf)  # on screen after 5 s or never: in the median, not left out
                    running.pipeline.call(RemoveTarget(got.id), 10)
                    continue
                got_received = _poll(page, lambda: next((t for t in jpeg_times if t >= pushed), None), 5)

                shown_ms = _poll(page, lambda: page.evaluate("window.__tm.probe.found"), 5)
                page.evaluate("window.__tm.probe = null")
                if shown_ms is None:
                    _log(f"click at ({uv[0]:.0f}, {uv[1]:.0f}): published, but the page drew no box around it in 5 s")
                    skipped.append("not drawn")
                    latencies.append(math.inf)
                    running.pipeline.call(RemoveTarget(got.id), 10)
                    continue
                latencies.append(shown_ms - t_down_ms)
                _log(f"click at ({uv[0]:.0f}, {uv[1]:.0f}): target {got.id} on screen {latencies[-1]:.0f} ms after the "
                     f"press, {shown_ms - t_up_ms:.0f} ms after the release")
                from_release.append(shown_ms - t_up_ms)
                if got_received is not None:
                    received.append((got_received - t_click) * 1e3)
                to_server.append((t_server - offset_s - t_down_ms / 1e3) * 1e3)
                running.pipeline.call(RemoveTarget(got.id), 10)
                page.wait_for_timeout(300)
            # A click drawn late (after 5 s, or never) counts as infinitely late; a median that is
            # then infinite (most clicks so) is "not measured".
            median = statistics.median(latencies) if latencies else float("nan")
            out["click_latency_ms"] = median if math.isfinite(median) else float("nan")
            out["click_latency_from_release_ms"] = statistics.median(from_release) if from_release else float("nan")
            out["click_latency_received_ms"] = statistics.median(received) if received else float("nan")
            out["click_to_server_ms"] = statistics.median(to_server) if to_server else float("nan")
            out["clicks_measured"] = float(sum(math.isfinite(x) for x in latencies))
            out["clicks_not_measured"] = float(len(skipped))
            browser.close()
    finally:
        running.stop()
        if priority is not None:
            restore_cpu_priority(priority)
    out["cpu_priority_raised"] = float(priority is not None and priority.applied)
    return out
