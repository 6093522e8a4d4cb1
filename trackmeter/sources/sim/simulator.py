"""``sim``: the tumbling mock-up rendered live through the rig's two cameras, with ground truth.

:class:`Simulator` turns a :class:`~trackmeter.sources.sim.scenario.Scenario` into a
:class:`~trackmeter.sources.base.Source`. Frame ``i`` is at ``t_i = i / rate_hz``; its pose
comes from the free rigid-body solution (Euler's equations, paper eq. 13, with quaternion
kinematics, eq. 15; :mod:`trackmeter.core.dynamics`) and the translation profile, and its images
from the stereo renderer (:mod:`trackmeter.sources.sim.render`). Every frame carries its ground
truth: ``T_cam_body``, the velocity of the body origin in the camera frame and the body-frame
angular velocity (paper eq. 14).

Frames are random-access (:meth:`Simulator.frame`): the sensor-noise generator of frame ``i`` is
seeded with ``(seed, i)``, so a frame renders identically whatever was rendered before it.
:meth:`Simulator.surface_points` says which body-frame surface point a left-image pixel sees at
a frame (or NaN), so a test can follow a surface point's true image through a sequence and tell
a locked target from a false lock.
"""

from __future__ import annotations

import warnings
from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from trackmeter.core.dynamics import FreeRotation, Translation, integrate_free_rotation
from trackmeter.core.stereo import StereoRig
from trackmeter.core.transforms import make_transform, matrix_to_quat_wxyz, quat_wxyz_to_matrix
from trackmeter.data.motion_csv import MotionSeries
from trackmeter.data.model import Model
from trackmeter.data.rigfile import load_rig
from trackmeter.errors import TrackmeterError
from trackmeter.sources.base import GroundTruth, Source, StereoFrame
from trackmeter.sources.pacing import Pacer
from trackmeter.sources.sim.mockup import Mockup, load_mockup
from trackmeter.sources.sim.render import Occluder, StereoRenderer
from trackmeter.sources.sim.render_ahead import RenderAhead
from trackmeter.sources.sim.scenario import Scenario, load_scenario, mockup_path, rig_path

FloatArray = NDArray[np.float64]
DEG = np.pi / 180.0


#: A mock-up that spans fewer pixels than this across is warned about as showing no target.
MIN_SPAN_PX = 2.0


