"""The orientation of a model from its camera attitudes: :func:`orient` and its result.

:func:`orient` pairs the model's camera orientations with the phone's, runs
the three estimators, and reads the chosen rotation's residuals into the
paper's diagnostics; :class:`OrientationResult` holds it all and writes
ORIENTATION.json.

The rotation is applied about a centre ``c``:
``X_world = Q (X_model − c) + c``. By default ``c`` is the centroid of the
estimated camera centres (the model stays where it was, only turned);
without camera centres it is the model origin.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np
from scipy.spatial.transform import Rotation

from .._atomic import atomic_write
from .._json import dump as strict_json_dump
from ..camera import attitude_from_rotation, rotation_from_attitude
from ..errors import input_error
from ..io.orientation_tables import (
    OrientationTable,
    PairedOrientations,
    pair_tables,
    read_orientation_table,
)
from ..geo import Georef
from .apply import rotate_cameras
from .declination import AUTO, SurveyDeclination, survey_declination
from .diagnostics import (
    DISTORTED_RESIDUAL_DEG,
    LinearFit,
    QualityFlag,
    fit_line,
    quality_flags,
    residual_angles,
    survey_path_position,
    unwrap_trend,
)
from .estimate import (
    METHODS,
    PAPER_STEP_DEG,
    RotationEstimate,
    _axis_angle,
    _trend_plunge,
    estimate_rotation_lsq,
    estimate_rotation_paper,
    estimate_rotation_robust,
    lower_hemisphere_axis,
    rotation_error_deg,
)

__all__ = ["OrientationResult", "orient", "orient_files", "save_orientation"]

@dataclass
class OrientationResult:
    """The orientation of a model and its diagnostics (ORIENTATION.json).

    Attributes
    ----------
    method : str
        The estimator whose rotation is the result.
    estimates : dict of str to RotationEstimate
        All three estimators' results.
    center : (3,) array
        Rotation centre in the model frame, metres.
    center_source : str
        ``"cameras"`` (centroid of estimated camera centres), ``"origin"``
        or ``"given"``.
    photos : list of str
        Paired photos, in capture order of the MEASURED table.
    delta_xi_deg, delta_rho_deg : (N,) arrays
        Signed residuals under the chosen rotation, degrees.
    path_position : (N,) array
        Position along the survey path, 0–1.
    path_position_source : str
    measured_trend_deg : (N,) array
        Measured trend unwrapped about its circular mean, degrees.
    measured : (N, 3, 3) array
        ``cam_from_world`` measured.
    oriented : (N, 3, 3) array
        ``cam_from_world`` of the estimated cameras after rotation.
    oriented_positions : (N, 3) array or None
        Estimated camera centres after rotation, metres.
    fits : dict of str to LinearFit or None
        ``delta_xi_vs_path``, ``delta_rho_vs_path``, ``delta_xi_vs_trend``,
        ``delta_rho_vs_trend``.
    flags : list of QualityFlag
    notes : list of str
    inputs : dict
        Where the tables came from.
    """

    method: str
    estimates: dict[str, RotationEstimate]
    center: np.ndarray
    center_source: str
    photos: list[str]
    delta_xi_deg: np.ndarray
    delta_rho_deg: np.ndarray
    path_position: np.ndarray
    path_position_source: str
    measured_trend_deg: np.ndarray
    measured: np.ndarray
    oriented: np.ndarray
    oriented_positions: np.ndarray | None
    fits: dict[str, LinearFit | None]
    flags: list[QualityFlag]
    notes: list[str] = field(default_factory=list)
    inputs: dict[str, Any] = field(default_factory=dict)

    # ------------------------------------------------------------ views
    @property
    def chosen(self) -> RotationEstimate:
        return self.estimates[self.method]

    @property
    def rotation(self) -> np.ndarray:
        """``Q``, world_from_model, (3, 3)."""
        return self.chosen.rotation

    @property
    def angle_deg(self) -> float:
        return self.chosen.angle_deg

    @property
    def axis(self) -> np.ndarray:
        return self.chosen.axis

    @property
    def transform(self) -> np.ndarray:
        """4 × 4 world_from_model: ``X_world = Q (X − c) + c``."""
        T = np.eye(4)
        T[:3, :3] = self.rotation
        T[:3, 3] = self.center - self.rotation @ self.center
        return T

    @property
    def used(self) -> np.ndarray:
        """(N,) bool: photos the chosen estimator rests on (the diagnostics use these)."""
        return self.chosen.inliers

    @property
    def mean_abs_delta_xi_deg(self) -> float:
        """Mean |Δξ| over the photos used, degrees."""
        return float(np.mean(np.abs(self.delta_xi_deg[self.used])))

    @property
    def mean_abs_delta_rho_deg(self) -> float:
        """Mean |Δρ| over the photos used, degrees."""
        return float(np.mean(np.abs(self.delta_rho_deg[self.used])))

    @property
    def outliers(self) -> list[str]:
        """Photos the robust estimator set aside."""
        keep = self.estimates["robust"].inliers
        return [p for p, k in zip(self.photos, keep) if not k]

    @property
    def warnings(self) -> list[QualityFlag]:
        return [f for f in self.flags if f.status == "warn"]

    def summary_lines(self) -> list[str]:
        """A short human summary (used by the CLI and the widget)."""
        trend, plunge, angle = lower_hemisphere_axis(self.axis, self.angle_deg)
        names = {
            "paper": f"paper (J tensor + {self.estimates['paper'].details['step_deg']:g}° search)",
            "lsq": "least squares",
            "robust": "robust",
        }
        sense = "clockwise" if angle >= 0 else "anticlockwise"
        lines = [
            f"{len(self.photos)} photos paired; {names[self.method]}: rotation {abs(angle):.2f}° "
            f"{sense} looking down an axis plunging {plunge:.1f}° toward {trend:.1f}° "
            f"(about the {self._center_text()})",
        ]
        for name in METHODS:
            if name == self.method:
                continue
            est = self.estimates[name]
            lines.append(
                f"  {names[name]}: {est.angle_deg:.2f}°, "
                f"{rotation_error_deg(est.rotation, self.rotation):.2f}° from the "
                f"{self.method} result"
            )
        if self.outliers:
            shown = ", ".join(self.outliers[:6]) + (", ..." if len(self.outliers) > 6 else "")
            lines.append(f"  robust fit set aside {len(self.outliers)} photo(s): {shown}")
        lines.append(
            f"mean |Δξ| {self.mean_abs_delta_xi_deg:.2f}°, "
            f"mean |Δρ| {self.mean_abs_delta_rho_deg:.2f}°"
        )
        for flag in self.flags:
            label = {"pass": "ok", "warn": "WARNING", "n/a": "n/a"}[flag.status]
            lines.append(f"  [{label}] {flag.reading}")
        return lines

    def _center_text(self) -> str:
        c = ", ".join(f"{v:.2f}" for v in self.center)
        return {
            "cameras": f"camera centroid ({c})",
            "origin": "model origin",
            "given": f"point ({c})",
        }[self.center_source]

    # ------------------------------------------------------------- JSON
    def to_dict(self) -> dict[str, Any]:
        """ORIENTATION.json content (JSON-ready)."""
        axis, angle = _axis_angle(self.rotation)
        trend, plunge = _trend_plunge(axis)
        lower_trend, lower_plunge, lower_angle = lower_hemisphere_axis(axis, angle)
        robust_keep = self.estimates["robust"].inliers
        measured_att = [attitude_from_rotation(R) for R in self.measured]
        oriented_att = [attitude_from_rotation(R) for R in self.oriented]
        photos = []
        for i, name in enumerate(self.photos):
            entry: dict[str, Any] = {
                "photo": name,
                "delta_xi_deg": float(self.delta_xi_deg[i]),
                "delta_rho_deg": float(self.delta_rho_deg[i]),
                "path_position": float(self.path_position[i]),
                "measured_trend_deg": float(self.measured_trend_deg[i]) % 360.0,
                "measured": dict(zip(("trend_deg", "plunge_deg", "roll_deg"), measured_att[i])),
                "oriented": dict(zip(("trend_deg", "plunge_deg", "roll_deg"), oriented_att[i])),
                "robust_outlier": bool(not robust_keep[i]),
                "used": bool(self.used[i]),
            }
            if self.oriented_positions is not None:
                entry["oriented"]["position"] = self.oriented_positions[i].tolist()
            photos.append(entry)
        units = {
            "delta_xi_vs_path": "degrees per survey path length",
            "delta_rho_vs_path": "degrees per survey path length",
            "delta_xi_vs_trend": "degrees per degree of measured trend",
            "delta_rho_vs_trend": "degrees per degree of measured trend",
        }
        slopes = {}
        for key, fit in self.fits.items():
            slopes[key] = None if fit is None else {**fit.to_dict(), "units": units[key]}
        return {
            "method": self.method,
            "rotation": {
                "matrix": self.rotation.tolist(),
                "axis": axis.tolist(),
                "axis_trend_deg": trend,
                "axis_plunge_deg": plunge,
                "angle_deg": angle,
                "lower_hemisphere": {
                    "axis_trend_deg": lower_trend,
                    "axis_plunge_deg": lower_plunge,
                    "angle_deg": lower_angle,
                    "sense": "positive clockwise looking down the plunge",
                },
                "center": self.center.tolist(),
                "center_source": self.center_source,
                "transform_4x4": self.transform.tolist(),
                "convention": "X_world = matrix @ (X_model - center) + center; right-handed "
                "about axis; world +X east, +Y north, +Z up",
            },
            "estimators": {name: est.to_dict(self.photos) for name, est in self.estimates.items()},
            "residuals": {
                "mean_abs_delta_xi_deg": self.mean_abs_delta_xi_deg,
                "mean_abs_delta_rho_deg": self.mean_abs_delta_rho_deg,
                "mean_abs_delta_xi_all_deg": float(np.mean(np.abs(self.delta_xi_deg))),
                "mean_abs_delta_rho_all_deg": float(np.mean(np.abs(self.delta_rho_deg))),
                "n_used": int(self.used.sum()),
                "sign": "positive when the measured vector is clockwise (seen from above) of "
                "the estimated-and-rotated one",
                "photos": photos,
            },
            "path_position": {
                "source": self.path_position_source,
                "definition": "0 at one end of the survey, 1 at the other; grows in capture order",
            },
            "slopes": slopes,
            "flags": [f.to_dict() for f in self.flags],
            "notes": list(self.notes),
            "inputs": dict(self.inputs),
        }


# -------------------------------------------------------------- pipeline
def orient(
    estimated: OrientationTable | PairedOrientations | str | os.PathLike,
    measured: OrientationTable | str | os.PathLike | None = None,
    method: str = "robust",
    weights: Mapping[str, float] | None = None,
    center: np.ndarray | str | None = None,
    step_deg: float = PAPER_STEP_DEG,
    declination_deg: float | str = 0.0,
    georef: Georef | str | os.PathLike | None = None,
) -> OrientationResult:
    """Orient a model from estimated and measured camera attitudes.

    Parameters
    ----------
    estimated : OrientationTable, PairedOrientations or path
        The model's camera orientations (its frame), or tables already
        paired by :func:`~napari_imgreg.io.orientation_tables.pair_tables`;
        a path is read by ``read_orientation_table`` (any supported format).
    measured : OrientationTable or path
        The phone's (true north); omit when ``estimated`` is paired.
    method : {"robust", "lsq", "paper"}
        Estimator whose rotation is the result (all three are reported).
    weights : mapping of photo name to weight, optional
        Per-photo weights for ``lsq`` and ``robust`` (missing names: 1).
    center : (3,) array, "cameras" or "origin", optional
        Rotation centre in the model frame. Default: the centroid of the
        estimated camera centres when known, else the origin.
    step_deg : float
        Angle increment of the paper's search, degrees.
    declination_deg : float or "auto"
        Magnetic declination, degrees east of true north, added to the
        measured trends (for a phone that logs magnetic headings). ``"auto"``:
        the World Magnetic Model's at the origin of ``georef`` (without it:
        the measured photos' median GPS position) on the median capture day
        of the measured photos
        (:func:`~napari_imgreg.orient.declination.survey_declination`).
        ORIENTATION.json's ``inputs.declination`` says which was used and
        where it came from.
    georef : Georef or path-like, optional
        The model's ``georef.json``; read (only) for ``"auto"``.

    Returns
    -------
    OrientationResult

    Raises
    ------
    InputError
        The tables do not pair (see ``pair_tables``), or their angles fit far
        better read in radians or with plunge or roll negated (a table in
        another convention: the message says which); with ``"auto"``: no
        place (neither a georeference nor photos with GPS), no capture date,
        or a date or place the World Magnetic Model does not cover.
    ValueError
        Unknown ``method``, an unknown declination word, or ``"auto"``
        without the measured table (already paired tables carry no dates).
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if isinstance(estimated, (str, os.PathLike)):
        estimated = read_orientation_table(estimated)
    if isinstance(measured, (str, os.PathLike)):
        measured = read_orientation_table(measured)
    if isinstance(estimated, PairedOrientations):
        paired = estimated
        inputs: dict[str, Any] = {}
    else:
        if measured is None:
            raise ValueError("give both the estimated and the measured table")
        paired = pair_tables(estimated, measured)
        inputs = {
            "estimated": str(estimated.source) if estimated.source else None,
            "estimated_format": estimated.kind,
            "measured": str(measured.source) if measured.source else None,
            "measured_format": measured.kind,
        }
    inputs["n_photos"] = len(paired)
    declination_notes: list[str] = []
    if isinstance(declination_deg, str):
        survey = _auto_declination(declination_deg, measured, georef)
        declination_deg = survey.declination_deg
        inputs["declination"] = survey.to_dict()
        declination_notes.append(survey.note())
    else:
        inputs["declination"] = {"declination_deg": float(declination_deg), "source": "given"}
    inputs["declination_deg"] = float(declination_deg)
    if isinstance(measured, OrientationTable):
        declination_notes += _heading_reference_notes(measured, float(declination_deg))
    w = None
    if weights is not None:
        w = np.array([float(weights.get(p, 1.0)) for p in paired.photos])

    E, M = paired.estimated, paired.measured
    _refuse_other_angle_conventions(
        E, M, inputs.get("measured"), inputs.get("estimated"),
        estimated_may_be_radians=inputs.get("estimated_format") == "csv",
    )
    if declination_deg:
        # Turning every measured axis clockwise (seen from above) adds to its trend.
        M = M @ Rotation.from_rotvec([0.0, 0.0, declination_deg], degrees=True).as_matrix()
    estimates = {
        "paper": estimate_rotation_paper(E, M, step_deg),
        "lsq": estimate_rotation_lsq(E, M, w),
        "robust": estimate_rotation_robust(E, M, w),
    }
    Q = estimates[method].rotation

    positions = paired.estimated_positions
    if isinstance(center, str):
        if center == "cameras" and positions is None:
            raise input_error(
                inputs.get("estimated"), "no camera centres to rotate about (use the origin)"
            )
        if center not in ("cameras", "origin"):
            raise ValueError(f"center must be 'cameras', 'origin' or a point, got {center!r}")
        center_source = center
    elif center is not None:
        center_source = "given"
    else:
        center_source = "cameras" if positions is not None else "origin"
    if center_source == "cameras":
        c = positions.mean(axis=0)
    elif center_source == "origin":
        c = np.zeros(3)
    else:
        c = np.asarray(center, dtype=np.float64).reshape(3)

    d_xi, d_rho = residual_angles(Q, E, M)
    path_source_positions = positions if positions is not None else paired.measured_positions
    path_position, path_source = survey_path_position(path_source_positions, paired.capture_order)
    trend = unwrap_trend(np.degrees(np.arctan2(M[:, 2, 0], M[:, 2, 1])))
    # Photos the chosen estimator set aside (gross sensor errors) would drive
    # the fits; they are reported, not fitted.
    used = estimates[method].inliers
    fits = {
        "delta_xi_vs_path": fit_line(path_position[used], d_xi[used]),
        "delta_rho_vs_path": fit_line(path_position[used], d_rho[used]),
        "delta_xi_vs_trend": fit_line(trend[used], d_xi[used]),
        "delta_rho_vs_trend": fit_line(trend[used], d_rho[used]),
    }
    mean_abs = max(float(np.mean(np.abs(d_xi[used]))), float(np.mean(np.abs(d_rho[used]))))
    # Steep views leave Δξ without a meaningful sign (diagnostics): the flags need the plunge.
    view_z = np.abs(np.clip(M[used, 2, 2], -1.0, 1.0))
    median_abs_plunge = float(np.degrees(np.median(np.arcsin(view_z))))
    flags = quality_flags(mean_abs, fits["delta_xi_vs_path"], fits["delta_xi_vs_trend"],
                          median_abs_plunge, n_set_aside=int((~used).sum()))
    oriented, oriented_positions = rotate_cameras(E, positions, Q, c)
    return OrientationResult(
        method=method,
        estimates=estimates,
        center=c,
        center_source=center_source,
        photos=list(paired.photos),
        delta_xi_deg=d_xi,
        delta_rho_deg=d_rho,
        path_position=path_position,
        path_position_source=path_source,
        measured_trend_deg=trend,
        measured=M,
        oriented=oriented,
        oriented_positions=oriented_positions,
        fits=fits,
        flags=flags,
        notes=list(paired.notes) + declination_notes,
        inputs=inputs,
    )


