"""Motion CSV files: a sequence's ``groundtruth.csv`` and a run's ``states.csv`` (DESIGN.md 6).

Both are comma-separated with a one-line header and one row per frame, sharing the meaning of
their columns:

- ``groundtruth.csv``: ``t,x,y,z,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz``
- ``states.csv``: ``t,valid,x,y,z,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz,n_tracked,n_lost,latency_ms``

``t`` in seconds; ``x,y,z`` the body origin in the left camera frame (m) and ``qw..qz`` the
scalar-first attitude of ``T_cam_body``; ``vx,vy,vz`` the velocity of the body origin in the
camera frame (m/s); ``wx,wy,wz`` the angular velocity in the BODY frame (rad/s, paper eq. 14);
``valid`` 0/1: 1 when every field of the row is a number, so a valid row reads like a
``groundtruth.csv`` row; a row with ``valid = 0`` may carry empty or ``nan`` fields (a run writes
a pose whose rates are not estimated yet as ``valid = 0``, the pose filled in, the rates empty).
Any further column (``n_tracked``, ``latency_ms``, ...) is kept as a float array in
:attr:`MotionSeries.extra`.

One reader (:func:`read_motion_csv`) reads both; :func:`write_groundtruth_csv` and
:func:`write_states_csv` write a whole series atomically; :class:`MotionCsvWriter` appends one
complete, flushed row at a time for writers that run while frames arrive (a ``track`` run, a
sequence being rendered), so a reader never sees half a row.
"""

from __future__ import annotations

import math
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from trackmeter.core.checks import time_order
from trackmeter.core.transforms import quat_signs_continuous
from trackmeter.data.atomic import AppendFile, write_text_atomic
from trackmeter.data.trajectory import Trajectory, warn_far_from_unit_norm
from trackmeter.errors import TrackmeterError, quoted

FloatArray = NDArray[np.float64]

#: Columns every motion CSV must have: time and pose ``T_cam_body``.
POSE_COLUMNS: tuple[str, ...] = ("t", "x", "y", "z", "qw", "qx", "qy", "qz")
#: Velocity of the body origin in cam (m/s) and omega in the body frame (rad/s).
RATE_COLUMNS: tuple[str, ...] = ("vx", "vy", "vz", "wx", "wy", "wz")
#: Header of a sequence's ``groundtruth.csv`` (contract, DESIGN.md section 6).
GROUNDTRUTH_COLUMNS: tuple[str, ...] = POSE_COLUMNS + RATE_COLUMNS
#: Header of a run directory's ``states.csv`` (contract, DESIGN.md section 6).
STATES_COLUMNS: tuple[str, ...] = (
    ("t", "valid") + POSE_COLUMNS[1:] + RATE_COLUMNS + ("n_tracked", "n_lost", "latency_ms")
)
_KNOWN = set(GROUNDTRUTH_COLUMNS) | {"valid"}
_INT_COLUMNS = {"valid", "n_tracked", "n_lost"}


