"""``napari-imgreg render``: render a mesh from a prior or a registered pose (contract §8).

The pose comes from a sensor record (contract §3: the prior) or a
RESULT.json (§4: the registered pose). Writes the colour image and, on
request, the z-depth and per-pixel model coordinates as ``.npy`` arrays.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ._common import (
    EXIT_OK,
    load_scene,
    refuse_overwriting_inputs,
    same_file,
    write_npy,
)
from ..errors import input_error
from ..io.photos import save_image
from ..prior import load_camera_and_pose
from ..render import render
from ..scene import size_text
from ..validate import MAX_RENDER_PIXELS, check_option, check_writable

#: Largest ``--scale``: finer than 8× the camera shows nothing new.
MAX_SCALE = 8.0

__all__ = ["add_parser", "run"]


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``render`` sub-command; its handler is :func:`run`."""
    p = subparsers.add_parser(
        "render",
        help="render a mesh from a prior (sensor record) or a RESULT.json pose",
        description="Render colour (and optionally depth / xyz) of MESH from the pose in "
        "PRIOR_OR_RESULT.json: a sensor record (docs/formats.md §3) or a registration result "
        "(§4).",
    )
    p.add_argument("mesh", metavar="MESH", help="the model: a mesh (OBJ+MTL+image, PLY, "
                   "GLB/GLTF) or a lidar point cloud (LAS/LAZ, E57, PTS/XYZ, PLY)")
    p.add_argument("pose_file", metavar="PRIOR_OR_RESULT.json")
    p.add_argument("--out", required=True, metavar="RENDER.png", help="colour image to write")
    p.add_argument("--depth", metavar="DEPTH.npy", help="also write z-depth (metres, NaN = no hit)")
    p.add_argument("--xyz", metavar="XYZ.npy", help="also write per-pixel model coordinates (H, W, 3)")
    p.add_argument("--dem", help="DEM GeoTIFF or .asc (altitude for priors without one)")
    p.add_argument("--georef", help="georef.json (default: the one beside MESH, if any)")
    p.add_argument("--scale", type=float, default=1.0,
                   help=f"resolution factor, in (0, {MAX_SCALE:g}] (default 1); the render may "
                        f"have at most {MAX_RENDER_PIXELS / 1e6:g} MP")
    p.add_argument(
        "--mode", default="auto", choices=["auto", "color", "shaded", "color_shaded", "normal"],
        help="colouring (default: texture or colours, shading for plain meshes)",
    )
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``render``: load the scene and the pose, render, write the images."""
    out = Path(args.out)
    if out.suffix.lower() not in (".png", ".jpg", ".jpeg", ".tif", ".tiff"):
        raise input_error(out, "output must be .png, .jpg or .tif")
    if args.depth and Path(args.depth).suffix.lower() != ".npy":
        raise input_error(args.depth, "depth output must be a .npy file")
    if args.xyz and Path(args.xyz).suffix.lower() != ".npy":
        raise input_error(args.xyz, "xyz output must be a .npy file")
    check_option(args.scale, "--scale", 0.0, MAX_SCALE, low_open=True)
    if args.depth and args.xyz and same_file(args.depth, args.xyz):
        raise input_error(args.xyz, "refusing to write --depth and --xyz to one file; "
                                    "choose another name")
    inputs = [("mesh", args.mesh), ("pose file", args.pose_file),
              ("georeference", args.georef), ("DEM", args.dem)]
    # An OBJ's material file and texture images are inputs too: a render
    # written over the texture would destroy the model.
    for companion in _mesh_companions(args.mesh):
        what = "mesh's material file" if companion.suffix.lower() == ".mtl" else "mesh's texture"
        inputs.append((what, companion))
    for output in (out, args.depth, args.xyz):
        refuse_overwriting_inputs(output, inputs)
    # Before loading the model: a path that cannot be written fails now.
    for path in (out, args.depth, args.xyz):
        if path:
            check_writable(path)
    pose_file = Path(args.pose_file)
    if not pose_file.exists():
        raise input_error(pose_file, "no such file")
    scene = load_scene(args.mesh, args.georef, args.dem)
    intr, pose, kind, notes = load_camera_and_pose(
        pose_file, scene.georef, scene.dem, scene.terrain_height, model_bounds=scene.bounds
    )
    t0 = time.perf_counter()
    result = render(scene, intr, pose, scale=args.scale, mode=args.mode)
    elapsed = time.perf_counter() - t0
    save_image(out, result.rgb)
    if args.depth:
        write_npy(args.depth, result.depth)
    if args.xyz:
        write_npy(args.xyz, result.xyz)
    trend, plunge, roll = pose.attitude
    x, y, z = pose.center
    print(
        f"rendered {scene.name} ({size_text(scene)}) from the {kind} pose "
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
        + (f", xyz -> {args.xyz}" if args.xyz else "")
    )
    back = _back_face_share(scene, result)
    if back > 0.5:
        print(f"  warning: {back:.0%} of the surface in view is seen from behind (its "
              "triangles face away from the camera): is the camera below the ground or "
              "inside the model (its altitude, the DEM), or are the model's triangles wound "
              "inward?")
    far = _far_from_origin_warning(scene, pose)
    if far:
        print(f"  warning: {far}")
    if result.coverage == 0:
        print("  warning: nothing of the model is in view: is the pose in the model's frame "
              "(the georef.json beside the model) and facing it?")
    return EXIT_OK


def _mesh_companions(mesh: str | Path) -> list[Path]:
    """The files an OBJ reads beside it (its MTL and texture images)."""
    from ..io.meshes import _companions

    path = Path(mesh)
    if not path.is_file():
        return []
    return _companions(path)[1:]


#: Coordinates beyond this (metres) lose more than ~1 cm in single precision.
FAR_FROM_ORIGIN_M = 1.0e5


def _far_from_origin_warning(scene, pose) -> str | None:
    """A warning when the model or the camera lies so far from the origin of
    the model frame (e.g. a mesh in UTM coordinates) that single-precision
    ray casting and the float32 xyz lose centimetres or more."""
    import numpy as np

    model_reach = float(np.abs(np.asarray(scene.bounds, np.float64)).max())
    camera_reach = float(np.abs(pose.center).max())
    reach = max(model_reach, camera_reach)
    if not reach > FAR_FROM_ORIGIN_M:
        return None
    step = float(np.spacing(np.float32(reach)))
    what = "the model's coordinates reach" if model_reach >= camera_reach else "the camera lies"
    return (f"{what} {reach:,.0f} m from the origin: single-precision "
            f"ray casting resolves only ~{step:.2g} m there, so xyz and depth may be off "
            f"by that much or more; use a local frame (coordinates minus an origin, the "
            f"origin in georef.json)")


def _back_face_share(scene, result) -> float:
    """Of the pixels that see a mesh, the share that see a triangle from
    behind (0 for a point cloud, whose normals have no outside)."""
    import numpy as np

    if getattr(scene, "is_cloud", False) or not result.mask.any():
        return 0.0
    faces = result.face_id[result.mask]
    normals = scene.face_array("normals")[faces]
    view = result.xyz[result.mask] - result.cam_from_world.center.astype(np.float32)
    return float(np.mean(np.einsum("ij,ij->i", normals, view) > 0))
