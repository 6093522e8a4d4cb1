"""TUM trajectory files: one pose per line, ``t tx ty tz qx qy qz qw``.

Seconds, metres, and a scalar-LAST quaternion because the TUM format says so (the only
scalar-last place in the project); in memory quaternions are ``wxyz``. Poses are
``T_cam_body``. Lines starting with ``#`` are comments.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from trackmeter.core.checks import as_rows, time_order
from trackmeter.core.transforms import quat_signs_continuous
from trackmeter.data.atomic import write_text_atomic
from trackmeter.errors import TrackmeterError, quoted

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A timed sequence of poses ``T_cam_body``.

    Attributes:
        t_s: (N,) timestamps, s, non-decreasing (:func:`read_tum` keeps one pose a time).
        position_m: (N,3) body origin in the camera frame, m.
        quat_wxyz: (N,4) unit quaternions of ``R_cam_body``.
    """

    t_s: FloatArray
    position_m: FloatArray
    quat_wxyz: FloatArray

    def __post_init__(self) -> None:
        t = np.asarray(self.t_s, dtype=float).reshape(-1)
        p = as_rows(self.position_m, "position_m", 3)
        q = as_rows(self.quat_wxyz, "quat_wxyz", 4)
        if not (len(t) == len(p) == len(q)):
            raise TrackmeterError("trajectory arrays differ in length")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
            raise TrackmeterError("trajectory has non-finite values")
        time_order(t, "trajectory")
        norms = np.linalg.norm(q, axis=1)
        if np.any(norms < 1e-9):
            raise TrackmeterError("trajectory has a zero quaternion")
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "position_m", p)
        object.__setattr__(self, "quat_wxyz", q / norms[:, None])

    def __len__(self) -> int:
        return len(self.t_s)


