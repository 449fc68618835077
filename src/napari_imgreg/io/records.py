"""Sensor records (``PHOTO.json``, contract §3) and registration results (§4).

A sensor record is what a phone logged for one photo. :func:`prior_from_record`
turns it into a camera and a prior pose, filling gaps (altitude from the DEM,
intrinsics from a default) and saying what it assumed.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np

from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.errors import InputError, input_error

if TYPE_CHECKING:
    from napari_imgreg.geo import DEM, Georef

__all__ = [
    "DEFAULT_HEIGHT_ABOVE_GROUND_M",
    "Sigma",
    "SensorRecord",
    "Prior",
    "read_json",
    "load_sensor_record",
    "prior_from_record",
    "load_camera_and_pose",
]

DEFAULT_HEIGHT_ABOVE_GROUND_M = 1.6


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
        The ``camera`` block (pixels or millimetres).
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
    """

    camera: dict | None = None
    position: dict | None = None
    orientation: dict | None = None
    sigma: Sigma = field(default_factory=Sigma)
    source: Path | None = None
    time: str | None = None
    sun: dict | None = None

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
        return out


@dataclass
class Prior:
    """A camera and its prior pose, with what was assumed to build it.

    Attributes
    ----------
    intrinsics : Intrinsics
    pose : Pose
        ``cam_from_world`` of the prior.
    sigma : Sigma
    assumptions : list of str
        Plain-language notes ("altitude from DEM + 1.6 m", ...).
    sun : (3,) array or None
        Unit vector toward the sun at capture, local frame (None: unknown).
    sun_source : str
        How the sun was found ("EXIF time", "record time", "record sun", ...).
    """

    intrinsics: Intrinsics
    pose: Pose
    sigma: Sigma = field(default_factory=Sigma)
    assumptions: list[str] = field(default_factory=list)
    sun: np.ndarray | None = None
    sun_source: str = ""


