"""Stereo renderer of the satellite mock-up: what the rig's two cameras see, geometrically exact.

For each camera the mock-up's planar faces are drawn into an undistorted pinhole *canvas*
(the camera's K, shifted so the canvas covers every ray of the real image), then the rig's lens
distortion is applied once with ``cv2.remap`` through a map computed at start-up (each original,
distorted pixel → its pinhole canvas position, via :meth:`Camera.undistort`). The right camera
renders with its own pose ``T_cam1_body = rig.T_cam1_cam @ T_cam_body`` and its own K and
distortion, so the rig's rotation and distortion are exercised for real.

A face is drawn with one ``cv2.warpPerspective`` over its bounding box: the homography maps
texel centres ``(i, j, 1)`` to canvas pixels (Hartley & Zisserman, plane-induced homography)

    H = K_canvas [R e_u s_u | R e_v s_v | R (origin + s_u/2 e_u + s_v/2 e_v) + t]

where ``s_u = w / n_u`` is the texel size and ``(R, t) = T_view_body``; OpenCV's warps and
remap both put integer pixel coordinates at pixel centres, the convention of this project,
so a texture point lands exactly where ``StereoRig.project`` puts it (tests check 0.05 px).
Visibility: back faces are culled; faces are drawn far to near and composited "over" with
their (premultiplied) coverage, behind a per-pixel depth test on ``1/z``, which is affine in
the pixel coordinates for a plane: ``1/z = (n·K⁻¹[u v 1]ᵀ) / (n·p0)``. (Radiance and coverage
go through one warp of a 4-channel texture, which OpenCV does for about the cost of one
1-channel warp; the compositing works in place on views of the canvas; the distortion remap
covers only the image pixels that see a drawn box. All of it is exact: the images are the ones
the plain per-channel code gives, bit for bit, ``tests/test_render_paths.py``.)

Shading is done per texel, in texture space, before warping (a texel's view direction and
sun direction are exact there): Lambert with the perturbed normal ``n'``,
``albedo (ambient + E max(n'·s, 0) lit)``, plus glints ``spec E lit exp(k (n'·h - 1))``
(a Phong-like lobe, ``h`` the half vector of sun and view directions, ``k`` the sharpness).
``lit`` is 0 in shadows, which are the faces (and occluders) between the face and the sun,
projected along the sun onto the face's plane and rasterised into its texture.

Approximations, all far below a pixel or a grey level where it matters: ``h`` is exact on a
7x7 grid per face and bilinear in between; faces smaller than ~300 px² in the image receive
no shadows; a face's glints are skipped when no facet tilt can bring ``n'`` within the lobe.
Texture minification uses mip levels (area-averaged, each covering the whole face, so the
texel-centre formula above stays exact at every level), blended trilinearly: the two levels
around a face's level of detail, weighted by its fraction, so a face's texture changes smoothly
as it turns and recedes instead of switching level from one frame to the next.

Then auto-iris exposure (a high percentile of the satellite's radiance in the left image is
set to a target grey level), sensor noise (read noise and shot noise, Gaussian with the
Poisson variance ``gain * signal``), optional motion blur (the average of sub-frame renders
spread over the shutter time centred on the current pose), 8-bit grey output.
"""

from __future__ import annotations

import argparse
import functools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence, cast

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import map_coordinates
from scipy.spatial.transform import Rotation

from trackmeter.core.params import check_params, param
from trackmeter.core.stereo import Camera, StereoRig
from trackmeter.errors import TrackmeterError
from trackmeter.sources.sim.mockup import Face, MaterialSpec, Mockup, Surface, TextureLevel, _make_face

F32 = NDArray[np.float32]
FloatArray = NDArray[np.float64]

_NEAR_M = 0.02  # faces with a corner closer than this to a camera are not drawn
_MIN_SHADOW_AREA_PX = 300.0  # smaller faces (a few px across) are not worth a shadow test
_SUM3 = np.ones((1, 3))  # cv2.transform matrix: sum of a 3-channel image's channels
_LIT_OF_MASK = (1.0 - np.arange(256, dtype=np.float32) / 255.0).astype(np.float32)  # shadow mask (0..255) -> lit fraction


@dataclass(frozen=True)
class RenderParams:
    """Lighting, exposure, sensor and blur of the simulated cameras (part of a scenario file)."""

    sun_irradiance: float = param(1.0, "Sun irradiance, relative radiance units (sets the scale of everything).", min=0.0)
    ambient: float = param(0.03, "Ambient light (Earth albedo, lab walls), fraction of the sun's irradiance.", min=0.0, max=10.0)
    glint_strength: float = param(1.0, "Multiplies every material's specular (glint) strength.", min=0.0, max=100.0)
    glint_sharpness: float = param(1.0, "Multiplies every material's specular exponent (>1: smaller, faster-changing glints).", min=0.01, max=100.0)
    auto_exposure: bool = param(True, "Auto-iris: scale each frame so exposure_percentile of the satellite sits at exposure_target_grey.")
    exposure_percentile: float = param(99.0, "Percentile of the satellite's pixels (left image) the auto-iris holds at the target.", min=50.0, max=100.0)
    exposure_target_grey: float = param(200.0, "Grey level the auto-iris puts that percentile at.", min=1.0, max=255.0)
    exposure_gain_grey: float = param(400.0, "Grey levels per unit radiance when auto_exposure is off.", min=0.0)
    max_gain_grey: float = param(4000.0, "Auto-iris limit: largest gain, grey levels per unit radiance (fully open iris).", min=0.0)
    black_level_grey: float = param(3.0, "Sensor black level (offset added before noise and quantisation), grey levels.", min=0.0, max=255.0)
    read_noise_grey: float = param(1.0, "Read noise standard deviation, grey levels.", min=0.0, max=100.0)
    shot_noise_gain: float = param(0.02, "Conversion gain for shot noise, grey levels per photo-electron: variance = gain * signal.", min=0.0, max=100.0)
    motion_blur_subframes: int = param(1, "Sub-frames averaged for motion blur (1: none; needs T_cam_body_prev).", min=1, max=64)
    shutter_fraction: float = param(0.5, "Exposure time as a fraction of the frame interval (motion blur), centred on the frame's pose.", min=0.0, max=1.0)
    occluder_albedo: float = param(0.03, "Diffuse reflectance of occluder panels (dark, matte).", min=0.0, max=1.0)
    mip_bias: float = param(0.0, "Texture level-of-detail bias, octaves (+: blurrier, less aliasing).", min=-4.0, max=4.0)
    trilinear: bool = param(True, "Blend the two nearest mip levels by the fractional level of detail (GPUs' trilinear "
                            "filtering), so a face's texture does not change at once when its level switches.")

    def __post_init__(self) -> None:
        check_params(self)  # declared ranges and choices, as the config loader checks them


