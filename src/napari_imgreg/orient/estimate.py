"""Orient a photogrammetry model from the camera attitudes a phone recorded.

A structure-from-motion model built without ground control sits in an
arbitrary frame. Each photo's camera has, in that frame, an estimated view
direction ξ (camera z) and image long axis ρ (camera x); the phone measured
the same two vectors in the true-north frame (trend, plunge, roll, contract
§2). The rotation ``Q`` (``world_from_model``) that best carries the
estimated vectors onto the measured ones orients the model, and what
remains per photo — Δξ and Δρ — reveals sensor errors and model distortion
(Tavani, Corradetti et al., 2019, "Smartphone: an alternative to ground control
points for orienting virtual outcrop models and assessing their quality",
Geosphere 15(6), 2043, doi:10.1130/GES02167.1).

Three estimators are computed side by side:

``paper``
    The paper's method: J vectors join measured and estimated ξ and ρ; the
    rotation axis is the eigenvector of the smallest eigenvalue of their
    orientation tensor; the angle is found by a residual-sum-of-squares
    search about that axis in 0.1° steps.
``lsq``
    The closed-form least-squares rotation over all ξ and ρ pairs (Wahba's
    problem, solved by SVD in :meth:`scipy.spatial.transform.Rotation.align_vectors`),
    optionally weighted per photo.
``robust``
    Least squares after setting aside photos whose attitude disagrees
    grossly with the rest (a 20° compass error): every photo alone defines a
    rotation; the one with the least median residual seeds an iteratively
    trimmed least-squares fit.

Diagnostics follow the paper: per-photo Δξ and Δρ, their mean absolute
values, and the best-fit slopes and R² of Δξ against the position along the
survey path and against the measured trend, read as quality flags
(mean < 2°, |slope vs path| < 3, |slope vs trend| ≤ 0.1).

Units and definitions
---------------------
* Δξ (Δρ) is the angle in degrees between the measured ξ (ρ) and the
  estimated-and-rotated one, signed positive when the measured vector lies
  clockwise of the rotated estimate seen from above (the sign of the trend
  difference); a vector with no horizontal turn counts as positive.
* Position along the survey path is dimensionless, 0 at one end of the
  survey and 1 at the other: each camera centre is projected on the survey
  line (the principal axis of the camera centres), oriented so it grows in
  capture order. Without camera centres, the photo's rank in the MEASURED
  table is used. The slope against it is therefore in degrees per survey
  length: the change of Δξ from one end of the path to the other. The paper
  gives no formula; its numbers imply this scale (a slope of 26 "implying
  values of about −13° and 13° at the two ends", and slopes < 3.2 meaning a
  "maximum distortion between the edges of the models" of ~3°).
* The slope against the measured trend is in degrees per degree (the
  paper: Δξ from −4° to 4° over trends 200°–280° is a slope of 0.1); trends
  are unwrapped about their circular mean so a survey across north is one
  interval.
* The J vectors are normalised before they enter the orientation tensor
  (they stand for the normals of the planes γ); on generated surveys this
  gives a better axis than weighting by their length.
* The rotation is applied about a centre ``c``:
  ``X_world = Q (X_model − c) + c``. By default ``c`` is the centroid of the
  estimated camera centres (the model stays where it was, only turned);
  without camera centres it is the model origin.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from napari_imgreg.camera import attitude_from_rotation
from napari_imgreg.errors import input_error
from napari_imgreg.io.orientation_tables import (
    OrientationTable,
    PairedOrientations,
    pair_tables,
    read_orientation_table,
)

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = [
    "METHODS",
    "PAPER_STEP_DEG",
    "MEAN_RESIDUAL_MAX_DEG",
    "PATH_SLOPE_MAX",
    "TREND_SLOPE_MAX",
    "RotationEstimate",
    "LinearFit",
    "QualityFlag",
    "OrientationResult",
    "j_vectors",
    "orientation_tensor",
    "rotation_axis_from_j",
    "angle_by_rss_search",
    "estimate_rotation_paper",
    "estimate_rotation_lsq",
    "estimate_rotation_robust",
    "residual_angles",
    "survey_path_position",
    "unwrap_trend",
    "fit_line",
    "quality_flags",
    "orient",
    "orient_files",
    "rotate_points",
    "rotate_cameras",
    "apply_to_mesh_file",
    "MESH_OUT_SUFFIXES",
    "draw_residual_plots",
    "save_residual_plots",
    "save_orientation",
    "SimulatedSurvey",
    "simulate_survey",
    "rotation_error_deg",
    "lower_hemisphere_axis",
]

METHODS = ("paper", "lsq", "robust")
PAPER_STEP_DEG = 0.1
# The paper's quality indicators (its concluding paragraph).
MEAN_RESIDUAL_MAX_DEG = 2.0  # mean |Δξ|, |Δρ| of faithful models
DISTORTED_RESIDUAL_DEG = 4.0  # ... and of noticeably distorted ones
PATH_SLOPE_MAX = 3.0  # |slope| of Δξ vs path position, degrees per path length
TREND_SLOPE_MAX = 0.1  # |slope| of Δξ vs measured trend, degrees per degree

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


def residual_angles(
    rotation: np.ndarray, estimated: np.ndarray, measured: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Signed Δξ and Δρ of each photo under a rotation.

    Parameters
    ----------
    rotation : (3, 3) array
        ``world_from_model``.
    estimated : (N, 3, 3) array
        ``cam_from_model`` of each photo.
    measured : (N, 3, 3) array
        ``cam_from_world`` of each photo.

    Returns
    -------
    delta_xi_deg, delta_rho_deg : (N,) arrays
        Angles in degrees between measured and estimated-and-rotated ξ and
        ρ, positive when the measured vector is clockwise of the rotated one
        seen from above.
    """
    xi_e, rho_e = _axes(estimated)
    xi_m, rho_m = _axes(measured)
    Q = np.asarray(rotation, dtype=np.float64)

    def signed(est: np.ndarray, meas: np.ndarray) -> np.ndarray:
        turned = est @ Q.T
        angle = _angle_between(turned, meas)
        clockwise = np.cross(turned, meas) @ _UP <= 0.0
        return np.where(clockwise, angle, -angle)

    return signed(xi_e, xi_m), signed(rho_e, rho_m)


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


