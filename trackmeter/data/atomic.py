"""Writing files so that a reader sees either the old file or the whole new one, never half.

Every file the project writes whole (rig files, TUM trajectories, models, reports, run.yaml)
goes through here: written to a temporary file in the same folder, then renamed over the
target (``os.replace`` is atomic on POSIX within one file system).
"""

from __future__ import annotations

import contextlib
import os
import secrets
import tempfile
from pathlib import Path
from typing import Callable, Iterator, Mapping

from trackmeter.errors import TrackmeterError


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it over ``path``.

    On an exception the temporary file is removed and ``path`` is untouched. The file gets
    the ordinary permissions of a new file (``0o666 & ~umask``), not ``mkstemp``'s 0600.
    ``suffix`` keeps an extension for writers that choose their format by it (OpenCV).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_files_atomic(contents: Mapping[Path, bytes]) -> None:
    """Write several files as one piece of work (a report's summary, table and plots).

    Each is first written whole to a temporary file beside it; only when every one is whole
    are they renamed over their targets. On a failure while writing (a disk that fills) the
    temporaries are removed and every target is left as it was: an earlier report stays
    whole, not mixed with half of the new one; folders made for the files are removed again.
    A failure while renaming (a target that turned out to be a folder) puts back the targets
    already replaced, from hard links to them made before the first rename.

    Raises:
        TrackmeterError: a file could not be written (naming it and the OS's reason).
    """
    target: Path | None
    for target in contents:
        if Path(target).is_dir():  # os.replace would fail on it after replacing the others
            raise TrackmeterError(f"{target}: cannot write: it is a folder")
    written: list[tuple[Path, Path]] = []  # (temporary, target)
    made: list[Path] = []  # folders this call created, outermost first
    target = None
    try:
        for target, data in contents.items():
            missing = [d for d in (target.parent, *target.parent.parents) if not d.exists()]
            target.parent.mkdir(parents=True, exist_ok=True)
            made += [d for d in reversed(missing) if d not in made]
            fd, tmp_name = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.")
            written.append((Path(tmp_name), target))
            try:
                view = memoryview(data)
                while view:
                    view = view[os.write(fd, view):]
            finally:
                os.close(fd)
            os.chmod(tmp_name, 0o666 & ~_umask())
    except BaseException as exc:
        for tmp, _ in written:
            tmp.unlink(missing_ok=True)
        for folder in reversed(made):  # innermost first; only while empty
            try:
                folder.rmdir()
            except OSError:
                break
        if isinstance(exc, OSError):
            raise TrackmeterError(f"{target}: cannot write: {exc.strerror or exc}") from None
        raise
    _replace_all(written)


def _replace_all(written: list[tuple[Path, Path]]) -> None:
    """Rename each temporary over its target, all or none: the targets that were there are
    hard-linked aside first and put back when a later rename fails (on a file system without
    hard links, a target already replaced keeps its new file)."""
    kept: dict[Path, Path | None] = {}  # a target there before -> a link to its old file, if one was made
    done: list[Path] = []
    target: Path | None = None
    link: Path | None
    try:
        for _, target in written:
            if os.path.lexists(target):
                link = target.with_name(f".{target.name}.old.{os.getpid()}.{secrets.token_hex(4)}")
                try:
                    os.link(target, link, follow_symlinks=False)
                except OSError:
                    link = None
                kept[target] = link
        for tmp, target in written:
            os.replace(tmp, target)
            done.append(target)
    except OSError as exc:
        for put_back in done:
            with contextlib.suppress(OSError):
                if put_back not in kept:
                    put_back.unlink()  # it was not there before
                elif (link := kept[put_back]) is not None:
                    os.replace(link, put_back)
        for tmp, _ in written:
            tmp.unlink(missing_ok=True)
        _unlink_links(kept)
        raise TrackmeterError(f"{target}: cannot write: {exc.strerror or exc}") from None
    _unlink_links(kept)


def _unlink_links(kept: Mapping[Path, Path | None]) -> None:
    for link in kept.values():
        if link is not None:
            with contextlib.suppress(OSError):
                link.unlink(missing_ok=True)


def unwritable_ancestor(path: str | Path) -> Path | None:
    """The nearest existing path at or above ``path`` when it is not a folder this process may
    create files in; None when ``path`` (or the folders leading to it) can be made there."""
    existing = Path(path).absolute()
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        return existing
    # The permission bits do not tell all: root may write anywhere by them, and /proc or a
    # read-only mount still refuses. A folder made and removed at once asks the filesystem.
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".trackmeter-write-check-", dir=existing))
    except OSError:
        return existing
    return None


