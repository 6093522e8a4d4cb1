"""The threaded pipeline of DESIGN.md section 4: acquisition, tracking, snapshots, recording.

::

    Source ──read()──> [acquisition thread] ──latest-frame slot──> [tracking thread] ──> Snapshot
                              │                  commands queue ^          │
                              └──> [recorder thread] (own queue)  └── console / CLI   v
                                                                   newest-snapshot slot + subscribers

- The acquisition thread calls ``source.read()`` at the source's own pace and puts each frame
  into a one-frame slot. When the tracking thread has not taken the previous frame yet, the new
  one replaces it (latest frame wins) and the old one is counted as dropped: the source is never
  blocked and memory never grows. For offline runs (a recorded sequence read as fast as
  possible), ``drop_frames=False`` makes the acquisition wait for the slot instead, so every
  frame is tracked. A frame read for a step (paused) waits likewise: the operator asked for it.
- The tracking thread owns the engine (:class:`EngineLike`, all tracker state). It takes the newest frame,
  calls ``engine.process(frame)``, publishes an immutable :class:`Snapshot`, and between frames
  applies the queued :class:`Command` objects in the order they were sent, resolving each
  command's ``reply`` future. Pause, step, restart and recording are handled here; everything
  else goes to ``engine.handle(command, frame)`` with the frame the operator saw.
- Automatic selection filters its frame (the Gabor bank) on the tracking thread, inside the
  step. A helper thread filtering it while the step tracked the targets was measured slower
  on two cores: its many short OpenCV calls each wait for the GIL the tracking thread holds,
  so the step waited ~14 ms for a ~12 ms filtering (recorded sequence: 57-65 fps with the
  helper, 73 without).
- The recorder writes every frame the acquisition read to a sequence folder from its own
  bounded queue (``record_queue_frames`` deep). It never blocks the acquisition; if the disk
  cannot keep up and the queue is full, the frame is counted in
  :attr:`RecordingStats.frames_dropped` (never silently lost).
- A source that raises mid-run is reported in ``Snapshot.source_status``; the pipeline stays
  up (a restart may bring the source back).
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import logging
import math
import queue
import signal
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable, Iterator, Protocol, Sequence

from trackmeter.core.patch_tracking import warm_up
from trackmeter.core.stereo import StereoRig
from trackmeter.core.targets import TargetState
from trackmeter.errors import TrackmeterError, counted, quoted_name
from trackmeter.signals import STOP_SIGNALS, interrupt_kept
from trackmeter.pipeline.engine import SelectModelPoints
from trackmeter.pipeline.snapshot import (
    AcquireModel,
    ClearTargets,
    Command,
    CommandReply,
    LoadModel,
    PoseEstimate,
    RemoveNearest,
    RemoveTarget,
    ResetTracking,
    RestartSource,
    SelectPoint,
    SetCase,
    SetPaused,
    SetRecording,
    Snapshot,
    StepOnce,
    Timings,
)
from trackmeter.sources.base import Source, StereoFrame

if TYPE_CHECKING:
    from types import FrameType

log = logging.getLogger(__name__)
#: A failing source's one line (a console's terminal shows it). The status also reaches every
#: snapshot: a consumer that reports it itself (``trackmeter track``) quiets this logger.
source_log = logging.getLogger(f"{__name__}.source")

@contextlib.contextmanager
def source_said_by_caller() -> Iterator[None]:
    """:data:`source_log` silent within the block (its level restored after): for a caller
    that says the source's failure itself, with what it means there (``track``'s run status,
    the console's status line), so that it is not said twice."""
    level = source_log.level
    source_log.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        source_log.setLevel(level)


ErrorsDict = dict[str, Any]


class EngineLike(Protocol):
    """What the tracking thread needs from the tracker (``trackmeter.pipeline.engine.Engine``).

    No threads inside: the pipeline calls both methods from the tracking thread only. An engine
    that offers ``targets`` (every target as it stands after the commands) has a command's effect,
    e.g. a click's new target, published at once on the frame the operator saw. The snapshot's
    tracker settings are read, where offered, from ``case``, ``auto_enabled``, ``auto_count``,
    ``auto_method``, ``auto_shortfall``, ``filter_cutoff_hz`` and ``model`` (its ``ids``; the
    recorder writes it with the frames); an engine without them gets defaults.
    """

    def handle(self, command: Command, frame: StereoFrame | None) -> CommandReply:
        """Apply one command; ``frame`` is the last processed frame (the one the operator saw)."""
        ...

    def process(self, frame: StereoFrame) -> tuple[Sequence[TargetState], PoseEstimate, ErrorsDict | None]:
        """Track one frame: targets after the step, the pose estimate, errors against truth."""
        ...


class RecordWriter(Protocol):
    """A sequence writer (``trackmeter.data.sequence.SequenceWriter``)."""

    def write(self, frame: StereoFrame) -> None: ...

    def close(self) -> None: ...


WriterFactory = Callable[[Path], RecordWriter]


