"""Fixed-length time-series windows for the live plots (no viser here).

The tracking thread appends one row per snapshot (a cheap ``deque.append``); the console's
publisher turns the window into the tuple of 1-D arrays uPlot wants, at its own rate. Rows are
only appended when the values exist (a valid pose, known errors).

A plot must not join the last point before a stretch without values to the first point after
it: the straight line would say the pose was there when it was not. So :meth:`SeriesWindow.arrays`
puts one separator row between two rows that lie on either side of a gap: its time is between
theirs and its values are NaN. A gap is

- a frame whose values did not exist (:meth:`SeriesWindow.mark_gap`: pose invalid, error
  unknown, a non-finite value, a discontinuous stream), or
- more time between two consecutive rows than :data:`GAP_FACTOR` times the window's usual row
  spacing (frames that never reached the plot).

NaN is only the "no value" of this module: uPlot breaks a line only at ``null`` (a NaN is drawn
as a line straight across, and a NaN at the start of an array empties its auto-ranged y axis),
so the console hands uPlot ``null`` for it (``console.app.uplot_data``). The separator is never
the first or the last row.
"""

from __future__ import annotations

import collections
import threading

import numpy as np
from numpy.typing import ArrayLike, NDArray

from trackmeter.core.transforms import matrix_to_quat_wxyz, quat_sign_nearest
from trackmeter.pipeline.snapshot import Snapshot

#: Plot name → (title with its unit, series labels). The x axis is the frame time, s.
PLOTS: dict[str, tuple[str, tuple[str, ...]]] = {
    "position": ("Position, camera frame [m]", ("x", "y", "z (depth)")),
    "attitude": ("Attitude, quaternion wxyz", ("qw", "qx", "qy", "qz")),
    "velocity": ("Linear velocity, camera frame [mm/s]", ("vx", "vy", "vz")),
    "omega": ("Angular velocity, body frame [deg/s]", ("wx", "wy", "wz")),
    "err_position": ("Position error [mm]", ("x", "y", "z (depth)")),
    "err_attitude": ("Attitude error, eqs. 16-17 [deg]", ("about x", "about y", "about z", "total")),
    "err_velocity": ("Linear speed error [mm/s]", ("vx", "vy", "vz")),
    "err_omega": ("Angular speed error [deg/s]", ("wx", "wy", "wz")),
}

#: Plots fed from the pose (a gap in all of them while the pose is invalid).
POSE_PLOTS = ("position", "attitude", "velocity", "omega")

#: Two consecutive rows further apart than this many times the window's median spacing have
#: a gap between them. A frame or two dropped under load (2-3x) keeps its line; a pause in the
#: rows the snapshots did not explain (seconds at 25 Hz) does not.
GAP_FACTOR = 5.0


class SeriesWindow:
    """The last ``maxlen`` rows ``(t, v1, ..., vk)``; thread-safe append and read."""

    def __init__(self, n_values: int, maxlen: int = 1000) -> None:
        self.n_values = n_values
        self._rows: collections.deque[NDArray[np.float64]] = collections.deque(maxlen=maxlen)
        # Parallel to _rows (same maxlen, appended together): the row follows a gap.
        self._after_gap: collections.deque[bool] = collections.deque(maxlen=maxlen)
        self._gap_pending = False
        self._lock = threading.Lock()
        self.version = 0

    def append(self, t_s: float, values: ArrayLike | None) -> None:
        """Add the row at ``t_s``; ``values`` None or not all finite (e.g. no pose, a velocity
        not yet estimated) make it a blank row: the line breaks there, and the time axis goes
        on (without a row the plot stood still at the last value while the pose was lost)."""
        if not np.isfinite(t_s):
            self.mark_gap()
            return
        row = np.full(self.n_values + 1, np.nan)
        row[0] = t_s
        if values is not None:
            v = np.asarray(values, dtype=float).reshape(-1)
            if np.all(np.isfinite(v)):
                row[1:] = v
        with self._lock:
            if self._rows and t_s <= self._rows[-1][0]:
                # The source restarted: time went back. The old rows are of another run.
                self._rows.clear()
                self._after_gap.clear()
                self._gap_pending = False
            self._rows.append(row)
            self._after_gap.append(self._gap_pending)
            self._gap_pending = False
            self.version += 1

    def mark_gap(self) -> None:
        """A frame without values here: the next row starts a new line. (No version bump: the
        plot changes only when that row comes.)"""
        with self._lock:
            self._gap_pending = True

    def clear(self) -> None:
        with self._lock:
            self._rows.clear()
            self._after_gap.clear()
            self._gap_pending = False
            self.version += 1

    def __len__(self) -> int:
        return len(self._rows)

    def arrays(self) -> tuple[NDArray[np.float64], ...]:
        """``(t, v1, ..., vk)`` as 1-D arrays (empty arrays before the first row), with a
        separator row (its time midway, its values NaN) at each gap; ``t`` stays increasing."""
        with self._lock:
            rows = np.array(self._rows) if self._rows else np.zeros((0, self.n_values + 1))
            after_gap = np.fromiter(self._after_gap, bool, len(self._after_gap))
        if len(rows) >= 2:
            t = rows[:, 0]
            dt = np.diff(t)
            gap = after_gap[1:].copy()  # a flag on the oldest row has nothing before it to cut
            usual = dt[~gap]
            if usual.size:
                gap |= dt > GAP_FACTOR * float(np.median(usual))
            where = np.flatnonzero(gap)  # gap between rows where and where + 1
            if where.size:
                separators = np.full((where.size, self.n_values + 1), np.nan)
                separators[:, 0] = (t[where] + t[where + 1]) / 2.0
                rows = np.insert(rows, where + 1, separators, axis=0)
        return tuple(np.ascontiguousarray(rows[:, i]) for i in range(self.n_values + 1))


