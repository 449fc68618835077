"""Camera resection from 2D–3D correspondences when the intrinsics are unknown.

Two solvers, both on correspondences only (a mesh scene, a point cloud or
picked control points give them alike):

* :func:`dlt_camera` / :func:`dlt_ransac`: the normalised **six-point DLT**
  (Hartley & Zisserman, *Multiple View Geometry*, alg. 7.1), the camera
  estimator of seed 003 (Morago et al.). It estimates the whole 3 × 4
  projection matrix, so focal lengths, principal point and pose; it needs 3D
  points **off one plane** (on a plane the 12 unknowns are not determined).
* :func:`pose_unknown_focal`: the minimal **P4Pf** solver (Bujnak, Kukelova
  & Pajdla; poselib's ``p4pf``) in a RANSAC loop, followed by a joint
  refinement of pose, focal length and (optionally) the radial distortion
  ``k1``. Square pixels and a principal point at the image centre: one photo
  does not observe the principal point well (it trades with the rotation to
  within a few pixels for a 60° view), and fixing it is what the field does
  (COLMAP, poselib) unless the camera is calibrated. Works on planar scenes.

Conventions are the package's (:mod:`napari_imgreg.camera`): pixels (x =
column, y = row) with the first pixel's centre at (0, 0), ``cam_from_world``
poses, OpenCV distortion ``(k1, k2, p1, p2, k3)``.

A failed estimate returns a :class:`ResectionResult` whose ``ok`` is False
and whose ``reason`` says why; only :func:`dlt_camera` (the direct solve)
raises, with one line saying what is wrong with its input.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ..camera import MAX_FOCAL_PER_SIDE, MIN_FOCAL_PER_SIDE, Intrinsics, Pose

__all__ = [
    "ResectionResult",
    "dlt_camera",
    "dlt_ransac",
    "pose_unknown_focal",
    "refine_camera",
    "nonplanarity",
    "MIN_NONPLANARITY",
    "DLT_MIN_POINTS",
    "P4PF_MIN_POINTS",
]

#: The DLT's minimal sample (11 unknowns, two equations per point).
DLT_MIN_POINTS = 6
#: P4Pf's minimal sample (7 unknowns: pose and focal length).
P4PF_MIN_POINTS = 4
#: Smallest ratio of the 3D points' smallest to largest spread (singular
#: values of the centred points) for which the DLT is attempted: below it the
#: points lie on one plane to within 1/100 of their extent, and the DLT's
#: focal length and principal point are not determined.
MIN_NONPLANARITY = 0.01
#: A sample of the RANSAC is skipped below this ratio (a degenerate sample).
_SAMPLE_NONPLANARITY = 0.02


@dataclass
class ResectionResult:
    """A camera solved from correspondences.

    Attributes
    ----------
    ok : bool
    pose : Pose or None
        ``cam_from_world``; None when ``ok`` is False.
    fx, fy : float
        Focal lengths, pixels (equal for :func:`pose_unknown_focal`: square
        pixels). NaN when not ok.
    cx, cy : float
        Principal point, pixels (the image centre unless estimated).
    k1 : float
        Radial distortion (OpenCV, normalised coordinates); 0 unless estimated.
    inliers : (N,) bool array
        Correspondences within the threshold of the camera.
    errors_px : (N,) float array
        Reprojection error of every correspondence (inf behind the camera,
        NaN without a camera).
    method : str
        ``"p4pf"`` or ``"dlt"``.
    estimated : tuple of str
        The camera fields the solver estimated (``("fx", "fy")``, with
        ``"cx", "cy"`` for the DLT and ``"dist"`` when ``k1`` was).
    reason : str
        Why it failed ("" when ok).
    """

    ok: bool
    pose: Pose | None
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float
    inliers: np.ndarray
    errors_px: np.ndarray
    method: str
    estimated: tuple[str, ...] = ()
    reason: str = ""
    iterations: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    def intrinsics(self, width: int, height: int) -> Intrinsics:
        """The solved camera as :class:`~napari_imgreg.camera.Intrinsics` of a
        ``width`` × ``height`` image, its ``estimated`` set.

        Raises
        ------
        ValueError
            When not ok, or the solved values are outside the camera's ranges.
        """
        if not self.ok:
            raise ValueError(f"no camera was solved ({self.reason})")
        dist = (self.k1, 0.0, 0.0, 0.0, 0.0) if "dist" in self.estimated else ()
        return Intrinsics(width, height, self.fx, self.fy, self.cx, self.cy, dist,
                          estimated=self.estimated)


def _failed(n: int, method: str, reason: str, cx: float = math.nan,
            cy: float = math.nan) -> ResectionResult:
    return ResectionResult(False, None, math.nan, math.nan, cx, cy, 0.0, np.zeros(n, bool),
                           np.full(n, np.nan), method, reason=reason)


# ------------------------------------------------------------------ helpers
def nonplanarity(points_3d: np.ndarray) -> float:
    """How far 3D points are from lying on one plane, in [0, 1].

    Parameters
    ----------
    points_3d : (N, 3) array
        Points, metres.

    Returns
    -------
    float
        The smallest over the largest singular value of the centred points:
        0 for coplanar points, about 1 for a cloud as deep as it is wide.

    Examples
    --------
    >>> nonplanarity(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.]]))
    0.0
    """
    X = np.asarray(points_3d, np.float64).reshape(-1, 3)
    if len(X) < 4:
        return 0.0
    sv = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    return float(sv[2] / sv[0]) if sv[0] > 0 else 0.0


def _hartley(points: np.ndarray) -> np.ndarray:
    """Hartley's similarity for ``points`` (N, d): centroid to the origin,
    mean distance √d. Returns the (d+1) × (d+1) homogeneous matrix."""
    d = points.shape[1]
    c = points.mean(axis=0)
    mean_dist = float(np.mean(np.linalg.norm(points - c, axis=1)))
    s = math.sqrt(d) / mean_dist if mean_dist > 0 else 1.0
    T = np.eye(d + 1)
    T[:d, :d] *= s
    T[:d, d] = -s * c
    return T


def _project(R: np.ndarray, t: np.ndarray, f: tuple[float, float], c: tuple[float, float],
             k1: float, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of world points (N, 3) and their camera depths (N,)."""
    Xc = X @ R.T + t
    z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = Xc[:, 0] / z
        yn = Xc[:, 1] / z
    if k1:
        radial = 1.0 + k1 * (xn * xn + yn * yn)
        xn, yn = xn * radial, yn * radial
    return np.stack([f[0] * xn + c[0], f[1] * yn + c[1]], axis=1), z


