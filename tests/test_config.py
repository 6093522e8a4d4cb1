"""Configuration (trackmeter.data.config): config/default.yaml agrees with the Params dataclasses,
bad values are refused with their dotted key, and a user file layers over the defaults."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import pytest
import yaml

from trackmeter.data.config import Config, build_dataclass, config_to_dict, load_config, read_yaml_mapping
from trackmeter.errors import TrackmeterError
from trackmeter.paths import DEFAULT_CONFIG


def leaf_fields(cls: type, prefix: str = "") -> Iterator[tuple[str, dataclasses.Field, Any]]:  # type: ignore[type-arg]
    """Every non-dataclass field of ``cls`` and nested dataclasses: (dotted key, field, default)."""
    instance = cls()
    for f in dataclasses.fields(cls):
        value = getattr(instance, f.name)
        if dataclasses.is_dataclass(value):
            yield from leaf_fields(type(value), f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", f, value


def yaml_keys_with_comment(path: Path) -> dict[str, bool]:
    """Dotted key → whether the line just above it (blank lines excluded) is a comment."""
    out: dict[str, bool] = {}
    stack: list[tuple[int, str]] = []
    previous = ""
    for line in path.read_text().splitlines():
        stripped = line.strip()
        if not stripped:
            continue
        match = re.match(r"^(\s*)([A-Za-z_][A-Za-z0-9_]*)\s*:", line)
        if match and not stripped.startswith("#"):
            indent = len(match.group(1))
            while stack and stack[-1][0] >= indent:
                stack.pop()
            dotted = ".".join([k for _, k in stack] + [match.group(2)])
            out[dotted] = previous.startswith("#")
            stack.append((indent, match.group(2)))
        previous = stripped
    return out


def _get(data: dict[str, Any], dotted: str) -> Any:
    for part in dotted.split("."):
        data = data[part]
    return data


def _plain(value: Any) -> Any:
    return [_plain(v) for v in value] if isinstance(value, (tuple, list)) else value


def _same_kind(value: Any, default: Any) -> bool:
    """YAML ``8`` for an int default, ``8`` or ``8.0`` for a float, ``true`` for a bool."""
    if isinstance(default, bool) or isinstance(value, bool):
        return type(value) is type(default)
    if isinstance(default, int):
        return isinstance(value, int)
    if isinstance(default, float):
        return isinstance(value, (int, float))
    return True


# --------------------------------------------------------------------------- default.yaml agrees


def test_every_param_is_in_default_yaml_with_its_default() -> None:
    data = read_yaml_mapping(DEFAULT_CONFIG)
    missing, different = [], []
    for dotted, _, default in leaf_fields(Config):
        try:
            value = _get(data, dotted)
        except (KeyError, TypeError):
            missing.append(dotted)
            continue
        if _plain(value) != _plain(default) or not _same_kind(value, default):
            different.append(f"{dotted}: yaml {value!r} vs dataclass {default!r}")
    assert not missing, f"missing from {DEFAULT_CONFIG.name}: {missing}"
    assert not different, different


def test_every_key_of_default_yaml_has_a_comment_above_it() -> None:
    comments = yaml_keys_with_comment(DEFAULT_CONFIG)
    leaves = [dotted for dotted, _, _ in leaf_fields(Config)]
    assert leaves, "Config has no fields"
    uncommented = [k for k in leaves if not comments.get(k, False)]
    assert not uncommented, f"keys without a comment line above them: {uncommented}"


def test_every_param_declares_a_doc_string() -> None:
    for dotted, f, _ in leaf_fields(Config):
        assert f.metadata.get("doc"), f"{dotted} is not declared with param(..., doc)"


def test_default_yaml_has_no_key_the_dataclasses_lack() -> None:
    """load_config() builds Config from the file: an extra key would be refused."""
    config = load_config()
    assert config == Config()
    assert config_to_dict(config) == yaml.safe_load(yaml.safe_dump(config_to_dict(Config())))


# --------------------------------------------------------------------------- refusals


def _first_leaf(kind: type) -> tuple[str, dataclasses.Field, Any]:  # type: ignore[type-arg]
    for dotted, f, default in leaf_fields(Config):
        if type(default) is kind:
            return dotted, f, default
    pytest.skip(f"no {kind.__name__} parameter registered")


def _nested(dotted: str, value: Any) -> dict[str, Any]:
    out: Any = value
    for part in reversed(dotted.split(".")):
        out = {part: out}
    return out


def _write(tmp_path: Path, data: Any) -> Path:
    path = tmp_path / "user.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_unknown_key_is_refused_with_its_dotted_path(tmp_path: Path) -> None:
    section = dataclasses.fields(Config)[0].name
    with pytest.raises(TrackmeterError, match=rf"'{section}\.no_such_key'"):
        load_config(_write(tmp_path, {section: {"no_such_key": 1}}))
    with pytest.raises(TrackmeterError, match=r"'no_such_section'"):
        load_config(_write(tmp_path, {"no_such_section": {}}))


@pytest.mark.parametrize("text, said", [
    ("tracker: {max_targts: 12}", "unknown key 'tracker.max_targts' "
                                  "(did you mean 'tracker.max_targets'?)"),
    ("trackr: {max_targets: 12}", "unknown key 'trackr' (did you mean 'tracker'?)"),
    ("tracker: {zzzz: 1}", "unknown key 'tracker.zzzz'"),
    ("tracker: {MAX_TARGETS: 12}", "unknown key 'tracker.MAX_TARGETS' (did you mean 'tracker.max_targets'?)"),
    ("pose: {max_targets: 12}", "unknown key 'pose.max_targets' (it is a key of another section: tracker.max_targets)"),
    ("max_targets: 12", "unknown key 'max_targets' (it is a key of a section: tracker.max_targets)"),
])
def test_a_misspelt_key_is_refused_with_the_key_it_likely_meant(tmp_path: Path, text: str, said: str) -> None:
    """'unknown key tracker.max_targts' left the user to find the spelling in a 600-line file
    (an outside probe)."""
    path = tmp_path / "c.yaml"
    path.write_text(text + "\n")
    with pytest.raises(TrackmeterError) as info:
        load_config(path)
    assert str(info.value) == f"{path}: {said}"


def test_wrong_type_is_refused_with_its_dotted_path(tmp_path: Path) -> None:
    dotted, _, _ = _first_leaf(int)
    with pytest.raises(TrackmeterError, match=rf"'{re.escape(dotted)}'.*expected an integer") as info:
        load_config(_write(tmp_path, _nested(dotted, "eight")))
    assert "\n" not in str(info.value)
    with pytest.raises(TrackmeterError, match=re.escape(dotted)):
        load_config(_write(tmp_path, _nested(dotted, 8.5)))
    with pytest.raises(TrackmeterError, match=re.escape(dotted)):
        load_config(_write(tmp_path, _nested(dotted, True)))  # bool is not an int here
    section = dotted.split(".")[0]
    with pytest.raises(TrackmeterError, match=rf"'{section}' must be a mapping"):
        load_config(_write(tmp_path, {section: 3}))


def test_out_of_range_is_refused_with_its_dotted_path(tmp_path: Path) -> None:
    for dotted, f, _ in leaf_fields(Config):
        if "min" in f.metadata and isinstance(f.default, (int, float)) and not isinstance(f.default, bool):
            low = f.metadata["min"] - 1
            value = int(low) if isinstance(f.default, int) else float(low)
            with pytest.raises(TrackmeterError, match=rf"'{re.escape(dotted)}': expected a value in \["):
                load_config(_write(tmp_path, _nested(dotted, value)))
        if "max" in f.metadata and isinstance(f.default, (int, float)) and not isinstance(f.default, bool):
            high = f.metadata["max"] + 1
            value = int(high) if isinstance(f.default, int) else float(high)
            with pytest.raises(TrackmeterError, match=rf"'{re.escape(dotted)}'"):
                load_config(_write(tmp_path, _nested(dotted, value)))


@pytest.mark.parametrize("value", [float("inf"), float("-inf"), float("nan")])
def test_non_finite_numbers_are_refused_everywhere(tmp_path: Path, value: float) -> None:
    # YAML spells them .inf / .nan; no setting takes infinity to mean "unbounded", and an
    # unbounded scenario duration or gate only fails later, far from the file.
    for dotted, f, _ in leaf_fields(Config):
        if type(f.default) is float:
            with pytest.raises(TrackmeterError, match=rf"'{re.escape(dotted)}': expected a finite number"):
                load_config(_write(tmp_path, _nested(dotted, value)))


def test_an_empty_disparity_range_is_refused_naming_both_settings(tmp_path: Path) -> None:
    text = {"measure": {"min_disparity_px": 300.0, "max_disparity_px": 200.0}}
    with pytest.raises(TrackmeterError, match=r"'measure': min_disparity_px \(300\) must be below max_disparity_px \(200\)"):
        load_config(_write(tmp_path, text))


@pytest.mark.parametrize("text, words", [
    ({"features": {"min_depth_m": 60.0, "max_depth_m": 50.0}}, r"'features': min_depth_m \(60\) must be below max_depth_m \(50\)"),
    ({"tracker": {"min_search_px": 100.0, "max_search_px": 96.0}}, r"'tracker': min_search_px \(100\) must not exceed max_search_px \(96\)"),
    ({"features": {"gabor_wavelengths_px": []}}, r"'features': gabor_wavelengths_px needs at least one wavelength"),
])
def test_crossed_or_empty_settings_are_refused_at_load_not_on_every_frame(tmp_path: Path, text: dict, words: str) -> None:
    with pytest.raises(TrackmeterError, match=words):
        load_config(_write(tmp_path, text))


def test_a_number_in_exponent_notation_is_a_number(tmp_path: Path) -> None:
    """PyYAML (YAML 1.1) reads ``1e3`` as a string; whoever wrote it meant a thousand."""
    path = tmp_path / "c.yaml"
    path.write_text("output_filter:\n  cutoff_hz: 1e3\nmeasure:\n  min_sigma_disparity_px: 2E-2\n")
    config = load_config(path)
    assert config.output_filter.cutoff_hz == 1000.0 and config.measure.min_sigma_disparity_px == 0.02
    path.write_text("output_filter:\n  cutoff_hz: 1e3x\n")
    with pytest.raises(TrackmeterError, match="expected a number"):
        load_config(path)


def test_choice_outside_the_list_is_refused(tmp_path: Path) -> None:
    with pytest.raises(TrackmeterError, match=r"'calibrate\.distortion_model': expected one of"):
        load_config(_write(tmp_path, {"calibrate": {"distortion_model": "fisheye"}}))


@pytest.mark.parametrize("path", sorted(p for p in DEFAULT_CONFIG.parent.rglob("*.yaml") if p.parent.name != "rigs"),
                         ids=lambda p: p.name)  # the rigs are OpenCV FileStorage files, read apart
def test_the_fast_loader_reads_every_shipped_file_as_the_python_one_does(path: Path) -> None:
    assert read_yaml_mapping(path) == yaml.load(path.read_text(encoding="utf-8"), Loader=yaml.SafeLoader)  # noqa: S506


def test_malformed_yaml_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("measure:\n  patch_size: [8\n")
    with pytest.raises(TrackmeterError, match=r"malformed YAML at line \d+") as info:
        load_config(path)
    assert str(path) in str(info.value)
    path.write_text("- a list\n- not a mapping\n")
    with pytest.raises(TrackmeterError, match="mapping"):
        load_config(path)
    with pytest.raises(TrackmeterError, match="no such file"):
        load_config(tmp_path / "absent.yaml")


def test_a_key_given_twice_is_refused_with_both_lines(tmp_path: Path) -> None:
    # PyYAML keeps the last of two equal keys: a second `evaluate:` section wholly replaced the
    # first, its settle_s lost without a word.
    path = tmp_path / "twice.yaml"
    path.write_text("evaluate:\n  settle_s: 2.0\nmeasure:\n  patch_size: 8\nevaluate:\n  tolerance_s: 0.02\n")
    with pytest.raises(TrackmeterError, match=r"twice\.yaml: key 'evaluate' given twice \(lines 1 and 5\)"):
        load_config(path)
    path.write_text("measure:\n  patch_size: 8\n  patch_size: 10\n")  # within a section too
    with pytest.raises(TrackmeterError, match=r"key 'patch_size' given twice \(lines 2 and 3\)"):
        load_config(path)
    # A model's points (their own loader) and YAML's merge key are read as before.
    from trackmeter.data.model import load_model

    model = tmp_path / "model.yaml"
    model.write_text("points:\n  - {id: a, xyz: [0, 0, 0]}\n  - {id: b, xyz: [0.1, 0, 0], xyz: [0.2, 0, 0]}\n"
                     "  - {id: c, xyz: [0, 0.1, 0]}\n")
    with pytest.raises(TrackmeterError, match="key 'xyz' given twice"):
        load_model(model)
    path.write_text("base: &b {settle_s: 2.0}\nevaluate:\n  <<: *b\n  tolerance_s: 0.02\n")
    assert read_yaml_mapping(path)["evaluate"] == {"settle_s": 2.0, "tolerance_s": 0.02}


# --------------------------------------------------------------------------- layering


def test_user_file_layers_over_defaults(tmp_path: Path) -> None:
    path = _write(tmp_path, {"calibrate": {"subpix_window_px": 11}})
    config = load_config(path)
    assert config.calibrate.subpix_window_px == 11
    # untouched keys of the same section and other sections keep their defaults
    assert config.calibrate.reject_ratio == Config().calibrate.reject_ratio
    assert config.measure == Config().measure
    # overrides apply last
    config = load_config(path, overrides={"calibrate": {"subpix_window_px": 7}})
    assert config.calibrate.subpix_window_px == 7
    # an empty user file is the defaults
    (tmp_path / "empty.yaml").write_text("")
    assert load_config(tmp_path / "empty.yaml") == Config()


def test_several_user_files_layer_in_the_order_given(tmp_path: Path) -> None:
    """``--config`` given twice kept only the last file (an outside probe): the first was
    neither layered nor even read, so an unknown key in it went unnoticed."""
    first = tmp_path / "first.yaml"
    first.write_text("calibrate:\n  subpix_window_px: 11\n  reject_ratio: 4\n")
    second = tmp_path / "second.yaml"
    second.write_text("calibrate:\n  subpix_window_px: 7\nmeasure:\n  min_score: 0.5\n")
    config = load_config([first, second])
    assert config.calibrate.subpix_window_px == 7  # the later file wins where both set a key
    assert config.calibrate.reject_ratio == 4.0  # the earlier file's other keys stay
    assert config.measure.min_score == 0.5
    assert config == load_config(second, overrides={"calibrate": {"reject_ratio": 4}})
    assert load_config([]) == Config() == load_config(None)
    bad = tmp_path / "bad.yaml"
    bad.write_text("measure:\n  patch_sizee: 9\n")
    with pytest.raises(TrackmeterError, match=r"bad\.yaml: unknown key 'measure\.patch_sizee'"):
        load_config([bad, second])
    wrong = tmp_path / "wrong.yaml"
    wrong.write_text("calibrate:\n  subpix_window_px: many\n")
    with pytest.raises(TrackmeterError, match=r"wrong\.yaml.*'calibrate\.subpix_window_px'"):
        load_config([first, wrong])
    # Each file is checked as it is layered, so the error names the file that gave the value,
    # even where a later file sets the key again.
    with pytest.raises(TrackmeterError, match=r"^[^:]*wrong\.yaml: 'calibrate\.subpix_window_px'"):
        load_config([wrong, second])
    # ... and the checks across keys see the layers below: a window set by the first file is
    # the one the second file's values are judged with.
    far = tmp_path / "far.yaml"
    far.write_text("features:\n  max_depth_m: 200\n")
    beyond = tmp_path / "beyond.yaml"
    beyond.write_text("features:\n  min_depth_m: 60\n")
    assert load_config([far, beyond]).features.min_depth_m == 60.0
    with pytest.raises(TrackmeterError, match=r"beyond\.yaml.*min_depth_m \(60\) must be below max_depth_m \(50\)"):
        load_config([beyond, far])


def test_int_is_accepted_for_float_and_config_is_frozen(tmp_path: Path) -> None:
    config = load_config(_write(tmp_path, {"calibrate": {"reject_ratio": 3}}))
    assert config.calibrate.reject_ratio == 3.0 and isinstance(config.calibrate.reject_ratio, float)
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.calibrate.reject_ratio = 1.0  # type: ignore[misc]


@dataclasses.dataclass(frozen=True)
class Inner:
    n: int = 1


@dataclasses.dataclass(frozen=True)
class Outer:
    name: str = "x"
    values: tuple[float, ...] = (1.0,)
    inner: Inner = dataclasses.field(default_factory=Inner)


def test_build_dataclass_is_generic() -> None:
    built = build_dataclass(Outer, {"values": [1, 2.5], "inner": {"n": 4}}, source="m.yaml")
    assert built == Outer("x", (1.0, 2.5), Inner(4))
    with pytest.raises(TrackmeterError, match=r"m\.yaml: 'inner\.n'"):
        build_dataclass(Outer, {"inner": {"n": "four"}}, source="m.yaml")
    with pytest.raises(TrackmeterError, match=r"'values\[1\]'"):
        build_dataclass(Outer, {"values": [1, "b"]}, source="m.yaml")


def test_a_binary_file_given_as_yaml_is_named_so(tmp_path: Path) -> None:
    """A binary file given as --config, --model or --scenario said "cannot read: 'utf-8'
    codec can't decode byte 0x89 in position 0: invalid start byte"."""
    path = tmp_path / "image.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\xff\xfe")
    with pytest.raises(TrackmeterError) as info:
        read_yaml_mapping(path)
    assert str(info.value) == f"{path}: not a text file (YAML is UTF-8 text)"


