"""Free (torque-free) rigid-body motion: Euler's equations and quaternion kinematics.

Paper section 3. The attitude of a body with no external torque obeys Euler's equations in
its principal axes (paper eq. 13, Goldstein, *Classical Mechanics*, 3rd ed., eq. 5.39')::

    I1 dw1/dt = (I2 - I3) w2 w3
    I2 dw2/dt = (I3 - I1) w3 w1
    I3 dw3/dt = (I1 - I2) w1 w2

and the attitude quaternion ``q_world_body`` follows the body-frame angular velocity through
paper eq. 15, ``q_dot = 1/2 q ⊗ (0, omega_body)`` (:func:`trackmeter.core.transforms.quat_derivative`).

The 7-dimensional system is integrated once with an adaptive 8th-order Dormand-Prince method
(``scipy.integrate.solve_ivp``, ``DOP853``) at tight tolerances; its dense output gives the
state at any time in the span, and the quaternion is renormalised on evaluation. Kinetic
energy and the magnitude of the angular momentum are conserved to ~1e-12 relative over
minutes of tumbling (see ``tests/test_dynamics.py``).

An inertia tensor given in any body frame is reduced to principal axes
(:func:`principal_axes`); the integration runs in principal axes and the state is reported
back in the given body frame, so callers never see the principal frame unless they ask.

Translation of the body origin (its centre of mass) is kinematic: a constant velocity, or a
smooth approach from one position to another (:class:`Translation`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from trackmeter.core.transforms import quat_derivative, quat_multiply
from trackmeter.errors import TrackmeterError

FloatArray = NDArray[np.float64]


# --------------------------------------------------------------------------- inertia


def inertia_tensor(values: ArrayLike) -> FloatArray:
    """A (3,3) inertia tensor, kg m², from 3 principal moments, 6 components or a (3,3) matrix.

    Args:
        values: ``(I1, I2, I3)`` (diagonal), ``(Ixx, Iyy, Izz, Ixy, Ixz, Iyz)`` (the tensor's
            off-diagonal *elements*, i.e. minus the products of inertia) or a (3,3) matrix.

    Raises:
        TrackmeterError: wrong size, not symmetric, not positive definite, or violating the
            triangle inequality ``Ii + Ij >= Ik`` that every physical body satisfies.
    """
    v = np.asarray(values, dtype=float)
    if v.shape == (3,):
        J = np.diag(v)
    elif v.shape == (6,):
        xx, yy, zz, xy, xz, yz = v
        J = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
    elif v.shape == (3, 3):
        J = v.copy()
    else:
        raise TrackmeterError(f"inertia must have 3, 6 or 3x3 values, got shape {v.shape}")
    if not np.all(np.isfinite(J)) or not np.allclose(J, J.T, rtol=0, atol=1e-12 * max(1.0, np.abs(J).max())):
        raise TrackmeterError("inertia tensor must be finite and symmetric")
    moments = np.linalg.eigvalsh(J)
    if moments[0] <= 0:
        raise TrackmeterError(f"inertia tensor must be positive definite, got principal moments {moments}")
    if moments[0] + moments[1] < moments[2] * (1 - 1e-12):
        raise TrackmeterError(f"principal moments {moments} violate the triangle inequality I1 + I2 >= I3")
    return J


def principal_axes(inertia: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Principal moments (ascending) and the rotation ``R_body_principal``.

    ``inertia_body = R @ diag(moments) @ R.T`` with ``R`` a proper rotation (det +1) whose
    columns are the principal axes expressed in the body frame. For an already diagonal
    tensor with ascending moments, ``R`` is the identity.

    Args:
        inertia: anything :func:`inertia_tensor` accepts.

    Returns:
        ``(moments (3,), R_body_principal (3,3))``.
    """
    J = inertia_tensor(inertia)
    moments, vecs = np.linalg.eigh(J)
    # Sign each eigenvector so the diagonal case returns exactly the identity, then make it proper.
    for k in range(3):
        if vecs[np.argmax(np.abs(vecs[:, k])), k] < 0:
            vecs[:, k] *= -1
    if np.linalg.det(vecs) < 0:
        vecs[:, 2] *= -1
    return moments, vecs


