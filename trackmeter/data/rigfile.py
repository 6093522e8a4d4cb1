"""Stereo rig files: OpenCV FileStorage YAML (DESIGN.md section 6).

Keys: ``image_width``, ``image_height``, ``K1``, ``D1``, ``K2``, ``D2``, ``R``, ``T`` (metres),
optional ``rms_px``, ``E``, ``F``. OpenCV's stereo sample pair ``intrinsics.yml`` (``M1 D1 M2
D2``) + ``extrinsics.yml`` (``R T ...``) is read too: give either file and the other is found
beside it (or one file holding both halves); that pair carries no image size, so pass
``image_size``. So is Kalibr's ``camchain.yaml`` (pinhole, radial-tangential), as real stereo
data often comes with one, and so is Middlebury's ``calib.txt`` (2014 and 2021 stereo
datasets: a pair rectified already, ``cam0``/``cam1`` camera matrices, ``baseline`` in mm).
Matrices may be plain YAML lists, in any style PyYAML reads; ``R`` may be a rotation vector (3
numbers, ``cv2.Rodrigues``), as OpenCV's stereo functions take it.
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path
from typing import Literal, cast, overload

import cv2
import numpy as np
import yaml

from trackmeter.core.stereo import Camera, StereoRig, whole_pixels
from trackmeter.data.atomic import write_files_atomic
from trackmeter.data.config import (
    FAST_SAFE_LOADER,
    MIDDLEBURY_CALIB_START,
    DuplicateKeyError,
    check_yaml_expansion,
)
from trackmeter.errors import TrackmeterError, shown_value


def _open(path: Path, strict: bool = True) -> cv2.FileStorage:
    if path.is_dir():
        raise TrackmeterError(f"{path}: a folder, not a rig file")
    if not path.is_file():
        presets = ""
        if path.parent == Path("."):  # a bare name: perhaps a preset's, mistyped
            from trackmeter.paths import RIGS_DIR, preset_names

            presets = f" (a file, or a preset: {', '.join(preset_names(RIGS_DIR))})"
        raise TrackmeterError(f"{path}: no such rig file{presets}")
    not_filestorage = TrackmeterError(f"{path}: not an OpenCV FileStorage file (YAML/XML)")
    try:
        text = _filestorage_text(path)
    except OSError:
        raise TrackmeterError(f"{path}: cannot read as a text file") from None
    if text is None:
        raise not_filestorage
    read_as_plain_yaml = False  # by _plain_yaml, which has checked its values already
    fs: cv2.FileStorage | None
    try:
        # Parsed from memory, never from the name: OpenCV crashes the process (a segmentation
        # fault) on a name that is not UTF-8 (Python's surrogate escapes of its bytes).
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError):
        read_as_plain_yaml = True
        # OpenCV 5's binding wraps the parser's cv2.error in a SystemError.
        fs = _plain_yaml(path)
        if fs is None:
            raise not_filestorage from None
    if not fs.isOpened():
        raise not_filestorage
    if not fs.root().isMap():  # a list or a scalar: every key lookup would assert inside OpenCV
        raise TrackmeterError(f"{path}: not a mapping of keys (image_width, K1, ...): a rig file's top level "
                              "must be key: value pairs")
    if not strict or read_as_plain_yaml:  # strict=False: asked only what the file is (is_rig_file)
        return fs
    keys = list(fs.root().keys())
    repeated = [k for i, k in enumerate(keys) if k in keys[:i]]
    if repeated:  # OpenCV keeps the first, PyYAML (and so any other tool) the last
        raise TrackmeterError(f"{path}: key {repeated[0]!r} given twice: one file, two calibrations; keep one")
    # OpenCV reads true/false as 1/0 ("T: [-0.12, true, 0]" a baseline of 1 m): asked of the
    # file as plain YAML, which a file of !!opencv-matrix tags is not (nothing to ask there).
    plain = _plain_yaml_data(text, path)
    if plain is not None:
        _check_plain_values(plain, path, finite=False)
    return fs


#: Far beyond any rig file (a few kB): a video or an image given as --rig is not read whole.
_MAX_RIG_FILE_BYTES = 16 * 2**20


def _filestorage_text(path: Path) -> str | None:
    """The text of a FileStorage file as OpenCV reads it from disk: gzip-compressed (its
    ``.gz`` names), a UTF-8 byte-order mark left out (a Windows editor's; OpenCV's parser
    refuses it), and bytes that are not UTF-8 (a comment in another encoding) kept one
    character each, as OpenCV keeps them. None when it cannot be one (too large, NUL bytes).

    Raises:
        OSError: the file cannot be read.
    """
    import gzip
    import zlib

    if path.stat().st_size > _MAX_RIG_FILE_BYTES:
        return None
    raw = path.read_bytes()
    if raw[:2] == b"\x1f\x8b":
        try:
            raw = gzip.decompress(raw)
        except (OSError, EOFError, zlib.error):
            return None
    raw = raw.removeprefix(b"\xef\xbb\xbf")
    if b"\x00" in raw:
        return None
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def _plain_yaml(path: Path) -> cv2.FileStorage | None:
    """The file as FileStorage when it is plain YAML that OpenCV's parser refuses but PyYAML
    reads (``yaml.safe_dump`` writes nested lists as zero-indented ``- - x`` blocks), via the
    JSON form OpenCV does read; None when it is not a mapping of plain values."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError):
        return None
    data = _plain_yaml_data(text, path)
    if data is None:
        return None
    _check_plain_values(data, path, finite=True)
    try:
        return cv2.FileStorage(json.dumps(data, allow_nan=False), cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (TypeError, ValueError, cv2.error, SystemError):
        return None


def _plain_yaml_data(text: str, path: Path, strict: bool = True) -> dict | None:
    """``text`` read as plain YAML (PyYAML; a key given twice refused, unless not ``strict``),
    None when it is not a mapping PyYAML reads (OpenCV's ``!!opencv-matrix`` tags, XML).

    Raises:
        TrackmeterError: a key given twice; YAML aliases that expand beyond any rig file.
    """
    try:
        loader = FAST_SAFE_LOADER if strict else yaml.SafeLoader
        data = yaml.load(without_directives(text.removeprefix("\ufeff")), Loader=loader)  # noqa: S506
    except DuplicateKeyError as exc:
        raise TrackmeterError(f"{path}: {exc.problem}") from None
    except yaml.YAMLError:
        return None
    check_yaml_expansion(data, path)
    return data if isinstance(data, dict) else None


def _check_plain_values(data: dict, path: Path, finite: bool) -> None:
    """Refuse what OpenCV would read as numbers: true/false in a list (1/0), and, with
    ``finite``, a non-finite value (the JSON OpenCV is given has none)."""
    for key, value in data.items():
        leaves = _leaves(value)
        # JSON has no NaN: said here by its key, as OpenCV's own form of the file is.
        if finite and any(isinstance(x, float) and not math.isfinite(x) for x in leaves):
            raise TrackmeterError(f"{path}: {key} has non-finite values")
        # ... and OpenCV reads true/false as 1/0: a baseline of 1 m from "T: [true, 0, 0]".
        if isinstance(value, list) and any(isinstance(x, bool) for x in leaves):
            raise TrackmeterError(f"{path}: key '{key}' holds true/false where numbers go")


def _leaves(value: object) -> list[object]:
    """The scalars of nested lists (``value`` itself when it is none)."""
    if isinstance(value, list):
        return [leaf for v in value for leaf in _leaves(v)]
    return [value]


#: The keys of a rig file (rig.yaml) and of OpenCV's intrinsics.yml / extrinsics.yml pair.
_RIG_KEYS = ("K1", "D1", "K2", "D2", "R", "T", "M1", "M2")

#: Keys whose matrix is 3x3: a flat list of nine numbers is read row by row.
_SQUARE_KEYS = frozenset({"K1", "K2", "M1", "M2", "R"})


@overload
def _matrix(fs: cv2.FileStorage, key: str, path: Path, required: Literal[True] = True) -> np.ndarray: ...
@overload
def _matrix(fs: cv2.FileStorage, key: str, path: Path, required: bool) -> np.ndarray | None: ...
def _matrix(fs: cv2.FileStorage, key: str, path: Path, required: bool = True) -> np.ndarray | None:
    """``key``'s matrix: an ``!!opencv-matrix``, a number, or a plain YAML list (flat, or a list
    of rows) of numbers as a hand-written or another tool's file has it."""
    node = fs.getNode(key)
    if node.empty() or node.isNone():
        if required:
            raise TrackmeterError(f"{path}: missing key '{key}'")
        return None
    not_matrix = TrackmeterError(f"{path}: key '{key}' is not a matrix (an !!opencv-matrix or a list of numbers)")
    if node.isReal() or node.isInt():
        return np.array([node.real()])
    if node.isSeq():
        try:
            values = np.array(_numbers(node), dtype=float)
        except (TypeError, ValueError):  # a string inside, or rows of unequal length
            raise not_matrix from None
        if values.ndim > 2:
            raise not_matrix  # (an empty list is kept: "D1: []", no distortion)
        return values.reshape(3, 3) if key in _SQUARE_KEYS and values.size == 9 else values
    try:
        mat = node.mat()
    except (cv2.error, SystemError):  # a mapping that is not an !!opencv-matrix, or a string
        raise not_matrix from None
    if mat is None:
        if node.isMap() and node.getNode("rows").isInt() and int(node.getNode("rows").real()) == 0:
            return np.zeros(0)  # cv2.FileStorage's form of an empty array ("D1: []")
        raise not_matrix
    return np.asarray(mat, dtype=float)


def _camera(width: int, height: int, fs: cv2.FileStorage, k_key: str, d_key: str, path: Path) -> Camera:
    """The camera of keys ``k_key`` (its matrix) and ``d_key`` (its distortion); a refusal names
    them: a rig file has two of each, and "K has non-finite values" did not say which."""
    K, dist = _matrix(fs, k_key, path), _matrix(fs, d_key, path)
    try:
        return Camera(width, height, K, dist)
    except TrackmeterError as exc:
        said = str(exc)
        if said.startswith("K"):  # "K has non-finite values", "K's last row ...", "K[1][0] ..."
            said = k_key + said[1:]
        elif said.startswith("distortion"):
            said = f"{d_key}: {said}"
        raise TrackmeterError(f"{path}: {said}") from None


def _rotation(fs: cv2.FileStorage, path: Path) -> np.ndarray:
    """Key ``R``: a 3x3 matrix, or a rotation vector (3 numbers, axis times angle in radians:
    ``cv2.Rodrigues``), the other form OpenCV's own stereo functions take."""
    R = _matrix(fs, "R", path)
    assert R is not None
    if R.size == 3 and np.all(np.isfinite(R)):
        return cv2.Rodrigues(R.reshape(3, 1))[0]
    return R


def _numbers(node: cv2.FileNode) -> list | float | str:
    """A plain YAML sequence as nested Python lists (a non-number leaf stays a string)."""
    if node.isSeq():
        return [_numbers(node.at(i)) for i in range(node.size())]
    if node.isReal() or node.isInt():
        return float(node.real())
    return "not a number"


def _scalar(fs: cv2.FileStorage, key: str, path: Path) -> float | None:
    """Optional key ``key``'s number; None when it is not given.

    Raises:
        TrackmeterError: it is given, and not a number ("rms_px: abc" was left out unsaid).
    """
    node = fs.getNode(key)
    if node.empty() or node.isNone():
        return None
    if not (node.isReal() or node.isInt()):
        raise TrackmeterError(f"{path}: key '{key}' is not a number")
    return float(node.real())


#: No camera image is narrower than this (px); a smaller size in a rig file is a typo or a boolean.
MIN_IMAGE_SIZE_PX = 16
#: ... nor wider than OpenCV can remap (its maps hold coordinates as 16-bit integers): a larger
#: size is a typo, and would ask for a canvas of hundreds of gigabytes.
MAX_IMAGE_SIZE_PX = 32767


def _image_size_scalar(fs: cv2.FileStorage, key: str, path: Path) -> int | None:
    """``key``'s whole number of pixels (``640`` or ``640.``); None when the key is absent.

    Raises:
        TrackmeterError: the key holds anything else (NaN, a fraction, a string, a list) or
            fewer than :data:`MIN_IMAGE_SIZE_PX` or more than :data:`MAX_IMAGE_SIZE_PX` pixels.
    """
    node = fs.getNode(key)
    if node.empty() or node.isNone():
        return None
    value = float(node.real()) if node.isReal() or node.isInt() else math.nan
    if not (math.isfinite(value) and value == round(value)):
        shown = node.string() if node.isString() else (value if node.isReal() or node.isInt() else "not a number")
        raise TrackmeterError(f"{path}: key '{key}' must be a whole number of pixels, got {shown!r}")
    if value < MIN_IMAGE_SIZE_PX:
        # OpenCV's parser reads YAML's true/false as 1/0, which would load as a 1 px camera.
        raise TrackmeterError(f"{path}: key '{key}' must be at least {MIN_IMAGE_SIZE_PX} px, got {int(value)} "
                              "(a YAML true/false reads as 1/0)")
    if value > MAX_IMAGE_SIZE_PX:
        raise TrackmeterError(f"{path}: key '{key}' must be at most {MAX_IMAGE_SIZE_PX} px (OpenCV's limit), "
                              f"got {value:.0f}")
    return int(value)


def swapped_cameras(rig: StereoRig) -> bool:
    """True when the right camera's centre lies left of the left camera (a horizontal rig whose
    files or cameras were swapped): every disparity then lies below a point at infinity's and nothing matches."""
    centre = -rig.R.T @ rig.T  # the right camera's optical centre in the left camera frame
    return bool(centre[0] < 0 and abs(centre[0]) > max(abs(centre[1]), abs(centre[2])))


#: A baseline longer than this (m) is taken for one written in millimetres (DESIGN.md: ``T`` in
#: metres): no stereo rig of this domain is 10 m wide, and any baseline from 1 cm up in mm is.
MAX_PLAUSIBLE_BASELINE_M = 10.0
#: ... and one shorter than this (m) measures nothing: 1 px of disparity at 1000 px focal
#: length is 1 m away.
MIN_PLAUSIBLE_BASELINE_M = 1e-3


def load_rig(path: str | Path, image_size: tuple[int, int] | None = None) -> StereoRig:
    """Read a stereo rig from an OpenCV FileStorage file (see :func:`_load_rig`); warns when
    its baseline is longer than :data:`MAX_PLAUSIBLE_BASELINE_M` (``T`` in millimetres: every
    depth would come out 1000 times too far). A rig that cannot be matched (swapped or vertical
    cameras) loads; measuring and tracking refuse it with the remedy
    (:func:`trackmeter.core.stereo.check_side_by_side`)."""
    resolved = resolve_rig_path(path)
    middlebury = _middlebury_calib(resolved)  # first: a few bytes read tell it
    rig = _load_middlebury(middlebury, resolved, image_size) if middlebury is not None else _load_rig(resolved, image_size)
    try:
        rig.rectification  # computed once and cached: a lens model that cannot be rectified is the file's fault
    except TrackmeterError as exc:
        raise TrackmeterError(f"{resolved}: {exc}") from None
    for problem in (baseline_problem(rig, "mm" if middlebury is not None else "m"), skew_problem(rig)):
        if problem:
            warnings.warn(f"{path}: {problem}", stacklevel=2)
    return rig


#: A skew that moves no point by more than this (px, at the image's top and bottom edges) is
#: rounding noise in a calibration, not worth a warning on every run.
SKEW_NEGLIGIBLE_PX = 0.01


def skew_problem(rig: StereoRig) -> str | None:
    """One line when a camera matrix has a skew (``K[0][1]``, ``s``) that matters, else None:
    OpenCV's camera model (projection, undistortion, rectification) reads fx, fy, cx and cy
    only, so every point is measured as if ``s`` were 0, off by ``s * y / z`` px across the
    rows, largest at the top and bottom edges (``|y / z| = (height / 2) / fy``)."""
    skewed = []
    for side, cam in (("left", rig.left), ("right", rig.right)):
        edge_px = abs(cam.K[0, 1]) * (cam.height / 2) / abs(cam.K[1, 1])
        if edge_px > SKEW_NEGLIGIBLE_PX:
            skewed.append((side, cam.K[0, 1], edge_px))
    if not skewed:
        return None
    who = "the left and right cameras' skews" if len(skewed) == 2 else f"the {skewed[0][0]} camera's skew"
    values = " and ".join(f"{s:.4g} px" for _, s, _ in skewed)
    return (f"{who} (K[0][1]) {values} {'are' if len(skewed) == 2 else 'is'} ignored: OpenCV's camera model has no "
            f"skew, so points are measured as if it were 0, off by up to {max(e for _, _, e in skewed):.2g} px at the "
            "image's top and bottom (calibrate with the skew fixed at 0)")


def baseline_problem(rig: StereoRig, file_unit: str = "m") -> str | None:
    """One line when the rig's baseline is longer than :data:`MAX_PLAUSIBLE_BASELINE_M` (its
    ``T`` most likely in millimetres: calibrated with the square size in mm) or shorter than
    :data:`MIN_PLAUSIBLE_BASELINE_M`, else None. ``file_unit`` ``"mm"``: the file gives the
    baseline in millimetres (Middlebury's ``calib.txt``), and one too short was likely written
    in metres."""
    if rig.baseline_m < MIN_PLAUSIBLE_BASELINE_M:
        if file_unit == "mm":
            return (f"baseline {rig.baseline_m * 1000:.4g} mm is shorter than 1 mm: no depth can be measured with it "
                    f"(a calib.txt's baseline is in millimetres: {rig.baseline_m * 1000:.4g} m would be "
                    f"{rig.baseline_m * 1e6:.4g})")
        return (f"baseline {rig.baseline_m:.4g} m (|T|) is shorter than 1 mm: no depth can be measured with it "
                "(T must be in metres)")
    if rig.baseline_m <= MAX_PLAUSIBLE_BASELINE_M:
        return None
    return (f"baseline {rig.baseline_m:.4g} m (|T|): T must be in metres; if it is in millimetres (calibrated with "
            "the square size in mm), every depth and distance comes out 1000x too large")


def resolve_rig_path(name_or_path: str | Path) -> Path:
    """A rig file: an existing path, else a preset's name (``config/rigs/NAME[.yaml]``, as
    scenarios are named); otherwise the path as given, so that reading it says what is wrong."""
    from trackmeter.paths import RIGS_DIR, preset

    return preset(name_or_path, RIGS_DIR) or Path(name_or_path)


def _load_rig(path: str | Path, image_size: tuple[int, int] | None = None) -> StereoRig:
    """Read a stereo rig from an OpenCV FileStorage file.

    Args:
        path: ``rig.yaml`` (DESIGN.md keys), or OpenCV's ``intrinsics.yml`` or
            ``extrinsics.yml`` (the other is read from the same folder).
        image_size: ``(width, height)``, px; required only when the file has no size.

    Raises:
        TrackmeterError: missing file, not FileStorage, a missing key or a malformed matrix.
    """
    path = Path(path)
    camchain = _kalibr_camchain(path)
    if camchain is not None:
        return _load_kalibr(camchain, path)
    fs = _open(path)
    try:
        if all(fs.getNode(key).empty() for key in _RIG_KEYS):
            # Another FileStorage file (OpenCV's stereo_calib.xml lists images): not one key short.
            raise TrackmeterError(f"{path}: not a stereo rig file: it has none of the keys K1, D1, K2, D2, R, T "
                                  "(a rig.yaml) nor M1, D1, M2, D2 and R, T (OpenCV's intrinsics.yml and extrinsics.yml)")
        if fs.getNode("K1").empty() and (not fs.getNode("M1").empty() or not fs.getNode("R").empty()):
            return _load_opencv_pair(path, image_size)
        width = _image_size_scalar(fs, "image_width", path)
        height = _image_size_scalar(fs, "image_height", path)
        size_from_frames = width is None or height is None
        if width is None or height is None:  # (as size_from_frames, spelt out for mypy's narrowing)
            if image_size is None:
                raise TrackmeterError(f"{path}: missing key 'image_width'/'image_height'")
            width, height = image_size
        left = _camera(int(width), int(height), fs, "K1", "D1", path)
        right = _camera(int(width), int(height), fs, "K2", "D2", path)
        if size_from_frames:
            # Checked as OpenCV's pair is: a rig.yaml without its size on other frames said
            # nothing, and every candidate point was refused as having no match.
            _check_size_taken_from_frames(left, right, path, "the file has no image_width/image_height",
                                          stacklevel=4)  # load_rig -> here -> the check
        rms = _scalar(fs, "rms_px", path)
        return StereoRig(left, right, _rotation(fs, path), _matrix(fs, "T", path).ravel(), rms_px=rms, name=path.stem)
    except TrackmeterError as exc:
        if str(exc).startswith(str(path)):
            raise
        raise TrackmeterError(f"{path}: {exc}") from None
    finally:
        fs.release()


def is_rig_file(path: str | Path) -> bool:
    """Whether ``path`` is a stereo rig file: one this module reads (a rig.yaml, OpenCV's
    intrinsics.yml or extrinsics.yml, a Kalibr camchain.yaml), judged by its keys. What a
    command may replace with ``--overwrite``: not the user's other files."""
    path = Path(path)
    try:  # a file of the right keys, right or wrong in what they hold (a key given twice)
        if _middlebury_text(path) is not None or _kalibr_camchain(path, strict=False) is not None:
            return True
        fs = _open(path, strict=False)
    except TrackmeterError:
        return False
    try:
        return any(not fs.getNode(key).empty() for key in _RIG_KEYS)
    finally:
        fs.release()


def _kalibr_camchain(path: Path, strict: bool = True) -> dict | None:
    """The file's contents when it is a Kalibr ``camchain.yaml`` (a mapping with ``cam0``), else
    None (not YAML PyYAML reads, e.g. OpenCV's ``!!opencv-matrix`` tags, or another mapping)."""
    if not path.is_file():
        return None
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return None
    data = _plain_yaml_data(text, path, strict)
    return data if data is not None and isinstance(data.get("cam0"), dict) else None


def without_directives(text: str) -> str:
    # OpenCV-style writers put a "%YAML:1.0" directive first, which PyYAML refuses.
    return "\n".join(line for line in text.splitlines() if not line.startswith("%"))


def pinhole_radtan_camera(entry: dict, distortion_key: str) -> Camera:
    """A camera from a Kalibr or EuRoC calibration entry: ``camera_model`` pinhole,
    ``intrinsics`` ``[fu, fv, cu, cv]``, ``resolution`` ``[w, h]`` and radial-tangential
    coefficients ``[k1, k2, p1, p2]`` under ``distortion_key`` (OpenCV's model and order).

    Raises:
        TrackmeterError: another camera or distortion model (equidistant, omni, ...), or a
            ``resolution`` that is not two whole numbers.
        KeyError, TypeError, ValueError: a missing or malformed entry.
    """
    model, distortion = entry.get("camera_model", "pinhole"), entry.get("distortion_model", "radtan")
    if model != "pinhole" or distortion not in ("radial-tangential", "radtan", "plumb_bob", "none"):
        raise TrackmeterError(f"camera model {model}/{distortion} is not supported (pinhole with "
                              "radial-tangential distortion is: OpenCV's model)")
    fu, fv, cu, cv = (float(x) for x in entry["intrinsics"])
    size = entry["resolution"]
    if not (isinstance(size, (list, tuple)) and len(size) == 2 and all(whole_pixels(x) is not None for x in size)):
        raise TrackmeterError(f"'resolution' must be two whole numbers of pixels [width, height], got {shown_value(size)}")
    width, height = (int(x) for x in size)
    dist = np.array([float(x) for x in entry.get(distortion_key) or [0.0, 0.0, 0.0, 0.0]])
    return Camera(width, height, np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]]), dist)


