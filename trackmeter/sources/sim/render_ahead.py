"""Render simulator frames ahead of the reader, in a separate process.

A camera hands the tracker finished images at no CPU cost to the tracking process. The
simulator's renderer is pure NumPy/OpenCV and costs about as much CPU per stereo pair as the whole
tracking step; run in the reader's process it competes with tracking for the interpreter lock,
and a live ``sim`` source could not keep 25 Hz beside a 25 Hz tracker on two cores.
:class:`RenderAhead` moves rendering into a worker process and keeps the next ``depth`` frames in
flight, so the reader's process only tracks.

Frames are random-access and deterministic (each frame's noise is seeded by ``(seed, index)``;
see :class:`~trackmeter.sources.sim.simulator.Simulator`), so a frame rendered in the worker is
the frame the reader would have rendered itself, bit for bit.

The worker is a plain ``python -c`` child talking over its stdin/stdout pipes, not a
``multiprocessing`` pool: ``fork`` is unsafe in a process that already runs threads (pipeline,
viser), and ``spawn`` re-imports the caller's main script, which breaks any script that opens a
source without an ``if __name__ == "__main__"`` guard. The child exits when its stdin closes, so
it never outlives the reader. A thread of the reader drains the child's stdout into a queue: a
frame (~0.7 MB) is larger than a pipe's buffer, and an undrained pipe would stall the child
after each frame instead of letting it render ahead.

Protocol (native byte order): the reader sends the pickled scenario once, length-prefixed, then
one int64 frame index per request; the worker answers each request in order with an int64
status header (``index`` or -1 on error), then either ``left`` and ``right`` as raw uint8 bytes
of the rig's image size followed by the frame's ground truth as 22 float64 (``T_cam_body``
row-major, ``velocity_cam_m_s``, ``omega_body_rad_s``: the worker computed it for the render,
and evaluating the rotation's solution again would cost the reader ~0.5 ms a frame), or a
length-prefixed UTF-8 error message.
"""

from __future__ import annotations

import os
import pickle
import queue
import struct
import subprocess
import sys
import threading
import warnings
from collections import deque
from collections.abc import Callable
from typing import IO, TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from trackmeter.errors import TrackmeterError
from trackmeter.sources.base import GroundTruth

if TYPE_CHECKING:
    from trackmeter.sources.sim.scenario import Scenario

_INT = struct.Struct("=q")
_TRUTH_FLOATS = 22  # T_cam_body (16), velocity_cam_m_s (3), omega_body_rad_s (3)


def _truth_bytes(truth: GroundTruth) -> bytes:
    return np.concatenate([np.asarray(truth.T_cam_body, np.float64).ravel(), np.asarray(truth.velocity_cam_m_s, np.float64).ravel(),
                           np.asarray(truth.omega_body_rad_s, np.float64).ravel()]).tobytes()


def _truth_from_bytes(data: bytes) -> GroundTruth:
    x = np.frombuffer(data, np.float64).copy()
    return GroundTruth(x[:16].reshape(4, 4), x[16:19], x[19:22])


def _widen_pipe(fd: int, frame_bytes: int) -> None:
    """Make the pipe ``fd`` hold a whole answer if the system allows (Linux ``F_SETPIPE_SZ``,
    up to ``/proc/sys/fs/pipe-max-size``, 1 MiB by default); else leave it (64 KiB).

    With the default size a frame crosses in a dozen pieces, and the reader's drain thread
    must win the interpreter lock back from the tracking threads for each one: with a busy
    reader (the tracker, the console) frames then arrive at well under the rate the worker
    renders them. A pipe that holds a frame lets the worker write it at once and go on
    rendering, and the drain thread take it in one read.
    """
    try:
        import fcntl

        size = 1 << max(16, (frame_bytes - 1).bit_length())
        try:
            with open("/proc/sys/fs/pipe-max-size") as f:
                size = min(size, int(f.read()))
        except (OSError, ValueError):
            pass
        if size > fcntl.fcntl(fd, fcntl.F_GETPIPE_SZ):
            fcntl.fcntl(fd, fcntl.F_SETPIPE_SZ, size)
    except (ImportError, AttributeError, OSError):
        pass  # not Linux, or not allowed: the default pipe works, only slower


