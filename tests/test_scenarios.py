"""Scenarios and the Simulator source: loading, determinism, ground truth, the motions asked for."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from trackmeter.core.dynamics import symmetric_precession_rate
from trackmeter.core.transforms import apply_transform, matrix_to_quat_wxyz, omega_body_between
from trackmeter.data.config import load_config
from trackmeter.errors import TrackmeterError
from trackmeter.paths import SCENARIOS_DIR
from trackmeter.sources import open_source
from trackmeter.sources.sim.scenario import load_scenario
from trackmeter.sources.sim.simulator import Simulator

SCENARIOS = sorted(p.stem for p in SCENARIOS_DIR.glob("*.yaml"))
DEG = np.pi / 180


@pytest.fixture(scope="module")
def sims() -> dict[str, Simulator]:
    return {name: Simulator(load_scenario(name)) for name in SCENARIOS}


def test_the_five_scenarios_exist():
    assert {"estec", "fast_tumble", "approach", "harsh_light", "static_ranges"} <= set(SCENARIOS)


def test_estec_is_the_papers_trial(sims):
    sim = sims["estec"]
    sc = sim.scenario
    assert sim.true_rig.image_size == (726, 512)
    assert sim.true_rig.left.focal_px == pytest.approx(1152.0)  # 12 mm lens
    assert sim.true_rig.baseline_m == pytest.approx(0.28, abs=1e-6)
    assert sc.rate_hz == 25.0 and sim.n_frames == 1500  # 60 s
    t = np.arange(0, sim.n_frames, 25)
    truths = [sim.truth(int(i)) for i in t]
    ranges = np.array([np.linalg.norm(g.T_cam_body[:3, 3]) for g in truths])
    assert np.all(np.abs(ranges - 3.5) < 0.3)
    rates = np.array([np.linalg.norm(g.omega_body_rad_s) for g in truths]) / DEG
    assert np.all((rates > 1.0) & (rates < 10.0))  # a few deg/s
    # Symmetric body in precession with nutation: w3 constant, (w1, w2) turning at the closed-form rate.
    moments = sorted(sc.inertia_kg_m2)
    assert moments[1] == moments[2] or moments[0] == moments[1]
    w = np.array([g.omega_body_rad_s for g in truths])
    assert np.ptp(w[:, 2]) < 1e-12
    angle = np.unwrap(np.arctan2(w[:, 1], w[:, 0]))
    expected = symmetric_precession_rate(sc.inertia_kg_m2, w[0, 2])
    assert np.polyfit(t / 25.0, angle, 1)[0] == pytest.approx(expected, rel=1e-8)
    # Nutation: the symmetry axis is tilted from the (constant) angular momentum by a fixed angle.
    I = np.diag(sc.inertia_kg_m2)
    L = np.array([g.T_cam_body[:3, :3] @ I @ g.omega_body_rad_s for g in truths])
    z_axis = np.array([g.T_cam_body[:3, 2] for g in truths])
    nutation = np.degrees(np.arccos(np.einsum("ij,ij->i", z_axis, L) / np.linalg.norm(L, axis=1)))
    assert np.ptp(nutation) < 1e-6 and 10 < nutation[0] < 80
    assert np.allclose(L, L[0], atol=1e-9 * np.linalg.norm(L[0]))


@pytest.mark.parametrize("name", ["estec", "fast_tumble", "approach", "harsh_light", "hold_release"])
def test_truth_rates_are_the_derivatives_of_the_truth_pose(sims, name):
    sim = sims[name]
    for i in (0, sim.n_frames // 3, sim.n_frames - 2):
        g0, g1 = sim.truth(i), sim.truth(i + 1)
        gm = sim.truth(i)
        dt = 1 / sim.rate_hz
        # Omega (body, eq. 14) against the finite rotation between frames; velocity against the
        # position difference (both second-order accurate at the midpoint).
        w_fd = omega_body_between(matrix_to_quat_wxyz(g0.T_cam_body[:3, :3]), matrix_to_quat_wxyz(g1.T_cam_body[:3, :3]), dt)
        w_mid = 0.5 * (g0.omega_body_rad_s + g1.omega_body_rad_s)
        assert np.linalg.norm(w_fd - w_mid) < 2e-3 * max(np.linalg.norm(w_mid), 1e-3)
        v_fd = (g1.T_cam_body[:3, 3] - g0.T_cam_body[:3, 3]) / dt
        v_mid = 0.5 * (g0.velocity_cam_m_s + g1.velocity_cam_m_s)
        assert np.linalg.norm(v_fd - v_mid) < 1e-3 * max(np.linalg.norm(v_mid), 1e-3) + 1e-9
        assert gm.T_cam_body.shape == (4, 4)


def _max_image_speeds(sim: Simulator) -> np.ndarray:
    """Per frame interval, the fastest image speed of the mock-up's salient points (left image), px/s."""
    speeds = []
    pts = sim.model_points_body
    prev = None
    for i in range(sim.n_frames):
        uv = sim.true_rig.left.project(apply_transform(sim.truth(i).T_cam_body, pts))
        if prev is not None:
            speeds.append(np.max(np.linalg.norm(uv - prev, axis=1)) * sim.rate_hz)
        prev = uv
    return np.array(speeds)


