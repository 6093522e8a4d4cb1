"""Track targets and estimate pose and velocities, headless, into a run folder.

Runs the pipeline (acquisition and tracking threads) without the console on any source, with
targets from --target and/or automatic selection (--auto N), and writes the run directory:
trajectory.tum (valid poses), states.csv (one row per frame), pose_covariance.csv (each valid
pose's 6x6 covariance), targets.csv, run.yaml. Recorded and simulated sources are processed
frame by frame as fast as possible (no frame dropped); cameras run live. Ends at the end of
the source or on Ctrl-C, with complete files either way.

Model cases (paper section 2.C):
  a  no model: the body frame from three tracked points (x from the first toward the second,
     xy-plane through the third; origin at their centroid); redundant points carry it when one
     is lost
  b  a-priori model (--model, or the source's own model.yaml): targets named by model point
     id (--target ID=U,V) bind to it; automatic targets join it once the pose is known.
     Chosen by default only when a target is bound to a model point (--target ID=U,V or
     --select-model-points): without one the pose can never be known, so a model alone runs (a)
  c  model acquired while the object is held still (pose.still_time_s), output in that frame

Examples (the simulator's 60 s; --max-frames 250 tracks its first 10 s):
  trackmeter track --source sim --auto 16 --out runs/estec_a
  trackmeter track --source sim --target bus_pxmypz=329.5,159.8 bus_pxmymz=275.4,481.0 \\
      bus_mxmypz=211.9,87.7 bus_mxmymz=175.4,358.3 wing_north_c3=571.9,233.7 --auto 16 --out runs/b
    (five of the mock-up's corners where estec's first frame shows them: case (b) needs three
    measured at once, and a corner's patch is often lost as the faces around it turn)
  trackmeter track --source sim --case b --select-model-points --auto 16 --out runs/estec_b
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from typing import TYPE_CHECKING, Any, Callable, NotRequired, TypedDict, cast

from trackmeter.cli.common import parse_uv, plain_progress_due, rig_help, source_warning_since
from trackmeter.errors import TrackmeterError, counted

if TYPE_CHECKING:
    from trackmeter.pipeline.snapshot import ModelCase, Snapshot
    from trackmeter.pipeline.views import SwappedViewsWatch
    from trackmeter.sources.base import Source, StereoFrame


#: The summary's reason for an invalid first frame (its targets start on it, tracked from the next).
FIRST_FRAME_REASON = "the first frame (the targets set on it are tracked from the next frame)"

#: --select-model-points on a source whose truth starts after its first frame.
TRUTH_LATER = "the first frame has no ground truth: the model points are selected at the first frame that has it"

#: How many invalid-pose reasons the closing summary prints (run.yaml keeps them all).
SUMMARY_REASONS = 5

_COUNTDOWN = re.compile(r"\(\d+(?:\.\d+)? s left\)")


def summary_reason(reason: str) -> str:
    """``reason`` as the run's summary counts it: a countdown ("hold still (1.9 s left)", case
    (c)'s acquisition) is one reason whatever its seconds, not one per tenth of a second."""
    return _COUNTDOWN.sub("(counting down)", reason)


