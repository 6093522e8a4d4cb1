"""Declaring tunable parameters: a dataclass field with a doc string and a valid range.

Every tunable of the system is a field of a frozen dataclass in the core module that uses it
(e.g. ``MeasureParams`` in :mod:`trackmeter.core.matching`), declared with :func:`param`. The
configuration loader (:mod:`trackmeter.data.config`) builds those dataclasses from
``config/default.yaml`` and a user's file, and checks each value against what is declared
here, so a bad value is refused with its dotted key and the expected range.

A dataclass built in a script is held to the same ranges: each ``...Params`` class calls
:func:`check_params` from its ``__post_init__`` (``VelocityParams(method="Screw")`` would
otherwise run another estimator silently). Both use :func:`range_problem`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import typing
from collections.abc import Mapping
from dataclasses import field
from numbers import Integral, Real
from typing import Any

import numpy as np

from trackmeter.errors import TrackmeterError, shown_value


def param(
    default: Any,
    doc: str,
    *,
    min: float | None = None,  # noqa: A002 - reads naturally at the call site
    max: float | None = None,  # noqa: A002
    choices: tuple[Any, ...] | None = None,
) -> Any:
    """A dataclass field for a tunable: default, one-line doc, and its valid range or choices.

    ``min``/``max`` are inclusive bounds for numbers (and for every element of a tuple).
    """
    metadata: dict[str, Any] = {"doc": doc}
    if min is not None:
        metadata["min"] = min
    if max is not None:
        metadata["max"] = max
    if choices is not None:
        metadata["choices"] = tuple(choices)
    if isinstance(default, (list, dict)):
        raise TypeError("use a tuple for sequence defaults so the dataclass stays immutable")
    return field(default=default, metadata=metadata)


def range_problem(value: Any, meta: Mapping[str, Any], finite: bool = False) -> str | None:
    """What is wrong with one value against a field's declared range or choices, or None.

    ``meta`` is the field's metadata from :func:`param` (``min``, ``max`` inclusive;
    ``choices``). NaN is never inside a range; with ``finite`` neither is an infinity (an
    unbounded side still refuses ``inf`` then: no setting means "unbounded").

    Returns:
        ``"expected a value in [lo, hi], got V"``, ``"expected one of 'a', 'b', got V"``, or None.
    """
    lo, hi = meta.get("min"), meta.get("max")
    if lo is not None or hi is not None:
        bounds = f"[{lo if lo is not None else '-inf'}, {hi if hi is not None else 'inf'}]"
        if isinstance(value, bool) or not isinstance(value, Real):
            return f"expected a number in {bounds}, got {shown_value(value)}"
        nan = isinstance(value, float) and math.isnan(value)
        infinite = finite and isinstance(value, float) and not math.isfinite(value)
        if nan or infinite or lo is not None and value < lo or hi is not None and value > hi:
            return f"expected a value in {bounds}, got {shown_value(value)}"
    choices = meta.get("choices")
    if choices is not None and value not in choices:
        return f"expected one of {', '.join(map(repr, choices))}, got {shown_value(value)}"
    return None


def check_params(params: Any) -> None:
    """Hold every field of a parameter dataclass to its declared range or choices (each element
    of a tuple), as the config loader holds a YAML value; call it from ``__post_init__``.

    Raises:
        TrackmeterError: ``"FilterParams.order: expected a value in [1, 8], got 0"``.
    """
    params_class: type = type(params)  # not type[Any]: mypy holds that not Hashable (lru_cache's argument)
    kinds = _simple_kinds(params_class)
    for f in dataclasses.fields(params):
        meta = f.metadata
        value = getattr(params, f.name)
        kind = kinds.get(f.name)
        if kind is not None and not _is_kind(value, kind):
            raise TrackmeterError(f"{type(params).__name__}.{f.name}: expected {KIND_NAMES[kind]}, "
                                  f"got {shown_value(value)}")
        if "min" not in meta and "max" not in meta and "choices" not in meta:
            continue
        items = enumerate(value) if isinstance(value, tuple) else ((None, value),)
        for i, item in items:
            problem = range_problem(item, meta)
            if problem is not None:
                index = "" if i is None else f"[{i}]"
                raise TrackmeterError(f"{type(params).__name__}.{f.name}{index}: {problem}")


#: How a message names each simple field type (the config loader's messages too).
KIND_NAMES = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}


@functools.lru_cache(maxsize=None)
def _simple_kinds(cls: type) -> dict[str, type]:
    """The fields of a parameter dataclass annotated ``bool``, ``int``, ``float`` or ``str``,
    by name (resolved once per class: ``typing.get_type_hints`` is slow)."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls) if hints.get(f.name) in KIND_NAMES}


def _is_kind(value: Any, kind: type) -> bool:
    """Whether ``value`` is of ``kind`` as a setting is: numpy's numbers too, an integer for a
    float, never a bool for a number (True is 1 to Python, not to a user)."""
    if kind is bool:
        return isinstance(value, (bool, np.bool_))
    if isinstance(value, (bool, np.bool_)):
        return False
    if kind is int:
        return isinstance(value, Integral)
    if kind is float:
        return isinstance(value, Real)
    return isinstance(value, str)
