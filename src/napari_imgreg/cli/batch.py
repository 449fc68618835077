"""``napari-imgreg batch``: register every photo of a field scene folder (contract §8).

After fieldwork a scene folder holds one textured mesh, optionally a DEM
(``dem.tif`` / ``dem.asc``) and ``georef.json``, and the day's photos, each
with an optional sensor record ``PHOTO.json`` beside it (photos without one
fall back to their EXIF/XMP). ``batch`` checks the scene, registers the
photos on Dask distributed (a local cluster of worker processes by default,
``--workers``/``--threads-per-worker``; a running scheduler with
``--scheduler``; in this process with ``--workers 0``; see
:mod:`napari_imgreg.registration.batch` and docs/batch.md) and writes, into
RESULTS_DIR,

- ``<photo stem>.result.json`` per photo: the same RESULT.json as
  ``register`` (contract §4), written by the worker that registered it;
- ``summary.csv`` and ``summary.json``: one row per photo (status, grade,
  Q, pose, error) in name order, rewritten by this process after every
  photo. A photo whose worker died is registered again on another worker;
  one that killed ``--allowed-failures`` + 1 workers is reported as ``error``.

Every file is written atomically, so an interrupted batch (Ctrl-C, a crash)
keeps the finished results and a summary consistent with them; run it again
with ``--skip-existing`` to carry on.

A bad photo (unreadable, no sensor record and no usable EXIF, a wrong field
in its record) does not stop the batch: its one-line error goes to stderr and
into the summary's ``error`` column. A bad scene (missing folder, no mesh,
a corrupt mesh, DEM or parameter file) stops it before anything is written.

Exit code: 2 when the scene is bad or any photo had bad input, else 1 when
any registration failed its quality bar, else 0. SIGTERM (a scheduler or
``kill``) is handled like Ctrl-C: the summary is written with
``interrupted: true`` and the command exits with 143 (130 after Ctrl-C).
A closed stdout (``| head``) only silences the progress lines.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import re
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .. import _platform
from .._atomic import OutputError, atomic_write
from .._deprecated import forward_moved_names
from ._common import (
    EXIT_BAD_INPUT,
    EXIT_FAILED,
    EXIT_OK,
    Terminated,
    load_scene,
    one_line,
    print_error,
    progress_printer,
    read_params,
    say,
    sigterm_as_interrupt,
    write_json,
)
from ..errors import InputError, input_error
from ..io.meshes import MESH_SUFFIXES
from ..io.pointclouds import POINT_CLOUD_SUFFIXES
from ..scene import size_text
from ..io.photos import PHOTO_SUFFIXES
from ..registration.quality import outcome_words
from ..io.records import read_json
from ..io.workspace_files import (
    acquire_lock,
    file_fingerprint,
    fingerprint_difference,
    release_lock,
)
from ..validate import check_writable

if TYPE_CHECKING:
    from ..registration.batch import ClusterParams

# The module, not its ``register``: looked up at call time, so tests can
# substitute ``napari_imgreg.registration.pipeline.register``.

__all__ = [
    "add_parser", "run", "exit_code_of", "find_scene_files", "SceneFiles", "SUMMARY_COLUMNS",
]

#: Columns of ``summary.csv``, in order.
SUMMARY_COLUMNS = (
    "photo", "status", "grade", "Q", "n_trials", "seconds", "x", "y", "z",
    "trend_deg", "plunge_deg", "roll_deg", "reprojection_error_px", "error",
)

#: DEM file names found without ``--dem`` (any ``*.asc`` grid counts too).
_DEM_NAMES = ("dem.tif", "dem.tiff", "dem.asc")
#: TIFF tags that make a TIFF a GeoTIFF (a raster, not a photo).
_GEOTIFF_TAGS = (33550, 33922, 34264, 34735)


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``batch`` sub-command; its handler is :func:`run`."""
    p = subparsers.add_parser(
        "batch",
        help="register every photo of a scene folder (writes RESULTS_DIR)",
        description="Register every photo in SCENE_DIR (one mesh, optional dem.tif/.asc and "
        "georef.json, photos with optional PHOTO.json sensor records) on a Dask cluster (local "
        "by default). Writes RESULTS_DIR/<photo>.result.json per photo and summary.csv + "
        "summary.json, updated after every photo. A bad photo is reported and skipped; the "
        "batch goes on. Exit 0 when all registered, 1 when any failed its quality bar, 2 on "
        "bad input.",
    )
    p.add_argument("scene_dir", metavar="SCENE_DIR", help="folder with the mesh and the photos")
    p.add_argument("--out", required=True, metavar="RESULTS_DIR", help="folder for the results")
    p.add_argument("--mesh", help="the mesh, when SCENE_DIR holds several (default: the only one)")
    p.add_argument("--dem", help="DEM GeoTIFF or .asc (default: dem.tif / dem.asc in SCENE_DIR)")
    p.add_argument("--georef",
                   help="georef.json (default: the one in SCENE_DIR or beside the mesh)")
    p.add_argument("--params", metavar="PARAMS.json", help="registration parameters (any subset)")
    p.add_argument("--skip-existing", action="store_true",
                   help="keep photos whose RESULTS_DIR/<photo>.result.json exists (resume a "
                        "batch); one of another model or of an earlier version of the photo is "
                        "redone")
    p.add_argument("-v", "--verbose", action="store_true",
                   help="print progress within each photo (with --workers 0 only)")
    add_cluster_arguments(p)
    p.set_defaults(func=run)
    return p