def _option_of(command: Any, auto_label: str | None = None) -> str:
    """The command-line option a command came from, as the user typed it (for its warnings);
    ``auto_label`` names automatic selection started by the configuration instead."""
    from trackmeter.pipeline.engine import SelectModelPoints
    from trackmeter.pipeline.snapshot import SelectPoint, SetAuto

    if isinstance(command, SelectPoint):
        named = f"{command.target_id}=" if command.target_id else ""
        return f"--target {named}{command.u:g},{command.v:g}"
    if isinstance(command, SelectModelPoints):
        return "--select-model-points"
    if isinstance(command, SetAuto):
        return auto_label or f"--auto {command.count}"
    return type(command).__name__


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--source", required=True, metavar="SPEC",
                        help="sim, sim:SCENARIO, seq:DIR or DIR, video:LEFT,RIGHT, camera:I[,J]")
    parser.add_argument("--rig", metavar="RIG",
                        help=rig_help("default: the source's own"))
    parser.add_argument("--model", metavar="MODEL",
                        help="model.yaml for case (b) (default: the source's own model); unused in cases (a) and (c)")
    parser.add_argument("--target", action="extend", nargs="+", default=[], metavar="[ID=]U,V",
                        help="targets at left-image pixels U,V of the first frame, optionally named "
                        "(several may follow one --target, or repeat it)")
    parser.add_argument("--auto", type=int, metavar="N",
                        help="keep N targets alive, topping up with automatically selected ones (the --target and "
                             "model points count among the N: 3 --target points with --auto 16 add up to 13); model "
                             "points re-locked through the pose (paper 2.D) come on top of them (grown ones while fewer "
                             "than tracker.max_targets less pose.operator_reserve_targets are tracked: 24 by "
                             "default); without it, tracker.auto: true in a --config keeps features.count")
    parser.add_argument("--select-model-points", action="store_true",
                        help="case (b) on a source with ground truth: simulate the operator clicking every model "
                             "point visible in the first frame (at its true projection), and again whenever the "
                             "pose has been invalid for pose.operator_reselect_s")
    parser.add_argument("--case", choices=("a", "b", "c"),
                        help="model case (default: b when a model is given or carried by the source AND a target is "
                             "bound to a model point with --target ID=U,V or --select-model-points; else a, with a "
                             "note on stderr when a model was there)")
    parser.add_argument("--max-frames", type=int, metavar="N", help="stop after N frames")
    parser.add_argument("--out", required=True, metavar="DIR", help="run folder to write")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an earlier run in --out (and its report) once the new run has tracked: one "
                             "that ends with nothing to track or no frame gives the earlier run back")


def parse_target(text: str) -> tuple[str | None, tuple[float, float]]:
    """``"[ID=]U,V"`` → ``(id or None, (u, v))``."""
    name, sep, rest = text.partition("=")
    if sep and not name.strip():
        raise TrackmeterError(f"--target: empty id in {text!r} (expected ID=U,V)")
    try:
        uv = parse_uv(rest if sep else text)
    except TrackmeterError:  # quoted whole, as typed (not just what follows the '=')
        raise TrackmeterError(f"--target {text!r}: expected [ID=]U,V, a pixel's U,V two finite numbers") from None
    return (name.strip() if sep else None), uv


class _Limited:
    """A source that ends after ``n`` frames (``--max-frames``); everything else delegates."""

    def __init__(self, source: Any, n: int) -> None:
        self._source = source
        self._left = n
        self.rig = source.rig
        self.rate_hz = source.rate_hz

    def __getattr__(self, name: str) -> Any:
        # What the pipeline asks of some sources only (resume, model, warning, ...): the wrapped
        # source's, or the AttributeError it would give. Only names not set above reach here;
        # "_source" itself does before __init__ (copy, pickle), and must not recurse; the
        # dunders (__deepcopy__, __len__, ...) are the wrapper's, not the source's.
        if name == "_source" or name.startswith("__"):
            raise AttributeError(name)
        return getattr(self._source, name)

    def read(self) -> StereoFrame | None:
        if self._left <= 0:
            return None
        self._left -= 1
        return self._source.read()

    def restart(self) -> None:
        self._source.restart()

    def close(self) -> None:
        self._source.close()


class _RunState(TypedDict):
    """What ``_run``'s snapshot and reply callbacks and its closing lines share."""

    pending: Snapshot | None  # the snapshot whose frame is written once the next arrives (never frameless)
    invalid: dict[str, int]  # frames with an invalid pose, by summary_reason
    last_draw: float  # time.monotonic() of the last progress line
    t0: float  # time.monotonic() at the start
    status: str | None  # the last snapshot's source_status
    most_auto: NotRequired[int]  # the most automatic targets measured at once
    first_index: NotRequired[int]
    first_t_s: NotRequired[float]
    write_error: NotRequired[str]  # why the files could not be written
    said_late: NotRequired[bool]
    nothing: NotRequired[bool]  # nothing will ever be tracked
    views: NotRequired[SwappedViewsWatch]


