"""Rotations, rigid transforms and the paper's attitude equations.

Conventions (see ``docs/conventions.md``):

- ``T_a_b`` (4x4) or ``(R_a_b, t_a_b)`` maps points from frame b to frame a:
  ``p_a = R_a_b @ p_b + t_a_b``, so chains cancel: ``T_a_c = T_a_b @ T_b_c``.
- Quaternions are scalar-first ``wxyz`` and always pass through
  :class:`scipy.spatial.transform.Rotation` with ``scalar_first=True``.
- ``omega_body`` is the angular velocity expressed in the body frame (rad/s).

Equation numbers refer to the TV-Trackmeter paper (section 3: rigid-body kinematics,
section 4: error measures).
"""

from __future__ import annotations

import inspect
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from trackmeter.core.checks import finite_rows, rotation_problem, vectors
from trackmeter.errors import TrackmeterError

FloatArray = NDArray[np.float64]


# --------------------------------------------------------------------------- quaternions


def quat_wxyz_to_matrix(quat_wxyz: ArrayLike) -> FloatArray:
    """Rotation matrix (3,3) or (N,3,3) from unit quaternion(s) ``wxyz`` (4,) or (N,4); one
    that is not of unit norm is normalised (scipy).

    Raises:
        TrackmeterError: a quaternion of zero norm, not finite, or of another shape.
    """
    return _rotation_of_quat(quat_wxyz, "quat_wxyz").as_matrix()


def _rotation_of_quat(quat_wxyz: ArrayLike, name: str) -> Rotation:
    """scipy's Rotation of unit quaternion(s) ``wxyz`` (4,) or (N,4) (normalised if not unit).

    Raises:
        TrackmeterError: of another shape, not finite, or of zero norm: scipy says "zero norm"
            of a NaN too, and takes an infinity silently.
    """
    q = vectors(quat_wxyz, name, 4)
    rows = q.reshape(-1, 4)
    bad = ~np.isfinite(rows).all(axis=1) | ~(np.abs(rows).max(axis=1) > 0)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        where = name if q.ndim == 1 else f"{name}[{i}]"
        raise TrackmeterError(f"{where} must be a finite quaternion of non-zero norm, got "
                              f"{[float(x) for x in rows[i]]}")
    return Rotation.from_quat(q, scalar_first=True)


def rotation_from_matrix(R: ArrayLike, refuse_far: bool = False) -> Rotation:
    """``Rotation.from_matrix(R)`` for (3,3) or (N,3,3), with the same numbers but a cheaper check.

    scipy (1.17) first checks each matrix: determinant > 0 (else ValueError) and Gram matrix
    ``R R^T`` within ``isclose(atol=1e-12)`` of identity; those that pass are converted as
    they are, the others are first projected onto SO(3) by an SVD. The check costs ~5x the
    conversion (~0.1 ms a call, mostly ``np.isclose``). Here a tighter check
    (``|R R^T - I| <= 1e-13`` everywhere, det > 0) lets the conversion skip scipy's
    (``assume_valid=True``): whatever passes it passes scipy's, so the result is bit-identical;
    anything else (drifted, reflected, NaN) goes through the full ``Rotation.from_matrix``.

    ``refuse_far``: anything else is first asked
    :func:`~trackmeter.core.checks.rotation_problem` (TrackmeterError beyond a file's
    rounding), since scipy projects any matrix, ``2 I`` onto the identity.
    """
    R = np.asarray(R, dtype=float)
    exact = _exact_rotation(R)
    if exact and _HAS_ASSUME_VALID:
        return Rotation.from_matrix(R, assume_valid=True)
    if not exact and refuse_far and (problem := rotation_problem(R)) is not None:
        raise TrackmeterError(problem)
    return Rotation.from_matrix(R)


def _exact_rotation(R: FloatArray) -> bool:
    """Whether ``R`` (3,3) or (N,3,3) is a rotation to working precision: ``|R R^T - I| <=
    1e-13`` everywhere and det > 0 (NaN is not). What passes asks nothing more of scipy or of
    :func:`~trackmeter.core.checks.rotation_problem`."""
    return bool(R.shape[-2:] == (3, 3) and R.size
                and np.abs(R @ np.swapaxes(R, -1, -2) - _EYE3).max() <= 1e-13 and np.linalg.det(R).min() > 0)


