"""Georeferencing: the model frame, projected CRSs, geodetic points and DEMs.

Conventions (public contract):

* Model ("local") frame: metres, right-handed, +X east, +Y north, +Z up (ENU).
* ``georef.json`` = ``{"crs": "EPSG:32630", "origin": [E, N, H]}``; a
  projected-CRS coordinate is ``local + origin``.  Geodetic (WGS84 lat/lon)
  input is projected into ``crs`` with pyproj, then ``origin`` is subtracted.
* A DEM is a north-up raster in the georeference CRS with heights in metres,
  read from GeoTIFF (``.tif``/``.tiff``) or ESRI ASCII grid (``.asc``)
  (the file formats are :mod:`napari_imgreg.io.rasters`').
  The altitude of a camera is the bilinear DEM height at (E, N) plus its
  height above ground (default 1.6 m, eye level).
* Every problem with an input file raises a single :class:`GeoError` whose
  message starts with the file and says what is wrong.

This module is backend only: no Qt or napari imports.
"""

from __future__ import annotations

import json
import math
import os
import threading
from dataclasses import dataclass
from datetime import date as date_type
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import numpy.typing as npt

from ._atomic import atomic_path
from ._json import dumps as strict_json_dumps
from ._deprecated import forward_moved_names
from .io.rasters import GeoError, read_dem_raster, write_dem_asc, write_dem_geotiff

__all__ = [
    "GeoError",
    "Georef",
    "DEM",
    "camera_altitude",
    "dem_height_local",
    "DEFAULT_HEIGHT_ABOVE_GROUND_M",
    "DeclinationError",
    "MagneticDeclination",
    "magnetic_declination",
    "declination_deg",
    "site_latitude_longitude",
    "WMM_GRACE_YEARS",
]

#: Default camera height above the DEM surface (hand-held, eye level), metres.
DEFAULT_HEIGHT_ABOVE_GROUND_M = 1.6

#: The raster file formats that moved to napari_imgreg.io.rasters in 0.2.
_MOVED = dict.fromkeys(("GeoRaster", "read_geotiff", "NODATA_WRITE"), "napari_imgreg.io.rasters")
__getattr__ = forward_moved_names(__name__, _MOVED)




# ---------------------------------------------------------------------------
# small helpers
# ---------------------------------------------------------------------------


def _is_number(v: Any) -> bool:
    # bool is an int subclass; "origin": [true, 0, 0] is certainly a mistake.
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _fmt(v: float) -> str:
    """Short, readable number for error messages."""
    return f"{v:.3f}".rstrip("0").rstrip(".") if math.isfinite(v) else str(v)


def _fmt1(v: float) -> str:
    """Number with at least one decimal (``100.0``) for extents."""
    s = _fmt(v)
    return s + ".0" if math.isfinite(v) and "." not in s else s


def _check_crs(
    crs: Any, source: str, what: str = "field 'crs'", *, projected: bool = True
) -> str:
    """Validate a CRS string (projected and metre-based unless
    ``projected=False``); return it unchanged."""
    if not isinstance(crs, str) or not crs.strip():
        raise GeoError(f"{source}: {what} must be a non-empty string such as 'EPSG:32630'")
    import pyproj  # local: keeps ``import napari_imgreg.geo`` cheap

    try:
        c = pyproj.CRS.from_user_input(crs)
    except pyproj.exceptions.CRSError as exc:
        raise GeoError(f"{source}: {what} {crs!r} is not a valid CRS ({exc})") from None
    if not projected:
        return crs
    if not c.is_projected:
        raise GeoError(
            f"{source}: {what} {crs!r} is not a projected CRS; the model frame "
            "needs easting/northing in metres (e.g. a UTM zone)"
        )
    units = {a.unit_name.lower() for a in c.axis_info[:2]}
    if not units <= {"metre", "meter"}:
        raise GeoError(
            f"{source}: {what} {crs!r} has axis units {sorted(units)}; "
            "the model frame is in metres"
        )
    return crs


