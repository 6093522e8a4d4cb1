"""Sub-pixel 2D patch tracking, batched over targets (paper section 2.B).

Three pure steps, each vectorised across all targets of a frame:

1. :func:`sample_patches` — bilinear sampling of square patches centred at sub-pixel points,
   with exact float weights (``cv2.remap`` quantises its weights to 1/32 px, which would put a
   pixel-locking pattern of up to 0.016 px into every result), optionally through a coordinate
   map (the rectification maps, so patches can be taken in rectified images from the original
   ones without rectifying whole images).
2. :func:`zncc_search` — coarse integer search of the best zero-mean normalised
   cross-correlation (``cv2.matchTemplate``, ``TM_CCOEFF_NORMED``) in a window.
3. :func:`refine_lk` — inverse-compositional Lucas-Kanade on translation (Baker & Matthews,
   "Lucas-Kanade 20 years on", IJCV 2004, section 3.2) with the gain and bias of the image
   patch solved in closed form at every iteration (so the match is invariant to the affine
   brightness changes of a glinting surface, like ZNCC). The translation is found by
   Gauss-Newton on interpolated intensities, not by fitting a parabola to integer scores, so
   it carries no pixel-locking bias.

Template strategy (:func:`track_patches`): "template update with drift correction",
Matthews, Ishikawa & Baker, PAMI 2004 ("The template update problem", strategy 3). Each target
keeps its ANCHOR template (taken when it was created or last re-anchored) with the affine warp
that maps it into the current image, and its CURRENT template (the patch where it was found in
the previous frame). The window is searched with the current template (which looks most like
this frame); the position is then measured against the anchor by similarity LK (shift,
rotation, scale; the affine fit's shear and stretch are noise on 8x8 patches), so the error does
not accumulate and the rotation of a tumbling surface does not pull the patch centre off its
point. When the anchor no longer matches (a glint, a large change of view) the current
template's match is used, and once the rest of the step verified it (stereo match, gating,
rigid-body check) the anchor is replaced by it (a re-anchor). Measured against naive
every-frame template update in ``tests/test_patch_tracking.py`` and the ``tracker`` benchmark.

A similarity cannot follow FORESHORTENING (a turn out of the image plane compresses the patch
along one direction), so on an asymmetric texture its best fit moves the centre: on the
simulated estec runs the targets slid on the surface by a median 0.08 px within 2 deg of the
anchor's view and 0.24-0.33 px at 20-40 deg. A free affine fit follows it but is noisy on 8x8
patches. With ``anchor_warp="plane"`` a stereo tracker PREDICTS the linear part instead: the
target's surface plane from the rectified disparity slope (:func:`fit_disparity_plane`), the
body's rigid motion since the anchor, and the plane-induced homography's Jacobian
(:func:`plane_jacobian`); only the position is fitted (:func:`refine_lk_translation`).
Measured on estec (case b chain, 30 s): median slide 0.24 -> 0.17 px at 20-40 deg, 0.49 -> 0.12
px beyond 40 deg, tracked fraction 0.86 -> 0.91. What remains is not the warp: the anchor fitted
with the TRUE plane-induced warp slides as much (median 0.11 px after 40-200 frames, up to
1.4 px: the bump shading and the texture's mip level change with the view). It is opt-in: it
keeps targets longer, and on the tracker benchmark's estec frames some of them end more than
2 px from their first point (false locks 80 of ~3000 target-frames, 35 with ``body_check``,
against 0 with the similarity fit).

Pixels: (u, v) = (column, row), centre of the top-left pixel at (0, 0). A patch of side ``n``
centred at ``c`` samples ``c + k - (n-1)/2`` for ``k = 0..n-1`` (as ``cv2.getRectSubPix``).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Any, Callable, TypeAlias, cast, overload

import cv2
import numpy as np
from numpy.typing import NDArray

from trackmeter.core import lk_kernels
from trackmeter.core.matching import MeasureParams, refine_positions
from trackmeter.core.stereo import Rectification

FloatArray = NDArray[np.float64]
F32 = NDArray[np.float32]


def patch_offsets(size: int) -> F32:
    """Offsets (size,) of a patch's samples from its centre, px: ``k - (size-1)/2``."""
    return _patch_grid(size)[0].copy()


@lru_cache(maxsize=32)
def _patch_grid(size: int) -> tuple[F32, F32, F32, FloatArray, FloatArray]:
    """Per patch side, computed once (read-only): the offsets (size,) float32, the sample grid's
    x and y offsets (size,size) float32, and the same raveled (size²,) float64."""
    off = (np.arange(size, dtype=np.float32) - (size - 1) / 2.0).astype(np.float32)
    gx, gy = np.meshgrid(off, off)
    out = (off, gx, gy, gx.astype(np.float64).ravel(), gy.astype(np.float64).ravel())
    for a in out:
        a.flags.writeable = False
    return out


@overload
def bilinear(image: NDArray[np.complex64], x: NDArray, y: NDArray) -> tuple[NDArray[np.complex64], NDArray[np.bool_]]: ...


@overload
def bilinear(image: lk_kernels.Image, x: NDArray, y: NDArray) -> tuple[F32, NDArray[np.bool_]]: ...


def bilinear(image: NDArray, x: NDArray, y: NDArray) -> tuple[NDArray, NDArray[np.bool_]]:
    """Bilinear interpolation of a float32 (or uint8) image at sub-pixel points (any equal shapes).

    ``image`` is (H,W), or a stack (N,H,W) sampled with ``x, y`` of shape (N, ...) — point
    ``[i, ...]`` in image ``i``. Returns ``(values, inside)``; points outside
    ``[0, W-1] x [0, H-1]`` are clamped to the border and flagged ``inside = False``.
    """
    # Called a dozen times per tracker step on a few hundred points, so its cost is per-call
    # overhead: float32 and uint8 images are sampled by a compiled loop of the same arithmetic
    # (lk_kernels.sample_stack), anything else (a complex table, a NaN coordinate) by numpy.
    x = np.asarray(x, dtype=np.float32)
    y = np.asarray(y, dtype=np.float32)
    shape = x.shape
    if _compiled(image, x, y) and (image.ndim == 2 or (x.ndim and shape[0] == image.shape[0])):
        stack = image[None] if image.ndim == 2 else image
        values = np.empty(x.size, np.float32)
        flags = np.empty(x.size, np.bool_)
        per_image = x.size if image.ndim == 2 else x.size // max(shape[0], 1)
        if lk_kernels.sample_stack(stack, np.ascontiguousarray(x).reshape(-1), np.ascontiguousarray(y).reshape(-1),
                                   per_image, values, flags):
            return values.reshape(shape), flags.reshape(shape)
    return _bilinear_numpy(image, x, y)


_COMPILED_DTYPES = (np.dtype(np.float32), np.dtype(np.uint8))


def _compiled(image: NDArray, x: F32, y: F32) -> bool:
    """Whether the compiled samplers take ``image`` (float32 or uint8, (H,W) or (N,H,W), at
    least 2x2: a pixel's right and lower neighbours exist) at the float32 points ``x, y``
    (as many, at least one)."""
    return (image.dtype in _COMPILED_DTYPES and image.ndim in (2, 3) and image.shape[-1] >= 2 and image.shape[-2] >= 2
            and x.size > 0 and x.shape == y.shape)


def _bilinear_numpy(image: NDArray, x: F32, y: F32) -> tuple[NDArray, NDArray[np.bool_]]:
    """:func:`bilinear` in numpy, ``x, y`` float32: any image type (a complex64 table too).
    The four neighbours come from ONE gather of a (4, M) index array and the two horizontal
    interpolations run as one (2, M) operation (same arithmetic, same dtypes, so the same
    numbers as four gathers and three interpolations)."""
    h, w = image.shape[-2:]
    shape = x.shape
    inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    xc = np.minimum(np.maximum(x, 0), np.float32(w - 1.001)).reshape(-1)
    yc = np.minimum(np.maximum(y, 0), np.float32(h - 1.001)).reshape(-1)
    x0 = xc.astype(np.intp)  # floor: xc >= 0
    y0 = yc.astype(np.intp)
    # float32 - integer promotes to float64, exactly as the fractions always were
    fx = xc - x0
    fy = yc - y0
    i00 = y0 * w + x0
    if image.ndim == 3:
        i00 = (i00.reshape(shape) + (np.arange(image.shape[0], dtype=np.intp) * (h * w)).reshape((-1,) + (1,) * (x.ndim - 1))).reshape(-1)
    # uint8 images are gathered, then converted; a complex64 image (two channels, e.g. a pair
    # of remap tables as x + iy) keeps its type.
    out_t = np.complex64 if image.dtype == np.complex64 else np.float32
    quad = image.reshape(-1).take(i00 + _QUAD_OFFSETS[w]).astype(out_t, copy=False).reshape(2, 2, -1)
    lo = quad[:, 0]
    rows = lo + fx * (quad[:, 1] - lo)  # (2, M): the top and bottom rows at x
    top = rows[0]
    return (top + fy * (rows[1] - top)).astype(out_t, copy=False).reshape(shape), inside


