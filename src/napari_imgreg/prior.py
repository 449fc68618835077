"""The prior of a photo: a camera and a first pose, with what was assumed.

A sensor record (``PHOTO.json``, contract §3, read by
:mod:`napari_imgreg.io.records`) says what a phone logged for one photo; the
photo's EXIF/XMP (:mod:`napari_imgreg.io.exif`) may say more.
:func:`prior_from_record` turns a record into a camera and a prior pose,
filling gaps (altitude from the DEM, intrinsics from a default) and saying
what it assumed; :func:`prior_for_photo` does so for a photo, completing its
record from the metadata and adding the sun at capture
(:mod:`napari_imgreg.solar`). The prior is the registration's input.

This module is backend only: no Qt or napari imports.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, replace
from datetime import date
from pathlib import Path
from typing import Mapping

import numpy as np

from ._atomic import atomic_write
from ._json import dump as strict_json_dump
from .camera import Intrinsics, Pose
from .errors import InputError, input_error
from .geo import (
    DEFAULT_HEIGHT_ABOVE_GROUND_M,
    DEM,
    GeoError,
    Georef,
    magnetic_declination,
    site_latitude_longitude,
)
from .io.exif import (
    EXIF_MIRRORED,
    EXIF_QUARTER_TURNS,
    HEADING_REFERENCES,
    capture_date,
    exif_orientation,
    record_from_exif,
)
from .io.records import (
    SensorRecord,
    Sigma,
    load_sensor_record,
    parse_sensor_record,
    read_json,
)
from .solar import meridian_convergence_deg, sun_for_photo, sun_from_record
from .validate import FieldValueError

__all__ = [
    "DEFAULT_HEIGHT_ABOVE_GROUND_M",
    "Prior",
    "prior_from_record",
    "prior_for_photo",
    "load_camera_and_pose",
    "check_photo_size",
    "save_pose_to_record",
]


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


def prior_from_record(
    record: SensorRecord,
    georef: Georef | None = None,
    dem: DEM | None = None,
    terrain_height=None,
    image_size: tuple[int, int] | None = None,
    height_above_ground_m: float = DEFAULT_HEIGHT_ABOVE_GROUND_M,
    exif_orientation: int | None = None,
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
    exif_orientation : int, optional
        The photo's EXIF ``Orientation`` (its pixels already turned by it).
        A camera block of the photo's size turned by 90° is the sensor's: with
        orientation 6 or 8 the camera and its attitude are turned as the
        pixels were (a portrait phone photo with its landscape record);
        without, the record is refused with a line that says how to fix it.
        With orientation 3 (a photo taken upside down, turned 180° for
        display) the record is the sensor's unless its ``image_frame`` is
        ``"shown"``: camera and attitude are turned by 180°. The record's
        ``image_frame`` (``"stored"`` / ``"shown"``) overrides the guess for
        the attitude. Without ``image_frame`` and without a camera size of
        its own, the record's roll decides: a phone chooses the orientation
        that shows the photo within 45° of level, so a roll level only once
        turned is the sensor's (not for views steeper than 60°). A roll the
        record does not give is taken as 0 for the photo as shown (never
        turned). A mirrored orientation (2, 4, 5, 7)
        is refused: a mirror image has no camera pose.

    Returns
    -------
    Prior

    Raises
    ------
    InputError
        The record lacks what a pose needs (camera, position, orientation),
        a geodetic position comes without a georeference, or the photo's EXIF
        orientation mirrors it.
    """
    src = record.source
    if exif_orientation in EXIF_MIRRORED:
        raise _mirrored_error(src, exif_orientation)
    notes: list[str] = []
    if record.image_frame is None and not _has_size(record.camera):
        frame = _frame_from_roll(record, exif_orientation, notes)
        if frame is not None:
            record = replace(record, image_frame=frame)
    intrinsics, camera_turns = _intrinsics_of(record, image_size, notes, exif_orientation)
    _check_field_of_view(intrinsics, src)
    # A heading from true or magnetic north becomes one from +Y (prior_for_photo
    # has done so already, with the photo's EXIF date at hand).
    record = _heading_to_grid_north(record, georef, notes)

    if record.position is None:
        raise input_error(src, "no 'position' block (needs x, y[, z] or lat, lon[, alt])")
    pos = record.position
    if "lat" in pos:
        if georef is None:
            raise input_error(src, "geodetic position (lat/lon) needs a georef.json")
        try:
            xyz = np.asarray(
                georef.geodetic_to_local(float(pos["lat"]), float(pos["lon"]), pos.get("alt")),
                dtype=np.float64,
            ).reshape(3)
        except (ValueError, TypeError, OverflowError) as exc:  # GeoError, pyproj's
            raise input_error(src, f"field 'position' (lat {pos.get('lat')}, lon "
                                   f"{pos.get('lon')}): {exc}") from None
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
            except ValueError as exc:  # outside the DEM, or on its nodata
                raise InputError(f"{src}: no altitude in 'position' and none from the DEM "
                                 f"({exc}); give the camera's 'z' (or 'alt' with lat/lon)"
                                 ) from None
            notes.append(f"altitude from DEM + {height_above_ground_m:g} m")
        elif terrain_height is not None:
            try:
                ground = float(terrain_height(x, y))
            except InputError as exc:
                # The model is not under the camera: the record's position is
                # what to check (swapped lat/lon, another photo's record).
                raise input_error(src, f"no altitude in 'position' and the model is not under "
                                       f"the camera at ({x:.1f}, {y:.1f}) m ({exc}): is the "
                                       "position right? Give the camera's 'z' (or 'alt'), or "
                                       "a DEM") from None
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
        notes.append("roll assumed 0°" + (" (level photo as shown)" if exif_orientation in
                                          (3, 6, 8) else ""))
    pose = Pose.from_attitude(trend, plunge, roll, np.array([x, y, z]))
    turns = _attitude_turns(record, exif_orientation, camera_turns, notes)
    if turns:  # the record's attitude is the sensor's: turn it with the pixels
        pose = pose.rotated(turns)
    return Prior(intrinsics, pose, record.sigma, notes)


