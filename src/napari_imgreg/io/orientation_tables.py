"""Camera orientation tables for ``orient`` (contract §7): read, pair, write.

A table lists photos with their camera attitude (trend, plunge, roll,
contract §2) and optionally their camera centres. MEASURED tables hold what
the phone or drone recorded (true-north frame); ESTIMATED tables hold the same
photos as the photogrammetry model has them (its arbitrary frame).

Readers, chosen by :func:`read_orientation_table`:

* contract CSV ``photo,trend_deg,plunge_deg,roll_deg[,x,y,z][,time]``;
* Agisoft Metashape / PhotoScan camera XML (File > Export > Cameras);
* COLMAP ``images.txt`` (or a sparse-model folder holding it);
* a folder of photos: DJI XMP gimbal angles (full attitude) or EXIF
  ``GPSImgDirection`` (trend only).

Every problem with a file is one :class:`~napari_imgreg.errors.InputError`
naming the file and the problem (missing column, bad number at row N, no
photos in common between the two tables).
"""

from __future__ import annotations

import csv
import math
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from datetime import date, datetime
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from .._deprecated import forward_moved_names
from ..camera import attitude_from_rotation, rotation_from_attitude
from ..errors import InputError, input_error
from . import exif
from ._table_csv import cell_number, header_excerpt, read_table_rows

__all__ = [
    "OrientationTable",
    "PairedOrientations",
    "read_orientation_table",
    "read_orientation_csv",
    "read_metashape_xml",
    "read_colmap_images",
    "read_photo_attitudes",
    "pair_tables",
    "write_orientation_csv",
    "photo_capture_dates",
    "photo_gps_sites",
    "CSV_COLUMNS",
]

CSV_COLUMNS = ("photo", "trend_deg", "plunge_deg", "roll_deg")
_POSITION_COLUMNS = ("x", "y", "z")
_PHOTO_SUFFIXES = (".jpg", ".jpeg", ".tif", ".tiff", ".dng", ".png", *exif.HEIF_SUFFIXES)
# Chunk translations farther than this from the origin are geocentric (ECEF).
_GEOCENTRIC_M = 1.0e5

#: The photo-metadata readers that moved to napari_imgreg.io.exif in 0.2.
_MOVED = dict.fromkeys(
    ("attitude_from_dji_gimbal", "dji_gimbal_angles", "raw_xmp", "_DJI_TAGS"), "napari_imgreg.io.exif")
__getattr__ = forward_moved_names(__name__, _MOVED)




