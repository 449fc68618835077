"""Read and write lidar point clouds: LAS/LAZ, E57, vertex-only PLY, PTS/XYZ text.

A point cloud is the reference surface of a terrestrial laser scan: millions
of measured points with a laser intensity and often no colour. The readers
return one :class:`PointCloud` of plain arrays in the model frame (metres,
east-north-up), whatever the file format:

* **LAS / LAZ** through laspy (the lazrs backend decompresses LAZ), read in
  chunks so that a 50-million-point file never sits in memory as float64
  beyond the points kept; intensity and RGB (8- or 16-bit) where present;
  the CRS record is checked against ``georef.json`` (the rule below).
* **E57** through pye57: every scan of the file, each moved by its own pose
  into the file's frame, merged into one cloud; intensity and colour where
  present; invalid points (``cartesianInvalidState``) dropped.
* **PLY with vertices only** (ASCII or binary) through trimesh's PLY parser:
  ``x y z`` plus ``intensity`` / ``scalar_intensity`` (any case) and/or
  ``red green blue``. A PLY with faces is a mesh and is refused with a line
  pointing at the mesh loader.
* **PTS** (a point count line, then ``x y z intensity [r g b]``) and **XYZ**
  text (``x y z [intensity] [r g b]``, comma- or space-separated).

The CRS rule (the public contract's): a cloud whose CRS record equals the
georeference's CRS (pyproj ``CRS.equals``; a compound CRS matches on its
horizontal part) and is projected has ``georef.origin`` subtracted from its
coordinates; otherwise (no CRS record, an unreadable one, or a different one)
the coordinates are taken as the model frame and :attr:`PointCloud.notes`
says so.

Large clouds are decimated on a voxel grid to at most ``max_points`` points
(:class:`PointCloudParams`); the notes say from how many to how many and on
which voxel size. Writers (:func:`write_point_cloud`) exist for round trips
and for the benchmarks' generated scans; they write atomically.
"""

from __future__ import annotations

import contextlib
import math
import os
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .._atomic import atomic_path
from ..errors import input_error

if TYPE_CHECKING:  # annotations only: geo sits above io in the layers
    from ..geo import Georef

__all__ = [
    "BYTES_PER_KEPT_POINT",
    "DEFAULT_MAX_POINTS",
    "POINT_CLOUD_SUFFIXES",
    "PointCloud",
    "PointCloudParams",
    "is_point_cloud_file",
    "read_point_cloud",
    "write_point_cloud",
]

POINT_CLOUD_SUFFIXES = (".las", ".laz", ".e57", ".ply", ".pts", ".xyz")

#: Default cap on the points kept in memory. A kept point costs
#: :data:`BYTES_PER_KEPT_POINT` bytes (float64 xyz, float32 intensity, uint8
#: RGB), so 10 M points are ~0.3 GB of arrays. Measured while reading
#: (``benchmarks/bench_pointcloud_io.py``, docs/benchmarks.md): a LAZ read
#: whole peaks at ~48 B per point (50 M points: 2.4 GB), a 50 M-point LAZ
#: decimated to this cap at 2.1 GB; an E57 (read whole, each scan in one
#: piece by pye57) at ~100 B per point (50 M: 4.8 GB).
DEFAULT_MAX_POINTS = 10_000_000

#: Bytes of one kept point in a :class:`PointCloud` with intensity and RGB.
BYTES_PER_KEPT_POINT = 3 * 8 + 4 + 3

# Voxel keys pack three 21-bit cell indices into one int64. The voxel is never
# smaller than the cloud's largest extent / 2**20, so the cloud's bounding box
# spans at most 2**20 cells per axis and 2**19 cells of slack on each side
# absorb points a sloppy LAS header leaves outside its bounding box.
_KEY_BITS = 21
_KEY_SPAN = 2**20
_KEY_SLACK = 2**19


@dataclass
class PointCloudParams:
    """How a point cloud is read.

    Attributes
    ----------
    max_points : int or None
        At most this many points are kept (default 10 000 000, range ≥ 1;
        None: no cap). A larger cloud is decimated on a voxel grid whose
        voxel is chosen so that the result fits.
    voxel_m : float or None
        Decimate on this voxel size, metres (> 0), even below ``max_points``;
        coarsened further if the result would still exceed ``max_points``.
        Default None: no decimation below the cap.
    intensity_percentiles : (float, float)
        The raw intensities at these percentiles of the file's points are
        mapped to 0 and 1 (clipped outside); default (0.5, 99.5), so a few
        specular returns or dropouts do not flatten the rest. Range
        0 ≤ low < high ≤ 100.
    chunk_points : int
        Points decoded at a time from LAS/LAZ and text files (default
        2 000 000, range 1 000 – 50 000 000); bounds the memory used besides
        the kept points.
    """

    max_points: int | None = DEFAULT_MAX_POINTS
    voxel_m: float | None = None
    intensity_percentiles: tuple[float, float] = (0.5, 99.5)
    chunk_points: int = 2_000_000

    def __post_init__(self) -> None:
        if self.max_points is not None and (
            not isinstance(self.max_points, (int, np.integer)) or self.max_points < 1
        ):
            raise ValueError(f"max_points must be a whole number ≥ 1 or None, got {self.max_points!r}")
        if self.voxel_m is not None and not (
            isinstance(self.voxel_m, (int, float)) and math.isfinite(self.voxel_m) and self.voxel_m > 0
        ):
            raise ValueError(f"voxel_m must be a positive number of metres or None, got {self.voxel_m!r}")
        lo, hi = self.intensity_percentiles
        if not (0.0 <= lo < hi <= 100.0):
            raise ValueError(
                f"intensity_percentiles must satisfy 0 ≤ low < high ≤ 100, got {self.intensity_percentiles!r}"
            )
        if not (1_000 <= int(self.chunk_points) <= 50_000_000):
            raise ValueError(f"chunk_points must be within 1000 – 50 000 000, got {self.chunk_points!r}")