# ----------------------------------------------------------- diagnostics
def survey_path_position(
    positions: np.ndarray | None, capture_order: np.ndarray
) -> tuple[np.ndarray, str]:
    """Position of each photo along the survey path, 0 at one end, 1 at the other.

    Parameters
    ----------
    positions : (N, 3) array or None
        Camera centres (any frame), metres.
    capture_order : (N,) array
        Rank of each photo in capture order.

    Returns
    -------
    position : (N,) array
        Dimensionless, in [0, 1], growing in capture order.
    source : str
        How it was computed (for reports).
    """
    order = np.asarray(capture_order, dtype=np.float64)
    n = len(order)
    if positions is not None and n >= 2:
        centred = np.asarray(positions, dtype=np.float64) - np.mean(positions, axis=0)
        _, singular, vt = np.linalg.svd(centred, full_matrices=False)
        if singular[0] > 1e-9:
            along = centred @ vt[0]
            if np.ptp(order) > 0 and np.corrcoef(along, order)[0, 1] < 0:
                along = -along  # so the position grows in capture order
            span = np.ptp(along)
            return (along - along.min()) / span, "camera centres projected on the survey line"
    ranks = np.argsort(np.argsort(order)).astype(np.float64)
    return ranks / max(n - 1, 1), "photo order in the measured table"


def unwrap_trend(trend_deg: np.ndarray) -> np.ndarray:
    """Trends (degrees) unwrapped about their circular mean, so 355° and 5° are 10° apart."""
    from scipy.stats import circmean

    t = np.asarray(trend_deg, dtype=np.float64)
    mean = float(circmean(t, high=360.0, low=0.0))
    return mean + (t - mean + 180.0) % 360.0 - 180.0


@dataclass(frozen=True)
class LinearFit:
    """Least-squares line ``y = slope · x + intercept``.

    Attributes
    ----------
    slope, intercept : float
        In the units of y per unit of x, and of y.
    r2 : float
        Coefficient of determination.
    n : int
        Points fitted.
    x_span : float
        Range of x covered.
    """

    slope: float
    intercept: float
    r2: float
    n: int
    x_span: float

    def to_dict(self) -> dict[str, Any]:
        return {
            "slope": _finite(self.slope),
            "intercept": _finite(self.intercept),
            "r2": _finite(self.r2),
            "n": self.n,
            "x_span": _finite(self.x_span),
        }


def fit_line(x: np.ndarray, y: np.ndarray) -> LinearFit | None:
    """Best-fit line by :func:`scipy.stats.linregress`; None with < 3 points or constant x."""
    from scipy.stats import linregress

    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if len(x) < 3 or np.ptp(x) <= 0:
        return None
    fit = linregress(x, y)
    return LinearFit(
        float(fit.slope), float(fit.intercept), float(fit.rvalue**2), len(x), float(np.ptp(x))
    )


@dataclass(frozen=True)
class QualityFlag:
    """One of the paper's quality indicators, read for the user.

    Attributes
    ----------
    key : str
        ``"mean_residual"``, ``"slope_vs_path"`` or ``"slope_vs_trend"``.
    title : str
        Short name for displays.
    status : str
        ``"pass"``, ``"warn"`` or ``"n/a"`` (too few photos to tell).
    value, threshold : float or None
        The indicator and its limit.
    reading : str
        What it means, in plain language.
    """

    key: str
    title: str
    status: str
    value: float | None
    threshold: float
    reading: str

    def to_dict(self) -> dict[str, Any]:
        return {
            "key": self.key,
            "title": self.title,
            "status": self.status,
            "value": _finite(self.value),
            "threshold": self.threshold,
            "reading": self.reading,
        }


