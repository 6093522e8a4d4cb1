"""Multi-target patch tracking in both images with Kalman prediction (paper section 2.B).

:class:`Tracker` is the thin stateful wrapper: it holds the targets and, every frame, calls the
pure steps of :mod:`trackmeter.core.kalman`, :mod:`trackmeter.core.patch_tracking` and
:mod:`trackmeter.core.features`, batched over all targets:

1. predict each target's left pixel with its constant-acceleration Kalman filter; the search
   window's half-size is ``window_sigmas`` predicted standard deviations;
2. find the patch in the window (integer ZNCC with the CURRENT template), refine it sub-pixel
   (inverse-compositional LK with gain/bias), then refine against the ANCHOR template (drift
   correction, Matthews et al. 2004; see :mod:`trackmeter.core.patch_tracking`); with
   ``anchor_warp: plane`` the anchor's linear warp is predicted from the rigid motion since the
   anchor (this step's motion check, accumulated) and the target's stereo surface plane;
3. gate the match on the filter's innovation (Mahalanobis, chi-square) and fuse it;
4. re-match the patch along the rectified epipolar line in the right image, near the previous
   disparity, sub-pixel; triangulate and propagate the covariance (paper eqs. 1-2);
5. check the 3D points against the rigid motion of the others: this frame's motion fitted to
   all targets (a jump across the line of sight), each target's first point carried by the
   body's motion (slow creep), and the pairwise distances of points on one rigid body, which
   stay constant within their uncertainty.

A target failing any check — low score, no convergence, ambiguous peak, gated jump, stereo or
epipolar failure, rigid inconsistency, left the image — is marked ``lost`` at once with the
reason; it never keeps reporting a guess. Lost targets are looked for again near where they
were lost (anchor template, strict score), or re-locked by the pose estimator through
:meth:`Tracker.relock` (paper 2.D). With automatic selection on, lost automatic targets are
replaced so that ``features.count`` targets stay alive; a new automatic point is accepted only
at the depth of the body (its disparity near the targets'), since a false stereo match at
creation would carry a wrong 3D point from the start.
"""

from __future__ import annotations

import collections
import copy
import re
import warnings
from dataclasses import dataclass, field, replace
from typing import Any, Collection, Iterable, Sequence, cast

import cv2
import numpy as np
from filterpy.kalman import KalmanFilter
from numpy.typing import ArrayLike, NDArray
from scipy.stats import chi2

from trackmeter.core import kalman as kf_mod
from trackmeter.core.features import FeatureParams, nothing_selectable_reason, select_features
from trackmeter.core.frames import StereoFrame
from trackmeter.core.kalman import KalmanParams
from trackmeter.core.matching import MeasureParams, PointMeasurement, measure_points
from trackmeter.core.params import check_params, param
from trackmeter.core.patch_tracking import (
    EpipolarMatch,
    PatchTrack,
    Templates,
    complex_map,
    fit_disparity_plane,
    grid_patch,
    make_templates,
    match_epipolar,
    track_patches,
    plane_jacobian,
    sample_patches,
    transform_plane,
    zncc_search,
)
from trackmeter.core.stereo import StereoRig, check_side_by_side
from trackmeter.core.targets import Refusal, TargetOrigin, TargetState, TargetStatus
from trackmeter.core.transforms import absolute_orientation
from trackmeter.errors import TrackmeterError

FloatArray = NDArray[np.float64]
_NAN2 = np.full(2, np.nan)
_NAN3 = np.full(3, np.nan)
_NAN33 = np.full((3, 3), np.nan)


#: How far from a target a remove-click may land, px (:meth:`Tracker.remove_nearest`).
REMOVE_NEAREST_PX = 20.0

#: :attr:`Tracker.auto_refusals` reasons of automatic selection's own (the rest are
#: :data:`trackmeter.core.matching.REASONS` and the target checks').
NO_CANDIDATE = "no candidate point (black space, no texture, or no unique stereo match)"
OFF_THE_BODY = "stereo match off the body's depth range"
#: How far (each axis) the integer search's best window may lie from the point the template was
#: made around while the point stays where it was: half a pixel, the search's grid.
SEARCH_CELL_PX = 0.5
#: Frames a target must have been tracked before its filter's velocity counts as measured.
SETTLED_FRAMES = 3
# The ids the tracker generates (origin operator, auto, model, other; then a number).
_GENERATED_ID = re.compile(r"[pamt](\d+)")


@dataclass(frozen=True)
class TrackerParams:
    """Tunables of multi-target tracking."""

    max_targets: int = param(32, "most targets tracked at once (operator + automatic)", min=1, max=1024)
    patch_size: int = param(8, "side of the tracked square patch, px (paper: 8)", min=3, max=63)
    min_score: float = param(0.8, "left-image ZNCC below which a target is lost", min=-1.0, max=1.0)
    ambiguity_margin: float = param(
        0.02, "lost when another peak in the search window comes within this ZNCC of the best", min=0.0, max=2.0
    )
    anchor_min_score: float = param(0.92, "ZNCC the anchor template must reach to correct drift", min=-1.0, max=1.0)
    drift_tolerance_px: float = param(
        0.25, "anchor refinement may move the match at most this far; a re-anchor needs the anchor and current "
        "template to agree this closely (each re-anchor can add this much drift), px", min=0.0,
    )
    anchor_warp: str = param(
        "similarity", "warp fitted to the anchor: similarity (4 dof), euclidean (scale from depth), affine (6 dof, noisy on 8x8) "
        "or plane (linear part predicted from the body's motion and the stereo surface plane, position fitted)",
        choices=("similarity", "euclidean", "affine", "plane"),
    )
    plane_patch_size: int = param(
        24, "side of the patch whose stereo disparity slope gives a target's surface plane (anchor_warp plane), px", min=5, max=127,
    )
    plane_samples: int = param(
        8, "stereo plane measurements per target (median, in its anchor frame); none are made after that", min=1, max=1000,
    )
    plane_min_samples: int = param(3, "plane measurements a target needs before its anchor warp is predicted", min=1, max=1000)
    plane_interval_frames: int = param(
        2, "surface planes are measured on every this many frames (its cost is mostly per batched call)", min=1, max=1000,
    )
    plane_min_score: float = param(0.9, "ZNCC a stereo plane fit must reach to count", min=-1.0, max=1.0)
    plane_max_tilt_deg: float = param(
        75.0, "a surface plane seen more obliquely than this (normal to line of sight) is not used, deg", min=0.0, max=90.0,
    )
    anchor_tolerance_px: float = param(0.05, "anchor fit converged when its last step moves the patch less than this, px", min=0.0)
    anchor_max_scale_error: float = param(
        0.2, "anchor fit rejected when its scale differs from the depth-implied one by more than this fraction", min=0.0,
    )
    anchor_scale_fallback: str = param(
        "operator", "an anchor similarity fit refused (not converged, or its scale off the depth-implied one) is fitted "
        "again with that scale held: for the operator's targets, all targets, or none (never the a-priori model's points)",
        choices=("operator", "all", "none"),
    )
    near_first_px: float = param(
        4.0, "a wide search window is first searched this far around the prediction; a unique good match there, "
        "off the near window's border, is taken, else the whole window is searched, px (0: off)", min=0.0,
    )
    near_first_settled_above_px: float = param(
        6.0, "a settled target's window (its velocity measured) is searched near first when its half-size exceeds this, px",
        min=0.0,
    )
    near_first_new_above_px: float = param(
        12.0, "a new target's window (its velocity still a guess) is searched near first when its half-size exceeds this, px",
        min=0.0,
    )
    min_search_px: float = param(3.0, "smallest search window half-size, px", min=0.0)
    max_search_px: float = param(96.0, "largest search window half-size, px", min=1.0)
    stereo_search_px: int = param(6, "disparity change searched per frame while tracking, +-px", min=1, max=256)
    stereo_min_score: float = param(0.8, "right-image ZNCC below which a target is lost", min=-1.0, max=1.0)
    uniqueness_margin: float = param(
        0.05, "the epipolar match must beat every other peak on its line by this ZNCC", min=0.0, max=2.0
    )
    epipolar_tolerance_px: float = param(1.0, "largest vertical offset of the right match from the rectified row, px", min=0.0)
    stereo_row_fit: bool = param(
        False, "a tracked disparity is the shift fit along the rectified row that measure makes (the 2D fit kept for "
        "the epipolar check) instead of the 2D fit's, whose vertical freedom leaks into it on oblique texture"
    )
    still_camera_fits: bool = param(
        False, "start the sub-pixel fits at the prediction where the search agrees with it, search the stereo strip "
        "from a whole disparity, and take a new target's first 3D point from the tracker's own stereo match: a still "
        "camera's sharp images keep their targets"
    )
    sigma_disparity_px: float = param(0.1, "std of a tracked sub-pixel disparity, px (paper: 0.07)", min=0.0)
    sigma_uv_px: float = param(0.05, "std of a tracked left-image position, px", min=0.0)
    min_gradient_eig: float = param(
        20.0, "smallest eigenvalue of the patch's mean gradient structure tensor, grey²/px² (aperture problem)", min=0.0
    )
    rigid_check: bool = param(True, "lose targets whose 3D distances to the others change (rigid-body check)")
    rigid_sigmas: float = param(4.0, "a distance change beyond this many standard deviations is inconsistent", min=0.0)
    rigid_tolerance_m: float = param(0.001, "distance change always tolerated, m", min=0.0)
    rigid_min_pairs: int = param(3, "pairs with other targets needed to judge rigid consistency", min=1)
    motion_check: bool = param(
        True, "lose targets whose 3D point does not follow the rigid motion the others made since the last frame"
    )
    motion_gate_probability: float = param(
        0.9999, "chi-square (3 dof) probability of that check's gate on each point's motion residual", min=0.5, max=1.0 - 1e-12,
    )
    motion_tolerance_px: float = param(
        0.4, "std added in every direction to a point's motion residual (frame-to-frame tracking jitter, fit error), "
        "in left-image px at the point's depth", min=0.0,
    )
    motion_min_targets: int = param(4, "targets followed from the last frame needed for the rigid-motion check", min=3)
    body_check: bool = param(
        False, "lose targets that drift from where the rigid body, fitted to all targets' first 3D points, puts their first point"
    )
    body_drift_px: float = param(
        1.5, "largest distance across the line of sight, in left-image px, of a target from its first point moved with the body", min=0.0,
    )
    recover_lost: bool = param(True, "look for lost targets again where they were lost (paper 2.D, no model)")
    recover_min_score: float = param(0.92, "anchor ZNCC needed to recover a lost target", min=-1.0, max=1.0)
    recover_search_px: float = param(24.0, "half-size of the window searched to recover a target, px", min=1.0)
    recover_interval_frames: int = param(3, "frames between two recovery attempts of a lost target", min=1)
    neighbour_velocity_sigma_px_s: float = param(
        30.0, "std added to the other targets' velocity spread for a new target's velocity, px/s", min=0.0
    )
    rigid_velocity_guess: bool = param(
        True, "a new or re-found target's image velocity is the one the tracked points' rigid motion gives its 3D point",
    )
    rigid_velocity_sigma_px_s: float = param(
        10.0, "std added to that prediction's median miss on the settled targets, px/s", min=0.0,
    )
    track_blur_sigma_px: float = param(
        0.7, "std of a Gaussian smoothing of the left image for the frame-to-frame sub-pixel fits and their templates, "
        "px (0: none; the integer search and the stereo match always use the image itself; at most 5: wider "
        "smooths an 8x8 patch flat, and 1e6 took minutes a frame)", min=0.0, max=5.0,
    )
    search_on_pixel_grid: bool = param(
        False, "the integer search's template is the window of the image's own pixels nearest the target, its "
        "offset from the target added back to the search's result, not the template resampled at the target "
        "(compared half a pixel off: a still target on a sharp texture is lost as a low score)",
    )
    track_blur_recheck_px: float = param(
        0.25, "with the smoothing, each sub-pixel fit is refined again on the image itself and must land within this "
        "of the smoothed fit, else it failed, px (0: no re-check)", min=0.0,
    )
    lost_keep_frames: int = param(10, "frames a lost automatic target is kept before it is replaced", min=0)
    click_snap_px: float = param(
        5.0, "an operator's unnamed target refused where it was clicked is put on the nearest trackable corner "
        "within this many px, and the reply says so (0: never; a target named after a model point never)",
        min=0.0, max=50.0,
    )
    auto: bool = param(False, "automatic feature selection on at start")
    auto_interval_frames: int = param(5, "automatic selection tops up at most every this many frames", min=1)
    auto_disparity_margin_px: float = param(
        16.0, "automatic selection accepts a new point only when its disparity lies within the targets' disparities widened by this, px", min=0.0,
    )
    auto_range_min_targets: int = param(
        3, "targets (or, before there are so many, measured candidates) needed to bound the disparity of new automatic points", min=1,
    )
    kalman: KalmanParams = field(default_factory=KalmanParams)

    def __post_init__(self) -> None:
        check_params(self)  # declared ranges and choices first (trackmeter.core.params)
        if not self.min_search_px <= self.max_search_px:
            raise TrackmeterError(f"min_search_px ({self.min_search_px:g}) must not exceed max_search_px ({self.max_search_px:g})")


