"""Camera and stereo-rig geometry: projection, rectification, triangulation, error propagation.

Frames: ``cam`` is the LEFT camera's optical frame (OpenCV: +x right, +y down, +z forward);
``cam1`` the right camera's, with ``p_cam1 = R @ p_cam + T`` (OpenCV ``stereoCalibrate``).
``rect`` is the rectified left frame, ``p_rect = R1 @ p_cam`` (OpenCV ``stereoRectify``).

Pixels: (u, v) = (column, row) with the CENTRE of the top-left pixel at (0, 0), as OpenCV's
projection functions and ``remap`` use it.

Projection and distortion go through OpenCV (``projectPoints``, ``undistortPoints``,
``stereoRectify``, ``initUndistortRectifyMap``); nothing here re-implements them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import cast

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from trackmeter.core.checks import as_rows, rotation_problem
from trackmeter.core.transforms import procrustes_rotation
from trackmeter.errors import TrackmeterError

FloatArray = NDArray[np.float64]


_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)


def _undistort_points(
    pts: FloatArray, K: FloatArray, dist: FloatArray, R: FloatArray | None = None, P: FloatArray | None = None
) -> FloatArray:
    """OpenCV's iterative undistortion run to convergence (~1e-6 px), (N,1,2) → (N,2).

    The default 5 iterations of ``cv2.undistortPoints`` leave errors of a few hundredths of a
    pixel with real lenses: too much for sub-pixel work. OpenCV 4 names the variant with
    termination criteria ``undistortPointsIter``; OpenCV 5 takes them in ``undistortPoints``.
    """
    if hasattr(cv2, "undistortPointsIter"):
        out = cv2.undistortPointsIter(pts, K, dist, R, P, _UNDISTORT_CRITERIA)
    else:
        out = cv2.undistortPoints(pts, K, dist, R=R, P=P, criteria=_UNDISTORT_CRITERIA)
    return np.asarray(out, dtype=float).reshape(-1, 2)


def whole_pixels(value: object) -> int | None:
    """``value`` as a whole number of pixels, None when it is none (640.7, NaN, text)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        return None
    return int(value) if math.isfinite(value) and float(value).is_integer() else None


def _as_matrix(value: ArrayLike, shape: tuple[int, ...], name: str) -> FloatArray:
    array = np.asarray(value, dtype=float)
    if array.size != int(np.prod(shape)):
        raise TrackmeterError(f"{name} must have shape {shape}, got {array.shape}")
    array = array.reshape(shape)
    if not np.all(np.isfinite(array)):
        raise TrackmeterError(f"{name} has non-finite values")
    return array


def _non_negative(sigma_px: float | ArrayLike, name: str) -> None:
    """Refuse a negative standard deviation, px (scalar or array; cheap: runs every frame).
    NaN passes: a caller's marker of an unmeasured point stays its business."""
    s = np.asarray(sigma_px, dtype=float)
    if np.any(s < 0):
        raise TrackmeterError(f"{name} must be >= 0 px, got {s[s < 0].ravel()[0]:g}")


def _nearest_rotation(R: FloatArray) -> FloatArray:
    """R itself when orthonormal to working precision, else the nearest rotation (Frobenius
    norm: the polar factor ``U V^T`` of ``R = U S V^T``) when R is within
    :data:`~trackmeter.core.checks.ROTATION_TOLERANCE` of one; downstream code (rectification,
    pose) assumes an exact rotation.

    Raises:
        TrackmeterError: a reflection (det < 0) or a matrix too far from any rotation.
    """
    problem = rotation_problem(R)
    if problem is not None:
        raise TrackmeterError(problem)
    if np.abs(R.T @ R - np.eye(3)).max() <= 1e-12:
        return R  # already a rotation: keep it bit for bit (files round-trip unchanged)
    return procrustes_rotation(R)[0]


