"""Cheap checks of array arguments at the core's public entry points.

A NaN in a point or a covariance of the wrong shape otherwise surfaces deep inside numpy
("SVD did not converge", "cannot reshape array"), or not at all (a NaN pose). These helpers
turn it into one :class:`~trackmeter.errors.TrackmeterError` line that names the argument, the
expected shape and the offending row. They run every frame inside the tracker, so each is a
handful of vectorised numpy operations (no per-row Python loop unless something is wrong).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from trackmeter.errors import TrackmeterError

FloatArray = NDArray[np.float64]

#: Largest asymmetry ``|C - C^T|`` of a covariance, relative to its largest element, still
#: taken as rounding (``R^T C R`` and sums of such are symmetric only to ~1e-16).
SYMMETRY_TOLERANCE = 1e-6


def _shape_text(shape: tuple[int | str, ...]) -> str:
    """``(6,3)``, ``(3,)``: numpy's tuple notation without the spaces, as the docstrings write it."""
    return "(" + ",".join(str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"


def finite_rows(value: ArrayLike, name: str, shape: tuple[int | None, ...]) -> FloatArray:
    """``value`` as a float array of ``shape`` (``None``: any length), every element finite.

    Args:
        value: the argument as given.
        name: its name in the message (``points_cam``).
        shape: expected shape, e.g. ``(None, 3)`` for (N,3) points or ``(3,)`` for one point.

    Raises:
        TrackmeterError: ``"points_cam must be (N,3), got shape (5, 2)"`` or
            ``"points_cam[4] is not finite: [nan, 0, 3.5]"``.
    """
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise TrackmeterError(f"{name} must be a numeric array of shape {_expected(shape)}") from None
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
        raise TrackmeterError(f"{name} must be {_expected(shape)}, got shape {_shape_text(a.shape)}")
    if not np.isfinite(a).all():
        _raise_not_finite(a, name)
    return a


def _expected(shape: tuple[int | None, ...]) -> str:
    return _shape_text(tuple("N" if s is None else s for s in shape))


def _raise_not_finite(a: FloatArray, name: str) -> None:
    bad = np.argwhere(~np.isfinite(a))[0]
    if a.ndim <= 1:
        where = f"{name}[{bad[0]}]" if a.ndim == 1 else name
        raise TrackmeterError(f"{where} is not finite: {np.array2string(a, separator=', ', threshold=8)}")
    row = int(bad[0])
    raise TrackmeterError(f"{name}[{row}] is not finite: "
                          f"{np.array2string(a[row], separator=', ', threshold=9).replace(chr(10), '')}")


def covariances(value: ArrayLike, name: str, n: int, definite: bool = True) -> FloatArray:
    """``value`` as ``n`` symmetric 3x3 covariances (n,3,3), positive-definite (``definite``) or
    positive semi-definite (not ``definite``: a zero matrix is an exact point).

    Positive-definiteness is Sylvester's criterion on the leading minors (three products per
    matrix, no factorisation); semi-definiteness needs the eigenvalues (``eigvalsh``), allowed
    down to ``-1e-9`` times the matrix's largest element for rounding.

    Raises:
        TrackmeterError: wrong shape (a single (3,3) given for N points, (N,2,2)), a NaN, an
            asymmetric or indefinite matrix, naming ``name[i]``.
    """
    C = finite_rows(value, name, (n, 3, 3))
    scale = np.abs(C).max(axis=(1, 2))
    asym = np.abs(C - np.swapaxes(C, 1, 2)).max(axis=(1, 2))
    bad = np.flatnonzero(asym > SYMMETRY_TOLERANCE * scale)
    if bad.size:
        raise TrackmeterError(f"{name}[{bad[0]}] must be a symmetric positive-{'definite' if definite else 'semi-definite'} "
                              f"3x3 covariance: it is not symmetric")
    if definite:
        a, b, c = C[:, 0, 0], C[:, 0, 1], C[:, 0, 2]
        d, e, f = C[:, 1, 1], C[:, 1, 2], C[:, 2, 2]
        m2 = a * d - b * b
        det = a * (d * f - e * e) - b * (b * f - c * e) + c * (b * e - d * c)
        bad = np.flatnonzero(~((a > 0) & (m2 > 0) & (det > 0)))
        kind = "definite"
    else:
        bad = np.flatnonzero(np.linalg.eigvalsh(C)[:, 0] < -1e-9 * scale) if n else np.zeros(0, int)
        kind = "semi-definite (zero for an exact point)"
    if bad.size:
        raise TrackmeterError(f"{name}[{bad[0]}] must be a symmetric positive-{kind} 3x3 covariance, got "
                              f"{np.array2string(C[bad[0]], separator=', ', precision=3).replace(chr(10), '')}")
    return C


#: Largest ``|R^T R - I|`` element of a rotation matrix still taken as rounding (a product of
#: a few rotations in float64 is orthonormal to ~1e-15).
ORTHONORMAL_TOLERANCE = 1e-6


def rotation_matrix(value: ArrayLike, name: str) -> FloatArray:
    """``value`` as a finite (3,3) rotation: orthonormal (:data:`ORTHONORMAL_TOLERANCE`) with
    determinant +1. A reflection or a scaled matrix passed on fails later, and far from its
    cause, in scipy's "Non-positive determinant" or a filter state that keeps it.

    Raises:
        TrackmeterError: ``"R_cam_body must be a rotation (orthonormal, determinant +1), got
            determinant -1"``.
    """
    R = finite_rows(value, name, (3, 3))
    off = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if off > ORTHONORMAL_TOLERANCE or det <= 0:
        raise TrackmeterError(f"{name} must be a rotation (orthonormal, determinant +1), got determinant {det:.3g}"
                              + (f" and R^T R off the identity by {off:.3g}" if off > ORTHONORMAL_TOLERANCE else ""))
    return R


#: How far ``R^T R`` may be from the identity (largest entry) for R to be taken as a rotation
#: written with too few decimals: 5 decimals leave ~1e-5; a real non-rotation is far beyond.
ROTATION_TOLERANCE = 1e-3


def rotation_problem(value: ArrayLike, name: str = "R") -> str | None:
    """Why ``value`` (3,3) or (N,3,3) is no rotation matrix, or None when each is one within
    :data:`ROTATION_TOLERANCE` (``|R^T R - I|``, largest entry) with det > 0: the looser
    check, of matrices from outside (a file's, a caller's), which are then projected onto the
    rotation nearest; :func:`rotation_matrix` is the tight one of the core's own."""
    a = np.asarray(value, dtype=float)
    if a.shape[-2:] != (3, 3) or a.ndim not in (2, 3):
        return f"{name} must be (3,3) or (N,3,3), got shape {_shape_text(a.shape)}"
    if a.size == 0:
        return None  # no matrix: none of them is wrong
    if not np.isfinite(a).all():
        return f"{name} must be a finite rotation matrix: it holds a NaN or an infinity"
    error = float(np.max(np.abs(np.swapaxes(a, -1, -2) @ a - np.eye(3))))
    det = float(np.min(np.linalg.det(a)))
    if det <= 0 or error > ROTATION_TOLERANCE:
        return f"{name} must be a rotation matrix (orthonormal, det +1): |R^T R - I| = {error:.2g}, det = {det:.6g}"
    return None


def vectors(value: ArrayLike, name: str, size: int) -> FloatArray:
    """``value`` as a float array of shape (size,) or (N,size), kept so (values unchecked)."""
    a = np.asarray(value, dtype=float)
    if a.ndim not in (1, 2) or a.shape[-1] != size:
        raise TrackmeterError(f"{name} must be ({size},) or (N,{size}), got shape {_shape_text(a.shape)}")
    return a


def as_rows(value: ArrayLike, name: str, size: int) -> FloatArray:
    """``value`` as (N, size) rows: one (size,), N of them (N, size), OpenCV's (N, 1, size),
    or none (an empty array of any shape); values unchecked.

    Raises:
        TrackmeterError: any other shape, which ``reshape(-1, size)`` would turn into other
            points whenever its count of numbers divides evenly (three homogeneous points (3,4)
            into four 3D points).
    """
    a = np.asarray(value, dtype=float)
    if a.size == 0 or (a.shape[-1:] == (size,) and (a.ndim <= 2 or (a.ndim == 3 and a.shape[1] == 1))):
        return a.reshape(-1, size)
    raise TrackmeterError(f"{name} must be ({size},) or (N,{size}), got shape {_shape_text(a.shape)}")


def finite_time(value: float, name: str) -> float:
    """``value`` as a float time, s, refused when it is not a finite number.

    Raises:
        TrackmeterError: ``"t_s is not finite: nan"``.
    """
    try:
        # float() reads "1.0", b"1", a bytearray and True: a time is a real number, or a 0-d array of one.
        if isinstance(value, (str, bytes, bytearray, memoryview, bool, np.bool_)):
            raise TypeError
        if np.ndim(value) != 0 or np.asarray(value).dtype.kind not in "fiu":
            raise TypeError
        t = float(value)
    except (TypeError, ValueError):
        raise TrackmeterError(f"{name} must be a number of seconds, got {value!r}") from None
    if not np.isfinite(t):
        raise TrackmeterError(f"{name} is not finite: {t}")
    return t


def time_order(t_s: NDArray[np.float64], name: str) -> None:
    """Refuse timestamps ``t_s`` (N,) s that go backwards anywhere; repeats are allowed.

    Nearest-time pairing (``searchsorted``) assumes sorted times: unsorted ones pair with
    nothing, silently.

    Raises:
        TrackmeterError: ``"trajectory: timestamps go backwards: t = 0 s after 1 s"``.
    """
    t_s = np.asarray(t_s, dtype=float)
    if not np.all(np.isfinite(t_s)):  # a NaN compares as neither order: a step back across it passed
        i = int(np.flatnonzero(~np.isfinite(t_s))[0])
        raise TrackmeterError(f"{name}: timestamp {i} is not a number ({t_s[i]})")
    back = np.flatnonzero(np.diff(t_s) < 0)
    if len(back):
        i = int(back[0])
        raise TrackmeterError(f"{name}: timestamps go backwards: t = {t_s[i + 1]:.9g} s after {t_s[i]:.9g} s")
