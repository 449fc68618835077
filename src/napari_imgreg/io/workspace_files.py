"""The files of a workspace folder (``campaign.imgreg/``), as plain JSON and arrays.

A workspace folder holds one versioned manifest, ``workspace.json``, and one
sub-folder per photo (``photos/<key>/``) with that photo's own files, so that
saving one photo never rewrites another's (docs/formats.md, "Workspace
folder"). This module only reads and writes those files as dicts, lists and
arrays; turning them into a :class:`~napari_imgreg.workspace.Workspace` (and
writing the interpretation GeoJSON through :mod:`napari_imgreg.interpret.files`)
is :mod:`napari_imgreg.workspace`'s job, one layer up.

Every write goes through :mod:`napari_imgreg._atomic`: a file is either its
old complete self or its new complete self. The manifest is written last, so
a crash between a photo's files and the manifest leaves the manifest naming
only photos whose files are complete.

Versions: ``1`` is today's layout. A manifest without ``format``/``version``
(or ``version`` 0) is the single-file state of the development versions'
``Workspace.to_dict()`` and is migrated by :func:`migrate_v0`; any other
version is refused with one line naming the file and the version.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import socket
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from .._atomic import atomic_path, atomic_write
from .._json import dumps as strict_dumps
from .._platform import portable_name
from ..errors import InputError, input_error
from .records import read_json

__all__ = [
    "FORMAT",
    "VERSION",
    "MANIFEST",
    "PHOTOS_DIR",
    "PHOTO_STATE",
    "PHOTO_TRIALS",
    "PHOTO_RESULT",
    "PHOTO_LINES",
    "PHOTO_MATCHES",
    "FEATURES_3D",
    "MEASUREMENTS",
    "MEASUREMENTS_JSON",
    "V0_BACKUP",
    "LOCK",
    "acquire_lock",
    "release_lock",
    "is_workspace",
    "manifest_path",
    "read_manifest",
    "check_manifest",
    "migrate_v0",
    "write_json",
    "json_text",
    "write_text",
    "read_json_file",
    "write_arrays",
    "read_arrays",
    "file_ref",
    "resolve_ref",
    "photo_key",
    "file_fingerprint",
    "fingerprint_difference",
    "utc_now",
]

#: The manifest's ``format`` value.
FORMAT = "napari-imgreg workspace"
#: The manifest version this napari-imgreg writes (and the newest it reads).
VERSION = 1
#: File names inside the workspace folder.
MANIFEST = "workspace.json"
PHOTOS_DIR = "photos"
PHOTO_STATE = "photo.json"
PHOTO_TRIALS = "trials.json"
PHOTO_RESULT = "RESULT.json"
PHOTO_LINES = "LINES.geojson"
PHOTO_MATCHES = "correspondences.npz"
FEATURES_3D = "LINES3D.geojson"
MEASUREMENTS = "MEASUREMENTS.csv"
#: The measurements at full precision, for reopening (MEASUREMENTS.csv is for people).
MEASUREMENTS_JSON = "measurements.json"
#: The version-0 manifest is kept under this name when it is migrated.
V0_BACKUP = "workspace.v0.json"
#: Held by the session saving into the folder: a second writer would undo the first's saves.
LOCK = "workspace.lock"


def utc_now() -> str:
    """The time now, ISO 8601 in UTC to the second (``2026-12-01T20:53:51Z``)."""
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def manifest_path(folder: str | os.PathLike) -> Path:
    return Path(folder) / MANIFEST


def is_workspace(folder: str | os.PathLike) -> bool:
    """Whether ``folder`` holds a workspace manifest."""
    return manifest_path(folder).is_file()


# ------------------------------------------------------------------ writing
def json_text(data: Any, compact: bool = False) -> str:
    """``data`` as the text a workspace file holds: strict JSON (non-finite
    numbers are ``null``, see :mod:`napari_imgreg._json`), indented, or
    ``compact`` (one line: the files rewritten at every edit, which Python's
    C encoder writes several times faster)."""
    kwargs = {"separators": (",", ":")} if compact else {"indent": 1}
    try:  # plain data with finite numbers (nearly always): the C encoder as it is
        return json.dumps(data, allow_nan=False, **kwargs) + "\n"
    except (ValueError, TypeError):  # a non-finite number or a NumPy value: convert
        return strict_dumps(data, **kwargs) + "\n"


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically (UTF-8)."""
    with atomic_write(path, encoding="utf-8") as fh:
        fh.write(text)