@dataclass(eq=False)
class _Target:
    id: str
    origin: TargetOrigin
    kf: KalmanFilter
    anchor: Templates  # one target's templates (leading axis of length 1)
    current: Templates
    t_s: float
    # The current template from the image itself (``current``'s values when the fits are not
    # smoothed): the integer search's template, and the re-check's (track_blur_recheck_px).
    current_raw: Templates
    anchor_raw: Templates  # the anchor from the image itself (``anchor`` when the fits are not smoothed)
    status: TargetStatus = "tracking"
    generated_id: bool = False  # its id made up by the tracker (p<n>, a<n>, ...), not given
    uv: FloatArray = field(default_factory=lambda: _NAN2.copy())
    uv_right: FloatArray = field(default_factory=lambda: _NAN2.copy())
    point_cam: FloatArray = field(default_factory=lambda: _NAN3.copy())
    cov_cam: FloatArray = field(default_factory=lambda: _NAN33.copy())
    disparity_px: float = float("nan")
    score: float = float("nan")
    predicted_uv: FloatArray = field(default_factory=lambda: _NAN2.copy())
    search_box: tuple[float, float, float, float] = (np.nan, np.nan, np.nan, np.nan)
    lost_reason: str | None = None
    age_frames: int = 0
    lost_frames: int = 0
    reanchors: int = 0
    slot: int = -1
    # The integer search's template cut on the image's pixel grid, and the target's offset from
    # its centre, px (None: the current template's values, resampled at the target: no offset).
    search_window: NDArray[np.float32] | None = None
    search_offset: FloatArray = field(default_factory=lambda: np.zeros(2))
    anchor_lin: FloatArray = field(default_factory=lambda: np.eye(2))  # anchor → image linear warp
    anchor_z_m: float = float("nan")  # depth when the anchor was taken (nan: not yet measured)
    # anchor_warp "plane": the anchor's pixel and frame, the rigid motion (anchor camera → camera
    # at the last step; NaN: unknown) and the surface plane measurements (m · X = 1, anchor camera)
    anchor_uv: FloatArray = field(default_factory=lambda: _NAN2.copy())
    anchor_frame: int = -1
    anchor_R: FloatArray = field(default_factory=lambda: np.full((3, 3), np.nan))
    anchor_t: FloatArray = field(default_factory=lambda: _NAN3.copy())
    planes: list[FloatArray] = field(default_factory=list)
    plane_m: FloatArray = field(default_factory=lambda: _NAN3.copy())  # their median
    anchor_body: tuple[int, FloatArray, FloatArray] | None = None  # (body frame generation, body → anchor camera)
    body_point: FloatArray = field(default_factory=lambda: _NAN3.copy())  # first 3D point, tracker's body frame

    @property
    def search(self) -> NDArray[np.float32]:
        """(size,size) the integer search's template: the current patch of the image itself
        (``search_offset`` from the target when cut on the pixel grid)."""
        return self.current_raw.values[0] if self.search_window is None else self.search_window

    def state(self) -> TargetState:
        lost = self.status == "lost"
        return TargetState(
            id=self.id,
            origin=self.origin,
            status=self.status,
            uv=self.uv.copy(),
            uv_right=_NAN2.copy() if lost else self.uv_right.copy(),
            point_cam=_NAN3.copy() if lost else self.point_cam.copy(),
            cov_cam=_NAN33.copy() if lost else self.cov_cam.copy(),
            score=float("nan") if lost else float(self.score),
            predicted_uv=self.predicted_uv.copy(),
            search_box=self.search_box,
            lost_reason=self.lost_reason if lost else None,
            age_frames=self.age_frames,
        )


@dataclass(frozen=True)
class StoredTarget:
    """A removed target kept whole (its templates, its anchor) so that it can be re-found later
    where it should be (:meth:`Tracker.restore_many`): the same surface texture, not whatever
    lies at that pixel then. Opaque outside the tracker; ``id`` is the target's."""

    id: str
    target: "_Target" = field(repr=False)


def _stack(ts: list[Templates]) -> Templates:
    return Templates(
        np.concatenate([t.values for t in ts]),
        np.concatenate([t.gx for t in ts]),
        np.concatenate([t.gy for t in ts]),
        np.concatenate([t.hessian_inv for t in ts]),
        np.concatenate([t.ok for t in ts]),
    )


@dataclass
class _FrameCache:
    index: int
    left: NDArray[np.uint8]
    right: NDArray[np.uint8]
    track: NDArray  # the left image the temporal fits use


