"""Reading images and image sets from disk.

:func:`read_grey` reads any image OpenCV decodes (PNG, JPEG, PGM, TIFF, ...; 8 or 16 bit, 16-bit
files holding 10- to 16-bit data (:func:`data_bits`); grey, colour or with alpha) as an 8-bit
grey ``(H, W)`` array, the layout every matcher and tracker of
the project works on. :func:`expand_globs` and :func:`pair_stereo_paths` turn command-line
globs into an ordered list of left/right pairs.
"""

from __future__ import annotations

import contextlib
import glob
import re
import threading
import warnings
from pathlib import Path
from typing import Callable, Iterable, Iterator, Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from trackmeter.errors import TrackmeterError


_quiet_lock = threading.Lock()
_quiet_users = 0
_quiet_saved_level = 0


def _opencv_log_level() -> tuple[Callable[[], int], Callable[[int], object], int] | None:
    """OpenCV's log level ``(get, set, silent level)``: ``cv2.utils.logging`` in OpenCV 5,
    ``cv2.getLogLevel`` / ``cv2.setLogLevel`` (silent is 0) in OpenCV 4; None in a build with
    neither."""
    logging = getattr(getattr(cv2, "utils", None), "logging", None)
    if logging is not None:
        return logging.getLogLevel, logging.setLogLevel, int(logging.LOG_LEVEL_SILENT)
    if hasattr(cv2, "getLogLevel") and hasattr(cv2, "setLogLevel"):
        return cv2.getLogLevel, cv2.setLogLevel, 0  # type: ignore[attr-defined]
    return None


@contextlib.contextmanager
def _opencv_quiet() -> Iterator[None]:
    """OpenCV's own logging off while the block runs, then as it was. Threads may decode at
    once: the first to enter saves the level, the last to leave restores it."""
    global _quiet_users, _quiet_saved_level
    api = _opencv_log_level()
    if api is None:
        yield
        return
    get_level, set_level, silent = api
    with _quiet_lock:
        if _quiet_users == 0:
            _quiet_saved_level = get_level()
            set_level(silent)
        _quiet_users += 1
    try:
        yield
    finally:
        with _quiet_lock:
            _quiet_users -= 1
            if _quiet_users == 0:
                set_level(_quiet_saved_level)


def decode_image(path: str | Path) -> NDArray[np.generic]:
    """The image file as OpenCV decodes it, unchanged (any depth and channel count).

    The bytes are decoded with ``cv2.imdecode`` rather than ``cv2.imread`` because the latter
    prints its own warning on stderr for unreadable files, and with OpenCV's logging off
    because its decoders log too (a PNG cut short: "[ WARN:0@...] ... PNG input buffer is
    incomplete"); here the caller gets one :class:`TrackmeterError` instead.

    Raises:
        TrackmeterError: missing file, unreadable file, or a file that is not a decodable image.
    """
    path = Path(path)
    if path.is_dir():
        raise TrackmeterError(f"{path}: a folder, not an image file")
    if not path.is_file():
        raise TrackmeterError(f"{path}: no such image file")
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError as exc:
        raise TrackmeterError(f"{path}: cannot read: {exc.strerror or exc}") from None
    if _png_cut_short(data):
        # libpng prints its own "libpng error: ..." line for this on stderr, whatever OpenCV's
        # logging level: told here without decoding.
        raise TrackmeterError(f"{path}: not an image file OpenCV can decode (a PNG file cut short)")
    with _opencv_quiet():
        image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if image is None:
        raise TrackmeterError(f"{path}: not an image file OpenCV can decode")
    return image


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _png_cut_short(data: NDArray[np.uint8]) -> bool:
    """True for a PNG file (by its signature) without its closing IEND chunk anywhere: cut
    short. Bytes after the IEND chunk (some writers leave them) do not count against it."""
    if data[: len(_PNG_SIGNATURE)].tobytes() != _PNG_SIGNATURE:
        return False
    # A whole file ends in its IEND chunk (12 bytes): its tail says so without copying the
    # whole file, read once a frame; only a file without it there is searched throughout.
    return b"IEND" not in data[-64:].tobytes() and data.tobytes().rfind(b"IEND") < 0


#: The sample depths 16-bit files are told apart by (:func:`data_bits`).
SAMPLE_BITS = (10, 12, 14, 16)


