"""Watching the first frames of a run for left and right images given the wrong way round, or
one image given as both.

A thin stateful wrapper over :func:`trackmeter.core.stereo.swapped_views_problem`, shared by
``trackmeter track`` (a warning line) and the console (a pop-up): with cam0 and cam1 exchanged
the matcher finds no stereo match, or look-alikes at made-up depths, and a run ends with no
pose and no word of why.
"""

from __future__ import annotations

from numpy.typing import NDArray

from trackmeter.core.stereo import SWAPPED_MIN_MATCHES, StereoRig, swapped_views_problem, view_disparities_px


class SwappedViewsWatch:
    """Looks at the first frames until one shows enough distinctive points to tell the views'
    order (at most ``frames`` of them: the body may come into view late), then never again.

    Args:
        rig: the stereo rig the frames are measured with.
        frames: how many frames without enough points to look at before giving up.
    """

    def __init__(self, rig: StereoRig, frames: int = 5) -> None:
        self.rig = rig
        self._left_to_check = frames

    def check(self, left: NDArray, right: NDArray) -> str | None:
        """The problem's one line the first time a frame tells the views are swapped (or one
        image twice), else
        None (in order, untold, or already looked at enough frames). Costs one ORB match of
        the rectified pair (10-75 ms) while it looks, nothing after."""
        if self._left_to_check <= 0:
            return None
        disparities = view_disparities_px(self.rig, left, right)
        told = len(disparities) >= SWAPPED_MIN_MATCHES
        self._left_to_check = 0 if told else self._left_to_check - 1
        return swapped_views_problem(self.rig, left, right, disparities) if told else None
