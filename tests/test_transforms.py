"""Rotations, rigid transforms and the paper's eqs. 14-17 (trackmeter.core.transforms).

References: scipy's Rotation (scalar-first), numerical derivatives, closed forms.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from trackmeter.core import transforms as tf
from trackmeter.errors import TrackmeterError

finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
quats = arrays(np.float64, 4, elements=finite).filter(lambda q: np.linalg.norm(q) > 0.1).map(lambda q: q / np.linalg.norm(q))
rotvecs = arrays(np.float64, 3, elements=st.floats(-3.0, 3.0, allow_nan=False))
vectors = arrays(np.float64, 3, elements=st.floats(-10.0, 10.0, allow_nan=False))


def random_quats(n: int, seed: int = 0) -> np.ndarray:
    return Rotation.random(n, rng=np.random.default_rng(seed)).as_quat(scalar_first=True)


# --------------------------------------------------------------------------- quaternion <-> matrix


def test_quat_matrix_match_scipy() -> None:
    q = random_quats(50)
    np.testing.assert_allclose(tf.quat_wxyz_to_matrix(q), Rotation.from_quat(q, scalar_first=True).as_matrix(), atol=1e-14)
    # scalar-first: the quaternion (cos a/2, 0, 0, sin a/2) is a rotation about z
    a = 0.3
    Rz = tf.quat_wxyz_to_matrix([np.cos(a / 2), 0, 0, np.sin(a / 2)])
    np.testing.assert_allclose(Rz, [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]], atol=1e-15)


def test_matrix_to_quat_is_canonical() -> None:
    q = random_quats(50, 1)
    back = tf.matrix_to_quat_wxyz(tf.quat_wxyz_to_matrix(q))
    assert np.all(back[:, 0] >= 0)
    np.testing.assert_allclose(back, q * np.sign(q[:, :1]), atol=1e-12)


def test_rotation_from_matrix_is_scipys_conversion_bit_for_bit() -> None:
    """The cheaper validity check must give exactly scipy's numbers: on products of rotations
    (what the pipeline converts), on matrices drifted from SO(3) on both sides of scipy's 1e-12
    orthogonality tolerance (scipy projects those by SVD), singly and stacked."""
    rng = np.random.default_rng(7)
    A = Rotation.random(400, rng=8).as_matrix()
    products = A[:200] @ A[200:]
    drift = np.logspace(-16, -9, 200)[:, None, None] * rng.normal(size=(200, 3, 3))
    for M in (products, A[:200] + drift):
        for m in M:
            np.testing.assert_array_equal(tf.rotation_from_matrix(m).as_quat(), Rotation.from_matrix(m).as_quat())
        for k in range(0, 200, 5):
            np.testing.assert_array_equal(tf.rotation_from_matrix(M[k:k + 5]).as_rotvec(),
                                          Rotation.from_matrix(M[k:k + 5]).as_rotvec())
    # a reflection or NaN still goes through scipy's checks and fails as there
    with pytest.raises(ValueError):
        tf.rotation_from_matrix(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(np.linalg.LinAlgError), np.errstate(invalid="ignore"):  # det of NaN: expected
        tf.rotation_from_matrix(np.full((3, 3), np.nan))


@settings(max_examples=100, deadline=None)
@given(quats)
def test_property_quat_matrix_round_trip(q: np.ndarray) -> None:
    back = tf.matrix_to_quat_wxyz(tf.quat_wxyz_to_matrix(q))
    assert abs(abs(back @ q) - 1.0) < 1e-9  # same attitude up to sign


@settings(max_examples=100, deadline=None)
@given(rotvecs)
def test_property_exp_log_round_trip(rv: np.ndarray) -> None:
    """exp (rotation vector → rotation) then log recovers the vector inside the ball |v| < pi."""
    angle = np.linalg.norm(rv)
    if angle > np.pi - 1e-6:
        rv = rv * (np.pi - 1e-3) / angle
    q = Rotation.from_rotvec(rv).as_quat(scalar_first=True)
    R = tf.quat_wxyz_to_matrix(q)
    back = Rotation.from_quat(tf.matrix_to_quat_wxyz(R), scalar_first=True).as_rotvec()
    np.testing.assert_allclose(back, rv, atol=1e-9)


def test_quat_multiply_matches_scipy_composition() -> None:
    q1, q2 = random_quats(20, 2), random_quats(20, 3)
    expected = (Rotation.from_quat(q1, scalar_first=True) * Rotation.from_quat(q2, scalar_first=True)).as_quat(
        scalar_first=True
    )
    prod = tf.quat_multiply(q1, q2)
    np.testing.assert_allclose(prod * np.sign(prod[:, :1] * expected[:, :1]), expected, atol=1e-12)
    np.testing.assert_allclose(tf.quat_multiply(q1, tf.quat_conjugate(q1)), np.tile([1.0, 0, 0, 0], (20, 1)), atol=1e-12)


# --------------------------------------------------------------------------- eqs. 14-15


def _rotating(q0: np.ndarray, omega_body: np.ndarray, t: float) -> np.ndarray:
    """Attitude at t under a constant body-frame rate: q(t) = q0 ⊗ exp(omega t)."""
    r = Rotation.from_quat(q0, scalar_first=True) * Rotation.from_rotvec(omega_body * t)
    return r.as_quat(scalar_first=True)


def _continuous(q: np.ndarray, ref: np.ndarray) -> np.ndarray:
    return q if q @ ref >= 0 else -q


def test_eq15_quat_derivative_matches_numerical_derivative() -> None:
    rng = np.random.default_rng(4)
    for q0 in random_quats(10, 5):
        omega = rng.normal(0, 1.0, 3)
        h = 1e-6
        qp = _continuous(_rotating(q0, omega, h), q0)
        qm = _continuous(_rotating(q0, omega, -h), q0)
        numeric = (qp - qm) / (2 * h)
        np.testing.assert_allclose(tf.quat_derivative(q0, omega), numeric, atol=1e-8)


def test_eq14_is_the_inverse_of_eq15() -> None:
    q = random_quats(30, 6)
    omega = np.random.default_rng(7).normal(0, 2.0, (30, 3))
    np.testing.assert_allclose(tf.omega_body_from_quat_rate(q, tf.quat_derivative(q, omega)), omega, atol=1e-12)
    # the rate of a unit quaternion is orthogonal to it (|q| stays 1)
    np.testing.assert_allclose(np.sum(q * tf.quat_derivative(q, omega), axis=1), 0.0, atol=1e-12)


def test_eq14_from_numerical_rate() -> None:
    q0 = random_quats(1, 8)[0]
    omega = np.array([0.3, -0.7, 1.1])
    h = 1e-6
    rate = (_continuous(_rotating(q0, omega, h), q0) - _continuous(_rotating(q0, omega, -h), q0)) / (2 * h)
    np.testing.assert_allclose(tf.omega_body_from_quat_rate(q0, rate), omega, atol=1e-7)


def test_omega_body_between_constant_rate() -> None:
    q0 = random_quats(1, 9)[0]
    omega = np.array([0.2, -0.5, 0.9])
    dt = 0.4
    q1 = _rotating(q0, omega, dt)
    np.testing.assert_allclose(tf.omega_body_between(q0, q1, dt), omega, atol=1e-12)
    np.testing.assert_allclose(tf.omega_body_between(-q0, q1, dt), omega, atol=1e-12)
    np.testing.assert_allclose(tf.omega_body_between(q0, -q1, dt), omega, atol=1e-12)
    with pytest.raises(TrackmeterError):
        tf.omega_body_between(q0, q1, 0.0)


def test_omega_body_is_in_the_body_frame() -> None:
    """A rotation about the body's x axis, with the body turned 90 deg about world z,
    is a rotation about world y: omega_body stays (w, 0, 0)."""
    q0 = Rotation.from_euler("z", 90, degrees=True).as_quat(scalar_first=True)
    q1 = (Rotation.from_quat(q0, scalar_first=True) * Rotation.from_euler("x", 10, degrees=True)).as_quat(scalar_first=True)
    np.testing.assert_allclose(tf.omega_body_between(q0, q1, 1.0), [np.radians(10), 0, 0], atol=1e-12)
    world = Rotation.from_quat(q1, scalar_first=True) * Rotation.from_quat(q0, scalar_first=True).inv()
    np.testing.assert_allclose(world.as_rotvec(), [0, np.radians(10), 0], atol=1e-12)


# --------------------------------------------------------------------------- eqs. 16-17


def test_attitude_error_known_rotation() -> None:
    q_true = random_quats(1, 10)[0]
    err_cam = np.array([0.01, -0.02, 0.005])
    q_est = (Rotation.from_rotvec(err_cam) * Rotation.from_quat(q_true, scalar_first=True)).as_quat(scalar_first=True)
    np.testing.assert_allclose(tf.attitude_error_components(q_est, q_true), err_cam, atol=1e-14)
    assert tf.attitude_error_angle(q_est, q_true) == pytest.approx(np.linalg.norm(err_cam), abs=1e-14)


def test_attitude_error_closed_form_and_sign_insensitive() -> None:
    q_est, q_true = random_quats(40, 11), random_quats(40, 12)
    angle = tf.attitude_error_angle(q_est, q_true)
    closed = 2 * np.arccos(np.clip(np.abs(np.sum(q_est * q_true, axis=1)), 0, 1))
    np.testing.assert_allclose(angle, closed, atol=1e-7)
    np.testing.assert_allclose(tf.attitude_error_angle(-q_est, q_true), angle, atol=1e-12)
    np.testing.assert_allclose(tf.attitude_error_components(q_est, -q_true), tf.attitude_error_components(q_est, q_true), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(tf.attitude_error_components(q_est, q_true), axis=1), angle, atol=1e-15)


def test_attitude_error_small_angles_keep_precision() -> None:
    q_true = np.array([1.0, 0, 0, 0])
    q_est = Rotation.from_rotvec([1e-9, 0, 0]).as_quat(scalar_first=True)
    assert tf.attitude_error_angle(q_est, q_true) == pytest.approx(1e-9, rel=1e-6)


def test_attitude_error_180_degrees() -> None:
    q_true = random_quats(1, 13)[0]
    q_est = (Rotation.from_rotvec([0, np.pi, 0]) * Rotation.from_quat(q_true, scalar_first=True)).as_quat(scalar_first=True)
    assert tf.attitude_error_angle(q_est, q_true) == pytest.approx(np.pi, abs=1e-7)
    comp = tf.attitude_error_components(q_est, q_true)
    assert abs(abs(comp[1]) - np.pi) < 1e-7 and np.allclose(comp[[0, 2]], 0, atol=1e-7)
    assert tf.attitude_error_angle(q_true, q_true) == pytest.approx(0.0, abs=1e-15)


# --------------------------------------------------------------------------- rigid transforms


@settings(max_examples=50, deadline=None)
@given(quats, vectors, arrays(np.float64, (5, 3), elements=st.floats(-10, 10, allow_nan=False)))
def test_property_invert_apply_round_trip(q: np.ndarray, t: np.ndarray, points: np.ndarray) -> None:
    T = tf.transform_from_pose(t, q)
    p_a = tf.apply_transform(T, points)
    np.testing.assert_allclose(tf.apply_transform(tf.invert_transform(T), p_a), points, atol=1e-9)
    np.testing.assert_allclose(tf.invert_transform(T), np.linalg.inv(T), atol=1e-9)


def test_transform_chain_cancels() -> None:
    q = random_quats(2, 14)
    T_a_b = tf.transform_from_pose([1, 2, 3], q[0])
    T_b_c = tf.transform_from_pose([-1, 0.5, 2], q[1])
    p_c = np.array([[0.1, 0.2, 0.3]])
    np.testing.assert_allclose(tf.apply_transform(T_a_b @ T_b_c, p_c), tf.apply_transform(T_a_b, tf.apply_transform(T_b_c, p_c)), atol=1e-12)
    # position is the origin of b in a
    np.testing.assert_allclose(tf.apply_transform(T_a_b, np.zeros(3)), [1, 2, 3])


# --------------------------------------------------------------------------- absolute orientation


def test_absolute_orientation_recovers_exact_transform() -> None:
    rng = np.random.default_rng(15)
    for seed in range(5):
        R = Rotation.random(rng=rng).as_matrix()
        t = rng.normal(0, 2, 3)
        b = rng.normal(0, 1, (6, 3))
        a = b @ R.T + t
        R_est, t_est = tf.absolute_orientation(a, b)
        np.testing.assert_allclose(R_est, R, atol=1e-12)
        np.testing.assert_allclose(t_est, t, atol=1e-12)


def test_weighted_absolute_orientation_matches_scipy_align_vectors() -> None:
    rng = np.random.default_rng(16)
    R = Rotation.random(rng=rng)
    b = rng.normal(0, 1, (10, 3))
    a = R.apply(b) + np.array([0.5, -1, 3]) + rng.normal(0, 0.05, (10, 3))
    w = rng.uniform(0.1, 3.0, 10)
    R_est, t_est = tf.absolute_orientation(a, b, w)
    ca, cb = w @ a / w.sum(), w @ b / w.sum()
    ref, _ = Rotation.align_vectors(a - ca, b - cb, weights=w)
    np.testing.assert_allclose(R_est, ref.as_matrix(), atol=1e-10)
    np.testing.assert_allclose(t_est, ca - ref.apply(cb), atol=1e-10)
    # weights matter: unweighted differs on noisy data
    R_unw, _ = tf.absolute_orientation(a, b)
    assert not np.allclose(R_unw, R_est, atol=1e-6)


def test_zero_weights_ignore_points() -> None:
    rng = np.random.default_rng(17)
    R = Rotation.random(rng=rng).as_matrix()
    b = rng.normal(0, 1, (5, 3))
    a = b @ R.T
    a[4] += 100.0  # a wild outlier with zero weight
    R_est, t_est = tf.absolute_orientation(a, b, np.array([1, 1, 1, 1, 0.0]))
    np.testing.assert_allclose(R_est, R, atol=1e-12)
    np.testing.assert_allclose(t_est, 0, atol=1e-12)


def test_reflection_case_gives_a_proper_rotation() -> None:
    """Point sets related by a mirror: the best proper rotation (Umeyama's fix), det +1."""
    rng = np.random.default_rng(18)
    b = rng.normal(0, 1, (8, 3))
    a = b * np.array([1, 1, -1])
    R_est, _ = tf.absolute_orientation(a, b)
    assert np.linalg.det(R_est) == pytest.approx(1.0)
    np.testing.assert_allclose(R_est @ R_est.T, np.eye(3), atol=1e-12)
    ref, _ = Rotation.align_vectors(a - a.mean(0), b - b.mean(0))
    np.testing.assert_allclose(R_est, ref.as_matrix(), atol=1e-9)


def test_coplanar_points_are_enough() -> None:
    rng = np.random.default_rng(19)
    R = Rotation.random(rng=rng).as_matrix()
    b = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]])
    R_est, _ = tf.absolute_orientation(b @ R.T, b)
    np.testing.assert_allclose(R_est, R, atol=1e-12)


