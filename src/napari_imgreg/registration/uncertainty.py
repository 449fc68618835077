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

The halves also say how far a keypoint is from where *independent* evidence
puts it: the residual of one half's keypoints under the other half's pose
(larger than the fit residual, which the pose partly absorbs). Propagated
through the pose's geometry — how firmly keypoints at these places and
depths pin points over the whole frame, counting keypoints that share a
neighbourhood as one, since they share its shading and its unresolved relief
— that is the **support term**: large when the keypoints are few, crowded in a
corner, or all on the near ground while the frame shows the far cliff, however
well they agree with each other.

The estimate is what RESULT.json writes as ``uncertainty``
(``reprojection_px``, ``position_m``, ``rotation_deg``; docs/formats.md §4).

What it cannot see: a bias the same everywhere in the image that a pose change
absorbs exactly (a pure shift or a pure zoom of all keypoints); both halves
then agree on the same wrong pose. Both terms come from the keypoints; no
photometric check (edges, residual flow against a render) enters it yet.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import ClassVar

import cv2
import numpy as np

from ..camera import Intrinsics, Pose
from ..validate import StageParams, check_ranges
from .pose import PoseParams, estimate_pose

__all__ = [
    "UNCERTAIN_PX",
    "Uncertainty",
    "UncertaintyParams",
    "estimate_uncertainty",
    "frame_points",
    "support_term",
]

#: A pose whose ``reprojection_px`` is this or more (at 1632 px width) is not
#: verified, so never "registered" and never graded above "fair".
UNCERTAIN_PX = 4.0