def folder_identity(folder: Path) -> tuple[int, int] | None:
    """``(device, inode)`` of ``folder``, None when it is gone."""
    try:
        st = os.stat(folder)
    except OSError:
        return None
    return (st.st_dev, st.st_ino)


class FolderLock:
    """An exclusive lock on a folder while one writer fills it (``flock`` on the folder itself:
    no lock file is left behind, and the kernel drops the lock with the process).

    Two writers that truncate and append the same files interleave them (holes of NUL bytes,
    rows of both); the second is refused instead. Where ``fcntl`` is missing (not POSIX) the
    lock is a no-op.

    Raises:
        TrackmeterError: another writer holds the folder (``what`` names it in the message).
    """

    def __init__(self, folder: str | Path, what: str) -> None:
        self.folder = Path(folder)
        self._fd: int | None = None
        try:
            import fcntl
        except ImportError:  # pragma: no cover - not POSIX
            return
        try:
            fd = os.open(self.folder, os.O_RDONLY)
        except OSError as exc:
            raise TrackmeterError(f"{self.folder}: cannot open it to lock it ({exc.strerror or exc})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise TrackmeterError(f"{self.folder}: {what} is writing there now; wait for it to end or "
                                  "choose another folder") from None
        except OSError:  # a filesystem without flock (some network mounts): write unlocked
            os.close(fd)
            return
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor drops the lock
            self._fd = None

    def follow_move(self) -> Path | None:
        """Where the locked folder is now when it was moved (renamed) away from :attr:`folder`,
        read from the descriptor the lock holds open on it (Linux's ``/proc/self/fd``), and
        :attr:`folder` set to it; None when it is still there, was removed, or the system
        cannot tell. A writer's open files go with a moved folder, so it can follow
        (:func:`repoint`)."""
        if self._fd is None:
            return None
        try:
            held = os.fstat(self._fd)
            path = Path(os.readlink(f"/proc/self/fd/{self._fd}"))
            there = os.stat(path)
        except OSError:
            return None
        if (there.st_dev, there.st_ino) != (held.st_dev, held.st_ino) or not path.is_absolute() or path == self.folder:
            return None
        self.folder = path
        return path


def repoint(path: Path, old: Path, new: Path) -> Path:
    """``path``, inside folder ``old``, as the same file of that folder moved to ``new``."""
    return new / Path(path).relative_to(old)


def claim_folder(folder: Path, writer: str, recheck: Callable[[], object], cannot_create: str
                 ) -> tuple[FolderLock, bool]:
    """Make ``folder`` (and its parents) unless it exists, lock it (:class:`FolderLock`, ``writer``
    naming the other writer in a refusal), and run ``recheck`` under the lock: whatever another
    writer did before the lock is seen. Returns ``(lock, created)``: ``created`` when this call
    made the folder, the one thing its writer may remove again; refused by the lock, the folder
    is the other writer's, whoever made it, and is left alone.

    Raises:
        TrackmeterError: the folder cannot be made (``cannot_create`` then the reason), another
            writer holds it, or ``recheck`` raised it (the lock released).
    """
    try:
        folder.mkdir(parents=True)
        created = True
    except FileExistsError:
        created = False
    except OSError as exc:
        raise TrackmeterError(f"{cannot_create}: {exc.strerror or exc}") from None
    lock = FolderLock(folder, writer)
    try:
        recheck()
    except BaseException:
        lock.release()
        raise
    return lock, created


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