#: The focal lengths a camera is accepted with, in px per px of the image's larger side: a
#: fisheye seeing 180 deg across has about 0.3, a telescope seeing 0.06 deg about 1000.
MIN_FOCAL_PER_IMAGE, MAX_FOCAL_PER_IMAGE = 0.01, 1e4


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera with OpenCV lens distortion.

    Attributes:
        width, height: image size, px.
        K: (3,3) intrinsic matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``, px.
        dist: OpenCV distortion coefficients ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``.
    """

    width: int
    height: int
    K: FloatArray
    dist: FloatArray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self) -> None:
        width, height = whole_pixels(self.width), whole_pixels(self.height)
        if width is None or height is None:  # int() took 640.7 as 640, and NaN with numpy's own error
            raise TrackmeterError(f"image size must be whole numbers of pixels, got {self.width!r}x{self.height!r}")
        if width <= 0 or height <= 0:
            raise TrackmeterError(f"image size must be positive, got {width}x{height}")
        object.__setattr__(self, "width", width)
        object.__setattr__(self, "height", height)
        object.__setattr__(self, "K", _as_matrix(self.K, (3, 3), "K"))
        dist = np.asarray(self.dist, dtype=float)
        if dist.ndim > 2 or (dist.ndim == 2 and min(dist.shape) > 1):
            # OpenCV writes coefficients as a 1xN or Nx1 matrix; a 2x2 flattened would be read as k1 k2 p1 p2.
            raise TrackmeterError("distortion must be a row or a column of coefficients, got a "
                                  + "x".join(str(n) for n in dist.shape) + " matrix")
        dist = dist.ravel()
        if dist.size not in (0, 4, 5, 8, 12, 14):
            raise TrackmeterError(f"distortion must have 4, 5, 8, 12 or 14 finite coefficients, got {dist.size}")
        if not np.all(np.isfinite(dist)):
            raise TrackmeterError("distortion has non-finite values")
        object.__setattr__(self, "dist", dist if dist.size else np.zeros(5))
        if self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise TrackmeterError("K must have positive focal lengths")
        size = max(self.width, self.height)
        for name, f in (("fx", self.K[0, 0]), ("fy", self.K[1, 1])):
            if not MIN_FOCAL_PER_IMAGE * size <= f <= MAX_FOCAL_PER_IMAGE * size:
                # 1e300 px passed and was refused later as the right camera "turned 0 deg about its
                # viewing axis" (an outside probe): a focal length no lens has, said as such.
                raise TrackmeterError(f"K's focal length {name} = {f:g} px is no lens's for a "
                                      f"{self.width}x{self.height} image ({MIN_FOCAL_PER_IMAGE:g} to "
                                      f"{MAX_FOCAL_PER_IMAGE:g} times its larger side): K of another unit or a typo?")
        if not np.array_equal(self.K[2], [0.0, 0.0, 1.0]):
            # A pinhole K's last row is [0 0 1]; OpenCV reads only fx, fy, cx, cy (not even the
            # skew) and would ignore any other, e.g. a K scaled as a whole for a resized image.
            raise TrackmeterError(f"K's last row must be [0, 0, 1], got {np.array2string(self.K[2], separator=', ')}")
        if self.K[1, 0] != 0.0:
            # Not a camera matrix (upper triangular): OpenCV would ignore the element silently.
            raise TrackmeterError(f"K[1][0] must be 0 (K is [[fx, skew, cx], [0, fy, cy], [0, 0, 1]]), got {self.K[1, 0]:g}")
        cx, cy = self.K[0, 2], self.K[1, 2]
        if not (-self.width <= cx <= 2 * self.width and -self.height <= cy <= 2 * self.height):
            # A lens's axis meets its sensor inside the image, or near it on an off-centre crop:
            # a whole image away, K is of another image size or unit, and every point would be
            # refused as lying in the border the rectification crops.
            raise TrackmeterError(f"K's principal point ({cx:g}, {cy:g}) lies more than an image away from the "
                                  f"{self.width}x{self.height} image: K of another image size or unit?")

    @property
    def image_size(self) -> tuple[int, int]:
        """``(width, height)`` in px, the order OpenCV takes."""
        return (self.width, self.height)

    @property
    def focal_px(self) -> float:
        """Mean focal length ``(fx + fy) / 2``, px."""
        return float(0.5 * (self.K[0, 0] + self.K[1, 1]))

    def project(self, points_cam: ArrayLike) -> FloatArray:
        """Project (N,3) points of this camera's frame (m) to distorted pixels (N,2).

        As OpenCV's ``projectPoints``, a point behind the camera (z < 0) is projected too,
        through ``(x/z, y/z)``: it may land on an in-image pixel (mirrored through the centre);
        one at z = 0 through ``(x, y)`` (OpenCV takes 1/z as 1 there), an ordinary-looking pixel.
        Check ``z > 0`` before taking a pixel as seen; :meth:`contains` looks at the pixel only.

        Raises:
            TrackmeterError: points not (3,) or (N,3).
        """
        p = as_rows(points_cam, "points_cam", 3)
        if len(p) == 0:
            return np.zeros((0, 2))
        uv, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), self.K, self.dist)
        return cast(FloatArray, uv.reshape(-1, 2))

    def undistort(self, uv: ArrayLike) -> FloatArray:
        """Normalised image coordinates (N,2) ``(x/z, y/z)`` of distorted pixels (N,2).

        Iterated to convergence (see :func:`_undistort_points`).
        """
        pts = as_rows(uv, "uv", 2).reshape(-1, 1, 2)
        if len(pts) == 0:
            return np.zeros((0, 2))
        return _undistort_points(pts, self.K, self.dist)

    def contains(self, uv: ArrayLike, margin_px: float = 0.0) -> NDArray[np.bool_]:
        """Whether pixels (N,2) lie inside the image, at least ``margin_px`` from its border.

        The pixel alone: a point behind the camera can project inside the image
        (:meth:`project`), so test its depth as well before calling it visible."""
        uv = as_rows(uv, "uv", 2)
        return (
            (uv[:, 0] >= -0.5 + margin_px)
            & (uv[:, 0] <= self.width - 0.5 - margin_px)
            & (uv[:, 1] >= -0.5 + margin_px)
            & (uv[:, 1] <= self.height - 0.5 - margin_px)
        )


@dataclass(frozen=True, eq=False)
class StereoRig:
    """Two calibrated cameras and their extrinsics ``p_cam1 = R @ p_cam + T`` (T in m).

    Attributes:
        left, right: the cameras (``cam`` and ``cam1``).
        R: (3,3) rotation from the left to the right camera frame.
        T: (3,) translation, m. For a side-by-side rig with the right camera at +x,
            ``T ≈ (-baseline_m, 0, 0)``.
        rms_px: calibration RMS reprojection error when known, px.
        name: a label for reports.
    """

    left: Camera
    right: Camera
    R: FloatArray
    T: FloatArray
    rms_px: float | None = None
    name: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "R", _nearest_rotation(_as_matrix(self.R, (3, 3), "R")))
        T = _as_matrix(self.T, (3,), "T")
        if np.linalg.norm(T) <= 0:
            raise TrackmeterError("T must be non-zero (the baseline)")
        object.__setattr__(self, "T", T)
        if self.rms_px is not None:
            rms = float(self.rms_px)
            if not (math.isfinite(rms) and rms >= 0):
                raise TrackmeterError(f"rms_px must be a finite number >= 0 px, got {rms:g}")
            object.__setattr__(self, "rms_px", rms)
        if self.left.image_size != self.right.image_size:
            raise TrackmeterError(
                f"left and right images differ in size: {self.left.image_size} and {self.right.image_size}"
            )

    @property
    def image_size(self) -> tuple[int, int]:
        """``(width, height)`` of both images, px."""
        return self.left.image_size

    @property
    def baseline_m(self) -> float:
        """Distance between the two optical centres, m."""
        return float(np.linalg.norm(self.T))

    @property
    def T_cam1_cam(self) -> FloatArray:
        """4x4 transform from the left camera frame to the right camera frame."""
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.T
        return T

    def project(self, points_cam: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Project (N,3) left-camera-frame points (m) into both images: ``(uv_left, uv_right)``,
        each (N,2) distorted pixels. A point behind either camera still gets a pixel, possibly
        inside the image (:meth:`Camera.project`): check its depth in both camera frames."""
        p = as_rows(points_cam, "points_cam", 3)
        return self.left.project(p), self.right.project(p @ self.R.T + self.T)

    @cached_property
    def rectification(self) -> Rectification:
        """The rig's rectification (computed once, then cached)."""
        return Rectification.of(self)