@pytest.mark.parametrize(
    "points",
    [np.zeros((2, 3)) + [[0, 0, 0], [1, 0, 0]], np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0.0]])],
    ids=["two_points", "collinear"],
)
def test_absolute_orientation_refuses_degenerate_sets(points: np.ndarray) -> None:
    with pytest.raises(TrackmeterError):
        tf.absolute_orientation(points, points)


def test_absolute_orientation_refuses_bad_shapes_and_weights() -> None:
    a = np.random.default_rng(0).normal(size=(4, 3))
    with pytest.raises(TrackmeterError):
        tf.absolute_orientation(a, a[:3])
    with pytest.raises(TrackmeterError):
        tf.absolute_orientation(a, a, np.array([1, 1, -1, 1.0]))
    with pytest.raises(TrackmeterError, match="at least 3"):
        tf.absolute_orientation(a, a, np.array([1, 1, 0, 0.0]))


# --------------------------------------------------------------------------- three-point frame


def test_frame_from_three_points_definition() -> None:
    p1, p2, p3 = np.array([1.0, 2, 3]), np.array([2.0, 2, 3]), np.array([1.5, 3, 3])
    R, origin = tf.frame_from_three_points(p1, p2, p3)
    np.testing.assert_allclose(origin, p1)
    np.testing.assert_allclose(R, np.eye(3), atol=1e-15)  # x toward p2, p3 at +y, z = x × y


