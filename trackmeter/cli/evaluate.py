"""Compare an estimated trajectory with the ground truth (the paper's trial evaluation, section 4).

Pairs poses by timestamp, one to one: an estimated and a truth pose that are each other's
nearest, within --tolerance (a tolerance over half the truth's period leaves ties to rounding),
optionally fits the constant offset between the estimate's and the truth's body frames (--align
body; by default for a run tracked in case a or c, as its run.yaml says, whose body frame is its
own; the estimate is then referred to the TRUE body frame, so its position error is that of the
true body origin, lever arm of the attitude error included), skips a settle time, and reports
position errors (camera frame; z = viewing axis), attitude errors (paper eq. 17 per axis, eq. 16
total), linear velocity errors (camera frame, of the body origin) and angular velocity errors
(body frame, paper eq. 14; both only when the estimate is a run directory or its states.csv and
the truth has rates (a groundtruth.csv, also one beside a TUM file given, or sim[:SCENARIO])),
each as RMS, max and 95th percentile, plus the SPEED challenge score. Without alignment, a run
folder's pose_covariance.csv is judged too: the NEES of each pose (e^T P^-1 e over position and
attitude errors), its median and share within chi-square(6)'s 95 % bound (5.35 and 95 % when
the covariance is honest).

  --truth    TUM file, groundtruth.csv, or a sequence folder; sim[:SCENARIO] for a run of the
             sim source: the scenario's motion (a path of that name, if one exists, comes first)
  --estimate TUM file, states.csv, or a `trackmeter track` run directory

"matched" counts the evaluated pairs; "unmatched" the estimated poses with no truth pose within
the tolerance plus the truth poses with no estimate where the run had a frame (a run directory
or states.csv: its rows, within the tolerance, so a truth sampled faster than the run is not
counted between its frames; a TUM file: every truth pose inside its poses' span), both after
the settle time, as the pairs are; the run's frames after the settle (in the truth's span)
that have a pose are given as a percentage (not for a TUM estimate, which does not list its
frames). A warning says when the run's run.yaml names another sequence or scenario than the
truth's (by the scenario's motion, where both are known). --json prints the summary in SI
units, with the settings it was made with ("settings": truth, estimate, align, settle_s,
tolerance_s, the run's case); --out DIR also writes errors.csv, summary.json (the same), PNG
plots of the errors against time and report.md beside the paper's figures.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from trackmeter.cli.common import load_config_from_args

if TYPE_CHECKING:
    from trackmeter.core.metrics import EvaluateParams
    from trackmeter.data.evaluation import LoadedMotion

#: An estimate of unknown case whose attitude is off by more than this (RMS) is told about
#: --align body: tracking errors are tenths of a degree, a frame of its own tens of degrees.
UNKNOWN_CASE_OFFSET_RAD = math.radians(10.0)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--truth", required=True, metavar="TUM_CSV_OR_SEQ",
                        help="ground truth: TUM file, groundtruth.csv (or EuRoC's ground-truth data.csv, by its "
                        "header) or sequence folder; or sim[:SCENARIO], the "
                        "scenario's motion, for a run of the sim source (which keeps no ground truth)")
    parser.add_argument("--estimate", required=True, metavar="TUM_CSV_OR_RUN_DIR", help="estimate: TUM file, states.csv or run directory")
    parser.add_argument("--align", choices=("none", "body", "auto"),
                        help="none: same body frame; body: fit a constant body-frame offset; auto: body for a run "
                        "tracked in case a or c (its run.yaml says), none otherwise (default from config: auto)")
    parser.add_argument("--settle", type=float, metavar="S",
                        help="seconds to skip from the start of the run (its first states.csv row, with a pose or not; "
                        "for a TUM file, its first pose paired with the truth); default from config: 0")
    parser.add_argument("--tolerance", type=float, metavar="S",
                        help="largest timestamp difference of a pair, s (default from config: 0.01)")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON (SI units)")
    parser.add_argument("--out", metavar="DIR", help="write errors.csv, summary.json, plots and report.md here")


def _params(args: argparse.Namespace) -> EvaluateParams:
    from trackmeter.core.metrics import EvaluateParams
    from trackmeter.data.config import check_option

    params = load_config_from_args(args).evaluate
    changes = {}
    if args.align is not None:
        changes["align"] = args.align
    if args.settle is not None:
        changes["settle_s"] = check_option(EvaluateParams, "settle_s", args.settle, "--settle")
    if args.tolerance is not None:
        changes["tolerance_s"] = check_option(EvaluateParams, "tolerance_s", args.tolerance, "--tolerance")
    return replace(params, **changes)


def _sim_scenario(spec: str) -> str | None:
    """The scenario ``--truth sim`` / ``sim:SCENARIO`` names (a name or a file), or None when
    ``spec`` is no such form or is the path of something that exists (a folder named sim)."""
    kind, _, name = spec.partition(":")
    if kind != "sim" or Path(spec).exists():
        return None
    from trackmeter.sources import DEFAULT_SCENARIO

    return name or DEFAULT_SCENARIO


def _load_truth(spec: str, until_s: float | None = None) -> LoadedMotion:
    """``--truth``: a file or folder (:func:`trackmeter.data.evaluation.load_truth`), or, where
    no such path exists, ``sim`` / ``sim:SCENARIO``: the scenario's motion (a ``track --source
    sim`` run keeps no ground truth; this is the one ``trackmeter simulate`` would write),
    carried on to ``until_s`` when the run goes on past the scenario's end (a sequence
    simulated with a longer ``--duration``)."""
    from trackmeter.data.evaluation import LoadedMotion, load_truth

    name = _sim_scenario(spec)
    if name is None:
        return load_truth(spec)
    from trackmeter.sources.sim.scenario import MAX_DURATION_S, load_scenario
    from trackmeter.sources.sim.simulator import scenario_truth

    scenario = load_scenario(name)
    # (times past an hour are no run of it: epoch times, paired with no truth, as before)
    if until_s is not None and scenario.span_s < until_s < MAX_DURATION_S and not scenario.static_ranges_m:
        scenario = scenario.with_duration(until_s + 1.0 / scenario.rate_hz)
    return LoadedMotion(scenario_truth(scenario), f"sim:{name} (the scenario's motion)", True)


def _previous_run_note(estimate: Path) -> str:
    """Where a run killed during ``track --overwrite`` keeps the run it was replacing (a hidden
    folder the next ``--overwrite`` of that folder gives back or replaces), or ""."""
    from trackmeter.data.rundir import PREVIOUS_RUN

    previous = (estimate if estimate.is_dir() else estimate.parent) / PREVIOUS_RUN
    if not (previous / "run.yaml").is_file():
        return ""
    return f"; the earlier run it was replacing (--overwrite) is kept in {previous}"


def _other_sequence(truth_spec: str, estimate_spec: str) -> str | None:
    """Why the truth may be of another sequence than the one the run was tracked on (its
    run.yaml's ``source.folder`` and ``source.scenario``), or None: scenarios that differ, or,
    where one is unknown, sequence folders that differ (the same scenario simulated twice is
    the same motion; a truth file outside any sequence folder says nothing of its sequence)."""
    import yaml

    from trackmeter.data.sequence import is_sequence_folder, sequence_identity, sequence_motion_digest
    from trackmeter.errors import TrackmeterError
    from trackmeter.sources.sim.scenario import load_scenario

    estimate = Path(estimate_spec)
    run_dir = estimate if estimate.is_dir() else estimate.parent
    try:
        source = yaml.safe_load((run_dir / "run.yaml").read_text(encoding="utf-8"))["source"]
        run_folder, run_scenario, run_motion = source.get("folder"), source.get("scenario"), source.get("motion")
    except (OSError, UnicodeDecodeError, yaml.YAMLError, KeyError, TypeError, AttributeError):
        return None
    truth_folder: Path | None = None
    truth_scenario: str | None = None
    truth_motion: str | None = None
    scenario = _sim_scenario(truth_spec)
    if scenario is not None:
        try:
            loaded = load_scenario(scenario)
        except TrackmeterError:
            return None
        truth_scenario = loaded.name  # a file's name: key, as the run recorded it
        truth_motion = loaded.motion_digest()
    else:
        path = Path(truth_spec)
        folder = path if path.is_dir() else path.parent
        for candidate in (folder, folder.parent):  # DIR, or DIR/mav0 holding the truth
            if is_sequence_folder(candidate):
                truth_folder, truth_scenario = sequence_identity(candidate)
                truth_motion = sequence_motion_digest(candidate)
                break
    run_said = f"{run_folder or 'the simulator'}" + (f", scenario {run_scenario}" if run_scenario else "")
    truth_said = f"{truth_folder or 'the simulator'}" + (f", scenario {truth_scenario}" if truth_scenario else "")
    if isinstance(run_motion, str) and truth_motion:
        # The motion itself, whatever the names: two files called alike, or one renamed.
        return None if run_motion == truth_motion else (
            f"{truth_said}; the run: {run_said}" + ("; their motions differ" if run_scenario == truth_scenario else ""))
    if run_scenario and truth_scenario:
        return None if run_scenario == truth_scenario else f"{truth_said}; the run: {run_said}"
    if run_folder and truth_folder and Path(run_folder).resolve() != truth_folder:
        return f"{truth_said}; the run: {run_said}"
    return None


def run(args: argparse.Namespace) -> int:
    from trackmeter.core.metrics import evaluate, resolve_align
    from trackmeter.data.evaluation import (check_report_directory, format_summary, in_seconds, judge_pose_covariance,
                                             likely_mixups, load_estimate, write_evaluation)

    from trackmeter.errors import TrackmeterError

    params = _params(args)
    if args.out:
        check_report_directory(args.out)  # before the work, which may take a while
        out, estimate_path = Path(args.out), Path(args.estimate)
        if (out / "run.yaml").exists() and out.resolve() != (
                estimate_path if estimate_path.is_dir() else estimate_path.parent).resolve():
            # Its report is of its own run: another's there would replace it, and describe
            # a run the folder does not hold.
            raise TrackmeterError(f"{out}: another run's folder (its run.yaml) than --estimate's; a report goes "
                                  "into the estimate's own run folder or one of its own: choose another --out")
    # The truth first (its errors said first), but a scenario's motion once the run's span is known.
    truth = None if _sim_scenario(args.truth) is not None else _load_truth(args.truth)
    try:
        estimate = load_estimate(args.estimate)
    except TrackmeterError as exc:
        # A run killed before its first frame holds no pose, but may hold the run it replaced.
        raise TrackmeterError(f"{exc}{_previous_run_note(Path(args.estimate))}") from None
    if truth is None:
        truth = _load_truth(args.truth, float(estimate.series.t_s[-1]) if len(estimate.series) else None)
    truth, estimate = in_seconds(truth, estimate, params.tolerance_s)
    params = replace(params, align=resolve_align(params.align, estimate.case))
    result = evaluate(truth.series, estimate.series, params, estimate.t_start_s, estimate.frame_times_s)
    if params.align == "none":
        nees, warning = judge_pose_covariance(estimate, result)
        if warning:
            print(f"trackmeter evaluate: warning: {warning}", file=sys.stderr)
        if nees:
            result.summary["pose_nees"] = nees
    t_t, t_e = truth.series.t_s, estimate.series.t_s
    overlap = min(t_t[-1], t_e[-1]) - max(t_t[0], t_e[0])
    longer = max(t_t[-1] - t_t[0], t_e[-1] - t_e[0])
    assoc = result.association
    if longer > 0 and overlap < 0.01 * longer and assoc.unmatched_est > assoc.matched:
        # The figures then describe the few poses in the overlap: clocks in other units or epochs?
        # (A short run, or a single pose, within a long truth pairs all its poses: nothing to say.)
        print(f"trackmeter evaluate: warning: the time spans barely overlap (truth {t_t[0]:.6g}..{t_t[-1]:.6g} s, "
              f"estimate {t_e[0]:.6g}..{t_e[-1]:.6g} s; {assoc.matched} of {len(t_e)} estimated "
              "poses paired): timestamps in other units or from another clock?", file=sys.stderr)
    elif assoc.matched:
        # A truth cut short (or started late) leaves the rest of the run unevaluated: the
        # coverage line counts only frames within the truth's span. (A truth sampled more
        # sparsely than the run may end a sample or two before it: nothing to say.)
        steps = sorted(t_t[1:] - t_t[:-1])
        reach = max(params.tolerance_s, 2.0 * steps[len(steps) // 2] if steps else 0.0)
        tol = params.tolerance_s
        before = int((t_e < t_t[0] - tol).sum()) if t_e[0] < t_t[0] - reach else 0
        after = int((t_e > t_t[-1] + tol).sum()) if t_e[-1] > t_t[-1] + reach else 0
        if after:
            print(f"trackmeter evaluate: warning: the truth ends at {t_t[-1]:.3f} s, the estimate at {t_e[-1]:.3f} s: its "
                  f"{after} pose(s) after the truth's end are not evaluated", file=sys.stderr)
        if before:
            print(f"trackmeter evaluate: warning: the truth starts at {t_t[0]:.3f} s, the estimate at {t_e[0]:.3f} s: its "
                  f"{before} pose(s) before the truth's start are not evaluated", file=sys.stderr)
    if params.align == "body" and 0 < assoc.matched < 3:
        # The offset's six parameters fitted to one pose make its errors zero by construction.
        print(f"trackmeter evaluate: warning: --align body fitted the body-frame offset to {assoc.matched} pose(s): it "
              "absorbs most of their error (all of it with one), so the figures say little", file=sys.stderr)
    cuts, redefined = estimate.restarts
    if params.align == "body" and estimate.case in ("a", "c") and cuts + redefined:
        # Each start defines the body frame anew (case (c) acquires its model again): one
        # offset fitted to all of them measures how those frames differ as well.
        print(f"trackmeter evaluate: warning: the run defined its body frame {1 + cuts + redefined} times "
              f"({cuts} cut(s) in its source: a loop or a restart; {redefined} after a total loss), and one offset "
              "is fitted to all of them, so the figures include how those frames differ", file=sys.stderr)
    if params.align == "none" and estimate.case in ("a", "c"):
        # Such a run's body frame is its own (three tracked points, or the acquired model):
        # without the fitted offset the figures measure where its frame sits, not the tracking.
        print(f"trackmeter evaluate: warning: the run was tracked in case ({estimate.case}), whose body frame is "
              "not the truth's: compare with --align body", file=sys.stderr)
    other = _other_sequence(args.truth, args.estimate)
    if other:
        print(f"trackmeter evaluate: warning: the truth may not be of the sequence the run was tracked on ({other}, "
              "its run.yaml): if so, the figures compare two different motions", file=sys.stderr)
    if estimate.valid_rows_without_rates and result.summary.get("velocity_m_s") is not None:
        # README: a states.csv row is valid (1) when every field is a number (a pose whose
        # rates are pending is a valid-0 row): a hand edit, or another writer's convention. Its
        # pose counts, its rates cannot, and the rate figures rest on fewer frames than the pose's.
        print(f"trackmeter evaluate: warning: {estimate.valid_rows_without_rates} rows with a pose of {estimate.source} "
              "have a rate that is not a number (a states.csv's valid (1) row holds numbers in every field): their "
              "poses are evaluated, their rates left out", file=sys.stderr)
    if estimate.status == "write failed":
        # Stopped at the first frame that did not fit (a full disk): whole up to there.
        print("trackmeter evaluate: warning: the run's run.yaml says its writes failed (a full disk?), so it ended "
              "early; its frames up to there are whole" + _previous_run_note(Path(args.estimate)), file=sys.stderr)
    if estimate.status == "source failed":
        print("trackmeter evaluate: warning: the run's run.yaml says its source failed, so it ended early (its "
              "summary's source_status says how)", file=sys.stderr)
    if estimate.status == "running":
        # The writer never closed it: killed, a disk that filled (track then says run.yaml could
        # not be updated), or still being written; its summary is missing.
        print("trackmeter evaluate: warning: the run's run.yaml says it is still running: it was killed, its disk "
              "filled, or it is still being written, so it may end early and its summary is missing"
              + _previous_run_note(Path(args.estimate)), file=sys.stderr)
    mixups = likely_mixups(truth.series, estimate.series, assoc.index_truth, assoc.index_est,
                           estimate.quat_read_scalar_first) \
        if params.align == "none" else []
    for hint in mixups:
        print(f"trackmeter evaluate: warning: {hint}", file=sys.stderr)
    attitude_rms_rad = result.summary.get("attitude_rad", {}).get("total", {}).get("rms", 0.0)
    if params.align == "none" and estimate.case is None and attitude_rms_rad > UNKNOWN_CASE_OFFSET_RAD and not mixups:
        # A bare trajectory does not say whose body frame it is in: a case (a) or (c) run's
        # own frame, compared as it is, reads as errors of tens of degrees and centimetres.
        print(f"trackmeter evaluate: warning: the attitude is off by {math.degrees(attitude_rms_rad):.0f} deg (RMS); if "
              "the estimate is in a body frame of its own (tracked in case a or c), compare with --align body",
              file=sys.stderr)
    settings = {"truth": truth.source, "estimate": estimate.source, "align": params.align,
                "settle_s": params.settle_s, "tolerance_s": params.tolerance_s, "case": estimate.case}
    if args.out:
        write_evaluation(result, args.out, settings)
    if args.json:
        from trackmeter.data.jsontext import json_text

        print(json_text({**result.summary, "settings": settings}))
    else:
        print(format_summary(result.summary, truth.source, estimate.source, params.align))
        if args.out:
            print(f"wrote {args.out}/report.md, errors.csv, summary.json and plots")
    return 0
