"""Running the paper's error analysis (sections 2.F-2.G) on a source of a still target.

The source (the simulator's ``static_ranges`` scenario, or any sequence of a still object) is
read frame by frame and split into *ranges*: runs of consecutive frames with the same true pose
when the source has ground truth (the target held still at one range), else runs of frames
between jumps of the view (the target moved to another range). On the first frame of each
range, points are selected on the target (Shi-Tomasi corners, inside the lit object, away from
its outline where a patch would straddle the black sky); then every frame of that range
measures them with the stereo matcher (:func:`trackmeter.core.matching.measure_points`). The
pure statistics are :mod:`trackmeter.core.error_analysis`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Callable, Iterable, Iterator, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from trackmeter.core.error_analysis import (
    AnalyzeParams,
    ErrorAnalysis,
    RangeStatistics,
    analyze_ranges,
    noise_limited_disparity_sigma,
    point_disparity_sigma,
    range_statistics,
    temporal_noise_variance,
    truth_errors,
)
from trackmeter.core.exposure import ExposureParams, apply_gain, exposure_gain
from trackmeter.core.features import erode_square
from trackmeter.core.matching import MeasureParams, measure_points
from trackmeter.core.stereo import StereoRig
from trackmeter.core.targets import count_reasons
from trackmeter.core.transforms import apply_transform, rotation_from_matrix
from trackmeter.errors import TrackmeterError
from trackmeter.sources.base import Source, StereoFrame

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class RangeMeasurements:
    """Everything measured at one range.

    Attributes:
        t_s: (F,) frame times, s.
        uv: (P,2) selected left-image pixels, px.
        xyz_m: (F,P,3) measured points, left camera frame, m (NaN when refused).
        sigma_m: (F,P,3) error-propagation sigma of each measurement, m (NaN when refused).
        sigma_disparity_px: (F,P) the matcher's disparity sigma (NaN when refused).
        refusals: reason -> count of refused measurements.
        true_range_m: the true range of the target's origin when the source knows it, else NaN.
        true_xyz_m: (P,3) the true surface points at ``uv`` (left camera frame, m) when the
            source can say (the simulator's ``surface_points``), else None.
        noise_sigma_disparity_px: (P,) the disparity sigma that the image noise measured over
            the range's frames allows each patch (Cramer-Rao bound, NaN when unknown).
        image_motion_px: median image motion of the points from the range's first to its last
            left frame (:func:`image_motion_px`), px; NaN when it cannot be told.
        exposure_gain: the gain every frame of the range was multiplied by before it was
            measured (:mod:`trackmeter.core.exposure`; 1: normally exposed).
        candidates: how many corners were found on the target in the range's first frame.
    """

    t_s: FloatArray
    uv: FloatArray
    xyz_m: FloatArray
    sigma_m: FloatArray
    sigma_disparity_px: FloatArray
    refusals: dict[str, int]
    true_range_m: float
    true_xyz_m: FloatArray | None = None
    noise_sigma_disparity_px: FloatArray | None = None
    image_motion_px: float = float("nan")
    exposure_gain: float = 1.0
    candidates: int = 0


@dataclass(frozen=True, eq=False)
class AnalysisRun:
    """The result of :func:`run_error_analysis`."""

    analysis: ErrorAnalysis
    measurements: tuple[RangeMeasurements, ...]
    statistics: tuple[RangeStatistics, ...]
    predicted_sigma_disparity_px: float  # median of the matcher's own estimates
    skipped_ranges: tuple[str, ...] = field(default_factory=tuple)
    gross_sigmas: float = 8.0
    min_samples: int = 5
    moving_ranges: tuple[str, ...] = field(default_factory=tuple)  # one line each: the target moved
    exposure_gains: tuple[float, ...] = field(default_factory=tuple)  # every range read, skipped ones too
    frames_without_truth_s: tuple[float, ...] = field(default_factory=tuple)  # left out of every range, s

    def to_dict(self) -> dict[str, object]:
        d = self.analysis.to_dict()
        d["predicted_sigma_disparity_px"] = self.predicted_sigma_disparity_px
        f, b = self.analysis.focal_px, self.analysis.baseline_m
        ratios: list[FloatArray] = []
        limits: list[FloatArray] = []
        per_range: list[tuple[float, float] | None] = []
        for m in self.measurements:
            if m.noise_sigma_disparity_px is None:
                per_range.append(None)
                continue
            measured = point_disparity_sigma(m.xyz_m, f, b, self.min_samples)
            ok = np.isfinite(measured) & np.isfinite(m.noise_sigma_disparity_px)
            limits.append(m.noise_sigma_disparity_px[ok])
            ratios.append(measured[ok] / m.noise_sigma_disparity_px[ok])
            per_range.append(
                (float(np.sqrt(np.mean(limits[-1] ** 2))), float(np.median(ratios[-1])))
                if np.any(ok) else None
            )
        lim_all = np.concatenate(limits) if limits else np.zeros(0)
        rat_all = np.concatenate(ratios) if ratios else np.zeros(0)
        # RMS of the limits: the sigma a fit over the points' variances would see; the median
        # ratio per point: does the matcher reach what the noise allows (1 = it does)?
        d["noise_limited_sigma_disparity_px"] = float(np.sqrt(np.mean(lim_all**2))) if len(lim_all) else float("nan")
        d["measured_over_noise_limit_median"] = float(np.median(rat_all)) if len(rat_all) else float("nan")
        # The analysis's ranges are this run's statistics in the same (stable) order: paired by
        # place, not by depth, which two ranges may share to the micrometre.
        ranges = cast("list[dict[str, object]]", d["ranges"])  # ErrorAnalysis.to_dict's, one dict a range
        for entry, m, pr in zip(ranges, self.measurements, per_range, strict=True):
            entry["true_range_m"] = m.true_range_m
            entry["n_frames"] = len(m.t_s)
            entry["n_selected"] = len(m.uv)
            entry["refused"] = dict(m.refusals)
            entry["image_motion_px"] = m.image_motion_px
            entry["exposure_gain"] = m.exposure_gain
            if pr is not None:
                entry["noise_limited_sigma_disparity_px"], entry["measured_over_noise_limit_median"] = pr
            if m.true_xyz_m is not None:
                te = truth_errors(m.xyz_m, m.true_xyz_m, self.gross_sigmas)
                entry["truth_error"] = {
                    "n_points": te.n_points,
                    "n_gross": te.n_gross,
                    "rms_m": dict(zip("xyz", map(float, te.rms_m))),
                    "bias_rms_m": dict(zip("xyz", map(float, te.bias_rms_m))),
                    "median_abs_m": dict(zip("xyz", map(float, te.median_abs_m))),
                }
        d["skipped_ranges"] = list(self.skipped_ranges)
        return d


def select_points(left: NDArray[np.uint8], params: AnalyzeParams, min_grey: float, max_points: int | None = None) -> FloatArray:
    """Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) inside the lit target, (P,2) px, best first.

    The mask keeps pixels brighter than ``min_grey`` (the target against black sky), eroded by
    ``params.border_px`` so that no 8x8 patch straddles the outline or the image border.
    ``max_points``: at most this many (None: ``params.points_per_range``).
    """
    mask = erode_square((left > min_grey).astype(np.uint8) * 255, params.border_px)
    corners = cv2.goodFeaturesToTrack(
        left, maxCorners=int(params.points_per_range if max_points is None else max_points), qualityLevel=float(params.corner_quality),
        minDistance=float(params.corner_min_distance_px), mask=mask,
    )
    if corners is None:
        return np.zeros((0, 2))
    return corners.reshape(-1, 2).astype(float)


#: Frames whose true pose is within this distance of their range's first frame's (and
#: :data:`STILL_ANGLE_TOLERANCE_RAD`) belong to its range: a measured ground truth (motion
#: capture, a total station) jitters by a few hundredths of a millimetre about a still target.
STILL_POSITION_TOLERANCE_M = 1e-3
#: ... and within this rotation angle of it (0.1 deg: 0.9 mm at half a metre from the origin).
STILL_ANGLE_TOLERANCE_RAD = math.radians(0.1)


def split_ranges(frames: Iterable[StereoFrame], position_tolerance_m: float = STILL_POSITION_TOLERANCE_M,
                 skipped: list[float] | None = None,
                 angle_tolerance_rad: float = STILL_ANGLE_TOLERANCE_RAD) -> Iterator[list[StereoFrame]]:
    """Group consecutive frames with the same true pose (the target held still: within
    ``position_tolerance_m`` and ``angle_tolerance_rad`` of the range's first frame's); without
    ground truth, where the view jumps (:func:`split_where_the_view_jumps`).

    Where some frames have truth, those without (rows missing or NaN in the truth file) belong
    to no range: they are left out, and their times (s) appended to ``skipped``.
    """
    group: list[StereoFrame] = []
    key: FloatArray | None = None
    seen_truth = False
    for frame in frames:
        if frame.truth is None:
            if seen_truth:
                if skipped is not None:
                    skipped.append(frame.t_s)
            else:
                group.append(frame)  # split by the images, unless truth comes later
            continue
        T = np.asarray(frame.truth.T_cam_body, dtype=float)
        if not seen_truth:
            if skipped is not None:
                skipped.extend(f.t_s for f in group)
            group, seen_truth = [], True
        if group and key is not None and _moved(key, T, position_tolerance_m, angle_tolerance_rad):
            yield group
            group = []
        if not group:
            key = T  # the range's first pose: a slow drift is not a still target either
        group.append(frame)
    if group and not seen_truth:
        yield from split_where_the_view_jumps(group)
    elif group:
        yield group


def _moved(T_a: FloatArray, T_b: FloatArray, position_tolerance_m: float, angle_tolerance_rad: float) -> bool:
    """Whether two 4x4 poses differ by more than the tolerances (translation, m; rotation angle)."""
    if np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]) > position_tolerance_m:
        return True
    return bool(rotation_from_matrix(T_a[:3, :3].T @ T_b[:3, :3]).magnitude() > angle_tolerance_rad)


#: A change of the view larger than this many times the median frame-to-frame change is the
#: target moved to another range (a still target's view changes by its noise: measured
#: 0.15-0.32 grey levels at 1/8 scale on static_ranges, against 3-28 where it moves).
VIEW_JUMP_OVER_MEDIAN = 5.0
#: ... and larger than this (grey levels, mean absolute difference at 1/8 scale), so that
#: frames with no noise at all (one image repeated) are not split by a rounding difference.
VIEW_JUMP_MIN_GREY = 0.5


def split_where_the_view_jumps(frames: list[StereoFrame]) -> list[list[StereoFrame]]:
    """Consecutive frames of a source without ground truth grouped into still ranges: a new
    range starts where the left image changes from the frame before by more than
    :data:`VIEW_JUMP_OVER_MEDIAN` times the median change between consecutive frames (and
    :data:`VIEW_JUMP_MIN_GREY`). The change is the mean absolute difference of the images
    shrunk to 1/8 (area averaging), where a still view differs by its noise alone.

    A target that moves all the time changes its view by about the median on every frame:
    it stays one range, which the analysis then reports as moving.
    """
    if len(frames) < 3:
        return [frames] if frames else []

    def shrunk(image: NDArray[np.uint8]) -> NDArray[np.float32]:
        h, w = image.shape[:2]
        return cv2.resize(image, (max(1, w // 8), max(1, h // 8)), interpolation=cv2.INTER_AREA).astype(np.float32)

    views = [shrunk(f.left) for f in frames]
    # Images of another size than the frame before: another view, whatever their content.
    change = np.array([float(np.mean(np.abs(b - a))) if a.shape == b.shape else np.inf
                       for a, b in zip(views, views[1:])])
    finite = change[np.isfinite(change)]
    jump = max(VIEW_JUMP_OVER_MEDIAN * (float(np.median(finite)) if len(finite) else 0.0), VIEW_JUMP_MIN_GREY)
    starts = [0, *(int(k) + 1 for k in np.flatnonzero(change > jump)), len(frames)]
    return [frames[a:b] for a, b in zip(starts, starts[1:])]


def measure_range(
    frames: list[StereoFrame],
    rig: StereoRig,
    measure: MeasureParams,
    params: AnalyzeParams,
    surface_points: Callable[[int, FloatArray], FloatArray] | None = None,
) -> RangeMeasurements:
    """Select points on the first frame and measure them in every frame of one range.

    The corners are tried best first (at most 20 times ``params.points_per_range``, four times
    that many at a time): the first ``points_per_range`` the matcher accepts on the first frame
    (a corner on a repetitive grid or seen by the left camera only is refused there, and would
    only add refusals later), and where some of them then fall short of ``params.min_samples``
    good measurements over the range, as many more as make up for them, so that the statistics
    count the points asked for wherever the target has them. When none is accepted,
    ``refusals`` holds the first frame's reasons and ``candidates`` how many corners were found.
    """
    first = frames[0]
    n = params.points_per_range
    candidates = select_points(first.left, params, measure.min_mean_grey, 20 * n)  # best first
    first_refusals: dict[str, int] = {}
    refusals: dict[str, int] = {}

    def accepted_batches() -> Iterator[FloatArray]:
        for start in range(0, len(candidates), 4 * n):
            batch = candidates[start:start + 4 * n]
            results = measure_points(rig, first.left, first.right, batch, measure)
            for m in results:
                if not m.ok:
                    first_refusals[str(m.reason)] = first_refusals.get(str(m.reason), 0) + 1
            yield batch[np.array([m.ok for m in results], dtype=bool)]

    F = len(frames)
    uv = np.zeros((0, 2))
    xyz, sig, sd = np.zeros((F, 0, 3)), np.zeros((F, 0, 3)), np.zeros((F, 0))
    pool: list[FloatArray] = []
    batches = accepted_batches()
    while True:
        good = int(np.sum(np.sum(np.isfinite(xyz[..., 2]), axis=0) >= params.min_samples))
        need = n - (good if F >= params.min_samples else len(uv))  # too few frames: no point could make up
        while len(pool) < need and (batch := next(batches, None)) is not None:
            pool.extend(batch)
        if need <= 0 or not pool:
            break
        new, pool = np.asarray(pool[:need], dtype=float).reshape(-1, 2), pool[need:]
        x_new, s_new = np.full((F, len(new), 3), np.nan), np.full((F, len(new), 3), np.nan)
        d_new = np.full((F, len(new)), np.nan)
        for f, frame in enumerate(frames):
            for p, m in enumerate(measure_points(rig, frame.left, frame.right, new, measure)):
                if m.ok:
                    x_new[f, p], s_new[f, p], d_new[f, p] = m.xyz_m, m.sigma_m, m.sigma_disparity_px
                else:
                    refusals[str(m.reason)] = refusals.get(str(m.reason), 0) + 1
        uv = np.vstack([uv, new])
        xyz, sig, sd = (np.concatenate(pair, axis=1) for pair in ((xyz, x_new), (sig, s_new), (sd, d_new)))
    P = len(uv)
    noise_sd = _noise_limited_sigmas(frames, uv, xyz, measure.patch_size, rig) if F >= 2 and P > 0 else None
    truth = first.truth
    true_range = float(np.linalg.norm(truth.T_cam_body[:3, 3])) if truth is not None else float("nan")
    true_xyz = None
    if surface_points is not None and truth is not None and P > 0:
        p_body = np.asarray(surface_points(first.index, uv), dtype=float).reshape(-1, 3)
        true_xyz = apply_transform(truth.T_cam_body, p_body)
    motion = image_motion_px(first.left, frames[-1].left, uv) if F >= 2 else float("nan")
    return RangeMeasurements(np.array([fr.t_s for fr in frames]), uv, xyz, sig, sd, refusals if P else first_refusals,
                             true_range, true_xyz, noise_sd, motion, candidates=len(candidates))


def image_motion_px(first: NDArray[np.uint8], last: NDArray[np.uint8], uv: FloatArray) -> float:
    """Median displacement, px, of the pixels ``uv`` (P,2) from image ``first`` to ``last``
    (pyramidal Lucas-Kanade, ``cv2.calcOpticalFlowPyrLK``, 21 px window, 3 levels: up to about
    30 px), over the points it tracks; NaN when it tracks none.

    The analysis measures fixed pixels frame after frame, which is only the scatter of repeated
    measurements of one surface point while the target stands still."""
    if len(uv) == 0:
        return float("nan")
    p0 = np.asarray(uv, dtype=np.float32).reshape(-1, 1, 2)
    p1, status, _ = cv2.calcOpticalFlowPyrLK(first, last, p0, None, winSize=(21, 21), maxLevel=3)
    ok = status.reshape(-1).astype(bool)
    if not ok.any():
        return float("nan")
    return float(np.median(np.linalg.norm((p1 - p0).reshape(-1, 2)[ok], axis=1)))


def _noise_limited_sigmas(
    frames: list[StereoFrame], uv: FloatArray, xyz: FloatArray, patch_size: int, rig: StereoRig
) -> FloatArray:
    """Per point, the noise-limited disparity sigma (:func:`noise_limited_disparity_sigma`)
    from the frame-averaged left patch's x-gradients and the temporal noise of both images
    (the right patch located by projecting the mean measured point). Rows of the original
    images stand in for the rectified epipolar lines (the rig's rectification turns them by
    a fraction of a degree)."""
    left = np.stack([f.left for f in frames]).astype(float)
    right = np.stack([f.right for f in frames]).astype(float)
    mean_left = left.mean(axis=0)
    var_left = temporal_noise_variance(left)
    var_right = temporal_noise_variance(right)
    H, W = mean_left.shape
    half = patch_size // 2
    out = np.full(len(uv), np.nan)
    counts = np.sum(np.all(np.isfinite(xyz), axis=2), axis=0)
    for p, (u, v) in enumerate(uv):
        if counts[p] == 0:
            continue
        mean_xyz = np.nanmean(xyz[:, p, :], axis=0)
        _, uv_right = rig.project(mean_xyz[None, :])
        ur, vr = np.round(uv_right[0]).astype(int)
        u0, v0 = int(round(u)) - half, int(round(v)) - half
        if not (1 <= u0 and u0 + patch_size + 1 <= W and 0 <= v0 and v0 + patch_size <= H):
            continue
        if not (0 <= ur - half and ur - half + patch_size <= W and 0 <= vr - half and vr - half + patch_size <= H):
            continue
        patch = mean_left[v0 : v0 + patch_size, u0 - 1 : u0 + patch_size + 1]
        noise = 0.5 * (
            float(np.mean(var_left[v0 : v0 + patch_size, u0 : u0 + patch_size]))
            + float(np.mean(var_right[vr - half : vr - half + patch_size, ur - half : ur - half + patch_size]))
        )
        out[p] = noise_limited_disparity_sigma(patch, noise)
    return out


def run_error_analysis(
    source: Source,
    rig: StereoRig,
    measure: MeasureParams,
    params: AnalyzeParams,
    progress: Callable[[Iterable[StereoFrame]], Iterable[StereoFrame]] | None = None,
    exposure: ExposureParams | None = None,
) -> AnalysisRun:
    """Read ``source`` to its end and run the error analysis over its ranges.

    ``exposure``: an underexposed range is measured as the tracking engine and ``measure`` see
    it, every frame multiplied by the gain :func:`~trackmeter.core.exposure.exposure_gain` finds
    for the range's first left image (one gain per range, so the frame-to-frame noise the
    analysis measures is the images' own); None: the images as they are.

    Ranges where fewer than 3 points have ``params.min_samples`` good measurements are skipped
    and named in :attr:`AnalysisRun.skipped_ranges` (e.g. the target too small far away).

    Raises:
        TrackmeterError: an empty source, or no usable range.
    """

    def frames() -> Iterator[StereoFrame]:
        while (frame := source.read()) is not None:
            yield frame

    stream: Iterable[StereoFrame] = frames()
    if progress is not None:
        stream = progress(stream)
    measured: list[RangeMeasurements] = []
    stats: list[RangeStatistics] = []
    skipped: list[str] = []
    moving: list[str] = []
    n_ranges = n_frames = 0
    gains: list[float] = []
    problem = getattr(source, "truth_problem", None)
    if problem:
        raise TrackmeterError(f"analyze splits the source into its still ranges by the ground truth, and {problem}: "
                              "mend the file, or move it away to analyze the source as one range")
    without_truth: list[float] = []
    for group in split_ranges(stream, skipped=without_truth):
        gain = exposure_gain(group[0].left, exposure) if exposure is not None else 1.0
        gains.append(gain)
        if gain != 1.0:
            group = [replace(f, left=apply_gain(f.left, gain), right=apply_gain(f.right, gain)) for f in group]
        m = measure_range(group, rig, measure, params, getattr(source, "surface_points", None))
        if gain != 1.0:
            m = replace(m, exposure_gain=gain)
        n_ranges += 1
        n_frames += len(m.t_s)
        label = f"{m.true_range_m:.2f} m" if np.isfinite(m.true_range_m) else f"frames from t={m.t_s[0]:.3f} s"
        if len(m.uv) == 0:
            # Not "no point has N good measurements": none was measured, or even found.
            why = count_reasons(m.refusals, 2)
            skipped.append(f"{label}: no point selectable on its first frame: " + (
                f"none of {m.candidates} corners accepted by the matcher ("
                + ", ".join(f"{k} {r}" for r, k in why) + ")" if m.candidates else
                f"no corner {params.border_px} px inside the lit target and the image"))
            continue
        try:
            st = range_statistics(m.xyz_m, m.sigma_m, params.min_samples, params.max_abs_residual_sigmas)
        except TrackmeterError as exc:
            skipped.append(f"{label}: {exc}")
            continue
        if st.n_points < 3:
            skipped.append(f"{label}: only {st.n_points} point(s) measured often enough")
            continue
        measured.append(m)
        stats.append(st)
        if m.image_motion_px > params.max_still_motion_px:
            moving.append(f"{label}: the points moved {m.image_motion_px:.1f} px (median, first to last frame): "
                          "the analysis needs a still target; this range's scatter is mostly that motion")
    if not stats:
        if not skipped:
            detail = "the source gave no frames"
        elif len(skipped) <= 3:
            detail = "; ".join(skipped)
        else:  # a moving object: every frame its own "range"; one line, not one reason per frame
            detail = (f"{n_ranges} ranges of {n_frames / n_ranges:.1f} frames on average, e.g. {skipped[0]}; "
                      f"a range is the frames with one true pose: the analysis needs a still target")
        raise TrackmeterError(f"no usable range for the error analysis ({detail})")
    focal = rig.rectification.focal_px
    baseline = rig.rectification.baseline_m
    analysis = analyze_ranges(stats, focal, baseline, params.histogram_bins)
    sd_all = np.concatenate([m.sigma_disparity_px.reshape(-1) for m in measured])
    predicted_sd = float(np.nanmedian(sd_all)) if np.any(np.isfinite(sd_all)) else float("nan")
    order = sorted(range(len(stats)), key=lambda i: stats[i].range_m)  # stable, as analyze_ranges sorts
    return AnalysisRun(
        analysis,
        tuple(measured[i] for i in order),
        tuple(stats[i] for i in order),
        predicted_sd,
        tuple(skipped),
        params.max_abs_residual_sigmas,
        params.min_samples,
        tuple(moving),
        tuple(gains),
        tuple(without_truth),
    )
