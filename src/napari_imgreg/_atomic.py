"""Atomic file writes: nothing already saved is lost or half-overwritten."""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import IO, Iterator

__all__ = [
    "atomic_write", "atomic_path", "umask", "file_mode", "resolve_target", "fsync_dir", "fsync_file",
]


def umask() -> int:
    """The process umask, read without changing it (``os.umask`` would race
    with other threads); 0o022 where /proc is not available."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
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


def fsync_file(path: str | os.PathLike) -> None:
    """Flush a written file's content to the disk (before it is renamed into place)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it over ``path`` on success.

    The temporary file keeps the target's extension (so writers that choose a
    format by extension, such as OpenCV or tifffile, still work). On any error
    the temporary file is removed and ``path`` is untouched.

    Durability: the temporary file is fsynced before the rename and its
    folder after it, so once this returns the new content survives a power
    cut (never an empty file under the new name). A symlinked ``path`` is
    followed: the file it points to is replaced and the link is kept.
    """
    target = resolve_target(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{target.name}.", suffix=suffix if suffix is not None else target.suffix,
        dir=target.parent,
    )
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        # mkstemp makes the file private (0600): give it the target's mode.
        os.chmod(tmp_path, file_mode(target))
        fsync_file(tmp_path)
        os.replace(tmp_path, target)
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