@dataclass
class PointCloud:
    """A point cloud in the model frame, with its laser intensity and colour.

    Attributes
    ----------
    xyz : (N, 3) float64 array
        Point positions, model-frame metres (east, north, up).
    intensity : (N,) float32 array or None
        Laser intensity normalised per file to [0, 1]: the file's raw
        intensity at the 0.5th percentile of its points is 0, at the 99.5th
        percentile 1, clipped outside (:class:`PointCloudParams`). After voxel
        decimation, the mean of the raw intensities of the voxel's points.
        None when the file has none (or the same value in every point).
    rgb : (N, 3) uint8 array or None
        Colour where the file has one; 16-bit colours are scaled to 8 bits.
    crs_wkt : str or None
        The file's CRS record as WKT, when it has a readable one.
    crs_epsg : int or None
        Its EPSG code, when pyproj finds one.
    origin_subtracted : (3,) float64 array or None
        The georeference origin subtracted from the file's coordinates (map
        coordinate = ``xyz + origin_subtracted``), or None when the file's
        coordinates were taken as the model frame.
    notes : list of str
        What the reader assumed or did, as sentences for the user (no CRS
        record, decimation, 8-bit colours, ...).
    source : Path or None
        The file read.
    n_points_file : int
        Points in the file (valid ones), before decimation.
    voxel_m : float or None
        The voxel size of the decimation, metres; None when every point was kept.
    intensity_range : (float, float) or None
        The raw intensities mapped to 0 and 1.
    """

    xyz: np.ndarray
    intensity: np.ndarray | None = None
    rgb: np.ndarray | None = None
    crs_wkt: str | None = None
    crs_epsg: int | None = None
    origin_subtracted: np.ndarray | None = None
    notes: list[str] = field(default_factory=list)
    source: Path | None = None
    n_points_file: int = 0
    voxel_m: float | None = None
    intensity_range: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        self.xyz = np.ascontiguousarray(self.xyz, dtype=np.float64)
        if self.xyz.ndim != 2 or self.xyz.shape[1] != 3:
            raise ValueError(f"xyz must have shape (N, 3), got {self.xyz.shape}")
        n = len(self.xyz)
        if self.intensity is not None:
            self.intensity = np.asarray(self.intensity, dtype=np.float32).reshape(-1)
            if len(self.intensity) != n:
                raise ValueError(f"intensity has {len(self.intensity)} values for {n} points")
        if self.rgb is not None:
            self.rgb = np.asarray(self.rgb, dtype=np.uint8)
            if self.rgb.shape != (n, 3):
                raise ValueError(f"rgb must have shape ({n}, 3), got {self.rgb.shape}")
        if self.origin_subtracted is not None:
            self.origin_subtracted = np.asarray(self.origin_subtracted, dtype=np.float64).reshape(3)
        if self.source is not None:
            self.source = Path(self.source)
        if not self.n_points_file:
            self.n_points_file = n

    def __len__(self) -> int:
        return len(self.xyz)

    @property
    def warnings(self) -> list[str]:
        """The notes, under :class:`~napari_imgreg.io.meshes.MeshData`'s name."""
        return self.notes

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The (3,) minimum and maximum corners of the points, metres."""
        return self.xyz.min(axis=0), self.xyz.max(axis=0)


# ---------------------------------------------------------------------------
# Reading


def is_point_cloud_file(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a point cloud by its suffix; a ``.ply`` only when
    its header declares no faces (otherwise it is a mesh for
    :func:`napari_imgreg.io.meshes.load_mesh`). Reads at most the PLY header."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in POINT_CLOUD_SUFFIXES:
        return False
    if suffix != ".ply":
        return True
    try:
        header = _ply_header(path)
    except Exception:  # an unreadable PLY is left to whichever loader opens it
        return False
    return header["counts"].get("face", 0) == 0


def read_point_cloud(
    path: str | os.PathLike,
    georef: Georef | None = None,
    max_points: int | None = DEFAULT_MAX_POINTS,
    voxel_m: float | None = None,
    params: PointCloudParams | None = None,
) -> PointCloud:
    """Read a point cloud into the model frame.

    Parameters
    ----------
    path : path-like
        ``.las``, ``.laz``, ``.e57``, ``.ply`` (vertices only), ``.pts`` or
        ``.xyz``.
    georef : Georef or None
        The scene's georeference: a cloud whose CRS record matches it has
        ``georef.origin`` subtracted (see the module docstring).
    max_points : int or None
        Cap on the points kept (decimation above it); None: no cap.
    voxel_m : float or None
        Decimate on this voxel size (metres) even below the cap.
    params : PointCloudParams or None
        All reading settings; ``max_points`` and ``voxel_m`` given here
        override the ones in it when given (``max_points`` other than the
        default, ``voxel_m`` other than None).

    Returns
    -------
    PointCloud

    Raises
    ------
    InputError
        One line naming the file and the problem: missing, unknown suffix,
        corrupt or truncated, empty, NaN coordinates, a PLY with faces.
    """
    if params is None:
        p = PointCloudParams(max_points=max_points, voxel_m=voxel_m)
    else:  # explicit arguments win over the ones in params
        p = replace(
            params,
            max_points=params.max_points if max_points == DEFAULT_MAX_POINTS else max_points,
            voxel_m=params.voxel_m if voxel_m is None else voxel_m,
        )
    path = Path(path)
    if not path.exists():
        raise input_error(path, "no such file")
    if path.is_dir():
        raise input_error(path, "is a folder, not a point cloud file")
    suffix = path.suffix.lower()
    if suffix not in POINT_CLOUD_SUFFIXES:
        raise input_error(
            path, f"not a point cloud format (expected one of {', '.join(POINT_CLOUD_SUFFIXES)})"
        )
    if path.stat().st_size == 0:
        raise input_error(path, "is empty (0 bytes)")
    reader = {
        ".las": _read_las, ".laz": _read_las, ".e57": _read_e57, ".ply": _read_ply,
        ".pts": _read_text, ".xyz": _read_text,
    }[suffix]
    try:
        cloud = reader(path, p, georef)
        if (p.voxel_m is None and p.max_points is not None and cloud.voxel_m is not None
                and len(cloud) < _REREAD_BELOW * p.max_points):
            # The voxel measured on the first points kept far fewer than the cap
            # (points not in scan order: the first ones are a thin sample of the
            # whole surface): read again on the voxel the kept count calls for,
            # still capped. The count saturates at the file's points as the voxel
            # shrinks, as N (1 - exp(-a / voxel²)) does: a (the surface's area per
            # point) from the kept count, then the voxel for 97 % of the cap.
            n_file, first = cloud.n_points_file, len(cloud)
            voxel = _finer_voxel(cloud.voxel_m, first, n_file, p.max_points)
            if voxel is not None:
                cloud = reader(path, replace(p, voxel_m=voxel), georef)
                cloud.notes.append(f"read twice: the first voxel kept only {_count(first)} "
                                   "points (the file's points are not in scan order)")
    except OSError as exc:  # permissions, a disk error, a file vanishing mid-read
        raise input_error(path, f"cannot read ({exc.strerror or _why(exc)})") from None
    except MemoryError:
        raise input_error(path, "does not fit in memory: lower max_points or give voxel_m") from None
    cloud.source = path
    return cloud


#: A decimated cloud keeping fewer than this share of the cap is read again on a finer voxel.
_REREAD_BELOW = 0.75


def _finer_voxel(voxel: float, kept: int, n_file: int, cap: int) -> float | None:
    """The voxel that keeps about 97 % of ``cap`` of a file's ``n_file`` points,
    given that ``voxel`` kept ``kept``; None when there is none to find (a
    degenerate cloud: everything kept already, or a voxel out of range)."""
    wanted = min(0.97 * cap, 0.99 * n_file)
    if not (0 < kept < wanted < n_file) or not (math.isfinite(voxel) and voxel > 0):
        return None
    try:
        area = -math.log(1.0 - kept / n_file) * voxel**2
        finer = math.sqrt(area / -math.log(1.0 - wanted / n_file))
    except (OverflowError, ValueError, ZeroDivisionError):
        return None
    return finer if math.isfinite(finer) and 0 < finer < voxel else None


# -- intensity, colour, CRS --------------------------------------------------


def _normalise_intensity(
    raw: np.ndarray, lo: float, hi: float
) -> np.ndarray:
    out = (np.asarray(raw, dtype=np.float64) - lo) / (hi - lo)
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def _intensity_limits(
    values: np.ndarray | None, hist: np.ndarray | None, p: PointCloudParams, notes: list[str]
) -> tuple[float, float] | None:
    """The raw intensities mapped to 0 and 1, from all the file's points (an
    array, or a histogram of integer intensities); None when they carry no
    information (a constant)."""
    q_lo, q_hi = p.intensity_percentiles
    if hist is not None:
        cdf = np.cumsum(hist)
        total = int(cdf[-1])
        if total == 0:
            return None
        # inverted CDF: the smallest value with at least q % of the points at or below it
        lo = float(np.searchsorted(cdf, max(1, math.ceil(q_lo / 100.0 * total))))
        hi = float(np.searchsorted(cdf, max(1, math.ceil(q_hi / 100.0 * total))))
        nz = np.flatnonzero(hist)
        vmin, vmax = float(nz[0]), float(nz[-1])
    else:
        if values is None or len(values) == 0:
            return None
        lo, hi = (float(v) for v in np.percentile(values, [q_lo, q_hi]))
        vmin, vmax = float(values.min()), float(values.max())
    if vmax <= vmin:
        notes.append(f"intensity is {_num(vmin)} in every point: no intensity used")
        return None
    if hi <= lo:
        notes.append(
            f"intensity is {_num(lo)} in nearly every point: normalised over its full range "
            f"{_num(vmin)}–{_num(vmax)} instead of its {q_lo:g}th–{q_hi:g}th percentiles"
        )
        return vmin, vmax
    return lo, hi


def _rgb_to_8bit(rgb16: np.ndarray, file_max: int, notes: list[str], what: str) -> np.ndarray:
    """Colours of a format that may hold 8- or 16-bit values (LAS says 16)."""
    if file_max <= 255:
        if file_max > 0:
            notes.append(f"{what} colours are all ≤ 255: taken as 8-bit colours")
        return rgb16.astype(np.uint8)
    return np.rint(rgb16.astype(np.float32) / 257.0).clip(0, 255).astype(np.uint8)


def _crs_label(crs) -> str:
    epsg = crs.to_epsg()
    return f"EPSG:{epsg}" if epsg else repr(crs.name)


def _apply_crs_rule(
    crs, has_record: bool, georef, xyz_lo: np.ndarray, xyz_hi: np.ndarray, notes: list[str], what: str
) -> np.ndarray | None:
    """The contract's CRS rule: the origin to subtract, or None (model frame),
    with the note that says which and why."""
    if crs is None:
        if has_record:
            notes.append(f"{what} CRS record is not one pyproj reads: coordinates taken as the model frame")
        else:
            notes.append("no CRS record: coordinates taken as the model frame")
        return None
    label = _crs_label(crs)
    if georef is None:
        notes.append(f"CRS record {label} but no georef.json: coordinates taken as the model frame")
        return None
    import pyproj

    target = pyproj.CRS.from_user_input(georef.crs)
    horizontal = crs
    if crs.is_compound and crs.sub_crs_list:
        horizontal = crs.sub_crs_list[0]
    same = crs.equals(target, ignore_axis_order=True) or (
        horizontal is not crs and horizontal.equals(target, ignore_axis_order=True)
    )
    if not same:
        notes.append(
            f"CRS record {label} differs from georef.json's {_crs_label(target)}: "
            "coordinates taken as the model frame"
        )
        return None
    if not horizontal.is_projected:
        notes.append(f"CRS record {label} is not a projected CRS: coordinates taken as the model frame")
        return None
    origin = np.asarray(georef.origin, dtype=np.float64)
    if horizontal is not crs:
        notes.append(f"CRS record {label}: its horizontal CRS matches georef.json; heights taken as georef.json's")
    notes.append(f"CRS record {label} matches georef.json: its origin {_xyz(origin)} subtracted")
    far = np.maximum(np.abs(xyz_lo - origin), np.abs(xyz_hi - origin)).max()
    if far > 100_000:
        notes.append(
            f"after subtracting georef.json's origin the points are still up to {far / 1000:.0f} km from it: "
            "check the origin"
        )
    return origin


def _refuse_degrees(path: Path, crs, lo: np.ndarray, hi: np.ndarray, georef) -> None:
    """Refuse a cloud whose CRS record is geographic and whose x, y are degrees.

    Taken as the model frame, a 200 m outcrop would be 0.003 units wide with
    heights in metres: nothing a camera could be registered to. Reprojecting
    is the user's step (PDAL, CloudCompare), as it is for a mesh.

    Parameters
    ----------
    path : Path
        The file, for the message.
    crs : pyproj.CRS or None
        The file's CRS record.
    lo, hi : ndarray, shape (3,)
        The points' bounding box in the file's coordinates.
    georef : Georef or None
        Named in the message as the CRS to reproject to.

    Raises
    ------
    InputError
        The record is geographic (or compound on a geographic one) and x, y
        lie within ±180°, ±90° (a record that lies about metres is left to
        the CRS rule).
    """
    if crs is None:
        return
    horizontal = crs.sub_crs_list[0] if crs.is_compound and crs.sub_crs_list else crs
    if not horizontal.is_geographic:
        return
    if not (max(abs(lo[0]), abs(hi[0])) <= 180.0 and max(abs(lo[1]), abs(hi[1])) <= 90.0):
        return
    target = f"georef.json's {georef.crs}" if georef is not None else "a projected CRS such as UTM"
    raise input_error(
        path, f"coordinates are longitude/latitude in degrees (CRS record {_crs_label(crs)}, geographic), "
              f"not metres: reproject the cloud to {target} first (e.g. with PDAL or CloudCompare)")


def _map_like_note(lo: np.ndarray, hi: np.ndarray, notes: list[str], crs=None) -> None:
    reach = float(np.maximum(np.abs(lo), np.abs(hi)).max())
    if reach > 100_000:
        centre = np.round((np.asarray(lo) + np.asarray(hi)) / 2.0, -2)
        if crs is not None and getattr(crs, "is_projected", False):
            # The file says everything a georef.json needs: say what to write.
            code = crs.to_epsg()
            name = f"EPSG:{code}" if code else "<its CRS>"
            fix = (f"write a georef.json beside it, e.g. {{\"crs\": \"{name}\", \"origin\": "
                   f"[{centre[0]:.0f}, {centre[1]:.0f}, 0]}}")
        else:
            fix = "subtract georef.json's origin, or give the file a matching CRS record"
        notes.append(
            f"coordinates reach {reach:,.0f} m from 0: they look like map coordinates but are used as the "
            f"model frame, where a camera is unlikely to see them ({fix})"
        )


# -- the accumulator: every point, or one per voxel --------------------------


class _Accumulator:
    """Collects the points of a file, chunk by chunk (in file order): all of
    them when they fit, otherwise one per voxel.

    Voxel mode keeps, per occupied voxel, the first point read (a measured
    point, not a centroid), its colour, and the sum and count of the raw
    intensities of every point that fell in it. After the voxel grew, a
    voxel keeps the first of the points kept until then, and the sums of the
    points they stood for. Each chunk is merged on its
    own; the chunks' candidates are merged with the kept set when they
    outnumber it (or the cap), which bounds the memory to about twice the cap.
    When the merged set exceeds the cap the voxel grows by
    ``1.02 sqrt(count / cap)`` (at least 1.03×; a scan is a surface, so the
    voxel count falls with the voxel's area) and the survivors are merged
    again.
    """

    def __init__(self, n_total: int, lo: np.ndarray, hi: np.ndarray, p: PointCloudParams,
                 has_intensity: bool, has_rgb: bool, rgb_dtype=np.uint16, preallocate: bool = True):
        self.n_total = int(n_total)
        self.cap = p.max_points
        self.has_i, self.has_rgb = has_intensity, has_rgb
        self.lo = np.asarray(lo, dtype=np.float64)
        self.hi = np.asarray(hi, dtype=np.float64)
        extent = np.maximum(self.hi - self.lo, 0.0)
        self.min_voxel = max(float(extent.max()) / _KEY_SPAN, 1e-6)
        self.voxel: float | None = None
        self.decimating = p.voxel_m is not None or (self.cap is not None and self.n_total > self.cap)
        if p.voxel_m is not None:
            self.voxel = max(float(p.voxel_m), self.min_voxel)
        # else: chosen from the first chunk (_estimate_voxel)
        self.n_read = 0
        self.n_clipped = 0
        if not self.decimating and preallocate:
            self.xyz = np.empty((self.n_total, 3), np.float64)
            self.inten = np.empty(self.n_total, np.float32) if has_intensity else None
            self.rgb = np.empty((self.n_total, 3), rgb_dtype) if has_rgb else None
        elif self.decimating:
            self.parts: list[tuple] = []
            self.n_pending = 0
            self.kept: tuple | None = None

    def _estimate_voxel(self, xyz: np.ndarray) -> float:
        """The voxel that keeps about ``cap / n_total`` of the points, measured
        on the first chunk: the share of occupied voxels among a contiguous run
        of up to 300 000 points (full density: files list points in scan
        order). On a surface the share falls with the voxel's area, so each
        step scales the voxel by ``sqrt(share / target)``."""
        target = self.cap / self.n_total
        sample = xyz[:300_000]
        if len(sample) < self.n_total and self._spans_the_file(sample):
            return self._estimate_voxel_from_spread(sample)
        origin = sample.min(axis=0)

        def share(voxel: float) -> float:
            cells = np.floor((sample - origin) / voxel).astype(np.int64)
            span = cells.max(axis=0) + 1
            keys = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
            return len(np.unique(keys)) / len(sample)

        ex = np.sort(np.maximum(sample.max(axis=0) - origin, 1e-3))
        voxel = max(math.sqrt(ex[1] * ex[2] / max(1.0, target * len(sample))), self.min_voxel)
        # aim 3 % under the cap: the merges then rarely need to coarsen
        aim = 0.97 * target
        for _ in range(8):
            got = share(voxel)
            if abs(got / aim - 1.0) < 0.02:
                break
            voxel = max(voxel * min(4.0, max(0.25, math.sqrt(got / aim))), self.min_voxel)
        return voxel

    def _spans_the_file(self, sample: np.ndarray) -> bool:
        """Whether the first points are spread over the whole file (a shuffled,
        thinned or merged export), not a contiguous patch of a scan: their box
        covers at least 80 % of the header's along every axis the file spans."""
        extent = self.hi - self.lo
        spread = sample.max(axis=0) - sample.min(axis=0)
        axes = extent > 1e-6
        return bool(axes.any() and (spread[axes] >= 0.8 * extent[axes]).all())

    def _estimate_voxel_from_spread(self, sample: np.ndarray) -> float:
        """The voxel that keeps about ``0.97 cap`` voxels of the whole file, from
        first points spread over it (a sample of every part at a lower density).

        The sample's occupied voxels are counted where it is dense enough to
        fill them (about 8 and 32 points per voxel); their ratio gives the
        surface's dimension D (2 for a plane, more for rough rock), and the
        whole file's count at a finer voxel follows ``count ∝ voxel^-D``.
        (The patch estimate would take the sample's low density for the file's
        and keep ~14× too few points of a shuffled 12 M scan.)
        """
        origin = sample.min(axis=0)

        def count(voxel: float) -> int:
            cells = np.floor((sample - origin) / voxel).astype(np.int64)
            span = cells.max(axis=0) + 1
            return len(np.unique((cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]))

        ex = np.sort(np.maximum(sample.max(axis=0) - origin, 1e-3))
        v1 = math.sqrt(ex[1] * ex[2] * 8.0 / len(sample))  # ~8 sample points per voxel
        for _ in range(8):  # coarser until the voxels hold ~8 points each
            c1 = count(v1)
            if len(sample) / c1 >= 8.0:
                break
            v1 *= 1.4
        c2 = count(2.0 * v1)
        dim = min(3.0, max(1.5, math.log2(c1 / max(c2, 1))))
        aim = 0.97 * self.cap
        voxel = v1 * (c1 / aim) ** (1.0 / dim) if c1 < aim else v1
        return max(voxel, self.min_voxel)

    def add(self, xyz: np.ndarray, inten: np.ndarray | None, rgb: np.ndarray | None) -> None:
        n = len(xyz)
        if not self.decimating:
            end = self.n_read + n
            if end > self.n_total:
                raise ValueError(f"holds more points than its header declares ({self.n_total})")
            self.xyz[self.n_read:end] = xyz
            if self.inten is not None:
                self.inten[self.n_read:end] = inten
            if self.rgb is not None:
                self.rgb[self.n_read:end] = rgb
            self.n_read = end
            return
        if self.voxel is None:
            self.voxel = self._estimate_voxel(xyz)
        self.n_read += n
        isum = np.asarray(inten, dtype=np.float64) if self.has_i else None
        cnt = np.ones(n, np.float64)
        part = self._merge((self._keys(xyz, count_clipped=True), xyz, isum, cnt, rgb))
        self.parts.append(part)
        self.n_pending += len(part[0])
        # merge when the candidates outgrow the kept set (amortised) or the cap
        if self.n_pending > max(self.cap or 0, 0 if self.kept is None else len(self.kept[0]), 1_000_000):
            self._compact()

    def _keys(self, xyz: np.ndarray, count_clipped: bool = False) -> np.ndarray:
        cells = np.floor((xyz - self.lo) / self.voxel).astype(np.int64) + _KEY_SLACK
        bad = (cells < 0) | (cells >= 2**_KEY_BITS)
        if bad.any():
            if count_clipped:
                self.n_clipped += int(bad.any(axis=1).sum())
            np.clip(cells, 0, 2**_KEY_BITS - 1, out=cells)
        return (cells[:, 0] << (2 * _KEY_BITS)) | (cells[:, 1] << _KEY_BITS) | cells[:, 2]

    @staticmethod
    def _merge(arrays: tuple) -> tuple:
        """One entry per key: the first in order; intensity sums and counts added."""
        keys, xyz, isum, cnt, rgb = arrays
        order = np.argsort(keys, kind="stable")
        ks = keys[order]
        first = np.empty(len(ks), bool)
        first[:1] = True
        np.not_equal(ks[1:], ks[:-1], out=first[1:])
        starts = np.flatnonzero(first)
        sel = order[starts]
        cnt_out = np.add.reduceat(cnt[order], starts)
        isum_out = np.add.reduceat(isum[order], starts) if isum is not None else None
        # back to file order, so that "first" stays first at the next merge
        back = np.argsort(sel, kind="stable")
        sel = sel[back]
        return (keys[sel], xyz[sel], None if isum_out is None else isum_out[back], cnt_out[back],
                None if rgb is None else rgb[sel])

    def _compact(self) -> None:
        parts = ([self.kept] if self.kept is not None else []) + self.parts
        self.parts, self.n_pending = [], 0
        if not parts:
            return
        cat = tuple(
            None if parts[0][i] is None else np.concatenate([q[i] for q in parts]) for i in range(5)
        )
        self.kept = self._merge(cat)
        while self.cap is not None and len(self.kept[0]) > self.cap:
            factor = max(1.03, 1.02 * math.sqrt(len(self.kept[0]) / self.cap))
            self.voxel *= factor
            self.kept = self._merge((self._keys(self.kept[1]),) + self.kept[1:])

    def finish(self):
        """xyz, raw intensity (mean per voxel), rgb of the kept points."""
        if not self.decimating:
            n = self.n_read
            return (self.xyz[:n], None if self.inten is None else self.inten[:n],
                    None if self.rgb is None else self.rgb[:n])
        self._compact()
        if self.kept is None:
            return np.empty((0, 3)), None, None
        _, xyz, isum, cnt, rgb = self.kept
        inten = None if isum is None else (isum / cnt).astype(np.float32)
        return xyz, inten, rgb


def _decimation_note(acc: _Accumulator, n_kept: int, notes: list[str]) -> None:
    if not acc.decimating:
        return
    notes.append(
        f"decimated {_count(acc.n_read)} → {_count(n_kept)} points on a {_length(acc.voxel)} voxel grid "
        "(one measured point per voxel, the first read; intensity averaged over the voxel)"
    )
    if acc.n_clipped:
        notes.append(f"{_count(acc.n_clipped)} points lie far outside the file's bounding box")


def _finish_cloud(
    acc: _Accumulator, path: Path, p: PointCloudParams, notes: list[str], *,
    intensity_limits: tuple[float, float] | None, rgb_max: int | None, rgb_what: str,
    crs=None, crs_record: bool = False, georef=None, apply_crs: bool = True,
) -> PointCloud:
    xyz, inten_raw, rgb_raw = acc.finish()
    if len(xyz) == 0:
        raise input_error(path, "holds no points (empty cloud)")
    _decimation_note(acc, len(xyz), notes)
    intensity = None
    if inten_raw is not None and intensity_limits is not None:
        intensity = _normalise_intensity(inten_raw, *intensity_limits)
    rgb = None
    if rgb_raw is not None:
        rgb = rgb_raw if rgb_raw.dtype == np.uint8 else _rgb_to_8bit(rgb_raw, int(rgb_max or 0), notes, rgb_what)
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    if len(xyz) > 1 and np.array_equal(lo, hi):
        raise input_error(path, f"all {_count(len(xyz))} points lie at one position {_xyz(lo)}: no surface")
    keep = _not_stacked(xyz, notes)
    if keep is not None:
        xyz = xyz[keep]
        intensity = None if intensity is None else intensity[keep]
        rgb = None if rgb is None else rgb[keep]
        lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    _refuse_degrees(path, crs, lo, hi, georef)
    origin = None
    if apply_crs:
        origin = _apply_crs_rule(crs, crs_record, georef, lo, hi, notes, rgb_what)
    if origin is not None:
        xyz -= origin
    else:
        _map_like_note(lo, hi, notes, crs)
    return PointCloud(
        xyz=xyz, intensity=intensity, rgb=rgb,
        crs_wkt=None if crs is None else crs.to_wkt(),
        crs_epsg=None if crs is None else crs.to_epsg(),
        origin_subtracted=origin, notes=notes, source=path, n_points_file=acc.n_read,
        voxel_m=acc.voxel, intensity_range=intensity_limits,
    )


#: A position shared by more points than this is no surface: a scanner's
#: missed returns written at one place (often 0, 0, 0). A scan quantised
#: coarsely (1 cm) close to its scanner puts tens of points on one position;
#: over a thousand, the normals' neighbour search grows with the square of
#: their number (100,000 took 25 s more to load), and their splats draw one
#: blot in every render.
STACKED_POINTS_MAX = 1000


def _not_stacked(xyz: np.ndarray, notes: list[str]) -> np.ndarray | None:
    """The points not stacked on a position shared by more than
    :data:`STACKED_POINTS_MAX` points, as a mask; None when there are none
    (the usual case, found in one pass over a hash of the coordinates).

    Parameters
    ----------
    xyz : (N, 3) float64 array
    notes : list of str
        Gets a line saying how many points were left out, and where.
    """
    n = len(xyz)
    if n <= STACKED_POINTS_MAX:
        return None
    bits = np.ascontiguousarray(xyz, dtype=np.float64).view(np.uint64).reshape(n, 3)
    # Equal positions hash alike; a bucket holding over the limit is checked exactly.
    hashed = (bits[:, 0] * np.uint64(0x9E3779B97F4A7C15)
              ^ bits[:, 1] * np.uint64(0xC2B2AE3D27D4EB4F)
              ^ bits[:, 2] * np.uint64(0x165667B19E3779F9))
    table = min(2 * n + 1, 1 << 24) | 1
    bucket = (hashed % np.uint64(table)).astype(np.int64)
    heavy = np.flatnonzero(np.bincount(bucket, minlength=table) > STACKED_POINTS_MAX)
    if not heavy.size:
        return None
    candidates = np.flatnonzero(np.isin(bucket, heavy))
    positions, inverse, counts = np.unique(xyz[candidates], axis=0, return_inverse=True,
                                           return_counts=True)
    stacked = candidates[counts[inverse.ravel()] > STACKED_POINTS_MAX]
    if not stacked.size:
        return None
    keep = np.ones(n, bool)
    keep[stacked] = False
    where = positions[counts > STACKED_POINTS_MAX]
    notes.append(f"{_count(len(stacked))} points stacked on {len(where)} position(s) (e.g. "
                 f"{_xyz(where[0])}, more than {STACKED_POINTS_MAX} each): a scanner's missed "
                 "returns, left out")
    return keep

def _check_finite(path: Path, xyz: np.ndarray) -> None:
    if not np.isfinite(xyz).all():
        raise input_error(path, "has points with NaN or infinite coordinates")


# -- LAS / LAZ ---------------------------------------------------------------


def _read_las(path: Path, p: PointCloudParams, georef) -> PointCloud:
    kind = "LAZ" if path.suffix.lower() == ".laz" else "LAS"
    try:
        return _read_las_checked(path, p, georef, kind)
    except (Exception, KeyboardInterrupt, SystemExit, GeneratorExit):
        raise
    except BaseException as exc:  # noqa: BLE001 - lazrs's pyo3_runtime.PanicException
        # A Rust panic in lazrs (a corrupt LAZ chunk) arrives as a
        # BaseException that no ``except Exception`` above catches.
        problem = f"cannot read {kind} (the decoder failed: {_why(exc)}; truncated or corrupt?)"
        raise input_error(path, problem) from None


def _read_las_checked(path: Path, p: PointCloudParams, georef, kind: str) -> PointCloud:
    import laspy

    notes: list[str] = []
    _check_las_header(path, kind)
    _check_laz_sizes(path)
    try:
        # One decompression thread: the machine's other cores belong to the
        # renders and registrations running beside the reader.
        reader = laspy.open(path, laz_backend=laspy.LazBackend.Lazrs)
    except Exception as exc:  # laspy/lazrs raise many types for a bad file
        raise input_error(path, f"cannot read {kind} ({_why(exc)})") from None
    with reader:
        header = reader.header
        n = int(header.point_count)
        if n == 0:
            raise input_error(path, "holds no points (empty cloud)")
        lo, hi = np.asarray(header.mins, float), np.asarray(header.maxs, float)
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()) or (hi < lo).any():
            raise input_error(path, "has an invalid bounding box in its header (corrupt header)")
        coarsest = float(np.max(np.abs(header.scales)))
        if coarsest > _LAS_COARSE_SCALE_M:
            notes.append(f"coordinates stored to {_length(coarsest)} (its header's scale factors "
                         f"{', '.join(f'{v:g}' for v in header.scales)}): detail finer than that is lost")
        dims = set(header.point_format.dimension_names)
        has_rgb = {"red", "green", "blue"} <= dims
        try:
            crs = header.parse_crs()
        except Exception:  # a CRS record pyproj cannot parse
            crs = None
        _refuse_degrees(path, crs, lo, hi, georef)  # from the header: before minutes of decoding
        crs_record = any(v.user_id == "LASF_Projection" for v in header.vlrs) or bool(
            header.evlrs and any(v.user_id == "LASF_Projection" for v in header.evlrs)
        )
        acc = _Accumulator(n, lo, hi, p, has_intensity=True, has_rgb=has_rgb)
        hist = np.zeros(65536, np.int64)
        rgb_max = 0
        try:
            for chunk in reader.chunk_iterator(p.chunk_points):
                m = len(chunk)
                if m == 0:
                    break
                xyz = np.empty((m, 3), np.float64)
                xyz[:, 0], xyz[:, 1], xyz[:, 2] = chunk.x, chunk.y, chunk.z
                _check_finite(path, xyz)
                inten = np.asarray(chunk.intensity)
                hist += np.bincount(inten, minlength=65536)
                rgb = None
                if has_rgb:
                    rgb = np.stack([np.asarray(chunk.red), np.asarray(chunk.green), np.asarray(chunk.blue)], 1)
                    rgb_max = max(rgb_max, int(rgb.max()))
                acc.add(xyz, inten, rgb)
                del xyz, inten, rgb, chunk
        except Exception as exc:
            if getattr(exc, "args", None) and str(exc).startswith(f"{os.fspath(path)}:"):
                raise
            raise input_error(path, f"cannot read {kind} points ({_why(exc)}; truncated or corrupt?)") from None
        if acc.n_read < n:
            raise input_error(
                path, f"holds {acc.n_read} of the {n} points its header declares (truncated)"
            )
    limits = _intensity_limits(None, hist, p, notes)
    return _finish_cloud(
        acc, path, p, notes, intensity_limits=limits, rgb_max=rgb_max, rgb_what=kind,
        crs=crs, crs_record=crs_record, georef=georef,
    )