# Kept under their old names for callers of 0.2.
_EXIF_TURNS = EXIF_QUARTER_TURNS
_EXIF_MIRRORED = EXIF_MIRRORED


def _mirrored_error(path, orientation: int) -> InputError:
    """One line: a mirrored EXIF orientation, and how to get a photo that registers."""
    return input_error(
        path, f"the photo's EXIF orientation {orientation} mirrors it (a front camera or an "
              "editor's flip) and a mirror image has no camera pose; save the photo as the "
              "camera took it, unmirrored (e.g. `exiftool -n -Orientation=1 PHOTO` when its "
              "stored pixels are unmirrored, else flip it back in an image editor), and "
              "register again")


def _attitude_turns(record: SensorRecord, exif_orientation: int | None, camera_turns: int,
                    notes: list[str]) -> int:
    """The quarter turns the record's attitude needs to be that of the photo as shown.

    The attitude is the sensor's (turned with the pixels) when the record
    says so (``image_frame: "stored"``) or, without ``image_frame``, when its
    camera block was found to be the sensor's (``camera_turns``, from the
    block's size or, for orientation 3, by default). A roll the record does
    not give is the shown photo's (0: level), so nothing is turned then.
    """
    turns = EXIF_QUARTER_TURNS.get(exif_orientation or 1, 0)
    if not turns or exif_orientation in EXIF_MIRRORED:
        return 0
    frame = record.image_frame or ("stored" if camera_turns else "shown")
    if frame == "shown":
        if camera_turns:
            notes.append("attitude is of the photo as shown (record image_frame \"shown\"): "
                         "not turned")
        return 0
    if (record.orientation or {}).get("roll_deg") is None:
        return 0
    notes.append(f"attitude is the sensor's: turned {90 * turns:+d}° with the pixels (EXIF "
                 f"orientation {exif_orientation}; write \"image_frame\": \"shown\" in the "
                 "record if it is of the photo as shown)")
    return turns


#: The largest tilt, degrees, of a photo as shown by the EXIF orientation a
#: phone chose: it picks the quarter turn that shows the photo nearest to
#: level (the edge of the screen closest to up), so within 45° of it.
_SHOWN_ROLL_LIMIT_DEG = 45.0
#: Steeper than this, degrees, the view is too near vertical for the phone's
#: choice of orientation (and the roll) to say which way is up.
_STEEP_PLUNGE_DEG = 60.0


def _frame_from_roll(record: SensorRecord, exif_orientation: int | None,
                     notes: list[str]) -> str | None:
    """The frame of a record's roll from its value, when nothing else says it.

    A record with a roll but no ``image_frame`` and no camera size of its own
    (no block, or one without width and height: the photo's or the EXIF's
    size is used, which is the shown photo's) gives no clue whether the roll
    is the sensor's (as a phone logs it) or of the photo as shown. A phone
    chooses the EXIF orientation 3, 6 or 8 so that the shown photo is within
    45° of level: a roll that is level only once turned with the pixels is
    the sensor's. Returns ``"stored"``, ``"shown"`` or None (undecided: no
    turning orientation, no roll, a near-vertical view, or a tilt that fits
    neither), with a note for a sensor's roll.
    """
    turns = EXIF_QUARTER_TURNS.get(exif_orientation or 1, 0)
    o = record.orientation or {}
    if not turns or exif_orientation in EXIF_MIRRORED or o.get("roll_deg") is None:
        return None
    if abs(float(o.get("plunge_deg") or 0.0)) > _STEEP_PLUNGE_DEG:
        return None
    roll = float(o["roll_deg"])

    def tilt(angle: float) -> float:  # distance from level, degrees in [0, 180]
        return abs((angle + 180.0) % 360.0 - 180.0)

    as_shown, turned = tilt(roll), tilt(roll - 90.0 * turns)
    if as_shown <= _SHOWN_ROLL_LIMIT_DEG < turned:
        return "shown"
    if turned <= _SHOWN_ROLL_LIMIT_DEG < as_shown:
        notes.append(f"the record's roll {roll:g}° is the sensor's: the photo as shown (EXIF "
                     f"orientation {exif_orientation}, chosen by the phone within 45° of level) "
                     f"would be tilted {as_shown:g}°")
        return "stored"
    return None