def _refuse_degrees_as_origin(crs: str, origin: Sequence[float], source: str) -> None:
    """Refuse an origin that is latitude and longitude, not easting and northing.

    Refused when both of its horizontal numbers could be degrees (|value| ≤
    180) *and*, read as map coordinates, they lie more than a degree outside
    the area the CRS is made for (pyproj's ``area_of_use``): a UTM zone's
    eastings are hundreds of kilometres, so ``[53.35, -1.81, 350]`` in
    EPSG:32630 sits 1.5° west of its zone, on the equator. Any origin the CRS
    is used for passes, and so does ``(0, 0)``: a model already in map
    coordinates.
    """
    east, north = float(origin[0]), float(origin[1])
    # (0, 0): a model already in map coordinates, shifted by nothing.
    if abs(east) > 180 or abs(north) > 180 or east == north == 0.0:
        return
    import pyproj

    area = pyproj.CRS.from_user_input(crs).area_of_use
    if area is None:
        return
    lon, lat = _transformer(crs, "EPSG:4326").transform(east, north)
    margin = 1.0
    inside = (area.west - margin <= lon <= area.east + margin
              and area.south - margin <= lat <= area.north + margin)
    if math.isfinite(lon) and math.isfinite(lat) and inside:
        return
    raise GeoError(
        f"{source}: field 'origin' [{_fmt(east)}, {_fmt(north)}, {_fmt(float(origin[2]))}] looks "
        f"like latitude and longitude, not {crs}'s easting and northing (read as map "
        f"coordinates it lies outside the area {crs} is for): give the map coordinates, "
        "in metres, of the model's (0, 0, 0)")


# pyproj Transformers are not guaranteed to be safe to share between threads
# (napari runs workers in threads), so cache one per thread and CRS pair.
_tls = threading.local()


def _transformer(src: str, dst: str) -> Any:
    cache: dict[tuple[str, str], Any] | None = getattr(_tls, "cache", None)
    if cache is None:
        cache = _tls.cache = {}
    key = (src, dst)
    tr = cache.get(key)
    if tr is None:
        import pyproj

        tr = cache[key] = pyproj.Transformer.from_crs(src, dst, always_xy=True)
    return tr


def _as_points(xyz: npt.ArrayLike, name: str) -> tuple[np.ndarray, bool]:
    """Return ``(pts (N, 3) float64, was_single)`` for (3,) or (N, 3) input."""
    a = np.asarray(xyz, dtype=np.float64)
    if a.shape == (3,):
        return a[None, :], True
    if a.ndim == 2 and a.shape[1] == 3:
        return a, False
    raise ValueError(f"{name} must have shape (3,) or (N, 3), got {a.shape}")


# ---------------------------------------------------------------------------
# Georef
# ---------------------------------------------------------------------------


