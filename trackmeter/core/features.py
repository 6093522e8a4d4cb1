"""Automatic selection of the points to track (paper section 2.B), three methods, one interface.

- ``"gabor"``: a Gabor-wavelet directional filter bank (``cv2.getGaborKernel``, quadrature
  pairs at several orientations and wavelengths). The energy ``sqrt(even² + odd²)`` of each
  orientation (max over wavelengths) says how strongly the neighbourhood varies across that
  direction; a good feature answers strongly in at least two directions (corners, blobs,
  crossings), so its score is the ``min_directions``-th largest orientation energy. An edge
  answers in one direction only and scores low: it would slide along itself (aperture problem).
- ``"centroid"``: the centroid point of the bright target against black space (largest bright
  connected regions first, image moments).
- ``"shi_tomasi"``: ``cv2.goodFeaturesToTrack`` (Shi & Tomasi 1994, min eigenvalue), the baseline.

Whatever the method, the points are on the target (their whole patch, plus a margin, is
brighter than black space), spread over it (at least ``min_distance_px`` apart and from the
excluded points), away from the border, and — when a right image is given — stereo-matchable:
unique along their epipolar line (:func:`trackmeter.core.patch_tracking.match_epipolar`).

Selection runs inside the tracker's 25 Hz step, so its cost matters (``benchmarks/select.py``):
the Gabor bank is filtered with separable 1D passes (the same numbers as the 2D kernels, ~7-10x
cheaper), only on the bounding box of the selectable pixels; the greedy spreading uses one k-d
tree query; and the stereo check scores the whole epipolar line of all candidates at once with
``cv2.remap`` and batched ZNCC, in score order until enough pass (:func:`stereo_matchable`),
optionally over a narrower disparity range the caller knows (``disparity_range_px``).
"""

from __future__ import annotations

import weakref
from collections.abc import Iterator
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import cast

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from trackmeter.core.params import check_params, param
from trackmeter.core.stereo import Rectification, StereoRig
from trackmeter.errors import TrackmeterError

FloatArray = NDArray[np.float64]

METHODS = ("gabor", "centroid", "shi_tomasi")

#: Beyond any image's diagonal, and within what OpenCV's drawing and corner calls take as a C
#: int: a distance past 2^31 px (a typo in a config file) crashed the process inside OpenCV.
MAX_DISTANCE_PX = 1e5


@dataclass(frozen=True)
class FeatureParams:
    """Tunables of automatic feature selection."""

    method: str = param("gabor", "selection method: gabor, centroid or shi_tomasi", choices=METHODS)
    count: int = param(16, "number of targets automatic selection keeps alive", min=1, max=1024)
    patch_size: int = param(8, "side of the patch a selected point must be trackable with, px", min=3, max=63)
    min_distance_px: float = param(20.0, "minimum distance between selected points (and from existing targets), px",
                                   min=0.0, max=MAX_DISTANCE_PX)
    border_px: int = param(16, "no selection closer than this to the image border, px", min=0)
    black_level: int = param(16, "grey level at or below which a pixel is black space (black_snr 0)", min=0, max=254)
    black_snr: float = param(
        10.0, "> 0: a pixel is on the target when the mean of its 5x5 neighbourhood exceeds the sky level "
        "(the 5th percentile of those means) by this many of the mean's noise sigmas (the image's noise, "
        "estimated by noise_sigma_grey), when black_level leaves nothing selectable: a target in deep "
        "shadow is still a target; 0: black_level only", min=0.0,
    )
    target_margin_px: int = param(3, "the patch grown by this margin must lie entirely on the bright target, px", min=0)
    gabor_wavelengths_px: tuple[float, ...] = param((4.0, 8.0), "Gabor wavelengths (scales), px", min=2.0)
    gabor_orientations: int = param(4, "number of Gabor orientations over 180 degrees", min=2, max=16)
    gabor_pyramid: bool = param(False, "filter wavelengths of 2^l times the smallest on pyramid level l (half resolution, ...): faster, approximate")
    min_directions: int = param(2, "a good feature answers strongly in at least this many directions", min=1, max=16)
    quality: float = param(0.05, "keep candidates scoring at least this fraction of the best score", min=0.0, max=1.0)
    candidates_factor: int = param(10, "candidates stereo-checked per requested point", min=1, max=100)
    min_depth_m: float = param(1.0, "nearest depth searched when checking stereo matchability, m", min=0.01)
    max_depth_m: float = param(50.0, "farthest depth searched when checking stereo matchability, m", min=0.02)
    stereo_min_score: float = param(0.85, "ZNCC a selected point must reach along its epipolar line", min=-1.0, max=1.0)
    uniqueness_margin: float = param(0.1, "the best epipolar match must beat every other peak by this ZNCC", min=0.0, max=2.0)
    stereo_refine: bool = param(False, "also confirm each selected point with the sub-pixel epipolar match (match_epipolar), not only its integer ZNCC profile along the line")
    stereo_min_span_px: float = param(64.0, "a disparity range given to the stereo check is widened to at least this span, px", min=1.0)

    def __post_init__(self) -> None:
        check_params(self)  # declared ranges and choices first (trackmeter.core.params)
        # Refused here, not on every selection of a running tracker, where they would fail far
        # from the cause (an empty bank has no score; a crossed depth range no disparity).
        if not self.gabor_wavelengths_px:
            raise TrackmeterError("gabor_wavelengths_px needs at least one wavelength")
        if not self.min_depth_m < self.max_depth_m:
            raise TrackmeterError(f"min_depth_m ({self.min_depth_m:g}) must be below max_depth_m ({self.max_depth_m:g})")


