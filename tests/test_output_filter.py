"""Output filter: Butterworth low-pass on position and on the rotation group (paper 2.E)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal
from scipy.spatial.transform import Rotation

from trackmeter.core.output_filter import FilterParams, PoseFilter, dc_group_delay_s, design_lowpass
from trackmeter.errors import TrackmeterError

RATE = 25.0
AXIS = np.array([0.3, -0.8, 0.52]) / np.linalg.norm([0.3, -0.8, 0.52])
R0 = Rotation.from_rotvec([1.0, 0.2, -0.4]).as_matrix()
RATE_RAD_S = np.radians(10.0)


def rotation_at(t: float) -> np.ndarray:
    return R0 @ Rotation.from_rotvec(AXIS * RATE_RAD_S * t).as_matrix()


def test_design_is_scipy_butterworth() -> None:
    sos = design_lowpass(2.0, 2, RATE)
    np.testing.assert_allclose(sos, signal.butter(2, 2.0, fs=RATE, output="sos"))
    w, h = signal.sosfreqz(sos, worN=[2.0], fs=RATE)
    assert abs(abs(h[0]) - 1 / np.sqrt(2)) < 1e-9


def test_constant_rate_rotation_passes_with_the_group_delay_only() -> None:
    f = PoseFilter(FilterParams(cutoff_hz=2.0, order=2, velocity_compensated=False), RATE)
    tau = f.group_delay_s
    assert 0.05 < tau < 0.2
    t = np.arange(150) / RATE
    out = [f.update(ti, rotation_at(ti), np.zeros(3))[0] for ti in t]
    for ti, R in zip(t[100:], out[100:]):
        err = Rotation.from_matrix(R @ rotation_at(ti - tau).T).magnitude()
        assert err < 1e-6  # rotation about one axis: exactly the scalar filter on the angle
        assert abs(np.linalg.det(R) - 1) < 1e-12


def test_componentwise_quaternion_filter_would_be_wrong() -> None:
    """Filtering q's components with the same IIR leaves the unit sphere and lags differently."""
    sos = design_lowpass(2.0, 2, RATE)
    t = np.arange(300) / RATE
    fast = np.radians(90.0)  # a quick tumble makes the components' attenuation obvious
    q = Rotation.from_matrix([R0 @ Rotation.from_rotvec(AXIS * fast * ti).as_matrix() for ti in t]).as_quat(
        scalar_first=True)
    qf = signal.sosfilt(sos, q, axis=0, zi=signal.sosfilt_zi(sos)[:, :, None] * q[0])[0]
    norms = np.linalg.norm(qf[100:], axis=1)
    assert np.max(np.abs(norms - 1)) > 1e-3
    f = PoseFilter(FilterParams(cutoff_hz=2.0, order=2, velocity_compensated=False), RATE)
    tau = f.group_delay_s
    out = [f.update(ti, R0 @ Rotation.from_rotvec(AXIS * fast * ti).as_matrix(), np.zeros(3))[0] for ti in t]
    ours = max(Rotation.from_matrix(R @ (R0 @ Rotation.from_rotvec(AXIS * fast * (ti - tau)).as_matrix()).T).magnitude()
               for ti, R in zip(t[100:], out[100:]))
    theirs = max(
        (Rotation.from_quat(qi / np.linalg.norm(qi), scalar_first=True).inv()
         * Rotation.from_matrix(R0 @ Rotation.from_rotvec(AXIS * fast * (ti - tau)).as_matrix())).magnitude()
        for ti, qi in zip(t[100:], qf[100:]))
    assert ours < 1e-6
    assert theirs > 1e-3


def test_velocity_compensated_filter_has_no_delay_on_constant_velocity() -> None:
    f = PoseFilter(FilterParams(cutoff_hz=1.0, order=2, velocity_compensated=True), RATE)
    t = np.arange(100) / RATE
    v = np.array([0.01, -0.02, 0.005])
    w = AXIS * RATE_RAD_S
    # rotation_at is R0 exp(axis rate t): body-frame omega = axis * rate
    for ti in t:
        R, p = f.update(ti, rotation_at(ti), v * ti, v, w)
        assert Rotation.from_matrix(R @ rotation_at(ti).T).magnitude() < 1e-9
        np.testing.assert_allclose(p, v * ti, atol=1e-12)


