"""A textured plane moving in front of a stereo rig: exact ground truth for tracking tests.

A small, fast stand-in for the full simulator (:mod:`trackmeter.sources.sim`) where only the
geometry matters: a rectangular textured plate (the ``body``: plate in its z = 0 plane, centred
at the origin) on black space, rendered by ray casting into both cameras of a rig, with the
plate's pose ``T_cam_body(t)`` given by a function. Every pixel's ray (lens distortion
included) is intersected with the plate exactly, so the true image of any surface point is
known: :meth:`PlaneScene.surface_points` and :meth:`PlaneScene.project`.

Texture texel ``(i, j)`` of an ``nu x nv`` texture has its centre at the body point
``((i + 0.5) w / nu - w/2, (j + 0.5) h / nv - h/2, 0)``.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from trackmeter.core.stereo import Camera, StereoRig
from trackmeter.sources.base import GroundTruth, Source, StereoFrame

FloatArray = NDArray[np.float64]


def plate_texture(shape: tuple[int, int] = (768, 1024), seed: int = 0, brightness: float = 140.0) -> NDArray[np.uint8]:
    """A bright, textured grey texture (rows, cols): blurred noise at several scales plus
    sharp-edged patches (panels, labels), all blurred by at least 1.5 texels.

    The renderer point-samples the texture, so detail finer than a pixel would alias (a real
    camera integrates over its pixels and optics); at the default plate size and 3.5 m one
    texel is about 0.4 px.
    """
    rng = np.random.default_rng(seed)
    rows, cols = shape
    acc = np.zeros(shape, np.float32)
    for sigma, amp in ((3.0, 25.0), (6.0, 25.0), (12.0, 20.0)):
        noise = rng.standard_normal(shape).astype(np.float32)
        blurred = cv2.GaussianBlur(noise, (0, 0), sigma)
        acc += amp * blurred / (blurred.std() + 1e-9)
    shapes = np.zeros(shape, np.float32)
    for _ in range(int(rows * cols / 4000)):
        x, y = int(rng.integers(0, cols)), int(rng.integers(0, rows))
        w, h = int(rng.integers(6, 40)), int(rng.integers(6, 40))
        cv2.rectangle(shapes, (x, y), (x + w, y + h), float(rng.uniform(-50, 50)), -1)
    acc += cv2.GaussianBlur(shapes, (0, 0), 1.5)
    return np.clip(brightness + acc, 40, 255).astype(np.uint8)


def _rays(cam: Camera, size: tuple[int, int]) -> FloatArray:
    w, h = size
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    xy = cam.undistort(np.column_stack([u.ravel(), v.ravel()]))
    return np.column_stack([xy, np.ones(len(xy))]).reshape(h, w, 3)


class PlaneScene(Source):
    """Stereo frames of a textured plate moving with ``pose(t) -> T_cam_body`` (4,4).

    Args:
        rig: the stereo rig.
        pose: ``T_cam_body`` as a function of time, s.
        texture: (nv, nu) uint8 texture of the plate (default :func:`plate_texture` at about
            850 texels per metre).
        size_m: ``(w, h)`` of the plate, m.
        rate_hz: frame rate.
        noise_sigma: std of additive image noise, grey levels.
        gain: optional ``gain(t)`` multiplying the plate's brightness (lighting changes).
        n_frames: frames before the end of the stream.
        seed: seed of the image noise.
    """

    def __init__(
        self,
        rig: StereoRig,
        pose: Callable[[float], FloatArray],
        texture: NDArray[np.uint8] | None = None,
        size_m: tuple[float, float] = (1.2, 0.9),
        rate_hz: float = 25.0,
        noise_sigma: float = 1.0,
        gain: Callable[[float], float] | None = None,
        n_frames: int = 100,
        seed: int = 0,
    ) -> None:
        self.rig: StereoRig = rig
        self.pose = pose
        if texture is None:
            # About 850 texels per metre (0.4 px per texel at 3.5 m with the 12 mm rig).
            texture = plate_texture((int(round(size_m[1] * 853)), int(round(size_m[0] * 853))), seed=seed)
        self.texture = np.asarray(texture, np.uint8)
        self.size_m = size_m
        self.rate_hz: float = rate_hz
        self.noise_sigma = noise_sigma
        self.gain = gain
        self.n_frames = n_frames
        self.seed = seed
        size = rig.image_size
        self._rays = (_rays(rig.left, size), _rays(rig.right, size))
        self._next = 0

    def T_cam_body(self, index: int) -> FloatArray:
        return np.asarray(self.pose(index / self.rate_hz), dtype=float)

    def _render(self, side: int, T_c_b: FloatArray, gain: float, rng: np.random.Generator) -> NDArray[np.uint8]:
        R, t = T_c_b[:3, :3], T_c_b[:3, 3]
        rays = self._rays[side]
        n = R[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (n @ t) / (rays @ n)
        X = rays * lam[..., None] - t
        body = X @ R  # rows: R^T (X - t)
        w, h = self.size_m
        nv, nu = self.texture.shape
        tu = ((body[..., 0] + w / 2) * nu / w - 0.5).astype(np.float32)
        tv = ((body[..., 1] + h / 2) * nv / h - 0.5).astype(np.float32)
        bad = ~np.isfinite(lam) | (lam <= 0)
        tu[bad] = -10
        tv[bad] = -10
        img = cast(NDArray[np.float32], cv2.remap(self.texture.astype(np.float32), tu, tv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0))
        img *= gain
        if self.noise_sigma > 0:
            img += rng.normal(0, self.noise_sigma, img.shape).astype(np.float32)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)

    def frame(self, index: int) -> StereoFrame:
        t_s = index / self.rate_hz
        T = self.T_cam_body(index)
        g = 1.0 if self.gain is None else float(self.gain(t_s))
        rng = np.random.default_rng((self.seed, index))
        left = self._render(0, T, g, rng)
        right = self._render(1, self.rig.T_cam1_cam @ T, g, rng)
        truth = GroundTruth(T_cam_body=T, velocity_cam_m_s=np.full(3, np.nan), omega_body_rad_s=np.full(3, np.nan))
        return StereoFrame(index=index, t_s=t_s, left=left, right=right, truth=truth)

    def read(self) -> StereoFrame | None:
        if self._next >= self.n_frames:
            return None
        f = self.frame(self._next)
        if self._take_cut():
            f = replace(f, cut=True)
        self._next += 1
        return f

    def restart(self) -> None:
        self._next = 0
        self._cut = True

    def surface_points(self, index: int, uv_left: NDArray) -> FloatArray:
        """Body points (N,3) seen at left pixels ``uv_left`` (N,2) in frame ``index``; NaN where
        the ray misses the plate."""
        T = self.T_cam_body(index)
        R, t = T[:3, :3], T[:3, 3]
        xy = self.rig.left.undistort(np.asarray(uv_left, float).reshape(-1, 2))
        rays = np.column_stack([xy, np.ones(len(xy))])
        n = R[:, 2]
        lam = (n @ t) / (rays @ n)
        body = (rays * lam[:, None] - t) @ R
        w, h = self.size_m
        out = (np.abs(body[:, 0]) > w / 2) | (np.abs(body[:, 1]) > h / 2) | (lam <= 0)
        body[out] = np.nan
        return body

    def project(self, index: int, points_body: NDArray) -> tuple[FloatArray, FloatArray]:
        """True left and right pixels (N,2) of body points (N,3) in frame ``index``."""
        T = self.T_cam_body(index)
        p = np.asarray(points_body, float).reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
        return self.rig.project(p)


def pose_translating(z_m: float, velocity_m_s: tuple[float, float, float], omega_rad_s: tuple[float, float, float] = (0, 0, 0), start_m: tuple[float, float] = (0.0, 0.0)) -> Callable[[float], FloatArray]:
    """``T_cam_body(t)``: plate facing the camera at depth ``z_m``, moving at constant velocity and
    rotating at a constant rate (rotation vector ``omega t`` applied in the body frame)."""
    from scipy.spatial.transform import Rotation

    v = np.asarray(velocity_m_s, float)
    w = np.asarray(omega_rad_s, float)

    def pose(t: float) -> FloatArray:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(w * t).as_matrix()
        T[:3, 3] = np.array([start_m[0], start_m[1], z_m]) + v * t
        return T

    return pose