@dataclass(eq=False)
class Georef:
    """Link between the local model frame and a projected CRS.

    Parameters
    ----------
    crs : str
        Projected, metre-based CRS, anything ``pyproj.CRS.from_user_input``
        accepts (normally ``"EPSG:<code>"``).
    origin : ndarray, shape (3,), float64
        CRS coordinates (E, N, H) in metres of the local origin:
        ``crs_xyz = local_xyz + origin``.
    """

    crs: str
    origin: np.ndarray

    def __post_init__(self) -> None:
        # Only "does pyproj know it": files are held to "projected, metres" in
        # from_dict, but code may build a frame for a CRS-less DEM.
        self.crs = _check_crs(self.crs, "georef", projected=False)
        o = np.asarray(self.origin, dtype=np.float64)
        if o.shape != (3,) or not np.all(np.isfinite(o)):
            raise GeoError("georef: field 'origin' must be a list of 3 finite numbers")
        self.origin = o

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Georef):
            return NotImplemented
        return self.crs == other.crs and bool(np.array_equal(self.origin, other.origin))

    # -- serialisation -----------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready ``{"crs": str, "origin": [E, N, H]}``."""
        return {"crs": self.crs, "origin": [float(v) for v in self.origin]}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: str = "georef") -> "Georef":
        """Build from a parsed ``georef.json`` mapping.

        Parameters
        ----------
        d : mapping
            Must hold ``"crs"`` (str) and ``"origin"`` (3 numbers). Other keys
            are ignored so newer files still load.
        source : str
            File name used in error messages.

        Raises
        ------
        GeoError
            Missing or wrongly typed field, or invalid CRS.
        """
        if not isinstance(d, Mapping):
            raise GeoError(f"{source}: expected a JSON object, got {type(d).__name__}")
        if "crs" not in d:
            raise GeoError(f"{source}: missing field 'crs'")
        if "origin" not in d:
            raise GeoError(f"{source}: missing field 'origin'")
        crs = _check_crs(d["crs"], source)
        origin = d["origin"]
        if (
            not isinstance(origin, (list, tuple))
            or len(origin) != 3
            or not all(_is_number(v) and math.isfinite(v) for v in origin)
        ):
            raise GeoError(f"{source}: field 'origin' must be a list of 3 numbers")
        _refuse_degrees_as_origin(crs, origin, source)
        return cls(crs=crs, origin=np.array(origin, dtype=np.float64))

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> "Georef":
        """Read ``georef.json``.

        Raises
        ------
        GeoError
            File missing or unreadable, invalid JSON, bad fields.
        """
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise GeoError(f"{p}: file not found") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise GeoError(f"{p}: cannot read file ({exc})") from None
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise GeoError(f"{p}: invalid JSON ({exc})") from None
        return cls.from_dict(d, source=str(p))

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write ``georef.json`` atomically (temp file + ``os.replace``)."""
        text = strict_json_dumps(self.to_dict(), indent=2) + "\n"

        def write(tmp: str) -> None:
            with open(tmp, "w", encoding="utf-8") as f:
                f.write(text)
                f.flush()
                os.fsync(f.fileno())

        with atomic_path(path) as tmp:
            write(os.fspath(tmp))

    # -- coordinate conversion ---------------------------------------------

    def local_to_crs(self, xyz: npt.ArrayLike) -> np.ndarray:
        """Local ENU (m) → CRS (E, N, H) (m); shape (3,) or (N, 3) preserved."""
        pts, single = _as_points(xyz, "xyz")
        out = pts + self.origin
        return out[0] if single else out

    def crs_to_local(self, enh: npt.ArrayLike) -> np.ndarray:
        """CRS (E, N, H) (m) → local ENU (m); shape (3,) or (N, 3) preserved."""
        pts, single = _as_points(enh, "enh")
        out = pts - self.origin
        return out[0] if single else out

    def geodetic_to_local(
        self,
        lat: npt.ArrayLike,
        lon: npt.ArrayLike,
        alt: npt.ArrayLike | None = None,
    ) -> np.ndarray:
        """WGS84 latitude/longitude (degrees) → local ENU (m).

        Parameters
        ----------
        lat, lon : float or array, shape (N,)
            WGS84 (EPSG:4326) degrees.
        alt : float or array, shape (N,), optional
            Height in metres in the CRS's vertical reference (the same as the
            DEM and ``origin[2]``); passed through unchanged, only ``origin[2]``
            is subtracted. ``None`` gives NaN z for the caller to fill from a
            DEM.

        Returns
        -------
        ndarray, shape (3,) for scalar input or (N, 3)
        """
        lat_a = np.asarray(lat, dtype=np.float64)
        lon_a = np.asarray(lon, dtype=np.float64)
        single = lat_a.ndim == 0 and lon_a.ndim == 0 and np.ndim(alt) == 0
        lat_a, lon_a = np.broadcast_arrays(np.atleast_1d(lat_a), np.atleast_1d(lon_a))
        lat_a, lon_a = lat_a.ravel(), lon_a.ravel()
        if np.any(np.abs(lat_a) > 90):
            raise GeoError(
                f"latitude {_fmt(float(lat_a[np.abs(lat_a) > 90][0]))} is outside "
                "[-90, 90] (were latitude and longitude swapped?)"
            )
        tr = _transformer("EPSG:4326", self.crs)
        e, n = tr.transform(lon_a, lat_a)  # always_xy: lon first
        e, n = np.asarray(e, dtype=np.float64), np.asarray(n, dtype=np.float64)
        bad = np.isfinite(lat_a) & np.isfinite(lon_a) & ~(np.isfinite(e) & np.isfinite(n))
        if np.any(bad):
            i = int(np.argmax(bad))
            raise GeoError(
                f"cannot project lat {lat_a[i]}, lon {lon_a[i]} into {self.crs}"
            )
        if alt is None:
            z = np.full(e.shape, np.nan)
        else:
            z = np.broadcast_to(np.asarray(alt, dtype=np.float64).ravel(), e.shape)
        out = np.column_stack([e, n, z]) - self.origin
        return out[0] if single else out

    def local_to_geodetic(
        self, xyz: npt.ArrayLike
    ) -> tuple[float | np.ndarray, float | np.ndarray, float | np.ndarray]:
        """Local ENU (m) → WGS84 ``(lat, lon, alt)``.

        Parameters
        ----------
        xyz : array, shape (3,) or (N, 3)

        Returns
        -------
        lat, lon : float or ndarray (N,)
            Degrees.
        alt : float or ndarray (N,)
            ``z + origin[2]``, metres (vertical reference unchanged).
        """
        pts, single = _as_points(xyz, "xyz")
        enh = pts + self.origin
        tr = _transformer(self.crs, "EPSG:4326")
        lon, lat = tr.transform(enh[:, 0], enh[:, 1])
        lat = np.asarray(lat, dtype=np.float64)
        lon = np.asarray(lon, dtype=np.float64)
        alt = enh[:, 2]
        if single:
            return float(lat[0]), float(lon[0]), float(alt[0])
        return lat, lon, alt


# ---------------------------------------------------------------------------
# DEM
# ---------------------------------------------------------------------------


@dataclass(eq=False)
class DEM:
    """North-up raster of heights in a projected CRS.

    Parameters
    ----------
    heights : ndarray, shape (rows, cols), float64
        Heights in metres; NaN is nodata. Row 0 is the NORTH row.
    x0, y0 : float
        CRS coordinates (m) of the CENTRE of the top-left pixel.
    dx, dy : float
        Positive pixel spacings (m): column ``c`` has easting ``x0 + c*dx``,
        row ``r`` has northing ``y0 - r*dy``.
    crs : str or None
        ``"EPSG:<code>"`` when the file says so.
    source : str
        File name used in messages.
    """

    heights: np.ndarray
    x0: float
    y0: float
    dx: float
    dy: float
    crs: str | None = None
    source: str = "<array>"

    def __post_init__(self) -> None:
        h = np.array(self.heights, dtype=np.float64)  # copy: own our data
        if h.ndim != 2 or h.size == 0:
            raise GeoError(
                f"{self.source}: DEM heights must be a non-empty 2D array, got shape {h.shape}"
            )
        h[~np.isfinite(h)] = np.nan  # ±inf is as unusable as nodata
        self.heights = h
        for name in ("x0", "y0", "dx", "dy"):
            v = float(getattr(self, name))
            if not math.isfinite(v):
                raise GeoError(f"{self.source}: DEM {name} must be finite, got {v}")
            setattr(self, name, v)
        if self.dx <= 0 or self.dy <= 0:
            raise GeoError(
                f"{self.source}: DEM pixel spacing must be positive, "
                f"got dx={self.dx}, dy={self.dy}"
            )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, DEM):
            return NotImplemented
        return (
            (self.x0, self.y0, self.dx, self.dy, self.crs)
            == (other.x0, other.y0, other.dx, other.dy, other.crs)
            and np.array_equal(self.heights, other.heights, equal_nan=True)
        )

    # -- construction --------------------------------------------------------

    @classmethod
    def from_array(
        cls,
        heights: npt.ArrayLike,
        x0: float,
        y0: float,
        dx: float,
        dy: float,
        crs: str | None = None,
        source: str = "<array>",
    ) -> "DEM":
        """Build a DEM from an array; see the class docstring for the geometry."""
        return cls(np.asarray(heights), x0, y0, dx, dy, crs=crs, source=source)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> "DEM":
        """Read a DEM from ``.tif``/``.tiff`` (GeoTIFF) or ``.asc`` (ESRI ASCII grid).

        Raises
        ------
        GeoError
            Missing file, unknown extension, unreadable or un-georeferenced
            content; the message names the file.
        """
        grid = read_dem_raster(path)
        return cls(grid.data, grid.x0, grid.y0, grid.dx, grid.dy, crs=grid.crs, source=grid.source)

    # -- writing -------------------------------------------------------------

    def save_geotiff(self, path: str | os.PathLike[str]) -> None:
        """Write a float32 GeoTIFF (PixelIsArea, NaN → -9999 + GDAL_NODATA).

        Atomic (temp file + ``os.replace``). ``crs`` must be ``None`` or have
        an EPSG code; a compound CRS stores its horizontal part only. See
        :func:`napari_imgreg.io.rasters.write_dem_geotiff`.
        """
        write_dem_geotiff(path, self.heights, self.x0, self.y0, self.dx, self.dy, self.crs)

    def save_asc(self, path: str | os.PathLike[str]) -> None:
        """Write an ESRI ASCII grid (``xllcorner``; NaN → -9999). Atomic.

        Uses ``cellsize`` when ``dx == dy``, otherwise GDAL's ``dx``/``dy``
        header keys. When ``crs`` is set, an ESRI ``.prj`` sidecar is written
        too so that :meth:`load` recovers it. See
        :func:`napari_imgreg.io.rasters.write_dem_asc`.
        """
        write_dem_asc(path, self.heights, self.x0, self.y0, self.dx, self.dy, self.crs)

    # -- geometry --------------------------------------------------------------

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)``."""
        return self.heights.shape  # type: ignore[return-value]

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """``(xmin, xmax, ymin, ymax)`` of pixel CENTRES, metres."""
        rows, cols = self.heights.shape
        return (
            self.x0,
            self.x0 + (cols - 1) * self.dx,
            self.y0 - (rows - 1) * self.dy,
            self.y0,
        )

    def grid(self) -> tuple[np.ndarray, np.ndarray]:
        """Pixel-centre coordinates ``(E, N)``, each shape (rows, cols), metres."""
        rows, cols = self.heights.shape
        e = self.x0 + np.arange(cols) * self.dx
        n = self.y0 - np.arange(rows) * self.dy
        return np.meshgrid(e, n)

    def _extent_str(self) -> str:
        xmin, xmax, ymin, ymax = self.extent
        return f"E {_fmt1(xmin)}–{_fmt1(xmax)}, N {_fmt1(ymin)}–{_fmt1(ymax)}"

    # -- sampling ----------------------------------------------------------------

    def height_at(
        self, e: npt.ArrayLike, n: npt.ArrayLike, *, strict: bool = True
    ) -> float | np.ndarray:
        """Bilinear DEM height at CRS point(s) (E, N).

        Interpolates between the four surrounding pixel centres. Points up to
        half a pixel beyond the outermost centres are clamped onto them.
        Nodata neighbours are dropped and the remaining bilinear weights
        renormalised.

        Parameters
        ----------
        e, n : float or array
            Easting, northing in metres (broadcast together).
        strict : bool
            ``True``: raise on a point outside the DEM or with only nodata
            around it. ``False``: return NaN there.

        Returns
        -------
        float for scalar input, else ndarray of the broadcast shape (metres).

        Raises
        ------
        GeoError
            (strict only) point outside the DEM, or all neighbours nodata.
        """
        e_a, n_a = np.broadcast_arrays(
            np.asarray(e, dtype=np.float64), np.asarray(n, dtype=np.float64)
        )
        scalar = e_a.ndim == 0
        ef, nf = e_a.ravel(), n_a.ravel()
        h = self.heights
        rows, cols = h.shape

        # Fractional pixel indices (centre of pixel (0, 0) is (0, 0)).
        c = (ef - self.x0) / self.dx
        r = (self.y0 - nf) / self.dy
        tol = 0.5 + 1e-9  # half a pixel, plus rounding slack
        inside = (c >= -tol) & (c <= cols - 1 + tol) & (r >= -tol) & (r <= rows - 1 + tol)
        c = np.clip(np.where(inside, c, 0.0), 0.0, cols - 1)
        r = np.clip(np.where(inside, r, 0.0), 0.0, rows - 1)
        # Lower-left index of the 2x2 cell; at the last row/col use the cell
        # before it (weight 1 on the edge) so c0 + 1 stays in range.
        c0 = np.minimum(np.floor(c).astype(np.intp), max(cols - 2, 0))
        r0 = np.minimum(np.floor(r).astype(np.intp), max(rows - 2, 0))
        c1 = np.minimum(c0 + 1, cols - 1)
        r1 = np.minimum(r0 + 1, rows - 1)
        fc = c - c0
        fr = r - r0
        if cols == 1:
            fc = np.zeros_like(fc)
        if rows == 1:
            fr = np.zeros_like(fr)

        vals = np.stack([h[r0, c0], h[r0, c1], h[r1, c0], h[r1, c1]])
        w = np.stack([(1 - fr) * (1 - fc), (1 - fr) * fc, fr * (1 - fc), fr * fc])
        valid = ~np.isnan(vals)
        w = np.where(valid, w, 0.0)
        wsum = w.sum(axis=0)
        has = wsum > 1e-12  # zero weight on every valid neighbour = nodata here
        with np.errstate(invalid="ignore", divide="ignore"):
            out = np.where(valid, vals * w, 0.0).sum(axis=0) / wsum
        out = np.where(inside & has, out, np.nan)

        if strict:
            if not np.all(inside):
                i = int(np.argmin(inside))
                raise GeoError(
                    f"{self.source}: point (E={_fmt(ef[i])}, N={_fmt(nf[i])}) is outside "
                    f"the DEM (extent {self._extent_str()})"
                )
            if not np.all(has):
                i = int(np.argmin(has))
                raise GeoError(
                    f"{self.source}: no DEM height at (E={_fmt(ef[i])}, N={_fmt(nf[i])}): nodata"
                )
        if scalar:
            return float(out[0])
        return out.reshape(e_a.shape)