def _load_kalibr(camchain: dict, path: Path) -> StereoRig:
    """A stereo rig from Kalibr's ``camchain.yaml``: ``cam1``'s ``T_cn_cnm1`` (4x4) maps cam0
    points into cam1, ``p_cam1 = R p_cam0 + T``: OpenCV's ``R, T``."""
    cams = []
    try:
        if not isinstance(camchain.get("cam1"), dict):
            raise TrackmeterError("a Kalibr camchain needs cam0 and cam1 (a stereo calibration)")
        for name in ("cam0", "cam1"):
            try:
                cams.append(pinhole_radtan_camera(camchain[name], "distortion_coeffs"))
            except TrackmeterError as exc:
                raise TrackmeterError(f"{name}: Kalibr {exc}") from None
        try:
            T_c1_c0 = np.array(camchain["cam1"]["T_cn_cnm1"], dtype=float).reshape(4, 4)
        except (TypeError, ValueError):
            raise TrackmeterError("cam1: 'T_cn_cnm1' must be a 4x4 matrix of numbers (4 rows of 4)") from None
        return StereoRig(cams[0], cams[1], T_c1_c0[:3, :3], T_c1_c0[:3, 3], name=path.stem)
    except (KeyError, TypeError, ValueError) as exc:
        raise TrackmeterError(f"{path}: not a usable Kalibr camchain ({exc.__class__.__name__}: {exc})") from None
    except TrackmeterError as exc:
        raise TrackmeterError(f"{path}: {exc}") from None


