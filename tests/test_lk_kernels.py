"""The compiled Lucas-Kanade loops (trackmeter.core.lk_kernels, through patch_tracking's
refine_lk and warp fits) against the numpy implementations they replaced (tests/lk_reference.py):
the same arithmetic in another summation order, so the same results to ~1e-9, on textures,
brightness changes, stacks of strips, failures at the border and every warp model."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from tests.lk_reference import refine_lk_reference, refine_lk_warp_reference
from trackmeter.core import patch_tracking as pt


def texture(shape=(120, 140), seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = ndimage.gaussian_filter(rng.standard_normal(shape), 1.5)
    return (128 + 40 * img / img.std()).astype(np.float32)


def moved(img: np.ndarray, du: float, dv: float, gain: float = 1.0, bias: float = 0.0) -> np.ndarray:
    return (gain * ndimage.shift(img, (dv, du), order=3, mode="nearest") + bias).astype(np.float32)


def starts(n: int, shape, seed: int, margin: float = 14.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(margin, shape[1] - margin, n), rng.uniform(margin, shape[0] - margin, n)])


def assert_same_lk(got: pt.LKResult, ref: pt.LKResult) -> None:
    np.testing.assert_array_equal(got.converged, ref.converged)
    np.testing.assert_array_equal(got.iterations, ref.iterations)
    np.testing.assert_allclose(got.uv, ref.uv, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got.score, ref.score, rtol=0, atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("axis_mask", [(1.0, 1.0), (1.0, 0.0)])
@pytest.mark.parametrize("dtype", [np.float32, np.uint8])
def test_translation_matches_numpy_reference(seed: int, axis_mask, dtype) -> None:
    I0 = texture(seed=seed)
    I1 = np.clip(moved(I0, 0.37 + seed * 0.4, -0.61, gain=1.3, bias=-20.0), 0, 255).astype(dtype)  # uint8: a camera frame
    pts = starts(24, I0.shape, seed)
    pts[0] = [3.0, 50.0]  # the template half outside: not ok, never iterates
    pts[1] = [9.0, 60.0]  # the search walks off the image
    T = pt.make_templates(I0, pts, 8)
    uv0 = np.round(pts + [0.4, -0.6])
    for kw in ({}, dict(max_iterations=3, tolerance_px=1e-6), dict(max_shift_px=0.2)):
        assert_same_lk(pt.refine_lk(I1, T, uv0, axis_mask=axis_mask, **kw),
                       refine_lk_reference(I1, T, uv0, axis_mask=axis_mask, **kw))


def test_translation_on_a_stack_of_strips_matches_numpy_reference() -> None:
    I0 = texture(seed=3)
    strips = np.stack([moved(I0, 0.3 * k, 0.1, gain=0.8 + 0.1 * k)[30:50, 20:90] for k in range(5)])
    T = pt.make_templates(I0[30:50, 20:90], np.array([[30.0 + 5 * k, 9.5] for k in range(5)]), 8)
    uv0 = np.array([[30.0 + 5 * k, 9.5] for k in range(5)])
    assert_same_lk(pt.refine_lk(strips, T, uv0), refine_lk_reference(strips, T, uv0))


@pytest.mark.parametrize("model", ["affine", "similarity", "euclidean", "disparity_plane"])
def test_warp_fits_match_numpy_reference(model: str) -> None:
    I0 = texture(seed=4)
    rows = np.arange(I0.shape[0], dtype=float)[:, None]
    cols = np.arange(I0.shape[1], dtype=float)[None, :]
    # a small rotation and scale about the image centre, and a brightness change
    a, s, c = np.deg2rad(2.0), 1.03, np.array([70.0, 60.0])
    x = (np.cos(a) * (cols - c[0]) + np.sin(a) * (rows - c[1])) / s + c[0]
    y = (-np.sin(a) * (cols - c[0]) + np.cos(a) * (rows - c[1])) / s + c[1]
    I1 = (1.2 * ndimage.map_coordinates(I0, [y, x], order=3, mode="nearest") + 5).astype(np.float32)
    I1 = np.clip(I1, 0, 255).astype(np.uint8) if model == "similarity" else I1  # the anchors' fit runs on camera frames
    pts = starts(20, I0.shape, 5)
    pts[0] = [2.0, 40.0]
    T = pt.make_templates(I0, pts, 8)
    W0 = np.concatenate([np.broadcast_to(np.eye(2), (len(pts), 2, 2)), np.round(pts)[:, :, None]], axis=2)
    hold = np.arange(len(pts)) % 3 == 0
    converged = []
    for kw in (dict(hold_linear=None), dict(hold_linear=hold), dict(hold_linear=None, max_iterations=2)):
        args = (I1, T, W0, model, kw.get("max_iterations", 20), 1e-3, 3.0, kw["hold_linear"])
        got, ref = pt._refine_lk_warp(*args), refine_lk_warp_reference(*args)
        np.testing.assert_array_equal(got.converged, ref.converged)
        np.testing.assert_allclose(got.warp, ref.warp, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got.score, ref.score, rtol=0, atol=1e-9)
        converged.append(int(got.converged.sum()))
    assert converged[0] >= len(pts) // 2, converged  # the comparison is not of failures only


def test_translation_converges_on_most_points() -> None:
    """Guards the reference comparison above against comparing two failures."""
    I0 = texture(seed=6)
    I1 = moved(I0, 0.45, 0.2)
    pts = starts(16, I0.shape, 6)
    res = pt.refine_lk(I1, pt.make_templates(I0, pts, 8), np.round(pts + [0.45, 0.2]))
    assert res.converged.sum() >= 14
    np.testing.assert_allclose(res.uv[res.converged], (pts + [0.45, 0.2])[res.converged], atol=0.05)


def test_compiles_without_a_writable_cache(monkeypatch: pytest.MonkeyPatch) -> None:
    """A read-only install and home: numba refuses cache=True at decoration; compile per process."""
    import numba

    from trackmeter.core import lk_kernels

    real = numba.njit

    def njit(**options):  # type: ignore[no-untyped-def]
        if options.get("cache"):
            raise RuntimeError("cannot cache function 'f': no locator available for file 'f.py'")
        return real(**options)

    monkeypatch.setattr(numba, "njit", njit)

    def double(x):  # type: ignore[no-untyped-def]
        return 2.0 * x

    assert lk_kernels._jit(double)(1.5) == 3.0


def test_warm_up_compiles_what_a_tracker_runs(estec_rig) -> None:  # type: ignore[no-untyped-def]
    """After warm_up a tracker step compiles nothing more: a live pipeline calls it before the
    source starts, so no frame waits for a compile (or a cache load)."""
    from tests.test_tracking import add_all, interior_points, make_tracker
    import numba

    from trackmeter.core import lk_kernels
    from trackmeter.sources.plane import PlaneScene, pose_translating

    if numba.config.DISABLE_JIT:
        pytest.skip("NUMBA_DISABLE_JIT=1: the loops run as Python, nothing is compiled")
    pt.warm_up()
    compiled = {k: list(getattr(lk_kernels, k).signatures) for k in ("lk_translation", "lk_warp")}
    scene = PlaneScene(estec_rig, pose_translating(3.5, (0.1, 0.05, 0.0), (0.0, 0.0, 0.2)), noise_sigma=1.0)
    tracker = make_tracker(estec_rig)
    f0 = scene.frame(0)
    assert len(add_all(tracker, f0, interior_points(f0, 6))) >= 4
    for k in range(1, 4):
        tracker.step(scene.frame(k))
    assert {k: list(getattr(lk_kernels, k).signatures) for k in compiled} == compiled


def test_no_patches_and_a_diverged_start() -> None:
    """Zero patches give empty results (the warp fits reshaped them by -1 and raised); a NaN
    start does not converge, where numpy's clamp passed the NaN to an index."""
    img = texture(seed=7)
    none = pt.make_templates(img, np.zeros((0, 2)), 8)
    assert pt.refine_lk(img, none, np.zeros((0, 2))).uv.shape == (0, 2)
    assert pt.refine_lk_similarity(img, none, np.zeros((0, 2, 3))).warp.shape == (0, 2, 3)
    one = pt.make_templates(img, np.array([[60.0, 60.0]]), 8)
    assert not pt.refine_lk(img, one, np.array([[np.nan, 60.0]])).converged[0]
    assert not pt.refine_lk_similarity(img, one, np.array([[[np.nan, 0.0, 60.0], [0.0, 1.0, 60.0]]])).converged[0]
