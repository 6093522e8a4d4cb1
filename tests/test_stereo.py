"""Camera and stereo geometry (trackmeter.core.stereo), pinned to OpenCV and closed forms."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trackmeter.core.stereo import Camera, Rectification, StereoRig, depth_sigma
from trackmeter.data.rigfile import load_rig
from trackmeter.errors import TrackmeterError

RIGS = Path(__file__).resolve().parent.parent / "config" / "rigs"


@pytest.fixture(scope="module")
def wide_rig() -> StereoRig:
    """The 4.8 mm preset: the strongest distortion of the presets."""
    return load_rig(RIGS / "estec_4p8mm.yaml")


def points_in_view(rig: StereoRig, n: int, seed: int, z_range: tuple[float, float] = (1.5, 8.0)) -> np.ndarray:
    """Left-camera points (n,3) that project inside both images."""
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        z = rng.uniform(*z_range)
        uv = rng.uniform([40, 40], [rig.image_size[0] - 40, rig.image_size[1] - 40])
        ray = np.linalg.solve(rig.left.K, [uv[0], uv[1], 1.0])
        p = ray * z
        l, r = rig.project(p)
        if rig.left.contains(l, 5)[0] and rig.right.contains(r, 5)[0]:
            out.append(p)
    return np.array(out)


# --------------------------------------------------------------------------- projection


def test_project_matches_cv2(estec_rig: StereoRig) -> None:
    p = points_in_view(estec_rig, 30, 0)
    l, r = estec_rig.project(p)
    expected_l, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), estec_rig.left.K, estec_rig.left.dist)
    rvec, _ = cv2.Rodrigues(estec_rig.R)
    expected_r, _ = cv2.projectPoints(p, rvec, estec_rig.T, estec_rig.right.K, estec_rig.right.dist)
    np.testing.assert_allclose(l, expected_l.reshape(-1, 2), atol=1e-9)
    np.testing.assert_allclose(r, expected_r.reshape(-1, 2), atol=1e-9)


def test_principal_point_projects_to_itself(estec_rig: StereoRig) -> None:
    uv = estec_rig.left.project([[0.0, 0.0, 3.5]])
    np.testing.assert_allclose(uv, [[estec_rig.left.K[0, 2], estec_rig.left.K[1, 2]]], atol=1e-12)


def test_undistort_inverts_project(wide_rig: StereoRig) -> None:
    p = points_in_view(wide_rig, 50, 1)
    xy = wide_rig.left.undistort(wide_rig.left.project(p))
    np.testing.assert_allclose(xy, p[:, :2] / p[:, 2:], atol=1e-9)


def test_contains_uses_pixel_centre_convention() -> None:
    cam = Camera(10, 8, np.array([[10.0, 0, 4.5], [0, 10, 3.5], [0, 0, 1]]))
    inside = cam.contains([[-0.5, -0.5], [9.5, 7.5], [-0.51, 0], [0, 7.51]])
    assert inside.tolist() == [True, True, False, False]


# --------------------------------------------------------------------------- rectification


@pytest.mark.parametrize("rig_name", ["estec_12mm", "estec_8mm", "estec_4p8mm"])
def test_rectify_unrectify_round_trip(rig_name: str) -> None:
    rig = load_rig(RIGS / f"{rig_name}.yaml")
    rect = rig.rectification
    rng = np.random.default_rng(2)
    uv = rng.uniform([20, 20], [rig.image_size[0] - 20, rig.image_size[1] - 20], (200, 2))
    for side in (0, 1):
        back = rect.unrectify_points(rect.rectify_points(uv, side), side)
        np.testing.assert_allclose(back, uv, atol=1e-6)


def test_rectify_points_match_cv2_remap_maps(estec_rig: StereoRig) -> None:
    """The rectified maps send a rectified pixel to the original pixel that rectify_points
    sends back: the image warp and the point mapping agree."""
    rect = estec_rig.rectification
    (mx, my), _ = rect.maps
    rows, cols = np.mgrid[50:450:40, 50:650:60]
    uv_rect = np.column_stack([cols.ravel(), rows.ravel()]).astype(float)
    uv_orig = np.column_stack([mx[rows, cols].ravel(), my[rows, cols].ravel()])
    np.testing.assert_allclose(rect.rectify_points(uv_orig, 0), uv_rect, atol=2e-3)  # float32 maps


def test_rectified_rows_are_equal(wide_rig: StereoRig, estec_rig: StereoRig) -> None:
    for rig in (estec_rig, wide_rig):
        p = points_in_view(rig, 50, 3)
        l, r = rig.project(p)
        rect = rig.rectification
        np.testing.assert_allclose(rect.rectify_points(l, 0)[:, 1], rect.rectify_points(r, 1)[:, 1], atol=1e-6)


def test_rectification_parameters(estec_rig: StereoRig) -> None:
    rect = estec_rig.rectification
    assert rect.baseline_m == pytest.approx(estec_rig.baseline_m, rel=1e-9)
    assert rect.disparity_offset_px == pytest.approx(0.0, abs=1e-9)  # CALIB_ZERO_DISPARITY
    np.testing.assert_allclose(rect.R1 @ rect.R1.T, np.eye(3), atol=1e-12)
    # OpenCV's Q agrees with the triangulation: [X Y Z W] = Q [u v d 1]
    uv, d = np.array([[300.0, 200.0]]), np.array([90.0])
    X = rect.Q @ np.array([300.0, 200.0, 90.0, 1.0])
    np.testing.assert_allclose(rect.triangulate(uv, d)[0] @ rect.R1.T, X[:3] / X[3], rtol=1e-12)


# --------------------------------------------------------------------------- triangulation

_RIG_CACHE: dict[str, StereoRig] = {}


@settings(max_examples=100, deadline=None)
@given(
    st.floats(-0.4, 0.4), st.floats(-0.3, 0.3), st.floats(0.5, 20.0),
    st.sampled_from(["estec_12mm", "estec_4p8mm"]),
)
def test_property_triangulate_project_round_trip(x: float, y: float, z: float, rig_name: str) -> None:
    rig = _RIG_CACHE.setdefault(rig_name, load_rig(RIGS / f"{rig_name}.yaml"))
    p = np.array([[x * z, y * z, z]])
    rect = rig.rectification
    uv, d = rect.project_rectified(p)
    np.testing.assert_allclose(rect.triangulate(uv, d), p, atol=1e-9)


def test_triangulate_from_original_pixels(wide_rig: StereoRig, estec_rig: StereoRig) -> None:
    """The full path a measurement takes: distorted pixels in both images → rectify → disparity
    → 3D, back to the point that produced them."""
    for rig in (estec_rig, wide_rig):
        p = points_in_view(rig, 50, 4)
        l, r = rig.project(p)
        rect = rig.rectification
        lr, rr = rect.rectify_points(l, 0), rect.rectify_points(r, 1)
        xyz = rect.triangulate(lr, lr[:, 0] - rr[:, 0])
        # 1e-6 px of undistortion residual is 1e-6 px * z^2 / (f b) in depth
        np.testing.assert_allclose(xyz, p, atol=1e-6)


def test_triangulate_refuses_non_positive_disparity(estec_rig: StereoRig) -> None:
    xyz = estec_rig.rectification.triangulate([[300.0, 200.0], [300.0, 200.0]], [0.0, -3.0])
    assert np.all(np.isnan(xyz))


def test_triangulate_refuses_an_infinite_disparity_and_unequal_counts(estec_rig: StereoRig) -> None:
    """d = inf gave the point (0, 0, 0) with a zero covariance, a certain point at the camera
    centre; 1 pixel with 3 disparities gave 3 points (an outside code review)."""
    from trackmeter.errors import TrackmeterError

    rect = estec_rig.rectification
    assert np.all(np.isnan(rect.triangulate([[300.0, 200.0]], [np.inf])))
    assert np.all(np.isnan(rect.point_covariance([[300.0, 200.0]], [np.inf], 0.07, 0.2)))
    with pytest.raises(TrackmeterError, match="1 pixels but 3 disparities"):
        rect.triangulate([[300.0, 200.0]], [20.0, 30.0, 40.0])
    with pytest.raises(TrackmeterError, match="3 pixels but 2 disparities"):
        rect.triangulate([[300.0, 200.0]] * 3, [20.0, 30.0])
    np.testing.assert_array_equal(rect.triangulate([[300.0, 200.0]] * 2, 25.0), rect.triangulate([[300.0, 200.0]] * 2, [25.0, 25.0]))


# --------------------------------------------------------------------------- error propagation


def test_point_covariance_matches_numerical_jacobian(estec_rig: StereoRig) -> None:
    rect = estec_rig.rectification
    p = points_in_view(estec_rig, 5, 5)
    uv, d = rect.project_rectified(p)
    s_uv, s_d = 0.2, 0.07
    C = rect.point_covariance(uv, d, s_d, s_uv)
    h = 1e-4
    for i in range(len(p)):
        J = np.zeros((3, 3))
        for k, delta in enumerate(np.eye(3) * h):
            plus = rect.triangulate(uv[i] + delta[:2], d[i] + delta[2])[0]
            minus = rect.triangulate(uv[i] - delta[:2], d[i] - delta[2])[0]
            J[:, k] = (plus - minus) / (2 * h)
        expected = J @ np.diag([s_uv**2, s_uv**2, s_d**2]) @ J.T
        np.testing.assert_allclose(C[i], expected, rtol=1e-6, atol=1e-16)
    np.testing.assert_allclose(rect.point_sigma(uv, d, s_d, s_uv), np.sqrt(np.diagonal(C, axis1=1, axis2=2)))


def test_depth_sigma_closed_form(estec_rig: StereoRig) -> None:
    """Eq. 2 on the optical axis of the rectified frame: sigma_z = z² sigma_d / (f b)."""
    rect = estec_rig.rectification
    f, b = rect.focal_px, rect.baseline_m
    for z in (1.0, 3.5, 10.0):
        p_cam = rect.R1.T @ np.array([0.0, 0.0, z])
        uv, d = rect.project_rectified(p_cam[None])
        C = rect.point_covariance(uv, d, 0.1)
        sigma_along_axis = np.sqrt(rect.R1[2] @ C[0] @ rect.R1[2])
        assert sigma_along_axis == pytest.approx(z * z * 0.1 / (f * b), rel=1e-9)
        assert depth_sigma(z, f, b, 0.1) == pytest.approx(z * z * 0.1 / (f * b), rel=1e-12)
    # a parabola: doubling the range quadruples sigma
    assert depth_sigma(7.0, f, b, 0.1) == pytest.approx(4 * depth_sigma(3.5, f, b, 0.1))


def test_paper_figure_at_3p5_m() -> None:
    """The paper's rig (f = 1152 px, b = 0.28 m) at 3.5 m with 0.1 px disparity sigma:
    z² sigma_d / (f b) = 3.8 mm, the paper's 'about 4 mm at 3.5 m'."""
    assert depth_sigma(3.5, 1152.0, 0.28, 0.1) == pytest.approx(3.80e-3, abs=0.01e-3)


