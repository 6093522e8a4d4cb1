"""Immutable snapshots the tracking thread publishes, and the commands it accepts.

The tracking thread owns all tracker state. Everything else (console callbacks, the CLI,
recorders) talks to it by putting a :class:`Command` on its queue and reads the newest
:class:`Snapshot`. A command that needs an answer (a click that may be refused) carries a
:class:`concurrent.futures.Future` the tracking thread resolves with a :class:`CommandReply`.
"""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from trackmeter.core.targets import TargetState
from trackmeter.sources.base import StereoFrame

ModelCase = Literal["a", "b", "c"]


@dataclass(frozen=True, eq=False)
class PoseEstimate:
    """The motion estimate of one frame (paper section 2.C-2.E).

    Attributes:
        valid: False when no pose could be made (then ``reason`` says why; the arrays are NaN).
        reason: why the pose is invalid; for a valid pose None, or, while coasting, what it is.
        case: the model case used, ``"a"``, ``"b"`` or ``"c"``.
        T_cam_body: (4,4) filtered pose of the body in the left camera frame.
        cov_pose: (6,6) covariance of (position m, rotation vector rad) in the camera frame: the
            fit's, from the points' uncertainties, and in case (b) the body frame's error the
            a-priori points' own error leaves (``pose.apriori_bias_sigma_m``) with the drift
            of the model since they last fixed it (``pose.model_drift_m_per_sqrt_s``).
        velocity_cam_m_s: (3,) velocity of the body origin in the camera frame, m/s.
        omega_body_rad_s: (3,) angular velocity in the body frame, rad/s.
        n_points: number of points used.
        outlier_ids: targets rejected as outliers this frame.
        coasting_s: 0 for a pose measured this frame; > 0: no model point was measured for this
            long and the pose is the last one carried on the motion model
            (:func:`trackmeter.core.dynamics.coast_pose`), valid only while its covariance is
            within ``pose.coast_valid_*`` (``n_points`` is 0, ``reason`` says so).
        body_frame: which body frame the pose refers to, counted by the engine from 1: a pose
            whose number differs from the one before is in a frame defined since (case
            switched, a model loaded or acquired, case (a)'s frame redefined after a loss), so
            the step between the two is not a motion. 0 for an invalid pose.
    """

    valid: bool
    reason: str | None
    case: ModelCase
    T_cam_body: NDArray[np.float64]
    cov_pose: NDArray[np.float64]
    velocity_cam_m_s: NDArray[np.float64]
    omega_body_rad_s: NDArray[np.float64]
    n_points: int = 0
    outlier_ids: tuple[str, ...] = ()
    coasting_s: float = 0.0
    body_frame: int = 0

    @staticmethod
    def invalid(reason: str, case: ModelCase = "a") -> PoseEstimate:
        nan3 = np.full(3, np.nan)
        return PoseEstimate(False, reason, case, np.full((4, 4), np.nan), np.full((6, 6), np.nan), nan3, nan3.copy())


@dataclass(frozen=True)
class Timings:
    """Rates and latencies, measured by the pipeline.

    Attributes:
        acquisition_hz: frames read from the source per second (recent average).
        tracking_hz: frames processed by the tracking thread per second.
        latency_ms: from the frame leaving the source to its pose being published.
        step_ms: time of the last tracking step.
        frames_read, frames_processed, frames_dropped: counters since start.
        counts_at_restart: ``(frames_read, frames_dropped)`` when the source was last restarted
            (the stream's share dropped counts from there), None before any restart.
    """

    acquisition_hz: float = 0.0
    tracking_hz: float = 0.0
    latency_ms: float = 0.0
    step_ms: float = 0.0
    frames_read: int = 0
    frames_processed: int = 0
    frames_dropped: int = 0
    counts_at_restart: tuple[int, int] | None = None


