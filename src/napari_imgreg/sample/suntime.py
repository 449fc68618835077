"""Capture times for synthetic photos: when does the sun stand where the photo is lit from?

The generator chooses a photo's light first (a sun direction in the model's
local frame, :class:`~napari_imgreg.sample.photo.PhotoConditions`); a real
photo's light follows from when and where it was taken. To make synthetic
photos consistent with their EXIF (so that sun-aware registration computes the
sun a real phone's photo would give it), we search the year for the instant
at which the sun, seen from the camera, is closest to the chosen direction,
and write that instant as the photo's capture time. The remaining difference
(usually a few hundredths of a degree; more for a direction the sun never
takes at that latitude) is reported so callers can keep the photo's own sun
equal to the time's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone

import numpy as np
import numpy.typing as npt

from ..geo import Georef
from ..solar import sun_direction_local, sun_positions

__all__ = ["SunTime", "time_for_sun", "local_utc_offset"]


@dataclass(frozen=True)
class SunTime:
    """An instant at which the sun stands (nearly) in a wanted direction.

    Attributes
    ----------
    when : datetime
        Time-zone aware instant, in the place's civil offset (see
        :func:`local_utc_offset`).
    direction : (3,) float64 array
        Unit vector toward the sun at ``when``, local frame.
    azimuth_deg, elevation_deg : float
        That direction as grid azimuth (clockwise from the local +Y) and elevation.
    miss_deg : float
        Angle between the wanted and the found direction, degrees.
    """

    when: datetime
    direction: np.ndarray
    azimuth_deg: float
    elevation_deg: float
    miss_deg: float


def local_utc_offset(longitude_deg: float) -> timezone:
    """A civil-time offset for a longitude: the nearest whole hour (nautical time)."""
    return timezone(timedelta(hours=int(round(longitude_deg / 15.0))))


def _best(times, lat: float, lon: float, alt: float, georef: Georef | None,
          center: np.ndarray, wanted: np.ndarray) -> tuple[int, np.ndarray]:
    track = sun_positions(times, lat, lon, alt)
    dirs = sun_direction_local(track, georef, center)
    score = dirs @ wanted
    k = int(np.argmax(score))
    return k, dirs[k]


def time_for_sun(
    wanted_direction: npt.ArrayLike,
    georef: Georef,
    center_local: npt.ArrayLike,
    year: int = 2024,
) -> SunTime:
    """The instant of ``year`` at which the sun is closest to a local direction.

    A coarse search (every 20 minutes of the year) is refined around its best
    instant (every 10 seconds over ±40 minutes on the same and the
    neighbouring days). Vectorised through :func:`napari_imgreg.solar.sun_positions`.

    Parameters
    ----------
    wanted_direction : (3,) array
        Toward the sun, local frame (grid north = +Y, up = +Z).
    georef : Georef
        Places the local frame on the Earth.
    center_local : (3,) array
        The observer (camera), local metres.
    year : int

    Returns
    -------
    SunTime
    """
    import pandas as pd

    wanted = np.asarray(wanted_direction, np.float64).reshape(3)
    wanted = wanted / np.linalg.norm(wanted)
    center = np.asarray(center_local, np.float64).reshape(3)
    lat, lon, alt = (float(v) for v in georef.local_to_geodetic(center))
    alt = alt if math.isfinite(alt) else 0.0
    coarse = pd.date_range(f"{year}-01-01", f"{year + 1}-01-01", freq="20min", tz="UTC",
                           inclusive="left")
    k, _ = _best(coarse, lat, lon, alt, georef, center, wanted)
    t0 = coarse[k]
    window = pd.timedelta_range("-40min", "40min", freq="10s")
    days = pd.to_timedelta(np.arange(-3, 4), unit="D")
    fine = pd.DatetimeIndex([t0 + d + w for d in days for w in window])
    k, direction = _best(fine, lat, lon, alt, georef, center, wanted)
    when = fine[k].to_pydatetime().replace(microsecond=0).astimezone(local_utc_offset(lon))
    miss = math.degrees(math.acos(float(np.clip(direction @ wanted, -1.0, 1.0))))
    az = math.degrees(math.atan2(direction[0], direction[1])) % 360.0
    el = math.degrees(math.asin(float(np.clip(direction[2], -1.0, 1.0))))
    return SunTime(when, direction, az, el, miss)