def test_preset_rig_focal_and_baseline(estec_rig: StereoRig) -> None:
    assert estec_rig.left.focal_px == pytest.approx(1152.0)
    assert estec_rig.baseline_m == pytest.approx(0.28)
    assert estec_rig.rectification.focal_px == pytest.approx(1152.0, rel=0.05)


# --------------------------------------------------------------------------- validation


def test_camera_and_rig_refuse_bad_values() -> None:
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    with pytest.raises(TrackmeterError):
        Camera(0, 480, K)
    with pytest.raises(TrackmeterError):
        Camera(640, 480, K[:2])
    with pytest.raises(TrackmeterError):
        Camera(640, 480, K, np.zeros(3))
    with pytest.raises(TrackmeterError):
        Camera(640, 480, K * np.array([[-1], [1], [1]]))
    cam = Camera(640, 480, K)
    with pytest.raises(TrackmeterError, match="rotation"):
        StereoRig(cam, cam, np.diag([1.0, 1.0, -1.0]), [-0.1, 0, 0])
    with pytest.raises(TrackmeterError, match="baseline"):
        StereoRig(cam, cam, np.eye(3), [0, 0, 0])
    with pytest.raises(TrackmeterError, match="differ in size"):
        StereoRig(cam, Camera(320, 240, K), np.eye(3), [-0.1, 0, 0])