def axis_sigmas(cov: ArrayLike) -> FloatArray:
    """Per-axis standard deviations (..., 3) of covariances (..., 3, 3): the square roots of the
    diagonals. A covariance of rank below 3 (e.g. a point's with no pixel noise, all along its
    ray) rotated into another frame can hold a zero diagonal entry that rounding made slightly
    negative; it is a zero, not a NaN. A NaN diagonal (nothing measured) stays NaN."""
    return np.sqrt(np.maximum(np.diagonal(np.asarray(cov, dtype=float), axis1=-2, axis2=-1), 0.0))


#: Largest ratio (either way) of the rectified focal length to the cameras' own: a lens's
#: distortion zooms a rectification that keeps only valid pixels by a few percent (OpenCV's
#: calibration sample, k1 -0.29: 1.1 times); 4 times keeps a sixteenth of the image.
MAX_RECTIFICATION_ZOOM = 4.0
#: ... blamed on the distortion only where the same rig without it zooms at most this much
#: (either way): a converging rig's own zoom (2 at 15 deg of toe-in) grows steeply with any
#: lens, and is the geometry's, not the coefficients'.
LENSLESS_ZOOM_FOR_BLAME = 2.0


def _rectified_apart(rig: StereoRig) -> bool:
    """Whether ``rig`` is a pair rectified already (no rotation, the baseline along x, no lens
    distortion, the same square-pixel focal length and principal row) whose principal points
    lie apart."""
    K1, K2 = rig.left.K, rig.right.K
    scale = float(np.max(np.abs(K1)))
    same = np.isclose(np.delete(K1.ravel(), 2), np.delete(K2.ravel(), 2), rtol=0.0, atol=1e-9 * scale)
    return bool(
        np.all(same)
        and abs(K1[0, 0] - K1[1, 1]) <= 1e-9 * scale  # square pixels: the maps are then the identity
        and abs(K1[0, 2] - K2[0, 2]) > 1e-9 * scale
        and np.max(np.abs(rig.R - np.eye(3))) <= 1e-9
        and np.max(np.abs(rig.T[1:])) <= 1e-9 * abs(rig.T[0])
        and not np.any(rig.left.dist)
        and not np.any(rig.right.dist)
    )


