"""Reproduce the README results table from scratch: ``python -m benchmarks.reproduce``.

Every figure comes from the project's own commands, run here as a user would run them (the
README's commands), in this order:

1. ``trackmeter simulate`` the scenarios into sequence folders (``estec``, ``harsh_light``,
   ``fast_tumble``, ``static_ranges``);
2. ``trackmeter track`` each tumbling sequence (16 automatic targets; model case b started from
   the model points visible in the first frame, and case a on ``estec``) into run directories;
3. ``trackmeter evaluate`` each run against its sequence's ground truth (2 s settle time;
   ``--align body`` for case a, whose body frame is its own);
4. ``trackmeter analyze`` the ``static_ranges`` sequence (sigma versus range, sub-pixel accuracy);
5. ``python -m benchmarks`` (speed figures: medians and same-run ratios).

A step whose command is not built yet (it says "not built yet" and exits 2) or that fails is
reported as missing or failed in the table, with the reason - never filled with a made-up
number; the steps that depend on it are skipped. Everything is written under ``--out``
(default ``results/``, ignored by git): the sequences and runs in ``work/``, each command's
output and log, and the table in ``results.md``, which is also printed.

Options: ``--quick`` renders short sequences (10 s, 6 frames per static range) and runs only the
quick benchmarks, to check the chain in a few minutes; the README's figures come from a full run.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import importlib.util
import json
import math
import os
import platform
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from benchmarks import CONFIG_ENV, NAMES, browser_unmet

REPO = Path(__file__).resolve().parent.parent
PAPER_VIEW_NOTE = "paper's viewing axis was y, ours is z"


@dataclass
class Step:
    """One command run: its status is ``ok``, ``missing`` (not built yet), ``failed`` or ``skipped``."""

    name: str
    argv: list[str]
    status: str = "pending"
    reason: str = ""
    seconds: float = 0.0
    stdout: str = ""

    @property
    def command(self) -> str:
        """The command as a user types it (``trackmeter ...``, ``python -m ...``)."""
        argv = list(self.argv)
        if argv[:3] == [sys.executable, "-m", "trackmeter.cli.main"]:
            argv = ["trackmeter", *argv[3:]]
        elif argv[:2] == [sys.executable, "-m"]:
            argv = ["python", "-m", *argv[2:]]
        return " ".join(shlex.quote(a) for a in argv)


@dataclass
class Runner:
    out: Path
    log_dir: Path
    steps: list[Step] = field(default_factory=list)

    built: dict[str, bool] = field(default_factory=dict)

    def is_built(self, command: str) -> bool:
        """Whether ``trackmeter COMMAND`` exists beyond its placeholder (its --help says so)."""
        if command not in self.built:
            proc = subprocess.run(trackmeter(command, "--help"), cwd=REPO, capture_output=True, text=True)
            self.built[command] = proc.returncode == 0 and "not built yet" not in proc.stdout
        return self.built[command]

    def run(self, name: str, argv: list[str], needs: list[Step] | None = None, timeout_s: float = 7200,
            env: dict[str, str] | None = None) -> Step:
        """Run one command unless a step it needs did not succeed; log it; classify the result.
        ``env``: variables set for this command on top of the environment."""
        step = Step(name, argv)
        self.steps.append(step)
        if argv[:3] == trackmeter() and not self.is_built(argv[3]):
            step.status, step.reason = "missing", f"trackmeter {argv[3]} is not built yet"
            print(f"[reproduce] missing {name}: {step.reason}", file=sys.stderr, flush=True)
            return step
        blocked = [s for s in (needs or []) if s.status != "ok"]
        if blocked:
            step.status = "skipped"
            step.reason = f"needs {blocked[0].name} ({blocked[0].status})"
            print(f"[reproduce] skip   {name}: {step.reason}", file=sys.stderr, flush=True)
            return step
        print(f"[reproduce] run    {name}: {step.command}", file=sys.stderr, flush=True)
        start = time.monotonic()
        try:
            # The table is the default configuration's: an opt-in file meant for one benchmark
            # (TRACKMETER_BENCH_CONFIG) must not slip into it from the caller's environment.
            base = {k: v for k, v in os.environ.items() if k != CONFIG_ENV}
            proc = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, timeout=timeout_s,
                                  env={**base, **(env or {})})
        except subprocess.TimeoutExpired:
            step.status, step.reason = "failed", f"timed out after {timeout_s:.0f} s"
            return step
        step.seconds = time.monotonic() - start
        step.stdout = proc.stdout
        log = self.log_dir / f"{name}.log"
        log.write_text(f"$ {step.command}\n# exit {proc.returncode}\n--- stdout\n{proc.stdout}\n--- stderr\n{proc.stderr}")
        last = next((line for line in reversed(proc.stderr.splitlines()) if line.strip()), "")
        # The table names paths inside the output folder (work/..., logs/...), wherever --out
        # put it, and others as the checkout does.
        last = last.replace(f"{self.out}{os.sep}", "").replace(f"{REPO}{os.sep}", "")
        if proc.returncode == 0:
            step.status = "ok"
        elif "not built yet" in proc.stderr:
            step.status, step.reason = "missing", last.strip()
        else:
            step.status, step.reason = "failed", short_reason(f"exit {proc.returncode}: {last.strip()}", name)
        print(f"[reproduce] {step.status:<6} {name} ({step.seconds:.1f} s){': ' + step.reason if step.reason else ''}",
              file=sys.stderr, flush=True)
        return step

    def json_of(self, step: Step, partial: bool = False) -> dict | None:
        """The step's JSON (its stdout, else its ``--out`` file), None when it did not succeed.
        ``partial``: a failed step's ``--out`` file too (``python -m benchmarks`` writes the
        figures of the benchmarks that finished when another fails; the caller removes the
        file before the step, so it is never an earlier run's)."""
        if step.status == "failed" and partial and "--out" in step.argv:
            out = Path(step.argv[step.argv.index("--out") + 1])
            try:
                return json.loads(out.read_text(encoding="utf-8")) if out.is_file() else None
            except (OSError, json.JSONDecodeError):
                return None
        if step.status != "ok":
            return None
        try:
            return json.loads(step.stdout)
        except json.JSONDecodeError:
            pass
        # A command's stdout may carry more than its JSON (a library's banner): its --out file does not.
        if "--out" in step.argv:
            out = Path(step.argv[step.argv.index("--out") + 1])
            try:
                return json.loads(out.read_text(encoding="utf-8")) if out.is_file() else None
            except (OSError, json.JSONDecodeError):
                pass
        step.status, step.reason = "failed", "printed no JSON"
        return None


