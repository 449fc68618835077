"""Dense pose refinement by mutual information between the photo and the model.

Feature matching leaves a pose good to a few pixels; this module polishes it
(and helps verify it) by maximising the *mutual information* (MI) between the
photo's intensities and attributes of the model seen from the pose — the idea
of Corsini et al. (2009, MeshLab): MI only asks that one image be *predictable*
from the other, not that they look alike, so it tolerates other light, other
exposure and a gamma curve, and it can use model attributes that are not
colours at all (surface-normal direction, Lambert shading), which is what lets
it register photos of the shape to untextured meshes. Several attributes
("modes") are compared at once and their MI summed.

How it is made fast
    A render is cast once per pyramid level (and again only when the pose has
    moved enough that what is visible may change), at twice the level's
    resolution and low-passed, so texture detail does not alias. Every
    sampled pixel keeps its exact 3D point (``RenderResult.xyz``; pixels that
    see nothing become points at infinity along their ray, so the skyline
    counts) and its labels (binned local contrast of the model colour,
    normal-direction class, ...). A candidate pose then costs no ray casting:
    the samples are projected into the (blurred, downscaled) photo, which is
    sampled there bilinearly, and the joint histogram of (label, photo value),
    counted with ``np.bincount``, gives the MI.

How it converges
    The photo axis of the joint histogram uses a quadratic B-spline Parzen
    window, so the MI is differentiable in the photo values; with the photo's
    gradients and the projection's Jacobian that gives the MI's gradient and
    an approximate Hessian analytically (the second-order MI optimisation of
    Dame & Marchand, written from the equations). Steps solve that quadratic
    model inside a trust region measured in pixels of image motion
    (Levenberg–Marquardt damping with the pixel metric), so rotation,
    position and focal length share one scale. A handful of steps per level,
    coarse to fine.

Parameters of a step: a rotation vector ω applied in the camera frame and an
offset δ of the camera centre along the camera's own axes (x/y sideways, z
along the view), optionally a relative focal change φ::

    R' = exp(ω) R,   C' = C + Rᵀ δ,   f' = f (1 + φ)

Reach: the start must put every part of the scene within a few pixels of its
place at the coarsest level (128 px wide by default). A position error moves
near ground far more than the cliff behind it: with ground 4 m from the camera,
0.25 m is recovered but 1 m is not (the far surface aligns, the turn
compensates the shift, and the near ground stays off by ~100 px at full size).

Scores are in bits.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable, ClassVar, Sequence

import cv2
import numpy as np

from ...camera import Intrinsics, Pose, match_scale
from ...validate import StageParams
from ..filters import masked_gaussian
from .pyramid import (
    PyramidLevel,
    RenderFn,
    as_render_fn,
    bilinear_taps,
    check_ranges,
    level_widths,
    scene_renderer,
    with_keywords,
)
from ...render import RenderResult, _light_direction
from ...scene import Scene, has_appearance

__all__ = [
    "DENSE_MODES",
    "DenseParams",
    "DenseLevel",
    "DenseResult",
    "mutual_information",
    "entropy",
    "mi_score",
    "mi_scores",
    "refine_pose_mi",
]

#: Model attributes that can be compared with the photo:
#: ``color`` luminance of the model's colour (or of ``render_fn``'s image);
#: ``shaded`` Lambert shading under ``light_direction``;
#: ``normal`` the class of the world-frame surface normal among fixed
#: directions — any lighting that is a function of the normal is learnt by MI;
#: ``normal_z`` the normal's vertical component (ground vs rock face);
#: ``detail`` the local contrast of the model's colour (minus its local mean,
#: over its local spread) against the photo's: broad shading, exposure and
#: haze, which differ most under other light, are gone from both;
#: ``depth_edges`` occluding contours (depth jumps), compared with the
#: photo's gradient magnitude rather than its intensity.
DENSE_MODES = ("color", "shaded", "normal", "normal_z", "detail", "depth_edges")

# The photo channel each mode is compared with.
_PHOTO_CHANNEL = {"color": "lum", "shaded": "lum", "normal": "lum", "normal_z": "lum",
                  "detail": "detail", "depth_edges": "grad"}
# Width of the local-contrast window of ``detail``, level pixels.
_DETAIL_PX = 4.0

# Samples whose ray misses the model sit this far along their ray: at
# infinity for any practical camera move, so only rotation moves them.
_FAR_M = 1.0e6
# Directions (on a sphere) that define the "normal" classes.
_N_NORMAL_CLASSES = 64
# A level with fewer hit pixels than this cannot support a 6-DoF fit.
_MIN_HITS = 400
_LN2 = math.log(2.0)


# --------------------------------------------------------------------------
# Plain MI of two images
# --------------------------------------------------------------------------
def _bin_values(
    values: np.ndarray, bins: int, binning: str, value_range: tuple[float, float] | None
) -> np.ndarray:
    """Integer bins 0..bins-1 of finite values (uniform or equal-population)."""
    v = values.astype(np.float64, copy=False)
    if binning == "quantile":
        # Equal-population bins: invariant to any increasing remap of values.
        edges = np.quantile(v, np.linspace(0.0, 1.0, bins + 1)[1:-1])
        return np.searchsorted(edges, v, side="right").astype(np.intp)
    if binning != "uniform":
        raise ValueError(f"binning must be 'uniform' or 'quantile', not {binning!r}")
    lo, hi = (float(v.min()), float(v.max())) if value_range is None else value_range
    if hi <= lo:
        return np.zeros(v.shape, np.intp)
    idx = np.floor((v - lo) * (bins / (hi - lo))).astype(np.intp)
    return np.clip(idx, 0, bins - 1)


def _entropy_bits(p: np.ndarray) -> float:
    p = p[p > 0]
    return float(-(p * np.log(p)).sum() / _LN2)


def entropy(
    a: np.ndarray,
    mask: np.ndarray | None = None,
    bins: int = 32,
    binning: str = "uniform",
) -> float:
    """Shannon entropy of an image's binned values, bits.

    Parameters
    ----------
    a : array
        Values (any shape); non-finite values are ignored.
    mask : bool array, optional
        Same shape as ``a``; only True elements count.
    bins : int
        Number of bins.
    binning : {"uniform", "quantile"}
        See :func:`mutual_information`.
    """
    v = np.asarray(a).ravel()
    keep = np.isfinite(v)
    if mask is not None:
        keep &= np.asarray(mask, bool).ravel()
    if not keep.any():
        return 0.0
    idx = _bin_values(v[keep], bins, binning, None)
    return _entropy_bits(np.bincount(idx, minlength=bins) / keep.sum())


def mutual_information(
    a: np.ndarray,
    b: np.ndarray,
    mask: np.ndarray | None = None,
    bins: int = 32,
    *,
    normalized: bool = False,
    binning: str = "uniform",
    smoothing: float = 0.0,
    range_a: tuple[float, float] | None = None,
    range_b: tuple[float, float] | None = None,
) -> float:
    """Mutual information of two images (or any two equally shaped arrays).

    The joint histogram is counted with one ``np.bincount`` over combined bin
    indices (an order of magnitude faster than ``np.histogram2d``).

    Parameters
    ----------
    a, b : arrays of the same shape
        Values, e.g. (H, W) intensities; elements where either is not finite
        are ignored.
    mask : bool array, optional
        Same shape; only True elements count.
    bins : int
        Bins per variable.
    normalized : bool
        Return Studholme's normalised MI ``(H(A) + H(B)) / H(A, B)``, which is
        1 for independent and 2 for identical (bijectively related) images and
        depends less on the overlap than MI does.
    binning : {"uniform", "quantile"}
        ``uniform``: equal-width bins over the value range; ``quantile``:
        equal-population bins, which makes the result exactly invariant to any
        increasing remap of either image (gamma, exposure, contrast).
    smoothing : float
        Standard deviation (bins) of a Gaussian smoothing of the joint
        histogram — a Parzen-window estimate; smoother in the alignment, at
        the price of a small downward bias. 0 for the plain histogram.
    range_a, range_b : (lo, hi), optional
        Value ranges for ``uniform`` binning (default: each array's min, max).

    Returns
    -------
    float
        MI in bits (or the dimensionless normalised MI); 0 (1 normalised) when
        nothing is left to compare.
    """
    a = np.asarray(a)
    b = np.asarray(b)
    if a.shape != b.shape:
        raise ValueError(f"a and b must have the same shape, not {a.shape} and {b.shape}")
    va, vb = a.ravel(), b.ravel()
    keep = np.isfinite(va) & np.isfinite(vb)
    if mask is not None:
        keep &= np.asarray(mask, bool).ravel()
    if keep.sum() < 2:
        return 1.0 if normalized else 0.0
    ia = _bin_values(va[keep], bins, binning, range_a)
    ib = _bin_values(vb[keep], bins, binning, range_b)
    joint = np.bincount(ia * bins + ib, minlength=bins * bins).reshape(bins, bins)
    joint = joint.astype(np.float64)
    if smoothing > 0:
        joint = cv2.GaussianBlur(joint, (0, 0), smoothing, borderType=cv2.BORDER_CONSTANT)
    return _mi_from_joint(joint / joint.sum(), normalized)


def _mi_from_joint(p: np.ndarray, normalized: bool) -> float:
    """MI (bits) or normalised MI of a joint distribution (rows: A, cols: B)."""
    h_a = _entropy_bits(p.sum(axis=1))
    h_b = _entropy_bits(p.sum(axis=0))
    h_ab = _entropy_bits(p.ravel())
    if normalized:
        return (h_a + h_b) / h_ab if h_ab > 0 else 1.0
    return max(0.0, h_a + h_b - h_ab)


# --------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------
@dataclass
class DenseLevel:
    """What happened at one pyramid level.

    Attributes
    ----------
    width : int
        Photo (and render) width at this level, pixels.
    mi_start, mi_end : float
        Objective (sum over modes of MI, bits) when the level started / ended.
    iterations : int
        Accepted and rejected steps.
    renders : int
        Ray-cast renders made at this level.
    n_samples : int
        Samples (rendered pixels) used.
    step_px : float
        Size of the last step, pixels at this level.
    seconds : float
    pose : Pose or None
        The pose when the level ended.
    """

    width: int
    mi_start: float
    mi_end: float
    iterations: int
    renders: int
    n_samples: int
    step_px: float
    seconds: float
    pose: Pose | None = None

    def to_dict(self) -> dict:
        return {k: (round(v, 5) if isinstance(v, float) else v)
                for k, v in self.__dict__.items() if k != "pose"}


@dataclass
class DenseResult:
    """The outcome of :func:`refine_pose_mi`.

    Attributes
    ----------
    pose : Pose
        Refined ``cam_from_world`` (the start pose when nothing improved).
    intrinsics : Intrinsics
        The camera; its focal length refined when ``optimize_focal``.
    score : float
        Objective at the end (sum over modes of MI, bits) at the finest level.
    score_start : float
        The same objective at the start pose (same samples, same level).
    nmi : float
        Mean normalised MI ``(H(A)+H(B))/H(A,B)`` over modes at the end, in
        [1, 2] (the sample scenes: ≈ 1.05–1.14 at the true pose, depending on
        the light; ≈ 1.03–1.05 two degrees or five metres off).
    sharpness : float
        How peaked the MI is at the returned pose (see :func:`mi_scores`):
        0.17–0.7 at right poses, below 0.03 at poses 2° or 5 m off on the
        sample scenes; blind to position errors only near ground reveals.
    history : list of DenseLevel
    n_evaluations : int
        Objective evaluations (each a projection and a histogram, no render).
    n_renders : int
    seconds : float
    converged : bool
        The finest level ended with a step below the tolerance.
    reason : str
        Empty on success, else why the refinement stopped or failed.
    modes : tuple of str
        The model attributes used.
    """

    pose: Pose
    intrinsics: Intrinsics
    score: float
    score_start: float
    nmi: float
    sharpness: float
    history: list[DenseLevel] = field(default_factory=list)
    n_evaluations: int = 0
    n_renders: int = 0
    seconds: float = 0.0
    converged: bool = False
    reason: str = ""
    modes: tuple[str, ...] = ()

    @property
    def improved(self) -> bool:
        return self.score > self.score_start

    def to_dict(self) -> dict:
        return {
            "pose": self.pose.to_dict(),
            "camera": self.intrinsics.to_dict(),
            "score": round(self.score, 5),
            "score_start": round(self.score_start, 5),
            "nmi": round(self.nmi, 5),
            "sharpness": round(self.sharpness, 5),
            "history": [lv.to_dict() for lv in self.history],
            "n_evaluations": self.n_evaluations,
            "n_renders": self.n_renders,
            "seconds": round(self.seconds, 3),
            "converged": self.converged,
            "reason": self.reason,
            "modes": list(self.modes),
        }


# --------------------------------------------------------------------------
# The photo side: a pyramid level ready for sampling
# --------------------------------------------------------------------------
def _luminance(rgb: np.ndarray) -> np.ndarray:
    """(H, W) float32 luminance of an (H, W, 3) or (H, W) image."""
    img = np.asarray(rgb)
    if img.ndim == 2:
        return img.astype(np.float32)
    img = img[..., :3].astype(np.float32)
    return img[..., 0] * 0.299 + img[..., 1] * 0.587 + img[..., 2] * 0.114


@dataclass
class _PhotoLevel:
    """The photo at one level, ready for bilinear sampling.

    ``channels`` maps a photo channel name (see :data:`_PHOTO_CHANNEL`) to
    three flat float32 arrays of length H * W: the value in bin units
    [0, bins - 1] (after histogram equalisation) and its x and y derivatives
    (bins per pixel).
    """

    channels: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]
    shape: tuple[int, int]
    bins: int


def _equalized(img: np.ndarray, bins: int) -> np.ndarray:
    """Map values through their (smoothed) CDF onto [0, bins - 1].

    Equalising spreads the photo evenly over the bins whatever its exposure
    and gamma, and keeps it continuous (the Parzen window needs gradients).
    """
    lo, hi = np.percentile(img, [0.2, 99.8])
    if hi <= lo:
        return np.zeros_like(img, dtype=np.float32)
    grid = np.linspace(lo, hi, 257)
    hist, _ = np.histogram(np.clip(img, lo, hi), bins=256, range=(lo, hi))
    # A floor keeps the map strictly increasing (no flat steps, no zero gradient).
    cdf = np.concatenate([[0.0], np.cumsum(hist + 0.02 * hist.mean())])
    cdf = cdf / cdf[-1] * (bins - 1)
    return np.interp(img, grid, cdf).astype(np.float32)


def _local_contrast(img: np.ndarray, mask: np.ndarray | None, sigma: float) -> np.ndarray:
    """Detail of an image: minus its local mean, over its local spread.

    Removes what differs most between a photo and a render under other light
    (broad shading, exposure, haze) and keeps the texture both share.
    """
    if mask is None:
        mean = cv2.GaussianBlur(img, (0, 0), sigma)
        detail = img - mean
        spread = np.sqrt(cv2.GaussianBlur(detail * detail, (0, 0), sigma))
    else:
        mean = masked_gaussian(img, mask, sigma, reduce_wide=False)
        detail = np.where(mask, img - mean, 0).astype(np.float32)
        spread = np.sqrt(masked_gaussian(detail * detail, mask, sigma, reduce_wide=False))
    return detail / (spread + 1e-3 * float(np.abs(img).max() + 1.0))


def _photo_level(
    level: PyramidLevel, photo_lum: np.ndarray, bins: int, blur_px: float,
    channels: set[str], detail_px: float,
) -> _PhotoLevel:
    img = level.resize(photo_lum)
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    out = {}
    if "lum" in channels:
        out["lum"] = _with_gradients(_equalized(img, bins))
    if "detail" in channels:
        out["detail"] = _with_gradients(_equalized(_local_contrast(img, None, detail_px), bins))
    if "grad" in channels:
        gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
        gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
        mag = cv2.GaussianBlur(np.sqrt(gx * gx + gy * gy), (0, 0), max(blur_px, 0.7))
        out["grad"] = _with_gradients(_equalized(mag, bins))
    return _PhotoLevel(out, (level.height, level.width), bins)


def _with_gradients(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    # Central differences: the derivative of the bilinear interpolant on average.
    gx = cv2.Sobel(t, cv2.CV_32F, 1, 0, ksize=1, scale=0.5)
    gy = cv2.Sobel(t, cv2.CV_32F, 0, 1, ksize=1, scale=0.5)
    return t.ravel(), gx.ravel(), gy.ravel()


# --------------------------------------------------------------------------
# The model side: samples from a render
# --------------------------------------------------------------------------
@dataclass
class _Samples:
    """Rendered pixels as 3D points with their labels, one per mode.

    Attributes
    ----------
    points : (3, N) float64
        World points (coordinates in rows); misses are at ``_FAR_M`` along
        their ray.
    labels : list of (N,) intp arrays
        Render bin of every sample per mode (0 is "no surface").
    n_labels : list of int
    photo_channel : list of str
        The photo channel each mode is compared with (:data:`_PHOTO_CHANNEL`).
    n_hits : int
        Samples on the surface.
    """

    points: np.ndarray
    labels: list[np.ndarray]
    n_labels: list[int]
    photo_channel: list[str]
    n_hits: int

    def only(self, k: int) -> _Samples:
        """The samples with mode ``k`` alone."""
        return _Samples(self.points, [self.labels[k]], [self.n_labels[k]], [self.photo_channel[k]],
                        self.n_hits)


def _fibonacci_sphere(n: int) -> np.ndarray:
    """``n`` nearly evenly spread unit vectors, (n, 3)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


_NORMAL_DIRS = _fibonacci_sphere(_N_NORMAL_CLASSES).astype(np.float32)


def _quantile_labels(values: np.ndarray, n_bins: int) -> np.ndarray:
    """Labels 1..n_bins-1 by equal-population bins of ``values`` (1-D)."""
    if values.size == 0:
        return np.zeros(0, np.intp)
    edges = np.quantile(values, np.linspace(0.0, 1.0, n_bins)[1:-1])
    return 1 + np.searchsorted(edges, values, side="right")


def _samples_from_render(
    rr: RenderResult,
    modes: Sequence[str],
    bins: int,
    stride: int,
    blur_px: float,
    light_direction: np.ndarray | None,
    use_background: bool,
    max_samples: int,
) -> _Samples:
    """Samples every ``stride``-th pixel of a render made ``stride`` times finer.

    Values are low-passed with a Gaussian of ``blur_px`` *level* pixels
    (``stride * blur_px`` render pixels) before they are picked: a point
    sample of a detailed texture is otherwise aliased noise that the
    area-averaged photo level does not contain. Each sample keeps the exact
    3D point of its render pixel, so there is no offset to bias the pose.
    """
    h, w = rr.shape
    hit = rr.mask
    pose = rr.cam_from_world
    sigma = blur_px * stride
    off = stride // 2
    rows = np.arange(off, h, stride)
    cols = np.arange(off, w, stride)
    pick = (rows[:, None] * w + cols[None, :]).ravel()
    hit_s = hit.ravel()[pick]
    keep = np.ones_like(hit_s) if use_background else hit_s
    pick, hit_s = pick[keep], hit_s[keep]
    if pick.size > max_samples:
        # A fixed random subset: deterministic, and no regular pattern.
        sub = np.sort(np.random.default_rng(0).choice(pick.size, max_samples, replace=False))
        pick, hit_s = pick[sub], hit_s[sub]
    on = pick[hit_s]  # render pixels of samples on the surface

    def picked(img: np.ndarray) -> np.ndarray:
        """Values of an (H, W[, C]) image at the surface samples, (n[, C])."""
        flat = img.reshape(h * w, -1)[on]
        return flat[:, 0] if img.ndim == 2 else flat

    labels: list[np.ndarray] = []
    n_labels: list[int] = []
    normals = None
    for mode in modes:
        lab = np.zeros(pick.size, np.intp)
        n_lab = bins
        if mode in ("shaded", "normal", "normal_z") and normals is None:
            normals = picked(masked_gaussian(rr.normal, hit, sigma, reduce_wide=False))
            normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-6)
        if mode == "color":
            lum = masked_gaussian(_luminance(rr.rgb), hit, sigma, reduce_wide=False)
            lab[hit_s] = _quantile_labels(picked(lum), bins)
        elif mode == "detail":
            lum = masked_gaussian(_luminance(rr.rgb), hit, sigma, reduce_wide=False)
            lab[hit_s] = _quantile_labels(picked(_local_contrast(lum, hit, _DETAIL_PX * stride)),
                                          bins)
        elif mode == "shaded":
            light = _light_direction(pose.R) if light_direction is None else light_direction
            light = np.asarray(light, np.float32) / np.linalg.norm(light)
            lab[hit_s] = _quantile_labels(np.clip(normals @ light, 0.0, None), bins)
        elif mode == "normal":
            lab[hit_s] = 1 + np.argmax(normals @ _NORMAL_DIRS.T, axis=1)
            n_lab = _N_NORMAL_CLASSES + 1
        elif mode == "normal_z":
            lab[hit_s] = _quantile_labels(normals[:, 2], bins)
        elif mode == "depth_edges":
            lab = _quantile_labels(_depth_edges(rr.depth, hit, sigma).ravel()[pick], bins) - 1
        else:
            raise ValueError(f"unknown mode {mode!r}; choose from {DENSE_MODES}")
        labels.append(lab)
        n_labels.append(n_lab)

    points = np.empty((3, pick.size))
    points[:, hit_s] = rr.xyz.reshape(-1, 3)[on].T
    if not hit_s.all():
        r, c = np.divmod(pick[~hit_s], w)
        _, dirs = pose.rays(rr.intrinsics, np.stack([c, r], axis=1).astype(np.float64))
        points[:, ~hit_s] = (pose.center + _FAR_M * dirs).T
    return _Samples(points, labels, n_labels, [_PHOTO_CHANNEL[m] for m in modes],
                    int(hit_s.sum()))


