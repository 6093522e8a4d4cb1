"""A stereo frame and the ground truth that may come with it: plain data, the unit every layer
passes on (a source yields frames, the tracker and the engine step on them, a sequence writer
stores them). Here, in the bottom layer, so that the core's API does not reach up to the
sources layer that makes them; :mod:`trackmeter.sources.base` re-exports both.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from trackmeter.errors import TrackmeterError


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """What the frame really showed, when the source knows (simulator, sequences with truth).

    Attributes:
        T_cam_body: (4,4) pose of the body in the left camera frame.
        velocity_cam_m_s: (3,) velocity of the body origin, camera frame, m/s.
        omega_body_rad_s: (3,) angular velocity in the body frame, rad/s (paper eq. 14).
    """

    T_cam_body: NDArray[np.float64]
    velocity_cam_m_s: NDArray[np.float64]
    omega_body_rad_s: NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class StereoFrame:
    """One stereo pair.

    Attributes:
        index: frame number from the start of the source (0, 1, ...).
        t_s: timestamp, s.
        left, right: (H,W) uint8 grey images, unrectified, as the cameras delivered them.
        truth: ground truth at ``t_s`` when the source has it.
        cut: the stream is discontinuous before this frame: the first frame after a
            ``restart()`` or of a looping source's new pass. The scene jumps here, so nothing
            tracked may carry over (a tracker would re-find its points on the wrong surfaces).
        stamp_ns: the source's own timestamp in integer nanoseconds where it has one (a
            sequence's file names), ``t_s`` to the nanosecond; None otherwise. A recording
            keeps it exactly, which ``t_s`` cannot: EuRoC's stamps (~1.4e18 ns) are 238 ns
            apart as float seconds.
    """

    index: int
    t_s: float
    left: NDArray[np.uint8]
    right: NDArray[np.uint8]
    truth: GroundTruth | None = None
    cut: bool = False
    stamp_ns: int | None = None

    def __post_init__(self) -> None:
        # Every filter downstream steps by differences of it: one NaN turned a target's Kalman
        # state into NaN for good, without a word. A source delivering it fails here instead.
        try:
            finite = math.isfinite(self.t_s)
        except TypeError:  # None, a string: a source's bug, named like a NaN
            finite = False
        if not finite:
            raise TrackmeterError(f"frame {self.index}: its time is not a finite number ({self.t_s!r})")
