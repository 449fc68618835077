"""The sun: where it stood when a photo was taken, as a direction in the model frame.

Gives the sun's position at an instant (NREL SPA through pvlib) and turns it
into a direction in the local model frame, whose +Y is the *grid* north of a
projected CRS, not true north. :func:`sun_for_photo` finds the sun of a photo
from its EXIF capture time; :func:`sun_from_record` the sun of a sensor record
or ``survey.json`` (a ``sun`` block or an ISO ``time``). Relighting a render
for that sun lives in :mod:`napari_imgreg.registration.stages.relight`, EXIF
reading in :mod:`napari_imgreg.io.exif`.

Frames: the local frame is metres ENU (+X east, +Y grid north, +Z up);
azimuths are degrees clockwise from north, elevations degrees above the
horizon.

This module is backend only: no Qt or napari imports.

References
----------
.. [1] I. Reda and A. Andreas, "Solar position algorithm for solar radiation
   applications", Solar Energy 76(5), 577-589, 2004.
   :doi:`10.1016/j.solener.2003.12.003` (NREL/TP-560-34302).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from datetime import datetime, timedelta, tzinfo
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np
import numpy.typing as npt

from .errors import InputError
from .geo import Georef, _transformer
from .io.exif import gps_degrees, read_capture_time

if TYPE_CHECKING:
    from .io.records import SensorRecord

__all__ = [
    "SunPosition",
    "SunTrack",
    "sun_position",
    "sun_positions",
    "sun_vector_enu",
    "meridian_convergence_deg",
    "sun_direction_local",
    "sun_for_photo",
    "sun_from_record",
]


# ---------------------------------------------------------------------------
# sun position
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class SunPosition:
    """The sun seen from one place at one time.

    Attributes
    ----------
    when : datetime
        The (time-zone aware) instant.
    latitude_deg, longitude_deg : float
        WGS84 observer position, degrees (east positive).
    altitude_m : float
        Observer height, metres.
    azimuth_deg : float
        Degrees clockwise from TRUE north, in [0, 360).
    elevation_deg : float
        Apparent topocentric elevation (with atmospheric refraction), degrees.
    zenith_deg : float
        Apparent topocentric zenith angle, ``90 - elevation_deg``.
    geometric_elevation_deg : float
        Topocentric elevation without refraction, degrees.
    """

    when: datetime
    latitude_deg: float
    longitude_deg: float
    altitude_m: float
    azimuth_deg: float
    elevation_deg: float
    zenith_deg: float
    geometric_elevation_deg: float

    @property
    def is_up(self) -> bool:
        """The sun's apparent centre is above the (flat) horizon."""
        return self.elevation_deg > 0.0

    def direction_true(self) -> np.ndarray:
        """(3,) unit vector toward the sun, ENU with +Y = true north."""
        return sun_vector_enu(self.azimuth_deg, self.elevation_deg)


@dataclass(frozen=True)
class SunTrack:
    """The sun at many instants (vectorised :class:`SunPosition`).

    Attributes
    ----------
    times : pandas.DatetimeIndex, (N,)
        The instants, in UTC.
    latitude_deg, longitude_deg, altitude_m : float
        Observer.
    azimuth_deg, elevation_deg, zenith_deg, geometric_elevation_deg : (N,) float64 arrays
        As in :class:`SunPosition`.
    """

    times: Any
    latitude_deg: float
    longitude_deg: float
    altitude_m: float
    azimuth_deg: np.ndarray
    elevation_deg: np.ndarray
    zenith_deg: np.ndarray
    geometric_elevation_deg: np.ndarray

    def __len__(self) -> int:
        return len(self.azimuth_deg)

    def __getitem__(self, i: int) -> SunPosition:
        return SunPosition(
            when=self.times[i].to_pydatetime(),
            latitude_deg=self.latitude_deg,
            longitude_deg=self.longitude_deg,
            altitude_m=self.altitude_m,
            azimuth_deg=float(self.azimuth_deg[i]),
            elevation_deg=float(self.elevation_deg[i]),
            zenith_deg=float(self.zenith_deg[i]),
            geometric_elevation_deg=float(self.geometric_elevation_deg[i]),
        )

    def direction_true(self) -> np.ndarray:
        """(N, 3) unit vectors toward the sun, ENU with +Y = true north."""
        return sun_vector_enu(self.azimuth_deg, self.elevation_deg)