def _middlebury_text(path: Path) -> tuple[str, bool] | None:
    """``(text, whole)``: the file's text (up to :data:`MIDDLEBURY_CALIB_MAX_BYTES`, a
    byte-order mark left out; ``whole`` when that is all of it) when it is a Middlebury
    ``calib.txt`` (its first line ``cam0=[...]``, blank and ``#`` comment lines aside), else None."""
    if not path.is_file():
        return None
    try:
        with path.open("rb") as f:
            head = f.read(MIDDLEBURY_CALIB_MAX_BYTES + 1)
        text = head[:MIDDLEBURY_CALIB_MAX_BYTES].decode("utf-8-sig")  # Windows editors write a byte-order mark
    except (OSError, UnicodeDecodeError):
        return None
    if not MIDDLEBURY_CALIB_START.match(text.lstrip()):
        return None
    return text, len(head) <= MIDDLEBURY_CALIB_MAX_BYTES


def _middlebury_calib(path: Path) -> dict[str, str] | None:
    """The file's ``key=value`` lines (keys lower-cased) when it is a Middlebury ``calib.txt``,
    else None.

    Raises:
        TrackmeterError: a key given twice, or a file too large to be one.
    """
    found = _middlebury_text(path)
    if found is None:
        return None
    text, whole = found
    if not whole:
        raise TrackmeterError(f"{path}: Middlebury calib: larger than {MIDDLEBURY_CALIB_MAX_BYTES // 1024} KiB: "
                              "a calib.txt is a dozen short lines")
    entries: dict[str, str] = {}
    first_line: dict[str, int] = {}
    for number, line in enumerate(text.splitlines(), 1):
        key, sep, value = line.partition("#")[0].partition("=")  # a hand-added comment is not a value
        key = key.strip().lower()
        if not sep:
            continue
        if key in entries:
            raise TrackmeterError(f"{path}: Middlebury calib: '{key}' given twice (lines {first_line[key]} and "
                                  f"{number})")
        entries[key], first_line[key] = value.strip(), number
    return entries


