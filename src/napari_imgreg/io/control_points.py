"""Control-point files: pairs of a photo pixel and the model point it shows (CSV).

The file behind manual registration from a file (``napari-imgreg register
--pairs``) and the workbench's *Save pairs…* / *Load pairs…*
(``docs/formats.md``, "Control points"). One row per pair, a header first::

    photo_x,photo_y,x,y,z,name
    512.250,301.750,-3.1042,10.5518,4.2071,GCP1

``photo_x, photo_y``: the photo pixel (x = column, y = row), the first
pixel's centre at (0, 0). ``x, y, z``: the model point, model frame, metres.
Instead of ``x, y, z`` the point may be given in the georeference's CRS as
``easting, northing, elevation`` (a GNSS survey of targets), or as WGS84
``latitude, longitude`` (degrees) with ``elevation``; either is taken into
the model frame with the scene's georeference (:meth:`ControlPoints.model_xyz`).
``elevation`` is a height in the model's vertical datum (the DEM's and the
georeference origin's), as the sensor record's altitude is: a GNSS receiver's
ellipsoidal heights must be converted first (:meth:`ControlPoints.check_heights`
refuses points tens of metres above or below the surface).
``name`` is optional. Commas, semicolons or tabs separate fields; blank lines
and lines starting with ``#`` are skipped; other columns are ignored.

Pixels of a reference render (``render_x, render_y``) are not read: the
workbench writes each pair's model point, which needs no render to be
repeated, and other tools give model or CRS coordinates.

Every problem is one :class:`~napari_imgreg.errors.InputError` naming the file,
the row (its line number, the header being row 1 when it is the first line)
and the problem.
"""

from __future__ import annotations

import csv
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np

from .._atomic import atomic_write
from ..errors import input_error
from ._table_csv import cell_number, header_excerpt, read_table_rows

if TYPE_CHECKING:  # only the georeference's crs_to_local is used
    from ..geo import Georef

__all__ = [
    "ControlPoints",
    "read_control_points",
    "write_control_points",
    "PIXEL_COLUMNS",
    "MODEL_COLUMNS",
    "CRS_COLUMNS",
    "GEODETIC_COLUMNS",
]

#: The photo pixel of each pair.
PIXEL_COLUMNS = ("photo_x", "photo_y")
#: The model point in the model frame, metres.
MODEL_COLUMNS = ("x", "y", "z")
#: The model point in the georeference's CRS (``crs = local + origin``), metres.
CRS_COLUMNS = ("easting", "northing", "elevation")
#: The model point as WGS84 latitude and longitude (degrees) and a height in
#: the georeference's vertical datum (metres).
GEODETIC_COLUMNS = ("latitude", "longitude", "elevation")
#: Each way of giving the model point, and the frame it is in.
_POINT_COLUMNS = {"model": MODEL_COLUMNS, "crs": CRS_COLUMNS, "geodetic": GEODETIC_COLUMNS}
#: A point whose nearest model vertex is more than this far (metres), mostly
#: straight above or below it, is not on the model (:meth:`ControlPoints.check_heights`).
HEIGHT_OFFSET_M = 10.0
_RENDER_COLUMNS = ("render_x", "render_y")