class SpaceReserve:
    """``size`` bytes of disk held so that a last small file can still be written once the disk
    is full: a run's final ``run.yaml`` (its status and summary) after its rows filled the disk.

    The bytes are written (not a sparse file, which holds no blocks), so the file system has
    given them to the file; then its name is removed and only an open descriptor holds them.
    :meth:`release` closes it and gives them back. A run that stops on a full disk releases
    it and writes ``run.yaml`` in the space it held; a process killed outright (SIGKILL, the
    OOM killer) has its descriptors closed by the kernel, so nothing is left in the folder.

    Args:
        path: where the bytes are written, a hidden name in the folder they are for (only
            while they are written).
        size: bytes to hold.
        purpose: what they are held for, for the error (``"run.yaml's final version"``).

    Raises:
        TrackmeterError: the reserve cannot be written (the disk is full already), naming the
            folder, the purpose and the system's reason (not the hidden name, which the user
            never sees); nothing is left behind.
    """

    def __init__(self, path: str | Path, size: int, purpose: str = "a last file") -> None:
        self._fd: int | None = None
        path = Path(path)
        fd: int | None = None
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o600)
            view = memoryview(bytes(size))
            while view:  # a full disk may take part of a write before refusing the rest
                view = view[os.write(fd, view):]
        except OSError as exc:
            if fd is not None:
                os.close(fd)
            raise TrackmeterError(f"{path.parent}: cannot set aside {size} bytes for {purpose} "
                                  f"({exc.strerror or exc})") from None
        finally:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)
        self._fd = fd

    @property
    def held(self) -> bool:
        """Whether the space is still held (not released)."""
        return self._fd is not None

    def release(self) -> bool:
        """Give the space back; whether it was still held."""
        if self._fd is None:
            return False
        fd, self._fd = self._fd, None
        os.close(fd)
        return True


class AppendFile:
    """A file written in whole pieces while it grows (a CSV row, one frame's rows).

    Each :meth:`append` lands whole or not at all: when the disk fills or the write fails
    midway, the file is cut back to where the piece began, so a reader (or the run after a
    failure) never finds half a row. Unbuffered: a piece is in the file when ``append``
    returns, as a flushed write would be.

    Args:
        path: created, or truncated if it exists.
        header: the first piece (e.g. a CSV header), written at once.

    Raises:
        TrackmeterError: the file cannot be created or a piece cannot be written, with the
            path and the system's reason (``append`` leaves the file as before the piece).
    """

    def __init__(self, path: str | Path, header: str = "") -> None:
        self.path = Path(path)
        try:
            # Readable too: what was written can be written again (:meth:`restore_if_removed`).
            self._fd: int | None = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o666)
        except OSError as exc:
            raise TrackmeterError(f"{self.path}: cannot create ({exc.strerror or exc})") from None
        self.size = 0
        if header:
            self.append(header)

    def append(self, text: str) -> None:
        """Write ``text`` (UTF-8) at the end, whole or not at all."""
        if self._fd is None:
            raise TrackmeterError(f"{self.path}: closed")
        start = self.size
        data = text.encode("utf-8")
        view = memoryview(data)
        try:
            while view:  # a full disk may take part of a write before refusing the rest
                view = view[os.write(self._fd, view):]
        except OSError as exc:
            self.truncate(start)
            raise TrackmeterError(f"{self.path}: cannot write ({exc.strerror or exc})") from None
        self.size = start + len(data)

    def restore_if_removed(self) -> bool:
        """Write the file again at :attr:`path` when it was deleted or replaced there since it
        was opened, from what this object wrote (still in the open, unlinked file); True when
        it did. False when it is in place, or when its folder is gone (the caller's to say).

        Why: the appends would go on into a file no one can open again, and be lost at close.
        """
        if self._fd is None:
            return False
        try:
            here = os.stat(self.path)
        except FileNotFoundError:
            here = None
        except OSError:
            return False  # a folder on the path replaced by a file: the caller's writes say so
        mine = os.fstat(self._fd)
        if here is not None and (here.st_ino, here.st_dev) == (mine.st_ino, mine.st_dev):
            return False
        if not self.path.parent.is_dir():
            return False
        written = os.pread(self._fd, self.size, 0)
        tmp = self.path.with_name(f".{self.path.name}.tmp")
        try:
            fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o666)
            try:
                view = memoryview(written)
                while view:
                    view = view[os.write(fd, view):]
                os.replace(tmp, self.path)
            except BaseException:
                os.close(fd)
                raise
        except OSError as exc:
            with contextlib.suppress(OSError):
                tmp.unlink()
            raise TrackmeterError(f"{self.path}: removed, and cannot be written again ({exc.strerror or exc})") from None
        os.close(self._fd)
        self._fd = fd
        return True

    def truncate(self, size: int) -> None:
        """Cut the file back to ``size`` bytes (shrinking needs no free space)."""
        if self._fd is None:
            return
        try:
            os.ftruncate(self._fd, size)
            os.lseek(self._fd, size, os.SEEK_SET)
        except OSError:
            return  # the pieces before are whole either way; the next append says what is wrong
        self.size = size

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
