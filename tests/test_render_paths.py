"""The renderer's fast paths equal the plain ones: one 4-channel warp of (radiance, alpha)
against two 1-channel warps, in-place compositing against NumPy's, and the remap of only the
image box that can see drawn canvas pixels against the remap of the whole image.

Bit for bit on some CPUs; on others OpenCV's vectorised 4-channel and 1-channel warps round
differently, and 143 of 384192 canvas pixels came out a float32 ulp or two apart (3e-8 of a
radiance near 1, 2026-12-02): the canvases are held to 1e-6, the 8-bit images they make to at
most one grey level in a handful of pixels (identical on both hosts seen)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from trackmeter.paths import MODELS_DIR
from trackmeter.sources.sim.mockup import load_mockup
from trackmeter.sources.sim.render import RenderParams, StereoRenderer, _View, look_at

WARP = dict(flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def _plain_draw(self, canvas, zbuf, rad_pm, lvl, H, box, g, read, write) -> None:  # type: ignore[no-untyped-def]
    """The renderer's compositing step written plainly (two 1-channel warps, NumPy arithmetic)."""
    a0, b0, a1, b1 = box
    size = (a1 - a0, b1 - b0)
    rw = cv2.warpPerspective(rad_pm, H, size, **WARP)
    aw = cv2.warpPerspective(lvl.alpha, H, size, **WARP)
    zb = zbuf[b0:b1, a0:a1]
    cv = canvas[b0:b1, a0:a1]
    if read or write:
        xs = np.arange(a0, a1, dtype=np.float32) * g[0]
        ys = np.arange(b0, b1, dtype=np.float32) * g[1] + g[2]
        iz = ys[:, None] + xs[None, :]
        if read and float(zb.max()) * (1.0 - 1e-3) > min(xs[0], xs[-1]) + min(ys[0], ys[-1]):
            vis = (iz >= zb * np.float32(1.0 - 1e-3)).astype(np.float32)
            aw *= vis
            rw *= vis
        if write:
            np.copyto(zb, iz, where=aw >= 0.5)
    if read:
        cv -= cv * aw
    cv += rw


@pytest.fixture(scope="module")
def estec_pair(estec_rig):  # type: ignore[no-untyped-def]
    mockup = load_mockup(MODELS_DIR / "estec_mockup.yaml")
    return StereoRenderer(estec_rig, mockup, RenderParams()), StereoRenderer(estec_rig, mockup, RenderParams())


@pytest.mark.parametrize("pose", [((0.1, 0.0, 3.5), (-110.0, 35.0, 20.0)), ((-0.4, 0.2, 2.2), (60.0, -20.0, 150.0))])
def test_fast_compositing_equals_plain(estec_pair, pose, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    fast, plain = estec_pair
    monkeypatch.setattr(plain, "_draw", _plain_draw.__get__(plain))
    T = look_at(np.array(pose[0]), np.array(pose[1]))
    sun = np.array([-0.5, -0.6, -0.6])
    for side in (0, 1):
        a, _ = fast.radiance_canvas(side, T, sun)
        b, _ = plain.radiance_canvas(side, T, sun)
        assert (a > 0).mean() > 0.05
        np.testing.assert_allclose(a, b, rtol=0.0, atol=1e-6)
    # whole images, noise seeded the same
    fa = fast.render(T, sun, np.random.default_rng(3))
    pa = plain.render(T, sun, np.random.default_rng(3))
    for f, p in zip(fa[:2], pa[:2]):
        diff = np.abs(f.astype(int) - p.astype(int))
        assert diff.max() <= 1 and np.count_nonzero(diff) <= 10


def test_image_box_holds_every_pixel_that_sees_the_canvas_box(estec_rig) -> None:  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(0)
    for cam in (estec_rig.left, estec_rig.right):
        view = _View(cam)
        Wc, Hc = view.size
        for _ in range(6):
            x0, x1 = sorted(rng.integers(0, Wc, 2))
            y0, y1 = sorted(rng.integers(0, Hc, 2))
            x1, y1 = x1 + 1, y1 + 1
            canvas = np.zeros((Hc, Wc), np.float32)
            canvas[y0:y1, x0:x1] = rng.uniform(0.5, 1.0, (y1 - y0, x1 - x0)).astype(np.float32)
            full = cv2.remap(canvas, view.map_x, view.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            box = view.image_box((int(x0), int(y0), int(x1), int(y1)))
            inside = np.zeros(full.shape, bool)
            if box is not None:
                c0, r0, c1, r1 = box
                inside[r0:r1, c0:c1] = True
                part = cv2.remap(canvas, view.map_x[r0:r1, c0:c1], view.map_y[r0:r1, c0:c1], cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=0)
                assert np.array_equal(part, full[r0:r1, c0:c1])
            assert not full[~inside].any()
            # and the box is tight: it is not much larger than the image of the canvas box
            if full.any():
                rows, cols = np.flatnonzero(full.any(axis=1)), np.flatnonzero(full.any(axis=0))
                assert box is not None and box[0] >= cols[0] - 3 and box[2] <= cols[-1] + 4
                assert box[1] >= rows[0] - 3 and box[3] <= rows[-1] + 4


def test_reused_buffers_leave_nothing_behind(estec_rig) -> None:  # type: ignore[no-untyped-def]
    """A render after one of a nearer, larger view (with motion blur: both buffer slots) equals
    the same render by a fresh renderer."""
    mockup = load_mockup(MODELS_DIR / "estec_mockup.yaml")
    params = RenderParams(motion_blur_subframes=3)
    used, fresh = StereoRenderer(estec_rig, mockup, params), StereoRenderer(estec_rig, mockup, params)
    sun = np.array([-0.5, -0.6, -0.6])
    near = look_at(np.array([-0.3, 0.2, 2.0]), np.array([60.0, -20.0, 150.0]))
    T = look_at(np.array([0.4, 0.1, 4.5]), np.array([-110.0, 35.0, 20.0]))
    T_prev = look_at(np.array([0.4, 0.1, 4.5]), np.array([-108.0, 34.0, 21.0]))
    used.render(near, sun, np.random.default_rng(1), T_cam_body_prev=T)
    a = used.render(T, sun, np.random.default_rng(2), T_cam_body_prev=T_prev)
    b = fresh.render(T, sun, np.random.default_rng(2), T_cam_body_prev=T_prev)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
