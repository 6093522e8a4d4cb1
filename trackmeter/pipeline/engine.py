"""The tracking thread's whole per-frame logic: tracker step, pose, velocities, filter, recovery.

No threads and no I/O here: :class:`trackmeter.pipeline.pipeline.Pipeline` owns one
:class:`Engine` on its tracking thread and calls :meth:`Engine.process` for every frame and
:meth:`Engine.handle` for every command; ``trackmeter track`` and the benchmarks call it the
same way, or directly.

Per frame (:meth:`Engine.process`):

1. ``tracker.step(frame, reject_ids)`` — ``reject_ids`` are last frame's pose outliers, which
   the tracker marks lost.
2. The model: body-frame coordinates of tracked points, by id. Case (b): the a-priori model
   (fixed) plus grown points; case (a): built from the first three well-spread points (paper
   section 2.C: origin at point 1, x toward point 2, xy-plane through point 3; output origin
   at their centroid) and every point tracked at that moment; case (c): points averaged while
   the object was held still (:class:`~trackmeter.pipeline.snapshot.AcquireModel`), frame =
   the camera frame at that time, origin at their centroid.
3. Pose: robust generalised least squares over every measured model point
   (:func:`trackmeter.core.pose.robust_pose`); fewer than ``pose.min_points`` gives an invalid
   pose with the reason — never a made-up one. Outliers go to ``reject_ids``.
4. Model upkeep while the pose is known: measured (not a-priori) model points are averaged
   (information-weighted) so the model sharpens as the body turns; new targets consistent for
   ``join_after_frames`` frames join the model with their body coordinates from the pose, so
   the model grows as new faces come into view (paper 2.D). With ``pose.slide_sigma_m_per_sqrt_s``
   a grown point is a random walk on the surface (a tracked pixel wanders): its covariance grows
   with the time since its last refinement, so it follows its target and weighs less in the pose.
   Losing one of the three frame points of case (a) changes nothing: the frame lives on in the
   model (no jump). Case (b) with ``pose.anchor_time_s`` > 0: the a-priori points seen reveal how far the grown model's
   frame has drifted from theirs, and the grown model is moved back (:meth:`Engine._anchor`).
5. Velocities (:mod:`trackmeter.core.velocity`) from the raw poses, then the output filter
   (:mod:`trackmeter.core.output_filter`).
6. Recovery (paper 2.D): lost model points are reprojected through the current pose
   (``rig.project``) and re-locked with ``tracker.relock_many``; a-priori model points without a
   target are measured at their projection (``tracker.add_target(origin="model")``). A
   re-locked point whose 3D position disagrees with the pose is rejected at once. Without a
   model the tracker itself looks again where a target was lost.
7. Errors against ``frame.truth`` (cases a and c: after an online body alignment, the chordal
   mean of ``T_true^-1 T_est`` (``T_bodytrue_bodyest``) so far — the same constant offset
   ``evaluate --align body`` fits over the whole run).
"""

from __future__ import annotations

import warnings
from collections import deque
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple, Sequence, TypedDict, cast

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from trackmeter.core.dynamics import coast_pose, fit_centre_of_mass
from trackmeter.core.exposure import ExposureParams, expose_pair
from trackmeter.core.features import corners_near
from trackmeter.core.output_filter import FilterParams, PoseFilter
from trackmeter.core.patch_tracking import plane_jacobian
from trackmeter.core.pose import (
    PoseFit,
    PoseParams,
    choose_frame_points,
    fuse_point_correlated,
    handover_offset,
    hold_frame,
    position_jacobians,
    robust_pose,
    solve_pose,
    three_point_body_frame,
    to_body,
)
from trackmeter.core.stereo import StereoRig
from trackmeter.core.targets import Refusal, TargetState, count_reasons
from trackmeter.core.transforms import (attitude_error_components, make_transform, matrix_to_quat_wxyz,
                                       procrustes_rotation, skew)
from trackmeter.core.velocity import VelocityEstimator, VelocityParams, block_weights
from trackmeter.errors import TrackmeterError, counted
from trackmeter.pipeline.snapshot import (
    AcquireModel,
    ClearTargets,
    Command,
    CommandReply,
    LoadModel,
    ModelCase,
    PoseEstimate,
    RemoveNearest,
    RemoveTarget,
    ResetTracking,
    SelectPoint,
    SetAuto,
    SetCase,
    SetFilterCutoff,
)
from trackmeter.sources.base import StereoFrame

if TYPE_CHECKING:
    from trackmeter.core.tracking import StoredTarget

FloatArray = NDArray[np.float64]


#: The reply of :class:`SelectModelPoints` on a frame without ground truth (a source that has
#: none never will: the command cannot start a target there).
NEEDS_TRUTH = "selecting model points needs a frame with ground truth (a simulated source, or a recording with its truth)"
NEEDS_CASE_B = "selecting model points needs case (b) with a model"
#: The end of case (b)'s pose reason while no target names a model point: nothing binds the
#: model until one does (the console adds where its controls for it are).
MODEL_NOT_TARGETED = "none is a target yet: target them by id"
#: Said on the pose line of a frame where the repeating simulated operator clicked: the pose
#: was computed before, its targets are measured from the next frame on.
CLICKED_NOW = "the model points in view were clicked again at this frame"


def _pixel(u: float, v: float) -> str:
    """``(u, v)`` to a tenth of a pixel, as replies quote a click; a click on the border
    (-0.04) reads 0.0, not "-0.0"."""

    def tenth(x: float) -> str:
        text = f"{x:.1f}"
        return "0.0" if text == "-0.0" else text

    return f"({tenth(u)}, {tenth(v)})"


@dataclass(frozen=True, eq=False)
class SelectModelPoints(Command):
    """Simulated operator (case b on a source with ground truth): create a target at the TRUE
    projection of every model point that falls inside both images of the frame, named by its
    model id — what an operator does by clicking the model's points. A point the operator
    cannot see is not clicked: one whose stereo measurement lies farther than
    ``pose.operator_hidden_m`` from its true position is hidden behind another surface (with
    only three model points, a hidden one measured on the wrong surface cannot be told from
    the others by the pose's outlier test).

    ``repeat``: the operator keeps watching, as at the console: whenever the pose has been
    invalid for ``pose.operator_reselect_s`` (e.g. too few model points in view at the start,
    or all lost in a dark spell), the visible model points not tracked are clicked again."""

    repeat: bool = False


_NO_POSE_ERROR = np.zeros((3, 6))


@dataclass
class _ModelPoint:
    b: FloatArray  # (3,) body frame, m
    cov: FloatArray  # (3,3) m², total (cm + L L^T); zeros for an a-priori point
    fixed: bool  # a-priori: never refined
    cm: FloatArray | None = None  # (3,3) m², the independent (measurement) part; None: all of cov
    L: FloatArray = field(default_factory=lambda: _NO_POSE_ERROR)  # (3,6) pose-error factor, m
    t_s: float = 0.0  # time of the last refinement (the slide since adds pose.slide_sigma_m_per_sqrt_s), s


@dataclass
class _Candidate:
    b: FloatArray
    cov: FloatArray
    cm: FloatArray
    L: FloatArray
    count: int = 1


class _Motion(NamedTuple):
    """A pose with its rates, the start of a coast: ``t_s`` s, ``R`` (3,3) R_cam_body, ``p``
    (3,) m in the camera, ``cov`` (6,6) (position m, rotation vector rad), ``v`` (3,) m/s in the
    camera, ``omega`` (3,) rad/s in the body frame."""

    t_s: float
    R: FloatArray
    p: FloatArray
    cov: FloatArray
    v: FloatArray
    omega: FloatArray


@dataclass
class _Acquisition:
    """Case (c): points collected while the object is held still."""

    t_start: float | None = None
    points: dict[str, list[FloatArray]] = field(default_factory=dict)
    covs: dict[str, list[FloatArray]] = field(default_factory=dict)
    frames: int = 0
    #: The reason the last acquisition was started over (the object moved), said until this one
    #: has seen the object still: a restarted one cannot tell stillness for its first frames.
    moved: str | None = None


@dataclass
class EngineStats:
    """Counters since the start (or the last reset)."""

    frames: int = 0
    valid_frames: int = 0
    outliers_rejected: int = 0
    relock_attempts: int = 0
    recoveries: int = 0
    recoveries_rejected: int = 0
    model_points_joined: int = 0
    frames_redefined: int = 0
    operator_reselections: int = 0  # the repeating simulated operator clicked the model points again
    stream_cuts: int = 0  # frames after which the stream jumped (StereoFrame.cut): tracking started over
    models_bound_progressively: int = 0  # case (b): a-priori models bound through a provisional frame
    handovers_held: int = 0  # losses of measured points after which the survivors were moved (pose.handover_hold)
    stored_relocks: int = 0  # grown points re-locked on their own stored target (pose.relock_stored)
    frames_gained: int = 0  # underexposed frames brought up by a gain (config section exposure)
    largest_gain: float = 1.0  # the largest such gain

    def add_provisional(self, inner: EngineStats) -> None:
        """Add the events of a progressive binding's provisional engine (case (b)), which
        tracked on this one's behalf. Not its frames (this engine counted them), its valid
        frames (poses in its own frame, never output) or its exposure (this engine's, applied
        before the frames reach it): summed, they made run.yaml's valid frames outnumber the
        valid poses and the largest gain pass the exposure's max_gain."""
        for name, value in vars(inner).items():
            if name not in ("frames", "valid_frames", "frames_gained", "largest_gain"):
                setattr(self, name, getattr(self, name) + value)


def click_room(targets: Sequence[TargetState]) -> str | None:
    """The target an operator's click takes the place of when the target limit is reached: a
    lost one (automatic first, then the oldest), else the youngest automatic one (the least
    invested in: automatic selection makes another); None when every target is tracking and
    not automatic (the operator's own clicks and model points are not given up for a click)."""
    lost = [t for t in targets if t.status == "lost"]
    if lost:
        return min(lost, key=lambda t: (t.origin != "auto", -t.age_frames)).id
    auto = [t for t in targets if t.origin == "auto"]
    return min(auto, key=lambda t: t.age_frames).id if auto else None


class _ClickRoom(TypedDict, total=False):
    """The keywords of ``Tracker.add_target`` that make room for a target at the limit."""

    in_place_of: str | None  # the target it takes the place of (:func:`click_room`)
    replace_lost: bool


