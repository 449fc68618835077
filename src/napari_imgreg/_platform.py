"""What differs between Linux, macOS and Windows, kept in one place.

Field geologists run the tool on Windows and macOS laptops; CI runs on Linux.
The rules here are the ones that make a difference to this package: where a
cache belongs, which file names Windows refuses, what its console can print
and what it says when a file is held open by another program. The tests
emulate each platform through :data:`WINDOWS` and these helpers
(tests/test_portability.py).
"""

from __future__ import annotations

import codecs
import contextlib
import errno
import os
import re
import sys
from pathlib import Path
from typing import Iterator

__all__ = [
    "WINDOWS", "cache_root", "portable_name", "tolerant_console", "held_open_hint", "held_open",
]

#: Windows rules apply (a module flag, so tests can emulate them on Linux).
WINDOWS = os.name == "nt"

#: The environment variable that overrides :func:`cache_root`.
CACHE_ENV = "NAPARI_IMGREG_CACHE"

#: Device names Windows reserves in every folder, with any extension
#: (``con.jpg`` too): a file or folder cannot have them.
WINDOWS_RESERVED_NAMES = frozenset(
    ["CON", "PRN", "AUX", "NUL", "CONIN$", "CONOUT$"]
    + [f"{dev}{n}" for dev in ("COM", "LPT") for n in (*"123456789", "¹", "²", "³")]
)

#: Characters no Windows file name may hold (and ``/``, nowhere allowed), and
#: the control characters.
_FORBIDDEN_CHARS = re.compile(r'[<>:"/\\|?*\x00-\x1f]')

#: Longest name :func:`portable_name` makes, characters: leaves room for a
#: workspace's folders within Windows' 260-character paths.
PORTABLE_NAME_MAX = 100


def cache_root() -> Path:
    """Where the caches live: ``$NAPARI_IMGREG_CACHE``, or the user cache
    folder of the system (``~/.cache/napari-imgreg`` on Linux, or under
    ``$XDG_CACHE_HOME``; ``~/Library/Caches/napari-imgreg`` on macOS;
    ``%LOCALAPPDATA%\\napari-imgreg\\Cache`` on Windows)."""
    env = os.environ.get(CACHE_ENV)
    if env:
        return Path(env).expanduser()
    import platformdirs

    return Path(platformdirs.user_cache_dir("napari-imgreg", appauthor=False))


def portable_name(text: str, fallback: str = "file") -> str:
    """``text`` made a file or folder name every system accepts.

    Characters Windows forbids (``<>:"/\\|?*``, control characters) become
    ``_``; trailing dots and spaces (which Windows drops, so two names would
    meet) go; a reserved device name (``CON``, ``NUL``, ``COM1``, also with an
    extension) gets a ``_`` after its first part; ``.`` and ``..`` and an
    empty result become ``fallback``; the name is cut to
    :data:`PORTABLE_NAME_MAX` characters.

    Parameters
    ----------
    text : str
        A photo's stem, a label: text a user chose.
    fallback : str
        The name when nothing usable is left.

    Returns
    -------
    str
        The name (``text`` itself when it is already portable).
    """
    name = _FORBIDDEN_CHARS.sub("_", text)[:PORTABLE_NAME_MAX].rstrip(". ")
    if not name.strip("."):
        return fallback
    first, dot, rest = name.partition(".")
    if first.rstrip(" ").upper() in WINDOWS_RESERVED_NAMES:
        name = f"{first}_{dot}{rest}"
    return name


@contextlib.contextmanager
def tolerant_console() -> Iterator[None]:
    """Let stdout and stderr print any text while the block runs.

    A Windows console is UTF-8 for Python, but output redirected to a file or
    a pipe (``> log.txt``, a GUI running the command) is encoded in the
    system's code page (cp1252, cp437): a ``σ``, ``→`` or a photo's name in
    another script would raise :class:`UnicodeEncodeError` and end the
    command. Streams whose encoding cannot hold every character print such
    characters as ``\\u03c3`` escapes instead; UTF-8 streams are left alone.
    """
    changed = []
    for stream in (sys.stdout, sys.stderr):
        reconfigure = getattr(stream, "reconfigure", None)
        if reconfigure is None or getattr(stream, "errors", None) != "strict" \
                or _encodes_all_text(getattr(stream, "encoding", None)):
            continue
        with contextlib.suppress(ValueError, OSError):  # a closed or detached stream
            reconfigure(errors="backslashreplace")
            changed.append(stream)
    try:
        yield
    finally:
        for stream in changed:
            with contextlib.suppress(ValueError, OSError):
                stream.reconfigure(errors="strict")


def _encodes_all_text(encoding: str | None) -> bool:
    """Whether ``encoding`` is a Unicode one (every character has its bytes)."""
    try:
        name = codecs.lookup(encoding or "ascii").name
    except LookupError:
        return False
    return name.startswith(("utf-8", "utf-16", "utf-32")) or name == "gb18030"


#: Windows errors of a file another program holds open (or a read-only one):
#: ERROR_ACCESS_DENIED, ERROR_SHARING_VIOLATION, ERROR_LOCK_VIOLATION.
_WINDOWS_HELD_OPEN_ERRORS = (5, 32, 33)


def held_open_hint(target: Path, cause: OSError) -> str | None:
    """Why Windows refused to replace ``target``, in words a user can act on.

    Windows cannot replace or delete a file another program has open (a CSV
    in Excel, a GeoPackage in QGIS): the rename fails with "Access is
    denied". None when ``cause`` is not that (or not on Windows).
    """
    if not WINDOWS or not isinstance(cause, PermissionError) or not target.is_file():
        return None
    winerror = getattr(cause, "winerror", None)
    if winerror is not None and winerror not in _WINDOWS_HELD_OPEN_ERRORS:
        return None
    return ("it is open in another program, or read-only: close it there "
            "(Excel, QGIS, a viewer) and run again")


def held_open(exc: OSError) -> bool:
    """Whether a refused write is Windows refusing to replace a file that
    another program holds open (an :class:`~napari_imgreg._atomic.OutputError`
    keeps the system's errno)."""
    return WINDOWS and exc.errno in (errno.EACCES, errno.EPERM)
