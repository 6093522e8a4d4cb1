"""Free rigid-body dynamics (paper eqs. 13, 15) against conservation laws and closed forms."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from trackmeter.core.dynamics import (
    Translation,
    angular_momentum_world,
    euler_rates,
    inertia_tensor,
    integrate_free_rotation,
    kinetic_energy,
    principal_axes,
    symmetric_precession_rate,
)
from trackmeter.core.transforms import omega_body_between
from trackmeter.errors import TrackmeterError

DEG = np.pi / 180.0
# An asymmetric body (kg m²) like a box bus with solar wings, given with products of inertia so
# the reduction to principal axes is exercised.
INERTIA_6 = (420.0, 610.0, 780.0, 25.0, -12.0, 30.0)


def _tumble_10deg():
    omega0 = np.array([0.6, -0.5, 0.62])
    omega0 *= 10 * DEG / np.linalg.norm(omega0)
    q0 = Rotation.from_rotvec([0.3, -0.2, 0.9]).as_quat(scalar_first=True)
    return integrate_free_rotation(INERTIA_6, q0, omega0, 600.0)


def test_energy_and_momentum_conserved_over_ten_minutes():
    motion = _tumble_10deg()
    t = np.linspace(0.0, 600.0, 6001)
    q, w = motion.state(t)
    E = kinetic_energy(w, INERTIA_6)
    L = angular_momentum_world(q, w, INERTIA_6)
    L_norm = np.linalg.norm(L, axis=1)
    energy_drift = np.max(np.abs(E / E[0] - 1.0))
    momentum_drift = np.max(np.abs(L_norm / L_norm[0] - 1.0))
    # World-frame angular momentum VECTOR is constant too (attitude integration, not only omega).
    vector_drift = np.max(np.linalg.norm(L - L[0], axis=1)) / L_norm[0]
    print(f"\nenergy drift {energy_drift:.2e}, |L| drift {momentum_drift:.2e}, L_world drift {vector_drift:.2e}")
    assert energy_drift < 1e-9
    assert momentum_drift < 1e-9
    assert vector_drift < 1e-9
    assert np.allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-15 * 10)
    # The body really tumbles (omega changes direction in the body): not a trivial pass.
    assert np.max(np.linalg.norm(w - w[0], axis=1)) > 0.1 * np.linalg.norm(w[0])


def test_quaternion_follows_omega_eq15():
    """The finite-difference body rate of the attitude (eq. 14) equals the integrated omega."""
    motion = _tumble_10deg()
    t = np.linspace(10.0, 20.0, 11)
    dt = 1e-4
    q0, w0 = motion.state(t - dt)
    q1, w1 = motion.state(t + dt)
    _, w = motion.state(t)
    w_fd = np.array([omega_body_between(a, b, 2 * dt) for a, b in zip(q0, q1)])
    assert np.max(np.abs(w_fd - w)) < 1e-8


def test_symmetric_top_precession_rate_matches_closed_form():
    moments = (500.0, 500.0, 800.0)
    w3 = 4 * DEG
    omega0 = np.array([1.5 * DEG, 0.0, w3])
    motion = integrate_free_rotation(moments, [1, 0, 0, 0], omega0, 120.0)
    t = np.linspace(0.0, 120.0, 2401)
    _, w = motion.state(t)
    angle = np.unwrap(np.arctan2(w[:, 1], w[:, 0]))
    fitted = np.polyfit(t, angle, 1)[0]
    expected = symmetric_precession_rate(moments, w3)
    rel = abs(fitted / expected - 1)
    print(f"\nprecession rate fitted {fitted:.12f} rad/s, closed form {expected:.12f}, rel error {rel:.1e}")
    assert rel < 1e-9
    # w3 and the transverse magnitude are constant for a symmetric top.
    assert np.max(np.abs(w[:, 2] - w3)) < 1e-12
    assert np.ptp(np.hypot(w[:, 0], w[:, 1])) < 1e-12


def test_symmetric_top_with_general_tensor_in_rotated_body_frame():
    """The same top given by its tensor in a rotated body frame: rate unchanged, reported in body."""
    moments = np.array([500.0, 500.0, 800.0])
    R_bp = Rotation.from_rotvec([0.4, -0.3, 0.2]).as_matrix()
    J_body = R_bp @ np.diag(moments) @ R_bp.T
    w3 = 3 * DEG
    omega0_body = R_bp @ np.array([1.0 * DEG, 0.5 * DEG, w3])
    motion = integrate_free_rotation(J_body, [1, 0, 0, 0], omega0_body, 60.0)
    t = np.linspace(0.0, 60.0, 1201)
    q, w_body = motion.state(t)
    symmetry_axis_body = R_bp[:, 2]
    assert np.allclose(w_body @ symmetry_axis_body, w3, atol=1e-12)
    E = kinetic_energy(w_body, J_body)
    assert np.max(np.abs(E / E[0] - 1)) < 1e-10
    w_p = w_body @ R_bp  # back to the principal frame to fit the rate
    angle = np.unwrap(np.arctan2(w_p[:, 1], w_p[:, 0]))
    assert abs(np.polyfit(t, angle, 1)[0] / symmetric_precession_rate(moments, w3) - 1) < 1e-8


def test_intermediate_axis_unstable_major_axis_stable():
    moments = (300.0, 500.0, 800.0)
    eps = 1e-3
    spin = 10 * DEG
    # Spin about the intermediate axis (2) with a tiny perturbation: it flips (tennis-racket).
    inter = integrate_free_rotation(moments, [1, 0, 0, 0], [eps * spin, spin, eps * spin], 600.0)
    _, w = inter.state(np.linspace(0, 600, 6001))
    off_axis = np.hypot(w[:, 0], w[:, 2]) / spin
    assert off_axis.max() > 0.5  # grew by more than 500x
    assert w[:, 1].min() < 0  # the spin axis turned over
    # About the major axis (3) the same perturbation stays small; also about the minor axis (1).
    for axis in (2, 0):
        w0 = np.full(3, eps * spin)
        w0[axis] = spin
        stable = integrate_free_rotation(moments, [1, 0, 0, 0], w0, 600.0)
        _, w = stable.state(np.linspace(0, 600, 6001))
        off = np.linalg.norm(np.delete(w, axis, axis=1), axis=1) / spin
        assert off.max() < 5 * eps


def test_euler_rates_match_goldstein():
    moments = np.array([2.0, 3.0, 5.0])
    w = np.array([0.1, -0.2, 0.3])
    # I dw/dt = (I w) x w for torque-free motion (Goldstein 5.39 in vector form).
    expected = np.cross(moments * w, w) / moments
    assert np.allclose(euler_rates(w, moments), expected, rtol=1e-14)


def test_principal_axes_reconstructs_tensor():
    J = inertia_tensor(INERTIA_6)
    moments, R = principal_axes(J)
    assert np.all(np.diff(moments) > 0)
    assert np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(R @ np.diag(moments) @ R.T, J, atol=1e-10)
    _, R_diag = principal_axes((1.0, 2.0, 3.0))
    assert np.allclose(R_diag, np.eye(3))


@pytest.mark.parametrize("bad", [(1.0, 2.0), (1.0, 1.0, 5.0), (-1.0, 2.0, 2.0), (1.0, 2.0, 3.0, 0.0, 5.0, 0.0)])
def test_bad_inertia_refused(bad):
    with pytest.raises(TrackmeterError):
        inertia_tensor(bad)


def test_state_outside_span_refused():
    motion = integrate_free_rotation((1, 2, 2.5), [1, 0, 0, 0], [0.1, 0, 0], 10.0)
    with pytest.raises(TrackmeterError):
        motion.state(11.0)


def test_translation_constant_velocity_and_approach():
    lin = Translation([0.1, 0.0, 3.5], [0.01, 0.0, -0.02])
    p, v = lin.at(2.0)
    assert np.allclose(p, [0.12, 0.0, 3.46]) and np.allclose(v, [0.01, 0, -0.02])
    app = Translation([0.0, 0.0, 10.0], end_m=[0.0, 0.0, 2.0], approach_s=40.0)
    t = np.linspace(0, 50, 5001)
    p, v = app.at(t)
    assert np.allclose(p[0], [0, 0, 10]) and np.allclose(p[-1], [0, 0, 2])
    assert np.allclose(v[0], 0) and np.allclose(v[-1], 0)
    # The velocity is the derivative of the position (central differences).
    fd = np.gradient(p[:, 2], t)
    assert np.max(np.abs(fd[1:-1] - v[1:-1, 2])) < 1e-4
    assert np.all(np.diff(p[:, 2]) <= 0)


@pytest.mark.parametrize("inertia", [(2.0, 1.0, 3.0), "rotated"])
def test_principal_axes_are_a_proper_rotation_for_unordered_or_rotated_moments(inertia: tuple | str) -> None:
    """An unordered diagonal (2, 1, 3) sorts its eigenvectors into a permutation of det -1, and
    eigh's signs make half of all full tensors improper: principal_axes must return a proper
    rotation (det +1) with ``R diag(m) R^T = J`` (its docstring), and the free-rotation
    integrator built on it must conserve kinetic energy and the world angular momentum
    (Goldstein ch. 5) for such a tensor."""
    if inertia == "rotated":
        Q = Rotation.random(random_state=5).as_matrix()  # eigh's sign-fixed axes come out improper here
        J = Q @ np.diag([2.0, 1.0, 2.5]) @ Q.T
    else:
        J = np.diag(inertia)
    moments, R = principal_axes(J)
    np.testing.assert_allclose(moments, np.sort(np.linalg.eigvalsh(J)), rtol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R @ np.diag(moments) @ R.T, J, atol=1e-12)

    q0 = Rotation.from_rotvec([0.3, -0.2, 0.9]).as_quat(scalar_first=True)
    motion = integrate_free_rotation(J, q0, np.array([0.2, -0.15, 0.1]), 30.0)
    q, w = motion.state(np.linspace(0.0, 30.0, 301))
    E = kinetic_energy(w, J)
    L = angular_momentum_world(q, w, J)
    assert np.max(np.abs(E / E[0] - 1.0)) < 1e-9
    assert np.max(np.linalg.norm(L - L[0], axis=1)) < 1e-9 * np.linalg.norm(L[0])
    # The attitude comes back through the principal frame unchanged at t = 0 (q and -q alike).
    np.testing.assert_allclose(Rotation.from_quat(motion.state(0.0)[0], scalar_first=True).as_matrix(),
                               Rotation.from_quat(q0, scalar_first=True).as_matrix(), atol=1e-12)


def test_a_small_body_s_unequal_moments_are_not_a_symmetric_top() -> None:
    # isclose's absolute tolerance (1e-8 kg m^2) took any two moments of a small body as equal
    symmetric_precession_rate([2e-9, 2e-9, 6e-9], 10.0)  # equal: a top
    with pytest.raises(TrackmeterError, match="not a symmetric top"):
        symmetric_precession_rate([1e-9, 5e-9, 6e-9], 10.0)
