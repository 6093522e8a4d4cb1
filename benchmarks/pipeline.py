"""Throughput of the whole pipeline (issue 5): live on the simulator, and offline on a recording.

Figures:

- ``live_rate_hz``: frames tracked per second by the tracking thread, the ``sim`` source (the
  ``estec`` scenario rendered live at its 25 Hz) with 16 automatic targets, over
  ``MEASURE_S`` seconds after ``WARMUP_S`` of warm-up counted from the first frame tracked (on a
  loaded host the start-up alone took 5-7 s of a warm-up counted from the start), while the
  stream is also recorded.
  Target: 25 Hz.
- ``dropped_fraction``: frames the tracker never saw (latest frame won) over frames read, same
  window. Target: < 0.01.
- ``live_rate_hz_window_median`` / ``_min``, ``dropped_fraction_window_median`` / ``_max``: the
  same over each of ``LIVE_WINDOWS`` equal sub-windows, their median and worst: how steady the
  pooled figures above were (the machine is shared; one window alone would not say).
- ``acquisition_hz``: frames the source delivered per second in that window.
- ``source_alone_fps``: the simulator rendering as fast as it can with nothing else running
  (in its render-ahead worker process, as the live source does), measured in the same run: the
  ceiling the live figures are bounded by on this machine.
- ``latency_ms_median``, ``step_ms_median``: frame leaving the source → pose published, and the
  tracking step alone, medians over the window.
- ``recorded_fraction``: frames written by the recorder over frames read during the live run
  (every frame must be recorded: 1.0), and ``record_not_recorded`` (frames the recorder had to
  count as not recorded).
- ``offline_fps``: ``trackmeter track``'s pipeline on a recorded sequence folder
  (``OFFLINE_FRAMES`` frames of the same scenario), as fast as possible, lossless, 16 automatic
  targets: the median of ``OFFLINE_REPEATS`` runs. Target: >= 60.
- ``offline_read_fps``: reading the same folder without tracking (baseline, same run), and
  ``offline_ratio_to_read`` = ``offline_fps / offline_read_fps``.
- ``offline_engine_alone_fps``: the same engine called in a plain loop (read + process on one
  thread, no pipeline), and ``offline_ratio_to_engine_alone`` = ``offline_fps`` over it: the
  pipeline's own cost (1.0 = none; above 1 when reading overlaps tracking).
- ``offline_engine_alone_cpu_ms``, ``offline_cpu_ms``: CPU time of the whole process per frame
  (all threads) in those runs (medians); less sensitive than the rates to other programs sharing the
  cores. ``offline_tracking_cpu_ms``: CPU time of the tracking thread alone per frame in the
  pipeline runs (its critical path when the other core is free).

Environment: ``TRACKMETER_BENCH_LIVE_S`` changes ``MEASURE_S`` (default 40).
"""

from __future__ import annotations

import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

WARMUP_S = 10.0
MEASURE_S = float(os.environ.get("TRACKMETER_BENCH_LIVE_S", "40"))
LIVE_WINDOWS = 4  # sub-windows of MEASURE_S: 10 s, 250 frames each by default
OFFLINE_FRAMES = 150
OFFLINE_REPEATS = 3
N_TARGETS = 16


def _log(msg: str) -> None:
    print(f"[pipeline] {msg}", file=sys.stderr, flush=True)


def make_engine(source: Any, case: str = "a", live_errors: bool = True) -> Any:
    """The real tracking engine for ``source`` (config/default.yaml); ``live_errors=False`` as
    ``trackmeter track`` builds it (no errors against the truth while tracking)."""
    from trackmeter.data.config import load_config
    from trackmeter.pipeline.engine import Engine

    return Engine(load_config(), source.rig, model=source.model, case=case,  # type: ignore[arg-type]
                  rate_hz=source.rate_hz, live_errors=live_errors)