class Tracker:
    """Holds the targets and tracks them frame by frame in both images.

    Args:
        rig: the stereo rig of the frames.
        params: tracking tunables.
        features: automatic selection tunables (method, count, ...).
        measure: point measurement tunables (shared with ``trackmeter measure``).
    """

    def __init__(self, rig: StereoRig, params: TrackerParams, features: FeatureParams, measure: MeasureParams) -> None:
        check_side_by_side(rig)
        measure.disparity_range_px(rig.rectification)  # an empty search range on this rig: refused once, here
        self.rig = rig
        self.params = params
        self.features = features
        # A target's first measurement is the same kind of fit as every later one (the
        # translation fit of match_epipolar): with measure's slanted fit its 3D point would move
        # between its first frame and the next on every slanted face, and a model grown from it
        # with it. Measured (estec, 20 s, three noise seeds): case (a) lateral error 1.28 mm
        # (median of the maxima) with the shift fit, 1.89 mm with the slanted one.
        #
        # Nor is a new point refused for a look-alike the search could not see (the unseen-rival
        # check): a candidate is measured over the whole disparity range, the body's depth not
        # yet known, so the range of most is cut by the image's edge, and an 8x8 self-match on
        # the solar panels' cells refused points the wider window had accepted (estec, 20 s,
        # three noise seeds: case (a) lateral 1.28 -> 1.87 mm). The tracker has its own guard
        # against a false stereo match: a new point is kept only at the body's disparity, and
        # every target is held to the rigid motion of the others.
        self.measure = replace(measure, subpixel_slanted=False, unseen_rival_check=False)
        self.rect = rig.rectification
        # Rectified → original remap tables, interpolated bilinearly at the sampled points (the
        # tables are smooth: far cheaper than projecting thousands of points every frame).
        self._maps = tuple(complex_map(*m) for m in self.rect.maps)
        self._targets: dict[str, _Target] = {}
        #: Targets whose refused anchor fits are never refitted with the scale held
        #: (``anchor_scale_fallback``): the a-priori model's points, set by the engine. A model
        #: corner kept on a held fit holds the body frame where its appearance slid it: on the
        #: 60 s estec case-(b) run the attitude error about the lateral axes grew from 0.89 to
        #: 1.55 deg (docs/results.md, Tracking).
        self.strict_anchor_ids: frozenset[str] = frozenset()
        #: Ids a new target is never given unasked (:meth:`reserve_ids`): the a-priori model's,
        #: which name their points as freely as the engine names targets (p1, a1, ...); a plain
        #: click made "p1" was bound to model point p1 by name, wherever it was.
        self._model_ids: set[str] = set()
        # Names given to targets that the counter has yet to reach (an operator's "a90").
        self._named_ahead: set[str] = set()
        self._next_number = 1  # of the next generated id (p<n>, a<n>, m<n>, t<n>)
        # The prefix each number was handed out with (0: skipped): which ids this tracker made
        # up (:meth:`_made_up`), one byte a target, where a set of the names would be ~60.
        self._prefix_of = bytearray()
        self._auto = bool(params.auto)
        self._auto_count = features.count
        self._auto_method = features.method
        # Reference pairwise 3D distances (and their variances) for the rigid-body check,
        # indexed by each target's slot.
        self._ref_d = np.full((0, 0), np.nan)
        self._ref_v = np.full((0, 0), np.nan)
        self._free_slots: list[int] = []
        self.last_losses: dict[str, str] = {}
        # Lost automatic targets the top-up removed in the last step, whole (:meth:`take_removed`;
        # each step starts it over, so nothing piles up where no one takes them).
        self._removed: dict[str, StoredTarget] = {}
        self._last_top_up: int | None = None
        self.stats = {"losses": 0, "recoveries": 0, "reanchors": 0, "added": 0, "auto_added": 0}
        # Why automatic selection's candidates did not become targets (reason -> count): when it
        # starts none at all (images too dark, no texture), the run can say why.
        self.auto_refusals: collections.Counter[str] = collections.Counter()
        # Why the last top-up started no target while no automatic target is alive (its most
        # frequent reason), else None: an operator's "Automatic selection" that does nothing
        # says why in the console (a top-up that adds none beside live ones is no news).
        self.auto_shortfall: str | None = None
        self._motion_gate = float(chi2.ppf(params.motion_gate_probability, 3))
        # The rigid motion (R (3,3), t (3,)) from the tracker's body frame to the camera at the
        # last step, fitted to the targets' first points (:meth:`_body_drift`); None: unknown.
        self._body: tuple[FloatArray, FloatArray] | None = None
        # This step's frame-to-frame rigid motion (previous camera → camera), None: unknown.
        self._delta: tuple[FloatArray, FloatArray] | None = None
        # The last known one and the steps since it (anchor_warp "plane" carries it over gaps).
        self._last_delta: tuple[FloatArray, FloatArray] | None = None
        self._delta_age = 0
        # Whether the targets' anchor motions already reach this step's frame (composed after its
        # fit): the warp predicted for a re-lock after the step is then not moved a frame on.
        self._anchor_motion_current = False
        self._last_step_t_s: float | None = None  # time of the last step's frame, s
        self._step_dt_s = 0.0  # interval of this step (the rigid motion's), s
        self._body_gen = 0  # counts the body frames started (:meth:`_body_drift`)
        # The last frame's images as the fits read them, with the frame and the smoothing they
        # were made for: a step, its re-locks and its new targets all read the same frame, and
        # smoothing the whole left image is a millisecond each time.
        self._frame_cache: tuple[StereoFrame, float, _FrameCache] | None = None

    # ------------------------------------------------------------------ public state

    @property
    def targets(self) -> tuple[TargetState, ...]:
        """Every target's state after the last step (lost ones included)."""
        return tuple(t.state() for t in self._targets.values())

    @property
    def auto(self) -> tuple[bool, int, str]:
        """``(enabled, count, method)`` of automatic selection."""
        return self._auto, self._auto_count, self._auto_method

    def set_auto(self, enabled: bool, count: int | None = None, method: str | None = None) -> None:
        """Toggle automatic selection; optionally change how many targets it keeps and its method."""
        from trackmeter.core.features import METHODS

        if method is not None and method not in METHODS:
            raise TrackmeterError(f"unknown feature selection method {method!r} (known: {', '.join(METHODS)})")
        if count is not None:
            # A whole number only: int() took 2.7 as 2 and True as 1 without a word.
            whole = not isinstance(count, (bool, np.bool_)) and isinstance(count, (int, np.integer))
            if not whole or not 1 <= int(count) <= self.params.max_targets:
                raise TrackmeterError(f"automatic target count must be a whole number in [1, {self.params.max_targets}], "
                                      f"got {count!r}")
        self._auto = bool(enabled)
        if not self._auto:
            self.auto_shortfall = None
        if count is not None:
            self._auto_count = int(count)
        if method is not None:
            self._auto_method = method

    def generated_ids(self) -> frozenset[str]:
        """The ids of the targets whose id the tracker made up (not given by a click or a model)."""
        return frozenset(t.id for t in self._targets.values() if t.generated_id)

    def remove_target(self, target_id: str) -> bool:
        """Forget a target; False when there was none of that id."""
        t = self._targets.pop(target_id, None)
        if t is None:
            return False
        self._forget_distances(t)
        self._free_slots.append(t.slot)
        return True

    def detach(self, target_id: str) -> StoredTarget | None:
        """Remove a target and return it whole (None when there was none of that id)."""
        t = self._targets.get(target_id)
        if t is None:
            return None
        self.remove_target(target_id)
        t.slot = -1
        return StoredTarget(target_id, t)

    def take_removed(self) -> dict[str, StoredTarget]:
        """The lost automatic targets the last step's top-up removed, whole (each once)."""
        out, self._removed = self._removed, {}
        return out

    def restore_many(
        self, requests: Sequence[tuple[StoredTarget, tuple[float, float], ArrayLike, ArrayLike | None]], frame: StereoFrame
    ) -> list[TargetState | Refusal]:
        """Re-find stored targets, ``requests = [(stored, uv_predicted, point_cam_predicted (3,),
        image_warp)]``, as a lost target is re-found (:meth:`relock_many`: its own templates
        searched within ``recover_search_px`` of the prediction, the drift-free anchor must
        confirm, stereo re-match), but without the rigid-distance check: a target stored long
        ago has no reference distances to the targets tracked now, so the caller judges the 3D
        point (e.g. against a model through the pose). The search for the right-image match is
        centred on the predicted point's disparity.

        ``image_warp`` (2,2) or None: the linear map of the image around the point from the
        target's last tracked frame to this one, predicted (e.g. from the body's rotation since).
        Given, the anchor fit starts from the anchor's warp then composed with it, AT the
        predicted pixel (no integer search: the last template, unwarped, matches a patch turned
        since poorly), so the prediction must be good to about a pixel.

        A target re-found is tracked again under its id; one not found is not added. Either
        way the ``stored`` handle is left as it was (a re-found target the caller then removes,
        e.g. as a look-alike, can be tried again from it)."""
        results: list[TargetState | Refusal | None] = [None] * len(requests)
        targets: list[_Target] = []
        centres: list[FloatArray] = []
        slots: list[int] = []
        given: list[bool] = []
        for k, (stored, uv_predicted, point_cam, image_warp) in enumerate(requests):
            uvf = np.asarray(uv_predicted, dtype=float).reshape(2)
            key = (float(uvf[0]), float(uvf[1]))
            if stored.id in self._targets:
                results[k] = Refusal(key, f"a target named {stored.id!r} exists")
                continue
            if len(self._targets) >= self.params.max_targets:
                results[k] = Refusal(key, f"target limit reached ({self.params.max_targets} targets)")
                continue
            # Each attempt works on a copy (the tracker rebinds a target's fields, never writes
            # into them), so the handle stays as it was stored whatever becomes of the attempt.
            t = copy.copy(stored.target)
            P = np.asarray(point_cam, dtype=float).reshape(3)
            if not (np.all(np.isfinite(P)) and P[2] > 0):
                results[k] = Refusal(key, "predicted point is not in front of the camera")
                continue
            t.status, t.point_cam = "lost", P.copy()
            t.disparity_px = float(self.rect.project_rectified(P[None])[1][0])
            warp = None if image_warp is None else np.asarray(image_warp, dtype=float).reshape(2, 2)
            given.append(warp is not None and bool(np.all(np.isfinite(warp))))
            if given[-1]:
                assert warp is not None  # given[-1] says so
                t.anchor_lin = warp @ t.anchor_lin
            t.slot = self._new_slot()
            self._targets[t.id] = t
            targets.append(t)
            centres.append(uvf)
            slots.append(k)
        if targets:
            outcomes = self._try_recover(self._frame(frame), frame, targets, np.array(centres), check_rigid=False,
                                         at_centre=np.array(given))
            for k, t, uvf, (ok, reason) in zip(slots, targets, centres, outcomes):
                if ok:
                    results[k] = t.state()
                else:
                    self.remove_target(t.id)
                    results[k] = Refusal((float(uvf[0]), float(uvf[1])), reason or "not found")
        return results  # type: ignore[return-value]

    def _forget_distances(self, t: _Target) -> None:
        if 0 <= t.slot < len(self._ref_d):
            self._ref_d[t.slot, :] = self._ref_d[:, t.slot] = np.nan
            self._ref_v[t.slot, :] = self._ref_v[:, t.slot] = np.nan

    def _new_slot(self) -> int:
        if self._free_slots:
            return self._free_slots.pop()
        n = len(self._ref_d)
        grow = max(8, n)
        for name in ("_ref_d", "_ref_v"):
            old = getattr(self, name)
            new = np.full((n + grow, n + grow), np.nan)
            new[:n, :n] = old
            setattr(self, name, new)
        self._free_slots.extend(range(n + grow - 1, n, -1))
        return n

    def remove_nearest(self, uv: tuple[float, float], max_distance_px: float = REMOVE_NEAREST_PX,
                       exclude: Collection[str] = ()) -> str | None:
        """Remove the target whose left pixel is nearest to ``uv`` (within ``max_distance_px``),
        passing over the ids in ``exclude`` (targets the operator cannot see)."""
        best, best_d = None, max_distance_px
        for t in self._targets.values():
            if t.id in exclude:
                continue
            d = float(np.hypot(*(t.uv - np.asarray(uv, float))))
            if d <= best_d:
                best, best_d = t.id, d
        if best is not None:
            self.remove_target(best)
        return best

    def clear(self) -> None:
        """Remove every target."""
        self._targets.clear()
        self._ref_d = np.full((0, 0), np.nan)
        self._ref_v = np.full((0, 0), np.nan)
        self._free_slots = []
        self._body = None
        self._body_gen += 1
        # The removed targets' motion is no one's now: carried into new targets' anchors it
        # would give them a motion they did not make.
        self._delta = self._last_delta = None
        self._delta_age = 0

    # ------------------------------------------------------------------ frames

    def _set_search(self, fc: _FrameCache, t: _Target) -> None:
        """Cut ``t``'s integer-search template at its pixel ``t.uv`` (see ``search_on_pixel_grid``)."""
        if not self.params.search_on_pixel_grid:  # per target per frame: nothing to do when off
            return
        cut = grid_patch(fc.left, t.uv, self.params.patch_size)
        t.search_window, t.search_offset = (None, np.zeros(2)) if cut is None else cut

    def _search(self, fc: _FrameCache, t: _Target, centre: FloatArray, half: NDArray) -> tuple[FloatArray, float, float] | None:
        """:func:`zncc_search` of ``t``'s template for the target near ``centre`` (2,): where the
        target would be, its template's offset taken into account both ways."""
        if t.search_window is None:  # the resampled template: no offset
            return zncc_search(fc.left, t.search, centre, half)
        found = zncc_search(fc.left, t.search_window, np.asarray(centre, dtype=float) - t.search_offset, half)
        return None if found is None else (found[0] + t.search_offset, found[1], found[2])

    def _templates(self, fc: _FrameCache, uv: FloatArray) -> tuple[Templates, Templates]:
        """The templates at ``uv`` (N,2) for the sub-pixel fits (from the possibly smoothed image)
        and those of the image itself (its values: the integer search's templates)."""
        fit = make_templates(fc.track, uv, self.params.patch_size)
        raw = fit if fc.track is fc.left else make_templates(fc.left, uv, self.params.patch_size)
        return fit, raw

    def _frame(self, frame: StereoFrame) -> _FrameCache:
        sig = self.params.track_blur_sigma_px
        cached = self._frame_cache
        if cached is not None and cached[0] is frame and cached[1] == sig:
            return cached[2]
        # uint8 as delivered: the samplers gather from it and convert only what they read.
        left = np.ascontiguousarray(frame.left)
        track = cv2.GaussianBlur(left.astype(np.float32), (0, 0), sig) if sig > 0 else left
        fc = _FrameCache(frame.index, left, np.ascontiguousarray(frame.right), track)
        self._frame_cache = (frame, sig, fc)
        return fc

    # ------------------------------------------------------------------ adding targets

    def _check_click(self, left: NDArray[np.uint8], uv: FloatArray) -> str | None:
        p = self.params
        n = p.patch_size
        if not np.all(np.isfinite(uv)):
            return "not a finite pixel"
        margin = n / 2 + 2
        w, h = self.rig.image_size
        if not (margin - 0.5 <= uv[0] <= w - 0.5 - margin and margin - 0.5 <= uv[1] <= h - 0.5 - margin):
            return f"outside the image (the {n}x{n} patch must fit with a 2 px margin)"
        patch, _ = sample_patches(left, uv[None], n + 2)
        gx = 0.5 * (patch[0, 1:-1, 2:] - patch[0, 1:-1, :-2])
        gy = 0.5 * (patch[0, 2:, 1:-1] - patch[0, :-2, 1:-1])
        st = np.array([[np.mean(gx * gx), np.mean(gx * gy)], [np.mean(gx * gy), np.mean(gy * gy)]])
        lam = float(np.linalg.eigvalsh(st)[0])
        if lam < p.min_gradient_eig:
            return f"textureless patch in one direction (aperture problem: min gradient eigenvalue {lam:.1f})"
        return None

    def reserve_ids(self, ids: Iterable[str]) -> None:
        """Never generate these ids for a new target: a model's point ids (only those of the
        generated kind, p<n>, a<n>, m<n>, t<n>, are kept)."""
        self._model_ids.update(str(tid) for tid in ids if _GENERATED_ID.fullmatch(str(tid)))

    def _made_up(self, target_id: str) -> bool:
        """Whether ``target_id`` is one this tracker generated (and no model names since): a
        model point's target re-made under the id of the target it was grown from (``a17``)
        keeps that id's origin; an a-priori point named ``p0`` or ``p3`` never had it."""
        match = _GENERATED_ID.fullmatch(target_id)
        if match is None or target_id in self._model_ids:
            return False
        n = int(match.group(1))
        return 1 <= n <= len(self._prefix_of) and self._prefix_of[n - 1] == ord(target_id[0])

    def _new_id(self, origin: str) -> str:
        prefix = {"operator": "p", "auto": "a", "model": "m"}.get(origin, "t")
        while True:
            n = self._next_number
            self._next_number += 1
            tid = f"{prefix}{n}"
            if tid not in self._targets and tid not in self._model_ids and tid not in self._named_ahead:
                self._prefix_of.extend(bytes(n - 1 - len(self._prefix_of)))  # the numbers skipped
                self._prefix_of.append(ord(prefix))
                return tid

    def _velocity_guess(self, uv: FloatArray | None = None, point_cam: FloatArray | None = None
                        ) -> tuple[FloatArray, float | None]:
        """A new target's image velocity (2,) px/s and its std.

        With its 3D point ``point_cam`` (3,) at left pixel ``uv`` (2,) and this step's rigid
        motion of the tracked points (``P_now = R P_prev + t``, fitted by the motion check), the
        velocity the body's motion gives that point: ``(proj(R X + t) - uv) / dt`` (a turning
        body moves its points at different image speeds, which one median cannot give), with
        the std of the same prediction against the settled targets' own filtered velocities.
        Otherwise the median of the settled targets' velocities (one rigid body moves them all
        alike) with their spread; else zero with the wide default std (None)."""
        p = self.params
        settled = [t for t in self._targets.values() if t.status != "lost" and t.age_frames >= SETTLED_FRAMES]
        if len(settled) < 2:
            return np.zeros(2), None
        v = np.array([t.kf.x[2:4] for t in settled])
        if (p.rigid_velocity_guess and self._delta is not None and self._step_dt_s > 0 and uv is not None
                and point_cam is not None and np.all(np.isfinite(point_cam))):
            P = np.array([t.point_cam for t in settled])
            U = np.array([t.uv for t in settled])
            ok = np.all(np.isfinite(P), axis=1)
            if ok.sum() >= 2:
                predicted = self._rigid_image_velocity(np.vstack([P[ok], point_cam]), np.vstack([U[ok], uv]))
                miss = np.linalg.norm(predicted[:-1] - v[ok], axis=1)
                return predicted[-1], float(np.median(miss)) + p.rigid_velocity_sigma_px_s
        med = np.median(v, axis=0)
        spread = float(np.max(np.abs(v - med)))
        return med, spread + p.neighbour_velocity_sigma_px_s

    def _rigid_image_velocity(self, P: FloatArray, uv: FloatArray) -> FloatArray:
        """Left-image velocities (N,2) px/s of points ``P`` (N,3) at pixels ``uv`` (N,2) moved by
        this step's rigid motion over this step's interval."""
        R, t = self._delta  # type: ignore[misc]
        moved, _ = self.rig.project(P @ R.T + t)
        return (moved - uv) / self._step_dt_s

    def add_target(
        self,
        frame: StereoFrame,
        uv: tuple[float, float],
        target_id: str | None = None,
        origin: TargetOrigin = "operator",
        in_place_of: str | None = None,
        replace_lost: bool = False,
        replace_remade: bool = False,
    ) -> TargetState | Refusal:
        """Create a target at left pixel ``uv`` (ORIGINAL image, px) of ``frame``.

        Refused (with the reason) when: the target limit is reached, the id exists, the pixel is
        outside the image, the patch is black space or textureless, or it has no strong, unique
        stereo match along its epipolar line — as a measurement of that point would be.
        ``in_place_of``: at the limit, the target the new one replaces, removed only once the
        new one is made (a refused click costs no target). ``replace_lost``: a lost target of
        ``target_id`` is no refusal but replaced, likewise only once the new one is made;
        ``replace_remade``: so is one made at a model point's projection (origin ``"model"``).
        """
        uvf = np.asarray(uv, dtype=float).reshape(2)
        key = (float(uvf[0]), float(uvf[1]))
        old = self._targets.get(target_id) if target_id is not None else None
        replaceable = old is not None and ((replace_lost and old.status == "lost")
                                           or (replace_remade and old.origin == "model"))
        if old is not None and not replaceable:
            return Refusal(key, f"a target named {target_id!r} exists")
        full = old is None and len(self._targets) >= self.params.max_targets
        if full and in_place_of not in self._targets:
            return Refusal(key, f"target limit reached ({self.params.max_targets} targets)")
        # Refused exactly as a measurement of the point would be (paper 2.A, H2's matcher)...
        meas = measure_points(self.rig, frame.left, frame.right, uvf[None], self.measure)[0]
        order = list(self._targets) if old is not None else []
        if old is not None:
            del self._targets[old.id]  # out of the way of its successor; back in its place if refused
        result = self._create(frame, uvf, meas, target_id, origin)
        if old is not None:
            if isinstance(result, Refusal):
                self._targets[old.id] = old
                self._targets = {tid: self._targets[tid] for tid in order}
            else:
                self._forget_distances(old)
                self._free_slots.append(old.slot)
        if full and in_place_of is not None and not isinstance(result, Refusal):
            self.remove_target(in_place_of)
        return result

    def _create(
        self, frame: StereoFrame, uvf: FloatArray, meas: PointMeasurement, target_id: str | None, origin: TargetOrigin,
        first: tuple[Any, int] | None = None,
    ) -> TargetState | Refusal:
        """A new target at ``uvf`` (2,) from its measurement ``meas`` (:func:`measure_points`), or the refusal.
        ``first``: its first stereo match (an :class:`EpipolarMatch` and the row) where
        ``still_camera_fits`` asks for one and the caller batched it (:meth:`_first_matches`)."""
        key = (float(uvf[0]), float(uvf[1]))
        if not meas.ok:
            return Refusal(key, str(meas.reason))
        # ... and where it could not be tracked (patch too close to the border, aperture problem).
        fc = self._frame(frame)
        reason = self._check_click(fc.left, uvf)
        if reason is not None:
            return Refusal(key, reason)
        tid = target_id or self._new_id(origin)
        match = _GENERATED_ID.fullmatch(target_id) if target_id else None
        if match is not None and int(match.group(1)) >= self._next_number:
            assert target_id is not None  # it matched
            self._named_ahead.add(target_id)  # an operator's "a90" is not generated again once lost
        tmpl, search = self._templates(fc, uvf[None])
        v0, sv = self._velocity_guess(uvf, np.asarray(meas.xyz_m, float))
        kf = kf_mod.make_filter(uvf, self.params.kalman, velocity_px_s=v0, velocity_sigma_px_s=sv)
        t = _Target(tid, origin, kf, tmpl, tmpl, frame.t_s, search, search, uv=uvf.copy(), predicted_uv=uvf.copy(),
                    generated_id=not target_id or (origin == "model" and self._made_up(target_id)))
        self._new_anchor(t, frame.index)
        self._set_search(fc, t)
        t.slot = self._new_slot()
        t.disparity_px = float(meas.disparity_px)
        t.point_cam = np.asarray(meas.xyz_m, float).copy()
        t.cov_cam = np.asarray(meas.cov_m, float).copy()
        t.uv_right = np.asarray(meas.right_uv, float).copy()
        t.score = float(meas.score)
        # Its first 3D point from the tracker's own stereo match, as every later one: measure's
        # match (a strip sampled otherwise) differs from it by up to 0.2 px of disparity on a
        # sharp image, which the rigid-motion check saw, one frame on, as the point moving.
        if self.params.still_camera_fits:
            m, j = first if first is not None else (self._first_matches(fc, uvf[None], np.array([t.disparity_px])), 0)
            if m.reason[j] is None:
                self._set_stereo([t], m, np.array([j]))
        if self._body is not None:
            R, tvec = self._body
            t.body_point = R.T @ (t.point_cam - tvec)
        n2 = self.params.patch_size / 2
        t.search_box = (uvf[0] - n2, uvf[1] - n2, uvf[0] + n2, uvf[1] + n2)
        self._targets[tid] = t
        self._set_reference_distances(t)
        self.stats["added"] += 1
        return t.state()

    def _set_reference_distances(self, t: _Target) -> None:
        """Remember a new (or just verified, recovered) target's 3D distances to the targets
        measured now where none is known yet, so its next step is already checked against the
        rigid body (a jump to a look-alike is caught)."""
        others = [o for o in self._targets.values() if o is not t and o.status != "lost"]
        for o in others:
            diff = t.point_cam - o.point_cam
            dist = float(np.linalg.norm(diff))
            if not np.isfinite(dist):
                continue
            if np.isfinite(self._ref_d[t.slot, o.slot]):
                continue  # keep the older reference
            u = diff / max(dist, 1e-12)
            var = float(u @ (t.cov_cam + o.cov_cam) @ u)
            self._ref_d[t.slot, o.slot] = self._ref_d[o.slot, t.slot] = dist
            self._ref_v[t.slot, o.slot] = self._ref_v[o.slot, t.slot] = var

    def relock(self, target_id: str, uv_predicted: tuple[float, float], frame: StereoFrame) -> TargetState | Refusal:
        """Re-lock a (lost) target near ``uv_predicted`` (e.g. a model point reprojected through
        the current pose, paper 2.D): anchor-template search in ``recover_search_px``, strict
        score, stereo re-match. The target is ``recovered`` on success."""
        return self.relock_many([(target_id, uv_predicted)], frame)[0]

    def relock_many(
        self, requests: Sequence[tuple[str, tuple[float, float]]], frame: StereoFrame
    ) -> list[TargetState | Refusal]:
        """:meth:`relock` for several targets at once, ``requests`` = ``[(target_id, uv_predicted)]``;
        one result per request, in order. The searches, the sub-pixel fits and the stereo
        matches are each one batched call (most of their cost is per call, not per target)."""
        results: list[TargetState | Refusal | None] = [None] * len(requests)
        targets: list[_Target] = []
        centres: list[FloatArray] = []
        slots: list[int] = []
        for k, (target_id, uv_predicted) in enumerate(requests):
            uvf = np.asarray(uv_predicted, dtype=float).reshape(2)
            t = self._targets.get(target_id)
            if t is None:
                results[k] = Refusal((float(uvf[0]), float(uvf[1])), f"no target named {target_id!r}")
                continue
            if any(s is t for s in targets):  # one target re-found twice would count twice
                results[k] = Refusal((float(uvf[0]), float(uvf[1])), f"{target_id!r} is asked for twice")
                continue
            targets.append(t)
            centres.append(uvf)
            slots.append(k)
        if targets:
            outcomes = self._try_recover(self._frame(frame), frame, targets, np.array(centres))
            for k, t, uvf, (ok, reason) in zip(slots, targets, centres, outcomes):
                results[k] = t.state() if ok else Refusal((float(uvf[0]), float(uvf[1])), reason or "not found")
        return results  # type: ignore[return-value]

    # ------------------------------------------------------------------ stereo

    def _stereo(self, fc: _FrameCache, uv: FloatArray, d_low: FloatArray, span: int | NDArray) -> EpipolarMatch:
        p = self.params
        cl = self.rect.rectify_points(uv, 0)
        return match_epipolar(
            fc.left,
            fc.right,
            self._maps[0],
            self._maps[1],
            cl,
            d_low,
            span,
            p.patch_size,
            min_score=p.stereo_min_score,
            uniqueness_margin=p.uniqueness_margin,
            epipolar_tolerance_px=p.epipolar_tolerance_px,
            row_fit=self.measure if p.stereo_row_fit else None,
            whole_disparity=p.still_camera_fits,
        )

    def _first_matches(self, fc: _FrameCache, uv: FloatArray, disparity_px: FloatArray) -> EpipolarMatch:
        """New targets' first stereo matches at left pixels ``uv`` (N,2), one batched
        :meth:`_stereo` around their measured disparities (N,), as a tracked target's next is."""
        ss = self.params.stereo_search_px
        return self._stereo(fc, uv, np.asarray(disparity_px, float) - ss, np.full(len(uv), 2 * ss))

    def _set_stereo(self, ts: list[_Target], m: EpipolarMatch, idx: NDArray) -> None:
        """Triangulate matches ``idx`` of ``m`` (batched) into targets ``ts``."""
        if len(ts) == 0:
            return
        p = self.params
        cl = m.uv_rect_left[idx]
        d = m.disparity_px[idx]
        P = self.rect.triangulate(cl, d)
        C = self.rect.point_covariance(cl, d, p.sigma_disparity_px, p.sigma_uv_px)
        # The right pixel the point is measured from: on the left pixel's row at the disparity
        # (as measure's right_uv), not the 2D fit's, whose vertical offset only checks the match.
        right_rect = cl.copy()
        right_rect[:, 0] -= d
        R = self.rect.unrectify_points(right_rect, 1)
        for k, t in enumerate(ts):
            t.disparity_px = float(d[k])
            t.point_cam = P[k]
            t.cov_cam = C[k]
            t.uv_right = R[k]
            t.score = float(m.score[idx[k]])  # the state's score: this stereo match's ZNCC

    # ------------------------------------------------------------------ recovery

    def _try_recover(
        self, fc: _FrameCache, frame: StereoFrame, targets: list[_Target], centres: FloatArray, check_rigid: bool = True,
        at_centre: NDArray[np.bool_] | None = None,
    ) -> list[tuple[bool, str | None]]:
        """Re-find lost ``targets`` near ``centres`` (N,2) (the step batches the same pieces for
        its own lost targets); returns ``(recovered, why not)`` per target. ``check_rigid``: the
        re-found point must keep its reference distances (:meth:`_rigid_recheck`). ``at_centre``
        (N,): the sub-pixel fit starts at the centre itself, no integer search (a prediction
        good to a pixel, with the anchor's warp predicted too)."""
        centres = np.asarray(centres, dtype=float).reshape(-1, 2)
        i: int | np.integer  # a row of targets: np.flatnonzero's, then found_i's
        if at_centre is None:
            out, found_i, starts = self._recover_search(fc, targets, centres)
        else:
            searched = np.flatnonzero(~np.asarray(at_centre, bool))
            out_s, found_s, starts_s = self._recover_search(fc, [targets[i] for i in searched], centres[searched])
            out = [(False, None)] * len(targets)
            for i, o in zip(searched, out_s):
                out[i] = o
            start_of = {int(searched[k]): st for k, st in zip(found_s, starts_s)}
            start_of.update({int(i): centres[i] for i in np.flatnonzero(at_centre)})
            found_i = sorted(start_of)
            starts = [start_of[i] for i in found_i]
        if not found_i:
            return out
        found = [targets[i] for i in found_i]
        res = self._fit_patches(fc, found, np.array(starts))
        refined = self._recover_refined(res, np.arange(len(found)), found_i, out)
        if not refined:
            return out
        lo, span = self._recover_disparities([found[k] for k in refined])
        m = self._stereo(fc, res.uv[refined], lo, span)
        for j, k in enumerate(refined):
            i = found_i[k]
            out[i] = self._recover_accept(fc, frame, targets[i], centres[i], res, k, m, j, check_rigid)
        return out

    def _recover_disparities(self, targets: list[_Target]) -> tuple[FloatArray, NDArray]:
        """Disparity search of re-found targets ``(d_low (N,), span (N,))``: twice the tracking
        search around the last disparity (the target was not followed while lost)."""
        ss = self.params.stereo_search_px
        lo = np.array([t.disparity_px - 2 * ss for t in targets], dtype=float)
        return lo, np.full(len(targets), 4 * ss)

    def _recover_search(
        self, fc: _FrameCache, targets: list[_Target], centres: FloatArray
    ) -> tuple[list[tuple[bool, str | None]], list[int], list[FloatArray]]:
        """Integer search for lost targets: ``(outcomes so far, indices found, start points)``."""
        p = self.params
        out: list[tuple[bool, str | None]] = [(False, None)] * len(targets)
        half = np.array([p.recover_search_px, p.recover_search_px])
        found_i: list[int] = []
        starts: list[FloatArray] = []
        for i, (t, centre) in enumerate(zip(targets, centres)):
            # The current template is the last verified appearance of the target.
            found = self._search(fc, t, centre, half)
            if found is None:
                out[i] = (False, "search window outside the image")
                continue
            uv0, best, second = found
            if best < p.recover_min_score or second > best - p.ambiguity_margin:
                out[i] = (False, f"not found (score {best:.2f})")
                continue
            found_i.append(i)
            starts.append(uv0)
        return out, found_i, starts

    def _recover_refined(self, res: PatchTrack, rows: NDArray, found_i: list[int], out: list[tuple[bool, str | None]]) -> list[int]:
        """Which re-found targets (rows ``rows`` of ``res``, outcome slots ``found_i``) the
        drift-free sub-pixel fit confirms; returns their positions in ``rows``."""
        p = self.params
        refined: list[int] = []
        for k, r in enumerate(rows):
            if not res.converged[r] or res.score[r] < p.recover_min_score:
                out[found_i[k]] = (False, "sub-pixel refinement failed")
            elif not res.anchored[r]:
                # Only the drift-free anchor may re-find a target: the current template is the
                # one that was last seen where tracking failed, and a look-alike matches it as well.
                out[found_i[k]] = (False, "the anchor template does not confirm the re-found patch")
            else:
                refined.append(k)
        return refined

    def _recover_accept(
        self, fc: _FrameCache, frame: StereoFrame, t: _Target, centre: FloatArray, res: PatchTrack, r: int,
        m: EpipolarMatch, j: int,
        check_rigid: bool = True,
    ) -> tuple[bool, str | None]:
        """Finish re-finding ``t`` from row ``r`` of the patch fit and row ``j`` of the stereo match."""
        p = self.params
        if m.reason[j] is not None:
            return False, m.reason[j]
        # Without a model, a look-alike elsewhere on the body is the danger: the recovered
        # 3D point must keep its old distances to the targets tracked now (rigid body).
        why = self._rigid_recheck(t, m, j) if check_rigid else None
        if why is None and p.body_check:
            P = self.rect.triangulate(m.uv_rect_left[j : j + 1], m.disparity_px[j : j + 1])
            drift = self._body_offsets_px(P, t.body_point[None])[0]
            if drift > p.body_drift_px:
                why = f"re-found point is {drift:.1f} px from where the rigid body puts it"
        if why is not None:
            return False, why
        uv = res.uv[r]
        half = p.recover_search_px
        t.uv = uv.copy()
        t.predicted_uv = np.array(centre, dtype=float)
        t.search_box = (centre[0] - half, centre[1] - half, centre[0] + half, centre[1] + half)
        self._set_stereo([t], m, np.array([j]))
        v0, sv = self._velocity_guess(uv, t.point_cam)
        t.kf = kf_mod.make_filter(uv, p.kalman, velocity_px_s=v0, velocity_sigma_px_s=sv)
        t.anchor_lin = res.anchor_lin[r].copy()
        t.current, t.current_raw = self._templates(fc, uv[None])
        self._set_search(fc, t)
        t.status = "recovered"
        t.lost_reason = None
        t.lost_frames = 0
        t.t_s = frame.t_s
        self._set_reference_distances(t)
        self.stats["recoveries"] += 1
        return True, None

    def _fit_patches(self, fc: _FrameCache, ts: list[_Target], starts: FloatArray) -> PatchTrack:
        """The drift-free sub-pixel fit (:func:`track_patches`) of targets ``ts`` from ``starts`` (N,2)."""
        p = self.params
        recheck = fc.track is not fc.left and p.track_blur_recheck_px > 0
        return track_patches(
            fc.track,
            _stack([t.anchor for t in ts]),
            np.array([t.anchor_lin for t in ts]),
            _stack([t.current for t in ts]),
            starts,
            anchor_min_score=p.anchor_min_score,
            drift_tolerance_px=p.drift_tolerance_px,
            anchor_warp=p.anchor_warp,
            anchor_tolerance_px=p.anchor_tolerance_px,
            expected_scale=self._expected_scale(ts),
            max_scale_error=p.anchor_max_scale_error,
            predicted_lin=self._predicted_lin(ts) if p.anchor_warp == "plane" else None,
            raw_image=fc.left if recheck else None,
            raw_anchor=_stack([t.anchor_raw for t in ts]) if recheck else None,
            raw_current=_stack([t.current_raw for t in ts]) if recheck else None,
            raw_tolerance_px=p.track_blur_recheck_px,
            scale_fallback=self._scale_fallback_rows(ts),
        )

    def _scale_fallback_rows(self, ts: Sequence[_Target]) -> NDArray[np.bool_]:
        """Which of ``ts`` get the scale-held anchor refit (``anchor_scale_fallback``), (N,)."""
        mode = self.params.anchor_scale_fallback
        return np.array([(mode == "all" or (mode == "operator" and t.origin == "operator")) and t.id not in self.strict_anchor_ids
                         for t in ts], dtype=bool)

    # ------------------------------------------------------------------ the step

    def _search_near_first(
        self, fc: _FrameCache, t: _Target, pred: FloatArray, half: FloatArray
    ) -> tuple[FloatArray, float, float] | None:
        """:func:`zncc_search` of a wide window's centre (``near_first_px`` around the prediction
        ``pred`` (2,)), when it finds a unique good match there; else None (search the window).

        A target's window is 4 predicted standard deviations, so it widens fast as the frame
        interval does: a new target's (velocity 0 +- 50 px/s, acceleration 0 +- 1000 px/s²) is
        +-8.6 px at 25 Hz, +-20 at 12.5 Hz and +-60 at 6.25 Hz, a settled one's +-3, +-7.9 and
        +-27 px. A wide window on a repeated texture (a solar panel's grid) holds peaks alike
        and the target is lost as ambiguous, while most targets moved little. So a window wider
        than ``near_first_new_above_px`` (``near_first_settled_above_px`` once the target is
        settled) is first searched near its prediction, and a match taken there only if it
        scores ``min_score``, beats the near window's other peaks by ``ambiguity_margin`` and is
        off its border (a best on the border may be the flank of a peak outside); a fast target
        finds no such match there and gets the whole window. The thresholds leave 25 Hz's
        windows alone: searched near first, new targets at 25 Hz took estec case (a)'s largest
        lateral error from 1.28 to 1.62 mm (median of three noise seeds, 20 s)."""
        p = self.params
        above = p.near_first_settled_above_px if t.age_frames >= SETTLED_FRAMES else p.near_first_new_above_px
        if p.near_first_px <= 0 or max(float(half[0]), float(half[1])) <= above:  # floats: run per target per frame
            return None
        near = self._search(fc, t, pred, np.minimum(half, p.near_first_px))
        if near is None or np.any(np.abs(near[0] - pred) > p.near_first_px - 1.0):
            return None
        _, best, second = near
        return near if best >= p.min_score and second <= best - p.ambiguity_margin else None

    def _lose(self, t: _Target, reason: str) -> None:
        t.status = "lost"
        t.lost_reason = reason
        t.lost_frames = 0
        self.last_losses[t.id] = reason
        self.stats["losses"] += 1
        # Its reference distances are kept: a recovery must agree with them.

    def step(
        self,
        frame: StereoFrame,
        reject_ids: Collection[str] = (),
    ) -> tuple[TargetState, ...]:
        """Track every target into ``frame``; returns all targets' states (see module doc)."""
        p = self.params
        fc = self._frame(frame)
        self.last_losses = {}
        self._removed = {}
        self._delta = None
        self._anchor_motion_current = False
        self._step_dt_s = frame.t_s - self._last_step_t_s if self._last_step_t_s is not None else 0.0
        self._last_step_t_s = frame.t_s
        live = [t for t in self._targets.values() if t.status != "lost"]
        lost = [t for t in self._targets.values() if t.status == "lost"]
        final: list[tuple[_Target, bool]] = []
        for t in self._targets.values():
            t.age_frames += 1
        for t in lost:
            t.lost_frames += 1

        # 1-2. predict, search, refine with the current template.
        searched: list[_Target] = []
        starts = []
        n2 = p.patch_size / 2
        kf_mod.predict_many([t.kf for t in live], [max(frame.t_s - t.t_s, 0.0) for t in live], p.kalman)
        halves = kf_mod.search_half_sizes([t.kf for t in live], p.kalman, p.min_search_px, p.max_search_px)
        for t, half in zip(live, halves):
            t.t_s = frame.t_s
            pred = t.kf.x[:2].copy()
            t.predicted_uv = pred
            t.search_box = (pred[0] - half[0] - n2, pred[1] - half[1] - n2, pred[0] + half[0] + n2, pred[1] + half[1] + n2)
            if not np.all(np.isfinite(pred)):
                self._lose(t, "prediction diverged")
                continue
            found = self._search_near_first(fc, t, pred, half) or self._search(fc, t, pred, half)
            if found is None:
                self._lose(t, "left the image")
                continue
            uv0, best, second = found
            if best < p.min_score:
                self._lose(t, f"low match score ({best:.2f})")
                continue
            if second > best - p.ambiguity_margin:
                self._lose(t, f"ambiguous in the search window (scores {best:.2f}, {second:.2f})")
                continue
            searched.append(t)
            # The search puts the patch's centre on a half-pixel grid, up to 0.7 px from where
            # the target is; a prediction the search agrees with is nearer: on a still sharp
            # image the anchor's similarity fit, started 0.7 px off, used up its iterations
            # short of converging and the target was lost.
            near = p.still_camera_fits and float(np.max(np.abs(np.asarray(uv0) - pred))) <= SEARCH_CELL_PX
            starts.append(pred.copy() if near else uv0)
        # Lost targets due for recovery (where they were lost, no model) join the same batched
        # fit and stereo match: each batched call has a fixed cost that dwarfs a few patches.
        due = [t for t in lost if p.recover_lost and t.lost_frames % p.recover_interval_frames == 0]
        rec_out, rec_found, rec_starts = self._recover_search(fc, due, np.array([t.uv for t in due], dtype=float).reshape(-1, 2))
        rec_ts = [due[i] for i in rec_found]
        n_s = len(searched)
        if searched or rec_ts:
            res = self._fit_patches(fc, searched + rec_ts, np.array(starts + rec_starts, dtype=float).reshape(-1, 2))
            uv_all, anchored = res.uv, res.anchored
            w, h = self.rig.image_size
            inner = (uv_all[:, 0] >= n2 + 1) & (uv_all[:, 0] <= w - n2 - 2) & (uv_all[:, 1] >= n2 + 1) & (uv_all[:, 1] <= h - n2 - 2)
        survivors: list[tuple[_Target, FloatArray, bool]] = []
        matched: list[int] = []
        for i, t in enumerate(searched):
            if not res.converged[i]:
                self._lose(t, "sub-pixel match did not converge")
            elif res.score[i] < p.min_score:
                self._lose(t, f"low match score ({res.score[i]:.2f})")
            elif not inner[i]:
                self._lose(t, "left the image")
            else:
                matched.append(i)
        # 3. gating on the innovation, and the filter update (batched).
        accepted, d2 = kf_mod.update_many([searched[i].kf for i in matched], uv_all[matched] if matched else np.zeros((0, 2)), p.kalman)
        for j, i in enumerate(matched):
            t = searched[i]
            if not accepted[j]:
                self._lose(t, f"jump rejected by the filter (Mahalanobis² {d2[j]:.1f})")
                continue
            if anchored[i]:
                t.anchor_lin = res.anchor_lin[i].copy()
            survivors.append((t, uv_all[i], bool(anchored[i])))

        rec_refined = self._recover_refined(res, n_s + np.arange(len(rec_ts)), rec_found, rec_out) if rec_ts else []

        # 4. right-image re-match near the previous disparity (re-found targets: twice as wide).
        m = None
        if survivors or rec_refined:
            ss = p.stereo_search_px
            uv = np.array([s[1] for s in survivors] + [res.uv[n_s + k] for k in rec_refined]).reshape(-1, 2)
            rec_lo, rec_spans = self._recover_disparities([rec_ts[k] for k in rec_refined])
            lo = np.concatenate([[s[0].disparity_px - ss for s in survivors], rec_lo])
            spans = np.concatenate([np.full(len(survivors), 2 * ss), rec_spans]).astype(int)
            m = self._stereo(fc, uv, lo, spans)
        if survivors:
            assert m is not None  # matched with the survivors above
            good = []
            for i, (t, uvi, _) in enumerate(survivors):
                if m.reason[i] is not None:
                    self._lose(t, cast(str, m.reason[i]))  # mypy narrows no item at a variable index
                    continue
                t.uv = uvi.copy()
                good.append(i)
            kept = [(survivors[i][0], survivors[i][2]) for i in good]
            prev_P = np.array([t.point_cam for t, _ in kept]).reshape(-1, 3)
            prev_C = np.array([t.cov_cam for t, _ in kept]).reshape(-1, 3, 3)
            self._set_stereo([t for t, _ in kept], m, np.array(good, dtype=int))
            # 5. rigid-body consistency: this frame's motion, then the distances since creation.
            if p.motion_check and kept:
                for tid, why in self._motion_outliers([t for t, _ in kept], prev_P, prev_C).items():
                    self._lose(self._targets[tid], why)
            if p.body_check:
                for tid, why in self._body_drift([t for t, _ in kept if t.status != "lost"]).items():
                    self._lose(self._targets[tid], why)
            elif p.anchor_warp == "plane" and kept:
                # the body's motion for the anchors' (the drift check itself is off: nobody lost)
                self._body_drift([t for t, _ in kept if t.status != "lost"])
            if p.rigid_check and kept:
                bad = self._rigid_inconsistent([t for t, _ in kept if t.status != "lost"])
                for tid, why in bad.items():
                    self._lose(self._targets[tid], why)
            final = []
            for t, anch in kept:
                if t.status == "lost" and t.lost_reason is not None and t.id not in reject_ids:
                    continue
                if t.id in reject_ids:
                    if t.status != "lost":
                        self._lose(t, "rejected by the pose estimator")
                    continue
                t.status = "tracking"
                final.append((t, anch))
            # Template strategy: refresh the current template where the anchor confirmed the
            # match; re-anchor on this verified match when the anchor no longer fits.
            if final:
                new, raw = self._templates(fc, np.array([t.uv for t, _ in final]))
                for k, (t, anch) in enumerate(final):
                    if not new.ok[k]:
                        continue
                    # A slice: views of the batch's arrays (templates are never written to),
                    # not five fancy-indexed copies per target and frame.
                    one = new.select(slice(k, k + 1))
                    one_raw = one if raw is new else raw.select(slice(k, k + 1))
                    t.current, t.current_raw = one, one_raw
                    self._set_search(fc, t)
                    if not anch:
                        self._new_anchor(t, frame.index)
                        t.anchor, t.anchor_raw = one, one_raw
                        t.anchor_lin = np.eye(2)
                        t.anchor_z_m = float(t.point_cam[2])
                        t.reanchors += 1
                        self.stats["reanchors"] += 1

        if p.anchor_warp == "plane":
            self._carry_anchor_motion(frame.index)
            if frame.index % p.plane_interval_frames == 0:
                self._measure_planes(fc, [t for t, _ in final if t.status == "tracking"], frame.index)

        # Recovery of lost targets where they were lost (no model), after the tracked ones were
        # updated: their fresh 3D points are what a re-found point's distances are checked against.
        for j, k in enumerate(rec_refined):
            assert m is not None  # matched with rec_refined above
            t = rec_ts[k]
            self._recover_accept(fc, frame, t, t.uv.copy(), res, n_s + k, m, len(survivors) + j)
        for t in lost:
            if t.status == "lost":
                t.t_s = frame.t_s

        if self._auto:
            self._top_up(frame, fc)
        return self.targets

    def _expected_scale(self, targets: list[_Target]) -> FloatArray:
        """Image scale of each target's anchor implied by its depth change, ``z_anchor / z``
        (pinhole: image size ~ 1/depth), from the last measured depth; 1 where unknown."""
        out = np.ones(len(targets))
        for i, t in enumerate(targets):
            z = float(t.point_cam[2])
            if not np.isfinite(t.anchor_z_m) and np.isfinite(z):
                t.anchor_z_m = z  # the first depth measured is the anchor's (taken at creation)
            if np.isfinite(t.anchor_z_m) and np.isfinite(z) and z > 0:
                out[i] = t.anchor_z_m / z
        return out

    # ------------------------------------------------------------------ anchor_warp "plane"

    def _step_delta(self) -> tuple[FloatArray, FloatArray] | None:
        """The rigid motion (last camera → camera) of this step: the fitted one, else the last
        known one for up to 3 steps (the body turns ~0.15 deg per frame: a frame's gap adds
        about that to the predicted warp's angle), else None."""
        if self._delta is not None:
            return self._delta
        return self._last_delta if self._delta_age < 3 else None

    def _anchor_motion(self, t: _Target) -> tuple[FloatArray, FloatArray]:
        """``t``'s rigid motion (R (3,3), t (3,)) from its anchor camera to the camera of the
        last body fit: from the body's pose then and at the anchor (no error accumulates), else
        the frame-to-frame motions composed since the anchor (NaN when unknown)."""
        if t.anchor_body is not None and self._body is not None and t.anchor_body[0] == self._body_gen:
            _, Ra, ta = t.anchor_body
            Rb, tb = self._body
            R = Rb @ Ra.T
            return R, tb - R @ ta
        return t.anchor_R, t.anchor_t

    def _new_anchor(self, t: _Target, index: int) -> None:
        """``t``'s anchor is (re)taken at its current pixel in frame ``index``: its motion starts
        at identity, its plane measurements are carried into the new anchor frame."""
        R, tv = self._anchor_motion(t) if t.anchor_frame < index else (np.eye(3), np.zeros(3))
        if t.planes and np.all(np.isfinite(R)) and np.all(np.isfinite(tv)):
            t.planes = list(transform_plane(np.array(t.planes), np.broadcast_to(R, (len(t.planes), 3, 3)),
                                            np.broadcast_to(tv, (len(t.planes), 3))))
        else:
            t.planes = []
        t.plane_m = np.median(np.array(t.planes), axis=0) if t.planes else _NAN3.copy()
        t.anchor_uv = t.uv.copy()
        t.anchor_frame = index
        t.anchor_R = np.eye(3)
        t.anchor_t = np.zeros(3)
        t.anchor_body = None if self._body is None else (self._body_gen, self._body[0].copy(), self._body[1].copy())

    def _carry_anchor_motion(self, index: int) -> None:
        """Compose this step's rigid motion into every target's anchor → camera motion (the
        targets anchored this step excepted); unknown (NaN) where the motion is unknown."""
        if self._delta is not None:
            self._last_delta, self._delta_age = self._delta, 0
        else:
            self._delta_age += 1
        d = self._step_delta()
        for t in self._targets.values():
            if t.anchor_frame >= index:
                continue
            if d is None:
                t.anchor_R = np.full((3, 3), np.nan)
                t.anchor_t = _NAN3.copy()
            else:
                t.anchor_R, t.anchor_t = d[0] @ t.anchor_R, d[0] @ t.anchor_t + d[1]
        self._anchor_motion_current = True

    def _tilt_ok(self, m: FloatArray, uv: FloatArray) -> NDArray[np.bool_]:
        """Planes ``m`` (N,3) seen from pixels ``uv`` (N,2) within ``plane_max_tilt_deg`` of face-on."""
        K = self.rig.left.K
        ray = np.column_stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))])
        cos = np.einsum("ni,ni->n", m, ray) / (np.linalg.norm(m, axis=1) * np.linalg.norm(ray, axis=1))
        return np.isfinite(cos) & (cos >= np.cos(np.radians(self.params.plane_max_tilt_deg)))

    def _predicted_lin(self, ts: list[_Target]) -> FloatArray:
        """The anchor → image linear warp (N,2,2) of targets ``ts`` predicted for this frame from
        their anchor motion (extrapolated by the last frame's) and their surface plane
        (:func:`~trackmeter.core.patch_tracking.plane_jacobian`); NaN where either is unknown."""
        p = self.params
        out = np.full((len(ts), 2, 2), np.nan)
        motion = [self._anchor_motion(t) for t in ts]
        rows = [i for i, t in enumerate(ts) if len(t.planes) >= p.plane_min_samples and np.all(np.isfinite(motion[i][0]))
                and t.origin == "auto"]
        if not rows:
            return out
        sel = [ts[i] for i in rows]
        m = np.array([t.plane_m for t in sel])
        R = np.array([motion[i][0] for i in rows])
        tv = np.array([motion[i][1] for i in rows])
        # In a step, before its fit, the motions reach the last frame: moved on by the last known
        # motion as this frame's. A re-lock after the step (relock_many, restore_many) is on the
        # frame they already reach.
        d = None if self._anchor_motion_current else self._step_delta()
        if d is not None:
            R, tv = d[0] @ R, tv @ d[0].T + d[1]
        uv_a = np.array([t.anchor_uv for t in sel])
        m_now = transform_plane(m, R, tv)
        ok = self._tilt_ok(m, uv_a) & self._tilt_ok(m_now, np.array([t.uv for t in sel]))
        J = plane_jacobian(self.rig.left.K, R, tv, m, uv_a)
        out[np.array(rows)[ok]] = J[ok]
        return out

    def _measure_planes(self, fc: _FrameCache, ts: list[_Target], index: int) -> None:
        """Measure the surface plane of targets ``ts`` (tracked this step) by the stereo
        disparity slope (:func:`~trackmeter.core.patch_tracking.fit_disparity_plane`) while they
        hold fewer than ``plane_samples``; kept in each one's anchor camera frame."""
        p = self.params
        # Automatic targets only: operator and model points are salient points, mostly corners,
        # whose patch spans several faces (no one plane; on estec case b the plane warp moved
        # the a-priori points' median error from 1.2 / 4.0 to 1.7 / 4.8 mm, lateral / depth).
        ts = [t for t in ts if len(t.planes) < p.plane_samples and np.isfinite(t.disparity_px) and t.origin == "auto"]
        motion = [self._anchor_motion(t) for t in ts]
        ts = [t for t, mo in zip(ts, motion) if np.all(np.isfinite(mo[0]))]
        motion = [mo for mo in motion if np.all(np.isfinite(mo[0]))]
        if not ts:
            return
        uv = np.array([t.uv for t in ts])
        r = self.rect
        fit = fit_disparity_plane(
            fc.left, fc.right, self._maps[0], self._maps[1], r.rectify_points(uv, 0), np.array([t.disparity_px for t in ts]),
            p.plane_patch_size, focal_px=r.focal_px, baseline_m=r.baseline_m, principal_px=(r.cx_left, r.cy),
            disparity_offset_px=r.disparity_offset_px, max_iterations=10, tolerance_px=0.02,
        )
        m_cam = fit.plane_rect @ r.R1  # rows (R1ᵀ m)ᵀ: the plane in the left camera frame
        ok = fit.converged & (fit.score >= p.plane_min_score) & np.all(np.isfinite(m_cam), axis=1) & self._tilt_ok(m_cam, uv)
        R = np.array([mo[0] for mo in motion])
        tv = np.array([mo[1] for mo in motion])
        Rt = np.transpose(R, (0, 2, 1))
        m_anchor = transform_plane(m_cam, Rt, -np.einsum("nij,nj->ni", Rt, tv))  # camera → anchor camera
        for i in np.flatnonzero(ok):
            t = ts[i]
            t.planes = [*t.planes, m_anchor[i]]  # rebound, not appended: a stored handle shares the list
            t.plane_m = np.median(np.array(t.planes), axis=0)

    def _rigid_recheck(self, t: _Target, m: EpipolarMatch, j: int = 0) -> str | None:
        """Why a re-found target's 3D point disagrees with its reference distances to the
        targets measured now (None when it agrees with every one of them, at least ``rigid_min_pairs``)."""
        p = self.params
        others = [o for o in self._targets.values() if o is not t and o.status != "lost" and o.slot >= 0]
        if t.slot < 0 or t.slot >= len(self._ref_d):
            return "no reference distances to check the recovery against"
        P = self.rect.triangulate(m.uv_rect_left[j : j + 1], m.disparity_px[j : j + 1])[0]
        C = self.rect.point_covariance(m.uv_rect_left[j : j + 1], m.disparity_px[j : j + 1], p.sigma_disparity_px, p.sigma_uv_px)[0]
        z = []
        for o in others:
            ref, ref_v = self._ref_d[t.slot, o.slot], self._ref_v[t.slot, o.slot]
            if not np.isfinite(ref):
                continue
            diff = P - o.point_cam
            dist = float(np.linalg.norm(diff))
            u = diff / max(dist, 1e-12)
            var = float(u @ (C + o.cov_cam) @ u)
            z.append(abs(dist - ref) / (p.rigid_sigmas * np.sqrt(var + ref_v) + p.rigid_tolerance_m))
        if len(z) < p.rigid_min_pairs:
            return f"only {len(z)} reference distances to check the recovery against"
        # Every pair must agree (not their median): a look-alike a few cm along the surface
        # keeps the distances across that direction and changes only the others.
        if float(np.max(z)) > 1.0:
            return "re-found patch is not where the rigid body puts it"
        return None

    def _motion_outliers(self, ts: list[_Target], prev_P: FloatArray, prev_C: FloatArray) -> dict[str, str]:
        """Targets whose 3D point did not follow the rigid motion of the others since the last frame.

        The rigid motion ``P_now = R P_prev + t`` of the targets followed from the last frame
        (``prev_P`` (N,3), ``prev_C`` (N,3,3), their points then) is fitted by weighted absolute
        orientation (:func:`~trackmeter.core.transforms.absolute_orientation`, weights
        ``1 / trace`` of the residual covariance); each residual ``r = P_now - (R P_prev + t)``
        is tested against ``S = C_now + R C_prev Rᵀ + (motion_tolerance_px z / f)² I`` with the
        chi-square gate ``rᵀ S⁻¹ r <= chi2_3(motion_gate_probability)``. The worst point
        beyond the gate is lost and the fit repeats without it, while at least
        ``motion_min_targets`` remain.

        Unlike the pairwise distances (:meth:`_rigid_inconsistent`), whose tolerance along a
        pair's direction carries the stereo depth noise (~3 mm at 3.2 m), this uses each point's
        full covariance: a jump across the line of sight is judged by the left image's
        precision, ``motion_tolerance_px`` (the gate is ~1.9 px at 0.4 px). On the simulator a
        new target jumped 3.5 px (10 mm across the line of sight) to a look-alike and passed the
        distance test. Good targets' residuals reach ~1.4 px across the line of sight
        (tracking jitter, the fit's own error): on 250 estec frames a 0.5 mm tolerance lost 32
        targets, ~28 of them good; 0.4 px lost 4, three of them real 3.5-10 px jumps.
        """
        p = self.params
        P = np.array([t.point_cam for t in ts]).reshape(-1, 3)
        C = np.array([t.cov_cam for t in ts]).reshape(-1, 3, 3)
        ok = np.all(np.isfinite(P), axis=1) & np.all(np.isfinite(prev_P), axis=1)
        ok &= np.all(np.isfinite(C), axis=(1, 2)) & np.all(np.isfinite(prev_C), axis=(1, 2))
        idx = np.flatnonzero(ok)
        bad: dict[str, str] = {}
        self._delta = None
        gate = self._motion_gate
        # the tolerance, px in the image, as metres at each point's depth (pinhole: z / f)
        tol = ((p.motion_tolerance_px * np.abs(P[:, 2]) / self.rect.focal_px) ** 2)[:, None, None] * np.eye(3)
        while len(idx) >= p.motion_min_targets:
            S0 = C[idx] + prev_C[idx] + tol[idx]
            w = 1.0 / np.trace(S0, axis1=1, axis2=2)
            try:
                R, tvec = absolute_orientation(P[idx], prev_P[idx], w)
            except TrackmeterError:
                break  # collinear points: the motion is not determined
            r = P[idx] - (prev_P[idx] @ R.T + tvec)
            S = C[idx] + np.einsum("ij,njk,lk->nil", R, prev_C[idx], R) + tol[idx]
            d2 = np.einsum("ni,ni->n", r, np.linalg.solve(S, r[..., None])[..., 0])
            worst = int(np.argmax(d2))
            if not d2[worst] > gate:
                self._delta = (R, tvec)
                break
            t = ts[idx[worst]]
            bad[t.id] = f"3D point left the rigid motion of the others (Mahalanobis² {d2[worst]:.0f})"
            idx = np.delete(idx, worst)
        return bad

    def _body_offsets_px(self, P: FloatArray, Q: FloatArray) -> FloatArray:
        """Distance (N,) across the line of sight, in left-image px (``|e_perp| f / z``), of
        points ``P`` (N,3) from body points ``Q`` (N,3) moved by the current body motion; NaN
        where unknown (no body motion, or NaN points)."""
        if self._body is None:
            return np.full(len(P), np.nan)
        R, tvec = self._body
        e = P - (Q @ R.T + tvec)
        los = P / np.linalg.norm(P, axis=1, keepdims=True)
        e_perp = e - np.einsum("ni,ni->n", e, los)[:, None] * los
        return np.linalg.norm(e_perp, axis=1) * self.rect.focal_px / P[:, 2]

    def _body_drift(self, ts: list[_Target]) -> dict[str, str]:
        """Targets ``ts`` (tracked this frame) that drifted from their first 3D point on the body.

        Each target keeps its first 3D point in a body frame of the tracker's own
        (``body_point``; the camera frame of the step that first had ``motion_min_targets``
        targets). Every step the rigid motion body → camera is fitted to all tracked targets'
        (first point, point now) pairs by weighted absolute orientation; a target whose point
        now lies more than ``body_drift_px`` across the line of sight from its first point so
        moved is lost (the worst first, then the fit repeats without it). Depth is left out:
        its noise (~3 mm at 3.2 m) is several pixels' worth across the image.

        The frame-to-frame check (:meth:`_motion_outliers`) sees jumps; this sees slow creep,
        where every per-frame residual stays small: on the simulator's estec scenario targets
        crept ~0.3 px per 100 frames from their first point (most on patches straddling a depth
        edge), one 2.3 px off its surface point after 110 frames. Target-frames more than 2 px
        from their first point while tracking, 1000 estec frames: 40 without this check, 12
        with it (tracked fraction 0.810 -> 0.804); the 12 are two targets whose own fresh 3D
        points agree with the fitted body while the truth puts them 2.0-2.1 px off (a
        disparity bias the tracker cannot see). Re-found targets are held to the same test
        (:meth:`_recover_accept`), so re-recoveries cannot add up drift either.
        """
        p = self.params
        with_q = [t for t in ts if np.all(np.isfinite(t.body_point)) and np.all(np.isfinite(t.point_cam))]
        if len(with_q) < p.motion_min_targets and self._body is not None and self._delta is not None:
            # Too few targets hold a first point to fit the body's motion: carry it by this
            # frame's motion (fitted to all targets followed from the last frame), so that the
            # first points of targets lost meanwhile stay valid.
            (Rb, tb), (Rd, td) = self._body, self._delta
            self._body = (Rd @ Rb, Rd @ tb + td)
        elif len(with_q) < p.motion_min_targets:
            # No motion to carry it by either: start a new body frame (this camera frame);
            # lost targets' first points in the old one are forgotten.
            fresh = [t for t in ts if np.all(np.isfinite(t.point_cam))]
            self._body_gen += 1
            if len(fresh) < p.motion_min_targets:
                self._body = None
                return {}
            for t in self._targets.values():
                t.body_point = _NAN3.copy()
            for t in fresh:
                t.body_point = t.point_cam.copy()
            self._body = (np.eye(3), np.zeros(3))
            return {}
        else:
            return self._fit_body(ts, with_q)
        R, tvec = self._body
        for t in ts:
            if not np.all(np.isfinite(t.body_point)) and np.all(np.isfinite(t.point_cam)):
                t.body_point = R.T @ (t.point_cam - tvec)
        return {}

    def _fit_body(self, ts: list[_Target], with_q: list[_Target]) -> dict[str, str]:
        """The body motion fitted to targets ``with_q`` (first point known), the worst drifting
        ones lost one by one (see :meth:`_body_drift`); first points given to the rest of ``ts``."""
        p = self.params
        bad: dict[str, str] = {}
        P = np.array([t.point_cam for t in with_q])
        Q = np.array([t.body_point for t in with_q])
        w = 1.0 / np.trace(np.array([t.cov_cam for t in with_q]), axis1=1, axis2=2)
        w = np.where(np.isfinite(w), w, 0.0)
        keep = np.arange(len(with_q))
        while len(keep) >= p.motion_min_targets:
            try:
                self._body = absolute_orientation(P[keep], Q[keep], w[keep])
            except TrackmeterError:
                return bad  # collinear points: keep the last motion
            off = self._body_offsets_px(P[keep], Q[keep])
            worst = int(np.argmax(off))
            if not off[worst] > p.body_drift_px:
                break
            t = with_q[keep[worst]]
            bad[t.id] = f"drifted {off[worst]:.1f} px from its first 3D point on the rigid body"
            keep = np.delete(keep, worst)
        assert self._body is not None  # set by the loop, which runs: _body_drift passes at least motion_min_targets
        R, tvec = self._body
        for t in ts:
            if t.id not in bad and not np.all(np.isfinite(t.body_point)) and np.all(np.isfinite(t.point_cam)):
                t.body_point = R.T @ (t.point_cam - tvec)
        return bad

    def _rigid_inconsistent(self, ts: list[_Target]) -> dict[str, str]:
        """Targets whose distances to the other targets changed beyond their uncertainty.

        For targets i, j on one rigid body ``|P_i - P_j|`` is constant. Each pair's distance is
        remembered when first measured; its change is compared with
        ``rigid_sigmas * sigma + rigid_tolerance_m``, sigma propagated from both points'
        covariances along the pair's direction (and from the reference). The target whose
        median normalised change is worst is lost, and the test repeats without it.
        """
        p = self.params
        n = len(ts)
        if n < 2:
            return {}
        slots = np.array([t.slot for t in ts])
        P = np.array([t.point_cam for t in ts])
        C = np.array([t.cov_cam for t in ts])
        diff = P[:, None, :] - P[None, :, :]
        dist = np.linalg.norm(diff, axis=2)
        u = diff / np.maximum(dist, 1e-12)[..., None]
        q = np.einsum("ijk,ikl,ijl->ij", u, C, u)  # u_ij^T C_i u_ij
        var = q + q.T
        ix = np.ix_(slots, slots)
        ref_d, ref_v = self._ref_d[ix], self._ref_v[ix]
        fresh = ~np.isfinite(ref_d)
        np.fill_diagonal(fresh, False)
        ref_d = np.where(fresh, dist, ref_d)
        ref_v = np.where(fresh, var, ref_v)
        self._ref_d[ix] = ref_d
        self._ref_v[ix] = ref_v
        z = np.abs(dist - ref_d) / (p.rigid_sigmas * np.sqrt(var + ref_v) + p.rigid_tolerance_m)
        z[fresh] = np.nan
        np.fill_diagonal(z, np.nan)
        bad: dict[str, str] = {}
        if not np.any(z > 1.0):  # NaN compares False: the common, all-consistent case
            return bad
        alive = np.ones(n, bool)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            while alive.sum() > p.rigid_min_pairs:
                zz = np.where(alive[None, :] & alive[:, None], z, np.nan)
                counts = np.isfinite(zz).sum(1)
                med = np.nanmedian(zz, axis=1)
                med[(counts < p.rigid_min_pairs) | ~alive] = np.nan
                if not np.any(np.isfinite(med)):
                    break
                worst = int(np.nanargmax(med))
                if med[worst] <= 1.0:
                    break
                bad[ts[worst].id] = "3D distances to the other targets changed (not on the rigid body)"
                alive[worst] = False
        return bad

    def _top_up_resting(self, index: int) -> bool:
        """Whether frame ``index`` falls within ``auto_interval_frames`` after the last top-up
        (a frame index below it, e.g. after a restart, does not)."""
        last = self._last_top_up
        return last is not None and 0 <= index - last < self.params.auto_interval_frames

    def _top_up(self, frame: StereoFrame, fc: _FrameCache) -> None:
        p = self.params
        if self._top_up_resting(frame.index):
            return
        for t in list(self._targets.values()):
            if t.origin == "auto" and t.status == "lost" and t.lost_frames >= p.lost_keep_frames:
                stored = self.detach(t.id)
                if stored is not None:
                    self._removed[t.id] = stored
        alive = sum(1 for t in self._targets.values() if t.status != "lost")
        need = min(self._auto_count - alive, p.max_targets - len(self._targets))
        if need <= 0:
            self.auto_shortfall = None
            return
        exclude = np.array([t.uv for t in self._targets.values()]).reshape(-1, 2)
        fp = self.features
        self._last_top_up = frame.index
        # Ask for spares: the measurement may still refuse some (e.g. disparity too uncertain).
        pts = select_features(frame.left, frame.right, self.rig, 3 * need, self._auto_method, fp, exclude)
        if len(pts) == 0:
            why = nothing_selectable_reason(frame.left, fp) or NO_CANDIDATE
            self.auto_refusals[why] += 1
            self._note_shortfall(why)
            return
        pts = np.asarray(pts, float).reshape(-1, 2)
        # One batched measurement of all the candidates (most of its cost is per call).
        meas = measure_points(self.rig, frame.left, frame.right, pts, self.measure)
        rng = self.auto_disparity_range([m.disparity_px for m in meas])
        firsts = None
        if p.still_camera_fits:  # one batched stereo match for the measured candidates' first points
            rows = [i for i, m in enumerate(meas) if m.ok and (rng is None or rng[0] <= m.disparity_px <= rng[1])]
            if rows:
                matched = self._first_matches(fc, pts[rows], np.array([meas[i].disparity_px for i in rows]))
                firsts = {i: (matched, k) for k, i in enumerate(rows)}
        added = 0
        refused: collections.Counter[str] = collections.Counter()
        for i, (uv, m) in enumerate(zip(pts, meas)):
            if added >= need or len(self._targets) >= p.max_targets:
                break
            # A refused measurement has no disparity (NaN, outside any range): _create gives its reason.
            if m.ok and rng is not None and not rng[0] <= m.disparity_px <= rng[1]:
                refused[OFF_THE_BODY] += 1
                continue  # a false stereo match: not at the body's depth
            made = self._create(frame, uv, m, None, "auto", firsts.get(i) if firsts else None)
            if isinstance(made, TargetState):
                added += 1
                self.stats["auto_added"] += 1
            else:
                refused[made.reason] += 1
        self.auto_refusals.update(refused)
        self._note_shortfall(refused.most_common(1)[0][0] if added == 0 and refused else None)

    def _note_shortfall(self, why: str | None) -> None:
        """Keep ``why`` as :attr:`auto_shortfall` while no automatic target is alive."""
        alive = any(t.origin == "auto" and t.status != "lost" for t in self._targets.values())
        self.auto_shortfall = why if not alive else None

    def auto_disparity_range(self, candidates_px: Sequence[float] = ()) -> tuple[float, float] | None:
        """Disparities (low, high), rectified px, a new automatic point's measured disparity
        must lie in: those of the targets (lost ones with their last disparity: the body's
        depth changes slowly) widened by ``auto_disparity_margin_px`` — one body, a new point
        on it lies near their depths. With fewer than ``auto_range_min_targets`` targets, the
        robust spread of the candidates' own disparities ``candidates_px`` (NaN: refused ones):
        quartiles widened by the interquartile range and the margin. None when neither is known.

        The whole measurement range (``MeasureParams.disparity_range_px``: by default 1 m to
        infinity) holds, on a textured surface, false peaks that pass every
        stereo check while the true one is weak (glare on one camera) or leaves the right
        image. On the simulator (500 frames of estec and harsh_light) two of the three false
        locks were such new points: z 9.0 m and 2.2 m measured for surfaces at 3.0 m and 3.4 m.
        """
        p = self.params
        d = np.array([t.disparity_px for t in self._targets.values()], dtype=float)
        d = d[np.isfinite(d)]
        if len(d) >= p.auto_range_min_targets:
            lo, hi = float(d.min()), float(d.max())
        else:
            c = np.asarray(candidates_px, dtype=float).reshape(-1)
            c = c[np.isfinite(c)]
            if len(c) < p.auto_range_min_targets:
                return None
            q1, q3 = np.percentile(c, [25.0, 75.0])
            lo, hi = float(q1 - (q3 - q1)), float(q3 + (q3 - q1))
        return lo - p.auto_disparity_margin_px, hi + p.auto_disparity_margin_px
