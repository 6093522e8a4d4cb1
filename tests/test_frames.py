"""The stereo frame every layer passes on: what it refuses at the boundary."""

from __future__ import annotations

import math

import numpy as np
import pytest

from trackmeter.core.frames import StereoFrame
from trackmeter.errors import TrackmeterError


@pytest.mark.parametrize("t_s", [math.nan, math.inf, -math.inf, np.float64("nan"), None, "0.28"])
def test_a_frame_without_a_finite_time_is_refused(t_s: float) -> None:
    # One NaN time turned a target's Kalman state into NaN for good (predict steps by the
    # difference of the times), without a word; a source delivering it now fails, named. None or
    # a string raised a bare TypeError.
    img = np.zeros((4, 4), np.uint8)
    with pytest.raises(TrackmeterError, match=r"frame 7: its time is not a finite number"):
        StereoFrame(7, t_s, img, img)
    assert StereoFrame(7, 0.28, img, img).t_s == 0.28
