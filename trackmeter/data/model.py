"""Model files: named points of the target in its body frame (DESIGN.md section 6).

YAML, metres, body frame::

    points:
      - {id: corner_1, xyz: [0.5, 0.5, 0.5]}
      - {id: corner_2, xyz: [-0.5, 0.5, 0.5]}
      - {id: antenna_tip, xyz: [0.0, 0.0, 1.2]}

The a-priori model of pose case (b) (paper section 2.C) needs at least three points that are
not collinear; ids are strings (numbers are read as written: ``010`` is "010", not 8), unique,
not empty and without ``=`` (``--target ID=U,V`` names them). Other
keys (``units: m``, a point's ``note``), which files from other tools carry, are ignored
with one warning naming them; every check of ``points`` itself stays.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray

from trackmeter.data.config import UniqueKeys, build_dataclass, read_yaml_mapping
from trackmeter.data.atomic import write_text_atomic
from trackmeter.errors import TrackmeterError

FloatArray = NDArray[np.float64]

#: A model's points must spread off their best line by more than this fraction of their spread
#: along it (singular values of the centred points): else they are (nearly) collinear.
MIN_PLANARITY = 1e-3


@dataclass(frozen=True, eq=False)
class Model:
    """Named points of a rigid target in its body frame.

    Attributes:
        ids: (N,) point names, unique.
        points_body: (N,3) coordinates in the body frame, m (read-only array).
    """

    ids: tuple[str, ...]
    points_body: FloatArray

    def __post_init__(self) -> None:
        ids = tuple(str(i) for i in self.ids)
        p = np.array(self.points_body, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3 or len(p) != len(ids):
            raise TrackmeterError(f"model needs one (x, y, z) per id: {len(ids)} ids, points of shape {p.shape}")
        if not np.all(np.isfinite(p)):
            raise TrackmeterError("model has a non-finite coordinate")
        if len(ids) < 3:
            raise TrackmeterError(f"a model needs at least 3 points, got {len(ids)}")
        seen: set[str] = set()
        for i in ids:
            if i in seen:
                raise TrackmeterError(f"model point id {i!r} appears twice")
            seen.add(i)
        # Points on one line (or at one place) leave the attitude about that line undefined;
        # within a thousandth of their extent of it, the stereo noise alone decides it.
        spread = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
        if not spread[1] > MIN_PLANARITY * max(spread[0], 1e-300):
            raise TrackmeterError(
                f"a model's points must not all be (nearly) collinear or at one place: {len(ids)} points within "
                f"{MIN_PLANARITY:g} of their extent of one line leave the attitude about it undefined"
            )
        p.flags.writeable = False
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "points_body", p)

    def __len__(self) -> int:
        return len(self.ids)

    @classmethod
    def from_pairs(cls, pairs: Iterable[tuple[str, ArrayLike]]) -> Model:
        """From ``(name, xyz_body)`` pairs, e.g. a mock-up's ``salient_points``."""
        items = list(pairs)
        return cls(tuple(str(n) for n, _ in items), np.array([np.asarray(x, dtype=float).reshape(3) for _, x in items]).reshape(-1, 3))

    def point(self, point_id: str) -> FloatArray:
        """The (3,) body-frame coordinates of one point, m."""
        try:
            return self.points_body[self.ids.index(str(point_id))]
        except ValueError:
            raise TrackmeterError(f"model has no point {point_id!r}") from None


@dataclass(frozen=True)
class _PointEntry:
    id: str | int
    xyz: tuple[float, float, float]


@dataclass(frozen=True)
class _ModelFile:
    points: tuple[_PointEntry, ...]
    name: str = ""


def _drop_unknown_keys(data: dict[str, Any], path: Path) -> dict[str, Any]:
    """``data`` without the keys the model format does not define, warning once about them.

    Unlike a config file (where an unknown key is a typo that would silently change
    nothing), a model file is an exchange format: other tools add their own keys, and the
    points are all that matter here.
    """
    top = {f.name for f in dataclasses.fields(_ModelFile)}
    per_point = {f.name for f in dataclasses.fields(_PointEntry)}
    ignored = [str(k) for k in data if k not in top]
    out = {k: v for k, v in data.items() if k in top}
    if isinstance(out.get("points"), list):
        points = []
        for entry in out["points"]:
            if isinstance(entry, dict):  # anything else is left for build_dataclass to refuse
                ignored += [f"points[].{k}" for k in entry if k not in per_point and f"points[].{k}" not in ignored]
                entry = {k: v for k, v in entry.items() if k in per_point}
            points.append(entry)
        out["points"] = points
    if ignored:
        warnings.warn(f"{path}: ignoring key(s) that are not part of a model file: {', '.join(ignored)}", stacklevel=3)
    return out


class _IntAsWritten(int):
    """An integer that remembers its text in the file (``010``, ``0x1f``, ``1_000``)."""

    text: str


class _FloatAsWritten(float):
    """A float that remembers its text in the file (``1.50``, ``1e3``)."""

    text: str


class _ModelLoader(UniqueKeys, yaml.SafeLoader):
    """A SafeLoader whose numbers keep their text: a point's id is a name, and YAML 1.1
    would read ``010`` as 8 and ``0x1f`` as 31, which ``--target 010=U,V`` could never name."""


