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

from .._platform import cache_root
from ..errors import input_error

__all__ = [
    "MeshData", "load_mesh", "MESH_SUFFIXES", "DSM_SUFFIXES", "model_formats_text",
    "check_model_suffix", "mesh_cache_dir", "mesh_cache_limit_bytes",
    "check_mesh_arrays", "evict_mesh_cache", "MESH_CACHE_LIMIT_BYTES",
]

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".off", ".stl")
#: A DSM given as the model (GeoTIFF or ESRI ASCII grid), which the workbench's
#: Model field and ``project`` turn into a surface (:meth:`Scene.from_dem`).
DSM_SUFFIXES = (".tif", ".tiff", ".asc")


def model_formats_text(dsm: bool = False) -> str:
    """The model formats a reader takes, for a message: meshes and point
    clouds, and with ``dsm`` a DSM too."""
    from .pointclouds import POINT_CLOUD_SUFFIXES

    clouds = [s for s in POINT_CLOUD_SUFFIXES if s not in MESH_SUFFIXES]
    text = f"a mesh: {', '.join(MESH_SUFFIXES)}; a point cloud: {', '.join(clouds)}"
    return text + (f"; a DSM: {', '.join(DSM_SUFFIXES)}" if dsm else "")


def check_model_suffix(path: str | os.PathLike, dsm: bool = False) -> None:
    """Refuse a file whose suffix is no model format, naming those taken.

    ``dsm``: a DSM (:data:`DSM_SUFFIXES`) is taken too, as by the workbench's
    Model field. A missing file or a folder is left to the reader.

    Raises
    ------
    InputError
        ``"<file>: not a model format (a mesh: ...; a point cloud: ...[; a DSM: ...])"``.
    """
    from .pointclouds import POINT_CLOUD_SUFFIXES

    path = Path(path)
    if not path.is_file():
        return
    accepted = MESH_SUFFIXES + POINT_CLOUD_SUFFIXES + (DSM_SUFFIXES if dsm else ())
    if path.suffix.lower() not in accepted:
        raise input_error(path, f"not a model format ({model_formats_text(dsm)})")

# Bump when what the loader produces changes: old cache entries are ignored.
# 2: content keys, entries checked on read, eviction by size.
_CACHE_VERSION = 2
# Meshes smaller than this are parsed every time (parsing is cheap for them).
_CACHE_MIN_BYTES = 20_000_000
#: Default total size of the mesh cache (2 GiB, about ten 5-million-triangle
#: textured meshes); ``NAPARI_IMGREG_MESH_CACHE_MB`` overrides it (0: no cache).
#: Past it, the least recently used entries are deleted.
MESH_CACHE_LIMIT_BYTES = 2 * 1024**3


