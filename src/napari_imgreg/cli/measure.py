"""``napari-imgreg measure``: orientations of projected traces and facets (contract §6, §8).

Fits each trace's 3D line (plunge/trend) and, where the drawing determines
it (not a line drawn straight, which lies in the viewing plane), its plane
(dip/dip direction), each angle with a Monte Carlo σ; fits each facet's plane to the surface inside
it; writes MEASUREMENTS.csv and optionally a stereonet. Bad input raises
:class:`~napari_imgreg.errors.InputError`, which the main command turns into
one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ._common import EXIT_OK
from ..errors import input_error
from ..interpret.structural import DEFAULT_THRESHOLDS
from ..validate import check_option, check_writable

__all__ = ["add_parser", "run"]

#: Why a plane was rejected: (a word of its ``note``, the summary's wording).
_REJECTIONS = (
    ("planarity", "planarity below the threshold (a line or a blob)"),
    ("relief", "trace nearly straight (too little relief)"),
    ("outcrop surface", "plane is the outcrop surface (surface effect)"),
    (" points (< ", "too few points"),
    ("through the camera", "trace lies in its viewing plane (drawn straight: the plane is "
     "not determined)"),
    ("viewing rays", "plane contains the viewing rays"),
    ("pin the plane down", "dip σ above --max-dip-sigma (plane too close to the viewing plane)"),
    ("camera position unknown", "no camera position in the file (re-run `project`)"),
    ("on one line", "points on one line"),
    ("plane of the three points", "3-point plane: the camera lies in it (the viewing plane)"),
    ("three clicked points", "3-point plane: not three clicked points on the surface"),
    ("no three_point_xyz", "3-point plane without its surface points (re-run `project`)"),
)


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``measure`` sub-command; its handler is :func:`run`."""
    p = subparsers.add_parser(
        "measure",
        help="plunge/trend and dip/dip direction of projected traces and facets (CSV)",
        description="Fit each trace's best 3D line (plunge/trend) and, where the drawing "
        "determines it, its best plane (dip/dip direction); fit each facet's plane to the "
        "surface inside it. A trace's plane is given only when its points leave the viewing "
        "plane through the camera centre (a line drawn straight on the photo never defines "
        "one) and its Monte Carlo dip σ is small, besides CloudCompare Compass's vetting "
        "(planarity, surface effect) and a relief test; rejected ones leave the cells empty "
        "and say why in 'note'. Every angle gets a σ column (pose uncertainty, drawing "
        "noise, mesh resolution). Traces of one contact (the same properties.contact and "
        "label) on several photos also get one combined row; a 3-point plane is the plane "
        "through its three surface points. Azimuths are from the model's +Y: the grid north "
        "of its CRS (the summary gives the angle to true north). Writes MEASUREMENTS.csv "
        "(docs/formats.md §8) and optionally a stereonet with confidence cones and Kamb "
        "contours.",
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
    p.add_argument("--min-view-spread", type=float, default=DEFAULT_THRESHOLDS.min_view_spread,
                   metavar="SIGMAS",
                   help="a trace's points must leave the plane through its camera centre by "
                   "this many times their expected error to define a plane (default "
                   f"{DEFAULT_THRESHOLDS.min_view_spread:g})")
    p.add_argument("--max-dip-sigma", type=float, default=5.0, metavar="DEG",
                   help="withhold a trace's plane whose Monte Carlo dip σ (the spread of "
                   "its dip over the samples) exceeds this many degrees (default 5°)")
    p.add_argument("--min-ray-angle", type=float, default=DEFAULT_THRESHOLDS.min_ray_angle_deg,
                   metavar="DEG", help="a trace's plane must make this angle with the viewing "
                   f"rays (default {DEFAULT_THRESHOLDS.min_ray_angle_deg:g}°)")
    p.add_argument("--samples", type=int, default=200,
                   help="Monte Carlo samples per feature for the σ columns (default 200, "
                   "20–5000)")
    p.add_argument("--seed", type=int, default=0,
                   help="Monte Carlo seed, 0 to 2**32 - 1 (default 0)")
    p.set_defaults(func=run)
    return p


#: GeoJSON ``crs`` names of longitude/latitude in degrees (RFC 7946's
#: default, and the old GeoJSON spelling of WGS84).
_DEGREE_CRS = ("CRS84", "EPSG::4326", "EPSG:4326", "EPSG::4979", "EPSG:4979", "CRS:84")


def _refuse_degrees(path) -> None:
    """Refuse projected lines whose coordinates are longitude and latitude:
    planes fitted to degrees and metres together are meaningless (every
    trace comes out vertical)."""
    from ..io.records import read_json

    data = read_json(path)
    crs = data.get("crs") if isinstance(data, dict) else None
    name = ((crs or {}).get("properties") or {}).get("name") if isinstance(crs, dict) else None
    if isinstance(name, str) and name.upper().endswith(_DEGREE_CRS):
        raise input_error(path, f"coordinates in longitude and latitude ({name}): measure needs "
                                "metres, the model frame (project's default) or a projected "
                                "CRS (project --georeferenced)")


def run(args: argparse.Namespace) -> int:
    """Run ``measure``: fit lines and planes, write MEASUREMENTS.csv (and a stereonet)."""
    from ..interpret.structural import (
        FitThresholds,
        dip_dip_direction,
        fisher_mean,
        pole_of_plane,
        save_stereonet,
        stereonet_format,
        vector_from_plunge_trend,
    )
    from ..interpret.project import measure_features
    from ..interpret.files import (
        azimuth_reference,
        read_features_geojson,
        write_measurements_csv,
    )

    out = Path(args.out)
    if out.suffix.lower() != ".csv":
        raise input_error(out, "output must be a .csv file")
    if args.stereonet:
        stereonet_format(args.stereonet)
    check_writable(out)
    if args.stereonet:
        check_writable(args.stereonet)
    import math

    import numpy as np

    from ..interpret.uncertainty import UncertaintyParams

    if not 0.0 <= args.min_planarity <= 1.0:
        raise input_error(None, "--min-planarity must be in [0, 1]")
    for name, value, lo, hi in (("--surface-effect", args.surface_effect, 0.0, 90.0),
                                ("--min-relief", args.min_relief, 0.0, 1.0),
                                ("--min-view-spread", args.min_view_spread, 0.0, 100.0),
                                ("--max-dip-sigma", args.max_dip_sigma, 0.0, 90.0),
                                ("--min-ray-angle", args.min_ray_angle, 0.0, 90.0),
                                ("--samples", args.samples, 20, 5000)):
        if not (math.isfinite(value) and lo <= value <= hi):
            raise input_error(None, f"{name} must be in [{lo:g}, {hi:g}] (got {value:g})")
    check_option(args.seed, "--seed", 0, 2**32 - 1)  # NumPy's seed range, as for `sample`
    features, frame = read_features_geojson(args.lines3d)
    _refuse_degrees(args.lines3d)
    if not features:
        raise input_error(args.lines3d, "no features to measure (an empty FeatureCollection)")
    thresholds = FitThresholds(
        min_planarity=args.min_planarity, surface_effect_deg=args.surface_effect,
        min_relief=args.min_relief, min_view_spread=args.min_view_spread,
        min_ray_angle_deg=args.min_ray_angle, max_dip_sigma_deg=args.max_dip_sigma,
    )
    unc = UncertaintyParams(samples=args.samples, seed=args.seed)
    measurements = measure_features(features, thresholds, unc)
    write_measurements_csv(out, measurements)
    n_planes = sum(m.has_plane for m in measurements)
    n_traces = sum(m.kind == "trace" for m in measurements)
    n_facets = sum(m.kind == "facet" for m in measurements)
    n_off = sum(m.n_points == 0 for m in measurements)
    print(
        f"{len(measurements)} feature(s) measured from {args.lines3d}: {n_traces} trace(s), "
        f"{n_facets} facet(s); {n_planes} with a well-posed plane"
        + (f"; {n_off} off the surface (a row with empty cells)" if n_off else "")
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
    if any(m.note.startswith("no plane") for m in measurements):
        print("  no plane, by reason (a trace may have several):")
    for key, why in _REJECTIONS:
        n = sum(1 for m in measurements if m.note.startswith("no plane") and key in m.note)
        if n:
            print(f"    {n}: {why}")
    if frame.get("frame") == "crs":
        print(f"  centroids in {frame.get('crs', 'the file CRS')}")
    print("  " + azimuth_reference(frame, np.array([m.centroid for m in measurements])))
    if args.stereonet:
        save_stereonet(args.stereonet, measurements,
                       colors={m.label: m.color for m in measurements if m.color})
        print(f"  stereonet -> {args.stereonet}")
    print(f"  -> {out}")
    return EXIT_OK