_EYE3 = np.eye(3)
_HAS_ASSUME_VALID = "assume_valid" in inspect.signature(Rotation.from_matrix).parameters  # not in every scipy the project allows


def matrix_to_quat_wxyz(R: ArrayLike) -> FloatArray:
    """Unit quaternion(s) ``wxyz`` with non-negative w from rotation matrix (3,3) or (N,3,3).

    A matrix within :data:`~trackmeter.core.checks.ROTATION_TOLERANCE` of a rotation (one
    written with few decimals) is projected onto it (scipy).

    Raises:
        TrackmeterError: ``R`` of another shape, not finite, a reflection (det < 0), or
            farther from a rotation: scipy projects any matrix, ``2 I`` onto the identity.
    """
    return np.asarray(rotation_from_matrix(R, refuse_far=True).as_quat(scalar_first=True, canonical=True), dtype=float)


def quat_sign_nearest(quat_wxyz: ArrayLike, reference_wxyz: ArrayLike | None) -> FloatArray:
    """``q`` or ``-q`` (the same rotation), whichever is nearer ``reference_wxyz``; shapes (4,).

    A series written one quaternion at a time with ``w >= 0`` flips all four components where
    the rotation passes half a turn; choosing each sign against the one written before keeps the
    series continuous (for a plot, or a finite difference as in eq. 14). ``reference_wxyz`` None
    returns ``q`` as given.
    """
    q = np.asarray(quat_wxyz, dtype=float)
    if reference_wxyz is not None and float(np.dot(q, np.asarray(reference_wxyz, dtype=float))) < 0.0:
        return -q
    return q


def quat_signs_continuous(quat_wxyz: ArrayLike) -> FloatArray:
    """A series of quaternions (N,4) written as docs/conventions.md says: the first with
    ``w >= 0``, each after it on the side of the one before (:func:`quat_sign_nearest` along
    the series). Rows that are not finite (no pose) are kept as they are and skipped: the row
    after them takes the side of the last one with a pose."""
    q = vectors(quat_wxyz, "quat_wxyz", 4).reshape(-1, 4).copy()
    rows = np.flatnonzero(np.isfinite(q).all(axis=1))
    if len(rows) == 0:
        return q
    given = q[rows]
    turns = np.where(np.sum(given[1:] * given[:-1], axis=1) < 0.0, -1.0, 1.0)
    first = -1.0 if given[0, 0] < 0.0 else 1.0
    q[rows] = given * (first * np.concatenate([[1.0], np.cumprod(turns)]))[:, None]
    return q


def quat_multiply(q1_wxyz: ArrayLike, q2_wxyz: ArrayLike) -> FloatArray:
    """Hamilton product ``q1 ⊗ q2`` of (possibly non-unit) quaternions, shapes (4,) or (N,4).

    Needed for quaternion *rates* (eqs. 14-15), which are not rotations, so scipy's
    :class:`Rotation` cannot hold them.
    """
    a = vectors(q1_wxyz, "q1_wxyz", 4)
    b = vectors(q2_wxyz, "q2_wxyz", 4)
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        axis=-1,
    )


def quat_conjugate(q_wxyz: ArrayLike) -> FloatArray:
    """Conjugate ``(w, -x, -y, -z)``; the inverse of a unit quaternion."""
    q = vectors(q_wxyz, "q_wxyz", 4).copy()
    q[..., 1:] *= -1.0
    return q


def quat_derivative(quat_wxyz: ArrayLike, omega_body: ArrayLike) -> FloatArray:
    """Quaternion kinematics, paper eq. 15: ``q_dot = 1/2 q ⊗ (0, omega_body)``.

    Args:
        quat_wxyz: (4,) or (N,4) attitude ``q_world_body`` (maps body to world).
        omega_body: (3,) or (N,3) angular velocity in the body frame, rad/s.

    Returns:
        (4,) or (N,4) time derivative of the quaternion, 1/s.
    """
    w = vectors(omega_body, "omega_body", 3)
    omega_quat = np.concatenate([np.zeros(w.shape[:-1] + (1,)), w], axis=-1)
    return 0.5 * quat_multiply(quat_wxyz, omega_quat)


