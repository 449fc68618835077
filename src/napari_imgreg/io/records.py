"""Sensor records (``PHOTO.json``, contract §3): read and validate.

A sensor record is what a phone logged for one photo: camera, position,
attitude, the expected errors of all three (``sigma``) and, as extensions,
the capture time and the sun. This module reads the file format only; the
camera and prior pose built from a record are :mod:`napari_imgreg.prior`'s,
the records made from EXIF/XMP :mod:`napari_imgreg.io.exif`'s.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any, Mapping

from .._deprecated import forward_moved_names
from ..camera import ESTIMABLE_FIELDS
from ..errors import input_error
from ..validate import MAX_IMAGE_SIDE_PX, FieldValueError, check_number

__all__ = [
    "Sigma",
    "SensorRecord",
    "read_json",
    "RECORD_RANGES",
    "IMAGE_FRAMES",
    "parse_sensor_record",
    "load_sensor_record",
]

#: Names that moved out of this module in 0.2 -> their new module.
_MOVED = {
    **dict.fromkeys(("Prior", "prior_from_record", "prior_for_photo", "load_camera_and_pose",
                     "_attach_sun"), "napari_imgreg.prior"),
    "DEFAULT_HEIGHT_ABOVE_GROUND_M": "napari_imgreg.geo",
    "record_from_exif": "napari_imgreg.io.exif",
    "_dms": "napari_imgreg.io.exif:gps_degrees",
}
__getattr__ = forward_moved_names(__name__, _MOVED)




@dataclass(frozen=True)
class Sigma:
    """Expected error of the prior (contract §3 ``sigma``).

    Attributes
    ----------
    position_m : float
        Horizontal position error, metres.
    altitude_m : float
        Vertical position error, metres.
    angles_deg : float
        Attitude error, degrees.
    """

    position_m: float = 5.0
    altitude_m: float = 10.0
    angles_deg: float = 5.0

    def to_dict(self) -> dict[str, float]:
        return {
            "position_m": self.position_m,
            "altitude_m": self.altitude_m,
            "angles_deg": self.angles_deg,
        }


@dataclass
class SensorRecord:
    """A parsed ``PHOTO.json``; every block is optional (None when absent).

    Attributes
    ----------
    camera : dict or None
        The ``camera`` block (pixels or millimetres). Without a focal length
        (``{"width", "height"}`` only) the focal length is unknown and
        estimated during registration. Its optional ``estimated`` (a list of
        camera field names, as RESULT.json writes it) marks values that are
        estimates: a block with ``fx`` and ``"estimated": ["fx", "fy"]`` (a
        registration's result saved as the next record) gives the start of
        another estimation, not a known focal length.
    position : dict or None
        ``{"x", "y"[, "z"]}`` local metres or ``{"lat", "lon"[, "alt"]}``.
    orientation : dict or None
        ``{"trend_deg", "plunge_deg", "roll_deg"}``.
    sigma : Sigma
        Expected prior errors (defaults when absent).
    source : Path or None
        The file it came from (for messages).
    time : str or None
        Extension: capture instant, ISO 8601 with its UTC offset
        (``"2024-08-03T07:21:10+01:00"``); overrides the EXIF time.
    sun : dict or None
        Extension: ``{"azimuth_deg", "elevation_deg"}`` of the sun at capture,
        azimuth clockwise from *true* north; overrides the time.
    image_frame : str or None
        Extension: ``"stored"`` when ``camera`` and ``orientation`` are those
        of the image as stored in the file (the sensor's, as a phone logs
        them), ``"shown"`` when they are of the photo with its EXIF
        orientation applied (as napari-imgreg saves a pose); None: decided
        from the camera block's size (see
        :func:`napari_imgreg.prior.prior_from_record`).
    """

    camera: dict | None = None
    position: dict | None = None
    orientation: dict | None = None
    sigma: Sigma = field(default_factory=Sigma)
    source: Path | None = None
    time: str | None = None
    sun: dict | None = None
    image_frame: str | None = None

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        if self.camera is not None:
            out["camera"] = dict(self.camera)
        if self.position is not None:
            out["position"] = dict(self.position)
        if self.orientation is not None:
            out["orientation"] = dict(self.orientation)
        out["sigma"] = self.sigma.to_dict()
        if self.time is not None:
            out["time"] = self.time
        if self.sun is not None:
            out["sun"] = dict(self.sun)
        if self.image_frame is not None:
            out["image_frame"] = self.image_frame
        return out

    @property
    def capture_datetime(self) -> datetime | None:
        """The ``time`` as an aware datetime; None when absent or without UTC offset."""
        return None if self.time is None else _aware_iso(self.time)


def read_json(path: str | os.PathLike) -> Any:
    """Read a JSON file; one clear :class:`InputError` when missing or invalid."""
    path = Path(path)
    if not path.exists():
        raise input_error(path, "no such file")
    if path.is_dir():
        raise input_error(path, "is a folder, not a JSON file")
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    except json.JSONDecodeError as exc:
        # Some of json's messages end in "at", meant to be followed by the place.
        problem = exc.msg.removesuffix(" at")
        raise input_error(path, f"invalid JSON at line {exc.lineno} column {exc.colno}: "
                                f"{problem}") from None
    except UnicodeDecodeError:
        # A photo, a GeoPackage or another binary file given for a JSON one.
        kind = f" ({path.suffix.lstrip('.').upper()})" if path.suffix else ""
        raise input_error(path, f"is not a JSON file: binary content{kind}, not text") from None
    except OSError as exc:
        raise input_error(path, f"cannot read ({exc.strerror or exc})") from None


#: The declared range of every number of a sensor record, by block and field:
#: ``(low, high, whole)``. Anything outside is a unit mix-up or a typo and is
#: refused with the file and the field named (docs/limits.md).
RECORD_RANGES: dict[str, dict[str, tuple[float, float, bool]]] = {
    "camera": {
        "width": (1, MAX_IMAGE_SIDE_PX, True),
        "height": (1, MAX_IMAGE_SIDE_PX, True),
        # Pixel focal lengths: their ratio to the image side is checked
        # when the camera is built (a view between 0.006° and 170°).
        "fx": (0.0, 1e9, False),
        "fy": (0.0, 1e9, False),
        "cx": (-1e9, 1e9, False),
        "cy": (-1e9, 1e9, False),
        "focal_length_mm": (0.0, 10_000.0, False),
        "sensor_width_mm": (0.0, 1_000.0, False),
        "sensor_height_mm": (0.0, 1_000.0, False),
        "focal_length_35mm": (0.0, 10_000.0, False),
    },
    "position": {
        "lat": (-90.0, 90.0, False),
        "lon": (-180.0, 360.0, False),
        "alt": (-12_000.0, 100_000.0, False),
        "x": (-1e8, 1e8, False),
        "y": (-1e8, 1e8, False),
        "z": (-1e8, 1e8, False),
    },
    "orientation": {
        "trend_deg": (-360.0, 360.0, False),
        "plunge_deg": (-90.0, 90.0, False),
        "roll_deg": (-360.0, 360.0, False),
    },
    "sigma": {
        "position_m": (0.0, 100_000.0, False),
        "altitude_m": (0.0, 100_000.0, False),
        "angles_deg": (0.0, 180.0, False),
    },
    "sun": {
        "azimuth_deg": (-360.0, 360.0, False),
        "elevation_deg": (-90.0, 90.0, False),
    },
}

#: The values of the record's ``image_frame`` (extension): the frame of its
#: camera and attitude, the image as stored in the file or as shown.
IMAGE_FRAMES = ("stored", "shown")

#: Fields whose value must be above (not at) the low end of the range.
_POSITIVE = {("camera", k) for k in ("fx", "fy", "focal_length_mm", "sensor_width_mm",
                                     "sensor_height_mm", "focal_length_35mm")}


def _number(block: Mapping, key: str, where: str, src: Path | None) -> float:
    """The block's number ``key``, finite and within :data:`RECORD_RANGES`."""
    low, high, whole = RECORD_RANGES.get(where, {}).get(key, (-math.inf, math.inf, False))
    try:
        return check_number(block.get(key), key, low, high, integer=whole,
                            low_open=(where, key) in _POSITIVE)
    except FieldValueError as exc:
        value = block.get(key)
        if (where, key) in _POSITIVE and isinstance(value, (int, float)) \
                and not isinstance(value, bool) and value <= 0:
            raise input_error(src, f"field '{where}.{key}' must be positive, got {value!r}") \
                from None
        raise input_error(src, exc.within(where)) from None


