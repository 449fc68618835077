"""``napari-imgreg workspace``: a campaign's workspace folder from the command line.

The same workspace folder the workbench opens (docs/formats.md, "Workspace
folder"): every step saves into it as it goes, so each is resumable — a
``register`` interrupted after 40 of 300 photos keeps the 40 and, run again,
starts at the 41st.

::

    napari-imgreg workspace create campaign.imgreg SCENE_DIR   # the scene and its photos
    napari-imgreg workspace add campaign.imgreg IMG_0301.jpg ...
    napari-imgreg workspace register campaign.imgreg [--photo NAME]... [--retry-failed] [--redo]
    napari-imgreg workspace lines campaign.imgreg IMG_0001.jpg LINES.geojson
    napari-imgreg workspace project campaign.imgreg          # project and measure
    napari-imgreg workspace export campaign.imgreg --out LINES3D.geojson [--measurements M.csv]
    napari-imgreg workspace info campaign.imgreg

Exit codes as for every command: 0 done (``register``: every photo asked for
is registered), 1 some photo did not register, 2 bad input (one line). What a
sub-command writes (the workspace folder, ``export``'s files) is checked for
writability first, before the scene or the workspace is read.
"""

from __future__ import annotations

import argparse
import os
import time
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING

from ._common import (
    EXIT_BAD_INPUT,
    EXIT_FAILED,
    EXIT_OK,
    one_line,
    print_error,
    progress_printer,
    read_params,
    same_file,
    say,
)
from .batch import SceneFiles, add_cluster_arguments, cluster_params, find_scene_files
from ..errors import InputError, input_error
from ..io import workspace_files as wsfiles
from ..validate import check_writable
from ..registration.quality import outcome_words

if TYPE_CHECKING:  # the commands import their backend when run: a fast --help
    from ..workspace import Workspace

__all__ = ["add_parser", "run"]


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``workspace`` command and its sub-commands; the handler is :func:`run`."""
    p = subparsers.add_parser(
        "workspace",
        help="a campaign's workspace folder: create, add photos, register, project, export",
        description="Work on a workspace folder (campaign.imgreg) as the workbench does: every "
        "step is saved as it goes and can be resumed.",
    )
    sub = p.add_subparsers(dest="action", required=True, metavar="ACTION")

    c = sub.add_parser("create", help="a new workspace from a scene folder (mesh, DEM, photos)")
    c.add_argument("folder", metavar="WORKSPACE",
                   help="the new folder, e.g. campaign.imgreg (.imgreg is added to a name "
                   "without it, as the workbench does)")
    c.add_argument("scene", metavar="SCENE_DIR",
                   help="a folder with one mesh, optionally georef.json and a DEM, and the photos")
    c.add_argument("--mesh", help="the mesh, when the folder has several")
    c.add_argument("--dem", help="the DEM, when the folder has several")
    c.add_argument("--georef", help="georef.json (default: the one in SCENE_DIR)")
    c.add_argument("--params", metavar="PARAMS.json", help="registration parameters (any subset)")
    c.add_argument("--no-photos", action="store_true", help="the scene only; add photos later")

    a = sub.add_parser("add", help="add photos (each with its sensor record beside it)")
    a.add_argument("folder", metavar="WORKSPACE")
    a.add_argument("photos", metavar="PHOTO", nargs="+")

    r = sub.add_parser("register", help="register the photos not registered yet (resumable)")
    r.add_argument("folder", metavar="WORKSPACE")
    r.add_argument("--photo", action="append", metavar="NAME",
                   help="only this photo (its file name; where two photos share one, its "
                   "folder name under photos/ or its path); repeat for several")
    r.add_argument("--retry-failed", action="store_true",
                   help="register again the photos whose last registration failed")
    r.add_argument("--redo", action="store_true", help="register every photo again")
    r.add_argument("--once", action="store_true",
                   help="one trial from the current pose (the workbench's Run) instead of Auto")
    r.add_argument("-v", "--verbose", action="store_true",
                   help="print progress within each photo (with --workers 0 only)")
    add_cluster_arguments(r)

    li = sub.add_parser("lines", help="set what is drawn on a photo from a pixel GeoJSON")
    li.add_argument("folder", metavar="WORKSPACE")
    li.add_argument("photo", metavar="PHOTO_NAME",
                    help="the photo's file name in the workspace (where two photos share one, "
                    "its folder name under photos/ or its path)")
    li.add_argument("lines", metavar="LINES.geojson", help="pixel GeoJSON (docs/formats.md §7)")

    pa = sub.add_parser("pairs", help="register a photo from control points (a PAIRS.csv), as "
                        "the workbench's Manual tab does")
    pa.add_argument("folder", metavar="WORKSPACE")
    pa.add_argument("photo", metavar="PHOTO_NAME",
                    help="the photo's file name in the workspace (where two photos share one, "
                    "its folder name under photos/)")
    pa.add_argument("pairs", metavar="PAIRS.csv",
                    help="control points: photo_x,photo_y and x,y,z, easting,northing,elevation "
                    "or latitude,longitude,elevation (docs/formats.md, Control points)")
    pa.add_argument("--solve-focal", action="store_true",
                    help="also solve the focal length (6 or more pairs)")

    sub.add_parser("project", help="project every photo's drawings onto the model and measure "
                   "them").add_argument("folder", metavar="WORKSPACE")

    e = sub.add_parser("export", help="write the projected interpretations and measurements")
    e.add_argument("folder", metavar="WORKSPACE")
    e.add_argument("--out", required=True, metavar="LINES3D",
                   help="the features; the format by its suffix, as for `napari-imgreg project`")
    e.add_argument("--measurements", metavar="MEASUREMENTS.csv", help="also the measurements")
    e.add_argument("--georeferenced", action="store_true",
                   help="coordinates in the georeference's CRS (model + origin)")

    sub.add_parser("info", help="the photos and how far each has come").add_argument(
        "folder", metavar="WORKSPACE")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``workspace ACTION``."""
    if args.action == "create":
        args.folder = str(workspace_folder_name(args.folder))
    elif Path(args.folder).is_file():  # before "cannot write here" or "no such workspace"
        raise input_error(args.folder, "is a file, not a workspace folder")
    _check_outputs(args)
    try:
        return _ACTIONS[args.action](args)
    finally:
        # Released at once, not when collected: a Python caller of main()
        # (a script, the tests) may open the same folder again right away.
        while _OPENED:
            _OPENED.pop().detach()


