"""Rig files (trackmeter.data.rigfile): our FileStorage YAML, OpenCV's stereo sample pair, presets."""

from __future__ import annotations

import re
import subprocess
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from trackmeter.core.stereo import Camera, StereoRig
from trackmeter.data.rigfile import load_rig, save_rig
from trackmeter.errors import TrackmeterError
from trackmeter.paths import RIGS_DIR


def _rig(n_dist: int = 5, rms: float | None = 0.123) -> StereoRig:
    rng = np.random.default_rng(0)
    K1 = np.array([[801.5, 0, 330.25], [0, 799.75, 241.5], [0, 0, 1]])
    K2 = np.array([[805.0, 0, 318.0], [0, 804.0, 236.0], [0, 0, 1]])
    R = Rotation.from_rotvec([0.01, -0.02, 0.005]).as_matrix()
    return StereoRig(
        Camera(640, 480, K1, rng.normal(0, 0.05, n_dist)),
        Camera(640, 480, K2, rng.normal(0, 0.05, n_dist)),
        R,
        np.array([-0.2801, 0.0012, -0.0034]),
        rms_px=rms,
    )


@pytest.mark.parametrize("n_dist", [4, 5, 8, 14])
def test_save_load_round_trip(tmp_path: Path, n_dist: int) -> None:
    rig = _rig(n_dist)
    path = save_rig(rig, tmp_path / "deep" / "rig.yaml")
    back = load_rig(path)
    for a, b in ((rig.left, back.left), (rig.right, back.right)):
        assert (a.width, a.height) == (b.width, b.height)
        np.testing.assert_array_equal(a.K, b.K)
        np.testing.assert_array_equal(a.dist, b.dist)
    np.testing.assert_array_equal(rig.R, back.R)
    np.testing.assert_array_equal(rig.T, back.T)
    assert back.rms_px == rig.rms_px
    assert sorted(p.name for p in path.parent.iterdir()) == ["rig.yaml"]  # no temp file left


@pytest.mark.parametrize("name, head", [("rig.xml", "<?xml"), ("rig.json", "{"), ("rig.yml", "%YAML"),
                                        ("rig.XML", "<?xml"), ("rig.txt", "%YAML")])
def test_a_rig_file_is_written_in_the_format_its_name_says(tmp_path: Path, name: str, head: str) -> None:
    """`calibrate --out rig.xml` (or .json) wrote YAML under that name, which OpenCV reads
    (it looks at the text) but no XML or JSON tool does (an outside probe). OpenCV FileStorage
    writes each by its extension; a name without one of them stays YAML."""
    rig = _rig()
    path = save_rig(rig, tmp_path / name, {"std_baseline": 0.001})
    assert path.read_text().lstrip().startswith(head)
    back = load_rig(path)
    np.testing.assert_array_equal(back.left.K, rig.left.K)
    np.testing.assert_array_equal(back.T, rig.T)
    if name.lower().endswith(".json"):
        import json

        assert json.loads(path.read_text())["std_baseline"] == 0.001


def test_round_trip_without_rms_and_with_extras(tmp_path: Path) -> None:
    rig = _rig(rms=None)
    path = save_rig(rig, tmp_path / "rig.yaml", {"E": np.eye(3), "std_baseline": 0.001})
    assert load_rig(path).rms_px is None
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        np.testing.assert_array_equal(fs.getNode("E").mat(), np.eye(3))
        assert fs.getNode("std_baseline").real() == 0.001
        # the keys DESIGN.md names, readable by any OpenCV program
        for key in ("image_width", "image_height", "K1", "D1", "K2", "D2", "R", "T"):
            assert not fs.getNode(key).empty(), key
        assert fs.getNode("T").mat().shape == (3, 1)
    finally:
        fs.release()


def test_failed_save_leaves_old_file_intact(tmp_path: Path) -> None:
    path = save_rig(_rig(), tmp_path / "rig.yaml")
    before = path.read_bytes()
    with pytest.raises(Exception):
        save_rig(_rig(), path, {"bad": "not a number"})  # type: ignore[dict-item]
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig.yaml"]


# --------------------------------------------------------------------------- OpenCV's sample pair


def _write_opencv_pair(folder: Path, rig: StereoRig, intrinsics: str = "intrinsics.yml", extrinsics: str = "extrinsics.yml") -> None:
    """Write intrinsics.yml / extrinsics.yml as OpenCV's samples/cpp/stereo_calib.cpp does:
    ``fs << "M1" << cameraMatrix[0] << "D1" << distCoeffs[0] << "M2" << ... << "D2" << ...``
    then ``fs << "R" << R << "T" << T << "R1" << R1 << "R2" << R2 << "P1" << P1 << "P2" << P2 << "Q" << Q``.
    """
    R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(
        rig.left.K, rig.left.dist, rig.right.K, rig.right.dist, rig.image_size, rig.R, rig.T.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=1
    )
    fs = cv2.FileStorage(str(folder / intrinsics), cv2.FILE_STORAGE_WRITE)
    fs.write("M1", rig.left.K)
    fs.write("D1", rig.left.dist.reshape(1, -1))
    fs.write("M2", rig.right.K)
    fs.write("D2", rig.right.dist.reshape(1, -1))
    fs.release()
    fs = cv2.FileStorage(str(folder / extrinsics), cv2.FILE_STORAGE_WRITE)
    for key, value in (("R", rig.R), ("T", rig.T.reshape(3, 1)), ("R1", R1), ("R2", R2), ("P1", P1), ("P2", P2), ("Q", Q)):
        fs.write(key, value)
    fs.release()