@dataclass(frozen=True)
class RecordingStats:
    """Counters of one recording (or the last one, after it stopped).

    Attributes:
        directory: the sequence folder, or None when nothing was ever recorded.
        active: True while recording.
        frames_queued: frames handed to the recorder.
        frames_written: frames on disk.
        frames_dropped: frames that did not fit the recorder's queue (its writes too slow: the
            disk, or a CPU busy elsewhere, which encodes the PNGs); each
            one is counted, never lost silently.
        queue_depth: frames waiting to be written now.
        error: why the recording failed, else None.
        frames_lost: frames not written because the writer had failed (the one it failed on
            included).
        discarded: it ended without a frame, and nothing of it was kept (a folder of csv
            headers is no sequence: ``SequenceWriter.discarded``).
        image_bytes_written: bytes of the image files written (the writer's
            ``image_bytes_written``; 0 for one that does not count them).
    """

    directory: str | None = None
    active: bool = False
    frames_queued: int = 0
    frames_written: int = 0
    frames_dropped: int = 0
    queue_depth: int = 0
    error: str | None = None
    frames_lost: int = 0
    discarded: bool = False
    image_bytes_written: int = 0

    def summary(self) -> str:
        """What a stopped recording holds, one line: ``recorded N frames to DIR`` and what was
        not kept, or that no frame came and nothing was kept."""
        if self.discarded:
            return f"recorded no frame (none came while recording: paused?): nothing kept in {self.directory}"
        return (f"recorded {counted(self.frames_written, 'frame')} to {self.directory}" + self.not_recorded()
                + (f"; {self.error}" if self.error else ""))

    def not_recorded(self) -> str:
        """``", N NOT recorded (why)"`` for each kind of frame not kept, else ``""``."""
        return ((f", {self.frames_dropped} NOT recorded (the writer fell behind: disk or CPU too slow)" if self.frames_dropped else "")
                + (f", {self.frames_lost} NOT recorded (the writer failed)" if self.frames_lost else ""))


def _default_writer_factory(rig: StereoRig | None, model: Callable[[], Any | None] = lambda: None) -> WriterFactory:
    def make(directory: Path) -> RecordWriter:
        from trackmeter.data.sequence import SequenceWriter

        # The model goes with the frames (the one in use when the recording starts: the
        # operator may load another): replayed with --source DIR, case (b) finds it.
        return SequenceWriter(directory, rig, model())  # refuses a folder that holds a sequence

    return make


class _Recorder:
    """Writes frames to a sequence folder on its own thread, from a bounded queue.

    Every frame offered is written or counted: ``frames_dropped`` when the queue was full (the
    writer too slow), ``frames_lost`` once the writer failed (disk full; the failed frame
    included). A failure ends the recording at once (the folder closed with what it holds);
    the thread still takes every frame queued, so a stop never waits on a full queue.

    A sequence's time only increases: when the stream's time goes back (the source restarted),
    the frames after it are written with their time carried on past the last one by its frame
    interval, as a looping source's are. The jump itself is marked: the frame that starts a new
    pass (``StereoFrame.cut``; the next kept one when that frame is not) is listed in the
    folder's ``cuts.csv``, so played back the replay starts over there as the live run did.
    """

    _STOP = object()

    def __init__(self, directory: Path, writer: RecordWriter, max_frames: int) -> None:
        self.directory = directory
        self._writer: RecordWriter | None = writer  # None once closed
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=max_frames)
        self._lock = threading.Lock()
        self.frames_queued = 0
        self.frames_written = 0
        self.frames_dropped = 0
        self.frames_lost = 0
        self.image_bytes_written = 0
        self.error: str | None = None
        self.discarded = False  # the writer kept nothing (no frame came)
        self._cut_dropped = False  # the last frame not kept started a new pass (offer's thread only)
        self._shift_s = 0.0  # added to the stream's time since its last restart
        self._last_t_s: float | None = None  # last written time and interval, s
        self._last_dt_s = 0.04
        self._thread = threading.Thread(target=self._run, name="trackmeter-recorder", daemon=True)
        self._thread.start()

    @property
    def failed(self) -> bool:
        """The writer failed: the folder is closed, nothing more is recorded."""
        return self.error is not None

    def offer(self, frame: StereoFrame) -> None:
        """Queue ``frame`` without ever blocking; count it when it cannot be kept."""
        if self.failed:
            with self._lock:
                self.frames_lost += 1
            return
        if self._cut_dropped and not frame.cut:
            # A new pass began on a frame not kept: the jump is before this one.
            frame = dataclasses.replace(frame, cut=True)
        try:
            self._queue.put_nowait(frame)
            self._cut_dropped = False
            with self._lock:
                self.frames_queued += 1
        except queue.Full:
            self._cut_dropped = frame.cut
            with self._lock:
                self.frames_dropped += 1
                first = self.frames_dropped == 1
            if first:  # once per recording; the count is in the stats
                # Not "and later ones": the queue drains and takes frames again (gaps, not a cut-off).
                log.warning("recorder queue full (the writer fell behind: disk or CPU too slow): frame %d not "
                            "recorded, nor others while it stays full", frame.index)

    def _run(self) -> None:
        while (item := self._queue.get()) is not self._STOP:
            if self.failed:
                with self._lock:
                    self.frames_lost += 1
                continue
            try:
                assert self._writer is not None
                self._writer.write(self._carried_on(item))
                with self._lock:
                    self.frames_written += 1
                    self.image_bytes_written = int(getattr(self._writer, "image_bytes_written", 0))
                    # where the writer follows a folder moved while recording (SequenceWriter)
                    self.directory = Path(getattr(self._writer, "directory", self.directory))
            except Exception as exc:  # disk full, permissions: report, keep the pipeline up
                with self._lock:  # stats() reads the counts and the error together
                    self.frames_lost += 1
                    self.error = f"recording failed: {exc}"
                log.error("%s", self.error)
                self._close_writer()
        self._close_writer()

    def _close_writer(self) -> None:
        writer, self._writer = self._writer, None
        if writer is None:
            return
        try:
            writer.close()
            self.discarded = bool(getattr(writer, "discarded", False))
        except Exception as exc:
            with self._lock:
                self.error = self.error or f"closing the recording failed: {exc}"
            log.error("%s", self.error)

    def _carried_on(self, frame: StereoFrame) -> StereoFrame:
        t = frame.t_s + self._shift_s
        if self._last_t_s is not None:
            if t <= self._last_t_s:  # the stream started again
                self._shift_s += self._last_t_s + self._last_dt_s - t
                t = self._last_t_s + self._last_dt_s
            else:
                self._last_dt_s = t - self._last_t_s
        self._last_t_s = t
        return frame if t == frame.t_s else dataclasses.replace(frame, t_s=t, stamp_ns=None)

    def close(self) -> None:
        """Write everything queued, close the folder, join the thread."""
        self._queue.put(self._STOP)  # the thread takes every item, failed or not: this returns
        self._thread.join()

    def stats(self, active: bool) -> RecordingStats:
        with self._lock:
            return RecordingStats(str(self.directory), active and not self.failed, self.frames_queued,
                                  self.frames_written, self.frames_dropped, self._queue.qsize(), self.error,
                                  self.frames_lost, self.discarded, self.image_bytes_written)