def _errors(R, t, f, c, k1, X, x) -> np.ndarray:
    """Reprojection errors (N,), inf behind the camera."""
    uv, z = _project(R, t, f, c, k1, X)
    err = np.linalg.norm(uv - x, axis=1)
    return np.where((z > 0) & np.isfinite(err), err, np.inf)


def _ransac_trials(inlier_ratio: float, sample: int, confidence: float, cap: int) -> int:
    """RANSAC iterations for ``confidence`` at ``inlier_ratio`` (at most ``cap``)."""
    w = inlier_ratio ** sample
    if w >= 1.0:
        return 1
    if w <= 0.0:
        return cap
    return int(min(cap, math.ceil(math.log(1.0 - confidence) / math.log(1.0 - w))))


def _check_pairs(points_3d, points_2d) -> tuple[np.ndarray, np.ndarray]:
    X = np.asarray(points_3d, np.float64).reshape(-1, 3)
    x = np.asarray(points_2d, np.float64).reshape(-1, 2)
    if len(X) != len(x):
        raise ValueError(f"{len(X)} 3D points but {len(x)} 2D points: they must pair up")
    return X, x


# ----------------------------------------------------------------------- DLT
def dlt_camera(points_3d: np.ndarray, points_2d: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The camera through 2D–3D correspondences by the normalised DLT.

    Both point sets are normalised (Hartley: centroid at the origin, mean
    distance √2 in the image, √3 in space), the 2N × 12 system is solved by
    SVD, and the 3 × 3 part of the de-normalised matrix is split into ``K R``
    by an RQ decomposition, with signs chosen so that ``K`` has a positive
    diagonal and ``det R = +1``.

    Parameters
    ----------
    points_3d : (N, 3) array
        World points, metres, N ≥ 6, not all on one plane.
    points_2d : (N, 2) array
        Their pixels (x, y).

    Returns
    -------
    P : (3, 4) array
        The projection matrix, scaled so that ``K[2, 2] = 1``.
    K : (3, 3) array
        Upper-triangular camera matrix (its ``K[0, 1]`` is the skew).
    R : (3, 3) array
        World-to-camera rotation.
    t : (3,) array
        Translation, metres: ``x ~ K (R X + t)``.

    Raises
    ------
    ValueError
        Fewer than 6 pairs, non-finite values, or 3D points on one plane
        (:func:`nonplanarity` below :data:`MIN_NONPLANARITY`).
    """
    X, x = _check_pairs(points_3d, points_2d)
    n = len(X)
    if n < DLT_MIN_POINTS:
        raise ValueError(f"the DLT needs at least {DLT_MIN_POINTS} 2D–3D pairs, got {n}")
    if not (np.isfinite(X).all() and np.isfinite(x).all()):
        raise ValueError("the 2D–3D pairs contain non-finite values")
    flat = nonplanarity(X)
    if flat < MIN_NONPLANARITY:
        raise ValueError(
            f"the 3D points lie on one plane (out-of-plane spread {flat:.3g} of their extent, "
            f"need {MIN_NONPLANARITY:g}): the DLT cannot solve the camera; use the "
            "unknown-focal solver (P4Pf), which handles planar scenes")
    T3, T2 = _hartley(X), _hartley(x)
    Xh = np.c_[X, np.ones(n)] @ T3.T
    xh = np.c_[x, np.ones(n)] @ T2.T
    A = np.zeros((2 * n, 12))
    A[0::2, 0:4] = Xh
    A[0::2, 8:12] = -xh[:, :1] * Xh
    A[1::2, 4:8] = Xh
    A[1::2, 8:12] = -xh[:, 1:2] * Xh
    _, _, Vt = np.linalg.svd(A, full_matrices=False)
    P = np.linalg.solve(T2, Vt[-1].reshape(3, 4)) @ T3
    return _decompose(P)


def _decompose(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``P`` (3, 4) → (P, K, R, t) with K's diagonal positive, det R = +1, K[2, 2] = 1."""
    M = P[:, :3]
    if np.linalg.det(M) < 0:  # P is known up to any scale, its sign included
        P = -P
        M = P[:, :3]
    K, R = scipy.linalg.rq(M)
    D = np.diag(np.sign(np.where(np.diag(K) == 0, 1.0, np.diag(K))))
    K, R = K @ D, D @ R  # D @ D = I: K R unchanged
    if np.linalg.det(R) < 0:  # only with a degenerate M; keep R a rotation
        R = -R
        K = -K
    scale = K[2, 2]
    K = K / scale
    P = P / scale
    t = np.linalg.solve(K, P[:, 3])
    return P, K, R, t


def dlt_ransac(
    points_3d: np.ndarray,
    points_2d: np.ndarray,
    threshold_px: float = 4.0,
    confidence: float = 0.999,
    max_iterations: int = 2000,
    seed: int = 0,
    *,
    refine: bool = True,
) -> ResectionResult:
    """The camera by six-point DLT in RANSAC, re-fitted on the inliers and refined.

    Parameters
    ----------
    points_3d : (N, 3) array
        World points, metres.
    points_2d : (N, 2) array
        Their pixels (x, y).
    threshold_px : float
        Inlier threshold, pixels.
    confidence : float
        Probability of drawing one outlier-free sample, (0, 1): sets the
        iterations adaptively.
    max_iterations : int
        Samples at most.
    seed : int
        Seed of the sampling.
    refine : bool
        After the DLT on all inliers, minimise the reprojection error over
        pose, ``fx``, ``fy``, ``cx``, ``cy`` (zero skew) with a robust loss
        (:func:`refine_camera`), then take the inliers again.

    Returns
    -------
    ResectionResult
        ``method`` "dlt"; ``estimated`` fx, fy, cx, cy. Not ok (``reason``
        says why) with fewer than 6 pairs, when the 3D points lie on one
        plane, or when no sample explains 6 pairs.
    """
    X, x = _check_pairs(points_3d, points_2d)
    n = len(X)
    if n < DLT_MIN_POINTS:
        return _failed(n, "dlt", f"only {n} 2D–3D correspondences (the DLT needs "
                                 f"{DLT_MIN_POINTS})")
    flat = nonplanarity(X)
    if flat < MIN_NONPLANARITY:
        return _failed(n, "dlt", f"the 3D points lie on one plane (out-of-plane spread "
                                 f"{flat:.3g} of their extent): the DLT cannot solve the camera")
    rng = np.random.default_rng(seed)
    best_inl = np.zeros(n, bool)
    best_score = math.inf
    needed = max_iterations
    k = 0
    thr2 = threshold_px ** 2
    while k < min(needed, max_iterations):
        k += 1
        idx = rng.choice(n, DLT_MIN_POINTS, replace=False)
        if nonplanarity(X[idx]) < _SAMPLE_NONPLANARITY:
            continue
        try:
            _, K, R, t = dlt_camera(X[idx], x[idx])
        except (ValueError, np.linalg.LinAlgError):
            continue
        err = _errors_K(K, R, t, X, x)
        # MSAC score: inliers cost their squared error, outliers the threshold's.
        score = float(np.minimum(err * err, thr2).sum())
        if score < best_score:
            best_score = score
            best_inl = err < threshold_px
            needed = _ransac_trials(best_inl.mean(), DLT_MIN_POINTS, confidence, max_iterations)
    if best_inl.sum() < DLT_MIN_POINTS:
        return _failed(n, "dlt", "RANSAC DLT found no camera that explains 6 correspondences")
    inl = best_inl
    for _ in range(2):  # re-fit on all inliers; points that agree then join in
        try:
            _, K, R, t = dlt_camera(X[inl], x[inl])
        except ValueError as exc:
            return _failed(n, "dlt", f"DLT on the inliers failed: {exc}")
        err = _errors_K(K, R, t, X, x)
        new = err < threshold_px
        if new.sum() < DLT_MIN_POINTS:
            break
        inl = new
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    pose = Pose(R, t)
    if refine:
        pose, (fx, fy), (cx, cy), _ = refine_camera(
            X[inl], x[inl], pose, (fx, fy), (cx, cy), 0.0, estimate_k1=False,
            free_principal_point=True, square_pixels=False, loss_scale_px=threshold_px / 2)
    err = _errors(pose.R, pose.t, (fx, fy), (cx, cy), 0.0, X, x)
    inl = err < threshold_px
    if inl.sum() < DLT_MIN_POINTS or not (fx > 0 and fy > 0):
        return _failed(n, "dlt", "the refined DLT camera keeps fewer than 6 inliers")
    return ResectionResult(True, pose, float(fx), float(fy), float(cx), float(cy), 0.0, inl, err,
                           "dlt", ("fx", "fy", "cx", "cy"), iterations=k,
                           extra={"skew": float(K[0, 1]), "nonplanarity": flat})


def _errors_K(K, R, t, X, x) -> np.ndarray:
    """Reprojection errors under ``K [R | t]`` with K's skew."""
    Xc = X @ R.T + t
    uvw = Xc @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = uvw[:, :2] / uvw[:, 2:3]
    err = np.linalg.norm(uv - x, axis=1)
    return np.where((Xc[:, 2] > 0) & np.isfinite(err), err, np.inf)


# ------------------------------------------------------------ unknown focal
def pose_unknown_focal(
    points_3d: np.ndarray,
    points_2d: np.ndarray,
    width: int,
    height: int,
    threshold_px: float = 4.0,
    confidence: float = 0.999,
    max_iterations: int = 2000,
    seed: int = 0,
    *,
    estimate_k1: bool = False,
    principal_point: tuple[float, float] | None = None,
    hfov_range_deg: tuple[float, float] = (2.0, 150.0),
    refine: bool = True,
) -> ResectionResult:
    """Pose and focal length (and ``k1``) from 2D–3D pairs: P4Pf in RANSAC, then refinement.

    Parameters
    ----------
    points_3d : (N, 3) array
        World points, metres (N ≥ 4; planar scenes are fine).
    points_2d : (N, 2) array
        Their pixels (x, y) in a ``width`` × ``height`` photo.
    width, height : int
        The photo's size, pixels.
    threshold_px : float
        Inlier threshold, pixels.
    confidence : float
        Probability of drawing one outlier-free sample, (0, 1).
    max_iterations : int
        Samples at most.
    seed : int
        Seed of the sampling.
    estimate_k1 : bool
        Also estimate the radial distortion ``k1`` in the refinement (it needs
        points spread toward the image corners; leave off for a few dozen
        points near the centre).
    principal_point : (cx, cy), optional
        Held fixed; default the image centre ``((width − 1) / 2, (height − 1) / 2)``.
    hfov_range_deg : (float, float)
        Horizontal fields of view a solution may have: samples giving a focal
        length outside are discarded (default 2–150°).
    refine : bool
        Minimise the reprojection error over pose, focal length (and ``k1``)
        on the inliers with a robust (soft-L1) loss (:func:`refine_camera`),
        twice, taking the inliers again after each.

    Returns
    -------
    ResectionResult
        ``method`` "p4pf", ``fx == fy``; ``estimated`` ("fx", "fy"), with
        "dist" when ``k1`` was estimated.
    """
    import poselib  # the minimal solvers; imported here, where they are needed

    X, x = _check_pairs(points_3d, points_2d)
    n = len(X)
    cx, cy = principal_point if principal_point is not None else ((width - 1) / 2.0,
                                                                   (height - 1) / 2.0)
    if n < P4PF_MIN_POINTS + 1:
        return _failed(n, "p4pf", f"only {n} 2D–3D correspondences (the unknown-focal solver "
                                  f"needs {P4PF_MIN_POINTS + 1})", cx, cy)
    f_lo = (width / 2.0) / math.tan(math.radians(max(hfov_range_deg)) / 2.0)
    f_hi = (width / 2.0) / math.tan(math.radians(min(hfov_range_deg)) / 2.0)
    f_lo = max(f_lo, MIN_FOCAL_PER_SIDE * max(width, height))
    f_hi = min(f_hi, MAX_FOCAL_PER_SIDE * max(width, height))
    # Conditioning: 3D points centred and scaled to unit spread, pixels
    # centred on the principal point and divided by the image size.
    c3 = X.mean(axis=0)
    s3 = float(np.mean(np.linalg.norm(X - c3, axis=1))) or 1.0
    Xn = (X - c3) / s3
    s2 = float(max(width, height))
    xn = (x - (cx, cy)) / s2
    rng = np.random.default_rng(seed)
    thr2 = threshold_px ** 2
    best = None
    best_score = math.inf
    needed = max_iterations
    k = 0
    while k < min(needed, max_iterations):
        k += 1
        idx = rng.choice(n, P4PF_MIN_POINTS, replace=False)
        solutions: list[tuple[np.ndarray, np.ndarray, float]] = []
        if nonplanarity(Xn[idx]) >= _SAMPLE_NONPLANARITY:
            try:
                poses, focals = poselib.p4pf(xn[idx], Xn[idx], True)
            except (RuntimeError, ValueError):
                poses, focals = [], []
            solutions = [(np.asarray(cp.R), np.asarray(cp.t), float(f))
                         for cp, f in zip(poses, focals)]
        if not solutions:
            # P4Pf is degenerate on (nearly) coplanar points, and a rock face
            # often is one: the planar four-point solver instead.
            solutions = _planar_focal_pose(xn[idx], Xn[idx])
        for Rn, tn, f in solutions:
            f_px = float(f) * s2
            if not (math.isfinite(f_px) and f_lo <= f_px <= f_hi):
                continue
            R = Rn
            t = tn * s3 - R @ c3  # back to world metres
            err = _errors(R, t, (f_px, f_px), (cx, cy), 0.0, X, x)
            score = float(np.minimum(err * err, thr2).sum())
            if score < best_score:
                best_score, best = score, (R, t, f_px)
                needed = _ransac_trials(float((err < threshold_px).mean()), P4PF_MIN_POINTS,
                                        confidence, max_iterations)
    if best is None:
        return _failed(n, "p4pf", "RANSAC P4Pf found no camera with a plausible focal length",
                       cx, cy)
    R, t, f = best
    pose, k1 = Pose(R, t), 0.0
    err = _errors(R, t, (f, f), (cx, cy), 0.0, X, x)
    inl = err < threshold_px
    if inl.sum() < P4PF_MIN_POINTS + 1:
        return _failed(n, "p4pf", "RANSAC P4Pf found no camera that explains 5 correspondences",
                       cx, cy)
    if refine:
        for _ in range(2):
            pose, (f, _f), _, k1 = refine_camera(
                X[inl], x[inl], pose, (f, f), (cx, cy), k1, estimate_k1=estimate_k1,
                free_principal_point=False, square_pixels=True, loss_scale_px=threshold_px / 2)
            err = _errors(pose.R, pose.t, (f, f), (cx, cy), k1, X, x)
            new = err < threshold_px
            if new.sum() < P4PF_MIN_POINTS + 1:
                break
            inl = new
    err = _errors(pose.R, pose.t, (f, f), (cx, cy), k1, X, x)
    inl = err < threshold_px
    if inl.sum() < P4PF_MIN_POINTS + 1 or not (f_lo <= f <= f_hi):
        return _failed(n, "p4pf", "the refined camera keeps fewer than 5 inliers or leaves the "
                                  "plausible focal lengths", cx, cy)
    estimated = ("fx", "fy", "dist") if estimate_k1 else ("fx", "fy")
    return ResectionResult(True, pose, float(f), float(f), float(cx), float(cy), float(k1), inl,
                           err, "p4pf", estimated, iterations=k)


def _planar_focal_pose(x: np.ndarray, X: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Pose and focal length from four pairs on (nearly) one plane.

    The plane-to-image homography is ``H ~ K [r1 r2 t]``; with the principal
    point at the origin of ``x`` and square pixels, ``K = diag(f, f, 1)``,
    and the two constraints ``r1 · r2 = 0``, ``|r1| = |r2|`` give ``1/f²`` in
    least squares (Zhang's calibration from one view). Degenerate when the
    plane is seen square-on: then focal length and distance trade exactly.

    Parameters
    ----------
    x : (4, 2) array
        Image points relative to the principal point (any common scale).
    X : (4, 3) array
        Their 3D points.

    Returns
    -------
    list of (R, t, f)
        Zero or one solution, ``x ~ f (R X + t)`` projected.
    """
    c = X.mean(axis=0)
    _, _, Vt = np.linalg.svd(X - c)
    e1, e2 = Vt[0], Vt[1]
    B = np.stack([e1, e2, np.cross(e1, e2)], axis=1)  # columns: plane axes, det +1
    q = (X - c) @ B[:, :2]
    A = np.zeros((8, 9))
    A[0::2, 0:2], A[0::2, 2] = q, 1.0
    A[0::2, 6:8], A[0::2, 8] = -x[:, :1] * q, -x[:, 0]
    A[1::2, 3:5], A[1::2, 5] = q, 1.0
    A[1::2, 6:8], A[1::2, 8] = -x[:, 1:2] * q, -x[:, 1]
    try:
        Hm = np.linalg.svd(A)[2][-1].reshape(3, 3)
    except np.linalg.LinAlgError:
        return []
    h1, h2 = Hm[:, 0], Hm[:, 1]
    a = np.array([h1[0] * h2[0] + h1[1] * h2[1],
                  h1[0] ** 2 + h1[1] ** 2 - h2[0] ** 2 - h2[1] ** 2])
    b = np.array([h1[2] * h2[2], h1[2] ** 2 - h2[2] ** 2])
    denom = float(a @ a)
    if denom <= 0:
        return []
    w = -float(a @ b) / denom  # 1 / f²
    if not (w > 0 and math.isfinite(w)):
        return []
    f = 1.0 / math.sqrt(w)
    M = np.diag([1.0 / f, 1.0 / f, 1.0]) @ Hm
    lam = 2.0 / (np.linalg.norm(M[:, 0]) + np.linalg.norm(M[:, 1]))
    if M[2, 2] * lam < 0:  # the plane's origin must lie in front of the camera
        lam = -lam
    r1, r2, t = lam * M[:, 0], lam * M[:, 1], lam * M[:, 2]
    U, _, Vt2 = np.linalg.svd(np.stack([r1, r2, np.cross(r1, r2)], axis=1))
    Rp = U @ Vt2
    if np.linalg.det(Rp) < 0:
        return []
    R = Rp @ B.T
    return [(R, t - R @ c, f)]


# ---------------------------------------------------------------- refinement
def refine_camera(
    points_3d: np.ndarray,
    points_2d: np.ndarray,
    pose: Pose,
    focal: tuple[float, float],
    principal_point: tuple[float, float],
    k1: float = 0.0,
    *,
    estimate_k1: bool = False,
    free_principal_point: bool = False,
    square_pixels: bool = True,
    loss_scale_px: float = 2.0,
    max_evaluations: int = 200,
) -> tuple[Pose, tuple[float, float], tuple[float, float], float]:
    """Joint least squares of pose and intrinsics on 2D–3D pairs (robust loss).

    The parameters are the rotation vector, the translation, the logarithm of
    the focal length(s) (keeps them positive and equally scaled), optionally
    the principal point and ``k1``. The loss is soft-L1 with scale
    ``loss_scale_px``: pairs beyond it count linearly, so a few outliers left
    among the inliers do not pull the camera.

    Parameters
    ----------
    points_3d : (N, 3) array
        World points, metres (centred internally for conditioning).
    points_2d : (N, 2) array
        Pixels (x, y).
    pose : Pose
        Start, ``cam_from_world``.
    focal : (fx, fy)
        Start, pixels (with ``square_pixels`` only ``fx`` is used).
    principal_point : (cx, cy)
        Start (or the fixed value), pixels.
    k1 : float
        Start (or the fixed value) of the radial distortion.
    estimate_k1, free_principal_point, square_pixels : bool
        Which intrinsics vary: ``k1``; ``cx, cy``; ``fx == fy`` or both.
    loss_scale_px : float
        Soft-L1 scale, pixels.
    max_evaluations : int
        Residual evaluations at most.

    Returns
    -------
    pose, (fx, fy), (cx, cy), k1
    """
    X = np.asarray(points_3d, np.float64).reshape(-1, 3)
    x = np.asarray(points_2d, np.float64).reshape(-1, 2)
    c3 = X.mean(axis=0)
    Xc = X - c3
    # The centred problem's translation: R (X - c) + t' with t' = t + R c.
    t0 = pose.t + pose.R @ c3
    r0 = Rotation.from_matrix(pose.R).as_rotvec()
    fx0, fy0 = focal
    v0 = [*r0, *t0, math.log(fx0)]
    if not square_pixels:
        v0.append(math.log(fy0))
    if free_principal_point:
        v0 += list(principal_point)
    if estimate_k1:
        v0.append(k1)
    v0 = np.array(v0, np.float64)

    def unpack(v):
        i = 7
        fx = math.exp(v[6])
        fy = fx
        if not square_pixels:
            fy = math.exp(v[i])
            i += 1
        c = principal_point
        if free_principal_point:
            c = (v[i], v[i + 1])
            i += 2
        kk = v[i] if estimate_k1 else k1
        return Rotation.from_rotvec(v[:3]).as_matrix(), v[3:6], (fx, fy), c, kk

    def residuals(v):
        R, t, f, c, kk = unpack(v)
        uv, z = _project(R, t, f, c, kk, Xc)
        r = uv - x
        # Behind the camera: a large, smooth penalty instead of NaN.
        bad = ~(z > 1e-9) | ~np.isfinite(r).all(axis=1)
        r[bad] = 1e4
        return r.ravel()

    # Scale the variables so one step means about as much for each.
    x_scale = np.ones_like(v0)
    x_scale[3:6] = max(1.0, float(np.linalg.norm(t0))) * 1e-3
    x_scale[:3] = 1e-3
    x_scale[6:] = 1e-3
    if free_principal_point:
        j = 7 + (0 if square_pixels else 1)
        x_scale[j:j + 2] = 1.0
    sol = least_squares(residuals, v0, loss="soft_l1", f_scale=loss_scale_px, x_scale=x_scale,
                        max_nfev=max_evaluations, method="trf")
    R, t, f, c, kk = unpack(sol.x)
    out = Pose(R, np.asarray(t) - R @ c3)
    return out, (float(f[0]), float(f[1])), (float(c[0]), float(c[1])), float(kk)
