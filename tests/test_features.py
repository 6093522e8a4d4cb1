"""Automatic feature selection: Gabor directional bank, centroid, Shi-Tomasi; on the target,
spread, away from excluded points, stereo-matchable."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from trackmeter.core import features as ft
from trackmeter.core.features import FeatureParams, select_features
from trackmeter.core.patch_tracking import match_epipolar
from trackmeter.errors import TrackmeterError
from trackmeter.sources.plane import PlaneScene, pose_translating


@pytest.fixture(scope="module")
def plate(estec_rig):  # type: ignore[no-untyped-def]
    scene = PlaneScene(estec_rig, pose_translating(3.5, (0.0, 0.0, 0.0), start_m=(0.1, 0.0)), noise_sigma=0.5)
    return scene, scene.frame(0)


@pytest.fixture(scope="module")
def estec():  # type: ignore[no-untyped-def]
    """One frame of the simulated mock-up: bright faces, black space, and a regular grid
    (repetitive along the epipolar lines) on the solar panel and the side face."""
    from trackmeter.sources.sim.simulator import Simulator

    sim = Simulator("estec")
    return sim.rig, sim.frame(30)


def texture(shape: tuple[int, int], seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.integers(0, 256, shape).astype(np.uint8), (0, 0), 1.5)


@pytest.mark.parametrize("pyramid", [False, True])
def test_gabor_prefers_a_corner_to_an_edge(pyramid: bool) -> None:
    """A good feature answers in at least two directions; a straight edge in one only."""
    img = np.full((120, 160), 40, np.uint8)
    img[30:90, 20:70] = 200  # a square: corners at (20,30), (69,30), ...
    img[:, 110:] = 200  # a long vertical edge at u = 110 (no corner in the middle rows)
    score = ft.gabor_score(img, FeatureParams(gabor_pyramid=pyramid))
    corner = score[25:36, 15:26].max()
    edge = score[55:66, 105:116].max()
    assert corner > 2 * edge
    energy = ft.gabor_directional_energy(img, (4.0, 8.0), 4, pyramid=pyramid)
    e = energy[:, 60, 110]
    assert np.sort(e)[-1] > 5 * np.sort(e)[-2]  # the edge answers in one direction


@pytest.mark.parametrize(("wavelengths", "orientations"), [((4.0, 8.0), 4), ((3.0,), 6), ((5.0, 7.0), 3)])
def test_separable_gabor_equals_the_2d_bank(wavelengths, orientations) -> None:  # type: ignore[no-untyped-def]
    """The separable filtering is the 2D bank (cv2.getGaborKernel, zero-mean even part)
    applied with cv2.filter2D, to float32 rounding."""
    img = texture((90, 110))
    ref = np.zeros((orientations, *img.shape), np.float32)
    for k, scales in enumerate(ft.gabor_bank(wavelengths, orientations)):
        for even, odd in scales:
            e = cv2.filter2D(img.astype(np.float32), cv2.CV_32F, even)
            o = cv2.filter2D(img.astype(np.float32), cv2.CV_32F, odd)
            np.maximum(ref[k], np.hypot(e, o), out=ref[k])
    got = ft.gabor_directional_energy(img, wavelengths, orientations)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-5 * ref.max())


def test_pyramid_gabor_approximates_the_exact_bank() -> None:
    """The 8 px wavelength filtered at half resolution: the same energies where they matter
    (the strongest tenth) within a few percent, without bias."""
    img = texture((200, 240))
    exact = ft.gabor_directional_energy(img, (4.0, 8.0), 4)
    pyr = ft.gabor_directional_energy(img, (4.0, 8.0), 4, pyramid=True)
    strong = exact > np.percentile(exact, 90)
    rel = pyr[strong] / exact[strong] - 1
    assert abs(np.median(rel)) < 0.05
    assert np.median(np.abs(rel)) < 0.08
    # The pyramid level only changes the 8 px band: a 4 px-only bank is untouched.
    np.testing.assert_allclose(ft.gabor_directional_energy(img, (4.0,), 4, pyramid=True), ft.gabor_directional_energy(img, (4.0,), 4), rtol=1e-6)


def greedy_reference(points: np.ndarray, scores: np.ndarray, d: float, limit: int) -> np.ndarray:
    kept: list[np.ndarray] = []
    for i in np.argsort(-scores, kind="stable"):
        if all(((points[i] - q) ** 2).sum() >= d * d for q in kept):
            kept.append(points[i])
            if len(kept) >= limit:
                break
    return np.array(kept, dtype=float).reshape(-1, 2)


@pytest.mark.parametrize("seed", range(6))
def test_spread_is_the_greedy_non_maximum_suppression(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 300))
    # Integer pixels (exact distances of 20 px occur: such a pair is kept) and tied scores.
    pts = rng.integers(0, 150, (n, 2)).astype(float) if seed % 2 else rng.random((n, 2)) * 150
    scores = rng.integers(0, 10, n).astype(float)
    for d, limit in [(20.0, 1000), (13.0, 7), (0.0, 5)]:
        np.testing.assert_array_equal(ft.spread(pts, scores, d, limit), greedy_reference(pts, scores, d, limit))


def test_spread_of_a_plateau_holds_no_neighbour_lists_of_every_point() -> None:
    """Every pixel of a flat image was a candidate (370k at 726x512), and the neighbours of
    each within min_distance_px (1,250 at 20 px) were listed before the greedy pass: 20 GB
    and 40 s for one frame (an outside probe). Only the kept points' neighbours are needed."""
    import tracemalloc

    ys, xs = np.mgrid[0:200, 0:200]
    pts = np.column_stack([xs.ravel(), ys.ravel()]).astype(float)
    scores = np.ones(len(pts))
    tracemalloc.start()
    try:
        kept = ft.spread(pts, scores, 10.0, 64)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 20e6, f"{peak / 1e6:.0f} MB"
    np.testing.assert_array_equal(kept, greedy_reference(pts, scores, 10.0, 64))


