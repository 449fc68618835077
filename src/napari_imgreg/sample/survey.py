"""A generated orientation survey with a known answer (tests, benchmark, docs).

:func:`simulate_survey` walks along a wall photographing it, as in the test
survey of Tavani, Corradetti et al. (2019), and reports the camera attitudes
a phone would measure (true north) and a structure-from-motion model would
estimate (its own frame), with the true rotation between the two
(``world_from_model``). :func:`napari_imgreg.orient.orient` should recover it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from ..io.orientation_tables import OrientationTable

__all__ = ["SimulatedSurvey", "simulate_survey"]

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
    """

    estimated: OrientationTable
    measured: OrientationTable
    rotation: np.ndarray
    outliers: np.ndarray


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
    model_centres = scale * (centres @ rotation) + rng.normal(scale=100.0, size=3)
    estimated = OrientationTable.from_rotations(photos, estimated_R, model_centres, kind="memory")
    return SimulatedSurvey(estimated, measured, rotation, outliers)
