"""Property tests (Hypothesis) of the file contracts other tools read (DESIGN.md section 6):
what we write reads back as what was written, over the whole range of values, not only the
hand-picked series of test_motion_csv.py, test_rigfile.py and test_track_cli.py.

- TUM (``t tx ty tz qx qy qz qw``): nine decimals, so back within half a nanosecond / nanometre
  (and the float's own spacing for large clock times), the rotation within a few nanoradians;
- ``states.csv``/``groundtruth.csv``: every value but ``t`` shortest round-trip text, so back
  exactly (the quaternion within an ulp or two: it is renormalised when read); ``t`` with nine
  decimals, as in the TUM file; an invalid row's NaN stays NaN, and -0.0 stays -0.0;
- the rig (OpenCV FileStorage YAML): back exactly.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from tempfile import TemporaryDirectory

import numpy as np
from hypothesis import example, given, reject, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from trackmeter.core.stereo import Camera, StereoRig
from trackmeter.core.transforms import quat_signs_continuous
from trackmeter.data.motion_csv import MotionSeries, read_motion_csv, write_groundtruth_csv, write_states_csv
from trackmeter.data.rigfile import load_rig, save_rig
from trackmeter.data.trajectory import Trajectory, read_tum, write_tum
from trackmeter.errors import TrackmeterError


def _floats(bound: float) -> st.SearchStrategy[float]:
    return st.floats(-bound, bound, allow_nan=False, allow_infinity=False)


@st.composite
def _times(draw: st.DrawFn, n: int) -> np.ndarray:
    """``n`` strictly increasing times: a clock from a run's 0 s to a Unix time's 2e9 s, steps
    from 1 ms (a fast camera) to 100 s (a sparse truth), each at least 20 float spacings."""
    t0 = draw(st.one_of(st.just(0.0), _floats(1e4), st.floats(1e9, 2e9)))
    steps = draw(arrays(np.float64, n, elements=st.floats(1e-3, 100.0)))
    t = t0 + np.concatenate([[0.0], np.cumsum(steps[1:])])
    if np.any(np.diff(t) <= 20 * np.spacing(np.abs(t[1:]))):
        reject()  # a time step below the float's resolution at this clock is no step: draw another
    return t


@st.composite
def _quats(draw: st.DrawFn, n: int) -> np.ndarray:
    seed = draw(st.integers(0, 2**32 - 1))
    return Rotation.random(n, rng=np.random.default_rng(seed)).as_quat(scalar_first=True)


def _angle_between(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Rotation angle (rad) between unit quaternions row by row (q and -q alike); scipy's
    magnitude (an arctan2, where an arccos of the dot product loses 1e-8 rad near zero)."""
    r1, r2 = Rotation.from_quat(q1, scalar_first=True), Rotation.from_quat(q2, scalar_first=True)
    return np.asarray((r1.inv() * r2).magnitude())


@settings(max_examples=60, deadline=None)
@given(data=st.data(), n=st.integers(1, 12))
def test_tum_round_trip(data: st.DataObject, n: int) -> None:
    t = data.draw(_times(n))
    p = data.draw(arrays(np.float64, (n, 3), elements=_floats(1e4)))
    q = data.draw(_quats(n))
    with TemporaryDirectory() as tmp:
        back = read_tum(write_tum(Path(tmp) / "trajectory.tum", Trajectory(t, p, q)))
    assert len(back) == n
    # Nine decimals: half a unit of the ninth, plus the float's spacing where that is coarser.
    np.testing.assert_allclose(back.t_s, t, rtol=0, atol=0.5e-9 + float(np.spacing(np.abs(t).max())))
    np.testing.assert_allclose(back.position_m, p, rtol=0, atol=0.5e-9 + float(np.spacing(1e4)))
    # Each component within 0.5e-9, the quaternion renormalised on reading: a few nanoradians.
    assert float(_angle_between(back.quat_wxyz, q).max()) < 1e-8


