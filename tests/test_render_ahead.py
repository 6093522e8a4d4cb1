"""The simulator's render-ahead worker gives the very frames the reader would render itself."""

from __future__ import annotations

import io
import pickle

import numpy as np
import pytest

from trackmeter.errors import TrackmeterError
from trackmeter.sources.sim.render_ahead import _INT, RenderAhead, worker_main
from trackmeter.sources.sim.scenario import load_scenario
from trackmeter.sources.sim.simulator import Simulator


@pytest.fixture(scope="module")
def short_estec():
    return load_scenario("estec").with_duration(0.12)  # 3 frames


def test_streamed_frames_are_identical_and_wrap(short_estec):
    here = Simulator(short_estec, loop=True)
    ahead = Simulator(short_estec, mockup=here.mockup, loop=True, render_ahead=True)
    try:
        frames = [ahead.read() for _ in range(7)]
        assert [f.index for f in frames] == list(range(7))
        for f in frames:
            ref = here.frame(f.index)
            assert np.array_equal(f.left, ref.left) and np.array_equal(f.right, ref.right)
            assert np.array_equal(f.truth.T_cam_body, ref.truth.T_cam_body)
            assert np.array_equal(f.truth.velocity_cam_m_s, ref.truth.velocity_cam_m_s)
            assert np.array_equal(f.truth.omega_body_rad_s, ref.truth.omega_body_rad_s)
        assert np.allclose(np.diff([f.t_s for f in frames]), 0.04)
        # A restart discards what was queued and starts again at frame 0.
        assert [f.cut for f in frames] == [False, False, False, True, False, False, True]
        ahead.restart()
        again = ahead.read()
        assert again.index == 0 and np.array_equal(again.left, frames[0].left) and again.cut
        worker = ahead._ahead
        assert worker is not None
    finally:
        ahead.close()
    assert worker._proc.poll() is not None, "close() must stop the worker process"


def test_a_stream_that_ends_ends(short_estec):
    with Simulator(short_estec, render_ahead=True) as sim:
        assert [sim.read() is None for _ in range(4)] == [False, False, False, True]


def test_a_worker_error_is_one_clear_message_and_the_worker_serves_on(short_estec):
    ahead = RenderAhead(short_estec, (726, 512), depth=2)
    try:
        with pytest.raises(TrackmeterError, match="failed on frame 99.*outside the scenario"):
            ahead.images(99, lambda i: None)
        left, right = ahead.images(1, lambda i: None)
        assert np.array_equal(left, Simulator(short_estec).frame(1).left)
    finally:
        ahead.close()


def test_worker_protocol_in_process(short_estec):
    blob = pickle.dumps(short_estec)
    requests = io.BytesIO(_INT.pack(len(blob)) + blob + _INT.pack(2) + _INT.pack(5))
    answers = io.BytesIO()
    assert worker_main(requests, answers) == 0  # ends cleanly at end of input
    data = answers.getvalue()
    n = 726 * 512
    assert _INT.unpack_from(data, 0)[0] == 2
    ref = Simulator(short_estec).frame(2)
    assert data[8:8 + n] == ref.left.tobytes() and data[8 + n:8 + 2 * n] == ref.right.tobytes()
    truth = np.frombuffer(data[8 + 2 * n:8 + 2 * n + 8 * 22], np.float64)
    assert np.array_equal(truth[:16].reshape(4, 4), ref.truth.T_cam_body)
    assert np.array_equal(truth[16:19], ref.truth.velocity_cam_m_s) and np.array_equal(truth[19:], ref.truth.omega_body_rad_s)
    rest = data[8 + 2 * n + 8 * 22:]
    assert _INT.unpack_from(rest, 0)[0] == -1
    size = _INT.unpack_from(rest, 8)[0]
    assert b"outside the scenario" in rest[16:16 + size]


def test_a_worker_whose_reader_is_gone_ends_quietly(short_estec):
    # A second Ctrl-C can kill the reader before it closes the worker's stdin: the worker's
    # next answer meets a broken pipe, and must end the worker, not print a traceback.
    class GonePipe(io.BytesIO):
        def write(self, data):  # type: ignore[no-untyped-def, override]
            raise BrokenPipeError(32, "Broken pipe")

    blob = pickle.dumps(short_estec)
    requests = io.BytesIO(_INT.pack(len(blob)) + blob + _INT.pack(0) + _INT.pack(1))
    assert worker_main(requests, GonePipe()) == 0


def test_a_dead_worker_is_reported(short_estec):
    ahead = RenderAhead(short_estec, (726, 512))
    ahead._proc.kill()
    ahead._proc.wait()
    with pytest.raises(TrackmeterError, match="render worker stopped"):
        ahead.images(0, lambda i: i + 1)
    ahead.close()


def test_a_killed_worker_is_reported_with_its_exit_code_not_none(short_estec):
    """The console said "exit code None" for a worker killed with SIGKILL where track said -9:
    the pipe closes a moment before the kernel reports the exit."""
    ahead = RenderAhead(short_estec, (726, 512))
    ahead._proc.kill()
    ahead._proc.poll = lambda: None  # type: ignore[method-assign]  # the moment before the exit is reported
    with pytest.raises(TrackmeterError, match=r"render worker stopped \(exit code -9\)"):
        for k in range(50):
            ahead.images(k, lambda i: i + 1)
    ahead.close()


def test_the_pipe_holds_a_whole_frame_where_the_system_allows(short_estec):
    fcntl = pytest.importorskip("fcntl")
    if not hasattr(fcntl, "F_GETPIPE_SZ"):
        pytest.skip("no F_GETPIPE_SZ on this system")
    with open("/proc/sys/fs/pipe-max-size") as f:
        allowed = int(f.read())
    ahead = RenderAhead(short_estec, (726, 512))
    try:
        size = fcntl.fcntl(ahead._proc.stdout.fileno(), fcntl.F_GETPIPE_SZ)
        assert size >= min(allowed, 2 * 726 * 512 + 16 + 8 * 22)
    finally:
        ahead.close()


def test_the_worker_runs_in_a_session_of_its_own(short_estec):
    # Autogroup scheduling shares the CPUs between sessions: the camera stand-in must not take
    # its CPU out of the tracking process's share (trackmeter.priority).
    import os

    ahead = RenderAhead(short_estec, (726, 512))
    try:
        assert os.getsid(ahead._proc.pid) == ahead._proc.pid != os.getsid(0)
        left, right = ahead.images(0, lambda i: i + 1)  # and it renders as before
        assert left.shape == right.shape == (512, 726) and left.any()
    finally:
        ahead.close()
