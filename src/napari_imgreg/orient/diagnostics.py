"""What remains after orienting: per-photo residuals, their trends, and the paper's flags.

Diagnostics follow Tavani, Corradetti et al. (2019): per-photo Δξ and Δρ,
their mean absolute values, and the best-fit slopes and R² of Δξ against the
position along the survey path and against the measured trend, read as
quality flags (mean < 2°, |slope vs path| < 3, |slope vs trend| ≤ 0.1).

Units and definitions
---------------------
* Δξ (Δρ) is the angle in degrees between the measured ξ (ρ) and the
  estimated-and-rotated one, signed positive when the measured vector lies
  clockwise of the rotated estimate seen from above (the sign of the trend
  difference); a vector with no horizontal turn counts as positive.
* Position along the survey path is dimensionless, 0 at one end of the
  survey and 1 at the other: each camera centre is projected on the survey
  line (the principal axis of the camera centres), oriented so it grows in
  capture order. Without camera centres, the photo's rank in the MEASURED
  table is used. The slope against it is therefore in degrees per survey
  length: the change of Δξ from one end of the path to the other. The paper
  gives no formula; its numbers imply this scale (a slope of 26 "implying
  values of about −13° and 13° at the two ends", and slopes < 3.2 meaning a
  "maximum distortion between the edges of the models" of ~3°).
* The slope against the measured trend is in degrees per degree (the
  paper: Δξ from −4° to 4° over trends 200°–280° is a slope of 0.1); trends
  are unwrapped about their circular mean so a survey across north is one
  interval.

When the slopes cannot be read
------------------------------
The two slope flags are ``n/a`` rather than pass or warn when the data
cannot test them (each case measured on generated surveys):

* fewer than :data:`MIN_SLOPE_PHOTOS` photos: with 2° of phone noise a
  line through three photos taken at one spot "found" a slope of −7.6;
* photos facing a range narrower than :data:`NARROW_TREND_SPAN_DEG`: the
  phone's own trend error is on both axes of the trend plot, which biases
  the slope towards 1 (errors in variables: ``σ² / (σ² + var(trend))``),
  so a calibrated phone pointed one way reads as uncalibrated;
* views steeper than :data:`STEEP_VIEW_PLUNGE_DEG` on median (nadir
  drone surveys): the sign of Δξ comes from the trend of a near-vertical
  vector and is noise, so a model domed by 26° gave a path slope of
  1.7–2 ("no doming"), and a compass error shows in Δξ only as ``cos(plunge)``
  of itself.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .estimate import _UP, _angle_between, _axes, _finite

__all__ = [
    "MEAN_RESIDUAL_MAX_DEG",
    "DISTORTED_RESIDUAL_DEG",
    "PATH_SLOPE_MAX",
    "TREND_SLOPE_MAX",
    "MIN_SLOPE_PHOTOS",
    "NARROW_TREND_SPAN_DEG",
    "STEEP_VIEW_PLUNGE_DEG",
    "LinearFit",
    "QualityFlag",
    "residual_angles",
    "survey_path_position",
    "unwrap_trend",
    "fit_line",
    "quality_flags",
]

# The paper's quality indicators (its concluding paragraph).
MEAN_RESIDUAL_MAX_DEG = 2.0  # mean |Δξ|, |Δρ| of faithful models
DISTORTED_RESIDUAL_DEG = 4.0  # ... and of noticeably distorted ones
PATH_SLOPE_MAX = 3.0  # |slope| of Δξ vs path position, degrees per path length
TREND_SLOPE_MAX = 0.1  # |slope| of Δξ vs measured trend, degrees per degree

# When the slopes say nothing (module docstring): too few photos, too narrow
# a fan of view directions, or views too steep for Δξ to carry a sign.
MIN_SLOPE_PHOTOS = 6
NARROW_TREND_SPAN_DEG = 20.0
STEEP_VIEW_PLUNGE_DEG = 60.0


def residual_angles(
    rotation: np.ndarray, estimated: np.ndarray, measured: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Signed Δξ and Δρ of each photo under a rotation.

    Parameters
    ----------
    rotation : (3, 3) array
        ``world_from_model``.
    estimated : (N, 3, 3) array
        ``cam_from_model`` of each photo.
    measured : (N, 3, 3) array
        ``cam_from_world`` of each photo.

    Returns
    -------
    delta_xi_deg, delta_rho_deg : (N,) arrays
        Angles in degrees between measured and estimated-and-rotated ξ and
        ρ, positive when the measured vector is clockwise of the rotated one
        seen from above.
    """
    xi_e, rho_e = _axes(estimated)
    xi_m, rho_m = _axes(measured)
    Q = np.asarray(rotation, dtype=np.float64)

    def signed(est: np.ndarray, meas: np.ndarray) -> np.ndarray:
        turned = est @ Q.T
        angle = _angle_between(turned, meas)
        clockwise = np.cross(turned, meas) @ _UP <= 0.0
        return np.where(clockwise, angle, -angle)

    return signed(xi_e, xi_m), signed(rho_e, rho_m)


