"""``video:LEFT,RIGHT``, ``camera:I,J`` and ``camera:I``: stereo frames through OpenCV's VideoCapture.

Two files or devices give the left and right images; one side-by-side stereo device
(``camera:I``) delivers both in one frame, left half and right half. Colour is converted to
8-bit grey. Video files carry their frame rate; frame i is stamped ``i / fps`` (the nominal
time: container timestamps differ between the two files and between backends). Cameras are
stamped with the wall clock (monotonic, from the first frame), taken after both grabs.
"""

from __future__ import annotations

import os
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from trackmeter.core.stereo import StereoRig
from trackmeter.errors import TrackmeterError, counted
from trackmeter.sources.base import NO_RATE_INTERVAL_S, Source, StereoFrame
from trackmeter.sources.pacing import Pacer


def _grey(image: NDArray[Any]) -> NDArray[np.uint8]:
    if image.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        image = cv2.cvtColor(image, code) if image.shape[2] in (3, 4) else image[:, :, 0]
    if image.dtype != np.uint8:
        image = (image >> 8).astype(np.uint8) if image.dtype == np.uint16 else image.astype(np.uint8)
    return np.ascontiguousarray(image)


def _opencv_name(path: Path) -> str:
    """``path`` as OpenCV's binding must get it: the file name's own bytes read as UTF-8 (the
    binding passes a string's UTF-8 bytes on), never Python's surrogate escapes, on which
    OpenCV crashes the process (a name that is not UTF-8, or a non-ASCII one under a C locale).

    Raises:
        TrackmeterError: the name's bytes are not UTF-8 (OpenCV cannot be given it).
    """
    try:
        return os.fsencode(path).decode("utf-8")
    except UnicodeDecodeError:
        raise TrackmeterError(f"{path}: the file's name is not UTF-8, which OpenCV cannot open: rename it") from None


#: Reads :attr:`VideoSource.frame_size` makes for a frame that decodes (a file whose first
#: hundred frames are all spoilt is taken to have none; at its end each read fails at once).
SIZE_PROBE_FRAMES = 100


