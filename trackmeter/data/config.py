"""Configuration: ``config/default.yaml`` layered with a user's YAML, into frozen dataclasses.

``config/default.yaml`` holds every tunable with a comment. A user's file (``--config``)
only needs the keys it changes; it is merged over the defaults key by key. Every value is
checked against the field that declares it (:func:`trackmeter.core.params.param`): an unknown
key, a wrong type or an out-of-range value raises :class:`TrackmeterError` naming the dotted
key (``tracker.max_targets``) and what was expected.

Adding a section: define a frozen ``XxxParams`` dataclass with :func:`param` fields in the
core module that uses it, add it as a field of :class:`Config`, and add its keys with comments
to ``config/default.yaml`` (a test checks the two agree).
"""

from __future__ import annotations

import difflib
import dataclasses
import math
import os
import re
import stat
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Literal, Mapping, Sequence, get_args, get_origin, get_type_hints

import yaml

from trackmeter.core.calibration import CalibrationParams
from trackmeter.core.matching import MeasureParams
from trackmeter.core.error_analysis import AnalyzeParams
from trackmeter.core.exposure import ExposureParams
from trackmeter.core.features import FeatureParams
from trackmeter.core.metrics import EvaluateParams
from trackmeter.core.output_filter import FilterParams
from trackmeter.core.params import KIND_NAMES, range_problem
from trackmeter.core.pose import PoseParams
from trackmeter.core.tracking import TrackerParams
from trackmeter.core.velocity import VelocityParams
from trackmeter.errors import TrackmeterError, quoted_name, shown_value
from trackmeter.paths import DEFAULT_CONFIG


@dataclass(frozen=True)
class Config:
    """The whole configuration; one field per section of ``config/default.yaml``."""

    measure: MeasureParams = field(default_factory=MeasureParams)
    calibrate: CalibrationParams = field(default_factory=CalibrationParams)
    evaluate: EvaluateParams = field(default_factory=EvaluateParams)
    analyze: AnalyzeParams = field(default_factory=AnalyzeParams)
    pose: PoseParams = field(default_factory=PoseParams)
    velocity: VelocityParams = field(default_factory=VelocityParams)
    output_filter: FilterParams = field(default_factory=FilterParams)
    tracker: TrackerParams = field(default_factory=TrackerParams)
    features: FeatureParams = field(default_factory=FeatureParams)
    exposure: ExposureParams = field(default_factory=ExposureParams)


def load_config(
    user_file: str | Path | Sequence[str | Path] | None = None, overrides: Mapping[str, Any] | None = None
) -> Config:
    """Load ``config/default.yaml``, layer ``user_file`` and then ``overrides`` over it.

    Args:
        user_file: a YAML file with any subset of the default keys, or several (``--config``
            given more than once), layered in order: a later file's value wins. Each file is
            checked as it is layered, over the defaults and the files before it, so an error
            names the file that gave the value (even one a later file would set again).
        overrides: a nested mapping applied last (e.g. from command-line options).

    Raises:
        TrackmeterError: unreadable or malformed YAML, unknown key, wrong type, out of range.
    """
    files = [] if user_file is None else [user_file] if isinstance(user_file, (str, Path)) else list(user_file)
    merged = read_yaml_mapping(DEFAULT_CONFIG)
    for path in files:
        merged = _merge(merged, read_yaml_mapping(Path(path), kind="a configuration file"), str(path), "")
        if len(files) > 1:
            build_dataclass(Config, merged, source=str(path))
    if overrides:
        merged = _merge(merged, dict(overrides), "overrides", "")
    return build_dataclass(Config, merged, source=str(files[-1] if files else DEFAULT_CONFIG))


def config_to_dict(config: Any) -> dict[str, Any]:
    """A plain nested dict of a config dataclass (tuples as lists), for YAML output."""

    def plain(value: Any) -> Any:
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        return value

    return plain(dataclasses.asdict(config))


#: libyaml's safe loader where PyYAML was built with it (the same resolvers and constructors as
#: :class:`yaml.SafeLoader`, scanned in C): the pure-Python scanner took 60 ms over the comments
#: of ``config/default.yaml``, which every command and every engine built reads.
_SAFE_LOADER: type[Any] = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


class DuplicateKeyError(yaml.constructor.ConstructorError):
    """A mapping that gives one key twice (YAML says keys are unique; PyYAML keeps the last)."""