def read_json(path: str | os.PathLike) -> Any:
    """Read a JSON file; one clear :class:`InputError` when missing or invalid."""
    path = Path(path)
    if not path.exists():
        raise input_error(path, "no such file")
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    except json.JSONDecodeError as exc:
        raise input_error(path, f"invalid JSON at line {exc.lineno}: {exc.msg}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise input_error(path, f"cannot read ({exc})") from None


def _number(block: Mapping, key: str, where: str, src: Path | None) -> float:
    value = block.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise input_error(src, f"field '{where}.{key}' must be a number, got {value!r}")
    return float(value)


def parse_sensor_record(data: Any, source: str | os.PathLike | None = None) -> SensorRecord:
    """Validate a sensor-record dict (contract §3) into a :class:`SensorRecord`.

    Raises
    ------
    InputError
        A block is not an object or a field has the wrong type; the message
        names the file and the field.
    """
    src = Path(source) if source is not None else None
    if not isinstance(data, dict):
        raise input_error(src, "a sensor record must be a JSON object")
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
        for key in ("fx", "fy", "cx", "cy", "focal_length_mm", "sensor_width_mm",
                    "sensor_height_mm", "focal_length_35mm"):
            if camera.get(key) is not None:
                _number(camera, key, "camera", src)
        if "dist" in camera and not (
            isinstance(camera["dist"], list)
            and all(isinstance(k, (int, float)) for k in camera["dist"])
        ):
            raise input_error(src, "field 'camera.dist' must be a list of numbers")

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
        plunge = orientation.get("plunge_deg")
        if plunge is not None and abs(plunge) > 90:
            raise input_error(src, f"field 'orientation.plunge_deg' must be in [-90, 90], got {plunge}")

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
        if abs(_number(sun, "elevation_deg", "sun", src)) > 90:
            raise input_error(src, "field 'sun.elevation_deg' must be in [-90, 90]")
    return SensorRecord(camera, position, orientation, sigma, src, when, sun)


def _aware_iso(text: str):
    """An ISO 8601 string with a UTC offset → aware datetime, else None."""
    from datetime import datetime

    try:
        when = datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    except ValueError:
        return None
    return when if when.tzinfo is not None else None


def load_sensor_record(path: str | os.PathLike) -> SensorRecord:
    """Read and validate ``PHOTO.json`` (contract §3)."""
    return parse_sensor_record(read_json(path), path)


def prior_from_record(
    record: SensorRecord,
    georef: Georef | None = None,
    dem: DEM | None = None,
    terrain_height=None,
    image_size: tuple[int, int] | None = None,
    height_above_ground_m: float = DEFAULT_HEIGHT_ABOVE_GROUND_M,
) -> Prior:
    """Camera and prior pose from a sensor record.

    Parameters
    ----------
    record : SensorRecord
    georef : Georef, optional
        Needed for geodetic positions and for DEM look-ups in CRS coordinates.
    dem : DEM, optional
        Gives the altitude when the record has none.
    terrain_height : callable, optional
        ``f(x, y) -> z`` in the local frame, used when there is no DEM (e.g.
        :meth:`Scene.terrain_height`).
    image_size : (width, height), optional
        The photo's size, used when the camera block has none.
    height_above_ground_m : float
        Camera height above the DEM surface.

    Returns
    -------
    Prior

    Raises
    ------
    InputError
        The record lacks what a pose needs (camera, position, orientation),
        or a geodetic position comes without a georeference.
    """
    src = record.source
    notes: list[str] = []
    intrinsics = _intrinsics_of(record, image_size, notes)

    if record.position is None:
        raise input_error(src, "no 'position' block (needs x, y[, z] or lat, lon[, alt])")
    pos = record.position
    if "lat" in pos:
        if georef is None:
            raise input_error(src, "geodetic position (lat/lon) needs a georef.json")
        xyz = np.asarray(
            georef.geodetic_to_local(float(pos["lat"]), float(pos["lon"]), pos.get("alt")),
            dtype=np.float64,
        ).reshape(3)
        x, y = float(xyz[0]), float(xyz[1])
        z = float(xyz[2]) if pos.get("alt") is not None else None
    else:
        x, y = float(pos["x"]), float(pos["y"])
        z = float(pos["z"]) if pos.get("z") is not None else None
    if z is None:
        if dem is not None:
            ox, oy, oz = (georef.origin if georef is not None else (0.0, 0.0, 0.0))
            try:
                ground = float(dem.height_at(x + ox, y + oy)) - oz
            except ValueError as exc:
                raise InputError(f"{src}: {exc}") from None
            notes.append(f"altitude from DEM + {height_above_ground_m:g} m")
        elif terrain_height is not None:
            ground = float(terrain_height(x, y))
            notes.append(f"altitude from the model surface + {height_above_ground_m:g} m")
        else:
            raise input_error(src, "no altitude in 'position' and no DEM to take it from")
        z = ground + height_above_ground_m

    o = record.orientation
    if o is None or o.get("trend_deg") is None:
        raise input_error(src, "no 'orientation.trend_deg' (compass heading) in the record")
    trend = float(o["trend_deg"])
    plunge = float(o.get("plunge_deg") or 0.0)
    roll = float(o.get("roll_deg") or 0.0)
    if o.get("plunge_deg") is None:
        notes.append("plunge assumed 0° (level camera)")
    if o.get("roll_deg") is None:
        notes.append("roll assumed 0°")
    pose = Pose.from_attitude(trend, plunge, roll, np.array([x, y, z]))
    return Prior(intrinsics, pose, record.sigma, notes)


def _intrinsics_of(
    record: SensorRecord, image_size: tuple[int, int] | None, notes: list[str]
) -> Intrinsics:
    cam = dict(record.camera or {})
    if image_size is not None:
        if "width" in cam and (int(cam["width"]), int(cam["height"])) != tuple(image_size):
            # The photo may have been resized after logging: scale the camera.
            notes.append(
                f"camera block is {cam['width']}×{cam['height']}, photo is "
                f"{image_size[0]}×{image_size[1]}: intrinsics scaled"
            )
            base = Intrinsics.from_dict(cam) if _has_focal(cam) else None
            if base is not None:
                return base.scaled(image_size[0] / base.width)
        cam.setdefault("width", image_size[0])
        cam.setdefault("height", image_size[1])
    if "width" not in cam or "height" not in cam:
        raise input_error(record.source, "no camera width/height in the record and no photo")
    if not _has_focal(cam):
        notes.append("no focal length: assumed a 65° horizontal field of view (phone camera)")
        return Intrinsics.from_fov(int(cam["width"]), int(cam["height"]), 65.0)
    try:
        return Intrinsics.from_dict(cam)
    except (KeyError, ValueError) as exc:
        raise input_error(record.source, f"field 'camera': {exc}") from None


def _has_focal(cam: Mapping) -> bool:
    return "fx" in cam or ("focal_length_mm" in cam and "sensor_width_mm" in cam) or (
        "focal_length_35mm" in cam
    )


def load_camera_and_pose(
    path: str | os.PathLike,
    georef: Georef | None = None,
    dem: DEM | None = None,
    terrain_height=None,
) -> tuple[Intrinsics, Pose, str, list[str]]:
    """Camera and pose from either a RESULT.json or a sensor record.

    Returns
    -------
    intrinsics, pose, kind, notes
        ``kind`` is ``"result"`` or ``"prior"``.
    """
    data = read_json(path)
    if isinstance(data, dict) and isinstance(data.get("pose"), dict) and "R" in data["pose"]:
        try:
            intr = Intrinsics.from_dict(data["camera"])
            pose = Pose.from_dict(data["pose"])
        except (KeyError, TypeError, ValueError) as exc:
            raise input_error(path, f"bad 'camera' or 'pose' in result ({exc})") from None
        R = pose.R
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6):
            raise input_error(path, "field 'pose.R' is not a rotation matrix")
        return intr, pose, "result", []
    record = parse_sensor_record(data, path)
    prior = prior_from_record(record, georef, dem, terrain_height)
    return prior.intrinsics, prior.pose, "prior", prior.assumptions


