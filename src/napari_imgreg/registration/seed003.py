"""Seed 003's own registration path: reflectivity + wireframe views, HOG, six-point DLT.

Morago et al. (seed 003) register a photo to a lidar scan with no assumption
about the camera: the scan is rendered from a synthetic camera as a
*reflectivity view* (laser intensity) and a *wireframe view* (outlines and
intersections of its RANSAC planes); the photo's gradient magnitude is
matched with the reflectivity view's, its Canny edges with the wireframe;
SIFT keypoints (photo: near LSD segments; render: on segmented planes) are
described by HOG on oriented multi-scale patches; the render's matched
keypoints are lifted to 3D and the camera's 3 × 4 projection matrix follows
from the six-point DLT in RANSAC — focal lengths, principal point and pose
(all the building blocks are in :mod:`~napari_imgreg.registration.lidar_views`,
:mod:`~napari_imgreg.registration.hog` and
:mod:`~napari_imgreg.registration.resection`).

:func:`register_seed003` runs that path on its own, beside the default
pipeline (:func:`napari_imgreg.registration.pipeline.register`), so that a
benchmark can show what it does by itself. It iterates as the seed's
synthetic cameras do: render the scan from the current camera (the prior's
at first), match, solve the DLT, render again from the solved camera (its
focal lengths and principal point too), until the camera stops moving in
the image. Its trial is scored like every other pose of the package: the
seven metrics and Q (:mod:`~napari_imgreg.registration.quality`), the
verification (converged, enough 3D inliers, small residual flow between the
photo's and the final render's matched keypoints) and the cross-validated
``uncertainty`` (:func:`~napari_imgreg.registration.round.trial_from_round`).

Where this departs from the seed, and why:

* Matches pass a 2D check (fundamental matrix, MAGSAC++) before the DLT, as
  the package's keypoint path does (``geometric_check``): the seed gives the
  DLT's RANSAC every HOG match, and at the 10–30 % inlier ratios of photo ↔
  render matches a six-point RANSAC needs 10⁴–10⁶ samples.
* Nearly coplanar 3D points (a single rock face seen head-on) leave the
  DLT's intrinsics undetermined; :func:`~napari_imgreg.registration.pose.estimate_pose`
  then solves P4Pf (focal length only, principal point at the image
  centre); the result's ``assumptions`` say so, and its camera's
  ``estimated`` then lists fx and fy only.
* The photo and the render are matched at a reduced width
  (``match_width``), the camera solved at the photo's full resolution.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, ClassVar

import cv2
import numpy as np

from ..camera import Intrinsics, Pose, match_scale, pixels_to_full
from ..prior import Prior
from ..render import RenderResult, render
from ..validate import FieldValueError, StageParams, check_ranges
from .features import FeatureParams
from .lidar_views import (
    LidarViewParams,
    PhotoViewFeatures,
    PlaneSegmentation,
    check_matches,
    describe_photo_views,
    lift_to_3d,
    match_render_views,
    scene_planes,
)
from .params import RegistrationParams
from .pipeline import Cancelled, Registration
from .pose import PoseParams, estimate_pose
from .quality import evaluate_rules
from .round import Correspondences, Round, image_shift, round_metrics, trial_from_round
from .uncertainty import UncertaintyParams

__all__ = ["Seed003Params", "Seed003Matches", "register_seed003", "seed003_matches", "scene_planes",
           "SEED003_ORIGIN",
           "SEED003_MATCHER"]

#: ``Trial.origin`` of the seed's trial (RESULT.json ``trials[].origin``).
SEED003_ORIGIN = "seed 003"
#: ``Trial.matcher`` of the seed's trial.
SEED003_MATCHER = "seed003"
#: The view pairs :attr:`Seed003Params.pairs` may name.
VIEW_PAIRS = ("reflectivity", "wireframe")
#: Converged also when a round moves the camera less than this (degrees,
#: metres, relative focal length): the keypoint trials' defaults.
CONVERGED_DEG, CONVERGED_M, CONVERGED_FOCAL = 0.05, 0.05, 1e-3
#: 2D checks :attr:`Seed003Params.geometric_check` may name.
GEOMETRIC_CHECKS = ("fundamental", "homography", "none")


@dataclass
class Seed003Params(StageParams):
    """Settings of seed 003's registration path.

    Attributes
    ----------
    views : LidarViewParams
        The views, planes, keypoints, HOG and matching
        (:class:`~napari_imgreg.registration.lidar_views.LidarViewParams`).
    pairs : tuple of str
        View pairs matched: ``"reflectivity"`` (photo gradient ↔ intensity
        gradient), ``"wireframe"`` (photo Canny ↔ plane outlines), or both
        (default, the seed's "All").
    match_width : int
        Photo and render are matched at this width, pixels (64–16384; the
        photo's own when smaller). Default 768, the keypoint path's.
    max_rounds : int
        Render → match → DLT rounds at most (1–20). Default 8: with the
        principal point and both focal lengths free, the DLT's camera
        settles more slowly than a known camera's pose (on the small
        sample's textured mesh, masks off: 1 of 2 photos converged within 4
        rounds, 2 of 2 within 8; a converged trial stops early).
    converged_shift_px : float
        The rounds stop when the new camera moves the inlier 3D points by
        less than this in the image (median), pixels at 1632 px width,
        scaled with the photo's (0.01–50). Default 0.5.
    geometric_check : {"fundamental", "homography", "none"}
        2D check of each round's HOG matches before the DLT (MAGSAC++, see
        the module notes). Default "fundamental".
    geometric_threshold_px : float
        Its inlier threshold, pixels at the matching width (0.5–20).
        Default 3.
    reprojection_error_px : float
        DLT RANSAC inlier threshold, pixels at the photo's full resolution
        (0.1–200). Default 6, the keypoint path's.
    ransac_iterations : int
        RANSAC samples at most (10–20 000; adaptive below that). Default 20 000.
    confidence : float
        RANSAC confidence (0.5–0.999999). Default 0.999.
    min_hfov_deg, max_hfov_deg : float
        Horizontal fields of view a solved camera may have (0.5–170°).
        Defaults 2–150°.
    uncertainty : UncertaintyParams
        The cross-validated error estimate of the pose.
    seed : int
        Seed of the random draws (plane RANSAC, pose RANSAC, OpenCV's RNG),
        0–2³¹ − 1.
    """

    KIND: ClassVar[str] = "seed-003"

    views: LidarViewParams = field(default_factory=LidarViewParams)
    pairs: tuple[str, ...] = VIEW_PAIRS
    match_width: int = 768
    max_rounds: int = 8
    converged_shift_px: float = 0.5
    geometric_check: str = "fundamental"
    geometric_threshold_px: float = 3.0
    reprojection_error_px: float = 6.0
    ransac_iterations: int = 20_000
    confidence: float = 0.999
    min_hfov_deg: float = 2.0
    max_hfov_deg: float = 150.0
    uncertainty: UncertaintyParams = field(default_factory=UncertaintyParams)
    seed: int = 0

    #: Inclusive valid range of each numeric field.
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "match_width": (64, 16384),
        "max_rounds": (1, 20),
        "converged_shift_px": (0.01, 50.0),
        "geometric_threshold_px": (0.5, 20.0),
        "reprojection_error_px": (0.1, 200.0),
        "ransac_iterations": (10, 20_000),
        "confidence": (0.5, 0.999999),
        "min_hfov_deg": (0.5, 170.0),
        "max_hfov_deg": (0.5, 170.0),
        "seed": (0, 2 ** 31 - 1),
    }

    def __post_init__(self) -> None:
        if isinstance(self.views, dict):
            self.views = LidarViewParams.from_dict(self.views)
        if isinstance(self.uncertainty, dict):
            self.uncertainty = UncertaintyParams.from_dict(self.uncertainty)
        self.pairs = tuple(self.pairs)
        if not self.pairs or set(self.pairs) - set(VIEW_PAIRS):
            raise FieldValueError("pairs", f"must name one or both of {', '.join(VIEW_PAIRS)}, "
                                           f"got {list(self.pairs)}")
        if self.geometric_check not in GEOMETRIC_CHECKS:
            raise FieldValueError("geometric_check", f"must be one of "
                                  f"{', '.join(GEOMETRIC_CHECKS)}, got {self.geometric_check!r}")
        check_ranges(self)
        if self.min_hfov_deg >= self.max_hfov_deg:
            raise FieldValueError("min_hfov_deg", f"must be below max_hfov_deg "
                                                  f"({self.max_hfov_deg:g})")

    def pose_params(self) -> PoseParams:
        """The DLT settings as the package's :class:`PoseParams` (``solver="dlt"``)."""
        return PoseParams(reprojection_error_px=self.reprojection_error_px,
                          iterations=self.ransac_iterations, confidence=self.confidence,
                          refine=True, solver="dlt", min_hfov_deg=self.min_hfov_deg,
                          max_hfov_deg=self.max_hfov_deg)

    def registration_params(self) -> RegistrationParams:
        """The :class:`RegistrationParams` a trial records (its pose, width,
        rounds, uncertainty and seed are these; the keypoint settings are unused)."""
        return RegistrationParams(pose=self.pose_params(), match_width=self.match_width,
                                  max_iterations=self.max_rounds, auto_adapt=False,
                                  max_trials=1, search_prior=False, sun_relight=False,
                                  edge_align=False, dense_refine=False, area_match=False,
                                  uncertainty=self.uncertainty, seed=self.seed)


# ------------------------------------------------------------------ rounds
def _photo_side(photo_small: np.ndarray, p: Seed003Params) -> PhotoViewFeatures:
    return describe_photo_views(photo_small, p.views, None, p.pairs)


def _reduce(photo: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    h, w = shape
    if photo.shape[:2] == (h, w):
        return photo
    return cv2.resize(photo, (w, h), interpolation=cv2.INTER_AREA)


def _match_round(photo_side: PhotoViewFeatures, rendered: RenderResult,
                 planes: PlaneSegmentation, p: Seed003Params, scale: float
                 ) -> tuple[dict, Correspondences, dict]:
    """Match both view pairs, check in 2D, lift; arrays at full resolution."""
    m = match_render_views(photo_side, rendered, planes, p.views)
    counts = {f"seed003_{name}_matches": m.counts[f"{name}_matches"] for name in p.pairs}
    if p.geometric_check == "none":
        inlier = np.ones(len(m), bool)
    else:
        fp = FeatureParams(geometric_model=p.geometric_check,
                           geometric_threshold_px=p.geometric_threshold_px)
        inlier = check_matches(m.photo_points, m.render_points, fp)
    xyz, lifted = lift_to_3d(rendered, m.render_points, p.views.wireframe_depth_jump)
    lifted &= inlier
    for name in p.pairs:
        counts[f"seed003_{name}_lifted"] = int((lifted & (m.source == name)).sum())
    corr = Correspondences(pixels_to_full(m.photo_points, scale),
                           pixels_to_full(m.render_points, scale),
                           inlier, lifted, np.zeros(len(inlier), bool), xyz)
    return {"points_photo": photo_side.n_keypoints, "points_render": m.n_keypoints_render}, \
        corr, {"counts": counts, "source": m.source}


@dataclass
class Seed003Matches:
    """One round's matches of seed 003's path from a given camera (for
    diagnosis: :func:`seed003_matches`).

    Attributes
    ----------
    correspondences : Correspondences
        Photo and render pixels at the photo's full resolution, the 2D
        check (``feature_inlier``), ``lifted`` and the render's ``xyz``
        (``pose_inlier`` all False: no pose is solved).
    source : (M,) array of str
        The view pair of each match.
    counts : dict
        Keypoints of photo and render and matches per pair.
    rendered : RenderResult
        The render matched (at the matching width).
    """

    correspondences: Correspondences
    source: np.ndarray
    counts: dict
    rendered: RenderResult


def seed003_matches(scene, photo_rgb: np.ndarray, camera: Intrinsics, pose: Pose,
                    params: Seed003Params | None = None) -> Seed003Matches:
    """The matches :func:`register_seed003` would find in a round rendered
    from ``camera`` and ``pose`` (e.g. the prior, or the true camera to see
    what the views can match at best).

    Parameters
    ----------
    scene : CloudScene or Scene
    photo_rgb : (H, W, 3) uint8 array
        At ``camera``'s size.
    camera : Intrinsics
    pose : Pose
    params : Seed003Params, optional

    Returns
    -------
    Seed003Matches
    """
    p = params or Seed003Params()
    planes = scene_planes(scene, p.views, p.seed)
    cv2.setRNGSeed(int(p.seed))
    scale = match_scale(camera.width, p.match_width)
    rendered = render(scene, camera, pose, scale=scale)
    side = _photo_side(_reduce(photo_rgb, rendered.shape), p)
    counts, corr, info = _match_round(side, rendered, planes, p, scale)
    return Seed003Matches(corr, info["source"], {**counts, **info["counts"]}, rendered)


def register_seed003(
    scene,
    photo_rgb: np.ndarray,
    prior: Prior,
    params: Seed003Params | None = None,
    cancelled: Callable[[], bool] | None = None,
    *,
    photo_name: str = "",
) -> Registration:
    """Register a photo to a lidar scan (or a mesh) by seed 003's path alone.

    Render the scene's reflectivity and wireframe views from the current
    camera (the prior's at first), match them with the photo's gradient
    magnitude and Canny edges (SIFT + oriented multi-scale HOG, LSD and plane
    masks), lift the render's keypoints to 3D and solve the camera by the
    six-point DLT in RANSAC — pose, focal lengths and principal point, with
    no assumption about the intrinsics; then render from the solved camera
    and repeat, at most ``max_rounds`` times, until the camera stops moving.
    The trial is scored, verified and given its ``uncertainty`` as every
    trial of the package is.

    Parameters
    ----------
    scene : CloudScene or Scene
        A scan with intensity (a mesh: its texture or colours as the
        reflectivity, its triangles as the planes' elements).
    photo_rgb : (H, W, 3) uint8 array
        The photo; its size must match ``prior.intrinsics``.
    prior : Prior
        The prior pose and the camera of the first render (its focal length
        may be a guess: it is not used beyond the first render).
    params : Seed003Params, optional
    cancelled : callable, optional
        Polled between steps; when it returns True,
        :class:`~napari_imgreg.registration.pipeline.Cancelled` is raised.
    photo_name : str
        For RESULT.json.

    Returns
    -------
    Registration
        One trial (origin ``"seed 003"``, matcher ``"seed003"``). The camera
        (``intrinsics``) is the DLT's, its ``estimated`` listing fx, fy, cx,
        cy (P4Pf's fx, fy where the 3D points were nearly coplanar); the
        prior's camera where no camera was solved. ``status`` "registered"
        only for a verified pose.

    Raises
    ------
    ValueError
        The photo's size is not the camera's.
    Cancelled
    """
    p = params or Seed003Params()
    intr0 = prior.intrinsics
    h, w = photo_rgb.shape[:2]
    if (w, h) != (intr0.width, intr0.height):
        raise ValueError(f"photo is {w}×{h} but the camera is {intr0.width}×{intr0.height}")

    def check() -> None:
        if cancelled is not None and cancelled():
            raise Cancelled()

    t_total = time.perf_counter()
    timings = {"planes": 0.0, "render": 0.0, "views_match": 0.0, "pose": 0.0}
    t0 = time.perf_counter()
    planes = scene_planes(scene, p.views, p.seed)
    timings["planes"] = time.perf_counter() - t0
    check()
    cv2.setRNGSeed(int(p.seed))
    scale = match_scale(intr0.width, p.match_width)
    pose_params = p.pose_params()
    photo_side: PhotoViewFeatures | None = None
    camera, pose = intr0, prior.pose
    last_ok: tuple[Round, Pose, Intrinsics] | None = None
    first: Round | None = None
    converged = False
    rounds = 0
    for k in range(p.max_rounds):
        rounds = k + 1
        t0 = time.perf_counter()
        rendered = render(scene, camera, pose, scale=scale)
        timings["render"] += time.perf_counter() - t0
        check()
        t0 = time.perf_counter()
        if photo_side is None:
            photo_side = _photo_side(_reduce(photo_rgb, rendered.shape), p)
        counts, corr, info = _match_round(photo_side, rendered, planes, p, scale)
        timings["views_match"] += time.perf_counter() - t0
        check()
        t0 = time.perf_counter()
        estimate = estimate_pose(camera, corr.xyz[corr.lifted], corr.photo_points[corr.lifted],
                                 pose_params, rng_seed=int(p.seed))
        timings["pose"] += time.perf_counter() - t0
        metrics, pose_inlier = round_metrics(counts["points_photo"], counts["points_render"],
                                             corr.feature_inlier, corr.lifted, estimate, rendered)
        corr.pose_inlier = pose_inlier
        metrics.update(info["counts"])
        if estimate.ok:
            src = info["source"][pose_inlier]
            for name in p.pairs:
                metrics[f"seed003_{name}_inliers"] = int((src == name).sum())
        this = Round(estimate, metrics, corr, rendered)
        if first is None:
            first = this
        if not estimate.ok:
            break
        solved = estimate.intrinsics or camera
        shift = image_shift(camera, pose, estimate.pose, corr, solved)
        d_rot = pose.rotation_error_deg(estimate.pose)
        d_pos = float(np.linalg.norm(pose.center - estimate.pose.center))
        d_focal = abs(solved.fx / camera.fx - 1.0)
        last_ok = (this, estimate.pose, solved)
        camera, pose = solved, estimate.pose
        # As the pipeline's trials: the points stop moving in the image, or
        # the camera in angle, position and focal length.
        if shift < p.converged_shift_px * intr0.width / 1632.0 or (
                d_rot < CONVERGED_DEG and d_pos < CONVERGED_M and d_focal < CONVERGED_FOCAL):
            converged = True
            break

    if last_ok is not None:
        last, pose_out, camera_out = last_ok
        if last is not this:   # a later round found nothing: judged on the last that did
            last.metrics["seed003_failed_round"] = rounds
    else:
        last, pose_out, camera_out = first, None, None
    reg_params = p.registration_params()
    trial = trial_from_round(
        last, index=0, params=reg_params, pose=pose_out, start_pose=prior.pose, rounds=rounds,
        converged=converged, origin=SEED003_ORIGIN, seconds=time.perf_counter() - t_total,
        image_width=intr0.width, matcher=SEED003_MATCHER, intrinsics=camera_out,
        uncertainty_params=p.uncertainty)
    # The six rules tune the keypoint path's detector and matcher, not this one.
    rule_hints = {hit.hint for hit in evaluate_rules(trial.metrics, reg_params, intr0.width)}
    trial.hints = [h for h in trial.hints if h not in rule_hints]
    if pose_out is None:
        trial.hints.insert(0, f"Seed 003's path found no camera: {last.estimate.reason or 'no pose'} "
                              f"({last.metrics['correspondences_3d']} matches lifted to 3D of "
                              f"{last.metrics['putative_matches']}).")
    status = "registered" if trial.verified and trial.grade != "failed" else "failed"
    assumptions = list(prior.assumptions)
    assumptions.append("seed 003's path: the camera by the six-point DLT (focal lengths and "
                       "principal point estimated; the prior's camera only for the first render)")
    if camera_out is not None and last.estimate.solver != "dlt":
        assumptions.append(f"the matched 3D points are nearly coplanar: the camera by "
                           f"{last.estimate.solver.upper()} (square pixels, principal point at "
                           "the image centre) instead of the DLT")
    hints = list(trial.hints)
    if status == "failed" and not hints:
        hints = ["No verified pose: try the default pipeline or the manual control-point "
                 "registration."]
    timings["total"] = time.perf_counter() - t_total
    return Registration(
        status=status, photo=photo_name, intrinsics=camera_out or intr0,
        pose=pose_out if pose_out is not None else prior.pose, prior=prior,
        metrics=trial.metrics, q=trial.q, grade=trial.grade, hints=hints, trials=[trial],
        timings_s=timings, best_trial=0, assumptions=assumptions, uncertainty=trial.uncertainty)

