"""Automatic selection's Gabor score made ahead (FeatureResponse): the same points, targets and
snapshots as filtering in the step, bit for bit; the pipeline makes it on its helper thread."""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest

from trackmeter.core.features import FeatureParams, feature_response, select_features
from trackmeter.core.matching import MeasureParams
from trackmeter.core.tracking import Tracker, TrackerParams
from trackmeter.pipeline.pipeline import Pipeline
from trackmeter.pipeline.snapshot import PoseEstimate
from trackmeter.sources.base import Source, StereoFrame

N_FRAMES = 16


@pytest.fixture(scope="module")
def estec_frames(estec_sim_frames):  # type: ignore[no-untyped-def]
    rig, frames = estec_sim_frames
    return rig, frames[:N_FRAMES]


@pytest.mark.slow
def test_select_features_with_the_response_made_ahead_is_bit_for_bit_the_same(estec_frames) -> None:  # type: ignore[no-untyped-def]
    rig, frames = estec_frames
    f = frames[5]
    params = FeatureParams()
    plain = select_features(f.left, f.right, rig, 12, "gabor", params)
    assert len(plain) == 12
    # keep-out circles around some points shrink the selectable region inside the response's
    exclude = plain[::3] + 3.0
    resp = feature_response(f.left, params)
    assert resp is not None
    for ex in (np.zeros((0, 2)), exclude):
        want = select_features(f.left, f.right, rig, 12, "gabor", params, ex)
        got = select_features(f.left, f.right, rig, 12, "gabor", params, ex, response=resp)
        assert np.array_equal(want, got)
    # a response made with other tunables (or of a smaller region) is not used: filtered again
    other = feature_response(f.left, dataclasses.replace(params, gabor_wavelengths_px=(4.0,)))
    assert other is not None and not other.covers(resp.x0, resp.y0, resp.x0 + resp.score.shape[1], resp.y0 + resp.score.shape[0], params)
    assert np.array_equal(select_features(f.left, f.right, rig, 12, "gabor", params, response=other), plain)
    small = dataclasses.replace(resp, x0=resp.x0 + 40)
    assert np.array_equal(select_features(f.left, f.right, rig, 12, "gabor", params, response=small), plain)


@pytest.mark.slow
def test_tracker_given_the_response_tracks_the_same_targets(estec_frames) -> None:  # type: ignore[no-untyped-def]
    rig, frames = estec_frames
    trackers = [Tracker(rig, TrackerParams(auto=True), FeatureParams(), MeasureParams()) for _ in range(2)]
    used = []
    for f in frames:
        due = trackers[1].top_up_due(f.index)

        def ahead(f: StereoFrame = f):  # type: ignore[no-untyped-def]
            used.append(f.index)
            return trackers[1].feature_response(f)

        n_used = len(used)
        a = trackers[0].step(f)
        b = trackers[1].step(f, feature_response=ahead)
        assert len(used) == n_used or due  # a top-up the tracker did not announce filters itself
        assert [(t.id, t.status) for t in a] == [(t.id, t.status) for t in b]
        for s, t in zip(a, b):
            assert np.array_equal(s.uv, t.uv) and np.array_equal(s.point_cam, t.point_cam, equal_nan=True)
    assert len(used) >= 2 and trackers[1].stats["added"] >= 10


class _Frames(Source):
    def __init__(self, n: int) -> None:
        self.i, self.n = 0, n

    def read(self) -> StereoFrame | None:
        if self.i >= self.n:
            return None
        img = np.full((4, 6), self.i, np.uint8)
        self.i += 1
        return StereoFrame(self.i - 1, (self.i - 1) / 25.0, img, img.copy())

    def close(self) -> None:
        pass


class _AheadEngine:
    """Engine double: a top-up is due every third frame; records where the response was made."""

    def __init__(self) -> None:
        self.made: dict[int, int] = {}  # frame index -> thread that made its response
        self.got: dict[int, int] = {}  # frame index -> the response process() received
        self.process_thread: set[int] = set()

    def top_up_due(self, index: int) -> bool:
        return index % 3 == 0

    def feature_response(self, frame):  # type: ignore[no-untyped-def]
        self.made[frame.index] = threading.get_ident()
        return frame.index * 10

    def handle(self, command, frame):  # type: ignore[no-untyped-def]
        raise AssertionError("no commands in this test")

    def process(self, frame, feature_response=None):  # type: ignore[no-untyped-def]
        self.process_thread.add(threading.get_ident())
        if feature_response is not None:
            self.got[frame.index] = feature_response()
        return [], PoseEstimate.invalid("test double"), None


def test_pipeline_makes_the_response_on_its_helper_thread_for_due_frames_only() -> None:
    engine = _AheadEngine()
    with Pipeline(_Frames(10), engine, drop_frames=False) as pipe:  # type: ignore[arg-type]
        pipe.run_until_end(timeout_s=20)
    assert engine.got == {i: 10 * i for i in (0, 3, 6, 9)}
    assert set(engine.made) == {0, 3, 6, 9}
    assert not set(engine.made.values()) & engine.process_thread  # made on another thread
    assert not any(t.name.startswith("trackmeter-features") for t in threading.enumerate())  # joined
