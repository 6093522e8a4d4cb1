"""Stereo calibration (trackmeter.core.calibration) on OpenCV's own sample pairs.

Reference: ``../shared/data/stereo_calib_opencv/reference_opencv_stereocalibrate.json``, what
plain OpenCV gives on the same 13 pairs; variant C (joint refinement, 5-parameter distortion)
is the best plain result. Also checked against ``cv2.stereoCalibrate`` run here.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from trackmeter.core import calibration as cal
from trackmeter.core.stereo import Camera, StereoRig
from trackmeter.data.images import read_grey
from trackmeter.errors import TrackmeterError

PATTERN = (9, 6)
SIZE = (640, 480)


@pytest.fixture(scope="module")
def calib_dir(shared_data: Path) -> Path:
    return shared_data / "stereo_calib_opencv"


@pytest.fixture(scope="module")
def reference(calib_dir: Path) -> dict:
    return json.loads((calib_dir / "reference_opencv_stereocalibrate.json").read_text())


@pytest.fixture(scope="module")
def corners(calib_dir: Path, reference: dict) -> tuple[list, list]:
    params = cal.CalibrationParams()
    left = [cal.detect_corners(read_grey(calib_dir / l), PATTERN, params) for l, _ in reference["pairs_used"]]
    right = [cal.detect_corners(read_grey(calib_dir / r), PATTERN, params) for _, r in reference["pairs_used"]]
    return left, right


@pytest.fixture(scope="module")
def result(corners: tuple[list, list]) -> cal.StereoCalibration:
    return cal.calibrate_stereo(corners[0], corners[1], PATTERN, 1.0, SIZE)


# --------------------------------------------------------------------------- the must-show figures


def test_rms_reaches_opencv_best_variant(result: cal.StereoCalibration, reference: dict) -> None:
    best = reference["C_joint_5param_free"]["rms"]
    assert result.rms_px <= 0.22
    assert result.rms_px <= best + 1e-4
    assert result.rig.rms_px == pytest.approx(result.rms_px)


def test_baseline_within_0p3_percent(result: cal.StereoCalibration, reference: dict) -> None:
    assert result.rig.baseline_m == pytest.approx(3.327, rel=0.003)
    assert result.rig.baseline_m == pytest.approx(reference["C_joint_5param_free"]["baseline"], rel=1e-4)
    # the baseline's standard deviation must cover the spread between OpenCV's variants B and C
    spread = abs(reference["B_mono_then_fix_intrinsic"]["baseline"] - reference["C_joint_5param_free"]["baseline"])
    assert 0 < result.std["baseline"] < 0.01 * result.rig.baseline_m
    assert spread < 3 * result.std["baseline"]


def test_matches_reference_parameters(result: cal.StereoCalibration, reference: dict) -> None:
    ref = reference["C_joint_5param_free"]
    np.testing.assert_allclose(result.rig.left.K, ref["K1"], atol=0.05)
    np.testing.assert_allclose(result.rig.right.K, ref["K2"], atol=0.05)
    np.testing.assert_allclose(result.rig.T, ref["T"], atol=1e-3)
    rvec_deg = np.degrees(cv2.Rodrigues(result.rig.R)[0].ravel())
    np.testing.assert_allclose(rvec_deg, ref["R_rodrigues_deg"], atol=1e-3)


def test_agrees_with_plain_cv2_stereocalibrate(corners: tuple[list, list], result: cal.StereoCalibration) -> None:
    """Mono calibration then free joint stereoCalibrate, written out with cv2 alone."""
    obj = np.zeros((54, 3), np.float32)
    obj[:, :2] = np.mgrid[0:9, 0:6].T.reshape(-1, 2)
    objs = [obj] * len(corners[0])
    left = [np.float32(c).reshape(-1, 1, 2) for c in corners[0]]
    right = [np.float32(c).reshape(-1, 1, 2) for c in corners[1]]
    _, K1, D1, _, _ = cv2.calibrateCamera(objs, left, SIZE, None, None)
    _, K2, D2, _, _ = cv2.calibrateCamera(objs, right, SIZE, None, None)
    rms, K1, D1, K2, D2, R, T, _, _ = cv2.stereoCalibrate(
        objs, left, right, K1, D1, K2, D2, SIZE, flags=cv2.CALIB_USE_INTRINSIC_GUESS,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-9),
    )
    assert result.rms_px == pytest.approx(rms, abs=1e-6)
    np.testing.assert_allclose(result.rig.R, R, atol=1e-7)
    np.testing.assert_allclose(result.rig.T, T.ravel(), atol=1e-5)
    np.testing.assert_allclose(result.rig.left.K, K1, atol=1e-3)
    np.testing.assert_allclose(result.rig.right.dist, D2.ravel()[:5], atol=1e-5)


def test_clean_data_rejects_no_view(result: cal.StereoCalibration) -> None:
    assert result.rejected == ()
    assert result.used_views == tuple(range(13))
    assert result.per_view_rms_px.shape == (13, 2)
    # per-view errors combine to the overall RMS (same number of corners in each image)
    assert np.sqrt(np.mean(result.per_view_rms_px**2)) == pytest.approx(result.rms_px, rel=1e-6)


# --------------------------------------------------------------------------- outlier views


def test_corrupted_view_is_rejected_and_result_recovers(corners: tuple[list, list], result: cal.StereoCalibration) -> None:
    rng = np.random.default_rng(7)
    right = list(corners[1])
    right[4] = right[4] + rng.normal(0.0, 1.5, right[4].shape)
    res = cal.calibrate_stereo(corners[0], right, PATTERN, 1.0, SIZE)
    assert [r.index for r in res.rejected] == [4]
    assert "RMS" in res.rejected[0].reason and "median" in res.rejected[0].reason
    assert res.rejected[0].rms_px[1] > 1.0
    assert 4 not in res.used_views
    assert res.rms_px <= 0.22
    assert res.rig.baseline_m == pytest.approx(result.rig.baseline_m, rel=3e-3)


def test_view_without_corners_is_rejected_with_reason(corners: tuple[list, list]) -> None:
    left = list(corners[0])
    left[2] = None
    res = cal.calibrate_stereo(left, corners[1], PATTERN, 1.0, SIZE)
    assert [r.index for r in res.rejected] == [2]
    assert "left image" in res.rejected[0].reason
    assert len(res.used_views) == 12


def test_corners_reported_from_the_opposite_end_are_reordered(corners: tuple[list, list], result: cal.StereoCalibration) -> None:
    right = list(corners[1])
    right[3] = right[3][::-1].copy()
    res = cal.calibrate_stereo(corners[0], right, PATTERN, 1.0, SIZE)
    assert res.rejected == ()
    assert res.rms_px == pytest.approx(result.rms_px, rel=1e-9)


def test_too_few_views_is_an_error(corners: tuple[list, list]) -> None:
    left = [c if i < 4 else None for i, c in enumerate(corners[0])]
    with pytest.raises(TrackmeterError, match="only 4 of 13"):
        cal.calibrate_stereo(left, corners[1], PATTERN, 1.0, SIZE)


def test_outlier_rule() -> None:
    params = cal.CalibrationParams()
    tight = np.array([0.20, 0.21, 0.19, 0.20, 0.22, 0.20])
    assert cal.find_outlier_view(tight, params) is None
    # 30 % above the median is ordinary scatter, even in a tight set
    assert cal.find_outlier_view(np.append(tight, 0.27), params) is None
    pos, reason = cal.find_outlier_view(np.append(tight, 0.9), params)  # type: ignore[misc]
    assert pos == 6 and "0.900" in reason
    # (V,2): the worse image of a view counts
    per_view = np.column_stack([tight, tight])
    per_view[1, 1] = 1.0
    assert cal.find_outlier_view(per_view, params)[0] == 1  # type: ignore[index]
    # noisy but uniform set: the robust-sigma rule keeps every view
    uniform = np.array([0.2, 0.5, 0.3, 0.6, 0.25, 0.55, 0.45])
    assert cal.find_outlier_view(uniform, params) is None
    # A sharp set (rendered boards, an outside probe): a view at 0.12 px, twice the median, is
    # noisier, not wrong, and kept; one at 0.9 px is not.
    sharp = np.array([0.050, 0.057, 0.060, 0.052, 0.066, 0.057, 0.055])
    assert cal.find_outlier_view(np.append(sharp, 0.12), params) is None
    assert cal.find_outlier_view(np.append(sharp, 0.9), params)[0] == 7  # type: ignore[index]


# --------------------------------------------------------------------------- uncertainties


def test_mono_std_matches_opencv(corners: tuple[list, list], result: cal.StereoCalibration) -> None:
    """Our Gauss-Newton covariance reproduces calibrateCameraExtended's stdDeviationsIntrinsics,
    which validates the machinery behind the stereo standard deviations."""
    board = cal.object_points(PATTERN, 1.0)
    uv = [corners[0][i] for i in result.used_views]
    mine = cal.mono_parameter_std(result.left, [board] * len(uv), uv)
    np.testing.assert_allclose(mine, result.left.std_intrinsics, rtol=1e-3)


def test_parameters_the_views_do_not_separate_are_warned_about(corners: tuple[list, list]) -> None:
    """The rational model's k1..k6 on these 13 views are nearly dependent: a Monte-Carlo refit
    (the corners re-drawn with the residual's 0.14 px) scatters k1 by 18, its linearised
    standard deviation says 5 (on a rendered set 281 against 0.02, an outside probe: the
    pseudo-inverse of JᵀJ, condition 1e17, dropped the direction). They are said not to be
    determined separately; the 5-coefficient model's are (no warning)."""
    import warnings

    size = SIZE
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        standard = cal.calibrate_stereo(corners[0], corners[1], PATTERN, 1.0, size)
    assert not [w for w in said if "not determined separately" in str(w.message)]
    rational = cal.CalibrationParams(distortion_model="rational")
    with pytest.warns(UserWarning, match=r"k1_1, .*k1_2, .* are not determined separately by these views "
                                         r"\(nearly dependent: condition number .* of the scaled Jacobian"):
        result = cal.calibrate_stereo(corners[0], corners[1], PATTERN, 1.0, size, rational)
    assert result.std["k1_1"] > 100 * standard.std["k1_1"]  # the linearised figure: still far too small


def test_stereo_std_consistent_with_mono(result: cal.StereoCalibration) -> None:
    std = result.std
    mono = result.left.std_intrinsics
    for k, name in enumerate(("fx1", "fy1", "cx1", "cy1")):
        # the joint solution sees twice the corners: similar or smaller uncertainty, same order
        assert 0.3 * mono[k] < std[name] < 1.5 * mono[k]
    assert all(np.isfinite(v) and v > 0 for v in std.values())


# --------------------------------------------------------------------------- rectification check


def test_rectification_check_on_real_data(result: cal.StereoCalibration) -> None:
    rc = result.rectification
    assert rc.per_view_rms_px.shape == (13,)
    # vertical disparity is the difference of two corner errors of ~0.2 px each
    assert 0 < rc.rms_px < 0.3
    assert rc.max_abs_px < 1.0


def test_rectification_check_is_zero_for_exact_projections(estec_rig: StereoRig) -> None:
    board = cal.object_points((9, 6), 0.05)
    rng = np.random.default_rng(1)
    uv_l, uv_r = [], []
    for _ in range(3):
        R = cv2.Rodrigues(rng.normal(0, 0.3, 3))[0]
        p = board @ R.T + np.array([0.0, 0.0, 2.0])
        l, r = estec_rig.project(p)
        uv_l.append(l)
        uv_r.append(r)
    rc = cal.rectification_check(estec_rig, uv_l, uv_r)
    assert rc.max_abs_px < 1e-5


def test_rectification_check_sees_a_vertical_offset(estec_rig: StereoRig) -> None:
    board = cal.object_points((9, 6), 0.05) + np.array([-0.2, -0.1, 2.0], np.float32)
    l, r = estec_rig.project(board)
    rc = cal.rectification_check(estec_rig, [l], [r + np.array([0.0, 0.5])])
    assert rc.rms_px == pytest.approx(0.5, abs=0.02)


# --------------------------------------------------------------------------- small pieces


def test_parse_pattern() -> None:
    assert cal.parse_pattern("9x6") == (9, 6)
    assert cal.parse_pattern("7X5") == (7, 5)
    for bad in ("9", "9x", "x6", "9x6x2", "nine", "1x6", "9*6", "2x2", "9x2"):  # OpenCV asserts below 3x3
        with pytest.raises(TrackmeterError, match="pattern"):
            cal.parse_pattern(bad)


def test_object_points_follow_opencv_corner_order(calib_dir: Path) -> None:
    board = cal.object_points((9, 6), 0.025)
    assert board.shape == (54, 3)
    np.testing.assert_allclose(board[1], [0.025, 0, 0])  # along a row first
    np.testing.assert_allclose(board[9], [0, 0.025, 0])
    with pytest.raises(TrackmeterError):
        cal.object_points((9, 6), 0.0)


def test_detect_corners_uses_the_configured_subpix_window(calib_dir: Path) -> None:
    image = read_grey(calib_dir / "left01.jpg")
    found, raw = cv2.findChessboardCorners(image, PATTERN, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    assert found
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    for win in (5, 11):
        expected = cv2.cornerSubPix(image, raw.copy(), (win, win), (-1, -1), crit).reshape(-1, 2)
        got = cal.detect_corners(image, PATTERN, replace(cal.CalibrationParams(), subpix_window_px=win))
        np.testing.assert_allclose(got, expected, atol=1e-6)
    assert cal.detect_corners(np.zeros((480, 640), np.uint8), PATTERN) is None


def test_calibrated_rig_is_a_valid_camera_model(result: cal.StereoCalibration) -> None:
    rig = result.rig
    assert isinstance(rig.left, Camera) and rig.left.dist.size == 5
    assert rig.image_size == SIZE
    # the essential matrix is [T]x R
    T = rig.T
    Tx = np.array([[0, -T[2], T[1]], [T[2], 0, -T[0]], [-T[1], T[0], 0]])
    np.testing.assert_allclose(result.E, Tx @ rig.R, atol=1e-6)