def workspace_folder_name(folder: str | Path) -> Path:
    """The folder a new workspace is saved as: ``.imgreg`` added to a name
    without it, as the workbench's "Save workspace as" does (napari opens
    only ``*.imgreg`` folders as workspaces); an existing workspace keeps its name."""
    folder = Path(folder)
    if folder.name in ("", ".", "..") or folder.suffix == ".imgreg" \
            or (folder / "workspace.json").exists():
        return folder  # "." or "..": not a name to extend (refused as not empty)
    return folder.with_name(folder.name + ".imgreg")


#: The workspaces the running sub-command saves into.
_OPENED: list[Workspace] = []


#: The sub-commands that save into the workspace folder as they go.
_WRITE_INTO_FOLDER = ("create", "add", "register", "lines", "pairs", "project")


def _check_outputs(args: argparse.Namespace) -> None:
    """Refuse, before any work, an output that cannot be written: the
    workspace folder of a sub-command that saves into it (read-only, under
    /proc, inside a file), ``export``'s ``--out`` and ``--measurements`` (which
    must be a .csv file, and not the ``--out`` file, and neither may be in the
    workspace folder)."""
    if args.action in _WRITE_INTO_FOLDER:
        check_writable(args.folder, folder=True)
    elif args.action == "export":
        for output in (args.out, args.measurements):
            # Its own LINES3D.geojson or MEASUREMENTS.csv overwritten by an
            # export (georeferenced, say) would corrupt every later export.
            if output and _inside(output, args.folder):
                raise input_error(output, f"is inside the workspace folder {args.folder}: "
                                          "write exports outside it")
        if args.measurements:
            if Path(args.measurements).suffix.lower() != ".csv":
                raise input_error(args.measurements, "output must be a .csv file")  # as `measure`
            if same_file(args.out, args.measurements):
                raise input_error(args.measurements, "refusing to write --out and "
                                                      "--measurements to one file; choose "
                                                      "another name")
        check_writable(args.out)
        if args.measurements:
            check_writable(args.measurements)


def _inside(path: str | Path, folder: str | Path) -> bool:
    """``path`` is ``folder`` or lies in it (links and ``..`` resolved)."""
    return Path(os.path.realpath(path)).is_relative_to(os.path.realpath(folder))