# ------------------------------------------------------------------ table
@dataclass
class OrientationTable:
    """Camera attitudes (and optionally centres) of a set of photos.

    Attributes
    ----------
    photos : list of str
        Photo names, in the table's order (for a phone log: capture order).
    cam_from_world : (N, 3, 3) float array
        World-to-camera rotations (rows: camera x = ρ, y, z = ξ in the
        table's frame). All-NaN for photos whose attitude is incomplete.
    trend_deg : (N,) float array
        Trend of ξ in degrees; known even where plunge and roll are not
        (EXIF ``GPSImgDirection``).
    positions : (N, 3) float array or None
        Camera centres in the table's frame, metres (NaN where unknown);
        None when the table has none.
    source : Path or None
        The file or folder it was read from (for messages).
    kind : str
        ``"csv"``, ``"metashape"``, ``"colmap"``, ``"photos"`` or ``"memory"``.
    notes : list of str
        What the reader skipped or assumed.
    capture_dates : list of (datetime.date or None), or None
        The day each photo was taken (a CSV's ``time`` column, a photo's
        EXIF); None when the table has no dates at all.
    heading_references : list of str, or None
        What each trend is measured from, where the table knows it:
        ``"true"`` or ``"magnetic"`` north (photo metadata), ``""`` unknown;
        None for tables that do not say (CSV, the model's tables).
    """

    photos: list[str]
    cam_from_world: np.ndarray
    trend_deg: np.ndarray
    positions: np.ndarray | None = None
    source: Path | None = None
    kind: str = "memory"
    notes: list[str] = field(default_factory=list)
    capture_dates: list[date | None] | None = None
    heading_references: list[str] | None = None

    # ------------------------------------------------------------ build
    @classmethod
    def from_attitudes(
        cls,
        photos: Sequence[str],
        trend_deg: Sequence[float],
        plunge_deg: Sequence[float],
        roll_deg: Sequence[float],
        positions: np.ndarray | None = None,
        **kwargs,
    ) -> OrientationTable:
        """Table from trend, plunge and roll in degrees (contract §2).

        NaN plunge or roll marks an incomplete attitude (trend only).
        """
        trend = np.asarray(trend_deg, dtype=np.float64) % 360.0
        plunge = np.asarray(plunge_deg, dtype=np.float64)
        roll = np.asarray(roll_deg, dtype=np.float64)
        R = np.full((len(photos), 3, 3), np.nan)
        for i, (t, p, r) in enumerate(zip(trend, plunge, roll)):
            if np.isfinite([t, p, r]).all():
                R[i] = rotation_from_attitude(t, p, r)
        return cls(list(photos), R, trend, _positions_or_none(positions), **kwargs)

    @classmethod
    def from_rotations(
        cls,
        photos: Sequence[str],
        cam_from_world: np.ndarray,
        positions: np.ndarray | None = None,
        **kwargs,
    ) -> OrientationTable:
        """Table from world-to-camera rotations, shape (N, 3, 3)."""
        R = np.asarray(cam_from_world, dtype=np.float64).reshape(-1, 3, 3)
        xi = R[:, 2]
        trend = np.degrees(np.arctan2(xi[:, 0], xi[:, 1])) % 360.0
        return cls(list(photos), R.copy(), trend, _positions_or_none(positions), **kwargs)

    # ---------------------------------------------------------- derived
    def __len__(self) -> int:
        return len(self.photos)

    @property
    def complete(self) -> np.ndarray:
        """(N,) bool: the photo has a full attitude (trend, plunge and roll)."""
        return np.isfinite(self.cam_from_world).all(axis=(1, 2))

    @property
    def view_directions(self) -> np.ndarray:
        """ξ, the unit view directions (camera z), shape (N, 3)."""
        return self.cam_from_world[:, 2].copy()

    @property
    def long_axes(self) -> np.ndarray:
        """ρ, the unit long axes of the image (camera x), shape (N, 3)."""
        return self.cam_from_world[:, 0].copy()

    @property
    def attitudes(self) -> np.ndarray:
        """(N, 3) trend, plunge, roll in degrees (NaN plunge/roll where unknown)."""
        out = np.full((len(self), 3), np.nan)
        out[:, 0] = self.trend_deg
        for i in np.flatnonzero(self.complete):
            out[i] = attitude_from_rotation(self.cam_from_world[i])
        return out

    @property
    def label(self) -> str:
        return str(self.source) if self.source is not None else "table"


def _positions_or_none(positions: np.ndarray | None) -> np.ndarray | None:
    if positions is None:
        return None
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    return None if not np.isfinite(p).any() else p


# ---------------------------------------------------------------- dispatch
def read_orientation_table(path: str | os.PathLike) -> OrientationTable:
    """Read an orientation table, choosing the reader from the file.

    Parameters
    ----------
    path : path-like
        ``.csv`` (contract §7); ``.xml`` (Metashape cameras); COLMAP
        ``images.txt`` or a folder holding it; a folder of photos (DJI XMP
        gimbal angles or EXIF ``GPSImgDirection``). A ``.txt`` file whose
        header names ``photo`` and ``trend_deg`` is read as CSV.

    Raises
    ------
    InputError
        Missing file, unknown format, or any problem the reader finds.
    """
    path = Path(path)
    if not path.exists():
        raise input_error(path, "no such file")
    if path.is_dir():
        if (path / "images.txt").exists():
            return read_colmap_images(path / "images.txt")
        if (path / "images.bin").exists():
            raise input_error(
                path,
                "binary COLMAP model: convert it with `colmap model_converter "
                "--output_type TXT` and pass images.txt",
            )
        photos = sorted(p for p in path.iterdir() if p.suffix.lower() in _PHOTO_SUFFIXES)
        if not photos:
            raise input_error(path, "folder holds neither COLMAP images.txt nor photos")
        return read_photo_attitudes(photos, source=path)
    suffix = path.suffix.lower()
    if suffix == ".csv":
        return read_orientation_csv(path)
    if suffix == ".xml":
        return read_metashape_xml(path)
    if suffix == ".txt":
        if _looks_like_csv(path):
            return read_orientation_csv(path)
        return read_colmap_images(path)
    if suffix in _PHOTO_SUFFIXES:
        return read_photo_attitudes([path], source=path)
    raise input_error(
        path,
        "unknown orientation table format (expected .csv, Metashape cameras .xml, "
        "COLMAP images.txt, or a folder of photos)",
    )


