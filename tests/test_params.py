"""Parameter dataclasses built in a script hold their declared ranges and choices, as the
config loader holds YAML values (trackmeter.core.params.check_params)."""

from __future__ import annotations

import dataclasses
import math

import pytest

from trackmeter.core.calibration import CalibrationParams
from trackmeter.core.error_analysis import AnalyzeParams
from trackmeter.core.exposure import ExposureParams
from trackmeter.core.features import FeatureParams
from trackmeter.core.kalman import KalmanParams
from trackmeter.core.matching import MeasureParams
from trackmeter.core.metrics import EvaluateParams
from trackmeter.core.output_filter import FilterParams
from trackmeter.core.pose import PoseParams
from trackmeter.core.tracking import TrackerParams
from trackmeter.core.velocity import VelocityParams
from trackmeter.errors import TrackmeterError
from trackmeter.sources.sim.render import RenderParams

ALL_PARAMS = [AnalyzeParams, CalibrationParams, EvaluateParams, ExposureParams, FeatureParams, FilterParams,
              KalmanParams, MeasureParams, PoseParams, RenderParams, TrackerParams, VelocityParams]


@pytest.mark.parametrize(
    "build, message",
    [
        (lambda: VelocityParams(method="Screw"), r"^VelocityParams\.method: expected one of 'screw', .*got 'Screw'$"),
        (lambda: VelocityParams(method="bogus"), r"VelocityParams\.method: expected one of"),
        (lambda: PoseParams(min_points=1), r"^PoseParams\.min_points: expected a value in \[3, inf\], got 1$"),
        (lambda: FilterParams(order=0), r"^FilterParams\.order: expected a value in \[1, 8\], got 0$"),
        (lambda: FilterParams(cutoff_hz=-1.0), r"^FilterParams\.cutoff_hz: expected a value in \[0\.01, inf\]"),
        (lambda: FilterParams(cutoff_hz=math.nan), r"^FilterParams\.cutoff_hz: expected a value in .*got nan$"),
        (lambda: dataclasses.replace(PoseParams(), outlier_probability=1.0), r"PoseParams\.outlier_probability"),
    ],
)
def test_an_out_of_range_param_is_refused_naming_class_field_and_range(build, message) -> None:
    """These were accepted; 'Screw' and 'bogus' silently ran another velocity estimator."""
    with pytest.raises(TrackmeterError, match=message):
        build()


def test_a_tuple_param_is_checked_element_by_element() -> None:
    field = next(f for cls in ALL_PARAMS for f in dataclasses.fields(cls)
                 if isinstance(f.default, tuple) and f.default and "min" in f.metadata)
    cls = next(c for c in ALL_PARAMS if field in dataclasses.fields(c))
    bad = (field.default[0], field.metadata["min"] - 1) + field.default[2:]
    with pytest.raises(TrackmeterError, match=rf"^{cls.__name__}\.{field.name}\[1\]: expected a value in"):
        cls(**{field.name: bad})


@pytest.mark.parametrize("cls", ALL_PARAMS, ids=lambda c: c.__name__)
def test_every_params_class_checks_its_fields_and_its_defaults_pass(cls) -> None:
    cls()  # the defaults are within their own ranges
    bounded = [f for f in dataclasses.fields(cls) if "min" in f.metadata and isinstance(f.default, (int, float))
               and not isinstance(f.default, bool)]
    assert bounded, cls
    f = bounded[0]
    with pytest.raises(TrackmeterError, match=rf"^{cls.__name__}\.{f.name}: "):
        cls(**{f.name: f.metadata["min"] - 1})


@pytest.mark.parametrize(
    "build, message",
    [
        (lambda: PoseParams(ransac_trials=2.5), r"^PoseParams\.ransac_trials: expected an integer, got 2\.5$"),
        (lambda: PoseParams(refine_iterations=1.5), r"^PoseParams\.refine_iterations: expected an integer"),
        (lambda: PoseParams(robust_scale="no"), r"^PoseParams\.robust_scale: expected true or false, got 'no'$"),
        (lambda: FilterParams(cutoff_hz="2"), r"^FilterParams\.cutoff_hz: expected a number, got '2'$"),
    ],
)
def test_a_value_of_the_wrong_type_is_refused_when_built(build, message) -> None:
    """`PoseParams(ransac_trials=2.5)` was accepted and robust_pose failed later with "'float'
    object cannot be interpreted as an integer"; `robust_scale='no'` was taken as true (a
    re-check)."""
    with pytest.raises(TrackmeterError, match=message):
        build()


def test_numbers_of_numpy_types_and_ints_for_floats_are_taken() -> None:
    import numpy as np

    assert PoseParams(ransac_trials=np.int64(50), robust_scale=np.bool_(False)).ransac_trials == 50
    assert FilterParams(cutoff_hz=2).cutoff_hz == 2
