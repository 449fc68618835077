"""Photo metadata: EXIF capture time, GPS position and DJI XMP gimbal angles.

The one place where EXIF and XMP tags are read and interpreted:

* :func:`exif_of_image`: the tags of an open PIL image by name, as
  :func:`napari_imgreg.io.photos.load_photo` stores them in ``Photo.exif``;
* :func:`read_capture_time`: when the photo was taken, time zone included,
  and how that was found (Exif 2.31 offsets, GPS time, an assumed zone);
  :func:`capture_date` / :func:`read_photo_capture_date`: only the day, which
  needs no time zone (what a magnetic declination needs);
* :func:`gps_degrees`: EXIF GPS degrees/minutes/seconds to signed degrees;
* :func:`dji_gimbal_angles` / :func:`attitude_from_dji_gimbal`: a drone's
  camera attitude from its XMP packet (:func:`raw_xmp` finds the packet in
  files PIL does not parse it from);
* :func:`record_from_exif`: a sensor record (contract §3) from all of these.

Tags are looked up by name (``"DateTimeOriginal"``, GPS tags in a
``"GPSInfo"`` mapping, the XMP packet under ``"XMP"``); values may be str or
bytes, rationals PIL ``IFDRational``, numbers or ``(num, den)`` pairs.

This module is backend only: no Qt or napari imports.

References
----------
.. [1] CIPA DC-008-2016 (Exif 2.31): ``OffsetTimeOriginal`` and the GPS
   time tags.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from datetime import date, datetime, timedelta, timezone, tzinfo
from pathlib import Path
from typing import Any, Mapping

from ..camera import Intrinsics
from ..errors import InputError, input_error
from ..validate import FieldValueError, check_number
from .records import RECORD_RANGES, SensorRecord

__all__ = [
    "CaptureTime",
    "read_capture_time",
    "capture_time_from_exif",
    "capture_date",
    "read_photo_capture_date",
    "HEADING_REFERENCES",
    "gps_heading_reference",
    "gps_degrees",
    "exif_of_image",
    "ensure_heif_opener",
    "HEIF_SUFFIXES",
    "read_photo_xmp_and_gps",
    "raw_xmp",
    "dji_gimbal_angles",
    "DJI_GIMBAL_RANGES",
    "attitude_from_dji_gimbal",
    "EXIF_QUARTER_TURNS",
    "EXIF_MIRRORED",
    "exif_orientation",
    "record_from_exif",
]


# ---------------------------------------------------------------------------
# capture time
# ---------------------------------------------------------------------------

_EXIF_DATETIME = re.compile(
    r"^\s*(\d{4})[:\-](\d{2})[:\-](\d{2})[ T](\d{2}):(\d{2}):(\d{2})(?:[.,](\d+))?\s*$"
)
_EXIF_DATE = re.compile(r"^\s*(\d{4})[:\-](\d{2})[:\-](\d{2})\s*$")
_UTC_OFFSET = re.compile(r"^\s*(?:(Z)|([+-])(\d{2}):?(\d{2}))\s*$")


@dataclass(frozen=True)
class CaptureTime:
    """When a photo was taken, and how we know.

    Attributes
    ----------
    when : datetime or None
        Time-zone aware capture instant; None when the EXIF cannot fix it.
    source : str
        ``"DateTimeOriginal+OffsetTimeOriginal"`` (or ``+OffsetTimeDigitized``,
        ``+OffsetTime``), ``"GPSDateStamp+GPSTimeStamp"``,
        ``"DateTimeOriginal+assumed time zone"`` or ``"none"``.
    notes : tuple of str
        What was assumed or found odd, for the user (e.g. a guessed time zone).
    """

    when: datetime | None
    source: str
    notes: tuple[str, ...] = field(default_factory=tuple)


def _text(value: Any) -> str | None:
    """EXIF ASCII value (str or bytes, NUL padded) → stripped str, or None."""
    if value is None:
        return None
    if isinstance(value, (bytes, bytearray)):
        value = bytes(value).decode("ascii", "replace")
    s = str(value).strip("\x00 \t")
    return s or None


def _parse_local_datetime(value: Any, subsec: Any = None) -> datetime | None:
    """``"YYYY:MM:DD HH:MM:SS"`` (+ SubSecTime digits) → naive datetime, None if blank/bad."""
    if isinstance(value, datetime):
        return value.replace(tzinfo=None) if value.tzinfo is None else value
    s = _text(value)
    m = _EXIF_DATETIME.match(s) if s else None
    if m is None:
        return None
    y, mo, d, hh, mm, ss, frac = m.groups()
    sub = frac or _text(subsec)
    micro = 0
    if sub and sub.isdigit():
        micro = int(round(float("0." + sub) * 1e6))
    try:
        return datetime(int(y), int(mo), int(d), int(hh), int(mm), int(ss)) + timedelta(
            microseconds=micro
        )
    except ValueError:  # "0000:00:00 00:00:00" and other placeholders
        return None


def _parse_offset(value: Any) -> timezone | None:
    """``"+02:00"`` / ``"-0700"`` / ``"Z"`` → fixed-offset tzinfo, None if blank/bad."""
    s = _text(value)
    m = _UTC_OFFSET.match(s) if s else None
    if m is None:
        return None
    if m.group(1):
        return timezone.utc
    sign = -1 if m.group(2) == "-" else 1
    hours, minutes = int(m.group(3)), int(m.group(4))
    if hours > 14 or minutes >= 60:
        return None
    return timezone(sign * timedelta(hours=hours, minutes=minutes))


def _number(v: Any) -> float:
    """An EXIF rational (IFDRational, (num, den) tuple, number) → float."""
    if isinstance(v, (tuple, list)) and len(v) == 2:
        return float(v[0]) / float(v[1])
    return float(v)


def _gps_utc(gps: Mapping[str, Any]) -> datetime | None:
    """GPSDateStamp + GPSTimeStamp (UTC by definition) → aware datetime, or None."""
    date_s = _text(gps.get("GPSDateStamp"))
    stamp = gps.get("GPSTimeStamp")
    dm = _EXIF_DATE.match(date_s) if date_s else None
    if dm is None or stamp is None:
        return None
    try:
        if isinstance(stamp, (str, bytes)):
            hms = [float(p) for p in (_text(stamp) or "").split(":")]
        else:
            hms = [_number(p) for p in stamp]
        if len(hms) != 3 or not all(math.isfinite(v) for v in hms):
            return None
        seconds = hms[0] * 3600.0 + hms[1] * 60.0 + hms[2]
        if not 0.0 <= seconds < 86400.5:
            return None
        day = datetime(int(dm.group(1)), int(dm.group(2)), int(dm.group(3)), tzinfo=timezone.utc)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return day + timedelta(seconds=seconds)


def _as_tzinfo(zone: str | timedelta | tzinfo) -> tzinfo:
    """``"+02:00"``, an IANA name (``"Europe/Madrid"``), a timedelta or a tzinfo → tzinfo."""
    if isinstance(zone, tzinfo):
        return zone
    if isinstance(zone, timedelta):
        return timezone(zone)
    tz = _parse_offset(zone)
    if tz is not None:
        return tz
    from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

    try:
        return ZoneInfo(str(zone))
    except (ZoneInfoNotFoundError, ValueError):
        raise InputError(
            f"time zone {zone!r} is neither a UTC offset like '+02:00' nor a known "
            "IANA name like 'Europe/Madrid'"
        ) from None


def _tz_label(tz: tzinfo, at: datetime) -> str:
    off = tz.utcoffset(at) or timedelta(0)
    total = int(off.total_seconds() // 60)
    sign = "-" if total < 0 else "+"
    label = f"UTC{sign}{abs(total) // 60:02d}:{abs(total) % 60:02d}"
    key = getattr(tz, "key", None)  # ZoneInfo name
    return f"{key} ({label})" if key else label


def read_capture_time(
    exif: Mapping[str, Any],
    assume_time_zone: str | timedelta | tzinfo | None = None,
) -> CaptureTime:
    """The capture instant of a photo from its EXIF, with how it was found.

    Order: (1) ``DateTimeOriginal`` (+ ``SubsecTimeOriginal``) with its
    Exif 2.31 offset ``OffsetTimeOriginal`` (else ``OffsetTimeDigitized``,
    else ``OffsetTime``: phones write them alike); (2) the GPS fix time
    ``GPSDateStamp`` + ``GPSTimeStamp`` (UTC); (3) a ``DateTimeOriginal``
    without any zone: only with ``assume_time_zone``, and the note says the
    zone was assumed. Otherwise ``when`` is None: the time zone is never
    guessed silently (an hour off moves the sun ~15° in azimuth).

    Parameters
    ----------
    exif : mapping
        Tags by name as :func:`napari_imgreg.io.photos.load_photo` gives
        them: EXIF and IFD0 tags at the top level, GPS tags in a
        ``"GPSInfo"`` mapping (GPS tags at the top level are accepted too).
        Values may be str or bytes; rationals as PIL ``IFDRational``,
        numbers or ``(num, den)`` pairs.
    assume_time_zone : str, timedelta or tzinfo, optional
        Zone for a zone-less ``DateTimeOriginal``: ``"+02:00"`` or, better
        (daylight saving is then right), an IANA name ``"Europe/Madrid"``.

    Returns
    -------
    CaptureTime
    """
    gps = exif.get("GPSInfo")
    if not isinstance(gps, Mapping):  # an empty GPS IFD leaves its offset (an int)
        gps = exif
    local = _parse_local_datetime(exif.get("DateTimeOriginal"), exif.get("SubsecTimeOriginal"))
    gps_time = _gps_utc(gps)
    notes: list[str] = []

    if local is not None and local.tzinfo is not None:  # an aware datetime was given
        return CaptureTime(local, "DateTimeOriginal", ())
    if local is not None:
        for tag in ("OffsetTimeOriginal", "OffsetTimeDigitized", "OffsetTime"):
            tz = _parse_offset(exif.get(tag))
            if tz is None:
                continue
            when = local.replace(tzinfo=tz)
            if tag != "OffsetTimeOriginal":
                notes.append(f"time zone of DateTimeOriginal taken from EXIF {tag}")
            if gps_time is not None:
                gap_min = abs((when - gps_time).total_seconds()) / 60.0
                if gap_min > 5.0:
                    notes.append(
                        f"camera clock and GPS time differ by {gap_min:.0f} min; "
                        "using the camera clock"
                    )
            return CaptureTime(when, f"DateTimeOriginal+{tag}", tuple(notes))
    if gps_time is not None:
        notes.append("capture time from the GPS time stamp (UTC)")
        return CaptureTime(gps_time, "GPSDateStamp+GPSTimeStamp", tuple(notes))
    if local is not None:
        if assume_time_zone is not None:
            tz = _as_tzinfo(assume_time_zone)
            when = local.replace(tzinfo=tz)
            notes.append(
                f"EXIF capture time {local.isoformat(sep=' ')} has no time zone: "
                f"assumed {_tz_label(tz, when)}"
            )
            return CaptureTime(when, "DateTimeOriginal+assumed time zone", tuple(notes))
        notes.append(
            f"EXIF capture time {local.isoformat(sep=' ')} has no time zone (no "
            "OffsetTimeOriginal, no GPS time stamp): capture time unknown; give the "
            "photo's time zone to use it"
        )
        return CaptureTime(None, "none", tuple(notes))
    return CaptureTime(None, "none", ("no capture time in the photo's EXIF",))


def capture_time_from_exif(
    exif: Mapping[str, Any],
    assume_time_zone: str | timedelta | tzinfo | None = None,
) -> datetime | None:
    """The time-zone-aware capture instant from EXIF, or None.

    A ``DateTimeOriginal`` without ``OffsetTime*`` and without GPS time gives
    None unless ``assume_time_zone`` is given; see :func:`read_capture_time`
    (which also says how the time was found) for the rules.
    """
    return read_capture_time(exif, assume_time_zone).when


def capture_date(exif: Mapping[str, Any]) -> date | None:
    """The day a photo was taken, from its EXIF, or None.

    ``DateTimeOriginal``'s calendar date as the camera wrote it (local: no
    time zone is needed for a day), else the GPS ``GPSDateStamp`` (UTC).
    A day is what a magnetic declination needs: it changes by a few
    hundredths of a degree in a month, so the zone (a day at most) is moot.

    Parameters
    ----------
    exif : mapping
        Tags by name, as for :func:`read_capture_time`.

    Returns
    -------
    datetime.date or None
    """
    local = _parse_local_datetime(exif.get("DateTimeOriginal"), exif.get("SubsecTimeOriginal"))
    if local is not None:
        return local.date()
    gps = exif.get("GPSInfo")
    if not isinstance(gps, Mapping):
        gps = exif
    stamp = _text(gps.get("GPSDateStamp"))
    found = _EXIF_DATE.match(stamp) if stamp else None
    if found is None:
        return None
    try:
        return date(int(found.group(1)), int(found.group(2)), int(found.group(3)))
    except ValueError:  # "0000:00:00"
        return None


def read_photo_capture_date(path: str | os.PathLike) -> date | None:
    """The day a photo file was taken (:func:`capture_date`), without decoding
    its pixels; None when its EXIF has no date or the file has no EXIF.

    Raises
    ------
    InputError
        The file cannot be read as an image.
    """
    return capture_date(_read_header(Path(path), exif_of_image))


def _read_header(path: Path, read: Any) -> Any:
    """``read(image)`` on a photo file opened by PIL (its header and tags,
    no pixels decoded); a file PIL cannot open is one InputError."""
    from PIL import Image, UnidentifiedImageError

    if path.suffix.lower() in HEIF_SUFFIXES:
        ensure_heif_opener()
    try:
        with Image.open(path) as im:
            return read(im)
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise input_error(path, f"cannot read photo metadata ({exc})") from None


# ---------------------------------------------------------------------------
# GPS position
# ---------------------------------------------------------------------------


def gps_degrees(value: Any, ref: Any) -> float | None:
    """EXIF GPS degrees/minutes/seconds (+ N/S/E/W reference) to signed degrees.

    Parameters
    ----------
    value : sequence of 3 numbers
        ``GPSLatitude`` or ``GPSLongitude``: degrees, minutes, seconds
        (rationals or numbers).
    ref : str or bytes
        ``GPSLatitudeRef`` / ``GPSLongitudeRef``: ``"S"`` and ``"W"`` are
        negative.

    Returns
    -------
    float or None
        Degrees (north and east positive); None when ``value`` is missing or
        not three finite numbers.
    """
    try:
        d, m, sec = (float(v) for v in value)
    except (TypeError, ValueError):
        return None
    deg = d + m / 60.0 + sec / 3600.0
    if not math.isfinite(deg):
        return None
    return -deg if str(ref).strip().upper() in ("S", "W") else deg


# ---------------------------------------------------------------------------
# reading the tags of a file
# ---------------------------------------------------------------------------


def exif_of_image(im: Any) -> dict[str, Any]:
    """The EXIF tags of an open PIL image, by name.

    Parameters
    ----------
    im : PIL.Image.Image
        An opened image (its pixels need not be decoded).

    Returns
    -------
    dict
        IFD0 and Exif sub-IFD tags at the top level (``FocalLength``,
        ``Model``, ``DateTimeOriginal``, ...); GPS tags as a dict by name
        under ``"GPSInfo"`` (absent without GPS); the XMP packet as text
        under ``"XMP"`` (absent without XMP).
    """
    from PIL import ExifTags

    raw_exif = im.getexif()
    exif: dict[str, Any] = {ExifTags.TAGS.get(k, str(k)): v for k, v in raw_exif.items()}
    # Camera details (FocalLength, ...) live in the Exif sub-IFD.
    for k, v in raw_exif.get_ifd(ExifTags.IFD.Exif).items():
        exif[ExifTags.TAGS.get(k, str(k))] = v
    gps = raw_exif.get_ifd(ExifTags.IFD.GPSInfo)
    exif.pop("GPSInfo", None)  # the IFD offset, not the tags
    if gps:
        exif["GPSInfo"] = {ExifTags.GPSTAGS.get(k, str(k)): v for k, v in gps.items()}
    xmp = im.info.get("xmp")
    if xmp:
        exif["XMP"] = xmp.decode("utf-8", "replace") if isinstance(xmp, bytes) else xmp
    return exif


#: Suffixes of HEIC/HEIF photos, which Pillow opens through pillow-heif.
HEIF_SUFFIXES = (".heic", ".heif")


def ensure_heif_opener() -> None:
    """Let Pillow open HEIC/HEIF photos (pillow-heif's plugin; registered once)."""
    global _HEIF_REGISTERED
    if not _HEIF_REGISTERED:
        from pillow_heif import register_heif_opener

        register_heif_opener()
        _HEIF_REGISTERED = True


_HEIF_REGISTERED = False


def read_photo_xmp_and_gps(path: str | os.PathLike) -> tuple[str | None, dict[str, Any]]:
    """The XMP packet and the GPS tags of a photo file, without decoding its pixels.

    The XMP packet is PIL's (JPEG ``xmp``, PNG ``XML:com.adobe.xmp``), else
    the one found in the file's first MiB (TIFF, DNG: see :func:`raw_xmp`).

    Returns
    -------
    xmp : str or None
    gps : dict
        GPS tags by name (``GPSImgDirection``, ...); empty without GPS.

    Raises
    ------
    InputError
        The file cannot be read as an image.
    """
    from PIL import ExifTags

    path = Path(path)
    xmp, gps = _read_header(path, lambda im: (
        im.info.get("xmp") or im.info.get("XML:com.adobe.xmp"),
        im.getexif().get_ifd(ExifTags.IFD.GPSInfo)))
    xmp_text = xmp.decode("utf-8", "replace") if isinstance(xmp, bytes) else xmp
    if not xmp_text:
        xmp_text = raw_xmp(path)
    return xmp_text, {ExifTags.GPSTAGS.get(k, str(k)): v for k, v in gps.items()}


def raw_xmp(path: Path, limit: int = 1 << 20) -> str | None:
    """The XMP packet found in the first ``limit`` bytes of a file, if any."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(limit)
    except OSError:
        return None
    start = head.find(b"<x:xmpmeta")
    end = head.find(b"</x:xmpmeta>", start)
    if start < 0 or end < 0:
        return None
    return head[start : end + len(b"</x:xmpmeta>")].decode("utf-8", "replace")


# ---------------------------------------------------------------------------
# DJI gimbal angles (XMP)
# ---------------------------------------------------------------------------

_DJI_TAGS = ("GimbalYawDegree", "GimbalPitchDegree", "GimbalRollDegree")

#: The declared range of each DJI gimbal angle, degrees: those of the
#: attitude it becomes (yaw → trend, pitch → −plunge, roll → roll; see
#: :data:`napari_imgreg.io.records.RECORD_RANGES`). DJI writes yaw and roll
#: within ±180 and pitch within ±90; anything else is a corrupt packet.
DJI_GIMBAL_RANGES = {
    "GimbalYawDegree": RECORD_RANGES["orientation"]["trend_deg"][:2],
    "GimbalPitchDegree": RECORD_RANGES["orientation"]["plunge_deg"][:2],
    "GimbalRollDegree": RECORD_RANGES["orientation"]["roll_deg"][:2],
}


#: Accepted EXIF ``GPSImgDirection``, degrees (wrapped to [0, 360)).
GPS_IMG_DIRECTION_RANGE = (-720.0, 720.0)


def dji_gimbal_angles(xmp: str, source: str | os.PathLike | None = None
                      ) -> tuple[float, float, float] | None:
    """(yaw, pitch, roll) from ``drone-dji:Gimbal*Degree`` (attribute or element form).

    Parameters
    ----------
    xmp : str
        The XMP packet.
    source : path-like, optional
        The photo, named in the error.

    Returns
    -------
    (yaw, pitch, roll) in degrees, or None
        None when the packet has no gimbal angles (not a DJI photo, or only
        some of the three tags).

    Raises
    ------
    InputError
        A gimbal tag is present but not a finite number within
        :data:`DJI_GIMBAL_RANGES` (``field 'XMP drone-dji:GimbalPitchDegree'
        must be within [-90, 90], got 135``).
    """
    found = {}
    for tag in _DJI_TAGS:
        match = re.search(
            rf"drone-dji:{tag}\s*=\s*\"([^\"]*)\"|<drone-dji:{tag}>\s*([^<]*?)\s*</", xmp
        )
        if match is not None:
            found[tag] = match.group(1) if match.group(1) is not None else match.group(2)
    if len(found) < len(_DJI_TAGS):
        return None
    values = []
    for tag in _DJI_TAGS:
        text = found[tag].strip()
        low, high = DJI_GIMBAL_RANGES[tag]
        try:
            value: Any = float(text)
        except ValueError:
            value = text
        try:
            values.append(check_number(value, f"XMP drone-dji:{tag}", low, high))
        except FieldValueError as exc:
            raise input_error(source, str(exc)) from None
    return values[0], values[1], values[2]


def attitude_from_dji_gimbal(
    yaw_deg: float, pitch_deg: float, roll_deg: float
) -> tuple[float, float, float]:
    """Contract trend, plunge, roll from DJI gimbal yaw, pitch, roll.

    DJI writes aerospace (NED, Z-Y-X) Euler angles of the gimbal: yaw
    clockwise from north, pitch positive nose-up (−90 looking straight
    down), roll positive right side down. Hence trend = yaw mod 360,
    plunge = −pitch, roll = roll (positive roll lowers the camera x axis,
    as in contract §2).
    """
    return float(yaw_deg) % 360.0, -float(pitch_deg), float(roll_deg)


# ---------------------------------------------------------------------------
# EXIF orientation
# ---------------------------------------------------------------------------

#: EXIF ``Orientation`` → quarter turns (clockwise) that its display applies
#: to the stored pixels (:meth:`Intrinsics.rotated`, :meth:`Pose.rotated`).
#: The mirrored ones (2, 4, 5, 7) are listed with the turn of their
#: unmirrored part, for messages only: a mirrored image has no camera pose.
EXIF_QUARTER_TURNS = {1: 0, 2: 0, 3: 2, 4: 2, 5: 1, 6: 1, 7: -1, 8: -1}

#: EXIF orientations whose display mirrors the stored pixels.
EXIF_MIRRORED = (2, 4, 5, 7)


def exif_orientation(exif: Mapping[str, Any] | None) -> int | None:
    """The EXIF ``Orientation`` tag (1–8) of tags by name; None when absent or
    not one of the eight values (Pillow then leaves the pixels as stored)."""
    value = (exif or {}).get("Orientation")
    if isinstance(value, bool):
        return None
    try:
        value = int(value)
    except (TypeError, ValueError, OverflowError):
        return None
    return value if 1 <= value <= 8 else None


# ---------------------------------------------------------------------------
# a sensor record from the metadata
# ---------------------------------------------------------------------------

_BLOCKS = ("camera", "position", "orientation")


def _checked(value: Any, tag: str, low: float, high: float, source) -> float:
    """An EXIF/XMP number, finite and within ``[low, high]`` (the range of the
    record field it fills, :data:`RECORD_RANGES`); one InputError naming the
    photo and the tag."""
    try:
        number: Any = _number(value) if not isinstance(value, str) else float(value)
    except (TypeError, ValueError, ZeroDivisionError, OverflowError):
        number = value
    try:
        return check_number(number, tag, low, high)
    except FieldValueError as exc:
        raise input_error(source, str(exc)) from None


def _unknown_rational(value: Any) -> bool:
    """True for an EXIF rational that is not a finite number (0/0): a value
    unknown to its writer, not a corrupt one."""
    try:
        return value is not None and not math.isfinite(_number(value))
    except (TypeError, ValueError, ZeroDivisionError, OverflowError):
        return False  # not a number at all: refused where it is read


def _positive(value: Any) -> float | None:
    """An EXIF number that is finite and positive, else None."""
    try:
        number = _number(value) if value is not None else None
    except (TypeError, ValueError, ZeroDivisionError, OverflowError):
        return None
    return number if number is not None and math.isfinite(number) and number > 0 else None


def _gps_angle(gps: Mapping[str, Any], tag: str, default_ref: str, block_key: str, source
               ) -> float:
    """A GPS latitude or longitude in signed degrees, checked against its range."""
    low, high, _ = RECORD_RANGES["position"][block_key]
    degrees = gps_degrees(gps.get(tag), gps.get(f"{tag}Ref", default_ref))
    if degrees is None:
        raise input_error(source, f"field 'EXIF {tag}' must be three finite numbers (degrees, "
                                  f"minutes, seconds), got {gps.get(tag)!r:.60}")
    return _checked(degrees, f"EXIF {tag}", low, high, source)


def record_from_exif(photo, blocks=_BLOCKS) -> tuple[SensorRecord, list[str]]:
    """A sensor record from the photo's metadata, and where each block came from.

    Camera: EXIF focal length (see :meth:`Intrinsics.from_exif`; for a photo
    turned by its EXIF orientation the focal-plane resolution is the stored
    image's, so the camera is made at the stored size and turned with the
    pixels), marked ``estimated``: a nominal value the registration starts
    from and refines. Position: EXIF GPS latitude/longitude/altitude. Orientation: DJI
    XMP gimbal angles (drone photos), else EXIF ``GPSImgDirection`` for the
    trend only; its ``heading_reference`` says what the heading is from
    (``"true"``, or ``"magnetic"`` for ``GPSImgDirectionRef`` ``M``), for the
    prior to turn it to the model's grid north.

    Parameters
    ----------
    photo : Photo
        A photo as :func:`napari_imgreg.io.photos.load_photo` reads it.
    blocks : iterable of str
        The blocks to read (``"camera"``, ``"position"``, ``"orientation"``):
        those a sensor record lacks, so that a corrupt tag the record makes
        unnecessary does not refuse the photo.

    Returns
    -------
    record : SensorRecord
        Its ``source`` is the photo's path; blocks the metadata lack (or not
        asked for) are None.
    notes : list of str
        One per block found ("position from EXIF GPS", ...).

    Raises
    ------
    InputError
        A tag that fills an asked-for block is present but not a finite
        number in the range of the record field it becomes (a DJI gimbal
        pitch of 135°, a GPS latitude of 95°, a ``GPSImgDirection`` of NaN);
        the message names the photo and the tag.
    """
    exif = photo.exif or {}
    blocks = set(blocks)
    src = photo.path
    notes: list[str] = []
    record = SensorRecord(source=src)
    w, h = photo.size
    if "camera" in blocks:
        # EXIF sizes and focal-plane resolutions are those of the stored image.
        turns = EXIF_QUARTER_TURNS.get(exif_orientation(exif) or 1, 0)
        stored = (h, w) if turns % 2 else (w, h)
        try:
            # EXIF focal lengths are nominal (a lens's marked value, the 35 mm
            # equivalent rounded to a millimetre: 1–3 % off, several pixels at
            # the frame's edge): the registration refines it from there.
            record.camera = {**Intrinsics.from_exif(exif, *stored).rotated(turns).to_dict(),
                             "estimated": ["fx", "fy"]}
            notes.append("camera from EXIF focal length (nominal: refined by the registration)")
            zoom = _positive(exif.get("DigitalZoomRatio"))
            if zoom is not None and zoom > 1.01:
                # Phones differ: some fold the digital zoom into the 35 mm
                # equivalent, none into FocalLength; the registration's
                # estimate of the focal length settles it.
                notes.append(f"camera from EXIF may be {zoom:g}× too wide: EXIF "
                             f"DigitalZoomRatio {zoom:g} (a crop; not every phone counts it "
                             "in the focal length)")
        except ValueError:
            focal_mm = _positive(exif.get("FocalLength"))
            if focal_mm is not None:
                # Said, or the "no focal length" of the prior reads as a missing tag.
                notes.append(f"camera not from EXIF FocalLength {focal_mm:g} mm: no sensor "
                             "size for it (no FocalLengthIn35mmFilm, no "
                             "FocalPlaneXResolution, camera model "
                             f"{_text(exif.get('Model')) or 'absent'!r} not known)")
    gps = exif.get("GPSInfo")
    if not isinstance(gps, Mapping):  # an empty GPS IFD leaves its offset (an int)
        gps = {}
    if "position" in blocks and gps.get("GPSLatitude") is not None \
            and gps.get("GPSLongitude") is not None:
        lat = _gps_angle(gps, "GPSLatitude", "N", "lat", src)
        lon = _gps_angle(gps, "GPSLongitude", "E", "lon", src)
        record.position = {"lat": lat, "lon": lon}
        for tag, default in (("GPSLatitudeRef", "N"), ("GPSLongitudeRef", "E")):
            if _text(gps.get(tag)) is None:
                # A lost hemisphere puts the camera thousands of km away: said.
                notes.append(f"position from EXIF GPS: {tag} missing, taken as {default}")
        alt = gps.get("GPSAltitude")
        unknown_alt = _unknown_rational(alt)
        if alt is not None and not unknown_alt:
            alt = _checked(alt, "EXIF GPSAltitude", *RECORD_RANGES["position"]["alt"][:2], src)
            below = gps.get("GPSAltitudeRef") in (1, b"\x01")
            record.position["alt"] = -alt if below else alt
        # A 0/0 altitude is how some phones write "no vertical fix": the DEM gives it.
        notes.append("position from EXIF GPS" + (" (GPSAltitude unknown, 0/0: ignored)"
                                                 if unknown_alt else ""))
    if "orientation" not in blocks:
        return record, notes
    gimbal = dji_gimbal_angles(exif.get("XMP") or "", src)
    if gimbal is not None:
        trend, plunge, roll = attitude_from_dji_gimbal(*gimbal)
        # DJI's gimbal yaw is from true north (the aircraft's compass corrected).
        record.orientation = {"trend_deg": trend, "plunge_deg": plunge, "roll_deg": roll,
                              "heading_reference": "true"}
        notes.append("attitude from DJI gimbal angles (XMP)")
    elif _unknown_rational(gps.get("GPSImgDirection")):
        # 0/0: the phone had no compass reading. Refused (the trend is what a
        # prior cannot do without), saying how to give it.
        raise input_error(src, "field 'EXIF GPSImgDirection' must be a finite number, got 0/0 "
                               "(no compass reading): give 'orientation.trend_deg' in a sensor "
                               "record (.json beside the photo)")
    elif gps.get("GPSImgDirection") is not None:
        # EXIF says 0.00 to 359.99; writers that add a declination past a
        # full turn are wrapped. Beyond two turns the tag is corrupt.
        trend = _checked(gps["GPSImgDirection"], "EXIF GPSImgDirection",
                         *GPS_IMG_DIRECTION_RANGE, src)
        reference = gps_heading_reference(gps)
        # The prior turns a magnetic heading to true north where it knows the
        # place and the date (napari_imgreg.prior), and says so either way.
        record.orientation = {"trend_deg": trend % 360.0, "heading_reference": reference}
        notes.append("trend from EXIF GPSImgDirection"
                     + (" (magnetic north)" if reference == "magnetic" else ""))
    return record, notes


#: What a heading is measured from, as a sensor record's
#: ``orientation.heading_reference`` says (extension): ``"grid"`` the model's
#: +Y (a record's trend without the field), ``"true"`` true north,
#: ``"magnetic"`` magnetic north.
HEADING_REFERENCES = ("grid", "true", "magnetic")


def gps_heading_reference(gps: Mapping[str, Any]) -> str:
    """``"magnetic"`` for EXIF ``GPSImgDirectionRef`` ``M``, else ``"true"``
    (``T``, or the tag absent: EXIF's default)."""
    return "magnetic" if (_text(gps.get("GPSImgDirectionRef")) or "T").upper().startswith("M") \
        else "true"
