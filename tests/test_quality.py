"""Quality (quality.py): the paper's seven metrics and weights, Q, grades, six rules, adaptation.

Kehl et al. (2018), "Statistical Evaluation and Communication": Q = Σ P_i·w_i
with P_i ∈ {+1, 0, −1} and weights 0.1 per image for the point counts, then
0.25, 0.25, 0.3, 0.3, 0.3, 0.3; six rules in descending priority. The
metric limits and grade bounds are read from the module (they are ours and may
be tuned); the weights and rule thresholds are the paper's and are asserted.
"""

from __future__ import annotations

import math

import pytest

from napari_imgreg.registration.params import RegistrationParams
from napari_imgreg.registration.quality import (
    GRADES,
    METRICS,
    REFERENCE_WIDTH_PX,
    adapt,
    classify,
    evaluate_rules,
    grade_of,
    metric_trend,
    quality_q,
)

BY_KEY = {m.key: m for m in METRICS}
KEYS = ["points_photo", "points_render", "feature_inliers", "correspondences_3d",
        "inlier_ratio_2d", "inliers_3d", "inlier_ratio_3d", "reprojection_error_px"]


def value_for(metric, cls: int, width: int = REFERENCE_WIDTH_PX) -> float:
    """A value of ``metric`` that classifies as ``cls`` (+1, 0, −1) at ``width``."""
    s = width / REFERENCE_WIDTH_PX if metric.scales_with_width else 1.0
    inf, sup = metric.inferior * s, metric.superior * s
    if cls == 1:
        return sup
    if cls == 0:
        return (inf + sup) / 2
    return inf * 2 if metric.lower_is_better else inf / 2


# ------------------------------------------------------------- the paper
def test_the_seven_metrics_and_the_papers_weights():
    assert [m.key for m in METRICS] == KEYS  # RESULT.json metric names, contract §4
    weights = {m.key: m.weight for m in METRICS}
    assert weights == {
        "points_photo": 0.1, "points_render": 0.1,  # (1) #points, 0.1 per image
        "feature_inliers": 0.25,  # (2)
        "correspondences_3d": 0.25,  # (3)
        "inlier_ratio_2d": 0.3,  # (4) r_in(feat)
        "inliers_3d": 0.3,  # (5)
        "inlier_ratio_3d": 0.3,  # (6) r_in(opt)
        "reprojection_error_px": 0.3,  # (7)
    }
    assert math.isclose(sum(weights.values()), 1.9)
    # Only the reprojection error is better when lower, and only it scales with width.
    assert [m.key for m in METRICS if m.lower_is_better] == ["reprojection_error_px"]
    assert [m.key for m in METRICS if m.scales_with_width] == ["reprojection_error_px"]
    assert REFERENCE_WIDTH_PX == 1632  # the paper's Nexus 5 photos
    for m in METRICS:  # superior is the better side of inferior
        assert (m.superior < m.inferior) if m.lower_is_better else (m.superior > m.inferior)


# -------------------------------------------------------------- classify
@pytest.mark.parametrize("key", KEYS)
def test_classify_boundaries(key):
    m = BY_KEY[key]
    inf, sup = m.inferior, m.superior
    eps = 1e-9 * max(1.0, abs(inf), abs(sup))
    if m.lower_is_better:
        assert classify(m, sup) == 1  # at the superior limit: superior
        assert classify(m, sup - 1.0) == 1
        assert classify(m, sup + eps) == 0
        assert classify(m, inf) == 0  # at the inferior limit: still normal
        assert classify(m, inf + eps) == -1
        assert classify(m, 10 * inf) == -1
    else:
        assert classify(m, sup) == 1
        assert classify(m, 10 * sup) == 1
        assert classify(m, sup - eps) == 0
        assert classify(m, inf) == 0
        assert classify(m, inf - eps) == -1
        assert classify(m, 0) == -1
    # Missing and NaN values are inferior.
    assert classify(m, None) == -1
    assert classify(m, float("nan")) == -1


