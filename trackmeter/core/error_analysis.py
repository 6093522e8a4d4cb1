"""Error analysis of stereo point measurements (paper sections 2.F-2.G, Figs. 2-3).

The paper explained its accuracy from repeated measurements of a still target at several
ranges:

- the standard deviation of a single-point measurement, per axis, grows with range; along the
  viewing axis as ``sigma_z = k z^2`` (Fig. 3's parabola; 4 mm at 3.5 m);
- eq. 2, ``sigma_z = z^2 sigma_d / (f b)``, turns the fitted k into the sub-pixel accuracy of
  the disparity, ``sigma_d = k f b`` (paper: 0.07 px);
- the error propagation (eq. 1-2, :meth:`trackmeter.core.stereo.Rectification.point_sigma`)
  predicts sigma; we put the prediction beside the measurement;
- the measurement error is Gaussian (Fig. 2: its probability density and the best normal fit).

This module is the pure part: statistics of measurement stacks, the parabola fit, eq. 2
inverted, and the error density. Frames: the left camera (z = the viewing axis; the paper's
was y). Units: m, px.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import stats

from trackmeter.core.features import MAX_DISTANCE_PX
from trackmeter.core.params import check_params, param
from trackmeter.errors import TrackmeterError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class AnalyzeParams:
    """Tunables of ``trackmeter analyze``."""

    points_per_range: int = param(30, "points selected on the target at each range (Shi-Tomasi corners)", min=3, max=1000)
    corner_quality: float = param(0.01, "Shi-Tomasi quality level, relative to the best corner", min=1e-6, max=1.0)
    corner_min_distance_px: float = param(12.0, "smallest distance between two selected points, px", min=1.0,
                                          max=MAX_DISTANCE_PX)
    border_px: int = param(16, "points closer than this to the image border or the target's outline are skipped, px", min=0)
    min_samples: int = param(5, "a point needs this many good measurements to count in the statistics", min=2)
    histogram_bins: int = param(31, "bins of the error density histogram (Fig. 2)", min=5, max=1000)
    max_abs_residual_sigmas: float = param(
        8.0, "residuals beyond this many robust sigmas are mismatches, not noise: left out and counted", min=2.0
    )
    max_still_motion_px: float = param(
        1.0, "a range whose points move more than this in the left image (median, first to last frame) is "
        "warned about: its scatter is the target's motion, not measurement noise, px", min=0.01,
    )


# --------------------------------------------------------------------------- per range

    def __post_init__(self) -> None:
        check_params(self)  # declared ranges and choices, as the config loader checks them


@dataclass(frozen=True, eq=False)
class RangeStatistics:
    """Repeated measurements of still points at one range.

    Attributes:
        range_m: mean depth z of the points, m.
        n_points: points with at least ``min_samples`` good measurements.
        n_samples: good measurements of those points in all.
        n_outliers: measurements left out as mismatches (beyond the residual limit).
        sigma_m: (3,) pooled standard deviation of a single measurement per camera axis, m.
        depth_k_per_m: this range's own ``k`` of eq. 2 (``sigma_z = k z^2``), pooled point by
            point: ``sqrt(sum_p sum_i ((z_pi - mean_p) / mean_p^2)^2 / dof)``, 1/m. Equal to
            ``sigma_z / range^2`` for points at one depth; right also for a scene spread in
            depth, where that quotient mixes near and far points.
        predicted_sigma_m: (3,) mean error-propagation sigma of the same measurements, m
            (NaN when not given).
        residuals_m: (n_samples, 3) measurement minus its point's mean, m.
        depth_studentised: (n_samples,) each depth residual over its point's spread without
            it (externally studentised: Student's t with ``n_p - 2`` degrees of freedom for
            Gaussian noise), mapped through the t and normal quantiles: N(0, 1) for Gaussian
            noise whatever the point's sigma, so that points of different noise (texture,
            depth) pool into one density without a mixture of scales making heavy tails. NaN
            for a point measured fewer than 3 times or whose other measurements are all equal.
    """

    range_m: float
    n_points: int
    n_samples: int
    n_outliers: int
    sigma_m: FloatArray
    depth_k_per_m: float
    predicted_sigma_m: FloatArray
    residuals_m: FloatArray
    depth_studentised: FloatArray


def range_statistics(
    points_cam_m: ArrayLike,
    predicted_sigma_m: ArrayLike | None = None,
    min_samples: int = 5,
    max_abs_residual_sigmas: float = np.inf,
) -> RangeStatistics:
    """Pooled single-measurement standard deviation of still points, per axis.

    For each point p with n_p good samples, the residuals about its own mean give the pooled
    (unbiased) variance ``sum_p sum_i (x_pi - mean_p)^2 / sum_p (n_p - 1)`` — the points'
    true positions differ, their noise is what we want. Residuals beyond
    ``max_abs_residual_sigmas`` robust sigmas (1.4826 MAD, per axis) are counted and dropped
    first, because a wrong match is not measurement noise. With ``predicted_sigma_m`` each
    residual is weighed in units of its own predicted sigma first, so that in a scene spread
    in depth the far points' larger noise (eq. 2: ``sigma_z`` grows as ``z^2``) is not taken
    for mismatches.

    Args:
        points_cam_m: (F, P, 3) measurements of P points over F frames, left camera frame, m;
            NaN where a measurement failed.
        predicted_sigma_m: (F, P, 3) error-propagation sigma of each measurement, m, or None.
        min_samples: points with fewer good samples are ignored (at least 2).

    Raises:
        TrackmeterError: wrong shapes, or no point with enough samples.
    """
    X = np.asarray(points_cam_m, dtype=float)
    if X.ndim != 3 or X.shape[2] != 3:
        raise TrackmeterError(f"range statistics need (frames, points, 3) measurements, got {X.shape}")
    good = np.all(np.isfinite(X), axis=2)  # (F, P)

    def point_means(mask: NDArray[np.bool_]) -> FloatArray:
        n = mask.sum(axis=0)[:, None]
        total = np.where(mask[..., None], X, 0.0).sum(axis=0)
        return np.divide(total, n, out=np.full(total.shape, np.nan), where=n > 0)

    S = None
    if predicted_sigma_m is not None:
        S = np.asarray(predicted_sigma_m, dtype=float)
        if S.shape != X.shape:
            raise TrackmeterError(f"predicted sigma shape {S.shape} differs from the measurements' {X.shape}")
    mean = point_means(good)
    resid = X - mean[None]
    n_outliers = 0
    if np.isfinite(max_abs_residual_sigmas) and np.count_nonzero(good) > 2:
        # In units of each measurement's own predicted sigma where it has one.
        weighed, gate = resid, good
        if S is not None:
            usable = good & np.all(np.isfinite(S) & (S > 0), axis=2)
            if np.count_nonzero(usable) > 2:  # else no usable predicted sigmas: the raw residuals
                weighed, gate = np.where(usable[..., None], resid / np.where(usable[..., None], S, 1.0), 0.0), usable
        # The spread from the points the statistics count: a point seen once has a residual of
        # exactly 0, and many such drew the cut-off down onto the good samples.
        counted = gate & (good.sum(axis=0) >= max(int(min_samples), 2))[None, :]
        r = weighed[counted if np.count_nonzero(counted) > 2 else gate]
        mad = 1.4826 * np.median(np.abs(r - np.median(r, axis=0)), axis=0)
        bad = gate & np.any(np.abs(weighed) > max_abs_residual_sigmas * np.maximum(mad, 1e-300), axis=2)
        n_outliers = int(np.count_nonzero(bad))
        if n_outliers:
            good &= ~bad
            mean = point_means(good)
            resid = X - mean[None]
    counts = good.sum(axis=0)  # (P,)
    use = counts >= max(int(min_samples), 2)
    if not np.any(use):
        raise TrackmeterError(f"no point has {max(int(min_samples), 2)} good measurements at this range")
    sel = good & use[None, :]
    R = resid[sel]  # (n, 3)
    dof = float(np.sum(counts[use] - 1))
    sigma = np.sqrt(np.sum(R * R, axis=0) / dof)
    depth_k = float(np.sqrt(np.sum((resid[..., 2] / mean[None, :, 2] ** 2)[sel] ** 2) / dof))
    predicted = np.full(3, np.nan) if S is None else np.sqrt(np.mean(S[sel] ** 2, axis=0))  # their RMS
    # Each depth residual against its point's other measurements (leave one out: mean and
    # spread without it), t_i = r_i sqrt(n / (n - 1)) / s_(-i), is Student's t with n - 2
    # degrees of freedom for Gaussian noise whatever the point's sigma; its t quantile taken
    # to the normal's makes it exactly N(0, 1). (r_i over the point's own spread with r_i in
    # it is bounded by sqrt(n - 1), and 9000 such failed the normality test by light tails.)
    n_p = counts.astype(float)[None, :]
    r_z = np.where(sel, resid[..., 2], 0.0)
    ss = (r_z**2).sum(axis=0)[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        s2_without = (ss - n_p / (n_p - 1) * r_z**2) / (n_p - 2)
        t_stat = r_z * np.sqrt(n_p / (n_p - 1)) / np.sqrt(s2_without)
        usable = sel & (n_p >= 3) & (s2_without > 0)
        studentised = np.where(usable, stats.norm.isf(stats.t.sf(t_stat, np.maximum(n_p - 2, 1))), np.nan)[sel]
    return RangeStatistics(
        range_m=float(np.mean(X[sel][:, 2])),
        n_points=int(np.count_nonzero(use)),
        n_samples=int(len(R)),
        n_outliers=n_outliers,
        sigma_m=sigma,
        depth_k_per_m=depth_k,
        predicted_sigma_m=predicted,
        residuals_m=R,
        depth_studentised=studentised,
    )


@dataclass(frozen=True, eq=False)
class TruthErrors:
    """Errors of repeated measurements of still points against their true positions.

    Attributes:
        rms_m: (3,) RMS of all errors per axis, gross mismatches left out, m.
        bias_rms_m: (3,) RMS over the measurements of their point's mean error (the systematic
            part), m: each point weighed by its measurements, as in ``rms_m``, so the part is
            never larger than the whole (over points alike, a point measured in fewer frames
            with a larger bias made it so: an outside probe, 9.34 against 8.87 mm at 5 m).
        median_abs_m: (3,) median absolute error per axis (all points), m.
        n_points: points compared (with a known true position and a good measurement).
        n_gross: points whose mean error is a gross outlier (left out of the RMS figures).
    """

    rms_m: FloatArray
    bias_rms_m: FloatArray
    median_abs_m: FloatArray
    n_points: int
    n_gross: int


def truth_errors(points_cam_m: ArrayLike, true_points_cam_m: ArrayLike, gross_sigmas: float = 8.0) -> TruthErrors:
    """Errors of repeated measurements against the true points (when a simulator knows them).

    The repeated-measurement sigma only sees what changes from frame to frame (sensor noise);
    a still target's systematic matching error (texture, interpolation, foreshortening, a
    wrong match) is the same in every frame and only shows against the truth. A point whose
    mean error is more than ``gross_sigmas`` robust sigmas (1.4826 MAD over points, per axis,
    with the noise its own mean still carries) from the median is a gross mismatch: counted, and left out of the RMS figures.

    Args:
        points_cam_m: (F, P, 3) measurements, m (NaN where refused).
        true_points_cam_m: (P, 3) the true points, same frame, m (NaN where unknown).
    """
    X = np.asarray(points_cam_m, dtype=float)
    T = np.asarray(true_points_cam_m, dtype=float).reshape(1, -1, 3)
    if X.ndim != 3 or X.shape[1:] != T.shape[1:]:
        raise TrackmeterError(f"truth errors need (F,P,3) measurements and (P,3) truth, got {X.shape}, {T.shape[1:]}")
    E = X - T
    good = np.all(np.isfinite(E), axis=2)
    n = good.sum(axis=0)
    has = n > 0
    if not np.any(has):
        nan = np.full(3, np.nan)
        return TruthErrors(nan, nan, nan, 0, 0)
    bias = np.where(good[..., None], E, 0.0).sum(axis=0)[has] / n[has][:, None]  # (Q,3)
    # Spread of the point means: their systematic scatter (MAD over points) plus, for a point
    # measured n times, the frame-to-frame noise s_w / sqrt(n) its mean still carries.
    mad = 1.4826 * np.median(np.abs(bias - np.median(bias, axis=0)), axis=0)
    resid = np.where(good[..., None], E - np.where(has[:, None], np.where(good[..., None], E, 0.0).sum(axis=0) / np.maximum(n, 1)[:, None], 0.0), 0.0)
    s_w = np.sqrt(np.sum(resid**2, axis=(0, 1)) / max(float(np.sum(n[has] - 1)), 1.0))
    spread = np.sqrt(mad[None, :] ** 2 + s_w[None, :] ** 2 / n[has][:, None])
    gross = np.any(np.abs(bias - np.median(bias, axis=0)) > gross_sigmas * np.maximum(spread, 1e-12), axis=1)
    keep = np.zeros_like(has)
    keep[np.flatnonzero(has)[~gross]] = True
    Ek = E[good & keep[None, :]]
    return TruthErrors(
        np.sqrt(np.mean(Ek**2, axis=0)) if len(Ek) else np.full(3, np.nan),
        np.sqrt(np.average(bias[~gross] ** 2, axis=0, weights=n[has][~gross])) if np.any(~gross) else np.full(3, np.nan),
        np.median(np.abs(E[good]), axis=0),
        int(np.count_nonzero(has)),
        int(np.count_nonzero(gross)),
    )


# --------------------------------------------------------------------------- noise-limited disparity


def temporal_noise_variance(images: ArrayLike) -> FloatArray:
    """Per-pixel variance of the sensor noise over a stack of images of a still scene, grey levels².

    What changes from frame to frame of a still target is the sensor noise (read and shot
    noise) and, outside a laboratory, the light. The light changes slowly, so the noise is taken
    from the second differences in time, ``e_t = x_(t+1) - 2 x_t + x_(t-1)``, in which a
    brightness that changes linearly cancels exactly (and a smooth swing nearly): for white noise
    of variance s² each has variance 6 s², so ``s² = sum e_t² / (6 (F - 2))`` (von Neumann's
    successive-difference idea, one order up). With two frames, ``(x_2 - x_1)² / 2``. The plain
    variance over frames counted a ±60 % swing of the light as noise (5 times the true s²).

    Args:
        images: (F, H, W) grey images, F >= 2.
    """
    stack = np.asarray(images, dtype=float)
    if stack.ndim != 3 or stack.shape[0] < 2:
        raise TrackmeterError(f"temporal noise needs (frames >= 2, H, W) images, got {stack.shape}")
    if stack.shape[0] == 2:
        return 0.5 * (stack[1] - stack[0]) ** 2
    second = stack[2:] - 2.0 * stack[1:-1] + stack[:-2]
    return np.sum(second * second, axis=0) / (6.0 * (stack.shape[0] - 2))


def noise_limited_disparity_sigma(patch: ArrayLike, noise_variance: float) -> float:
    """Disparity standard deviation that image noise alone allows for one patch match, px.

    Matching a patch along the epipolar line (x) is the estimation of a 1-D shift between two
    noisy copies of a texture. Linearising the sum of squared differences about the true shift,
    ``d_hat - d = sum g (n_r - n_l) / sum g^2`` with g the x-gradient of the texture and n_l, n_r
    the two images' independent noise of variance s^2, so
    ``sigma_d^2 = 2 s^2 / sum g^2`` — the Cramer-Rao bound of 1-D registration with noise in both
    images (Robinson & Milanfar, "Fundamental performance limits in image registration",
    IEEE TIP 13(9), 2004). The paper's 0.07 px sits well above this bound on its hardware; a
    measured sigma_d near it means the matcher wastes nothing. The gradient is taken by central
    differences, which see a texture frequency w (rad/px) attenuated by sin(w)/w: near the
    Nyquist limit the bound comes out larger (conservative) than the exact one.

    Args:
        patch: (P, Q) noise-free (e.g. averaged) grey levels of the patch with one extra column
            on each side, so the central differences cover Q - 2 columns.
        noise_variance: s^2 of one image's noise, grey levels².
    """
    a = np.asarray(patch, dtype=float)
    if a.ndim != 2 or a.shape[1] < 3:
        raise TrackmeterError(f"patch must be (P, Q >= 3), got {a.shape}")
    g = 0.5 * (a[:, 2:] - a[:, :-2])
    energy = float(np.sum(g * g))
    if energy <= 0:
        return float("inf")
    return float(np.sqrt(2.0 * noise_variance / energy))


def point_disparity_sigma(points_cam_m: ArrayLike, focal_px: float, baseline_m: float, min_samples: int = 5) -> FloatArray:
    """Each still point's repeated-measurement sigma, turned into disparity by eq. 2, px.

    ``sigma_d,p = std(z_p) f b / mean(z_p)^2`` over the point's good samples (unbiased std);
    NaN for points with fewer than ``min_samples`` (at least 2) good samples. Compared point by
    point with :func:`noise_limited_disparity_sigma`, it tells whether the matcher reaches
    what the image noise allows.

    Args:
        points_cam_m: (F, P, 3) measurements, left camera frame, m (NaN where refused).
    """
    X = np.asarray(points_cam_m, dtype=float)
    if X.ndim != 3 or X.shape[2] != 3:
        raise TrackmeterError(f"need (frames, points, 3) measurements, got {X.shape}")
    out = np.full(X.shape[1], np.nan)
    good = np.all(np.isfinite(X), axis=2)
    for p in range(X.shape[1]):
        z = X[good[:, p], p, 2]
        if len(z) >= max(int(min_samples), 2):
            out[p] = float(np.std(z, ddof=1)) * focal_px * baseline_m / float(np.mean(z)) ** 2
    return out


# --------------------------------------------------------------------------- the parabola


@dataclass(frozen=True, eq=False)
class ParabolaFit:
    """Least-squares ``sigma = k z^2`` (paper Fig. 3).

    Attributes:
        k_per_m: the coefficient, 1/m (sigma in m for z in m).
        k_std_per_m: its standard error from the fit residuals, 1/m (NaN with one range).
        rms_residual_m: RMS of ``sigma_i - k z_i^2``, m.
        r2: coefficient of determination of the through-origin fit, ``1 - SSR / sum sigma^2``
            (NaN with one range).
    """

    k_per_m: float
    k_std_per_m: float
    rms_residual_m: float
    r2: float


def fit_parabola(range_m: ArrayLike, sigma_m: ArrayLike) -> ParabolaFit:
    """Fit ``sigma = k z^2`` by linear least squares through the origin.

    Minimising ``sum_i (sigma_i - k z_i^2)^2`` gives ``k = sum sigma_i z_i^2 / sum z_i^4``
    (one regressor, no intercept: eq. 2 has none).
    """
    z = np.asarray(range_m, dtype=float).reshape(-1)
    s = np.asarray(sigma_m, dtype=float).reshape(-1)
    if len(z) != len(s) or len(z) == 0:
        raise TrackmeterError("parabola fit needs as many ranges as sigmas, at least one")
    if not (np.all(np.isfinite(z)) and np.all(np.isfinite(s))) or np.any(z <= 0):
        raise TrackmeterError("parabola fit needs finite sigmas at positive ranges")
    x = z * z
    k = float(np.dot(x, s) / np.dot(x, x))
    r = s - k * x
    ssr = float(np.dot(r, r))
    k_std = float(np.sqrt(ssr / (len(z) - 1) / np.dot(x, x))) if len(z) > 1 else float("nan")
    total = float(np.dot(s, s))
    # One range: the curve through the origin passes through it exactly, an R² of 1 that says nothing.
    r2 = 1.0 - ssr / total if total > 0 and len(z) > 1 else float("nan")
    return ParabolaFit(k, k_std, float(np.sqrt(ssr / len(z))), r2)


def subpixel_accuracy_px(k_per_m: float, focal_px: float, baseline_m: float) -> float:
    """Disparity standard deviation implied by ``sigma_z = k z^2``: paper eq. 2 inverted,
    ``sigma_d = k f b`` (px), the inverse of :func:`trackmeter.core.stereo.depth_sigma`."""
    return float(k_per_m * focal_px * baseline_m)


# --------------------------------------------------------------------------- error density


@dataclass(frozen=True, eq=False)
class DensityFit:
    """Empirical probability density of errors with its best Gaussian (paper Fig. 2).

    Attributes:
        bin_edges: (B+1,) histogram edges (unit of the errors).
        density: (B,) histogram normalised to unit area.
        mu, sigma: maximum-likelihood normal fit (``scipy.stats.norm.fit``).
        ks_statistic, ks_pvalue: Kolmogorov-Smirnov distance to the fitted normal (the p-value
            is optimistic because mu, sigma come from the same data — Lilliefors).
        k2_statistic, k2_pvalue: D'Agostino-Pearson omnibus normality test
            (``scipy.stats.normaltest``; NaN below 8 samples).
        n: number of errors.
    """

    bin_edges: FloatArray
    density: FloatArray
    mu: float
    sigma: float
    ks_statistic: float
    ks_pvalue: float
    k2_statistic: float
    k2_pvalue: float
    n: int


def error_density(errors: ArrayLike, bins: int = 31) -> DensityFit:
    """Histogram density of ``errors`` (1-D) and its best normal fit with normality statistics."""
    e = np.asarray(errors, dtype=float).reshape(-1)
    e = e[np.isfinite(e)]
    if len(e) < 3:
        raise TrackmeterError(f"error density needs at least 3 errors, got {len(e)}")
    density, edges = np.histogram(e, bins=bins, density=True)
    mu, sigma = stats.norm.fit(e)
    if sigma > 0:
        ks = stats.kstest(e, "norm", args=(mu, sigma))
        ks_stat, ks_p = float(ks.statistic), float(ks.pvalue)
    else:
        ks_stat, ks_p = float("nan"), float("nan")
    if len(e) >= 8 and sigma > 0:
        k2 = stats.normaltest(e)
        k2_stat, k2_p = float(k2.statistic), float(k2.pvalue)
    else:
        k2_stat = k2_p = float("nan")
    return DensityFit(edges, density, float(mu), float(sigma), ks_stat, ks_p, k2_stat, k2_p, len(e))


# --------------------------------------------------------------------------- the whole analysis


@dataclass(frozen=True, eq=False)
class ErrorAnalysis:
    """The paper's error analysis over several ranges.

    Attributes:
        ranges: per-range statistics, by increasing range.
        fits: ``sigma = k z^2`` per camera axis ``"x"``, ``"y"``, ``"z"``.
        sigma_disparity_px: sub-pixel disparity accuracy from the z fit (eq. 2 inverted).
        density: error density of the depth residuals, each over its point's spread without
            it (:attr:`RangeStatistics.depth_studentised`: dimensionless, so all points and
            ranges pool; Fig. 2). Over one sigma per range instead, points of different
            noise (a texture's sigma_d 0.012 to 0.094 px, depths spread) made a mixture whose
            heavy tails failed the normality tests on Gaussian noise (an outside probe).
        density_range: error density of the depth residuals at the range nearest 3.5 m, m.
        focal_px, baseline_m: the rig used in eq. 2.
    """

    ranges: tuple[RangeStatistics, ...]
    fits: dict[str, ParabolaFit]
    sigma_disparity_px: float
    density: DensityFit
    density_range: DensityFit
    focal_px: float
    baseline_m: float

    def to_dict(self) -> dict[str, object]:
        """A JSON-friendly summary (SI units, px)."""

        def dens(d: DensityFit) -> dict[str, float]:
            return {"n": d.n, "mu": d.mu, "sigma": d.sigma, "ks_statistic": d.ks_statistic,
                    "ks_pvalue": d.ks_pvalue, "k2_statistic": d.k2_statistic, "k2_pvalue": d.k2_pvalue}

        return {
            "focal_px": self.focal_px,
            "baseline_m": self.baseline_m,
            "ranges": [
                {
                    "range_m": r.range_m, "n_points": r.n_points, "n_samples": r.n_samples,
                    "n_outliers": r.n_outliers,
                    "sigma_m": dict(zip("xyz", map(float, r.sigma_m))),
                    "predicted_sigma_m": dict(zip("xyz", map(float, r.predicted_sigma_m))),
                    # eq. 2 inverted at this range alone: is sigma_d constant over range?
                    "sigma_disparity_px": subpixel_accuracy_px(r.depth_k_per_m, self.focal_px, self.baseline_m),
                }
                for r in self.ranges
            ],
            "fit": {
                axis: {"k_per_m": f.k_per_m, "k_std_per_m": f.k_std_per_m, "rms_residual_m": f.rms_residual_m, "r2": f.r2}
                for axis, f in self.fits.items()
            },
            "sigma_disparity_px": self.sigma_disparity_px,
            "sigma_z_at_3p5_m": self.fits["z"].k_per_m * 3.5**2,
            "density_normalised": dens(self.density),
            "density_at_range": {"range_m": self.ranges[self._nearest_3p5()].range_m, **dens(self.density_range)},
        }

    def _nearest_3p5(self) -> int:
        return int(np.argmin([abs(r.range_m - 3.5) for r in self.ranges]))


def analyze_ranges(
    ranges: list[RangeStatistics] | tuple[RangeStatistics, ...], focal_px: float, baseline_m: float, bins: int = 31
) -> ErrorAnalysis:
    """Fit the parabola per axis, infer the sub-pixel accuracy, fit the error densities.

    Args:
        ranges: statistics at (ideally) several ranges.
        focal_px, baseline_m: the rectified rig's focal length (px) and baseline (m) of eq. 2.
    """
    if not ranges:
        raise TrackmeterError("error analysis needs measurements at one range at least")
    rs = tuple(sorted(ranges, key=lambda r: r.range_m))
    # Round-off of identical frames scatters by ~1e-15 m: a nanometre is no measurement noise.
    if not any(r.sigma_m[2] > 1e-9 * r.range_m for r in rs):
        # Identical frames (a still image repeated, a noise-free render): no scatter to fit.
        raise TrackmeterError("error analysis needs measurements that scatter: every range's depth "
                              "spread is zero (are the frames identical copies?)")
    z = np.array([r.range_m for r in rs])
    fits = {axis: fit_parabola(z, [r.sigma_m[i] for r in rs]) for i, axis in enumerate("xy")}
    # Depth: each range's sigma_z at its mean depth from its own points' k (eq. 2 point by
    # point): the same for a flat target, and right for a scene spread in depth.
    fits["z"] = fit_parabola(z, [r.depth_k_per_m * r.range_m**2 for r in rs])
    normalised = np.concatenate([r.depth_studentised for r in rs])
    near = int(np.argmin(np.abs(z - 3.5)))
    return ErrorAnalysis(
        rs,
        fits,
        subpixel_accuracy_px(fits["z"].k_per_m, focal_px, baseline_m),
        error_density(normalised, bins),
        error_density(rs[near].residuals_m[:, 2], bins),
        float(focal_px),
        float(baseline_m),
    )