def quality_flags(
    mean_abs_deg: float, path_fit: LinearFit | None, trend_fit: LinearFit | None
) -> list[QualityFlag]:
    """The paper's three indicators as pass/warn flags with plain readings.

    Parameters
    ----------
    mean_abs_deg : float
        The larger of mean |Δξ| and mean |Δρ|, degrees.
    path_fit, trend_fit : LinearFit or None
        Δξ against position along the survey path (degrees per path
        length) and against measured trend (degrees per degree).
    """
    flags = []
    if mean_abs_deg < MEAN_RESIDUAL_MAX_DEG:
        reading = (
            f"Camera directions agree with the phone to {mean_abs_deg:.1f}° on average "
            f"(< {MEAN_RESIDUAL_MAX_DEG:g}°): a geometrically faithful model, oriented about "
            "as well as the phone's sensors allow."
        )
        status = "pass"
    else:
        status = "warn"
        cause = (
            f"above {DISTORTED_RESIDUAL_DEG:g}°, like the paper's distorted models"
            if mean_abs_deg > DISTORTED_RESIDUAL_DEG
            else f"faithful models stay below {MEAN_RESIDUAL_MAX_DEG:g}°"
        )
        reading = (
            f"Camera directions differ from the phone's by {mean_abs_deg:.1f}° on average "
            f"({cause}): the model is distorted or the phone's sensors were off; the two "
            "slopes tell which."
        )
    flags.append(
        QualityFlag(
            "mean_residual", "mean |Δξ|, |Δρ|", status, mean_abs_deg, MEAN_RESIDUAL_MAX_DEG,
            reading,
        )
    )

    if path_fit is None:
        flags.append(
            QualityFlag("slope_vs_path", "Δξ vs survey path", "n/a", None, PATH_SLOPE_MAX,
                        "Too few photos (or no spread along the path) to test for doming.")
        )
    else:
        s, r2 = path_fit.slope, path_fit.r2
        if abs(s) < PATH_SLOPE_MAX:
            reading = (
                f"No doming along the survey path: Δξ changes by {s:+.1f}° from one end of "
                f"the path to the other (R² {r2:.2f}; bent models exceed ±{PATH_SLOPE_MAX:g}°)."
            )
            status = "pass"
        else:
            reading = (
                f"Doming along the survey path: Δξ changes by {s:+.1f}° from one end of the "
                f"path to the other (R² {r2:.2f}), so the model is bent and its ends are "
                f"turned about ±{abs(s) / 2:.0f}° from true. Add oblique, convergent photos "
                "and more overlap, or use ground control."
            )
            status = "warn"
        flags.append(
            QualityFlag("slope_vs_path", "Δξ vs survey path", status, s, PATH_SLOPE_MAX, reading)
        )

    if trend_fit is None:
        flags.append(
            QualityFlag("slope_vs_trend", "Δξ vs measured trend", "n/a", None, TREND_SLOPE_MAX,
                        "Too few photos (or all facing one way) to test the compass.")
        )
    else:
        s, r2, span = trend_fit.slope, trend_fit.r2, trend_fit.x_span
        narrow = (
            f"; the photos face a range of only {span:.0f}°, so this is loosely constrained"
            if span < 20
            else ""
        )
        if abs(s) <= TREND_SLOPE_MAX:
            reading = (
                f"Compass consistent: Δξ changes by {s:+.2f}° per degree of view direction "
                f"(R² {r2:.2f}; ≤ {TREND_SLOPE_MAX:g} in calibrated surveys){narrow}."
            )
            status = "pass"
        else:
            reading = (
                f"Compass not calibrated: Δξ changes by {s:+.2f}° per degree of view direction "
                f"(R² {r2:.2f}; calibrated phones give ≤ {TREND_SLOPE_MAX:g}), about "
                f"{abs(s) * span:.0f}° across the {span:.0f}° of directions photographed"
                f"{narrow}. "
                "Recalibrate the compass (figure-of-eight), switch on airplane mode, keep away "
                "from metal, and re-measure."
            )
            status = "warn"
        flags.append(
            QualityFlag(
                "slope_vs_trend", "Δξ vs measured trend", status, s, TREND_SLOPE_MAX, reading
            )
        )
    return flags