#: The fields of a TUM line, in order.
TUM_FIELDS = ("t", "tx", "ty", "tz", "qx", "qy", "qz", "qw")


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file; raises TrackmeterError naming the file and line on bad input."""
    path = Path(path)
    if not path.is_file():
        raise TrackmeterError(f"{path}: no such file")
    rows: list[list[float]] = []
    line_numbers: list[int] = []
    comma_line: int | None = None
    try:
        text_read = path.read_text(encoding="utf-8-sig")
        lines = text_read.splitlines()
    except UnicodeDecodeError:
        raise TrackmeterError(f"{path}: not a text file (a TUM trajectory is lines of 't tx ty tz qx qy qz qw')") from None
    except OSError as exc:
        raise TrackmeterError(f"{path}: cannot read: {exc.strerror or exc}") from None
    # The last line with data, found from the end (a cut one is left out, below).
    last_data = next((n for n in range(len(lines), 0, -1) if lines[n - 1].split("#", 1)[0].strip()), 0)
    cut_line = None
    for number, line in enumerate(lines, 1):
        # '#' starts a comment anywhere on a line, as numpy.loadtxt (and so evo) read TUM files.
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        if comma_line is None and "," in text:
            comma_line = number
        fields = text.replace(",", " ").split()
        unended = number == len(lines) and not text_read.endswith(("\n", "\r"))
        if number == last_data and rows and len(fields) < 8 and (len(fields) > 1 or unended):
            cut_line = number  # a writer stopped mid-line (killed, a full disk): the poses before are whole
            break
        if len(fields) != 8:
            raise TrackmeterError(f"{path}:{number}: expected 8 values 't tx ty tz qx qy qz qw', got {len(fields)}")
        try:
            row = [float(x) for x in fields]
        except ValueError:
            if unended and rows:  # cut inside its last field ("-", "1e"): the poses before are whole
                cut_line = number
                break
            raise TrackmeterError(f"{path}:{number}: not a number in {quoted(text, 80)}") from None
        if unended and rows and _cut_in_qw(row, rows):
            cut_line = number
            break
        # Checked here, not only by Trajectory, so that the message names the line.
        if not all(math.isfinite(x) for x in row):
            bad = next(k for k, x in enumerate(row) if not math.isfinite(x))
            raise TrackmeterError(f"{path}:{number}: {TUM_FIELDS[bad]} is not finite ({fields[bad]})")
        if math.hypot(*row[4:8]) < 1e-9:
            raise TrackmeterError(f"{path}:{number}: zero quaternion (qx qy qz qw all 0)")
        rows.append(row)
        line_numbers.append(number)
    if not rows:
        raise TrackmeterError(f"{path}: no poses in the file")
    if cut_line is not None:
        warnings.warn(f"{path}:{cut_line}: the last line is cut short, left out", stacklevel=2)
    if comma_line is not None:
        # TUM separates by spaces: a file with commas may as well be groundtruth.csv's rows
        # without their header, whose quaternion comes scalar first.
        warnings.warn(f"{path}:{comma_line}: values separated by commas, read as TUM (t tx ty tz qx qy qz qw, "
                      "scalar last); rows in groundtruth.csv's order (t,x,y,z,qw,qx,qy,qz) need its header line",
                      stacklevel=2)
    data = np.array(rows)
    order = np.argsort(data[:, 0], kind="stable")
    data = data[order]
    repeats = np.flatnonzero(np.diff(data[:, 0]) == 0) + 1
    if len(repeats):
        # Two poses at one time: which one pairs with the other trajectory would depend on the
        # lines' order. The first in the file is kept (the stable sort keeps file order), as a
        # sequence's data.csv rows repeating a timestamp are skipped.
        first = int(order[repeats[0]])
        warnings.warn(f"{path}: {len(repeats)} pose(s) skipped that repeat an earlier line's timestamp (the first: "
                      f"line {line_numbers[first]}, t = {data[repeats[0], 0]:.9g} s); the first pose at each time is kept",
                      stacklevel=2)
        data = np.delete(data, repeats, axis=0)
    quat_wxyz = data[:, [7, 4, 5, 6]]
    file_order = np.delete(order, repeats) if len(repeats) else order
    warn_far_from_unit_norm(path, quat_wxyz, lambda i: line_numbers[int(file_order[i])], "line")
    try:
        return Trajectory(data[:, 0], data[:, 1:4], quat_wxyz)
    except TrackmeterError as exc:
        raise TrackmeterError(f"{path}: {exc}") from None


#: How far from 1 the quaternion norm of a line written with 9 decimals can be (rounding).
_UNIT_NORM_TOLERANCE = 1e-6
#: A quaternion whose norm is further from 1 than this is not one rounded (four decimals are
#: within 1e-4): it is normalised all the same, and said.
FAR_FROM_UNIT_NORM = 0.01


def warn_far_from_unit_norm(path: Path | str, quat: ArrayLike, line_of: Callable[[int], object], rows: str) -> None:
    """Warn (naming the first ``rows``' line, ``line_of(row index)``) when quaternions of
    ``quat`` (N, 4) have a norm more than :data:`FAR_FROM_UNIT_NORM` from 1: values that are
    no quaternion (angles in its columns), which normalising turns into some attitude."""
    norms = np.linalg.norm(np.asarray(quat, dtype=float).reshape(-1, 4), axis=1)
    far = np.flatnonzero(np.abs(norms - 1.0) > FAR_FROM_UNIT_NORM)
    if len(far):
        first = int(far[0])
        warnings.warn(f"{path}:{line_of(first)}: {len(far)} {rows}(s) whose quaternion's norm is far from 1 "
                      f"({norms[first]:.4g} on this line): normalised; are these columns a quaternion, not angles?",
                      stacklevel=3)


def _cut_in_qw(row: list[float], rows: list[list[float]]) -> bool:
    """Whether an unended last line was cut inside its qw (a writer killed mid-field): its
    quaternion is not unit while every line before holds a unit one. A cut number still
    parses ("0.707106781" -> "0.7") and renormalising would silently give another attitude."""
    def off_unit(r: list[float]) -> bool:
        return abs(math.hypot(*r[4:8]) - 1.0) > _UNIT_NORM_TOLERANCE

    return off_unit(row) and not any(off_unit(r) for r in rows)


def format_tum_line(t_s: float, position_m: FloatArray, quat_wxyz: FloatArray) -> str:
    """One TUM line (no newline) for a pose."""
    p = position_m
    w, x, y, z = quat_wxyz
    return f"{t_s:.9f} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} {x:.9f} {y:.9f} {z:.9f} {w:.9f}"


def write_tum(path: str | Path, trajectory: Trajectory) -> Path:
    """Write a TUM file atomically (temporary file in the same folder, then rename), its
    quaternions' signs continuous as docs/conventions.md says (:func:`quat_signs_continuous`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    quats = quat_signs_continuous(trajectory.quat_wxyz)
    text = "".join(format_tum_line(t, p, q) + "\n" for t, p, q in zip(trajectory.t_s, trajectory.position_m, quats))
    write_text_atomic(path, "# t tx ty tz qx qy qz qw  (T_cam_body)\n" + text)
    return path