def short_reason(text: str, step_name: str, limit: int = 200) -> str:
    """``text`` for a table cell: whole up to ``limit`` characters, else cut at the last word
    before it and marked, with the log that holds it all (``logs/<step>.log``)."""
    if len(text) <= limit:
        return text
    cut = text[:limit].rsplit(" ", 1)[0].rstrip(" ;:,(")
    return f"{cut} … (the whole message: logs/{step_name}.log)"


def trackmeter(*args: str) -> list[str]:
    return [sys.executable, "-m", "trackmeter.cli.main", *args]


# --------------------------------------------------------------------------- table


def _fmt(value: float | None, scale: float, digits: int, unit: str) -> str:
    if value is None or not math.isfinite(value):
        return "—"
    return f"{value * scale:.{digits}f} {unit}".rstrip()


def _status_cell(*steps: Step) -> str:
    for s in steps:
        if s.status != "ok":
            word = {"missing": "missing", "skipped": "not run", "failed": "failed"}.get(s.status, s.status)
            return f"_{word}: {s.name}{' — ' + s.reason if s.reason else ''}_".replace("|", "/")
    return ""


def evaluation_rows(label: str, summary: dict | None, steps: list[Step], command: str) -> list[str]:
    """Rows for one run: the paper's trial figures at 3.5 m beside our largest errors (RMS)."""
    rows = []
    spec = [  # (capability, paper, group, axes, scale, unit, digits)
        ("position error, lateral x/y (max / RMS)", "±3 mm", "position_m", ("x", "y"), 1e3, "mm", 2),
        ("position error, viewing axis z (max / RMS)", "±5 mm", "position_m", ("z",), 1e3, "mm", 2),
        ("attitude error about the viewing axis (eq. 17)", "±0.5°", "attitude_rad", ("z",), 180 / math.pi, "°", 3),
        ("attitude error about the other axes (eq. 17)", "±1°", "attitude_rad", ("x", "y"), 180 / math.pi, "°", 3),
        ("linear speed error, lateral", "±2 mm/s", "velocity_m_s", ("x", "y"), 1e3, "mm/s", 2),
        ("linear speed error, viewing axis", "±3.5 mm/s", "velocity_m_s", ("z",), 1e3, "mm/s", 2),
        ("angular speed error (body frame, eq. 14)", "±0.75°/s mostly, ±1°/s peaks", "omega_rad_s", ("x", "y", "z"), 180 / math.pi, "°/s", 3),
    ]
    missing = _status_cell(*steps)
    if missing:
        return [f"| {label}: pose, velocity and angular velocity errors | ±3/±5 mm, ±0.5/±1°, ±2/±3.5 mm/s, ±0.75°/s "
                f"| {missing} | `{command}` |"]
    for capability, paper, group, axes, scale, unit, digits in spec:
        if missing:
            ours = missing
        elif summary is None or summary.get(group) is None:
            ours = "— (no velocities in the run)"
        else:
            mx = max(summary[group][a]["max"] for a in axes)
            rms = max(summary[group][a]["rms"] for a in axes)
            ours = f"{_fmt(mx, scale, digits, unit)} / {_fmt(rms, scale, digits, unit)}"
        rows.append(f"| {label}: {capability} | {paper} | {ours} | `{command}` |")
    if summary is not None and not missing:
        rows.append(f"| {label}: SPEED score (mean angle + relative position error) | — | {summary['speed_score']:.5f} | `{command}` |")
    return rows


