"""Georeferenced rasters on disk: GeoTIFF and ESRI ASCII grid, read and written.

The file side of :mod:`napari_imgreg.geo`: :func:`read_geotiff` reads any
north-up GeoTIFF (orthophotos, DEMs) with its georeferencing;
:func:`read_dem_raster` reads a height grid (GeoTIFF or ``.asc``) and
:func:`write_dem_geotiff` / :func:`write_dem_asc` write one. They take and
give plain arrays with their grid geometry; :class:`napari_imgreg.geo.DEM`
is built from them (``DEM.load``, ``DEM.save_geotiff``, ``DEM.save_asc``).

Grid geometry (as :class:`napari_imgreg.geo.DEM`'s): north-up, row 0 the
NORTH row; ``x0, y0`` the CRS coordinates (m) of the CENTRE of the top-left
pixel; ``dx, dy`` positive spacings, so that column ``c`` has easting
``x0 + c*dx`` and row ``r`` northing ``y0 - r*dy``. Files store the pixel
corner (PixelIsArea, ``xllcorner``); :func:`_exact_inverse` makes a round
trip reproduce ``x0``/``y0`` bit for bit.

Every problem with a file raises one :class:`GeoError` whose message starts
with the file and says what is wrong.

This module is backend only: no Qt or napari imports.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import re
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from .._atomic import atomic_path
from ..errors import InputError

__all__ = [
    "GeoError",
    "GeoRaster",
    "NODATA_WRITE",
    "read_geotiff",
    "read_dem_raster",
    "write_dem_geotiff",
    "write_dem_asc",
    "quiet_tifffile",
]

log = logging.getLogger(__name__)

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


#: Largest raster read, cells × bands (250 M: a 15,800² DEM, 1 GB as float32).
MAX_RASTER_CELLS = 250_000_000


class _TifffileToDebug(logging.Filter):
    """Turns tifffile's log records into debug records of ours while the
    thread that logs them is inside :func:`quiet_tifffile`."""

    def __init__(self) -> None:
        super().__init__()
        self.depth = threading.local()  # other threads' tifffile logs are theirs

    def filter(self, record: logging.LogRecord) -> bool:
        if not getattr(self.depth, "n", 0):
            return True
        log.debug("tifffile: %s", record.getMessage())
        return False


_TIFFFILE_TO_DEBUG = _TifffileToDebug()


@contextlib.contextmanager
def quiet_tifffile() -> Iterator[None]:
    """Keep tifffile's own log lines (``<TiffTag.fromfile> raised ...``, one
    per bad tag of a corrupt file) off stderr while reading a raster here.

    The reader turns a file it cannot use into one error that names it; the
    lines tifffile logs on the way there would come first and bury it. They
    are kept as debug records of this module. Only the calling thread's
    records are held back.
    """
    logging.getLogger("tifffile").addFilter(_TIFFFILE_TO_DEBUG)  # once: addFilter ignores repeats
    depth = _TIFFFILE_TO_DEBUG.depth
    depth.n = getattr(depth, "n", 0) + 1
    try:
        yield
    finally:
        depth.n -= 1


class _TooLarge(Exception):
    """A raster header claims more cells than :data:`MAX_RASTER_CELLS`."""


class GeoError(InputError):
    """Bad georeference / DEM input or a query the DEM cannot answer.

    A :class:`~napari_imgreg.errors.InputError` (hence a ``ValueError``), so
    the command line and widgets report it as one line. The message names the
    file involved (path or basename) and the problem. Defined here, with the
    file readers that raise it, and public as :class:`napari_imgreg.geo.GeoError`.
    """


def _atomic_write(path: str | os.PathLike[str], write: Callable[[str], None]) -> None:
    """Call ``write(tmp)`` on a temp file beside ``path``, then rename it over
    ``path`` (readers see the old file or the complete new one, never half)."""
    with atomic_path(path) as tmp:
        write(os.fspath(tmp))


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


# ---------------------------------------------------------------------------
# reading
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
        with quiet_tifffile(), tifffile.TiffFile(p) as tf:
            page = tf.pages[0]
            # Checked before decoding: a corrupt header can claim any size.
            cells = int(page.imagelength) * int(page.imagewidth) * int(page.samplesperpixel)
            if cells > MAX_RASTER_CELLS:
                raise _TooLarge(f"{page.imagewidth}×{page.imagelength} cells is more than "
                                f"{MAX_RASTER_CELLS:,} (a corrupt header, or a DEM to tile)")
            # tifffile allocates what the strips or tiles declare: a corrupt
            # byte count asked for gigabytes of a file of a few hundred bytes.
            size = p.stat().st_size
            offsets = np.asarray(page.dataoffsets, np.int64)
            counts = np.asarray(page.databytecounts, np.int64)
            if len(offsets) != len(counts) or np.any(offsets + counts > size):
                raise _TooLarge("its image data runs past the end of the file "
                                "(truncated or corrupt)")
            # ... and fills the strips or tiles its size needs but the file
            # does not list with zeros: one flipped byte of a 408-byte file
            # made 16.5 million rows of zero heights, decoded for 20 s.
            needed = math.prod(page.chunked)
            if len(offsets) != needed:
                raise _TooLarge(f"its size ({page.imagewidth}×{page.imagelength}) needs "
                                f"{needed:,} strips or tiles of image data and the file "
                                f"lists {len(offsets):,} (truncated or corrupt)")
            tags = {t.code: t.value for t in page.tags}
            data = np.asarray(page.asarray())
            spp = int(page.samplesperpixel)
            contig = int(page.planarconfig) == 1
            nrows, ncols = int(page.imagelength), int(page.imagewidth)
    except _TooLarge as exc:
        raise GeoError(f"{p}: {exc}") from None
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


def read_dem_raster(path: str | os.PathLike[str]) -> GeoRaster:
    """Read a height grid from ``.tif``/``.tiff`` (GeoTIFF) or ``.asc`` (ESRI ASCII grid).

    The file side of :meth:`napari_imgreg.geo.DEM.load`, which builds the DEM.

    Returns
    -------
    GeoRaster
        ``data``: (rows, cols) float64 heights, metres, nodata already NaN
        (hence ``nodata`` None); first band of a multi-band GeoTIFF; row 0
        the NORTH row. ``crs`` from the GeoKeys or the ``.prj`` sidecar.

    Raises
    ------
    GeoError
        Missing file, unknown extension, unreadable or un-georeferenced
        content; the message names the file.
    """
    p = Path(path)
    ext = p.suffix.lower()
    if p.is_dir():
        raise GeoError(f"{p}: is a folder, not a DEM file ({', '.join(_DEM_EXTENSIONS)})")
    if ext not in _DEM_EXTENSIONS:
        raise GeoError(
            f"{p}: unknown DEM file type {p.suffix!r}; expected one of "
            + ", ".join(_DEM_EXTENSIONS)
        )
    if not p.is_file():
        raise GeoError(f"{p}: file not found")
    if ext == ".asc":
        return _read_asc(p)
    return _read_geotiff_heights(p)


def _read_geotiff_heights(p: Path) -> GeoRaster:
    r = read_geotiff(p)
    data = r.data[..., 0] if r.data.ndim == 3 else r.data  # first band
    if not (np.issubdtype(data.dtype, np.floating) or np.issubdtype(data.dtype, np.integer)):
        raise GeoError(f"{p}: unsupported sample type {data.dtype} for a DEM")
    heights = _mask_nodata(data, r.nodata)
    return GeoRaster(heights, r.x0, r.y0, r.dx, r.dy, crs=r.crs, source=r.source)


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


def _read_asc(p: Path) -> GeoRaster:
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
    return GeoRaster(heights, x0, y0, dx, dy, crs=crs, source=p.name)


# ---------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------


def write_dem_geotiff(
    path: str | os.PathLike[str],
    heights: np.ndarray,
    x0: float,
    y0: float,
    dx: float,
    dy: float,
    crs: str | None = None,
) -> None:
    """Write a height grid as a float32 GeoTIFF (PixelIsArea, NaN → -9999 + GDAL_NODATA).

    Atomic (temp file + ``os.replace``). The geometry is
    :class:`napari_imgreg.geo.DEM`'s, whose :meth:`~napari_imgreg.geo.DEM.save_geotiff`
    calls this.

    Parameters
    ----------
    path : path-like
    heights : (rows, cols) float array
        Metres; NaN is nodata; row 0 is the NORTH row.
    x0, y0 : float
        CRS coordinates (m) of the CENTRE of the top-left pixel.
    dx, dy : float
        Positive pixel spacings, metres.
    crs : str or None
        Must be None or have an EPSG code; a compound CRS stores its
        horizontal part only.

    Raises
    ------
    GeoError
        A CRS without EPSG code.
    """
    import tifffile

    heights = np.asarray(heights, np.float64)
    x0, y0, dx, dy = float(x0), float(y0), float(dx), float(dy)

    keys: list[tuple[int, int]] = [
        (_KEY_GT_MODEL_TYPE, 1),
        (_KEY_GT_RASTER_TYPE, _RASTER_PIXEL_IS_AREA),
    ]
    if crs is not None:
        code, geographic = _epsg_of(crs, os.fspath(path))
        if geographic:
            keys[0] = (_KEY_GT_MODEL_TYPE, 2)
            keys.append((_KEY_GEOGRAPHIC_TYPE, code))
        else:
            keys.append((_KEY_PROJECTED_CS_TYPE, code))
    geokeys = [1, 1, 0, len(keys)]
    for key_id, value in sorted(keys):
        geokeys += [key_id, 0, 1, value]

    # PixelIsArea: the tiepoint is the top-left pixel's outer corner.
    cx = _exact_inverse(x0, lambda c: c + 0.5 * dx, x0 - 0.5 * dx)
    cy = _exact_inverse(y0, lambda c: c - 0.5 * dy, y0 + 0.5 * dy)
    data = np.where(np.isnan(heights), NODATA_WRITE, heights).astype(np.float32)
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


def write_dem_asc(
    path: str | os.PathLike[str],
    heights: np.ndarray,
    x0: float,
    y0: float,
    dx: float,
    dy: float,
    crs: str | None = None,
) -> None:
    """Write a height grid as an ESRI ASCII grid (``xllcorner``; NaN → -9999). Atomic.

    Uses ``cellsize`` when ``dx == dy``, otherwise GDAL's ``dx``/``dy``
    header keys. When ``crs`` is set, an ESRI ``.prj`` sidecar is written
    too so that :func:`read_dem_raster` recovers it. Parameters as for
    :func:`write_dem_geotiff`.
    """
    heights = np.asarray(heights, np.float64)
    x0, y0, dx, dy = float(x0), float(y0), float(dx), float(dy)
    rows, cols = heights.shape
    xll = _exact_inverse(x0, lambda c: c + 0.5 * dx, x0 - 0.5 * dx)
    # reader: y0 = yllcorner + 0.5*dy + (rows-1)*dy
    yll = _exact_inverse(
        y0,
        lambda c: (c + 0.5 * dy) + (rows - 1) * dy,
        y0 - (rows - 1) * dy - 0.5 * dy,
    )
    lines = [f"ncols {cols}", f"nrows {rows}", f"xllcorner {xll!r}", f"yllcorner {yll!r}"]
    lines += [f"cellsize {dx!r}"] if dx == dy else [f"dx {dx!r}", f"dy {dy!r}"]
    lines.append(f"NODATA_value {_fmt_nodata(NODATA_WRITE)}")
    nod = _fmt_nodata(NODATA_WRITE)
    body = "\n".join(
        " ".join(nod if math.isnan(v) else repr(float(v)) for v in row)
        for row in heights
    )
    text = "\n".join(lines) + "\n" + body + "\n"

    def write(tmp: str) -> None:
        with open(tmp, "w", encoding="ascii") as f:
            f.write(text)

    prj_text = None
    if crs is not None:
        import pyproj

        prj_text = pyproj.CRS.from_user_input(crs).to_wkt(version="WKT1_ESRI")
    _atomic_write(path, write)
    if prj_text is not None:

        def write_prj(tmp: str) -> None:
            with open(tmp, "w", encoding="ascii") as f:
                f.write(prj_text)

        _atomic_write(Path(path).with_suffix(".prj"), write_prj)