class LiveWindow:
    """Counters of a running pipeline between :meth:`begin` and :meth:`end`.

    The figures are pooled over the whole window (frames counted over its time: the issue's
    rate and dropped fraction), and also taken per sub-window between the :meth:`mark` calls
    (:meth:`wait`): their median, and the worst one, say how steady the pooled figure was on a
    shared machine, where one 40 s window alone could not.
    """

    def __init__(self, pipe: Any, clock: Callable[[], float] = time.monotonic) -> None:
        self.pipe = pipe
        self.clock = clock
        self.latencies: list[float] = []
        self.steps: list[float] = []
        self._last_processed = -1
        self._on = False
        self._marks: list[tuple[float, Any]] = []
        pipe.subscribe(self._collect)

    def _collect(self, snap: Any) -> None:
        t = snap.timings
        if self._on and t.frames_processed != self._last_processed:
            self.latencies.append(t.latency_ms)
            self.steps.append(t.step_ms)
        self._last_processed = t.frames_processed

    def begin(self) -> None:
        self.t0 = self.clock()
        self.s0 = self.pipe.latest().timings
        self._marks = [(self.t0, self.s0)]
        self._on = True

    def mark(self) -> None:
        """End one sub-window and start the next."""
        self._marks.append((self.clock(), self.pipe.latest().timings))

    def wait(self, seconds: float, windows: int, sleep: Callable[[float], object] = time.sleep) -> None:
        """Let ``seconds`` pass in ``windows`` equal sub-windows (the last one ends at :meth:`end`)."""
        for k in range(windows):
            sleep(seconds / windows)
            if k < windows - 1:
                self.mark()

    def end(self) -> dict[str, float]:
        self._on = False
        self.mark()
        rates, dropped = [], []
        for (ta, sa), (tb, sb) in zip(self._marks, self._marks[1:]):
            read = sb.frames_read - sa.frames_read
            rates.append((sb.frames_processed - sa.frames_processed) / (tb - ta))
            dropped.append((sb.frames_dropped - sa.frames_dropped) / read if read else float("nan"))
        t1, s1 = self._marks[-1]
        dt = t1 - self.t0
        read = s1.frames_read - self.s0.frames_read
        return {
            "rate_hz": (s1.frames_processed - self.s0.frames_processed) / dt,
            "acquisition_hz": read / dt,
            "dropped_fraction": (s1.frames_dropped - self.s0.frames_dropped) / read if read else float("nan"),
            "latency_ms_median": statistics.median(self.latencies) if self.latencies else float("nan"),
            "step_ms_median": statistics.median(self.steps) if self.steps else float("nan"),
            "windows": float(len(rates)),
            "rate_hz_window_median": statistics.median(rates),
            "rate_hz_window_min": min(rates),
            "dropped_fraction_window_median": statistics.median(dropped),
            "dropped_fraction_window_max": max(dropped),
        }


def start_live(record_dir: Path | None = None, n_targets: int = N_TARGETS) -> Any:
    """The live pipeline on ``sim`` (realtime, looping) with ``n_targets`` automatic targets."""
    from trackmeter.pipeline.pipeline import Pipeline
    from trackmeter.pipeline.snapshot import SetAuto
    from trackmeter.sources import open_source

    source = open_source("sim", realtime=True, loop=True)
    pipe = Pipeline(source, make_engine(source), drop_frames=True, record_dir=record_dir)
    pipe.submit(SetAuto(True, n_targets, "gabor"))
    return pipe.start()


def source_alone_fps(seconds: float = 6.0) -> float:
    from trackmeter.sources import open_source

    with open_source("sim", realtime=False, loop=True) as source:
        source.read()
        n, t0 = 0, time.monotonic()
        while time.monotonic() - t0 < seconds:
            source.read()
            n += 1
        return n / (time.monotonic() - t0)


def offline(tmp: Path) -> dict[str, float]:
    """Render ``OFFLINE_FRAMES`` frames of the scenario to a sequence folder under ``tmp``, then
    :func:`offline_on` it."""
    from trackmeter.data.sequence import SequenceWriter
    from trackmeter.sources import open_source

    seq = tmp / "offline_seq"
    sim = open_source("sim", realtime=False)
    _log(f"rendering {OFFLINE_FRAMES} frames to {seq}")
    with SequenceWriter(seq, sim.rig) as writer:
        for _ in range(OFFLINE_FRAMES):
            frame = sim.read()
            if frame is None:
                break
            writer.write(frame)
    sim.close()  # stops its render-ahead worker
    return offline_on(seq)