def _has_size(camera: Mapping | None) -> bool:
    """True when a record's camera block gives its own width and height."""
    return camera is not None and "width" in camera and "height" in camera


def _camera_from_block(cam: Mapping, source) -> Intrinsics:
    """The camera of a record's block; one InputError naming the file and field."""
    try:
        return Intrinsics.from_dict(cam)
    except FieldValueError as exc:
        raise input_error(source, exc.within("camera")) from None
    except (KeyError, TypeError, ValueError) as exc:
        raise input_error(source, f"field 'camera': {exc}") from None


def _intrinsics_of(
    record: SensorRecord,
    image_size: tuple[int, int] | None,
    notes: list[str],
    exif_orientation: int | None = None,
) -> tuple[Intrinsics, int]:
    """The record's camera for the photo, and the quarter turns it was given.

    A camera block of the photo's size turned by 90° is the sensor's (a phone
    photo stored landscape and shown portrait through its EXIF orientation);
    so is, with orientation 3 (shown turned 180°: same size), any block of
    a record whose ``image_frame`` is not ``"shown"``. That camera is turned
    as the pixels were.
    """
    src = record.source
    cam = dict(record.camera or {})
    turns = 0
    if image_size is not None:
        photo = (int(image_size[0]), int(image_size[1]))
        block = (int(cam["width"]), int(cam["height"])) if "width" in cam and "height" in cam \
            else None
        if block is not None and block != photo and _swapped_aspect(block, photo):
            turns = _turns_for_portrait(block, photo, exif_orientation, src)
        elif exif_orientation == 3 and record.image_frame != "shown":
            turns = 2
        if turns:
            sensor = block or photo  # turned by 180°, the photo's size is the sensor's
            cam["width"], cam["height"] = sensor
            base = (_camera_from_block(cam, src) if _has_focal(cam) else
                    _assumed_camera(sensor[0], sensor[1]))
            if not _has_focal(cam):
                notes.append("no focal length: assumed a 65° horizontal field of view of the "
                              f"sensor (phone camera) as the start; {_ESTIMATED_NOTE}")
            turned = base.rotated(turns)
            notes.append(
                f"camera is the sensor's {base.width}×{base.height}; the photo is shown "
                f"{photo[0]}×{photo[1]} (EXIF orientation {exif_orientation}): camera turned "
                f"{90 * turns:+d}° with the pixels")
            if (turned.width, turned.height) != photo:
                notes.append(f"photo is {photo[0]}×{photo[1]}: intrinsics scaled")
                turned = turned.scaled(photo[0] / turned.width)
            return turned, turns
        if block is not None and block != photo:
            # The photo may have been resized after logging: scale the camera.
            notes.append(
                f"camera block is {cam['width']}×{cam['height']}, photo is "
                f"{photo[0]}×{photo[1]}: intrinsics scaled"
            )
            if _has_focal(cam):
                return _camera_from_block(cam, src).scaled(photo[0] / int(cam["width"])), 0
            cam["width"], cam["height"] = photo
        cam.setdefault("width", photo[0])
        cam.setdefault("height", photo[1])
    if "width" not in cam or "height" not in cam:
        raise input_error(src, "no camera width/height in the record and no photo")
    if not _has_focal(cam):
        notes.append("no focal length: assumed a 65° horizontal field of view (phone camera) "
                     f"as the start; {_ESTIMATED_NOTE}")
        return _assumed_camera(int(cam["width"]), int(cam["height"])), 0
    return _camera_from_block(cam, src), 0


#: Horizontal fields of view, degrees, beyond any camera a pinhole model with
#: distortion describes (a 50× zoom sees ~1.5°, a phone's ultra-wide ~120°):
#: outside them the record's camera mixes units (``focal_length_mm`` 4250 for
#: 4.25, ``sensor_width_mm`` in metres), which gave a 0.08° view unsaid.
FIELD_OF_VIEW_RANGE_DEG = (0.5, 175.0)


def _check_field_of_view(intrinsics: Intrinsics, source) -> None:
    """Refuse a camera whose field of view no camera has (one line naming the file)."""
    hfov = math.degrees(2.0 * math.atan2(intrinsics.width / 2.0, intrinsics.fx))
    low, high = FIELD_OF_VIEW_RANGE_DEG
    if not low <= hfov <= high:
        raise input_error(
            source, f"field 'camera': a horizontal field of view of {hfov:.3g}° (fx "
                    f"{intrinsics.fx:.4g} px for {intrinsics.width} px): no camera sees "
                    f"{'so little' if hfov < low else 'so much'}; check the units "
                    "(focal_length_mm and sensor_width_mm in millimetres, fx in pixels)")


#: The field of view assumed for a camera without a focal length (a phone's).
ASSUMED_HFOV_DEG = 65.0
_ESTIMATED_NOTE = ("the focal length is estimated during registration (RESULT.json "
                   "camera.estimated)")


def _assumed_camera(width: int, height: int) -> Intrinsics:
    """A camera without a known focal length: :data:`ASSUMED_HFOV_DEG`, its
    focal length marked unknown (``estimated``), so the registration
    estimates it and starts from this one."""
    return replace(Intrinsics.from_fov(width, height, ASSUMED_HFOV_DEG),
                   estimated=("fx", "fy"))