def sun_vector_enu(azimuth_deg: npt.ArrayLike, elevation_deg: npt.ArrayLike) -> np.ndarray:
    """Unit vector(s) toward the sun from azimuth and elevation.

    Parameters
    ----------
    azimuth_deg : float or array
        Degrees clockwise from the frame's north (+Y).
    elevation_deg : float or array
        Degrees above the horizontal.

    Returns
    -------
    ndarray, shape (..., 3)
        ``[sin A cos E, cos A cos E, sin E]`` (east, north, up).
    """
    a = np.radians(np.asarray(azimuth_deg, np.float64))
    e = np.radians(np.asarray(elevation_deg, np.float64))
    a, e = np.broadcast_arrays(a, e)
    return np.stack([np.sin(a) * np.cos(e), np.cos(a) * np.cos(e), np.sin(e)], axis=-1)


def _utc_index(times: Any):
    """Time-zone-aware instants → UTC ``pandas.DatetimeIndex``; naive ones raise."""
    import pandas as pd

    naive = (
        "has no time zone: the sun's position needs the instant. Give an aware "
        "datetime (e.g. datetime(2024, 6, 15, 9, 30, tzinfo=timezone.utc) or "
        "ZoneInfo('Europe/Madrid'))"
    )
    if isinstance(times, datetime):
        if times.tzinfo is None or times.utcoffset() is None:
            raise InputError(f"time {times.isoformat()} {naive}")
        return pd.DatetimeIndex([pd.Timestamp(times)]).tz_convert("UTC")
    if isinstance(times, pd.DatetimeIndex):
        if times.tz is None:
            raise InputError(f"DatetimeIndex {naive}")
        return times.tz_convert("UTC")
    if isinstance(times, np.ndarray) and np.issubdtype(times.dtype, np.datetime64):
        raise InputError(f"numpy datetime64 {naive}")
    items = list(times)
    for t in items:
        if not isinstance(t, datetime):
            raise InputError(f"expected datetimes, got {type(t).__name__}")
        if t.tzinfo is None or t.utcoffset() is None:
            raise InputError(f"time {t.isoformat()} {naive}")
    # Per item: mixed time zones are allowed.
    return pd.DatetimeIndex([pd.Timestamp(t).tz_convert("UTC") for t in items])


def sun_positions(
    times: Any,
    latitude_deg: float,
    longitude_deg: float,
    altitude_m: float = 0.0,
    *,
    pressure_pa: float | None = None,
    temperature_c: float = 12.0,
    delta_t_s: float | None = None,
) -> SunTrack:
    """Sun position at many instants from one place (NREL SPA, vectorised).

    Parameters
    ----------
    times : aware datetime, sequence of aware datetimes or tz-aware pandas.DatetimeIndex
        E.g. ``pandas.date_range("2024-06-15", periods=288, freq="5min", tz="UTC")``.
    latitude_deg, longitude_deg : float
        WGS84 degrees, north and east positive.
    altitude_m : float
        Observer height above sea level, metres (parallax; default pressure).
    pressure_pa : float, optional
        Air pressure for refraction; default: standard atmosphere at
        ``altitude_m``.
    temperature_c : float
        Air temperature for refraction, °C.
    delta_t_s : float, optional
        TT − UT1 in seconds; default: pvlib's estimate for the year and month
        (about 69 s in 2024; 1 s changes the azimuth by at most ~0.004°).

    Returns
    -------
    SunTrack

    Raises
    ------
    InputError (a ValueError)
        A naive time (no time zone), or a latitude outside [-90, 90].
    """
    from pvlib import atmosphere, solarposition

    if not -90.0 <= float(latitude_deg) <= 90.0:
        raise InputError(f"latitude {latitude_deg} is outside [-90, 90]")
    idx = _utc_index(times)
    if pressure_pa is None:
        pressure_pa = float(atmosphere.alt2pres(float(altitude_m)))
    df = solarposition.spa_python(
        idx,
        float(latitude_deg),
        float(longitude_deg),
        altitude=float(altitude_m),
        pressure=float(pressure_pa),
        temperature=float(temperature_c),
        delta_t=delta_t_s,
    )
    return SunTrack(
        times=idx,
        latitude_deg=float(latitude_deg),
        longitude_deg=float(longitude_deg),
        altitude_m=float(altitude_m),
        azimuth_deg=df["azimuth"].to_numpy(np.float64) % 360.0,
        elevation_deg=df["apparent_elevation"].to_numpy(np.float64),
        zenith_deg=df["apparent_zenith"].to_numpy(np.float64),
        geometric_elevation_deg=df["elevation"].to_numpy(np.float64),
    )


