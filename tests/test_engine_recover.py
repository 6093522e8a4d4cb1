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



class Restoring(Tracker):
    """The real tracker, recording the stored targets it re-found: (frame index, id, left pixel)."""

    def __init__(self, *a, **k) -> None:  # type: ignore[no-untyped-def]
        super().__init__(*a, **k)
        self.restored: list[tuple[int, str, np.ndarray]] = []
        self.last_seen: dict[str, tuple[int, np.ndarray]] = {}  # id -> (frame index, left pixel) last measured
        self.stored_at: dict[str, tuple[int, np.ndarray]] = {}  # the same when a re-found target was dropped

    def step(self, frame, reject_ids=()):  # type: ignore[no-untyped-def]
        out = super().step(frame, reject_ids)
        for t in out:
            if t.measured:
                self.last_seen[t.id] = (frame.index, t.uv.copy())
        return out

    def restore_many(self, requests, frame):  # type: ignore[no-untyped-def]
        out = super().restore_many(requests, frame)
        for r in out:
            if isinstance(r, TargetState):
                self.restored.append((frame.index, r.id, r.uv.copy()))
                self.stored_at[f"{r.id}@{frame.index}"] = self.last_seen[r.id]
        return out


class Judging(Engine):
    """The real engine, recording which re-locks it kept: (frame count, id) -> kept."""

    kept: dict[tuple[int, str], bool]

    def _judge_recovery(self, pid, is_target, x_cam, result, R, cov):  # type: ignore[no-untyped-def]
        kept = super()._judge_recovery(pid, is_target, x_cam, result, R, cov)
        self.kept = getattr(self, "kept", {})
        self.kept[(self.stats.frames, pid)] = kept
        return kept


@pytest.mark.slow
def test_a_grown_point_is_re_locked_on_the_surface_point_it_was_grown_from(estec_frames) -> None:  # type: ignore[no-untyped-def]
    """``pose.relock_stored``: a grown point whose target was dropped is re-found on its own
    texture — the body surface point its target sat on when last measured (the simulator's
    truth), not wherever the model, drifted since, projects. (The tracker's re-find may land
    on a look-alike: the engine's gate against the model through the pose then refuses it.)"""
    from trackmeter.sources.sim.scenario import load_scenario
    from trackmeter.sources.sim.simulator import Simulator

    rig, frames = estec_frames
    config = load_config(overrides={"pose": {"relock_stored": True}})
    tracker = Restoring(rig, config.tracker, config.features, config.measure)
    engine = Judging(config, rig, case="a", tracker=tracker, rate_hz=25)
    for k, frame in enumerate(frames):
        engine.process(frame)
        if k == 0:
            engine.handle(SetAuto(True, 16, "gabor"), frame)
    kept = [(index, tid, uv) for index, tid, uv in tracker.restored if engine.kept[(index + 1, tid)]]
    assert engine.stats.stored_relocks == len(kept) >= 3
    sim = Simulator(load_scenario("estec"))
    off = []
    for index, tid, uv in kept:
        seen_index, seen_uv = tracker.stored_at[f"{tid}@{index}"]
        assert index - seen_index > 1  # dropped in between
        off.append(np.linalg.norm(sim.surface_points(index, uv[None])[0] - sim.surface_points(seen_index, seen_uv[None])[0]))
    assert np.all(np.isfinite(off)) and max(off) < 0.002, off  # m (a re-made target: anywhere)


def test_an_unnamed_click_refused_where_it_is_goes_to_a_trackable_corner_nearby(estec_sim_frames) -> None:  # type: ignore[no-untyped-def]
    # On estec's first frame most clicks on the mock-up are refused (200 on its lit part: 37
    # accepted; an outside console probe: 1 of 6 "obvious" clicks). A trackable corner a few
    # pixels away is where the operator meant; a click named after a model point stays put.
    from dataclasses import replace

    from trackmeter.pipeline.snapshot import SelectPoint

    rig, frames = estec_sim_frames
    config = load_config()
    plain = Engine(replace(config, tracker=replace(config.tracker, click_snap_px=0.0)), rig, None, "a", rate_hz=25)
    snapping = Engine(config, rig, None, "a", rate_hz=25)
    frame = frames[0]
    for engine in (plain, snapping):
        engine.process(frame)
    lit = np.argwhere(frame.left[::7, ::7] > 60) * 7  # (v, u) on a coarse grid, fixed
    tried = 0
    for v, u in lit:
        refused = plain.handle(SelectPoint(float(u), float(v)), frame)
        if refused.ok:
            plain.tracker.remove_target(refused.target_id)
            continue
        tried += 1
        reply = snapping.handle(SelectPoint(float(u), float(v)), frame)
        if reply.ok:
            break
        assert reply.message == refused.message  # nothing found nearby: the refusal as it was
    else:
        pytest.fail(f"no refused click of {tried} was put on a corner nearby")
    assert "px to a trackable corner (where asked: " in reply.message
    assert refused.message.split(": ", 1)[1] in reply.message
    target = next(t for t in snapping.targets if t.id == reply.target_id)
    assert 0 < np.hypot(target.uv[0] - u, target.uv[1] - v) == pytest.approx(reply.moved_px, abs=1e-6)
    assert reply.moved_px <= config.tracker.click_snap_px
    named = snapping.handle(SelectPoint(float(u), float(v), "p_named"), frame)
    assert not named.ok and named.message == refused.message


