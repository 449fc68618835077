"""Registration quality: the seven metrics, Q, five grades, six rules, adaptation.

After Kehl et al. (2018), "Statistical Evaluation and Communication". Each
metric is classed superior (+1), normal (0) or inferior (−1) against the
limits below; ``Q = Σ P_i · w_i`` with the paper's weights (0.1 per image for
the point counts, then 0.25, 0.25, 0.3, 0.3, 0.3, 0.3), so Q lies in
[−1.9, 1.9]. The six heuristic rules, in the paper's priority order, give the
hint text and the parameter change for the next trial.

The paper gives the weights and the rule thresholds; the superior limits and
the grade boundaries are ours, documented here and in ``docs/method.md``.
Pixel limits refer to a 1632-pixel-wide photo (the paper's camera) and scale
with the photo's width.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

from .params import RegistrationParams

__all__ = [
    "Metric",
    "METRICS",
    "GRADES",
    "Grade",
    "RuleHit",
    "classify",
    "quality_q",
    "grade_of",
    "evaluate_rules",
    "adapt",
    "metric_trend",
    "REFERENCE_WIDTH_PX",
]

REFERENCE_WIDTH_PX = 1632


@dataclass(frozen=True)
class Metric:
    """One quality metric and its limits.

    Attributes
    ----------
    key : str
        Field name in RESULT.json ``metrics``.
    label : str
        Short text for the GUI.
    weight : float
        Quality weight w_i.
    inferior : float
        Below this (above, for an error) the metric is inferior (−1).
    superior : float
        At or above this (at or below, for an error) it is superior (+1).
    lower_is_better : bool
        True for the reprojection error.
    """

    key: str
    label: str
    weight: float
    inferior: float
    superior: float
    lower_is_better: bool = False
    scales_with_width: bool = False


METRICS: tuple[Metric, ...] = (
    Metric("points_photo", "points (photo)", 0.10, 500, 2000),
    Metric("points_render", "points (render)", 0.10, 500, 2000),
    Metric("feature_inliers", "feature inliers", 0.25, 7, 60),
    Metric("correspondences_3d", "correspondences in 3D", 0.25, 7, 50),
    Metric("inlier_ratio_2d", "inlier ratio 2D", 0.30, 0.1, 0.4),
    Metric("inliers_3d", "3D inliers", 0.30, 7, 40),
    Metric("inlier_ratio_3d", "inlier ratio 3D", 0.30, 0.1, 0.5),
    Metric("reprojection_error_px", "reprojection error (px)", 0.30, 4.0, 1.0,
           lower_is_better=True, scales_with_width=True),
)


@dataclass(frozen=True)
class Grade:
    """One of the five overall grades: Q at or above ``q_min``."""

    name: str
    q_min: float
    color: str
    text: str


#: Best first. Q ranges: excellent [1.2, 1.9], good [0.6, 1.2), fair [0, 0.6),
#: poor [−0.6, 0), failed [−1.9, −0.6) — and "failed" whenever no pose was found.
GRADES: tuple[Grade, ...] = (
    Grade("excellent", 1.2, "#1a9850", "registered; use it"),
    Grade("good", 0.6, "#91cf60", "registered; check the overlay"),
    Grade("fair", 0.0, "#fee08b", "uncertain; inspect before mapping"),
    Grade("poor", -0.6, "#fc8d59", "doubtful; adapt the parameters"),
    Grade("failed", float("-inf"), "#d73027", "not registered"),
)


def _limit(metric: Metric, image_width: int) -> tuple[float, float]:
    if metric.scales_with_width:
        s = image_width / REFERENCE_WIDTH_PX
        return metric.inferior * s, metric.superior * s
    return metric.inferior, metric.superior


def classify(metric: Metric, value: float | None, image_width: int = REFERENCE_WIDTH_PX) -> int:
    """+1 superior, 0 normal, −1 inferior (missing or NaN values are inferior)."""
    if value is None or value != value:  # NaN
        return -1
    inferior, superior = _limit(metric, image_width)
    if metric.lower_is_better:
        return 1 if value <= superior else (-1 if value > inferior else 0)
    return 1 if value >= superior else (-1 if value < inferior else 0)


def quality_q(metrics: dict, image_width: int = REFERENCE_WIDTH_PX) -> float:
    """Q = Σ P_i · w_i over the seven metrics (both point counts weighted 0.1)."""
    return round(
        sum(m.weight * classify(m, metrics.get(m.key), image_width) for m in METRICS), 6
    )


def grade_of(q: float, pose_found: bool = True) -> Grade:
    """The grade for a Q value; "failed" when there is no pose at all."""
    if not pose_found:
        return GRADES[-1]
    for grade in GRADES:
        if q >= grade.q_min:
            return grade
    return GRADES[-1]


#: Why a grade is not enough when the photo did not register (its error
#: estimate, or the verification, said no).
_UNREGISTERED_GRADE = {"fair": "uncertain", "poor": "doubtful"}


def outcome_words(status: str, grade: str) -> str:
    """A registration's grade in words that agree with its status.

    ``"grade good"`` for a registered photo; one that did not register says
    that its grade is its best trial's and why that is not enough: ``"best
    trial fair (uncertain)"``, ``"best trial excellent (not verified)"``,
    ``"best trial failed"``. RESULT.json keeps ``status`` and ``grade`` as
    they are; this is what is printed and shown beside them.

    Examples
    --------
    >>> outcome_words("failed", "fair")
    'best trial fair (uncertain)'
    """
    if status == "registered":
        return f"grade {grade}"
    if grade == "failed":
        return "best trial failed"
    return f"best trial {grade} ({_UNREGISTERED_GRADE.get(grade, 'not verified')})"


@dataclass(frozen=True)
class RuleHit:
    """A rule that fired: its number (1–6 = priority), hint and adaptation."""

    rule: int
    hint: str
    adaptation: str
    apply: Callable[[RegistrationParams], RegistrationParams]


def _more_points(p: RegistrationParams) -> RegistrationParams:
    p = p.copy()
    p.features.threshold_scale = max(0.05, p.features.threshold_scale * 0.5)
    p.features.max_features = min(30_000, int(p.features.max_features * 1.5))
    return p


def _filter_step(p: RegistrationParams) -> RegistrationParams:
    """The next step of the radiometric ladder: Wallis, then CLAHE, then a looser ratio."""
    p = p.copy()
    if not (p.photo_filters.wallis and p.render_filters.wallis):
        p.photo_filters.wallis = p.render_filters.wallis = True
    elif not (p.photo_filters.clahe and p.render_filters.clahe):
        p.photo_filters.clahe = p.render_filters.clahe = True
    else:
        p.features.ratio = min(0.95, p.features.ratio + 0.05)
    return p


def _filter_step_text(p: RegistrationParams) -> str:
    if not (p.photo_filters.wallis and p.render_filters.wallis):
        return "Wallis filter on photo and render"
    if not (p.photo_filters.clahe and p.render_filters.clahe):
        return "CLAHE on photo and render"
    return f"ratio test relaxed to {min(0.95, p.features.ratio + 0.05):.2f}"


def _relax_pnp(p: RegistrationParams) -> RegistrationParams:
    p = p.copy()
    p.pose.reprojection_error_px = min(40.0, p.pose.reprojection_error_px * 2)
    return p


def _relax_epipolar(p: RegistrationParams) -> RegistrationParams:
    p = p.copy()
    p.features.geometric_threshold_px = min(12.0, p.features.geometric_threshold_px * 1.5)
    return p


def _stricter(p: RegistrationParams) -> RegistrationParams:
    p = p.copy()
    p.features.geometric_threshold_px = max(0.5, p.features.geometric_threshold_px * 0.6)
    p.features.ratio = max(0.6, p.features.ratio - 0.05)
    return p


def evaluate_rules(
    metrics: dict, params: RegistrationParams, image_width: int = REFERENCE_WIDTH_PX
) -> list[RuleHit]:
    """The rules that fire, in the paper's priority order (first = the one to act on).

    Parameters
    ----------
    metrics : dict
        RESULT.json ``metrics`` of a trial.
    params : RegistrationParams
        The trial's parameters (the adaptation texts name the new values).
    image_width : int
        Photo width, pixels (scales the reprojection-error limit of rule 6).
    """
    hits: list[RuleHit] = []
    pts = min(metrics.get("points_photo", 0) or 0, metrics.get("points_render", 0) or 0)
    inl2 = metrics.get("feature_inliers", 0) or 0
    inl3 = metrics.get("inliers_3d", 0) or 0
    r2 = metrics.get("inlier_ratio_2d", 0.0) or 0.0
    r3 = metrics.get("inlier_ratio_3d", 0.0) or 0.0
    err = metrics.get("reprojection_error_px")
    err_limit = 2.0 * image_width / REFERENCE_WIDTH_PX
    f = params.features
    if pts < 500:
        hits.append(RuleHit(
            1,
            f"Too few salient points ({pts} < 500 in the photo or the render): "
            "lower the detection threshold and keep more points.",
            f"detector threshold ×0.5 (scale {max(0.05, f.threshold_scale * 0.5):.2f}), "
            f"max features {min(30_000, int(f.max_features * 1.5))}",
            _more_points,
        ))
    if inl2 < 7:
        hits.append(RuleHit(
            2,
            f"Too few correct correspondences ({inl2} feature inliers < 7): the photo and "
            "the render differ too much radiometrically; filter the images.",
            _filter_step_text(params),
            _filter_step,
        ))
    if inl3 < 7:
        hits.append(RuleHit(
            3,
            f"Too few 3D inliers after RANSAC EPnP ({inl3} < 7): the reprojection "
            "constraint is too strict, or the matches are scattered at random.",
            f"PnP reprojection threshold {min(40.0, params.pose.reprojection_error_px * 2):.1f} px",
            _relax_pnp,
        ))
    if r2 < 0.1:
        hits.append(RuleHit(
            4,
            f"Feature inlier ratio {_num(r2, '<', 0.1)} < 0.1: many false correspondences, likely from "
            "illumination differences; filter the images.",
            _filter_step_text(params),
            _filter_step,
        ))
    if r2 > 0.1 and r3 < 0.1:
        # A ratio of a handful of matches says little: say so (a photo of
        # another place keeps 8 of 17 chance matches, "ratio 0.47").
        few = (f", but of only {inl2} matches: perhaps chance ones, from a start far off"
               if inl2 < 20 else "")
        hits.append(RuleHit(
            5,
            f"2D correspondences are good (ratio {_num(r2, '>', 0.1)}{few}) but few survive the "
            f"pose (3D ratio {_num(r3, '<', 0.1)} < 0.1): features are badly localised; relax the "
            "epipolar constraint slightly.",
            f"epipolar threshold {min(12.0, f.geometric_threshold_px * 1.5):.1f} px",
            _relax_epipolar,
        ))
    if r2 > 0.1 and r3 > 0.1 and err is not None and err > err_limit:
        hits.append(RuleHit(
            6,
            f"The pose is probably right but imprecise (reprojection error "
            f"{_num(err, '>', err_limit)} px > {_num(err_limit, '<', err)} px): impose stricter correspondence constraints.",
            f"epipolar threshold {max(0.5, f.geometric_threshold_px * 0.6):.1f} px, "
            f"ratio {max(0.6, f.ratio - 0.05):.2f}",
            _stricter,
        ))
    return hits


def _num(value: float, op: str, other: float, decimals: int = 2) -> str:
    """``value`` with the fewest decimals (from ``decimals``, at most 6) that
    keep ``value op other`` true once both are printed so.

    A hint must not read "1.27 px > 1.3": the rounded numbers would say the
    opposite of the comparison that fired the rule.

    >>> _num(1.2849, ">", 1.2806), _num(1.2806, "<", 1.2849)
    ('1.285', '1.281')
    >>> _num(0.0996, "<", 0.1)
    '0.0996'
    >>> _num(2.5, ">", 1.28)
    '2.50'
    """
    for d in range(decimals, 7):
        a, b = round(value, d), round(other, d)
        if (a > b) if op == ">" else (a < b):
            return f"{value:.{d}f}"
    return f"{value:.6g}"


def adapt(
    metrics: dict, params: RegistrationParams, image_width: int = REFERENCE_WIDTH_PX
) -> tuple[RegistrationParams, RuleHit | None]:
    """Parameters for the next trial: the adaptation of the highest-priority rule.

    Returns
    -------
    params : RegistrationParams
        A new object (``params`` is not modified); unchanged when no rule fires.
    rule : RuleHit or None
    """
    hits = evaluate_rules(metrics, params, image_width)
    if not hits:
        return params.copy(), None
    return hits[0].apply(params), hits[0]


def metric_trend(metric: Metric, value: float | None, previous: float | None) -> int:
    """Whether a metric got better (+1), worse (−1) or stayed (0) since the previous trial.

    For the quality panel's arrows.

    Parameters
    ----------
    metric : Metric
        Knows whether lower is better (the reprojection error).
    value, previous : float or None
        A missing (None/NaN) value is the worst possible.

    Examples
    --------
    >>> error = next(m for m in METRICS if m.key == "reprojection_error_px")
    >>> metric_trend(error, 0.8, 2.0), metric_trend(error, None, 2.0)
    (1, -1)
    """
    def known(v) -> bool:
        return v is not None and v == v

    if not known(value) and not known(previous):
        return 0
    if not known(previous):
        return 1
    if not known(value):
        return -1
    if math.isclose(float(value), float(previous), rel_tol=1e-9, abs_tol=1e-12):
        return 0
    up = float(value) > float(previous)
    return (-1 if up else 1) if metric.lower_is_better else (1 if up else -1)