def _middlebury_matrix(entries: dict[str, str], key: str) -> np.ndarray:
    text = entries.get(key)
    if text is None:
        raise TrackmeterError(f"missing '{key}' (a camera matrix [f 0 cx; 0 f cy; 0 0 1])")
    try:
        rows = [[float(x) for x in row.split()] for row in text.strip().removeprefix("[").removesuffix("]").split(";")]
        K = np.array(rows, dtype=float)
    except ValueError:
        K = np.empty(0)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or not np.allclose(K[2], (0.0, 0.0, 1.0)) or K[1, 0] != 0.0:
        raise TrackmeterError(f"'{key}' must be a camera matrix [f 0 cx; 0 f cy; 0 0 1], got {shown_value(text)}")
    return K


def _middlebury_number(entries: dict[str, str], key: str) -> float | None:
    text = entries.get(key)
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise TrackmeterError(f"'{key}' must be a number, got {shown_value(text)}")
    return value


#: How far ``doffs`` may differ from ``cx1 - cx0`` (px): the files give both to three decimals.
MIDDLEBURY_DOFFS_TOLERANCE_PX = 0.01
#: A ``calib.txt`` is a dozen short lines: one larger than this is not read whole.
MIDDLEBURY_CALIB_MAX_BYTES = 64 * 1024
#: A ``dymax`` (the views' largest vertical disparity, px) past this is warned about: measured on
#: Tsukuba with its right image moved down, 0.25 px cost 12 % of the accepted points, 0.5 px 40 %.
MIDDLEBURY_DYMAX_WARN_PX = 0.25


