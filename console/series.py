"""Fixed-length time-series windows for the live plots (no viser here).

The tracking thread appends one row per snapshot (a cheap ``deque.append``); the console's
publisher turns the window into the tuple of 1-D arrays uPlot wants, at its own rate. Rows are
only appended when the values exist (a valid pose, known errors), so the arrays never hold NaN
(uPlot's auto-range does not survive NaN).
"""

from __future__ import annotations

import collections
import threading

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from trackmeter.pipeline.snapshot import Snapshot

#: Plot name → (title, series labels, unit). The x axis is the frame time, s.
PLOTS: dict[str, tuple[str, tuple[str, ...]]] = {
    "position": ("Position, camera frame [m]", ("x", "y", "z (depth)")),
    "attitude": ("Attitude, rotation vector [deg]", ("rx", "ry", "rz")),
    "velocity": ("Linear velocity, camera frame [mm/s]", ("vx", "vy", "vz")),
    "omega": ("Angular velocity, body frame [deg/s]", ("wx", "wy", "wz")),
    "err_position": ("Position error [mm]", ("x", "y", "z (depth)")),
    "err_attitude": ("Attitude error, eqs. 16-17 [deg]", ("about x", "about y", "about z", "total")),
    "err_velocity": ("Linear speed error [mm/s]", ("vx", "vy", "vz")),
    "err_omega": ("Angular speed error [deg/s]", ("wx", "wy", "wz")),
}


class SeriesWindow:
    """The last ``maxlen`` rows ``(t, v1, ..., vk)``; thread-safe append and read."""

    def __init__(self, n_values: int, maxlen: int = 1000) -> None:
        self.n_values = n_values
        self._rows: collections.deque[NDArray[np.float64]] = collections.deque(maxlen=maxlen)
        self._lock = threading.Lock()
        self.version = 0

    def append(self, t_s: float, values: ArrayLike) -> None:
        row = np.empty(self.n_values + 1)
        row[0] = t_s
        row[1:] = np.asarray(values, dtype=float).reshape(-1)
        if not np.all(np.isfinite(row)):
            return
        with self._lock:
            if self._rows and t_s <= self._rows[-1][0]:
                self._rows.clear()  # the source restarted: time went back
            self._rows.append(row)
            self.version += 1

    def clear(self) -> None:
        with self._lock:
            self._rows.clear()
            self.version += 1

    def __len__(self) -> int:
        return len(self._rows)

    def arrays(self) -> tuple[NDArray[np.float64], ...]:
        """``(t, v1, ..., vk)`` as 1-D arrays (empty arrays before the first row)."""
        with self._lock:
            rows = np.array(self._rows) if self._rows else np.zeros((0, self.n_values + 1))
        return tuple(np.ascontiguousarray(rows[:, i]) for i in range(self.n_values + 1))


class PlotData:
    """One :class:`SeriesWindow` per entry of :data:`PLOTS`, fed from snapshots."""

    def __init__(self, maxlen: int = 1000) -> None:
        self.windows = {name: SeriesWindow(len(labels), maxlen) for name, (_, labels) in PLOTS.items()}

    def add(self, snap: Snapshot) -> None:
        """Append the pose, velocities and errors of ``snap`` (called on the tracking thread)."""
        if snap.frame is None:
            return
        t = snap.frame.t_s
        pose = snap.pose
        if pose.valid:
            T = np.asarray(pose.T_cam_body)
            self.windows["position"].append(t, T[:3, 3])
            self.windows["attitude"].append(t, np.degrees(Rotation.from_matrix(T[:3, :3]).as_rotvec()))
            self.windows["velocity"].append(t, np.asarray(pose.velocity_cam_m_s) * 1e3)
            self.windows["omega"].append(t, np.degrees(pose.omega_body_rad_s))
        e = snap.errors
        if e:
            if "position_m" in e:
                self.windows["err_position"].append(t, np.asarray(e["position_m"]) * 1e3)
            if "attitude_rad" in e and "attitude_total_rad" in e:
                self.windows["err_attitude"].append(
                    t, np.degrees(np.r_[np.asarray(e["attitude_rad"]).reshape(3), float(e["attitude_total_rad"])]))  # type: ignore[arg-type]
            if "velocity_m_s" in e:
                self.windows["err_velocity"].append(t, np.asarray(e["velocity_m_s"]) * 1e3)
            if "omega_rad_s" in e:
                self.windows["err_omega"].append(t, np.degrees(e["omega_rad_s"]))

    def clear(self) -> None:
        for w in self.windows.values():
            w.clear()
