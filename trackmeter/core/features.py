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
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from trackmeter.core.params import param
from trackmeter.core.stereo import StereoRig
from trackmeter.errors import TrackmeterError

FloatArray = NDArray[np.float64]

METHODS = ("gabor", "centroid", "shi_tomasi")


@dataclass(frozen=True)
class FeatureParams:
    """Tunables of automatic feature selection."""

    method: str = param("gabor", "selection method: gabor, centroid or shi_tomasi", choices=METHODS)
    count: int = param(16, "number of targets automatic selection keeps alive", min=1, max=1024)
    patch_size: int = param(8, "side of the patch a selected point must be trackable with, px", min=3, max=63)
    min_distance_px: float = param(20.0, "minimum distance between selected points (and from existing targets), px", min=0.0)
    border_px: int = param(16, "no selection closer than this to the image border, px", min=0)
    black_level: int = param(16, "grey level at or below which a pixel is black space", min=0, max=254)
    target_margin_px: int = param(3, "the patch grown by this margin must lie entirely on the bright target, px", min=0)
    gabor_wavelengths_px: tuple[float, ...] = param((4.0, 8.0), "Gabor wavelengths (scales), px", min=2.0)
    gabor_orientations: int = param(4, "number of Gabor orientations over 180 degrees", min=2, max=16)
    min_directions: int = param(2, "a good feature answers strongly in at least this many directions", min=1, max=16)
    quality: float = param(0.05, "keep candidates scoring at least this fraction of the best score", min=0.0, max=1.0)
    candidates_factor: int = param(10, "candidates stereo-checked per requested point", min=1, max=100)
    min_depth_m: float = param(1.0, "nearest depth searched when checking stereo matchability, m", min=0.01)
    max_depth_m: float = param(50.0, "farthest depth searched when checking stereo matchability, m", min=0.02)
    stereo_min_score: float = param(0.85, "ZNCC a selected point must reach along its epipolar line", min=-1.0, max=1.0)
    uniqueness_margin: float = param(0.1, "the best epipolar match must beat every other peak by this ZNCC", min=0.0, max=2.0)


@lru_cache(maxsize=8)
def gabor_bank(wavelengths_px: tuple[float, ...], orientations: int) -> tuple[tuple[tuple[NDArray, NDArray], ...], ...]:
    """Quadrature Gabor pairs ``[orientation][wavelength] = (even, odd)`` (zero-mean even part).

    Bandwidth of about one octave: ``sigma = 0.56 lambda``, aspect ratio 1
    (Daugman 1985; ``cv2.getGaborKernel``).
    """
    bank = []
    for k in range(orientations):
        theta = np.pi * k / orientations
        scales = []
        for lam in wavelengths_px:
            sigma = 0.56 * lam
            ksize = int(2 * np.ceil(2.5 * sigma) + 1)
            even = cv2.getGaborKernel((ksize, ksize), sigma, theta, lam, 1.0, 0.0, ktype=cv2.CV_32F)
            odd = cv2.getGaborKernel((ksize, ksize), sigma, theta, lam, 1.0, np.pi / 2, ktype=cv2.CV_32F)
            even -= even.mean()
            scales.append((even, odd))
        bank.append(tuple(scales))
    return tuple(bank)


def gabor_directional_energy(image: NDArray, wavelengths_px: tuple[float, ...], orientations: int) -> NDArray[np.float32]:
    """Directional energy (orientations, H, W): per orientation, the max over wavelengths of the
    quadrature energy ``sqrt(even² + odd²)`` of the filtered image."""
    img = np.asarray(image, dtype=np.float32)
    out = np.zeros((orientations, *img.shape), np.float32)
    for k, scales in enumerate(gabor_bank(tuple(float(w) for w in wavelengths_px), int(orientations))):
        for even, odd in scales:
            e = cv2.filter2D(img, cv2.CV_32F, even)
            o = cv2.filter2D(img, cv2.CV_32F, odd)
            np.maximum(out[k], cv2.magnitude(e, o), out=out[k])
    return out


def gabor_score(image: NDArray, params: FeatureParams) -> NDArray[np.float32]:
    """Per-pixel Gabor feature score (H,W): the ``min_directions``-th largest directional energy."""
    energy = gabor_directional_energy(image, params.gabor_wavelengths_px, params.gabor_orientations)
    k = min(params.min_directions, energy.shape[0])
    return np.sort(energy, axis=0)[-k]