def _load_middlebury(entries: dict[str, str], path: Path, image_size: tuple[int, int] | None) -> StereoRig:
    """A stereo rig from Middlebury's ``calib.txt`` (stereo datasets of 2014 and 2021).

    The views are rectified already: ``cam0``/``cam1`` are their camera matrices, no lens
    distortion, no rotation between them, the right camera ``baseline`` mm along +x, so OpenCV's
    ``R = I`` and ``T = (-baseline / 1000, 0, 0)`` m. Their principal points lie ``doffs = cx1 -
    cx0`` px apart (checked when given), so a pixel pair's own disparity ``d`` has the depth
    ``Z = baseline * f / (d + doffs)``, Middlebury's formula; the rig keeps the principal points
    apart (:class:`trackmeter.core.stereo.Rectification`). ``width``/``height`` give the size
    (else ``image_size``); a ``dymax`` past :data:`MIDDLEBURY_DYMAX_WARN_PX` is warned about;
    ``ndisp``, ``vmin``, ``vmax`` and the rest are not needed.
    """
    try:
        K0, K1 = _middlebury_matrix(entries, "cam0"), _middlebury_matrix(entries, "cam1")
        baseline_mm = _middlebury_number(entries, "baseline")
        if baseline_mm is None:
            raise TrackmeterError("missing 'baseline' (mm)")
        if baseline_mm <= 0.0:
            raise TrackmeterError(f"'baseline' must be positive (mm), got {baseline_mm:g}")
        doffs = _middlebury_number(entries, "doffs")
        if doffs is not None and abs((K1[0, 2] - K0[0, 2]) - doffs) > MIDDLEBURY_DOFFS_TOLERANCE_PX:
            raise TrackmeterError(f"'doffs' {doffs:g} is not cx1 - cx0 = {K1[0, 2] - K0[0, 2]:g} (the principal "
                                  "points' columns in cam0 and cam1)")
        width, height = _middlebury_number(entries, "width"), _middlebury_number(entries, "height")
        if width is None or height is None:
            if image_size is None:
                raise TrackmeterError("missing 'width'/'height' (the images' size, px)")
            width, height = image_size
        for key, value in (("width", width), ("height", height)):
            if not (whole_pixels(value) is not None and MIN_IMAGE_SIZE_PX <= value <= MAX_IMAGE_SIZE_PX):
                raise TrackmeterError(f"'{key}' must be a whole number of pixels from {MIN_IMAGE_SIZE_PX} to "
                                      f"{MAX_IMAGE_SIZE_PX}, got {value:g}")
        if not (K0[0, 0] == K0[1, 1] == K1[0, 0] == K1[1, 1] and K0[1, 2] == K1[1, 2] and K0[0, 1] == K1[0, 1] == 0.0):
            # A typing slip: Middlebury's rectified views share f and cy. The rig is then
            # rectified again (resampled), and disparity_px is no longer the pair's own.
            warnings.warn(f"{path}: Middlebury calib: cam0 and cam1 are not the matrices of a rectified pair (one "
                          "focal length f and principal row cy in both, no skew): the images are rectified again, "
                          "and disparities are the re-rectified images'", stacklevel=3)
        dymax = _middlebury_number(entries, "dymax")
        if dymax is not None and dymax > MIDDLEBURY_DYMAX_WARN_PX:
            # Middlebury's "imperfect" calibrations: the matching searches along a row, so points
            # are refused (low score, uncertain) the more, the further the rows are apart.
            warnings.warn(f"{path}: Middlebury calib: dymax={dymax:g}: the views' rows are up to {dymax:g} px apart "
                          "(an imperfect rectification); the matching assumes aligned rows and refuses more points "
                          "the further apart they are (Tsukuba with its rows 0.5 px apart: 40 % fewer, 1 px: 63 %)",
                          stacklevel=3)
        cams = [Camera(int(width), int(height), K) for K in (K0, K1)]
        return StereoRig(cams[0], cams[1], np.eye(3), np.array([-baseline_mm / 1000.0, 0.0, 0.0]), name=path.stem)
    except TrackmeterError as exc:
        raise TrackmeterError(f"{path}: Middlebury calib: {exc}") from None


