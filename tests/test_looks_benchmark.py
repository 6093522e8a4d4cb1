"""The looks benchmark's frame transforms (benchmarks.looks): what each does to a frame."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.looks import LOOKS, looked
from trackmeter.core.exposure import grey_percentiles
from trackmeter.sources.sim.simulator import Simulator


@pytest.fixture(scope="module")
def frame():  # type: ignore[no-untyped-def]
    return Simulator("estec").frame(3)


@pytest.mark.parametrize("name", [n for n, fn in LOOKS.items() if fn is not None])
def test_each_look_keeps_the_frame_and_changes_its_images_reproducibly(frame, name: str) -> None:  # type: ignore[no-untyped-def]
    transform = looked(LOOKS[name])
    a, b = transform(frame), transform(frame)
    assert a.truth is frame.truth and a.index == frame.index and a.t_s == frame.t_s
    for image, original in ((a.left, frame.left), (a.right, frame.right)):
        assert image.dtype == np.uint8 and image.shape == original.shape
    np.testing.assert_array_equal(a.left, b.left)
    np.testing.assert_array_equal(a.right, b.right)
    changed = [not np.array_equal(a.left, frame.left), not np.array_equal(a.right, frame.right)]
    assert changed == ([False, True] if name == "gain_mismatch" else [True, True])


def test_the_underexposed_look_is_darker_than_the_exposure_reference(frame) -> None:  # type: ignore[no-untyped-def]
    dim = looked(LOOKS["underexposed"])(frame)
    (bright,) = grey_percentiles(dim.left, (99.5,))
    (rendered,) = grey_percentiles(frame.left, (99.5,))
    assert rendered >= 128 > bright and bright == pytest.approx(0.35 * rendered, abs=6)
    assert LOOKS["as_rendered"] is None and looked(None) is None
