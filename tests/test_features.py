"""Automatic feature selection: Gabor directional bank, centroid, Shi-Tomasi; on the target,
spread, away from excluded points, stereo-matchable."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from trackmeter.core import features as ft
from trackmeter.core.features import FeatureParams, select_features
from trackmeter.errors import TrackmeterError
from trackmeter.sources.plane import PlaneScene, pose_translating


@pytest.fixture(scope="module")
def plate(estec_rig):  # type: ignore[no-untyped-def]
    scene = PlaneScene(estec_rig, pose_translating(3.5, (0.0, 0.0, 0.0), start_m=(0.1, 0.0)), noise_sigma=0.5)
    return scene, scene.frame(0)


def test_gabor_prefers_a_corner_to_an_edge() -> None:
    """A good feature answers in at least two directions; a straight edge in one only."""
    img = np.full((120, 160), 40, np.uint8)
    img[30:90, 20:70] = 200  # a square: corners at (20,30), (69,30), ...
    img[:, 110:] = 200  # a long vertical edge at u = 110 (no corner in the middle rows)
    score = ft.gabor_score(img, FeatureParams())
    corner = score[25:36, 15:26].max()
    edge = score[55:66, 105:116].max()
    assert corner > 2 * edge
    energy = ft.gabor_directional_energy(img, (4.0, 8.0), 4)
    e = energy[:, 60, 110]
    assert np.sort(e)[-1] > 5 * np.sort(e)[-2]  # the edge answers in one direction


def test_centroid_of_a_bright_disc_on_black_space() -> None:
    img = np.zeros((200, 300), np.uint8)
    cv2.circle(img, (180, 90), 40, 180, -1)
    rng = np.random.default_rng(0)
    img = np.clip(img + (img > 0) * rng.integers(0, 30, img.shape), 0, 255).astype(np.uint8)
    pts = select_features(img, None, None, 1, "centroid", FeatureParams(), ())
    assert len(pts) == 1
    np.testing.assert_allclose(pts[0], (180, 90), atol=0.5)


@pytest.mark.parametrize("method", ["gabor", "shi_tomasi"])
def test_selected_points_are_on_the_target_spread_and_stereo_matchable(plate, estec_rig, method) -> None:
    scene, f = plate
    params = FeatureParams()
    exclude = np.array([[400.0, 250.0]])
    pts = select_features(f.left, f.right, estec_rig, 12, method, params, exclude)
    assert 6 <= len(pts) <= 12
    # On the plate (not black space), and the whole patch too.
    assert np.all(np.isfinite(scene.surface_points(0, pts)))
    for u, v in pts:
        patch = f.left[int(v) - 4 : int(v) + 5, int(u) - 4 : int(u) + 5]
        assert patch.min() > params.black_level
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2) + np.eye(len(pts)) * 1e9
    assert d.min() >= params.min_distance_px - 1e-9
    assert np.linalg.norm(pts - exclude, axis=1).min() >= params.min_distance_px
    # Stereo-matchable: every point has a unique epipolar match (and it is the right one).
    assert ft.stereo_matchable(f.left, f.right, estec_rig, pts, params).all()


def test_nothing_is_selected_on_black_space(estec_rig) -> None:
    black = np.full((512, 726), 5, np.uint8)
    for method in ft.METHODS:
        assert len(select_features(black, black, estec_rig, 5, method, FeatureParams(), ())) == 0


def test_unknown_method_is_refused() -> None:
    with pytest.raises(TrackmeterError, match="unknown feature selection method"):
        select_features(np.zeros((10, 10), np.uint8), None, None, 3, "sift", FeatureParams(), ())
