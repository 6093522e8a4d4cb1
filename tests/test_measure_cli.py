"""``trackmeter measure`` end to end: the JSON contract (DESIGN.md section 6), the table, and
bad input (one line on stderr, exit code 2, no traceback)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from benchmarks.measure import estec_plane
from trackmeter.cli.main import main
from trackmeter.core.matching import REASON_OUTSIDE_IMAGE, MeasureParams, measure_points

REPO = Path(__file__).resolve().parent.parent
RIG = REPO / "config" / "rigs" / "estec_12mm.yaml"
KEYS = ["uv", "ok", "reason", "right_uv", "disparity_px", "xyz_m", "sigma_m", "score"]


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    rig, left, right, truth = estec_plane(seed=5)
    folder = tmp_path_factory.mktemp("pair")
    cv2.imwrite(str(folder / "left.png"), left)
    cv2.imwrite(str(folder / "right.png"), cv2.cvtColor(right, cv2.COLOR_GRAY2BGR))  # colour is converted
    return rig, left, right, truth, folder


def _run(folder: Path, *extra: str, rig: Path = RIG, left: str = "left.png", right: str = "right.png") -> int:
    return main(["measure", "--rig", str(rig), "--left", str(folder / left), "--right", str(folder / right), *extra])


def _one_error_line(capsys: pytest.CaptureFixture[str], *words: str) -> str:
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert "Traceback" not in captured.err
    assert lines[0].startswith("trackmeter measure")
    for word in words:
        assert word in lines[0], lines[0]
    assert captured.out == ""
    return lines[0]


def test_json_is_the_contract_and_agrees_with_the_library_and_the_truth(pair, capsys) -> None:  # type: ignore[no-untyped-def]
    rig, left, right, truth, folder = pair
    ats = [(300.3, 250.6), (-5.0, 3.0), (420.0, 180.25)]
    # DESIGN's `--at U,V [--at U,V ...]`, and several pixels after one --at as well.
    assert _run(folder, "--at", "300.3,250.6", "--at", "420,180.25", "--json") == 0
    repeated = capsys.readouterr().out
    assert _run(folder, "--at", "300.3,250.6", "420,180.25", "--json") == 0
    assert capsys.readouterr().out == repeated and len(json.loads(repeated)) == 2
    assert _run(folder, "--at", "300.3,250.6", "--at=-5,3", "--at", "420,180.25", "--json") == 0
    out = json.loads(capsys.readouterr().out)
    assert isinstance(out, list) and len(out) == 3
    assert all(list(o) == KEYS for o in out)
    assert [o["uv"] for o in out] == [list(a) for a in ats]
    lib = measure_points(rig, left, right, ats, MeasureParams())
    for o, m in zip(out, lib):
        assert o["ok"] == m.ok and o["reason"] == m.reason
    good = [o for o in out if o["ok"]]
    assert len(good) == 2
    for o, at in zip((out[0], out[2]), (ats[0], ats[2])):
        assert o["reason"] is None
        xyz = np.array(o["xyz_m"])
        np.testing.assert_allclose(xyz, truth(np.array([at]))[0], atol=4e-3)
        np.testing.assert_allclose(o["right_uv"], rig.project(xyz)[1][0], atol=1e-3)
        assert 0 < o["sigma_m"][2] < 0.01 and 0.8 <= o["score"] <= 1.0 and o["disparity_px"] > 0
    refused = out[1]
    assert refused["ok"] is False and refused["reason"] == REASON_OUTSIDE_IMAGE
    assert refused["xyz_m"] is None and refused["right_uv"] is None and refused["disparity_px"] is None


def test_twelve_bit_pair_in_sixteen_bit_files_measures_like_the_eight_bit_one(pair, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    """A camera's 12-bit samples stored as they are in 16-bit PNGs (values below 4096) are
    the same pair: the same measurements, not a black image refused everywhere."""
    _, left, right, _, folder = pair
    assert _run(folder, "--at", "300.3,250.6", "--at", "420,180.25", "--json") == 0
    eight = json.loads(capsys.readouterr().out)
    cv2.imwrite(str(tmp_path / "left.png"), left.astype(np.uint16) << 4)
    cv2.imwrite(str(tmp_path / "right.png"), right.astype(np.uint16) << 4 | np.uint16(5))
    assert _run(tmp_path, "--at", "300.3,250.6", "--at", "420,180.25", "--json") == 0
    twelve = json.loads(capsys.readouterr().out)
    assert twelve == eight and all(o["ok"] for o in twelve)


def test_an_underexposed_pair_measures_as_the_normal_one(pair, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    """The same pair at 0.15 of its grey levels (an underexposed camera): measured after the
    exposure gain (config section ``exposure``), as `track` does, within three sigmas of the
    normal pair's figures (the dim pair's quantisation is noise the gain cannot undo); refused
    as textureless without it."""
    _, left, right, _, folder = pair
    ats = ("--at", "300.3,250.6", "--at", "420,180.25", "--json")
    assert _run(folder, *ats) == 0
    normal = json.loads(capsys.readouterr().out)
    for name, image in (("left.png", left), ("right.png", right)):
        cv2.imwrite(str(tmp_path / name), np.rint(image * 0.15).astype(np.uint8))
    assert _run(tmp_path, *ats) == 0
    dim = json.loads(capsys.readouterr().out)
    assert all(o["ok"] for o in dim)
    for o, n in zip(dim, normal):
        np.testing.assert_allclose(o["xyz_m"], n["xyz_m"], atol=3 * max(n["sigma_m"]))
    (tmp_path / "off.yaml").write_text("exposure:\n  reference_grey: 0\n")
    assert _run(tmp_path, *ats, "--config", str(tmp_path / "off.yaml")) == 0
    assert [o["reason"] for o in json.loads(capsys.readouterr().out)] == ["textureless"] * 2


def test_table_and_patch_option(pair, capsys) -> None:  # type: ignore[no-untyped-def]
    *_, folder = pair
    assert _run(folder, "--at", "300.3,250.6", "--at", "1,1", "--patch", "11") == 0
    text = capsys.readouterr().out.splitlines()
    assert text[0].split()[:3] == ["u", "v", "ok"] and len(text) == 3
    assert " yes " in text[1] and "3.4" in text[1]
    assert " no " in text[2] and "patch not inside image" in text[2]


def test_a_pixel_far_off_the_image_takes_its_columns_not_300_digits(pair, capsys) -> None:  # type: ignore[no-untyped-def]
    *_, folder = pair
    assert _run(folder, "--at", "1e308,1e308", "--at", "300.3,250.6") == 0
    text = capsys.readouterr().out.splitlines()
    assert text[1].split()[:3] == ["1e+308", "1e+308", "no"] and len(text[1]) < 200
    assert text[2].startswith("  300.30   250.60  yes ")


def test_help_runs_as_a_console_script() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "trackmeter.cli.main", "measure", "--help"], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0 and "--at" in done.stdout and "xyz_m" in done.stdout


def test_missing_rig(pair, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    *_, folder = pair
    assert _run(folder, "--at", "1,1", rig=tmp_path / "none.yaml") == 2
    _one_error_line(capsys, "none.yaml")


def test_malformed_rig(pair, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    *_, folder = pair
    bad = tmp_path / "bad.yaml"
    bad.write_text("%YAML:1.0\nimage_width: 726\nK1: [1, 2\n")
    assert _run(folder, "--at", "1,1", rig=bad) == 2
    _one_error_line(capsys, "bad.yaml")
    partial = tmp_path / "partial.yaml"
    partial.write_text("%YAML:1.0\n---\nimage_width: 726\nimage_height: 512\n")
    assert _run(folder, "--at", "1,1", rig=partial) == 2
    _one_error_line(capsys, "partial.yaml")


def test_image_of_the_wrong_size(pair, capsys) -> None:  # type: ignore[no-untyped-def]
    *_, left, _, _, folder = pair
    cv2.imwrite(str(folder / "small.png"), left[:, :700])
    assert _run(folder, "--at", "1,1", right="small.png") == 2
    _one_error_line(capsys, "small.png", "700x512", "726x512")


def test_opencv_sample_pair_takes_the_size_of_the_left_image(opencv_sample_rig: Path, shared_data: Path,
                                                             capsys) -> None:  # type: ignore[no-untyped-def]
    """OpenCV's intrinsics.yml/extrinsics.yml carry no image size: measure takes the left image's.
    On OpenCV's own chessboard pair, neighbouring corners come out one square apart."""
    images = shared_data / "stereo_calib_opencv"
    left = cv2.imread(str(images / "left01.jpg"), cv2.IMREAD_GRAYSCALE)
    found, corners = cv2.findChessboardCorners(left, (9, 6))
    assert found
    corners = cv2.cornerSubPix(left, corners, (5, 5), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)).reshape(6, 9, 2)
    ats = [f"--at={u:.3f},{v:.3f}" for u, v in corners.reshape(-1, 2)]
    for rig_file in ("intrinsics.yml", "extrinsics.yml"):
        code = main(["measure", "--rig", str(opencv_sample_rig / rig_file), "--left", str(images / "left01.jpg"),
                     "--right", str(images / "right01.jpg"), *ats, "--json"])
        captured = capsys.readouterr()
        assert code == 0, captured.err
        out = json.loads(captured.out)
        xyz = np.array([o["xyz_m"] if o["ok"] else [np.nan] * 3 for o in out]).reshape(6, 9, 3)
        assert np.isfinite(xyz[..., 0]).sum() >= 40  # most corners; a few are refused as ambiguous
        step = np.linalg.norm(np.diff(xyz, axis=1), axis=2)  # along a row of corners, in squares
        assert np.nanmedian(step) == pytest.approx(1.0, abs=0.01)