class _RateMeter:
    """Events per second over the last ``window`` events (monotonic clock)."""

    def __init__(self, window: int = 50) -> None:
        self._times: collections.deque[float] = collections.deque(maxlen=window)
        self._since = -math.inf

    def tick(self, t: float) -> None:
        if t >= self._since:  # an event of before the reset (a frame read before a pause) is not counted
            self._times.append(t)

    def reset(self) -> None:
        self._since = time.monotonic()
        self._times.clear()

    def rate_hz(self, now: float | None = None) -> float:
        if len(self._times) < 2:
            return 0.0
        span = self._times[-1] - self._times[0]
        # A stalled stream reads as slowing down, not as its last good rate.
        if now is not None:
            span = max(span, now - self._times[0] - (span / (len(self._times) - 1)))
        return (len(self._times) - 1) / span if span > 0 else 0.0


# The replies of commands the pipeline never got to apply (it stopped, or the run ended first):
# not refusals by the tracker.
STOPPED = "pipeline stopped"
NOT_APPLIED = "not applied"

class Pipeline:
    """Acquisition and tracking threads around one source and one engine.

    Use as a context manager or call :meth:`start` and :meth:`stop`::

        with Pipeline(source, engine, rig=source.rig) as pipe:
            reply = pipe.call(SelectPoint(320.0, 240.0))
            snap = pipe.latest()

    Args:
        source: where frames come from; only the acquisition thread reads it.
        engine: the tracker; only the tracking thread touches it.
        rig: the stereo rig (for recordings); defaults to ``source.rig``.
        drop_frames: True for live sources (latest frame wins, drops counted). False for
            offline runs: the acquisition waits until the tracking thread took the frame.
        record_dir: start recording to this folder at once.
        record_queue_frames: frames the recorder may hold while the disk catches up.
        writer_factory: makes the recording writer for a folder (default: SequenceWriter).
        paused: start paused (no frame is read until play or step).
    """

    def __init__(
        self,
        source: Source,
        engine: EngineLike,
        *,
        rig: StereoRig | None = None,
        drop_frames: bool = True,
        record_dir: str | Path | None = None,
        record_queue_frames: int = 256,
        writer_factory: WriterFactory | None = None,
        paused: bool = False,
    ) -> None:
        self.source = source
        self.engine = engine
        self.rig = rig if rig is not None else source.rig
        self.drop_frames = drop_frames
        self._record_queue_frames = int(record_queue_frames)
        self._writer_factory = writer_factory or _default_writer_factory(self.rig, self._model_in_use)
        self._initial_record_dir = Path(record_dir) if record_dir is not None else None

        # One condition guards the frame slot, the command queue and the run state, so the
        # tracking thread wakes for either a frame or a command.
        self._cond = threading.Condition()
        self._slot: tuple[StereoFrame, float] | None = None
        self._commands: collections.deque[Command] = collections.deque()
        self._stop = False
        self._paused = paused
        self._steps = 0
        self._source_status: str | None = None
        self._source_done = False  # ended or failed: acquisition waits for a restart
        self._source_lock = threading.Lock()
        self._subscribers: list[Callable[[Snapshot], None]] = []

        self._frames_read = 0
        self._frames_processed = 0
        self._frames_dropped = 0
        self._counts_at_restart: tuple[int, int] | None = None
        self._source_generation = 0  # counts restarts; see _acquire_loop
        self._acq_rate = _RateMeter()
        self._trk_rate = _RateMeter()

        self._recorder: _Recorder | None = None
        self._source_pass = 1  # a looping source's pass of the frame last tracked (tracking thread)
        self._tracked_since_restart = 0
        self._stopped_recordings: list[RecordingStats] = []  # every one of the run, in order
        self._closing: list[_Recorder] = []  # stopped by the operator, still writing what they queued
        self._closing_threads: list[threading.Thread] = []
        self._record_lock = threading.Lock()

        self._last_frame: StereoFrame | None = None
        self._last_targets: tuple[TargetState, ...] = ()
        self._last_pose = PoseEstimate.invalid("no frame yet")
        self._last_errors: ErrorsDict | None = None
        self._last_latency_ms = 0.0
        self._last_step_ms = 0.0
        self._sequence = 0
        self._snapshot = self._make_snapshot()
        self._snap_cond = threading.Condition()
        self.engine_errors = 0

        self._acq_thread = threading.Thread(target=self._acquire_loop, name="trackmeter-acquisition", daemon=True)
        self._trk_thread = threading.Thread(target=self._track_loop, name="trackmeter-tracking", daemon=True)
        self._started = False

    # ------------------------------------------------------------------ life cycle
    def start(self) -> Pipeline:
        """Start recording (if asked) and both threads. Returns self."""
        if self._started:
            raise RuntimeError("pipeline already started")
        self._started = True
        with interrupt_kept():  # a stop signal during a compile is otherwise lost there
            warm_up()  # before the source runs: its first frames are not dropped for a compile
        if self._initial_record_dir is not None:
            self._start_recording(self._initial_record_dir)
        self._trk_thread.start()
        self._acq_thread.start()
        return self

    def request_stop(self) -> None:
        """Ask both threads to stop after what they are doing, without waiting for them: safe
        on the tracking thread itself (a snapshot subscriber, a command's reply callback).
        :meth:`stop` still joins them and closes the recording."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()

    def stop(self, timeout_s: float = 10.0) -> None:
        """Stop both threads, join them, close the recording (everything queued is written)."""
        self.request_stop()
        for thread in (self._acq_thread, self._trk_thread):
            if thread.is_alive():
                thread.join(timeout_s)
                if thread.is_alive():
                    log.error("%s did not stop within %.1f s", thread.name, timeout_s)
        self._stop_recording()
        with self._record_lock:
            closing = list(self._closing_threads)
        for thread in closing:  # recordings the operator stopped, still writing what they queued
            thread.join()
        # Commands nobody will apply any more must not leave a caller waiting forever.
        with self._cond:
            pending, self._commands = list(self._commands), collections.deque()
        for command in pending:
            _resolve(command, CommandReply(False, STOPPED))

    def close(self) -> None:
        """Stop and close the source."""
        self.stop()
        try:
            self.source.close()
        except Exception as exc:
            log.warning("closing the source failed: %s", exc)

    def __enter__(self) -> Pipeline:
        return self.start() if not self._started else self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def running(self) -> bool:
        return self._trk_thread.is_alive()

    # ------------------------------------------------------------------ observers
    def latest(self) -> Snapshot:
        """The newest published snapshot (never None: a placeholder before the first frame)."""
        return self._snapshot

    def subscribe(self, callback: Callable[[Snapshot], None]) -> Callable[[], None]:
        """Call ``callback(snapshot)`` on the tracking thread for every published snapshot.

        The callback must be quick (hand the snapshot to another thread if it does real
        work). Returns a function that unsubscribes.
        """
        with self._cond:
            self._subscribers = [*self._subscribers, callback]

        def unsubscribe() -> None:
            with self._cond:
                self._subscribers = [s for s in self._subscribers if s is not callback]

        return unsubscribe

    def wait_snapshot(self, after_sequence: int, timeout_s: float | None = None) -> Snapshot | None:
        """Block until a snapshot newer than ``after_sequence`` is published (None on timeout)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._snap_cond:
            while self._snapshot.sequence <= after_sequence:
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None
                self._snap_cond.wait(remaining)
            return self._snapshot

    def _recording(self) -> bool:
        """A recording is on and its writer has not failed."""
        with self._record_lock:
            return self._recorder is not None and not self._recorder.failed

    def recording_stats(self) -> RecordingStats:
        """Counters of the current (or last) recording: one stopped but still writing what it
        queued shows its queue draining."""
        with self._record_lock:
            if self._recorder is not None:
                return self._recorder.stats(True)
            if self._closing:
                return self._closing[-1].stats(False)
            return self._stopped_recordings[-1] if self._stopped_recordings else RecordingStats()

    def recordings(self) -> tuple[RecordingStats, ...]:
        """Counters of every recording of the run, in the order they were stopped (those still
        writing what they queued after them, the one going on last)."""
        with self._record_lock:
            current = (self._recorder.stats(True),) if self._recorder is not None else ()
            closing = tuple(r.stats(False) for r in self._closing)
            return (*self._stopped_recordings, *closing, *current)

    # ------------------------------------------------------------------ commands
    def submit(self, command: Command) -> Future[CommandReply]:
        """Queue a command for the tracking thread; returns the future of its reply.

        Safe from any thread (viser callbacks, signal handlers). Commands are applied in the
        order they were submitted, between frames.
        """
        if command.reply is None:
            command = dataclasses.replace(command, reply=Future())
        assert command.reply is not None
        with self._cond:
            if self._stop:
                _resolve(command, CommandReply(False, STOPPED))
            else:
                self._commands.append(command)
                self._cond.notify_all()
        return command.reply

    def call(self, command: Command, timeout_s: float = 10.0) -> CommandReply:
        """Submit ``command`` and wait for its reply."""
        return self.submit(command).result(timeout_s)

    # ------------------------------------------------------------------ acquisition thread
    def _acquire_loop(self) -> None:
        while True:
            with self._cond:
                while not self._stop and (self._source_done or (self._paused and self._steps == 0)):
                    self._cond.wait()
                if self._stop:
                    return
                stepped = self._paused  # the operator asked for this very frame
                if stepped:
                    self._steps -= 1
            # The stream a frame comes from: a Restart applied between this read and the hand-over
            # below makes the frame (or the end, or the failure) one of the stream before it.
            try:
                with self._source_lock:
                    generation = self._source_generation
                    frame = self.source.read()
            except Exception as exc:  # a failing camera must not take the process down
                message = str(exc) if isinstance(exc, TrackmeterError) else f"{type(exc).__name__}: {exc}"
                source_log.error("source failed: %s", message)
                self._source_finished(f"source failed: {message}", generation)
                continue
            if frame is None:
                self._source_finished("ended", generation)
                continue
            t_read = time.monotonic()
            with self._record_lock:
                # Offered under the lock (offer never blocks): a stop taking the recorder
                # between the two would close it first, and the frame queued behind its end
                # would be neither written nor counted.
                if self._recorder is not None:
                    self._recorder.offer(frame)
            with self._cond:
                self._frames_read += 1
                read_after_restart = generation != self._source_generation  # counted after the restart's tally
                self._acq_rate.tick(t_read)
                if not self.drop_frames or stepped:
                    while self._slot is not None and not self._stop and generation == self._source_generation:
                        self._cond.wait()
                if generation != self._source_generation:
                    # Read before a restart (or restarted while it waited): recorded, not tracked.
                    self._frames_dropped += 1
                    self._old_stream_counted(read=read_after_restart)
                    continue
                if self._slot is not None:
                    self._frames_dropped += 1
                    if self._slot[0].cut and not frame.cut:
                        # The dropped frame began a new pass: the jump is still before this one
                        frame = dataclasses.replace(frame, cut=True)
                self._slot = (frame, t_read)
                self._cond.notify_all()

    def _source_finished(self, status: str, generation: int) -> None:
        with self._cond:
            if generation != self._source_generation:
                return  # the stream that ended or failed was restarted meanwhile
            self._source_done = True
            self._source_status = status
            self._steps = 0
            self._cond.notify_all()

    # ------------------------------------------------------------------ tracking thread
    def _track_loop(self) -> None:
        published_status: str | None = None
        while True:
            with self._cond:
                while (not self._stop and self._slot is None and not self._ready_commands()
                       and self._source_status == published_status):
                    self._cond.wait()
                if self._stop:
                    return
                item, self._slot = self._slot, None
                commands = self._take_commands()
                status = self._source_status
                self._cond.notify_all()  # a lossless acquisition waits for the slot to empty
            changed = False
            # Commands first: they act on the frame already published (the one the operator
            # clicked on), and the waiting frame then tracks what they added, so a click costs
            # no extra tracking step before it shows.
            for command in commands:
                self._apply(command)
                changed = True
                if isinstance(command, RestartSource) and item is not None:
                    item = None  # a frame of the stream before the restart
                    with self._cond:
                        self._frames_dropped += 1
                        self._old_stream_counted(read=False)
            if commands and self._refresh_targets() and item is not None:
                # The answer to a click (its target on the frame the operator clicked) is shown
                # now, not one tracking step later.
                self._publish()
            if item is not None:
                self._process(*item)
                changed = True
            if status != published_status or changed:
                published_status = status
                self._publish()

    def _refresh_targets(self) -> bool:
        """Take the engine's targets as they stand after the commands (engines that offer
        ``targets``); True when they changed."""
        current = getattr(self.engine, "targets", None)
        if current is None or self._last_frame is None:
            return False
        current = tuple(current)
        if [(t.id, t.status) for t in current] == [(t.id, t.status) for t in self._last_targets]:
            return False
        self._last_targets = current
        return True

    def _ready_commands(self) -> bool:
        if not self._commands:
            return False
        # Engine commands wait for the first frame: they act on the frame the operator saw.
        return self._last_frame is not None or any(_is_pipeline_command(c) for c in self._commands)

    def _take_commands(self) -> list[Command]:
        if self._last_frame is not None:
            taken, self._commands = list(self._commands), collections.deque()
            return taken
        taken = [c for c in self._commands if _is_pipeline_command(c)]
        self._commands = collections.deque(c for c in self._commands if not _is_pipeline_command(c))
        return taken

    def _process(self, frame: StereoFrame, t_read: float) -> None:
        start = time.monotonic()
        try:
            targets, pose, errors = self.engine.process(frame)
            self._last_targets = tuple(targets)
            self._last_pose = pose
            self._last_errors = errors
        except Exception as exc:  # a tracker bug must not stop the console: report and go on
            self.engine_errors += 1
            if isinstance(exc, TrackmeterError):  # input the engine refuses: its message says what
                log.error("tracking failed on frame %d: %s", frame.index, exc)
                reason = f"tracking failed: {exc}"
            else:
                log.exception("tracking failed on frame %d", frame.index)
                reason = f"tracking failed: {type(exc).__name__}: {exc}"
            self._last_pose = PoseEstimate.invalid(reason, self._last_pose.case)
            self._last_errors = None
        done = time.monotonic()
        self._last_frame = frame
        # Counted here, where every cut arrives (a dropped frame's is carried to the next kept
        # one), not from the snapshots a display happens to see; a restart's own cut is none.
        if frame.cut and self._tracked_since_restart > 0:
            self._source_pass += 1
        self._tracked_since_restart += 1
        self._last_step_ms = (done - start) * 1e3
        self._last_latency_ms = (done - t_read) * 1e3
        with self._cond:
            self._frames_processed += 1
            self._trk_rate.tick(done)

    def _apply(self, command: Command) -> None:
        try:
            reply = self._apply_unsafe(command)
            if reply is None:
                return  # answered later, by the thread that finishes it
        except TrackmeterError as exc:
            reply = CommandReply(False, str(exc))
        except Exception as exc:
            log.exception("command %s failed", type(command).__name__)
            reply = CommandReply(False, f"{type(command).__name__} failed: {type(exc).__name__}: {exc}")
        _resolve(command, reply)

    def _apply_unsafe(self, command: Command) -> CommandReply | None:
        if isinstance(command, SetPaused):
            if not command.paused:
                with self._source_lock:
                    # A real-time source's pacing starts over: the pause is no lateness to make
                    # up (it sent the frames "missed" back to back, counted as dropped).
                    self.source.resume()
            with self._cond:
                self._paused = bool(command.paused)
                if not self._paused:
                    self._steps = 0
                    # The rates start over: a window holding the pause read 0.3 Hz after Play.
                    self._acq_rate.reset()
                    self._trk_rate.reset()
                self._cond.notify_all()
            return CommandReply(True, "paused" if command.paused else "playing")
        if isinstance(command, StepOnce):
            with self._cond:
                if not self._paused:
                    return CommandReply(False, "step works while paused")
                if self._source_done:
                    return CommandReply(False, f"source {self._source_status}")
                self._steps += 1
                self._cond.notify_all()
            return CommandReply(True, "stepping one frame")
        if isinstance(command, RestartSource):
            self._source_pass, self._tracked_since_restart = 1, 0
            # One step under both locks: no frame of the restarted stream can be read (nor a
            # waiting old one handed over) between the restart and the state it starts from.
            with self._source_lock:
                self.source.restart()
                with self._cond:
                    # A failed source (a camera unplugged) may fail again: the reply says from what it
                    # restarted, not only "restarted" (the operator read that as fixed).
                    failure = (self._source_status if self._source_done and self._source_status
                               and self._source_status.startswith("source failed") else None)
                    self._source_generation += 1
                    if self._slot is not None:
                        self._frames_dropped += 1  # a frame of the stream before the restart
                    self._counts_at_restart = (self._frames_read, self._frames_dropped)
                    self._slot = None
                    self._source_done = False
                    self._source_status = None
                    self._acq_rate.reset()
                    # Paused, the page would go on showing the frame from before the restart with
                    # its targets, as if nothing had happened: step to the first frame instead.
                    paused = self._paused
                    self._steps = 1 if paused else 0
                    self._cond.notify_all()
            return CommandReply(True, "source restarted" + (f" after '{failure}': it may fail again" if failure else "")
                                + ("; paused at its first frame" if paused else "")
                                + ("; the recording goes on, its time carried on" if self._recording() else ""))
        if isinstance(command, SetRecording):
            if command.directory is None:
                return self._stop_recording_in_background(command)
            self._start_recording(Path(command.directory))
            return CommandReply(True, f"recording to {command.directory}"
                                + ("; paused: frames are recorded as the source plays or steps" if self._paused else ""))
        reply = self.engine.handle(command, self._last_frame)
        if isinstance(command, (ClearTargets, ResetTracking)) and reply.ok:
            # The published pose went with the targets it came from (paused, no step would
            # replace it: the console showed a valid pose beside no target).
            what = "targets cleared" if isinstance(command, ClearTargets) else "tracking reset"
            self._last_pose = PoseEstimate.invalid(what, self._last_pose.case)
            self._last_errors = None
        elif (isinstance(command, _REMOVE_COMMANDS) and reply.ok and self._last_pose.valid
              and (self._paused or self._source_done)
              and any(t.id == reply.target_id and t.status != "lost" for t in self._last_targets)):
            # The same for a removal of a target the pose may have used, when no frame is coming
            # to estimate without it: paused, or the source ended (all four targets removed,
            # "pose valid (4 points)" stayed). (A source that ends while its last read blocks
            # is marked done only after: that pose is left, as a running one would be.)
            ending = _AFTER_THE_END if self._source_done else _BEFORE_TARGETS
            self._last_pose = PoseEstimate.invalid(f"a target removed{ending}", self._last_pose.case)
            self._last_errors = None
        elif (isinstance(command, _TARGET_COMMANDS) and reply.ok and self._paused and not self._last_pose.valid
              and self._last_frame is not None and not (self._last_pose.reason or "").endswith(_BEFORE_TARGETS)):
            # Paused, no frame comes to estimate the pose with the new targets: its reason (e.g.
            # "none is a target yet") would go on contradicting the target list.
            self._last_pose = PoseEstimate.invalid(f"{self._last_pose.reason}{_BEFORE_TARGETS}", self._last_pose.case)
        elif isinstance(command, _CASE_COMMANDS) and reply.ok:
            # The engine dropped the motion of the case it left: so goes the pose of that case.
            case = getattr(self.engine, "case", self._last_pose.case)
            self._last_pose = PoseEstimate.invalid(f"model case ({case}) from the next frame", case)
            self._last_errors = None
        return reply

    def _start_recording(self, directory: Path) -> None:
        with self._record_lock:
            failed = self._recorder is not None and self._recorder.failed
            if self._recorder is not None and not failed:
                raise TrackmeterError(f"already recording to {self._recorder.directory}")
        if failed:
            self._stop_recording()  # a new recording after a failed one: the failed one's stats are kept
        try:
            writer = self._writer_factory(directory)  # raises TrackmeterError on a bad folder
        except OSError as exc:  # no such parent, a file in the way, no permission
            raise TrackmeterError(f"cannot record to {directory}: {exc.strerror or exc}") from None
        except ValueError:  # the OS's calls refuse a NUL character in a path ("embedded null byte")
            raise TrackmeterError(f"cannot record to {quoted_name(str(directory))}: a folder name cannot hold a NUL "
                                  "character") from None
        with self._record_lock:
            self._recorder = _Recorder(directory, writer, self._record_queue_frames)

    def _old_stream_counted(self, read: bool) -> None:
        """A frame of the stream before the last restart, dropped (and read, ``read``) after the
        restart tallied the counters (``Timings.counts_at_restart``): it goes to that tally, so
        the new stream's share dropped holds the new stream's frames only. Under ``_cond``."""
        if self._counts_at_restart is not None:
            frames_read, frames_dropped = self._counts_at_restart
            self._counts_at_restart = (frames_read + int(read), frames_dropped + 1)

    def _stop_recording(self) -> RecordingStats | None:
        """Stop the recording and wait until everything queued is written; its stats (None:
        none was on)."""
        with self._record_lock:
            recorder, self._recorder = self._recorder, None
        return None if recorder is None else self._finish_recording(recorder)

    def _finish_recording(self, recorder: _Recorder) -> RecordingStats:
        try:
            recorder.close()
        finally:  # its stats are the run's, and it is closing no more, whatever closing raised
            stats = recorder.stats(False)
            with self._record_lock:
                if recorder in self._closing:
                    self._closing.remove(recorder)
                self._stopped_recordings.append(stats)
        return stats

    def _stop_recording_in_background(self, command: SetRecording) -> CommandReply | None:
        """The operator's stop: the recorder leaves at once, and a thread of its own writes
        what it queued and answers ``command``. On the tracking thread the wait (a slow disk
        behind a full queue: seconds) froze tracking, the snapshots and every command.
        None: the reply comes from that thread."""
        with self._record_lock:
            recorder, self._recorder = self._recorder, None
            if recorder is None:
                return CommandReply(False, "not recording")
            self._closing.append(recorder)

        def finish() -> None:
            try:
                stats = self._finish_recording(recorder)
                reply = CommandReply(stats.error is None and stats.frames_dropped == 0, stats.summary())
            except Exception as exc:  # the reply must come whatever happens
                log.exception("closing the recording failed")
                reply = CommandReply(False, f"closing the recording failed: {type(exc).__name__}: {exc}")
            _resolve(command, reply)

        thread = threading.Thread(target=finish, name="trackmeter-recorder-close", daemon=True)
        with self._record_lock:
            self._closing_threads = [t for t in self._closing_threads if t.is_alive()] + [thread]
        thread.start()
        return None

    def _publish(self) -> None:
        snapshot = self._make_snapshot()
        with self._snap_cond:
            self._snapshot = snapshot
            self._snap_cond.notify_all()
        for callback in self._subscribers:
            try:
                callback(snapshot)
            except Exception:
                log.exception("snapshot subscriber failed")

    def timings(self) -> Timings:
        """The counters and rates as they stand now: after :meth:`stop`, the run's totals (the
        last published snapshot may lag a frame read but not yet tracked)."""
        with self._cond:
            return self._timings_locked(time.monotonic())

    def _timings_locked(self, now: float) -> Timings:
        return Timings(
            acquisition_hz=self._acq_rate.rate_hz(now),
            tracking_hz=self._trk_rate.rate_hz(now),
            latency_ms=self._last_latency_ms,
            step_ms=self._last_step_ms,
            frames_read=self._frames_read,
            frames_processed=self._frames_processed,
            frames_dropped=self._frames_dropped,
            counts_at_restart=self._counts_at_restart,
        )

    def _make_snapshot(self) -> Snapshot:
        now = time.monotonic()
        with self._cond:
            timings = self._timings_locked(now)
            paused, status = self._paused, self._source_status
        recording = self._recording()
        self._sequence += 1
        engine = self.engine
        return Snapshot(
            frame=self._last_frame,
            targets=self._last_targets,
            pose=self._last_pose,
            errors=self._last_errors,
            timings=timings,
            auto_enabled=bool(getattr(engine, "auto_enabled", False)),
            auto_count=int(getattr(engine, "auto_count", 0)),
            auto_method=str(getattr(engine, "auto_method", "gabor")),
            auto_shortfall=getattr(engine, "auto_shortfall", None),
            filter_cutoff_hz=float(getattr(engine, "filter_cutoff_hz", float("nan"))),
            paused=paused,
            recording=recording,
            source_status=status,
            source_warning=self._source_warning(),
            sequence=self._sequence,
            source_pass=self._source_pass,
            model_ids=tuple(getattr(getattr(engine, "model", None), "ids", ()) or ()),
        )

    def _source_warning(self) -> str | None:
        """The source's ``warning`` (read while the acquisition thread plays it): never the
        reason a snapshot is not published."""
        try:
            warning = getattr(self.source, "warning", None)
        except Exception:
            log.exception("reading the source's warning failed")
            return None
        return str(warning) if warning else None

    def _model_in_use(self) -> Any | None:
        """The engine's a-priori model, else the one the source carries (None without)."""
        model = getattr(self.engine, "model", None)
        return model if model is not None else self.source.model

    # ------------------------------------------------------------------ headless runs
    def run_until_end(self, timeout_s: float | None = None) -> Snapshot:
        """Block until the source ended or failed and its last frame is published.

        Ctrl-C (KeyboardInterrupt) propagates to the caller; call :meth:`close` (or use the
        context manager) so threads are joined and the recording is closed either way.
        """
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        seq = 0
        while True:
            snap = self.wait_snapshot(seq, 0.2)
            if snap is not None:
                seq = snap.sequence
                with self._cond:
                    # Engine commands still waiting for a first frame never run once the
                    # source ended without one: they do not keep the run alive.
                    idle = self._slot is None and not self._ready_commands()
                t = snap.timings
                if snap.source_status is not None and idle and t.frames_processed + t.frames_dropped == t.frames_read:
                    return snap
            if deadline is not None and time.monotonic() > deadline:
                return self.latest()
            if not self.running:
                return self.latest()