def _ranged(convert, noun: str, unit: str, low, high, what: str):
    """An argparse type: a number (``convert``: int or float) in [low, high]."""

    def parse(text: str):
        try:
            value = convert(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} must be {noun}, not {text!r}") from None
        if not low <= value <= high:  # also refuses nan
            raise argparse.ArgumentTypeError(f"{what} must be {low:g}-{high:g}{unit}, not {text}")
        return value

    return parse


def _count(low: int, high: int, what: str):
    """An argparse type: an integer in [low, high]."""
    return _ranged(int, "a whole number", "", low, high, what)


def _seconds(low: float, high: float, what: str):
    """An argparse type: a number of seconds in [low, high]."""
    return _ranged(float, "a number of seconds", " s", low, high, what)


def add_cluster_arguments(p: argparse.ArgumentParser) -> None:
    """The Dask options of ``batch`` and ``workspace register`` (docs/batch.md)."""
    g = p.add_argument_group(
        "where the photos are registered (Dask distributed; docs/batch.md)",
        "By default a local cluster: one worker process per core (at most one per photo), "
        "each loading the scene once. A photo whose worker dies is retried on another.")
    g.add_argument("--workers", type=_count(0, 1024, "--workers"), metavar="N",
                   help="local worker processes (default: cores / threads per worker, at most "
                   "one per photo); 0: no cluster, one photo after another in this process")
    g.add_argument("--threads-per-worker", type=_count(1, 256, "--threads-per-worker"),
                   metavar="M", help="threads of each local worker, and the size of its "
                   "OpenCV/BLAS/ray-cast pools (default 1)")
    g.add_argument("--scheduler", metavar="ADDRESS",
                   help="use the workers of a running Dask scheduler (tcp://host:8786 or a "
                   "scheduler.json file) instead of a local cluster")
    g.add_argument("--allowed-failures", type=_count(0, 100, "--allowed-failures"), default=2,
                   metavar="K", help="give a photo up after its worker died K+1 times "
                   "(default 2; local clusters)")
    g.add_argument("--connect-timeout", type=_seconds(1.0, 3600.0, "--connect-timeout"),
                   default=30.0, metavar="SECONDS",
                   help="with --scheduler: how long to wait for it to answer, and to reconnect "
                   "when the connection drops mid-run (default 30)")


def cluster_params(args: argparse.Namespace) -> ClusterParams:
    """The :class:`ClusterParams` of the command line's options."""
    from ..registration.batch import ClusterParams

    return ClusterParams(workers=args.workers, threads_per_worker=args.threads_per_worker,
                         scheduler=args.scheduler, allowed_failures=args.allowed_failures,
                         connect_timeout_s=args.connect_timeout)


# ------------------------------------------------------------------ scene
@dataclass
class SceneFiles:
    """What a scene folder holds.

    Attributes
    ----------
    folder : Path
    mesh : Path
    dem : Path or None
    georef : Path or None
    photos : list of Path
        In name order.
    ignored : dict of str to str
        Image files that are not photos (textures, GeoTIFFs, ...), with why.
    """

    folder: Path
    mesh: Path
    dem: Path | None = None
    georef: Path | None = None
    photos: list[Path] = field(default_factory=list)
    ignored: dict[str, str] = field(default_factory=dict)


