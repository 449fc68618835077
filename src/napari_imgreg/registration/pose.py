"""Camera pose from 2D–3D correspondences: RANSAC EPnP, then refinement.

When the camera's focal length is unknown (``Intrinsics.focal_known`` False:
a record with width and height only) or :attr:`PoseParams.solver` asks for
it, the focal length is estimated with the pose
(:mod:`napari_imgreg.registration.resection`: P4Pf in RANSAC and a joint
refinement, or the six-point DLT), and the estimate carries the solved camera.

A failed estimate returns a :class:`PoseEstimate` whose ``ok`` is False and
whose ``reason`` says why; it does not raise.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar

import cv2
import numpy as np

from ..camera import Intrinsics, Pose
from ..validate import FieldValueError, StageParams, check_ranges
from .resection import MIN_NONPLANARITY, dlt_ransac, nonplanarity, pose_unknown_focal

__all__ = [
    "PoseParams",
    "PoseEstimate",
    "estimate_pose",
    "pose_agreement",
    "reprojection_errors",
    "MIN_POINTS",
    "POSE_SOLVERS",
    "with_known_focal",
]

#: :attr:`PoseParams.solver` values.
POSE_SOLVERS = ("auto", "epnp", "p4pf", "dlt")

#: EPnP needs at least 4 points; RANSAC with fewer than 6 is meaningless.
MIN_POINTS = 6


@dataclass
class PoseParams(StageParams):
    """RANSAC EPnP settings.

    Attributes
    ----------
    reprojection_error_px : float
        RANSAC inlier threshold at the photo's full resolution (0.1–200 px;
        the GUI offers 1–50).
    iterations : int
        RANSAC iterations (10–1 000 000).
    confidence : float
        RANSAC confidence (0.5–0.999999).
    refine : bool
        Levenberg–Marquardt refinement on the inliers (with an estimated
        focal length: the joint refinement of pose and focal length).
    solver : {"auto", "epnp", "p4pf", "dlt"}
        How the pose is solved. ``"auto"`` (default): EPnP with the photo's
        camera when its focal length is known, else ``"p4pf"``. ``"epnp"``:
        always the camera as given (an unknown focal length stays at its
        assumed value). ``"p4pf"``: estimate the focal length with the pose
        (minimal P4Pf solver in RANSAC, planar scenes by a homography, then a
        joint refinement; square pixels, principal point held at the
        camera's, normally the image centre). ``"dlt"``: the six-point DLT of
        seed 003, which estimates fx, fy, cx and cy too; it needs 3D points
        off one plane, and falls back to P4Pf on (nearly) planar ones.
        ``"auto"`` also tries the DLT when P4Pf finds nothing.
    estimate_k1 : bool
        With an estimated focal length, also estimate the radial distortion
        ``k1`` (needs matches spread to the image corners). Default False.
    min_hfov_deg, max_hfov_deg : float
        The horizontal fields of view an estimated focal length may give
        (0.5–170°, min below max; default 2–150°): beyond, a solution is
        taken as wrong.
    """

    KIND: ClassVar[str] = "pose"

    reprojection_error_px: float = 6.0
    iterations: int = 5000
    confidence: float = 0.999
    refine: bool = True
    solver: str = "auto"
    estimate_k1: bool = False
    min_hfov_deg: float = 2.0
    max_hfov_deg: float = 150.0

    #: Inclusive valid range of each numeric field.
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "reprojection_error_px": (0.1, 200.0),
        "iterations": (10, 1_000_000),
        "confidence": (0.5, 0.999999),
        "min_hfov_deg": (0.5, 170.0),
        "max_hfov_deg": (0.5, 170.0),
    }

    def __post_init__(self) -> None:
        check_ranges(self)
        if self.solver not in POSE_SOLVERS:
            raise FieldValueError("solver", f"must be one of {', '.join(POSE_SOLVERS)}, "
                                            f"got {self.solver!r}")
        numbers = all(isinstance(v, (int, float)) for v in (self.min_hfov_deg, self.max_hfov_deg))
        if numbers and self.min_hfov_deg >= self.max_hfov_deg:
            raise FieldValueError("min_hfov_deg", f"must be below max_hfov_deg "
                                                  f"({self.max_hfov_deg:g}), got "
                                                  f"{self.min_hfov_deg:g}")


@dataclass
class PoseEstimate:
    """Outcome of a pose estimation.

    Attributes
    ----------
    ok : bool
    pose : Pose or None
        ``cam_from_world``; None when ``ok`` is False.
    inliers : (N,) bool array
        Which correspondences agree with the pose (the *3D feature inliers*).
    errors_px : (N,) float array
        Reprojection error of every correspondence under the pose (NaN when
        there is no pose).
    reason : str
        Why it failed ("" when ok).
    intrinsics : Intrinsics or None
        The camera solved with the pose (focal length estimated: its
        ``estimated`` says which fields); None: the camera given.
    solver : str
        The solver that gave the pose ("epnp", "p4pf", "dlt"; "" when none).
    """

    ok: bool
    pose: Pose | None
    inliers: np.ndarray
    errors_px: np.ndarray
    reason: str = ""
    intrinsics: Intrinsics | None = None
    solver: str = ""

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    @property
    def mean_error_px(self) -> float:
        """Mean reprojection error of the inliers, pixels (NaN without inliers)."""
        if not self.inliers.any():
            return float("nan")
        return float(np.mean(self.errors_px[self.inliers]))


def reprojection_errors(
    intrinsics: Intrinsics, pose: Pose, points_3d: np.ndarray, points_2d: np.ndarray
) -> np.ndarray:
    """Pixel distance between projected 3D points and their 2D positions, (N,)."""
    proj = pose.project(intrinsics, points_3d)
    err = np.linalg.norm(proj - np.asarray(points_2d, np.float64), axis=1)
    return np.where(np.isfinite(err), err, np.inf)


def estimate_pose(
    intrinsics: Intrinsics,
    points_3d: np.ndarray,
    points_2d: np.ndarray,
    params: PoseParams | None = None,
    *,
    rng_seed: int = 0,
    auto_focal: bool = False,
) -> PoseEstimate:
    """RANSAC EPnP on 2D–3D correspondences, refined on the inliers.

    Parameters
    ----------
    intrinsics : Intrinsics
        The photo's camera (distortion honoured).
    points_3d : (N, 3) array
        Model-frame points, metres.
    points_2d : (N, 2) array
        Their pixel positions (x, y) in the photo.
    params : PoseParams, optional
    rng_seed : int
        Seeds OpenCV's RNG so results are reproducible.
    auto_focal : bool
        With ``params.solver`` "auto": estimate the focal length when the
        camera's is unknown (``intrinsics.focal_known`` False), as the
        registration's rounds do. False (a direct call, e.g. the
        control-point solve or the cross-validation): "auto" is EPnP with the
        camera as given; "p4pf" and "dlt" estimate the focal length whatever.

    Returns
    -------
    PoseEstimate

    Notes
    -----
    EPnP is degenerate when all points are (nearly) collinear; a planar
    scene is handled, but gives a less stable pose at grazing views. With an
    unknown focal length (``params.solver``) the estimate's ``intrinsics``
    hold the solved camera (:func:`_estimate_with_focal`).
    """
    params = params or PoseParams()
    p3 = np.ascontiguousarray(points_3d, np.float64).reshape(-1, 3)
    p2 = np.ascontiguousarray(points_2d, np.float64).reshape(-1, 2)
    n = len(p3)
    none = PoseEstimate(False, None, np.zeros(n, bool), np.full(n, np.nan))
    if n < MIN_POINTS:
        none.reason = f"only {n} 2D–3D correspondences (need {MIN_POINTS})"
        return none
    solver = params.solver
    if solver == "auto":
        solver = "p4pf" if (auto_focal and not intrinsics.focal_known) else "epnp"
    if solver != "epnp":
        return _estimate_with_focal(intrinsics, p3, p2, params, solver, rng_seed)
    # Centre the 3D points: keeps EPnP well conditioned for georeferenced
    # coordinates far from the origin.
    centre = p3.mean(axis=0)
    q3 = p3 - centre
    K, dist = intrinsics.K, intrinsics.dist_coeffs
    cv2.setRNGSeed(rng_seed)
    try:
        ok, rvec, tvec, idx = cv2.solvePnPRansac(
            q3, p2, K, dist,
            iterationsCount=int(params.iterations),
            reprojectionError=float(params.reprojection_error_px),
            confidence=float(params.confidence),
            flags=cv2.SOLVEPNP_EPNP,
        )
    except cv2.error as exc:
        none.reason = f"RANSAC EPnP failed ({exc.err})"
        return none
    if not ok or idx is None or len(idx) < 4:
        none.reason = "RANSAC EPnP found no consistent pose"
        return none
    inl = np.zeros(n, bool)
    inl[idx.ravel()] = True
    sv = np.linalg.svd(q3[inl] - q3[inl].mean(axis=0), compute_uv=False)
    if sv[1] <= 1e-3 * sv[0]:
        none.reason = "the 2D–3D correspondences are (nearly) collinear: the pose is undetermined"
        return none
    # solvePnPRansac re-fits EPnP on all inliers in float32, which flips to the
    # mirror pose on (near-)planar scenes; SQPnP on the inliers is globally optimal.
    try:
        ok_sq, rvec_sq, tvec_sq = cv2.solvePnP(q3[inl], p2[inl], K, dist, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:
        ok_sq = False
    if ok_sq:
        def _count(rv, tv):
            return int((reprojection_errors(intrinsics, Pose.from_rvec_tvec(rv, tv), q3, p2)
                        < params.reprojection_error_px).sum())
        if _count(rvec_sq, tvec_sq) >= _count(rvec, tvec):
            rvec, tvec = rvec_sq, tvec_sq
    if params.refine and inl.sum() >= 4:
        rvec, tvec = cv2.solvePnPRefineLM(q3[inl], p2[inl], K, dist, rvec, tvec)
        # One more round: points that agree with the refined pose join in.
        pose_c = Pose.from_rvec_tvec(rvec, tvec)
        err = reprojection_errors(intrinsics, pose_c, q3, p2)
        inl2 = err < params.reprojection_error_px
        if inl2.sum() >= inl.sum() and inl2.sum() >= 4:
            inl = inl2
            rvec, tvec = cv2.solvePnPRefineLM(q3[inl], p2[inl], K, dist, rvec, tvec)
    pose_c = Pose.from_rvec_tvec(rvec, tvec)
    # Undo the centring: X_cam = R (X - c) + t = R X + (t - R c).
    pose = Pose(pose_c.R, pose_c.t - pose_c.R @ centre)
    errors = reprojection_errors(intrinsics, pose, p3, p2)
    inliers = errors < params.reprojection_error_px
    if inliers.sum() < 4:
        return PoseEstimate(False, None, inliers, errors, "refined pose keeps fewer than 4 inliers")
    in_front = pose.transform(p3[inliers])[:, 2] > 0
    if not in_front.all():
        return PoseEstimate(False, None, inliers, errors, "pose puts inliers behind the camera")
    return PoseEstimate(True, pose, inliers, errors, solver="epnp")


def _estimate_with_focal(intrinsics: Intrinsics, p3: np.ndarray, p2: np.ndarray,
                         params: PoseParams, solver: str, rng_seed: int) -> PoseEstimate:
    """Pose and focal length (``"p4pf"``) or the whole camera (``"dlt"``).

    The DLT falls back to P4Pf on (nearly) planar points; with ``solver``
    "auto" resolved to "p4pf", P4Pf falls back to the DLT when it finds
    nothing on non-planar points. The solved camera keeps the given camera's
    size and lists what was estimated in ``estimated`` (with what the given
    camera already listed).
    """
    n = len(p3)
    w, h = intrinsics.width, intrinsics.height
    thr = float(params.reprojection_error_px)
    # A Python RANSAC loop around the minimal solver: adaptive, so it stops
    # far below the cap at any plausible inlier ratio.
    its = int(min(params.iterations, 20_000))

    def p4pf():
        return pose_unknown_focal(
            p3, p2, w, h, thr, float(params.confidence), its, rng_seed,
            estimate_k1=params.estimate_k1, principal_point=(intrinsics.cx, intrinsics.cy),
            hfov_range_deg=(params.min_hfov_deg, params.max_hfov_deg), refine=params.refine)

    def dlt():
        return dlt_ransac(p3, p2, thr, float(params.confidence), its, rng_seed,
                          refine=params.refine)

    planar = nonplanarity(p3) < MIN_NONPLANARITY
    if solver == "dlt":
        result = p4pf() if planar else dlt()
    else:
        result = p4pf()
        if not result.ok and not planar and params.solver == "auto":
            result = dlt()
    if not result.ok:
        return PoseEstimate(False, None, np.zeros(n, bool), np.full(n, np.nan), result.reason,
                            solver=result.method)
    dist = intrinsics.dist
    if "dist" in result.estimated:
        dist = (result.k1, *intrinsics.dist_coeffs[1:])
    try:
        solved = Intrinsics(w, h, result.fx, result.fy, result.cx, result.cy, dist,
                            estimated=tuple(intrinsics.estimated) + tuple(result.estimated))
    except ValueError as exc:  # FieldValueError: a focal length or centre out of range
        return PoseEstimate(False, None, np.zeros(n, bool), np.full(n, np.nan),
                            f"the {result.method.upper()} camera is implausible ({exc})",
                            solver=result.method)
    if result.method == "dlt":
        # The DLT's focal lengths must still look like one camera's pixels.
        fov = solved.hfov_deg
        if not (params.min_hfov_deg <= fov <= params.max_hfov_deg):
            return PoseEstimate(False, None, np.zeros(n, bool), np.full(n, np.nan),
                                f"the DLT camera's {fov:.1f}° field of view is implausible",
                                solver="dlt")
    errors = reprojection_errors(solved, result.pose, p3, p2)
    inliers = errors < thr
    if inliers.sum() < MIN_POINTS:
        return PoseEstimate(False, None, inliers, errors,
                            f"the {result.method.upper()} camera keeps fewer than {MIN_POINTS} "
                            "inliers", solver=result.method)
    return PoseEstimate(True, result.pose, inliers, errors, intrinsics=solved,
                        solver=result.method)


def with_known_focal(intrinsics: Intrinsics) -> Intrinsics:
    """The camera with its values taken as known (``estimated`` emptied): the
    focal length held fixed, e.g. by the uncertainty's split halves."""
    return replace(intrinsics, estimated=()) if intrinsics.estimated else intrinsics