def _open(folder: str) -> Workspace:
    from ..workspace import Workspace
    ws = Workspace.open(folder)
    _OPENED.append(ws)
    _say_open_problems(ws)
    ws.autosave_failed.connect(lambda message: say(f"  not saved: {message}"))
    return ws


def _say_open_problems(ws: Workspace) -> None:
    """What opening the workspace could not restore, and the files changed since
    the photos were registered on them (opened, but to check)."""
    for line in ws.open_problems:
        say(f"  warning: {line}" if line in ws.open_warnings else f"  not opened: {line}")


def _photo_named(ws: Workspace, folder: str, name: str):
    """The photo ``name`` names: its file name, its folder name in the
    workspace (``photos/<key>``) or its path.

    Raises
    ------
    InputError
        No such photo, or a file name that several photos have (two cameras'
        ``IMG_0001.jpg``): picking one of them would put drawings or a
        registration on the wrong photo without a word.
    """
    def same_path(ps) -> bool:
        return ps.photo.path is not None and same_file(ps.photo.path, name)

    for matches in ([ps for ps in ws.photos if ws.photo_key(ps) == name],
                    [ps for ps in ws.photos if ps.name == name],
                    [ps for ps in ws.photos if same_path(ps)]):
        if len(matches) == 1:
            return matches[0]
        if matches:
            which = ", ".join(f"{ws.photo_key(ps)} ({ps.photo.path})" for ps in matches)
            raise input_error(folder, f"{len(matches)} photos are named {name!r}: {which}; "
                                      "name one by its folder name in the workspace or its path")
    raise input_error(folder, f"no photo named {name!r} in the workspace")


def _label(ws: Workspace, ps, names: Counter | None = None) -> str:
    """The photo's file name, with its folder name in the workspace when
    another photo has the same file name (two cameras' ``IMG_0001.jpg``).

    ``names``: how many photos have each file name (counted once by a caller
    labelling every photo: counting for each grew with the square of the photos).
    """
    names = names if names is not None else Counter(other.name for other in ws.photos)
    return f"{ps.name} ({ws.photo_key(ps)})" if names[ps.name] > 1 else ps.name


def _create(args: argparse.Namespace) -> int:
    from ..workspace import Workspace
    folder = Path(args.folder)
    if wsfiles.is_workspace(folder):
        raise input_error(folder, "already holds a workspace (add photos with 'workspace add')")
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        raise input_error(folder, "exists and is not an empty folder: choose a new one")
    files = _scene_files(args)
    ws = Workspace(read_params(args.params))  # a bad file is refused before the scene loads
    ws.open_scene(files.mesh, files.dem, files.georef)
    if args.params:  # the file's fields over the scene's defaults (a point cloud's)
        ws.set_params(read_params(args.params, ws.scene))
    _OPENED.append(ws)
    for note in ws.scene.warnings:  # e.g. a cloud's CRS rule, as batch says it
        say(f"  assumed: {note}")
    try:
        ws.save(folder)
    except OSError as exc:  # checked writable above; the disk can still fill up
        raise input_error(folder, f"cannot write here: {exc.strerror or one_line(exc)}") from None
    # Added after saving: each photo is in the workspace as soon as it is read.
    errors = [] if args.no_photos else ws.add_photos(files.photos)
    for line in errors:
        say(f"  not added: {line}")
    for sub, why in files.ignored.items():
        if sub.endswith("/"):  # photos kept by day or camera: 'workspace add' takes them
            say(f"  not added: {sub} ({why}; 'workspace add' adds them)")
    say(f"{folder}: workspace with {files.mesh.name} and {len(ws.photos)} photo(s)"
        + (f"; {len(errors)} could not be read" if errors else ""))
    return _not_added(errors, "create") if errors else EXIT_OK


def _scene_files(args: argparse.Namespace) -> SceneFiles:
    """The model, DEM, georeference and photos of ``create``'s scene folder.

    Raises
    ------
    InputError
        As :func:`~napari_imgreg.cli.batch.find_scene_files` (with
        ``--no-photos`` a folder without photos is a scene too), a file given
        for the folder said in ``create``'s words.
    """
    scene = Path(args.scene)
    if scene.is_file():
        raise input_error(scene, "is a file, not a scene folder: give the folder that holds "
                                 f"the model and the photos ({scene.absolute().parent})")
    try:
        return find_scene_files(scene, args.mesh, args.dem, args.georef,
                                photos_required=not args.no_photos)
    except InputError as exc:
        if "no photos in the folder" in str(exc):
            raise InputError(f"{exc}; --no-photos makes a workspace of the scene only") from None
        raise