def test_fast_tumble_passes_1000_px_per_s(sims):
    speeds = _max_image_speeds(sims["fast_tumble"])
    print(f"\nfast_tumble: max image speed median {np.median(speeds):.0f} px/s, max {speeds.max():.0f} px/s")
    assert np.median(speeds) > 1000.0


def test_estec_speeds_are_gentle(sims):
    speeds = _max_image_speeds(sims["estec"])
    assert speeds.max() < 200.0  # within the 1995 Kalman-aided tracker's 200 px/s


def test_approach_closes_from_10_to_2_m_while_tumbling(sims):
    sim = sims["approach"]
    z = np.array([sim.truth(i).T_cam_body[2, 3] for i in range(0, sim.n_frames, 5)])
    assert z[0] == pytest.approx(10.0) and z[-1] == pytest.approx(2.0)
    assert np.all(np.diff(z) <= 1e-12)
    assert np.linalg.norm(sim.truth(sim.n_frames - 1).omega_body_rad_s) > 2 * DEG


def test_static_ranges_hold_still_at_each_range(sims):
    sim = sims["static_ranges"]
    sc = sim.scenario
    assert sim.n_frames == len(sc.static_ranges_m) * sc.frames_per_range
    for i in range(sim.n_frames):
        g = sim.truth(i)
        assert np.linalg.norm(g.T_cam_body[:3, 3]) == pytest.approx(sim.static_range_of(i))
        assert np.all(g.velocity_cam_m_s == 0) and np.all(g.omega_body_rad_s == 0)
    assert [sim.static_range_of(k * sc.frames_per_range) for k in range(len(sc.static_ranges_m))] == list(sc.static_ranges_m)


def test_hold_release_holds_still_then_moves_as_estec_from_its_start(sims):
    # Case (c)'s scenario: the model is acquired while a manipulator holds the target still
    # (pose.still_time_s), then the target is released into the estec trial's motion.
    sim, estec = sims["hold_release"], sims["estec"]
    release = sim.scenario.release_s
    assert release >= 2 * load_config().pose.still_time_s
    k = int(round(release * sim.rate_hz))  # the frame of the release: the motion's first
    for i in range(k + 1):
        g = sim.truth(i)
        assert np.array_equal(g.T_cam_body, estec.truth(0).T_cam_body)
        if i < k:
            assert np.all(g.velocity_cam_m_s == 0) and np.all(g.omega_body_rad_s == 0)
    for j in (0, 1, 25, 200):
        g, e = sim.truth(k + j), estec.truth(j)
        np.testing.assert_allclose(g.T_cam_body, e.T_cam_body, atol=1e-8)  # two integrations' tolerance
        np.testing.assert_allclose(g.omega_body_rad_s, e.omega_body_rad_s, atol=1e-10)
        np.testing.assert_allclose(g.velocity_cam_m_s, e.velocity_cam_m_s, atol=1e-12)
    with pytest.raises(TrackmeterError, match="release_s"):
        dataclasses.replace(sim.scenario, release_s=-1.0)


