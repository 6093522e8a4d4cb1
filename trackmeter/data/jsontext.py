"""JSON text that every parser reads: what the project prints and writes as JSON.

Python's ``json`` writes a NaN or an infinity as the bare words ``NaN``/``Infinity``, which are
not JSON (RFC 8259): JavaScript's ``JSON.parse``, jq and most other readers refuse the whole
document. A number that is not finite (a figure not computed: one range, no match) is written
as ``null`` instead.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np


def finite_or_none(value: Any) -> Any:
    """``value`` with every non-finite float (Python or numpy) replaced by None, recursively
    through dicts, lists and tuples (tuples become lists, as JSON has them); numpy scalars and
    arrays become Python numbers and lists."""
    if isinstance(value, dict):
        return {k: finite_or_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_none(v) for v in value]
    if isinstance(value, np.ndarray):
        return finite_or_none(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def json_text(value: Any, indent: int | None = 2) -> str:
    """``json.dumps`` of ``value`` with non-finite numbers as null (:func:`finite_or_none`)."""
    return json.dumps(finite_or_none(value), indent=indent, allow_nan=False)
