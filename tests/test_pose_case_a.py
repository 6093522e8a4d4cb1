"""Case (a) model maths: holding the body frame through a model refinement (pose.hold_frame).

Pinned to closed forms: a purely rigid change is undone exactly, a point without information
has no say, and too few points leave the frame alone.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from trackmeter.core.pose import hold_frame


def _points(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-0.4, 0.4, (n, 3))


def test_hold_frame_undoes_a_rigid_update_exactly() -> None:
    b = _points(8)
    R = Rotation.from_rotvec([0.01, -0.02, 0.015]).as_matrix()
    t = np.array([0.002, -0.001, 0.003])
    after = b @ R.T + t
    cov = np.tile(np.eye(3) * 1e-6, (8, 1, 1)) * np.arange(1, 9)[:, None, None]
    R_h, t_h = hold_frame(b, after, cov)
    np.testing.assert_allclose(after @ R_h.T + t_h, b, atol=1e-12)


def test_hold_frame_keeps_the_shape_change_of_an_uninformed_point() -> None:
    b = _points(8, seed=1)
    after = b.copy()
    after[0] += [0.01, 0.0, -0.005]  # only the youngest point moves
    cov = np.tile(np.eye(3) * 1e-6, (8, 1, 1))
    cov[0] *= 1e8  # it knew (almost) nothing before: the frame is held by the others
    R_h, t_h = hold_frame(b, after, cov)
    np.testing.assert_allclose(R_h, np.eye(3), atol=1e-9)
    np.testing.assert_allclose(t_h, 0, atol=1e-10)


def test_hold_frame_with_too_few_points_is_the_identity() -> None:
    b = _points(2)
    R_h, t_h = hold_frame(b, b + 0.01, np.tile(np.eye(3), (2, 1, 1)))
    np.testing.assert_array_equal(R_h, np.eye(3))
    np.testing.assert_array_equal(t_h, np.zeros(3))



def test_engine_with_frame_hold_stays_exact_through_the_loss_of_frame_points(estec_rig) -> None:
    """Noise-free points: with ``pose.frame_hold`` the case (a) pose stays glued to the body
    while the three frame points are lost one after another (the hand-over to the redundant
    points keeps the frame, and holding it adds no motion of its own)."""
    from dataclasses import replace

    from tests.test_engine import DT, frame_at, make_engine, run, true_pose

    engine, tracker, _ = make_engine(estec_rig, with_model=False, noise=False)
    engine.pose_params = replace(engine.pose_params, frame_hold=True)
    age = engine.pose_params.frame_min_age_frames
    run(engine, range(age + 1))
    assert engine.frame_ids == ("m0", "m1", "m2")
    def raw_pose() -> np.ndarray:  # the fitted pose, before the output filter
        R, t, _ = engine._last_fit
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        return T

    run(engine, range(age + 1, age + 40))
    X = np.linalg.inv(true_pose((age + 39) * DT)) @ raw_pose()  # the frame in the body
    lost: set[str] = set()
    for n, k in enumerate(range(age + 40, age + 100)):
        if n % 15 == 0 and len(lost) < 3:
            lost.add(f"m{len(lost)}")
            tracker.force_lost = set(lost)
        _, pose, _ = engine.process(frame_at(k))
        assert pose.valid
        np.testing.assert_allclose(np.linalg.inv(true_pose(k * DT)) @ raw_pose(), X, atol=1e-9)
