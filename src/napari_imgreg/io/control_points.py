"""Control-point files: pairs of a photo pixel and the model point it shows (CSV).

The file behind manual registration from a file (``napari-imgreg register
--pairs``) and the workbench's *Save pairs…* / *Load pairs…*
(``docs/formats.md``, "Control points"). One row per pair, a header first::

    photo_x,photo_y,x,y,z,name
    512.250,301.750,-3.1042,10.5518,4.2071,GCP1

``photo_x, photo_y``: the photo pixel (x = column, y = row), the first
pixel's centre at (0, 0). ``x, y, z``: the model point, model frame, metres.
Instead of ``x, y, z`` the point may be given in the georeference's CRS as
``easting, northing, elevation`` (a GNSS survey of targets); it is taken into
the model frame with the scene's georeference (:meth:`ControlPoints.model_xyz`).
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
from ._table_csv import cell_number, read_table_rows

if TYPE_CHECKING:  # only the georeference's crs_to_local is used
    from ..geo import Georef

__all__ = [
    "ControlPoints",
    "read_control_points",
    "write_control_points",
    "PIXEL_COLUMNS",
    "MODEL_COLUMNS",
    "CRS_COLUMNS",
]

#: The photo pixel of each pair.
PIXEL_COLUMNS = ("photo_x", "photo_y")
#: The model point in the model frame, metres.
MODEL_COLUMNS = ("x", "y", "z")
#: The model point in the georeference's CRS (``crs = local + origin``), metres.
CRS_COLUMNS = ("easting", "northing", "elevation")
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
        "model"``) or the georeference's CRS (``frame == "crs"``), metres.
        :meth:`model_xyz` gives them in the model frame either way.
    names : list of str
        Each pair's ``name`` ("" when the file has none).
    rows : list of int
        Each pair's line number in the file, for messages.
    frame : {"model", "crs"}
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
            raise input_error(self.source, "points are given as easting,northing,elevation "
                              "but the model has no georeference (georef.json beside it, or "
                              "--georef): give x,y,z in the model frame instead")
        return np.asarray(georef.crs_to_local(self.xyz), np.float64).reshape(-1, 3)

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
        given = (f"easting,northing,elevation in {crs or 'the georeference'}'s coordinates "
                 "(not latitude and longitude)" if self.frame == "crs"
                 else "x,y,z in the model frame (easting,northing,elevation for map "
                      "coordinates)")
        far = f"{distance / 1000.0:.0f} km" if distance >= 10_000 else f"{distance:.0f} m"
        raise input_error(self.source, f"the control points lie a median {far} from the model "
                          f"({diagonal:.0f} m across): are columns swapped, or the coordinates "
                          f"of another system? They must be {given}")

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
    expected = "expected photo_x,photo_y,x,y,z[,name] or photo_x,photo_y,easting,northing,elevation"
    header, rows = read_table_rows(path, expected)
    point_columns = _point_columns(path, header, expected)
    frame = "model" if point_columns == MODEL_COLUMNS else "crs"
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


def _point_columns(path: Path, header: list[str], expected: str) -> tuple[str, ...]:
    """Which columns hold the model point: x,y,z or easting,northing,elevation."""
    missing = [c for c in PIXEL_COLUMNS if c not in header]
    if missing:
        raise input_error(path, f"missing column{'s' if len(missing) > 1 else ''} "
                          f"{', '.join(missing)} (header is: {','.join(header)}; {expected})")
    has_model = [c for c in MODEL_COLUMNS if c in header]
    has_crs = [c for c in CRS_COLUMNS if c in header]
    if len(has_model) == 3 and len(has_crs) == 3:
        raise input_error(path, "both x,y,z and easting,northing,elevation: give the model "
                          "point one way")
    if len(has_model) == 3:
        return MODEL_COLUMNS
    if len(has_crs) == 3:
        return CRS_COLUMNS
    if has_crs:
        missing = [c for c in CRS_COLUMNS if c not in header]
    elif has_model:
        missing = [c for c in MODEL_COLUMNS if c not in header]
    elif all(c in header for c in _RENDER_COLUMNS):
        raise input_error(path, "render_x,render_y (pixels of a render) are not read: give "
                          "each pair's model point as x,y,z (the workbench's Save pairs… "
                          "writes them)")
    else:
        missing = list(MODEL_COLUMNS)
    raise input_error(path, f"missing column{'s' if len(missing) > 1 else ''} "
                      f"{', '.join(missing)} (header is: {','.join(header)}; {expected})")


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