def mesh_cache_limit_bytes() -> int:
    """The mesh cache's size limit: ``$NAPARI_IMGREG_MESH_CACHE_MB`` (mebibytes)
    or :data:`MESH_CACHE_LIMIT_BYTES`; an unreadable value is the default."""
    value = os.environ.get("NAPARI_IMGREG_MESH_CACHE_MB")
    if value:
        try:
            mb = float(value)
        except ValueError:
            log.warning("NAPARI_IMGREG_MESH_CACHE_MB=%r is not a number: using %d MiB",
                        value, MESH_CACHE_LIMIT_BYTES // 2**20)
        else:
            if mb == mb and mb >= 0:  # not NaN
                return int(min(mb, 2.0**40) * 2**20)
    return MESH_CACHE_LIMIT_BYTES


def mesh_cache_dir() -> Path:
    """Where parsed meshes are cached: ``meshes`` in
    :func:`~napari_imgreg._platform.cache_root` (``$NAPARI_IMGREG_CACHE``, or
    the system's user cache folder)."""
    return cache_root() / "meshes"


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
        by the content (a BLAKE2 hash) of the mesh and of its MTL and texture
        files, so touching a file costs nothing and any change is a miss. An
        entry is checked when read (array shapes, face indices in range,
        finite coordinates, its stored key) and rebuilt when it fails; the
        cache keeps to :func:`mesh_cache_limit_bytes` by deleting the least
        recently used entries.

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
        raise input_error(path, f"not a model format ({model_formats_text()})")
    use_cache = cache and path.stat().st_size >= _CACHE_MIN_BYTES and mesh_cache_limit_bytes() > 0
    key = _cache_key(path) if use_cache else None
    if key is not None:
        cached = _read_cache(key)
        if cached is not None:
            return cached
    data = _parse(path)
    if key is not None:
        _write_cache(key, data)
    return data


def check_mesh_arrays(vertices, faces, uv=None, texture=None, vertex_colors=None) -> str | None:
    """What is wrong with a mesh's arrays, or None when they are consistent.

    Checks the shapes and types of :class:`MeshData`, that every face
    indexes an existing vertex and that coordinates are finite.

    Returns
    -------
    str or None
        The first problem found, in words.
    """
    v, f = np.asarray(vertices), np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or v.dtype.kind != "f":
        return f"vertices have shape {v.shape} and type {v.dtype} (expected (V, 3) float)"
    if f.ndim != 2 or f.shape[1] != 3 or f.dtype.kind not in "iu":
        return f"faces have shape {f.shape} and type {f.dtype} (expected (F, 3) integers)"
    if len(f) == 0:
        return "no faces"
    if f.min() < 0 or f.max() >= len(v):
        return f"face indices span {f.min()}..{f.max()} but there are {len(v)} vertices"
    if not np.isfinite(v).all():
        return "vertices with NaN or infinite coordinates"
    if uv is not None:
        uv = np.asarray(uv)
        if uv.shape != (len(v), 2) or uv.dtype.kind != "f" or not np.isfinite(uv).all():
            return f"texture coordinates of shape {uv.shape} (expected ({len(v)}, 2), finite)"
    if texture is not None:
        t = np.asarray(texture)
        if t.ndim != 3 or t.shape[2] != 3 or t.dtype != np.uint8 or 0 in t.shape:
            return f"texture of shape {t.shape} and type {t.dtype} (expected (H, W, 3) uint8)"
    if vertex_colors is not None:
        c = np.asarray(vertex_colors)
        if c.shape != (len(v), 3) or c.dtype != np.uint8:
            return f"vertex colours of shape {c.shape} (expected ({len(v)}, 3) uint8)"
    return None


def _unreadable_mesh(path: Path, exc: Exception):
    """The one-line error of a mesh file the reader fails on: what it likely
    is, then the reader's own words (for a bug report)."""
    kind = path.suffix.lstrip(".").upper() or "mesh"
    return input_error(path, f"cannot read mesh: damaged, truncated or not a {kind} file "
                             f"({type(exc).__name__}: {exc})")


def _parse(path: Path) -> MeshData:
    import trimesh

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            loaded = trimesh.load(path, process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise _unreadable_mesh(path, exc) from None

    try:
        meshes = _triangle_meshes(loaded)
    except Exception as exc:  # e.g. face indices past the vertex buffer
        raise _unreadable_mesh(path, exc) from None
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
            # Closed at once: on Windows an open file cannot be replaced (a re-export).
            with path.open("rb") as fh:
                head = fh.read(65536).decode("utf-8", "replace")
        except OSError:
            head = ""
        for line in head.splitlines():
            if line.startswith("mtllib"):
                mtl = path.parent / line.split(None, 1)[1].strip()
                if mtl.exists():
                    out.append(mtl)
                    for mline in mtl.read_text(encoding="utf-8", errors="replace").splitlines():
                        parts = mline.split()
                        if parts and parts[0].lower().startswith("map_"):
                            tex = path.parent / parts[-1]
                            if tex.exists():
                                out.append(tex)
    return out


def _cache_key(path: Path) -> str:
    """BLAKE2 hash of the loader version and the content of the mesh and its
    companions (with their names relative to the mesh)."""
    import hashlib

    h = hashlib.blake2b(f"v{_CACHE_VERSION}".encode(), digest_size=20)
    for p in _companions(path):
        try:
            name = p.relative_to(path.parent).as_posix()
        except ValueError:
            name = p.name
        h.update(f"|{name}|{p.stat().st_size}|".encode())
        with open(p, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    return h.hexdigest()


def _drop(file: Path, why: str) -> None:
    log.warning("mesh cache entry %s %s: rebuilding it", file.name, why)
    try:
        file.unlink()
    except OSError:
        pass


def _read_cache(key: str) -> MeshData | None:
    """The cached parse for ``key``, or None (missing, damaged or wrong: deleted)."""
    file = mesh_cache_dir() / f"{key}.npz"
    if not file.exists():
        return None
    try:
        with np.load(file, allow_pickle=False) as z:
            get = lambda name: z[name] if name in z.files else None  # noqa: E731
            stored_key = str(z["key"]) if "key" in z.files else None
            notes = [str(n) for n in z["warnings"]] if "warnings" in z.files else []
            data = MeshData(z["vertices"], z["faces"], get("uv"), get("texture"),
                            get("vertex_colors"), notes)
    except Exception:  # noqa: BLE001 - a damaged entry is only a cache miss
        _drop(file, "is unreadable")
        return None
    if stored_key != key:
        _drop(file, "does not hold the key it is named by")
        return None
    problem = check_mesh_arrays(data.vertices, data.faces, data.uv, data.texture,
                                data.vertex_colors)
    if problem is not None:
        _drop(file, f"is inconsistent ({problem})")
        return None
    data.vertices = data.vertices.astype(np.float64, copy=False)
    data.faces = data.faces.astype(np.int32, copy=False)
    try:  # the access time of a hit: eviction removes the least recently used
        os.utime(file)
    except OSError:
        pass
    return data


def _write_cache(key: str, data: MeshData) -> None:
    from .._atomic import atomic_path

    arrays = {"vertices": data.vertices, "faces": data.faces, "key": np.array(key),
              "warnings": np.array(data.warnings, dtype=str)}
    for name in ("uv", "texture", "vertex_colors"):
        if getattr(data, name) is not None:
            arrays[name] = getattr(data, name)
    limit = mesh_cache_limit_bytes()
    if sum(a.nbytes for a in arrays.values()) > limit:
        log.info("parsed mesh larger than the mesh cache limit (%d MiB): not cached", limit >> 20)
        return
    try:
        with atomic_path(mesh_cache_dir() / f"{key}.npz") as tmp:
            np.savez(tmp, **arrays)
    except OSError as exc:  # a read-only home must not stop the load
        log.warning("could not cache the parsed mesh: %s", exc)
        return
    evict_mesh_cache(limit, keep=key)


def evict_mesh_cache(limit: int | None = None, keep: str | None = None) -> list[Path]:
    """Delete the least recently used cache entries until the cache's total
    size is at most ``limit`` bytes (default :func:`mesh_cache_limit_bytes`).

    Parameters
    ----------
    limit : int, optional
    keep : str, optional
        Key of an entry never deleted (the one just written).

    Returns
    -------
    list of Path
        The entries deleted.
    """
    limit = mesh_cache_limit_bytes() if limit is None else limit
    entries = []
    for file in mesh_cache_dir().glob("*.npz"):
        try:
            st = file.stat()
        except OSError:  # removed by another process meanwhile
            continue
        entries.append((st.st_mtime_ns, st.st_size, file))
    total = sum(size for _, size, _ in entries)
    removed = []
    for _, size, file in sorted(entries, key=lambda e: e[0]):
        if total <= limit:
            break
        if keep is not None and file.stem == keep:
            continue
        try:
            file.unlink()
        except OSError:
            continue
        total -= size
        removed.append(file)
    return removed