class _QuadOffsets(dict):
    """Index offsets (4,1) of a pixel's right, lower and lower-right neighbours, per row width."""

    def __missing__(self, w: int) -> NDArray[np.intp]:
        off = np.array([0, 1, w, w + 1], dtype=np.intp).reshape(4, 1)
        self[w] = off
        return off


_QUAD_OFFSETS = _QuadOffsets()


CoordMap: TypeAlias = "tuple[F32, F32] | NDArray[np.complex64] | Callable[[NDArray, NDArray], tuple[NDArray, NDArray]]"


def sample_points(image: lk_kernels.Image, x: NDArray, y: NDArray, coord_map: CoordMap | None = None) -> tuple[F32, NDArray[np.bool_]]:
    """Sample ``image`` at points (x, y); with ``coord_map`` the points are first sent through it:
    a pair of remap tables ``(map_x, map_y)`` (e.g. ``Rectification.maps``, interpolated), the
    same as one complex table ``map_x + 1j map_y`` (:func:`complex_map`, one gather instead of
    two), or a function ``(x, y) -> (x', y')`` (e.g. :func:`rectified_to_original`, exact)."""
    if coord_map is None:
        return bilinear(image, x, y)
    if callable(coord_map):
        mx, my = coord_map(np.asarray(x), np.asarray(y))
        return bilinear(image, mx, my)
    if isinstance(coord_map, np.ndarray):  # complex table x + iy: one gather for both
        xs = np.asarray(x, dtype=np.float32)
        ys = np.asarray(y, dtype=np.float32)
        img = np.asarray(image)
        if (coord_map.dtype == np.complex64 and coord_map.ndim == 2 and min(coord_map.shape) >= 2 and img.ndim == 2
                and _compiled(img, xs, ys)):
            # Both lookups in one compiled loop (the same numbers as the two bilinear calls below).
            values = np.empty(xs.size, np.float32)
            flags = np.empty(xs.size, np.bool_)
            if lk_kernels.sample_through_table(img, coord_map, np.ascontiguousarray(xs).reshape(-1),
                                               np.ascontiguousarray(ys).reshape(-1), values, flags):
                return values.reshape(xs.shape), flags.reshape(xs.shape)
        mxy, inside_m = bilinear(coord_map, x, y)
        values, inside = bilinear(image, mxy.real, mxy.imag)
        return values, inside & inside_m
    mx, inside_m = bilinear(coord_map[0], x, y)
    my, _ = bilinear(coord_map[1], x, y)
    values, inside = bilinear(image, mx, my)
    return values, inside & inside_m


def complex_map(map_x: NDArray, map_y: NDArray) -> NDArray[np.complex64]:
    """One complex64 table ``map_x + 1j map_y`` from a pair of remap tables (see :func:`sample_points`)."""
    return (np.asarray(map_x, np.float32) + 1j * np.asarray(map_y, np.float32)).astype(np.complex64)


def rectified_to_original(rect: Rectification, side: int) -> Callable[[NDArray, NDArray], tuple[NDArray, NDArray]]:
    """A coordinate map: rectified pixels (any shape) → original pixels of the left (0) or right
    (1) image, exactly (``Rectification.unrectify_points``: one ``cv2.projectPoints`` call)."""

    def to_original(x: NDArray, y: NDArray) -> tuple[NDArray, NDArray]:
        shape = np.shape(x)
        uv = rect.unrectify_points(np.column_stack([np.ravel(x), np.ravel(y)]), side)
        return uv[:, 0].reshape(shape), uv[:, 1].reshape(shape)

    return to_original


def sample_patches(
    image: lk_kernels.Image, centres: NDArray, size: int, coord_map: CoordMap | None = None
) -> tuple[F32, NDArray[np.bool_]]:
    """Patches (N,size,size) centred at ``centres`` (N,2) px, and whether each lies fully inside."""
    c = np.asarray(centres, dtype=np.float32).reshape(-1, 2)
    _, gx, gy, _, _ = _patch_grid(size)
    x = c[:, 0, None, None] + gx
    y = c[:, 1, None, None] + gy
    values, inside = sample_points(image, x, y, coord_map)
    return values, cast("NDArray[np.bool_]", inside.reshape(len(c), size * size).all(axis=1))  # numpy's stubs: or a bool


@dataclass(frozen=True, eq=False)
class Templates:
    """Reference patches of N targets with what inverse-compositional LK precomputes.

    Attributes:
        values: (N,n,n) intensities.
        gx, gy: (N,n,n) central-difference gradients, per px.
        hessian_inv: (N,2,2) inverse Gauss-Newton Hessian of the zero-mean template.
        ok: (N,) the template lay inside the image and has texture (a regular Hessian).
    """

    values: F32
    gx: F32
    gy: F32
    hessian_inv: FloatArray
    ok: NDArray[np.bool_]

    @property
    def size(self) -> int:
        return int(self.values.shape[-1])

    def select(self, index: NDArray | slice) -> "Templates":
        return Templates(self.values[index], self.gx[index], self.gy[index], self.hessian_inv[index], self.ok[index])


def make_templates(image: lk_kernels.Image, centres: NDArray, size: int, coord_map: CoordMap | None = None) -> Templates:
    """Templates (side ``size``) at ``centres`` (N,2): a (size+4)² patch is sampled so the
    gradients are finite differences of real samples."""
    # Five-point derivative (-1, 8, 0, -8, 1)/12: the plain central difference under-estimates
    # the gradient of fine texture, which makes Gauss-Newton overshoot and converge slowly.
    big, inside = sample_patches(image, centres, size + 4, coord_map)
    values = np.ascontiguousarray(big[:, 2:-2, 2:-2])
    # float32: a Python float keeps an array's type (NEP 50), which numpy's stubs do not say.
    gx = cast(F32, (8.0 * (big[:, 2:-2, 3:-1] - big[:, 2:-2, 1:-3]) - (big[:, 2:-2, 4:] - big[:, 2:-2, :-4])) / 12.0)
    gy = cast(F32, (8.0 * (big[:, 3:-1, 2:-2] - big[:, 1:-3, 2:-2]) - (big[:, 4:, 2:-2] - big[:, :-4, 2:-2])) / 12.0)
    return Templates(values, gx, gy, *_hessian(gx, gy, inside))


def _hessian(gx: F32, gy: F32, inside: NDArray[np.bool_]) -> tuple[FloatArray, NDArray[np.bool_]]:
    # Gradients of a zero-mean template are the same as of the template; the gain/bias solved
    # in closed form leaves the geometric Hessian sum(grad grad^T).
    gxx = np.einsum("nij,nij->n", gx, gx, dtype=np.float64)
    gyy = np.einsum("nij,nij->n", gy, gy, dtype=np.float64)
    gxy = np.einsum("nij,nij->n", gx, gy, dtype=np.float64)
    det = gxx * gyy - gxy * gxy
    ok = inside & (det > 1e-6 * np.maximum(gxx + gyy, 1e-12) ** 2) & (gxx + gyy > 1e-6)
    with np.errstate(divide="ignore", invalid="ignore"):
        hinv = np.stack([np.stack([gyy, -gxy], -1), np.stack([-gxy, gxx], -1)], -2) / det[:, None, None]
    hinv[~ok] = 0.0
    return hinv, ok


def _project_out(J: FloatArray, t_unit: FloatArray) -> FloatArray:
    """Columns of J (N,K[,P]) minus their mean and their component along the unit, zero-mean
    template ``t_unit`` (N,K): the part a gain/bias change cannot explain."""
    if J.ndim == 2:
        J = J - J.mean(1, keepdims=True)
        return J - (J * t_unit).sum(1, keepdims=True) * t_unit
    J = J - J.mean(1, keepdims=True)
    return J - np.einsum("nkp,nk->np", J, t_unit)[:, None, :] * t_unit[:, :, None]


