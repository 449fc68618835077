"""``napari-imgreg orient``: orient a model from phone camera attitudes (contract §7, §8).

Wired into the main command line by :func:`add_parser`; the handler
:func:`cmd_orient` returns the exit code (0 also when quality flags warn:
the warnings are printed). Bad input raises
:class:`~napari_imgreg.errors.InputError`, which the main command turns
into one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ._common import refuse_overwriting_inputs
from ..errors import InputError, input_error
from ..validate import check_option, check_writable

__all__ = ["add_parser", "cmd_orient"]

EXIT_OK = 0


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``orient`` sub-command; its handler is :func:`cmd_orient`."""
    p = subparsers.add_parser(
        "orient",
        help="orient a model from the camera attitudes a phone recorded",
        description="Find the rotation that carries the model's camera orientations "
        "(ESTIMATED, its arbitrary frame) onto the phone's (MEASURED, true north), report "
        "per-photo residuals Δξ/Δρ and the quality flags of Corradetti/Tavani et al., and "
        "optionally rotate a mesh or point cloud. Tables: CSV "
        "photo,trend_deg,plunge_deg,roll_deg[,x,y,z]; Metashape camera .xml; COLMAP "
        "images.txt; a folder of photos with DJI gimbal XMP.",
    )
    p.add_argument("estimated", metavar="ESTIMATED", help="the model's camera orientations")
    p.add_argument("measured", metavar="MEASURED", help="the phone's camera attitudes")
    p.add_argument("--out", required=True, metavar="ORIENTATION.json", help="result to write")
    p.add_argument(
        "--method", default="robust", choices=["robust", "lsq", "paper"],
        help="estimator whose rotation is the result (all three are reported; default robust)",
    )
    p.add_argument("--apply", metavar="MESH", help="mesh or point cloud (model frame) to rotate")
    p.add_argument("--mesh-out", metavar="OUT", help="where to write the rotated --apply mesh")
    p.add_argument(
        "--about", default="auto", choices=["auto", "cameras", "origin"],
        help="rotation centre: the centroid of the model's camera centres or the model "
        "origin (default: cameras when the table has centres)",
    )
    p.add_argument(
        "--declination", type=_declination, default=0.0, metavar="DEG|auto",
        help="magnetic declination, degrees east in [-180, 180], added to MEASURED trends "
        "(default 0: the phone logged true north); 'auto': the World Magnetic Model's at the "
        "model's georeferenced origin (without georef.json: the MEASURED photos' median GPS "
        "position) on the photos' median capture day",
    )
    p.add_argument(
        "--georef", metavar="georef.json",
        help="the model's georeference, whose origin places the site for --declination auto "
        "(default: a georef.json beside the --apply mesh or the ESTIMATED table, else one "
        "folder up from them)",
    )
    p.add_argument("--plots", metavar="DIR", help="write the Δξ/Δρ plots (PNG) into DIR")
    p.set_defaults(func=cmd_orient)
    return p


