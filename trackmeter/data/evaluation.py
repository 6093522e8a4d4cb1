"""Inputs and outputs of ``trackmeter evaluate``: find and read truth and estimate, write the
error time series, the plots (paper Figs. 6-7 kind) and a report beside the paper's figures.

Truth (``--truth``): a TUM file (velocities from a ``groundtruth.csv`` beside it, when its
timestamps agree), a ``groundtruth.csv`` file, or a sequence folder (its ``groundtruth.csv``,
else ``groundtruth.tum``; ``DIR`` or ``DIR/mav0``).
Estimate (``--estimate``): a TUM file, a ``states.csv`` file, or a ``track`` run directory
(its ``states.csv`` valid rows and the pose-only rows its ``trajectory.tum`` lists as valid
poses, else that file); a ``states.csv`` file is read the same way, with the ``trajectory.tum``
beside it.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence, TypedDict, cast

import numpy as np
import yaml

from trackmeter.core.metrics import Evaluation, associate
from trackmeter.core.transforms import attitude_error_angle
from trackmeter.data.motion_csv import (MotionSeries, header_fields, is_comment_line, names_a_header,
                                         other_separator_header, read_motion_csv)
from trackmeter.data.atomic import write_files_atomic
from trackmeter.data.jsontext import json_text
from trackmeter.data.sequence import check_output_folder, find_sequence_file, seconds_if_nanoseconds
from trackmeter.data.trajectory import read_tum
from trackmeter.errors import TrackmeterError, counted

if TYPE_CHECKING:  # matplotlib is imported only where a report is drawn
    from matplotlib.figure import Figure


@dataclass(frozen=True, eq=False)
class LoadedMotion:
    """A truth or estimate as read, with where it came from (for messages and reports)."""

    series: MotionSeries  # the rows with a pose (all marked valid)
    source: str  # the file(s) read
    has_velocity: bool
    t_start_s: float | None = None  # start of a run (first states.csv row, valid or not)
    frame_times_s: np.ndarray | None = None  # a run's frames (every states.csv row, valid or not)
    case: str | None = None  # a track run's pose case ("a", "b", "c"; its run.yaml), else None
    # how often a track run started its body frame anew (its run.yaml's summary): at a cut in
    # its source, and case (a)'s new frames after a total loss: (stream_cuts, frames_redefined)
    restarts: tuple[int, int] = (0, 0)
    status: str | None = None  # a track run's run.yaml status ("complete", "interrupted", "running", ...)
    # a states.csv's valid (1) rows with a rate that is not a number: README says a valid row
    # holds numbers in every field (a pose whose rates are pending is a valid-0 row)
    valid_rows_without_rates: int = 0
    # a track run's pose covariances (its pose_covariance.csv), (N,6,6) beside the series' rows
    # (NaN where a row has none), or None without the file; and which rows the file has (N,)
    cov_pose: np.ndarray | None = None
    cov_pose_rows: np.ndarray | None = None
    # how its quaternions were read: scalar first (a CSV: qw qx qy qz), scalar last (TUM:
    # qx qy qz qw), or None (not said): which other order a mix-up hint may name
    quat_read_scalar_first: bool | None = None


def _looks_like_motion_csv(path: Path) -> bool:
    try:
        with open(path, encoding="utf-8") as f:
            for line in f:
                if line.strip() and not is_comment_line(line):
                    if other_separator_header(path, 0, line) is not None:
                        return True  # read_motion_csv says what it is
                    fields = header_fields(line)
                    # A header of names with commas is a CSV's even without its `t` column (a
                    # renamed one was read as a TUM line and told "expected 8 values").
                    return names_a_header(fields)
    except (OSError, UnicodeDecodeError):
        return False
    return False


def _read_pose_file(path: Path) -> MotionSeries:
    """A TUM file or a motion CSV, by content (a header starting ``t,`` means CSV)."""
    if _looks_like_motion_csv(path):
        return read_motion_csv(path).valid_only()
    return MotionSeries.from_trajectory(read_tum(path))


def _finite_rows(a: np.ndarray) -> np.ndarray:
    """(N,) True where row ``a[i]`` is all finite."""
    return np.all(np.isfinite(a), axis=1)


def _rows_with_rates(series: MotionSeries) -> np.ndarray:
    """(N,) True where both the linear and the angular velocity are known."""
    return _finite_rows(series.velocity_cam_m_s) & _finite_rows(series.omega_body_rad_s)


def _poses_of_run(states: MotionSeries, declared_t_s: np.ndarray, undeclared_why: str | None = None) -> MotionSeries:
    """The rows of a run's ``states.csv`` that carry a valid pose, all marked valid.

    Those are the valid rows, and the rows a ``track`` run writes with valid 0 while its rates
    are still unknown (pose filled in, rates empty) whose times its ``trajectory.tum`` lists as
    valid poses (``declared_t_s``), so the two files evaluate alike. Any other valid-0 row is
    left out, whatever it holds (another producer may write a held or predicted pose there).
    The rates of the pose-only rows stay NaN (left out of the velocity figures).
    ``undeclared_why``: why a track run's ``trajectory.tum`` could not declare its poses
    (:func:`_declared_pose_times`); where pose-only rows are then left out, that is warned.
    """
    pose = _finite_rows(states.position_m) & _finite_rows(states.quat_wxyz)
    pose_only = pose & ~states.valid & ~_rows_with_rates(states)
    if np.any(pose_only) and len(declared_t_s):
        declared = np.zeros(len(states), bool)
        listed = np.sort(np.asarray(declared_t_s, float))
        a = associate(listed, states.t_s[pose_only], 1e-6)
        declared[np.flatnonzero(pose_only)[a.index_est]] = True
        unlisted = int(np.count_nonzero(pose_only & ~declared))
        missed = int(np.count_nonzero(states.valid)) - associate(listed, states.t_s[states.valid], 1e-6).matched
        if unlisted and missed > 0:
            # A track run lists every valid pose there: this one is cut short (or edited).
            warnings.warn(f"trajectory.tum beside it lists {len(listed)} poses and misses {missed} of states.csv's "
                          f"valid ones (cut short?): the {unlisted} poses logged before the rates were known that it "
                          "does not list are left out", stacklevel=2)
        pose_only &= declared
    else:
        if np.any(pose_only) and undeclared_why:
            warnings.warn(f"{undeclared_why}: the {int(np.count_nonzero(pose_only))} poses logged before the rates "
                          "were known (states.csv valid 0, declared poses only there) are left out", stacklevel=2)
        elif np.any(pose_only):
            # Said, so that a track run's states.csv read without its folder does not score
            # fewer poses than the folder, silently.
            warnings.warn(f"{int(np.count_nonzero(pose_only))} rows with a pose but valid 0 left out: no trajectory.tum "
                          "beside lists them as valid poses (a track run writes its poses before the rates are known "
                          "so, and lists them there)", stacklevel=2)
        pose_only[:] = False
    keep = states.valid | pose_only
    with_rates = states.valid[keep][:, None]
    return MotionSeries(states.t_s[keep], np.ones(int(np.count_nonzero(keep)), bool), states.position_m[keep],
                        states.quat_wxyz[keep], np.where(with_rates, states.velocity_cam_m_s[keep], np.nan),
                        np.where(with_rates, states.omega_body_rad_s[keep], np.nan),
                        {k: a[keep] for k, a in states.extra.items()})


def _declared_pose_times(run_dir: Path) -> tuple[np.ndarray, str | None]:
    """Times (s) of the valid poses the run's ``trajectory.tum`` lists, and why none could be
    read where a track run (its ``run.yaml`` beside) should have them: the file is missing or
    does not read (cut short by a full disk, edited). Another producer's folder without one
    has nothing missing."""
    tum = run_dir / "trajectory.tum"
    if not tum.is_file():
        return np.zeros(0), (f"{tum}: missing beside the run's run.yaml" if (run_dir / "run.yaml").is_file() else None)
    try:
        return read_tum(tum).t_s, None
    except TrackmeterError as exc:
        return np.zeros(0), f"{exc} (the file is not read)"


#: Poses of a TUM truth and of the groundtruth.csv beside it that differ by more than this
#: (m; rad) are of other motions: the csv's velocities are not taken. A TUM file keeps 9
#: decimals; another tool's may round to a tenth of a millimetre.
SAME_TRUTH_TOLERANCE = (1e-3, 1e-3)


def _with_rates_from(series: MotionSeries, csv_path: Path) -> MotionSeries | None:
    """``series`` poses with the velocities of ``csv_path`` when every timestamp agrees
    (within 1 µs) and so do the poses (:data:`SAME_TRUTH_TOLERANCE`; a warning when they do
    not), else None."""
    try:
        rates = read_motion_csv(csv_path).valid_only()
    except TrackmeterError:
        return None
    a = associate(rates.t_s, series.t_s, 1e-6)
    if a.matched != len(series) or not rates.has_velocity:
        return None
    order = np.argsort(a.index_est)
    it = a.index_truth[order]
    apart_m = float(np.max(np.linalg.norm(rates.position_m[it] - series.position_m, axis=1)))
    apart_rad = float(np.max(attitude_error_angle(rates.quat_wxyz[it], series.quat_wxyz)))
    if apart_m > SAME_TRUTH_TOLERANCE[0] or apart_rad > SAME_TRUTH_TOLERANCE[1]:
        warnings.warn(f"{csv_path} beside the truth gives other poses at its times (up to {1e3 * apart_m:.3f} mm and "
                      f"{math.degrees(apart_rad):.3f} deg apart): its velocities are not used", stacklevel=3)
        return None
    return MotionSeries(series.t_s, series.valid, series.position_m, series.quat_wxyz,
                        rates.velocity_cam_m_s[it], rates.omega_body_rad_s[it])


def _require_file(path: Path) -> None:
    """A ``--truth`` or ``--estimate`` that is not a folder must be a regular file (not a
    device or a pipe: both would read as empty and be reported as having no poses)."""
    if not path.exists():
        raise TrackmeterError(f"{path}: no such file or folder")
    if not path.is_file():
        raise TrackmeterError(f"{path}: not a regular file or folder")


def load_truth(spec: str | Path) -> LoadedMotion:
    """Read ``--truth`` (see the module docstring).

    Raises:
        TrackmeterError: nothing readable there, or a file in the wrong format.
    """
    path = Path(spec)
    if path.is_dir():
        # The sequence reader's own rule, so evaluate and track see the same ground truth.
        found = find_sequence_file(path, "groundtruth.csv", "groundtruth.tum")
        if found is None:
            raise TrackmeterError(f"{path}: folder has no groundtruth.csv or groundtruth.tum")
        if found.suffix == ".csv":
            s = read_motion_csv(found).valid_only()
            if len(s) == 0:
                raise TrackmeterError(f"{found}: no valid pose")
            return LoadedMotion(s, str(found), s.has_velocity)
        s = MotionSeries.from_trajectory(read_tum(found))
        return LoadedMotion(s, str(found), False)
    _require_file(path)
    series = _read_pose_file(path)
    if len(series) == 0:  # e.g. a run's states.csv that never had a pose
        raise TrackmeterError(f"{path}: no valid pose")
    beside = path.parent / "groundtruth.csv"
    if not series.has_velocity and beside.is_file() and beside.resolve() != path.resolve():
        merged = _with_rates_from(series, beside)
        if merged is not None:
            return LoadedMotion(merged, f"{path} (+ velocities from {beside})", True)
    return LoadedMotion(series, str(path), series.has_velocity)


def load_estimate(spec: str | Path) -> LoadedMotion:
    """Read ``--estimate``: a TUM file, a ``states.csv``, or a run directory.

    Raises:
        TrackmeterError: nothing readable there, a file in the wrong format, or no valid pose.
    """
    path = Path(spec)
    loaded = _load_estimate(path)
    run_dir = path if path.is_dir() else path.parent
    counts = [_run_meta(run_dir, "summary", "engine", key) for key in ("stream_cuts", "frames_redefined")]
    restarts = tuple(c if isinstance(c, int) and not isinstance(c, bool) and c > 0 else 0 for c in counts)
    status = _run_meta(run_dir, "status")
    case = _run_case(run_dir)
    problem = _run_yaml_problem(run_dir) if case is None else None
    if problem:
        warnings.warn(f"{problem}: the run's pose case is unknown, so --align auto compares without aligning "
                      "(give --align body for a run tracked in case a or c)", stacklevel=2)
    return replace(loaded, case=case, restarts=(restarts[0], restarts[1]),
                   status=status if isinstance(status, str) else None,
                   **_pose_covariances(path, loaded.series.t_s))


class _PoseCovariances(TypedDict):
    cov_pose: np.ndarray | None
    cov_pose_rows: np.ndarray | None


def _pose_covariances(estimate: Path, t_s: np.ndarray) -> _PoseCovariances:
    """A track run's pose covariances at the poses ``t_s`` (N,) of ``estimate``: (N,6,6), NaN
    for a pose its ``pose_covariance.csv`` has no row for (both files write the times to 9
    decimals: the same numbers). Only for the run's own poses: ``estimate`` its folder (with its
    ``run.yaml``), its ``states.csv`` or its ``trajectory.tum``, not another file put beside
    them. As :class:`LoadedMotion`'s ``cov_pose`` and ``cov_pose_rows``; None otherwise, or with
    a warning when the file cannot be read."""
    from trackmeter.data.rundir import read_pose_covariance

    run_dir = estimate if estimate.is_dir() else estimate.parent
    own = estimate.is_dir() or estimate.name in ("states.csv", "trajectory.tum")
    path = run_dir / "pose_covariance.csv"
    none: _PoseCovariances = {"cov_pose": None, "cov_pose_rows": None}
    if not own or not path.is_file() or not (run_dir / "run.yaml").is_file():
        return none
    try:
        t_cov, cov = read_pose_covariance(path)
    except TrackmeterError as exc:
        warnings.warn(f"{exc}: the pose covariance is not judged", stacklevel=3)
        return none
    at = {round(float(t), 9): k for k, t in enumerate(t_cov)}
    out = np.full((len(t_s), 6, 6), np.nan)
    rows = np.zeros(len(t_s), dtype=bool)
    for k, t in enumerate(t_s):
        j = at.get(round(float(t), 9))
        if j is not None:
            out[k], rows[k] = cov[j], True
    return {"cov_pose": out, "cov_pose_rows": rows}


def judge_pose_covariance(estimate: LoadedMotion, evaluation: Evaluation) -> tuple[dict[str, float] | None, str | None]:
    """How honest a track run's pose covariance is (its ``pose_covariance.csv``, read by
    :func:`load_estimate`) on the poses ``evaluation`` paired, compared without alignment:
    ``(nees, warning)``, :func:`~trackmeter.core.metrics.nees_summary` over the poses with a
    usable covariance (None when none has one, or there is nothing to judge) and one line on the
    poses left out (None when none was). Not for a case (a) or (c) run, whose body frame is its
    own: the covariance describes that frame, not its placement on the truth's."""
    from trackmeter.core.metrics import MotionErrors, nees_summary, pose_nees, usable_covariances

    if estimate.cov_pose is None or estimate.case in ("a", "c"):
        return None, None
    index = evaluation.association.index_est
    cov = estimate.cov_pose[index]
    listed = np.ones(len(index), bool) if estimate.cov_pose_rows is None else estimate.cov_pose_rows[index]
    finite, definite = usable_covariances(cov)
    has, e = finite & definite, evaluation.errors
    where = Path(estimate.source).parent / "pose_covariance.csv"
    if not has.any():
        return None, (f"none of the {len(has)} paired poses has a usable covariance in {where} (no row at their "
                      "times, or none a positive definite matrix): the covariance is not judged")
    warning = None
    if not has.all():
        parts = [(int((~listed).sum()), "without a row at their time (another run's file, or cut short?)"),
                 (int((listed & ~finite).sum()), "not finite"),
                 (int((finite & ~definite).sum()), "not positive definite or beyond what doubles can weigh")]
        why = ", ".join(f"{n} {what}" for n, what in parts if n)
        warning = (f"{int((~has).sum())} of the {len(has)} paired poses have no usable covariance in {where} ({why}): "
                   f"the NEES is over the other {int(has.sum())}")
    judged = MotionErrors(e.t_s[has], e.position_m[has], e.attitude_rad[has], None, None, e.position_rel[has])
    return nees_summary(pose_nees(judged, cov[has])), warning


