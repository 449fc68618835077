"""The point-cloud scene: a lidar scan behind the interface of :class:`Scene`.

A :class:`CloudScene` holds the points (model frame: metres, +X east, +Y
north, +Z up), their laser intensity and/or colour, a georeference and a DEM,
and what the renderer and the ray queries need, computed once per scene by
:meth:`CloudScene.build_engine` and cached on the object (and beside the
source file by :meth:`CloudScene.load`):

* **normals** by local PCA: the eigenvector of the smallest eigenvalue of the
  covariance of each point's ``k_normals`` nearest neighbours (SciPy
  ``cKDTree``), turned toward the nearest scanner position when one is
  given;
* **spacing**: the distance to the ``k_spacing``-th neighbour, from which each
  point's surfel (disc) radius follows.

Rendering is :func:`napari_imgreg.render_points.splat_cloud`; a ray meets the
surface where it first crosses a surfel's disc (:meth:`CloudScene.cast_rays`).
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import threading
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numba import njit

from .camera import Intrinsics, Pose
from .errors import InputError, input_error
from .geo import dem_height_local
from .render_points import SplatParams, _run_blocks, splat_depth, warm_up
from .validate import check_number

if TYPE_CHECKING:
    from .geo import DEM, Georef

__all__ = ["RENDER_DETAILS", "CloudLevelOfDetail", "CloudParams", "CloudRayHits", "CloudScene",
           "LodParams"]

log = logging.getLogger(__name__)

#: Bumped when a cache's contents change (2: normals stored as float32, not float16).
_CACHE_VERSION = 2


@dataclass(frozen=True)
class LodParams:
    """The level of detail of a large cloud, for interactive renders.

    Built once per scene (:meth:`CloudScene.build_engine`): the points are
    sorted into cubic *blocks* and, within each block, coarsest level first,
    so that each level is a prefix of the block and a subset of the next
    finer one. Level *L* keeps one point (the first in the file's order) per
    cubic voxel of ``2**L`` times the cloud's median grid step; its surfels
    grow by the square root of the block's thinning, so they still cover the
    surface. A render (``detail="auto"``) culls the blocks outside the view
    and draws each of the others at the coarsest level whose surfels, at the
    block's nearest point, are at most ``max_radius_px`` pixels in radius.

    Attributes
    ----------
    min_points : int
        Clouds with fewer points get no level of detail: every render draws
        every point (identical to ``detail="full"``), in [0, 10**10].
        10 M keeps the registration benchmarks' 3–8 M-point scans on the
        full renderer; above it a full render of the whole cloud takes
        seconds.
    max_radius_px : float
        Screen radius of a level's median surfel at which the next coarser
        level is taken, pixels, in [0.25, 8]. 1.0 keeps a level's point
        spacing (radius / ``splat_scale``) within about 1.3 pixel footprints
        (every point covers at least ``SplatParams.min_radius_px`` anyway):
        on the benchmark wall of 50 M points seen from 13 m, level 1, 6.5 M
        points drawn for 1.4 M covered pixels, depth within 2.5 mm (median)
        of every point's render (``docs/benchmarks.md``, ``bench_cloud_render``).
    block_points : int
        Points per block at full resolution on a plane (the block side is
        ``sqrt(block_points)`` grid steps), in [256, 1 000 000]: smaller
        blocks cull and choose levels more finely, at more per-block work.
    max_levels : int
        Coarsest level, in [1, 12] (level 8 keeps 1 / 65 536 of a plane).
    """

    min_points: int = 10_000_000
    max_radius_px: float = 1.0
    block_points: int = 4096
    max_levels: int = 8

    def __post_init__(self) -> None:
        check_number(self.min_points, "min_points", 0, 1e10, integer=True)
        check_number(self.max_radius_px, "max_radius_px", 0.25, 8.0)
        check_number(self.block_points, "block_points", 256, 1_000_000, integer=True)
        check_number(self.max_levels, "max_levels", 1, 12, integer=True)


#: Values of ``detail``: ``"auto"`` draws a large cloud through its level of
#: detail (:class:`LodParams`), ``"full"`` every point.
RENDER_DETAILS = ("auto", "full")


@dataclass(frozen=True)
class CloudParams:
    """How a cloud's normals, spacing and ray queries are computed.

    Attributes
    ----------
    k_normals : int
        Neighbours (the point included) whose covariance gives the PCA
        normal, in [6, 64]. 16 smooths 5 mm range noise on a 1 mrad scan
        without rounding edges of a few centimetres.
    k_spacing : int
        The local spacing is the distance to this neighbour (0 = the point
        itself), in [1, k_normals - 1]. The 8th neighbour of a regular grid
        lies at √2 × the grid step.
    chunk_points : int
        Points per block of the neighbour query (bounds its memory:
        ~ chunk × k × 40 bytes), in [1 000, 10 000 000].
    splat : SplatParams
        The surfels of the ray queries (and the default of renders).
    max_brute_force : float
        A ray query costs rays × points operations when done point by point;
        above this product, rays from one origin are answered from a splat
        render of a virtual camera instead.
    max_brute_force_misses : float
        Rays of a virtual-camera query that see nothing drawn around them
        (beyond its window's border, through a wide gap) are asked point by
        point while rays × points stays under this.
    gap_scale : float
        A ray that crosses no disc through a gap of a random sampling (or a
        gap of the front surface, where it would reach one behind) meets the
        discs enlarged this many times, in [1, 4]; rays just off a
        silhouette hit up to ``(gap_scale - 1) × radius`` beyond it.
    ray_window_px : int
        Longer side of that virtual camera's image, pixels, in [64, 4096].
    terrain_radius_m : float
        ``terrain_height`` without a DEM takes the lowest points within this
        horizontal radius (doubled up to 8 times until 10 points are found).
    lod : LodParams
        The level of detail of clouds of ``lod.min_points`` points or more.
    render_detail : {"auto", "full"}
        What a render draws when its caller does not say (``render()`` does
        not): ``"auto"`` the level of detail where the cloud has one,
        ``"full"`` every point (e.g. for a registration that wants the
        full-resolution z-buffer of a cloud above ``lod.min_points``).
    """

    k_normals: int = 16
    k_spacing: int = 8
    chunk_points: int = 262_144
    splat: SplatParams = field(default_factory=SplatParams)
    max_brute_force: float = 4e7
    max_brute_force_misses: float = 2e8
    gap_scale: float = 1.5
    ray_window_px: int = 1024
    terrain_radius_m: float = 1.0
    lod: LodParams = field(default_factory=LodParams)
    render_detail: str = "auto"

    def __post_init__(self) -> None:
        if self.render_detail not in RENDER_DETAILS:
            raise ValueError(f"render_detail must be one of {RENDER_DETAILS}, "
                             f"not {self.render_detail!r}")
        check_number(self.k_normals, "k_normals", 6, 64, integer=True)
        check_number(self.k_spacing, "k_spacing", 1, self.k_normals - 1, integer=True)
        check_number(self.chunk_points, "chunk_points", 1000, 10_000_000, integer=True)
        check_number(self.max_brute_force, "max_brute_force", 0.0, 1e12)
        check_number(self.max_brute_force_misses, "max_brute_force_misses", 0.0, 1e12)
        check_number(self.gap_scale, "gap_scale", 1.0, 4.0)
        check_number(self.ray_window_px, "ray_window_px", 64, 4096, integer=True)
        check_number(self.terrain_radius_m, "terrain_radius_m", 0.0, 1e4, low_open=True)


@dataclass
class CloudRayHits:
    """First hits of rays on a cloud's surfels (the fields of :class:`RayHits`).

    Attributes
    ----------
    distance : (N,) float32 array
        Distance along each (unit) ray to the hit, metres; ``inf`` for a miss.
    face_id : (N,) int32 array
        Index of the point whose surfel was hit, -1 for a miss (the name is
        that of :class:`~napari_imgreg.scene.RayHits`, so callers need not
        know which kind of scene they cast on).
    bary_u, bary_v : (N,) float32 arrays
        Zeros: a surfel has no barycentric coordinates.
    points : (N, 3) float64 array
        The hits (origin + distance × direction), NaN for misses.
    """

    distance: np.ndarray
    face_id: np.ndarray
    bary_u: np.ndarray
    bary_v: np.ndarray
    points: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        """(N,) bool: the ray met the surface."""
        return self.face_id >= 0


def _threads() -> int:
    env = os.environ.get("NAPARI_IMGREG_THREADS")
    return max(1, int(env)) if env else max(1, os.cpu_count() or 1)


class CloudScene:
    """A point cloud ready for splat rendering and ray queries.

    Parameters
    ----------
    xyz : (N, 3) array
        Point positions in the local frame, metres.
    intensity : (N,) array, optional
        Laser intensity. Values in [0, 1] are used as they are; others are
        normalised by their 0.5 and 99.5 percentiles (and clipped).
    rgb : (N, 3) uint8 array, optional
        Point colours, where the scan has them.
    georef : Georef, optional
    dem : DEM, optional
    name : str
    normals, spacing : arrays, optional
        Precomputed (N, 3) unit normals and (N,) spacings, metres (e.g. from
        the on-disk cache); computed by :meth:`build_engine` otherwise.
    viewpoints : (M, 3) array, optional
        Scanner positions: each normal is turned toward the nearest one.
        Without them normals face the side of the cloud's thinnest axis that
        points up (or toward +Y, then +X); renders and projections turn
        every normal toward their camera anyway.
    params : CloudParams

    Notes
    -----
    The mesh :class:`~napari_imgreg.scene.Scene` members a cloud has no
    counterpart for: ``faces``, ``n_faces``, ``uv`` and ``texture`` (None),
    ``face_array`` other than ``"normals"`` (per point here).
    """

    #: Tells the stages and the renderer a cloud from a mesh.
    is_cloud = True

    def __init__(
        self,
        xyz: np.ndarray,
        intensity: np.ndarray | None = None,
        rgb: np.ndarray | None = None,
        georef: Georef | None = None,
        dem: DEM | None = None,
        name: str = "cloud",
        normals: np.ndarray | None = None,
        spacing: np.ndarray | None = None,
        viewpoints: np.ndarray | None = None,
        params: CloudParams = CloudParams(),
    ) -> None:
        xyz = np.ascontiguousarray(xyz, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ValueError("xyz must have shape (N, 3)")
        if len(xyz) < params.k_normals:
            raise ValueError(f"a point cloud needs at least {params.k_normals} points, "
                             f"got {len(xyz)}")
        if not np.isfinite(xyz).all():
            raise ValueError("xyz holds NaN or infinite coordinates")
        n = len(xyz)
        self.xyz = xyz
        self.intensity = None if intensity is None else _normalise_intensity(intensity, n)
        if rgb is not None:
            rgb = np.ascontiguousarray(rgb)
            if rgb.shape != (n, 3):
                raise ValueError(f"rgb must have shape ({n}, 3), got {rgb.shape}")
            if rgb.dtype != np.uint8:
                hi = 65535.0 if rgb.max(initial=0) > 255 else 255.0
                rgb = np.clip(rgb / hi * 255.0 + 0.5, 0, 255).astype(np.uint8)
        self.vertex_colors = rgb
        self.georef = georef
        self.dem = dem
        self.name = name
        self.params = params
        self.viewpoints = None if viewpoints is None else np.asarray(viewpoints, float).reshape(-1, 3)
        self.texture = None
        self.uv = None
        self.survey_sun: np.ndarray | None = None
        self.warnings: list[str] = []
        self.timings_s: dict[str, float] = {}
        self.source: Path | None = None
        self._normals = None if normals is None else _check_normals(normals, n)
        self._spacing = None
        if spacing is not None:
            spacing = np.ascontiguousarray(spacing, np.float32).reshape(-1)
            if len(spacing) != n or not (np.isfinite(spacing).all() and (spacing >= 0).all()):
                raise ValueError(f"spacing must be {n} finite non-negative numbers")
            self._spacing = spacing
        self._surface_variation: np.ndarray | None = None
        self._cache: dict[Any, np.ndarray] = {}
        self._engine = None
        self._engine_lock = threading.Lock()
        self._lod: CloudLevelOfDetail | None = None
        self._lod_lock = threading.Lock()

    # ------------------------------------------------------------ construct
    @classmethod
    def from_point_cloud(
        cls,
        cloud: Any,
        georef: Georef | None = None,
        dem: DEM | None = None,
        name: str | None = None,
        params: CloudParams = CloudParams(),
    ) -> CloudScene:
        """A scene from a reader's result: reads only ``cloud.xyz``,
        ``cloud.intensity`` and ``cloud.rgb`` (either may be None).

        Parameters
        ----------
        cloud : PointCloud
            From :func:`napari_imgreg.io.pointclouds.read_point_cloud`.
        georef, dem : optional
        name : str, optional
            Default: the cloud's ``name`` or ``"cloud"``.
        """
        return cls(cloud.xyz, getattr(cloud, "intensity", None), getattr(cloud, "rgb", None),
                   georef=georef, dem=dem, name=name or getattr(cloud, "name", None) or "cloud",
                   params=params)

    @classmethod
    def load(
        cls,
        path: str | os.PathLike,
        georef: Georef | str | os.PathLike | None = None,
        dem: DEM | str | os.PathLike | None = None,
        cache: bool = True,
        params: CloudParams = CloudParams(),
        max_points: int | None | str = "default",
    ) -> CloudScene:
        """Load a point-cloud file (and optionally a georeference and a DEM).

        As :meth:`Scene.load`: a ``georef.json`` beside the file is used when
        ``georef`` is None. With ``cache``, the normals and spacings are read
        from (or, once computed, written to) ``<file>.imgreg-normals.npz``
        beside the file; a cache of other points or parameters is ignored.
        ``max_points`` is the reader's cap (``"default"``: the reader's own,
        :class:`~napari_imgreg.io.pointclouds.PointCloudParams`; None: every
        point, drawn through the level of detail above ``params.lod.min_points``).

        Raises
        ------
        InputError
            A file is missing or unreadable, or holds fewer than
            ``params.k_normals`` points.
        """
        from .geo import DEM, Georef
        from .io.pointclouds import read_point_cloud

        t0 = time.perf_counter()
        path = Path(path)
        if georef is None and (path.parent / "georef.json").exists():
            georef = path.parent / "georef.json"
        if georef is not None and not isinstance(georef, Georef):
            georef = Georef.load(georef)
        if dem is not None and not isinstance(dem, DEM):
            dem = DEM.load(dem)
        if isinstance(max_points, str):
            cloud = read_point_cloud(path, georef=georef)
        else:
            cloud = read_point_cloud(path, georef=georef, max_points=max_points)
        n_read = len(np.asarray(cloud.xyz).reshape(-1, 3))
        if n_read < params.k_normals:  # the PCA needs k_normals neighbours per point
            raise input_error(path, f"a point cloud needs at least {params.k_normals} points "
                              f"(its normals are fitted to {params.k_normals} neighbours), "
                              f"got {n_read}")
        scene = cls.from_point_cloud(cloud, georef=georef, dem=dem, name=path.stem,
                                     params=params)
        scene.warnings = list(getattr(cloud, "notes", None) or [])
        scene.source = path
        if cache:
            scene._read_cache()
        scene.timings_s["load"] = time.perf_counter() - t0
        return scene

    # ------------------------------------------------------------- geometry
    @property
    def n_points(self) -> int:
        return len(self.xyz)

    @property
    def vertices(self) -> np.ndarray:
        """(N, 3) float64: the points (the name of the mesh's vertices)."""
        return self.xyz

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) array: min and max corner of the cloud, metres."""
        if "bounds" not in self._cache:
            self._cache["bounds"] = np.stack([self.xyz.min(axis=0), self.xyz.max(axis=0)])
        return self._cache["bounds"]

    @property
    def has_texture(self) -> bool:
        return False

    @property
    def uv_wraps(self) -> bool:
        return False

    @property
    def has_intensity(self) -> bool:
        return self.intensity is not None

    @property
    def xyz32(self) -> np.ndarray:
        """(N, 3) float32 copy of the points for the renderer (the local
        frame keeps float32 at ~10 µm over 100 m)."""
        if "xyz32" not in self._cache:
            self._cache["xyz32"] = np.ascontiguousarray(self.xyz, dtype=np.float32)
        return self._cache["xyz32"]

    @property
    def colors(self) -> np.ndarray:
        """(N, 3) uint8 colours the renderer draws: the points' colour, or
        their intensity as grey, or grey 180."""
        if "colors" not in self._cache:
            if self.vertex_colors is not None:
                c = self.vertex_colors
            elif self.intensity is not None:
                g = np.clip(self.intensity * 255.0 + 0.5, 0, 255).astype(np.uint8)
                c = np.repeat(g[:, None], 3, axis=1)
            else:
                c = np.full((self.n_points, 3), 180, np.uint8)
            self._cache["colors"] = np.ascontiguousarray(c)
        return self._cache["colors"]

    @property
    def normals(self) -> np.ndarray:
        """(N, 3) float32 unit PCA normals (computed on first use)."""
        if self._normals is None:
            self._compute_normals()
        return self._normals

    @property
    def spacing(self) -> np.ndarray:
        """(N,) float32 local point spacing, metres: distance to the
        ``k_spacing``-th neighbour (computed on first use)."""
        if self._spacing is None:
            self._compute_normals()
        return self._spacing

    @property
    def surface_variation(self) -> np.ndarray:
        """(N,) float32 λ₀ / (λ₀ + λ₁ + λ₂) of the neighbourhood covariance:
        0 on a plane, 1/3 for isotropic scatter (vegetation, noise)."""
        if self._surface_variation is None:
            self._compute_normals()
        return self._surface_variation

    @property
    def render_detail(self) -> str:
        """What a render draws by default: ``params.render_detail``."""
        return self.params.render_detail

    @property
    def level_of_detail(self) -> CloudLevelOfDetail | None:
        """The blocks and levels of a cloud of ``params.lod.min_points``
        points or more, None for a smaller cloud. Built on first use
        (:meth:`build_engine` builds it) and, for a loaded file, cached beside
        it as ``<file>.imgreg-lod.npz`` (its points' order; ignored when the
        points or ``block_points`` / ``max_levels`` differ)."""
        if self.n_points < self.params.lod.min_points:
            return None
        if self._lod is None:
            normals, spacing, colors = self.normals, self.spacing, self.colors
            with self._lod_lock:
                if self._lod is None:
                    t0 = time.perf_counter()
                    order = self._read_lod_cache()
                    if order is None:
                        order = CloudLevelOfDetail.block_order(self.xyz, spacing,
                                                               self.params.lod)
                        self._write_lod_cache(*order)
                    self._lod = CloudLevelOfDetail.assemble(*order, self.xyz32, normals,
                                                            colors, spacing)
                    self.timings_s["lod"] = time.perf_counter() - t0
        return self._lod

    def splat_radius(self, scale: float) -> np.ndarray:
        """(N,) float32 surfel radii, metres: ``scale × spacing``."""
        key = ("radius", float(scale))
        if key not in self._cache:
            self._cache = {k: v for k, v in self._cache.items()
                           if not (isinstance(k, tuple) and k[0] == "radius")}
            self._cache[key] = (self.spacing * np.float32(scale)).astype(np.float32)
        return self._cache[key]

    def face_array(self, name: str) -> np.ndarray:
        """``"normals"``: the (N, 3) float32 point normals, indexed by the
        ``face_id`` of a render or a ray query as a mesh's face normals are.

        Raises
        ------
        ValueError
            Any other name: a cloud has no faces, texture coordinates or
            corner colours.
        """
        if name == "normals":
            return self.normals
        raise ValueError(f"{self.name}: a point cloud has no per-face {name!r}")

    # -------------------------------------------------------------- engine
    @property
    def engine(self) -> CloudScene:
        """The cloud itself once its normals and spacings exist (the mesh's
        Embree scene has no counterpart: the kernels run on the arrays)."""
        if self._engine is None:
            self.build_engine()
        return self._engine

    def build_engine(self) -> float:
        """Compute normals and spacings (or take them from the cache), the
        level of detail of a large cloud, and compile the render kernels;
        returns the seconds it took."""
        with self._engine_lock:
            if self._engine is not None:
                return 0.0
            t0 = time.perf_counter()
            _ = self.normals
            t1 = time.perf_counter()
            # Compile (or load) the kernels now, so that the first real
            # render is not charged for it.
            warm_up()
            _ = self.level_of_detail
            t_probe, id_probe = np.full(1, np.inf), np.full(1, -1, np.int64)
            _cast_brute(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), self.xyz32[:1],
                        self.normals[:1], self.splat_radius(self.params.splat.splat_scale)[:1],
                        self.params.splat.grazing_cos, t_probe, id_probe)
            self._engine = self
            self.timings_s["normals"] = t1 - t0
            self.timings_s["compile"] = time.perf_counter() - t1 - self.timings_s.get("lod", 0.0)
            self.timings_s["build"] = time.perf_counter() - t0
            return self.timings_s["build"]

    def _compute_normals(self) -> None:
        from scipy.spatial import cKDTree

        t0 = time.perf_counter()
        p = self.params
        xyz = self.xyz
        n = len(xyz)
        tree = cKDTree(xyz)
        normals = np.empty((n, 3), np.float32)
        spacing = np.empty(n, np.float32)
        variation = np.empty(n, np.float32)
        # Queries in spatial order run ~4x faster than in a random one (the
        # tree's nodes stay in cache): visit the points cell by cell.
        lo_corner, hi_corner = self.bounds
        cell = max(float(np.linalg.norm(hi_corner - lo_corner)) / 256.0, 1e-9)
        ijk = ((xyz - lo_corner) / cell).astype(np.int64)
        order = np.argsort((ijk[:, 0] * 1024 + ijk[:, 1]) * 1024 + ijk[:, 2], kind="stable")
        del ijk
        for lo in range(0, n, p.chunk_points):
            sel = order[lo:lo + p.chunk_points]
            dist, idx = tree.query(xyz[sel], k=p.k_normals, workers=_threads())
            nrm = np.empty((len(sel), 3))
            var = np.empty(len(sel))
            _pca_kernel(xyz, idx, nrm, var)
            normals[sel] = nrm
            spacing[sel] = dist[:, p.k_spacing]
            variation[sel] = var
        del tree
        self._orient(normals)
        self._normals = normals
        self._spacing = spacing
        self._surface_variation = variation
        self.timings_s["normals_compute"] = time.perf_counter() - t0
        self._write_cache()

    def _orient(self, normals: np.ndarray) -> None:
        """Turn the normals toward the nearest scanner, or (without one) to
        the up side of the cloud's thinnest axis."""
        if self.viewpoints is not None and len(self.viewpoints):
            from scipy.spatial import cKDTree

            _, k = cKDTree(self.viewpoints).query(self.xyz, workers=_threads())
            toward = self.viewpoints[k] - self.xyz
        else:
            sample = self.xyz[:: max(1, len(self.xyz) // 200_000)]
            centred = sample - sample.mean(axis=0)
            axis = np.linalg.eigh(centred.T @ centred)[1][:, 0]
            for comp in (2, 1, 0):
                if abs(axis[comp]) > 0.3:
                    axis = axis * np.sign(axis[comp])
                    break
            toward = axis[None, :]
        flip = np.einsum("ij,ij->i", normals, np.broadcast_to(toward, normals.shape)) < 0
        normals[flip] *= -1

    # --------------------------------------------------------------- cache
    def _cache_path(self) -> Path | None:
        return None if self.source is None else self.source.with_name(
            self.source.name + ".imgreg-normals.npz")

    def _fingerprint(self) -> str:
        h = hashlib.sha1()
        sample = self.xyz32[:: max(1, self.n_points // 100_000)]
        h.update(np.ascontiguousarray(sample).tobytes())
        h.update(repr((_CACHE_VERSION, self.n_points, self.params.k_normals,
                       self.params.k_spacing)).encode())
        if self.viewpoints is not None:
            h.update(np.ascontiguousarray(self.viewpoints).tobytes())
        return h.hexdigest()

    def _read_cache(self) -> None:
        path = self._cache_path()
        if path is None or not path.exists() or self._normals is not None:
            return
        try:
            with np.load(path, allow_pickle=False) as data:
                if str(data["fingerprint"]) != self._fingerprint():
                    return
                normals = data["normals"].astype(np.float32)
                spacing = data["spacing"].astype(np.float32)
                variation = data["surface_variation"].astype(np.float32)
            n = self.n_points
            # Well-formed but wrong (NaN normals, a truncated array): computed again.
            if (normals.shape != (n, 3) or spacing.shape != (n,) or variation.shape != (n,)
                    or not np.isfinite(normals).all() or not np.isfinite(spacing).all()
                    or not np.isfinite(variation).all() or (spacing < 0).any()):
                log.info("%s: normals cache not used (wrong shape or non-finite values)", path)
                return
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            log.info("%s: normals cache not used (%s)", path, exc)
            return
        self._normals, self._spacing, self._surface_variation = normals, spacing, variation

    def _write_cache(self) -> None:
        path = self._cache_path()
        if path is None:
            return
        from ._atomic import atomic_path

        try:
            with atomic_path(path) as tmp:
                # As computed (float32): float16 normals (0.03° off) once moved a
                # registration by 0.5 m, so a run with the cache differed from the
                # first run without it. A cache must cost only time.
                np.savez(tmp, fingerprint=np.array(self._fingerprint()),
                         normals=self._normals.astype(np.float32), spacing=self._spacing,
                         surface_variation=self._surface_variation.astype(np.float32))
        except OSError as exc:  # a read-only folder: compute again next time
            log.info("%s: normals cache not written (%s)", path, exc)

    def _lod_cache_path(self) -> Path | None:
        return None if self.source is None else self.source.with_name(
            self.source.name + ".imgreg-lod.npz")

    def _lod_fingerprint(self) -> str:
        lod = self.params.lod
        return self._fingerprint() + repr((lod.block_points, lod.max_levels))

    def _read_lod_cache(self):
        """(ids, starts, counts, step) of the level of detail from
        ``<file>.imgreg-lod.npz`` beside the source, or None."""
        path = self._lod_cache_path()
        if path is None or not path.exists():
            return None
        try:
            with np.load(path, allow_pickle=False) as data:
                if str(data["fingerprint"]) != self._lod_fingerprint():
                    return None
                ids = data["ids"].astype(np.int32)
                starts = data["starts"].astype(np.int64)
                counts = data["counts"].astype(np.int64)
                step = float(data["step_m"])
            if (len(ids) != self.n_points or counts.shape[0] != len(starts)
                    or int(counts[:, 0].sum()) != self.n_points):
                return None
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            log.info("%s: level-of-detail cache not used (%s)", path, exc)
            return None
        return ids, starts, counts, step

    def _write_lod_cache(self, ids, starts, counts, step) -> None:
        path = self._lod_cache_path()
        if path is None:
            return
        from ._atomic import atomic_path

        try:
            with atomic_path(path) as tmp:
                np.savez(tmp, fingerprint=np.array(self._lod_fingerprint()), ids=ids,
                         starts=starts, counts=counts.astype(np.int32), step_m=np.array(step))
        except OSError as exc:  # a read-only folder: build again next time
            log.info("%s: level-of-detail cache not written (%s)", path, exc)

    # --------------------------------------------------------- ray queries
    def cast_rays(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        max_distance: float | np.ndarray | None = None,
    ) -> CloudRayHits:
        """First surfels met by rays.

        A ray hits a point's surfel (its disc of radius ``splat_scale ×
        spacing`` in its tangent plane) where it crosses the disc; a ray
        seeing a surfel edge-on (``grazing_cos``) hits it where it passes
        within the radius of the point. Small queries test every point;
        larger ones from one origin (a camera's pixels) are answered from a
        splat render of a virtual camera at the origin, then intersected
        exactly with the surfels seen at and around each ray.

        Parameters
        ----------
        origins : (N, 3) or (3,) array
            Ray origins, metres.
        directions : (N, 3) array
            Unit ray directions.
        max_distance : float or (N,) array, optional
            Ignore hits farther than this.

        Returns
        -------
        CloudRayHits
        """
        d = np.asarray(directions, np.float64).reshape(-1, 3)
        m = len(d)
        o = np.asarray(origins, np.float64)
        o = np.broadcast_to(o, (m, 3)) if o.ndim == 1 else o.reshape(-1, 3)
        d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
        t = np.full(m, np.inf)
        ids = np.full(m, -1, np.int64)
        if m:
            _ = self.engine
            one_origin = bool(np.all(o == o[0]))
            big = m * self.n_points > self.params.max_brute_force
            if one_origin and big:
                t, ids = self._cast_from_origin(o[0], d)
            elif big and np.all(np.abs(d - d[0]) < 1e-9):
                t, ids = self._cast_parallel(o, d[0])
            else:
                _cast_brute(np.ascontiguousarray(o), np.ascontiguousarray(d), self.xyz32,
                            self.normals, self.splat_radius(self.params.splat.splat_scale),
                            self.params.splat.grazing_cos, t, ids, self.params.gap_scale,
                            self.params.splat.fill_depth_tol)
        if max_distance is not None:
            far = t > np.broadcast_to(np.asarray(max_distance, np.float64), (m,))
            t[far] = np.inf
            ids[far] = -1
        ids[~np.isfinite(t)] = -1
        t[ids < 0] = np.inf
        points = np.where((ids >= 0)[:, None], o + d * np.where(np.isfinite(t), t, 0)[:, None],
                          np.nan)
        zeros = np.zeros(m, np.float32)
        return CloudRayHits(t.astype(np.float32), ids.astype(np.int32), zeros, zeros.copy(),
                            points)

    def _cast_parallel(self, origins: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Parallel rays (a sun's shadow rays): the surfels binned on grids
        across ``d``, each ray tested against the surfels of its 3 × 3 cells.

        Exact as the brute force is: a surfel goes to the grid whose cells
        are no smaller than its wide disc (grids double in cell size, from
        the median disc's), so the 3 × 3 cells around a ray hold every
        surfel it can meet.
        """
        helper = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
        ax = np.cross(helper, d)
        ax /= np.linalg.norm(ax)
        ay = np.cross(d, ax)
        gap_scale = self.params.gap_scale
        radius = self.splat_radius(self.params.splat.splat_scale)
        reach = radius.astype(np.float64) * gap_scale
        xyz = self.xyz
        pu, pv = xyz @ ax, xyz @ ay
        # At most ~2048 cells a side per grid.
        extent = max(float(np.ptp(pu)), float(np.ptp(pv)), 1e-6)
        cell0 = max(float(np.median(reach)), extent / 2048.0, 1e-6)
        level = np.ceil(np.log2(np.maximum(reach / cell0, 1.0))).astype(np.int64)
        m = len(origins)
        best_t, wide_t = np.full(m, np.inf), np.full(m, np.inf)
        best_id, wide_id = np.full(m, -1, np.int64), np.full(m, -1, np.int64)
        o = np.ascontiguousarray(origins, np.float64)
        dd = np.ascontiguousarray(d, np.float64)
        n_threads = min(_threads(), m)
        for lv in np.unique(level):
            members = np.flatnonzero(level == lv)
            cell = max(cell0 * 2.0 ** int(lv), extent / 2048.0)
            cu = np.floor(pu[members] / cell).astype(np.int64)
            cv = np.floor(pv[members] / cell).astype(np.int64)
            u0, v0 = int(cu.min()), int(cv.min())
            nu, nv = int(cu.max()) - u0 + 1, int(cv.max()) - v0 + 1
            key = (cu - u0) * nv + (cv - v0)
            sort = np.argsort(key, kind="stable")
            order = members[sort]
            starts = np.searchsorted(key[sort], np.arange(nu * nv + 1)).astype(np.int64)
            dims = np.array([u0, v0, nu, nv], np.int64)
            _run_blocks(_parallel_kernel, m, n_threads, o, dd, ax, ay, cell, dims, starts, order,
                        self.xyz32, self.normals, radius, self.params.splat.grazing_cos, gap_scale,
                        best_t, best_id, wide_t, wide_id)
        # As _brute_kernel ends: the wide hit where it lies in front or alone.
        use_wide = (wide_id >= 0) & ((best_id < 0)
                                     | (wide_t < best_t * (1.0 - self.params.splat.fill_depth_tol)))
        t = np.where(use_wide, wide_t, best_t)
        ids = np.where(use_wide, wide_id, best_id)
        return t, ids

    def _cast_from_origin(self, origin: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rays from one origin through a virtual camera's splat render."""
        t = np.full(len(d), np.inf)
        ids = np.full(len(d), -1, np.int64)
        mean = d.sum(axis=0)
        norm = np.linalg.norm(mean)
        if norm < 1e-9 or (d @ (mean / norm)).min() < math.cos(math.radians(60.0)):
            # A wide fan: one virtual camera per dominant axis (≤ 55° off it).
            axis = np.abs(d).argmax(axis=1) * 2 + (d[np.arange(len(d)), np.abs(d).argmax(axis=1)] < 0)
            for g in np.unique(axis):
                sel = np.flatnonzero(axis == g)
                view = np.zeros(3)
                view[g // 2] = -1.0 if g % 2 else 1.0
                t[sel], ids[sel] = self._cast_window(origin, d[sel], view)
            return t, ids
        return self._cast_window(origin, d, mean / norm)

    def _cast_window(self, origin: np.ndarray, d: np.ndarray,
                     view: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        helper = np.array([0.0, 0.0, 1.0]) if abs(view[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = np.cross(helper, view)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(view, x), view])
        dc = d @ R.T
        xn, yn = dc[:, 0] / dc[:, 2], dc[:, 1] / dc[:, 2]
        lo = np.array([xn.min(), yn.min()])
        hi = np.array([xn.max(), yn.max()])
        pad = 4
        step = float(np.clip((hi - lo).max() / (self.params.ray_window_px - 2 * pad), 2e-5, 2e-3))
        w, h = (np.ceil((hi - lo) / step).astype(int) + 2 * pad + 1)
        intr = Intrinsics(int(w), int(h), 1.0 / step, 1.0 / step,
                          pad - lo[0] / step, pad - lo[1] / step)
        pose = Pose(R, -R @ origin)
        z = splat_depth(self, intr, pose, self.params.splat)
        idbuf = z["ids"]
        u = xn / step + intr.cx
        v = yn / step + intr.cy
        u0 = np.clip(np.floor(u).astype(int), 0, w - 2)
        v0 = np.clip(np.floor(v).astype(int), 0, h - 2)
        cand = np.stack([idbuf[v0, u0], idbuf[v0, u0 + 1], idbuf[v0 + 1, u0],
                         idbuf[v0 + 1, u0 + 1]], axis=1).astype(np.int64)  # (M, 4)
        ok = cand >= 0
        ci = np.where(ok, cand, 0)
        p = self.xyz[ci]  # (M, 4, 3)
        nrm = self.normals[ci].astype(np.float64)
        r = self.splat_radius(self.params.splat.splat_scale)[ci].astype(np.float64)
        rel = p - origin
        den = np.einsum("mkj,mj->mk", nrm, d)
        with np.errstate(divide="ignore", invalid="ignore"):
            th = np.einsum("mkj,mkj->mk", nrm, rel) / den
        q = origin + th[..., None] * d[:, None, :]
        off2 = np.einsum("mkj,mkj->mk", q - p, q - p) / (r * r)
        facing = ok & (np.abs(den) > self.params.splat.grazing_cos) & (th > 0)
        rows = np.arange(len(d))
        disc = facing & (off2 <= 1.0)
        th_disc = np.where(disc, th, np.inf)
        best = th_disc.argmin(axis=1)
        t = th_disc[rows, best]
        ids = np.where(np.isfinite(t), cand[rows, best], -1)
        # No candidate's disc crossed (the ray passes through a gap the
        # render filled): the tangent plane of the candidate whose disc it
        # passes nearest — exact on a plane, as the filled pixel was.
        miss = ~np.isfinite(t) & facing.any(axis=1)
        if miss.any():
            nearest = np.where(facing, off2, np.inf)[miss].argmin(axis=1)
            t[miss] = th[miss][np.arange(miss.sum()), nearest]
            ids[miss] = cand[miss][np.arange(miss.sum()), nearest]
        # Nothing drawn around the ray at all: point by point, when few.
        lost = np.flatnonzero(ids < 0)
        if len(lost) and len(lost) * self.n_points <= self.params.max_brute_force_misses:
            t_l, id_l = np.full(len(lost), np.inf), np.full(len(lost), -1, np.int64)
            _cast_brute(np.ascontiguousarray(np.broadcast_to(origin, (len(lost), 3))),
                        np.ascontiguousarray(d[lost]), self.xyz32, self.normals,
                        self.splat_radius(self.params.splat.splat_scale),
                        self.params.splat.grazing_cos, t_l, id_l, self.params.gap_scale,
                        self.params.splat.fill_depth_tol)
            t[lost], ids[lost] = t_l, id_l
        return t, ids

    def surface_points(self, hits: CloudRayHits) -> np.ndarray:
        """The hit points, (N, 3) float64; NaN for misses."""
        return np.where(hits.hit[:, None], hits.points, np.nan)

    # --------------------------------------------------------------- terrain
    def terrain_height(self, x: float, y: float) -> float:
        """Terrain height (local frame) at local (x, y): the DEM when there is
        one, else the 2nd percentile of the heights of the points within
        ``terrain_radius_m`` (growing) of (x, y) — the ground below a cliff,
        robust to a few noise points under it.

        Raises
        ------
        InputError
            Outside the DEM, or no points near (x, y) without a DEM.
        """
        if self.dem is not None:
            return dem_height_local(self.dem, self.georef, x, y)
        tree, z = self._terrain_tree()
        radius = self.params.terrain_radius_m
        for _ in range(9):
            near = tree.query_ball_point([x, y], radius)
            if len(near) >= 10:
                return float(np.percentile(z[near], 2.0))
            radius *= 2.0
        raise InputError(f"{self.name}: no points within {radius / 2:.0f} m of "
                         f"({x:.1f}, {y:.1f}) and no DEM")

    def height_grid(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """Highest point in each cell of a grid (a surface model of the cloud),
        for map views (the mesh scene's answer is a ray cast down per cell,
        which costs a cloud all its points per ray).

        Parameters
        ----------
        xs : (C,) array
            Cell centres along x, increasing, evenly spaced, metres.
        ys : (R,) array
            Cell centres along y, evenly spaced (either direction), metres.

        Returns
        -------
        (R, C) float64 array
            Heights, metres (local frame); NaN where a cell holds no point.
        """
        xs = np.asarray(xs, np.float64)
        ys = np.asarray(ys, np.float64)
        dx = (xs[-1] - xs[0]) / max(len(xs) - 1, 1) or 1.0
        dy = (ys[-1] - ys[0]) / max(len(ys) - 1, 1) or 1.0
        col = np.floor((self.xyz[:, 0] - xs[0]) / dx + 0.5).astype(np.int64)
        row = np.floor((self.xyz[:, 1] - ys[0]) / dy + 0.5).astype(np.int64)
        ok = (col >= 0) & (col < len(xs)) & (row >= 0) & (row < len(ys))
        grid = np.full(len(ys) * len(xs), -np.inf)
        np.maximum.at(grid, row[ok] * len(xs) + col[ok], self.xyz[ok, 2])
        grid[~np.isfinite(grid)] = np.nan
        return grid.reshape(len(ys), len(xs))

    def _terrain_tree(self):
        if "terrain" not in self._cache:
            from scipy.spatial import cKDTree

            step = max(1, self.n_points // 2_000_000)
            sample = self.xyz[::step]
            self._cache["terrain"] = (cKDTree(sample[:, :2]), sample[:, 2].copy())
        return self._cache["terrain"]

    def __repr__(self) -> str:
        colour = ("colour" if self.vertex_colors is not None else
                  "intensity" if self.intensity is not None else "no intensity")
        return f"CloudScene({self.name!r}, {self.n_points} points, {colour})"


# ---------------------------------------------------------------- helpers
def _normalise_intensity(intensity: np.ndarray, n: int) -> np.ndarray:
    """Intensity as float32 in [0, 1]; values outside it are rescaled by
    their 0.5 and 99.5 percentiles."""
    a = np.asarray(intensity, np.float32).reshape(-1)
    if len(a) != n:
        raise ValueError(f"intensity must have {n} values, got {len(a)}")
    if not np.isfinite(a).all():
        raise ValueError("intensity holds NaN or infinite values")
    if a.size and (a.min() < 0.0 or a.max() > 1.0):
        lo, hi = np.percentile(a, [0.5, 99.5])
        a = np.clip((a - lo) / max(float(hi - lo), 1e-12), 0.0, 1.0).astype(np.float32)
    return np.ascontiguousarray(a)


def _check_normals(normals: np.ndarray, n: int) -> np.ndarray:
    a = np.ascontiguousarray(normals, np.float32)
    if a.shape != (n, 3) or not np.isfinite(a).all():
        raise ValueError(f"normals must have shape ({n}, 3) and be finite")
    length = np.linalg.norm(a, axis=1, keepdims=True)
    return np.ascontiguousarray(a / np.maximum(length, 1e-12))


@njit(cache=True, nogil=True, error_model="numpy")
def _pca_kernel(xyz, idx, out_normal, out_variation):  # pragma: no cover
    # Per point: covariance of its neighbours, its eigenvalues in closed form
    # (Smith's trigonometric solution for a symmetric 3 × 3), and the
    # eigenvector of the smallest as the best-conditioned cross product of
    # two rows of (C - λ I). ~10x faster than numpy's batched eigh.
    k = idx.shape[1]
    for j in range(idx.shape[0]):
        mx = my = mz = 0.0
        for a in range(k):
            q = idx[j, a]
            mx += xyz[q, 0]
            my += xyz[q, 1]
            mz += xyz[q, 2]
        mx /= k
        my /= k
        mz /= k
        cxx = cxy = cxz = cyy = cyz = czz = 0.0
        for a in range(k):
            q = idx[j, a]
            dx = xyz[q, 0] - mx
            dy = xyz[q, 1] - my
            dz = xyz[q, 2] - mz
            cxx += dx * dx
            cxy += dx * dy
            cxz += dx * dz
            cyy += dy * dy
            cyz += dy * dz
            czz += dz * dz
        tr = cxx + cyy + czz
        m = tr / 3.0
        p1 = cxy * cxy + cxz * cxz + cyz * cyz
        p2 = (cxx - m) ** 2 + (cyy - m) ** 2 + (czz - m) ** 2 + 2.0 * p1
        pp = math.sqrt(p2 / 6.0)
        if pp <= 1e-300 * (1.0 + tr):
            out_normal[j, 0] = 0.0
            out_normal[j, 1] = 0.0
            out_normal[j, 2] = 1.0
            out_variation[j] = 1.0 / 3.0
            continue
        bxx = (cxx - m) / pp
        byy = (cyy - m) / pp
        bzz = (czz - m) / pp
        bxy = cxy / pp
        bxz = cxz / pp
        byz = cyz / pp
        det = (bxx * (byy * bzz - byz * byz) - bxy * (bxy * bzz - byz * bxz)
               + bxz * (bxy * byz - byy * bxz))
        r = min(max(det / 2.0, -1.0), 1.0)
        phi = math.acos(r) / 3.0
        lam = m + 2.0 * pp * math.cos(phi + 2.0 * math.pi / 3.0)  # the smallest
        ax, ay, az = cxx - lam, cxy, cxz
        bx, by, bz = cxy, cyy - lam, cyz
        ex, ey, ez = cxz, cyz, czz - lam
        v1x, v1y, v1z = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        v2x, v2y, v2z = ay * ez - az * ey, az * ex - ax * ez, ax * ey - ay * ex
        v3x, v3y, v3z = by * ez - bz * ey, bz * ex - bx * ez, bx * ey - by * ex
        n1 = v1x * v1x + v1y * v1y + v1z * v1z
        n2 = v2x * v2x + v2y * v2y + v2z * v2z
        n3 = v3x * v3x + v3y * v3y + v3z * v3z
        if n1 >= n2 and n1 >= n3:
            vx, vy, vz, nn = v1x, v1y, v1z, n1
        elif n2 >= n3:
            vx, vy, vz, nn = v2x, v2y, v2z, n2
        else:
            vx, vy, vz, nn = v3x, v3y, v3z, n3
        if nn <= 0.0:
            vx, vy, vz, nn = 0.0, 0.0, 1.0, 1.0
        s = 1.0 / math.sqrt(nn)
        out_normal[j, 0] = vx * s
        out_normal[j, 1] = vy * s
        out_normal[j, 2] = vz * s
        out_variation[j] = max(lam, 0.0) / tr if tr > 0.0 else 1.0 / 3.0


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _surfel_test(i, ox, oy, oz, dx, dy, dz, xyz, normals, radius, grazing, gap_scale,
                 best):  # pragma: no cover
    # Where the ray (o, d) meets surfel i: (t, inner); t = inf when it
    # misses the wide disc or lies beyond ``best``; inner: within the disc
    # itself (not only the gap_scale wider one).
    r = np.float64(radius[i]) * gap_scale
    vx = xyz[i, 0] - ox
    vy = xyz[i, 1] - oy
    vz = xyz[i, 2] - oz
    tp = vx * dx + vy * dy + vz * dz
    if tp <= 0.0 or tp - r >= best:
        return np.inf, False
    d2 = vx * vx + vy * vy + vz * vz - tp * tp
    r2 = r * r
    if d2 > r2:
        return np.inf, False  # the ray passes outside the point's (wide) sphere
    nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
    den = nx * dx + ny * dy + nz * dz
    if abs(den) > grazing:
        th = (nx * vx + ny * vy + nz * vz) / den
        qx = th * dx - vx
        qy = th * dy - vy
        qz = th * dz - vz
        q2 = qx * qx + qy * qy + qz * qz
        if th <= 0.0 or q2 > r2:
            return np.inf, False
        return th, q2 * gap_scale * gap_scale <= r2
    return tp, d2 * gap_scale * gap_scale <= r2  # edge-on: where the ray passes the point


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _surfel_update(i, ox, oy, oz, dx, dy, dz, xyz, normals, radius, grazing, gap_scale,
                   best, bi, wide, wi):  # pragma: no cover
    # The ray's first inner hit (best, bi) and first wide hit (wide, wi)
    # after testing surfel i.
    th, inner = _surfel_test(i, ox, oy, oz, dx, dy, dz, xyz, normals, radius, grazing,
                             gap_scale, best)
    if inner and th < best:
        best, bi = th, i
    if th < wide:
        wide, wi = th, i
    return best, bi, wide, wi


@njit(cache=True, nogil=True, error_model="numpy")
def _brute_kernel(lo, hi, origins, dirs, xyz, normals, radius, grazing, gap_scale, gap_tol,
                  out_t, out_id):  # pragma: no cover
    # Rays lo..hi against every surfel: the first disc each ray crosses. A
    # random sampling leaves gaps between the discs; discs gap_scale times
    # larger close them, and win where they lie on a surface in front
    # (by more than gap_tol of the distance) or where no disc was crossed.
    for j in range(lo, hi):
        ox, oy, oz = origins[j, 0], origins[j, 1], origins[j, 2]
        dx, dy, dz = dirs[j, 0], dirs[j, 1], dirs[j, 2]
        best = np.inf
        bi = -1
        wide = np.inf
        wi = -1
        for i in range(xyz.shape[0]):
            best, bi, wide, wi = _surfel_update(i, ox, oy, oz, dx, dy, dz, xyz, normals, radius,
                                                grazing, gap_scale, best, bi, wide, wi)
        if wi >= 0 and (bi < 0 or wide < best * (1.0 - gap_tol)):
            best = wide
            bi = wi
        out_t[j] = best
        out_id[j] = bi


@njit(cache=True, nogil=True, error_model="numpy")
def _parallel_kernel(lo, hi, origins, d, ax, ay, cell, dims, starts, order, xyz, normals, radius,
                     grazing, gap_scale, best_t, best_id, wide_t, wide_id):  # pragma: no cover
    # Rays lo..hi, all along d, against the surfels binned by their position
    # across d (axes ax, ay; cells no smaller than these surfels' wide discs):
    # each ray tests the surfels of its cell and the 8 around it, as
    # _brute_kernel does, updating its first inner and first wide hit.
    dx, dy, dz = d[0], d[1], d[2]
    for j in range(lo, hi):
        ox, oy, oz = origins[j, 0], origins[j, 1], origins[j, 2]
        cu = np.int64(math.floor((ox * ax[0] + oy * ax[1] + oz * ax[2]) / cell)) - dims[0]
        cv = np.int64(math.floor((ox * ay[0] + oy * ay[1] + oz * ay[2]) / cell)) - dims[1]
        best, bi, wide, wi = best_t[j], best_id[j], wide_t[j], wide_id[j]
        for gu in range(max(cu - 1, 0), min(cu + 2, dims[2])):
            for gv in range(max(cv - 1, 0), min(cv + 2, dims[3])):
                c = gu * dims[3] + gv
                for k in range(starts[c], starts[c + 1]):
                    i = order[k]
                    best, bi, wide, wi = _surfel_update(i, ox, oy, oz, dx, dy, dz, xyz, normals,
                                                        radius, grazing, gap_scale, best, bi,
                                                        wide, wi)
        best_t[j], best_id[j], wide_t[j], wide_id[j] = best, bi, wide, wi


def _cast_brute(origins, dirs, xyz, normals, radius, grazing, out_t, out_id,
                gap_scale=1.5, gap_tol=0.02) -> None:
    """:func:`_brute_kernel` over all rays, on a few threads (it releases the GIL)."""
    m = len(dirs)
    _run_blocks(_brute_kernel, m, min(_threads(), m), origins, dirs, xyz, normals, radius,
                grazing, gap_scale, gap_tol, out_t, out_id)


# -------------------------------------------------------- level of detail
@njit(cache=True, nogil=True, error_model="numpy")
def _voxel_keys(xyz, cand, lo, inv_cell, dims, out):  # pragma: no cover
    # Flat voxel index of points cand (all points when cand is empty).
    m = out.shape[0]
    for j in range(m):
        i = cand[j] if cand.shape[0] else j
        a = np.int64((xyz[i, 0] - lo[0]) * inv_cell)
        b = np.int64((xyz[i, 1] - lo[1]) * inv_cell)
        c = np.int64((xyz[i, 2] - lo[2]) * inv_cell)
        out[j] = (min(a, dims[0] - 1) * dims[1] + min(b, dims[1] - 1)) * dims[2] + min(c, dims[2] - 1)


@njit(cache=True, nogil=True, error_model="numpy")
def _first_of_each(keys, expected):  # pragma: no cover
    # Positions (increasing) of the first occurrence of each distinct
    # (non-negative) key: an open-addressing hash set sized for `expected`
    # distinct keys, doubled and run again when there are more.
    bits = 4
    while (1 << bits) < 2 * max(expected, 1):
        bits += 1
    out = np.empty(keys.shape[0], np.int64)
    while True:
        size = 1 << bits
        mask = size - 1
        table = np.full(size, -1, np.int64)
        n = 0
        full = False
        for j in range(keys.shape[0]):
            k = keys[j]
            # Fibonacci hashing: the top bits of k × 2^64 / φ (wrapping).
            h = ((k * -7046029254386353131) >> (64 - bits)) & mask
            while True:
                if table[h] == -1:
                    table[h] = k
                    out[n] = j
                    n += 1
                    break
                if table[h] == k:
                    break
                h = (h + 1) & mask
            if n * 2 > size:
                full = True
                break
        if not full:
            return out[:n]
        bits += 1


@njit(cache=True, nogil=True, error_model="numpy")
def _counting_order(keys, n_bins):  # pragma: no cover
    # The stable order that sorts keys in [0, n_bins).
    start = np.zeros(n_bins + 1, np.int64)
    for j in range(keys.shape[0]):
        start[keys[j] + 1] += 1
    for b in range(n_bins):
        start[b + 1] += start[b]
    order = np.empty(keys.shape[0], np.int64)
    for j in range(keys.shape[0]):
        order[start[keys[j]]] = j
        start[keys[j]] += 1
    return order


@njit(cache=True, nogil=True, error_model="numpy")
def _gather_kernel(lo, hi, starts, counts, offsets, factors, xyz_p, normals_p, colors_p,
                   spacing_p, ids_p, out_xyz, out_normals, out_colors, out_radius,
                   out_ids):  # pragma: no cover
    # Copy the chosen prefix of blocks lo..hi into the sub-cloud, the surfel
    # radius scaled by the level's factor (splat_scale included).
    for b in range(lo, hi):
        s = starts[b]
        o = offsets[b]
        f = factors[b]
        for k in range(counts[b]):
            for c in range(3):
                out_xyz[o + k, c] = xyz_p[s + k, c]
                out_normals[o + k, c] = normals_p[s + k, c]
                out_colors[o + k, c] = colors_p[s + k, c]
            out_radius[o + k] = spacing_p[s + k] * f
            out_ids[o + k] = ids_p[s + k]


class _SubCloud:
    """The points a level-of-detail render draws, with the members
    :func:`~napari_imgreg.render_points.splat_depth` reads; ``ids`` maps
    them back to the scene's point indices."""

    def __init__(self, n: int) -> None:
        self.xyz32 = np.empty((n, 3), np.float32)
        self.normals = np.empty((n, 3), np.float32)
        self.colors = np.empty((n, 3), np.uint8)
        self.radius = np.empty(n, np.float32)
        self.ids = np.empty(n, np.int32)

    def splat_radius(self, scale: float) -> np.ndarray:
        return self.radius  # scaled when gathered

    @property
    def n_points(self) -> int:
        return len(self.ids)


@dataclass
class CloudLevelOfDetail:
    """A cloud's points in blocks, each block's points coarsest level first
    (see :class:`LodParams`). Built by :meth:`build`; 35 bytes per point.

    Attributes
    ----------
    xyz32, normals : (N, 3) float32 arrays
        The points and their normals, in block order.
    colors : (N, 3) uint8 array
    spacing : (N,) float32 array
        Full-resolution spacing, metres.
    ids : (N,) int32 array
        Each point's index in the scene.
    starts : (B,) int64 array
        First point of each block.
    counts : (B, L + 1) int64 array
        Points of each block at levels 0 (all) … L (coarsest).
    centre : (B, 3) float64 array
        Centre of each block's bounding box, metres.
    half_diagonal : (B,) float64 array
        Radius of the sphere around it that holds the block, metres.
    mean_spacing : (B,) float64 array
        Mean full-resolution spacing of the block's points, metres.
    step_m : float
        The grid step of level 0 (level L's voxel is ``step_m × 2**L``).
    """

    xyz32: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    spacing: np.ndarray
    ids: np.ndarray
    starts: np.ndarray
    counts: np.ndarray
    centre: np.ndarray
    half_diagonal: np.ndarray
    mean_spacing: np.ndarray
    step_m: float

    @property
    def n_blocks(self) -> int:
        return len(self.starts)

    @property
    def n_levels(self) -> int:
        return self.counts.shape[1]

    @classmethod
    def build(cls, xyz: np.ndarray, xyz32: np.ndarray, normals: np.ndarray, colors: np.ndarray,
              spacing: np.ndarray, params: LodParams = LodParams()) -> CloudLevelOfDetail:
        """Levels and blocks of a cloud.

        Parameters
        ----------
        xyz : (N, 3) float64 array
            The points, metres.
        xyz32, normals : (N, 3) float32 arrays
        colors : (N, 3) uint8 array
        spacing : (N,) float32 array
            Local spacing (:attr:`CloudScene.spacing`), metres.
        params : LodParams
        """
        ids, starts, counts, step = cls.block_order(xyz, spacing, params)
        return cls.assemble(ids, starts, counts, step, xyz32, normals, colors, spacing)

    @staticmethod
    def block_order(xyz: np.ndarray, spacing: np.ndarray, params: LodParams = LodParams()
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """The points' order (block by block, coarsest level first), as
        ``ids``, ``starts``, ``counts`` and ``step_m`` of the attributes."""
        n = len(xyz)
        lo = xyz.min(axis=0)
        extent = xyz.max(axis=0) - lo
        step = max(float(np.median(spacing[:: max(1, n // 200_000)])) / math.sqrt(2.0), 1e-9)
        # Level of each point: the coarsest level at which it is its voxel's
        # first point in the file's order (as the reader's decimation keeps
        # the first point read: a measured point, each at about the same
        # place in its voxel, so a level is an even sampling). A level-L
        # voxel is the union of eight level-(L-1) voxels, so the levels nest.
        level = np.zeros(n, np.uint8)
        cand = np.arange(n, dtype=np.int64)
        for lev in range(1, params.max_levels + 1):
            cell = step * 2.0 ** lev
            dims = (extent / cell).astype(np.int64) + 1
            keys = np.empty(len(cand), np.int64)
            _voxel_keys(xyz, cand, lo, 1.0 / cell, dims, keys)
            first = _first_of_each(keys, len(cand) // 2 + 16)
            del keys
            cand = cand[first]
            level[cand] = lev
            if len(cand) <= 1:
                break
        del cand
        n_levels = int(level.max()) + 1
        # Blocks, and within each block the coarsest level first (stable:
        # the file's order, usually the scan's, within a level).
        block = max(step * math.sqrt(params.block_points), 1e-9)
        bdims = (extent / block).astype(np.int64) + 1
        bkey = np.empty(n, np.int64)
        _voxel_keys(xyz, np.empty(0, np.int64), lo, 1.0 / block, bdims, bkey)
        bkey *= n_levels
        bkey += (n_levels - 1) - level
        n_bins = int(np.prod(bdims)) * n_levels
        if n_bins <= 16_000_000:
            order = _counting_order(bkey, n_bins)  # O(N), stable
        else:  # a sparse, wide cloud: a sort
            order = np.argsort(bkey, kind="stable")
        bkey = bkey[order] // n_levels
        starts = np.flatnonzero(np.r_[True, bkey[1:] != bkey[:-1]])
        del bkey
        lev_sorted = level[order]
        del level
        counts = np.empty((len(starts), n_levels), np.int64)
        for lev in range(n_levels):
            counts[:, lev] = np.add.reduceat((lev_sorted >= lev).astype(np.int64), starts)
        del lev_sorted
        return order.astype(np.int32), starts.astype(np.int64), counts, step

    @classmethod
    def assemble(cls, ids: np.ndarray, starts: np.ndarray, counts: np.ndarray, step: float,
                 xyz32: np.ndarray, normals: np.ndarray, colors: np.ndarray,
                 spacing: np.ndarray) -> CloudLevelOfDetail:
        """The level of detail from an order (:meth:`block_order`, or the
        cache) and the scene's arrays."""
        xyz_p = xyz32[ids]
        lo_b = np.minimum.reduceat(xyz_p, starts, axis=0).astype(np.float64)
        hi_b = np.maximum.reduceat(xyz_p, starts, axis=0).astype(np.float64)
        spacing_p = spacing[ids]
        mean_spacing = np.add.reduceat(spacing_p.astype(np.float64), starts) / counts[:, 0]
        # Compile (or load) the gather kernel now, not in the first render.
        none = np.zeros(0, np.int64)
        _gather_kernel(0, 0, none, none, none, np.zeros(0, np.float32), xyz_p, normals[:1],
                       colors[:1], spacing_p, ids, xyz_p[:0], normals[:0], colors[:0],
                       spacing_p[:0], ids[:0])
        return cls(xyz32=xyz_p, normals=normals[ids], colors=colors[ids], spacing=spacing_p,
                   ids=ids, starts=starts, counts=counts,
                   centre=(lo_b + hi_b) / 2.0,
                   half_diagonal=np.linalg.norm(hi_b - lo_b, axis=1) / 2.0,
                   mean_spacing=mean_spacing, step_m=step)

    def sample(self, max_points: int) -> np.ndarray:
        """Scene indices of an even sample of at most ``max_points`` points
        (the finest whole level that fits; e.g. for a 3D view of the cloud).

        Returns
        -------
        (M,) int32 array
            Point indices into the scene, M ≤ ``max_points`` (at least the
            coarsest level's points).
        """
        totals = self.counts.sum(axis=0)
        fits = np.flatnonzero(totals <= max_points)
        lev = int(fits[0]) if len(fits) else self.n_levels - 1
        within = np.arange(len(self.ids)) - np.repeat(self.starts, self.counts[:, 0])
        return self.ids[within < np.repeat(self.counts[:, lev], self.counts[:, 0])]

    def choose(self, R: np.ndarray, t: np.ndarray, fov: np.ndarray, focal_px: float,
               splat_scale: float, near: float, max_radius_px: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The blocks a camera sees and the level of each.

        Parameters
        ----------
        R, t : (3, 3), (3,) arrays
            ``cam_from_world``.
        fov : (4,) array
            Field of view in normalised coordinates: x min, x max, y min, y max.
        focal_px : float
            The larger focal length, pixels.
        splat_scale : float
            Surfel radius over spacing.
        near : float
            Nearest depth drawn, metres.
        max_radius_px : float
            See :class:`LodParams`.

        Returns
        -------
        blocks : (K,) int64 array
            Indices of the blocks in view.
        level : (K,) int64 array
            The level drawn of each.
        factor : (K,) float64 array
            Its surfels' radius over their full-resolution spacing
            (``splat_scale`` included).
        """
        c = self.centre @ R.T + t
        rho = self.half_diagonal
        x, y, z = c[:, 0], c[:, 1], c[:, 2]
        keep = z + rho > near
        # Outside one of the four planes of the view's sides (through the
        # camera centre), by more than the block's radius.
        for a, comp, sign in ((fov[0], x, -1.0), (fov[1], x, 1.0), (fov[2], y, -1.0),
                              (fov[3], y, 1.0)):
            keep &= sign * (comp - a * z) / math.sqrt(1.0 + a * a) <= rho
        blocks = np.flatnonzero(keep)
        d_near = np.maximum(z[blocks] - rho[blocks], near)
        counts = self.counts[blocks]
        with np.errstate(divide="ignore"):
            thin = np.sqrt(counts[:, :1] / np.maximum(counts, 0).astype(np.float64))
        thin[counts == 0] = np.inf
        radius_px = (splat_scale * self.mean_spacing[blocks, None] * thin * focal_px
                     / d_near[:, None])
        level = np.maximum((radius_px <= max_radius_px).sum(axis=1) - 1, 0)
        factor = splat_scale * thin[np.arange(len(blocks)), level]
        return blocks, level, factor

    def subcloud(self, R: np.ndarray, t: np.ndarray, fov: np.ndarray, focal_px: float,
                 splat_scale: float, near: float, max_radius_px: float,
                 n_threads: int = 1) -> _SubCloud:
        """The points to draw for a camera (arguments of :meth:`choose`),
        gathered into contiguous arrays."""
        blocks, level, factor = self.choose(R, t, fov, focal_px, splat_scale, near,
                                            max_radius_px)
        counts = self.counts[blocks, level]
        offsets = np.zeros(len(blocks), np.int64)
        np.cumsum(counts[:-1], out=offsets[1:])
        total = int(counts.sum())
        sub = _SubCloud(total)
        args = (self.starts[blocks], counts, offsets, factor.astype(np.float32), self.xyz32,
                self.normals, self.colors, self.spacing, self.ids, sub.xyz32, sub.normals,
                sub.colors, sub.radius, sub.ids)
        k = len(blocks)
        if n_threads <= 1 or total < 500_000:
            _gather_kernel(0, k, *args)
        else:
            # Blocks split at equal shares of the points.
            cuts = np.searchsorted(offsets, np.linspace(0, total, n_threads + 1)[1:-1])
            bounds = np.r_[0, cuts, k]
            _run_blocks(_gather_kernel, k, n_threads, *args, bounds=bounds)
        return sub