def _looks_like_csv(path: Path) -> bool:
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as fh:
            for line in fh:
                if line.strip() and not line.lstrip().startswith("#"):
                    header = line.lower()
                    return "photo" in header and "trend_deg" in header
    except OSError:
        return False
    return False


# ---------------------------------------------------------------------- CSV
def read_orientation_csv(path: str | os.PathLike) -> OrientationTable:
    """Read the contract's orientation CSV (§7).

    Header first: ``photo,trend_deg,plunge_deg,roll_deg`` and optionally
    ``x,y,z`` and ``time`` (when the photo was taken: an ISO 8601 date or
    date and time, ``2026-06-01`` or ``2026-06-01T10:21:00+02:00``; EXIF's
    ``2026:06:01 10:21:00`` too; only the day is kept, for a magnetic
    declination); other columns are ignored. Commas, semicolons or tabs separate
    fields; blank lines and lines starting with ``#`` are skipped. An empty
    plunge or roll cell marks a trend-only attitude (the photo is left out of
    the fit, with a note).

    Raises
    ------
    InputError
        Missing column, a bad or non-finite number ("row N" is the line
        number in the file, the header being row 1), plunge outside
        [-90, 90], a ``time`` that is not a date, an empty or repeated photo
        name, or no data rows.
    """
    path = Path(path)
    header, rows = read_table_rows(
        path, "expected a header photo,trend_deg,plunge_deg,roll_deg")
    missing = [c for c in CSV_COLUMNS if c not in header]
    if missing:
        raise input_error(
            path,
            f"missing column{'s' if len(missing) > 1 else ''} {', '.join(missing)} "
            f"(header is: {header_excerpt(header)}; "
            "expected photo,trend_deg,plunge_deg,roll_deg[,x,y,z])",
        )
    present_xyz = [c for c in _POSITION_COLUMNS if c in header]
    if present_xyz and len(present_xyz) != 3:
        raise input_error(path, f"has column(s) {', '.join(present_xyz)} but not all of x, y, z")
    col = {name: header.index(name) for name in CSV_COLUMNS + tuple(present_xyz)}

    has_time = "time" in header
    photos: list[str] = []
    values: list[list[float]] = []
    dates: list[date | None] = []
    first_row: dict[str, int] = {}
    for row_number, cells in rows:
        photo = cells[col["photo"]]
        if not photo:
            raise input_error(path, f"row {row_number}: empty photo name")
        if photo in first_row:
            raise input_error(
                path,
                f"row {row_number}: photo {photo!r} appears twice "
                f"(first at row {first_row[photo]})",
            )
        first_row[photo] = row_number
        record = []
        for name in ("trend_deg", "plunge_deg", "roll_deg") + tuple(present_xyz):
            optional = name in ("plunge_deg", "roll_deg") or name in _POSITION_COLUMNS
            record.append(cell_number(path, row_number, name, cells[col[name]], optional))
        if abs(record[1]) > 90:
            raise input_error(
                path, f"row {row_number}: plunge_deg must be in [-90, 90], got {record[1]:g}"
            )
        photos.append(photo)
        values.append(record)
        if has_time:
            dates.append(_cell_date(path, row_number, cells[header.index("time")]))
    if not photos:
        raise input_error(path, "no data rows after the header")

    data = np.array(values, dtype=np.float64)
    table = OrientationTable.from_attitudes(
        photos, data[:, 0], data[:, 1], data[:, 2],
        positions=data[:, 3:6] if present_xyz else None,
        source=path, kind="csv", capture_dates=dates if has_time else None,
    )
    incomplete = int((~table.complete).sum())
    if incomplete:
        table.notes.append(f"{incomplete} photo(s) have no plunge or roll (trend only)")
    return table