@dataclass(frozen=True, eq=False)
class MotionSeries:
    """Pose and velocities over time, as in ``groundtruth.csv`` / ``states.csv``.

    Attributes:
        t_s: (N,) timestamps, s, non-decreasing.
        valid: (N,) bool; False rows carry no usable pose (their values may be NaN).
        position_m: (N,3) body origin in the left camera frame, m.
        quat_wxyz: (N,4) attitude of ``T_cam_body``, scalar first, unit norm on valid rows.
        velocity_cam_m_s: (N,3) velocity of the body origin in the camera frame, m/s
            (NaN when unknown).
        omega_body_rad_s: (N,3) angular velocity in the body frame, rad/s (NaN when unknown).
        extra: further columns by name, each (N,) float (e.g. ``n_tracked``, ``latency_ms``).
    """

    t_s: FloatArray
    valid: NDArray[np.bool_]
    position_m: FloatArray
    quat_wxyz: FloatArray
    velocity_cam_m_s: FloatArray
    omega_body_rad_s: FloatArray
    extra: Mapping[str, FloatArray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        t = np.asarray(self.t_s, dtype=float).reshape(-1)
        n = len(t)

        def rows(value: Any, width: int, name: str) -> FloatArray:
            a = np.asarray(value, dtype=float)
            if a.size != n * width:
                raise TrackmeterError(f"motion series: {name} has {a.size} values, expected {n}x{width}")
            return a.reshape(n, width).copy()

        valid = np.asarray(self.valid, dtype=bool).reshape(-1)
        if valid.shape != (n,):
            raise TrackmeterError(f"motion series: valid has {valid.size} values, expected {n}")
        p = rows(self.position_m, 3, "position_m")
        q = rows(self.quat_wxyz, 4, "quat_wxyz")
        v = rows(self.velocity_cam_m_s, 3, "velocity_cam_m_s")
        w = rows(self.omega_body_rad_s, 3, "omega_body_rad_s")
        if not np.all(np.isfinite(t)):
            raise TrackmeterError("motion series: non-finite timestamp")
        time_order(t, "motion series")
        if not (np.all(np.isfinite(p[valid])) and np.all(np.isfinite(q[valid]))):
            raise TrackmeterError("motion series: a valid row has a non-finite pose")
        norms = np.linalg.norm(q[valid], axis=1)
        if np.any(norms < 1e-9):
            raise TrackmeterError("motion series: a valid row has a zero quaternion")
        q[valid] /= norms[:, None]
        extra = {str(k): rows(a, 1, str(k)).reshape(n) for k, a in dict(self.extra).items()}
        for a in (t, valid, p, q, v, w, *extra.values()):
            a.flags.writeable = False
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "valid", valid)
        object.__setattr__(self, "position_m", p)
        object.__setattr__(self, "quat_wxyz", q)
        object.__setattr__(self, "velocity_cam_m_s", v)
        object.__setattr__(self, "omega_body_rad_s", w)
        object.__setattr__(self, "extra", MappingProxyType(extra))

    def __len__(self) -> int:
        return len(self.t_s)

    @property
    def has_velocity(self) -> bool:
        """True when every valid row carries finite linear and angular velocities."""
        v = self.valid
        return bool(np.any(v)) and bool(
            np.all(np.isfinite(self.velocity_cam_m_s[v])) and np.all(np.isfinite(self.omega_body_rad_s[v]))
        )

    def valid_only(self) -> MotionSeries:
        """The same series restricted to its valid rows."""
        m = self.valid
        return MotionSeries(
            self.t_s[m], m[m], self.position_m[m], self.quat_wxyz[m],
            self.velocity_cam_m_s[m], self.omega_body_rad_s[m], {k: a[m] for k, a in self.extra.items()},
        )

    def to_trajectory(self) -> Trajectory:
        """The valid poses as a :class:`Trajectory` (what ``trajectory.tum`` holds)."""
        m = self.valid
        if not np.any(m):
            raise TrackmeterError("motion series has no valid pose")
        return Trajectory(self.t_s[m], self.position_m[m], self.quat_wxyz[m])

    @classmethod
    def from_trajectory(
        cls,
        trajectory: Trajectory,
        velocity_cam_m_s: FloatArray | None = None,
        omega_body_rad_s: FloatArray | None = None,
    ) -> MotionSeries:
        """A series of valid poses from a trajectory; velocities NaN unless given."""
        n = len(trajectory)
        nan = np.full((n, 3), np.nan)
        return cls(
            trajectory.t_s, np.ones(n, dtype=bool), trajectory.position_m, trajectory.quat_wxyz,
            nan if velocity_cam_m_s is None else velocity_cam_m_s,
            nan if omega_body_rad_s is None else omega_body_rad_s,
        )

    def column(self, name: str) -> FloatArray:
        """Values of one CSV column by its header name, (N,) float."""
        index = {"x": 0, "y": 1, "z": 2}
        if name == "t":
            return self.t_s
        if name == "valid":
            return self.valid.astype(float)
        if name in index:
            return self.position_m[:, index[name]]
        if name in ("qw", "qx", "qy", "qz"):
            return self.quat_wxyz[:, "wxyz".index(name[1])]
        if name in ("vx", "vy", "vz"):
            return self.velocity_cam_m_s[:, index[name[1]]]
        if name in ("wx", "wy", "wz"):
            return self.omega_body_rad_s[:, index[name[1]]]
        if name in self.extra:
            return self.extra[name]
        raise TrackmeterError(f"motion series has no column {name!r}")


# --------------------------------------------------------------------------- reading


def header_fields(line: str) -> list[str]:
    """The column names of a motion CSV header line (a leading ``#``, as EuRoC writes its
    headers, is not part of the first name), EuRoC's ground-truth names read as ours
    (:func:`_our_name`). A name in double quotes (R's ``write.csv``, Python's ``csv.QUOTE_ALL``)
    is read without them."""
    return [_our_name(_unquoted(h).lstrip("#").strip()) for h in line.strip().lstrip("\ufeff").split(",")]


