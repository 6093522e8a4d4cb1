"""Image reading and stereo image-set pairing (trackmeter.data.images)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from trackmeter.data.images import (_opencv_log_level, data_bits, expand_globs, pair_stereo_paths, read_grey,
                                    read_grey_pair, to_grey_u8)
from trackmeter.errors import TrackmeterError


@pytest.fixture()
def colour() -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)


def test_real_file_reads_as_grey(shared_data: Path) -> None:
    path = shared_data / "middlebury_tsukuba" / "img_left.png"
    img = read_grey(path)
    assert img.dtype == np.uint8 and img.shape == (288, 384)
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    expected = raw if raw.ndim == 2 else cv2.cvtColor(raw, cv2.COLOR_BGR2GRAY)
    np.testing.assert_array_equal(img, expected)


def test_colour_is_converted_with_opencv_weights(tmp_path: Path, colour: np.ndarray) -> None:
    cv2.imwrite(str(tmp_path / "c.png"), colour)
    np.testing.assert_array_equal(read_grey(tmp_path / "c.png"), cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY))
    bgra = np.dstack([colour, np.full(colour.shape[:2], 7, np.uint8)])
    cv2.imwrite(str(tmp_path / "a.png"), bgra)
    np.testing.assert_array_equal(read_grey(tmp_path / "a.png"), cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY))


def test_sixteen_bit_keeps_the_high_byte(tmp_path: Path) -> None:
    img16 = np.arange(0, 65536, 256, dtype=np.uint16).reshape(16, 16) + 255
    cv2.imwrite(str(tmp_path / "d.png"), img16)
    np.testing.assert_array_equal(read_grey(tmp_path / "d.png"), (img16 >> 8).astype(np.uint8))


@pytest.mark.parametrize(("largest", "bits"), [(0, 10), (1023, 10), (1024, 12), (4095, 12), (4096, 14),
                                               (16383, 14), (16384, 16), (65535, 16)])
def test_data_bits_is_the_smallest_sample_depth_that_holds_the_values(largest: int, bits: int) -> None:
    img = np.zeros((4, 5), np.uint16)
    img[2, 3] = largest
    assert data_bits([img]) == bits
    # the largest value over all the images decides; 8-bit images have no say
    assert data_bits([img, np.full((2, 2), 255, np.uint8)]) == bits
    assert data_bits([np.full((2, 2), 40, np.uint16), img]) == max(bits, 10)


def test_data_bits_of_eight_bit_images_is_eight() -> None:
    assert data_bits([np.full((3, 3), 255, np.uint8)]) == 8
    assert data_bits([]) == 8


def test_twelve_bit_data_in_sixteen_bit_files_reads_like_the_eight_bit_image(tmp_path: Path) -> None:
    """A machine-vision camera's 12-bit samples stored as they are (values below 4096) read as
    their top 8 bits, not as a black image (>> 8 would leave at most 15 grey levels)."""
    rng = np.random.default_rng(3)
    img8 = rng.integers(0, 256, (24, 32), dtype=np.uint8)
    low = rng.integers(0, 16, img8.shape, dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "l.png"), (img8.astype(np.uint16) << 4) | low)
    np.testing.assert_array_equal(read_grey(tmp_path / "l.png"), img8)
    # an explicit depth is obeyed, and values beyond it saturate instead of wrapping
    np.testing.assert_array_equal(read_grey(tmp_path / "l.png", bits=16), img8 >> 4)
    np.testing.assert_array_equal(read_grey(tmp_path / "l.png", bits=10), np.minimum(img8.astype(int) * 4 + (low >> 2), 255))
    # a pair is scaled alike: a darker right image keeps the left one's depth
    dark = ((img8 // 8).astype(np.uint16) << 4)
    cv2.imwrite(str(tmp_path / "r.png"), dark)
    np.testing.assert_array_equal(read_grey(tmp_path / "r.png"), (img8 // 8) * 4)  # alone: read as 10-bit data
    with pytest.warns(UserWarning, match="4x darker"):  # or a shallower camera: one pair cannot tell
        left, right = read_grey_pair(tmp_path / "l.png", tmp_path / "r.png")
    np.testing.assert_array_equal(left, img8)
    np.testing.assert_array_equal(right, img8 // 8)


@pytest.mark.parametrize("content", [b"", b"hello", bytes(range(256))])
def test_non_image_raises(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "x.png"
    path.write_bytes(content)
    with pytest.raises(TrackmeterError, match="not an image"):
        read_grey(path)


@pytest.mark.parametrize("keep", [20, 3000, 30000, 200000])
def test_a_cut_short_png_is_one_error_and_nothing_from_opencv(tmp_path: Path, capfd: pytest.CaptureFixture[str],
                                                             keep: int) -> None:
    """A PNG cut short (a copy that stopped, a crash while writing) made OpenCV's decoder log
    "[ WARN:0@...] global grfmt_png.cpp:793 readFromStreamOrBuffer PNG input buffer is
    incomplete" (and an [ERROR ...] line for a cut header) on the process's stderr, before
    the command's own one-line error; cut past its first few compressed chunks, libpng itself
    printed "libpng error: PNG input buffer is incomplete" (OpenCV 5; no logging level stops it)."""
    rng = np.random.default_rng(1)
    ok, buf = cv2.imencode(".png", rng.integers(0, 256, (512, 726), dtype=np.uint8))
    path = tmp_path / "cut.png"
    path.write_bytes(buf.tobytes()[:keep])
    get_level = _opencv_log_level()[0]  # type: ignore[index]
    level = get_level()
    capfd.readouterr()
    with pytest.raises(TrackmeterError, match="not an image"):
        read_grey(path)
    assert capfd.readouterr().err == ""
    assert get_level() == level  # OpenCV's own logging is given back


def test_missing_file_raises(tmp_path: Path) -> None:
    with pytest.raises(TrackmeterError, match="no such image"):
        read_grey(tmp_path / "nope.png")


def _touch(folder: Path, *names: str) -> list[Path]:
    for n in names:
        (folder / n).write_bytes(b"")
    return [folder / n for n in names]


def test_expand_globs_sorts_naturally(tmp_path: Path) -> None:
    _touch(tmp_path, "img10.png", "img2.png", "img1.png")
    assert [p.name for p in expand_globs(str(tmp_path / "img*.png"))] == ["img1.png", "img2.png", "img10.png"]
    # a shell-expanded list works as well, without duplicates
    files = [str(tmp_path / "img2.png"), str(tmp_path / "img*.png")]
    assert len(expand_globs(files)) == 3
    with pytest.raises(TrackmeterError, match="no images match"):
        expand_globs(str(tmp_path / "none*.png"))
    (odd,) = _touch(tmp_path, "shot[1].png")
    assert expand_globs(str(odd)) == [odd]


def test_pairing_by_number_and_by_order(tmp_path: Path) -> None:
    left = _touch(tmp_path, "left01.png", "left02.png", "left05.png")
    right = _touch(tmp_path, "right02.png", "right05.png", "right07.png")
    with pytest.warns(UserWarning, match=r"2 image\(s\) without a partner .* left out: left01.png, right07.png"):
        pairs = pair_stereo_paths(left, right)
    assert [(a.name, b.name) for a, b in pairs] == [("left02.png", "right02.png"), ("left05.png", "right05.png")]
    left = _touch(tmp_path, "a.png", "b.png")
    right = _touch(tmp_path, "c.png", "d.png")
    assert [(a.name, b.name) for a, b in pair_stereo_paths(left, right)] == [("a.png", "c.png"), ("b.png", "d.png")]
    with pytest.raises(TrackmeterError, match="1 left and 2 right"):
        pair_stereo_paths(left[:1], right)
    with pytest.raises(TrackmeterError, match=r"share a frame number to pair by \(left 1, right 2\)"):
        pair_stereo_paths(_touch(tmp_path, "l1.png"), _touch(tmp_path, "r2.png"))


def test_pairing_refused_says_which_name_stops_it(tmp_path: Path) -> None:
    """A glob that also matched one file without a number (``left_extra.png`` beside
    ``left01..03``) was refused as "their names carry no frame numbers", though all others do;
    camera time stamps a few units apart shared no number and the message gave no way out
    (an outside probe)."""
    left = _touch(tmp_path, "left01.png", "left02.png", "left03.png", "left_extra.png")
    right = _touch(tmp_path, "right01.png", "right02.png", "right03.png")
    with pytest.raises(TrackmeterError, match=r"^4 left and 3 right images, and not every name carries a frame number of its own "
                                              r"to pair by \(left_extra.png has none\)$"):
        pair_stereo_paths(left, right)
    twice = _touch(tmp_path, "a_1.png", "b_1.png", "a_2.png")
    with pytest.raises(TrackmeterError, match=r"\(left: a_1.png and b_1.png carry the same number, 1\)$"):
        pair_stereo_paths(twice, right[:2])
    with pytest.raises(TrackmeterError, match=r"to pair by$"):
        pair_stereo_paths(_touch(tmp_path, "x.png", "y.png"), _touch(tmp_path, "z.png"))
    stamps_l = _touch(tmp_path, "L_1000.png", "L_1040.png")
    stamps_r = _touch(tmp_path, "R_1003.png", "R_1043.png")
    with pytest.raises(TrackmeterError, match=r"\(left 1000-1040, right 1003-1043\): rename them so that a pair's "
                                              r"names carry one number$"):
        pair_stereo_paths(stamps_l, stamps_r)


@pytest.mark.parametrize("full_scale", [255.0, 65535.0])
def test_float_images_of_whole_numbers_are_integer_data(full_scale: float) -> None:
    # A float TIFF saved from 8-bit data holds 0-255: clipped to [0, 1] it read as white, and
    # every point was "textureless" with nothing said (an outside probe).
    grey = np.arange(0, 256, dtype=np.uint8).reshape(16, 16)
    image = np.round(grey.astype(np.float64) * (full_scale / 255.0)).astype(np.float32)
    np.testing.assert_array_equal(to_grey_u8(image), grey)


def test_float_images_on_the_unit_range_saturate_their_highlights() -> None:
    # A scene-linear image with 2 % of its pixels at 8.0 (a glint) is still on [0, 1].
    rng = np.random.default_rng(2)
    image = rng.uniform(0.05, 0.9, size=(50, 50)).astype(np.float32)
    image.flat[::50] = 8.0
    out = to_grey_u8(image)
    np.testing.assert_array_equal(out, np.clip(np.round(image * 255.0), 0, 255).astype(np.uint8))


def test_a_small_target_on_black_sky_in_whole_numbers_keeps_its_grey_levels() -> None:
    image = np.zeros((100, 100), np.float32)
    image[45:54, 45:54] = np.arange(81, dtype=np.float32).reshape(9, 9) + 100.0  # 0.81 % of the pixels
    out = to_grey_u8(image)
    assert out[0, 0] == 0 and out[45, 45] == 100 and out[53, 53] == 180


def test_a_pair_of_float_images_is_scaled_alike(tmp_path: Path) -> None:
    # The dark image of a pair of whole-number images (all 0 and 1, no target) stays black: it
    # is read on the range the other says, not on [0, 1] by itself.
    lit = np.zeros((20, 30), np.float32)
    lit[5:10, 5:10] = 200.0
    dark = np.zeros((20, 30), np.float32)
    dark[0, :5] = 1.0
    cv2.imwrite(str(tmp_path / "l.tif"), lit)
    cv2.imwrite(str(tmp_path / "r.tif"), dark)
    left, right = read_grey_pair(tmp_path / "l.tif", tmp_path / "r.tif")
    assert left[7, 7] == 200 and right.max() <= 1


def test_float_images_beyond_sixteen_bit_are_refused() -> None:
    with pytest.raises(TrackmeterError, match="float"):
        to_grey_u8(np.full((8, 8), 1e6, np.float32), "x.tif")


def test_a_pair_of_different_sample_depths_is_warned_about(tmp_path: Path) -> None:
    # Scaled alike (as a pair must be), a 12-bit left beside a full 16-bit right reads black,
    # and every point came back "too dark" with nothing said.
    rng = np.random.default_rng(1)
    left = rng.integers(0, 4096, (20, 30), dtype=np.uint16)
    right = rng.integers(0, 65536, (20, 30), dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "l.png"), left)
    cv2.imwrite(str(tmp_path / "r.png"), right)
    with pytest.warns(UserWarning, match="12-bit.*16-bit"):
        read_grey_pair(tmp_path / "l.png", tmp_path / "r.png")


def test_a_pair_two_bits_apart_is_warned_about_with_what_it_was_read_as(tmp_path: Path) -> None:
    # 10-bit left beside 12-bit right went without a word; one pair cannot tell a darker image
    # from a shallower camera, so it is read alike, and said.
    rng = np.random.default_rng(2)
    img8 = rng.integers(0, 256, (20, 30), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "l.png"), img8.astype(np.uint16) << 2)
    cv2.imwrite(str(tmp_path / "r.png"), img8.astype(np.uint16) << 4)
    with pytest.warns(UserWarning, match=r"l.png looks 10-bit and .*r.png 12-bit: all are read as 12-bit .*4x dark"):
        left, right = read_grey_pair(tmp_path / "l.png", tmp_path / "r.png")
    np.testing.assert_array_equal(left, img8 >> 2)
    np.testing.assert_array_equal(right, img8)


def test_opencv_4s_log_level_functions_are_used_where_opencv_5s_module_is_missing(tmp_path: Path,
                                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    # OpenCV 4 (the project allows >= 4.9) has cv2.setLogLevel / cv2.getLogLevel and no
    # cv2.utils.logging: every image read raised AttributeError there.
    import types

    calls: list[int] = []
    monkeypatch.setattr(cv2, "utils", types.SimpleNamespace())
    monkeypatch.setattr(cv2, "getLogLevel", lambda: 3, raising=False)
    monkeypatch.setattr(cv2, "setLogLevel", calls.append, raising=False)
    ok, buf = cv2.imencode(".png", np.full((8, 8), 7, np.uint8))
    (tmp_path / "ok.png").write_bytes(buf.tobytes())
    assert read_grey(tmp_path / "ok.png")[0, 0] == 7
    assert calls == [0, 3]  # silent (OpenCV 4's LOG_LEVEL_SILENT is 0) while decoding, then as it was
