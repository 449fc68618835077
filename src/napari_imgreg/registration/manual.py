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

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from .._deprecated import forward_moved_names
from ..camera import Intrinsics, Pose
from . import explain
from .params import RegistrationParams
from .pipeline import Cancelled, Registration, _Context
from .pose import PoseParams, estimate_pose, reprojection_errors
from .quality import GRADES
from .round import (MIN_VERIFIED_INLIERS, STAGE_Q_CEILING, Trial, grade_pose, score_round,
                    trial_from_round)
from .uncertainty import UNCERTAIN_PX, Uncertainty
from ..prior import Prior
from ..scene import Scene

__all__ = [
    "MIN_PAIRS",
    "MIN_PAIRS_FOCAL",
    "CLICK_SIGMA_PX",
    "MAX_EXPECTED_ROTATION_DEG",
    "pair_uncertainty",
    "ManualSolution",
    "solve_manual",
    "score_pose",
    "registers",
    "adopt_pair_uncertainty",
    "register_from_pairs",
    "gui_hint",
    "RUN_FROM_IT",
    "RUN_FROM_IT_GUI",
]

#: Pairs needed for a pose (EPnP's minimum).
MIN_PAIRS = 4
#: Pairs needed to solve the focal length as well.
MIN_PAIRS_FOCAL = 6
#: Least error of a picked pair, pixels of the photo per axis: a click on the
#: photo and one on the reference (each about 1 px), however well the pairs fit.
CLICK_SIGMA_PX = 1.5
#: A pose whose expected rotation error (:func:`pair_uncertainty`) reaches this
#: is no pose: the pairs lie nearly on a line, and fit a pose 20–90° off to a
#: fraction of a pixel.
MAX_EXPECTED_ROTATION_DEG = 10.0

#: How the hint of a manual pose the photo's features confirm names the next
#: step (a Run from it): for RESULT.json and the command line, which reach it
#: both ways, and for the workbench (:func:`gui_hint`), which shows its own.
RUN_FROM_IT = "(the workbench's Run, or register --prior with this result)"
RUN_FROM_IT_GUI = "(Register tab → Run)"

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

#: Grade names, best first.
GRADE_NAMES = [g.name for g in GRADES]


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
        ``"ransac-epnp"`` (six or more pairs), ``"ransac-p4pf"`` (six or
        more pairs, focal length solved) or ``"pnp"`` (all pairs).
    reason : str
        Why it failed ("" when ok).
    uncertainty : Uncertainty or None
        The pose's expected error from the agreeing pairs' geometry and click
        noise (:func:`pair_uncertainty`); None when ``ok`` is False. Not the
        RMS: four pairs fit any pose almost exactly, so their RMS says
        nothing of the error.
    warning : str
        Why the pose may be wrong though solved ("" when nothing is
        suspect): pairs set aside that agree under another focal length.
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
    uncertainty: Uncertainty | None = None
    warning: str = ""

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


def _count_distinct(photo_px: np.ndarray, points_3d: np.ndarray, tol_px: float = 2.0) -> int:
    """How many pairs are different points: a pair whose photo pick lies
    within ``tol_px`` of an earlier one's, or whose 3D point is an earlier
    one's (within a millionth of the points' extent), is the same point
    picked twice and adds nothing to fix the pose."""
    extent = float(np.ptp(points_3d, axis=0).max()) if len(points_3d) else 0.0
    tol_m = 1e-6 * max(extent, 1.0)
    kept: list[int] = []
    for i in range(len(photo_px)):
        same = any(np.linalg.norm(photo_px[i] - photo_px[k]) < tol_px
                   or np.linalg.norm(points_3d[i] - points_3d[k]) < tol_m for k in kept)
        if not same:
            kept.append(i)
    return len(kept)