def pose_agreement(
    intrinsics: Intrinsics,
    pose: Pose,
    points_3d: np.ndarray,
    points_2d: np.ndarray,
    params: PoseParams | None = None,
) -> PoseEstimate:
    """How well a *given* pose explains 2D–3D correspondences, as an estimate.

    The counterpart of :func:`estimate_pose` for a pose found elsewhere (from
    picked control points, a nudge): nothing is solved; a correspondence is an
    inlier when its 3D point projects within ``params.reprojection_error_px``
    of its pixel. So a given pose is scored with the same metrics as an
    estimated one.

    Parameters
    ----------
    intrinsics : Intrinsics
        The photo's camera.
    pose : Pose
        ``cam_from_world`` to test.
    points_3d : (N, 3) array
        Model-frame points, metres.
    points_2d : (N, 2) array
        Their pixel positions (x, y) in the photo.
    params : PoseParams, optional
        Only ``reprojection_error_px`` is used.

    Returns
    -------
    PoseEstimate
        ``ok`` (and ``pose`` set to the given pose) when at least one
        correspondence agrees; ``errors_px`` for all (inf behind the camera).
    """
    params = params or PoseParams()
    errors = reprojection_errors(intrinsics, pose, points_3d, points_2d)
    inliers = errors < params.reprojection_error_px
    if not inliers.any():
        return PoseEstimate(False, None, inliers, errors,
                            f"no correspondence within {params.reprojection_error_px:g} px "
                            "of the pose")
    return PoseEstimate(True, pose, inliers, errors)