def test_rotation_written_with_five_decimals_becomes_the_nearest_rotation() -> None:
    """A rig file's R rounded to 5 decimals (|R^T R - I| ~ 1e-5) is a rotation as written by a
    person or another tool: taken, and replaced by the nearest exact rotation."""
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    cam = Camera(640, 480, K)
    exact = cv2.Rodrigues(np.array([0.013, -0.41, 0.027]))[0]
    rounded = np.round(exact, 5)
    assert np.max(np.abs(rounded.T @ rounded - np.eye(3))) > 1e-6  # what the old check refused
    rig = StereoRig(cam, cam, rounded, [-0.1, 0, 0])
    np.testing.assert_allclose(rig.R.T @ rig.R, np.eye(3), rtol=0, atol=1e-14)
    assert np.linalg.det(rig.R) == pytest.approx(1.0, abs=1e-14)
    np.testing.assert_allclose(rig.R, exact, rtol=0, atol=1e-5)
    # An exact rotation is kept bit for bit.
    assert np.array_equal(StereoRig(cam, cam, exact, [-0.1, 0, 0]).R, exact)
    # A reflection, however close to orthonormal, and a clear non-rotation stay refused.
    for bad in (np.round(exact, 5) @ np.diag([1.0, 1.0, -1.0]), exact * 1.01, exact + 0.01 * np.eye(3)):
        with pytest.raises(TrackmeterError, match="R must be a rotation matrix"):
            StereoRig(cam, cam, bad, [-0.1, 0, 0])