@lru_cache(maxsize=8)
def gabor_bank(wavelengths_px: tuple[float, ...], orientations: int) -> tuple[tuple[tuple[NDArray, NDArray], ...], ...]:
    """Quadrature Gabor pairs ``[orientation][wavelength] = (even, odd)`` (zero-mean even part).

    Bandwidth of about one octave: ``sigma = 0.56 lambda``, aspect ratio 1
    (Daugman 1985; ``cv2.getGaborKernel``). The 2D reference of the separable filtering that
    :func:`gabor_directional_energy` actually runs.
    """
    bank = []
    for k in range(orientations):
        theta = np.pi * k / orientations
        scales = []
        for lam in wavelengths_px:
            sigma = 0.56 * lam
            ksize = _gabor_ksize(sigma)
            even = cv2.getGaborKernel((ksize, ksize), sigma, theta, lam, 1.0, 0.0, ktype=cv2.CV_32F)
            odd = cv2.getGaborKernel((ksize, ksize), sigma, theta, lam, 1.0, np.pi / 2, ktype=cv2.CV_32F)
            even -= even.mean()
            scales.append((even, odd))
        bank.append(tuple(scales))
    return tuple(bank)


def _gabor_ksize(sigma: float) -> int:
    return int(2 * np.ceil(2.5 * sigma) + 1)


@dataclass(frozen=True)
class _SeparableGabor:
    """One wavelength, one orientation ``theta`` and, when ``mirror`` is set, ``pi - theta`` too.

    With aspect ratio 1 the complex Gabor kernel factorises,
    ``exp(-(x²+y²)/2σ²) exp(i k (x cos θ + y sin θ)) = r(x) c(y)`` with
    ``r(x) = exp(-x²/2σ²) exp(i k x cos θ)`` and ``c(y) = exp(-y²/2σ²) exp(i k y sin θ)``, so
    ``Z = c ⊛_y (r ⊛_x I)``: 1D passes of ``ksize`` taps instead of one 2D pass of ``ksize²``
    (the even part is ``Re Z``, the odd ``∓Im Z``). ``π - θ`` only conjugates ``r`` (``cos``
    changes sign, ``sin`` does not), so it reuses all four passes of ``θ`` with other signs.
    The even kernel's mean (removed so flat grey answers 0) is ``Re(Σr Σc) / ksize²``, taken off
    with one box sum shared by all orientations of the wavelength.
    """

    orientation: int
    mirror: int | None
    row_re: NDArray[np.float32]  # (1, ksize)
    row_im: NDArray[np.float32] | None  # None where it is zero (theta = 90 degrees)
    col_re: NDArray[np.float32]  # (ksize, 1)
    col_im: NDArray[np.float32] | None  # None where it is zero (theta = 0)
    even_mean: float
    mirror_even_mean: float