def _declination(text: str) -> float | str:
    """``--declination``: degrees (checked for range later) or ``auto``."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected degrees east (e.g. 3.0) or 'auto', got {text!r}") from None


def _georef_for_auto(args: argparse.Namespace) -> Path | None:
    """The georef.json that places the site for ``--declination auto``; None
    when there is none (the MEASURED photos' GPS places it then)."""
    from ..orient import default_georef_path

    if args.georef:
        if not Path(args.georef).is_file():
            raise input_error(args.georef, "no such file")
        return Path(args.georef)
    return default_georef_path(args.apply, args.estimated)


def cmd_orient(args: argparse.Namespace) -> int:
    """Run ``orient``: read, estimate, write ORIENTATION.json, print a summary."""
    from ..io.orientation_tables import read_orientation_table
    from ..orient import (
        MESH_OUT_SUFFIXES,
        apply_to_mesh_file,
        orient,
        save_orientation,
        save_residual_plots,
    )

    out = Path(args.out)
    if out.suffix.lower() != ".json":
        raise input_error(out, "output must be a .json file")
    auto = args.declination == "auto"
    if not auto:
        # A NaN declination would turn every trend into NaN (and the fit into nonsense).
        check_option(args.declination, "--declination", -180.0, 180.0)
    if args.georef and not auto:
        raise input_error(args.georef, "--georef is read only with --declination auto")
    georef = _georef_for_auto(args) if auto else None
    if bool(args.apply) != bool(args.mesh_out):
        raise input_error(
            args.apply or args.mesh_out, "--apply MESH and --mesh-out OUT go together"
        )
    if args.apply:
        if not Path(args.apply).exists():
            raise input_error(args.apply, "no such file")
        if Path(args.mesh_out).suffix.lower() not in MESH_OUT_SUFFIXES:
            raise input_error(
                args.mesh_out, f"output must be one of {', '.join(MESH_OUT_SUFFIXES)}"
            )
    tables = [("ESTIMATED table", args.estimated), ("MEASURED table", args.measured)]
    refuse_overwriting_inputs(out, [*tables, ("mesh", args.apply), ("georef", georef)])
    refuse_overwriting_inputs(args.mesh_out, [("mesh", args.apply), *tables])
    check_writable(out)
    if args.mesh_out:
        check_writable(args.mesh_out)
    if args.plots:
        check_writable(args.plots, folder=True)

    if Path(args.estimated).resolve() == Path(args.measured).resolve():
        raise input_error(args.measured, "is the ESTIMATED table too: MEASURED is the phone's "
                                         "attitudes, ESTIMATED the model's cameras")
    estimated = read_orientation_table(args.estimated)
    measured = read_orientation_table(args.measured)
    # The model's cameras come from photogrammetry, the phone's attitudes
    # from a log; the other way round the rotation is the inverse.
    swapped = (measured.kind in ("metashape", "colmap")
               and estimated.kind in ("csv", "photos") and estimated.positions is None)
    if args.about == "cameras" and (estimated.positions is None
                                    or not np.isfinite(estimated.positions).all(axis=1).any()):
        raise input_error(args.estimated, "no camera centres (x, y, z) to rotate about: "
                                          "use --about origin")
    try:
        result = orient(
            estimated, measured, method=args.method,
            center=None if args.about == "auto" else args.about,
            declination_deg=args.declination, georef=georef,
        )
    except InputError as exc:
        # A paired photo without a centre: orient() words the fix for the API,
        # here it is an option.
        raise InputError(str(exc).replace("(use the origin)", "(use --about origin)")) from None
    # The mesh first: it is read before anything is written, so a bad mesh
    # leaves an earlier ORIENTATION.json as it was.
    written = (apply_to_mesh_file(args.apply, args.mesh_out, result.rotation, result.center)
               if args.apply else None)
    save_orientation(result, out)

    for line in result.summary_lines():
        print(line)
    for note in result.notes:
        print(f"  note: {note}")
    if auto and georef is not None and not args.georef:
        from ..orient.declination import georef_found_above

        if georef_found_above(georef, args.apply, args.estimated):
            print(f"  note: {georef} was found one folder up from the tables and placed the "
                  "site of the declination (--georef FILE names another)")
    if swapped:
        print(f"warning: the MEASURED table {args.measured} is a photogrammetry export and "
              f"the ESTIMATED table {args.estimated} has no camera centres: are they swapped? "
              "ESTIMATED comes first (the model's cameras), then MEASURED (the phone's)",
              file=sys.stderr)
    if args.apply:
        print(f"rotated {args.apply} ({written}) -> {args.mesh_out}")
        if any("geocentric" in note for note in estimated.notes):
            # The rotation is of the chunk's internal frame; Metashape exports a
            # referenced chunk's mesh in its CRS, where it would turn it wrongly.
            print(f"warning: {args.estimated}: the chunk is referenced to a CRS, so the "
                  f"rotation is of its internal frame: {args.mesh_out} is right only if "
                  f"{args.apply} was exported in local (chunk) coordinates, not in the CRS",
                  file=sys.stderr)
    if args.plots:
        print(f"plots -> {save_residual_plots(result, args.plots)}")
    n_warn = len(result.warnings)
    warned = f" ({n_warn} quality warning{'s' if n_warn > 1 else ''})" if n_warn else ""
    print(f"-> {out}{warned}")
    return EXIT_OK