def _swapped_aspect(block: tuple[int, int], photo: tuple[int, int]) -> bool:
    """True when the photo is the block turned by 90° (maybe resized): one is
    portrait, the other landscape, with the same aspect ratio to 1 %."""
    (bw, bh), (pw, ph) = block, photo
    if (bw > bh) == (pw > ph) or bw == bh:
        return False
    return abs((bw / bh) / (ph / pw) - 1.0) < 0.01


def _turns_for_portrait(block, photo, exif_orientation, src) -> int:
    """Quarter turns from the EXIF orientation, or one InputError that says how to fix it."""
    if exif_orientation in (6, 8):
        return EXIF_QUARTER_TURNS[exif_orientation]
    shape = "portrait" if photo[1] > photo[0] else "landscape"
    if exif_orientation in EXIF_MIRRORED:
        raise _mirrored_error(src, exif_orientation)
    raise input_error(
        src, f"field 'camera' is {block[0]}×{block[1]} but the photo is {photo[0]}×{photo[1]} "
             f"({shape}) and its EXIF orientation does not turn it (tag "
             f"{exif_orientation if exif_orientation is not None else 'absent'}); give the "
             f"camera of the photo as shown: width {photo[0]}, height {photo[1]}, fx and fy "
             "exchanged, cx and cy exchanged (or drop the camera block)")


def _has_focal(cam: Mapping) -> bool:
    return "fx" in cam or ("focal_length_mm" in cam and "sensor_width_mm" in cam) or (
        "focal_length_35mm" in cam
    )


def load_camera_and_pose(
    path: str | os.PathLike,
    georef: Georef | None = None,
    dem: DEM | None = None,
    terrain_height=None,
    model_bounds=None,
) -> tuple[Intrinsics, Pose, str, list[str]]:
    """Camera and pose from either a RESULT.json or a sensor record.

    ``model_bounds`` (the scene's ``bounds``), given: a record whose
    ``position.x, y`` are the georeference's map coordinates is refused
    (:func:`_refuse_misplaced_position`).

    Returns
    -------
    intrinsics, pose, kind, notes
        ``kind`` is ``"result"`` or ``"prior"``.
    """
    data = read_json(path)
    if isinstance(data, dict) and isinstance(data.get("pose"), dict) and "R" in data["pose"]:
        # A NaN translation or fx 0 would otherwise give renders and
        # projections of nothing (exit 0 with an empty file).
        if not isinstance(data.get("camera"), dict):
            raise input_error(path, "field 'camera' of the result must be an object")
        try:
            intr = Intrinsics.from_dict(data["camera"])
        except FieldValueError as exc:
            raise input_error(path, exc.within("camera")) from None
        except (KeyError, TypeError, ValueError) as exc:
            raise input_error(path, f"bad 'camera' in result ({exc})") from None
        try:
            pose = Pose.from_dict(data["pose"])
        except FieldValueError as exc:
            raise input_error(path, exc.within("pose")) from None
        except (KeyError, TypeError, ValueError) as exc:
            raise input_error(path, f"bad 'pose' in result ({exc})") from None
        R = pose.R
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6):
            raise input_error(path, "field 'pose.R' is not a rotation matrix")
        return intr, pose, "result", []
    record = parse_sensor_record(data, path)
    _refuse_misplaced_position(record, path, georef, model_bounds)
    prior = prior_from_record(record, georef, dem, terrain_height)
    return prior.intrinsics, prior.pose, "prior", prior.assumptions


def save_pose_to_record(
    path: str | os.PathLike, pose: Pose, camera: Intrinsics | None = None
) -> dict:
    """Write a pose into a sensor record (``PHOTO.json``) atomically: the next prior.

    The record's ``position`` becomes the local ``{"x", "y", "z"}`` of the
    camera centre and its ``orientation`` the pose's trend, plunge and roll
    (contract §3) and ``image_frame`` becomes ``"shown"`` (the pose is that of
    the photo as shown, its EXIF orientation applied, and is not turned when
    read back); every other field (``sigma``, unknown extras) is kept. A
    missing file is created. With ``camera``, the ``camera`` block is
    replaced by its pixel form (a solved focal length).

    Parameters
    ----------
    path : path-like
        The sidecar JSON beside the photo.
    pose : Pose
    camera : Intrinsics, optional

    Returns
    -------
    dict
        What was written.

    Raises
    ------
    InputError
        The existing file is not a JSON object.
    """
    path = Path(path)
    data: dict = {}
    if path.exists():
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise input_error(path, f"cannot read the sensor record ({exc})") from None
        if not isinstance(data, dict):
            raise input_error(path, "a sensor record must be a JSON object")
    trend, plunge, roll = pose.attitude
    x, y, z = (float(v) for v in pose.center)
    data["position"] = {"x": x, "y": y, "z": z}
    data["orientation"] = {"trend_deg": trend, "plunge_deg": plunge, "roll_deg": roll}
    # The pose is of the photo as shown (EXIF orientation applied): the next
    # prior must not turn it again as it turns a phone's sensor record.
    data["image_frame"] = "shown"
    if camera is not None:
        data["camera"] = camera.to_dict()
    with atomic_write(path, encoding="utf-8") as fh:
        strict_json_dump(data, fh, indent=1)
        fh.write("\n")
    return data