def test_a_flat_image_has_no_gabor_candidates() -> None:
    # A saturated or blank frame's score is floating-point residue (1e-4 at grey 255), which
    # passed "score > 0" and the relative quality test at every pixel; a step of one grey
    # level scores about 1, the noise of a real sensor about 10.
    params = FeatureParams()
    for grey in (0, 128, 255):
        flat = np.full((120, 160), grey, np.uint8)
        assert len(ft._candidates_gabor(flat, np.full(flat.shape, 255, np.uint8), params, 64)) == 0
    step = np.full((120, 160), 128, np.uint8)
    step[60:, 80:] = 129
    assert len(ft._candidates_gabor(step, np.full(step.shape, 255, np.uint8), params, 64)) > 0


def full_range_reference(rig, frame, uv, params) -> np.ndarray:  # type: ignore[no-untyped-def]
    """match_epipolar over the whole depth range in one pass: what stereo_matchable decides."""
    rect = rig.rectification
    lo, hi = ft.search_disparities(rig, params)
    m = match_epipolar(
        frame.left, frame.right, rect.maps[0], rect.maps[1], rect.rectify_points(uv, 0), np.full(len(uv), lo), int(np.ceil(hi - lo)),
        params.patch_size, min_score=params.stereo_min_score, uniqueness_margin=params.uniqueness_margin, epipolar_tolerance_px=1.0,
    )  # fmt: skip
    return m.ok


def test_stereo_check_equals_match_epipolar_over_the_whole_line(estec) -> None:  # type: ignore[no-untyped-def]
    """The two-stage check (cheap ZNCC profile over the line, match_epipolar near the peak)
    decides as match_epipolar over the whole line, on the mock-up's candidates: many are
    ambiguous on its regular grid."""
    rig, f = estec
    params = FeatureParams()
    cand = ft._candidates_gabor(f.left, ft.target_mask(f.left, params), params, 80)
    ref = full_range_reference(rig, f, cand, params)
    assert 10 <= ref.sum() <= len(cand) - 10  # both outcomes are exercised
    np.testing.assert_array_equal(ft.stereo_matchable(f.left, f.right, rig, cand, params), ref)
    # need=k: the same first k, nothing checked after the k-th pass.
    first = ft.stereo_matchable(f.left, f.right, rig, cand, params, need=5)
    k = np.flatnonzero(ref)[4]
    np.testing.assert_array_equal(first[: k + 1], ref[: k + 1])
    assert first.sum() >= 5
    # Without the second stage: every point match_epipolar passes, and few more.
    coarse = ft.stereo_matchable(f.left, f.right, rig, cand, params, refine=False)
    assert np.all(coarse[ref]) and (coarse & ~ref).sum() <= 0.05 * ref.sum()