def test_a_save_on_a_full_disk_raises_and_leaves_the_old_file(tmp_path: Path, full_disk) -> None:  # type: ignore[no-untyped-def]
    path = save_rig(_rig(), tmp_path / "rig.yaml")
    before = path.read_bytes()
    full_disk(100)
    with pytest.raises(TrackmeterError, match="rig.yaml: cannot write: No space left on device"):
        save_rig(_rig(rms=0.5), path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig.yaml"]


@pytest.mark.parametrize("which", ["intrinsics.yml", "extrinsics.yml"])
def test_reads_opencv_stereo_sample_pair(tmp_path: Path, which: str) -> None:
    rig = _rig(14, rms=None)  # stereo_calib.cpp's rational model: OpenCV writes 14 coefficients
    _write_opencv_pair(tmp_path, rig)
    back = load_rig(tmp_path / which, image_size=(640, 480))
    np.testing.assert_array_equal(back.left.K, rig.left.K)
    np.testing.assert_array_equal(back.right.dist, rig.right.dist)
    np.testing.assert_array_equal(back.R, rig.R)
    np.testing.assert_array_equal(back.T, rig.T)
    assert back.image_size == (640, 480)


@pytest.mark.parametrize(("intrinsics", "extrinsics"), [("intrinsics.xml", "extrinsics.xml"), ("intrinsics.xml", "extrinsics.yml"),
                                                     ("intrinsics.yaml", "extrinsics.xml")])
def test_the_opencv_pair_is_found_whatever_suffixes_opencv_wrote(tmp_path: Path, intrinsics: str, extrinsics: str) -> None:
    rig = _rig(5, rms=None)
    _write_opencv_pair(tmp_path, rig, intrinsics, extrinsics)
    for given in (intrinsics, extrinsics):
        back = load_rig(tmp_path / given, image_size=(640, 480))
        np.testing.assert_array_equal(back.left.K, rig.left.K)
        np.testing.assert_array_equal(back.T, rig.T)


def test_opencv_pair_needs_image_size_and_both_files(tmp_path: Path) -> None:
    _write_opencv_pair(tmp_path, _rig())
    with pytest.raises(TrackmeterError, match="image size"):
        load_rig(tmp_path / "intrinsics.yml")
    (tmp_path / "extrinsics.yml").unlink()
    with pytest.raises(TrackmeterError, match=r"intrinsics.yml: OpenCV's intrinsics file needs its extrinsics file "
                                              r"beside it \(.*extrinsics.yml: no such file\)"):
        load_rig(tmp_path / "intrinsics.yml", image_size=(640, 480))


def test_an_opencv_pair_for_another_image_size_is_refused_by_its_principal_point(tmp_path: Path) -> None:
    """The pair carries no size: frames half the calibrated size put the principal point
    (330, 241) outside them, and every point was refused as "patch not inside image"."""
    _write_opencv_pair(tmp_path, _rig())
    with pytest.raises(TrackmeterError, match=r"principal point \(330\.2, 241\.5\) lies outside the 320x240 px frames: "
                                              r"calibrated for another image size"):
        load_rig(tmp_path / "intrinsics.yml", image_size=(320, 240))
    assert load_rig(tmp_path / "intrinsics.yml", image_size=(640, 480)).image_size == (640, 480)


def test_an_opencv_pair_whose_principal_point_is_near_the_frames_edge_is_warned_about(tmp_path: Path) -> None:
    """A 640x480 calibration on 384x288 frames (Tsukuba; an outside probe): the principal point
    (330, 241) lies inside them, so it passed, and `measure` refused every point saying the
    images looked swapped. The pair carries no size, so the likely cause is said at loading."""
    _write_opencv_pair(tmp_path, _rig())
    with pytest.warns(UserWarning, match=r"intrinsics.yml: the principal point \(330\.2, 241\.5\) lies 36% of the "
                                         r"384x288 px frames from their centre: calibrated for another image size\?") as said:
        load_rig(tmp_path / "intrinsics.yml", image_size=(384, 288))
    assert said[0].filename == __file__
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_rig(tmp_path / "intrinsics.yml", image_size=(640, 480)).image_size == (640, 480)


def test_a_rig_yaml_without_its_size_is_checked_against_the_frames_as_opencv_s_pair_is(tmp_path: Path) -> None:
    """A rig.yaml without image_width/image_height takes the frames' size, as OpenCV's pair
    does, but its principal point was never checked: on frames half its size `track` said
    only that --auto found no candidate, while the same rig as intrinsics.yml was refused."""
    path = save_rig(_rig(), tmp_path / "rig.yaml")
    text = "\n".join(line for line in path.read_text().splitlines() if not line.startswith("image_"))
    path.write_text(text + "\n")
    with pytest.raises(TrackmeterError, match=r"rig.yaml: the principal point \(330\.2, 241\.5\) lies outside the "
                                              r"320x240 px frames: calibrated for another image size"):
        load_rig(path, image_size=(320, 240))
    with pytest.warns(UserWarning, match=r"rig.yaml: the principal point \(330\.2, 241\.5\) lies 36% of the 384x288 "
                                         r"px frames from their centre: calibrated for another image size\? \(the file "
                                         r"has no image_width/image_height; the frames' is taken\)") as said:
        load_rig(path, image_size=(384, 288))
    assert said[0].filename == __file__  # where load_rig was called, not inside it (a code review)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_rig(path, image_size=(640, 480)).image_size == (640, 480)
        # A file that gives its size is its own word: its frames are compared with it elsewhere.
        assert load_rig(save_rig(_rig(), tmp_path / "sized.yaml"), image_size=(320, 240)).image_size == (640, 480)


# --------------------------------------------------------------------------- presets


PAPER_LENS_MM = {"estec_12mm": 12.0, "estec_8mm": 8.0, "estec_4p8mm": 4.8}


@pytest.mark.parametrize("name", sorted(PAPER_LENS_MM))
def test_presets_load_with_the_papers_geometry(name: str) -> None:
    rig = load_rig(RIGS_DIR / f"{name}.yaml")
    assert rig.image_size == (726, 512)
    assert rig.baseline_m == pytest.approx(0.280, abs=1e-9)
    assert rig.T[0] < 0  # right camera at +x of the left one
    # the same sensor behind each lens: focal length in px scales with the lens's mm
    assert rig.left.focal_px == pytest.approx(1152.0 * PAPER_LENS_MM[name] / 12.0, rel=1e-9)
    assert rig.right.focal_px == pytest.approx(rig.left.focal_px)
    # rectifies to usable geometry
    assert rig.rectification.baseline_m == pytest.approx(0.280, rel=1e-9)


def test_12mm_preset_has_35_by_25_degree_field_of_view() -> None:
    rig = load_rig(RIGS_DIR / "estec_12mm.yaml")
    fovx, fovy, *_ = cv2.calibrationMatrixValues(rig.left.K, rig.image_size, 0.0, 0.0)
    assert fovx == pytest.approx(35.0, abs=0.5)
    assert fovy == pytest.approx(25.0, abs=0.5)
    # closed form 2 atan(w / 2f) (OpenCV splits the width at cx, half a pixel off centre)
    assert 2 * np.degrees(np.arctan(726 / 2 / 1152.0)) == pytest.approx(fovx, abs=1e-3)


def test_wider_lenses_have_wider_fields() -> None:
    fov = {
        name: cv2.calibrationMatrixValues(load_rig(RIGS_DIR / f"{name}.yaml").left.K, (726, 512), 0.0, 0.0)[0]
        for name in PAPER_LENS_MM
    }
    assert fov["estec_12mm"] < fov["estec_8mm"] < fov["estec_4p8mm"]
    assert fov["estec_8mm"] == pytest.approx(2 * np.degrees(np.arctan(363 / 768)), abs=1e-3)


def test_files_written_whole_get_ordinary_permissions(tmp_path, estec_rig):
    """Atomic writes go through mkstemp (mode 0600); the result must be a normal file (0666 & ~umask)."""
    import os

    from trackmeter.data.atomic import write_text_atomic
    from trackmeter.data.rigfile import save_rig

    mask = os.umask(0o022)
    try:
        save_rig(estec_rig, tmp_path / "rig.yaml")
        write_text_atomic(tmp_path / "a.txt", "x\n")
    finally:
        os.umask(mask)
    for name in ("rig.yaml", "a.txt"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o644
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "rig.yaml"]  # no temporary left


def test_a_rig_with_its_cameras_swapped_loads_silently_and_is_refused_where_it_is_used(tmp_path: Path) -> None:
    # Measuring and tracking refuse a swapped rig with the remedy (check_side_by_side); a
    # warning at load as well said the same thing twice on every command.
    import dataclasses
    import warnings

    from trackmeter.core.stereo import check_side_by_side

    rig = _rig()
    swapped = dataclasses.replace(rig, left=rig.right, right=rig.left, R=rig.R.T, T=-rig.R.T @ rig.T)
    vertical = dataclasses.replace(rig, T=np.array([0.001, -0.25, 0.0]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_rig(save_rig(rig, tmp_path / "rig.yaml"))
        load_rig(save_rig(vertical, tmp_path / "vertical.yaml"))
        for preset in sorted(RIGS_DIR.glob("*.yaml")):
            load_rig(preset)
        loaded = load_rig(save_rig(swapped, tmp_path / "swapped.yaml"))
    with pytest.raises(TrackmeterError, match="right camera lies left of the left one.*exchange the left and right"):
        check_side_by_side(loaded)


def test_a_rig_with_its_baseline_in_millimetres_is_warned_about(tmp_path: Path) -> None:
    import dataclasses
    import warnings

    rig = _rig()
    in_mm = dataclasses.replace(rig, T=rig.T * 1000.0)
    with pytest.warns(UserWarning, match=r"baseline .* m \(\|T\|\): T must be in metres.*1000x too large"):
        load_rig(save_rig(in_mm, tmp_path / "mm.yaml"))
    wide = dataclasses.replace(rig, T=rig.T / np.linalg.norm(rig.T) * 9.0)  # wide, but metres
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_rig(save_rig(wide, tmp_path / "wide.yaml"))


@pytest.mark.parametrize("header", ["%YAML:1.0\n---\n", ""])
def test_plain_yaml_lists_are_matrices_too(tmp_path: Path, header: str) -> None:
    """A rig written by hand or by another tool as plain YAML lists (nested rows or flat) reads
    as the same rig as the ``!!opencv-matrix`` form; a key that is no matrix at all is one
    clear error, not OpenCV's."""
    rig = _rig()
    K1, K2 = rig.left.K, rig.right.K

    def flat(a: np.ndarray) -> str:
        return "[" + ", ".join(repr(float(x)) for x in np.ravel(a)) + "]"

    def rows(a: np.ndarray) -> str:
        return "[" + ", ".join(flat(r) for r in a) + "]"

    text = (f"{header}image_width: 640\nimage_height: 480\nK1: {rows(K1)}\nD1: {flat(rig.left.dist)}\n"
            f"K2: {flat(K2)}\nD2: {rows(rig.right.dist.reshape(1, -1))}\nR: {rows(rig.R)}\nT: {flat(rig.T)}\n")
    path = tmp_path / "plain.yaml"
    path.write_text(text)
    got = load_rig(path)
    np.testing.assert_array_equal(got.left.K, K1)
    np.testing.assert_array_equal(got.right.K, K2)
    np.testing.assert_array_equal(got.left.dist, rig.left.dist)
    np.testing.assert_array_equal(got.right.dist, rig.right.dist)
    np.testing.assert_allclose(got.R, rig.R, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(got.T, rig.T)
    path.write_text(text.replace(f"D1: {flat(rig.left.dist)}", "D1: []"))  # no distortion, as hand-written
    np.testing.assert_array_equal(load_rig(path).left.dist, np.zeros(5))
    for bad, words in (("K1: hello", "'K1' is not a matrix"), ("K1: [[1, 2], [3]]", "'K1' is not a matrix"),
                       ("K1: {a: 1}", "'K1' is not a matrix")):
        path.write_text(text.replace(f"K1: {rows(K1)}", bad))
        with pytest.raises(TrackmeterError, match=words):
            load_rig(path)


def test_a_folder_given_as_the_rig_is_named_as_one(tmp_path: Path) -> None:
    with pytest.raises(TrackmeterError, match="a folder, not a rig file"):
        load_rig(tmp_path)
    with pytest.raises(TrackmeterError, match="no such rig file"):
        load_rig(tmp_path / "missing.yaml")


def test_a_preset_is_named_as_scenarios_are(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)  # no file of that name here
    by_name = load_rig("estec_12mm")
    by_path = load_rig(RIGS_DIR / "estec_12mm.yaml")
    np.testing.assert_array_equal(by_name.left.K, by_path.left.K)
    np.testing.assert_array_equal(by_name.T, by_path.T)
    assert load_rig("estec_12mm.yaml").image_size == by_path.image_size
    (tmp_path / "estec_12mm").write_text("not a rig")  # a file of that name wins over the preset
    with pytest.raises(TrackmeterError, match="not an OpenCV FileStorage"):
        load_rig("estec_12mm")
    with pytest.raises(TrackmeterError, match=r"estec_21mm: no such rig file \(a file, or a preset: estec_12mm, "):
        load_rig("estec_21mm")


def test_an_empty_opencv_matrix_is_no_distortion(tmp_path: Path) -> None:
    """``cv2.FileStorage`` writes an empty array as an ``!!opencv-matrix`` of 0 rows: no
    distortion, as a hand-written ``D1: []`` is."""
    rig = _rig()
    path = tmp_path / "empty_d.yaml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for key, value in (("image_width", 640), ("image_height", 480), ("K1", rig.left.K), ("D1", np.zeros((0, 0))),
                       ("K2", rig.right.K), ("D2", rig.right.dist), ("R", rig.R), ("T", rig.T)):
        fs.write(key, value)
    fs.release()
    assert "rows: 0" in path.read_text()
    got = load_rig(path)
    np.testing.assert_array_equal(got.left.dist, np.zeros(5))
    np.testing.assert_array_equal(got.right.dist, rig.right.dist)


def _kalibr_camchain(rig: StereoRig, model: str = "radtan") -> str:
    """Kalibr's ``camchain.yaml`` of ``rig``: ``T_cn_cnm1`` maps cam0 points into cam1."""
    def cam(c: Camera) -> str:
        K = c.K
        return (f"  camera_model: pinhole\n  distortion_coeffs: {[float(x) for x in c.dist[:4]]}\n"
                f"  distortion_model: {model}\n  intrinsics: {[float(K[i, j]) for i, j in ((0, 0), (1, 1), (0, 2), (1, 2))]}\n"
                f"  resolution: [{c.width}, {c.height}]\n  rostopic: /cam/image_raw\n")
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rig.R, rig.T
    rows = "".join(f"  - {[float(x) for x in r]}\n" for r in T)
    return f"cam0:\n  cam_overlaps: [1]\n{cam(rig.left)}cam1:\n  T_cn_cnm1:\n{rows}  cam_overlaps: [0]\n{cam(rig.right)}"


def test_a_kalibr_camchain_reads_as_the_same_rig(tmp_path: Path) -> None:
    """Kalibr's stereo calibration (pinhole, radial-tangential ``[k1 k2 p1 p2]``, OpenCV's
    model and order) is the same rig: ``R, T`` are ``T_cn_cnm1``'s rotation and translation."""
    rig = _rig(n_dist=4)
    path = tmp_path / "camchain-stereo.yaml"
    path.write_text(_kalibr_camchain(rig))
    got = load_rig(path)
    assert got.image_size == rig.image_size
    for a, b in ((got.left, rig.left), (got.right, rig.right)):
        np.testing.assert_array_equal(a.K, b.K)
        np.testing.assert_array_equal(a.dist[:4], b.dist)
    np.testing.assert_array_equal(got.R, rig.R)
    np.testing.assert_array_equal(got.T, rig.T)
    path.write_text(_kalibr_camchain(rig, model="equidistant"))
    with pytest.raises(TrackmeterError, match="Kalibr camera model pinhole/equidistant is not supported"):
        load_rig(path)
    path.write_text(_kalibr_camchain(rig).split("cam1:")[0])
    with pytest.raises(TrackmeterError, match="Kalibr camchain needs cam0 and cam1"):
        load_rig(path)


@pytest.mark.parametrize("value", [".nan", ".inf", "-.inf", "726.5", "abc", "[726]"])
def test_an_image_size_that_is_no_whole_number_is_refused_by_its_key(tmp_path: Path, value: str) -> None:
    """``image_width: .nan`` raised Python's ValueError (a traceback from the command line),
    ``.inf`` an OverflowError; 726.5 was cut to 726 and a string was ignored, the size then
    taken from the frames without a word."""
    path = save_rig(_rig(), tmp_path / "rig.yaml")
    text = path.read_text()
    assert "image_width: 640\n" in text
    path.write_text(text.replace("image_width: 640\n", f"image_width: {value}\n"))
    for size in (None, (640, 480)):
        with pytest.raises(TrackmeterError, match=r"rig\.yaml: key 'image_width' must be a whole number of pixels"):
            load_rig(path, image_size=size)


@pytest.mark.parametrize("value", ["true", "false", "0", "3"])
def test_an_image_size_too_small_for_any_camera_is_refused_with_the_yaml_hint(tmp_path: Path, value: str) -> None:
    """OpenCV's parser reads ``image_width: true`` as 1 (and ``false`` as 0): the rig loaded as a
    1 px wide camera and only a confusing size mismatch with the frames said anything was wrong."""
    path = save_rig(_rig(), tmp_path / "rig.yaml")
    path.write_text(path.read_text().replace("image_width: 640\n", f"image_width: {value}\n"))
    with pytest.raises(TrackmeterError, match=r"rig\.yaml: key 'image_width' must be at least 16 px, got \d .*true/false"):
        load_rig(path)


def test_r_written_as_a_rotation_vector_reads_as_its_matrix(tmp_path: Path) -> None:
    """OpenCV's stereo functions take R as a 3x3 matrix or a rotation vector (Rodrigues); a rig
    written by another tool with the vector reads as the same rig."""
    rig = _rig()
    path = save_rig(rig, tmp_path / "rig.yaml")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    keys = {k: fs.getNode(k).mat() for k in ("K1", "D1", "K2", "D2", "T")}
    fs.release()
    out = cv2.FileStorage(str(tmp_path / "rotvec.yaml"), cv2.FILE_STORAGE_WRITE)
    out.write("image_width", 640)
    out.write("image_height", 480)
    for k, v in keys.items():
        out.write(k, v)
    out.write("R", cv2.Rodrigues(rig.R)[0])  # (3, 1)
    out.release()
    loaded = load_rig(tmp_path / "rotvec.yaml")
    np.testing.assert_allclose(loaded.R, rig.R, atol=1e-12)
    np.testing.assert_allclose(loaded.R, Rotation.from_rotvec([0.01, -0.02, 0.005]).as_matrix(), atol=1e-12)


def test_a_k_whose_last_row_is_not_0_0_1_is_refused(tmp_path: Path) -> None:
    """OpenCV reads fx, fy, cx, cy of K and ignores its last row: a K scaled as a whole (last row
    [0 0 2]) was taken as the unscaled one without a word."""
    path = save_rig(_rig(), tmp_path / "rig.yaml")
    src = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    out = cv2.FileStorage(str(tmp_path / "scaled.yaml"), cv2.FILE_STORAGE_WRITE)
    out.write("image_width", 640)
    out.write("image_height", 480)
    for k in ("D1", "K2", "D2", "R", "T"):
        out.write(k, src.getNode(k).mat())
    scaled = 2.0 * src.getNode("K1").mat()
    out.write("K1", scaled)
    src.release()
    out.release()
    with pytest.raises(TrackmeterError, match=r"scaled\.yaml: K1's last row must be \[0, 0, 1\], got \[0\., 0\., 2\.\]"):
        load_rig(tmp_path / "scaled.yaml")
    with pytest.raises(TrackmeterError, match="K's last row must be"):
        Camera(640, 480, scaled)


def test_a_k_that_is_no_camera_matrix_or_of_another_image_is_refused(tmp_path: Path) -> None:
    # An element below the diagonal (OpenCV ignores it) and a principal point 50 images to the
    # right were read without a word; `measure` then refused every point as lying in the border
    # the rectification crops.
    K = np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]])
    lower = K.copy()
    lower[1, 0] = 5.0
    with pytest.raises(TrackmeterError, match=r"K\[1\]\[0\] must be 0 .* got 5"):
        Camera(640, 480, lower)
    far = K.copy()
    far[0, 2] = 36250.0
    with pytest.raises(TrackmeterError, match=r"principal point \(36250, 240\) lies more than an image away from the "
                                              r"640x480 image"):
        Camera(640, 480, far)
    off_centre = K.copy()
    off_centre[:2, 2] = (-200.0, 700.0)  # an off-centre crop's principal point, outside but near: read
    assert Camera(640, 480, off_centre).K[0, 2] == -200.0
    rig = _rig()
    path = save_rig(rig, tmp_path / "rig.yaml")
    path.write_text(path.read_text().replace("image_width: 640\n", "image_width: 64\n"))
    with pytest.raises(TrackmeterError, match=r"rig\.yaml: .*principal point .* 64x480 image"):
        load_rig(path)


