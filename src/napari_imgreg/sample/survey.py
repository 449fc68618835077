"""A generated orientation survey with a known answer (tests, benchmark, docs).

:func:`simulate_survey` walks along a wall photographing it, as in the test
survey of Tavani, Corradetti et al. (2019), and reports the camera attitudes
a phone would measure (true north) and a structure-from-motion model would
estimate (its own frame), with the true rotation between the two
(``world_from_model``). :func:`napari_imgreg.orient.orient` should recover it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from datetime import date
from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from ..io.orientation_tables import OrientationTable

__all__ = ["SimulatedSurvey", "simulate_survey", "wall_model", "write_metashape_xml",
           "write_orientation_example"]

_UP = np.array([0.0, 0.0, 1.0])


def _unwrap_trend(trend_deg: np.ndarray) -> np.ndarray:
    """Trends (degrees) unwrapped about their circular mean, so 355° and 5° are 10° apart.

    The same as :func:`napari_imgreg.orient.unwrap_trend`, which ``sample``
    may not import (orient and sample are sibling layers).
    """
    from scipy.stats import circmean

    t = np.asarray(trend_deg, dtype=np.float64)
    mean = float(circmean(t, high=360.0, low=0.0))
    return mean + (t - mean + 180.0) % 360.0 - 180.0


@dataclass
class SimulatedSurvey:
    """A generated survey with a known orientation (tests, benchmark, docs).

    Attributes
    ----------
    estimated, measured : OrientationTable
        What the model and the phone would report.
    rotation : (3, 3) array
        The true ``world_from_model``.
    outliers : (N,) bool array
        Photos given a gross compass error.
    strike_deg : float
        The wall's strike, degrees from north (it runs through the world origin).
    path_length_m, distance_m : float
        The walk's length along the wall and the cameras' distance from it.
    model_scale : float
    model_offset : (3,) array
        The model frame: ``model = model_scale · rotationᵀ · world + model_offset``.
    """

    estimated: OrientationTable
    measured: OrientationTable
    rotation: np.ndarray
    outliers: np.ndarray
    strike_deg: float = 0.0
    path_length_m: float = 200.0
    distance_m: float = 30.0
    model_scale: float = 1.0
    model_offset: np.ndarray = field(default_factory=lambda: np.zeros(3))


def simulate_survey(
    rng: np.random.Generator,
    n_stations: int = 17,
    view_offsets_deg: Sequence[float] = (-50.0, 0.0, 50.0),
    rotation: np.ndarray | None = None,
    noise_deg: float = 0.0,
    outlier_fraction: float = 0.0,
    outlier_error_deg: float = 20.0,
    doming_deg: float = 0.0,
    compass_gain: float = 0.0,
    path_length_m: float = 200.0,
    distance_m: float = 30.0,
) -> SimulatedSurvey:
    """A walk along a wall, photographing it square-on and obliquely.

    As in the paper's test survey (51 photos: 17 stations × perpendicular
    and ±50° oblique views, ~30 m from a 200 m wall). The wall strikes in a
    random direction; plunges and rolls are random within ±10° and ±5°.

    Parameters
    ----------
    rng : numpy.random.Generator
    n_stations : int
        Camera stations along the path.
    view_offsets_deg : sequence of float
        View directions at each station relative to square-on, degrees.
    rotation : (3, 3) array, optional
        True world_from_model; default a random axis and 5–120° angle.
    noise_deg : float
        Standard deviation of the phone's trend, plunge and roll errors.
    outlier_fraction : float
        Share of photos given a ±``outlier_error_deg`` compass error.
    doming_deg : float
        Doming: the model turns the cameras about the vertical by
        ``doming_deg × (s − 0.5)`` at path position ``s`` (the paper's
        model 2 had 26°).
    compass_gain : float
        Uncalibrated compass: measured trend errs by ``compass_gain ×
        (trend − mean trend)``.
    path_length_m, distance_m : float
        Survey geometry, metres.
    """
    if rotation is None:
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        rotation = Rotation.from_rotvec(axis * math.radians(rng.uniform(5.0, 120.0))).as_matrix()
    strike = rng.uniform(0.0, 360.0)
    facing = strike + 90.0  # the photographer looks across the strike
    along = np.array([math.sin(math.radians(strike)), math.cos(math.radians(strike)), 0.0])
    towards = np.array([math.sin(math.radians(facing)), math.cos(math.radians(facing)), 0.0])

    photos, true_att, centres, s_along = [], [], [], []
    for k, s in enumerate(np.linspace(0.0, 1.0, n_stations)):
        centre = (s - 0.5) * path_length_m * along - distance_m * towards + [0, 0, 1.6]
        for offset in view_offsets_deg:
            photos.append(f"IMG_{len(photos) + 1:04d}.jpg")
            true_att.append(
                ((facing + offset) % 360.0, rng.uniform(-10.0, 10.0), rng.uniform(-5.0, 5.0))
            )
            centres.append(centre + rng.normal(scale=0.3, size=3))
            s_along.append(s)
    true_att = np.array(true_att)
    centres = np.array(centres)
    s_along = np.array(s_along)
    n = len(photos)

    measured_att = true_att + rng.normal(scale=noise_deg, size=true_att.shape)
    unwrapped = _unwrap_trend(true_att[:, 0])
    measured_att[:, 0] += compass_gain * (unwrapped - unwrapped.mean())
    outliers = np.zeros(n, bool)
    n_out = int(round(outlier_fraction * n))
    if n_out:
        outliers[rng.choice(n, n_out, replace=False)] = True
        measured_att[outliers, 0] += outlier_error_deg * rng.choice([-1.0, 1.0], n_out)
    measured = OrientationTable.from_attitudes(
        photos, measured_att[:, 0], np.clip(measured_att[:, 1], -90, 90), measured_att[:, 2],
        kind="memory",
    )

    true_R = OrientationTable.from_attitudes(photos, *true_att.T).cam_from_world
    doming = Rotation.from_rotvec(
        np.outer(doming_deg * (s_along - 0.5), _UP), degrees=True
    ).as_matrix()
    # cam_from_model = cam_from_world · (turned by doming)ᵀ · Q
    estimated_R = true_R @ np.transpose(doming, (0, 2, 1)) @ rotation
    scale = rng.uniform(0.2, 5.0)  # an SfM model has an arbitrary scale and origin too
    model_offset = rng.normal(scale=100.0, size=3)
    model_centres = scale * (centres @ rotation) + model_offset
    estimated = OrientationTable.from_rotations(photos, estimated_R, model_centres, kind="memory")
    return SimulatedSurvey(estimated, measured, rotation, outliers, strike_deg=float(strike),
                           path_length_m=float(path_length_m), distance_m=float(distance_m),
                           model_scale=float(scale), model_offset=model_offset)


#: Colours of the wall's beds (sandstone, mudstone), RGB 0–1.
_BED_COLORS = np.array([[0.80, 0.70, 0.50], [0.55, 0.54, 0.52]])


def wall_model(survey: SimulatedSurvey, height_m: float = 25.0, spacing_m: float = 4.0,
               bed_thickness_m: float = 3.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The wall the survey photographed, as a mesh in the model's frame.

    A steep wall along the survey's strike, a little longer than the walk,
    with a few metres of smooth relief (bays and buttresses) and a slight
    lean away from the cameras, expressed in the model frame the estimated
    table is in (``model_scale · rotationᵀ · world + model_offset``): what
    a structure-from-motion model of it would hold before it is oriented.
    Its vertices are coloured by horizontal beds of sandstone and mudstone,
    so an oriented model shows them level.

    Parameters
    ----------
    survey : SimulatedSurvey
    height_m : float
        Height of the wall above the cameras' ground, metres.
    spacing_m : float
        Grid spacing, metres.
    bed_thickness_m : float
        Thickness of the coloured beds, metres.

    Returns
    -------
    vertices : (N, 3) array
        Model frame.
    faces : (M, 3) int array
        Triangles, turned towards the cameras.
    colors : (N, 3) array
        Vertex colours, RGB 0–1.
    """
    strike = math.radians(survey.strike_deg)
    along = np.array([math.sin(strike), math.cos(strike), 0.0])
    towards = np.array([math.cos(strike), -math.sin(strike), 0.0])  # strike + 90°
    half = 0.6 * survey.path_length_m
    u = np.linspace(-half, half, int(round(2 * half / spacing_m)) + 1)
    h = np.linspace(-2.0, height_m, int(round((height_m + 2.0) / spacing_m)) + 1)
    U, H = np.meshgrid(u, h)
    relief = (2.0 * np.sin(2 * np.pi * U / 70.0) + 1.0 * np.sin(2 * np.pi * U / 23.0 + 1.0)
              + 0.15 * H)
    world = U[..., None] * along + relief[..., None] * towards + H[..., None] * _UP
    vertices = survey.model_scale * (world.reshape(-1, 3) @ survey.rotation) + survey.model_offset
    n_u = len(u)
    corner = (np.arange(len(h) - 1)[:, None] * n_u + np.arange(n_u - 1)[None, :]).ravel()
    faces = np.concatenate([
        np.stack([corner, corner + n_u + 1, corner + 1], axis=1),
        np.stack([corner, corner + n_u, corner + n_u + 1], axis=1),
    ])
    bed = (np.floor(H.ravel() / bed_thickness_m).astype(int)) % 2
    return vertices, faces, _BED_COLORS[bed]


