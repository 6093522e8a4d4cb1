"""Rigid-body pose from tracked 3D points: the paper's section 2.C, cases (a), (b) and (c).

All three cases end in the same problem: body-frame coordinates ``b_i`` of the tracked points
(a model) and their measurements ``p_i`` in the left camera frame, each with a covariance
``C_i`` from the stereo error propagation (paper eqs. 1-2). The pose ``T_cam_body`` minimises
the Mahalanobis sum (generalised least-squares absolute orientation)

    sum_i r_i^T W_i r_i,     r_i = R b_i + t - p_i,     W_i = (C_i + R Cb_i R^T)^-1

where ``Cb_i`` is the uncertainty of the model point (zero for an a-priori model). A stereo
point is ~20 times less precise along its viewing ray than across it, so the full 3x3
weights matter: the isotropic weighted Kabsch solution (:func:`absolute_orientation`) is only
the starting point; a few Gauss-Newton steps on SE(3) with the perturbation
``R <- exp([dtheta]x) R``, ``t <- t + dt`` (camera frame) finish it. The inverse of the
Gauss-Newton normal matrix is the first-order covariance of ``(t, dtheta)`` — the 6x6 pose
covariance, position in m and rotation vector in rad, both in the camera frame; ``dtheta`` is
the rotation vector of ``R_est R_true^T``, the per-axis error of the paper's eq. 17.

Robustness: a target that slides onto another surface is a gross outlier. With five or more
points a least-median-of-squares consensus over minimal triples (Rousseeuw & Leroy 1987) picks
a starting pose no single bad point can bend, then points whose Mahalanobis residual exceeds a
chi-square gate (3 degrees of freedom) are rejected and the fit is repeated on the rest. With
four points the consensus still runs but cannot single out one bad point (its criterion, the
4th-smallest residual, is then the largest: every triple's pose leaves one point off), and
with three nothing can be rejected: a gross mismatch bends the pose. With three it still shows
in the residual (:attr:`PoseFit.residual_per_dof`), which callers must check; with four the
robust scale takes it up instead (a large ``scale2``, the covariance inflated by it).

Case (a) builds the body frame from three points with
:func:`trackmeter.core.transforms.frame_from_three_points` (origin placed at the three points'
centroid); case (c) averages the points tracked while the object is held still into a model
whose frame is the camera frame at that time, origin at the points' centroid.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from itertools import combinations
from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from trackmeter.core.checks import covariances, finite_rows, rotation_matrix
from trackmeter.core.params import check_params, param
from trackmeter.core.transforms import absolute_orientation, frame_from_three_points, procrustes_rotation, skew
from trackmeter.errors import TrackmeterError

FloatArray = NDArray[np.float64]

#: Median of the chi-square distribution with 3 degrees of freedom (robust scale of d²).
_CHI2_3_MEDIAN = float(chi2.median(3))


@dataclass(frozen=True)
class PoseParams:
    """Tunables of the motion estimation (paper section 2.C) and of its model handling."""

    min_points: int = param(3, "fewest measured model points for a pose (3 is the minimum that fixes it)", min=3)
    outlier_probability: float = param(
        0.999, "chi-square (3 dof) gate on a point's Mahalanobis residual; beyond it the point is an outlier",
        min=0.9, max=0.9999999,
    )
    ransac_trials: int = param(80, "minimal triples tried by the least-median-of-squares consensus", min=1)
    refine_iterations: int = param(3, "Gauss-Newton iterations of the weighted absolute orientation", min=1, max=20)
    robust_scale: bool = param(
        True, "inflate the point covariances by the robust residual scale when they are too optimistic"
    )
    point_sigma_floor_m: float = param(
        0.0003, "isotropic std added to every point's stereo covariance: tracking and surface errors the "
        "stereo propagation does not see (also keeps the covariances invertible), m", min=0.0,
    )
    min_triangle_m: float = param(
        0.05, "case (a): the third frame point must lie at least this far off the line of the first two, m", min=0.0
    )
    max_residual_per_dof: float = param(
        25.0, "a pose whose inlier residual exceeds this chi-square per degree of freedom (after the robust "
        "scale) is refused: with 3 points a gross mismatch cannot be rejected, only detected", min=1.0,
    )
    bind_sigma_floor_m: float = param(
        0.003, "case (b) progressive binding: isotropic std added to each located a-priori point's "
        "covariance when the binding's residual is TESTED against max_residual_per_dof (not when it is "
        "fitted): a corner's patch measures the faces around it, an error averaging over frames does "
        "not remove, m", min=0.0,
    )
    apriori_bias_sigma_m: float = param(
        0.0015, "case (b): isotropic std of an a-priori point's own error (a corner's patch measures the faces "
        "around it), common to every frame it is seen in: the body frame the a-priori points define keeps it, "
        "and the REPORTED pose covariance adds that frame error (sigma² (sum J^T J)^-1 over the a-priori "
        "inliers not made at a projection through the pose); the fit and the pose do not change; 0: the points' noise alone, m", min=0.0,
    )
    model_drift_m_per_sqrt_s: float = param(
        0.00035, "case (b): rate of the random walk of a model located through the pose it gives (grown points, "
        "targets remade through the pose), added to the REPORTED pose covariance from the last frame that "
        "independently located a-priori points determined the frame (or the first pose): q² dt per position "
        "axis, (q / r)² dt per rotation axis (r: the a-priori points' rms distance from their centroid); the "
        "automatic targets' median slide, 1.10 mm after 10 s, over sqrt(10 s) (1.2-1.5 times the per-axis rate "
        "of a random walk with that median: on the safe side); 0: none, m/sqrt(s)", min=0.0,
    )
    frame_min_age_frames: int = param(
        12, "case (a): only points tracked for at least this many frames define the frame and the first model",
        min=0,
    )
    frame_hold: bool = param(
        False, "case (a): undo the rigid part of each model refinement (hold_frame), so averaging the points' "
        "observations sharpens the model without moving the body frame (estec: 60 s better, first 20 s worse)",
    )
    redefine_after_s: float = param(
        3.0, "case (a): without a pose for this long, the frame is given up and defined anew from the "
        "points tracked then (a new body frame), s", min=0.0,
    )
    model_refine: bool = param(
        True, "average the body coordinates of measured (not a-priori) model points over time"
    )
    bind_progressively: bool = param(
        True, "case (b): while fewer than min_points a-priori points are measured at once, track in a "
        "provisional case-(a) frame and locate each a-priori point in it as it is seen; bind the model "
        "once min_points are located (seen at different times)",
    )
    anchor_time_s: float = param(
        0.0, "case (b): time constant with which the grown model is moved onto the a-priori points' frame "
        "as the a-priori points seen reveal its drift, s (0: never)", min=0.0,
    )
    anchor_moves_history: bool = param(
        True, "case (b): each step of the anchoring also moves the poses the velocities (and the coast's "
        "centre of mass) are fitted to, so that a correction of the frame is not read as motion"
    )
    anchor_memory_s: float = param(
        1.0, "case (b): how long the a-priori points' evidence of the grown model's drift is remembered "
        "(exponential forgetting), s", min=0.04,
    )
    anchor_prior_m: float = param(
        0.01, "case (b): expected drift of the grown model's frame, position (1 sigma; directions the "
        "a-priori points do not see stay put; tiny: the grown model's frame is held), m", min=1e-12,
    )
    anchor_prior_rad: float = param(
        0.02, "case (b): expected drift of the grown model's frame, attitude (1 sigma), rad", min=1e-12,
    )
    slide_sigma_m_per_sqrt_s: float = param(
        0.0, "how fast a grown model point's target wanders on the surface (random walk: std after t seconds "
        "is this times sqrt(t)); its body coordinates follow it and it weighs less in the pose, m/sqrt(s)", min=0.0,
    )
    join_after_frames: int = param(
        1, "a new target joins the model after this many consecutive consistent frames", min=1
    )
    model_pose_error_correlated: bool = param(
        False, "a grown model point's share of the pose error is common to all its observations and is not "
        "averaged away (fuse_point_correlated): points grown through drifting poses stay as uncertain as "
        "those poses, so the a-priori points keep their say; off: observations fused as independent"
    )
    still_time_s: float = param(2.0, "case (c): how long the object must be held still to acquire a model, s", min=0.0)
    still_max_d2: float = param(
        9.0, "case (c): largest mean squared Mahalanobis scatter of a point about its mean still counted as "
        "'still' (3 when perfectly still)", min=0.0,
    )
    recover_model_points: bool = param(
        True, "re-lock lost model points at their projection through the current pose (paper 2.D)"
    )
    relock_stored: bool = param(
        False, "a grown model point whose target was dropped is re-locked by searching for that target's own "
        "templates (the same surface texture) at its projection, and only where they are not found re-made from "
        "whatever lies there (a loop closure: the texture the point was grown from, not the model's drift)"
    )
    recovery_interval_frames: int = param(5, "frames between two re-lock attempts of one model point", min=1)
    apriori_remake_after_s: float = param(
        1.0, "an a-priori model point's target lost this long is re-made at its projection through a measured "
        "pose (its old template, of another view, is given up), s; 0: kept and searched for with its own "
        "template only", min=0.0,
    )
    max_model_points: int = param(
        64, "grown model points kept (re-locked by measurement at their projection after their target was "
        "dropped); beyond this the longest unseen go", min=3,
    )
    operator_hidden_m: float = param(
        0.03, "simulated operator (SelectModelPoints): a model point whose stereo measurement lies farther than "
        "this from its true position is hidden behind another surface and not clicked, m", min=0.0,
    )
    operator_reselect_s: float = param(
        1.0, "repeating simulated operator: clicks the visible model points not tracked again after the pose "
        "has been invalid this long (and at most once per this interval), s", min=0.0,
    )
    operator_reserve_targets: int = param(
        8, "grown model points are re-made as targets only while this many target slots stay free (for the "
        "operator's clicks and automatic selection)", min=0,
    )
    coast_max_s: float = param(
        2.0, "after the pose is lost, model points are still re-locked this long at their projection through "
        "the last pose carried forward at its last velocities, s", min=0.0,
    )
    coast_sigma_m_per_s: float = param(
        0.02, "growth rate of the carried-forward pose's position uncertainty (1 sigma), m/s", min=0.0,
    )
    coast_sigma_rad_per_s: float = param(
        0.05, "growth rate of the carried-forward pose's attitude uncertainty (1 sigma), rad/s", min=0.0,
    )
    max_attitude_sigma_deg: float = param(
        5.0, "a measured pose whose attitude 1-sigma exceeds this is undetermined (e.g. nearly collinear points): "
        "invalid, deg", min=0.0,
    )
    max_position_sigma_m: float = param(0.05, "... or whose position 1-sigma exceeds this, m", min=0.0)
    coast_valid_attitude_sigma_deg: float = param(
        5.0, "with no model point measured, the pose carried on the motion model (dynamics.coast_pose) is "
        "output as valid, flagged coasting, while its attitude 1-sigma stays below this, deg (0: never)", min=0.0,
    )
    coast_valid_position_sigma_m: float = param(
        0.05, "... and while its position 1-sigma stays below this, m", min=0.0,
    )
    coast_fit_centre_of_mass: bool = param(
        True, "coasting: bound the centre of mass's speed by fitting it to the poses before the loss "
        "(dynamics.fit_centre_of_mass) instead of assuming the worst the lever allows",
    )
    coast_centre_of_mass_window_s: float = param(
        10.0, "coasting: fit the centre of mass to the measured poses of this many seconds before the loss "
        "(the same body frame), s (0: to the velocity window's)", min=0.0,
    )
    coast_velocity_sigma_m_s: float = param(
        0.003, "coasting: 1-sigma error of the estimated origin velocity, per axis, m/s", min=0.0,
    )
    coast_omega_sigma_rad_s: float = param(
        0.004, "coasting: 1-sigma error of the estimated body angular velocity, per axis, rad/s", min=0.0,
    )
    coast_lever_m: float = param(
        0.5, "coasting (and the velocity's free-body fit): largest distance of the body origin from the centre "
        "of mass the body turns about, m",
        min=0.0,
    )
    coast_rejoin_attitude_sigma_deg: float = param(
        5.0, "while the coasted pose's attitude 1-sigma is below this, newly measured targets join the model "
        "through it (the pose goes on in the same body frame when the light returns; case a keeps its "
        "frame), deg (0: never)", min=0.0,
    )
    coast_rejoin_position_sigma_m: float = param(
        0.05, "... and while its position 1-sigma is below this, m", min=0.0,
    )
    coast_blend_s: float = param(
        0.3, "when points are measured again after coasting, the output moves from the coasted pose onto the "
        "measured one with this time constant (no jump), s (0: at once)", min=0.0,
    )
    handover_hold: bool = param(
        False, "when measured model points are lost, move the survivors' body coordinates rigidly so the pose "
        "fitted to them alone, on their recent mean observations, is the whole set's (handover_offset): "
        "no jump",
    )
    handover_window_s: float = param(
        0.5, "time constant of the running mean of each point's residual that handover_hold uses, s", min=0.04,
    )
    handover_probability: float = param(
        0.99, "handover_hold moves the survivors only when their disagreement with the whole set passes this "
        "chi-square (6 dof) probability (Hausman's test); smaller ones are noise", min=0.0, max=0.9999999,
    )
    max_recoveries_per_frame: int = param(4, "re-lock attempts per frame at most (bounds the step time)", min=0)
    recovery_margin_px: float = param(8.0, "a projected model point must lie this far inside both images, px",
                                      min=0.0)

    def __post_init__(self) -> None:
        check_params(self)  # declared ranges and choices, as the config loader checks them


@dataclass(frozen=True, eq=False)
class PoseFit:
    """A weighted least-squares pose and what it used.

    Attributes:
        R_cam_body: (3,3) rotation, body to camera.
        t_cam_body: (3,) body origin in the camera frame, m.
        cov: (6,6) covariance of (t m, rotation vector rad), camera frame.
        inliers: (N,) bool, the points used in the final fit.
        d2: (N,) squared Mahalanobis residual of every point against the final pose (for an
            outlier, against its predictive covariance).
        scale2: factor the point covariances were inflated by (>= 1; 1 when they were honest).

    With 3 or 4 points no outlier can be rejected (module docstring). With 3, check
    :attr:`residual_per_dof` against a limit (the engine uses ``PoseParams.max_residual_per_dof``)
    before trusting the pose; with 4 a mismatch inflates ``scale2`` (and ``cov``) instead.
    """

    R_cam_body: FloatArray
    t_cam_body: FloatArray
    cov: FloatArray
    inliers: NDArray[np.bool_]
    d2: FloatArray
    scale2: float = 1.0

    @property
    def residual_per_dof(self) -> float:
        """Chi-square of the inliers per degree of freedom, after the robust scale:
        ``sum(d2[inliers]) / (3 k - 6) / max(scale2, 1)`` for ``k`` inliers (3 coordinates a
        point, 6 pose unknowns). About 1 when the points agree with the model within their
        covariances; far above it when a point is a gross mismatch that could not be rejected
        (3 points: 3 of their 9 coordinates are redundant, so a mismatch bends the pose but
        still shows here, and ``scale2`` stays 1). nan when there is no redundancy (``k < 3``)."""
        dof = 3 * int(np.count_nonzero(self.inliers)) - 6
        if dof <= 0:
            return float("nan")
        return float(np.sum(self.d2[self.inliers])) / dof / max(self.scale2, 1.0)

    @property
    def T_cam_body(self) -> FloatArray:
        T = np.eye(4)
        T[:3, :3] = self.R_cam_body
        T[:3, 3] = self.t_cam_body
        return T


def _cond_above(H: FloatArray, limit: float) -> bool:
    """``np.linalg.cond(H) > limit`` for one square matrix (2-norm condition number
    ``s_max / s_min`` of the singular values, 0/0 counting as inf as in cond), straight from
    the SVD without cond's ~15 us of array checks (it runs every Gauss-Newton step)."""
    s_max, s_min = (float(x) for x in np.linalg.svd(H, compute_uv=False)[[0, -1]])
    return s_min == 0.0 or s_max / s_min > limit