def _cell_date(path: Path, row: int, cell: str) -> date | None:
    """A ``time`` cell's day: ISO 8601 (``Z`` accepted) or EXIF's colons; empty: None."""
    text = cell.strip()
    if not text:
        return None
    exif_style = len(text) >= 10 and text[4] == ":" and text[7] == ":"
    candidate = (text[:10].replace(":", "-") + text[10:]) if exif_style else text
    try:
        return datetime.fromisoformat(candidate.replace("Z", "+00:00")).date()
    except ValueError:
        raise input_error(path, f"row {row}: time is not a date ({cell!r}; expected e.g. "
                                "2026-06-01 or 2026-06-01T10:21:00+02:00)") from None


def _photo_files(photos: Sequence[str], folder: str | os.PathLike) -> list[Path | None] | None:
    """The file of each photo found in ``folder`` by its name (None: not
    found); None when the folder cannot be read or holds none of them.

    A name matches the file of that name, or of that stem with a photo
    suffix (``IMG_0001`` → ``IMG_0001.JPG``), case aside.
    """
    folder = Path(folder)
    try:
        files = {p.name.lower(): p for p in folder.iterdir()
                 if p.is_file() and p.suffix.lower() in _PHOTO_SUFFIXES}
    except OSError:
        return None
    by_stem = {Path(name).stem: p for name, p in files.items()}
    found = []
    for photo in photos:
        name = Path(photo).name.lower()
        found.append(files.get(name) or by_stem.get(Path(name).stem if Path(name).suffix.lower()
                                                    in _PHOTO_SUFFIXES else name))
    return found if any(path is not None for path in found) else None


def photo_capture_dates(photos: Sequence[str], folder: str | os.PathLike
                        ) -> list[date | None] | None:
    """The EXIF day of each photo found in ``folder`` by its name
    (:func:`_photo_files`). Unreadable files and photos without a date give None.

    Returns
    -------
    list of (datetime.date or None), or None when no photo was found.
    """
    files = _photo_files(photos, folder)
    if files is None:
        return None
    dates: list[date | None] = []
    for path in files:
        try:  # a damaged photo dates nothing; the others still do
            dates.append(exif.read_photo_capture_date(path) if path is not None else None)
        except InputError:
            dates.append(None)
    return dates


def photo_gps_sites(photos: Sequence[str], folder: str | os.PathLike
                    ) -> list[tuple[float, float] | None] | None:
    """The EXIF GPS latitude and longitude (degrees, WGS84) of each photo
    found in ``folder`` by its name (:func:`_photo_files`); None for a photo
    without them or unreadable.

    Returns
    -------
    list of ((lat_deg, lon_deg) or None), or None when no photo was found.
    """
    files = _photo_files(photos, folder)
    if files is None:
        return None
    sites: list[tuple[float, float] | None] = []
    for path in files:
        site = None
        if path is not None:
            try:
                _, gps = exif.read_photo_xmp_and_gps(path)
            except InputError:
                gps = {}
            lat = exif.gps_degrees(gps.get("GPSLatitude"), gps.get("GPSLatitudeRef", "N"))
            lon = exif.gps_degrees(gps.get("GPSLongitude"), gps.get("GPSLongitudeRef", "E"))
            if lat is not None and lon is not None and abs(lat) <= 90 and abs(lon) <= 180 \
                    and (lat, lon) != (0.0, 0.0):  # 0, 0: a phone without a fix
                site = (lat, lon)
        sites.append(site)
    return sites