#: The fixed part of the LAS public header block, bytes, by minor version
#: (what laspy reads before the VLRs; LAS 1.5 adds the GPS time range).
_LAS_FIXED_HEADER = {0: 227, 1: 227, 2: 227, 3: 235, 4: 375}
#: Scale factors coarser than this (1 cm, what airborne LAS files use) round a
#: terrestrial scan's millimetre-to-centimetre detail away: a note says so.
_LAS_COARSE_SCALE_M = 0.01
_LAS_VLR_HEADER = 54  # bytes of a VLR's header
_LAS_EVLR_HEADER = 60  # bytes of an extended VLR's header
#: A compressed point takes at least ~1 byte (LASzip's arithmetic coder on
#: real scans: 5–15 bytes), so a LAZ declaring more points than this many per
#: byte of its point data cannot hold them; lazrs would decode garbage for
#: as long as the count lasts.
_LAZ_MAX_POINTS_PER_BYTE = 64


def _check_las_header(path: Path, kind: str) -> None:
    """Check the sizes the LAS public header declares against the file's size
    before laspy reads it.

    laspy trusts them: it reads as many VLRs as the header counts (hours for
    2**32 − 1 of them), everything up to the offset to the point data in one
    read, each extended VLR's declared length in one allocation, and the
    point records the count and record length add up to. Each is refused
    here with one line naming the header field. A file that is not LAS at
    all is left to laspy, which names the problem.
    """
    import struct

    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(_LAS_FIXED_HEADER[4])
        if len(head) < _LAS_FIXED_HEADER[0] or head[:4] != b"LASF":
            return
        minor = head[25]
        header_size, offset, n_vlrs = struct.unpack_from("<HII", head, 94)
        point_format, record_length = head[104], struct.unpack_from("<H", head, 105)[0]

        def bad(problem: str) -> None:
            raise input_error(path, f"cannot read {kind} ({problem}: truncated or corrupt)")

        if offset > size:
            bad(f"its header's offset to the point data, {offset}, lies beyond the file's {size} bytes")
        scales = struct.unpack_from("<3d", head, 131)  # x, y, z scale factors (every LAS version)
        if not all(math.isfinite(v) and v != 0.0 for v in scales):
            # 0 puts every point on the offset: a cloud of one position, whose
            # normals cost n² (hours), not a surface.
            raise input_error(path, f"cannot read {kind} (its header's scale factors are "
                                    f"{', '.join(f'{v:g}' for v in scales)}: each must be a finite "
                                    "number other than 0; corrupt header)")
        fixed = _LAS_FIXED_HEADER.get(minor, _LAS_FIXED_HEADER[4] + 18)
        if header_size < fixed:
            bad(f"its header size, {header_size} bytes, is smaller than LAS 1.{minor}'s {fixed}")
        if offset < header_size:
            bad(f"its header's offset to the point data, {offset}, lies inside its {header_size}-byte header")
        if n_vlrs * _LAS_VLR_HEADER > offset - header_size:
            bad(f"its header's number of VLRs, {n_vlrs}, does not fit in the {offset - header_size} bytes "
                "between the header and the point data")
        if minor >= 4:
            evlr_start, n_evlrs, count = struct.unpack_from("<QIQ", head, 235)
        else:
            evlr_start, n_evlrs, count = 0, 0, struct.unpack_from("<I", head, 107)[0]
        compressed = bool(point_format & 0x80) and not point_format & 0x40  # laspy's rule
        room = size - offset
        if not compressed and count * record_length > room:
            bad(f"its header's point count {count} × record length {record_length} is "
                f"{count * record_length} bytes, but {room} bytes follow the offset to the point data")
        if compressed and count > _LAZ_MAX_POINTS_PER_BYTE * room:
            bad(f"its header's point count {count} is more than {room} bytes of compressed points can hold")
        if n_evlrs:
            if evlr_start + _LAS_EVLR_HEADER * n_evlrs > size:
                bad(f"its header's {n_evlrs} EVLRs from byte {evlr_start} do not fit in the file's {size} bytes")
            at = evlr_start
            for i in range(n_evlrs):  # each takes ≥ 60 bytes: at most size / 60 rounds
                fh.seek(at)
                evlr = fh.read(_LAS_EVLR_HEADER)
                if len(evlr) < _LAS_EVLR_HEADER:
                    bad(f"its EVLR {i + 1} of {n_evlrs}, at byte {at}, is cut short")
                length = struct.unpack_from("<Q", evlr, 20)[0]
                if at + _LAS_EVLR_HEADER + length > size:
                    bad(f"its EVLR {i + 1} of {n_evlrs}, at byte {at}, declares {length} bytes, "
                        "beyond the file's end")
                at += _LAS_EVLR_HEADER + length


