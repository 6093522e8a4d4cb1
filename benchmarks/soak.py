"""Memory over a long live run (issue 5): resident memory must stay flat.

The live pipeline of ``benchmarks.pipeline`` (the ``sim`` source at 25 Hz, 16 automatic
targets) runs for ``TRACKMETER_SOAK_S`` seconds (default 600: the issue's 10 minutes, which
is longer than the 5 minutes DESIGN.md allows other benchmarks; set e.g. 120 for a quick check).
The process's resident set size (``VmRSS`` of ``/proc/self/status``) is sampled every
``SAMPLE_S`` seconds.

Figures:

- ``rss_growth_fraction``: (median RSS of the last 30 s − median RSS around the end of the
  first minute) / the latter. Target: < 0.05. The first minute is excluded: caches, imports,
  the tracker's buffers and the allocator's arenas fill up there.
- ``rss_mb_at_1min``, ``rss_mb_end``, ``rss_mb_max``: the numbers behind it.
- ``duration_s``, ``frames_processed``, ``tracking_rate_hz``, ``dropped_fraction``: what ran.
- ``slope_mb_per_min``: least-squares slope of RSS after the first minute (a leak shows as a
  steady slope even when the run is too short for 5 %).
- ``log_errors``: ERROR records logged by ``trackmeter`` and ``console`` during the run.

With ``TRACKMETER_SOAK_CONSOLE=1`` the run is the operator console instead (issue 7: the
``sim`` console with two headless Chromium pages connected); the RSS is this process's (the
pipeline, the console and the viser server), not the browsers'.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from typing import TYPE_CHECKING, Callable, Protocol, cast

import numpy as np

if TYPE_CHECKING:
    from playwright.sync_api import ViewportSize

    from trackmeter.pipeline.snapshot import Snapshot

SAMPLE_S = 2.0
DURATION_S = float(os.environ.get("TRACKMETER_SOAK_S", "600"))
SETTLE_S = 60.0


def rss_mb() -> float:
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


class _ErrorCounter(logging.Handler):
    """Counts ERROR records and prints each (with its traceback) to stderr: a count alone does
    not say what went wrong."""

    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.count = 0
        self.setFormatter(logging.Formatter("[soak] logged %(levelname)s from %(name)s at %(relativeCreated).0f ms: %(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        self.count += 1
        print(self.format(record), file=sys.stderr, flush=True)


class _Live(Protocol):
    """What :func:`soak` runs: a started pipeline, or anything with ``latest()`` and ``close()``."""

    def latest(self) -> Snapshot: ...

    def close(self) -> None: ...


def soak(duration_s: float, start_live: Callable[[], _Live] | None = None) -> dict[str, float]:
    """Run ``start_live()`` (a started pipeline, or anything with ``latest()`` and ``close()``)
    for ``duration_s`` and sample memory."""
    if start_live is None:
        from benchmarks.pipeline import start_live
    assert start_live is not None  # benchmarks.pipeline's when not given (mypy does not follow the import)
    settle = min(SETTLE_S, duration_s / 2)
    errors = _ErrorCounter()
    for name in ("trackmeter", "console"):
        logging.getLogger(name).addHandler(errors)
    pipe = start_live()
    times, rss = [], []
    measured, valid = [], []  # sampled with the memory: one end snapshot can fall on a loop's wrap
    t0 = time.monotonic()
    next_log = t0
    try:
        while (now := time.monotonic()) - t0 < duration_s:
            times.append(now - t0)
            rss.append(rss_mb())
            latest = pipe.latest()
            if latest is not None and now - t0 >= settle:
                measured.append(sum(1 for x in latest.targets if x.measured))
                valid.append(bool(latest.pose.valid))
            if now >= next_log:
                s = pipe.latest().timings
                print(f"[soak] {now - t0:5.0f} s  rss {rss[-1]:7.1f} MB  tracked {s.frames_processed}  "
                      f"dropped {s.frames_dropped}", file=sys.stderr, flush=True)
                next_log = now + 30.0
            time.sleep(SAMPLE_S)
        snap = pipe.latest()
        snap_s = time.monotonic() - t0  # its frame count over the time it was taken at, not the last sample's
    finally:
        pipe.close()
        for name in ("trackmeter", "console"):
            logging.getLogger(name).removeHandler(errors)
    t, r = np.array(times), np.array(rss)
    at_settle = float(np.median(r[np.abs(t - settle) <= 5.0])) if np.any(np.abs(t - settle) <= 5.0) else float(r[0])
    end = float(np.median(r[t >= t[-1] - 30.0]))
    after = t >= settle
    slope = float(np.polyfit(t[after] / 60.0, r[after], 1)[0]) if after.sum() >= 3 else float("nan")
    tm = snap.timings
    return {
        "rss_growth_fraction": (end - at_settle) / at_settle,
        "rss_mb_at_1min": at_settle,
        "rss_mb_end": end,
        "rss_mb_max": float(r.max()),
        "slope_mb_per_min": slope,
        "duration_s": float(t[-1]),
        "frames_processed": float(tm.frames_processed),
        "tracking_rate_hz": tm.frames_processed / snap_s if snap_s > 0 else float("nan"),
        "dropped_fraction": tm.frames_dropped / tm.frames_read if tm.frames_read else float("nan"),
        "targets_measured_at_end": float(sum(1 for x in snap.targets if x.measured)),
        "targets_measured_median": float(np.median(measured)) if measured else float("nan"),
        "targets_measured_min": float(min(measured)) if measured else float("nan"),
        "pose_valid_fraction": float(np.mean(valid)) if valid else float("nan"),
        "log_errors": float(errors.count),
    }


class _ConsoleRun:
    """The ``sim`` console with automatic selection and two headless browsers connected."""

    def __init__(self) -> None:
        import shutil

        from playwright.sync_api import sync_playwright

        from benchmarks.pipeline import make_engine
        from console.server import start_console
        from tests.browser.conftest import CHROMIUM_ARGS, VIEWPORT, free_port
        from trackmeter.pipeline.snapshot import SetAuto
        from trackmeter.sources import open_source

        from benchmarks.console import console_priority

        _, self._priority = console_priority()  # as trackmeter console does
        source = open_source("sim", realtime=True, loop=True)
        self.running = start_console(source, make_engine(source), port=free_port())
        self.running.pipeline.submit(SetAuto(True, 16, "gabor"))
        self._pw = sync_playwright().start()
        self._browser = self._pw.chromium.launch(executable_path=shutil.which("chromium"), args=CHROMIUM_ARGS)
        self.pages = []
        for _ in range(2):
            page = self._browser.new_context(viewport=cast("ViewportSize", VIEWPORT)).new_page()
            page.goto(self.running.url)
            self.pages.append(page)

    def latest(self) -> Snapshot:
        return self.running.pipeline.latest()

    def close(self) -> None:
        try:
            self._browser.close()
            self._pw.stop()
        finally:
            self.running.stop()
            if self._priority is not None:
                from trackmeter.priority import restore_cpu_priority

                restore_cpu_priority(self._priority)


def unmet() -> str | None:
    """What this benchmark needs and this machine lacks: the browsers' for the console soak."""
    from benchmarks import browser_unmet

    return browser_unmet() if os.environ.get("TRACKMETER_SOAK_CONSOLE") == "1" else None


def run() -> dict[str, float]:
    if os.environ.get("TRACKMETER_SOAK_CONSOLE") == "1":
        out = soak(DURATION_S, _ConsoleRun)
        out["console"] = 1.0
        return out
    return soak(DURATION_S)