@lru_cache(maxsize=8)
def _separable_bank(wavelengths_px: tuple[float, ...], orientations: int) -> tuple[tuple[int, tuple[_SeparableGabor, ...]], ...]:
    """Per wavelength ``(ksize, filters)``: the bank of :func:`gabor_bank` as separable factors."""
    out = []
    for lam in wavelengths_px:
        sigma = 0.56 * lam
        ksize = _gabor_ksize(sigma)
        x = np.arange(ksize, dtype=np.float64) - ksize // 2
        g = np.exp(-(x**2) / (2 * sigma**2))
        wavenumber = 2 * np.pi / lam
        filters = []
        for o in range(orientations // 2 + 1):
            mirror = orientations - o
            mirror_o = mirror if 0 < o < mirror < orientations else None
            theta = np.pi * o / orientations
            r = g * np.exp(1j * wavenumber * np.cos(theta) * x)
            c = g * np.exp(1j * wavenumber * np.sin(theta) * x)
            # cos(90°) is 6e-17, not 0: drop imaginary factors that are rounding noise.
            r_im = r.imag if np.abs(r.imag).max() > 1e-9 * np.abs(r.real).max() else None
            c_im = c.imag if np.abs(c.imag).max() > 1e-9 * np.abs(c.real).max() else None
            sr, sc = r.sum(), c.sum()
            filters.append(
                _SeparableGabor(
                    orientation=o,
                    mirror=mirror_o,
                    row_re=r.real.astype(np.float32)[None, :],
                    row_im=None if r_im is None else r_im.astype(np.float32)[None, :],
                    col_re=c.real.astype(np.float32)[:, None],
                    col_im=None if c_im is None else c_im.astype(np.float32)[:, None],
                    even_mean=float((sr * sc).real) / ksize**2,
                    mirror_even_mean=float((np.conj(sr) * sc).real) / ksize**2,
                )
            )
        out.append((ksize, tuple(filters)))
    return tuple(out)


def _binomial_response(cycles_per_px: float) -> float:
    """Amplitude response of ``cv2.pyrDown``'s 1D smoothing ``[1 4 6 4 1]/16`` at a frequency."""
    w = 2 * np.pi * cycles_per_px
    return float((6 + 8 * np.cos(w) + 2 * np.cos(2 * w)) / 16)


@lru_cache(maxsize=8)
def _gabor_plan(wavelengths_px: tuple[float, ...], orientations: int, pyramid: bool) -> tuple[tuple[int, int, tuple[_SeparableGabor, ...], tuple[float, ...]], ...]:
    """Per wavelength ``(level, ksize, filters, gain per orientation)``.

    With ``pyramid``, a wavelength ``2^l`` times the smallest one is filtered on pyramid level
    ``l`` (``cv2.pyrDown`` ``l`` times) with the kernel of wavelength ``lambda / 2^l``: the same
    octave band on ``4^l`` times fewer pixels with ``2^l`` times shorter kernels (a 25-tap
    8 px-wavelength pass becomes a 13-tap pass on a quarter of the pixels). The energy is
    scaled back by ``4^l`` (a level-l pixel averages ``4^l`` pixels) over the pyramid
    smoothing's response at the band's centre frequency along the orientation.
    """
    lam_min = min(wavelengths_px)
    plan = []
    for lam in wavelengths_px:
        level = int(np.floor(np.log2(lam / lam_min) + 1e-9)) if pyramid else 0
        lam_l = lam / 2**level
        ((ksize, filters),) = _separable_bank((lam_l,), orientations)
        gains = []
        for o in range(orientations):
            theta = np.pi * o / orientations
            h = 1.0
            for j in range(level):  # level j's pixels are 2^j px: the frequency in its units
                h *= _binomial_response(2**j * np.cos(theta) / lam) * _binomial_response(2**j * np.sin(theta) / lam)
            gains.append(4.0**level / h)
        plan.append((level, ksize, filters, tuple(gains)))
    return tuple(plan)


def _iter_directional_energy(img: NDArray[np.float32], wavelengths_px: tuple[float, ...], orientations: int,
                             pyramid: bool = False) -> Iterator[tuple[int, NDArray[np.float32]]]:
    """Yield ``(orientation, energy (H,W))`` for every orientation, max over wavelengths."""
    levels: dict[int, dict[int, NDArray[np.float32]]] = {}
    images = [img]

    def f(a: NDArray[np.float32], k: NDArray[np.float32]) -> NDArray[np.float32]:
        # The default border (reflect-101) of the 2D reference, applied per axis: the same.
        return cast("NDArray[np.float32]", cv2.filter2D(a, cv2.CV_32F, k))

    for level, ksize, filters, gains in _gabor_plan(wavelengths_px, orientations, pyramid):
        while len(images) <= level:
            images.append(cast("NDArray[np.float32]", cv2.pyrDown(images[-1])))
        im = images[level]
        energies = levels.setdefault(level, {})

        def fold(o: int, even: NDArray[np.float32], odd: NDArray[np.float32] | None) -> None:
            mag = cast("NDArray[np.float32]", cv2.magnitude(even, odd)) if odd is not None else np.abs(even)
            if level > 0:
                mag *= np.float32(gains[o])
            if o in energies:
                np.maximum(energies[o], mag, out=energies[o])
            else:
                energies[o] = mag

        box = cv2.boxFilter(im, cv2.CV_32F, (ksize, ksize), normalize=False)
        for s in filters:
            h_re = f(im, s.row_re)
            h_im = None if s.row_im is None else f(im, s.row_im)
            rr = f(h_re, s.col_re)
            ii = None if h_im is None or s.col_im is None else f(h_im, s.col_im)
            ri = None if s.col_im is None else f(h_re, s.col_im)
            ir = None if h_im is None else f(h_im, s.col_re)
            # Z = (rr - ii) + i (ri + ir); the mirror (pi - theta): (rr + ii) + i (ri - ir).
            even = rr if ii is None else rr - ii
            odd = ri if ir is None else (ir if ri is None else ri + ir)
            fold(s.orientation, cast("NDArray[np.float32]", cv2.scaleAdd(box, -s.even_mean, even)), odd)
            if s.mirror is not None:
                even_m = rr if ii is None else rr + ii
                odd_m = ri if ir is None else (-ir if ri is None else ri - ir)
                fold(s.mirror, cast("NDArray[np.float32]", cv2.scaleAdd(box, -s.mirror_even_mean, even_m)), odd_m)
    h, w = img.shape
    for o in range(orientations):
        out: NDArray[np.float32] | None = None
        for level in sorted(levels):
            e = levels[level][o]
            for _ in range(level):
                # pyrUp puts level-l pixel i back on pixel 2i, where pyrDown took it from
                # (cv2.resize would shift it by half a pixel), at 1/4 of warpAffine's cost.
                e = cast("NDArray[np.float32]", cv2.pyrUp(e, dstsize=(2 * e.shape[1], 2 * e.shape[0])))
            if level > 0:
                e = e[:h, :w]
            out = e if out is None else np.maximum(out, e, out=out)
        assert out is not None
        yield o, out


def gabor_directional_energy(image: NDArray, wavelengths_px: tuple[float, ...], orientations: int, pyramid: bool = False) -> NDArray[np.float32]:
    """Directional energy (orientations, H, W): per orientation, the max over wavelengths of the
    quadrature energy ``sqrt(even² + odd²)`` of the image filtered with :func:`gabor_bank`
    (``cv2.filter2D`` correlation, reflect-101 border).

    Computed with separable 1D passes (:class:`_SeparableGabor`): equal to the 2D filtering to
    float32 rounding, ~10x cheaper for the 25x25 kernels of an 8 px wavelength. With
    ``pyramid`` the longer wavelengths are filtered on a half-resolution (quarter, ...)
    pyramid level (:func:`_gabor_plan`): an approximation of the same energies (median error
    ~5 % where they are strong) at about half the cost again — but it re-ranks the
    candidates: on 50 estec frames the tracker accepted 31 % of 16 pyramid-selected points
    against 36 % of the exact ones, so selection does not use it by default.
    """
    img = np.ascontiguousarray(image, dtype=np.float32)
    out = np.empty((orientations, *img.shape), np.float32)
    for o, e in _iter_directional_energy(img, tuple(float(w) for w in wavelengths_px), int(orientations), pyramid):
        out[o] = e
    return out


def gabor_score(image: NDArray, params: FeatureParams) -> NDArray[np.float32]:
    """Per-pixel Gabor feature score (H,W): the ``min_directions``-th largest directional energy."""
    img = np.ascontiguousarray(image, dtype=np.float32)
    wl = tuple(float(w) for w in params.gabor_wavelengths_px)
    n_o = int(params.gabor_orientations)
    k = min(params.min_directions, n_o)
    energies = _iter_directional_energy(img, wl, n_o, params.gabor_pyramid)
    if k == 1:
        top = np.zeros(img.shape, np.float32)
        for _, e in energies:
            np.maximum(top, e, out=top)
        return top
    if k == 2:
        # Running top two, no sort over the orientation axis: second = max(second, min(first, e)),
        # started from the first two orientations (energies are >= 0, so this equals starting
        # from zeros, with four fewer passes over the image).
        _, e0 = next(energies)
        _, e1 = next(energies)
        first = np.maximum(e0, e1)
        second = np.minimum(e0, e1, out=e1)
        low = np.empty_like(first)
        for _, e in energies:
            np.maximum(second, np.minimum(first, e, out=low), out=second)
            np.maximum(first, e, out=first)
        return second
    stack = np.stack([e for _, e in energies])
    return np.partition(stack, n_o - k, axis=0)[n_o - k]


def noise_sigma_grey(image: NDArray) -> float:
    """Standard deviation of the image's pixel noise, grey levels, from the image alone.

    Immerkaer's estimator (*Fast noise variance estimation*, CVIU 64(2), 1996): the kernel
    ``N = [[1,-2,1],[-2,4,-2],[1,-2,1]]`` (the difference of two Laplacians) cancels a locally
    linear image, so ``I * N`` is mostly noise, with variance ``36 sigma²`` for white noise of
    variance ``sigma²``. Robust variant: the median of ``|I * N|`` (of the interior, every second
    row and column) over ``6 * 0.6745`` (the normal's median absolute value), so the texture and
    edges of a target covering less than half the image do not count as noise.
    """
    img = np.asarray(image, dtype=np.float32)
    if img.shape[0] < 3 or img.shape[1] < 3:
        return 0.0
    r = cv2.filter2D(img, -1, _IMMERKAER, borderType=cv2.BORDER_REPLICATE)[1:-1:2, 1:-1:2]
    return float(np.median(np.abs(r))) / (6.0 * 0.6744897501960817)


_IMMERKAER = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)