#: A principal point farther than this fraction of the frames' width (height) from their centre
#: is warned about in a rig file that carries no image size (lenses put it within a few per cent).
OFF_CENTRE_WARN_FRACTION = 0.3


def _check_size_taken_from_frames(left: Camera, right: Camera, path: Path, why_taken: str, stacklevel: int) -> None:
    """For a rig file that carries no image size, whose cameras were given the frames': refuse
    a principal point outside the frames, and warn of one more than
    :data:`OFF_CENTRE_WARN_FRACTION` of them from their centre (``why_taken`` says why the
    frames' size was taken). Both mean a calibration made at another image size, which nothing
    else would tell: every point is then refused for reasons that do not name the rig.
    ``stacklevel``: the warning's, from here to :func:`load_rig`'s caller."""
    width, height = left.width, left.height
    for cam in (left, right):
        cx, cy = cam.K[0, 2], cam.K[1, 2]
        if not (0 <= cx <= width and 0 <= cy <= height):
            raise TrackmeterError(f"{path}: the principal point ({cx:.1f}, {cy:.1f}) lies outside the {width}x{height} "
                                  "px frames: calibrated for another image size")
        off_centre = max(abs(cx - (width - 1) / 2) / width, abs(cy - (height - 1) / 2) / height)
        if off_centre > OFF_CENTRE_WARN_FRACTION:
            # Inside the frames, yet near their edge: a 640x480 calibration on 384x288 frames
            # (cx 340.7 of 384) refused every point as "the images look swapped" (an outside probe).
            warnings.warn(f"{path}: the principal point ({cx:.1f}, {cy:.1f}) lies {off_centre:.0%} of the "
                          f"{width}x{height} px frames from their centre: calibrated for another image size? "
                          f"({why_taken}; the frames' is taken)", stacklevel=stacklevel)
            return