def _total_frames(source: Any, max_frames: int | None) -> int | None:
    try:
        n = len(source)
    except TypeError:
        n = None
    if max_frames is not None:
        n = max_frames if n is None else min(n, max_frames)
    return n


def run(args: argparse.Namespace) -> int:
    started: list[bool] = []  # the run folder was made
    try:
        return _run(args, started)
    except KeyboardInterrupt as exc:
        if exc.args or started:  # said what it kept
            raise
        # Opening a source, reading a model and loading the compiled fits take seconds: an
        # interrupt then leaves no folder, and the user should not go looking for one.
        raise KeyboardInterrupt(f"interrupted while starting; nothing was written to {args.out}") from None


def _run(args: argparse.Namespace, started: list[bool]) -> int:
    from trackmeter.cli.common import load_config_from_args, open_source_with_rig
    from trackmeter.core.matching import inside_image
    from trackmeter.data.config import config_to_dict
    from trackmeter.data.model import load_model
    from trackmeter.data.rundir import RunWriter, check_run_directory
    from trackmeter.pipeline.engine import NEEDS_TRUTH, Engine, SelectModelPoints
    from trackmeter.pipeline.pipeline import NOT_APPLIED, STOPPED, interrupts_deferred, run_headless, source_said_by_caller
    from trackmeter.pipeline.snapshot import SelectPoint, SetAuto, Snapshot

    config = load_config_from_args(args)
    targets = [parse_target(t) for t in args.target]
    most = config.tracker.max_targets
    if args.auto is not None and not 1 <= args.auto <= most:
        raise TrackmeterError(f"--auto must be in [1, {most}] (tracker.max_targets), got {args.auto}")
    # `tracker.auto: true` in a --config starts automatic selection as the console does, keeping
    # features.count targets (at most the tracker's); --auto N says how many either way.
    auto = args.auto if args.auto is not None else (min(config.features.count, most) if config.tracker.auto else None)
    auto_label = None if args.auto is not None or auto is None else (
        f"tracker.auto (features.count {config.features.count}"
        + (f", capped at tracker.max_targets {most})" if config.features.count > most else ")"))
    if auto_label and config.features.count > most:
        print(f"trackmeter track: note: tracker.auto keeps {most} targets: features.count ({config.features.count}) "
              f"is more than tracker.max_targets holds", file=sys.stderr)
    named = [i for i, _ in targets if i is not None]
    twice = sorted({i for i in named if named.count(i) > 1})
    if twice:  # known before the source opens: not a warning after the first frame
        raise TrackmeterError(f"--target id {twice[0]!r} given twice: each target's id names one point")
    if len(targets) > most:
        raise TrackmeterError(f"{len(targets)} --target points but at most {counted(most, 'target')} "
                              f"{'is' if most == 1 else 'are'} tracked (tracker.max_targets)")
    if args.max_frames is not None and args.max_frames < 1:
        raise TrackmeterError(f"--max-frames must be at least 1, got {args.max_frames}")
    check_run_directory(args.out, args.overwrite)  # before the source: its notes would come first
    model = load_model(args.model) if args.model else None

    # The rig is read once the source is open (a rig file may need its frame size) and checked
    # against its frames here, before the run folder is made.
    # The folder's own model only when it may be used: not with --model, nor in case (a) or (c);
    # and when the default case would run (a) anyway (no target bound to it), a broken one is
    # only warned about.
    binds = any(i for i, _ in targets) or args.select_model_points
    source = open_source_with_rig(args.source, args.rig, realtime=args.source.startswith("camera"),
                                  own_model=model is None and args.case in (None, "b"),
                                  model_optional=args.case is None and not binds)
    warning_at_open = getattr(source, "warning", None)  # shown by the source already
    try:
        rig = source.rig
        if rig is None:
            raise TrackmeterError(f"source {args.source!r} carries no stereo rig: give --rig")
        # A pixel off the image is a typing slip, known once the rig is: one line before the run,
        # not a refusal after its first frame (with the case's note before it).
        width, height = rig.image_size
        for text, (_, (u, v)) in zip(args.target, targets):
            if not inside_image(u, v, rig.image_size):
                raise TrackmeterError(f"--target {text}: outside the {width}x{height} image (U from -0.5 to "
                                      f"{width - 0.5:g}, V from -0.5 to {height - 0.5:g}: pixel centres are whole "
                                      "numbers, 0 the first)")
        # After the inputs are read: a wrong path is the error to fix first.
        if not targets and auto is None and not args.select_model_points:
            raise TrackmeterError("nothing to track: give --target [ID=]U,V, --auto N and/or --select-model-points")
        if model is None and args.case in (None, "b"):
            model = source.model
        model_label = args.model or ("source" if model is not None else None)
        # Case (b) needs targets bound to model point ids: without one its pose could never be
        # valid, so a model alone does not choose it.
        case: ModelCase = args.case or ("b" if model is not None and binds else "a")
        if args.case:
            case_reason = "--case"
        elif case == "b":
            case_reason = "default: a model and targets bound to model points"
        elif model is not None:
            case_reason = "default: a model but no target bound to a model point"
            print(f"trackmeter track: note: running case (a) without the model ({model_label}): no target is bound "
                  f"to a model point; bind them with --target ID=U,V or --select-model-points, or force --case b",
                  file=sys.stderr)
        else:
            case_reason = "default: no model"
        if case == "b":
            if model is None:
                raise TrackmeterError("case (b) needs a model: give --model (the source carries none)")
            unknown = [i for i, _ in targets if i is not None and i not in model.ids]
            if unknown:
                raise TrackmeterError(f"--target id {unknown[0]!r} is not in the model (ids: {', '.join(model.ids[:8])}"
                                      f"{', ...' if len(model.ids) > 8 else ''})")
            if not binds:
                print("trackmeter track: warning: case (b) but no model point is selected: the pose stays invalid "
                      "until 3 model points are tracked (give --target ID=U,V, or --select-model-points on a "
                      "source with ground truth: a simulation, or a recording with its truth)", file=sys.stderr)
        if args.select_model_points and case != "b":
            raise TrackmeterError("--select-model-points needs case (b) and a model")
        engine = Engine(config, rig, model if case == "b" else None, case, rate_hz=source.rate_hz or 25.0,
                        live_errors=False)  # the run directory holds no errors: evaluate makes them
        # The named targets first: an unnamed one is given the next free id (p1, p2, ...), which
        # must not take a name given later on the command line.
        commands: list[Any] = [SelectPoint(uv[0], uv[1], tid) for tid, uv in sorted(targets, key=lambda x: x[0] is None)]
        if args.select_model_points:
            commands.insert(0, SelectModelPoints(repeat=True))
        if auto is not None:
            commands.append(SetAuto(True, auto, None))
        total = _total_frames(source, args.max_frames)
        # Not a Source subclass, but it answers as one: what it does not set, the source does.
        feed = cast("Source", _Limited(source, args.max_frames)) if args.max_frames else source
        source_info = {
            "spec": args.source,
            "rig": args.rig or _source_rig_label(source, rig),
            # from the frames' median interval: 24.99999999999998 says no more than 25 does
            "rate_hz": None if source.rate_hz is None else float(f"{source.rate_hz:.9g}"),
            "model": model_label if case == "b" else None,  # the model used, None when none was
            "model_available": model_label,  # given or carried, used or not
            "case": case,
            "case_reason": case_reason,
            "targets": [f"{i + '=' if i else ''}{u:g},{v:g}" for i, (u, v) in targets],
            "auto": auto,
            "select_model_points": bool(args.select_model_points),
            **_source_identity(source),
        }
        started.append(True)  # from here on the folder may exist (RunWriter makes it first)
        writer = RunWriter(args.out, config_to_dict(config), source_info, overwrite=args.overwrite)
        tty = sys.stderr.isatty()
        t0 = time.monotonic()
        state: _RunState = {"pending": None, "invalid": {}, "last_draw": 0.0 if tty else t0, "t0": t0, "status": None}

        def flush_pending() -> None:
            snap = state["pending"]
            if snap is None:
                return
            state["pending"] = None
            assert snap.frame is not None  # on_snapshot keeps none without a frame
            writer.write_frame(snap.frame.t_s, snap.targets, snap.pose, snap.timings.latency_ms)
            alive_auto = sum(1 for t in snap.targets if t.origin == "auto" and t.measured)
            state["most_auto"] = max(state.get("most_auto", 0), alive_auto)
            first = state.setdefault("first_index", snap.frame.index) == snap.frame.index
            if not snap.pose.valid:
                # The first frame's pose was estimated before the commands (--target, --auto,
                # --select-model-points) acted on it: its reason would ask for what they did next.
                reason = FIRST_FRAME_REASON if first else summary_reason(snap.pose.reason or "?")
                state["invalid"][reason] = state["invalid"].get(reason, 0) + 1

        def on_snapshot(snap: Snapshot) -> bool:
            """Write the frame before ``snap``'s; True (stop the run) when its files cannot be written."""
            state["status"] = snap.source_status
            frame = snap.frame
            if frame is None or state.get("write_error"):
                return bool(state.get("write_error"))
            state.setdefault("first_t_s", float(frame.t_s))
            # A frame's row is written once the next frame arrives (or at the end): the
            # commands act on frame 0 after it was processed (--target, --auto), and the
            # snapshot they publish, not the first one, holds frame 0's targets.
            pending = state["pending"]
            if pending is not None and cast("StereoFrame", pending.frame).index != frame.index:
                try:
                    flush_pending()
                except TrackmeterError as exc:  # a full disk: the frames before are whole
                    state["write_error"] = str(exc)
                    return True
            state["pending"] = snap
            _check_views(state, rig, frame, tty)
            now = time.monotonic()
            if now - state["last_draw"] > 0.25 if tty else plain_progress_due(state["last_draw"], now):
                state["last_draw"] = now
                n = writer.frames
                of = f"/{total}" if total else ""
                fps = n / max(now - state["t0"], 1e-9)
                ok = "valid" if snap.pose.valid else "INVALID"
                line = (f"track: frame {n}{of}  {fps:5.1f} fps  pose {ok:7s}  "
                        f"targets {sum(t.measured for t in snap.targets):2d}/{len(snap.targets):2d}")
                sys.stderr.write(f"\r{line}   " if tty else f"{line}\n")
                sys.stderr.flush()
            return False

        # Without --auto only the --target points and --select-model-points can start a target:
        # when the tracker refuses every point, and the model points cannot be selected at all
        # (no ground truth), nothing will ever be tracked and playing the rest is time lost.
        said: set[int] = set()  # the commands whose refusal was shown
        for_good: set[int] = set()  # ... and could never succeed later

        def on_replies(replies: list[Any]) -> bool:
            """Each refusal shown as soon as frame 0 gave it, not after the whole run."""
            first_t, start_t = state.get("first_t_s"), getattr(source, "start_t_s", None)
            if (targets and not state.get("said_late") and isinstance(first_t, float) and isinstance(start_t, float)
                    and first_t > start_t + 1e-9):
                # The pixels were chosen on the source's first frame; it did not play.
                state["said_late"] = True
                if tty:
                    sys.stderr.write("\r\033[K")
                print(f"trackmeter track: note: --target: the pixels were placed on the first frame that played, "
                      f"t = {first_t:.3f} s; the pair(s) before it were skipped (said at the end)", file=sys.stderr)
            for k, (command, reply) in enumerate(zip(commands, replies)):
                if not reply.ok and reply.message not in (STOPPED, NOT_APPLIED):
                    if tty:
                        sys.stderr.write("\r\033[K")  # over the progress line
                    if reply.message == NEEDS_TRUTH and source.has_truth:
                        # the engine selects them at the first frame with truth
                        print(f"trackmeter track: note: {_option_of(command, auto_label)}: {TRUTH_LATER}", file=sys.stderr)
                    else:
                        print(f"trackmeter track: warning: {_option_of(command, auto_label)}: {reply.message}", file=sys.stderr)
                    said.add(k)
                    # A source with truth from a later frame on may still let the points be selected.
                    if isinstance(command, SelectPoint) or (reply.message == NEEDS_TRUTH and not source.has_truth):
                        for_good.add(k)
                elif reply.ok and reply.moved_px > 0 and k not in said:
                    # Put on a trackable corner near the pixel given, not on it: say where.
                    if tty:
                        sys.stderr.write("\r\033[K")
                    print(f"trackmeter track: note: {_option_of(command, auto_label)}: {reply.message}", file=sys.stderr)
                    said.add(k)
            starters = [k for k, c in enumerate(commands) if isinstance(c, (SelectPoint, SelectModelPoints))]
            state["nothing"] = auto is None and all(k in for_good for k in starters)
            return bool(state["nothing"])

        status = "complete"

        def interrupted() -> str:
            if writer.kept_earlier_run:
                return f"interrupted before the first frame was tracked; the earlier run in {writer.directory} is kept"
            return f"interrupted after {writer.frames} frames; files in {writer.directory} are complete"

        try:
            # A failing source is said once, below, with the run's status (not also by the log).
            with source_said_by_caller():
                last, replies = run_headless(feed, engine, on_snapshot=on_snapshot, commands=commands,
                                             realtime=args.source.startswith("camera"), rig=rig, on_replies=on_replies)
        except KeyboardInterrupt:
            # The one line main prints for an interrupt, with what the user needs to know.
            with interrupts_deferred(interrupted):  # a second Ctrl-C must not leave the files half-closed
                _finish_writing(writer, flush_pending, state)
                writer.close("interrupted", _summary(engine, writer, state))
                if tty:
                    sys.stderr.write("\n")
                raise KeyboardInterrupt(interrupted()) from None
        # Past here the run is written out: a Ctrl-C waits until run.yaml has its final status.
        with interrupts_deferred(interrupted):
            _finish_writing(writer, flush_pending, state)
            if tty:
                sys.stderr.write("\n")
            if state.get("write_error"):
                try:
                    writer.close("write failed", _summary(engine, writer, state))
                    kept = (f"; run.yaml says so, and the {counted(writer.frames, 'frame')} before are whole in "
                            f"{writer.directory}")
                    if writer.earlier_run_kept_in is not None:
                        kept += f"; the earlier run it was to replace is kept in {writer.earlier_run_kept_in}"
                except TrackmeterError:
                    kept = "" if writer.folder_lost else (
                        f"; run.yaml could not be updated (it says running); the {counted(writer.frames, 'frame')} "
                        f"before are whole in {writer.directory}")
                raise TrackmeterError(f"{state['write_error']}: run stopped{kept}")
            src_status = last.source_status or state["status"]
            summary = _summary(engine, writer, state)
            summary["source_status"] = src_status
            summary["dropped_frames"] = last.timings.frames_dropped
            # What the source skipped while playing (unreadable images) is only known now.
            source_warning = getattr(source, "warning", None)
            if source_warning:
                summary["source_warning"] = source_warning
            if writer.frames == 0:
                # Every image unreadable, an empty video: one line (the commands that waited for a
                # first frame need no warning of their own), and run.yaml says so too.
                writer.close("no frame", summary)
                detail = f": {src_status}" if src_status and src_status != "ended" else ""
                detail += f"; {source_warning}" if source_warning else ""
                kept = (f"the earlier run in {writer.directory} is kept" if writer.kept_earlier_run
                        else f"{writer.directory} holds an empty run")
                raise TrackmeterError(f"source {args.source!r} delivered no frame{detail} (nothing tracked; {kept})")
            new_warning = source_warning_since(source, warning_at_open)
            if new_warning:
                print(f"trackmeter track: warning: {new_warning}", file=sys.stderr)
            for k, (command, reply) in enumerate(zip(commands, replies)):
                if not reply.ok and k not in said:
                    print(f"trackmeter track: warning: {_option_of(command, auto_label)}: {reply.message}", file=sys.stderr)
                if (isinstance(command, SelectModelPoints) and reply.message == NEEDS_TRUTH and source.has_truth
                        and engine.stats.operator_reselections == 0):
                    # The note said they would be selected at the first frame with truth: none came.
                    print("trackmeter track: warning: --select-model-points: no frame of the run had ground truth: "
                          "no model point was selected", file=sys.stderr)
            if state.get("nothing"):
                writer.close("nothing to track", summary)
                why = " and ".join((["every --target was refused on the first frame"] if targets else [])
                                   + (["the source has no ground truth to select model points with"]
                                      if args.select_model_points else []))
                kept = (f"the earlier run in {writer.directory} is kept" if writer.kept_earlier_run
                        else f"{writer.directory} holds {'them' if writer.frames != 1 else 'it'}")
                raise TrackmeterError(f"nothing to track: {why}, and there is no --auto (stopped after "
                                      f"{counted(writer.frames, 'frame')}; {kept})")
            if src_status and src_status != "ended":
                status = "source failed"
                print(f"trackmeter track: source stopped: {src_status}", file=sys.stderr)
            try:
                writer.close(status, summary)
            except TrackmeterError as exc:
                if writer.folder_lost:  # said already: the frames went with the folder
                    raise
                raise TrackmeterError(f"{exc}: run.yaml could not be updated (it says running); the "
                                      f"{counted(writer.frames, 'frame')} {'is' if writer.frames == 1 else 'are'} "
                                      f"whole in {writer.directory}") from None
            elapsed = time.monotonic() - state["t0"]
            print(f"{counted(writer.frames, 'frame')} in {elapsed:.1f} s ({writer.frames / max(elapsed, 1e-9):.1f} fps), "
                  f"{counted(writer.valid_frames, 'valid pose')}"
                  + (f" ({writer.coasted_frames} coasted)" if writer.coasted_frames else "")
                  + (f", {writer.rates_pending_frames} of them before the rates were known (states.csv valid 0)"
                     if writer.rates_pending_frames else "")
                  + f", case ({case}) -> {writer.directory}")
            ranked = sorted(state["invalid"].items(), key=lambda kv: -kv[1])
            for reason, count in ranked[:SUMMARY_REASONS]:
                print(f"  invalid in {counted(count, 'frame')}: {reason}")
            if len(ranked) > SUMMARY_REASONS:
                rest = sum(count for _, count in ranked[SUMMARY_REASONS:])
                print(f"  invalid in {counted(rest, 'more frame')} for "
                      f"{counted(len(ranked) - SUMMARY_REASONS, 'other reason')}: run.yaml lists them all")
            gained = engine.stats.frames_gained
            if gained:
                print(f"trackmeter track: note: {counted(gained, 'frame')} underexposed (the left image's brightest "
                      f"pixels below grey {engine.exposure_params.reference_grey:g}), tracked at a gain of up to "
                      f"{engine.stats.largest_gain:.2f} (config section exposure)", file=sys.stderr)
            short = _auto_shortfall(engine.tracker, auto, state.get("most_auto", 0), auto_label) if auto else None
            if short:
                print(f"trackmeter track: warning: {short}", file=sys.stderr)
            return 0 if status == "complete" else 2
    finally:
        source.close()


