"""Patch stereo matching and 3D point measurement (paper section 2.A).

The operator points at a pixel of the LEFT image; its neighbourhood (default 8x8, as the paper)
is searched for along the epipolar line of the rectified RIGHT image with the zero-mean
normalised cross-correlation (ZNCC), refined to sub-pixel, checked, and triangulated with its
uncertainty from the stereo error propagation (paper eqs. 1-2).

Only the pixels a point needs are rectified: the patch and the search strip are sampled
straight from the original images through slices of the rectification maps
(:attr:`trackmeter.core.stereo.Rectification.maps`), so one point costs a few small remaps
instead of two full-image remaps (:func:`sample_rectified`). The integer search runs on a
bilinear strip; the sub-pixel fit resamples the patch and the match's neighbourhood with
Lanczos-4, whose small phase error keeps left and right (resampled at different fractional
positions) consistent. The patch is centred EXACTLY on the requested pixel (an even-sized
patch samples between pixels): the disparity belongs to that pixel, not to a neighbour half a
pixel away.

Many points at once (:func:`measure_points`, e.g. a tracker's ~50 automatic candidates) go
through the stages of a single point's match together: each stage resamples the blocks of
all its points in one ``cv2.remap`` over their stacked maps (:func:`sample_rectified_blocks`,
the same samples bit for bit), the sub-pixel fit runs for all of them in lock step
(:func:`refine_positions`, equal to the scalar fit up to summation order, ~1e-14 px), and the
left rows for the left-right check are resampled only for the points that get that far. Each
point gets the reason and numbers it gets alone (``tests/test_matching_batch.py``). On the
estec scenario's automatic candidates a batch of 50 costs ~0.6 per point of the
point-by-point loop it replaces (``python -m benchmarks select``:
``measure_batch_ratio_16`` against the same points one call each, same run).

Sub-pixel refinement without pixel locking
------------------------------------------
A parabola through the three ZNCC scores around the integer peak (``subpixel="parabola"``)
is the textbook refinement and is biased toward integer disparities ("pixel locking",
Shimizu & Okutomi 2001): the correlation peak is not a parabola. The default
(``subpixel="gauss_newton"``) instead fits the right patch itself at a fractional position:
with ``R(x)`` the strip interpolated at column offset ``x`` (cubic B-spline on prefiltered
coefficients, Unser 1999, or Keys cubic convolution; exact derivative), it solves the linear
least-squares problem

    T ≈ a R(x) + c R'(x) + b          (gain a, offset b, shift step dx = c / a)

and iterates ``x ← x + dx`` (Lucas & Kanade 1981 in 1D, with the gain/offset that makes it
maximise ZNCC). The fit's residual gives the disparity's standard deviation,
``sigma_x² = s² [(AᵀA)⁻¹]_cc / a²`` with ``s² = |r|² / (n - 3)``. ``benchmarks/measure.py``
measures the bias curves on exactly shifted synthetic textures: parabola ~0.024 px, Keys
~0.019 px, B-spline (the default) at the noise floor (~0.005 px).

A shift fit assumes one disparity over the patch. On a slanted surface it measures the
disparity where the patch's texture is, not at its centre: on a plane 60° from the line of
sight at 3.5 m, a median 0.078 px off (3 mm of depth), 2.9 times its own sigma (RMS). With
``subpixel_slanted`` (the default) each accepted shift fit is refined once more with the
disparity's horizontal and vertical gradients across the patch (:func:`refine_slanted`, a
Gaussian prior holding them near zero where noise hides them): 0.016 px there, and the same
0.010 px as the shift fit on a fronto-parallel plane (``benchmarks/measure.py``,
``plane<deg>_*``).

Checks (a refused point has ``ok=False`` and a reason from :data:`REASONS`, never a number):
outside the image, patch not inside the image (or inside it but in the border the
rectification crops), too dark (black sky or deep shadow), textureless, no texture
along the epipolar line, search window outside the right image, beyond the disparity range
(peak at the edge of the search), match may lie beyond the right image's edge (the peak at the
end of a search the image's edge cut short of the disparity range), low score, ambiguous (a
second peak outside the main lobe nearly as good), sub-pixel refinement failed (or its refined
score low), disparity too uncertain (the fit's own standard deviation is large: the aperture
problem along the epipolar line), repetitive texture (a wider window, allowed to be foreshortened, does not prefer the
best peak over the other strong ones: see :func:`_context_decide`), left-right inconsistent
(matching the right patch back along the left row lands elsewhere), a look-alike where the
search left the right image (:func:`_rival_unseen`; ``unseen_rival_check``), depth edge inside the
patch (windows shifted a few pixels each way disagree with the patch's disparity by more than
a plane allows: see :func:`_edge_decide`).

The checks are independent (each looks at the integer match or the sub-pixel fit, not at
another check's outcome), so their order decides only which reason a point failing several
of them gets. The sub-pixel fit runs before the wider-window check because it is the cheaper
of the two and the most frequent refusal of automatically selected points: on the estec
scenario's top-ups ~3/4 of the candidates are refused as too uncertain, and testing that first
spares them the wider window (measure_points ~22 % faster on those candidates).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal, Sequence, cast, overload

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from trackmeter.core.checks import as_rows
from trackmeter.core.params import check_params, param
from trackmeter.core.stereo import Rectification, StereoRig, axis_sigmas, check_side_by_side
from trackmeter.errors import TrackmeterError

FloatArray = NDArray[np.float64]

REASON_OUTSIDE_IMAGE = "outside image"
REASON_PATCH_OUTSIDE = "patch not inside image"
REASON_PATCH_CROPPED = "patch in the border the rectification crops"
REASON_TOO_DARK = "too dark (black sky or deep shadow)"
REASON_TEXTURELESS = "textureless"
REASON_NO_EPIPOLAR_TEXTURE = "no texture along epipolar line"
REASON_SEARCH_OUTSIDE = "search window outside right image"
REASON_BEYOND_RANGE = "beyond disparity range"
REASON_MATCH_OFF_IMAGE = "match may lie beyond the right image's edge"
REASON_LOW_SCORE = "low score"
REASON_AMBIGUOUS = "ambiguous (second peak)"
REASON_REPETITIVE = "ambiguous (repetitive texture)"
REASON_UNSEEN_RIVAL = "ambiguous (its texture repeats where the search left the right image)"
REASON_LEFT_RIGHT = "left-right inconsistent"
REASON_SUBPIXEL = "sub-pixel refinement failed"
REASON_UNCERTAIN = "disparity too uncertain"
REASON_DEPTH_EDGE = "depth edge inside the patch"

#: Every reason a point can be refused for, in the order the checks run.
REASONS: tuple[str, ...] = (
    REASON_OUTSIDE_IMAGE,
    REASON_PATCH_OUTSIDE,
    REASON_PATCH_CROPPED,
    REASON_TOO_DARK,
    REASON_TEXTURELESS,
    REASON_NO_EPIPOLAR_TEXTURE,
    REASON_SEARCH_OUTSIDE,
    REASON_BEYOND_RANGE,
    REASON_MATCH_OFF_IMAGE,
    REASON_LOW_SCORE,
    REASON_AMBIGUOUS,
    REASON_SUBPIXEL,
    REASON_UNCERTAIN,
    REASON_REPETITIVE,
    REASON_LEFT_RIGHT,
    REASON_UNSEEN_RIVAL,
    REASON_DEPTH_EDGE,
)

#: Extra strip columns kept on each side of the candidate positions, so the cubic
#: interpolation of the sub-pixel fit and the "is the peak inside the range" test have data.
STRIP_MARGIN_PX = 2

#: Columns kept on each side of the integer match when the strip is resampled finely for the
#: sub-pixel fit (the B-spline prefilter needs ~7 columns of context to be exact to 1e-4).
FINE_MARGIN_PX = 10


@dataclass(frozen=True)
class MeasureParams:
    """Tunables of a single 3D point measurement."""

    patch_size: int = param(8, "side of the square patch matched between the images, px", min=3, max=63)
    min_disparity_px: float = param(0.0, "smallest disparity searched, px past a point at infinity's (0: infinity)", min=0.0)
    max_disparity_px: float = param(
        0.0, "largest disparity searched, px past a point at infinity's; 0: a point's at min_range_m "
        "(disparity_range_px)", min=0.0, max=4096.0,
    )
    min_range_m: float = param(
        1.0, "when max_disparity_px is 0: the nearest range searched, m (a rig's focal length x baseline / it: "
        "326 px for the 12 mm ESTEC rig, 420 px for f 1400 px and b 0.3 m)", min=0.01,
    )
    min_score: float = param(0.8, "smallest ZNCC accepted at the refined match", min=-1.0, max=1.0)
    uniqueness_margin: float = param(
        0.05, "refuse when a second ZNCC peak outside the main lobe comes this close to the best", min=0.0, max=2.0
    )
    left_right_tolerance_px: float = param(
        1.0, "largest disagreement of the right-to-left match with the left-to-right one, px", min=0.0
    )
    min_mean_grey: float = param(12.0, "darker patches (mean grey level) are black sky and refused", min=0.0, max=255.0)
    min_texture_std: float = param(3.0, "smallest standard deviation of the patch, grey levels", min=0.0)
    min_gradient_rms: float = param(
        1.0, "smallest RMS of the patch's horizontal (epipolar) gradient, grey levels per px", min=0.0
    )
    slant_scales: tuple[float, ...] = param(
        (),
        "horizontal stretches of the right patch tried at the best peaks (slanted surfaces); empty: off",
        min=0.5,
        max=2.0,
    )
    slant_candidates: int = param(3, "how many of the highest correlation peaks are re-scored for slant", min=1, max=10)
    context_width_px: int = param(
        32, "width of the wider window that decides between strong peaks (repetitive texture), px; 0 = off", min=0, max=255
    )
    context_height_px: int = param(16, "height of that window, px", min=1, max=255)
    unseen_rival_check: bool = param(
        True, "refuse a point whose texture repeats (by the left row) at a disparity the search could not see, "
        "beyond the right image's edge or the rectification's crop: a look-alike may be the match seen"
    )
    context_window: float = param(
        0.25, "peaks scoring within this ZNCC of the best are re-scored with the wider window", min=0.0, max=2.0
    )
    context_ratio: float = param(
        8.0, "... and whose ZNCC deficit 1 - c is at most this times the best's", min=1.0
    )
    context_candidates: int = param(4, "largest number of peaks (the best included) re-scored with the wider window", min=2, max=10)
    context_margin: float = param(
        0.03, "refuse unless the best peak's wider-window ZNCC beats every other candidate's by this", min=0.0, max=1.0
    )
    context_scales: tuple[float, ...] = param(
        (0.7, 0.8, 0.9, 1.12, 1.25, 1.43),
        "horizontal stretches of the wider right window tried besides 1 (foreshortened, slanted faces)",
        min=0.5,
        max=2.0,
    )
    subpixel: str = param(
        "gauss_newton", "sub-pixel refinement: gauss_newton (unbiased) or parabola (baseline)",
        choices=("gauss_newton", "parabola"),
    )
    subpixel_interpolation: str = param(
        "bspline", "interpolation of the right strip at fractional shifts: bspline (flat response) or keys (cubic convolution)",
        choices=("bspline", "keys"),
    )
    subpixel_iterations: int = param(10, "largest number of Gauss-Newton steps", min=1, max=100)
    subpixel_tolerance_px: float = param(1e-3, "Gauss-Newton stops when a step is smaller, px", min=0.0)
    subpixel_slanted: bool = param(
        True, "gauss_newton: after the shift fit, fit the disparity's horizontal and vertical gradients across "
        "the patch with it (a slanted surface), so the disparity is the patch centre's, not its texture "
        "centroid's (refine_slanted)",
    )
    slant_prior_px_per_px: float = param(
        0.03, "slanted fit: standard deviation of the Gaussian prior on the disparity's gradients across the "
        "patch, px/px (0: none): where noise hides the slant, its two extra parameters would only add noise, "
        "so they are held near zero unless the patch shows them", min=0.0,
    )
    max_sigma_disparity_px: float = param(
        0.08, "refuse when the fit's own disparity standard deviation is larger (aperture problem), px", min=0.0
    )
    edge_shift_px: int = param(
        3, "depth-edge check: shift of the four windows refitted around the patch, px; 0 = off", min=0, max=16
    )
    edge_tolerance_px: float = param(
        0.7, "refuse when a shifted pair's disparities depart from a plane through the patch's by more, px", min=0.0
    )
    edge_min_score: float = param(
        0.5, "refuse when a shifted window's ZNCC near the patch's disparity is lower", min=-1.0, max=1.0
    )
    sigma_disparity_px: float = param(
        0.0, "disparity standard deviation for the error propagation, px; 0 = estimate from the fit", min=0.0
    )
    min_sigma_disparity_px: float = param(
        0.02, "floor under an estimated disparity standard deviation, px", min=0.0
    )
    sigma_uv_px: float = param(0.0, "standard deviation of the left pixel itself, px (0: taken as exact)", min=0.0)

    def __post_init__(self) -> None:
        check_params(self)  # declared ranges and choices first (trackmeter.core.params)
        if self.max_disparity_px and not self.min_disparity_px < self.max_disparity_px:
            # An empty search range would refuse every point as "beyond range", far from the cause.
            raise TrackmeterError(f"min_disparity_px ({self.min_disparity_px:g}) must be below "
                                  f"max_disparity_px ({self.max_disparity_px:g})")

    def disparity_range_px(self, rect: Rectification) -> tuple[float, float]:
        """The disparities searched along a rectified row, ``(low, high)`` px, for the rig ``rect``.

        ``min_disparity_px`` and ``max_disparity_px`` count from a point at infinity's
        disparity, the rectification's ``disparity_offset_px`` (0 on a rig rectified to one
        principal point; ``cx1 - cx2`` on a pair rectified already, e.g. minus Middlebury's
        ``doffs``), which is added to both. ``high`` is ``max_disparity_px`` when given, else
        the disparity of a point at ``min_range_m`` (``f b / z``), so that the
        nearest range searched is the same on any rig: a fixed 320 px was 1 m on the ESTEC
        rig but 1.4 m on a 1280 px wide one (f 1400 px, b 0.3 m), where a near face was refused
        as "low score" or "ambiguous" without a word of range. Never more than the rectified
        image's width, the largest disparity a point in both views can have.

        Raises:
            TrackmeterError: a range that is empty on this rig (``min_disparity_px`` too large).
        """
        width = float(rect.rig.image_size[0])
        offset = rect.disparity_offset_px
        high = min(float(self.max_disparity_px or rect.focal_px * rect.baseline_m / self.min_range_m) + offset, width)
        low = float(self.min_disparity_px) + offset
        if not low < high:
            raise TrackmeterError(f"min_disparity_px ({self.min_disparity_px:g}) must be below the largest disparity "
                                  f"searched, {high - offset:.4g} px on this rig (max_disparity_px, or min_range_m's)")
        return low, high


# --------------------------------------------------------------------------- results


@dataclass(frozen=True, eq=False)
class StripMatch:
    """Result of matching one template along one strip (:func:`match_strip`).

    Attributes:
        ok, reason: whether the match passed the score/uniqueness/range checks, and why not.
        position_px: sub-pixel column ``x`` of the template's first column in the strip:
            ``template ≈ strip[:, x : x + P]`` (NaN when refused before refinement).
        integer_position: the best candidate column (-1 when there was none).
        score: ZNCC at ``position_px`` (NaN when not computed).
        second_score: best ZNCC outside the main lobe (-1 when none).
        sigma_px: standard deviation of ``position_px`` from the fit residual, px.
        scores: (W - P + 1,) ZNCC at every integer column of the strip.
    """

    ok: bool
    reason: str | None
    position_px: float
    integer_position: int
    score: float
    second_score: float
    sigma_px: float
    scores: NDArray[np.float32]


@dataclass(frozen=True, eq=False)
class PointMeasurement:
    """One measured (or refused) point.

    Attributes:
        uv: (2,) requested pixel of the ORIGINAL left image, px.
        ok: True when every check passed and the numbers below are valid.
        reason: why the point was refused (one of :data:`REASONS`), None when ok.
        uv_rect: (2,) the requested pixel in the rectified left image, px (NaN if outside).
        right_uv: (2,) matched pixel of the ORIGINAL right image, px (NaN when refused).
        disparity_px: rectified disparity ``u_left - u_right``, px (NaN when refused).
        sigma_disparity_px: its standard deviation used for ``sigma_m``/``cov_m``, px.
        xyz_m: (3,) point in the LEFT camera frame, m (NaN when refused).
        sigma_m: (3,) standard deviation per axis of ``xyz_m``, m.
        cov_m: (3,3) covariance of ``xyz_m`` (paper eqs. 1-2 propagated), m².
        score: ZNCC of the match (NaN when not computed; may be given for refused points).
    """

    uv: FloatArray
    ok: bool
    reason: str | None
    uv_rect: FloatArray
    right_uv: FloatArray
    disparity_px: float
    sigma_disparity_px: float
    xyz_m: FloatArray
    sigma_m: FloatArray
    cov_m: FloatArray
    score: float

    def to_json(self) -> dict[str, Any]:
        """The DESIGN.md ``measure --json`` object; unavailable numbers are ``None`` (null)."""

        def num(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        def vec(a: FloatArray) -> list[float | None] | None:
            return None if not np.all(np.isfinite(a)) else [float(v) for v in a]

        return {
            "uv": [num(self.uv[0]), num(self.uv[1])],  # a NaN pixel asked for: null, not JSON's NaN
            "ok": bool(self.ok),
            "reason": self.reason,
            "right_uv": vec(self.right_uv),
            "disparity_px": num(self.disparity_px),
            "xyz_m": vec(self.xyz_m),
            "sigma_m": vec(self.sigma_m),
            "score": num(self.score),
        }


# --------------------------------------------------------------------------- sampling


def _block_map(
    mx_full: NDArray[np.float32], my_full: NDArray[np.float32], x0: float, y0: float, width: int, height: int,
    w_img: int, h_img: int,
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.bool_] | None, tuple[float, float, float, float]]:
    """One rectified block's maps ``(mx, my)`` (height, width), its ``col_ok`` (None when every
    source pixel is inside the image) and the extent ``(x_lo, x_hi, y_lo, y_hi)`` of its source
    pixels in the original image (see :func:`sample_rectified`)."""
    bx, by = math.floor(x0), math.floor(y0)
    H, W = mx_full.shape
    if bx < 0 or by < 0 or bx + width >= W or by + height >= H:
        raise ValueError(f"rectified block at ({x0}, {y0}) size {width}x{height} leaves the {W}x{H} grid")
    # Bilinear interpolation of the (smooth) maps at the block's fractional offset, one call each.
    centre = (x0 + 0.5 * (width - 1), y0 + 0.5 * (height - 1))
    mx = cast("NDArray[np.float32]", cv2.getRectSubPix(mx_full, (width, height), centre))
    my = cast("NDArray[np.float32]", cv2.getRectSubPix(my_full, (width, height), centre))
    # The maps are smooth and monotonic, so the block's extent in the original image is that
    # of its corners (the bilinear interpolation stays inside the grid cells around them); the
    # 0.1 px margin covers a lens's curvature of the map along the block's few rows.
    x_lo = min(float(mx_full[by, bx]), float(mx_full[by + height, bx]))
    x_hi = max(float(mx_full[by, bx + width]), float(mx_full[by + height, bx + width]))
    y_lo = min(float(my_full[by, bx]), float(my_full[by, bx + width]))
    y_hi = max(float(my_full[by + height, bx]), float(my_full[by + height, bx + width]))
    col_ok = None
    if not (x_lo >= 0.1 and y_lo >= 0.1 and x_hi <= w_img - 1.1 and y_hi <= h_img - 1.1):
        col_ok = np.all((mx >= 0) & (mx <= w_img - 1) & (my >= 0) & (my <= h_img - 1), axis=0)
    return mx, my, col_ok, (x_lo, x_hi, y_lo, y_hi)


def _source_region(extent: tuple[float, float, float, float], w_img: int, h_img: int) -> tuple[int, int, int, int]:
    """The region ``(u0, v0, u1, v1)`` of the original image an exact (Lanczos-4) block of
    source extent ``extent`` needs: Lanczos-4 reaches 3 pixels beyond the 2x2 cell; take the
    extent plus 4 and let remap replicate at the true image border (those columns are flagged
    invalid anyway)."""
    x_lo, x_hi, y_lo, y_hi = extent
    u0 = min(max(int(math.floor(x_lo)) - 4, 0), w_img - 1)
    u1 = max(min(int(math.floor(x_hi)) + 6, w_img), u0 + 1)
    v0 = min(max(int(math.floor(y_lo)) - 4, 0), h_img - 1)
    v1 = max(min(int(math.floor(y_hi)) + 6, h_img), v0 + 1)
    return u0, v0, u1, v1


@overload
def sample_rectified(
    rect: Rectification, image: NDArray[np.uint8], side: int, x0: float, y0: float, width: int, height: int,
    interpolation: int = cv2.INTER_LANCZOS4, exact: Literal[True] = True,
) -> tuple[NDArray[np.float32], NDArray[np.bool_] | None]: ...


@overload
def sample_rectified(
    rect: Rectification, image: NDArray[np.uint8], side: int, x0: float, y0: float, width: int, height: int,
    interpolation: int = cv2.INTER_LANCZOS4, *, exact: Literal[False],
) -> tuple[NDArray[np.uint8], NDArray[np.bool_] | None]: ...


@overload
def sample_rectified(
    rect: Rectification, image: NDArray[np.uint8], side: int, x0: float, y0: float, width: int, height: int,
    interpolation: int = cv2.INTER_LANCZOS4, exact: bool = True,
) -> tuple[NDArray[np.float32] | NDArray[np.uint8], NDArray[np.bool_] | None]: ...


def sample_rectified(
    rect: Rectification,
    image: NDArray[np.uint8],
    side: int,
    x0: float,
    y0: float,
    width: int,
    height: int,
    interpolation: int = cv2.INTER_LANCZOS4,
    exact: bool = True,
) -> tuple[NDArray[np.float32] | NDArray[np.uint8], NDArray[np.bool_] | None]:
    """Sample a block of the RECTIFIED image straight from the original image.

    Returns the rectified pixels at ``(x0 + j, y0 + i)``, ``j < width``, ``i < height``
    (``x0``, ``y0`` may be fractional), as (height, width) float32, and ``col_ok``: per column
    whether every source pixel lies inside the original image, or None when all do (the
    common case, spared an array). The rectification maps are interpolated bilinearly at the
    fractional offset (they are smooth), the image with ``cv2.remap`` (``interpolation``,
    Lanczos-4 by default) over just the
    region it needs, converted to float so no grey-level rounding is added.

    Args:
        rect: the rig's rectification.
        image: (H, W) uint8 original left (side 0) or right (side 1) image.
        side: 0 left, 1 right.
        x0, y0: rectified position of the block's top-left sample, px. The block plus one
            column and row must lie on the rectified grid (callers clip first).
        width, height: block size, px.
        interpolation: OpenCV interpolation flag for the image.
        exact: True: float32 output with no rounding (for sub-pixel work); False: uint8 output
            rounded to grey levels, straight from the image without a float copy (for the
            integer search, where it is cheaper and good enough).
    """
    mx_full, my_full = rect.maps[side]
    h_img, w_img = image.shape
    mx, my, col_ok, extent = _block_map(mx_full, my_full, x0, y0, width, height, w_img, h_img)
    if not exact:
        return cast("NDArray[np.uint8]", cv2.remap(image, mx, my, interpolation, borderMode=cv2.BORDER_REPLICATE)), col_ok
    u0, v0, u1, v1 = _source_region(extent, w_img, h_img)
    roi = image[v0:v1, u0:u1].astype(np.float32)
    if u0:
        mx -= np.float32(u0)
    if v0:
        my -= np.float32(v0)
    out = cast("NDArray[np.float32]", cv2.remap(roi, mx, my, interpolation, borderMode=cv2.BORDER_REPLICATE))
    return out, col_ok


#: Width of the map rows when many blocks are resampled in one ``cv2.remap`` (OpenCV asks for
#: maps narrower than 32767 columns).
_STACK_COLS = 1024


@overload
def sample_rectified_blocks(
    rect: Rectification, image: NDArray[np.uint8], side: int, blocks: Sequence[tuple[float, float, int, int]],
    interpolation: int = cv2.INTER_LANCZOS4, exact: Literal[True] = True,
) -> list[tuple[NDArray[np.float32], NDArray[np.bool_] | None]]: ...


@overload
def sample_rectified_blocks(
    rect: Rectification, image: NDArray[np.uint8], side: int, blocks: Sequence[tuple[float, float, int, int]],
    interpolation: int = cv2.INTER_LANCZOS4, *, exact: Literal[False],
) -> list[tuple[NDArray[np.uint8], NDArray[np.bool_] | None]]: ...


@overload
def sample_rectified_blocks(
    rect: Rectification, image: NDArray[np.uint8], side: int, blocks: Sequence[tuple[float, float, int, int]],
    interpolation: int = cv2.INTER_LANCZOS4, exact: bool = True,
) -> list[tuple[NDArray[np.float32] | NDArray[np.uint8], NDArray[np.bool_] | None]]: ...


def sample_rectified_blocks(
    rect: Rectification,
    image: NDArray[np.uint8],
    side: int,
    blocks: Sequence[tuple[float, float, int, int]],
    interpolation: int = cv2.INTER_LANCZOS4,
    exact: bool = True,
) -> list[tuple[NDArray[Any], NDArray[np.bool_] | None]]:  # float32 or uint8 (the overloads say which)
    """:func:`sample_rectified` for many blocks ``(x0, y0, width, height)`` of one image at once.

    Each block's maps are interpolated exactly as :func:`sample_rectified` does; the maps of all
    blocks are laid end to end in one map of :data:`_STACK_COLS` columns and the image is
    resampled in ONE ``cv2.remap`` (``exact``: from the float copy of the union of the regions
    the blocks need, which reaches every sample's interpolation support as each block's own
    region does). ``remap`` computes every output pixel from its own map entry alone, so each
    block is the same as :func:`sample_rectified`'s, bit for bit, at a fraction of the fixed
    cost of one call per block.

    Returns:
        One ``(block, col_ok)`` per block, in order, as :func:`sample_rectified`.
    """
    if len(blocks) == 0:
        return []
    if len(blocks) == 1:
        return [sample_rectified(rect, image, side, *blocks[0], interpolation=interpolation, exact=exact)]
    mxs, mys, oks, roi = _block_maps(rect, image.shape, side, blocks, exact)
    return list(zip(_remap_stacked(image, mxs, mys, roi, interpolation), oks))


def _block_maps(
    rect: Rectification, image_shape: tuple[int, ...], side: int, blocks: Sequence[tuple[float, float, int, int]], exact: bool
) -> tuple[list[NDArray[np.float32]], list[NDArray[np.float32]], list[NDArray[np.bool_] | None], tuple[int, int, int, int] | None]:
    """The maps and ``col_ok`` of each block as :func:`sample_rectified` computes them, and
    (``exact``) the union ``(u0, v0, u1, v1)`` of the image regions their samples need."""
    mx_full, my_full = rect.maps[side]
    h_img, w_img = image_shape
    mxs, mys, oks = [], [], []
    u0 = v0 = 1 << 30
    u1 = v1 = -1
    for x0, y0, width, height in blocks:
        mx, my, col_ok, extent = _block_map(mx_full, my_full, x0, y0, width, height, w_img, h_img)
        if exact:  # the region sample_rectified would take, merged into the union
            bu0, bv0, bu1, bv1 = _source_region(extent, w_img, h_img)
            u0, v0, u1, v1 = min(u0, bu0), min(v0, bv0), max(u1, bu1), max(v1, bv1)
        mxs.append(mx)
        mys.append(my)
        oks.append(col_ok)
    return mxs, mys, oks, ((u0, v0, u1, v1) if exact else None)


@overload
def _remap_stacked(
    image: NDArray[np.uint8], mxs: Sequence[NDArray[np.float32]], mys: Sequence[NDArray[np.float32]],
    roi: tuple[int, int, int, int], interpolation: int,
) -> list[NDArray[np.float32]]: ...


@overload
def _remap_stacked(
    image: NDArray[np.uint8], mxs: Sequence[NDArray[np.float32]], mys: Sequence[NDArray[np.float32]],
    roi: None, interpolation: int,
) -> list[NDArray[np.uint8]]: ...


@overload
def _remap_stacked(
    image: NDArray[np.uint8], mxs: Sequence[NDArray[np.float32]], mys: Sequence[NDArray[np.float32]],
    roi: tuple[int, int, int, int] | None, interpolation: int,
) -> list[NDArray[np.float32] | NDArray[np.uint8]]: ...


def _remap_stacked(
    image: NDArray[np.uint8],
    mxs: Sequence[NDArray[np.float32]],
    mys: Sequence[NDArray[np.float32]],
    roi: tuple[int, int, int, int] | None,
    interpolation: int,
) -> list[NDArray[Any]]:  # float32 or uint8 (the overloads say which)
    """Resample ``image`` at every block's maps in one ``cv2.remap``: from the float copy of
    ``roi`` (float32 blocks), or from the image itself when ``roi`` is None (uint8 blocks)."""
    sizes = [m.size for m in mxs]
    total = sum(sizes)
    if total == 0:
        return [np.zeros(m.shape, np.float32 if roi else np.uint8) for m in mxs]
    if len(mxs) == 1 and mxs[0].shape[1] < 32767:  # one block: its own maps
        MX, MY = np.array(mxs[0], np.float32, order="C"), np.array(mys[0], np.float32, order="C")
    else:
        rows = -(-total // _STACK_COLS)
        MX = np.zeros(rows * _STACK_COLS, np.float32)
        MY = np.zeros(rows * _STACK_COLS, np.float32)
        np.concatenate([m.ravel() for m in mxs], out=MX[:total])
        np.concatenate([m.ravel() for m in mys], out=MY[:total])
        MX, MY = MX.reshape(rows, _STACK_COLS), MY.reshape(rows, _STACK_COLS)
    src: NDArray[np.float32] | NDArray[np.uint8]
    if roi is not None:
        u0, v0, u1, v1 = roi
        src = image[v0:v1, u0:u1].astype(np.float32)
        # subtracting a whole number from a float32 map entry is exact (the difference is a
        # multiple of the entry's ulp and smaller than it), so the samples are those of the
        # block's own region
        if u0:
            MX -= np.float32(u0)
        if v0:
            MY -= np.float32(v0)
    else:
        src = image
    flat = cast("NDArray[np.float32] | NDArray[np.uint8]", cv2.remap(src, MX, MY, interpolation, borderMode=cv2.BORDER_REPLICATE).ravel())
    out: list[NDArray[np.float32] | NDArray[np.uint8]] = []
    at = 0
    for m, size in zip(mxs, sizes):
        out.append(flat[at : at + size].reshape(m.shape))
        at += size
    return out


# --------------------------------------------------------------------------- 1D matching


def _keys_weights(t: float) -> tuple[tuple[float, float, float, float], tuple[float, float, float, float]]:
    """Keys (1981) cubic convolution (a = -1/2) weights for samples -1, 0, 1, 2 at offset t in
    [0, 1), and their derivatives with respect to t."""
    t2, t3 = t * t, t * t * t
    w = (-0.5 * t3 + t2 - 0.5 * t, 1.5 * t3 - 2.5 * t2 + 1.0, -1.5 * t3 + 2.0 * t2 + 0.5 * t, 0.5 * t3 - 0.5 * t2)
    dw = (-1.5 * t2 + 2.0 * t - 0.5, 4.5 * t2 - 5.0 * t, -4.5 * t2 + 4.0 * t + 0.5, 1.5 * t2 - t)
    return w, dw


def _bspline_weights(t: float) -> tuple[tuple[float, float, float, float], tuple[float, float, float, float]]:
    """Cubic B-spline weights for coefficients -1, 0, 1, 2 at offset t in [0, 1), and their
    derivatives with respect to t."""
    t2, t3, u = t * t, t * t * t, 1.0 - t
    w = (u * u * u / 6.0, (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0, (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0, t3 / 6.0)
    dw = (-0.5 * u * u, 1.5 * t2 - 2.0 * t, -1.5 * t2 + t + 0.5, 0.5 * t2)
    return w, dw


#: The cubic B-spline's inverse (prefilter) 6 / (z + 4 + 1/z) as a truncated FIR:
#: h[k] = sqrt(3) * (sqrt(3) - 2)^|k|, |k| <= 7 (the tail is below 1e-4).
_BSPLINE_PREFILTER = (math.sqrt(3.0) * (math.sqrt(3.0) - 2.0) ** np.abs(np.arange(-7, 8))).reshape(1, -1)
_BSPLINE_PREFILTER = (_BSPLINE_PREFILTER / _BSPLINE_PREFILTER.sum()).astype(np.float32)


def zncc(a: ArrayLike, b: ArrayLike) -> float:
    """Zero-mean normalised cross-correlation of two equal-shaped patches, in [-1, 1]."""
    a = np.asarray(a, dtype=np.float64).ravel()
    b = np.asarray(b, dtype=np.float64).ravel()
    a = cast(FloatArray, a - a.mean())  # numpy's stubs: Any, which would leave a as the ArrayLike
    b = cast(FloatArray, b - b.mean())
    den = math.sqrt(float(a @ a) * float(b @ b))
    return float(a @ b) / den if den > 0 else 0.0


def _main_lobe(scores: NDArray[np.float32], best: int, lo: int, hi: int) -> tuple[int, int]:
    """Columns ``[l, r]`` of the peak at ``best``: walk out while the scores keep falling (at
    least one column each side)."""
    l = best
    while l - 1 >= lo and (scores[l - 1] < scores[l] or l == best):
        l -= 1
    r = best
    while r + 1 <= hi and (scores[r + 1] < scores[r] or r == best):
        r += 1
    return l, r


def match_strip(
    template: NDArray[np.floating] | NDArray[np.uint8],
    strip: NDArray[np.floating] | NDArray[np.uint8],
    params: MeasureParams,
    lo: int | None = None,
    hi: int | None = None,
    refine: bool = True,
) -> StripMatch:
    """Find a (rectified) template along a (rectified) strip of the same height, sub-pixel.

    ZNCC at every integer column (``cv2.matchTemplate``, ``TM_CCOEFF_NORMED``); the best of
    the candidate columns ``[lo, hi]`` is checked and refined (see the module docstring):

    - beyond range: the best candidate sits on ``lo`` or ``hi`` and the column outside it
      scores higher (or does not exist), so the true peak may lie outside the range;
    - ambiguous: the best candidate outside the main lobe (the monotonic descent around the
      peak) scores within ``params.uniqueness_margin`` of the peak;
    - low score: the refined ZNCC is below ``params.min_score``.

    Args:
        template: (P, P) patch, e.g. the rectified left patch or a tracker's stored template.
        strip: (P, W) rectified strip along the epipolar line, W >= P (both uint8 or float).
        params: matching tunables (``subpixel``, scores, iterations).
        lo, hi: candidate columns (default: all, leaving :data:`STRIP_MARGIN_PX` columns each
            side as margin when the strip is wide enough).
        refine: refine to sub-pixel here (:func:`refine_position`); when False the position is
            the parabola's and ``sigma_px`` NaN, for callers that refine on better-resampled
            data (as :func:`measure_points` does).

    Returns:
        :class:`StripMatch`; ``position_px`` is where ``template`` starts in ``strip``.
    """
    T = np.ascontiguousarray(template)
    S = np.ascontiguousarray(strip)
    if not (T.dtype == S.dtype and T.dtype in (np.uint8, np.float32)):  # what matchTemplate takes
        T, S = T.astype(np.float32), S.astype(np.float32)
    P = T.shape[1]
    n = S.shape[1] - P + 1
    empty = np.zeros(0, np.float32)
    if S.shape[0] != T.shape[0] or n < 1:
        raise ValueError(f"strip {S.shape} cannot hold template {T.shape}")
    scores = cast("NDArray[np.float32]", cv2.matchTemplate(S, T, cv2.TM_CCOEFF_NORMED).ravel())
    if lo is None:
        lo = STRIP_MARGIN_PX if n > 2 * STRIP_MARGIN_PX else 0
    if hi is None:
        hi = n - 1 - STRIP_MARGIN_PX if n > 2 * STRIP_MARGIN_PX else n - 1
    lo, hi = max(lo, 0), min(hi, n - 1)
    if hi < lo:
        return StripMatch(False, REASON_SEARCH_OUTSIDE, math.nan, -1, math.nan, -1.0, math.nan, scores if n else empty)
    cand = scores[lo : hi + 1]
    best = lo + int(np.argmax(cand))
    c0 = float(scores[best])
    rivals = -1.0  # best slant-corrected score of the other candidate peaks
    if params.slant_scales and params.slant_candidates > 1:
        best, c0, rivals = _slant_rescore(T, S, scores, lo, hi, params)

    def refuse(reason: str, score: float = c0, second: float = -1.0) -> StripMatch:
        return StripMatch(False, reason, math.nan, best, score, second, math.nan, scores)

    # A peak on the range's edge is only a peak if the score falls beyond it.
    cb = float(scores[best])
    if (best == lo and (lo == 0 or scores[lo - 1] >= cb)) or (best == hi and (hi == n - 1 or scores[hi + 1] >= cb)):
        return refuse(REASON_BEYOND_RANGE)
    l, r = _main_lobe(scores, best, lo, hi)
    outside = np.concatenate([scores[lo:l], scores[r + 1 : hi + 1]])
    second = max(float(outside.max()) if outside.size else -1.0, rivals)
    if c0 < params.min_score:
        return refuse(REASON_LOW_SCORE, c0, second)
    if second > c0 - params.uniqueness_margin:
        return refuse(REASON_AMBIGUOUS, c0, second)

    # Parabola through the three scores around the peak: the baseline, and the start of the fit.
    cm, cp = float(scores[best - 1]), float(scores[best + 1])
    den = cm - 2.0 * cb + cp
    delta = 0.5 * (cm - cp) / den if den < 0 else 0.0
    x = best + min(max(delta, -0.5), 0.5)
    if not refine:
        return StripMatch(True, None, x, best, c0, second, math.nan, scores)
    x, sigma, score, reason = refine_position(T, S, x, params)
    if reason is not None:
        return refuse(reason, score, second)
    return StripMatch(True, None, x, best, score, second, sigma, scores)


def _slant_rescore(
    T: NDArray[np.generic], S: NDArray[np.generic], scores: NDArray[np.float32], lo: int, hi: int, params: MeasureParams
) -> tuple[int, float, float]:
    """Re-score the best few peaks allowing for a slanted surface.

    On a surface slanted away from the fronto-parallel, the disparity changes across the
    patch and the right patch is the left one stretched horizontally by ``s = 1 - dd/du``
    about its centre. A strongly slanted, regularly textured face (a radiator's tile grid seen
    obliquely) then correlates worse at its true disparity than at a wrong one: measured on
    the simulated mock-up, true 0.70 against a false 0.87. Each of the
    ``params.slant_candidates`` highest local maxima is scored again with the right patch
    resampled (linearly, about its centre) at each of ``params.slant_scales``, and keeps its
    best score. Returns ``(column, score, best score of the other peaks)``.

    Off by default: on the simulated mock-up (estec scenario, three frames, 8 px grid) it cut
    accepted points more than 2 cm off from 123 of 1130 to 93 of 1108, and costs ~0.1 ms a
    point; the rest of those errors are patches straddling depth edges.
    """
    P = T.shape[1]
    inner = scores[lo : hi + 1]
    if inner.size < 3:
        b = lo + int(np.argmax(inner))
        return b, float(scores[b]), -1.0
    peaks = np.flatnonzero((inner[1:-1] >= inner[:-2]) & (inner[1:-1] >= inner[2:])) + 1 + lo
    ends = [e for e in (lo, hi) if scores[e] >= scores[e + 1 if e == lo else e - 1]]
    peaks = np.concatenate([peaks, np.array(ends, dtype=int)]) if ends else peaks
    if peaks.size == 0:
        b = lo + int(np.argmax(inner))
        return b, float(scores[b]), -1.0
    k = min(params.slant_candidates, peaks.size)
    top = peaks[np.argsort(scores[peaks])[::-1][:k]]
    scales = np.array((1.0, *params.slant_scales))
    m = 0.5 * (P - 1)
    # columns of the stretched right patch: centre c + m, offsets (j - m) * s
    pos = top[:, None, None] + m + (np.arange(P)[None, None, :] - m) * scales[None, :, None]
    pos = np.clip(pos, 0.0, S.shape[1] - 1.000001).reshape(-1)
    i0 = pos.astype(np.intp)
    t = pos - i0
    R = S[:, i0] * (1.0 - t) + S[:, i0 + 1] * t  # (rows, k * scales * P), float64
    rows = R.shape[0]
    R = R.reshape(rows, -1, P).transpose(1, 0, 2).reshape(-1, rows * P)  # (k * scales, rows * P)
    R -= R.mean(axis=1, keepdims=True)
    Tc = T.astype(np.float64).ravel()
    Tc -= Tc.mean()
    den = np.sqrt((R * R).sum(axis=1) * float(Tc @ Tc))
    zn = (R @ Tc / np.maximum(den, 1e-12)).reshape(k, len(scales)).max(axis=1)  # (k,)
    order = np.argsort(zn)[::-1]
    b = int(top[order[0]])
    rival = float(zn[order[1]]) if k > 1 else -1.0
    return b, float(zn[order[0]]), rival


def refine_position(
    template: NDArray[np.floating], strip: NDArray[np.floating], x: float, params: MeasureParams
) -> tuple[float, float, float, str | None]:
    """Sub-pixel position of ``template`` in ``strip`` near column ``x`` (see module docstring).

    ``params.subpixel`` selects the Gauss-Newton fit (iterated from ``x``) or the parabola
    baseline (``x`` kept as given); either way the fit at the final position gives the
    standard deviation and the ZNCC, which are checked against ``params.max_sigma_disparity_px``
    and ``params.min_score``.

    Returns:
        ``(x, sigma_x, zncc, reason)``; ``reason`` is None when the position is accepted.
    """
    T = np.asarray(template, dtype=np.float32)
    fit = _ShiftFit(T, strip, params.subpixel_interpolation)
    start = x
    if params.subpixel == "parabola":
        _, _, sigma, score = fit.solve(x)
    else:
        x, sigma, score = _gauss_newton(fit, x, params)
        if not math.isfinite(x) or abs(x - start) > 1.0:
            return math.nan, math.nan, score, REASON_SUBPIXEL
    if not score >= params.min_score:
        return math.nan, math.nan, score, REASON_LOW_SCORE
    if not sigma <= params.max_sigma_disparity_px:
        return math.nan, math.nan, score, REASON_UNCERTAIN
    return x, sigma, score, None


class _ShiftFit:
    """Least-squares fit of a template by a shifted strip window, ``T ≈ a R(x) + c R'(x) + b``.

    ``R(x)`` is cubic interpolation (``kernel``: the cubic B-spline or Keys' cubic
    convolution), a weighted sum of four integer-shifted windows
    ``S_k`` (k = -1..2) with weights ``w(t)``, ``t = x - floor(x)``. All the fit needs are the
    moments of those four windows with each other, with the template and with 1; they are
    computed once per integer position, so each Gauss-Newton step is a few scalar operations.
    """

    def __init__(self, template: NDArray[np.floating], strip: NDArray[np.floating], kernel: str = "bspline") -> None:
        self.t = np.asarray(template, dtype=np.float64).ravel()
        if kernel == "bspline":
            # B-spline coefficients of each row (Unser 1999): interpolating them with the cubic
            # B-spline reproduces the samples exactly and has a far flatter response than Keys.
            self.strip = cv2.filter2D(
                np.asarray(strip, dtype=np.float32), cv2.CV_32F, _BSPLINE_PREFILTER, borderType=cv2.BORDER_REFLECT_101
            )
            self.weights = _bspline_weights
        else:
            self.strip = strip
            self.weights = _keys_weights
        self.P = template.shape[1]
        self.n = self.t.size
        t1 = float(self.t.sum())
        self.t1 = t1
        self.ctt = float(self.t @ self.t) - t1 * t1 / self.n
        self._base: int | None = None

    def _moments(self, i: int) -> tuple[FloatArray, FloatArray]:
        """Centred moments (4x4 with each other, 4 with the template) of the windows
        ``S[:, i-1+k : i-1+k+P]``, k = 0..3. Computed for six windows around the first ``i``
        asked for, so the fit's steps across one integer boundary reuse them."""
        if self._base is None or not (self._base <= i - 1 and i + 2 <= self._base + 5):
            P, S = self.P, self.strip
            width = S.shape[1]
            base = i - 2
            if base >= 0 and base + P + 5 <= width:
                win = S[:, base : base + P + 5]
            else:
                win = S[:, np.clip(np.arange(base, base + P + 5), 0, width - 1)]
            Sk = np.stack([win[:, k : k + P] for k in range(6)]).reshape(6, -1).astype(np.float64)
            s1 = Sk.sum(axis=1)
            # centred moments: removing the means solves for the offset b in closed form
            self._G = Sk @ Sk.T - np.outer(s1, s1) / self.n
            self._h = Sk @ self.t - s1 * (self.t1 / self.n)
            self._base = base
        k = i - 1 - self._base
        return self._G[k : k + 4, k : k + 4], self._h[k : k + 4]

    def solve(self, x: float) -> tuple[float, float, float, float]:
        """Fit at ``x``: ``(a, step, sigma_x, zncc)`` with ``step = c / a`` the Gauss-Newton
        update of ``x``, ``sigma_x`` its standard deviation from the residual, and the ZNCC of
        the template with ``R(x)``."""
        i = math.floor(x)
        G, h = self._moments(i)
        Wm = np.array(self.weights(x - i))  # rows: w, dw
        (cvv, cvd), (_, cdd) = (Wm @ G @ Wm.T).tolist()
        cvt, cdt = (Wm @ h).tolist()
        det = cvv * cdd - cvd * cvd
        if det <= 0 or cvv <= 0 or self.ctt <= 0:
            return math.nan, math.nan, math.nan, math.nan
        a = (cdd * cvt - cvd * cdt) / det
        c = (cvv * cdt - cvd * cvt) / det
        rss = max(self.ctt - (a * cvt + c * cdt), 0.0)
        s2 = rss / max(self.n - 3, 1)
        score = cvt / math.sqrt(cvv * self.ctt)
        if a <= 0:  # anti-correlated: not a match
            return a, math.nan, math.nan, score
        return a, c / a, math.sqrt(s2 * cvv / det) / a, score