def test_harsh_light_has_a_low_sun_and_a_passing_occluder(sims):
    sim = sims["harsh_light"]
    # Low sun: nearly perpendicular to the viewing axis.
    assert abs(sim.sun_dir_cam[2]) < 0.5
    present = [len(sim.occluders_at(i)) for i in range(sim.n_frames)]
    assert present[0] == 0 and max(present) == 1 and present[-1] == 0
    # While present, the panel does hide part of the target: some pixels of the target's image
    # see no body surface that they see without the panel.
    i = int(np.argmax(np.array(present) > 0)) + int(4 * sim.rate_hz)
    assert present[i] == 1
    occ = sim.occluders_at(i)[0]
    centre_uv = sim.true_rig.left.project(occ.T_cam_occluder[:3, 3][None])[0]
    assert np.all(np.isnan(sim.surface_points(i, centre_uv[None])))


def test_frames_are_deterministic_and_random_access(sims):
    sim = sims["estec"]
    a = sim.frame(7)
    b = Simulator(sim.scenario, mockup=sim.mockup).frame(7)
    assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
    assert a.left.shape == (512, 726) and a.left.dtype == np.uint8
    # Sequential reading gives the same frame 7, and differs from frame 8 (noise and motion).
    seq = Simulator(sim.scenario, mockup=sim.mockup)
    frames = [seq.read() for _ in range(9)]
    assert np.array_equal(frames[7].left, a.left) and frames[7].t_s == pytest.approx(7 / 25)
    assert not np.array_equal(frames[8].left, a.left)


def test_surface_points_follow_a_model_point(sims):
    """The pixel where a visible bus corner projects sees (nearly) that body point."""
    sim = sims["estec"]
    for i in (0, 600):
        T = sim.truth(i).T_cam_body
        # A point in the middle of the bus face turned most toward the camera.
        normals = {"+x": (0, 0.4), "-x": (0, -0.4), "+z": (2, 0.45), "-z": (2, -0.45)}
        best = None
        for axis, (k, c) in normals.items():
            p = np.zeros(3)
            p[k] = c
            n = np.sign(c) * np.eye(3)[k]
            facing = -(T[:3, :3] @ n) @ apply_transform(T, p)
            if best is None or facing > best[0]:
                best = (facing, p)
        p = best[1]
        uv = sim.true_rig.left.project(apply_transform(T, p[None]))
        got = sim.surface_points(i, uv)[0]
        assert np.linalg.norm(got - p) < 0.01


def test_sim_specs(sims):
    src = open_source("sim")
    assert isinstance(src, Simulator) and src.scenario.name == "estec"
    assert open_source("sim:harsh_light").scenario.name == "harsh_light"
    assert open_source(f"sim:{SCENARIOS_DIR / 'approach.yaml'}").scenario.name == "approach"
    with pytest.raises(TrackmeterError, match="no scenario"):
        open_source("sim:no_such_scenario")


def test_loop_keeps_time_increasing(sims, tmp_path):
    sc = sims["estec"].scenario.with_duration(0.12)
    sim = Simulator(sc, mockup=sims["estec"].mockup, loop=True)
    assert sim.n_frames == 3
    frames = [sim.read() for _ in range(7)]
    assert [f.index for f in frames] == list(range(7))
    assert np.allclose(np.diff([f.t_s for f in frames]), 0.04)
    # The scene jumps where a pass starts again: those frames are marked, the others not.
    assert [f.cut for f in frames] == [False, False, False, True, False, False, True]
    sim.restart()
    assert [sim.read().cut for _ in range(2)] == [True, False]
    assert np.array_equal(frames[3].left, frames[0].left)
    assert np.array_equal(sim.truth(frames[5].index).T_cam_body, frames[5].truth.T_cam_body)
    uv = np.array([[363.0, 256.0]])
    assert np.array_equal(sim.surface_points(frames[5].index, uv), sim.surface_points(2, uv), equal_nan=True)
    once = Simulator(sc, mockup=sims["estec"].mockup)
    assert [once.read() is None for _ in range(4)] == [False, False, False, True]