def test_an_origin_turning_about_the_spin_axis_passes_without_lag() -> None:
    """A body origin r off a constant spin axis moves on a circle: its velocity turns by
    omega dt within each frame, and stepping the chart along the newest velocity alone missed by
    |omega| |v| dt^2 / 2 a frame, which the filter turned into a lag of about
    omega^2 r dt (group delay) / 2: 7.8 mm at 195 deg/s and 0.3 m (an outside review). The
    chart now steps by the mean of the last two velocities (trapezoid rule)."""
    f = PoseFilter(FilterParams(cutoff_hz=2.0, order=2, velocity_compensated=True), RATE)
    w = np.radians(195.0)
    axis_point = np.array([0.0, 0.0, 3.5])  # the spin axis through here, along the camera's y
    r0 = np.array([0.3, 0.0, 0.0])  # the body origin, 0.3 m off the axis at t = 0
    worst = 0.0
    for ti in np.arange(100) / RATE:
        R = Rotation.from_rotvec([0.0, w * ti, 0.0]).as_matrix()
        p = axis_point + R @ r0
        v = np.cross([0.0, w, 0.0], R @ r0)  # velocity of the origin, camera frame
        _, p_out = f.update(ti, R, p, v, np.array([0.0, w, 0.0]))  # R_cam_body = R: omega_body along y
        if ti >= 1.0:
            worst = max(worst, float(np.linalg.norm(p_out - p)))
    assert worst < 0.5e-3  # 7.8 mm stepping with the newest velocity alone; 0.18 mm now


def test_noise_variance_reduced_as_the_filter_predicts() -> None:
    """Small attitude and position noise about a fixed pose: output variance = input variance
    times the impulse response energy sum(h²) of the IIR (white noise through an LTI filter)."""
    rng = np.random.default_rng(1)
    f = PoseFilter(FilterParams(cutoff_hz=2.0, order=2, velocity_compensated=False), RATE)
    n = 6000
    sigma_rad, sigma_m = np.radians(0.05), 0.001
    out_rot, out_pos = [], []
    for k in range(n):
        R = Rotation.from_rotvec(rng.normal(0, sigma_rad, 3)).as_matrix() @ R0
        p = np.array([0, 0, 3.5]) + rng.normal(0, sigma_m, 3)
        Rf, pf = f.update(k / RATE, R, p)
        out_rot.append(Rotation.from_matrix(Rf @ R0.T).as_rotvec())
        out_pos.append(pf)
    impulse = signal.sosfilt(f.sos, np.r_[1.0, np.zeros(500)])
    gain = np.sum(impulse**2)
    var_rot = np.var(np.array(out_rot[100:]), axis=0) / sigma_rad**2
    var_pos = np.var(np.array(out_pos[100:]), axis=0) / sigma_m**2
    np.testing.assert_allclose(var_rot, gain, rtol=0.15)
    np.testing.assert_allclose(var_pos, gain, rtol=0.15)
    assert gain < 0.3


def test_disabled_filter_passes_through() -> None:
    f = PoseFilter(FilterParams(enabled=False), RATE)
    R, p = f.update(0.0, R0, np.ones(3))
    R, p = f.update(0.04, rotation_at(1.0), np.zeros(3))
    np.testing.assert_allclose(R, rotation_at(1.0))


def test_dc_group_delay_of_first_order_filter() -> None:
    sos = design_lowpass(1.0, 1, RATE)
    b, a = signal.sos2tf(sos)
    # single pole p: y = ... ; DC group delay = p/(1-p) - (zero term) computed by scipy
    _, gd = signal.group_delay((b, a), w=[1e-6], fs=RATE)
    assert abs(dc_group_delay_s(sos, RATE) - gd[0] / RATE) < 1e-12