def test_non_image_file(pair, capsys) -> None:  # type: ignore[no-untyped-def]
    *_, folder = pair
    (folder / "notes.png").write_text("not an image\n")
    assert _run(folder, "--at", "1,1", left="notes.png") == 2
    _one_error_line(capsys, "notes.png")
    assert _run(folder, "--at", "1,1", left="missing.png") == 2
    _one_error_line(capsys, "missing.png")


def test_a_cut_short_png_is_one_line_on_the_process_stderr(pair, capfd) -> None:  # type: ignore[no-untyped-def]
    """OpenCV's decoder wrote its own [ WARN ...] line to the process's stderr (where capsys
    does not look) before the command's error."""
    *_, folder = pair
    (folder / "cut.png").write_bytes((folder / "left.png").read_bytes()[:3000])
    capfd.readouterr()
    assert _run(folder, "--at", "1,1", left="cut.png") == 2
    err = capfd.readouterr().err
    assert err.splitlines() == [f"trackmeter measure: error: {folder / 'cut.png'}: not an image file OpenCV can decode "
                                "(a PNG file cut short)"]


@pytest.mark.parametrize("at", ["1", "1,2,3", "a,b", "1;2", "", "nan,100", "100,inf", "-inf,1"])
def test_bad_at(pair, capsys, at: str) -> None:  # type: ignore[no-untyped-def]
    *_, folder = pair
    assert _run(folder, f"--at={at}") == 2
    _one_error_line(capsys, "U,V")


