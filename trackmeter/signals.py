"""The signals that stop a command as Ctrl-C does: files completed, threads joined.

SIGINT is Ctrl-C; SIGTERM is a service manager's (or ``kill``'s) stop; SIGHUP comes when the
terminal a command runs in closes or an ssh session drops, and by default it kills outright,
which would leave a recording or a run directory half-written. Kept free of heavy imports:
the command line's entry point reads it before any command is loaded.
"""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator

STOP_SIGNALS: tuple[signal.Signals, ...] = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))
"""SIGHUP exists only on POSIX systems."""


def takes_over(signum: int, handler: object) -> bool:
    """Whether the command line should install its stop handler for ``signum`` over
    ``handler``, the one it found: yes over the defaults, never over an inherited SIG_IGN
    (``nohup`` ignores SIGHUP, a shell's ``cmd &`` SIGINT) or a handler someone else set."""
    if signum == signal.SIGINT:
        return handler is signal.default_int_handler
    return handler in (signal.SIG_DFL, None)


class StopSignal(KeyboardInterrupt):
    """The KeyboardInterrupt the command line raises for a stop signal it took (Ctrl-C,
    SIGTERM, SIGHUP); ``except KeyboardInterrupt`` catches it as any.

    A subclass because CPython marks a plain KeyboardInterrupt that leaves code made from a
    string (``exec``/``eval``, as dataclasses and namedtuple make their methods, so a signal
    in an import's first second often lands there) as unhandled, and a ``python -m`` process
    then kills itself with SIGINT at exit (status -2) whatever the command returned, though
    it caught the interrupt and completed its files. The mark is for the exact type only."""


#: The stop signal the command line took during the running command (:func:`note_taken`),
#: or None.
_taken: int | None = None


def note_taken(signum: int | None) -> None:
    """Record that the command line's handler took stop signal ``signum`` (None: a command
    starts, none taken yet)."""
    global _taken
    _taken = signum


def taken() -> int | None:
    """The stop signal taken during the running command, or None."""
    return _taken


@contextlib.contextmanager
def interrupt_kept() -> Iterator[None]:
    """Run a block in which the KeyboardInterrupt of a stop signal may be lost, and raise one
    after it when a stop signal was taken during it.

    A C library that calls back into Python drops an exception raised in its callback: numba's
    compile (through ctypes) reports the handler's KeyboardInterrupt as "Exception ignored"
    and goes on, to its end (the stop lost: the run carried on, exit 0) or to an error of its
    own ("RuntimeError: no compiled object yet", exit 1 and a run folder left "running").
    Either way the block ends here as the interrupt it was. A signal taken before the block
    (the command already stopping) is not raised again."""
    before = _taken
    try:
        yield
    except Exception:
        if before is None and _taken is not None:
            raise StopSignal from None
        raise
    if before is None and _taken is not None:
        raise StopSignal