def _depth_edges(depth: np.ndarray, hit: np.ndarray, sigma: float) -> np.ndarray:
    """Strength of depth discontinuities (log-depth gradient), the skyline included."""
    far = float(np.nanmax(depth)) * 4.0 if hit.any() else 1.0
    log_d = np.log(np.where(hit, depth, far)).astype(np.float32)
    gx = cv2.Sobel(log_d, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(log_d, cv2.CV_32F, 0, 1, ksize=3)
    return cv2.GaussianBlur(np.sqrt(gx * gx + gy * gy), (0, 0), max(sigma, 0.7))


# --------------------------------------------------------------------------
# The objective and its derivatives
# --------------------------------------------------------------------------
@dataclass
class _Eval:
    value: float  # sum over modes of MI, bits
    nmi: float  # mean normalised MI over modes
    n_valid: int
    grad: np.ndarray | None = None  # (P,)
    hess: np.ndarray | None = None  # (P, P), negative definite near a maximum
    pixel_metric: np.ndarray | None = None  # (P, P): mean squared pixel motion per step


def _project(points: np.ndarray, pose: Pose, intr: Intrinsics) -> tuple[np.ndarray, ...]:
    """Camera-frame coordinates (3, N) and pixels u, v (N,) of world points (3, N)."""
    pc = pose.R @ points + pose.t[:, None]
    if intr.has_distortion:
        uv = intr.project(pc.T)
        return pc, uv[:, 0], uv[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = np.where(pc[2] > 0, 1.0 / pc[2], np.nan)
    return pc, intr.fx * pc[0] * inv_z + intr.cx, intr.fy * pc[1] * inv_z + intr.cy


def _projection_jacobian(pc: np.ndarray, u: np.ndarray, v: np.ndarray,
                         intr_level: Intrinsics, n_params: int) -> tuple[np.ndarray, np.ndarray]:
    """d(u, v) / d(ω, δ[, φ]) at camera-frame points (3, N): two (P, N) arrays.

    Undistorted pinhole: distortion changes the Jacobian by a few per cent
    only, and the objective itself is evaluated with the exact camera model.
    """
    n = pc.shape[1]
    # float32: these arrays dominate the memory traffic of a step.
    inv_z = (1.0 / pc[2]).astype(np.float32)
    xb, yb = pc[0].astype(np.float32) * inv_z, pc[1].astype(np.float32) * inv_z
    fx, fy = np.float32(intr_level.fx), np.float32(intr_level.fy)
    du = np.zeros((n_params, n), np.float32)
    dv = np.zeros((n_params, n), np.float32)
    xy = xb * yb
    du[0] = -fx * xy
    du[1] = fx * (1 + xb * xb)
    du[2] = -fx * yb
    du[3] = -fx * inv_z
    du[5] = fx * xb * inv_z
    dv[0] = -fy * (1 + yb * yb)
    dv[1] = fy * xy
    dv[2] = fy * xb
    dv[4] = -fy * inv_z
    dv[5] = fy * yb * inv_z
    if n_params == 7:
        du[6] = u - intr_level.cx
        dv[6] = v - intr_level.cy
    return du, dv


def _evaluate(
    samples: _Samples,
    photo: _PhotoLevel,
    pose: Pose,
    intr_level: Intrinsics,
    n_params: int,
    derivatives: bool,
    curvature: bool = True,
    margin_px: float = 2.0,
) -> _Eval:
    """Objective (and derivatives w.r.t. the step parameters) at a pose.

    Samples fade out over ``margin_px`` at the photo's border: a sample that
    simply dropped out when it crossed the border would make the objective
    jump (by hundredths of a bit when it is a row of sky).
    """
    pc, u, v = _project(samples.points, pose, intr_level)
    h, w = photo.shape
    with np.errstate(invalid="ignore"):
        border = np.minimum(np.minimum(u, w - 1 - u), np.minimum(v, h - 1 - v))
        valid = border > 0  # NaN compares False
    n_valid = int(valid.sum())
    if n_valid < _MIN_HITS:
        return _Eval(-math.inf, 1.0, n_valid)
    u, v = u[valid], v[valid]
    weight = np.minimum(border[valid] / margin_px, 1.0)
    jac = (_projection_jacobian(pc[:, valid], u, v, intr_level, n_params)
           if derivatives else None)

    total, nmi_sum = 0.0, 0.0
    grad = np.zeros(n_params) if derivatives else None
    hess = np.zeros((n_params, n_params)) if derivatives else None
    n_eff = float(weight.sum())
    for channel in sorted(set(samples.photo_channel)):
        planes = photo.channels[channel]
        t_idx, wts, dwts, dt = _parzen_terms(planes, photo.shape, u, v, photo.bins, jac, weight)
        # Per-sample first and second derivatives of the MI w.r.t. the photo
        # value, summed over the modes that share these photo values.
        g_sum = np.zeros(n_valid) if derivatives else None
        s_sum = np.zeros(n_valid) if derivatives else None
        for labels_all, n_lab, mode_channel in zip(samples.labels, samples.n_labels,
                                                   samples.photo_channel):
            if mode_channel != channel:
                continue
            mi, nmi, g_i, s_i, h_hist = _mi_and_derivatives(
                labels_all[valid], n_lab, photo.bins, t_idx, wts, dwts, weight, n_eff,
                dt if (derivatives and curvature) else None, derivatives)
            total += mi
            nmi_sum += nmi
            if derivatives:
                g_sum += g_i
                s_sum += s_i
                if h_hist is not None:
                    hess += h_hist
        if derivatives:
            grad += dt @ (g_sum * weight).astype(np.float32) / (n_eff * _LN2)
            hess += (dt * (s_sum * weight).astype(np.float32)) @ dt.T / (n_eff * _LN2)
    out = _Eval(total, nmi_sum / len(samples.labels), n_valid, grad, hess)
    if derivatives:
        # Only measures step sizes: a subset of the samples is plenty.
        du, dv = (j[:, :: max(1, n_valid // 20000)].astype(np.float64) for j in jac)
        out.pixel_metric = (du @ du.T + dv @ dv.T) / du.shape[1]
    return out


def _parzen_terms(planes, shape, u, v, bins, jac, weight):
    """Photo values at the samples as quadratic-B-spline Parzen weights.

    Returns the left bin of each sample's 3-bin support (in a histogram
    padded by one bin each side), the three weights times the sample weight,
    the three weights' derivatives with respect to the value, and the
    value's derivative with respect to the step parameters (P, N) (None
    without ``jac``).
    """
    # One set of taps for the value and its two derivatives; float32 weights
    # as the planes (these gathers dominate a step's memory traffic).
    taps = bilinear_taps(u, v, shape, dtype=np.float32)
    sampled = [taps.sample(p) for p in (planes if jac is not None else planes[:1])]
    t = sampled[0].astype(np.float64)
    inside = (t > 0) & (t < bins - 1)
    t = np.clip(t, 0, bins - 1)
    c = np.floor(t + 0.5)
    d = t - c  # in [-0.5, 0.5]
    wts = (0.5 * (0.5 - d) ** 2 * weight, (0.75 - d * d) * weight, 0.5 * (0.5 + d) ** 2 * weight)
    dwts = (d - 0.5, -2.0 * d, d + 0.5)
    dt = None
    if jac is not None:
        du, dv = jac
        gx = np.where(inside, sampled[1], np.float32(0))
        gy = np.where(inside, sampled[2], np.float32(0))
        dt = du * gx
        dt += dv * gy
    return c.astype(np.intp), wts, dwts, dt


def _mi_and_derivatives(labels, n_lab, bins, t_idx, wts, dwts, weight, n_eff, dt, derivatives):
    """MI (bits) and NMI of one mode, with per-sample derivatives.

    With ``P`` the joint distribution of (render label r, photo bin b) and
    ``L = log P(r, b) / P(b)``, the MI's derivative is ``Σ dP · L`` (the
    marginal of r does not move) and its second derivative is
    ``Σ d²P · L + Σ dP dPᵀ / P(r, b) - Σ dP(b) dP(b)ᵀ / P(b)`` (image second
    derivatives dropped). The first two are sums over samples of the Parzen
    window's slope and curvature against ``L``: returned per sample (``g_i``,
    ``s_i``, nats, before the sample weight) for the caller to contract with
    the value's Jacobian. The histogram term (bits, (P, P)) is computed only
    when ``dt`` is given.
    """
    width = bins + 2
    base = labels * width + t_idx
    size = n_lab * width
    joint = (np.bincount(base, wts[0], size) + np.bincount(base + 1, wts[1], size)
             + np.bincount(base + 2, wts[2], size))
    P = joint.reshape(n_lab, width) / n_eff
    p_r = P.sum(axis=1)
    p_b = P.sum(axis=0)
    h_r, h_b, h_rb = _entropy_bits(p_r), _entropy_bits(p_b), _entropy_bits(P.ravel())
    mi = max(0.0, h_r + h_b - h_rb)
    nmi = (h_r + h_b) / h_rb if h_rb > 0 else 1.0
    if not derivatives:
        return mi, nmi, None, None, None

    tiny = 1e-12
    L = np.log((P + tiny) / (p_b + tiny)).ravel()
    L0, L1, L2 = np.take(L, base), np.take(L, base + 1), np.take(L, base + 2)
    g_i = dwts[0] * L0 + dwts[1] * L1 + dwts[2] * L2
    s_i = L0 - 2.0 * L1 + L2
    hess_hist = None
    if dt is not None:
        n_params = dt.shape[0]
        dP = np.empty((size, n_params))
        dw = [dwts[k] * weight for k in range(3)]
        for j in range(n_params):
            col = dt[j]
            dP[:, j] = (np.bincount(base, dw[0] * col, size)
                        + np.bincount(base + 1, dw[1] * col, size)
                        + np.bincount(base + 2, dw[2] * col, size))
        dP /= n_eff
        occupied = P.ravel() > tiny
        dPo = dP[occupied]
        hess_hist = dPo.T @ (dPo / P.ravel()[occupied][:, None])
        dPb = dP.reshape(n_lab, width, n_params).sum(axis=0)
        ob = p_b > tiny
        hess_hist -= dPb[ob].T @ (dPb[ob] / p_b[ob][:, None])
        hess_hist /= _LN2
    return mi, nmi, g_i, s_i, hess_hist


# --------------------------------------------------------------------------
# Pose steps
# --------------------------------------------------------------------------
def _apply_step(pose: Pose, intr: Intrinsics, step: np.ndarray) -> tuple[Pose, Intrinsics]:
    """``R' = exp(ω) R``, ``C' = C + Rᵀ δ``, ``f' = f (1 + φ)``."""
    dR, _ = cv2.Rodrigues(np.asarray(step[:3], np.float64).reshape(3, 1))
    center = pose.center + pose.R.T @ step[3:6]
    new_pose = Pose.from_center(dR @ pose.R, center)
    if step.size > 6:
        k = 1.0 + float(step[6])
        intr = replace(intr, fx=intr.fx * k, fy=intr.fy * k)
    return new_pose, intr


def _positive_definite(hess: np.ndarray) -> np.ndarray:
    """``-H`` made positive definite (eigenvalues mirrored and floored).

    Far from the peak the approximate Hessian is not negative definite; the
    mirrored model still points uphill and the trust region bounds the step.
    """
    A = -0.5 * (hess + hess.T)
    vals, vecs = np.linalg.eigh(A)
    vals = np.abs(vals)
    vals = np.maximum(vals, vals.max() * 1e-9 + 1e-30)
    return (vecs * vals) @ vecs.T


def _trust_step(A: np.ndarray, grad: np.ndarray, metric: np.ndarray,
                radius_px: float) -> tuple[np.ndarray, float]:
    """Step maximising the quadratic model within ``radius_px`` of image motion.

    Solves ``(A + λ M) Δ = g`` (``A`` = −Hessian made positive definite,
    ``M`` the pixel-motion metric) with the smallest ``λ ≥ 0`` whose step
    moves the image at most ``radius_px`` (RMS): Levenberg–Marquardt damping
    measured in pixels, so rotation, translation and focal are on one scale.

    Returns
    -------
    step : (P,) array
    predicted : float
        Increase of the objective the model predicts.
    """
    M = metric + np.eye(len(grad)) * (1e-9 * np.trace(metric) / len(grad))

    def solve(lam: float) -> np.ndarray:
        return np.linalg.solve(A + lam * M, grad)

    def size(step: np.ndarray) -> float:
        return float(math.sqrt(max(step @ metric @ step, 0.0)))

    step = solve(0.0)
    if size(step) > radius_px:
        # ‖Δ(λ)‖ falls monotonically with λ: bisect log λ.
        scale = np.trace(A) / np.trace(M)
        lo, hi = math.log(scale * 1e-8), math.log(scale * 1e8)
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            if size(solve(math.exp(mid))) > radius_px:
                lo = mid
            else:
                hi = mid
        step = solve(math.exp(hi))
    predicted = float(grad @ step - 0.5 * step @ A @ step)
    return step, predicted


def _sharpness(samples: _Samples, photo: _PhotoLevel, pose: Pose, intr_level: Intrinsics,
               mi: float, shift_px: float) -> float:
    """1 − (mean MI with the view turned ``shift_px`` up, down, left, right) / MI.

    Same samples, no render. A right pose sits on a peak of the MI (0.17–0.7
    for 2 px at 256 px width on the sample scenes); one 2° or 5 m off on a
    plateau (below 0.03). It tests the alignment of what dominates the image;
    a position error that only near ground reveals can keep 0.1–0.4.
    """
    if mi <= 0:
        return 0.0
    angle = shift_px / intr_level.fx
    shifted = []
    for axis in ((1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)):
        turned, _ = _apply_step(pose, intr_level, np.array([axis[0] * angle, axis[1] * angle,
                                                            0.0, 0.0, 0.0, 0.0]))
        shifted.append(max(_evaluate(samples, photo, turned, intr_level, 6, False).value, 0.0))
    return float(1.0 - np.mean(shifted) / mi)


def _rms_shift_px(samples: _Samples, pose_a: Pose, pose_b: Pose, intr_a: Intrinsics,
                  intr_b: Intrinsics) -> float:
    """RMS image motion (pixels) of (a subset of) the samples between two poses."""
    pts = samples.points[:, :: max(1, samples.points.shape[1] // 4000)]
    _, ua, va = _project(pts, pose_a, intr_a)
    _, ub, vb = _project(pts, pose_b, intr_b)
    d2 = (ua - ub) ** 2 + (va - vb) ** 2
    d2 = d2[np.isfinite(d2)]
    return float(np.sqrt(d2.mean())) if d2.size else 0.0


# --------------------------------------------------------------------------
# Public entry points
# --------------------------------------------------------------------------
def _resolve_modes(scene: Scene | None, modes: Sequence[str] | None, render_fn) -> tuple[str, ...]:
    coloured = render_fn is not None or (
        scene is not None and has_appearance(scene))
    if modes is None:
        return ("detail", "normal") if coloured else ("shaded", "normal")
    modes = tuple(modes)
    for m in modes:
        if m not in DENSE_MODES:
            raise ValueError(f"unknown mode {m!r}; choose from {DENSE_MODES}")
    if not coloured and ("color" in modes or "detail" in modes):
        # An uncoloured mesh renders flat grey: the colour terms carry nothing.
        modes = tuple(m for m in modes if m not in ("color", "detail")) or ("shaded", "normal")
    if not modes:
        raise ValueError("modes must not be empty")
    return modes


def _renderer(scene: Scene | None, render_fn: RenderFn | None, modes: Sequence[str],
              where: str) -> RenderFn:
    """The :class:`RenderFn` of a refinement: ``render_fn``, or the scene rendered for ``modes``."""
    if render_fn is not None:
        return as_render_fn(render_fn, scene, where)
    if scene is None:
        raise ValueError("give a scene or a render_fn")
    # Colour only when needed; otherwise the cheapest mode (normals come anyway).
    return scene_renderer(scene, "color" if ("color" in modes or "detail" in modes) else "normal")


class _Level(PyramidLevel):
    """Everything one pyramid level needs: photo, samples, cameras.

    ``scaled(intr)`` gives a (possibly focal-refined) camera at the level's
    resolution.
    """

    def __init__(self, width: int, intrinsics: Intrinsics, photo_lum: np.ndarray, bins: int,
                 blur_px: float, modes: Sequence[str], supersample: int) -> None:
        self.scale = match_scale(intrinsics.width, width)  # width <= the photo's
        super().__init__(intrinsics, self.scale)
        # Render finer than the level (never finer than the photo) and low-pass.
        self.stride = max(1, min(supersample, int(1.0 / self.scale + 1e-9)))
        self.photo = _photo_level(self, photo_lum, bins, blur_px,
                                  {_PHOTO_CHANNEL[m] for m in modes}, _DETAIL_PX)


def mi_scores(
    scene: Scene | None,
    photo_rgb: np.ndarray,
    intrinsics: Intrinsics,
    pose: Pose,
    *,
    modes: Sequence[str] | None = None,
    width: int = 256,
    bins: int = 32,
    blur_px: float = 1.0,
    supersample: int = 2,
    light_direction: np.ndarray | None = None,
    use_background: bool = True,
    render_fn: RenderFn | None = None,
    sharpness_px: float = 2.0,
) -> dict:
    """Dense agreement of a photo with the model rendered from a pose.

    Parameters
    ----------
    scene : Scene or None
        The model (None when ``render_fn`` is given).
    photo_rgb : (H, W, 3) uint8 array
        The photo (or an (H, W) grey image), at ``intrinsics``' resolution.
    intrinsics : Intrinsics
        The photo's camera.
    pose : Pose
        ``cam_from_world`` to score.
    modes : sequence of str, optional
        Model attributes, see :data:`DENSE_MODES`; default ``("detail",
        "normal")`` for coloured models, ``("shaded", "normal")`` otherwise.
    width : int
        Scoring resolution, pixels (never above the photo's).
    bins : int
        Histogram bins per variable.
    blur_px : float
        Gaussian blur of photo and render values, pixels at ``width``.
    supersample : int
        The render is made this many times finer than ``width`` and low-passed.
    light_direction : (3,) array, optional
        Toward the light (world frame) for ``shaded``.
    use_background : bool
        Count pixels where the model is not seen (sky) as a class of their own.
    render_fn : RenderFn, optional
        ``render_fn(intrinsics, pose, scale) -> RenderResult`` replacing
        :func:`~napari_imgreg.render.render` (e.g. a sun-lit renderer for the
        ``color`` mode).
    sharpness_px : float
        Turn (pixels at ``width``) used to measure ``sharpness``.

    Returns
    -------
    dict
        ``mi`` (sum over modes, bits), ``nmi`` (mean normalised MI, in [1, 2]),
        ``sharpness`` (1 − mean MI of the view turned ``sharpness_px`` four
        ways / MI: 0.17–0.7 on the peak of a right pose on the sample scenes,
        below 0.03 two degrees or five metres off),
        ``per_mode`` {mode: (mi, nmi)}, ``coverage`` (fraction of samples on
        the model), ``width``.
    """
    modes = _resolve_modes(scene, modes, render_fn)
    level = _Level(min(width, intrinsics.width), intrinsics, _luminance(photo_rgb), bins,
                   blur_px, modes, supersample)
    rr = _renderer(scene, render_fn, modes, "mi_scores")(intrinsics, pose,
                                                         level.scale * level.stride)
    samples = _samples_from_render(rr, modes, bins, level.stride, blur_px, light_direction,
                                   use_background, max_samples=10**9)
    intr_level = level.scaled(intrinsics)
    per_mode = {}
    for k, mode in enumerate(modes):
        ev = _evaluate(samples.only(k), level.photo, pose, intr_level, 6, False)
        per_mode[mode] = (max(ev.value, 0.0), ev.nmi)
    mi = float(sum(m for m, _ in per_mode.values()))
    return {
        "mi": mi,
        "nmi": float(np.mean([n for _, n in per_mode.values()])),
        "sharpness": _sharpness(samples, level.photo, pose, intr_level, mi, sharpness_px),
        "per_mode": per_mode,
        "coverage": samples.n_hits / max(1, samples.points.shape[1]),
        "width": level.width,
    }


def mi_score(
    scene: Scene | None,
    photo_rgb: np.ndarray,
    intrinsics: Intrinsics,
    pose: Pose,
    *,
    normalized: bool = True,
    **kwargs,
) -> float:
    """One number for how well a pose explains the photo (see :func:`mi_scores`).

    Returns the mean normalised MI over modes (``normalized``, in [1, 2]) or
    the sum of MI in bits. Keyword arguments are those of :func:`mi_scores`.
    """
    s = mi_scores(scene, photo_rgb, intrinsics, pose, **kwargs)
    return s["nmi"] if normalized else s["mi"]


@dataclass
class DenseParams(StageParams):
    """Settings of the MI refinement (:func:`refine_pose_mi`), each with its valid range.

    Attributes
    ----------
    modes : tuple of str or None
        Model attributes compared with the photo, their MI summed (see
        :data:`DENSE_MODES`). None: ``("detail", "normal")`` for coloured
        models, ``("shaded", "normal")`` otherwise.
    levels : tuple of int
        Pyramid widths, px, coarse to fine (capped at the photo width), each in
        [32, 16384]. Adding 1024 (or the photo width) halves the final error
        for about 0.5–1 s more.
    bins : int
        Photo bins (and render bins per continuous mode) at levels of 256 px
        and more; half as many below (fewer samples), [8, 256].
    optimize_focal : bool
        Also refine the focal length (``fx`` and ``fy`` by the same factor).
    max_seconds : float
        Stop (keeping the best pose so far) after this long, seconds, [0, 3600].
    use_background : bool
        Use pixels where the model is not seen (sky) as points at infinity:
        the skyline then constrains the rotation. Switch off when the mesh
        ends inside the view in front of unmodelled terrain.
    blur_px : float
        Gaussian blur (pixels at each level) of photo and render values, [0, 10].
    supersample : int
        Renders are made this many times finer than the level (never finer
        than the photo) and low-passed, so that texture detail does not
        alias, [1, 8].
    max_iterations : int
        Steps per render, [1, 1000].
    tol_px : float
        A level has converged when a step moves the image less than this
        (RMS, pixels at the level), [0, 10].
    rerender_px : float
        Render again when the pose has moved the image this much since the
        last render (visibility may have changed), px at the level, [0, 100].
    max_renders_per_level : int
        [1, 20].
    max_rotation_deg : float
        Give up (``reason="diverged"``) when the pose turns further than this
        from the start, degrees, [0, 180].
    max_samples : int
        Samples per level at most (a fixed random subset above), [1000, 10⁹].
    max_step_px : float
        Largest step (RMS image motion, pixels at the level), [0.01, 100].
    curvature : bool
        Include the joint histogram's own curvature in the Hessian model
        (more exact, costs 3 × 6 extra histograms per step; in tests it
        changed neither the steps needed nor the result).
    full_pose_from : int
        Levels narrower than this (px) refine the rotation (and focal) only,
        [0, 16384]. At a coarse level a shift and a turn move the far surface
        alike; when only badly predicted near ground tells them apart (other
        light), the position can drift along that valley. In tests on the
        sample scenes all-6-DoF from the first level converged more often,
        hence 0.
    """

    KIND: ClassVar[str] = "dense"

    modes: tuple[str, ...] | None = None
    levels: tuple[int, ...] = (128, 256, 512)
    bins: int = 32
    optimize_focal: bool = False
    max_seconds: float = 10.0
    use_background: bool = True
    blur_px: float = 1.0
    supersample: int = 2
    max_iterations: int = 25
    tol_px: float = 0.01
    rerender_px: float = 1.5
    max_renders_per_level: int = 3
    max_rotation_deg: float = 10.0
    max_samples: int = 120_000
    max_step_px: float = 2.0
    curvature: bool = False
    full_pose_from: int = 0

    #: Inclusive valid range of each numeric field (every element of a tuple).
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "levels": (32, 16384),
        "bins": (8, 256),
        "max_seconds": (0.0, 3600.0),
        "blur_px": (0.0, 10.0),
        "supersample": (1, 8),
        "max_iterations": (1, 1000),
        "tol_px": (0.0, 10.0),
        "rerender_px": (0.0, 100.0),
        "max_renders_per_level": (1, 20),
        "max_rotation_deg": (0.0, 180.0),
        "max_samples": (1000, 10**9),
        "max_step_px": (0.01, 100.0),
        "full_pose_from": (0, 16384),
    }

    def __post_init__(self) -> None:
        # JSON brings lists; keep tuples (hashable, compared as the defaults).
        self.levels = tuple(self.levels)
        if not self.levels:
            raise ValueError("levels must name at least one width")
        if any(isinstance(w, bool) or not isinstance(w, int) for w in self.levels):
            raise ValueError(f"levels must be integers (px), not {list(self.levels)!r}")
        if self.modes is not None:
            if isinstance(self.modes, str):
                raise ValueError(f"modes must be a list of names, not {self.modes!r}")
            self.modes = tuple(self.modes)
            if not self.modes:
                raise ValueError("modes must not be empty (null: the default for the model)")
            for m in self.modes:
                if m not in DENSE_MODES:
                    raise ValueError(f"unknown mode {m!r}; choose from {', '.join(DENSE_MODES)}")
        check_ranges(self)


def refine_pose_mi(
    scene: Scene | None,
    photo_rgb: np.ndarray,
    intrinsics: Intrinsics,
    start: Pose,
    params: DenseParams | None = None,
    *,
    light_direction: np.ndarray | None = None,
    render_fn: RenderFn | None = None,
    cancelled: Callable[[], bool] | None = None,
    **deprecated_keywords,
) -> DenseResult:
    """Refine a camera pose by maximising MI between the photo and the model.

    Parameters
    ----------
    scene : Scene or None
        The model (None when ``render_fn`` is given).
    photo_rgb : (H, W, 3) uint8 array
        The photo (or (H, W) grey), at ``intrinsics``' resolution.
    intrinsics : Intrinsics
        The photo's camera (distortion honoured).
    start : Pose
        ``cam_from_world`` to start from. Every part of the scene must be
        within a few pixels of its place at the coarsest level: 1° and 1 m
        when all the surface is 30 m away or more; 1° and 0.25 m with ground
        4 m from the camera (see the module notes).
    params : DenseParams, optional
        The refinement's settings (default ``DenseParams()``).
    light_direction : (3,) array, optional
        Toward the light, world frame, for the ``shaded`` mode.
    render_fn : RenderFn, optional
        ``render_fn(intrinsics, pose, scale) -> RenderResult`` replacing
        :func:`~napari_imgreg.render.render` (e.g. a sun-lit renderer). Only
        its ``xyz``, ``mask``, ``normal``, ``depth``, ``rgb`` and camera are
        used, so a focal change need not reach it.
    cancelled : callable, optional
        Polled between steps; when it returns True the refinement stops
        with ``reason="cancelled"``. It may raise instead.
    **deprecated_keywords
        Fields of :class:`DenseParams` as keywords, as before version 0.2
        (DeprecationWarning).

    Returns
    -------
    DenseResult
        Never a pose the finest level scores below the start: then the start,
        with ``reason`` "no improvement over the start pose".

    Examples
    --------
    >>> result = refine_pose_mi(scene, photo.image, intrinsics, pnp_pose)  # doctest: +SKIP
    >>> result.pose, result.score, result.sharpness                       # doctest: +SKIP
    """
    t_start = time.perf_counter()
    params = with_keywords(params or DenseParams(), deprecated_keywords, "refine_pose_mi")
    modes = _resolve_modes(scene, params.modes, render_fn)
    render_at = _renderer(scene, render_fn, modes, "refine_pose_mi")
    photo_lum = _luminance(photo_rgb)
    if photo_lum.shape != (intrinsics.height, intrinsics.width):
        raise ValueError(
            f"photo is {photo_lum.shape[1]}x{photo_lum.shape[0]} but the camera is "
            f"{intrinsics.width}x{intrinsics.height}")
    n_params = 7 if params.optimize_focal else 6
    widths = level_widths(params.levels, intrinsics.width)

    pose, intr = start, intrinsics
    history: list[DenseLevel] = []
    n_eval = n_render = 0
    reason = ""
    converged = False
    last: tuple[_Samples, _Level] | None = None
    final_eval: _Eval | None = None

    def stop_reason() -> str:
        if cancelled is not None and cancelled():
            return "cancelled"
        if time.perf_counter() - t_start > params.max_seconds:
            return "time limit"
        return ""

    for width in widths:
        t_level = time.perf_counter()
        level_bins = params.bins if width >= 256 else max(8, params.bins // 2)
        level = _Level(width, intrinsics, photo_lum, level_bins, params.blur_px, modes,
                       params.supersample)
        free_params = [0, 1, 2] if width < params.full_pose_from else list(range(6))
        if params.optimize_focal:
            free_params.append(6)
        mi_level_start = math.nan
        iterations = renders = 0
        step_px = math.nan
        level_converged = False
        radius = params.max_step_px
        while renders < params.max_renders_per_level and not reason:
            rr = render_at(intr, pose, level.scale * level.stride)
            renders += 1
            n_render += 1
            if rr.mask.sum() < _MIN_HITS:
                reason = "the model is hardly in view"
                break
            samples = _samples_from_render(rr, modes, level_bins, level.stride, params.blur_px,
                                           light_direction, params.use_background,
                                           params.max_samples)
            render_pose, render_intr = pose, intr
            last = (samples, level)
            current = _evaluate(samples, level.photo, pose, level.scaled(intr), n_params,
                                True, params.curvature)
            n_eval += 1
            if math.isnan(mi_level_start):
                mi_level_start = current.value
            for _ in range(params.max_iterations):
                reason = stop_reason()
                if reason or not np.isfinite(current.value):
                    break
                free = np.array(free_params)
                A = _positive_definite(current.hess[np.ix_(free, free)])
                sub_step, predicted = _trust_step(A, current.grad[free],
                                                  current.pixel_metric[np.ix_(free, free)], radius)
                step = np.zeros(n_params)
                step[free] = sub_step
                step_px = float(math.sqrt(max(step @ current.pixel_metric @ step, 0.0)))
                new_pose, new_intr = _apply_step(pose, intr, step)
                trial = _evaluate(samples, level.photo, new_pose, level.scaled(new_intr),
                                  n_params, False)
                n_eval += 1
                iterations += 1
                gain = trial.value - current.value
                if gain > 0:
                    pose, intr = new_pose, new_intr
                    current = _evaluate(samples, level.photo, pose, level.scaled(intr),
                                        n_params, True, params.curvature)
                    n_eval += 1
                    ratio = gain / predicted if predicted > 0 else 0.0
                    if ratio > 0.75 and step_px > 0.8 * radius:
                        radius = min(2.0 * radius, params.max_step_px)
                    elif ratio < 0.25:
                        radius *= 0.5
                else:
                    radius = 0.5 * min(radius, step_px)
                if step_px < params.tol_px or radius < params.tol_px:
                    level_converged = True
                    break
            final_eval = current
            if start.rotation_error_deg(pose) > params.max_rotation_deg:
                reason = "diverged"
                break
            moved = _rms_shift_px(samples, render_pose, pose, level.scaled(render_intr),
                                  level.scaled(intr))
            if moved < params.rerender_px:
                break
        history.append(DenseLevel(
            width=level.width, mi_start=float(mi_level_start),
            mi_end=float(final_eval.value) if final_eval is not None else math.nan,
            iterations=iterations, renders=renders,
            n_samples=last[0].points.shape[1] if last else 0,
            step_px=float(step_px), seconds=time.perf_counter() - t_level, pose=pose))
        converged = level_converged
        if reason:
            break

    elapsed = time.perf_counter() - t_start
    if last is None or final_eval is None or not np.isfinite(final_eval.value):
        return DenseResult(start, intrinsics, math.nan, math.nan, 1.0, 0.0, history, n_eval,
                           n_render, elapsed, False,
                           reason or "too few model samples inside the photo", modes)
    samples, level = last
    # Both ends scored on the same (finest) samples; the sharpness uses the
    # turn of mi_scores' default (2 px at 256 px width).
    sharp_px = 2.0 * level.width / 256.0
    if pose is not start:
        start_eval = _evaluate(samples, level.photo, start, level.scaled(intrinsics),
                               n_params, False)
        n_eval += 1
    else:
        start_eval = final_eval
    if reason == "diverged" or final_eval.value < start_eval.value:
        # Never hand back a pose that explains the photo worse than the start.
        reason = reason or "no improvement over the start pose"
        pose, intr, final_eval, converged = start, intrinsics, start_eval, False
    sharpness = _sharpness(samples, level.photo, pose, level.scaled(intr), final_eval.value,
                           sharp_px)
    n_eval += 4
    return DenseResult(pose, intr, final_eval.value, start_eval.value, final_eval.nmi, sharpness,
                       history, n_eval, n_render, time.perf_counter() - t_start,
                       converged and not reason, reason, modes)
