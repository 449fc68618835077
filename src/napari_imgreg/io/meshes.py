"""Load textured surface meshes (OBJ+MTL+image, PLY, GLB/GLTF) through trimesh.

The loader returns plain arrays so the rest of the package never depends on
trimesh's visual classes: vertices, triangles, per-vertex UVs and the texture
image, or per-vertex colours. Problems with the file are one clear
:class:`~napari_imgreg.errors.InputError`; a missing texture is a warning and
the mesh falls back to vertex colours or grey.
"""

from __future__ import annotations

import logging
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import input_error

__all__ = ["MeshData", "load_mesh", "MESH_SUFFIXES"]

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".off", ".stl")


@dataclass
class MeshData:
    """A triangle mesh with its colour information, in the file's frame.

    Attributes
    ----------
    vertices : (V, 3) float64 array
        Vertex positions, metres.
    faces : (F, 3) int32 array
        Triangle vertex indices.
    uv : (V, 2) float32 array or None
        Texture coordinates, OpenGL convention (v = 0 at the image bottom).
    texture : (H, W, 3) uint8 array or None
        Texture image, RGB, row 0 at the top.
    vertex_colors : (V, 3) uint8 array or None
        Per-vertex RGB colours.
    warnings : list of str
        What the loader assumed (missing texture, ...).
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None = None
    texture: np.ndarray | None = None
    vertex_colors: np.ndarray | None = None
    warnings: list[str] = field(default_factory=list)


def load_mesh(path: str | os.PathLike) -> MeshData:
    """Read a surface mesh with its texture or vertex colours.

    Parameters
    ----------
    path : path-like
        OBJ (with MTL and texture image beside it), PLY (vertex colours or
        texture), GLB/GLTF, OFF or STL.

    Returns
    -------
    MeshData

    Raises
    ------
    InputError
        The file is missing, not a mesh format, unreadable, or holds no
        triangles.
    """
    import trimesh

    path = Path(path)
    if not path.exists():
        raise input_error(path, "no such file")
    if path.is_dir():
        raise input_error(path, "is a folder, not a mesh file")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise input_error(
            path, f"not a mesh format (expected one of {', '.join(MESH_SUFFIXES)})"
        )
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            loaded = trimesh.load(path, process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise input_error(path, f"cannot read mesh ({type(exc).__name__}: {exc})") from None

    try:
        meshes = _triangle_meshes(loaded)
    except Exception as exc:  # e.g. face indices past the vertex buffer
        raise input_error(path, f"cannot read mesh ({type(exc).__name__}: {exc})") from None
    if not meshes:
        raise input_error(path, "contains no triangles (corrupt or empty mesh)")
    notes: list[str] = []
    if len(meshes) > 1:
        mesh = _merge(meshes, notes)
    else:
        mesh = meshes[0]

    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int32)
    if not np.isfinite(vertices).all():
        raise input_error(path, "has vertices with NaN or infinite coordinates")
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise input_error(path, "has faces that index missing vertices")

    uv, texture, colors = _colour_of(mesh, path, notes)
    for note in notes:
        log.warning("%s: %s", path.name, note)
    return MeshData(vertices, faces, uv, texture, colors, notes)


def _triangle_meshes(loaded) -> list:
    import trimesh

    if isinstance(loaded, trimesh.Trimesh):
        return [loaded] if len(loaded.faces) else []
    if isinstance(loaded, trimesh.Scene):
        # Apply each node's transform so GLB scenes land where they are drawn.
        out = []
        for node in loaded.graph.nodes_geometry:
            transform, name = loaded.graph[node]
            geom = loaded.geometry[name]
            if isinstance(geom, trimesh.Trimesh) and len(geom.faces):
                g = geom.copy()
                g.apply_transform(transform)
                out.append(g)
        return out
    return []


def _merge(meshes: list, notes: list[str]):
    """Concatenate several meshes; trimesh packs their textures into one atlas."""
    import trimesh

    try:
        return trimesh.util.concatenate(meshes)
    except Exception:  # texture packing can fail on exotic materials
        notes.append(f"{len(meshes)} parts merged without their textures")
        for m in meshes:
            m.visual = trimesh.visual.ColorVisuals(m)
        return trimesh.util.concatenate(meshes)


def _colour_of(mesh, path: Path, notes: list[str]):
    """(uv, texture, vertex_colors) of a trimesh mesh; see :class:`MeshData`."""
    visual = mesh.visual
    n = len(mesh.vertices)
    if getattr(visual, "kind", None) == "texture":
        uv = getattr(visual, "uv", None)
        image = _texture_image(getattr(visual, "material", None))
        if uv is not None and len(uv) == n and image is not None:
            tex = np.asarray(image.convert("RGB"), dtype=np.uint8)
            return np.asarray(uv, dtype=np.float32), np.ascontiguousarray(tex), None
        if uv is None or len(uv) != n:
            notes.append("texture coordinates missing or incomplete; texture ignored")
        else:
            notes.append("texture image missing or unreadable; using vertex colours or grey")
        colors = _material_colour(getattr(visual, "material", None), n)
        return None, None, colors
    if getattr(visual, "kind", None) in ("vertex", "face"):
        try:
            vc = np.asarray(visual.vertex_colors)[:, :3].astype(np.uint8)
            if len(vc) == n:
                return None, None, vc
        except Exception:
            pass
    notes.append("mesh has no texture or colours; rendered grey with shading")
    return None, None, None


def _texture_image(material):
    if material is None:
        return None
    for attr in ("image", "baseColorTexture"):
        img = getattr(material, attr, None)
        if img is not None and getattr(img, "size", (0, 0))[0] > 2:
            return img
    return None


def _material_colour(material, n: int) -> np.ndarray | None:
    """A flat per-vertex colour from the material's diffuse colour, if any."""
    for attr in ("diffuse", "baseColorFactor", "main_color"):
        c = getattr(material, attr, None) if material is not None else None
        if c is not None:
            c = np.asarray(c).ravel()
            if c.size >= 3:
                c = c[:3]
                if c.dtype.kind == "f" and c.max() <= 1.0:
                    c = c * 255
                return np.tile(np.clip(c, 0, 255).astype(np.uint8), (n, 1))
    return None
