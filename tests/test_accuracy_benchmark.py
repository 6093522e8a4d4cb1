"""The accuracy benchmark's evaluation of a case-(a) run whose body frame was defined anew."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from benchmarks.accuracy import figures, figures_per_body_frame, validity_while_hidden
from trackmeter.data.motion_csv import MotionSeries

from tests.test_metrics import DT, tumbling_truth


def _in_body_frame(truth: MotionSeries, rows: slice, rotvec: list[float], t_body_m: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """Poses of ``truth`` (rows) referred to another body frame: T_cam_est = T_cam_true T_true_est."""
    R_x, t_x = Rotation.from_rotvec(rotvec), np.asarray(t_body_m)
    R = Rotation.from_quat(truth.quat_wxyz[rows], scalar_first=True)
    return truth.position_m[rows] + R.apply(t_x), (R * R_x).as_quat(scalar_first=True)


def test_each_body_frame_definition_is_aligned_on_its_own():
    truth = tumbling_truth(n=300)  # 24 s
    n = len(truth)
    p = np.full((n, 3), np.nan)
    q = np.full((n, 4), np.nan)
    valid = np.zeros(n, bool)
    frames = np.zeros(n, int)
    # definition 0 until a total loss at frame 140; definition 1 from frame 160, a different frame
    p[:140], q[:140] = _in_body_frame(truth, slice(0, 140), [0.3, -0.2, 0.1], [0.05, 0.02, -0.1])
    p[160:], q[160:] = _in_body_frame(truth, slice(160, n), [-1.0, 0.4, 0.7], [-0.2, 0.1, 0.05])
    valid[:140] = valid[160:] = True
    frames[140:] = 1
    nan = np.full((n, 3), np.nan)  # no rates: pose figures only
    est = MotionSeries(truth.t_s, valid, p, q, nan, nan)

    out = figures_per_body_frame(truth, est, frames, "x")
    assert out["x_body_frames"] == 2
    assert out["x_valid_fraction"] == pytest.approx(280 / 300)
    for key in ("x_pos_lateral_max_mm", "x_pos_depth_max_mm", "x_att_view_max_deg", "x_att_other_max_deg"):
        assert out[key] < 1e-6, key
    # each definition settles for 2 s from its first pose (25 samples), then runs to its last
    assert out["x_seconds"] == pytest.approx(2 * (139 - 25) * DT, abs=1e-9)
    # one alignment over both definitions cannot fit them: the reason for evaluating them apart
    whole = figures(truth, est, "body", "x")
    assert whole["x_pos_lateral_max_mm"] > 50


def test_a_single_definition_is_the_plain_evaluation():
    truth = tumbling_truth(n=150)
    p, q = _in_body_frame(truth, slice(None), [0.1, 0.2, 0.3], [0.01, 0.0, 0.02])
    p = p + np.array([0.0, 0.0, 0.002])  # a camera-frame error the body alignment cannot absorb
    est = MotionSeries(truth.t_s, np.ones(len(truth), bool), p, q, truth.velocity_cam_m_s, truth.omega_body_rad_s)
    out = figures_per_body_frame(truth, est, np.zeros(len(truth), int), "y")
    plain = figures(truth, est, "body", "y")
    assert out == {**plain, "y_body_frames": 1.0}
    assert out["y_pos_depth_max_mm"] > 0.5


def test_labels_must_match_the_estimates():
    truth = tumbling_truth(n=100)
    with pytest.raises(ValueError):
        figures_per_body_frame(truth, truth, [0] * 99, "z")


def test_drift_since_a_coast_began_is_measured_in_any_body_frame():
    """The coast figure: the estimate against the truth carried by the body offset the coast
    started with (``_jump_sigma`` with the starting pair), in sigmas of the given covariance."""
    from benchmarks.accuracy import _jump_sigma

    def T(rotvec, t):
        M = np.eye(4)
        M[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
        M[:3, 3] = t
        return M

    X = T([0.4, -0.1, 0.9], [0.2, -0.05, 0.1])  # case (a): the estimate's body frame is not the truth's
    true0, true = T([0.1, 0.2, 0.3], [0.0, 0.05, 3.5]), T([0.3, 0.1, 0.5], [0.01, 0.04, 3.49])
    est0 = true0 @ X
    cov = np.diag([1e-4] * 3 + [1e-4] * 3)  # 10 mm, 0.01 rad
    assert _jump_sigma(est0, true @ X, cov, true0, true) == pytest.approx(0.0, abs=1e-9)
    off = true @ X
    off[:3, 3] += [0.0, 0.02, 0.0]  # 2 sigma off in y
    assert _jump_sigma(est0, off, cov, true0, true) == pytest.approx(2.0)
    turned = T([0.0, 0.0, 0.03], [0, 0, 0]) @ (true @ X)
    turned[:3, 3] = (true @ X)[:3, 3]
    assert _jump_sigma(est0, turned, cov, true0, true) == pytest.approx(3.0)


def test_validity_while_hidden_counts_the_occlusion_and_what_follows_the_first_pose():
    t = np.arange(20) * 0.5  # 0 .. 9.5 s
    valid = t >= 3.0  # the pose starts at 3 s, inside the occlusion [2, 6)
    valid[t == 5.0] = False  # one loss while hidden
    got = validity_while_hidden(t, valid, [(2.0, 6.0), (8.0, 8.6)])
    # hidden frames: 2.0 .. 5.5 (8) and 8.0, 8.5 (2); valid among them: 3.0, 3.5, 4.0, 4.5, 5.5, 8.0, 8.5
    assert got["valid_fraction_occluded"] == pytest.approx(7 / 10)
    # from the first valid pose (3.0 s): 3.0 .. 5.5 (6) and 8.0, 8.5 (2); 7 of 8 valid
    assert got["valid_fraction_occluded_once_valid"] == pytest.approx(7 / 8)
    assert validity_while_hidden(t, np.zeros(20, bool), [(2.0, 6.0)]) == {"valid_fraction_occluded": 0.0}
    assert validity_while_hidden(t, valid, [(20.0, 30.0)]) == {}


def test_nees_is_the_pose_error_in_the_covariance_metric():
    """``_nees``: position and camera-frame rotation-vector errors weighed by the inverse pose
    covariance (closed forms on a diagonal covariance), and chi-square(6) when the errors are
    drawn from the covariance itself (median 5.35, 95 % under 12.59)."""
    from benchmarks.accuracy import _nees, nees_figures

    true = np.eye(4)
    true[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 0.9]).as_matrix()
    true[:3, 3] = [0.05, -0.02, 3.5]
    cov = np.diag([1e-6, 4e-6, 9e-6, 1e-6, 1e-6, 4e-6])  # 1 / 2 / 3 mm, 1 / 1 / 2 mrad
    assert _nees(true, cov, true) == pytest.approx(0.0, abs=1e-12)
    off = true.copy()
    off[:3, 3] += [0.0, 0.004, 0.0]  # 2 sigma in y
    assert _nees(off, cov, true) == pytest.approx(4.0)
    turned = true.copy()
    turned[:3, :3] = Rotation.from_rotvec([0.0, 0.0, 0.006]).as_matrix() @ true[:3, :3]  # 3 sigma about camera z
    assert _nees(turned, cov, true) == pytest.approx(9.0)

    rng = np.random.default_rng(0)
    A = rng.standard_normal((6, 6)) * 1e-3
    P = A @ A.T + 1e-8 * np.eye(6)
    values = []
    for e in rng.multivariate_normal(np.zeros(6), P, size=4000):
        T = true.copy()
        T[:3, :3] = Rotation.from_rotvec(e[3:]).as_matrix() @ true[:3, :3]
        T[:3, 3] = true[:3, 3] + e[:3]
        values.append(_nees(T, P, true))
    got = nees_figures(values, "x")
    assert got["x_nees_median"] == pytest.approx(5.35, abs=0.3)
    assert got["x_nees_within_95"] == pytest.approx(0.95, abs=0.015)
    assert nees_figures([], "x") == {}


def test_the_settle_counts_from_the_run_s_start_not_its_first_valid_pose():
    # The benchmark counted the 2 s from the first valid pose, where `trackmeter evaluate
    # --settle 2` counts them from the run's first frame: a case (a) run valid from 0.52 s was
    # judged from 2.52 s (an outside review of the benchmarks).
    truth = tumbling_truth(n=60)  # 12.5 Hz from t = 2 s
    valid = truth.t_s >= truth.t_s[0] + 0.5
    p = truth.position_m.copy()
    late = (truth.t_s >= truth.t_s[0] + 2.0) & (truth.t_s < truth.t_s[0] + 2.3)
    p[late] += [0.004, 0.0, 0.0]  # 4 mm off just after the settle from the start, before it from 0.5 s
    est = MotionSeries(truth.t_s, valid, p, truth.quat_wxyz, truth.velocity_cam_m_s, truth.omega_body_rad_s)
    assert figures(truth, est, "none", "x")["x_pos_lateral_max_mm"] == pytest.approx(4.0)


def test_a_seed_without_a_largest_error_is_not_left_out_of_the_median():
    # Two seeds at 1.2 and 1.4 mm and one with no pose after the settle gave a "median" of
    # 1.30 mm, and the goal of 1.5 mm passed; the seed that failed counts as infinite.
    from benchmarks.accuracy import median_over_runs

    runs = [{"b_pos_lateral_max_mm": 1.2, "b_valid_fraction": 0.9}, {"b_pos_lateral_max_mm": 1.4},
            {"b_valid_fraction": 0.1}]
    out = median_over_runs(runs)
    assert out["b_pos_lateral_max_mm"] == 1.4 and out["b_valid_fraction"] == pytest.approx(0.5)
    assert np.isnan(out["b_pos_lateral_max_mm_seed2"])
    assert np.isnan(median_over_runs([{"b_pos_lateral_max_mm": 1.2}, {}, {}])["b_pos_lateral_max_mm"])


def test_the_motion_estimation_alone_runs_case_b_on_its_tracker_double() -> None:
    # The geometric benchmark's tracker double stands in for the Tracker the engine drives: an
    # engine that asks the tracker something new breaks it (the model's ids reserved, 2026-12-07),
    # and only the benchmark's run showed it. Case (b), whose body frame is the truth's, within
    # the paper's figures at 3.5 m (3 mm lateral, 5 mm along the viewing axis).
    from benchmarks.accuracy import run_geometric

    truth, est = run_geometric("b")
    out = figures(truth, est, "none", "geom_b")
    assert out["geom_b_valid_fraction"] > 0.99, out
    assert out["geom_b_pos_lateral_max_mm"] < 3.0 and out["geom_b_pos_depth_max_mm"] < 5.0, out
