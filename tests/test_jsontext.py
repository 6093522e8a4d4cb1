"""JSON the project prints and writes is strict JSON (RFC 8259): no NaN or Infinity words."""

from __future__ import annotations

import json

import numpy as np
import pytest

from trackmeter.data.jsontext import json_text


def _strict(text: str):  # type: ignore[no-untyped-def]
    def refuse(word: str) -> None:
        raise ValueError(f"not JSON: {word}")

    return json.loads(text, parse_constant=refuse)


def test_non_finite_numbers_are_null_and_everything_else_is_kept() -> None:
    value = {"k": 0.5, "nan": float("nan"), "inf": [1.0, float("-inf")], "np": np.float64(np.nan),
             "arr": np.array([1.5, np.nan]), "n": np.int64(3), "tuple": (1, "a"), "nested": {"x": [np.float32(np.inf)]}}
    with pytest.raises(ValueError, match="not JSON"):
        _strict(json.dumps({"nan": float("nan")}))  # what json.dumps alone writes
    assert _strict(json_text(value)) == {"k": 0.5, "nan": None, "inf": [1.0, None], "np": None, "arr": [1.5, None],
                                         "n": 3, "tuple": [1, "a"], "nested": {"x": [None]}}