def prior_for_photo(
    photo,
    scene=None,
    record_path: str | os.PathLike | None = None,
    height_above_ground_m: float = DEFAULT_HEIGHT_ABOVE_GROUND_M,
) -> Prior:
    """The prior of a photo: its sensor record, completed from its metadata.

    The sensor record (``record_path``, by default the ``.json`` beside the
    photo) wins; blocks it lacks come from EXIF/XMP (:func:`record_from_exif`),
    then from defaults. The prior's ``assumptions`` say which. A heading from
    the metadata (true north) is turned to the georeference's grid north;
    a phone's (not a drone's) EXIF GPS altitude gives way to the DEM where
    the DEM covers the camera (the method's altitude).

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
        Neither a record nor metadata gives a position and a heading; a
        metadata tag that fills a block the record lacks is out of its range
        (:func:`~napari_imgreg.io.exif.record_from_exif`); the photo's EXIF
        orientation mirrors it (2, 4, 5, 7: no camera pose exists for a
        mirror image); or the record is refused by :func:`prior_from_record`.
    """
    given = record_path is not None
    record_path = Path(record_path) if given else photo.sidecar
    if given and not record_path.exists():
        # A misspelt record must not quietly give way to the EXIF (another prior).
        raise input_error(record_path, "no such file (the sensor record given for the photo)")
    orientation = _exif_orientation(photo)
    if orientation in EXIF_MIRRORED:
        raise _mirrored_error(photo.path, orientation)
    if given and _is_result(read_json(record_path)):
        return _prior_from_result(record_path, photo, scene)
    notes: list[str] = []
    if record_path is not None and record_path.exists():
        record = load_sensor_record(record_path)
        if record.image_frame is None and not _has_size(record.camera):
            # Decided before the EXIF camera (of the shown photo's size) fills the block.
            record.image_frame = _frame_from_roll(record, orientation, notes)
        # Only what the record lacks is read from the metadata: a corrupt tag
        # the record makes unnecessary does not refuse the photo.
        wanted = [block for block in ("camera", "position", "orientation")
                  if getattr(record, block) is None]
        if record.camera is not None and not _has_focal(record.camera):
            wanted.append("camera")
        from_exif, exif_notes = record_from_exif(photo, blocks=wanted)
        from_metadata = set()
        for block in ("camera", "position", "orientation"):
            if getattr(record, block) is None and getattr(from_exif, block) is not None:
                setattr(record, block, getattr(from_exif, block))
                from_metadata.add(block)
                notes += [n for n in exif_notes if n.split()[0] in _NOTE_WORDS[block]]
        if record.camera is not None and not _has_focal(record.camera) and from_exif.camera:
            record.camera = _with_exif_focal(record.camera, from_exif.camera, orientation)
            notes.append("focal length from EXIF")
    else:
        from_exif, exif_notes = record_from_exif(photo)
        if from_exif.position is None or from_exif.orientation is None:
            lacking = " and ".join(what for what, block in (
                ("GPS position", from_exif.position), ("compass heading", from_exif.orientation))
                if block is None)
            raise input_error(
                photo.path,
                f"no sensor record (.json beside the photo) and no {lacking} in its EXIF/XMP",
            )
        record = from_exif
        notes += exif_notes
        from_metadata = {"camera", "position", "orientation"}
    georef = getattr(scene, "georef", None)
    # A metadata heading says what it is from (true or magnetic north); a
    # record's own may (orientation.heading_reference). The photo's EXIF date
    # dates a magnetic one when the record gives no time.
    record = _heading_to_grid_north(record, georef, notes,
                                    exif_date=capture_date(getattr(photo, "exif", None) or {}))
    if "position" in from_metadata and not _is_drone_photo(photo):
        _phone_altitude_from_dem(record, georef, getattr(scene, "dem", None),
                                 height_above_ground_m, notes)
    if "position" not in from_metadata:
        _refuse_misplaced_position(record, record_path, georef, getattr(scene, "bounds", None))
    prior = prior_from_record(
        record,
        georef=georef,
        dem=getattr(scene, "dem", None),
        terrain_height=getattr(scene, "terrain_height", None),
        image_size=photo.size,
        height_above_ground_m=height_above_ground_m,
        exif_orientation=orientation,
    )
    prior.assumptions = notes + prior.assumptions
    _say_if_far_from_the_model(prior, scene)
    _attach_sun(prior, record, photo, getattr(scene, "georef", None))
    return prior


#: A camera farther than this from the model, metres (and than ten times
#: the model's width), sees it as a speck: its position is almost surely wrong.
_FAR_FROM_MODEL_M = 10_000.0


def _model_xy_bounds(bounds) -> tuple[np.ndarray, np.ndarray] | None:
    """The horizontal part (low, high corners) of a model's ``bounds``, or None without a model."""
    try:
        low, high = (np.asarray(corner, np.float64)[:2] for corner in bounds)
    except (TypeError, ValueError):  # no model (a scene stand-in)
        return None
    return low, high