_PIPELINE_COMMANDS = (SetPaused, StepOnce, RestartSource, SetRecording)
#: Engine commands that start the motion estimation over in a model case (paper 2.C).
_CASE_COMMANDS = (SetCase, AcquireModel, LoadModel)
#: Commands that add targets, and what an invalid pose's reason says once they did while paused.
_TARGET_COMMANDS = (SelectPoint, SelectModelPoints)
#: Commands that remove targets one at a time.
_REMOVE_COMMANDS = (RemoveTarget, RemoveNearest)
_BEFORE_TARGETS = " (before the targets changed: Step or Play to update)"
_AFTER_THE_END = " (the source has ended: Restart to track again)"


def _is_pipeline_command(command: Command) -> bool:
    return isinstance(command, _PIPELINE_COMMANDS)


def _resolve(command: Command, reply: CommandReply) -> None:
    future = command.reply
    if future is not None and not future.done():
        try:
            future.set_result(reply)
        except Exception:  # cancelled by the caller in between
            pass


def run_headless(
    source: Source,
    engine: EngineLike,
    *,
    on_snapshot: Callable[[Snapshot], bool | None] | None = None,
    commands: Iterable[Command] = (),
    realtime: bool = False,
    rig: StereoRig | None = None,
    record_dir: str | Path | None = None,
    timeout_s: float | None = None,
    on_replies: Callable[[list[CommandReply]], bool] | None = None,
) -> tuple[Snapshot, list[CommandReply]]:
    """Run the pipeline without a console until the source ends (``trackmeter track``).

    Args:
        source: the frames; it is NOT closed here (the caller opened it).
        engine: the tracker.
        on_snapshot: called on the tracking thread with every published snapshot, in order.
            With ``realtime=False`` no frame is dropped, so that is one snapshot per frame
            (plus one per applied command and one at the end with ``source_status``).
            Returning True ends the run there (e.g. its files can no longer be written).
        commands: sent before the first frame; engine commands act on frame 0 after it is
            processed (e.g. ``SelectPoint`` for ``--target``, ``SetAuto`` for ``--auto``).
        realtime: True for live sources (latest frame wins, drops counted).
        record_dir: also record the stream there.
        timeout_s: give up waiting after this long (the snapshot so far is returned).
        on_replies: called once with the replies to ``commands`` (in order) as soon as every
            one has its reply (on the tracking thread, as the commands are applied);
            returning True ends the run there, after at most the frame already waiting (e.g.
            every ``--target`` refused: nothing will ever be tracked).

    Returns:
        The last snapshot and the replies to ``commands`` (in order).

    Ctrl-C stops the threads cleanly (files closed) and re-raises KeyboardInterrupt.
    """
    pipe = Pipeline(source, engine, rig=rig, drop_frames=realtime, record_dir=record_dir)
    if on_snapshot is not None:
        deliver = on_snapshot

        def stop_when_asked(snapshot: Snapshot) -> None:
            if deliver(snapshot):
                pipe.request_stop()

        pipe.subscribe(stop_when_asked)
    futures = [pipe.submit(c) for c in commands]
    if on_replies is not None:
        def stop_when_replied(replies: list[CommandReply]) -> None:
            if on_replies(replies):
                pipe.request_stop()

        _when_all_replied(futures, stop_when_replied)
    pipe.start()
    try:
        last = pipe.run_until_end(timeout_s)
    finally:
        # A Ctrl-C (or a second one) while the threads wind down would leave the tracking
        # thread publishing into files the caller is closing: it waits until they are joined.
        with interrupts_deferred():
            pipe.stop()
    replies = [f.result(0) if f.done() else CommandReply(False, NOT_APPLIED) for f in futures]
    return last, replies