def _run_yaml_problem(run_dir: Path) -> str | None:
    """What is wrong with a ``run.yaml`` beside the estimate that records no pose case (cut
    short, edited, another program's file), or None where there is none or it is a run's."""
    path = run_dir / "run.yaml"
    if not path.exists():
        return None
    if not path.is_file():
        return f"{path}: not a file"
    try:
        value = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else exc.__class__.__name__
        return f"{path}: not readable as YAML ({first})"
    if not isinstance(value, dict):
        return f"{path}: not a run's record ({'an empty file' if value is None else f'a {type(value).__name__}'})"
    source = value.get("source")
    case = source.get("case") if isinstance(source, dict) else None
    return (f"{path}: no pose case recorded (source.case)" if case is None
            else f"{path}: an unknown pose case {case!r} (a, b or c)")


def _run_meta(run_dir: Path, *keys: str) -> Any:
    """``run.yaml[keys[0]][keys[1]]...`` of a ``track`` run directory; None when there is no
    readable one or it lacks the key."""
    try:
        value = yaml.safe_load((run_dir / "run.yaml").read_text(encoding="utf-8"))
        for key in keys:
            value = value[key]
    except (OSError, UnicodeDecodeError, yaml.YAMLError, KeyError, TypeError, IndexError):
        return None
    return value