def omega_body_from_quat_rate(quat_wxyz: ArrayLike, quat_rate_wxyz: ArrayLike) -> FloatArray:
    """Body-frame angular velocity from a quaternion and its rate, paper eq. 14.

    ``(0, omega_body) = 2 q* ⊗ q_dot`` — the inverse of :func:`quat_derivative`.

    Args:
        quat_wxyz: (4,) or (N,4) unit attitude quaternion ``q_world_body``.
        quat_rate_wxyz: (4,) or (N,4) its time derivative, 1/s.

    Returns:
        (3,) or (N,3) omega in the body frame, rad/s.
    """
    return 2.0 * quat_multiply(quat_conjugate(quat_wxyz), quat_rate_wxyz)[..., 1:]


def omega_body_between(quat0_wxyz: ArrayLike, quat1_wxyz: ArrayLike, dt_s: float) -> FloatArray:
    """Mean body-frame angular velocity taking attitude q0 to q1 in ``dt_s`` seconds.

    The finite-difference form of eq. 14 done exactly on the rotation group:
    ``omega_body = log(q0^-1 ⊗ q1) / dt`` (constant rate about a body-fixed axis).
    Sign-flipped quaternions (q and -q) give the same answer.

    Raises:
        TrackmeterError: ``dt_s`` not positive and finite.
    """
    if not 0 < dt_s < math.inf:  # an infinite interval would turn any rotation into a zero rate
        raise TrackmeterError(f"dt_s must be positive and finite, s; got {dt_s:g}")
    r0 = _rotation_of_quat(quat0_wxyz, "quat0_wxyz")
    r1 = _rotation_of_quat(quat1_wxyz, "quat1_wxyz")
    return np.asarray((r0.inv() * r1).as_rotvec(), dtype=float) / dt_s


# --------------------------------------------------------------------------- attitude errors


def attitude_error_angle(quat_est_wxyz: ArrayLike, quat_true_wxyz: ArrayLike) -> FloatArray:
    """Total attitude error angle, paper eq. 16: the angle of ``R_est R_true^T``, rad.

    ``theta = 2 arccos |<q_est, q_true>|`` in [0, pi]; insensitive to the sign of either
    quaternion. Computed through ``atan2`` of the relative rotation so it stays exact for
    small angles, where ``arccos`` loses half the digits.
    """
    return np.linalg.norm(attitude_error_components(quat_est_wxyz, quat_true_wxyz), axis=-1)


def attitude_error_components(quat_est_wxyz: ArrayLike, quat_true_wxyz: ArrayLike) -> FloatArray:
    """Per-axis attitude error, paper eq. 17, in the camera (parent) frame, rad.

    The rotation vector of the error rotation ``R_err = R_est @ R_true^T``: its x, y, z are
    the small rotations about the camera's x, y and z (viewing) axes that take the true
    attitude onto the estimate; its norm is eq. 16's total angle.

    Args:
        quat_est_wxyz, quat_true_wxyz: (4,) or (N,4) quaternions of ``T_cam_body``.

    Returns:
        (3,) or (N,3) rotation vector of the error, rad.
    """
    r_est = _rotation_of_quat(quat_est_wxyz, "quat_est_wxyz")
    r_true = _rotation_of_quat(quat_true_wxyz, "quat_true_wxyz")
    return np.asarray((r_est * r_true.inv()).as_rotvec(), dtype=float)


# --------------------------------------------------------------------------- rigid transforms


