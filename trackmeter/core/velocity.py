"""Linear and angular velocity from a stream of poses (paper eq. 14, and a better estimator).

The paper differentiates the measured attitude: ``(0, omega_body) = 2 q* ⊗ q_dot`` (eq. 14),
which on sampled poses is the finite difference on the rotation group
``omega_body = log(R_{k-1}^T R_k) / dt`` (:func:`trackmeter.core.transforms.omega_body_between`)
and ``v_cam = (t_k - t_{k-1}) / dt`` for the body origin. Differencing two independent
samples multiplies the noise by sqrt(2) and divides it by ``dt`` (40 ms at 25 Hz): a 1 mm position
noise becomes ~35 mm/s.

The other estimators fit a causal local polynomial instead. ``'poly'`` is a Savitzky-Golay fit
on the rotation group and R^3 separately: over the poses of the last ``window_s`` seconds,
express each attitude in the chart of the newest one as a body-frame rotation vector ``phi_k =
log(R_ref^T R_k)``, fit a polynomial of degree ``order`` in time to ``phi`` and to the position
by least squares, and evaluate its derivative at the newest time. With ``R(tau) = R_ref
exp(phi(tau))`` the body angular velocity is ``omega_body = J_r(phi) phi'`` (``J_r``: right
Jacobian of SO(3)), which is eq. 14 applied to the fitted curve. A motion that is polynomial of
degree ``order`` in the chart (constant rate, constant angular acceleration about a fixed axis)
is differentiated exactly; noise is averaged over the window. ``benchmarks/accuracy.py``
compares it with the plain eq. 14 difference.

The default (``VelocityParams.method``), ``'screw'``, fits on SE(3) instead: each pose of the
window enters as the twist coordinates ``x_k = log(T_ref^-1 T_k)`` (6,) in the chart of the
newest pose, a polynomial of degree ``screw_order`` (default 1) is fitted to them, and the
fitted curve ``T(tau) = T_ref exp(x(tau))`` is differentiated at the newest time. A constant
body twist (a screw motion: constant ``omega_body`` and constant body-frame velocity of the
origin) is a straight line in this chart, so order 1 differentiates it exactly *whatever the
origin* —
whereas the SO(3) x R^3 fit above sees an origin off the rotation axis move on a curve (its
velocity ``v + omega x r`` turns with the body) and needs order 2, whose end-point slope has
about 4 times the standard deviation of order 1's over the same window
(Savitzky-Golay end-point weights). The window is ``screw_window_s`` long but reaches back no
further than the body has turned ``screw_max_angle_deg``: the chart stays far from the cut
locus at pi (a fast tumble's poses would otherwise wrap), and since Euler's equations are
invariant under ``omega -> s omega, t -> t/s``, a window fixed in angle gives a torque-free
tumble the same relative lag at any spin rate.

Measured on the estec scenario, case (a), from recorded engine poses (first 20 s; the errors
after a 2 s settle, max/RMS): 'poly' 3.3/0.8 mm/s lateral, 2.7/0.9 mm/s depth, 0.42/0.08 deg/s;
'screw' 0.8/0.2, 1.2/0.5, 0.10/0.03. What remains is mostly the pose's own low-frequency error
(slowly varying per-point measurement errors), not steps where the set of tracked points
changes: frame-to-frame pose steps are only ~5 % larger at set changes than without one.
The price is lag when the twist changes: fed the TRUE poses, 'screw' errs by up to 0.035 deg/s
and 0.35 mm/s on estec (the precession turns omega; 'poly' 0.002 deg/s, 0.27 mm/s), and on the
195 deg/s fast_tumble, whose window the 30 deg cap makes ~0.15 s long, by 8 deg/s (4 %) where
the SO(3) chart of 'poly' wraps (errors of hundreds of deg/s).

A constant twist is not how a free-floating target moves while it is approached: its centre of
mass drifts in a straight line across its spin axis, and the screw fit turns that velocity with
the body (:func:`free_body_velocity`). 'screw' therefore also fits the centre of mass moving in
a straight line and blends that fit's velocity in as the error that fit says the screw makes,
``tau (omega x v)``, stands clear of its own noise (``free_body_min_bias_sigmas`` to
``free_body_full_bias_sigmas``, the share smoothed over ``free_body_blend_s``); 'free_body'
always takes it (noisier over a short turn).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Literal, NamedTuple, overload

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from trackmeter.core.checks import finite_rows, finite_time, rotation_matrix
from trackmeter.core.params import check_params, param
from trackmeter.core.transforms import omega_body_between, rotation_from_matrix, skew
from trackmeter.errors import TrackmeterError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class VelocityParams:
    """Tunables of the velocity estimation."""

    method: str = param(
        "screw", "'screw': causal polynomial fit on SE(3) (constant twist exact at order 1); 'free_body': the "
        "screw fit's angular velocity, and the origin's velocity from the centre of mass drifting in a straight "
        "line while the body turns about it; 'poly': on SO(3) and R^3 separately; 'difference': eq. 14 finite difference",
        choices=("screw", "free_body", "poly", "difference"),
    )
    screw_window_s: float = param(2.5, "screw: longest window of the fit, s", min=0.05)
    screw_order: int = param(1, "screw: degree of the polynomial in the twist chart (1 = constant twist)",
                             min=1, max=3)
    screw_max_angle_deg: float = param(
        30.0, "screw: the window reaches back no further than the body has turned this far, deg "
        "(a fast tumble gets a short window, and the chart never wraps)", min=1.0, max=170.0,
    )
    free_body_rss_ratio: float = param(
        1.0, "screw: blend in the free-body velocity only when its fit leaves less than this fraction of the "
        "screw fit's position residual per degree of freedom, over a window of min_span_s at least (a body "
        "drifting across its spin axis); 0: never", min=0.0, max=1.0,
    )
    free_body_min_bias_sigmas: float = param(
        6.0, "screw: ... and when the error the screw fit would make, tau (omega x v), exceeds this many of its "
        "own standard deviations, from the free-body fit's velocity (a slow drift keeps the less noisy screw fit; "
        "pose errors correlated in time put estec's 3 mm/s drift at up to 7, rarely over 6)", min=0.0,
    )
    free_body_full_bias_sigmas: float = param(
        10.0, "screw: ... wholly from this many sigmas on, in proportion between (a switch at one threshold "
        "flipped the velocity by the screw's error, mm/s, frame to frame, where the drift hovers near it)",
        min=0.0,
    )
    free_body_blend_s: float = param(
        0.5, "screw: time constant of the free-body velocity's share (its changes are smoothed: a share "
        "stepping with the noise of the test would step the velocity), s", min=0.0,
    )
    window_s: float = param(1.2, "poly: window of the attitude fit (angular velocity), s", min=0.05)
    order: int = param(2, "poly: degree of the attitude polynomial (1 = constant rate, 2 = constant acceleration)",
                       min=1, max=4)
    position_window_s: float = param(
        3.0, "poly: window of the position fit, s (the relative translation is slow and smooth)", min=0.05
    )
    position_order: int = param(2, "poly: degree of the position polynomial (1 = constant velocity)", min=1, max=4)
    min_span_s: float = param(
        0.4, "screw, free_body, poly: no velocity is reported until the fitted poses span this long (a "
        "restart after a gap would otherwise report a two-pose difference; screw and free_body also once "
        "their window is capped by screw_max_angle_deg), s", min=0.0,
    )
    max_gap_s: float = param(0.5, "a gap between valid poses longer than this restarts the output filter, s", min=0.0)
    bridge_gap_s: float = param(
        2.5, "poses before a gap up to this long stay in the velocity window (same body frame): the "
        "rates after a short loss are fitted across it, not from the few poses since; a longer gap "
        "restarts the estimator, s", min=0.0,
    )
    change_f: float = param(
        300.0, "screw: a change of the spin (a release from rest, a capture attempt's push) cuts the window: "
        "when two constant angular velocities, before and after some pose, explain the window's attitudes "
        "better than one by this Chow F statistic, the poses before are dropped; 0: never. Measured 23-98 "
        "at most on 20 s of estec and harsh_light in cases (a) and (b) (no change; pose errors are "
        "correlated in time, so F runs well above its table), 406 0.32 s and 1153 0.40 s after a release "
        "from rest (hold_release). The attitudes only: a body drifting across its spin axis is no "
        "constant twist in position, and free_body_rss_ratio handles that. Each side of a split spans "
        "min_span_s at least (and 0.2 s)", min=0.0,
    )
    weighted: bool = param(
        True, "weight each pose of the window by its covariance (rotation and position parts "
        "separately): a pose measured from few points counts for little",
    )

    def __post_init__(self) -> None:
        check_params(self)  # declared ranges and choices, as the config loader checks them


def right_jacobian_so3(phi: ArrayLike) -> FloatArray:
    """Right Jacobian of SO(3) at rotation vector ``phi`` (3,): ``d/dt exp(phi) = exp(phi) [J_r phi']x``.

    ``J_r = I - (1 - cos θ)/θ² [phi]x + (θ - sin θ)/θ³ [phi]x²`` (Chirikjian, *Stochastic Models,
    Information Theory and Lie Groups* vol. 2, eq. 10.86; Barfoot, *State Estimation for
    Robotics*, eq. 7.77b).
    """
    phi = np.asarray(phi, dtype=float)
    theta = float(np.linalg.norm(phi))
    K = skew(phi)
    if theta < 1e-6:
        return np.eye(3) - 0.5 * K + K @ K / 6.0
    return np.eye(3) - (1 - np.cos(theta)) / theta**2 * K + (theta - np.sin(theta)) / theta**3 * K @ K


def finite_difference_rates(
    t0_s: float, R0: ArrayLike, p0: ArrayLike, t1_s: float, R1: ArrayLike, p1: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Plain eq. 14 on two poses: ``(v_cam (3,) m/s, omega_body (3,) rad/s)``.

    ``R0``, ``R1`` (3,3) ``R_cam_body`` and ``p0``, ``p1`` (3,) body origins in the camera frame,
    m, at ``t0_s`` < ``t1_s``, s.

    Raises:
        TrackmeterError: ``t1_s`` not after ``t0_s``, or a time not finite (checked before dividing: no warning);
            ``R0``/``R1`` not a rotation or ``p0``/``p1`` not a finite (3,) (a NaN rotation
            raised numpy's LinAlgError from scipy).
    """
    dt = t1_s - t0_s
    if not 0 < dt < math.inf:
        raise TrackmeterError(f"t1_s must come after t0_s: dt_s must be positive and finite, s; got {dt:g}")
    Rs = np.stack([rotation_matrix(R0, "R0"), rotation_matrix(R1, "R1")])
    p_start, p_end = finite_rows(p0, "p0", (3,)), finite_rows(p1, "p1", (3,))
    # one scipy conversion for both (each row is the single call's number)
    q0, q1 = rotation_from_matrix(Rs).as_quat(scalar_first=True)
    v = (p_end - p_start) / dt
    return v, omega_body_between(q0, q1, dt)


def block_weights(cov_pose: ArrayLike) -> FloatArray:
    """Per-pose weights ``(w_position, w_rotation)`` (N,2) from pose covariances (N,6,6) (position
    m, rotation vector rad): the inverse of each block's mean variance, ``3 / tr(Sigma_block)``.

    A trace is invariant under rotation, so the weight is the same whatever frame the block is
    expressed in (the fits below work in the newest pose's body chart). A non-finite or
    non-positive block weighs 0."""
    C = np.asarray(cov_pose, dtype=float).reshape(-1, 6, 6)
    tr = np.stack([np.trace(C[:, :3, :3], axis1=1, axis2=2), np.trace(C[:, 3:, 3:], axis1=1, axis2=2)], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(np.isfinite(tr) & (tr > 0), 3.0 / tr, 0.0)
    return w


def weighted_polyfit(V: ArrayLike, X: ArrayLike, weights: ArrayLike | None = None) -> FloatArray:
    """Least-squares coefficients ``coef`` (K,M) of ``X ≈ V @ coef`` for a design matrix ``V`` (N,K)
    and data ``X`` (N,M), column ``j`` of ``X`` weighted by ``weights[:, j]`` (N,M) (inverse
    variances; None: all equal): ``coef_j = (Vᵀ W_j V)⁻¹ Vᵀ W_j x_j`` — the weighted
    Savitzky-Golay fit. A column whose weights cannot determine its fit (fewer positive
    weights than coefficients) falls back to equal weights."""
    V = np.asarray(V, dtype=float)
    X = np.asarray(X, dtype=float)
    if weights is None:
        return np.linalg.lstsq(V, X, rcond=None)[0]
    W = np.broadcast_to(np.asarray(weights, dtype=float), X.shape)
    K = V.shape[1]
    usable = (W > 0).sum(axis=0) >= K
    W = np.where(usable[None, :], W, 1.0)
    W = W / W.max(axis=0, keepdims=True)  # the solution is scale-free; this keeps it conditioned
    A = np.einsum("nk,nm,nl->mkl", V, W, V)  # (M,K,K) normal matrices
    b = np.einsum("nk,nm,nm->mk", V, W, X)  # (M,K)
    return np.linalg.solve(A, b[..., None])[..., 0].T


def _increasing_times(times_s: ArrayLike) -> FloatArray:
    """``times_s`` as a finite (N,) array, N >= 2, that increases strictly, s.

    The fits differentiate in ``tau = t - t_newest``: times given newest-first flip the sign of
    every rate, and equal times leave nothing to differentiate (v = omega = 0, silently).

    Raises:
        TrackmeterError: naming the first time that does not follow its predecessor.
    """
    t = finite_rows(times_s, "times_s", (None,))
    if len(t) < 2:  # one pose holds no motion: its degree-0 fit said v = omega = 0
        raise TrackmeterError(f"rates need at least 2 poses, got {len(t)}")
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        k = int(back[0]) + 1
        raise TrackmeterError(f"times_s must increase strictly: times_s[{k}] = {t[k]:g} follows {t[k - 1]:g}")
    return t


def local_polynomial_rates(
    times_s: ArrayLike, R: ArrayLike, p: ArrayLike, order: int, t_eval_s: float | None = None,
    weights: ArrayLike | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Fit a polynomial to a window of poses on SE(3) and differentiate it (Savitzky-Golay on the group).

    Args:
        times_s: (N,) strictly increasing times, N >= 2, s (else TrackmeterError).
        R: (N,3,3) attitudes ``R_cam_body``.
        p: (N,3) body-origin positions in the camera frame, m.
        order: polynomial degree; uses ``min(order, N-1)``.
        t_eval_s: where to evaluate; default the newest time.
        weights: optional (N,2) ``(w_position, w_rotation)`` per pose (:func:`block_weights`).

    Returns:
        ``(p_fit (3,), R_fit (3,3), v_cam (3,) m/s, omega_body (3,) rad/s)`` at ``t_eval_s``.
    """
    t = _increasing_times(times_s)
    Rm = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    P = np.asarray(p, dtype=float).reshape(-1, 3)
    t_eval = t[-1] if t_eval_s is None else float(t_eval_s)
    deg = min(order, len(t) - 1)
    R_ref = Rm[-1]
    phi = rotation_from_matrix(np.einsum("ji,njk->nik", R_ref, Rm)).as_rotvec()  # log(R_ref^T R_k)
    tau = t - t_eval
    scale = max(float(np.max(np.abs(tau))), 1e-9)  # conditioning of the Vandermonde matrix
    V = np.vander(tau / scale, deg + 1, increasing=True)
    Wc = None if weights is None else np.repeat(np.asarray(weights, dtype=float).reshape(-1, 2)[:, ::-1], 3, axis=1)
    coef = weighted_polyfit(V, np.column_stack([phi, P]), Wc)
    value = coef[0]
    slope = coef[1] / scale if deg >= 1 else np.zeros(6)
    phi0, phi_dot = value[:3], slope[:3]
    R_fit = R_ref @ Rotation.from_rotvec(phi0).as_matrix()
    omega = right_jacobian_so3(phi0) @ phi_dot
    return value[3:], R_fit, slope[3:], omega


def se3_log(R: ArrayLike, t: ArrayLike) -> FloatArray:
    """Twist coordinates ``(rho, theta)`` of rigid transforms ``(R, t)``: ``(R, t) = exp(x)``.

    ``theta = log(R)`` (rotation vector) and ``rho = J_l(theta)^-1 t`` with the inverse left
    Jacobian of SO(3) ``J_l^-1 = I - [theta]x / 2 + (1/θ² - (1 + cos θ) / (2 θ sin θ)) [theta]x²``
    (Barfoot, *State Estimation for Robotics*, eqs. 7.83, 7.85 and 7.86). ``rho`` is the
    body-frame velocity of the origin times the time of a constant twist.

    Args:
        R: (3,3) or (N,3,3) rotations; t: (3,) or (N,3) translations, m.

    Returns:
        (6,) or (N,6) ``(rho, theta)``.
    """
    Rm = np.asarray(R, dtype=float)
    single = Rm.ndim == 2
    Rm = Rm.reshape(-1, 3, 3)
    tv = np.asarray(t, dtype=float).reshape(-1, 3)
    theta = rotation_from_matrix(Rm).as_rotvec()
    a = np.linalg.norm(theta, axis=1)
    small = a < 1e-4
    a_safe = np.where(small, 1.0, a)
    # coefficient of [theta]x^2; its series 1/12 + θ²/720 near 0
    c2 = np.where(small, 1.0 / 12.0 + a**2 / 720.0,
                  1.0 / a_safe**2 - (1.0 + np.cos(a_safe)) / (2.0 * a_safe * np.sin(a_safe)))
    cross1 = np.cross(theta, tv)
    cross2 = np.cross(theta, cross1)
    rho = tv - 0.5 * cross1 + c2[:, None] * cross2
    out = np.concatenate([rho, theta], axis=1)
    return out[0] if single else out


def se3_exp(x: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Inverse of :func:`se3_log`: ``(R (3,3), t (3,))`` of the twist coordinates ``x = (rho, theta)``."""
    x = np.asarray(x, dtype=float)
    return Rotation.from_rotvec(x[3:]).as_matrix(), right_jacobian_so3(-x[3:]) @ x[:3]


@overload
def screw_rates(
    times_s: ArrayLike, R: ArrayLike, p: ArrayLike, order: int = 1, t_eval_s: float | None = None,
    weights: ArrayLike | None = None, return_rss: Literal[False] = False,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]: ...


@overload
def screw_rates(
    times_s: ArrayLike, R: ArrayLike, p: ArrayLike, order: int = 1, t_eval_s: float | None = None,
    weights: ArrayLike | None = None, *, return_rss: Literal[True],
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, float]: ...


@overload
def screw_rates(
    times_s: ArrayLike, R: ArrayLike, p: ArrayLike, order: int = 1, t_eval_s: float | None = None,
    weights: ArrayLike | None = None, return_rss: bool = False,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray] | tuple[FloatArray, FloatArray, FloatArray, FloatArray, float]: ...


def screw_rates(
    times_s: ArrayLike, R: ArrayLike, p: ArrayLike, order: int = 1, t_eval_s: float | None = None,
    weights: ArrayLike | None = None, return_rss: bool = False,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray] | tuple[FloatArray, FloatArray, FloatArray, FloatArray, float]:
    """Fit a polynomial to a window of poses in the twist chart of SE(3) and differentiate it.

    With ``T_ref`` the newest pose, ``x_k = log(T_ref^-1 T_k)`` (:func:`se3_log`) is fitted by a
    polynomial ``x(tau)`` of degree ``min(order, N-1)`` (least squares); the motion
    ``T(tau) = T_ref exp(x(tau))`` is then differentiated by a central difference of the
    fitted curve (step 1e-4 of the window: exact to ~1e-8 relative). For a constant body
    twist ``x_k`` is linear in time, so order 1 is exact (module docstring). The rotation
    between any pose of the window and the newest must stay below pi (the caller's window).

    Args:
        times_s: (N,) strictly increasing times, N >= 2, s (else TrackmeterError).
        R: (N,3,3) attitudes ``R_cam_body``.
        p: (N,3) body-origin positions in the camera frame, m.
        order: polynomial degree.
        t_eval_s: where to evaluate; default the newest time.
        weights: optional (N,2) ``(w_position, w_rotation)`` per pose (:func:`block_weights`):
            ``rho`` is fitted with the position weights, ``theta`` with the rotation weights.

        return_rss: also return the fit's position residual ``sum_k w_k |rho_k - rho(tau_k)|²``
            (m², the position weights or 1; ``rho`` is the origin's displacement in the chart,
            within a few per cent of its metres over the window's turn).

    Returns:
        ``(p_fit (3,), R_fit (3,3), v_cam (3,) m/s, omega_body (3,) rad/s)`` at ``t_eval_s``:
        ``v_cam`` is the body origin's velocity in the camera frame, ``omega_body`` the angular
        velocity in the body frame (eq. 14 on the fitted curve); and the residual with ``return_rss``.
    """
    t = _increasing_times(times_s)
    Rm = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    P = np.asarray(p, dtype=float).reshape(-1, 3)
    t_eval = t[-1] if t_eval_s is None else float(t_eval_s)
    deg = min(order, len(t) - 1)
    R_ref, p_ref = Rm[-1], P[-1]
    X = se3_log(np.einsum("ji,njk->nik", R_ref, Rm), (P - p_ref) @ R_ref)
    tau = t - t_eval
    scale = max(float(np.max(np.abs(tau))), 1e-9)  # conditioning of the Vandermonde matrix
    Wc = None if weights is None else np.repeat(np.asarray(weights, dtype=float).reshape(-1, 2), 3, axis=1)
    V = np.vander(tau / scale, deg + 1, increasing=True)
    coef = weighted_polyfit(V, X, Wc)

    h = 1e-4 * scale
    # the fitted twist at 0, -h and +h, exponentiated in one scipy call (from_rotvec costs
    # ~20 us a call, about the same for three; each row is se3_exp's number)
    x = np.array([np.vander(np.array([s / scale]), deg + 1, increasing=True)[0] @ coef for s in (0.0, -h, h)])
    dR = Rotation.from_rotvec(x[:, 3:]).as_matrix()
    poses = [(R_ref @ dR[k], p_ref + R_ref @ (right_jacobian_so3(-x[k, 3:]) @ x[k, :3])) for k in range(3)]
    (R_fit, p_fit), (R_a, p_a), (R_b, p_b) = poses
    v = (p_b - p_a) / (2 * h)
    omega = rotation_from_matrix(R_a.T @ R_b).as_rotvec() / (2 * h)
    if not return_rss:
        return p_fit, R_fit, v, omega
    w_pos = np.ones(len(t)) if weights is None else np.asarray(weights, dtype=float).reshape(-1, 2)[:, 0]
    residual = X[:, :3] - V @ coef[:, :3]
    return p_fit, R_fit, v, omega, float(np.einsum("n,ni,ni->", w_pos, residual, residual))


def twist_change_point(times_s: ArrayLike, X: ArrayLike, weights: ArrayLike | None = None,
                       min_span_s: float = 0.4) -> tuple[float, int]:
    """The strongest change of a linear trend in ``X`` over time: Chow's F test at every split.

    One straight line per column of ``X`` over the whole window against two, one before pose
    ``s`` and one from it (G. C. Chow, "Tests of equality between sets of coefficients in two
    linear regressions", Econometrica 28, 1960):
    ``F = ((RSS_1 - RSS_2) / k) / (RSS_2 / (M N - 2 k))``, ``k = 2 M`` coefficients per line set,
    weighted least squares (the residual sums of all ``M`` columns). Each split leaves at least
    ``min_span_s`` on both sides; the sums of every split come from prefix sums, so the scan
    costs one pass.

    Args:
        times_s: (N,) increasing times, s.
        X: (N,M) data, e.g. the twist coordinates of :func:`screw_rates` (a constant twist is a
            straight line in them).
        weights: (N,M) inverse variances per entry (None: equal).
        min_span_s: shortest span of either segment, s.

    Returns:
        ``(F, s)``: the largest F and the index of the first pose after that split; ``(0.0, 0)``
        when no split leaves both segments long enough (or they fit exactly).
    """
    t = np.asarray(times_s, dtype=float)
    Xm = np.asarray(X, dtype=float).reshape(len(t), -1)
    n, m = Xm.shape
    W = np.ones_like(Xm) if weights is None else np.broadcast_to(np.asarray(weights, dtype=float), Xm.shape)
    W = W / max(float(W.max()), 1e-300)  # one scale for all: F is scale-free, the columns keep their weights
    Xm = Xm - (W * Xm).sum(axis=0) / np.maximum(W.sum(axis=0), 1e-300)  # centred: less cancellation
    tau = (t - t[-1]) / max(t[-1] - t[0], 1e-9)
    T = tau[:, None]
    parts = np.stack([W, W * T, W * T * T, W * Xm, W * T * Xm, W * Xm * Xm])  # (6,N,M)
    cum = np.concatenate([np.zeros((6, 1, m)), np.cumsum(parts, axis=1)], axis=1)  # (6,N+1,M)

    def rss(total: NDArray[np.float64]) -> NDArray[np.float64]:  # (6,...,M) sums -> (...,) residual
        s0, s1, s2, sy, sty, syy = total
        det = s0 * s2 - s1 * s1
        with np.errstate(divide="ignore", invalid="ignore"):
            fit = np.where(det > 0, (s2 * sy * sy - 2 * s1 * sy * sty + s0 * sty * sty) / det, 0.0)
        return np.maximum(syy - fit, 0.0).sum(axis=-1)

    split = np.arange(2, n - 1)  # the first pose after the split; two poses at least on each side
    ok = (t[split - 1] - t[0] >= min_span_s) & (t[-1] - t[split] >= min_span_s)
    candidates = split[ok]
    dof = m * n - 4 * m
    if len(candidates) == 0 or dof <= 0:
        return 0.0, 0
    one = rss(cum[:, n])
    if one <= 1e-12 * float(cum[5, n].sum()):  # one line fits to rounding: nothing to split
        return 0.0, 0
    two = rss(cum[:, candidates]) + rss(cum[:, [n]] - cum[:, candidates])
    with np.errstate(divide="ignore", invalid="ignore"):
        F = np.where(two > 0, ((one - two) / (2 * m)) / (two / dof), 0.0)
    best = int(np.argmax(F))
    return float(F[best]), int(candidates[best])


class FreeBodyVelocity(NamedTuple):
    """Result of :func:`free_body_velocity`."""

    v_origin: FloatArray  #: (3,) the body origin's velocity in the camera frame, m/s
    rss: float  #: the fit's weighted position residual, m² (as :func:`screw_rates`'s)
    screw_bias_sigmas: float  #: the screw fit's expected error over the fitted velocity's sigma
    residual_dof: float  #: the residual's degrees of freedom (CentreOfMassFit's)


def free_body_velocity(times_s: ArrayLike, R: ArrayLike, p: ArrayLike, omega_body: ArrayLike,
                       position_weights: ArrayLike, lever_m: float) -> FreeBodyVelocity | None:
    """The body origin's velocity (3,) m/s in the camera frame at the newest pose of a window, for
    a free body: its centre of mass drifts in a straight line while it turns about it.

    :func:`trackmeter.core.dynamics.fit_centre_of_mass` fits ``p_k + R_k c = a + v tau_k`` (``c``
    the centre of mass in the body frame, prior ``c ~ N(0, lever_m² I)``); the origin
    ``p = a + v tau - R c`` then moves at ``v_origin = v - R (omega_body x c)`` (``dR/dt =
    R [omega]x``). A constant screw is the case of a centre on the screw axis moving along it,
    so the fit holds it too; but a centre drifting across the spin axis — a free-floating
    target approached while it tumbles — is not a constant body twist: the screw fit turns its
    velocity with the body, an error of about ``tau (omega x v)`` for a window of mean age
    ``tau``.

    Returns:
        :class:`FreeBodyVelocity`: ``screw_bias_sigmas`` is the screw fit's expected error
        ``tau (omega_cam x v)`` (``tau`` half the window) over its own standard deviation
        (the largest of ``J cov_v J^T``, ``J = tau [omega_cam]x``), i.e. how clearly the drift
        across the spin axis is seen. None with fewer than 3 weighted poses.
    """
    from trackmeter.core.dynamics import fit_centre_of_mass

    Rm = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    fit = fit_centre_of_mass(times_s, Rm, p, position_weights, lever_m)
    if fit is None:
        return None
    omega = np.asarray(omega_body, dtype=float)
    t = np.asarray(times_s, dtype=float)
    # The expected error and its own sigma: J = tau [omega_cam]x maps the fitted v (and its
    # covariance) onto it. The v of the centre of mass alone is loose over a short turn (mm/s,
    # told from the centre's place only by the turn), but the part of it across the spin
    # axis, which makes the error, is not (2026-12-06, an outside probe's renderer).
    J = 0.5 * (t[-1] - t[0]) * skew(Rm[-1] @ omega)
    bias = float(np.linalg.norm(J @ fit.v_cam))
    sigma = float(np.sqrt(max(np.linalg.eigvalsh(J @ fit.cov[6:, 6:] @ J.T).max(), 0.0)))
    sigmas = bias / sigma if sigma > 0 else float("inf")
    return FreeBodyVelocity(fit.v_cam - Rm[-1] @ np.cross(omega, fit.c_body), fit.rss, float(sigmas),
                            fit.residual_dof)


def free_body_noise_weight(times_s: ArrayLike, R: ArrayLike, p: ArrayLike, omega_body: ArrayLike,
                           screw_rss_m2: float, lever_m: float) -> float:
    """The poses' position weight ``1 / sigma²`` (1/m², one per pose) read from the free-body
    fit's own residual, for a window of poses given without covariances.

    The N poses' positions (3N numbers) are fitted by :func:`free_body_velocity` with 9 unknowns
    (the centre of mass ``c`` in the body frame, its place ``a`` and velocity ``v``), so with
    each coordinate's noise of variance ``sigma²`` the unweighted residual's expectation is
    the fit's ``residual_dof`` times ``sigma²`` (``3N - 9`` where the poses fix every unknown;
    more where the prior on ``c`` holds some: its component along a fixed spin axis always,
    part of the rest over a short turn), and ``residual_dof / rss`` estimates the weight. The
    fit weighs that prior (``lever_m``) against the data by the weight, so it is run with a
    first guess: the screw fit's residual ``screw_rss_m2`` over its ``3N - 6`` degrees of
    freedom (6 unknowns). The screw's residual alone would not do: it holds the very error of a
    body drifting across its spin axis that the free-body fit is there to see. Counting
    ``3N - 9`` made the weight 11 % too low over 8 poses turning 2.5 deg and 1 % over 25
    turning 9 deg (tests/test_velocity.py).

    Args:
        times_s: (N,) increasing, s; R: (N,3,3) R_cam_body; p: (N,3) origin in the camera, m.
        omega_body: (3,) rad/s, the screw fit's angular velocity in the body frame.
        screw_rss_m2: the screw fit's unweighted position residual over the same poses, m².
        lever_m: prior 1-sigma of each coordinate of ``c``, m.

    Returns:
        The weight, 1/m²; 1.0 with 3 poses or fewer or when the fit fails. Residuals are
        floored at 1e-10 m² per degree of freedom (noise-free poses).
    """
    n = len(np.asarray(times_s).reshape(-1))
    if n <= 3:  # before the first guess: with 2 poses it would be 0 / 0
        return 1.0
    first = (3 * n - 6) / max(float(screw_rss_m2), (3 * n - 6) * 1e-10)
    free = free_body_velocity(times_s, R, p, omega_body, np.full(n, first), lever_m)
    if free is None:
        return 1.0
    dof = free.residual_dof
    return dof / max(free.rss / first, dof * 1e-10)


class VelocityEstimator:
    """Causal velocity estimation over a stream of poses (stateful wrapper of the functions above).

    Feed every valid pose with :meth:`update`; :meth:`reset` when the body frame changes
    (new model, case switch) or tracking restarts.
    """

    def __init__(self, params: VelocityParams = VelocityParams(), lever_m: float = 0.5) -> None:
        """``lever_m``: prior 1-sigma of each coordinate of the centre of mass in the body frame
        (its distance from the body origin), m, for the free-body fit (the engine passes
        ``pose.coast_lever_m``, the same prior its coast fits with)."""
        self.params = params
        self.lever_m = float(lever_m)
        self._t: deque[float] = deque()
        self._R: deque[FloatArray] = deque()
        self._p: deque[FloatArray] = deque()
        self._w: deque[FloatArray] = deque()  # (w_position, w_rotation) per pose
        self._capped = False  # screw: the last window was cut short by screw_max_angle_deg
        self._free_share = 0.0  # screw: the free-body velocity's share in the last velocity
        self._free_share_t: float | None = None  # and when it was set, s

    @property
    def settled(self) -> bool:
        """True once the poses in the window span ``min_span_s`` — or, for 'screw', once the
        window is limited by ``screw_max_angle_deg`` and holds at least 3 poses (a fast tumble)
        — before that the rates are provisional: fine for the output filter's chart, not for
        reporting."""
        if self.params.method == "difference":
            return len(self._t) >= 2
        if self.params.method in ("screw", "free_body") and self._capped:
            return True
        # 1 us of slack: epoch times (EuRoC's nanoseconds, 1.7e9 s) are 2.4e-7 s apart as
        # doubles, and a span of exactly min_span_s came out a hair short there.
        return len(self._t) >= 2 and self._t[-1] - self._t[0] >= self.params.min_span_s - 1e-6

    def window(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """The poses the rates are fitted to: ``(times (N,), R_cam_body (N,3,3), p_cam (N,3),
        weights (N,2) (w_position, w_rotation), NaN for a pose given without covariance)``
        (copies; the weights are kept whether or not ``params.weighted`` uses them in the fits)."""
        return (np.array(self._t, dtype=float), np.array(self._R, dtype=float).reshape(-1, 3, 3),
                np.array(self._p, dtype=float).reshape(-1, 3), np.array(self._w, dtype=float).reshape(-1, 2))

    def move_body_frame(self, R_old_new: ArrayLike, t_old_new: ArrayLike) -> None:
        """Re-express the window's poses in a new body frame: ``T_cam_new = T_cam_old T_old_new``
        (``R <- R R_old_new``, ``p <- p + R t_old_new``, ``t_old_new`` in m in the old body frame).

        Why: a correction of the body frame (the engine moving its grown model onto the a-priori
        points) changes the poses that follow by ``T_old_new`` without any motion; left in the
        window's older poses, the fit would read that step as a velocity."""
        Rd = np.asarray(R_old_new, dtype=float)
        td = np.asarray(t_old_new, dtype=float)
        for k in range(len(self._R)):
            R = self._R[k]
            self._p[k] = self._p[k] + R @ td
            self._R[k] = R @ Rd

    def reset(self) -> None:
        self._capped = False
        self._free_share, self._free_share_t = 0.0, None
        self._t.clear()
        self._R.clear()
        self._p.clear()
        self._w.clear()

    def _free_share_for(self, bias_sigmas: float) -> float:
        """The free-body velocity's share for a screw error of ``bias_sigmas`` of its own sigmas:
        0 up to ``free_body_min_bias_sigmas``, 1 from ``free_body_full_bias_sigmas``, linear between."""
        lo, hi = self.params.free_body_min_bias_sigmas, self.params.free_body_full_bias_sigmas
        if hi <= lo:
            return float(bias_sigmas > lo)
        return float(np.clip((bias_sigmas - lo) / (hi - lo), 0.0, 1.0))

    def _smoothed_share(self, share: float, t_s: float) -> float:
        """``share`` through a first-order lag of ``free_body_blend_s`` (exact for its time step)."""
        tau = self.params.free_body_blend_s
        if self._free_share_t is None or tau <= 0.0:
            self._free_share = share
        else:
            self._free_share += (share - self._free_share) * -np.expm1(-max(t_s - self._free_share_t, 0.0) / tau)
        self._free_share_t = t_s
        return self._free_share

    def _change_cut(self, t: FloatArray, R: FloatArray, Wp: FloatArray | None, start: int) -> int:
        """How many of the window's oldest poses to drop because the spin changed after them
        (:func:`twist_change_point` on the attitudes of the screw fit's window from ``start``, in
        the newest pose's chart; ``change_f``), 0 when it did not."""
        # Each side at least min_span_s, and never under 0.2 s (5 poses at 25 Hz): F of two
        # segments of a couple of poses is mostly noise.
        span = max(self.params.min_span_s, 0.2)
        if self.params.change_f <= 0 or len(t) - start < 12 or t[-1] - t[start] < 2 * span:
            return 0
        phi = rotation_from_matrix(np.einsum("ji,njk->nik", R[-1], R[start:])).as_rotvec()  # log(R_ref^T R_k)
        W = None if Wp is None else np.repeat(Wp[start:, 1:], 3, axis=1)
        F, split = twist_change_point(t[start:], phi, W, span)
        return start + split if F > self.params.change_f else 0

    def update(self, t_s: float, R_cam_body: ArrayLike, p_cam: ArrayLike, cov_pose: ArrayLike | None = None
               ) -> tuple[FloatArray, FloatArray] | None:
        """Add a pose; return ``(v_cam m/s, omega_body rad/s)``, or None until two poses are known.

        A pose whose ``t_s`` is not after the previous one's (repeated or backward: a source
        restarted or replayed), or more than ``bridge_gap_s`` after it, starts the estimator
        over (:meth:`reset`): the window then holds this pose alone and None is returned. A
        repeated time cannot be differentiated and a backward one would flip every rate's sign,
        and the poses before it are taken to belong to another run.

        ``cov_pose`` (6,6) (position m, rotation vector rad), when given and ``params.weighted``,
        weighs the pose in the fits (:func:`block_weights`). Why: the poses just before a loss
        are often measured from 3-4 points (attitude sigma ~1 deg against ~0.05 deg with 16);
        fitted with equal weights they turned the rates at the loss by ~2 deg/s on harsh_light,
        which a coast then integrates.

        Raises:
            TrackmeterError: ``R_cam_body`` not a (3,3) rotation, ``p_cam`` not a finite (3,),
                ``t_s`` not finite, ``cov_pose`` not (6,6) (a non-finite one weighs 0): refused
                before it joins the window, where one NaN would spoil every fit over the next
                ``window_s``; the window is left as it was."""
        t_s = finite_time(t_s, "t_s")
        R_new = rotation_matrix(R_cam_body, "R_cam_body")
        p_new = finite_rows(p_cam, "p_cam", (3,))
        w_new = np.full(2, np.nan)
        if cov_pose is not None:
            cov = np.asarray(cov_pose, dtype=float)
            if cov.shape != (6, 6):
                raise TrackmeterError(f"cov_pose must be (6,6) (position m, rotation vector rad), got {cov.shape}")
            w_new = block_weights(cov)[0]
        if self._t and (t_s <= self._t[-1] or t_s - self._t[-1] > self.params.bridge_gap_s):
            self.reset()
        self._t.append(float(t_s))
        self._R.append(R_new)
        self._p.append(p_new)
        self._w.append(w_new)
        keep = 2 if self.params.method == "difference" else None
        if self.params.method in ("screw", "free_body"):
            longest = self.params.screw_window_s
        else:
            longest = max(self.params.window_s, self.params.position_window_s)
        while len(self._t) > 2 and (keep is not None and len(self._t) > keep or t_s - self._t[0] > longest):
            self._t.popleft(), self._R.popleft(), self._p.popleft(), self._w.popleft()
        if len(self._t) < 2:
            return None
        if self.params.method == "difference":
            return finite_difference_rates(self._t[-2], self._R[-2], self._p[-2], self._t[-1], self._R[-1], self._p[-1])
        t = np.array(self._t)
        R = np.array(self._R)
        P = np.array(self._p)
        Wp: FloatArray | None
        Wp = np.array(self._w)  # assigned apart from the declaration: mypy narrows it to an array
        if not self.params.weighted or not np.all(np.isfinite(Wp)):
            Wp = None  # equal weights: plain least squares
        if self.params.method in ("screw", "free_body"):
            # Newest poses within screw_max_angle_deg of the newest attitude (angle from the trace).
            cos = (np.einsum("ij,nij->n", R[-1], R) - 1.0) / 2.0
            far = np.flatnonzero(cos < np.cos(np.radians(self.params.screw_max_angle_deg)))
            start = int(far[-1]) + 1 if len(far) else 0
            cut = self._change_cut(t, R, Wp, start)
            if cut:  # the motion changed: the poses before it belong to another twist, for good
                for _ in range(cut):
                    self._t.popleft(), self._R.popleft(), self._p.popleft(), self._w.popleft()
                t, R, P = t[cut:], R[cut:], P[cut:]
                Wp = None if Wp is None else Wp[cut:]
                start = 0
            self._capped = start > 0 and len(t) - start >= 3
            if len(t) - start < 2:  # turned further than the cap within one frame: the last two
                start = len(t) - 2
            _, _, v, omega, rss = screw_rates(t[start:], R[start:], P[start:], self.params.screw_order,
                                              weights=None if Wp is None else Wp[start:], return_rss=True)
            always = self.params.method == "free_body"
            n = len(t) - start
            # Compared only over a window long enough to tell the paths apart (a few poses are
            # fitted almost exactly by either), residual per degree of freedom (9 against 6).
            compare = self.params.free_body_rss_ratio > 0 and t[-1] - t[start] >= self.params.min_span_s and n >= 6
            if always or compare:
                weight = 1.0
                if Wp is None:
                    # Without the poses' covariances, their noise as the free-body fit's residual
                    # shows it: unit weights made it 1 m, and the screw's own residual holds the
                    # very error the test looks for (the share never came in; two re-checks).
                    weight = free_body_noise_weight(t[start:], R[start:], P[start:], omega, rss, self.lever_m)
                free = free_body_velocity(t[start:], R[start:], P[start:], omega,
                                          np.full(n, weight) if Wp is None else Wp[start:, 0], self.lever_m)
                # A free-floating body that drifts across its spin axis: the constant twist cannot
                # follow its path (module docstring), and the straight-line centre fits it better.
                # Blended in by how clearly the screw's error shows, the share smoothed in time.
                if free is not None and always:
                    v = free.v_origin
                elif free is not None:
                    share = 0.0
                    if free.rss / weight / (3 * n - 9) < self.params.free_body_rss_ratio * rss / (3 * n - 6):
                        share = self._free_share_for(free.screw_bias_sigmas)
                    v = v + self._smoothed_share(share, t_s) * (free.v_origin - v)
            else:
                self._smoothed_share(0.0, t_s)
            return v, omega
        rot = t >= t_s - self.params.window_s - 1e-9
        pos = t >= t_s - self.params.position_window_s - 1e-9
        rot[-2:] = pos[-2:] = True
        _, _, _, omega = local_polynomial_rates(t[rot], R[rot], P[rot], self.params.order, weights=None if Wp is None else Wp[rot])
        _, _, v, _ = local_polynomial_rates(t[pos], R[pos], P[pos], self.params.position_order,
                                         weights=None if Wp is None else Wp[pos])
        return v, omega