@dataclass(frozen=True, eq=False)
class Occluder:
    """A dark flat rectangular panel between the camera and the mock-up (harsh-light scenarios).

    Attributes:
        T_cam_occluder: (4,4) pose of the panel in the LEFT camera frame; the panel spans
            ``|x| <= w/2``, ``|y| <= h/2`` of its own frame, at z = 0. It hides what is behind it
            and casts shadows.
        size_m: ``(w, h)``, m.
    """

    T_cam_occluder: FloatArray
    size_m: tuple[float, float]

    def __post_init__(self) -> None:
        T = np.asarray(self.T_cam_occluder, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise TrackmeterError("Occluder.T_cam_occluder must be a finite 4x4 matrix")
        if len(self.size_m) != 2 or min(self.size_m) <= 0:
            raise TrackmeterError(f"Occluder.size_m must be two positive lengths, got {self.size_m}")
        object.__setattr__(self, "T_cam_occluder", T)
        object.__setattr__(self, "size_m", (float(self.size_m[0]), float(self.size_m[1])))


class _View:
    """One camera: its pinhole canvas and the distortion map (original pixel → canvas pixel)."""

    def __init__(self, cam: Camera, margin_px: int = 3) -> None:
        self.cam = cam
        W, H = cam.image_size
        uu, vv = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
        xy = cam.undistort(np.column_stack([uu.ravel(), vv.ravel()]))
        K = cam.K
        u_pin = K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2]
        v_pin = K[1, 1] * xy[:, 1] + K[1, 2]
        ox = math.floor(u_pin.min()) - margin_px
        oy = math.floor(v_pin.min()) - margin_px
        self.K_canvas = K.copy()
        self.K_canvas[0, 2] -= ox
        self.K_canvas[1, 2] -= oy
        self.K_canvas_inv = np.linalg.inv(self.K_canvas)
        self.size = (int(math.ceil(u_pin.max())) - ox + margin_px + 1, int(math.ceil(v_pin.max())) - oy + margin_px + 1)
        map_x = (u_pin - ox).reshape(H, W).astype(np.float32)
        map_y = (v_pin - oy).reshape(H, W).astype(np.float32)
        self.map_x, self.map_y = map_x, map_y
        # extents of the canvas columns each image column reads (and rows each row reads), so
        # that only the image pixels that can see drawn canvas pixels are remapped
        self.col_min_x, self.col_max_x = map_x.min(axis=0), map_x.max(axis=0)
        self.row_min_y, self.row_max_y = map_y.min(axis=1), map_y.max(axis=1)

    def image_box(self, canvas_box: tuple[int, int, int, int]) -> tuple[int, int, int, int] | None:
        """The box ``(c0, r0, c1, r1)`` of image pixels (columns c0..c1, rows r0..r1) that can
        read any canvas pixel of ``canvas_box`` = ``(x0, y0, x1, y1)`` through the bilinear
        remap (which reads the canvas pixels at ``floor(map)`` and ``floor(map) + 1``); every
        image pixel outside it reads only canvas pixels outside ``canvas_box``. None if empty."""
        x0, y0, x1, y1 = canvas_box
        cols = np.flatnonzero((self.col_max_x > x0 - 2) & (self.col_min_x < x1 + 1))
        rows = np.flatnonzero((self.row_max_y > y0 - 2) & (self.row_min_y < y1 + 1))
        if len(cols) == 0 or len(rows) == 0:
            return None
        return int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1