_RIG_FORMS = {
    "filestorage.yaml": "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\nK1: !!opencv-matrix\n   rows: 3\n"
                        "   cols: 3\n   dt: d\n   data: [ 800., 0., 320., 0., 800., 240., 0., 0., 1. ]\n",
    "plain.yaml": "image_width: 640\nimage_height: 480\nK1: [[800, 0, 320], [0, 800, 240], [0, 0, 1]]\n"
                  "K2: [[800, 0, 320], [0, 800, 240], [0, 0, 1]]\nT: [-0.2, 0, 0]\n",
    "filestorage.xml": '<?xml version="1.0"?>\n<opencv_storage>\n<image_width>640</image_width>\n'
                       '<K1 type_id="opencv-matrix"><rows>3</rows><cols>3</cols><dt>d</dt>\n'
                       '  <data>800. 0. 320. 0. 800. 240. 0. 0. 1.</data></K1>\n</opencv_storage>\n',
    "camchain.yaml": "cam0:\n  camera_model: pinhole\n  intrinsics: [800, 800, 320, 240]\n  resolution: [640, 480]\n"
                     "cam1:\n  camera_model: pinhole\n  intrinsics: [800, 800, 320, 240]\n  resolution: [640, 480]\n",
    "calib.txt": "cam0=[800 0 320; 0 800 240; 0 0 1]\ncam1=[800 0 330; 0 800 240; 0 0 1]\ndoffs=10\nbaseline=200\n"
                 "width=640\nheight=480\n",
    "calib_bom.txt": "\ufeffcam0=[800 0 320; 0 800 240; 0 0 1]\r\ncam1=[800 0 330; 0 800 240; 0 0 1]\r\nbaseline=200\r\n",
}