def _read_exact(stream: IO[bytes], n: int) -> bytes:
    data = stream.read(n)
    if data is None or len(data) != n:
        raise EOFError(f"expected {n} bytes, got {0 if data is None else len(data)}")
    return data


def worker_main(stdin: IO[bytes] | None = None, stdout: IO[bytes] | None = None) -> int:
    """The worker's loop: read the scenario, then render each requested frame (until EOF)."""
    import signal

    from trackmeter.sources.sim.simulator import Simulator

    if stdin is None:
        # The reader shuts down by closing our stdin, which ends this loop. Ctrl-C in a terminal
        # does not reach this session of our own; an interrupt sent anyway would only print a
        # traceback and fail the frames still in flight.
        signal.signal(signal.SIGINT, signal.SIG_IGN)

    inp = stdin if stdin is not None else sys.stdin.buffer
    out = stdout if stdout is not None else sys.stdout.buffer
    if stdin is None:
        import cv2

        from trackmeter.priority import autogroup_follows_nice

        # One thread: the worker renders ahead, so its CPU per frame matters, not its latency;
        # OpenCV's thread pool costs a few % more CPU (same images) and competes with the reader.
        cv2.setNumThreads(1)
        # Our own session (see RenderAhead): at the priority the reader gave us, if it raised its own.
        autogroup_follows_nice()
    try:
        (size,) = _INT.unpack(_read_exact(inp, _INT.size))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the reader's own Simulator has said them
            sim = Simulator(pickle.loads(_read_exact(inp, size)))
    except EOFError:
        return 0
    while True:
        try:
            (index,) = _INT.unpack(_read_exact(inp, _INT.size))
        except EOFError:
            return 0
        try:
            frame = sim.frame(index)
            assert frame.truth is not None
            payload = [_INT.pack(index), np.ascontiguousarray(frame.left).tobytes(),
                       np.ascontiguousarray(frame.right).tobytes(), _truth_bytes(frame.truth)]
        except Exception as exc:  # report to the reader, keep serving
            msg = f"{type(exc).__name__}: {exc}".encode()
            payload = [_INT.pack(-1), _INT.pack(len(msg)), msg]
        try:
            out.write(b"".join(payload))
            out.flush()
        except BrokenPipeError:
            # The reader is gone (killed, or a second Ctrl-C cut its cleanup short): nobody is
            # left to serve, and no traceback should land on the terminal it shared.
            if stdout is None:
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # the exit flush too
            return 0