def _run_case(run_dir: Path) -> str | None:
    """The pose case a ``track`` run directory's ``run.yaml`` records; None when there is no
    readable one."""
    case = _run_meta(run_dir, "source", "case")
    return case if case in ("a", "b", "c") else None


def _why_no_valid_pose(run_dir: Path) -> str:
    """The reason ``track`` gave most often for an invalid pose (run.yaml's summary), as
    ``" (N of its M frames: REASON)"``, or ``""`` when it gave none: what to change is in
    that reason, not in evaluate's message."""
    reasons = _run_meta(run_dir, "summary", "invalid_reasons")
    if not isinstance(reasons, dict):
        return ""
    counts = {str(k): v for k, v in reasons.items() if isinstance(v, int) and not isinstance(v, bool) and v > 0}
    if not counts:
        return ""
    reason = max(counts, key=lambda k: counts[k])
    return f" ({counts[reason]} of its {sum(counts.values())} frames: {reason})"


def _load_estimate(path: Path) -> LoadedMotion:
    t_start: float | None
    frames: np.ndarray | None
    if path.is_dir():
        if (path / "states.csv").is_file():
            full = read_motion_csv(path / "states.csv")
            t_start, frames = float(full.t_s[0]), full.t_s.copy()
            s = _poses_of_run(full, *_declared_pose_times(path))
            if len(s) == 0:
                raise TrackmeterError(f"{path / 'states.csv'}: no valid pose in the run{_why_no_valid_pose(path)}")
            return LoadedMotion(s, str(path / "states.csv"), bool(np.any(_rows_with_rates(s))), t_start,
                                frame_times_s=frames, valid_rows_without_rates=_valid_rows_without_rates(full),
                                quat_read_scalar_first=True)
        if (path / "trajectory.tum").is_file():
            if (path / "run.yaml").is_file():  # a run's folder: its states.csv was expected
                what = "not a file" if (path / "states.csv").exists() else "missing"
                warnings.warn(f"{path / 'states.csv'}: {what}: the poses of {path / 'trajectory.tum'} are "
                              "evaluated, without rates", stacklevel=3)
            s = MotionSeries.from_trajectory(read_tum(path / "trajectory.tum"))
            return LoadedMotion(s, str(path / "trajectory.tum"), False, quat_read_scalar_first=False)
        raise TrackmeterError(f"{path}: not a run directory (no states.csv or trajectory.tum)")
    _require_file(path)
    t_start = frames = None
    without_rates = 0
    read_scalar_first = _looks_like_motion_csv(path)
    if read_scalar_first:
        full = read_motion_csv(path)
        t_start, frames = float(full.t_s[0]), full.t_s.copy()
        s = _poses_of_run(full, *_declared_pose_times(path.parent))
        without_rates = _valid_rows_without_rates(full)
    else:
        s = MotionSeries.from_trajectory(read_tum(path))
    if len(s) == 0:
        raise TrackmeterError(f"{path}: no valid pose")
    return LoadedMotion(s, str(path), bool(np.any(_rows_with_rates(s))), t_start, frame_times_s=frames,
                        valid_rows_without_rates=without_rates, quat_read_scalar_first=read_scalar_first)