def bright_pixels(image: NDArray, params: FeatureParams, snr: bool = False) -> NDArray[np.uint8]:
    """1 where a pixel is on the target, 0 on black space: above ``black_level``, or with ``snr``
    (and ``black_snr`` > 0) its 5x5 mean above the sky level by ``black_snr`` noise sigmas."""
    img = np.asarray(image)
    if not snr or params.black_snr <= 0:
        return (img > params.black_level).astype(np.uint8)
    m = cv2.blur(img.astype(np.float32), (5, 5), borderType=cv2.BORDER_REPLICATE)
    sky = float(np.percentile(m[::4, ::4], 5.0))
    # The 5x5 mean of white noise of std sigma has std sigma / 5.
    return (m > sky + params.black_snr * noise_sigma_grey(img) / 5.0).astype(np.uint8)


def target_mask(image: NDArray, params: FeatureParams) -> NDArray[np.uint8]:
    """255 where a patch (plus margin) centred on the pixel lies entirely on the bright target.

    Black space is what ``black_level`` says; only when that leaves no selectable pixel at all
    (the target in deep shadow, the exposure set by glints) and ``black_snr`` > 0 is it told
    by its signal-to-noise ratio instead (:func:`bright_pixels`): on estec the signal-to-noise
    test everywhere accepted dim parts an 8x8 patch cannot track (false locks 0 -> 30-39 of
    500 frames), so it is the fallback of a dark image, not the rule."""
    return _target_pixels(image, params)[1]


def _target_pixels(image: NDArray, params: FeatureParams) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """The bright map :func:`target_mask` chose (:func:`bright_pixels`, 1 on the target) and
    the mask it made of it (255 where a patch fits)."""
    if np.asarray(image).size == 0:
        empty = np.zeros(np.asarray(image).shape[:2], np.uint8)
        return empty, empty
    bright = bright_pixels(image, params)
    mask = _patch_mask(bright, params)
    if params.black_snr > 0 and not mask.any():
        bright = bright_pixels(image, params, snr=True)
        mask = _patch_mask(bright, params)
    return bright, mask


#: Why automatic selection found nothing, where the image itself leaves no pixel selectable
#: (:func:`nothing_selectable_reason`).
NOTHING_LIT = ("nothing lit to select on: no patch-sized area brighter than black space (the target out of "
               "view, in deep shadow, or underexposed)")
NO_ROOM = "no room for a patch: features.target_margin_px or features.border_px leave no pixel of the lit target"


def nothing_selectable_reason(image: NDArray, params: FeatureParams) -> str | None:
    """Why no pixel of ``image`` is selectable (:data:`NOTHING_LIT` or :data:`NO_ROOM`), or None
    where :func:`target_mask` leaves some. Asked only once a selection came back empty, so that
    a setting that leaves nothing (``target_margin_px: 400``) is named, and only then: a lit
    area a patch fits in without the margin and the border is what the settings took away; a
    dark image's few lit specks (noise, a sliver in shadow) are not."""
    if target_mask(image, params).any():
        return None
    bare = replace(params, target_margin_px=0, border_px=0)
    return NO_ROOM if target_mask(image, bare).any() else NOTHING_LIT


def erode_square(mask: NDArray[np.uint8], radius_px: int) -> NDArray[np.uint8]:
    """``mask`` (H,W) eroded by the (2r+1) x (2r+1) square, outside the image counted as 0: a
    pixel stays only where the whole square around it lies inside the image on non-zero pixels.

    A square wider than the image leaves nothing; that is said without building its kernel
    (a radius of 100000 px, a typo in a config file, would allocate 40 GB).
    """
    r = int(radius_px)
    if 2 * r + 1 > min(mask.shape[:2]):
        return np.zeros_like(mask)
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * r + 1, 2 * r + 1))
    return cast("NDArray[np.uint8]", cv2.erode(mask, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0))


