"""Apply an orientation: rotate points, cameras, and mesh or point cloud files.

A rotation ``Q`` (``world_from_model``, (3, 3)) about a centre ``c`` carries
a model-frame point to ``Q (X − c) + c`` (metres, the model's units).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .._atomic import atomic_path, atomic_write
from ..errors import input_error
from ..io.meshes import load_mesh

__all__ = ["rotate_points", "rotate_cameras", "apply_to_mesh_file", "MESH_OUT_SUFFIXES"]

def rotate_points(
    points: np.ndarray, rotation: np.ndarray, center: np.ndarray | None = None
) -> np.ndarray:
    """Rotate points about a centre: ``Q (X − c) + c``.

    Parameters
    ----------
    points : (N, 3) array
        Model-frame points, metres.
    rotation : (3, 3) array
        ``Q``, world_from_model.
    center : (3,) array, optional
        Rotation centre (default: origin).

    Returns
    -------
    (N, 3) float64 array
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    c = np.zeros(3) if center is None else np.asarray(center, dtype=np.float64).reshape(3)
    return (p - c) @ np.asarray(rotation, dtype=np.float64).T + c


def rotate_cameras(
    cam_from_model: np.ndarray,
    centres: np.ndarray | None,
    rotation: np.ndarray,
    center: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Cameras of a rotated model.

    Parameters
    ----------
    cam_from_model : (N, 3, 3) array
        World-to-camera rotations in the model frame.
    centres : (N, 3) array or None
        Camera centres in the model frame.
    rotation : (3, 3) array
        ``Q``, world_from_model.
    center : (3,) array, optional
        Rotation centre.

    Returns
    -------
    cam_from_world : (N, 3, 3) array
        ``R Qᵀ``.
    centres_world : (N, 3) array or None
    """
    R = np.asarray(cam_from_model, dtype=np.float64).reshape(-1, 3, 3) @ np.asarray(rotation).T
    return R, None if centres is None else rotate_points(centres, rotation, center)


MESH_OUT_SUFFIXES = (".obj", ".ply", ".glb", ".off", ".stl")


def apply_to_mesh_file(
    source: str | os.PathLike,
    destination: str | os.PathLike,
    rotation: np.ndarray,
    center: np.ndarray | None = None,
) -> str:
    """Rotate a mesh or point cloud file and write it (atomically).

    Meshes keep their texture or vertex colours (an OBJ is written with an
    MTL and texture image named after it); a PLY without faces is treated
    as a point cloud and written as PLY with its colours.

    Parameters
    ----------
    source, destination : path-like
        Input (any format :func:`~napari_imgreg.io.meshes.load_mesh` reads,
        or a PLY point cloud) and output (``.obj``, ``.ply``, ``.glb``,
        ``.off``, ``.stl``).
    rotation : (3, 3) array
        ``Q``, world_from_model.
    center : (3,) array, optional
        Rotation centre (default: origin).

    Returns
    -------
    str
        What was written, e.g. ``"mesh, 12,345 vertices"``.

    Raises
    ------
    InputError
        Unreadable input or unsupported output format.
    """
    import trimesh  # heavy: only when a file is written

    source, destination = Path(source), Path(destination)
    suffix = destination.suffix.lower()
    if suffix not in MESH_OUT_SUFFIXES:
        raise input_error(destination, f"output must be one of {', '.join(MESH_OUT_SUFFIXES)}")
    if source.resolve() == destination.resolve():
        raise input_error(destination, "refusing to overwrite the input mesh; choose another name")

    if source.suffix.lower() == ".ply" and source.is_file() and _ply_has_no_faces(source):
        cloud = trimesh.load(source, process=False)
        if not isinstance(cloud, trimesh.PointCloud) or len(cloud.vertices) == 0:
            raise input_error(source, "PLY has neither faces nor readable points")
        if suffix != ".ply":
            raise input_error(destination, "a point cloud is written as .ply")
        colors = cloud.colors if len(getattr(cloud, "colors", [])) else None
        rotated = trimesh.PointCloud(rotate_points(cloud.vertices, rotation, center), colors=colors)
        with atomic_path(destination) as tmp:
            rotated.export(tmp, file_type="ply")
        return f"point cloud, {len(rotated.vertices):,} points"

    data = load_mesh(source)
    vertices = rotate_points(data.vertices, rotation, center)
    visual = None
    if data.texture is not None and data.uv is not None:
        from PIL import Image

        material = trimesh.visual.material.SimpleMaterial(
            image=Image.fromarray(data.texture), name=destination.stem
        )
        visual = trimesh.visual.TextureVisuals(uv=data.uv, material=material)
    elif data.vertex_colors is not None:
        visual = trimesh.visual.ColorVisuals(vertex_colors=data.vertex_colors)
    mesh = trimesh.Trimesh(vertices, data.faces, visual=visual, process=False)
    if suffix == ".obj":
        from trimesh.exchange.obj import export_obj

        text, extra_files = export_obj(
            mesh, return_texture=True, mtl_name=f"{destination.stem}.mtl"
        )
        for name, blob in extra_files.items():
            with atomic_write(destination.parent / name, "wb") as fh:
                fh.write(blob)
        with atomic_write(destination, encoding="utf-8") as fh:
            fh.write(text)
    else:
        with atomic_path(destination) as tmp:
            mesh.export(tmp, file_type=suffix[1:])
    return f"mesh, {len(vertices):,} vertices" + (", textured" if data.texture is not None else "")


def _ply_has_no_faces(path: Path) -> bool:
    """True when a PLY header declares no (or zero) faces."""
    with open(path, "rb") as fh:
        head = fh.read(1 << 16)
    header = head.split(b"end_header", 1)[0].decode("ascii", "replace").lower()
    for line in header.splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[0] == "element" and parts[1] == "face":
            return parts[2] == "0"
    return True