def _valid_rows_without_rates(rows: MotionSeries) -> int:
    """How many of a states.csv's valid (1) rows have a rate that is not a number, when some
    of its valid rows have all their rates (a file without rates at all is a pose-only one)."""
    has = _rows_with_rates(rows)[rows.valid]
    return int((~has).sum()) if has.any() else 0


def in_seconds(truth: LoadedMotion, estimate: LoadedMotion, tolerance_s: float) -> tuple[LoadedMotion, LoadedMotion]:
    """``truth`` and ``estimate`` with times in seconds: one whose times can only be integer
    nanoseconds (EuRoC's epoch nanoseconds, on either side or both), or are integers that pair
    with the other's only as nanoseconds, is converted, with a warning naming it
    (:func:`trackmeter.data.sequence.seconds_if_nanoseconds`)."""
    out = []
    for this, other in ((truth, estimate), (estimate, truth)):
        t, note = seconds_if_nanoseconds(other.series.t_s, this.series.t_s, tolerance_s, other.source)
        if note:
            warnings.warn(f"{this.source}: {note}", stacklevel=2)
            start = None if this.t_start_s is None else this.t_start_s * 1e-9
            frames = None if this.frame_times_s is None else this.frame_times_s * 1e-9
            this = replace(this, series=replace(this.series, t_s=t), t_start_s=start, frame_times_s=frames)
        out.append(this)
    return out[0], out[1]


