"""Operator targets benchmark: how long targets an operator clicks stay tracked.

The console's way of working (DESIGN.md section 5): automatic selection runs, and the operator
clicks points of the satellite on the left image. Here, on the simulator's ``estec`` and
``harsh_light`` scenarios, pose case (a), 16 automatic targets for ``WARMUP_S`` seconds, then
``CLICKS`` clicks on pixels drawn at random from the satellite's lit pixels of that frame (one
draw per seed; a click refused where it lands is moved to a trackable corner within
``tracker.click_snap_px`` as the console does), tracked ``TRACK_S`` seconds more.

Figures, medians over the seeds ``SEEDS``:

- ``operator_tracked_fraction_<scenario>``: the share of the clicked targets' frames in which
  they were tracking (a lost target recovered counts again from its recovery), with the
  configuration the benchmark runs (:func:`benchmarks.bench_config`);
  ``..._none``: the same run with ``tracker.anchor_scale_fallback: none``;
  ``operator_tracked_ratio_<scenario>``: the median over the seeds of the two's ratio.
- ``operator_false_frames_<scenario>`` (and ``..._none``): the clicked targets' frames, from
  the click to their first loss (a recovered target may be on another point), marked tracking
  more than 2 px from the true image of the surface point under the pixel they were made at
  (``Simulator.surface_points``); summed over the seeds.
- ``operator_error_median_px_<scenario>`` (and ``..._none``): the median distance of those
  frames from that true image, px.
- ``operator_pose_lateral_max_mm_<scenario>`` / ``..._depth_...`` (and ``..._none``; per seed
  ``..._seed<i>``): the largest position error of the case-(a) pose over the 2 s, lateral (x or
  y) and along the viewing axis, after the engine's online body alignment: the clicked targets
  are among the pose's points, so what their refitted frames do to it shows here.
"""

from __future__ import annotations

import dataclasses
import math
import statistics
import sys
from collections.abc import Iterable

import numpy as np

from benchmarks import bench_config
from benchmarks.tracker import off_target

SCENARIOS = ("estec", "harsh_light")
SEEDS = (0, 1, 2, 3, 4)
CLICKS = 8
WARMUP_S = 1.0
TRACK_S = 2.0
#: Pixels at least this bright are the satellite's (the simulator's sky is black).
LIT_GREY = 20


def log(msg: str) -> None:
    print(f"[operator] {msg}", file=sys.stderr, flush=True)


def clicked_run(scenario: str, seed: int, fallback: str | None) -> dict[str, float]:
    """One run: the clicked targets' tracked frames, false frames and error (see module doc);
    ``fallback`` overrides ``tracker.anchor_scale_fallback`` (None: the configuration's)."""
    from trackmeter.pipeline.engine import Engine
    from trackmeter.pipeline.snapshot import SelectPoint, SetAuto
    from trackmeter.sources.sim.simulator import Simulator

    config = bench_config()
    if fallback is not None:
        config = dataclasses.replace(config, tracker=dataclasses.replace(config.tracker, anchor_scale_fallback=fallback))
    sim = Simulator(scenario)
    engine = Engine(config, sim.rig, model=None, case="a", rate_hz=sim.rate_hz)
    frame = sim.frame(0)
    engine.process(frame)
    engine.handle(SetAuto(True, 16, "gabor"), frame)
    warmup = round(WARMUP_S * sim.rate_hz)
    for k in range(1, warmup + 1):
        frame = sim.frame(k)
        engine.process(frame)
    rng = np.random.default_rng(seed)
    rows, cols = np.nonzero(np.asarray(frame.left) >= LIT_GREY)
    body: dict[str, np.ndarray] = {}
    for _ in range(50 * CLICKS):
        if len(body) == CLICKS:
            break
        i = int(rng.integers(len(cols)))
        reply = engine.handle(SelectPoint(float(cols[i]), float(rows[i])), frame)
        if reply.ok and reply.target_id is not None:
            uv = next(t.uv for t in engine.tracker.targets if t.id == reply.target_id)
            body[reply.target_id] = sim.surface_points(frame.index, np.asarray(uv, float)[None])[0]
    steps = round(TRACK_S * sim.rate_hz)
    tracked = false = 0
    errors: list[float] = []
    pose_lateral_m: list[float] = []  # empty: no pose error to tell, NaN, not 0
    pose_depth_m: list[float] = []
    lost_once: set[str] = set()
    for k in range(warmup + 1, warmup + 1 + steps):
        frame = sim.frame(k)
        targets, _, pose_errors = engine.process(frame)
        if pose_errors is not None:
            p = np.abs(np.asarray(pose_errors["position_m"], float))
            pose_lateral_m.append(float(max(p[0], p[1])))
            pose_depth_m.append(float(p[2]))
        assert frame.truth is not None  # a simulator frame's truth is always set
        T = frame.truth.T_cam_body
        for t in targets:
            if t.id not in body:
                continue
            if t.status == "lost":
                lost_once.add(t.id)
                continue
            tracked += 1
            if t.id in lost_once or not np.all(np.isfinite(body[t.id])):
                continue
            false += int(off_target(sim.rig, T, body[t.id], t.uv))
            true_uv, _ = sim.rig.project((T[:3, :3] @ body[t.id] + T[:3, 3])[None])
            errors.append(float(np.linalg.norm(true_uv[0] - t.uv)))
    return {
        "tracked_fraction": tracked / max(steps * len(body), 1),
        "false_frames": float(false),
        "error_median_px": statistics.median(errors) if errors else float("nan"),
        "pose_lateral_max_mm": 1e3 * max(pose_lateral_m) if pose_lateral_m else float("nan"),
        "pose_depth_max_mm": 1e3 * max(pose_depth_m) if pose_depth_m else float("nan"),
    }


def _median_of_finite(values: Iterable[float]) -> float:
    """The median of the finite ``values`` (statistics.median with a NaN among them depends on
    the order); NaN when there is none."""
    finite = [v for v in values if math.isfinite(v)]
    return statistics.median(finite) if finite else float("nan")


def run() -> dict[str, float]:
    out: dict[str, float] = {}
    for name in SCENARIOS:
        per: dict[str, list[dict[str, float]]] = {"": [], "_none": []}
        for seed in SEEDS:
            for suffix, fallback in (("", None), ("_none", "none")):
                log(f"{name}, seed {seed}{', fallback none' if fallback else ''}")
                per[suffix].append(clicked_run(name, seed, fallback))
        for suffix, runs in per.items():
            out[f"operator_tracked_fraction_{name}{suffix}"] = statistics.median(r["tracked_fraction"] for r in runs)
            out[f"operator_false_frames_{name}{suffix}"] = sum(r["false_frames"] for r in runs)
            out[f"operator_error_median_px_{name}{suffix}"] = _median_of_finite(r["error_median_px"] for r in runs)
            out[f"operator_pose_lateral_max_mm_{name}{suffix}"] = _median_of_finite(r["pose_lateral_max_mm"] for r in runs)
            out[f"operator_pose_depth_max_mm_{name}{suffix}"] = _median_of_finite(r["pose_depth_max_mm"] for r in runs)
            for i, r in enumerate(runs):
                out[f"operator_pose_lateral_max_mm_{name}{suffix}_seed{i}"] = r["pose_lateral_max_mm"]
        out[f"operator_tracked_ratio_{name}"] = statistics.median(
            a["tracked_fraction"] / b["tracked_fraction"] if b["tracked_fraction"] > 0 else float("nan")
            for a, b in zip(per[""], per["_none"])
        )
    return out
