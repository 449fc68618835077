"""The magnetic declination of a survey, for phones that log magnetic headings.

:func:`survey_declination` gives the World Magnetic Model's declination
(:func:`napari_imgreg.geo.magnetic_declination`) at the model's
georeferenced origin — or, for a model without a georeference (what
``orient`` is for), at the median GPS position of the MEASURED photos —
on the survey's date: the median day of the MEASURED
table's capture dates (a CSV's ``time`` column, the EXIF of a folder of
photos), else of the EXIF ``DateTimeOriginal`` of its photos found beside
it. Over a survey's few hundred metres and few days the declination varies
by hundredths of a degree, far below a phone compass's error, so one value
serves every photo.
"""

from __future__ import annotations

import os
import statistics
from dataclasses import dataclass
from datetime import date
from pathlib import Path
from typing import Any

from ..errors import input_error
from ..geo import (
    GeoError,
    Georef,
    MagneticDeclination,
    magnetic_declination,
    site_latitude_longitude,
)
from ..io.orientation_tables import OrientationTable, photo_capture_dates, photo_gps_sites

__all__ = ["AUTO", "SurveyDeclination", "survey_date", "survey_site", "survey_declination",
           "default_georef_path", "georef_found_above", "gui_wording", "GIVE_GEOREF",
           "GIVE_DECLINATION"]

#: What the command line and the widget take for "compute it".
AUTO = "auto"

#: How a message asks for the inputs of a declination, in the command line's
#: words; :func:`gui_wording` gives the Orient model dock's.
GIVE_GEOREF = "give --georef FILE, or the declination as a number (--declination DEG)"
GIVE_DECLINATION = "(--declination DEG)"
_GUI_WORDS = (
    (GIVE_GEOREF, "choose the model's georef.json in the Georef field, or untick Auto (WMM) "
                  "and type the declination in the Declination box"),
    (GIVE_DECLINATION, "(untick Auto (WMM) and type it in the Declination box)"),
)


def gui_wording(message: str) -> str:
    """A declination message in the Orient model dock's words: its Georef
    field and declination box instead of ``--georef`` and ``--declination``
    (the command line keeps its own)."""
    for cli, gui in _GUI_WORDS:
        message = message.replace(cli, gui)
    return message


@dataclass(frozen=True)
class SurveyDeclination:
    """A survey's declination and where each of its inputs came from.

    Attributes
    ----------
    declination : MagneticDeclination
        The value (degrees east), the WMM edition and the date.
    date_source : str
        How the date was found ("median of 51 capture dates in the MEASURED
        table's time column", ...).
    georef_source : str
        The ``georef.json`` that placed the site (or ``"given"``); "" when
        the photos' GPS did.
    place_source : str
        What placed the site, in words ("the origin of georef.json", "the
        median GPS position of 12 photos in ...").
    """

    declination: MagneticDeclination
    date_source: str
    georef_source: str
    place_source: str = ""

    @property
    def declination_deg(self) -> float:
        """Degrees, east positive."""
        return self.declination.declination_deg

    def to_dict(self) -> dict[str, Any]:
        """The ``inputs.declination`` block of ORIENTATION.json."""
        return {**self.declination.to_dict(), "date_from": self.date_source,
                "place": ("the georeferenced model origin" if self.georef_source
                          else self.place_source),
                "georef": self.georef_source or None}

    def note(self) -> str:
        """One line for the result's notes."""
        d = self.declination
        extra = "".join((
            "; near a magnetic pole, where a compass is poor" if d.caution else "",
            "; extrapolated past the model's years" if d.extrapolated else ""))
        return (f"declination {d.label()} added to the measured trends: World Magnetic Model "
                f"at {abs(d.latitude_deg):.4f}° {'N' if d.latitude_deg >= 0 else 'S'}, "
                f"{abs(d.longitude_deg):.4f}° {'E' if d.longitude_deg >= 0 else 'W'} ("
                f"{self.place_source or 'the origin of ' + self.georef_source}) on the "
                f"{self.date_source}{extra}")


def survey_date(measured: OrientationTable) -> tuple[date, str]:
    """The median capture day of a MEASURED table, and how it was found.

    The table's own dates (a CSV ``time`` column, a folder of photos' EXIF)
    first; else the EXIF ``DateTimeOriginal`` of the table's photos found
    beside it (a CSV's folder), by name.

    Raises
    ------
    InputError
        No date in the table nor in photos beside it: the message names the
        table and asks for the declination as a number.
    """
    dates, where = measured.capture_dates, "the MEASURED table's time column"
    if measured.kind == "photos":
        where = "the photos' EXIF"
    if not _any(dates) and measured.source is not None:
        folder = _photo_folder(measured)
        dates = photo_capture_dates(measured.photos, folder)
        where = f"EXIF DateTimeOriginal of the photos in {folder}"
    known = [d for d in (dates or []) if d is not None]
    if not known:
        raise input_error(
            measured.source, "no capture dates for an automatic declination (no time column, "
            f"no photos with EXIF DateTimeOriginal beside it): give the declination as a "
            f"number {GIVE_DECLINATION}")
    # The median day: a survey over a few days is dated by its middle.
    middle = date.fromordinal(int(statistics.median_low(d.toordinal() for d in known)))
    count = f"{len(known)} capture date{'s' if len(known) > 1 else ''}"
    span = (max(known) - min(known)).days
    spread = f", over {span + 1} days" if span else ""
    return middle, f"median of {count} in {where}{spread}"