def _unquoted(field: str) -> str:
    """``field`` stripped of spaces, and of one pair of double quotes around it."""
    f = field.strip()
    return f[1:-1].strip() if len(f) >= 2 and f[0] == f[-1] == '"' else f


#: EuRoC's ground-truth column names (``state_groundtruth_estimate0/data.csv``, ``leica0``,
#: ``vicon0``: ``#timestamp [ns], p_RS_R_x [m], ..., q_RS_w [], ..., v_RS_R_x [m s^-1], ...``)
#: and ours: the pose ``T_R_S`` of frame S in R, scalar first, the velocity of S's origin in R.
#: Its ``b_w_RS_S_*`` are gyroscope biases, not an angular velocity: kept as extra columns.
#: The frame letters may be left out (``p_x [m]``, ``q_w []``).
_EUROC_NAMES = (
    (re.compile(r"timestamp", re.IGNORECASE), "t"),
    (re.compile(r"p_(?:[A-Za-z]+_)*([xyz])", re.IGNORECASE), r"\1"),
    (re.compile(r"q_(?:[A-Za-z]+_)*([wxyz])", re.IGNORECASE), r"q\1"),
    (re.compile(r"v_(?:[A-Za-z]+_)*([xyz])", re.IGNORECASE), r"v\1"),
)


def _our_name(name: str) -> str:
    """A header ``name`` as this module's columns name it: EuRoC's (:data:`_EUROC_NAMES`)
    mapped, with their unit in brackets left off; any other name as it is."""
    bare = re.sub(r"\s*\[[^\]]*\]$", "", name)
    for pattern, ours in _EUROC_NAMES:
        if pattern.fullmatch(bare):
            return pattern.sub(ours, bare).lower()
    return name


#: Separators other tools write CSV with, by the name a message gives them.
_OTHER_SEPARATORS = {"\t": "tabs", ";": "semicolons"}


def other_separator_header(path: Path | str, line_number: int, line: str) -> TrackmeterError | None:
    """The error for a header ``line`` of names separated by tabs or semicolons (a
    spreadsheet's export), not commas; None when it is not one."""
    name = _other_separator(line)
    if name is None:
        return None
    return TrackmeterError(f"{path}:{line_number}: a header of names separated by {name} "
                           f"({quoted(line.strip(), 40)}): a motion CSV's are separated by commas "
                           f"({','.join(GROUNDTRUTH_COLUMNS)})")


def _other_separator(line: str) -> str | None:
    """The name of the separator (tabs, semicolons) a header ``line`` is written with when not
    commas, else None. A ``#`` line must name a ``t`` column (EuRoC's headers are ``#`` lines,
    and a note with semicolons is not one)."""
    text = line.strip().lstrip("\ufeff")
    if len(header_fields(text)) > 1:
        return None
    for separator, name in _OTHER_SEPARATORS.items():
        names = [h.strip().lstrip("#").strip() for h in text.split(separator)]
        if names_a_header(names) and (not text.startswith("#") or "t" in names):
            return name
    return None


def names_a_header(fields: Sequence[str]) -> bool:
    """Whether a first line's ``fields`` are a motion CSV's header: more than one, with a
    ``t`` among them or no number (a header whose time column is renamed is still one)."""
    return len(fields) > 1 and ("t" in fields or not any(_is_number(f) for f in fields))


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def is_comment_line(line: str) -> bool:
    """A ``#`` line that is not a header: one that names no ``t`` column (e.g. a producer's
    note above the header)."""
    text = line.strip().lstrip("\ufeff")
    return text.startswith("#") and "t" not in header_fields(text) and _other_separator(text) is None


