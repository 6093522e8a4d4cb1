"""Exposure normalisation (trackmeter.core.exposure) and the engine and `measure` using it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from trackmeter.core.exposure import ExposureParams, apply_gain, expose_pair, exposure_gain, grey_percentiles
from trackmeter.data.config import load_config
from trackmeter.pipeline.engine import Engine
from trackmeter.pipeline.snapshot import SelectPoint, SetAuto
from trackmeter.sources.base import StereoFrame


def test_grey_percentiles_are_numpys_inverted_cdf() -> None:
    rng = np.random.default_rng(3)
    for image in (rng.integers(0, 256, (37, 53), dtype=np.uint8), (rng.gamma(2.0, 9.0, (40, 60))).clip(0, 255).astype(np.uint8)):
        qs = (5.0, 50.0, 99.5, 99.9, 100.0)
        want = tuple(int(np.percentile(image, q, method="inverted_cdf")) for q in qs)
        assert grey_percentiles(image, qs) == want


def test_a_normally_exposed_image_is_left_as_it_is() -> None:
    rng = np.random.default_rng(0)
    image = rng.integers(0, 200, (60, 80), dtype=np.uint8)  # 99.5th percentile about 199 > 128
    left, right, gain = expose_pair(image, image.copy(), ExposureParams())
    assert gain == 1.0 and left is image  # the very object: nothing downstream changes
    assert exposure_gain(image // 4, ExposureParams(reference_grey=0.0)) == 1.0  # switched off


def test_the_gain_brings_the_bright_percentile_to_the_reference() -> None:
    """g = min(reference / p_bright, saturation / p_top, max_gain), from the closed form."""
    image = np.zeros((100, 100), np.uint8)
    image[:50] = 10
    image[50:] = 40  # p99.5 = p99.9 = 40
    params = ExposureParams(reference_grey=128.0, saturation_grey=250.0, max_gain=8.0)
    assert exposure_gain(image, params) == pytest.approx(128 / 40)
    # A few glint pixels above the top percentile saturate; the 0.1 % below them do not.
    image.flat[:5] = 200  # 0.05 % of the pixels
    image.flat[5:10] = 100
    assert grey_percentiles(image, (99.9,)) == (40,)
    image.flat[10:20] = 100  # now 0.15 % at 100 or more: the top percentile is 100
    assert exposure_gain(image, params) == pytest.approx(250 / 100)
    assert exposure_gain(np.full((10, 10), 2, np.uint8), params) == 8.0  # capped
    gained = apply_gain(image, 2.5)
    assert gained.dtype == np.uint8 and gained[50, 0] == 100 and gained.flat[0] == 255  # 500 saturates


def _dim(frame: StereoFrame, factor: float) -> StereoFrame:
    scale = lambda image: np.clip(np.rint(image * factor), 0, 255).astype(np.uint8)  # noqa: E731
    return dataclasses.replace(frame, left=scale(frame.left), right=scale(frame.right))


def test_an_underexposed_estec_is_tracked_as_the_normal_one_is() -> None:
    """Estec's frames at 0.35 of their grey levels (an underexposed camera, another renderer's
    darker images): without the gain the fixed grey-level gates refused every point (automatic
    selection kept no target at all); with it the engine tracks them about as the normally
    exposed frames are tracked (here: target-frames over the first 14 frames)."""
    from trackmeter.sources.sim.simulator import Simulator

    sim = Simulator("estec")

    def tracked(factor: float, reference: float) -> tuple[int, Engine]:
        config = load_config(overrides={"exposure": {"reference_grey": reference}})
        engine = Engine(config, sim.rig, None, "a", rate_hz=sim.rate_hz)
        first = _dim(sim.frame(0), factor)
        engine.process(first)
        assert engine.handle(SetAuto(True, 16, "gabor"), first).ok
        total = 0
        for k in range(1, 15):
            targets, _, _ = engine.process(_dim(sim.frame(k), factor))
            total += sum(t.status != "lost" for t in targets)
        return total, engine

    normal, engine = tracked(1.0, 128.0)
    assert engine.stats.frames_gained == 0 and engine.gain == 1.0
    without, engine = tracked(0.35, 0.0)
    assert without == 0 and engine.stats.frames_gained == 0
    gained, engine = tracked(0.35, 128.0)
    assert engine.stats.frames_gained == 15 and engine.gain > 1.5  # 128 / 66 or so
    assert gained >= 0.4 * normal


def test_a_click_on_an_underexposed_frame_is_judged_on_the_gained_images() -> None:
    from trackmeter.sources.sim.simulator import Simulator

    sim = Simulator("estec")
    raw = sim.frame(0)
    frame = _dim(raw, 0.35)
    engine = Engine(load_config(), sim.rig, None, "a", rate_hz=sim.rate_hz)
    engine.process(frame)
    off = Engine(load_config(overrides={"exposure": {"reference_grey": 0.0}}), sim.rig, None, "a", rate_hz=sim.rate_hz)
    off.process(frame)
    from trackmeter.core.features import FeatureParams, select_features

    # Points automatic selection finds on the normally exposed frame, clicked on the dim one.
    points = select_features(raw.left, raw.right, sim.rig, 6, "gabor", FeatureParams())
    assert len(points) == 6
    accepted = sum(engine.handle(SelectPoint(float(u), float(v)), frame).ok for u, v in points)
    refused_without = sum(not off.handle(SelectPoint(float(u), float(v)), frame).ok for u, v in points)
    assert accepted == 6 and refused_without >= 3


def test_an_estec_frame_is_not_gained() -> None:
    """The reference geometry's images are normally exposed: the engine tracks them bit for bit
    as they came (so every figure measured before the gain existed holds)."""
    from trackmeter.sources.sim.simulator import Simulator

    sim = Simulator("estec")
    engine = Engine(load_config(), sim.rig, None, "a", rate_hz=sim.rate_hz)
    for k in (0, 300, 700, 1100):
        frame = sim.frame(k)
        assert engine._exposed(frame) is frame