class UniqueKeys:
    """A SafeLoader mix-in that refuses a key given twice in one mapping: PyYAML keeps the last
    silently, so a second ``evaluate:`` section in a ``--config`` file wholly replaced the first
    (its ``settle_s`` lost without a word)."""

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, Any] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue  # '<<' merges another mapping in: not a key of this one
                key = self.construct_object(key_node, deep=True)  # type: ignore[attr-defined]
                try:
                    first = seen.setdefault(key, key_node)
                except TypeError:
                    continue  # an unhashable key: SafeConstructor says so itself
                if first is not key_node:
                    lines = f"lines {first.start_mark.line + 1} and {key_node.start_mark.line + 1}"
                    if first.start_mark.line == key_node.start_mark.line:
                        lines = f"both on line {key_node.start_mark.line + 1}"
                    raise DuplicateKeyError(None, None, f"key {str(key)!r} given twice ({lines}): the second would "
                                            "replace the first", key_node.start_mark)
        return super().construct_mapping(node, deep)  # type: ignore[misc]


class _FastUniqueKeysLoader(UniqueKeys, _SAFE_LOADER):
    pass


#: The loader every YAML file of the project is read with: libyaml's where there is one,
#: refusing a key given twice (:class:`UniqueKeys`).
FAST_SAFE_LOADER: type[Any] = _FastUniqueKeysLoader


#: Largest YAML file read (settings, scenarios, models: a few kB to a few hundred kB).
MAX_YAML_BYTES = 16 * 2**20


#: The most values (mapping keys and values, list items, scalars) a YAML file may expand to
#: through its aliases: every file of ours holds hundreds; a 1 KB alias bomb expands to
#: hundreds of millions, which matrix parsing then takes seconds and gigabytes over.
MAX_YAML_VALUES = 1_000_000


def check_yaml_expansion(data: Any, source: object) -> None:
    """Refuse YAML ``data`` whose aliases expand it beyond :data:`MAX_YAML_VALUES` values or
    make a value contain itself (``&a [*a]``). Counted over the shared nodes once each, so
    the check costs what the file holds, not what it expands to.

    Raises:
        TrackmeterError: naming ``source`` and what the aliases do.
    """
    sizes: dict[int, int] = {}
    open_nodes: set[int] = set()

    def size(node: Any) -> int:
        if isinstance(node, dict):
            children: list[Any] = [*node.keys(), *node.values()]
        elif isinstance(node, list):
            children = node
        else:
            return 1
        key = id(node)
        if key in open_nodes:
            raise TrackmeterError(f"{source}: a YAML value contains itself (an alias to its own anchor)")
        if key not in sizes:
            open_nodes.add(key)
            sizes[key] = 1 + sum(size(child) for child in children)
            open_nodes.discard(key)
        return sizes[key]

    try:
        total = size(data)
    except RecursionError:
        raise TrackmeterError(f"{source}: YAML nested too deeply") from None
    if total > MAX_YAML_VALUES:
        raise TrackmeterError(f"{source}: its YAML aliases expand to {total:,} values (at most {MAX_YAML_VALUES:,}): "
                              "an alias bomb, not a file of ours")