def _add(args: argparse.Namespace) -> int:
    ws = _open(args.folder)
    before = len(ws.photos)
    for path in args.photos:  # skipped by add_photos: said, so that "0 added" is not a puzzle
        there = ws.photo_at_path(path) if Path(path).exists() else None
        if there is not None:
            say(f"  already in the workspace: {path}")
    errors = ws.add_photos([Path(p) for p in args.photos])
    for line in errors:
        say(f"  not added: {line}")
    say(f"{args.folder}: {len(ws.photos) - before} photo(s) added, {len(ws.photos)} in all")
    return _not_added(errors, "add") if errors else EXIT_OK


def _not_added(errors: list[str], action: str) -> int:
    """Exit code 2 with one error line on stderr for the photos that could
    not be read (each is listed on stdout): the first, and how many more;
    ``action`` (``create``, ``add``) names the sub-command in it."""
    more = f" (and {len(errors) - 1} more photo(s), listed above)" if len(errors) > 1 else ""
    print_error(f"workspace {action}", " ".join(f"not added: {errors[0]}{more}".split()))
    return EXIT_BAD_INPUT


def _register(args: argparse.Namespace) -> int:
    ws = _open(args.folder)
    chosen = {id(_photo_named(ws, args.folder, name)) for name in args.photo or []}
    asked = [k for k, ps in enumerate(ws.photos) if not args.photo or id(ps) in chosen]
    todo = []
    for k in asked:
        reg = ws.photos[k].registration
        if args.redo or reg is None or (args.retry_failed and not reg.registered):
            todo.append(k)
    done = len(asked) - len(todo)
    say(f"{args.folder}: {len(todo)} photo(s) to register"
        + (f" ({done} already done)" if done else ""))
    cluster = cluster_params(args)
    try:
        code = _register_photos(args, ws, asked, todo, cluster)
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: each photo was saved as it came back
        say(f"{args.folder}: interrupted; every photo registered so far is saved there "
            "(run 'workspace register' again to carry on)", flush=True)
        raise
    unopened = [line for line in ws.open_problems if line not in ws.open_warnings]
    if unopened and not args.photo:
        # Every photo was asked for: one that could not be read is not registered
        # (as a bad photo of 'batch', exit code 2, not 0).
        more = f" (and {len(unopened) - 1} more, listed above)" if len(unopened) > 1 else ""
        print_error("workspace register", " ".join(
            f"not registered, could not be opened: {unopened[0]}{more}".split()))
        return EXIT_BAD_INPUT
    return code


def _register_photos(args: argparse.Namespace, ws: Workspace, asked: list[int],
                     todo: list[int], cluster) -> int:
    """Register the photos ``todo`` (indices into ``ws.photos``) on the cluster,
    or one after another here; the exit code covers the photos ``asked``."""
    from ..workspace import one_line
    if not cluster.in_process and len(todo) > 1:
        failed = _register_on_cluster(ws, todo, auto=not args.once, cluster=cluster)
        missing = sum(ws.photos[k].registration is None or not ws.photos[k].registration.registered
                      for k in asked)
        return EXIT_FAILED if (failed or missing) else EXIT_OK
    failed = 0
    names = Counter(ps.name for ps in ws.photos)
    for n, k in enumerate(todo, 1):
        ws.select_photo(k)
        ps = ws.current
        start = time.perf_counter()
        try:
            reg = ws.register(auto=not args.once,
                              on_progress=progress_printer(args.verbose, "    "))
        except KeyboardInterrupt:
            raise  # the photos done are saved; a rerun goes on from this one
        except Exception as exc:  # noqa: BLE001 - one photo's crash does not stop the campaign
            say(f"  [{n}/{len(todo)}] {_label(ws, ps, names)}: not registered: {one_line(exc)}")
            failed += 1
            continue
        failed += not reg.registered
        say(f"  [{n}/{len(todo)}] {_label(ws, ps, names)}: {reg.status} — "
            f"{outcome_words(reg.status, reg.grade)} (Q = {reg.q:+.2f}), {len(reg.trials)} "
            f"trial(s), {time.perf_counter() - start:.1f} s")
    missing = sum(ws.photos[k].registration is None or not ws.photos[k].registration.registered
                  for k in asked)
    return EXIT_FAILED if (failed or missing) else EXIT_OK


