"""``napari-imgreg register``: register one photo to a mesh (contract §4, §8).

From the photo's sensor prior (its ``.json`` record, else EXIF/XMP): render,
match, solve the pose, score it, adapt and retry; writes RESULT.json. Exit 0
when registered, 1 when the result failed its quality bar.
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
from ..io.photos import load_photo
from ..prior import prior_for_photo
from ..validate import check_writable

__all__ = ["add_parser", "run"]


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``register`` sub-command; its handler is :func:`run`."""
    p = subparsers.add_parser(
        "register",
        help="register a photo to a mesh (writes RESULT.json)",
        description="Register PHOTO to MESH from its sensor prior: render, match, solve the pose, "
        "score it, adapt and retry. Exit 0 when registered, 1 when it failed its quality bar.",
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
    p.add_argument("--out", metavar="RESULT.json", help="default: PHOTO.result.json beside the photo")
    p.add_argument("-v", "--verbose", action="store_true", help="print progress")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``register``: register the photo, write RESULT.json, print a summary."""
    from ..registration import pipeline
    from ..prior import check_photo_size

    photo_path = Path(args.photo)
    if not photo_path.name:
        raise input_error(args.photo or "PHOTO", "no photo file named")
    out = Path(args.out) if args.out else photo_path.with_suffix(".result.json")
    refuse_overwriting_inputs(out, [
        ("sensor record", args.prior), ("photo", photo_path), ("mesh", args.mesh),
        ("georeference", args.georef), ("DEM", args.dem), ("parameters", args.params),
    ])
    # Checked before the registration, not found out after it.
    check_writable(out)
    if args.prior and not Path(args.prior).exists():
        # Not silently replaced by the photo's EXIF.
        raise input_error(args.prior, "no such file")
    read_params(args.params)  # a bad file is refused before the scene loads
    scene = load_scene(args.mesh, args.georef, args.dem)
    params = read_params(args.params, scene)  # a point cloud's defaults under the file's
    photo = load_photo(photo_path)
    prior = prior_for_photo(photo, scene, record_path=args.prior)
    check_photo_size(photo, prior, args.prior)  # as batch does: one line, not a traceback
    reg = pipeline.register(scene, photo.image, prior, params, photo_path.name,
                            on_progress=progress_printer(args.verbose, "  "))
    write_json(out, reg.to_dict())
    trend, plunge, roll = reg.pose.attitude
    x, y, z = reg.pose.center
    m = reg.metrics
    print(
        f"{photo_path.name}: {reg.status.upper()} — grade {reg.grade} (Q = {reg.q:+.2f}) "
        f"after {len(reg.trials)} trial(s) in {reg.timings_s['total']:.1f} s"
    )
    print(
        f"  pose ({x:.2f}, {y:.2f}, {z:.2f}) m, trend {trend:.2f}° plunge {plunge:.2f}° "
        f"roll {roll:.2f}°; moved {np.linalg.norm(reg.pose.center - prior.pose.center):.1f} m, "
        f"{reg.pose.rotation_error_deg(prior.pose):.1f}° from the prior"
    )
    err = m.get("reprojection_error_px")
    print(
        f"  points {m.get('points_photo')}/{m.get('points_render')}, feature inliers "
        f"{m.get('feature_inliers')}, 3D inliers {m.get('inliers_3d')}, reprojection error "
        + (f"{err:.2f} px" if err is not None else "–")
    )
    for note in prior.assumptions:
        print(f"  assumed: {note}")
    for hint in reg.hints:
        print(f"  hint: {hint}")
    print(f"  -> {out}")
    return EXIT_OK if reg.registered else EXIT_FAILED