def survey_path_position(
    positions: np.ndarray | None, capture_order: np.ndarray
) -> tuple[np.ndarray, str]:
    """Position of each photo along the survey path, 0 at one end, 1 at the other.

    Parameters
    ----------
    positions : (N, 3) array or None
        Camera centres (any frame), metres.
    capture_order : (N,) array
        Rank of each photo in capture order.

    Returns
    -------
    position : (N,) array
        Dimensionless, in [0, 1], growing in capture order.
    source : str
        How it was computed (for reports).
    """
    order = np.asarray(capture_order, dtype=np.float64)
    n = len(order)
    if positions is not None and n >= 2:
        centred = np.asarray(positions, dtype=np.float64) - np.mean(positions, axis=0)
        _, singular, vt = np.linalg.svd(centred, full_matrices=False)
        if singular[0] > 1e-9:
            along = centred @ vt[0]
            if np.ptp(order) > 0 and np.corrcoef(along, order)[0, 1] < 0:
                along = -along  # so the position grows in capture order
            span = np.ptp(along)
            return (along - along.min()) / span, "camera centres projected on the survey line"
    ranks = np.argsort(np.argsort(order)).astype(np.float64)
    return ranks / max(n - 1, 1), "photo order in the measured table"


def unwrap_trend(trend_deg: np.ndarray) -> np.ndarray:
    """Trends (degrees) unwrapped about their circular mean, so 355° and 5° are 10° apart."""
    from scipy.stats import circmean

    t = np.asarray(trend_deg, dtype=np.float64)
    mean = float(circmean(t, high=360.0, low=0.0))
    return mean + (t - mean + 180.0) % 360.0 - 180.0


@dataclass(frozen=True)
class LinearFit:
    """Least-squares line ``y = slope · x + intercept``.

    Attributes
    ----------
    slope, intercept : float
        In the units of y per unit of x, and of y.
    r2 : float
        Coefficient of determination.
    n : int
        Points fitted.
    x_span : float
        Range of x covered.
    slope_stderr : float
        Standard error of the slope (NaN when unknown).
    """

    slope: float
    intercept: float
    r2: float
    n: int
    x_span: float
    slope_stderr: float = math.nan

    def to_dict(self) -> dict[str, Any]:
        return {
            "slope": _finite(self.slope),
            "intercept": _finite(self.intercept),
            "r2": _finite(self.r2),
            "n": self.n,
            "x_span": _finite(self.x_span),
            "slope_stderr": _finite(self.slope_stderr),
        }


def fit_line(x: np.ndarray, y: np.ndarray) -> LinearFit | None:
    """Best-fit line by :func:`scipy.stats.linregress`; None with < 3 points or constant x."""
    from scipy.stats import linregress

    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if len(x) < 3 or np.ptp(x) <= 0:
        return None
    fit = linregress(x, y)
    return LinearFit(
        float(fit.slope), float(fit.intercept), float(fit.rvalue**2), len(x), float(np.ptp(x)),
        float(fit.stderr),
    )