def skew(v: ArrayLike) -> FloatArray:
    """``[v]x`` (...,3,3), the cross-product matrix of each ``v`` (...,3): ``[v]x w = v x w``."""
    v = np.asarray(v, dtype=float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def make_transform(R_a_b: ArrayLike, t_a_b: ArrayLike) -> FloatArray:
    """4x4 homogeneous ``T_a_b`` from a rotation (3,3) and a translation (3,), m.

    Raises:
        TrackmeterError: either of the wrong shape (numpy would broadcast a (3,) rotation row
            or refuse with "could not broadcast").
    """
    R = _rotation(R_a_b, "R_a_b")
    t = _shaped(t_a_b, "t_a_b", (3,))
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _shaped(value: ArrayLike, name: str, shape: tuple[int, ...]) -> FloatArray:
    """``value`` as a float array of exactly ``shape`` (values unchecked: NaN passes, as before)."""
    a = np.asarray(value, dtype=float)
    if a.shape != shape:
        want = "(" + ",".join(map(str, shape)) + ("," if len(shape) == 1 else "") + ")"
        got = "(" + ",".join(map(str, a.shape)) + ("," if a.ndim == 1 else "") + ")"
        raise TrackmeterError(f"{name} must be {want}, got shape {got}")
    return a


def _rotation(value: ArrayLike, name: str) -> FloatArray:
    """``value`` as a (3,3) rotation within :data:`~trackmeter.core.checks.ROTATION_TOLERANCE`
    (NaN passes, as before: a caller's marker of no pose)."""
    R = _shaped(value, name, (3, 3))
    if np.isfinite(R).all() and not _exact_rotation(R):
        problem = rotation_problem(R, name)
        if problem is not None:
            raise TrackmeterError(problem)
    return R


def _rigid(value: ArrayLike, name: str) -> FloatArray:
    """``value`` as a (4,4) rigid transform: a rotation (:func:`_rotation`) and ``[0, 0, 0, 1]``
    below it. Its inverse and its action are taken from that structure, so another matrix
    would come back as a wrong answer (``invert_transform(diag(2, 2, 2, 1))`` itself)."""
    T = _shaped(value, name, (4, 4))
    _rotation(T[:3, :3], f"{name}[:3, :3]")
    if np.isfinite(T).all() and not np.array_equal(T[3], _LAST_ROW):
        raise TrackmeterError(f"{name} must be a rigid transform, its last row [0, 0, 0, 1]; got "
                              f"{[float(x) for x in T[3]]}")
    return T


_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])


def transform_from_pose(position: ArrayLike, quat_wxyz: ArrayLike) -> FloatArray:
    """4x4 ``T_a_b`` from the position of b's origin in a (m) and b's attitude ``q_a_b``."""
    return make_transform(quat_wxyz_to_matrix(quat_wxyz), position)


def invert_transform(T_a_b: ArrayLike) -> FloatArray:
    """``T_b_a`` from ``T_a_b`` (4,4) using the rigid structure (no general matrix inverse).

    Raises:
        TrackmeterError: ``T_a_b`` not of shape (4,4), or no rigid transform.
    """
    T = _rigid(T_a_b, "T_a_b")
    R = T[:3, :3]
    return make_transform(R.T, -R.T @ T[:3, 3])


def apply_transform(T_a_b: ArrayLike, points_b: ArrayLike) -> FloatArray:
    """Map points (N,3) or (3,) from frame b to frame a: ``p_a = R_a_b p_b + t_a_b``; ``T_a_b``
    (4,4). Returns the same shape as ``points_b``, m.

    Raises:
        TrackmeterError: ``T_a_b`` not a (4,4) rigid transform or points not (3,)/(N,3).
    """
    T = _rigid(T_a_b, "T_a_b")
    p = np.asarray(points_b, dtype=float)
    if p.ndim not in (1, 2) or p.shape[-1] != 3:
        got = "(" + ",".join(map(str, p.shape)) + ("," if p.ndim == 1 else "") + ")"
        raise TrackmeterError(f"points_b must be (3,) or (N,3), got shape {got}")
    return p @ T[:3, :3].T + T[:3, 3]


# --------------------------------------------------------------------------- absolute orientation