def position_jacobians(points_body: FloatArray, R_cam_body: FloatArray) -> FloatArray:
    """(...,3,6) derivative of body points' camera positions ``R b + t`` (``points_body``
    (...,3)) by the pose error ``(dt, dtheta)``, camera frame, to first order:
    ``d(R b + t) = dt - [R b]x dtheta``, i.e. ``[I | -[R b]x]``."""
    Rb = np.asarray(points_body, dtype=float) @ R_cam_body.T
    return np.concatenate([np.broadcast_to(np.eye(3), Rb.shape[:-1] + (3, 3)), -skew(Rb)], axis=-1)


def _weights(R: FloatArray, cov_cam: FloatArray, cov_body: FloatArray | None) -> FloatArray:
    C = cov_cam if cov_body is None else cov_cam + R @ cov_body @ R.T
    return cast(FloatArray, np.linalg.inv(C))  # numpy's stubs: floating[Any]


def mahalanobis_d2(
    R_cam_body: FloatArray,
    t_cam_body: FloatArray,
    points_body: FloatArray,
    points_cam: FloatArray,
    cov_cam: FloatArray,
    cov_body: FloatArray | None = None,
) -> FloatArray:
    """Squared Mahalanobis residual (N,) of each point against a pose: ``r^T (C + R Cb R^T)^-1 r``."""
    r = points_body @ R_cam_body.T + t_cam_body - points_cam
    W = _weights(R_cam_body, cov_cam, cov_body)
    return np.einsum("ni,nij,nj->n", r, W, r)


