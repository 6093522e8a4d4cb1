"""Where case (b)'s whole-chain error comes from: the tracker's measurements replayed with parts made perfect.

``python -m benchmarks.error_budget`` (a diagnostic, not in ``python -m benchmarks``' list: it
runs the slow chain). The ``estec`` chain of ``benchmarks/accuracy.py`` (case b, 16 automatic
targets plus the model points an operator clicks) is run once for ``TRACKMETER_BUDGET_S``
seconds (default 60; the configuration as :func:`benchmarks.bench_config`, i.e. a YAML named by
``TRACKMETER_BENCH_CONFIG`` over the defaults) and what the tracker handed the engine each frame
is recorded. The engine is
then run again on that record (:class:`Replay`: the recorded targets; re-locks refused, the
record already holds what they gave) with measurements replaced by oracles built from the
renderer's surface truth under each target (:meth:`Simulator.surface_points`):

- ``recorded``: as measured (the replay reproduces the chain: ``replay_max_diff_mm``);
- ``oracle_apriori``: the a-priori (model) points measured at their TRUE body point, with noise
  drawn from their own covariance — corners measured without the bias of their patch;
- ``oracle_auto``: the automatic targets measured at the surface point under their pixel with
  noise from their covariance (no matcher bias; the pixel still wanders on the surface);
- ``oracle_auto_pinned``: ... at the surface point under their FIRST pixel (a target that does
  not wander);
- ``oracle_all``: both oracles, pinned;
- ``*_anchored`` (``recorded``, ``oracle_apriori``, and ``oracle_apriori_bias1mm`` / ``_bias2mm``:
  the a-priori oracle with a constant bias per point, sigma 1 or 2 mm in depth, a third of it
  across): the engine pulls its grown model onto the a-priori points' frame whenever they are
  seen (``pose.anchor_time_s`` 0.5 s, ``anchor_memory_s`` 1 s; :data:`ANCHORED`).

Figures ``<variant>_<span>s_<metric>`` for spans 20, 40, 60 s (``benchmarks.accuracy.figures``,
metrics as ``estec_b_*``), plus measurement statistics of the chain: ``slide_median_mm_1s`` /
``_2s`` / ``_10s`` (how far the surface point under an automatic target has moved after that
long), ``auto_depth_bias_mm`` (median depth error of automatic targets' 3D points),
``apriori_lateral_error_median_mm`` / ``apriori_depth_error_median_mm`` (median absolute error
of the a-priori points' measurements against their true position), ``apriori_depth_bias_worst_mm``
/ ``_sigmas`` (the a-priori point whose measurements are the most biased in depth: the mean of its
depth errors, signed, in mm and in its measurements' mean 1-sigma).
Measured 2026-11-26 (60 s; lateral / depth mm and attitude-other deg maxima over 20 and 60 s):
recorded 2.60 / 6.24 / 0.23 and 8.89 / 9.52 / 0.89; oracle_apriori 1.42 / 4.47 / 0.17 and
7.74 / 8.27 / 0.97; oracle_auto 4.04 / 6.68 / 0.40 and 8.85 / 9.24 / 0.67; oracle_auto_pinned
1.74 / 2.97 / 0.08 and 2.96 / 2.97 / 0.16; oracle_all 0.29 / 1.08 / 0.04 and 1.45 / 1.46 / 0.14
(the only variant that meets every estec_b goal of issue 5). slide_median_mm 0.38 (1 s), 0.61
(2 s), 1.10 (10 s); a-priori points measured a median 1.5 mm (lateral) / 4.1 mm (depth) off
their true position, the worst one -13.2 mm in depth on average (3.1 sigma). Both the targets'
wandering on the surface and the corners' bias must go for the goals; pinned targets alone keep
the depth offset the corners gave the frame when the model bound. The oracles' noise is one draw
(on 2026-11-22, before the blended mip levels, another draw or scenario seed 2 moved
oracle_auto_pinned's 60 s lateral between 1.4 and 3.0 mm).
Anchored (2026-11-27, the same 60 s record; lateral / depth mm over 20 and 60 s): recorded
4.75 / 6.71 and 9.38 / 7.76 (anchoring to the corners as measured makes it worse);
oracle_apriori 0.76 / 1.63 and 5.30 / 6.51 (over 20 s, the corners without their bias and the
grown model pulled onto them meet both position goals, with the targets still sliding);
bias 1 mm 1.08 / 1.79 and 5.05 / 6.58; bias 2 mm 1.63 / 1.92 and 4.81 / 6.69. A measurement
of the corners that would carry case (b) over 20 s must be unbiased to about 1 mm in depth
(0.03 px of disparity at 3.5 m) and a third of that across; the patch measures them 4-15 mm off.
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import replace
from typing import Any

import numpy as np

from benchmarks import bench_config
from benchmarks.accuracy import MAX_POINTS, _series, figures
from trackmeter.core.targets import Refusal, TargetState
from trackmeter.data.config import Config

SPANS_S = (20.0, 40.0, 60.0)
METRICS = ("pos_lateral", "pos_depth", "att_view", "att_other", "vel_lateral", "vel_depth", "omega")


def _log(msg: str) -> None:
    print(f"[error_budget] {msg}", file=sys.stderr, flush=True)


class Replay:
    """A tracker double that hands the engine the recorded targets of each frame."""

    def __init__(self, frames: list[tuple[TargetState, ...]]) -> None:
        self.frames = frames
        self.k = 0
        self.auto = (True, MAX_POINTS, None)
        self.stats: dict[str, float] = {}

    def step(self, frame: Any, reject_ids: Any = ()) -> tuple[TargetState, ...]:
        self.k = frame.index
        return self.frames[frame.index]

    @property
    def targets(self) -> tuple[TargetState, ...]:
        return self.frames[self.k]

    def relock(self, tid: str, uv: Any, frame: Any) -> Refusal:
        return Refusal(tuple(uv), "replay")

    def relock_many(self, requests: Any, frame: Any) -> list[Refusal]:
        return [Refusal(tuple(uv), "replay") for _, uv in requests]

    def add_target(self, frame: Any, uv: Any, target_id: Any = None, origin: str = "operator") -> Refusal:
        return Refusal(tuple(uv), "replay")

    def add_targets(self, frame: Any, requests: Any, *args: Any, **kwargs: Any) -> list[Refusal]:
        return [Refusal((0.0, 0.0), "replay") for _ in requests]

    def remove_target(self, tid: str) -> bool:
        return False

    def set_auto(self, *args: Any, **kwargs: Any) -> None:
        pass


def record(seconds: float, scenario: str = "estec") -> dict[str, Any]:
    """Run the case (b) chain; per frame the targets the tracker gave, the truth and the pose."""
    from trackmeter.pipeline.engine import Engine, SelectModelPoints
    from trackmeter.pipeline.snapshot import SetAuto
    from trackmeter.sources.sim.simulator import Simulator

    sim = Simulator(scenario)
    engine = Engine(bench_config(), sim.rig, sim.model, "b", rate_hz=sim.rate_hz or 25.0)
    step = engine.tracker.step
    seen: list[tuple[TargetState, ...]] = []

    def recording_step(frame: Any, reject_ids: Any = ()) -> tuple[TargetState, ...]:
        out = step(frame, reject_ids=reject_ids)
        seen.append(tuple(out))
        return out

    engine.tracker.step = recording_step  # type: ignore[method-assign]
    n = min(len(sim), int(round(seconds * (sim.rate_hz or 25.0))) + 1)
    truth, poses = [], []
    start = time.perf_counter()
    for k in range(n):
        frame = sim.read()
        if frame is None:
            break
        _, pose, _ = engine.process(frame)
        if k == 0:
            engine.handle(SelectModelPoints(), frame)
            engine.handle(SetAuto(True, MAX_POINTS, None), frame)
        gt = frame.truth
        truth.append((frame.t_s, gt.T_cam_body, gt.velocity_cam_m_s, gt.omega_body_rad_s))
        poses.append(pose.T_cam_body if pose.valid else None)
        if k % 100 == 0:
            _log(f"chain frame {k}/{n} ({time.perf_counter() - start:.0f} s)")
    surface = []
    for k, targets in enumerate(seen):
        ms = [t for t in targets if t.measured and np.all(np.isfinite(t.point_cam))]
        sb = sim.surface_points(k, np.array([t.uv for t in ms])) if ms else np.zeros((0, 3))
        surface.append({t.id: s for t, s in zip(ms, sb)})
    return {"targets": seen, "truth": truth, "poses": poses, "surface": surface, "rig": sim.rig,
            "model": sim.model, "apriori": dict(sim.mockup.salient_points)}


def _sqrtm(C: np.ndarray) -> np.ndarray:
    w, V = np.linalg.eigh(0.5 * (C + C.T))
    return V * np.sqrt(np.clip(w, 0.0, None))


def oracle_frames(rec: dict[str, Any], apriori: bool, auto: bool, pinned: bool, seed: int = 0,
                  apriori_bias_sd_m: float = 0.0) -> list[tuple[TargetState, ...]]:
    """The recorded targets with the chosen measurements replaced by truth + their own noise.

    ``apriori_bias_sd_m`` > 0: each a-priori point's oracle measurement is also off by a constant
    bias of its own, drawn once (camera frame: sigma ``apriori_bias_sd_m`` in depth and a third
    of it in x and y, the proportions of the tracked corners' errors) from a generator of its
    own, so the noise is the same draw as without the bias. How good a measurement of the
    corners must be, short of perfect.
    """
    rng = np.random.default_rng(seed)
    bias_rng = np.random.default_rng(seed + 1)
    bias_scale = apriori_bias_sd_m * np.array([1 / 3, 1 / 3, 1.0])
    bias = {tid: bias_scale * bias_rng.standard_normal(3) for tid in sorted(rec["apriori"])}
    first: dict[str, np.ndarray] = {}
    out = []
    for targets, (_, T, _, _), surf in zip(rec["targets"], rec["truth"], rec["surface"]):
        R, t = T[:3, :3], T[:3, 3]
        new = []
        for tg in targets:
            if tg.measured and np.all(np.isfinite(tg.point_cam)):
                noise = _sqrtm(np.asarray(tg.cov_cam, float)) @ rng.standard_normal(3)
                if tg.id in rec["apriori"]:
                    if apriori:
                        tg = replace(tg, point_cam=R @ rec["apriori"][tg.id] + t + noise + bias[tg.id])
                elif auto and np.all(np.isfinite(surf.get(tg.id, np.nan))):
                    b = first.setdefault(tg.id, surf[tg.id]) if pinned else surf[tg.id]
                    tg = replace(tg, point_cam=R @ b + t + noise)
            new.append(tg)
        out.append(tuple(new))
    return out


def replay(rec: dict[str, Any], frames: list[tuple[TargetState, ...]], config: Config | None = None
           ) -> tuple[Any, Any]:
    """Run a fresh engine over recorded frames; (truth, estimate) as MotionSeries."""
    from trackmeter.pipeline.engine import Engine
    from trackmeter.sources.base import GroundTruth, StereoFrame

    engine = Engine(config if config is not None else bench_config(), rec["rig"], rec["model"], "b",
                    tracker=Replay(frames), rate_hz=25.0)
    blank = np.zeros((1, 1), np.uint8)
    truth_rows, est_rows = [], []
    for k, (t_s, T, v, w) in enumerate(rec["truth"]):
        _, pose, _ = engine.process(StereoFrame(k, t_s, blank, blank, GroundTruth(T, v, w)))
        truth_rows.append((t_s, True, (T, v, w)))
        est_rows.append((t_s, pose.valid, (pose.T_cam_body, pose.velocity_cam_m_s, pose.omega_body_rad_s)))
    return _series(truth_rows), _series(est_rows)


def _span(series: Any, s: float) -> Any:
    m = series.t_s <= s + 1e-6
    return type(series)(series.t_s[m], series.valid[m], series.position_m[m], series.quat_wxyz[m],
                        series.velocity_cam_m_s[m], series.omega_body_rad_s[m])


def measurement_stats(rec: dict[str, Any]) -> dict[str, float]:
    """Slide of automatic targets on the surface; depth bias; error of the a-priori points' measurements."""
    out: dict[str, float] = {}
    tracks: dict[str, list[tuple[float, np.ndarray]]] = {}
    depth, ap_lat, ap_depth = [], [], []
    ap_per_point: dict[str, list[tuple[float, float]]] = {}  # id -> (depth error, its 1-sigma), m
    for targets, (t_s, T, _, _), surf in zip(rec["targets"], rec["truth"], rec["surface"]):
        R, t = T[:3, :3], T[:3, 3]
        for tg in targets:
            if not (tg.measured and np.all(np.isfinite(tg.point_cam))):
                continue
            if tg.id in rec["apriori"]:
                e = np.asarray(tg.point_cam) - (R @ rec["apriori"][tg.id] + t)
                if np.linalg.norm(e) < 0.05:  # a lock on another surface is the pose's outlier, not a bias
                    ap_lat.append(np.linalg.norm(e[:2]))
                    ap_depth.append(abs(e[2]))
                    ap_per_point.setdefault(tg.id, []).append((e[2], np.sqrt(np.asarray(tg.cov_cam)[2, 2])))
            elif np.all(np.isfinite(surf.get(tg.id, np.nan))):
                e = np.asarray(tg.point_cam) - (R @ surf[tg.id] + t)
                if np.linalg.norm(e) < 0.02:
                    depth.append(e[2])
                tracks.setdefault(tg.id, []).append((t_s, surf[tg.id]))
    for after in (1.0, 2.0, 10.0):
        d = []
        for pts in tracks.values():
            ts = np.array([p[0] for p in pts])
            k = int(np.searchsorted(ts - ts[0], after))
            if k < len(ts):
                d.append(np.linalg.norm(pts[k][1] - pts[0][1]))
        out[f"slide_median_mm_{after:.0f}s"] = float(np.median(d) * 1e3) if d else float("nan")
    out["auto_depth_bias_mm"] = float(np.median(depth) * 1e3) if depth else float("nan")
    out["apriori_lateral_error_median_mm"] = float(np.median(ap_lat) * 1e3) if ap_lat else float("nan")
    out["apriori_depth_error_median_mm"] = float(np.median(ap_depth) * 1e3) if ap_depth else float("nan")
    # A bias, not noise: the point's mean error over all its measurements, against their sigma.
    biases = [(float(np.mean([e for e, _ in v])), float(np.mean([sd for _, sd in v]))) for v in ap_per_point.values()]
    bias_m, sigma_m = max(biases, key=lambda b: abs(b[0]), default=(float("nan"), float("nan")))
    out["apriori_depth_bias_worst_mm"] = bias_m * 1e3
    out["apriori_depth_bias_worst_sigmas"] = bias_m / sigma_m
    return out


# pose.anchor_time_s / anchor_memory_s of the *_anchored variants: the grown model pulled onto
# the a-priori points' frame whenever they are seen (off in the default configuration).
ANCHORED = dict(anchor_time_s=0.5, anchor_memory_s=1.0)


def run() -> dict[str, float]:
    seconds = float(os.environ.get("TRACKMETER_BUDGET_S", "60"))
    base = bench_config()  # before the long recording: a bad TRACKMETER_BENCH_CONFIG is refused at once
    rec = record(seconds)
    out = measurement_stats(rec)
    anchored = replace(base, pose=replace(base.pose, **ANCHORED))
    oracle_apriori = dict(apriori=True, auto=False, pinned=False)
    variants: dict[str, tuple[dict[str, Any] | None, Config]] = {
        "recorded": (None, base),
        "oracle_apriori": (oracle_apriori, base),
        "oracle_auto": (dict(apriori=False, auto=True, pinned=False), base),
        "oracle_auto_pinned": (dict(apriori=False, auto=True, pinned=True), base),
        "oracle_all": (dict(apriori=True, auto=True, pinned=True), base),
        "recorded_anchored": (None, anchored),
        "oracle_apriori_anchored": (oracle_apriori, anchored),
        "oracle_apriori_bias1mm_anchored": (dict(oracle_apriori, apriori_bias_sd_m=0.001), anchored),
        "oracle_apriori_bias2mm_anchored": (dict(oracle_apriori, apriori_bias_sd_m=0.002), anchored),
    }
    for name, (kw, config) in variants.items():
        frames = rec["targets"] if kw is None else oracle_frames(rec, **kw)
        truth, est = replay(rec, frames, config)
        if name == "recorded":
            diffs = [np.linalg.norm(T[:3, 3] - p) for T, p, ok in zip(rec["poses"], est.position_m, est.valid)
                     if T is not None and ok]
            out["replay_max_diff_mm"] = float(max(diffs) * 1e3) if diffs else float("nan")
        for s in SPANS_S:
            if truth.t_s[-1] < s - 0.1:
                break
            f = figures(_span(truth, s), _span(est, s), "none", "x")
            for m in METRICS:
                for key, value in f.items():
                    if key.startswith(f"x_{m}_max_"):
                        out[f"{name}_{s:.0f}s_{key[2:]}"] = value
        _log(f"{name} done")
    return out


if __name__ == "__main__":
    from benchmarks import main_of

    main_of("error_budget", __doc__, run)