def test_reprojection_error_limits_scale_with_image_width():
    m = BY_KEY["reprojection_error_px"]
    for width in (816, 1632, 3264, 4000):
        s = width / 1632
        assert classify(m, m.superior * s, width) == 1
        assert classify(m, m.superior * s * 1.001, width) == 0
        assert classify(m, m.inferior * s, width) == 0
        assert classify(m, m.inferior * s * 1.001, width) == -1
    # The same error is worse on a smaller photo.
    err = m.inferior * 1.5
    assert classify(m, err, 1632) == -1
    assert classify(m, err, 3264) == 0  # limits doubled at twice the width
    # Counts and ratios do not scale.
    n = BY_KEY["feature_inliers"]
    assert classify(n, n.superior, 400) == classify(n, n.superior, 8000) == 1


# ------------------------------------------------------------------- Q
def test_q_all_superior_is_1_9():
    assert quality_q({m.key: value_for(m, 1) for m in METRICS}) == pytest.approx(1.9)


def test_q_all_inferior_is_minus_1_9():
    assert quality_q({m.key: value_for(m, -1) for m in METRICS}) == pytest.approx(-1.9)
    assert quality_q({}) == pytest.approx(-1.9)  # nothing measured: all inferior


def test_q_all_normal_is_0():
    assert quality_q({m.key: value_for(m, 0) for m in METRICS}) == pytest.approx(0.0)


def test_q_of_a_mixed_set_by_hand():
    classes = {
        "points_photo": +1,  # +1 × 0.10 = +0.10
        "points_render": +1,  # +1 × 0.10 = +0.10
        "feature_inliers": 0,  #  0 × 0.25 =  0
        "correspondences_3d": -1,  # −1 × 0.25 = −0.25
        "inlier_ratio_2d": +1,  # +1 × 0.30 = +0.30
        "inliers_3d": 0,  #  0 × 0.30 =  0
        "inlier_ratio_3d": -1,  # −1 × 0.30 = −0.30
        "reprojection_error_px": +1,  # +1 × 0.30 = +0.30
    }  # Q = 0.10 + 0.10 + 0 − 0.25 + 0.30 + 0 − 0.30 + 0.30 = 0.25
    metrics = {k: value_for(BY_KEY[k], c) for k, c in classes.items()}
    assert {k: classify(BY_KEY[k], v) for k, v in metrics.items()} == classes
    assert quality_q(metrics) == pytest.approx(0.25)


def test_q_of_a_second_mixed_set_by_hand_at_another_width():
    # A 4896-px photo (3 × 1632): the reprojection limits are tripled.
    width = 4896
    classes = {
        "points_photo": -1,  # −0.10
        "points_render": 0,  #  0
        "feature_inliers": +1,  # +0.25
        "correspondences_3d": +1,  # +0.25
        "inlier_ratio_2d": -1,  # −0.30
        "inliers_3d": +1,  # +0.30
        "inlier_ratio_3d": 0,  #  0
        "reprojection_error_px": 0,  #  0
    }  # Q = −0.10 + 0 + 0.25 + 0.25 − 0.30 + 0.30 + 0 + 0 = 0.40
    metrics = {k: value_for(BY_KEY[k], c, width) for k, c in classes.items()}
    assert quality_q(metrics, width) == pytest.approx(0.40)
    # The same error at the reference width is inferior: 0.40 − 0.30 = 0.10.
    assert quality_q(metrics) == pytest.approx(0.10)


def test_q_missing_metric_counts_as_inferior():
    metrics = {m.key: value_for(m, 1) for m in METRICS}
    del metrics["inlier_ratio_3d"]  # 1.9 − 2 × 0.3
    assert quality_q(metrics) == pytest.approx(1.3)