def test_an_image_size_written_as_a_whole_float_reads(tmp_path: Path) -> None:
    path = save_rig(_rig(), tmp_path / "rig.yaml")
    path.write_text(path.read_text().replace("image_width: 640\n", "image_width: 640.\n"))
    assert load_rig(path).image_size == (640, 480)


@pytest.mark.parametrize("edit, words", [
    (("resolution: [640, 480]", "resolution: [.inf, 480]"), "cam0: Kalibr 'resolution' must be two whole numbers of pixels"),
    (("resolution: [640, 480]", "resolution: [640.5, 480]"), "cam0: Kalibr 'resolution' must be two whole numbers of pixels"),
    (("resolution: [640, 480]", "resolution: [640]"), "cam0: Kalibr 'resolution' must be two whole numbers of pixels"),
    (("  - [0.0, 0.0, 0.0, 1.0]\n", "  - [0.0, 0.0, 1.0]\n"), "'T_cn_cnm1' must be a 4x4 matrix"),
    (("-0.2801", "1e400"), "camchain-stereo.yaml: .*T has non-finite values"),
])
def test_a_malformed_kalibr_camchain_is_one_error_naming_the_file(tmp_path: Path, edit: tuple[str, str],
                                                                   words: str) -> None:
    """A resolution of .inf raised Python's OverflowError (a traceback from the command line),
    640.5 was cut to 640, a T_cn_cnm1 row too short gave numpy's 'inhomogeneous shape' text,
    and a non-finite T was refused without the file's name."""
    path = tmp_path / "camchain-stereo.yaml"
    text = _kalibr_camchain(_rig(n_dist=4))
    assert edit[0] in text
    path.write_text(text.replace(edit[0], edit[1], 1))
    with pytest.raises(TrackmeterError, match=words) as info:
        load_rig(path)
    assert str(info.value).startswith(str(path))