def parse_sensor_record(data: Any, source: str | os.PathLike | None = None) -> SensorRecord:
    """Validate a sensor-record dict (contract §3) into a :class:`SensorRecord`.

    Raises
    ------
    InputError
        A block is not an object, a field has the wrong type or lies outside
        its range (:data:`RECORD_RANGES`: a zero or negative focal length, a
        width of 10¹², a latitude of 95°, an integer of 2⁶³), the camera
        gives a width without a height, or ``image_frame`` is not one of
        :data:`IMAGE_FRAMES`; the message names the file and the field.
    """
    src = Path(source) if source is not None else None
    if not isinstance(data, dict):
        raise input_error(src, "a sensor record must be a JSON object")
    # Other files of a scene folder, given where a record belongs (--prior).
    if data.get("type") in ("FeatureCollection", "Feature"):
        raise input_error(src, "is GeoJSON (a drawing or projected lines), not a sensor record "
                               "(camera, position, orientation) or RESULT.json")
    if "crs" in data and "origin" in data:
        raise input_error(src, "is a georef.json, not a sensor record (camera, position, "
                               "orientation) or RESULT.json")
    blocks: dict[str, dict | None] = {}
    for key in ("camera", "position", "orientation", "sigma"):
        block = data.get(key)
        if block is not None and not isinstance(block, dict):
            raise input_error(src, f"field '{key}' must be an object")
        blocks[key] = block

    camera = blocks["camera"]
    if camera is not None:
        for key in ("width", "height"):
            if key in camera:
                _number(camera, key, "camera", src)
        if ("width" in camera) != ("height" in camera):
            given, missing = ("width", "height") if "width" in camera else ("height", "width")
            raise input_error(src, f"field 'camera.{missing}' is missing (the block gives "
                                   f"'{given}'; give both or neither)")
        for key in ("fx", "fy", "cx", "cy", "focal_length_mm", "sensor_width_mm",
                    "sensor_height_mm", "focal_length_35mm"):
            if camera.get(key) is not None:
                _number(camera, key, "camera", src)
        dist = camera.get("dist")
        if dist is not None:
            if not isinstance(dist, list):
                raise input_error(src, "field 'camera.dist' must be a list of numbers")
            if len(dist) > 5:
                raise input_error(src, f"field 'camera.dist' has {len(dist)} coefficients; "
                                       "only OpenCV's (k1, k2, p1, p2, k3) are supported")
            for k in dist:
                try:
                    check_number(k, "dist", -1000.0, 1000.0)
                except FieldValueError:
                    raise input_error(src, f"field 'camera.dist' must be finite numbers "
                                           f"within ±1000, got {dist!r}") from None
        estimated = camera.get("estimated")
        if estimated is not None and not (
                isinstance(estimated, list)
                and all(isinstance(e, str) and e in ESTIMABLE_FIELDS for e in estimated)):
            raise input_error(src, f"field 'camera.estimated' must be a list of camera field "
                                   f"names ({', '.join(ESTIMABLE_FIELDS)}), got "
                                   f"{_short(estimated)}")

    position = blocks["position"]
    if position is not None:
        if "lat" in position or "lon" in position:
            _number(position, "lat", "position", src)
            _number(position, "lon", "position", src)
            if position.get("alt") is not None:
                _number(position, "alt", "position", src)
        else:
            _number(position, "x", "position", src)
            _number(position, "y", "position", src)
            if position.get("z") is not None:
                _number(position, "z", "position", src)

    orientation = blocks["orientation"]
    if orientation is not None:
        for key in ("trend_deg", "plunge_deg", "roll_deg"):
            if orientation.get(key) is not None:
                _number(orientation, key, "orientation", src)

    sigma = Sigma()
    if blocks["sigma"] is not None:
        s = blocks["sigma"]
        sigma = Sigma(
            *(
                _number(s, key, "sigma", src) if s.get(key) is not None else default
                for key, default in (
                    ("position_m", sigma.position_m),
                    ("altitude_m", sigma.altitude_m),
                    ("angles_deg", sigma.angles_deg),
                )
            )
        )
    when = data.get("time")
    if when is not None:
        if not isinstance(when, str) or _aware_iso(when) is None:
            raise input_error(
                src, f"field 'time' must be an ISO 8601 time with its UTC offset "
                     f"(e.g. 2024-08-03T07:21:10+01:00), got {when!r}")
    sun = data.get("sun")
    if sun is not None:
        if not isinstance(sun, dict):
            raise input_error(src, "field 'sun' must be an object")
        _number(sun, "azimuth_deg", "sun", src)
        _number(sun, "elevation_deg", "sun", src)
    frame = data.get("image_frame")
    if frame is not None and frame not in IMAGE_FRAMES:
        raise input_error(src, f"field 'image_frame' must be one of "
                               f"{', '.join(repr(f) for f in IMAGE_FRAMES)}, got {_short(frame)}")
    return SensorRecord(camera, position, orientation, sigma, src, when, sun, frame)


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _aware_iso(text: str) -> datetime | None:
    """An ISO 8601 string with a UTC offset → aware datetime, else None."""
    try:
        when = datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    except ValueError:
        return None
    return when if when.tzinfo is not None else None


def load_sensor_record(path: str | os.PathLike) -> SensorRecord:
    """Read and validate ``PHOTO.json`` (contract §3)."""
    return parse_sensor_record(read_json(path), path)