def pair_uncertainty(
    intrinsics: Intrinsics, pose: Pose, points_3d: np.ndarray, photo_points: np.ndarray,
    focal_free: bool = False, click_sigma_px: float = CLICK_SIGMA_PX,
) -> Uncertainty:
    """The expected error of a pose solved from picked pairs.

    The pose's covariance from the pairs' geometry, σ² (JᵀJ)⁻¹ with J the
    Jacobian of the pairs' reprojections by rotation, translation (and the
    focal length when it is free), propagated to the camera centre, the
    rotation and the frame's pixels. σ is the larger of the residuals' estimate
    (their sum of squares over the degrees of freedom left) and
    ``click_sigma_px``: with four pairs two numbers are left over, and an
    RMS near 0 px is luck, not precision.

    Parameters
    ----------
    intrinsics : Intrinsics
        The camera of the pose (with the solved focal length).
    pose : Pose
    points_3d : (N, 3) array
        The agreeing pairs' 3D points, model frame.
    photo_points : (N, 2) array
        Their photo pixels (x, y).
    focal_free : bool
        The focal length is not known for sure: solved with the pose, or an
        assumed value. Its freedom is included (with an assumed focal length
        and fewer than :data:`MIN_PAIRS_FOCAL` pairs, the error is then
        large or infinite: the pairs cannot tell focal length from distance).
    click_sigma_px : float
        Least error of one pair, pixels per axis.

    Returns
    -------
    Uncertainty
        ``reprojection_px``: the median over the frame (a grid of the photo
        at the pairs' median depth) of the expected distance between where
        the solved and the true pose put a model point (RMS of the 2D
        error); ``position_m``, ``rotation_deg``: RMS errors of the camera
        centre and rotation; ``focal_px`` when free. Infinite when the pairs
        do not fix the pose (a singular geometry).
    """
    p3 = np.asarray(points_3d, np.float64).reshape(-1, 3)
    p2 = np.asarray(photo_points, np.float64).reshape(-1, 2)
    centre = p3.mean(axis=0)
    c3 = p3 - centre
    pose_c = Pose(pose.R, pose.t + pose.R @ centre)
    f0 = intrinsics.fx
    n_par = 7 if focal_free else 6
    v0 = np.concatenate([pose_c.rvec, pose_c.t, [0.0]])[:n_par]

    def project(v: np.ndarray, points: np.ndarray = c3) -> np.ndarray:
        intr = _with_focal(intrinsics, f0 * math.exp(v[6])) if len(v) > 6 else intrinsics
        proj, _ = cv2.projectPoints(points, v[:3], v[3:6], intr.K, intr.dist_coeffs)
        return proj.reshape(-1, 2)

    # The model seen over the frame, approximated by a 5 × 5 grid of the
    # photo at the pairs' median depth: the pairs themselves are where the
    # fitted pose errs least.
    depth = float(np.median(pose_c.transform(c3)[:, 2]))
    gx, gy = np.meshgrid(np.linspace(0, intrinsics.width - 1, 5),
                         np.linspace(0, intrinsics.height - 1, 5))
    cam = np.c_[(gx.ravel() - intrinsics.cx) / intrinsics.fx,
                (gy.ravel() - intrinsics.cy) / intrinsics.fy, np.ones(gx.size)] * depth
    frame = (cam - pose_c.t) @ pose_c.R  # camera -> centred model frame

    def camera(v: np.ndarray) -> np.ndarray:
        """Centre (model frame) and the rotation vector from the solved
        rotation: its length is the rotation's error angle."""
        p = Pose.from_rvec_tvec(v[:3], v[3:6])
        m = p.R @ pose_c.R.T  # near the identity: its skew part is the small turn
        turn = 0.5 * np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])
        return np.concatenate([p.center + centre, turn])

    def jacobian(fun, v: np.ndarray) -> np.ndarray:
        steps = np.r_[np.full(3, 1e-6), np.full(3, 1e-6 * max(1.0, np.abs(v[3:6]).max())),
                      np.full(len(v) - 6, 1e-6)]
        cols = []
        for k, h in enumerate(steps):
            dv = np.zeros_like(v)
            dv[k] = h
            cols.append((np.ravel(fun(v + dv)) - np.ravel(fun(v - dv))) / (2 * h))
        return np.stack(cols, axis=1)

    inf = Uncertainty(math.inf, math.inf, math.inf, focal_px=math.inf if focal_free else None,
                      basis="control points")
    J = jacobian(project, v0)
    residual = (project(v0) - p2).ravel()
    dof = residual.size - n_par
    sigma = click_sigma_px
    if dof > 0:
        sigma = max(sigma, float(np.sqrt(residual @ residual / dof)))
    try:
        cov = sigma**2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return inf
    if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) < 0):
        return inf
    J_cam = jacobian(camera, v0)
    cov_cam = J_cam @ cov @ J_cam.T
    # Each frame point's 2D error: its two rows of the Jacobian, traced.
    J_frame = jacobian(lambda v: project(v, frame), v0)
    per_point = np.einsum("ij,jk,ik->i", J_frame, cov, J_frame).reshape(-1, 2).sum(axis=1)
    focal = None
    if focal_free:
        focal = f0 * math.sqrt(max(cov[6, 6], 0.0))
    return Uncertainty(
        reprojection_px=float(np.median(np.sqrt(np.maximum(per_point, 0.0)))),
        position_m=float(np.sqrt(max(np.trace(cov_cam[:3, :3]), 0.0))),
        rotation_deg=float(np.degrees(np.sqrt(max(np.trace(cov_cam[3:, 3:]), 0.0)))),
        focal_px=focal, basis="control points")