def write_json(path: str | os.PathLike, data: Any) -> str:
    """Write ``data`` as strict JSON, atomically; returns the text written
    (serialised first: a value that has no JSON form writes nothing)."""
    text = json_text(data)
    write_text(path, text)
    return text


def write_arrays(path: str | os.PathLike, arrays: dict[str, np.ndarray]) -> None:
    """Write named arrays as an uncompressed ``.npz``, atomically."""
    with atomic_path(path, suffix=".npz") as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **arrays)


# ------------------------------------------------------------------ reading
def read_json_file(path: str | os.PathLike) -> Any:
    """A workspace JSON file; one :class:`InputError` line when missing or corrupt."""
    return read_json(path)


def read_arrays(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The arrays of a ``.npz`` (empty when the file is missing).

    Raises
    ------
    InputError
        The file exists but is not a readable ``.npz``.
    """
    path = Path(path)
    if not path.exists():
        return {}
    try:
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError) as exc:
        raise input_error(path, f"not a readable .npz ({exc})") from None


def check_manifest(data: Any, path: str | os.PathLike) -> int:
    """The version of a manifest dict; refuses what this version cannot read.

    Returns
    -------
    int
        0 (a single-file ``Workspace.to_dict()`` state, to migrate) or :data:`VERSION`.

    Raises
    ------
    InputError
        Not a workspace manifest, or a version other than 0 and 1 (one line
        naming the file and the version).
    """
    if not isinstance(data, dict):
        raise input_error(path, "not a napari-imgreg workspace manifest (not a JSON object)")
    fmt = data.get("format")
    if fmt is None and "version" not in data:
        if "photos" in data and "scene" in data:
            return 0  # Workspace.to_dict() in one file: no format, no version
        raise input_error(path, "not a napari-imgreg workspace manifest (no 'format' field)")
    if fmt is not None and fmt != FORMAT:
        raise input_error(path, f"not a napari-imgreg workspace manifest (format {fmt!r}, "
                                f"expected {FORMAT!r})")
    version = data.get("version")
    if isinstance(version, bool) or not isinstance(version, int):
        raise input_error(path, f"workspace version {version!r} is not known "
                                f"(this napari-imgreg reads versions 0 to {VERSION})")
    if version > VERSION:
        raise input_error(path, f"workspace version {version} is newer than this napari-imgreg "
                                f"reads (up to {VERSION}): update napari-imgreg to open it")
    if version not in (0, VERSION):
        raise input_error(path, f"workspace version {version} is not known "
                                f"(this napari-imgreg reads versions 0 to {VERSION})")
    return version


def read_manifest(folder: str | os.PathLike) -> tuple[dict, int]:
    """Read and check a workspace's manifest.

    Returns
    -------
    manifest : dict
        As stored (version 0 is returned as it is; see :func:`migrate_v0`).
    version : int
        The version it was stored in.

    Raises
    ------
    InputError
        No manifest, invalid JSON, or a version this napari-imgreg does not read.
    """
    path = manifest_path(folder)
    if not Path(folder).is_dir():
        raise input_error(folder, "no such workspace folder")
    if not path.exists():
        raise input_error(path, "no such file: not a napari-imgreg workspace folder")
    data = read_json(path)
    return data, check_manifest(data, path)


# ---------------------------------------------------------------- migration
def migrate_v0(data: dict, folder: str | os.PathLike) -> tuple[dict, list[dict]]:
    """A version-0 state (``Workspace.to_dict()`` in one file) as version 1.

    Version 0 kept everything inline: ``scene`` (absolute paths), ``params``,
    ``current`` and ``photos``, each with ``photo``, ``record``, ``camera``,
    ``pose``, ``pose_label``, ``runs``, ``trials`` (``{run, kind, trial}``),
    ``selected_trial``, ``pairs``, ``sun`` and ``interpretations`` (inline
    ``{geometry, pixels, properties}``). It had no prior, no undo/redo stacks
    and no RESULT.json; those start empty (the prior is rebuilt from the
    sensor record on opening).

    Parameters
    ----------
    data : dict
        The version-0 document.
    folder : path-like
        The workspace folder (to make the paths relative).

    Returns
    -------
    manifest : dict
        A version-1 manifest.
    photos : list of dict
        Per photo, in manifest order: ``{"state": photo.json dict, "trials":
        trials list, "interpretations": inline list}`` for the caller to
        write in version-1 form.
    """
    folder = Path(folder)
    scene = data.get("scene") or {}
    photos_in = data.get("photos") or []
    if not isinstance(photos_in, list):
        raise input_error(manifest_path(folder), "version-0 'photos' must be a list")
    entries, photos, keys = [], [], set()
    for k, p in enumerate(photos_in):
        if not isinstance(p, dict) or "photo" not in p:
            raise input_error(manifest_path(folder), f"version-0 photo {k + 1}: no 'photo' path")
        key = photo_key(p["photo"], keys)
        entries.append({"key": key, "photo": file_ref(p["photo"], folder)})
        history = {"current": p.get("pose"), "label": p.get("pose_label", "prior"),
                   "undo": [], "redo": []}
        state = {
            "photo": file_ref(p["photo"], folder),
            "record": file_ref(p.get("record"), folder) if p.get("record") else None,
            "camera": p.get("camera"),
            "prior": None,
            "history": history,
            "runs": int(p.get("runs", 0)),
            "selected_trial": p.get("selected_trial"),
            "result_trials": None,
            "pairs": p.get("pairs") or {},
            "sun": p.get("sun"),
            "sun_estimate": None,
            "manual_solution": None,
        }
        photos.append({"state": state, "trials": list(p.get("trials") or []),
                       "interpretations": list(p.get("interpretations") or [])})
    manifest = {
        "format": FORMAT, "version": VERSION, "saved": utc_now(),
        "migrated_from": 0,
        "scene": {name: file_ref(scene.get(name), folder) if scene.get(name) else None
                  for name in ("mesh", "dem", "georef")},
        "params": data.get("params") or {},
        "photos": entries,
        "current": data.get("current"),
        "projection": None,
    }
    return manifest, photos


# -------------------------------------------------------------------- paths
def file_ref(path: str | os.PathLike | None, folder: str | os.PathLike) -> dict | None:
    """A file as a workspace stores it: relative to the workspace folder when
    possible (so a campaign moved with its data still opens), and absolute
    (so a workspace moved alone still finds it).

    Returns
    -------
    dict or None
        ``{"path": relative (POSIX) or absolute, "absolute": absolute}``.
    """
    if path is None or str(path) == "":
        return None
    absolute = Path(os.path.abspath(path))
    try:
        rel = Path(os.path.relpath(absolute, os.path.abspath(folder))).as_posix()
    except ValueError:  # another drive (Windows): no relative path
        rel = absolute.as_posix()
    return {"path": rel, "absolute": absolute.as_posix()}


def resolve_ref(ref: Any, folder: str | os.PathLike) -> Path | None:
    """The file a stored reference points to: the relative path if that
    exists, else the absolute one (else the relative one, for the error)."""
    if ref is None or ref == "":
        return None
    if isinstance(ref, str):  # a bare path
        ref = {"path": ref}
    if not isinstance(ref, dict) or not ref.get("path"):
        raise InputError(f"{manifest_path(folder)}: a file reference must be "
                         f"{{'path': ...}}, got {ref!r}")
    rel = Path(ref["path"])
    candidate = rel if rel.is_absolute() else Path(folder) / rel
    if candidate.exists() or not ref.get("absolute"):
        return Path(os.path.normpath(candidate))
    absolute = Path(ref["absolute"])
    return absolute if absolute.exists() else Path(os.path.normpath(candidate))


#: Bytes read from each end of a file for its fingerprint.
FINGERPRINT_BYTES = 1 << 16


def file_fingerprint(path: str | os.PathLike | None) -> dict | None:
    """What tells a file from a newer version of it under the same name, cheaply.

    Its size and a hash of its size and first and last 64 KiB: a photo's
    header (EXIF, start of its data) and a model re-exported or edited differ
    there, and reading 128 KiB stays quick for a 1 GB mesh and for 300 photos.
    Dates are left out: a copy to another disk or machine changes them, not the file.

    Returns
    -------
    dict or None
        ``{"size": bytes, "blake2b": hex}``; None when there is no such file.
    """
    if path is None or str(path) == "":
        return None
    try:
        with open(path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            digest = hashlib.blake2b(str(size).encode(), digest_size=16)
            digest.update(fh.read(FINGERPRINT_BYTES))
            if size > FINGERPRINT_BYTES:
                fh.seek(max(size - FINGERPRINT_BYTES, FINGERPRINT_BYTES))
                digest.update(fh.read(FINGERPRINT_BYTES))
    except OSError:
        return None
    return {"size": int(size), "blake2b": digest.hexdigest()}


def fingerprint_difference(saved: Any, now: dict | None) -> str:
    """How a file differs from its saved fingerprint, in words ("" when it does
    not, or when either is unknown: a file missing is reported where it is read)."""
    if not isinstance(saved, dict) or not saved.get("blake2b") or now is None:
        return ""
    if saved.get("size") != now["size"]:
        return f"{saved.get('size')} bytes then, {now['size']} now"
    return "" if saved["blake2b"] == now["blake2b"] else "same size, other content"


def photo_key(photo: str | os.PathLike, taken: set[str]) -> str:
    """A folder name for a photo: its stem, made unique among ``taken`` (added to it).

    Letters, digits and ``-_.`` are kept, anything else becomes ``_``; the
    name is then made one every system accepts
    (:func:`~napari_imgreg._platform.portable_name`): a photo ``CON.jpg`` or
    ``IMG..jpg`` gets a folder Windows can make, ``...jpg`` one inside
    ``photos/`` (not ``photos/..``). Unique ignoring case, as the folders
    are on Windows' and macOS's disks.
    """
    stem = "".join(c if c.isalnum() or c in "-_." else "_" for c in Path(photo).stem)
    stem = portable_name(stem, fallback="photo")
    key, n = stem, 2
    while key.lower() in {t.lower() for t in taken}:
        key, n = f"{stem}_{n}", n + 1
    taken.add(key)
    return key


# -------------------------------------------------------------------- lock
def _process_alive(pid: int) -> bool:
    """Whether process ``pid`` runs on this machine.

    psutil, not ``os.kill(pid, 0)``: on Windows signal 0 is CTRL_C_EVENT,
    which would interrupt the lock's holder (or fail, and the holder's lock
    be taken for stale).
    """
    import psutil

    try:
        return psutil.pid_exists(pid) and psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False
    except psutil.Error:  # alive, another user's
        return True


#: How long a lock file that cannot be read yet is taken for one being
#: written by another session starting at the same moment, seconds.
LOCK_UNREADABLE_GRACE_S = 2.0

#: Age beyond which a takeover guard (``NAME.takeover``) is taken for one left
#: by a session that died while taking a stale lock over, seconds; a takeover
#: holds it for a few milliseconds.
TAKEOVER_GUARD_STALE_S = 5.0


def _create_lock(path: Path, text: str) -> bool:
    """Create ``path`` holding ``text``, all at once; False when it exists.

    The text goes into a temporary file first, then a hard link gives it the
    lock's name (refused when that name exists): another session never sees
    the lock empty or half-written, which it would take for a stale lock
    and take over. Where hard links are not supported (some network and FAT
    file systems) the file is created exclusively and then written.
    """
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}")
    tmp.write_text(text, encoding="utf-8")
    try:
        os.link(tmp, path)
        return True
    except FileExistsError:
        return False
    except OSError:  # no hard links here
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            return False
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        return True
    finally:
        tmp.unlink(missing_ok=True)


def _remove_stale_lock(path: Path, stale: bytes | None) -> int:
    """Delete the lock at ``path`` if it still holds ``stale``; 1 when it did.

    Two sessions that read the same stale lock would each delete "it" and
    create their own, and the later deletion would remove the other's new
    lock: both would then hold the folder. So the check and the deletion are
    done together under a guard file (``NAME.takeover``) that one session at
    a time creates; a lock that changed since it was read is left alone (the
    caller reads it again). A guard older than :data:`TAKEOVER_GUARD_STALE_S`
    was left by a session that died in the middle and is removed.
    """
    guard = path.with_name(f"{path.name}.takeover")
    if not _create_lock(guard, json_text({"pid": os.getpid(), "host": socket.gethostname(),
                                          "since": utc_now()})):
        try:
            if time.time() - guard.stat().st_mtime > TAKEOVER_GUARD_STALE_S:
                guard.unlink(missing_ok=True)
        except OSError:
            pass
        time.sleep(0.02)  # another session is taking it over: read the lock again
        return 0
    try:
        try:
            still_stale = stale is not None and path.read_bytes() == stale
        except FileNotFoundError:
            return 0
        except OSError:  # unreadable as before: the caller's grace has passed
            still_stale = stale is None
        if still_stale:
            try:
                path.unlink(missing_ok=True)
            except PermissionError:  # Windows: another session is reading it this instant
                return 0  # the caller reads it again
            return 1
        return 0
    finally:
        guard.unlink(missing_ok=True)


def acquire_lock(folder: str | os.PathLike, own_stale: bool = True, lock_name: str = LOCK,
                 kind: str = "workspace") -> str:
    """Take the folder's ``workspace.lock`` for this process; returns its token.

    ``lock_name`` and ``kind`` (``"workspace"``, or ``"batch"`` for the
    ``batch.lock`` of a results folder) name the lock and the session the
    error lines speak of.

    A lock left by a process that is gone (killed, crashed) on this machine is
    taken over; so is one of this process (``own_stale``: the caller knows no
    live session of its own holds the folder). A lock that cannot be read is
    taken over only once it is :data:`LOCK_UNREADABLE_GRACE_S` old (before
    that it may be another session's, being written).

    Raises
    ------
    InputError
        Another live napari-imgreg session saves into the folder, or one on
        another machine (which cannot be checked): the line says which and how
        to go on.
    """
    path = Path(folder) / lock_name
    host, pid = socket.gethostname(), os.getpid()
    token = uuid.uuid4().hex
    text = json_text({"pid": pid, "host": host, "since": utc_now(), "token": token})
    takeovers = 0
    deadline = time.monotonic() + LOCK_UNREADABLE_GRACE_S + 1.0
    while takeovers < 3 and time.monotonic() < deadline:
        if _create_lock(path, text):
            return token
        try:
            raw = path.read_bytes()
        except FileNotFoundError:  # given back meanwhile
            continue
        except OSError:
            raw = None
        try:
            held = json.loads(raw.decode("utf-8"))
            other_pid, other_host = int(held["pid"]), str(held["host"])
        except (AttributeError, ValueError, KeyError, TypeError):
            try:
                age_s = time.time() - path.stat().st_mtime
            except OSError:
                continue
            if age_s < LOCK_UNREADABLE_GRACE_S:  # another session's, being written
                time.sleep(0.1)
                continue
            held, other_pid, other_host = {}, -1, host  # a torn write long ago: stale
        since = held.get("since", "?")
        if other_host != host:
            if kind == "batch":
                raise input_error(folder, f"a napari-imgreg batch on {other_host} (pid "
                                          f"{other_pid}, since {since}) writes its results "
                                          f"here; let it end or stop it there, or delete "
                                          f"{lock_name} if it is gone")
            raise input_error(folder, f"is open in napari-imgreg on {other_host} (pid "
                                      f"{other_pid}, since {since}); close it "
                                      f"there, or delete {lock_name} if that session is gone")
        if other_pid == pid and not own_stale:
            raise input_error(folder, "is already open in this session")
        if other_pid != pid and other_pid > 0 and _process_alive(other_pid):
            if kind == "batch":
                raise input_error(folder, f"another napari-imgreg batch (pid {other_pid}, since "
                                          f"{since}) writes its results here: let it end or "
                                          f"stop it, or delete {lock_name} if no batch runs")
            # (Nothing opens a folder read-only in the workbench: say what to do instead.)
            raise input_error(folder, f"is open in another napari-imgreg (pid {other_pid}, "
                                      f"since {since}): close it first, or "
                                      f"delete {lock_name} if no napari-imgreg has it open")
        takeovers += _remove_stale_lock(path, raw)  # stale: its process is gone
    raise input_error(path, f"could not take the {kind} lock (another session keeps taking it)")


def release_lock(folder: str | os.PathLike, token: str, lock_name: str = LOCK) -> None:
    """Give the lock back, if it is still this token's."""
    path = Path(folder) / lock_name
    try:
        if json.loads(path.read_text(encoding="utf-8")).get("token") == token:
            path.unlink()
    except (OSError, ValueError, AttributeError):
        pass