def test_frame_from_three_points_properties() -> None:
    rng = np.random.default_rng(20)
    for _ in range(10):
        p1, p2, p3 = rng.normal(0, 1, (3, 3))
        R, origin = tf.frame_from_three_points(p1, p2, p3)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        # the points in the body frame: p1 at 0, p2 on +x, p3 in the xy-plane with y > 0
        body = (np.array([p1, p2, p3]) - origin) @ R
        np.testing.assert_allclose(body[0], 0, atol=1e-12)
        assert body[1, 0] > 0 and abs(body[1, 1]) < 1e-12 and abs(body[1, 2]) < 1e-12
        assert body[2, 1] > 0 and abs(body[2, 2]) < 1e-12
        # invariant: moving all three points rigidly moves the frame with them
        Q = Rotation.random(rng=rng).as_matrix()
        t = rng.normal(0, 1, 3)
        R2, o2 = tf.frame_from_three_points(Q @ p1 + t, Q @ p2 + t, Q @ p3 + t)
        np.testing.assert_allclose(R2, Q @ R, atol=1e-12)
        np.testing.assert_allclose(o2, Q @ p1 + t, atol=1e-12)


def test_frame_from_three_points_refuses_collinear() -> None:
    with pytest.raises(TrackmeterError):
        tf.frame_from_three_points([0, 0, 0], [1, 0, 0], [2, 0, 0])
    with pytest.raises(TrackmeterError):
        tf.frame_from_three_points([0, 0, 0], [0, 0, 0], [0, 1, 0])