#: (benchmark, figure) -> (capability, paper figure, scale, unit, digits)
BENCHMARK_ROWS: dict[tuple[str, str], tuple[str, str, float, str, int]] = {
    ("measure", "point_ms_median"): ("one 3D point measurement (8x8 patch, sub-pixel)", "15 ms", 1.0, "ms", 3),
    ("measure", "batch100_ms_median"): ("100 point measurements", "1.5 s", 1.0, "ms", 1),
    ("measure", "subpixel_rms_px"): ("sub-pixel disparity error, synthetic shifts (RMS)", "0.07 px", 1.0, "px", 4),
    ("tracker", "step_ms_6"): ("tracking step, 6 targets", "160 ms (6.25 Hz)", 1.0, "ms", 2),
    ("tracker", "step_ms_50"): ("tracking step, 50 targets", "—", 1.0, "ms", 2),
    ("tracker", "max_speed_px_s"): ("Kalman-aided tracking, fastest image motion held", "200 px/s", 1.0, "px/s", 0),
    ("tracker", "rubberwhale_median_epe_px"): ("patch tracking end-point error, RubberWhale (median)", "—", 1.0, "px", 4),
    ("tracker", "rubberwhale_median_epe_px_lk"): ("the same, OpenCV pyramidal LK on the same points", "—", 1.0, "px", 4),
    ("tracker", "step_ratio_vs_lk_6"): ("tracking step, 6 targets, over pyramidal LK (same run)", "—", 1.0, "x", 2),
    ("tracker", "tracked_fraction_estec"): ("target-frames tracked, 16 automatic targets, estec (20 s)", "—", 100.0, "%", 1),
    ("tracker", "false_locks_estec"): ("false locks (> 2 px off the point measured), estec", "—", 1.0, "", 0),
    ("tracker", "false_locks_pixel_estec"): ("false locks against the centre-pixel surface point, estec", "—", 1.0, "", 0),
    ("tracker", "tracked_fraction_harsh_light"): ("target-frames tracked, harsh_light (20 s)", "—", 100.0, "%", 1),
    ("tracker", "false_locks_harsh_light"): ("false locks (> 2 px off the point measured), harsh_light", "—", 1.0, "", 0),
    ("tracker", "false_locks_pixel_harsh_light"): ("false locks against the centre-pixel surface point, harsh_light", "—", 1.0, "", 0),
    ("operator", "operator_tracked_fraction_estec"): ("operator's clicked targets: frames tracked, estec (2 s after 8 clicks, median of 5 draws)", "—", 100.0, "%", 1),
    ("operator", "operator_tracked_ratio_estec"): ("the same, over the run without the scale-held anchor refit (same run)", "—", 1.0, "x", 2),
    ("operator", "operator_tracked_fraction_harsh_light"): ("operator's clicked targets: frames tracked, harsh_light", "—", 100.0, "%", 1),
    ("operator", "operator_false_frames_estec"): ("operator's clicked targets: frames > 2 px off their surface point before a first loss, estec", "—", 1.0, "", 0),
    ("select", "select_ms_4"): ("automatic selection of 4 points (Gabor bank + stereo check)", "—", 1.0, "ms", 1),
    ("accuracy", "estec_b_pos_lateral_max_mm"): ("whole chain, estec case (b), first {estec_duration_s} s, median over noise seeds: position error, lateral (max)", "±3 mm", 1.0, "mm", 2),
    ("accuracy", "estec_b_pos_depth_max_mm"): ("whole chain, estec case (b), first {estec_duration_s} s, median over noise seeds: position error, viewing axis (max)", "±5 mm", 1.0, "mm", 2),
    ("accuracy", "estec_b_att_view_max_deg"): ("whole chain, estec case (b), first {estec_duration_s} s, median over noise seeds: attitude error about the viewing axis (max)", "±0.5°", 1.0, "°", 3),
    ("accuracy", "estec_b_att_other_max_deg"): ("whole chain, estec case (b), first {estec_duration_s} s, median over noise seeds: attitude error about the other axes (max)", "±1°", 1.0, "°", 3),
    ("accuracy", "estec_b_vel_lateral_max_mm_s"): ("whole chain, estec case (b), first {estec_duration_s} s, median over noise seeds: linear speed error, lateral (max)", "±2 mm/s", 1.0, "mm/s", 2),
    ("accuracy", "estec_b_vel_depth_max_mm_s"): ("whole chain, estec case (b), first {estec_duration_s} s, median over noise seeds: linear speed error, viewing axis (max)", "±3.5 mm/s", 1.0, "mm/s", 2),
    ("accuracy", "estec_b_omega_max_deg_s"): ("whole chain, estec case (b), first {estec_duration_s} s, median over noise seeds: angular speed error (max)", "±0.75°/s", 1.0, "°/s", 3),
    ("accuracy", "estec_b_valid_fraction"): ("whole chain, estec case (b), first {estec_duration_s} s, median over noise seeds: valid poses", "—", 100.0, "%", 1),
    ("accuracy", "estec_a_pos_lateral_max_mm"): ("whole chain, estec case (a), first {estec_duration_s} s, median over noise seeds: position error, lateral (max)", "±3 mm", 1.0, "mm", 2),
    ("accuracy", "estec_a_pos_depth_max_mm"): ("whole chain, estec case (a), first {estec_duration_s} s, median over noise seeds: position error, viewing axis (max)", "±5 mm", 1.0, "mm", 2),
    ("accuracy", "estec_a_att_view_max_deg"): ("whole chain, estec case (a), first {estec_duration_s} s, median over noise seeds: attitude error about the viewing axis (max)", "±0.5°", 1.0, "°", 3),
    ("accuracy", "estec_a_att_other_max_deg"): ("whole chain, estec case (a), first {estec_duration_s} s, median over noise seeds: attitude error about the other axes (max)", "±1°", 1.0, "°", 3),
    ("accuracy", "estec_a_vel_lateral_max_mm_s"): ("whole chain, estec case (a), first {estec_duration_s} s, median over noise seeds: linear speed error, lateral (max)", "±2 mm/s", 1.0, "mm/s", 2),
    ("accuracy", "estec_a_vel_depth_max_mm_s"): ("whole chain, estec case (a), first {estec_duration_s} s, median over noise seeds: linear speed error, viewing axis (max)", "±3.5 mm/s", 1.0, "mm/s", 2),
    ("accuracy", "estec_a_omega_max_deg_s"): ("whole chain, estec case (a), first {estec_duration_s} s, median over noise seeds: angular speed error (max)", "±0.75°/s", 1.0, "°/s", 3),
    ("accuracy", "estec_a_valid_fraction"): ("whole chain, estec case (a), first {estec_duration_s} s, median over noise seeds: valid poses", "—", 100.0, "%", 1),
    ("accuracy", "harsh_light_b_valid_fraction"): ("whole chain, harsh_light case (b), first {harsh_light_duration_s} s: valid poses", "—", 100.0, "%", 1),
    ("accuracy", "harsh_light_b_valid_fraction_occluded"): ("whole chain, harsh_light case (b): valid poses while the panel passes (6-14 s)", "—", 100.0, "%", 1),
    ("accuracy", "harsh_light_b_valid_fraction_occluded_once_valid"): ("whole chain, harsh_light case (b): valid poses while the panel passes, from the first valid pose on (stays valid)", "—", 100.0, "%", 1),
    ("accuracy", "harsh_light_b_max_jump_sigma_at_loss_or_recovery"): ("harsh_light case (b): largest pose jump at a loss or recovery, in pose sigmas", "—", 1.0, "σ", 2),
    ("accuracy", "harsh_light_a_valid_fraction"): ("whole chain, harsh_light case (a), first {harsh_light_duration_s} s: valid poses", "—", 100.0, "%", 1),
    ("accuracy", "harsh_light_a_valid_fraction_occluded"): ("whole chain, harsh_light case (a): valid poses while the panel passes (6-14 s)", "—", 100.0, "%", 1),
    ("accuracy", "harsh_light_a_valid_fraction_occluded_once_valid"): ("whole chain, harsh_light case (a): valid poses while the panel passes, from the first valid pose on (stays valid)", "—", 100.0, "%", 1),
    ("accuracy", "harsh_light_a_max_jump_sigma_at_loss_or_recovery"): ("harsh_light case (a): largest pose jump at a loss or recovery, in pose sigmas", "—", 1.0, "σ", 2),
    ("accuracy", "harsh_light_a_loss_or_recovery_frames"): ("harsh_light case (a): frames with a target lost or recovered (valid pose before and after)", "—", 1.0, "", 0),
    ("accuracy", "harsh_light_a_recoveries_through_pose"): ("harsh_light case (a): model points re-locked through the pose", "—", 1.0, "", 0),
    ("accuracy", "harsh_light_a_coasted_frames"): ("harsh_light case (a): frames output from the coast (no point measured; flagged coasting)", "—", 1.0, "", 0),
    ("accuracy", "harsh_light_a_longest_coast_s"): ("harsh_light case (a): longest coast", "—", 1.0, "s", 2),
    ("accuracy", "harsh_light_a_coast_drift_max_sigma"): ("harsh_light case (a): largest drift while coasting, in sigmas of the covariance the coast added", "—", 1.0, "σ", 2),
    ("accuracy", "harsh_light_a_body_frames"): ("harsh_light case (a): body frames defined (a new one after a total loss; each aligned on its own)", "—", 1.0, "", 0),
    ("accuracy", "harsh_light_a_pos_lateral_max_mm"): ("harsh_light case (a): position error, lateral (max)", "±3 mm", 1.0, "mm", 2),
    ("accuracy", "harsh_light_a_pos_depth_max_mm"): ("harsh_light case (a): position error, viewing axis (max)", "±5 mm", 1.0, "mm", 2),
    ("accuracy", "harsh_light_a_att_other_max_deg"): ("harsh_light case (a): attitude error about the other axes (max)", "±1°", 1.0, "°", 3),
    ("looks", "looks_underexposed_a_valid_fraction"): ("whole chain on underexposed images (estec's first {looks_duration_s} s at 0.35 of their grey levels, noise added), case (a): valid poses", "—", 100.0, "%", 1),
    ("looks", "looks_underexposed_a_valid_fraction_gain_off"): ("the same without the exposure gain (same run)", "—", 100.0, "%", 1),
    ("looks", "looks_underexposed_b_valid_fraction"): ("whole chain on underexposed images, case (b): valid poses", "—", 100.0, "%", 1),
    ("looks", "looks_underexposed_b_valid_fraction_gain_off"): ("the same without the exposure gain (same run)", "—", 100.0, "%", 1),
    ("render", "stereo_fps"): ("simulator: stereo frames rendered per second", "—", 1.0, "fps", 1),
    ("pipeline", "live_rate_hz"): ("live pipeline rate, 16 targets", "6.25 Hz (6 points)", 1.0, "Hz", 2),
    ("pipeline", "dropped_fraction"): ("live pipeline dropped frames", "—", 100.0, "%", 2),
    ("pipeline", "offline_fps"): ("track on a recorded sequence, 16 targets", "—", 1.0, "fps", 1),
    ("soak", "rss_growth_fraction"): ("memory growth over a 10-minute live run", "—", 100.0, "%", 2),
    ("console", "tracking_rate_hz"): ("tracking rate with the browser console connected", "—", 1.0, "Hz", 2),
    ("console", "click_latency_ms"): ("click to target on screen (the operator's box drawn by the page; median over the clicks)", "—", 1.0, "ms", 0),
    ("console", "clicks_measured"): ("clicks measured in that run", "—", 1.0, "", 0),
    ("console", "browser_image_updates_per_s"): ("image updates received by the browser", "—", 1.0, "/s", 1),
    ("console", "dropped_fraction"): ("frames dropped with the console connected", "—", 100.0, "%", 2),
    ("console", "cpu_nice"): ("console's CPU priority in that run (nice; `trackmeter console --cpu-nice`)", "—", 1.0, "", 0),
    ("console", "browser_images_shown_per_s"): ("images the browser drew per second in that run (software WebGL, same cores)", "—", 1.0, "/s", 2),
}