def _distance_to_box(xy: np.ndarray, low: np.ndarray, high: np.ndarray) -> float:
    return float(np.linalg.norm(xy - np.clip(xy, low, high)))


def _refuse_misplaced_position(record: SensorRecord, record_path,
                               georef: Georef | None, bounds) -> None:
    """Refuse a record whose position is the right place written the wrong way:
    ``position.x, y`` that are the georeference's map coordinates (easting,
    northing) rather than the model frame's, or ``lat`` and ``lon`` swapped.

    Common slips when a record is written from a GNSS log: the camera then
    lies thousands of kilometres from the model, and the registration would
    search in vain. Refused only when the corrected position (minus
    georef.json's origin; lat and lon exchanged) lies near the model, so the
    diagnosis is sure; other far cameras get
    :func:`_say_if_far_from_the_model`'s note.

    Raises
    ------
    InputError
        ``"<record>: position x,y (578979.2, 5911918.5) are map coordinates ..."``,
        ``"<record>: position lat -1.81, lon 53.35 look swapped ..."``.
    """
    box = _model_xy_bounds(bounds)
    pos = record.position or {}
    if georef is None or box is None:
        return
    low, high = box
    near = max(_FAR_FROM_MODEL_M, 10.0 * float(np.linalg.norm(high - low)))

    def far(xy) -> float:
        return _distance_to_box(np.asarray(xy, np.float64), low, high)

    problem = None
    try:
        if "x" in pos:
            xy = np.array([float(pos["x"]), float(pos["y"])])
            shifted = xy - georef.origin[:2]
            if far(xy) > near and far(shifted) <= near:
                problem = (
                    f"position x,y ({xy[0]:.1f}, {xy[1]:.1f}) are map coordinates of "
                    f"{georef.crs}, {far(xy) / 1000.0:,.0f} km from the model: x,y,z are "
                    "model-frame metres, the map coordinates minus georef.json's origin "
                    f"(here ({shifted[0]:.1f}, {shifted[1]:.1f})); or give lat,lon")
        elif "lat" in pos:
            lat, lon = float(pos["lat"]), float(pos["lon"])
            if abs(lon) <= 90:  # else it cannot be a latitude: not swapped
                given = georef.geodetic_to_local(lat, lon)[:2]
                swapped = georef.geodetic_to_local(lon, lat)[:2]
                if far(given) > near and far(swapped) <= near:
                    problem = (
                        f"position lat {lat:g}, lon {lon:g} look swapped: read that way the "
                        f"camera is {far(given) / 1000.0:,.0f} km from the model, and at lat "
                        f"{lon:g}, lon {lat:g} it is at the model")
    except (KeyError, TypeError, ValueError, OverflowError):
        return  # refused by the record's own checks, with the field named
    if problem:
        raise input_error(record_path, problem)


def _say_if_far_from_the_model(prior: Prior, scene) -> None:
    """Add a note when the prior's camera is kilometres away from the model.

    A lost hemisphere (``GPSLatitudeRef``), a CRS of the other hemisphere's
    UTM zone or another photo's record put the camera hundreds of kilometres
    away; the registration then fails for no reason its hints could name.
    """
    box = _model_xy_bounds(getattr(scene, "bounds", None))
    if box is None:
        return
    low, high = box
    distance = _distance_to_box(prior.pose.center[:2], low, high)
    if distance > max(_FAR_FROM_MODEL_M, 10.0 * float(np.linalg.norm(high - low))):
        prior.assumptions.append(
            f"camera is {distance / 1000.0:,.0f} km from the model: its position is likely "
            "wrong (a GPS hemisphere reference, georef.json's CRS, or another photo's record)")


def _local_xy(record: SensorRecord, georef: Georef | None) -> tuple[float, float] | None:
    """The record's horizontal position in the local frame, metres (None: unknown)."""
    pos = record.position or {}
    try:
        if "lat" in pos:
            if georef is None:
                return None
            x, y, _ = georef.geodetic_to_local(float(pos["lat"]), float(pos["lon"]))
            return float(x), float(y)
        return float(pos["x"]), float(pos["y"])
    except (KeyError, TypeError, ValueError, OverflowError):  # refused later, with the file
        return None