def test_rectification_of_alpha_one_keeps_geometry(estec_rig: StereoRig) -> None:
    rect = Rectification.of(estec_rig, alpha=1.0)
    p = points_in_view(estec_rig, 10, 6)
    uv, d = rect.project_rectified(p)
    np.testing.assert_allclose(rect.triangulate(uv, d), p, atol=1e-9)


def test_matching_needs_the_right_camera_to_the_right(estec_rig: StereoRig) -> None:
    """The matcher searches along rectified ROWS with ``d = u_left - u_right > 0``: a vertical
    rig (its epipolar lines are columns) or a swapped one (every depth negative) would give
    points that look measured and are not, so measuring and tracking refuse them up front."""
    import dataclasses

    from trackmeter.core.matching import measure_points
    from trackmeter.core.stereo import check_side_by_side
    from trackmeter.core.tracking import Tracker, TrackerParams
    from trackmeter.core.features import FeatureParams
    from trackmeter.core.matching import MeasureParams

    check_side_by_side(estec_rig)  # right camera at +x: fine
    slightly_tilted = dataclasses.replace(estec_rig, T=np.array([-0.28, 0.09, 0.02]))
    check_side_by_side(slightly_tilted)  # rectification turns it level
    vertical = dataclasses.replace(estec_rig, T=np.array([0.0, -0.28, 0.0]))
    swapped = dataclasses.replace(estec_rig, T=-estec_rig.T)
    img = np.zeros(estec_rig.image_size[::-1], np.uint8)
    for rig, words in ((vertical, "not side by side"), (swapped, "lies left of the left one")):
        with pytest.raises(TrackmeterError, match=words):
            check_side_by_side(rig)
        with pytest.raises(TrackmeterError, match=words):
            measure_points(rig, img, img, [(300.0, 200.0)])
        with pytest.raises(TrackmeterError, match=words):
            Tracker(rig, TrackerParams(), FeatureParams(), MeasureParams())