class _Geom:
    """Faces as stacked arrays, for vectorised visibility, projection and shadow tests."""

    def __init__(self, faces: Sequence[Face]) -> None:
        self.faces = list(faces)
        self.origin = np.array([f.origin for f in faces])
        self.normal = np.array([f.normal for f in faces])
        self.has_back = np.array([f.back is not None for f in faces])
        self.corners = np.array(
            [f.origin + np.array([[0, 0], [f.size_m[0], 0], [f.size_m[0], f.size_m[1]], [0, f.size_m[1]]]) @ np.vstack([f.e_u, f.e_v]) for f in faces]
        )
        self.n_texels = np.array([float(np.prod(f.front.levels[0].shape)) for f in faces])
        self.e_u = np.array([f.e_u for f in faces])
        self.centre = self.corners.mean(axis=1)
        self.half_diag = np.array([0.5 * math.hypot(*f.size_m) for f in faces])
        self.e_v = np.array([f.e_v for f in faces])
        self.size = np.array([f.size_m for f in faces])
        # (nv, nu) of every mip level (front and back share the texel grid), padded with the last
        self.n_levels = np.array([len(f.front.levels) for f in faces])
        lmax = int(self.n_levels.max())
        self.level_shape = np.array(
            [[f.front.levels[min(k, len(f.front.levels) - 1)].shape for k in range(lmax)] for f in faces], dtype=float
        )
        # shadow casters: one convex solid per part (a box's shadow is that of its 8 corners),
        # as vertices and edges so that the part on the sun side of a plane can be cut out
        parts: dict[str, int] = {}
        verts, vid, edges = [], [], []
        n = 0
        for f in faces:
            c = parts.setdefault(f.part or f.name, len(parts))
            k = len(f.outline)
            verts.append(f.outline_body)
            vid.append(np.full(k, c))
            edges.append(np.column_stack([np.arange(k), (np.arange(k) + 1) % k]) + n)
            n += k
        self.caster_verts = np.concatenate(verts)
        self.caster_of_vert = np.concatenate(vid)
        self.caster_edges = np.concatenate(edges)
        self.n_casters = len(parts)
        self._cuts: dict[tuple[int, bool], tuple[FloatArray, NDArray[np.intp], NDArray[np.intp]] | None] = {}

    def cut_casters(self, index: int, n_side: FloatArray) -> tuple[FloatArray, NDArray[np.intp], NDArray[np.intp]] | None:
        """The shadow casters on the ``n_side`` side of face ``index``'s plane (which does not
        depend on the sun, so it is cut once per face and side): ``(pts, starts, counts)``, the
        points (N,3) grouped by part, part k's being ``pts[starts[k] : starts[k] + counts[k]]``,
        body frame, m; None when no caster reaches that side."""
        key = (index, bool(n_side @ self.normal[index] > 0))
        if key in self._cuts:
            return self._cuts[key]
        face = self.faces[index]
        eps = 1e-4
        V = self.caster_verts
        dist = (V - face.origin) @ n_side - eps
        pos = dist > 0
        out = None
        if pos.any():
            a, b = self.caster_edges[:, 0], self.caster_edges[:, 1]
            cross = pos[a] != pos[b]
            a, b = a[cross], b[cross]
            tt = dist[a] / (dist[a] - dist[b])
            X = V[a] + tt[:, None] * (V[b] - V[a])
            pts = np.concatenate([V[pos], X])
            ids = np.concatenate([self.caster_of_vert[pos], self.caster_of_vert[a]])
            order = np.argsort(ids, kind="stable")
            ids, pts = ids[order], pts[order]
            starts = np.flatnonzero(np.concatenate([[True], ids[1:] != ids[:-1]]))
            out = (pts, starts, np.diff(np.append(starts, len(ids))))
        self._cuts[key] = out
        return out