def _source_identity(source: Any) -> dict[str, str]:
    """run.yaml's record of which sequence (folder, scenario) the run saw, for evaluate to tell a
    truth of another one: a sequence folder's resolved path and scenario, the simulator's scenario,
    and where known the fingerprint of the scenario's motion (``motion``: two scenario files
    of one name are told apart by it)."""
    from trackmeter.data.sequence import sequence_identity, sequence_motion_digest

    index = getattr(source, "index", None)
    if index is not None and getattr(index, "root", None) is not None:
        folder, scenario = sequence_identity(index.root)
        motion = sequence_motion_digest(index.root)
        return {"folder": str(folder), **({"scenario": scenario} if scenario else {}), **({"motion": motion} if motion else {})}
    sim_scenario = getattr(source, "scenario", None)
    scenario = getattr(sim_scenario, "name", None)
    if not isinstance(scenario, str):
        return {}
    digest = getattr(sim_scenario, "motion_digest", None)
    motion = digest() if callable(digest) else None
    return {"scenario": scenario, **({"motion": motion} if motion else {})}


def _source_rig_label(source: Any, rig: Any) -> str:
    """run.yaml's word for the rig a source carries: its file where the source read one (a
    sequence folder's: one with both DIR/rig.yaml and DIR/mav0/rig.yaml said only "the
    source's", an outside probe), else its name (a scenario's preset)."""
    index = getattr(source, "index", None)
    rig_file = getattr(index, "rig_file", None)
    if rig_file is not None:
        return f"the source's ({rig_file})"
    return f"the source's ({rig.name})" if rig.name and rig.name != "rig" else "the source's"