def camera_altitude(
    dem: DEM,
    e: float,
    n: float,
    height_above_ground_m: float = DEFAULT_HEIGHT_ABOVE_GROUND_M,
) -> float:
    """Camera height (m, CRS vertical reference): DEM height at (E, N) + offset.

    Raises
    ------
    GeoError
        The point is outside the DEM or on nodata.
    """
    return float(dem.height_at(e, n)) + float(height_above_ground_m)


def dem_height_local(dem, georef, x: float, y: float) -> float:
    """The DEM's height at local (x, y), in the local frame (metres): the DEM is
    in the georeference CRS, so the origin is added, then its height taken off."""
    if georef is not None:
        e, n, oz = x + georef.origin[0], y + georef.origin[1], georef.origin[2]
    else:
        e, n, oz = x, y, 0.0
    return float(dem.height_at(e, n)) - oz


# ---------------------------------------------------------------------------
# Magnetic declination (World Magnetic Model)
# ---------------------------------------------------------------------------


class DeclinationError(GeoError):
    """The World Magnetic Model cannot give a declination there and then: a
    date outside its models' spans, or a place inside a magnetic pole's
    blackout zone. A :class:`GeoError`, so it is reported as one line."""


#: The World Magnetic Model editions used, oldest first: (name, first decimal
#: year, pygeomag module and attribute of its coefficients). Each is valid
#: for five years from its epoch (NOAA/NCEI); a date is given to the newest
#: edition whose epoch it is not before.
_WMM_EDITIONS = (
    ("WMM2010", 2010.0, "pygeomag.wmm.wmm_2010", "WMM_2010"),
    ("WMM2015v2", 2015.0, "pygeomag.wmm.wmm_2015v2", "WMM_2015v2"),
    ("WMM2020", 2020.0, "pygeomag.wmm.wmm_2020", "WMM_2020"),
    ("WMM2025", 2025.0, "pygeomag.wmm.wmm_2025", "WMM_2025"),
)
_WMM_SPAN_YEARS = 5.0