@dataclass
class ControlPoints:
    """The pairs of a control-point file.

    Attributes
    ----------
    photo_px : (N, 2) float array
        Photo pixels (x, y), pixel-centre convention (first centre at (0, 0)).
    xyz : (N, 3) float array
        The model points as the file gives them: model frame (``frame ==
        "model"``, metres), the georeference's CRS (``frame == "crs"``,
        metres) or WGS84 latitude, longitude (degrees) and elevation (metres)
        (``frame == "geodetic"``). :meth:`model_xyz` gives them in the model
        frame either way.
    names : list of str
        Each pair's ``name`` ("" when the file has none).
    rows : list of int
        Each pair's line number in the file, for messages.
    frame : {"model", "crs", "geodetic"}
    source : Path or None
        The file read.
    """

    photo_px: np.ndarray
    xyz: np.ndarray
    names: list[str] = field(default_factory=list)
    rows: list[int] = field(default_factory=list)
    frame: str = "model"
    source: Path | None = None

    def __len__(self) -> int:
        return len(self.photo_px)

    def model_xyz(self, georef: Georef | None) -> np.ndarray:
        """The model points in the model frame, (N, 3) metres.

        Raises
        ------
        InputError
            CRS coordinates but no georeference to take them into the model frame.
        """
        if self.frame == "model":
            return self.xyz.copy()
        if georef is None:
            columns = ",".join(_POINT_COLUMNS[self.frame])
            raise input_error(self.source, f"points are given as {columns} "
                              "but the model has no georeference (georef.json beside it, or "
                              "--georef): give x,y,z in the model frame instead")
        if self.frame == "crs":
            return np.asarray(georef.crs_to_local(self.xyz), np.float64).reshape(-1, 3)
        from .rasters import GeoError  # geo's, defined beside the raster readers

        lat, lon, elevation = self.xyz.T
        try:
            return np.asarray(georef.geodetic_to_local(lat, lon, elevation),
                              np.float64).reshape(-1, 3)
        except GeoError as exc:
            raise input_error(self.source, str(exc)) from None

    def model_points_for(self, scene) -> np.ndarray:
        """The model points in ``scene``'s model frame, checked to be the model's.

        :meth:`check_not_degrees`, :meth:`model_xyz` through the scene's
        georeference, then :meth:`check_near_model` and :meth:`check_heights`.

        Parameters
        ----------
        scene : Scene or CloudScene

        Returns
        -------
        (N, 3) float array, model frame, metres.

        Raises
        ------
        InputError
            As those four methods.
        """
        georef = scene.georef
        self.check_not_degrees()
        xyz = self.model_xyz(georef)
        self.check_near_model(xyz, scene.bounds, georef.crs if georef is not None else None)
        self.check_heights(xyz, scene.vertices)
        return xyz

    def check_near_model(self, model_xyz: np.ndarray, bounds: np.ndarray,
                         crs: str | None = None) -> None:
        """Refuse control points far beyond the model: swapped or mislabelled
        columns, or coordinates of another CRS (latitude and longitude given
        as easting and northing), which no pose fits.

        Far is more than 1 km and ten times the model's diagonal from its
        bounding box, for the median point (a target on a pole, or on a hill
        behind the outcrop, is not far).

        Parameters
        ----------
        model_xyz : (N, 3) array
            The points in the model frame (:meth:`model_xyz`), metres.
        bounds : (2, 3) array
            The model's bounding box (min, max corners), model frame, metres.
        crs : str, optional
            The georeference's CRS, named in the message for CRS coordinates.

        Raises
        ------
        InputError
            ``"<file>: the control points lie a median 5333 km from the model ..."``.
        """
        lo, hi = np.asarray(bounds, float)
        outside = np.maximum(np.maximum(lo - model_xyz, model_xyz - hi), 0.0)
        distance = float(np.median(np.linalg.norm(outside, axis=1)))
        diagonal = float(np.linalg.norm(hi - lo))
        if distance <= max(1000.0, 10.0 * diagonal):
            return
        given = {
            "crs": f"easting,northing,elevation in {crs or 'the georeference'}'s coordinates "
                   "(not latitude and longitude)",
            "geodetic": "WGS84 latitude,longitude in degrees with the elevation in metres",
            "model": "x,y,z in the model frame (easting,northing,elevation for map "
                     "coordinates)",
        }[self.frame]
        far = f"{distance / 1000.0:.0f} km" if distance >= 10_000 else f"{distance:.0f} m"
        raise input_error(self.source, f"the control points lie a median {far} from the model "
                          f"({diagonal:.0f} m across): are columns swapped, or the coordinates "
                          f"of another system? They must be {given}")

    def check_not_degrees(self) -> None:
        """Refuse latitude and longitude given as ``x,y`` or ``easting,northing``.

        Refused when the points spread over less than a metre horizontally
        while each could be degrees (|first| ≤ 180 and |second| ≤ 90, or the
        other way round): a survey's targets in degrees span thousandths of
        a unit, and the points then lie near the model's origin, where no
        other check would catch them.

        Raises
        ------
        InputError
            ``"<file>: the control points' x,y span only 0.002 × 0.001: ..."``.
        """
        if self.frame == "geodetic" or len(self.xyz) < 2:
            return
        a, b = self.xyz[:, 0], self.xyz[:, 1]
        span = np.ptp(self.xyz[:, :2], axis=0)
        degrees = ((np.abs(a) <= 180).all() and (np.abs(b) <= 90).all()) or \
                  ((np.abs(a) <= 90).all() and (np.abs(b) <= 180).all())
        if span.max() >= 1.0 or not degrees:
            return
        names = _POINT_COLUMNS[self.frame][:2]
        raise input_error(self.source, f"the control points' {names[0]},{names[1]} span only "
                          f"{span[0]:.3g} × {span[1]:.3g}: are they latitude and longitude? "
                          "Give those as latitude,longitude,elevation")

    def check_heights(self, model_xyz: np.ndarray, surface_xyz: np.ndarray) -> None:
        """Refuse control points that float above or sink below the model:
        elevations in another height system than the model's (a GNSS
        receiver's ellipsoidal heights differ from the DEM's by up to ~100 m).
        A pose fits such points as well as the right ones, with the camera
        that far off, and lines mapped from it would miss the rock.

        Refused when the median point is more than :data:`HEIGHT_OFFSET_M`
        from its nearest model vertex, and three quarters of the points are
        that far on the same side, most of it (70 %) vertical. A target on
        the ground in front of a cliff the model does not cover is far from
        it sideways, not vertically, and passes. Only the model's vertices
        within 20 m of the points' extent in plan are searched; where they
        are sparse (more than 2.5 m apart on average: a few large
        triangles) the points are not checked.

        Parameters
        ----------
        model_xyz : (N, 3) array
            The points in the model frame (:meth:`model_xyz`), metres.
        surface_xyz : (M, 3) array
            The model's vertices (or a scan's points), model frame, metres.

        Raises
        ------
        InputError
            ``"<file>: the control points lie a median 41 m above the model's surface ..."``.
        """
        from scipy.spatial import cKDTree

        surface = np.asarray(surface_xyz).reshape(-1, 3)
        if len(surface) == 0 or len(model_xyz) == 0:
            return
        # Only the model under and around the points (in plan) can be below
        # or above them: the search is that small, not the whole model's
        # (this runs when a file is loaded, in the workbench on its GUI thread).
        reach = 2.0 * HEIGHT_OFFSET_M
        low, high = model_xyz[:, :2].min(axis=0) - reach, model_xyz[:, :2].max(axis=0) + reach
        near = np.all((surface[:, :2] >= low) & (surface[:, :2] <= high), axis=1)
        surface = np.asarray(surface[near], np.float64)
        if len(surface) == 0:
            return  # nothing of the model under the points: beside it, not above it
        # Its vertices stand for the surface only where they are dense: a
        # model of a few large triangles (a DEM, a test wall) is not checked.
        diagonal = float(np.linalg.norm(np.ptp(surface, axis=0)))
        if diagonal / np.sqrt(len(surface)) > HEIGHT_OFFSET_M / 4:
            return
        surface = surface[::max(len(surface) // 1_000_000, 1)]
        distance, nearest = cKDTree(surface).query(model_xyz)
        if float(np.median(distance)) <= HEIGHT_OFFSET_M:
            return
        dz = model_xyz[:, 2] - surface[nearest, 2]
        far = distance > HEIGHT_OFFSET_M
        vertical = far & (np.abs(dz) >= 0.7 * distance)
        above, below = int((vertical & (dz > 0)).sum()), int((vertical & (dz < 0)).sum())
        if max(above, below) < 0.75 * len(model_xyz):
            return
        side = "above" if above >= below else "below"
        columns = ",".join(_POINT_COLUMNS[self.frame])
        raise input_error(self.source, f"the control points lie a median "
                          f"{float(np.median(distance)):.0f} m {side} the model's surface "
                          f"({max(above, below)} of {len(model_xyz)}): is their height in "
                          "another system (GNSS ellipsoidal heights)? The "
                          f"{columns.rsplit(',', 1)[1]} column must be in the model's vertical "
                          "datum, that of its DEM and georef.json origin")

    def check_inside(self, width: int, height: int) -> None:
        """Refuse a photo pixel outside a ``width`` × ``height`` photo.

        Raises
        ------
        InputError
            ``"<file>: row N: photo pixel (x, y) is outside the W×H photo"``
            for the first such row.
        """
        x, y = self.photo_px[:, 0], self.photo_px[:, 1]
        # Pixel centres run 0 … W-1: the photo covers -0.5 … W-0.5.
        outside = (x < -0.5) | (y < -0.5) | (x > width - 0.5) | (y > height - 0.5)
        if outside.any():
            k = int(np.flatnonzero(outside)[0])
            raise input_error(self.source, f"row {self.rows[k]}: photo pixel "
                              f"({x[k]:g}, {y[k]:g}) is outside the {width}×{height} photo "
                              "(x is the column, y the row, the first pixel's centre (0, 0))")


def read_control_points(path: str | os.PathLike, min_pairs: int = 0) -> ControlPoints:
    """Read a control-point CSV (see the module docstring for the format).

    Parameters
    ----------
    path : path-like
    min_pairs : int
        Refuse a file with fewer pairs (manual registration needs
        :data:`~napari_imgreg.registration.manual.MIN_PAIRS`).

    Returns
    -------
    ControlPoints
        Coordinates as in the file; :meth:`ControlPoints.model_xyz` for the model frame.

    Raises
    ------
    InputError
        A missing or unreadable file; a missing column (or both x,y,z and
        easting,northing,elevation); an empty, non-numeric or non-finite
        cell; a row repeated or a name used twice; fewer than ``min_pairs`` pairs.
    """
    path = Path(path)
    expected = ("expected photo_x,photo_y,x,y,z[,name], photo_x,photo_y,easting,northing,"
                "elevation or photo_x,photo_y,latitude,longitude,elevation")
    header, rows = read_table_rows(path, expected)
    frame = _point_frame(path, header, expected)
    point_columns = _POINT_COLUMNS[frame]
    numeric = PIXEL_COLUMNS + point_columns
    col = {name: header.index(name) for name in numeric}
    name_col = header.index("name") if "name" in header else None

    values: list[list[float]] = []
    names: list[str] = []
    row_numbers: list[int] = []
    first_of_values: dict[tuple[float, ...], int] = {}
    first_of_name: dict[str, int] = {}
    for row_number, cells in rows:
        record = [cell_number(path, row_number, name, cells[col[name]]) for name in numeric]
        if frame == "geodetic":
            _check_degrees(path, row_number, record[2], record[3])
        key = tuple(record)
        if key in first_of_values:
            raise input_error(path, f"row {row_number}: repeats row {first_of_values[key]}")
        first_of_values[key] = row_number
        name = cells[name_col] if name_col is not None else ""
        if name:
            if name in first_of_name:
                raise input_error(path, f"row {row_number}: name {name!r} appears twice "
                                  f"(first at row {first_of_name[name]})")
            first_of_name[name] = row_number
        values.append(record)
        names.append(name)
        row_numbers.append(row_number)
    if len(values) < max(min_pairs, 1):
        found = "no pairs after the header" if not values else f"{len(values)} pairs"
        raise input_error(path, f"{found}: need at least {max(min_pairs, 1)}")
    data = np.array(values, np.float64).reshape(-1, 5)
    return ControlPoints(photo_px=data[:, :2].copy(), xyz=data[:, 2:].copy(), names=names,
                         rows=row_numbers, frame=frame, source=path)


def _point_frame(path: Path, header: list[str], expected: str) -> str:
    """How the file gives the model point: ``"model"`` (x,y,z), ``"crs"``
    (easting,northing,elevation) or ``"geodetic"`` (latitude,longitude,elevation)."""
    missing = [c for c in PIXEL_COLUMNS if c not in header]
    if missing:
        raise input_error(path, f"missing column{'s' if len(missing) > 1 else ''} "
                          f"{', '.join(missing)} (header is: {header_excerpt(header)}; {expected})")
    complete = [frame for frame, columns in _POINT_COLUMNS.items()
                if all(c in header for c in columns)]
    if len(complete) > 1:
        ways = " and ".join(",".join(_POINT_COLUMNS[f]) for f in complete)
        raise input_error(path, f"both {ways}: give the model point one way")
    if complete:
        return complete[0]
    # The way the header half-gives: the one whose own columns (not the shared
    # elevation) it has most of.
    partial = max(_POINT_COLUMNS, key=lambda f: sum(c in header for c in _POINT_COLUMNS[f][:2]))
    if not any(c in header for f in _POINT_COLUMNS for c in _POINT_COLUMNS[f]):
        if all(c in header for c in _RENDER_COLUMNS):
            raise input_error(path, "render_x,render_y (pixels of a render) are not read: give "
                              "each pair's model point as x,y,z (the workbench's Save pairs… "
                              "writes them)")
        partial = "model"
    if partial == "geodetic" and "elevation" not in header and any(
            h in header for h in ("ellipsoidal_height", "height", "h", "altitude")):
        raise input_error(path, "latitude,longitude need an elevation column: the height in "
                          "the model's vertical datum (that of its DEM), not a GNSS "
                          "receiver's ellipsoidal height")
    missing = [c for c in _POINT_COLUMNS[partial] if c not in header]
    raise input_error(path, f"missing column{'s' if len(missing) > 1 else ''} "
                      f"{', '.join(missing)} (header is: {header_excerpt(header)}; {expected})")


def _check_degrees(path: Path, row_number: int, latitude: float, longitude: float) -> None:
    """Refuse a latitude or longitude that cannot be WGS84 degrees (map metres, swapped)."""
    if abs(latitude) > 90:
        raise input_error(path, f"row {row_number}: latitude {latitude:g} is outside [-90, 90] "
                          "(latitude,longitude are WGS84 degrees; map coordinates go in "
                          "easting,northing,elevation)")
    if abs(longitude) > 180:
        raise input_error(path, f"row {row_number}: longitude {longitude:g} is outside "
                          "[-180, 180] (latitude,longitude are WGS84 degrees; map coordinates "
                          "go in easting,northing,elevation)")


def write_control_points(path: str | os.PathLike, photo_px: np.ndarray, xyz: np.ndarray,
                         names: Sequence[str] | None = None) -> None:
    """Write pairs as a control-point CSV, atomically (model frame, ``x,y,z``).

    Parameters
    ----------
    path : path-like
    photo_px : (N, 2) array
        Photo pixels (x, y), pixel-centre convention.
    xyz : (N, 3) array
        Model points, model frame, metres; all finite.
    names : sequence of str, optional
        Written as the ``name`` column (default: none).

    Raises
    ------
    ValueError
        Shapes that do not match, or a non-finite coordinate (a pair without
        a model point is the caller's to leave out).
    """
    px = np.asarray(photo_px, np.float64).reshape(-1, 2)
    pts = np.asarray(xyz, np.float64).reshape(-1, 3)
    if len(px) != len(pts) or (names is not None and len(names) != len(px)):
        raise ValueError(f"{len(px)} photo pixels, {len(pts)} model points"
                         + ("" if names is None else f", {len(names)} names"))
    if not (np.isfinite(px).all() and np.isfinite(pts).all()):
        raise ValueError("control points must be finite")
    columns = [*PIXEL_COLUMNS, *MODEL_COLUMNS] + (["name"] if names is not None else [])
    with atomic_write(path, newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(columns)
        for k in range(len(px)):
            # Micrometres and micropixels: exact enough to round-trip any pose.
            row = [f"{v:.6f}" for v in (*px[k], *pts[k])]
            writer.writerow(row + ([names[k]] if names is not None else []))