CONSOLE_SOAK_ROWS = (
    ("rss_growth_fraction", "memory growth over a 10-minute console run, two browsers connected", 100.0, "%", 2),
    ("log_errors", "errors logged in that run", 1.0, "", 0),
    ("tracking_rate_hz", "tracking rate in that run (the browsers share the two cores)", 1.0, "Hz", 1),
)


def console_soak_rows(results: dict | None, step: Step) -> list[str]:
    """The table rows of the console soak (``results``: its ``python -m benchmarks soak`` JSON)."""
    cmd = "TRACKMETER_SOAK_CONSOLE=1 python -m benchmarks soak"
    figures = (results or {}).get("soak", {})
    rows = []
    for key, capability, scale, unit, digits in CONSOLE_SOAK_ROWS:
        value = figures.get(key)
        ours = _fmt(float(value), scale, digits, unit) if value is not None else (_status_cell(step) or "—")
        rows.append(f"| {capability} | — | {ours} | `{cmd}` |")
    return rows


def _per_seed(figures: dict, key: str) -> list[float]:
    """The values of ``key`` per noise seed (``<key>_seed0``, ``_seed1``, ...), in seed order."""
    values: list[float] = []
    while f"{key}_seed{len(values)}" in figures:
        value = figures[f"{key}_seed{len(values)}"]
        values.append(float("nan") if value is None else float(value))  # null: not finite in that run
    return values


