"""The tracker's guards against false locks (issue 4: a target more than 2 px from its point while
still tracking must never happen): the frame-to-frame rigid-motion check, and automatic
selection refusing new points whose stereo match puts them off the body's depth."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from trackmeter.core.features import FeatureParams, target_mask
from trackmeter.core.matching import MeasureParams
from trackmeter.core.targets import TargetState
from trackmeter.core.tracking import Tracker, TrackerParams
from trackmeter.sources.base import StereoFrame
from trackmeter.sources.plane import PlaneScene, plate_texture, pose_translating


def make_tracker(rig, **kw) -> Tracker:  # type: ignore[no-untyped-def]
    return Tracker(rig, TrackerParams(**kw), FeatureParams(), MeasureParams())


def corners(left: np.ndarray, n: int, max_u: float = 1e9) -> np.ndarray:
    mask = target_mask(left, FeatureParams(target_margin_px=30))
    mask[:, int(min(max_u, left.shape[1])) :] = 0
    return cv2.goodFeaturesToTrack(left, n, 0.05, 30, mask=mask).reshape(-1, 2).astype(float)


def add_all(tr: Tracker, frame: StereoFrame, pts: np.ndarray) -> list[str]:
    out = [tr.add_target(frame, (float(u), float(v))) for u, v in pts]
    return [r.id for r in out if isinstance(r, TargetState)]


@pytest.fixture(scope="module")
def tracked(estec_rig):  # type: ignore[no-untyped-def]
    """A tracker with targets on a plate at 3.5 m, stepped once, and its live targets."""
    scene = PlaneScene(estec_rig, pose_translating(3.5, (0.1, 0.05, 0.0), (0.0, 0.0, 0.2)), noise_sigma=1.0)
    f0 = scene.frame(0)
    tr = make_tracker(estec_rig)
    add_all(tr, f0, corners(f0.left, 8))
    tr.step(scene.frame(1))
    live = [tr._targets[t.id] for t in tr.targets if t.status != "lost"]
    assert len(live) >= 6
    return tr, live


def test_motion_check_keeps_rigid_motion_within_noise_and_loses_a_sideways_jump(tracked, estec_rig) -> None:
    tr, live = tracked
    prev_P = np.array([t.point_cam for t in live])
    prev_C = np.array([t.cov_cam for t in live])
    R = Rotation.from_rotvec([0.01, -0.02, 0.015]).as_matrix()
    tvec = np.array([0.01, -0.005, 0.02])
    rng = np.random.default_rng(1)
    moved = prev_P @ R.T + tvec
    # Each new point off by one draw of its own measurement noise (mostly depth, ~3 mm).
    noisy = np.array([rng.multivariate_normal(p, c) for p, c in zip(moved, prev_C)])
    try:
        for t, p in zip(live, noisy):
            t.point_cam = p
        assert tr._motion_outliers(live, prev_P, prev_C) == {}
        # A 3 px jump across the line of sight (3 z / f = 9 mm at 3.5 m: a look-alike next to
        # the target; the simulator's was 3.5 px) is beyond the gate (~4.6 x 0.4 px of
        # motion_tolerance_px): that target alone is lost.
        f = estec_rig.rectification.focal_px
        jumped = live[3]
        jumped.point_cam = jumped.point_cam + np.array([0.0, 3.0 * jumped.point_cam[2] / f, 0.0])
        bad = tr._motion_outliers(live, prev_P, prev_C)
        assert list(bad) == [jumped.id]
        assert "rigid motion" in bad[jumped.id]
        # Too few targets to tell the motion: no verdict.
        assert tr._motion_outliers(live[:3], prev_P[:3], prev_C[:3]) == {}
    finally:
        for t, p in zip(live, moved):
            t.point_cam = p


def test_auto_disparity_range_from_the_targets_or_the_candidates_spread(tracked) -> None:
    tr, live = tracked
    d = np.array([t.disparity_px for t in tr._targets.values()])
    lo, hi = tr.auto_disparity_range([1.0, 300.0])  # the targets decide, not the candidates
    m = tr.params.auto_disparity_margin_px
    assert (lo, hi) == pytest.approx((d.min() - m, d.max() + m))
    empty = make_tracker(tr.rig)
    assert empty.auto_disparity_range([100.0, 101.0]) is None  # fewer than auto_range_min_targets
    lo, hi = empty.auto_disparity_range([100.0, 101.0, 102.0, 103.0, 104.0, 36.0, np.nan])
    # quartiles 100.25, 102.75 (linear interpolation) widened by their distance and the margin:
    # 36 px (a false match, 3x farther away) is out, the body's spread is in.
    assert (lo, hi) == pytest.approx((97.75 - m, 105.25 + m))
    assert not lo <= 36.0 <= hi


def test_automatic_selection_refuses_points_off_the_bodys_depth(estec_rig) -> None:
    # A plate at 3.5 m (disparity ~92 px) on the left and a small one at 1.6 m (~202 px) on the
    # right, apart in both images. Targets on the far plate bound the disparity of new automatic
    # points: none lands on the near plate, unless the margin is widened to take it in.
    far = PlaneScene(estec_rig, pose_translating(3.5, (0, 0, 0), start_m=(-0.55, 0.0)), size_m=(0.6, 0.6), noise_sigma=1.0)
    # the near plate's texels as small in the image as the far one's (853 per metre at 3.5 m)
    texture = plate_texture((int(0.4 * 853 * 3.5 / 1.6), int(0.3 * 853 * 3.5 / 1.6)), seed=3)
    near = PlaneScene(estec_rig, pose_translating(1.6, (0, 0, 0), start_m=(0.333, 0.0)), texture, size_m=(0.3, 0.4), noise_sigma=1.0, seed=3)
    a, b = far.frame(0), near.frame(0)
    frame = StereoFrame(index=0, t_s=0.0, left=np.maximum(a.left, b.left), right=np.maximum(a.right, b.right), truth=None)
    z = {}
    for margin in (16.0, 400.0):
        tr = make_tracker(estec_rig, max_targets=40, auto_disparity_margin_px=margin)
        ops = add_all(tr, frame, corners(a.left, 6, max_u=370))
        assert len(ops) >= 4
        tr.set_auto(True, count=len(ops) + 12, method="gabor")
        states = tr.step(frame)
        z[margin] = np.array([t.point_cam[2] for t in states if t.origin == "auto" and t.status != "lost"])
        assert len(z[margin]) >= 4
    assert np.all(np.abs(z[16.0] - 3.5) < 0.2), z[16.0]
    assert np.any(np.abs(z[400.0] - 1.6) < 0.1), z[400.0]


def test_body_check_loses_a_target_that_crept_from_its_first_point(estec_rig) -> None:
    scene = PlaneScene(estec_rig, pose_translating(3.5, (0.1, 0.05, 0.0), (0.0, 0.0, 0.2)), noise_sigma=1.0)
    f0 = scene.frame(0)
    tr = make_tracker(estec_rig, body_check=True)  # off by default: see config/default.yaml
    add_all(tr, f0, corners(f0.left, 8))
    for k in range(1, 6):
        tr.step(scene.frame(k))
    live = [tr._targets[t.id] for t in tr.targets if t.status != "lost"]
    assert len(live) >= 6
    P = np.array([t.point_cam for t in live])
    Q = np.array([t.body_point for t in live])
    # The plate turned 0.2 rad/s and moved: every first point, carried by the fitted motion,
    # is still on its target (the fit and the points' noise stay far below the limit).
    assert np.all(np.isfinite(Q))
    assert tr._body_offsets_px(P, Q).max() < 0.3 * tr.params.body_drift_px
    f = estec_rig.rectification.focal_px
    crept = live[2]
    for shift_px, lost in ((1.0, False), (2.0, True)):  # limit 1.5 px
        crept.point_cam = P[2] + np.array([shift_px * P[2][2] / f, 0.0, 0.0])
        bad = tr._body_drift(live)
        assert list(bad) == ([crept.id] if lost else []), bad
    crept.point_cam = P[2]


def test_candidates_the_measurement_refuses_are_counted_by_its_reason_not_as_off_the_body(estec_rig) -> None:
    # With targets on the body, new points must lie within their disparities (the test above).
    # A candidate the measurement itself refuses has no disparity (NaN) and is refused for the
    # measurement's reason; it is not a stereo match off the body, and `track`'s line on an
    # --auto that started nothing names the reasons counted here.
    from trackmeter.core.matching import REASON_UNCERTAIN
    from trackmeter.core.tracking import OFF_THE_BODY

    scene = PlaneScene(estec_rig, pose_translating(3.5, (0.0, 0.0, 0.0)), noise_sigma=1.0)
    frame = scene.frame(0)
    tr = make_tracker(estec_rig, max_targets=40)
    assert len(add_all(tr, frame, corners(frame.left, 6))) >= 4
    # Every new measurement now too uncertain: the top-up's candidates are all refused.
    tr.measure = dataclasses.replace(tr.measure, max_sigma_disparity_px=1e-6)
    tr.set_auto(True, count=12, method="gabor")
    tr.step(scene.frame(1))
    assert tr.stats["auto_added"] == 0
    assert tr.auto_refusals[REASON_UNCERTAIN] > 0, dict(tr.auto_refusals)
    assert tr.auto_refusals[OFF_THE_BODY] == 0, dict(tr.auto_refusals)


@pytest.mark.parametrize("margin_px, black_image, reason", [
    (3, True, "nothing lit"),
    (3, "noise", "nothing lit"),  # a dark image's specks of noise are no lit target cut by a setting
    (400, False, "features.target_margin_px"),
])
def test_an_auto_selection_with_no_selectable_pixel_says_why(estec_rig, margin_px: int, black_image: bool,
                                                             reason: str) -> None:
    """`--auto` with `features.target_margin_px: 400` (an outside probe) said "no candidate point
    (black space, no texture, or no unique stereo match)" of a lit, textured target: the margin
    the patch must keep from black space had left no pixel to select, and nothing named it."""
    from trackmeter.core.tracking import NO_CANDIDATE

    scene = PlaneScene(estec_rig, pose_translating(3.5, (0.0, 0.0, 0.0)), noise_sigma=1.0)
    frame = scene.frame(1)
    if black_image == "noise":  # sensor noise over black: the signal-to-noise fallback finds specks
        rng = np.random.default_rng(1)
        dark = [np.clip(rng.normal(8.0, 3.0, frame.left.shape), 0, 255).astype(np.uint8) for _ in range(2)]
        frame = dataclasses.replace(frame, left=dark[0], right=dark[1])
    elif black_image:
        frame = dataclasses.replace(frame, left=np.zeros_like(frame.left), right=np.zeros_like(frame.right))
    tr = Tracker(estec_rig, TrackerParams(), FeatureParams(target_margin_px=margin_px), MeasureParams())
    tr.set_auto(True, count=8, method="gabor")
    tr.step(frame)
    assert tr.stats["auto_added"] == 0
    said = [r for r in tr.auto_refusals if reason in r]
    assert said and NO_CANDIDATE not in tr.auto_refusals, dict(tr.auto_refusals)
    # The last top-up's shortfall is kept for the console (an operator ticking "Automatic
    # selection" saw nothing happen, and nothing said why) until a top-up starts a target.
    assert tr.auto_shortfall == said[0]
    tr.features = FeatureParams()
    tr.step(scene.frame(1 + tr.params.auto_interval_frames))
    assert tr.stats["auto_added"] > 0 and tr.auto_shortfall is None
    # A top-up that starts none beside live automatic targets is no news.
    before = sum(tr.auto_refusals.values())
    tr.features = FeatureParams(target_margin_px=400)
    tr.set_auto(True, count=tr.params.max_targets)
    tr.step(scene.frame(1 + 2 * tr.params.auto_interval_frames))
    assert sum(tr.auto_refusals.values()) > before and tr.auto_shortfall is None
    tr.set_auto(False)
    assert tr.auto_shortfall is None
