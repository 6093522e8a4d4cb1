"""A ``trackmeter track`` run directory (DESIGN.md section 6), written while frames arrive.

::

    DIR/trajectory.tum   valid poses only, TUM (t tx ty tz qx qy qz qw), pose T_cam_body
    DIR/states.csv       t,valid,x,y,z,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz,n_tracked,n_lost,latency_ms
                         one row per frame; valid 1 when every field is a number (pose and
                         rates), so a reader may use a valid row as it would groundtruth.csv.
                         A valid pose whose rates are not estimated yet (the velocity fit's
                         first poses after the pose is found) is a row with valid 0 that
                         carries the pose and leaves the rates empty; with no pose, the pose
                         fields are empty too.
    DIR/targets.csv      t,id,state,u,v,u_right,v_right,x,y,z,score  one row per target per frame
    DIR/run.yaml         config, source, versions; the summary once the run ends

Every row is written whole or not at all, and a frame goes into all three files or none, so an
interrupted run (Ctrl-C, a source that fails, a disk that fills) leaves complete, readable
files; ``run.yaml`` is rewritten atomically (``status:
running`` at the start, the final status and summary at the end).
"""

from __future__ import annotations

import contextlib
import errno
import os
import platform
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Collection, Sequence

import numpy as np
import yaml
from numpy.typing import NDArray

from trackmeter.core.targets import TargetState
from trackmeter.core.transforms import matrix_to_quat_wxyz, quat_sign_nearest
from trackmeter.data.motion_csv import STATES_COLUMNS, MotionCsvWriter
from trackmeter.data.atomic import (AppendFile, FolderLock, SpaceReserve, claim_folder, folder_identity, repoint,
                                    write_text_atomic)
from trackmeter.data.sequence import check_output_folder
from trackmeter.data.trajectory import format_tum_line
from trackmeter.errors import TrackmeterError, counted

#: Header of ``targets.csv`` (a contract, DESIGN.md section 6).
TARGETS_COLUMNS: tuple[str, ...] = ("t", "id", "state", "u", "v", "u_right", "v_right", "x", "y", "z", "score")

#: Axes of a pose's covariance: position x, y, z (m) and the rotation vector's x, y, z (rad),
#: both in the camera frame (:attr:`trackmeter.pipeline.snapshot.PoseEstimate.cov_pose`).
POSE_AXES: tuple[str, ...] = ("x", "y", "z", "rx", "ry", "rz")
#: Header of ``pose_covariance.csv``: the time, then the 6x6 covariance's upper triangle row by
#: row (``x_x, x_y, ..., x_rz, y_y, ..., rz_rz``; m², m rad, rad²). Not a DESIGN.md contract:
#: ``states.csv``'s columns are, so the covariance has a file of its own.
POSE_COVARIANCE_COLUMNS: tuple[str, ...] = ("t", *(f"{POSE_AXES[i]}_{POSE_AXES[j]}" for i in range(6) for j in range(i, 6)))
_UPPER = np.triu_indices(6)

_RUN_FILES = ("trajectory.tum", "states.csv", "pose_covariance.csv", "targets.csv", "run.yaml")
# Held while a run is written, released for the final run.yaml when the disk is full; the
# name is the reserve's only while it is written (then an open descriptor holds its space).
RESERVE_NAME = ".run.yaml.reserve"
#: Where ``--overwrite`` keeps the earlier run (its files and report) until the new one has
#: tracked (:class:`RunWriter`); left there only by a writer killed outright.
PREVIOUS_RUN = ".previous-run"
#: Statuses of a run that tracked nothing (refused on its first frame, or given no frame): with
#: ``--overwrite`` the earlier run is given back.
UNTRACKED_STATUSES = frozenset({"nothing to track", "no frame"})
# Bytes held beyond the first run.yaml's size: the final one adds the status, the summary (its
# invalid reasons, tracker and engine counts: about 2 KB on estec) and the finish time.
RESERVE_EXTRA_BYTES = 32 * 1024


