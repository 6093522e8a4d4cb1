"""Error metrics are exact: truth/estimate pairs whose every figure is known in closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from trackmeter.core.metrics import (
    EvaluateParams,
    associate,
    error_statistics,
    estimate_body_offset,
    evaluate,
    motion_errors,
    refer_to_true_body,
)
from trackmeter.data.motion_csv import MotionSeries
from trackmeter.data.trajectory import Trajectory
from trackmeter.errors import TrackmeterError

DT = 0.08  # 12.5 Hz, the paper's single-point tracking rate


def tumbling_truth(n: int = 60, seed: int = 1) -> MotionSeries:
    """A body at ~3.5 m translating at constant velocity and spinning at a constant body rate:
    R(t) = R0 exp(t [w_b]x), p(t) = p0 + v t, so v and omega_body are exact at every sample."""
    rng = np.random.default_rng(seed)
    t = 2.0 + DT * np.arange(n)
    w_b = np.array([0.05, -0.2, 0.3])
    v = np.array([0.01, -0.004, -0.02])
    p0 = np.array([0.1, -0.05, 3.5])
    R0 = Rotation.from_rotvec(rng.normal(size=3))
    R = R0 * Rotation.from_rotvec(np.outer(t - t[0], w_b))
    return MotionSeries(t, np.ones(n, bool), p0 + np.outer(t - t[0], v), R.as_quat(scalar_first=True),
                        np.tile(v, (n, 1)), np.tile(w_b, (n, 1)))


def with_pose(s: MotionSeries, *, t=None, p=None, q=None, v=None, w=None) -> MotionSeries:
    return MotionSeries(
        s.t_s if t is None else t, np.ones(len(s.t_s if t is None else t), bool),
        s.position_m if p is None else p, s.quat_wxyz if q is None else q,
        s.velocity_cam_m_s if v is None else v, s.omega_body_rad_s if w is None else w,
    )


def S(summary, group, axis):
    return summary[group][axis]


# --------------------------------------------------------------------------- statistics


def test_error_statistics_closed_form():
    st = error_statistics([3.0, -4.0])
    assert st["rms"] == pytest.approx(math.sqrt(12.5), abs=1e-15)
    assert st["max"] == 4.0
    assert st["p95"] == pytest.approx(3.95, abs=1e-12)  # linear interpolation between |3| and |-4|
    with pytest.raises(TrackmeterError):
        error_statistics([])


# --------------------------------------------------------------------------- pose errors


def test_identical_trajectories_have_zero_error_and_json_shape():
    truth = tumbling_truth()
    ev = evaluate(truth, truth)
    s = ev.summary
    assert list(s) == ["matched", "unmatched", "pose_coverage", "position_m", "attitude_rad", "velocity_m_s", "omega_rad_s", "speed_score",
                       "body_offset"]
    assert s["matched"] == 60 and s["unmatched"] == 0
    assert set(s["position_m"]) == {"x", "y", "z", "norm"}
    assert set(s["attitude_rad"]) == {"x", "y", "z", "total"}
    assert set(s["velocity_m_s"]) == {"x", "y", "z", "norm"} == set(s["omega_rad_s"])
    for group in ("position_m", "attitude_rad", "velocity_m_s", "omega_rad_s"):
        for leaf in s[group].values():
            assert set(leaf) == {"rms", "max", "p95"}
            assert max(leaf.values()) < 1e-7
    assert s["speed_score"] < 1e-7


def test_constant_position_offset_and_speed_score():
    truth = tumbling_truth()
    d = np.array([0.003, -0.004, 0.012])  # |d| = 13 mm
    est = with_pose(truth, p=truth.position_m + d)
    s = evaluate(truth, est).summary
    for i, axis in enumerate("xyz"):
        for stat in ("rms", "max", "p95"):
            assert S(s, "position_m", axis)[stat] == pytest.approx(abs(d[i]), abs=1e-12)
    assert S(s, "position_m", "norm")["rms"] == pytest.approx(0.013, abs=1e-12)
    assert S(s, "attitude_rad", "total")["max"] < 1e-12
    expected = np.mean(0.013 / np.linalg.norm(truth.position_m, axis=1))
    assert s["speed_score"] == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_attitude_error_about_one_camera_axis(axis):
    """R_est = R_err R_true with R_err about camera axis k by 1 deg: eq. 17 gives (k: 1 deg),
    eq. 16 gives 1 deg, and SPEED adds the angle in radians."""
    truth = tumbling_truth()
    angle = math.radians(1.0)
    r_err = Rotation.from_rotvec(angle * np.eye(3)[axis])
    q_est = (r_err * Rotation.from_quat(truth.quat_wxyz, scalar_first=True)).as_quat(scalar_first=True)
    s = evaluate(truth, with_pose(truth, q=q_est)).summary
    for k, name in enumerate("xyz"):
        assert S(s, "attitude_rad", name)["rms"] == pytest.approx(angle if k == axis else 0.0, abs=1e-12)
    assert S(s, "attitude_rad", "total")["max"] == pytest.approx(angle, abs=1e-12)
    assert s["speed_score"] == pytest.approx(angle, abs=1e-12)


def test_half_turn_error_is_pi_and_sign_flipped_quaternions_are_no_error():
    truth = tumbling_truth()
    flipped = evaluate(truth, with_pose(truth, q=-truth.quat_wxyz)).summary
    assert S(flipped, "attitude_rad", "total")["max"] < 1e-12
    R = Rotation.from_quat(truth.quat_wxyz, scalar_first=True)
    half = (Rotation.from_rotvec([0.0, math.pi, 0.0]) * R).as_quat(scalar_first=True)
    half[::2] *= -1.0  # sign flips must not matter for the half turn either
    s = evaluate(truth, with_pose(truth, q=half)).summary
    assert S(s, "attitude_rad", "total")["rms"] == pytest.approx(math.pi, abs=1e-9)
    assert S(s, "attitude_rad", "y")["max"] == pytest.approx(math.pi, abs=1e-9)
    assert S(s, "attitude_rad", "x")["max"] < 1e-6 and S(s, "attitude_rad", "z")["max"] < 1e-6
    assert s["speed_score"] == pytest.approx(math.pi, abs=1e-9)


def test_velocity_errors_are_differences_in_their_frames():
    truth = tumbling_truth()
    dv = np.array([0.002, 0.0, -0.0035])
    dw = np.array([0.0, math.radians(0.75), 0.0])
    s = evaluate(truth, with_pose(truth, v=truth.velocity_cam_m_s + dv, w=truth.omega_body_rad_s + dw)).summary
    assert S(s, "velocity_m_s", "x")["max"] == pytest.approx(0.002, abs=1e-15)
    assert S(s, "velocity_m_s", "z")["rms"] == pytest.approx(0.0035, abs=1e-15)
    assert S(s, "velocity_m_s", "norm")["p95"] == pytest.approx(np.linalg.norm(dv), abs=1e-15)
    assert S(s, "omega_rad_s", "y")["rms"] == pytest.approx(dw[1], abs=1e-15)
    assert S(s, "omega_rad_s", "x")["max"] == 0.0


def test_bare_trajectories_give_pose_metrics_only():
    truth = tumbling_truth()
    traj = Trajectory(truth.t_s, truth.position_m, truth.quat_wxyz)
    s = evaluate(traj, truth).summary
    assert s["velocity_m_s"] is None and s["omega_rad_s"] is None and s["matched"] == 60


# --------------------------------------------------------------------------- association


def test_time_shift_within_tolerance_pairs_nearest():
    truth = tumbling_truth()
    shift = 0.004
    ev = evaluate(truth, with_pose(truth, t=truth.t_s + shift), EvaluateParams(tolerance_s=0.005))
    assert ev.summary["matched"] == 60 and ev.summary["unmatched"] == 0
    np.testing.assert_allclose(ev.association.dt_s, shift, atol=1e-12)
    assert S(ev.summary, "position_m", "norm")["max"] < 1e-12
    with pytest.raises(TrackmeterError, match="no overlapping timestamps"):
        evaluate(truth, with_pose(truth, t=truth.t_s + 0.006), EvaluateParams(tolerance_s=0.005))


def test_dropped_poses_are_counted_unmatched():
    truth = tumbling_truth()
    keep = np.ones(60, bool)
    keep[[0, 7, 8, 30, 59]] = False  # the two ends are outside the estimate's span: not counted
    est = MotionSeries(truth.t_s[keep], np.ones(55, bool), truth.position_m[keep], truth.quat_wxyz[keep],
                       truth.velocity_cam_m_s[keep], truth.omega_body_rad_s[keep])
    s = evaluate(truth, est).summary
    assert s["matched"] == 55 and s["unmatched"] == 3


def test_unmatched_counts_the_same_span_as_matched_after_the_settle():
    # "matched" counts pairs after the settle time; "unmatched" counted gaps before it too, so a
    # run that dropped frames while settling reported them beside pairs that left them out (an
    # outside evaluator's probe).
    truth = tumbling_truth()
    keep = np.ones(60, bool)
    keep[[3, 4, 40]] = False  # two dropped while settling, one after
    est = MotionSeries(truth.t_s[keep], np.ones(57, bool), truth.position_m[keep], truth.quat_wxyz[keep],
                       truth.velocity_cam_m_s[keep], truth.omega_body_rad_s[keep])
    settle = float(truth.t_s[10] - truth.t_s[0])
    s = evaluate(truth, est, EvaluateParams(settle_s=settle)).summary
    assert s["matched"] == 49 and s["unmatched"] == 1
    assert evaluate(truth, est).summary["unmatched"] == 3  # no settle: every gap


def test_truth_between_the_runs_frames_is_not_unmatched():
    """A truth sampled faster than the run (30 Hz truth, a 15 Hz run; motion capture at 200 Hz)
    counted every truth pose between two frames as "unmatched": a run of 15 Hz read "matched 44,
    unmatched 45" with a pose at every frame (an outside probe). With the run's frames known,
    a truth pose is unmatched only where the run had a frame and no pose."""
    truth = tumbling_truth()  # 12.5 Hz; the run at every second truth time
    frames = truth.t_s[::2]
    valid = np.ones(len(frames), bool)
    valid[10] = False  # one frame without a pose
    est = MotionSeries(frames[valid], np.ones(int(valid.sum()), bool), truth.position_m[::2][valid],
                       truth.quat_wxyz[::2][valid], truth.velocity_cam_m_s[::2][valid],
                       truth.omega_body_rad_s[::2][valid])
    s = evaluate(truth, est, frame_times_s=frames).summary
    assert s["matched"] == len(frames) - 1 and s["unmatched"] == 1
    assert evaluate(truth, est).summary["unmatched"] == 30  # no frames known: every truth pose in the span without one


def test_estimates_outside_truth_and_duplicates_stay_unmatched():
    a = associate([0.0, 1.0, 2.0], [-0.5, 0.999, 1.0, 1.002, 2.0, 3.0], tolerance_s=0.01)
    assert a.index_truth.tolist() == [1, 2] and a.index_est.tolist() == [2, 4]
    assert a.unmatched_est == 4 and a.unmatched_truth == 1  # truth 0.0 lies inside [-0.5, 3]
    assert a.unmatched == 5


def test_settle_time_skips_the_start():
    truth = tumbling_truth()
    p = truth.position_m.copy()
    p[truth.t_s < truth.t_s[0] + 1.0] += 0.5  # big errors while "settling"
    ev = evaluate(truth, with_pose(truth, p=p), EvaluateParams(settle_s=1.0))
    assert ev.summary["matched"] == int(np.count_nonzero(truth.t_s >= truth.t_s[0] + 1.0))
    assert S(ev.summary, "position_m", "norm")["max"] < 1e-12
    with pytest.raises(TrackmeterError, match="settle"):
        evaluate(truth, truth, EvaluateParams(settle_s=100.0))


def test_settle_cuts_on_the_runs_clock_when_it_counts_from_the_runs_start():
    # The settle counts from the run's first frame (t_start_s, the estimate's clock); cut on the
    # truth's times, an estimate a few ms late (well inside the tolerance) lost its first pose
    # after the settle, counted neither matched nor unmatched (an outside probe).
    truth = tumbling_truth(n=20)
    settle = 5 * DT
    for offset_s in (0.0, 0.004, -0.004):
        est = with_pose(truth, t=truth.t_s + offset_s)
        s = evaluate(truth, est, EvaluateParams(settle_s=settle), t_start_s=float(est.t_s[0]),
                     frame_times_s=est.t_s).summary
        after = int(np.count_nonzero(est.t_s >= est.t_s[0] + settle - 1e-9))
        assert (s["matched"], s["unmatched"], s["pose_coverage"]) == (after, 0, 1.0), offset_s


def test_a_step_back_in_time_across_a_nan_is_refused_as_the_nan() -> None:
    # NaN < x is False both ways: [0, 1, 2, nan, 0.5] passed the time-order check, and the
    # nearest-time pairing then paired nothing, silently (an outside probe).
    from trackmeter.core.checks import time_order

    with pytest.raises(TrackmeterError, match=r"est: timestamp 3 is not a number"):
        time_order(np.array([0.0, 1.0, 2.0, np.nan, 0.5]), "est")
    with pytest.raises(TrackmeterError, match=r"timestamps go backwards: t = 0.5 s after 2 s"):
        time_order(np.array([0.0, 1.0, 2.0, 0.5]), "est")
    time_order(np.array([0.0, 1.0, 1.0, 2.0]), "est")  # a repeat is allowed


# --------------------------------------------------------------------------- body alignment


def _offset_estimate(truth: MotionSeries, R_X: np.ndarray, t_X: np.ndarray, h: float = 1e-5):
    """The same rigid motion described in another body frame: T_cam_est = T_cam_true X.
    Velocities of the estimated origin by central differences of the exact motion."""
    R0 = Rotation.from_quat(truth.quat_wxyz[0], scalar_first=True)
    w_b, v = truth.omega_body_rad_s[0], truth.velocity_cam_m_s[0]

    def pose(t):
        R = R0 * Rotation.from_rotvec(np.outer(t - truth.t_s[0], w_b))
        p = truth.position_m[0] + np.outer(t - truth.t_s[0], v)
        return R * Rotation.from_matrix(R_X), p + R.apply(t_X)

    r, p = pose(truth.t_s)
    v_est = (pose(truth.t_s + h)[1] - pose(truth.t_s - h)[1]) / (2 * h)
    w_est = np.tile(R_X.T @ w_b, (len(truth), 1))
    return with_pose(truth, p=p, q=r.as_quat(scalar_first=True), v=v_est, w=w_est)


def test_align_body_recovers_a_known_offset():
    truth = tumbling_truth()
    R_X = Rotation.from_rotvec([0.4, -1.1, 2.0]).as_matrix()
    t_X = np.array([0.12, -0.3, 0.05])
    est = _offset_estimate(truth, R_X, t_X)
    unaligned = evaluate(truth, est).summary
    assert S(unaligned, "attitude_rad", "total")["rms"] > 1.0
    ev = evaluate(truth, est, EvaluateParams(align="body"))
    R_fit, t_fit = ev.body_offset
    np.testing.assert_allclose(R_fit, R_X, atol=1e-6)
    np.testing.assert_allclose(t_fit, t_X, atol=1e-6)
    s = ev.summary
    assert S(s, "position_m", "norm")["max"] < 1e-6
    assert S(s, "attitude_rad", "total")["max"] < 1e-6
    assert S(s, "velocity_m_s", "norm")["max"] < 1e-6  # lever-arm term omega x r removed
    assert S(s, "omega_rad_s", "norm")["max"] < 1e-6  # omega re-expressed in the true body frame


def test_align_body_fit_is_least_squares_under_noise():
    """With zero-mean noise on the estimate the fit stays close and residuals are the noise."""
    truth = tumbling_truth(n=400)
    R_X = Rotation.from_rotvec([3.0, 0.1, 0.0]).as_matrix()  # near a half turn
    t_X = np.array([0.0, 0.2, -0.1])
    est = _offset_estimate(truth, R_X, t_X)
    rng = np.random.default_rng(3)
    noisy = Rotation.from_rotvec(rng.normal(scale=1e-3, size=(400, 3))) * Rotation.from_quat(est.quat_wxyz, scalar_first=True)
    est = with_pose(est, p=est.position_m + rng.normal(scale=1e-3, size=(400, 3)), q=noisy.as_quat(scalar_first=True))
    R_fit, t_fit = estimate_body_offset(truth.quat_wxyz, truth.position_m, est.quat_wxyz, est.position_m)
    angle = Rotation.from_matrix(R_fit.T @ R_X).magnitude()
    assert angle < 4 * 1e-3 * math.sqrt(3) / math.sqrt(400)
    assert np.linalg.norm(t_fit - t_X) < 1e-3


def test_refer_to_true_body_inverts_the_offset():
    truth = tumbling_truth(n=5)
    R_X = Rotation.from_rotvec([0.2, 0.3, -0.4]).as_matrix()
    t_X = np.array([0.05, 0.0, -0.2])
    est = _offset_estimate(truth, R_X, t_X)
    q, p, v, w = refer_to_true_body(est.quat_wxyz, est.position_m, R_X, t_X, est.velocity_cam_m_s, est.omega_body_rad_s)
    np.testing.assert_allclose(np.abs(np.sum(q * truth.quat_wxyz, axis=1)), 1.0, atol=1e-12)
    np.testing.assert_allclose(p, truth.position_m, atol=1e-12)
    np.testing.assert_allclose(v, truth.velocity_cam_m_s, atol=1e-8)
    np.testing.assert_allclose(w, truth.omega_body_rad_s, atol=1e-12)


def test_velocity_statistics_skip_samples_without_velocity():
    """An estimator warming up writes valid poses without velocities: those samples count for
    the pose errors only."""
    truth = tumbling_truth()
    v = truth.velocity_cam_m_s + [0.0, 0.001, 0.0]
    v[:5] = np.nan
    w = truth.omega_body_rad_s.copy()
    w[:5] = np.nan
    s = evaluate(truth, with_pose(truth, v=v, w=w)).summary
    assert s["matched"] == 60
    assert S(s, "velocity_m_s", "y")["rms"] == pytest.approx(0.001, abs=1e-15)
    assert S(s, "omega_rad_s", "norm")["max"] == 0.0
    none = evaluate(truth, with_pose(truth, v=np.full((60, 3), np.nan), w=w)).summary
    assert none["velocity_m_s"] is None and none["omega_rad_s"] is None


def test_pose_coverage_counts_the_run_s_frames_whatever_the_truth_s_rate() -> None:
    """The share of the run's frames after the settle with a pose: a truth sampled twice as
    densely as the frames (mocap, EuRoC's 200 Hz) must not halve it; without the frames (a
    TUM estimate) it is unknown (None)."""
    from trackmeter.core.metrics import EvaluateParams, evaluate

    truth = tumbling_truth()  # every 0.08 s from 2.0 s
    frames = truth.t_s[::2]  # the run: every 0.16 s
    has_pose = np.ones(len(frames), bool)
    has_pose[5:10] = False  # five frames without a pose
    est = MotionSeries(frames[has_pose], np.ones(int(has_pose.sum()), bool), truth.position_m[::2][has_pose],
                       truth.quat_wxyz[::2][has_pose], truth.velocity_cam_m_s[::2][has_pose],
                       truth.omega_body_rad_s[::2][has_pose])
    params = EvaluateParams(settle_s=0.0)
    ev = evaluate(truth, est, params, float(frames[0]), frames)
    assert ev.summary["pose_coverage"] == pytest.approx(has_pose.sum() / len(frames))
    assert evaluate(truth, est, params).summary["pose_coverage"] is None
    settled = evaluate(truth, est, EvaluateParams(settle_s=1.0), float(frames[0]), frames)
    after = frames >= frames[0] + 1.0 - 1e-9
    assert settled.summary["pose_coverage"] == pytest.approx((has_pose & after).sum() / after.sum())
    # A truth sparser than the frames, or with a gap (mocap), counts the run's poses all the same.
    sparse = MotionSeries(truth.t_s[::5], np.ones(len(truth.t_s[::5]), bool), truth.position_m[::5],
                          truth.quat_wxyz[::5], truth.velocity_cam_m_s[::5], truth.omega_body_rad_s[::5])
    keep = np.ones(len(truth.t_s), bool)
    keep[20:40] = False
    gappy = MotionSeries(truth.t_s[keep], keep[keep], truth.position_m[keep], truth.quat_wxyz[keep],
                         truth.velocity_cam_m_s[keep], truth.omega_body_rad_s[keep])
    for other in (sparse, gappy):
        ev = evaluate(other, est, params, float(frames[0]), frames)
        assert ev.summary["pose_coverage"] == pytest.approx(has_pose.sum() / len(frames), abs=0.02)


def test_a_trajectory_whose_times_go_backwards_is_refused_not_paired_with_nothing() -> None:
    """An outside review: Trajectory([1, 0, 0], ...) was accepted, and `associate` then paired
    none of it with a truth sampled at exactly 0 and 1 s (its search assumes sorted times)."""
    q = np.tile([1.0, 0.0, 0.0, 0.0], (3, 1))
    with pytest.raises(TrackmeterError, match=r"^trajectory: timestamps go backwards: t = 0 s after 1 s$"):
        Trajectory(np.array([1.0, 0.0, 0.0]), np.zeros((3, 3)), q)
    with pytest.raises(TrackmeterError, match=r"^estimate: timestamps go backwards: t = 0 s after 1 s"):
        associate(np.array([0.0, 1.0]), np.array([1.0, 0.0, 0.0]), 0.01)
    with pytest.raises(TrackmeterError, match=r"^truth: timestamps go backwards: t = 0\.5 s after 1 s"):
        associate(np.array([0.0, 1.0, 0.5]), np.array([0.0]), 0.01)
    # repeated times are not "backwards": the state of a frame read twice is still a sample
    assert len(Trajectory(np.array([0.0, 1.0, 1.0]), np.zeros((3, 3)), q)) == 3


def test_usable_covariances_are_the_finite_ones_cholesky_accepts() -> None:
    # Pinned to numpy's Cholesky factorisation, which exists exactly for the symmetric positive
    # definite matrices (Golub and Van Loan 4.2).
    from trackmeter.core.metrics import usable_covariances

    rng = np.random.default_rng(21)
    mats = []
    for k in range(40):
        A = rng.normal(size=(6, 6))
        kind = k % 5
        if kind == 0:
            mats.append(A @ A.T + 1e-3 * np.eye(6))  # positive definite
        elif kind == 1:
            mats.append(-(A @ A.T))  # negative definite
        elif kind == 2:
            M = A @ A.T
            M[5, :] = M[:, 5] = 0.0
            mats.append(M)  # rank 5: singular (exactly, so that Cholesky's rounding cannot pass it)
        elif kind == 3:
            M = A @ A.T
            M[0, 0] = np.nan
            mats.append(M)
        else:
            mats.append(A @ A.T + np.diag([0, 0, 0, 0, 0, -50.0]))  # an eigenvalue below zero, mostly
    finite, definite = usable_covariances(np.array(mats))

    def cholesky_ok(M: np.ndarray) -> bool:
        try:
            np.linalg.cholesky(M)
            return bool(np.all(np.isfinite(M)))
        except np.linalg.LinAlgError:
            return False

    expected = np.array([cholesky_ok(M) for M in mats])
    np.testing.assert_array_equal(finite & definite, expected)
    np.testing.assert_array_equal(finite, [k % 5 != 3 for k in range(40)])


def test_a_trajectory_of_positions_or_quaternions_of_another_shape_is_refused() -> None:
    """An outside probe: Trajectory(t of 2, positions (3,2), ...) was taken as 2 positions, the
    six numbers re-read three at a time."""
    q = np.tile([1.0, 0.0, 0.0, 0.0], (2, 1))
    with pytest.raises(TrackmeterError, match=r"position_m must be \(3,\) or \(N,3\), got shape \(3,2\)"):
        Trajectory(np.arange(2.0), np.zeros((3, 2)), q)
    with pytest.raises(TrackmeterError, match=r"quat_wxyz must be \(4,\) or \(N,4\), got shape \(4,2\)"):
        Trajectory(np.arange(2.0), np.zeros((2, 3)), q.T)
    assert len(Trajectory(np.arange(2.0), np.zeros((2, 3)), q)) == 2
    assert len(Trajectory(np.array([0.5]), np.zeros(3), q[0])) == 1  # one pose, unbatched


def test_paired_samples_of_another_shape_or_length_are_refused_not_broadcast() -> None:
    """An outside probe of the library API: the core re-read arrays of another shape
    (reshape(-1, 3)); here a single estimated pose was also paired with every true one."""
    n = 4
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    p = np.tile([0.0, 0.0, 3.5], (n, 1))
    t = np.arange(n) * 0.04
    with pytest.raises(TrackmeterError, match="paired samples differ in length: t_s 4, position_true_m 4, "
                                              "position_est_m 1"):
        motion_errors(t, q, p, q, p[:1])
    with pytest.raises(TrackmeterError, match=r"velocity_est_cam_m_s 2"):
        motion_errors(t, q, p, q, p, np.zeros((n, 3)), np.zeros((2, 3)))
    with pytest.raises(TrackmeterError, match=r"position_est_m must be \(3,\) or \(N,3\), got shape \(3,4\)"):
        motion_errors(t[:3], q[:3], p[:3], q[:3], np.ones((3, 4)))
    with pytest.raises(TrackmeterError, match="paired samples differ in length"):
        estimate_body_offset(q, p, q[:2], p[:2])
    with pytest.raises(TrackmeterError, match="paired samples differ in length"):
        refer_to_true_body(q, p[:3], np.eye(3), np.zeros(3))
    assert np.allclose(motion_errors(t, q, p, q, p).position_m, 0.0)
