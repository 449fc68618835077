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
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .estimate import _UP, _angle_between, _axes, _finite

__all__ = [
    "MEAN_RESIDUAL_MAX_DEG",
    "DISTORTED_RESIDUAL_DEG",
    "PATH_SLOPE_MAX",
    "TREND_SLOPE_MAX",
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
    """

    slope: float
    intercept: float
    r2: float
    n: int
    x_span: float

    def to_dict(self) -> dict[str, Any]:
        return {
            "slope": _finite(self.slope),
            "intercept": _finite(self.intercept),
            "r2": _finite(self.r2),
            "n": self.n,
            "x_span": _finite(self.x_span),
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
        float(fit.slope), float(fit.intercept), float(fit.rvalue**2), len(x), float(np.ptp(x))
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
        ``"pass"``, ``"warn"`` or ``"n/a"`` (too few photos to tell).
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


def quality_flags(
    mean_abs_deg: float, path_fit: LinearFit | None, trend_fit: LinearFit | None
) -> list[QualityFlag]:
    """The paper's three indicators as pass/warn flags with plain readings.

    Parameters
    ----------
    mean_abs_deg : float
        The larger of mean |Δξ| and mean |Δρ|, degrees.
    path_fit, trend_fit : LinearFit or None
        Δξ against position along the survey path (degrees per path
        length) and against measured trend (degrees per degree).
    """
    flags = []
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
            f"({cause}): the model is distorted or the phone's sensors were off; the two "
            "slopes tell which."
        )
    flags.append(
        QualityFlag(
            "mean_residual", "mean |Δξ|, |Δρ|", status, mean_abs_deg, MEAN_RESIDUAL_MAX_DEG,
            reading,
        )
    )

    if path_fit is None:
        flags.append(
            QualityFlag("slope_vs_path", "Δξ vs survey path", "n/a", None, PATH_SLOPE_MAX,
                        "Too few photos (or no spread along the path) to test for doming.")
        )
    else:
        s, r2 = path_fit.slope, path_fit.r2
        if abs(s) < PATH_SLOPE_MAX:
            reading = (
                f"No doming along the survey path: Δξ changes by {s:+.1f}° from one end of "
                f"the path to the other (R² {r2:.2f}; bent models exceed ±{PATH_SLOPE_MAX:g}°)."
            )
            status = "pass"
        else:
            reading = (
                f"Doming along the survey path: Δξ changes by {s:+.1f}° from one end of the "
                f"path to the other (R² {r2:.2f}), so the model is bent and its ends are "
                f"turned about ±{abs(s) / 2:.0f}° from true. Add oblique, convergent photos "
                "and more overlap, or use ground control."
            )
            status = "warn"
        flags.append(
            QualityFlag("slope_vs_path", "Δξ vs survey path", status, s, PATH_SLOPE_MAX, reading)
        )

    if trend_fit is None:
        flags.append(
            QualityFlag("slope_vs_trend", "Δξ vs measured trend", "n/a", None, TREND_SLOPE_MAX,
                        "Too few photos (or all facing one way) to test the compass.")
        )
    else:
        s, r2, span = trend_fit.slope, trend_fit.r2, trend_fit.x_span
        narrow = (
            f"; the photos face a range of only {span:.0f}°, so this is loosely constrained"
            if span < 20
            else ""
        )
        if abs(s) <= TREND_SLOPE_MAX:
            reading = (
                f"Compass consistent: Δξ changes by {s:+.2f}° per degree of view direction "
                f"(R² {r2:.2f}; ≤ {TREND_SLOPE_MAX:g} in calibrated surveys){narrow}."
            )
            status = "pass"
        else:
            reading = (
                f"Compass not calibrated: Δξ changes by {s:+.2f}° per degree of view direction "
                f"(R² {r2:.2f}; calibrated phones give ≤ {TREND_SLOPE_MAX:g}), about "
                f"{abs(s) * span:.0f}° across the {span:.0f}° of directions photographed"
                f"{narrow}. "
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
