"""The per-target image-plane Kalman filter: constant-acceleration model, noise, gating, window."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.common import Q_discrete_white_noise
from scipy.stats import chi2

from trackmeter.core import kalman
from trackmeter.core.kalman import KalmanParams


def test_transition_is_exact_for_constant_acceleration() -> None:
    dt = 0.04
    x = np.array([10.0, -5.0, 300.0, -120.0, 800.0, 50.0])  # u, v, u', v', u'', v''
    out = kalman.transition_matrix(dt) @ x
    pos = x[:2] + x[2:4] * dt + 0.5 * x[4:6] * dt**2
    vel = x[2:4] + x[4:6] * dt
    np.testing.assert_allclose(out, np.r_[pos, vel, x[4:6]], rtol=0, atol=1e-12)


def test_process_noise_is_filterpys_discrete_white_noise_in_our_state_order() -> None:
    dt, s = 0.04, 500.0
    Q = kalman.process_noise(dt, s)
    # Per axis, Gamma Gamma^T var with Gamma = (dt²/2, dt, 1) (Bar-Shalom 6.3.3).
    g = np.array([dt**2 / 2, dt, 1.0])
    per_axis = np.outer(g, g) * s**2
    for axis in (0, 1):
        idx = [axis, axis + 2, axis + 4]
        np.testing.assert_allclose(Q[np.ix_(idx, idx)], per_axis, rtol=1e-12)
    np.testing.assert_allclose(Q, Q_discrete_white_noise(3, dt, s**2, block_size=2, order_by_dim=False))
    assert Q[0, 1] == 0.0  # axes independent


def test_filter_learns_velocity_and_acceleration_and_predicts_the_next_frame() -> None:
    p = KalmanParams(initial_velocity_sigma_px_s=1000.0)  # starts fast with no velocity guess
    dt = 0.04
    u = lambda t: 100 + 400 * t + 0.5 * 600 * t**2  # noqa: E731
    v = lambda t: 200 - 250 * t  # noqa: E731
    kf = kalman.make_filter((u(0), v(0)), p)
    rng = np.random.default_rng(0)
    for k in range(1, 60):
        kalman.predict(kf, dt, p)
        ok, _ = kalman.update(kf, (u(k * dt) + rng.normal(0, 0.05), v(k * dt) + rng.normal(0, 0.05)), p)
        assert ok
    kalman.predict(kf, dt, p)
    t = 60 * dt
    sigma = np.sqrt(np.diag(kalman.innovation_covariance(kf)))
    assert np.all(sigma < 1.0)
    assert abs(kf.x[0] - u(t)) < 3 * sigma[0] and abs(kf.x[1] - v(t)) < 3 * sigma[1]
    assert abs(kf.x[2] - (400 + 600 * t)) < 15 and abs(kf.x[3] + 250) < 15


def test_gate_rejects_a_jump_and_keeps_the_prediction() -> None:
    p = KalmanParams()
    kf = kalman.make_filter((50.0, 50.0), p, velocity_px_s=(0, 0))
    for k in range(20):
        kalman.predict(kf, 0.04, p)
        kalman.update(kf, (50.0, 50.0), p)
    kalman.predict(kf, 0.04, p)
    before = kf.x.copy()
    S = kalman.innovation_covariance(kf)
    jump = 30.0
    ok, d2 = kalman.update(kf, (50.0 + jump, 50.0), p)
    assert not ok
    assert d2 == pytest.approx(jump**2 / S[0, 0], rel=1e-6) if S[0, 1] == 0 else d2 > 100
    np.testing.assert_array_equal(kf.x, before)  # not fused
    assert kalman.gate_threshold(p.gate_probability) == pytest.approx(chi2.ppf(p.gate_probability, 2))
    ok, _ = kalman.update(kf, (50.1, 49.9), p)
    assert ok


def test_search_window_follows_the_predicted_covariance() -> None:
    p = KalmanParams()
    kf = kalman.make_filter((0.0, 0.0), p)
    kalman.predict(kf, 0.04, p)
    first = kalman.search_half_size(kf, p, 0.0, 1e9)
    s = np.sqrt(np.diag(kalman.innovation_covariance(kf)))
    np.testing.assert_allclose(first, p.window_sigmas * s)
    for _ in range(30):
        kalman.update(kf, (0.0, 0.0), p)
        kalman.predict(kf, 0.04, p)
    settled = kalman.search_half_size(kf, p, 0.0, 1e9)
    assert np.all(settled < first / 3)  # a settled target is searched in a small window
    np.testing.assert_allclose(kalman.search_half_size(kf, p, 5.0, 6.0), np.clip(settled, 5.0, 6.0))


def test_batched_predict_and_update_equal_filterpys() -> None:
    p = KalmanParams()
    rng = np.random.default_rng(2)
    ours, ref = [], []
    for i in range(5):
        a = kalman.make_filter(rng.uniform(0, 500, 2), p, velocity_px_s=rng.normal(0, 100, 2))
        b = kalman.make_filter(a.x[:2], p, velocity_px_s=a.x[2:4])
        ours.append(a)
        ref.append(b)
    dts = [0.04, 0.04, 0.02, 0.04, 0.0]
    kalman.predict_many(ours, dts, p)
    for kf, dt in zip(ref, dts):
        if dt > 0:
            kalman.predict(kf, dt, p)
    for a, b in zip(ours, ref):
        np.testing.assert_allclose(a.x, b.x, rtol=1e-12)
        np.testing.assert_allclose(a.P, b.P, rtol=1e-10)
    np.testing.assert_allclose(
        kalman.search_half_sizes(ours, p, 0, 1e9), np.array([kalman.search_half_size(k, p, 0, 1e9) for k in ref])
    )
    z = np.array([kf.x[:2] + rng.normal(0, 0.5, 2) for kf in ref])
    z[1] += 1000.0  # a jump: gated out
    accepted, d2 = kalman.update_many(ours, z, p)
    for i, kf in enumerate(ref):
        ok, d2_ref = kalman.update(kf, z[i], p)
        assert ok == accepted[i]
        assert d2[i] == pytest.approx(d2_ref, rel=1e-9)
        np.testing.assert_allclose(ours[i].x, kf.x, rtol=1e-10)
        np.testing.assert_allclose(ours[i].P, kf.P, rtol=1e-8, atol=1e-12)
    assert not accepted[1]


def test_a_measurement_that_is_not_finite_is_rejected_by_both_forms() -> None:
    """update() let a NaN through its gate (NaN > gate is False) and wrote NaN into the state,
    where update_many rejected it (an outside code review)."""
    p = KalmanParams()
    one = kalman.make_filter((50.0, 50.0), p, velocity_px_s=(0, 0))
    many = kalman.make_filter((50.0, 50.0), p, velocity_px_s=(0, 0))
    accepted, _ = kalman.update(one, (np.nan, 50.0), p)
    accepted_many, _ = kalman.update_many([many], np.array([[np.nan, 50.0]]), p)
    assert not accepted and not accepted_many[0]
    assert np.all(np.isfinite(one.x)) and np.array_equal(one.x, many.x)
