"""The interface every stereo frame source implements, and the frame it yields.

Sources: the simulator (``sim``), sequence folders (``seq``), video files and cameras. A
source yields :class:`StereoFrame` objects until it ends; :func:`trackmeter.sources.open_source`
turns a SPEC string (DESIGN.md section 6) into a source.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING

from trackmeter.core.frames import GroundTruth, StereoFrame
from trackmeter.core.stereo import StereoRig

#: A looping source's interval from a pass's last frame to the next pass's first where it
#: knows no frame rate (a video without one, a one-pair sequence), s.
NO_RATE_INTERVAL_S = 0.04

if TYPE_CHECKING:
    from trackmeter.data.model import Model

#: The frame a source yields is defined in the bottom layer (:mod:`trackmeter.core.frames`).
__all__ = ["GroundTruth", "Source", "StereoFrame"]


class Source(ABC):
    """A stream of stereo frames.

    Attributes:
        rig: the stereo rig of the images when the source carries one (simulator scenario,
            a sequence's ``rig.yaml``), else None. A command given ``--rig`` replaces it.
        rate_hz: nominal frame rate, Hz, or None when unknown.
        model: the body model the source carries (a scenario's mock-up points, a sequence
            folder's ``model.yaml``), else None: case (b)'s a-priori model unless a command is
            given ``--model``.
    """

    rig: StereoRig | None = None
    rate_hz: float | None = None
    model: Model | None = None
    # Set by a source whose next frame follows a restart() or starts a new pass of a loop.
    _cut: bool = False

    def _take_cut(self) -> bool:
        """Whether the frame being made is a cut (:attr:`StereoFrame.cut`); clears the mark."""
        cut, self._cut = self._cut, False
        return cut

    @property
    def has_truth(self) -> bool:
        """Whether any frame may carry ground truth (:attr:`StereoFrame.truth`): a simulator,
        a sequence folder with a ground-truth file (whose first frames may still have none)."""
        return False

    @property
    def frame_size(self) -> tuple[int, int] | None:
        """``(width, height)`` of the frames, px, known before the first :meth:`read`, or None
        when the source cannot tell. Commands check it against the rig's image size before
        tracking, and a rig file without a size (OpenCV's ``intrinsics.yml``) takes it."""
        return None

    @abstractmethod
    def read(self) -> StereoFrame | None:
        """The next frame, or None at the end of the stream. Raises TrackmeterError on failure."""

    def restart(self) -> None:
        """Go back to the first frame (sources that cannot raise TrackmeterError)."""
        from trackmeter.errors import TrackmeterError

        raise TrackmeterError(f"{type(self).__name__} cannot restart")

    def resume(self) -> None:
        """Playing again after a pause: a source played in real time paces on from its next
        frame (the pause is no lateness to make up). Nothing to do for the others."""

    def close(self) -> None:
        """Release files and devices."""

    def __enter__(self) -> Source:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