@st.composite
def _series(draw: st.DrawFn, with_extra: bool) -> MotionSeries:
    n = draw(st.integers(1, 10))
    t = draw(_times(n))
    valid = draw(arrays(np.bool_, n))
    values = st.one_of(_floats(1e6), st.floats(-1e-6, 1e-6, allow_nan=False), st.just(-0.0))
    p = draw(arrays(np.float64, (n, 3), elements=values))
    q = draw(_quats(n))
    v = draw(arrays(np.float64, (n, 3), elements=st.one_of(values, st.just(math.nan))))
    w = draw(arrays(np.float64, (n, 3), elements=st.one_of(values, st.just(math.nan))))
    # An invalid row's pose is NaN as states.csv writes it (no pose known).
    p[~valid] = np.nan
    q[~valid] = np.nan
    extra = {}
    if with_extra:
        extra = {"n_tracked": draw(arrays(np.float64, n, elements=st.integers(0, 200).map(float))),
                 "n_lost": draw(arrays(np.float64, n, elements=st.integers(0, 200).map(float))),
                 "latency_ms": draw(arrays(np.float64, n, elements=st.floats(0.0, 1e4)))}
    return MotionSeries(t, valid, p, q, v, w, extra)


def _assert_same(back: MotionSeries, series: MotionSeries) -> None:
    assert len(back) == len(series)
    t = series.t_s
    np.testing.assert_allclose(back.t_s, t, rtol=0, atol=0.5e-9 + float(np.spacing(np.abs(t).max())))
    for name in ("position_m", "velocity_cam_m_s", "omega_body_rad_s"):
        # Exact, NaN for NaN; and -0.0 stays -0.0 (its text is "-0.0").
        np.testing.assert_array_equal(getattr(back, name), getattr(series, name), err_msg=name)
        assert np.array_equal(np.signbit(getattr(back, name)), np.signbit(getattr(series, name))), name
    valid = series.valid
    # Renormalised when read (a file's quaternions are other tools' too): within an ulp or two;
    # the signs written as the conventions say (test_the_library_writers_keep_the_quaternion_sign_rule...).
    written = quat_signs_continuous(series.quat_wxyz)
    np.testing.assert_allclose(back.quat_wxyz[valid], written[valid], rtol=0, atol=4e-16)


@settings(max_examples=60, deadline=None)
@given(series=_series(with_extra=True))
def test_states_csv_round_trip(series: MotionSeries) -> None:
    with TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing we write is warned about when read
        back = read_motion_csv(write_states_csv(Path(tmp) / "states.csv", series))
    _assert_same(back, series)
    np.testing.assert_array_equal(back.valid, series.valid)
    for name, column in series.extra.items():
        np.testing.assert_array_equal(back.extra[name], column, err_msg=name)


@settings(max_examples=40, deadline=None)
@given(series=_series(with_extra=False))
def test_groundtruth_csv_round_trip(series: MotionSeries) -> None:
    series = MotionSeries(series.t_s, np.ones(len(series), bool),
                          np.nan_to_num(series.position_m), np.where(np.isnan(series.quat_wxyz), 0.5, series.quat_wxyz),
                          series.velocity_cam_m_s, series.omega_body_rad_s)
    with TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("error")
        back = read_motion_csv(write_groundtruth_csv(Path(tmp) / "groundtruth.csv", series))
    _assert_same(back, series)
    assert back.valid.all()


@st.composite
def _rigs(draw: st.DrawFn) -> StereoRig:
    width = draw(st.integers(64, 4096))
    height = draw(st.integers(48, 3072))

    def camera() -> Camera:
        # Fields of view up to about 55 degrees across the larger side (the rectifier's own limits
        # on wide lenses with strong distortion are test_rigfile's and test_stereo's).
        f = draw(st.floats(max(width, height), 20000.0))
        K = np.array([[f * draw(st.floats(0.9, 1.1)), 0.0, draw(st.floats(0.4, 0.6)) * width],
                      [0.0, f, draw(st.floats(0.4, 0.6)) * height], [0.0, 0.0, 1.0]])
        n_dist = draw(st.sampled_from([0, 4, 5, 8, 12, 14]))
        # Lenses as calibrations find them (OpenCV's order k1 k2 p1 p2 k3 k4 k5 k6 s1-s4 tx ty):
        # a lens far outside them is refused when read, as it cannot be rectified (test_rigfile).
        bounds = np.array([0.3, 0.3, 0.005, 0.005, 0.3, 0.3, 0.3, 0.3, 0.005, 0.005, 0.005, 0.005, 0.01, 0.01])
        dist = np.array([draw(st.floats(-b, b)) for b in bounds[:n_dist]])
        return Camera(width, height, K, dist)

    left, right = camera(), camera()
    R = Rotation.from_rotvec(draw(arrays(np.float64, 3, elements=st.floats(-0.2, 0.2)))).as_matrix()
    baseline = draw(st.floats(0.01, 2.0))
    T = np.array([-baseline, draw(st.floats(-0.01, 0.01)), draw(st.floats(-0.01, 0.01))])
    rms = draw(st.one_of(st.none(), st.floats(0.01, 2.0)))
    return StereoRig(left, right, R, T, rms_px=rms)


