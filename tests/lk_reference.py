"""The numpy implementations of the Lucas-Kanade fits that
:mod:`trackmeter.core.lk_kernels` compiles: vectorised over the patches, readable, and the
reference ``tests/test_lk_kernels.py`` checks the compiled loops against. Kept as they were in
:mod:`trackmeter.core.patch_tracking` before the loops were compiled (2026-11-27), but for the
warp fits' precomputation, which both share (:func:`~trackmeter.core.patch_tracking.warp_steepest_descent`)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from trackmeter.core.patch_tracking import (
    AffineLKResult,
    CoordMap,
    F32,
    LKResult,
    Templates,
    _row_mean,
    _zncc_centred,
    sample_patches,
    sample_warped,
    warp_steepest_descent,
)


def _retire(converged: NDArray[np.bool_], active: NDArray[np.bool_], idx: NDArray, done: NDArray[np.bool_],
            bad: NDArray[np.bool_]) -> NDArray | None:
    """End the Gauss-Newton iterations of the rows ``idx`` that converged (``done`` and not
    ``bad``, marked in ``converged``) or failed (``bad``); returns the rows still iterating, or
    None when none stopped (the caller keeps its arrays unindexed then)."""
    stop = done | bad
    if not stop.any():
        return None
    converged[idx[done & ~bad]] = True
    active[idx[stop]] = False
    return idx[~stop]


def _gain_and_residual(I: NDArray, Tm: NDArray) -> tuple[NDArray, NDArray]:
    """Closed-form gain (k,) of the patches ``I`` (k,K) to the zero-mean templates ``Tm``
    (the least-squares fit of ``gain (I - mean I)``; the bias drops out with the means) and
    the residuals ``gain (I - mean I) - Tm`` (k,K)."""
    Im = I - _row_mean(I)
    cov = (Im * Tm).sum(1)
    ivar = (Im * Im).sum(1)
    with np.errstate(divide="ignore", invalid="ignore"):
        gain = np.where(ivar > 1e-9, cov / ivar, 0.0)
    return gain, Im * gain[:, None] - Tm


def refine_lk_reference(
    image: F32,
    templates: Templates,
    uv0: NDArray,
    *,
    coord_map: CoordMap | None = None,
    max_iterations: int = 10,
    tolerance_px: float = 5e-3,
    max_shift_px: float = 3.0,
    axis_mask: tuple[float, float] = (1.0, 1.0),
) -> LKResult:
    """``patch_tracking.refine_lk`` in numpy (see its docstring); ``coord_map`` as
    :func:`~trackmeter.core.patch_tracking.sample_points`'s."""
    n = templates.size
    p = np.asarray(uv0, dtype=np.float64).reshape(-1, 2).copy()
    p0 = p.copy()
    N = len(p)
    T = templates.values.reshape(N, -1).astype(np.float64)
    Tm = T - _row_mean(T)
    Tn = Tm / np.maximum(np.linalg.norm(Tm, axis=1, keepdims=True), 1e-9)
    # Template gradients (N, 2, n²): x and y rows side by side, so each Gauss-Newton product
    # below is one numpy call for both axes (the same element-wise arithmetic and sums).
    g = np.stack([templates.gx.reshape(N, -1), templates.gy.reshape(N, -1)], axis=1).astype(np.float64)
    active = templates.ok.copy()
    converged = np.zeros(N, bool)
    iters = np.zeros(N, np.int32)
    mask = np.asarray(axis_mask, dtype=np.float64)
    # multiplying by 1.0 changes no number: only a real mask is applied
    mask_col = None if np.all(mask == 1.0) else mask.reshape(1, 2, 1)
    # Rows still iterating: a slice while all are (no gathers), their indices once some stopped.
    idx = np.flatnonzero(active)
    rows: slice | NDArray = slice(None) if len(idx) == N else idx
    for _ in range(max_iterations):
        if len(idx) == 0:
            break
        big, inside = sample_patches(image if image.ndim == 2 else image[rows], p[rows], n + 4, coord_map)
        big = big.astype(np.float64)
        I = big[:, 2:-2, 2:-2].reshape(len(idx), -1)
        Tmi = Tm[rows]
        gain, err = _gain_and_residual(I, Tmi)
        # ESM (Benhimane & Malis 2004): the mean of the template's and the warped image's
        # gradients gives second-order convergence (plain IC converges slowly on fine texture).
        ix = (8.0 * (big[:, 2:-2, 3:-1] - big[:, 2:-2, 1:-3]) - (big[:, 2:-2, 4:] - big[:, 2:-2, :-4])) / 12.0
        iy = (8.0 * (big[:, 3:-1, 2:-2] - big[:, 1:-3, 2:-2]) - (big[:, 4:, 2:-2] - big[:, :-4, 2:-2])) / 12.0
        k = len(idx)
        J = 0.5 * (g[rows] + gain[:, None, None] * np.stack([ix.reshape(k, -1), iy.reshape(k, -1)], axis=1))
        if mask_col is not None:
            J = J * mask_col
        # Variable projection: the gain and bias are solved in closed form, so the Jacobian
        # must be orthogonal to what they explain (span{1, T}); otherwise a shift that looks
        # like a brightness change is counted twice and the steps fall short.
        Tni = Tn[rows][:, None, :]
        J = J - _row_mean(J)
        J = J - (J * Tni).sum(2, keepdims=True) * Tni
        Hm = (J[:, :, None, :] * J[:, None, :, :]).sum(3)  # (k, 2, 2) Gauss-Newton Hessian
        hxx, hyy, hxy = Hm[:, 0, 0], Hm[:, 1, 1], Hm[:, 0, 1]
        det = hxx * hyy - hxy * hxy
        bx, by = (J * err[:, None, :]).sum(2).T
        if mask[1] == 0.0:
            with np.errstate(divide="ignore", invalid="ignore"):
                dp = np.column_stack([np.where(hxx > 1e-9, bx / hxx, 0.0), np.zeros(len(idx))])
        else:
            with np.errstate(divide="ignore", invalid="ignore"):
                dp = np.column_stack([(hyy * bx - hxy * by) / det, (hxx * by - hxy * bx) / det])
            dp[~(det > 1e-12)] = 0.0
        pi = p[rows] - dp
        p[rows] = pi
        iters[rows] += 1
        step = np.abs(dp).max(1)
        bad = ~inside | (np.abs(pi - p0[rows]).max(1) > max_shift_px) | (gain <= 0)
        done = step < tolerance_px
        still = _retire(converged, active, idx, done, bad)
        if still is not None:
            idx = rows = still
    final, inside = sample_patches(image, p, n, coord_map)
    score = _zncc_centred(Tm, final)
    converged &= inside & templates.ok
    return LKResult(uv=p, score=score, converged=converged, iterations=iters)


