"""Render a tumbling-satellite scenario to a stereo sequence folder (EuRoC layout).

The folder holds the left and right images (cam0/, cam1/ with data.csv), rig.yaml,
groundtruth.tum, groundtruth.csv, model.yaml (the mock-up's salient points) and scenario.yaml
(the scenario as run). It is written into DIR.partial and renamed to DIR only when complete,
so DIR never holds half a sequence; an existing non-empty DIR is refused (--overwrite replaces
a sequence this command wrote, once the new one is complete).

examples:
  trackmeter simulate --out /tmp/estec                      (the estec scenario, 60 s)
  trackmeter simulate --scenario harsh_light --duration 5 --out /tmp/harsh
  trackmeter simulate --scenario my_scenario.yaml --out /tmp/mine
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import warnings
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", metavar="FILE", default="estec",
                        help="scenario file, or a name in config/scenarios/ (default: estec)")
    parser.add_argument("--duration", metavar="S", type=float, default=None,
                        help="render S seconds instead of the scenario's duration_s: its first S, or its motion "
                             "carried on past its end (static_ranges: S spread over its ranges)")
    parser.add_argument("--out", metavar="DIR", required=True, help="sequence folder to create (must not exist or be empty)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace --out when it is a sequence this command wrote (once the new one is complete)")


def _take_back(partial: Path) -> str:
    """Remove the unfinished folder this run made; what became of it, as a message says it."""
    shutil.rmtree(partial, ignore_errors=True)
    return f"the unfinished {partial} could not all be removed" if partial.exists() else f"the unfinished {partial} was removed"


def run(args: argparse.Namespace) -> int:
    import yaml

    from trackmeter.cli.common import load_config_from_args, progress
    from trackmeter.data.config import config_to_dict
    from trackmeter.data.atomic import FolderLock, unwritable_ancestor
    from trackmeter.data.sequence import SequenceWriter
    from trackmeter.errors import TrackmeterError, counted
    from trackmeter.cli.common import check_rig_side_by_side
    from trackmeter.data.rigfile import load_rig
    from trackmeter.sources.sim.scenario import MAX_DURATION_S, load_scenario, rig_path
    from trackmeter.sources.sim.simulator import Simulator

    # Nothing the simulator does is configured there (the scenario is), but a --config that
    # is missing or wrong must fail as it does for every other command, not pass unread.
    load_config_from_args(args)
    out = Path(args.out)
    if out.name in ("", ".."):  # "." or "..": the folder has no name of its own to put ".partial" after
        out = Path(os.path.abspath(out))
    if out.is_symlink():
        # It would pass as empty (or as ours) through the link, and the rename at the end,
        # after the whole render, fail on the link itself.
        raise TrackmeterError(f"{out}: is a link; give the folder it leads to ({os.path.realpath(out)}) as --out")
    ours = {"cam0", "cam1", "groundtruth.csv", "groundtruth.tum", "model.yaml", "rig.yaml", "scenario.yaml"}
    replace_out = False
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        written = (out.is_dir() and (out / "scenario.yaml").is_file()
                   and all(p.name in ours or p.name.startswith(".") for p in out.iterdir()))
        if not args.overwrite:
            raise TrackmeterError(f"{out}: exists and is not an empty folder; choose a new --out"
                                  + (" or give --overwrite to replace this sequence" if written else ""))
        if not written:
            what = "a file" if out.is_file() else "a folder of other files"
            raise TrackmeterError(f"{out}: not a sequence simulate wrote ({what}); --overwrite replaces "
                                  "only those: move it away or choose a new --out")
        replace_out = True
    blocked = unwritable_ancestor(out)
    if blocked is not None:
        raise TrackmeterError(f"{out}: cannot create a sequence folder there ({blocked} is not a writable folder)")
    scenario = load_scenario(args.scenario)
    if args.duration is not None:
        if not (0 < args.duration <= MAX_DURATION_S):
            raise TrackmeterError(f"--duration must be a positive number of seconds, at most {MAX_DURATION_S:g} (an hour), "
                                  f"got {args.duration:g}")
        try:
            scenario = scenario.with_duration(args.duration)
        except TrackmeterError as exc:  # the motion carried on past the scenario's own end
            raise TrackmeterError(f"--duration {args.duration:g} with scenario {args.scenario!r}: "
                                  f"{exc}") from None
    # A rig that track and measure refuse (swapped, one camera above the other) rendered a
    # sequence nothing could use (an outside probe); track --source sim:SCENARIO refused it.
    rig_file = rig_path(scenario)
    with warnings.catch_warnings():  # the simulator reads it again below, and says what it warns of
        warnings.simplefilter("ignore")
        rig = load_rig(rig_file)
    check_rig_side_by_side(rig, f"the rig of scenario {args.scenario!r} ({rig_file})")
    partial = out.with_name(out.name + ".partial")
    if partial.exists() or partial.is_symlink():
        # Left over from a run of this command that was killed outright: replaced, but only
        # when it holds nothing a sequence writer would not have written, and no writer holds
        # it (another simulate to the same --out, still running: its lock refuses this one).
        if partial.is_symlink() or not partial.is_dir() or any(
                p.name not in ours and not p.name.startswith(".") for p in partial.iterdir()):
            raise TrackmeterError(f"{partial}: exists and is not a sequence this command left unfinished; "
                                  "move it away or choose another --out")
        leftover = FolderLock(partial, "another simulate (or recording)")
        try:
            shutil.rmtree(partial)
        finally:
            leftover.release()
    # Rendering ahead in a worker overlaps it with this process's image encoding and writing.
    sim = Simulator(scenario, render_ahead=True)
    # The folder's lock, held from the writer's start until the folder is renamed or removed:
    # without it, what this run takes back could be another simulate's that won the folder.
    lock: FolderLock | None = None
    try:
        with SequenceWriter(partial, rig=sim.true_rig, model_points=sim.model) as writer:
            lock = writer.detach_lock()
            (partial / "scenario.yaml").write_text(
                "# the scenario this sequence was rendered from\n"
                + yaml.safe_dump(config_to_dict(scenario), sort_keys=False), encoding="utf-8")
            for _ in progress(range(sim.n_frames), sim.n_frames, f"simulate {scenario.name}"):
                frame = sim.read()
                if frame is None:
                    raise TrackmeterError(f"scenario {scenario.name} ended before its {sim.n_frames} frames")
                writer.write(frame)
        if replace_out:
            # The old sequence goes only now that the new one is whole: moved aside, the new
            # one put in its place, then the old removed.
            old = out.with_name(f".{out.name}.replaced")
            shutil.rmtree(old, ignore_errors=True)
            out.rename(old)
            partial.rename(out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            if out.exists():
                out.rmdir()  # empty, checked above
            partial.rename(out)
    except OSError as exc:
        if lock is not None:  # the folder is this run's: take it back
            shutil.rmtree(partial, ignore_errors=True)
        if exc.filename2 is None and str(exc.filename) == str(partial):  # OUT is the user's name for it
            raise TrackmeterError(f"{out}: {exc.strerror or exc}") from None
        raise
    except TrackmeterError as exc:
        if lock is None:
            raise
        # What a failed write says is left in the folder (one camera's images kept) is not:
        # the unfinished folder goes whole.
        left = _take_back(partial)
        raise TrackmeterError(f"{str(exc).split('; ')[0]}; {left}; nothing was written to {out}") from None
    except KeyboardInterrupt:
        if lock is None:
            raise KeyboardInterrupt(f"interrupted; nothing was written to {out}") from None
        left = _take_back(partial)
        raise KeyboardInterrupt(f"interrupted: {left}; nothing was written to {out}") from None
    except BaseException:
        if lock is not None:
            shutil.rmtree(partial, ignore_errors=True)
        raise
    finally:
        if lock is not None:
            lock.release()
        sim.close()
    # A scenario given as a file is named by its name: key; say which file it was.
    named = scenario.name if Path(args.scenario).suffix.lower() not in (".yaml", ".yml") else f"{scenario.name} ({args.scenario})"
    print(f"wrote {counted(sim.n_frames, 'frame')} ({sim.n_frames / sim.rate_hz:.2f} s at {sim.rate_hz:g} Hz) of "
          f"scenario {named} to {out}", file=sys.stdout)
    return 0