def data_bits(images: Iterable[NDArray[np.generic]]) -> int:
    """How many low bits of 16-bit ``images`` hold the data: the smallest of
    :data:`SAMPLE_BITS` whose range holds their largest value; 8 when none is 16-bit.

    Many machine-vision cameras store 10-, 12- or 14-bit samples in 16-bit PNG or TIFF files as
    they are (a 12-bit image's values stay below 4096), not scaled up to the full 16-bit range
    as the PNG standard asks. Read as 16-bit such an image is black (at most 15 grey levels of
    256 for 12-bit data), so the depth is told from the values. The rule only changes images
    that would otherwise be that dark; decide it once per sequence or stereo pair (from
    several images, each with a lit target), so every frame is scaled alike.

    A float image of whole numbers (a float TIFF saved from integer data) counts as
    integer data too, from 8 bits up (:func:`_whole_number_max`); other float images are on
    [0, 1] and do not count.
    """
    largest16 = -1
    bits = 8
    for image in images:
        img = np.asarray(image)
        if img.dtype == np.uint16 and img.size:
            largest16 = max(largest16, int(img.max()))
        elif img.dtype in (np.float32, np.float64):
            whole = _whole_number_max(img)
            if whole is not None:
                bits = max(bits, _float_data_bits(whole))
    if largest16 >= 0:
        bits = max(bits, next(b for b in SAMPLE_BITS if largest16 < 2**b))
    return bits


def _float_data_bits(largest: float) -> int:
    """The sample depth of integer data stored as float whose largest value is ``largest``:
    the smallest of 8 and :data:`SAMPLE_BITS` that holds it (16 beyond)."""
    return next((b for b in (8, *SAMPLE_BITS) if largest < 2**b), 16)


def _whole_number_max(img: NDArray[np.floating]) -> float | None:
    """The largest value of a float image whose finite values are all whole numbers (integer
    data stored as float: a dark frame of it holds only 0 and 1), else None (an image on
    [0, 1], whose grey levels are fractions)."""
    finite = img[np.isfinite(img)]
    if finite.size == 0 or not np.array_equal(finite, np.round(finite)):
        return None
    return float(finite.max())


def read_grey(path: str | Path, bits: int | None = None) -> NDArray[np.uint8]:
    """Read an image file as 8-bit grey, (H, W) uint8 (:func:`decode_image`, :func:`to_grey_u8`).

    Colour is converted with OpenCV's luminance weights (``cvtColor``, BGR→GRAY), an alpha
    channel is dropped, 16-bit images keep the top 8 of their ``bits`` data bits (default:
    their own :func:`data_bits`) and float images (e.g. EXR) on [0, 1] are scaled to [0, 255]
    (highlights above 1 saturate); a float image of whole numbers is integer data, read as
    :func:`data_bits` says.

    Raises:
        TrackmeterError: missing file, unreadable file, or a file that is not a decodable image.
    """
    image = decode_image(path)
    return to_grey_u8(image, str(path), bits if bits is not None else data_bits([image]))


def read_grey_pair(left: str | Path, right: str | Path) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """:func:`read_grey` of a stereo pair, both 16-bit images scaled alike (their joint
    :func:`data_bits`)."""
    images = [decode_image(left), decode_image(right)]
    bits = joint_data_bits([(str(left), images[0]), (str(right), images[1])], "a pair is scaled alike")
    return to_grey_u8(images[0], str(left), bits), to_grey_u8(images[1], str(right), bits)


def joint_data_bits(named_images: Sequence[tuple[str, NDArray[np.generic]]], why: str, warn_from_bits: int = 2) -> int:
    """:func:`data_bits` of images read alike (a pair, a camera's frames), from ``(name,
    image)`` pairs; warns, saying ``why`` they are scaled alike, when their own depths differ
    by ``warn_from_bits`` or more: the joint scaling darkens the shallower ones by
    ``2**difference`` (4 bits: at most 15 grey levels of 256). Over frames of one camera, a
    smaller difference is a darker frame (``warn_from_bits`` 4); within a pair, a camera that
    may store fewer bits (2: a 10-bit left, a 12-bit right)."""
    own = [(data_bits([image]), name) for name, image in named_images if image.dtype != np.uint8]
    bits = max((b for b, _ in own), default=8)
    if own and bits - min(own)[0] >= warn_from_bits:
        (low, low_name), (high, high_name) = min(own), max(own)
        warnings.warn(f"{low_name} looks {low}-bit and {high_name} {high}-bit: all are read as {bits}-bit ({why}), "
                      f"so the {low}-bit ones are {2 ** (bits - low)}x darker", stacklevel=3)
    return bits