class RenderAhead:
    """The next frames of a scenario, rendered in a worker process while the caller works.

    Args:
        scenario: the scenario the worker renders (it loads its own mock-up and rig).
        image_size: (width, height) of the rendered images, px.
        depth: frames kept in flight (>= 1); the caller asks for them in order.

    :meth:`images` returns frame ``index``'s (left, right) and queues the frames after it (as
    ``next_index`` says: ``index + 1``, wrapped for a looping source, None at the end). Asking
    for any other frame than the one queued first (a restart, a seek) discards the queue.
    """

    def __init__(self, scenario: Scenario, image_size: tuple[int, int], depth: int = 3) -> None:
        if depth < 1:
            raise TrackmeterError(f"render ahead needs depth >= 1, got {depth}")
        self._shape = (int(image_size[1]), int(image_size[0]))
        self._depth = depth
        self._queue: deque[int] = deque()
        # The child imports trackmeter from wherever this process did.
        boot = (f"import sys; sys.path[:0] = {[p for p in sys.path if p]!r}; "
                "from trackmeter.sources.sim.render_ahead import worker_main; sys.exit(worker_main())")
        # A session of its own: on Linux with autogroup scheduling the sessions share the CPUs
        # equally, so the renderer, which stands in for the cameras' own hardware, does not take
        # its CPU out of the tracking process's share when another program (a browser) is busy.
        self._proc = subprocess.Popen([sys.executable, "-c", boot], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                      start_new_session=True)
        assert self._proc.stdout is not None
        _widen_pipe(self._proc.stdout.fileno(), 2 * self._shape[0] * self._shape[1] + 2 * _INT.size + 8 * _TRUTH_FLOATS)
        self._results: queue.Queue[tuple[int, object]] = queue.Queue()
        self._drain = threading.Thread(target=self._drain_stdout, name="render-ahead-drain", daemon=True)
        self._drain.start()
        blob = pickle.dumps(scenario)
        self._send(_INT.pack(len(blob)) + blob)

    def _send(self, data: bytes) -> None:
        assert self._proc.stdin is not None
        try:
            self._proc.stdin.write(data)
            self._proc.stdin.flush()
        except (BrokenPipeError, OSError):
            raise self._died() from None

    def _died(self) -> TrackmeterError:
        # A closed pipe comes a moment before the kernel reports the exit: wait for the code
        # (poll() alone said "exit code None" where track, a little later, said -9).
        try:
            code: int | None = self._proc.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            code = None
        if code is None:
            return TrackmeterError("simulator render worker stopped answering (its pipe closed)")
        return TrackmeterError(f"simulator render worker stopped (exit code {code})")

    def images(self, index: int, next_index: Callable[[int], int | None]) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
        """Frame ``index``'s (left, right) images (waits for the worker), with the next ones queued.

        Raises:
            TrackmeterError: the worker failed to render the frame, or stopped.
        """
        left, right, _ = self.rendered(index, next_index)
        return left, right

    def rendered(
        self, index: int, next_index: Callable[[int], int | None]
    ) -> tuple[NDArray[np.uint8], NDArray[np.uint8], GroundTruth]:
        """As :meth:`images`, with the frame's ground truth as the worker computed it."""
        if self._queue and self._queue[0] != index:
            self._discard_queue()
        if not self._queue:
            self._request(index)
        while len(self._queue) < self._depth + 1:
            nxt = next_index(self._queue[-1])
            if nxt is None:
                break
            self._request(nxt)
        return self._receive(self._queue.popleft())

    def _request(self, index: int) -> None:
        self._send(_INT.pack(index))
        self._queue.append(index)

    def _drain_stdout(self) -> None:
        """Reader thread: each answer of the worker onto ``self._results``; (-2, why) at the end."""
        out = self._proc.stdout
        assert out is not None
        n = self._shape[0] * self._shape[1]
        try:
            while True:
                (got,) = _INT.unpack(_read_exact(out, _INT.size))
                if got == -1:
                    (size,) = _INT.unpack(_read_exact(out, _INT.size))
                    self._results.put((-1, _read_exact(out, size).decode(errors="replace")))
                    continue
                left = np.frombuffer(_read_exact(out, n), np.uint8).reshape(self._shape)
                right = np.frombuffer(_read_exact(out, n), np.uint8).reshape(self._shape)
                truth = _truth_from_bytes(_read_exact(out, 8 * _TRUTH_FLOATS))
                self._results.put((got, (left, right, truth)))
        except (EOFError, OSError, ValueError):
            self._results.put((-2, None))

    def _receive(self, index: int) -> tuple[NDArray[np.uint8], NDArray[np.uint8], GroundTruth]:
        got, payload = self._results.get()
        if got == -2:
            self._results.put((got, payload))  # every later call fails the same way
            raise self._died()
        if got == -1:
            raise TrackmeterError(f"simulator render worker failed on frame {index}: {payload}")
        if got != index:
            raise TrackmeterError(f"simulator render worker out of step: frame {got} where {index} was due")
        return payload  # type: ignore[return-value]

    def _discard_queue(self) -> None:
        while self._queue:
            index = self._queue.popleft()
            try:
                self._receive(index)
            except TrackmeterError:
                if self._proc.poll() is not None:
                    raise

    def close(self) -> None:
        """Stop the worker (frames in flight are discarded)."""
        if self._proc.stdin is not None and not self._proc.stdin.closed:
            try:
                self._proc.stdin.close()
            except OSError:
                pass
        try:
            self._proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        self._drain.join(timeout=5)
        if self._proc.stdout is not None:
            self._proc.stdout.close()