def test_the_integer_profile_is_match_epipolars(estec) -> None:  # type: ignore[no-untyped-def]
    rig, f = estec
    params = FeatureParams()
    cand = ft._candidates_gabor(f.left, ft.target_mask(f.left, params), params, 40)
    rect = rig.rectification
    lo, hi = ft.search_disparities(rig, params)
    span = int(np.ceil(hi - lo))
    cl = rect.rectify_points(cand, 0)
    scores, k_best = ft._epipolar_profile(f.left.astype(np.float32), f.right.astype(np.float32), rect, cl, int(lo), span, params.patch_size)
    m = match_epipolar(
        f.left, f.right, rect.maps[0], rect.maps[1], cl, np.full(len(cl), lo), span,
        params.patch_size, min_score=params.stereo_min_score, uniqueness_margin=params.uniqueness_margin, epipolar_tolerance_px=1.0,
    )  # fmt: skip
    far = np.abs(np.arange(span + 1)[None] - k_best[:, None]) > params.patch_size // 2
    second = np.where(far, scores, -1).max(1)
    np.testing.assert_allclose(second, m.second_score, atol=1e-3)
    # The peak is where the refined match is (within the sub-pixel refinement).
    ok = np.array(m.ok)
    np.testing.assert_allclose((lo + span - k_best)[ok], m.disparity_px[ok], atol=1.0)


def test_centroid_of_a_bright_disc_on_black_space() -> None:
    img = np.zeros((200, 300), np.uint8)
    cv2.circle(img, (180, 90), 40, 180, -1)
    rng = np.random.default_rng(0)
    img = np.clip(img + (img > 0) * rng.integers(0, 30, img.shape), 0, 255).astype(np.uint8)
    pts = select_features(img, None, None, 1, "centroid", FeatureParams(), ())
    assert len(pts) == 1
    np.testing.assert_allclose(pts[0], (180, 90), atol=0.5)


def test_centroids_are_spread_as_every_method_s_points_are() -> None:
    # A bright ring round a separate bright disc: both centroids on the disc's centre, the
    # same point returned twice, though the points are to be min_distance_px apart.
    img = np.zeros((200, 200), np.uint8)
    cv2.circle(img, (100, 100), 70, 200, 12)
    cv2.circle(img, (100, 100), 30, 200, -1)
    params = FeatureParams(target_margin_px=0, border_px=0)
    pts = select_features(img, None, None, 5, "centroid", params, ())
    assert len(pts) == 1
    np.testing.assert_allclose(pts[0], (100, 100), atol=0.5)


def test_centroids_are_found_on_a_dim_target_as_the_other_methods_find_points() -> None:
    # The centroids were labelled with black_level only, not the signal-to-noise map the
    # selectable mask falls back to on a target in deep shadow: nothing, and no reason why.
    rng = np.random.default_rng(2)
    img = np.clip(rng.normal(4.0, 1.0, (200, 300)), 0, 255)
    disc = np.zeros((200, 300), np.uint8)
    cv2.circle(disc, (150, 100), 50, 1, -1)
    img = np.clip(img + disc * (10.0 + rng.normal(0, 1.0, img.shape)), 0, 255).astype(np.uint8)
    params = FeatureParams()
    assert (img[disc > 0] <= params.black_level).mean() > 0.95  # below black_level: in deep shadow
    assert len(select_features(img, None, None, 4, "shi_tomasi", params, ())) > 0
    pts = select_features(img, None, None, 4, "centroid", params, ())
    assert len(pts) == 1
    np.testing.assert_allclose(pts[0], (150, 100), atol=1.0)