def write_metashape_xml(path, table: OrientationTable) -> None:
    """Write camera orientations as Agisoft Metashape camera XML (atomically).

    What *File → Export → Export Cameras… → Agisoft XML* writes for an
    unreferenced chunk: one aligned ``<camera>`` per photo, labelled by the
    photo's name without its extension, with its camera-to-model transform
    (a row-major 4 × 4 matrix, OpenCV camera axes); no chunk transform.

    Parameters
    ----------
    path : path-like
    table : OrientationTable
        Rotations (``cam_from_world`` in the model frame) and positions.
    """
    from .._atomic import atomic_write

    cameras = []
    for i, (photo, cam_from_model) in enumerate(zip(table.photos, table.cam_from_world)):
        transform = np.eye(4)
        transform[:3, :3] = cam_from_model.T
        if table.positions is not None:
            transform[:3, 3] = table.positions[i]
        numbers = " ".join(f"{v:.12g}" for v in transform.ravel())
        label = photo.rsplit(".", 1)[0]
        cameras.append(f'    <camera id="{i}" sensor_id="0" label="{label}">\n'
                       f"     <transform>{numbers}</transform>\n    </camera>")
    text = ('<?xml version="1.0" encoding="UTF-8"?>\n'
            '<document version="1.5.0">\n'
            ' <chunk label="Chunk 1" enabled="true">\n'
            '  <sensors next_id="1">\n'
            '   <sensor id="0" label="phone" type="frame"/>\n'
            '  </sensors>\n'
            f'  <cameras next_id="{len(cameras)}" next_group_id="0">\n'
            + "\n".join(cameras)
            + "\n  </cameras>\n </chunk>\n</document>\n")
    with atomic_write(path, encoding="utf-8") as fh:
        fh.write(text)


