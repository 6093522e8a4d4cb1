"""The operator benchmark's run (benchmarks/operator.py) on a short stretch of estec: the
clicks it makes are the engine's targets and its figures are what it counted."""

from __future__ import annotations

import math

import benchmarks.operator as operator


def test_clicked_run_counts_the_clicked_targets_frames(monkeypatch) -> None:
    monkeypatch.setattr(operator, "WARMUP_S", 0.2)
    monkeypatch.setattr(operator, "TRACK_S", 0.4)
    monkeypatch.setattr(operator, "CLICKS", 3)
    made: list[str] = []
    from trackmeter.pipeline.engine import Engine

    handle = Engine.handle

    def spy(self, command, frame):  # type: ignore[no-untyped-def]
        reply = handle(self, command, frame)
        if type(command).__name__ == "SelectPoint" and reply.ok:
            made.append(reply.target_id)
        return reply

    monkeypatch.setattr(Engine, "handle", spy)
    out = operator.clicked_run("estec", 0, "none")
    assert len(made) == 3 and all(t.startswith("p") for t in made)
    assert 0.0 <= out["tracked_fraction"] <= 1.0
    # 10 frames x 3 targets: the fraction is a count over 30
    assert math.isclose(out["tracked_fraction"] * 30, round(out["tracked_fraction"] * 30), abs_tol=1e-9)
    assert out["false_frames"] <= out["tracked_fraction"] * 30
    assert math.isnan(out["error_median_px"]) or 0.0 <= out["error_median_px"] <= 2.0 or out["false_frames"] > 0


def test_the_default_refits_the_clicked_targets_anchors_and_none_does_not(monkeypatch) -> None:
    """End to end through the engine on estec: with the configuration's default
    (anchor_scale_fallback: operator) the clicked targets' refused anchor fits are refitted with
    the scale held; with "none" never."""
    import trackmeter.core.patch_tracking as pt

    monkeypatch.setattr(operator, "WARMUP_S", 0.2)
    monkeypatch.setattr(operator, "TRACK_S", 0.8)
    calls: list[int] = []
    real = pt._scale_held_refit

    def spy(*args, **kwargs):  # type: ignore[no-untyped-def]
        calls.append(int(args[4].sum()))
        return real(*args, **kwargs)

    monkeypatch.setattr(pt, "_scale_held_refit", spy)
    operator.clicked_run("estec", 0, "none")
    assert calls == []
    operator.clicked_run("estec", 0, None)
    assert sum(calls) > 0