DURATION_FIGURES = {"estec_duration_s": "TRACKMETER_ACCURACY_S", "harsh_light_duration_s": "TRACKMETER_HARSH_S",
                    "looks_duration_s": "TRACKMETER_LOOKS_S"}


def _with_duration(capability: str, figures: dict | None) -> str:
    """The capability with ``{estec_duration_s}`` (``{harsh_light_duration_s}``) replaced by the
    seconds the benchmark ran (that figure), or by the variable that sets them where it has none."""
    for key, variable in DURATION_FIGURES.items():
        seconds = (figures or {}).get(key)
        capability = capability.replace("{" + key + "}", variable if seconds is None else f"{float(seconds):g}")
    return capability


def benchmark_rows(results: dict | None, step: Step | None, names: list[str], not_built: list[str]) -> list[str]:
    rows = []
    for (bench, key), (capability, paper, scale, unit, digits) in BENCHMARK_ROWS.items():
        if bench not in names:
            continue
        capability = _with_duration(capability, results.get(bench) if results is not None else None)
        if results is not None and bench in results and key in results[bench]:
            value = results[bench][key]  # null: not finite in that run
            ours = _fmt(None if value is None else float(value), scale, digits, unit)
            per_seed = _per_seed(results[bench], key)
            if len(per_seed) > 1:  # a median over noise seeds: show each
                ours += f" (median of {', '.join(_fmt(float(v), scale, digits, '') for v in per_seed)})"
        elif bench in not_built:
            ours = f"_missing: benchmarks/{bench}.py not built yet_"
        elif step is not None and step.status != "ok":
            ours = _status_cell(step)
        else:
            ours = f"_missing: benchmark {bench} has no figure {key}_"
        rows.append(f"| {capability} | {paper} | {ours} | `python -m benchmarks {bench}` |")
    return rows