def _auto_declination(word: str, measured: OrientationTable | None,
                      georef: Georef | str | os.PathLike | None) -> SurveyDeclination:
    """The survey's WMM declination for ``declination_deg="auto"``."""
    if word != AUTO:
        raise ValueError(f"declination_deg must be degrees or {AUTO!r}, got {word!r}")
    if not isinstance(measured, OrientationTable):
        raise ValueError("an automatic declination needs the measured table (its capture "
                         "dates), not tables already paired")
    # Without a georeference the MEASURED photos' GPS places the site.
    return survey_declination(measured, georef)


def _heading_reference_notes(measured: OrientationTable, declination_deg: float) -> list[str]:
    """Say where the measured photos' own heading references disagree with the
    declination used: magnetic headings left as they are, or true-north ones turned."""
    references = measured.heading_references or []
    magnetic, true = references.count("magnetic"), references.count("true")
    if magnetic and not declination_deg:
        return [f"{magnetic} measured photo(s) give magnetic headings and no declination was "
                "added (--declination auto computes it; --declination DEG gives it)"]
    if true and declination_deg:
        return [f"{true} measured photo(s) give headings from true north (DJI gimbal yaw, EXIF "
                f"GPSImgDirectionRef T): the declination {declination_deg:+.1f}° was added to "
                "them too"]
    return []


