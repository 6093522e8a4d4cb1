"""Sub-pixel patch tracking: exact shifts, gain/bias, no pixel locking, affine anchor, drift,
epipolar matching, and the real RubberWhale optical-flow pair."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest
from scipy import ndimage

from trackmeter.core import patch_tracking as pt
from trackmeter.core.features import FeatureParams, target_mask
from trackmeter.sources.plane import PlaneScene, pose_translating


def smooth_texture(shape=(160, 160), sigma=1.5, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), sigma)
    return (128 + 40 * img / img.std()).astype(np.float32)


def test_bilinear_matches_exact_linear_interpolation() -> None:
    img = np.add.outer(np.arange(20.0) * 3, np.arange(30.0) * 2).astype(np.float32)  # 2u + 3v
    x = np.array([0.0, 3.25, 28.9, 10.5])
    y = np.array([0.0, 7.75, 18.1, 2.5])
    val, inside = pt.bilinear(img, x, y)
    np.testing.assert_allclose(val, 2 * x + 3 * y, atol=1e-4)
    assert inside.all()
    _, inside = pt.bilinear(img, np.array([-0.1, 29.5]), np.array([1.0, 1.0]))
    assert not inside.any()


def test_compiled_sampling_is_the_numpy_sampling_bit_for_bit() -> None:
    # bilinear's compiled loops (uint8 and float32 images, stacks, a complex rectification
    # table in sample_points) must give exactly the numpy code's numbers and flags, at the
    # border, outside and in between; a NaN coordinate falls back to numpy (which refuses it)
    rng = np.random.default_rng(4)
    for trial in range(60):
        h, w = (int(v) for v in rng.integers(2, 40, 2))
        img = (rng.integers(0, 256, (h, w), dtype=np.uint8) if trial % 2
               else (100 * rng.standard_normal((h, w))).astype(np.float32))
        x = rng.uniform(-3, w + 2, (5, 7)).astype(np.float32)
        y = rng.uniform(-3, h + 2, (5, 7))
        x[0, :3] = [0.0, w - 1, np.float32(w - 1.0005)]
        for got, ref in [(pt.bilinear(img, x, y), pt._bilinear_numpy(img, x, y.astype(np.float32)))]:
            np.testing.assert_array_equal(got[0], ref[0])
            np.testing.assert_array_equal(got[1], ref[1])
        stack = np.stack([img, img[::-1]])
        xs, ys = rng.uniform(-1, w, (2, 4, 4)).astype(np.float32), rng.uniform(-1, h, (2, 4, 4)).astype(np.float32)
        got, ref = pt.bilinear(stack, xs, ys), pt._bilinear_numpy(stack, xs, ys)
        np.testing.assert_array_equal(got[0], ref[0])
        np.testing.assert_array_equal(got[1], ref[1])
        table = (rng.uniform(-5, w + 5, (h + 3, w + 2)) + 1j * rng.uniform(-5, h + 5, (h + 3, w + 2))).astype(np.complex64)
        values, inside = pt.sample_points(img, x, y, table)
        mxy, inside_m = pt._bilinear_numpy(table, x, y.astype(np.float32))
        ref = pt._bilinear_numpy(img, mxy.real.copy(), mxy.imag.copy())
        np.testing.assert_array_equal(values, ref[0])
        np.testing.assert_array_equal(inside, ref[1] & inside_m)
    # numpy casts the NaN to an index (numpy 1.24 and later warn that it does) and the gather
    # then refuses it
    with pytest.raises(IndexError), warnings.catch_warnings():
        warnings.filterwarnings("ignore", "invalid value encountered in cast", RuntimeWarning)
        pt.bilinear(np.ones((4, 4), np.float32), np.array([np.nan, 1.0]), np.array([1.0, 1.0]))


@pytest.mark.parametrize("shift", [(0.3, 0.2), (-0.45, 0.7), (1.6, -1.2)])
def test_lk_recovers_exact_subpixel_shifts_with_gain_and_bias(shift) -> None:
    I0 = smooth_texture()
    # ndimage.shift moves the content by +shift (rows, cols): points move by (du, dv) = shift.
    I1 = ndimage.shift(I0, (shift[1], shift[0]), order=5, mode="nearest").astype(np.float32)
    I1 = 1.4 * I1 - 30.0  # brightness change: gain and bias
    pts = np.array([[60.0, 60.0], [80.0, 100.0], [100.0, 70.0], [70.0, 90.0]])
    T = pt.make_templates(I0, pts, 8)
    res = pt.refine_lk(I1, T, np.round(pts + shift), tolerance_px=1e-4, max_iterations=20)
    assert res.converged.all()
    np.testing.assert_allclose(res.uv - pts, np.broadcast_to(shift, pts.shape), atol=0.03)
    assert np.all(res.score > 0.99)


def test_no_pixel_locking_bias_over_a_pixel_of_shifts() -> None:
    """The mean error over many points must not follow the fractional shift (pixel locking
    bends it toward integers, e.g. a parabola fit's S-curve)."""
    I0 = smooth_texture((220, 220), sigma=1.3, seed=3)
    grid = np.stack(np.meshgrid(np.arange(40.0, 181.0, 20), np.arange(40.0, 181.0, 20)), -1).reshape(-1, 2)
    T = pt.make_templates(I0, grid, 8)
    bias = []
    for s in np.linspace(0.0, 0.9, 10):
        I1 = ndimage.shift(I0, (0.0, s), order=5, mode="nearest").astype(np.float32)
        res = pt.refine_lk(I1, T, grid + [np.round(s), 0.0], tolerance_px=1e-4, max_iterations=20)
        bias.append(np.mean(res.uv[:, 0] - grid[:, 0] - s))
    assert np.max(np.abs(bias)) < 0.02, bias


def test_affine_anchor_keeps_the_centre_on_its_point_under_rotation() -> None:
    I0 = smooth_texture((200, 200), sigma=1.6, seed=5)
    centre = np.array([100.0, 100.0])
    pts = np.array([[92.0, 95.0], [108.0, 103.0], [100.0, 112.0]])
    angle = 12.0
    M = cv2.getRotationMatrix2D(tuple(centre), angle, 1.0)
    I1 = cv2.warpAffine(I0, M, (200, 200), flags=cv2.INTER_CUBIC)
    truth = pts @ M[:, :2].T + M[:, 2]
    T = pt.make_templates(I0, pts, 8)
    W0 = np.concatenate([np.repeat(np.eye(2)[None], 3, 0), np.round(truth)[:, :, None]], axis=2)
    aff = pt.refine_lk_affine(I1, T, W0)
    trans = pt.refine_lk(I1, T, np.round(truth))
    assert aff.converged.all()
    err_aff = np.linalg.norm(aff.uv - truth, axis=1)
    err_trans = np.linalg.norm(trans.uv - truth, axis=1)
    assert err_aff.max() < 0.1
    assert err_aff.mean() < err_trans.mean()  # translation-only is pulled by the rotation
    # The recovered linear part is the rotation.
    np.testing.assert_allclose(aff.warp[:, :, :2], np.repeat(M[None, :, :2], 3, 0), atol=0.03)


def blob_texture(shape, A, seed=0, n=900, sigma=2.2) -> np.ndarray:
    """Gaussian blobs rendered analytically at ``A^-1 (x, y)``: the texture moved EXACTLY by the
    affine map A (2,3), with no resampling of an image."""
    rng = np.random.default_rng(seed)
    c = rng.uniform(0, shape[1], (n, 2))
    a = rng.uniform(-40, 40, n)
    y, x = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    X = np.stack([x - A[0, 2], y - A[1, 2]], -1) @ np.linalg.inv(A[:, :2]).T
    img = np.full(shape, 128.0)
    for (cx, cy), ai in zip(c, a):
        img += ai * np.exp(-((X[..., 0] - cx) ** 2 + (X[..., 1] - cy) ** 2) / (2 * sigma**2))
    return img.astype(np.float32)


def similarity_about(angle_deg: float, scale: float, centre) -> np.ndarray:
    t = np.radians(angle_deg)
    L = scale * np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    return np.column_stack([L, np.asarray(centre, float) - L @ np.asarray(centre, float)])


def test_similarity_anchor_recovers_rotation_and_scale_and_beats_affine_under_noise() -> None:
    """A texture turned by 4 deg and scaled by 4 %: the 4-dof fit recovers centre, angle and
    scale; with image noise and the tracker's budget (8 iterations, 0.02 px) it converges more
    often than the 6-dof affine fit, whose shear/stretch are barely determined by an 8x8 patch."""
    A = similarity_about(4.0, 1.04, (80, 80))
    I0 = blob_texture((160, 160), np.column_stack([np.eye(2), np.zeros(2)]))
    I1 = blob_texture((160, 160), A)
    g = np.stack(np.meshgrid(np.arange(50.0, 111, 15), np.arange(50.0, 111, 15)), -1).reshape(-1, 2)
    truth = g @ A[:, :2].T + A[:, 2]
    T = pt.make_templates(I0, g, 8)
    W0 = np.concatenate([np.repeat(np.eye(2)[None], len(g), 0), np.round(truth)[:, :, None]], 2)
    r = pt.refine_lk_similarity(I1, T, W0, tolerance_px=1e-4, max_iterations=30)
    assert r.converged.all()
    # The limit here is bilinear sampling of an 8x8 patch, not the warp model.
    assert np.abs(r.uv - truth).max() < 0.1
    angle = np.degrees(np.arctan2(r.warp[:, 1, 0], r.warp[:, 0, 0]))
    assert np.abs(angle - 4.0).max() < 1.0
    np.testing.assert_allclose(np.sqrt(np.linalg.det(r.warp[:, :, :2])), 1.04, atol=0.02)
    # The linear part stays a similarity (equal diagonal, opposite off-diagonal).
    np.testing.assert_allclose(r.warp[:, 0, 0], r.warp[:, 1, 1], atol=1e-9)
    np.testing.assert_allclose(r.warp[:, 0, 1], -r.warp[:, 1, 0], atol=1e-9)
    # Euclidean fit with the scale given (as the tracker's depth ratio would): same centre.
    We = W0.copy()
    We[:, :, :2] *= 1.04
    e = pt.refine_lk_euclidean(I1, T, We, tolerance_px=1e-4, max_iterations=30)
    assert e.converged.all() and np.abs(e.uv - truth).max() < 0.1
    np.testing.assert_allclose(np.sqrt(np.linalg.det(e.warp[:, :, :2])), 1.04, atol=1e-9)
    rng = np.random.default_rng(2)
    conv = {"similarity": [], "affine": []}
    for _ in range(10):
        noisy = (I1 + rng.normal(0.0, 4.0, I1.shape)).astype(np.float32)
        conv["similarity"].append(pt.refine_lk_similarity(noisy, T, W0, tolerance_px=0.02, max_iterations=8).converged.mean())
        conv["affine"].append(pt.refine_lk_affine(noisy, T, W0, tolerance_px=0.02, max_iterations=8).converged.mean())
    assert np.mean(conv["similarity"]) > np.mean(conv["affine"]) + 0.15, conv


def run_drift(scene: PlaneScene, uv0: np.ndarray, frames: int, naive: bool) -> np.ndarray:
    """Max error per frame of 2-frame tracking with the naive always-update template, or the
    anchored strategy (track_patches), against the scene's truth."""
    f0 = scene.frame(0)
    body = scene.surface_points(0, uv0)
    img = f0.left.astype(np.float32)
    anchor = pt.make_templates(img, uv0, 8)
    current = anchor
    lin = np.repeat(np.eye(2)[None], len(uv0), 0)
    uv = uv0.copy()
    errs = []
    for k in range(1, frames):
        img = scene.frame(k).left.astype(np.float32)
        starts = np.array([pt.zncc_search(img, current.values[i], uv[i], np.array([6.0, 6.0]))[0] for i in range(len(uv))])
        if naive:
            uv = pt.refine_lk(img, current, starts).uv
        else:
            res = pt.track_patches(img, anchor, lin, current, starts, anchor_min_score=0.9, drift_tolerance_px=0.5)
            uv = res.uv
            lin = np.where(res.anchored[:, None, None], res.anchor_lin, lin)
        current = pt.make_templates(img, uv, 8)
        truth, _ = scene.project(k, body)
        errs.append(np.linalg.norm(uv - truth, axis=1).max())
    return np.array(errs)


@pytest.mark.slow
def test_anchored_template_does_not_drift_where_naive_update_does(estec_rig) -> None:
    """A plate turning about the viewing axis (0.3 rad/s, 25 Hz) for 40 frames: the naive
    every-frame template update accumulates error; the anchored (drift-corrected) one does not."""
    scene = PlaneScene(estec_rig, pose_translating(3.5, (0.15, 0.05, 0.0), (0.0, 0.0, 0.3)), noise_sigma=1.0)
    f0 = scene.frame(0)
    mask = target_mask(f0.left, FeatureParams(target_margin_px=40))  # well inside the plate
    uv0 = cv2.goodFeaturesToTrack(f0.left, 12, 0.05, 30, mask=mask).reshape(-1, 2).astype(float)
    naive = run_drift(scene, uv0, 40, naive=True)
    anchored = run_drift(scene, uv0, 40, naive=False)
    print(f"max error after 40 frames: naive {naive[-1]:.3f} px, anchored {anchored[-1]:.3f} px")
    assert anchored.max() < 0.25
    assert naive[-1] > 2 * anchored[-1]


def still_plate_corners(rig, n: int):  # type: ignore[no-untyped-def]
    """A still textured plate at 3.5 m: its stereo frame, ``n`` interior corners (N,2) and their
    true rectified disparities (N,)."""
    scene = PlaneScene(rig, pose_translating(3.5, (0.0, 0.0, 0.0)), noise_sigma=0.5)
    f = scene.frame(0)
    mask = target_mask(f.left, FeatureParams(target_margin_px=10))
    uv = cv2.goodFeaturesToTrack(f.left, n, 0.05, 25, mask=mask).reshape(-1, 2).astype(float)
    T = scene.T_cam_body(0)
    _, d_true = rig.rectification.project_rectified(scene.surface_points(0, uv) @ T[:3, :3].T + T[:3, 3])
    return f, uv, d_true


def test_epipolar_match_recovers_the_true_disparity(estec_rig) -> None:
    f, uv, d_true = still_plate_corners(estec_rig, 20)
    rect = estec_rig.rectification
    m = pt.match_epipolar(
        f.left.astype(np.float32), f.right.astype(np.float32), rect.maps[0], rect.maps[1],
        rect.rectify_points(uv, 0), np.full(len(uv), 40.0), 80, 8,
        min_score=0.8, uniqueness_margin=0.05, epipolar_tolerance_px=1.0,
    )
    # Some corners of the texture's rectangles repeat along their rows: refused as ambiguous.
    assert m.ok.mean() > 0.5
    assert all(r is None or "ambiguous" in r for r in m.reason)
    err = np.abs(m.disparity_px - d_true)[m.ok]
    assert np.median(err) < 0.05 and err.max() < 0.2
    assert np.all(np.abs(m.epipolar_residual_px[m.ok]) < 0.2)


def test_rubberwhale_median_endpoint_error(shared_data) -> None:
    """Real imagery: Shi-Tomasi corners of frame10 tracked into frame11 against the true flow
    (Middlebury RubberWhale); OpenCV's pyramidal LK on the same points for comparison. The same
    evaluation the ``tracker`` benchmark reports."""
    from benchmarks.tracker import rubberwhale

    figures = rubberwhale(shared_data)
    print(f"RubberWhale median EPE: ours {figures['rubberwhale_median_epe_px']:.4f} px on "
          f"{figures['rubberwhale_points']:.0f} points, pyramidal LK "
          f"{figures['rubberwhale_median_epe_px_lk']:.4f} px on {figures['rubberwhale_points_lk']:.0f} points")
    assert figures["rubberwhale_points"] > 0.7 * figures["rubberwhale_points_known_flow"]
    assert figures["rubberwhale_median_epe_px"] <= 0.05


def test_match_epipolar_per_point_span_equals_separate_calls(estec_rig) -> None:
    """One batch with a span per point gives each point what a call with its own span gives,
    and a point whose true disparity lies just past its own span is not matched there."""
    f, uv, d_true = still_plate_corners(estec_rig, 12)
    rect = estec_rig.rectification
    n = len(uv)
    spans = np.where(np.arange(n) % 2 == 0, 12, 24)
    lo = np.floor(d_true) - spans // 2
    lo[-1] = np.floor(d_true[-1]) + 3  # the truth is below this point's range
    args = (f.left.astype(np.float32), f.right.astype(np.float32), rect.maps[0], rect.maps[1])
    kw = dict(min_score=0.8, uniqueness_margin=0.05, epipolar_tolerance_px=1.0)
    cl = rect.rectify_points(uv, 0)
    batch = pt.match_epipolar(*args, cl, lo, spans, 8, **kw)
    for i in range(n):
        one = pt.match_epipolar(*args, cl[i : i + 1], lo[i : i + 1], int(spans[i]), 8, **kw)
        assert batch.reason[i] == one.reason[0]
        if one.reason[0] is None:
            np.testing.assert_allclose(batch.disparity_px[i], one.disparity_px[0], atol=1e-9)
        np.testing.assert_allclose(batch.second_score[i], one.second_score[0], atol=1e-9)
    ok = batch.ok[:-1]
    assert ok.mean() > 0.5
    assert np.all(np.abs(batch.disparity_px[:-1][ok] - d_true[:-1][ok]) < 0.2)
    assert batch.reason[-1] is not None


def test_zncc_search_matches_a_numpy_reference() -> None:
    # the window, best position and second local maximum against a direct numpy formulation
    rng = np.random.default_rng(5)
    img = cv2.GaussianBlur(rng.random((80, 90)).astype(np.float32), (0, 0), 1.2)
    img[:, 60:] = 0.5  # a flat part: scores of -1/0 and windows clipped at the border
    for k in range(40):
        c = rng.uniform([-5, -5], [95, 85])
        half = rng.uniform(1, 12, size=2)
        tmpl = img[20 + k % 30 : 28 + k % 30, 10 + k : 18 + k]
        got = pt.zncc_search(img, tmpl, c, half)
        x0 = max(int(np.floor(c[0] - half[0] - 3.5)), 0)
        x1 = min(int(np.ceil(c[0] + half[0] + 3.5)) + 1, 90)
        y0 = max(int(np.floor(c[1] - half[1] - 3.5)), 0)
        y1 = min(int(np.ceil(c[1] + half[1] + 3.5)) + 1, 80)
        if x1 - x0 < 8 or y1 - y0 < 8:
            assert got is None
            continue
        res = cv2.matchTemplate(img[y0:y1, x0:x1], tmpl, cv2.TM_CCOEFF_NORMED)
        i, j = np.unravel_index(np.argmax(res), res.shape)
        peaks = res >= ndimage.maximum_filter(res, size=3, mode="nearest")
        peaks[max(i - 4, 0) : i + 5, max(j - 4, 0) : j + 5] = False
        np.testing.assert_array_equal(got[0], [x0 + j + 3.5, y0 + i + 3.5])
        assert got[1] == float(res[i, j])
        assert got[2] == float(np.max(res, where=peaks, initial=-1.0))


def test_row_mean_is_numpys_mean_bit_for_bit() -> None:
    # the LK loops' cheaper mean must give exactly np.mean's numbers (sum / count)
    rng = np.random.default_rng(3)
    for shape in [(1, 64), (7, 144), (5, 2, 64), (3, 1000)]:
        x = rng.normal(size=shape) * 10.0 ** rng.integers(-3, 4, size=shape[:-1] + (1,))
        np.testing.assert_array_equal(pt._row_mean(x), x.mean(axis=-1, keepdims=True))
    a, b = rng.random((9, 8, 8)).astype(np.float32), rng.random((9, 8, 8)).astype(np.float32)
    a64 = a.reshape(9, -1).astype(np.float64)
    ref = (a64 - a64.mean(1, keepdims=True)), b.reshape(9, -1).astype(np.float64)
    ref = (ref[0] * (ref[1] - ref[1].mean(1, keepdims=True))).sum(1) / np.sqrt(
        (ref[0] ** 2).sum(1) * ((ref[1] - ref[1].mean(1, keepdims=True)) ** 2).sum(1))
    np.testing.assert_array_equal(pt.zncc(a, b), ref)


def _blurred_pair(shift: tuple[float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(image 0, image 1 = image 0 moved by ``shift``, their Gaussian-smoothed copies (sigma 0.7))."""
    I0 = smooth_texture((160, 160), sigma=1.5, seed=5)
    I1 = ndimage.shift(I0, (shift[1], shift[0]), order=5, mode="nearest").astype(np.float32)
    return I0, I1, cv2.GaussianBlur(I0, (0, 0), 0.7), cv2.GaussianBlur(I1, (0, 0), 0.7)


def test_raw_recheck_takes_the_translation_refit_on_the_image_itself() -> None:
    """track_patches with raw_image: the anchored position and score are those of
    refine_lk_translation on the unsmoothed image, started from the smoothed fit's warp."""
    pts = np.array([[50.0, 50.0], [90.0, 70.0], [70.0, 110.0]])
    I0, I1, S0, S1 = _blurred_pair((0.4, -0.3))
    anchor, raw_anchor = pt.make_templates(S0, pts, 8), pt.make_templates(I0, pts, 8)
    lin = np.repeat(np.eye(2)[None], len(pts), 0)
    kw = dict(anchor_min_score=0.9, drift_tolerance_px=0.25, anchor_tolerance_px=1e-3)
    smoothed = pt.track_patches(S1, anchor, lin, anchor, np.round(pts + [0.4, -0.3]), **kw)
    res = pt.track_patches(S1, anchor, lin, anchor, np.round(pts + [0.4, -0.3]), raw_image=I1, raw_anchor=raw_anchor,
                           raw_current=raw_anchor, raw_tolerance_px=0.25, **kw)
    assert smoothed.anchored.all() and res.anchored.all()
    W = np.concatenate([smoothed.anchor_lin, smoothed.uv[:, :, None]], axis=2)
    ref = pt.refine_lk_translation(I1, raw_anchor, W, max_iterations=8, tolerance_px=1e-3, max_shift_px=2.0)
    np.testing.assert_allclose(res.uv, ref.uv, atol=1e-9)
    np.testing.assert_allclose(res.score, ref.score, atol=1e-9)
    np.testing.assert_allclose(res.uv - pts, np.broadcast_to([0.4, -0.3], pts.shape), atol=0.06)  # bilinear LK on 8x8


def test_raw_recheck_fails_a_fit_the_image_itself_puts_elsewhere() -> None:
    """Where the image itself puts the patch farther than raw_tolerance_px from the smoothed
    fit (here: the unsmoothed image is the smoothed one moved by 1 px), neither the anchor nor
    the current template counts as a match."""
    pts = np.array([[50.0, 50.0], [90.0, 70.0]])
    I0, I1, S0, S1 = _blurred_pair((0.2, 0.1))
    raw_moved = ndimage.shift(I1, (0.0, 1.0), order=5, mode="nearest").astype(np.float32)
    anchor, raw_anchor = pt.make_templates(S0, pts, 8), pt.make_templates(I0, pts, 8)
    lin = np.repeat(np.eye(2)[None], len(pts), 0)
    res = pt.track_patches(S1, anchor, lin, anchor, np.round(pts), anchor_min_score=0.9, drift_tolerance_px=0.25,
                           raw_image=raw_moved, raw_anchor=raw_anchor, raw_current=raw_anchor, raw_tolerance_px=0.25)
    assert not res.anchored.any() and not res.converged.any()
    agrees = pt.track_patches(S1, anchor, lin, anchor, np.round(pts), anchor_min_score=0.9, drift_tolerance_px=0.25,
                              raw_image=raw_moved, raw_anchor=raw_anchor, raw_current=raw_anchor, raw_tolerance_px=1.5)
    assert agrees.anchored.all()


def test_scale_fallback_refits_a_refused_anchor_with_its_scale_held() -> None:
    """track_patches(scale_fallback=...): an anchor similarity fit refused by the scale check
    (here a check of 1e-6, which any free scale fails) is fitted again with the scale held at
    the expected one, the result being refine_lk_euclidean's from the start rescaled to it;
    rows without the fallback stay refused (neither anchored nor, since the anchor does not
    confirm the current template, converged)."""
    pts = np.array([[50.0, 50.0], [90.0, 70.0], [70.0, 110.0]])
    shift = (0.4, -0.3)
    I0 = smooth_texture((160, 160), sigma=1.5, seed=5)
    I1 = ndimage.shift(I0, (shift[1], shift[0]), order=5, mode="nearest").astype(np.float32)
    anchor = pt.make_templates(I0, pts, 8)
    lin = np.repeat(np.eye(2)[None], len(pts), 0) * 0.97  # last frame's warp, a scale off
    starts = np.round(pts + shift)
    expect = np.array([1.0, 1.02, 0.99])
    kw = dict(anchor_min_score=0.9, drift_tolerance_px=0.25, anchor_tolerance_px=1e-3, expected_scale=expect,
              max_scale_error=1e-6)
    refused = pt.track_patches(I1, anchor, lin, anchor, starts, **kw)
    assert not refused.anchored.any() and not refused.converged.any()
    res = pt.track_patches(I1, anchor, lin, anchor, starts, scale_fallback=np.array([True, True, False]), **kw)
    assert res.anchored.tolist() == [True, True, False] and res.converged.tolist() == [True, True, False]
    W0 = np.concatenate([lin[:2] * expect[:2, None, None] / 0.97, starts[:2, :, None]], axis=2)
    ref = pt.refine_lk_euclidean(I1, anchor.select(np.arange(2)), W0, max_iterations=8, tolerance_px=1e-3, max_shift_px=2.0)
    np.testing.assert_allclose(res.uv[:2], ref.uv, atol=1e-9)
    np.testing.assert_allclose(res.anchor_lin[:2], ref.warp[:, :, :2], atol=1e-9)
    np.testing.assert_allclose(np.sqrt(np.linalg.det(res.anchor_lin[:2])), expect[:2], rtol=1e-9)  # held
    np.testing.assert_allclose(res.uv[0] - pts[0], shift, atol=0.06)  # bilinear LK on 8x8, scale right
    every = pt.track_patches(I1, anchor, lin, anchor, starts, scale_fallback=True, **kw)
    assert every.anchored.all()
    np.testing.assert_allclose(every.uv[:2], res.uv[:2], atol=1e-12)


def test_a_held_refit_below_the_anchor_score_confirms_the_current_template_only_where_known() -> None:
    """A held refit that converges but scores below anchor_min_score is not taken as the
    position; it confirms the current template's match (the re-anchor path) as any anchor fit
    does. It is made for the similarity rows of anchor_warp "plane" (no prediction), and not
    where the depth-implied scale is unknown (NaN): no scale to hold."""
    pts = np.array([[50.0, 50.0], [90.0, 70.0], [70.0, 110.0]])
    shift = (0.4, -0.3)
    I0 = smooth_texture((160, 160), sigma=1.5, seed=5)
    I1 = ndimage.shift(I0, (shift[1], shift[0]), order=5, mode="nearest").astype(np.float32)
    anchor = pt.make_templates(I0, pts, 8)
    lin = np.repeat(np.eye(2)[None], len(pts), 0)
    starts = np.round(pts + shift)
    kw = dict(anchor_min_score=0.999999, drift_tolerance_px=0.25, anchor_tolerance_px=1e-3, max_scale_error=1e-6)
    without = pt.track_patches(I1, anchor, lin, anchor, starts, expected_scale=np.ones(3), **kw)
    assert not without.converged.any()
    res = pt.track_patches(I1, anchor, lin, anchor, starts, expected_scale=np.array([1.0, 1.0, np.nan]),
                           scale_fallback=True, **kw)
    assert res.converged.tolist() == [True, True, False] and not res.anchored.any()
    current = pt.refine_lk(I1, anchor.select(np.arange(2)), starts[:2], max_iterations=8, tolerance_px=0.01)
    np.testing.assert_allclose(res.uv[:2], current.uv, atol=1e-12)  # the current template's position
    plane = pt.track_patches(I1, anchor, lin, anchor, starts, expected_scale=np.ones(3), scale_fallback=True,
                             anchor_warp="plane", predicted_lin=np.full((3, 2, 2), np.nan), **kw)
    assert plane.converged.all()


@pytest.mark.parametrize("slant_deg", [40.0, 60.0])
def test_the_row_fit_measures_an_oblique_plates_disparity_better_than_the_2d_fit(estec_rig, slant_deg) -> None:
    """match_epipolar's ``row_fit``: on a rectified pair the match lies on the row, and the 2D
    fit's vertical freedom leaks into the disparity where the texture is oblique. Against the
    plate's true disparity at each point (Shi-Tomasi corners, 1 grey level of noise), the
    shift fit along the row is nearer, on the median."""
    from trackmeter.core.matching import MeasureParams
    from trackmeter.core.patch_tracking import match_epipolar, rectified_to_original
    from trackmeter.core.stereo import Rectification
    from trackmeter.core.transforms import make_transform
    from trackmeter.sources.plane import PlaneScene

    R = cv2.Rodrigues(np.array([np.radians(20.0), np.radians(slant_deg), 0.0]))[0]
    plate = PlaneScene(estec_rig, lambda t: make_transform(R, np.array([0.0, 0.0, 3.5])), noise_sigma=1.0)
    f0 = plate.frame(0)
    pts = cv2.goodFeaturesToTrack(f0.left, 40, 0.02, 12).reshape(-1, 2).astype(float)
    rect = Rectification.of(estec_rig)
    T = plate.T_cam_body(0)
    _, d_true = rect.project_rectified(plate.surface_points(0, pts) @ T[:3, :3].T + T[:3, 3])
    maps = (rectified_to_original(rect, 0), rectified_to_original(rect, 1))
    errors = {}
    for name, row_fit in (("2d", None), ("row", MeasureParams())):
        m = match_epipolar(f0.left.astype(np.float32), f0.right.astype(np.float32), *maps, rect.rectify_points(pts, 0),
                           np.floor(d_true) - 6, 12, 8, min_score=0.8, uniqueness_margin=0.05, epipolar_tolerance_px=1.0,
                           row_fit=row_fit)
        ok = np.array([r is None for r in m.reason])
        assert ok.sum() >= 30
        errors[name] = float(np.median(np.abs(m.disparity_px - d_true)[ok]))
    assert errors["row"] < 0.9 * errors["2d"], errors


def test_a_whole_disparity_strip_matches_the_same_whatever_the_last_disparitys_fraction(shared_data) -> None:  # type: ignore[no-untyped-def]
    """``whole_disparity``: the right strip is sampled at a phase the left point sets, so the
    same match comes out of a search from 3.3 px and from 3.7 px; from the fraction itself
    the bilinear strip is another resampling of a sharp image, and the match moves."""
    from trackmeter.core.patch_tracking import match_epipolar, rectified_to_original
    from trackmeter.core.stereo import Camera, Rectification, StereoRig

    left = cv2.imread(str(shared_data / "middlebury_tsukuba" / "img_left.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(shared_data / "middlebury_tsukuba" / "img_right.png"), cv2.IMREAD_GRAYSCALE)
    K = np.array([[615.0, 0.0, 192.0], [0.0, 615.0, 144.0], [0.0, 0.0, 1.0]])
    rig = StereoRig(Camera(384, 288, K, np.zeros(5)), Camera(384, 288, K, np.zeros(5)), np.eye(3), np.array([-0.1, 0.0, 0.0]))
    rect = Rectification.of(rig)
    maps = (rectified_to_original(rect, 0), rectified_to_original(rect, 1))
    pts = cv2.goodFeaturesToTrack(left, 30, 0.05, 10).reshape(-1, 2).astype(float)
    disp = {}
    for whole in (False, True):
        for low in (3.3, 3.7):  # Tsukuba's disparities are 5-14 px
            m = match_epipolar(left.astype(np.float32), right.astype(np.float32), *maps, rect.rectify_points(pts, 0),
                               np.full(len(pts), low), 12, 8, min_score=0.8, uniqueness_margin=0.05,
                               epipolar_tolerance_px=1.0, whole_disparity=whole)
            ok = np.array([r is None for r in m.reason])
            disp[whole, low] = np.where(ok, m.disparity_px, np.nan)
    both = np.isfinite(disp[True, 3.3]) & np.isfinite(disp[True, 3.7])
    assert both.sum() >= 15
    np.testing.assert_array_equal(disp[True, 3.3][both], disp[True, 3.7][both])
    assert np.nanmax(np.abs(disp[False, 3.3] - disp[False, 3.7])) > 0.01


@pytest.mark.parametrize("size", [8, 7])
def test_grid_patch_is_the_pixel_window_nearest_the_point_and_its_offset(size: int) -> None:
    # The window's centre (x0 + (size-1)/2) is the nearest such centre to the point, within
    # half a pixel each axis, and its values are the image's own pixels; off the image: None.
    rng = np.random.default_rng(3)
    img = rng.random((40, 50)).astype(np.float32)
    half = (size - 1) / 2
    for uv in rng.uniform([size, size], [50 - size, 40 - size], size=(50, 2)):
        window, offset = pt.grid_patch(img, uv, size)
        centre = uv - offset
        assert np.all(np.abs(offset) <= 0.5)
        x0, y0 = centre - half
        assert float(x0).is_integer() and float(y0).is_integer()
        np.testing.assert_array_equal(window, img[int(y0) : int(y0) + size, int(x0) : int(x0) + size])
        # and the search finds that window again: its centre plus the offset is the point
        uv_found, best, _ = pt.zncc_search(img, window, uv - offset, np.array([3.0, 3.0]))
        np.testing.assert_allclose(uv_found + offset, uv, atol=1e-9)
        assert best > 0.999
    assert pt.grid_patch(img, np.array([1.0, 20.0]), size) is None
    assert pt.grid_patch(img, np.array([25.0, 39.0]), size) is None