def _gauss_newton(fit: _ShiftFit, x: float, params: MeasureParams) -> tuple[float, float, float]:
    """Refine the template's column ``x`` in the strip: solve ``T ≈ a R(x) + c R'(x) + b`` and
    step ``x += c / a`` until the step is below tolerance. Returns ``(x, sigma_x, zncc)``."""
    start = x
    sigma = score = math.nan
    for _ in range(params.subpixel_iterations):
        _, step, sigma, score = fit.solve(x)
        if not math.isfinite(step):
            return math.nan, math.nan, math.nan
        step = min(max(step, -0.5), 0.5)
        x += step
        if abs(x - start) > 1.0:
            return math.nan, math.nan, math.nan
        if abs(step) < params.subpixel_tolerance_px:
            break
    # sigma and score belong to the last fit, less than the tolerance away from x.
    return x, sigma, score


def _weight_polynomials(weights: Any) -> NDArray[np.float64]:
    """(4, 8) coefficients ``C``: ``[t^0..t^3] @ C`` is the weights ``weights(t)`` of samples
    -1..2 followed by their derivatives (both kernels are cubics in t), recovered by sampling
    the scalar functions at four offsets."""
    ts = np.array([0.0, 0.25, 0.5, 0.75])
    V = np.power.outer(ts, np.arange(4))
    w = np.array([weights(t)[0] for t in ts])
    dw = np.array([weights(t)[1] for t in ts])
    return np.concatenate([np.linalg.solve(V, w), np.linalg.solve(V, dw)], axis=1)


