"""The ``trackmeter`` command: a thin layer over library functions.

Each subcommand lives in its own module ``trackmeter.cli.<name>`` with two functions,
``add_arguments(parser)`` and ``run(args) -> int``; heavy imports happen inside ``run`` so
``--help`` stays fast. Any :class:`TrackmeterError` or :class:`OSError` (an output path that
cannot be written, a full disk) becomes one line on stderr and exit code 2; a closed stdout
(``... --json | head``) ends the command quietly. Any other exception is a bug and keeps its
traceback.
"""

from __future__ import annotations

import argparse
import codecs
import contextlib
import importlib
import logging
import os
import re
import signal
import sys
import threading
import warnings
from types import ModuleType
from typing import Any, Callable, NoReturn, Sequence, TextIO

from trackmeter.errors import TrackmeterError
from trackmeter import signals
from trackmeter.signals import STOP_SIGNALS, takes_over

#: name -> one-line help. The module ``trackmeter.cli.<name>`` implements it.
COMMANDS: dict[str, str] = {
    "console": "run the pipeline with the operator console in the browser (viser)",
    "calibrate": "calibrate a stereo rig from chessboard image pairs",
    "measure": "measure 3D points of a stereo pair at given left-image pixels",
    "simulate": "render a tumbling-satellite scenario to a stereo sequence folder",
    "track": "track targets and estimate pose and velocities, headless, into a run folder",
    "evaluate": "compare an estimated trajectory with the ground truth",
    "analyze": "error analysis: sigma versus range, sub-pixel accuracy, error density",
}


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage error as one line and exit code 2."""

    #: name -> the subcommand's parser (top-level parser only), so an unknown argument is
    #: reported by the command it was given to.
    commands: dict[str, argparse.ArgumentParser]
    #: the command line being parsed (for hints in error messages)
    argv: list[str] = []

    def error(self, message: str) -> NoReturn:
        missing = re.match(r"argument (--[\w-]+)(?:/-\w)?: expected (?:at least )?one argument", message)
        if missing:
            option = missing.group(1)
            given = [b for a, b in zip(self.argv, self.argv[1:]) if a == option and re.match(r"-\.?\d", b)]
            if given:
                # argparse reads "--at -5,3" as an option "-5,3": the user's value was there.
                message += f" (a value that starts with '-' must be joined to it: {option}={given[0]})"
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def build_parser() -> _Parser:
    parser = _Parser(
        prog="trackmeter",
        description="TV-Trackmeter: stereo tracking and motion estimation of a tumbling satellite.",
    )
    from trackmeter import __version__

    parser.add_argument("--version", action="version", version=f"trackmeter {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    parser.commands = {}
    for name, help_text in COMMANDS.items():
        module = _command_module(name)
        p = sub.add_parser(name, help=help_text, description=(module.__doc__ or help_text).strip(),
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        p.add_argument("--config", metavar="FILE", action="append",
                       help="YAML file layered over config/default.yaml; give it again to layer more, in order "
                            "(a later file's value wins)")
        module.add_arguments(p)
        parser.commands[name] = p
    return parser


def _command_module(name: str) -> ModuleType:
    return importlib.import_module(f"trackmeter.cli.{name}")


def _interrupt(signum: int, frame: object) -> None:
    """The first Ctrl-C, SIGTERM or SIGHUP stops the command (:class:`StopSignal`, a
    KeyboardInterrupt); any later one is only noted. A second signal arrives while the
    command winds down (Ctrl-C pressed twice; a wrapper such as ``timeout`` passing on the
    SIGTERM a service manager also sends): raised again, it would cut the wind-down short (a
    recording or a run left half-closed) or land inside the interpreter's own lock handling
    (``RuntimeError: release unlocked lock``)."""
    signals.note_taken(signum)
    _swap_handlers(_interrupt, _already_stopping)
    if signum == getattr(signal, "SIGHUP", None):
        _outlive_the_terminal()
    raise signals.StopSignal


def _caused_by_an_interrupt(exc: BaseException) -> bool:
    """Whether a KeyboardInterrupt is in ``exc``'s chain of causes and contexts."""
    seen: set[int] = set()
    link: BaseException | None = exc
    while link is not None and id(link) not in seen:
        if isinstance(link, KeyboardInterrupt):
            return True
        seen.add(id(link))
        link = link.__cause__ or link.__context__
    return False


