"""Linear and angular velocity from a stream of poses (paper eq. 14, and a better estimator).

The paper differentiates the measured attitude: ``(0, omega_body) = 2 q* ⊗ q_dot`` (eq. 14),
which on sampled poses is the finite difference on the rotation group
``omega_body = log(R_{k-1}^T R_k) / dt`` (:func:`trackmeter.core.transforms.omega_body_between`)
and ``v_cam = (t_k - t_{k-1}) / dt`` for the body origin. Differencing doubles the noise and
divides it by ``dt`` (40 ms at 25 Hz): a 1 mm position noise becomes ~35 mm/s.

The default estimator is a causal local polynomial fit (Savitzky-Golay on the rotation group):
over the poses of the last ``window_s`` seconds, express each attitude in the chart of the
newest one as a body-frame rotation vector ``phi_k = log(R_ref^T R_k)``, fit a polynomial of
degree ``order`` in time to ``phi`` and to the position by least squares, and evaluate its
derivative at the newest time. With ``R(tau) = R_ref exp(phi(tau))`` the body angular velocity
is ``omega_body = J_r(phi) phi'`` (``J_r``: right Jacobian of SO(3)), which is eq. 14 applied to
the fitted curve. A motion that is polynomial of degree ``order`` in the chart (constant rate,
constant angular acceleration about a fixed axis) is differentiated exactly; noise is averaged
over the window. ``benchmarks/accuracy.py`` compares it with the plain eq. 14 difference.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from trackmeter.core.params import param
from trackmeter.core.transforms import omega_body_between

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class VelocityParams:
    """Tunables of the velocity estimation."""

    method: str = param(
        "poly", "'poly': causal local polynomial fit on the rotation group; 'difference': eq. 14 finite difference",
        choices=("poly", "difference"),
    )
    window_s: float = param(1.2, "poly: window of the attitude fit (angular velocity), s", min=0.05)
    order: int = param(2, "poly: degree of the attitude polynomial (1 = constant rate, 2 = constant acceleration)",
                       min=1, max=4)
    position_window_s: float = param(
        3.0, "poly: window of the position fit, s (the relative translation is slow and smooth)", min=0.05
    )
    position_order: int = param(2, "poly: degree of the position polynomial (1 = constant velocity)", min=1, max=4)
    min_span_s: float = param(
        0.4, "poly: no velocity is reported until the fitted poses span this long (a restart after a "
        "gap would otherwise report a two-pose difference), s", min=0.0,
    )
    max_gap_s: float = param(0.5, "a gap between valid poses longer than this restarts the estimator, s", min=0.0)


def right_jacobian_so3(phi: ArrayLike) -> FloatArray:
    """Right Jacobian of SO(3) at rotation vector ``phi`` (3,): ``d/dt exp(phi) = exp(phi) [J_r phi']x``.

    ``J_r = I - (1 - cos θ)/θ² [phi]x + (θ - sin θ)/θ³ [phi]x²`` (Chirikjian, *Stochastic Models,
    Information Theory and Lie Groups* vol. 2, eq. 10.86; Barfoot, *State Estimation for
    Robotics*, eq. 7.77b).
    """
    phi = np.asarray(phi, dtype=float)
    theta = float(np.linalg.norm(phi))
    K = np.array([[0, -phi[2], phi[1]], [phi[2], 0, -phi[0]], [-phi[1], phi[0], 0]])
    if theta < 1e-6:
        return np.eye(3) - 0.5 * K + K @ K / 6.0
    return np.eye(3) - (1 - np.cos(theta)) / theta**2 * K + (theta - np.sin(theta)) / theta**3 * K @ K


def finite_difference_rates(
    t0_s: float, R0: ArrayLike, p0: ArrayLike, t1_s: float, R1: ArrayLike, p1: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Plain eq. 14 on two poses: ``(v_cam (3,) m/s, omega_body (3,) rad/s)``."""
    dt = t1_s - t0_s
    q0 = Rotation.from_matrix(np.asarray(R0, dtype=float)).as_quat(scalar_first=True)
    q1 = Rotation.from_matrix(np.asarray(R1, dtype=float)).as_quat(scalar_first=True)
    v = (np.asarray(p1, dtype=float) - np.asarray(p0, dtype=float)) / dt
    return v, omega_body_between(q0, q1, dt)


def local_polynomial_rates(
    times_s: ArrayLike, R: ArrayLike, p: ArrayLike, order: int, t_eval_s: float | None = None
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Fit a polynomial to a window of poses on SE(3) and differentiate it (Savitzky-Golay on the group).

    Args:
        times_s: (N,) increasing times, s.
        R: (N,3,3) attitudes ``R_cam_body``.
        p: (N,3) body-origin positions in the camera frame, m.
        order: polynomial degree; uses ``min(order, N-1)``.
        t_eval_s: where to evaluate; default the newest time.

    Returns:
        ``(p_fit (3,), R_fit (3,3), v_cam (3,) m/s, omega_body (3,) rad/s)`` at ``t_eval_s``.
    """
    t = np.asarray(times_s, dtype=float)
    Rm = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    P = np.asarray(p, dtype=float).reshape(-1, 3)
    t_eval = t[-1] if t_eval_s is None else float(t_eval_s)
    deg = min(order, len(t) - 1)
    R_ref = Rm[-1]
    phi = Rotation.from_matrix(np.einsum("ji,njk->nik", R_ref, Rm)).as_rotvec()  # log(R_ref^T R_k)
    tau = t - t_eval
    scale = max(float(np.max(np.abs(tau))), 1e-9)  # conditioning of the Vandermonde matrix
    V = np.vander(tau / scale, deg + 1, increasing=True)
    coef, *_ = np.linalg.lstsq(V, np.column_stack([phi, P]), rcond=None)
    value = coef[0]
    slope = coef[1] / scale if deg >= 1 else np.zeros(6)
    phi0, phi_dot = value[:3], slope[:3]
    R_fit = R_ref @ Rotation.from_rotvec(phi0).as_matrix()
    omega = right_jacobian_so3(phi0) @ phi_dot
    return value[3:], R_fit, slope[3:], omega


class VelocityEstimator:
    """Causal velocity estimation over a stream of poses (stateful wrapper of the functions above).

    Feed every valid pose with :meth:`update`; :meth:`reset` when the body frame changes
    (new model, case switch) or tracking restarts.
    """

    def __init__(self, params: VelocityParams = VelocityParams()) -> None:
        self.params = params
        self._t: deque[float] = deque()
        self._R: deque[FloatArray] = deque()
        self._p: deque[FloatArray] = deque()

    @property
    def settled(self) -> bool:
        """True once the poses in the window span ``min_span_s`` (before that the rates are
        provisional: fine for the output filter's chart, not for reporting)."""
        if self.params.method == "difference":
            return len(self._t) >= 2
        return len(self._t) >= 2 and self._t[-1] - self._t[0] >= self.params.min_span_s - 1e-9

    def reset(self) -> None:
        self._t.clear()
        self._R.clear()
        self._p.clear()

    def update(self, t_s: float, R_cam_body: ArrayLike, p_cam: ArrayLike) -> tuple[FloatArray, FloatArray] | None:
        """Add a pose; return ``(v_cam m/s, omega_body rad/s)``, or None until two poses are known."""
        if self._t and (t_s <= self._t[-1] or t_s - self._t[-1] > self.params.max_gap_s):
            self.reset()
        self._t.append(float(t_s))
        self._R.append(np.asarray(R_cam_body, dtype=float))
        self._p.append(np.asarray(p_cam, dtype=float))
        keep = 2 if self.params.method == "difference" else None
        longest = max(self.params.window_s, self.params.position_window_s)
        while len(self._t) > 2 and (keep is not None and len(self._t) > keep or t_s - self._t[0] > longest):
            self._t.popleft(), self._R.popleft(), self._p.popleft()
        if len(self._t) < 2:
            return None
        if self.params.method == "difference":
            return finite_difference_rates(self._t[-2], self._R[-2], self._p[-2], self._t[-1], self._R[-1], self._p[-1])
        t = np.array(self._t)
        R = np.array(self._R)
        P = np.array(self._p)
        rot = t >= t_s - self.params.window_s - 1e-9
        pos = t >= t_s - self.params.position_window_s - 1e-9
        rot[-2:] = pos[-2:] = True
        _, _, _, omega = local_polynomial_rates(t[rot], R[rot], P[rot], self.params.order)
        _, _, v, _ = local_polynomial_rates(t[pos], R[pos], P[pos], self.params.position_order)
        return v, omega
