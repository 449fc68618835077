"""Automatic registration of one photo: prior → render → match → pose, iterated.

:func:`register_photo` is a generator: it yields :class:`Progress` records
(stage, fraction, message) and returns a :class:`Registration`, so the GUI can
show progress and cancel between steps, and a script can simply call
:func:`register`.

One *trial* renders the model from the current pose, matches the (filtered)
photo against the render, lifts the render's matched keypoints to 3D through
its xyz map and solves the photo's pose with RANSAC EPnP — then renders again
from the new pose and repeats until the pose stops moving: a render from
nearly the right pose resembles the photo far more than the prior's render
does. Trials are scored with the seven metrics; when a trial is not good
enough, the first heuristic rule that fires adapts the parameters for the next
one. If nothing registers from the prior, perturbed priors within the sensor
record's ``sigma`` are tried at reduced resolution and the best is refined.

With an unknown focal length (``Intrinsics.focal_known`` False: a record with
the camera's size only), every round estimates the focal length with the pose
(:attr:`~napari_imgreg.registration.pose.PoseParams.solver`) and the next
round renders with the estimate; a trial that starts from an earlier trial's
pose starts from its focal length too, and the result's camera is the best
trial's, its ``estimated`` listing what was estimated.

A pose is reported ``registered`` only when it is also *verified*: the last
round converged and the matched keypoints of photo and final render coincide
(small residual flow). Q alone can be high for a wrong but self-consistent
pose; this check is what keeps wrong poses from being called good.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Generator

import numpy as np

from .._json import strict_output
from ..camera import Intrinsics, Pose, match_scale
from .features import Features, detect_and_describe
from .filters import apply_filters, illumination_invariant, reduce_for_matching
from ..prior import Prior
from .params import RegistrationParams
from .explain import diagnose, focal_retry_start, nothing_in_common
from .quality import GRADES, evaluate_rules, outcome_words
from .round import (  # noqa: F401  (re-exported: the names' old home)
    MIN_VERIFIED_INLIERS,
    STAGE_Q_CEILING,
    VERIFY_FLOW_PX,
    Correspondences,
    Round,
    Trial,
    grade_pose,
    image_shift,
    score_round,
    trial_from_round,
)
from .stages.area import search_schedule
from .stages.dense import refine_pose_mi
from .stages.edges import align_edges
from .uncertainty import Uncertainty
from ..render import RenderResult, render
from ..scene import Scene, has_appearance, has_colours

__all__ = [
    "Progress",
    "Trial",
    "Registration",
    "Cancelled",
    "register_photo",
    "register",
    "VERIFY_FLOW_PX",
    "MIN_VERIFIED_INLIERS",
]

#: A trial has converged when the new estimate moves the inlier points by less
#: than this in the image (median, px at 1632 px width) — or moves less than
#: ``converged_deg`` and ``converged_m``. Far from the camera a rotation and a
#: translation nearly cancel in the image, so the angle/metre test alone can
#: keep a pose that no longer changes what it shows "moving" for rounds.
CONVERGED_SHIFT_PX = 0.5
#: The same for area matching: its blocks are cut anew from every render, so
#: even at the right pose the estimate jitters by a few tenths of a pixel
#: between rounds (the residual-flow test still bounds the misfit).
AREA_CONVERGED_SHIFT_PX = 1.0
#: A start pose whose camera is less than this above the model's surface is
#: lifted to eye height above it (see :func:`_above_ground`).
MIN_GROUND_CLEARANCE_M = 0.5
#: Eye height used when a start pose is lifted.
EYE_HEIGHT_M = 1.6


class Cancelled(Exception):
    """Raised inside :func:`register_photo` when the caller cancels."""


@dataclass
class Progress:
    """A progress report: ``stage`` name, overall ``fraction`` in [0, 1], ``message``."""

    stage: str
    fraction: float
    message: str = ""
    trial: int | None = None


@dataclass
class Registration:
    """The outcome of registering one photo (RESULT.json, contract §4).

    :meth:`to_dict` is its RESULT.json;
    :func:`~napari_imgreg.registration.result_file.load_registration` (also
    ``napari_imgreg.load_registration``) reads one back.
    """

    status: str
    photo: str
    intrinsics: Intrinsics
    pose: Pose
    prior: Prior
    metrics: dict
    q: float
    grade: str
    hints: list[str]
    trials: list[Trial]
    timings_s: dict
    best_trial: int | None = None
    assumptions: list[str] = field(default_factory=list)
    #: The best trial's expected error (RESULT.json ``uncertainty``), None when not estimated.
    uncertainty: Uncertainty | None = None

    def __repr__(self) -> str:
        # Short: a notebook prints it (every trial's parameters would be ~20 000 characters).
        error = ("" if self.uncertainty is None
                 else f", ±{self.uncertainty.reprojection_px:.2f} px")
        return (f"Registration({self.photo!r}, {self.status}, {self.grade}, Q={self.q:+.2f}"
                f"{error}, {len(self.trials)} trial(s))")

    @property
    def registered(self) -> bool:
        return self.status == "registered"

    @property
    def grade_info(self):
        return next(g for g in GRADES if g.name == self.grade)

    @strict_output  # RESULT.json is strict JSON: non-finite numbers -> null + null_reasons
    def to_dict(self) -> dict:
        return {
            "status": self.status,
            "photo": self.photo,
            "camera": self.intrinsics.to_dict(),
            "pose": self.pose.to_dict(),
            "prior": {
                "pose": self.prior.pose.to_dict(),
                "sigma": self.prior.sigma.to_dict(),
                "assumptions": self.prior.assumptions,
            },
            "metrics": self.metrics,
            "quality": {"Q": self.q, "grade": self.grade, "hints": self.hints},
            "trials": [
                {"params": t.params.to_dict(), "metrics": t.metrics, "Q": t.q, **{
                    k: v for k, v in t.to_dict().items() if k not in ("params", "metrics", "Q")
                }}
                for t in self.trials
            ],
            "best_trial": self.best_trial,
            "timings_s": {k: round(v, 3) for k, v in self.timings_s.items()},
            **({} if self.uncertainty is None else {"uncertainty": self.uncertainty.to_dict()}),
        }


# --------------------------------------------------------------------------
class _Context:
    """What stays fixed across the trials of one photo (and caches)."""

    def __init__(self, scene: Scene, photo_rgb: np.ndarray, intrinsics: Intrinsics,
                 params: RegistrationParams, check: Callable[[], None]) -> None:
        self.scene = scene
        #: The camera of the current round: the prior's, or (focal length
        #: unknown) the latest estimate; :func:`_run_trial` sets and restores it.
        self.intrinsics = intrinsics
        self.check = check
        self.timings = {"render": 0.0, "filter": 0.0, "detect_match": 0.0,
                        "lift_3d": 0.0, "pose": 0.0}
        self._photo_rgb = photo_rgb
        self._photo_cache: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
        self._feature_cache: dict[tuple, Features] = {}
        self._area_cache: dict[tuple, np.ndarray] = {}
        self._unlit: tuple[tuple, RenderResult] | None = None
        #: The photo's described lidar views (``RegistrationParams.lidar_views``).
        self.lidar_cache: dict = {}
        #: Toward the photo's sun (local frame), when known and usable.
        self.sun: np.ndarray | None = None

    @property
    def photo(self) -> np.ndarray:
        return self._photo_rgb

    def render(self, pose: Pose, scale: float, mode: str = "plain",
               intrinsics: Intrinsics | None = None) -> RenderResult:
        """Render for matching: ``plain`` (texture or colours as they are) or
        ``sunlit`` (relit for the photo's sun with cast shadows)."""
        intr = intrinsics or self.intrinsics
        t0 = time.perf_counter()
        # A plain render of the view last rendered sun-lit is that render's
        # unlit twin, from the same ray cast (area matching in "auto" mode
        # matches both).
        key = (pose.R.tobytes(), pose.t.tobytes(), round(scale, 9), intr)
        photographed = has_colours(self.scene)
        if mode == "sunlit" and self.sun is not None:
            from .stages.relight import render_sunlit, render_unlit_and_sunlit

            if photographed:
                unlit, rendered = render_unlit_and_sunlit(self.scene, intr, pose, self.sun,
                                                          scale=scale,
                                                          survey_sun_dir=self.scene.survey_sun)
                self._unlit = (key, unlit)
            else:
                rendered = render_sunlit(self.scene, intr, pose, self.sun, scale=scale,
                                         survey_sun_dir=self.scene.survey_sun)
        else:
            if photographed and self._unlit is not None and self._unlit[0] == key:
                rendered = self._unlit[1]
            else:
                rendered = render(self.scene, intr, pose, scale=scale)
            if not photographed:
                # Grey shading under a made-up light, or a scan's intensity: none
                # of the photo's light is in the render, and every match shares
                # what the photo's shading does to it (the error estimate's
                # synthetic-light term, whole).
                rendered.shading_share = 1.0
        self.timings["render"] += time.perf_counter() - t0
        return rendered

    def photo_at(self, width: int) -> tuple[np.ndarray, float]:
        """The photo resized to ``width`` (never enlarged) and the scale used."""
        scale = match_scale(self.intrinsics.width, width)
        key = ("rgb", round(scale, 6))
        if key not in self._photo_cache:
            img, _ = reduce_for_matching(self._photo_rgb, width)
            self._photo_cache[key] = (img, np.array(scale))
        img, s = self._photo_cache[key]
        return img, float(s)

    def area_photo(self, photo_small: np.ndarray, sigma_px: float) -> np.ndarray:
        """The photo band-passed for area matching at ``photo_small``'s size (cached)."""
        from .stages.area import prepare_photo

        key = ("area", photo_small.shape, round(sigma_px, 3))
        if key not in self._area_cache:
            self._area_cache[key] = prepare_photo(photo_small, sigma_px)
        return self._area_cache[key]

    def photo_features(self, params: RegistrationParams, width: int,
                       invariant: bool = False) -> Features:
        """The photo's features at ``width`` (cached); with ``invariant``, the
        illumination-invariant channel's keypoints too (channel 1)."""
        key = (repr(params.photo_filters), repr(params.features), width)
        if key not in self._feature_cache:
            img, _ = self.photo_at(width)
            t0 = time.perf_counter()
            gray = apply_filters(img, params.photo_filters)
            t1 = time.perf_counter()
            feats = detect_and_describe(gray, params.features, color=img)
            t2 = time.perf_counter()
            self.timings["filter"] += t1 - t0
            self.timings["detect_match"] += t2 - t1
            self._feature_cache[key] = feats
        feats = self._feature_cache[key]
        if not invariant:
            return feats
        ikey = ("invariant",) + key
        if ikey not in self._feature_cache:
            img, _ = self.photo_at(width)
            t0 = time.perf_counter()
            inv = illumination_invariant(img)
            t1 = time.perf_counter()
            self._feature_cache[ikey] = detect_and_describe(inv, params.features)
            self.timings["filter"] += t1 - t0
            self.timings["detect_match"] += time.perf_counter() - t1
        return Features.concat([feats, self._feature_cache[ikey]])


def _above_ground(scene: Scene, pose: Pose) -> tuple[Pose, float]:
    """The pose with its camera lifted to eye height when it sits (nearly) in the ground.

    A prior altitude from a coarse DEM plus GNSS noise (or a GNSS altitude
    with σ ≈ 10 m) often puts the camera a metre or more *below* the model's
    surface. A render from there shows the underside of the terrain or a
    close-up of grass: nothing matches, however good the matcher (in the
    benchmark a third of the ground-level priors were below the surface, and
    every one of them failed from the prior). The surface under the camera is
    found by a ray cast down from 30 m above it; the horizontal position and
    the attitude are kept. Returns the pose and the lift in metres (0 when
    unchanged).
    """
    c = pose.center
    top = c + np.array([0.0, 0.0, 30.0])
    hits = scene.cast_rays(top[None], np.array([[0.0, 0.0, -1.0]]))
    if not hits.hit[0]:
        return pose, 0.0
    ground = float(top[2] - hits.distance[0])
    if c[2] - ground >= MIN_GROUND_CLEARANCE_M:
        return pose, 0.0
    lift = ground + EYE_HEIGHT_M - float(c[2])
    return pose.with_center(np.array([c[0], c[1], ground + EYE_HEIGHT_M])), lift


def _pose_change(a: Pose, b: Pose) -> tuple[float, float]:
    return a.rotation_error_deg(b), float(np.linalg.norm(a.center - b.center))


def _run_trial(
    ctx: _Context,
    index: int,
    start: Pose,
    params: RegistrationParams,
    origin: str,
    width: int | None = None,
    max_rounds: int | None = None,
    mode: str = "plain",
    matcher: str = "keypoints",
    far_start: bool = True,
    intrinsics: Intrinsics | None = None,
) -> Generator[tuple[int, int], None, Trial]:
    """Run one trial; yields (round, rounds) before each round, returns the Trial.

    Each round is :func:`~napari_imgreg.registration.round.score_round` from
    the last estimate; the trial is judged on the last round that found a pose
    (:func:`~napari_imgreg.registration.round.trial_from_round`).
    ``matcher`` "area" matches render blocks by correlation instead of
    keypoints, at widths and search radii that follow
    the pose's convergence (:func:`napari_imgreg.registration.stages.area.search_schedule`;
    ``far_start``: the start is the sensor prior, not a stage's estimate).
    A trial is converged only after a round at the full area width.
    ``intrinsics``: the camera to start from (default ``ctx.intrinsics``);
    rounds that estimate the focal length render the next round with their
    estimate, and the trial's ``intrinsics`` is its last estimate.
    ``ctx.intrinsics`` is as before when the trial ends.
    """
    t_start = time.perf_counter()
    before = ctx.intrinsics
    if intrinsics is not None:
        ctx.intrinsics = intrinsics
    try:
        trial = yield from _trial_rounds(ctx, index, start, params, origin, width, max_rounds,
                                         mode, matcher, far_start, t_start)
    finally:
        ctx.intrinsics = before
    return trial


def _trial_rounds(ctx: _Context, index: int, start: Pose, params: RegistrationParams,
                  origin: str, width: int | None, max_rounds: int | None, mode: str,
                  matcher: str, far_start: bool, t_start: float
                  ) -> Generator[tuple[int, int], None, Trial]:
    """The rounds of :func:`_run_trial` (which sets and restores ``ctx.intrinsics``)."""
    width = width or params.match_width
    rounds = max_rounds or params.max_iterations
    pose = start
    best: Round | None = None
    converged = False
    n_done = 0
    last_ok_pose: Pose | None = None
    area = matcher == "area"
    if area:
        # Coarse rounds do not count: up to two more to reach the full width.
        rounds += 2
    last_shift = float("inf")
    final_width = True
    for k in range(rounds):
        n_done = k + 1
        yield k, rounds
        if area:
            a_width, radius = search_schedule(params.area, k == 0, far_start, last_shift,
                                              ctx.intrinsics.width)
            final_width = a_width >= min(params.area.width, ctx.intrinsics.width)
            this = score_round(ctx, pose, params, a_width, matcher="area", search_px=radius,
                               mode=mode)
        else:
            # After a round that found a pose, the next render is close to the
            # photo: luminance features suffice.
            this = score_round(ctx, pose, params, width, near=last_ok_pose is not None,
                               mode=mode)
        estimate = this.estimate
        if not estimate.ok:
            if best is None:
                best = this
            break
        best = this
        d_rot, d_pos = _pose_change(pose, estimate.pose)
        solved = estimate.intrinsics or ctx.intrinsics
        shift = image_shift(ctx.intrinsics, pose, estimate.pose, this.correspondences, solved)
        d_focal = abs(solved.fx / ctx.intrinsics.fx - 1.0)
        ctx.intrinsics = solved  # the next round renders with the estimated focal length
        last_shift = shift
        last_ok_pose = estimate.pose
        pose = estimate.pose
        converged_px = AREA_CONVERGED_SHIFT_PX if area else CONVERGED_SHIFT_PX
        # A focal length still moving by more than 0.1 % is not converged
        # whatever the pose did (the shift test includes it).
        if final_width and ((d_rot < params.converged_deg and d_pos < params.converged_m
                             and d_focal < 1e-3) or (
            shift < converged_px * ctx.intrinsics.width / 1632.0
        )):
            converged = True
            break
    return trial_from_round(
        best, index=index, params=params, pose=last_ok_pose, start_pose=start, rounds=n_done,
        converged=converged, origin=origin, seconds=time.perf_counter() - t_start,
        image_width=ctx.intrinsics.width, render_mode=mode, matcher=matcher,
        intrinsics=ctx.intrinsics)


def _trial_camera(t: Trial, fallback: Intrinsics) -> Intrinsics:
    """The camera a trial's pose goes with (``fallback``: the camera it started from)."""
    return t.intrinsics if (t.intrinsics is not None and t.pose is not None) else fallback


def _trial_rank(t: Trial) -> tuple:
    return (t.verified, t.pose is not None, t.q, t.metrics.get("inliers_3d", 0))


def _perturbed_priors(prior: Prior, n: int, seed: int = 0,
                      start: Pose | None = None) -> list[Pose]:
    """Starting poses spread over the prior's uncertainty (heading first:
    compass error dominates what a render shows), around ``start`` (default:
    the prior's pose)."""
    rng = np.random.default_rng(seed)
    start = start if start is not None else prior.pose
    trend, plunge, roll = start.attitude
    c = start.center
    s_ang = prior.sigma.angles_deg
    s_pos = prior.sigma.position_m
    s_alt = prior.sigma.altitude_m
    poses = []
    # A deterministic ring of heading offsets, then random draws.
    for dt in (-1.5, 1.5, -3.0, 3.0):
        poses.append(Pose.from_attitude(trend + dt * s_ang, plunge, roll, c))
    while len(poses) < n:
        dt, dp, dr = rng.normal(0, 1, 3) * np.array([1.5 * s_ang, s_ang, 0.5 * s_ang])
        dxyz = rng.normal(0, 1, 3) * np.array([s_pos, s_pos, 0.5 * s_alt])
        poses.append(Pose.from_attitude(trend + dt, plunge + dp, roll + dr, c + dxyz))
    return poses[:n]


#: Heading offsets, degrees, tried when nothing matches from the sensor pose
#: (the prior search covers ±3σ of it).
WIDE_HEADING_OFFSETS_DEG = (45.0, -45.0, 90.0, -90.0, 135.0, -135.0, 180.0)


def _good(t: Trial) -> bool:
    return t.verified and t.grade in ("excellent", "good")


#: A verified keypoint pose whose expected error is this or more (pixels at
#: 1632 px width) is refined by one area-matching trial (:func:`_refinable`).
AREA_REFINE_MIN_PX = 0.5


def _refinable(t: Trial, width: int) -> bool:
    """A good keypoint pose with an error estimate of at least
    :data:`AREA_REFINE_MIN_PX`: worth one area-matching trial from it. Below,
    blocks rarely do better (the estimate's floor is 0.3 px, and a relit
    render's shared light adds about as much)."""
    return bool(_good(t) and t.matcher == "keypoints" and t.uncertainty is not None
                and t.uncertainty.reprojection_px >= AREA_REFINE_MIN_PX * width / 1632.0)


def _is_start(t: Trial) -> bool:
    """The trial's pose is worth starting the next trial from (≥ 12 3D inliers)."""
    return t.pose is not None and t.metrics.get("inliers_3d", 0) >= 12


def _area_light(ctx: _Context, mode: str) -> str:
    """The render mode of an area-matching trial: "auto" for a model with
    photographed colours whose photo's sun is known — each round matches the
    relit render and the colours as they are, and keeps the one whose pose
    fits its blocks better (:func:`~napari_imgreg.registration.round.score_round`)
    — else ``mode``."""
    return "auto" if mode == "sunlit" and ctx.sun is not None and has_colours(ctx.scene) else mode


def _robust_stages(ctx: _Context, prior: Prior, start_prior: Pose, params: RegistrationParams,
                   trials: list[Trial], first_mode: str, options: RegistrationParams,
                   progress, rounds_of, n_budget: int, untextured: bool = False,
                   biased: bool = False):
    """Illumination-robust stages, in order of cost, each ending in a trial
    from the pose it found (so every pose is verified the same way): a
    sun-lit render; area matching from the best pose so far; edge alignment
    from the prior; MI refinement of the best pose so far. After edges and
    MI, keypoints are matched again (textured models only: a bare mesh's
    shading has no keypoints of a photo's) and then blocks by correlation.
    ``biased``: the keypoint trials ended on biased matches
    (:attr:`~napari_imgreg.registration.round.Trial.biased`), so area matching
    comes before the sun-lit keypoints. Stops at the first verified good trial."""
    mode = "sunlit" if ctx.sun is not None else first_mode
    base = len(trials)

    def render_fn(intrinsics: Intrinsics, pose: Pose, scale: float) -> RenderResult:
        """The stages' :class:`~napari_imgreg.registration.stages.pyramid.RenderFn`."""
        return ctx.render(pose, scale, mode, intrinsics)

    def stage_trial(start: Pose, origin: str, label: str, at: float, matcher: str = "keypoints",
                    far_start: bool = False):
        trial = yield from rounds_of(
            _run_trial(ctx, len(trials), start, params, origin,
                       mode=_area_light(ctx, mode) if matcher == "area" else mode,
                       matcher=matcher, far_start=far_start),
            label, base=at, span=0.5)
        trials.append(trial)
        return trial

    def follow_up(start: Pose, origin: str, what: str, at: float, extra: dict):
        """Keypoints (textured models), then area matching, from a stage's pose."""
        trial = None
        if not untextured:
            trial = yield from stage_trial(start, origin, f"matching from the {what} pose", at)
            trial.metrics.update(extra)
            ctx.check()
            if _good(trial) or not options.area_match:
                return trial
        if options.area_match:
            trial = yield from stage_trial(start, origin, f"area matching from the {what} pose",
                                           at + 0.25, matcher="area")
            trial.metrics.update(extra)
            ctx.check()
        return trial

    def sunlit_keypoints():
        best = max(trials, key=_trial_rank)
        start = best.pose if _is_start(best) else start_prior
        trial = yield from stage_trial(start, "sun-lit render", "matching a sun-lit render", base)
        ctx.check()
        return trial

    def area_matching():
        best = max(trials, key=_trial_rank)
        near = _is_start(best)
        trial = yield from stage_trial(best.pose if near else start_prior, "area matching",
                                       "area matching", base + 0.5, matcher="area",
                                       far_start=not near)
        ctx.check()
        return trial

    sunlit = options.sun_relight and mode == "sunlit" and first_mode != "sunlit"
    # Keypoints whose halves disagree are biased (Trial.biased): blocks by
    # correlation first, then keypoints on the relit render.
    order = ([area_matching] if options.area_match else []) + ([sunlit_keypoints] if sunlit else [])
    if not biased:
        order.reverse()
    for stage in order:
        trial = yield from stage()
        if _good(trial):
            return

    if options.edge_align:
        yield progress("edges", "aligning the model's edges with the photo's", (base + 1.0) / n_budget)
        t0 = time.perf_counter()
        aligned = align_edges(
            ctx.scene, ctx.photo, ctx.intrinsics, start_prior, options.edges,
            position_sigma_m=prior.sigma.position_m, search_position_m=prior.sigma.position_m,
            render_fn=render_fn, cancelled=_raising(ctx.check))
        ctx.timings["edges"] = ctx.timings.get("edges", 0.0) + time.perf_counter() - t0
        if aligned.ok:
            extra = {"edge_inlier_fraction": round(aligned.inlier_fraction, 4),
                     "edge_chamfer_px": round(aligned.score, 3)}
            trial = yield from follow_up(aligned.pose, "edges", "edge", base + 1.5, extra)
            if trial is not None and _good(trial):
                return
            if trial is None or trial.pose is None:
                trials.append(_stage_trial(len(trials), trial or trials[-1], aligned.pose,
                                           start_prior, "edges", extra, aligned.seconds,
                                           f"edges agree ({aligned.inlier_fraction:.0%} of the "
                                           "model's edge points on photo edges) but no matching "
                                           "confirms the pose: not verified",
                                           ctx.intrinsics))

    if options.dense_refine:
        best = max(trials, key=_trial_rank)
        start = best.pose if best.pose is not None else start_prior
        yield progress("dense", "refining by mutual information", (base + 2.0) / n_budget)
        t0 = time.perf_counter()
        refined = refine_pose_mi(ctx.scene, ctx.photo, ctx.intrinsics, start, options.dense,
                                 render_fn=render_fn, cancelled=_raising(ctx.check))
        ctx.timings["dense"] = ctx.timings.get("dense", 0.0) + time.perf_counter() - t0
        if refined.improved:
            extra = {"mi_nmi": round(refined.nmi, 4),
                     "mi_sharpness": round(float(getattr(refined, "sharpness", float("nan"))), 4)}
            trial = yield from follow_up(refined.pose, "mutual information", "MI", base + 2.5,
                                         extra)
            if trial is None or (trial.pose is None and not _good(trial)):
                trials.append(_stage_trial(len(trials), trial or trials[-1], refined.pose, start,
                                           "mutual information", extra, refined.seconds,
                                           "mutual information peaks here but no matching "
                                           "confirms the pose: not verified",
                                           ctx.intrinsics))


def _stage_trial(index: int, keypoint_trial: Trial, pose: Pose, start: Pose, origin: str,
                 extra: dict, seconds: float, hint: str,
                 intrinsics: Intrinsics | None = None) -> Trial:
    """A pose found by edges or mutual information that keypoints could not
    confirm: kept (it is usually far better than the prior, a start for the
    manual registration) but never graded above "poor" — an MI or edge optimum
    alone can be a wrong pose."""
    metrics = {**keypoint_trial.metrics, **extra}
    q = min(keypoint_trial.q, STAGE_Q_CEILING)
    return Trial(
        index=index, params=keypoint_trial.params, metrics=metrics, q=q,
        grade=grade_pose(q, pose_found=True, verified=False, ceiling=STAGE_Q_CEILING).name,
        hints=[hint, *keypoint_trial.hints], pose=pose,
        start_pose=start, rounds=0, converged=False, verified=False,
        residual_flow_px=float("inf"), origin=origin, seconds=seconds,
        render_mode=keypoint_trial.render_mode, intrinsics=intrinsics)


def _raising(check: Callable[[], None]) -> Callable[[], bool]:
    """A ``cancelled()`` poll for the stages that raises :class:`Cancelled` itself."""
    def poll() -> bool:
        check()
        return False
    return poll


def register_photo(
    scene: Scene,
    photo_rgb: np.ndarray,
    prior: Prior,
    params: RegistrationParams | None = None,
    photo_name: str = "",
    cancelled: Callable[[], bool] | None = None,
) -> Generator[Progress, None, Registration]:
    """Register a photo to the scene, yielding progress; returns a Registration.

    Parameters
    ----------
    scene : Scene
    photo_rgb : (H, W, 3) uint8 array
        The photo; its size must match ``prior.intrinsics``.
    prior : Prior
        Camera and prior pose (from the sensor record).
    params : RegistrationParams, optional
        By default those for the scene (:meth:`RegistrationParams.for_scene`:
        a point cloud's differ from a mesh's).
    photo_name : str
        For RESULT.json.
    cancelled : callable, optional
        Polled between steps; when it returns True, :class:`Cancelled` is raised.

    Yields
    ------
    Progress

    Returns
    -------
    Registration
        ``status`` "registered" only for a verified pose; otherwise "failed"
        with the best pose found (or the prior) and hints saying why.
    """
    params = (params or RegistrationParams.for_scene(scene)).copy()
    intr = prior.intrinsics
    h, w = photo_rgb.shape[:2]
    if (w, h) != (intr.width, intr.height):
        raise ValueError(f"photo is {w}×{h} but the camera is {intr.width}×{intr.height}")

    def check() -> None:
        if cancelled is not None and cancelled():
            raise Cancelled()

    t_total = time.perf_counter()
    ctx = _Context(scene, photo_rgb, intr, params, check)
    if scene._engine is None:
        yield Progress("prepare", 0.0, "building the ray-casting engine")
        scene.build_engine()
    trials: list[Trial] = []
    assumptions = list(prior.assumptions)
    start_prior, lift = _above_ground(scene, prior.pose)
    if lift > 0:
        assumptions.append(
            f"prior camera {EYE_HEIGHT_M - lift:+.1f} m above the model surface: "
            f"lifted to {EYE_HEIGHT_M:g} m above it"
        )
    # A lidar cloud's intensity is its appearance (it is not sun-lit).
    untextured = not has_appearance(scene)
    # Relighting needs the photo's sun, and the appearance's own light to
    # divide out: a texture's survey sun, none on an untextured mesh; a
    # scan's intensity holds no sun at all (its incidence falloff stays in
    # the albedo). Without them it does more harm than good.
    relightable = (untextured or scene.survey_sun is not None
                   or bool(getattr(scene, "is_cloud", False)))
    if params.sun_relight and prior.sun is not None and relightable:
        ctx.sun = prior.sun
        assumptions.append(f"sun from the {prior.sun_source}")
    first_mode = "sunlit" if (untextured and ctx.sun is not None) else "plain"
    robust = params.sun_relight or params.edge_align or params.dense_refine or params.area_match
    n_budget = (max(1, params.max_trials) + (1 if params.search_prior else 0)
                + (3 if robust else 0))

    def progress(stage: str, msg: str, done: float) -> Progress:
        return Progress(stage, min(0.99, done), msg, len(trials) + 1)

    current = params
    start = start_prior
    start_camera = intr
    origin = "prior"

    def rounds_of(gen, label: str, base: float | None = None, span: float = 1.0):
        # Relay a trial's rounds as progress (the trial spans ``span`` budget
        # units from ``base``, default: after the trials so far); returns the trial.
        base = len(trials) if base is None else base
        while True:
            try:
                k, n = next(gen)
            except StopIteration as stop:
                return stop.value
            yield progress("trial", f"{label}, round {k + 1}/{n}", (base + span * k / n) / n_budget)

    def search(candidates: list[Pose], label: str, trial_params: RegistrationParams,
               origin: str, min_inliers: int = 0):
        # Each start one quick trial at reduced resolution (two rounds); the
        # trials with a pose (and ``min_inliers`` 3D inliers) are returned.
        scored = []
        for k, cand in enumerate(candidates):
            yield progress("search", f"{label} ({k + 1}/{len(candidates)})",
                           (len(trials) + 0.5 * k / len(candidates)) / n_budget)
            t = run_to_end(_run_trial(ctx, -1, cand, trial_params, origin,
                                      width=min(params.match_width, 800), max_rounds=2,
                                      mode=first_mode, intrinsics=start_camera))
            if t.pose is not None and t.metrics.get("inliers_3d", 0) >= min_inliers:
                scored.append(t)
            check()
        return scored

    def then_area(trial: Trial, camera: Intrinsics, label: str):
        # A keypoint trial of an adaptation that does not verify is followed,
        # as for an unknown focal length, by blocks over the whole frame from
        # its pose, which hold (and verify) it better. Both join the trials.
        trials.append(trial)
        check()
        if not _good(trial) and robust and params.area_match and trial.pose is not None:
            area = yield from rounds_of(
                _run_trial(ctx, len(trials), trial.pose, params, trial.origin,
                           mode=_area_light(ctx, first_mode), matcher="area",
                           far_start=False, intrinsics=_trial_camera(trial, camera)),
                label)
            area.adaptation = trial.adaptation
            trials.append(area)
            check()

    # Keypoints of a bare mesh's shading rarely match a photo's rock colours:
    # one trial to try, then the structure and dense stages.
    n_keypoint_trials = 1 if (untextured and robust) else (
        params.max_trials if params.auto_adapt else 1)
    # A textured model whose photo's sun is known (see the loop).
    early_area = (robust and params.area_match and params.sun_relight and ctx.sun is not None
                  and not untextured)
    for trial_no in range(n_keypoint_trials):
        trial = yield from rounds_of(
            _run_trial(ctx, len(trials), start, current, origin, mode=first_mode,
                       intrinsics=start_camera),
            f"trial {trial_no + 1}: {current.features.name}")
        trials.append(trial)
        check()
        if trial.verified and trial.grade in ("excellent", "good"):
            break
        if trial.biased and robust and params.area_match:
            # The keypoints agree but their halves do not: a bias they share
            # (shading), which another keypoint trial shares too. Blocks
            # matched by correlation (_area_light) are next, and cheaper than
            # more keypoint trials.
            trial.adaptation = "biased matches: to area matching"
            break
        if trial_no == 0 and early_area:
            # The sun is known and the keypoints did not verify (under another
            # sun they find next to nothing, and rarely recover by adapting or
            # searching: their descriptors see the survey light): blocks on
            # the relit render, or on the texture as it is when its blocks fit
            # better (_area_light), from the prior unless this trial found a
            # start. The adaptations and the search follow if they fail too.
            near = _is_start(trial)
            trial.adaptation = "not verified, sun known: area matching"
            area_trial = yield from rounds_of(
                _run_trial(ctx, len(trials), trial.pose if near else start_prior, current,
                           "area matching", mode=_area_light(ctx, "sunlit"), matcher="area",
                           far_start=not near, intrinsics=start_camera),
                "area matching")
            trials.append(area_trial)
            check()
            if _good(area_trial):
                break
        hits = evaluate_rules(trial.metrics, current, intr.width)
        if not params.auto_adapt or not hits:
            break
        adapted = hits[0].apply(current)
        # After the early area trial its note stays in front ("...; rule 6: ...").
        before = f"{trial.adaptation}; " if trial.adaptation else ""
        if adapted == current:
            # The rule's parameter is at its limit: another trial would repeat this one.
            trial.adaptation = f"{before}rule {hits[0].rule}: nothing left to adapt"
            break
        trial.adaptation = f"{before}rule {hits[0].rule}: {hits[0].adaptation}"
        current = adapted
        if _is_start(trial):
            start, origin = trial.pose, f"trial {trial.index + 1}"
            start_camera = _trial_camera(trial, start_camera)

    best = max(trials, key=_trial_rank)
    biased = robust and params.area_match and trials[-1].biased
    if not best.verified and params.search_prior and not (untextured and robust) and not biased:
        # Search the prior's uncertainty at reduced resolution, one round each.
        candidates = [_above_ground(scene, c)[0]
                      for c in _perturbed_priors(prior, params.n_search, seed=params.seed,
                                                       start=start_prior)]
        scored = yield from search(candidates, "searching the prior's uncertainty",
                                   best.params, "search")
        if scored:
            lead = max(scored, key=lambda t: (t.metrics.get("inliers_3d", 0), t.q))
            trial = yield from rounds_of(
                _run_trial(ctx, len(trials), lead.pose, best.params, "search", mode=first_mode,
                           intrinsics=_trial_camera(lead, start_camera)),
                "refining the best start from the search", base=len(trials) + 0.5, span=0.5)
            trials.append(trial)
        best = max(trials, key=_trial_rank)

    if robust and not _good(best):
        # The stages render (and align edges, refine MI) with the best camera so far.
        ctx.intrinsics = _trial_camera(best, start_camera)
        yield from _robust_stages(ctx, prior, start_prior, best.params, trials, first_mode,
                                  params, progress, rounds_of, n_budget, untextured, biased)
        best = max(trials, key=_trial_rank)

    if params.auto_adapt and intr.focal_known and not _good(best):
        # Nothing verified with the record's focal length: when the matches of
        # a trial fit another one far better (a record 40 % off failed after
        # five trials, a record without one registers), one trial estimates it.
        refit = focal_retry_start(trials, intr)
        if refit is not None:
            fx, start = refit.fx, refit.pose
            guess = replace(intr, fx=fx, fy=fx * intr.fy / intr.fx, estimated=("fx", "fy"))
            trial = yield from rounds_of(
                _run_trial(ctx, len(trials), start, params, "focal length",
                           mode=first_mode, intrinsics=guess),
                f"estimating the focal length (the matches fit {fx:.0f} px, not "
                f"{intr.fx:.0f} px)")
            trial.adaptation = (f"the record's focal length ({intr.fx:.0f} px) estimated: its "
                                f"matches fitted {fx:.0f} px far better")
            yield from then_area(trial, guess, "area matching with the estimated focal length")
            best = max(trials, key=_trial_rank)
            estimated = _trial_camera(best, intr)
            if best.origin == "focal length" and "fx" in (estimated.estimated or ()):
                assumptions.append(
                    f"focal length of the record ({intr.fx:.1f} px) did not fit the photo: "
                    f"estimated during registration, fx = {estimated.fx:.1f} px")

    if (params.auto_adapt and params.search_prior and not untextured and not _good(best)
            and nothing_in_common(trials) is not None):
        # From the sensor pose photo and render share almost nothing, and the
        # search covered ±3σ of heading: a compass 90° off (a phone held near
        # metal, a heading logged from the wrong axis) failed after nine
        # trials. Headings all round, at reduced resolution; the best refined.
        trend, plunge, roll = start_prior.attitude
        candidates = [_above_ground(scene, Pose.from_attitude(trend + dh, plunge, roll,
                                                              start_prior.center))[0]
                      for dh in WIDE_HEADING_OFFSETS_DEG]
        scored = yield from search(candidates, "searching headings all round", params,
                                   "heading search", MIN_VERIFIED_INLIERS)
        if scored:
            lead = max(scored, key=lambda t: (t.metrics.get("inliers_3d", 0), t.q))
            trial = yield from rounds_of(
                _run_trial(ctx, len(trials), lead.pose, params, "heading search",
                           mode=first_mode, intrinsics=_trial_camera(lead, start_camera)),
                "refining the best heading", base=len(trials) + 0.5, span=0.5)
            dh = lead.pose.attitude[0] - trend
            trial.adaptation = (f"nothing in common from the sensor heading: searched headings "
                                f"all round, the best {((dh + 180) % 360) - 180:+.0f}° from it")
            yield from then_area(trial, start_camera, "area matching from the best heading")
            best = max(trials, key=_trial_rank)

    if robust and params.area_match and _refinable(best, intr.width):
        # Keypoints verified, but their pose is held by a few hundred matches
        # (and under another sun sits on shading): blocks correlated over the
        # whole frame (_area_light) usually hold it far better — an estimated
        # focal length above all. Kept only when verified and its expected
        # error is smaller.
        refined = yield from rounds_of(
            _run_trial(ctx, len(trials), best.pose, best.params, f"trial {best.index + 1}",
                       mode=_area_light(ctx, "sunlit" if ctx.sun is not None else first_mode),
                       matcher="area",
                       far_start=False, intrinsics=_trial_camera(best, start_camera)),
            "refining by area matching", base=len(trials), span=0.5)
        trials.append(refined)
        check()
        kept = (_good(refined) and refined.uncertainty is not None
                and refined.uncertainty.reprojection_px < best.uncertainty.reprojection_px)
        note = ("verified: refined by area matching" if kept
                else "verified: area matching from it was no better")
        best.adaptation = f"{best.adaptation}; {note}" if best.adaptation else note
        if kept:
            best = refined

    if params.verify:
        status = "registered" if best.verified and best.grade != "failed" else "failed"
    else:
        status = "registered" if best.metrics.get("inliers_3d", 0) >= 7 else "failed"
    pose = best.pose if best.pose is not None else prior.pose
    camera = _trial_camera(best, intr)
    if not intr.focal_known:
        if camera.focal_known or camera is intr:
            assumptions.append(
                f"focal length unknown and not estimated (no pose solved with it): the assumed "
                f"{intr.hfov_deg:.0f}° horizontal view (fx = {intr.fx:.1f} px) stands")
        else:
            assumptions.append(
                f"focal length estimated during registration: fx = fy = {camera.fx:.1f} px "
                f"({camera.hfov_deg:.1f}° horizontal view; the start was {intr.fx:.1f} px); "
                f"estimated: {', '.join(camera.estimated)}")
    # The likely cause in the inputs (record, photo) first: the quality panel
    # shows the best trial's hints, RESULT.json the result's.
    diagnosis = [d for d in diagnose(trials, best, status, prior, camera, photo_rgb,
                                     appearance=not untextured)
                 if d not in best.hints]
    best.hints[:0] = diagnosis
    hints = list(best.hints)
    if status == "failed" and not hints:
        hints = ["No verified pose: try the manual control-point registration."]
    if status == "failed" and ctx.sun is None and bool(getattr(scene, "is_cloud", False)):
        # First: on a scan this is the missing input a user can supply, and
        # the diagnosis below cannot see it (it blames the pose or the photo).
        why = str(getattr(prior, "sun_source", "") or "").removeprefix("unknown: ") or "no capture time"
        hints.insert(0, (
            f"No sun is known for this photo ({why}): a lidar scan's intensity holds no light, so "
            "its render was not lit as the photo is, and photo and render often share too little "
            "to match. Give the photo its capture time with a time zone (the sensor record's "
            "\"time\", e.g. \"2024-04-04T08:15:10+00:00\", with the model's georef.json) or its sun "
            "(\"sun\": azimuth and elevation), then register again; or register with control "
            "points."))
    if status == "registered" and ctx.sun is None and bool(getattr(scene, "is_cloud", False)):
        # The known blind spot of the error estimate (method §4): the scan's
        # unlit render, edges and MI agree on a pose biased by the photo's light.
        hints.append(
            "No sun is known for this photo, so the scan's render was not relit, and the error "
            "estimate counts all of its contrast as light no check can see. Give the photo its "
            "capture time with a time zone (or its sun), or check the pose with a few control "
            "points before mapping on it.")
    timings = dict(ctx.timings)
    timings["total"] = time.perf_counter() - t_total
    yield Progress("done", 1.0, f"{'registered' if status == 'registered' else 'not registered'}"
                                f" — {outcome_words(status, best.grade)}, Q = {best.q:.2f}")
    return Registration(
        status=status,
        photo=photo_name,
        intrinsics=camera,
        pose=pose,
        prior=prior,
        metrics=best.metrics,
        q=best.q,
        grade=best.grade,
        hints=hints,
        trials=trials,
        timings_s=timings,
        best_trial=best.index,
        assumptions=assumptions,
        uncertainty=best.uncertainty,
    )


def run_to_end(gen: Generator[Progress, None, Any], on_progress=None) -> Any:
    """Drive a progress generator to its return value."""
    while True:
        try:
            p = next(gen)
        except StopIteration as stop:
            return stop.value
        if on_progress is not None:
            on_progress(p)


def register(
    scene: Scene,
    photo_rgb: np.ndarray,
    prior: Prior,
    params: RegistrationParams | None = None,
    photo_name: str = "",
    on_progress: Callable[[Progress], None] | None = None,
) -> Registration:
    """Blocking form of :func:`register_photo`."""
    return run_to_end(register_photo(scene, photo_rgb, prior, params, photo_name), on_progress)