def read_motion_csv(path: str | Path) -> MotionSeries:
    """Read a ``groundtruth.csv`` or ``states.csv`` (any column order; header required).

    Columns ``t,x,y,z,qw,qx,qy,qz`` are required (EuRoC's ``#timestamp, p_RS_R_x [m], ...,
    q_RS_w [], ...`` name them too: :data:`_EUROC_NAMES`); missing velocity columns read as NaN.
    Without a ``valid`` column (a ``groundtruth.csv``) a row is valid when its pose is whole; a
    row with an empty or ``nan`` pose field is read as invalid, with a warning. Empty fields
    and ``nan`` read as NaN. Blank lines and ``#`` lines (comments) are skipped. Rows are kept
    in file order and must not go back in time.

    Raises:
        TrackmeterError: naming the file (and line) when it is missing, empty, has no header
            with the required columns, a row of the wrong width, a value that is not a number,
            or a valid (1) row without a whole pose.
    """
    path = Path(path)
    if not path.is_file():
        raise TrackmeterError(f"{path}: no such file")
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError:
        raise TrackmeterError(f"{path}: not a text file (a motion CSV is a header line, then rows of numbers: "
                              f"{','.join(GROUNDTRUTH_COLUMNS)})") from None
    except OSError as exc:
        raise TrackmeterError(f"{path}: cannot read: {exc.strerror or exc}") from None
    numbered = [(i, line.strip()) for i, line in enumerate(lines, 1) if line.strip()]
    comment_before: tuple[int, str] | None = None  # the last comment line above the header
    while numbered and is_comment_line(numbered[0][1]):
        comment_before = numbered.pop(0)
    if not numbered:
        raise TrackmeterError(f"{path}: empty file")
    header_line, header_text = numbered[0]
    header = header_fields(header_text)
    missing = [c for c in POSE_COLUMNS if c not in header]
    if missing and (other := other_separator_header(path, header_line, header_text)) is not None:
        raise other
    if missing:
        # TUM's header comment written with commas: a TUM file, told so rather than a CSV's columns
        tum_names = {"tx", "ty", "tz", "qx", "qy", "qz", "qw"} <= set(header)
        raise TrackmeterError(
            f"{path}:{header_line}: " + (
                "reads as a TUM trajectory, whose fields are separated by spaces (t tx ty tz qx qy qz qw), "
                "but this one uses commas" if tum_names else
                f"not a motion CSV: header lacks {','.join(missing)} (expected {','.join(GROUNDTRUTH_COLUMNS)})"
                + (f"; line {comment_before[0]} above it is a comment ({quoted(comment_before[1], 40)}): a header "
                   "has no '#' and these column names"
                   if comment_before is not None and "," in comment_before[1] else ""))
        )
    if len(set(header)) != len(header):
        raise TrackmeterError(f"{path}:{header_line}: repeated column in the header")
    rates_missing = [c for c in RATE_COLUMNS if c not in header]
    if "valid" in header and 0 < len(rates_missing) < len(RATE_COLUMNS):
        # A run's states.csv (its "valid" column) with some of the rates was meant to have all; a
        # pose-only file says nothing of rates, and a ground truth may have only some (EuRoC's v).
        warnings.warn(f"{path}:{header_line}: the header has {','.join(c for c in RATE_COLUMNS if c in header)} but "
                      f"not {','.join(rates_missing)}: those read as unknown, and no velocity is compared without "
                      f"both the linear and the angular one", stacklevel=2)
    rows = [(number, text) for number, text in numbered[1:] if not text.startswith("#")]  # comments, as in data.csv
    if len(rows) >= 2 and 1 < len(rows[-1][1].split(",")) < len(header):
        # A writer stopped mid-line (killed, a full disk): the rows before it are whole.
        number, text = rows.pop()
        warnings.warn(f"{path}:{number}: the last line is cut short ({len(text.split(','))} of {len(header)} values), "
                      "left out", stacklevel=2)
    values = np.empty((len(rows), len(header)))
    for r, (number, text) in enumerate(rows):
        fields = text.split(",")
        if len(fields) != len(header):
            raise TrackmeterError(f"{path}:{number}: expected {len(header)} values, got {len(fields)}")
        for c, f in enumerate(fields):
            f = _unquoted(f)
            try:
                values[r, c] = float(f) if f else math.nan
            except ValueError:
                raise TrackmeterError(f"{path}:{number}: not a number in column {header[c]!r}: {quoted(f)}") from None
    if len(values) == 0:
        raise TrackmeterError(f"{path}: no rows after the header")
    col = {name: values[:, i] for i, name in enumerate(header)}
    n = len(values)
    back = np.flatnonzero(np.diff(col["t"]) < 0)
    if len(back):
        i = int(back[0])
        raise TrackmeterError(f"{path}:{rows[i + 1][0]}: t = {col['t'][i + 1]:.9g} s after {col['t'][i]:.9g} s on "
                              f"the line before: rows must be in time order")
    repeats = np.flatnonzero(np.diff(col["t"]) == 0) + 1
    if len(repeats):
        # Which of two poses at one time pairs with a frame would depend on the association: the
        # first is kept, as a TUM file's and a sequence's data.csv repeats are.
        warnings.warn(f"{path}:{rows[int(repeats[0])][0]}: {len(repeats)} row(s) repeating the timestamp of the row "
                      "before skipped (the first on this line); the first row at each time is kept", stacklevel=2)
        keep = np.ones(len(values), bool)
        keep[repeats] = False
        values, rows = values[keep], [r for r, k in zip(rows, keep) if k]
        col = {name: values[:, i] for i, name in enumerate(header)}
        n = len(values)

    def stack(names: Sequence[str]) -> FloatArray:
        return np.column_stack([col.get(c, np.full(n, np.nan)) for c in names])

    finite = np.all(np.isfinite(stack(POSE_COLUMNS[1:])), axis=1)
    zero_quaternion = finite & (np.linalg.norm(stack(("qw", "qx", "qy", "qz")), axis=1) < 1e-9)
    if "valid" in col:
        valid = col["valid"]
        if np.any(~np.isin(valid, (0.0, 1.0))):
            raise TrackmeterError(f"{path}: column 'valid' must hold 0 or 1")
        broken = np.flatnonzero((valid == 1.0) & ~finite)
        if len(broken):
            raise TrackmeterError(f"{path}:{rows[int(broken[0])][0]}: a valid (1) row without a whole pose "
                                  "(an empty or nan field in x..qz)")
        broken = np.flatnonzero((valid == 1.0) & zero_quaternion)
        if len(broken):
            raise TrackmeterError(f"{path}:{rows[int(broken[0])][0]}: a valid (1) row with a zero quaternion "
                                  "(qw..qz all 0)")
    else:
        # No column says which rows hold a pose (a groundtruth.csv): a row with an empty or
        # nan pose field, or no rotation at all, is a time without ground truth, not a broken file.
        valid = (finite & ~zero_quaternion).astype(float)
        unknown = np.flatnonzero(valid == 0.0)
        if len(unknown):
            warnings.warn(f"{path}:{rows[int(unknown[0])][0]}: {len(unknown)} row(s) without a whole pose "
                          "(a field of t, x..qz empty or nan, or a zero quaternion) read as no pose at their "
                          "time (the first on this line)", stacklevel=2)
    extra = {name: a for name, a in col.items() if name not in _KNOWN}
    posed = np.flatnonzero(valid == 1.0)
    warn_far_from_unit_norm(path, stack(("qw", "qx", "qy", "qz"))[posed], lambda i: rows[int(posed[i])][0], "row")
    try:
        return MotionSeries(
            col["t"], valid.astype(bool), stack(("x", "y", "z")), stack(("qw", "qx", "qy", "qz")),
            stack(("vx", "vy", "vz")), stack(("wx", "wy", "wz")), extra,
        )
    except TrackmeterError as exc:
        raise TrackmeterError(f"{path}: {str(exc).removeprefix('motion series: ')}") from None