def _heading_to_grid_north(record: SensorRecord, georef: Georef | None, notes: list[str],
                           exif_date: date | None = None) -> SensorRecord:
    """The record with its heading turned to the model's grid north (+Y).

    ``orientation.heading_reference`` says what the trend is measured from
    (:data:`~napari_imgreg.io.exif.HEADING_REFERENCES`): a metadata heading
    is from true north (EXIF ``GPSImgDirectionRef`` ``T``, a DJI gimbal yaw)
    or magnetic north (``M``); a record's trend without the field is from +Y
    and is used as given. The field is consumed: the record returned has
    none, so a second call leaves it as it is.

    Magnetic to true: plus the World Magnetic Model's declination at the
    camera on the capture date (:func:`~napari_imgreg.geo.magnetic_declination`),
    which needs the camera's latitude and longitude and a date (the record's
    ``time``, else ``exif_date``); without them the heading is used as if
    from true north, and a note says why. True to grid: minus the meridian
    convergence at the camera (up to ~3° at the edge of a UTM zone at
    mid-latitudes, more further north). Declination first, as it belongs to
    the place's true north: grid = magnetic + declination − convergence.

    Parameters
    ----------
    record : SensorRecord
    georef : Georef or None
        The model's georeference (no convergence without it).
    notes : list of str
        Gets one note per turn made (or not made).
    exif_date : datetime.date, optional
        The photo's EXIF capture day, for a record without ``time``.

    Returns
    -------
    SensorRecord
        ``record`` itself when there was nothing to turn, else a copy.

    Raises
    ------
    InputError
        ``heading_reference`` is not one of the known references.
    """
    orientation = record.orientation
    if not orientation or "heading_reference" not in orientation:
        return record
    reference = orientation["heading_reference"]
    if reference not in HEADING_REFERENCES:
        known = ", ".join(repr(r) for r in HEADING_REFERENCES)
        raise input_error(record.source, "field 'orientation.heading_reference' must be one of "
                                         f"{known}, got {reference!r:.40}")
    orientation = {k: v for k, v in orientation.items() if k != "heading_reference"}
    record = replace(record, orientation=orientation)
    if reference == "grid" or orientation.get("trend_deg") is None:
        return record
    trend = float(orientation["trend_deg"])
    if reference == "magnetic":
        trend = _magnetic_to_true(record, georef, trend, exif_date, notes)
    where = _local_xy(record, georef) if georef is not None else None
    if where is not None:
        convergence = float(meridian_convergence_deg(georef, (where[0], where[1], 0.0)))
        if math.isfinite(convergence) and abs(convergence) >= 0.005:
            grid = (trend - convergence) % 360.0
            notes.append(f"trend {trend:.2f}° from true north is {grid:.2f}° from the grid "
                         f"north of {georef.crs} (meridian convergence {convergence:+.2f}° at "
                         "the camera)")
            trend -= convergence
    record.orientation = {**orientation, "trend_deg": trend % 360.0}
    return record


def _magnetic_to_true(record: SensorRecord, georef: Georef | None, magnetic_deg: float,
                      exif_date: date | None, notes: list[str]) -> float:
    """A magnetic heading turned to true north by the WMM declination at the
    camera on the capture date, with a note; as it was (and a note saying
    why) when the place or the date is unknown or the model has no answer."""
    def not_applied(why: str) -> float:
        notes.append(f"magnetic heading: declination not applied ({why}): the trend is used "
                     "as if from true north")
        return magnetic_deg

    site = _latitude_longitude_height(record, georef)
    if site is None:
        return not_applied("the camera's latitude and longitude are unknown: a GPS position "
                           "or a georef.json is needed")
    when = record.capture_datetime or exif_date
    if when is None:
        return not_applied("no capture date: give the record's 'time' or keep the photo's "
                           "EXIF DateTimeOriginal")
    try:
        declination = magnetic_declination(*site, when)
    except GeoError as exc:
        return not_applied(str(exc).removeprefix("magnetic declination: "))
    true = (magnetic_deg + declination.declination_deg) % 360.0
    caveats = "".join((
        "; near a magnetic pole, where a compass is poor" if declination.caution else "",
        "; extrapolated past the model's years" if declination.extrapolated else ""))
    notes.append(f"magnetic heading: declination {declination.label()} applied (trend "
                 f"{magnetic_deg:.2f}° from magnetic north is {true:.2f}° from true "
                 f"north{caveats})")
    return true


def _latitude_longitude_height(record: SensorRecord, georef: Georef | None
                               ) -> tuple[float, float, float] | None:
    """The camera's WGS84 latitude and longitude (degrees) and height (metres,
    0 when unknown: immaterial to a declination), or None when unknown."""
    pos = record.position or {}
    try:
        if "lat" in pos:
            return float(pos["lat"]), float(pos["lon"]), float(pos.get("alt") or 0.0)
        if georef is None:
            return None
        local = (float(pos["x"]), float(pos["y"]), float(pos.get("z") or 0.0))
        return site_latitude_longitude(georef, local)
    except (KeyError, TypeError, ValueError, OverflowError):  # refused later, with the file
        return None


def _is_drone_photo(photo) -> bool:
    """A drone's photo (DJI XMP): its GPS altitude is the flight's, not a walker's."""
    return "drone-dji:" in str((getattr(photo, "exif", None) or {}).get("XMP") or "")


def _phone_altitude_from_dem(record: SensorRecord, georef: Georef | None, dem: DEM | None,
                             height_above_ground_m: float, notes: list[str]) -> None:
    """Take a phone photo's altitude from the DEM rather than its GPS altitude.

    A phone's GNSS altitude is its worst coordinate (tens of metres; 0 for a
    network fix; ellipsoidal or above sea level depending on the phone) and
    the DEM's is better (Kehl et al. 2017, fig. 2): with a DEM under the
    camera the EXIF ``GPSAltitude`` is dropped, and the note says by how much
    the two differed. Outside the DEM (or on nodata) the GPS altitude stays.
    """
    pos = record.position or {}
    if dem is None or pos.get("alt") is None:
        return
    where = _local_xy(record, georef)
    if where is None:
        return
    # The DEM and the GPS altitude are both heights of the CRS: no origin to take off.
    ox, oy = (georef.origin[:2] if georef is not None else (0.0, 0.0))
    ground = float(dem.height_at(where[0] + ox, where[1] + oy, strict=False))
    if not math.isfinite(ground):
        notes.append(f"camera outside the DEM (or on its nodata): altitude from EXIF GPS "
                     f"({float(pos['alt']):g} m)")
        return
    gps = float(pos["alt"])
    off_by = gps - (ground + height_above_ground_m)
    record.position = {k: v for k, v in pos.items() if k != "alt"}
    notes.append(f"EXIF GPS altitude {gps:g} m not used ({off_by:+.1f} m from the DEM's + "
                 f"{height_above_ground_m:g} m, which is taken: a phone's GPS altitude is "
                 "its least accurate coordinate)")