def _register_on_cluster(ws: Workspace, todo: list[int], auto: bool, cluster) -> int:
    """Register the photos ``todo`` on Dask workers; each is recorded (and
    autosaved) here as it comes back, so an interrupt keeps every finished
    one. Returns how many did not register."""
    from ..registration import batch as backend
    from ..workspace import one_line

    spec = backend.SceneSpec(*(str(Path(ws.scene_files[k]).resolve())
                               if ws.scene_files.get(k) else None
                               for k in ("mesh", "dem", "georef")))
    kind = "Auto" if auto else "Run"
    tasks = []
    for k in todo:
        ps = ws.photos[k]
        # As Workspace.registration_job sets them up for one photo.
        params = ws.params.copy()
        params.auto_adapt = auto
        if not auto:
            params.search_prior = False
            params.max_trials = 1
        tasks.append((str(k), backend.register_prior,
                      (spec, ps.photo, ws.registration_prior(ps), params, ps.name)))
    failed = 0
    names = Counter(ps.name for ps in ws.photos)
    with backend.PhotoRunner(cluster, len(todo)) as runner:
        say(f"  on the {runner.description}", flush=True)
        for n, (tag, reg) in enumerate(runner.run(tasks, lambda message: say(f"  {message}")),
                                       1):
            ps = ws.photos[int(tag)]
            if isinstance(reg, BaseException):
                say(f"  [{n}/{len(todo)}] {_label(ws, ps, names)}: not registered: {one_line(reg)}")
                failed += 1
                continue
            # Its pose becomes the photo's pose though another photo is current.
            ws.record_registration(reg, kind, ps, pose_if_not_current=True)
            failed += not reg.registered
            say(f"  [{n}/{len(todo)}] {_label(ws, ps, names)}: {reg.status} — "
                f"{outcome_words(reg.status, reg.grade)} (Q = {reg.q:+.2f}), "
                f"{len(reg.trials)} trial(s), "
                f"{reg.timings_s.get('total', 0.0):.1f} s")
    return failed


def _lines(args: argparse.Namespace) -> int:
    from ..interpret import files as interpret_files
    from ..workspace import check_drawings
    items = interpret_files.read_interpretations(args.lines)  # a bad file before the scene loads
    ws = _open(args.folder)
    ps = _photo_named(ws, args.folder, args.photo)
    try:
        # As projecting them would: refused now, nothing is saved that
        # would block every later 'workspace project'.
        check_drawings(items, ps.intrinsics, ps.name)
    except InputError as exc:
        raise input_error(args.lines, str(exc)) from None
    ws.set_interpretations(items, ps=ps)
    say(f"{_label(ws, ps)}: {len(items)} feature(s) drawn (from {args.lines})")
    return EXIT_OK


def _pairs(args: argparse.Namespace) -> int:
    from ..io.control_points import read_control_points
    from ..registration import manual
    from ..workspace import WorkbenchError

    # A bad file is refused before anything is rendered or saved.
    points = read_control_points(args.pairs, min_pairs=manual.MIN_PAIRS)
    if args.solve_focal and len(points) < manual.MIN_PAIRS_FOCAL:
        raise input_error(args.pairs, f"{len(points)} pairs: --solve-focal needs at least "
                                      f"{manual.MIN_PAIRS_FOCAL}")
    ws = _open(args.folder)
    ps = _photo_named(ws, args.folder, args.photo)
    ws.select_photo(ws.photos.index(ps))
    try:
        if ps.reference is None:  # the pairs are shown on one in the workbench
            ws.make_reference()
        ws.load_pairs(args.pairs)
        sol = ws.solve_manual(solve_focal=args.solve_focal)
    except WorkbenchError as exc:
        raise input_error(args.pairs, str(exc)) from None
    status = ws.photo_status(ps)
    if not sol.ok:
        say(f"{_label(ws, ps)}: not registered: no pose from the control points: {sol.reason}")
        return EXIT_FAILED
    unc = sol.uncertainty
    expected = ("" if unc is None else f"; expected error {unc.reprojection_px:.1f} px, "
                f"{unc.position_m:.2f} m, {unc.rotation_deg:.2f}°")
    focal = f", focal length {sol.intrinsics.fx:.1f} px" if sol.focal_solved else ""
    say(f"{_label(ws, ps)}: {status} from {sol.n_inliers} of {len(sol.inliers)} control "
        f"points (RMS {sol.rms_px:.2f} px{focal}){expected}")
    return EXIT_OK if status in ("registered", "accepted") else EXIT_FAILED