# --------------------------------------------------------------- grades
def test_grades_are_five_ordered_bins_with_colours():
    assert [g.name for g in GRADES] == ["excellent", "good", "fair", "poor", "failed"]
    mins = [g.q_min for g in GRADES]
    assert mins == sorted(mins, reverse=True) and mins[-1] == float("-inf")
    assert len({g.color for g in GRADES}) == 5
    assert all(g.color.startswith("#") and len(g.color) == 7 for g in GRADES)
    assert all(g.text for g in GRADES)
    assert -1.9 < mins[-2] < mins[0] <= 1.9


def test_grade_of_boundaries():
    for upper, lower in zip(GRADES, GRADES[1:]):
        assert grade_of(upper.q_min) is upper  # a bin includes its lower bound
        assert grade_of(upper.q_min - 1e-9) is lower
    assert grade_of(1.9).name == "excellent"
    assert grade_of(-1.9).name == "failed"


def test_no_pose_is_failed_whatever_q():
    for q in (1.9, 0.5, -1.9):
        assert grade_of(q, pose_found=False).name == "failed"


# ---------------------------------------------------------------- rules
def base_metrics(**changes) -> dict:
    """A good registration (no rule fires) with some metrics changed."""
    m = {
        "points_photo": 4000, "points_render": 5000,
        "feature_inliers": 200, "correspondences_3d": 180,
        "inlier_ratio_2d": 0.6, "inliers_3d": 150, "inlier_ratio_3d": 0.8,
        "reprojection_error_px": 1.2,
    }
    m.update(changes)
    return m


RULE_CASES = [
    # (metrics, rules expected to fire, in priority order)
    pytest.param(base_metrics(), [], id="none"),
    pytest.param(base_metrics(points_photo=499), [1], id="1-photo"),
    pytest.param(base_metrics(points_render=120), [1], id="1-render"),
    pytest.param(base_metrics(points_photo=500, points_render=500), [], id="1-at-500"),
    pytest.param(base_metrics(feature_inliers=6, inlier_ratio_2d=0.3), [2], id="2"),
    pytest.param(base_metrics(feature_inliers=7, inlier_ratio_2d=0.3), [], id="2-at-7"),
    pytest.param(base_metrics(inliers_3d=6, inlier_ratio_3d=0.2), [3], id="3"),
    pytest.param(base_metrics(inliers_3d=7, inlier_ratio_3d=0.2), [], id="3-at-7"),
    pytest.param(base_metrics(inlier_ratio_2d=0.05), [4], id="4"),
    pytest.param(base_metrics(inlier_ratio_2d=0.1), [], id="4/5-at-0.1"),
    pytest.param(base_metrics(inlier_ratio_3d=0.05), [5], id="5"),
    pytest.param(base_metrics(inlier_ratio_3d=0.1), [], id="5/6-at-0.1"),
    pytest.param(base_metrics(reprojection_error_px=2.5), [6], id="6"),
    pytest.param(base_metrics(reprojection_error_px=2.0), [], id="6-at-2px"),
    # Realistic combinations: a few matches, nothing survives.
    pytest.param(base_metrics(points_photo=300, feature_inliers=3, correspondences_3d=3,
                              inlier_ratio_2d=0.02, inliers_3d=0, inlier_ratio_3d=0.0,
                              reprojection_error_px=None), [1, 2, 3, 4], id="1+2+3+4"),
    pytest.param(base_metrics(feature_inliers=5, correspondences_3d=5, inlier_ratio_2d=0.25,
                              inliers_3d=4, inlier_ratio_3d=0.8, reprojection_error_px=1.0),
                 [2, 3], id="2+3"),
    pytest.param(base_metrics(inliers_3d=5, inlier_ratio_3d=0.03, reprojection_error_px=3.0),
                 [3, 5], id="3+5"),
    pytest.param(base_metrics(feature_inliers=20, inlier_ratio_2d=0.05, inlier_ratio_3d=0.05,
                              reprojection_error_px=5.0), [4], id="4-blocks-5-and-6"),
]


@pytest.mark.parametrize("metrics, expected", RULE_CASES)
def test_rules_that_fire_in_priority_order(metrics, expected):
    hits = evaluate_rules(metrics, RegistrationParams())
    assert [h.rule for h in hits] == expected
    for h in hits:
        assert h.hint and h.adaptation and callable(h.apply)