def zncc(a: F32 | FloatArray, b: F32) -> FloatArray:
    """Zero-mean normalised cross-correlation (N,) of two stacks of patches (N,n,n), in [-1, 1]."""
    a = a.reshape(len(a), -1).astype(np.float64)
    return _zncc_centred(a - _row_mean(a), b)


def _row_mean(x: FloatArray) -> FloatArray:
    """``x.mean(axis=-1, keepdims=True)`` without np.mean's per-call overhead: numpy's mean is
    this sum divided by the count, so the numbers are the same."""
    return x.sum(axis=-1, keepdims=True) / x.shape[-1]


def _zncc_centred(a: FloatArray, b: F32 | FloatArray) -> FloatArray:
    """:func:`zncc` with ``a`` (N,K) float64 already zero-mean (e.g. an LK fit's templates)."""
    b = b.reshape(len(b), -1).astype(np.float64)
    b = b - _row_mean(b)
    den = np.sqrt((a * a).sum(1) * (b * b).sum(1))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 1e-9, (a * b).sum(1) / den, 0.0)


@dataclass(frozen=True, eq=False)
class LKResult:
    """Result of :func:`refine_lk` for N patches.

    Attributes:
        uv: (N,2) refined centres, px (in the sampled image's coordinates).
        score: (N,) ZNCC between the template and the image patch at ``uv``.
        converged: (N,) the last step was below the tolerance and the patch stayed inside.
        iterations: (N,) Gauss-Newton iterations used.
    """

    uv: FloatArray
    score: FloatArray
    converged: NDArray[np.bool_]
    iterations: NDArray[np.int32]


def _image_stack(image: NDArray) -> NDArray:
    """``image`` (H,W) or (N,H,W) as a contiguous stack (1 or N, H, W) for the compiled fits:
    uint8 (a camera frame, sampled as it is: converting a whole frame per call cost more than
    the fit) or float32 (anything else is converted)."""
    image = np.asarray(image)
    image = np.ascontiguousarray(image) if image.dtype == np.uint8 else _f32(image)
    return image[None] if image.ndim == 2 else image


def _f32(a: NDArray) -> F32:
    """``a`` as a C-contiguous float32 array (a copy only where it is not one): the compiled
    fits are specialised for that layout."""
    return np.ascontiguousarray(a, dtype=np.float32)


_LK_MODELS = {
    "affine": lk_kernels.MODEL_AFFINE,
    "similarity": lk_kernels.MODEL_SIMILARITY,
    "euclidean": lk_kernels.MODEL_EUCLIDEAN,
    "disparity_plane": lk_kernels.MODEL_DISPARITY_PLANE,
}


def refine_lk(
    image: lk_kernels.Image,
    templates: Templates,
    uv0: NDArray,
    *,
    max_iterations: int = 10,
    tolerance_px: float = 5e-3,
    max_shift_px: float = 3.0,
    axis_mask: tuple[float, float] = (1.0, 1.0),
) -> LKResult:
    """Lucas-Kanade on translation with closed-form gain and bias, ESM steps.

    Minimises ``sum_x [ a (I(x + p) - mean I) - (T(x) - mean T) ]²`` over the translation
    ``p``: at each iteration the patch ``I(x + p)`` is sampled (bilinear, exact weights), the
    gain ``a`` is its least-squares fit to ``T`` (the bias drops out with the means), and the
    Gauss-Newton step uses the ESM Jacobian ``J = (grad T + a grad I(x + p)) / 2``
    (Benhimane & Malis, IROS 2004; Baker & Matthews 2004 for the IC family):
    ``p <- p - (J^T J)^-1 J^T (I' - T)``. The Jacobian is projected off span{1, T} (variable
    projection: the gain and bias are solved in closed form, so a shift that looks like a
    brightness change must not be counted twice). Each patch iterates until its step is below
    ``tolerance_px`` or it fails (left the image, moved past ``max_shift_px``, gain <= 0). The
    loop is compiled (:func:`trackmeter.core.lk_kernels.lk_translation`).

    Args:
        image: float32 or uint8 image (H,W) the patches are sampled from, or a stack (N,H,W) of one
            small image per patch (e.g. rectified strips).
        templates: N templates.
        uv0: (N,2) start centres, px.
        max_shift_px: a patch that moves farther than this from ``uv0`` did not converge.
        axis_mask: (1, 0) to move along u only (e.g. along a rectified epipolar line).
    """
    uv, score, converged, iterations = lk_kernels.lk_translation(
        _image_stack(image), image.ndim == 3, _f32(templates.values), _f32(templates.gx), _f32(templates.gy), np.asarray(templates.ok, dtype=bool),
        np.ascontiguousarray(np.asarray(uv0, dtype=np.float64).reshape(-1, 2)), float(axis_mask[0]), float(axis_mask[1]),
        int(max_iterations), float(tolerance_px), float(max_shift_px),
    )
    return LKResult(uv=uv, score=score, converged=converged, iterations=iterations)


_KERNEL_3X3 = np.ones((3, 3), np.uint8)


def grid_patch(image: NDArray, uv: NDArray, size: int) -> tuple[F32, FloatArray] | None:
    """The ``size`` x ``size`` window of ``image``'s own pixels whose centre is nearest ``uv``
    (2,) px, and ``uv`` minus that centre (2,), each within half a pixel; None when the window
    is not inside the image.

    The integer search (:func:`zncc_search`) compares windows of the image's pixels: a template
    resampled at a sub-pixel point is compared half a pixel off and blurred by the resampling
    (an 8x8 template made at a whole pixel, compared against the same image, scored 0.67 on a
    sharp texture), where a window of pixels scores 1 at its own place. Adding the offset to the
    search's result puts the point back where the template was made.
    """
    half = (size - 1) / 2.0
    x0 = math.floor(float(uv[0]) - half + 0.5)
    y0 = math.floor(float(uv[1]) - half + 0.5)
    h, w = image.shape[:2]
    if x0 < 0 or y0 < 0 or x0 + size > w or y0 + size > h:
        return None
    window = np.asarray(image[y0 : y0 + size, x0 : x0 + size], dtype=np.float32)
    return window, np.array([float(uv[0]) - (x0 + half), float(uv[1]) - (y0 + half)])


