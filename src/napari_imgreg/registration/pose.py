"""Camera pose from 2D–3D correspondences: RANSAC EPnP, then refinement.

A failed estimate returns a :class:`PoseEstimate` whose ``ok`` is False and
whose ``reason`` says why; it does not raise.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import ClassVar

import cv2
import numpy as np

from ..camera import Intrinsics, Pose
from ..validate import check_ranges

__all__ = [
    "PoseParams",
    "PoseEstimate",
    "estimate_pose",
    "pose_agreement",
    "reprojection_errors",
    "MIN_POINTS",
]

#: EPnP needs at least 4 points; RANSAC with fewer than 6 is meaningless.
MIN_POINTS = 6


@dataclass
class PoseParams:
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
        Levenberg–Marquardt refinement on the inliers.
    """

    reprojection_error_px: float = 6.0
    iterations: int = 5000
    confidence: float = 0.999
    refine: bool = True

    #: Inclusive valid range of each numeric field.
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "reprojection_error_px": (0.1, 200.0),
        "iterations": (10, 1_000_000),
        "confidence": (0.5, 0.999999),
    }

    def __post_init__(self) -> None:
        check_ranges(self)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> PoseParams:
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise KeyError(f"unknown pose parameter(s): {', '.join(sorted(unknown))}")
        return cls(**d)


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
    """

    ok: bool
    pose: Pose | None
    inliers: np.ndarray
    errors_px: np.ndarray
    reason: str = ""

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

    Returns
    -------
    PoseEstimate

    Notes
    -----
    EPnP is degenerate when all points are (nearly) collinear; a planar
    scene is handled, but gives a less stable pose at grazing views.
    """
    params = params or PoseParams()
    p3 = np.ascontiguousarray(points_3d, np.float64).reshape(-1, 3)
    p2 = np.ascontiguousarray(points_2d, np.float64).reshape(-1, 2)
    n = len(p3)
    none = PoseEstimate(False, None, np.zeros(n, bool), np.full(n, np.nan))
    if n < MIN_POINTS:
        none.reason = f"only {n} 2D–3D correspondences (need {MIN_POINTS})"
        return none
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
    return PoseEstimate(True, pose, inliers, errors)


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