def test_matrix_to_quat_of_a_stack_is_the_single_calls() -> None:
    # Engine._errors converts the estimate and the truth in one call: each row must be exactly
    # what the single conversion gives (also for nearly orthonormal and half-turn matrices)
    rng = np.random.default_rng(4)
    Rs = Rotation.random(300, random_state=5).as_matrix() + rng.normal(size=(300, 3, 3)) * 1e-9
    Rs = np.concatenate([Rs, [np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]])
    for a, b in zip(Rs[:-1], Rs[1:]):
        q2 = tf.matrix_to_quat_wxyz(np.stack([a, b]))
        np.testing.assert_array_equal(q2[0], tf.matrix_to_quat_wxyz(a))
        np.testing.assert_array_equal(q2[1], tf.matrix_to_quat_wxyz(b))


def test_absolute_orientation_names_a_non_finite_point() -> None:
    """A NaN point gave numpy's 'SVD did not converge'."""
    a = np.random.default_rng(0).normal(size=(5, 3))
    b = a.copy()
    b[4, 2] = np.nan
    with pytest.raises(TrackmeterError, match=r"points_b\[4\] is not finite"):
        tf.absolute_orientation(a, b)
    with pytest.raises(TrackmeterError, match=r"weights\[2\] .*-1"):
        tf.absolute_orientation(a, a, np.array([1, 1, -1, 1, 1.0]))


