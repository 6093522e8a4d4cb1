"""Stereo sequence folders in the EuRoC ASL layout (DESIGN.md section 6): write and index.

::

    DIR/rig.yaml                      stereo rig (trackmeter.data.rigfile), optional
    DIR/cam0/data.csv                 "#timestamp [ns],filename"
    DIR/cam0/data/<ns>.png            left image, 8-bit grey (colour is converted on read)
    DIR/cam1/data.csv, DIR/cam1/data/<ns>.png
    DIR/groundtruth.tum               optional: T_cam_body at the frame times (TUM format)
    DIR/groundtruth.csv               optional: t,x,y,z,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz
    DIR/model.yaml                    optional: model points in the body frame

Real EuRoC folders (``DIR/mav0/cam0/...`` with a ``sensor.yaml`` per camera and no
``rig.yaml``) are indexed too; their rig comes from the two ``sensor.yaml`` files when they
hold a pinhole radial-tangential calibration, else it is unknown (None) unless the caller gives one.
With that layout ``rig.yaml``, ``model.yaml`` and ``groundtruth.*`` are looked for in ``DIR``
first, then in ``DIR/mav0`` (:func:`find_sequence_file`, also used by ``evaluate --truth DIR``).
In place of ``rig.yaml`` a folder may carry OpenCV's stereo sample pair (``intrinsics.yml`` +
``extrinsics.yml``); a rig file without an image size takes the frames'.

:class:`SequenceWriter` appends frames while they arrive (the simulator, the pipeline's
recorder): each image is encoded in memory, written to a hidden temporary file and renamed,
and only then is its ``data.csv`` row appended in one flushed write, so a crash at any moment
leaves only complete images and complete rows. :func:`index_sequence` reads a folder back:
it pairs left and right images by nearest timestamp within a tolerance, skips (and counts,
and says why) images that are missing, unreadable rows and unpaired timestamps. The source
that plays a folder is :class:`trackmeter.sources.sequence.SequenceSource`.
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import json
import math
import errno
import os
import re
import shutil
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence, overload

import cv2
import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray

from trackmeter.core.frames import StereoFrame
from trackmeter.core.stereo import StereoRig
from trackmeter.core.transforms import matrix_to_quat_wxyz, quat_sign_nearest
from trackmeter.data.atomic import (AppendFile, FolderLock, claim_folder, folder_identity, repoint,
                                    unwritable_ancestor)
from trackmeter.data.images import decode_image, joint_data_bits
from trackmeter.data.model import Model, load_model, save_model
from trackmeter.data.motion_csv import GROUNDTRUTH_COLUMNS, MotionCsvWriter, MotionSeries, read_motion_csv
from trackmeter.data.rigfile import load_rig, save_rig
from trackmeter.data.trajectory import format_tum_line, read_tum
from trackmeter.errors import TrackmeterError, counted, quoted

FloatArray = NDArray[np.float64]
DATA_CSV_HEADER = "#timestamp [ns],filename"
#: A sequence's cuts (an extension of the EuRoC layout; other tools ignore it): the frames at
#: which the scene jumps, each the first of a new pass of a looping source or of a restart,
#: recorded so that a replay starts over there as the live run did (DESIGN.md's frame ``cut``).
CUTS_FILE = "cuts.csv"
CUTS_CSV_HEADER = "#timestamp [ns] of each frame that starts a new pass (the scene jumps there)"
CAMERAS = ("cam0", "cam1")


def seconds_to_ns(t_s: float) -> int:
    """Timestamp in integer nanoseconds (EuRoC ``data.csv``) from float seconds."""
    return int(round(float(t_s) * 1e9))


@overload
def ns_to_seconds(ns: int) -> float: ...
@overload
def ns_to_seconds(ns: NDArray[np.int64]) -> FloatArray: ...
def ns_to_seconds(ns: int | NDArray[np.int64]) -> float | FloatArray:
    """Seconds from integer nanoseconds, correctly rounded (exactly so below 2**53 ns, 104 days).

    ``ns / 1e9`` is one correctly rounded division; ``ns * 1e-9`` multiplies by an inexact
    constant and can land one unit in the last place off (1000 ns -> 1.0000000000000002e-06).
    Every conversion goes through here so a frame's time joins exactly across data.csv,
    groundtruth.* and a run's files.
    """
    return ns / 1e9


# --------------------------------------------------------------------------- writing


def check_record_directory(directory: str | Path) -> Path:
    """``directory`` as a Path when a recording may go there: a new or empty folder under a
    folder this process may write in. A folder that holds anything is refused, so a recording
    never overwrites or mixes with what is there (an earlier recording, a run's files).

    Raises:
        TrackmeterError: an empty name, a file, a folder that is not empty, or no writable parent.
    """
    if not str(directory).strip():
        raise TrackmeterError("cannot record to '': the folder's name is empty")
    path = Path(directory)
    try:
        if path.exists() and not path.is_dir():
            raise TrackmeterError(f"cannot record to {path}: it is a file, not a folder")
        if path.is_dir() and any(path.iterdir()):
            what = "a sequence (cam0/data.csv)" if (path / "cam0" / "data.csv").exists() else "files"
            raise TrackmeterError(f"cannot record to {path}: it already holds {what}; record into a new or empty folder")
    except OSError as exc:  # a name too long, a folder that cannot be listed
        raise TrackmeterError(f"cannot record to {path}: {exc.strerror or exc}") from None
    blocked = unwritable_ancestor(path)
    if blocked is not None:
        raise TrackmeterError(f"cannot record to {path}: {blocked} is not a writable folder")
    return path


#: A file a :class:`SequenceWriter` keeps in its folder until it is closed: a recording killed
#: mid-way (its frames whole up to the last) is then told from a complete one when read.
UNFINISHED_MARK = ".trackmeter-unfinished"


class SequenceWriter:
    """Write a sequence folder frame by frame (DESIGN.md section 6 layout).

    Args:
        directory: the folder (created; it may already exist, but empty: see
            :func:`check_record_directory`).
        rig: written to ``rig.yaml`` at once when given.
        model_points: a :class:`Model` or ``(name, xyz_body)`` pairs, written to ``model.yaml``.
        png_compression: None (OpenCV's default PNG settings: the fastest measured, since a
            recorder must keep up with the live stream; ``python -m benchmarks sequence_write``)
            or a zlib level 0-9.

    Usage::

        with SequenceWriter(out, rig=rig, model_points=mockup.salient_points) as w:
            for frame in frames:
                w.write(frame)

    Frames carrying ``truth`` add rows to ``groundtruth.csv`` and ``groundtruth.tum``
    (created at the first such frame). A frame marked ``cut`` after the first adds its
    timestamp to ``cuts.csv`` (:data:`CUTS_FILE`, created at the first cut). Timestamps must
    increase (equal nanoseconds would overwrite an image).
    """

    def __init__(
        self,
        directory: str | Path,
        rig: StereoRig | None = None,
        model_points: Model | Sequence[tuple[str, ArrayLike]] | None = None,
        png_compression: int | None = None,
    ) -> None:
        self.directory = check_record_directory(directory)
        if png_compression is not None and not 0 <= png_compression <= 9:
            raise TrackmeterError(f"PNG compression must be 0-9, got {png_compression}")
        # OpenCV 5's default PNG settings (fast filter, RLE, low level) measured fastest on noisy
        # 726x512 frames, ~2x faster than an explicit level 1 (which switches to all filters) and
        # no larger; an explicit level trades speed for size.
        self._png_params = [] if png_compression is None else [cv2.IMWRITE_PNG_COMPRESSION, int(png_compression)]
        self._csv: dict[str, AppendFile] = {}
        self._mark: Path | None = None
        self._truth_csv: MotionCsvWriter | None = None
        self._truth_tum: AppendFile | None = None
        self._last_truth_quat_wxyz: FloatArray | None = None  # the next one takes the sign nearer it
        self._cuts: AppendFile | None = None
        self._last_ns: int | None = None
        self.frames_written = 0
        #: bytes of the image files written (PNG), the bulk of the folder: a recording of a
        #: looping source grows without end, and the operator is shown how far.
        self.image_bytes_written = 0
        self._failed = False  # a write failed and said why: the close does not say it again
        self._rig, self._model_points = rig, model_points  # written again if deleted while recording
        # Two recordings started into one new folder at once would truncate each other's files:
        # the second is refused, and the folder checked again under the lock.
        lock, created = claim_folder(self.directory, "another recording",
                                     lambda: check_record_directory(self.directory), f"cannot record to {self.directory}")
        self._lock: FolderLock | None = lock
        self._folder_id = folder_identity(self.directory)
        made: list[Path] = []  # what this writer creates here, each named before it is made
        try:
            self._mark = self.directory / UNFINISHED_MARK
            made.append(self._mark)
            self._mark.write_text("a trackmeter recording in progress (removed when it is closed)\n", encoding="utf-8")
            for cam in CAMERAS:
                if not (self.directory / cam).exists():
                    made.append(self.directory / cam)
                (self.directory / cam / "data").mkdir(parents=True, exist_ok=True)
            for cam in CAMERAS:
                self._csv[cam] = AppendFile(self.directory / cam / "data.csv", DATA_CSV_HEADER + "\n")
            if rig is not None:
                made.append(self.directory / "rig.yaml")
                save_rig(rig, self.directory / "rig.yaml")
            if model_points is not None:
                made.append(self.directory / "model.yaml")
                save_model(self.directory / "model.yaml", model_points)
        except BaseException as exc:
            # Nothing half-made left: what this writer made (and the folder when it made it;
            # only what it made, should the filesystem not lock), the lock last.
            for f in self._csv.values():
                with contextlib.suppress(Exception):
                    f.close()
            self._csv = {}
            self._remove_made(made, created)
            self._mark = None
            self._release_lock()
            if isinstance(exc, OSError):
                raise TrackmeterError(f"cannot record to {self.directory}: {exc.strerror or exc}") from None
            raise
        self._made, self._created = made, created
        self._frame_offered = False  # write() was called (a write that failed keeps the folder: it says why)
        #: Closed without a frame offered: what it made was removed (a folder of csv headers is
        #: no sequence: track refuses it), the folder too where this writer made it.
        self.discarded = False

    def _remove_made(self, made: Sequence[Path], created: bool) -> None:
        """Remove what this writer made in its folder (``made``), and the folder when it made it
        (``created``; only what it made, should the filesystem not lock)."""
        for path in made:
            if path.is_dir():
                shutil.rmtree(path, ignore_errors=True)
            else:
                path.unlink(missing_ok=True)
        if created:
            with contextlib.suppress(OSError):
                self.directory.rmdir()

    def _release_lock(self) -> None:
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def detach_lock(self) -> FolderLock | None:
        """Hand the folder's lock to the caller, who releases it: :meth:`close` then does not
        (``simulate`` holds its folder until it is renamed into place or removed)."""
        lock, self._lock = self._lock, None
        return lock

    def write(self, frame: StereoFrame) -> None:
        """Append one stereo frame (and its ground truth when it has one)."""
        if not self._csv:
            raise TrackmeterError(f"{self.directory}: sequence writer is closed")
        self._frame_offered = True
        try:
            self._follow_folder()
            self._restore_deleted_files()
        except TrackmeterError:
            self._failed = True
            raise
        ns = frame.stamp_ns if frame.stamp_ns is not None else seconds_to_ns(frame.t_s)
        if self._last_ns is not None and ns <= self._last_ns:
            raise TrackmeterError(f"frame at {frame.t_s} s does not come after the previous one")
        name = f"{ns}.png"
        images = [self.directory / cam / "data" / name for cam in CAMERAS]
        # A frame is recorded whole or not at all: when a write fails (a full disk), what this
        # frame had written is taken back, and the frames before stay a playable sequence.
        sizes = {cam: f.size for cam, f in self._csv.items()}
        cuts_size = None if self._cuts is None else self._cuts.size
        try:
            for path, image in zip(images, (frame.left, frame.right)):
                self._write_image(path, image)
            for cam in CAMERAS:
                self._csv[cam].append(f"{ns},{name}\n")
            if frame.cut and self.frames_written:
                if self._cuts is None:
                    self._cuts = AppendFile(self.directory / CUTS_FILE, CUTS_CSV_HEADER + "\n")
                    cuts_size = self._cuts.size
                self._cuts.append(f"{ns}\n")
            if frame.truth is not None:
                self._write_truth(ns_to_seconds(ns), frame)
        except (TrackmeterError, OSError) as exc:
            self._failed = True
            for cam, size in sizes.items():  # (the truth's files take back their own rows)
                self._csv[cam].truncate(size)
            if self._cuts is not None and cuts_size is not None:
                self._cuts.truncate(cuts_size)
            for path in images:
                with contextlib.suppress(OSError):  # its folder replaced by a file: the write said so
                    path.unlink(missing_ok=True)
            if isinstance(exc, OSError) and exc.errno == errno.ENOENT:
                raise TrackmeterError(self._files_removed_message()) from None
            if isinstance(exc, OSError):
                raise TrackmeterError(f"{exc.filename or self.directory}: cannot write ({exc.strerror or exc})") from None
            raise
        self._last_ns = ns
        self.frames_written += 1

    def _files_removed_message(self) -> str:
        """What a write that found its files gone (the folder is there, or followed) lost: one
        camera's images or the whole recording's (``mv`` to another file system copies, then
        removes the files while the folder is still there)."""
        how = "removed while recording (deleted, or moved to another file system)"
        gone = [cam for cam in CAMERAS if not (self.directory / cam / "data").is_dir()]
        if len(gone) == 1:
            (cam,) = gone
            (kept,) = (other for other in CAMERAS if other != cam)
            lost = (f"the {counted(self.frames_written, 'frame')} written there lost their {cam} images, {kept} keeps its "
                    "own" if self.frames_written else "before its first frame")
            return f"{self.directory}: {cam}'s files were {how}; {lost}"
        lost = (f"the {counted(self.frames_written, 'frame')} written there went with them" if self.frames_written
                else "before its first frame")
        return f"{self.directory}: the recording's files were {how}; {lost}"

    def _follow_folder(self) -> None:
        """Follow the folder when it was moved (renamed) while recording: its open files went
        with it, and the frames to come go there too (said once). Raises TrackmeterError when
        it was removed: every frame's images are written by name, and would fail one by one."""
        if self._folder_id is None or folder_identity(self.directory) == self._folder_id:
            return
        moved = None if self._lock is None else self._lock.follow_move()
        if moved is None:
            if not self.frames_written:
                raise TrackmeterError(f"{self.directory}: the recording folder was removed while recording, before its "
                                      "first frame")
            raise TrackmeterError(f"{self.directory}: the recording folder was removed while recording; the "
                                  f"{counted(self.frames_written, 'frame')} written there went with it")
        old, self.directory = self.directory, moved
        if self._mark is not None:
            self._mark = repoint(self._mark, old, moved)
        for file in (*self._csv.values(), self._truth_csv, self._truth_tum, self._cuts):
            if file is not None:
                file.path = repoint(file.path, old, moved)
        warnings.warn(f"{old}: the recording folder was moved to {moved} while recording; the recording goes on there",
                      stacklevel=3)

    def _restore_deleted_files(self) -> None:
        """Write a file of the recording again when it was deleted while recording (a camera's
        ``data.csv``, the ground truth, ``cuts.csv`` from their open files; ``rig.yaml`` and
        ``model.yaml`` from what they were written from): the rows would go on into the unlinked
        file and be lost at the close, and without ``data.csv`` the folder plays as no frames.
        Every file is tried; the first that cannot be written again is raised (TrackmeterError)."""
        first_failure: TrackmeterError | None = None
        for file in (*self._csv.values(), self._truth_csv, self._truth_tum, self._cuts):
            try:
                restored = file is not None and file.restore_if_removed()
            except TrackmeterError as exc:  # the others are still written again
                first_failure = first_failure or exc
                continue
            if restored:
                assert file is not None
                warnings.warn(f"{file.path}: removed while recording; written again from the recorder's own copy "
                              f"(the {counted(self.frames_written, 'frame')} before kept)", stacklevel=3)
        rig, model_points = self._rig, self._model_points
        described: list[tuple[str, Callable[[Path], object]]] = []
        if rig is not None:
            described.append(("rig.yaml", lambda path: save_rig(rig, path)))
        if model_points is not None:
            described.append(("model.yaml", lambda path: save_model(path, model_points)))
        for name, save in described:
            path = self.directory / name
            if path.exists() or not self.directory.is_dir():
                continue
            try:
                save(path)
            except (TrackmeterError, OSError) as exc:
                first_failure = first_failure or TrackmeterError(f"{path}: removed, and cannot be written again ({exc})")
                continue
            warnings.warn(f"{path}: removed while recording; written again", stacklevel=3)
        if first_failure is not None:
            raise first_failure

    def _write_image(self, path: Path, image: NDArray[np.uint8]) -> None:
        img = np.asarray(image)
        if img.dtype != np.uint8 or img.ndim != 2:
            raise TrackmeterError(f"sequence images must be (H,W) uint8, got {img.dtype} {img.shape}")
        ok, buf = cv2.imencode(".png", img, self._png_params)
        if not ok:  # pragma: no cover - PNG encoding of uint8 does not fail
            raise TrackmeterError(f"{path}: PNG encoding failed")
        tmp = path.with_name(f".{path.name}.tmp")
        try:
            with open(tmp, "wb") as f:
                f.write(buf.tobytes())
            os.replace(tmp, path)
            self.image_bytes_written += buf.size
        except BaseException:
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
            raise

    def _write_truth(self, t_s: float, frame: StereoFrame) -> None:
        truth = frame.truth
        assert truth is not None
        T = np.asarray(truth.T_cam_body, dtype=float)
        q = quat_sign_nearest(matrix_to_quat_wxyz(T[:3, :3]), self._last_truth_quat_wxyz)
        if self._truth_csv is None or self._truth_tum is None:
            # Both or neither: with the csv kept and the tum not made, the next frame's truth
            # failed on an assertion that its rollback did not catch, leaving a half frame.
            csv = MotionCsvWriter(self.directory / "groundtruth.csv", GROUNDTRUTH_COLUMNS)
            try:
                tum = AppendFile(self.directory / "groundtruth.tum", "# t tx ty tz qx qy qz qw  (T_cam_body)\n")
            except BaseException:
                csv.close()
                with contextlib.suppress(OSError):
                    (self.directory / "groundtruth.csv").unlink()
                raise
            self._truth_csv, self._truth_tum = csv, tum
        csv_size, tum_size, rows = self._truth_csv.size, self._truth_tum.size, self._truth_csv.rows_written
        try:
            self._write_truth_rows(t_s, T, q, truth)
        except TrackmeterError:
            self._truth_csv.truncate(csv_size, rows)
            self._truth_tum.truncate(tum_size)
            raise
        self._last_truth_quat_wxyz = q

    def _write_truth_rows(self, t_s: float, T: FloatArray, q: FloatArray, truth: Any) -> None:
        assert self._truth_csv is not None and self._truth_tum is not None
        self._truth_csv.write(t=t_s, position_m=T[:3, 3], quat_wxyz=q, velocity_cam_m_s=truth.velocity_cam_m_s,
                              omega_body_rad_s=truth.omega_body_rad_s)
        self._truth_tum.append(format_tum_line(t_s, T[:3, 3], q) + "\n")

    def close(self) -> None:
        """Close the files (idempotent); the folder's lock is dropped whatever fails."""
        try:
            self._close_files()
        finally:
            self._release_lock()

    def _close_files(self) -> None:
        restored: TrackmeterError | None = None
        if self._csv and self.frames_written and not self._failed:
            # What happened to the folder after the last frame, as a next frame would find it:
            # moved (followed), removed, a camera's images gone, a file deleted (written again).
            try:
                self._follow_folder()
                self._restore_deleted_files()
                if any(not (self.directory / cam / "data").is_dir() for cam in CAMERAS):
                    raise TrackmeterError(self._files_removed_message())
            except TrackmeterError as exc:
                restored = exc
        for f in self._csv.values():
            f.close()
        self._csv = {}
        if self._truth_csv is not None:
            self._truth_csv.close()
        if self._truth_tum is not None:
            self._truth_tum.close()
            self._truth_tum = None
        if self._cuts is not None:
            self._cuts.close()
            self._cuts = None
        if restored is not None:
            self._mark = None  # a file of the recording is gone: the folder stays marked unfinished
            raise restored
        if not self._frame_offered and self._mark is not None:
            self._mark = None
            self._remove_made(self._made, self._created)
            self.discarded = True
            return
        if self._mark is not None:
            mark, self._mark = self._mark, None
            try:
                mark.unlink(missing_ok=True)  # after every file is closed: the folder is whole
            except OSError as exc:
                raise TrackmeterError(f"{mark}: cannot remove ({exc.strerror or exc}): the "
                                      f"{counted(self.frames_written, 'frame')} recorded "
                                      f"{'is' if self.frames_written == 1 else 'are'} whole, but the folder stays "
                                      "marked unfinished") from None

    def __enter__(self) -> SequenceWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------- reading


@dataclass(frozen=True, eq=False)
class SequenceIndex:
    """What a sequence folder holds, paired and checked; images are not loaded.

    Attributes:
        root: the folder holding ``cam0``/``cam1`` (``DIR`` or ``DIR/mav0``).
        t_s: (N,) timestamps of the stereo pairs (the left image's), s, increasing.
        t_ns: (N,) the same, as the integer nanoseconds the files give (empty when built
            without them).
        left_paths, right_paths: (N,) image files of each pair.
        rig: from ``rig.yaml`` when present, else from a real EuRoC folder's two
            ``sensor.yaml`` (:func:`read_euroc_rig`), else None.
        rig_file: the file ``rig`` was read from (the left camera's ``sensor.yaml`` for
            EuRoC's pair), None when there is no rig or it was not read.
        model: from ``model.yaml`` when present, else None.
        truth: ground truth per pair (N rows, NaN rows where a pair has no truth within
            the tolerance), from ``groundtruth.csv`` or else ``groundtruth.tum``; None when
            the folder has neither.
        skipped: number of images (left and right) that are not part of any pair.
        cuts: increasing positions of the pairs that start a new pass (``cuts.csv``: the
            scene jumps there; a recording made across a looping source's new pass).
        warnings: one human-readable line per kind of problem found (empty when clean).
        tolerance_s: the pairing tolerance used, s.
        truth_problem: why the folder's ground truth is of no use: its file did not read
            (``truth`` is then None and the reason is among ``warnings``), or no row gives a
            whole pose; None otherwise.
    """

    root: Path
    t_s: FloatArray
    left_paths: tuple[Path, ...]
    right_paths: tuple[Path, ...]
    rig: StereoRig | None = None
    model: Model | None = None
    truth: MotionSeries | None = None
    skipped: int = 0
    warnings: tuple[str, ...] = field(default_factory=tuple)
    tolerance_s: float = 0.0
    cuts: tuple[int, ...] = ()
    truth_problem: str | None = None
    t_ns: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    rig_file: Path | None = None

    def __len__(self) -> int:
        return len(self.t_s)

    @property
    def rate_hz(self) -> float | None:
        """Nominal frame rate, Hz (None with fewer than 2 frames): one over the mean of the
        intervals within 10 % of the median one (a dropped frame or a pause left out), to 7
        significant digits: timestamps in whole nanoseconds (or seconds as floats, 0.2 us apart
        for EuRoC's epoch times) are that exact, so 40 000 000 ns apart is 25 Hz, not
        24.99999999999998, and frames 66 666 667 and 66 666 666 ns apart are 15 Hz."""
        if len(self.t_s) < 2:
            return None
        dt = np.diff(self.t_s)
        median = float(np.median(dt))
        if not median > 0:
            return None
        regular = dt[np.abs(dt - median) <= 0.1 * median]
        mean = float(np.mean(regular)) if regular.size else math.nan
        rate = 1.0 / mean if math.isfinite(mean) and mean > 0 else 1.0 / median
        return float(f"{rate:.7g}")


def _sequence_root(directory: Path) -> Path | None:
    for root in (directory, directory / "mav0"):
        if (root / "cam0" / "data.csv").is_file() and (root / "cam1" / "data.csv").is_file():
            return root
    return None


def is_sequence_folder(directory: str | Path) -> bool:
    """Whether ``directory`` holds a sequence (``cam0``/``cam1`` with their ``data.csv``, or
    the same below ``mav0``)."""
    return _sequence_root(Path(directory)) is not None


def check_output_folder(directory: str | Path, contents: str, folder: str) -> Path:
    """``directory`` as a Path when a command's output may go there; nothing is created.

    Args:
        contents, folder: what the messages call the output (``"a run's files"``, ``"a run
            folder"``).

    Raises:
        TrackmeterError: it is a file, a sequence folder or inside one of its camera folders
            (a recording is not mixed with other files), or its nearest existing parent is not
            a folder this process may write in.
    """
    path = Path(directory)
    if path.exists() and not path.is_dir():
        raise TrackmeterError(f"{path}: exists and is not a folder")
    if is_sequence_folder(path):
        raise TrackmeterError(f"{path}: a sequence folder (cam0/, cam1/): {contents} do not go into a recording; "
                              "choose another --out")
    # Nor among a camera's images (SEQ/cam0/data): a folder beside the recording is fine.
    for inner, outer in zip((path, *path.parents), path.parents):
        if inner.name in CAMERAS and is_sequence_folder(outer):
            raise TrackmeterError(f"{path}: inside a sequence's {inner.name}/ (its images): {contents} do not go "
                                  "into a recording; choose another --out")
    blocked = unwritable_ancestor(path)
    if blocked is not None:
        raise TrackmeterError(f"{path}: cannot create {folder} there ({blocked} is not a writable folder)")
    return path


def sequence_identity(directory: str | Path) -> tuple[Path, str | None]:
    """What tells a sequence folder from another: ``(DIR resolved (the folder above mav0/ for
    that layout), the name of the scenario it was simulated from (its scenario.yaml) or None)``.
    Recorded in a run's run.yaml, so that evaluate can tell a truth of another sequence."""
    d = Path(directory).resolve()
    if d.name == "mav0" and not (d / "scenario.yaml").is_file():
        d = d.parent
    try:
        name = yaml.safe_load((d / "scenario.yaml").read_text(encoding="utf-8")).get("name")
    except (OSError, UnicodeDecodeError, yaml.YAMLError, AttributeError):
        name = None
    return d, name if isinstance(name, str) else None


#: The scenario settings that make its motion (its ground truth): the rest is how it looks,
#: and its duration, which cuts the same motion shorter or carries it on; its frame rate
#: samples the same motion, except where static ranges change at a frame count.
MOTION_KEYS = ("inertia_kg_m2", "attitude0_wxyz", "omega0_body_deg_s", "position0_m", "velocity_m_s", "approach_to_m",
               "approach_s", "static_ranges_m", "release_s")
STATIC_RANGE_KEYS = ("frames_per_range", "rate_hz")


def motion_digest(scenario: Mapping[str, Any]) -> str | None:
    """A fingerprint of a scenario's motion from its settings (``MOTION_KEYS``): equal for two
    scenarios whose ground truth is the same, whatever their names; None when a key is missing
    or not numbers (a scenario.yaml of another kind)."""
    def numbers(value: Any) -> Any:
        if value is None:
            return None
        if isinstance(value, (list, tuple)):
            return [numbers(v) for v in value]
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise TypeError(value)
        return float(value)

    try:
        values = [numbers(scenario[key]) for key in MOTION_KEYS]
        if values[MOTION_KEYS.index("static_ranges_m")]:
            values += [numbers(scenario[key]) for key in STATIC_RANGE_KEYS]
    except (KeyError, TypeError):
        return None
    return hashlib.sha256(json.dumps(values).encode()).hexdigest()[:16]


def sequence_motion_digest(directory: str | Path) -> str | None:
    """:func:`motion_digest` of the scenario a sequence folder was simulated from (its
    scenario.yaml, as :func:`sequence_identity` finds it); None without one."""
    d, _ = sequence_identity(directory)
    try:
        data = yaml.safe_load((d / "scenario.yaml").read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return None
    return motion_digest(data) if isinstance(data, dict) else None


def find_sequence_root(directory: str | Path) -> Path:
    """``DIR`` or ``DIR/mav0``: the folder holding ``cam0`` and ``cam1``.

    Raises:
        TrackmeterError: no such folder, or neither layout found.
    """
    d = Path(directory)
    if d.exists() and not d.is_dir():
        raise TrackmeterError(f"{d}: a file, not a sequence folder")
    if not d.is_dir():
        raise TrackmeterError(f"{d}: no such sequence folder")
    root = _sequence_root(d)
    if root is None:
        if (d / UNFINISHED_MARK).exists():
            raise TrackmeterError(f"{d}: a recording stopped before its first frame was written (no data.csv yet; "
                                  f"{UNFINISHED_MARK} is there: its writer was killed, or is still starting)")
        raise TrackmeterError(f"{d}: not a sequence folder (expected cam0/data.csv and cam1/data.csv, or mav0/...)")
    return root


def find_sequence_file(directory: str | Path, *names: str) -> Path | None:
    """The first of ``names`` in ``DIR``, else the first in ``DIR/mav0``; None when none is a file.

    DESIGN.md puts ``rig.yaml``, ``model.yaml`` and ``groundtruth.*`` in ``DIR`` whatever the
    image layout, and EuRoC's own files live under ``mav0``: every reader of a sequence folder
    looks with this one rule so they all find the same file. ``names`` in order of preference
    (``groundtruth.csv`` before ``groundtruth.tum``) within each folder.
    """
    d = Path(directory)
    for folder in (d, d / "mav0"):
        for name in names:
            if (folder / name).is_file():
                return folder / name
    return None


#: Above this frame rate a sequence's timestamps are taken for another unit than nanoseconds
#: (microseconds give 25 kHz for a 25 Hz camera, frame numbers 1 GHz), and warned about.
MAX_PLAUSIBLE_RATE_HZ = 2000.0


def _timestamp_unit_guess(interval_s: float) -> str:
    """The question to ask of timestamps ``interval_s`` apart read as nanoseconds: the unit that
    would give a camera's rate (1 to 1000 Hz), else frame numbers or another unit."""
    if abs(interval_s - 1e-9) < 1e-12:  # one apart
        return "are these frame numbers?"
    for unit, ns in (("microseconds", 1e3), ("milliseconds", 1e6), ("seconds", 1e9)):
        rate_hz = 1.0 / (interval_s * ns)
        if 1.0 <= rate_hz <= 1000.0:
            return f"are these {unit} ({rate_hz:.4g} Hz then)?"
    return "are these in another unit, or frame numbers?"


#: Frame intervals (the median one) past which a pause in a sequence's frame times is warned of.
GAP_INTERVALS = 3.0


def _read_data_csv(path: Path) -> tuple[list[tuple[int, Path]], int, int, Path | None, str | None]:
    """Rows ``(ns, image path)`` of one camera's data.csv in time order, counts of bad rows and
    missing files, the first missing file's path (None when none is missing), and what of the
    file goes back in time (None when nothing does).

    A row is ``timestamp_ns,filename``; columns after those two (other tools' extras) are
    ignored. A file with rows but none usable is refused, quoting its first row.
    """
    entries: list[tuple[int, Path]] = []
    bad = missing = 0
    first_bad: str | None = None
    first_missing: Path | None = None
    # Rows are played in time order whatever their order in the file, but a row earlier than
    # the one above is a clock reset or a wrong stamp as often as rows written out of order:
    # said, with where, not silently interleaved.
    back = 0
    first_back = ""
    previous_ns: int | None = None
    try:
        # A BOM from a spreadsheet is not a timestamp; a stray byte spoils its row, not the file.
        # Escaped, not replaced: a file name that is not UTF-8 (Latin-1's caf\xe9.png) still
        # names its file on disk, where "caf\ufffd.png" named none.
        text = path.read_text(encoding="utf-8-sig", errors="surrogateescape")
    except OSError as exc:
        raise TrackmeterError(f"{path}: cannot read: {exc.__class__.__name__}") from None
    lines = text.split("\n")
    # A last line without its newline is a row another tool wrote so (RFC 4180 allows it), or
    # one cut short by a crash: kept when it is whole (a number, and a file that is there: a
    # cut name lacks its extension's end), else counted as cut short, not as a missing file.
    header_allowed = True
    for line_number, line in enumerate(lines, start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        if line_number == len(lines) and not _whole_row(s, path):
            bad += 1
            continue
        parts = [p.strip() for p in s.split(",")]
        if header_allowed:  # the first row may be a header written without EuRoC's '#'
            header_allowed = False
            if re.fullmatch(r"[A-Za-z_ \[\]()]+", parts[0]):
                continue
        try:
            if len(parts) < 2 or not parts[1]:
                raise ValueError
            ns = int(parts[0])
            if not -(2**63) <= ns < 2**63:  # not a time any clock writes; numpy's int64 cannot hold it
                raise ValueError
        except ValueError:
            bad += 1
            first_bad = first_bad or s
            continue
        if previous_ns is not None and ns < previous_ns:
            back += 1
            first_back = first_back or f"the first on line {line_number}, {(previous_ns - ns) * 1e-9:.3g} s back"
        previous_ns = ns
        image = path.parent / "data" / parts[1]
        if not image.is_file():
            missing += 1
            first_missing = first_missing or image
            continue
        entries.append((ns, image))
    if first_bad is not None and not entries and not missing:
        raise TrackmeterError(f"{path}: no usable row: expected 'timestamp_ns,filename' with an integer "
                              f"timestamp in nanoseconds, got {quoted(first_bad, 80)}")
    entries.sort(key=lambda e: e[0])
    backwards = (f"{back} row(s) back in time from the row above ({first_back}): played in time order, "
                 "as if listed so (a camera clock reset would mix two runs)") if back else None
    return entries, bad, missing, first_missing, backwards


def _whole_row(row: str, path: Path) -> bool:
    """Whether ``row`` (stripped) of the data.csv at ``path`` is a whole ``timestamp_ns,filename``
    row naming an image that is there."""
    parts = [p.strip() for p in row.split(",")]
    return (len(parts) >= 2 and re.fullmatch(r"[+-]?\d+", parts[0]) is not None and bool(parts[1])
            and (path.parent / "data" / parts[1]).is_file())


def _nearest(x: FloatArray, y: FloatArray) -> NDArray[np.intp]:
    """For each of ``x``, the index of the nearest of ``y`` (sorted ascending, not empty); the
    earlier one on a tie."""
    if len(y) == 1:
        return np.zeros(len(x), dtype=np.intp)
    k = np.clip(np.searchsorted(y, x), 1, len(y) - 1)
    left_closer = np.abs(x - y[k - 1]) <= np.abs(y[k] - x)
    return np.where(left_closer, k - 1, k)


#: Left and right images paired further apart than this (median, s) are said to be: a target
#: moving 200 px/s is seen 0.2 px apart by the two cameras per millisecond between them.
SKEW_WORTH_SAYING_S = 1e-3


def _right_minus_left(t_left: FloatArray, t_right: FloatArray) -> FloatArray:
    """For each left timestamp, its nearest right one minus it, s (both sides not empty)."""
    left, right = np.asarray(t_left, float), np.sort(np.asarray(t_right, float))
    return right[_nearest(left, right)] - left


def _camera_offset(t_left: FloatArray, t_right: FloatArray) -> str:
    """``": ..."``: how far each left timestamp is from its nearest right one (median, s), and
    what that means, for the refusal of a sequence with no pair; "" when a side is empty."""
    if len(t_left) == 0 or len(t_right) == 0:
        return ""
    nearest = _right_minus_left(t_left, t_right)
    return (f": each left image's nearest right one is a median {float(np.median(np.abs(nearest))) * 1e3:.3g} ms away "
            f"(right minus left: {float(np.median(nearest)) * 1e3:+.3g} ms); the cameras were not triggered together, "
            "or their clocks differ by a constant (shift cam1/data.csv's timestamps by it)")


def _median_and_its_sigma(x: FloatArray) -> tuple[float, float]:
    """Median of ``x`` (N,) and its standard error, from the median absolute deviation (a
    normal sample's: 1.2533 * 1.4826 * MAD / sqrt(N))."""
    median = float(np.median(x))
    return median, 1.2533 * 1.4826 * float(np.median(np.abs(x - median))) / np.sqrt(len(x))


def _clock_drift(t_left: FloatArray, t_right: FloatArray, tolerance_s: float) -> str:
    """``" (...)"``: how the right camera's nearest image moves away from the left's between
    the first and the last quarter of the sequence, when by more than half ``tolerance_s``
    (clocks running at different rates lose their pairs from where they part); else ""."""
    # Only the time both cameras cover: a camera that starts late or ends early has no image
    # near the other's first or last ones, which is no drift.
    both = (t_left >= np.min(t_right)) & (t_left <= np.max(t_right)) if len(t_right) else np.zeros(len(t_left), bool)
    if np.count_nonzero(both) < 8:
        return ""
    nearest = _right_minus_left(t_left[both], t_right)
    quarter = len(nearest) // 4
    start, end = float(np.median(nearest[:quarter])), float(np.median(nearest[-quarter:]))
    if abs(end - start) <= 0.5 * tolerance_s:
        return ""
    return (f" (right minus left, nearest: {start * 1e3:+.3g} ms over the first quarter, {end * 1e3:+.3g} ms over the "
            "last: the cameras' clocks drift apart)")


def pair_by_nearest(t_left: ArrayLike, t_right: ArrayLike, tolerance: float) -> list[tuple[int, int]]:
    """Pairs ``(i, j)`` of mutually nearest timestamps with ``|t_left[i] - t_right[j]| <= tolerance``.

    Both inputs sorted ascending. Each index appears in at most one pair; pairs are in order.
    """
    a = np.asarray(t_left, dtype=float)
    b = np.asarray(t_right, dtype=float)
    if len(a) == 0 or len(b) == 0:
        return []
    j_of_i = _nearest(a, b)
    i_of_j = _nearest(b, a)
    return [(i, int(j)) for i, j in enumerate(j_of_i) if i_of_j[j] == i and abs(a[i] - b[j]) <= tolerance]


#: Integer times at least this large are nanoseconds, not seconds: 1e15 s is 30 million years,
#: 1e15 ns eleven days (EuRoC's epoch nanoseconds are about 1.4e18).
NANOSECONDS_AT_LEAST = 1e15
#: Integer times whose median step between poses is at least this are nanoseconds too: as
#: seconds, poses more than a day apart; as nanoseconds, 10 kHz or slower.
NANOSECOND_STEP_AT_LEAST = 1e5


def looks_like_nanoseconds(t: ArrayLike) -> bool:
    """True when the times ``t`` (N,), whatever they are paired with, can only be integer
    nanoseconds (EuRoC's unit): integers at least :data:`NANOSECONDS_AT_LEAST`, or with a
    median step of at least :data:`NANOSECOND_STEP_AT_LEAST`."""
    t = np.asarray(t, dtype=float).reshape(-1)
    if len(t) == 0 or not np.all(np.isfinite(t)) or not np.all(t == np.round(t)):
        return False
    if float(np.max(np.abs(t))) >= NANOSECONDS_AT_LEAST:
        return True
    steps = np.diff(np.unique(t))
    return len(steps) > 0 and float(np.median(steps)) >= NANOSECOND_STEP_AT_LEAST


def seconds_if_nanoseconds(t_ref_s: ArrayLike, t: ArrayLike, tolerance_s: float, ref_name: str = "the reference"
                           ) -> tuple[FloatArray, str | None]:
    """Times ``t`` in seconds, given times ``t_ref_s`` (s) they should pair with: ``t`` itself,
    or ``t * 1e-9`` with a note when ``t`` can only be nanoseconds
    (:func:`looks_like_nanoseconds`), or are integers of which fewer than half pair (nearest,
    within ``tolerance_s``) as seconds and more than twice as many as nanoseconds (e.g. a
    ``groundtruth.csv`` written in EuRoC's integer nanoseconds: it pairs with no frame in
    seconds, or only with one at t = 0)."""
    t = np.asarray(t, dtype=float)
    if looks_like_nanoseconds(t):
        return t * 1e-9, (f"its times read as integer nanoseconds ({t.min():.0f} to {t.max():.0f}: as seconds, "
                          f"too large or too far apart)")
    as_s = len(pair_by_nearest(t_ref_s, t, tolerance_s))
    if as_s >= min(len(np.atleast_1d(t_ref_s)), len(t)) / 2 or not np.all(t == np.round(t)):
        return t, None
    as_ns = len(pair_by_nearest(t_ref_s, t * 1e-9, tolerance_s))
    if as_ns <= max(2 * as_s, 1):
        return t, None
    return t * 1e-9, (f"its times read as integer nanoseconds ({as_ns} of its {len(t)} rows pair with {ref_name} so, "
                      f"{as_s} as seconds)")


def index_sequence(
    directory: str | Path, tolerance_s: float | None = None, *, read_rig: bool = True, read_model: bool = True,
    model_optional: bool = False,
) -> SequenceIndex:
    """Index a sequence folder: pair its images, read its rig, model and ground truth.

    Args:
        directory: ``DIR`` (or an EuRoC ``DIR`` with ``mav0/``).
        tolerance_s: how far apart a left and a right timestamp may be to form a pair, s.
            Default: a quarter of the median left frame interval (1 ms when unknown).
        read_rig, read_model: False leaves the folder's rig (model) unread and None, e.g. when
            the user gives another (``--rig``, ``--model``): a broken file there then stops nothing.
        model_optional: the caller may run without the model (e.g. case (a) unless a target is
            bound to it): a ``model.yaml`` that cannot be read is described in ``warnings`` and
            ``model`` is None, as a broken ground truth is.

    Raises:
        TrackmeterError: not a sequence folder, unreadable CSV or rig/model file, or no
            stereo pair at all. Missing images and unpaired timestamps are not errors: they
            are skipped, counted in ``skipped`` and described in ``warnings``; nor is a
            ground-truth file that cannot be read (``truth`` None, the reason in ``warnings``).
    """
    root = find_sequence_root(directory)
    (left, bad_l, miss_l, gone_l, back_l), (right, bad_r, miss_r, gone_r, back_r) = (
        _read_data_csv(root / cam / "data.csv") for cam in CAMERAS)
    t_left = np.array([e[0] for e in left], dtype=np.int64)
    t_right = np.array([e[0] for e in right], dtype=np.int64)
    if tolerance_s is None:
        # Distinct stamps: a data.csv appended to twice (skipped and warned below) halves the
        # median gap to 0, and a tolerance of 0 paired nothing with a camera 0.1 ms off.
        distinct = np.unique(t_left)
        tolerance_s = 0.25 * float(ns_to_seconds(np.median(np.diff(distinct)))) if len(distinct) > 1 else 1e-3
    for cam, entries, missing, gone, bad in (("cam0", left, miss_l, gone_l, bad_l), ("cam1", right, miss_r, gone_r, bad_r)):
        if not entries:
            path = root / cam / "data.csv"
            # The path looked for shows a filename column written relative to another folder.
            raise TrackmeterError(f"{path}: none of the {missing} image(s) it lists exists (the first looked for: {gone})"
                                  if missing else f"{path}: lists no image" + (
                                      f" but {counted(bad, 'row')} malformed or cut short" if bad else ""))
    pairs = pair_by_nearest(ns_to_seconds(t_left), ns_to_seconds(t_right), tolerance_s)
    unpaired = (len(left) - len(pairs)) + (len(right) - len(pairs))
    # A row repeating an earlier timestamp (a data.csv appended to twice) finds no partner of
    # its own: said as what it is, apart from the images without a partner.
    repeats_l, repeats_r = len(t_left) - len(np.unique(t_left)), len(t_right) - len(np.unique(t_right))
    repeated = min(repeats_l + repeats_r, unpaired)
    unpaired -= repeated
    warnings: list[str] = []
    if Path(directory).name.endswith(".partial"):
        # `trackmeter simulate` writes into DIR.partial and renames it only when complete: this
        # one was stopped (killed) before, and reads as a shorter, complete-looking sequence.
        warnings.append("an unfinished simulation ('.partial': stopped before it was complete), it may end early")
    elif (root / UNFINISHED_MARK).exists():
        # A recording whose writer never closed it: killed, or still being written.
        warnings.append("a recording that was not closed (its writer was killed, or is still writing): it may end early")
    warnings += [f"{cam}/data.csv: {back}" for cam, back in zip(CAMERAS, (back_l, back_r)) if back]
    if miss_l or miss_r:
        warnings.append(f"{miss_l + miss_r} image(s) listed in data.csv are missing (cam0: {miss_l}, cam1: {miss_r})")
    if bad_l or bad_r:
        warnings.append(f"{bad_l + bad_r} malformed or cut-short data.csv row(s) ignored (cam0: {bad_l}, cam1: {bad_r})")
    if repeated:
        warnings.append(f"{repeated} data.csv row(s) repeating an earlier timestamp skipped (cam0: {repeats_l}, "
                        f"cam1: {repeats_r})")
    drift = _clock_drift(ns_to_seconds(t_left), ns_to_seconds(t_right), tolerance_s) if unpaired else ""
    if unpaired:
        warnings.append(f"{unpaired} image(s) without a partner within {tolerance_s * 1e3:.3g} ms skipped{drift}")
    if not pairs:
        raise TrackmeterError(f"{directory}: no stereo pair (left and right timestamps within {tolerance_s * 1e3:.3g} ms)"
                              + _camera_offset(ns_to_seconds(t_left), ns_to_seconds(t_right)))
    skew_s, skew_sigma_s = _median_and_its_sigma(np.array([t_right[j] - t_left[i] for i, j in pairs], float) * 1e-9)
    # Jittered timestamps of cameras triggered together scatter their median too: said only
    # when it stands out of its own scatter (3 sigma).
    if abs(skew_s) >= max(SKEW_WORTH_SAYING_S, 3.0 * skew_sigma_s) and not drift:  # no one shift mends a drift
        warnings.append(f"left and right images paired a median {abs(skew_s) * 1e3:.3g} ms apart (right minus left: "
                        f"{skew_s * 1e3:+.3g} ms): a moving target is seen at two instants; if the cameras were "
                        f"triggered together, shift cam1/data.csv's timestamps by {-skew_s * 1e3:+.3g} ms")
    t_s = ns_to_seconds(np.array([t_left[i] for i, _ in pairs], dtype=np.int64))
    dt: float | FloatArray
    if len(t_s) > 1 and (dt := float(np.median(np.diff(t_s)))) > 0 and 1.0 / dt > MAX_PLAUSIBLE_RATE_HZ:
        warnings.append(f"frames {dt * 1e6:.4g} µs apart ({1.0 / dt:.0f} Hz): data.csv timestamps are "
                        f"nanoseconds; {_timestamp_unit_guess(float(dt))} (tracking would take the motion between "
                        "frames as that fast)")
    if len(t_s) > 2 and (step := float(np.median(np.diff(t_s)))) > 0:
        dt = np.diff(t_s)
        gaps = np.flatnonzero(dt > GAP_INTERVALS * step)
        if len(gaps):
            # Tracked across as one step: the motion between is predicted, not seen.
            worst = int(gaps[np.argmax(dt[gaps])])
            warnings.append(f"{len(gaps)} gap(s) in the frame times longer than {GAP_INTERVALS:g} frame intervals "
                            f"(the longest {dt[worst]:.3f} s, after t = {t_s[worst]:.3f} s): no frames there")
    rig_file = find_sequence_file(directory, *RIG_FILE_NAMES)
    rig: StereoRig | None = None
    if not read_rig:
        rig_file = None
    elif rig_file is not None:
        rig = load_rig(rig_file, image_size=_first_frame_size(left[i][1] for i, _ in pairs))
    else:
        rig, problem = read_euroc_rig(root)
        if problem:
            warnings.append(problem)
        rig_file = root / "cam0" / "sensor.yaml" if rig is not None else None
    model_file = find_sequence_file(directory, "model.yaml") if read_model else None
    model: Model | None = None
    try:
        model = load_model(model_file) if model_file is not None else None
    except TrackmeterError as exc:
        if not model_optional:
            raise
        warnings.append(f"{exc}; model not used")
    truth_problem: str | None = None
    truth_file = find_sequence_file(directory, "groundtruth.csv", "groundtruth.tum")
    try:
        truth = _read_truth(truth_file, t_s, tolerance_s)
    except TrackmeterError as exc:
        # Optional, and most runs (tracking a real sequence) do not need it: told, not fatal,
        # as a broken rig.yaml is not when another rig is given.
        truth, truth_problem = None, str(exc)
        warnings.append(f"{exc}; ground truth not used")
    if truth is not None and len(truth) and not truth.valid.any():
        # Every row without a whole pose (warned by row): a command that needs truth is told.
        truth_problem = f"{truth_file}: no row gives a whole pose at the frames' times"
    pair_ns = np.array([t_left[i] for i, _ in pairs], dtype=np.int64)
    try:
        cuts = _read_cuts(find_sequence_file(directory, CUTS_FILE), pair_ns)
    except TrackmeterError as exc:
        cuts = ()  # optional, as the ground truth is
        warnings.append(f"{exc}; its cuts not used")
    return SequenceIndex(
        cuts=cuts,
        root=root,
        t_s=t_s,
        left_paths=tuple(left[i][1] for i, _ in pairs),
        right_paths=tuple(right[j][1] for _, j in pairs),
        rig=rig,
        model=model,
        truth=truth,
        skipped=miss_l + miss_r + bad_l + bad_r + repeated + unpaired,
        warnings=tuple(warnings),
        tolerance_s=float(tolerance_s),
        truth_problem=truth_problem,
        t_ns=pair_ns,
        rig_file=rig_file,
    )


def _read_cuts(path: Path | None, pair_ns: NDArray[np.int64]) -> tuple[int, ...]:
    """The positions among the pairs at ``pair_ns`` (N,) of the timestamps ``path``
    (:data:`CUTS_FILE`, one integer nanosecond a line, ``#`` lines skipped) lists, in order;
    () without the file. A timestamp of no pair (its images missing) marks the next pair."""
    if path is None:
        return ()
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise TrackmeterError(f"{path}: cannot read ({exc.__class__.__name__})") from None
    cuts: set[int] = set()
    for number, line in enumerate(lines, 1):
        text = line.split(",")[0].strip()
        if not text or text.startswith("#"):
            continue
        try:
            ns = int(text)
        except ValueError:
            raise TrackmeterError(f"{path}:{number}: not an integer timestamp in nanoseconds: {quoted(text)}") from None
        position = int(np.searchsorted(pair_ns, ns))
        if position < len(pair_ns):
            cuts.add(position)
    return tuple(sorted(cuts))


#: A folder's rig, in order of preference: DESIGN.md's ``rig.yaml``, else OpenCV's stereo
#: sample pair (``intrinsics.yml`` + ``extrinsics.yml``, found from either).
RIG_FILE_NAMES = ("rig.yaml", "intrinsics.yml", "intrinsics.yaml", "intrinsics.xml")


def _first_frame_size(paths: Iterable[Path], tries: int = 3) -> tuple[int, int] | None:
    """``(width, height)`` of the first decodable of the first few ``paths``, for a rig file
    that carries no image size (the rig reader uses it only then; one decode per index, read
    whatever the rig holds to keep the reader's interface plain); None when none decodes."""
    for path in itertools.islice(paths, tries):
        try:
            image = decode_image(path)
        except TrackmeterError:
            continue
        return int(image.shape[1]), int(image.shape[0])
    return None


def read_euroc_rig(root: Path) -> tuple[StereoRig | None, str | None]:
    """The stereo rig of a real EuRoC folder from its ``cam0/sensor.yaml`` and ``cam1/sensor.yaml``.

    Each file gives ``T_BS`` (the camera's pose in the MAV body frame, 4x4 row-major), the
    ``resolution`` ``[w, h]``, pinhole ``intrinsics`` ``[fu, fv, cu, cv]`` and radial-tangential
    ``distortion_coefficients`` ``[k1, k2, p1, p2]`` (OpenCV's model and order). The stereo
    extrinsics follow: ``T_cam1_cam0 = inv(T_BS1) @ T_BS0``, i.e. ``p_cam1 = R p_cam0 + T``.

    Returns:
        ``(rig, None)``; ``(None, None)`` when the folder has no sensor.yaml files (a sequence
        without calibration); ``(None, reason)`` when they exist but cannot be used.
    """
    files = [root / cam / "sensor.yaml" for cam in CAMERAS]
    if not all(f.is_file() for f in files):
        return None, None
    from trackmeter.data.config import check_yaml_expansion
    from trackmeter.data.rigfile import pinhole_radtan_camera, without_directives

    cams = []
    poses = []
    for f in files:
        try:
            data = yaml.safe_load(without_directives(f.read_text(encoding="utf-8"))) or {}
            check_yaml_expansion(data, f)
            cams.append(pinhole_radtan_camera(data, "distortion_coefficients"))
            poses.append(np.array([float(x) for x in data["T_BS"]["data"]]).reshape(4, 4))
        except KeyError as exc:
            return None, f"{f}: no key {exc} in the camera calibration; rig unknown"
        except (OSError, UnicodeDecodeError, yaml.YAMLError, TypeError, ValueError, AttributeError) as exc:
            return None, f"{f}: cannot read the camera calibration ({exc.__class__.__name__}); rig unknown"
        except TrackmeterError as exc:
            return None, f"{f}: {exc}; rig unknown"
    from trackmeter.core.transforms import invert_transform

    T_c1_c0 = invert_transform(poses[1]) @ poses[0]
    try:
        return StereoRig(cams[0], cams[1], T_c1_c0[:3, :3], T_c1_c0[:3, 3], name=root.parent.name), None
    except TrackmeterError as exc:
        return None, f"{root}: EuRoC sensor.yaml files do not make a stereo rig ({exc}); rig unknown"


def _read_truth(path: Path | None, t_s: FloatArray, tolerance_s: float) -> MotionSeries | None:
    """Ground truth (``groundtruth.csv`` or ``.tum`` at ``path``) resampled to the pair times by
    nearest row within the tolerance (NaN elsewhere); None without a file."""
    if path is None:
        return None
    series = read_motion_csv(path) if path.suffix == ".csv" else MotionSeries.from_trajectory(read_tum(path))
    if path.suffix == ".csv":
        # Frame times come from data.csv's nanoseconds; a producer may have written its
        # groundtruth.csv EuRoC-style in integer nanoseconds too.
        t_truth, note = seconds_if_nanoseconds(t_s, series.t_s, tolerance_s, "the frames")
        if note:
            warnings.warn(f"{path}: {note}", stacklevel=2)
            series = replace(series, t_s=t_truth)
    pairs = pair_by_nearest(t_s, series.t_s, tolerance_s)
    if len(t_s) and series.valid.any() and not any(series.valid[j] for _, j in pairs):
        # Else only "no ground truth" later, of a folder that has some (another time base).
        shown = series.t_s[series.valid]
        raise TrackmeterError(f"{path}: its times (from {shown[0]:.3f} s to {shown[-1]:.3f} s) meet none of the "
                              f"frames' (from {t_s[0]:.3f} s to {t_s[-1]:.3f} s) within {tolerance_s * 1e3:.3g} ms: "
                              "another time base?")
    n = len(t_s)
    p = np.full((n, 3), np.nan)
    q = np.full((n, 4), np.nan)
    v = np.full((n, 3), np.nan)
    w = np.full((n, 3), np.nan)
    valid = np.zeros(n, dtype=bool)
    for i, j in pairs:
        valid[i] = bool(series.valid[j])
        p[i], q[i] = series.position_m[j], series.quat_wxyz[j]
        v[i], w[i] = series.velocity_cam_m_s[j], series.omega_body_rad_s[j]
    return MotionSeries(t_s, valid, p, q, v, w)


def sequence_data_bits(index: SequenceIndex, samples: int = 3) -> tuple[int, int]:
    """The sample depth of each camera's images, ``(left, right)``
    (:func:`trackmeter.data.images.data_bits`), decided once for the whole sequence from
    ``samples`` pairs spread over it (first, middle, last), so every frame of a camera is
    scaled alike; 8 when they are 8-bit, and when none of them can be read (reading them later
    says why). Two cameras of different depths (a 10-bit left, a 12-bit right) are each read at
    their own, and warned about: over several frames that is no one darker frame."""
    n = len(index)
    positions = sorted({round(k * (n - 1) / max(samples - 1, 1)) for k in range(samples)}) if n else []
    depths = []
    for paths in (index.left_paths, index.right_paths):
        images = []
        for pos in positions:
            try:
                images.append((str(paths[pos]), decode_image(paths[pos])))
            except TrackmeterError:
                continue
        depths.append(joint_data_bits(images, "every frame of a camera is scaled alike", warn_from_bits=4))
    left, right = depths
    if left != right:
        warnings.warn(f"{index.root}: {CAMERAS[0]}'s images look {left}-bit and {CAMERAS[1]}'s {right}-bit (in "
                       f"{len(positions)} pairs sampled over the sequence): each camera is read at its own depth",
                       stacklevel=3)
    return left, right
