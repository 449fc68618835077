"""``napari-imgreg project``: lines drawn on a registered photo onto the mesh (contract §5, §8).

Casts the lines and polygons of LINES.geojson (pixel coordinates) through the
registered camera of RESULT.json onto the mesh, or onto a DEM used as the
surface, and writes 3D GeoJSON (or CSV / OBJ / PLY by the ``--out`` suffix).
Bad input raises :class:`~napari_imgreg.errors.InputError`, which the main
command turns into one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import math
from collections import Counter
from pathlib import Path

from ._common import EXIT_OK, load_scene, refuse_overwriting_inputs
from ..errors import InputError, input_error
from ..io.records import read_json
from ..prior import load_camera_and_pose
from ..scene import Scene
from ..validate import check_writable

__all__ = ["add_parser", "run"]

#: A ``MESH`` with one of these suffixes is a DEM, used as the surface.
_DEM_SUFFIXES = (".tif", ".tiff", ".asc")


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``project`` sub-command; its handler is :func:`run`."""
    p = subparsers.add_parser(
        "project",
        help="project lines drawn on a registered photo onto the mesh (3D GeoJSON)",
        description="Cast the lines and polygons of LINES.geojson (pixel [col, row] "
        "coordinates, properties.label) through the registered camera of RESULT.json onto "
        "MESH. Lines follow the relief (about one ray per pixel) and are split where they "
        "leave the surface (sky, holes, occluding ridges), never bridged. Writes 3D "
        "GeoJSON (or .gpkg / .shp / .csv / .obj / .ply by the --out suffix) with properties.source naming "
        "the photo. Several RESULT.json/LINES.geojson pairs merge into one file.",
    )
    p.add_argument("result", metavar="RESULT.json",
                   help="registration result (a sensor record works too: its prior pose)")
    p.add_argument("mesh", metavar="MESH",
                   help="the model: a mesh (OBJ+MTL+image, PLY, GLB/GLTF), a lidar point "
                   "cloud (LAS/LAZ, E57, PTS/XYZ) or a DEM (.tif/.asc) as the surface")
    p.add_argument("lines", metavar="LINES.geojson", help="interpretations drawn on the photo")
    p.add_argument("--also", nargs=2, action="append", default=[],
                   metavar=("RESULT.json", "LINES.geojson"),
                   help="another photo's result and lines, merged into the same output "
                   "(repeatable)")
    p.add_argument("--out", required=True, metavar="LINES3D.geojson",
                   help="3D output: .geojson, .gpkg (GeoPackage layers traces, facets, "
                   "measurements, cameras; in the georef CRS when known), .shp (3D shapefiles, "
                   "the same layers), .csv (vertices), .obj or .ply (polylines)")
    p.add_argument("--georeferenced", action="store_true",
                   help="write CRS coordinates (local + georef origin) instead of local ones")
    p.add_argument("--georef", help="georef.json (default: the one beside MESH, if any)")
    p.add_argument("--dem", help="DEM GeoTIFF or .asc (altitude for a sensor-record pose)")
    p.add_argument("--step", type=float, default=1.0, metavar="PX",
                   help="sample spacing along the lines, pixels (default 1, at least 0.05: "
                   "a line has at most its length in the photo / step samples)")
    p.add_argument("--pixel-noise", type=float, default=1.5, metavar="PX",
                   help="the drawing's expected error at each vertex, pixels (default 1.5); "
                   "with the pose's uncertainty and the mesh resolution it gives each "
                   "feature's sigma_m and the σ columns of `measure`")
    p.add_argument("--grazing", type=float, default=5.0, metavar="DEG",
                   help="split where the surface would be seen more obliquely than this "
                   "(default 5°)")
    p.add_argument("--gap-spacings", type=float, default=None, metavar="N",
                   help="point clouds: split a line where the range jumps by more than N "
                   "point spacings (times the range factor, plus the oblique allowance; "
                   "default 4, in [0.5, 100]); ignored on a mesh")
    p.set_defaults(func=run)
    return p


def _load_surface(mesh: str, georef: str | None, dem: str | None) -> Scene:
    """The mesh, or the DEM given as ``MESH`` (with the georef.json beside it,
    unless ``--georef`` names one)."""
    path = Path(mesh)
    if not path.exists():
        raise input_error(path, "no such file")
    if path.suffix.lower() in _DEM_SUFFIXES:
        return Scene.from_dem(path, georef=georef or None)  # else the georef.json beside it
    from ..io.meshes import check_model_suffix

    check_model_suffix(path, dsm=True)  # a DSM is taken here: the message says so
    return load_scene(path, georef, dem)


