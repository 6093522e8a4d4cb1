"""Simulation scenarios: what the rig sees, how the target moves, how it is lit (``config/scenarios/``).

A scenario file is YAML validated into the frozen :class:`Scenario` (every key, type and range
checked by :func:`trackmeter.data.config.build_dataclass`; an error names the dotted key).
Everything random in a simulation (sensor noise, texture glints) is drawn from generators
seeded by ``seed`` and the frame index, so a scenario renders the same images every time and
frame ``i`` can be rendered on its own.

Frames and motion (DESIGN.md section 3): the simulator's inertial frame ``world`` is the left
camera frame (the rig is held still, as in the ESTEC trials where the mock-up moved on a
manipulator in front of fixed cameras), so ``T_cam_body = T_world_body``. The body frame is
the mock-up file's frame; its inertia tensor may be given with products of inertia and is
reduced to principal axes by :mod:`trackmeter.core.dynamics`.

Units: SI, except where a name says otherwise (``_deg``, ``_deg_s``) because people write
those by hand.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from trackmeter.core.dynamics import Translation, inertia_tensor
from trackmeter.core.params import param
from trackmeter.data.config import build_dataclass, read_yaml_mapping
from trackmeter.data.sequence import motion_digest
from trackmeter.errors import TrackmeterError
from trackmeter.paths import MODELS_DIR, RIGS_DIR, SCENARIOS_DIR, preset, preset_names
from trackmeter.sources.sim.render import RenderParams

FloatArray = NDArray[np.float64]


#: The longest scenario, s: its motion is integrated whole before the first frame (an hour
#: takes ~2 s; 1e300 s ran silently until interrupted).
MAX_DURATION_S = 3600.0
#: ... and at most this many frames (an hour at 100 Hz): the whole motion is integrated, frame
#: by frame, before the first is rendered (an hour at 10 kHz, 36 million frames, was accepted).
MAX_FRAMES = 360_000

@dataclass(frozen=True)
class OccluderSpec:
    """A flat panel passing between the rig and the target (``occluders[i]``).

    It exists from ``start_s`` to ``end_s``; its centre moves at constant velocity from
    ``position_m`` (at ``start_s``), in the camera frame. The panel's plane is its local xy
    plane, rotated by ``rotvec_deg`` from the camera axes (zero: facing the camera).
    """

    start_s: float = param(0.0, "Time the panel appears, s.", min=0.0)
    end_s: float = param(0.0, "Time the panel disappears, s.", min=0.0)
    position_m: tuple[float, float, float] = param((0.0, 0.0, 2.0), "Panel centre at start_s, camera frame, m.")
    velocity_m_s: tuple[float, float, float] = param((0.0, 0.0, 0.0), "Panel velocity, camera frame, m/s.")
    rotvec_deg: tuple[float, float, float] = param((0.0, 0.0, 0.0), "Panel orientation (rotation vector from the camera axes), deg.")
    size_m: tuple[float, float] = param((0.5, 0.5), "Panel width and height, m.", min=0.001)


@dataclass(frozen=True)
class Scenario:
    """One simulation: rig, mock-up, motion, light, occluders, rendering, timing, seed."""

    name: str = param("scenario", "Scenario name.")
    description: str = param("", "What the scenario is for.")
    rig: str = param("estec_12mm.yaml", "Stereo rig file: a path, or a name in config/rigs/.")
    mockup: str = param("estec_mockup.yaml", "Mock-up file: a path, or a name in config/models/.")
    inertia_kg_m2: tuple[float, ...] = param(
        (900.0, 900.0, 1300.0),
        "Inertia in the body frame: 3 principal moments, or Ixx, Iyy, Izz, Ixy, Ixz, Iyz (tensor elements), kg m^2.",
    )
    attitude0_wxyz: tuple[float, float, float, float] = param(
        (1.0, 0.0, 0.0, 0.0), "Initial attitude q_cam_body (scalar first; normalised)."
    )
    omega0_body_deg_s: tuple[float, float, float] = param(
        (0.0, 0.0, 0.0), "Initial angular velocity, body frame, deg/s (at most 10 turns a second about each axis: "
        "the motion is integrated before the first frame, and a typo's rate would run for minutes).",
        min=-3600.0, max=3600.0,
    )
    position0_m: tuple[float, float, float] = param((0.0, 0.0, 3.5), "Body origin at t = 0, camera frame, m.")
    velocity_m_s: tuple[float, float, float] = param((0.0, 0.0, 0.0), "Constant drift of the body origin, camera frame, m/s.")
    approach_to_m: tuple[float, float, float] | None = param(
        None, "If set, the body origin approaches this camera-frame point (minimum-jerk profile), m."
    )
    approach_s: float = param(0.0, "Duration of the approach, s (needed with approach_to_m).", min=0.0)
    static_ranges_m: tuple[float, ...] = param(
        (), "If set, the target is held still (no rotation) at each of these ranges along position0_m's direction in turn, m."
    )
    frames_per_range: int = param(25, "Frames per static range.", min=1)
    release_s: float = param(
        0.0, "The target is held still (no rotation, no drift) at its initial pose until this time, then released "
        "into its motion (rotation, drift, approach), which starts then as it would at t = 0, s.", min=0.0,
    )
    sun_dir_cam: tuple[float, float, float] = param((0.3, -0.5, -0.8), "Direction toward the sun, camera frame (normalised).")
    occluders: tuple[OccluderSpec, ...] = param((), "Panels passing in front of the target.")
    render: RenderParams = field(default_factory=RenderParams)
    rate_hz: float = param(25.0, "Frame rate, Hz.", min=0.1, max=10000.0)
    duration_s: float = param(60.0, "Length of the sequence, s (static_ranges: ranges x frames_per_range frames); at "
                              "most an hour and 360 000 frames (90 000 at 25 Hz: the whole motion is integrated before the first)",
                              min=0.0, max=MAX_DURATION_S)
    seed: int = param(0, "Seed of everything random (noise, glints), combined with the frame index.", min=0)

    def __post_init__(self) -> None:
        inertia_tensor(self.inertia_kg_m2)  # raises with the reason when not a physical body
        if np.linalg.norm(self.attitude0_wxyz) < 1e-9:
            raise TrackmeterError("'attitude0_wxyz' must be a non-zero quaternion")
        if not self.position0_m[2] > 0:
            raise TrackmeterError(f"'position0_m': z = {self.position0_m[2]:g} m puts the body at or behind the camera "
                                  "(z is the viewing axis, forward)")
        if np.linalg.norm(self.sun_dir_cam) < 1e-9:
            raise TrackmeterError("'sun_dir_cam' must be a non-zero direction")
        if self.approach_to_m is not None and self.approach_s <= 0:
            raise TrackmeterError("'approach_s' must be positive when 'approach_to_m' is set")
        if not self.release_s >= 0:
            raise TrackmeterError(f"'release_s' must be >= 0 s, got {self.release_s}")
        if any(r <= 0 for r in self.static_ranges_m):
            raise TrackmeterError("'static_ranges_m' must all be positive")
        if not self.static_ranges_m and self.duration_s <= 0:
            raise TrackmeterError(f"'duration_s': expected a value in (0, {MAX_DURATION_S:g}] (0 only with "
                                  f"'static_ranges_m', which sets the frames), got {self.duration_s:g}")
        for i, occ in enumerate(self.occluders):
            if occ.end_s <= occ.start_s:
                raise TrackmeterError(f"'occluders[{i}]': end_s must come after start_s")
        if self.n_frames > MAX_FRAMES:
            raise TrackmeterError(f"{self.n_frames} frames ('duration_s' {self.duration_s:g} s at 'rate_hz' "
                                  f"{self.rate_hz:g}): at most {MAX_FRAMES} (an hour at 100 Hz), the whole motion "
                                  "being integrated before the first frame")
        times, origins = self.origin_path_m()
        behind = np.flatnonzero(~(origins[:, 2] > 0))
        if behind.size:
            k = int(behind[0])
            raise TrackmeterError(f"the motion ('velocity_m_s', 'approach_to_m') takes the body origin to z = "
                                  f"{origins[k, 2]:.3g} m at t = {times[k]:.2f} s, at or behind the camera (z is the "
                                  "viewing axis, forward)")

    def motion_digest(self) -> str | None:
        """The fingerprint of this scenario's motion (:func:`trackmeter.data.sequence.motion_digest`)."""
        return motion_digest(dataclasses.asdict(self))

    def origin_path_m(self) -> tuple[FloatArray, FloatArray]:
        """``(t_s (N,), origin (N,3))``: the body origin in the camera frame, m, at each frame's
        time (static ranges: at each range's first frame)."""
        if self.static_ranges_m:
            direction = np.asarray(self.position0_m, dtype=float)
            origins = np.outer(self.static_ranges_m, direction / np.linalg.norm(direction))
            return np.arange(len(origins)) * self.frames_per_range / self.rate_hz, origins
        times = np.arange(self.n_frames) / self.rate_hz
        translation = Translation(
            np.asarray(self.position0_m, dtype=float), np.asarray(self.velocity_m_s, dtype=float),
            None if self.approach_to_m is None else np.asarray(self.approach_to_m, dtype=float), self.approach_s,
        )
        return times, np.atleast_2d(translation.at(np.maximum(times - self.release_s, 0.0))[0])

    @property
    def n_frames(self) -> int:
        """Number of frames: ``duration * rate`` (rounded), or ranges x frames_per_range."""
        if self.static_ranges_m:
            return len(self.static_ranges_m) * self.frames_per_range
        return max(1, int(round(self.duration_s * self.rate_hz)))

    @property
    def span_s(self) -> float:
        """Time of the last frame, s (frame i is at ``i / rate_hz``)."""
        return (self.n_frames - 1) / self.rate_hz

    def with_duration(self, duration_s: float) -> Scenario:
        """The same scenario cut (or extended) to ``duration_s``; static ranges keep all ranges
        with fewer frames each."""
        if not 0 < duration_s <= MAX_DURATION_S:
            raise TrackmeterError(f"duration must be positive and at most {MAX_DURATION_S:g} s (an hour), got {duration_s:g}")
        if self.static_ranges_m:
            per = max(1, int(round(duration_s * self.rate_hz / len(self.static_ranges_m))))
            return dataclasses.replace(self, frames_per_range=per, duration_s=per * len(self.static_ranges_m) / self.rate_hz)
        return dataclasses.replace(self, duration_s=float(duration_s))


