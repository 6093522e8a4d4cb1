"""The operator's commands to the engine on real simulated frames (estec, case (b)): what a
reply says is what the next frames do."""

from __future__ import annotations

import numpy as np
import pytest

from trackmeter.data.config import load_config
from trackmeter.pipeline.engine import Engine, SelectModelPoints
from trackmeter.pipeline.snapshot import RemoveTarget, SelectPoint


@pytest.fixture(scope="module")
def estec_model():  # type: ignore[no-untyped-def]
    from trackmeter.sources import open_source

    source = open_source("sim", render_ahead=False)
    try:
        return source.model
    finally:
        source.close()


def _case_b(estec_sim_frames, estec_model):  # type: ignore[no-untyped-def]
    rig, frames = estec_sim_frames
    engine = Engine(load_config(), rig, estec_model, "b", rate_hz=25.0)
    engine.process(frames[0])
    assert engine.handle(SelectModelPoints(), frames[0]).ok
    return rig, frames, engine


def _true_pixel(rig, model, frame, point_id: str) -> tuple[float, float]:  # type: ignore[no-untyped-def]
    T = np.asarray(frame.truth.T_cam_body)
    x = model.points_body[list(model.ids).index(point_id)] @ T[:3, :3].T + T[:3, 3]
    u, v = rig.project(x[None])[0][0]
    return float(u), float(v)


def test_a_model_point_the_operator_removed_is_not_targeted_again(estec_sim_frames, estec_model) -> None:
    # "removed bus_mxmymz", and eleven frames later it was back: the engine kept the a-priori
    # point in its model (so as not to move the frame) and its recovery made a target of it
    # again; at the target limit the slot the operator freed was taken back (an outside review).
    _, frames, engine = _case_b(estec_sim_frames, estec_model)
    for k in range(1, 6):
        targets, pose, _ = engine.process(frames[k])
    assert pose.valid
    victim = sorted(t.id for t in targets if t.status != "lost" and t.id in estec_model.ids)[0]
    assert engine.handle(RemoveTarget(victim), frames[5]).ok
    for k in range(6, 30):
        targets, pose, _ = engine.process(frames[k])
        assert victim not in {t.id for t in targets}, k
    assert pose.valid  # the others carry the pose


def test_a_named_click_takes_the_place_of_its_lost_target(estec_sim_frames, estec_model) -> None:
    # The console offers every model id for the next click, lost ones too (not drawn): the click
    # named after a lost target was refused ("a target named ... exists"), and the same click
    # unnamed made a plain target, not the model point (an outside review).
    rig, frames, engine = _case_b(estec_sim_frames, estec_model)
    for k in range(1, 40):
        targets, _, _ = engine.process(frames[k])
        lost = [t for t in targets if t.status == "lost" and t.id in estec_model.ids]
        if lost:
            break
    assert lost, "no model point's target was lost in the first 40 frames: the case this test needs"
    name = lost[0].id
    reply = engine.handle(SelectPoint(*_true_pixel(rig, estec_model, frames[k], name), name), frames[k])
    assert reply.ok and reply.target_id == name, reply.message
    mine = [t for t in engine.targets if t.id == name]
    assert len(mine) == 1 and mine[0].status != "lost"


def test_generated_target_ids_never_take_a_model_point_s_name(estec_sim_frames) -> None:
    # A model file may name its points as the engine names new targets (p1, a1, ...): a plain
    # click then became "p1" and was bound to model point p1 by name, wherever it was (an
    # outside review). Generated ids skip the model's.
    from trackmeter.data.model import Model
    from trackmeter.sources import open_source

    source = open_source("sim", render_ahead=False)
    try:
        given = source.model
    finally:
        source.close()
    n = len(given.ids)
    names = tuple(f"p{k + 1}" for k in range(n // 2)) + tuple(f"a{k + 1}" for k in range(n - n // 2))
    model = Model(names, given.points_body)
    rig, frames = estec_sim_frames
    engine = Engine(load_config(), rig, model, "b", rate_hz=25.0)
    engine.process(frames[0])
    assert engine.handle(SelectModelPoints(), frames[0]).ok
    bound = {t.id for t in engine.targets}
    assert bound and bound <= set(names)
    for k in range(1, 4):
        engine.process(frames[k])
    # a plain click on a good feature away from the model points, then automatic targets
    from trackmeter.core.features import FeatureParams, select_features

    taken = [t.uv for t in engine.targets]
    u, v = select_features(frames[3].left, frames[3].right, rig, 1, "gabor", FeatureParams(), taken)[0]
    reply = engine.handle(SelectPoint(float(u), float(v)), frames[3])
    assert reply.ok, reply.message
    assert reply.target_id not in names, reply.message
    engine.tracker.set_auto(True, 16)
    for k in range(4, 12):
        targets, _, _ = engine.process(frames[k])
    auto = {t.id for t in targets if t.origin == "auto"}
    assert auto, "no automatic target started: the case this test needs"
    # (they were a2, a4, ...: bound to model points they are not on, each lost at once)
    assert not auto & set(names), sorted(auto & set(names))
    # every target named after a model point is on it
    for t in targets:
        if t.id in names and t.status != "lost":
            off = np.hypot(*(np.asarray(t.uv) - _true_pixel(rig, model, frames[k], t.id)))
            assert off < 3.0, (t.id, t.origin, off)


def test_a_model_loaded_later_does_not_take_over_targets_the_engine_named_as_its_points(
        estec_sim_frames, estec_model, tmp_path) -> None:  # type: ignore[no-untyped-def]
    # Loaded while automatic targets a1, a2, ... were tracked, a model naming its points a1, a2,
    # ... would have them as its points by name, wherever they are.
    from trackmeter.data.model import save_model
    from trackmeter.pipeline.snapshot import LoadModel

    rig, frames = estec_sim_frames
    engine = Engine(load_config(), rig, None, "a", rate_hz=25.0)
    engine.tracker.set_auto(True, 16)
    for k in range(4):
        targets, _, _ = engine.process(frames[k])
    auto = {t.id for t in targets if t.origin == "auto"}
    names = tuple(f"a{k + 1}" for k in range(len(estec_model.ids)))
    assert auto & set(names), "no automatic target named as the model's points: the case this test needs"
    path = save_model(tmp_path / "model.yaml", list(zip(names, estec_model.points_body)))
    reply = engine.handle(LoadModel(str(path)), frames[3])
    assert reply.ok, reply.message
    assert not {t.id for t in engine.targets} & set(names), reply.message
    assert "removed" in reply.message