def test_bad_patch(pair, capsys) -> None:  # type: ignore[no-untyped-def]
    *_, folder = pair
    assert _run(folder, "--at", "1,1", "--patch", "2") == 2
    _one_error_line(capsys, "--patch")


def test_a_swapped_pair_is_said_to_look_swapped(pair, capsys) -> None:  # type: ignore[no-untyped-def]
    # --left and --right exchanged refused every point as "low score" or "too dark" with no
    # hint of the cause (an outside probe); the pair in order says nothing of it.
    *_, folder = pair
    assert _run(folder, "--at", "300.3,250.6", left="right.png", right="left.png") == 0
    err = capsys.readouterr().err
    assert err.startswith("trackmeter measure: warning: the left and right images look swapped"), err
    assert _run(folder, "--at", "300.3,250.6") == 0
    assert "swapped" not in capsys.readouterr().err


def test_points_beyond_the_range_searched_name_the_range_and_its_setting(pair, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    # The mock-up's plane at 3.5 m (94.5 px of disparity) searched only to 93.5 px: the peak
    # sits on the range's edge. The table's "beyond disparity range" alone does not say which
    # range, nor where to change it.
    *_, folder = pair
    config = tmp_path / "near.yaml"
    config.write_text("measure:\n  max_disparity_px: 93.5\n")
    assert _run(folder, "--at", "310,250", "--config", str(config)) == 0
    captured = capsys.readouterr()
    assert "beyond disparity range" in captured.out
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("trackmeter measure: warning: 1 point beyond the disparity range searched, 0 to 93.5 px on this rig"), lines[0]
    assert "measure.max_disparity_px (93.5 px)" in lines[0] and "--config" in lines[0]
    assert _run(folder, "--at", "310,250") == 0  # the default range: measured, nothing said
    assert capsys.readouterr().err == ""


def test_config_given_twice_layers_both_files_in_order(pair, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    """An outside probe: with ``--config`` twice only the last file was used, the first not even
    read (an unknown key in it passed, exit 0). DESIGN's ``--config`` layers a YAML over the
    defaults; given twice, both are layered, in order."""
    *_, folder = pair
    parabola = tmp_path / "parabola.yaml"
    parabola.write_text("measure:\n  subpixel: parabola\n")
    small = tmp_path / "small.yaml"
    small.write_text("measure:\n  patch_size: 5\n")
    both = tmp_path / "both.yaml"
    both.write_text("measure:\n  subpixel: parabola\n  patch_size: 5\n")
    ats = ("--at", "310,250", "--at", "300,250", "--at", "200,200", "--json")

    def measured(*configs: Path) -> list:
        assert _run(folder, *ats, *[a for c in configs for a in ("--config", str(c))]) == 0
        return json.loads(capsys.readouterr().out)

    layered = measured(parabola, small)
    assert layered == measured(both)
    assert layered != measured(small) and layered != measured(parabola)  # each file counted
    misspelt = tmp_path / "misspelt.yaml"
    misspelt.write_text("measure:\n  patch_sizee: 9\n")
    assert _run(folder, "--at", "300,250", "--config", str(misspelt), "--config", str(small)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "misspelt.yaml: unknown key 'measure.patch_sizee'" in err[0], err


def test_a_rig_with_its_cameras_swapped_is_refused_naming_the_file(pair, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    """'the right camera lies left of the left one ...: exchange the left and right cameras'
    did not say which rig file (an outside probe): a command may be given several files."""
    import dataclasses

    from trackmeter.data.rigfile import save_rig

    rig = pair[0]
    swapped = save_rig(dataclasses.replace(rig, left=rig.right, right=rig.left, R=rig.R.T, T=-rig.R.T @ rig.T),
                       tmp_path / "swapped.yaml")
    assert _run(pair[4], "--at", "300,200", rig=swapped) == 2
    line = _one_error_line(capsys, "lies left of the left one")
    assert f"error: {swapped}: " in line


def test_the_range_searched_on_a_pair_with_principal_points_apart_is_counted_as_its_settings_are(
        tmp_path: Path, shared_data, capsys) -> None:  # type: ignore[no-untyped-def]
    """On a pair rectified already whose principal points lie apart (Tsukuba's right image moved
    12 px right, its principal point with it), the warning printed the range as rectified
    disparities, "-9--2 px", beside the settings that asked for 3 to 10 (an outside probe)."""
    from benchmarks.measure import identity_rig, load_tsukuba, principal_points_apart
    from trackmeter.data.rigfile import save_rig

    left, right, _ = load_tsukuba(shared_data / "middlebury_tsukuba")
    moved_rig, moved = principal_points_apart(identity_rig(384, 288, focal_px=400.0), right, 12)
    cv2.imwrite(str(tmp_path / "left.png"), left)
    cv2.imwrite(str(tmp_path / "right.png"), moved)
    rig = save_rig(moved_rig, tmp_path / "rig.yaml")
    config = tmp_path / "narrow.yaml"
    config.write_text("measure:\n  min_disparity_px: 3\n  max_disparity_px: 4\n")
    # (100, 100) lies 5 px apart in the pair as given (Middlebury's truth): beyond 3 to 4.
    assert _run(tmp_path, "--at", "100,100", "--config", str(config), rig=rig) == 0
    captured = capsys.readouterr()
    assert "beyond disparity range" in captured.out
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert "searched, 3 to 4 px past a point at infinity's (-12 px: the principal points apart)" in lines[0], lines[0]
