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
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numba import njit

from .camera import Intrinsics, Pose
from .errors import InputError
from .geo import dem_height_local
from .render_points import SplatParams, splat_depth, warm_up
from .validate import check_number

if TYPE_CHECKING:
    from .geo import DEM, Georef

__all__ = ["CloudParams", "CloudRayHits", "CloudScene"]

log = logging.getLogger(__name__)

_CACHE_VERSION = 1


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

    def __post_init__(self) -> None:
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
    ) -> CloudScene:
        """Load a point-cloud file (and optionally a georeference and a DEM).

        As :meth:`Scene.load`: a ``georef.json`` beside the file is used when
        ``georef`` is None. With ``cache``, the normals and spacings are read
        from (or, once computed, written to) ``<file>.imgreg-normals.npz``
        beside the file; a cache of other points or parameters is ignored.

        Raises
        ------
        InputError
            A file is missing or unreadable.
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
        cloud = read_point_cloud(path, georef=georef)
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
        """Compute normals and spacings (or take them from the cache) and
        compile the render kernels; returns the seconds it took."""
        with self._engine_lock:
            if self._engine is not None:
                return 0.0
            t0 = time.perf_counter()
            _ = self.normals
            t1 = time.perf_counter()
            # Compile (or load) the kernels now, so that the first real
            # render is not charged for it.
            warm_up()
            t_probe, id_probe = np.full(1, np.inf), np.full(1, -1, np.int64)
            _cast_brute(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), self.xyz32[:1],
                        self.normals[:1], self.splat_radius(self.params.splat.splat_scale)[:1],
                        self.params.splat.grazing_cos, t_probe, id_probe)
            self._engine = self
            self.timings_s["normals"] = t1 - t0
            self.timings_s["compile"] = time.perf_counter() - t1
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
            if normals.shape != (self.n_points, 3) or spacing.shape != (self.n_points,):
                return
        except (OSError, ValueError, KeyError) as exc:
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
                # float16 normals: 0.03° is far below the PCA's own noise.
                np.savez(tmp, fingerprint=np.array(self._fingerprint()),
                         normals=self._normals.astype(np.float16), spacing=self._spacing,
                         surface_variation=self._surface_variation.astype(np.float16))
        except OSError as exc:  # a read-only folder: compute again next time
            log.info("%s: normals cache not written (%s)", path, exc)

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
            if one_origin and m * self.n_points > self.params.max_brute_force:
                t, ids = self._cast_from_origin(o[0], d)
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
            r = np.float64(radius[i]) * gap_scale
            vx = xyz[i, 0] - ox
            vy = xyz[i, 1] - oy
            vz = xyz[i, 2] - oz
            tp = vx * dx + vy * dy + vz * dz
            if tp <= 0.0 or tp - r >= best:
                continue
            d2 = vx * vx + vy * vy + vz * vz - tp * tp
            r2 = r * r
            if d2 > r2:
                continue  # the ray passes outside the point's (wide) sphere
            nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
            den = nx * dx + ny * dy + nz * dz
            if abs(den) > grazing:
                th = (nx * vx + ny * vy + nz * vz) / den
                qx = th * dx - vx
                qy = th * dy - vy
                qz = th * dz - vz
                q2 = qx * qx + qy * qy + qz * qz
                if th <= 0.0 or q2 > r2:
                    continue
                inner = q2 * gap_scale * gap_scale <= r2
            else:
                th = tp  # edge-on: where the ray passes the point
                inner = d2 * gap_scale * gap_scale <= r2
            if inner and th < best:
                best = th
                bi = i
            if th < wide:
                wide = th
                wi = i
        if wi >= 0 and (bi < 0 or wide < best * (1.0 - gap_tol)):
            best = wide
            bi = wi
        out_t[j] = best
        out_id[j] = bi


def _cast_brute(origins, dirs, xyz, normals, radius, grazing, out_t, out_id,
                gap_scale=1.5, gap_tol=0.02) -> None:
    """:func:`_brute_kernel` over all rays, on a few threads (it releases the GIL)."""
    m = len(dirs)
    n_threads = min(_threads(), m)
    if n_threads <= 1:
        _brute_kernel(0, m, origins, dirs, xyz, normals, radius, grazing, gap_scale, gap_tol,
                      out_t, out_id)
        return
    bounds = np.linspace(0, m, n_threads + 1).astype(int)
    with ThreadPoolExecutor(n_threads) as pool:
        list(pool.map(lambda b: _brute_kernel(int(bounds[b]), int(bounds[b + 1]), origins, dirs,
                                              xyz, normals, radius, grazing, gap_scale, gap_tol,
                                              out_t, out_id),
                      range(n_threads)))