@pytest.mark.parametrize("method", ft.METHODS)
def test_targets_far_outside_the_image_or_an_empty_image_are_no_opencv_error(method: str) -> None:
    # A diverged target's pixel (3e9) was given to cv2.circle as it was: a bare cv2.error.
    img = np.zeros((100, 120), np.uint8)
    cv2.rectangle(img, (30, 30), (90, 70), 150, -1)
    far = np.array([[3e9, 50.0], [-1e12, -1e12], [60.0, 50.0]])
    pts = select_features(img, None, None, 3, method, FeatureParams(border_px=0), far)
    assert np.all(np.hypot(pts[:, 0] - 60.0, pts[:, 1] - 50.0) >= 20.0)
    assert len(select_features(np.zeros((0, 0), np.uint8), None, None, 3, method, FeatureParams(), ())) == 0
    assert ft.nothing_selectable_reason(np.zeros((0, 0), np.uint8), FeatureParams()) == ft.NOTHING_LIT


def test_a_distance_beyond_any_image_is_refused_not_a_crash_in_opencv() -> None:
    # features.min_distance_px 3e9 (and analyze.corner_min_distance_px) reached
    # cv2.goodFeaturesToTrack, which crashed the process (a segmentation fault).
    from trackmeter.core.error_analysis import AnalyzeParams

    for make in (lambda d: FeatureParams(min_distance_px=d), lambda d: AnalyzeParams(corner_min_distance_px=d)):
        for distance in (3e9, float("inf")):
            with pytest.raises(TrackmeterError, match="min_distance_px: expected a value in"):
                make(distance)
        make(1e5)


@pytest.mark.parametrize(("method", "refine"), [("gabor", True), ("shi_tomasi", True), ("gabor", False)])
def test_selected_points_are_on_the_target_spread_and_stereo_matchable(plate, estec_rig, method, refine) -> None:
    scene, f = plate
    params = FeatureParams(stereo_refine=refine)
    exclude = np.array([[400.0, 250.0]])
    pts = select_features(f.left, f.right, estec_rig, 12, method, params, exclude)
    assert 6 <= len(pts) <= 12
    # On the plate (not black space), and the whole patch too.
    assert np.all(np.isfinite(scene.surface_points(0, pts)))
    for u, v in pts:
        patch = f.left[int(v) - 4 : int(v) + 5, int(u) - 4 : int(u) + 5]
        assert patch.min() > params.black_level
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2) + np.eye(len(pts)) * 1e9
    assert d.min() >= params.min_distance_px - 1e-9
    assert np.linalg.norm(pts - exclude, axis=1).min() >= params.min_distance_px
    # Stereo-matchable: every point has a unique epipolar match (with the sub-pixel checks
    # too when refined; without, a rare point may fail those).
    ok = ft.stereo_matchable(f.left, f.right, estec_rig, pts, params)
    assert ok.all() if refine else ok.mean() >= 0.9


def test_nothing_is_selected_on_black_space(estec_rig) -> None:
    black = np.full((512, 726), 5, np.uint8)
    for method in ft.METHODS:
        assert len(select_features(black, black, estec_rig, 5, method, FeatureParams(), ())) == 0


def test_unknown_method_is_refused() -> None:
    with pytest.raises(TrackmeterError, match="unknown feature selection method"):
        select_features(np.zeros((10, 10), np.uint8), None, None, 3, "sift", FeatureParams(), ())


def test_a_disparity_range_narrows_the_search_but_not_below_the_minimum_span(plate, estec_rig) -> None:
    scene, f = plate
    params = FeatureParams()
    full = ft.search_disparities(estec_rig, params)
    assert ft.search_disparities(estec_rig, params, (80.0, 110.0)) == (63.0, 127.0)  # widened to 64 px about 95
    assert ft.search_disparities(estec_rig, params, (40.0, 200.0)) == (40.0, 200.0)
    assert ft.search_disparities(estec_rig, params, (-50.0, 1000.0)) == full  # clipped to the depth range
    # The plate at 3.5 m: around its disparity, the same points as over the whole range.
    d = estec_rig.rectification.focal_px * estec_rig.rectification.baseline_m / 3.5 + estec_rig.rectification.disparity_offset_px
    pts = select_features(f.left, f.right, estec_rig, 8, "gabor", params)
    near = select_features(f.left, f.right, estec_rig, 8, "gabor", params, disparity_range_px=(d - 20, d + 20))
    assert len(pts) == 8
    np.testing.assert_array_equal(near, pts)
    for bad in [(10.0,), (5.0, 1.0), (np.nan, 3.0)]:
        with pytest.raises(TrackmeterError, match="disparity_range_px"):
            select_features(f.left, f.right, estec_rig, 3, "gabor", params, disparity_range_px=bad)  # type: ignore[arg-type]