def offline_on(seq: Path) -> dict[str, float]:
    """The ``offline_*`` figures on the recorded sequence folder ``seq``."""
    from trackmeter.pipeline.pipeline import run_headless
    from trackmeter.pipeline.snapshot import SetAuto
    from trackmeter.sources import open_source

    source = open_source(f"seq:{seq}")
    t0 = time.perf_counter()
    n_read = 0
    while source.read() is not None:
        n_read += 1
    read_fps = n_read / (time.perf_counter() - t0)
    source.close()

    # Baseline: the same engine called in a plain loop on this thread (no pipeline threads).
    source = open_source(f"seq:{seq}")
    engine = make_engine(source, live_errors=False)  # as track builds it
    first = source.read()
    assert first is not None
    t0, c0 = time.perf_counter(), time.process_time()
    engine.process(first)
    engine.handle(SetAuto(True, N_TARGETS, "gabor"), first)
    n_direct = 1
    while (frame := source.read()) is not None:
        engine.process(frame)
        n_direct += 1
    direct_fps = n_direct / (time.perf_counter() - t0)
    direct_cpu_ms = (time.process_time() - c0) * 1e3 / n_direct
    source.close()

    fps, cpu_ms, tracking_ms = [], [], []
    for repeat in range(OFFLINE_REPEATS):
        source = open_source(f"seq:{seq}")
        engine = make_engine(source, live_errors=False)  # as track builds it
        tracking_cpu_s: list[float] = []

        def timed_process(frame: Any, process: Any = engine.process, spent: list[float] = tracking_cpu_s) -> Any:
            c = time.thread_time()  # the tracking thread's own CPU time
            try:
                return process(frame)
            finally:
                spent.append(time.thread_time() - c)

        engine.process = timed_process
        t0, c0 = time.perf_counter(), time.process_time()
        last, _ = run_headless(source, engine, commands=[SetAuto(True, N_TARGETS, "gabor")])
        wall = time.perf_counter() - t0
        cpu_s = time.process_time() - c0
        source.close()
        processed = last.timings.frames_processed
        n_tracked = sum(1 for t in last.targets if t.measured)
        fps.append(processed / wall)
        cpu_ms.append(cpu_s * 1e3 / processed if processed else float("nan"))
        tracking_ms.append(1e3 * sum(tracking_cpu_s) / len(tracking_cpu_s) if tracking_cpu_s else float("nan"))
        _log(f"offline run {repeat + 1}/{OFFLINE_REPEATS}: {processed} frames in {wall:.1f} s ({fps[-1]:.1f} fps), "
             f"{n_tracked} targets measured at the end")
    offline_fps = statistics.median(fps)
    return {
        "offline_fps": offline_fps,
        "offline_fps_min": min(fps),
        "offline_fps_max": max(fps),
        "offline_read_fps": read_fps,
        "offline_ratio_to_read": offline_fps / read_fps if read_fps else float("nan"),
        "offline_engine_alone_fps": direct_fps,
        "offline_ratio_to_engine_alone": offline_fps / direct_fps,
        "offline_engine_alone_cpu_ms": direct_cpu_ms,
        "offline_cpu_ms": statistics.median(cpu_ms),
        "offline_tracking_cpu_ms": statistics.median(tracking_ms),
        "offline_frames": float(processed),
        "offline_targets_at_end": float(n_tracked),
    }


#: The longest the live run waits for its first tracked frame before the warm-up begins, s.
FIRST_FRAME_TIMEOUT_S = 120.0


def _wait_for_first_frame(pipe: Any) -> None:
    """Until ``pipe`` has tracked a frame (or :data:`FIRST_FRAME_TIMEOUT_S`, and the warm-up
    begins all the same): the start-up (the render worker, the first compile) is not warm-up."""
    start = time.monotonic()
    while pipe.timings().frames_processed == 0 and time.monotonic() - start < FIRST_FRAME_TIMEOUT_S:
        time.sleep(0.05)
    _log(f"live: first frame tracked after {time.monotonic() - start:.1f} s")


def run() -> dict[str, float]:
    out: dict[str, float] = {}
    _log("source alone ...")
    out["source_alone_fps"] = source_alone_fps()
    with tempfile.TemporaryDirectory(prefix="trackmeter-bench-") as tmp_name:
        tmp = Path(tmp_name)
        _log(f"live: warm-up {WARMUP_S:.0f} s, measure {MEASURE_S:.0f} s (recording on)")
        pipe = start_live(record_dir=tmp / "live_rec")
        window = LiveWindow(pipe)
        try:
            _wait_for_first_frame(pipe)
            time.sleep(WARMUP_S)
            window.begin()
            window.wait(MEASURE_S, LIVE_WINDOWS)
            live = window.end()
            snap = pipe.latest()
        finally:
            pipe.close()
        rec = pipe.recording_stats()
        out["live_rate_hz"] = live["rate_hz"]
        out["dropped_fraction"] = live["dropped_fraction"]
        out["acquisition_hz"] = live["acquisition_hz"]
        out["latency_ms_median"] = live["latency_ms_median"]
        out["step_ms_median"] = live["step_ms_median"]
        for key in ("rate_hz_window_median", "rate_hz_window_min", "dropped_fraction_window_median",
                    "dropped_fraction_window_max"):
            out[key if key.startswith("dropped") else f"live_{key}"] = live[key]
        out["live_targets_measured"] = float(sum(1 for t in snap.targets if t.measured))
        out["live_pose_valid"] = float(snap.pose.valid)
        total_read = pipe.timings().frames_read  # the totals (the last snapshot may lag a frame read)
        out["recorded_fraction"] = rec.frames_written / total_read if total_read else float("nan")
        out["record_not_recorded"] = float(rec.frames_dropped + rec.frames_lost)
        _log(f"live: {out}")
        out.update(offline(tmp))
    return out