# ----------------------------------------------------------------- result
@dataclass
class OrientationResult:
    """The orientation of a model and its diagnostics (ORIENTATION.json).

    Attributes
    ----------
    method : str
        The estimator whose rotation is the result.
    estimates : dict of str to RotationEstimate
        All three estimators' results.
    center : (3,) array
        Rotation centre in the model frame, metres.
    center_source : str
        ``"cameras"`` (centroid of estimated camera centres), ``"origin"``
        or ``"given"``.
    photos : list of str
        Paired photos, in capture order of the MEASURED table.
    delta_xi_deg, delta_rho_deg : (N,) arrays
        Signed residuals under the chosen rotation, degrees.
    path_position : (N,) array
        Position along the survey path, 0–1.
    path_position_source : str
    measured_trend_deg : (N,) array
        Measured trend unwrapped about its circular mean, degrees.
    measured : (N, 3, 3) array
        ``cam_from_world`` measured.
    oriented : (N, 3, 3) array
        ``cam_from_world`` of the estimated cameras after rotation.
    oriented_positions : (N, 3) array or None
        Estimated camera centres after rotation, metres.
    fits : dict of str to LinearFit or None
        ``delta_xi_vs_path``, ``delta_rho_vs_path``, ``delta_xi_vs_trend``,
        ``delta_rho_vs_trend``.
    flags : list of QualityFlag
    notes : list of str
    inputs : dict
        Where the tables came from.
    """

    method: str
    estimates: dict[str, RotationEstimate]
    center: np.ndarray
    center_source: str
    photos: list[str]
    delta_xi_deg: np.ndarray
    delta_rho_deg: np.ndarray
    path_position: np.ndarray
    path_position_source: str
    measured_trend_deg: np.ndarray
    measured: np.ndarray
    oriented: np.ndarray
    oriented_positions: np.ndarray | None
    fits: dict[str, LinearFit | None]
    flags: list[QualityFlag]
    notes: list[str] = field(default_factory=list)
    inputs: dict[str, Any] = field(default_factory=dict)

    # ------------------------------------------------------------ views
    @property
    def chosen(self) -> RotationEstimate:
        return self.estimates[self.method]

    @property
    def rotation(self) -> np.ndarray:
        """``Q``, world_from_model, (3, 3)."""
        return self.chosen.rotation

    @property
    def angle_deg(self) -> float:
        return self.chosen.angle_deg

    @property
    def axis(self) -> np.ndarray:
        return self.chosen.axis

    @property
    def transform(self) -> np.ndarray:
        """4 × 4 world_from_model: ``X_world = Q (X − c) + c``."""
        T = np.eye(4)
        T[:3, :3] = self.rotation
        T[:3, 3] = self.center - self.rotation @ self.center
        return T

    @property
    def used(self) -> np.ndarray:
        """(N,) bool: photos the chosen estimator rests on (the diagnostics use these)."""
        return self.chosen.inliers

    @property
    def mean_abs_delta_xi_deg(self) -> float:
        """Mean |Δξ| over the photos used, degrees."""
        return float(np.mean(np.abs(self.delta_xi_deg[self.used])))

    @property
    def mean_abs_delta_rho_deg(self) -> float:
        """Mean |Δρ| over the photos used, degrees."""
        return float(np.mean(np.abs(self.delta_rho_deg[self.used])))

    @property
    def outliers(self) -> list[str]:
        """Photos the robust estimator set aside."""
        keep = self.estimates["robust"].inliers
        return [p for p, k in zip(self.photos, keep) if not k]

    @property
    def warnings(self) -> list[QualityFlag]:
        return [f for f in self.flags if f.status == "warn"]

    def summary_lines(self) -> list[str]:
        """A short human summary (used by the CLI and the widget)."""
        trend, plunge, angle = lower_hemisphere_axis(self.axis, self.angle_deg)
        names = {
            "paper": f"paper (J tensor + {self.estimates['paper'].details['step_deg']:g}° search)",
            "lsq": "least squares",
            "robust": "robust",
        }
        sense = "clockwise" if angle >= 0 else "anticlockwise"
        lines = [
            f"{len(self.photos)} photos paired; {names[self.method]}: rotation {abs(angle):.2f}° "
            f"{sense} looking down an axis plunging {plunge:.1f}° toward {trend:.1f}° "
            f"(about the {self._center_text()})",
        ]
        for name in METHODS:
            if name == self.method:
                continue
            est = self.estimates[name]
            lines.append(
                f"  {names[name]}: {est.angle_deg:.2f}°, "
                f"{rotation_error_deg(est.rotation, self.rotation):.2f}° from the "
                f"{self.method} result"
            )
        if self.outliers:
            shown = ", ".join(self.outliers[:6]) + (", ..." if len(self.outliers) > 6 else "")
            lines.append(f"  robust fit set aside {len(self.outliers)} photo(s): {shown}")
        lines.append(
            f"mean |Δξ| {self.mean_abs_delta_xi_deg:.2f}°, "
            f"mean |Δρ| {self.mean_abs_delta_rho_deg:.2f}°"
        )
        for flag in self.flags:
            label = {"pass": "ok", "warn": "WARNING", "n/a": "n/a"}[flag.status]
            lines.append(f"  [{label}] {flag.reading}")
        return lines

    def _center_text(self) -> str:
        c = ", ".join(f"{v:.2f}" for v in self.center)
        return {
            "cameras": f"camera centroid ({c})",
            "origin": "model origin",
            "given": f"point ({c})",
        }[self.center_source]

    # ------------------------------------------------------------- JSON
    def to_dict(self) -> dict[str, Any]:
        """ORIENTATION.json content (JSON-ready)."""
        axis, angle = _axis_angle(self.rotation)
        trend, plunge = _trend_plunge(axis)
        lower_trend, lower_plunge, lower_angle = lower_hemisphere_axis(axis, angle)
        robust_keep = self.estimates["robust"].inliers
        measured_att = [attitude_from_rotation(R) for R in self.measured]
        oriented_att = [attitude_from_rotation(R) for R in self.oriented]
        photos = []
        for i, name in enumerate(self.photos):
            entry: dict[str, Any] = {
                "photo": name,
                "delta_xi_deg": float(self.delta_xi_deg[i]),
                "delta_rho_deg": float(self.delta_rho_deg[i]),
                "path_position": float(self.path_position[i]),
                "measured_trend_deg": float(self.measured_trend_deg[i]) % 360.0,
                "measured": dict(zip(("trend_deg", "plunge_deg", "roll_deg"), measured_att[i])),
                "oriented": dict(zip(("trend_deg", "plunge_deg", "roll_deg"), oriented_att[i])),
                "robust_outlier": bool(not robust_keep[i]),
                "used": bool(self.used[i]),
            }
            if self.oriented_positions is not None:
                entry["oriented"]["position"] = self.oriented_positions[i].tolist()
            photos.append(entry)
        units = {
            "delta_xi_vs_path": "degrees per survey path length",
            "delta_rho_vs_path": "degrees per survey path length",
            "delta_xi_vs_trend": "degrees per degree of measured trend",
            "delta_rho_vs_trend": "degrees per degree of measured trend",
        }
        slopes = {}
        for key, fit in self.fits.items():
            slopes[key] = None if fit is None else {**fit.to_dict(), "units": units[key]}
        return {
            "method": self.method,
            "rotation": {
                "matrix": self.rotation.tolist(),
                "axis": axis.tolist(),
                "axis_trend_deg": trend,
                "axis_plunge_deg": plunge,
                "angle_deg": angle,
                "lower_hemisphere": {
                    "axis_trend_deg": lower_trend,
                    "axis_plunge_deg": lower_plunge,
                    "angle_deg": lower_angle,
                    "sense": "positive clockwise looking down the plunge",
                },
                "center": self.center.tolist(),
                "center_source": self.center_source,
                "transform_4x4": self.transform.tolist(),
                "convention": "X_world = matrix @ (X_model - center) + center; right-handed "
                "about axis; world +X east, +Y north, +Z up",
            },
            "estimators": {name: est.to_dict(self.photos) for name, est in self.estimates.items()},
            "residuals": {
                "mean_abs_delta_xi_deg": self.mean_abs_delta_xi_deg,
                "mean_abs_delta_rho_deg": self.mean_abs_delta_rho_deg,
                "mean_abs_delta_xi_all_deg": float(np.mean(np.abs(self.delta_xi_deg))),
                "mean_abs_delta_rho_all_deg": float(np.mean(np.abs(self.delta_rho_deg))),
                "n_used": int(self.used.sum()),
                "sign": "positive when the measured vector is clockwise (seen from above) of "
                "the estimated-and-rotated one",
                "photos": photos,
            },
            "path_position": {
                "source": self.path_position_source,
                "definition": "0 at one end of the survey, 1 at the other; grows in capture order",
            },
            "slopes": slopes,
            "flags": [f.to_dict() for f in self.flags],
            "notes": list(self.notes),
            "inputs": dict(self.inputs),
        }


