"""Chessboard stereo calibration in steps, on OpenCV's calibration functions.

The steps (paper section 2.A: "multi-step calibration, linear initialisation then
Levenberg-Marquardt"):

1. :func:`detect_corners`: chessboard inner corners (``findChessboardCorners``), refined to
   sub-pixel with ``cornerSubPix`` (half-window ``subpix_window_px``).
2. :func:`calibrate_camera`: each camera on its own with ``calibrateCameraExtended``: Zhang's
   closed-form (linear) initialisation from the plane homographies, then Levenberg-Marquardt
   on the reprojection error; gives per-view errors and parameter standard deviations.
3. :func:`calibrate_stereo`: both cameras refined jointly with ``stereoCalibrateExtended``
   starting from step 2 (every intrinsic left free, ``CALIB_USE_INTRINSIC_GUESS``), so the
   extrinsics ``R``, ``T`` and the intrinsics share one least-squares solution. Views whose
   reprojection error is far above the others (:func:`find_outlier_view`) are dropped and the
   whole calibration repeated without them, one view at a time. Before that, where the joint
   fit is far worse than the corners allow (``pair_check_rms_px``), pairs whose two images did
   not see the board at one moment (a numbering off by one, two swapped) are found
   (:func:`pair_agreement`: the two cameras' own board poses put the right camera somewhere
   against the left, the same place in every true pair) and dropped, or the calibration
   refused when most disagree.
4. Standard deviations of the joint solution (:func:`stereo_parameter_std`): OpenCV's stereo
   functions give none, so they come from the Gauss-Newton covariance
   ``sigma² (JᵀJ)⁻¹``, ``sigma² = |r|² / (m - n)`` — the same estimate
   ``calibrateCameraExtended`` reports for one camera (a test checks the two agree).
5. :func:`rectification_check`: the corners of both images mapped through the rig's
   rectification should land on equal rows; their vertical disparity measures what is left.

Frames: ``cam`` = left camera, ``cam1`` = right camera, ``p_cam1 = R @ p_cam + T``. Lengths
come out in the unit of ``square`` (metres for a rig file). Pixels: OpenCV convention, the
centre of the top-left pixel is (0, 0) (``findChessboardCorners`` and ``cornerSubPix`` use it).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Callable, Sequence, cast

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from trackmeter.core.params import check_params, param
from trackmeter.core.stereo import Camera, StereoRig
from trackmeter.errors import TrackmeterError

FloatArray = NDArray[np.float64]

#: distortion model name -> (number of coefficients, OpenCV flags)
DISTORTION_MODELS: dict[str, tuple[int, int]] = {
    "k1k2p1p2": (5, cv2.CALIB_FIX_K3),
    "k1k2p1p2k3": (5, 0),
    "rational": (8, cv2.CALIB_RATIONAL_MODEL),
}


@dataclass(frozen=True)
class CalibrationParams:
    """Tunables of ``trackmeter calibrate``."""

    subpix_window_px: int = param(
        5, "cornerSubPix half-window, px (winSize; the search window is 2*N+1 px wide)", min=1, max=30
    )
    subpix_max_iterations: int = param(30, "cornerSubPix iteration limit", min=1, max=1000)
    subpix_epsilon_px: float = param(0.01, "cornerSubPix stops when a corner moves less than this, px", min=0.0, max=1.0)
    distortion_model: str = param(
        "k1k2p1p2k3",
        "lens distortion model: k1k2p1p2 (4 coefficients), k1k2p1p2k3 (5) or rational (8)",
        choices=tuple(DISTORTION_MODELS),
    )
    lm_max_iterations: int = param(100, "Levenberg-Marquardt iteration limit of each calibration step", min=1, max=10000)
    lm_epsilon: float = param(1e-9, "Levenberg-Marquardt stops when the relative parameter change is below this", min=0.0, max=1.0)
    reject_ratio: float = param(
        2.0, "a view is an outlier only if its RMS exceeds this multiple of the median view RMS", min=1.0
    )
    reject_mad_sigmas: float = param(
        4.0, "... and exceeds the median by this many robust sigmas (1.4826 x median absolute deviation)", min=0.0
    )
    reject_min_rms_px: float = param(
        0.25, "... and exceeds this RMS, px: a view fitted better holds no gross error (one corner of 54 "
        "2 px off gives 0.27 px) and is kept, however sharp the others", min=0.0,
    )
    min_views: int = param(5, "never reject views below this many; fewer usable views is an error", min=3)
    pair_check_rms_px: float = param(
        1.0, "when the joint fit's RMS exceeds this, px, the pairs are checked for images not taken together "
        "(pair_max_deg, pair_max_baseline_fraction)", min=0.0,
    )
    pair_max_deg: float = param(
        3.0, "a pair is mismatched (its images not taken together) when the right camera's orientation against "
        "the left, from each camera's own view of the board, is turned more than this from the other pairs', deg",
        min=0.0,
    )
    pair_max_baseline_fraction: float = param(
        0.5, "... or its position is farther than this fraction of the baseline from theirs", min=0.0,
    )


# --------------------------------------------------------------------------- step 1: corners

    def __post_init__(self) -> None:
        check_params(self)  # declared ranges and choices, as the config loader checks them


def parse_pattern(text: str) -> tuple[int, int]:
    """``"9x6"`` → ``(9, 6)``: inner corners per row (columns) and per column (rows).

    Raises:
        TrackmeterError: not two integers ≥ 3 separated by ``x``.
    """
    parts = text.lower().replace("×", "x").split("x")
    try:
        if len(parts) != 2:
            raise ValueError
        cols, rows = int(parts[0]), int(parts[1])
    except ValueError:
        raise TrackmeterError(f"expected the pattern as COLSxROWS inner corners (e.g. 9x6), got {text!r}") from None
    if cols < 3 or rows < 3:  # OpenCV's findChessboardCorners asserts on fewer
        raise TrackmeterError(f"a chessboard pattern needs at least 3x3 inner corners, got {text!r}")
    return cols, rows


def object_points(pattern: tuple[int, int], square: float) -> NDArray[np.float32]:
    """Chessboard inner corners in the board frame, (cols*rows, 3) float32, z = 0.

    Row-major in the order ``findChessboardCorners`` reports them: x = column * square,
    y = row * square, in the unit of ``square``.
    """
    cols, rows = pattern
    if not square > 0:
        raise TrackmeterError(f"the square size must be positive, got {square}")
    grid = np.zeros((rows * cols, 3), np.float32)
    grid[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square
    return grid


def detect_corners(
    image: NDArray[np.uint8], pattern: tuple[int, int], params: CalibrationParams = CalibrationParams()
) -> FloatArray | None:
    """Sub-pixel chessboard inner corners of an 8-bit grey image, (cols*rows, 2) px, or None.

    ``findChessboardCorners`` (adaptive threshold, normalised image) finds the corners to
    about a pixel, then ``cornerSubPix`` refines each to where the image gradients around it
    are orthogonal to the direction to the corner (Förstner).
    """
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(image, pattern, flags=flags)
    if not found or corners is None:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, params.subpix_max_iterations, params.subpix_epsilon_px)
    win = params.subpix_window_px
    corners = cv2.cornerSubPix(image, corners, (win, win), (-1, -1), criteria)
    return np.asarray(corners, dtype=float).reshape(-1, 2)


# --------------------------------------------------------------------------- step 2: one camera


@dataclass(frozen=True, eq=False)
class MonoCalibration:
    """One camera calibrated on its own (step 2).

    Attributes:
        camera: intrinsics and distortion.
        rms_px: RMS reprojection error over all corners of all views, px.
        per_view_rms_px: (V,) RMS reprojection error of each view, px.
        std_intrinsics: standard deviations of ``(fx, fy, cx, cy, k1, k2, p1, p2, k3, ...)``
            (as many distortion terms as ``camera.dist``), px and unitless; 0 for fixed ones.
        rvecs, tvecs: (V,3) board poses in this camera's frame (Rodrigues, unit of square).
    """

    camera: Camera
    rms_px: float
    per_view_rms_px: FloatArray
    std_intrinsics: FloatArray
    rvecs: FloatArray
    tvecs: FloatArray


def _criteria(params: CalibrationParams) -> tuple[int, int, float]:
    return (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, params.lm_max_iterations, params.lm_epsilon)


def calibrate_camera(
    points_board: Sequence[ArrayLike],
    uv: Sequence[ArrayLike],
    image_size: tuple[int, int],
    params: CalibrationParams = CalibrationParams(),
) -> MonoCalibration:
    """Calibrate one camera: linear initialisation, then Levenberg-Marquardt (OpenCV).

    Args:
        points_board: per view (N,3) board points, unit of the square.
        uv: per view (N,2) detected corners, px.
        image_size: ``(width, height)``, px.
    """
    n_dist, flags = DISTORTION_MODELS[params.distortion_model]
    obj = [np.asarray(p, np.float32).reshape(-1, 1, 3) for p in points_board]
    img = [np.asarray(p, np.float32).reshape(-1, 1, 2) for p in uv]
    # The stubs take no None for an output array (cameraMatrix) that OpenCV allocates.
    rms, K, dist, rvecs, tvecs, std_in, _std_ex, per_view = cv2.calibrateCameraExtended(  # type: ignore[call-overload]
        obj, img, image_size, None, np.zeros(n_dist), flags=flags, criteria=_criteria(params)
    )
    dist = np.asarray(dist, float).ravel()[:n_dist]
    return MonoCalibration(
        camera=Camera(image_size[0], image_size[1], K, dist),
        rms_px=float(rms),
        per_view_rms_px=np.asarray(per_view, float).ravel(),
        std_intrinsics=np.asarray(std_in, float).ravel()[: 4 + n_dist],
        rvecs=np.asarray(rvecs, float).reshape(-1, 3),
        tvecs=np.asarray(tvecs, float).reshape(-1, 3),
    )


# --------------------------------------------------------------------------- step 3: the pair


@dataclass(frozen=True, eq=False)
class RejectedView:
    """A view left out of the calibration, and why.

    Attributes:
        index: index into the input views.
        rms_px: ``(left, right)`` RMS of the view when it was rejected, px (NaN if no corners).
        reason: one line for the report.
    """

    index: int
    rms_px: tuple[float, float]
    reason: str


@dataclass(frozen=True, eq=False)
class RectificationCheck:
    """Vertical disparity ``v_left - v_right`` of the rectified corners (ideally 0), px.

    Attributes:
        rms_px, max_abs_px: over all corners of the used views.
        per_view_rms_px: (V,) per used view.
    """

    rms_px: float
    max_abs_px: float
    per_view_rms_px: FloatArray


@dataclass(frozen=True, eq=False)
class StereoCalibration:
    """Result of :func:`calibrate_stereo`.

    Attributes:
        rig: the calibrated rig (``rms_px`` set), lengths in the unit of the square.
        rms_px: RMS reprojection error of the joint refinement over both images, px.
        used_views: indices (into the input views) of the views in the final solution.
        per_view_rms_px: (V,2) RMS of each used view in the left and right image, px.
        rejected: views left out, in the order they were rejected.
        left, right: the per-camera calibrations (step 2) on the used views.
        std: standard deviations of the joint solution, name → value: ``fx1 fy1 cx1 cy1``
            (px), ``D1`` terms ``k1_1 k2_1 p1_1 p2_1 k3_1`` ..., the same with ``_2`` / ``2``,
            ``rx ry rz`` (rotation vector of R, rad), ``tx ty tz`` (unit of square) and
            ``baseline``.
        E, F: essential and fundamental matrices of the pair.
        rectification: the rectification check on the used views.
    """

    rig: StereoRig
    rms_px: float
    used_views: tuple[int, ...]
    per_view_rms_px: FloatArray
    rejected: tuple[RejectedView, ...]
    left: MonoCalibration
    right: MonoCalibration
    std: dict[str, float]
    E: FloatArray
    F: FloatArray
    rectification: RectificationCheck


def match_corner_order(uv_left: NDArray[np.float32], uv_right: NDArray[np.float32]) -> NDArray[np.float32]:
    """The right image's corners in the left image's order.

    ``findChessboardCorners`` may report a board's corners starting from the opposite corner
    in the two images (a 180-degree ambiguity of the pattern). In a side-by-side rig the board
    appears with about the same orientation in both images, so when the first-to-last corner
    directions point opposite ways, the right list is reversed.
    """
    d_left = uv_left[-1] - uv_left[0]
    d_right = uv_right[-1] - uv_right[0]
    return uv_right[::-1].copy() if float(d_left @ d_right) < 0 else uv_right


def relative_poses(left: MonoCalibration, right: MonoCalibration) -> tuple[FloatArray, FloatArray]:
    """Per view, where the right camera is against the left by the two cameras' own board
    poses: ``R_i = R_right,i R_left,iᵀ``, ``T_i = t_right,i - R_i t_left,i`` (``p_cam1 = R p_cam
    + T``, as the rig). A rigid rig whose two images of a view were taken together gives every
    view the same, up to the board poses' noise.

    Returns:
        ``(R, T)``: (V,3,3) and (V,3), T in the unit of the square.
    """
    from scipy.spatial.transform import Rotation

    R_left = Rotation.from_rotvec(left.rvecs).as_matrix()
    R_right = Rotation.from_rotvec(right.rvecs).as_matrix()
    R = R_right @ np.transpose(R_left, (0, 2, 1))
    T = right.tvecs - np.einsum("vij,vj->vi", R, left.tvecs)
    return R, T


@dataclass(frozen=True, eq=False)
class PairAgreement:
    """How far each view's :func:`relative_poses` lies from the agreeing pairs' mean.

    Attributes:
        agree: (V,) bool, the view is among the largest set of views that agree with one
            another within ``pair_max_deg`` and ``pair_max_baseline_fraction``.
        angle_deg: (V,) rotation between the view's relative orientation and the mean, deg.
        shift_fraction: (V,) distance of its relative position from the mean over the
            baseline (the views' median length of ``T``).
    """

    agree: NDArray[np.bool_]
    angle_deg: FloatArray
    shift_fraction: FloatArray


def pair_agreement(left: MonoCalibration, right: MonoCalibration,
                   params: CalibrationParams = CalibrationParams()) -> PairAgreement:
    """Which views' two images show the board at one moment: the largest set of views whose
    :func:`relative_poses` agree, each within ``pair_max_deg`` and ``pair_max_baseline_fraction``
    of a member's (the member with the most such neighbours), then measured against their mean.

    Why: a pair whose images were taken at different moments (the right images numbered one
    off the left ones, two swapped) fits each camera alone as well as any, and the joint fit
    spreads its error over every view (OpenCV's 13 sample pairs with one number off: joint RMS
    41 px against 0.2 px for each camera, every view alike, so no view stands out). Their
    relative poses differ by the board's motion between the two moments (12-124 deg there),
    where true pairs agree within 0.4 deg and 3 % of the baseline.
    """
    from scipy.spatial.transform import Rotation

    R, T = relative_poses(left, right)
    V = len(T)
    # angle between every two views' relative orientations, and their distance over the baseline
    cos = (np.einsum("aij,bij->ab", R, R) - 1.0) / 2.0
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    # Distances over the baseline; over a thousandth of the board's distance where the
    # "baseline" is none (copies of one camera's images: the same place, refused later as such).
    board_distance = float(np.median(np.linalg.norm(left.tvecs, axis=1)))
    baseline = max(float(np.median(np.linalg.norm(T, axis=1))), 1e-3 * board_distance)
    shift = np.linalg.norm(T[:, None, :] - T[None, :, :], axis=2) / baseline
    near = (angle <= params.pair_max_deg) & (shift <= params.pair_max_baseline_fraction)
    centre = max(range(V), key=lambda i: (int(near[i].sum()), -float(angle[i][near[i]].sum())))
    members = near[centre]
    R_mean = Rotation.from_matrix(R[members]).mean()
    T_mean = T[members].mean(axis=0)
    angle_deg = np.degrees((Rotation.from_matrix(R) * R_mean.inv()).magnitude())
    shift_fraction = np.linalg.norm(T - T_mean, axis=1) / baseline
    agree = (angle_deg <= params.pair_max_deg) & (shift_fraction <= params.pair_max_baseline_fraction)
    return PairAgreement(agree, angle_deg, shift_fraction)


def find_outlier_view(per_view_rms_px: ArrayLike, params: CalibrationParams = CalibrationParams()) -> tuple[int, str] | None:
    """The worst view if it is an outlier, as ``(position, reason)``, else None.

    A view's error is the larger of its left and right RMS. It is an outlier when that error
    is both ``reject_ratio`` times the median view error and more than ``reject_mad_sigmas``
    robust standard deviations (1.4826 × median absolute deviation) above the median: the
    first rule keeps a tight set of good views intact (their spread is tiny, so the second
    alone would flag ordinary scatter), the second keeps a noisy but uniform set intact. And
    it must exceed ``reject_min_rms_px``: on sharp images (rendered boards, 0.05-0.07 px) the
    first two rules dropped views at 0.11-0.12 px that were only noisier, and the RMS then
    reported fell below what the corners allow (an outside probe).

    Args:
        per_view_rms_px: (V,) or (V,2) per-view RMS errors, px.
    """
    e = np.asarray(per_view_rms_px, dtype=float)
    e = e.max(axis=1) if e.ndim == 2 else e
    if len(e) < 3:
        return None
    median = float(np.median(e))
    sigma = 1.4826 * float(np.median(np.abs(e - median)))
    worst = int(np.argmax(e))
    threshold = max(params.reject_ratio * median, median + params.reject_mad_sigmas * sigma, params.reject_min_rms_px)
    if e[worst] > threshold:
        return worst, (
            f"RMS {e[worst]:.3f} px > {threshold:.3f} px "
            f"(max of {params.reject_ratio:g} x median {median:.3f} px, median + "
            f"{params.reject_mad_sigmas:g} robust sigma {sigma:.3f} px and {params.reject_min_rms_px:g} px)"
        )
    return None


def rectification_check(rig: StereoRig, uv_left: Sequence[ArrayLike], uv_right: Sequence[ArrayLike]) -> RectificationCheck:
    """Vertical disparity of corresponding corners after rectification (0 for a perfect rig).

    Uses :meth:`trackmeter.core.stereo.Rectification.rectify_points` on each image's corners.
    """
    rect = rig.rectification
    per_view = []
    all_dv = []
    for ul, ur in zip(uv_left, uv_right):
        dv = rect.rectify_points(ul, 0)[:, 1] - rect.rectify_points(ur, 1)[:, 1]
        per_view.append(float(np.sqrt(np.mean(dv**2))))
        all_dv.append(dv)
    dv = np.concatenate(all_dv)
    return RectificationCheck(
        rms_px=float(np.sqrt(np.mean(dv**2))),
        max_abs_px=float(np.max(np.abs(dv))),
        per_view_rms_px=np.asarray(per_view),
    )


def _stereo_step(
    obj: list[NDArray[np.float32]],
    uv_left: list[NDArray[np.float32]],
    uv_right: list[NDArray[np.float32]],
    image_size: tuple[int, int],
    params: CalibrationParams,
) -> tuple[MonoCalibration, MonoCalibration, tuple]:
    left = calibrate_camera(obj, uv_left, image_size, params)
    right = calibrate_camera(obj, uv_right, image_size, params)
    _, model_flags = DISTORTION_MODELS[params.distortion_model]
    # The stubs take no None for the output arrays (R, T) that OpenCV allocates.
    out = cv2.stereoCalibrateExtended(  # type: ignore[call-overload]
        [o.reshape(-1, 1, 3) for o in obj],
        [u.reshape(-1, 1, 2) for u in uv_left],
        [u.reshape(-1, 1, 2) for u in uv_right],
        left.camera.K.copy(),
        left.camera.dist.copy(),
        right.camera.K.copy(),
        right.camera.dist.copy(),
        image_size,
        None,
        None,
        flags=cv2.CALIB_USE_INTRINSIC_GUESS | model_flags,
        criteria=_criteria(params),
    )
    return left, right, out


def calibrate_stereo(
    uv_left: Sequence[ArrayLike | None],
    uv_right: Sequence[ArrayLike | None],
    pattern: tuple[int, int],
    square: float,
    image_size: tuple[int, int],
    params: CalibrationParams = CalibrationParams(),
) -> StereoCalibration:
    """Calibrate a stereo rig from chessboard corners seen in both images of each view.

    Steps 2-5 of the module docstring: each camera alone, then jointly; the worst view is
    dropped and everything recomputed while :func:`find_outlier_view` finds one (and at least
    ``min_views`` views would remain); then standard deviations and the rectification check.

    Args:
        uv_left, uv_right: per view the (cols*rows, 2) corners from :func:`detect_corners`, px,
            or None where the board was not found (those views are rejected and said so).
        pattern: ``(cols, rows)`` inner corners.
        square: side of a chessboard square; the unit of ``T`` and of the baseline (m for a
            rig file).
        image_size: ``(width, height)`` of both images, px.

    Raises:
        TrackmeterError: fewer than ``min_views`` views with corners in both images.
    """
    if len(uv_left) != len(uv_right):
        raise TrackmeterError(f"{len(uv_left)} left views but {len(uv_right)} right views")
    board = object_points(pattern, square)
    n_corners = len(board)
    rejected: list[RejectedView] = []
    used: list[int] = []
    for i, (ul, ur) in enumerate(zip(uv_left, uv_right)):
        missing = [side for side, u in (("left", ul), ("right", ur)) if u is None or len(np.asarray(u).reshape(-1, 2)) != n_corners]
        if missing:
            rejected.append(RejectedView(i, (np.nan, np.nan), f"no {pattern[0]}x{pattern[1]} chessboard found in the {' and '.join(missing)} image"))
        else:
            used.append(i)
    if len(used) < params.min_views:
        raise TrackmeterError(
            f"the {pattern[0]}x{pattern[1]} chessboard was found in both images of only {len(used)} of "
            f"{len(uv_left)} pairs; at least {params.min_views} are needed"
        )
    L = {i: np.asarray(uv_left[i], np.float32).reshape(-1, 2) for i in used}
    Rr = {i: match_corner_order(L[i], np.asarray(uv_right[i], np.float32).reshape(-1, 2)) for i in used}

    pairs_checked = False
    while True:
        obj = [board] * len(used)
        left, right, out = _stereo_step(obj, [L[i] for i in used], [Rr[i] for i in used], image_size, params)
        if not pairs_checked and float(out[0]) > params.pair_check_rms_px:
            # A joint fit far worse than the corners allow: are some pairs' images not taken
            # together? Asked only then, since a camera's own fit that stopped in a poorer
            # solution (a wide lens) scatters its board poses while the joint fit is good.
            pairs_checked = True
            kept = _without_mismatched_pairs(used, left, right, params, rejected)
            if len(kept) < len(used):
                used = kept
                continue
        per_view = np.asarray(out[11], float).reshape(-1, 2)
        outlier = find_outlier_view(per_view, params) if len(used) > params.min_views else None
        if outlier is None:
            break
        pos, reason = outlier
        rejected.append(RejectedView(used[pos], (float(per_view[pos, 0]), float(per_view[pos, 1])), reason))
        used.pop(pos)

    rms, K1, D1, K2, D2, R, T, E, F, rvecs, tvecs, _ = out
    n_dist, _ = DISTORTION_MODELS[params.distortion_model]
    size = image_size
    rig = StereoRig(
        Camera(size[0], size[1], K1, np.asarray(D1, float).ravel()[:n_dist]),
        Camera(size[0], size[1], K2, np.asarray(D2, float).ravel()[:n_dist]),
        R,
        np.asarray(T, float).ravel(),
        rms_px=float(rms),
        name="calibrated",
    )
    uv_l = [L[i] for i in used]
    uv_r = [Rr[i] for i in used]
    std = stereo_parameter_std(
        rig, [board] * len(used), uv_l, uv_r, np.asarray(rvecs, float).reshape(-1, 3), np.asarray(tvecs, float).reshape(-1, 3), params
    )
    return StereoCalibration(
        rig=rig,
        rms_px=float(rms),
        used_views=tuple(used),
        per_view_rms_px=per_view,
        rejected=tuple(rejected),
        left=left,
        right=right,
        std=std,
        E=np.asarray(E, float),
        F=np.asarray(F, float),
        rectification=rectification_check(rig, uv_l, uv_r),
    )


def _without_mismatched_pairs(used: list[int], left: MonoCalibration, right: MonoCalibration,
                              params: CalibrationParams, rejected: list[RejectedView]) -> list[int]:
    """``used`` without the views :func:`pair_agreement` finds mismatched on the two cameras'
    own calibrations over them (``left``, ``right``), each appended to ``rejected`` with why
    (its RMS is each camera's own fit's: the joint one spreads a mismatch over every view).

    Raises:
        TrackmeterError: fewer than half of the views (or than ``min_views``) agree: the
            images are not paired as taken, and no subset can be trusted to be the rig.
    """
    pairs = pair_agreement(left, right, params)
    n_agree = int(pairs.agree.sum())
    if n_agree < max(params.min_views, (len(used) + 1) // 2):
        raise TrackmeterError(
            f"the pairs disagree on where the right camera is against the left: only {n_agree} of {len(used)} agree "
            f"within {params.pair_max_deg:g} deg and {params.pair_max_baseline_fraction:.0%} of the baseline (the "
            f"others are off by a median {float(np.median(pairs.angle_deg[~pairs.agree])):.1f} deg), though each "
            f"camera alone fits its images to {left.rms_px:.2f} and {right.rms_px:.2f} px: were the left and right "
            "images of one number taken at the same moment? (numbers off by one pair each left image with another "
            "view's right one)")
    kept = []
    for pos, i in enumerate(used):
        if pairs.agree[pos]:
            kept.append(i)
        else:
            rejected.append(RejectedView(i, (float(left.per_view_rms_px[pos]), float(right.per_view_rms_px[pos])),
                                         f"not taken together: the right camera against the left is "
                                         f"{pairs.angle_deg[pos]:.1f} deg and {pairs.shift_fraction[pos]:.0%} of the "
                                         "baseline off the other pairs' (a mismatched pair?)"))
    return kept


# --------------------------------------------------------------------------- step 4: uncertainty


def _free_intrinsics(params: CalibrationParams) -> tuple[list[int], list[str]]:
    """Indices into ``[fx, fy, cx, cy, dist...]`` that the calibration leaves free, and names."""
    n_dist, flags = DISTORTION_MODELS[params.distortion_model]
    names = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"][: 4 + n_dist]
    free = [j for j in range(len(names)) if not (names[j] == "k3" and flags & cv2.CALIB_FIX_K3)]
    return free, names


#: Condition number of the column-scaled reprojection Jacobian above which parameters are said
#: not to be determined separately: the linearised standard deviations of the 5-coefficient model
#: (condition 3e2 and 1e3 on OpenCV's sample boards and a rendered set) match a Monte-Carlo
#: refit's, those of the rational model (1.3e5 and 2.5e6) were 4 and 5000 times too small.
MAX_SCALED_CONDITION = 1e4


def reprojection_covariance(residual_fn: Callable[[FloatArray], FloatArray], x0: FloatArray,
                            step: FloatArray, names: Sequence[str] | None = None) -> tuple[FloatArray, float]:
    """Gauss-Newton covariance ``sigma² (JᵀJ)⁻¹`` of a least-squares solution ``x0``.

    ``J`` by central differences of ``residual_fn`` with per-parameter ``step``;
    ``sigma² = |r(x0)|² / (m - n)`` is the residual variance per coordinate, as in OpenCV's
    ``calibrateCameraExtended``. The inverse is taken from the SVD of ``J`` with its columns
    scaled to unit norm (``(JᵀJ)⁻¹ = D⁻¹ V S⁻² Vᵀ D⁻¹``): ``JᵀJ`` itself squares the condition
    number, and its pseudo-inverse dropped the near-dependent directions of the rational model
    (condition 1e17), giving standard deviations 20 times too small where they should be largest.
    When the scaled condition number exceeds :data:`MAX_SCALED_CONDITION` the parameters that
    make up the near-dependent directions (``names``, one per parameter) are warned about: no
    linearised standard deviation of theirs is to be trusted. Returns ``(covariance (n,n), sigma²)``.
    """
    r0 = residual_fn(x0)
    J = np.empty((len(r0), len(x0)))
    for j in range(len(x0)):
        dx = np.zeros_like(x0)
        dx[j] = step[j]
        J[:, j] = (residual_fn(x0 + dx) - residual_fn(x0 - dx)) / (2 * step[j])
    dof = len(r0) - len(x0)
    if dof <= 0:
        raise TrackmeterError("too few corners to estimate parameter uncertainties")
    sigma2 = float(r0 @ r0) / dof
    scale = np.linalg.norm(J, axis=0)
    scale[scale == 0] = 1.0  # a parameter nothing depends on: an infinite variance below
    _, S, Vt = np.linalg.svd(J / scale, full_matrices=False)
    with np.errstate(divide="ignore"):
        cov = (Vt.T / S**2) @ Vt / np.outer(scale, scale)
    condition = float(S[0] / S[-1]) if S[-1] > 0 else np.inf
    if names is not None and condition > MAX_SCALED_CONDITION:
        # Each parameter's largest share in a direction the views leave nearly undetermined.
        weak = np.max(Vt[S * MAX_SCALED_CONDITION < S[0]] ** 2, axis=0)
        part = list(dict.fromkeys(name for name, share in zip(names, weak) if share > 0.05))
        warnings.warn(f"{', '.join(part)} are not determined separately by these views (nearly dependent: condition "
                      f"number {condition:.2g} of the scaled Jacobian, above {MAX_SCALED_CONDITION:g}): their standard "
                      "deviations are unreliable, in truth much larger; the projection they make together is "
                      "determined", stacklevel=3)
    return cast(FloatArray, sigma2 * cov), sigma2  # numpy's stubs: floating[Any]


def _camera_vector(cam: Camera, n_dist: int) -> FloatArray:
    K = cam.K
    dist = np.zeros(n_dist)
    dist[: min(n_dist, cam.dist.size)] = cam.dist[:n_dist]
    return np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], dist])


def _camera_from_vector(v: FloatArray) -> tuple[FloatArray, FloatArray]:
    K = np.array([[v[0], 0.0, v[2]], [0.0, v[1], v[3]], [0.0, 0.0, 1.0]])
    return K, v[4:]


def mono_parameter_std(
    mono: MonoCalibration,
    points_board: Sequence[ArrayLike],
    uv: Sequence[ArrayLike],
    params: CalibrationParams = CalibrationParams(),
) -> FloatArray:
    """Standard deviations of ``(fx, fy, cx, cy, dist...)`` of one camera by :func:`reprojection_covariance`.

    The same estimate ``calibrateCameraExtended`` returns in ``stdDeviationsIntrinsics``;
    it exists to check the Jacobian machinery that :func:`stereo_parameter_std` relies on.
    """
    n_dist, _ = DISTORTION_MODELS[params.distortion_model]
    free, _ = _free_intrinsics(params)
    cam0 = _camera_vector(mono.camera, n_dist)
    obj = [np.asarray(p, float).reshape(-1, 3) for p in points_board]
    meas = np.concatenate([np.asarray(u, float).reshape(-1, 2) for u in uv]).ravel()
    V = len(obj)
    x0 = np.concatenate([cam0[free], mono.rvecs.ravel(), mono.tvecs.ravel()])
    nf = len(free)

    def residual(x: FloatArray) -> FloatArray:
        cam = cam0.copy()
        cam[free] = x[:nf]
        K, dist = _camera_from_vector(cam)
        rv = x[nf : nf + 3 * V].reshape(V, 3)
        tv = x[nf + 3 * V :].reshape(V, 3)
        proj = [cv2.projectPoints(o, rv[i], tv[i], K, dist)[0].reshape(-1, 2) for i, o in enumerate(obj)]
        return np.concatenate(proj).ravel() - meas

    cov, _ = reprojection_covariance(residual, x0, _steps(x0))
    std = np.zeros(4 + n_dist)
    std[free] = np.sqrt(np.clip(np.diag(cov)[:nf], 0, None))
    return std


def _steps(x: FloatArray) -> FloatArray:
    return 1e-6 * np.maximum(np.abs(x), 1e-2)


def stereo_parameter_std(
    rig: StereoRig,
    points_board: Sequence[ArrayLike],
    uv_left: Sequence[ArrayLike],
    uv_right: Sequence[ArrayLike],
    rvecs: FloatArray,
    tvecs: FloatArray,
    params: CalibrationParams = CalibrationParams(),
) -> dict[str, float]:
    """Standard deviations of the joint stereo solution (see :class:`StereoCalibration` ``std``).

    Parameters are those ``stereoCalibrateExtended`` refined: both cameras' free intrinsics,
    the rotation vector and translation of ``R``, ``T``, and each view's board pose in the
    left camera (``rvecs``, ``tvecs``, (V,3)). The right camera sees the board at
    ``R R_i``, ``R t_i + T``.
    """
    n_dist, _ = DISTORTION_MODELS[params.distortion_model]
    free, names = _free_intrinsics(params)
    nf = len(free)
    cam1_0 = _camera_vector(rig.left, n_dist)
    cam2_0 = _camera_vector(rig.right, n_dist)
    obj = [np.asarray(p, float).reshape(-1, 3) for p in points_board]
    meas = np.concatenate(
        [np.concatenate([np.asarray(a, float).reshape(-1, 2), np.asarray(b, float).reshape(-1, 2)]) for a, b in zip(uv_left, uv_right)]
    ).ravel()
    V = len(obj)
    rvec_R = cv2.Rodrigues(rig.R)[0].ravel()
    x0 = np.concatenate([cam1_0[free], cam2_0[free], rvec_R, rig.T, rvecs.ravel(), tvecs.ravel()])
    base = 2 * nf + 6

    def residual(x: FloatArray) -> FloatArray:
        c1, c2 = cam1_0.copy(), cam2_0.copy()
        c1[free] = x[:nf]
        c2[free] = x[nf : 2 * nf]
        K1, d1 = _camera_from_vector(c1)
        K2, d2 = _camera_from_vector(c2)
        R = cv2.Rodrigues(x[2 * nf : 2 * nf + 3])[0]
        T = x[2 * nf + 3 : 2 * nf + 6]
        rv = x[base : base + 3 * V].reshape(V, 3)
        tv = x[base + 3 * V :].reshape(V, 3)
        out = []
        for i, o in enumerate(obj):
            Ri = cv2.Rodrigues(rv[i])[0]
            out.append(cv2.projectPoints(o, rv[i], tv[i], K1, d1)[0].reshape(-1, 2))
            r2 = cv2.Rodrigues(R @ Ri)[0]
            out.append(cv2.projectPoints(o, r2, R @ tv[i] + T, K2, d2)[0].reshape(-1, 2))
        return np.concatenate(out).ravel() - meas

    labels = ([f"{names[j]}{i}" if j < 4 else f"{names[j]}_{i}" for i in (1, 2) for j in free]
              + ["R", "R", "R", "T", "T", "T"] + [f"view {v + 1}'s board pose" for _ in range(2) for v in range(V)
                                                  for _ in range(3)])
    cov, _ = reprojection_covariance(residual, x0, _steps(x0), labels)
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    std: dict[str, float] = {}
    for cam_i, offset in ((1, 0), (2, nf)):
        for k, j in enumerate(free):
            std[f"{names[j]}{cam_i}" if j < 4 else f"{names[j]}_{cam_i}"] = float(sd[offset + k])
    for k, name in enumerate(("rx", "ry", "rz", "tx", "ty", "tz")):
        std[name] = float(sd[2 * nf + k])
    T = rig.T
    g = T / np.linalg.norm(T)
    cov_T = cov[2 * nf + 3 : 2 * nf + 6, 2 * nf + 3 : 2 * nf + 6]
    std["baseline"] = float(np.sqrt(max(float(g @ cov_T @ g), 0.0)))
    return std