def test_rig_override_is_reported_not_rendered(sims, estec_rig):
    from trackmeter.data.rigfile import load_rig
    from trackmeter.paths import RIGS_DIR

    other = load_rig(RIGS_DIR / "estec_8mm.yaml")
    sim = Simulator(sims["estec"].scenario, rig_override=other, mockup=sims["estec"].mockup)
    assert sim.rig is other
    assert np.allclose(sim.true_rig.left.K, estec_rig.left.K)
    assert sim.frame_size == estec_rig.image_size  # the size of the rendered frames, not of the reported rig


@pytest.mark.parametrize(
    "text, match",
    [
        ("omega0_body_deg_s: [1, 2]", r"'omega0_body_deg_s'"),
        ("omega0_body_deg_s: [1, two, 3]", r"'omega0_body_deg_s\[1\]'"),
        # A typo's rate (1e8 deg/s) integrated for minutes without a word before a frame came.
        ("omega0_body_deg_s: [1.0e8, 0, 0]", r"'omega0_body_deg_s\[0\]': expected a value in \[-3600.0, 3600.0\]"),
        ("inertia_kg_m2: [1, 1, 5]", "triangle inequality"),
        ("rate_hz: -25", "'rate_hz'"),
        ("render: {no_such_knob: 1}", r"unknown key 'render.no_such_knob'"),
        ("occluders: [{start_s: 5, end_s: 2}]", "occluders\\[0\\]"),
        ("spin: 3", "unknown key 'spin'"),
        ("rig: no_such_rig.yaml", "'rig': no such file"),
        ("mockup: nothing.yaml", "'mockup': no such file"),
        ("approach_to_m: [0, 0, 2]", "approach_s"),
        ("seed: [1", "malformed YAML"),
        # An hour at 10 kHz: 36 million frames, integrated before the first (gigabytes).
        ("rate_hz: 10000\nduration_s: 3600", r"36000000 frames \('duration_s' 3600 s at 'rate_hz' 10000\): at most 360000"),
        # Said as the range -2 is said in (an outside probe: "must be positive" against "[0.0, 3600.0]").
        ("duration_s: 0", r"'duration_s': expected a value in \(0, 3600\] \(0 only with 'static_ranges_m', which "
                          r"sets the frames\), got 0"),
    ],
)
def test_malformed_scenarios_name_the_key(tmp_path, text, match):
    path = tmp_path / "bad.yaml"
    path.write_text(text + "\n")
    with pytest.raises(TrackmeterError, match=match) as info:
        load_scenario(path)
    assert str(path) in str(info.value)


@pytest.mark.slow
def test_estec_depth_sigma_matches_paper():
    """estec's noise gives the paper's single-point depth sigma: 4 mm at 3.5 m (eq. 2: 0.105 px)."""
    from trackmeter.sources.sim.noise_calibration import static_depth_sigma

    r = static_depth_sigma(load_scenario("estec"))
    print(f"\nestec static point at 3.5 m: sigma_z {r.sigma_z_m * 1e3:.2f} mm, sigma_d {r.sigma_disparity_px:.3f} px, "
          f"{r.n_points} points x {r.n_frames} frames, default matcher accepts {r.accepted_default_fraction:.0%}")
    assert r.n_points >= 100
    assert r.sigma_z_m == pytest.approx(0.004, rel=0.1)
    assert r.sigma_disparity_px == pytest.approx(0.004 * 1152 * 0.28 / 3.5**2, rel=0.1)
    assert r.outlier_fraction < 0.01


def test_an_empty_scenario_file_is_warned_about(tmp_path) -> None:
    """``sim:empty.yaml`` ran the default scenario without a word: most likely the wrong file."""
    import warnings

    from trackmeter.sources.sim.scenario import Scenario, load_scenario

    empty = tmp_path / "empty.yaml"
    empty.write_text("# nothing yet\n")
    with pytest.warns(UserWarning, match=r"empty\.yaml: no settings: every one is the default"):
        scenario = load_scenario(empty)
    assert scenario.duration_s == Scenario().duration_s
    named = tmp_path / "named.yaml"
    named.write_text("duration_s: 2.0\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_scenario(named)