def procrustes_rotation(M: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """The proper rotation R (det +1) maximising ``trace(R^T M)``, and M's singular values.

    The orthogonal Procrustes problem kept off reflections (Kabsch 1976; Umeyama 1991, IEEE
    PAMI 13(4), eq. 39-41): with ``M = U S V^T``, ``R = U diag(1, 1, s) V^T``,
    ``s = sign(det U det V)`` (1 where that is 0). With M a cross-covariance
    ``sum_i w_i a_i b_i^T`` this is R_a_b of the best rigid fit; with M a sum of rotations, their
    chordal mean; with M itself near a rotation, the nearest rotation (Frobenius norm).

    Args:
        M: (3,3) or (K,3,3).

    Returns:
        ``(R, S)``: R of M's shape; S (3,) or (K,3), the singular values, largest first (a
        small ``S[1]`` means a rank-1 M: collinear points, R undetermined).
    """
    U, S, Vt = np.linalg.svd(np.asarray(M, dtype=float))
    s = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    D = np.zeros(U.shape)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = np.where(s == 0, 1.0, s)
    return U @ D @ Vt, S


def absolute_orientation(
    points_a: ArrayLike,
    points_b: ArrayLike,
    weights: ArrayLike | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Weighted least-squares rigid transform between two point sets (Kabsch / Umeyama).

    Finds ``R_a_b`` (proper rotation, det +1) and ``t_a_b`` minimising
    ``sum_i w_i |p_a_i - (R_a_b p_b_i + t_a_b)|^2`` in closed form: the weighted centroids
    give t, the SVD of the weighted cross-covariance gives R with the reflection fix of
    Umeyama (1991), "Least-squares estimation of transformation parameters between two point
    patterns", IEEE PAMI 13(4), eq. 39-41 (scale fixed to 1).

    Args:
        points_a: (N,3) points in frame a, m.
        points_b: (N,3) the same points in frame b, m.
        weights: (N,) non-negative weights (e.g. 1/sigma^2), default all ones.

    Returns:
        ``(R_a_b, t_a_b)``: (3,3) and (3,).

    Raises:
        TrackmeterError: fewer than 3 points with positive weight, the points are collinear so
            the rotation is not determined, or an argument of the wrong shape or with a
            non-finite (or, for ``weights``, negative) element, named with its row.
    """
    a = finite_rows(points_a, "points_a", (None, 3))
    b = finite_rows(points_b, "points_b", (len(a), 3))
    w = np.ones(len(a)) if weights is None else finite_rows(weights, "weights", (len(a),))
    if np.any(w < 0):
        k = int(np.flatnonzero(w < 0)[0])
        raise TrackmeterError(f"weights[{k}] is {w[k]:g}: absolute orientation weights must be non-negative")
    if np.count_nonzero(w > 0) < 3:
        raise TrackmeterError(f"absolute orientation needs at least 3 weighted points, got {np.count_nonzero(w > 0)}")
    w = w / w.sum()
    centroid_a = w @ a
    centroid_b = w @ b
    da = a - centroid_a
    db = b - centroid_b
    cross_cov = (da * w[:, None]).T @ db  # sum_i w_i da_i db_i^T, (3,3)
    R, S = procrustes_rotation(cross_cov)
    if S[1] <= 1e-12 * max(S[0], 1e-300):
        raise TrackmeterError("absolute orientation is undetermined: the points are collinear")
    t = centroid_a - R @ centroid_b
    return R, t


def frame_from_three_points(p1: ArrayLike, p2: ArrayLike, p3: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """The paper's case-(a) body frame from three points (section 2.C), as ``(R_a_body, origin_a)``.

    Origin at ``p1``, x axis toward ``p2``, xy-plane through ``p3`` (y toward p3's side), z
    completing a right-handed frame. Points are (3,) in any frame a; the columns of
    ``R_a_body`` are the body axes expressed in a.

    Raises:
        TrackmeterError: the three points are (nearly) collinear or coincident, or one is not
            a finite (3,) vector.
    """
    p1 = finite_rows(p1, "p1", (3,))
    x = finite_rows(p2, "p2", (3,)) - p1
    v = finite_rows(p3, "p3", (3,)) - p1
    nx = np.linalg.norm(x)
    z = np.cross(x, v)
    nz = np.linalg.norm(z)
    if nx < 1e-12 or nz < 1e-9 * nx * max(float(np.linalg.norm(v)), 1e-300):
        raise TrackmeterError("three-point frame is undetermined: the points are collinear")
    x = x / nx
    z = z / nz
    y = np.cross(z, x)
    return np.column_stack([x, y, z]), p1
