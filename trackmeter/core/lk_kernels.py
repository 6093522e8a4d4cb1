"""Compiled inner loops of the Lucas-Kanade fits in :mod:`trackmeter.core.patch_tracking`.

Why compiled: a tracker step fits a dozen or two 8x8 patches, a few Gauss-Newton iterations
each. Batched over the patches in numpy, each iteration is some forty numpy calls on arrays of
a few hundred numbers, so what the fits cost was numpy's per-call overhead, not arithmetic:
about a quarter of the tracking thread's time (``python -m benchmarks pipeline``,
2026-11-27). Here every patch runs its own loop, compiled by numba (``cache=True``: compiled
once per installation, about 3.5 s, then loaded from the cache in about 0.3 s;
:func:`~trackmeter.core.patch_tracking.warm_up` does either before a live pipeline starts).

The arithmetic is the numpy code's, element for element and in the same precision: sample
coordinates rounded to float32 (as :func:`~trackmeter.core.patch_tracking.bilinear` takes
them), interpolation weights in float64 on float32 intensities, the sampled values rounded to
float32, everything after in float64. Only the order of the sums differs (numpy sums pairwise,
these sequentially), so the results agree to 1e-9 px, not to the bit: ``tests/test_lk_kernels.py``
checks them against the numpy code, kept in ``tests/lk_reference.py``.

The functions take and return plain arrays; :mod:`~trackmeter.core.patch_tracking` wraps them
(templates, models, result types) and documents the maths.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numba
import numpy as np
from numpy.typing import NDArray

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
Bools = NDArray[np.bool_]
Image = NDArray[np.float32] | NDArray[np.uint8]  # (H,W), or (M,H,W) for the fits

# Warp models of :func:`lk_warp`, as :func:`trackmeter.core.patch_tracking._refine_lk_warp` names them.
MODEL_AFFINE = 0
MODEL_SIMILARITY = 1
MODEL_EUCLIDEAN = 2
MODEL_DISPARITY_PLANE = 3

_OPTIONS: dict[str, Any] = dict(nogil=True, fastmath=False, error_model="numpy")


def _jit_inline(function: Callable[..., Any]) -> Any:
    """``numba.njit`` inlined into its callers (a per-sample helper: a call returning a tuple
    cost the samplers a few percent of the tracking step)."""
    return numba.njit(inline="always", **_OPTIONS)(function)


def _jit(function: Callable[..., Any]) -> Any:
    """``numba.njit`` with its on-disk cache where one can be written (beside this file, else
    the user's cache folder); without one (a read-only install and home), compiled per process."""
    try:
        return numba.njit(cache=True, **_OPTIONS)(function)
    except RuntimeError:  # numba: "cannot cache function ...: no locator available"
        return numba.njit(**_OPTIONS)(function)


@_jit_inline
def _cell(h: int, w: int, xf: float, yf: float) -> tuple[int, int, float, float, bool]:
    """The bilinear cell of the float32 point (xf, yf) in an (h, w) grid: its top-left corner
    ``(x0, y0)``, the float64 offsets ``(fx, fy)`` from it, and whether the point lies inside
    ``[0, w-1] x [0, h-1]``; outside points are clamped to the border (as
    :func:`~trackmeter.core.patch_tracking.bilinear`, in its float32 arithmetic)."""
    inside = (xf >= 0) and (xf <= w - 1) and (yf >= 0) and (yf <= h - 1)
    xmax = np.float32(w - 1.001)
    ymax = np.float32(h - 1.001)
    # NaN coordinates (a diverged fit) sample the corner: numpy's clip would pass them through
    xc = xf if xf > 0 else np.float32(0.0)
    yc = yf if yf > 0 else np.float32(0.0)
    if xc > xmax:
        xc = xmax
    if yc > ymax:
        yc = ymax
    x0 = int(xc)
    y0 = int(yc)
    return x0, y0, np.float64(xc) - x0, np.float64(yc) - y0, inside


@_jit
def _sample(img: Image, x: float, y: float) -> tuple[float, bool]:
    """Bilinear value of ``img`` (H,W) float32 or uint8 at (x, y), and whether the point
    lies inside ``[0, W-1] x [0, H-1]``; outside points are clamped to the border (as
    :func:`~trackmeter.core.patch_tracking.bilinear`)."""
    h, w = img.shape
    x0, y0, fx, fy, inside = _cell(h, w, np.float32(x), np.float32(y))
    a = np.float64(img[y0, x0])
    b = np.float64(img[y0, x0 + 1])
    c = np.float64(img[y0 + 1, x0])
    d = np.float64(img[y0 + 1, x0 + 1])
    # float32 differences, as numpy subtracts the float32 quads before promoting
    top = a + fx * np.float64(np.float32(b) - np.float32(a))
    bottom = c + fx * np.float64(np.float32(d) - np.float32(c))
    return np.float64(np.float32(top + fy * (bottom - top))), inside


@_jit
def _sample_square(img: Image, px: float, py: float, out: F64) -> bool:
    """``out`` (s,s) = the square patch of ``img`` centred at (px, py), sampled as
    :func:`~trackmeter.core.patch_tracking.sample_patches` does (the centre rounded to float32,
    plus the float32 offsets ``k - (s-1)/2``); whether all samples lie inside."""
    side = out.shape[0]
    half = (side - 1) / 2.0
    cx = np.float32(px)
    cy = np.float32(py)
    inside = True
    for a in range(side):
        y = cy + np.float32(a - half)
        for b in range(side):
            v, ins = _sample(img, cx + np.float32(b - half), y)
            out[a, b] = v
            inside = inside and ins
    return inside


@_jit
def _centred_products(tm: F64, values: F64) -> tuple[float, float, float]:
    """``values`` (K,) minus its mean, in place; then ``(<tm, tm>, <v, v>, <tm, v>)`` with the
    zero-mean template ``tm`` (K,)."""
    k = values.shape[0]
    mean = 0.0
    for j in range(k):
        mean += values[j]
    mean /= k
    tt = 0.0
    vv = 0.0
    tv = 0.0
    for j in range(k):
        values[j] -= mean
        tt += tm[j] * tm[j]
        vv += values[j] * values[j]
        tv += tm[j] * values[j]
    return tt, vv, tv


@_jit
def _zncc_centred(tm: F64, values: F64) -> float:
    """ZNCC of a zero-mean template ``tm`` (K,) with ``values`` (K,) (centred in place)."""
    tt, vv, tv = _centred_products(tm, values)
    den = math.sqrt(tt * vv)
    return tv / den if den > 1e-9 else 0.0


@_jit
def _centre_and_gain(I: F64, tm: F64, err: F64) -> float:
    """``I`` (K,) minus its mean in place; the closed-form gain ``<I, tm> / <I, I>`` of the
    zero-mean patch to the zero-mean template (0 on a flat patch) and the residual
    ``err = gain I - tm`` written into ``err``."""
    _, ivar, cov = _centred_products(tm, I)
    gain = cov / ivar if ivar > 1e-9 else 0.0
    for j in range(I.shape[0]):
        err[j] = I[j] * gain - tm[j]
    return gain


@_jit
def lk_translation(
    image: Image, stacked: bool, values: F32, gx: F32, gy: F32, ok: Bools, uv0: F64, mask_x: float, mask_y: float,
    max_iterations: int, tolerance_px: float, max_shift_px: float,
) -> tuple[F64, F64, Bools, NDArray[np.int32]]:
    """Translation LK with closed-form gain and ESM steps, one loop per patch.

    ``image`` (M,H,W) float32 or uint8: patch ``i`` is sampled in ``image[i]`` when ``stacked``, else in
    ``image[0]``. ``values, gx, gy`` (N,n,n) float32 templates and their gradients, ``ok`` (N,),
    ``uv0`` (N,2) start centres. Returns ``(uv (N,2), score (N,), converged (N,), iterations
    (N,))`` as :func:`trackmeter.core.patch_tracking.refine_lk` documents them.
    """
    N, n, _ = values.shape
    K = n * n
    big_n = n + 4
    uv = uv0.copy()
    score = np.zeros(N)
    converged = np.zeros(N, np.bool_)
    iterations = np.zeros(N, np.int32)
    tm = np.empty(K)
    tn = np.empty(K)
    g0 = np.empty(K)
    g1 = np.empty(K)
    big = np.empty((big_n, big_n))
    I = np.empty(K)
    err = np.empty(K)
    jx = np.empty(K)
    jy = np.empty(K)
    final = np.empty((n, n))
    for i in range(N):
        img = image[i] if stacked else image[0]
        mean = 0.0
        for a in range(n):
            for b in range(n):
                mean += np.float64(values[i, a, b])
        mean /= K
        norm = 0.0
        for a in range(n):
            for b in range(n):
                j = a * n + b
                tm[j] = np.float64(values[i, a, b]) - mean
                norm += tm[j] * tm[j]
                g0[j] = np.float64(gx[i, a, b])
                g1[j] = np.float64(gy[i, a, b])
        norm = max(math.sqrt(norm), 1e-9)
        for j in range(K):
            tn[j] = tm[j] / norm
        px = uv0[i, 0]
        py = uv0[i, 1]
        if ok[i]:
            for _ in range(max_iterations):
                inside = _sample_square(img, px, py, big)
                for a in range(n):
                    for b in range(n):
                        I[a * n + b] = big[a + 2, b + 2]
                gain = _centre_and_gain(I, tm, err)
                # ESM Jacobian, then projected off span{1, T} (variable projection)
                mx = 0.0
                my = 0.0
                for a in range(n):
                    for b in range(n):
                        j = a * n + b
                        ix = (8.0 * (big[a + 2, b + 3] - big[a + 2, b + 1]) - (big[a + 2, b + 4] - big[a + 2, b])) / 12.0
                        iy = (8.0 * (big[a + 3, b + 2] - big[a + 1, b + 2]) - (big[a + 4, b + 2] - big[a, b + 2])) / 12.0
                        jx[j] = 0.5 * (g0[j] + gain * ix) * mask_x
                        jy[j] = 0.5 * (g1[j] + gain * iy) * mask_y
                        mx += jx[j]
                        my += jy[j]
                mx /= K
                my /= K
                dx = 0.0
                dy = 0.0
                for j in range(K):
                    jx[j] -= mx
                    jy[j] -= my
                    dx += jx[j] * tn[j]
                    dy += jy[j] * tn[j]
                hxx = 0.0
                hyy = 0.0
                hxy = 0.0
                bx = 0.0
                by = 0.0
                for j in range(K):
                    jx[j] -= dx * tn[j]
                    jy[j] -= dy * tn[j]
                    hxx += jx[j] * jx[j]
                    hyy += jy[j] * jy[j]
                    hxy += jx[j] * jy[j]
                    bx += jx[j] * err[j]
                    by += jy[j] * err[j]
                det = hxx * hyy - hxy * hxy
                if mask_y == 0.0:
                    stepx = bx / hxx if hxx > 1e-9 else 0.0
                    stepy = 0.0
                elif det > 1e-12:
                    stepx = (hyy * bx - hxy * by) / det
                    stepy = (hxx * by - hxy * bx) / det
                else:
                    stepx = 0.0
                    stepy = 0.0
                px -= stepx
                py -= stepy
                iterations[i] += 1
                step = max(abs(stepx), abs(stepy))
                bad = (not inside) or max(abs(px - uv0[i, 0]), abs(py - uv0[i, 1])) > max_shift_px or gain <= 0
                done = step < tolerance_px
                if done or bad:
                    converged[i] = done and not bad
                    break
        uv[i, 0] = px
        uv[i, 1] = py
        inside = _sample_square(img, px, py, final)
        score[i] = _zncc_centred(tm, final.reshape(K))
        converged[i] = converged[i] and inside and ok[i]
    return uv, score, converged, iterations


@_jit
def _sample_warped(img: Image, W: F64, ox: F64, oy: F64, out: F64) -> bool:
    """``out`` (K,) = ``img`` sampled at ``W[:2] @ (ox, oy, 1)`` (float64 coordinates rounded
    to float32 by :func:`_sample`); whether all samples lie inside."""
    inside = True
    for j in range(ox.shape[0]):
        x = W[0, 0] * ox[j] + W[0, 1] * oy[j] + W[0, 2]
        y = W[1, 0] * ox[j] + W[1, 1] * oy[j] + W[1, 2]
        v, ins = _sample(img, x, y)
        out[j] = v
        inside = inside and ins
    return inside


@_jit
def lk_warp(
    image: Image, stacked: bool, tm: F64, sd: F64, hinv: F64, ok: Bools, warp0: F64, ox: F64, oy: F64, model: int,
    max_iterations: int, tolerance_px: float, max_shift_px: float,
) -> tuple[F64, F64, Bools]:
    """The inverse-compositional warp fits' iterations, one loop per patch.

    ``tm`` (N,K) zero-mean templates, ``sd`` (N,K,P) their steepest-descent images projected
    off span{1, T}, ``hinv`` (N,P,P) the inverse (damped) Gauss-Newton Hessians, ``ok`` (N,),
    ``warp0`` (N,2,3) start warps, ``ox, oy`` (K,) the template's sample offsets from its centre,
    ``model`` one of the ``MODEL_*`` constants. Returns ``(warp (N,2,3), score (N,), converged
    (N,))`` as :func:`trackmeter.core.patch_tracking._refine_lk_warp` documents them.
    """
    N, K, P = sd.shape
    n = int(round(math.sqrt(K)))
    r = (n - 1) / 2.0
    warp = np.empty((N, 2, 3))
    score = np.zeros(N)
    converged = np.zeros(N, np.bool_)
    I = np.empty(K)
    err = np.empty(K)
    g = np.empty(P)
    dp = np.empty(P)
    W = np.empty((3, 3))
    for i in range(N):
        img = image[i] if stacked else image[0]
        for a in range(2):
            for b in range(3):
                W[a, b] = warp0[i, a, b]
        W[2, 0] = 0.0
        W[2, 1] = 0.0
        W[2, 2] = 1.0
        sx = W[0, 2]
        sy = W[1, 2]
        if ok[i]:
            for _ in range(max_iterations):
                inside = _sample_warped(img, W, ox, oy, I)
                gain = _centre_and_gain(I, tm[i], err)
                for p in range(P):
                    acc = 0.0
                    for j in range(K):
                        acc += sd[i, j, p] * err[j]
                    g[p] = acc
                for p in range(P):
                    acc = 0.0
                    for q in range(P):
                        acc += hinv[i, p, q] * g[q]
                    dp[p] = acc
                # The increment D (in the model's group) as its linear part and translation.
                if model == MODEL_AFFINE:
                    d00, d10, d01, d11 = 1.0 + dp[0], dp[1], dp[2], 1.0 + dp[3]
                    lin_step = max(max(abs(dp[0]), abs(dp[1])), max(abs(dp[2]), abs(dp[3])))
                elif model == MODEL_SIMILARITY:
                    d00 = d11 = 1.0 + dp[0]
                    d10 = dp[1]
                    d01 = -dp[1]
                    lin_step = math.hypot(dp[0], dp[1])
                elif model == MODEL_DISPARITY_PLANE:  # x' = (1+p1) x + p2 y
                    d00, d01, d10, d11 = 1.0 + dp[0], dp[1], 0.0, 1.0
                    lin_step = max(abs(dp[0]), abs(dp[1]))
                else:  # a rotation by dp0 (exact, so the scale of warp0 is kept)
                    c = math.cos(dp[0])
                    s = math.sin(dp[0])
                    d00, d01, d10, d11 = c, -s, s, c
                    lin_step = abs(dp[0])
                tx = dp[P - 2]
                ty = dp[P - 1]
                # W <- W D^-1, D^-1 = [[A^-1, -A^-1 t], [0, 1]]
                ddet = d00 * d11 - d01 * d10
                e00 = d11 / ddet
                e01 = -d01 / ddet
                e10 = -d10 / ddet
                e11 = d00 / ddet
                et0 = -(e00 * tx + e01 * ty)
                et1 = -(e10 * tx + e11 * ty)
                for a in range(2):
                    w0 = W[a, 0]
                    w1 = W[a, 1]
                    W[a, 0] = w0 * e00 + w1 * e10
                    W[a, 1] = w0 * e01 + w1 * e11
                    W[a, 2] = w0 * et0 + w1 * et1 + W[a, 2]
                step = max(abs(tx), abs(ty)) + r * lin_step
                det = W[0, 0] * W[1, 1] - W[0, 1] * W[1, 0]
                moved = max(abs(W[0, 2] - sx), abs(W[1, 2] - sy))
                finite = math.isfinite(W[0, 0]) and math.isfinite(W[0, 1]) and math.isfinite(W[1, 0]) and math.isfinite(W[1, 1])
                bad = (not inside) or moved > max_shift_px or not (det >= 0.5 and det <= 2.0) or gain <= 0 or not finite
                done = step < tolerance_px
                if done or bad:
                    converged[i] = done and not bad
                    break
        for a in range(2):
            for b in range(3):
                warp[i, a, b] = W[a, b]
        inside = _sample_warped(img, W, ox, oy, I)
        score[i] = _zncc_centred(tm[i], I)
        converged[i] = converged[i] and inside and ok[i]
    return warp, score, converged


# ---------------------------------------------------------------- point sampling
# :func:`trackmeter.core.patch_tracking.bilinear` and :func:`~trackmeter.core.patch_tracking.sample_points`
# run a dozen times per tracker step on a few hundred points each; in numpy that was some
# twenty-five calls of per-call overhead each (~60 us), about 5 % of the tracking thread. These
# loops are its arithmetic, element for element (:func:`_sample`), so the values are the same
# to the bit. Coordinates numpy would not sample the same way (NaN) and tables with a non-finite
# entry are left to the numpy code: the kernels then return False and the caller falls back.


@_jit
def sample_stack(image: NDArray, x: F32, y: F32, per_image: int, values: F32, inside: Bools) -> bool:
    """``values[i], inside[i]`` = :func:`_sample` of ``image[i // per_image]`` ((N,H,W), float32
    or uint8) at ``(x[i], y[i])`` (float32); False (outputs unspecified) on a NaN coordinate."""
    for i in range(x.shape[0]):
        xf = x[i]
        yf = y[i]
        if math.isnan(xf) or math.isnan(yf):
            return False
        v, ins = _sample(image[i // per_image], xf, yf)
        values[i] = v
        inside[i] = ins
    return True


@_jit
def _sample_table(table: NDArray, x: float, y: float) -> tuple[float, float, bool, bool]:
    """Bilinear value of a complex64 table (H,W) at (x, y) (float32): ``(real, imag, inside,
    finite)``, as ``bilinear`` computes it: the corner differences in complex64, then float64
    weights (numpy's ``float64 * complex`` multiplies by ``(w, 0)``, the same numbers for a
    finite table), rounded to float32 per part. ``finite``: the four corners are."""
    h, w = table.shape
    x0, y0, fx, fy, inside = _cell(h, w, x, y)
    a = table[y0, x0]
    b = table[y0, x0 + 1]
    c = table[y0 + 1, x0]
    d = table[y0 + 1, x0 + 1]
    finite = (math.isfinite(a.real) and math.isfinite(a.imag) and math.isfinite(b.real) and math.isfinite(b.imag)
              and math.isfinite(c.real) and math.isfinite(c.imag) and math.isfinite(d.real) and math.isfinite(d.imag))
    top_r = np.float64(a.real) + fx * np.float64(np.float32(b.real) - np.float32(a.real))
    top_i = np.float64(a.imag) + fx * np.float64(np.float32(b.imag) - np.float32(a.imag))
    bot_r = np.float64(c.real) + fx * np.float64(np.float32(d.real) - np.float32(c.real))
    bot_i = np.float64(c.imag) + fx * np.float64(np.float32(d.imag) - np.float32(c.imag))
    return (np.float64(np.float32(top_r + fy * (bot_r - top_r))), np.float64(np.float32(top_i + fy * (bot_i - top_i))),
            inside, finite)


@_jit
def sample_through_table(image: NDArray, table: NDArray, x: F32, y: F32, values: F32, inside: Bools) -> bool:
    """``values[i]`` = :func:`_sample` of ``image`` (H,W) at the point the complex64 ``table``
    (map_x + i map_y, (H',W')) gives for ``(x[i], y[i])`` (float32): numpy's
    ``bilinear(image, *bilinear(table, x, y))``; ``inside[i]`` both lookups' flags. False
    (outputs unspecified) on a NaN coordinate or a non-finite table entry."""
    for i in range(x.shape[0]):
        xf = x[i]
        yf = y[i]
        if math.isnan(xf) or math.isnan(yf):
            return False
        mx, my, ins_m, finite = _sample_table(table, xf, yf)
        if not finite:
            return False
        v, ins = _sample(image, np.float32(mx), np.float32(my))
        values[i] = v
        inside[i] = ins and ins_m
    return True