def test_corners_near_a_click_are_opencv_s_corners_there_nearest_first() -> None:
    # A bright square on black: its four corners are the only Shi-Tomasi corners (OpenCV's own
    # cv2.goodFeaturesToTrack), and a click beside one finds it first, one farther away none.
    img = np.zeros((80, 100), np.uint8)
    img[20:50, 30:70] = 200
    found = ft.corners_near(img, (32.0, 23.0), radius_px=6.0)
    assert len(found) >= 1 and np.hypot(*(found[0] - [30, 20])) < 1.5, found
    assert np.all(np.diff(np.hypot(found[:, 0] - 32, found[:, 1] - 23)) >= 0)
    reference = cv2.goodFeaturesToTrack(img, 8, 0.05, 2, blockSize=5).reshape(-1, 2)
    assert min(np.hypot(*(reference - found[0]).T)) < 1e-6  # one of OpenCV's corners, as it found it
    assert len(ft.corners_near(img, (50.0, 35.0), radius_px=6.0)) == 0  # mid-square: nothing
    assert len(ft.corners_near(img, (-40.0, 300.0), radius_px=6.0)) == 0  # off the image
    assert len(ft.corners_near(img, (32.0, 23.0), radius_px=0.0)) == 0


@pytest.mark.parametrize("margin_px", [0, 5, 40, 100_000])
def test_the_target_mask_is_the_square_erosion_at_any_margin(margin_px: int) -> None:
    # A margin of 100000 px (a typo in --config) allocated a 200001 x 200001 kernel: a
    # MemoryError on every frame. A square wider than the image leaves nothing, at no cost.
    rng = np.random.default_rng(0)
    image = np.where(rng.random((60, 80)) < 0.97, 200, 0).astype(np.uint8)
    image[20:50, 10:70] = 200
    params = FeatureParams(target_margin_px=margin_px, border_px=3)
    r = params.patch_size // 2 + margin_px
    expected = np.zeros(image.shape, np.uint8)
    if 2 * r + 1 <= min(image.shape):
        for v in range(image.shape[0]):
            for u in range(image.shape[1]):
                window = image[max(v - r, 0):v + r + 1, max(u - r, 0):u + r + 1]
                inside = r <= v < image.shape[0] - r and r <= u < image.shape[1] - r
                expected[v, u] = 255 if inside and (window > params.black_level).all() else 0
        expected[:3], expected[-3:], expected[:, :3], expected[:, -3:] = 0, 0, 0, 0
    np.testing.assert_array_equal(ft.target_mask(image, params), expected)


def test_the_stereo_check_searches_from_infinity_on_a_pair_rectified_with_principal_points_apart(shared_data) -> None:  # type: ignore[no-untyped-def]
    """On a pair rectified already whose principal points lie apart (Middlebury 2014's
    ``doffs``), a point at infinity has the disparity ``cx1 - cx2``; the stereo check's range
    was cut at 0, so with Tsukuba's right image moved 12 px right (its principal point with it)
    hardly a point (5-14 px apart, now -7 to 2) passed."""
    from benchmarks.measure import identity_rig, load_tsukuba, principal_points_apart

    left, right, _ = load_tsukuba(shared_data / "middlebury_tsukuba")
    rig = identity_rig(384, 288, focal_px=400.0)
    moved_rig, moved = principal_points_apart(rig, right, 12)
    as_given = select_features(left, right, rig, 40, "shi_tomasi", FeatureParams())
    as_moved = select_features(left, moved, moved_rig, 40, "shi_tomasi", FeatureParams())
    assert len(as_given) >= 30
    assert len(as_moved) >= 0.9 * len(as_given), (len(as_moved), len(as_given))