def refine_lk_warp_reference(
    image: F32,
    templates: Templates,
    warp0: NDArray,
    model: str,
    max_iterations: int,
    tolerance_px: float,
    max_shift_px: float,
    hold_linear: NDArray[np.bool_] | None = None,
) -> AffineLKResult:
    """``patch_tracking._refine_lk_warp``'s iterations in numpy (see its docstring)."""
    n = templates.size
    N = len(templates.values)
    W = np.zeros((N, 3, 3))
    W[:, :2, :] = np.asarray(warp0, dtype=np.float64).reshape(N, 2, 3)
    W[:, 2, 2] = 1.0
    start = W[:, :2, 2].copy()
    Tm, SD, Hinv = warp_steepest_descent(templates, model, hold_linear)
    active = templates.ok.copy()
    converged = np.zeros(N, bool)
    r = (n - 1) / 2.0
    # The per-target arrays are indexed by the still-active rows only when some have stopped
    # (on a tracker step most targets take the same few iterations): numpy's per-call
    # overhead, not arithmetic, is what this loop costs for a handful of 8x8 patches.
    idx = np.flatnonzero(active)
    rows: slice | NDArray = slice(None) if len(idx) == N else idx
    for _ in range(max_iterations):
        if len(idx) == 0:
            break
        Wi = W[rows]
        patches, inside = sample_warped(image if image.ndim == 2 else image[rows], Wi[:, :2, :], n)
        I = patches.reshape(len(idx), -1).astype(np.float64)
        gain, err = _gain_and_residual(I, Tm[rows])
        dp = np.einsum("nij,nj->ni", Hinv[rows], np.einsum("nki,nk->ni", SD[rows], err))
        D = np.zeros((len(idx), 3, 3))
        D[:, 2, 2] = 1.0
        if model == "affine":
            D[:, 0, 0] = 1 + dp[:, 0]
            D[:, 1, 0] = dp[:, 1]
            D[:, 0, 1] = dp[:, 2]
            D[:, 1, 1] = 1 + dp[:, 3]
            lin_step = np.abs(dp[:, :4]).max(1)
        elif model == "similarity":
            D[:, 0, 0] = D[:, 1, 1] = 1 + dp[:, 0]
            D[:, 1, 0] = dp[:, 1]
            D[:, 0, 1] = -dp[:, 1]
            lin_step = np.hypot(dp[:, 0], dp[:, 1])
        elif model == "disparity_plane":  # x' = (1+p1) x + p2 y: the row's disparity slopes
            D[:, 0, 0] = 1 + dp[:, 0]
            D[:, 0, 1] = dp[:, 1]
            D[:, 1, 1] = 1.0
            lin_step = np.abs(dp[:, :2]).max(1)
        else:  # a rotation by dp0 (exact, so the scale of warp0 is kept)
            c, s_ = np.cos(dp[:, 0]), np.sin(dp[:, 0])
            D[:, 0, 0] = D[:, 1, 1] = c
            D[:, 1, 0] = s_
            D[:, 0, 1] = -s_
            lin_step = np.abs(dp[:, 0])
        D[:, 0, 2] = dp[:, -2]
        D[:, 1, 2] = dp[:, -1]
        Wi = Wi @ np.linalg.inv(D)
        W[rows] = Wi
        # Convergence: the largest displacement the step causes over the patch.
        step = np.abs(dp[:, -2:]).max(1) + r * lin_step
        lin = Wi[:, :2, :2]
        det = lin[:, 0, 0] * lin[:, 1, 1] - lin[:, 0, 1] * lin[:, 1, 0]
        moved = np.abs(Wi[:, :2, 2] - start[rows]).max(1)
        # det is NaN where the warp is not finite: (det > 0.5) & (det < 2.0) fails there too.
        bad = ~inside | (moved > max_shift_px) | ~((det >= 0.5) & (det <= 2.0)) | (gain <= 0) | ~np.isfinite(lin).all(axis=(1, 2))
        done = step < tolerance_px
        still = _retire(converged, active, idx, done, bad)
        if still is not None:
            idx = rows = still
    final, inside = sample_warped(image, W[:, :2, :], n)
    score = _zncc_centred(Tm, final)
    return AffineLKResult(warp=W[:, :2, :].copy(), score=score, converged=converged & inside & templates.ok)