_BSPLINE_POLY = _weight_polynomials(_bspline_weights)
_KEYS_POLY = _weight_polynomials(_keys_weights)

#: Fewer points are refined one by one (the array operations' fixed cost outweighs the loop's).
_MIN_BATCH = 4


def refine_positions(
    templates: Sequence[NDArray[np.floating]],
    strips: Sequence[NDArray[np.floating]],
    x: ArrayLike,
    params: MeasureParams,
) -> tuple[FloatArray, FloatArray, FloatArray, list[str | None]]:
    """:func:`refine_position` for many (template, strip, start) at once, same results.

    The Gauss-Newton fit of every point runs in lock step on stacked arrays: the B-spline
    prefilter of all strips of one width in one ``cv2.filter2D`` call (it filters along rows
    only, so stacking rows changes nothing), each step's 4x4 moments and 2x2 solve for all
    points still iterating as array operations, a point leaving the loop exactly when its own
    scalar loop would. The numbers equal the scalar fit's up to the summation order of the
    moment sums (differences ~1e-15 px). The parabola baseline, and fewer than
    :data:`_MIN_BATCH` points, run point by point (:func:`refine_position`).

    Args:
        templates: m (P, P) float patches (one size P).
        strips: m (P, W_j) strips (widths may differ).
        x: (m,) start columns of each template in its strip.

    Returns:
        ``(x, sigma_x, zncc, reasons)``, as :func:`refine_position` per point.
    """
    m = len(templates)
    x_in = np.array(x, dtype=float).reshape(m)
    if m < _MIN_BATCH or params.subpixel != "gauss_newton":
        res = [refine_position(T, S, float(xi), params) for T, S, xi in zip(templates, strips, x_in)]
        return (np.array([r[0] for r in res]), np.array([r[1] for r in res]), np.array([r[2] for r in res]), [r[3] for r in res])
    P = templates[0].shape[1]
    n = P * templates[0].shape[0]
    coef, widths, weight_poly = _strip_coefficients(strips, params.subpixel_interpolation)
    t = np.stack([np.asarray(T, dtype=np.float32) for T in templates]).reshape(m, n).astype(np.float64)
    t1 = t.sum(axis=1)
    ctt = np.einsum("ij,ij->i", t, t) - t1 * t1 / n
    G = np.zeros((m, 6, 6))
    h = np.zeros((m, 6))
    base = np.full(m, np.iinfo(np.int64).min // 4, np.int64)  # no moments yet: always refreshed
    span = np.arange(P + 5)
    x = x_in.copy()
    sigma = np.full(m, np.nan)
    score = np.full(m, np.nan)
    active = np.arange(m)
    failed = np.zeros(m, bool)
    four = np.arange(4)
    with np.errstate(all="ignore"):
        for _ in range(params.subpixel_iterations):
            if active.size == 0:
                break
            xa = x[active]
            i = np.floor(xa).astype(np.int64)
            b = base[active]
            stale = ~((b <= i - 1) & (i + 2 <= b + 5))
            if stale.any():  # moments of the six windows around i, as _ShiftFit._moments
                js = active[stale]
                nb = i[stale] - 2
                cols = np.clip(nb[:, None] + span, 0, widths[js, None] - 1)
                win = np.take_along_axis(coef[js], np.broadcast_to(cols[:, None, :], (js.size, P, P + 5)), axis=2)
                Sk = np.stack([win[:, :, k : k + P] for k in range(6)], axis=1).reshape(js.size, 6, n).astype(np.float64)
                s1 = Sk.sum(axis=2)
                G[js] = Sk @ Sk.transpose(0, 2, 1) - s1[:, :, None] * s1[:, None, :] / n
                h[js] = np.einsum("jkn,jn->jk", Sk, t[js]) - s1 * (t1[js] / n)[:, None]
                base[js] = nb
            k = i - 1 - base[active]
            rows = k[:, None] + four
            Ga = G[active[:, None, None], rows[:, :, None], rows[:, None, :]]
            ha = h[active[:, None], rows]
            # rows w, dw of the kernel's weights at offset t: powers of t times its coefficients
            Wm = (np.power.outer(xa - i, four) @ weight_poly).reshape(-1, 2, 4)
            Q = Wm @ Ga @ Wm.transpose(0, 2, 1)
            r = (Wm @ ha[:, :, None])[:, :, 0]
            cvv, cvd, cdd, cvt, cdt = Q[:, 0, 0], Q[:, 0, 1], Q[:, 1, 1], r[:, 0], r[:, 1]
            det = cvv * cdd - cvd * cvd
            a = (cdd * cvt - cvd * cdt) / det
            c = (cvv * cdt - cvd * cvt) / det
            s2 = np.maximum(ctt[active] - (a * cvt + c * cdt), 0.0) / max(n - 3, 1)
            sig = np.sqrt(s2 * cvv / det) / a
            step = c / a
            good = (det > 0) & (cvv > 0) & (ctt[active] > 0) & (a > 0) & np.isfinite(step)
            sigma[active], score[active] = sig, cvt / np.sqrt(cvv * ctt[active])
            step = np.clip(step, -0.5, 0.5)
            xn = xa + step
            gone = ~good | (np.abs(xn - x_in[active]) > 1.0)
            x[active] = xn
            failed[active[gone]] = True
            active = active[~gone & ~(np.abs(step) < params.subpixel_tolerance_px)]
    x[failed], sigma[failed], score[failed] = np.nan, np.nan, np.nan
    reasons: list[str | None] = []
    for j in range(m):
        if not math.isfinite(x[j]) or abs(x[j] - x_in[j]) > 1.0:
            reasons.append(REASON_SUBPIXEL)
        elif not score[j] >= params.min_score:
            reasons.append(REASON_LOW_SCORE)
        elif not sigma[j] <= params.max_sigma_disparity_px:
            reasons.append(REASON_UNCERTAIN)
        else:
            reasons.append(None)
    bad = np.array([r is not None for r in reasons], bool)
    x[bad], sigma[bad] = np.nan, np.nan
    return x, sigma, score, reasons


def _strip_coefficients(
    strips: Sequence[NDArray[np.floating]], interpolation: str
) -> tuple[NDArray[np.float32], NDArray[np.intp], NDArray[np.float64]]:
    """The strips' interpolation coefficients stacked, zero-padded to the widest, ``(m, rows,
    wmax)``: B-spline coefficients (the rows prefiltered, all strips of one width in one
    ``cv2.filter2D`` call: it filters along rows only) or, for Keys, the samples themselves;
    with the strips' widths (m,) and the kernel's weight polynomials (:func:`_weight_polynomials`)."""
    rows = strips[0].shape[0]
    widths = np.array([S.shape[1] for S in strips], dtype=np.intp)
    coef = np.zeros((len(strips), rows, int(widths.max())), np.float32)
    if interpolation == "bspline":
        for w in np.unique(widths).tolist():
            sel = np.flatnonzero(widths == w)
            stack = np.concatenate([np.asarray(strips[int(j)], dtype=np.float32) for j in sel])
            f = cv2.filter2D(stack, cv2.CV_32F, _BSPLINE_PREFILTER, borderType=cv2.BORDER_REFLECT_101)
            coef[sel, :, :w] = f.reshape(len(sel), rows, w)
        return coef, widths, _BSPLINE_POLY
    for j, S in enumerate(strips):
        coef[j, :, : widths[j]] = S
    return coef, widths, _KEYS_POLY


#: Largest disparity gradient across a patch the slanted fit accepts, px/px. A plane seen 80°
#: from its normal at 3.5 m with the paper's rig changes disparity by ~0.45 px per px.
MAX_DISPARITY_GRADIENT = 0.5


def refine_slanted(
    templates: Sequence[NDArray[np.floating]],
    strips: Sequence[NDArray[np.floating]],
    x: ArrayLike,
    params: MeasureParams,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Sub-pixel position of each template in its strip on a slanted surface, batched.

    On a surface slanted away from the fronto-parallel, the disparity changes across the patch,
    ``d(j, i) = d + g_u (j - c) + g_v (i - c)`` (affine in the rectified image for a plane), and
    a fit of one shift (:func:`refine_positions`) measures a disparity weighted by where the
    patch's texture is (its horizontal gradient energy), not the centre's: a patch whose
    texture sits 1 px off its centre on a plane seen 60° from its normal at 3.5 m (``g_u``
    ~0.14 px/px with the paper's rig) is off by ~0.14 px, 5 mm of depth. Here the gradients
    are fitted with the position, by Gauss-Newton (forward additive; Lucas & Kanade 1981 with
    the warp of "slanted" support windows, Bleyer, Rhemann & Rother 2011, PatchMatch Stereo):

        T(i, j) ≈ a R(i, x + j + g_u (j - c) + g_v (i - c)) + b

    linearised as ``T ≈ a R + b + a dx R' + a dg_u (j - c) R' + a dg_v (i - c) R'`` (five
    unknowns, linear least squares per step), ``c = (P - 1) / 2``, ``R`` the strip row
    interpolated as in :func:`refine_positions`. ``x`` is then the position of the template's
    first column AT ITS CENTRE's disparity (``x + c`` is where the centre lands).

    Two more unknowns cost precision where the patch cannot tell them: at the paper's noise
    (the simulated estec mock-up, read noise 2.52 grey levels, 8x8 patches) the unconstrained
    fit scatters about 1.5 times as much as the shift fit over repeated frames of a still
    scene (single-point depth sigma 6.25 against 3.82 mm, below). So
    the gradients get a Gaussian prior ``g ~ N(0, sg² I)``, ``sg = params.slant_prior_px_per_px``
    (MAP: the penalty ``s² |g|² / sg²`` joins the least squares, ``s²`` the residual variance),
    which holds them near zero unless the patch shows a slant clearly. Its standard deviation
    is the posterior's, ``sigma_x² = s² [(AᵀA + P)⁻¹]_xx / a²``, ``s² = |r|² / (n - 5)``.

    Measured (2026-11-27): on a band-limited texture on a plane at 3.5 m rendered exactly
    through the paper's rig, 1 grey level of noise, the median disparity error at 0/45/60/70°
    of slant is 0.010/0.010/0.016/0.033 px, where the shift fit gives 0.010/0.040/0.078/0.099
    px; with 6 grey levels 0.063/0.051/0.051/0.067 against 0.063/0.059/0.090/0.124 px. The
    estec mock-up's single-point depth sigma at 3.5 m (the simulator's calibration, 4 mm as
    the paper's) is 4.01 mm with ``sg`` = 0.03 px/px, 3.82 with 0.01, 5.65 with 0.1, 6.25
    without the prior and 3.82 with the shift fit alone.

    Args:
        templates: m (P, P) left patches.
        strips: m (P, W_j) right strips, the same rows.
        x: (m,) start columns (e.g. the shift fit's).

    Returns:
        ``(x, sigma_x, zncc, gradient)``: (m,), (m,), (m,) and (m, 2) ``(g_u, g_v)`` px/px;
        NaN where the fit failed (a singular system, a negative gain, a step off the strip,
        or a result more than 1 px from the start or with a gradient over
        :data:`MAX_DISPARITY_GRADIENT`).
    """
    m = len(templates)
    x_in = np.array(x, dtype=float).reshape(m)
    out_x, out_sigma, out_score = np.full(m, np.nan), np.full(m, np.nan), np.full(m, np.nan)
    out_g = np.full((m, 2), np.nan)
    if m == 0:
        return out_x, out_sigma, out_score, out_g
    rows, P = templates[0].shape
    n = rows * P
    coef, widths, weight_poly = _strip_coefficients(strips, params.subpixel_interpolation)
    t = np.stack([np.asarray(T, dtype=np.float64).reshape(n) for T in templates])
    jj = np.tile(np.arange(P) - 0.5 * (P - 1), rows)
    ii = np.repeat(np.arange(rows) - 0.5 * (rows - 1), P)
    row_of = np.repeat(np.arange(rows), P)
    four = np.arange(4)
    x_cur = x_in.copy()
    g = np.zeros((m, 2))
    g_tolerance = params.subpixel_tolerance_px / max(0.5 * (P - 1), 1.0)  # moves a patch corner by the tolerance
    failed = np.zeros(m, bool)
    active = np.arange(m)
    with np.errstate(all="ignore"):
        for _ in range(params.subpixel_iterations):
            if active.size == 0:
                break
            pos = x_cur[active, None] + 0.5 * (P - 1) + jj * (1.0 + g[active, :1]) + ii * g[active, 1:]  # (a, n)
            i0 = np.floor(pos).astype(np.intp)
            off = (i0.min(axis=1) < 1) | (i0.max(axis=1) > widths[active] - 3)
            i0 = np.clip(i0, 1, (widths[active] - 3)[:, None])
            Wm = np.power.outer(pos - i0, four) @ weight_poly  # (a, n, 8): weights of taps -1..2, derivatives
            taps = coef[active[:, None, None], row_of[None, :, None], i0[:, :, None] - 1 + four]  # (a, n, 4)
            val = np.einsum("ank,ank->an", Wm[..., :4], taps)
            der = np.einsum("ank,ank->an", Wm[..., 4:], taps)
            A = np.stack([val, np.ones_like(val), der, der * jj, der * ii], axis=2)  # (a, n, 5)
            AtA = np.einsum("anp,anq->apq", A, A)
            det = np.linalg.det(AtA)
            ok = ~off & np.isfinite(det) & (det > 0)
            AtA[~ok] = np.eye(5)
            Atb = np.einsum("anp,an->ap", A, t[active])
            sol = np.linalg.solve(AtA, Atb[:, :, None])[:, :, 0]
            if params.slant_prior_px_per_px > 0:
                # MAP with g ~ N(0, sg² I): the penalty s² |g + u / a|² / sg² on the increments
                # u = a dg, with the gain a and residual variance s² of the fit without it.
                r0 = t[active] - np.einsum("anp,ap->an", A, sol)
                a0 = np.maximum(sol[:, 0], 1e-9)
                lam = np.einsum("an,an->a", r0, r0) / max(n - 5, 1) / (a0 * params.slant_prior_px_per_px) ** 2
                AtA[:, 3, 3] += lam
                AtA[:, 4, 4] += lam
                Atb[:, 3:] -= (lam * a0)[:, None] * g[active]
                sol = np.linalg.solve(AtA, Atb[:, :, None])[:, :, 0]
            inv = np.linalg.inv(AtA)  # with the prior: the posterior covariance / s²
            gain = sol[:, 0]
            ok &= gain > 0
            resid = t[active] - np.einsum("anp,ap->an", A, sol)
            rss = np.einsum("an,an->a", resid, resid)
            out_sigma[active] = np.sqrt(np.maximum(rss, 0.0) / max(n - 5, 1) * inv[:, 2, 2]) / gain
            vc = val - val.mean(axis=1, keepdims=True)
            tc = t[active] - t[active].mean(axis=1, keepdims=True)
            out_score[active] = np.einsum("an,an->a", vc, tc) / np.sqrt(
                np.einsum("an,an->a", vc, vc) * np.einsum("an,an->a", tc, tc))
            step = sol[:, 2:] / gain[:, None]
            x_cur[active] += np.clip(step[:, 0], -0.5, 0.5)
            g[active] += np.clip(step[:, 1:], -0.1, 0.1)
            ok &= (np.abs(x_cur[active] - x_in[active]) <= 1.0) & np.all(np.abs(g[active]) <= MAX_DISPARITY_GRADIENT, axis=1)
            failed[active[~ok]] = True
            done = (np.abs(step[:, 0]) < params.subpixel_tolerance_px) & np.all(np.abs(step[:, 1:]) < g_tolerance, axis=1)
            active = active[ok & ~done]
    good = ~failed
    out_x[good], out_g[good] = x_cur[good], g[good]
    out_sigma[failed], out_score[failed] = np.nan, np.nan
    return out_x, out_sigma, out_score, out_g


# --------------------------------------------------------------------------- one point


@dataclass(frozen=True)
class _Match:
    reason: str | None
    disparity_px: float = math.nan
    sigma_px: float = math.nan
    score: float = math.nan


def _disparity_range(lo_px: float, hi_px: float) -> tuple[int, int]:
    d_lo = int(math.ceil(lo_px))
    d_hi = int(math.floor(hi_px))
    return d_lo, max(d_hi, d_lo)


def _match_many(
    rect: Rectification,
    left: NDArray[np.uint8],
    right: NDArray[np.uint8],
    uv_rect: FloatArray,
    params: MeasureParams,
    disparity_ranges: Sequence[tuple[float, float]],
) -> list[_Match]:
    """Match rectified left pixels (m, 2) along their rectified right rows, one result each.

    The points go through the stages of a single point's match together, so that each
    stage's resampling is one :func:`sample_rectified_blocks` call for all of them (patches;
    left rows and right strips; the fine strips around the integer matches) and the
    sub-pixel fit one :func:`refine_positions`. A point refused at a stage drops out of the
    later ones; its reason is the one it gets alone (the checks and their order are a single
    point's).
    """
    P = params.patch_size
    W, H = rect.rig.image_size
    half = 0.5 * (P - 1)
    m = len(uv_rect)
    out: list[_Match | None] = [None] * m
    geo: dict[int, tuple[float, float, int, int, float]] = {}
    for j in range(m):
        x0, y0 = float(uv_rect[j, 0]) - half, float(uv_rect[j, 1]) - half
        bx, by = math.floor(x0), math.floor(y0)
        if not (math.isfinite(x0) and math.isfinite(y0)) or bx < 0 or by < 0 or bx + P >= W or by + P >= H:
            out[j] = _Match(REASON_PATCH_OUTSIDE)
        else:
            geo[j] = (x0, y0, bx, by, x0 - bx)

    # Stage 1: the Lanczos patches, texture checks, strip geometry.
    todo = list(geo)
    patches = sample_rectified_blocks(rect, left, 0, [(geo[j][0], geo[j][1], P, P) for j in todo])
    T_fine: dict[int, NDArray[np.float32]] = {}
    strips: dict[int, tuple[int, int, int, int, int, int]] = {}
    T: NDArray[np.float32] | NDArray[np.uint8]  # a Lanczos patch here, a uint8 one in stage 2
    for j, (T, col_ok) in zip(todo, patches):
        if col_ok is not None and not col_ok.all():
            out[j] = _Match(REASON_PATCH_OUTSIDE)
            continue
        mean, std = cv2.meanStdDev(T)
        if float(mean[0, 0]) < params.min_mean_grey:
            out[j] = _Match(REASON_TOO_DARK)
            continue
        if float(std[0, 0]) < params.min_texture_std:
            out[j] = _Match(REASON_TEXTURELESS)
            continue
        gx = (T[:, 1:] - T[:, :-1]).ravel()
        if math.sqrt(float(gx @ gx) / gx.size) < params.min_gradient_rms:
            out[j] = _Match(REASON_NO_EPIPOLAR_TEXTURE)
            continue
        bx = geo[j][2]
        # Right strip: the patch for integer disparity d starts at rectified column x0 - d.
        d_lo, d_hi = _disparity_range(*disparity_ranges[j])
        mg = STRIP_MARGIN_PX
        c_first = max(bx - d_hi - mg, 0)  # strip's first grid column
        c_last = min(bx - d_lo + mg + P - 1, W - 2)  # last grid column (bilinear map needs +1)
        if c_last - c_first + 1 < P:
            out[j] = _Match(REASON_SEARCH_OUTSIDE)
            continue
        # Integer search on bilinearly resampled strips (fast); the sub-pixel fit below
        # resamples just the neighbourhood of the match with Lanczos-4 (accurate). One left strip
        # serves the search template and the left-right check, whose candidates lie within the
        # disparity range's width on either side of the patch.
        spread = d_hi - d_lo
        l_first = max(bx - spread - mg, 0)
        l_last = min(bx + spread + mg + P - 1, W - 2)
        T_fine[j] = T
        strips[j] = (d_lo, d_hi, c_first, c_last, l_first, l_last)

    # Stage 2: the bilinear right strips and left patches, the integer search. The left rows
    # around the patches (for the left-right check) get their maps now but are resampled in
    # stage 4, for the points that get there: the patch is their slice, the same samples.
    todo = list(strips)
    lmx, lmy, lok, _ = _block_maps(
        rect, left.shape, 0, [(strips[j][4] + geo[j][4], geo[j][1], strips[j][5] - strips[j][4] + 1, P) for j in todo], False
    )
    lrow_of = {j: k for k, j in enumerate(todo)}
    tcol = [geo[j][2] - strips[j][4] for j in todo]  # the patch's first column in its left row
    patches8 = _remap_stacked(
        left, [mx[:, c : c + P] for mx, c in zip(lmx, tcol)], [my[:, c : c + P] for my, c in zip(lmy, tcol)], None, cv2.INTER_LINEAR
    )
    rstrips = sample_rectified_blocks(
        rect, right, 1, [(strips[j][2] + geo[j][4], geo[j][1], strips[j][3] - strips[j][2] + 1, P) for j in todo],
        cv2.INTER_LINEAR, exact=False,
    )  # fmt: skip
    found: dict[int, tuple[Any, ...]] = {}
    for j, T, (S, s_ok) in zip(todo, patches8, rstrips):
        bx = geo[j][2]
        d_lo, d_hi, c_first, c_last, l_first, _ = strips[j]
        # Column position x in the strip <-> disparity d = bx - (c_first + x).
        n = S.shape[1] - P + 1
        lo = max(bx - d_hi - c_first, 0)
        hi = min(bx - d_lo - c_first, n - 1)
        if hi < lo:
            out[j] = _Match(REASON_SEARCH_OUTSIDE)
            continue
        if s_ok is not None:  # drop candidates whose right patch leaves the original right image
            valid = np.flatnonzero(_windows_ok(s_ok, P)[lo : hi + 1]) + lo
            if valid.size == 0:
                out[j] = _Match(REASON_SEARCH_OUTSIDE)
                continue
            lo, hi = int(valid[0]), int(valid[-1])
        sm = match_strip(T, S, params, lo, hi, refine=False)
        if not sm.ok:
            reason = sm.reason
            if reason == REASON_BEYOND_RANGE and (
                    (sm.integer_position == lo and bx - (c_first + lo) < d_hi)
                    or (sm.integer_position == hi and bx - (c_first + hi) > d_lo)):
                # The peak is at an end the image's edge set, not the range: the match may lie
                # past the edge (a point near the left image's left edge, a near one), and
                # another range would not find it.
                reason = REASON_MATCH_OFF_IMAGE
            out[j] = _Match(reason, score=sm.score)
            continue
        f_first = max(c_first + sm.integer_position - FINE_MARGIN_PX, 0)
        f_last = min(c_first + sm.integer_position + P - 1 + FINE_MARGIN_PX, W - 2)
        found[j] = (S, sm, lo, hi, f_first, f_last)

    # Stage 3: the sub-pixel fit on Lanczos strips around the matches, before the wider-window
    # check: cheaper, and the most frequent refusal (see the module docstring); neither depends
    # on the other's outcome.
    todo = list(found)
    fine = sample_rectified_blocks(
        rect, right, 1, [(found[j][4] + geo[j][4], geo[j][1], found[j][5] - found[j][4] + 1, P) for j in todo]
    )
    xs, sigmas, fit_scores, fit_reasons = refine_positions(
        [T_fine[j] for j in todo], [f[0] for f in fine],
        [found[j][1].position_px - (found[j][4] - strips[j][2]) for j in todo], params,
    )  # fmt: skip
    # Stage 4: the wider-window check, the left-right check (on the left rows, resampled now
    # for the points still in), the depth-edge check.
    # The checks are independent, so each one's samples are taken for all the points it sees
    # at once; a point's reason is still the first check it fails, in the single-point order.
    plans: dict[int, bool | tuple[Any, ...]] = {}
    for k, j in enumerate(todo):
        if fit_reasons[k] is not None:
            out[j] = _Match(fit_reasons[k], score=float(fit_scores[k]))
        elif params.context_width_px > 0:
            S, sm, lo, hi, _, _ = found[j]
            plans[j] = _context_plan(rect, geo[j][0], geo[j][1], strips[j][2], sm, lo, hi, params)
        else:
            plans[j] = True
    need = [j for j, pl in plans.items() if not isinstance(pl, bool)]
    lcs = sample_rectified_blocks(rect, left, 0, [plans[j][0] for j in need], cv2.INTER_LINEAR, exact=False)  # type: ignore[index]
    scs = sample_rectified_blocks(rect, right, 1, [plans[j][1] for j in need], cv2.INTER_LINEAR, exact=False)  # type: ignore[index]
    for j, (Lc, _), (Sc, _) in zip(need, lcs, scs):
        plans[j] = _context_decide(plans[j], Lc, Sc, params)  # type: ignore[arg-type]
    kept = []
    for k, j in enumerate(todo):
        if j in plans:
            if plans[j]:
                kept.append((k, j))
            else:
                out[j] = _Match(REASON_REPETITIVE, score=found[j][1].score)
    lrows = _remap_stacked(
        left, [lmx[lrow_of[j]] for _, j in kept], [lmy[lrow_of[j]] for _, j in kept], None, cv2.INTER_LINEAR
    )
    edge: dict[int, Any] = {}
    accepted: list[tuple[int, int]] = []  # (k, j) of the points every check accepts
    if params.edge_shift_px > 0:
        for k, j in kept:
            edge[j] = _edge_blocks(rect, geo[j][0], geo[j][1], geo[j][2] - found[j][4] - float(xs[k]), params)
    need = [j for j, eb in edge.items() if eb is not None]
    els = sample_rectified_blocks(rect, left, 0, [edge[j][0] for j in need], cv2.INTER_LINEAR, exact=False)
    ers = sample_rectified_blocks(rect, right, 1, [edge[j][1] for j in need], cv2.INTER_LINEAR, exact=False)
    edge_samples = {j: (L[0], R[0]) for j, L, R in zip(need, els, ers)}
    for (k, j), Lrow in zip(kept, lrows):
        x0, y0, bx, _, _ = geo[j]
        d_lo, d_hi, c_first, _, l_first, _ = strips[j]
        S, sm, lo, hi, f_first, _ = found[j]
        l_ok = lok[lrow_of[j]]
        x, sigma, score = float(xs[k]), float(sigmas[k]), float(fit_scores[k])
        d = bx - f_first - x

        # Left-right check: the right patch at the integer match, searched along the left row.
        d0 = bx - c_first - sm.integer_position
        R0 = S[:, sm.integer_position : sm.integer_position + P]
        r_col = bx - d0  # right patch's first grid column
        # left patch for disparity d starts at column r_col + d, i.e. Lrow column r_col + d - l_first
        l_lo = max(r_col + d_lo - l_first, 0)
        l_hi = min(r_col + d_hi - l_first, Lrow.shape[1] - P)
        if l_hi >= l_lo:
            Lsub = Lrow[:, l_lo : l_hi + P]
            lr_scores = cv2.matchTemplate(Lsub, np.ascontiguousarray(R0), cv2.TM_CCOEFF_NORMED).ravel()
            if l_ok is not None:
                lr_scores = np.where(_windows_ok(l_ok, P)[l_lo : l_hi + 1], lr_scores, -np.inf)
            if np.isfinite(lr_scores.max()):
                d_back = (l_first + l_lo + int(np.argmax(lr_scores))) - r_col
                if abs(d_back - d0) > params.left_right_tolerance_px:
                    out[j] = _Match(REASON_LEFT_RIGHT, score=score)
                    continue
        searched = (bx - c_first - hi, bx - c_first - lo)  # the disparities the search could see
        if params.unseen_rival_check and _rival_unseen(Lrow, l_ok, bx - l_first, d0, searched, (d_lo, d_hi),
                                                        sm.score - params.uniqueness_margin, P):
            out[j] = _Match(REASON_UNSEEN_RIVAL, score=score)
            continue
        if j in edge_samples and not _edge_decide(*edge_samples[j], d, params):
            out[j] = _Match(REASON_DEPTH_EDGE, score=score)
            continue
        out[j] = _Match(None, d, sigma, score)
        accepted.append((k, j))
    if accepted and params.subpixel_slanted and params.subpixel == "gauss_newton":
        # The accepted points' numbers become the slanted fit's (where it converges). The checks
        # above judged the shift fit (its sigma is the aperture test, its disparity the depth-edge
        # test's reference), so the slanted fit changes what an accepted point measures, never
        # which points are accepted (the tracker's selection and the simulator's noise
        # calibration are the shift fit's).
        xsl, ssl, csl, _ = refine_slanted([T_fine[j] for _, j in accepted], [fine[k][0] for k, _ in accepted],
                                          xs[[k for k, _ in accepted]], params)
        for (_, j), xk, sk, ck in zip(accepted, xsl.tolist(), ssl.tolist(), csl.tolist()):
            if math.isfinite(xk) and math.isfinite(sk):  # else the shift fit's numbers stand
                out[j] = _Match(None, geo[j][2] - found[j][4] - xk, sk, ck)
    return out  # type: ignore[return-value]


def _rival_unseen(
    Lrow: NDArray[np.uint8], l_ok: NDArray[np.bool_] | None, t0: int, d: int, searched: tuple[int, int],
    full: tuple[int, int], threshold: float, P: int,
) -> bool:
    """Whether the left patch's own texture repeats at an offset the search could not see.

    Where the disparity range reaches past the right image's edge (or the rectified image's
    crop), the search sees only part of it: a second peak there is never compared, and on a
    repeated texture (a chessboard, a grid of cells) the best VISIBLE peak can be one period
    off the true match, which lies beyond the edge (a rational-model rig rectified with a 10 %
    zoom: 5 of 517 chessboard corners matched two squares off, scores 0.98). A rival at
    disparity ``d + k`` means the right image repeats with period ``k`` there, and so does the
    left one, which still shows it: the patch (at column ``t0`` of its left row ``Lrow``) is
    matched against the row at offsets ``+-k`` for every unsearched ``d + k`` of the ``full``
    range, outside the patch's own main lobe, and a score above ``threshold`` (the match's less
    the uniqueness margin, the second-peak rule) refuses the point.
    """
    lo_cut = range(full[0] - d, searched[0] - d)  # negative offsets, cut at the low end
    hi_cut = range(searched[1] - d + 1, full[1] - d + 1)
    if not lo_cut and not hi_cut:
        return False
    scores = cast("NDArray[np.float32]", cv2.matchTemplate(Lrow, np.ascontiguousarray(Lrow[:, t0 : t0 + P]), cv2.TM_CCOEFF_NORMED).ravel())
    if l_ok is not None:
        scores = np.where(_windows_ok(l_ok, P)[: scores.size], scores, -np.inf)
    left_end, right_end = _main_lobe(scores, t0, 0, scores.size - 1)
    for cut in (lo_cut, hi_cut):
        k = np.abs(np.asarray(cut))
        for cols in (t0 + k, t0 - k):
            cols = cols[(cols >= 0) & (cols < scores.size) & ((cols < left_end) | (cols > right_end))]
            if cols.size and float(scores[cols].max()) > threshold:
                return True
    return False


_EDGE_REACH = 3  # integer disparities the depth-edge check searches either side of round(d)


def _edge_blocks(
    rect: Rectification, x0: float, y0: float, d: float, params: MeasureParams
) -> tuple[tuple[float, float, int, int], tuple[float, float, int, int]] | None:
    """The left and right blocks ``(x0, y0, width, height)`` :func:`_edge_decide` samples, or
    None near the image border (check skipped)."""
    P, sh = params.patch_size, params.edge_shift_px
    W, H = rect.rig.image_size
    bx, by = math.floor(x0), math.floor(y0)
    fx = x0 - bx
    reach = _EDGE_REACH
    di = int(round(d))
    r0 = bx - di - sh - reach  # right block's first grid column
    if bx - sh < 0 or by - sh < 0 or bx + P + sh + 1 >= W or by + P + sh + 1 >= H or r0 < 0 or r0 + P + 2 * (sh + reach) + 1 >= W:
        return None
    # One left and one right block (bilinear, 8 bit: the test needs tenths of a pixel, not
    # hundredths) hold all four windows and their searches.
    return (x0 - sh, y0 - sh, P + 2 * sh, P + 2 * sh), (r0 + fx, y0 - sh, P + 2 * (sh + reach), P + 2 * sh)


def _edge_decide(L: NDArray[np.uint8], R: NDArray[np.uint8], d: float, params: MeasureParams) -> bool:
    """Whether the disparity is that of one (possibly slanted) surface across the patch.

    A patch straddling a depth edge takes the disparity of whichever side has the stronger
    texture, often not that of its centre pixel (on the simulated mock-up: 0.5-2 px errors
    along the silhouettes, ~5 px where a patch on the body catches a thin boom or mast in
    front). The patch is matched again at four windows shifted by ``s = edge_shift_px``
    left, right, up and down ("multiple windows", Fusiello, Roberto & Trucco 1997, used here
    as a test). On a plane the disparity is linear in the
    image, so each opposite pair averages to the patch's own:
    ``|d(-s) + d(+s) - 2 d| <= edge_tolerance_px`` for both axes, whatever the slant; across a
    depth edge one side jumps, or its window has no correlation peak near ``d`` at all, or
    one below ``edge_min_score`` (the window sees another surface): refused too.

    Each window is searched over integer disparities within 3 px of ``d`` on bilinear 8-bit
    samples (``cv2.matchTemplate``) and refined by a parabola: the test needs tenths of a
    pixel, and this costs a fraction of the Gauss-Newton fit (which gave the same figures).

    Measured on three renders of the ``estec`` mock-up (8 px grid, after the wider-window
    check, ``max_sigma_disparity_px`` 0.08): accepted points > 2 cm off 60 of 1063 -> 27 of
    871 (tolerance 0.7 px, s = 3, ZNCC floor 0.5; tolerance 0.5 px: 20 of 741; with
    Gauss-Newton fits and no floor, tolerance 1.0 px: 37 of 994; shifts of 4 px: 14 of 682). Near the image border (the
    shifted windows and their search do not fit) the check is skipped.

    Args:
        L, R: the left and right blocks :func:`_edge_blocks` names, sampled (uint8).
        d: the patch's refined disparity, px.
    """
    P, sh = params.patch_size, params.edge_shift_px
    reach = _EDGE_REACH
    di = int(round(d))
    disp = []
    for dx, dy in ((-sh, 0), (sh, 0), (0, -sh), (0, sh)):
        T = np.ascontiguousarray(L[sh + dy : sh + dy + P, sh + dx : sh + dx + P])
        # window (dx, dy) at disparity di + reach - k starts at right block column sh + dx + k
        S = np.ascontiguousarray(R[sh + dy : sh + dy + P, sh + dx : sh + dx + P + 2 * reach])
        c = cv2.matchTemplate(S, T, cv2.TM_CCOEFF_NORMED).ravel()
        k = int(np.argmax(c))
        if not (0 < k < 2 * reach) or not c[k] >= params.edge_min_score:
            return False  # no peak near d, or a poor one: the window sees another surface
        den = float(c[k - 1]) - 2.0 * float(c[k]) + float(c[k + 1])
        delta = 0.5 * (float(c[k - 1]) - float(c[k + 1])) / den if den < 0 else 0.0
        disp.append(di + reach - (k + delta))
    second = (disp[0] + disp[1] - 2.0 * d, disp[2] + disp[3] - 2.0 * d)
    return all(abs(v) <= params.edge_tolerance_px for v in second)


def _context_plan(
    rect: Rectification, x0: float, y0: float, c_first: int, sm: StripMatch, lo: int, hi: int, params: MeasureParams
) -> bool | tuple[Any, ...]:
    """:func:`_context_decide`'s decision when it needs no samples (True: no rival peak; False:
    no room for the right window), else its left and right blocks ``(x0, y0, width, height)``
    and what :func:`_context_decide` needs."""
    sc = sm.scores
    best = sm.integer_position
    inner = sc[lo : hi + 1]
    if inner.size < 3:
        return True
    peaks = np.flatnonzero((inner[1:-1] >= inner[:-2]) & (inner[1:-1] >= inner[2:])) + 1 + lo
    l, r = _main_lobe(sc, best, lo, hi)
    c0 = float(sc[best])
    # a rival: within context_window of the best, and its ZNCC deficit 1 - c within
    # context_ratio times the best's (a far worse fit than a near-perfect best is no rival)
    floor = max(c0 - params.context_window, 1.0 - params.context_ratio * (1.0 - c0))
    peaks = peaks[((peaks < l) | (peaks > r)) & (sc[peaks] >= floor)]
    if peaks.size == 0:
        return True
    peaks = peaks[np.argsort(sc[peaks])[::-1][: params.context_candidates - 1]]
    cand = np.concatenate([[best], peaks])
    P = params.patch_size
    W, H = rect.rig.image_size
    cw, ch = min(params.context_width_px, W - 3), min(params.context_height_px, H - 3)
    # The window shares the patch's centre, shifted by whole pixels to stay inside the image
    # near its borders (it only has to contain the patch); same fractional offset as the patch.
    fx, fy = x0 - math.floor(x0), y0 - math.floor(y0)
    bx0 = min(max(math.floor(x0) - (cw - P) // 2, 0), W - 2 - cw)
    by0 = min(max(math.floor(y0) - (ch - P) // 2, 0), H - 2 - ch)
    # Right column of window column j for candidate disparity d_c, stretched by s about the
    # patch centre Xc: Xr = Xc - d_c + s (X_j - Xc).
    xc = x0 + 0.5 * (P - 1)
    d_c = math.floor(x0) - c_first - cand  # integer disparity of each candidate
    scales = np.array((1.0, *params.context_scales))
    xr = (xc - d_c)[:, None, None] + scales[None, :, None] * (bx0 + fx + np.arange(cw)[None, None, :] - xc)
    r_lo = max(math.floor(float(xr.min())) - 1, 0)
    r_hi = min(math.ceil(float(xr.max())) + 1, W - 2)
    if r_hi - r_lo < 2:
        return False
    return (bx0 + fx, by0 + fy, cw, ch), (r_lo + fx, by0 + fy, r_hi - r_lo + 1, ch), xr, r_lo + fx, len(cand), len(scales)


def _context_decide(plan: tuple[Any, ...], Lc: NDArray[np.uint8], S: NDArray[np.uint8], params: MeasureParams) -> bool:
    """Whether a wider window confirms the patch's best peak over its other strong peaks.

    An 8x8 patch on a regular texture (a radiator's tile grid, a solar panel's cells) matches
    one period away nearly as well as at the truth, and on an obliquely seen face
    foreshortening lowers the true peak below a false one (measured on the simulated mock-up:
    0.70 against 0.87), so neither the margin of :func:`match_strip` nor the left-right check
    (the wrong right patch matches back to the same left patch) can tell. A window of
    ``context_width_px`` x ``context_height_px`` around the same centre reaches the pattern's
    irregularities and borders. It is scored at each peak outside the best one's main lobe
    that comes within ``context_window`` of the best and whose deficit ``1 - c`` is at most
    ``context_ratio`` times the best's (at most ``context_candidates`` in all),
    the right window stretched horizontally about the patch's centre by each of ``context_scales``
    (and 1) so that a slanted face is not penalised, keeping each peak's best ZNCC (bilinear
    resampling: it only ranks peaks). The best peak is confirmed when its score beats every
    other candidate's by ``context_margin``. Only the decision uses the wide window: the
    disparity is still fitted on the small patch, whose smaller footprint keeps it off depth
    edges.

    Measured on three frames of the ``estec`` scenario (8 px grid, as ``python -m benchmarks
    measure``, ``max_sigma_disparity_px`` 0.08): accepted points more than 2 cm off fall from
    123 of 1130 to 60 of 1063, those more than 10 cm off (false matches several px away) from 88 to 25; most of the rest are
    patches straddling depth edges (:func:`_edge_decide`). A smaller ``context_window`` (0.15)
    leaves 71; ``context_ratio`` 8 changes nothing there (5: a few more) but spares the check
    on most well-textured points, whose best peak is near-perfect. Near the image border the
    window is shifted inward by whole pixels (it only has to contain the patch).

    Args:
        plan: what :func:`_context_plan` returned for the patch (its blocks and candidates).
        Lc, S: the left window and the right strip block it names, sampled (uint8).

    Returns:
        True when the wide window prefers the best peak (the no-rival case is decided by the plan).
    """
    (_, _, cw, ch), _, xr, s_first, n_cand, n_scales = plan
    # every (candidate, scale) window side by side, resampled in one bilinear remap
    pos = np.clip(xr - s_first, 0.0, S.shape[1] - 1.0).astype(np.float32).reshape(1, -1)
    rows = np.arange(ch, dtype=np.float32).reshape(-1, 1)
    R = cv2.remap(S, np.repeat(pos, ch, axis=0), np.repeat(rows, pos.shape[1], axis=1), cv2.INTER_LINEAR)
    R = R.astype(np.float32).reshape(ch, -1, cw).transpose(1, 0, 2).reshape(-1, ch * cw)
    R -= R.mean(axis=1, keepdims=True)
    Tc = Lc.astype(np.float32).ravel()
    Tc -= Tc.mean()
    den = np.sqrt(np.einsum("ij,ij->i", R, R) * float(Tc @ Tc))
    zn = (R @ Tc / np.maximum(den, 1e-12)).reshape(n_cand, n_scales).max(axis=1)
    return bool(zn[0] >= float(zn[1:].max()) + params.context_margin)


def _windows_ok(col_ok: NDArray[np.bool_], P: int) -> NDArray[np.bool_]:
    """Per window start: all ``P`` columns valid."""
    return np.convolve(col_ok.astype(np.int32), np.ones(P, np.int32), "valid") == P


# --------------------------------------------------------------------------- points


def check_stereo_pair(rig: StereoRig, left: NDArray[Any], right: NDArray[Any]) -> None:
    """Raise :class:`TrackmeterError` unless both images are (H, W) uint8 of the rig's size and
    the rig is side by side (:func:`~trackmeter.core.stereo.check_side_by_side`)."""
    check_side_by_side(rig)
    W, H = rig.image_size
    for name, img in (("left", left), ("right", right)):
        arr = np.asarray(img)
        if arr.ndim != 2 or arr.dtype != np.uint8:
            raise TrackmeterError(f"{name} image must be 8-bit grey (H, W) uint8, got {arr.dtype} {arr.shape}")
        if arr.shape != (H, W):
            raise TrackmeterError(f"{name} image is {arr.shape[1]}x{arr.shape[0]} px but the rig expects {W}x{H}")


def measure_points(
    rig: StereoRig,
    left: NDArray[np.uint8],
    right: NDArray[np.uint8],
    uv_left: ArrayLike,
    params: MeasureParams | None = None,
    disparity_range_px: ArrayLike | None = None,
) -> tuple[PointMeasurement, ...]:
    """Measure the 3D points at pixels of the left image (paper section 2.A).

    For each pixel: rectify it (``rig.rectification``, cached), match its P x P patch along the
    rectified right row (:func:`_match_many`; all pixels stage by stage together, see
    the module docstring), triangulate (``Rectification.triangulate``)
    and propagate the disparity's standard deviation (paper eqs. 1-2,
    ``Rectification.point_covariance``) — ``params.sigma_disparity_px``, or when 0 the fit's own
    estimate floored at ``params.min_sigma_disparity_px``.

    Args:
        rig: the calibrated stereo rig.
        left, right: (H, W) uint8 ORIGINAL (unrectified) images of the rig's size.
        uv_left: (N, 2) pixels of the original left image, px (centre of top-left pixel = 0, 0).
        params: matching tunables (default :class:`MeasureParams`).
        disparity_range_px: optional (N, 2) or (2,) ``[min, max]`` disparity searched per point,
            px, instead of ``params.disparity_range_px`` — e.g. a tracker's predicted
            disparity ± a margin: a narrower search is faster and less often ambiguous. A
            peak on its edge is refused as beyond range, as with the global range.

    Returns:
        One :class:`PointMeasurement` per pixel, in order. Refused points carry a reason and
        NaN numbers.

    Raises:
        TrackmeterError: images of the wrong type or size, or pixels not (2,) or (N,2).
    """
    params = params or MeasureParams()
    check_stereo_pair(rig, left, right)
    uv = as_rows(uv_left, "uv_left", 2).copy()  # a copy: its rows are handed out
    n = len(uv)
    if n == 0:
        return ()
    if disparity_range_px is None:
        ranges = [params.disparity_range_px(rig.rectification)] * n
    else:
        rng_arr = np.broadcast_to(np.asarray(disparity_range_px, dtype=float), (n, 2))
        if not np.all(np.isfinite(rng_arr)) or np.any(rng_arr[:, 1] < rng_arr[:, 0]):
            raise TrackmeterError("disparity_range_px must be finite [min, max] pairs with min <= max")
        empty = np.flatnonzero(np.ceil(rng_arr[:, 0]) > np.floor(rng_arr[:, 1]))
        if len(empty):
            # The search is over whole disparities: a range between two would be searched at
            # the next one up, outside it, and every point refused as beyond the range.
            lo, hi = rng_arr[empty[0]]
            raise TrackmeterError(f"disparity_range_px [{lo:g}, {hi:g}] holds no whole number of px: "
                                  "the search is over whole disparities")
        ranges = [(float(a), float(b)) for a, b in rng_arr]
    rect = rig.rectification
    inside = [inside_image(u, v, rig.image_size) for u, v in uv.tolist()]
    W, H = rig.image_size
    if all(inside):
        uv_rect = rect.rectify_points(uv, 0)
    else:
        uv_rect = np.full((n, 2), np.nan)
        if any(inside):
            uv_rect[inside] = rect.rectify_points(uv[inside], 0)

    reasons: list[str | None] = [REASON_OUTSIDE_IMAGE] * n
    scores = [math.nan] * n
    disp = np.full(n, np.nan)
    sig_d = np.full(n, np.nan)
    todo = [i for i in range(n) if inside[i]]
    for i, m in zip(todo, _match_many(rect, left, right, uv_rect[todo], params, [ranges[i] for i in todo])):
        reasons[i], scores[i] = m.reason, m.score
        if m.reason is None:
            disp[i], sig_d[i] = m.disparity_px, m.sigma_px
        elif m.reason == REASON_PATCH_OUTSIDE and _patch_inside(uv[i], params.patch_size, W, H):
            # Inside the image the user sees: say why it is refused (alpha 0 keeps only pixels
            # both rectified views hold, so a distorted or zoomed rig loses a border).
            reasons[i] = REASON_PATCH_CROPPED

    right_uv = np.full((n, 2), np.nan)
    xyz = np.full((n, 3), np.nan)
    cov = np.full((n, 3, 3), np.nan)
    idx = [i for i in range(n) if reasons[i] is None]
    if idx:
        if params.sigma_disparity_px > 0:
            sig_d[idx] = params.sigma_disparity_px
        else:  # the fit's own estimate, floored (a NaN estimate becomes infinite: no confidence)
            est = sig_d[idx]
            sig_d[idx] = np.where(est == est, np.fmax(est, params.min_sigma_disparity_px), np.inf)
        xyz[idx] = rect.triangulate(uv_rect[idx], disp[idx])
        # Disparity <= 0, or within 3 sigma of 0 (e.g. the same image given twice): the point
        # may lie at infinity, and its "depth" would be any number the noise makes of it.
        near_zero = (disp - rect.disparity_offset_px) <= 3.0 * np.where(np.isfinite(sig_d), sig_d, 0.0)
        at_infinity = [i for i in idx if not math.isfinite(xyz[i, 2]) or near_zero[i]]
        for i in at_infinity:
            reasons[i] = REASON_BEYOND_RANGE
        if at_infinity:
            idx = [i for i in idx if reasons[i] is None]
    if idx:
        right_rect = uv_rect[idx]  # fancy indexing: a copy
        right_rect[:, 0] -= disp[idx]
        right_uv[idx] = rect.unrectify_points(right_rect, 1)
        cov[idx] = rect.point_covariance(uv_rect[idx], disp[idx], sig_d[idx], params.sigma_uv_px)
    sigma = axis_sigmas(cov)
    for arr in (uv, uv_rect, right_uv, xyz, cov, sigma):
        arr.flags.writeable = False  # rows are handed out as read-only views

    out = []
    for i in range(n):
        if reasons[i] is None:
            pm = PointMeasurement(
                uv[i], True, None, uv_rect[i], right_uv[i], float(disp[i]), float(sig_d[i]),
                xyz[i], sigma[i], cov[i], float(scores[i]),
            )
        else:
            pm = PointMeasurement(
                uv[i], False, reasons[i], uv_rect[i], _NAN2, math.nan, math.nan, _NAN3, _NAN3, _NAN33, float(scores[i])
            )
        out.append(pm)
    return tuple(out)


def inside_image(u: float, v: float, image_size: tuple[int, int]) -> bool:
    """Whether pixel ``(u, v)`` lies on a ``(width, height)`` image: pixel centres are whole
    numbers, so the image spans ``[-0.5, width - 0.5] x [-0.5, height - 0.5]``. NaN is outside."""
    width, height = image_size
    return -0.5 <= u <= width - 0.5 and -0.5 <= v <= height - 0.5


def _patch_inside(uv: FloatArray, patch_size: int, width: int, height: int) -> bool:
    """Whether the ``patch_size`` square centred on ``uv`` (2,) lies inside a width x height
    image with room for its samples' interpolation (Lanczos-4 reaches 4 pixels past a cell;
    one more for the rectification's rounding): a patch refused that far inside was refused
    by the rectified geometry, not by the image's edge."""
    half = 0.5 * (patch_size - 1)
    bx, by = math.floor(float(uv[0]) - half), math.floor(float(uv[1]) - half)
    m = 5
    return bx >= m and by >= m and bx + patch_size + m < width and by + patch_size + m < height


def _frozen_nan(*shape: int) -> FloatArray:
    a = np.full(shape, np.nan)
    a.flags.writeable = False
    return a


_NAN2, _NAN3, _NAN33 = _frozen_nan(2), _frozen_nan(3), _frozen_nan(3, 3)


def measurements_to_json(measurements: Sequence[PointMeasurement]) -> list[dict[str, Any]]:
    """The ``trackmeter measure --json`` list (DESIGN.md section 6)."""
    return [m.to_json() for m in measurements]