@dataclass
class UncertaintyParams(StageParams):
    """Settings of the split-half cross-validation, each with its valid range ``[low, high]``.

    Nested in :class:`~napari_imgreg.registration.params.RegistrationParams`
    as ``uncertainty`` (``--params`` files: ``{"uncertainty": {...}}``).

    Attributes
    ----------
    directions_deg : tuple of float
        Directions of the lines that split the correspondences (0° = a vertical
        line: left half against right half), degrees in [0, 180), at least
        one. Default four: left/right, top/bottom and the two diagonals.
    min_half : int
        Fewest correspondences a half needs to be solved, [6, 10000]; a split
        with fewer on a side is skipped. Default 12.
    gain : float
        Scale from half of the half-poses' disagreement to the full pose's
        expected error, [0, 10]. Default 1.0 (half the disagreement of two
        independent halves is what either half's bias is, on average, and the
        full pose's is about as large: the bias is shared, not averaged out).
    floor_px : float
        Error that no split can see (camera model, render sampling), pixels at
        1632 px width, added in quadrature, [0, 20]. Default 0.3.
    max_eval_points : int
        Model points the half-poses are compared at (a subsample), [10, 10⁶].
        Default 4000.
    candidate_factor : float
        With ``robust``: the halves' RANSAC sees only matches within this
        multiple of the pose's inlier threshold (``PoseParams.reprojection_error_px``)
        of the pose, [0, 100]; 0 (default): every lifted match. A match 2× the
        threshold off is a wrong match, not a biased keypoint (a bias is a few
        pixels), and wrong matches crowded in one half let its RANSAC lock onto
        another pose. Offline on the rough benchmark's dumped trial poses
        (issue 13), 2 cut the false alarms on correct poses (estimate ≥ 4 px,
        true error < 2 px) from 9 to 3 of 42 and from 5 to 3 of 41, with no new
        miss, but raised some correct poses' estimates toward the gate (a
        0.33 px pose: 2.4 → 3.7 px): not the default until a benchmark run
        with it decides.
    support : bool
        Add the support term (True, default): the held-out keypoint error
        propagated through the pose's geometry to the whole frame. False: the
        split halves and the simulated noise only (the estimate before
        ``ROUGH_VERSION`` 2's benchmark).
    cell_fraction : float
        Keypoints closer than this fraction of the photo's width count as one
        independent observation in the support term, [0.01, 1]. Default 1/8
        (204 px at 1632 px: a bed, a gully or a patch of near ground, whose
        shading and unresolved relief move its keypoints alike).
    robust : bool
        Solve each half by RANSAC EPnP with its own inliers (True, default),
        not by least squares from the full pose: the full pose's inliers were
        chosen to agree with it, and a half restricted to them agrees too.
    """

    KIND: ClassVar[str] = "uncertainty"

    directions_deg: tuple[float, ...] = (0.0, 45.0, 90.0, 135.0)
    min_half: int = 12
    gain: float = 1.0
    floor_px: float = 0.3
    max_eval_points: int = 4000
    robust: bool = True
    candidate_factor: float = 0.0
    support: bool = True
    cell_fraction: float = 0.125

    #: Inclusive valid range of each numeric field (``--params``, GUI, code).
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "directions_deg": (0.0, 180.0),
        "min_half": (6, 10_000),
        "gain": (0.0, 10.0),
        "floor_px": (0.0, 20.0),
        "max_eval_points": (10, 1_000_000),
        "cell_fraction": (0.01, 1.0),
        "candidate_factor": (0.0, 100.0),
    }

    def __post_init__(self) -> None:
        # JSON brings lists; keep tuples (hashable, compared as the defaults).
        self.directions_deg = tuple(self.directions_deg)
        if not self.directions_deg:
            raise ValueError("directions_deg must name at least one direction")
        check_ranges(self)


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
           robust: PoseParams | None, rng_seed: int = 0) -> Pose | None:
    """The pose of one half: RANSAC EPnP with ``robust`` (its own inliers, so a
    half is not held to the full pose's choice of inliers), else least squares
    from ``start`` (Levenberg–Marquardt), centred for conditioning."""
    if robust is not None:
        est = estimate_pose(intr, X, u, robust, rng_seed=rng_seed)
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
    *,
    rng_seed: int = 0,
) -> Uncertainty:
    """The expected error of ``pose`` by cross-validation over spatially separate halves.

    For each direction, the correspondences are split at the median of their
    image coordinate along it; a pose is solved from each half (RANSAC EPnP,
    ``robust``) and the two are compared at ``eval_points``. The same splits
    of simulated matches (the pose's exact projections of its inliers plus
    Gaussian noise of their spread) say how far apart noise alone puts the
    halves; the excess, in quadrature, is the bias. The spread term is the
    larger of the full pose's noise error (the simulated full solve against
    ``pose``) and, with ``params.support``, the support term
    (:func:`support_term`: the median held-out residual of one half's inliers
    under the other half's pose, propagated through the pose's geometry to
    ``eval_points``). The estimate is the spread term and ``gain`` × half the
    worst excess over the directions, with ``floor_px``, added in quadrature;
    position and rotation likewise (without the floor).

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
    rng_seed : int
        Seed of the halves' RANSAC and of the simulated noise (reproducible).

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
    threshold = (pose_params or PoseParams()).reprojection_error_px
    fit = np.linalg.norm(pose.project(intrinsics, X) - u, axis=1)
    if params.candidate_factor > 0:
        near = fit < params.candidate_factor * threshold
        X, u, fit = X[near], u[near], fit[near]
    inl = fit < threshold
    if inl.sum() < 2 * params.min_half:
        return inf
    sigma = float(np.median(fit[inl])) / 1.1774  # median of a 2D Gaussian's norm = 1.1774 σ
    rng = np.random.default_rng(rng_seed)
    u_sim = pose.project(intrinsics, X[inl]) + rng.normal(0.0, sigma, (int(inl.sum()), 2))
    full_sim = _solve(intrinsics, X[inl], u_sim, pose, None)
    if full_sim is None:
        return inf
    noise = _disagreement(intrinsics, full_sim, pose, E)
    bias = np.zeros(3)
    splits = 0
    held_out: list[float] = []
    for ang in params.directions_deg:
        d = np.array([np.cos(np.radians(ang)), np.sin(np.radians(ang))])
        cut = np.median(u @ d)
        real = _split(intrinsics, X, u, u @ d < cut, pose, E, params.min_half, robust, rng_seed,
                      held_out=held_out, inlier=inl)
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
    spread = noise
    if params.support and held_out:
        sigma_cv = float(np.median(held_out)) / 1.1774
        spread = np.maximum(noise, support_term(intrinsics, pose, X[inl], u[inl], E, sigma_cv,
                                                params.cell_fraction * intrinsics.width))
    px, m, deg = np.sqrt(spread**2 + (g * bias) ** 2)
    return Uncertainty(float(np.hypot(px, floor)), float(m), float(deg), splits)


def _pixel_jacobian(intr: Intrinsics, pose: Pose, X: np.ndarray) -> np.ndarray:
    """(N, 2, 6) derivative of the pixels of ``X`` by a small turn ``w`` (rad) and
    shift ``v`` (m) of the camera, both in the camera frame (``Xc → Xc + w × Xc + v``;
    pinhole, the distortion's small effect on the derivative left out)."""
    Xc = pose.transform(X)
    x, y, z = Xc.T
    fx, fy = intr.K[0, 0], intr.K[1, 1]
    D = np.zeros((len(X), 2, 3))
    D[:, 0, 0], D[:, 0, 2] = fx / z, -fx * x / z**2
    D[:, 1, 1], D[:, 1, 2] = fy / z, -fy * y / z**2
    S = np.zeros((len(X), 3, 6))
    S[:, 0, 1], S[:, 0, 2] = z, -y  # w × Xc = -[Xc]× w
    S[:, 1, 0], S[:, 1, 2] = -z, x
    S[:, 2, 0], S[:, 2, 1] = y, -x
    S[:, :, 3:] = np.eye(3)
    return D @ S


def support_term(intrinsics: Intrinsics, pose: Pose, X: np.ndarray, u: np.ndarray,
                 E: np.ndarray, sigma_px: float, cell_px: float) -> np.ndarray:
    """How firmly keypoints at ``u`` (3D ``X``) pin the frame, given their error.

    First-order pose covariance ``σ² (JᵀJ)⁻¹`` of a least-squares pose from
    the keypoints (``J``: pixels by camera turn and shift,
    :func:`_pixel_jacobian`), inflated by ``N / cells``: keypoints in the same
    ``cell_px`` square share their error, so only the occupied cells count as
    independent. Propagated to the frame points ``E``.

    Parameters
    ----------
    intrinsics, pose : the photo's camera and the pose.
    X : (N, 3) array
        The pose's inlier 3D points, model frame, metres.
    u : (N, 2) array
        Their pixels.
    E : (M, 3) array
        Model points over the whole frame.
    sigma_px : float
        Per-axis error of a keypoint, pixels (held out: from the other half's pose).
    cell_px : float
        Side of a neighbourhood of shared error, pixels.

    Returns
    -------
    (3,) array
        Median expected image error at ``E`` (px), camera-centre error (m),
        rotation error (degrees); infinite when the keypoints do not fix a pose.
    """
    n = len(X)
    if n < 6 or len(E) == 0 or not np.isfinite(sigma_px):
        return np.full(3, np.inf)
    cells = len(np.unique(np.floor(u / max(cell_px, 1e-6)).astype(np.int64), axis=0))
    J = _pixel_jacobian(intrinsics, pose, X).reshape(-1, 6)
    try:
        cov = np.linalg.inv(J.T @ J) * (sigma_px**2 * n / cells)
    except np.linalg.LinAlgError:
        return np.full(3, np.inf)
    JE = _pixel_jacobian(intrinsics, pose, E)
    var = np.einsum("nij,jk,nik->n", JE, cov, JE)
    px = float(np.median(np.sqrt(np.maximum(var, 0.0))))
    # The centre moves by -Rᵀ v (same length as v); the turn by |w|.
    m = float(np.sqrt(max(np.trace(cov[3:, 3:]), 0.0)))
    deg = float(np.degrees(np.sqrt(max(np.trace(cov[:3, :3]), 0.0))))
    return np.array([px, m, deg])


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
           E: np.ndarray, min_half: int, robust: PoseParams | None, rng_seed: int = 0,
           held_out: list[float] | None = None, inlier: np.ndarray | None = None,
           ) -> np.ndarray | None:
    """The disagreement of the poses solved from each side of a split, or None
    when a side has too few matches or cannot be solved. ``held_out`` gets the
    median residual of each side's ``inlier`` keypoints under the other side's pose."""
    if side.sum() < min_half or (~side).sum() < min_half:
        return None
    pa = _solve(intr, X[side], u[side], pose, robust, rng_seed)
    pb = _solve(intr, X[~side], u[~side], pose, robust, rng_seed)
    if pa is None or pb is None:
        return None
    if held_out is not None:
        keep = np.ones(len(X), bool) if inlier is None else inlier
        for p_other, mine in ((pb, side & keep), (pa, ~side & keep)):
            front = p_other.transform(X[mine])[:, 2] > 0
            if front.sum() >= 3:
                r = np.linalg.norm(p_other.project(intr, X[mine][front]) - u[mine][front], axis=1)
                held_out.append(float(np.median(r)))
    return _disagreement(intr, pa, pb, E)