def _patch_mask(bright: NDArray[np.uint8], params: FeatureParams) -> NDArray[np.uint8]:
    mask = erode_square(bright, params.patch_size // 2 + params.target_margin_px)
    b = params.border_px
    if b > 0:
        mask[:b] = 0
        mask[-b:] = 0
        mask[:, :b] = 0
        mask[:, -b:] = 0
    return mask * 255


def _exclusion(mask: NDArray[np.uint8], exclude_uv: FloatArray, radius: float) -> NDArray[np.uint8]:
    """``mask`` with a disc of ``radius`` px cleared around each point of ``exclude_uv`` (M,2).

    The radius is held to the image's diagonal, and a point farther than it outside the image
    is skipped: what OpenCV draws with must fit a C int (a diverged target's pixel, 3e9, was a
    bare cv2.error)."""
    mask = mask.copy()
    h, w = mask.shape[:2]
    r = int(np.ceil(min(radius, float(np.hypot(h, w)) + 1.0)))
    for u, v in exclude_uv:
        if np.isfinite(u) and np.isfinite(v) and -r <= u <= w + r and -r <= v <= h + r:
            cv2.circle(mask, (int(round(u)), int(round(v))), r, 0, -1)
    return mask


#: Up to this many candidates, :func:`spread` lists every one's neighbours in one query (at
#: most a few million entries even on a plateau); beyond, only the kept points' are asked.
SPREAD_BATCH_MAX_POINTS = 2000


def spread(points: FloatArray, scores: FloatArray, min_distance_px: float, limit: int) -> FloatArray:
    """Greedy non-maximum suppression: best-scoring points first, each at least
    ``min_distance_px`` from those already kept; at most ``limit`` points (N,2).

    Neighbours closer than ``min_distance_px`` come from k-d tree queries
    (``scipy.spatial.cKDTree.query_ball_point``): every candidate's at once for a frame's few
    hundred (one query, half the time), the kept points' only beyond
    :data:`SPREAD_BATCH_MAX_POINTS`, where listing every candidate's neighbours took 20 GB (a
    plateau of 370k candidates at 20 px).
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(pts) == 0 or limit <= 0:
        return np.zeros((0, 2))
    order = np.argsort(-np.asarray(scores, dtype=float), kind="stable")
    pts = pts[order]
    if min_distance_px <= 0:
        return pts[:limit]
    tree = cKDTree(pts)
    # Strictly closer than min_distance_px suppresses (a point exactly at it is kept).
    radius = np.nextafter(min_distance_px, 0.0)
    free = np.ones(len(pts), bool)
    batch = tree.query_ball_point(pts, radius) if len(pts) <= SPREAD_BATCH_MAX_POINTS else None
    kept: list[int] = []
    for i in range(len(pts)):
        if free[i]:
            kept.append(i)
            if len(kept) >= limit:
                break
            free[batch[i] if batch is not None else tree.query_ball_point(pts[i], radius)] = False
    return pts[kept]


def _gabor_region(mask: NDArray[np.uint8], params: FeatureParams) -> tuple[int, int, int, int] | None:
    """``(x0, y0, x1, y1)``: the bounding box of the selectable pixels plus the filters' reach
    (kernel, pyramid smoothing and up-sampling, in full-resolution px), its corner on the
    coarsest pyramid level's grid; None when nothing is selectable."""
    bx, by, bw, bh = cv2.boundingRect(mask)
    if bw == 0 or bh == 0:
        return None
    plan = _gabor_plan(tuple(float(w) for w in params.gabor_wavelengths_px), params.gabor_orientations, params.gabor_pyramid)
    pad = max((ksize // 2 + 3) * 2**level for level, ksize, _, _ in plan)
    grid = 2 ** max(level for level, _, _, _ in plan)
    x0, x1 = max((bx - pad) // grid * grid, 0), min(bx + bw + pad, mask.shape[1])
    y0, y1 = max((by - pad) // grid * grid, 0), min(by + bh + pad, mask.shape[0])
    return x0, y0, x1, y1


#: The Gabor score below which a pixel has no texture: a flat image scores floating-point
#: residue (1.3e-4 at grey 255, 3e-5 at 128), a step of one grey level about 1, a real
#: sensor's noise about 10 (sigma 0.5 grey) to 50 (2.5). Without it every pixel of a saturated
#: or blank frame was a candidate, each a local maximum of a flat score.
GABOR_MIN_SCORE = 0.01


def _candidates_gabor(left: NDArray, mask: NDArray[np.uint8], params: FeatureParams, limit: int) -> FloatArray:
    # Filter only the bounding box of the selectable pixels: every selectable pixel's score is
    # the whole image's.
    region = _gabor_region(mask, params)
    if region is None:
        return np.zeros((0, 2))
    x0, y0, x1, y1 = region
    m = mask[y0:y1, x0:x1]
    score = gabor_score(np.asarray(left)[y0:y1, x0:x1], params)
    np.copyto(score, np.float32(0.0), where=m == 0)
    best = float(score.max())
    if best <= GABOR_MIN_SCORE:
        return np.zeros((0, 2))
    peak = cv2.dilate(score, np.ones((5, 5), np.uint8))
    ys, xs = np.nonzero((score >= peak) & (score >= params.quality * best) & (score > GABOR_MIN_SCORE))
    pts = np.column_stack([xs + x0, ys + y0]).astype(float)
    return spread(pts, score[ys, xs].astype(float), params.min_distance_px, limit)


def _candidates_shi_tomasi(left: NDArray, mask: NDArray[np.uint8], params: FeatureParams, limit: int) -> FloatArray:
    pts = cv2.goodFeaturesToTrack(
        np.asarray(left, np.uint8),
        maxCorners=int(limit),
        qualityLevel=max(params.quality, 1e-4),
        minDistance=params.min_distance_px,
        mask=mask,
        blockSize=max(3, params.patch_size // 2 * 2 + 1),
    )
    return np.zeros((0, 2)) if pts is None else pts.reshape(-1, 2).astype(float)


def corners_near(image: NDArray, uv: ArrayLike, radius_px: float, limit: int = 4,
                 quality: float = 0.05) -> FloatArray:
    """Shi-Tomasi corners (``cv2.goodFeaturesToTrack``, 5 px blocks) within ``radius_px`` of
    the pixel ``uv`` (2,) of a grey ``image``, nearest first, at most ``limit``: (K, 2) px.

    Where an operator's click is refused (a patch without a unique stereo match, an edge that
    would slide along itself), a corner a few pixels away often is trackable: these are the
    places to try instead. ``quality`` is relative to the strongest corner in the neighbourhood.
    """
    u, v = (float(x) for x in np.asarray(uv, dtype=float).reshape(2))
    img = np.asarray(image)
    h, w = img.shape[:2]
    if radius_px <= 0 or not (np.isfinite(u) and np.isfinite(v)) or not (-radius_px <= u < w + radius_px
                                                                       and -radius_px <= v < h + radius_px):
        return np.zeros((0, 2))
    margin = int(np.ceil(radius_px)) + 4  # the corner measure looks 2-3 px around each pixel
    x0, y0 = max(int(u) - margin, 0), max(int(v) - margin, 0)
    x1, y1 = min(int(u) + margin + 1, w), min(int(v) + margin + 1, h)
    if x1 - x0 < 5 or y1 - y0 < 5:
        return np.zeros((0, 2))
    crop = np.ascontiguousarray(img[y0:y1, x0:x1], dtype=np.uint8)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    mask = (((xx - u) ** 2 + (yy - v) ** 2) <= radius_px**2).astype(np.uint8) * 255
    pts = cv2.goodFeaturesToTrack(crop, maxCorners=4 * int(limit), qualityLevel=quality, minDistance=2,
                                  mask=mask, blockSize=5)
    if pts is None:
        return np.zeros((0, 2))
    pts = pts.reshape(-1, 2).astype(float) + [x0, y0]
    order = np.argsort(np.hypot(pts[:, 0] - u, pts[:, 1] - v), kind="stable")
    return cast(FloatArray, pts[order[: int(limit)]])


def _candidates_centroid(left: NDArray, mask: NDArray[np.uint8], params: FeatureParams, limit: int) -> FloatArray:
    """The centroids of the bright regions (largest first) that fall on ``mask``, at least
    ``min_distance_px`` apart. The regions are those of the bright map the mask was made from
    (:func:`target_mask`: a dim target's signal-to-noise map, not black_level's nothing)."""
    bright = _target_pixels(left, params)[0]
    if bright.size == 0:
        return np.zeros((0, 2))
    n_labels, labels, stats, centroids = cv2.connectedComponentsWithStats(bright, connectivity=8)
    order = np.argsort(-stats[1:, cv2.CC_STAT_AREA]) + 1  # label 0 is black space
    pts, areas = [], []
    for label in order:
        if stats[label, cv2.CC_STAT_AREA] < params.patch_size**2:
            break
        c = centroids[label]
        u, v = int(round(c[0])), int(round(c[1]))
        if 0 <= v < mask.shape[0] and 0 <= u < mask.shape[1] and mask[v, u]:
            pts.append(c)
            areas.append(float(stats[label, cv2.CC_STAT_AREA]))
    if not pts:
        return np.zeros((0, 2))
    # A ring round a disc has its centroid on the disc's: one point, not the same one twice.
    return spread(np.array(pts, dtype=float), np.array(areas), params.min_distance_px, limit)


def select_features(
    left: NDArray,
    right_or_none: NDArray | None,
    rig: StereoRig | None,
    n: int,
    method: str,
    params: FeatureParams,
    exclude_uv: ArrayLike = (),
    disparity_range_px: tuple[float, float] | None = None,
) -> FloatArray:
    """Up to ``n`` points (N,2), left ORIGINAL image px, good to track, best first.

    Args:
        left: (H,W) uint8 left image.
        right_or_none: (H,W) uint8 right image; when given (with ``rig``), only points with a
            unique, strong match along their epipolar line are returned.
        rig: the stereo rig (needed for the stereo check).
        n: how many points.
        method: ``"gabor"``, ``"centroid"`` or ``"shi_tomasi"``.
        params: selection tunables.
        exclude_uv: (M,2) existing targets: nothing within ``min_distance_px`` of them.
        disparity_range_px: optional ``(low, high)`` disparity (px, rectified,
            ``d = u_left - u_right``) the stereo check searches instead of the whole
            ``[min_depth_m, max_depth_m]`` range, e.g. around the disparities of the targets
            already tracked on the object. See :func:`stereo_matchable`.

    The candidates (up to ``candidates_factor * n``, best first) are stereo-checked in score
    order until ``n`` pass (:func:`stereo_matchable` with ``need=n``, and its sub-pixel second
    stage when ``params.stereo_refine``): the result is the first ``n`` that pass, as if all
    had been checked.

    Raises:
        TrackmeterError: unknown method, malformed ``disparity_range_px``.
    """
    if method not in METHODS:
        raise TrackmeterError(f"unknown feature selection method {method!r} (known: {', '.join(METHODS)})")
    if n <= 0:
        return np.zeros((0, 2))
    stereo = right_or_none is not None and rig is not None
    if stereo and disparity_range_px is not None:
        _check_disparity_range(disparity_range_px)
    excl = np.asarray(exclude_uv, dtype=float).reshape(-1, 2)
    mask = _exclusion(target_mask(left, params), excl, params.min_distance_px)
    limit = n * params.candidates_factor if right_or_none is not None else n
    finder = {"gabor": _candidates_gabor, "centroid": _candidates_centroid, "shi_tomasi": _candidates_shi_tomasi}[method]
    cand = finder(left, mask, params, limit)
    if not stereo or len(cand) == 0:
        return cand[:n]
    assert right_or_none is not None and rig is not None
    ok = stereo_matchable(left, right_or_none, rig, cand, params, disparity_range_px, need=n, refine=params.stereo_refine)
    return cand[ok][:n]


def disparity_range(rig: StereoRig, min_depth_m: float, max_depth_m: float) -> tuple[float, float]:
    """Disparities (low, high) of depths ``max_depth_m`` and ``min_depth_m``, px (``d = f b / z``)."""
    rect = rig.rectification
    fb = rect.focal_px * rect.baseline_m
    return fb / max_depth_m + rect.disparity_offset_px, fb / min_depth_m + rect.disparity_offset_px


def _check_disparity_range(disparity_range_px: tuple[float, float]) -> tuple[float, float]:
    r = np.asarray(disparity_range_px, dtype=float).reshape(-1)
    if r.shape != (2,) or not np.all(np.isfinite(r)) or r[1] < r[0]:
        raise TrackmeterError(f"disparity_range_px must be a finite (low, high) pair with low <= high, got {disparity_range_px!r}")
    return float(r[0]), float(r[1])


def search_disparities(rig: StereoRig, params: FeatureParams, disparity_range_px: tuple[float, float] | None = None) -> tuple[float, float]:
    """Disparity range (low, high) px the stereo check searches.

    The whole ``[min_depth_m, max_depth_m]`` range, or ``disparity_range_px`` widened about
    its centre to at least ``stereo_min_span_px`` — a narrow range could hide the second peak
    of a repetitive texture and let an ambiguous point pass as unique — and clipped to the
    whole range and to the image width.
    """
    full_lo, full_hi = disparity_range(rig, params.min_depth_m, params.max_depth_m)
    lo, hi = full_lo, full_hi
    if disparity_range_px is not None:
        lo, hi = _check_disparity_range(disparity_range_px)
        if hi - lo < params.stereo_min_span_px:
            c = 0.5 * (lo + hi)
            lo, hi = c - 0.5 * params.stereo_min_span_px, c + 0.5 * params.stereo_min_span_px
        lo, hi = max(lo, full_lo), min(hi, full_hi)
    return float(np.floor(lo)), min(hi, rig.image_size[0] - 1.0)


_COMPLEX_MAPS: weakref.WeakKeyDictionary[Rectification, tuple[NDArray[np.complex64], NDArray[np.complex64]]] = weakref.WeakKeyDictionary()


def _complex_maps(rect: Rectification) -> tuple[NDArray[np.complex64], NDArray[np.complex64]]:
    """The rectification maps as complex tables (one gather per sample instead of two), once per rig."""
    from trackmeter.core.patch_tracking import complex_map

    maps = _COMPLEX_MAPS.get(rect)
    if maps is None:
        maps = _COMPLEX_MAPS[rect] = (complex_map(*rect.maps[0]), complex_map(*rect.maps[1]))
    return maps


def _remap_points(image: NDArray[np.float32], mapping: tuple[NDArray[np.float32], NDArray[np.float32]], x: NDArray[np.float32], y: NDArray[np.float32]) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """``image`` sampled (bilinear) at rectified pixels ``x, y`` (2D float32 arrays) through the
    rectified → original ``mapping`` (the map itself interpolated, as
    :func:`trackmeter.core.patch_tracking.sample_points` does) — two ``cv2.remap`` passes, where
    the numpy gathers cost ~10x more. ``inside`` as ``sample_points``'s: the point is inside
    both the map and the image."""
    h, w = image.shape
    mh, mw = mapping[0].shape
    mx = cv2.remap(mapping[0], x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=-1.0)
    my = cv2.remap(mapping[1], x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=-1.0)
    inside = (x >= 0) & (x <= mw - 1) & (y >= 0) & (y <= mh - 1) & (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)
    return cast("NDArray[np.float32]", cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)), inside


def _epipolar_profile(
    left: NDArray[np.float32], right: NDArray[np.float32], rect: Rectification, cl: FloatArray, d_low: int, span: int, size: int
) -> tuple[FloatArray, NDArray[np.int64]]:
    """The integer stage of :func:`~trackmeter.core.patch_tracking.match_epipolar`: ZNCC (N, span+1)
    of each rectified left patch at ``cl`` with the rectified right row at disparities
    ``d_low + span - k`` (column k; -1 where the window leaves the images), and the best column.

    The same samples (patch centres, strip positions, map interpolation) as ``match_epipolar``,
    taken with ``cv2.remap`` and scored for all points at once: the scores agree with it to
    ~1e-4 (OpenCV quantises remap positions to 1/32 px) at ~1/10 of its cost per point, most
    of which is its numpy gathers along the 300 px line.
    """
    n = len(cl)
    half = (size - 1) / 2.0
    offs = np.arange(size, dtype=np.float64) - half
    width = span + size
    left_map, right_map = rect.maps
    tx = np.broadcast_to(cl[:, 0, None, None] + offs[None, None, :], (n, size, size)).reshape(n * size, size).astype(np.float32)
    ty = np.broadcast_to(cl[:, 1, None, None] + offs[None, :, None], (n, size, size)).reshape(n * size, size).astype(np.float32)
    templates, _ = _remap_points(left, left_map, tx, ty)
    x_first = cl[:, 0] - (d_low + span) - half
    sx = np.broadcast_to(x_first[:, None, None] + np.arange(width)[None, None, :], (n, size, width)).reshape(n * size, width).astype(np.float32)
    sy = np.broadcast_to(cl[:, 1, None, None] + offs[None, :, None], (n, size, width)).reshape(n * size, width).astype(np.float32)
    strips, inside = _remap_points(right, right_map, sx, sy)
    s = strips.reshape(n, size, width).astype(np.float64)
    t: FloatArray = templates.reshape(n, size * size).astype(np.float64)
    t -= t.mean(axis=1, keepdims=True)
    t = t.reshape(n, size, size)
    # ZNCC of every window, in float64 like match_epipolar: the numerator is a sum over the
    # template's columns of batched (1 x size) @ (size x K) products (the template is
    # zero-mean, so the window's mean drops out); the windows' sums and sums of squares are
    # differences of running sums along the strip.
    k = span + 1
    num = np.zeros((n, k))
    for j in range(size):
        num += np.matmul(t[:, None, :, j], s[:, :, j : j + k])[:, 0]
    zero = np.zeros((n, 1))
    c1 = np.concatenate([zero, np.cumsum(s.sum(axis=1), axis=1)], axis=1)
    c2 = np.concatenate([zero, np.cumsum((s * s).sum(axis=1), axis=1)], axis=1)
    w1 = c1[:, size:] - c1[:, :-size]
    w2 = c2[:, size:] - c2[:, :-size]
    den = np.sqrt(np.maximum(w2 - w1 * w1 / (size * size), 0.0) * (t * t).sum(axis=(1, 2))[:, None])
    col_ok = np.concatenate([np.zeros((n, 1), np.int64), np.cumsum(inside.reshape(n, size, width).all(axis=1), axis=1)], axis=1)
    valid = (col_ok[:, size:] - col_ok[:, :-size]) == size
    with np.errstate(divide="ignore", invalid="ignore"):
        scores = np.where(valid & (den > 1e-9), num / den, -1.0)
    return scores, scores.argmax(axis=1)


def stereo_matchable(
    left: NDArray,
    right: NDArray,
    rig: StereoRig,
    uv: FloatArray,
    params: FeatureParams,
    disparity_range_px: tuple[float, float] | None = None,
    need: int | None = None,
    refine: bool = True,
) -> NDArray[np.bool_]:
    """Whether each left point (N,2) has a strong, unique match along its epipolar line:
    :func:`trackmeter.core.patch_tracking.match_epipolar` over :func:`search_disparities`.

    Done in two stages with the same result. First the integer ZNCC along the whole searched
    line for every point (:func:`_epipolar_profile`, cheap): a point whose best score is
    below ``stereo_min_score``, whose second peak (outside ±``patch_size/2`` of the best)
    comes within ``uniqueness_margin`` of it, or whose best is at the edge of the range fails
    here — the majority on repetitive texture. The survivors then go through
    ``match_epipolar`` itself (score, sub-pixel LK convergence, epipolar residual, refined
    score) on a short range around their peak, where its own uniqueness test repeats the
    first stage's locally. The first stage fails only points beyond ``1e-3`` ZNCC of a
    threshold (its scores agree with ``match_epipolar``'s to ~1e-4); points within that
    tolerance are re-checked over the whole range. On the estec frames the result equals
    ``match_epipolar`` over the whole range for every candidate, at ~1/5 of its cost.

    Args:
        need: stop once this many points (in the order given) have passed; the points after
            the last one checked are reported False. None: check all.
        refine: run the second stage; without it a point passes on the first stage alone
            (strong, unique integer peak inside the range; only points within the tolerance
            go through ``match_epipolar``). On the estec frames ~0.6 % of those then fail
            the sub-pixel checks; the call costs ~3 ms less (``match_epipolar``'s fixed cost).
    """
    from trackmeter.core.patch_tracking import match_epipolar

    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    ok = np.zeros(len(uv), bool)
    rect = rig.rectification
    lo, hi = search_disparities(rig, params, disparity_range_px)
    if len(uv) == 0 or hi <= lo:
        return ok
    d_low, span, size = int(lo), int(np.ceil(hi - lo)), params.patch_size
    n = len(uv)
    cl = rect.rectify_points(uv, 0)
    left_f = np.asarray(left, np.float32)
    right_f = np.asarray(right, np.float32)
    maps = _complex_maps(rect)
    lc, rc = np.ascontiguousarray(left), np.ascontiguousarray(right)
    r = max(size // 2, 2)
    tol = 1e-3
    # Second-stage window: +-2 patches around the peak, slid inside the searched range (the
    # peak is never at its edge: the first stage refuses those at the range's edges).
    w_span = min(4 * size, span)
    passed = 0
    start = 0
    pending: list[tuple[int, int, bool]] = []  # first-stage survivors: (point, window low, borderline)
    while need is None or passed < need:
        want = n if need is None else need - passed + 1
        while len(pending) < want and start < n:
            # With ``need``, the first stage too runs on chunks in the given order, a few times
            # the points still missing (on repetitive texture most candidates are ambiguous).
            stop = n if need is None else min(n, start + max(8, 3 * want))
            chunk = np.arange(start, stop)
            start = stop
            scores, k_best = _epipolar_profile(left_f, right_f, rect, cl[chunk], d_low, span, size)
            best = scores[np.arange(len(chunk)), k_best]
            far = np.abs(np.arange(span + 1)[None, :] - k_best[:, None]) > r
            second = np.where(far, scores, -1.0).max(axis=1)
            unique_by = best - params.uniqueness_margin - second
            survive = (best >= params.stereo_min_score - tol) & (unique_by >= -tol) & (k_best > 0) & (k_best < span)
            # Within the tolerance of a threshold the first stage cannot decide: whole range again.
            borderline = (best < params.stereo_min_score + tol) | (unique_by < tol)
            w_lo = np.clip(d_low + span - k_best - w_span // 2, d_low, d_low + span - w_span)
            pending.extend((int(chunk[i]), d_low if borderline[i] else int(w_lo[i]), bool(borderline[i])) for i in np.flatnonzero(survive))
        if not pending:
            break
        # The survivors pass at ~0.99: one batch of what is still missing (and one spare).
        batch, pending = pending[:want], pending[want:]
        if not refine:
            sure = [i for i, _, b in batch if not b]
            ok[sure] = True
            passed += len(sure)
        for wide in (False, True) if refine else (True,):
            sel = [(i, w) for i, w, b in batch if b == wide]
            if not sel:
                continue
            pts = np.array([i for i, _ in sel])
            m = match_epipolar(
                lc,
                rc,
                maps[0],
                maps[1],
                cl[pts],
                np.array([w for _, w in sel], dtype=float),
                span if wide else w_span,
                size,
                min_score=params.stereo_min_score,
                uniqueness_margin=params.uniqueness_margin,
                epipolar_tolerance_px=1.0,
            )
            ok[pts] = m.ok
            passed += int(m.ok.sum())
    return ok
