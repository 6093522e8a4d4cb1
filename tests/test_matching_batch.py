"""Batched point measurement: ``measure_points`` on many points at once gives each point the
result it gets alone.

References: :func:`trackmeter.core.matching.sample_rectified` (one block per call, itself pinned
to OpenCV's full-image remap in ``test_matching.py``), :func:`refine_position` (the scalar
Gauss-Newton fit), and ``measure_points`` called point by point on the real Middlebury Tsukuba
pair and on a plane rendered through the paper's rig (distortion, rotated right camera).
"""

from __future__ import annotations

import collections
import dataclasses

import cv2
import numpy as np
import pytest

from benchmarks.measure import band_limited_texture, estec_plane, identity_rig, load_tsukuba, shifted_pair, tsukuba_grid
from trackmeter.core.matching import (
    MeasureParams,
    measure_points,
    refine_position,
    refine_positions,
    sample_rectified,
    sample_rectified_blocks,
)


@pytest.fixture(scope="module")
def plane():  # type: ignore[no-untyped-def]
    return estec_plane(seed=5)


@pytest.mark.parametrize("interp, exact", [(cv2.INTER_LANCZOS4, True), (cv2.INTER_LINEAR, False), (cv2.INTER_LINEAR, True)])
def test_sample_rectified_blocks_are_sample_rectified_bit_for_bit(plane, interp: int, exact: bool) -> None:  # type: ignore[no-untyped-def]
    rig, left, right, _ = plane
    rect = rig.rectification
    W, H = rig.image_size
    rng = np.random.default_rng(0)
    blocks = []
    for _ in range(40):
        w, h = int(rng.integers(8, 300)), int(rng.integers(8, 17))
        blocks.append((float(rng.uniform(0, W - w - 2)), float(rng.uniform(0, H - h - 2)), w, h))
    blocks += [(0.3, 5.5, 40, 8), (W - 42.0 + 0.7, H - 10.2, 41, 8)]  # at the borders: col_ok flags (left image)
    n_flagged = 0
    for side, image in ((0, left), (1, right)):
        got = sample_rectified_blocks(rect, image, side, blocks, interp, exact)
        for b, (block, col_ok) in zip(blocks, got):
            ref, ref_ok = sample_rectified(rect, image, side, *b, interpolation=interp, exact=exact)
            assert block.dtype == ref.dtype and np.array_equal(block, ref)
            assert (col_ok is None) == (ref_ok is None)
            if ref_ok is not None:
                n_flagged += 1
                assert np.array_equal(col_ok, ref_ok)
    assert n_flagged >= 1
    assert sample_rectified_blocks(rect, left, 0, []) == []


@pytest.mark.parametrize("kernel", ["bspline", "keys"])
def test_refine_positions_is_refine_position_per_point(kernel: str) -> None:
    params = MeasureParams(subpixel_interpolation=kernel)
    rng = np.random.default_rng(1)
    templates, strips, starts, truth = [], [], [], []
    for k in range(60):
        d = float(rng.uniform(3, 9))
        left, right = shifted_pair(band_limited_texture(rng), 40, 8, d, float(rng.choice([0.5, 4.0, 30.0])), rng)
        left, right = left.astype(np.float32), right.astype(np.float32)
        if k % 10 == 0:  # textureless template: the fit fails or is too uncertain
            left[:] = 100.0
        width = int(rng.choice([28, 24]))
        templates.append(left[:, 20:28])
        strips.append(right[:, 20 - 14 : 20 - 14 + width])
        starts.append(14 - d + float(rng.normal(0, 0.3)))
        truth.append(14 - d)
    x, sigma, score, reasons = refine_positions(templates, strips, starts, params)
    counts = collections.Counter(reasons)
    assert counts[None] >= 30 and len(counts) >= 2  # accepted and refused points both exercised
    for j in range(len(templates)):
        rx, rs, rc, rr = refine_position(templates[j], strips[j], starts[j], params)
        assert reasons[j] == rr
        assert np.isnan(score[j]) == np.isnan(rc) and (np.isnan(rc) or abs(score[j] - rc) < 1e-9)
        if rr is None:
            assert abs(x[j] - rx) < 1e-9 and abs(sigma[j] - rs) < 1e-9
            assert abs(x[j] - truth[j]) < 0.2
        else:
            assert np.isnan(x[j]) and np.isnan(sigma[j])


def _assert_same(batch, single) -> None:  # type: ignore[no-untyped-def]
    for b, s in zip(batch, single, strict=True):
        assert b.reason == s.reason and b.ok == s.ok
        assert np.array_equal(b.uv_rect, s.uv_rect, equal_nan=True)
        assert np.isnan(b.score) == np.isnan(s.score) and (np.isnan(s.score) or abs(b.score - s.score) < 1e-9)
        if s.ok:
            assert abs(b.disparity_px - s.disparity_px) < 1e-9
            np.testing.assert_allclose(b.xyz_m, s.xyz_m, rtol=0, atol=1e-9)
            np.testing.assert_allclose(b.right_uv, s.right_uv, rtol=0, atol=1e-9)
            np.testing.assert_allclose(b.cov_m, s.cov_m, rtol=1e-9, atol=0)


def test_measure_points_batch_is_one_by_one_on_tsukuba(shared_data) -> None:  # type: ignore[no-untyped-def]
    left, right, gt = load_tsukuba()
    pts = tsukuba_grid(left, gt, step=12)
    # and points the checks refuse: black-free but flat, at the border, outside the image
    pts = np.vstack([pts, [[2.0, 2.0], [383.0, 100.0], [-3.0, 50.0], [200.5, 300.0]]])
    rig = identity_rig(left.shape[1], left.shape[0])
    params = MeasureParams(min_disparity_px=0, max_disparity_px=15)
    batch = measure_points(rig, left, right, pts, params)
    single = [measure_points(rig, left, right, p[None], params)[0] for p in pts]
    reasons = collections.Counter(m.reason for m in single)
    assert reasons[None] > 100 and len(reasons) >= 4, reasons
    _assert_same(batch, single)
    # per-point disparity ranges, and the checks switched off
    ranges = np.column_stack([np.zeros(len(pts)), np.linspace(6, 15, len(pts))])
    _assert_same(
        measure_points(rig, left, right, pts, params, ranges),
        [measure_points(rig, left, right, p[None], params, r)[0] for p, r in zip(pts, ranges)],
    )
    off = dataclasses.replace(params, context_width_px=0, edge_shift_px=0)
    _assert_same(measure_points(rig, left, right, pts, off), [measure_points(rig, left, right, p[None], off)[0] for p in pts])


def test_measure_points_batch_is_one_by_one_through_the_paper_rig(plane) -> None:  # type: ignore[no-untyped-def]
    rig, left, right, _ = plane
    W, H = rig.image_size
    gu, gv = np.meshgrid(np.arange(3, W, 23) + 0.37, np.arange(2, H, 29) + 0.61)
    pts = np.vstack([np.column_stack([gu.ravel(), gv.ravel()]), [[-1.0, 10.0], [W + 2.0, 5.0]]])
    params = MeasureParams()
    batch = measure_points(rig, left, right, pts, params)
    single = [measure_points(rig, left, right, p[None], params)[0] for p in pts]
    assert sum(m.ok for m in single) > 100
    _assert_same(batch, single)