def _mean_residual_deg(E: np.ndarray, M: np.ndarray) -> float:
    """The larger of mean |Δξ| and mean |Δρ| under the least-squares rotation, degrees."""
    d_xi, d_rho = residual_angles(estimate_rotation_lsq(E, M).rotation, E, M)
    return max(float(np.mean(np.abs(d_xi))), float(np.mean(np.abs(d_rho))))


def _signed_trend(attitudes: np.ndarray) -> np.ndarray:
    """Trends in (-180, 180]: a radian table's negative trends were stored modulo 360."""
    return np.where(attitudes[:, 0] > 180.0, attitudes[:, 0] - 360.0, attitudes[:, 0])


def _looks_like_radians(attitudes: np.ndarray) -> bool:
    """Every trend, plunge and roll (degrees, (N, 3)) is within a radian's range."""
    trend = _signed_trend(attitudes)
    return bool(
        np.all((trend >= -math.pi) & (trend <= 2 * math.pi))
        and np.all(np.abs(attitudes[:, 1]) <= math.pi / 2)
        and np.all(np.abs(attitudes[:, 2]) <= math.pi)
    )


def _as_degrees(attitudes: np.ndarray) -> np.ndarray:
    """Attitudes whose numbers were radians, in degrees."""
    return np.degrees(np.column_stack([_signed_trend(attitudes), attitudes[:, 1:]]))