def _num(value: float, fmt: str = ".9f") -> str:
    return "" if value is None or not np.isfinite(value) else format(float(value), fmt)


def _csv_text(text: str) -> str:
    """``text`` as one CSV field (RFC 4180, as :mod:`csv` writes it with minimal quoting): a
    target id from a model file may hold a comma or a quote, which would otherwise shift the
    row's columns for every reader."""
    if any(c in text for c in ',"\r\n'):
        return '"' + text.replace('"', '""') + '"'
    return text


def versions() -> dict[str, str]:
    """Versions of the software that made the run."""
    import cv2
    import scipy

    from trackmeter import __version__

    return {
        "trackmeter": __version__,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "opencv": cv2.__version__,
    }


def check_run_directory(directory: str | Path, overwrite: bool = False) -> Path:
    """``directory`` as a Path when a run can be written there; nothing is created.

    Called before a run opens its source, so a bad ``--out`` is the one line the user sees.

    Raises:
        TrackmeterError: it is a file, holds a run already (without ``overwrite``), holds
            no run but files that are not a run's or its report's (even with ``overwrite``),
            is a sequence folder, or its nearest existing parent is not a folder this process
            may write in.
    """
    if not str(directory).strip():
        raise TrackmeterError("the run folder's name is empty")
    path = Path(directory)
    if (path / "run.yaml").exists() and not overwrite:
        raise TrackmeterError(f"{path}: holds a run already (run.yaml); choose another --out or give --overwrite")
    others = [name for name in _RUN_FILES if (path / name).exists()]
    if others and not overwrite:
        raise TrackmeterError(f"{path}: holds {', '.join(others)} already (not from a run: no run.yaml); "
                              "choose another --out or give --overwrite to replace them")
    check_output_folder(path, "a run's files", "a run folder")  # a sequence folder is told as one
    if not (path / "run.yaml").exists():
        # Not even with --overwrite: that replaces a run (whose folder may hold the user's
        # notes beside it), it does not mix one into a folder of other things (--out / or .
        # wrote run.yaml and three CSVs among them).
        refuse_other_files(path, run_folder_files(path), "a run folder is new, empty or an earlier run's")
    return path


def run_folder_files(path: Path) -> frozenset[str]:
    """The names a folder without ``run.yaml`` may hold and be a run's: a run's files and the
    reserve, and an evaluate report's where a run's file is there too (a ``states.csv``
    evaluated in place); a report alone is no run."""
    from trackmeter.data.evaluation import REPORT_FILES

    has_run = any((path / name).exists() for name in _RUN_FILES)
    return frozenset({*_RUN_FILES, RESERVE_NAME, *(REPORT_FILES if has_run else ())})


def refuse_other_files(path: Path, ours: Collection[str], what_is_allowed: str) -> None:
    """Refuse an existing folder ``path`` that holds files other than ``ours`` or hidden ones:
    a command's output is not mixed into a folder of other things (``--out .``, ``--out /``).

    Raises:
        TrackmeterError: naming up to three of the other files and ``what_is_allowed``.
    """
    if not path.is_dir():
        return
    foreign = sorted(e.name for e in path.iterdir() if e.name not in ours and not e.name.startswith("."))
    if foreign:
        shown = ", ".join(foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3 else "")
        raise TrackmeterError(f"{path}: holds other files ({shown}); {what_is_allowed}: choose another --out")


