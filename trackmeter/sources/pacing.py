"""Real-time pacing of recorded streams: play frames at the rate they were recorded."""

from __future__ import annotations

import time
from collections.abc import Callable


class Pacer:
    """Sleep so that frames come out at their media time, measured from the first frame.

    ``wait(t_s)`` returns at wall-clock ``start + (t_s - t_first)``, or at once when the
    caller is already late (a slow consumer never makes the pacer sleep to catch up twice).
    ``reset()`` starts a new reference (after a restart or a loop).
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep) -> None:
        self._clock = clock
        self._sleep = sleep
        self._origin: tuple[float, float] | None = None

    def reset(self) -> None:
        self._origin = None

    def wait(self, t_s: float) -> None:
        now = self._clock()
        if self._origin is None:
            self._origin = (now, t_s)
            return
        wall0, media0 = self._origin
        delay = wall0 + (t_s - media0) - now
        if delay > 0:
            self._sleep(delay)
        elif delay < -0.5:
            # Far behind (paused consumer, slow disk): re-anchor rather than rush frames out.
            self._origin = (now, t_s)