def _check_views(state: _RunState, rig: Any, frame: Any, tty: bool) -> None:
    """Warn once when the first frames' left and right images look swapped, or are one image
    (:class:`~trackmeter.pipeline.views.SwappedViewsWatch`)."""
    from trackmeter.pipeline.views import SwappedViewsWatch

    if "views" not in state:  # setdefault would build a watch on every frame
        state["views"] = SwappedViewsWatch(rig)
    watch = state["views"]
    problem = watch.check(frame.left, frame.right)
    if problem:
        if tty:
            sys.stderr.write("\r\033[K")
        print(f"trackmeter track: warning: {problem}", file=sys.stderr)


def _auto_shortfall(tracker: Any, asked: int, most_at_once: int, auto_label: str | None = None) -> str | None:
    """One line when --auto (or ``auto_label``: the configuration's tracker.auto) started no
    target in the whole run, or never had as many as ``asked`` measured at once, with its
    candidates' refusal reasons (the images too dark, too small a target); None otherwise."""
    stats, refusals = getattr(tracker, "stats", None), getattr(tracker, "auto_refusals", None)
    if not isinstance(stats, dict) or not refusals or most_at_once >= asked:
        return None
    reasons = ", ".join(f"{reason} ({count})" for reason, count in refusals.most_common(3))
    if not stats.get("auto_added", 1):
        return f"{auto_label or '--auto'} started no target: its candidates were refused: {reasons}"
    return (f"{auto_label or f'--auto {asked}'}: at most {counted(most_at_once, 'automatic target')} at once; its "
            f"other candidates were refused: {reasons}")


def _finish_writing(writer: Any, flush_pending: Callable[[], None], state: _RunState) -> None:
    """Write the frame still pending, unless the files already failed (then it is dropped)."""
    if state.get("write_error"):
        return
    try:
        flush_pending()
    except TrackmeterError as exc:
        state["write_error"] = str(exc)


def _summary(engine: Any, writer: Any, state: _RunState) -> dict[str, Any]:
    import dataclasses

    out: dict[str, Any] = {"engine": dataclasses.asdict(engine.stats)}
    stats = getattr(engine.tracker, "stats", None)
    if isinstance(stats, dict):
        out["tracker"] = {k: int(v) for k, v in stats.items()}
    out["invalid_reasons"] = dict(state["invalid"])
    out["elapsed_s"] = round(time.monotonic() - state["t0"], 3)
    return out


