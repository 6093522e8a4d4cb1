"""The signals that stop a command as Ctrl-C does: files completed, threads joined.

SIGINT is Ctrl-C; SIGTERM is a service manager's (or ``kill``'s) stop; SIGHUP comes when the
terminal a command runs in closes or an ssh session drops, and by default it kills outright,
which would leave a recording or a run directory half-written. Kept free of heavy imports:
the command line's entry point reads it before any command is loaded.
"""

from __future__ import annotations

import signal

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