def write_orientation_csv(path: str | os.PathLike, table: OrientationTable) -> None:
    """Write a table as the contract's CSV (atomically).

    Positions are written as ``x,y,z`` when the table has them, capture
    dates as a ``time`` column (ISO 8601 days) when it has those; unknown
    values are empty cells.
    """
    from .._atomic import atomic_write

    attitudes = table.attitudes
    dates = table.capture_dates
    columns = (list(CSV_COLUMNS) + (list(_POSITION_COLUMNS) if table.positions is not None else [])
               + (["time"] if dates is not None else []))

    def fmt(v: float) -> str:
        return "" if not np.isfinite(v) else f"{v:.10g}"

    with atomic_write(path, newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(columns)
        for i, photo in enumerate(table.photos):
            row = [photo] + [fmt(v) for v in attitudes[i]]
            if table.positions is not None:
                row += [fmt(v) for v in table.positions[i]]
            if dates is not None:
                row.append(dates[i].isoformat() if dates[i] is not None else "")
            writer.writerow(row)


# ------------------------------------------------------------- Metashape
def read_metashape_xml(
    path: str | os.PathLike, chunk_transform: bool | None = None
) -> OrientationTable:
    """Read camera orientations from Agisoft Metashape / PhotoScan camera XML.

    Each aligned ``<camera label=...>`` has a ``<transform>``: 16 numbers, a
    row-major 4 × 4 camera-to-chunk matrix. Metashape's camera frame is
    OpenCV's (x right, y down, z forward), as in the contract. The chunk's
    own ``<transform>`` (``rotation``, ``translation``, ``scale``) — in
    Metashape 1.6 and later, the ``<transform>`` of the camera's
    ``<component>`` — maps chunk coordinates to the coordinates models are
    exported in; it is applied so the orientations match an exported mesh.

    Parameters
    ----------
    path : path-like
    chunk_transform : bool, optional
        Apply the chunk (component) transform. Default (None): apply it
        unless it maps to geocentric (ECEF) coordinates — a chunk referenced
        from the photos' GPS — where the orientations stay in the internal
        chunk frame and a note says so.

    Raises
    ------
    InputError
        Not XML, no chunk, no aligned camera, or a transform that is not a
        rotation.
    """
    path = Path(path)
    if not path.exists():
        raise input_error(path, "no such file")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise input_error(path, f"not valid XML ({exc})") from None
    except OSError as exc:
        raise input_error(path, f"cannot read ({exc})") from None
    chunks = [root] if root.tag == "chunk" else list(root.iter("chunk"))
    if not chunks:
        raise input_error(path, "no <chunk> element: not a Metashape camera XML")

    notes: list[str] = []
    for chunk_index, chunk in enumerate(chunks):
        cameras = chunk.find("cameras")
        elements = [] if cameras is None else list(cameras.iter("camera"))
        aligned = [c for c in elements if c.find("transform") is not None]
        if aligned:
            break
    else:
        raise input_error(path, "no aligned camera (no <camera> with a <transform>)")
    if len(chunks) > 1:
        notes.append(f"read chunk {chunk.get('label', chunk_index)!r} of {len(chunks)}")
    unaligned = len(elements) - len(aligned)
    if unaligned:
        notes.append(f"{unaligned} camera(s) not aligned (no transform) skipped")

    # Metashape 1.6+ gives each component its own <transform> (cameras name
    # theirs by component_id); PhotoScan has one chunk-level <transform>.
    transforms: dict[str | None, tuple[np.ndarray, np.ndarray, float]] = {}
    if chunk.find("transform") is not None:
        transforms[None] = _metashape_chunk_transform(path, chunk.find("transform"))
    for component in chunk.findall("components/component"):
        if component.find("transform") is not None:
            transforms[component.get("id", "0")] = _metashape_chunk_transform(
                path, component.find("transform")
            )
    identity = (np.eye(3), np.zeros(3), 1.0)
    geocentric_seen = False

    photos: list[str] = []
    rotations, centres = [], []
    for camera in aligned:
        label = camera.get("label") or f"camera {camera.get('id', '?')}"
        numbers = _floats(camera.find("transform").text)
        if numbers is None or len(numbers) != 16:
            raise input_error(path, f"camera {label!r}: <transform> must hold 16 numbers")
        M = np.array(numbers).reshape(4, 4)
        chunk_rotation, chunk_translation, chunk_scale = identity
        transform = transforms.get(camera.get("component_id"), transforms.get(None))
        if transform is not None and chunk_transform is not False:
            geocentric = np.linalg.norm(transform[1]) > _GEOCENTRIC_M
            if geocentric and chunk_transform is None:
                geocentric_seen = True
            else:
                chunk_rotation, chunk_translation, chunk_scale = transform
        world_from_cam = chunk_rotation @ _as_rotation(path, f"camera {label!r}", M[:3, :3])
        photos.append(label)
        rotations.append(world_from_cam.T)
        centres.append(chunk_scale * chunk_rotation @ M[:3, 3] + chunk_translation)
    if geocentric_seen:
        notes.append(
            "chunk transform is geocentric (chunk referenced to a CRS): orientations "
            "read in the internal chunk frame"
        )
    return OrientationTable.from_rotations(
        photos, np.array(rotations), np.array(centres), source=path, kind="metashape", notes=notes
    )


def _metashape_chunk_transform(
    path: Path, element: ET.Element
) -> tuple[np.ndarray, np.ndarray, float]:
    """(rotation, translation, scale) of a chunk ``<transform>``."""
    rotation_el = element.find("rotation")
    if rotation_el is not None:
        r = _floats(rotation_el.text)
        t_el, s_el = element.find("translation"), element.find("scale")
        t = _floats(t_el.text) if t_el is not None else [0.0, 0.0, 0.0]
        s = _floats(s_el.text) if s_el is not None else [1.0]
        if r is None or len(r) != 9 or t is None or len(t) != 3 or not s:
            raise input_error(
                path, "chunk <transform> has a malformed rotation, translation or scale"
            )
        rotation = _as_rotation(path, "chunk transform", np.array(r).reshape(3, 3))
        return rotation, np.array(t), float(s[0])
    numbers = _floats(element.text)
    if numbers is None or len(numbers) != 16:
        raise input_error(
            path, "chunk <transform> must hold rotation/translation/scale or 16 numbers"
        )
    M = np.array(numbers).reshape(4, 4)
    scale = float(np.cbrt(np.linalg.det(M[:3, :3])))
    if scale <= 0:
        raise input_error(path, "chunk <transform> is not a similarity (non-positive scale)")
    return _as_rotation(path, "chunk transform", M[:3, :3] / scale), M[:3, 3], scale


def _as_rotation(path: Path, what: str, M: np.ndarray) -> np.ndarray:
    """The nearest rotation to ``M``; an error unless ``M`` is one already."""
    is_rotation = (
        np.isfinite(M).all() and np.allclose(M @ M.T, np.eye(3), atol=1e-4) and np.linalg.det(M) > 0
    )
    if not is_rotation:
        raise input_error(path, f"{what}: not a rotation (scaled, sheared or mirrored)")
    U, _, Vt = np.linalg.svd(M)
    return U @ Vt


def _floats(text: str | None) -> list[float] | None:
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split()]
    except ValueError:
        return None
    return values if all(math.isfinite(v) for v in values) else None