def _dms(value, ref) -> float | None:
    """EXIF degrees/minutes/seconds (+ N/S/E/W reference) to signed degrees."""
    try:
        d, m, sec = (float(v) for v in value)
    except (TypeError, ValueError):
        return None
    deg = d + m / 60.0 + sec / 3600.0
    if not math.isfinite(deg):
        return None
    return -deg if str(ref).strip().upper() in ("S", "W") else deg


def record_from_exif(photo) -> tuple[SensorRecord, list[str]]:
    """A sensor record from the photo's metadata, and where each block came from.

    Camera: EXIF focal length (see :meth:`Intrinsics.from_exif`). Position:
    EXIF GPS latitude/longitude/altitude. Orientation: DJI XMP gimbal angles
    (drone photos), else EXIF ``GPSImgDirection`` for the trend only.
    """
    from napari_imgreg.io.orientation_tables import attitude_from_dji_gimbal, dji_gimbal_angles

    exif = photo.exif or {}
    notes: list[str] = []
    record = SensorRecord(source=photo.path)
    w, h = photo.size
    try:
        record.camera = Intrinsics.from_exif(exif, w, h).to_dict()
        notes.append("camera from EXIF focal length")
    except ValueError:
        pass
    gps = exif.get("GPSInfo")
    if not isinstance(gps, Mapping):  # an empty GPS IFD leaves its offset (an int)
        gps = {}
    lat = _dms(gps.get("GPSLatitude"), gps.get("GPSLatitudeRef", "N"))
    lon = _dms(gps.get("GPSLongitude"), gps.get("GPSLongitudeRef", "E"))
    if lat is not None and lon is not None:
        record.position = {"lat": lat, "lon": lon}
        alt = gps.get("GPSAltitude")
        try:
            alt = float(alt) if alt is not None else None
        except (TypeError, ValueError):
            alt = None
        if alt is not None and math.isfinite(alt):
            below = gps.get("GPSAltitudeRef") in (1, b"\x01")
            record.position["alt"] = -alt if below else alt
        notes.append("position from EXIF GPS")
    gimbal = dji_gimbal_angles(exif.get("XMP") or "")
    if gimbal is not None:
        trend, plunge, roll = attitude_from_dji_gimbal(*gimbal)
        record.orientation = {"trend_deg": trend, "plunge_deg": plunge, "roll_deg": roll}
        notes.append("attitude from DJI gimbal angles (XMP)")
    elif gps.get("GPSImgDirection") is not None:
        try:
            record.orientation = {"trend_deg": float(gps["GPSImgDirection"]) % 360.0}
            notes.append("trend from EXIF GPSImgDirection")
            if str(gps.get("GPSImgDirectionRef", "T")).strip().upper().startswith("M"):
                notes.append("trend is a magnetic heading: declination not applied")
        except (TypeError, ValueError):
            pass
    return record, notes


