"""Estimators of the rotation that orients a model: the paper's, least squares, robust.

A photo's camera has, in the model frame, an estimated view direction ξ
(camera z) and image long axis ρ (camera x); the phone measured the same two
vectors in the true-north frame. Each estimator finds the rotation ``Q``
(``world_from_model``) that best carries the estimated vectors onto the
measured ones (see :mod:`napari_imgreg.orient` for the three methods).

The J vectors are normalised before they enter the orientation tensor (they
stand for the normals of the planes γ); on generated surveys this gives a
better axis than weighting by their length.

Rotations are (3, 3) arrays; ``estimated`` is ``cam_from_model`` and
``measured`` ``cam_from_world``, each (N, 3, 3); angles are in degrees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "METHODS",
    "PAPER_STEP_DEG",
    "RotationEstimate",
    "j_vectors",
    "orientation_tensor",
    "rotation_axis_from_j",
    "angle_by_rss_search",
    "estimate_rotation_paper",
    "estimate_rotation_lsq",
    "estimate_rotation_robust",
    "rotation_error_deg",
    "lower_hemisphere_axis",
]

METHODS = ("paper", "lsq", "robust")
PAPER_STEP_DEG = 0.1

_UP = np.array([0.0, 0.0, 1.0])


# ------------------------------------------------------------ small helpers
def _axes(cam_from_frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ξ, ρ), each (N, 3): rows 2 and 0 of (N, 3, 3) camera rotations."""
    R = np.asarray(cam_from_frame, dtype=np.float64).reshape(-1, 3, 3)
    return R[:, 2], R[:, 0]