def _write_obj(path, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray,
               comment: str) -> None:
    """Write a vertex-coloured OBJ (``v x y z r g b`` lines), atomically."""
    from .._atomic import atomic_write

    with atomic_write(path, encoding="utf-8") as fh:
        fh.write(f"# {comment}\n")
        fh.writelines(f"v {x:.4f} {y:.4f} {z:.4f} {r:.3f} {g:.3f} {b:.3f}\n"
                      for (x, y, z), (r, g, b) in zip(vertices, colors))
        fh.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces)


#: The files of the orientation example (:func:`write_orientation_example`).
#: The day the example survey's phone photos were taken (``phone.csv``'s ``time``).
EXAMPLE_SURVEY_DATE = date(2026, 6, 12)

ORIENTATION_EXAMPLE_FILES = {
    "estimated": "cameras.xml",
    "measured": "phone.csv",
    "model": "model.obj",
    "truth": "truth.json",
}


def write_orientation_example(folder, rng: np.random.Generator,
                              noise_deg: float = 1.0) -> dict[str, str]:
    """Write an example survey for ``napari-imgreg orient`` into a folder.

    The paper's test survey (:func:`simulate_survey`: 51 photos along a
    200 m wall) with phone errors of ``noise_deg`` on trend, plunge and roll:

    * ``cameras.xml`` — the model's camera orientations, as Metashape exports them;
    * ``phone.csv`` — the phone's attitudes (the contract's CSV), each with
      its capture day (:data:`EXAMPLE_SURVEY_DATE`, a ``time`` column);
    * ``model.obj`` — the wall in the model's frame (:func:`wall_model`);
    * ``truth.json`` — the true rotation ``world_from_model`` (matrix, axis
      and angle; and as ``orient`` reports it: the axis pointing down, the
      angle positive clockwise looking down it) and the model frame's scale
      and offset.

    Parameters
    ----------
    folder : path-like
        Created if missing.
    rng : numpy.random.Generator
    noise_deg : float

    Returns
    -------
    dict of str to str
        :data:`ORIENTATION_EXAMPLE_FILES`.
    """
    import json
    from pathlib import Path

    from .._atomic import atomic_write
    from ..io.orientation_tables import write_orientation_csv

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    survey = simulate_survey(rng, noise_deg=noise_deg)
    files = ORIENTATION_EXAMPLE_FILES
    write_metashape_xml(folder / files["estimated"], survey.estimated)
    # The day of the field survey: what `orient --declination auto` needs.
    measured = dataclasses.replace(survey.measured,
                                   capture_dates=[EXAMPLE_SURVEY_DATE] * len(survey.measured))
    write_orientation_csv(folder / files["measured"], measured)
    vertices, faces, colors = wall_model(survey)
    _write_obj(folder / files["model"], vertices, faces, colors,
               "the surveyed wall, in the model frame of cameras.xml (not yet oriented)")
    rotvec = Rotation.from_matrix(survey.rotation).as_rotvec()
    angle = float(np.linalg.norm(rotvec))
    axis = rotvec / angle
    # As orient reports it: the axis pointing down, the angle positive
    # clockwise looking down it.
    down_axis, signed_angle = (-axis, -angle) if axis[2] > 0 else (axis, angle)
    truth = {
        "world_from_model": np.round(survey.rotation, 12).tolist(),
        "axis": np.round(axis, 9).tolist(),
        "angle_deg": round(math.degrees(angle), 6),
        "lower_hemisphere": {
            "axis_trend_deg": round(math.degrees(math.atan2(down_axis[0], down_axis[1])) % 360, 3),
            "axis_plunge_deg": round(math.degrees(math.asin(-down_axis[2])), 3),
            "angle_deg": round(math.degrees(signed_angle), 3),
        },
        "model_scale": round(survey.model_scale, 9),
        "model_offset": np.round(survey.model_offset, 6).tolist(),
        "phone_noise_deg": noise_deg,
        "n_photos": len(survey.measured),
    }
    with atomic_write(folder / files["truth"], encoding="utf-8") as fh:
        # One line per entry: the matrix's rows stay readable.
        fh.write("{\n" + ",\n".join(f" {json.dumps(key)}: {json.dumps(value)}"
                                      for key, value in truth.items()) + "\n}\n")
    return dict(files)