class Simulator(Source):
    """A scenario rendered frame by frame, with ground truth.

    Args:
        scenario: a :class:`Scenario` or the name/path of a scenario file.
        rig_override: the rig this source *reports* (``--rig``), e.g. a deliberately
            miscalibrated one; the images are always rendered through the scenario's true rig
            (:attr:`true_rig`).
        realtime: deliver frames at ``rate_hz`` (sleeping as needed); else as fast as rendered.
        loop: start again after the last frame; indices and timestamps keep increasing (each
            loop is shifted by ``n_frames / rate_hz``) and the images repeat exactly. The
            index-taking methods (:meth:`truth`, :meth:`surface_points`, ...) then accept a
            streamed frame's index and take it modulo ``n_frames``.
        mockup: an already loaded mock-up (saves reloading its textures), else the scenario's.
        render_ahead: stream (:meth:`read`) frames rendered ahead in a separate process
            (:class:`~trackmeter.sources.sim.render_ahead.RenderAhead`), so that rendering
            does not take CPU from the reader's process, as a camera would not; else render in
            the caller's thread. Started at the first :meth:`read`, stopped by :meth:`close`;
            the images are identical either way.

    Attributes:
        scenario: the scenario.
        true_rig: the rig the images are rendered through.
        rig: ``rig_override`` or ``true_rig``.
        rate_hz: the scenario's frame rate.
        mockup: the mock-up.
        model: the mock-up's salient points as a :class:`Model` (what ``model.yaml`` holds).
        renderer: the :class:`StereoRenderer`.
    """

    def __init__(
        self,
        scenario: Scenario | str,
        rig_override: StereoRig | None = None,
        realtime: bool = False,
        loop: bool = False,
        mockup: Mockup | None = None,
        render_ahead: bool = False,
    ) -> None:
        self.scenario = load_scenario(scenario) if isinstance(scenario, str) else scenario
        sc = self.scenario
        self.true_rig = load_rig(rig_path(sc))
        self.rig: StereoRig = rig_override if rig_override is not None else self.true_rig
        self.rate_hz: float = float(sc.rate_hz)
        self.mockup = mockup if mockup is not None else load_mockup(mockup_path(sc))
        try:
            self.model: Model | None = Model.from_pairs(self.mockup.salient_points)
        except TrackmeterError:  # fewer than 3 salient points, or collinear ones: no case (b) on it
            self.model = None
        self._renderer: StereoRenderer | None = None  # made at the first frame (the truth alone needs none)
        self.realtime = realtime
        self.loop = loop
        sun = np.asarray(sc.sun_dir_cam, dtype=float)
        self.sun_dir_cam: FloatArray = sun / np.linalg.norm(sun)
        q0 = np.asarray(sc.attitude0_wxyz, dtype=float)
        self._q0 = q0 / np.linalg.norm(q0)
        self._rotation: FreeRotation | None = None
        if not sc.static_ranges_m:
            self._rotation = integrate_free_rotation(
                sc.inertia_kg_m2, self._q0, np.asarray(sc.omega0_body_deg_s, dtype=float) * DEG,
                max(sc.span_s - sc.release_s, 1e-6),
            )
        self._translation = Translation(
            np.asarray(sc.position0_m, dtype=float), np.asarray(sc.velocity_m_s, dtype=float),
            None if sc.approach_to_m is None else np.asarray(sc.approach_to_m, dtype=float), sc.approach_s,
        )
        path = self.scenario.origin_path_m()  # (times, body origins): both checks read it
        self._warn_if_the_camera_comes_within_reach(*path)
        self._warn_if_the_mock_up_leaves_the_view(*path)
        self._pacer = Pacer()
        self._render_ahead = bool(render_ahead)
        self._ahead: RenderAhead | None = None
        self._pos = 0
        self._count = 0
        self._loops = 0

    @property
    def renderer(self) -> StereoRenderer:
        """The :class:`StereoRenderer`, made when first asked for: its canvases and distortion
        maps are the size of the rig's images, which the motion alone (``scenario_truth``) and a
        source rendering in a worker never need."""
        if self._renderer is None:
            self._renderer = StereoRenderer(self.true_rig, self.mockup, self.scenario.render)
        return self._renderer

    def _warn_if_the_camera_comes_within_reach(self, times: FloatArray, origins: FloatArray) -> None:
        """Warn when a camera comes nearer the body origin than the mock-up reaches: it may be
        among the mock-up's parts there, where the renderer, culling faces seen from behind,
        draws a black or half-empty view (nothing says so otherwise)."""
        sc = self.scenario
        centres = np.stack([np.zeros(3), -self.true_rig.R.T @ np.asarray(self.true_rig.T, dtype=float).reshape(3)])
        distance_m = np.linalg.norm(origins[:, None, :] - centres[None], axis=2).min(axis=1)
        k = int(np.argmin(distance_m))
        if distance_m[k] < self.mockup.radius_m:
            warnings.warn(f"scenario {sc.name!r}: the camera comes within {distance_m[k]:.2f} m of the body origin at "
                          f"t = {times[k]:.2f} s, where the mock-up reaches {self.mockup.radius_m:.2f} m: it may be "
                          "among its parts there, and faces seen from behind are not drawn (black or half-empty "
                          "images)", stacklevel=3)

    def _warn_if_the_mock_up_leaves_the_view(self, times: FloatArray, origins: FloatArray) -> None:
        """Warn when the mock-up lies wholly outside the left image, or spans under
        :data:`MIN_SPAN_PX`, at some frames (static ranges: at some range): those images show
        no target, and only ``track`` said so, afterwards (an outside probe's 10 m to the side
        rendered black frames with exit 0). Its bounding sphere through the pinhole, without
        the lens's distortion: a warning, not a refusal."""
        sc = self.scenario
        cam = self.true_rig.left
        z = origins[:, 2]
        uv = origins[:, :2] / z[:, None] @ cam.K[:2, :2].T + cam.K[:2, 2]
        r_px = cam.focal_px * self.mockup.radius_m / z
        width, height = cam.image_size
        outside = ((uv[:, 0] + r_px < -0.5) | (uv[:, 0] - r_px > width - 0.5)
                   | (uv[:, 1] + r_px < -0.5) | (uv[:, 1] - r_px > height - 0.5))
        tiny = 2.0 * r_px < MIN_SPAN_PX
        gone = outside | tiny
        if np.any(gone):
            k = np.flatnonzero(gone)
            what = "out of the left camera's view" if np.any(outside) else f"under {MIN_SPAN_PX:g} px across"
            if np.any(outside) and np.any(tiny):
                what += f" or under {MIN_SPAN_PX:g} px across"
            unit = "ranges" if sc.static_ranges_m else "frames"
            warnings.warn(f"scenario {sc.name!r}: the mock-up is {what} in {len(k)} of {len(gone)} {unit} "
                          f"(t = {times[k[0]]:.2f} to {times[k[-1]]:.2f} s): those images show no target",
                          stacklevel=3)

    # ------------------------------------------------------------------ random access

    @property
    def frame_size(self) -> tuple[int, int]:
        """``(width, height)`` px: the images are rendered through :attr:`true_rig`, whatever
        rig the source reports."""
        return self.true_rig.image_size

    @property
    def has_truth(self) -> bool:
        return True  # every frame: the simulated motion is the truth

    @property
    def n_frames(self) -> int:
        """Frames in one pass of the scenario."""
        return self.scenario.n_frames

    def __len__(self) -> int:
        return self.n_frames

    def time_of(self, index: int) -> float:
        """``t_i = i / rate_hz``, s (index within one pass)."""
        return index / self.rate_hz

    def _check(self, index: int) -> int:
        # A looping source numbers its frames on (StereoFrame.index); frame k shows pass frame
        # k mod n, so callers holding a frame's index get the right answer.
        if self.loop and int(index) >= 0:
            return int(index) % self.n_frames
        if not 0 <= int(index) < self.n_frames:
            raise TrackmeterError(f"frame {index} outside the scenario's {self.n_frames} frames")
        return int(index)

    def truth(self, index: int) -> GroundTruth:
        """Ground truth of frame ``index``: pose, origin velocity (cam), omega (body)."""
        i = self._check(index)
        sc = self.scenario
        if sc.static_ranges_m:
            k = i // sc.frames_per_range
            direction = np.asarray(sc.position0_m, dtype=float)
            direction = direction / np.linalg.norm(direction)
            T = make_transform(quat_wxyz_to_matrix(self._q0), direction * sc.static_ranges_m[k])
            return GroundTruth(T, np.zeros(3), np.zeros(3))
        t = self.time_of(i) - sc.release_s  # the motion's own time: it starts at the release
        assert self._rotation is not None
        q, w = self._rotation.state(min(max(t, 0.0), self._rotation.duration_s))
        p, v = self._translation.at(max(t, 0.0))
        if t < 0:  # held still
            w, v = np.zeros(3), np.zeros(3)
        return GroundTruth(make_transform(quat_wxyz_to_matrix(q), p), v, w)

    def static_range_of(self, index: int) -> float | None:
        """For a static-ranges scenario, the nominal range of frame ``index``, m; else None."""
        sc = self.scenario
        if not sc.static_ranges_m:
            return None
        return float(sc.static_ranges_m[self._check(index) // sc.frames_per_range])

    def occluders_at(self, index: int) -> tuple[Occluder, ...]:
        """The occluding panels present at frame ``index``."""
        t = self.time_of(self._check(index))
        out = []
        for occ in self.scenario.occluders:
            if occ.start_s <= t <= occ.end_s:
                centre = np.asarray(occ.position_m, dtype=float) + (t - occ.start_s) * np.asarray(occ.velocity_m_s, dtype=float)
                R = Rotation.from_rotvec(np.asarray(occ.rotvec_deg, dtype=float) * DEG).as_matrix()
                out.append(Occluder(make_transform(R, centre), cast("tuple[float, float]", tuple(occ.size_m))))
        return tuple(out)

    def frame(self, index: int) -> StereoFrame:
        """Render frame ``index`` of the scenario (deterministic; no pacing)."""
        i = self._check(index)
        gt = self.truth(i)
        # The pose one frame earlier, for motion blur. Frame 0 has none in the scenario, so it
        # takes frame 1's: the blur spreads symmetrically about the current pose, so the
        # direction of the motion does not matter, only its size. (Not computed when the
        # scenario has no blur: the renderer would not use it.)
        rp = self.renderer.params
        prev = None
        if rp.motion_blur_subframes > 1 and rp.shutter_fraction > 0:
            prev = self.truth(i - 1).T_cam_body if i > 0 else (self.truth(1).T_cam_body if self.n_frames > 1 else None)
        rng = np.random.default_rng([self.scenario.seed, i])
        left, right = self.renderer.render(gt.T_cam_body, self.sun_dir_cam, rng, T_cam_body_prev=prev,
                                           occluders=self.occluders_at(i))
        return StereoFrame(index=i, t_s=self.time_of(i), left=left, right=right, truth=gt)

    def surface_points(self, index: int, uv_left: ArrayLike) -> FloatArray:
        """Body-frame surface points (N,3), m, seen at left-image pixels ``uv_left`` (N,2) in
        frame ``index`` (distorted, as rendered); NaN rows where a pixel sees space or an occluder."""
        i = self._check(index)
        return self.renderer.surface_points(self.truth(i).T_cam_body, np.asarray(uv_left, dtype=float).reshape(-1, 2),
                                            occluders=self.occluders_at(i))

    @property
    def model_points_body(self) -> FloatArray:
        """(N,3) the mock-up's salient points in the body frame, m."""
        return np.array([np.asarray(x, dtype=float) for _, x in self.mockup.salient_points]).reshape(-1, 3)

    # ------------------------------------------------------------------ streaming

    def read(self) -> StereoFrame | None:
        if self._pos >= self.n_frames:
            if not self.loop:
                return None
            self._pos = 0
            self._loops += 1
            self._cut = True
        f = self._streamed_frame(self._pos)
        self._pos += 1
        t = f.t_s + self._loops * self.n_frames / self.rate_hz
        if self.realtime:
            self._pacer.wait(t)
        out = StereoFrame(index=self._count, t_s=t, left=f.left, right=f.right, truth=f.truth, cut=self._take_cut())
        self._count += 1
        return out

    def _streamed_frame(self, index: int) -> StereoFrame:
        if not self._render_ahead:
            return self.frame(index)
        if self._ahead is None:
            self._ahead = RenderAhead(self.scenario, self.true_rig.left.image_size)
        left, right, truth = self._ahead.rendered(index, self._next_in_pass)
        return StereoFrame(index=index, t_s=self.time_of(index), left=left, right=right, truth=truth)

    def _next_in_pass(self, index: int) -> int | None:
        if index + 1 < self.n_frames:
            return index + 1
        return 0 if self.loop else None

    def resume(self) -> None:
        self._pacer.reset()

    def restart(self) -> None:
        self._pos = 0
        self._count = 0
        self._loops = 0
        self._cut = True
        self._pacer.reset()

    def close(self) -> None:
        if self._ahead is not None:
            self._ahead.close()
            self._ahead = None


def scenario_truth(scenario: Scenario | str) -> MotionSeries:
    """The scenario's motion at its frame times: the ground truth ``trackmeter simulate`` writes
    (``groundtruth.csv``), without rendering a frame; for evaluating a run of the ``sim`` source,
    which keeps none. One pass of the scenario (a looping source's later passes repeat it)."""
    sim = Simulator(scenario)
    try:
        truths = [sim.truth(i) for i in range(sim.n_frames)]
    finally:
        sim.close()
    T = np.array([g.T_cam_body for g in truths], dtype=float).reshape(-1, 4, 4)
    return MotionSeries(
        np.array([sim.time_of(i) for i in range(sim.n_frames)]), np.ones(sim.n_frames, dtype=bool), T[:, :3, 3],
        matrix_to_quat_wxyz(T[:, :3, :3]), np.array([g.velocity_cam_m_s for g in truths], dtype=float),
        np.array([g.omega_body_rad_s for g in truths], dtype=float),
    )