# ------------------------------------------------------------------ COLMAP
def read_colmap_images(path: str | os.PathLike) -> OrientationTable:
    """Read COLMAP's ``images.txt`` (text model).

    Each image takes two lines: ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID
    NAME`` and its 2D points (possibly empty; a file without the points
    lines is read too). ``(QW, QX, QY, QZ)`` and
    ``(TX, TY, TZ)`` are ``cam_from_world`` in COLMAP's camera frame, which
    is OpenCV's (x right, y down, z forward); the centre is ``-Rᵀ t``.

    Raises
    ------
    InputError
        A malformed image line (named by its line number), a zero
        quaternion, or no images.
    """
    path = Path(path)
    if not path.exists():
        raise input_error(path, "no such file")
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise input_error(path, f"cannot read ({exc})") from None
    photos: list[str] = []
    rotations, centres = [], []
    number = 0
    while number < len(lines):
        line = lines[number].strip()
        number += 1
        if not line or line.startswith("#"):
            continue
        fields = line.split()
        if len(fields) < 10:
            raise input_error(
                path,
                f"line {number}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, "
                f"got {len(fields)} field(s)",
            )
        try:
            q_wxyz = np.array([float(v) for v in fields[1:5]])
            t = np.array([float(v) for v in fields[5:8]])
        except ValueError:
            raise input_error(path, f"line {number}: QW..TZ must be numbers") from None
        valid = np.isfinite(q_wxyz).all() and np.isfinite(t).all()
        if not valid or np.linalg.norm(q_wxyz) < 1e-9:
            raise input_error(path, f"line {number}: invalid quaternion or translation")
        R = Rotation.from_quat(q_wxyz, scalar_first=True).as_matrix()
        photos.append(" ".join(fields[9:]))
        rotations.append(R)
        centres.append(-R.T @ t)
        if number < len(lines) and _is_points2d_line(lines[number]):
            number += 1  # the POINTS2D line that follows an image line
    if not photos:
        raise input_error(path, "no images in COLMAP images.txt")
    return OrientationTable.from_rotations(
        photos, np.array(rotations), np.array(centres), source=path, kind="colmap"
    )