class StereoRenderer:
    """Renders the rig's left and right images of a mock-up at a pose (see the module doc).

    A renderer reuses its work buffers from call to call (a frame's canvases, the faces'
    4-channel textures), so one renderer serves one thread at a time; give each thread its own.

    Args:
        rig: the stereo rig (image size, intrinsics, distortion, extrinsics).
        mockup: the mock-up (:func:`trackmeter.sources.sim.mockup.load_mockup`).
        params: lighting, exposure, noise and blur.
    """

    def __init__(self, rig: StereoRig, mockup: Mockup, params: RenderParams | None = None) -> None:
        self.rig = rig
        self.mockup = mockup
        self.params = params if params is not None else RenderParams()
        self._views = (_View(rig.left), _View(rig.right))
        self._geom = _Geom(mockup.faces)
        self._occluder_surfaces: dict[tuple[float, float], Face] = {}
        self._last_gain = float("nan")
        # per texture level drawn: a 4-channel (radiance, alpha, 0, 0) texture, alpha filled once,
        # and the radiance array its channel 0 holds
        self._tex4: dict[TextureLevel, tuple[F32, F32]] = {}
        self._unlit: dict[tuple[TextureLevel, float], F32] = {}  # radiance of faces the sun does not reach
        self._buffers: dict[tuple[int, int], tuple[F32, F32, tuple[int, int, int, int]]] = {}  # radiance_canvas(_slot=)

    @property
    def last_gain_grey(self) -> float:
        """The exposure gain of the last :meth:`render`, grey levels per unit radiance."""
        return self._last_gain

    # ------------------------------------------------------------------ public API

    def render(
        self,
        T_cam_body: FloatArray,
        sun_dir_cam: FloatArray,
        rng: np.random.Generator,
        T_cam_body_prev: FloatArray | None = None,
        occluders: Sequence[Occluder] = (),
        noise: bool = True,
    ) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
        """Render a stereo pair.

        Args:
            T_cam_body: (4,4) pose of the mock-up in the left camera frame (m).
            sun_dir_cam: (3,) direction TOWARD the sun in the left camera frame (normalised here).
            rng: source of the sensor noise (the only randomness).
            T_cam_body_prev: pose one frame interval earlier; with ``motion_blur_subframes > 1``
                the image averages sub-frames over ``shutter_fraction`` of the interval, centred
                on ``T_cam_body``.
            occluders: dark panels in the left camera frame.
            noise: False gives the noise-free image (black level still added), for tests.

        Returns:
            ``(left, right)``: (H,W) uint8 grey images, unrectified, with the rig's distortion.
        """
        p = self.params
        T_cam_body = _as_pose(T_cam_body, "T_cam_body")
        s_cam = np.asarray(sun_dir_cam, dtype=float).reshape(3)
        if not np.all(np.isfinite(s_cam)) or np.linalg.norm(s_cam) == 0:
            raise TrackmeterError("sun_dir_cam must be a finite non-zero 3-vector")
        s_cam = s_cam / np.linalg.norm(s_cam)
        poses = [T_cam_body]
        if T_cam_body_prev is not None and p.motion_blur_subframes > 1 and p.shutter_fraction > 0:
            poses = _subframe_poses(_as_pose(T_cam_body_prev, "T_cam_body_prev"), T_cam_body, p.motion_blur_subframes, p.shutter_fraction)
        canvases: list[F32] = [np.zeros(0, np.float32), np.zeros(0, np.float32)]
        boxes: list[list[tuple[int, int, int, int]]] = [[], []]  # canvas boxes drawn into, per side
        cover: NDArray[np.bool_] | None = None
        for k, T in enumerate(poses):
            shared: dict = {}
            for side in (0, 1):
                rad, zbuf = self.radiance_canvas(side, T, s_cam, occluders, _shared=shared, _slot=min(k, 1))
                boxes[side].append(shared[("box", side)])
                canvases[side] = rad if k == 0 else canvases[side] + rad
                if side == 0 and cover is None:
                    cover = rad[::2, ::2] > 0  # the first sub-frame's satellite, for the auto-iris
        if len(poses) > 1:
            for c in canvases:
                c *= np.float32(1.0 / len(poses))
        assert cover is not None
        if p.auto_exposure:
            vals = canvases[0][::2, ::2][cover]
            level = float(np.percentile(vals[:: max(1, len(vals) // 20000)], p.exposure_percentile)) if len(vals) else 0.0
            gain = p.exposure_target_grey / level if level > 0 else p.max_gain_grey
            gain = min(gain, p.max_gain_grey)
        else:
            gain = p.exposure_gain_grey
        self._last_gain = gain
        out = []
        for side in (0, 1):
            view = self._views[side]
            W, H = view.cam.image_size
            # the canvas is 0 outside the faces' boxes, and so is the image where it only sees that
            x0, y0 = min(b[0] for b in boxes[side]), min(b[1] for b in boxes[side])
            x1, y1 = max(b[2] for b in boxes[side]), max(b[3] for b in boxes[side])
            box = view.image_box((x0, y0, x1, y1)) if x1 > x0 and y1 > y0 else None
            c0, r0, c1, r1 = box if box is not None else (0, 0, 0, 0)
            img = np.empty((H, W), np.float32)  # zeroed below outside the box (np.zeros page-faults)
            img[:r0] = 0.0
            img[r1:] = 0.0
            img[r0:r1, :c0] = 0.0
            img[r0:r1, c1:] = 0.0
            if box is not None:
                cv2.remap(canvases[side], view.map_x[r0:r1, c0:c1], view.map_y[r0:r1, c0:c1], cv2.INTER_LINEAR,
                          dst=img[r0:r1, c0:c1], borderMode=cv2.BORDER_CONSTANT, borderValue=0)
                img[r0:r1, c0:c1] *= np.float32(gain)
            if noise:
                # Gaussian with the Poisson variance of the signal plus the read noise. OpenCV's
                # generator (seeded from rng, so runs repeat) is ~2x faster than numpy's here.
                sigma = cv2.sqrt(cv2.add(img * np.float32(p.shot_noise_gain), p.read_noise_grey**2)) if p.shot_noise_gain > 0 else None
                z = np.empty_like(img)
                cv2.setRNGSeed(int(rng.integers(0, 2**31 - 1)))
                cv2.randn(z, 0.0, 1.0)  # type: ignore[call-overload]
                if sigma is None:
                    z *= np.float32(p.read_noise_grey)
                else:
                    z *= sigma
                img += z
            img += p.black_level_grey + 0.5
            np.clip(img, 0.0, 255.0, out=img)
            out.append(img.astype(np.uint8))
        return out[0], out[1]

    def surface_points(self, T_cam_body: FloatArray, uv_left: FloatArray, occluders: Sequence[Occluder] = ()) -> FloatArray:
        """Body-frame surface point (N,3), m, seen at each ORIGINAL left pixel (N,2); NaN rows where
        the pixel sees black space or an occluder.

        Same visibility as :meth:`render`: the nearest front-facing (or two-sided) face whose
        coverage at that point is at least one half.
        """
        return self._surface_points(0, _as_pose(T_cam_body, "T_cam_body"), _as_pose(T_cam_body, "T_cam_body"), uv_left, occluders)

    def surface_points_right(self, T_cam_body: FloatArray, uv_right: FloatArray, occluders: Sequence[Occluder] = ()) -> FloatArray:
        """As :meth:`surface_points` for ORIGINAL right-image pixels (N,2)."""
        T = _as_pose(T_cam_body, "T_cam_body")
        return self._surface_points(1, self.rig.T_cam1_cam @ T, T, uv_right, occluders)

    # ------------------------------------------------------------------ internals

    def _occluder_faces(self, T_cam_body: FloatArray, occluders: Sequence[Occluder]) -> list[Face]:
        """Occluder panels as two-sided faces in the body frame (textures cached by size)."""
        faces = []
        T_body_cam = np.linalg.inv(T_cam_body)
        for k, occ in enumerate(occluders):
            key = occ.size_m
            proto = self._occluder_surfaces.get(key)
            if proto is None:
                mat = MaterialSpec(name="occluder", kind="plain", albedo=self.params.occluder_albedo, albedo_variation=0.0)
                proto = _make_face("occluder", np.zeros(3), np.eye(3)[0], np.eye(3)[1], key, mat, mat, "rect", self.mockup.texel_m, 0, "")
                self._occluder_surfaces[key] = proto
            T = T_body_cam @ occ.T_cam_occluder
            e_u, e_v = T[:3, 0], T[:3, 1]
            origin = T[:3, 3] - 0.5 * key[0] * e_u - 0.5 * key[1] * e_v
            faces.append(
                Face(
                    name=f"occluder_{k}",
                    origin=origin,
                    e_u=e_u,
                    e_v=e_v,
                    size_m=key,
                    front=proto.front,
                    back=proto.back,
                    outline=proto.outline,
                    part=f"occluder_{k}",
                )
            )
        return faces

    def radiance_canvas(
        self,
        side: int,
        T_cam_body: FloatArray,
        sun_dir_cam: FloatArray,
        occluders: Sequence[Occluder] = (),
        _shared: dict | None = None,
        _slot: int | None = None,
    ) -> tuple[F32, F32]:
        """Noise-free radiance of one camera's undistorted pinhole canvas and its ``1/z`` buffer
        (0 where nothing is drawn; only kept up to date where a later face needs it: use the
        radiance, not this buffer, to tell space from satellite). ``side`` 0 = left, 1 = right.

        ``_shared`` lets the two cameras of one instant share what does not depend on the view
        (shadows, diffuse shading); pass the same fresh dict for both. With ``_slot`` the two
        buffers returned are the renderer's own, reused (and overwritten) by the next call with
        the same side and slot; else they are new.
        """
        view = self._views[side]
        T_view_body = T_cam_body if side == 0 else self.rig.T_cam1_cam @ T_cam_body
        R, t = T_view_body[:3, :3], T_view_body[:3, 3]
        s_body = T_cam_body[:3, :3].T @ np.asarray(sun_dir_cam, dtype=float)
        s_body = s_body / np.linalg.norm(s_body)
        C = -R.T @ t
        shared = _shared if _shared is not None else {}
        geom = shared.get("geom")
        if geom is None:
            geom = self._geom if not occluders else _Geom(list(self.mockup.faces) + self._occluder_faces(T_cam_body, occluders))
            shared["geom"] = geom
        Wc, Hc = view.size
        Kc = view.K_canvas
        p = self.params
        E = p.sun_irradiance

        # visibility, projection and level of detail of every face at once
        dC = np.einsum("fk,fk->f", C - geom.origin, geom.normal)
        sgn = np.where(dC > 0, 1.0, -1.0)
        drawable = (dC > 0) | geom.has_back
        P = geom.corners @ R.T + t  # (F,4,3) view frame
        z = P[..., 2]
        drawable &= z.min(axis=1) >= _NEAR_M
        uvw = P @ Kc.T
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = uvw[..., :2] / uvw[..., 2:]
        x0 = np.floor(uv[..., 0].min(axis=1)) - 2
        y0 = np.floor(uv[..., 1].min(axis=1)) - 2
        x1 = np.ceil(uv[..., 0].max(axis=1)) + 3
        y1 = np.ceil(uv[..., 1].max(axis=1)) + 3
        drawable &= (x1 > 0) & (y1 > 0) & (x0 < Wc) & (y0 < Hc)
        u, v = uv[..., 0], uv[..., 1]
        prev = [3, 0, 1, 2]  # np.roll(., 1, axis=1) of the 4 corners, without its overhead
        area = 0.5 * np.abs(np.einsum("fk,fk->f", u, v[:, prev]) - np.einsum("fk,fk->f", v, u[:, prev]))
        with np.errstate(divide="ignore", invalid="ignore"):
            lod = 0.5 * np.log2(geom.n_texels / np.maximum(area, 1e-6)) + 0.5 + p.mip_bias
        order = np.flatnonzero(drawable)
        order = order[np.argsort(-z[order].mean(axis=1), kind="stable")]
        s_side_n = (geom.normal @ s_body) * sgn  # sun elevation over each visible side
        # per-face mip level, homography (texel centres -> canvas ROI) and 1/z plane, vectorised
        # Nearest filtering rounds the level of detail (the +0.5 above); trilinear filtering blends
        # the two levels around the unrounded one, which keeps the same sharpness on average.
        lod = np.nan_to_num(lod - 0.5 if p.trilinear else lod, nan=0.0, posinf=0.0, neginf=0.0)
        level = np.clip(np.floor(lod), 0, geom.n_levels - 1).astype(int)
        nvnu = geom.level_shape[np.arange(len(level)), level]
        su = geom.size[:, 0] / nvnu[:, 1]
        sv = geom.size[:, 1] / nvnu[:, 0]
        o = geom.origin + 0.5 * su[:, None] * geom.e_u + 0.5 * sv[:, None] * geom.e_v
        M = np.stack([(geom.e_u @ R.T) * su[:, None], (geom.e_v @ R.T) * sv[:, None], o @ R.T + t], axis=2)
        Hs = np.einsum("ij,fjk->fik", Kc, M)
        ix0 = np.clip(x0, 0, Wc).astype(int)
        iy0 = np.clip(y0, 0, Hc).astype(int)
        ix1 = np.clip(x1, 0, Wc).astype(int)
        iy1 = np.clip(y1, 0, Hc).astype(int)
        Hs[:, 0] -= ix0[:, None] * Hs[:, 2]  # texel centres -> pixels of the face's box
        Hs[:, 1] -= iy0[:, None] * Hs[:, 2]
        n_v = (geom.normal * sgn[:, None]) @ R.T
        # A face seen edge-on (its plane through the camera centre) covers no pixel: its
        # inverse-depth gradient, infinite, is never read (numpy's warning said so on stderr).
        with np.errstate(divide="ignore", invalid="ignore"):
            gz = (n_v @ view.K_canvas_inv) / np.einsum("fk,fk->f", n_v, geom.origin @ R.T + t)[:, None]
        gz = gz.astype(np.float32)
        big_enough = area >= _MIN_SHADOW_AREA_PX
        # which drawn faces' boxes overlap an earlier one (must read the depth buffer) or a later
        # one (must write it)
        bx0, by0, bx1, by1 = ix0[order], iy0[order], ix1[order], iy1[order]
        overlap = (bx0[:, None] < bx1[None, :]) & (bx0[None, :] < bx1[:, None]) & (by0[:, None] < by1[None, :]) & (by0[None, :] < by1[:, None])
        rank = np.arange(len(order))
        must_read = dict(zip(order.tolist(), (overlap & (rank[None, :] < rank[:, None])).any(axis=1).tolist()))
        must_write = dict(zip(order.tolist(), (overlap & (rank[None, :] > rank[:, None])).any(axis=1).tolist()))

        if len(order):
            box = (int(ix0[order].min()), int(iy0[order].min()), int(ix1[order].max()), int(iy1[order].max()))
        else:
            box = (0, 0, 0, 0)
        shared[("box", side)] = box
        if _slot is None:
            canvas = np.zeros((Hc, Wc), np.float32)
            zbuf = np.zeros((Hc, Wc), np.float32)
        else:
            # reused buffers: only the box the last call drew into needs clearing (a fresh zeroed
            # array of this size costs page faults, several times the clearing)
            reuse = self._buffers.get((side, _slot))
            if reuse is None:
                canvas, zbuf = np.zeros((Hc, Wc), np.float32), np.zeros((Hc, Wc), np.float32)
            else:
                canvas, zbuf, (a0, b0, a1, b1) = reuse
                canvas[b0:b1, a0:a1] = 0.0
                zbuf[b0:b1, a0:a1] = 0.0
            self._buffers[(side, _slot)] = (canvas, zbuf, box)
        amb = p.ambient * E
        n_sides = sgn[:, None] * geom.normal
        # glint test geometry of every face: distance to the camera, angle of the half vector of
        # the sun and the face centre's view direction to the face's normal (see below)
        to_cam = C - geom.centre
        dists = np.sqrt(np.einsum("fk,fk->f", to_cam, to_cam))
        h_c = to_cam / dists[:, None] + s_body
        with np.errstate(divide="ignore", invalid="ignore"):
            offs = np.arccos(np.clip(np.einsum("fk,fk->f", h_c, n_sides) / np.sqrt(np.einsum("fk,fk->f", h_c, h_c)), -1.0, 1.0))
            spreads = 0.5 * np.arctan(geom.half_diag / dists) + 0.02
        levels = level.tolist()
        # Trilinear filtering: the fraction of the way to the next (coarser) level. A switch of
        # level alone changes a face's whole texture from one frame to the next (estec: at
        # t = 1.0 s the grid faces went one level sharper and a tracker lost 9-11 of its 15
        # targets in one frame), which no camera does.
        blend = np.clip(lod - level, 0.0, 1.0) if p.trilinear else None
        for f in order.tolist():
            face = geom.faces[f]
            surf = face.front if sgn[f] > 0 else face.back
            assert surf is not None
            lvl = surf.levels[levels[f]]
            nv, nu = lvl.shape
            face_light = (geom, f, surf, n_sides[f], s_body, s_side_n[f], E, amb, C, offs[f], spreads[f], big_enough[f], shared)
            rad_pm = self._face_radiance(*face_light, levels[f])
            w = 0.0 if blend is None else float(blend[f])
            if w > 1e-3 and levels[f] + 1 < len(surf.levels):
                coarse = self._face_radiance(*face_light, levels[f] + 1)
                up = cv2.resize(coarse, (nu, nv), interpolation=cv2.INTER_LINEAR)
                rad_pm = cast(F32, cv2.addWeighted(rad_pm, 1.0 - w, up, w, 0.0))
            self._draw(canvas, zbuf, rad_pm, lvl, Hs[f], (int(ix0[f]), int(iy0[f]), int(ix1[f]), int(iy1[f])), gz[f], must_read[f], must_write[f])
        return canvas, zbuf

    def _face_radiance(self, geom: _Geom, f: int, surf: Surface, n_side: FloatArray, s_body: FloatArray,
                       s_side_n: float, E: float, amb: float, C: FloatArray, off: float, spread: float,
                       big_enough: bool, shared: dict, level: int) -> F32:
        """Premultiplied radiance of face ``f``'s visible side ``surf`` on the texel grid of mip
        ``level``: ambient + diffuse (with the face's cast shadows) + glint."""
        p = self.params
        face = geom.faces[f]
        lvl = surf.levels[level]
        nv, nu = lvl.shape
        if s_side_n <= 0 or E == 0:
            unlit_key = (lvl, amb)
            rad_pm = self._unlit.get(unlit_key)
            if rad_pm is None:
                rad_pm = self._unlit[unlit_key] = lvl.albedo_pm * np.float32(amb)
        else:
            key = (f, level)
            cached = shared.get(key)
            if cached is None:
                lit = _shadow_mask(geom, f, n_side, (nv, nu), s_body) if big_enough else None
                s_loc = np.array([s_body @ face.e_u, s_body @ face.e_v, s_side_n])
                ndl = cv2.transform(lvl.normal, s_loc.reshape(1, 3))  # n'.s per texel
                ndl = cv2.max(ndl, 0.0)
                if lit is not None:
                    ndl = cv2.multiply(ndl, lit)
                diffuse = cv2.multiply(ndl, lvl.albedo_pm, scale=E)
                diffuse = cv2.scaleAdd(lvl.albedo_pm, amb, diffuse)
                cached = (diffuse, lit, s_loc)
                shared[key] = cached
            diffuse, lit, s_loc = cached
            rad_pm = cast(F32, diffuse)
            k_spec = p.glint_strength * E
            sharp = surf.sharpness * p.glint_sharpness
            if k_spec * surf.material.specular > 0:
                # skip faces whose facets cannot reach the lobe: the steepest facet tilt is
                # ~4 sigma of the material's slope, the lobe is negligible 7/k below its peak,
                # and across the face h turns by at most half the view direction's spread
                tilt = math.atan(4.0 * surf.material.slope)
                lobe = math.acos(max(-1.0, 1.0 - 7.0 / sharp))
                if off - spread - tilt < lobe:
                    hv = _half_vectors(face, n_side, C, s_loc)
                    big = cv2.resize(hv, (nu, nv), interpolation=cv2.INTER_LINEAR)
                    ndh = cv2.transform(cv2.multiply(lvl.normal, big), _SUM3)  # n'.h
                    glint = cv2.exp(cv2.addWeighted(ndh, sharp, ndh, 0.0, -sharp))  # exp(k (n'.h - 1))
                    glint = cv2.multiply(glint, lvl.spec_pm, scale=k_spec)
                    if lit is not None:
                        glint = cv2.multiply(glint, lit)
                    rad_pm = cast(F32, cv2.add(diffuse, glint))
        return rad_pm

    def _draw(
        self, canvas: F32, zbuf: F32, rad_pm: F32, lvl: TextureLevel, H: FloatArray, box: tuple[int, int, int, int], g: F32,
        read: bool, write: bool,
    ) -> None:
        """Composite one face's warped premultiplied radiance "over" the canvas in ``box``
        (columns a0..a1, rows b0..b1), behind the ``1/z`` depth test when ``read`` (something may
        be drawn there already) and updating ``zbuf`` where it covers when ``write``.
        ``H`` maps texel centres to the box's pixels; ``g`` is the face's ``1/z`` plane;
        ``rad_pm`` the face's premultiplied radiance on the texel grid of ``lvl``, the mip level
        whose ``alpha`` is the coverage."""
        a0, b0, a1, b1 = box
        size = (a1 - a0, b1 - b0)
        cv = canvas[b0:b1, a0:a1]  # views: OpenCV reads and writes them in place
        zb = zbuf[b0:b1, a0:a1]
        if not read and not write:
            # nothing was drawn in this box yet (the canvas there is 0, so "over" is a copy), nor
            # will be: neither coverage nor depth is needed
            cv2.warpPerspective(rad_pm, H, size, dst=cv, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            return
        # Radiance and coverage in one warp of a 4-channel texture: OpenCV's 4-channel float path
        # costs about as much as one 1-channel warp (its 2-channel path several times more), and
        # interpolates each channel exactly as a 1-channel warp would.
        tex, held = self._tex4.get(lvl, (None, None))
        if tex is None:
            tex = np.zeros((*lvl.shape, 4), np.float32)
            cv2.insertChannel(lvl.alpha, tex, 1)
        if held is not rad_pm:  # the same array again (unlit, or the other camera's diffuse): already in
            cv2.insertChannel(rad_pm, tex, 0)
            self._tex4[lvl] = (tex, rad_pm)
        both = cv2.warpPerspective(tex, H, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        aw = cv2.extractChannel(both, 1)
        if not read:
            cv2.extractChannel(both, 0, dst=cv)  # nothing was drawn in this box yet: a copy
            rw = None
        else:
            rw = cv2.extractChannel(both, 0)
        # inverse depth of the face's plane over the box: 1/z = g . (u, v, 1)
        g0, g1, g2 = g
        xs = np.arange(a0, a1, dtype=np.float32) * g0
        ys = np.arange(b0, b1, dtype=np.float32) * g1 + g2
        iz = None
        if read:
            assert rw is not None
            # depth test, skipped when the face is nearer than everything drawn in its box
            # (1/z is affine, so its minimum over the box is at a corner)
            iz_min = min(xs[0], xs[-1]) + min(ys[0], ys[-1])
            if cv2.minMaxLoc(zb)[1] * (1.0 - 1e-3) > iz_min:
                iz = ys[:, None] + xs[None, :]
                vis = (iz >= zb * np.float32(1.0 - 1e-3)).astype(np.float32)
                aw *= vis
                rw *= vis
        if write:
            if iz is None:
                iz = ys[:, None] + xs[None, :]
            cv2.copyTo(iz, cv2.compare(aw, 0.5, cv2.CMP_GE), zb)  # type: ignore[call-overload]  # where covered; np.copyto(where=) is far slower
        if read:
            assert rw is not None
            cv2.subtract(cv, cv2.multiply(cv, aw), dst=cv)  # premultiplied "over": cv (1 - a) + rad
            cv2.add(cv, rw, dst=cv)

    def _surface_points(
        self, side: int, T_view_body: FloatArray, T_cam_body: FloatArray, uv: FloatArray, occluders: Sequence[Occluder]
    ) -> FloatArray:
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        cam = self._views[side].cam
        xy = cam.undistort(uv)
        rays = np.column_stack([xy, np.ones(len(xy))])
        R, t = T_view_body[:3, :3], T_view_body[:3, 3]
        C = -R.T @ t
        d = rays @ R  # rows R^T r
        best = np.full(len(uv), np.inf)
        blocked = np.zeros(len(uv), bool)
        n_mock = len(self.mockup.faces)
        faces = list(self.mockup.faces) + self._occluder_faces(T_cam_body, occluders)
        for index, face in enumerate(faces):
            n = face.normal
            if (C - face.origin) @ n > 0:
                surf = face.front
            elif face.back is not None:
                surf = face.back
            else:
                continue
            denom = d @ n
            with np.errstate(divide="ignore", invalid="ignore"):
                lam = ((face.origin - C) @ n) / denom
            P = C + lam[:, None] * d
            x = (P - face.origin) @ face.e_u
            y = (P - face.origin) @ face.e_v
            w, h = face.size_m
            hit = np.isfinite(lam) & (lam > 0) & (x >= 0) & (x <= w) & (y >= 0) & (y <= h) & (lam < best)
            if not hit.any():
                continue
            lvl = surf.levels[0]
            nv, nu = lvl.shape
            a = map_coordinates(lvl.alpha, [y[hit] / (h / nv) - 0.5, x[hit] / (w / nu) - 0.5], order=1, mode="constant", cval=0.0)
            idx = np.flatnonzero(hit)[a >= 0.5]
            best[idx] = lam[idx]
            blocked[idx] = index >= n_mock
        out = C + best[:, None] * d
        out[~np.isfinite(best) | blocked] = np.nan
        return out


# --------------------------------------------------------------------------- helpers


def _as_pose(T: FloatArray, name: str) -> FloatArray:
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise TrackmeterError(f"{name} must be a finite 4x4 matrix")
    return T


def _subframe_poses(T_prev: FloatArray, T_cur: FloatArray, n: int, shutter: float) -> list[FloatArray]:
    """Poses spread over the shutter time centred on ``T_cur``: rotation along the geodesic,
    translation linear, extrapolated half a shutter past ``T_cur`` with the same motion."""
    dR = T_cur[:3, :3] @ T_prev[:3, :3].T
    rv = Rotation.from_matrix(dR).as_rotvec()
    out = []
    for a in 1.0 + shutter * np.linspace(-0.5, 0.5, n):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(a * rv).as_matrix() @ T_prev[:3, :3]
        T[:3, 3] = T_prev[:3, 3] + a * (T_cur[:3, 3] - T_prev[:3, 3])
        out.append(T)
    return out


@functools.lru_cache(maxsize=1024)
def _grid(size_m: tuple[float, float], g: int) -> tuple[FloatArray, FloatArray]:
    """Centres of a g x g grid over a face of ``size_m`` (w, h): local x (g,) and y (g,), m."""
    w, h = size_m
    return cast("tuple[FloatArray, FloatArray]", ((np.arange(g) + 0.5) * (w / g), (np.arange(g) + 0.5) * (h / g)))


def _half_vectors(face: Face, n_side: FloatArray, C: FloatArray, s_loc: FloatArray, g: int = 7) -> F32:
    """Unit half vectors of sun and view directions, (g,g,3) float32 in the face's local frame
    ``(e_u, e_v, n_side)``, exact at a g x g grid placed where ``cv2.resize``'s bilinear
    interpolation to the texture size puts its samples (h varies smoothly over a face)."""
    d = C - face.origin
    xs, ys = _grid(face.size_m, g)
    v = np.empty((g, g, 3))
    v[..., 0] = d @ face.e_u - xs[None, :]
    v[..., 1] = d @ face.e_v - ys[:, None]
    v[..., 2] = d @ n_side
    v /= np.sqrt((v * v).sum(axis=2, keepdims=True))
    hv = v + s_loc
    hv /= np.sqrt((hv * hv).sum(axis=2, keepdims=True))
    return hv.astype(np.float32)


def _shadow_mask(geom: _Geom, index: int, n_side: FloatArray, shape: tuple[int, int], s_body: FloatArray) -> F32 | None:
    """Lit fraction (nv,nu) of a face's texels (1 lit, 0 in shadow), or None when nothing shades it.

    Each part (a convex solid: box, panel, disc) is cut to the sun side of the face's plane
    (its vertices there plus its edges' crossings of the plane), projected along the sun
    direction onto the plane, and the convex hull filled (anti-aliased) in texel coordinates.
    """
    face = geom.faces[index]
    cut = geom.cut_casters(index, n_side)
    if cut is None:
        return None
    pts, starts, counts = cut
    nv, nu = shape
    w, h = face.size_m
    sn = float(s_body @ n_side)
    Q = pts - np.outer(((pts - face.origin) @ n_side) / sn, s_body)
    ij = np.column_stack([(Q - face.origin) @ face.e_u * (nu / w) - 0.5, (Q - face.origin) @ face.e_v * (nv / h) - 0.5])
    # per-part bounding boxes of the projections; only parts whose shadow reaches the face are drawn
    lo = np.minimum.reduceat(ij, starts, axis=0)
    hi = np.maximum.reduceat(ij, starts, axis=0)
    hits = np.flatnonzero((counts >= 3) & (hi[:, 0] >= -1) & (hi[:, 1] >= -1) & (lo[:, 0] <= nu) & (lo[:, 1] <= nv))
    if len(hits) == 0:
        return None
    mask = np.zeros((nv, nu), np.uint8)
    for k in hits:
        chunk = ij[starts[k] : starts[k] + counts[k]]
        hull = cv2.convexHull(np.round(chunk * 16).astype(np.int32))
        cv2.fillConvexPoly(mask, hull, 255, cv2.LINE_AA, shift=4)
    return cast(F32, cv2.LUT(mask, _LIT_OF_MASK))


# --------------------------------------------------------------------------- preview pictures


def look_at(position_cam: FloatArray, rotvec_deg: FloatArray) -> FloatArray:
    """A pose ``T_cam_body`` with the body origin at ``position_cam`` (m) and attitude given as a
    rotation vector (deg) of the body axes in the camera frame."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    T[:3, 3] = position_cam
    return T


#: README pictures: scenario name -> frame indices (one left|right row per frame). estec 1250:
#: wings, dish and its shadow at 50 s; harsh_light 276: the panel hides part of the lit face,
#: differently in the two cameras; 326: glints and the star tracker's shadow.
PREVIEW_FRAMES: dict[str, tuple[int, ...]] = {"estec": (1250,), "harsh_light": (276, 326)}


def preview_pairs(out_dir: Path, frames: dict[str, tuple[int, ...]] | None = None, scale: float = 0.7) -> list[Path]:
    """Render the README pictures: for each scenario, its left|right pairs at the given frames,
    exactly as the simulator delivers them (noise included), cropped to the satellite plus a
    margin (the same crop in both images, so the disparity shows), shown at ``scale`` (area
    averaging; keeps the PNGs small despite the sensor noise), into ``sim_<name>.png``."""
    from trackmeter.sources.sim.simulator import Simulator

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, indices in (frames or PREVIEW_FRAMES).items():
        sim = Simulator(name)
        pairs = [sim.frame(i) for i in indices]
        lit: NDArray[np.bool_] = np.zeros(pairs[0].left.shape, bool)
        for i in indices:
            clean = sim.renderer.render(sim.truth(i).T_cam_body, sim.sun_dir_cam, np.random.default_rng(0), noise=False,
                                        occluders=sim.occluders_at(i))
            lit |= (clean[0] > 12) | (clean[1] > 12)
        rows, cols = np.flatnonzero(lit.any(axis=1)), np.flatnonzero(lit.any(axis=0))
        h, w = lit.shape
        r0, r1 = (max(0, rows[0] - 24), min(h, rows[-1] + 25)) if len(rows) else (0, h)
        c0, c1 = (max(0, cols[0] - 24), min(w, cols[-1] + 25)) if len(cols) else (0, w)
        gap = np.full((r1 - r0, 6), 255, np.uint8)
        rows_img = [np.hstack([f.left[r0:r1, c0:c1], gap, f.right[r0:r1, c0:c1]]) for f in pairs]
        sheet = np.vstack([x for row in rows_img for x in (row, np.full((6, row.shape[1]), 255, np.uint8))][:-1])
        if scale != 1.0:
            sheet = cv2.resize(sheet, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        path = out_dir / f"sim_{name}.png"
        tmp = path.with_name(path.stem + ".tmp.png")
        cv2.imwrite(str(tmp), sheet, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        tmp.replace(path)
        paths.append(path)
    return paths


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m trackmeter.sources.sim.render",
        description="Render the README pictures: left|right pairs of the estec and harsh_light scenarios "
        "(frames in PREVIEW_FRAMES) into DIR/sim_estec.png and DIR/sim_harsh_light.png.",
    )
    parser.add_argument("--preview", type=Path, required=True, metavar="DIR", help="output folder, e.g. docs/images")
    args = parser.parse_args(argv)
    for path in preview_pairs(args.preview):
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