#: Years past the newest edition's span during which it is still used,
#: extrapolated (and said): its secular variation drifts by about 0.1° a
#: year at mid-latitudes, well under a phone compass's error, while a
#: pygeomag with the next edition may not be installed yet.
WMM_GRACE_YEARS = 1.0

#: Horizontal field strength (nT) below which NOAA calls a place a blackout
#: zone (declination and compass meaningless) and a caution zone.
_BLACKOUT_NT, _CAUTION_NT = 2000.0, 6000.0

# pygeomag's GeoMag keeps scratch arrays between calls: one per thread.
_wmm_tls = threading.local()


@dataclass(frozen=True)
class MagneticDeclination:
    """The declination at a place and date, and what it was computed from.

    Attributes
    ----------
    declination_deg : float
        Angle from true north to magnetic north, degrees, **east positive**:
        a true azimuth is the magnetic azimuth plus this.
    model : str
        The World Magnetic Model edition used (``"WMM2025"``).
    date : datetime.date
        The (UTC) date it was computed for.
    decimal_year : float
        The same instant as a decimal year, as the model takes it.
    latitude_deg, longitude_deg : float
        WGS84 degrees of the place.
    height_m : float
        Height of the place, metres (the model wants it above the ellipsoid;
        100 m either way changes the declination by well under 0.001°).
    uncertainty_deg : float
        The model's own error of the declination there (NOAA's error model
        of the edition), degrees; larger where the horizontal field is weak.
        NaN for WMM2010 (no error model at hand).
    horizontal_field_nT : float
        Horizontal field strength, nanotesla.
    caution : bool
        The place is in a caution zone near a magnetic pole (horizontal
        field under 6000 nT): compass headings there are poor.
    extrapolated : bool
        The date lies past the newest edition's five years (within
        :data:`WMM_GRACE_YEARS`).
    """

    declination_deg: float
    model: str
    date: date_type
    decimal_year: float
    latitude_deg: float
    longitude_deg: float
    height_m: float
    uncertainty_deg: float
    horizontal_field_nT: float
    caution: bool = False
    extrapolated: bool = False

    def label(self) -> str:
        """``"+3.2° (WMM2025, 2026-06-01)"``: the value and where it came from."""
        return f"{self.declination_deg:+.1f}° ({self.model}, {self.date.isoformat()})"

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready record of the value and its source (for result files)."""
        return {
            "declination_deg": round(float(self.declination_deg), 4),
            "source": "World Magnetic Model",
            "model": self.model,
            "date": self.date.isoformat(),
            "latitude_deg": round(float(self.latitude_deg), 6),
            "longitude_deg": round(float(self.longitude_deg), 6),
            "height_m": round(float(self.height_m), 1),
            "uncertainty_deg": (round(float(self.uncertainty_deg), 2)
                                if math.isfinite(self.uncertainty_deg) else None),
            "caution_zone": bool(self.caution),
            "extrapolated": bool(self.extrapolated),
        }


def _decimal_year(when: Any) -> tuple[float, Any]:
    """A datetime (aware: taken in UTC) or date → (decimal year, UTC date)."""
    if isinstance(when, datetime):
        if when.tzinfo is not None:
            when = when.astimezone(timezone.utc).replace(tzinfo=None)
    elif isinstance(when, date_type):
        when = datetime(when.year, when.month, when.day)
    else:
        raise TypeError(f"when must be a datetime or a date, got {type(when).__name__}")
    start, end = datetime(when.year, 1, 1), datetime(when.year + 1, 1, 1)
    fraction = (when - start).total_seconds() / (end - start).total_seconds()
    return when.year + fraction, when.date()


def _wmm_edition(year: float, when_date: Any) -> tuple[str, str, str, float, bool]:
    """The edition for a decimal year: (name, module, attribute, epoch, extrapolated)."""
    oldest, newest = _WMM_EDITIONS[0], _WMM_EDITIONS[-1]
    newest_end = newest[1] + _WMM_SPAN_YEARS
    if year < oldest[1]:
        raise DeclinationError(
            f"magnetic declination: {when_date.isoformat()} is before {oldest[1]:.1f}, the "
            f"start of the oldest World Magnetic Model known ({oldest[0]}): give the "
            "declination as a number")
    if year > newest_end + WMM_GRACE_YEARS:
        raise DeclinationError(
            f"magnetic declination: {when_date.isoformat()} is past the newest World "
            f"Magnetic Model installed ({newest[0]}, valid to {newest_end:.1f}; used "
            f"{WMM_GRACE_YEARS:g} year beyond): update pygeomag or give the declination as a "
            "number")
    name, epoch, module, attribute = next(e for e in reversed(_WMM_EDITIONS) if year >= e[1])
    return name, module, attribute, epoch, year > epoch + _WMM_SPAN_YEARS


def _wmm(module: str, attribute: str) -> Any:
    """This thread's pygeomag ``GeoMag`` for one edition (loaded once)."""
    import importlib

    cache: dict[str, Any] | None = getattr(_wmm_tls, "cache", None)
    if cache is None:
        cache = _wmm_tls.cache = {}
    geomag = cache.get(attribute)
    if geomag is None:
        from pygeomag import GeoMag

        coefficients = getattr(importlib.import_module(module), attribute)
        geomag = cache[attribute] = GeoMag(coefficients_data=coefficients)
    return geomag