class VideoSource(Source):
    """Stereo frames from two video files.

    Args:
        left, right: video files OpenCV can decode (same frame count, frame rate and size:
            frames pair by position; other counts or rates are warned about).
        rig: the rig of the cameras that recorded them (videos carry none).
        realtime: play at the file's frame rate; else as fast as decoded.
        loop: start again at the end (timestamps keep increasing).

    Raises:
        TrackmeterError: a file that is missing, a folder, the same file twice, or one that
            OpenCV cannot open.
    """

    def __init__(self, left: str | Path, right: str | Path, rig: StereoRig | None = None,
                 realtime: bool = False, loop: bool = False) -> None:
        self.paths = (Path(left), Path(right))
        for p in self.paths:
            if p.is_dir():
                raise TrackmeterError(f"{p}: a folder, not a video file (a sequence folder plays as seq:DIR)")
            if not p.is_file():
                raise TrackmeterError(f"{p}: no such video file")
        if os.path.samefile(*self.paths):  # a hard link too, which resolve() leaves apart
            raise TrackmeterError(f"video: LEFT and RIGHT are the same file ({self.paths[0]}): a stereo pair needs both cameras' videos")
        self.rig = rig
        self.realtime = realtime
        self.loop = loop
        self._caps = [self._open(p) for p in self.paths]
        rates = [float(cap.get(cv2.CAP_PROP_FPS) or 0.0) for cap in self._caps]
        self.rate_hz = rates[0] if rates[0] > 0 else None
        counts = [int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0) for cap in self._caps]
        problems = []
        # Frames pair by position: files at other rates pair frames of other times.
        if min(rates) > 0 and abs(rates[0] - rates[1]) > 1e-3 * max(rates):
            problems.append(f"the frame rates differ ({self._label(0)}: {rates[0]:.4g} Hz, "
                            f"{self._label(1)}: {rates[1]:.4g} Hz): frames pair by position, not by time")
        if min(counts) > 0 and counts[0] != counts[1]:
            # The longer file's tail is never played.
            problems.append(f"the videos differ in length ({self._label(0)}: {counts[0]} frames, "
                            f"{self._label(1)}: {counts[1]}): the stream ends with the shorter")
        self._problems = problems
        # The frames both headers count, 0 when unknown: a read that fails before it is one bad
        # frame (OpenCV decodes those after it), skipped; one at it is the end.
        self._expected = min(counts) if min(counts) > 0 else 0
        self._undecoded: list[tuple[int, int | None]] = []  # (position, file 0/1 or None: both) on the first pass
        self._short_by = 0  # frames the first pass ended before the count (a file cut short)
        self._ran_out_first: int | None = None  # the file (0 left, 1 right) that ran out while the other read
        self._delivered = 0  # pairs delivered on this pass
        self._looped = False
        #: One line on what does not match between the files and, as playing finds them, the
        #: frames that did not decode (None when nothing found).
        self.warning: str | None = "; ".join(problems) or None
        if self.warning:
            warnings.warn(self.warning, stacklevel=2)
        self._pacer = Pacer()
        self._count = 0
        self._pos = 0
        self._t_offset = 0.0
        self._last_t = -np.inf
        self._frame_size: tuple[int, int] | None = None
        self._frame_size_read = False  # None is an answer too: the files are not read again

    @property
    def frame_size(self) -> tuple[int, int] | None:
        """``(width, height)`` px of the left file's first frame that decodes (the right file's
        when the left has none: :meth:`read` delivers pairs of one size only), decoded once by
        a capture of its own (the stream is not disturbed), or None when neither has such a
        frame. Decoded rather than taken from ``CAP_PROP_FRAME_WIDTH``: the size of what
        :meth:`read` delivers.

        Raises:
            TrackmeterError: the right file's first frame has another size (no stereo pair).
        """
        if not self._frame_size_read:
            sizes = [self._first_frame_size(path) for path in self.paths]
            if None not in sizes and sizes[0] != sizes[1]:
                raise TrackmeterError(self._size_mismatch(*sizes))  # type: ignore[arg-type]
            self._frame_size = sizes[0] or sizes[1]
            self._frame_size_read = True
        return self._frame_size

    def _first_frame_size(self, path: Path) -> tuple[int, int] | None:
        """The size of the first frame of ``path`` that decodes: a spoilt first frame is skipped
        as :meth:`read` skips it (left unknown, the rig's size went unchecked and every frame
        failed in the tracker). None after :data:`SIZE_PROBE_FRAMES` reads."""
        cap = self._open(path)
        try:
            for _ in range(SIZE_PROBE_FRAMES):
                ok, image = cap.read()
                if ok and image is not None:
                    return int(image.shape[1]), int(image.shape[0])
        finally:
            cap.release()
        return None

    def _size_mismatch(self, left: tuple[int, int], right: tuple[int, int]) -> str:
        return (f"left and right videos differ in frame size: {self._label(0)} is {left[0]}x{left[1]} px, "
                f"{self._label(1)} is {right[0]}x{right[1]} px")

    @staticmethod
    def _open(path: Path) -> cv2.VideoCapture:
        # FFmpeg prints its own errors (e.g. "moov atom not found", "No JPEG data found in
        # image" at level 8) above the one line that says what failed or was skipped: quiet
        # (-8, AV_LOG_QUIET). A user's own setting wins.
        os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
        cap = cv2.VideoCapture(_opencv_name(path))
        if not cap.isOpened():
            cap.release()
            raise TrackmeterError(f"{path}: OpenCV cannot open this video file")
        return cap

    def read(self) -> StereoFrame | None:
        while True:
            ok_l, left = self._caps[0].read()
            ok_r, right = self._caps[1].read()
            ok_l, ok_r = ok_l and left is not None, ok_r and right is not None
            if (ok_l and ok_r) or self._pos >= self._expected:
                break
            # Both files step on together, so the pairs stay matched; the frame's time is skipped.
            if not self._looped and all(pos != self._pos for pos, _ in self._undecoded):  # once, across restarts
                self._undecoded.append((self._pos, None if not (ok_l or ok_r) else 0 if not ok_l else 1))
            self._pos += 1
        if not (ok_l and ok_r):
            self._end_of_pass()
            if not self.loop or self._pos == 0:
                return None
            self._t_offset = self._last_t + (1.0 / self.rate_hz if self.rate_hz else NO_RATE_INTERVAL_S)
            self._rewind()
            self._pacer.reset()
            self._cut = True
            return self.read()
        # Without a rate, frames are NO_RATE_INTERVAL_S apart, as between loop passes and as the
        # engine assumes (they were a second apart: speeds 25 times too small, playback at 1 Hz).
        t = self._pos * (1.0 / self.rate_hz if self.rate_hz else NO_RATE_INTERVAL_S)
        t += self._t_offset
        self._pos += 1
        self._last_t = t
        left, right = _grey(left), _grey(right)
        if left.shape != right.shape:
            raise TrackmeterError(self._size_mismatch(left.shape[::-1], right.shape[::-1]))
        if self.realtime:
            self._pacer.wait(t)
        frame = StereoFrame(index=self._count, t_s=t, left=left, right=right, cut=self._take_cut())
        self._count += 1
        self._delivered += 1
        if self._undecoded and not self._looped:
            self._update_warning()
        return frame

    def _end_of_pass(self) -> None:
        """At the end of the files: the failed reads that ran on to the end are a file cut
        short, not bad frames; said once, on the first pass."""
        if self._looped:
            return
        ran_out = set()
        while self._undecoded and self._undecoded[-1][0] == self._expected - 1 - self._short_by:
            ran_out.add(self._undecoded.pop()[1])
            self._short_by += 1
        # One file ran out while the other still read: cut short, or frames lost inside it
        # (a damaged file, whose broken frames the decoder skips without a failed read).
        self._ran_out_first = next(iter(ran_out)) if len(ran_out) == 1 and None not in ran_out else None
        self._update_warning()
        self._looped = True

    def _label(self, which: int) -> str:
        """File ``which`` (0 left, 1 right) as a message names it: its name, or its path when
        both files have the same name (``L/cam.avi``, ``R/cam.avi``)."""
        same = self.paths[0].name == self.paths[1].name
        return str(self.paths[which]) if same else self.paths[which].name

    def _update_warning(self) -> None:
        parts = list(self._problems)
        if self._undecoded:
            shown = [f"{self._label(which)}'s frame {pos} did not decode" if which is not None
                     else f"frame {pos} did not decode in either file" for pos, which in self._undecoded[:3]]
            more = len(self._undecoded) - len(shown)
            parts.append(f"{counted(len(self._undecoded), 'frame pair')} skipped: {', '.join(shown)}"
                         + (f" and {more} more" if more else ""))
        # A frame short in both files is a header's estimate (FFmpeg counts some containers by
        # duration); one file short while the other still read lacks that frame, by one too.
        if self._short_by >= 1 and self._ran_out_first is not None:
            short, other = self._label(self._ran_out_first), self._label(1 - self._ran_out_first)
            parts.append(f"the stream ended after {self._delivered} of the {self._expected} frame pairs the files count: "
                         f"{short} ran out {counted(self._short_by, 'frame')} before {other}, cut short or with frames "
                         "lost inside it (a damaged file), after which every pair is out of step by as many frames")
        elif self._short_by >= 2:
            parts.append(f"the stream ended after {self._delivered} of the {self._expected} frame pairs the files count "
                         f"(a file cut short?)")
        self.warning = "; ".join(parts) or None

    def _rewind(self) -> None:
        for cap in self._caps:
            cap.release()
        self._caps = [self._open(p) for p in self.paths]
        self._pos = 0
        self._delivered = 0

    def resume(self) -> None:
        self._pacer.reset()

    def restart(self) -> None:
        self._rewind()
        self._cut = True
        self._count = 0
        self._t_offset = 0.0
        self._last_t = -np.inf
        self._pacer.reset()

    def close(self) -> None:
        for cap in self._caps:
            cap.release()