def _load_opencv_pair(path: Path, image_size: tuple[int, int] | None) -> StereoRig:
    folder = path.parent

    def partner(stem: str) -> Path:
        # OpenCV writes .yml, .yaml or .xml by the name it is given: the partner's own suffix
        # first, then the others.
        names = [stem + path.suffix] + [stem + s for s in (".yml", ".yaml", ".xml") if s != path.suffix]
        return next((folder / n for n in names if (folder / n).is_file()), folder / names[0])

    fs = _open(path)
    try:
        # One file holding both halves (M1 D1 M2 D2 and R T) needs no partner.
        whole = not fs.getNode("M1").empty() and not fs.getNode("R").empty()
        if whole:  # its own size, when it has one, before the frames' (a mismatch is then told)
            width, height = _image_size_scalar(fs, "image_width", path), _image_size_scalar(fs, "image_height", path)
            image_size = (width, height) if width is not None and height is not None else image_size
    finally:
        fs.release()
    if whole:
        intr, extr = path, path
    elif path.name.startswith("extrinsics"):
        intr, extr = partner("intrinsics"), path
    else:
        intr, extr = path, partner("extrinsics")
    for needed in (intr, extr):
        if needed != path and not needed.is_file():
            raise TrackmeterError(f"{path}: OpenCV's {path.stem} file needs its {needed.stem} file beside it "
                                  f"({needed}: no such file)")
    fi, fe = _open(intr), _open(extr)
    try:
        if image_size is None:
            raise TrackmeterError(f"{path}: OpenCV's intrinsics/extrinsics (M1 D1 M2 D2 R T) have no image size; "
                                  "give it (image_width, image_height)")
        width, height = image_size
        left = _camera(width, height, fi, "M1", "D1", intr)
        right = _camera(width, height, fi, "M2", "D2", intr)
        # load_rig -> _load_rig -> here -> the check
        _check_size_taken_from_frames(left, right, path, "OpenCV's intrinsics/extrinsics carry none", stacklevel=5)
        return StereoRig(left, right, _rotation(fe, extr), _matrix(fe, "T", extr).ravel(), name=folder.name)
    finally:
        fi.release()
        fe.release()