def _focal_warning(intr: Intrinsics, c3: np.ndarray, q2: np.ndarray, thr: float,
                   n_agree: int, agree_errors: np.ndarray) -> str:
    """A warning when the pairs fit another focal length clearly better.

    A focal length 40 % off in the photo's record puts the pose ~20 m off
    with a residual of a few pixels only, within the agreement threshold, or
    sets good pairs aside; P4Pf (the focal length free) then keeps more
    pairs, or fits the same ones with a residual 1.5× smaller.
    """
    est = estimate_pose(intr, c3, q2, PoseParams(reprojection_error_px=thr, iterations=2000,
                                                 confidence=0.999, refine=True, solver="p4pf"))
    if not est.ok or est.intrinsics is None:
        return ""
    f = est.intrinsics.fx
    rms = float(np.sqrt(np.mean(agree_errors**2))) if len(agree_errors) else math.inf
    rms_free = float(np.sqrt(np.mean(est.errors_px[est.inliers] ** 2)))
    better = est.n_inliers > n_agree or (
        est.n_inliers == n_agree and rms > max(1.5 * rms_free, CLICK_SIGMA_PX))
    if not better or abs(f / intr.fx - 1.0) < 0.05:
        return ""
    return (f"the pairs fit a focal length of {f:.0f} px better ({est.n_inliers} agree, RMS "
            f"{rms_free:.1f} px) than the photo's {intr.fx:.0f} px ({n_agree}, RMS {rms:.1f} px): "
            "if its camera may be wrong, solve the focal length too")