@pytest.mark.parametrize("form", sorted(_RIG_FORMS))
@pytest.mark.parametrize("kind", ["config", "scenario", "mockup", "model"])
def test_a_stereo_rig_given_for_another_file_is_named_as_one(tmp_path: Path, form: str, kind: str) -> None:
    """A rig file given as --config, a scenario, a mock-up or a model said "unknown key
    'image_width'", "expected a mapping of keys at the top level, got str" (XML) or "missing
    key 'points'" (an outside probe), in whichever form the rig reader takes it."""
    from trackmeter.data.model import load_model
    from trackmeter.sources.sim.mockup import load_mockup
    from trackmeter.sources.sim.scenario import load_scenario

    path = tmp_path / form
    path.write_text(_RIG_FORMS[form])
    load = {"config": load_config, "scenario": load_scenario, "mockup": load_mockup, "model": load_model}[kind]
    with pytest.raises(TrackmeterError) as info:
        load(path)
    assert str(info.value).startswith(f"{path}: ") and "a stereo rig" in str(info.value), info.value
    assert {"config": "not a configuration file", "scenario": "not a scenario file", "mockup": "not a mock-up file",
            "model": "not a model file"}[kind] in str(info.value), info.value


def test_a_yaml_alias_bomb_is_refused_in_a_short_message_quickly(tmp_path: Path) -> None:
    """Nine levels of nine aliases (1 KB) as a model's points: the refusal quoted the whole
    expansion, 312 million characters built in seconds, while the console's tracking thread
    waited and the browser tab crashed on the message (an outside probe)."""
    import time
    import warnings

    from trackmeter.data.model import load_model

    lines = ['a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for prev, name in zip("abcdefgh", "bcdefghi"):
        lines.append(f"{name}: &{name} [{', '.join([f'*{prev}'] * 9)}]")
    lines.append("points: *i")
    path = tmp_path / "bomb.yaml"
    path.write_text("\n".join(lines) + "\n")
    start = time.perf_counter()
    with warnings.catch_warnings(), pytest.raises(TrackmeterError) as info:
        warnings.simplefilter("ignore")
        load_model(path)
    assert len(str(info.value)) < 300, str(info.value)[:300]
    assert "YAML aliases expand to" in str(info.value), str(info.value)
    assert time.perf_counter() - start < 1.0  # was 4-8 s: the expansion's repr, not the parse


@pytest.mark.parametrize("value", [list(range(10_000)), "x" * 10_000, {"k": [[[[[[[[1]]]]]]]]}])
def test_a_refused_value_is_quoted_short(tmp_path: Path, value: object) -> None:
    from trackmeter.data.model import load_model

    path = tmp_path / "m.yaml"
    path.write_text(yaml.safe_dump({"points": [{"id": "a", "xyz": value}, {"id": "b", "xyz": [0, 0, 1]},
                                               {"id": "c", "xyz": [0, 1, 0]}]}))
    with pytest.raises(TrackmeterError) as info:
        load_model(path)
    assert "xyz" in str(info.value) and len(str(info.value)) < 300, str(info.value)[:400]


def test_a_model_point_id_that_is_no_text_is_refused(tmp_path: Path) -> None:
    """An id written as a YAML escape of a lone surrogate ("p\\udcff") passed: the console's
    dropdown could not send it (every page went blank) and no run file could write it (an
    outside probe)."""
    from trackmeter.data.model import load_model

    path = tmp_path / "m.yaml"
    path.write_text('points:\n- {id: "p\\udcff", xyz: [0, 0, 0]}\n- {id: b, xyz: [1, 0, 0]}\n'
                    '- {id: c, xyz: [0, 1, 0]}\n')
    with pytest.raises(TrackmeterError, match=r"points\[0\]\.id .* is not text"):
        load_model(path)


@pytest.mark.parametrize("ids", [("hinge,1", "b", "c"), ("panel,left", "panel,right", "antenna"),
                                 ("a[1]", "a]2", "b"), ("x}", "{y", "?z"), ("010", "yes", "0x1f")])
def test_a_saved_model_reads_back_with_the_ids_it_was_given(tmp_path: Path, ids: tuple[str, ...]) -> None:
    """Ids were quoted for a block, not for the flow mapping each point is written in: "hinge,1"
    read back as "hinge" (with a warning), "a[1]" as malformed YAML (an outside probe)."""
    from trackmeter.data.model import Model, load_model, save_model

    points = [[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.2, 0.0]]
    back = load_model(save_model(tmp_path / "model.yaml", Model(ids, points)))
    assert back.ids == ids and np.array_equal(back.points_body, points)


def test_a_model_that_its_reader_would_refuse_is_not_saved(tmp_path: Path) -> None:
    from trackmeter.data.model import Model, save_model

    with pytest.raises(TrackmeterError, match="empty"):
        save_model(tmp_path / "model.yaml", Model(("", "b", "c"), [[0, 0, 0], [1, 0, 0], [0, 1, 0]]))
    assert not (tmp_path / "model.yaml").exists()


def _alias_bomb(key: str, levels: int = 9) -> str:
    lines = [f'{key}: &a [1, 1, 1, 1, 1, 1, 1, 1, 1]'.replace(f"{key}: ", "a: ", 1)]
    names = "abcdefghijkl"
    for prev, name in zip(names, names[1:levels]):
        lines.append(f"{name}: &{name} [{', '.join([f'*{prev}'] * 9)}]")
    lines.append(f"{key}: *{names[levels - 1]}")
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("key", ["T", "image_width", "K1"])
def test_a_rig_file_with_an_alias_bomb_is_refused_at_once(tmp_path: Path, key: str) -> None:
    """A 1 KB plain-YAML rig whose T (or image_width, K1) is nine levels of nine aliases took
    27-53 s and 2.7 GB before "key 'T' is not a matrix" (an outside re-check)."""
    import time

    from trackmeter.data.rigfile import load_rig

    plain = {"image_width": 726, "image_height": 512, "K1": [[1152, 0, 362.5], [0, 1152, 255.5], [0, 0, 1]],
             "D1": [0, 0, 0, 0, 0], "K2": [[1152, 0, 362.5], [0, 1152, 255.5], [0, 0, 1]], "D2": [0, 0, 0, 0, 0],
             "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "T": [-0.28, 0, 0]}
    del plain[key]
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(plain) + _alias_bomb(key))
    start = time.perf_counter()
    with pytest.raises(TrackmeterError, match="aliases expand to"):
        load_rig(path)
    assert time.perf_counter() - start < 2.0


def test_a_yaml_value_that_contains_itself_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text("tracker: &a {patch: *a}\n")
    with pytest.raises(TrackmeterError, match="contains itself"):
        read_yaml_mapping(path)


def test_a_name_is_quoted_as_the_command_line_shows_it() -> None:
    """NUL escaped, a byte that is not UTF-8 as ``\\xfe`` (not Python's ``\\udcfe``), and a name
    that holds the text ``\\udcfe`` itself left as it is."""
    from trackmeter.errors import quoted_name

    assert quoted_name("a\udcfe\x00b") == r"'a\xfe\x00b'"
    assert quoted_name("a\\udcfe") == r"'a\\udcfe'"
    assert quoted_name("a\\\udc80") == r"'a\\\x80'"
    assert quoted_name("plain") == repr("plain")