@pytest.mark.parametrize("form", ["opencv", "plain"])
def test_a_rig_file_saved_with_a_byte_order_mark_reads(tmp_path: Path, form: str) -> None:
    """A rig file saved by a Windows editor starts with a UTF-8 byte order mark: OpenCV's
    parser then said 'not an OpenCV FileStorage file' (data.csv, TUM, model and config files
    with one read)."""
    rig = _rig()
    path = save_rig(rig, tmp_path / "rig.yaml")
    text = path.read_text()
    if form == "plain":
        text = "\n".join(line for line in text.splitlines() if not line.startswith(("%", "---")))
    path.write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode())
    back = load_rig(path)
    np.testing.assert_array_equal(back.left.K, rig.left.K)
    np.testing.assert_array_equal(back.T, rig.T)
    assert back.image_size == rig.image_size


def test_a_plain_yaml_rig_in_pyyamls_own_block_style_reads(tmp_path: Path) -> None:
    """``yaml.safe_dump`` of a rig's numbers writes nested lists as zero-indented ``- - x``
    blocks, which OpenCV's parser refuses: the file is plain YAML all the same and reads as
    the same rig (README: "plain YAML lists are read too")."""
    import yaml

    rig = _rig()
    data = {"image_width": 640, "image_height": 480, "K1": rig.left.K.tolist(), "D1": rig.left.dist.tolist(),
            "K2": rig.right.K.tolist(), "D2": rig.right.dist.tolist(), "R": rig.R.tolist(), "T": rig.T.tolist()}
    path = tmp_path / "block.yaml"
    path.write_text(yaml.safe_dump(data))
    assert "- - " in path.read_text()  # the form OpenCV refuses
    got = load_rig(path)
    np.testing.assert_array_equal(got.left.K, rig.left.K)
    np.testing.assert_array_equal(got.right.dist, rig.right.dist)
    np.testing.assert_array_equal(got.R, rig.R)
    np.testing.assert_array_equal(got.T, rig.T)
    assert got.image_size == (640, 480)
    path.write_text("K1:\n- - 1\n  - oops: [\n")  # neither parser reads it: still one clear line
    with pytest.raises(TrackmeterError, match="not an OpenCV FileStorage file"):
        load_rig(path)