def check_photo_size(photo: Any, prior: Any, record_path: str | os.PathLike | None = None
                     ) -> None:
    """Refuse a photo that the prior's camera does not fit.

    A camera block of another size but the photo's aspect ratio is scaled to
    the photo (a resized photo) when the prior is made; one of another aspect
    ratio is left as it is and refused here, before the registration.

    Parameters
    ----------
    photo : Photo
    prior : Prior
        Made from ``photo`` (:func:`~napari_imgreg.prior.prior_for_photo`).
    record_path : path-like, optional
        The sensor record the prior was made from; default: the photo's sidecar.

    Raises
    ------
    InputError
        Naming the record (the photo without one) and quoting the record's own
        camera size, not the one scaled to the photo's width.
    """
    w, h = photo.size
    camera = (prior.intrinsics.width, prior.intrinsics.height)
    if (w, h) == camera:
        return
    record = Path(record_path) if record_path is not None else photo.sidecar
    if record is None or not Path(record).exists():
        raise input_error(photo.path, f"the camera is {camera[0]}×{camera[1]} px but the "
                                      f"photo is {w}×{h} px")
    block = read_json(record).get("camera") or {}
    stated = (block.get("width"), block.get("height"))
    if None not in stated:
        camera = stated
    raise input_error(record, f"the camera is {camera[0]}×{camera[1]} px but the photo is "
                              f"{w}×{h} px, another aspect ratio (the record of another "
                              "photo, or a cropped photo?)")


def _is_result(data) -> bool:
    """A RESULT.json (a solved ``pose.R``), not a sensor record."""
    return isinstance(data, dict) and isinstance(data.get("pose"), dict) and "R" in data["pose"]


def _prior_from_result(path: Path, photo, scene) -> Prior:
    """A registration's RESULT.json as the start of another registration of its photo.

    Its camera and pose are the start; its focal length stays an estimate
    where the result says it estimated it. The prior's sigma is the default
    one (the search covers a sensor-sized error, whatever the result says).
    """
    intrinsics, pose, _, _ = load_camera_and_pose(path)
    if photo.size != (intrinsics.width, intrinsics.height):
        raise input_error(path, f"the result is of a {intrinsics.width}×{intrinsics.height} "
                          f"image; the photo is {photo.size[0]}×{photo.size[1]}")
    prior = Prior(intrinsics, pose, assumptions=[f"start pose from the result {path.name}"])
    _attach_sun(prior, SensorRecord(), photo, getattr(scene, "georef", None))
    return prior


def _with_exif_focal(block: dict, exif_camera: dict, orientation: int | None) -> dict:
    """A record's camera block without a focal length, completed from the EXIF camera.

    The EXIF camera is of the photo as shown; a block of the sensor's size
    (a landscape block of a portrait photo) keeps its size and gets the
    EXIF camera turned back to the sensor and scaled to the block, so that
    :func:`prior_from_record` still sees the sensor's block (and turns the
    attitude with it).
    """
    exif_intr = Intrinsics.from_dict(exif_camera)
    if "width" in block and "height" in block:
        size = (int(block["width"]), int(block["height"]))
        shown = (exif_intr.width, exif_intr.height)
        if size != shown and _swapped_aspect(size, shown):
            exif_intr = exif_intr.rotated(-EXIF_QUARTER_TURNS.get(orientation or 1, 0) or 1)
        if (exif_intr.width, exif_intr.height) != size and size[0] > 0:
            exif_intr = exif_intr.scaled(size[0] / exif_intr.width)
        return {**exif_intr.to_dict(), **block}  # the block's own fields win
    return {**exif_camera, **{k: v for k, v in block.items() if k not in ("width", "height")}}


def _exif_orientation(photo) -> int | None:
    """The photo's EXIF ``Orientation`` tag (1–8), None when absent or unreadable."""
    return exif_orientation(getattr(photo, "exif", None))


def _attach_sun(prior: Prior, record: SensorRecord, photo, georef: Georef | None) -> None:
    """Give the prior the sun at capture: record ``sun``, else record ``time``, else EXIF."""
    center = prior.pose.center
    if record.sun is not None or record.time is not None:
        if record.sun is None and georef is None:
            prior.assumptions.append("capture time given but no georeference: sun unknown")
            prior.sun_source = "unknown: capture time given but no georeference"
            return
        prior.sun = sun_from_record(record, georef, center)
        prior.sun_source = (
            "sensor record sun" if record.sun is not None else f"sensor record time {record.time}"
        )
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