@dataclass(frozen=True)
class QualityFlag:
    """One of the paper's quality indicators, read for the user.

    Attributes
    ----------
    key : str
        ``"mean_residual"``, ``"slope_vs_path"`` or ``"slope_vs_trend"``.
    title : str
        Short name for displays.
    status : str
        ``"pass"``, ``"warn"`` or ``"n/a"`` (the data cannot test it: too few
        photos, too narrow a fan of view directions, or steep views).
    value, threshold : float or None
        The indicator and its limit.
    reading : str
        What it means, in plain language.
    """

    key: str
    title: str
    status: str
    value: float | None
    threshold: float
    reading: str

    def to_dict(self) -> dict[str, Any]:
        return {
            "key": self.key,
            "title": self.title,
            "status": self.status,
            "value": _finite(self.value),
            "threshold": self.threshold,
            "reading": self.reading,
        }


def _plus_minus(fit: LinearFit, fmt: str) -> str:
    """``"+0.2° ± 1.4°"``-style slope with its standard error (when known)."""
    text = format(fit.slope, fmt)
    if math.isfinite(fit.slope_stderr):
        text += " ± " + format(fit.slope_stderr, fmt.lstrip("+"))
    return text


def _untestable(fit: LinearFit | None, steep_deg: float | None, what: str) -> str | None:
    """Why a slope flag cannot be read (None when it can): too few photos or steep views."""
    if fit is None:
        return f"Too few photos, or no spread between them, to test {what}."
    if fit.n < MIN_SLOPE_PHOTOS:
        return f"Only {fit.n} photos: too few to test {what} (at least {MIN_SLOPE_PHOTOS})."
    if steep_deg is not None and steep_deg > STEEP_VIEW_PLUNGE_DEG:
        return (f"The photos look steeply down (median plunge {steep_deg:.0f}°): the sign of Δξ "
                f"is then noise, so its slope cannot test {what}; judge from the mean residual "
                "and the plot.")
    return None


