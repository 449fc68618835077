"""A sun-shift nuisance for area matching on a relit model (issue 13; tried, no-go).

Under a low sun, relief the model lacks (beds standing proud, gullies) casts
shadows the relit render does not: the photo's band-passed shading sits a
little *away from the sun* from where the render paints it. The shift is
systematic and its direction is known, so it can be modelled: each block's
3D point ``X`` is observed at the projection of ``X + b f(X) a(X)``, with
``a`` the unit direction away from the sun projected onto the surface's
tangent plane, ``f`` 1 (``"tangent"``) or the length of a shadow cast by a
unit step under the local sun, ``cot`` of the sun's elevation above the
surface, clipped (``"shadow"``), and ``b`` one unknown length (metres) per
photo, solved with the pose.

Measured by ``diag_shading_bias.py --sunshift`` and ``--sunshift-trials``
(docs/benchmarks.md, the notes after the rough section): one ``b`` is nearly
confounded with the pose (multiple correlation 0.96-0.99 for "tangent",
0.86-0.96 for "shadow") and even the ``b``
fitted at the true pose leaves poses 1.8-4.5 px off, so the pipeline does not
use it. :func:`patched` puts it into the area rounds for the diagnostic.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from time import perf_counter

import cv2
import numpy as np
from scipy.optimize import least_squares

from napari_imgreg.camera import Intrinsics, Pose, pixels_to_scaled
from napari_imgreg.registration import pipeline as P
from napari_imgreg.registration import round as R
from napari_imgreg.registration.pose import PoseEstimate, reprojection_errors

#: Values of the nuisance's model (``"off"``: none).
SUN_SHIFT_MODES = ("off", "tangent", "shadow")


def block_normals(normal: np.ndarray, mask: np.ndarray, size_px: int) -> np.ndarray:
    """A render's normals averaged over ``size_px`` boxes (mask-aware), unit, (H, W, 3)."""
    m = mask.astype(np.float32)
    k = (int(size_px), int(size_px))
    acc = np.stack([cv2.boxFilter(normal[..., i].astype(np.float32) * m, -1, k,
                                  normalize=False) for i in range(3)], axis=-1)
    length = np.linalg.norm(acc, axis=-1, keepdims=True)
    return np.where(length > 1e-6, acc / np.maximum(length, 1e-6), 0.0).astype(np.float32)


def sun_shift_directions(normals: np.ndarray, sun: np.ndarray, mode: str = "tangent",
                         max_factor: float = 4.0) -> np.ndarray:
    """Per point, the 3D displacement (metres per metre of ``b``) of its shading.

    Parameters
    ----------
    normals : (N, 3) array
        Unit surface normals (block-averaged).
    sun : (3,) array
        Unit vector toward the sun.
    mode : {"tangent", "shadow"}
        ``tangent``: the unit sun-away direction in the tangent plane;
        ``shadow``: that times ``cot`` of the sun's elevation above the
        surface, clipped to ``max_factor`` (faces turned away get the clip).
    max_factor : float

    Returns
    -------
    (N, 3) float64 array; zero where the sun is along the normal or no normal.
    """
    n = np.asarray(normals, np.float64).reshape(-1, 3)
    s = np.asarray(sun, np.float64).reshape(3)
    s = s / np.linalg.norm(s)
    sn = n @ s
    tang = -(s[None, :] - sn[:, None] * n)  # away from the sun, in the tangent plane
    length = np.linalg.norm(tang, axis=1)
    ok = length > 1e-6
    a = np.zeros_like(n)
    a[ok] = tang[ok] / length[ok, None]
    if mode == "tangent":
        return a
    if mode != "shadow":
        raise ValueError(f"mode must be one of {SUN_SHIFT_MODES[1:]}, not {mode!r}")
    # Elevation e of the sun above the local surface: sin e = n·s, cot e = |tang| / (n·s).
    with np.errstate(divide="ignore", invalid="ignore"):
        cot = np.where(sn > 1e-6, length / sn, np.inf)
    return a * np.minimum(cot, max_factor)[:, None]