def test_one_file_holding_opencvs_intrinsics_and_extrinsics_reads_alone(tmp_path: Path) -> None:
    """``M1 D1 M2 D2`` and ``R T`` written into one file (with or without the image size) need
    no partner file; its own size goes before the frames' (a mismatch is then refused where
    frames meet the rig)."""
    rig = _rig(5, rms=None)
    path = tmp_path / "rig.yaml"
    for with_size in (True, False):
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
        if with_size:
            fs.write("image_width", 640)
            fs.write("image_height", 480)
        for key, value in (("M1", rig.left.K), ("D1", rig.left.dist.reshape(1, -1)), ("M2", rig.right.K),
                           ("D2", rig.right.dist.reshape(1, -1)), ("R", rig.R), ("T", rig.T.reshape(3, 1))):
            fs.write(key, value)
        fs.release()
        got = load_rig(path, image_size=(320, 240)) if with_size else load_rig(path, image_size=(640, 480))
        np.testing.assert_array_equal(got.left.K, rig.left.K)
        np.testing.assert_array_equal(got.right.K, rig.right.K)
        np.testing.assert_array_equal(got.T, rig.T)
        assert got.image_size == (640, 480)
    with pytest.raises(TrackmeterError, match="no image size"):
        load_rig(path)


@pytest.mark.parametrize("text", ["- 1\n- 2\n", "%YAML:1.0\n---\n- 3\n", "[1, 2]\n"])
def test_a_rig_file_that_is_a_list_is_refused_in_one_line(tmp_path: Path, text: str) -> None:
    # Every key lookup on a list asserted inside OpenCV: a 21-line cv2.error traceback from
    # measure, track, analyze and console (an outside probe); a scalar was already refused.
    path = tmp_path / "rig.yaml"
    path.write_text(text)
    with pytest.raises(TrackmeterError, match="rig.yaml: not (a mapping of keys|an OpenCV FileStorage file)"):
        load_rig(path)


def test_the_plain_yaml_rig_of_the_presets_readme_reads_and_measures_tsukuba(tmp_path: Path, shared_data: Path) -> None:
    """config/rigs/README.md shows a hand-written plain-YAML rig: it must read as written, and
    its Tsukuba point measure the disparity the README quotes and the ground truth gives
    (disp_gt.pgm: value / 16, integer-valued)."""
    import re

    from trackmeter.core.matching import MeasureParams, measure_points
    from trackmeter.data.images import read_grey_pair

    text = (RIGS_DIR / "README.md").read_text(encoding="utf-8")
    block = re.search(r"```yaml\n(.*?)```", text, re.S)
    quoted = re.search(r"--at 150,150` then measures a point\s+([\d.]+) px of disparity \(([\d.]+) m\)", text)
    assert block is not None and quoted is not None
    (tmp_path / "tsukuba.yaml").write_text(block.group(1))
    rig = load_rig(tmp_path / "tsukuba.yaml")
    folder = shared_data / "middlebury_tsukuba"
    left, right = read_grey_pair(folder / "img_left.png", folder / "img_right.png")
    m = measure_points(rig, left, right, np.array([[150.0, 150.0]]), MeasureParams())[0]
    assert m.ok
    disparity = m.disparity_px
    assert disparity == pytest.approx(float(quoted.group(1)), abs=0.05)
    assert m.xyz_m[2] == pytest.approx(615.0 * 0.1 / disparity) == pytest.approx(float(quoted.group(2)), abs=0.005)
    truth = cv2.imread(str(folder / "disp_gt.pgm"), cv2.IMREAD_UNCHANGED)[150, 150] / 16.0
    assert abs(disparity - truth) < 1.0


def test_a_block_style_rig_with_a_nan_says_which_key(tmp_path: Path) -> None:
    # yaml.safe_dump's block lists with a .nan in T: "not an OpenCV FileStorage file", where the
    # flow style [.nan, 0, 0] said "T has non-finite values" (an outside probe).
    import yaml

    rig = _rig()
    data = {"image_width": 640, "image_height": 480, "K1": rig.left.K.tolist(), "D1": [0.0] * 5,
            "K2": rig.right.K.tolist(), "D2": [0.0] * 5, "R": np.eye(3).tolist(), "T": [float("nan"), 0.0, 0.0]}
    path = tmp_path / "nan.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(TrackmeterError, match=r"nan\.yaml: .*T has non-finite values"):
        load_rig(path)


def test_a_rig_with_a_baseline_under_a_millimetre_is_warned_about(tmp_path: Path) -> None:
    # T = [-1e-9, 0, 0] loaded without a word and measured every point at 0.0000 m.
    import dataclasses

    rig = _rig()
    tiny = dataclasses.replace(rig, T=rig.T / np.linalg.norm(rig.T) * 1e-9)
    with pytest.warns(UserWarning, match=r"baseline 1e-09 m \(\|T\|\) is shorter than 1 mm"):
        load_rig(save_rig(tiny, tmp_path / "tiny.yaml"))


def test_an_image_size_past_opencv_s_limit_is_refused(tmp_path: Path) -> None:
    # image_width 200000 loaded, and the simulator then asked for 149 GiB (a traceback).
    path = save_rig(_rig(), tmp_path / "rig.yaml")
    path.write_text(path.read_text().replace("image_width: 640\n", "image_width: 200000\n"))
    with pytest.raises(TrackmeterError, match=r"rig\.yaml: key 'image_width' must be at most 32767 px .*got 200000"):
        load_rig(path)


def test_a_true_or_false_in_a_rig_matrix_is_refused_by_its_key(tmp_path: Path) -> None:
    # T: [true, 0, 0] in block style read as a baseline of 1 m (then "the right camera lies
    # left of the left one", without the file's name).
    import yaml

    rig = _rig()
    data = {"image_width": 640, "image_height": 480, "K1": rig.left.K.tolist(), "D1": [0.0] * 5,
            "K2": rig.right.K.tolist(), "D2": [0.0] * 5, "R": np.eye(3).tolist(), "T": [True, 0.0, 0.0]}
    path = tmp_path / "bool.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(TrackmeterError, match=r"bool\.yaml: key 'T' holds true/false where numbers go"):
        load_rig(path)


_FLOW_RIG = """image_width: 640
image_height: 480
K1: [[500, 0, 320], [0, 500, 240], [0, 0, 1]]
D1: [0, 0, 0, 0, 0]
K2: [[500, 0, 320], [0, 500, 240], [0, 0, 1]]
D2: [0, 0, 0, 0, 0]
R: [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
T: [-0.1, 0, 0]
"""