def prior_for_photo(
    photo,
    scene=None,
    record_path: str | os.PathLike | None = None,
    height_above_ground_m: float = DEFAULT_HEIGHT_ABOVE_GROUND_M,
) -> Prior:
    """The prior of a photo: its sensor record, completed from its metadata.

    The sensor record (``record_path``, by default the ``.json`` beside the
    photo) wins; blocks it lacks come from EXIF/XMP (:func:`record_from_exif`),
    then from defaults. The prior's ``assumptions`` say which.

    Parameters
    ----------
    photo : Photo
    scene : Scene, optional
        Gives the georeference, the DEM and, without a DEM, the terrain.
    record_path : path-like, optional
        Sensor record; defaults to the photo's sidecar.

    Raises
    ------
    InputError
        Neither a record nor metadata gives a position and a heading.
    """
    record_path = Path(record_path) if record_path is not None else photo.sidecar
    from_exif, exif_notes = record_from_exif(photo)
    notes: list[str] = []
    if record_path is not None and record_path.exists():
        record = load_sensor_record(record_path)
        for block in ("camera", "position", "orientation"):
            if getattr(record, block) is None and getattr(from_exif, block) is not None:
                setattr(record, block, getattr(from_exif, block))
                notes += [n for n in exif_notes if n.split()[0] in _NOTE_WORDS[block]]
        if record.camera is not None and not _has_focal(record.camera) and from_exif.camera:
            record.camera = {**from_exif.camera, **{k: v for k, v in record.camera.items()
                                                    if k not in ("width", "height")}}
            notes.append("focal length from EXIF")
    else:
        if from_exif.position is None or from_exif.orientation is None:
            raise input_error(
                photo.path,
                "no sensor record (.json beside the photo) and no GPS position and "
                "compass heading in its EXIF/XMP",
            )
        record = from_exif
        notes += exif_notes
    prior = prior_from_record(
        record,
        georef=getattr(scene, "georef", None),
        dem=getattr(scene, "dem", None),
        terrain_height=getattr(scene, "terrain_height", None),
        image_size=photo.size,
        height_above_ground_m=height_above_ground_m,
    )
    prior.assumptions = notes + prior.assumptions
    _attach_sun(prior, record, photo, getattr(scene, "georef", None))
    return prior


def _attach_sun(prior: Prior, record: SensorRecord, photo, georef: Georef | None) -> None:
    """Give the prior the sun at capture: record ``sun``, else record ``time``, else EXIF."""
    from napari_imgreg.sun import sun_direction_local, sun_for_photo, sun_position, sun_vector_enu

    center = prior.pose.center
    if record.sun is not None:
        from napari_imgreg.sun import meridian_convergence_deg

        conv = 0.0 if georef is None else meridian_convergence_deg(georef, center)
        prior.sun = sun_vector_enu(record.sun["azimuth_deg"] - conv, record.sun["elevation_deg"])
        prior.sun_source = "sensor record sun"
        return
    if record.time is not None:
        if georef is None:
            prior.assumptions.append("capture time given but no georeference: sun unknown")
            return
        lat, lon, alt = georef.local_to_geodetic(center)
        sun = sun_position(_aware_iso(record.time), float(lat), float(lon),
                           float(alt) if math.isfinite(alt) else 0.0)
        prior.sun = sun_direction_local(sun, georef, center)
        prior.sun_source = f"sensor record time {record.time}"
        return
    direction, sun, sun_notes = sun_for_photo(photo.exif or {}, georef, center)
    if direction is None:
        # Not an assumption: the sun is simply not used (said where it matters).
        prior.sun_source = "unknown: " + "; ".join(sun_notes or ["no capture time"])
        return
    prior.sun = direction
    prior.sun_source = f"EXIF time {sun.when.isoformat()}"
    prior.assumptions += [f"sun: {n}" for n in sun_notes]


_NOTE_WORDS = {"camera": ("camera",), "position": ("position",),
               "orientation": ("attitude", "trend")}