def test_frame_from_three_points_refuses_nan_and_bad_shapes() -> None:
    """A NaN gave a NaN frame silently; 2-vectors numpy's ValueError."""
    with pytest.raises(TrackmeterError, match=r"p1\[2\] is not finite"):
        tf.frame_from_three_points([0, 0, np.nan], [1, 0, 0], [0, 1, 0])
    with pytest.raises(TrackmeterError, match=r"p2 must be \(3,\), got shape \(2,\)"):
        tf.frame_from_three_points([0, 0, 0], [1, 0], [0, 1, 0])


def test_transforms_refuse_wrong_shapes_by_name() -> None:
    """make_transform(np.eye(2), ...) raised numpy's 'could not broadcast', apply_transform of
    (N,2) points a gufunc matmul error."""
    with pytest.raises(TrackmeterError, match=r"R_a_b must be \(3,3\), got shape \(2,2\)"):
        tf.make_transform(np.eye(2), np.zeros(3))
    with pytest.raises(TrackmeterError, match=r"t_a_b must be \(3,\), got shape \(2,\)"):
        tf.make_transform(np.eye(3), np.zeros(2))
    with pytest.raises(TrackmeterError, match=r"points_b must be \(3,\) or \(N,3\), got shape \(4,2\)"):
        tf.apply_transform(np.eye(4), np.zeros((4, 2)))
    with pytest.raises(TrackmeterError, match=r"T_a_b must be \(4,4\), got shape \(3,3\)"):
        tf.apply_transform(np.eye(3), np.zeros((4, 3)))


