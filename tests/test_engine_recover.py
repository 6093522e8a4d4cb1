"""The engine's recovery (paper 2.D) batches its template re-locks (``Tracker.relock_many``):
the same targets and poses, frame by frame, as re-locking one target after another."""

from __future__ import annotations

import numpy as np
import pytest

from trackmeter.core.targets import TargetState
from trackmeter.core.tracking import Tracker
from trackmeter.data.config import load_config
from trackmeter.pipeline.engine import Engine
from trackmeter.pipeline.snapshot import SetAuto

N_FRAMES = 60  # on estec, model points are lost and re-locked in batches of 2-4 (3 batches by frame 60)


class OneByOne(Tracker):
    """A tracker that re-locks each target of a batch on its own, one after another."""

    def relock_many(self, requests, frame):  # type: ignore[no-untyped-def]
        return [super(OneByOne, self).relock_many([r], frame)[0] for r in requests]


class Counting(Tracker):
    """The real batched re-lock, counting batches of several targets that re-locked some."""

    batches = 0

    def relock_many(self, requests, frame):  # type: ignore[no-untyped-def]
        out = super().relock_many(requests, frame)
        if len(requests) > 1 and any(isinstance(r, TargetState) for r in out):
            self.batches += 1
        return out


@pytest.fixture(scope="module")
def estec_frames(estec_sim_frames):  # type: ignore[no-untyped-def]
    rig, frames = estec_sim_frames
    return rig, frames[:N_FRAMES]


def run(cls, rig, frames):  # type: ignore[no-untyped-def]
    config = load_config()
    tracker = cls(rig, config.tracker, config.features, config.measure)
    engine = Engine(config, rig, case="a", tracker=tracker, rate_hz=25)
    out = []
    for k, frame in enumerate(frames):
        out.append(engine.process(frame))
        if k == 0:
            engine.handle(SetAuto(True, 16, "gabor"), frame)
    return out, tracker, engine


@pytest.mark.slow
def test_batched_recovery_equals_one_relock_after_another(estec_frames) -> None:  # type: ignore[no-untyped-def]
    rig, frames = estec_frames
    batched, tracker, engine = run(Counting, rig, frames)
    single, _, _ = run(OneByOne, rig, frames)
    assert tracker.batches >= 1, "no batch of several re-locks succeeded: the test shows nothing"
    assert engine.stats.recoveries >= 1
    for (tb, pb, _), (ts, ps, _) in zip(batched, single, strict=True):
        assert [(t.id, t.status) for t in tb] == [(t.id, t.status) for t in ts]
        for a, b in zip(tb, ts):
            np.testing.assert_allclose(a.uv, b.uv, rtol=0, atol=1e-9)
            np.testing.assert_allclose(a.point_cam, b.point_cam, rtol=0, atol=1e-9)
        assert pb.valid == ps.valid and pb.reason == ps.reason
        np.testing.assert_allclose(pb.T_cam_body, ps.T_cam_body, rtol=0, atol=1e-9)