@pytest.mark.parametrize("rate_hz", [0.0, float("nan"), -25.0, float("inf")])
def test_a_rate_that_is_no_frame_rate_is_refused(rate_hz: float) -> None:
    """0 or nan gave scipy's 'attempt to get argmin of an empty sequence'; -25 was accepted."""
    with pytest.raises(TrackmeterError, match=r"rate_hz must be a positive, finite frame rate"):
        PoseFilter(FilterParams(), rate_hz)


def test_a_non_finite_pose_is_refused_and_does_not_poison_the_filter() -> None:
    """One NaN position made every later output NaN (the IIR state kept it)."""
    f = PoseFilter(FilterParams(velocity_compensated=False), 25.0)
    for k in range(5):
        f.update(k / 25, np.eye(3), [0.0, 0.0, 3.5])
    with pytest.raises(TrackmeterError, match=r"p_cam\[1\] is not finite"):
        f.update(5 / 25, np.eye(3), [0.0, np.nan, 3.5])
    R_bad = np.eye(3)
    R_bad[0, 0] = np.inf
    with pytest.raises(TrackmeterError, match=r"R_cam_body\[0\] is not finite"):
        f.update(5 / 25, R_bad, [0.0, 0.0, 3.5])
    R_out, p_out = f.update(6 / 25, np.eye(3), [0.0, 0.0, 3.5])
    assert np.all(np.isfinite(R_out)) and np.allclose(p_out, [0.0, 0.0, 3.5])


@pytest.mark.parametrize("fresh", [True, False])
def test_a_reflection_or_a_time_that_is_no_number_is_refused_and_does_not_poison_the_filter(fresh: bool) -> None:
    """A reflection (det -1) given to a fresh filter was taken as its base, and every later
    pose then failed with scipy's "Non-positive determinant"; mid-stream that ValueError came
    raw; a NaN time was taken silently (a re-check)."""
    f = PoseFilter(FilterParams(velocity_compensated=False), 25.0)
    if not fresh:
        for k in range(5):
            f.update(k / 25, np.eye(3), [0.0, 0.0, 3.5])
    with pytest.raises(TrackmeterError, match=r"R_cam_body must be a rotation"):
        f.update(5 / 25, np.diag([1.0, 1.0, -1.0]), [0.0, 0.0, 3.5])
    with pytest.raises(TrackmeterError, match=r"R_cam_body must be a rotation"):
        f.update(5 / 25, 2 * np.eye(3), [0.0, 0.0, 3.5])
    with pytest.raises(TrackmeterError, match=r"t_s is not finite"):
        f.update(np.nan, np.eye(3), [0.0, 0.0, 3.5])
    R_out, p_out = f.update(6 / 25, np.eye(3), [0.0, 0.0, 3.5])
    assert np.allclose(R_out, np.eye(3)) and np.allclose(p_out, [0.0, 0.0, 3.5])


def test_a_new_cutoff_takes_over_from_the_last_output_without_a_step() -> None:
    """The console's cutoff field rebuilt the filter, whose first output was the raw pose: a
    1.6 mm step in a probe's run. Retuned, the filter starts at rest on its last output (the
    chart's zero state), so the next output is that output moved by the new design's first
    coefficient times the new sample's offset from it: sos[:, 0]'s product (scipy)."""
    rng = np.random.default_rng(3)
    f = PoseFilter(FilterParams(cutoff_hz=2.0, order=2, velocity_compensated=False), RATE)
    R_true, p_true = rotation_at(0.0), np.array([0.1, -0.2, 3.5])
    for k in range(50):
        R_out, p_out = f.update(k / RATE, R_true, p_true + rng.normal(0, 2e-3, 3))
    retuned = f.retuned(FilterParams(cutoff_hz=0.5, order=2, velocity_compensated=False))
    assert retuned.params.cutoff_hz == 0.5 and f.params.cutoff_hz == 2.0  # a new filter; the old one as it was
    p_new = p_true + np.array([4e-3, -3e-3, 5e-3])
    R_new = R_true @ Rotation.from_rotvec([0.004, -0.002, 0.003]).as_matrix()
    R_next, p_next = retuned.update(50 / RATE, R_new, p_new)
    gain = float(np.prod(design_lowpass(0.5, 2, RATE)[:, 0]))
    np.testing.assert_allclose(p_next - p_out, gain * (p_new - p_out), atol=1e-15)
    np.testing.assert_allclose(Rotation.from_matrix(R_out.T @ R_next).as_rotvec(),
                               gain * Rotation.from_matrix(R_out.T @ R_new).as_rotvec(), atol=1e-12)
    rebuilt = PoseFilter(FilterParams(cutoff_hz=0.5, order=2, velocity_compensated=False), RATE)
    assert np.allclose(rebuilt.update(50 / RATE, R_new, p_new)[1], p_new)  # what it did: the raw pose
    fresh = PoseFilter(FilterParams(cutoff_hz=0.5), RATE).retuned(FilterParams(cutoff_hz=1.0))
    assert np.allclose(fresh.update(0.0, R_new, p_new)[1], p_new)  # nothing to take over: starts as a new one


