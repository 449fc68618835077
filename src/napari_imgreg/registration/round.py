"""One registration round — render → match → lift → pose → metrics — and the trial it makes.

Every pose the package scores goes through here: the automatic keypoint
rounds and the area (block-correlation) rounds of
:mod:`napari_imgreg.registration.pipeline`, and the scoring of a hand-made
pose (:func:`napari_imgreg.registration.manual.score_pose`).

* :func:`match_round` renders the model from a pose at the matching width,
  matches the (filtered) photo against the render — keypoints, or render
  blocks found by correlation — and lifts the render's matched points to 3D
  through its ``xyz`` map.
* :func:`pose_round` either *solves* the photo's pose from those 2D–3D
  correspondences (RANSAC EPnP) or *tests* a given pose against them, and
  counts the round's metrics. :func:`score_round` is the two in a row.
* :func:`trial_from_round` turns a trial's last round into a :class:`Trial`:
  the verification (photo and render points coincide), Q, the grade — capped
  for an unverified pose (:func:`grade_pose`) — and the hints; with the
  photo's camera also the pose's ``uncertainty``, an error estimate by
  cross-validation over halves of the image
  (:mod:`napari_imgreg.registration.uncertainty`), which a verified pose must
  keep below :data:`~napari_imgreg.registration.uncertainty.UNCERTAIN_PX`.

Conventions are the package's: pixels (x = column, y = row) with the first
pixel's centre at (0, 0); matching happens at reduced resolution, points are
reported and poses solved at the photo's full resolution.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from time import perf_counter
from typing import Protocol

import cv2
import numpy as np

from ..camera import Intrinsics, Pose, match_scale, pixels_to_full
from .features import (
    Features,
    detect_and_describe,
    match_features,
    match_guided,
)
from .filters import apply_filters, illumination_invariant
from .lidar_views import lidar_view_matches
from .params import RegistrationParams
from .pose import PoseEstimate, PoseParams, estimate_pose, pose_agreement, reprojection_errors
from .quality import (
    REFERENCE_WIDTH_PX,
    Grade,
    evaluate_rules,
    grade_of,
    quality_q,
)
from .stages.area import match_blocks, prepare_render
from .uncertainty import (
    Uncertainty,
    UncertaintyParams,
    estimate_uncertainty,
    frame_points,
)
from ..render import RenderResult

__all__ = [
    "Correspondences",
    "Trial",
    "Round",
    "MatchedRound",
    "RoundSource",
    "score_round",
    "match_round",
    "pose_round",
    "trial_from_round",
    "round_metrics",
    "residual_flow",
    "image_shift",
    "grade_pose",
    "VERIFY_FLOW_PX",
    "MIN_VERIFIED_INLIERS",
    "UNVERIFIED_Q_CEILING",
    "STAGE_Q_CEILING",
]

#: Median residual flow (px at 1632 px width) between the photo's and the final
#: render's matched keypoints below which a converged pose counts as verified.
VERIFY_FLOW_PX = 2.5
#: 3D inliers a verified pose needs at the least.
MIN_VERIFIED_INLIERS = 15
#: An unverified keypoint pose is graded as if its Q were at most this: "fair" at best.
UNVERIFIED_Q_CEILING = 0.59
#: The same for an unverified area-matching pose, whose block counts (the
#: "points") are high whatever the photo shows, and for a pose that only an
#: edge or mutual-information optimum supports (it can be a wrong pose):
#: "poor" at best.
STAGE_Q_CEILING = -0.01


@dataclass
class Correspondences:
    """The last round's matches, for drawing (pixels at full resolution).

    Attributes
    ----------
    photo_points, render_points : (M, 2) arrays
        Putative matches (after ratio and symmetry tests).
    feature_inlier : (M,) bool
        Passed the geometric verification.
    lifted : (M,) bool
        Has a 3D point.
    pose_inlier : (M,) bool
        Agrees with the estimated pose.
    xyz : (M, 3) array, optional
        The render keypoints' 3D points (NaN where not lifted).
    """

    photo_points: np.ndarray
    render_points: np.ndarray
    feature_inlier: np.ndarray
    lifted: np.ndarray
    pose_inlier: np.ndarray
    xyz: np.ndarray | None = None


@dataclass
class Trial:
    """One trial: its parameters, metrics, score and outcome."""

    index: int
    params: RegistrationParams
    metrics: dict
    q: float
    grade: str
    hints: list[str]
    pose: Pose | None
    start_pose: Pose
    rounds: int
    converged: bool
    verified: bool
    residual_flow_px: float
    adaptation: str = ""
    origin: str = "prior"
    seconds: float = 0.0
    correspondences: Correspondences | None = None
    render_mode: str = "plain"
    #: "keypoints" (detected and described features) or "area" (render
    #: blocks found in the photo by correlation, :mod:`napari_imgreg.registration.stages.area`).
    matcher: str = "keypoints"
    #: The pose's expected error by cross-validation (RESULT.json ``uncertainty``);
    #: None when not estimated (no pose, or a pose scored without the camera).
    uncertainty: Uncertainty | None = None
    #: The camera the pose goes with: the photo's, or the one estimated with
    #: the pose when its focal length is unknown (``estimated`` lists what).
    #: None: the photo's camera, unchanged (a pose scored without the camera).
    intrinsics: Intrinsics | None = None

    @property
    def biased(self) -> bool:
        """The keypoints agree on a pose, but poses from separate halves of the
        photo do not (the uncertainty gate fired): the matches share a bias,
        e.g. shading under another sun, that more keypoint trials share too."""
        return bool(self.pose is not None and self.matcher == "keypoints"
                    and self.metrics.get("inliers_3d", 0) >= MIN_VERIFIED_INLIERS
                    and self.uncertainty is not None
                    and self.intrinsics is not None
                    and not self.uncertainty.is_small(self.intrinsics.width))

    def to_dict(self) -> dict:
        return {
            "index": self.index,
            "origin": self.origin,
            "render_mode": self.render_mode,
            "matcher": self.matcher,
            "params": self.params.to_dict(),
            "metrics": self.metrics,
            "Q": self.q,
            "grade": self.grade,
            "hints": self.hints,
            "rounds": self.rounds,
            "converged": self.converged,
            "verified": self.verified,
            "residual_flow_px": self.residual_flow_px,
            "adaptation": self.adaptation,
            "pose": None if self.pose is None else self.pose.to_dict(),
            "uncertainty": None if self.uncertainty is None else self.uncertainty.to_dict(),
            "seconds": round(self.seconds, 3),
        }


@dataclass
class MatchedRound:
    """A round's matches lifted to 3D, before any pose (:func:`match_round`).

    Attributes
    ----------
    photo_points, render_points : (M, 2) arrays
        Putative matches, pixels at the photo's full resolution.
    feature_inlier : (M,) bool array
        Passed the geometric check (blocks: correlate clearly).
    lifted : (M,) bool array
        Has a 3D point, and passed the check.
    xyz : (M, 3) array
        The render points' model-frame points, metres (NaN where not lifted).
    points_photo, points_render : int
        Keypoints detected in each image (blocks searched, for area matching).
    rendered : RenderResult
        The render matched, at the matching width.
    extra_metrics : dict
        Added to the round's metrics (area matching: width and search radius).
    """

    photo_points: np.ndarray
    render_points: np.ndarray
    feature_inlier: np.ndarray
    lifted: np.ndarray
    xyz: np.ndarray
    points_photo: int
    points_render: int
    rendered: RenderResult
    extra_metrics: dict


@dataclass
class Round:
    """What one round found.

    Attributes
    ----------
    estimate : PoseEstimate
        The pose solved from the correspondences, or the given pose tested
        against them (``score_round(..., solve=False)``).
    metrics : dict
        The round's metrics under their RESULT.json names (the trial adds
        ``residual_flow_px``).
    correspondences : Correspondences
        With the 3D points.
    rendered : RenderResult
        The render matched, at the matching width.
    """

    estimate: PoseEstimate
    metrics: dict
    correspondences: Correspondences
    rendered: RenderResult


class RoundSource(Protocol):
    """What a round reads besides the pose: the photo at any width, renders, time spent.

    :class:`napari_imgreg.registration.pipeline._Context` is the one
    implementation; it caches the reduced photo and its features across the
    rounds and trials of one photo.
    """

    #: The photo's camera, at full resolution.
    intrinsics: Intrinsics
    #: Seconds spent per step ("render", "filter", "detect_match", "lift_3d", "pose", ...).
    timings: dict[str, float]

    def check(self) -> None:
        """Raise :class:`~napari_imgreg.registration.pipeline.Cancelled` when cancelled."""

    def render(self, pose: Pose, scale: float, mode: str = "plain") -> RenderResult:
        """The model from ``pose`` at ``scale`` times the photo's resolution."""

    def photo_at(self, width: int) -> tuple[np.ndarray, float]:
        """The photo reduced to ``width`` (never enlarged) and the scale used."""

    def photo_features(self, params: RegistrationParams, width: int,
                       invariant: bool = False) -> Features:
        """The filtered photo's features at ``width`` (with the invariant channel's)."""

    def area_photo(self, photo_small: np.ndarray, sigma_px: float) -> np.ndarray:
        """The photo band-passed for area matching at ``photo_small``'s size."""