def _project(args: argparse.Namespace) -> int:
    from ..workspace import WorkbenchError, check_drawings
    ws = _open(args.folder)
    for ps in ws.photos:  # saved before 'lines' checked drawings: say which file to redo
        try:
            check_drawings(ps.interpretations, ps.intrinsics, ps.name)
        except InputError as exc:
            lines = Path(args.folder) / wsfiles.PHOTOS_DIR / ws.photo_key(ps) / wsfiles.PHOTO_LINES
            raise input_error(lines, f"{exc}; set its drawings again with 'workspace lines'") \
                from None
    try:
        features = ws.project_interpretations()
    except WorkbenchError as exc:
        raise input_error(args.folder, str(exc)) from None
    on_surface = sum(1 for f in features if f.parts)
    planes = sum(1 for m in ws.measurements if m.dip_deg is not None)
    say(f"{args.folder}: {len(features)} feature(s) projected ({on_surface} on the surface), "
        f"{len(ws.measurements)} measured, {planes} with a plane")
    return EXIT_OK


def _export(args: argparse.Namespace) -> int:
    from ..interpret import files as interpret_files
    from ..workspace import Workspace
    ws = Workspace.open(args.folder, autosave=False)
    if not ws.features_3d:
        raise input_error(args.folder, "nothing projected yet: run 'workspace project' first")
    georef = ws.scene.georef if ws.scene is not None else None
    # The campaign's own measurements (contacts combined across photos) fill
    # a GeoPackage's measurements layer.
    notes = interpret_files.export_features(args.out, ws.features_3d, georef,
                                            args.georeferenced,
                                            measurements=ws.measurements or None)
    in_crs = interpret_files.export_in_crs(args.out, georef, args.georeferenced)
    if args.measurements:
        # In the frame of the exported features (centroids; angles are the same).
        interpret_files.write_measurements_csv(
            args.measurements,
            interpret_files.measurements_in_frame(ws.measurements, georef.origin)
            if in_crs else ws.measurements)
    frame = f"{georef.crs} (local + origin)" if in_crs else "local frame"
    say(f"{args.out}: {len(ws.features_3d)} feature(s), {frame}"
        + (f"; {args.measurements}: {len(ws.measurements)} measurement(s)"
           if args.measurements else ""))
    for note in notes:
        say(f"  note: {note}")
    if ws.projection_out_of_date():
        say(f"  note: {_out_of_date(ws)}")
    return EXIT_OK


def _out_of_date(ws: Workspace) -> str:
    """The projection is older than what some photos hold now, in words."""
    names = Counter(ps.name for ps in ws.photos)
    stale = [_label(ws, ps, names) for ps in ws.projection_out_of_date()]
    listed = ", ".join(stale[:5]) + (", ..." if len(stale) > 5 else "")
    return (f"the projection is older than the drawings or poses of {len(stale)} photo(s) "
            f"({listed}): run 'workspace project' to bring it up to date")


def _info(args: argparse.Namespace) -> int:
    from ..workspace import Workspace
    manifest, _ = wsfiles.read_manifest(args.folder)
    ws = Workspace.open(args.folder, autosave=False)  # a version 0 is not migrated by a look
    mesh = ws.scene_files.get("mesh") or "(none)"
    say(f"{args.folder}: version {manifest.get('version', 0)}, model {mesh}, "
        f"{len(ws.photos)} photo(s)")
    names = Counter(ps.name for ps in ws.photos)
    for ps in ws.photos:
        reg = ps.registration
        state = "not registered" if reg is None else (
            f"{reg.status}, {outcome_words(reg.status, reg.grade)}, Q = {reg.q:+.2f}")
        say(f"  {_label(ws, ps, names)}: {state}; {len(ps.trials)} trial(s), "
            f"{len(ps.interpretations)} drawn")
    _say_open_problems(ws)
    if ws.features_3d:
        say(f"  projected: {len(ws.features_3d)} feature(s), {len(ws.measurements)} measured"
            + (f"; {_out_of_date(ws)}" if ws.projection_out_of_date() else ""))
    return EXIT_OK


_ACTIONS = {"create": _create, "add": _add, "register": _register, "lines": _lines,
            "pairs": _pairs,
            "project": _project, "export": _export, "info": _info}