@contextlib.contextmanager
def interrupts_deferred(message: Callable[[], str] | None = None) -> Iterator[None]:
    """Hold the stop signals (SIGINT, SIGTERM, SIGHUP) off while the block runs (threads
    winding down, files being closed) and, when one came, hand it after the block to the handler it found there; a
    KeyboardInterrupt that handler raises (Python's own Ctrl-C handler, or a SIGTERM left at
    its default, which would kill) is raised with ``message()`` as its text.

    Python runs signal handlers between bytecodes of the main thread, so a Ctrl-C landing in
    ``Thread.join`` or half-way through closing a run's files would leave them half-done (a
    run.yaml still "running", a frame published after its file was closed). A handler that
    ignores the signal (the command line's, once the process is already stopping) keeps
    ignoring it. Outside the main thread (where no handler runs) the block simply runs.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []

    def hold(signum: int, frame: object) -> None:
        caught.append(signum)

    # Looked up by the plain number hold was given (caught), hence int keys.
    previous: dict[int, Callable[[int, FrameType | None], Any] | int | None] = {
        sig: signal.signal(sig, hold) for sig in STOP_SIGNALS}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if not caught:
        return
    handler = previous[caught[0]]
    if handler == signal.SIG_IGN:
        return
    try:
        if not callable(handler):  # SIG_DFL (or unknown): stop, as Ctrl-C would
            raise KeyboardInterrupt
        handler(caught[0], None)
    except KeyboardInterrupt:
        raise KeyboardInterrupt(*([message()] if message is not None else [])) from None


def _when_all_replied(futures: list[Future[CommandReply]], callback: Callable[[list[CommandReply]], Any]) -> None:
    """Call ``callback(replies)`` once, on the thread that resolves the last of ``futures``."""
    lock = threading.Lock()
    left = [len(futures)]

    def one_done(_: Future[CommandReply]) -> None:
        with lock:
            left[0] -= 1
            if left[0] != 0:
                return
        callback([f.result() for f in futures])

    if not futures:
        callback([])
    for f in futures:
        f.add_done_callback(one_done)