class Engine:
    """Tracker + motion estimation for one stream (see the module docstring).

    Args:
        config: the whole configuration (sections ``tracker``, ``features``, ``measure``,
            ``pose``, ``velocity``, ``output_filter``, ``exposure``; missing sections take
            their defaults).
        rig: the stereo rig of the frames.
        model: an a-priori model (case b), bound to targets by id.
        case: ``"a"``, ``"b"`` or ``"c"``; default ``"b"`` with a model, else ``"a"``.
        tracker: a tracker to use instead of building
            :class:`trackmeter.core.tracking.Tracker` from the config (tests inject doubles).
        rate_hz: the source's frame rate, Hz (25 when None): the output filter is designed
            for it, and ``pose.apriori_remake_after_s`` is counted in frames at it.
        live_errors: compute each pose's errors against the frame's ground truth when it has
            one (the console's error plots); a caller that never reads them (``track``, whose
            run directory holds no errors: ``evaluate`` computes them afterwards) saves the work.

    Raises:
        TrackmeterError: case ``"b"`` without a model.
    """

    def __init__(
        self,
        config: Any,
        rig: StereoRig,
        model: Any | None = None,
        case: ModelCase | None = None,
        *,
        tracker: Any | None = None,
        rate_hz: float | None = None,
        live_errors: bool = True,
    ) -> None:
        self.config = config
        self.rig = rig
        self.pose_params: PoseParams = getattr(config, "pose", None) or PoseParams()
        self.velocity_params: VelocityParams = getattr(config, "velocity", None) or VelocityParams()
        self.filter_params: FilterParams = getattr(config, "output_filter", None) or FilterParams()
        self.exposure_params: ExposureParams = getattr(config, "exposure", None) or ExposureParams()
        self.gain = 1.0  # the exposure gain of the last frame processed
        self._exposed_last: tuple[StereoFrame, StereoFrame] | None = None  # (as delivered, as tracked)
        if tracker is None:
            from trackmeter.core.features import FeatureParams
            from trackmeter.core.matching import MeasureParams
            from trackmeter.core.tracking import Tracker, TrackerParams

            tracker = Tracker(
                rig,
                getattr(config, "tracker", None) or TrackerParams(),
                getattr(config, "features", None) or FeatureParams(),
                getattr(config, "measure", None) or MeasureParams(),
            )
        self.tracker = tracker
        from trackmeter.core.tracking import TrackerParams

        # Re-made targets of grown model points follow the tracker's rules for automatic ones:
        # dropped after lost_keep_frames, and never into the room the operator needs.
        tracker_params = getattr(config, "tracker", None) or TrackerParams()
        self._lost_keep_frames = tracker_params.lost_keep_frames
        self._max_targets = tracker_params.max_targets
        self._click_snap_px = float(tracker_params.click_snap_px)
        self._patch_px = int(tracker_params.patch_size)
        self.rate_hz = float(rate_hz) if rate_hz else 25.0
        if self.filter_params.cutoff_hz > self.max_filter_cutoff_hz:
            # design_lowpass clips it, so it filters at that; a console field shows it clipped
            warnings.warn(f"output_filter.cutoff_hz {self.filter_params.cutoff_hz:g} Hz is above the "
                          f"{self.max_filter_cutoff_hz:g} Hz the filter takes at {self.rate_hz:g} frames a second "
                          f"(0.95 of Nyquist): it filters at {self.max_filter_cutoff_hz:g} Hz", stacklevel=2)
        self.live_errors = bool(live_errors)
        chosen: ModelCase = case or ("b" if model is not None else "a")
        if chosen not in ("a", "b", "c"):
            raise TrackmeterError(f"model case must be a, b or c, got {chosen!r}")
        if chosen == "b" and model is None:
            raise TrackmeterError("case (b) needs an a-priori model (a model file, or a source that carries one)")
        self._given_model = model
        if model is not None:
            self.tracker.reserve_ids(model.ids)
        self._case: ModelCase = chosen
        self._gate = float(chi2.ppf(self.pose_params.outlier_probability, 3))
        self.stats = EngineStats()
        # Case (c) from the start acquires at once, as when it is chosen later (SetCase).
        self._acquisition: _Acquisition | None = self._fresh_acquisition()
        self._operator_t: float | None = None  # the repeating simulated operator's last clicks, s
        # Model points never forgotten for room (a provisional frame's a-priori points, located
        # one at a time, must all still be there when the model is bound).
        self._keep_ids: frozenset[str] = frozenset()
        self._body_frame = 0  # counts the body frames defined: each _reset_motion starts one
        self._reset_motion()

    # ------------------------------------------------------------------ read-only state

    @property
    def case(self) -> ModelCase:
        return self._case

    @property
    def auto_enabled(self) -> bool:
        return bool(self.tracker.auto[0])

    @property
    def auto_count(self) -> int:
        return int(self.tracker.auto[1])

    @property
    def auto_method(self) -> str:
        return str(self.tracker.auto[2])

    @property
    def auto_shortfall(self) -> str | None:
        """Why automatic selection's last top-up started no target (``Tracker.auto_shortfall``)."""
        why = getattr(self.tracker, "auto_shortfall", None)
        return str(why) if why else None

    @property
    def max_targets(self) -> int:
        """Most targets tracked at once (``tracker.max_targets``): automatic ones included."""
        return self._max_targets

    @property
    def filter_cutoff_hz(self) -> float:
        """The output filter's cutoff, Hz."""
        return float(self.filter_params.cutoff_hz)

    @property
    def min_filter_cutoff_hz(self) -> float:
        """Lowest cutoff the output filter takes (``FilterParams.cutoff_hz``'s declared minimum), Hz."""
        return float(next(f.metadata["min"] for f in fields(FilterParams) if f.name == "cutoff_hz"))

    @property
    def max_filter_cutoff_hz(self) -> float:
        """Highest cutoff the output filter takes at this frame rate (0.95 of Nyquist), Hz."""
        return 0.95 * 0.5 * self.rate_hz

    @property
    def targets(self) -> tuple[TargetState, ...]:
        """Every target as it stands now (lost ones included): after the last step and any
        command since, e.g. a click's new target, measured on the frame the operator clicked."""
        return tuple(self.tracker.targets)

    @property
    def model(self) -> Any | None:
        """The a-priori model (case b), or None."""
        return self._given_model

    @property
    def model_ids(self) -> tuple[str, ...]:
        """Ids of every point in the working model (a-priori, grown, acquired)."""
        return tuple(self._model)

    @property
    def model_points_body(self) -> FloatArray:
        """(N,3) body coordinates of the working model, in the order of :attr:`model_ids`."""
        return np.array([m.b for m in self._model.values()]).reshape(-1, 3)

    @property
    def frame_ids(self) -> tuple[str, ...]:
        """Case (a): the ids of the three points that define the body frame (empty before)."""
        return self._frame_ids

    @property
    def acquiring(self) -> bool:
        """Case (c): True while a model is being acquired."""
        return self._acquisition is not None

    # ------------------------------------------------------------------ state resets

    def _reset_motion(self) -> None:
        """Forget the working model, the pose history, the filter (not the targets): the next
        pose is in a body frame of its own (:attr:`PoseEstimate.body_frame`)."""
        self._body_frame += 1
        self._model: dict[str, _ModelPoint] = {}
        # The a-priori points' centroid (body frame, m) and rms distance from it: what the model's
        # drift turns the frame about, and by how much (_apriori_frame_report).
        self._apriori_centroid_m = np.zeros(3)
        self._apriori_radius_m = 0.0
        if self._case == "b" and self._given_model is not None:
            for pid, b in zip(self._given_model.ids, self._given_model.points_body):
                self._model[pid] = _ModelPoint(np.array(b, dtype=float), np.zeros((3, 3)), True)
            B0 = np.asarray(self._given_model.points_body, float)
            with np.errstate(over="ignore", invalid="ignore"):  # a model spanning 1e300 m is warned about where it is loaded
                self._apriori_centroid_m = B0.mean(axis=0)
                self._apriori_radius_m = float(np.sqrt(np.mean(np.sum((B0 - self._apriori_centroid_m) ** 2, axis=1))))
        self._frame_ids: tuple[str, ...] = ()
        # Model points whose target the operator removed: kept in the model (an a-priori point, a
        # case (a) frame point) but not looked for again, until a click names them again.
        self._operator_removed: set[str] = set()
        self._candidates: dict[str, _Candidate] = {}
        self._pending_reject: set[str] = set()
        self._last_fit: tuple[FloatArray, FloatArray, FloatArray] | None = None
        self._last_valid_t: float | None = None
        self._last_attempt: dict[str, int] = {}
        self._seen_t: dict[str, float] = {}
        self._frame_t_s = 0.0  # time of the frame being processed, s
        self._lost_since: dict[str, int] = {}  # target id -> frame index it was first seen lost
        # pose.relock_stored: the dropped targets of grown model points, whole, with the pose of
        # the last frame each was measured in (id -> (StoredTarget, (R, t) or None)), and that
        # pose for every model point measured (id -> (R, t)).
        self._stored: dict[str, tuple[Any, tuple[FloatArray, FloatArray] | None]] = {}
        self._pose_when_seen: dict[str, tuple[FloatArray, FloatArray]] = {}
        # The last measured pose and its raw rates, for the constant-twist carry of recovery and
        # the out-of-view check (_carried_pose).
        self._last_measured: _Motion | None = None
        self._left_view = False  # the body was last seen moving out of view (_out_of_view)
        self._gone_from_view = False  # ... and case (a)'s frame was given up since (_establish_frame)
        # The last output (filtered) pose with settled rates, where the reported coast starts
        # (_coast_state: core.dynamics.coast_pose).
        self._last_output: _Motion | None = None
        self._com_cache: tuple[float, float | None] | None = None
        # Measured poses (t, R, p, position weight) for the centre-of-mass fit, this body frame.
        self._com_history: deque[tuple[float, FloatArray, FloatArray, float]] = deque()
        self._frame_move: tuple[FloatArray, FloatArray] | None = None  # set by _anchor, see _move_history
        # Whether the last output was coasted, and the offset being blended out after a coast.
        self._coasting = False
        self._blend: tuple[float, FloatArray, FloatArray] | None = None
        # Model points whose body coordinates share one rigid error of the frame they were
        # carried into (joined through a coasted pose, carried into the a-priori frame by a
        # binding, or joined through a pose resting on such points), and that error, (6,6).
        self._frame_error_ids: set[str] = set()
        self._frame_cov: FloatArray | None = None
        # The last frame error independently located a-priori points determined: (time s, (6,6)
        # in the body frame), reported with the drift since (_apriori_frame_report).
        self._apriori_frame_anchor: tuple[float, FloatArray] | None = None
        # The points a progressive binding carried and its error with the corners' own (_bind).
        self._binding_ids: set[str] = set()
        self._binding_cov_reported: FloatArray | None = None
        self._shared_frame_report = np.zeros((6, 6))  # reported on top of the fit's (_note_shared_frame_error)
        self._velocity = VelocityEstimator(self.velocity_params, self.pose_params.coast_lever_m)
        self._filter = PoseFilter(self.filter_params, self.rate_hz)
        self._align_M = np.zeros((3, 3))
        self._align_t = np.zeros(3)
        self._align_n = 0
        self._anchor_H = np.zeros((6, 6))
        self._anchor_g = np.zeros(6)
        self._anchor_t: float | None = None
        # pose.handover_hold: running mean of each inlier's body-frame residual and its last
        # measurement's covariance in the body frame (id -> ((3,) m, (3,3) m²)), the time of their
        # last update, and the inliers of the last fit (None: no fit last frame).
        self._residual_mean: dict[str, tuple[FloatArray, FloatArray]] = {}
        self._residual_t: float | None = None
        self._prev_inliers: set[str] | None = None
        # Case (b) progressive binding: whether a pose in the a-priori frame was ever had (or the
        # model was bound), and the provisional case-(a) engine tracking until then.
        self._bound = False
        self._provisional: Engine | None = None

    # ------------------------------------------------------------------ commands

    def handle(self, command: Command, frame: StereoFrame | None) -> CommandReply:
        """Apply one command; ``frame`` is the last processed frame (the one the operator saw)."""
        try:
            return self._handle(command, self._exposed(frame) if frame is not None else None)
        except TrackmeterError as exc:
            return CommandReply(False, str(exc))

    def _exposed(self, frame: StereoFrame, count: bool = False) -> StereoFrame:
        """``frame`` as the tracker sees it: an underexposed pair multiplied by its exposure gain
        (:mod:`trackmeter.core.exposure`), else ``frame`` itself. A command on the frame just
        processed gets the same images (kept, not recomputed); ``count``: a frame processed."""
        last = self._exposed_last
        if last is not None and last[0] is frame:
            return last[1]
        left, right, gain = expose_pair(frame.left, frame.right, self.exposure_params)
        exposed = frame if gain == 1.0 else replace(frame, left=left, right=right)
        if count:
            self.gain = gain
            self.stats.frames_gained += gain > 1.0
            self.stats.largest_gain = max(self.stats.largest_gain, gain)
        self._exposed_last = (frame, exposed)
        return exposed

    def _snap_click(self, frame: StereoFrame, command: SelectPoint, refusal: Refusal, room: dict[str, Any]
                    ) -> tuple[TargetState | Refusal, float, str]:
        """An unnamed point refused where it is: a target on the nearest trackable corner within
        ``tracker.click_snap_px`` (:func:`trackmeter.core.features.corners_near`), how far it
        moved (px) and the note saying so and why; else the refusal as it was, 0, ""."""
        if self._click_snap_px <= 0 or refusal.reason.startswith(("target limit", "outside image")):
            return refusal, 0.0, ""
        for corner in corners_near(frame.left, (command.u, command.v), self._click_snap_px):
            if self._target_at((float(corner[0]), float(corner[1]))) is not None:
                continue  # tracked already
            result = self.tracker.add_target(frame, (float(corner[0]), float(corner[1])), None, "operator", **room)
            if not isinstance(result, Refusal):
                moved = float(np.hypot(corner[0] - command.u, corner[1] - command.v))
                return result, moved, f", moved {moved:.1f} px to a trackable corner (where asked: {refusal.reason})"
        return refusal, 0.0, ""

    def _target_at(self, uv: tuple[float, float]) -> tuple[str, float] | None:
        """The operator's (or a model point's) tracked target whose patch centre lies within
        half a patch of ``uv`` (id, px), if any: a new unnamed target there would track the same
        patch twice. An automatic target does not count: a click on it is the operator taking
        that point for their own (kept whatever automatic selection does)."""
        reach = 0.5 * self._patch_px
        best: tuple[str, float] | None = None
        for t in self.tracker.targets:
            if t.origin == "auto" or t.status == "lost" or not np.all(np.isfinite(t.uv)):
                continue
            d = float(np.hypot(t.uv[0] - uv[0], t.uv[1] - uv[1]))
            if d <= reach and (best is None or d < best[1]):
                best = (t.id, d)
        return best

    def _handle(self, command: Command, frame: StereoFrame | None) -> CommandReply:
        if isinstance(command, SelectPoint):
            if frame is None:
                return CommandReply(False, "no frame yet")
            there = self._target_at((command.u, command.v)) if command.target_id is None else None
            if there is not None:
                return CommandReply(False, f"refused at {_pixel(command.u, command.v)}: target {there[0]} is "
                                           f"already there ({there[1]:.1f} px away)")
            states = self.tracker.targets
            # Clicked where the lost one of its name should be: it makes way once the new one is
            # made, as for the model points' click (its name was refused: "a target named ...
            # exists", where none is drawn), and a refused click costs no target.
            named = next((t for t in states if t.id == command.target_id), None) if command.target_id else None
            replacing = named is not None and named.status == "lost"
            # So does one the engine made at the point's projection through the pose (_remake): it
            # repeats the pose's error across the line of sight, which the operator's click does
            # not (docs/results.md, "How honest the pose covariance is").
            remade = named is not None and not replacing and named.origin == "model"
            # At the limit the click takes a lost or automatic target's place (kept otherwise).
            room: dict[str, Any] = ({"replace_lost": True} if replacing else {"replace_remade": True} if remade else
                                    {"in_place_of": click_room(states)} if len(states) >= self._max_targets else {})
            if "in_place_of" in room and room["in_place_of"] is None:
                return CommandReply(False, f"refused at {_pixel(command.u, command.v)}: target limit reached "
                                           f"({counted(self._max_targets, 'target')}, all the operator's or model points "
                                           "and tracking): remove one (shift-click it) first")
            result = self.tracker.add_target(frame, (command.u, command.v), command.target_id, "operator", **room)
            moved_px, note = 0.0, ""
            if isinstance(result, Refusal) and command.target_id is None:
                result, moved_px, note = self._snap_click(frame, command, result, room)
            if isinstance(result, Refusal):
                return CommandReply(False, f"refused at {_pixel(command.u, command.v)}: {result.reason}")
            if "in_place_of" in room:
                gone = next(t for t in states if t.id == room["in_place_of"])
                note += (f" (in place of {'lost ' if gone.status == 'lost' else ''}"
                         f"{'automatic' if gone.origin == 'auto' else gone.origin} target {gone.id}: "
                         f"{self._max_targets} is the limit)")
            if remade:
                note += " (in place of the target made at its projection through the pose)"
            if self._case == "b" and command.target_id is not None and command.target_id not in self._model:
                note += " (not a model point: it joins the model once the pose is known)"
            self._operator_removed.discard(result.id)  # named again: looked for again when lost
            return CommandReply(True, f"target {result.id} at {result.point_cam[2]:.3f} m{note}", result.id, moved_px)
        if isinstance(command, SelectModelPoints):
            reply = self._select_model_points(frame)
            # Not armed where clicking again cannot help (no case (b)): a later switch to it
            # would start clicks nobody asked for then.
            watch = command.repeat and reply.message != NEEDS_CASE_B
            self._operator_t = (frame.t_s if frame is not None else 0.0) if watch else None
            if watch and reply.message == NEEDS_TRUTH:
                # A recording's truth may start after its first frame: click at the first frame
                # that has it, not operator_reselect_s after this one.
                self._operator_t = -np.inf
            if watch and not reply.ok and reply.message != NEEDS_TRUTH:
                # Refused now is not refused for good: say that it goes on.
                return replace(reply, message=f"{reply.message}; clicked again after each "
                                              f"{self.pose_params.operator_reselect_s:g} s without a pose")
            return reply
        if isinstance(command, RemoveTarget):
            if not self.tracker.remove_target(command.target_id):
                return CommandReply(False, f"no target {command.target_id!r}")
            self._forget(command.target_id)
            return CommandReply(True, f"removed {command.target_id}", command.target_id)
        if isinstance(command, RemoveNearest):
            tid = self.tracker.remove_nearest((command.u, command.v), exclude=command.exclude)
            if tid is None:
                from trackmeter.core.tracking import REMOVE_NEAREST_PX

                return CommandReply(False, f"no target within {REMOVE_NEAREST_PX:g} px of {_pixel(command.u, command.v)}")
            self._forget(tid)
            return CommandReply(True, f"removed {tid}", tid)
        if isinstance(command, ClearTargets):
            self.tracker.clear()
            self._operator_t = None
            # Case (c): the points being averaged went with the targets; acquire the next ones.
            self._acquisition = self._fresh_acquisition()
            self._reset_motion()
            return CommandReply(True, "all targets removed" + (
                "; the model acquisition starts again: hold the object still" if self._acquisition else ""))
        if isinstance(command, SetAuto):
            self.tracker.set_auto(command.enabled, command.count, command.method)
            enabled, count, method = self.tracker.auto
            # The centroid method finds one point a bright region (paper 2.B), whatever the count.
            how = f"{method}: one a bright region, its centroid" if method == "centroid" else method
            return CommandReply(True, f"automatic selection {'on' if enabled else 'off'} ({counted(count, 'target')}, {how})",
                                notable=enabled and method == "centroid")
        if isinstance(command, SetCase):
            if command.case not in ("a", "b", "c"):
                return CommandReply(False, f"unknown model case {command.case!r} (a, b or c)")
            if command.case == "b" and self._given_model is None:
                return CommandReply(False, "case (b) needs an a-priori model: load one first")
            self._case = command.case
            self._acquisition = self._fresh_acquisition()
            self._reset_motion()
            if command.case != "b":
                self._operator_t = None  # it clicks case (b)'s model points: nothing to click now
            extra = ": hold the object still to acquire the model" if command.case == "c" else ""
            return CommandReply(True, f"model case ({command.case}){extra}")
        if isinstance(command, AcquireModel):
            # An acquired model is case (c)'s: from another case, say so (the case selector
            # changes under the operator's eyes, and case (b)'s buttons then refuse).
            switched = "" if self._case == "c" else f" (model case ({self._case}) -> (c))"
            self._case = "c"
            self._acquisition = _Acquisition()
            self._reset_motion()
            self._operator_t = None  # it clicks case (b)'s model points: nothing to click now
            return CommandReply(True, f"acquiring a model: hold the object still for {self.pose_params.still_time_s:g} s"
                                      f"{switched}")
        if isinstance(command, LoadModel):
            from trackmeter.data.model import load_model

            if not command.path.strip():
                return CommandReply(False, "no model file given")
            # Absolute: a name is looked for where the server runs, which the operator's
            # browser does not show; the answer says where.
            path = Path(command.path.strip()).expanduser().absolute()
            with warnings.catch_warnings(record=True) as said:
                warnings.simplefilter("always")
                model = load_model(path)
            # catch_warnings is process-wide: another thread's warning in these milliseconds is
            # given on as well (and named in the answer), not lost.
            for w in said:  # on the server's stderr as before, and in the answer
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
            self._given_model = model
            self.tracker.reserve_ids(model.ids)
            self._case = "b"
            self._acquisition = None
            self._reset_motion()
            notes = "".join(f"; {str(w.message).removeprefix(f'{path}: ')}" for w in said)
            # A target is bound to the model point of its name: those the engine named as the
            # model names its points (a1, p2, ...) are elsewhere on the body.
            clash = sorted(self.tracker.generated_ids() & set(model.ids))
            for tid in clash:
                self.tracker.remove_target(tid)
            if clash:
                notes += f"; removed {counted(len(clash), 'target')} named as its points ({', '.join(clash)})"
            return CommandReply(True, f"model with {len(model)} points loaded: case (b){notes}", notable=bool(notes))
        if isinstance(command, SetFilterCutoff):
            # The low end is FilterParams.cutoff_hz's declared minimum, which building the
            # params checks too: said here in the operator's words.
            low = self.min_filter_cutoff_hz
            if not low <= command.cutoff_hz <= self.max_filter_cutoff_hz:
                return CommandReply(False, f"filter cutoff must be in [{low:g}, {self.max_filter_cutoff_hz:g}] Hz "
                                           f"(0.95 of half the {self.rate_hz:g} Hz frame rate), got {command.cutoff_hz:g}")
            self.filter_params = replace(self.filter_params, cutoff_hz=float(command.cutoff_hz))
            self._filter = self._filter.retuned(self.filter_params)  # on from its last output, no step
            if not self.filter_params.enabled:
                return CommandReply(True, f"output filter cutoff {command.cutoff_hz:g} Hz, but the filter is off "
                                          "(output_filter.enabled: false): the output is the unfiltered pose", notable=True)
            return CommandReply(True, f"output filter cutoff {command.cutoff_hz:g} Hz")
        if isinstance(command, ResetTracking):
            self._start_over()
            self._operator_t = None
            self.stats = EngineStats()
            return CommandReply(True, "tracking reset")
        return CommandReply(False, f"{type(command).__name__} is not an engine command")

    def _select_model_points(self, frame: StereoFrame | None) -> CommandReply:
        if frame is None or frame.truth is None:
            return CommandReply(False, NEEDS_TRUTH)
        if self._given_model is None or self._case != "b":
            return CommandReply(False, NEEDS_CASE_B)
        T = np.asarray(frame.truth.T_cam_body, float)
        X = self._given_model.points_body @ T[:3, :3].T + T[:3, 3]
        uv_l, uv_r = self.rig.project(X)
        w, h = self.rig.image_size
        m = self.pose_params.recovery_margin_px
        states = {s.id: s for s in self.tracker.targets}
        made, refused, hidden, already = [], [], [], []
        for pid, x, ul, ur in zip(self._given_model.ids, X, uv_l, uv_r):
            inside = x[2] > 0 and all(m <= u[0] <= w - 1 - m and m <= u[1] <= h - 1 - m for u in (ul, ur))
            if pid in states and states[pid].status != "lost":
                already.append(pid)  # said: "0 selected" beside them in the target list read as a contradiction
                continue
            if not inside:
                continue
            if pid in states:
                # Clicked again where the lost one should be: it goes, even if the click is
                # refused. Kept, a lost model point's target is re-locked on its old templates,
                # which the turned faces and the glints no longer match: on harsh_light case (b)
                # (the repeating operator, 2026-12-07) the largest lateral error rose from 6.8 to
                # 21.4 mm; dropped, the engine re-makes it at its projection through the pose.
                self.tracker.remove_target(pid)
            # At the limit a model point takes a lost or automatic target's place, as a click does.
            now = self.tracker.targets
            room: _ClickRoom = {"in_place_of": click_room(now)} if len(now) >= self._max_targets else {}
            result = (Refusal((float(ul[0]), float(ul[1])), f"target limit reached ({self._max_targets} targets)")
                      if room and room["in_place_of"] is None
                      else self.tracker.add_target(frame, (float(ul[0]), float(ul[1])), pid, "operator", **room))
            if isinstance(result, Refusal):
                refused.append(result.reason)
            elif not np.linalg.norm(np.asarray(result.point_cam, float) - x) <= self.pose_params.operator_hidden_m:
                self.tracker.remove_target(pid)
                hidden.append(pid)
            else:
                made.append(pid)
                self._operator_removed.discard(pid)
        targeted = len(made) + len(already)
        ok = targeted >= self.pose_params.min_points
        why = count_reasons(refused)
        return CommandReply(ok, partial=0 < targeted < self.pose_params.min_points,
                            message=f"{counted(len(made), 'model point')} selected" + (f" ({', '.join(made)})" if made else "")
                                + (f"; {len(already)} already {'a target' if len(already) == 1 else 'targets'} ({', '.join(already)})" if already else "")
                                + f"; {len(refused)} refused" + (f" ({', '.join(f'{n} {r}' for r, n in why)})" if why else "")
                                + (f"; {len(hidden)} hidden ({', '.join(hidden)})" if hidden else ""))

    def _operator_watch(self, frame: StereoFrame) -> bool:
        """The repeating simulated operator (:class:`SelectModelPoints` ``repeat``): clicks the
        visible model points again once the pose has been invalid for ``operator_reselect_s``.
        Returns whether it clicked: the frame's targets and pose line must then show it (paused,
        that frame stays on screen)."""
        if self._operator_t is None or frame.truth is None:
            return False
        last = max(self._operator_t, self._last_valid_t if self._last_valid_t is not None else -np.inf)
        if frame.t_s - last < self.pose_params.operator_reselect_s:
            return False
        self._operator_t = frame.t_s
        self.stats.operator_reselections += 1
        self._select_model_points(frame)
        return True

    def _fresh_acquisition(self) -> _Acquisition | None:
        """A model acquisition starting now in case (c) (the points held still from here on),
        None in the other cases."""
        return _Acquisition() if self._case == "c" else None

    def _start_over(self) -> None:
        """Drop every target, the working model and the motion history; the settings (case,
        given model, automatic selection, the simulated operator) stay."""
        self.tracker.clear()
        self._acquisition = self._fresh_acquisition()
        self._reset_motion()
        if self._operator_t is not None:
            # A new stream's clock starts again: its first frame would wait for the time of
            # the last clicks to come round again (a Restart at 40 s: 40 s without a pose).
            self._operator_t = -np.inf

    def _forget(self, target_id: str) -> None:
        """A target the operator removed: drop its measured model point and candidacy."""
        point = self._model.get(target_id)
        if point is not None and not point.fixed and target_id not in self._frame_ids:
            del self._model[target_id]
        elif point is not None:  # kept in the model, so as not to move the frame: not re-targeted
            self._operator_removed.add(target_id)
        self._candidates.pop(target_id, None)
        self._stored.pop(target_id, None)
        self._pending_reject.discard(target_id)  # else a new click of that name is lost at the next step
        inner = self._provisional
        if inner is not None and self._given_model is not None and target_id in inner.frame_ids \
                and target_id in self._given_model.ids:
            # A model point defining the provisional frame, removed (a click under a wrong name,
            # perhaps): the frame keeps it where it was measured, and it would count as located
            # there, or, clicked again, be fitted against that place. The frame starts again
            # from the points tracked now; the located points are located in it anew.
            self.stats.add_provisional(inner.stats)
            self._provisional = None
        elif inner is not None:
            inner._forget(target_id)

    # ------------------------------------------------------------------ per frame

    def _a_priori_ids(self) -> frozenset[str]:
        """The a-priori model's point ids while the pose uses it (case (b)), else none: the
        targets the tracker keeps on the strict anchor fit (``Tracker.strict_anchor_ids``)."""
        if self._case == "b" and self._given_model is not None:
            return frozenset(self._given_model.ids)
        return frozenset()

    def process(self, frame: StereoFrame) -> tuple[tuple[TargetState, ...], PoseEstimate, dict | None]:
        """Track one frame; returns ``(targets, pose, errors)`` (see the module docstring)."""
        frame = self._exposed(frame, count=True)
        if frame.cut:
            # The scene jumped (a looping source's new pass, a restart): a model grown before
            # would re-lock onto whatever lies where its points were, and the coasted pose
            # would carry new points into it, so the body frame would change silently.
            self._start_over()
            self.stats.stream_cuts += 1
        reject = self._pending_reject
        self._pending_reject = set()
        # Set here, by the engine that steps the tracker: a provisional case-(a) engine shares it.
        self.tracker.strict_anchor_ids = self._a_priori_ids()
        targets = self.tracker.step(frame, reject_ids=reject)
        self.stats.frames += 1
        return self._after_step(frame, targets)

    def _after_step(self, frame: StereoFrame, targets: tuple[TargetState, ...]
                    ) -> tuple[tuple[TargetState, ...], PoseEstimate, dict | None]:
        """Everything after the tracker's step of ``frame`` (:meth:`process`)."""
        self._frame_t_s = frame.t_s
        if self._binding_pending():
            assert self._given_model is not None  # _binding_pending says so
            located_now = sum(1 for t in targets if t.measured and t.id in self._given_model.ids)
            if located_now < self.pose_params.min_points:
                return self._process_provisional(frame, targets)
        floor = self.pose_params.point_sigma_floor_m**2 * np.eye(3)
        measured = {
            t.id: replace(t, cov_cam=np.asarray(t.cov_cam, float) + floor) for t in targets
            if t.measured and np.all(np.isfinite(t.point_cam)) and np.all(np.isfinite(t.cov_cam))
        }
        self._forget_stale(frame, targets, measured)
        for pid in [p for p in self._candidates if p not in measured]:
            del self._candidates[pid]

        reason: str | None = None
        if self._last_valid_t is None and self._model and self._case == "a":
            self._last_valid_t = frame.t_s
        if self._case == "c" and self._acquisition is not None:
            reason = self._acquire(frame, measured)
        if self._case == "a" and not self._model:
            reason = self._establish_frame(measured)
        fit = None
        if reason is None:
            fit, reason = self._fit(frame, measured)
        if fit is None:
            pose = PoseEstimate.invalid(reason or "no pose", self._case)
            since = frame.t_s - (self._last_valid_t if self._last_valid_t is not None else frame.t_s)
            self._recovered_any = False
            coast = self._carried_pose(frame.t_s)
            if coast is not None and self.pose_params.recover_model_points:
                # Paper 2.D through a loss: the model points are where the motion carries them.
                self._recover(frame, *coast, carried=True)
            if since > self.velocity_params.bridge_gap_s:
                self._velocity.reset()
            if since > self.velocity_params.max_gap_s:
                self._filter.reset()
                self._last_fit = None
            rejoin = self._rejoin_through_coast(frame.t_s, measured)
            coasted = self._coasted_pose(frame.t_s, pose.reason or "no pose")
            if since > self.pose_params.redefine_after_s and not rejoin and coasted is None:
                if self._case == "a" and self._model:
                    # The frame's points are gone for good and the coast has run out: define a
                    # new frame from the points tracked now (a new body frame starts here).
                    gone = self._out_of_view(frame.t_s)
                    self._reset_motion()
                    self._gone_from_view = gone  # said while the new frame waits for points
                    self.stats.frames_redefined += 1
            clicked = self._operator_watch(frame)
            if clicked:
                pose = replace(pose, reason=f"{pose.reason}; {CLICKED_NOW}")
                coasted = None if coasted is None else replace(coasted, reason=f"{coasted.reason}; {CLICKED_NOW}")
            now = self.tracker.targets if self._recovered_any or clicked else targets
            if coasted is not None:
                self._coasting = True
                return now, coasted, self._errors(frame, coasted)
            self._coasting = False
            return now, pose, None
        R, t, cov, n_used, outliers = fit
        if self._provisional is not None:  # three a-priori points at once: bound without it
            self.stats.add_provisional(self._provisional.stats)
        self._bound, self._provisional = True, None
        self.stats.valid_frames += 1
        self._last_valid_t = frame.t_s
        rates = self._velocity.update(frame.t_s, R, t, cov)
        self._remember_for_com(frame.t_s, R, t, cov)
        self._move_history()
        v, w = rates if rates is not None else (np.full(3, np.nan), np.full(3, np.nan))
        self._last_measured = _Motion(frame.t_s, R, t, cov, np.asarray(v, float), np.asarray(w, float))
        self._left_view = False
        R_f, t_f = self._filter.update(frame.t_s, R, t, v if rates else None, w if rates else None)
        if not self._velocity.settled:  # provisional rates steer the filter but are not reported
            v, w = np.full(3, np.nan), np.full(3, np.nan)
        R_f, t_f, cov_out = self._blend_out(frame.t_s, R_f, t_f, cov)
        v_arr, w_arr = np.asarray(v, float), np.asarray(w, float)
        self._last_output = (_Motion(frame.t_s, R_f, t_f, cov_out, v_arr, w_arr)
                             if np.all(np.isfinite(v_arr)) and np.all(np.isfinite(w_arr)) else None)
        T = np.eye(4)
        T[:3, :3] = R_f
        T[:3, 3] = t_f
        # Reported only: the coast, its gates and the points joining through it work relative to
        # the model's frame, which every point shares (the frame's own error is common to them).
        cov_reported = cov_out + self._apriori_frame_report(frame.t_s, R) + self._shared_frame_report
        pose = PoseEstimate(True, None, self._case, T, cov_reported, v_arr, w_arr, n_used, tuple(outliers),
                            body_frame=self._body_frame)
        self._recovered_any = False
        if self.pose_params.recover_model_points:
            self._recover(frame, R, t, cov)
        errors = self._errors(frame, pose)
        return (self.tracker.targets if self._recovered_any else targets), pose, errors

    _recovered_any = False

    # ------------------------------------------------------------------ case (b): progressive binding

    def _binding_pending(self) -> bool:
        """Case (b) before its first pose in the a-priori frame, with ``pose.bind_progressively``."""
        return (self._case == "b" and not self._bound and self._given_model is not None
                and self.pose_params.bind_progressively)

    def _process_provisional(self, frame: StereoFrame, targets: tuple[TargetState, ...]
                             ) -> tuple[tuple[TargetState, ...], PoseEstimate, dict | None]:
        """Case (b) while fewer than ``min_points`` a-priori points are measured at once: a case-(a)
        engine on the same tracker carries a provisional body frame, and every a-priori point
        tracked joins its model like any point (located in that frame, averaged as it is seen
        again). Once ``min_points`` of them are located, :meth:`_bind` carries the provisional
        model into the a-priori frame. The output stays invalid until then, with the reason."""
        assert self._given_model is not None
        inner = self._provisional
        if inner is None:
            inner = Engine(self.config, self.rig, None, "a", tracker=self.tracker, rate_hz=self.rate_hz,
                           live_errors=False)
            inner._keep_ids = frozenset(self._given_model.ids)
            self._provisional = inner
        out_targets, _, _ = inner._after_step(frame, targets)
        # The next step's rejections are the provisional fit's outliers (this engine steps the tracker).
        self._pending_reject |= inner._pending_reject
        inner._pending_reject = set()
        need = self.pose_params.min_points
        located = [pid for pid in self._given_model.ids if pid in inner._model]
        reason = (f"case (b): binding the model: {len(located)} of its points located in a provisional frame "
                  f"({need} needed)")
        if not located and not any(t.id in inner._keep_ids for t in out_targets):
            # The operator's next step, which the count alone does not say: nothing binds a model
            # whose points nobody has targeted.
            reason += f"; {MODEL_NOT_TARGETED}"
        elif len(located) < need:
            # A model point's target lost before the provisional frame located it (a corner's
            # patch often is, as the faces around it turn) counts for nothing: say which, and
            # what would help, since waiting alone may never bind the model.
            gone = sorted(t.id for t in out_targets if t.id in inner._keep_ids and not t.measured and t.id not in located)
            if gone:
                reason += (f"; {', '.join(gone)} {'is' if len(gone) == 1 else 'are'} lost before "
                           f"{'it was' if len(gone) == 1 else 'they were'} located: target more of its points")
        if len(located) >= need:
            refused = self._bind(inner, located)
            reason = refused if refused is not None else f"case (b): model bound through {len(located)} of its points"
        if self._operator_watch(frame):
            out_targets = self.tracker.targets
            if len(located) < need:  # what the clause above said of the targets is stale beside the clicks
                reason = reason.split("; ")[0] + f"; {CLICKED_NOW}"
        return out_targets, PoseEstimate.invalid(reason, self._case), None

    def _bind(self, inner: "Engine", located: list[str]) -> str | None:
        """Carry the provisional model of ``inner`` into the a-priori frame through the a-priori
        points it has located: the weighted absolute orientation ``b_prov = R b_model + t`` of
        their two sets of coordinates (:func:`trackmeter.core.pose.solve_pose`, the provisional
        ones with their covariances), refused like a pose (non-collinear points, 1-sigma within
        ``max_*_sigma_*``, chi-square per degree of freedom within ``max_residual_per_dof``).
        Every other provisional point becomes a grown point ``R^T (b_prov - t)``, its covariance
        plus the transform's. Returns why the binding was refused, or None when bound."""
        assert self._given_model is not None
        p = self.pose_params
        given = dict(zip(self._given_model.ids, self._given_model.points_body))
        B = np.array([given[pid] for pid in located], dtype=float)
        if choose_frame_points(B, p.min_triangle_m) is None:
            return (f"case (b): binding the model: its {len(located)} located points are (nearly) collinear; "
                    f"waiting for another")
        floor = p.point_sigma_floor_m**2 * np.eye(3)
        P = np.array([inner._model[pid].b for pid in located])
        C = np.array([inner._model[pid].cov for pid in located]) + floor
        try:
            R, t, cov = solve_pose(B, P, C, None, None, p.refine_iterations)
        except (TrackmeterError, np.linalg.LinAlgError) as exc:
            return f"case (b): binding the model: {exc}"
        r = P - (B @ R.T + t)
        # Tested with the corners' own error added (pose.bind_sigma_floor_m), fitted without it.
        C_test = C + p.bind_sigma_floor_m**2 * np.eye(3)
        d2 = float(np.einsum("ni,nij,nj->", r, np.linalg.inv(C_test), r))
        dof = 3 * len(located) - 6
        if dof > 0 and d2 / dof > p.max_residual_per_dof:
            return (f"case (b): binding the model: its located points disagree with the model (chi-square "
                    f"{d2 / dof:.0f} per degree of freedom)")
        if not _sigmas_within(cov, p.max_attitude_sigma_deg, p.max_position_sigma_m):
            return "case (b): binding the model: the located points leave the binding undetermined"
        cov_reported = cov
        if p.apriori_bias_sigma_m > 0:  # the located corners' own error, which the fit leaves out
            try:
                cov_reported = solve_pose(B, P, C + p.apriori_bias_sigma_m**2 * np.eye(3), None, (R, t),
                                          p.refine_iterations)[2]
            except (TrackmeterError, np.linalg.LinAlgError):
                pass
        carried = set()
        for pid, m in inner._model.items():
            if pid in given:
                continue  # the a-priori coordinates stand
            b = R.T @ (m.b - t)
            cov_b = R.T @ (m.cov + _position_cov(cov, b, R)) @ R
            self._model[pid] = _ModelPoint(b, cov_b, False, t_s=m.t_s)
            carried.add(pid)
        self._share_frame_error(carried, cov)
        self._binding_ids, self._binding_cov_reported = set(carried), _isotropic_bound(cov_reported)
        self._seen_t.update(inner._seen_t)
        self._lost_since.update(inner._lost_since)
        if inner._last_fit is not None:
            R_c, t_c, cov_c = inner._last_fit
            self._last_fit = (R_c @ R, R_c @ t + t_c, cov_c)  # T_cam_model = T_cam_prov T_prov_model
        self.stats.add_provisional(inner.stats)
        self.stats.models_bound_progressively += 1
        self._bound, self._provisional = True, None
        return None

    # ------------------------------------------------------------------ model building

    def _establish_frame(self, measured: dict[str, TargetState]) -> str | None:
        """Case (a): the three-point frame and the initial model from the measured points that
        have been tracked for ``frame_min_age_frames`` (a frame and model made of targets that
        die within a few frames of their creation would be re-made from poorly fitted poses:
        the body frame would wander until the model settles)."""
        min_age = self.pose_params.frame_min_age_frames
        ids = [i for i, s in measured.items() if s.age_frames >= min_age]
        if len(ids) < 3:
            return ((f"case (a): waiting for 3 points tracked for {counted(min_age, 'frame')} to define the frame ({len(ids)} so far)"
                     if min_age else f"case (a): {counted(len(ids), 'measured point')}, 3 needed to define the frame")
                    + ("; the body was last seen moving out of view" if self._gone_from_view else ""))
        self._gone_from_view = False
        P = np.array([measured[i].point_cam for i in ids])
        triple = choose_frame_points(P, self.pose_params.min_triangle_m)
        if triple is None:
            return "case (a): the measured points are (nearly) collinear or clustered: no frame"
        i, j, k = triple
        R_frame, origin = three_point_body_frame(P[i], P[j], P[k])
        C = np.array([measured[x].cov_cam for x in ids])
        b, Cb = to_body(R_frame, origin, P, C)
        assert Cb is not None
        self._model = {pid: _ModelPoint(b[n], Cb[n], False) for n, pid in enumerate(ids)}
        self._frame_ids = (ids[i], ids[j], ids[k])
        return None

    def _acquire(self, frame: StereoFrame, measured: dict[str, TargetState]) -> str | None:
        """Case (c): collect points while still; on success freeze the model. Returns the reason
        the pose is not available yet (None once the model exists)."""
        acq = self._acquisition
        assert acq is not None
        p = self.pose_params
        if len(measured) < 3:
            self._acquisition = _Acquisition()
            return f"acquiring a model: {counted(len(measured), 'measured point')}, 3 needed"
        if acq.t_start is None:
            acq.t_start = frame.t_s
        acq.frames += 1
        for tid, tgt in measured.items():
            acq.points.setdefault(tid, []).append(np.asarray(tgt.point_cam, float))
            acq.covs.setdefault(tid, []).append(np.asarray(tgt.cov_cam, float))
        # Still? Each point's samples must scatter about their mean as their covariance says.
        checked = False
        for tid, pts in acq.points.items():
            if len(pts) < 3:
                continue
            checked = True
            P = np.array(pts)
            C = np.array(acq.covs[tid])
            r = P - P.mean(axis=0)
            d2 = float(np.mean(np.einsum("ni,nij,nj->n", r, np.linalg.inv(C), r)))
            if d2 > p.still_max_d2:
                moved = f"acquiring a model: the object moved (point {tid}); hold it still"
                self._acquisition = _Acquisition(moved=moved)
                return moved
        if checked:
            acq.moved = None
        elif acq.moved is not None:
            return acq.moved
        elapsed = frame.t_s - acq.t_start
        if elapsed < p.still_time_s:
            return f"acquiring a model: hold still ({p.still_time_s - elapsed:.1f} s left)"
        need = max(2, acq.frames // 2)
        ids = [tid for tid, pts in acq.points.items() if len(pts) >= need and tid in measured]
        if len(ids) < 3:
            self._acquisition = _Acquisition()
            return "acquiring a model: fewer than 3 points stayed tracked; hold still"
        means, covs = [], []
        for tid in ids:
            W = np.linalg.inv(np.array(acq.covs[tid]))
            Wsum = W.sum(axis=0)
            C = np.linalg.inv(Wsum)
            means.append(C @ np.einsum("nij,nj->i", W, np.array(acq.points[tid])))
            covs.append(C)
        M = np.array(means)
        if choose_frame_points(M, p.min_triangle_m) is None:
            self._acquisition = _Acquisition()
            return "acquiring a model: the points are (nearly) collinear; select spread-out points"
        centroid = M.mean(axis=0)
        self._model = {tid: _ModelPoint(M[n] - centroid, covs[n], False) for n, tid in enumerate(ids)}
        self._acquisition = None
        return None

    # ------------------------------------------------------------------ pose

    def _fit(self, frame: StereoFrame, measured: dict[str, TargetState]
             ) -> tuple[tuple[FloatArray, FloatArray, FloatArray, int, list[str]] | None, str | None]:
        prev_inliers, self._prev_inliers = self._prev_inliers, None  # set again by a pose this frame
        ids = [i for i in measured if i in self._model]
        if not self._model:
            return None, "no model" if self._case != "a" else "case (a): no frame yet"
        if len(ids) < self.pose_params.min_points:
            # Case (a)'s "model" is its body frame's tracked points: no model to the operator.
            points = counted(len(ids), "model point") if self._case != "a" else f"{len(ids)} of the body frame's points"
            reason = f"only {points} measured ({self.pose_params.min_points} needed)"
            if self._out_of_view(frame.t_s):
                # Not an occlusion to wait out: the chaser must turn or move to see it again.
                reason += ": the body was last seen moving out of view"
            return None, reason
        b = np.array([self._model[i].b for i in ids])
        Cb = np.array([self._model_cov(self._model[i], frame.t_s) for i in ids])
        P = np.array([measured[i].point_cam for i in ids])
        C = np.array([measured[i].cov_cam for i in ids])
        initial = (self._last_fit[0], self._last_fit[1]) if self._last_fit is not None else None
        try:
            fit = robust_pose(b, P, C, Cb, self.pose_params, initial=initial, seed=frame.index)
        except (TrackmeterError, np.linalg.LinAlgError) as exc:
            return None, f"pose undetermined: {exc}"
        if not (np.isfinite(fit.R_cam_body).all() and np.isfinite(fit.t_cam_body).all()):
            # Never seen (the points and covariances are finite and checked, the normal matrix's
            # conditioning is), but the velocity estimator and output filter refuse such a pose:
            # an invalid frame, not an exception out of the tracking thread.
            return None, "pose undetermined: the fit is not finite"
        if fit.inliers.sum() < self.pose_params.min_points:
            return None, f"only {counted(int(fit.inliers.sum()), 'consistent model point')}"
        # With as few points as the pose has unknowns (3), nothing can be singled out as an
        # outlier: a gross mismatch bends the pose instead. The residual still shows it (3 of
        # the 9 coordinates are redundant): chi-square per degree of freedom of the inliers
        # (nan, never above the limit, when there is no redundancy).
        per_dof = fit.residual_per_dof
        if per_dof > self.pose_params.max_residual_per_dof:
            return None, (f"the measured model points disagree with the model (chi-square {per_dof:.0f} per "
                          f"degree of freedom): a wrong match among too few points to single it out")
        if not _sigmas_within(fit.cov, self.pose_params.max_attitude_sigma_deg, self.pose_params.max_position_sigma_m):
            sd = np.sqrt(np.diag(fit.cov))
            return None, (f"{int(fit.inliers.sum())} model points leave the pose undetermined (1-sigma "
                          f"{sd[:3].max() * 1e3:.0f} mm, {np.degrees(sd[3:].max()):.1f} deg; nearly collinear?)")
        resting = self._rests_on_frame_error(ids, fit.inliers)
        cov = fit.cov + cast("FloatArray", self._frame_cov) if resting else fit.cov  # resting: it is set
        if resting and not _sigmas_within(cov, self.pose_params.max_attitude_sigma_deg, self.pose_params.max_position_sigma_m):
            sd = np.sqrt(np.diag(cast("FloatArray", self._frame_cov)))
            return None, (f"the model points measured share the error of the coast or binding they joined through "
                          f"(1-sigma {sd[:3].max() * 1e3:.0f} mm, {np.degrees(sd[3:].max()):.1f} deg): too uncertain "
                          f"for a pose until points free of it are measured")
        contradiction = self._contradicts_coast(frame.t_s, fit)
        if contradiction is not None:
            # Which of them is wrong is unknown, and kept they would give the same pose again
            # once the coast has run out: all are dropped (re-found later through the pose).
            self._pending_reject.update(ids)
            self.stats.outliers_rejected += len(ids)
            return None, contradiction
        outliers = [ids[n] for n in np.flatnonzero(~fit.inliers)]
        self._pending_reject.update(outliers)
        self.stats.outliers_rejected += len(outliers)
        if self.pose_params.handover_hold and prev_inliers is not None:
            fit = self._hold_handover(frame.t_s, ids, fit, prev_inliers, P, C)
            cov = fit.cov + cast("FloatArray", self._frame_cov) if resting else fit.cov
        R, t = fit.R_cam_body, fit.t_cam_body
        self._last_fit = (R, t, cov)
        self._note_apriori_frame_error(frame.t_s, R, [i for n, i in enumerate(ids)
                                                      if fit.inliers[n] and self._model[i].fixed and measured[i].origin != "model"])
        self._note_shared_frame_error(R, ids, fit.inliers, b, C, Cb, resting)
        hold = self._case == "a" and self.pose_params.frame_hold
        held = {i: (self._model[i].b.copy(), self._model[i].cov.copy()) for i in ids} if hold else {}
        before = set(self._model)
        self._update_model(R, t, cov, fit.scale2, ids, fit.inliers, measured)
        if resting:
            # Points joining through this pose are located in the same offset frame.
            self._frame_error_ids = (self._frame_error_ids | (set(self._model) - before)) & self._model.keys()
        if held:
            self._hold_frame(held)
        self._anchor(frame.t_s, R, t, ids, fit.inliers, measured)
        if self.pose_params.relock_stored:
            for n in np.flatnonzero(fit.inliers):
                self._pose_when_seen[ids[n]] = (R, t)
        if self.pose_params.handover_hold:
            self._track_residuals(frame.t_s, R, t, [i for n, i in enumerate(ids) if fit.inliers[n]], measured,
                                  fresh=prev_inliers is None)
        return (R, t, cov, int(fit.inliers.sum()), outliers), None

    def _note_apriori_frame_error(self, t_s: float, R: FloatArray, apriori: list[str]) -> None:
        """Case (b): the body frame's error the a-priori points' own errors leave (``pose.apriori_bias_sigma_m``,
        sigma, isotropic and the same in every frame a point is seen in), ``sigma² (sum_i J_i^T J_i)^-1``
        over the a-priori inliers ``apriori`` of the pose ``R`` (J_i: :func:`position_jacobians`),
        (6,6), kept in the body frame with its time ``t_s``, from which the model's drift runs
        (:meth:`_apriori_frame_report`). Only points located independently of the pose count (the
        caller's choice): a target the engine made at a model point's projection through the pose
        (origin ``"model"``, :meth:`_recover`) measures whatever surface point the pose's error put
        it on, so across the line of sight it repeats that error (estec case (b), 40-60 s: the
        corners' mean offset follows the pose's error, correlation 0.40 and 0.95 on the two axes
        across it; docs/results.md) and pins nothing. Kept from the last frame that determined it:
        while fewer such points are measured the grown model carries the frame they left. Before
        any frame has three (a progressive binding's poses), the drift runs from the first pose,
        with no frame term of its own; so it does with ``sigma`` 0."""
        if self._case != "b":
            return
        anchor = self._apriori_frame_anchor
        if anchor is not None and t_s < anchor[0]:  # the clock went back without a cut: the drift starts again
            self._apriori_frame_anchor = anchor = (t_s, anchor[1])
        frame_body: FloatArray | None = None
        sigma = self.pose_params.apriori_bias_sigma_m
        if len(apriori) >= 3 and sigma <= 0:
            frame_body = np.zeros((6, 6))
        elif len(apriori) >= 3:
            J = position_jacobians(np.array([self._model[i].b for i in apriori]), R)
            try:
                frame_cov = sigma**2 * np.linalg.inv(np.einsum("nij,nik->jk", J, J))
            except np.linalg.LinAlgError:
                frame_cov = np.full((6, 6), np.nan)
            if np.all(np.isfinite(frame_cov)) and _sigmas_within(frame_cov, self.pose_params.max_attitude_sigma_deg,
                                                                   self.pose_params.max_position_sigma_m):
                B = _pose_block_rotation(R)
                frame_body = B.T @ frame_cov @ B
        if frame_body is not None:
            self._apriori_frame_anchor = (t_s, frame_body)
        elif anchor is None:
            self._apriori_frame_anchor = (t_s, np.zeros((6, 6)))

    def _apriori_frame_report(self, t_s: float, R: FloatArray) -> FloatArray:
        """Case (b): the body frame's error reported on top of the fit's covariance for a pose of
        attitude ``R`` at ``t_s``, (6,6), camera frame (zero before the first pose). ``R`` is the
        fit's (or the coast's) attitude, whose frame error this is; the filtered pose reported
        beside it lags it by a fraction of a degree. The anchor's frame error
        (:meth:`_note_apriori_frame_error`) turned with the body (an error of the body frame:
        position and rotation vector both turn by ``R``), plus the drift since of a model located
        through the pose it gives (its grown points and the targets remade through it), a random
        walk: ``q² dt`` on each position axis of the a-priori points' centroid c and
        ``(q / r)² dt`` on each rotation axis (q: ``pose.model_drift_m_per_sqrt_s``, r: their rms
        distance from c, the lever a point's drift turns the frame by), the turn moving the body
        origin by ``[c]x dtheta`` too (body frame: ``A diag(q² dt I, (q / r)² dt I) A^T``,
        ``A = [[I, [c]x], [0, I]]``)."""
        if self._apriori_frame_anchor is None:
            return np.zeros((6, 6))
        t0, frame_body = self._apriori_frame_anchor
        q, dt = self.pose_params.model_drift_m_per_sqrt_s, max(t_s - t0, 0.0)
        if q > 0 and dt > 0:
            turn = (q / self._apriori_radius_m) ** 2 * dt if self._apriori_radius_m > 0 else 0.0
            # The frame turns about the points' centroid c: the body origin moves by
            # dtheta x (0 - c) = [c]x dtheta on top of the centroid's own walk.
            A = np.eye(6)
            if np.all(np.isfinite(self._apriori_centroid_m)):
                A[:3, 3:] = skew(self._apriori_centroid_m)
            frame_body = frame_body + A @ np.diag([q**2 * dt] * 3 + [turn] * 3) @ A.T
        B = _pose_block_rotation(R)
        return B @ frame_body @ B.T

    def _note_shared_frame_error(self, R: FloatArray, ids: list[str], inliers: NDArray[np.bool_], b: FloatArray,
                                 C: FloatArray, Cb: FloatArray, resting: bool) -> None:
        """Case (b) after a progressive binding: the part of the binding's error that this
        frame's fit keeps, for the reported covariance (``_shared_frame_report``, (6,6)). The
        points the binding carried share its error, a rigid offset ``d`` of their frame
        (``_binding_cov_reported``: the binding's covariance with the located corners' own
        error, ``pose.apriori_bias_sigma_m``, which its fit leaves out); ``d`` moves each of them
        by ``J_i d`` and the fit by ``K d``, ``K = H^-1 G`` (H: the fit's normal matrix over its
        inliers, G: that of the carried ones; J_i: :func:`position_jacobians`, weights
        ``(C_i + R Cb_i R^T)^-1``), so it adds ``K S K^T``. With three corners measured the fit
        counts itself pinned and adds nothing of it, though the carried points may still carry
        most of its weight (harsh_light case (b) after its binding: 3-5 mm and 0.5 deg off for
        4 s against a 1.2 mm 1-sigma); resting on them it adds ``_frame_cov`` (K ~ I), and only
        what that leaves out is added here."""
        self._shared_frame_report = np.zeros((6, 6))
        S = self._binding_cov_reported
        if S is None:
            return
        if resting:
            if self._frame_cov is not None:
                self._shared_frame_report = np.maximum(S - self._frame_cov, 0.0)
            return
        use = np.flatnonzero(inliers)
        carried = np.array([ids[n] in self._binding_ids for n in use])
        if not carried.any():
            return
        J = position_jacobians(b[use], R)
        W = np.linalg.inv(C[use] + R @ Cb[use] @ R.T)
        JW = np.swapaxes(J, -1, -2) @ W @ J
        try:
            K = np.linalg.solve(JW.sum(axis=0), JW[carried].sum(axis=0))
        except np.linalg.LinAlgError:
            return
        self._shared_frame_report = K @ S @ K.T

    def _update_model(self, R: FloatArray, t: FloatArray, cov: FloatArray, scale2: float, ids: list[str],
                      inliers: NDArray[np.bool_], measured: dict[str, TargetState]) -> None:
        """Refine measured model points and let consistent new targets join. A body-frame
        observation ``b = R^T (p - t)`` carries the point's covariance (inflated by the fit's
        robust scale) plus the pose's, propagated to that point.

        Each refinement also carries a rigid part, the pose error of the frame the points were
        observed through, taken up unequally by young and old points: left in, it moves the
        body frame a little (a gauge drift, :func:`trackmeter.core.pose.hold_frame`). By default
        it is left in; ``pose.frame_hold`` (case a) undoes it (:meth:`_hold_frame`), measured
        better over 60 s and worse over the first 20 s on estec. The a-priori points of case
        (b) are not refined, and hold their frame."""
        p = self.pose_params

        L_pose = np.linalg.cholesky(0.5 * (cov + cov.T) + 1e-18 * np.eye(6)) if p.model_pose_error_correlated else None
        t_s = self._frame_t_s

        def observe(tgts: list[TargetState]) -> tuple[FloatArray, FloatArray, FloatArray]:
            """Body-frame observations (N,3), their measurement covariances (N,3,3) and their
            pose-error factors (N,3,6), all points in one go (the cost is numpy's per call)."""
            b_obs = (np.array([tg.point_cam for tg in tgts], float) - t) @ R  # R^T (p - t) per row
            Cm = R.T @ (scale2 * np.array([tg.cov_cam for tg in tgts], float)) @ R
            if L_pose is None:
                return b_obs, Cm + R.T @ _position_cov(cov, b_obs, R) @ R, np.zeros((len(tgts), 3, 6))
            return b_obs, Cm, R.T @ position_jacobians(b_obs, R) @ L_pose

        def fuse(points: Sequence[_ModelPoint | _Candidate], cm: FloatArray, b_obs: FloatArray,
                 cm_obs: FloatArray, L_obs: FloatArray) -> None:
            """Fuse each point with its observation (in place)."""
            b, cm, L = fuse_point_correlated(np.array([m.b for m in points]), cm, np.array([m.L for m in points]),
                                             b_obs, cm_obs, L_obs)
            total = cm + L @ np.swapaxes(L, -1, -2)
            for k, m in enumerate(points):
                m.b, m.cm, m.L, m.cov = b[k], cm[k], L[k], total[k]

        if p.model_refine:
            refine = [pid for n, pid in enumerate(ids) if inliers[n] and not self._model[pid].fixed]
            if refine:
                points = [self._model[pid] for pid in refine]
                cm_old = np.array([(m.cov if m.cm is None else m.cm) + self._slide_cov(m, t_s) for m in points])
                fuse(points, cm_old, *observe([measured[pid] for pid in refine]))
                for m in points:
                    m.t_s = t_s
        # Candidates: measured targets not yet in the model.
        new = [tid for tid in measured if tid not in self._model]
        if not new:
            return
        b_obs, cm_obs, L_obs = observe([measured[tid] for tid in new])
        cov_obs = cm_obs + L_obs @ np.swapaxes(L_obs, -1, -2)
        again: list[int] = []
        restarted: set[str] = set()  # an observation off its candidate starts it over, not joining now
        for k, tid in enumerate(new):
            cand = self._candidates.get(tid)
            if cand is not None:
                r = b_obs[k] - cand.b
                # The innovation's pose parts partly cancel; their sum bounds it (a loose gate).
                if float(r @ np.linalg.solve(cand.cov + cov_obs[k], r)) <= self._gate:
                    again.append(k)
                    continue
                restarted.add(tid)
            self._candidates[tid] = _Candidate(b_obs[k], cov_obs[k], cm_obs[k], L_obs[k])
        if again:
            cands = [self._candidates[new[k]] for k in again]
            fuse(cands, np.array([c.cm for c in cands]), b_obs[again], cm_obs[again], L_obs[again])
            for c in cands:
                c.count += 1
        for tid in new:
            cand = self._candidates[tid]
            if tid not in restarted and cand.count >= p.join_after_frames:
                self._model[tid] = _ModelPoint(cand.b, cand.cov, False, cand.cm, cand.L, t_s)
                # Seen now: a point that joins and is lost before its next measurement must not
                # rank as the stalest of the grown model (pruned first, never re-locked).
                self._seen_t[tid] = t_s
                del self._candidates[tid]
                self.stats.model_points_joined += 1

    def _hold_frame(self, held: dict[str, tuple[FloatArray, FloatArray]]) -> None:
        """Case (a): undo the rigid part of this frame's model refinement (:func:`hold_frame`), so
        averaging the points' observations sharpens the model without moving the body frame.
        ``held``: body coordinates and covariances of the refined points before the update."""
        ids = [i for i in held if i in self._model and not np.array_equal(self._model[i].b, held[i][0])]
        if len(ids) < 3:
            return
        R_h, t_h = hold_frame(np.array([held[i][0] for i in ids]), np.array([self._model[i].b for i in ids]),
                              np.array([held[i][1] for i in ids]))
        self._move_points(ids, R_h, t_h)

    def _move_points(self, ids: list[str], R: FloatArray, t: FloatArray) -> None:
        """Move model points rigidly, ``b <- R b + t``, their covariances and pose-error factors with them."""
        for i in ids:
            m = self._model[i]
            m.b = R @ m.b + t
            m.cov = R @ m.cov @ R.T
            if m.cm is not None:
                m.cm = R @ m.cm @ R.T
            m.L = R @ m.L

    def _hold_handover(self, t_s: float, ids: list[str], fit: PoseFit, prev_inliers: set[str], P: FloatArray,
                       C: FloatArray) -> PoseFit:
        """``pose.handover_hold``: after measured model points were lost since the last frame (or
        rejected), move the survivors so their recent mean observations put the pose where the
        whole set's did (:func:`handover_offset`) and fit the pose again: no jump.
        A-priori points among the inliers hold the frame themselves: nothing is moved then.

        ``P``, ``C``: (N,3) and (N,3,3) the measured points and covariances of ``ids``."""
        now = {ids[n] for n in np.flatnonzero(fit.inliers)}
        if prev_inliers <= now or any(self._model[i].fixed for i in now):
            return fit
        before = [i for i in self._residual_mean if i in self._model]
        survivors = [k for k, i in enumerate(before) if i in now]
        if len(survivors) < 3 or len(survivors) == len(before):
            return fit
        b = np.array([self._model[i].b for i in before])
        observed = b + np.array([self._residual_mean[i][0] for i in before])
        cov = np.array([self._model_cov(self._model[i], t_s) + self._residual_mean[i][1] for i in before])
        try:
            R_d, t_d, d2 = handover_offset(b, observed, cov, np.array(survivors))
        except (TrackmeterError, np.linalg.LinAlgError):
            return fit
        if d2 <= chi2.ppf(self.pose_params.handover_probability, 6):
            return fit
        moved = [before[k] for k in survivors]
        self._move_points(moved, R_d, t_d)
        for k in survivors:
            i = before[k]
            self._residual_mean[i] = (observed[k] - self._model[i].b, self._residual_mean[i][1])
        inl = fit.inliers
        b_all = np.array([self._model[i].b for i in ids])
        Cb_all = np.array([self._model_cov(self._model[i], t_s) for i in ids])
        try:
            R2, t2, cov2 = solve_pose(b_all[inl], P[inl], C[inl], Cb_all[inl], (fit.R_cam_body, fit.t_cam_body),
                                      self.pose_params.refine_iterations)
        except (TrackmeterError, np.linalg.LinAlgError):
            return fit
        self.stats.handovers_held += 1
        return replace(fit, R_cam_body=R2, t_cam_body=t2, cov=cov2 * fit.scale2)

    def _track_residuals(self, t_s: float, R: FloatArray, t: FloatArray, inliers: list[str],
                         measured: dict[str, TargetState], fresh: bool) -> None:
        """Update the running mean (time constant ``pose.handover_window_s``) of each inlier's
        body-frame residual ``R^T (p - t) - b`` after this frame's model update; points not among
        the inliers are forgotten, and after a frame without a pose the means start over."""
        keep = [i for i in inliers if i in self._model]
        if not keep:
            self._residual_mean, self._prev_inliers = {}, set()
            return
        obs = (np.array([measured[i].point_cam for i in keep], float) - t) @ R
        r = obs - np.array([self._model[i].b for i in keep])
        C_body = R.T @ np.array([measured[i].cov_cam for i in keep], float) @ R
        dt = 0.0 if self._residual_t is None or fresh else max(0.0, t_s - self._residual_t)
        a = 1.0 - float(np.exp(-dt / self.pose_params.handover_window_s))
        old = {} if fresh else self._residual_mean
        self._residual_mean = {
            i: (r[n] if i not in old else old[i][0] + a * (r[n] - old[i][0]), C_body[n]) for n, i in enumerate(keep)
        }
        self._residual_t = t_s
        self._prev_inliers = set(keep)

    def _slide_cov(self, m: _ModelPoint, t_s: float) -> FloatArray:
        """(3,3) how far a grown point may have slid on the surface since its last refinement: a
        tracked pixel is not a fixed body point (template updates and sub-pixel re-centring let it
        wander), modelled as a random walk, ``sigma² = slide_sigma_m_per_sqrt_s² dt`` per axis, m²."""
        q = self.pose_params.slide_sigma_m_per_sqrt_s ** 2
        if m.fixed or q <= 0.0:
            return np.zeros((3, 3))
        return q * max(0.0, t_s - m.t_s) * np.eye(3)

    def _model_cov(self, m: _ModelPoint, t_s: float) -> FloatArray:
        """Covariance (3,3) of a model point's body coordinates at ``t_s``, m²."""
        return m.cov + self._slide_cov(m, t_s)

    def _anchor(self, t_s: float, R: FloatArray, t: FloatArray, ids: list[str], inliers: NDArray[np.bool_],
                measured: dict[str, TargetState]) -> None:
        """Case (b): move the grown model onto the a-priori frame as the a-priori points reveal its drift.

        Grown points carry the pose error of the frames they joined in: the grown model sits in a
        frame ``Delta`` off the a-priori one, ``b_grown = R_d b_true + t_d``. The pose from the grown
        points alone, ``T_g = T_true Delta^-1``, puts an a-priori point ``b_f`` at ``T_g b_f`` where
        it is measured at ``T_g Delta b_f``: the residual ``r = p_f - T_g b_f = R_g (dt - [b_f]x dtheta)``
        (first order) is linear in the drift ``(dt, dtheta)``. Its normal equations are summed over
        frames (forgetting over ``anchor_memory_s``; as the body turns, one or two a-priori points
        seen now and then reveal every direction), solved with the prior ``anchor_prior_*`` (what
        they do not reveal stays put), and a fraction ``dt / anchor_time_s`` of the drift is
        removed from every grown point per frame — slowly, so the output does not jump."""
        p = self.pose_params
        if p.anchor_time_s <= 0 or self._case != "b":
            return
        dt = 0.0 if self._anchor_t is None else max(0.0, t_s - self._anchor_t)
        self._anchor_t = t_s
        decay = float(np.exp(-dt / p.anchor_memory_s))
        self._anchor_H *= decay
        self._anchor_g *= decay
        fixed = [i for n, i in enumerate(ids) if inliers[n] and self._model[i].fixed]
        grown = [i for n, i in enumerate(ids) if inliers[n] and not self._model[i].fixed]
        if fixed and len(grown) >= 3:
            self._anchor_evidence(R, t, fixed, grown, measured)
        if not np.any(self._anchor_g):
            return
        prior = np.diag([p.anchor_prior_m**-2] * 3 + [p.anchor_prior_rad**-2] * 3)
        drift = np.linalg.solve(self._anchor_H + prior, self._anchor_g)
        step = drift * min(1.0, dt / p.anchor_time_s)
        # The poses fitted from now on differ from the earlier ones by what moving the grown
        # points does to this frame's pose (not the step itself: the a-priori points hold their
        # place in the fit), without any motion of the body. Measured as one re-fit before the
        # move against the same re-fit after it: against the engine's own fit of this frame
        # (its robust weights and outlier test) it would also move the history by how the two
        # fits differ (harsh_light: 0.07 mm a frame median, the step's own 0.02 mm).
        used = [i for n, i in enumerate(ids) if inliers[n]]
        before = self._refit(t_s, R, t, used, measured) if p.anchor_moves_history else None
        R_s = Rotation.from_rotvec(step[3:]).as_matrix()
        for m in list(self._model.values()) + list(self._candidates.values()):
            if isinstance(m, _ModelPoint) and m.fixed:
                continue
            m.b = R_s.T @ (m.b - step[:3])
        self._anchor_g -= self._anchor_H @ step
        after = self._refit(t_s, R, t, used, measured) if before is not None else None
        if before is not None and after is not None:
            (R1, t1), (R2, t2) = before, after
            # Applied once this frame's pose (fitted before the move) has joined the history.
            self._frame_move = (R1.T @ R2, R1.T @ (t2 - t1))

    def _anchor_evidence(self, R: FloatArray, t: FloatArray, fixed: list[str], grown: list[str],
                         measured: dict[str, TargetState]) -> None:
        """Add to :meth:`_anchor`'s normal equations what the a-priori points ``fixed`` say of
        the drift of the grown points ``grown`` (inliers of this frame's fit ``(R, t)``).

        Nothing when the pose from the grown points alone is not determined within the pose
        bounds (``max_*_sigma``): three nearly collinear grown points leave it free about their
        line, and the linear residual model then reads metres of drift from a few millimetres
        of noise (estec case (b), one noise seed: 0.8 m at 0.16 s, a valid pose 0.85 m off
        after 5 s)."""
        p = self.pose_params
        try:
            R_g, t_g, cov_g = solve_pose(
                np.array([self._model[i].b for i in grown]), np.array([measured[i].point_cam for i in grown]),
                np.array([measured[i].cov_cam for i in grown]), np.array([self._model[i].cov for i in grown]),
                (R, t), 2)
        except (TrackmeterError, np.linalg.LinAlgError):
            return
        if not _sigmas_within(cov_g, p.max_attitude_sigma_deg, p.max_position_sigma_m):
            return
        for i in fixed:
            b_f = self._model[i].b
            J = R_g @ np.hstack([np.eye(3), -skew(b_f)])
            W = np.linalg.inv(np.asarray(measured[i].cov_cam, float) + _position_cov(cov_g, b_f, R_g))
            r = np.asarray(measured[i].point_cam, float) - (R_g @ b_f + t_g)
            self._anchor_H += J.T @ W @ J
            self._anchor_g += J.T @ W @ r

    def _refit(self, t_s: float, R: FloatArray, t: FloatArray, used: list[str],
               measured: dict[str, TargetState]) -> tuple[FloatArray, FloatArray] | None:
        """The pose ``(R_cam_body, t_cam_body)`` fitted to the model points ``used`` as the model
        holds them now (two Gauss-Newton steps from ``(R, t)``); None where the fit fails."""
        try:
            R2, t2, _ = solve_pose(
                np.array([self._model[i].b for i in used]), np.array([measured[i].point_cam for i in used]),
                np.array([measured[i].cov_cam for i in used]),
                np.array([self._model_cov(self._model[i], t_s) for i in used]), (R, t), 2)
        except (TrackmeterError, np.linalg.LinAlgError):
            return None
        return R2, t2

    def _move_history(self) -> None:
        """Re-express the poses the velocities and the coast's centre of mass are fitted to in
        the body frame :meth:`_anchor` moved the grown model to (``T_cam_new = T_cam_old D``)."""
        if self._frame_move is None:
            return
        R_d, t_d = self._frame_move
        self._frame_move = None
        self._velocity.move_body_frame(R_d, t_d)
        h = self._com_history
        for k, (t_k, R_k, p_k, w_k) in enumerate(h):
            h[k] = (t_k, R_k @ R_d, p_k + R_k @ t_d, w_k)

    # ------------------------------------------------------------------ recovery

    def _forget_stale(self, frame: StereoFrame, targets: tuple[TargetState, ...], measured: dict[str, TargetState]) -> None:
        """Bound what re-locking keeps: grown model points outlive their targets (they are
        re-locked by measurement at their projection, like a-priori points) up to
        ``max_model_points``; a re-made target of a grown point that stays lost is dropped again."""
        for pid in measured:
            if pid in self._model:  # only model points compete for a place (the dict stays bounded)
                self._seen_t[pid] = frame.t_s
        keep = self.pose_params.relock_stored
        # Handed over (take_removed keeps no reference): detach below may add None.
        removed = cast("dict[str, StoredTarget | None]", self.tracker.take_removed()) if keep and hasattr(self.tracker, "take_removed") else {}
        for t in targets:
            m = self._model.get(t.id)
            # A target made for a model point the model no longer has (a case change, a binding,
            # the pruning below): nothing re-makes it, and lost nothing else drops it.
            orphan = m is None and t.origin == "model"
            if t.status != "lost" or (t.origin != "model" and (m is None or not m.fixed)):
                self._lost_since.pop(t.id, None)
                continue
            since = self._lost_since.setdefault(t.id, frame.index)
            if m is not None and m.fixed:
                continue  # re-made through a measured pose (_recover), never just dropped
            if frame.index - since >= self._lost_keep_frames:
                if keep and not orphan:
                    removed[t.id] = self.tracker.detach(t.id)
                else:
                    self.tracker.remove_target(t.id)
                self._lost_since.pop(t.id, None)
        for pid, stored in removed.items():
            m = self._model.get(pid)
            # The first target of a point is the texture it was grown from: a target re-made
            # at its projection since (where that was not found) does not replace it.
            if m is not None and not m.fixed and stored is not None:
                self._stored.setdefault(pid, (stored, self._pose_when_seen.get(pid)))
        for table in (self._pose_when_seen, self._last_attempt):
            for pid in [p for p in table if p not in self._model]:
                del table[pid]
        grown = [pid for pid, m in self._model.items()
                 if not m.fixed and pid not in self._frame_ids and pid not in self._keep_ids]
        excess = len(grown) - self.pose_params.max_model_points
        if excess > 0:
            grown.sort(key=lambda pid: self._seen_t.get(pid, -np.inf))
            for pid in grown[:excess]:
                if pid not in measured:
                    del self._model[pid]
                    self._seen_t.pop(pid, None)
                    self._stored.pop(pid, None)

    def _carried_pose(self, t_s: float) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """The last valid pose carried forward to ``t_s`` at its last velocities (constant twist:
        ``R(t) = R0 exp([omega_body dt]x)``, ``p(t) = p0 + v dt``) with its covariance grown by
        ``coast_sigma_*`` per second; None beyond ``coast_max_s`` or before any pose."""
        if self._last_measured is None:
            return None
        t0, R0, p0, cov0, v, w = self._last_measured
        dt = t_s - t0
        p = self.pose_params
        if not 0.0 < dt <= p.coast_max_s:
            return None
        v = np.where(np.isfinite(v), v, 0.0)
        w = np.where(np.isfinite(w), w, 0.0)
        R = R0 @ Rotation.from_rotvec(w * dt).as_matrix()
        grow = np.concatenate([np.full(3, (p.coast_sigma_m_per_s * dt) ** 2), np.full(3, (p.coast_sigma_rad_per_s * dt) ** 2)])
        return R, p0 + v * dt, cov0 + np.diag(grow)

    def _out_of_view(self, t_s: float) -> bool:
        """Whether the body was last seen moving out of view: carried on from its last measured
        pose (:meth:`_carried_pose`, within ``coast_max_s``), it had fewer than ``min_points`` of
        its model points in front of the rig and inside both images, so its points went from
        view, not hidden or lost by the tracker. Once true it holds until the next measured
        pose: the carried pose is no evidence of where the body is later. Visibility is not
        asked (a point on the far side counts as in view), so the answer errs toward "in view"."""
        if self._left_view:
            return True
        carried = self._carried_pose(t_s)
        if carried is None or not self._model:
            return False
        R, t, _ = carried
        x_cam = np.array([m.b for m in self._model.values()]) @ R.T + t
        self._left_view = int(np.count_nonzero(self._in_view(x_cam, 0.0))) < self.pose_params.min_points
        return self._left_view

    def _in_view(self, x_cam: FloatArray, margin_px: float) -> NDArray[np.bool_]:
        """(N,) whether each camera-frame point (N,3) lies in front of the rig and projects at
        least ``margin_px`` inside both images."""
        x_cam = np.asarray(x_cam, float).reshape(-1, 3)
        front = x_cam[:, 2] > 0
        inside = np.zeros(len(x_cam), bool)
        if np.any(front):
            w, h = self.rig.image_size
            low, high = np.array([margin_px, margin_px]), np.array([w - 1 - margin_px, h - 1 - margin_px])
            uv_l, uv_r = self.rig.project(x_cam[front])
            inside[front] = np.all((uv_l >= low) & (uv_l <= high) & (uv_r >= low) & (uv_r <= high), axis=1)
        return inside

    def _coast_state(self, t_s: float) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, float] | None:
        """The last output pose carried to ``t_s`` on the motion model
        (:func:`trackmeter.core.dynamics.coast_pose`): ``(R, p, v_cam, cov, dt)``, or None
        without a pose with settled rates."""
        if self._last_output is None:
            return None
        t0, R0, p0, cov0, v, w = self._last_output
        dt = t_s - t0
        if dt <= 0:
            return None
        p = self.pose_params
        R, pos, v_t, cov = coast_pose(R0, p0, cov0, v, w, dt, p.coast_velocity_sigma_m_s,
                                      p.coast_omega_sigma_rad_s, p.coast_lever_m, self._com_speed_bound(t0))
        return R, pos, v_t, cov, dt

    def _com_speed_bound(self, t0: float) -> float | None:
        """A bound on the centre of mass's speed from the poses before the coast that starts at
        ``t0`` (:func:`fit_centre_of_mass` on the velocity window, or on the measured poses of the
        last ``coast_centre_of_mass_window_s`` when that is set; once per coast), m/s, or None.
        Unknown, the coast must assume the worst the lever allows (``|v| + |omega| lever``: on
        harsh_light 55 mm/s, which bent the predicted path's bound past 50 mm in 3 s)."""
        if self._com_cache is not None and self._com_cache[0] == t0:
            return self._com_cache[1]
        bound = None
        if self.pose_params.coast_fit_centre_of_mass:
            if self.pose_params.coast_centre_of_mass_window_s > 0:
                h = self._com_history
                t, R, P = (np.array([x[k] for x in h]) for k in range(3))
                w = np.array([x[3] for x in h])
            else:
                t, R, P, W = self._velocity.window()
                w = W[:, 0]
            fit = fit_centre_of_mass(t, R, P, w, self.pose_params.coast_lever_m) if len(t) else None
            bound = fit.speed_bound_m_s if fit is not None else None
        self._com_cache = (t0, bound)
        return bound

    def _remember_for_com(self, t_s: float, R: FloatArray, p: FloatArray, cov: FloatArray) -> None:
        """Keep measured poses of the last ``coast_centre_of_mass_window_s`` for
        :meth:`_com_speed_bound` (nothing when it is 0)."""
        span = self.pose_params.coast_centre_of_mass_window_s
        if span <= 0:
            return
        h = self._com_history
        h.append((t_s, np.array(R, float), np.array(p, float), float(block_weights(cov)[0][0])))
        while h and h[0][0] < t_s - span:
            h.popleft()

    def _coast_within(self, t_s: float, attitude_sigma_deg: float, position_sigma_m: float
                      ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, float] | None:
        """:meth:`_coast_state` while its covariance is within the bounds (deg, m; an attitude
        bound of 0 switches it off), else None."""
        if attitude_sigma_deg <= 0:
            return None
        state = self._coast_state(t_s)
        if state is None or not _sigmas_within(state[3], attitude_sigma_deg, position_sigma_m):
            return None
        return state

    def _coasted_pose(self, t_s: float, why: str) -> PoseEstimate | None:
        """No pose measured this frame: the coasted one, valid while its covariance stays within
        ``coast_valid_attitude_sigma_deg`` and ``coast_valid_position_sigma_m``, else None.
        Flagged: ``coasting_s`` > 0, no points, and the reason says what it is."""
        p = self.pose_params
        state = self._coast_within(t_s, p.coast_valid_attitude_sigma_deg, p.coast_valid_position_sigma_m)
        if state is None:
            return None
        R, pos, v, cov, dt = state
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = pos
        w = self._last_output.omega if self._last_output is not None else np.full(3, np.nan)
        return PoseEstimate(True, f"coasting {dt:.2f} s on the motion model ({why})", self._case, T,
                            cov + self._apriori_frame_report(t_s, R) + self._shared_frame_report, v, np.asarray(w, float).copy(), 0, (), coasting_s=float(dt), body_frame=self._body_frame)

    def _rejoin_through_coast(self, t_s: float, measured: dict[str, TargetState]) -> bool:
        """No pose: while the coasted pose is within ``coast_rejoin_*``, measured targets that are
        not model points join the model through it (paper 2.D's model growth, through the
        predicted pose instead of a measured one: their body coordinates carry its covariance),
        so that when the light returns the pose goes on in the same body frame from the new
        points, continuous with the coast. Returns whether the coast is within those bounds
        (case a then keeps its frame instead of defining a new one)."""
        p = self.pose_params
        state = (self._coast_within(t_s, p.coast_rejoin_attitude_sigma_deg, p.coast_rejoin_position_sigma_m)
                 if self._model else None)
        if state is None:
            return False
        R, pos, _, cov, _ = state
        before = set(self._model)
        self._update_model(R, pos, cov, 1.0, [], np.zeros(0, bool), measured)
        joined = set(self._model) - before
        self._share_frame_error(joined, cov)  # the coast's error: a rigid offset of the frame they define
        return True

    def _share_frame_error(self, ids: set[str], cov: FloatArray) -> None:
        """Model points ``ids`` were carried into the body frame by one transform of covariance
        ``cov`` (6,6) (position m, rotation rad): a coasted pose they joined through, or the
        binding that carried a provisional model into the a-priori frame. They share its error,
        a rigid offset of the frame they define, which a pose fit to them would average away;
        it is kept as an isotropic bound (rotation-invariant blocks, so it holds in any later
        camera pose) and added to such poses (:meth:`_rests_on_frame_error`)."""
        if not ids:
            return
        # Forgotten model points leave the set: a long run would grow it, and one that joins
        # again is judged by the pose it joins through.
        self._frame_error_ids = (self._frame_error_ids | ids) & self._model.keys()
        iso = _isotropic_bound(cov)
        self._frame_cov = iso if self._frame_cov is None else np.maximum(self._frame_cov, iso)

    def _rests_on_frame_error(self, ids: list[str], inliers: NDArray[np.bool_]) -> bool:
        """Whether a fit to the model points ``ids`` (``inliers`` (N,) used) carries the frame's
        common error (``_frame_cov``, :meth:`_share_frame_error`): the fit's covariance treats
        every point's error as independent, so it is added unless at least 3 points free of it
        (a-priori points, points grown through poses pinned by such points) pin the frame."""
        if self._frame_cov is None:
            return False
        pinned = sum(1 for n, i in enumerate(ids) if inliers[n] and i not in self._frame_error_ids)
        return pinned < 3

    def _contradicts_coast(self, t_s: float, fit: PoseFit) -> str | None:
        """Why a fit from just ``min_points`` points, the first after a coast, is not trusted (None
        when it is). Three points fix a pose with nothing to spare: three wrong matches whose
        distances happen to fit the model (look-alikes re-found after a loss) give a
        self-consistent, wrong pose that no residual reveals. The motion carried through the
        loss does: a fit outside the chi-square gate (6 dof) of ``cov + cov_coast`` around the
        coasted pose is refused (harsh_light, case b: a 3-point fit 150 mm and 15 deg off
        right after a 0.7 s coast). With a fourth point the outlier test can single a wrong
        match out, and a disagreement means the coast was wrong (:meth:`_blend_out`)."""
        p = self.pose_params
        if not self._coasting or int(fit.inliers.sum()) > p.min_points:
            return None
        state = self._coast_state(t_s)
        if state is None:
            return None
        R_c, p_c, _, cov_c, _ = state
        e, d2 = _offset_from(R_c, p_c, cov_c, fit.R_cam_body, fit.t_cam_body, fit.cov)
        if d2 <= chi2.ppf(p.outlier_probability, 6):
            return None
        return (f"{int(fit.inliers.sum())} model points give a pose {np.linalg.norm(e[:3]) * 1e3:.0f} mm from the "
                f"motion carried through the loss (chi-square {d2:.0f}, 6 dof): too few points to trust")

    def _blend_out(self, t_s: float, R: FloatArray, pos: FloatArray, cov: FloatArray
                   ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The output after a coast: measured again, the pose would jump from the coasted one by
        the coast's error. Instead the offset ``e`` (coasted minus measured: position, rotation
        vector, camera frame) at the first measured frame is removed with the time constant
        ``coast_blend_s``: output ``exp(a e) (R, p)`` with ``a = exp(-(t - t_e) / coast_blend_s)``
        and covariance ``cov + a² cov_coast`` (the part of the coast's error still in it). An
        offset outside the chi-square gate (6 dof) of ``cov + cov_coast`` means the coast was
        wrong: no blending, the measured pose is output (the jump is real)."""
        p = self.pose_params
        if self._coasting and p.coast_blend_s > 0:
            state = self._coast_state(t_s)
            self._blend = None
            if state is not None:
                R_c, p_c, _, cov_c, _ = state
                e, d2 = _offset_from(R_c, p_c, cov_c, R, pos, cov)
                if d2 <= chi2.ppf(p.outlier_probability, 6):
                    self._blend = (t_s, e, cov_c)
        self._coasting = False
        if self._blend is None:
            return R, pos, cov
        t_e, e, cov_c = self._blend
        a = float(np.exp(-(t_s - t_e) / p.coast_blend_s))
        if a < 1e-3:
            self._blend = None
            return R, pos, cov
        return Rotation.from_rotvec(a * e[3:]).as_matrix() @ R, pos + a * e[:3], cov + a * a * cov_c

    def _recover(self, frame: StereoFrame, R: FloatArray, t: FloatArray, cov: FloatArray, carried: bool = False) -> None:
        """Re-lock lost model points at their projection through the pose ``(R, t)`` (paper 2.D).

        Lost targets are searched for with their own (anchor) templates; model points without a
        target are measured at their projection, which is only safe through a measured pose:
        through a ``carried`` one (coasting after a loss) a wrong prediction would measure
        whatever surface lies there, so only template re-locks are tried. An a-priori point's
        target lost ``pose.apriori_remake_after_s`` is given up and measured afresh there: its
        template is of a view that seldom comes back (estec: most corners unmeasured after 20 s
        while 9-14 of them stay in view)."""
        p = self.pose_params
        states = {s.id: s for s in self.tracker.targets}
        # Re-made targets of grown points must leave the operator room to click.
        room = len(states) < self._max_targets - p.operator_reserve_targets
        # A stored target re-found is worth a slot more than a lost one kept for its own
        # recovery: counted against the targets tracked only (within the tracker's limit).
        room_stored = bool(self._stored) and len(states) < self._max_targets and (
            sum(1 for s in states.values() if s.status != "lost") < self._max_targets - p.operator_reserve_targets)
        todo: list[tuple[str, bool]] = []
        # An a-priori point's target lost this long was made in another view: measured afresh.
        # In frames, as _lost_since counts (tracker.lost_keep_frames is a frame count): at the
        # rate the engine was given, 25 Hz when the source told none.
        remake_after_frames = p.apriori_remake_after_s * self.rate_hz
        stale: set[str] = set()
        for pid, m in self._model.items():
            s = states.get(pid)
            if s is not None and s.status == "lost":
                if (m.fixed and not carried and remake_after_frames > 0
                        and frame.index - self._lost_since.get(pid, frame.index) >= remake_after_frames):
                    stale.add(pid)
                todo.append((pid, pid not in stale))
            elif (s is None and (m.fixed or room or (room_stored and pid in self._stored)) and (not carried or pid in self._stored)
                  and pid not in self._operator_removed):  # what the operator removed stays removed
                todo.append((pid, False))
        if not todo:
            return
        todo.sort(key=lambda item: self._last_attempt.get(item[0], -10**9))
        # The attempts (at most max_recoveries_per_frame, in that order) do not depend on their
        # outcomes: choose them first, then run each stretch of consecutive template re-locks as
        # one batched call (Tracker.relock_many: one search, fit and stereo match for all).
        chosen: list[tuple[str, bool, FloatArray, tuple[float, float]]] = []
        for pid, is_target in todo:
            if len(chosen) >= p.max_recoveries_per_frame:
                break
            last = self._last_attempt.get(pid)
            if last is not None and frame.index - last < p.recovery_interval_frames:
                continue
            x_cam = R @ self._model[pid].b + t
            if not self._in_view(x_cam, p.recovery_margin_px)[0]:
                continue
            uv_l = self.rig.project(x_cam[None])[0][0]
            self._last_attempt[pid] = frame.index
            if pid in stale:
                self.tracker.remove_target(pid)
                self._lost_since.pop(pid, None)
            chosen.append((pid, is_target, x_cam, (float(uv_l[0]), float(uv_l[1]))))
        self.stats.relock_attempts += len(chosen)
        k, restored = 0, False
        while k < len(chosen):
            end = k + 1
            if chosen[k][1]:
                while end < len(chosen) and chosen[end][1]:
                    end += 1
                results = self.tracker.relock_many([(pid, uv) for pid, _, _, uv in chosen[k:end]], frame)
            else:
                result, restored = self._remake(frame, chosen[k][0], chosen[k][2], chosen[k][3], (R, t), carried)
                results = [result]
            for (pid, is_target, x_cam, _), result in zip(chosen[k:end], results):
                kept = self._judge_recovery(pid, is_target, x_cam, result, R, cov)
                if kept and restored:
                    # Its stored target is tracked again (stored anew if it is dropped again).
                    del self._stored[pid]
                    self.stats.stored_relocks += 1
            k, restored = end, False

    def _remake(self, frame: StereoFrame, pid: str, x_cam: FloatArray, uv: tuple[float, float],
                pose: tuple[FloatArray, FloatArray], carried: bool) -> tuple[TargetState | Refusal, bool]:
        """A target for model point ``pid`` without one, predicted at ``x_cam`` (3,), left pixel
        ``uv``, through ``pose`` ``(R_cam_body, t_cam_body)``: its stored target re-found
        (``pose.relock_stored``), else (through a measured pose only) a new target at that
        pixel. Returns the tracker's answer and whether it is the stored target's."""
        stored = self._stored.get(pid)
        if stored is not None:
            target, then = stored
            warp = None if then is None else self._image_warp_since(then, pose, self._model[pid].b)
            result = self.tracker.restore_many([(target, uv, x_cam, warp)], frame)[0]
            if isinstance(result, TargetState):
                return result, True
            if carried:
                return result, False
        return self.tracker.add_target(frame, uv, pid, "model"), False

    def _image_warp_since(self, then: tuple[FloatArray, FloatArray], now: tuple[FloatArray, FloatArray],
                          b: FloatArray) -> FloatArray:
        """(2,2) the linear map of the left image around body point ``b`` (3,) from the pose
        ``then`` to the pose ``now`` (``(R_cam_body, t_cam_body)`` each), its surface taken
        face-on to the line of sight then (its normal is not known): the rotation about the
        line of sight and the scale are the body's, the foreshortening a guess."""
        R0, t0 = then
        R1, t1 = now
        X0 = R0 @ b + t0
        R_rel = R1 @ R0.T
        m = X0 / float(X0 @ X0)  # the plane through X0 facing the camera: m . X = 1
        uv0 = self.rig.left.project(X0[None])[0]
        return plane_jacobian(self.rig.left.K, R_rel[None], (t1 - R_rel @ t0)[None], m[None], uv0[None])[0]

    def _judge_recovery(self, pid: str, is_target: bool, x_cam: FloatArray, result: TargetState | Refusal,
                        R: FloatArray, cov: FloatArray) -> bool:
        """Keep a re-locked model point only where the pose ``(R, cov)`` puts it (``x_cam``);
        whether it was kept."""
        if isinstance(result, Refusal):
            return False
        self._recovered_any = True
        m = self._model[pid]
        r = np.asarray(result.point_cam, float) - x_cam
        C = np.asarray(result.cov_cam, float) + R @ m.cov @ R.T + _position_cov(cov, m.b, R)
        d2 = float(r @ np.linalg.solve(C, r)) if np.all(np.isfinite(r)) else np.inf
        if d2 > self._gate:
            self.stats.recoveries_rejected += 1
            if is_target:
                self._pending_reject.add(pid)
            else:
                self.tracker.remove_target(pid)
            return False
        self.stats.recoveries += 1
        return True

    # ------------------------------------------------------------------ errors

    def _errors(self, frame: StereoFrame, pose: PoseEstimate) -> dict | None:
        truth = frame.truth
        if truth is None or not pose.valid or not self.live_errors:
            return None
        T_true = np.asarray(truth.T_cam_body, float)
        R_e, p_e = pose.T_cam_body[:3, :3], pose.T_cam_body[:3, 3]
        v_e, w_e = pose.velocity_cam_m_s, pose.omega_body_rad_s
        if self._case != "b":
            # Online body alignment X = T_bodytrue_bodyest: chordal mean of R_true^T R_est and
            # mean of R_true^T (p_est - p_true) so far (metrics.estimate_body_offset, running).
            from trackmeter.core.metrics import refer_to_true_body

            self._align_M += T_true[:3, :3].T @ R_e
            self._align_t += T_true[:3, :3].T @ (p_e - T_true[:3, 3])
            self._align_n += 1
            R_X, _ = procrustes_rotation(self._align_M)
            t_X = self._align_t / self._align_n
            # one scipy conversion for both (from_matrix costs ~0.25 ms a call, about the same
            # for two matrices; the rows are the single calls' numbers)
            q_est, q_true = matrix_to_quat_wxyz(np.stack([R_e, T_true[:3, :3]]))
            q, pos, vel, om = refer_to_true_body(q_est, p_e, R_X, t_X,
                                                 v_e[None] if np.all(np.isfinite(v_e)) else None,
                                                 w_e[None] if np.all(np.isfinite(w_e)) else None)
            R_e = Rotation.from_quat(q[0], scalar_first=True).as_matrix()
            p_e = pos[0]
            v_e = vel[0] if vel is not None else np.full(3, np.nan)
            w_e = om[0] if om is not None else np.full(3, np.nan)
            q_est = matrix_to_quat_wxyz(R_e)
            T_bodytrue_bodyest = make_transform(R_X, t_X)
        else:
            q_est, q_true = matrix_to_quat_wxyz(np.stack([R_e, T_true[:3, :3]]))
            T_bodytrue_bodyest = np.eye(4)
        att = attitude_error_components(q_est, q_true)
        return {
            # The body alignment the errors were taken after (identity in case (b)): the 3D
            # view draws the mock-up, whose mesh is in the true body frame, through it.
            "T_bodytrue_bodyest": T_bodytrue_bodyest,
            "position_m": p_e - T_true[:3, 3],
            "attitude_rad": att,
            "attitude_total_rad": float(np.linalg.norm(att)),
            "velocity_m_s": np.asarray(v_e, float) - np.asarray(truth.velocity_cam_m_s, float),
            "omega_rad_s": np.asarray(w_e, float) - np.asarray(truth.omega_body_rad_s, float),
        }


def _offset_from(R_c: FloatArray, p_c: FloatArray, cov_c: FloatArray, R: FloatArray, p: FloatArray,
                 cov: FloatArray) -> tuple[FloatArray, float]:
    """Offset ``e`` (6,) of pose ``(R_c, p_c)`` from ``(R, p)`` (position m, rotation vector rad,
    camera frame) and its squared Mahalanobis distance under ``cov_c + cov`` (both (6,6))."""
    e = np.concatenate([p_c - p, Rotation.from_matrix(R_c @ R.T).as_rotvec()])
    return e, float(e @ np.linalg.solve(cov + cov_c, e))


def _pose_block_rotation(R: FloatArray) -> FloatArray:
    """(6,6) ``diag(R, R)``: takes a body-frame error of a pose (position, rotation vector) to
    the camera frame of a pose of attitude ``R`` (``B cov B^T``; ``B^T cov B`` back)."""
    B = np.zeros((6, 6))
    B[:3, :3] = R
    B[3:, 3:] = R
    return B


def _isotropic_bound(cov_pose: FloatArray) -> FloatArray:
    """(6,6) diagonal bound of a pose covariance by blocks: its largest position variance on
    the position axes, its largest rotation variance on the rotation axes (rotation-invariant,
    so it holds in any later camera pose)."""
    d = np.diag(cov_pose)
    return np.diag([d[:3].max()] * 3 + [d[3:].max()] * 3)


def _sigmas_within(cov_pose: FloatArray, attitude_sigma_deg: float, position_sigma_m: float) -> bool:
    """Whether every standard deviation of a (6,6) pose covariance (position m, rotation vector
    rad) is within the bounds: rotation components in degrees, position components in metres."""
    d = np.diag(cov_pose)
    return bool(np.sqrt(d[3:].max()) <= np.radians(attitude_sigma_deg) and np.sqrt(d[:3].max()) <= position_sigma_m)


def _position_cov(cov_pose: FloatArray, b: FloatArray, R: FloatArray) -> FloatArray:
    """Covariance (...,3,3) of body points ``R b + t`` (b (...,3)) in the camera frame from the
    pose covariance (6,6)."""
    J = position_jacobians(b, R)
    return J @ cov_pose @ np.swapaxes(J, -1, -2)