def test_rule_6_limit_scales_with_width():
    m = base_metrics(reprojection_error_px=3.0)
    assert [h.rule for h in evaluate_rules(m, RegistrationParams(), 1632)] == [6]
    assert [h.rule for h in evaluate_rules(m, RegistrationParams(), 3264)] == []  # limit 4 px
    assert [h.rule for h in evaluate_rules(m, RegistrationParams(), 816)] == [6]  # limit 1 px
    m = base_metrics(reprojection_error_px=1.5)
    assert [h.rule for h in evaluate_rules(m, RegistrationParams(), 816)] == [6]


def test_rule_1_hint_names_the_count():
    hits = evaluate_rules(base_metrics(points_render=321), RegistrationParams())
    assert "321" in hits[0].hint and "500" in hits[0].hint


# ------------------------------------------------------------ adaptation
def diff(a: RegistrationParams, b: RegistrationParams) -> dict:
    """Changed fields, as {"section.field": (old, new)}."""
    out = {}
    da, db = a.to_dict(), b.to_dict()
    for key in da:
        if isinstance(da[key], dict):
            for sub in da[key]:
                if da[key][sub] != db[key][sub]:
                    out[f"{key}.{sub}"] = (da[key][sub], db[key][sub])
        elif da[key] != db[key]:
            out[key] = (da[key], db[key])
    return out


def adapted(metrics, params):
    before = params.to_dict()
    new, hit = adapt(metrics, params)
    assert params.to_dict() == before  # the input is left unchanged
    assert new is not params
    for part in ("photo_filters", "render_filters", "features", "pose"):
        assert getattr(new, part) is not getattr(params, part)
    return new, hit


def test_rule_1_lowers_the_threshold_and_keeps_more_points():
    p = RegistrationParams()
    p.features.threshold_scale, p.features.max_features = 1.0, 4000
    new, hit = adapted(base_metrics(points_photo=100), p)
    assert hit.rule == 1
    d = diff(p, new)
    assert set(d) == {"features.threshold_scale", "features.max_features"}
    assert new.features.threshold_scale < 1.0
    assert new.features.max_features > 4000


@pytest.mark.parametrize("rule, metrics", [
    (2, base_metrics(feature_inliers=4, inlier_ratio_2d=0.3)),
    (4, base_metrics(inlier_ratio_2d=0.05)),
])
def test_rules_2_and_4_climb_the_filter_ladder(rule, metrics):
    p = RegistrationParams()
    p.photo_filters.wallis = p.render_filters.wallis = False
    p.photo_filters.clahe = p.render_filters.clahe = False
    p.features.ratio = 0.8
    # Step 1: Wallis on the photo AND the render.
    p1, hit = adapted(metrics, p)
    assert hit.rule == rule and "Wallis" in hit.adaptation
    assert diff(p, p1) == {"photo_filters.wallis": (False, True),
                           "render_filters.wallis": (False, True)}
    # Step 2: then CLAHE on both.
    p2, hit = adapted(metrics, p1)
    assert hit.rule == rule and "CLAHE" in hit.adaptation
    assert diff(p1, p2) == {"photo_filters.clahe": (False, True),
                            "render_filters.clahe": (False, True)}
    # Step 3: then a looser ratio test.
    p3, hit = adapted(metrics, p2)
    assert hit.rule == rule and "ratio" in hit.adaptation
    d = diff(p2, p3)
    assert set(d) == {"features.ratio"} and p3.features.ratio > 0.8
    assert f"{p3.features.ratio:.2f}" in hit.adaptation


def test_filter_ladder_turns_wallis_on_for_both_when_only_one_has_it():
    p = RegistrationParams()
    p.photo_filters.wallis, p.render_filters.wallis = True, False
    new, hit = adapted(base_metrics(inlier_ratio_2d=0.05), p)
    assert new.photo_filters.wallis and new.render_filters.wallis
    assert diff(p, new) == {"render_filters.wallis": (False, True)}