def image_directions(intrinsics: Intrinsics, pose: Pose, xyz: np.ndarray,
                     dirs: np.ndarray, step_m: float = 0.05) -> np.ndarray:
    """Image displacement (px per metre of ``b``) of points moved along ``dirs``, (N, 2)."""
    p0 = pose.project(intrinsics, xyz)
    p1 = pose.project(intrinsics, xyz + step_m * dirs)
    return (p1 - p0) / step_m


def fit_shift_scalar(shift: np.ndarray, s: np.ndarray, huber_px: float | None = None
                     ) -> float:
    """The scalar ``b`` minimising ``|shift - b s|`` (least squares, or Huber by IRLS)."""
    w = np.ones(len(shift))
    b = 0.0
    for _ in range(20 if huber_px else 1):
        num = float(np.sum(w * np.einsum("ij,ij->i", shift, s)))
        den = float(np.sum(w * np.einsum("ij,ij->i", s, s)))
        b = num / den if den > 0 else 0.0
        if huber_px:
            r = np.linalg.norm(shift - b * s, axis=1)
            w = np.where(r <= huber_px, 1.0, huber_px / np.maximum(r, 1e-12))
    return b


@dataclass
class SunShiftFit:
    """A pose solved with the sun-shift nuisance.

    Attributes
    ----------
    pose : Pose
    b : float
        The shift's length, metres (positive: away from the sun).
    b_sigma : float
        Its standard error from the fit's covariance (NaN if singular).
    inliers : (N,) bool array
    errors_px : (N,) float array
        Reprojection errors with the shift applied.
    correlation : float
        Multiple correlation of ``b`` with the six pose parameters (1 =
        confounded with a pose change).
    """

    pose: Pose
    b: float
    b_sigma: float
    inliers: np.ndarray
    errors_px: np.ndarray
    correlation: float


def solve_pose_sun_shift(intrinsics: Intrinsics, start: Pose, xyz: np.ndarray,
                         uv: np.ndarray, dirs: np.ndarray, *, threshold_px: float = 6.0,
                         loss_scale_px: float = 1.5, b0: float = 0.0,
                         fix_b: float | None = None, rounds: int = 2) -> SunShiftFit:
    """Pose and ``b`` by robust least squares: ``uv ≈ project(pose, xyz + b dirs)``.

    Starts from ``start`` (a RANSAC pose); the inliers are the points within
    ``threshold_px`` of the fit, re-selected ``rounds`` times. ``fix_b``: hold
    ``b`` at that value (the pose alone, for comparison).
    """
    xyz = np.asarray(xyz, np.float64)
    uv = np.asarray(uv, np.float64)
    dirs = np.asarray(dirs, np.float64)
    centre = xyz.mean(axis=0)
    q = xyz - centre
    K, dist = intrinsics.K, intrinsics.dist_coeffs
    # Centred frame: X_cam = R (X - c) + (t + R c).
    rvec0 = start.rvec
    tvec0 = start.t + start.R @ centre
    free_b = fix_b is None

    def project(x: np.ndarray, pts: np.ndarray, d: np.ndarray) -> np.ndarray:
        b = x[6] if free_b else fix_b
        p, _ = cv2.projectPoints(pts + b * d, x[:3], x[3:6], K, dist)
        return p.reshape(-1, 2)

    x = np.concatenate([rvec0, tvec0, [b0 if free_b else 0.0]])
    if not free_b:
        x = x[:6]
    inl = reprojection_errors(intrinsics, start, xyz + (b0 if free_b else fix_b) * dirs, uv) \
        < threshold_px
    res = None
    for _ in range(max(1, rounds)):
        if inl.sum() < 8:
            break
        qi, ui, di = q[inl], uv[inl], dirs[inl]
        res = least_squares(lambda v: (project(v, qi, di) - ui).ravel(), x, loss="soft_l1",
                            f_scale=loss_scale_px, method="trf", x_scale="jac")
        x = res.x
        err = np.linalg.norm(project(x, q, dirs) - uv, axis=1)
        inl = err < threshold_px
    R, _ = cv2.Rodrigues(x[:3])
    pose = Pose(R, x[3:6] - R @ centre)
    b = float(x[6]) if free_b else float(fix_b)
    err = reprojection_errors(intrinsics, pose, xyz + b * dirs, uv)
    b_sigma, corr = float("nan"), float("nan")
    if res is not None and free_b:
        J = res.jac
        try:
            r = res.fun
            dof = max(1, len(r) - len(x))
            s2 = float(r @ r) / dof
            info = J.T @ J
            cov = np.linalg.inv(info) * s2
            b_sigma = float(math.sqrt(max(cov[6, 6], 0.0)))
            # Multiple correlation of b with the six pose parameters:
            # R² = 1 - 1 / (C_bb (C⁻¹)_bb).
            corr = float(math.sqrt(max(0.0, 1.0 - 1.0 / (cov[6, 6] * info[6, 6] / s2))))
        except np.linalg.LinAlgError:
            pass
    return SunShiftFit(pose, b, b_sigma, err < threshold_px, err, corr)


