"""Georeferencing: the model frame, projected CRSs, geodetic points and DEMs.

Conventions (public contract):

* Model ("local") frame: metres, right-handed, +X east, +Y north, +Z up (ENU).
* ``georef.json`` = ``{"crs": "EPSG:32630", "origin": [E, N, H]}``; a
  projected-CRS coordinate is ``local + origin``.  Geodetic (WGS84 lat/lon)
  input is projected into ``crs`` with pyproj, then ``origin`` is subtracted.
* A DEM is a north-up raster in the georeference CRS with heights in metres,
  read from GeoTIFF (``.tif``/``.tiff``) or ESRI ASCII grid (``.asc``).
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
import re
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import numpy.typing as npt

from napari_imgreg._atomic import atomic_path
from napari_imgreg.errors import InputError

__all__ = [
    "GeoError",
    "Georef",
    "DEM",
    "GeoRaster",
    "read_geotiff",
    "camera_altitude",
    "DEFAULT_HEIGHT_ABOVE_GROUND_M",
]

#: Default camera height above the DEM surface (hand-held, eye level), metres.
DEFAULT_HEIGHT_ABOVE_GROUND_M = 1.6

#: Value written for NaN cells in GeoTIFF / ASCII grid files.
NODATA_WRITE = -9999.0

# GeoTIFF tag codes (GeoTIFF 1.1 spec, OGC 19-008r4) and GDAL's nodata tag.
_TAG_MODEL_PIXEL_SCALE = 33550
_TAG_MODEL_TIEPOINT = 33922
_TAG_MODEL_TRANSFORMATION = 34264
_TAG_GEO_KEY_DIRECTORY = 34735
_TAG_GDAL_NODATA = 42113
# GeoKey ids and values.
_KEY_GT_MODEL_TYPE = 1024  # 1 = projected, 2 = geographic
_KEY_GT_RASTER_TYPE = 1025  # 1 = PixelIsArea, 2 = PixelIsPoint
_KEY_GEOGRAPHIC_TYPE = 2048
_KEY_PROJECTED_CS_TYPE = 3072
_RASTER_PIXEL_IS_AREA = 1
_RASTER_PIXEL_IS_POINT = 2
_USER_DEFINED = 32767

_DEM_EXTENSIONS = (".tif", ".tiff", ".asc")


class GeoError(InputError):
    """Bad georeference / DEM input or a query the DEM cannot answer.

    A :class:`~napari_imgreg.errors.InputError` (hence a ``ValueError``), so
    the command line and widgets report it as one line. The message names the
    file involved (path or basename) and the problem.
    """


# ---------------------------------------------------------------------------
# small helpers
# ---------------------------------------------------------------------------


def _atomic_write(path: str | os.PathLike[str], write: Callable[[str], None]) -> None:
    """Call ``write(tmp)`` on a temp file beside ``path``, then rename it over
    ``path`` (readers see the old file or the complete new one, never half)."""
    with atomic_path(path) as tmp:
        write(os.fspath(tmp))


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
        text = json.dumps(self.to_dict(), indent=2) + "\n"

        def write(tmp: str) -> None:
            with open(tmp, "w", encoding="utf-8") as f:
                f.write(text)
                f.flush()
                os.fsync(f.fileno())

        _atomic_write(path, write)

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


def _exact_inverse(target: float, forward: Callable[[float], float], guess: float) -> float:
    """Nudge ``guess`` by a few ulps so that ``forward(value) == target``.

    Files store the pixel CORNER while we keep the pixel CENTRE; this makes
    ``load(save(dem))`` reproduce ``x0``/``y0`` bit for bit instead of to
    within one rounding error.  Falls back to ``guess`` if no such value.
    """
    if forward(guess) == target:
        return guess
    up = down = guess
    for _ in range(16):
        up = float(np.nextafter(up, math.inf))
        if forward(up) == target:
            return up
        down = float(np.nextafter(down, -math.inf))
        if forward(down) == target:
            return down
    return guess


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
        p = Path(path)
        ext = p.suffix.lower()
        if ext not in _DEM_EXTENSIONS:
            raise GeoError(
                f"{p}: unknown DEM file type {p.suffix!r}; expected one of "
                + ", ".join(_DEM_EXTENSIONS)
            )
        if not p.is_file():
            raise GeoError(f"{p}: file not found")
        if ext == ".asc":
            return _read_asc(p)
        return _read_geotiff_dem(p)

    # -- writing -------------------------------------------------------------

    def save_geotiff(self, path: str | os.PathLike[str]) -> None:
        """Write a float32 GeoTIFF (PixelIsArea, NaN → -9999 + GDAL_NODATA).

        Atomic (temp file + ``os.replace``). ``crs`` must be ``None`` or have
        an EPSG code; a compound CRS stores its horizontal part only.
        """
        import tifffile

        keys: list[tuple[int, int]] = [
            (_KEY_GT_MODEL_TYPE, 1),
            (_KEY_GT_RASTER_TYPE, _RASTER_PIXEL_IS_AREA),
        ]
        if self.crs is not None:
            code, geographic = _epsg_of(self.crs, os.fspath(path))
            if geographic:
                keys[0] = (_KEY_GT_MODEL_TYPE, 2)
                keys.append((_KEY_GEOGRAPHIC_TYPE, code))
            else:
                keys.append((_KEY_PROJECTED_CS_TYPE, code))
        geokeys = [1, 1, 0, len(keys)]
        for key_id, value in sorted(keys):
            geokeys += [key_id, 0, 1, value]

        # PixelIsArea: the tiepoint is the top-left pixel's outer corner.
        dx, dy = self.dx, self.dy
        cx = _exact_inverse(self.x0, lambda c: c + 0.5 * dx, self.x0 - 0.5 * dx)
        cy = _exact_inverse(self.y0, lambda c: c - 0.5 * dy, self.y0 + 0.5 * dy)
        data = np.where(np.isnan(self.heights), NODATA_WRITE, self.heights).astype(np.float32)
        extratags = [
            (_TAG_MODEL_PIXEL_SCALE, "d", 3, (dx, dy, 0.0), True),
            (_TAG_MODEL_TIEPOINT, "d", 6, (0.0, 0.0, 0.0, cx, cy, 0.0), True),
            (_TAG_GEO_KEY_DIRECTORY, "H", len(geokeys), tuple(geokeys), True),
            (_TAG_GDAL_NODATA, "s", 0, _fmt_nodata(NODATA_WRITE), True),
        ]

        def write(tmp: str) -> None:
            tifffile.imwrite(
                tmp,
                data,
                photometric="minisblack",
                compression="zlib",  # deflate: every GeoTIFF reader has it
                metadata=None,  # no tifffile JSON description
                extratags=extratags,
            )

        _atomic_write(path, write)

    def save_asc(self, path: str | os.PathLike[str]) -> None:
        """Write an ESRI ASCII grid (``xllcorner``; NaN → -9999). Atomic.

        Uses ``cellsize`` when ``dx == dy``, otherwise GDAL's ``dx``/``dy``
        header keys. When ``crs`` is set, an ESRI ``.prj`` sidecar is written
        too so that :meth:`load` recovers it.
        """
        rows, cols = self.heights.shape
        dx, dy = self.dx, self.dy
        xll = _exact_inverse(self.x0, lambda c: c + 0.5 * dx, self.x0 - 0.5 * dx)
        # reader: y0 = yllcorner + 0.5*dy + (rows-1)*dy
        yll = _exact_inverse(
            self.y0,
            lambda c: (c + 0.5 * dy) + (rows - 1) * dy,
            self.y0 - (rows - 1) * dy - 0.5 * dy,
        )
        lines = [f"ncols {cols}", f"nrows {rows}", f"xllcorner {xll!r}", f"yllcorner {yll!r}"]
        lines += [f"cellsize {dx!r}"] if dx == dy else [f"dx {dx!r}", f"dy {dy!r}"]
        lines.append(f"NODATA_value {_fmt_nodata(NODATA_WRITE)}")
        nod = _fmt_nodata(NODATA_WRITE)
        body = "\n".join(
            " ".join(nod if math.isnan(v) else repr(float(v)) for v in row)
            for row in self.heights
        )
        text = "\n".join(lines) + "\n" + body + "\n"

        def write(tmp: str) -> None:
            with open(tmp, "w", encoding="ascii") as f:
                f.write(text)

        prj_text = None
        if self.crs is not None:
            import pyproj

            prj_text = pyproj.CRS.from_user_input(self.crs).to_wkt(version="WKT1_ESRI")
        _atomic_write(path, write)
        if prj_text is not None:

            def write_prj(tmp: str) -> None:
                with open(tmp, "w", encoding="ascii") as f:
                    f.write(prj_text)

            _atomic_write(Path(path).with_suffix(".prj"), write_prj)

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


# ---------------------------------------------------------------------------
# file formats
# ---------------------------------------------------------------------------


def _fmt_nodata(v: float) -> str:
    return str(int(v)) if float(v).is_integer() else repr(float(v))


def _epsg_of(crs: str, source: str) -> tuple[int, bool]:
    """``(EPSG code, is_geographic)`` of the horizontal part of ``crs``."""
    import pyproj

    try:
        c = pyproj.CRS.from_user_input(crs)
    except pyproj.exceptions.CRSError as exc:
        raise GeoError(f"{source}: DEM crs {crs!r} is not a valid CRS ({exc})") from None
    if c.is_compound:  # GeoTIFF keys here carry the horizontal part only
        c = c.sub_crs_list[0]
    code = c.to_epsg()
    if code is None or not 0 < code < _USER_DEFINED:
        raise GeoError(
            f"{source}: DEM crs {crs!r} has no EPSG code, so it cannot be stored in GeoTIFF keys"
        )
    return code, bool(c.is_geographic)


def _mask_nodata(data: np.ndarray, nodata: float | None) -> np.ndarray:
    """float64 copy of ``data`` with ``nodata`` (compared in ``data``'s dtype) → NaN."""
    out = data.astype(np.float64)
    if nodata is None or math.isnan(nodata):
        return out  # NaN nodata is already NaN
    if np.issubdtype(data.dtype, np.floating):
        # GDAL writes e.g. -3.4028234663852886e+38 for float32: compare in float32.
        with np.errstate(over="ignore"):
            out[data == np.asarray(nodata).astype(data.dtype)] = np.nan
    elif float(nodata).is_integer():
        info = np.iinfo(data.dtype)
        if info.min <= nodata <= info.max:
            out[data == int(nodata)] = np.nan
    return out


@dataclass(eq=False)
class GeoRaster:
    """A north-up GeoTIFF image as stored (any dtype, any number of bands).

    Parameters
    ----------
    data : ndarray, shape (rows, cols) or (rows, cols, bands)
        Samples as stored (no nodata masking); row 0 is the NORTH row.
    x0, y0 : float
        CRS coordinates (m) of the CENTRE of the top-left pixel.
    dx, dy : float
        Positive pixel spacings (m); row ``r`` has northing ``y0 - r*dy``.
    crs : str or None
        ``"EPSG:<code>"`` from the GeoKeys, if any.
    nodata : float or None
        The ``GDAL_NODATA`` value, if any.
    source : str
        File name for messages.
    """

    data: np.ndarray
    x0: float
    y0: float
    dx: float
    dy: float
    crs: str | None = None
    nodata: float | None = None
    source: str = "<array>"


def read_geotiff(path: str | os.PathLike[str]) -> GeoRaster:
    """Read a north-up GeoTIFF (first page) with its georeferencing.

    Understands ModelPixelScaleTag + ModelTiepointTag or a north-up
    ModelTransformationTag, GTRasterTypeGeoKey (PixelIsArea: the tiepoint is
    the pixel's outer corner; PixelIsPoint: its centre),
    ProjectedCSTypeGeoKey (or GeographicTypeGeoKey for geographic files) and
    GDAL_NODATA. Bottom-up files (negative y scale) are flipped to north-up.

    Raises
    ------
    GeoError
        Missing, unreadable or un-georeferenced file, rotated raster; the
        message names the file.
    """
    import tifffile

    p = Path(path)
    if not p.is_file():
        raise GeoError(f"{p}: file not found")
    try:
        with tifffile.TiffFile(p) as tf:
            page = tf.pages[0]
            tags = {t.code: t.value for t in page.tags}
            data = np.asarray(page.asarray())
            spp = int(page.samplesperpixel)
            contig = int(page.planarconfig) == 1
            nrows, ncols = int(page.imagelength), int(page.imagewidth)
    except Exception as exc:  # tifffile raises many types for junk input
        raise GeoError(f"{p}: cannot read as TIFF ({type(exc).__name__}: {exc})") from None

    # Bands last: planar files come as (bands, rows, cols).
    if data.ndim == 3 and spp > 1 and not contig:
        data = np.moveaxis(data, 0, -1)
    if data.shape[:2] != (nrows, ncols) or data.ndim not in (2, 3):
        raise GeoError(f"{p}: unsupported TIFF layout (image data shape {data.shape})")

    # GeoKeys: (version, revision, minor, count) then (id, location, count, value).
    keys: dict[int, int] = {}
    gk = tags.get(_TAG_GEO_KEY_DIRECTORY)
    if gk is not None:
        gk = [int(v) for v in gk]
        nkeys = gk[3] if len(gk) >= 4 else 0
        for i in range(4, 4 + 4 * nkeys, 4):
            if i + 3 < len(gk) and gk[i + 1] == 0:  # location 0: value inline
                keys[gk[i]] = gk[i + 3]
    raster_type = keys.get(_KEY_GT_RASTER_TYPE, _RASTER_PIXEL_IS_AREA)
    if raster_type not in (_RASTER_PIXEL_IS_AREA, _RASTER_PIXEL_IS_POINT):
        raise GeoError(f"{p}: unknown GTRasterTypeGeoKey value {raster_type}")
    # Raster coordinate of the top-left pixel's centre: PixelIsArea puts
    # raster (0, 0) on its outer corner, PixelIsPoint on its centre.
    off = 0.5 if raster_type == _RASTER_PIXEL_IS_AREA else 0.0

    crs: str | None = None
    pcs = keys.get(_KEY_PROJECTED_CS_TYPE)
    gcs = keys.get(_KEY_GEOGRAPHIC_TYPE)
    if pcs is not None and 0 < pcs < _USER_DEFINED:
        crs = f"EPSG:{pcs}"
    elif keys.get(_KEY_GT_MODEL_TYPE) == 2 and gcs is not None and 0 < gcs < _USER_DEFINED:
        crs = f"EPSG:{gcs}"

    if _TAG_MODEL_TRANSFORMATION in tags:
        m = np.asarray(tags[_TAG_MODEL_TRANSFORMATION], dtype=np.float64)
        if m.size != 16:
            raise GeoError(f"{p}: ModelTransformationTag must hold 16 numbers, has {m.size}")
        m = m.reshape(4, 4)
        if m[0, 1] != 0 or m[1, 0] != 0 or not (m[0, 0] > 0 and m[1, 1] < 0):
            raise GeoError(
                f"{p}: rotated or flipped raster (ModelTransformationTag); "
                "only north-up rasters are supported, warp it first (e.g. gdalwarp)"
            )
        dx, dy = float(m[0, 0]), float(-m[1, 1])
        x0 = float(m[0, 3] + off * dx)
        y0 = float(m[1, 3] - off * dy)
    elif _TAG_MODEL_PIXEL_SCALE in tags and _TAG_MODEL_TIEPOINT in tags:
        scale = np.asarray(tags[_TAG_MODEL_PIXEL_SCALE], dtype=np.float64)
        tie = np.asarray(tags[_TAG_MODEL_TIEPOINT], dtype=np.float64)
        if scale.size < 2 or tie.size < 6:
            raise GeoError(f"{p}: malformed ModelPixelScaleTag/ModelTiepointTag")
        if tie.size > 6:
            raise GeoError(f"{p}: multiple tiepoints (unrectified raster) are not supported")
        dx, sy = float(scale[0]), float(scale[1])
        i_t, j_t, x_t, y_t = tie[0], tie[1], tie[3], tie[4]
        if not (dx > 0 and math.isfinite(dx)) or sy == 0 or not math.isfinite(sy):
            raise GeoError(f"{p}: invalid pixel scale ({dx}, {sy})")
        # Model = tiepoint + (raster - tie raster) * scale, raster y pointing down.
        x0 = float(x_t + (off - i_t) * dx)
        y0 = float(y_t - (off - j_t) * sy)
        if sy < 0:  # rows run north (bottom-up file): flip to north-up
            data = data[::-1]
            y0 = float(y0 - (nrows - 1) * sy)
        dy = abs(sy)
    else:
        raise GeoError(
            f"{p}: no GeoTIFF georeferencing (needs ModelPixelScaleTag + "
            "ModelTiepointTag or ModelTransformationTag)"
        )

    nodata: float | None = None
    nd = tags.get(_TAG_GDAL_NODATA)
    if nd is not None:
        s = (nd.decode("ascii", "replace") if isinstance(nd, bytes) else str(nd)).strip("\x00 ")
        try:
            nodata = float(s)
        except ValueError:
            raise GeoError(f"{p}: GDAL_NODATA tag {s!r} is not a number") from None
    return GeoRaster(data, x0, y0, dx, dy, crs=crs, nodata=nodata, source=p.name)


def _read_geotiff_dem(p: Path) -> DEM:
    r = read_geotiff(p)
    data = r.data[..., 0] if r.data.ndim == 3 else r.data  # first band
    if not (np.issubdtype(data.dtype, np.floating) or np.issubdtype(data.dtype, np.integer)):
        raise GeoError(f"{p}: unsupported sample type {data.dtype} for a DEM")
    heights = _mask_nodata(data, r.nodata)
    return DEM(heights, r.x0, r.y0, r.dx, r.dy, crs=r.crs, source=r.source)


_ASC_KEYS = {
    "ncols",
    "nrows",
    "xllcorner",
    "xllcenter",
    "yllcorner",
    "yllcenter",
    "cellsize",
    "dx",
    "dy",
    "nodata_value",
}


def _read_asc(p: Path) -> DEM:
    try:
        text = p.read_text(encoding="ascii", errors="strict")
    except (OSError, UnicodeDecodeError) as exc:
        raise GeoError(f"{p}: cannot read as an ESRI ASCII grid ({exc})") from None

    # Header: "key value" lines until the first line starting with a number.
    header: dict[str, str] = {}
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        parts = lines[i].split()
        if not parts:
            i += 1
            continue
        key = parts[0].lower()
        if re.match(r"^[+-]?(\d|\.\d|nan|inf)", key):
            break
        if key not in _ASC_KEYS or len(parts) != 2:
            raise GeoError(f"{p}: bad ESRI ASCII grid header line {lines[i].strip()!r}")
        if key in header:
            raise GeoError(f"{p}: header key {parts[0]!r} appears twice")
        header[key] = parts[1]
        i += 1

    def num(key: str) -> float:
        try:
            v = float(header[key])
        except ValueError:
            raise GeoError(f"{p}: header {key} {header[key]!r} is not a number") from None
        if not math.isfinite(v):
            raise GeoError(f"{p}: header {key} must be finite")
        return v

    for k in ("ncols", "nrows"):
        if k not in header:
            raise GeoError(f"{p}: header is missing {k!r}")
    ncols, nrows = num("ncols"), num("nrows")
    if not (ncols.is_integer() and nrows.is_integer() and ncols > 0 and nrows > 0):
        raise GeoError(f"{p}: ncols/nrows must be positive integers")
    ncols_i, nrows_i = int(ncols), int(nrows)

    if "cellsize" in header:
        if "dx" in header or "dy" in header:
            raise GeoError(f"{p}: header has both 'cellsize' and 'dx'/'dy'")
        dx = dy = num("cellsize")
    elif "dx" in header and "dy" in header:
        dx, dy = num("dx"), num("dy")
    else:
        raise GeoError(f"{p}: header is missing 'cellsize' (or 'dx' and 'dy')")
    if dx <= 0 or dy <= 0:
        raise GeoError(f"{p}: cell size must be positive")

    def ll(axis: str, step: float) -> float:
        corner, centre = f"{axis}llcorner", f"{axis}llcenter"
        if (corner in header) == (centre in header):
            raise GeoError(f"{p}: header needs exactly one of {corner!r} or {centre!r}")
        # xllcorner is the outer corner of the lower-left cell: centre is half a cell in.
        return num(corner) + 0.5 * step if corner in header else num(centre)

    x0 = ll("x", dx)
    y0 = ll("y", dy) + (nrows_i - 1) * dy  # row 0 of the file is the NORTH row
    nodata = num("nodata_value") if "nodata_value" in header else None

    try:
        values = np.array(" ".join(lines[i:]).split(), dtype=np.float64)
    except ValueError as exc:
        raise GeoError(f"{p}: non-numeric value in the grid ({exc})") from None
    if values.size != nrows_i * ncols_i:
        raise GeoError(
            f"{p}: grid has {values.size} values, header says {nrows_i} x {ncols_i} = "
            f"{nrows_i * ncols_i}"
        )
    heights = values.reshape(nrows_i, ncols_i)
    if nodata is not None:
        heights[heights == nodata] = np.nan

    crs: str | None = None
    prj = p.with_suffix(".prj")
    if prj.is_file():  # optional ESRI sidecar
        import pyproj

        try:
            c = pyproj.CRS.from_user_input(prj.read_text(encoding="utf-8", errors="replace"))
        except pyproj.exceptions.CRSError as exc:
            raise GeoError(f"{prj}: not a valid CRS ({exc})") from None
        code = c.to_epsg()
        crs = f"EPSG:{code}" if code is not None else c.to_string()
    return DEM(heights, x0, y0, dx, dy, crs=crs, source=p.name)