def _natural_key(name: str) -> list:
    """Sort ``IMG_2`` before ``IMG_10`` (and ignore case)."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def _resolve(path: str, folder: Path) -> Path:
    """A path as given, or relative to the scene folder when only that exists."""
    p = Path(path)
    if not p.exists() and not p.is_absolute() and (folder / p).exists():
        return folder / p
    return p.absolute()  # as the scene folder: the workers may run elsewhere


def _textures_named_by(mesh_files: list[Path], folder: Path) -> dict[str, str]:
    """Image files the mesh(es) and their materials use: not photos."""
    out: dict[str, str] = {}

    def add(name: str, why: str) -> None:
        name = name.strip().strip('"')
        if name:
            out[Path(name).name.lower()] = why

    for mtl in folder.iterdir():
        if mtl.suffix.lower() != ".mtl" or not mtl.is_file():
            continue
        try:
            text = mtl.read_text(encoding="utf-8", errors="replace")
        except OSError:
            continue
        for line in text.splitlines():
            parts = line.split()
            if len(parts) >= 2 and parts[0].lower().startswith(("map_", "bump", "disp", "decal")):
                add(parts[-1], f"texture in {mtl.name}")
    for mesh in mesh_files:
        suffix = mesh.suffix.lower()
        try:
            if suffix == ".gltf":
                data = json.loads(mesh.read_text(encoding="utf-8", errors="replace"))
                for image in data.get("images", []) if isinstance(data, dict) else []:
                    if isinstance(image, dict) and isinstance(image.get("uri"), str) \
                            and not image["uri"].startswith("data:"):
                        add(image["uri"], f"texture of {mesh.name}")
            elif suffix == ".ply":
                with open(mesh, "rb") as fh:
                    head = fh.read(4096).decode("latin-1")
                for line in head.split("end_header")[0].splitlines():
                    parts = line.split()
                    if len(parts) >= 3 and parts[0] == "comment" \
                            and parts[1].lower() == "texturefile":
                        add(" ".join(parts[2:]), f"texture of {mesh.name}")
        except (OSError, ValueError):
            continue
    return out


def _manifest_files(folder: Path) -> dict[str, str]:
    """Images a sample-scene manifest (``scene.json`` ``files``) names: not photos."""
    path = folder / "scene.json"
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    files = data.get("files") if isinstance(data, dict) else None
    if not isinstance(files, dict):
        return {}
    return {Path(v).name.lower(): f"scene.json: {k}"
            for k, v in files.items() if isinstance(v, str)}


def _is_geotiff(path: Path) -> bool:
    """A TIFF with georeferencing tags: a DEM or an orthophoto, not a field photo."""
    try:
        import tifffile

        from ..io.rasters import quiet_tifffile

        with quiet_tifffile(), tifffile.TiffFile(path) as tif:
            tags = tif.pages[0].tags
            return any(tags.get(code) is not None for code in _GEOTIFF_TAGS)
    except Exception:  # not readable as TIFF: load_photo will say so
        return False


def find_scene_files(
    folder: str | Path,
    mesh: str | None = None,
    dem: str | None = None,
    georef: str | None = None,
    photos_required: bool = True,
) -> SceneFiles:
    """Find the mesh, DEM, georeference and photos of a scene folder.

    ``photos_required=False``: a folder of the scene alone is one too
    (``workspace create --no-photos``).

    Raises
    ------
    InputError
        No such folder, no mesh or several (without ``mesh``), several DEMs
        (without ``dem``), a given file missing, or no photos (when required).
    """
    folder = Path(folder).absolute()  # the workers' own working folder may differ
    if not folder.exists():
        raise input_error(folder, "no such folder")
    if not folder.is_dir():
        raise input_error(folder, "is not a folder (batch needs the scene folder)")
    files = sorted((p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")),
                   key=lambda p: _natural_key(p.name))

    # A model is a mesh or a lidar point cloud (LAS/LAZ, E57, PTS/XYZ; a PLY either).
    meshes = [p for p in files if p.suffix.lower() in {*MESH_SUFFIXES, *POINT_CLOUD_SUFFIXES}]
    if mesh is not None:
        mesh_path = _resolve(mesh, folder)
        if not mesh_path.exists():
            raise input_error(mesh_path, "no such file")
    elif not meshes:
        raise input_error(folder, "no model in the folder (expected a mesh: OBJ, PLY, GLB, "
                                  "GLTF; or a point cloud: LAS, LAZ, E57, PTS, XYZ)")
    elif len(meshes) > 1:
        raise input_error(
            folder, f"several models ({', '.join(p.name for p in meshes)}): choose one with --mesh"
        )
    else:
        mesh_path = meshes[0]

    dems = [p for p in files if p.name.lower() in _DEM_NAMES or p.suffix.lower() == ".asc"]
    if dem is not None:
        dem_path: Path | None = _resolve(dem, folder)
        if not dem_path.exists():
            raise input_error(dem_path, "no such file")
    elif len(dems) > 1:
        raise input_error(
            folder, f"several DEMs ({', '.join(p.name for p in dems)}): choose one with --dem"
        )
    else:
        dem_path = dems[0] if dems else None

    if georef is not None:
        georef_path: Path | None = _resolve(georef, folder)
        if not georef_path.exists():
            raise input_error(georef_path, "no such file")
    else:
        georef_path = folder / "georef.json" if (folder / "georef.json").is_file() else None

    not_photos = {**_manifest_files(folder), **_textures_named_by(meshes + [mesh_path], folder)}
    scene = SceneFiles(folder, mesh_path, dem_path, georef_path)
    for p in files:
        if p.suffix.lower() not in PHOTO_SUFFIXES:
            continue
        key = p.name.lower()
        if dem_path is not None and p.resolve() == dem_path.resolve():
            continue
        if key in _DEM_NAMES:
            scene.ignored[p.name] = "a DEM"
        elif key in not_photos:
            scene.ignored[p.name] = not_photos[key]
        elif p.suffix.lower() in (".tif", ".tiff") and _is_geotiff(p):
            scene.ignored[p.name] = "a GeoTIFF raster (DEM or orthophoto), not a photo"
        else:
            scene.photos.append(p)
    in_subfolders = _photos_in_subfolders(folder)
    if not scene.photos and photos_required:
        shown = ", ".join(in_subfolders)
        raise input_error(folder, "no photos in the folder (expected JPEG, PNG, TIFF or HEIC files)"
                          + (f"; there are photos in its subfolders ({shown}), not read: only "
                             "the folder itself is" if in_subfolders else ""))
    for sub, count in in_subfolders.items():
        scene.ignored[sub] = f"a subfolder with {count} photo(s): only the folder itself is read"
    return scene


def _shared_records(photos: list[Path]) -> dict[str, list[str]]:
    """Sensor record name -> the photos (two or more) that read it: a record is
    found by the photo's stem, so ``IMG_0001.JPG`` and ``IMG_0001.jpg`` (two
    cameras) both take ``IMG_0001.json``."""
    readers: dict[Path, list[str]] = {}
    for photo in photos:
        record = photo.with_suffix(".json")
        if record.is_file():
            readers.setdefault(record, []).append(photo.name)
    return {record.name: names for record, names in readers.items() if len(names) > 1}


def _photos_in_subfolders(folder: Path) -> dict[str, int]:
    """``"day2/"`` -> how many photos it holds (at any depth), for each
    subfolder of ``folder`` holding photos (a campaign kept by day or camera):
    they are not read, and the command says so."""
    counts: dict[str, int] = {}
    for p in sorted(folder.glob("*/**/*")):
        parts = p.relative_to(folder).parts
        if (p.suffix.lower() in PHOTO_SUFFIXES and not any(x.startswith(".") for x in parts)
                and p.is_file()):
            counts[f"{parts[0]}/"] = counts.get(f"{parts[0]}/", 0) + 1
    return counts


def _result_names(photos: list[Path]) -> dict[Path, str]:
    """``<stem>.result.json`` per photo (``<name>.result.json`` where stems clash,
    ``<name>.<k>.result.json`` where names differ only in case).

    Unique ignoring case: ``IMG_0001.JPG`` and ``IMG_0001.jpg`` (two cameras)
    live side by side on a case-sensitive disk, but their results would be one
    file on a case-insensitive one (a Windows share, a USB drive, macOS).
    """
    stems: dict[str, int] = {}
    for p in photos:
        stems[p.stem.lower()] = stems.get(p.stem.lower(), 0) + 1
    names: dict[Path, str] = {}
    taken: set[str] = set()
    for p in photos:
        name = f"{p.stem}.result.json" if stems[p.stem.lower()] == 1 else f"{p.name}.result.json"
        k = 2
        while name.lower() in taken:
            name, k = f"{p.name}.{k}.result.json", k + 1
        taken.add(name.lower())
        names[p] = name
    return names


#: Held in RESULTS_DIR while a batch writes there ({"pid", "host", "since", "token"}).
BATCH_LOCK = "batch.lock"
#: Statuses a result file of ours may hold.
_RESULT_STATUSES = ("registered", "failed")


# ---------------------------------------------------------------- summary
def _existing_row(photo: str, path: Path) -> dict[str, Any]:
    """The summary row of an earlier run's result file, checked.

    Raises
    ------
    InputError
        The file is not JSON, not a result of ours, or its body is malformed
        (a pose, quality or metrics block of the wrong shape): the photo is
        then registered again.
    """
    existing = read_json(path)
    if not isinstance(existing, dict) or existing.get("status") not in _RESULT_STATUSES:
        raise input_error(path, "not a registration result (no status 'registered' or 'failed')")
    for block in ("pose", "quality", "metrics", "timings_s"):
        if existing.get(block) is not None and not isinstance(existing[block], dict):
            raise input_error(path, f"'{block}' is not an object")
    position = (existing.get("pose") or {}).get("position")
    if position is not None and not (isinstance(position, list) and len(position) == 3):
        raise input_error(path, "'pose.position' is not a list of three numbers")
    if existing.get("trials") is not None and not isinstance(existing["trials"], list):
        raise input_error(path, "'trials' is not a list")
    try:
        return _row_of_result(photo, existing, None)
    except (TypeError, ValueError, AttributeError, IndexError) as exc:  # any other wrong shape
        raise input_error(path, f"malformed result ({type(exc).__name__}: {one_line(exc)})") \
            from None


def _num(value: Any, digits: int) -> float | None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return round(v, digits) if math.isfinite(v) else None


def _row_of_result(photo: str, result: dict, seconds: float | None) -> dict[str, Any]:
    """A summary row from a RESULT.json dict."""
    pose = result.get("pose") or {}
    quality = result.get("quality") or {}
    metrics = result.get("metrics") or {}
    position = pose.get("position") or [None, None, None]
    if seconds is None:
        seconds = (result.get("timings_s") or {}).get("total")
    return {
        "photo": photo,
        "status": result.get("status"),
        "grade": quality.get("grade"),
        "Q": _num(quality.get("Q"), 3),
        "n_trials": len(result.get("trials") or []),
        "seconds": _num(seconds, 2),
        "x": _num(position[0], 3),
        "y": _num(position[1], 3),
        "z": _num(position[2], 3),
        "trend_deg": _num(pose.get("trend_deg"), 3),
        "plunge_deg": _num(pose.get("plunge_deg"), 3),
        "roll_deg": _num(pose.get("roll_deg"), 3),
        "reprojection_error_px": _num(metrics.get("reprojection_error_px"), 3),
        "error": "",
    }


def _error_row(photo: str, status: str, message: str, seconds: float) -> dict[str, Any]:
    row: dict[str, Any] = {c: None for c in SUMMARY_COLUMNS}
    row.update(photo=photo, status=status, seconds=_num(seconds, 2), error=message,
               skipped=False, result=None)
    return row


def _refuse_unwritable_outputs(out: Path, result_names) -> None:
    """Refuse, before the scene loads and any photo is registered, a folder
    (or a link to one) where summary.csv, summary.json or a photo's
    RESULT.json goes: found only at the first write, it would end the run
    after its work (a summary) or fail every photo (a result).

    Raises
    ------
    InputError
        ``"<file>: cannot write here: it is a folder, not a file"``.
    """
    for name in ("summary.csv", "summary.json", *result_names):
        if (out / name).is_dir():  # a link to a folder too: its target is replaced
            raise input_error(out / name, "cannot write here: it is a folder, not a file")


def _write_summary(out: Path, header: dict[str, Any], rows: list[dict[str, Any]],
                   stale: dict[str, tuple[int, int, int]] | None = None) -> None:
    """Write summary.csv and summary.json atomically (csv first, json last).

    ``stale``: the results of another model found at the start (file name ->
    stamp, :func:`_stale_results`); those still in the folder unchanged are
    named in ``stale_results``, so a later ``--skip-existing`` redoes them.
    """
    if stale:
        now = _result_stamps_of(out, stale)
        header["stale_results"] = sorted(name for name, stamp in stale.items()
                                         if now.get(name) == stamp)
    with atomic_write(out / "summary.csv", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(SUMMARY_COLUMNS)
        for row in rows:
            writer.writerow(["" if row.get(c) is None else row[c] for c in SUMMARY_COLUMNS])
    counts = {k: sum(1 for r in rows if r["status"] == k)
              for k in ("registered", "failed", "bad_input", "error")}
    counts["skipped"] = sum(1 for r in rows if r.get("skipped"))
    write_json(out / "summary.json",
               {**header, "n_done": len(rows), "counts": counts, "photos": rows})


def exit_code_of(rows: list[dict[str, Any]]) -> int:
    """2 if any photo had bad input, else 1 if any did not register, else 0."""
    if any(r["status"] == "bad_input" for r in rows):
        return EXIT_BAD_INPUT
    if any(r["status"] != "registered" for r in rows):
        return EXIT_FAILED
    return EXIT_OK


# ------------------------------------------------------------------- run
def run(args: argparse.Namespace) -> int:
    """Run ``batch``: check the scene, register every photo, keep the summary current."""
    t_start = time.perf_counter()
    # Absolute: the workers of an existing scheduler resolve a relative path
    # in their own working folder, not the one this command was run in.
    out = Path(args.out).absolute()
    if out.exists() and not out.is_dir():
        raise input_error(out, "exists and is not a folder")
    check_writable(out, folder=True)  # before the scene loads: read-only, /proc, inside a file
    # One batch writes into a results folder at a time: two would each rewrite
    # the summary with their own rows only, and replace each other's results.
    lock: dict[str, str] = {}
    if out.is_dir():  # refused before the scene loads
        lock["token"] = acquire_lock(out, lock_name=BATCH_LOCK, kind="batch")
    try:
        return _run_scene(args, out, t_start, lock)
    finally:
        if lock:
            release_lock(out, lock["token"], BATCH_LOCK)


def _run_scene(args: argparse.Namespace, out: Path, t_start: float, lock: dict[str, str]) -> int:
    """:func:`run` once RESULTS_DIR is this command's (``lock``: the token of
    its ``batch.lock``, taken here when this command creates the folder)."""
    from ..registration.batch import SceneSpec

    cluster = cluster_params(args)
    if cluster.scheduler:
        from ..registration.batch import _scheduler_address

        _scheduler_address(cluster.scheduler)  # a missing or bad scheduler file: before the scene
    # Everything about the scene is checked here, before anything is written
    # (and the mesh cache the workers load from is made once).
    files = find_scene_files(args.scene_dir, args.mesh, args.dem, args.georef)
    _refuse_unwritable_outputs(out, _result_names(files.photos).values())
    read_params(args.params)  # a bad file is refused before the scene loads
    scene = load_scene(files.mesh, georef=files.georef, dem=files.dem)
    params = read_params(args.params, scene)  # a point cloud's defaults under the file's
    if cluster.in_process:
        scene.build_engine()
    n = len(files.photos)
    say(
        f"scene {files.folder}: {files.mesh.name} ({size_text(scene)})"
        + (f", DEM {files.dem.name}" if files.dem else ", no DEM")
        + (", georeferenced" if scene.georef is not None else "")
        + f"; {n} photo{'s' if n != 1 else ''} (loaded in {time.perf_counter() - t_start:.1f} s)",
        flush=True,
    )
    for note in scene.warnings:
        say(f"  assumed: {note}")
    if files.ignored:
        say("  not photos: " + ", ".join(f"{k} ({v})" for k, v in files.ignored.items()))
    for record, sharing in _shared_records(files.photos).items():
        say(f"  warning: {len(sharing)} photos share the sensor record {record} ("
            + ", ".join(sharing) + "): each is registered from it; if they are of different "
            "cameras, rename one photo and its record")
    spec = SceneSpec(str(files.mesh), None if files.dem is None else str(files.dem),
                     None if files.georef is None else str(files.georef))
    if not cluster.in_process:
        scene = None  # each worker loads its own; this process only collects

    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    if not lock:
        lock["token"] = acquire_lock(out, lock_name=BATCH_LOCK, kind="batch")
    names = _result_names(files.photos)
    earlier = _result_stamps(out, names)
    mesh_fingerprint = file_fingerprint(files.mesh)
    other_model = _other_model(out, mesh_fingerprint)
    stale = _stale_results(out, earlier, other_model)
    if other_model and stale:
        say(f"  {out}/ holds {len(stale)} result(s) registered on another model "
            f"({other_model}): they will be registered again"
            + ("" if args.skip_existing else " and replaced"))
    if earlier.keys() - stale.keys() and not args.skip_existing:
        say(f"  {out}/ holds {len(earlier.keys() - stale.keys())} result(s) of an earlier run: "
            "they will be replaced (--skip-existing keeps them and registers only the other "
            "photos)")
    header: dict[str, Any] = {
        "scene": str(files.folder),
        "mesh": str(files.mesh),
        "dem": str(files.dem) if files.dem else None,
        "georef": str(files.georef) if files.georef else None,
        "params": str(args.params) if args.params else None,
        "mesh_fingerprint": mesh_fingerprint,
        "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "n_photos": n,
        "complete": False,
        "interrupted": False,
    }
    rows: list[dict[str, Any]] = []

    try:
        # SIGTERM unwinds as Ctrl-C (Terminated): main() reports it, exit code 143.
        with sigterm_as_interrupt():
            return _run_photos(args, files, spec, scene, params, cluster, out, names, header,
                               rows, t_start, earlier, stale)
    except InputError:
        # No scheduler answers (nothing was registered): no empty results folder left behind.
        release_lock(out, lock.pop("token"), BATCH_LOCK)
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        raise


def _run_photos(args, files, spec, scene, params, cluster, out, names, header, rows,
                t_start, earlier, stale) -> int:
    """The photo loop of :func:`run`; the summary is current after every photo.

    Results kept from an earlier run (``--skip-existing``) come first; the
    others are tasks of a :class:`~napari_imgreg.registration.batch.PhotoRunner`,
    which writes each RESULT.json where it ran; this process writes the
    summary (its rows in the photos' name order) after each photo. After an
    interrupt the summary lists every result in RESULTS_DIR (``earlier``: the
    stamps of those there at the start, see :func:`_rows_left_in_folder`).
    Results in ``stale`` (of another model, :func:`_stale_results`) are
    registered again, never kept, and until then named in the summary's
    ``stale_results``, not listed as rows.
    """
    from ..registration import batch as backend

    n = len(files.photos)
    width = len(str(n))
    order = {p.name: k for k, p in enumerate(files.photos)}
    done = 0
    # Each result row names the version of its photo (a photo replaced under its
    # name, re-exported or cropped, makes its result another photo's).
    prints_now = {p.name: file_fingerprint(p) for p in files.photos}
    prints_before = _earlier_photo_prints(out)

    def with_print(row: dict[str, Any]) -> dict[str, Any]:
        if row.get("result"):
            row["photo_fingerprint"] = (prints_before.get(row["photo"]) if row.get("skipped")
                                        else prints_now[row["photo"]])
        return row

    summary_held: list[str] = []  # the refusal last said, while summary.csv is held open

    def record(row: dict[str, Any]) -> None:
        nonlocal done
        done += 1
        rows.append(with_print(row))
        rows.sort(key=lambda r: order[r["photo"]])
        try:
            _write_summary(out, header, rows, stale)
        except OutputError as exc:
            # On Windows a summary open in Excel (to watch the progress) cannot
            # be replaced: the photos go on, the summary follows once it is closed.
            if not _platform.held_open(exc):
                raise
            if not summary_held:
                say(f"  {exc}; the photos go on and the summary is updated once it is closed",
                    flush=True)
            summary_held[:] = [str(exc)]
        else:
            summary_held.clear()

    try:
        todo = []
        for photo_path in files.photos:
            result_path = out / names[photo_path]
            replaced = fingerprint_difference(prints_before.get(photo_path.name),
                                              prints_now[photo_path.name])
            if args.skip_existing and result_path.name in stale:
                say(f"{photo_path.name}: existing result registered on another model: redoing it")
            elif args.skip_existing and replaced and result_path.is_file():
                say(f"{photo_path.name}: the photo has changed since its existing result "
                    f"({replaced}): redoing it")
            elif args.skip_existing and result_path.is_file():
                try:
                    row = _existing_row(photo_path.name, result_path)
                except InputError as exc:
                    say(f"{photo_path.name}: existing result unreadable ({one_line(exc)}): "
                        "redoing it")
                else:
                    row.update(skipped=True, result=result_path.name)
                    record(row)
                    say(f"[{done:>{width}}/{n}] {photo_path.name}: skipped, result exists "
                        f"({row['status']}, {outcome_words(row['status'], row['grade'])})",
                        flush=True)
                    continue
            todo.append(photo_path)

        show = progress_printer(args.verbose, "      ") if cluster.in_process else None
        if args.verbose and not cluster.in_process:
            say("  -v: progress within a photo is shown with --workers 0 only (the photos run "
                "in other processes here)")
        if scene is not None:
            backend.cached_scene(spec, scene)  # in this process: the scene loaded above
        tasks = [(p.name, backend.register_photo_file,
                  (spec, str(p), str(out / names[p]), params, show)) for p in todo]
        with backend.PhotoRunner(cluster, len(todo)) as runner:
            if todo:
                runner.wait_for_workers(lambda message: say(message, flush=True))
                header["cluster"] = runner.description
                where = "in this process" if cluster.in_process else f"on the {runner.description}"
                say(f"registering {len(todo)} photo(s) {where}", flush=True)
            for name, outcome in runner.run(tasks, lambda message: say(message, flush=True)):
                _record_outcome(name, outcome, out, names[files.photos[order[name]]], record,
                                f"[{done + 1:>{width}}/{n}] {name}")
    except (KeyboardInterrupt, backend.SchedulerLost) as exc:  # Ctrl-C, SIGTERM, no scheduler
        header["interrupted"] = True
        if isinstance(exc, backend.SchedulerLost):
            header["error"] = str(exc)
        else:
            header["signal"] = "SIGTERM" if isinstance(exc, Terminated) else "SIGINT"
        left = _rows_left_in_folder(files.photos, out, names, rows, earlier)
        left = [r for r in left if not (r["skipped"] and r["result"] in stale)]
        rows.extend(with_print(r) for r in left)
        rows.sort(key=lambda r: order[r["photo"]])
        _write_summary(out, header, rows, stale)
        n_earlier = sum(1 for r in left if r["skipped"])
        say(f"{'stopped' if 'error' in header else 'interrupted'} after {len(rows)} of {n} photos"
            + (f" ({n_earlier} of them an earlier run's result, not replaced)" if n_earlier
               else "")
            + f"; finished results and the summary are in {out}/ (run again with "
            "--skip-existing to carry on)", flush=True)
        raise

    header["complete"] = True
    _write_summary(out, header, rows, stale)
    counts = {k: sum(1 for r in rows if r["status"] == k)
              for k in ("registered", "failed", "bad_input", "error")}
    skipped = sum(1 for r in rows if r.get("skipped"))
    parts = [f"{counts['registered']} registered", f"{counts['failed']} failed"]
    if counts["bad_input"]:
        parts.append(f"{counts['bad_input']} bad input")
    if counts["error"]:
        parts.append(f"{counts['error']} crashed")
    say(
        f"batch: {n} photo{'s' if n != 1 else ''} — {', '.join(parts)}"
        + (f" ({skipped} kept from earlier runs)" if skipped else "")
        + f" in {time.perf_counter() - t_start:.1f} s -> {out / 'summary.csv'}"
    )
    return exit_code_of(rows)


def _result_stamps(out: Path, names: dict[Path, str]) -> dict[str, tuple[int, int, int]]:
    """Result file name -> (inode, size, mtime) of the photos' results already in ``out``."""
    return _result_stamps_of(out, names.values())


def _earlier_photo_prints(out: Path) -> dict[str, dict]:
    """Photo name -> ``photo_fingerprint`` of the rows of the summary already in
    ``out`` (none for a summary written before rows recorded it)."""
    try:
        earlier = read_json(out / "summary.json")
        return {row["photo"]: row["photo_fingerprint"] for row in earlier["photos"]
                if isinstance(row.get("photo_fingerprint"), dict)}
    except (InputError, OSError, KeyError, TypeError, AttributeError):
        return {}


def _other_model(out: Path, mesh_fingerprint: dict | None) -> str:
    """How the model of the summary already in ``out`` differs from this
    run's (``mesh_fingerprint``), in words; "" when it does not, or when that
    cannot be told (no summary, an unreadable one, or one written before
    summaries recorded ``mesh_fingerprint``)."""
    try:
        earlier = read_json(out / "summary.json")
    except (InputError, OSError):
        return ""
    if not isinstance(earlier, dict):
        return ""
    difference = fingerprint_difference(earlier.get("mesh_fingerprint"), mesh_fingerprint)
    return f"{Path(str(earlier.get('mesh'))).name}: {difference}" if difference else ""


def _stale_results(out: Path, earlier: dict[str, tuple[int, int, int]], other_model: str
                   ) -> dict[str, tuple[int, int, int]]:
    """The results in ``out`` registered on another model than this run's:
    every one when the summary there is of another model (``other_model``),
    else those the summary still names in ``stale_results`` (an interrupted
    run on this model had not replaced them yet). Name -> stamp, as ``earlier``."""
    if other_model:
        return dict(earlier)
    try:
        named = read_json(out / "summary.json").get("stale_results") or []
    except (InputError, OSError, AttributeError):
        return {}
    return {name: earlier[name] for name in named if isinstance(name, str) and name in earlier}


def _result_stamps_of(out: Path, names) -> dict[str, tuple[int, int, int]]:
    """File name -> (inode, size, mtime) of the files ``names`` in ``out`` that exist."""
    stamps = {}
    for name in names:
        try:
            st = (out / name).stat()
        except OSError:  # none yet (or unreadable: registered again, as if none)
            continue
        stamps[name] = (st.st_ino, st.st_size, st.st_mtime_ns)
    return stamps


def _rows_left_in_folder(photos: list[Path], out: Path, names: dict[Path, str],
                         rows: list[dict[str, Any]], earlier: dict[str, tuple[int, int, int]]
                         ) -> list[dict[str, Any]]:
    """Summary rows of the results in ``out`` that no row of this run lists.

    At an interrupt a worker may have written a photo's result before this
    process heard of it, and an earlier run's results not yet replaced are
    still there: the summary is to describe the folder as it is. A result
    whose file is the one found at the start (same inode, size and
    modification time) is the earlier run's (``skipped``); another was
    written by this run.
    """
    listed = {r["photo"] for r in rows}
    left = []
    for photo in photos:
        name = names[photo]
        path = out / name
        if photo.name in listed or not path.is_file():
            continue
        try:
            row = _existing_row(photo.name, path)
            st = path.stat()
        except (InputError, OSError):  # not a whole result of ours: not listed
            continue
        row.update(skipped=earlier.get(name) == (st.st_ino, st.st_size, st.st_mtime_ns),
                   result=name)
        left.append(row)
    return left


def _record_outcome(name: str, outcome: Any, out: Path, result_name: str, record,
                    tag: str) -> None:
    """One finished task: its summary row, its stderr line when it did not run."""
    from ..registration.batch import TaskLost

    if isinstance(outcome, TaskLost):
        outcome = {"photo": name, "status": "error", "error": f"{name}: {outcome}",
                   "seconds": None}
    elif isinstance(outcome, BaseException):  # raised around the task (e.g. by Dask itself)
        outcome = {"photo": name, "status": "error",
                   "error": f"{name}: {type(outcome).__name__}: {one_line(outcome)}",
                   "seconds": None}
    status = outcome["status"]
    if status in ("bad_input", "error"):
        message = outcome["error"]
        print_error("batch", message)
        record(_error_row(name, status, message, outcome["seconds"]))
        say(f"{tag}: {'BAD INPUT' if status == 'bad_input' else 'ERROR'} — {message}", flush=True)
        return
    result = outcome["result"]
    row = _row_of_result(name, result, outcome["seconds"])
    row.update(skipped=False, result=result_name, hints=outcome["hints"],
               assumptions=outcome["assumptions"])
    record(row)
    def f1(key: str) -> str:
        return "?" if row[key] is None else f"{row[key]:.1f}"

    err = row["reprojection_error_px"]
    say(
        f"{tag}: {status.upper()} — {outcome_words(status, row['grade'])} "
        f"(Q = {row['Q'] or 0:+.2f}), "
        f"{row['n_trials']} trial(s), {row['seconds'] or 0:.1f} s; "
        f"({f1('x')}, {f1('y')}, {f1('z')}) m, trend {f1('trend_deg')}° "
        f"plunge {f1('plunge_deg')}° roll {f1('roll_deg')}°"
        + (f", reprojection {err:.2f} px" if err is not None else ""),
        flush=True,
    )
    if status != "registered":
        for hint in outcome["hints"][:2]:
            say(f"      hint: {hint}")


#: 0.1 names of this module -> their new names here.
_MOVED = {"cmd_batch": "napari_imgreg.cli.batch:run"}
__getattr__ = forward_moved_names(__name__, _MOVED)