def _rotations(attitudes: np.ndarray) -> np.ndarray:
    """(N, 3, 3) ``cam_from_world`` from (N, 3) trend, plunge, roll in degrees."""
    return np.array([rotation_from_attitude(*a) for a in attitudes])


def _refuse_other_angle_conventions(
    E: np.ndarray,
    M: np.ndarray,
    measured_source: str | None,
    estimated_source: str | None,
    estimated_may_be_radians: bool,
) -> None:
    """Refuse tables whose angles are evidently in another unit or sign convention.

    A phone table in radians, or logging plunge positive upward or roll the
    other way, still gives a rotation, with large residuals that the flags
    read as a distorted model or a bad compass. When the fit is poor (mean
    residual above :data:`DISTORTED_RESIDUAL_DEG`) and reading the angles in
    radians, or with plunge or roll negated, fits at least twice as well
    (and, for a sign, well enough to pass as undistorted), the table is
    refused with the fix; a merely poor survey fits no better in another
    convention and goes through (135 generated domed, uncalibrated and noisy
    surveys did).

    Parameters
    ----------
    E, M : (N, 3, 3) arrays
        Estimated ``cam_from_model`` and measured ``cam_from_world``.
    measured_source, estimated_source : str or None
        The tables' files, for the message.
    estimated_may_be_radians : bool
        The estimated table was typed in as angles (CSV), so it may be in radians too.

    Raises
    ------
    InputError
        Naming the table and the convention its numbers fit.
    """
    base = _mean_residual_deg(E, M)
    if not math.isfinite(base) or base <= DISTORTED_RESIDUAL_DEG:
        return
    measured_att = np.array([attitude_from_rotation(R) for R in M])
    # (source, problem, estimated, measured, is a unit rather than a sign)
    candidates = []
    if _looks_like_radians(measured_att):
        candidates.append((measured_source, "angles look like radians", E,
                           _rotations(_as_degrees(measured_att)), True))
    if estimated_may_be_radians:
        estimated_att = np.array([attitude_from_rotation(R) for R in E])
        if _looks_like_radians(estimated_att):
            candidates.append((estimated_source, "angles look like radians",
                               _rotations(_as_degrees(estimated_att)), M, True))
    for problem, signs in (
        ("plunge_deg looks positive upward", (1.0, -1.0, 1.0)),
        ("roll_deg looks positive anticlockwise", (1.0, 1.0, -1.0)),
        ("plunge_deg and roll_deg look opposite in sign", (1.0, -1.0, -1.0)),
    ):
        candidates.append((measured_source, problem, E, _rotations(measured_att * signs), False))
    for source, problem, E2, M2, is_unit in candidates:
        fitted = _mean_residual_deg(E2, M2)
        if fitted < base / 2 and (is_unit or fitted < DISTORTED_RESIDUAL_DEG):
            raise input_error(
                source,
                f"{problem}: read that way the cameras fit to {fitted:.1f}° on average instead "
                f"of {base:.1f}°; give trend_deg, plunge_deg and roll_deg in degrees, plunge "
                "positive looking down, roll positive when the image's right side dips "
                "(docs/orient.md, 'The angle convention')",
            )


def orient_files(
    estimated_path: str | os.PathLike, measured_path: str | os.PathLike, **kwargs
) -> OrientationResult:
    """Read two orientation tables (any supported format) and :func:`orient` them."""
    estimated = read_orientation_table(estimated_path)
    measured = read_orientation_table(measured_path)
    return orient(estimated, measured, **kwargs)


def save_orientation(result: OrientationResult, path: str | os.PathLike) -> None:
    """Write ORIENTATION.json atomically."""
    with atomic_write(path, encoding="utf-8") as fh:
        strict_json_dump(result.to_dict(), fh, indent=2, ensure_ascii=False)
        fh.write("\n")
