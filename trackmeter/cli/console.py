"""Run the tracking pipeline with the operator console in the browser (viser).

Starts the acquisition and tracking threads on SPEC (default: the ``estec`` scenario, a
tumbling satellite mock-up rendered live) and a web console at http://HOST:PORT: the left
camera image (click to add a target, shift-, ctrl- or alt-click to remove the nearest), the
tracked patches, the 3D point cloud, the estimated pose, live plots and every control of the
pipeline.
Runs until Ctrl-C, then stops cleanly (threads joined, recording closed); the exit code is 1
when a recording lost frames (the writer failed or fell behind), as the last line says.

The console binds to 127.0.0.1 (this machine only) unless --host says otherwise; a port
already in use is an error (exit 2), never a silent move to another port.

examples:
  trackmeter console
  trackmeter console --source seq:runs/approach --port 8081
  trackmeter console --source sim:harsh_light --record runs/rec1
  trackmeter console --source runs/rec1 --model model.yaml --case b --auto 16
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING, Any

from trackmeter.cli.common import rig_help
from trackmeter.errors import counted

if TYPE_CHECKING:
    from trackmeter.pipeline.snapshot import Timings


def stop_line(t: Timings) -> str:
    """The console's last line: every frame read is tracked, dropped (the tracker was still busy
    with an earlier one) or, at most one, read and waiting for the tracker when it stopped."""
    waiting = t.frames_read - t.frames_processed - t.frames_dropped
    return (f"trackmeter console: stopped after {counted(t.frames_read, 'frame')} read, {t.frames_processed} tracked, "
            f"{t.frames_dropped} dropped" + (f", {waiting} read but not yet tracked when it stopped" if waiting else ""))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--source", default="sim", metavar="SPEC",
                        help="frame source: sim, sim:SCENARIO, seq:DIR, DIR, video:L,R, camera:I[,J] (default: sim)")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: this machine only)")
    parser.add_argument("--port", type=int, default=8080, help="port to listen on (default 8080)")
    parser.add_argument("--record", metavar="DIR", help="record the incoming stereo stream to this sequence folder")
    parser.add_argument("--rig", metavar="RIG",
                        help=rig_help("default: the source's own"))
    parser.add_argument("--model", metavar="MODEL",
                        help="model.yaml for case (b) (default: the source's own model; the page's Model > Load model "
                             "loads one later)")
    parser.add_argument("--case", choices=("a", "b", "c"), help="model case at start (default: b when the source carries a model, else a; in case b a "
                             "target binds to a model point by id: Model > Next click is, in the page)")
    parser.add_argument("--auto", type=int, metavar="N",
                        help="start with automatic selection on, keeping N targets alive (the page's Automatic "
                             "selection; default: off, the operator clicks targets)")
    parser.add_argument("--publish-hz", type=float, default=12.0, metavar="HZ", help="browser update rate, Hz (default 12)")
    parser.add_argument("--cpu-nice", type=int, default=DEFAULT_CPU_NICE, metavar="N",
                        help=f"run tracking at this CPU priority, -20..19 (default {DEFAULT_CPU_NICE}: leave it alone). "
                             f"A negative N (e.g. -10) puts tracking ahead of other programs: for a tracking machine "
                             f"whose browser is elsewhere; a browser on the same, busy machine may then not get the CPU "
                             f"to load the page. Needs root or CAP_SYS_NICE, else it says so and runs as is")


#: 0: a raised priority starved a browser on the same two cores whenever the host was slow
#: (docs/results.md, "Why the browser took a whole core, and --cpu-nice"); the operator asks for it.
DEFAULT_CPU_NICE = 0


def run(args: argparse.Namespace) -> int:
    from trackmeter.cli.common import load_config_from_args
    from trackmeter.errors import TrackmeterError

    if not 1.0 <= args.publish_hz <= 30.0:
        raise TrackmeterError(f"--publish-hz must be 1-30, got {args.publish_hz}")
    if not -20 <= args.cpu_nice <= 19:
        raise TrackmeterError(f"--cpu-nice must be -20..19, got {args.cpu_nice}")
    config = load_config_from_args(args)
    most = config.tracker.max_targets
    if args.auto is not None and not 1 <= args.auto <= most:
        raise TrackmeterError(f"--auto must be in [1, {most}] (tracker.max_targets), got {args.auto}")
    # The command line is the one place where the library meets the console (viser).
    from console.server import check_port_free

    check_port_free(args.host, args.port)  # before the (slow) source opens
    if args.record is not None:
        from trackmeter.data.sequence import check_record_directory

        check_record_directory(args.record)
    from trackmeter.priority import raise_cpu_priority, restore_cpu_priority

    priority = None
    if args.cpu_nice:
        # Before the source opens: its threads and the simulator's render worker inherit it.
        priority = raise_cpu_priority(args.cpu_nice)
    try:
        return _serve(args, config, priority.message if priority is not None else None)
    finally:
        if priority is not None:
            restore_cpu_priority(priority)  # the autogroup is the terminal session's: give it back


def _serve(args: argparse.Namespace, config: Any, priority_note: str | None = None) -> int:
    from trackmeter.cli.common import open_source_with_rig
    from trackmeter.pipeline.pipeline import source_said_by_caller

    if sys.stderr.isatty():  # progress while a slow source opens; a bad one is then the only line
        print(f"trackmeter console: opening {args.source} ...", file=sys.stderr, flush=True)
    # --rig is read once the source is open (it may take its size from the source's frames),
    # and frames of another size than the rig's are refused before the console starts.
    # Cases (a) and (c) need no model: unless case (b) is asked for, a source's model that
    # cannot be read is warned about and the console runs without it.
    model = None
    if args.model:
        from trackmeter.data.model import load_model

        model = load_model(args.model)  # before the (slow) source opens
    source = open_source_with_rig(args.source, args.rig, realtime=True, loop=True, own_model=model is None,
                                  model_optional=args.case != "b")
    with source_said_by_caller():  # serve_forever says a failing source, once, as the status line shows it
        return _serve_source(args, config, source, model, priority_note)


def _serve_source(args: argparse.Namespace, config: Any, source: Any, model: Any, priority_note: str | None) -> int:
    from console.server import serve_forever, start_console
    from trackmeter.errors import TrackmeterError
    from trackmeter.pipeline.engine import Engine
    from trackmeter.pipeline.snapshot import SetAuto

    try:
        if source.rig is None:
            raise TrackmeterError(f"source {args.source} carries no stereo rig: give one with --rig")
        if args.case == "b" and model is None and source.model is None:
            raise TrackmeterError(f"case (b) needs an a-priori model: give --model (source {args.source} carries none)")
        engine = Engine(config, source.rig, model=model if model is not None else source.model, case=args.case,
                        rate_hz=source.rate_hz)
        running = start_console(source, engine, host=args.host, port=args.port, record_dir=args.record,
                                source_label=args.source, publish_hz=args.publish_hz,
                                patch_px=config.tracker.patch_size)
    except BaseException:
        source.close()
        raise
    if args.auto is not None:
        running.pipeline.submit(SetAuto(True, args.auto, None))
    if priority_note:
        print(f"trackmeter console: {priority_note}", file=sys.stderr, flush=True)
    print(f"TV-Trackmeter console: {running.url}   (Ctrl-C to stop)", flush=True)
    serve_forever(running)
    # The totals: the last snapshot may lag a frame read.
    print(stop_line(running.pipeline.timings()), file=sys.stderr)
    cut_short = False
    for rec in running.pipeline.recordings():  # every one, from --record and from the panel
        print(f"trackmeter console: {rec.summary()}", file=sys.stderr)
        cut_short = cut_short or bool(rec.error or rec.frames_dropped or rec.frames_lost)
    return 1 if cut_short else 0  # a script that records must be able to tell a recording cut short
