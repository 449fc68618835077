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

from napari_imgreg.errors import input_error

__all__ = ["MeshData", "load_mesh", "MESH_SUFFIXES", "mesh_cache_dir"]

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".off", ".stl")

# Bump when what the loader produces changes: old cache entries are ignored.
_CACHE_VERSION = 1
# Meshes smaller than this are parsed every time (parsing is cheap for them).
_CACHE_MIN_BYTES = 20_000_000


def mesh_cache_dir() -> Path:
    """Where parsed meshes are cached: ``$NAPARI_IMGREG_CACHE/meshes``
    (default ``~/.cache/napari-imgreg/meshes``)."""
    root = os.environ.get("NAPARI_IMGREG_CACHE") or Path.home() / ".cache" / "napari-imgreg"
    return Path(root) / "meshes"


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


def load_mesh(path: str | os.PathLike, cache: bool = True) -> MeshData:
    """Read a surface mesh with its texture or vertex colours.

    Parameters
    ----------
    path : path-like
        OBJ (with MTL and texture image beside it), PLY (vertex colours or
        texture), GLB/GLTF, OFF or STL.
    cache : bool
        Keep a binary copy of large parsed meshes (see :func:`mesh_cache_dir`)
        so the next load of the unchanged files skips parsing: trimesh's OBJ
        parser needs seconds for a million triangles. The cache entry is keyed
        by the paths, sizes and modification times of the mesh and of the
        files beside it that share its name stem or are named in its MTL.

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
    key = _cache_key(path) if cache and path.stat().st_size >= _CACHE_MIN_BYTES else None
    if key is not None:
        cached = _read_cache(key)
        if cached is not None:
            return cached
    data = _parse(path)
    if key is not None:
        _write_cache(key, data)
    return data


def _parse(path: Path) -> MeshData:
    import trimesh

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


# ------------------------------------------------------------------ cache
def _companions(path: Path) -> list[Path]:
    """Files whose change must invalidate a cached parse of ``path``."""
    out = [path]
    if path.suffix.lower() == ".obj":
        try:
            head = path.open("rb").read(65536).decode("utf-8", "replace")
        except OSError:
            head = ""
        for line in head.splitlines():
            if line.startswith("mtllib"):
                mtl = path.parent / line.split(None, 1)[1].strip()
                if mtl.exists():
                    out.append(mtl)
                    for mline in mtl.read_text(errors="replace").splitlines():
                        parts = mline.split()
                        if parts and parts[0].lower().startswith("map_"):
                            tex = path.parent / parts[-1]
                            if tex.exists():
                                out.append(tex)
    return out


def _cache_key(path: Path) -> str:
    import hashlib

    h = hashlib.sha1(f"v{_CACHE_VERSION}".encode())
    for p in _companions(path):
        st = p.stat()
        h.update(f"{p.resolve()}|{st.st_size}|{st.st_mtime_ns}".encode())
    return h.hexdigest()


def _read_cache(key: str) -> MeshData | None:
    file = mesh_cache_dir() / f"{key}.npz"
    if not file.exists():
        return None
    try:
        with np.load(file, allow_pickle=False) as z:
            get = lambda name: z[name] if name in z.files else None  # noqa: E731
            notes = [str(n) for n in z["warnings"]] if "warnings" in z.files else []
            return MeshData(z["vertices"], z["faces"], get("uv"), get("texture"),
                            get("vertex_colors"), notes)
    except Exception:  # a damaged entry is only a cache miss
        log.warning("ignoring unreadable mesh cache entry %s", file)
        return None


def _write_cache(key: str, data: MeshData) -> None:
    from napari_imgreg._atomic import atomic_path

    arrays = {"vertices": data.vertices, "faces": data.faces,
              "warnings": np.array(data.warnings, dtype=str)}
    for name in ("uv", "texture", "vertex_colors"):
        if getattr(data, name) is not None:
            arrays[name] = getattr(data, name)
    try:
        with atomic_path(mesh_cache_dir() / f"{key}.npz") as tmp:
            np.savez(tmp, **arrays)
    except OSError as exc:  # a read-only home must not stop the load
        log.warning("could not cache the parsed mesh: %s", exc)