def _is_points2d_line(line: str) -> bool:
    """True for the POINTS2D line of an image (empty, or ``X Y POINT3D_ID``
    triples of numbers). Files written by other tools may leave it out, and
    then the next line is the next image's (its NAME is not a number, and its
    10 fields are not triples): skipping it blindly lost every second image."""
    fields = line.split()
    if len(fields) % 3:
        return False
    try:
        [float(v) for v in fields]
    except ValueError:
        return False
    return True


# ------------------------------------------------------------ photo metadata
def read_photo_attitudes(
    paths: Iterable[str | os.PathLike], source: str | os.PathLike | None = None
) -> OrientationTable:
    """Camera attitudes from photo metadata.

    Tried per photo: DJI XMP ``drone-dji:GimbalYawDegree``,
    ``GimbalPitchDegree``, ``GimbalRollDegree`` (full attitude, see
    :func:`napari_imgreg.io.exif.attitude_from_dji_gimbal`); else EXIF
    ``GPSImgDirection`` (trend only: the photo is listed but cannot enter
    the fit). Photos with neither are skipped with a note. Positions are not read (GPS needs a
    georeference). Each photo's heading reference (DJI: true north; EXIF:
    ``GPSImgDirectionRef``) and EXIF capture day are kept.

    Raises
    ------
    InputError
        No photo carries attitude metadata, or a photo cannot be read.
    """
    paths = [Path(p) for p in paths]
    src = Path(source) if source is not None else (paths[0] if len(paths) == 1 else None)
    photos: list[str] = []
    attitudes: list[tuple[float, float, float]] = []
    references: list[str] = []
    dates: list[date | None] = []
    skipped: list[str] = []
    for path in paths:
        if not path.exists():
            raise input_error(path, "no such file")
        xmp_text, gps = exif.read_photo_xmp_and_gps(path)
        gimbal = exif.dji_gimbal_angles(xmp_text or "", path)
        if gimbal is not None:
            photos.append(path.name)
            attitudes.append(exif.attitude_from_dji_gimbal(*gimbal))
            references.append("true")  # DJI's yaw is from true north
            dates.append(exif.read_photo_capture_date(path))
            continue
        direction = gps.get("GPSImgDirection") if gps else None
        if direction is not None:
            try:
                trend = float(direction)
            except (TypeError, ValueError, ZeroDivisionError):
                trend = math.nan
            if math.isfinite(trend):
                photos.append(path.name)
                attitudes.append((trend % 360.0, math.nan, math.nan))
                references.append(exif.gps_heading_reference(gps))
                dates.append(exif.read_photo_capture_date(path))
                continue
        skipped.append(path.name)
    if not photos:
        raise input_error(
            src,
            "no photo carries camera attitude metadata (DJI XMP gimbal angles or "
            "EXIF GPSImgDirection)",
        )
    a = np.array(attitudes)
    table = OrientationTable.from_attitudes(
        photos, a[:, 0], a[:, 1], a[:, 2], source=src, kind="photos",
        capture_dates=dates if any(d is not None for d in dates) else None,
        heading_references=references,
    )
    trend_only = int((~table.complete).sum())
    if trend_only:
        table.notes.append(
            f"{trend_only} photo(s) give only a compass direction (EXIF GPSImgDirection), "
            "no plunge or roll"
        )
    magnetic = references.count("magnetic")
    if magnetic:
        # Whether a declination is added is orient's to say (--declination).
        table.notes.append(
            f"{magnetic} photo(s) give magnetic, not true, north (EXIF GPSImgDirectionRef M)"
        )
    if skipped:
        table.notes.append(f"{len(skipped)} photo(s) without attitude metadata skipped")
    return table