def _with_focal(intr: Intrinsics, f: float) -> Intrinsics:
    fy = f * intr.fy / intr.fx
    return Intrinsics(intr.width, intr.height, f, fy, intr.cx, intr.cy, intr.dist,
                      estimated=intr.estimated)


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
    (square pixels, principal point fixed) is solved with the pose: P4Pf in
    RANSAC finds it and the pairs that agree (at a wrong focal length RANSAC
    EPnP would set good pairs aside), then a search over 0.5–2× that focal
    length and joint least squares refine it. A pair picked twice (the same
    photo pixel or the same 3D point) counts once towards the minimum.

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
        A pair agrees with the pose within this many pixels; default 1.2 % of
        the photo width, at least 12 px.

    Returns
    -------
    ManualSolution
        ``ok`` False with a ``reason`` when the pairs do not determine a
        pose (too few, degenerate); never raises for that.

    Notes
    -----
    PnP is degenerate when the points are (nearly) collinear; spread the
    picks over the photo. Nearly collinear pairs fit a pose far off to a
    fraction of a pixel, so a pose whose expected rotation error
    (:attr:`ManualSolution.uncertainty`) reaches
    :data:`MAX_EXPECTED_ROTATION_DEG` is refused. Solving the focal length needs depth variety:
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
    # Two clicks of up to 3 px each put a good pair ~12 px off at 2σ: a tighter
    # default marked a good pair a mis-pick in most solves at that noise.
    thr = float(threshold_px) if threshold_px else max(12.0, 0.012 * intrinsics.width)
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
    distinct = _count_distinct(q2, q3)
    if distinct < MIN_PAIRS:
        return fail(f"{distinct} different pairs ({m - distinct} picked twice): "
                    f"need at least {MIN_PAIRS}")
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
    # The focal length the pairs are first tested with: the photo's, or,
    # when it is to be solved, the one P4Pf finds in RANSAC. With a wrong
    # focal length, RANSAC EPnP sets good pairs aside as mis-picks and the
    # focal length is then fitted to the few it kept.
    intr_start = intrinsics
    ransac = PoseParams(reprojection_error_px=thr, iterations=2000, confidence=0.999, refine=True)
    if solve_focal and distinct >= MIN_PAIRS_FOCAL:
        est = estimate_pose(intrinsics, c3, q2, dataclasses.replace(ransac, solver="p4pf"))
        if est.ok and est.n_inliers >= MIN_PAIRS_FOCAL and est.intrinsics is not None:
            intr_start = _with_focal(intrinsics, est.intrinsics.fx)
            pose_c, method, sel = est.pose, "ransac-p4pf", est.inliers
    if pose_c is None and m >= 6:
        est = estimate_pose(intrinsics, c3, q2, ransac)
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
        if int(sel.sum()) < MIN_PAIRS_FOCAL or distinct < MIN_PAIRS_FOCAL:
            pass  # not enough agreeing pairs: keep the focal length (caller sees focal_solved)
        else:
            intr, pose_c = _solve_focal(intr_start, c3[sel], q2[sel], pose_c)
            # RESULT.json's camera.estimated: the focal length was solved, not read.
            intr = dataclasses.replace(
                intr, estimated=tuple(dict.fromkeys((*intr.estimated, "fx", "fy"))))
            focal_solved = True
    pose = uncentre(pose_c)
    errors = nan.copy()
    errors[valid] = reprojection_errors(intr, pose, q3, q2)
    inliers = np.zeros(n, bool)
    inliers[valid] = errors[valid] < thr
    if not (pose.transform(q3[inliers[valid]])[:, 2] > 0).all():
        return fail("the pose puts picked points behind the camera")
    if inliers.sum() < MIN_PAIRS:
        agree = int(inliers.sum())
        return fail(f"only {agree} pair{'' if agree == 1 else 's'} agree{'s' if agree == 1 else ''} "
                    f"with any pose within {thr:.0f} px")
    # An assumed focal length (none in the photo's record) is as uncertain as a solved one.
    focal_free = focal_solved or not intr.focal_known
    unc = pair_uncertainty(intr, pose, p3[inliers], p2[inliers], focal_free)
    if not unc.rotation_deg < MAX_EXPECTED_ROTATION_DEG:
        return fail(f"these pairs do not fix the pose (expected error ≈ {unc.rotation_deg:.0f}°, "
                    f"{unc.position_m:.0f} m): spread them over the photo and over distance "
                    "(pairs nearly on a line fit a pose far off), or solve the focal length "
                    "too if the photo's may be wrong")
    warning = ""
    if not focal_solved and distinct >= MIN_PAIRS_FOCAL:
        warning = _focal_warning(intr, c3, q2, thr, int(inliers.sum()), errors[inliers])
    return ManualSolution(True, pose, intr, errors, inliers, thr, focal_solved, method,
                          uncertainty=unc, warning=warning)


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
    unverified pose is graded "fair" at best, and "poor" at best when fewer
    than ``MIN_VERIFIED_INLIERS`` matches agree with it (an automatic round
    would have found no pose there).

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
        With ``pose`` set to the given pose, ``rounds`` 0, the
        correspondences for drawing and, first among its hints, how far
        the photo's features confirm the pose and what to do next (a
        verified pose has no other).
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
    trial = trial_from_round(
        last, index=-1, params=params, pose=pose, start_pose=pose, rounds=0, converged=True,
        origin=origin, seconds=time.perf_counter() - t_start, image_width=w)
    inliers = int(trial.metrics.get("inliers_3d") or 0)
    # A verified pose keeps no advice of the six rules (stricter matching,
    # other filters): it is for the next automatic trial, and a given pose is
    # improved by better pairs or by a Run from it. An unverified one keeps
    # them after its own hint: they say why the matches do not confirm it.
    rule_hints = [] if trial.verified else trial.hints
    if inliers < MIN_VERIFIED_INLIERS:
        # An automatic round whose matches agree with no pose has none and
        # fails; a given pose that they do not support either must not read
        # "fair" on Q from the point counts alone.
        capped = grade_pose(trial.q, pose_found=True, verified=False, ceiling=STAGE_Q_CEILING)
        if GRADE_NAMES.index(capped.name) > GRADE_NAMES.index(trial.grade):
            trial.grade = capped.name
        trial.hints = [(
            f"The photo's features confirm this pose at only {inliers} points (need "
            f"{MIN_VERIFIED_INLIERS}): it rests on the control points alone, so it is "
            "graded \"poor\" at best — check the overlay at the pairs.")] + rule_hints
    else:
        # Clicks are a pixel or two off, the photo's matches a few tenths: on
        # the sample's photos one Run from a pose of 8 pairs clicked 1.5 px off
        # took it from 0.7-1.6 px to 0.1-0.4 px at the check points.
        trial.hints = [(
            f"{inliers} of the photo's features agree with this pose: one Run from it "
            f"{RUN_FROM_IT} refines it with them, "
            "from the clicks' pixel or two to a few tenths of a pixel.")] + rule_hints
    return trial