def euler_rates(omega_principal: ArrayLike, moments: ArrayLike) -> FloatArray:
    """Torque-free Euler's equations in principal axes, paper eq. 13.

    Args:
        omega_principal: (3,) or (N,3) angular velocity in principal axes, rad/s.
        moments: (3,) principal moments of inertia ``(I1, I2, I3)``, kg m².

    Returns:
        (3,) or (N,3) ``d omega / dt``, rad/s².
    """
    w = np.asarray(omega_principal, dtype=float)
    I1, I2, I3 = np.asarray(moments, dtype=float)
    w1, w2, w3 = np.moveaxis(w, -1, 0)
    return np.stack([(I2 - I3) / I1 * w2 * w3, (I3 - I1) / I2 * w3 * w1, (I1 - I2) / I3 * w1 * w2], axis=-1)


def kinetic_energy(omega_body: ArrayLike, inertia: ArrayLike) -> FloatArray:
    """Rotational kinetic energy ``1/2 w·J w``, J, for (3,) or (N,3) body-frame omega."""
    J = inertia_tensor(inertia)
    w = np.asarray(omega_body, dtype=float)
    return 0.5 * np.einsum("...i,ij,...j->...", w, J, w)


def angular_momentum_world(quat_world_body_wxyz: ArrayLike, omega_body: ArrayLike, inertia: ArrayLike) -> FloatArray:
    """Angular momentum ``L_world = R_world_body J omega_body``, kg m²/s, (3,) or (N,3).

    Constant in time for a torque-free body: the invariant the precession cones around.
    """
    J = inertia_tensor(inertia)
    L_body = np.asarray(omega_body, dtype=float) @ J.T
    return Rotation.from_quat(np.asarray(quat_world_body_wxyz, dtype=float), scalar_first=True).apply(L_body)


def symmetric_precession_rate(moments: ArrayLike, omega_symmetry_axis: float) -> float:
    """Body-frame precession rate of omega about the symmetry axis of a symmetric top, rad/s.

    For ``I1 = I2`` Euler's equations give ``(w1, w2)`` rotating at
    ``Omega = (I3 - I1) / I1 * w3`` (Goldstein eq. 5.67), counter-clockwise seen from +axis 3.
    """
    I1, I2, I3 = np.asarray(moments, dtype=float)
    if not np.isclose(I1, I2, rtol=1e-5, atol=0.0):  # relative: a small body's moments are all below isclose's atol
        raise TrackmeterError(f"not a symmetric top about axis 3: I1={I1}, I2={I2}")
    return float((I3 - I1) / I1 * omega_symmetry_axis)


# --------------------------------------------------------------------------- attitude solution


