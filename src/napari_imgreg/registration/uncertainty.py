"""An error estimate of a solved pose that does not come from its own residuals.

A pose fitted to keypoints that sit on *shading* rather than on rock (another
sun on relief the model does not resolve) has small residuals: the keypoints
are biased, not noisy, so they agree with each other and with a wrong pose.
The fit residual (``reprojection_error_px``) cannot see that. What can is
**cross-validation over spatially separate halves**: the correspondences are
split by a line through the image (four directions), a pose is solved from each
half alone, and the two half-poses are compared where it matters — at model
points spread over the whole frame, near ground included. A shading bias that
varies over the image pulls the halves apart; noise alone moves them by little.

The estimate is what RESULT.json writes as ``uncertainty``
(``reprojection_px``, ``position_m``, ``rotation_deg``; docs/formats.md §4).

What it cannot see: a bias the same everywhere in the image that a pose change
absorbs exactly (a pure shift or a pure zoom of all keypoints); both halves
then agree on the same wrong pose.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np

from ..camera import Intrinsics, Pose
from .params import PoseParams
from .pose import estimate_pose

__all__ = [
    "UNCERTAIN_PX",
    "Uncertainty",
    "UncertaintyParams",
    "estimate_uncertainty",
    "frame_points",
]

#: A pose whose ``reprojection_px`` is this or more (at 1632 px width) is not
#: verified, so never "registered" and never graded above "fair".
UNCERTAIN_PX = 4.0


@dataclass(frozen=True)
class UncertaintyParams:
    """Settings of the split-half cross-validation.

    Attributes
    ----------
    directions_deg : tuple of float
        Directions of the lines that split the correspondences (0° = a vertical
        line: left half against right half), degrees. Default four: left/right,
        top/bottom and the two diagonals.
    min_half : int
        Fewest correspondences a half needs to be solved (≥ 6); a split with
        fewer on a side is skipped. Default 12.
    gain : float
        Scale from half of the half-poses' disagreement to the full pose's
        expected error, calibrated on the benchmark's scenes (≥ 0). Default 1.0.
    floor_px : float
        Error that no split can see (camera model, render sampling), pixels at
        1632 px width, added in quadrature (≥ 0). Default 0.3.
    max_eval_points : int
        Model points the half-poses are compared at (a subsample). Default 4000.
    robust : bool
        Solve each half by RANSAC EPnP with its own inliers (True, default),
        not by least squares from the full pose: the full pose's inliers were
        chosen to agree with it, and a half restricted to them agrees too.
    """

    directions_deg: tuple[float, ...] = (0.0, 45.0, 90.0, 135.0)
    min_half: int = 12
    gain: float = 1.0
    floor_px: float = 0.3
    max_eval_points: int = 4000
    robust: bool = True

    def __post_init__(self) -> None:
        if self.min_half < 6:
            raise ValueError(f"min_half must be at least 6, not {self.min_half}")
        if self.gain < 0 or self.floor_px < 0:
            raise ValueError("gain and floor_px must be non-negative")
        if not self.directions_deg:
            raise ValueError("directions_deg must name at least one direction")


@dataclass(frozen=True)
class Uncertainty:
    """The expected error of a pose (RESULT.json ``uncertainty``).

    Attributes
    ----------
    reprojection_px : float
        Expected median distance, pixels of the photo, between where the
        estimated and the true pose put the model points visible in the photo.
    position_m : float
        Expected error of the camera centre, metres.
    rotation_deg : float
        Expected error of the camera rotation, degrees.
    splits : int
        Splits that could be solved (0: the estimate is the floor only, and
        ``reprojection_px`` is infinite when fewer than ``2 * min_half``
        correspondences were given).
    """

    reprojection_px: float
    position_m: float
    rotation_deg: float
    splits: int = 0

    def to_dict(self) -> dict:
        """The three RESULT.json fields (JSON-ready: infinite becomes None)."""
        def num(v: float, nd: int):
            return round(float(v), nd) if np.isfinite(v) else None
        return {"reprojection_px": num(self.reprojection_px, 3),
                "position_m": num(self.position_m, 4),
                "rotation_deg": num(self.rotation_deg, 4)}

    @classmethod
    def from_dict(cls, d: dict | None) -> Uncertainty | None:
        if not d:
            return None
        def val(k):
            v = d.get(k)
            return float("inf") if v is None else float(v)
        return cls(val("reprojection_px"), val("position_m"), val("rotation_deg"))

    def is_small(self, image_width: int) -> bool:
        """Below :data:`UNCERTAIN_PX` at 1632 px width (scaled to ``image_width``)."""
        return bool(self.reprojection_px < UNCERTAIN_PX * image_width / 1632.0)

    def as_dict(self) -> dict:
        return asdict(self)


def frame_points(xyz_image: np.ndarray, n: int = 4000) -> np.ndarray:
    """Model points visible over the whole frame: an even subsample of a render's ``xyz``.

    Parameters
    ----------
    xyz_image : (H, W, 3) array
        A render's model-frame points, NaN where nothing is hit.
    n : int
        About this many points.

    Returns
    -------
    (M, 3) float64 array, M ≤ about ``n``
    """
    h, w = xyz_image.shape[:2]
    step = max(1, int(np.sqrt(h * w / max(n, 1))))
    sub = xyz_image[step // 2::step, step // 2::step].reshape(-1, 3)
    return np.asarray(sub[np.isfinite(sub).all(axis=1)], np.float64)


def _solve(intr: Intrinsics, X: np.ndarray, u: np.ndarray, start: Pose,
           robust: PoseParams | None) -> Pose | None:
    """The pose of one half: RANSAC EPnP with ``robust`` (its own inliers, so a
    half is not held to the full pose's choice of inliers), else least squares
    from ``start`` (Levenberg–Marquardt), centred for conditioning."""
    if robust is not None:
        est = estimate_pose(intr, X, u, robust)
        return est.pose if est.ok else None
    c = X.mean(axis=0)
    start_c = Pose(start.R, start.t + start.R @ c)
    try:
        rvec, tvec = cv2.solvePnPRefineLM(
            np.ascontiguousarray(X - c), np.ascontiguousarray(u, np.float64), intr.K,
            intr.dist_coeffs, start_c.rvec.reshape(3, 1).copy(),
            start_c.t.reshape(3, 1).astype(np.float64).copy(),
            (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-10))
    except cv2.error:
        return None
    p = Pose.from_rvec_tvec(rvec, tvec)
    return Pose(p.R, p.t - p.R @ c)


def _rotation_deg(a: Pose, b: Pose) -> float:
    cos = (np.trace(a.R @ b.R.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def estimate_uncertainty(
    intrinsics: Intrinsics,
    pose: Pose,
    points_3d: np.ndarray,
    points_2d: np.ndarray,
    eval_points: np.ndarray | None = None,
    params: UncertaintyParams | None = None,
    pose_params: PoseParams | None = None,
) -> Uncertainty:
    """The expected error of ``pose`` by cross-validation over spatially separate halves.

    For each direction, the correspondences are split at the median of their
    image coordinate along it; a pose is solved from each half (RANSAC EPnP,
    ``robust``) and the two are compared at ``eval_points``. The same splits
    of simulated matches (the pose's exact projections of its inliers plus
    Gaussian noise of their spread) say how far apart noise alone puts the
    halves; the excess, in quadrature, is the bias. The estimate is the full
    pose's noise error (the simulated full solve against ``pose``) and
    ``gain`` × half the worst excess over the directions, with ``floor_px``,
    added in quadrature; position and rotation likewise.

    Parameters
    ----------
    intrinsics : Intrinsics
        The photo's camera, full resolution.
    pose : Pose
        The pose to judge (``cam_from_world``), solved from these correspondences.
    points_3d : (N, 3) array
        The correspondences' 3D points, model frame, metres: all that were
        lifted (``robust``), or the pose's inliers.
    points_2d : (N, 2) array
        Their pixels in the photo (x, y), full resolution.
    eval_points : (M, 3) array, optional
        Model points visible over the photo's whole frame (:func:`frame_points`
        of a render); default ``points_3d``.
    params : UncertaintyParams, optional
    pose_params : PoseParams, optional
        RANSAC settings of the halves (``robust``); default :class:`PoseParams`.

    Returns
    -------
    Uncertainty
        Pixels of this photo, metres, degrees. Infinite when fewer than
        ``2 * min_half`` correspondences are given or no split can be solved:
        nothing independent supports the pose.
    """
    params = params or UncertaintyParams()
    robust = (pose_params or PoseParams()) if params.robust else None
    X = np.asarray(points_3d, np.float64).reshape(-1, 3)
    u = np.asarray(points_2d, np.float64).reshape(-1, 2)
    ok = np.isfinite(X).all(axis=1) & np.isfinite(u).all(axis=1)
    X, u = X[ok], u[ok]
    scale = intrinsics.width / 1632.0
    floor = params.floor_px * scale
    inf = Uncertainty(float("inf"), float("inf"), float("inf"), 0)
    if len(X) < 2 * params.min_half:
        return inf
    E = X if eval_points is None else np.asarray(eval_points, np.float64).reshape(-1, 3)
    if len(E) > params.max_eval_points:
        E = E[np.linspace(0, len(E) - 1, params.max_eval_points).astype(int)]
    # Only points in front of the camera; a point far outside the frame says little.
    zc = pose.transform(E)[:, 2]
    E = E[zc > 0]
    if len(E) < 3:
        E = X
    # The same splits on simulated matches — the pose's exact projections plus
    # noise of the inliers' spread — say how far apart noise alone puts the
    # halves (a half extrapolates over the other half of the frame); only the
    # excess is bias.
    fit = np.linalg.norm(pose.project(intrinsics, X) - u, axis=1)
    inl = fit < (pose_params or PoseParams()).reprojection_error_px
    if inl.sum() < 2 * params.min_half:
        return inf
    sigma = float(np.median(fit[inl])) / 1.1774  # median of a 2D Gaussian's norm = 1.1774 σ
    rng = np.random.default_rng(0)
    u_sim = pose.project(intrinsics, X[inl]) + rng.normal(0.0, sigma, (int(inl.sum()), 2))
    full_sim = _solve(intrinsics, X[inl], u_sim, pose, None)
    if full_sim is None:
        return inf
    noise = _disagreement(intrinsics, full_sim, pose, E)
    bias = np.zeros(3)
    splits = 0
    for ang in params.directions_deg:
        d = np.array([np.cos(np.radians(ang)), np.sin(np.radians(ang))])
        cut = np.median(u @ d)
        real = _split(intrinsics, X, u, u @ d < cut, pose, E, params.min_half, robust)
        sim = _split(intrinsics, X[inl], u_sim, u[inl] @ d < cut, pose, E, params.min_half, None)
        if real is None or sim is None:
            continue
        if not np.isfinite(real).all():
            # One half puts the frame behind the camera: nothing holds the pose.
            return inf
        bias = np.maximum(bias, 0.5 * np.sqrt(np.maximum(real**2 - sim**2, 0.0)))
        splits += 1
    if splits == 0:
        return inf
    g = params.gain
    px, m, deg = np.sqrt(noise**2 + (g * bias) ** 2)
    return Uncertainty(float(np.hypot(px, floor)), float(m), float(deg), splits)


def _disagreement(intr: Intrinsics, a: Pose, b: Pose, E: np.ndarray) -> np.ndarray:
    """(median image distance at ``E`` px, centre distance m, rotation angle deg) of two
    poses; the image distance infinite when fewer than 3 points are in front of both."""
    front = (a.transform(E)[:, 2] > 0) & (b.transform(E)[:, 2] > 0)
    if front.sum() < 3:
        return np.array([np.inf, np.inf, np.inf])
    px = float(np.median(np.linalg.norm(a.project(intr, E[front]) - b.project(intr, E[front]),
                                        axis=1)))
    return np.array([px, float(np.linalg.norm(a.center - b.center)), _rotation_deg(a, b)])


def _split(intr: Intrinsics, X: np.ndarray, u: np.ndarray, side: np.ndarray, pose: Pose,
           E: np.ndarray, min_half: int, robust: PoseParams | None) -> np.ndarray | None:
    """The disagreement of the poses solved from each side of a split, or None
    when a side has too few matches or cannot be solved."""
    if side.sum() < min_half or (~side).sum() < min_half:
        return None
    pa = _solve(intr, X[side], u[side], pose, robust)
    pb = _solve(intr, X[~side], u[~side], pose, robust)
    if pa is None or pb is None:
        return None
    return _disagreement(intr, pa, pb, E)