def test_rule_3_doubles_the_pnp_threshold():
    p = RegistrationParams()
    p.pose.reprojection_error_px = 5.0
    new, hit = adapted(base_metrics(inliers_3d=3, inlier_ratio_3d=0.5), p)
    assert hit.rule == 3
    assert diff(p, new) == {"pose.reprojection_error_px": (5.0, 10.0)}
    assert "10.0" in hit.adaptation


def test_rule_5_raises_the_epipolar_threshold():
    p = RegistrationParams()
    p.features.geometric_threshold_px = 2.0
    new, hit = adapted(base_metrics(inlier_ratio_3d=0.05), p)
    assert hit.rule == 5
    d = diff(p, new)
    assert set(d) == {"features.geometric_threshold_px"}
    assert new.features.geometric_threshold_px > 2.0
    assert f"{new.features.geometric_threshold_px:.1f}" in hit.adaptation


def test_rule_6_lowers_the_epipolar_threshold_and_tightens_the_ratio():
    p = RegistrationParams()
    p.features.geometric_threshold_px, p.features.ratio = 4.0, 0.85
    new, hit = adapted(base_metrics(reprojection_error_px=3.5), p)
    assert hit.rule == 6
    d = diff(p, new)
    assert set(d) == {"features.geometric_threshold_px", "features.ratio"}
    assert new.features.geometric_threshold_px < 4.0
    assert new.features.ratio < 0.85
    assert f"{new.features.geometric_threshold_px:.1f}" in hit.adaptation
    assert f"{new.features.ratio:.2f}" in hit.adaptation


def test_adapt_acts_on_the_highest_priority_rule_only():
    p = RegistrationParams()
    m = base_metrics(points_photo=100, inliers_3d=2, inlier_ratio_3d=0.01)  # rules 1, 3, 5
    assert [h.rule for h in evaluate_rules(m, p)] == [1, 3, 5]
    new, hit = adapted(m, p)
    assert hit.rule == 1
    assert set(diff(p, new)) == {"features.threshold_scale", "features.max_features"}


def test_adapt_without_a_rule_returns_an_equal_copy():
    p = RegistrationParams()
    p.features.ratio = 0.77
    new, hit = adapted(base_metrics(), p)
    assert hit is None
    assert new == p and diff(p, new) == {}


def test_repeated_adaptation_stays_within_the_documented_ranges():
    # Documented ranges: threshold_scale 0.05–4, max_features ≤ 50 000, ratio 0.5–0.95,
    # geometric threshold 0.5–20 px, PnP threshold 1–50 px.
    p = RegistrationParams()
    for metrics in (base_metrics(points_photo=10), base_metrics(inliers_3d=1, inlier_ratio_3d=0.5),
                    base_metrics(inlier_ratio_3d=0.01), base_metrics(reprojection_error_px=9.0),
                    base_metrics(inlier_ratio_2d=0.01)):
        q = p
        for _ in range(30):
            q, _ = adapt(metrics, q)
        f = q.features
        assert 0.05 <= f.threshold_scale <= 4 and f.max_features <= 50_000
        assert 0.5 <= f.ratio <= 0.95 and 0.5 <= f.geometric_threshold_px <= 20
        assert 1 <= q.pose.reprojection_error_px <= 50


def test_metric_trend_knows_which_way_is_better():
    count = next(m for m in METRICS if m.key == "inliers_3d")
    error = next(m for m in METRICS if m.key == "reprojection_error_px")
    assert metric_trend(count, 40, 20) == 1 and metric_trend(count, 10, 20) == -1
    assert metric_trend(error, 0.8, 2.0) == 1 and metric_trend(error, 3.0, 2.0) == -1
    assert metric_trend(count, 20, 20) == 0
    assert metric_trend(error, None, 2.0) == -1 and metric_trend(error, 1.0, None) == 1
    assert metric_trend(error, None, None) == 0