@dataclass(frozen=True, eq=False)
class FreeRotation:
    """The integrated attitude motion of a torque-free rigid body over ``[0, duration_s]``.

    Create it with :func:`integrate_free_rotation`; evaluate with :meth:`state`.

    Attributes:
        inertia: (3,3) tensor in the body frame, kg m².
        moments: (3,) principal moments, ascending, kg m².
        R_body_principal: (3,3) principal axes (columns) in the body frame.
        duration_s: end of the integrated span, s (the state is defined on [0, duration_s]).
    """

    inertia: FloatArray
    moments: FloatArray
    R_body_principal: FloatArray
    duration_s: float
    _solution: Callable[[FloatArray], FloatArray] = field(repr=False)  # solve_ivp's dense output: (N,) times to (7,N)

    def state(self, t_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Attitude and body-frame angular velocity at times ``t_s``.

        Args:
            t_s: scalar or (N,) times in ``[0, duration_s]``, s.

        Returns:
            ``(quat_world_body_wxyz, omega_body_rad_s)``: (4,), (3,) for a scalar time or
            (N,4), (N,3) for an array. Quaternions are unit (renormalised dense output).
        """
        t = np.asarray(t_s, dtype=float)
        scalar = t.ndim == 0
        t = np.atleast_1d(t)
        tol = 1e-9 * max(1.0, self.duration_s)
        if np.any(t < -tol) or np.any(t > self.duration_s + tol):
            raise TrackmeterError(f"time outside the integrated span [0, {self.duration_s}] s")
        y = np.asarray(self._solution(np.clip(t, 0.0, self.duration_s)), dtype=float).T
        q_world_principal = y[:, :4] / np.linalg.norm(y[:, :4], axis=1, keepdims=True)
        omega_principal = y[:, 4:]
        # Back to the body frame: q_world_body = q_world_principal ⊗ q_principal_body. A product
        # with a constant quaternion is linear, so the sign stays continuous in time as integrated.
        q_principal_body = Rotation.from_matrix(self.R_body_principal.T).as_quat(scalar_first=True)
        q = quat_multiply(q_world_principal, q_principal_body)
        omega_body = omega_principal @ self.R_body_principal.T
        if scalar:
            return q[0], omega_body[0]
        return q, omega_body


def integrate_free_rotation(
    inertia: ArrayLike,
    quat0_world_body_wxyz: ArrayLike,
    omega0_body_rad_s: ArrayLike,
    duration_s: float,
    rtol: float = 1e-12,
    atol: float = 1e-14,
) -> FreeRotation:
    """Integrate Euler's equations (eq. 13) with quaternion kinematics (eq. 15) over ``[0, duration_s]``.

    The state ``(q_world_principal, omega_principal)`` is integrated with DOP853 (adaptive,
    8th order) and kept as dense output. ``rtol``/``atol`` apply to the quaternion
    components (dimensionless) and to omega (rad/s).

    Args:
        inertia: body-frame inertia (see :func:`inertia_tensor`), kg m².
        quat0_world_body_wxyz: (4,) initial attitude, maps body to world.
        omega0_body_rad_s: (3,) initial angular velocity in the body frame, rad/s.
        duration_s: length of the span, s (> 0).

    Returns:
        A :class:`FreeRotation` to evaluate at any time in the span.
    """
    if not duration_s > 0:
        raise TrackmeterError(f"duration must be positive, got {duration_s}")
    J = inertia_tensor(inertia)
    moments, R_bp = principal_axes(J)
    q0 = np.asarray(quat0_world_body_wxyz, dtype=float)
    if q0.shape != (4,) or not np.all(np.isfinite(q0)) or np.linalg.norm(q0) < 1e-9:
        raise TrackmeterError(f"initial attitude must be a non-zero quaternion wxyz, got {q0}")
    w0 = np.asarray(omega0_body_rad_s, dtype=float)
    if w0.shape != (3,) or not np.all(np.isfinite(w0)):
        raise TrackmeterError(f"initial angular velocity must be 3 finite numbers, got {w0}")
    r_world_body = Rotation.from_quat(q0 / np.linalg.norm(q0), scalar_first=True)
    q0_wp = (r_world_body * Rotation.from_matrix(R_bp)).as_quat(scalar_first=True)
    w0_p = R_bp.T @ w0

    def rhs(_t: float, y: FloatArray) -> FloatArray:
        q, w = y[:4], y[4:]
        # The quaternion is renormalised in the kinematics so rounding cannot make it drift.
        return np.concatenate([quat_derivative(q / np.linalg.norm(q), w), euler_rates(w, moments)])

    sol = solve_ivp(rhs, (0.0, float(duration_s)), np.concatenate([q0_wp, w0_p]), method="DOP853",
                    rtol=rtol, atol=atol, dense_output=True)
    if not sol.success:  # pragma: no cover - DOP853 does not fail on this smooth system
        raise TrackmeterError(f"rigid-body integration failed: {sol.message}")
    return FreeRotation(J, moments, R_bp, float(duration_s), sol.sol)


# --------------------------------------------------------------------------- translation


@dataclass(frozen=True, eq=False)
class Translation:
    """Position of the body origin (centre of mass) in the camera frame over time.

    Constant velocity ``p(t) = start + velocity t``, or, when ``end_m`` is given, a smooth
    approach from ``start_m`` to ``end_m`` over ``approach_s`` seconds with a quintic
    (minimum-jerk) profile ``s(x) = 10x³ - 15x⁴ + 6x⁵``: zero velocity and acceleration at
    both ends, then holding ``end_m``. ``velocity_m_s`` is added in both cases.

    Attributes:
        start_m: (3,) position at t = 0, m.
        velocity_m_s: (3,) constant drift velocity, m/s.
        end_m: (3,) approach target, m, or None.
        approach_s: duration of the approach, s.
    """

    start_m: FloatArray
    velocity_m_s: FloatArray = field(default_factory=lambda: np.zeros(3))
    end_m: FloatArray | None = None
    approach_s: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "start_m", np.asarray(self.start_m, dtype=float).reshape(3))
        object.__setattr__(self, "velocity_m_s", np.asarray(self.velocity_m_s, dtype=float).reshape(3))
        if self.end_m is not None:
            object.__setattr__(self, "end_m", np.asarray(self.end_m, dtype=float).reshape(3))
            if not self.approach_s > 0:
                raise TrackmeterError(f"an approach needs a positive duration, got {self.approach_s}")

    def at(self, t_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """``(position_m, velocity_m_s)`` of the body origin at ``t_s``: (3,) each, or (N,3)."""
        t = np.asarray(t_s, dtype=float)
        scalar = t.ndim == 0
        t = np.atleast_1d(t)[:, None]
        p = self.start_m + self.velocity_m_s * t
        v = np.broadcast_to(self.velocity_m_s, p.shape).copy()
        if self.end_m is not None:
            x = np.clip(t / self.approach_s, 0.0, 1.0)
            s = x**3 * (10 - 15 * x + 6 * x**2)
            ds = 30 * x**2 * (1 - x) ** 2 / self.approach_s
            d = self.end_m - self.start_m
            p = p + s * d
            v = v + ds * d
        if scalar:
            return p[0], v[0]
        return p, v


# --------------------------------------------------------------------------- coasting


def torque_free_accel_bound(omega_body: ArrayLike) -> float:
    """Largest angular acceleration, rad/s², any torque-free rigid body can have at ``omega_body``.

    Euler's equations in principal axes give ``|dw_i/dt| = |(I_j - I_k) / I_i| |w_j w_k|`` and
    every physical body has ``|I_j - I_k| <= I_i`` (triangle inequality of the moments), so
    ``|dw_i/dt| <= |w_j w_k|`` and ``|dw/dt|² <= w1²w2² + w2²w3² + w3²w1² <= |w|⁴ / 3``:
    ``|dw/dt| <= |w|² / sqrt(3)``, whatever the (unknown) inertia, in any body frame (the norm
    does not depend on the axes).
    """
    w = np.asarray(omega_body, dtype=float).reshape(3)
    return float(w @ w) / np.sqrt(3.0)


@dataclass(frozen=True)
class CentreOfMassFit:
    """Result of :func:`fit_centre_of_mass`.

    Attributes:
        c_body: (3,) the centre of mass in the body frame, m.
        a_cam: (3,) the centre of mass in the camera frame at the newest pose, m.
        v_cam: (3,) its velocity in the camera frame, m/s.
        cov: (9,9) covariance of ``(c_body, a_cam, v_cam)``, inflated by the fit's residual
            scale when the residuals exceed the pose covariances.
        rss: the weighted residual ``sum_k w_k |p_k + R_k c - a - v tau_k|²`` (the given
            position weights), m² times the weights' unit.
        residual_dof: the residual's degrees of freedom, ``3N - 2 tr(S) + tr(S²)`` with ``S =
            (H + prior)^-1 H`` the fit's hat matrix in the unknowns: where the position weights
            are the poses' inverse variances, ``rss`` averages ``residual_dof``. It is
            ``3N - 9`` only where every unknown is fixed by the poses; the prior holds ``c``'s
            component along a fixed spin axis (never seen) and, over a short turn, part of the
            rest, so it is about ``3N - 8`` for a steady spin and up to ``3N - 6``.
            (``cov``'s residual scale counts ``3N - 9``, a little pessimistic.)
    """

    c_body: FloatArray
    a_cam: FloatArray
    v_cam: FloatArray
    cov: FloatArray
    rss: float = float("nan")
    residual_dof: float = float("nan")

    @property
    def speed_bound_m_s(self) -> float:
        """``|v_cam|`` plus 3 sigma of it (the largest eigenvalue of its covariance), m/s."""
        return float(np.linalg.norm(self.v_cam) + 3.0 * np.sqrt(max(np.linalg.eigvalsh(self.cov[6:, 6:]).max(), 0.0)))


def fit_centre_of_mass(
    times_s: ArrayLike, R_cam_body: ArrayLike, p_cam: ArrayLike, position_weights: ArrayLike, lever_m: float
) -> CentreOfMassFit | None:
    """The point of the body that moves in a straight line, from a window of poses.

    A free body's centre of mass drifts at constant velocity (over seconds, relative orbital
    motion is negligible) while the body turns about it: with ``c`` its body coordinates,
    ``p_k + R_k c = a + v tau_k`` (``tau_k = t_k - t_newest``) for every pose ``(R_k, p_k)`` of
    the body origin. Linear in ``x = (c, a, v)`` (9,): weighted least squares with each pose's
    position weight (inverse variance, :func:`trackmeter.core.velocity.block_weights`) and the
    prior ``c ~ N(0, lever_m² I)`` (the origin lies within ``lever_m`` of the centre of mass),
    which keeps the component of ``c`` along a fixed spin axis — invisible to the poses — at 0.
    The velocity ``v`` and the off-axis ``c`` are told apart only by the curvature of the origin's
    path (a turn of a few tens of degrees): over a short window ``cov`` says how poorly.

    Args:
        times_s: (N,) increasing, s; R_cam_body: (N,3,3); p_cam: (N,3) origin, m.
        position_weights: (N,) inverse position variances, 1/m² (0 or NaN: pose left out).
        lever_m: prior 1-sigma of each coordinate of ``c``, m; 0: the origin is the centre of
            mass (``c`` = 0, its covariance rows 0).

    Returns:
        The fit, or None with fewer than 3 weighted poses.
    """
    t = np.asarray(times_s, dtype=float).reshape(-1)
    R = np.asarray(R_cam_body, dtype=float).reshape(-1, 3, 3)
    P = np.asarray(p_cam, dtype=float).reshape(-1, 3)
    w = np.asarray(position_weights, dtype=float).reshape(-1)
    use = np.isfinite(w) & (w > 0) & np.all(np.isfinite(P), axis=1)
    if use.sum() < 3:
        return None
    t, R, P, w = t[use], R[use], P[use], w[use]
    tau = t - t[-1]
    n = len(t)
    eye = np.broadcast_to(np.eye(3), (n, 3, 3))
    A = np.concatenate([R, -eye, -tau[:, None, None] * eye], axis=2)  # (n,3,9): R_k c - a - v tau_k = -p_k
    b = -P
    w_n = w / w.max()  # the solution does not depend on the weights' scale; the covariance does
    H = np.einsum("n,nij,nik->jk", w_n, A, A)
    g = np.einsum("n,nij,ni->j", w_n, A, b)
    # A lever of 0 puts the centre of mass at the origin: c is fixed at 0 and left out of the
    # unknowns (a prior of zero width would divide by zero).
    free = slice(0, 9) if lever_m > 0 else slice(3, 9)
    prior = np.zeros((9, 9))
    if lever_m > 0:
        prior[:3, :3] = np.eye(3) / (lever_m**2 * w.max())
    x = np.zeros(9)
    x[free] = np.linalg.solve((H + prior)[free, free], g[free])
    r = np.einsum("nij,j->ni", A, x) - b
    dof = 3 * n - (free.stop - free.start)
    scale2 = float(np.einsum("n,ni,ni->", w, r, r)) / dof if dof > 0 else 1.0
    cov = np.zeros((9, 9))
    cov[free, free] = np.linalg.inv((H + prior)[free, free]) / w.max() * max(1.0, scale2)
    rss = float(np.einsum("n,ni,ni->", w, r, r))
    S = np.linalg.solve((H + prior)[free, free], H[free, free])  # hat matrix in the unknowns
    residual_dof = 3 * n - 2.0 * float(np.trace(S)) + float(np.trace(S @ S))
    return CentreOfMassFit(x[:3], x[3:6], x[6:], 0.5 * (cov + cov.T), rss, residual_dof)


def coast_pose(
    R0: ArrayLike,
    p0: ArrayLike,
    cov0: ArrayLike,
    v_cam: ArrayLike,
    omega_body: ArrayLike,
    dt_s: float,
    velocity_sigma_m_s: float,
    omega_sigma_rad_s: float,
    lever_m: float,
    com_speed_m_s: float | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Carry a pose ``dt_s`` forward on the constant-twist motion model, with its covariance.

    Motion (the screw the velocity estimator fits, :func:`trackmeter.core.velocity.screw_rates`):
    the body twist ``(v_b, omega_b)`` with ``v_b = R0^T v_cam`` stays constant, so
    ``T(dt) = T0 exp(dt (v_b, omega_b))`` (:func:`trackmeter.core.velocity.se3_exp`) and the
    origin's velocity is ``v_cam(dt) = R(dt) v_b``.

    Covariance of ``(position m, rotation vector rad)`` in the camera frame (left-multiplied
    error, ``R = exp(dtheta) R_hat``, the pose covariance convention of
    :func:`trackmeter.core.pose.solve_pose`). The model's unknowns are constant over the coast:
    a rate error ``d_omega`` (``omega_sigma_rad_s`` per axis), an origin-velocity error ``d_v``
    (``velocity_sigma_m_s`` per axis) and the angular acceleration the constant-twist model
    ignores, bounded for a torque-free body by :func:`torque_free_accel_bound`
    (``sigma_alpha = |omega|² / 3`` per axis, so that the 3-vector's RMS equals the bound).
    To first order ``dtheta(dt) = dtheta0 + dt R d_omega + dt²/2 R alpha`` and the origin, at most
    ``lever_m`` from the centre of mass the body turns about, moves by ``dt d_v`` plus up to
    ``lever_m`` times the attitude error grown since ``dt = 0``. A centre of mass moving in a
    straight line is a constant body twist only when its velocity is along the spin axis; the
    screw bends its path by at most ``|v_c| |omega| dt² / 2`` (``|v_c| <= |v| + |omega| lever``),
    added as one more term. Taking the unknowns independent of each other and of the starting
    pose (its rates come from a window of earlier poses), with isotropic sigmas
    (``R sigma² I R^T = sigma² I``)::

        cov(dt) = cov0 + diag(a I3, b I3)
        b = sigma_omega² dt² + sigma_alpha² dt⁴ / 4
        a = sigma_v² dt² + lever² b + ((|v| + |omega| lever) |omega| dt² / 2)²

    The position error the attitude error causes through the lever is correlated with it, with
    a sign that depends on where the (unknown) centre of mass lies: the cross-covariance is left
    out, so each block bounds its own errors (``tests/test_coasting.py``), not their joint.

    Args:
        R0: (3,3) ``R_cam_body`` at the start; p0: (3,) origin, m; cov0: (6,6) its covariance.
        v_cam: (3,) origin velocity in the camera frame, m/s; omega_body: (3,) rad/s.
        dt_s: time carried forward, s (>= 0).
        velocity_sigma_m_s, omega_sigma_rad_s: 1-sigma errors of the rates, per axis.
        lever_m: largest distance of the body origin from the centre of mass, m.
        com_speed_m_s: a bound on the centre of mass's speed when one is known (e.g.
            :attr:`CentreOfMassFit.speed_bound_m_s`), m/s; it replaces ``|v| + |omega| lever``
            where smaller.

    Returns:
        ``(R (3,3), p (3,), v_cam (3,) at dt, cov (6,6))``.
    """
    from trackmeter.core.velocity import se3_exp

    R0 = np.asarray(R0, dtype=float)
    p0 = np.asarray(p0, dtype=float).reshape(3)
    w = np.asarray(omega_body, dtype=float).reshape(3)
    v_b = R0.T @ np.asarray(v_cam, dtype=float).reshape(3)
    dt = float(dt_s)
    dR, dp = se3_exp(dt * np.concatenate([v_b, w]))
    R = R0 @ dR
    sigma_alpha = float(w @ w) / 3.0
    b = omega_sigma_rad_s**2 * dt**2 + sigma_alpha**2 * dt**4 / 4.0
    speed_com = float(np.linalg.norm(v_b)) + float(np.linalg.norm(w)) * lever_m  # bound on |v| of the centre of mass
    if com_speed_m_s is not None and np.isfinite(com_speed_m_s):
        speed_com = min(speed_com, float(com_speed_m_s))
    bend = speed_com * float(np.linalg.norm(w)) * dt**2 / 2.0
    a = velocity_sigma_m_s**2 * dt**2 + lever_m**2 * b + bend**2
    cov = np.asarray(cov0, dtype=float) + np.diag([a, a, a, b, b, b])
    return R, p0 + R0 @ dp, R @ v_b, cov
