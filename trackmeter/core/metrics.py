"""Trajectory error metrics: estimated motion against ground truth (paper section 4).

The paper judged the TV-Trackmeter by comparing the motion it measured with the motion imposed
on the mock-up: position and attitude errors (eqs. 16-17), linear and angular speed errors
(eq. 14, body frame), after relating the two reference frames by a hand-eye SE(3) calibration.
This module does the same on sampled trajectories, in four pure steps:

1. :func:`associate` — pair each estimated pose with the nearest ground-truth timestamp within
   a tolerance, one to one; what has no partner is counted, not guessed.
2. :func:`estimate_body_offset` — for ``--align body``: the constant offset between the
   estimated and the true body frame, by least squares over the run (cases a and c of the
   paper estimate poses of a body frame of their own choosing).
3. :func:`motion_errors` — per-frame errors: position (camera frame), attitude (eq. 17
   components in the camera frame and eq. 16 total angle), linear velocity (camera frame),
   angular velocity (TRUE body frame), and the SPEED score terms.
4. :func:`summarize` — RMS, largest absolute value and 95th percentile of each, as the JSON
   summary of ``trackmeter evaluate`` (DESIGN.md section 6).

Frames: poses are ``T_cam_body`` (``p_cam = R p_body + t``); camera x, y lateral, z the viewing
axis (the paper's viewing axis was y). Units SI: m, rad, m/s, rad/s.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Literal, Protocol, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from trackmeter.core.checks import as_rows, time_order
from trackmeter.core.params import check_params, param
from trackmeter.core.transforms import (attitude_error_components, matrix_to_quat_wxyz, procrustes_rotation,
                                       quat_wxyz_to_matrix, rotation_from_matrix)
from trackmeter.errors import TrackmeterError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


@dataclass(frozen=True)
class EvaluateParams:
    """Tunables of ``trackmeter evaluate``."""

    tolerance_s: float = param(
        # At least 1 us: times read from nanoseconds as float seconds differ by a few 1e-7 s.
        0.01, "largest |t_estimate - t_truth| for two poses to be paired, s", min=1e-6, max=10.0
    )
    settle_s: float = param(
        0.0, "seconds skipped from the start of the run (else the first paired pose) before errors count, s",
        min=0.0, max=1e6,
    )
    align: str = param(
        "auto",
        "frame relation: none (same body frame), body (fit a constant body-frame offset), or auto "
        "(body for a case (a) or (c) run, whose body frame is its own; none otherwise)",
        choices=("auto", "none", "body"),
    )

    def __post_init__(self) -> None:
        check_params(self)  # declared ranges and choices, as the config loader checks them


def resolve_align(align: str, case: str | None) -> Literal["none", "body"]:
    """The frame relation ``align`` means for a run of pose ``case`` ("a", "b", "c" or None when
    unknown): "auto" is "body" for cases (a) and (c), whose body frame is defined by the run
    itself (three tracked points, or the model acquired while the target held still), and
    "none" otherwise (case (b)'s body frame is its a-priori model's, which is the truth's).

    Raises:
        TrackmeterError: ``align`` is not "auto", "none" or "body".
    """
    if align == "auto":
        return "body" if case in ("a", "c") else "none"
    if align not in ("none", "body"):
        raise TrackmeterError(f"align must be 'auto', 'none' or 'body', got {align!r}")
    return align  # type: ignore[return-value]


class PoseTrack(Protocol):
    """Anything with timed poses ``T_cam_body``: a :class:`~trackmeter.data.trajectory.Trajectory`
    or a :class:`~trackmeter.data.motion_csv.MotionSeries` (valid rows). Velocity attributes,
    when present, are ``velocity_cam_m_s`` (N,3) and ``omega_body_rad_s`` (N,3)."""

    @property
    def t_s(self) -> FloatArray: ...  # (N,) s
    @property
    def position_m(self) -> FloatArray: ...  # (N,3) body origin in cam, m
    @property
    def quat_wxyz(self) -> FloatArray: ...  # (N,4) attitude of T_cam_body


# --------------------------------------------------------------------------- association


@dataclass(frozen=True, eq=False)
class Association:
    """One-to-one pairs of ground-truth and estimated samples.

    Attributes:
        index_truth, index_est: (M,) indices of the paired samples, in time order.
        dt_s: (M,) ``t_est - t_truth`` of each pair, s.
        unmatched_est: estimated poses with no truth pose within the tolerance.
        unmatched_truth: truth poses inside the compared span (the run's, else the estimate's;
            widened by the tolerance) with no estimate: frames without a pose, and, when the
            truth is sampled more densely than the run's frames, the truth samples between them.
    """

    index_truth: IntArray
    index_est: IntArray
    dt_s: FloatArray
    unmatched_est: int
    unmatched_truth: int

    @property
    def matched(self) -> int:
        return len(self.index_truth)

    @property
    def unmatched(self) -> int:
        """Poses left without a partner on either side (see the attributes)."""
        return self.unmatched_est + self.unmatched_truth


def _nearest(times_s: FloatArray, t_s: FloatArray) -> IntArray:
    """(N,) index into the sorted ``times_s`` (K >= 1) of the time nearest each of ``t_s`` (the
    earlier of two as near)."""
    right = np.clip(np.searchsorted(times_s, t_s), 0, len(times_s) - 1)
    left = np.clip(right - 1, 0, len(times_s) - 1)
    return cast(IntArray, np.where(np.abs(t_s - times_s[left]) <= np.abs(t_s - times_s[right]), left, right))


def associate(t_truth_s: ArrayLike, t_est_s: ArrayLike, tolerance_s: float) -> Association:
    """Pair samples by nearest timestamp within ``tolerance_s``, each sample used at most once.

    Every estimate proposes its nearest truth sample; proposals are accepted closest first, so
    when two estimates want the same truth sample the nearer one gets it and the other stays
    unmatched (it is not moved to a farther neighbour: that would compare different instants).

    Args:
        t_truth_s: (N,) non-decreasing truth timestamps, s.
        t_est_s: (K,) non-decreasing estimate timestamps, s.
        tolerance_s: largest accepted ``|t_est - t_truth|``, s.

    Raises:
        TrackmeterError: timestamps that go backwards (they would pair with nothing).
    """
    tt = np.asarray(t_truth_s, dtype=float).reshape(-1)
    te = np.asarray(t_est_s, dtype=float).reshape(-1)
    time_order(tt, "truth")
    time_order(te, "estimate")
    if len(tt) == 0 or len(te) == 0:
        return Association(np.zeros(0, np.intp), np.zeros(0, np.intp), np.zeros(0), len(te), 0)
    nearest = _nearest(tt, te)
    gap = np.abs(te - tt[nearest])
    used = np.zeros(len(tt), dtype=bool)
    pairs: list[tuple[int, int]] = []
    for k in np.argsort(gap, kind="stable"):
        j = nearest[k]
        if gap[k] <= tolerance_s and not used[j]:
            used[j] = True
            pairs.append((j, k))
    pairs.sort()
    index_truth = np.array([p[0] for p in pairs], dtype=np.intp)
    index_est = np.array([p[1] for p in pairs], dtype=np.intp)
    in_span = (tt >= te[0] - tolerance_s) & (tt <= te[-1] + tolerance_s)
    return Association(
        index_truth,
        index_est,
        te[index_est] - tt[index_truth],
        unmatched_est=len(te) - len(pairs),
        unmatched_truth=int(np.count_nonzero(in_span & ~used)),
    )


# --------------------------------------------------------------------------- body-frame alignment


def estimate_body_offset(
    quat_true_wxyz: ArrayLike,
    position_true_m: ArrayLike,
    quat_est_wxyz: ArrayLike,
    position_est_m: ArrayLike,
) -> tuple[FloatArray, FloatArray]:
    """Least-squares constant offset ``T_bodytrue_bodyest`` with ``T_cam_est ≈ T_cam_true @ X``.

    The estimator's body frame may differ from the truth's by a fixed rigid transform X (the
    three-point frame of case a, the frozen frame of case c). With paired poses i:

    - rotation: ``R_true_i^T R_est_i = R_X`` for all i, so R_X is the rotation nearest (in the
      Frobenius/chordal sense) to their sum: the SVD projection onto SO(3) of
      ``M = sum_i R_true_i^T R_est_i`` (Hartley et al., "Rotation averaging", IJCV 2013, sec. 5.3
      — the chordal L2 mean);
    - translation: ``t_est_i = t_true_i + R_true_i t_X`` is linear in t_X; its least-squares
      solution is ``t_X = mean_i R_true_i^T (t_est_i - t_true_i)`` since every ``R^T R = I``.

    Noise-free pairs give X exactly (to rounding). The inverse, ``T_bodyest_bodytrue``, is
    what maps the estimate's body coordinates to the truth's.

    Args:
        quat_true_wxyz, quat_est_wxyz: (M,4) attitudes of the paired ``T_cam_body``.
        position_true_m, position_est_m: (M,3) body origins in the camera frame, m.

    Returns:
        ``(R_X, t_X)``: (3,3) and (3,) — ``R_bodytrue_bodyest`` and the estimated body origin
        in the true body frame, m.
    """
    q_true, q_est = as_rows(quat_true_wxyz, "quat_true_wxyz", 4), as_rows(quat_est_wxyz, "quat_est_wxyz", 4)
    p_true, p_est = as_rows(position_true_m, "position_true_m", 3), as_rows(position_est_m, "position_est_m", 3)
    _check_paired(quat_true_wxyz=q_true, quat_est_wxyz=q_est, position_true_m=p_true, position_est_m=p_est)
    if len(q_true) == 0:
        raise TrackmeterError("body alignment needs at least one paired pose")
    R_true, R_est = quat_wxyz_to_matrix(q_true), quat_wxyz_to_matrix(q_est)
    M = np.einsum("nji,njk->ik", R_true, R_est)
    R_X, _ = procrustes_rotation(M)
    dp = p_est - p_true
    t_X = np.einsum("nji,nj->ni", R_true, dp).mean(axis=0)
    return R_X, t_X


def refer_to_true_body(
    quat_est_wxyz: ArrayLike,
    position_est_m: ArrayLike,
    R_X: ArrayLike,
    t_X: ArrayLike,
    velocity_est_cam_m_s: ArrayLike | None = None,
    omega_est_body_rad_s: ArrayLike | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray | None, FloatArray | None]:
    """Express an estimate in the true body frame, given ``X = T_bodytrue_bodyest``.

    Pose: ``T_cam_true = T_cam_est @ X^-1``. Angular velocity (body frame, eq. 14):
    ``omega_true = R_X omega_est`` (the same rotation rate, other axes). Linear velocity of
    the TRUE body origin, which sits at ``r = -R_cam_true t_X`` from the estimated one:
    ``v_true_origin = v_est_origin + omega_cam × r`` with ``omega_cam = R_cam_est omega_est``.

    Returns:
        ``(quat_wxyz (M,4), position_m (M,3), velocity_cam_m_s (M,3) | None,
        omega_body_rad_s (M,3) | None)`` of the estimate, referred to the true body frame.
    """
    R_X = np.asarray(R_X, dtype=float)
    t_X = np.asarray(t_X, dtype=float)
    q_est, p_est = as_rows(quat_est_wxyz, "quat_est_wxyz", 4), as_rows(position_est_m, "position_est_m", 3)
    w_est = None if omega_est_body_rad_s is None else as_rows(omega_est_body_rad_s, "omega_est_body_rad_s", 3)
    v_est = None if velocity_est_cam_m_s is None else as_rows(velocity_est_cam_m_s, "velocity_est_cam_m_s", 3)
    _check_paired(quat_est_wxyz=q_est, position_est_m=p_est, omega_est_body_rad_s=w_est, velocity_est_cam_m_s=v_est)
    R_est = quat_wxyz_to_matrix(q_est)
    R_al = R_est @ R_X.T
    lever = -(R_al @ t_X)  # from the estimated to the true body origin, cam frame
    position = p_est + lever
    velocity = omega = None
    if w_est is not None:
        omega = w_est @ R_X.T
        if v_est is not None:
            omega_cam = np.einsum("nij,nj->ni", R_est, w_est)
            velocity = v_est + np.cross(omega_cam, lever)
    return matrix_to_quat_wxyz(R_al).reshape(-1, 4), position, velocity, omega


# --------------------------------------------------------------------------- errors


@dataclass(frozen=True, eq=False)
class MotionErrors:
    """Per-frame errors of the paired samples (estimate minus truth).

    Attributes:
        t_s: (M,) truth timestamps, s.
        position_m: (M,3) ``p_est - p_true``, camera frame, m.
        attitude_rad: (M,3) eq. 17 components: rotation vector of ``R_est R_true^T``, camera
            frame (z about the viewing axis), rad; its norm is eq. 16's total angle.
        velocity_m_s: (M,3) ``v_est - v_true``, camera frame, m/s, or None (NaN rows where a
            side had no velocity at that sample).
        omega_rad_s: (M,3) ``omega_est - omega_true``, TRUE body frame, rad/s, or None (ditto).
        position_rel: (M,) ``|p_est - p_true| / |p_true|`` (SPEED's position score).
    """

    t_s: FloatArray
    position_m: FloatArray
    attitude_rad: FloatArray
    velocity_m_s: FloatArray | None
    omega_rad_s: FloatArray | None
    position_rel: FloatArray

    @property
    def attitude_total_rad(self) -> FloatArray:
        """(M,) eq. 16 total attitude error angle in [0, pi], rad."""
        return np.linalg.norm(self.attitude_rad, axis=1)

    @property
    def speed_score(self) -> FloatArray:
        """(M,) per-frame SPEED score: orientation error angle (rad) + relative position error.

        The ESA/Stanford Satellite Pose Estimation Challenge (Kisantal et al., "Satellite Pose
        Estimation Challenge: Dataset, Competition Design and Results", IEEE TAES 2020):
        ``s = 2 arccos|<q_est, q_true>| + |t_est - t_true| / |t_true|``; the run's score is
        the mean over frames.
        """
        return self.attitude_total_rad + self.position_rel


def motion_errors(
    t_s: ArrayLike,
    quat_true_wxyz: ArrayLike,
    position_true_m: ArrayLike,
    quat_est_wxyz: ArrayLike,
    position_est_m: ArrayLike,
    velocity_true_cam_m_s: ArrayLike | None = None,
    velocity_est_cam_m_s: ArrayLike | None = None,
    omega_true_body_rad_s: ArrayLike | None = None,
    omega_est_body_rad_s: ArrayLike | None = None,
) -> MotionErrors:
    """Errors of paired samples already referred to the same frames (arrays (M,·) row-paired).

    Velocity errors are computed when both sides give them (else None).
    """
    t = np.asarray(t_s, dtype=float).reshape(-1)
    p_true = as_rows(position_true_m, "position_true_m", 3)
    p_est = as_rows(position_est_m, "position_est_m", 3)
    q_true, q_est = as_rows(quat_true_wxyz, "quat_true_wxyz", 4), as_rows(quat_est_wxyz, "quat_est_wxyz", 4)
    rates = {name: None if value is None else as_rows(value, name, 3) for name, value in (
        ("velocity_true_cam_m_s", velocity_true_cam_m_s), ("velocity_est_cam_m_s", velocity_est_cam_m_s),
        ("omega_true_body_rad_s", omega_true_body_rad_s), ("omega_est_body_rad_s", omega_est_body_rad_s))}
    _check_paired(t_s=t, position_true_m=p_true, position_est_m=p_est, quat_true_wxyz=q_true, quat_est_wxyz=q_est,
                  **rates)
    dp = p_est - p_true
    range_m = np.linalg.norm(p_true, axis=1)
    if np.any(range_m == 0):
        # SPEED's relative error is undefined at the camera centre; say so rather than divide.
        raise TrackmeterError("a true position is at the camera centre: relative position error undefined")
    att = attitude_error_components(q_est, q_true).reshape(-1, 3)

    def diff(est: FloatArray | None, true: FloatArray | None) -> FloatArray | None:
        return None if est is None or true is None else est - true

    return MotionErrors(
        t,
        dp,
        att,
        diff(rates["velocity_est_cam_m_s"], rates["velocity_true_cam_m_s"]),
        diff(rates["omega_est_body_rad_s"], rates["omega_true_body_rad_s"]),
        np.linalg.norm(dp, axis=1) / range_m,
    )


def _check_paired(**rows: FloatArray | None) -> None:
    """Refuse arrays paired row by row (samples, or times and samples) of different lengths:
    numpy would pair a single row with every other, or say only "operands could not be
    broadcast". None (not given) is left out."""
    lengths = {name: len(a) for name, a in rows.items() if a is not None}
    if len(set(lengths.values())) > 1:
        raise TrackmeterError("paired samples differ in length: "
                              + ", ".join(f"{name} {n}" for name, n in lengths.items()))


def error_statistics(values: ArrayLike) -> dict[str, float]:
    """``{"rms", "max", "p95"}`` of signed errors (M,): root mean square, largest absolute
    value, and 95th percentile of the absolute value (numpy's linear interpolation)."""
    v = np.asarray(values, dtype=float).reshape(-1)
    if len(v) == 0:
        raise TrackmeterError("no errors to summarise")
    a = np.abs(v)
    return {"rms": float(np.sqrt(np.mean(v * v))), "max": float(a.max()), "p95": float(np.percentile(a, 95))}


def _axes(e: FloatArray, total_name: str, total: FloatArray) -> dict[str, dict[str, float]]:
    out = {axis: error_statistics(e[:, i]) for i, axis in enumerate("xyz")}
    out[total_name] = error_statistics(total)
    return out


def pose_nees(errors: MotionErrors, cov_pose: ArrayLike) -> FloatArray:
    """Normalised estimation error squared of each paired pose: ``e^T P^-1 e``, ``e`` the
    position error and the rotation vector of ``R_est R_true^T`` (:class:`MotionErrors`, both
    in the camera frame: the pose covariance's own parametrisation, a turn applied on the left)
    and ``P`` that pose's (6,6) covariance. Chi-square with 6 degrees of freedom when the
    covariance is honest (Bar-Shalom, Li and Kirubarajan 2001, section 5.4.2): median 5.35, 95 %
    below 12.59. Meaningful only where the estimate's body frame is the truth's (no alignment).

    Args:
        errors: the paired poses' errors, M rows.
        cov_pose: (M,6,6) their covariances (position m, rotation vector rad).

    Returns:
        (M,) NEES of each pose.
    """
    P = np.asarray(cov_pose, dtype=float).reshape(-1, 6, 6)
    e = np.concatenate([errors.position_m, errors.attitude_rad], axis=1)
    if len(P) != len(e):
        raise TrackmeterError(f"{len(P)} covariances for {len(e)} paired poses")
    return np.einsum("ni,ni->n", e, np.linalg.solve(P, e[:, :, None])[:, :, 0])


def usable_covariances(cov_pose: ArrayLike) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Which of ``cov_pose`` (M,6,6) can weigh an error: ``(finite, positive_definite)``, each
    (M,); a covariance is usable where both hold. Positive definite: symmetric to 1e-9 of its
    largest entry and every eigenvalue above 1e-12 of the largest (a zero, rank-deficient or
    negative matrix read from a file would make :func:`pose_nees` fail or go negative), with
    entries between the square roots of the smallest normal double and of the largest (beyond,
    the solve loses its digits: 1e-310 gave negative NEES)."""
    P = np.asarray(cov_pose, dtype=float).reshape(-1, 6, 6)
    finite = np.all(np.isfinite(P), axis=(1, 2))
    definite = np.zeros(len(P), dtype=bool)
    if finite.any():
        Q = P[finite]
        scale = np.max(np.abs(Q), axis=(1, 2))
        symmetric = np.max(np.abs(Q - np.transpose(Q, (0, 2, 1))), axis=(1, 2)) <= 1e-9 * scale
        eig = np.linalg.eigvalsh((Q + np.transpose(Q, (0, 2, 1))) / 2.0)
        info = np.finfo(float)
        in_range = (scale > np.sqrt(info.tiny)) & (scale < np.sqrt(info.max))
        definite[finite] = symmetric & in_range & (eig[:, 0] > 1e-12 * eig[:, -1]) & (eig[:, -1] > 0)
    return finite, definite


def nees_summary(values: ArrayLike) -> dict[str, float]:
    """How honest a run's pose covariance is from its poses' :func:`pose_nees`: ``median``
    (5.35 when honest; larger: overconfident), ``within_95`` (the fraction under chi-square(6)'s
    95th percentile, 12.59: 0.95 when honest) and ``poses``. Empty without a value."""
    from scipy.stats import chi2

    v = np.asarray(values, dtype=float).reshape(-1)
    if not v.size:
        return {}
    return {"median": float(np.median(v)), "within_95": float(np.mean(v <= chi2.ppf(0.95, 6))), "poses": int(v.size)}


def summarize(errors: MotionErrors, association: Association, pose_coverage: float | None = None) -> dict[str, Any]:
    """The ``trackmeter evaluate --json`` summary (SI units; DESIGN.md section 6):

    ``{"matched", "unmatched", "pose_coverage", "position_m": {x,y,z,norm}, "attitude_rad":
    {x,y,z,total}, "velocity_m_s": {x,y,z,norm}, "omega_rad_s": {x,y,z,norm}, "speed_score"}``,
    each leaf ``{"rms", "max", "p95"}``; the velocity entries over the samples where both sides
    have one, None (null) where there are none (every key is always there: a script reading the
    JSON need not guess its shape). ``pose_coverage``: of the run's frames after the
    settle (inside the truth's span), the share with a pose; None (null) when the estimate does
    not list its frames (a TUM file).
    """
    out: dict[str, object] = {
        "matched": int(len(errors.t_s)),
        "unmatched": int(association.unmatched),
        "pose_coverage": pose_coverage,
        "position_m": _axes(errors.position_m, "norm", np.linalg.norm(errors.position_m, axis=1)),
        "attitude_rad": _axes(errors.attitude_rad, "total", errors.attitude_total_rad),
    }
    for key, e in (("velocity_m_s", errors.velocity_m_s), ("omega_rad_s", errors.omega_rad_s)):
        out[key] = None
        if e is None:
            continue
        finite = e[np.all(np.isfinite(e), axis=1)]  # rows where both sides had a velocity
        if len(finite):
            out[key] = _axes(finite, "norm", np.linalg.norm(finite, axis=1))
    out["speed_score"] = float(np.mean(errors.speed_score))
    return out


# --------------------------------------------------------------------------- the whole evaluation


@dataclass(frozen=True, eq=False)
class Evaluation:
    """Result of :func:`evaluate`.

    Attributes:
        summary: the JSON summary (:func:`summarize`), plus ``"body_offset"``: with ``--align
            body`` ``{"T_bodytrue_bodyest": {"rotation_vector_rad", "translation_m"}}``, else None.
        errors: per-frame errors after settling.
        association: the pairs after the settle time, and the poses left without a partner there.
        body_offset: ``(R_bodytrue_bodyest, t_X)`` with ``--align body``, else None.
    """

    summary: dict[str, Any]  # JSON-like: nested dicts of floats (see summarize)
    errors: MotionErrors
    association: Association
    body_offset: tuple[FloatArray, FloatArray] | None


def _rates(track: PoseTrack, index: IntArray) -> tuple[FloatArray | None, FloatArray | None]:
    """Velocities of the selected samples when the track has any finite ones (else None);
    rows without them (an estimator still warming up) stay NaN and are left out of the
    velocity statistics."""
    out = []
    for name in ("velocity_cam_m_s", "omega_body_rad_s"):
        a = getattr(track, name, None)
        a = None if a is None else np.asarray(a, dtype=float)[index]
        out.append(a if a is not None and np.any(np.all(np.isfinite(a), axis=-1)) else None)
    return out[0], out[1]


def _near_any(t_s: FloatArray, times_s: FloatArray, tolerance_s: float) -> NDArray[np.bool_]:
    """(N,) whether each of ``t_s`` is within ``tolerance_s`` of one of ``times_s`` (K >= 1)."""
    times = np.sort(times_s)
    return np.abs(times[_nearest(times, t_s)] - t_s) <= tolerance_s + 1e-9


def evaluate(
    truth: PoseTrack,
    estimate: PoseTrack,
    params: EvaluateParams = EvaluateParams(),
    t_start_s: float | None = None,
    frame_times_s: ArrayLike | None = None,
) -> Evaluation:
    """Associate, align (``params.align``; "auto", whose meaning depends on the run's pose case,
    is "none" here: resolve it first with :func:`resolve_align`), skip ``params.settle_s``, and
    measure the errors.

    The settle time counts from ``t_start_s`` (the start of the run, e.g. the first row of a
    ``states.csv`` whether or not it had a pose) or, when None, from the first paired pose.
    ``frame_times_s`` (the run's frames, a ``states.csv``'s rows with a pose or not) gives the
    run's span, over which truth poses at a frame without an estimate are counted (``unmatched``;
    else every truth pose without one over the estimate's own span), and ``pose_coverage``: the
    share of those frames after the settle (inside the truth's span) that have a pose.

    Velocity metrics need finite ``velocity_cam_m_s`` and ``omega_body_rad_s`` on both
    sides (for the paired samples); otherwise only pose metrics are computed.

    Raises:
        TrackmeterError: no pair within the tolerance, or nothing left after the settle time.
    """
    align = resolve_align(params.align, None)
    assoc = associate(truth.t_s, estimate.t_s, params.tolerance_s)
    if assoc.matched == 0:
        raise TrackmeterError(
            f"no overlapping timestamps: no estimate within {params.tolerance_s:g} s of a truth pose "
            f"(truth {truth.t_s[0]:.3f}..{truth.t_s[-1]:.3f} s, estimate {estimate.t_s[0]:.3f}..{estimate.t_s[-1]:.3f} s)"
        )
    it, ie = assoc.index_truth, assoc.index_est
    # The settle is the run's: cut on its clock, which t_start_s is on (the truth's may be a few
    # ms off it, inside the tolerance, and the first pose after the settle would be lost).
    t_paired = estimate.t_s[ie]
    t0 = float(t_paired[0]) if t_start_s is None else float(t_start_s)
    keep = t_paired >= t0 + params.settle_s
    if not np.any(keep):
        raise TrackmeterError(f"no paired poses left after the settle time of {params.settle_s:g} s (the paired "
                              f"poses end {float(t_paired[-1]) - t0:.3g} s after the start)")
    it, ie = it[keep], ie[keep]
    # The poses left without a partner, counted over the span the pairs are: after the settle.
    t_from = t0 + params.settle_s
    paired_est = np.zeros(len(estimate.t_s), dtype=bool)
    paired_est[assoc.index_est] = True
    paired_truth = np.zeros(len(truth.t_s), dtype=bool)
    paired_truth[assoc.index_truth] = True
    frames = None if frame_times_s is None else np.asarray(frame_times_s, dtype=float).reshape(-1)
    span_from, span_to = estimate.t_s[0], estimate.t_s[-1]
    coverage = None
    if frames is not None and len(frames):
        span_from, span_to = min(span_from, frames[0]), max(span_to, frames[-1])
        tol = params.tolerance_s

        def in_window(t: FloatArray) -> int:  # after the settle, within the truth's span
            return int(np.count_nonzero((t >= t_from - 1e-9) & (t >= truth.t_s[0] - tol) & (t <= truth.t_s[-1] + tol)))

        counted_frames = in_window(frames)
        # The run's own poses, not the pairs: a truth sparser than the frames, or with gaps
        # (mocap), must not read as frames without a pose.
        coverage = min(in_window(estimate.t_s) / counted_frames, 1.0) if counted_frames else None
    in_span = (truth.t_s >= span_from - params.tolerance_s) & (truth.t_s <= span_to + params.tolerance_s)
    if frames is not None and len(frames):
        # Only where the run had a frame: a truth sampled faster than the run (motion capture)
        # is not a pose missing between two frames.
        in_span &= _near_any(truth.t_s, frames, params.tolerance_s)
    assoc = replace(assoc, index_truth=it, index_est=ie, dt_s=assoc.dt_s[keep],
                    unmatched_est=int(np.count_nonzero(~paired_est & (estimate.t_s >= t_from))),
                    unmatched_truth=int(np.count_nonzero(in_span & ~paired_truth & (truth.t_s >= t_from))))

    v_t, w_t = _rates(truth, it)
    v_e, w_e = _rates(estimate, ie)
    q_t, p_t = truth.quat_wxyz[it], truth.position_m[it]
    q_e, p_e = estimate.quat_wxyz[ie], estimate.position_m[ie]
    offset = None
    if align == "body":
        offset = estimate_body_offset(q_t, p_t, q_e, p_e)
        q_e, p_e, v_e, w_e = refer_to_true_body(q_e, p_e, *offset, v_e, w_e)
    if v_t is None or w_t is None or v_e is None or w_e is None:
        v_t = w_t = v_e = w_e = None
    errors = motion_errors(truth.t_s[it], q_t, p_t, q_e, p_e, v_t, v_e, w_t, w_e)
    summary = summarize(errors, assoc, coverage)
    summary["body_offset"] = None if offset is None else {"T_bodytrue_bodyest": {
        "rotation_vector_rad": rotation_from_matrix(offset[0]).as_rotvec().tolist(),
        "translation_m": np.asarray(offset[1], float).tolist()}}
    return Evaluation(summary, errors, assoc, offset)
