"""Atomic file writes: nothing already saved is lost or half-overwritten."""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
import time
from pathlib import Path
from typing import IO, Iterator

from . import _platform

__all__ = [
    "atomic_write", "atomic_path", "umask", "file_mode", "resolve_target", "fsync_dir", "fsync_file",
    "replace_file", "OutputError",
]


class OutputError(OSError):
    """An output file could not be written (a folder in its way, no
    permission, a full disk): its message is one line naming the file and
    why, its ``errno`` the system's. The command line prints the line and
    exits with 2, as for bad input.

    Parameters
    ----------
    path : path-like
        The output as the caller named it (a link, not its target).
    cause : OSError
        What the operating system said.
    """

    def __init__(self, path: str | os.PathLike, cause: OSError):
        if isinstance(cause, IsADirectoryError):
            reason = "it is a folder, not a file"
        elif isinstance(cause, (FileExistsError, NotADirectoryError)):  # from making its folder
            reason = "a file is in the way of its folder"
        else:
            reason = (_platform.held_open_hint(Path(path), cause)
                      or cause.strerror or " ".join(str(cause).split()) or type(cause).__name__)
        super().__init__(f"{os.fspath(path)}: cannot write ({reason})")
        # errno only: with strerror or filename set, OSError's str() would
        # become "[Errno n] ..." instead of the one line above.
        self.errno = cause.errno
        self.path = Path(path)

    def __reduce__(self):
        # Rebuilt from its message (a batch worker sends it to the client):
        # the default would call __init__ with the message alone.
        return _output_error_from, (self.args[0], self.errno, os.fspath(self.path))


#: Errors of writing itself (not of what the writer reads): no space, no
#: quota, a file too large, the drive failing, a read-only file system.
_WRITE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO, errno.EROFS}


def _output_error_from(message: str, errno: int | None, path: str) -> OutputError:
    """An :class:`OutputError` with ``message`` as is (for unpickling)."""
    error = OutputError.__new__(OutputError)
    OSError.__init__(error, message)
    error.errno, error.path = errno, Path(path)
    return error


def umask() -> int:
    """The process umask, read without changing it (``os.umask`` would race
    with other threads); 0o022 where /proc is not available."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text(encoding="utf-8").splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    return 0o022


def file_mode(target: Path) -> int:
    """The mode a replaced file keeps, or what a plain ``open()`` would give."""
    try:
        return target.stat().st_mode & 0o777
    except OSError:
        return 0o666 & ~umask()


def resolve_target(path: str | os.PathLike) -> Path:
    """The file a write to ``path`` must replace: a symlink is followed (to
    its final target, even a dangling one), so the link stays a link and the
    file it points to gets the new content."""
    target = Path(path)
    # A bounded loop rather than Path.resolve(): only the last component's
    # links matter and a link cycle must not hang.
    for _ in range(40):
        if not target.is_symlink():
            return target
        link = Path(os.readlink(target))
        target = link if link.is_absolute() else target.parent / link
    raise OSError(f"{os.fspath(path)}: too many levels of symbolic links")


def fsync_dir(folder: str | os.PathLike) -> None:
    """Flush a folder's entries (a rename or a new file) to the disk.

    Without it a power cut shortly after a rename can leave the old name, or
    an empty file, on file systems that journal metadata lazily. Folders that
    cannot be opened for this (some network and Windows file systems) are
    skipped: the rename itself has still happened.
    """
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _flush_open_flags() -> int:
    """``os.open`` flags for a descriptor ``os.fsync`` accepts: read-only on
    POSIX (fsync flushes through any descriptor, whatever the file's mode),
    read-write in binary mode on Windows, where ``os.fsync`` is
    ``FlushFileBuffers``, which refuses a handle without write access (EBADF)."""
    if _platform.WINDOWS:
        return os.O_RDWR | getattr(os, "O_BINARY", 0)
    return os.O_RDONLY


def fsync_file(path: str | os.PathLike) -> None:
    """Flush a written file's content to the disk (before it is renamed into place).

    On Windows the file must still be writable: call this before the file
    gets a read-only mode (:func:`atomic_path` does).
    """
    fd = os.open(path, _flush_open_flags())
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


#: Pauses between the tries of a rename Windows refuses, seconds (0.75 s in all).
WINDOWS_RENAME_RETRY_S = (0.05, 0.1, 0.2, 0.4)


def replace_file(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    """``os.replace``; on Windows tried again for a moment when refused.

    A virus scanner or the search indexer opens a file that was just written
    for a moment, and Windows will not rename a file that is open (nor
    replace one): ``PermissionError``. A program holding the file for longer
    (Excel) still gets the error, after :data:`WINDOWS_RENAME_RETRY_S`.
    """
    for pause in WINDOWS_RENAME_RETRY_S if _platform.WINDOWS else ():
        try:
            os.replace(src, dst)
            return
        except PermissionError:
            time.sleep(pause)
    os.replace(src, dst)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it over ``path`` on success.

    Parameters
    ----------
    path : path-like
        The file to write. A symlink is followed: the file it points to is
        replaced (the temporary file sits beside it, so the rename stays on
        one file system) and the link is kept.
    suffix : str, optional
        The temporary file's extension; default: that of ``path`` *as given*.

    Yields
    ------
    Path
        The temporary file to write, which ends with ``path``'s extension.

    Notes
    -----
    The temporary file takes its extension from the name the caller gave,
    not from a link's target: writers choose the format from it (OpenCV,
    matplotlib) or append their own when it is missing (``np.save`` adds
    ``.npy``), so with ``d.npy -> store/abc123`` the temporary must still end
    in ``.npy``, else the data would go to a stray ``<temporary>.npy`` and the
    target would be replaced by an empty file.

    On any error the temporary file is removed and ``path`` is untouched; an
    :class:`OSError` of making the temporary file or of the rename is raised
    as an :class:`OutputError` naming ``path``. Durability: the temporary file is
    fsynced before the rename and its folder after it, so once this returns
    the new content survives a power cut (never an empty file under the new
    name).
    """
    target = resolve_target(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(
            prefix=f".{target.name}.", suffix=suffix if suffix is not None else Path(path).suffix,
            dir=target.parent,
        )
    except OSError as exc:
        raise OutputError(path, exc) from exc
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        try:
            yield tmp_path
            # Flushed while still writable: Windows opens it read-write to
            # flush, which a read-only target's mode would then forbid.
            fsync_file(tmp_path)
            # mkstemp makes the file private (0600): give it the target's mode.
            os.chmod(tmp_path, file_mode(target))
        except OSError as exc:
            # A full disk (or quota, or a dying drive) while writing names no
            # file: say which output it was. Other errors are the writer's.
            if exc.errno in _WRITE_ERRNOS and not isinstance(exc, OutputError):
                raise OutputError(path, exc) from exc
            raise
        try:
            replace_file(tmp_path, target)  # a folder in the way, an immutable file: refused
        except OSError as exc:
            raise OutputError(path, exc) from exc
    except BaseException:
        with contextlib.suppress(OSError):
            tmp_path.unlink()
        raise
    fsync_dir(target.parent)


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w", **kwargs) -> Iterator[IO]:
    """Open a temporary file beside ``path`` for writing; rename on success."""
    with atomic_path(path) as tmp:
        with open(tmp, mode, **kwargs) as fh:
            yield fh