def read_yaml_mapping(path: Path, loader: type[Any] = FAST_SAFE_LOADER, kind: str | None = None) -> dict[str, Any]:
    """Read a YAML file whose top level is a mapping (an empty file is an empty mapping),
    with ``loader`` (:data:`FAST_SAFE_LOADER`, a :class:`yaml.SafeLoader` or a subclass of it).
    ``kind`` names what the file should be ("a model file"): a stereo rig file given in its
    place, in any form the rig reader takes (:func:`_rig_form`), is then refused as one, not
    as "malformed YAML" (OpenCV's ``!!opencv-matrix``) or by its first unknown key.

    Only a regular file of at most :data:`MAX_YAML_BYTES` is read: a pipe with no writer would
    block the reading thread for ever (the console's tracking thread, loading a model) and a
    device such as ``/dev/zero`` would fill the memory."""
    try:
        info = os.stat(path)
    except FileNotFoundError:
        raise TrackmeterError(f"{path}: no such file") from None
    except OSError as exc:
        raise TrackmeterError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except ValueError:  # "embedded null byte": typed in the console's Model file field
        raise TrackmeterError(f"{quoted_name(str(path))}: no such file (a file name cannot hold a NUL character)") from None
    if stat.S_ISDIR(info.st_mode):
        raise TrackmeterError(f"{path}: a folder, not a file")
    if not stat.S_ISREG(info.st_mode):
        raise TrackmeterError(f"{path}: not a regular file (a device, a pipe or a socket): YAML is read from a file")
    if info.st_size > MAX_YAML_BYTES:
        raise TrackmeterError(f"{path}: {info.st_size / 2**20:.0f} MiB, too large for a YAML file "
                              f"(at most {MAX_YAML_BYTES // 2**20} MiB)")
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise TrackmeterError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise TrackmeterError(f"{path}: a folder, not a file") from None
    except UnicodeDecodeError:
        raise TrackmeterError(f"{path}: not a text file (YAML is UTF-8 text)") from None
    except OSError as exc:
        raise TrackmeterError(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        data = yaml.load(text, Loader=loader)  # noqa: S506 (a SafeLoader)
    except DuplicateKeyError as exc:
        raise TrackmeterError(f"{path}: {exc.problem}") from None
    except yaml.YAMLError as exc:
        if kind is not None and (rig := _rig_form(text, None)):
            raise TrackmeterError(f"{path}: {rig}, not {kind}") from None
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise TrackmeterError(f"{path}: malformed YAML{where}") from None
    check_yaml_expansion(data, path)
    rig = _rig_form(text, data) if kind is not None else None
    if rig:
        raise TrackmeterError(f"{path}: {rig}, not {kind}")
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise TrackmeterError(f"{path}: expected a mapping of keys at the top level, got {type(data).__name__}")
    return data


#: A camera matrix's key in a rig file (DESIGN.md's rig.yaml; OpenCV's intrinsics.yml).
_RIG_CAMERA_KEYS = frozenset({"K1", "K2", "M1", "M2"})

#: How a Middlebury ``calib.txt`` (a stereo rig) begins: ``cam0=[f 0 cx; ...]``, after any blank
#: or ``#`` comment lines (Middlebury's own files have none; a hand-annotated copy may).
MIDDLEBURY_CALIB_START = re.compile(r"(?:[ \t]*(?:#[^\n]*)?\r?\n)*[ \t]*cam0\s*=\s*\[", re.IGNORECASE)


def _rig_form(text: str, data: object) -> str | None:
    """Which form of stereo rig file ``text`` (``data`` as YAML read it, or None) is, said for
    an error, or None when it is none of those the rig reader takes."""
    head = text.lstrip("\ufeff \t\r\n")  # a byte-order mark too (Windows editors write one)
    if head.startswith("<?xml") and "<opencv_storage>" in head:
        return "an OpenCV FileStorage file in XML (a stereo rig?)"
    if head.startswith("%YAML:") or "!!opencv-matrix" in text:
        return "an OpenCV FileStorage file (a stereo rig?)"
    if isinstance(data, dict):
        if _RIG_CAMERA_KEYS & {str(k) for k in data}:
            return "a stereo rig file (its camera matrices K1, K2)"
        if isinstance(data.get("cam0"), dict) and "intrinsics" in data["cam0"]:
            return "a Kalibr camchain (a stereo rig)"
    if MIDDLEBURY_CALIB_START.match(head):
        return "a Middlebury calib.txt (a stereo rig)"
    return None


def _did_you_mean(key: str, known: Iterable[str], prefix: str, root: Mapping[str, Any] | None = None) -> str:
    """`` (did you mean 'PREFIX.KEY'?)`` for the known key a misspelt one likely meant: the same
    but for case, else the closest (:func:`difflib.get_close_matches`), else, with the whole
    default tree ``root``, the key under another section (``pose: max_targets`` is
    ``tracker.max_targets``); ``""`` when none is near."""
    names = [str(k) for k in known]
    by_case = {n.lower(): n for n in names}
    close = ([by_case[key.lower()]] if key.lower() in by_case
             else [by_case[c] for c in difflib.get_close_matches(key.lower(), list(by_case), n=1, cutoff=0.75)])
    if close:
        return f" (did you mean '{prefix}{close[0]}'?)"
    if root is not None:
        homes = [f"{section}.{key}" for section, keys in root.items() if isinstance(keys, dict) and key in keys]
        if homes:
            where = "another section" if prefix else "a section"
            return f" (it is a key of {where}: {', '.join(homes)})"
    return ""


def _merge(base: dict[str, Any], update: Mapping[str, Any], source: str, prefix: str,
           root: Mapping[str, Any] | None = None) -> dict[str, Any]:
    root = base if root is None else root
    out = dict(base)
    for key, value in update.items():
        dotted = f"{prefix}{key}"
        if key not in base:
            raise TrackmeterError(f"{source}: unknown key '{dotted}'{_did_you_mean(str(key), base, prefix, root)}")
        if isinstance(base[key], dict):
            if not isinstance(value, dict):
                raise TrackmeterError(f"{source}: '{dotted}' must be a mapping of keys, got {shown_value(value)}")
            out[key] = _merge(base[key], value, source, f"{dotted}.", root)
        else:
            out[key] = value
    return out


def build_dataclass(cls: type, data: Mapping[str, Any], source: str = "config", prefix: str = "") -> Any:
    """Build the frozen dataclass ``cls`` from a nested mapping, validating every value.

    Keys missing from ``data`` take the dataclass default. Generic over any dataclass whose
    fields are numbers, bools, strings, ``Literal``s, tuples of those, optionals, or nested
    dataclasses; scenario and model loaders use it too.
    """
    if not isinstance(data, Mapping):
        raise TrackmeterError(f"{source}: '{prefix.rstrip('.') or 'top level'}' must be a mapping of keys")
    hints = get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for key in data:
        if key not in fields:
            known = ", ".join(sorted(fields))
            raise TrackmeterError(f"{source}: unknown key '{prefix}{key}'{_did_you_mean(str(key), fields, prefix)} "
                                  f"(known here: {known})")
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        if name not in data:
            continue
        dotted = f"{prefix}{name}"
        kwargs[name] = _convert(hints[name], data[name], f.metadata, source, dotted)
    try:
        return cls(**kwargs)
    except TrackmeterError as exc:
        raise TrackmeterError(f"{source}: '{prefix.rstrip('.') or cls.__name__}': {exc}") from None
    except (TypeError, ValueError) as exc:
        raise TrackmeterError(f"{source}: '{prefix.rstrip('.') or cls.__name__}': {exc}") from None


def _describe(tp: Any) -> str:
    origin = get_origin(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in get_args(tp))
    if origin in (tuple,):
        args = get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_describe(args[0])}"
        return f"a list of {len(args)} values ({', '.join(_describe(a) for a in args)})"
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_describe(a) for a in get_args(tp))
    if tp is type(None):
        return "null"
    if dataclasses.is_dataclass(tp):
        return "a mapping of keys"
    return KIND_NAMES.get(tp, str(tp))


