"""benchmarks.error_budget's measurement statistics on a hand-made record (closed-form answers)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from benchmarks.error_budget import joint_fit, measurement_stats, oracle_frames
from trackmeter.core.targets import TargetState


def _target(tid: str, point_cam: np.ndarray, sigma_m: float, status: str = "tracking") -> TargetState:
    nan2 = np.full(2, np.nan)
    return TargetState(tid, "operator", status, np.zeros(2), nan2, np.asarray(point_cam, float),  # type: ignore[arg-type]
                       np.diag([1e-8, 1e-8, sigma_m**2]), 0.9, nan2, (0, 0, 1, 1))


def test_the_most_biased_a_priori_point_is_named_by_its_mean_depth_error_in_mm_and_sigmas() -> None:
    apriori = {"corner_a": np.array([0.1, 0.0, 0.0]), "corner_b": np.array([0.0, 0.2, 0.0])}
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    T[:3, 3] = (0.05, -0.02, 3.5)

    def seen(tid: str, dz_m: float, sigma_m: float) -> TargetState:
        return _target(tid, T[:3, :3] @ apriori[tid] + T[:3, 3] + [0.0, 0.0, dz_m], sigma_m)

    # corner_a: depth errors -6 and -10 mm (mean -8) at sigma 4 mm; corner_b: +3 and -1 mm (mean +1).
    frames = [(seen("corner_a", -0.006, 0.004), seen("corner_b", 0.003, 0.002)),
              (seen("corner_a", -0.010, 0.004), seen("corner_b", -0.001, 0.002)),
              # 200 mm off: a lock on another surface, not a bias; a lost target: no measurement.
              (seen("corner_a", 0.2, 0.004), _target("corner_b", np.full(3, np.nan), np.nan, "lost"))]
    rec = {"targets": frames, "truth": [(0.04 * k, T, None, None) for k in range(3)],
           "surface": [{} for _ in frames], "apriori": apriori}
    out = measurement_stats(rec)
    assert np.isclose(out["apriori_depth_bias_worst_mm"], -8.0)
    assert np.isclose(out["apriori_depth_bias_worst_sigmas"], -2.0)
    assert np.isclose(out["apriori_depth_error_median_mm"], np.median([6, 10, 3, 1]))
    assert np.isclose(out["apriori_lateral_error_median_mm"], 0.0, atol=1e-9)


def test_an_a_priori_oracle_with_a_bias_is_the_same_draw_moved_by_a_constant_per_point() -> None:
    """oracle_frames(apriori_bias_sd_m=...): each a-priori point is off by ONE offset of its own in
    every frame (a bias, not noise), depth about three times x and y; the noise and the
    automatic targets are those of the unbiased oracle."""
    apriori = {f"corner_{i}": np.array([0.1 * i, 0.05, -0.02 * i]) for i in range(40)}
    Ts = []
    for k in range(4):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec([0.05 * k, -0.1, 0.2]).as_matrix()
        T[:3, 3] = (0.01 * k, -0.02, 3.5)
        Ts.append(T)
    frames = [tuple(_target(tid, T[:3, :3] @ b + T[:3, 3], 0.002) for tid, b in apriori.items())
              + (_target("auto_1", T[:3, 3], 0.002),) for T in Ts]
    rec = {"targets": frames, "truth": [(0.04 * k, T, None, None) for k, T in enumerate(Ts)],
           "surface": [{"auto_1": np.zeros(3)} for _ in frames], "apriori": apriori}
    plain = oracle_frames(rec, apriori=True, auto=True, pinned=False)
    biased = oracle_frames(rec, apriori=True, auto=True, pinned=False, apriori_bias_sd_m=0.003)
    offsets = np.array([[np.asarray(b.point_cam) - np.asarray(p.point_cam) for p, b in zip(fp, fb)]
                        for fp, fb in zip(plain, biased)])  # (frames, targets, 3)
    assert np.allclose(offsets, offsets[0], atol=1e-12)  # constant per point over the frames
    assert np.allclose(offsets[0, -1], 0.0)  # the automatic target: untouched
    sd = offsets[0, :-1].std(axis=0)
    assert 0.002 < sd[2] < 0.004 and np.all((0.0005 < sd[:2]) & (sd[:2] < 0.0015))


def test_asking_a_standalone_benchmark_for_help_does_not_start_it() -> None:
    # error_budget runs a 60 s chain and a dozen replays: --help must only print the docstring.
    import subprocess
    import sys
    from pathlib import Path

    for module in ("error_budget", "render", "select"):
        proc = subprocess.run([sys.executable, "-m", f"benchmarks.{module}", "--help"], capture_output=True, text=True,
                              timeout=60, cwd=Path(__file__).resolve().parent.parent)
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.startswith(f"usage: python -m benchmarks.{module}") and "{" not in proc.stdout.splitlines()[0]


def _rigid_frames(n_frames: int, apriori: dict[str, np.ndarray], grown: dict[str, np.ndarray], sigma_m: float
                  ) -> tuple[list[np.ndarray], list[tuple[TargetState, ...]]]:
    """A body turning 2 deg a frame about a tilted axis at 3.5 m, every point measured exactly."""
    poses, frames = [], []
    for k in range(n_frames):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(np.radians(2.0 * k) * np.array([0.6, 0.8, 0.0])).as_matrix()
        T[:3, 3] = (0.01 * k, -0.02, 3.5 - 0.005 * k)
        poses.append(T)
        frames.append(tuple(_target(tid, T[:3, :3] @ X + T[:3, 3], sigma_m) for tid, X in {**apriori, **grown}.items()))
    return poses, frames


def _turned(T: np.ndarray, rotvec: np.ndarray, shift_m: np.ndarray) -> np.ndarray:
    out = T.copy()
    out[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix() @ T[:3, :3]
    out[:3, 3] += shift_m
    return out


def test_the_joint_fit_recovers_every_pose_from_exact_measurements_and_poses_a_little_off() -> None:
    rng = np.random.default_rng(4)
    apriori = {f"corner{i}": p for i, p in enumerate(np.array([[0.4, 0.0, 0.0], [0.0, 0.3, 0.0], [0.0, 0.0, 0.25]]))}
    grown = {f"auto{i}": rng.uniform(-0.3, 0.3, 3) for i in range(6)}
    poses, frames = _rigid_frames(12, apriori, grown, 0.002)
    # The a-priori points are seen in the first frames only: the later poses hang on the grown points.
    frames = [f if k < 4 else tuple(t for t in f if t.id.startswith("auto")) for k, f in enumerate(frames)]
    frames[7] = frames[7][:2]  # two points: no pose there
    start = [_turned(T, np.radians(1.0) * rng.standard_normal(3), 0.005 * rng.standard_normal(3)) for T in poses]
    start[5] = None  # no starting pose: the nearest frame's
    fitted = joint_fit(frames, apriori, start)
    assert fitted[7] is None
    for k, (T, F) in enumerate(zip(poses, fitted)):
        if k == 7:
            continue
        assert F is not None
        np.testing.assert_allclose(F[:3, 3], T[:3, 3], atol=1e-7)
        np.testing.assert_allclose(F[:3, :3], T[:3, :3], atol=1e-7)


def test_the_joint_fit_holds_a_pose_against_one_point_measured_on_another_surface() -> None:
    rng = np.random.default_rng(5)
    apriori = {f"corner{i}": p for i, p in enumerate(np.array([[0.4, 0.0, 0.0], [0.0, 0.3, 0.0], [0.0, 0.0, 0.25]]))}
    grown = {f"auto{i}": rng.uniform(-0.3, 0.3, 3) for i in range(5)}
    poses, frames = _rigid_frames(8, apriori, grown, 0.001)
    bad = list(frames[3])
    bad[4] = _target(bad[4].id, bad[4].point_cam + [0.0, 0.0, 0.05], 0.001)  # 50 mm off: 50 sigma
    frames[3] = tuple(bad)

    def error_mm(huber_sigmas: float) -> float:
        fitted = joint_fit(frames, apriori, poses, huber_sigmas=huber_sigmas)
        return float(np.linalg.norm(fitted[3][:3, 3] - poses[3][:3, 3]) * 1e3)  # type: ignore[index]

    # Plain least squares (a Huber threshold no residual reaches) is bent by millimetres.
    assert error_mm(1e9) > 3.0
    assert error_mm(2.0) < 0.5


def test_a_replay_of_exact_measurements_gives_the_true_pose() -> None:
    # replay() runs a fresh engine on a tracker double that hands it recorded targets: an
    # engine that asks its tracker something new broke it (the model's ids reserved,
    # 2026-12-07), which only the 60 s benchmark would have shown.
    from benchmarks.error_budget import replay
    from trackmeter.core.targets import TargetState
    from trackmeter.sources.sim.simulator import Simulator

    sim = Simulator("estec")
    model = sim.model
    rect = sim.rig.rectification
    truth, frames = [], []
    for k in range(40):
        gt = sim.truth(k)
        T = np.asarray(gt.T_cam_body)
        X = model.points_body @ T[:3, :3].T + T[:3, 3]
        uv_l, uv_r = sim.rig.project(X)
        uv_rect, d = rect.project_rectified(X)
        C = rect.point_covariance(uv_rect, d, 0.05, 0.05)
        truth.append((sim.time_of(k), T, np.asarray(gt.velocity_cam_m_s), np.asarray(gt.omega_body_rad_s)))
        frames.append(tuple(TargetState(pid, "operator", "tracking", uv_l[i], uv_r[i], X[i], C[i], 0.99, uv_l[i],
                                        (0, 0, 1, 1), age_frames=k)
                            for i, pid in enumerate(model.ids) if X[i, 2] > 0))
    rec = {"rig": sim.rig, "model": model, "truth": truth}
    true, est = replay(rec, frames)
    assert est.valid[5:].all()
    # within the output low-pass filter's lag on this slow drift (a few micrometres)
    assert np.abs(est.position_m[5:] - true.position_m[5:]).max() < 2e-5