def _already_stopping(signum: int, frame: object) -> None:
    _swap_handlers(_already_stopping, signal.SIG_IGN)  # said once is enough
    # os.write, not print: the signal may land while the main thread is inside a print to
    # stderr, and a re-entered buffered write raises.
    with contextlib.suppress(OSError):
        os.write(2, b"trackmeter: stopping already; the files are being completed\n")


def _without_signal_race_reports(hook: Callable[[Any], object]) -> Callable[[Any], None]:
    """``sys.unraisablehook`` minus the reports of a stop the command handles: the
    KeyboardInterrupt of a stop signal that a C library's callback dropped (numba's compile,
    through ctypes; :func:`trackmeter.signals.interrupt_kept` raises it again), and CPython's
    report of a signal that found SIG_IGN: a signal of a burst, already caught by the
    interpreter when its handler became SIG_IGN, is then ignored and reported as an
    unraisable error with a traceback ("Signal 15 ignored due to race condition"). That is
    the ignoring the command wants. SIG_IGN itself must stay: the
    interpreter's shutdown resets Python handlers to the default, and a late signal would
    then kill the process (exit -2) where an ignored one does not."""

    def report(unraisable: Any) -> None:
        exc = getattr(unraisable, "exc_value", None)
        if isinstance(exc, OSError) and "ignored due to race condition" in str(exc):
            return
        if isinstance(exc, KeyboardInterrupt) and signals.taken() is not None:
            return  # the stop's own, dropped by a C library's callback: it stops the command all the same
        hook(unraisable)

    return report


def _swap_handlers(installed: object, replacement: Callable[[int, object], None] | signal.Handlers) -> None:
    """Replace ``installed`` by ``replacement`` wherever it handles a stop signal."""
    for sig in STOP_SIGNALS:
        if signal.getsignal(sig) is installed:
            signal.signal(sig, replacement)