def solve_pose(
    points_body: ArrayLike,
    points_cam: ArrayLike,
    cov_cam: ArrayLike,
    cov_body: ArrayLike | None = None,
    initial: tuple[FloatArray, FloatArray] | None = None,
    iterations: int = 3,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Generalised least-squares absolute orientation with full 3x3 point covariances.

    Minimises ``sum_i r_i^T W_i r_i`` (module docstring) by Gauss-Newton on SE(3), starting
    from ``initial`` or from the isotropic weighted Kabsch solution (weights ``1/trace C_i``).

    Args:
        points_body: (N,3) model points, body frame, m.
        points_cam: (N,3) measured points, camera frame, m.
        cov_cam: (N,3,3) covariances of ``points_cam``, m².
        cov_body: (N,3,3) covariances of the model points (body frame), m², or None (exact).
        initial: ``(R_cam_body, t_cam_body)`` to start from.
        iterations: Gauss-Newton steps.

    Returns:
        ``(R_cam_body (3,3), t_cam_body (3,), cov (6,6))`` with ``cov`` the first-order
        covariance of (t, rotation vector), camera frame — the inverse normal matrix.

    Raises:
        TrackmeterError: fewer than 3 points, a degenerate (collinear) configuration, or a
            malformed argument (wrong shape, a non-finite value, a covariance that is not
            symmetric positive-definite; :func:`checked_points`).
    """
    b, p, C, Cb = checked_points(points_body, points_cam, cov_cam, cov_body)
    return _solve_pose(b, p, C, Cb, checked_initial(initial), iterations)


def checked_points(
    points_body: ArrayLike, points_cam: ArrayLike, cov_cam: ArrayLike, cov_body: ArrayLike | None = None
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray | None]:
    """The arguments of :func:`solve_pose` and :func:`robust_pose` as float arrays, checked.

    ``points_body`` and ``points_cam`` must be (N,3) and finite, ``cov_cam`` (N,3,3) symmetric
    positive-definite (its inverse weighs each point), ``cov_body`` None or (N,3,3) symmetric
    positive semi-definite (zero: an exact a-priori model point). Checked once at the public
    entry; the fits inside (robust_pose's refits) take the checked arrays as they are.

    Raises:
        TrackmeterError: naming the argument, the expected shape and the offending row,
            e.g. ``"points_cam[4] is not finite: [0.1, nan, 3.5]"``.
    """
    b = finite_rows(points_body, "points_body", (None, 3))
    n = len(b)
    p = finite_rows(points_cam, "points_cam", (n, 3))
    C = covariances(cov_cam, "cov_cam", n, definite=True)
    Cb = None if cov_body is None else covariances(cov_body, "cov_body", n, definite=False)
    return b, p, C, Cb


def checked_initial(initial: tuple[ArrayLike, ArrayLike] | None) -> tuple[FloatArray, FloatArray] | None:
    """``initial`` (``(R_cam_body, t_cam_body)`` or None) as float arrays, checked: a (3,3)
    rotation and a finite (3,) position.

    Raises:
        TrackmeterError: ``"initial R_cam_body must be a rotation ..."`` and the like.
    """
    if initial is None:
        return None
    if not (isinstance(initial, (tuple, list)) and len(initial) == 2):
        raise TrackmeterError(f"initial must be a pair (R_cam_body (3,3), t_cam_body (3,)), got "
                              f"{type(initial).__name__}" + (f" of {len(initial)}" if isinstance(initial, (tuple, list))
                                                             else f" of shape {np.shape(initial)}"))
    return (rotation_matrix(initial[0], "initial R_cam_body"),
            finite_rows(initial[1], "initial t_cam_body", (3,)))


def _solve_pose(
    b: FloatArray,
    p: FloatArray,
    C: FloatArray,
    Cb: FloatArray | None,
    initial: tuple[FloatArray, FloatArray] | None,
    iterations: int,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`solve_pose` on arrays already checked by :func:`checked_points`."""
    if len(b) < 3:
        raise TrackmeterError(f"a pose needs at least 3 points, got {len(b)}")
    if initial is None:
        R, t = absolute_orientation(p, b, 1.0 / np.trace(C, axis1=1, axis2=2))
    else:
        R, t = np.array(initial[0], dtype=float), np.array(initial[1], dtype=float)
    J = np.zeros((len(b), 3, 6))  # (N,3,6) d r_i / d(t, rotation vector): [I | -[R b_i]x]
    J[:, :, :3] = np.eye(3)
    for _ in range(max(1, iterations)):
        W = _weights(R, C, Cb)
        Rb = b @ R.T
        r = Rb + t - p
        J[:, :, 3:] = -skew(Rb)
        JtW = np.transpose(J, (0, 2, 1)) @ W
        H = np.einsum("nij,njk->ik", JtW, J)
        g = np.einsum("nij,nj->i", JtW, r)
        if _cond_above(H, 1e12):
            raise TrackmeterError("pose is undetermined: the points are (nearly) collinear")
        delta = -np.linalg.solve(H, g)
        t = t + delta[:3]
        R = Rotation.from_rotvec(delta[3:]).as_matrix() @ R
        if np.linalg.norm(delta) < 1e-12:
            break
    # Normal matrix at the solution, for the covariance.
    W = _weights(R, C, Cb)
    J[:, :, 3:] = -skew(b @ R.T)
    H = np.einsum("nji,njk,nkl->il", J, W, J)
    cov = np.linalg.inv(H)
    return R, t, 0.5 * (cov + cov.T)


def _kabsch_batch(a: FloatArray, b: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Unweighted Kabsch for K triples at once: a, b (K,3,3) -> R (K,3,3), t (K,3), sigma2 (K,)."""
    ca = a.mean(axis=1)
    cb = b.mean(axis=1)
    H = np.transpose(a - ca[:, None], (0, 2, 1)) @ (b - cb[:, None])
    R, S = procrustes_rotation(H)
    t = ca - np.einsum("kij,kj->ki", R, cb)
    return R, t, S[:, 1]


@lru_cache(maxsize=8)
def _chi2_3_ppf(probability: float) -> float:
    """``chi2.ppf(probability, 3)``, once per value (scipy's ppf costs ~0.1 ms a call)."""
    return float(chi2.ppf(probability, 3))


def _random_triples(n: int, trials: int, seed: int) -> NDArray[np.int64]:
    """(trials, 3) index triples, exactly ``[rng.choice(n, 3, replace=False) for _ in range(trials)]``
    with ``rng = np.random.default_rng(seed)``, drawn at once (the per-call overhead of 80
    ``choice`` calls was a third of :func:`robust_pose`).

    For ``n <= 10000`` numpy's ``Generator.choice`` runs Floyd's algorithm and shuffles the three
    (``_generator.pyx``): five bounded draws per triple, each ``(u * (j + 1)) >> 32`` for the
    next 32-bit output ``u`` (Lemire's method), redrawn only when the low word is below ``j + 1``
    (probability < n / 2^32). Those outputs come from the same generator as ``integers(0, 2**32,
    dtype=uint32)``. Where a redraw would be due, or ``n`` is outside that path, the triples are
    drawn by ``choice`` itself. ``tests/test_pose.py`` checks the equality.
    """
    if 4 <= n <= 10000:
        u = np.random.default_rng(seed).integers(0, 2**32, size=(trials, 5), dtype=np.uint32).astype(np.uint64)
        # range of each draw: Floyd's j = n-3, n-2, n-1 (0..j), then the shuffle's 0..2 and 0..1
        excl = np.array([n - 2, n - 1, n, 3, 2], dtype=np.uint64)
        m = u * excl
        if not ((m & np.uint64(0xFFFFFFFF)) < excl).any():
            v = (m >> np.uint64(32)).astype(np.int64)
            a, b, c = v[:, 0], v[:, 1].copy(), v[:, 2].copy()
            b[b == a] = n - 2  # Floyd: a value already taken is replaced by j
            c[(c == a) | (c == b)] = n - 1
            d = np.stack([a, b, c], axis=1)
            rows = np.arange(trials)
            for i, k in ((2, v[:, 3]), (1, v[:, 4])):  # Fisher-Yates: swap element i with k <= i
                t = d[rows, k].copy()
                d[rows, k] = d[:, i]
                d[:, i] = t
            return d
    rng = np.random.default_rng(seed)
    return np.array([rng.choice(n, 3, replace=False) for _ in range(trials)])


def robust_pose(
    points_body: ArrayLike,
    points_cam: ArrayLike,
    cov_cam: ArrayLike,
    cov_body: ArrayLike | None = None,
    params: PoseParams = PoseParams(),
    initial: tuple[FloatArray, FloatArray] | None = None,
    seed: int = 0,
) -> PoseFit:
    """Pose robust to gross outliers: LMedS consensus over minimal triples, then gated GLS.

    1. With N >= 4 points, try up to ``params.ransac_trials`` triples (all of them when there
       are fewer; deterministic for a given ``seed``) plus ``initial`` when given; keep the
       pose whose median squared Mahalanobis residual over all points (at least the 4th
       smallest: a triple fits itself exactly) is smallest. A single bad point is singled
       out from N >= 5 on: with 4, the 4th-smallest residual is the largest, and every
       triple's pose leaves one point off.
    2. Robust scale ``s² = median(d²) / median(chi2_3)`` (only ever >= 1: honest covariances are
       kept); points with ``d² > s² chi2_3(outlier_probability)`` are outliers.
    3. :func:`solve_pose` on the inliers; re-gate every point against the refined pose (a
       left-out point by its predictive covariance) and refit until the set is stable.

    With exactly 3 points no point can be rejected: all are inliers, and a gross mismatch bends
    the pose without inflating its covariance (``scale2`` stays 1). The fit is not exact (9
    coordinates, 6 unknowns), so the mismatch shows in :attr:`PoseFit.residual_per_dof`, which
    the caller must check. With 4 points a single bad point is not rejected either; the robust
    scale takes it up (a large ``scale2``, by which the covariance is inflated).

    Args:
        points_body, points_cam, cov_cam, cov_body: as :func:`solve_pose`.
        params: thresholds.
        initial: a pose hypothesis, e.g. the previous frame's.
        seed: of the triple sampler.

    Returns:
        A :class:`PoseFit`; its covariance is scaled by ``scale2``.

    Raises:
        TrackmeterError: fewer than 3 points, fewer than 3 inliers in a non-degenerate layout,
            or a malformed argument (:func:`checked_points`).
    """
    b, p, C, Cb = checked_points(points_body, points_cam, cov_cam, cov_body)
    initial = checked_initial(initial)
    n = len(b)
    if n < 3:
        raise TrackmeterError(f"a pose needs at least 3 points, got {n}")
    gate = _chi2_3_ppf(params.outlier_probability)
    inliers = np.ones(n, dtype=bool)
    # Three points have one optimum, which the closed form (weighted Kabsch) starts next to; from
    # a caller's old pose, tens of degrees off after a short loss, refine_iterations steps ended
    # short of it (30 deg: 1.7 deg of error instead of 1.0) or in a false minimum (45 deg: 14).
    start = initial if n >= 4 else None
    if n >= 4:
        all_triples = n * (n - 1) * (n - 2) // 6
        if all_triples <= params.ransac_trials:
            idx = np.array(list(combinations(range(n), 3)))
        else:
            idx = _random_triples(n, params.ransac_trials, seed)
        R_k, t_k, s1 = _kabsch_batch(p[idx], b[idx])
        ok = s1 > 1e-6  # collinear triples fix no rotation
        R_k, t_k = R_k[ok], t_k[ok]
        if initial is not None:
            R_k = np.concatenate([R_k, np.asarray(initial[0], dtype=float)[None]])
            t_k = np.concatenate([t_k, np.asarray(initial[1], dtype=float)[None]])
        if len(R_k):
            # Residuals of every point under every hypothesis, weighted by the measurement
            # covariance alone (cheap; the model's own uncertainty is added in the refinement).
            W = np.linalg.inv(C)
            r = np.einsum("kij,nj->kni", R_k, b) + t_k[:, None, :] - p[None]
            d2 = np.einsum("kni,nij,knj->kn", r, W, r)
            # The median, but never below the 4th-smallest residual: a minimal triple fits itself
            # exactly, so with 4-7 points the median can be one of its own zeros, and a triple
            # holding an outlier (its pose rotated about the line of the other two) would tie
            # with the true pose and win by its place in the list (Rousseeuw & Leroy's LMS takes
            # the h-th order statistic, h = [n/2] + [(p+1)/2], for the same reason).
            crit = np.maximum(np.median(d2, axis=1), np.partition(d2, min(3, n - 1), axis=1)[:, min(3, n - 1)])
            best = int(np.argmin(crit))
            start = (R_k[best], t_k[best])
            med = float(np.median(d2[best]))
            scale2 = max(1.0, med / _CHI2_3_MEDIAN)
            inliers = d2[best] <= gate * scale2
            if inliers.sum() < 3:
                inliers = d2[best] <= np.sort(d2[best])[2]
    scale2 = 1.0
    R, t, cov = _solve_pose(b[inliers], p[inliers], C[inliers], None if Cb is None else Cb[inliers],
                           start, params.refine_iterations)
    for _ in range(6):
        d2 = _gating_d2(R, t, cov, b, p, C, Cb, inliers)
        if n < 4:
            break
        scale2 = max(1.0, float(np.median(d2[inliers])) / _CHI2_3_MEDIAN) if params.robust_scale else 1.0
        new_inliers = d2 <= gate * scale2
        if new_inliers.sum() < 3 or np.array_equal(new_inliers, inliers):
            break
        inliers = new_inliers
        R, t, cov = _solve_pose(b[inliers], p[inliers], C[inliers], None if Cb is None else Cb[inliers],
                               (R, t), params.refine_iterations)
    else:  # the last refit is not gated yet (a break leaves d2 of the final pose and set)
        d2 = _gating_d2(R, t, cov, b, p, C, Cb, inliers)
    return PoseFit(R, t, cov * scale2, inliers, d2, scale2)


def _gating_d2(R: FloatArray, t: FloatArray, cov: FloatArray, b: FloatArray, p: FloatArray, C: FloatArray,
               Cb: FloatArray | None, inliers: NDArray[np.bool_]) -> FloatArray:
    """Squared Mahalanobis residuals for gating. A point left out of the fit is judged by its
    PREDICTIVE covariance ``C + R Cb R^T + J cov J^T`` (the pose from the other points is
    uncertain too): a far-out point the others barely constrain would otherwise never get back in."""
    d2 = mahalanobis_d2(R, t, b, p, C, Cb)
    out = np.flatnonzero(~inliers)
    if len(out):
        Rb = b[out] @ R.T
        J = position_jacobians(b[out], R)
        Cp = C[out] + J @ cov @ np.transpose(J, (0, 2, 1))
        if Cb is not None:
            Cp = Cp + R @ Cb[out] @ R.T
        r = Rb + t - p[out]
        d2[out] = np.einsum("ni,nij,nj->n", r, np.linalg.inv(Cp), r)
    return d2


# --------------------------------------------------------------------------- model frames


def three_point_body_frame(p1: ArrayLike, p2: ArrayLike, p3: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Case (a) body frame ``(R_a_body, origin_a)``: axes of the paper's three-point frame
    (x toward p2, xy-plane through p3; :func:`frame_from_three_points`), origin at the
    centroid of the three points (the output the paper gives: centroid + quaternion)."""
    R, _ = frame_from_three_points(p1, p2, p3)
    origin = (np.asarray(p1, dtype=float) + np.asarray(p2, dtype=float) + np.asarray(p3, dtype=float)) / 3.0
    return R, origin


def to_body(R_a_body: FloatArray, origin_a: FloatArray, points_a: ArrayLike, cov_a: ArrayLike | None = None
            ) -> tuple[FloatArray, FloatArray | None]:
    """Express points (N,3) and covariances (N,3,3) of frame a in a body frame given by its
    axes ``R_a_body`` and origin in a: ``b = R^T (p - o)``, ``Cb = R^T C R``."""
    p = np.asarray(points_a, dtype=float).reshape(-1, 3)
    b = (p - origin_a) @ R_a_body
    if cov_a is None:
        return b, None
    C = np.asarray(cov_a, dtype=float).reshape(-1, 3, 3)
    return b, R_a_body.T @ C @ R_a_body


def choose_frame_points(points: ArrayLike, min_offset_m: float) -> tuple[int, int, int] | None:
    """Case (a): indices of the three frame points, in the order given (selection order).

    The first triple in that order (lexicographic in the indices) where point 2 is at least
    ``min_offset_m`` from point 1 and point 3 at least ``min_offset_m`` off the line through 1
    and 2: point 1 is the first point given unless no later pair makes a frame with it, and so
    on. None when no such triple exists (all points (nearly) collinear or clustered).
    """
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    for i in range(len(p)):
        for j in range(i + 1, len(p)):
            x = p[j] - p[i]
            nx = np.linalg.norm(x)
            if nx < max(min_offset_m, 1e-9):
                continue
            for k in range(j + 1, len(p)):
                off = np.linalg.norm(np.cross(x / nx, p[k] - p[i]))
                if off >= max(min_offset_m, 1e-9):
                    return i, j, k
    return None


def fuse_point(b_old: FloatArray, C_old: FloatArray, b_new: FloatArray, C_new: FloatArray
               ) -> tuple[FloatArray, FloatArray]:
    """Information-weighted mean of two estimates (3,) of one body point with covariances (3,3):
    ``C = (C_old^-1 + C_new^-1)^-1``, ``b = C (C_old^-1 b_old + C_new^-1 b_new)``."""
    W_old = np.linalg.inv(C_old)
    W_new = np.linalg.inv(C_new)
    C = np.linalg.inv(W_old + W_new)
    return C @ (W_old @ b_old + W_new @ b_new), 0.5 * (C + C.T)


def fuse_point_correlated(
    b_old: FloatArray, Cm_old: FloatArray, L_old: FloatArray,
    b_new: FloatArray, Cm_new: FloatArray, L_new: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Fuse two estimates of one body point whose errors share the pose's error.

    A body point observed through an estimated pose, ``b = R^T (p - t)``, carries two errors:
    the measurement's, independent from frame to frame (covariance ``Cm``), and the pose's,
    ``L z`` with ``z`` the pose error in whitened units (``L`` (3,K) maps it to the point). The
    pose errors of consecutive frames are nearly the same (they come from the same model
    points), so averaging observations must not shrink that part: :func:`fuse_point` would, and
    a grown point would soon claim more precision than the pose it was measured through.

    Here ``z`` is taken as common to both estimates (perfect correlation). With the weights of
    the usual information mean, ``A = C Cold^-1``, ``B = C Cnew^-1``, ``C = (Cold^-1 + Cnew^-1)^-1``
    (``C* = Cm* + L* L*^T``), the fused point ``b = A b_old + B b_new`` has the exact error
    decomposition ``Cm = A Cm_old A^T + B Cm_new B^T`` and ``L = A L_old + B L_new``: with equal
    ``L`` the pose part stays as it is, with ``L = 0`` this is :func:`fuse_point`.

    Every argument may carry the same leading dimensions (N points fused at once, one call
    instead of N: the engine refines all its grown points every frame).

    Args:
        b_old, b_new: (...,3) estimates, body frame, m.
        Cm_old, Cm_new: (...,3,3) independent (measurement) covariances, m².
        L_old, L_new: (...,3,K) pose-error factors, m per unit of ``z``.

    Returns:
        ``(b (...,3), Cm (...,3,3), L (...,3,K))``; the total covariance is ``Cm + L L^T``.
    """
    C_old = Cm_old + L_old @ np.swapaxes(L_old, -1, -2)
    C_new = Cm_new + L_new @ np.swapaxes(L_new, -1, -2)
    W_old = np.linalg.inv(C_old)
    W_new = np.linalg.inv(C_new)
    C = np.linalg.inv(W_old + W_new)
    A = C @ W_old
    B = C @ W_new
    At, Bt = np.swapaxes(A, -1, -2), np.swapaxes(B, -1, -2)
    Cm = A @ Cm_old @ At + B @ Cm_new @ Bt
    b = (A @ b_old[..., None] + B @ b_new[..., None])[..., 0]
    return b, 0.5 * (Cm + np.swapaxes(Cm, -1, -2)), A @ L_old + B @ L_new


def hold_frame(b_before: ArrayLike, b_after: ArrayLike, cov_before: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Case (a): the rigid motion that puts refined model points back into the frame they were in.

    Refining the body coordinates of measured points (averaging their observations
    ``b = R^T (p - t)``) sharpens the model's *shape*, but each update also carries a rigid
    part — the pose error of the frame it was observed through, taken up unequally by young
    points (large gain) and old ones (small gain). Left in, that rigid part moves the body
    frame itself: the output origin and attitude wander although the body does not (a gauge
    drift). The frame is held by undoing it: the weighted least-squares rigid transform
    ``(R, t)`` with ``b_before_i ≈ R b_after_i + t`` (:func:`absolute_orientation`, weights the
    points' information before the update ``3 / trace(C_i)``, so a precise old point holds
    the frame and a fresh one follows it) is applied to the refined points. Shape changes
    that are not rigid pass unchanged; a purely rigid update is removed exactly.

    Args:
        b_before: (N,3) body coordinates before the update, m.
        b_after: (N,3) the same points after it, m.
        cov_before: (N,3,3) their covariances before the update, m².

    Returns:
        ``(R (3,3), t (3,))`` to apply as ``R b_after + t``; the identity when fewer than three
        points or a (nearly) collinear set leave the rotation undetermined.
    """
    a = np.asarray(b_before, dtype=float).reshape(-1, 3)
    b = np.asarray(b_after, dtype=float).reshape(-1, 3)
    C = np.asarray(cov_before, dtype=float).reshape(-1, 3, 3)
    if len(a) < 3:
        return np.eye(3), np.zeros(3)
    w = 3.0 / np.maximum(np.trace(C, axis1=1, axis2=2), 1e-18)
    try:
        return absolute_orientation(a, b, w)
    except TrackmeterError:
        return np.eye(3), np.zeros(3)


def handover_offset(
    b_model: ArrayLike, b_observed: ArrayLike, cov: ArrayLike, survivors: ArrayLike
) -> tuple[FloatArray, FloatArray, float]:
    """The rigid motion of the points still measured after a loss that keeps the pose where it was.

    A pose fitted to a set of model points sits where their body coordinates, on the whole, put
    it. Grown points carry the errors of the poses they were averaged through, so a subset of
    them fitted alone gives a pose a little off the whole set's, and when many points are lost at
    once the output jumps by that offset (estec case a, 60 s: 10 mm as 9 of 27 points went).

    The points' recent mean observations in the body frame, ``o_i = mean R^T (p_i - t)`` (a short
    running mean, so one frame's noise hardly enters), show it: the generalised least-squares
    fit ``o ≈ D_X b`` (:func:`solve_pose`, the points' full covariances) over the whole set
    (``D_A``) and over the survivors (``D_S``) are the two poses relative to the current one,
    ``T D_A`` and ``T D_S``. Moving the survivors by ``D = D_A^-1 D_S`` makes the pose fitted to
    them alone ``T D_A``, the whole set's; their shape is untouched.

    Most losses are of a point or two, and then ``D`` is mostly the noise of the running means:
    applied every time it would walk the frame about. ``D_S`` is the less efficient estimate of
    the same pose, so ``D_S - D_A`` has covariance ``cov_S - cov_A`` when the model is right
    (Hausman's test); its squared Mahalanobis length, chi-square with 6 degrees of freedom,
    says whether the survivors really disagree with the whole set.

    Args:
        b_model: (N,3) body coordinates of the points measured in the last frame, m.
        b_observed: (N,3) their recent mean observations in the body frame, m.
        cov: (N,3,3) covariances weighting each ``b_observed - b_model`` (model plus
            measurement, body frame), m².
        survivors: indices into the N of the points still measured, at least 3.

    Returns:
        ``(R (3,3), t (3,), d2)``: apply ``R b + t`` to the survivors; ``d2`` the Hausman
        statistic of ``D_S - D_A`` (position m and rotation vector, with the covariances
        :func:`solve_pose` gives from ``cov``).

    Raises:
        TrackmeterError: fewer than 3 survivors or a degenerate (collinear) set.
    """
    b = np.asarray(b_model, dtype=float).reshape(-1, 3)
    o = np.asarray(b_observed, dtype=float).reshape(-1, 3)
    C = np.asarray(cov, dtype=float).reshape(-1, 3, 3)
    k = np.asarray(survivors, dtype=int)
    identity = (np.eye(3), np.zeros(3))
    R_a, t_a, cov_a = solve_pose(b, o, C, None, identity, 4)
    R_s, t_s, cov_s = solve_pose(b[k], o[k], C[k], None, identity, 4)
    d = np.concatenate([t_s - t_a, Rotation.from_matrix(R_s @ R_a.T).as_rotvec()])
    w, V = np.linalg.eigh(0.5 * (cov_s - cov_a + (cov_s - cov_a).T))
    keep = w > 1e-12 * max(float(w.max()), 1e-300)  # directions the lost points did not inform carry no test
    d2 = float(np.sum((V[:, keep].T @ d) ** 2 / w[keep]))
    return R_a.T @ R_s, R_a.T @ (t_s - t_a), d2