# -------------------------------------------------------------- pipeline
def orient(
    estimated: OrientationTable | PairedOrientations,
    measured: OrientationTable | None = None,
    method: str = "robust",
    weights: Mapping[str, float] | None = None,
    center: np.ndarray | str | None = None,
    step_deg: float = PAPER_STEP_DEG,
    declination_deg: float = 0.0,
) -> OrientationResult:
    """Orient a model from estimated and measured camera attitudes.

    Parameters
    ----------
    estimated : OrientationTable or PairedOrientations
        The model's camera orientations (its frame), or tables already
        paired by :func:`~napari_imgreg.io.orientation_tables.pair_tables`.
    measured : OrientationTable
        The phone's (true north); omit when ``estimated`` is paired.
    method : {"robust", "lsq", "paper"}
        Estimator whose rotation is the result (all three are reported).
    weights : mapping of photo name to weight, optional
        Per-photo weights for ``lsq`` and ``robust`` (missing names: 1).
    center : (3,) array, "cameras" or "origin", optional
        Rotation centre in the model frame. Default: the centroid of the
        estimated camera centres when known, else the origin.
    step_deg : float
        Angle increment of the paper's search, degrees.
    declination_deg : float
        Magnetic declination, degrees east of true north, added to the
        measured trends (for a phone that logs magnetic headings).

    Returns
    -------
    OrientationResult

    Raises
    ------
    InputError
        The tables do not pair (see ``pair_tables``).
    ValueError
        Unknown ``method``.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if isinstance(estimated, PairedOrientations):
        paired = estimated
        inputs: dict[str, Any] = {}
    else:
        if measured is None:
            raise ValueError("give both the estimated and the measured table")
        paired = pair_tables(estimated, measured)
        inputs = {
            "estimated": str(estimated.source) if estimated.source else None,
            "estimated_format": estimated.kind,
            "measured": str(measured.source) if measured.source else None,
            "measured_format": measured.kind,
        }
    inputs["n_photos"] = len(paired)
    inputs["declination_deg"] = float(declination_deg)
    w = None
    if weights is not None:
        w = np.array([float(weights.get(p, 1.0)) for p in paired.photos])

    E, M = paired.estimated, paired.measured
    if declination_deg:
        # Turning every measured axis clockwise (seen from above) adds to its trend.
        M = M @ Rotation.from_rotvec([0.0, 0.0, declination_deg], degrees=True).as_matrix()
    estimates = {
        "paper": estimate_rotation_paper(E, M, step_deg),
        "lsq": estimate_rotation_lsq(E, M, w),
        "robust": estimate_rotation_robust(E, M, w),
    }
    Q = estimates[method].rotation

    positions = paired.estimated_positions
    if isinstance(center, str):
        if center == "cameras" and positions is None:
            raise input_error(
                inputs.get("estimated"), "no camera centres to rotate about (use the origin)"
            )
        if center not in ("cameras", "origin"):
            raise ValueError(f"center must be 'cameras', 'origin' or a point, got {center!r}")
        center_source = center
    elif center is not None:
        center_source = "given"
    else:
        center_source = "cameras" if positions is not None else "origin"
    if center_source == "cameras":
        c = positions.mean(axis=0)
    elif center_source == "origin":
        c = np.zeros(3)
    else:
        c = np.asarray(center, dtype=np.float64).reshape(3)

    d_xi, d_rho = residual_angles(Q, E, M)
    path_source_positions = positions if positions is not None else paired.measured_positions
    path_position, path_source = survey_path_position(path_source_positions, paired.capture_order)
    trend = unwrap_trend(np.degrees(np.arctan2(M[:, 2, 0], M[:, 2, 1])))
    # Photos the chosen estimator set aside (gross sensor errors) would drive
    # the fits; they are reported, not fitted.
    used = estimates[method].inliers
    fits = {
        "delta_xi_vs_path": fit_line(path_position[used], d_xi[used]),
        "delta_rho_vs_path": fit_line(path_position[used], d_rho[used]),
        "delta_xi_vs_trend": fit_line(trend[used], d_xi[used]),
        "delta_rho_vs_trend": fit_line(trend[used], d_rho[used]),
    }
    mean_abs = max(float(np.mean(np.abs(d_xi[used]))), float(np.mean(np.abs(d_rho[used]))))
    flags = quality_flags(mean_abs, fits["delta_xi_vs_path"], fits["delta_xi_vs_trend"])
    oriented, oriented_positions = rotate_cameras(E, positions, Q, c)
    return OrientationResult(
        method=method,
        estimates=estimates,
        center=c,
        center_source=center_source,
        photos=list(paired.photos),
        delta_xi_deg=d_xi,
        delta_rho_deg=d_rho,
        path_position=path_position,
        path_position_source=path_source,
        measured_trend_deg=trend,
        measured=M,
        oriented=oriented,
        oriented_positions=oriented_positions,
        fits=fits,
        flags=flags,
        notes=list(paired.notes),
        inputs=inputs,
    )


def orient_files(
    estimated_path: str | os.PathLike, measured_path: str | os.PathLike, **kwargs
) -> OrientationResult:
    """Read two orientation tables (any supported format) and :func:`orient` them."""
    estimated = read_orientation_table(estimated_path)
    measured = read_orientation_table(measured_path)
    return orient(estimated, measured, **kwargs)


def save_orientation(result: OrientationResult, path: str | os.PathLike) -> None:
    """Write ORIENTATION.json atomically."""
    import json

    from napari_imgreg._atomic import atomic_write

    with atomic_write(path, encoding="utf-8") as fh:
        json.dump(result.to_dict(), fh, indent=2, ensure_ascii=False)
        fh.write("\n")


# ----------------------------------------------------------------- apply
def rotate_points(
    points: np.ndarray, rotation: np.ndarray, center: np.ndarray | None = None
) -> np.ndarray:
    """Rotate points about a centre: ``Q (X − c) + c``.

    Parameters
    ----------
    points : (N, 3) array
        Model-frame points, metres.
    rotation : (3, 3) array
        ``Q``, world_from_model.
    center : (3,) array, optional
        Rotation centre (default: origin).

    Returns
    -------
    (N, 3) float64 array
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    c = np.zeros(3) if center is None else np.asarray(center, dtype=np.float64).reshape(3)
    return (p - c) @ np.asarray(rotation, dtype=np.float64).T + c


