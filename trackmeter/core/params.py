"""Declaring tunable parameters: a dataclass field with a doc string and a valid range.

Every tunable of the system is a field of a frozen dataclass in the core module that uses it
(e.g. ``MeasureParams`` in :mod:`trackmeter.core.matching`), declared with :func:`param`. The
configuration loader (:mod:`trackmeter.data.config`) builds those dataclasses from
``config/default.yaml`` and a user's file, and checks each value against what is declared
here, so a bad value is refused with its dotted key and the expected range.
"""

from __future__ import annotations

from dataclasses import field
from typing import Any


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
