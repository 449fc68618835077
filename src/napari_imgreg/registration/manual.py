"""Manual control-point registration: a pose from picked pairs, scored like a trial.

When the automatic registration cannot match the photo to the render (extreme
light, a prior that is far off), the geologist picks the same points on the
photo and on a *reference render* of the model (Kehl et al. 2018, "Creating
Reference Images for Manual Registration"). The reference render's ``xyz`` map
lifts its picks to 3D, so each pair becomes a 2D–3D correspondence and the
photo's pose follows by PnP (:func:`solve_manual`); with six or more pairs the
focal length can be solved too. The result is scored by the automatic
registration's own round (:func:`score_pose`, through
:func:`napari_imgreg.registration.round.score_round`), so its seven metrics,
Q and grade mean the same as an automatic trial's.

Hand corrections of a pose (nudges, the terrain map, undo) are in
:mod:`napari_imgreg.adjust`; the 3D viewer's camera conversions in
:mod:`napari_imgreg.widgets._layers`. Nothing here imports Qt or napari.

Conventions are the package's: pixels (x = column, y = row) with the first
pixel's centre at (0, 0); the model frame is local ENU metres; poses are
``cam_from_world`` (:class:`~napari_imgreg.camera.Pose`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from .._deprecated import forward_moved_names
from ..camera import Intrinsics, Pose
from .params import RegistrationParams
from .pipeline import Cancelled, _Context
from .pose import PoseParams, estimate_pose, reprojection_errors
from .round import Trial, score_round, trial_from_round
from ..scene import Scene

__all__ = [
    "MIN_PAIRS",
    "MIN_PAIRS_FOCAL",
    "ManualSolution",
    "solve_manual",
    "score_pose",
]

#: Pairs needed for a pose (EPnP's minimum).
MIN_PAIRS = 4
#: Pairs needed to solve the focal length as well.
MIN_PAIRS_FOCAL = 6

#: Names that moved out of this module in 0.2 -> their new module. The old
#: name keeps working with a DeprecationWarning (:func:`__getattr__`).
_MOVED = {
    **dict.fromkeys(
        ("nudge_pose", "pose_at_ground", "height_above_ground", "turn_toward", "PoseHistory",
         "TerrainMap", "terrain_map"), "napari_imgreg.adjust"),
    **dict.fromkeys(
        ("camera_from_view", "view_from_camera", "frustum_segments"),
        "napari_imgreg.widgets._layers"),
    **dict.fromkeys(("reduce_for_matching", "filtered_for_matching"),
                    "napari_imgreg.registration.filters"),
    "metric_trend": "napari_imgreg.registration.quality",
    "save_pose_to_record": "napari_imgreg.prior",
}
__getattr__ = forward_moved_names(__name__, _MOVED)


# ===================================================== manual registration
@dataclass
class ManualSolution:
    """A pose solved from manually picked pairs.

    Attributes
    ----------
    ok : bool
    pose : Pose or None
        ``cam_from_world`` of the photo; None when ``ok`` is False.
    intrinsics : Intrinsics
        The photo's camera (with the solved focal length when
        ``focal_solved``).
    errors_px : (N,) float array
        Reprojection error of every pair under the pose, photo pixels (NaN
        without a pose or for a pair without a 3D point).
    inliers : (N,) bool array
        Pairs that agree with the pose (error below the threshold).
    threshold_px : float
        The agreement threshold used.
    focal_solved : bool
    method : str
        ``"ransac-epnp"`` (six or more pairs) or ``"pnp"`` (all pairs).
    reason : str
        Why it failed ("" when ok).
    """

    ok: bool
    pose: Pose | None
    intrinsics: Intrinsics
    errors_px: np.ndarray
    inliers: np.ndarray
    threshold_px: float
    focal_solved: bool = False
    method: str = ""
    reason: str = ""

    @property
    def rms_px(self) -> float:
        """RMS reprojection error of the inliers, pixels (NaN without)."""
        if not self.ok or not self.inliers.any():
            return float("nan")
        return float(np.sqrt(np.mean(self.errors_px[self.inliers] ** 2)))

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


def _pnp_candidates(
    intr: Intrinsics, p3: np.ndarray, p2: np.ndarray, initial: Pose | None
) -> list[Pose]:
    """Poses from several PnP solvers on all points (3D points already centred)."""
    K, dist = intr.K, intr.dist_coeffs
    out: list[Pose] = []
    flags = [cv2.SOLVEPNP_EPNP, cv2.SOLVEPNP_SQPNP]
    for flag in flags:
        try:
            ok, rvec, tvec = cv2.solvePnP(p3, p2, K, dist, flags=flag)
        except cv2.error:
            continue
        if ok:
            out.append(Pose.from_rvec_tvec(rvec, tvec))
    if initial is not None:
        rvec0 = initial.rvec.reshape(3, 1).copy()
        tvec0 = initial.t.reshape(3, 1).copy()
        try:
            ok, rvec, tvec = cv2.solvePnP(
                p3, p2, K, dist, rvec0, tvec0, useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE
            )
        except cv2.error:
            ok = False
        if ok:
            out.append(Pose.from_rvec_tvec(rvec, tvec))
    refined = []
    for pose in out:
        try:
            rvec, tvec = cv2.solvePnPRefineLM(
                p3, p2, K, dist, pose.rvec.reshape(3, 1).copy(), pose.t.reshape(3, 1).copy()
            )
            refined.append(Pose.from_rvec_tvec(rvec, tvec))
        except cv2.error:
            refined.append(pose)
    return refined


def _best_pose(intr: Intrinsics, p3: np.ndarray, p2: np.ndarray, poses: list[Pose]) -> Pose | None:
    best, best_rms = None, np.inf
    for pose in poses:
        if not (pose.transform(p3)[:, 2] > 0).all():
            continue  # cheirality: every picked point in front of the camera
        err = reprojection_errors(intr, pose, p3, p2)
        rms = float(np.sqrt(np.mean(err**2)))
        if rms < best_rms:
            best, best_rms = pose, rms
    return best


def _with_focal(intr: Intrinsics, f: float) -> Intrinsics:
    fy = f * intr.fy / intr.fx
    return Intrinsics(intr.width, intr.height, f, fy, intr.cx, intr.cy, intr.dist)


def _solve_focal(
    intr: Intrinsics, p3: np.ndarray, p2: np.ndarray, pose: Pose
) -> tuple[Intrinsics, Pose]:
    """Focal length and pose together: a coarse focal search, then joint least squares."""
    from scipy.optimize import least_squares

    f0 = intr.fx
    best = (np.inf, f0, pose)
    for f in f0 * np.geomspace(0.5, 2.0, 25):
        cand = _with_focal(intr, f)
        p = _best_pose(cand, p3, p2, _pnp_candidates(cand, p3, p2, pose))
        if p is None:
            continue
        rms = float(np.sqrt(np.mean(reprojection_errors(cand, p, p3, p2) ** 2)))
        if rms < best[0]:
            best = (rms, f, p)
    _, f_start, p_start = best

    def residuals(v: np.ndarray) -> np.ndarray:
        cand = _with_focal(intr, f0 * math.exp(v[6]))
        proj, _ = cv2.projectPoints(p3, v[:3], v[3:6], cand.K, cand.dist_coeffs)
        return (proj.reshape(-1, 2) - p2).ravel()

    v0 = np.concatenate([p_start.rvec, p_start.t, [math.log(f_start / f0)]])
    sol = least_squares(residuals, v0, method="lm", x_scale="jac")
    f = f0 * math.exp(sol.x[6])
    return _with_focal(intr, f), Pose.from_rvec_tvec(sol.x[:3], sol.x[3:6])


def solve_manual(
    intrinsics: Intrinsics,
    photo_points: np.ndarray,
    points_3d: np.ndarray,
    initial: Pose | None = None,
    solve_focal: bool = False,
    threshold_px: float | None = None,
) -> ManualSolution:
    """The photo's pose from manually picked 2D–3D pairs.

    With six or more pairs, RANSAC EPnP with refinement
    (:func:`napari_imgreg.registration.pose.estimate_pose`) sets a mis-picked pair aside;
    with four or five, every pair is used: EPnP, SQPnP and (from ``initial``)
    iterative PnP, each refined by Levenberg–Marquardt, the one with the
    smallest RMS error that keeps all points in front of the camera wins.
    With ``solve_focal`` and six or more agreeing pairs, the focal length
    (square pixels, principal point fixed) is solved with the pose: a
    search over 0.5–2× the current focal length, then joint least squares.

    Parameters
    ----------
    intrinsics : Intrinsics
        The photo's camera.
    photo_points : (N, 2) array
        Picked pixels (x, y) in the photo.
    points_3d : (N, 3) array
        The same points on the model (model frame, metres), e.g. lifted
        through a reference render's ``xyz`` map; rows with NaN are ignored.
    initial : Pose, optional
        A pose near the answer (the prior), used as one more starting point.
    solve_focal : bool
        Also solve the focal length (needs :data:`MIN_PAIRS_FOCAL` pairs).
    threshold_px : float, optional
        A pair agrees with the pose within this many pixels; default 0.8 % of
        the photo width, at least 8 px.

    Returns
    -------
    ManualSolution
        ``ok`` False with a ``reason`` when the pairs do not determine a
        pose (too few, degenerate); never raises for that.

    Notes
    -----
    PnP is degenerate when the points are (nearly) collinear; spread the
    picks over the photo. Solving the focal length needs depth variety:
    with all points on one plane seen square-on, focal length and distance
    trade off.

    Examples
    --------
    >>> import numpy as np
    >>> from napari_imgreg.camera import Intrinsics, Pose
    >>> rng = np.random.default_rng(0)
    >>> intr = Intrinsics(1000, 750, 800.0, 800.0, 499.5, 374.5)
    >>> truth = Pose.from_attitude(10.0, 5.0, 1.0, np.array([0.0, -50.0, 2.0]))
    >>> pts = np.c_[rng.uniform(-20, 20, 8), rng.uniform(-5, 5, 8), rng.uniform(-5, 15, 8)]
    >>> sol = solve_manual(intr, truth.project(intr, pts), pts)
    >>> sol.ok, sol.pose.rotation_error_deg(truth) < 1e-4, sol.rms_px < 1e-6
    (True, True, True)
    """
    p2 = np.asarray(photo_points, np.float64).reshape(-1, 2)
    p3 = np.asarray(points_3d, np.float64).reshape(-1, 3)
    if len(p2) != len(p3):
        raise ValueError(f"{len(p2)} photo points but {len(p3)} 3D points")
    n = len(p2)
    thr = float(threshold_px) if threshold_px else max(8.0, 0.008 * intrinsics.width)
    valid = np.isfinite(p2).all(axis=1) & np.isfinite(p3).all(axis=1)
    nan = np.full(n, np.nan)

    def fail(reason: str) -> ManualSolution:
        return ManualSolution(False, None, intrinsics, nan.copy(), np.zeros(n, bool), thr,
                              reason=reason)

    m = int(valid.sum())
    if m < MIN_PAIRS:
        missing = n - m
        extra = f" ({missing} without a 3D point)" if missing else ""
        return fail(f"{m} usable pairs{extra}: need at least {MIN_PAIRS}")
    q2, q3 = p2[valid], p3[valid]
    centre = q3.mean(axis=0)
    c3 = q3 - centre
    if np.linalg.svd(c3, compute_uv=False)[1] < 1e-6 * max(1.0, np.abs(c3).max()):
        return fail("the picked points are (nearly) on a line: spread them over the photo")

    def uncentre(p: Pose) -> Pose:
        return Pose(p.R, p.t - p.R @ centre)

    def centred(p: Pose) -> Pose:
        return Pose(p.R, p.t + p.R @ centre)

    init_c = centred(initial) if initial is not None else None
    pose_c, method = None, ""
    sel = np.ones(m, bool)
    if m >= 6:
        est = estimate_pose(
            intrinsics, c3, q2,
            PoseParams(reprojection_error_px=thr, iterations=2000, confidence=0.999, refine=True),
        )
        if est.ok:
            pose_c, method, sel = est.pose, "ransac-epnp", est.inliers
    if pose_c is None:
        pose_c = _best_pose(intrinsics, c3, q2, _pnp_candidates(intrinsics, c3, q2, init_c))
        method = "pnp"
        if pose_c is None:
            return fail("no pose keeps all picked points in front of the camera")
    intr = intrinsics
    focal_solved = False
    if solve_focal:
        if int(sel.sum()) < MIN_PAIRS_FOCAL:
            pass  # not enough agreeing pairs: keep the focal length (caller sees focal_solved)
        else:
            intr, pose_c = _solve_focal(intrinsics, c3[sel], q2[sel], pose_c)
            focal_solved = True
    pose = uncentre(pose_c)
    errors = nan.copy()
    errors[valid] = reprojection_errors(intr, pose, q3, q2)
    inliers = np.zeros(n, bool)
    inliers[valid] = errors[valid] < thr
    if not (pose.transform(q3[inliers[valid]])[:, 2] > 0).all():
        return fail("the pose puts picked points behind the camera")
    if inliers.sum() < MIN_PAIRS:
        return fail(f"only {int(inliers.sum())} pairs agree with any pose within {thr:.0f} px")
    return ManualSolution(True, pose, intr, errors, inliers, thr, focal_solved, method)


# ================================================================ scoring
def score_pose(
    scene: Scene,
    photo_rgb: np.ndarray,
    intrinsics: Intrinsics,
    pose: Pose,
    params: RegistrationParams | None = None,
    origin: str = "manual",
    cancelled: Callable[[], bool] | None = None,
) -> Trial:
    """Score a given pose with the seven metrics of an automatic trial.

    One round of the automatic registration from ``pose``
    (:func:`~napari_imgreg.registration.round.score_round`): the model is
    rendered from it, photo and render are filtered, matched and verified,
    and the matched render keypoints are lifted to 3D; but instead of
    estimating a pose, the *given* pose is tested: a 3D inlier is a
    correspondence whose 3D point projects within
    ``params.pose.reprojection_error_px`` of its photo keypoint, and the
    reprojection error is their mean. The render is from a pose close to the
    photo's, so it is matched as the automatic rounds after the first are
    (luminance features only, guided when ``guided_radius_px`` > 0). The pose
    is *verified* as an automatic trial is
    (:func:`~napari_imgreg.registration.round.trial_from_round`): enough 3D
    inliers and photo and render keypoints coincide (small residual flow); an
    unverified pose is graded "fair" at best.

    Parameters
    ----------
    scene : Scene
    photo_rgb : (H, W, 3) uint8 array
    intrinsics : Intrinsics
        The photo's camera.
    pose : Pose
        The pose to score.
    params : RegistrationParams, optional
        Filters, features, matching width and PnP threshold.
    origin : str
        Stored in the returned trial (``"manual"``).
    cancelled : callable, optional
        Polled between steps; raises :class:`napari_imgreg.registration.pipeline.Cancelled`.

    Returns
    -------
    Trial
        With ``pose`` set to the given pose, ``rounds`` 0 and the
        correspondences for drawing.
    """
    t_start = time.perf_counter()
    params = (params or RegistrationParams()).copy()
    w, h = intrinsics.width, intrinsics.height
    if photo_rgb.shape[:2] != (h, w):
        raise ValueError(
            f"photo is {photo_rgb.shape[1]}×{photo_rgb.shape[0]} but the camera is {w}×{h}")

    def check() -> None:
        if cancelled is not None and cancelled():
            raise Cancelled()

    source = _Context(scene, photo_rgb, intrinsics, params, check)
    last = score_round(source, pose, params, params.match_width, near=True, solve=False)
    return trial_from_round(
        last, index=-1, params=params, pose=pose, start_pose=pose, rounds=0, converged=True,
        origin=origin, seconds=time.perf_counter() - t_start, image_width=w)