def test_a_second_click_on_a_target_is_refused_not_a_duplicate(estec_sim_frames) -> None:  # type: ignore[no-untyped-def]
    # An outside console probe clicked (300, 260) twice on a paused frame: two operator targets
    # on one pixel, one patch tracked twice, adding nothing to the pose.
    from trackmeter.pipeline.snapshot import SelectPoint, SetAuto

    rig, frames = estec_sim_frames
    engine = Engine(load_config(), rig, None, "a", rate_hz=25)
    frame = frames[0]
    engine.process(frame)
    lit = np.argwhere(frame.left[::7, ::7] > 60) * 7
    for v, u in lit:
        first = engine.handle(SelectPoint(float(u), float(v)), frame)
        if first.ok:
            break
    else:
        pytest.fail("no click accepted")
    target = next(t for t in engine.targets if t.id == first.target_id)
    again = engine.handle(SelectPoint(float(target.uv[0]) + 1.0, float(target.uv[1])), frame)
    assert not again.ok and f"target {first.target_id} is already there" in again.message, again.message
    assert [t.id for t in engine.targets] == [first.target_id]
    # On an automatic target, a click is the operator taking that point: not refused.
    engine.handle(SetAuto(True, 4, None), frame)
    engine.process(frames[1])
    auto = next(t for t in engine.targets if t.origin == "auto" and t.status == "tracking")
    taken = engine.handle(SelectPoint(float(auto.uv[0]), float(auto.uv[1])), frames[1])
    assert "already there" not in taken.message, taken.message
    # Named after a model point, the click binds that name (a model point may sit on a target).
    named = engine.handle(SelectPoint(float(target.uv[0]), float(target.uv[1]), "p_named"), frame)
    assert "already there" not in named.message


def test_a_click_at_the_target_limit_takes_the_place_of_a_lost_or_automatic_target(estec_sim_frames) -> None:  # type: ignore[no-untyped-def]
    # Lost targets stay (the operator's for ever), and automatic ones fill the rest: once 32
    # were held every click was refused, "target limit reached", while 14 were tracking (an
    # outside console probe). The click is the operator's: it takes a place, a lost target's
    # first, else the youngest automatic one's, never another click's.
    from dataclasses import replace

    from trackmeter.pipeline.engine import click_room
    from trackmeter.pipeline.snapshot import SelectPoint

    rig, frames = estec_sim_frames
    config = load_config()
    engine = Engine(replace(config, tracker=replace(config.tracker, max_targets=4)), rig, None, "a", rate_hz=25)
    frame = frames[0]
    engine.handle(SetAuto(True, 4), frame)
    engine.process(frame)
    autos = {t.id: t.age_frames for t in engine.targets}
    assert len(autos) == 4
    lit = np.argwhere(frame.left[::7, ::7] > 60) * 7
    clicks = []
    for v, u in lit:
        reply = engine.handle(SelectPoint(float(u), float(v)), frame)
        if reply.ok:
            clicks.append(reply.target_id)
            assert "(in place of automatic target a" in reply.message, reply.message
        else:
            assert "target limit" not in reply.message, reply.message
        if len(clicks) == 4:
            break
    assert len(clicks) == 4 and {t.id for t in engine.targets} == set(clicks)
    reply = engine.handle(SelectPoint(float(lit[-1][1]), float(lit[-1][0])), frame)
    assert not reply.ok and "target limit reached (4 targets, all the operator's or model points" in reply.message

    def state(tid, origin, status, age):  # type: ignore[no-untyped-def]
        nan2 = np.full(2, np.nan)
        return TargetState(tid, origin, status, nan2, nan2, np.full(3, np.nan), np.full((3, 3), np.nan), 0.0,
                           nan2, (0, 0, 0, 0), None, age)

    held = [state("op", "operator", "lost", 50), state("a1", "auto", "tracking", 9), state("a2", "auto", "tracking", 3),
            state("a3", "auto", "lost", 20), state("m", "model", "lost", 90)]
    assert [click_room(held[:k]) for k in (1, 3, 4)] == ["op", "op", "a3"]
    assert click_room(held[1:3]) == "a2"  # none lost: the youngest automatic one
    assert click_room(held) == "a3"  # a lost automatic target before a lost click or model point
    assert click_room([state("op", "operator", "tracking", 5)]) is None