def rotate_cameras(
    cam_from_model: np.ndarray,
    centres: np.ndarray | None,
    rotation: np.ndarray,
    center: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Cameras of a rotated model.

    Parameters
    ----------
    cam_from_model : (N, 3, 3) array
        World-to-camera rotations in the model frame.
    centres : (N, 3) array or None
        Camera centres in the model frame.
    rotation : (3, 3) array
        ``Q``, world_from_model.
    center : (3,) array, optional
        Rotation centre.

    Returns
    -------
    cam_from_world : (N, 3, 3) array
        ``R Qᵀ``.
    centres_world : (N, 3) array or None
    """
    R = np.asarray(cam_from_model, dtype=np.float64).reshape(-1, 3, 3) @ np.asarray(rotation).T
    return R, None if centres is None else rotate_points(centres, rotation, center)


MESH_OUT_SUFFIXES = (".obj", ".ply", ".glb", ".off", ".stl")


def apply_to_mesh_file(
    source: str | os.PathLike,
    destination: str | os.PathLike,
    rotation: np.ndarray,
    center: np.ndarray | None = None,
) -> str:
    """Rotate a mesh or point cloud file and write it (atomically).

    Meshes keep their texture or vertex colours (an OBJ is written with an
    MTL and texture image named after it); a PLY without faces is treated
    as a point cloud and written as PLY with its colours.

    Parameters
    ----------
    source, destination : path-like
        Input (any format :func:`~napari_imgreg.io.meshes.load_mesh` reads,
        or a PLY point cloud) and output (``.obj``, ``.ply``, ``.glb``,
        ``.off``, ``.stl``).
    rotation : (3, 3) array
        ``Q``, world_from_model.
    center : (3,) array, optional
        Rotation centre (default: origin).

    Returns
    -------
    str
        What was written, e.g. ``"mesh, 12,345 vertices"``.

    Raises
    ------
    InputError
        Unreadable input or unsupported output format.
    """
    import trimesh

    from napari_imgreg._atomic import atomic_path, atomic_write
    from napari_imgreg.io.meshes import load_mesh

    source, destination = Path(source), Path(destination)
    suffix = destination.suffix.lower()
    if suffix not in MESH_OUT_SUFFIXES:
        raise input_error(destination, f"output must be one of {', '.join(MESH_OUT_SUFFIXES)}")
    if source.resolve() == destination.resolve():
        raise input_error(destination, "refusing to overwrite the input mesh; choose another name")

    if source.suffix.lower() == ".ply" and source.is_file() and _ply_has_no_faces(source):
        cloud = trimesh.load(source, process=False)
        if not isinstance(cloud, trimesh.PointCloud) or len(cloud.vertices) == 0:
            raise input_error(source, "PLY has neither faces nor readable points")
        if suffix != ".ply":
            raise input_error(destination, "a point cloud is written as .ply")
        colors = cloud.colors if len(getattr(cloud, "colors", [])) else None
        rotated = trimesh.PointCloud(rotate_points(cloud.vertices, rotation, center), colors=colors)
        with atomic_path(destination) as tmp:
            rotated.export(tmp, file_type="ply")
        return f"point cloud, {len(rotated.vertices):,} points"

    data = load_mesh(source)
    vertices = rotate_points(data.vertices, rotation, center)
    visual = None
    if data.texture is not None and data.uv is not None:
        from PIL import Image

        material = trimesh.visual.material.SimpleMaterial(
            image=Image.fromarray(data.texture), name=destination.stem
        )
        visual = trimesh.visual.TextureVisuals(uv=data.uv, material=material)
    elif data.vertex_colors is not None:
        visual = trimesh.visual.ColorVisuals(vertex_colors=data.vertex_colors)
    mesh = trimesh.Trimesh(vertices, data.faces, visual=visual, process=False)
    if suffix == ".obj":
        from trimesh.exchange.obj import export_obj

        text, extra_files = export_obj(
            mesh, return_texture=True, mtl_name=f"{destination.stem}.mtl"
        )
        for name, blob in extra_files.items():
            with atomic_write(destination.parent / name, "wb") as fh:
                fh.write(blob)
        with atomic_write(destination, encoding="utf-8") as fh:
            fh.write(text)
    else:
        with atomic_path(destination) as tmp:
            mesh.export(tmp, file_type=suffix[1:])
    return f"mesh, {len(vertices):,} vertices" + (", textured" if data.texture is not None else "")


def _ply_has_no_faces(path: Path) -> bool:
    """True when a PLY header declares no (or zero) faces."""
    with open(path, "rb") as fh:
        head = fh.read(1 << 16)
    header = head.split(b"end_header", 1)[0].decode("ascii", "replace").lower()
    for line in header.splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[0] == "element" and parts[1] == "face":
            return parts[2] == "0"
    return True


# ------------------------------------------------------------------ plots
def draw_residual_plots(
    figure: Figure, result: OrientationResult, vertical: bool = False
) -> Figure:
    """Draw Δξ and Δρ against path position and against measured trend.

    Photos the chosen estimator set aside are drawn as crosses and left out
    of the fitted lines (as in the flags).

    Parameters
    ----------
    figure : matplotlib.figure.Figure
        Cleared and drawn into.
    result : OrientationResult
    vertical : bool
        Stack the two panels (for a narrow dock) instead of side by side.

    Returns
    -------
    Figure
    """
    from matplotlib.ticker import FuncFormatter

    figure.clear()
    panels = figure.subplots(2, 1) if vertical else figure.subplots(1, 2, sharey=True)
    set_aside = ~result.used
    series = (
        ("Δξ", result.delta_xi_deg, "tab:blue", "o", "delta_xi"),
        ("Δρ", result.delta_rho_deg, "tab:orange", "s", "delta_rho"),
    )
    for ax, x, key, xlabel, title, slope_fmt in (
        (panels[0], result.path_position, "path", "position along the survey path (0 to 1)",
         f"doming if |slope| ≥ {PATH_SLOPE_MAX:g}", "{:+.1f}"),
        (panels[1], result.measured_trend_deg, "trend", "measured trend of ξ (°)",
         f"compass off if |slope| > {TREND_SLOPE_MAX:g}", "{:+.2f}"),
    ):
        for name, y, color, marker, prefix in series:
            fit = result.fits[f"{prefix}_vs_{key}"]
            label = name
            if fit is not None:
                label += f": slope {slope_fmt.format(fit.slope)}, R² {fit.r2:.2f}"
            ax.scatter(
                x[~set_aside], y[~set_aside], s=12, color=color, marker=marker, label=label,
                alpha=0.75,
            )
            if set_aside.any():
                ax.scatter(x[set_aside], y[set_aside], s=28, color=color, marker="x")
            if fit is not None:
                xs = np.array([x.min(), x.max()])
                ax.plot(xs, fit.slope * xs + fit.intercept, color=color, lw=1.2)
        ax.axhline(0.0, color="0.6", lw=0.8)
        ax.set_xlabel(xlabel, fontsize=8)
        ax.set_ylabel("residual (°)", fontsize=8)
        ax.set_title(title, fontsize=8)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=6.5, loc="best", framealpha=0.7)
        ax.grid(alpha=0.3)
    # Trends are unwrapped about their mean for the fit; label them as compass readings.
    panels[1].xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v % 360:.0f}"))
    figure.tight_layout()
    return figure


def save_residual_plots(
    result: OrientationResult, folder: str | os.PathLike, dpi: int = 120
) -> Path:
    """Write ``orientation_residuals.png`` (Δξ, Δρ vs path and trend) into a folder."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from napari_imgreg._atomic import atomic_path

    figure = Figure(figsize=(10, 4))
    FigureCanvasAgg(figure)
    draw_residual_plots(figure, result)
    out = Path(folder) / "orientation_residuals.png"
    with atomic_path(out) as tmp:
        figure.savefig(tmp, dpi=dpi, format="png")
    return out


# -------------------------------------------------------------- simulation
@dataclass
class SimulatedSurvey:
    """A generated survey with a known orientation (tests, benchmark, docs).

    Attributes
    ----------
    estimated, measured : OrientationTable
        What the model and the phone would report.
    rotation : (3, 3) array
        The true ``world_from_model``.
    outliers : (N,) bool array
        Photos given a gross compass error.
    """

    estimated: OrientationTable
    measured: OrientationTable
    rotation: np.ndarray
    outliers: np.ndarray


def simulate_survey(
    rng: np.random.Generator,
    n_stations: int = 17,
    view_offsets_deg: Sequence[float] = (-50.0, 0.0, 50.0),
    rotation: np.ndarray | None = None,
    noise_deg: float = 0.0,
    outlier_fraction: float = 0.0,
    outlier_error_deg: float = 20.0,
    doming_deg: float = 0.0,
    compass_gain: float = 0.0,
    path_length_m: float = 200.0,
    distance_m: float = 30.0,
) -> SimulatedSurvey:
    """A walk along a wall, photographing it square-on and obliquely.

    As in the paper's test survey (51 photos: 17 stations × perpendicular
    and ±50° oblique views, ~30 m from a 200 m wall). The wall strikes in a
    random direction; plunges and rolls are random within ±10° and ±5°.

    Parameters
    ----------
    rng : numpy.random.Generator
    n_stations : int
        Camera stations along the path.
    view_offsets_deg : sequence of float
        View directions at each station relative to square-on, degrees.
    rotation : (3, 3) array, optional
        True world_from_model; default a random axis and 5–120° angle.
    noise_deg : float
        Standard deviation of the phone's trend, plunge and roll errors.
    outlier_fraction : float
        Share of photos given a ±``outlier_error_deg`` compass error.
    doming_deg : float
        Doming: the model turns the cameras about the vertical by
        ``doming_deg × (s − 0.5)`` at path position ``s`` (the paper's
        model 2 had 26°).
    compass_gain : float
        Uncalibrated compass: measured trend errs by ``compass_gain ×
        (trend − mean trend)``.
    path_length_m, distance_m : float
        Survey geometry, metres.
    """
    if rotation is None:
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        rotation = Rotation.from_rotvec(axis * math.radians(rng.uniform(5.0, 120.0))).as_matrix()
    strike = rng.uniform(0.0, 360.0)
    facing = strike + 90.0  # the photographer looks across the strike
    along = np.array([math.sin(math.radians(strike)), math.cos(math.radians(strike)), 0.0])
    towards = np.array([math.sin(math.radians(facing)), math.cos(math.radians(facing)), 0.0])

    photos, true_att, centres, s_along = [], [], [], []
    for k, s in enumerate(np.linspace(0.0, 1.0, n_stations)):
        centre = (s - 0.5) * path_length_m * along - distance_m * towards + [0, 0, 1.6]
        for offset in view_offsets_deg:
            photos.append(f"IMG_{len(photos) + 1:04d}.jpg")
            true_att.append(
                ((facing + offset) % 360.0, rng.uniform(-10.0, 10.0), rng.uniform(-5.0, 5.0))
            )
            centres.append(centre + rng.normal(scale=0.3, size=3))
            s_along.append(s)
    true_att = np.array(true_att)
    centres = np.array(centres)
    s_along = np.array(s_along)
    n = len(photos)

    measured_att = true_att + rng.normal(scale=noise_deg, size=true_att.shape)
    unwrapped = unwrap_trend(true_att[:, 0])
    measured_att[:, 0] += compass_gain * (unwrapped - unwrapped.mean())
    outliers = np.zeros(n, bool)
    n_out = int(round(outlier_fraction * n))
    if n_out:
        outliers[rng.choice(n, n_out, replace=False)] = True
        measured_att[outliers, 0] += outlier_error_deg * rng.choice([-1.0, 1.0], n_out)
    measured = OrientationTable.from_attitudes(
        photos, measured_att[:, 0], np.clip(measured_att[:, 1], -90, 90), measured_att[:, 2],
        kind="memory",
    )

    true_R = OrientationTable.from_attitudes(photos, *true_att.T).cam_from_world
    doming = Rotation.from_rotvec(
        np.outer(doming_deg * (s_along - 0.5), _UP), degrees=True
    ).as_matrix()
    # cam_from_model = cam_from_world · (turned by doming)ᵀ · Q
    estimated_R = true_R @ np.transpose(doming, (0, 2, 1)) @ rotation
    scale = rng.uniform(0.2, 5.0)  # an SfM model has an arbitrary scale and origin too
    model_centres = scale * (centres @ rotation) + rng.normal(scale=100.0, size=3)
    estimated = OrientationTable.from_rotations(photos, estimated_R, model_centres, kind="memory")
    return SimulatedSurvey(estimated, measured, rotation, outliers)