def resolve_scenario_path(name_or_path: str | Path) -> Path:
    """A scenario file: an existing path, else ``config/scenarios/NAME[.yaml]``.

    Raises:
        TrackmeterError: neither exists (the message lists the known scenarios).
    """
    p = Path(name_or_path)
    if p.is_file():
        return p
    found = preset(p, SCENARIOS_DIR)
    if found is not None:
        return found
    raise TrackmeterError(f"no scenario {str(name_or_path)!r} (a file, or one of: {', '.join(preset_names(SCENARIOS_DIR))})")


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Read and validate a scenario file (a path or a name in ``config/scenarios/``).

    ``rig`` and ``mockup`` are resolved at load time (the scenario's own folder first, then
    ``config/rigs/`` / ``config/models/``) and stored as absolute paths.

    Raises:
        TrackmeterError: missing file, malformed YAML, an unknown key, a wrong type or range,
            an unphysical inertia, a rig or mock-up file that does not exist; the message names
            the file and the dotted key.
    """
    path = resolve_scenario_path(name_or_path)
    data = read_yaml_mapping(path, kind="a scenario file")
    if not data:
        warnings.warn(f"{path}: no settings: every one is the default (is it the scenario meant?)", stacklevel=2)
    data.setdefault("name", path.stem)
    scenario: Scenario = build_dataclass(Scenario, data, source=str(path))
    try:
        rig = _resolve(scenario.rig, path.parent, RIGS_DIR, "rig")
        mockup = _resolve(scenario.mockup, path.parent, MODELS_DIR, "mockup")
    except TrackmeterError as exc:
        raise TrackmeterError(f"{path}: {exc}") from None
    return dataclasses.replace(scenario, rig=str(rig.resolve()), mockup=str(mockup.resolve()))


def _resolve(name: str, base: Path | None, default_dir: Path, key: str) -> Path:
    p = Path(name)
    candidates = [p] if p.is_absolute() else ([base / p] if base is not None else []) + [default_dir / p, p]
    for c in candidates:
        if c.is_file():
            return c
    where = ", ".join(dict.fromkeys(str(c.parent) for c in candidates))  # each folder once
    raise TrackmeterError(f"'{key}': no such file {name!r} (looked in {where})")


def rig_path(scenario: Scenario) -> Path:
    """The scenario's rig file (absolute after :func:`load_scenario`, else in ``config/rigs/``)."""
    return _resolve(scenario.rig, None, RIGS_DIR, "rig")


def mockup_path(scenario: Scenario) -> Path:
    """The scenario's mock-up file (absolute after :func:`load_scenario`, else in ``config/models/``)."""
    return _resolve(scenario.mockup, None, MODELS_DIR, "mockup")
