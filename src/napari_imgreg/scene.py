"""The Scene: a textured surface mesh, its ray-casting engine, georeference and DEM.

The ray-casting engine (Embree, through ``embreex``) is built once per Scene and
reused for every render, every feature lift and every projection of an
interpretation. Coordinates are the model ("local") frame of the contract:
metres, +X east, +Y north, +Z up.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .errors import InputError, input_error
from .geo import dem_height_local
from .io.rasters import read_geotiff
from .io.records import parse_sensor_record, read_json
from .solar import sun_from_record

if TYPE_CHECKING:
    from .geo import DEM, Georef

__all__ = ["Scene", "RayHits", "ray_threads", "has_appearance", "has_colours", "size_text"]

log = logging.getLogger(__name__)

# Embree releases the GIL while it traces, so a few threads use every core.
_MIN_RAYS_PER_THREAD = 50_000


def ray_threads() -> int:
    """Number of threads used for large ray casts (``NAPARI_IMGREG_THREADS`` or CPUs)."""
    env = os.environ.get("NAPARI_IMGREG_THREADS")
    if env:
        return max(1, int(env))
    return max(1, os.cpu_count() or 1)


def has_colours(scene) -> bool:
    """Whether a scene has photographed colours: a texture or vertex (point)
    colours, not only grey shading or a lidar scan's intensity."""
    return bool(scene.has_texture or scene.vertex_colors is not None)


def has_appearance(scene) -> bool:
    """Whether a scene renders with its own appearance (a texture, vertex
    colours, or a lidar scan's intensity) rather than grey shading only."""
    return has_colours(scene) or getattr(scene, "intensity", None) is not None


def size_text(scene) -> str:
    """How big a scene is, for messages: "126,990 triangles" or "3,755,840 points"."""
    if getattr(scene, "is_cloud", False):
        return f"{scene.n_points:,} points"
    return f"{scene.n_faces:,} triangles"


@dataclass
class RayHits:
    """First hits of rays on the surface.

    Attributes
    ----------
    distance : (N,) float32 array
        Distance along each (unit) ray to the hit, metres; ``inf`` for a miss.
    face_id : (N,) int32 array
        Index of the hit triangle, -1 for a miss.
    bary_u, bary_v : (N,) float32 arrays
        Embree's barycentric coordinates: the hit is
        ``(1 - u - v) * V0 + u * V1 + v * V2`` of the triangle.
    """

    distance: np.ndarray
    face_id: np.ndarray
    bary_u: np.ndarray
    bary_v: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        """(N,) bool: the ray met the surface."""
        return self.face_id >= 0