def test_the_cutoff_is_kept_up_to_095_of_nyquist_and_clipped_there() -> None:
    """design_lowpass is scipy's Butterworth at the cutoff asked for while it is below 0.95 of
    Nyquist (10 Hz at 25 Hz: Nyquist 12.5 Hz), and at 0.95 * 12.5 Hz above (its docstring)."""
    np.testing.assert_allclose(design_lowpass(10.0, 2, RATE), signal.butter(2, 10.0, fs=RATE, output="sos"),
                               rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(design_lowpass(20.0, 2, RATE), signal.butter(2, 0.95 * 12.5, fs=RATE, output="sos"),
                               rtol=1e-12, atol=1e-14)


def test_a_frame_without_velocity_forgets_the_last_one_so_the_next_moves_the_chart_by_its_own() -> None:
    """After an update without v_cam (rates unknown, a gap) the next velocity is not averaged with
    the one before it: the chart moves by v2 dt, not (v1 + v2) dt / 2. Checked by the chart's
    shift invariance: moving the chart by s with the filter's state unchanged gives the output
    of an unmoved chart fed the pose shifted by -s, plus s (x = p - p_base enters the IIR)."""
    v1, v2 = np.array([0.02, -0.01, 0.03]), np.array([-0.03, 0.02, 0.01])
    dt = 1.0 / RATE
    rng = np.random.default_rng(5)
    noise = rng.normal(0.0, 1e-3, (21, 3))

    def history() -> PoseFilter:
        f = PoseFilter(FilterParams(cutoff_hz=2.0, order=2, velocity_compensated=True), RATE)
        for k in range(20):
            f.update(k * dt, R0, v1 * k * dt + noise[k], v1)
        f.update(20 * dt, R0, v1 * 20 * dt + noise[20], None)  # rates unknown in this frame
        return f

    p = v1 * 20 * dt + v2 * dt + np.array([1e-3, -2e-3, 0.5e-3])
    _, p_moved = history().update(21 * dt, R0, p, v2)
    _, p_still = history().update(21 * dt, R0, p - v2 * dt, None)
    np.testing.assert_allclose(p_moved, p_still + v2 * dt, rtol=0, atol=1e-12)


def test_a_pose_out_of_time_order_starts_the_filter_over() -> None:
    """A repeated or backward time did not move the chart back and the next frame moved it
    twice: one frame out of order left the output 7.6 mm off under constant velocity (an outside
    code review). It starts over from that pose, as the velocity estimator does."""
    f = PoseFilter(FilterParams(cutoff_hz=1.0, order=2, velocity_compensated=True), RATE)
    v = np.array([0.01, -0.02, 0.005])
    w = AXIS * RATE_RAD_S
    for ti in np.arange(20) / RATE:
        f.update(ti, rotation_at(ti), v * ti, v, w)
    back = 10 / RATE
    R, p = f.update(back, rotation_at(back), v * back, v, w)
    np.testing.assert_allclose(p, v * back, atol=1e-12)  # the first pose of a new start
    for ti in back + np.arange(1, 6) / RATE:
        R, p = f.update(ti, rotation_at(ti), v * ti, v, w)
        np.testing.assert_allclose(p, v * ti, atol=1e-9)
        assert Rotation.from_matrix(R @ rotation_at(ti).T).magnitude() < 1e-9