def target_mask(image: NDArray, params: FeatureParams) -> NDArray[np.uint8]:
    """255 where a patch (plus margin) centred on the pixel lies entirely on the bright target."""
    bright = (np.asarray(image) > params.black_level).astype(np.uint8)
    r = params.patch_size // 2 + params.target_margin_px
    kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    mask = cv2.erode(bright, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    b = params.border_px
    if b > 0:
        mask[:b] = 0
        mask[-b:] = 0
        mask[:, :b] = 0
        mask[:, -b:] = 0
    return mask * 255


def _exclusion(mask: NDArray[np.uint8], exclude_uv: FloatArray, radius: float) -> NDArray[np.uint8]:
    mask = mask.copy()
    for u, v in exclude_uv:
        if np.isfinite(u) and np.isfinite(v):
            cv2.circle(mask, (int(round(u)), int(round(v))), int(np.ceil(radius)), 0, -1)
    return mask


def spread(points: FloatArray, scores: FloatArray, min_distance_px: float, limit: int) -> FloatArray:
    """Greedy non-maximum suppression: best-scoring points first, each at least
    ``min_distance_px`` from those already kept; at most ``limit`` points (N,2)."""
    order = np.argsort(-scores, kind="stable")
    kept: list[FloatArray] = []
    d2 = min_distance_px**2
    for i in order:
        p = points[i]
        if all(float(((p - q) ** 2).sum()) >= d2 for q in kept):
            kept.append(p)
            if len(kept) >= limit:
                break
    return np.array(kept, dtype=float).reshape(-1, 2)


def _candidates_gabor(left: NDArray, mask: NDArray[np.uint8], params: FeatureParams, limit: int) -> FloatArray:
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return np.zeros((0, 2))
    # Filter only the bounding box of the selectable target (plus the kernels' reach).
    pad = int(3 * max(params.gabor_wavelengths_px)) + 1
    x0, x1 = max(xs.min() - pad, 0), min(xs.max() + pad + 1, mask.shape[1])
    y0, y1 = max(ys.min() - pad, 0), min(ys.max() + pad + 1, mask.shape[0])
    score = np.zeros(mask.shape, np.float32)
    score[y0:y1, x0:x1] = gabor_score(np.asarray(left)[y0:y1, x0:x1], params)
    score = np.where(mask > 0, score, 0.0).astype(np.float32)
    peak = cv2.dilate(score, np.ones((5, 5), np.uint8))
    best = float(score.max())
    if best <= 0:
        return np.zeros((0, 2))
    ys, xs = np.nonzero((score >= peak) & (score >= params.quality * best) & (score > 0))
    pts = np.column_stack([xs, ys]).astype(float)
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


def _candidates_centroid(left: NDArray, mask: NDArray[np.uint8], params: FeatureParams, limit: int) -> FloatArray:
    bright = (np.asarray(left) > params.black_level).astype(np.uint8)
    n_labels, labels, stats, centroids = cv2.connectedComponentsWithStats(bright, connectivity=8)
    order = np.argsort(-stats[1:, cv2.CC_STAT_AREA]) + 1  # label 0 is black space
    pts = []
    for label in order:
        if stats[label, cv2.CC_STAT_AREA] < params.patch_size**2:
            break
        c = centroids[label]
        u, v = int(round(c[0])), int(round(c[1]))
        if 0 <= v < mask.shape[0] and 0 <= u < mask.shape[1] and mask[v, u]:
            pts.append(c)
        if len(pts) >= limit:
            break
    return np.array(pts, dtype=float).reshape(-1, 2)


def select_features(
    left: NDArray,
    right_or_none: NDArray | None,
    rig: StereoRig | None,
    n: int,
    method: str,
    params: FeatureParams,
    exclude_uv: ArrayLike = (),
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

    Raises:
        TrackmeterError: unknown method.
    """
    if method not in METHODS:
        raise TrackmeterError(f"unknown feature selection method {method!r} (known: {', '.join(METHODS)})")
    if n <= 0:
        return np.zeros((0, 2))
    excl = np.asarray(exclude_uv, dtype=float).reshape(-1, 2)
    mask = _exclusion(target_mask(left, params), excl, params.min_distance_px)
    limit = n * params.candidates_factor if right_or_none is not None else n
    finder = {"gabor": _candidates_gabor, "centroid": _candidates_centroid, "shi_tomasi": _candidates_shi_tomasi}[method]
    cand = finder(left, mask, params, limit)
    if right_or_none is None or rig is None or len(cand) == 0:
        return cand[:n]
    ok = stereo_matchable(left, right_or_none, rig, cand, params)
    return cand[ok][:n]


def disparity_range(rig: StereoRig, min_depth_m: float, max_depth_m: float) -> tuple[float, float]:
    """Disparities (low, high) of depths ``max_depth_m`` and ``min_depth_m``, px (``d = f b / z``)."""
    rect = rig.rectification
    fb = rect.focal_px * rect.baseline_m
    return fb / max_depth_m + rect.disparity_offset_px, fb / min_depth_m + rect.disparity_offset_px


def stereo_matchable(left: NDArray, right: NDArray, rig: StereoRig, uv: FloatArray, params: FeatureParams) -> NDArray[np.bool_]:
    """Whether each left point (N,2) has a strong, unique match along its epipolar line."""
    from trackmeter.core.patch_tracking import match_epipolar

    rect = rig.rectification
    lo, hi = disparity_range(rig, params.min_depth_m, params.max_depth_m)
    w = rig.image_size[0]
    hi = min(hi, w - 1)
    lo = max(0.0, np.floor(lo))
    cl = rect.rectify_points(uv, 0)
    m = match_epipolar(
        np.ascontiguousarray(left),
        np.ascontiguousarray(right),
        rect.maps[0],
        rect.maps[1],
        cl,
        np.full(len(cl), lo),
        int(np.ceil(hi - lo)),
        params.patch_size,
        min_score=params.stereo_min_score,
        uniqueness_margin=params.uniqueness_margin,
        epipolar_tolerance_px=1.0,
    )
    return m.ok