def save_rig(rig: StereoRig, path: str | Path, extra: dict[str, np.ndarray | float] | None = None) -> Path:
    """Write ``rig`` as OpenCV FileStorage YAML (XML or JSON for a ``.xml`` or ``.json`` name),
    atomically (temp file, then rename).

    ``extra`` adds keys such as ``E``, ``F`` or per-parameter standard deviations. The text is
    made in memory and written by :func:`write_files_atomic`: ``cv2.FileStorage`` writing a
    file itself does not report a failed write (a full disk left an empty rig file).

    Raises:
        TrackmeterError: the file could not be written (a full disk), the old one left as it was.
    """
    path = Path(path)
    # FileStorage writes the format its name's extension says: XML or JSON asked for by name
    # (`calibrate --out rig.xml`), YAML otherwise.
    kind = path.suffix.lower() if path.suffix.lower() in (".xml", ".json") else ".yaml"
    fs = cv2.FileStorage(kind, cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    try:
        fs.write("image_width", int(rig.left.width))
        fs.write("image_height", int(rig.left.height))
        fs.write("K1", rig.left.K)
        fs.write("D1", rig.left.dist.reshape(1, -1))
        fs.write("K2", rig.right.K)
        fs.write("D2", rig.right.dist.reshape(1, -1))
        fs.write("R", rig.R)
        fs.write("T", rig.T.reshape(3, 1))
        if rig.rms_px is not None:
            fs.write("rms_px", float(rig.rms_px))
        for key, value in (extra or {}).items():
            fs.write(key, np.asarray(value, dtype=float) if not np.isscalar(value) else float(cast(float, value)))
    except BaseException:
        fs.release()
        raise
    write_files_atomic({path: fs.releaseAndGetString().encode("utf-8")})
    return path
