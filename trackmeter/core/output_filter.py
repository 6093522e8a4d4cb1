"""Output filter of the pose (paper section 2.E): low-pass IIR on position and on the rotation group.

The paper low-pass filters its output. Component-wise filtering of a quaternion is wrong: the
filtered 4-vector leaves the unit sphere (a constant-rate rotation's components are sinusoids
the filter attenuates) and mixes q with -q. Here the filter runs in a local chart of SO(3):

- the filter keeps a base attitude ``R_base`` (the previous output) and its internal IIR state
  as tangent vectors at that base;
- each new attitude enters as the body-frame rotation vector ``x = log(R_base^T R_meas)``; the
  IIR (scipy.signal Butterworth, second-order sections) filters ``x`` to ``y``; the output is
  ``R_base exp(y)``;
- the chart is then re-centred on the output: since the filter has unit gain at DC, shifting
  all its past inputs and outputs by ``-y`` shifts its state by ``-y`` times the unit-step
  steady state (:func:`scipy.signal.sosfilt_zi`). For rotations about one axis this is exactly
  the scalar IIR filter on the angle; otherwise the chart error is second order in the
  (small) spread of the attitudes inside the filter's memory.

Position is filtered the same way (a vector space, so exactly).

A causal low-pass delays a ramp by its group delay at DC (a 2 Hz second-order Butterworth:
~0.11 s, i.e. 1.1 degrees behind a 10 deg/s tumble). With ``velocity_compensated`` the chart
moves with the estimated velocity (``R_base <- R_base exp(omega_body dt)``, ``p_base <- p_base +
(v_prev + v) dt / 2`` before each sample: the trapezoid rule, since a body origin off the spin
axis turns its velocity within a frame), so the filter only sees the deviation from
constant-velocity motion, and a constant-velocity motion passes with no delay while
measurement noise is still filtered.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import signal
from scipy.spatial.transform import Rotation

from trackmeter.core.checks import finite_rows, finite_time, rotation_matrix
from trackmeter.core.params import check_params, param
from trackmeter.core.transforms import rotation_from_matrix
from trackmeter.errors import TrackmeterError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class FilterParams:
    """Tunables of the pose output filter."""

    enabled: bool = param(True, "low-pass filter the output pose")
    cutoff_hz: float = param(2.0, "cutoff frequency of the Butterworth low-pass, Hz", min=0.01)
    order: int = param(2, "order of the Butterworth low-pass", min=1, max=8)
    velocity_compensated: bool = param(
        True, "filter in a chart moving with the estimated velocity: no group delay on constant-velocity motion"
    )

    def __post_init__(self) -> None:
        check_params(self)  # declared ranges and choices, as the config loader checks them


def design_lowpass(cutoff_hz: float, order: int, rate_hz: float) -> FloatArray:
    """Butterworth low-pass as second-order sections (scipy.signal.butter, ``output='sos'``).

    The cutoff is clipped just below Nyquist so a high setting degrades to "almost no filter".
    """
    nyquist = 0.5 * rate_hz
    wn = min(cutoff_hz, 0.95 * nyquist)
    return np.asarray(signal.butter(order, wn, btype="low", fs=rate_hz, output="sos"), dtype=float)


def dc_group_delay_s(sos: ArrayLike, rate_hz: float) -> float:
    """Group delay of the filter at zero frequency, s (how far a ramp lags behind)."""
    b, a = signal.sos2tf(np.asarray(sos, dtype=float))
    _, gd = signal.group_delay((b, a), w=[1e-6], fs=rate_hz)
    return float(gd[0]) / rate_hz


class PoseFilter:
    """Low-pass IIR filter of a pose stream on SE(3) = R^3 x SO(3) (see the module docstring).

    Args:
        params: cutoff, order, compensation.
        rate_hz: sample rate the filter is designed for (the source's frame rate), Hz; positive
            and finite.

    Raises:
        TrackmeterError: ``rate_hz`` is not a positive, finite number.
    """

    def __init__(self, params: FilterParams = FilterParams(), rate_hz: float = 25.0) -> None:
        self.params = params
        self.rate_hz = float(rate_hz)
        if not (self.rate_hz > 0 and np.isfinite(self.rate_hz)):  # scipy's butter fails obscurely, or not at all
            raise TrackmeterError(f"rate_hz must be a positive, finite frame rate, Hz; got {rate_hz!r}")
        self.sos = design_lowpass(params.cutoff_hz, params.order, self.rate_hz)
        self._zi_unit = signal.sosfilt_zi(self.sos)  # (sections, 2) steady state for a unit input
        self.reset()

    def reset(self) -> None:
        self._R_base: FloatArray | None = None
        self._p_base: FloatArray | None = None
        self._t_last: float | None = None
        self._v_last: FloatArray | None = None  # the last finite v_cam that moved the chart
        self._zi = np.zeros(self._zi_unit.shape + (6,))  # states for (rotation vector, position)

    def retuned(self, params: FilterParams) -> PoseFilter:
        """A filter of ``params`` that goes on from this one's last output without a step.

        The chart is centred on the last output, where a zero IIR state means "at rest there"
        (every past input and output equal to it), so the new design starts from that state:
        its first output is the last one moved by the new design's first coefficient times the
        new sample's offset. A new filter would start from the raw pose instead (the console's
        cutoff field made a 1.6 mm step). This filter is left as it was.
        """
        new = PoseFilter(params, self.rate_hz)
        if params.enabled and self._R_base is not None and self._p_base is not None:
            new._R_base, new._p_base, new._t_last = self._R_base.copy(), self._p_base.copy(), self._t_last
            new._v_last = None if self._v_last is None else self._v_last.copy()
        return new

    @property
    def group_delay_s(self) -> float:
        return dc_group_delay_s(self.sos, self.rate_hz)

    def update(
        self,
        t_s: float,
        R_cam_body: ArrayLike,
        p_cam: ArrayLike,
        v_cam: ArrayLike | None = None,
        omega_body: ArrayLike | None = None,
    ) -> tuple[FloatArray, FloatArray]:
        """Filter one pose; returns the filtered ``(R_cam_body (3,3), p_cam (3,))``. A time not
        after the last one's starts the filter over (:meth:`reset`) from this pose.

        Args:
            t_s: time of the pose, s.
            R_cam_body: (3,3) attitude, body to camera; finite.
            p_cam: (3,) body origin in the camera frame, m; finite.
            v_cam, omega_body: the current velocity estimates (m/s, camera frame; rad/s, body
                frame), used to move the chart when ``velocity_compensated`` is on; ignored
                when None or not finite (rates not yet known).

        Raises:
            TrackmeterError: a pose of the wrong shape or not finite, an ``R_cam_body`` that is
                no rotation (a reflection), a time that is not finite. Refused before it enters
                the IIR state, where one NaN would stay for ever; the filter is left as it was.
        """
        t_s = finite_time(t_s, "t_s")
        R = rotation_matrix(R_cam_body, "R_cam_body")
        p = finite_rows(p_cam, "p_cam", (3,))
        if not self.params.enabled:
            return R, p
        if self._t_last is not None and not float(t_s) > self._t_last:
            # Repeated or backward (a source restarted or replayed): started over from this
            # pose, as the velocity estimator does. Kept, the chart was not moved back and the
            # next frame moved it twice (7.6 mm off after one frame out of order).
            self.reset()
        if self._R_base is None or self._p_base is None or self._t_last is None:
            self._R_base, self._p_base, self._t_last = R.copy(), p.copy(), float(t_s)
            return R, p
        dt = float(t_s) - self._t_last
        self._t_last = float(t_s)
        if self.params.velocity_compensated and dt > 0:
            if omega_body is not None and np.all(np.isfinite(omega_body)):
                self._R_base = self._R_base @ Rotation.from_rotvec(np.asarray(omega_body, dtype=float) * dt).as_matrix()
            if v_cam is not None and np.all(np.isfinite(v_cam)):
                # The trapezoid rule: a body origin off the spin axis turns its velocity by
                # omega dt within the frame, and the newest velocity alone missed by
                # |omega| |v| dt^2 / 2 a frame, which the filter passed on as a lag.
                v = np.asarray(v_cam, dtype=float)
                mean_v = v if self._v_last is None else 0.5 * (self._v_last + v)
                self._p_base = self._p_base + mean_v * dt
                self._v_last = v.copy()
            else:
                self._v_last = None  # not averaged with a velocity from before a gap
        x = np.concatenate([rotation_from_matrix(self._R_base.T @ R).as_rotvec(), p - self._p_base])
        y, self._zi = signal.sosfilt(self.sos, x[None, :], axis=0, zi=self._zi)
        y = y[0]
        R_out = self._R_base @ Rotation.from_rotvec(y[:3]).as_matrix()
        p_out = self._p_base + y[3:]
        # Re-centre the chart on the output (unit DC gain: a constant shift of the signal
        # history shifts the state by that constant times the unit-step steady state).
        self._zi = self._zi - self._zi_unit[..., None] * y[None, None, :]
        self._R_base, self._p_base = R_out, p_out
        return R_out, p_out