# ---------------------------------------------------------------- pairing
@dataclass
class PairedOrientations:
    """The photos found in both tables, with complete attitudes in both.

    Attributes
    ----------
    photos : list of str
        Photo names as the MEASURED table has them, in its order.
    estimated : (N, 3, 3) array
        ``cam_from_model`` of each photo (ESTIMATED, the model's frame).
    measured : (N, 3, 3) array
        ``cam_from_world`` of each photo (MEASURED, true north).
    estimated_positions, measured_positions : (N, 3) array or None
        Camera centres from each table, when it has them.
    capture_order : (N,) int array
        Row of each photo in the MEASURED table (the capture order of a
        phone log).
    notes : list of str
        Unmatched and incomplete photos, and the readers' notes.
    """

    photos: list[str]
    estimated: np.ndarray
    measured: np.ndarray
    estimated_positions: np.ndarray | None
    measured_positions: np.ndarray | None
    capture_order: np.ndarray
    notes: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.photos)


def _photo_key(name: str) -> str:
    """File name without folder or extension, case-folded."""
    return Path(name.replace("\\", "/")).stem.casefold()


def pair_tables(
    estimated: OrientationTable, measured: OrientationTable, min_photos: int = 2
) -> PairedOrientations:
    """Pair two tables by photo name.

    Names match exactly, or else by file name without folder and extension,
    ignoring case (``IMG_0001`` matches ``photos/img_0001.JPG``).

    Raises
    ------
    InputError
        No photo in common, or fewer than ``min_photos`` with a complete
        attitude in both tables.
    """
    for table in (estimated, measured):
        if len(table) == 0:
            raise input_error(table.source, "the table lists no photos")
    exact = {name: i for i, name in enumerate(estimated.photos)}
    keys: dict[str, list[int]] = {}
    for i, name in enumerate(estimated.photos):
        keys.setdefault(_photo_key(name), []).append(i)

    notes = [f"{measured.label}: {n}" for n in measured.notes]
    notes += [f"{estimated.label}: {n}" for n in estimated.notes]
    pairs: list[tuple[int, int]] = []
    used: set[int] = set()
    for j, name in enumerate(measured.photos):
        i = exact.get(name)
        if i is None:
            candidates = keys.get(_photo_key(name), [])
            i = candidates[0] if len(candidates) == 1 else None
        if i is not None and i not in used:
            used.add(i)
            pairs.append((i, j))
    if not pairs:
        raise input_error(
            measured.source,
            f"no photos in common with {estimated.label} (e.g. {measured.photos[0]!r} "
            f"vs {estimated.photos[0]!r})",
        )
    unmatched_measured = len(measured) - len(pairs)
    unmatched_estimated = len(estimated) - len(pairs)
    if unmatched_measured:
        notes.append(f"{unmatched_measured} measured photo(s) not in the estimated table")
    if unmatched_estimated:
        notes.append(f"{unmatched_estimated} estimated photo(s) not in the measured table")

    est_complete, meas_complete = estimated.complete, measured.complete
    complete_pairs = [(i, j) for i, j in pairs if est_complete[i] and meas_complete[j]]
    incomplete = [
        measured.photos[j] for i, j in pairs if not (est_complete[i] and meas_complete[j])
    ]
    if incomplete:
        shown = ", ".join(incomplete[:5]) + (", ..." if len(incomplete) > 5 else "")
        notes.append(f"{len(incomplete)} photo(s) left out, attitude incomplete: {shown}")
    if len(complete_pairs) < min_photos:
        raise input_error(
            measured.source,
            f"only {len(complete_pairs)} photo(s) with a full attitude (trend, plunge and roll) "
            f"in both this table and {estimated.label}; at least {min_photos} needed",
        )
    est_idx = np.array([i for i, _ in complete_pairs])
    meas_idx = np.array([j for _, j in complete_pairs])

    def positions(table: OrientationTable, idx: np.ndarray) -> np.ndarray | None:
        if table.positions is None:
            return None
        p = table.positions[idx]
        return p if np.isfinite(p).all() else None

    return PairedOrientations(
        photos=[measured.photos[j] for j in meas_idx],
        estimated=estimated.cam_from_world[est_idx],
        measured=measured.cam_from_world[meas_idx],
        estimated_positions=positions(estimated, est_idx),
        measured_positions=positions(measured, meas_idx),
        capture_order=meas_idx,
        notes=notes,
    )