def _angle_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Angle in degrees between unit vectors along the last axis (atan2: exact when small)."""
    cross = np.linalg.norm(np.cross(u, v), axis=-1)
    return np.degrees(np.arctan2(cross, np.sum(u * v, axis=-1)))


def rotation_error_deg(A: np.ndarray, B: np.ndarray) -> float:
    """Angle in degrees of the rotation between two rotation matrices (3, 3)."""
    return float(np.degrees(Rotation.from_matrix(np.asarray(A) @ np.asarray(B).T).magnitude()))


def _axis_angle(Q: np.ndarray) -> tuple[np.ndarray, float]:
    """Unit axis (3,) and angle in degrees [0, 180] of a rotation; axis +Z for identity."""
    rotvec = Rotation.from_matrix(Q).as_rotvec()
    angle = float(np.linalg.norm(rotvec))
    if angle < 1e-12:
        return _UP.copy(), 0.0
    return rotvec / angle, math.degrees(angle)


def lower_hemisphere_axis(axis: np.ndarray, angle_deg: float) -> tuple[float, float, float]:
    """A rotation as geologists give it: (trend, plunge ≥ 0, signed angle), degrees.

    The axis is taken pointing downward; the angle is positive clockwise
    looking down the plunge (right-handed about the downward axis).
    """
    trend, plunge = _trend_plunge(axis)
    if plunge < 0:
        trend, plunge = _trend_plunge(-np.asarray(axis))
        angle_deg = -angle_deg
    return trend, plunge, angle_deg


def _trend_plunge(v: np.ndarray) -> tuple[float, float]:
    """Trend (clockwise from north) and plunge (positive down) of a vector, degrees."""
    v = np.asarray(v, dtype=np.float64) / np.linalg.norm(v)
    trend = math.degrees(math.atan2(v[0], v[1])) % 360.0
    return trend, math.degrees(math.asin(float(np.clip(-v[2], -1.0, 1.0))))


def _finite(value: float | None) -> float | None:
    """JSON-safe float: NaN and inf become None."""
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


# ----------------------------------------------------------- paper method
def j_vectors(estimated: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """J vectors joining estimated to measured unit vectors.

    Every rotation axis carrying ``estimated`` onto ``measured`` lies in the
    plane through the origin perpendicular to J (the paper's plane γ).

    Parameters
    ----------
    estimated, measured : (M, 3) arrays
        Unit vectors (ξ and ρ of all photos, stacked).

    Returns
    -------
    (M, 3) array
        ``measured − estimated``.
    """
    return np.asarray(measured, dtype=np.float64) - np.asarray(estimated, dtype=np.float64)


def orientation_tensor(vectors: np.ndarray, min_length: float = 1e-12) -> np.ndarray:
    """Second-order orientation tensor of directions (Whitaker & Engelder, 2005).

    Parameters
    ----------
    vectors : (M, 3) array
        Directions of any length; each is normalised (they stand for plane
        normals). Vectors shorter than ``min_length`` carry no direction and
        are skipped.

    Returns
    -------
    (3, 3) array
        ``mean(u uᵀ)`` over the unit vectors ``u``; zeros when none is left.
    """
    v = np.asarray(vectors, dtype=np.float64).reshape(-1, 3)
    length = np.linalg.norm(v, axis=1)
    u = v[length > min_length] / length[length > min_length, None]
    if len(u) == 0:
        return np.zeros((3, 3))
    return u.T @ u / len(u)


def rotation_axis_from_j(j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation axis: the direction of minimum concentration of the J vectors.

    It is the eigenvector of the smallest eigenvalue of their orientation
    tensor: the direction where the planes perpendicular to the J vectors
    intersect best.

    Parameters
    ----------
    j : (M, 3) array
        J vectors (:func:`j_vectors`).

    Returns
    -------
    axis : (3,) array
        Unit axis (sign arbitrary).
    eigenvalues : (3,) array
        The tensor's eigenvalues, ascending.
    """
    eigenvalues, eigenvectors = np.linalg.eigh(orientation_tensor(j))
    return eigenvectors[:, 0], eigenvalues


def angle_by_rss_search(
    axis: np.ndarray,
    estimated: np.ndarray,
    measured: np.ndarray,
    step_deg: float = PAPER_STEP_DEG,
) -> tuple[float, np.ndarray, np.ndarray]:
    """Rotation angle about ``axis`` minimising the residual sum of squares.

    The estimated vectors are turned about the axis in ``step_deg``
    increments over a full turn; the RSS is the sum of the squared angles
    (degrees²) between turned-estimated and measured vectors.

    Parameters
    ----------
    axis : (3,) array
        Unit rotation axis.
    estimated, measured : (M, 3) arrays
        Unit vectors.
    step_deg : float
        Search increment, degrees (the paper: 0.1).

    Returns
    -------
    angle_deg : float
        Best angle in [0, 360), right-handed about ``axis``.
    angles_deg : (K,) array
        The angles searched.
    rss : (K,) array
        RSS at each angle, degrees².
    """
    k = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    a = np.asarray(estimated, dtype=np.float64)
    b = np.asarray(measured, dtype=np.float64)
    # Rodrigues: a(θ) = a∥ + a⊥ cos θ + (k × a) sin θ, so b·a(θ) is
    # p + q cos θ + r sin θ with per-vector constants: one (K, M) array.
    a_par = np.outer(a @ k, k)
    p = np.sum(b * a_par, axis=1)
    q = np.sum(b * (a - a_par), axis=1)
    r = np.sum(b * np.cross(k, a), axis=1)
    angles_deg = np.arange(0.0, 360.0, step_deg)
    theta = np.radians(angles_deg)[:, None]
    cosines = np.clip(p + q * np.cos(theta) + r * np.sin(theta), -1.0, 1.0)
    rss = np.sum(np.degrees(np.arccos(cosines)) ** 2, axis=1)
    best = int(np.argmin(rss))
    return float(angles_deg[best]), angles_deg, rss


# ----------------------------------------------------------- estimators
@dataclass
class RotationEstimate:
    """One estimator's rotation ``Q`` (``world_from_model``).

    Attributes
    ----------
    method : str
        ``"paper"``, ``"lsq"`` or ``"robust"``.
    rotation : (3, 3) array
        ``Q``: a model-frame direction ``a`` is ``Q @ a`` in the world frame.
    inliers : (N,) bool array
        Photos the estimate rests on (all but the robust option's outliers).
    rms_deg : float
        Root mean square of all photos' Δξ and Δρ under this rotation.
    details : dict
        Estimator specifics (tensor eigenvalues and grid step for ``paper``,
        threshold and iterations for ``robust``).
    """

    method: str
    rotation: np.ndarray
    inliers: np.ndarray
    rms_deg: float
    details: dict[str, Any] = field(default_factory=dict)

    @property
    def axis(self) -> np.ndarray:
        """Unit rotation axis (3,), right-handed with :attr:`angle_deg` ≥ 0."""
        return _axis_angle(self.rotation)[0]

    @property
    def angle_deg(self) -> float:
        """Rotation angle in degrees, in [0, 180]."""
        return _axis_angle(self.rotation)[1]

    def to_dict(self, photos: Sequence[str] | None = None) -> dict[str, Any]:
        axis, angle = _axis_angle(self.rotation)
        trend, plunge = _trend_plunge(axis)
        out: dict[str, Any] = {
            "rotation_matrix": self.rotation.tolist(),
            "axis": axis.tolist(),
            "axis_trend_deg": trend,
            "axis_plunge_deg": plunge,
            "angle_deg": angle,
            "rms_residual_deg": _finite(self.rms_deg),
            "n_used": int(self.inliers.sum()),
        }
        if photos is not None and not self.inliers.all():
            out["photos_set_aside"] = [p for p, keep in zip(photos, self.inliers) if not keep]
        out.update({k: v for k, v in self.details.items()})
        return out


def _per_photo_residual(Q: np.ndarray, xi_e, rho_e, xi_m, rho_m) -> np.ndarray:
    """RMS of |Δξ| and |Δρ| per photo (degrees); ``Q`` may be (H, 3, 3) → (H, N)."""
    turned_xi = np.einsum("...ab,nb->...na", Q, xi_e)
    turned_rho = np.einsum("...ab,nb->...na", Q, rho_e)
    d_xi = _angle_between(turned_xi, xi_m)
    d_rho = _angle_between(turned_rho, rho_m)
    return np.sqrt((d_xi**2 + d_rho**2) / 2.0)


def _rms(Q: np.ndarray, xi_e, rho_e, xi_m, rho_m) -> float:
    return float(np.sqrt(np.mean(_per_photo_residual(Q, xi_e, rho_e, xi_m, rho_m) ** 2)))


def estimate_rotation_paper(
    estimated: np.ndarray, measured: np.ndarray, step_deg: float = PAPER_STEP_DEG
) -> RotationEstimate:
    """The paper's rotation: J-tensor axis, then an RSS angle search.

    Parameters
    ----------
    estimated : (N, 3, 3) array
        ``cam_from_model`` of each photo.
    measured : (N, 3, 3) array
        ``cam_from_world`` of each photo.
    step_deg : float
        Angle search increment, degrees.

    Returns
    -------
    RotationEstimate
        The angle is resolved to ``step_deg``; the axis is exact for
        noise-free data. Fails (gives a poor axis) when all J vectors are
        parallel, e.g. one photo whose ξ and ρ turn identically.
    """
    xi_e, rho_e = _axes(estimated)
    xi_m, rho_m = _axes(measured)
    est = np.concatenate([xi_e, rho_e])
    meas = np.concatenate([xi_m, rho_m])
    j = j_vectors(est, meas)
    axis, eigenvalues = rotation_axis_from_j(j)
    if not np.any(np.linalg.norm(j, axis=1) > 1e-12):
        Q = np.eye(3)  # the frames already agree: no J, no rotation
    else:
        angle, _, _ = angle_by_rss_search(axis, est, meas, step_deg)
        Q = Rotation.from_rotvec(axis * math.radians(angle)).as_matrix()
    return RotationEstimate(
        "paper",
        Q,
        np.ones(len(xi_e), bool),
        _rms(Q, xi_e, rho_e, xi_m, rho_m),
        {"step_deg": step_deg, "j_tensor_eigenvalues": eigenvalues.tolist()},
    )


def estimate_rotation_lsq(
    estimated: np.ndarray, measured: np.ndarray, weights: np.ndarray | None = None
) -> RotationEstimate:
    """Closed-form least-squares rotation over all ξ and ρ pairs (Wahba's problem).

    Minimises ``Σ wᵢ (|ξᵢ − Q ξ̂ᵢ|² + |ρᵢ − Q ρ̂ᵢ|²)`` by SVD
    (:meth:`scipy.spatial.transform.Rotation.align_vectors`).

    Parameters
    ----------
    estimated : (N, 3, 3) array
        ``cam_from_model`` of each photo.
    measured : (N, 3, 3) array
        ``cam_from_world`` of each photo.
    weights : (N,) array, optional
        Per-photo weights (e.g. 1/σ²), applied to both ξ and ρ.
    """
    xi_e, rho_e = _axes(estimated)
    xi_m, rho_m = _axes(measured)
    Q = _align(xi_e, rho_e, xi_m, rho_m, weights)
    return RotationEstimate(
        "lsq", Q, np.ones(len(xi_e), bool), _rms(Q, xi_e, rho_e, xi_m, rho_m)
    )


def _align(xi_e, rho_e, xi_m, rho_m, weights=None) -> np.ndarray:
    w = None if weights is None else np.concatenate([weights, weights])
    rotation, _ = Rotation.align_vectors(
        np.concatenate([xi_m, rho_m]), np.concatenate([xi_e, rho_e]), weights=w
    )
    return rotation.as_matrix()


def estimate_rotation_robust(
    estimated: np.ndarray,
    measured: np.ndarray,
    weights: np.ndarray | None = None,
    threshold_factor: float = 3.0,
    min_threshold_deg: float = 1.0,
    max_iterations: int = 20,
    max_hypotheses: int = 300,
) -> RotationEstimate:
    """Least-squares rotation that sets aside grossly wrong photos.

    Each photo alone fixes a rotation (``Qᵢ = Mᵢᵀ Eᵢ``). The hypothesis with
    the least median per-photo residual (LMedS) seeds the fit; then, until
    the kept set stops changing, photos whose residual exceeds
    ``threshold_factor × 1.4826 × median residual`` (at least
    ``min_threshold_deg``) are set aside and the rest fitted by
    :func:`estimate_rotation_lsq`. Works while fewer than half the photos
    are wrong.

    Parameters
    ----------
    estimated : (N, 3, 3) array
        ``cam_from_model`` of each photo.
    measured : (N, 3, 3) array
        ``cam_from_world`` of each photo.
    weights : (N,) array, optional
        Per-photo weights for the least-squares steps.
    threshold_factor : float
        Cut-off in robust standard deviations.
    min_threshold_deg : float
        Never set aside photos closer than this, degrees.
    max_iterations : int
        Trimming rounds at most.
    max_hypotheses : int
        Single-photo hypotheses tried at most (evenly spread over the photos).

    Returns
    -------
    RotationEstimate
        ``inliers`` marks the photos kept; ``details`` gives the final
        threshold in degrees and the number of rounds.
    """
    E = np.asarray(estimated, dtype=np.float64).reshape(-1, 3, 3)
    M = np.asarray(measured, dtype=np.float64).reshape(-1, 3, 3)
    xi_e, rho_e = _axes(E)
    xi_m, rho_m = _axes(M)
    n = len(E)
    picks = np.unique(np.linspace(0, n - 1, min(n, max_hypotheses)).round().astype(int))
    hypotheses = np.transpose(M[picks], (0, 2, 1)) @ E[picks]  # Mᵢᵀ Eᵢ, (H, 3, 3)
    scores = np.median(_per_photo_residual(hypotheses, xi_e, rho_e, xi_m, rho_m), axis=1)
    Q = hypotheses[int(np.argmin(scores))]

    inliers = np.ones(n, bool)
    threshold = math.inf
    rounds = 0
    for rounds in range(1, max_iterations + 1):
        residual = _per_photo_residual(Q, xi_e, rho_e, xi_m, rho_m)
        threshold = max(threshold_factor * 1.4826 * float(np.median(residual)), min_threshold_deg)
        keep = residual <= threshold
        if keep.sum() < 2:  # too few to fit: keep the best-agreeing ones
            keep = residual <= np.sort(residual)[min(1, n - 1)]
        w = None if weights is None else np.asarray(weights, dtype=np.float64)[keep]
        Q = _align(xi_e[keep], rho_e[keep], xi_m[keep], rho_m[keep], w)
        if rounds > 1 and np.array_equal(keep, inliers):
            break
        inliers = keep
    return RotationEstimate(
        "robust",
        Q,
        inliers,
        _rms(Q, xi_e, rho_e, xi_m, rho_m),
        {"threshold_deg": threshold, "rounds": rounds},
    )