def magnetic_declination(
    lat_deg: float, lon_deg: float, height_m: float, when: Any
) -> MagneticDeclination:
    """The magnetic declination of the World Magnetic Model, with its source.

    The WMM edition valid at ``when`` is used (WMM2010, WMM2015v2, WMM2020,
    WMM2025, each for five years from its epoch, as NOAA/NCEI publish them
    and pygeomag bundles them), evaluated by pygeomag, a port of NOAA's own
    code.

    Parameters
    ----------
    lat_deg, lon_deg : float
        WGS84 latitude and longitude, degrees (longitude east positive; any
        turn is wrapped to [-180, 180)).
    height_m : float
        Height above the WGS84 ellipsoid, metres (a height above sea level
        will do: the declination changes by well under 0.001° per 100 m).
    when : datetime.datetime or datetime.date
        The date; an aware datetime is taken in UTC, a naive one as it is.

    Returns
    -------
    MagneticDeclination

    Raises
    ------
    DeclinationError
        ``when`` is before 2010.0 or past the newest edition's span by more
        than :data:`WMM_GRACE_YEARS`, or the place is in a magnetic pole's
        blackout zone (horizontal field under 2000 nT), where a compass has
        no meaningful heading.
    GeoError
        Latitude outside [-90, 90], or a value that is not finite, or a
        height outside the model's -1 km to 850 km.
    """
    values = {"latitude": lat_deg, "longitude": lon_deg, "height": height_m}
    for name, value in values.items():
        if not _is_number(value) or not math.isfinite(value):
            raise GeoError(f"magnetic declination: {name} must be a finite number, got {value!r}")
    if abs(lat_deg) > 90.0:
        raise GeoError(f"magnetic declination: latitude {_fmt(lat_deg)} is outside [-90, 90]")
    if not -1000.0 <= height_m <= 850_000.0:
        raise GeoError(f"magnetic declination: height {_fmt(height_m)} m is outside the "
                       "model's -1 km to 850 km")
    lon = (float(lon_deg) + 180.0) % 360.0 - 180.0
    year, when_date = _decimal_year(when)
    name, module, attribute, epoch, extrapolated = _wmm_edition(year, when_date)
    # The grace beyond the span is ours: pygeomag refuses outside five years.
    field_ = _wmm(module, attribute).calculate(
        float(lat_deg), lon, float(height_m) / 1000.0, year,
        allow_date_outside_lifespan=extrapolated)
    if field_.h < _BLACKOUT_NT:
        raise DeclinationError(
            f"magnetic declination: at {_fmt(lat_deg)}°, {_fmt(lon)}° the horizontal field is "
            f"{field_.h:.0f} nT (a magnetic pole's blackout zone, under {_BLACKOUT_NT:.0f} nT): "
            "a compass heading means nothing there, and neither does a declination")
    try:  # NOAA's error model of the edition (pygeomag has WMM2015 and later)
        uncertainty = float(field_.calculate_uncertainty().d)
    except ValueError:
        uncertainty = math.nan
    return MagneticDeclination(
        declination_deg=float(field_.d), model=name, date=when_date, decimal_year=year,
        latitude_deg=float(lat_deg), longitude_deg=lon, height_m=float(height_m),
        uncertainty_deg=uncertainty, horizontal_field_nT=float(field_.h),
        caution=field_.h < _CAUTION_NT, extrapolated=extrapolated)


