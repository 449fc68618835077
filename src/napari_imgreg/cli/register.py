"""``napari-imgreg register``: register one photo to a mesh (contract §4, §8).

From the photo's sensor prior (its ``.json`` record, else EXIF/XMP): render,
match, solve the pose, score it, adapt and retry; writes RESULT.json. With
``--pairs``, the pose is solved from a control-point file instead
(:func:`~napari_imgreg.registration.manual.register_from_pairs`, the
workbench's manual registration). Exit 0 when registered, 1 when the result
failed its quality bar.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ._common import (
    EXIT_FAILED,
    EXIT_OK,
    load_scene,
    progress_printer,
    read_params,
    refuse_overwriting_inputs,
    write_json,
)
from ..errors import input_error
from ..io.control_points import read_control_points
from ..io.photos import PHOTO_SUFFIXES, load_photo
from ..prior import prior_for_photo
from ..validate import check_writable
from ..registration.quality import outcome_words

__all__ = ["add_parser", "run"]


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``register`` sub-command; its handler is :func:`run`."""
    p = subparsers.add_parser(
        "register",
        help="register a photo to a mesh (writes RESULT.json)",
        description="Register PHOTO to MESH from its sensor prior: render, match, solve the pose, "
        "score it, adapt and retry; or, with --pairs, solve the pose from control points (photo "
        "pixel and model point pairs) and score it. Exit 0 when registered, 1 when it failed "
        "its quality bar.",
    )
    p.add_argument("mesh", metavar="MESH", help="the model: a mesh (OBJ+MTL+image, PLY, "
                   "GLB/GLTF) or a lidar point cloud (LAS/LAZ, E57, PTS/XYZ, PLY)")
    p.add_argument("photo", metavar="PHOTO", help="JPEG, PNG, TIFF or HEIC/HEIF")
    p.add_argument("--prior", metavar="PHOTO.json",
                   help="sensor record (default: the .json beside the photo, then EXIF/XMP), "
                        "or an earlier RESULT.json of the photo to start from its pose")
    p.add_argument("--dem", help="DEM GeoTIFF or .asc")
    p.add_argument("--georef", help="georef.json (default: the one beside MESH, if any)")
    p.add_argument("--params", metavar="PARAMS.json", help="registration parameters (any subset)")
    p.add_argument("--pairs", metavar="PAIRS.csv",
                   help="control points (photo_x,photo_y,x,y,z[,name], or easting,northing,"
                        "elevation in the georeference's CRS, or latitude,longitude,elevation): "
                        "solve the pose from them "
                        "instead of matching; the prior gives the camera and the start")
    p.add_argument("--solve-focal", action="store_true",
                   help="with --pairs: also solve the focal length (6 or more pairs)")
    p.add_argument("--out", metavar="RESULT.json", help="default: PHOTO.result.json beside the photo")
    p.add_argument("-v", "--verbose", action="store_true", help="print progress")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``register``: register the photo, write RESULT.json, print a summary."""
    from ..registration import manual, pipeline
    from ..prior import check_photo_size

    photo_path = Path(args.photo)
    if not photo_path.name:
        raise input_error(args.photo or "PHOTO", "no photo file named")
    pairs_path = getattr(args, "pairs", None)
    if getattr(args, "solve_focal", False) and not pairs_path:
        raise input_error(None, "--solve-focal needs --pairs (the focal length is solved from "
                                "control points)")
    out = Path(args.out) if args.out else photo_path.with_suffix(".result.json")
    refuse_overwriting_inputs(out, [
        ("sensor record", args.prior), ("photo", photo_path), ("mesh", args.mesh),
        ("georeference", args.georef), ("DEM", args.dem), ("parameters", args.params),
        ("control points", pairs_path),
    ])
    if out.suffix.lower() != ".json":  # as measure's .csv: the file is RESULT.json
        raise input_error(out, "output must be a .json file (the RESULT.json)")
    # Checked before the registration, not found out after it.
    check_writable(out)
    if args.prior and not Path(args.prior).exists():
        # Not silently replaced by the photo's EXIF.
        raise input_error(args.prior, "no such file")
    read_params(args.params)  # a bad file is refused before the scene loads
    pairs = (read_control_points(pairs_path, min_pairs=manual.MIN_PAIRS) if pairs_path
             else None)  # likewise
    scene = load_scene(args.mesh, args.georef, args.dem)
    params = read_params(args.params, scene)  # a point cloud's defaults under the file's
    photo = load_photo(photo_path)
    prior = prior_for_photo(photo, scene, record_path=args.prior)
    check_photo_size(photo, prior, args.prior)  # as batch does: one line, not a traceback
    if pairs is None:
        reg = pipeline.register(scene, photo.image, prior, params, photo_path.name,
                                on_progress=progress_printer(args.verbose, "  "))
        assumptions = prior.assumptions
    else:
        if args.solve_focal and len(pairs) < manual.MIN_PAIRS_FOCAL:
            raise input_error(pairs_path, f"{len(pairs)} pairs: --solve-focal needs at least "
                                          f"{manual.MIN_PAIRS_FOCAL}")
        pairs.check_inside(prior.intrinsics.width, prior.intrinsics.height)
        named_for = _photo_named_by(Path(pairs_path), photo_path)
        if named_for is not None:
            print(f"warning: {Path(pairs_path).name} is named for {named_for}, not for "
                  f"{photo_path.name}: its pairs were probably picked on that photo")
        xyz = pairs.model_points_for(scene)
        if args.verbose:
            print(f"  solving the pose from {len(pairs)} control points, then scoring it",
                  flush=True)
        reg, sol = manual.register_from_pairs(scene, photo.image, prior, pairs.photo_px, xyz,
                                              solve_focal=args.solve_focal, params=params,
                                              photo_name=photo_path.name)
        assumptions = reg.assumptions
    write_json(out, reg.to_dict())
    # The model's own notes first: a cloud's CRS rule (a map-coordinate LAS
    # without georef.json) explains a camera "far from the model" below.
    _print_summary(reg, prior, photo_path, [*scene.warnings, *assumptions])
    if pairs is not None and sol.ok:
        _print_pairs(sol)
    print(f"  -> {out}")
    return EXIT_OK if reg.registered else EXIT_FAILED


def _photo_named_by(pairs_path: Path, photo_path: Path) -> str | None:
    """The photo beside a control-point file that the file is named for
    (``IMG_0001.pairs.csv`` beside ``IMG_0001.jpg``), when that is not the
    photo being registered; None otherwise."""
    stem = pairs_path.name.split(".")[0].lower()
    if stem == photo_path.stem.lower():
        return None
    for sibling in pairs_path.parent.iterdir():
        if sibling.stem.lower() == stem and sibling.suffix.lower() in PHOTO_SUFFIXES:
            return sibling.name
    return None


def _print_summary(reg, prior, photo_path: Path, assumptions) -> None:
    """The short human summary of a registration (status, pose, matches, notes)."""
    trend, plunge, roll = reg.pose.attitude
    x, y, z = reg.pose.center
    m = reg.metrics
    print(
        f"{photo_path.name}: {reg.status.upper()} — {outcome_words(reg.status, reg.grade)} "
        f"(Q = {reg.q:+.2f}) "
        f"after {len(reg.trials)} trial(s) in {reg.timings_s['total']:.1f} s"
    )
    print(
        f"  pose ({x:.2f}, {y:.2f}, {z:.2f}) m, trend {trend:.2f}° plunge {plunge:.2f}° "
        f"roll {roll:.2f}°; moved {np.linalg.norm(reg.pose.center - prior.pose.center):.1f} m, "
        f"{reg.pose.rotation_error_deg(prior.pose):.1f}° from the prior"
    )
    err = m.get("reprojection_error_px")
    if "points_photo" in m or "control_points" not in m:  # none scored: no pose from pairs
        print(
            f"  points {m.get('points_photo')}/{m.get('points_render')}, feature inliers "
            f"{m.get('feature_inliers')}, 3D inliers {m.get('inliers_3d')}, reprojection error "
            + (f"{err:.2f} px" if err is not None else "–")
        )
    for note in assumptions:
        print(f"  assumed: {note}")
    for hint in reg.hints:
        print(f"  hint: {hint}")


def _print_pairs(sol) -> None:
    """What the control points said of a solved pose: agreement and expected error."""
    unc = sol.uncertainty
    expected = ("" if unc is None else
                f"; expected error {unc.reprojection_px:.1f} px, {unc.position_m:.2f} m, "
                f"{unc.rotation_deg:.2f}°")
    focal = f"; focal length solved: {sol.intrinsics.fx:.1f} px" if sol.focal_solved else ""
    print(f"  control points: {sol.n_inliers} of {len(sol.inliers)} agree (RMS "
          f"{sol.rms_px:.2f} px, {sol.method}){expected}{focal}")