def sun_position(
    when: datetime,
    latitude_deg: float,
    longitude_deg: float,
    altitude_m: float = 0.0,
    **kw: Any,
) -> SunPosition:
    """Sun position at one instant (NREL SPA, ±0.0003° over -2000..6000).

    Parameters
    ----------
    when : datetime
        Time-zone aware instant (a naive datetime raises: the hour alone
        does not fix the sun).
    latitude_deg, longitude_deg : float
        WGS84 degrees, north and east positive.
    altitude_m : float
        Observer height above sea level, metres.
    **kw
        ``pressure_pa``, ``temperature_c``, ``delta_t_s``: see :func:`sun_positions`.

    Returns
    -------
    SunPosition
        Azimuth clockwise from TRUE north; for the local frame's grid north
        use :func:`sun_direction_local`.

    Raises
    ------
    InputError (a ValueError)
        ``when`` is naive.

    Examples
    --------
    >>> from datetime import datetime, timedelta, timezone
    >>> tz = timezone(timedelta(hours=-7))
    >>> s = sun_position(datetime(2003, 10, 17, 12, 30, 30, tzinfo=tz),
    ...                  39.742476, -105.1786, 1830.14, pressure_pa=82000.0,
    ...                  temperature_c=11.0, delta_t_s=67.0)
    >>> round(s.zenith_deg, 3), round(s.azimuth_deg, 3)
    (50.112, 194.34)
    """
    if not isinstance(when, datetime):
        raise InputError(f"expected a datetime, got {type(when).__name__}")
    track = sun_positions(when, latitude_deg, longitude_deg, altitude_m, **kw)
    # Keep the caller's time zone in the record (the instant is the same).
    return replace(track[0], when=when)

# ---------------------------------------------------------------------------
# grid north versus true north
# ---------------------------------------------------------------------------


def meridian_convergence_deg(georef: Georef, local_xyz: npt.ArrayLike = (0.0, 0.0, 0.0)):
    """Meridian convergence at local points: true north to grid north, degrees.

    PROJ's convention (``pyproj.Proj.get_factors(...).meridian_convergence``):
    positive when grid north lies clockwise of true north, as east of a UTM
    zone's central meridian in the northern hemisphere. Hence, at that point,

        grid azimuth = true azimuth − convergence.

    Computed from the georeference's own transform (the grid direction of a
    short step due north), which is exact for any CRS and needs no sign
    convention.

    Parameters
    ----------
    georef : Georef
    local_xyz : array, shape (3,) or (N, 3)
        Local-frame points, metres (default: the local origin).

    Returns
    -------
    float for one point, else (N,) float64 array, degrees.
    """
    lat, lon, _ = georef.local_to_geodetic(local_xyz)
    single = np.ndim(lat) == 0
    lat = np.atleast_1d(np.asarray(lat, np.float64))
    lon = np.atleast_1d(np.asarray(lon, np.float64))
    # A ~1 m step in latitude each way (central difference), kept off the poles.
    step = 1e-5
    lat_n = np.minimum(lat + step, 90.0)
    lat_s = np.maximum(lat - step, -90.0)
    tr = _transformer("EPSG:4326", georef.crs)
    e_n, n_n = tr.transform(lon, lat_n)
    e_s, n_s = tr.transform(lon, lat_s)
    grid_az_of_true_north = np.degrees(
        np.arctan2(np.asarray(e_n) - np.asarray(e_s), np.asarray(n_n) - np.asarray(n_s))
    )
    conv = -grid_az_of_true_north
    return float(conv[0]) if single else conv


def sun_direction_local(
    sun: SunPosition | SunTrack,
    georef: Georef | None,
    local_xyz: npt.ArrayLike = (0.0, 0.0, 0.0),
) -> np.ndarray:
    """Unit vector toward the sun in the local frame (grid north = +Y).

    The azimuth is turned from true to grid north by the meridian
    convergence at ``local_xyz``; the elevation is kept (conformal
    projections such as UTM preserve angles; the Earth's curvature across
    an outcrop, ~0.01° per km, is neglected).

    Parameters
    ----------
    sun : SunPosition or SunTrack
    georef : Georef or None
        None: the local +Y is taken as true north (no correction).
    local_xyz : array, shape (3,)
        Where the convergence is evaluated (the camera or the outcrop),
        local metres.

    Returns
    -------
    ndarray, shape (3,) (or (N, 3) for a SunTrack)
    """
    conv = 0.0 if georef is None else meridian_convergence_deg(georef, np.asarray(local_xyz, float))
    grid_az = np.asarray(sun.azimuth_deg, np.float64) - conv
    return sun_vector_enu(grid_az, sun.elevation_deg)


