"""``napari-imgreg project`` and ``napari-imgreg measure`` (contract §5, §6, §8).

Wired into the main command line by :func:`add_parsers`; the handlers return
exit codes. Bad input raises :class:`~napari_imgreg.errors.InputError`, which
the main command turns into one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

from napari_imgreg.errors import input_error

__all__ = ["add_parsers", "cmd_project", "cmd_measure"]

EXIT_OK = 0
_DEM_SUFFIXES = (".tif", ".tiff", ".asc")
_REJECTIONS = (
    ("planarity", "planarity below the threshold (a line or a blob)"),
    ("relief", "trace nearly straight (too little relief)"),
    ("outcrop surface", "plane is the outcrop surface (surface effect)"),
    ("points", "too few points"),
)


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    """Register the ``project`` and ``measure`` sub-commands."""
    p = subparsers.add_parser(
        "project",
        help="project lines drawn on a registered photo onto the mesh (3D GeoJSON)",
        description="Cast the lines and polygons of LINES.geojson (pixel [col, row] "
        "coordinates, properties.label) through the registered camera of RESULT.json onto "
        "MESH. Lines follow the relief (about one ray per pixel) and are split where they "
        "leave the surface (sky, holes, occluding ridges), never bridged. Writes 3D "
        "GeoJSON (or .csv / .obj / .ply by the --out suffix) with properties.source naming "
        "the photo. Several RESULT.json/LINES.geojson pairs merge into one file.",
    )
    p.add_argument("result", metavar="RESULT.json",
                   help="registration result (a sensor record works too: its prior pose)")
    p.add_argument("mesh", metavar="MESH",
                   help="OBJ+MTL+image, PLY, GLB/GLTF, or a DEM (.tif/.asc) as the surface")
    p.add_argument("lines", metavar="LINES.geojson", help="interpretations drawn on the photo")
    p.add_argument("--also", nargs=2, action="append", default=[],
                   metavar=("RESULT.json", "LINES.geojson"),
                   help="another photo's result and lines, merged into the same output "
                   "(repeatable)")
    p.add_argument("--out", required=True, metavar="LINES3D.geojson",
                   help="3D output: .geojson, .csv (vertices), .obj or .ply (polylines)")
    p.add_argument("--georeferenced", action="store_true",
                   help="write CRS coordinates (local + georef origin) instead of local ones")
    p.add_argument("--georef", help="georef.json (default: the one beside MESH, if any)")
    p.add_argument("--dem", help="DEM GeoTIFF or .asc (altitude for a sensor-record pose)")
    p.add_argument("--step", type=float, default=1.0, metavar="PX",
                   help="sample spacing along the lines, pixels (default 1)")
    p.add_argument("--grazing", type=float, default=5.0, metavar="DEG",
                   help="split where the surface would be seen more obliquely than this "
                   "(default 5°)")
    p.set_defaults(func=cmd_project)

    p = subparsers.add_parser(
        "measure",
        help="plunge/trend and dip/dip direction of projected traces and facets (CSV)",
        description="Fit each trace's best 3D line (plunge/trend) and, where it crosses "
        "enough relief, its best plane (dip/dip direction); fit each facet's plane to the "
        "surface inside it. Planes are vetted as CloudCompare's Compass does (planarity, "
        "surface effect) plus a relief test; rejected ones leave the cells empty and say "
        "why in 'note'. Writes MEASUREMENTS.csv (contract §6) and optionally a stereonet.",
    )
    p.add_argument("lines3d", metavar="LINES3D.geojson", help="output of `project`")
    p.add_argument("--out", required=True, metavar="MEASUREMENTS.csv")
    p.add_argument("--stereonet", metavar="PNG",
                   help="also draw poles, great circles, Fisher means and α95 per label")
    p.add_argument("--min-planarity", type=float, default=0.75,
                   help="Compass planarity 1 - λ3/λ2 a plane needs (default 0.75)")
    p.add_argument("--surface-effect", type=float, default=10.0, metavar="DEG",
                   help="reject a trace's plane within this angle of the outcrop surface "
                   "(default 10°)")
    p.add_argument("--min-relief", type=float, default=0.05,
                   help="sqrt(λ2/λ1) a trace needs to define a plane (default 0.05)")
    p.set_defaults(func=cmd_measure)


def _load_scene(mesh: str, georef: str | None, dem: str | None):
    from napari_imgreg.scene import Scene

    path = Path(mesh)
    if not path.exists():
        raise input_error(path, "no such file")
    if path.suffix.lower() in _DEM_SUFFIXES:
        from napari_imgreg.geo import Georef

        g = Georef.load(georef) if georef else None
        if g is None and (path.parent / "georef.json").exists():
            g = Georef.load(path.parent / "georef.json")
        return Scene.from_dem(path, georef=g)
    return Scene.load(path, georef=georef, dem=dem)


def cmd_project(args: argparse.Namespace) -> int:
    """Run ``project``: cast the drawn lines onto the mesh, write LINES3D."""
    from napari_imgreg.interpret.project import ProjectionParams, merge_interpretations, project_interpretations
    from napari_imgreg.interpret.files import EXPORT_SUFFIXES, export_features, read_interpretations
    from napari_imgreg.io.records import load_camera_and_pose, read_json

    out = Path(args.out)
    if out.suffix.lower() not in EXPORT_SUFFIXES + (".gpkg",):
        raise input_error(out, f"output must be one of {', '.join(EXPORT_SUFFIXES)}")
    if args.step <= 0:
        raise input_error(None, "--step must be positive")
    pairs = [(args.result, args.lines)] + [tuple(p) for p in args.also]
    for result, lines in pairs:
        for f in (result, lines):
            if not Path(f).exists():
                raise input_error(f, "no such file")
    # Read every input before the (slower) mesh, so bad input fails fast.
    drawn = [read_interpretations(lines) for _, lines in pairs]
    scene = _load_scene(args.mesh, args.georef, args.dem)
    if args.georeferenced and scene.georef is None:
        raise input_error(
            args.mesh, "--georeferenced needs a georeference (georef.json beside the mesh "
            "or --georef)")
    params = ProjectionParams(step_px=args.step, grazing_deg=args.grazing)
    sets = []
    for (result, lines), items in zip(pairs, drawn):
        intr, pose, kind, notes = load_camera_and_pose(
            result, scene.georef, scene.dem, scene.terrain_height)
        data = read_json(result)
        photo = str(data.get("photo") or Path(result).stem) if isinstance(data, dict) else ""
        status = data.get("status") if isinstance(data, dict) else None
        if kind == "prior":
            print(f"  warning: {result} is a sensor record: projecting with the PRIOR pose")
        elif status and status != "registered":
            print(f"  warning: {result} status is {status!r}: lines may be misplaced")
        features = project_interpretations(scene, intr, pose, items, source=photo, params=params)
        sets.append(features)
        n_parts = sum(len(f.parts) for f in features)
        split = sum(1 for f in features if len(f.parts) > 1)
        off = sum(1 for f in features if not f.parts)
        print(
            f"{photo}: {len(features)} feature(s) from {lines} -> {n_parts} part(s) on "
            f"{scene.name}" + (f"; {split} split where they left the surface" if split else "")
            + (f"; {off} entirely off the surface" if off else "")
        )
        for note in notes:
            print(f"  assumed: {note}")
    merged = merge_interpretations(*sets)
    export_features(out, merged, scene.georef, args.georeferenced)
    labels = Counter(f.label for f in merged)
    frame = f"{scene.georef.crs} (local + origin)" if args.georeferenced else "local frame"
    print(
        f"  {len(merged)} feature(s) ("
        + ", ".join(f"{n} {label}" for label, n in sorted(labels.items()))
        + f"), {frame} -> {out}"
    )
    return EXIT_OK


def cmd_measure(args: argparse.Namespace) -> int:
    """Run ``measure``: fit lines and planes, write MEASUREMENTS.csv (and a stereonet)."""
    from napari_imgreg.interpret.project import measure_features
    from napari_imgreg.interpret.files import read_features_geojson, write_measurements_csv
    from napari_imgreg.interpret.structural import FitThresholds, fisher_mean, save_stereonet, vector_from_plunge_trend
    from napari_imgreg.interpret.structural import dip_dip_direction, pole_of_plane

    out = Path(args.out)
    if out.suffix.lower() != ".csv":
        raise input_error(out, "output must be a .csv file")
    if args.stereonet and Path(args.stereonet).suffix.lower() not in (".png", ".svg", ".pdf"):
        raise input_error(args.stereonet, "stereonet must be .png, .svg or .pdf")
    if not 0.0 <= args.min_planarity <= 1.0:
        raise input_error(None, "--min-planarity must be in [0, 1]")
    features, frame = read_features_geojson(args.lines3d)
    thresholds = FitThresholds(
        min_planarity=args.min_planarity, surface_effect_deg=args.surface_effect,
        min_relief=args.min_relief,
    )
    measurements = measure_features(features, thresholds)
    write_measurements_csv(out, measurements)
    n_planes = sum(m.has_plane for m in measurements)
    n_traces = sum(m.kind == "trace" for m in measurements)
    n_facets = sum(m.kind == "facet" for m in measurements)
    print(
        f"{len(measurements)} feature(s) measured from {args.lines3d}: {n_traces} trace(s), "
        f"{n_facets} facet(s); {n_planes} with a well-posed plane"
    )
    for label in sorted({m.label for m in measurements}):
        planes = [m for m in measurements if m.label == label and m.has_plane]
        if not planes:
            continue
        poles = [vector_from_plunge_trend(*pole_of_plane(m.dip_deg, m.dip_direction_deg))
                 for m in planes]
        fm = fisher_mean(poles)
        dip, ddir = dip_dip_direction(fm.vector)
        a95 = f", α95 {fm.alpha95_deg:.1f}°, k {fm.kappa:.0f}" if fm.alpha95_deg is not None else ""
        print(f"  {label}: {len(planes)} plane(s), Fisher mean dip {dip:.1f}° toward "
              f"{ddir:.1f}°{a95}")
    for key, why in _REJECTIONS:
        n = sum(1 for m in measurements if m.note.startswith("no plane") and key in m.note)
        if n:
            print(f"  no plane for {n}: {why}")
    if frame.get("frame") == "crs":
        print(f"  centroids in {frame.get('crs', 'the file CRS')}")
    if args.stereonet:
        save_stereonet(args.stereonet, measurements,
                       colors={m.label: m.color for m in measurements if m.color})
        print(f"  stereonet -> {args.stereonet}")
    print(f"  -> {out}")
    return EXIT_OK