def _as_written(kind: type, construct: Any) -> Any:
    def build(loader: yaml.SafeLoader, node: yaml.ScalarNode) -> Any:
        value = kind(construct(loader, node))
        value.text = str(node.value)
        return value

    return build


_ModelLoader.add_constructor("tag:yaml.org,2002:int", _as_written(_IntAsWritten, yaml.SafeLoader.construct_yaml_int))
_ModelLoader.add_constructor("tag:yaml.org,2002:float", _as_written(_FloatAsWritten, yaml.SafeLoader.construct_yaml_float))


def _check_ids(ids: Sequence[str], path: Path) -> None:
    """Ids ``--target ID=U,V`` can name: not empty, no '=', no space around them."""
    for i, name in enumerate(ids):
        if not name.strip():
            raise TrackmeterError(f"{path}: points[{i}].id: empty (a point needs a name)")
        if "=" in name:
            raise TrackmeterError(f"{path}: points[{i}].id {name!r} contains '=' (--target ID=U,V could not name it)")
        if name != name.strip():
            raise TrackmeterError(f"{path}: points[{i}].id {name!r} begins or ends with a space")
        try:
            name.encode("utf-8")
        except UnicodeEncodeError:  # a YAML escape of a lone surrogate: no file or browser takes it
            raise TrackmeterError(f"{path}: points[{i}].id {name!r} is not text (a lone surrogate escape)") from None


#: A model whose points span more than this (m) is taken for one written in millimetres
#: (DESIGN.md: metres): a geostationary satellite's arrays span tens of metres, and any body
#: over 10 cm in mm spans more.
MAX_PLAUSIBLE_MODEL_SPAN_M = 100.0


#: What a model file holds, as the errors say it.
POINTS_FORM = "a list of {id: NAME, xyz: [x, y, z]}"


def load_model(path: str | Path) -> Model:
    """Read a model file.

    Keys other than ``name``, ``points`` and a point's ``id`` and ``xyz`` are ignored (one
    ``UserWarning`` names them).

    Raises:
        TrackmeterError: naming the file and the key: missing ``points``, an entry without
            ``id`` or ``xyz``, a non-numeric coordinate, fewer than 3 points, a repeated id.
    """
    path = Path(path)
    data = read_yaml_mapping(path, _ModelLoader, kind=f"a model file (points: {POINTS_FORM})")
    if "points" not in data:
        other = (" (this is a simulator mock-up's geometry, not a model; a simulated sequence folder holds its model.yaml)"
                 if "parts" in data or "materials" in data else "")
        raise TrackmeterError(f"{path}: missing key 'points' ({POINTS_FORM}){other}")
    data = _drop_unknown_keys(data, path)
    entries = data["points"]
    if isinstance(entries, list):
        for i, entry in enumerate(entries):
            if isinstance(entry, dict):
                for key in ("id", "xyz"):
                    if key not in entry:
                        raise TrackmeterError(f"{path}: 'points[{i}]': missing key '{key}'")
                if isinstance(entry["id"], (_IntAsWritten, _FloatAsWritten)):
                    entry["id"] = entry["id"].text  # a name: the text written, not the number read
    parsed = build_dataclass(_ModelFile, data, source=str(path))
    ids = tuple(str(e.id) for e in parsed.points)
    _check_ids(ids, path)
    try:
        model = Model(ids, np.array([e.xyz for e in parsed.points], dtype=float).reshape(-1, 3))
    except TrackmeterError as exc:
        raise TrackmeterError(f"{path}: {exc}") from None
    span = float(np.ptp(model.points_body, axis=0).max())
    if span > MAX_PLAUSIBLE_MODEL_SPAN_M:
        warnings.warn(f"{path}: the points span {span:.4g} m: a model is in metres; if it is in millimetres, no pose "
                      "will fit the tracked points", stacklevel=2)
    return model


def model_to_yaml(model: Model, name: str = "") -> str:
    """The model file text (flow-style point entries, shortest round-trip floats)."""
    head = f"name: {yaml.safe_dump(name, default_style=None).strip().splitlines()[0]}\n" if name else ""
    # Each id quoted as an item of a flow sequence, the context it is written in: a plain
    # scalar there ends at a comma or a bracket ("hinge,1" read back as "hinge").
    lines = [
        f"  - {{id: {yaml.safe_dump([i], default_flow_style=True, width=math.inf).strip()[1:-1]}, "
        f"xyz: [{', '.join(repr(float(c)) for c in p)}]}}"
        for i, p in zip(model.ids, model.points_body)
    ]
    return "# model points, body frame, metres\n" + head + "points:\n" + "\n".join(lines) + "\n"


def save_model(path: str | Path, model: Model | Sequence[tuple[str, ArrayLike]], name: str = "") -> Path:
    """Write a model file atomically (temp file, then rename). Accepts a Model or (name, xyz) pairs."""
    if not isinstance(model, Model):
        model = Model.from_pairs(model)
    path = Path(path)
    _check_ids(model.ids, path)  # what load_model would refuse is not written
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, model_to_yaml(model, name))
    return path


__all__ = ["Model", "load_model", "save_model", "model_to_yaml"]