@pytest.mark.parametrize(
    ("R", "T", "words"),
    [
        # Where the right camera's centre is (-R^T T in the left camera's frame, y down) is what
        # the message says, not the direction the rectified projection happens to carry.
        (np.eye(3), [0.193, 0.0, 0.0], "lies left of the left one"),
        # Left of it AND turned round: exchanging alone would give the same rig back (code review).
        (np.diag([-1.0, -1.0, 1.0]), [-0.193, 0.0, 0.0], "turned 180 deg about its viewing axis.*then exchange"),
        # Turned 90 deg counter-clockwise, an image's bottom is its right (an outside probe
        # found the way by trying; the message said "by 90 degrees").
        (np.eye(3), [0.0, -0.193, 0.0], "lies below the left one.*by 90 degrees counter-clockwise"),
        (np.eye(3), [0.0, 0.193, 0.0], "lies above the left one.*by 90 degrees clockwise"),
        (np.eye(3), [-0.01, 0.0, -0.193], "lies in front of the left one"),
        (np.eye(3), [-0.01, 0.0, 0.193], "lies behind the left one"),
        (np.diag([-1.0, -1.0, 1.0]), [0.193, 0.0, 0.0], "turned 180 deg about its viewing axis"),
    ],
)
def test_a_rig_that_cannot_be_matched_is_described_by_where_its_right_camera_is(
        estec_rig: StereoRig, R: np.ndarray, T: list[float], words: str) -> None:
    import dataclasses

    from trackmeter.core.stereo import check_side_by_side

    rig = dataclasses.replace(estec_rig, R=np.asarray(R, float), T=np.asarray(T, float))
    with pytest.raises(TrackmeterError, match=words) as caught:
        check_side_by_side(rig)
    centre = np.round(-rig.R.T @ rig.T, 3).tolist()
    assert str(centre) in str(caught.value), caught.value