def to_grey_u8(image: NDArray[np.generic], name: str = "image", bits: int | None = None) -> NDArray[np.uint8]:
    """Convert a decoded image ((H,W), (H,W,1), (H,W,3) BGR or (H,W,4) BGRA; any depth) to 8-bit
    grey. A 16-bit image's data are its low ``bits`` bits (:func:`data_bits`; None: 16): its
    top 8 of them are kept, larger values saturate at 255. A float image is on [0, 1] unless it
    holds whole numbers (integer data, on the range of ``bits`` or its own, the larger)."""
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.dtype == np.uint16:
        shift = min(max(int(bits if bits is not None else 16), 8), 16) - 8
        img = np.minimum(img >> shift, 255).astype(np.uint8)
    elif img.dtype in (np.float32, np.float64):
        whole = _whole_number_max(img)
        if whole is not None and whole > 65535:
            raise TrackmeterError(f"{name}: float pixel values up to {whole:.6g}: expected [0, 1], or whole numbers "
                                  "up to 65535")
        # Whole numbers: integer data, on the range of ``bits`` (the pair's or sequence's, at
        # least its own); else [0, 1], where a high-dynamic-range image's highlights saturate.
        if whole is None:
            scale = 1.0
        else:
            own = _float_data_bits(whole)
            scale = float(2 ** max(own, int(bits) if bits is not None else own) - 1)
        img = np.clip(np.nan_to_num(img) * (255.0 / scale) + 0.5, 0, 255).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise TrackmeterError(f"{name}: unsupported pixel type {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
    elif img.ndim != 2:
        raise TrackmeterError(f"{name}: unsupported image layout {img.shape}")
    return np.ascontiguousarray(img)


def _natural_key(path: Path) -> list[object]:
    """Sort key that orders ``img2`` before ``img10``."""
    return [int(tok) if tok.isdigit() else tok for tok in re.split(r"(\d+)", str(path))]


def expand_globs(patterns: str | Iterable[str], what: str = "images") -> list[Path]:
    """Files matching one or more glob patterns (or plain paths), naturally sorted, no duplicates.

    A shell may already have expanded an unquoted glob into many paths; both forms work.

    Raises:
        TrackmeterError: a pattern matches no file.
    """
    if isinstance(patterns, str):
        patterns = [patterns]
    found: dict[Path, None] = {}
    for pattern in patterns:
        literal = Path(pattern).expanduser()
        matches = [Path(p) for p in glob.glob(str(literal))]
        matches = [p for p in matches if p.is_file()]
        if not matches and literal.is_file():  # a file name with glob characters such as '['
            matches = [literal]
        if not matches:
            raise TrackmeterError(f"no {what} match {pattern!r}")
        for p in matches:
            found[p] = None
    return sorted(found, key=_natural_key)


def _frame_number(path: Path) -> int | None:
    """The last run of digits in the file's stem (``left07.jpg`` → 7), or None."""
    digits = re.findall(r"\d+", path.stem)
    return int(digits[-1]) if digits else None


def _number_span(numbers: Sequence[int | None]) -> str:
    """``"1000-1013"``: the range of a side's frame numbers (all there: the caller pairs by them)."""
    known = [n for n in numbers if n is not None]
    return f"{min(known)}-{max(known)}" if len(set(known)) > 1 else str(known[0])


def _why_not_numbered(left: Sequence[Path], nl: Sequence[int | None], right: Sequence[Path],
                      nr: Sequence[int | None]) -> str:
    """What stops pairing by number when most names carry one: the names without a number, or
    a number two names on one side share; empty when no name has one."""
    if all(n is None for n in (*nl, *nr)):
        return ""
    without = [p.name for p, n in (*zip(left, nl), *zip(right, nr)) if n is None]
    if without:
        more = ", ..." if len(without) > 3 else ""
        return f" ({', '.join(without[:3])}{more} {'has' if len(without) == 1 else 'have'} none)"
    for side, paths, numbers in (("left", left, nl), ("right", right, nr)):
        seen: dict[int | None, str] = {}
        for p, n in zip(paths, numbers):
            if n in seen:
                return f" ({side}: {seen[n]} and {p.name} carry the same number, {n})"
            seen[n] = p.name
    return ""


def pair_stereo_paths(left: Sequence[Path], right: Sequence[Path]) -> list[tuple[Path, Path]]:
    """Pair left and right image files.

    When every file name carries a number (``left07.png`` / ``right07.png``) and the numbers
    are unique on each side, files pair by number and unmatched files are left out; otherwise
    they pair in sorted order, which requires equal counts.

    Raises:
        TrackmeterError: no pairs, or unequal counts without numbers to pair by.
    """
    left, right = list(left), list(right)
    nl = [_frame_number(p) for p in left]
    nr = [_frame_number(p) for p in right]
    numbered = (
        None not in nl and None not in nr and len(set(nl)) == len(nl) and len(set(nr)) == len(nr)
    )
    if numbered:
        by_number = dict(zip(nr, right))
        pairs = [(lp, by_number[n]) for lp, n in zip(left, nl) if n in by_number]
        if not pairs:
            raise TrackmeterError(f"no left and right image share a frame number to pair by (left {_number_span(nl)}, "
                                  f"right {_number_span(nr)}): rename them so that a pair's names carry one number")
        paired = {n for n in nl if n in by_number}
        alone = [p.name for p, n in (*zip(left, nl), *zip(right, nr)) if n not in paired]
        if alone:
            warnings.warn(f"{len(alone)} image(s) without a partner of the same frame number left out: "
                          f"{', '.join(alone[:4])}{', ...' if len(alone) > 4 else ''}", stacklevel=2)
        return pairs
    if len(left) != len(right):
        why = _why_not_numbered(left, nl, right, nr)
        names = "not every name carries a frame number of its own" if why else "their names carry no frame numbers"
        raise TrackmeterError(f"{len(left)} left and {len(right)} right images, and {names} to pair by{why}")
    if not left:
        raise TrackmeterError("no image pairs")
    return list(zip(left, right))
