"""The pipeline's threads: latest frame wins, commands in order, immutable snapshots, shutdown,
source failures and lossless recording (DESIGN.md section 4).

The engine here is a recording test double (what the tracking thread called, with which
frame); the real engine has its own tests. No timings are asserted: every check is an exact
count or order, made deterministic with events rather than sleeps where order matters.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from trackmeter.core.targets import TargetState
from trackmeter.errors import TrackmeterError
from trackmeter.pipeline.pipeline import Pipeline, run_headless
from trackmeter.pipeline.snapshot import (
    AcquireModel,
    ClearTargets,
    CommandReply,
    LoadModel,
    PoseEstimate,
    RemoveTarget,
    ResetTracking,
    RestartSource,
    SelectPoint,
    SetCase,
    SetPaused,
    SetRecording,
    Snapshot,
    StepOnce,
)
from trackmeter.sources.base import Source, StereoFrame


class CountingSource(Source):
    """Frames 0..n-1 of tiny images whose pixels carry the index; optional failure."""

    def __init__(self, n: int, fail_at: int | None = None, gate: threading.Event | None = None,
                 gate_from: int = 0, delay_s: float = 0.0) -> None:
        self.n = n
        self.delay_s = delay_s
        self.gate_from = gate_from
        self.fail_at = fail_at
        self.gate = gate
        self.i = 0
        self.closed = False
        self.reads = 0

    def read(self) -> StereoFrame | None:
        if self.gate is not None and self.i >= self.gate_from:
            self.gate.wait(5)
        if self.fail_at is not None and self.i == self.fail_at:
            self.fail_at = None  # fails once; a restart brings it back
            raise TrackmeterError("camera unplugged")
        if self.i >= self.n:
            return None
        if self.delay_s:
            time.sleep(self.delay_s)  # a live source's pace
        img = np.full((4, 6), self.i % 256, np.uint8)
        frame = StereoFrame(self.i, self.i / 25.0, img, img.copy(), cut=self._take_cut())
        self.i += 1
        self.reads += 1
        return frame

    def restart(self) -> None:
        self.i = 0
        self._cut = True

    def close(self) -> None:
        self.closed = True


class RecordingEngine:
    """Test double of the tracker: remembers frames and commands; one target per SelectPoint."""

    def __init__(self, block_first: threading.Event | None = None, fail_on: int | None = None,
                 failure: Exception | None = None) -> None:
        self.failure = failure or RuntimeError("boom")
        self.processed: list[int] = []
        self.commands: list[tuple[str, int | None]] = []
        self.block_first = block_first
        self.entered = threading.Event()
        self.fail_on = fail_on
        self.targets: list[TargetState] = []
        self.thread_ids: set[int] = set()

    def handle(self, command, frame):  # type: ignore[no-untyped-def]
        self.thread_ids.add(threading.get_ident())
        self.commands.append((type(command).__name__, None if frame is None else frame.index))
        if isinstance(command, SelectPoint):
            if command.u < 0:
                return CommandReply(False, "outside the image")
            nan2 = np.full(2, np.nan)
            tid = f"t{len(self.targets)}"
            self.targets.append(TargetState(tid, "operator", "tracking", np.array([command.u, command.v]), nan2,
                                            np.zeros(3), np.eye(3), 1.0, nan2, (0, 0, 1, 1)))
            return CommandReply(True, "ok", tid)
        if isinstance(command, (ClearTargets, ResetTracking)):
            self.targets = []
            return CommandReply(True, "cleared")
        return CommandReply(False, "unknown")

    def process(self, frame):  # type: ignore[no-untyped-def]
        self.thread_ids.add(threading.get_ident())
        self.entered.set()
        if self.block_first is not None and not self.processed:
            self.block_first.wait(5)
        if self.fail_on is not None and frame.index == self.fail_on:
            raise self.failure
        self.processed.append(frame.index)
        return list(self.targets), PoseEstimate.invalid("test double"), None


class ListWriter:
    def __init__(self, directory: Path, slow: threading.Event | None = None) -> None:
        self.directory = directory
        self.indices: list[int] = []
        self.closed = False
        self.slow = slow

    def write(self, frame: StereoFrame) -> None:
        if self.slow is not None:
            self.slow.wait(5)
        self.indices.append(frame.index)

    def close(self) -> None:
        self.closed = True


def _wait_for_reads(source: CountingSource, n: int) -> None:
    """Wait (5 s at most) until ``source`` has delivered ``n`` frames; fail if it has not."""
    for _ in range(500):
        if source.reads == n:
            break
        threading.Event().wait(0.01)
    assert source.reads == n


def test_latest_frame_wins_and_every_drop_is_counted() -> None:
    release, go = threading.Event(), threading.Event()
    engine = RecordingEngine(block_first=release)
    source = CountingSource(60, gate=go, gate_from=1)
    with Pipeline(source, engine) as pipe:
        assert engine.entered.wait(5)
        # The tracker is stuck in frame 0 while the source runs to its end: the slot keeps
        # only the newest frame and never blocks the source.
        go.set()
        _wait_for_reads(source, 60)
        release.set()
        snap = pipe.run_until_end(10)
    t = snap.timings
    assert t.frames_read == 60
    assert t.frames_processed + t.frames_dropped == t.frames_read
    assert engine.processed[0] == 0 and engine.processed[-1] == 59  # the newest frame won
    assert engine.processed == [0, 59] and t.frames_dropped == 58
    assert engine.processed == sorted(engine.processed)
    assert snap.source_status == "ended"


class CutSource(CountingSource):
    """CountingSource whose frame ``cut_at`` starts a new pass (``StereoFrame.cut``)."""

    def __init__(self, n: int, cut_at: int, **kwargs) -> None:  # type: ignore[no-untyped-def]
        super().__init__(n, **kwargs)
        self.cut_at = cut_at

    def read(self) -> StereoFrame | None:
        frame = super().read()
        if frame is not None and frame.index == self.cut_at:
            frame = dataclasses.replace(frame, cut=True)
        return frame


def test_a_dropped_frame_that_starts_a_new_pass_hands_its_cut_on() -> None:
    """A looping source's first frame of a new pass may be dropped (latest frame wins): the
    frame tracked after it must still say the stream jumped, or tracking carries on across
    the jump (a pose 'valid' but off by a whole loop)."""
    release, go = threading.Event(), threading.Event()
    engine = RecordingEngine(block_first=release)
    cuts: dict[int, bool] = {}
    original = engine.process

    def process(frame):  # type: ignore[no-untyped-def]
        cuts[frame.index] = frame.cut
        return original(frame)

    engine.process = process  # type: ignore[method-assign]
    source = CutSource(60, cut_at=30, gate=go, gate_from=1)
    with Pipeline(source, engine) as pipe:
        assert engine.entered.wait(5)
        go.set()
        _wait_for_reads(source, 60)
        release.set()
        pipe.run_until_end(10)
    assert engine.processed == [0, 59]
    assert cuts == {0: False, 59: True}


def test_lossless_mode_tracks_every_frame_in_order() -> None:
    engine = RecordingEngine()
    seen: list[int] = []
    snap, _ = run_headless(CountingSource(80), engine,
                           on_snapshot=lambda s: seen.append(s.frame.index) if s.frame is not None else None)
    assert engine.processed == list(range(80))
    assert snap.timings.frames_dropped == 0 and snap.timings.frames_processed == 80
    assert sorted(set(seen)) == list(range(80))


def test_a_source_without_a_single_frame_ends_the_run_with_its_commands_unapplied() -> None:
    # Engine commands wait for the first frame; a source that never delivers one (all images
    # unreadable, an empty video) must still end the headless run, not hang it.
    engine = RecordingEngine()
    start = time.monotonic()
    snap, replies = run_headless(CountingSource(0), engine, commands=[SelectPoint(1.0, 1.0)], timeout_s=30)
    assert time.monotonic() - start < 10
    assert snap.source_status == "ended" and snap.frame is None
    assert [r.ok for r in replies] == [False] and engine.commands == []


def test_commands_applied_in_order_with_replies_on_the_tracking_thread() -> None:
    engine = RecordingEngine()
    source = CountingSource(10**6)
    with Pipeline(source, engine) as pipe:
        futures = [pipe.submit(SelectPoint(float(i), 1.0)) for i in range(20)]
        bad = pipe.submit(SelectPoint(-1.0, 0.0))
        replies = [f.result(5) for f in futures]
        assert [r.target_id for r in replies] == [f"t{i}" for i in range(20)]
        assert all(r.ok for r in replies)
        refused = bad.result(5)
        assert not refused.ok and refused.message == "outside the image"
        # The operator's view: once the reply came, a later snapshot shows the targets.
        snap = pipe.wait_snapshot(pipe.latest().sequence, 5)
        assert snap is not None and [t.id for t in snap.targets][:20] == [f"t{i}" for i in range(20)]
        # Engine commands act on an already processed frame (the one the operator saw).
        frames = [f for name, f in engine.commands if name == "SelectPoint"]
        assert all(f is not None and f in engine.processed for f in frames)
        assert pipe.call(ClearTargets()).ok
    assert len(engine.thread_ids) == 1 and threading.get_ident() not in engine.thread_ids


def test_a_command_is_applied_before_the_waiting_frame_which_then_tracks_it() -> None:
    # The operator clicked on the published frame 0 while frame 1+ waits in the slot: the click
    # acts on frame 0 and the waiting frame already tracks the new target (no extra step).
    release, go = threading.Event(), threading.Event()
    processed_when_applied: list[int] = []

    class Engine(RecordingEngine):
        def handle(self, command, frame):  # type: ignore[no-untyped-def]
            processed_when_applied.extend(self.processed)
            return super().handle(command, frame)

    engine = Engine(block_first=release)
    source = CountingSource(10**6, gate=go, gate_from=1, delay_s=0.002)
    with Pipeline(source, engine) as pipe:
        assert engine.entered.wait(5)
        go.set()
        for _ in range(500):
            if source.reads >= 3:
                break
            threading.Event().wait(0.01)
        future = pipe.submit(SelectPoint(2.0, 1.0))
        release.set()
        reply = future.result(5)
        assert reply.ok
        snap = pipe.wait_snapshot(pipe.latest().sequence, 5)
        while snap is not None and not snap.targets:
            snap = pipe.wait_snapshot(snap.sequence, 5)
    assert engine.commands[0] == ("SelectPoint", 0)
    assert processed_when_applied == [0]  # applied before the waiting frame was processed
    assert snap is not None and snap.frame is not None and snap.frame.index > 0


def test_a_click_is_published_on_the_clicked_frame_before_the_waiting_frame_is_tracked() -> None:
    # The operator's answer (the new target on the frame they clicked) must not wait for the
    # next tracking step: the pipeline publishes it as soon as the command is applied.
    release, go, hold = threading.Event(), threading.Event(), threading.Event()
    in_second = threading.Event()

    class Engine(RecordingEngine):
        def process(self, frame):  # type: ignore[no-untyped-def]
            if frame.index >= 1:
                in_second.set()
                hold.wait(5)
            return super().process(frame)

    engine = Engine(block_first=release)
    source = CountingSource(10**6, gate=go, gate_from=1)
    with Pipeline(source, engine) as pipe:
        assert engine.entered.wait(5)  # frame 0 is being tracked
        go.set()
        for _ in range(500):  # frame 1+ waits in the slot
            if source.reads >= 2:
                break
            threading.Event().wait(0.01)
        future = pipe.submit(SelectPoint(2.0, 1.0))
        release.set()
        assert future.result(5).ok
        assert in_second.wait(5)  # the waiting frame's step has begun and is held
        snap = pipe.latest()
        hold.set()
    assert snap.frame is not None and snap.frame.index == 0
    assert [t.id for t in snap.targets] == ["t0"]
    assert engine.processed[0] == 0


def test_pause_and_step_read_exactly_one_frame() -> None:
    engine = RecordingEngine()
    source = CountingSource(10**6, delay_s=0.002)
    with Pipeline(source, engine, paused=True) as pipe:
        assert pipe.call(StepOnce()).ok
        snap = pipe.wait_snapshot(0, 5)
        while snap is not None and snap.frame is None:
            snap = pipe.wait_snapshot(snap.sequence, 5)
        assert snap is not None and snap.paused and snap.frame is not None and snap.frame.index == 0
        assert pipe.call(StepOnce()).ok
        for _ in range(200):
            if engine.processed == [0, 1]:
                break
            threading.Event().wait(0.01)
        assert engine.processed == [0, 1] and source.reads == 2
        assert pipe.call(SetPaused(False)).ok
        assert not pipe.call(StepOnce()).ok  # stepping only means something while paused
        snap = pipe.wait_snapshot(pipe.latest().sequence, 5)
        assert snap is not None and not snap.paused


def test_an_invalid_pose_s_reason_says_it_predates_targets_added_while_paused() -> None:
    # Paused, the operator bound model points: the target list showed them, while the pose line
    # went on saying "none is a target yet: target them by id" (an outside console probe).
    engine = RecordingEngine()
    with Pipeline(CountingSource(10**6, delay_s=0.002), engine, paused=True) as pipe:
        assert pipe.call(StepOnce()).ok
        while not engine.processed:
            threading.Event().wait(0.01)
        threading.Event().wait(0.1)
        assert pipe.call(SelectPoint(10.0, 20.0)).ok
        assert pipe.call(SelectPoint(30.0, 20.0)).ok  # said once, not once per target
        pipe.wait_snapshot(0, 5)
        reason = pipe.latest().pose.reason
        assert reason == "test double (before the targets changed: Step or Play to update)", reason
        assert not pipe.call(SelectPoint(-1.0, 0.0)).ok  # a refused click changes nothing
        assert pipe.latest().pose.reason == reason


def test_the_rates_after_play_are_not_averaged_with_the_pause() -> None:
    # Ten seconds paused, then Play: the status read "read 0.3 Hz · tracking 0.3 Hz", then 3.3,
    # the pause inside the window of the last 50 frames (an outside console probe).
    engine = RecordingEngine()
    source = CountingSource(10**6, delay_s=0.01)
    with Pipeline(source, engine) as pipe:
        while len(engine.processed) < 5:
            threading.Event().wait(0.01)
        assert pipe.call(SetPaused(True)).ok
        threading.Event().wait(0.3)
        played_at = time.monotonic()
        assert pipe.call(SetPaused(False)).ok
        seen = len(engine.processed)
        while len(engine.processed) < seen + 5:
            threading.Event().wait(0.01)
        # The rates count only frames read and tracked since Play.
        for meter in (pipe._acq_rate, pipe._trk_rate):
            assert len(meter._times) >= 2 and min(meter._times) >= played_at, (played_at, list(meter._times))


def test_every_stepped_frame_is_tracked_even_when_the_steps_come_faster_than_the_tracker() -> None:
    # The operator pressing Step three times asked for three frames: a step's frame waits for the
    # tracker rather than replace one it has not taken (the latest-frame-wins drop is for live play).
    release, camera = threading.Event(), threading.Event()
    engine = RecordingEngine(block_first=release)
    source = CountingSource(10**6, gate=camera)
    with Pipeline(source, engine, paused=True) as pipe:
        for _ in range(3):  # all three steps taken while the camera is still delivering frame 0
            assert pipe.call(StepOnce()).ok
        camera.set()
        assert engine.entered.wait(5)  # a frame in the tracker, which is held there
        _wait_for_reads(source, 3)  # the other two read meanwhile: one in the slot, one waiting
        threading.Event().wait(0.05)
        assert pipe.timings().frames_dropped == 0
        release.set()
        for _ in range(500):
            if len(engine.processed) == 3:
                break
            threading.Event().wait(0.01)
        assert engine.processed == [0, 1, 2]
        assert pipe.timings().frames_dropped == 0


def test_a_restart_while_paused_shows_the_first_frame_and_stays_paused() -> None:
    # The operator pressed Restart on a paused console: the image must not keep showing the
    # frame from before the restart (with its targets) as if nothing had happened.
    engine = RecordingEngine()
    source = CountingSource(10**6, delay_s=0.002)
    with Pipeline(source, engine, paused=True) as pipe:
        for _ in range(3):
            assert pipe.call(StepOnce()).ok
        _wait_for_reads(source, 3)
        assert pipe.timings().counts_at_restart is None
        reply = pipe.call(RestartSource())
        assert reply.ok and "first frame" in reply.message, reply.message
        t = pipe.timings()  # the new stream's frames are counted from here (the console's share dropped)
        assert t.counts_at_restart is not None and 3 <= t.counts_at_restart[0] <= t.frames_read
        assert t.counts_at_restart[1] == t.frames_dropped
        _wait_for_reads(source, 4)
        snap = pipe.latest()
        for _ in range(500):
            if snap.frame is not None and snap.frame.index == 0 and engine.processed[-1:] == [0]:
                break
            snap = pipe.wait_snapshot(snap.sequence, 0.01) or pipe.latest()
        assert snap.paused and snap.frame is not None and snap.frame.index == 0
        threading.Event().wait(0.1)
        assert source.reads == 4 and engine.processed == [0, 1, 2, 0]  # still paused: nothing more read


def test_snapshots_are_immutable_and_never_change_after_publishing() -> None:
    engine = RecordingEngine()
    with Pipeline(CountingSource(10**6), engine) as pipe:
        assert pipe.call(SelectPoint(1.0, 2.0)).ok
        first = pipe.wait_snapshot(0, 5)
        while first is not None and not first.targets:
            first = pipe.wait_snapshot(first.sequence, 5)
        assert first is not None
        seq, n_targets, frame = first.sequence, len(first.targets), first.frame
        with pytest.raises(dataclasses.FrozenInstanceError):
            first.sequence = 0  # type: ignore[misc]
        with pytest.raises(dataclasses.FrozenInstanceError):
            first.timings.frames_read = 0  # type: ignore[misc]
        assert isinstance(first.targets, tuple)
        assert pipe.call(SelectPoint(3.0, 4.0)).ok
        later = pipe.wait_snapshot(seq + 3, 5)
        assert later is not None and later is not first
    assert first.sequence == seq and len(first.targets) == n_targets and first.frame is frame


def test_stop_joins_threads_resolves_pending_commands_and_closes_source() -> None:
    gate = threading.Event()
    source = CountingSource(10, gate=gate)  # the source hangs until the gate opens
    pipe = Pipeline(source, RecordingEngine()).start()
    pending = pipe.submit(ClearTargets())  # no frame ever arrives, so it waits
    gate.set()
    pipe.close()
    assert not pipe.running
    assert pending.done()
    assert source.closed
    assert not any(t.name.startswith("trackmeter-") for t in threading.enumerate())
    late = pipe.submit(ClearTargets()).result(1)
    assert not late.ok and "stopped" in late.message


def test_source_failure_is_reported_not_raised_and_restart_recovers() -> None:
    engine = RecordingEngine()
    source = CountingSource(30, fail_at=12)
    with Pipeline(source, engine) as pipe:
        snap = pipe.run_until_end(10)
        assert snap.source_status == "source failed: camera unplugged"
        assert pipe.running and snap.timings.frames_read == 12
        reply = pipe.call(RestartSource())
        assert reply.ok and reply.message == "source restarted after 'source failed: camera unplugged': it may fail again"
        snap = pipe.run_until_end(10)
        assert snap.source_status == "ended" and snap.timings.frames_read == 12 + 30
        assert pipe.call(RestartSource()).message == "source restarted"  # it ended, it did not fail


def test_tracker_exception_marks_the_pose_invalid_and_tracking_goes_on() -> None:
    engine = RecordingEngine(fail_on=5)
    snaps = []
    last, _ = run_headless(CountingSource(20), engine, on_snapshot=snaps.append)
    failed = [s for s in snaps if s.frame is not None and s.frame.index == 5]
    assert failed and "tracking failed: RuntimeError: boom" in (failed[0].pose.reason or "")
    assert engine.processed == [i for i in range(20) if i != 5]
    assert last.timings.frames_processed == 20


def test_input_the_tracker_refuses_is_said_in_one_line_not_a_traceback(caplog: pytest.LogCaptureFixture) -> None:
    """A frame the engine refuses as bad input (TrackmeterError: a video frame of another size
    than the rig's) printed a whole traceback, once per frame; its message says what is wrong.
    Another exception is a bug and keeps its traceback."""
    caplog.set_level(logging.ERROR, logger="trackmeter.pipeline.pipeline")
    engine = RecordingEngine(fail_on=3, failure=TrackmeterError("left image is 726x512 px but the rig expects 640x480"))
    snaps: list[Snapshot] = []
    run_headless(CountingSource(6), engine, on_snapshot=snaps.append)
    failed = [s for s in snaps if s.frame is not None and s.frame.index == 3]
    assert failed and failed[0].pose.reason == "tracking failed: left image is 726x512 px but the rig expects 640x480"
    records = [r for r in caplog.records if "tracking failed" in r.getMessage()]
    assert [r.getMessage() for r in records] == [
        "tracking failed on frame 3: left image is 726x512 px but the rig expects 640x480"]
    assert records[0].exc_info is None
    caplog.clear()
    run_headless(CountingSource(6), RecordingEngine(fail_on=3), on_snapshot=None)
    assert [r.exc_info is not None for r in caplog.records if "tracking failed" in r.getMessage()] == [True]


@pytest.mark.parametrize("drop_frames", [True, False])
def test_recording_loses_no_frame(tmp_path: Path, drop_frames: bool) -> None:
    release = threading.Event()
    writers: list[ListWriter] = []

    def factory(directory: Path) -> ListWriter:
        writers.append(ListWriter(directory))
        return writers[-1]

    # A slow tracker drops frames from tracking, never from the recording.
    engine = RecordingEngine(block_first=release)
    pipe = Pipeline(CountingSource(150), engine, drop_frames=drop_frames, record_dir=tmp_path / "rec",
                    writer_factory=factory)
    with pipe:
        assert engine.entered.wait(5)
        release.set()
        snap = pipe.run_until_end(20)
        assert snap.recording
    stats = pipe.recording_stats()
    assert writers[0].closed and not stats.active
    assert writers[0].indices == list(range(150))
    assert stats.frames_written == snap.timings.frames_read == 150 and stats.frames_dropped == 0


def test_recording_that_cannot_keep_up_counts_what_it_could_not_keep(tmp_path: Path) -> None:
    slow = threading.Event()
    writer = ListWriter(tmp_path, slow=slow)
    pipe = Pipeline(CountingSource(40), RecordingEngine(), writer_factory=lambda d: writer, record_queue_frames=5,
                    record_dir=tmp_path / "rec")
    with pipe:
        snap = pipe.run_until_end(10)
        slow.set()
        reply = pipe.call(SetRecording(None))
    stats = pipe.recording_stats()
    assert stats.frames_written + stats.frames_dropped == snap.timings.frames_read == 40
    assert stats.frames_dropped > 0 and not reply.ok and "NOT recorded" in reply.message
    assert writer.indices == sorted(writer.indices)


def test_a_cut_the_recorder_could_not_keep_marks_the_next_frame_it_keeps(tmp_path: Path) -> None:
    # The frame that starts a new pass, dropped by a recorder behind the stream (its queue
    # full), takes its cut with it: the jump is still between the frames kept.
    from trackmeter.pipeline.pipeline import _Recorder

    gate = threading.Event()
    writer = ListWriter(tmp_path, slow=gate)
    writer.cuts = []  # type: ignore[attr-defined]
    original = writer.write

    def write(frame: StereoFrame) -> None:
        original(frame)
        writer.cuts.append(frame.cut)  # type: ignore[attr-defined]

    writer.write = write  # type: ignore[method-assign]
    recorder = _Recorder(tmp_path, writer, max_frames=1)
    img = np.zeros((4, 6), np.uint8)
    frames = [StereoFrame(i, i / 25.0, img, img, cut=(i == 2)) for i in range(4)]
    recorder.offer(frames[0])
    for _ in range(500):  # the thread has taken frame 0 and waits in the writer
        if recorder._queue.empty():
            break
        time.sleep(0.01)
    recorder.offer(frames[1])  # queued
    recorder.offer(frames[2])  # the queue is full: dropped, with its cut
    gate.set()
    for _ in range(500):
        if len(writer.indices) == 2:
            break
        time.sleep(0.01)
    recorder.offer(frames[3])
    recorder.close()
    assert writer.indices == [0, 1, 3] and recorder.frames_dropped == 1
    assert writer.cuts == [False, False, True]  # type: ignore[attr-defined]


def test_recording_toggled_by_command(tmp_path: Path) -> None:
    writers: list[ListWriter] = []
    pipe = Pipeline(CountingSource(10**6, delay_s=0.002), RecordingEngine(), writer_factory=lambda d: writers.append(ListWriter(d)) or writers[-1])
    with pipe:
        assert pipe.call(SetRecording(str(tmp_path / "a"))).ok
        assert not pipe.call(SetRecording(str(tmp_path / "b"))).ok  # one recording at a time
        snap = pipe.wait_snapshot(pipe.latest().sequence + 5, 5)
        assert snap is not None and snap.recording
        reply = pipe.call(SetRecording(None))
        assert reply.ok, reply.message
    assert len(writers) == 1 and writers[0].closed and len(writers[0].indices) == pipe.recording_stats().frames_written > 0


def test_recording_with_the_sequence_writer_reads_back_every_frame(tmp_path: Path, estec_rig) -> None:  # type: ignore[no-untyped-def]
    from trackmeter.data.sequence import index_sequence

    pipe = Pipeline(CountingSource(50), RecordingEngine(), rig=estec_rig, record_dir=tmp_path / "rec")
    with pipe:
        snap = pipe.run_until_end(20)
    stats = pipe.recording_stats()
    index = index_sequence(tmp_path / "rec")
    assert len(index) == stats.frames_written == snap.timings.frames_read == 50
    # A folder that already holds a sequence is refused, with the reason, and nothing starts.
    with Pipeline(CountingSource(10**6, delay_s=0.002), RecordingEngine()) as pipe2:
        reply = pipe2.call(SetRecording(str(tmp_path / "rec")))
        assert not reply.ok and "already holds a sequence" in reply.message
        assert not pipe2.latest().recording


def test_a_recording_that_got_no_frame_leaves_no_folder_and_says_so(tmp_path: Path, estec_rig) -> None:  # type: ignore[no-untyped-def]
    """Recording ticked and unticked while paused wrote a folder with the csv headers only,
    which track refuses ("lists no image"), after "recording to ..." and "recorded 0 frames"
    (an outside monkey probe: six such folders). The start says that frames come as the source
    plays; the stop keeps nothing and says so. (The source here gives no frame at all: a frame
    read just before the pause may be recorded, and is then kept.)"""
    for folder, made_by_operator in ((tmp_path / "rec", False), (tmp_path / "mine", True)):
        if made_by_operator:
            folder.mkdir()  # empty: what the recording made goes, the folder stays
        gate = threading.Event()
        with Pipeline(CountingSource(10, gate=gate), RecordingEngine(), rig=estec_rig) as pipe:
            assert pipe.call(SetPaused(True)).ok
            started = pipe.call(SetRecording(str(folder)))
            assert started.ok and "paused" in started.message, started.message
            assert (folder / "cam0").is_dir()  # claimed while it records
            stopped = pipe.call(SetRecording(None))
            assert stopped.ok and "no frame" in stopped.message and "nothing kept" in stopped.message, stopped.message
            assert pipe.recording_stats().discarded
            gate.set()
        if made_by_operator:
            assert list(folder.iterdir()) == []
        else:
            assert not folder.exists()


def test_a_recording_carries_the_model_the_run_uses(tmp_path: Path, estec_rig) -> None:  # type: ignore[no-untyped-def]
    """Replayed with --source DIR, case (b) must find the model the live run had: the recording
    writes the source's model (or the engine's a-priori one) to model.yaml."""
    from trackmeter.data.model import Model
    from trackmeter.data.sequence import index_sequence

    model = Model(("c0", "c1", "c2"), np.array([[0.0, 0.0, 0.0], [0.4, 0.0, 0.0], [0.0, 0.3, 0.1]]))
    source = CountingSource(5)
    source.model = model  # type: ignore[attr-defined]
    with Pipeline(source, RecordingEngine(), rig=estec_rig, record_dir=tmp_path / "rec") as pipe:
        pipe.run_until_end(20)
    index = index_sequence(tmp_path / "rec")
    assert index.model is not None
    assert index.model.ids == model.ids
    assert np.array_equal(index.model.points_body, model.points_body)


def test_a_restart_while_recording_records_on_with_time_continued(tmp_path: Path, estec_rig) -> None:  # type: ignore[no-untyped-def]
    """The source restarted (its time from 0 again) must not end the recording: the frames after
    it are recorded too, their time carried on past the last one (as a looping source's is),
    so the folder plays back whole."""
    from trackmeter.data.sequence import index_sequence

    pipe = Pipeline(CountingSource(30), RecordingEngine(), rig=estec_rig, record_dir=tmp_path / "rec")
    with pipe:
        pipe.run_until_end(20)
        reply = pipe.call(RestartSource())
        assert reply.ok and "recording" in reply.message
        pipe.run_until_end(20)
        stopped = pipe.call(SetRecording(None))
    stats = pipe.recording_stats()
    assert stopped.ok and stats.error is None and stats.frames_dropped == 0, stopped.message
    index = index_sequence(tmp_path / "rec")
    assert len(index) == stats.frames_written == 60
    dt = np.diff(index.t_s)
    assert np.all(dt > 0) and np.allclose(dt, 0.04, atol=1e-6)
    # and the jump is marked where it is (cuts.csv), so a replay starts over there as the live
    # run did (unmarked, the replay tracked across it as motion; an outside console probe)
    assert index.cuts == (30,)


@pytest.mark.parametrize("where", ["/proc/no-such-dir/rec", "file"])
def test_a_recording_folder_that_cannot_be_made_is_one_line_not_a_traceback(tmp_path: Path, estec_rig, caplog,
                                                                           where: str) -> None:  # type: ignore[no-untyped-def]
    (tmp_path / "file").write_text("x")
    target = where if where.startswith("/") else str(tmp_path / "file" / "rec")
    with Pipeline(CountingSource(10**6, delay_s=0.002), RecordingEngine(), rig=estec_rig) as pipe:
        reply = pipe.call(SetRecording(target))
        assert not pipe.latest().recording
    assert not reply.ok and reply.message.startswith(f"cannot record to {target}:"), reply.message
    assert not [r for r in caplog.records if r.exc_info], "a traceback was logged"


def test_a_recording_that_fails_stops_and_says_why(tmp_path: Path) -> None:
    """A writer failing (disk full) ends the recording: the snapshots stop saying 'recording'
    (the console's REC mark and checkbox follow them), the folder is closed with what was
    written, and the stats keep the reason."""

    class FailingWriter(ListWriter):
        def write(self, frame: StereoFrame) -> None:
            if len(self.indices) == 4:
                raise OSError(28, "No space left on device")
            super().write(frame)

    writers: list[FailingWriter] = []
    # A paced source: the failure (early) comes well before the last frame's snapshot.
    pipe = Pipeline(CountingSource(100, delay_s=0.005), RecordingEngine(), record_dir=tmp_path / "rec",
                    writer_factory=lambda d: writers.append(FailingWriter(d)) or writers[-1])
    with pipe:
        snap = pipe.run_until_end(20)
    stats = pipe.recording_stats()
    assert not snap.recording and not stats.active
    assert writers[0].closed and stats.frames_written == 4 and "No space left" in (stats.error or "")


def test_the_totals_after_a_live_run_is_stopped_count_every_frame_read(tmp_path: Path) -> None:
    """Stopped mid-stream (Ctrl-C on the console), the last published snapshot may lag the
    frame the acquisition read last, which the recording holds: ``timings()`` has the totals."""
    writers: list[ListWriter] = []
    pipe = Pipeline(CountingSource(10**6, delay_s=0.002), RecordingEngine(), record_dir=tmp_path / "rec",
                    writer_factory=lambda d: writers.append(ListWriter(d)) or writers[-1])
    with pipe:
        time.sleep(0.5)
    stats = pipe.recording_stats()
    assert stats.frames_dropped == 0 and pipe.timings().frames_read == stats.frames_written == len(writers[0].indices)


def test_a_writer_failing_while_the_queue_is_full_neither_hangs_the_stop_nor_loses_a_count(tmp_path: Path) -> None:
    """The stop (Ctrl-C, the Record box) waits for the recorder; a write failing while frames
    wait in a full queue must not leave that wait hanging, and every frame offered is either
    written or counted (the failed one and those queued behind it as lost to the failure)."""
    from trackmeter.pipeline.pipeline import _Recorder

    go = threading.Event()

    class StuckThenFull:
        def write(self, frame: StereoFrame) -> None:
            go.wait(5)
            raise OSError(28, "No space left on device")

        def close(self) -> None:
            pass

    recorder = _Recorder(tmp_path / "rec", StuckThenFull(), max_frames=2)  # type: ignore[arg-type]
    img = np.zeros((4, 6), np.uint8)
    recorder.offer(StereoFrame(0, 0.0, img, img))
    time.sleep(0.1)  # the writer holds frame 0
    for i in range(1, 5):
        recorder.offer(StereoFrame(i, 0.04 * i, img, img))  # 1, 2 queued; 3, 4 dropped (queue full)
    closing = threading.Thread(target=recorder.close, daemon=True)
    closing.start()
    time.sleep(0.2)
    go.set()
    closing.join(5)
    assert not closing.is_alive(), "close() hangs"
    stats = recorder.stats(False)
    assert stats.frames_written == 0 and stats.frames_dropped == 2 and stats.frames_lost == 3
    assert "No space left" in (stats.error or "")


class _ValidPoseEngine(RecordingEngine):
    """Publishes a valid case-(b) pose every frame, and removes targets by id."""

    def handle(self, command, frame):  # type: ignore[no-untyped-def]
        if isinstance(command, RemoveTarget):
            self.targets = [t for t in self.targets if t.id != command.target_id]
            return CommandReply(True, f"removed {command.target_id}", command.target_id)
        return super().handle(command, frame)

    def process(self, frame):  # type: ignore[no-untyped-def]
        targets, _, errors = super().process(frame)
        T = np.eye(4)
        T[2, 3] = 3.5
        return targets, PoseEstimate(True, None, "b", T, np.eye(6) * 1e-6, np.zeros(3), np.zeros(3), 3), errors


def _first_valid_pose(pipe: Pipeline) -> Snapshot:
    assert pipe.call(StepOnce()).ok  # a first frame for the click
    snap = pipe.wait_snapshot(0, 5)
    while snap is not None and not (snap.frame is not None and snap.pose.valid):
        snap = pipe.wait_snapshot(snap.sequence, 5)
    assert snap is not None and snap.pose.valid
    return snap


def _await_no_pose(pipe: Pipeline, n_targets: int) -> Snapshot:
    snap = pipe.latest()
    deadline = time.monotonic() + 5
    while len(snap.targets) != n_targets or snap.pose.valid:
        assert time.monotonic() < deadline, (len(snap.targets), snap.pose)
        snap = pipe.wait_snapshot(snap.sequence, 1) or pipe.latest()
    return snap


def test_removing_a_target_while_paused_leaves_no_pose_shown() -> None:
    # Paused, every target shift-clicked away: the page showed "targets: 0 tracking, 0 lost"
    # beside "pose valid (case a, 4 points)" (an outside probe). A removal with no frame coming
    # takes the pose it came from, as Clear does; playing, the next frame's pose replaces it.
    engine = _ValidPoseEngine()
    with Pipeline(CountingSource(10**6, delay_s=0.002), engine, paused=True) as pipe:
        _first_valid_pose(pipe)
        assert pipe.call(SelectPoint(1.0, 2.0)).ok and pipe.call(SelectPoint(3.0, 4.0)).ok
        assert pipe.latest().pose.valid  # adding targets leaves a valid pose as it is
        assert pipe.call(RemoveTarget("t0")).ok
        snap = _await_no_pose(pipe, 1)
        assert "a target removed" in (snap.pose.reason or "") and snap.pose.case == "b"
        assert engine.processed == [0]  # no step taken meanwhile: the pose went with the removal


def test_removing_a_lost_target_while_paused_keeps_the_pose_and_after_the_end_says_restart() -> None:
    # A lost target is in no pose: removing it leaves the pose (an outside review). After the
    # source's end Step is refused, so the reason does not advise it.
    engine = _ValidPoseEngine()
    with Pipeline(CountingSource(10**6, delay_s=0.002), engine, paused=True) as pipe:
        _first_valid_pose(pipe)
        assert pipe.call(SelectPoint(1.0, 2.0)).ok
        engine.targets[0] = dataclasses.replace(engine.targets[0], status="lost")
        assert pipe.call(SelectPoint(3.0, 4.0)).ok  # the pipeline takes the targets as they stand
        assert pipe.call(RemoveTarget("t0")).ok
        assert pipe.latest().pose.valid
    engine = _ValidPoseEngine()
    with Pipeline(CountingSource(5), engine) as pipe:
        pipe.call(SelectPoint(1.0, 2.0))
        snap = pipe.run_until_end(10)
        assert snap.source_status == "ended" and snap.pose.valid and snap.targets
        assert pipe.call(RemoveTarget(snap.targets[0].id)).ok
        snap = _await_no_pose(pipe, len(snap.targets) - 1)
        assert snap.pose.reason == "a target removed (the source has ended: Restart to track again)", snap.pose.reason


@pytest.mark.parametrize("command, reason", [(ClearTargets(), "targets cleared"), (ResetTracking(), "tracking reset")])
def test_clearing_the_targets_while_paused_leaves_no_pose_shown(command, reason) -> None:  # type: ignore[no-untyped-def]
    # The console showed "targets: 0 tracking" beside "pose valid (case b, 14 points)" until
    # the next step: the published pose must not outlive the targets it came from.
    engine = _ValidPoseEngine()
    with Pipeline(CountingSource(10**6, delay_s=0.002), engine, paused=True) as pipe:
        _first_valid_pose(pipe)
        assert pipe.call(SelectPoint(1.0, 2.0)).ok
        assert pipe.call(command).ok
        snap = _await_no_pose(pipe, 0)
        assert reason in (snap.pose.reason or "") and snap.pose.case == "b"
        assert engine.processed == [0]  # no step taken meanwhile: the pose went with the clearing


@pytest.mark.parametrize("command", [SetCase("a"), AcquireModel(), LoadModel("model.yaml")])
def test_changing_the_model_case_while_paused_leaves_no_old_pose_shown(command) -> None:  # type: ignore[no-untyped-def]
    # The console kept "pose valid (case b)" after the operator chose case (a) until the next
    # step: the engine has dropped that motion, so the published pose must not outlive it.
    class CaseEngine(RecordingEngine):
        case = "b"

        def handle(self, command, frame):  # type: ignore[no-untyped-def]
            self.commands.append((type(command).__name__, None if frame is None else frame.index))
            self.case = {"SetCase": getattr(command, "case", None), "AcquireModel": "c", "LoadModel": "b"}[type(command).__name__]
            return CommandReply(True, f"model case ({self.case})")

        def process(self, frame):  # type: ignore[no-untyped-def]
            targets, _, errors = super().process(frame)
            T = np.eye(4)
            T[2, 3] = 3.5
            return targets, PoseEstimate(True, None, self.case, T, np.eye(6) * 1e-6, np.zeros(3), np.zeros(3), 3), errors

    engine = CaseEngine()
    with Pipeline(CountingSource(10**6, delay_s=0.002), engine, paused=True) as pipe:
        assert pipe.call(StepOnce()).ok
        snap = pipe.wait_snapshot(0, 5)
        while snap is not None and not (snap.frame is not None and snap.pose.valid):
            snap = pipe.wait_snapshot(snap.sequence, 5)
        assert snap is not None and snap.pose.valid and snap.pose.case == "b"
        assert pipe.call(command).ok
        snap = pipe.latest()
        deadline = time.monotonic() + 5
        while snap.pose.valid:
            assert time.monotonic() < deadline, snap.pose
            snap = pipe.wait_snapshot(snap.sequence, 1) or pipe.latest()
        assert snap.pose.case == engine.case and f"model case ({engine.case})" in (snap.pose.reason or "")
        assert engine.processed == [0]


def test_an_interrupt_while_winding_down_waits_for_the_block_to_finish() -> None:
    """Ctrl-C or SIGTERM inside the block (threads joining, files closing) is held and raised
    after it, with the message; the handlers are given back; without one the block is silent."""
    import os
    import signal

    from trackmeter.pipeline.pipeline import interrupts_deferred

    inherited = (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM))
    try:
        # The handlers of a command started at a terminal. A process started in the
        # background by a shell without job control (CI under nohup ... &, say) inherits
        # SIGINT ignored, and then the block rightly ends quietly (checked below with SIGTERM).
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        before = (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM))
        finished = []
        with pytest.raises(KeyboardInterrupt, match="files are complete"):
            with interrupts_deferred(lambda: "files are complete"):
                os.kill(os.getpid(), signal.SIGINT)
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)  # the handlers run here, in the main thread
                finished.append(True)
        assert finished == [True]
        assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
        with interrupts_deferred():
            pass
        with pytest.raises(ValueError):  # the block's own error goes through unchanged
            with interrupts_deferred():
                raise ValueError("x")
        assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
        # A process already stopping only notes a later signal: the block's then ends quietly,
        # handed to that handler, not raised.
        noted: list[int] = []
        signal.signal(signal.SIGTERM, lambda signum, frame: noted.append(signum))
        with interrupts_deferred(lambda: "never said"):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
        assert noted == [signal.SIGTERM]
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        with interrupts_deferred(lambda: "never said"):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
    finally:
        signal.signal(signal.SIGINT, inherited[0])
        signal.signal(signal.SIGTERM, inherited[1])


def test_a_frame_read_before_a_restart_never_reaches_the_tracker_after_it(tmp_path: Path) -> None:
    # The acquisition thread had read frame 3 when the Restart was applied: that frame is of the
    # stream before the restart and must not be tracked after it (it would be tracked as the
    # restarted stream's first frame, and the real first frame then taken for a jump back).
    engine = RecordingEngine()
    source = CountingSource(10**6, delay_s=0.002)
    with Pipeline(source, engine, paused=True, writer_factory=ListWriter) as pipe:
        for k in range(3):
            assert pipe.call(StepOnce()).ok
            # Each frame tracked before the next is read: a live pipeline drops a frame the
            # tracker has not taken yet (under load, frame 0 went so and the test failed).
            for _ in range(500):
                if len(engine.processed) > k:
                    break
                threading.Event().wait(0.01)
        _wait_for_reads(source, 3)
        assert pipe.call(SetRecording(tmp_path / "rec")).ok
        recorder = pipe._recorder
        assert recorder is not None
        offer = recorder.offer
        restarted: list[Any] = []

        def offer_then_restart(frame: StereoFrame) -> None:
            # Between the read and the hand-over to the tracker: the operator's Restart lands.
            # (Its reply, which asks whether the recording goes on, waits for this offer: the
            # recorder's lock is held here.)
            if frame.index == 3 and not restarted:
                generation = pipe._source_generation
                restarted.append(pipe.submit(RestartSource()))
                for _ in range(500):
                    if pipe._source_generation > generation:
                        break
                    threading.Event().wait(0.01)
            offer(frame)

        recorder.offer = offer_then_restart  # type: ignore[method-assign]
        assert pipe.call(StepOnce()).ok
        _wait_for_reads(source, 5)  # frame 3, then the restarted stream's frame 0
        for _ in range(500):
            if engine.processed[-1:] == [0] and len(engine.processed) > 3:
                break
            threading.Event().wait(0.01)
        assert restarted and restarted[0].result(5).ok, restarted
        assert engine.processed == [0, 1, 2, 0], engine.processed
        snap = pipe.latest()
        assert snap.timings.frames_read == 5
        # Not tracked, so counted as dropped; the recording kept it (it was read).
        assert snap.timings.frames_dropped == 1


def test_a_lossless_pipeline_drops_the_frames_read_before_a_restart_too() -> None:
    # Lossless (run_headless, track): the acquisition thread waits for the slot with frame 2 in
    # hand while the tracker, busy on frame 0, has frame 1 waiting and a Restart queued. Neither
    # old frame may be tracked after the restart (code review: frame 2 was, 10 runs in 10).
    gate = threading.Event()
    engine = RecordingEngine(block_first=gate)
    source = CountingSource(5)
    with Pipeline(source, engine, drop_frames=False) as pipe:
        assert engine.entered.wait(5)
        _wait_for_reads(source, 3)  # frame 1 in the slot, frame 2 waiting for it
        threading.Event().wait(0.05)
        restart = pipe.submit(RestartSource())
        gate.set()
        assert restart.result(5).ok
        snap = pipe.run_until_end(10)
    assert engine.processed == [0, 0, 1, 2, 3, 4], engine.processed
    t = snap.timings
    assert t.frames_read == 8 and t.frames_processed == 6 and t.frames_dropped == 2, t


def test_in_lossless_mode_no_frame_of_the_new_stream_counts_as_dropped_after_a_restart() -> None:
    """Frames of the stream before a restart, dropped after the restart tallied the counters
    (the one the tracking thread held, one the acquisition read just before), belong to that
    tally: lossless, the new stream drops nothing (a code review found 1-2 in 17 of 20)."""
    for _ in range(10):
        engine = RecordingEngine()
        source = CountingSource(10**6, delay_s=0.002)
        with Pipeline(source, engine, drop_frames=False) as pipe:
            while source.reads < 5:
                threading.Event().wait(0.002)
            assert pipe.call(RestartSource()).ok
            read_then = source.reads
            while source.reads < read_then + 5:
                threading.Event().wait(0.002)
            t = pipe.timings()
            assert t.counts_at_restart is not None
            assert t.frames_dropped - t.counts_at_restart[1] == 0, (t, source.reads)


def test_every_recording_of_a_run_is_kept_for_its_summary(tmp_path: Path) -> None:
    # The console's exit line named only the last recording (an outside console probe: three
    # made from the panel and the command line, one named).
    writers: list[ListWriter] = []
    pipe = Pipeline(CountingSource(10**6, delay_s=0.002), RecordingEngine(), writer_factory=lambda d: writers.append(ListWriter(d)) or writers[-1])
    with pipe:
        for name in ("a", "b"):
            assert pipe.call(SetRecording(str(tmp_path / name))).ok
            pipe.wait_snapshot(pipe.latest().sequence + 3, 5)
            assert pipe.call(SetRecording(None)).ok
        assert pipe.call(SetRecording(str(tmp_path / "c"))).ok
        pipe.wait_snapshot(pipe.latest().sequence + 3, 5)
        made = pipe.recordings()
        assert [Path(r.directory).name for r in made] == ["a", "b", "c"] and [r.active for r in made] == [False, False, True]
    made = pipe.recordings()
    assert [r.frames_written for r in made] == [len(w.indices) for w in writers] and all(r.frames_written for r in made)
    assert not any(r.active for r in made)


class LoopingSource(CountingSource):
    """``CountingSource`` played in passes of ``period`` frames, each new pass's first frame cut."""

    def __init__(self, period: int, **kw) -> None:  # type: ignore[no-untyped-def]
        super().__init__(10**6, **kw)
        self.period = period

    def read(self) -> StereoFrame | None:
        frame = super().read()
        if frame is not None and frame.index % self.period == 0 and frame.index > 0:
            frame = dataclasses.replace(frame, cut=True)
        return frame


def test_a_looping_source_s_passes_are_counted_from_every_frame_and_a_restart_starts_over() -> None:
    # The console counted passes from the frames it happened to publish: at 25 Hz it missed
    # most loops (pass 11 where it was 20), and took a loop for the Restart's own cut.
    pipe = Pipeline(LoopingSource(10, delay_s=0.002), RecordingEngine(), drop_frames=True)
    with pipe:
        deadline = time.monotonic() + 10
        while pipe.latest().frame is None or pipe.latest().frame.index < 95:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        snap = pipe.latest()
        assert snap.source_pass == snap.frame.index // 10 + 1, (snap.source_pass, snap.frame.index)
        assert pipe.call(RestartSource()).ok
        while pipe.latest().frame.index > 50 or pipe.latest().frame.index < 5:
            assert time.monotonic() < deadline
            time.sleep(0.005)
        assert pipe.latest().source_pass == 1  # the restart's first frame is no new pass
        while pipe.latest().frame.index < 15:
            time.sleep(0.005)
        assert pipe.latest().source_pass == 2


def test_a_recording_of_a_sequence_keeps_its_nanosecond_stamps(tmp_path: Path, estec_rig) -> None:  # type: ignore[no-untyped-def]
    """EuRoC's stamps (~1.4e18 ns) are 238 ns apart as float seconds: a recording that wrote
    ``round(t_s * 1e9)`` changed them by up to 128 ns (an outside probe: 1403636579813555584 was
    recorded as ...712), so its frames no longer joined their ground truth by stamp."""
    from trackmeter.data.sequence import SequenceWriter, index_sequence
    from trackmeter.sources import open_source

    stamps = [1403636579813555584 + k * 50_000_000 + k % 3 for k in range(6)]
    image = np.random.default_rng(0).integers(0, 255, estec_rig.image_size[::-1], dtype=np.uint8)
    with SequenceWriter(tmp_path / "euroc", estec_rig) as writer:
        for k, ns in enumerate(stamps):
            writer.write(StereoFrame(k, ns / 1e9, image, image, stamp_ns=ns))
    assert [int(line.split(",")[0]) for line in (tmp_path / "euroc" / "cam0" / "data.csv").read_text().splitlines()[1:]] == stamps
    with Pipeline(open_source(f"seq:{tmp_path / 'euroc'}"), RecordingEngine(), rig=estec_rig, record_dir=tmp_path / "rec") as pipe:
        pipe.run_until_end(20)
    assert index_sequence(tmp_path / "rec").t_ns.tolist() == stamps


class GatedWriter(ListWriter):
    """A disk far slower than the stream: each write waits for ``gate`` (10 s at most)."""

    def __init__(self, directory: Path, gate: threading.Event) -> None:
        super().__init__(directory)
        self.gate = gate

    def write(self, frame: StereoFrame) -> None:
        self.gate.wait(10)
        super().write(frame)


def test_stopping_a_recording_behind_a_slow_disk_does_not_stop_the_tracking(tmp_path: Path) -> None:
    # The stop waited on the tracking thread for every queued frame to be written: behind a
    # slow disk, seconds without a tracked frame, a snapshot or a command's reply (an outside
    # review: 5.9 s, and SetAuto unanswered for all of it).
    gate = threading.Event()
    writer = GatedWriter(tmp_path, gate)
    pipe = Pipeline(CountingSource(10**6, delay_s=0.002), RecordingEngine(), drop_frames=True,
                    writer_factory=lambda d: writer, record_queue_frames=20)
    with pipe:
        assert pipe.call(SetRecording(str(tmp_path / "rec"))).ok
        deadline = time.monotonic() + 10
        while pipe.recording_stats().queue_depth < 10:
            assert time.monotonic() < deadline
            time.sleep(0.005)
        stopped = pipe.submit(SetRecording(None))
        try:
            reply = pipe.call(SelectPoint(2.0, 2.0), timeout_s=3.0)  # answered while the disk still lags
            assert reply.ok and not stopped.done()
            closing = pipe.recording_stats()
            assert not closing.active and closing.queue_depth > 0  # its queue seen draining
            tracked = pipe.timings().frames_processed
            assert pipe.wait_snapshot(pipe.latest().sequence + 3, 3.0) is not None
            assert pipe.timings().frames_processed > tracked
        finally:
            gate.set()
        final = stopped.result(10.0)
        assert final.ok, final.message
        stats = pipe.recordings()[-1]
        assert stats.frames_written == len(writer.indices) == stats.frames_queued and writer.closed
    assert [r.directory for r in pipe.recordings()] == [str(tmp_path)]


def test_a_frame_offered_as_the_recording_stops_is_written_or_counted(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    # The acquisition thread took the recorder, let go of the lock, then offered the frame: a
    # stop in between closed the recorder first, and the frame queued behind its end was
    # neither written nor counted (an outside review: 3 frames in 800 toggles).
    from trackmeter.pipeline import pipeline as pipeline_module

    offered: list[int] = []
    in_offer = threading.Event()
    original = pipeline_module._Recorder.offer

    def slow_offer(self, frame):  # type: ignore[no-untyped-def]
        offered.append(frame.index)
        if len(offered) == 3:
            in_offer.set()
            time.sleep(0.3)  # the thread preempted here, while a stop comes
        original(self, frame)

    monkeypatch.setattr(pipeline_module._Recorder, "offer", slow_offer)
    writer = ListWriter(tmp_path)
    pipe = Pipeline(CountingSource(10**6, delay_s=0.002), RecordingEngine(), drop_frames=True,
                    writer_factory=lambda d: writer)
    with pipe:
        assert pipe.call(SetRecording(str(tmp_path / "rec"))).ok
        assert in_offer.wait(5)
        assert pipe.call(SetRecording(None), timeout_s=5.0).ok
    stats = pipe.recordings()[-1]
    assert stats.frames_written + stats.frames_dropped + stats.frames_lost == len(offered)
    assert writer.indices == offered


def test_play_after_a_pause_lets_the_source_pace_on_from_its_next_frame() -> None:
    # The source's pacing took the pause for lateness: after a pause under half a second it
    # sent the frames "missed" back to back, counted as dropped (an outside review: 24 frames
    # after three pauses of 0.45 s).
    class ResumedSource(CountingSource):
        resumed = 0

        def resume(self) -> None:
            self.resumed += 1

    source = ResumedSource(10**6, delay_s=0.002)
    with Pipeline(source, RecordingEngine(), paused=True) as pipe:
        assert pipe.call(SetPaused(True)).ok and source.resumed == 0
        assert pipe.call(SetPaused(False)).ok and source.resumed == 1


@pytest.mark.parametrize("spec", ["sim", "video"])
def test_a_real_time_source_resumed_paces_from_its_next_frame(spec: str, tmp_path: Path) -> None:
    from trackmeter.sources import open_source
    from trackmeter.sources.pacing import Pacer

    if spec == "video":
        from tests.test_sequence import _video

        paths = [_video(tmp_path / "left.avi", 6, fps=25.0), _video(tmp_path / "right.avi", 6, fps=25.0)]
        spec = f"video:{paths[0]},{paths[1]}"
    source = open_source(spec, realtime=True, **({"render_ahead": False} if spec == "sim" else {}))
    now, slept = [0.0], []

    def sleep(d: float) -> None:
        slept.append(d)
        now[0] += d

    source._pacer = Pacer(clock=lambda: now[0], sleep=sleep)  # type: ignore[attr-defined]
    try:
        source.read(), source.read()
        assert slept == pytest.approx([0.04])
        now[0] += 0.3  # paused for 0.3 s: under the pacer's half second of re-anchoring
        source.resume()
        source.read(), source.read()
        assert slept == pytest.approx([0.04, 0.04])  # not the next frames at once, 0.26 s "late"
    finally:
        source.close()
