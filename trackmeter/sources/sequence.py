"""``seq:DIR``: play a stereo sequence folder (DESIGN.md section 6, EuRoC layout)."""

from __future__ import annotations

import collections
import os
import warnings as _warnings
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from trackmeter.core.stereo import StereoRig
from trackmeter.core.transforms import transform_from_pose
from trackmeter.data.model import Model
from trackmeter.data.images import data_bits, decode_image, read_grey, to_grey_u8
from trackmeter.data.sequence import SequenceIndex, index_sequence, seconds_to_ns, sequence_data_bits
from trackmeter.errors import TrackmeterError, counted
from trackmeter.sources.base import NO_RATE_INTERVAL_S, GroundTruth, Source, StereoFrame
from trackmeter.sources.pacing import Pacer


class SequenceSource(Source):
    """Frames of a sequence folder, paired left/right by nearest timestamp.

    Args:
        directory: the folder (``DIR`` or an EuRoC ``DIR`` holding ``mav0/``).
        rig: overrides the folder's ``rig.yaml`` (a real EuRoC folder has none: rig is None
            unless given).
        realtime: sleep so frames come at their recorded times; else as fast as read.
        loop: start again after the last frame. Frame indices and timestamps keep increasing
            across loops (each loop is shifted by the sequence's span plus one frame
            interval), so downstream filters never see time go backwards.
        tolerance_s: left/right pairing tolerance (default: a quarter frame interval).
        read_rig, read_model: False leaves the folder's ``rig.yaml`` (``model.yaml``) unread:
            the user brings another, or needs none. With ``rig`` given, ``rig.yaml`` is not read.
        model_optional: a ``model.yaml`` that cannot be read is warned about and left out
            (``model`` None) instead of refusing the folder: the caller can run without it.

    Attributes:
        index: the :class:`SequenceIndex` (paths, times, truth).
        model: the folder's ``model.yaml`` as a :class:`Model`, or None.
        skipped: images not played (missing, unpaired, unreadable rows or files, pairs of
            another image size), counted.
        image_bits: the sample depth of its 16-bit images (8 for 8-bit ones), the same for
            every frame.
        warning: one line saying what was skipped and why, or None when nothing was.
    """

    def __init__(
        self,
        directory: str | Path,
        rig: StereoRig | None = None,
        realtime: bool = False,
        loop: bool = False,
        tolerance_s: float | None = None,
        read_rig: bool = True,
        read_model: bool = True,
        model_optional: bool = False,
    ) -> None:
        self.index: SequenceIndex = index_sequence(
            directory, tolerance_s, read_rig=read_rig and rig is None, read_model=read_model,
            model_optional=model_optional,
        )
        self.rig = rig if rig is not None else self.index.rig
        self.rate_hz = self.index.rate_hz
        self.model: Model | None = self.index.model
        self._cuts = frozenset(self.index.cuts)  # where a recorded scene jumps (cuts.csv)
        self.realtime = realtime
        self.loop = loop
        self._skipped_on_read = 0
        self._read_errors: list[str] = []
        self._skipped_for_size = 0
        self._size_errors: list[str] = []
        self._skipped_positions: set[int] = set()  # counted once across loops and restarts
        self._deeper: dict[Path, str] = {}  # images deeper than the sequence's depth: why, by path
        self._pacer = Pacer()
        self._pos = 0
        self._loops = 0
        self._count = 0
        n = len(self.index)
        # One pair has no rate: its passes are NO_RATE_INTERVAL_S apart (0 repeated its time).
        dt = 1.0 / self.rate_hz if self.rate_hz else NO_RATE_INTERVAL_S
        self._period_s = float(self.index.t_s[-1] - self.index.t_s[0]) + dt if n else 0.0
        # The same in whole nanoseconds for the stamps (float seconds hold EuRoC's to 238 ns).
        t_ns = self.index.t_ns
        self._period_ns = int(t_ns[-1] - t_ns[0]) + seconds_to_ns(dt) if len(t_ns) == n and n else 0
        self._frame_size: tuple[int, int] | None = None
        self._size_problem: str | None = None
        self._size_scanned = False
        self._image_bits: tuple[int, int] | None = None
        warning = self.warning
        if warning:
            # A warning that starts with a file of the folder names the folder already.
            named = warning.startswith(f"{Path(directory)}{os.sep}")
            _warnings.warn(warning if named else f"{directory}: {warning}", stacklevel=2)

    @property
    def image_bits(self) -> tuple[int, int]:
        """The sample depths the folder's left and right images are read with
        (:func:`sequence_data_bits`, decided on first use): 8 for 8-bit images, 10-16 for
        16-bit ones."""
        if self._image_bits is None:
            self._image_bits = sequence_data_bits(self.index)
        return self._image_bits

    @property
    def skipped(self) -> int:
        return self.index.skipped + self._skipped_on_read + self._skipped_for_size

    @property
    def warning(self) -> str | None:
        parts = list(self.index.warnings)
        if self._skipped_on_read:
            parts.append(f"{self._skipped_on_read} pair(s) with an unreadable image skipped ({self._read_errors[-1]})")
        if self._skipped_for_size:
            parts.append(f"{self._skipped_for_size} pair(s) of another image size skipped ({self._size_errors[-1]})")
        if self._deeper:
            parts.append(f"{len(self._deeper)} image(s) deeper than their camera's {_bits_text(self.image_bits)} read at their "
                         f"own depth ({list(self._deeper.values())[-1]})")
        # Each part counts in its own unit (images, rows, pairs): no total in front of them.
        return "; ".join(parts) if parts else None

    def __len__(self) -> int:
        return len(self.index)

    @property
    def frame_size(self) -> tuple[int, int] | None:
        """``(width, height)`` px of the sequence's frames (decided once), or None when no pair
        plays: the size most of three pairs spread over it have (the first pair whose images
        read and agree from its start, its middle and its end; a tie goes to the earliest). A
        first pair of another size, in one camera or both, was taken for the sequence's size,
        and the rig was blamed for all the others."""
        if self._frame_size is None and not self._size_scanned:
            self._size_scanned = True  # a folder where no pair plays is not read through twice
            n = len(self.index)
            starts = sorted({0, n // 2, n - 1}) if n else []
            sizes: list[tuple[int, int]] = []
            for k, start in enumerate(starts):
                end = starts[k + 1] if k + 1 < len(starts) else n
                size = next((sz for pos in range(start, end) if (sz := self._pair_size(pos)) is not None), None)
                if size is not None:
                    sizes.append(size)
            if sizes:
                self._frame_size = collections.Counter(sizes).most_common(1)[0][0]  # ties: the first seen
        return self._frame_size

    @property
    def start_t_s(self) -> float | None:
        """Time of the folder's first stereo pair, s (a pair skipped at read leaves a later
        first frame), None when it has none."""
        return float(self.index.t_s[0]) if len(self.index) else None

    @property
    def frame_size_problem(self) -> str | None:
        """Where :attr:`frame_size` is None because no pair plays: the first pair's problem
        (an image that does not read, or two images of different sizes); None otherwise."""
        return self._size_problem if self.frame_size is None else None

    def _pair_size(self, pos: int) -> tuple[int, int] | None:
        """``(width, height)`` of the ``pos``-th pair when both its images read and agree; the
        first problem met is kept for :attr:`frame_size_problem`."""
        left, right = self.index.left_paths[pos], self.index.right_paths[pos]
        try:
            shape = read_grey(left, self.image_bits[0]).shape[:2]
            other = read_grey(right, self.image_bits[1]).shape[:2]
        except TrackmeterError as exc:
            self._size_problem = self._size_problem or str(exc)
            return None
        if other != shape:  # read() skips it too
            self._size_problem = self._size_problem or (f"{left} is {shape[1]}x{shape[0]} px, "
                                                        f"{right} {other[1]}x{other[0]} px")
            return None
        return int(shape[1]), int(shape[0])

    @property
    def has_truth(self) -> bool:
        return self.index.truth is not None and bool(self.index.truth.valid.any())

    @property
    def truth_problem(self) -> str | None:
        """Why the folder's ground truth is of no use: its file did not read, or no row gives a
        whole pose (each warned at open); None otherwise."""
        return self.index.truth_problem

    @property
    def n_frames(self) -> int:
        """Stereo pairs in one pass of the folder (as :attr:`Simulator.n_frames`)."""
        return len(self.index)

    def truth_at(self, position: int) -> GroundTruth | None:
        """Ground truth of the ``position``-th pair of the folder, or None."""
        truth = self.index.truth
        if truth is None or not truth.valid[position]:
            return None
        return GroundTruth(
            T_cam_body=transform_from_pose(truth.position_m[position], truth.quat_wxyz[position]),
            velocity_cam_m_s=truth.velocity_cam_m_s[position].copy(),
            omega_body_rad_s=truth.omega_body_rad_s[position].copy(),
        )

    def read(self) -> StereoFrame | None:
        for _ in range(len(self.index) + 1):
            if self._pos >= len(self.index):
                if not self.loop:
                    return None
                self._pos = 0
                self._loops += 1
                self._cut = True
                self._pacer.reset()
            pos = self._pos
            self._pos += 1
            try:
                left = self._read_grey(self.index.left_paths[pos], self.image_bits[0])
                right = self._read_grey(self.index.right_paths[pos], self.image_bits[1])
            except TrackmeterError as exc:
                gone = self._removed_folder(pos)
                if gone is not None:  # not one bad file: every pair to come would be skipped
                    raise TrackmeterError(f"{gone[0]}: {gone[1]} while the sequence played, after "
                                          f"{counted(self._count, 'pair')}") from None
                if pos not in self._skipped_positions:
                    self._skipped_positions.add(pos)
                    # The message first: another thread may read ``warning`` in between.
                    self._read_errors.append(str(exc))
                    self._skipped_on_read += 1
                self._cut = self._cut or pos in self._cuts  # the scene's jump is the next frame's
                continue
            mismatch = self._size_mismatch(pos, left.shape, right.shape)
            if mismatch is not None:
                # A truncated or foreign image in a long recording is no frame of this rig (its
                # calibration holds for one image size): skip it like an unreadable one, counted
                # and named, rather than end the run on it or track garbage.
                if pos not in self._skipped_positions:
                    self._skipped_positions.add(pos)
                    self._size_errors.append(mismatch)
                    self._skipped_for_size += 1
                self._cut = self._cut or pos in self._cuts
                continue
            t = float(self.index.t_s[pos]) + self._loops * self._period_s
            if self.realtime:
                self._pacer.wait(t)
            frame = StereoFrame(index=self._count, t_s=t, left=left, right=right, truth=self.truth_at(pos),
                                cut=self._take_cut() or pos in self._cuts, stamp_ns=self._stamp_ns(pos))
            self._count += 1
            return frame
        return None  # a whole pass without one playable pair: a loop would spin for ever

    def _stamp_ns(self, pos: int) -> int | None:
        """Pair ``pos``'s file timestamp, ns, moved on by the passes played as ``t_s`` is; None
        where the index holds no integer stamps."""
        if len(self.index.t_ns) != len(self.index):
            return None
        return int(self.index.t_ns[pos]) + self._loops * self._period_ns

    def _removed_folder(self, pos: int) -> tuple[Path, str] | None:
        """The outermost folder of pair ``pos``'s images that is gone (removed, or moved) or
        holds no file any more (its images deleted), and which; None when both are there
        with files in them."""
        for path in (self.index.left_paths[pos], self.index.right_paths[pos]):
            folder = path.parent
            if not folder.is_dir():
                while not folder.parent.is_dir():
                    folder = folder.parent
                return folder, "removed or moved"
            if not path.exists() and next(os.scandir(folder), None) is None:
                return folder, "emptied of its images"
        return None

    def _read_grey(self, path: Path, bits: int) -> NDArray[np.uint8]:
        """One image as 8-bit grey at its camera's sample depth ``bits``; an image deeper than
        that (a 16-bit file among 8-bit ones) at its own, and noted: at its camera's it would
        saturate (a full-range 16-bit frame read as 8-bit is 90 % white)."""
        image = decode_image(path)
        if image.dtype != np.uint8:
            own = data_bits([image])
            if own > bits:
                self._deeper[path] = f"{path} is {own}-bit"
                bits = own
        return to_grey_u8(image, str(path), bits)

    def _size_mismatch(self, pos: int, left_shape: tuple[int, ...], right_shape: tuple[int, ...]) -> str | None:
        """Why the ``pos``-th pair is not of this sequence's image size, or None when it is."""
        left_path, right_path = self.index.left_paths[pos], self.index.right_paths[pos]
        if left_shape != right_shape:
            return (f"{left_path} is {left_shape[1]}x{left_shape[0]} px, {right_path} "
                    f"{right_shape[1]}x{right_shape[0]} px")
        size = self.frame_size
        if size is not None and (left_shape[1], left_shape[0]) != size:
            return f"{left_path} is {left_shape[1]}x{left_shape[0]} px, the sequence's {size[0]}x{size[1]} px"
        return None

    def resume(self) -> None:
        self._pacer.reset()

    def restart(self) -> None:
        self._pos = 0
        self._loops = 0
        self._count = 0
        self._cut = True
        self._pacer.reset()


__all__ = ["SequenceSource"]


def _bits_text(bits: tuple[int, int]) -> str:
    """``"12 bits"``, or ``"10 / 12 bits"`` (left / right) when the cameras differ."""
    return f"{bits[0]} bits" if bits[0] == bits[1] else f"{bits[0]} / {bits[1]} bits"