def lit_as(render_mode: str, metrics: dict) -> str:
    """The light of the render a round matched: ``render_mode``, or for "auto"
    the one :func:`score_round` kept ("sunlit" or "plain", from the round's
    ``area_residual_*_px`` metrics)."""
    if render_mode != "auto":
        return render_mode
    sunlit = metrics.get("area_residual_sunlit_px")
    unlit = metrics.get("area_residual_unlit_px")
    return "plain" if unlit is not None and (sunlit is None or unlit < sunlit) else "sunlit"


def _median_residual(r: Round, intrinsics: Intrinsics) -> float | None:
    """Median reprojection error of a round's pose inliers, px at full resolution
    (None without a pose)."""
    corr = r.correspondences
    if not r.estimate.ok or corr.xyz is None or not corr.pose_inlier.any():
        return None
    inl = corr.pose_inlier
    return float(np.median(reprojection_errors(r.estimate.intrinsics or intrinsics,
                                                r.estimate.pose, corr.xyz[inl],
                                                corr.photo_points[inl])))


def match_round(
    source: RoundSource,
    pose: Pose,
    params: RegistrationParams,
    width: int,
    *,
    matcher: str = "keypoints",
    near: bool = False,
    search_px: int | None = None,
    mode: str = "plain",
) -> MatchedRound:
    """A round's first half: render from ``pose``, match the photo against it, lift to 3D.

    Parameters
    ----------
    source : RoundSource
        The photo, its camera and the renderer.
    pose : Pose
        ``cam_from_world`` to render from.
    params : RegistrationParams
        Filters and features (or ``params.area`` for blocks).
    width : int
        Matching width, pixels (the photo's own when smaller).
    matcher : {"keypoints", "area"}
        Detected and described keypoints, or render blocks found in the photo
        by normalised correlation (:mod:`napari_imgreg.registration.stages.area`).
    near : bool
        Keypoints: the render is from a pose close to the photo's (estimated in
        this trial, or picked by hand), so it looks much like the photo. The
        luminance features then suffice (the illumination-invariant channel is
        for distant starts), and with ``guided_radius_px`` > 0 they are matched
        only near the same place (:func:`~napari_imgreg.registration.features.match_guided`).
    search_px : int
        Area matching: search radius, pixels at the round's width (required).
    mode : str
        Render mode of ``source.render`` ("plain" or "sunlit").

    Returns
    -------
    MatchedRound
    """
    timings = source.timings
    scale = match_scale(source.intrinsics.width, width)
    rendered = source.render(pose, scale, mode)
    source.check()
    extra: dict = {}
    if matcher == "keypoints":
        fp = params.features
        guided = near and fp.guided_radius_px > 0
        invariant = fp.invariant_channel and not near
        photo_feats = source.photo_features(params, width, invariant)
        source.check()
        t0 = perf_counter()
        # Keypoints on the rim of the surface sit on a depth edge: detect inside it.
        mask = cv2.erode(rendered.mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        gray = apply_filters(rendered.rgb, params.render_filters, mask=rendered.mask)
        inv = illumination_invariant(rendered.rgb, rendered.mask) if invariant else None
        t1 = perf_counter()
        render_feats = detect_and_describe(gray, fp, mask=mask, color=rendered.rgb)
        if inv is not None:
            render_feats = Features.concat([render_feats, detect_and_describe(inv, fp, mask=mask)])
        if guided:
            matches = match_guided(photo_feats, render_feats, fp)
        else:
            matches = match_features(photo_feats, render_feats, fp)
        t2 = perf_counter()
        timings["filter"] += t1 - t0
        timings["detect_match"] += t2 - t1
        source.check()
        inlier = matches.inlier
        photo_small = photo_feats.points[matches.idx_a] if len(matches) else np.zeros((0, 2))
        render_small = render_feats.points[matches.idx_b] if len(matches) else np.zeros((0, 2))
        n_points_photo, n_points_render = len(photo_feats), len(render_feats)
        scene = getattr(source, "scene", None)
        if params.lidar_views and getattr(scene, "is_cloud", False):
            # Seed 003's reflectivity and wireframe pairs join the keypoints
            # (lidar_views.lidar_view_matches); RegistrationParams.lidar_views gates them.
            t0 = perf_counter()
            photo_rgb, _ = source.photo_at(width)
            lv = lidar_view_matches(scene, photo_rgb, rendered,
                                    params.lidar, fp,
                                    getattr(source, "lidar_cache", None))
            timings["lidar_views"] = timings.get("lidar_views", 0.0) + perf_counter() - t0
            photo_small = np.vstack([photo_small, lv.photo_points])
            render_small = np.vstack([render_small, lv.render_points])
            inlier = np.concatenate([inlier, lv.inlier])
            n_points_photo += lv.points_photo
            n_points_render += lv.points_render
            extra = {"lidar_view_matches": len(lv), "lidar_view_inliers_2d": int(lv.inlier.sum())}
            source.check()
    elif matcher == "area":
        if search_px is None:
            raise ValueError("area matching needs search_px")
        ap = params.area
        t0 = perf_counter()
        photo_small_rgb, _ = source.photo_at(width)
        if photo_small_rgb.shape[:2] != rendered.shape:
            photo_small_rgb = cv2.resize(photo_small_rgb, (rendered.shape[1], rendered.shape[0]),
                                         interpolation=cv2.INTER_AREA)
        photo_bp = source.area_photo(photo_small_rgb, ap.band_sigma_px)
        render_bp = prepare_render(rendered.rgb, rendered.mask, ap.band_sigma_px)
        blocks = match_blocks(photo_bp, render_bp, rendered.mask, template_px=ap.template_px,
                              search_px=search_px, stride_px=ap.stride_px,
                              min_score=ap.min_score, max_second_ratio=ap.max_second_ratio,
                              min_texture=ap.min_texture, min_coverage=ap.min_coverage)
        timings["area"] = timings.get("area", 0.0) + perf_counter() - t0
        source.check()
        inlier = blocks.accepted
        photo_small, render_small = blocks.photo_points, blocks.render_points
        n_points_photo = n_points_render = blocks.n_blocks
        extra = {"area_width_px": int(rendered.shape[1]), "area_search_px": int(search_px)}
    else:
        raise ValueError(f"unknown matcher {matcher!r} (keypoints or area)")

    t0 = perf_counter()
    xyz, lifted = rendered.lift(render_small)
    lifted &= inlier
    timings["lift_3d"] += perf_counter() - t0
    return MatchedRound(
        photo_points=pixels_to_full(photo_small, scale),
        render_points=pixels_to_full(render_small, scale),
        feature_inlier=inlier, lifted=lifted, xyz=xyz, points_photo=n_points_photo,
        points_render=n_points_render, rendered=rendered, extra_metrics=extra)


def pose_round(
    matched: MatchedRound,
    intrinsics: Intrinsics,
    params: PoseParams,
    given_pose: Pose | None = None,
    timings: dict[str, float] | None = None,
    rng_seed: int = 0,
) -> Round:
    """A round's second half: the pose from the lifted matches, and the round's metrics.

    Parameters
    ----------
    matched : MatchedRound
    intrinsics : Intrinsics
        The photo's camera, full resolution.
    params : PoseParams
        RANSAC EPnP settings (or, with ``solver``, the unknown-focal solver's,
        whose estimate then carries the solved camera); their threshold also
        decides a given pose's inliers.
    given_pose : Pose, optional
        Test this pose against the correspondences
        (:func:`~napari_imgreg.registration.pose.pose_agreement`) instead of
        solving one (:func:`~napari_imgreg.registration.pose.estimate_pose`):
        the same metrics, for a hand-made pose.
    timings : dict, optional
        Its ``"pose"`` entry gets the seconds spent.
    rng_seed : int
        Seed of RANSAC (``RegistrationParams.seed``).

    Returns
    -------
    Round
    """
    m = matched
    t0 = perf_counter()
    if given_pose is None:
        # An unknown focal length is estimated with the pose (params.solver "auto").
        estimate = estimate_pose(intrinsics, m.xyz[m.lifted], m.photo_points[m.lifted], params,
                                 rng_seed=rng_seed, auto_focal=True)
    else:
        estimate = pose_agreement(intrinsics, given_pose, m.xyz[m.lifted],
                                  m.photo_points[m.lifted], params)
    if timings is not None:
        timings["pose"] += perf_counter() - t0
    metrics, pose_inlier = round_metrics(m.points_photo, m.points_render, m.feature_inlier,
                                         m.lifted, estimate, m.rendered)
    metrics.update(m.extra_metrics)
    corr = Correspondences(m.photo_points, m.render_points, m.feature_inlier, m.lifted,
                           pose_inlier, m.xyz)
    return Round(estimate, metrics, corr, m.rendered)


def score_round(
    source: RoundSource,
    pose: Pose,
    params: RegistrationParams,
    width: int,
    *,
    matcher: str = "keypoints",
    near: bool = False,
    search_px: int | None = None,
    mode: str = "plain",
    solve: bool = True,
) -> Round:
    """One round from ``pose``: render, match, lift to 3D, solve or test the pose, metrics.

    :func:`match_round`, then :func:`pose_round`.

    Parameters
    ----------
    source, pose, params, width, matcher, near, search_px
        As in :func:`match_round`; ``params.pose`` for the pose.
    mode : str
        As in :func:`match_round`; area matching also takes "auto": the
        render relit for the photo's sun and the model's colours as they are
        (one ray cast) are both matched and solved, and the round whose pose
        inliers have the smaller median reprojection error is kept — the
        render that predicts where the photo's blocks are. Relighting is
        right where the model has the relief that shades the photo, and paints
        a biased shading where the photo's light and shade come from relief
        finer than the model's (method §6). The metrics get both medians
        (``area_residual_sunlit_px``, ``area_residual_unlit_px``; :func:`lit_as`).
    solve : bool
        Solve the photo's pose from the correspondences (RANSAC EPnP); False:
        test ``pose`` itself against them (a hand-made pose), so that its
        metrics mean the same as an estimate's.

    Returns
    -------
    Round
        The metrics count the putative matches (for blocks: the blocks
        searched, both "points" metrics), their geometric inliers (blocks that
        correlate clearly), the lifted ones and the pose's inliers; area
        rounds add ``area_width_px`` and ``area_search_px``.
    """
    if mode == "auto":
        if matcher != "area":
            raise ValueError('render mode "auto" is for area matching only')
        lit = score_round(source, pose, params, width, matcher=matcher, search_px=search_px,
                          mode="sunlit", solve=solve)
        unlit = score_round(source, pose, params, width, matcher=matcher, search_px=search_px,
                            mode="plain", solve=solve)
        res_lit = _median_residual(lit, source.intrinsics)
        res_unlit = _median_residual(unlit, source.intrinsics)
        extra = {"area_residual_sunlit_px": None if res_lit is None else round(res_lit, 4),
                 "area_residual_unlit_px": None if res_unlit is None else round(res_unlit, 4)}
        kept = unlit if lit_as("auto", extra) == "plain" else lit
        kept.metrics.update(extra)
        return kept
    # Reproducible: FLANN's trees and USAC draw from OpenCV's global RNG; each
    # round starts it from the params' seed, whatever ran before.
    cv2.setRNGSeed(int(params.seed))
    matched = match_round(source, pose, params, width, matcher=matcher, near=near,
                          search_px=search_px, mode=mode)
    return pose_round(matched, source.intrinsics, params.pose, None if solve else pose,
                      source.timings, rng_seed=int(params.seed))


def round_metrics(points_photo: int, points_render: int, inlier: np.ndarray,
                  lifted: np.ndarray, estimate: PoseEstimate, rendered: RenderResult
                  ) -> tuple[dict, np.ndarray]:
    """A round's metrics (RESULT.json names) and which putative matches agree with the pose.

    Parameters
    ----------
    points_photo, points_render : int
        Keypoints detected in each image (blocks searched, for area matching).
    inlier : (M,) bool array
        Per putative match: passed the geometric check.
    lifted : (M,) bool array
        Per putative match: has a 3D point (and passed the check).
    estimate : PoseEstimate
        Over the lifted matches, in their order.
    rendered : RenderResult
        For the render's coverage.

    Returns
    -------
    metrics : dict
    pose_inlier : (M,) bool array
    """
    n_putative = len(inlier)
    n_inl = int(inlier.sum())
    n_3d = int(lifted.sum())
    pose_inlier = np.zeros(n_putative, bool)
    if estimate.ok:
        pose_inlier[np.flatnonzero(lifted)[estimate.inliers]] = True
    metrics = {
        "points_photo": points_photo,
        "points_render": points_render,
        "putative_matches": n_putative,
        "feature_inliers": n_inl,
        "correspondences_3d": n_3d,
        "inlier_ratio_2d": round(n_inl / n_putative, 4) if n_putative else 0.0,
        "inliers_3d": estimate.n_inliers if estimate.ok else 0,
        "inlier_ratio_3d": round(estimate.n_inliers / n_3d, 4) if (n_3d and estimate.ok) else 0.0,
        "reprojection_error_px": (
            round(estimate.mean_error_px, 4) if estimate.ok else None
        ),
        "render_coverage": round(rendered.coverage, 4),
    }
    return metrics, pose_inlier


def image_shift(intr: Intrinsics, a: Pose, b: Pose, corr: Correspondences,
                intr_b: Intrinsics | None = None) -> float:
    """Median distance (pixels) by which the pose-inlier 3D points move in the
    image from pose ``a`` to pose ``b``: how much a pose change *shows*.

    Far from the camera, a rotation and a translation can nearly cancel in
    the image; the change in angle and metres then overstates what moved.
    ``intr_b`` is the camera of pose ``b`` when it differs (a focal length
    estimated with the pose): the shift then includes the focal change.
    """
    if corr.xyz is None or corr.pose_inlier.sum() < 3:
        return float("inf")
    pts = corr.xyz[corr.pose_inlier]
    moved = b.project(intr_b or intr, pts)
    return float(np.median(np.linalg.norm(a.project(intr, pts) - moved, axis=1)))


def residual_flow(corr: Correspondences, regional_px: float | None = None) -> float:
    """Median distance between matched photo and render points that agree
    with the pose (pixels): near zero when the render is from the photo's pose.

    With ``regional_px`` (area matching), the points are grouped in square
    cells of that side and the flow is the median, over cells with five
    points or more, of the length of each cell's median shift: a block's
    correlation peak is noisier than a keypoint's position (a pixel or so
    when shading is matched against a coloured photo), and what the test is
    for is a systematic misfit of a part of the image, which survives the
    cell's median while the noise does not.
    """
    sel = corr.pose_inlier
    if sel.sum() < 3:
        return float("inf")
    shift = corr.photo_points[sel] - corr.render_points[sel]
    plain = float(np.median(np.linalg.norm(shift, axis=1)))
    if not regional_px:
        return plain
    cell = np.floor(corr.render_points[sel] / regional_px).astype(int)
    keys = cell[:, 0] * 100_003 + cell[:, 1]
    lengths = []
    for key in np.unique(keys):
        in_cell = keys == key
        if in_cell.sum() >= 5:
            lengths.append(float(np.linalg.norm(np.median(shift[in_cell], axis=0))))
    return float(np.median(lengths)) if len(lengths) >= 3 else plain


def grade_pose(q: float, *, pose_found: bool, verified: bool,
               ceiling: float = UNVERIFIED_Q_CEILING) -> Grade:
    """The grade of a pose with quality ``q``; an unverified pose is graded as if Q ≤ ``ceiling``.

    Q alone can be high for a wrong but self-consistent pose, so only a
    verified pose can be graded "good" or "excellent".

    Parameters
    ----------
    q : float
        Quality, [−1.9, 1.9].
    pose_found : bool
        False: "failed" whatever Q.
    verified : bool
    ceiling : float
        :data:`UNVERIFIED_Q_CEILING` (keypoints: "fair" at best) or
        :data:`STAGE_Q_CEILING` (area blocks, edge and MI poses: "poor" at best).
    """
    if pose_found and not verified:
        q = min(q, ceiling)
    return grade_of(q, pose_found)


def uncertainty_hint(uncertainty: Uncertainty, image_width: int) -> str:
    """What to make of a pose whose error estimate is too large to call it
    registered: the expected error, the likely cause and what to do.

    Parameters
    ----------
    uncertainty : Uncertainty
        The pose's estimate (not small at ``image_width``).
    image_width : int
        Width of the photo, px (the thresholds are set at 1632 px).

    Returns
    -------
    str
        One hint.
    """
    if math.isfinite(uncertainty.reprojection_px):
        expected = (f"expected error ≈ {uncertainty.reprojection_px:.1f} px, camera "
                    f"≈ {uncertainty.position_m:.2f} m, {uncertainty.rotation_deg:.2f}°")
    else:
        expected = "too few matches to estimate the error"
    shading = ("the model was shaded by a computed sun, which reproduces only the relief the "
               "model resolves — an error every match shares and no check can see. Photographed "
               "colours on the model (a texture, or the scan's RGB) and the photo's capture time "
               "reduce it; where both are given already, add control points by hand.")
    shared = (math.isfinite(uncertainty.reprojection_px)
              and uncertainty.shared_px >= 0.5 * uncertainty.reprojection_px)
    if not math.isfinite(uncertainty.halves_px) and not math.isfinite(uncertainty.reprojection_px):
        return (f"Independent check: the halves of the photo could not be solved separately "
                f"({expected}): the pose rests on too few matches to be checked, so it is not "
                "verified — add control points by hand.")
    if uncertainty.halves_disagree(image_width) or not math.isfinite(uncertainty.halves_px):
        # On a render's synthetic light (a bare mesh) its shared error is the likely cause.
        return (f"Independent check: poses solved from separate halves of the photo disagree "
                f"({expected}): the matches share an error or are partly wrong — a wrong focal "
                "length, shading under another sun, matches in one part of the photo only, or "
                "a wrong pose altogether. "
                + (f"Here {shading}" if shared else
                   "Check the overlay at a few control points, or add control points by hand."))
    if shared:
        return (f"Independent check: the render was matched on its synthetic light ({expected}): "
                + shading)
    return (f"Independent check: the matches leave the pose loose ({expected}): too few "
            "separate areas of the photo were matched — add control points by hand.")


def trial_from_round(
    last: Round,
    *,
    index: int,
    params: RegistrationParams,
    pose: Pose | None,
    start_pose: Pose,
    rounds: int,
    converged: bool,
    origin: str,
    seconds: float,
    image_width: int,
    render_mode: str = "plain",
    matcher: str = "keypoints",
    intrinsics: Intrinsics | None = None,
    uncertainty_params: UncertaintyParams | None = None,
) -> Trial:
    """A trial from its last round: verification, residual flow, Q, grade and hints.

    A pose is *verified* when the trial converged, has at least
    :data:`MIN_VERIFIED_INLIERS` 3D inliers and the matched points of photo
    and render coincide: their residual flow is at most
    :data:`VERIFY_FLOW_PX` (at 1632 px width; for area matching per regions
    of a quarter of the photo's width, :func:`residual_flow`). An unverified
    pose is graded at most "fair", at most "poor" for area matching
    (:func:`grade_pose`).

    Parameters
    ----------
    last : Round
        The trial's last round (the one that found ``pose``, or the failed
        first one).
    index : int
        The trial's number (−1 outside a registration).
    params : RegistrationParams
        The trial's parameters (copied into the trial); the six rules advise on them.
    pose : Pose or None
        The trial's pose: the last estimate, a given pose, or None when no
        round found one.
    start_pose : Pose
    rounds : int
        Rounds run (0 for a pose scored as it is).
    converged : bool
        The pose stopped moving (True for a pose scored as it is).
    origin : str
        Where the start came from ("prior", "search", "manual", ...).
    seconds : float
    image_width : int
        The photo's width, pixels: pixel limits refer to 1632 px and scale with it.
    render_mode, matcher : str
        As in :func:`score_round` (the trial's ``render_mode`` is the light of
        the render the last round matched, :func:`lit_as`).
    intrinsics : Intrinsics, optional
        The photo's camera, full resolution (with an estimated focal length:
        the estimate, re-solved with the pose in the uncertainty's bootstrap,
        so the focal length's own error is in it). Given: the pose's ``uncertainty``
        is estimated (:func:`~napari_imgreg.registration.uncertainty.estimate_uncertainty`
        on the round's lifted matches, compared over the render's whole
        frame), and a pose whose estimate reaches
        :data:`~napari_imgreg.registration.uncertainty.UNCERTAIN_PX` is not
        verified (so never "registered", never graded above "fair").
    uncertainty_params : UncertaintyParams, optional
        Default ``params.uncertainty``.

    Returns
    -------
    Trial
    """
    area = matcher == "area"
    corr = last.correspondences
    # Area matching: cells of a quarter of the photo's width.
    flow = residual_flow(corr, image_width / 4.0 if area else None)
    verified = bool(
        converged
        and pose is not None
        and last.metrics["inliers_3d"] >= MIN_VERIFIED_INLIERS
        and flow <= VERIFY_FLOW_PX * (image_width / REFERENCE_WIDTH_PX)
    )
    uncertainty = None
    if intrinsics is not None and pose is not None:
        use = corr.lifted & corr.feature_inlier
        # The halves are solved by EPnP whatever solver found the pose (the
        # camera held fixed); the bootstrap re-solves an estimated focal length.
        uncertainty = estimate_uncertainty(
            intrinsics, pose, corr.xyz[use], corr.photo_points[use],
            frame_points(last.rendered.xyz), uncertainty_params or params.uncertainty,
            replace(params.pose, solver="epnp"),
            shading_share=getattr(last.rendered, "shading_share", None) or 0.0,
            rng_seed=int(params.seed))
    uncertain = uncertainty is not None and not uncertainty.is_small(image_width)
    flow_verified = verified
    verified = verified and not uncertain
    metrics = {**last.metrics,
               "residual_flow_px": round(flow, 3) if math.isfinite(flow) else None}
    q = quality_q(metrics, image_width)
    grade = grade_pose(q, pose_found=pose is not None, verified=verified,
                       ceiling=STAGE_Q_CEILING if area else UNVERIFIED_Q_CEILING)
    # The six rules tune keypoint detection and matching: no advice for blocks.
    hints = [] if area else [hit.hint for hit in evaluate_rules(metrics, params, image_width)]
    if area and pose is None:
        hints.append(f"Area matching found too few consistent blocks ({metrics['feature_inliers']} "
                     f"of {metrics['points_render']} correlate clearly): the start may be too far "
                     "off, or the photo shows little of the model's relief.")
    if pose is not None and not converged:
        hints.append("The pose was still moving after the last round: not verified.")
    elif pose is not None and not flow_verified:
        # A pose scored as it is (no rounds) was rendered once, from itself.
        render = "final render" if rounds else "render from this pose"
        hints.append(
            f"Photo and {render} disagree (residual flow {flow:.1f} px, "
            f"{metrics['inliers_3d']} 3D inliers): pose not verified."
        )
    if pose is not None and intrinsics is not None and last.estimate.intrinsics is not None:
        spread = (f" ± {uncertainty.focal_px:.1f}" if uncertainty is not None
                  and uncertainty.focal_px is not None and math.isfinite(uncertainty.focal_px)
                  else "")
        hints.append(
            f"Focal length estimated with the pose: fx = {intrinsics.fx:.1f}{spread} px (a "
            f"{intrinsics.hfov_deg:.1f}° horizontal view); the uncertainty includes its error.")
    if uncertain:
        hints.append(uncertainty_hint(uncertainty, image_width))
    return Trial(
        index=index,
        params=params.copy(),
        metrics=metrics,
        q=q,
        grade=grade.name,
        hints=hints,
        pose=pose,
        start_pose=start_pose,
        rounds=rounds,
        converged=converged,
        verified=verified,
        residual_flow_px=flow,
        origin=origin,
        seconds=seconds,
        correspondences=corr,
        render_mode=lit_as(render_mode, last.metrics),
        matcher=matcher,
        uncertainty=uncertainty,
        intrinsics=intrinsics,
    )