#: The draw that CI's run failed on (2026-12-07): a lens no rectification takes, refused when read.
_UNRECTIFIABLE = StereoRig(
    Camera(285, 221, np.array([[1848.0, 0.0, 142.5], [0.0, 1848.0, 110.5], [0.0, 0.0, 1.0]]), np.zeros(8)),
    Camera(285, 221, np.array([[325.3125, 0.0, 115.78125], [0.0, 347.0, 110.5], [0.0, 0.0, 1.0]]),
           np.array([0.0, -0.25, 0.0, 0.0, 0.0, 0.25, 0.25, 0.0])),
    Rotation.from_rotvec([0.125, 0.0625, 0.125]).as_matrix(), np.array([-1.0, 0.0, 0.0]))


@settings(max_examples=40, deadline=None)
@given(rig=_rigs())
@example(rig=_UNRECTIFIABLE)
def test_rig_file_round_trip(rig: StereoRig) -> None:
    with TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # strong distortion or a long baseline may be warned about
        try:
            back = load_rig(save_rig(rig, Path(tmp) / "rig.yaml"))
        except TrackmeterError as exc:
            # Independent draws of the rational model's coefficients now and then make a lens
            # that no rectification can take (CI drew k2 -0.25, k4 k5 +0.25: a rectified focal
            # length 13 times the cameras'). Refused when read by design (test_rigfile), not a
            # round trip to check.
            if "cannot be rectified" not in str(exc):
                raise
            reject()
    for a, b in ((rig.left, back.left), (rig.right, back.right)):
        assert (a.width, a.height) == (b.width, b.height)
        np.testing.assert_array_equal(a.K, b.K)
        np.testing.assert_array_equal(np.ravel(a.dist), np.ravel(b.dist))
    np.testing.assert_array_equal(rig.R, back.R)
    np.testing.assert_array_equal(rig.T, back.T)
    assert back.rms_px == rig.rms_px


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 40), gap=st.integers(0, 39))
def test_the_library_writers_keep_the_quaternion_sign_rule_of_the_conventions(seed: int, n: int, gap: int) -> None:
    """docs/conventions.md: a written series starts with qw >= 0 and keeps each quaternion on the
    side of the one before it. The commands' writers did; write_tum, write_groundtruth_csv and
    write_states_csv wrote the signs they were given (an outside probe: qw -0.315 first, and a
    flip between rows 0 and 1)."""
    rng = np.random.default_rng(seed)
    # A tumble through half turns, each quaternion given with a random sign.
    q = Rotation.from_rotvec(np.outer(np.arange(n), rng.normal(size=3) * 0.7)).as_quat(scalar_first=True)
    q *= rng.choice([-1.0, 1.0], size=(n, 1))
    t = np.arange(n) * 0.04
    p = rng.normal(size=(n, 3))
    valid = np.ones(n, bool)
    valid[gap % n] = n < 3  # one invalid row (no pose) inside the series, where there is room
    q_states = np.where(valid[:, None], q, np.nan)

    def check(written: np.ndarray, given_q: np.ndarray) -> None:
        rows = written[np.isfinite(written).all(axis=1)]
        assert rows[0, 0] >= 0.0
        assert np.all(np.sum(rows[1:] * rows[:-1], axis=1) >= 0.0)
        same = np.abs(np.sum(rows * given_q[np.isfinite(given_q).all(axis=1)], axis=1))
        assert np.allclose(same, 1.0, atol=1e-9)  # the same rotations

    with TemporaryDirectory() as tmp:
        path = write_tum(Path(tmp) / "t.tum", Trajectory(t, p, q))
        xyzw = np.loadtxt(path, ndmin=2)[:, 4:8]
        check(np.column_stack([xyzw[:, 3], xyzw[:, :3]]), q)
        series = MotionSeries(t, np.ones(n, bool), p, q, np.zeros((n, 3)), np.zeros((n, 3)))
        check(read_motion_csv(write_groundtruth_csv(Path(tmp) / "g.csv", series)).quat_wxyz, q)
        states = MotionSeries(t, valid, np.where(valid[:, None], p, np.nan), q_states, np.zeros((n, 3)), np.zeros((n, 3)))
        check(read_motion_csv(write_states_csv(Path(tmp) / "s.csv", states)).quat_wxyz, q_states)