#: A number in exponent notation without a decimal point (``1e3``, ``-2E-4``).
_EXPONENT_NUMBER = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+")


def _convert(tp: Any, value: Any, meta: Mapping[str, Any], source: str, dotted: str) -> Any:
    def fail(expected: str | None = None) -> typing.NoReturn:
        raise TrackmeterError(f"{source}: '{dotted}': expected {expected or _describe(tp)}, got {shown_value(value)}")

    origin = get_origin(tp)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, Mapping):
            fail()
        return build_dataclass(tp, value, source, f"{dotted}.")  # type: ignore[arg-type]
    if origin in (typing.Union, types.UnionType):
        args = get_args(tp)
        if value is None:
            if type(None) in args:
                return None
            fail()
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(arg, value, meta, source, dotted)
            except TrackmeterError:
                continue
        fail()
    if origin is Literal:
        if value not in get_args(tp):
            fail()
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            fail()
        args = get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            items = [_convert(args[0], v, meta, source, f"{dotted}[{i}]") for i, v in enumerate(value)]
        else:
            if len(value) != len(args):
                fail()
            items = [_convert(a, v, meta, source, f"{dotted}[{i}]") for i, (a, v) in enumerate(zip(args, value))]
        return tuple(items)
    if tp is bool:
        if not isinstance(value, bool):
            fail()
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            fail()
        _check_range(value, meta, source, dotted)
        return value
    if tp is float:
        if isinstance(value, str) and _EXPONENT_NUMBER.fullmatch(value.strip()):
            value = float(value)  # YAML 1.1 (PyYAML) reads 1e3 as a string; YAML 1.2 and people a number
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            fail()
        value = float(value)
        if not math.isfinite(value):  # NaN or YAML's .inf: no setting means "unbounded"
            fail("a finite number")
        _check_range(value, meta, source, dotted)
        return value
    if tp is str:
        if not isinstance(value, str):
            fail()
        choices = meta.get("choices")
        if choices is not None and value not in choices:
            fail("one of " + ", ".join(repr(c) for c in choices))
        return value
    if tp is Any:
        return value
    fail()


def check_option(params_type: type, name: str, value: Any, option: str) -> Any:
    """``value`` of the command-line ``option`` that sets ``params_type``'s field ``name``, held
    to that field's range or choices (:func:`trackmeter.core.params.param`) as a ``--config``
    key is; a number must be finite.

    Raises:
        TrackmeterError: ``"OPTION: expected a value in [lo, hi], got V"`` and the like.
    """
    meta = next(f.metadata for f in dataclasses.fields(params_type) if f.name == name)
    _check_range(value, meta, option, "", finite=True)
    return value


def _check_range(value: float, meta: Mapping[str, Any], source: str, dotted: str, finite: bool = False) -> None:
    """Raise when ``value`` is outside ``meta``'s bounds or choices (or, with ``finite``, not a
    finite number); the message names ``source: 'dotted'``, or ``source`` alone without a key."""
    where = f"{source}: '{dotted}'" if dotted else source
    problem = range_problem(value, meta, finite)  # the same test a Params class's __post_init__ makes
    if problem is not None:
        raise TrackmeterError(f"{where}: {problem}")