def _run_status(folder: Path) -> str | None:
    """The ``status`` of ``folder/run.yaml``, None when there is no readable one."""
    try:
        meta = yaml.safe_load((folder / "run.yaml").read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return None
    return meta.get("status") if isinstance(meta, dict) else None


class RunWriter:
    """Writes one run directory incrementally.

    Args:
        directory: created if missing; refused when it already holds a run (``run.yaml``)
            unless ``overwrite``.
        config: a plain dict of the configuration (``config_to_dict``).
        source: the source SPEC and what it carried (rig name, model, rate).
        overwrite: replace an earlier run's files (and its report). They are set aside in
            :data:`PREVIOUS_RUN` while the new run writes, and given back when it closes with
            one of :data:`UNTRACKED_STATUSES` (``kept_earlier_run``) or cannot start: bad input
            found on the first frame does not cost the earlier run. A run whose writes failed
            (a full disk) leaves it in :data:`PREVIOUS_RUN` (``earlier_run_kept_in``).

    Raises:
        TrackmeterError: the folder holds a run already, or cannot be written.
    """

    def __init__(self, directory: str | Path, config: dict[str, Any], source: dict[str, Any],
                 overwrite: bool = False, extra: dict[str, Any] | None = None) -> None:
        self.directory = check_run_directory(directory, overwrite)
        lock, created = claim_folder(self.directory, "another run", lambda: check_run_directory(self.directory, overwrite),
                                     f"{self.directory}: cannot create")
        self._lock: FolderLock | None = lock
        self._begun: list[Path] = []  # the files this writer wrote or truncated, in order
        self._reserve: SpaceReserve | None = None
        self._previous: Path | None = None
        self.kept_earlier_run = False
        #: Where the run this one was replacing is kept when this one's writes failed, else None.
        self.earlier_run_kept_in: Path | None = None
        try:
            if overwrite:
                self._set_aside()
            self._open(config, source, extra)
        except BaseException:
            # Nothing half-made left behind (e.g. a disk already full): the files this writer
            # began, not an earlier run's it was to replace (--overwrite: given back), and the
            # folder when it made it; the lock last.
            for path in self._begun:
                path.unlink(missing_ok=True)
            self._give_back()
            if created:
                with contextlib.suppress(OSError):
                    self.directory.rmdir()
            self._release_lock()
            raise
        # The folder's identity: removed (or replaced) while the run writes, the open files would
        # go on into the deleted one and the closing run.yaml make a new folder of its own.
        self._folder_id = folder_identity(self.directory)
        self.folder_lost = False
        self.frames = 0
        self.valid_frames = 0
        # Valid poses carried on the motion model with no point measured (the states.csv
        # columns are a contract, so the count goes to the summary, not a new column).
        self.coasted_frames = 0
        # When: each run of consecutive coasted frames as [first, last] frame time, s.
        self.coasted_spans_s: list[list[float]] = []
        self._coasting = False
        # Valid poses whose rates were not estimated yet (states.csv valid 0, pose filled in).
        self.rates_pending_frames = 0
        # The quaternion last written: each next one takes the sign nearer it (no flips in the files).
        self._last_quat_wxyz: np.ndarray | None = None

    def _set_aside(self) -> None:
        """Move the earlier run's files and its report into :data:`PREVIOUS_RUN` (a leftover of
        a writer killed outright replaced), kept as ``_previous`` from the first move on."""
        import shutil

        from trackmeter.data.evaluation import REPORT_FILES

        names = [n for n in (*_RUN_FILES, *REPORT_FILES) if (self.directory / n).exists()]
        previous = self.directory / PREVIOUS_RUN
        if previous.is_dir() and not previous.is_symlink() and _run_status(self.directory) == "running":
            # A writer killed outright during an --overwrite: its files are of no use, and the
            # earlier run it had set aside is still the one this run is to replace.
            for name in names:
                (self.directory / name).unlink(missing_ok=True)
            self._previous = previous
            return
        if not names:
            return
        if previous.is_dir() and not previous.is_symlink():
            shutil.rmtree(previous)
        elif previous.exists() or previous.is_symlink():
            previous.unlink()
        previous.mkdir()
        self._previous = previous
        for name in names:
            os.replace(self.directory / name, previous / name)

    def _give_back(self) -> None:
        """Put the earlier run set aside by :meth:`_set_aside` back (its names freed first)."""
        if self._previous is None:
            return
        for entry in list(self._previous.iterdir()):
            os.replace(entry, self.directory / entry.name)
        self._previous.rmdir()
        self._previous = None

    def _open(self, config: dict[str, Any], source: dict[str, Any], extra: dict[str, Any] | None) -> None:
        self._meta: dict[str, Any] = {
            "status": "running",
            "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "command": " ".join(sys.argv),
            "source": source,
            "versions": versions(),
            **(extra or {}),
            "config": config,
        }
        text = self._write_meta()  # atomic: the earlier run.yaml stays whole until this one is
        self._begun.append(self.directory / "run.yaml")
        # A disk the rows fill would leave run.yaml saying "running": the space its final
        # version needs is held from the start (tests/test_rundir.py fills a real one).
        self._reserve = SpaceReserve(self.directory / RESERVE_NAME, len(text.encode("utf-8")) + RESERVE_EXTRA_BYTES,
                                     "run.yaml's final version")
        # Each file counts as begun before it is opened: opening truncates it.
        self._begun.append(self.directory / "states.csv")
        self._states = MotionCsvWriter(self.directory / "states.csv", STATES_COLUMNS)
        self._begun.append(self.directory / "trajectory.tum")
        self._tum: AppendFile | None = AppendFile(self.directory / "trajectory.tum", "# t tx ty tz qx qy qz qw  (T_cam_body)\n")
        self._begun.append(self.directory / "pose_covariance.csv")
        self._cov = AppendFile(self.directory / "pose_covariance.csv", ",".join(POSE_COVARIANCE_COLUMNS) + "\n")
        self._begun.append(self.directory / "targets.csv")
        self._targets: AppendFile | None = AppendFile(self.directory / "targets.csv", ",".join(TARGETS_COLUMNS) + "\n")

    def _write_meta(self) -> str:
        """Write run.yaml from ``self._meta``; returns the text written. On a full disk the
        space reserve, if still held, is released and the write tried once more."""
        path = self.directory / "run.yaml"
        text = yaml.safe_dump(self._meta, sort_keys=False, allow_unicode=True)
        try:
            try:
                write_text_atomic(path, text)
            except OSError as exc:
                if exc.errno not in (errno.ENOSPC, errno.EDQUOT) or self._reserve is None or not self._reserve.release():
                    raise
                write_text_atomic(path, text)
        except OSError as exc:
            raise TrackmeterError(f"{path}: cannot write ({exc.strerror or exc})") from None
        return text

    def write_frame(self, t_s: float, targets: Sequence[TargetState], pose: Any, latency_ms: float = float("nan")) -> None:
        """Append one frame: a ``states.csv`` row, its targets, and the pose when valid.

        ``pose`` is a :class:`trackmeter.pipeline.snapshot.PoseEstimate`.
        """
        if self._tum is None or self._targets is None:
            raise TrackmeterError(f"{self.directory}: run writer is closed")
        self._check_folder()
        # A frame is in all three files or in none: a write that fails (a full disk) takes
        # back what this frame had written to the others.
        sizes = (self._states.size, self._states.rows_written, self._tum.size, self._cov.size, self._targets.size)
        try:
            self._write_frame(t_s, targets, pose, latency_ms)
        except TrackmeterError:
            self._states.truncate(sizes[0], sizes[1])
            self._tum.truncate(sizes[2])
            self._cov.truncate(sizes[3])
            self._targets.truncate(sizes[4])
            raise

    def _write_frame(self, t_s: float, targets: Sequence[TargetState], pose: Any, latency_ms: float) -> None:
        assert self._tum is not None and self._targets is not None
        n_tracked = sum(1 for s in targets if s.measured)
        n_lost = len(targets) - n_tracked
        rates_known = False
        if pose.valid:
            p = pose.T_cam_body[:3, 3]
            q = quat_sign_nearest(matrix_to_quat_wxyz(pose.T_cam_body[:3, :3]), self._last_quat_wxyz)
            rates_known = bool(np.all(np.isfinite(pose.velocity_cam_m_s)) and np.all(np.isfinite(pose.omega_body_rad_s)))
            self._states.write(t=t_s, valid=int(rates_known), position_m=p, quat_wxyz=q,
                               velocity_cam_m_s=pose.velocity_cam_m_s, omega_body_rad_s=pose.omega_body_rad_s,
                               n_tracked=n_tracked, n_lost=n_lost, latency_ms=latency_ms)
            self._tum.append(format_tum_line(t_s, p, q) + "\n")
            cov = np.asarray(pose.cov_pose, dtype=float)
            self._cov.append(",".join([f"{t_s:.9f}", *(_num(c, ".9e") for c in (cov + cov.T)[_UPPER] / 2.0)]) + "\n")
        else:
            self._states.write(t=t_s, valid=0, n_tracked=n_tracked, n_lost=n_lost, latency_ms=latency_ms)
        lines = []
        for s in targets:
            uv, uvr, x = s.uv, s.uv_right, s.point_cam
            lines.append(",".join([
                f"{t_s:.9f}", _csv_text(s.id), s.status, _num(uv[0], ".4f"), _num(uv[1], ".4f"), _num(uvr[0], ".4f"),
                _num(uvr[1], ".4f"), _num(x[0]), _num(x[1]), _num(x[2]), _num(s.score, ".5f"),
            ]) + "\n")
        if lines:
            self._targets.append("".join(lines))  # one frame's rows in one write
        self.frames += 1
        if pose.valid:
            self._last_quat_wxyz = q
            self.valid_frames += 1
            self.rates_pending_frames += not rates_known
        coasting = bool(pose.valid and getattr(pose, "coasting_s", 0.0) > 0.0)
        if coasting:
            self.coasted_frames += 1
            t = round(float(t_s), 9)  # as states.csv writes it
            if self._coasting:
                self.coasted_spans_s[-1][1] = t
            else:
                self.coasted_spans_s.append([t, t])
        self._coasting = coasting

    def close(self, status: str = "complete", summary: dict[str, Any] | None = None) -> None:
        """Close the files and rewrite ``run.yaml`` with the final status and summary."""
        if self._tum is None:
            return
        try:
            self._close(status, summary)
            self._settle_previous(status)
        finally:
            if self._reserve is not None:
                self._reserve.release()
            self._release_lock()

    def _settle_previous(self, status: str) -> None:
        """With ``--overwrite``: a run that tracked nothing (:data:`UNTRACKED_STATUSES`) gives
        the earlier run back, its own files removed; any other replaces it. (A close that
        failed leaves both, the earlier one in :data:`PREVIOUS_RUN`: nothing is lost.)"""
        if self._previous is None:
            return
        if status in UNTRACKED_STATUSES or self.frames == 0:  # interrupted before its first frame too
            for name in _RUN_FILES:
                (self.directory / name).unlink(missing_ok=True)
            self._give_back()
            self.kept_earlier_run = True
        elif status == "write failed":
            # Cut short by the disk, not a replacement the user would choose: the earlier run
            # stays beside it (the next --overwrite of the folder replaces it).
            self.earlier_run_kept_in = self._previous
            self._previous = None
        else:
            import shutil

            shutil.rmtree(self._previous, ignore_errors=True)
            self._previous = None

    def _check_folder(self) -> None:
        """Follows the run folder when it was moved (renamed) while the run writes: the open
        files went with it, and so do the rest of the run and its closing run.yaml, said once.
        Raises TrackmeterError (and sets ``folder_lost``) when it is gone or another folder is
        in its place: what was written went with the old one."""
        if not self.folder_lost and folder_identity(self.directory) == self._folder_id:
            return
        moved = None if self.folder_lost or self._lock is None else self._lock.follow_move()
        if moved is not None:
            old, self.directory = self.directory, moved
            self._begun = [repoint(p, old, moved) for p in self._begun]
            if self._previous is not None:
                self._previous = repoint(self._previous, old, moved)
            for file in (self._states, self._tum, self._cov, self._targets):
                if file is not None:
                    file.path = repoint(file.path, old, moved)
            warnings.warn(f"{old}: the run folder was moved to {moved} while the run wrote to it; the run goes on "
                          "there", stacklevel=3)
            return
        self.folder_lost = True
        lost = (f"; the {counted(self.frames, 'frame')} written there {'is' if self.frames == 1 else 'are'} lost"
                if self.frames else ", before its first frame")
        raise TrackmeterError(f"{self.directory}: the run folder was removed or replaced while the run wrote to it{lost}")

    def _close(self, status: str, summary: dict[str, Any] | None) -> None:
        assert self._tum is not None
        self._states.close()
        self._tum.close()
        self._cov.close()
        if self._targets is not None:
            self._targets.close()
        self._tum = self._targets = None
        self._check_folder()  # no run.yaml alone in a folder made anew for it
        self._meta["status"] = status
        self._meta["finished_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        self._meta["summary"] = {"frames": self.frames, "valid_frames": self.valid_frames,
                                 "coasted_frames": self.coasted_frames, "coasted_spans_s": self.coasted_spans_s,
                                 "rates_pending_frames": self.rates_pending_frames, **(summary or {})}
        # Keep config last: the summary is what a reader looks for first.
        config = self._meta.pop("config")
        self._meta["config"] = config
        self._write_meta()

    def _release_lock(self) -> None:
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def __enter__(self) -> RunWriter:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        self.close("interrupted" if exc_type is not None else "complete")


def read_pose_covariance(path: str | Path) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A run's ``pose_covariance.csv``: ``(t_s (N,), cov (N,6,6))``, one per valid pose (the
    lines of its ``trajectory.tum``), axes :data:`POSE_AXES`; an empty field (how the writer
    gives a value that is not a number) reads as NaN. Left out, with a warning: a last line
    without its line end (the writer ends every row with one: it was cut off, perhaps inside a
    number) and the rows of a time given twice with different values (which one holds?).

    Raises:
        TrackmeterError: not such a file (its header), or a row that is not a time and 21 values."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise TrackmeterError(f"{path}: cannot read ({getattr(exc, 'strerror', None) or exc})") from None
    lines = text.splitlines()
    if not lines or lines[0].strip() != ",".join(POSE_COVARIANCE_COLUMNS):
        raise TrackmeterError(f"{path}: not a pose_covariance.csv (its header must be {','.join(POSE_COVARIANCE_COLUMNS[:4])},...)")
    if len(lines) > 1 and not text.endswith(("\n", "\r")):
        warnings.warn(f"{path}: its last line is cut off (no line end): left out", stacklevel=2)
        lines = lines[:-1]
    rows = [ln for ln in lines[1:] if ln.strip()]
    values = np.full((len(rows), len(POSE_COVARIANCE_COLUMNS)), np.nan)
    for k, line in enumerate(rows):
        fields = line.split(",")
        try:
            if len(fields) != len(POSE_COVARIANCE_COLUMNS):
                raise ValueError
            values[k] = [float(f) if f.strip() or i == 0 else np.nan for i, f in enumerate(fields)]
        except ValueError:
            raise TrackmeterError(f"{path}: line {k + 2}: expected {len(POSE_COVARIANCE_COLUMNS)} numbers") from None
    first: dict[float, int] = {}
    ambiguous: set[float] = set()
    keep = np.ones(len(values), dtype=bool)
    for k, row in enumerate(values):
        j = first.setdefault(float(row[0]), k)
        if j != k:
            keep[k] = False  # the same time again: one row is enough when they agree
            if not np.array_equal(row, values[j], equal_nan=True):
                ambiguous.add(float(row[0]))
    if ambiguous:
        warnings.warn(f"{path}: {counted(len(ambiguous), 'time')} given twice with different values: left out",
                      stacklevel=2)
        keep &= ~np.isin(values[:, 0], list(ambiguous))
    values = values[keep]
    cov = np.zeros((len(values), 6, 6))
    cov[:, _UPPER[0], _UPPER[1]] = values[:, 1:]
    cov[:, _UPPER[1], _UPPER[0]] = values[:, 1:]
    return values[:, 0], cov