def test_a_true_or_false_in_a_flow_style_rig_matrix_is_refused_too(tmp_path: Path) -> None:
    # The check ran only where OpenCV's parser had refused the file; where it read it, a
    # hand-typed "T: [-0.12, true, 0]" was a 1 m baseline, refused later as "not side by side".
    path = tmp_path / "rig.yaml"
    path.write_text(_FLOW_RIG.replace("T: [-0.1, 0, 0]", "T: [-0.12, true, 0]"))
    with pytest.raises(TrackmeterError, match=r"rig\.yaml: key 'T' holds true/false where numbers go"):
        load_rig(path)


@pytest.mark.parametrize("header", ["", "%YAML:1.0\n---\n"])
def test_a_rig_file_giving_a_key_twice_is_refused(tmp_path: Path, header: str) -> None:
    # OpenCV's parser keeps the first of two Ts, PyYAML (any other tool) the last: a
    # recalibration pasted under the old values loaded the old ones without a word.
    path = tmp_path / "rig.yaml"
    path.write_text(header + _FLOW_RIG + "T: [-0.25, 0, 0]\n")
    with pytest.raises(TrackmeterError, match=r"rig\.yaml: key 'T' given twice"):
        load_rig(path)
    kalibr = tmp_path / "camchain.yaml"
    kalibr.write_text("cam0:\n  camera_model: pinhole\ncam0:\n  camera_model: pinhole\n")
    with pytest.raises(TrackmeterError, match=r"camchain\.yaml: key 'cam0' given twice"):
        load_rig(kalibr)
    from trackmeter.data.rigfile import is_rig_file

    assert is_rig_file(path)  # still a rig file for --overwrite to replace, wrong as it is


def test_an_rms_that_is_not_a_number_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "rig.yaml"
    path.write_text(_FLOW_RIG + "rms_px: abc\n")
    with pytest.raises(TrackmeterError, match=r"rig\.yaml: key 'rms_px' is not a number"):
        load_rig(path)
    path.write_text(_FLOW_RIG + "rms_px: 0.25\n")
    assert load_rig(path).rms_px == 0.25


def test_a_filestorage_file_without_any_rig_key_is_said_not_to_be_a_rig(tmp_path) -> None:
    """OpenCV's stereo_calib.xml (its list of chessboard images) given as --rig said "missing
    key 'K1'" (an outside probe), as if one key were missing from a rig."""
    path = tmp_path / "stereo_calib.xml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("imagelist", "left01.jpg")
    fs.release()
    with pytest.raises(TrackmeterError) as info:
        load_rig(path)
    assert str(info.value).startswith(f"{path}: not a stereo rig file: it has none of the keys K1, D1, K2, D2, R, T")


def _in_child(code: str) -> "subprocess.CompletedProcess[str]":
    """Run ``code`` in a fresh interpreter: a crash inside OpenCV (a segmentation fault) fails
    the test instead of ending the test session."""
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)


def test_a_rig_in_a_folder_whose_name_is_not_utf8_is_read(tmp_path: Path) -> None:
    # OpenCV's FileStorage, given the name (with Python's surrogate escape for the byte 0xE9),
    # crashed the process with a segmentation fault (an outside probe: track, analyze, measure).
    import os

    folder = os.fsdecode(bytes(tmp_path) + b"/bad\xe9dir")
    os.mkdir(folder)
    save_rig(_rig(), Path(folder) / "rig.yaml")
    done = _in_child(f"from trackmeter.data.rigfile import load_rig; print(load_rig({str(Path(folder) / 'rig.yaml')!r}).T)")
    assert done.returncode == 0, (done.returncode, done.stderr)
    assert "-0.2801" in done.stdout


def test_a_rig_read_in_memory_keeps_what_opencv_read_from_the_file(tmp_path: Path) -> None:
    # Compressed (FileStorage writes and reads NAME.yaml.gz), and a comment in another encoding
    # than UTF-8: both read as OpenCV read them from the file.
    rig = _rig()
    fs = cv2.FileStorage(str(tmp_path / "rig.yaml.gz"), cv2.FILE_STORAGE_WRITE)
    for key, value in (("image_width", 640), ("image_height", 480), ("K1", rig.left.K), ("D1", rig.left.dist),
                       ("K2", rig.right.K), ("D2", rig.right.dist), ("R", rig.R), ("T", rig.T.reshape(3, 1))):
        fs.write(key, value)
    fs.release()
    np.testing.assert_array_equal(load_rig(tmp_path / "rig.yaml.gz").T, rig.T)
    text = save_rig(rig, tmp_path / "plain.yaml").read_bytes()
    (tmp_path / "latin1.yaml").write_bytes(text.replace(b"\nimage_width", b"\n# cam\xe9ra gauche\nimage_width", 1))
    np.testing.assert_array_equal(load_rig(tmp_path / "latin1.yaml").left.K, rig.left.K)