def _zoom(rig: StereoRig, P1: FloatArray, P2: FloatArray) -> float:
    """The rectified focal length (of ``P1``, ``P2``) over the cameras' mean; inf when not finite."""
    if not (np.all(np.isfinite(P1)) and np.all(np.isfinite(P2))):
        return math.inf
    return float(P1[0, 0]) / float(np.mean([rig.left.K[0, 0], rig.left.K[1, 1], rig.right.K[0, 0], rig.right.K[1, 1]]))


def _within(zoom: float, limit: float) -> bool:
    return 1.0 / limit <= zoom <= limit


def _distortion_problem(rig: StereoRig, zoom: float, lensless_zoom: float) -> str:
    """One line on distortion coefficients no lens has (``D1: [1e6, 0, 0, 0, 0]``), which
    otherwise surface as every point refused, or as NaN disparity ranges blamed on a setting;
    it names both cameras' coefficients (``D1``, ``D2``)."""
    said = f"{zoom:.3g} times the cameras'" if math.isfinite(zoom) else "not finite"
    coefficients = " and ".join(f"{key} [{', '.join(f'{c:.4g}' for c in cam.dist)}]"
                                for key, cam in (("D1", rig.left), ("D2", rig.right)))
    return (f"the rig cannot be rectified: with its lens distortion the rectified focal length is {said} "
            f"({lensless_zoom:.3g} without distortion; a lens changes it by a few percent, and beyond "
            f"{MAX_RECTIFICATION_ZOOM:g} times is refused): check {coefficients}")


