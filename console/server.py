"""Starting the console: the viser server on an exact port, the pipeline, and a clean stop.

viser silently moves to the next free port when the requested one is busy (DESIGN.md
section 8); an operator told to open ``:8080`` would then watch somebody else's console. So
the port is checked first and a busy port is a :class:`TrackmeterError` (exit code 2).
"""

from __future__ import annotations

import errno
import logging
import socket
import sys
import threading
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import viser

from console.app import Console, pin_mmap_threshold
from trackmeter.core.patch_tracking import warm_up
from trackmeter.errors import TrackmeterError
from trackmeter.signals import interrupt_kept
from trackmeter.pipeline.pipeline import EngineLike, Pipeline
from trackmeter.sources.base import Source

log = logging.getLogger(__name__)


def check_port_free(host: str, port: int) -> None:
    """Raise TrackmeterError when ``host:port`` cannot be bound (in use, or not our address)."""
    if not 0 < port < 65536:
        raise TrackmeterError(f"port must be 1-65535, got {port}")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as exc:
        raise TrackmeterError(f"cannot resolve host {host!r}: {exc.strerror}") from None
    family, _, _, _, addr = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as s:
        # Like the web server will: a port in TIME_WAIT is free, one somebody listens on is not.
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(addr)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise TrackmeterError(f"port {port} on {host} is already in use; choose another with --port") from None
            raise TrackmeterError(f"cannot listen on {host}:{port}: {exc.strerror}") from None


def start_server(host: str = "127.0.0.1", port: int = 8080, label: str = "TV-Trackmeter") -> viser.ViserServer:
    """A viser server on exactly ``host:port`` (TrackmeterError if that port is taken)."""
    check_port_free(host, port)
    server = viser.ViserServer(host=host, port=port, label=label, verbose=False)
    if server.get_port() != port:  # lost a race with another process
        server.stop()
        raise TrackmeterError(f"port {port} on {host} is already in use; choose another with --port")
    return server


def console_url(host: str, port: int) -> str:
    """The address to open for a console listening on ``host:port``: an address that means
    every interface as this machine's loopback of its family, and an IPv6 one in brackets
    (``http://::1:8080`` was printed, which no browser opens)."""
    shown = {"": "127.0.0.1", "0.0.0.0": "127.0.0.1", "::": "::1"}.get(host, host)
    if ":" in shown and not shown.startswith("["):
        shown = "[" + shown.replace("%", "%25") + "]"  # a zone ("fe80::1%eth0") escaped (RFC 6874)
    return f"http://{shown}:{port}"


def mockup_mesh_of(source: Source) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The mock-up's triangle mesh when the source is the simulator (else None)."""
    for holder in (source, getattr(source, "scenario", None)):
        mockup = getattr(holder, "mockup", None)
        if mockup is not None and hasattr(mockup, "to_trimesh_arrays"):
            try:
                return mockup.to_trimesh_arrays()
            except Exception as exc:
                log.warning("no mock-up mesh for the 3D view: %s", exc)
    return None


@dataclass
class RunningConsole:
    """A started console: the server, the pipeline and the console object; :meth:`stop` ends all."""

    server: viser.ViserServer
    pipeline: Pipeline
    console: Console
    url: str
    #: The source's warning when it opened, said then (warnings.warn, naming its folder); what
    #: the pipeline's reads find later (a first image that does not decode) is news.
    warning_at_open: str | None = None

    def stop(self) -> None:
        """Stop publishing, join the pipeline threads, close the recording and the source, stop the server."""
        self.console.stop()
        self.pipeline.close()
        self.server.stop()


def quiet_dead_client_warnings() -> None:
    """Leave out viser's warning that a message was queued on a closed connection: the answer
    (a pop-up) to a browser that reloaded or closed since its command, lost on purpose, reached
    the operator's terminal as 'warning: Queued a NotificationShowMessage on a closed
    connection ...' (an outside monkey probe). Other warnings pass."""
    warnings.filterwarnings("ignore", message=r"Queued a \w+ on a closed connection", category=UserWarning)


def start_console(
    source: Source,
    engine: EngineLike,
    *,
    host: str = "127.0.0.1",
    port: int = 8080,
    record_dir: str | Path | None = None,
    source_label: str = "",
    **console_options: Any,
) -> RunningConsole:
    """Start the server (exact port), the pipeline (live: latest frame wins) and the console.

    Raises:
        TrackmeterError: the port is taken; a recording folder that cannot be used.
    """
    pin_mmap_threshold()
    quiet_dead_client_warnings()
    # Compile the tracker's fits (about 15 s the first time after an install, then loaded from
    # numba's cache) before the server listens: a page opened during the compile was starved,
    # and viser's client drops an image still loading when the next arrives, so it stayed
    # black; the pipeline's own warm-up then finds them compiled.
    with interrupt_kept():  # a stop signal during a compile is otherwise lost there
        warm_up()
    warning_at_open = getattr(source, "warning", None)
    server = start_server(host, port)
    pipeline = Pipeline(source, engine, drop_frames=True, record_dir=record_dir)
    try:
        console = Console(server, pipeline, mockup_mesh=mockup_mesh_of(source), source_label=source_label,
                          **console_options)
        pipeline.start()
        console.start()
    except BaseException:
        pipeline.stop()
        server.stop()
        raise
    return RunningConsole(server, pipeline, console, console_url(host, port), warning_at_open)


def serve_forever(running: RunningConsole, stop: threading.Event | None = None, poll_s: float = 0.5) -> None:
    """Block until Ctrl-C (or ``stop`` is set), then stop everything cleanly. Meanwhile each new
    source status (ended, failed) and source warning (images skipped) is one line on stderr:
    whoever started the console sees what the browser's status line shows."""
    stop = stop or threading.Event()
    # The source's warning at open was said then, naming its folder (warnings.warn): not again.
    said: tuple[str | None, str | None] = (None, running.warning_at_open)
    try:
        while not stop.wait(poll_s):
            snap = running.pipeline.latest()
            status, warning = snap.source_status, snap.source_warning
            if warning and warning != said[1]:
                print(f"trackmeter console: warning: {warning}", file=sys.stderr, flush=True)
            if status and status != said[0]:
                print(f"trackmeter console: {snap.source_status_text}", file=sys.stderr, flush=True)
            said = (status, warning)
    except KeyboardInterrupt:
        pass
    finally:
        running.stop()