class _ForgivingStream:
    """A text stream whose writes and flushes may fail silently: after a hang-up the terminal
    is usually gone (writes raise EIO), and a command's last lines must not turn a clean
    stop, its files already complete, into an error. Output redirected to a file still
    gets them."""

    def __init__(self, stream: TextIO) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except (OSError, ValueError):
            return len(text)

    def flush(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            self._stream.flush()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


_streams_before_hangup: tuple[TextIO, TextIO] | None = None


def _outlive_the_terminal() -> None:
    global _streams_before_hangup
    if _streams_before_hangup is None:
        _streams_before_hangup = (sys.stdout, sys.stderr)
        sys.stdout = _ForgivingStream(sys.stdout)
        sys.stderr = _ForgivingStream(sys.stderr)


def _restore_streams() -> None:
    global _streams_before_hangup
    if _streams_before_hangup is not None:
        sys.stdout, sys.stderr = _streams_before_hangup
        _streams_before_hangup = None


def _describe_os_error(exc: OSError) -> str:
    """``PATH: strerror`` (both paths of a failed rename), as the OS reported it."""
    reason = exc.strerror or str(exc)
    if exc.filename is None:
        return reason
    where = str(exc.filename) if exc.filename2 is None else f"{exc.filename} -> {exc.filename2}"
    return f"{where}: {reason}"


def _silence_stdout() -> None:
    """Point stdout at devnull after its reader went away, so the interpreter's own flush at
    exit does not raise BrokenPipeError again (the recipe of Python's ``signal`` docs)."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):  # stdout is not a real file (captured, closed): nothing to do
        pass


def _name_bytes_else_escaped(exc: UnicodeError) -> tuple[str | bytes, int]:
    """Encoding error handler: Python's surrogate escapes of a file name's bytes are written
    as those bytes (as ``ls`` shows the name); anything else the stream cannot show is escaped."""
    if isinstance(exc, UnicodeEncodeError):
        chunk = exc.object[exc.start:exc.end]
        if all("\udc80" <= c <= "\udcff" for c in chunk):
            return bytes(ord(c) - 0xDC00 for c in chunk), exc.end
    return codecs.backslashreplace_errors(exc)


def _tolerant_output() -> None:
    """Let stdout and stderr print any path, by its own bytes on both: a name that is not UTF-8
    (or any non-ASCII one under a C locale) holds Python's surrogate escapes, which stdout
    refused with a traceback after the work was done and stderr spelt ``\\udcff``; and under
    a C locale without UTF-8 mode, so was any non-ASCII text."""
    codecs.register_error("trackmeter.name_bytes", _name_bytes_else_escaped)
    for stream in (sys.stdout, sys.stderr):
        reconfigure = getattr(stream, "reconfigure", None)
        if reconfigure is None:
            continue
        try:
            reconfigure(errors="trackmeter.name_bytes")
        except (AttributeError, LookupError, OSError, TypeError, ValueError):  # not a plain text stream
            pass


def _streams_even_if_closed() -> None:
    """A process started with its stdout or stderr closed (``>&-``, ``2>&-``) has None there,
    and every write, flush or ``isatty`` of it raised after the command's work was done
    ("'NoneType' object has no attribute 'flush'", exit 1). What it would have written goes
    nowhere, as its caller asked."""
    for name in ("stdout", "stderr"):
        if getattr(sys, name) is None:
            setattr(sys, name, open(os.devnull, "w", encoding="utf-8"))  # noqa: SIM115 - for the process's life


def main(argv: Sequence[str] | None = None) -> int:
    # Output still buffered is flushed here, where a closed pipe can be caught, not at exit
    # (where Python prints "Exception ignored ... BrokenPipeError"); argparse's --help
    # already ignores a closed stdout by itself.
    _streams_even_if_closed()
    _tolerant_output()
    try:
        code = _main(argv)
        sys.stdout.flush()
        return code
    except BrokenPipeError:
        _silence_stdout()
        return 1  # what the docs' recipe exits with: the output was cut short
    except KeyboardInterrupt:
        # A Ctrl-C before the command took over its signals (while the options are parsed and
        # its modules imported): nothing was begun, so one line, not a traceback.
        print("trackmeter: interrupted while starting; nothing was done", file=sys.stderr)
        return 130


def _warning_printer(command: str) -> Callable[..., None]:
    """``warnings.showwarning`` for a command: one line, ``trackmeter CMD: warning: ...``, as
    its errors are (the default shows the library's source path and line)."""

    def show(message: Warning | str, category: type[Warning], filename: str, lineno: int,
             file: TextIO | None = None, line: str | None = None) -> None:
        text = " ".join(str(message).split())
        try:
            print(f"trackmeter {command}: warning: {text}", file=file or sys.stderr)
        except (OSError, ValueError):  # stderr gone: a warning is not worth failing over
            pass

    return show


class _LogPrinter(logging.Handler):
    """The library's log lines of WARNING and above as the command's own, one line each:
    ``trackmeter CMD: error: ...`` (a recording that failed, a thread that did not stop).
    Without it they reached stderr bare, through Python's last-resort handler. A record with
    an exception keeps its traceback: that is a bug's, worth seeing whole."""

    def __init__(self, command: str) -> None:
        super().__init__(logging.WARNING)
        self.command = command

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = f"trackmeter {self.command}: {record.levelname.lower()}: {record.getMessage()}"
            if record.exc_info:
                text += "\n" + logging.Formatter().formatException(record.exc_info)
            print(text, file=sys.stderr)  # the stream of the moment (a test's capture, a hang-up's)
        except Exception:  # stderr gone, a message that does not format: not worth failing over
            pass


#: The loggers of the project's own packages (their modules log under ``__name__``).
PROJECT_LOGGERS = ("trackmeter", "console")


def _option_before(argv: list[str], value: str) -> str:
    """The option a stray ``value`` most likely belongs to: the last ``--option`` before it
    on the command line (``--at 1,2 -0.5,10``: ``--at``), else ``--OPTION``."""
    before = argv[: argv.index(value)] if value in argv else argv
    return next((a.split("=", 1)[0] for a in reversed(before) if a.startswith("--")), "--OPTION")


#: The metavars of options that name a file or folder (or a source, which may be one).
PATH_METAVARS = frozenset({"DIR", "FILE", "GLOB", "IMG", "MODEL", "RIG", "SPEC", "TUM_CSV_OR_SEQ", "TUM_CSV_OR_RUN_DIR"})


def _main(argv: Sequence[str] | None) -> int:
    parser = build_parser()
    _Parser.argv = list(sys.argv[1:] if argv is None else argv)
    args, unknown = parser.parse_known_args(argv)
    if unknown:
        negative = [u for u in unknown if re.match(r"-\.?\d", u)]
        hint = (f" (a value that starts with '-' must be joined to its own option, e.g. "
                f"{_option_before(_Parser.argv, negative[0])}={negative[0]})" if negative else "")
        parser.commands.get(args.command, parser).error(f"unrecognized arguments: {' '.join(unknown)}{hint}")
    if args.command is None:
        parser.error(f"a command is needed: {', '.join(COMMANDS)}")
    sub = parser.commands.get(args.command, parser)
    for action in sub._actions:
        value = getattr(args, action.dest, None)
        values = value if isinstance(value, list) else [value]
        if action.metavar in PATH_METAVARS and any(isinstance(v, str) and not v.strip() for v in values):
            # An empty path is the current folder to pathlib: `simulate --out ""` answered
            # that "." was not empty, `evaluate --truth ""` that "." held no ground truth.
            print(f"trackmeter {args.command}: error: argument {action.option_strings[-1]}: empty value "
                  "(see --help)", file=sys.stderr)
            return 2
    shown_before = warnings.showwarning
    warnings.showwarning = _warning_printer(args.command)
    log_printer = _LogPrinter(args.command)
    for name in PROJECT_LOGGERS:  # propagating still: a caller's handlers see them too
        logging.getLogger(name).addHandler(log_printer)
    # A service manager's stop (SIGTERM) ends a run as Ctrl-C does: threads joined, files
    # complete, the console's raised CPU priority given back (killed outright, none of that).
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous: dict[signal.Signals, Any] = {}  # the handlers found, of the signals taken over
    unraisable_hook = sys.unraisablehook
    if in_main_thread:
        for sig in STOP_SIGNALS:
            found = signal.getsignal(sig)
            if takes_over(sig, found):
                previous[sig] = found
                signal.signal(sig, _interrupt)
        sys.unraisablehook = _without_signal_race_reports(unraisable_hook)
    signals.note_taken(None)
    try:
        try:
            return int(_command_module(args.command).run(args) or 0)
        except Exception as exc:
            # The signal's KeyboardInterrupt, replaced on its way out: by a compiled module's
            # init (cv2, scipy) with its own "ImportError: initialization failed", or wrapped by
            # Python ("RuntimeError: Error calling __set_name__", caused by it). A Ctrl-C still.
            if signals.taken() is None or not (isinstance(exc, ImportError) or _caused_by_an_interrupt(exc)):
                raise
            raise signals.StopSignal from None
    except TrackmeterError as exc:
        print(f"trackmeter {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        raise  # stdout closed by its reader: not an error to report (see main)
    except MemoryError as exc:
        # Input that asks for more memory than the machine has (a huge image size, a border
        # of a million pixels): one line, as bad input is, not a traceback.
        print(f"trackmeter {args.command}: error: out of memory{f' ({exc})' if str(exc) else ''}: the input "
              "asks for more than this machine has", file=sys.stderr)
        return 2
    except OSError as exc:
        # A path the user named that cannot be written or read (unwritable --out, full disk):
        # their input or their system, not a bug, so one line like any other bad input.
        print(f"trackmeter {args.command}: error: {_describe_os_error(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        if in_main_thread:  # the command has stopped: a second Ctrl-C must not cut its last line
            _ignore_stop_signals(previous)
        # A command may say what it kept (KeyboardInterrupt("interrupted after ...")).
        print(f"trackmeter {args.command}: {exc.args[0] if exc.args else 'interrupted'}", file=sys.stderr)
        return 130
    finally:
        warnings.showwarning = shown_before
        for name in PROJECT_LOGGERS:
            logging.getLogger(name).removeHandler(log_printer)
        # The process's own command line (argv None) stays deaf to stop signals once its
        # command returned, until it exits: the command is done (its files complete), and a
        # signal now would kill it in the interpreter's shutdown (-SIGTERM, -SIGINT instead of
        # its exit code). SIG_IGN, not a Python handler that exits: the shutdown resets Python
        # handlers to the default, so a late signal would kill it all the same (measured: a
        # SIGHUP of a burst, exit -1). A caller passing argv gets its handlers back.
        if in_main_thread:
            if argv is None:
                _ignore_stop_signals(previous)
            else:
                for sig, handler in previous.items():
                    signal.signal(sig, signal.SIG_DFL if handler is None else handler)
                _restore_streams()  # a caller in the same process gets its own streams back
                sys.unraisablehook = unraisable_hook


def _ignore_stop_signals(taken_over: dict[signal.Signals, Any]) -> None:
    for sig in taken_over:
        signal.signal(sig, signal.SIG_IGN)


if __name__ == "__main__":
    sys.exit(main())