class Scene:
    """A textured surface model ready for rendering and ray casting.

    Parameters
    ----------
    vertices : (V, 3) array
        Vertex positions in the local frame, metres.
    faces : (F, 3) int array
        Triangles.
    uv : (V, 2) array, optional
        Texture coordinates (v = 0 at the texture's bottom row).
    texture : (H, W, 3) uint8 array, optional
        Texture image, row 0 at the top.
    vertex_colors : (V, 3) uint8 array, optional
        Used when there is no texture.
    georef : Georef, optional
        Maps the local frame to a projected CRS.
    dem : DEM, optional
        Terrain heights in the georeference CRS, for camera altitudes.
    name : str
        A short name for messages and layer names.
    """

    def __init__(
        self,
        vertices: np.ndarray,
        faces: np.ndarray,
        uv: np.ndarray | None = None,
        texture: np.ndarray | None = None,
        vertex_colors: np.ndarray | None = None,
        georef: Georef | None = None,
        dem: DEM | None = None,
        name: str = "scene",
    ) -> None:
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int32)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise ValueError("vertices must have shape (V, 3)")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise ValueError("faces must have shape (F, 3)")
        self.uv = None if uv is None else np.ascontiguousarray(uv, dtype=np.float32)
        self.texture = None if texture is None else np.ascontiguousarray(texture, dtype=np.uint8)
        if (self.uv is None) != (self.texture is None):
            self.uv, self.texture = None, None
        self.vertex_colors = (
            None if vertex_colors is None else np.ascontiguousarray(vertex_colors, dtype=np.uint8)
        )
        self.georef = georef
        self.dem = dem
        self.name = name
        #: Unit vector toward the sun the texture was photographed under (local
        #: frame), when known (``survey.json``): relighting divides its shading out.
        self.survey_sun: np.ndarray | None = None
        self.warnings: list[str] = []
        self._engine = None
        self._engine_lock = threading.Lock()
        self._face_cache: dict[str, np.ndarray] = {}
        self.timings_s: dict[str, float] = {}

    # ------------------------------------------------------------ construct
    @classmethod
    def load(
        cls,
        mesh_path: str | os.PathLike,
        georef: Georef | str | os.PathLike | None = None,
        dem: DEM | str | os.PathLike | None = None,
        cache: bool = True,
    ) -> Scene:
        """Load a mesh file (and optionally a georeference and a DEM).

        Parameters
        ----------
        mesh_path : path-like
            OBJ+MTL+image, PLY, GLB/GLTF (see :func:`napari_imgreg.io.meshes.load_mesh`);
            or a point cloud (LAS/LAZ, E57, PTS/XYZ, a PLY of vertices only:
            :func:`napari_imgreg.io.pointclouds.is_point_cloud_file`), for
            which a :class:`~napari_imgreg.cloud.CloudScene` is returned.
        georef, dem : object or path-like, optional
            A :class:`~napari_imgreg.geo.Georef` / :class:`~napari_imgreg.geo.DEM`
            or the path of ``georef.json`` / a GeoTIFF or ``.asc`` DEM. When
            ``georef`` is None and a ``georef.json`` lies beside the mesh, it
            is used.
        cache : bool
            Reuse a binary copy of a large parsed mesh (see
            :func:`napari_imgreg.io.meshes.load_mesh`).

        Raises
        ------
        InputError
            A file is missing or unreadable.
        """
        from .geo import DEM, Georef
        from .io.meshes import load_mesh
        from .io.pointclouds import is_point_cloud_file

        if is_point_cloud_file(mesh_path):
            # A lidar scan (LAS/LAZ, E57, PTS/XYZ, a PLY without faces): the
            # point-cloud scene, behind the same interface (issue 16).
            from .cloud import CloudScene

            return CloudScene.load(mesh_path, georef=georef, dem=dem, cache=cache)
        t0 = time.perf_counter()
        data = load_mesh(mesh_path, cache=cache)
        mesh_path = Path(mesh_path)
        if georef is None and (mesh_path.parent / "georef.json").exists():
            georef = mesh_path.parent / "georef.json"
        if georef is not None and not isinstance(georef, Georef):
            georef = Georef.load(georef)
        if dem is not None and not isinstance(dem, DEM):
            dem = DEM.load(dem)
        scene = cls(
            data.vertices,
            data.faces,
            data.uv,
            data.texture,
            data.vertex_colors,
            georef=georef,
            dem=dem,
            name=mesh_path.stem,
        )
        scene.warnings = list(data.warnings)
        survey = mesh_path.parent / "survey.json"
        if survey.exists() and has_colours(scene):
            scene.survey_sun = read_survey_sun(survey, georef, scene.bounds.mean(axis=0))
        scene.timings_s["load"] = time.perf_counter() - t0
        return scene

    @classmethod
    def from_dem(
        cls,
        dem: DEM | str | os.PathLike,
        georef: Georef | str | os.PathLike | None = None,
        orthophoto: str | os.PathLike | None = None,
        stride: int = 1,
    ) -> Scene:
        """A surface mesh from a DEM/DSM, optionally textured by an orthophoto.

        Two triangles join each 2 × 2 block of valid heights; nodata cells
        leave holes.

        Parameters
        ----------
        dem : DEM or path-like
            The height raster (GeoTIFF or ``.asc``).
        georef : Georef or path-like, optional
            Local frame (a ``georef.json`` path is read). When not given, the
            ``georef.json`` beside a DEM file is used, as for a mesh (the frame
            of the results and records made beside it); without one, a frame
            is made from the DEM's CRS with the origin at the DEM's centre (a
            DEM without a CRS is used as the local frame itself).
        orthophoto : path-like, optional
            A north-up RGB GeoTIFF in the same CRS; each vertex gets the
            orthophoto's texture coordinate at its (E, N).
        stride : int
            Take every ``stride``-th DEM cell (coarser mesh for huge DSMs).
        """
        from .geo import DEM, Georef

        if georef is None and not isinstance(dem, DEM):
            beside = Path(dem).parent / "georef.json"
            georef = beside if beside.exists() else None
        if georef is not None and not isinstance(georef, Georef):
            georef = Georef.load(georef)
        if not isinstance(dem, DEM):
            dem = DEM.load(dem)
        h = dem.heights[::stride, ::stride]
        E, N = dem.grid()
        E, N = E[::stride, ::stride], N[::stride, ::stride]
        if georef is None and dem.crs is not None:
            # Keep coordinates small (Embree works in float32): origin at the centre.
            cx, cy = float(np.round(E.mean())), float(np.round(N.mean()))
            georef = Georef(crs=dem.crs, origin=np.array([cx, cy, 0.0]))
        # A DEM without a CRS is used as it is: its coordinates are the local frame.
        origin = georef.origin if georef is not None else np.zeros(3)
        rows, cols = h.shape
        vertices = np.stack([E - origin[0], N - origin[1], h - origin[2]], axis=-1).reshape(-1, 3)
        idx = np.arange(rows * cols).reshape(rows, cols)
        a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
        c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
        # Rows run south, so (a, c, b) is counter-clockwise seen from above.
        faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
        valid = np.isfinite(vertices[:, 2])
        faces = faces[valid[faces].all(axis=1)]
        vertices = np.where(np.isfinite(vertices), vertices, 0.0)
        uv = texture = None
        if orthophoto is not None:
            uv, texture = _orthophoto_uv(orthophoto, vertices + origin)
        scene = cls(vertices, faces, uv, texture, georef=georef, dem=dem, name=dem.source)
        return scene

    # ------------------------------------------------------------- geometry
    @property
    def n_faces(self) -> int:
        return len(self.faces)

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) array: min and max corner of the mesh, metres."""
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

    @property
    def has_texture(self) -> bool:
        return self.texture is not None

    @property
    def uv_wraps(self) -> bool:
        """True when texture coordinates leave [0, 1] (a tiled texture)."""
        if "uv_wraps" not in self._face_cache:
            wraps = self.uv is not None and bool((self.uv < 0).any() or (self.uv > 1).any())
            self._face_cache["uv_wraps"] = np.array(wraps)
        return bool(self._face_cache["uv_wraps"])

    def face_array(self, name: str) -> np.ndarray:
        """Per-face arrays cached for rendering.

        ``"normals"`` (F, 3) float32 unit normals; ``"uv"`` (F, 3, 2) float32
        corner UVs; ``"colors"`` (F, 3, 3) float32 corner colours;
        ``"vertex_normals"`` (F, 3, 3) float32 corner normals (smooth shading).
        """
        if name not in self._face_cache:
            self._face_cache[name] = self._compute_face_array(name)
        return self._face_cache[name]

    def _compute_face_array(self, name: str) -> np.ndarray:
        tri = self.vertices[self.faces]
        if name == "normals":
            n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            length = np.linalg.norm(n, axis=1, keepdims=True)
            return (n / np.where(length > 0, length, 1.0)).astype(np.float32)
        if name == "uv":
            if self.uv is None:
                raise ValueError("scene has no texture coordinates")
            return np.ascontiguousarray(self.uv[self.faces], dtype=np.float32)
        if name == "colors":
            if self.vertex_colors is None:
                raise ValueError("scene has no vertex colours")
            return self.vertex_colors[self.faces].astype(np.float32)
        if name == "vertex_normals":
            fn = self.face_array("normals").astype(np.float64)
            area = np.linalg.norm(
                np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1
            )
            vn = np.zeros_like(self.vertices)
            for k in range(3):
                np.add.at(vn, self.faces[:, k], fn * area[:, None])
            vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)
            return vn[self.faces].astype(np.float32)
        raise KeyError(name)

    # --------------------------------------------------------- ray casting
    @property
    def engine(self):
        """The Embree scene, built on first use (thread-safe)."""
        if self._engine is None:
            self.build_engine()
        return self._engine

    def build_engine(self) -> float:
        """Build the ray-casting BVH now; returns the seconds it took."""
        with self._engine_lock:
            if self._engine is not None:
                return 0.0
            t0 = time.perf_counter()
            try:
                from embreex import rtcore_scene
                from embreex.mesh_construction import TriangleMesh
            except ImportError as exc:  # pragma: no cover - a core dependency
                raise ImportError(
                    "napari-imgreg needs embreex for ray casting: pip install embreex"
                ) from exc
            engine = rtcore_scene.EmbreeScene()
            TriangleMesh(
                scene=engine,
                vertices=self.vertices.astype(np.float32),
                indices=self.faces,
            )
            # Embree builds the BVH lazily at the first query: force it here so
            # the cost is paid (and timed) once, not inside the first render.
            engine.run(
                np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32), output=1
            )
            self._engine = engine
            elapsed = time.perf_counter() - t0
            self.timings_s["build"] = elapsed
            return elapsed

    def cast_rays(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        max_distance: float | np.ndarray | None = None,
    ) -> RayHits:
        """First hits of rays on the surface.

        Parameters
        ----------
        origins : (N, 3) or (3,) array
            Ray origins, metres (one origin broadcasts to all rays).
        directions : (N, 3) array
            Unit ray directions.
        max_distance : float or (N,) array, optional
            Ignore hits farther than this.

        Returns
        -------
        RayHits
        """
        directions = np.ascontiguousarray(directions, dtype=np.float32).reshape(-1, 3)
        n = len(directions)
        origins = np.asarray(origins, dtype=np.float32)
        if origins.ndim == 1:
            origins = np.broadcast_to(origins, (n, 3))
        origins = np.ascontiguousarray(origins, dtype=np.float32).reshape(-1, 3)
        if max_distance is None:
            dists = None
        else:
            dists = np.ascontiguousarray(
                np.broadcast_to(np.asarray(max_distance, dtype=np.float32), (n,))
            )

        engine = self.engine
        out_t = np.empty(n, np.float32)
        out_f = np.empty(n, np.int32)
        out_u = np.empty(n, np.float32)
        out_v = np.empty(n, np.float32)

        def run(lo: int, hi: int) -> None:
            kw = {} if dists is None else {"dists": dists[lo:hi].copy()}
            res = engine.run(origins[lo:hi], directions[lo:hi], output=1, **kw)
            out_t[lo:hi] = res["tfar"]
            out_f[lo:hi] = res["primID"]
            out_u[lo:hi] = res["u"]
            out_v[lo:hi] = res["v"]

        n_threads = min(ray_threads(), max(1, n // _MIN_RAYS_PER_THREAD))
        if n_threads <= 1:
            run(0, n)
        else:
            bounds = np.linspace(0, n, n_threads + 1).astype(int)
            with ThreadPoolExecutor(n_threads) as pool:
                list(pool.map(run, bounds[:-1], bounds[1:]))
        miss = out_f < 0
        out_f[miss] = -1
        out_t[miss] = np.inf
        return RayHits(out_t, out_f, out_u, out_v)

    def surface_points(self, hits: RayHits) -> np.ndarray:
        """Exact hit points from barycentrics, (N, 3) float64; NaN for misses."""
        out = np.full((len(hits.face_id), 3), np.nan)
        ok = hits.hit
        tri = self.vertices[self.faces[hits.face_id[ok]]]
        u = hits.bary_u[ok, None].astype(np.float64)
        v = hits.bary_v[ok, None].astype(np.float64)
        out[ok] = (1 - u - v) * tri[:, 0] + u * tri[:, 1] + v * tri[:, 2]
        return out

    # --------------------------------------------------------------- terrain
    def terrain_height(self, x: float, y: float) -> float:
        """Terrain height (local frame) at local (x, y): the DEM when there is
        one, else the highest mesh surface below a vertical ray.

        Raises
        ------
        InputError
            Outside the DEM, or no surface under (x, y) without a DEM.
        """
        if self.dem is not None:
            return dem_height_local(self.dem, self.georef, x, y)
        top = self.bounds[1, 2] + 10.0
        hits = self.cast_rays(np.array([[x, y, top]]), np.array([[0.0, 0.0, -1.0]]))
        if not hits.hit[0]:
            raise InputError(f"{self.name}: no surface below ({x:.1f}, {y:.1f}) and no DEM")
        return float(top - hits.distance[0])

    def __repr__(self) -> str:
        colour = "texture" if self.has_texture else (
            "vertex colours" if self.vertex_colors is not None else "no colour")
        return f"Scene({self.name!r}, {self.n_faces} triangles, {colour})"


def read_survey_sun(path: str | os.PathLike, georef, where: np.ndarray) -> np.ndarray:
    """The survey-day sun of a model's texture from ``survey.json``, local frame.

    ``survey.json`` (beside the mesh) gives either ``{"sun": {"azimuth_deg",
    "elevation_deg"}}`` (azimuth clockwise from true north) or ``{"time":
    "2024-06-15T10:30:00+01:00"}`` — the capture time of the photos the
    texture was made from (with a georeference, the sun is computed there).
    Read as a sensor record's ``sun`` and ``time`` are
    (:func:`napari_imgreg.solar.sun_from_record`).

    Parameters
    ----------
    path : path-like
        ``survey.json``.
    georef : Georef or None
        The model's georeference (needed for a ``time``).
    where : (3,) array
        Where the sun is seen from (the middle of the model), local metres.

    Returns
    -------
    (3,) float64 array
        Unit vector toward the survey sun, local frame.

    Raises
    ------
    InputError
        Unreadable file or wrong fields; the message names the file.
    """
    data = read_json(path)
    if not isinstance(data, dict) or ("sun" not in data and "time" not in data):
        raise input_error(path, "survey.json needs a 'sun' or a 'time' field")
    record = parse_sensor_record({k: data[k] for k in ("sun", "time") if k in data}, path)
    if record.sun is None and georef is None:
        raise input_error(path, "a survey 'time' needs georef.json beside the mesh")
    return sun_from_record(record, georef, where)


def _orthophoto_uv(path: str | os.PathLike, enh: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Texture coordinates of points (E, N, H) on a north-up RGB GeoTIFF."""
    raster = read_geotiff(path)
    image = raster.data
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] < 3:
        raise input_error(path, "orthophoto must be an RGB image")
    image = image[..., :3]
    if image.dtype != np.uint8:
        lo, hi = np.nanpercentile(image, [0.5, 99.5])
        image = np.clip((image - lo) / max(hi - lo, 1e-9) * 255, 0, 255).astype(np.uint8)
    rows, cols = image.shape[:2]
    col = (enh[:, 0] - raster.x0) / raster.dx
    row = (raster.y0 - enh[:, 1]) / raster.dy
    uv = np.stack([(col + 0.5) / cols, 1.0 - (row + 0.5) / rows], axis=1).astype(np.float32)
    return uv, np.ascontiguousarray(image)