def sun_shift_round(matched: R.MatchedRound, source, params, sun: np.ndarray,
                    mode: str) -> R.Round:
    """:func:`~napari_imgreg.registration.round.pose_round` with the nuisance:
    RANSAC EPnP, then the pose and ``b`` refined together on its inliers. The
    round's metrics get ``sun_shift_m``, ``sun_shift_sigma_m`` and
    ``sun_shift_confounding`` (:attr:`SunShiftFit.correlation`)."""
    rnd = R.pose_round(matched, source.intrinsics, params.pose, None, source.timings,
                       rng_seed=int(params.seed))
    if not rnd.estimate.ok:
        return rnd
    t0 = perf_counter()
    m = matched
    rr = m.rendered
    scale = rr.shape[1] / source.intrinsics.width
    nrm = block_normals(rr.normal, rr.mask, params.area.template_px)
    ij = np.clip(np.round(pixels_to_scaled(m.render_points[m.lifted], scale)).astype(int),
                 0, [rr.shape[1] - 1, rr.shape[0] - 1])
    dirs = sun_shift_directions(nrm[ij[:, 1], ij[:, 0]], sun, mode)
    xyz, uv = m.xyz[m.lifted], m.photo_points[m.lifted]
    fit = solve_pose_sun_shift(source.intrinsics, rnd.estimate.pose, xyz, uv, dirs,
                               threshold_px=params.pose.reprojection_error_px)
    source.timings["pose"] += perf_counter() - t0
    if fit.inliers.sum() < 4:
        return rnd
    estimate = PoseEstimate(True, fit.pose, fit.inliers, fit.errors_px, solver="epnp+sun")
    metrics, pose_inlier = R.round_metrics(m.points_photo, m.points_render, m.feature_inlier,
                                           m.lifted, estimate, m.rendered)
    metrics.update(m.extra_metrics)
    metrics["sun_shift_m"] = round(fit.b, 4)
    metrics["sun_shift_sigma_m"] = round(fit.b_sigma, 4) if math.isfinite(fit.b_sigma) else None
    metrics["sun_shift_confounding"] = (round(fit.correlation, 4)
                                        if math.isfinite(fit.correlation) else None)
    corr = R.Correspondences(m.photo_points, m.render_points, m.feature_inlier, m.lifted,
                             pose_inlier, m.xyz)
    return R.Round(estimate, metrics, corr, m.rendered)


@contextlib.contextmanager
def patched(model: str):
    """The pipeline's rounds with the nuisance (``model`` "tangent" or "shadow";
    "off": unchanged) on area rounds matched on a render relit for the
    photo's sun. The error estimate still sees the shifted matches as they
    are (it does not know ``b``)."""
    if model == "off":
        yield
        return
    original = P.score_round

    def score_round(source, pose, params, width, *, matcher="keypoints", near=False,
                    search_px=None, mode="plain", solve=True):
        sun = getattr(source, "sun", None)
        if not (matcher == "area" and solve and mode == "sunlit" and sun is not None):
            return original(source, pose, params, width, matcher=matcher, near=near,
                            search_px=search_px, mode=mode, solve=solve)
        cv2.setRNGSeed(int(params.seed))
        matched = R.match_round(source, pose, params, width, matcher=matcher, near=near,
                                search_px=search_px, mode=mode)
        if not (matched.rendered.shading_share or 0.0) > 0.0:
            return R.pose_round(matched, source.intrinsics, params.pose, None, source.timings,
                                rng_seed=int(params.seed))
        return sun_shift_round(matched, source, params, sun, model)

    P.score_round = score_round
    try:
        yield
    finally:
        P.score_round = original