@dataclass(frozen=True)
class Goal:
    """One "Must show" figure of an issue: benchmark ``bench``'s figure ``key`` must be at most
    (``at_most``) or at least ``limit`` (``strict``: under or over it), in the figure's own units."""

    bench: str
    key: str
    label: str
    limit: float
    at_most: bool
    scale: float
    unit: str
    digits: int

    strict: bool = False  # "under the limit" (the issue's "< 1 %"), not "at most"

    def met(self, value: float) -> bool:
        if self.strict:
            return value < self.limit if self.at_most else value > self.limit
        return value <= self.limit if self.at_most else value >= self.limit


def _issue5_goals() -> tuple[Goal, ...]:
    # Issue 5's Must-show: half the paper's figures on estec (both cases); no jump above 3 sigma
    # at a loss or recovery and a pose that stays valid while harsh_light's panel passes; the
    # pipeline's rates and memory. "Sustains 25 Hz" is read as within the 1 % the dropped-frame
    # goal allows (a 40 s window of a 25 Hz source counts 24.97-25.00 Hz).
    motion = (("pos_lateral_max_mm", "position, lateral", 1.5, 1.0, "mm", 2),
              ("pos_depth_max_mm", "position, viewing axis", 2.5, 1.0, "mm", 2),
              ("att_view_max_deg", "attitude about the viewing axis", 0.25, 1.0, "°", 3),
              ("att_other_max_deg", "attitude about the other axes", 0.5, 1.0, "°", 3),
              ("vel_lateral_max_mm_s", "linear speed, lateral", 1.0, 1.0, "mm/s", 2),
              ("vel_depth_max_mm_s", "linear speed, viewing axis", 1.75, 1.0, "mm/s", 2),
              ("omega_max_deg_s", "angular speed", 0.35, 1.0, "°/s", 3))
    goals = [Goal("accuracy", f"estec_{case}_{key}", f"estec case ({case}), median of the noise seeds' maxima: {label}",
                  limit, True, scale, unit, digits)
             for case in ("b", "a") for key, label, limit, scale, unit, digits in motion]
    for case in ("a", "b"):
        goals.append(Goal("accuracy", f"harsh_light_{case}_valid_fraction_occluded",
                          f"harsh_light case ({case}): valid poses while the panel passes", 1.0, False, 100.0, "%", 1))
        goals.append(Goal("accuracy", f"harsh_light_{case}_valid_fraction_occluded_once_valid",
                          f"harsh_light case ({case}): ... from the first valid pose on (the pose, once there, stays valid)",
                          1.0, False, 100.0, "%", 1))
        goals.append(Goal("accuracy", f"harsh_light_{case}_max_jump_sigma_at_loss_or_recovery",
                          f"harsh_light case ({case}): largest jump at a loss or recovery", 3.0, True, 1.0, "σ", 2))
    goals += [Goal("pipeline", "live_rate_hz", "live pipeline rate, sim source, 16 targets", 24.75, False, 1.0, "Hz", 2),
              Goal("pipeline", "dropped_fraction", "live pipeline dropped frames", 0.01, True, 100.0, "%", 2, strict=True),
              Goal("pipeline", "offline_fps", "track on a recorded sequence, 16 targets", 60.0, False, 1.0, "fps", 1),
              Goal("soak", "rss_growth_fraction", "memory growth over a 10-minute live run", 0.05, True, 100.0, "%", 2,
                   strict=True)]
    return tuple(goals)


ISSUE5_GOALS = _issue5_goals()


def goal_rows(results: dict | None, goals: tuple[Goal, ...] = ISSUE5_GOALS) -> list[str]:
    """A table of ``goals`` against this run's benchmark ``results``: the figure, and whether it
    meets its goal (a figure the run did not produce is "not measured", never met)."""
    rows = ["| goal (issue 5, Must show) | limit | this run | met |", "| --- | --- | --- | --- |"]
    for g in goals:
        value = (results or {}).get(g.bench, {}).get(g.key)
        sign = ("<" if g.at_most else ">") if g.strict else ("≤" if g.at_most else "≥")
        limit = f"{sign} {_fmt(g.limit, g.scale, g.digits, g.unit)}"
        if value is None or not math.isfinite(float(value)):
            rows.append(f"| {g.label} | {limit} | — | not measured |")
            continue
        verdict = "yes" if g.met(float(value)) else "**no**"
        rows.append(f"| {g.label} | {limit} | {_fmt(float(value), g.scale, g.digits, g.unit)} | {verdict} |")
    return rows