def sun_for_photo(
    exif: Mapping[str, Any],
    georef: Georef | None,
    camera_center_local: npt.ArrayLike,
    assume_time_zone: str | timedelta | tzinfo | None = None,
) -> tuple[np.ndarray | None, SunPosition | None, list[str]]:
    """The sun of a photo: direction in the local frame, position, assumptions.

    Parameters
    ----------
    exif : mapping
        The photo's EXIF (see :func:`napari_imgreg.io.exif.read_capture_time`).
    georef : Georef or None
        Needed to place the camera on the Earth. Without it, the EXIF GPS
        position is used and the local +Y is taken as true north (said in
        the assumptions).
    camera_center_local : array, shape (3,)
        Camera centre, local metres.
    assume_time_zone : str, timedelta or tzinfo, optional
        Zone for a capture time without one (see
        :func:`napari_imgreg.io.exif.read_capture_time`).

    Returns
    -------
    direction : (3,) float64 array or None
        Unit vector toward the sun, local frame; None without capture time
        or position.
    sun : SunPosition or None
    assumptions : list of str
        What was assumed or is odd (guessed time zone, GPS time, sun below
        the horizon, no georeference), for the user.
    """
    capture = read_capture_time(exif, assume_time_zone)
    notes = list(capture.notes)
    if capture.when is None:
        return None, None, notes
    center = np.asarray(camera_center_local, np.float64).reshape(3)
    if georef is not None:
        lat, lon, alt = georef.local_to_geodetic(center)
    else:
        gps = exif.get("GPSInfo")
        gps = gps if isinstance(gps, Mapping) else exif
        lat = gps_degrees(gps.get("GPSLatitude"), gps.get("GPSLatitudeRef", "N"))
        lon = gps_degrees(gps.get("GPSLongitude"), gps.get("GPSLongitudeRef", "E"))
        if lat is None or lon is None:
            notes.append("no georeference and no EXIF GPS position: sun position unknown")
            return None, None, notes
        alt = 0.0
        notes.append(
            "no georeference: sun placed at the EXIF GPS position, model +Y taken as true north"
        )
    alt = float(alt) if math.isfinite(alt) else 0.0
    sun = sun_position(capture.when, float(lat), float(lon), alt)
    if not sun.is_up:
        notes.append(
            f"the sun was below the horizon at capture time (elevation {sun.elevation_deg:.1f}°)"
        )
    return sun_direction_local(sun, georef, center), sun, notes


def sun_from_record(
    record: SensorRecord,
    georef: Georef | None,
    local_xyz: npt.ArrayLike,
) -> np.ndarray | None:
    """The sun of a sensor record (or ``survey.json``): unit vector, local frame.

    The one reading of a record's sun, shared by the prior of a photo
    (:func:`napari_imgreg.prior.prior_for_photo`) and the survey sun of a
    model's texture (:func:`napari_imgreg.scene.read_survey_sun`). A ``sun``
    block wins: its azimuth, clockwise from TRUE north, is turned to grid
    north by the meridian convergence at ``local_xyz`` (no correction without
    a georeference: +Y is then true north). Else the ``time`` gives the sun's
    position at ``local_xyz``, placed on the Earth by ``georef``.

    Parameters
    ----------
    record : SensorRecord
        Only its ``sun`` (``{"azimuth_deg", "elevation_deg"}``) and ``time``
        (ISO 8601 with its UTC offset) are read.
    georef : Georef or None
        The local frame's georeference; needed for a ``time``.
    local_xyz : array, shape (3,)
        Where the sun is seen from (a camera centre, the middle of a model),
        local metres.

    Returns
    -------
    (3,) float64 array or None
        Unit vector toward the sun, local frame (+Y grid north); None when
        the record has neither ``sun`` nor ``time``.

    Raises
    ------
    InputError
        A ``time`` without a georeference, or a ``time`` without UTC offset.
    """
    where = np.asarray(local_xyz, np.float64).reshape(3)
    if record.sun is not None:
        conv = 0.0 if georef is None else meridian_convergence_deg(georef, where)
        return sun_vector_enu(record.sun["azimuth_deg"] - conv, record.sun["elevation_deg"])
    if record.time is None:
        return None
    if georef is None:
        raise InputError(
            f"capture time {record.time} needs a georeference to place the sun"
        )
    when = record.capture_datetime
    if when is None:
        raise InputError(f"capture time {record.time!r} is not ISO 8601 with a UTC offset")
    lat, lon, alt = georef.local_to_geodetic(where)
    alt = float(alt) if math.isfinite(alt) else 0.0
    return sun_direction_local(sun_position(when, float(lat), float(lon), alt), georef, where)