class CameraSource(Source):
    """Live stereo frames from two devices (``camera:I,J``) or one side-by-side device (``camera:I``).

    Args:
        devices: one device index (side-by-side: left half, right half) or two (left, right).
        rig: the calibrated rig of these cameras.

    Raises:
        TrackmeterError: a device that cannot be opened or delivers no frame.
    """

    def __init__(self, devices: tuple[int, ...], rig: StereoRig | None = None) -> None:
        if len(devices) not in (1, 2):
            raise TrackmeterError(f"camera: give one side-by-side device or two devices, got {len(devices)}")
        self.devices = tuple(int(d) for d in devices)
        self.rig = rig
        self._caps: list[cv2.VideoCapture] = []
        for d in self.devices:
            cap = _open_device(d)
            if cap is None:
                self.close()
                raise TrackmeterError(f"camera {d} cannot be opened (no such device, or it is busy)")
            self._caps.append(cap)
        fps = float(self._caps[0].get(cv2.CAP_PROP_FPS) or 0.0)
        self.rate_hz = fps if fps > 0 else None
        self._count = 0
        self._t0: float | None = None
        self._frame_size: tuple[int, int] | None = None

    @property
    def frame_size(self) -> tuple[int, int]:
        """``(width, height)`` px of one image (half the device's width when side by side),
        from a frame grabbed once and dropped: what the device delivers, not what it reports."""
        if self._frame_size is None:
            left, _, _ = self._grab()
            self._frame_size = (int(left.shape[1]), int(left.shape[0]))
        return self._frame_size

    def read(self) -> StereoFrame | None:
        left, right, t_now = self._grab()
        if self._t0 is None:
            self._t0 = t_now
        frame = StereoFrame(index=self._count, t_s=t_now - self._t0, left=left, right=right)
        self._count += 1
        return frame

    def _grab(self) -> tuple[NDArray[np.uint8], NDArray[np.uint8], float]:
        """One stereo pair (left, right grey images) and its monotonic time, s."""
        for cap in self._caps:
            cap.grab()  # grab both before decoding: the two exposures stay as close as possible
        t_now = time.monotonic()
        images = []
        for d, cap in zip(self.devices, self._caps):
            ok, img = cap.retrieve()
            if not ok or img is None:
                raise TrackmeterError(f"camera {d} delivered no frame")
            images.append(_grey(img))
        if len(images) == 1:
            width = images[0].shape[1]
            if width % 2:
                raise TrackmeterError(f"camera {self.devices[0]}: side-by-side frame has an odd width {width}")
            left, right = images[0][:, : width // 2].copy(), images[0][:, width // 2 :].copy()
        else:
            left, right = images
            if left.shape != right.shape:
                raise TrackmeterError(f"cameras {self.devices} deliver different sizes: {left.shape} vs {right.shape}")
        return left, right, t_now

    def close(self) -> None:
        for cap in self._caps:
            cap.release()
        self._caps = []


def _open_device(index: int) -> cv2.VideoCapture | None:
    # A device node that does not exist makes OpenCV print backend warnings; check first on Linux.
    if sys.platform.startswith("linux") and not Path(f"/dev/video{index}").exists():
        return None
    cap = cv2.VideoCapture(index)
    if not cap.isOpened():
        cap.release()
        return None
    return cap