def gui_hint(hint: str) -> str:
    """A trial's hint in the workbench's words: the command-line way to the
    next step (:data:`RUN_FROM_IT`) left out. Other hints are returned as
    they are; RESULT.json and the command line keep the hint as made."""
    return hint.replace(RUN_FROM_IT, RUN_FROM_IT_GUI)


# ====================================================== a manual result
def adopt_pair_uncertainty(trial: Trial, solution: ManualSolution) -> None:
    """Give a scored manual pose the pairs' expected error, and a grade that agrees with it.

    :func:`score_pose` estimates no error of its own (its matches test the
    given pose, they do not solve one), so the pairs' estimate
    (:func:`pair_uncertainty`) is the pose's: shown, written as RESULT.json's
    ``uncertainty`` and projected with. A grade above "fair" is not kept
    when that estimate is not small (as for an automatic trial,
    :func:`~napari_imgreg.registration.round.trial_from_round`): the photo's
    matches may agree with the pose, but "good" must not stand beside an
    expected error of 4 px.

    Parameters
    ----------
    trial : Trial
        From :func:`score_pose`; changed in place.
    solution : ManualSolution
    """
    if trial.uncertainty is not None or solution.uncertainty is None:
        return
    trial.uncertainty = solution.uncertainty
    if not solution.uncertainty.is_small(solution.intrinsics.width):
        capped = grade_pose(trial.q, pose_found=True, verified=False)
        if GRADE_NAMES.index(capped.name) > GRADE_NAMES.index(trial.grade):
            trial.grade = capped.name


def note_record_offset(trial: Trial, prior: Prior) -> None:
    """Put first among a manual pose's hints how far it lies from the photo's
    sensor record, when far beyond the record's sigma.

    Pairs are often what a photo with a bad record needs, so this is said,
    not refused. Where the photo's own features confirm the pose, the record
    was off; where they do not, the likelier cause is pairs of another photo
    (they give that photo's pose, and agree with themselves perfectly).

    Parameters
    ----------
    trial : Trial
        From :func:`score_pose`; its ``hints`` changed in place.
    prior : Prior
        The photo's sensor prior (its pose and sigma).
    """
    offset = explain.prior_offset(trial.pose, prior)
    if offset is None:
        return
    if trial.verified:
        hint = explain.prior_offset_hint(trial.pose, prior, True)
    else:
        what, _ = offset
        hint = (f"The control points' pose differs from the photo's sensor record in {what}, "
                f"beyond the record's stated accuracy ({prior.sigma.position_m:g} m, "
                f"{prior.sigma.angles_deg:g}°), and the photo's features do not confirm it: "
                "check that the pairs are this photo's (another photo's pairs give that "
                "photo's pose) before mapping on it.")
    if hint and hint not in trial.hints:
        trial.hints.insert(0, hint)


def registers(solution: ManualSolution) -> bool:
    """Whether a manual pose registers its photo: solved, and its pairs'
    expected error (:func:`pair_uncertainty`) small.

    Small is what a verified automatic pose needs:
    :data:`~napari_imgreg.registration.uncertainty.UNCERTAIN_PX` at 1632 px
    width, scaled to the photo's. The scored trial's grade does not enter:
    a pose the photo's features hardly confirm (extreme light, the reason to
    pick pairs) still stands on good pairs. A solution without an estimate
    (saved before napari-imgreg made one) registers when solved.
    """
    unc = solution.uncertainty
    return bool(solution.ok and (unc is None or unc.is_small(solution.intrinsics.width)))