def test_matrix_to_quat_of_a_reflection_is_refused() -> None:
    """scipy's ValueError ('Non-positive determinant') came through."""
    with pytest.raises(TrackmeterError, match=r"R must be a rotation matrix \(orthonormal, det \+1\).*det = -1"):
        tf.matrix_to_quat_wxyz(np.diag([1.0, 1.0, -1.0]))


@pytest.mark.parametrize("dt_s", [0.0, -0.04, float("nan"), float("inf")])
def test_rates_over_no_time_are_refused(dt_s: float) -> None:
    """omega_body_between and finite_difference_rates raised a plain ValueError (the latter after
    numpy's divide-by-zero warning); over an infinite interval both returned zero rates."""
    import warnings

    from trackmeter.core.velocity import finite_difference_rates

    q = np.array([1.0, 0, 0, 0])
    with pytest.raises(TrackmeterError, match=r"dt_s must be positive and finite, s; got"):
        tf.omega_body_between(q, q, dt_s)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(TrackmeterError, match=r"t1_s must come after t0_s"):
            finite_difference_rates(1.0, np.eye(3), np.zeros(3), 1.0 + dt_s, np.eye(3), np.zeros(3))


def test_a_quaternion_that_is_no_rotation_and_a_transform_of_the_wrong_shape_are_refused_by_name() -> None:
    """A zero or NaN quaternion raised scipy's ValueError; invert_transform(np.eye(3)) an
    IndexError, and a (3,4) matrix was inverted silently (a re-check)."""
    from trackmeter.core.transforms import invert_transform, quat_wxyz_to_matrix
    from trackmeter.errors import TrackmeterError

    for q in ([0.0, 0.0, 0.0, 0.0], [np.nan, 0.0, 0.0, 1.0], [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]],
              [np.inf, 0.0, 0.0, 1.0]):  # an infinity gave a matrix of NaN (a second re-check)
        with pytest.raises(TrackmeterError, match=r"^quat_wxyz"):
            quat_wxyz_to_matrix(q)
    # one line, naming the row (a 7-line array with "..." before)
    with pytest.raises(TrackmeterError, match=r"^quat_wxyz\[20\] must be a finite quaternion of non-zero norm, "
                                              r"got \[0\.0, 0\.0, 0\.0, 0\.0\]$"):
        quat_wxyz_to_matrix(np.vstack([[1.0, 0.0, 0.0, 0.0]] * 20 + [[0.0, 0.0, 0.0, 0.0]]))
    for T in (np.eye(3), np.eye(4)[:3]):
        with pytest.raises(TrackmeterError, match=r"^T_a_b must be \(4,4\), got shape"):
            invert_transform(T)
    assert np.allclose(quat_wxyz_to_matrix([2.0, 0.0, 0.0, 0.0]), np.eye(3))  # not unit: normalised, as scipy does