def _pose_rms(R_truth: Any, p_truth: np.ndarray, R_est: Any, p_est: np.ndarray) -> tuple[float, float]:
    """RMS position error (m) and RMS attitude error (rad) of paired poses (scipy Rotations)."""
    position = float(np.sqrt(np.mean(np.sum((p_est - p_truth) ** 2, axis=1))))
    attitude = float(np.sqrt(np.mean((R_est * R_truth.inv()).magnitude() ** 2)))
    return position, attitude


#: A convention a mix-up hint names fits the truth's attitude at least this many times better
#: than the estimate as read, and its position no worse.
MIXUP_GAIN = 10.0


def likely_mixups(truth: MotionSeries, estimate: MotionSeries, index_truth: np.ndarray,
                  index_est: np.ndarray, read_scalar_first: bool | None = None) -> list[str]:
    """What an estimate far from the truth was likely written as, told apart on the paired
    poses: the inverse pose (``T_body_cam`` for ``T_cam_body``), a quaternion in the other
    order (scalar first where scalar last is read, or the reverse), or positions in
    millimetres. A convention is named only when it fits the truth :data:`MIXUP_GAIN` times
    better than the estimate as read (a rotation inverted alone too: a JPL quaternion), and
    positions when their sizes differ about a thousand- or a hundredfold (millimetres,
    centimetres); none when the estimate is close already. Compared as they are (no body
    alignment): a body frame of its own is none of these. ``read_scalar_first``: how the
    estimate's quaternions were read (True a CSV's qw first, False TUM's qw last), so that only
    the other order is named (a TUM file was told it had been "written scalar last where
    scalar first is read"); None names either."""
    from scipy.spatial.transform import Rotation

    if len(index_truth) == 0:
        return []
    p_t, p_e = truth.position_m[index_truth], estimate.position_m[index_est]
    q_e = estimate.quat_wxyz[index_est]
    R_t = Rotation.from_quat(truth.quat_wxyz[index_truth], scalar_first=True)
    R_e = Rotation.from_quat(q_e, scalar_first=True)
    position, attitude = _pose_rms(R_t, p_t, R_e, p_e)
    hints = []
    size_t, size_e = float(np.median(np.linalg.norm(p_t, axis=1))), float(np.median(np.linalg.norm(p_e, axis=1)))
    ratio = max(size_e / size_t, size_t / size_e) if size_t > 0 and size_e > 0 else 1.0
    unit = next((name for factor, name in ((1000, "millimetres"), (100, "centimetres"))
                 if factor / 1.5 < ratio < factor * 1.5), None)
    if unit is not None:
        larger, smaller = ("estimate", "truth") if size_e > size_t else ("truth", "estimate")
        hints.append(f"the {larger}'s positions are about {ratio:.0f}x the {smaller}'s (median distance {size_t:.4g} m "
                     f"in the truth, {size_e:.4g} in the estimate): {unit} where metres are read?")
    if attitude < math.radians(5.0) and not hints and position < 0.5 * size_t:
        return hints
    alternatives = {
        "inverted (T_body_cam where T_cam_body is read)": (R_e.inv(), -R_e.inv().apply(p_e)),
        "with its rotation inverted (a JPL or conjugated quaternion, or R_body_cam beside T_cam_body's position)":
            (R_e.inv(), p_e),
    }
    if read_scalar_first is not True:
        alternatives["written scalar first (w x y z) where scalar last is read (TUM: qx qy qz qw)"] = \
            (Rotation.from_quat(np.roll(q_e, -1, axis=1), scalar_first=True), p_e)
    if read_scalar_first is not False:
        alternatives["written scalar last (x y z w) where scalar first is read (qw qx qy qz)"] = \
            (Rotation.from_quat(np.roll(q_e, 1, axis=1), scalar_first=True), p_e)
    fits = []  # (position, attitude, what) of the conventions that fit far better
    for what, (R_alt, p_alt) in alternatives.items():
        position_alt, attitude_alt = _pose_rms(R_t, p_t, R_alt, p_alt)
        if attitude_alt * MIXUP_GAIN <= attitude and position_alt <= position:
            fits.append((position_alt, attitude_alt, what))
    if fits:  # the one that fits best (the whole pose inverted fits its rotation inverted as well)
        position_alt, attitude_alt, what = min(fits)
        hints.append(f"the estimate fits the truth far better {what}: attitude {math.degrees(attitude_alt):.3g} "
                     f"deg RMS instead of {math.degrees(attitude):.3g}, position {1e3 * position_alt:.4g} mm "
                     f"instead of {1e3 * position:.4g}")
    return hints