# --------------------------------------------------------------------------- writing


def format_csv_value(name: str, value: Any) -> str:
    """One CSV field: integers for ``valid``/counts, the time ``t`` with nine decimals as the TUM
    files and targets.csv give it (so a row's time is the same text in every file of a run or
    a sequence: joined as text, a shortest round-trip ``0.12000000000000001`` met ``0.120000000``),
    shortest round-trip text for other floats, empty for NaN/None (so an invalid row reads back
    as NaN)."""
    if value is None:
        return ""
    if isinstance(value, (bool, np.bool_)):
        return "1" if value else "0"
    v = float(value)
    if math.isnan(v):
        return ""
    if name in _INT_COLUMNS and v.is_integer():
        return str(int(v))
    if name == "t" and math.isfinite(v):
        return f"{v:.9f}"
    return repr(v)


def _series_text(series: MotionSeries, columns: Sequence[str]) -> str:
    # The signs as docs/conventions.md says a written series has them (the commands' writers
    # choose each against the row before, as they go).
    quats = quat_signs_continuous(series.quat_wxyz)
    data = [quats[:, "wxyz".index(c[1])] if c in ("qw", "qx", "qy", "qz") else series.column(c) for c in columns]
    out = [",".join(columns)]
    for r in range(len(series)):
        out.append(",".join(format_csv_value(c, a[r]) for c, a in zip(columns, data)))
    return "\n".join(out) + "\n"