# --------------------------------------------------------------------------- main


README_BEGIN = "<!-- reproduce:begin -->"
README_END = "<!-- reproduce:end -->"


def update_readme(readme: Path, table: str) -> bool:
    """Replace what lies between the README's reproduce markers with ``table`` (atomically);
    False when the markers are missing (nothing written)."""
    from trackmeter.data.atomic import write_text_atomic

    text = readme.read_text(encoding="utf-8")
    i, j = text.find(README_BEGIN), text.find(README_END)
    if i < 0 or j < i:
        return False
    note = "<!-- generated by `python -m benchmarks.reproduce`: edit the code, not this table -->"
    new = text[: i + len(README_BEGIN)] + "\n" + note + "\n\n" + table.strip() + "\n\n" + text[j:]
    write_text_atomic(readme, new)
    return True


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.reproduce", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=REPO / "results", help="output folder (default results/)")
    parser.add_argument("--quick", action="store_true", help="short sequences and quick benchmarks only")
    parser.add_argument("--benchmarks", nargs="*", metavar="NAME",
                        help="benchmarks to run (default: all built; --quick: measure tracker render)")
    parser.add_argument("--auto", type=int, default=16, help="automatic targets per run (default 16)")
    parser.add_argument("--no-readme", action="store_true",
                        help="do not write the table into README.md (a full run does, between its reproduce markers)")
    args = parser.parse_args(argv)

    built = [n for n in NAMES if importlib.util.find_spec(f"benchmarks.{n}") is not None]
    wanted = args.benchmarks if args.benchmarks is not None else (
        [n for n in ("measure", "tracker", "render") if n in built] if args.quick else built)
    not_built = [n for n in (args.benchmarks or NAMES) if n not in built]
    # Before the 15 minutes of simulating and tracking, not after them: the console's rows
    # (and the console soak's) need a browser.
    if any(n in wanted for n in ("console", "soak")) and not args.quick and (why := browser_unmet()):
        parser.error(f"the console benchmarks need {why} (or --benchmarks without console and soak)")

    out = args.out.resolve()
    work = out / "work"
    if work.exists():
        shutil.rmtree(work)  # from scratch: never mix figures of two runs
    logs = out / "logs"
    if logs.exists():
        shutil.rmtree(logs)
    work.mkdir(parents=True)
    logs.mkdir(parents=True)
    r = Runner(out, logs)
    duration = ["--duration", "10"] if args.quick else []
    started = _dt.datetime.now(_dt.timezone.utc)

    # 1-3. simulate, track, evaluate
    runs = [("estec", "b", "none"), ("estec", "a", "body"), ("harsh_light", "b", "none"), ("fast_tumble", "b", "none")]
    sims: dict[str, Step] = {}
    table: list[str] = []
    for scenario, case, align in runs:
        seq = work / f"seq_{scenario}"
        if scenario not in sims:
            sims[scenario] = r.run(f"simulate_{scenario}", trackmeter("simulate", "--scenario", scenario, *duration, "--out", str(seq)))
        run_dir = work / f"run_{scenario}_{case}"
        # Case (b) starts as the operator would: clicking the model points visible in the first
        # frame (track's --select-model-points puts them at their true projections).
        select = ["--select-model-points"] if case == "b" else []
        track = r.run(f"track_{scenario}_{case}",
                      trackmeter("track", "--source", f"seq:{seq}", "--auto", str(args.auto), *select, "--case", case,
                                 "--out", str(run_dir)),
                      needs=[sims[scenario]])
        ev = r.run(f"evaluate_{scenario}_{case}",
                   trackmeter("evaluate", "--truth", str(seq), "--estimate", str(run_dir), "--align", align,
                              "--settle", "2", "--json", "--out", str(out / f"evaluate_{scenario}_{case}")),
                   needs=[sims[scenario], track])
        summary = r.json_of(ev)
        command = (f"trackmeter simulate --scenario {scenario} --out SEQ && trackmeter track --source seq:SEQ "
                   f"--auto {args.auto} {' '.join(select)}{' ' if select else ''}--case {case} --out RUN && "
                   f"trackmeter evaluate --truth SEQ --estimate RUN "
                   f"--align {align} --settle 2")
        table += evaluation_rows(f"{scenario}, case ({case})", summary, [sims[scenario], track, ev], command)

    # 4. analyze
    static_seq = work / "seq_static_ranges"
    sim_static = r.run("simulate_static_ranges",
                       trackmeter("simulate", "--scenario", "static_ranges", *(["--duration", "1.44"] if args.quick else []),
                                  "--out", str(static_seq)))
    an = r.run("analyze_static_ranges", trackmeter("analyze", "--source", f"seq:{static_seq}", "--json",
                                                   "--out", str(out / "analyze_static_ranges")), needs=[sim_static])
    a = r.json_of(an)
    acmd = "trackmeter simulate --scenario static_ranges --out SEQ && trackmeter analyze --source seq:SEQ"
    miss = _status_cell(sim_static, an)
    if a is not None and not miss:
        table.append(f"| single-point sigma along the viewing axis at 3.5 m, the Shi-Tomasi corners `analyze` selects "
                     f"(fit σz = k z²) | 4 mm | "
                     f"{_fmt(a['sigma_z_at_3p5_m'], 1e3, 3, 'mm')} (R² {a['fit']['z']['r2']:.3f}) | `{acmd}` |")
        table.append(f"| sub-pixel disparity accuracy from k (eq. 2: σd = k f b) | 0.07 px | "
                     f"{_fmt(a['sigma_disparity_px'], 1, 4, 'px')} | `{acmd}` |")
        ratio = a.get("measured_over_noise_limit_median")
        if ratio is not None and math.isfinite(ratio):
            table.append(f"| matcher against the sensor-noise limit (measured σd / Cramér-Rao bound per point, median) "
                         f"| — | {ratio:.2f} | `{acmd}` |")
        near = min(a["ranges"], key=lambda e: abs(e["range_m"] - 3.5))
        te = near.get("truth_error")
        if te:
            table.append(f"| single-point depth error against the truth at {near['range_m']:.2f} m (RMS, "
                         f"{te['n_gross']} of {te['n_points']} points gross mismatches left out) | — | "
                         f"{_fmt(te['rms_m']['z'], 1e3, 3, 'mm')} | `{acmd}` |")
    else:
        table.append(f"| single-point sigma along the viewing axis at 3.5 m | 4 mm | {miss or '—'} | `{acmd}` |")
        table.append(f"| sub-pixel disparity accuracy (eq. 2) | 0.07 px | {miss or '—'} | `{acmd}` |")

    # 5. benchmarks
    bench_step = None
    results = None
    if wanted:
        (out / "benchmarks.json").unlink(missing_ok=True)  # a failed run reads what it wrote, never an earlier run's
        bench_step = r.run("benchmarks", [sys.executable, "-m", "benchmarks", *wanted, "--out", str(out / "benchmarks.json")])
        results = r.json_of(bench_step, partial=True)
    table += benchmark_rows(results, bench_step, [n for n in NAMES if n in wanted or n in not_built], not_built)
    for n in not_built:
        if not any(b == n for b, _ in BENCHMARK_ROWS):
            table.append(f"| benchmark `{n}` | — | _missing: benchmarks/{n}.py not built yet_ | `python -m benchmarks {n}` |")
    if "soak" in wanted and not args.quick:
        # Issue 7's soak: the operator console with two headless browsers for 10 minutes.
        soak_step = r.run("soak_console", [sys.executable, "-m", "benchmarks", "soak", "--out", str(out / "soak_console.json")],
                          env={"TRACKMETER_SOAK_CONSOLE": "1"})
        table += console_soak_rows(r.json_of(soak_step), soak_step)

    # the table
    header = [
        f"# Results (reproduced {started:%Y-%m-%d %H:%M} UTC{', QUICK run: short sequences' if args.quick else ''})",
        "",
        f"Machine: {platform.machine()}, {platform.system()} {platform.release()}, Python {platform.python_version()}; "
        f"command: `python -m benchmarks.reproduce{' --quick' if args.quick else ''}`.",
        f"Errors are the largest absolute value over the run after a 2 s settle time, then RMS; axes: x, y lateral, "
        f"z the viewing axis ({PAPER_VIEW_NOTE}); a lateral row gives the larger of x's and y's figures (each "
        "in `evaluate`'s output). Paper figures: the original system at 3.5 m.",
        "",
        "| capability | paper | ours | command |",
        "| --- | --- | --- | --- |",
    ]
    goals = ["", "Issue 5's goals against this run's benchmark figures (the table above has the rest):", ""]
    goals += goal_rows(results) if results is not None else ["_no benchmark figures in this run_"]
    status = ["", "## Steps", "", "| step | status | time | reason |", "| --- | --- | --- | --- |"]
    status += [f"| `{s.name}` | {s.status} | {s.seconds:.1f} s | {s.reason.replace('|', '/')} |" for s in r.steps]
    text = "\n".join(header + table + goals + status) + "\n"
    tmp = out / ".results.md.tmp"
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(out / "results.md")
    print(text)
    print(f"[reproduce] wrote {out / 'results.md'}", file=sys.stderr)
    if not args.quick and not args.no_readme:
        if update_readme(REPO / "README.md", "\n".join(header[2:] + table + goals)):
            print(f"[reproduce] wrote the table into {REPO / 'README.md'}", file=sys.stderr)
        else:
            print(f"[reproduce] README.md has no {README_BEGIN} ... {README_END} markers: not updated", file=sys.stderr)
    bad = [s for s in r.steps if s.status != "ok"]
    return 0 if not bad else 1


if __name__ == "__main__":
    sys.exit(main())