# --------------------------------------------------------------------------- paper figures

#: The paper's trial figures at 3.5 m (section 4), in OUR axes: x, y lateral, z the viewing
#: axis (the paper's viewing axis was y). Bounds of the error plots (±), SI units.
PAPER_BOUNDS: dict[str, dict[str, float]] = {
    "position_m": {"x": 0.003, "y": 0.003, "z": 0.005},
    "attitude_rad": {"x": math.radians(1.0), "y": math.radians(1.0), "z": math.radians(0.5)},
    "velocity_m_s": {"x": 0.002, "y": 0.002, "z": 0.0035},
    # "mostly within ±0.75 deg/s, peaks ±1 deg/s": compare p95 with 0.75 and max with 1.
    "omega_rad_s": {"x": math.radians(1.0), "y": math.radians(1.0), "z": math.radians(1.0)},
}
PAPER_OMEGA_MOSTLY_RAD_S = math.radians(0.75)

_DISPLAY = {  # group -> (title, unit, scale from SI)
    "position_m": ("position", "mm", 1e3),
    "attitude_rad": ("attitude", "deg", 180.0 / math.pi),
    "velocity_m_s": ("linear velocity", "mm/s", 1e3),
    "omega_rad_s": ("angular velocity (body frame)", "deg/s", 180.0 / math.pi),
}


#: Every plot a report may hold (:func:`render_error_plots`), file names in ``--out``.
REPORT_PLOTS = tuple(f"{group.split('_')[0]}_error.png" for group in _DISPLAY)


def format_summary(summary: dict, truth: str = "", estimate: str = "", align: str = "none") -> str:
    """Human-readable summary in mm and degrees (the display edge)."""
    lines = []
    if truth or estimate:
        lines.append(f"truth:    {truth}\nestimate: {estimate}\nalign:    {align}")
    coverage = summary.get("pose_coverage")
    lines.append(f"matched {counted(summary['matched'], 'pose')}, unmatched {summary['unmatched']}"
                 + (f"; {100 * coverage:.1f} % of the run's frames after the settle (in the truth's span) have a pose"
                    if coverage is not None else ""))
    rows = [(f"{title} [{unit}]", axis, *(f"{st[k] * scale:.3f}" for k in ("rms", "p95", "max")))
            for group, (title, unit, scale) in _DISPLAY.items() if summary.get(group) is not None
            for axis, st in summary[group].items()]
    # Columns as wide as their longest figure: an estimate in the wrong units has errors of
    # millions, which ran together in fixed columns of 10.
    width = max([9] + [len(figure) for row in rows for figure in row[2:]]) + 1
    lines.append(f"{'error':<40}{'axis':>6}{'rms':>{width}}{'p95':>{width}}{'max':>{width}}")
    lines += [f"{name:<40}{axis:>6}{rms:>{width}}{p95:>{width}}{top:>{width}}" for name, axis, rms, p95, top in rows]
    lines.append(f"SPEED score (mean of angle [rad] + |dt|/|t|): {summary['speed_score']:.6f}")
    nees = summary.get("pose_nees")
    if nees:
        median = f"{nees['median']:.2f}" if abs(nees["median"]) < 1e4 else f"{nees['median']:.3g}"
        lines.append(f"pose covariance: NEES median {median} over {counted(nees['poses'], 'pose')} (5.35 when "
                     f"honest), {100 * nees['within_95']:.1f} % within chi-square(6)'s 95 % bound (95 % when honest)")
    if summary.get("velocity_m_s") is None:
        lines.append("(no velocity errors: they need velocities on both sides, paired after the settle time: a "
                     "run's states.csv, once its rates settled, and a groundtruth.csv)")
    return "\n".join(lines)