def zncc_search(
    image: lk_kernels.Image, template: F32, centre: NDArray, half_size: NDArray
) -> tuple[FloatArray, float, float] | None:
    """Best integer ZNCC position of ``template`` (n,n) in a window around ``centre`` (2,).

    The window covers centres ``centre ± half_size`` (2,) px, clipped to the image. Returns
    ``(uv (2,), best score, best score of the other local maxima)``
    or None when the window is smaller than the template. The returned centre is the centre of
    the best window of whole pixels (a half-pixel grid for an even ``n``): a template cut on the
    pixel grid (:func:`grid_patch`) gets its own point back by adding its offset.
    """
    n = template.shape[0]
    h, w = image.shape
    half = (n - 1) / 2.0
    # Python floats and math.floor/ceil: the same integers as numpy's, without numpy's per-call cost
    cu, cv = float(centre[0]), float(centre[1])
    hu, hv = float(half_size[0]), float(half_size[1])
    x0 = max(math.floor(cu - hu - half), 0)
    x1 = min(math.ceil(cu + hu + half) + 1, w)
    y0 = max(math.floor(cv - hv - half), 0)
    y1 = min(math.ceil(cv + hv + half) + 1, h)
    if x1 - x0 < n or y1 - y0 < n:
        return None
    roi = np.asarray(image[y0:y1, x0:x1], dtype=np.float32)
    res = cv2.matchTemplate(roi, np.asarray(template, dtype=np.float32), cv2.TM_CCOEFF_NORMED)
    _, best, _, loc = cv2.minMaxLoc(res)
    j, i = loc
    # Second peak: the best other LOCAL MAXIMUM of the score (a broad main peak's flanks do not
    # count) farther than half a patch from the best (noise ripples on the main peak do not).
    r = max(n // 2, 2)
    peaks = res >= cv2.dilate(res, _KERNEL_3X3)
    peaks[max(i - r, 0) : i + r + 1, max(j - r, 0) : j + r + 1] = False
    # -1 (a flat window's score) is the floor: a maximum at or below it does not count. The
    # masked maximum by cv2.minMaxLoc (the score holds no NaN: OpenCV's normed scores are finite)
    # is np.max(res, where=peaks, initial=-1.0) at a fraction of its per-call cost.
    second = max(cv2.minMaxLoc(res, peaks.view(np.uint8))[1], -1.0) if peaks.any() else -1.0
    uv = np.array([x0 + j + half, y0 + i + half])
    return uv, float(best), second


@dataclass(frozen=True, eq=False)
class PatchTrack:
    """Result of :func:`track_patches` for N targets.

    Attributes:
        uv: (N,2) sub-pixel positions, px.
        score: (N,) ZNCC of the accepted match.
        converged: (N,) a match was found (anchor or current template).
        anchored: (N,) the position came from the anchor template (drift corrected).
        anchor_lin: (N,2,2) linear part of the anchor → image affine warp (identity where not
            anchored).
    """

    uv: FloatArray
    score: FloatArray
    converged: NDArray[np.bool_]
    anchored: NDArray[np.bool_]
    anchor_lin: FloatArray


def track_patches(
    image: lk_kernels.Image,
    anchor: Templates,
    anchor_lin: NDArray,
    current: Templates,
    uv0: NDArray,
    *,
    anchor_min_score: float,
    drift_tolerance_px: float,
    anchor_warp: str = "similarity",
    anchor_tolerance_px: float = 0.02,
    expected_scale: NDArray | None = None,
    max_scale_error: float = np.inf,
    predicted_lin: NDArray | None = None,
    raw_image: lk_kernels.Image | None = None,
    raw_anchor: Templates | None = None,
    raw_current: Templates | None = None,
    raw_tolerance_px: float = np.inf,
    scale_fallback: bool | NDArray[np.bool_] = False,
) -> PatchTrack:
    """Sub-pixel positions of N targets near ``uv0`` (N,2) (e.g. integer ZNCC search results).

    Template update with drift correction (Matthews, Ishikawa & Baker, PAMI 2004, strategy 3),
    arranged so the common case costs one refinement: each target is first aligned with its
    ANCHOR template by the ``anchor_warp`` LK fit (:func:`refine_lk_similarity` by default,
    or ``"euclidean"``/``"affine"``; started from last frame's linear warp ``anchor_lin``
    (N,2,2) and this frame's search result; ``anchor_tolerance_px`` is its convergence step).
    When the anchor converges within ``1 + drift_tolerance_px`` of the search result with ZNCC
    >= ``anchor_min_score``, and the fit's scale is within ``max_scale_error`` (a fraction) of
    ``expected_scale`` (N,) (a stereo tracker's depth ratio ``z_anchor / z``; 1 when None),
    its position is taken: every frame is measured against the same reference, so errors do
    not accumulate (no drift), and the affine warp follows rotation and foreshortening. Where
    the anchor no longer fits (appearance changed: a glint, a large turn), the CURRENT template
    (last frame's patch) is refined by translation LK (:func:`refine_lk`) instead; the caller
    re-anchors on that match once the rest of the step verified it.

    ``raw_image`` (with ``raw_anchor`` and ``raw_current``, the same templates taken from it):
    ``image`` is a smoothed copy of it (:class:`~trackmeter.core.tracking.TrackerParams`
    ``track_blur_sigma_px``), and every fit is refined once more on the image itself, the
    anchor's by translation with the smoothed fit's linear part held
    (:func:`refine_lk_translation`), the current template's by :func:`refine_lk`. The result
    is that refinement's position and ZNCC; where it does not converge or lands farther than
    ``raw_tolerance_px`` from the smoothed fit, the fit is taken as failed (an anchor: not
    anchored; the current template: not converged). Smoothing steadies the similarity fit's
    scale on 8x8 patches, but a broad bright structure (a glint) weighs more in a smoothed
    patch than in the image's fine texture and can pull the fit along; the refinement on the
    image itself is held by that texture, as an unsmoothed tracker is.

    ``scale_fallback`` (bool, or (N,) bool per row; rows fitted by the similarity warp whose
    ``expected_scale`` is known): an anchor fit refused (not converged, or its scale off
    ``expected_scale``) is fitted again with the scale held at the expected one
    (:func:`refine_lk_euclidean`), and that fit counts as any anchor fit does: taken where it
    scores ``anchor_min_score`` within the distance from the search result, and otherwise,
    converged, it may confirm the current template's match (the re-anchor above, within
    ``drift_tolerance_px``). An 8x8 patch holds its scale loosely, and the free scale is what
    most often fails a fit one to three frames after its anchor was made, on sharp texture;
    the operator's targets are then lost at once.

    ``anchor_warp="plane"``: where ``predicted_lin`` (N,2,2) is finite (the anchor → image
    linear map PREDICTED from the body's motion and the surface plane, :func:`plane_jacobian`),
    the anchor's linear part is held at it and only the position is fitted
    (:func:`refine_lk_translation`); a similarity fit cannot follow foreshortening, so on an
    asymmetric texture its centre slides, and a free affine fit is too noisy on 8x8 patches.
    Rows without a prediction (NaN) use the similarity fit. (Starting the similarity fit
    from the prediction instead, its rotation and scale corrected, slid more: on the estec
    case-b run, 30 s, 0.135 against 0.126 px median at 20-40 deg since the anchor, and lost
    more targets.)
    """
    N = len(uv0)
    uv0 = np.asarray(uv0, dtype=np.float64).reshape(N, 2)
    lin = np.asarray(anchor_lin, dtype=np.float64).reshape(N, 2, 2)
    expect = np.ones(N) if expected_scale is None else np.asarray(expected_scale, dtype=np.float64).reshape(N)
    scale_known = np.isfinite(expect) & (expect > 0) & (expected_scale is not None)
    expect = np.where(scale_known, expect, 1.0)
    if expected_scale is not None and anchor_warp == "euclidean":
        # The fit keeps the start's scale: start from the depth-implied one.
        lin = _with_scale(lin, expect)
    if anchor_warp not in _ANCHOR_FITS and anchor_warp not in _PLANE_FITS:
        raise ValueError(f"anchor_warp must be one of {sorted(_ANCHOR_FITS) + sorted(_PLANE_FITS)}, not {anchor_warp!r}")
    fits = np.full(N, anchor_warp, dtype=object)
    if anchor_warp in _PLANE_FITS:
        known = np.zeros(N, bool)
        if predicted_lin is not None:
            pred = np.asarray(predicted_lin, dtype=np.float64).reshape(N, 2, 2)
            known = np.all(np.isfinite(pred), axis=(1, 2))
            lin = np.where(known[:, None, None], pred, lin)
        fits = np.where(known, _PLANE_FITS[anchor_warp], "similarity")
    W0 = np.concatenate([lin, uv0[:, :, None]], axis=2)
    la = _fit_anchors(image, anchor, W0, fits, anchor_tolerance_px)
    # A fit whose scale disagrees with the one the target's depth change implies has slid along
    # a texture that does not move with the centre point (a depth edge, a glint): it is not a
    # match, neither for the position nor to confirm a re-anchor.
    scale = np.sqrt(np.abs(np.linalg.det(la.warp[:, :, :2])))
    fit_ok = la.converged & (np.abs(scale / expect - 1.0) <= max_scale_error)
    # Only where a similarity fit ran (plane mode: the rows without a prediction) and the depth
    # gives the scale to hold.
    refit = ~fit_ok & np.broadcast_to(np.asarray(scale_fallback, dtype=bool), (N,)) & (fits == "similarity") & scale_known
    if refit.any():
        la, held = _scale_held_refit(image, anchor, W0, la, refit, expect, anchor_tolerance_px)
        fit_ok = fit_ok | held
    moved = np.abs(la.uv - uv0).max(1)
    anchored = fit_ok & (la.score >= anchor_min_score) & (moved <= 1.0 + drift_tolerance_px)
    a_uv, a_score = la.uv.copy(), la.score.copy()
    if raw_image is not None and raw_anchor is not None and anchored.any():
        rows = np.flatnonzero(anchored)
        lf = refine_lk_translation(raw_image, raw_anchor.select(rows), la.warp[rows], max_iterations=8,
                                   tolerance_px=anchor_tolerance_px, max_shift_px=2.0)
        ok = lf.converged & (np.abs(lf.uv - la.uv[rows]).max(1) <= raw_tolerance_px)
        a_uv[rows[ok]] = lf.uv[ok]
        a_score[rows[ok]] = lf.score[ok]
        anchored[rows[~ok]] = False
    uv = np.where(anchored[:, None], a_uv, np.nan)
    score = np.where(anchored, a_score, np.nan)
    converged = anchored.copy()
    out_lin = np.where(anchored[:, None, None], la.warp[:, :, :2], np.eye(2))
    rest = np.flatnonzero(~anchored)
    if len(rest):
        lc = refine_lk(image, current.select(rest), uv0[rest], max_iterations=8, tolerance_px=0.01)
        if raw_image is not None and raw_current is not None:
            lr = refine_lk(raw_image, raw_current.select(rest), lc.uv, max_iterations=8, tolerance_px=0.01)
            near = np.abs(lr.uv - lc.uv).max(1) <= raw_tolerance_px
            lc = LKResult(np.where(near[:, None], lr.uv, lc.uv), np.where(near, lr.score, lc.score),
                          lc.converged & lr.converged & near, lc.iterations)
        uv[rest] = lc.uv
        score[rest] = lc.score
        # A re-anchor is only safe where the anchor still converged to the same spot (its score
        # merely dropped with the appearance); where the two disagree the target is not
        # trusted: following the current template alone is how template trackers drift away.
        agree = fit_ok[rest] & (np.abs(la.uv[rest] - lc.uv).max(1) <= drift_tolerance_px)
        converged[rest] = lc.converged & agree
    return PatchTrack(uv=uv, score=score, converged=converged, anchored=anchored, anchor_lin=out_lin)


@dataclass(frozen=True, eq=False)
class EpipolarMatch:
    """Right-image matches of N left points along their rectified epipolar lines.

    Attributes:
        uv_rect_left: (N,2) left points in the rectified left image, px.
        uv_rect_right: (N,2) sub-pixel matches in the rectified right image, px.
        disparity_px: (N,) ``u_rect_left - u_rect_right``, px.
        score: (N,) ZNCC of the refined match.
        second_score: (N,) best ZNCC along the searched line outside the chosen peak (ambiguity).
        epipolar_residual_px: (N,) vertical offset of the 2D-refined match from the left row, px.
        reason: (N,) None when accepted, else why not (one line).
    """

    uv_rect_left: FloatArray
    uv_rect_right: FloatArray
    disparity_px: FloatArray
    score: FloatArray
    second_score: FloatArray
    epipolar_residual_px: FloatArray
    reason: list[str | None]

    @property
    def ok(self) -> NDArray[np.bool_]:
        return np.array([r is None for r in self.reason], dtype=bool)


def match_epipolar(
    left: lk_kernels.Image,
    right: lk_kernels.Image,
    left_map: CoordMap,
    right_map: CoordMap,
    uv_rect_left: NDArray,
    disparity_low_px: NDArray,
    span_px: int | NDArray,
    size: int,
    *,
    min_score: float,
    uniqueness_margin: float,
    epipolar_tolerance_px: float,
    row_fit: MeasureParams | None = None,
    whole_disparity: bool = False,
) -> EpipolarMatch:
    """Match left patches along the rectified right rows, batched over N points.

    The left patch is sampled in the RECTIFIED left image at ``uv_rect_left`` (through the
    rectification map, so only the patch is rectified), and compared by ZNCC with the
    rectified right row at every integer disparity ``d_low .. d_low + span``. The best peak
    must score ``min_score`` and beat every other peak of the line (outside ±size/2 of it) by
    ``uniqueness_margin`` (else the point is ambiguous along its epipolar line). It is then
    refined by 2D inverse-compositional LK (:func:`refine_lk`); a refined match that leaves the
    row by more than ``epipolar_tolerance_px`` fails the epipolar consistency check.

    ``row_fit`` (the sub-pixel settings of :func:`trackmeter.core.matching.refine_positions`):
    the disparity is then that fit's, the shift along the row with gain and offset on a
    B-spline that ``trackmeter measure`` makes, started at the 2D fit; the 2D fit still makes
    the epipolar check, the score and the vertical coordinate. On a rectified pair the match
    lies on the row, and the 2D fit's vertical freedom leaks into the disparity where the
    texture is oblique: 148 points tracked on estec (two noise seeds, five frames) against the
    renderer's truth, median absolute disparity error 0.188 px with the 2D fit, 0.146 px with
    the row fit (``measure``'s own 0.149). Where the row fit fails the 2D fit's disparity stands.

    ``whole_disparity``: the searched range starts at a whole disparity (``disparity_low_px``
    rounded down, the span widened to keep its top), so the right strip samples the image at a
    sub-pixel phase set by the left point alone, not by the last disparity: on the sharp
    Tsukuba pair, resampled at another phase, the same match moved by up to 0.1 px from frame
    to frame.

    Args:
        left, right: the ORIGINAL images, uint8 or float32 (sampled alike).
        left_map, right_map: rectified → original coordinate maps (see :func:`sample_points`).
        uv_rect_left: (N,2) rectified left pixels.
        disparity_low_px: (N,) smallest disparity searched, px.
        span_px: number of disparities searched above it: one for all points, or (N,) one per
            point (e.g. a wider search for re-found targets batched with tracked ones).
        size: patch side, px.
    """
    cl = np.asarray(uv_rect_left, dtype=np.float64).reshape(-1, 2)
    N = len(cl)
    d_low = np.asarray(disparity_low_px, dtype=np.float64).reshape(-1)
    spans = np.broadcast_to(np.asarray(span_px, dtype=np.int64), (N,))
    if whole_disparity:
        asked, d_low = d_low, np.floor(d_low)
        spans = spans + (d_low < asked)
    span = int(spans.max()) if N else 0
    d_high = d_low + spans
    templates = make_templates(left, cl, size, left_map)
    half = (size - 1) / 2.0
    width = span + size
    margin = 4  # rows above and below the patch: room for the 2D refinement's gradients and vertical check
    x_first = cl[:, 0] - d_high - half
    xs = x_first[:, None] + np.arange(width)[None, :]
    ys = cl[:, 1, None] + patch_offsets(size + 2 * margin).astype(np.float64)[None, :]
    X = np.broadcast_to(xs[:, None, :], (N, size + 2 * margin, width))
    Y = np.broadcast_to(ys[:, :, None], (N, size + 2 * margin, width))
    # The rectified right strip around each epipolar line: the only right pixels rectified.
    strip, inside = sample_points(right, X, Y, right_map)
    core = strip[:, margin:-margin, :].astype(np.float64)
    inside = inside[:, margin:-margin, :]
    # ZNCC of the template with every window of the strip, all at once.
    # window k of point i is core[i, :, k : k + size] (a strided view, copied once by reshape)
    s0, s1, s2 = core.strides
    win = np.lib.stride_tricks.as_strided(core, (N, span + 1, size, size), (s0, s2, s1, s2), writeable=False)
    win = win.reshape(N, span + 1, size * size)
    t = templates.values.reshape(N, -1).astype(np.float64)
    t = t - t.mean(1, keepdims=True)
    wm = win - win.mean(2, keepdims=True)
    num = np.einsum("nkp,np->nk", wm, t)
    den = np.sqrt(np.einsum("nkp,nkp->nk", wm, wm) * (t * t).sum(1)[:, None])
    with np.errstate(divide="ignore", invalid="ignore"):
        scores = np.where(den > 1e-9, num / den, -1.0)
    # a window is valid when all its columns lie inside (running count of inside columns)
    col_in = np.zeros((N, width + 1), np.int32)
    np.cumsum(inside.all(axis=1), axis=1, out=col_in[:, 1:])
    valid_col = (col_in[:, size:] - col_in[:, :-size]) == size
    # Column k is disparity d_high - k: past a point's own span it is below its d_low.
    valid_col &= np.arange(span + 1)[None, :] <= spans[:, None]
    scores = np.where(valid_col, scores, -1.0)
    k_best = scores.argmax(1)
    best = scores[np.arange(N), k_best]
    r = max(size // 2, 2)
    kk = np.arange(span + 1)[None, :]
    far = np.abs(kk - k_best[:, None]) > r
    second = np.where(far, scores, -1.0).max(1) if span + 1 > 1 else np.full(N, -1.0)
    # Sub-pixel: 2D IC-LK inside the strips (strip pixel (j, r) is the rectified pixel
    # (x_first + j, v - half - margin + r), so bilinear sampling of the strip is bilinear
    # sampling of the rectified image).
    start = np.column_stack([k_best + half, np.full(N, margin + half)])
    lk = refine_lk(np.ascontiguousarray(strip), templates, start, max_shift_px=float(margin) / 2 - 0.01)
    u_right = x_first + lk.uv[:, 0]
    v_right = cl[:, 1] + (lk.uv[:, 1] - margin - half)
    if row_fit is not None and N:
        x_row, _, _, _ = refine_positions(list(templates.values), list(strip[:, margin:-margin, :]),
                                          np.clip(lk.uv[:, 0] - half, 0.0, width - size), _any_fit(row_fit))
        u_right = np.where(np.isfinite(x_row), x_first + x_row + half, u_right)
    disparity = cl[:, 0] - u_right
    resid = v_right - cl[:, 1]
    lk = LKResult(uv=np.column_stack([u_right, v_right]), score=lk.score, converged=lk.converged, iterations=lk.iterations)
    # The checks in order, vectorised: the first failing one names the reason (the loop below
    # only runs for failures, with Python scalars: numpy scalar access per point is slow).
    edge = (k_best == 0) | (k_best == spans)
    failed = (
        ~templates.ok
        | (best < min_score)
        | (second > best - uniqueness_margin)
        | (edge & (spans > 0))
        | ~lk.converged
        | (np.abs(resid) > epipolar_tolerance_px)
        | (lk.score < min_score)
    )
    reasons: list[str | None] = [None] * N
    for i in np.flatnonzero(failed).tolist():
        reasons[i] = _epipolar_reason(
            bool(templates.ok[i]), float(best[i]), float(second[i]), int(k_best[i]), int(spans[i]), bool(lk.converged[i]),
            float(resid[i]), float(lk.score[i]), min_score, uniqueness_margin, epipolar_tolerance_px,
        )
    return EpipolarMatch(cl, lk.uv, disparity, lk.score, second, resid, reasons)


@functools.lru_cache(maxsize=8)
def _any_fit(params: MeasureParams) -> MeasureParams:
    """``params`` with the score and uncertainty limits lifted: a tracked point's match is judged
    by :func:`match_epipolar`'s own checks, not by ``measure``'s acceptance of a new point.
    Cached: building a parameter set checks every field (:func:`~trackmeter.core.params.check_params`),
    and this runs every frame."""
    return replace(params, min_score=-1.0, max_sigma_disparity_px=math.inf)


def _epipolar_reason(
    ok: bool, best: float, second: float, k_best: int, span: int, converged: bool, resid: float, score: float,
    min_score: float, uniqueness_margin: float, epipolar_tolerance_px: float,
) -> str | None:
    """Why :func:`match_epipolar` refuses one point (None: accepted), the first failing check."""
    if not ok:
        return "textureless or outside the rectified image"
    if best < min_score:
        return f"no stereo match along the epipolar line (score {best:.2f})"
    if second > best - uniqueness_margin:
        return f"ambiguous along the epipolar line (scores {best:.2f} and {second:.2f})"
    if k_best in (0, span) and span > 0:
        return "stereo match at the edge of the disparity range"
    if not converged:
        return "stereo sub-pixel refinement did not converge"
    if abs(resid) > epipolar_tolerance_px:
        return f"off the epipolar line by {resid:.2f} px"
    if score < min_score:
        return f"weak stereo match (score {score:.2f})"
    return None


@dataclass(frozen=True, eq=False)
class AffineLKResult:
    """Result of :func:`refine_lk_affine` for N patches.

    Attributes:
        warp: (N,2,3) affine maps from template offsets ``(x, y, 1)`` to image pixels; the
            target's position is the last column (the template centre's image).
        score: (N,) ZNCC between the template and the warped image patch.
        converged: (N,) converged inside the image without degenerating.
    """

    warp: FloatArray
    score: FloatArray
    converged: NDArray[np.bool_]

    @property
    def uv(self) -> FloatArray:
        return self.warp[:, :, 2]


def sample_warped(image: lk_kernels.Image, warp: NDArray, size: int) -> tuple[F32, NDArray[np.bool_]]:
    """Patches (N,size,size) sampled at ``warp @ (x, y, 1)`` for the template offsets (x, y)."""
    _, _, _, ox, oy = _patch_grid(size)
    W = np.asarray(warp, dtype=np.float64)
    # both rows of the warp at once (N,2,size²): the same products and sums as per row
    xy = W[:, :, 0, None] * ox + W[:, :, 1, None] * oy + W[:, :, 2, None]
    values, inside = bilinear(image, xy[:, 0], xy[:, 1])
    return values.reshape(len(W), size, size), cast("NDArray[np.bool_]", inside.all(axis=1))  # numpy's stubs: or a bool


def refine_lk_affine(
    image: lk_kernels.Image,
    templates: Templates,
    warp0: NDArray,
    *,
    max_iterations: int = 20,
    tolerance_px: float = 1e-3,
    max_shift_px: float = 3.0,
) -> AffineLKResult:
    """Inverse-compositional Lucas-Kanade with an affine warp and closed-form gain/bias.

    Baker & Matthews 2004, section 3.2 with the 6-parameter affine warp
    ``W(x; p) = [[1+p1, p3, p5], [p2, 1+p4, p6]] (x, y, 1)`` about the template centre:
    steepest-descent images ``grad T * dW/dp = (x Tx, x Ty, y Tx, y Ty, Tx, Ty)``, Hessian
    ``H = sum SD^T SD`` precomputed, step ``dp = H^-1 sum SD^T (I'(W(x;p)) - T)``, update
    ``W <- W o W(dp)^-1``. Following the rotation, scaling and shear of a tumbling surface, the
    template CENTRE stays on its surface point, where a translation-only match of a rotated
    patch is pulled toward the patch's texture.

    On small patches (8x8) the four linear parameters are poorly determined: noise moves them
    by several per cent per frame and Gauss-Newton creeps along that valley, so prefer
    :func:`refine_lk_similarity` where the motion is mostly rotation and scale.

    Args:
        warp0: (N,2,3) start warps (e.g. last frame's linear part with this frame's position).
        max_shift_px: the centre may not move farther than this from ``warp0``'s.
    """
    return _refine_lk_warp(image, templates, warp0, "affine", max_iterations, tolerance_px, max_shift_px)


def refine_lk_similarity(
    image: lk_kernels.Image,
    templates: Templates,
    warp0: NDArray,
    *,
    max_iterations: int = 20,
    tolerance_px: float = 1e-3,
    max_shift_px: float = 3.0,
) -> AffineLKResult:
    """Inverse-compositional Lucas-Kanade with a similarity increment and closed-form gain/bias.

    As :func:`refine_lk_affine`, but each step is the 4-parameter similarity
    ``W(x; p) = [[1+p1, -p2, p3], [p2, 1+p1, p4]] (x, y, 1)`` (p1: scale change, p2: small
    rotation angle, rad; Baker & Matthews 2004, section 3.2 with the warp of their Table 1
    restricted to rotation + isotropic scale): steepest-descent images
    ``(x Tx + y Ty, x Ty - y Tx, Tx, Ty)``, update ``W <- W o W(dp)^-1``. The result keeps
    ``warp0``'s linear part composed with a similarity (a similarity when ``warp0``'s is one).

    Why: the in-plane rotation and the scale of a patch are well determined even by an 8x8
    patch, its shear and anisotropic stretch are not (on the simulated estec runs the affine
    fit's area jitters by 5 % per frame, median, where the true motion is ~0.14 deg/frame);
    dropping the two weak directions makes Gauss-Newton converge in a few steps instead of
    creeping along a noise valley, without giving up the rotation-following of the anchor.

    Args:
        warp0: (N,2,3) start warps (e.g. last frame's linear part with this frame's position).
        max_shift_px: the centre may not move farther than this from ``warp0``'s.
    """
    return _refine_lk_warp(image, templates, warp0, "similarity", max_iterations, tolerance_px, max_shift_px)


def refine_lk_euclidean(
    image: lk_kernels.Image,
    templates: Templates,
    warp0: NDArray,
    *,
    max_iterations: int = 20,
    tolerance_px: float = 1e-3,
    max_shift_px: float = 3.0,
) -> AffineLKResult:
    """As :func:`refine_lk_similarity` with the scale held at ``warp0``'s: 3 parameters,
    ``W(x; p) = [[cos p1, -sin p1, p2], [sin p1, cos p1, p3]] (x, y, 1)``, steepest-descent
    images ``(x Ty - y Tx, Tx, Ty)``. For a stereo tracker, which knows each target's scale
    change from its depth (pinhole: image size ~ 1/z) far better than an 8x8 patch does."""
    return _refine_lk_warp(image, templates, warp0, "euclidean", max_iterations, tolerance_px, max_shift_px)


def warp_steepest_descent(
    templates: Templates, model: str, hold_linear: NDArray[np.bool_] | None = None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """What the inverse-compositional warp fits precompute from N templates (side n, K = n²):
    the zero-mean templates ``Tm`` (N,K); the steepest-descent images ``grad T * dW/dp``
    (N,K,P) of ``model`` (Baker & Matthews 2004, section 3.2), with ``hold_linear`` rows'
    linear columns zeroed and every column projected off span{1, T} (the gain and bias are
    solved in closed form: variable projection); and the inverse Gauss-Newton Hessians
    (N,P,P), damped by 1e-6 of their trace so a textureless direction gives a zero step."""
    n = templates.size
    N = len(templates.values)
    _, _, _, ox, oy = _patch_grid(n)
    gx = templates.gx.reshape(N, n * n).astype(np.float64)
    gy = templates.gy.reshape(N, n * n).astype(np.float64)
    T = templates.values.reshape(N, n * n).astype(np.float64)
    Tm = T - _row_mean(T)
    Tn = Tm / np.maximum(np.linalg.norm(Tm, axis=1, keepdims=True), 1e-9)
    if model == "affine":
        SD = np.stack([ox * gx, ox * gy, oy * gx, oy * gy, gx, gy], axis=-1)  # (N, n², 6)
    elif model == "similarity":
        SD = np.stack([ox * gx + oy * gy, ox * gy - oy * gx, gx, gy], axis=-1)  # (N, n², 4)
    elif model == "euclidean":
        SD = np.stack([ox * gy - oy * gx, gx, gy], axis=-1)  # (N, n², 3)
    elif model == "disparity_plane":
        SD = np.stack([ox * gx, oy * gx, gx, gy], axis=-1)  # (N, n², 4)
    else:
        raise ValueError(f"unknown warp model {model!r}")
    P = SD.shape[-1]
    if hold_linear is not None and P > 2:
        SD[np.asarray(hold_linear, dtype=bool), :, : P - 2] = 0.0
    SD = _project_out(SD, Tn)
    H = np.einsum("nki,nkj->nij", SD, SD)
    damp = 1e-6 * np.trace(H, axis1=1, axis2=2)[:, None, None] * np.eye(P)
    return Tm, SD, np.linalg.inv(H + damp)


def _refine_lk_warp(
    image: lk_kernels.Image,
    templates: Templates,
    warp0: NDArray,
    model: str,
    max_iterations: int,
    tolerance_px: float,
    max_shift_px: float,
    hold_linear: NDArray[np.bool_] | None = None,
) -> AffineLKResult:
    """Shared IC-LK loop of the warp fits: ``model`` "affine", "similarity", "euclidean" or
    "disparity_plane" (:func:`fit_disparity_plane`).
    Every increment ``D`` lies in the model's group, so ``W o D^-1`` stays in it.

    ``hold_linear`` (N,): rows whose linear parameters are held at ``warp0``'s (their
    steepest-descent images are zeroed, so their steps are 0 exactly): a translation fit of
    those rows within the same batched call. The steepest-descent images and the Hessians come
    from :func:`warp_steepest_descent`, the iterations from :func:`trackmeter.core.lk_kernels.lk_warp`."""
    n = templates.size
    N = len(templates.values)
    W0 = np.ascontiguousarray(np.asarray(warp0, dtype=np.float64).reshape(N, 2, 3))
    _, _, _, ox, oy = _patch_grid(n)
    Tm, SD, Hinv = warp_steepest_descent(templates, model, hold_linear)
    warp, score, converged = lk_kernels.lk_warp(
        _image_stack(image), image.ndim == 3, np.ascontiguousarray(Tm), np.ascontiguousarray(SD), np.ascontiguousarray(Hinv),
        np.asarray(templates.ok, dtype=bool), W0, ox, oy, _LK_MODELS[model],
        int(max_iterations), float(tolerance_px), float(max_shift_px),
    )
    return AffineLKResult(warp=warp, score=score, converged=converged)


def warm_up() -> None:
    """Compile the fits' loops now, or load them from numba's cache: about 3.5 s the first
    time after an install, 0.3 s after, which a live pipeline would otherwise spend on the
    frame of its first target and drop the frames behind it. The arguments have the types
    of the tracker's calls, so the specialisations made here are the ones it runs."""
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, (24, 24), dtype=np.uint8)  # a camera frame
    centre = np.array([[12.0, 12.0]])
    templates = make_templates(frame, centre, 8)
    make_templates(frame.astype(np.float32), centre, 8)  # a smoothed frame
    sample_patches(frame, centre, 8, complex_map(*np.meshgrid(np.arange(24.0), np.arange(24.0))))  # through a rectification table
    for image in (frame, frame.astype(np.float32)[None]):  # and a stack of rectified strips
        refine_lk(image, templates, centre)
        refine_lk_similarity(image, templates, np.array([[[1.0, 0.0, 12.0], [0.0, 1.0, 12.0]]]))


def refine_lk_translation(
    image: lk_kernels.Image,
    templates: Templates,
    warp0: NDArray,
    *,
    max_iterations: int = 20,
    tolerance_px: float = 1e-3,
    max_shift_px: float = 3.0,
) -> AffineLKResult:
    """As :func:`refine_lk_affine` with ``warp0``'s linear part held fixed: only the position is
    fitted (steepest-descent images ``(Tx, Ty)``, the step mapped through the linear part). For
    an anchor whose shape change is known from geometry (:func:`plane_jacobian`), so the
    patch's own weakly determined linear parameters add no noise to the centre."""
    hold = np.ones(len(templates.values), dtype=bool)
    return _refine_lk_warp(image, templates, warp0, "similarity", max_iterations, tolerance_px, max_shift_px, hold)


def plane_jacobian(K: NDArray, R: NDArray, t: NDArray, m: NDArray, uv: NDArray) -> FloatArray:
    """Linear part (N,2,2) of the plane-induced homography between two pinhole views, at ``uv``.

    A plane ``m · X = 1`` (``m = n / c``: unit normal over distance, 1/m; (N,3)) in the first
    camera's frame, seen again after ``X' = R X + t`` ((N,3,3), (N,3)), maps pixels by
    ``H = K (R + t mᵀ) K⁻¹`` (Hartley & Zisserman, 2nd ed., result 13.1). Its Jacobian at the
    first view's pixel ``x = uv`` (N,2), with ``(a, w) = (H[:2] x̃, H[2] x̃)`` and ``x' = a / w``:
    ``J = (H[:2,:2] - x' H[2,:2]) / w``. This is the affine map of a small patch of the plane
    from the first image into the second (its foreshortening, rotation and scale). ``K`` (3,3)
    is shared; lens distortion is not modelled (on the estec rig it changes a patch's shape by
    far less than the 8x8 fit can see).
    """
    K = np.asarray(K, dtype=np.float64)
    Kinv = np.linalg.inv(K)
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    t = np.asarray(t, dtype=np.float64).reshape(-1, 3)
    m = np.asarray(m, dtype=np.float64).reshape(-1, 3)
    H = K @ (R + t[:, :, None] * m[:, None, :]) @ Kinv
    x = np.concatenate([np.asarray(uv, dtype=np.float64).reshape(-1, 2), np.ones((len(H), 1))], axis=1)
    hx = np.einsum("nij,nj->ni", H, x)
    w = hx[:, 2]
    xp = hx[:, :2] / w[:, None]
    return (H[:, :2, :2] - xp[:, :, None] * H[:, None, 2, :2]) / w[:, None, None]


def transform_plane(m: NDArray, R: NDArray, t: NDArray) -> FloatArray:
    """The plane ``m · X = 1`` (N,3) in the frame reached by ``X' = R X + t``: ``m' = R m / (1 + (R m) · t)``."""
    Rm = np.einsum("nij,nj->ni", np.asarray(R, dtype=np.float64).reshape(-1, 3, 3), np.asarray(m, dtype=np.float64).reshape(-1, 3))
    return Rm / (1.0 + np.einsum("ni,ni->n", Rm, np.asarray(t, dtype=np.float64).reshape(-1, 3)))[:, None]


@dataclass(frozen=True, eq=False)
class DisparityPlane:
    """Result of :func:`fit_disparity_plane` for N rectified left points.

    Attributes:
        disparity_px: (N,) disparity at the point, px (as measured: with the rectification's offset).
        slope: (N,2) ``(dd/du, dd/dv)``, px/px.
        plane_rect: (N,3) the plane ``m · X = 1`` in the rectified left camera frame, 1/m.
        score: (N,) ZNCC of the warped right patch with the left one.
        converged: (N,).
    """

    disparity_px: FloatArray
    slope: FloatArray
    plane_rect: FloatArray
    score: FloatArray
    converged: NDArray[np.bool_]


def fit_disparity_plane(
    left: lk_kernels.Image,
    right: lk_kernels.Image,
    left_map: CoordMap,
    right_map: CoordMap,
    uv_rect_left: NDArray,
    disparity_px: NDArray,
    size: int,
    *,
    focal_px: float,
    baseline_m: float,
    principal_px: tuple[float, float],
    disparity_offset_px: float = 0.0,
    max_iterations: int = 20,
    tolerance_px: float = 1e-3,
) -> DisparityPlane:
    """The local surface plane of N points from the rectified stereo pair.

    Over a planar patch the rectified disparity is affine, ``d(u, v) = d0 + gu du + gv dv``, so
    the right patch is the left one under the warp
    ``W (du, dv) = (u0 - d0 + (1 - gu) du - gv dv, v0 + dv + e)`` (``e``: a row offset left
    free, as the epipolar match does). It is fitted by inverse-compositional LK with
    closed-form gain/bias (model ``"disparity_plane"`` of the shared loop; the increments
    ``[[1+p1, p2, p3], [0, 1, p4]]`` form a group) between the RECTIFIED left patch (side
    ``size``) and the rectified right image around ``u0 - disparity_px``, both sampled through
    their coordinate maps. For the plane ``n · X = c`` (rectified left frame) and the pinhole
    ``d = f b / Z (+ offset)``: ``1/Z = (n_x (u - cx) + n_y (v - cy) + f n_z) / (f c)``, so
    ``gu = b n_x / c``, ``gv = b n_y / c``, ``d0 - offset = (f b / c) (n · ray0)``; with
    ``m = n / c``: ``m = (gu / b, gv / b, (d0 - offset - gu (u0 - cx) - gv (v0 - cy)) / (f b))``.

    Args:
        left, right: the ORIGINAL images, uint8 or float32 (sampled alike).
        left_map, right_map: rectified → original coordinate maps (see :func:`sample_points`).
        uv_rect_left: (N,2) rectified left pixels; ``disparity_px`` (N,) their disparities (start).
        size: side of the fitted patch (larger than the tracking patch: the slope of an 8x8
            patch is noise), px.
        principal_px: ``(cx, cy)`` of the rectified left camera.
    """
    cl = np.asarray(uv_rect_left, dtype=np.float64).reshape(-1, 2)
    d = np.asarray(disparity_px, dtype=np.float64).reshape(-1)
    N = len(cl)
    templates = make_templates(left, cl, size, left_map)
    # Room for the slopes: a face seen at 75 deg from face-on has |g| ~ 0.3, which moves the
    # patch's edge columns by ~size/6.
    margin = max(4, size // 3)
    side = size + 2 * margin
    centre_r = np.column_stack([cl[:, 0] - d, cl[:, 1]])
    # the rectified right image around each match, one small image per point
    strip, _ = sample_patches(right, centre_r, side, right_map)
    c = (side - 1) / 2.0
    W0 = np.zeros((N, 2, 3))
    W0[:, 0, 0] = W0[:, 1, 1] = 1.0
    W0[:, :, 2] = c
    fit = _refine_lk_warp(np.ascontiguousarray(strip), templates, W0, "disparity_plane", max_iterations, tolerance_px, 3.0)
    W = fit.warp
    u_right = centre_r[:, 0] - c + W[:, 0, 2]
    d0 = cl[:, 0] - u_right
    gu = 1.0 - W[:, 0, 0]
    gv = -W[:, 0, 1]
    f, b = float(focal_px), float(baseline_m)
    cx, cy = principal_px
    m = np.column_stack([gu / b, gv / b, (d0 - disparity_offset_px - gu * (cl[:, 0] - cx) - gv * (cl[:, 1] - cy)) / (f * b)])
    return DisparityPlane(d0, np.column_stack([gu, gv]), m, fit.score, fit.converged)


_ANCHOR_FITS = {"affine": refine_lk_affine, "similarity": refine_lk_similarity, "euclidean": refine_lk_euclidean}


#: anchor warps whose linear part is predicted, and the fit of the rows with a prediction
_PLANE_FITS = {"plane": "translation"}


def _with_scale(lin: FloatArray, scale: FloatArray) -> FloatArray:
    """Linear warps ``lin`` (N,2,2) rescaled to the scale ``scale`` (N,) (sqrt |det|)."""
    return lin * (scale / np.sqrt(np.maximum(np.abs(np.linalg.det(lin)), 1e-12)))[:, None, None]


def _scale_held_refit(
    image: lk_kernels.Image,
    anchor: Templates,
    W0: FloatArray,
    la: AffineLKResult,
    refit: NDArray[np.bool_],
    expect: FloatArray,
    tolerance_px: float,
) -> tuple[AffineLKResult, NDArray[np.bool_]]:
    """The anchor similarity fits ``la`` of rows ``refit`` (N,), refused (not converged, or their
    scale off the depth-implied one), fitted again with the scale held at the depth-implied
    ``expect`` (N,): :func:`refine_lk_euclidean` from ``W0`` (N,2,3) rescaled to it. Returns
    ``la`` with the rows whose refit converged replaced, and those rows (N,) (their scale is the
    expected one by construction).

    An 8x8 patch holds its scale loosely (one frame after their anchors, 200 estec corners fit
    0.80-1.06, 5th-95th percentile; the operator's targets lost in docs/results.md's "How long
    an operator's target lasts" 0.71-0.88), where the stereo depth gives it to 0.1 %: the held
    fit asks whether the anchor is still there without the free scale that lets a similarity
    fit wander."""
    rows = np.flatnonzero(refit)
    start = W0[rows].copy()
    start[:, :, :2] = _with_scale(start[:, :, :2], expect[rows])
    fit = _fit_anchors(image, anchor.select(rows), start, np.full(len(rows), "euclidean", dtype=object), tolerance_px)
    took = np.zeros(len(la.score), bool)
    took[rows[fit.converged]] = True
    warp, score, converged = la.warp.copy(), la.score.copy(), la.converged.copy()
    warp[took] = fit.warp[fit.converged]
    score[took] = fit.score[fit.converged]
    converged[took] = True
    return AffineLKResult(warp=warp, score=score, converged=converged), took


def _fit_anchors(image: lk_kernels.Image, anchor: Templates, W0: FloatArray, fits: NDArray, tolerance_px: float) -> AffineLKResult:
    """The anchor fits of :func:`track_patches` in one batched call (its cost is mostly per
    call). ``fits`` (N,): each row's model, the same :data:`_ANCHOR_FITS` model for every row,
    or "translation" rows among "similarity" ones (``anchor_warp="plane"``): those are
    similarity rows with their linear part held (:func:`refine_lk_translation`)."""
    kw: dict[str, Any] = dict(max_iterations=8, tolerance_px=tolerance_px, max_shift_px=2.0)
    hold = fits == "translation"
    if hold.any():
        return _refine_lk_warp(image, anchor, W0, "similarity", hold_linear=hold, **kw)
    return _ANCHOR_FITS[fits[0] if len(fits) else "similarity"](image, anchor, W0, **kw)


def track_points(
    previous: NDArray,
    current: NDArray,
    uv: NDArray,
    size: int = 8,
    search_px: float = 8.0,
    *,
    min_score: float = 0.8,
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Two-frame patch tracking (the left-image tracker without a filter): points ``uv`` (N,2)
    of ``previous`` found in ``current`` (both (H,W) grey) — ZNCC search in ``±search_px``,
    then :func:`track_patches` with the patch of ``previous`` as anchor and current template.

    Returns ``(uv_current (N,2), ok (N,))``.
    """
    a = np.asarray(previous, dtype=np.float32)
    b = np.asarray(current, dtype=np.float32)
    pts = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    tmpl = make_templates(a, pts, size)
    starts = np.full_like(pts, np.nan)
    ok = tmpl.ok.copy()
    for i in range(len(pts)):
        found = zncc_search(b, tmpl.values[i], pts[i], np.array([search_px, search_px])) if ok[i] else None
        if found is None or found[1] < min_score:
            ok[i] = False
            starts[i] = pts[i]
        else:
            starts[i] = found[0]
    res = track_patches(b, tmpl, np.repeat(np.eye(2)[None], len(pts), 0), tmpl, starts,
                        anchor_min_score=min_score, drift_tolerance_px=0.5)
    return res.uv, ok & res.converged & (res.score >= min_score)