def test_point_sigma_is_a_number_for_rank_one_covariance(estec_rig: StereoRig) -> None:
    """With no pixel noise the covariance is rank 1 (along the ray); on the camera's x = 0 and
    y = 0 planes its rotated diagonal holds a zero that rounding can make -1e-26, and its square
    root must be 0, not NaN (``measure`` printed ``sigma_m: null`` for an ok point)."""
    rect = estec_rig.rectification
    rng = np.random.default_rng(0)
    n = 2000
    p_cam = np.column_stack([np.zeros(n), rng.uniform(-1, 1, n), rng.uniform(1, 5, n)])
    p_cam[n // 2 :, [0, 1]] = p_cam[n // 2 :, [1, 0]]
    uv, d = rect.project_rectified(p_cam)
    with np.errstate(invalid="raise"):
        sigma = rect.point_sigma(uv, d, 0.05, 0.0)
    assert np.all(np.isfinite(sigma)) and np.all(sigma >= 0)
    # and the same numbers as the covariance wherever its diagonal is positive
    diag = np.diagonal(rect.point_covariance(uv, d, 0.05, 0.0), axis1=1, axis2=2)
    np.testing.assert_array_equal(sigma[diag > 0], np.sqrt(diag[diag > 0]))


def test_views_swapped_are_told_by_the_sign_of_their_disparities(estec_sim_frames, shared_data) -> None:
    """Left and right images exchanged under a rig in order (cam0 and cam1 mixed up) ran with no
    valid pose, every candidate refused, and one false match at 4.26 m where the body was at
    3.1-3.4 m (an outside probe): nothing said the views were swapped. The view of a rig in
    order shifts left from the left image to the right one (every disparity positive)."""
    import cv2

    from benchmarks.measure import estec_plane
    from trackmeter.core.stereo import Camera, StereoRig, swapped_views_problem, view_disparities_px

    rig, frames = estec_sim_frames
    f = frames[0]
    d = view_disparities_px(rig, f.left, f.right)
    # The body at about 3.3 m, 0.45 m deep: f b / z with the 12 mm rig's f b (px m).
    fb = rig.rectification.focal_px * rig.rectification.baseline_m
    assert len(d) > 50 and fb / 3.6 < np.median(d) < fb / 3.0, (len(d), np.median(d))
    assert swapped_views_problem(rig, f.left, f.right) is None
    problem = swapped_views_problem(rig, f.right, f.left)
    assert problem is not None and "look swapped" in problem, problem
    # One image twice: the two rectification maps shift it against itself (10 px with this
    # rig), which is no order of the views, but no stereo pair either.
    assert "one and the same image" in (swapped_views_problem(rig, f.left, f.left) or "")
    # A tilted plate filling the view (a global phase correlation got it wrong), in order and not.
    plate_rig, left, right, _ = estec_plane(seed=5)
    assert swapped_views_problem(plate_rig, left, right) is None
    assert swapped_views_problem(plate_rig, right, left) is not None
    # Real images: Middlebury's rectified Tsukuba pair (disparities 5-14 px).
    left = cv2.imread(str(shared_data / "middlebury_tsukuba" / "img_left.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(shared_data / "middlebury_tsukuba" / "img_right.png"), cv2.IMREAD_GRAYSCALE)
    K = np.array([[400.0, 0.0, 192.0], [0.0, 400.0, 144.0], [0.0, 0.0, 1.0]])
    tsukuba = StereoRig(Camera(384, 288, K, np.zeros(5)), Camera(384, 288, K, np.zeros(5)), np.eye(3),
                        np.array([-0.1, 0.0, 0.0]))
    d = view_disparities_px(tsukuba, left, right)
    assert len(d) > 50 and 5.0 <= np.median(d) <= 14.0, np.median(d)
    assert swapped_views_problem(tsukuba, left, right) is None
    assert swapped_views_problem(tsukuba, right, left) is not None
    # No view at all (black space) says nothing; one image twice is said.
    black = np.zeros_like(left)
    assert len(view_disparities_px(tsukuba, black, black)) == 0
    assert swapped_views_problem(tsukuba, black, black) is None
    assert "one and the same image" in (swapped_views_problem(tsukuba, left, left) or "")


def test_a_negative_standard_deviation_is_refused(estec_rig: StereoRig) -> None:
    """sigma_disparity_px=-0.1 gave a covariance as if it were +0.1."""
    rect = estec_rig.rectification
    uv, d = rect.project_rectified(np.array([[0.1, 0.0, 3.5], [0.0, 0.2, 4.0]]))
    with pytest.raises(TrackmeterError, match=r"sigma_disparity_px must be >= 0 px, got -0\.1"):
        rect.point_covariance(uv, d, -0.1)
    with pytest.raises(TrackmeterError, match=r"sigma_uv_px must be >= 0 px"):
        rect.point_covariance(uv, d, 0.1, np.array([0.1, -0.2]))


@pytest.mark.parametrize(
    "args, message",
    [
        ((-1.0, 1000.0, 0.3, 0.05), r"z_m must be positive \(in front of the camera\), m; got -1"),
        ((3.5, 1000.0, 0.3, -0.05), r"sigma_disparity_px must be >= 0 px"),
        ((3.5, 0.0, 0.3, 0.05), r"focal_px must be positive"),
        ((3.5, 1000.0, -0.3, 0.05), r"baseline_m must be positive"),
    ],
)
def test_depth_sigma_refuses_what_is_no_stereo_geometry(args, message) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(TrackmeterError, match=message):
        depth_sigma(*args)


def test_views_in_order_on_a_pair_rectified_with_principal_points_apart_are_not_called_swapped(shared_data) -> None:  # type: ignore[no-untyped-def]
    """On a pair rectified already whose principal points lie apart (Middlebury 2014's
    ``doffs``), a point at infinity has the disparity ``cx1 - cx2``, not 0: Tsukuba's right
    image moved 12 px right, its principal point with it, puts most of its points (5-14 px)
    at negative disparities, and the views in order were called swapped."""
    from benchmarks.measure import identity_rig, load_tsukuba, principal_points_apart
    from trackmeter.core.stereo import swapped_views_problem

    left, right, _ = load_tsukuba(shared_data / "middlebury_tsukuba")
    rig, moved = principal_points_apart(identity_rig(384, 288, focal_px=400.0), right, 12)
    assert rig.rectification.disparity_offset_px == pytest.approx(-12, abs=1e-4)
    assert swapped_views_problem(rig, left, moved) is None
    # Pixels not square: OpenCV's maps would not be the identity; rectified to one principal point.
    K1, K2 = rig.left.K.copy(), rig.right.K.copy()
    K1[1, 1] = K2[1, 1] = 410.0
    oblong = dataclasses.replace(rig, left=dataclasses.replace(rig.left, K=K1), right=dataclasses.replace(rig.right, K=K2))
    assert oblong.rectification.disparity_offset_px == 0.0


def test_a_stray_match_does_not_hide_views_swapped_on_a_rig_rectified_to_one_principal_point(estec_rig: StereoRig) -> None:
    """OpenCV's chessboard pairs swapped give 12-17 ORB matches, one of them a stray at +42 px
    (an outside review): 80 % of them past infinity's disparity says swapped, whatever the rest;
    a third of them, as a rig a little off sees a far scene, does not."""
    from trackmeter.core.stereo import swapped_views_problem

    blank = np.zeros((2, 2), np.uint8)
    stray = np.array([-84.0, -90, -95, -100, -110, -120, -130, -140, -150, -160, -163, 43.0])
    assert "look swapped" in (swapped_views_problem(estec_rig, blank, blank + 1, stray) or "")
    far = np.r_[np.full(4, -2.5), np.full(8, 0.5)]
    assert swapped_views_problem(estec_rig, blank, blank + 1, far) is None


@pytest.mark.parametrize("shift", [1, 2])
def test_views_swapped_on_a_pair_rectified_with_principal_points_apart_are_told(shared_data, shift: int) -> None:  # type: ignore[no-untyped-def]
    """A swap moves a point by twice the offset ``cx1 - cx2`` less than on a rig rectified to
    one principal point: Tsukuba's right image moved ``shift`` px right (its principal point with
    it) and swapped puts 94 / 55 % of the view's points where no point in front of the rig
    lies, and none with the views exchanged. Only 80 % and more was called swapped (an outside
    probe: Middlebury's Motorcycle swapped, 69 %, was measured at 10-26 m for 2-4 m, unsaid).
    One image twice, which a pair whose principal points lie apart measures as a plane at
    ``f b / |cx1 - cx2|``, is said too."""
    from benchmarks.measure import identity_rig, load_tsukuba, principal_points_apart
    from trackmeter.core.stereo import swapped_views_problem

    left, right, _ = load_tsukuba(shared_data / "middlebury_tsukuba")
    rig, moved = principal_points_apart(identity_rig(384, 288, focal_px=400.0), right, shift)
    assert swapped_views_problem(rig, left, moved) is None
    assert "look swapped" in (swapped_views_problem(rig, moved, left) or "")
    assert "one and the same image" in (swapped_views_problem(rig, left, left) or "")


# --------------------------------------------------------------------------- shapes at the boundary
# An outside probe of the library API: points of another shape were reshaped into other points
# whenever their count of numbers divided evenly (three homogeneous points (3,4) projected as
# four 3D points, one at -4e8 px), and a camera's image width 640.7 became 640.


def _estec() -> StereoRig:
    return load_rig(RIGS / "estec_12mm.yaml")


@pytest.mark.parametrize("call, dim", [
    (lambda rig, a: rig.left.project(a), 3),
    (lambda rig, a: rig.project(a), 3),
    (lambda rig, a: rig.left.undistort(a), 2),
    (lambda rig, a: rig.left.contains(a), 2),
    (lambda rig, a: rig.rectification.rectify_points(a), 2),
    (lambda rig, a: rig.rectification.unrectify_points(a), 2),
    (lambda rig, a: rig.rectification.triangulate(a, 50.0), 2),
    (lambda rig, a: rig.rectification.project_rectified(a), 3),
])
@pytest.mark.parametrize("shape", [(3, 4), (2, 3), (4, 2), (1, 2), (3, 1), (6,), (2, 2, 3)])
def test_points_of_another_shape_are_refused_not_reshaped(call, dim: int, shape: tuple[int, ...]) -> None:  # type: ignore[no-untyped-def]
    if shape[-1] == dim and len(shape) <= 2:
        return  # the shape the call takes
    with pytest.raises(TrackmeterError, match=rf"must be \({dim},\) or \(N,{dim}\), got shape"):
        call(_estec(), np.ones(shape))


def test_the_shapes_taken_give_what_they_gave() -> None:
    rig = _estec()
    p = np.array([[0.1, 0.2, 3.0], [0.0, 0.0, 4.0]])
    assert rig.left.project(p).shape == (2, 2)
    assert np.array_equal(rig.left.project(p[0]), rig.left.project(p)[:1])
    assert rig.left.project(np.zeros((0, 3))).shape == (0, 2) == rig.left.project([]).shape
    uv = rig.left.project(p)
    assert np.array_equal(rig.rectification.rectify_points(uv.reshape(-1, 1, 2)), rig.rectification.rectify_points(uv))
    assert rig.rectification.triangulate(uv[0], 50.0).shape == (1, 3)


@pytest.mark.parametrize("width", [640.7, float("nan"), float("inf"), "640"])
def test_an_image_size_that_is_no_whole_number_is_refused(width: object) -> None:
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    with pytest.raises(TrackmeterError, match="image size must be whole numbers of pixels"):
        Camera(width, 480, K)  # type: ignore[arg-type]
    assert Camera(np.int64(640), 480.0, K).image_size == (640, 480)  # type: ignore[arg-type]  # whole: taken


def test_a_point_in_the_camera_plane_projects_as_the_docstring_says_as_opencv_does() -> None:
    rig = _estec()
    uv = rig.left.project([0.1, 0.1, 0.0])
    assert np.array_equal(uv, rig.left.project([0.1, 0.1, 1.0]))  # through (x, y): 1/z taken as 1
    ref, _ = cv2.projectPoints(np.array([[0.1, 0.1, 0.0]]), np.zeros(3), np.zeros(3), rig.left.K, rig.left.dist)
    assert np.array_equal(uv, ref.reshape(-1, 2))


@pytest.mark.parametrize("f", [1e300, 1e-300, 3.0, 7e6])
def test_a_focal_length_no_lens_has_is_refused_as_such(f: float) -> None:
    """fx 1e300 (or 1e-300) px in a rig file passed and was refused later as the right camera
    "turned 0 deg about its viewing axis" (an outside probe)."""
    K = np.array([[f, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])
    with pytest.raises(TrackmeterError, match=re.escape(f"K's focal length fx = {f:g} px is no lens's for a 640x480 "
                                                        "image (0.01 to 10000 times its larger side)")):
        Camera(640, 480, K)
    Camera(640, 480, np.array([[7.0, 0.0, 319.5], [0.0, 6.4e6, 239.5], [0.0, 0.0, 1.0]]))  # the ends inside