def _any(dates) -> bool:
    return bool(dates) and any(d is not None for d in dates)


def _photo_folder(measured: OrientationTable) -> Path:
    """Where the MEASURED photos are: the folder read, or the table's own folder."""
    return measured.source if measured.source.is_dir() else measured.source.parent


def survey_site(measured: OrientationTable) -> tuple[float, float, str]:
    """The median EXIF GPS position of the MEASURED photos (a folder of
    photos, or the photos found beside a table): (lat_deg, lon_deg, where).

    Raises
    ------
    InputError
        No photo with a GPS position: the message asks for the model's
        georef.json or the declination as a number.
    """
    sites, where = None, ""
    if measured.source is not None:
        folder = _photo_folder(measured)
        sites = photo_gps_sites(measured.photos, folder)
        where = str(folder)
    known = [site for site in (sites or []) if site is not None]
    if not known:
        raise input_error(
            measured.source, "an automatic declination needs the site: the model's "
            "georef.json (its origin), or MEASURED photos with EXIF GPS beside the table; "
            f"{GIVE_GEOREF}")
    lat = statistics.median(site[0] for site in known)
    lon = statistics.median(site[1] for site in known)  # a survey spans metres, not 180°
    count = f"{len(known)} photo{'s' if len(known) > 1 else ''}"
    return lat, lon, f"the median GPS position of {count} in {where}"


def survey_declination(
    measured: OrientationTable, georef: Georef | str | os.PathLike | None = None
) -> SurveyDeclination:
    """The WMM declination at the site on the survey's date.

    Parameters
    ----------
    measured : OrientationTable
        The phone's table; its capture dates date the survey
        (:func:`survey_date`), and without ``georef`` its photos' GPS
        places it (:func:`survey_site`).
    georef : Georef or path-like, optional
        The model's ``georef.json`` (or the object): its origin is the site.

    Returns
    -------
    SurveyDeclination

    Raises
    ------
    InputError
        No capture date; a bad georef.json; a date no WMM edition covers or
        a site in a magnetic pole's blackout zone (the message names the
        georef.json or the table and asks for a number).
    """
    if georef is None:
        lat, lon, place = survey_site(measured)
        height, georef_source, blame = 0.0, "", measured.source  # immaterial to a declination
    else:
        if isinstance(georef, Georef):
            georef_source, blame = "the georeference given", None
        else:
            georef_source = blame = str(georef)
            georef = Georef.load(georef)
        lat, lon, height = site_latitude_longitude(georef)
        place = f"the origin of {georef_source}"
    when, date_source = survey_date(measured)
    try:
        declination = magnetic_declination(lat, lon, height, when)
    except GeoError as exc:
        raise input_error(blame, f"{exc} {GIVE_DECLINATION}") from None
    return SurveyDeclination(declination, date_source, georef_source, place)


def default_georef_path(*near: str | os.PathLike | None) -> Path | None:
    """The first ``georef.json`` beside (or inside, for a folder) the given
    files; else the first one folder up from them.

    One folder up: a survey's tables are often kept in a folder of their own
    beside the model (the sample's ``orient/``, with the scene's
    ``georef.json`` above it). The georeference only places the site of an
    automatic declination, which changes by about 0.1° in 10 km, so the
    project's own is as good; the note of the result names the file used
    (:meth:`SurveyDeclination.note`), and :func:`georef_found_above` says
    when it was found up there.

    Parameters
    ----------
    *near : path-like or None
        Files or folders in order of preference (the mesh to rotate, the
        ESTIMATED table); None entries are skipped.

    Returns
    -------
    Path or None
    """
    folders = []
    for item in near:
        if item is None or str(item) == "":
            continue
        path = Path(item)
        folders.append(path if path.is_dir() else path.parent)
    for folder in [*folders, *(f.parent for f in folders)]:
        candidate = folder / "georef.json"
        if candidate.is_file():
            return candidate
    return None


def georef_found_above(georef: str | os.PathLike | None,
                       *near: str | os.PathLike | None) -> bool:
    """Whether :func:`default_georef_path` found ``georef`` one folder up
    from the given files (not beside any of them)."""
    if not georef:
        return False
    folders = []
    for item in near:
        if item is None or str(item) == "":
            continue
        path = Path(item)
        folders.append((path if path.is_dir() else path.parent).resolve())
    return Path(georef).resolve().parent not in folders