def test_a_skew_in_k_is_warned_about_as_ignored(tmp_path: Path) -> None:
    # OpenCV's camera model (projection, undistortion, rectification) reads fx, fy, cx, cy
    # only: a calibration tool's skew was dropped without a word (an outside probe).
    import dataclasses
    import warnings

    rig = _rig()
    K = rig.right.K.copy()
    K[0, 1] = 0.8
    skewed = dataclasses.replace(rig, right=dataclasses.replace(rig.right, K=K))
    edge_px = 0.8 * (rig.right.height / 2) / rig.right.K[1, 1]  # x moves by skew * y/z: largest at the edge
    with pytest.warns(UserWarning, match=rf"the right camera's skew \(K\[0\]\[1\]\) 0\.8 px is ignored.* up to "
                                         rf"{edge_px:.2g} px at the image's top and bottom"):
        load_rig(save_rig(skewed, tmp_path / "skew.yaml"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_rig(save_rig(rig, tmp_path / "plain.yaml"))
        # A calibration's rounding noise in the skew (1e-9 px) moves no point by a measurable
        # amount: it warned on every run (an outside probe).
        K[0, 1] = 1e-9
        load_rig(save_rig(dataclasses.replace(rig, right=dataclasses.replace(rig.right, K=K)), tmp_path / "tiny.yaml"))


@pytest.mark.parametrize(("key", "said"), [("K2", "K2 has non-finite values"),
                                           ("D2", "D2: distortion has non-finite values"),
                                           ("D1", "D1: distortion has non-finite values")])
def test_a_nan_in_a_camera_names_its_key(tmp_path: Path, key: str, said: str) -> None:
    """A rig file has two cameras: "K has non-finite values" did not say which, and a NaN in D2
    was "distortion must have 4, 5, 8, 12 or 14 finite coefficients, got 5" (an outside probe)."""
    path = save_rig(_rig(), tmp_path / "rig.yaml")
    src = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    out = cv2.FileStorage(str(tmp_path / "nan.yaml"), cv2.FILE_STORAGE_WRITE)
    out.write("image_width", 640)
    out.write("image_height", 480)
    for k in ("K1", "D1", "K2", "D2", "R", "T"):
        m = src.getNode(k).mat().copy()
        if k == key:
            m.flat[1 if k.startswith("K") else 0] = np.nan
        out.write(k, m)
    src.release()
    out.release()
    with pytest.raises(TrackmeterError, match=rf"nan\.yaml: {said}$"):
        load_rig(tmp_path / "nan.yaml")


@pytest.mark.parametrize("k1", [1e300, 1e6, 50.0])
def test_a_distortion_no_lens_has_is_refused_at_load_naming_its_key(tmp_path: Path, k1: float) -> None:
    """An outside review: D1 = [1e300, 0, 0, 0, 0] loaded, and `measure` then leaked a numpy
    warning and blamed min_disparity_px ("... searched, nan px on this rig"); k1 = 1e6 loaded
    and refused every point as "in the border the rectification crops", the lens never named."""
    import dataclasses

    rig = _rig()
    bad = dataclasses.replace(rig, left=Camera(640, 480, rig.left.K, [k1, 0, 0, 0, 0]))
    path = save_rig(bad, tmp_path / "rig.yaml")
    with pytest.raises(TrackmeterError, match=r"rig\.yaml: .*cannot be rectified.*check D1 \[.*\] and D2 \["):
        load_rig(path)
    with pytest.raises(TrackmeterError, match="cannot be rectified"):
        bad.rectification
    # a strong but real lens (OpenCV's calibration sample fits k1 -0.29 to its camera) loads
    real = dataclasses.replace(rig, left=Camera(640, 480, rig.left.K, [-0.29, 0.11, 0, 0, 0]))
    assert load_rig(save_rig(real, tmp_path / "real.yaml")).rectification.focal_px > 0
    # and so does a real pincushion lens on cameras toed in by 18 deg, whose rectification zooms
    # 3.2 times without the lens and 4.8 with it: the geometry's zoom, not the coefficients'
    lens = [0.3, 0, 0, 0, 0]
    toed_in = StereoRig(Camera(640, 480, [[800, 0, 320], [0, 800, 240], [0, 0, 1]], lens),
                        Camera(640, 480, [[800, 0, 320], [0, 800, 240], [0, 0, 1]], lens),
                        Rotation.from_euler("y", -18, degrees=True).as_matrix(), [-0.3, 0, 0])
    assert toed_in.rectification.focal_px > 4 * 800


@pytest.mark.parametrize(("key", "value", "message"), [
    ("D1", "[[0, 0], [0, 0]]", r"D1: distortion must be a row or a column of coefficients, got a 2x2 matrix"),
    ("rms_px", "-1", r"rms_px must be a finite number >= 0 px, got -1"),
    ("rms_px", ".nan", r"rms_px must be a finite number >= 0 px, got nan"),
])
def test_a_distortion_matrix_and_a_negative_rms_are_refused_by_key(tmp_path: Path, key: str, value: str,
                                                                   message: str) -> None:
    """An outside review: D1 [[0, 0], [0, 0]] was flattened into 4 coefficients, and rms_px -1
    was taken, both without a word."""
    path = save_rig(_rig(), tmp_path / "rig.yaml")
    lines = [line for line in path.read_text().splitlines()]
    start = next(i for i, line in enumerate(lines) if line.startswith(f"{key}:"))
    end = next((i for i in range(start + 1, len(lines)) if lines[i] and not lines[i].startswith(" ")), len(lines))
    lines[start:end] = [f"{key}: {value}"]
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(TrackmeterError, match=rf"rig\.yaml: {message}$"):
        load_rig(path)


#: Middlebury 2014's Motorcycle (perfect) ``calib.txt`` (vision.middlebury.edu/stereo/data/scenes2014), as published.
MOTORCYCLE_CALIB = """cam0=[3979.911 0 1244.772; 0 3979.911 1019.507; 0 0 1]
cam1=[3979.911 0 1369.115; 0 3979.911 1019.507; 0 0 1]
doffs=124.343
baseline=193.001
width=2964
height=2000
ndisp=270
isint=0
vmin=23
vmax=245
dyavg=0
dymax=0
"""


def test_a_middlebury_calib_txt_is_the_rectified_pair_it_describes(tmp_path: Path) -> None:
    """Middlebury's ``calib.txt``: ``cam0``/``cam1`` the rectified views' camera matrices, the
    baseline in mm, the principal points ``doffs = cx1 - cx0`` apart. A pixel pair's own
    disparity ``d`` is at Middlebury's depth ``Z = baseline * f / (d + doffs)``, and the
    rectification is the identity (the pair is measured as it is)."""
    from trackmeter.data.rigfile import is_rig_file

    path = tmp_path / "calib.txt"
    path.write_text(MOTORCYCLE_CALIB)
    assert is_rig_file(path)
    rig = load_rig(path)
    assert rig.image_size == (2964, 2000)
    np.testing.assert_array_equal(rig.left.K, [[3979.911, 0, 1244.772], [0, 3979.911, 1019.507], [0, 0, 1]])
    np.testing.assert_array_equal(rig.right.K, [[3979.911, 0, 1369.115], [0, 3979.911, 1019.507], [0, 0, 1]])
    np.testing.assert_array_equal(rig.R, np.eye(3))
    np.testing.assert_array_equal(rig.T, [-0.193001, 0.0, 0.0])
    assert not np.any(rig.left.dist) and not np.any(rig.right.dist)
    rect = rig.rectification
    assert rect.disparity_offset_px == pytest.approx(-124.343, abs=1e-3)
    uv = np.array([[1500.0, 1000.0], [300.0, 1900.0], [2900.0, 40.0]])
    for side in (0, 1):
        np.testing.assert_allclose(rect.rectify_points(uv, side), uv, atol=1e-3)
    d = np.array([200.0, 23.0, 245.0])  # vmin and vmax among them
    z = rect.triangulate(uv, d)[:, 2]
    np.testing.assert_allclose(z, 193.001e-3 * 3979.911 / (d + 124.343), rtol=1e-6)


@pytest.mark.parametrize("change, message", [
    (("doffs=124.343", "doffs=120"), r"'doffs' 120 is not cx1 - cx0 = 124\.343"),
    (("baseline=193.001", "baseline=-193"), r"'baseline' must be positive \(mm\), got -193"),
    (("baseline=193.001\n", ""), r"missing 'baseline' \(mm\)"),
    (("baseline=193.001", "baseline=abc"), r"'baseline' must be a number, got 'abc'"),
    (("cam1=[3979.911 0 1369.115; 0 3979.911 1019.507; 0 0 1]\n", ""), r"missing 'cam1'"),
    (("0 3979.911 1019.507; 0 0 1]\ndoffs", "0 3979.911 1019.507]\ndoffs"), r"'cam1' must be a camera matrix"),
    (("width=2964", "width=2964.5"), r"'width' must be a whole number of pixels from 16 to 32767, got 2964\.5"),
    (("height=2000", "height=1e12"), r"'height' must be a whole number of pixels from 16 to 32767, got 1e\+12"),
    (("ndisp=270", "ndisp=270\nbaseline=1"), r"'baseline' given twice \(lines 4 and 8\)"),
])
def test_a_broken_middlebury_calib_txt_is_one_line_naming_the_file(tmp_path: Path, change: tuple[str, str],
                                                                    message: str) -> None:
    path = tmp_path / "calib.txt"
    assert change[0] in MOTORCYCLE_CALIB
    path.write_text(MOTORCYCLE_CALIB.replace(change[0], change[1]))
    with pytest.raises(TrackmeterError, match=rf"^{re.escape(str(path))}: Middlebury calib: {message}"):
        load_rig(path)


def test_a_middlebury_calib_txt_without_a_size_takes_the_frames(tmp_path: Path) -> None:
    path = tmp_path / "calib.txt"
    path.write_text(MOTORCYCLE_CALIB.replace("width=2964\nheight=2000\n", ""))
    with pytest.raises(TrackmeterError, match=r"missing 'width'/'height'"):
        load_rig(path)
    assert load_rig(path, image_size=(2964, 2000)).image_size == (2964, 2000)


def test_measure_with_a_middlebury_calib_txt_gives_the_pairs_own_disparity(tmp_path: Path, shared_data) -> None:  # type: ignore[no-untyped-def]
    """End to end on a real pair: Tsukuba with its right image moved 10 px right (its principal
    point with it, as Middlebury 2014's pairs are), described by a ``calib.txt``: ``measure
    --rig calib.txt`` gives the points of the same rig built in code, and the pair's own
    disparities (right pixel = left pixel less the disparity)."""
    import json

    from benchmarks.measure import identity_rig, load_tsukuba, principal_points_apart
    from trackmeter.core.matching import measure_points

    left, right, _ = load_tsukuba(shared_data / "middlebury_tsukuba")
    rig, moved = principal_points_apart(identity_rig(left.shape[1], left.shape[0]), right, 10)
    (K0, K1), b = (rig.left.K.tolist(), rig.right.K.tolist()), float(-rig.T[0] * 1000)
    calib = tmp_path / "calib.txt"
    calib.write_text(f"cam0=[{K0[0][0]} 0 {K0[0][2]}; 0 {K0[1][1]} {K0[1][2]}; 0 0 1]\n"
                     f"cam1=[{K1[0][0]} 0 {K1[0][2]}; 0 {K1[1][1]} {K1[1][2]}; 0 0 1]\n"
                     f"doffs={K1[0][2] - K0[0][2]}\nbaseline={b}\nwidth={left.shape[1]}\nheight={left.shape[0]}\n"
                     "ndisp=16\n")
    cv2.imwrite(str(tmp_path / "im0.png"), left)
    cv2.imwrite(str(tmp_path / "im1.png"), moved)
    pixels = [(float(u), float(v)) for v in range(40, 260, 40) for u in range(40, 360, 40)]
    run = subprocess.run([sys.executable, "-m", "trackmeter", "measure", "--rig", str(calib), "--left",
                          str(tmp_path / "im0.png"), "--right", str(tmp_path / "im1.png"), "--json", "--at",
                          *(f"{u:g},{v:g}" for u, v in pixels)], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    got = json.loads(run.stdout)
    want = measure_points(rig, left, moved, np.array(pixels))
    assert sum(m.ok for m in want) >= 10
    for g, w in zip(got, want):
        assert g["ok"] == w.ok
        if w.ok:
            assert g["xyz_m"] == pytest.approx(list(w.xyz_m), rel=1e-6)
            assert g["disparity_px"] == pytest.approx(g["uv"][0] - g["right_uv"][0], abs=1e-3)


def test_a_middlebury_calib_txt_written_by_a_windows_editor_reads_the_same(tmp_path: Path) -> None:
    """A byte-order mark first and CRLF line ends (Notepad, PowerShell's Out-File) hid the file's
    form: "not an OpenCV FileStorage file" (an outside probe)."""
    from trackmeter.data.rigfile import is_rig_file

    path = tmp_path / "calib.txt"
    path.write_bytes(b"\xef\xbb\xbf" + MOTORCYCLE_CALIB.replace("\n", "\r\n").encode())
    assert is_rig_file(path)
    got, want = load_rig(path), load_rig(_written(tmp_path / "plain.txt", MOTORCYCLE_CALIB))
    np.testing.assert_array_equal(got.left.K, want.left.K)
    np.testing.assert_array_equal(got.right.K, want.right.K)
    np.testing.assert_array_equal(got.T, want.T)


def _written(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_a_middlebury_calib_txt_that_is_not_a_rectified_pair_or_in_metres_is_warned_about(tmp_path: Path) -> None:
    """Middlebury's rectified views share f and cy: a typing slip in one is warned about (the
    pair is then rectified again, its disparities no longer its own), and a baseline written in
    metres is told in the file's unit, millimetres (it said "T must be in metres")."""
    path = _written(tmp_path / "calib.txt", MOTORCYCLE_CALIB.replace("0 3979.911 1019.507; 0 0 1]\ndoffs",
                                                                     "0 3979.911 1019.6; 0 0 1]\ndoffs"))
    with pytest.warns(UserWarning, match=r"cam0 and cam1 are not the matrices of a rectified pair"):
        load_rig(path)
    path = _written(tmp_path / "metres.txt", MOTORCYCLE_CALIB.replace("baseline=193.001", "baseline=0.193"))
    with pytest.warns(UserWarning, match=r"baseline 0\.193 mm is shorter than 1 mm: .* in millimetres: 0\.193 m "
                                         r"would be 193\)"):
        load_rig(path)


def test_a_file_named_calib_txt_too_large_to_be_one_is_refused_without_reading_it_all(tmp_path: Path) -> None:
    path = _written(tmp_path / "calib.txt", MOTORCYCLE_CALIB + "# padding\n" * 20000)
    with pytest.raises(TrackmeterError, match=r"larger than 64 KiB: a calib\.txt is a dozen short lines"):
        load_rig(path)


def test_a_middlebury_calib_txt_with_comments_added_by_hand_reads_the_same(tmp_path: Path) -> None:
    """Middlebury's files have no comments, but a copy annotated by hand may: ``#`` lines first
    (they hid the file's form), and a ``#`` after a value (it became part of the value)."""
    from trackmeter.data.config import load_config
    from trackmeter.data.rigfile import is_rig_file

    text = ("# Motorcycle, quarter size\n\n  # f, cx, cy from the published file\n"
            + MOTORCYCLE_CALIB.replace("baseline=193.001", "baseline=193.001  # mm"))
    path = _written(tmp_path / "calib.txt", text)
    assert is_rig_file(path)
    got, want = load_rig(path), load_rig(_written(tmp_path / "plain.txt", MOTORCYCLE_CALIB))
    np.testing.assert_array_equal(got.left.K, want.left.K)
    np.testing.assert_array_equal(got.right.K, want.right.K)
    np.testing.assert_array_equal(got.T, want.T)
    with pytest.raises(TrackmeterError, match=r"a Middlebury calib\.txt \(a stereo rig\)"):
        load_config(path)


def test_a_middlebury_calib_txt_with_rows_apart_is_warned_about(tmp_path: Path, shared_data) -> None:  # type: ignore[no-untyped-def]
    """Middlebury's "imperfect" calibrations say how far the views' rows are apart (``dyavg``,
    ``dymax``). The matching searches along one row: on Tsukuba with its right image moved down
    1 px, fewer than two thirds as many points are accepted, so a ``dymax`` like the imperfect
    files' (about 1.5 px) is warned about, and Middlebury's perfect files (0) are not."""
    import warnings

    from benchmarks.measure import identity_rig, load_tsukuba
    from trackmeter.core.matching import measure_points

    imperfect = _written(tmp_path / "calib.txt", MOTORCYCLE_CALIB.replace("dyavg=0\ndymax=0", "dyavg=0.918\ndymax=1.516"))
    with pytest.warns(UserWarning, match=r"dymax=1\.516: the views' rows are up to 1\.516 px apart"):
        load_rig(imperfect)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_rig(_written(tmp_path / "perfect.txt", MOTORCYCLE_CALIB))

    left, right, _ = load_tsukuba(shared_data / "middlebury_tsukuba")
    rig = identity_rig(left.shape[1], left.shape[0])
    pixels = np.column_stack([np.random.default_rng(0).uniform(30, 350, 200), np.random.default_rng(1).uniform(30, 255, 200)])
    down = cv2.warpAffine(right, np.float32([[1, 0, 0], [0, 1, 1.0]]), right.shape[::-1], flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT)
    aligned = sum(m.ok for m in measure_points(rig, left, right, pixels))
    apart = sum(m.ok for m in measure_points(rig, left, down, pixels))
    assert aligned >= 50 and apart < 2 / 3 * aligned, (aligned, apart)