def run(args: argparse.Namespace) -> int:
    """Run ``project``: cast the drawn lines onto the mesh, write LINES3D."""
    from ..interpret.files import (
        EXPORT_SUFFIXES,
        check_gis_outputs,
        export_features,
        export_in_crs,
        read_interpretations,
    )
    from ..interpret.project import (
        ProjectionParams,
        merge_interpretations,
        project_interpretations,
    )

    out = Path(args.out)
    if out.suffix.lower() not in EXPORT_SUFFIXES:
        raise input_error(out, f"output must be one of {', '.join(EXPORT_SUFFIXES)}")
    pairs = [(args.result, args.lines)] + [tuple(p) for p in args.also]
    refuse_overwriting_inputs(out, [
        *((what, path) for pair in pairs for what, path in zip(("result", "lines"), pair)),
        ("mesh", args.mesh), ("georeference", args.georef), ("DEM", args.dem),
    ])
    check_writable(out)  # before the mesh loads and the rays are cast
    if out.suffix.lower() == ".shp":  # and every other file of the shapefile set
        check_gis_outputs(out)
    from ..interpret.project import MIN_STEP_PX, check_drawing
    from ..interpret.uncertainty import PoseUncertainty, UncertaintyParams

    if not (math.isfinite(args.step) and MIN_STEP_PX <= args.step <= 100.0):
        raise input_error(None, f"--step must be between {MIN_STEP_PX} and 100 pixels "
                          f"(got {args.step:g})")
    if not (math.isfinite(args.grazing) and 0.0 <= args.grazing < 90.0):
        raise input_error(None, f"--grazing must be in [0, 90) degrees (got {args.grazing:g})")
    if not (math.isfinite(args.pixel_noise) and 0.0 <= args.pixel_noise <= 20.0):
        raise input_error(None, f"--pixel-noise must be in [0, 20] pixels "
                          f"(got {args.pixel_noise:g})")
    from ..interpret.on_cloud import CloudProjectionParams

    if args.gap_spacings is None:
        cloud_params = CloudProjectionParams()
    elif not (math.isfinite(args.gap_spacings) and 0.5 <= args.gap_spacings <= 100.0):
        raise input_error(None, f"--gap-spacings must be in [0.5, 100] point spacings "
                          f"(got {args.gap_spacings:g})")
    else:
        cloud_params = CloudProjectionParams(gap_spacings=args.gap_spacings)
    unc_params = UncertaintyParams(drawing_px=args.pixel_noise)
    for result, lines in pairs:
        for f in (result, lines):
            if not Path(f).exists():
                raise input_error(f, "no such file")
    # Read every input before the (slower) mesh, so bad input fails fast.
    drawn = [read_interpretations(lines) for _, lines in pairs]
    for (_, lines), items in zip(pairs, drawn):
        if not items:  # an empty output would look like a projection that lost everything
            raise input_error(lines, "no features to project (no lines or polygons in it)")
    scene = _load_surface(args.mesh, args.georef, args.dem)
    if args.georeferenced and scene.georef is None:
        raise input_error(
            args.mesh, "--georeferenced needs a georeference (georef.json beside the mesh "
            "or --georef)")
    for note in scene.warnings:  # e.g. a cloud's CRS rule: which frame its points are in
        print(f"  assumed: {note}")
    params = ProjectionParams(step_px=args.step, grazing_deg=args.grazing, cloud=cloud_params)
    sets = []
    for (result, lines), items in zip(pairs, drawn):
        intr, pose, kind, notes = load_camera_and_pose(
            result, scene.georef, scene.dem, scene.terrain_height, model_bounds=scene.bounds)
        data = read_json(result)
        photo = str(data.get("photo") or Path(result).stem) if isinstance(data, dict) else ""
        for k, item in enumerate(items):  # before any ray: bounded work
            try:
                check_drawing(item.pixels, intr.width, intr.height, f"feature {k + 1}")
            except InputError as exc:
                # The message names the photo's size already (check_drawing).
                raise input_error(lines, str(exc)) from None
        pose_unc = PoseUncertainty.from_result(data, intr.fx)
        status = data.get("status") if isinstance(data, dict) else None
        if kind == "prior":
            print(f"  warning: {result} is a sensor record: projecting with the PRIOR pose")
        elif status and status != "registered":
            print(f"  warning: {result} status is {status!r}: lines may be misplaced")
        features = project_interpretations(scene, intr, pose, items, source=photo, params=params,
                                           pose_uncertainty=pose_unc, uncertainty=unc_params)
        if pose_unc.source != "result":
            print(f"  {result}: no pose uncertainty in the result; assumed "
                  f"{pose_unc.reprojection_px:.1f} px, {pose_unc.position_m:.2f} m, "
                  f"{pose_unc.rotation_deg:.2f}° ({pose_unc.source})")
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
    notes = export_features(out, merged, scene.georef, args.georeferenced)
    labels = Counter(f.label for f in merged)
    in_crs = export_in_crs(out, scene.georef, args.georeferenced)
    frame = f"{scene.georef.crs} (local + origin)" if in_crs else "local frame"
    print(
        f"  {len(merged)} feature(s) ("
        + ", ".join(f"{n} {label}" for label, n in sorted(labels.items()))
        + f"), {frame} -> {out}"
    )
    for note in notes:
        print(f"  note: {note}")
    return EXIT_OK