def register_from_pairs(
    scene: Scene,
    photo_rgb: np.ndarray,
    prior: Prior,
    photo_points: np.ndarray,
    points_3d: np.ndarray,
    solve_focal: bool = False,
    params: RegistrationParams | None = None,
    photo_name: str = "",
    cancelled: Callable[[], bool] | None = None,
) -> tuple[Registration, ManualSolution]:
    """Register a photo from control points: its RESULT.json as a :class:`Registration`.

    The pose is solved from the pairs (:func:`solve_manual`, from the
    prior's camera and pose), scored as an automatic trial
    (:func:`score_pose`), and registered or not by :func:`registers`, as the
    workbench judges a manual pose.

    Parameters
    ----------
    scene : Scene
    photo_rgb : (H, W, 3) uint8 array
    prior : Prior
        The photo's camera (its focal length the start when ``solve_focal``)
        and the starting pose.
    photo_points : (N, 2) array
        Photo pixels (x, y), pixel-centre convention.
    points_3d : (N, 3) array
        The same points on the model, model frame, metres.
    solve_focal : bool
        Also solve the focal length (needs :data:`MIN_PAIRS_FOCAL` pairs).
    params : RegistrationParams, optional
        For the scoring (filters, features, matching width, PnP threshold).
    photo_name : str
        RESULT.json's ``photo``.
    cancelled : callable, optional
        Polled while scoring; raises :class:`~napari_imgreg.registration.pipeline.Cancelled`.

    Returns
    -------
    registration : Registration
        Status ``"registered"`` or ``"failed"``; ``uncertainty`` the pairs'
        own (basis ``"control points"``), or the photo's matches' where they
        verify the pose; ``camera.estimated`` holds ``fx,
        fy`` when the focal length was solved; one trial (origin ``manual``),
        none when no pose was solved (then the prior's pose, grade
        ``failed`` and the reason as the hint). ``metrics`` adds
        ``control_points``, ``control_point_inliers`` and
        ``control_point_rms_px`` to the trial's.
    solution : ManualSolution
    """
    t_start = time.perf_counter()
    params = (params or RegistrationParams()).copy()
    sol = solve_manual(prior.intrinsics, photo_points, points_3d, initial=prior.pose,
                       solve_focal=solve_focal)
    t_solved = time.perf_counter()
    counts = {"control_points": int(len(sol.inliers)),
              "control_point_inliers": sol.n_inliers, "control_point_rms_px": sol.rms_px}
    assumptions = list(prior.assumptions)
    if not sol.ok:
        timings = {"solve": t_solved - t_start, "total": t_solved - t_start}
        registration = Registration(
            status="failed", photo=photo_name, intrinsics=prior.intrinsics, pose=prior.pose,
            prior=prior, metrics=counts, q=math.nan, grade="failed",
            hints=[f"No pose from the control points: {sol.reason}."], trials=[],
            timings_s=timings, best_trial=None, assumptions=assumptions)
        return registration, sol
    trial = score_pose(scene, photo_rgb, sol.intrinsics, sol.pose, params, cancelled=cancelled)
    trial.index = 0
    adopt_pair_uncertainty(trial, sol)  # as the workbench records it
    note_record_offset(trial, prior)
    registered = registers(sol)
    hints = list(trial.hints)
    if sol.warning:
        hints.insert(0, sol.warning[:1].upper() + sol.warning[1:] + ".")
    if not registered and sol.uncertainty is not None:
        limit = UNCERTAIN_PX * sol.intrinsics.width / 1632.0
        hints.insert(0, (
            f"The control points leave the pose uncertain (expected error "
            f"{sol.uncertainty.reprojection_px:.1f} px, {sol.uncertainty.position_m:.2f} m, "
            f"{sol.uncertainty.rotation_deg:.2f}°; registered needs below {limit:.1f} px): "
            "add pairs spread over the photo and over distance."))
    if sol.focal_solved:
        assumptions.append(
            f"focal length solved from the control points: fx = fy = {sol.intrinsics.fx:.1f} px "
            f"({sol.intrinsics.hfov_deg:.1f}° horizontal view; the start was "
            f"{prior.intrinsics.fx:.1f} px)")
    t_end = time.perf_counter()
    timings = {"solve": t_solved - t_start, "score": t_end - t_solved, "total": t_end - t_start}
    registration = Registration(
        status="registered" if registered else "failed", photo=photo_name,
        intrinsics=sol.intrinsics, pose=sol.pose, prior=prior,
        metrics={**trial.metrics, **counts}, q=trial.q, grade=trial.grade, hints=hints,
        trials=[trial], timings_s=timings, best_trial=0, assumptions=assumptions,
        # The workbench's estimate of this pose: the photo's matches' own when
        # they verify it, else the pairs'.
        uncertainty=trial.uncertainty)
    return registration, sol
