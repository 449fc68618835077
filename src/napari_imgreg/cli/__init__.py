"""The ``napari-imgreg`` command line (contract §8).

Every command prints a short human summary and writes machine-readable
output. Exit codes: 0 success, 1 a registration that failed its quality bar,
2 bad input (one line on stderr naming the file and the problem).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from napari_imgreg import __version__
from napari_imgreg.errors import InputError, input_error

__all__ = ["main"]

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT = 0, 1, 2


def _scene(mesh: str, georef: str | None, dem: str | None):
    from napari_imgreg.scene import Scene

    return Scene.load(mesh, georef=georef, dem=dem)


# ----------------------------------------------------------------- render
def cmd_render(args: argparse.Namespace) -> int:
    from napari_imgreg._atomic import atomic_path
    from napari_imgreg.io.photos import save_image
    from napari_imgreg.io.records import load_camera_and_pose
    from napari_imgreg.render import render

    out = Path(args.out)
    if out.suffix.lower() not in (".png", ".jpg", ".jpeg", ".tif", ".tiff"):
        raise input_error(out, "output must be .png, .jpg or .tif")
    if args.depth and Path(args.depth).suffix.lower() != ".npy":
        raise input_error(args.depth, "depth output must be a .npy file")
    pose_file = Path(args.pose_file)
    if not pose_file.exists():
        raise input_error(pose_file, "no such file")
    scene = _scene(args.mesh, args.georef, args.dem)
    intr, pose, kind, notes = load_camera_and_pose(
        pose_file, scene.georef, scene.dem, scene.terrain_height
    )
    t0 = time.perf_counter()
    result = render(scene, intr, pose, scale=args.scale, mode=args.mode)
    elapsed = time.perf_counter() - t0
    save_image(out, result.rgb)
    if args.depth:
        with atomic_path(args.depth) as tmp:
            np.save(tmp, result.depth)
    if args.xyz:
        with atomic_path(args.xyz) as tmp:
            np.save(tmp, result.xyz)
    trend, plunge, roll = pose.attitude
    x, y, z = pose.center
    print(
        f"rendered {scene.name} ({scene.n_faces:,} triangles) from the {kind} pose "
        f"at ({x:.1f}, {y:.1f}, {z:.1f}) m, trend {trend:.1f}° plunge {plunge:.1f}° "
        f"roll {roll:.1f}°"
    )
    for note in notes + scene.warnings:
        print(f"  assumed: {note}")
    h, w = result.shape
    print(
        f"  {w}×{h} px in {elapsed:.2f} s, surface covers {result.coverage:.0%} "
        f"of the image -> {out}"
        + (f", depth -> {args.depth}" if args.depth else "")
    )
    return EXIT_OK


# --------------------------------------------------------------- register
def cmd_register(args: argparse.Namespace) -> int:
    from napari_imgreg._atomic import atomic_write
    from napari_imgreg.io.photos import load_photo
    from napari_imgreg.io.records import prior_for_photo
    from napari_imgreg.registration.params import RegistrationParams, load_params
    from napari_imgreg.registration.pipeline import register

    photo_path = Path(args.photo)
    out = Path(args.out) if args.out else photo_path.with_suffix(".result.json")
    params = load_params(args.params) if args.params else RegistrationParams()
    scene = _scene(args.mesh, args.georef, args.dem)
    photo = load_photo(photo_path)
    prior = prior_for_photo(photo, scene, record_path=args.prior)

    def show(p) -> None:
        if args.verbose and p.message:
            print(f"  [{p.fraction:4.0%}] {p.message}")

    reg = register(scene, photo.image, prior, params, photo_path.name, on_progress=show)
    with atomic_write(out) as fh:
        json.dump(reg.to_dict(), fh, indent=2)
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


# ------------------------------------------------------------------- demo
def cmd_demo(args: argparse.Namespace) -> int:
    from napari_imgreg._atomic import atomic_write
    from napari_imgreg.io.photos import load_photo, save_image
    from napari_imgreg.io.records import prior_for_photo
    from napari_imgreg.registration.pipeline import register
    from napari_imgreg.render import render
    from napari_imgreg.sample import load_truth, sample_scene
    from napari_imgreg.scene import Scene

    t0 = time.perf_counter()
    folder = sample_scene("small")
    print(f"sample outcrop scene: {folder} ({time.perf_counter() - t0:.1f} s)")
    scene = Scene.load(folder / "outcrop.obj", dem=folder / "dem.tif")
    t1 = time.perf_counter()
    scene.build_engine()
    print(
        f"loaded {scene.n_faces:,} triangles, texture "
        f"{scene.texture.shape[1]}×{scene.texture.shape[0]} in {t1 - t0:.1f} s; "
        f"ray engine built in {scene.timings_s['build']:.2f} s"
    )
    if args.gui:
        return _demo_gui(folder)
    out = Path(args.out)
    summary = []
    for photo_path in sorted(folder.glob("IMG_*.jpg")):
        photo = load_photo(photo_path)
        prior = prior_for_photo(photo, scene)
        stem = photo_path.stem
        # What the phone's sensors give: the model rendered from the prior.
        t = time.perf_counter()
        prior_view = render(scene, prior.intrinsics, prior.pose)
        render_s = time.perf_counter() - t
        save_image(out / f"{stem}_prior_render.png", prior_view.rgb)
        save_image(out / f"{stem}_photo_vs_prior.jpg",
                   np.concatenate([photo.image, prior_view.rgb], axis=1))
        # The main job: register the photo, then render from the registered pose.
        reg = register(scene, photo.image, prior, photo_name=photo_path.name)
        result_path = out / f"{stem}.result.json"
        with atomic_write(result_path) as fh:
            json.dump(reg.to_dict(), fh, indent=2)
        reg_view = render(scene, reg.intrinsics, reg.pose)
        save_image(out / f"{stem}_registered_render.png", reg_view.rgb)
        side_by_side = out / f"{stem}_photo_vs_registered.jpg"
        save_image(side_by_side, np.concatenate([photo.image, reg_view.rgb], axis=1))
        # How close it came: the sample's ground truth.
        truth = load_truth(photo_path).pose
        rot_err = reg.pose.rotation_error_deg(truth)
        pos_err = float(np.linalg.norm(reg.pose.center - truth.center))
        prior_rot_err = prior.pose.rotation_error_deg(truth)
        prior_pos_err = float(np.linalg.norm(prior.pose.center - truth.center))
        seconds = reg.timings_s["total"]
        print(
            f"  {photo_path.name}: {reg.status.upper()} — grade {reg.grade} (Q = {reg.q:+.2f}) "
            f"in {seconds:.1f} s; off the true pose by {rot_err:.3f}° and {pos_err:.2f} m "
            f"(the prior: {prior_rot_err:.1f}° and {prior_pos_err:.1f} m)"
        )
        print(f"      -> {result_path}, {side_by_side}")
        summary.append(
            {"photo": photo_path.name, "render": f"{stem}_prior_render.png",
             "render_s": round(render_s, 3), "pose": prior.pose.to_dict(),
             "assumptions": prior.assumptions,
             "registration": {
                 "status": reg.status, "grade": reg.grade, "Q": reg.q,
                 "seconds": round(seconds, 3), "result": result_path.name,
                 "render": f"{stem}_registered_render.png", "pose": reg.pose.to_dict(),
                 "rotation_error_deg": rot_err, "position_error_m": pos_err,
                 "prior_rotation_error_deg": prior_rot_err,
                 "prior_position_error_m": prior_pos_err,
             }}
        )
    with atomic_write(out / "demo.json") as fh:
        json.dump({"scene": str(folder), "photos": summary}, fh, indent=2)
    regs = [s["registration"] for s in summary]
    n_ok = sum(r["status"] == "registered" for r in regs)
    worst = (
        f" (largest error {max(r['rotation_error_deg'] for r in regs):.3f}°, "
        f"{max(r['position_error_m'] for r in regs):.2f} m)" if regs else ""
    )
    print(
        f"registered {n_ok} of {len(regs)} sample photos{worst} in "
        f"{time.perf_counter() - t0:.1f} s; results, renders and side-by-side views "
        f"(photo | prior, photo | registered) in {out}/"
    )
    return EXIT_OK if n_ok == len(regs) else EXIT_FAILED


def _demo_gui(folder: Path) -> int:  # pragma: no cover - interactive
    from napari_imgreg.widgets.demo import open_demo  # the only path of the CLI that needs Qt

    open_demo(folder)
    return EXIT_OK


# ----------------------------------------------------------------- sample
def cmd_sample(args: argparse.Namespace) -> int:
    from napari_imgreg.sample import generate_outcrop

    t0 = time.perf_counter()
    out = generate_outcrop(Path(args.out), size=args.size, seed=args.seed)
    print(f"sample outcrop ({args.size}, seed {args.seed}) written to {out} "
          f"in {time.perf_counter() - t0:.1f} s")
    return EXIT_OK


# ------------------------------------------------------------------ main
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="napari-imgreg",
        description="Register field photographs to textured 3D outcrop models.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser(
        "render",
        help="render a mesh from a prior (sensor record) or a RESULT.json pose",
        description="Render colour (and optionally depth / xyz) of MESH from the pose in "
        "PRIOR_OR_RESULT.json: a sensor record (contract §3) or a registration result (§4).",
    )
    p.add_argument("mesh", metavar="MESH", help="OBJ+MTL+image, PLY or GLB/GLTF")
    p.add_argument("pose_file", metavar="PRIOR_OR_RESULT.json")
    p.add_argument("--out", required=True, metavar="RENDER.png", help="colour image to write")
    p.add_argument("--depth", metavar="DEPTH.npy", help="also write z-depth (metres, NaN = no hit)")
    p.add_argument("--xyz", metavar="XYZ.npy", help="also write per-pixel model coordinates (H, W, 3)")
    p.add_argument("--dem", help="DEM GeoTIFF or .asc (altitude for priors without one)")
    p.add_argument("--georef", help="georef.json (default: the one beside MESH, if any)")
    p.add_argument("--scale", type=float, default=1.0, help="resolution factor (default 1)")
    p.add_argument(
        "--mode", default="auto", choices=["auto", "color", "shaded", "color_shaded", "normal"],
        help="colouring (default: texture or colours, shading for plain meshes)",
    )
    p.set_defaults(func=cmd_render)

    p = sub.add_parser(
        "register",
        help="register a photo to a mesh (writes RESULT.json)",
        description="Register PHOTO to MESH from its sensor prior: render, match, solve the pose, "
        "score it, adapt and retry. Exit 0 when registered, 1 when it failed its quality bar.",
    )
    p.add_argument("mesh", metavar="MESH")
    p.add_argument("photo", metavar="PHOTO", help="JPEG, PNG or TIFF")
    p.add_argument("--prior", metavar="PHOTO.json",
                   help="sensor record (default: the .json beside the photo, then EXIF/XMP)")
    p.add_argument("--dem", help="DEM GeoTIFF or .asc")
    p.add_argument("--georef", help="georef.json (default: the one beside MESH, if any)")
    p.add_argument("--params", metavar="PARAMS.json", help="registration parameters (any subset)")
    p.add_argument("--out", metavar="RESULT.json", help="default: PHOTO.result.json beside the photo")
    p.add_argument("-v", "--verbose", action="store_true", help="print progress")
    p.set_defaults(func=cmd_register)

    p = sub.add_parser(
        "demo",
        help="run the main job on the bundled sample scene",
        description="Generate (once, cached) the sample outcrop, register each sample photo "
        "from its sensor prior and compare the pose with the sample's ground truth. Writes "
        "RESULT.json per photo and side-by-side views photo | render from the prior and "
        "photo | render from the registered pose. Exit 0 when every photo registered.",
    )
    p.add_argument("--out", default="demo_output", help="output folder (default demo_output)")
    p.add_argument("--gui", action="store_true", help="open napari with the sample loaded")
    p.set_defaults(func=cmd_demo)

    from napari_imgreg.cli.batch import add_parser as add_batch_parser
    from napari_imgreg.cli.interpret import add_parsers as add_interpret_parsers
    from napari_imgreg.cli.orient import add_parser as add_orient_parser

    add_interpret_parsers(sub)
    add_orient_parser(sub)
    add_batch_parser(sub)

    p = sub.add_parser(
        "sample",
        help="write the generated sample outcrop scene to a folder",
        description="Write a generated outcrop (OBJ+MTL+JPEG, georef.json, dem.tif, photos with "
        "sensor records and ground truth).",
    )
    p.add_argument("--out", required=True, help="folder to write")
    p.add_argument("--size", default="small", choices=["small", "large"])
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_sample)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except InputError as exc:
        print(f"napari-imgreg {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