class PlotData:
    """One :class:`SeriesWindow` per entry of :data:`PLOTS`, fed from snapshots."""

    def __init__(self, maxlen: int = 1000) -> None:
        self.windows = {name: SeriesWindow(len(labels), maxlen) for name, (_, labels) in PLOTS.items()}
        # (index, t) of the frame last added: the pipeline publishes a frame again after a
        # command or a status change, and that is not a new sample (nor a gap).
        self._last_frame: tuple[int, float] | None = None
        self._last_quat_wxyz: NDArray[np.float64] | None = None  # the attitude plot's last row
        self._last_body_frame: int | None = None  # PoseEstimate.body_frame of the last valid pose

    def add(self, snap: Snapshot) -> None:
        """Append the pose, velocities and errors of ``snap`` (called on the tracking thread);
        a value the frame does not have marks a gap in its plot."""
        if snap.frame is None:
            return
        key = (snap.frame.index, snap.frame.t_s)
        if key == self._last_frame:
            return
        self._last_frame = key
        t = snap.frame.t_s
        if snap.frame.cut:
            # The stream is discontinuous before this frame (a restart, a new pass of a loop).
            for w in self.windows.values():
                w.mark_gap()
        pose = snap.pose
        if pose.valid:
            if self._last_body_frame is not None and pose.body_frame != self._last_body_frame:
                # The body frame was defined anew (case switched, model bound or acquired): the
                # old frame's pose, rates and body axes are not comparable with the new ones, and
                # the step between them is no motion. A break in the line is not enough: uPlot
                # joins a one-frame gap (under a pixel at the plots' width) with a vertical line,
                # a jump of the body that never happened. The pose plots start over.
                for name in POSE_PLOTS:
                    self.windows[name].clear()
                self._last_quat_wxyz = None
            self._last_body_frame = pose.body_frame
            T = np.asarray(pose.T_cam_body)
            self.windows["position"].append(t, T[:3, 3])
            # q and -q are one rotation: the sign nearest the last row's keeps the line
            # continuous through any turn. (A rotation vector, angle at most 180 deg, flips to
            # the other side there, a vertical line that a break in the plot did not hide: uPlot
            # strokes across a one-frame gap.)
            self._last_quat_wxyz = quat_sign_nearest(matrix_to_quat_wxyz(T[:3, :3]), self._last_quat_wxyz)
            self.windows["attitude"].append(t, self._last_quat_wxyz)
            self.windows["velocity"].append(t, np.asarray(pose.velocity_cam_m_s) * 1e3)
            self.windows["omega"].append(t, np.degrees(pose.omega_body_rad_s))
        else:
            for name in POSE_PLOTS:
                self.windows[name].append(t, None)
        e = snap.errors or {}
        self.windows["err_position"].append(t, np.asarray(e["position_m"]) * 1e3 if "position_m" in e else None)
        self.windows["err_attitude"].append(t, np.degrees(np.r_[np.asarray(e["attitude_rad"]).reshape(3), float(
            e["attitude_total_rad"])]) if "attitude_rad" in e and "attitude_total_rad" in e else None)
        self.windows["err_velocity"].append(t, np.asarray(e["velocity_m_s"]) * 1e3 if "velocity_m_s" in e else None)
        self.windows["err_omega"].append(t, np.degrees(e["omega_rad_s"]) if "omega_rad_s" in e else None)

    def clear(self) -> None:
        self._last_frame = None
        self._last_quat_wxyz = None
        self._last_body_frame = None
        for w in self.windows.values():
            w.clear()