@dataclass(frozen=True, eq=False)
class Rectification:
    """Rectified stereo geometry of a rig (OpenCV ``stereoRectify`` with ``alpha``).

    In the rectified images, a scene point has the same row in both images and its disparity
    ``d = u_left - u_right`` gives depth ``z = f b / (d - (cx1 - cx2))``. Rectified to one
    principal point (``CALIB_ZERO_DISPARITY``), ``cx1 - cx2`` is 0; a pair rectified already
    whose principal points lie apart keeps them, its maps the identity.

    Attributes:
        rig: the rig.
        R1, R2: (3,3) rotations ``p_rect = R1 @ p_cam``, ``p_rect1 = R2 @ p_cam1``.
        P1, P2: (3,4) projection matrices of the rectified cameras, px.
        Q: (4,4) disparity-to-depth matrix, ``[X Y Z W] = Q [u v d 1]``.
    """

    rig: StereoRig
    R1: FloatArray
    R2: FloatArray
    P1: FloatArray
    P2: FloatArray
    Q: FloatArray

    @classmethod
    def of(cls, rig: StereoRig, alpha: float = 0.0) -> Rectification:
        """Rectify ``rig``; ``alpha`` = 0 keeps only valid pixels, 1 keeps all source pixels.

        Raises:
            TrackmeterError: lens distortion no lens has (:data:`MAX_RECTIFICATION_ZOOM`,
                :data:`LENSLESS_ZOOM_FOR_BLAME`).
        """
        R1, R2, P1, P2, Q, _, _ = cast("tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, object, object]", cv2.stereoRectify(
            rig.left.K,
            rig.left.dist,
            rig.right.K,
            rig.right.dist,
            rig.image_size,
            rig.R,
            rig.T.reshape(3, 1),
            # A pair rectified already, its principal points apart (Middlebury 2014's ``doffs``),
            # keeps them: moved onto one it was zoomed and cropped (5 % on Motorcycle), every
            # pixel resampled, and its disparities were no longer the pair's own.
            flags=0 if _rectified_apart(rig) else cv2.CALIB_ZERO_DISPARITY,
            alpha=alpha,
        ))
        zoom = _zoom(rig, P1, P2)
        if not _within(zoom, MAX_RECTIFICATION_ZOOM):
            # The lenses' fault only if the same rig without distortion rectifies well: a rig
            # whose cameras are not side by side has its own message where it is used.
            no_lens = cv2.stereoRectify(rig.left.K, np.zeros(5), rig.right.K, np.zeros(5), rig.image_size, rig.R,
                                        rig.T.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=alpha)
            lensless_zoom = _zoom(rig, cast(FloatArray, no_lens[2]), cast(FloatArray, no_lens[3]))
            if _within(lensless_zoom, LENSLESS_ZOOM_FOR_BLAME):
                raise TrackmeterError(_distortion_problem(rig, zoom, lensless_zoom))
        return cls(rig=rig, R1=R1, R2=R2, P1=P1, P2=P2, Q=Q)

    # ----------------------------------------------------------------- rectified parameters

    @property
    def focal_px(self) -> float:
        """Focal length of both rectified cameras, px."""
        return float(self.P1[0, 0])

    @property
    def baseline_m(self) -> float:
        """Baseline along the rectified x axis, m: positive for a side-by-side rig, the right
        camera on the right (:func:`check_side_by_side` refuses any other); about 0 for a
        vertical rig and negative for swapped cameras, whose rectified disparities triangulate
        to nothing (NaN)."""
        return float(-self.P2[0, 3] / self.P2[0, 0])

    @property
    def cx_left(self) -> float:
        return float(self.P1[0, 2])

    @property
    def cx_right(self) -> float:
        return float(self.P2[0, 2])

    @property
    def cy(self) -> float:
        return float(self.P1[1, 2])

    @property
    def disparity_offset_px(self) -> float:
        """``cx1 - cx2``: the disparity of a point at infinity (0 with ``CALIB_ZERO_DISPARITY``)."""
        return self.cx_left - self.cx_right

    # ----------------------------------------------------------------- maps and images

    @cached_property
    def maps(self) -> tuple[tuple[NDArray[np.float32], NDArray[np.float32]], tuple[NDArray[np.float32], NDArray[np.float32]]]:
        """``((map1x, map1y), (map2x, map2y))`` float32 remap tables, rectified → original."""
        size = self.rig.image_size
        left = cast("tuple[NDArray[np.float32], NDArray[np.float32]]", cv2.initUndistortRectifyMap(self.rig.left.K, self.rig.left.dist, self.R1, self.P1, size, cv2.CV_32FC1))
        right = cast("tuple[NDArray[np.float32], NDArray[np.float32]]", cv2.initUndistortRectifyMap(self.rig.right.K, self.rig.right.dist, self.R2, self.P2, size, cv2.CV_32FC1))
        return (left[0], left[1]), (right[0], right[1])

    def rectify_images(self, left: NDArray[np.uint8], right: NDArray[np.uint8]) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
        """Rectify a full stereo pair with bilinear interpolation."""
        (lx, ly), (rx, ry) = self.maps
        return (
            cast("NDArray[np.uint8]", cv2.remap(left, lx, ly, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)),
            cast("NDArray[np.uint8]", cv2.remap(right, rx, ry, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)),
        )

    # ----------------------------------------------------------------- pixel mappings

    def rectify_points(self, uv: ArrayLike, side: int = 0) -> FloatArray:
        """Original (distorted) pixels (N,2) of the left (side 0) or right (1) image → rectified."""
        cam = self.rig.left if side == 0 else self.rig.right
        Rr, P = (self.R1, self.P1) if side == 0 else (self.R2, self.P2)
        pts = as_rows(uv, "uv", 2).reshape(-1, 1, 2)
        if len(pts) == 0:
            return np.zeros((0, 2))
        return _undistort_points(pts, cam.K, cam.dist, Rr, P)

    def unrectify_points(self, uv_rect: ArrayLike, side: int = 0) -> FloatArray:
        """Rectified pixels (N,2) → original (distorted) pixels of the left (0) or right (1) image."""
        cam = self.rig.left if side == 0 else self.rig.right
        Rr, P = (self.R1, self.P1) if side == 0 else (self.R2, self.P2)
        uv = as_rows(uv_rect, "uv_rect", 2)
        if len(uv) == 0:
            return np.zeros((0, 2))
        rays_rect = np.column_stack([uv, np.ones(len(uv))]) @ np.linalg.inv(P[:3, :3]).T
        return cam.project(rays_rect @ Rr)  # p_cam = Rr^T p_rect, row form p @ Rr

    # ----------------------------------------------------------------- triangulation

    def triangulate(self, uv_rect_left: ArrayLike, disparity_px: ArrayLike) -> FloatArray:
        """3D points in the LEFT CAMERA frame (N,3), m, from rectified left pixels and disparities.

        ``Z_rect = f b / d'``, ``X_rect = (u - cx1) b / d'``, ``Y_rect = (v - cy) b / d'`` with
        ``d' = d - (cx1 - cx2)`` (OpenCV's Q matrix), then ``p_cam = R1^T p_rect``.
        Non-positive or infinite ``d'`` gives NaN rows. One disparity for every pixel, or one
        per pixel.

        Raises:
            TrackmeterError: as many disparities as neither 1 nor the pixels.
        """
        uv = as_rows(uv_rect_left, "uv_rect_left", 2)
        d = np.asarray(disparity_px, dtype=float).reshape(-1) - self.disparity_offset_px
        if len(d) not in (1, len(uv)):
            raise TrackmeterError(f"{len(uv)} pixels but {len(d)} disparities")
        d = np.broadcast_to(d, (len(uv),))
        b, f = self.baseline_m, self.focal_px
        with np.errstate(divide="ignore", invalid="ignore"):
            # d' = inf would put a point of no uncertainty at the camera centre.
            scale = np.where(np.isfinite(d) & (d > 0), b / d, np.nan)
        p_rect = np.column_stack([(uv[:, 0] - self.cx_left) * scale, (uv[:, 1] - self.cy) * scale, f * scale])
        return p_rect @ self.R1  # rows: (R1^T p)^T = p^T R1

    def project_rectified(self, points_cam: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Rectified left pixels (N,2) and disparities (N,) of left-camera-frame points (N,3), m."""
        p_rect = as_rows(points_cam, "points_cam", 3) @ self.R1.T
        z = p_rect[:, 2]
        f, b = self.focal_px, self.baseline_m
        uv = np.column_stack([f * p_rect[:, 0] / z + self.cx_left, f * p_rect[:, 1] / z + self.cy])
        return uv, f * b / z + self.disparity_offset_px

    def point_covariance(
        self,
        uv_rect_left: ArrayLike,
        disparity_px: ArrayLike,
        sigma_disparity_px: float | ArrayLike,
        sigma_uv_px: float | ArrayLike = 0.0,
    ) -> FloatArray:
        """Covariance (N,3,3) of triangulated points in the left camera frame, m².

        First-order error propagation of the paper's eqs. 1-2: with ``Z = f b / d'``,
        ``X = (u - cx) Z / f``, ``Y = (v - cy) Z / f`` the Jacobian is

            dZ/dd = -Z²/(f b)            (eq. 2: sigma_z = z² sigma_d / (f b))
            dX/dd = -X Z/(f b),  dX/du = Z/f
            dY/dd = -Y Z/(f b),  dY/dv = Z/f

        and ``C_cam = R1^T J diag(su², sv², sd²) J^T R1``.

        Args:
            uv_rect_left: (N,2) rectified left pixel.
            disparity_px: (N,) disparity.
            sigma_disparity_px: standard deviation of the disparity (scalar or (N,)), px, >= 0.
            sigma_uv_px: standard deviation of the left pixel position per axis (scalar or
                (N,)), px, >= 0.

        Raises:
            TrackmeterError: a negative standard deviation (squared, it would pass as positive).
        """
        _non_negative(sigma_disparity_px, "sigma_disparity_px")
        _non_negative(sigma_uv_px, "sigma_uv_px")
        p_rect = self.triangulate(uv_rect_left, disparity_px) @ self.R1.T
        n = len(p_rect)
        f, b = self.focal_px, self.baseline_m
        X, Y, Z = p_rect.T
        J = np.zeros((n, 3, 3))
        J[:, 0, 0] = Z / f
        J[:, 1, 1] = Z / f
        J[:, 0, 2] = -X * Z / (f * b)
        J[:, 1, 2] = -Y * Z / (f * b)
        J[:, 2, 2] = -Z * Z / (f * b)
        s_uv = np.broadcast_to(np.asarray(sigma_uv_px, dtype=float), (n,))
        s_d = np.broadcast_to(np.asarray(sigma_disparity_px, dtype=float), (n,))
        S = np.zeros((n, 3, 3))
        S[:, 0, 0] = s_uv**2
        S[:, 1, 1] = s_uv**2
        S[:, 2, 2] = s_d**2
        C_rect = J @ S @ np.transpose(J, (0, 2, 1))
        return self.R1.T @ C_rect @ self.R1

    def point_sigma(
        self,
        uv_rect_left: ArrayLike,
        disparity_px: ArrayLike,
        sigma_disparity_px: float | ArrayLike,
        sigma_uv_px: float | ArrayLike = 0.0,
    ) -> FloatArray:
        """Per-axis standard deviation (N,3) in the left camera frame, m (sqrt of the diagonal of
        :meth:`point_covariance`)."""
        return axis_sigmas(self.point_covariance(uv_rect_left, disparity_px, sigma_disparity_px, sigma_uv_px))


def check_side_by_side(rig: StereoRig) -> None:
    """Raise :class:`TrackmeterError` unless ``rig`` can be matched: after rectification its
    right camera must lie to the right of the left one, so that a point's match lies on the
    same rectified ROW with a disparity ``d = u_left - u_right`` past a point at infinity's
    (the stereo matcher searches rows, and depth is ``f b / (d - (cx1 - cx2))``).

    A rig whose right camera lies mostly in front of or behind the left one is refused too.
    A vertical rig rectifies to equal columns (``P2[1,3]`` carries the baseline, ``P2[0,3]`` is
    0): a row search finds look-alikes at made-up depths. A swapped rig (right camera at -x:
    the images or the cameras exchanged) gives every depth negative.
    """
    P2 = rig.rectification.P2
    bx, by = float(P2[0, 3]), float(P2[1, 3])
    centre = -rig.R.T @ rig.T
    # A baseline more along the viewing axis than across it: rectification would turn both
    # views by more than 45 deg toward the baseline, and what disparity there is grows with the
    # distance from the epipole more than with nearness (a choice of bound, not a field of view).
    along_axis = abs(float(centre[2])) > float(np.hypot(centre[0], centre[1]))
    if abs(by) <= abs(bx) and bx < 0 and not along_axis:
        return  # every measurement passes here: nothing else to do
    raise TrackmeterError(_not_side_by_side_reason(rig))


def _not_side_by_side_reason(rig: StereoRig) -> str:
    """Why ``rig`` cannot be matched, told by where its right camera is: its centre
    ``-R^T T`` in the left camera's frame (x right, y down, z forward), and its turn about the
    viewing axis against the left camera."""
    centre = -rig.R.T @ rig.T
    at = f"its centre at {(np.round(centre, 3) + 0.0).tolist()} m in the left camera's frame, x right, y down"
    roll_deg = math.degrees(math.atan2(float(rig.R[1, 0]), float(rig.R[0, 0])))
    cx, cy, cz = (float(v) for v in centre)
    if abs(cz) > math.hypot(cx, cy):
        return (f"the rig is not side by side: the right camera lies {'in front of' if cz > 0 else 'behind'} "
                f"the left one ({at}); matching needs the right camera beside the left one, "
                "T about (-baseline, 0, 0)")
    if abs(cy) > abs(cx):
        return (f"the rig is not side by side: the right camera lies {'below' if cy > 0 else 'above'} the "
                f"left one ({at}); matching searches along rectified rows, so the right camera must lie "
                "to the right of the left one (T about (-baseline, 0, 0)); turn both images and the rig "
                f"by 90 degrees {'counter-clockwise' if cy > 0 else 'clockwise'} (the "
                f"{'bottom' if cy > 0 else 'top'} of an image then lies to its right)")
    if cx < 0 and abs(roll_deg) > 90.0:
        return (f"the right camera lies left of the left one ({at}) and is turned {abs(roll_deg):.0f} deg about "
                "its viewing axis against it (R): turn the right images to match the left ones and R with them, "
                "then exchange the left and right images (and the rig's cameras)")
    if cx < 0:
        return (f"the right camera lies left of the left one ({at}): the rig's cameras are swapped, or its T has "
                "the wrong sign: negate T if the left images are the left camera's, else exchange the left and "
                "right images (and the rig's cameras)")
    # Beside it, on the right, yet rectification does not put it there: it is turned round.
    return (f"the right camera lies right of the left one ({at}) but is turned {abs(roll_deg):.0f} deg about "
            "its viewing axis against it (R): turn the right images to match the left ones and R with them")


#: A disparity below minus this (px) is the views' order, not a far point's noise.
SWAPPED_MIN_SHIFT_PX = 2.0
#: Matches a verdict on the views' order needs (a chessboard's repeated corners give a few).
SWAPPED_MIN_MATCHES = 10
#: ... and the share of them at a disparity no point in front of the rig has (below a point at
#: infinity's) that says the views are swapped: measured 99-100 % on swapped pairs (the
#: simulated mock-up at 726x512 to 2048x1536, a textured plate, Tsukuba), 0-1 % on the same
#: pairs in order.
SWAPPED_MIN_FRACTION = 0.8
#: On a pair whose principal points lie apart a swap moves the points by twice the offset less:
#: Middlebury's Motorcycle (offset -31 px) swapped has 69 % of its matches there, Tsukuba's right
#: image moved 2 px right (its principal point with it) swapped 55 %, and 0 % with the views
#: exchanged back. There the views are swapped from this share on when, exchanged, at most
#: :data:`SWAPPED_MAX_OTHER_FRACTION` would be (kept to such pairs: a rig a little off looking
#: at a far scene puts a third of its points 2 px past infinity, an outside review).
SWAPPED_MIN_FRACTION_APART = 0.3
SWAPPED_MAX_OTHER_FRACTION = 0.05


def view_disparities_px(rig: StereoRig, left: NDArray, right: NDArray, features: int = 500) -> FloatArray:
    """Disparities ``d = u_left - u_right`` (px, rectified) of the view's distinctive points.

    ORB keypoints (``cv2.ORB.create``) of the two rectified images, matched by descriptor with
    a cross-check, those on the matches' common row offset (within 3 px of its median: views
    rectified by a rig they do not fit are off by a few rows). A global phase correlation was
    tried first and gave a textured plate's pair, tilted, 37 px where its points lie at 91 px.

    Args:
        rig: the stereo rig.
        left, right: (H,W) grey images as the cameras gave them (not rectified).
        features: ORB keypoints per image at most.
    Returns:
        (M,) disparities, px; empty when the views have no distinctive point (black space).
    """
    rect_left, rect_right = rig.rectification.rectify_images(np.asarray(left), np.asarray(right))
    orb = cv2.ORB.create(nfeatures=features)
    keys_left, desc_left = orb.detectAndCompute(rect_left, None)
    keys_right, desc_right = orb.detectAndCompute(rect_right, None)
    if desc_left is None or desc_right is None:
        return np.zeros(0)
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(desc_left, desc_right)
    if not matches:
        return np.zeros(0)
    uv_left = np.array([keys_left[m.queryIdx].pt for m in matches])
    uv_right = np.array([keys_right[m.trainIdx].pt for m in matches])
    dv = uv_left[:, 1] - uv_right[:, 1]
    on_row = np.abs(dv - np.median(dv)) < 3.0
    return (uv_left[on_row, 0] - uv_right[on_row, 0]).astype(float)


def swapped_views_problem(rig: StereoRig, left: NDArray, right: NDArray,
                          disparities_px: FloatArray | None = None) -> str | None:
    """One line when the views look swapped or are one image twice, else None.

    Swapped: most of the view's distinctive points (:func:`view_disparities_px`, or
    ``disparities_px`` when already found) lie further right in the right image than a point at
    infinity would, which no point in front of the rig does (:data:`SWAPPED_MIN_FRACTION`; on a
    pair whose principal points lie apart, fewer when exchanged almost none would:
    :data:`SWAPPED_MIN_FRACTION_APART`). The matcher then finds nothing, or look-alikes at
    made-up depths. One image given twice (with distinctive points: two black frames of empty
    space are no mistake) is no stereo pair: its points are refused, or measured at depths the
    rectification alone makes (on Middlebury's rigs, ``cx2 > cx1``, a plane at
    ``f b / (cx2 - cx1)``).
    """
    d = view_disparities_px(rig, left, right) if disparities_px is None else np.asarray(disparities_px, float)
    if len(d) < SWAPPED_MIN_MATCHES:
        return None
    if np.array_equal(left, right):
        return ("the left and right images are one and the same image: no depth can be measured from one view; "
                "give the right camera's images as the right ones (a sequence's cam1)")
    offset = rig.rectification.disparity_offset_px
    given, exchanged = d - offset, -d - offset  # past a point at infinity's: >= 0 in front of the rig
    impossible = given < -SWAPPED_MIN_SHIFT_PX
    share = float(np.mean(impossible))
    apart = (offset != 0 and share >= SWAPPED_MIN_FRACTION_APART
             and np.mean(exchanged < -SWAPPED_MIN_SHIFT_PX) <= SWAPPED_MAX_OTHER_FRACTION)
    if share < SWAPPED_MIN_FRACTION and not apart:
        return None
    return (f"the left and right images look swapped: {share:.0%} of the view's points lie "
            f"{-float(np.median(given[impossible])):.0f} px further right in "
            "the right image than a point at infinity would (rectified), where every point in front of the rig lies "
            "further left; give the left camera's images as the left ones (a sequence's cam0)")


def depth_sigma(z_m: ArrayLike, focal_px: float, baseline_m: float, sigma_disparity_px: float) -> FloatArray:
    """Depth standard deviation of a stereo point, paper eq. 2: ``sigma_z = z² sigma_d / (f b)``, m.

    The parabola of the paper's Fig. 3; inverted, it gives the sub-pixel disparity accuracy
    ``sigma_d = k f b`` from a fitted ``sigma_z = k z²``.

    Args:
        z_m: depth(s) along the viewing axis, m, positive (in front of the camera).
        focal_px: focal length, px, positive.
        baseline_m: stereo baseline, m, positive.
        sigma_disparity_px: disparity standard deviation, px, >= 0.

    Raises:
        TrackmeterError: any of them out of its range (a depth behind the camera squared would
            pass for one in front).
    """
    z = np.asarray(z_m, dtype=float)
    if not np.all(z > 0):
        bad = z[~(z > 0)].ravel()[0]
        raise TrackmeterError(f"z_m must be positive (in front of the camera), m; got {bad:g}")
    for value, name, unit in ((focal_px, "focal_px", "px"), (baseline_m, "baseline_m", "m")):
        if not (np.isfinite(value) and value > 0):
            raise TrackmeterError(f"{name} must be positive, {unit}; got {value:g}")
    _non_negative(sigma_disparity_px, "sigma_disparity_px")
    return z * z * sigma_disparity_px / (focal_px * baseline_m)