# LASzip item types of the layered (LAS 1.4, point formats 6–10) compression
# and the number of layers each writes per chunk (Byte14: one per extra byte).
_LAZ_LAYERS = {10: 9, 11: 1, 12: 2, 13: 1}
_LAZ_BYTE14 = 14


def _check_laz_sizes(path: Path) -> None:
    """Check the sizes a compressed LAS file declares before lazrs reads it.

    lazrs allocates what the file's chunk table and chunk headers declare,
    and a failed allocation aborts the whole process (Rust), so a corrupt LAZ
    would take napari down. The chunk table's version, the chunk count, the
    points the chunks hold (at least the header's count), the chunk byte
    counts and the layer sizes of the layered formats are therefore checked
    against the header and the file's size first; a LAS that is not
    compressed is left to laspy.
    """
    import struct

    size = path.stat().st_size

    def bad(problem: str) -> None:
        raise input_error(path, f"cannot read LAZ ({problem}: truncated or corrupt)")

    with open(path, "rb") as fh:
        head = fh.read(375)
        if len(head) < 227 or head[:4] != b"LASF":
            return  # laspy names the problem
        header_size, offset, n_vlrs = struct.unpack_from("<HII", head, 94)
        point_format, point_size = head[104], struct.unpack_from("<H", head, 105)[0]
        if not point_format & 0x80:  # LASzip sets bit 7 of the point format
            return
        if not (header_size <= offset <= size - 8):
            bad("its point data starts outside the file")
        fh.seek(header_size)
        record = None
        for _ in range(min(n_vlrs, 1000)):
            vlr = fh.read(54)
            if len(vlr) < 54:
                break
            user_id = vlr[2:18].split(b"\0")[0]  # as laspy reads it: up to the first NUL
            record_id, length = struct.unpack_from("<HH", vlr, 18)
            if user_id == b"laszip encoded" and record_id == 22204:
                record = fh.read(length)
                break
            fh.seek(length, os.SEEK_CUR)
        if record is None or len(record) < 34:
            return  # laspy names the missing LASzip record
        items = [struct.unpack_from("<HH", record, 34 + 6 * i)
                 for i in range(min(struct.unpack_from("<H", record, 32)[0], (len(record) - 34) // 6))]
        fh.seek(offset)
        table_at = struct.unpack("<q", fh.read(8))[0]
        if table_at == -1:  # written without seeking back: the offset closes the file
            fh.seek(size - 8)
            table_at = struct.unpack("<q", fh.read(8))[0]
        if not (offset + 8 <= table_at <= size - 8):
            bad("its chunk table lies outside the file")
        fh.seek(table_at)
        version, n_chunks = struct.unpack("<II", fh.read(8))
        if version != 0:  # LASzip's chunk table has version 0
            bad(f"its chunk table has version {version}")
        if n_chunks > (table_at - offset):  # every chunk takes at least one byte
            bad(f"it declares {n_chunks} chunks in {table_at - offset} bytes")
        import lazrs

        fh.seek(offset)
        try:
            table = lazrs.read_chunk_table(fh, lazrs.LazVlr(record))
        except Exception as exc:  # lazrs raises its own error type
            bad(f"unreadable chunk table, {_why(exc)}")
        if table is None or sum(int(b) for _, b in table) > table_at - offset - 8:
            bad("its chunks are larger than the file")
        # The decompressor reads the chunks in order whatever the table says:
        # a table that accounts for fewer points than the header (a moved or
        # overwritten table) would leave chunks whose sizes nobody checked.
        n_points = struct.unpack_from("<I", head, 107)[0]
        if not n_points and header_size >= 375:  # LAS 1.4: the 64-bit count
            n_points = struct.unpack_from("<Q", head, 247)[0]
        held = sum(int(n) for n, _ in table)
        if held < n_points:
            bad(f"its chunk table holds {held} of its {n_points} points")
        n_layers = sum(_LAZ_LAYERS.get(t, 0) if t != _LAZ_BYTE14 else s for t, s in items)
        if not n_layers:
            return
        start = offset + 8
        fixed = point_size + 4 + 4 * n_layers  # raw first point, point count, layer sizes
        for _points, byte_count in table:
            fh.seek(start)
            chunk = fh.read(fixed)
            if len(chunk) < fixed:
                bad("a chunk is cut short")
            layers = struct.unpack_from(f"<{n_layers}I", chunk, point_size + 4)
            if sum(layers) > byte_count - fixed:
                bad("a chunk declares layers larger than itself")
            start += int(byte_count)


# -- E57 ---------------------------------------------------------------------


def _read_e57(path: Path, p: PointCloudParams, georef) -> PointCloud:
    try:
        import pye57
    except ImportError:  # not installed on Intel Macs (no wheel; see pyproject.toml)
        raise input_error(path, "reading E57 needs pye57, which is not installed (it has no "
                                "wheel for this system): convert the scan to LAZ (CloudCompare, "
                                "PDAL) or pip install pye57 (builds with Xerces-C)") from None

    notes: list[str] = []
    _check_e57_header(path)
    with _quiet_stderr():
        return _read_e57_scans(path, p, georef, notes, pye57)


def _read_e57_scans(path: Path, p: PointCloudParams, georef, notes: list[str], pye57) -> PointCloud:
    try:
        e57 = pye57.E57(str(path))
    except Exception as exc:
        raise input_error(path, f"cannot read E57 ({_why(exc)})") from None
    try:
        n_scans = e57.scan_count
        if n_scans == 0:
            raise input_error(path, "holds no scans (empty cloud)")
        scans = []
        with_i = with_rgb = 0
        for index in range(n_scans):
            fields = set(e57.get_header(index).point_fields)
            with_i += "intensity" in fields
            with_rgb += {"colorRed", "colorGreen", "colorBlue"} <= fields
        # one cloud has intensity (colour) in every point or in none
        any_i, any_rgb = with_i == n_scans, with_rgb == n_scans
        if 0 < with_i < n_scans:
            notes.append(f"intensity in {with_i} of {n_scans} scans only: no intensity used")
        if 0 < with_rgb < n_scans:
            notes.append(f"colour in {with_rgb} of {n_scans} scans only: no colour used")
        for index in range(n_scans):
            if e57.get_header(index).point_count == 0:
                # libE57 fails on an empty scan's binary section: skip it, and an
                # all-empty file is refused below as one with no points.
                notes.append(f"scan {index + 1} of {n_scans} holds no points: skipped")
                continue
            try:
                data = e57.read_scan(index, intensity=any_i, colors=any_rgb, transform=True,
                                     ignore_missing_fields=True)
            except Exception as exc:
                if not any_rgb:
                    raise
                # 16-bit E57 colours do not fit pye57's 8-bit buffers
                notes.append(f"colours not read ({_why(exc)})")
                any_rgb = False
                data = e57.read_scan(index, intensity=any_i, colors=False, transform=True,
                                     ignore_missing_fields=True)
            xyz = np.column_stack([data["cartesianX"], data["cartesianY"], data["cartesianZ"]])
            _check_finite(path, xyz)
            inten = np.asarray(data["intensity"], np.float32) if any_i else None
            rgb = (np.column_stack([data["colorRed"], data["colorGreen"], data["colorBlue"]]).astype(np.uint8)
                   if any_rgb else None)
            scans.append((xyz, inten, rgb))
        try:
            crs_text = str(e57.root["coordinateMetadata"].value()) if e57.root.isDefined("coordinateMetadata") else ""
        except Exception:
            crs_text = ""
    except Exception as exc:
        if str(exc).startswith(f"{os.fspath(path)}:"):
            raise
        raise input_error(path, f"cannot read E57 points ({_why(exc)}; truncated or corrupt?)") from None
    finally:
        e57.close()
    if len(scans) > 1:
        notes.append(f"{len(scans)} scans merged, each moved by its own pose")
    xyz = np.concatenate([s[0] for s in scans]) if scans else np.empty((0, 3))
    inten = np.concatenate([s[1] for s in scans]) if any_i and scans else None
    rgb = np.concatenate([s[2] for s in scans]) if any_rgb and scans else None
    del scans
    crs = None
    if crs_text.strip():
        import pyproj

        try:
            crs = pyproj.CRS.from_user_input(crs_text)
        except Exception:
            crs = None
    return _cloud_from_arrays(path, p, georef, notes, xyz, inten, rgb, rgb_what="E57",
                              crs=crs, crs_record=bool(crs_text.strip()))


def _check_e57_header(path: Path) -> None:
    """The E57 physical header (ASTM E2807 §8): the signature and the file
    length it records, so that garbage and truncated files get one line
    before libE57 is asked (which prints its own report on failure)."""
    with open(path, "rb") as fh:
        head = fh.read(48)
    if len(head) < 48 or head[:8] != b"ASTM-E57":
        raise input_error(path, "cannot read E57 (no ASTM-E57 signature: not an E57 file, or corrupt)")
    recorded = int.from_bytes(head[16:24], "little")
    actual = path.stat().st_size
    if recorded != actual:
        raise input_error(
            path, f"cannot read E57: {actual} bytes where its header records {recorded} (truncated or corrupt)"
        )


@contextlib.contextmanager
def _quiet_stderr() -> Iterator[None]:
    """Silence file descriptor 2 while libE57 runs: its C++ layer prints a
    multi-line report for every exception, which pye57 then raises (and we
    turn into one line). Output of other threads in that window is lost."""
    try:
        saved = os.dup(2)
    except OSError:
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _cloud_from_arrays(path, p, georef, notes, xyz, inten, rgb, *, rgb_what, crs=None, crs_record=False,
                       apply_crs=True) -> PointCloud:
    """Normalise, decimate and place arrays read whole."""
    if len(xyz) == 0:
        raise input_error(path, "holds no points (empty cloud)")
    _check_finite(path, xyz)
    if inten is not None and not np.isfinite(inten).all():
        raise input_error(path, "has NaN or infinite intensities")
    limits = _intensity_limits(inten, None, p, notes) if inten is not None else None
    rgb_max = None
    if rgb is not None and rgb.dtype != np.uint8:
        rgb_max = int(rgb.max())
    acc = _Accumulator(len(xyz), xyz.min(axis=0), xyz.max(axis=0), p, has_intensity=inten is not None,
                       has_rgb=rgb is not None, rgb_dtype=rgb.dtype if rgb is not None else np.uint8,
                       preallocate=False)
    if acc.decimating:
        for s in range(0, len(xyz), p.chunk_points):
            acc.add(xyz[s:s + p.chunk_points], None if inten is None else inten[s:s + p.chunk_points],
                    None if rgb is None else rgb[s:s + p.chunk_points])
    else:  # every point kept: hand the arrays over without a copy
        acc.xyz, acc.inten, acc.rgb, acc.n_read = xyz, inten, rgb, len(xyz)
    if not crs_record and crs is None and rgb_what in ("PLY", "PTS", "XYZ"):
        notes.append(f"{rgb_what} files carry no CRS: coordinates taken as the model frame")
        apply_crs = False
    return _finish_cloud(acc, path, p, notes, intensity_limits=limits, rgb_max=rgb_max, rgb_what=rgb_what,
                         crs=crs, crs_record=crs_record, georef=georef, apply_crs=apply_crs)


# -- PLY ---------------------------------------------------------------------

_PLY_INTENSITY = ("intensity", "scalar_intensity")


def _ply_header(path: Path) -> dict:
    """The element counts and vertex properties of a PLY header."""
    counts: dict[str, int] = {}
    props: list[str] = []
    fmt = None
    current = None
    with open(path, "rb") as fh:
        if fh.readline().strip() != b"ply":
            raise ValueError("no 'ply' signature")
        for _ in range(10_000):
            line = fh.readline()
            if not line:
                raise ValueError("header has no end_header")
            words = line.decode("ascii", "replace").split()
            if not words:
                continue
            if words[0] == "end_header":
                return {"counts": counts, "vertex_properties": props, "format": fmt}
            if words[0] == "format" and len(words) > 1:
                fmt = words[1]
            elif words[0] == "element" and len(words) >= 3:
                current = words[1]
                counts[current] = int(words[2])
            elif words[0] == "property" and current == "vertex":
                props.append(words[-1])
    raise ValueError("header too long")


def _read_ply(path: Path, p: PointCloudParams, georef) -> PointCloud:
    from trimesh.exchange.ply import load_ply

    try:
        header = _ply_header(path)
    except Exception as exc:
        raise input_error(path, f"cannot read PLY ({_why(exc)})") from None
    n_faces = header["counts"].get("face", 0)
    if n_faces:
        raise input_error(
            path, f"has {n_faces} faces: it is a mesh, not a point cloud (open it as a mesh, "
            "napari_imgreg.io.meshes.load_mesh)"
        )
    n = header["counts"].get("vertex", 0)
    if n == 0:
        raise input_error(path, "holds no points (empty cloud)")
    try:
        with warnings.catch_warnings(), open(path, "rb") as fh:
            warnings.simplefilter("ignore")
            loaded = load_ply(fh)
        raw = loaded["metadata"]["_ply_raw"]["vertex"]["data"]
    except Exception as exc:
        raise input_error(path, f"cannot read PLY ({_why(exc)}; truncated or corrupt?)") from None
    columns = _ply_columns(raw)
    lower = {k.lower(): k for k in columns}
    if not {"x", "y", "z"} <= set(lower):
        raise input_error(path, "has no x, y, z vertex properties")
    m = len(columns[lower["x"]])
    if m != n:
        raise input_error(path, f"holds {m} of the {n} vertices its header declares (truncated)")
    xyz = np.column_stack([np.asarray(columns[lower[a]], np.float64).reshape(-1) for a in "xyz"])
    inten = None
    for name in _PLY_INTENSITY:
        if name in lower:
            inten = np.asarray(columns[lower[name]], np.float32).reshape(-1)
            break
    rgb = None
    if {"red", "green", "blue"} <= set(lower):
        rgb = np.column_stack([np.asarray(columns[lower[c]]).reshape(-1) for c in ("red", "green", "blue")])
        if rgb.dtype != np.uint8:
            if np.issubdtype(rgb.dtype, np.floating) and rgb.max() <= 1.0:
                rgb = np.rint(rgb * 255)  # colours stored as 0–1 floats
            rgb = np.clip(rgb, 0, 65535).astype(np.uint16)
    del loaded, raw, columns
    return _cloud_from_arrays(path, p, georef, [], xyz, inten, rgb, rgb_what="PLY")


def _ply_columns(raw) -> dict:
    """trimesh's raw vertex data (a structured array for binary PLY, a dict of
    columns for ASCII) as name → array."""
    if isinstance(raw, dict):
        return dict(raw)
    return {name: raw[name] for name in raw.dtype.names}


# -- PTS / XYZ text ----------------------------------------------------------


def _text_blocks(fh, block_bytes: int) -> Iterator[bytes]:
    """The file in blocks that end at a line end."""
    rest = b""
    while True:
        data = fh.read(block_bytes)
        if not data:
            if rest.strip():
                yield rest
            return
        data = rest + data
        cut = data.rfind(b"\n")
        if cut < 0:
            rest = data
            continue
        rest = data[cut + 1:]
        yield data[:cut + 1]


def _parse_block(block: bytes, ncols: int, path: Path, first_line: int, is_pts: bool) -> np.ndarray:
    """(rows, ncols) float64 of a block of text lines; a PTS block's point
    count lines (one number alone) are skipped."""
    text = block.replace(b",", b" ").replace(b";", b" ")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            flat = np.fromstring(text, dtype=np.float64, sep=" ")  # text mode: C speed
    except ValueError:  # a token that is not a number: the slow path names its line
        flat = np.empty(0)
    arr = np.frombuffer(text, np.uint8)
    newlines = np.flatnonzero(arr == 10)
    if len(newlines) == 0 or newlines[-1] != len(arr) - 1:
        newlines = np.append(newlines, len(arr) - 1)
    solid = np.cumsum(~np.isin(arr, (9, 10, 13, 32)))  # non-blank bytes up to each position
    at_end = solid[newlines]
    per_line = np.diff(np.concatenate([[0], at_end]))
    n_lines = int((per_line > 0).sum())
    if flat.size == n_lines * ncols:
        return flat.reshape(n_lines, ncols)
    # slow path: find the bad line (or PTS block headers) line by line
    rows = []
    for i, line in enumerate(text.split(b"\n")):
        words = line.split()
        if not words:
            continue
        if is_pts and len(words) == 1:
            continue
        if len(words) != ncols:
            raise input_error(path, f"line {first_line + i}: {len(words)} values where {ncols} were expected")
        try:
            rows.append([float(w) for w in words])
        except ValueError:
            raise input_error(path, f"line {first_line + i}: not a number in {line.decode(errors='replace')[:60]!r}") from None
    return np.asarray(rows, np.float64).reshape(-1, ncols)


# Column names of text headers (CloudCompare writes e.g. "//X,Y,Z,R,G,B,Intensity").
_TEXT_NAMES = {
    "x": "x", "y": "y", "z": "z",
    "intensity": "i", "i": "i", "scalar_intensity": "i", "reflectance": "i", "scalar_field": "i",
    "r": "r", "red": "r", "rf": "r", "g": "g", "green": "g", "gf": "g", "b": "b", "blue": "b", "bf": "b",
}


def _split_words(line: bytes) -> list[bytes]:
    return line.replace(b",", b" ").replace(b";", b" ").split()


def _column_names(line: bytes) -> list[str] | None:
    """The roles of a header line's columns ('x', 'i', 'r', ..., or '' for
    others), or None when it names no x, y and z."""
    words = [w.decode("ascii", "replace").lower().lstrip("/#").strip() for w in _split_words(line)]
    roles = [_TEXT_NAMES.get(w, "") for w in words]
    return roles if {"x", "y", "z"} <= set(roles) else None


def _read_text(path: Path, p: PointCloudParams, georef) -> PointCloud:
    is_pts = path.suffix.lower() == ".pts"
    kind = "PTS" if is_pts else "XYZ"
    notes: list[str] = []
    declared = None
    names = None
    with open(path, "rb") as fh:
        # the header: comments, a PTS point count, a line of column names
        line_no = 0
        while True:
            pos = fh.tell()
            line = fh.readline()
            if not line:
                raise input_error(path, "holds no points (empty cloud)")
            line_no += 1
            stripped = line.strip()
            if not stripped:
                continue
            words = _split_words(stripped)
            try:
                [float(w) for w in words]
            except ValueError:
                if names is None and line_no <= 3:
                    names = _column_names(stripped)
                if stripped.startswith((b"#", b"//")) or line_no <= 3:
                    continue  # a comment, or a line of column names
                raise input_error(
                    path, f"line {line_no}: not a number in {stripped.decode(errors='replace')[:60]!r}"
                ) from None
            if is_pts and declared is None and len(words) == 1:
                count = float(words[0])
                if not (math.isfinite(count) and count >= 0 and count == int(count)):
                    raise input_error(path, f"line {line_no}: a PTS file starts with its point count, not {count:g}")
                declared = int(count)
                continue
            fh.seek(pos)
            line_no -= 1
            ncols = len(words)
            break
        if names is not None and len(names) == ncols:
            roles = names
            ignored = ncols - sum(1 for r in roles if r)
            if ignored:
                notes.append(f"{ignored} column(s) the header does not name as x y z, intensity or r g b: ignored")
        else:
            layouts = {3: "xyz", 4: "xyzi", 6: "xyzrgb", 7: "xyzirgb"}
            if ncols not in layouts:
                raise input_error(
                    path, f"has {ncols} columns; expected 3, 4, 6 or 7 (x y z [intensity] [r g b]) "
                    "or a header line naming them"
                )
            roles = list(layouts[ncols])
        col = {r: roles.index(r) for r in "xyzirgb" if r in roles}
        xyz_cols = [col["x"], col["y"], col["z"]]
        rgb_cols = [col["r"], col["g"], col["b"]] if {"r", "g", "b"} <= set(col) else None
        # each block is split into compact columns at once: float64 xyz,
        # float32 intensity, the colour columns as read
        parts: list[tuple] = []
        block_bytes = max(1 << 20, p.chunk_points * 8 * ncols)
        for block in _text_blocks(fh, block_bytes):
            rows = _parse_block(block, ncols, path, line_no + 1, is_pts)
            line_no += block.count(b"\n")
            parts.append((rows[:, xyz_cols], rows[:, col["i"]].astype(np.float32) if "i" in col else None,
                          rows[:, rgb_cols] if rgb_cols else None))
            del rows
    n_rows = sum(len(q[0]) for q in parts)
    if declared is not None:
        if n_rows < declared:
            raise input_error(path, f"holds {n_rows} of the {declared} points its first line declares (truncated)")
        if n_rows > declared:
            notes.append(f"holds {n_rows} points, more than the {declared} its first line declares: all read")
    if n_rows == 0:
        raise input_error(path, "holds no points (empty cloud)")
    xyz = np.concatenate([q[0] for q in parts])
    inten = np.concatenate([q[1] for q in parts]) if "i" in col else None
    cols = np.concatenate([q[2] for q in parts]) if rgb_cols else None
    del parts
    rgb = None
    if cols is not None:
        if not np.isfinite(cols).all():
            raise input_error(path, "has NaN or infinite colours")
        if cols.min() < 0 or cols.max() > 65535:
            if np.abs(cols).max() <= 1.0 + 1e-6 and names is None:
                notes.append("the last three columns lie within −1…1: taken as normals, not colours, and ignored")
            else:
                raise input_error(path, "has colours outside 0–255 (or 0–65535)")
        elif cols.max() <= 1.0 and (cols % 1).any():
            rgb = np.rint(cols * 255).astype(np.uint16)  # colours as 0–1 fractions
            notes.append("colours within 0–1: taken as fractions of full brightness")
        else:
            rgb = np.rint(cols).astype(np.uint16)
        del cols
    if rgb is not None and int(rgb.max()) <= 255:
        rgb = rgb.astype(np.uint8)
    return _cloud_from_arrays(path, p, georef, notes, xyz, inten, rgb, rgb_what=kind)


# ---------------------------------------------------------------------------
# Writing


def write_point_cloud(path: str | os.PathLike, cloud: PointCloud, chunk_points: int = 2_000_000) -> Path:
    """Write a point cloud, atomically (the file is complete or left as it was).

    Parameters
    ----------
    path : path-like
        ``.las`` / ``.laz`` (LAS 1.4, point format 6, or 7 with colour;
        0.1 mm resolution; intensity × 65535), ``.e57`` (one scan; points
        stored as float32 relative to a double-precision pose at their centre),
        ``.ply`` (binary little-endian; x y z double, ``intensity`` float,
        ``red green blue`` uchar), ``.pts`` (count line, then ``x y z i
        [r g b]`` with ``i`` in −2048…2047, Leica's range) or ``.xyz``
        (``x y z [intensity] [r g b]``, space-separated). Text coordinates are
        written to 0.1 mm.
    cloud : PointCloud
        Its intensity (normalised, [0, 1]) and colour are written where the
        format holds them. LAS/LAZ get the cloud's CRS record; when the
        cloud's origin was subtracted on reading, they get the map coordinates
        back (``xyz + origin_subtracted``), so the file reads the same again
        with the same ``georef.json``. E57 (pye57 writes no CRS record), PLY
        and text get model-frame ``xyz``.
    chunk_points : int
        Points encoded at a time (LAS/LAZ, text), bounding the extra memory.

    Returns
    -------
    Path
        The file written.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in POINT_CLOUD_SUFFIXES:
        raise input_error(path, f"not a point cloud format (expected one of {', '.join(POINT_CLOUD_SUFFIXES)})")
    if len(cloud) == 0:
        raise input_error(path, "cannot write an empty cloud")
    writer = {
        ".las": _write_las, ".laz": _write_las, ".e57": _write_e57, ".ply": _write_ply,
        ".pts": _write_text, ".xyz": _write_text,
    }[suffix]
    with atomic_path(path) as tmp:
        writer(tmp, cloud, chunk_points)
    return path


def _file_coordinates(cloud: PointCloud, start: int = 0, stop: int | None = None) -> np.ndarray:
    xyz = cloud.xyz[start:stop]
    if cloud.origin_subtracted is not None:
        xyz = xyz + cloud.origin_subtracted
    return xyz


def _cloud_crs(cloud: PointCloud):
    import pyproj

    if cloud.crs_wkt:
        return pyproj.CRS.from_wkt(cloud.crs_wkt)
    if cloud.crs_epsg:
        return pyproj.CRS.from_epsg(int(cloud.crs_epsg))
    return None


def _write_las(tmp: Path, cloud: PointCloud, chunk_points: int) -> None:
    import laspy

    header = laspy.LasHeader(point_format=7 if cloud.rgb is not None else 6, version="1.4")
    lo, hi = cloud.bounds
    if cloud.origin_subtracted is not None:
        lo, hi = lo + cloud.origin_subtracted, hi + cloud.origin_subtracted
    # 0.1 mm where the int32 coordinates reach across the cloud, else coarser
    scale = 1e-4
    while (hi - lo).max() / scale > 2.0e9:
        scale *= 10
    header.scales = np.full(3, scale)
    header.offsets = np.floor(lo)
    crs = _cloud_crs(cloud)
    if crs is not None:
        header.add_crs(crs)
    with laspy.open(tmp, mode="w", header=header, do_compress=tmp.suffix.lower() == ".laz",
                    laz_backend=laspy.LazBackend.Lazrs) as writer:
        for s in range(0, len(cloud), chunk_points):
            e = min(s + chunk_points, len(cloud))
            points = laspy.ScaleAwarePointRecord.zeros(e - s, header=header)
            xyz = _file_coordinates(cloud, s, e)
            points.x, points.y, points.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
            if cloud.intensity is not None:
                points.intensity = np.rint(np.clip(cloud.intensity[s:e], 0, 1) * 65535).astype(np.uint16)
            if cloud.rgb is not None:
                rgb16 = cloud.rgb[s:e].astype(np.uint16) * 257  # LAS colours are 16-bit
                points.red, points.green, points.blue = rgb16[:, 0], rgb16[:, 1], rgb16[:, 2]
            writer.write_points(points)


def _write_e57(tmp: Path, cloud: PointCloud, chunk_points: int) -> None:
    import pye57

    # pye57 writes an empty coordinateMetadata of its own (libE57 refuses to
    # set it twice), so the E57 gets no CRS record and model-frame xyz.
    xyz = cloud.xyz
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    # pye57 stores coordinates as float32: keep them small, the pose carries the offset
    centre = np.floor((lo + hi) / 2)
    local = xyz - centre
    data = {"cartesianX": local[:, 0], "cartesianY": local[:, 1], "cartesianZ": local[:, 2]}
    if cloud.intensity is not None:
        data["intensity"] = cloud.intensity.astype(np.float32)
    if cloud.rgb is not None:
        data["colorRed"], data["colorGreen"], data["colorBlue"] = (cloud.rgb[:, i].copy() for i in range(3))
    with _quiet_stderr():
        e57 = pye57.E57(str(tmp), mode="w")
        try:
            e57.write_scan_raw(data, name="napari-imgreg", rotation=np.array([1.0, 0.0, 0.0, 0.0]),
                               translation=centre.astype(np.float64))
        finally:
            e57.close()


def _write_ply(tmp: Path, cloud: PointCloud, chunk_points: int) -> None:
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if cloud.intensity is not None:
        fields.append(("intensity", "<f4"))
    if cloud.rgb is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    ply_type = {"<f8": "double", "<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", "comment napari-imgreg point cloud",
              f"element vertex {len(cloud)}"]
    header += [f"property {ply_type[t]} {name}" for name, t in fields]
    header.append("end_header")
    dtype = np.dtype(fields)
    with open(tmp, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        for s in range(0, len(cloud), chunk_points):
            e = min(s + chunk_points, len(cloud))
            rec = np.empty(e - s, dtype)
            rec["x"], rec["y"], rec["z"] = cloud.xyz[s:e, 0], cloud.xyz[s:e, 1], cloud.xyz[s:e, 2]
            if cloud.intensity is not None:
                rec["intensity"] = cloud.intensity[s:e]
            if cloud.rgb is not None:
                rec["red"], rec["green"], rec["blue"] = cloud.rgb[s:e, 0], cloud.rgb[s:e, 1], cloud.rgb[s:e, 2]
            fh.write(rec.tobytes())


def _write_text(tmp: Path, cloud: PointCloud, chunk_points: int) -> None:
    is_pts = tmp.suffix.lower() == ".pts"
    with open(tmp, "w", encoding="ascii", newline="\n") as fh:
        if is_pts:
            fh.write(f"{len(cloud)}\n")
        fmt = ["%.4f"] * 3
        if cloud.intensity is not None:
            fmt.append("%d" if is_pts else "%.6f")
        if cloud.rgb is not None:
            fmt += ["%d"] * 3
        for s in range(0, len(cloud), chunk_points):
            e = min(s + chunk_points, len(cloud))
            cols = [cloud.xyz[s:e]]
            if cloud.intensity is not None:
                i = cloud.intensity[s:e].astype(np.float64)
                cols.append((np.rint(i * 4095) - 2048 if is_pts else i)[:, None])
            if cloud.rgb is not None:
                cols.append(cloud.rgb[s:e].astype(np.float64))
            np.savetxt(fh, np.hstack(cols), fmt=" ".join(fmt))


# ---------------------------------------------------------------------------
# Wording


def _why(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    return f"{type(exc).__name__}: {text}"[:200] if text else type(exc).__name__


def _count(n: int) -> str:
    """52.1 M, 980 k, 640."""
    if n >= 1_000_000:
        return f"{n / 1e6:.1f} M"
    if n >= 10_000:
        return f"{n / 1e3:.0f} k"
    return str(n)


def _length(metres: float) -> str:
    if metres < 1.0:
        return f"{metres * 100:.2g} cm" if metres >= 0.01 else f"{metres * 1000:.2g} mm"
    return f"{metres:.3g} m"


def _num(v: float) -> str:
    return f"{v:g}"


def _xyz(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{x:.3f}" for x in v) + ")"