def declination_deg(lat_deg: float, lon_deg: float, height_m: float, when: Any) -> float:
    """Magnetic declination at a place and date, degrees **east positive**.

    True azimuth = magnetic azimuth + declination. The World Magnetic Model
    edition valid at ``when``; see :func:`magnetic_declination` (which also
    says which edition, and how sure it is) for the parameters and errors.

    Parameters
    ----------
    lat_deg, lon_deg : float
        WGS84 degrees.
    height_m : float
        Height above the ellipsoid (or sea level), metres.
    when : datetime.datetime or datetime.date

    Returns
    -------
    float
        Degrees, in (-180, 180].

    Raises
    ------
    DeclinationError, GeoError
        As :func:`magnetic_declination`.
    """
    return magnetic_declination(lat_deg, lon_deg, height_m, when).declination_deg


def site_latitude_longitude(georef: Georef, local_xyz: npt.ArrayLike = (0.0, 0.0, 0.0)
                            ) -> tuple[float, float, float]:
    """WGS84 ``(lat, lon, height)`` of a local point (default: the model origin).

    Parameters
    ----------
    georef : Georef
    local_xyz : array, shape (3,)
        Local ENU metres.

    Returns
    -------
    lat, lon : float
        Degrees.
    height : float
        Metres, in the CRS's vertical reference.
    """
    lat, lon, alt = georef.local_to_geodetic(np.asarray(local_xyz, dtype=np.float64).reshape(3))
    return float(lat), float(lon), float(alt)