def test_skew_is_the_cross_product_matrix() -> None:
    from trackmeter.core.transforms import skew

    rng = np.random.default_rng(2)
    v, w = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    S = skew(v)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", S, w), np.cross(v, w), atol=1e-15)
    np.testing.assert_array_equal(S, -np.swapaxes(S, 1, 2))
    np.testing.assert_allclose(skew(v[0]) @ w[0], np.cross(v[0], w[0]), atol=1e-15)


def test_procrustes_rotation_is_scipys_best_alignment_and_never_a_reflection() -> None:
    """R of M = sum_i w_i a_i b_i^T minimises sum_i w_i |a_i - R b_i|^2 (scipy's align_vectors),
    one matrix or a stack, and a reflection-like M still gives det +1 (Umeyama's fix)."""
    rng = np.random.default_rng(3)
    stack = []
    for k in range(4):
        a, b, w = rng.normal(size=(6, 3)), rng.normal(size=(6, 3)), rng.uniform(0.5, 2.0, 6)
        reference, _ = Rotation.align_vectors(a, b, weights=w)
        M = (a * w[:, None]).T @ b
        R, S = tf.procrustes_rotation(M)
        np.testing.assert_allclose(R, reference.as_matrix(), atol=1e-12)
        np.testing.assert_allclose(S, np.linalg.svd(M, compute_uv=False), rtol=1e-12)
        stack.append((M, R))
    R_stack, S_stack = tf.procrustes_rotation(np.stack([M for M, _ in stack]))
    assert R_stack.shape == (4, 3, 3) and S_stack.shape == (4, 3)
    np.testing.assert_allclose(R_stack, np.stack([R for _, R in stack]), atol=1e-12)
    mirror = np.diag([1.0, 1.0, -1.0]) @ Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix()
    R, _ = tf.procrustes_rotation(mirror)
    assert np.linalg.det(R) == pytest.approx(1.0)


# --------------------------------------------------------------------------- validation at the boundary
# An outside probe of the library API: matrices that are no rotation came back as a wrong
# answer (matrix_to_quat_wxyz(2 I) the identity, invert_transform(diag(2, 2, 2, 1)) itself),
# and a bad quaternion raised scipy's or numpy's own error with another reason.


@pytest.mark.parametrize("R", [2 * np.eye(3), np.diag([1.0, 1.0, 1.5]), np.ones((3, 3)), np.zeros((3, 3)),
                               np.stack([np.eye(3), 2 * np.eye(3)])])
def test_a_matrix_far_from_any_rotation_is_refused_not_projected(R: np.ndarray) -> None:
    with pytest.raises(TrackmeterError, match=r"R must be a rotation matrix \(orthonormal, det \+1\)"):
        tf.matrix_to_quat_wxyz(R)


def test_a_rotation_written_with_few_decimals_is_still_projected_as_documented() -> None:
    R = Rotation.from_rotvec([0.3, -0.2, 0.9]).as_matrix()
    rounded = np.round(R, 5)  # a file's few decimals: within the tolerance, projected as before
    q = tf.matrix_to_quat_wxyz(rounded)
    assert np.allclose(q, Rotation.from_matrix(rounded).as_quat(scalar_first=True, canonical=True), atol=1e-15)
    assert tf.attitude_error_angle(q, Rotation.from_matrix(R).as_quat(scalar_first=True)) < 1e-4
    with pytest.raises(TrackmeterError, match="det = -1"):
        tf.matrix_to_quat_wxyz(np.diag([1.0, 1.0, -1.0]))  # a reflection: orthonormal, det -1


@pytest.mark.parametrize("T", [np.diag([2.0, 2.0, 2.0, 1.0]), np.ones((4, 4)),
                               np.vstack([np.eye(4)[:3], [0.0, 0.0, 1.0, 1.0]])])
def test_a_matrix_that_is_no_rigid_transform_is_refused(T: np.ndarray) -> None:
    with pytest.raises(TrackmeterError, match="T_a_b"):
        tf.invert_transform(T)
    with pytest.raises(TrackmeterError, match="T_a_b"):
        tf.apply_transform(T, [1.0, 2.0, 3.0])