def write_groundtruth_csv(path: str | Path, series: MotionSeries) -> Path:
    """Write ``groundtruth.csv`` (header :data:`GROUNDTRUTH_COLUMNS`) atomically.

    Raises:
        TrackmeterError: the series has an invalid row (ground truth is always valid).
    """
    if not np.all(series.valid):
        raise TrackmeterError("ground truth cannot have invalid rows")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, _series_text(series, GROUNDTRUTH_COLUMNS))
    return path


def write_states_csv(path: str | Path, series: MotionSeries, columns: Sequence[str] = STATES_COLUMNS) -> Path:
    """Write a whole ``states.csv`` atomically (extra columns taken from ``series.extra``,
    NaN -> empty when a series lacks one)."""
    missing = [c for c in columns if c not in _KNOWN and c not in series.extra]
    if missing:
        n = len(series)
        extra = dict(series.extra) | {c: np.full(n, np.nan) for c in missing}
        series = MotionSeries(series.t_s, series.valid, series.position_m, series.quat_wxyz,
                              series.velocity_cam_m_s, series.omega_body_rad_s, extra)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, _series_text(series, columns))
    return path


class MotionCsvWriter:
    """Append rows to a motion CSV while it is being produced; every row is written whole or
    not at all (:class:`~trackmeter.data.atomic.AppendFile`), so a concurrent reader, a crash
    or a full disk leaves only complete rows.

    Usage::

        with MotionCsvWriter(run_dir / "states.csv", STATES_COLUMNS) as w:
            w.write(t=0.1, valid=True, position_m=p, quat_wxyz=q, velocity_cam_m_s=v,
                    omega_body_rad_s=w_body, n_tracked=6, n_lost=0, latency_ms=12.5)

    ``write`` takes the column names directly (``x=..., qw=...``) or the grouped names
    ``position_m`` (3,), ``quat_wxyz`` (4,), ``velocity_cam_m_s`` (3,), ``omega_body_rad_s`` (3,).
    Columns not given are written empty (read back as NaN); unknown names are refused.
    The file is created (truncated) with its header when the writer opens.
    """

    _GROUPS = {
        "position_m": ("x", "y", "z"),
        "quat_wxyz": ("qw", "qx", "qy", "qz"),
        "velocity_cam_m_s": ("vx", "vy", "vz"),
        "omega_body_rad_s": ("wx", "wy", "wz"),
    }

    def __init__(self, path: str | Path, columns: Sequence[str] = GROUNDTRUTH_COLUMNS) -> None:
        self.path = Path(path)
        self.columns = tuple(columns)
        missing = [c for c in POSE_COLUMNS if c not in self.columns]
        if missing:
            raise TrackmeterError(f"motion CSV columns lack {','.join(missing)}")
        if len(set(self.columns)) != len(self.columns):
            raise TrackmeterError("motion CSV columns repeat a name")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file: AppendFile | None = AppendFile(self.path, ",".join(self.columns) + "\n")
        self.rows_written = 0

    def write(self, **values: Any) -> None:
        """Append one row (see the class docstring for the accepted names)."""
        if self._file is None:
            raise TrackmeterError(f"{self.path}: writer is closed")
        flat: dict[str, Any] = {}
        for name, value in values.items():
            if name in self._GROUPS:
                parts = np.asarray(value, dtype=float).reshape(-1)
                names = self._GROUPS[name]
                if len(parts) != len(names):
                    raise TrackmeterError(f"{name} needs {len(names)} values, got {len(parts)}")
                flat.update(zip(names, parts))
            else:
                flat[name] = value
        unknown = [k for k in flat if k not in self.columns]
        if unknown:
            raise TrackmeterError(f"{self.path}: no column {', '.join(unknown)}")
        line = ",".join(format_csv_value(c, flat.get(c)) for c in self.columns) + "\n"
        self._file.append(line)  # whole or not at all: readers see whole rows
        self.rows_written += 1

    def restore_if_removed(self) -> bool:
        """:meth:`trackmeter.data.atomic.AppendFile.restore_if_removed` of the file."""
        return self._file is not None and self._file.restore_if_removed()

    @property
    def size(self) -> int:
        """Bytes written so far (header and whole rows): :meth:`truncate` goes back to it."""
        return 0 if self._file is None else self._file.size

    def truncate(self, size: int, rows: int) -> None:
        """Cut the file back to ``size`` bytes, which held ``rows`` rows (undo a frame's row
        when a file written beside it failed)."""
        if self._file is not None:
            self._file.truncate(size)
            self.rows_written = rows

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> MotionCsvWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
