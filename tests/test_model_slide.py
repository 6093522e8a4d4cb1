"""Case (b) model growth with targets that wander on the surface (pose.slide_sigma_m_per_sqrt_s).

A tracked pixel is not a fixed body point: on the estec chain the surface point under an
automatic target moves by a median 0.4 mm in 1 s and 1 mm in 10 s (the renderer's surface truth
under each target, H5's analysis). The model treats a grown point's body coordinates as a random
walk: before each refinement its covariance grows by ``slide_sigma² dt`` per axis.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from tests.test_engine import DT, growing_engine, run
from trackmeter.data.config import load_config

SLIDE_M_PER_S = np.array([0.0003, -0.00015, 0.0001])  # a steady slide of one grown target (0.35 mm/s)


def _slide_lag(estec_rig, slide_sigma: float) -> tuple[float, float]:  # type: ignore[no-untyped-def]
    """Run 100 frames with target a1 sliding at SLIDE_M_PER_S (body frame), noise-free; returns
    (distance of a1's model point from where the target is now, the distance slid), m."""
    config = load_config()
    config = replace(config, pose=replace(config.pose, slide_sigma_m_per_sqrt_s=slide_sigma))
    engine, tracker, _, _ = growing_engine(estec_rig, config)
    start = tracker.body["a1"].copy()
    for k in range(10, 110):
        tracker.body["a1"] = start + SLIDE_M_PER_S * (k - 9) * DT
        (_, pose, _), = run(engine, [k])
        assert pose.valid and "a1" not in pose.outlier_ids  # a slow slide, within the gate
    lag = float(np.linalg.norm(engine._model["a1"].b - tracker.body["a1"]))
    return lag, float(np.linalg.norm(tracker.body["a1"] - start))


def test_without_slide_noise_a_sliding_point_is_averaged_over_its_whole_life(estec_rig) -> None:
    """The information mean of a ramp's samples lies well behind the target (equal weights: half-way;
    with the stereo covariance turning with the body the matrix weights even move it off the ramp,
    here by more than the travel): the pose fit is pulled by the gap."""
    lag, travel = _slide_lag(estec_rig, 0.0)
    assert lag > 0.3 * travel


def test_with_slide_noise_a_sliding_point_is_followed(estec_rig) -> None:
    """With the random walk (0.5 mm/sqrt(s), about the slide measured on estec) the model point
    follows the target with a Kalman filter's bounded lag behind a ramp (here 0.4 mm after 1.4 mm
    of travel, against 2.4 mm without)."""
    lag0, travel = _slide_lag(estec_rig, 0.0)
    lag, _ = _slide_lag(estec_rig, 0.0005)
    assert lag < 0.35 * travel
    assert lag < 0.25 * lag0


def test_model_covariance_grows_with_time_since_last_refinement(estec_rig) -> None:
    """The fit weighs a grown point by its covariance plus the slide since its last refinement
    (``sigma² dt`` per axis); a-priori points never slide."""
    sigma = 0.0004
    config = load_config()
    config = replace(config, pose=replace(config.pose, slide_sigma_m_per_sqrt_s=sigma))
    engine, _, _, _ = growing_engine(estec_rig, config)
    m = engine._model["a1"]
    for later in (0.0, 0.5, 3.0):
        np.testing.assert_allclose(engine._model_cov(m, m.t_s + later), m.cov + sigma**2 * later * np.eye(3),
                                   rtol=0, atol=1e-18)
    fixed = engine._model["m0"]
    np.testing.assert_array_equal(engine._model_cov(fixed, fixed.t_s + 10.0), fixed.cov)


@pytest.mark.parametrize("slide_sigma", [0.0, 0.0005])
def test_noise_free_grown_points_stay_exact(estec_rig, slide_sigma: float) -> None:
    """Targets that do not slide: refinement with or without the random walk keeps exact points exact."""
    config = load_config()
    config = replace(config, pose=replace(config.pose, slide_sigma_m_per_sqrt_s=slide_sigma))
    engine, _, pts, ids = growing_engine(estec_rig, config)
    run(engine, range(10, 60))
    for i, tid in enumerate(ids[10:], start=10):
        np.testing.assert_allclose(engine._model[tid].b, pts[i], atol=1e-9)
