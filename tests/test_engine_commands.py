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