def quality_flags(
    mean_abs_deg: float,
    path_fit: LinearFit | None,
    trend_fit: LinearFit | None,
    median_abs_plunge_deg: float | None = None,
    n_set_aside: int = 0,
) -> list[QualityFlag]:
    """The paper's three indicators as pass/warn flags with plain readings.

    Parameters
    ----------
    mean_abs_deg : float
        The larger of mean |Δξ| and mean |Δρ|, degrees.
    path_fit, trend_fit : LinearFit or None
        Δξ against position along the survey path (degrees per path
        length) and against measured trend (degrees per degree).
    median_abs_plunge_deg : float, optional
        Median |plunge| of the measured view directions, degrees; above
        :data:`STEEP_VIEW_PLUNGE_DEG` the slope flags are ``n/a``.
    n_set_aside : int
        Photos the estimator set aside as gross errors (not in the
        indicators); the mean residual's reading says so.

    Notes
    -----
    The slope flags are ``n/a`` with fewer than :data:`MIN_SLOPE_PHOTOS`
    photos, and the trend flag also when the photos face a range narrower
    than :data:`NARROW_TREND_SPAN_DEG` (see the module docstring).
    """
    flags = []
    slopes_readable = (
        _untestable(path_fit, median_abs_plunge_deg, "") is None
        or _untestable(trend_fit, median_abs_plunge_deg, "") is None
    )
    if mean_abs_deg < MEAN_RESIDUAL_MAX_DEG:
        reading = (
            f"Camera directions agree with the phone to {mean_abs_deg:.1f}° on average "
            f"(< {MEAN_RESIDUAL_MAX_DEG:g}°): a geometrically faithful model, oriented about "
            "as well as the phone's sensors allow."
        )
        status = "pass"
    else:
        status = "warn"
        cause = (
            f"above {DISTORTED_RESIDUAL_DEG:g}°, like the paper's distorted models"
            if mean_abs_deg > DISTORTED_RESIDUAL_DEG
            else f"faithful models stay below {MEAN_RESIDUAL_MAX_DEG:g}°"
        )
        reading = (
            f"Camera directions differ from the phone's by {mean_abs_deg:.1f}° on average "
            f"({cause}): the model is distorted or the phone's sensors were off; "
            + ("the two slopes tell which." if slopes_readable
               else "the slopes cannot tell which here (n/a below): look at the plots.")
        )
    if n_set_aside:
        # The mean is over the photos kept: a pass must not hide that many were dropped.
        reading += (f" Not counted: {n_set_aside} photo(s) set aside as gross errors "
                    "(listed with the result).")
    flags.append(
        QualityFlag(
            "mean_residual", "mean |Δξ|, |Δρ|", status, mean_abs_deg, MEAN_RESIDUAL_MAX_DEG,
            reading,
        )
    )

    why_not = _untestable(path_fit, median_abs_plunge_deg, "for doming")
    if why_not is not None:
        flags.append(
            QualityFlag("slope_vs_path", "Δξ vs survey path", "n/a",
                        None if path_fit is None else path_fit.slope, PATH_SLOPE_MAX, why_not)
        )
    else:
        s, r2 = path_fit.slope, path_fit.r2
        change = _plus_minus(path_fit, "+.1f").replace(" ±", "° ±")
        if abs(s) < PATH_SLOPE_MAX:
            reading = (
                f"No doming along the survey path: Δξ changes by {change}° from one end of "
                f"the path to the other (R² {r2:.2f}; bent models exceed ±{PATH_SLOPE_MAX:g}°)."
            )
            status = "pass"
        else:
            reading = (
                f"Doming along the survey path: Δξ changes by {change}° from one end of the "
                f"path to the other (R² {r2:.2f}), so the model is bent and its ends are "
                f"turned about ±{abs(s) / 2:.0f}° from true. Add oblique, convergent photos "
                "and more overlap, or use ground control."
            )
            status = "warn"
        flags.append(
            QualityFlag("slope_vs_path", "Δξ vs survey path", status, s, PATH_SLOPE_MAX, reading)
        )

    why_not = _untestable(trend_fit, median_abs_plunge_deg, "the compass")
    if why_not is None and trend_fit.x_span < NARROW_TREND_SPAN_DEG:
        # The phone's trend error sits on both axes of this plot: over a narrow
        # fan it alone makes a slope near 1, whatever the compass calibration.
        why_not = (
            f"The photos face a range of only {trend_fit.x_span:.0f}° "
            f"(< {NARROW_TREND_SPAN_DEG:g}°): too narrow to test the compass, as the phone's "
            f"own noise sets the slope (here {trend_fit.slope:+.2f}° per degree)."
        )
    if why_not is not None:
        flags.append(
            QualityFlag("slope_vs_trend", "Δξ vs measured trend", "n/a",
                        None if trend_fit is None else trend_fit.slope, TREND_SLOPE_MAX, why_not)
        )
    else:
        s, r2, span = trend_fit.slope, trend_fit.r2, trend_fit.x_span
        change = _plus_minus(trend_fit, "+.2f")
        if abs(s) <= TREND_SLOPE_MAX:
            reading = (
                f"Compass consistent: Δξ changes by {change}° per degree of view direction "
                f"(R² {r2:.2f}; ≤ {TREND_SLOPE_MAX:g} in calibrated surveys)."
            )
            status = "pass"
        else:
            reading = (
                f"Compass not calibrated: Δξ changes by {change}° per degree of view direction "
                f"(R² {r2:.2f}; calibrated phones give ≤ {TREND_SLOPE_MAX:g}), about "
                f"{abs(s) * span:.0f}° across the {span:.0f}° of directions photographed. "
                "Recalibrate the compass (figure-of-eight), switch on airplane mode, keep away "
                "from metal, and re-measure."
            )
            status = "warn"
        flags.append(
            QualityFlag(
                "slope_vs_trend", "Δξ vs measured trend", status, s, TREND_SLOPE_MAX, reading
            )
        )
    return flags