def paper_table(summary: dict) -> str:
    """Markdown table: our max / p95 / RMS beside the paper's ± bounds, per axis."""
    rows = [
        "| error | axis (ours) | paper (3.5 m) | ours max | ours p95 | ours RMS | within paper |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    camera_axes = {"x": "x lateral", "y": "y lateral", "z": "z viewing"}
    body_axes = {"x": "x body", "y": "y body", "z": "z body"}  # omega_body: not the camera's axes
    for group, bounds in PAPER_BOUNDS.items():
        if summary.get(group) is None:
            continue
        title, unit, scale = _DISPLAY[group]
        axis_note = body_axes if group == "omega_rad_s" else camera_axes
        for axis, bound in bounds.items():
            st = summary[group][axis]
            if group == "omega_rad_s":
                paper = f"±{PAPER_OMEGA_MOSTLY_RAD_S * scale:.2f} mostly, ±{bound * scale:.1f} peaks {unit}"
                ok = st["max"] <= bound and st["p95"] <= PAPER_OMEGA_MOSTLY_RAD_S
            else:
                paper = f"±{bound * scale:g} {unit}"
                ok = st["max"] <= bound
            rows.append(
                f"| {title} | {axis_note[axis]} | {paper} | {st['max'] * scale:.3f} {unit} | "
                f"{st['p95'] * scale:.3f} {unit} | {st['rms'] * scale:.3f} {unit} | {'yes' if ok else 'no'} |"
            )
    return "\n".join(rows)


def error_table_csv(evaluation: Evaluation) -> str:
    """The per-frame error time series as CSV text (SI units, camera frame; omega in the
    true body frame), each column named with its unit: ``t_s, ex_m..ez_m, e_norm_m, ax_rad..az_rad,
    a_total_rad, [evx_m_s..evz_m_s, ewx_rad_s..ewz_rad_s,] speed_score`` (dimensionless)."""
    e = evaluation.errors
    cols = ["t_s", "ex_m", "ey_m", "ez_m", "e_norm_m", "ax_rad", "ay_rad", "az_rad", "a_total_rad"]
    data = [e.t_s[:, None], e.position_m, np.linalg.norm(e.position_m, axis=1)[:, None],
            e.attitude_rad, e.attitude_total_rad[:, None]]
    if e.velocity_m_s is not None and e.omega_rad_s is not None:
        cols += ["evx_m_s", "evy_m_s", "evz_m_s", "ewx_rad_s", "ewy_rad_s", "ewz_rad_s"]
        data += [e.velocity_m_s, e.omega_rad_s]
    cols.append("speed_score")
    data.append(e.speed_score[:, None])
    table = np.hstack(data)
    # A value not known (a frame's rates before the fit has them) is an empty field, as in
    # states.csv and targets.csv, not Python's "nan" that some CSV readers take for text.
    return ",".join(cols) + "\n" + "".join(",".join(repr(float(v)) if math.isfinite(v) else "" for v in row) + "\n"
                                           for row in table)


def error_plot_title(group: str) -> str:
    """An error plot's title, on two lines (one was cut at the figure's 880 px), with the axes
    its panels are in: the angular velocity's are the body's (an outside probe read "z = viewing
    axis" above the body-frame omega), the others the camera's."""
    title = _DISPLAY[group][0]
    axes = "body axes" if group == "omega_rad_s" else "camera axes, z = the viewing axis"
    return f"{title} error (estimate - truth), {axes}\ndashed: the paper's bounds at 3.5 m"


def render_error_plots(evaluation: Evaluation) -> dict[str, bytes]:
    """PNG plots of the errors against time, one panel per axis (the paper's Figs. 6 and 7),
    in mm, deg, mm/s and deg/s, with the paper's ± bounds dashed: file name -> PNG bytes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    e = evaluation.errors
    t = e.t_s - e.t_s[0]
    # Break the lines where poses are missing (more than 1.5 typical intervals), so a gap is
    # not drawn as a straight line across it.
    gaps = np.zeros(0, dtype=int)
    if len(t) > 2:
        dt = np.diff(t)
        gaps = np.flatnonzero(dt > 1.5 * np.median(dt)) + 1
    t = np.insert(t, gaps, np.nan)
    groups = [("position_m", e.position_m), ("attitude_rad", e.attitude_rad)]
    if e.velocity_m_s is not None and e.omega_rad_s is not None:
        groups += [("velocity_m_s", e.velocity_m_s), ("omega_rad_s", e.omega_rad_s)]
    plots = {}
    for group, values in groups:
        title, unit, scale = _DISPLAY[group]
        fig, axes = plt.subplots(3, 1, figsize=(8, 6.5), sharex=True)
        for i, (ax, axis) in enumerate(zip(axes, "xyz")):
            ax.plot(t, np.insert(values[:, i] * scale, gaps, np.nan), lw=0.9)
            bound = PAPER_BOUNDS[group][axis] * scale
            ax.axhline(bound, ls="--", c="grey", lw=0.8)
            ax.axhline(-bound, ls="--", c="grey", lw=0.8)
            ax.set_ylabel(f"{axis} [{unit}]")
            ax.grid(alpha=0.3)
        axes[0].set_title(error_plot_title(group), fontsize=10)
        axes[-1].set_xlabel("time since the first evaluated pose [s]")
        fig.tight_layout()
        plots[REPORT_PLOTS[list(_DISPLAY).index(group)]] = figure_png(fig)
        plt.close(fig)
    return plots


def figure_png(fig: Figure) -> bytes:
    """A matplotlib figure as PNG bytes (written to disk by the caller, with its other files)."""
    import io

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    return buffer.getvalue()


#: The files ``write_evaluation`` puts in its folder (a report of a run is stale once the run
#: is replaced: ``track --overwrite`` removes them).
REPORT_FILES = ("summary.json", "errors.csv", "report.md", "position_error.png", "attitude_error.png",
                "velocity_error.png", "omega_error.png")


def check_report_directory(directory: str | Path, report_files: Sequence[str] = REPORT_FILES,
                           report: str = "a report", beside_a_run: bool = True) -> Path:
    """``directory`` as a Path when a report can be written there; nothing is created.

    The folder is new, empty, or an earlier report's (``report_files[0]`` there: it is replaced,
    made again from the same files, with whatever the user keeps beside it); with ``beside_a_run``
    (evaluate's report) also a run's folder, or one holding a run's files.

    Raises:
        TrackmeterError: it is a file, a sequence folder (a recording is not mixed with
            reports), a folder of other files, or its nearest existing parent is not a folder
            this process may write in.
    """
    from trackmeter.data.rundir import refuse_other_files, run_folder_files

    path = check_output_folder(directory, "reports", "a report folder")
    if not ((path / report_files[0]).exists() or (beside_a_run and (path / "run.yaml").exists())):
        # Not an earlier report's folder (its first file, not any of its names: a lone
        # report.md is the user's) nor a run's: only what a run may hold without run.yaml.
        ours = run_folder_files(path) if beside_a_run else frozenset()
        refuse_other_files(path, ours, f"{report}'s folder is new, empty or an earlier one's"
                                       + (" or a run's" if beside_a_run else ""))
    return path


def write_evaluation(evaluation: Evaluation, out_dir: str | Path, settings: dict[str, Any]) -> list[Path]:
    """Write ``summary.json``, ``errors.csv``, the PNG plots and ``report.md`` into ``out_dir``.

    ``settings`` says what was compared and how (``truth``, ``estimate``, ``align``,
    ``settle_s``, ``tolerance_s``, ``case``): ``summary.json`` carries it under ``"settings"``,
    so the file reads alone.
    """
    out = check_report_directory(out_dir)
    s = evaluation.summary
    truth, estimate, align, settle_s = (settings[k] for k in ("truth", "estimate", "align", "settle_s"))
    plots = render_error_plots(evaluation)
    offset = ""
    if evaluation.body_offset is not None:
        from scipy.spatial.transform import Rotation

        R, t = evaluation.body_offset
        rv = Rotation.from_matrix(R).as_rotvec(degrees=True)
        offset = (
            f"\nBody-frame offset fitted (`--align body`, T_bodytrue_bodyest): rotation vector "
            f"[{rv[0]:.3f}, {rv[1]:.3f}, {rv[2]:.3f}] deg, translation "
            f"[{t[0] * 1e3:.2f}, {t[1] * 1e3:.2f}, {t[2] * 1e3:.2f}] mm.\n"
        )
    coverage = ("" if s.get("pose_coverage") is None
                else f"; frames after the settle (in the truth's span) with a pose: {100 * cast(float, s['pose_coverage']):.1f} %")
    report = f"""# Trajectory evaluation

- truth: `{truth}`
- estimate: `{estimate}`
- alignment: `{align}`; settle time skipped: {settle_s:g} s
- matched poses: {s['matched']}; unmatched: {s['unmatched']}{coverage}
- SPEED score (mean orientation error [rad] + relative position error): {s['speed_score']:.6f}
{offset}
## Ours beside the paper

The paper's figures are the bounds of its trial error plots at 3.5 m (section 4, Figs. 6-7).
Its viewing axis was **y**; ours is **z** (x, y lateral), and the table maps the paper's
figures onto our axes. Attitude errors are eq. 17 components in the camera frame (eq. 16 total
below); angular velocity errors are in the body frame (eq. 14).

{paper_table(s)}

## All figures (SI units converted to mm, deg)

```
{format_summary(s)}
```

## Plots

""" + "".join(f"![{Path(name).stem}]({name})\n" for name in plots)
    files = {out / "summary.json": (json_text({**s, "settings": settings}) + "\n").encode(), out / "errors.csv": error_table_csv(evaluation).encode(),
             **{out / name: png for name, png in plots.items()}, out / "report.md": report.encode("utf-8", "surrogateescape")}
    write_files_atomic(files)
    # An earlier report's plots this one has none of (a run folder's velocity plots, then a TUM
    # pair's report without velocities) would sit beside a report that does not show them.
    for name in REPORT_PLOTS:
        if name not in plots:
            (out / name).unlink(missing_ok=True)
    return list(files)