def test_make_transform_refuses_a_rotation_that_is_none() -> None:
    with pytest.raises(TrackmeterError, match="R_a_b"):
        tf.make_transform(np.ones((3, 3)), [0.0, 0.0, 0.0])
    T = tf.make_transform(Rotation.from_rotvec([0.1, 0.2, 0.3]).as_matrix(), [1.0, 2.0, 3.0])
    assert np.allclose(tf.invert_transform(T) @ T, np.eye(4), atol=1e-15)


@pytest.mark.parametrize("call", [
    lambda q: tf.attitude_error_angle(q, [1.0, 0.0, 0.0, 0.0]),
    lambda q: tf.attitude_error_components([1.0, 0.0, 0.0, 0.0], q),
    lambda q: tf.omega_body_between(q, [1.0, 0.0, 0.0, 0.0], 0.1),
    lambda q: tf.omega_body_between([1.0, 0.0, 0.0, 0.0], q, 0.1),
])
@pytest.mark.parametrize("q, reason", [([0.0, 0.0, 0.0, 0.0], "finite quaternion of non-zero norm"),
                                       ([np.nan, 0.0, 0.0, 0.0], "finite quaternion of non-zero norm"),
                                       ([1.0, 0.0, 0.0], r"must be \(4,\) or \(N,4\)")])
def test_a_bad_attitude_quaternion_is_refused_with_its_reason(call, q, reason) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(TrackmeterError, match=reason):
        call(q)


def test_quaternion_algebra_refuses_other_shapes() -> None:
    with pytest.raises(TrackmeterError, match=r"q1_wxyz must be \(4,\) or \(N,4\)"):
        tf.quat_multiply([1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0])
    with pytest.raises(TrackmeterError, match=r"omega_body must be \(3,\) or \(N,3\)"):
        tf.quat_derivative([1.0, 0.0, 0.0, 0.0], [1.0, 2.0])
    with pytest.raises(TrackmeterError, match=r"q_wxyz must be \(4,\) or \(N,4\)"):
        tf.quat_conjugate(np.ones((2, 2, 4)))
    # Non-unit quaternions (rates) stay the algebra's business: no norm asked of them.
    assert np.allclose(tf.quat_multiply([2.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]), [0.0, 2.0, 0.0, 0.0])


def test_continuous_signs_are_quat_sign_nearest_along_the_series() -> None:
    rng = np.random.default_rng(3)
    q = Rotation.random(50, rng=rng).as_quat(scalar_first=True) * rng.choice([-1.0, 1.0], size=(50, 1))
    q[[7, 8, 30]] = np.nan  # rows without a pose: skipped, kept
    want, last = q.copy(), None
    for i, row in enumerate(q):
        if np.isfinite(row).all():
            want[i] = last = tf.quat_sign_nearest(row if last is not None else row * np.sign(row[0]), last)
    got = tf.quat_signs_continuous(q)
    assert np.array_equal(got, want, equal_nan=True)
    assert np.array_equal(tf.quat_signs_continuous(got), got, equal_nan=True)  # written once, kept
    assert tf.quat_signs_continuous(np.full((2, 4), np.nan)).shape == (2, 4)


def test_no_matrices_give_no_quaternions() -> None:
    assert tf.matrix_to_quat_wxyz(np.zeros((0, 3, 3))).shape == (0, 4)


def test_a_reflection_is_no_rigid_transform() -> None:
    # The check of 8ca936d skipped any matrix orthonormal to working precision, a reflection too.
    with pytest.raises(TrackmeterError, match=r"R_a_b must be a rotation matrix.*det = -1"):
        tf.make_transform(np.diag([1.0, 1.0, -1.0]), [0.0, 0.0, 0.0])
    with pytest.raises(TrackmeterError, match=r"T_a_b\[:3, :3\] must be a rotation matrix.*det = -1"):
        tf.invert_transform(np.diag([1.0, 1.0, -1.0, 1.0]))