@dataclass(frozen=True, eq=False)
class Snapshot:
    """Everything observers may know about one processed frame. Never mutated after publishing.

    Attributes:
        frame: the stereo frame (images, time, ground truth when the source has it).
        targets: every target after this frame's step.
        pose: the motion estimate.
        errors: pose errors against ground truth when known: keys ``position_m`` (3,),
            ``attitude_rad`` (3,) per axis (eq. 17), ``attitude_total_rad`` (eq. 16),
            ``velocity_m_s`` (3,), ``omega_rad_s`` (3,), and ``T_bodytrue_bodyest`` (4,4), the
            body alignment they were taken after (cases a and c; identity in case b); None
            without truth or without a pose.
        timings: rates and latencies.
        auto_enabled, auto_count, auto_method: automatic feature selection settings.
        auto_shortfall: why its last top-up that wanted targets started none, None otherwise.
        filter_cutoff_hz: the output filter's cutoff, Hz (NaN when the engine has none).
        paused, recording: pipeline state.
        source_status: None while the source delivers; else what went wrong or "ended".
        source_warning: what the source skipped or doubts (``Source.warning``, e.g. unreadable
            images of a sequence folder), None when nothing.
        sequence: increasing number of the snapshot.
        source_pass: the pass of a looping source the frame is from (1 until it starts over;
            an operator's Restart starts at 1 again).
        model_ids: the ids of the a-priori model's points (case b), empty without one: an
            operator binds a click to one of them (:class:`SelectPoint` ``target_id``).
    """

    frame: StereoFrame | None
    targets: tuple[TargetState, ...]
    pose: PoseEstimate
    errors: dict[str, NDArray[np.float64] | float] | None
    timings: Timings
    auto_enabled: bool = False
    auto_count: int = 0
    auto_method: str = "gabor"
    auto_shortfall: str | None = None
    filter_cutoff_hz: float = float("nan")
    paused: bool = False
    recording: bool = False
    source_status: str | None = None
    source_warning: str | None = None
    sequence: int = 0
    source_pass: int = 1
    model_ids: tuple[str, ...] = ()

    @property
    def source_status_text(self) -> str | None:
        """``source_status`` as a line says it: "source ended", "source failed: ...", None
        while the source delivers (the terminal and the console's status box say the same)."""
        status = self.source_status
        if not status:
            return None
        return status if status.startswith("source") else f"source {status}"


@dataclass(frozen=True)
class CommandReply:
    """The answer to a command: ``ok`` or not, and a one-line message for the operator;
    ``target_id`` the target a point selection made, ``moved_px`` how far from the pixel asked
    for it was put (``tracker.click_snap_px``: a refused pixel's trackable corner nearby);
    ``notable``: a success whose message says more than the new state a display shows;
    ``partial``: not done, but part of it was (some model points selected, too few for a pose)."""

    ok: bool
    message: str = ""
    target_id: str | None = None
    moved_px: float = 0.0
    notable: bool = False
    partial: bool = False


@dataclass(frozen=True, eq=False)
class Command:
    """Base of all commands. ``reply`` (optional) is resolved with a :class:`CommandReply`."""

    reply: Future[CommandReply] | None = field(default=None, kw_only=True)


@dataclass(frozen=True, eq=False)
class SelectPoint(Command):
    """Create a target at a left-image pixel (original image), optionally named."""

    u: float
    v: float
    target_id: str | None = None


@dataclass(frozen=True, eq=False)
class RemoveTarget(Command):
    target_id: str


@dataclass(frozen=True, eq=False)
class RemoveNearest(Command):
    """Remove the target nearest to a left-image pixel; not one of ``exclude`` (the console's
    lost targets it no longer draws: the operator cannot see them to aim at)."""

    u: float
    v: float
    exclude: tuple[str, ...] = ()


@dataclass(frozen=True, eq=False)
class ClearTargets(Command):
    pass


@dataclass(frozen=True, eq=False)
class SetAuto(Command):
    """Automatic feature selection on/off; ``count`` targets kept alive with ``method``."""

    enabled: bool
    count: int | None = None
    method: str | None = None


@dataclass(frozen=True, eq=False)
class SetCase(Command):
    case: ModelCase


@dataclass(frozen=True, eq=False)
class AcquireModel(Command):
    """Case (c): average the tracked points while the object is held still into a model."""


@dataclass(frozen=True, eq=False)
class LoadModel(Command):
    path: str


@dataclass(frozen=True, eq=False)
class SetFilterCutoff(Command):
    cutoff_hz: float


@dataclass(frozen=True, eq=False)
class SetPaused(Command):
    paused: bool


@dataclass(frozen=True, eq=False)
class StepOnce(Command):
    """While paused, process exactly one more frame."""


@dataclass(frozen=True, eq=False)
class RestartSource(Command):
    pass


@dataclass(frozen=True, eq=False)
class ResetTracking(Command):
    """Drop all targets, the model and the filters; keep the source running."""


@dataclass(frozen=True, eq=False)
class SetRecording(Command):
    """Start recording the incoming stereo stream to ``directory`` (None stops it)."""

    directory: str | None
