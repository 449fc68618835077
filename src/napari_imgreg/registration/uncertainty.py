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

The halves are a *test*: their disagreement is a bias a split can see, and
it is noisy (four splits, the worst one counts). How large the error of a
pose that passes the test is, is estimated with less noise by a **block
bootstrap**: whole neighbourhoods of matches (cells of an eighth of the
photo's width) are drawn with replacement, the pose is re-solved from each
draw, and the spread of the re-solved poses over the frame is the error of
a pose built from that many independent neighbourhoods. It sees the same
shared neighbourhood errors as the support term, without its linearisation
or its noise model. Its **gain** (1.7) is the median ratio of the true to the
bootstrapped error of poses matched against the model's own colours on the
rough benchmark (issue 13): neighbourhoods an eighth of the photo wide are
not quite independent.

What neither sees is a bias every match shares. The one we know to expect is
the **synthetic light** of a render relit for the photo's sun
(:func:`~napari_imgreg.registration.stages.relight.shading_share`): the model
shades and shadows only the relief it has, so what its light draws sits
where the photo's light draws it only to within the relief it lacks, for
every match alike, and a small turn of the camera absorbs it. The estimate
adds that part of the matches' held-out error whole: ``√share`` × the median
held-out residual, with a margin (``shared_gain``, 1.25) because nothing in
the photo can check it.

The estimate is what RESULT.json writes as ``uncertainty``; a pose whose
halves disagree beyond the limit keeps their (larger) figure.

A camera whose focal length (or principal point, or distortion) was
estimated with the pose is re-solved whole in every draw: the pose and the
camera trade against each other (a longer lens and a step back look alike at
the centre of the frame, not at its edges), and an estimate that held the
estimated focal length fixed would not see that trade. The halves, a test,
hold it fixed.

What it cannot see still: a bias the same everywhere in the image that a pose
change absorbs exactly, from anything but the synthetic light (a texture
whose colours shifted since the survey, a model off by a constant).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import ClassVar

import cv2
import numpy as np

from ..camera import Intrinsics, Pose
from ..validate import StageParams, check_ranges
from .pose import PoseParams, estimate_pose, with_known_focal
from .resection import refine_camera

__all__ = [
    "UNCERTAIN_PX",
    "Uncertainty",
    "UncertaintyParams",
    "estimate_uncertainty",
    "bootstrap_term",
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
        of the pose, [0, 100]; 0: every lifted match. Default 2: a match 2×
        the threshold off is a wrong match, not a biased keypoint (a bias is a
        few pixels), and wrong matches crowded in one half let its RANSAC lock
        onto another pose. On the rough benchmark (issue 13, 120 photos) 2
        against 0: changed light 39 → 40 of 40 registered, correct trial poses
        (< 1.5 px) called uncertain (≥ 4 px) 25 → 17, no trial pose ≥ 4 px
        off passing either way, every registered photo within 2× its
        estimate, Spearman 0.63 → 0.65.
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
    estimate : {"bootstrap", "halves"}
        What the estimate is: the block bootstrap with the synthetic light's
        shared error, the halves serving as a test (``"bootstrap"``,
        default); or the halves' own figure (``"halves"``: the estimate up
        to the issue-13 rough benchmark's third round, kept to reproduce it).
    bootstrap_samples : int
        Draws of the block bootstrap, [10, 1000]. Default 40: on the rough
        benchmark's trial poses the bootstrap of 40 draws is within 6 % of
        that of 200 (median; 13 % at the 90th percentile), with no bias.
    bootstrap_gain : float
        Scale from the bootstrap's spread to the expected error, [0, 10].
        Default 1.7 (module docstring).
    shared_gain : float
        Scale of the synthetic light's shared error, [0, 10]. Default 1.25
        (module docstring); 0 leaves it out.
    """

    KIND: ClassVar[str] = "uncertainty"

    directions_deg: tuple[float, ...] = (0.0, 45.0, 90.0, 135.0)
    min_half: int = 12
    gain: float = 1.0
    floor_px: float = 0.3
    max_eval_points: int = 4000
    robust: bool = True
    candidate_factor: float = 2.0
    support: bool = True
    cell_fraction: float = 0.125
    estimate: str = "bootstrap"
    bootstrap_samples: int = 40
    bootstrap_gain: float = 1.7
    shared_gain: float = 1.25

    #: Inclusive valid range of each numeric field (``--params``, GUI, code).
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "directions_deg": (0.0, 180.0),
        "min_half": (6, 10_000),
        "gain": (0.0, 10.0),
        "floor_px": (0.0, 20.0),
        "max_eval_points": (10, 1_000_000),
        "cell_fraction": (0.01, 1.0),
        "candidate_factor": (0.0, 100.0),
        "bootstrap_samples": (10, 1000),
        "bootstrap_gain": (0.0, 10.0),
        "shared_gain": (0.0, 10.0),
    }

    #: The values ``estimate`` takes.
    ESTIMATES: ClassVar[tuple[str, ...]] = ("bootstrap", "halves")

    def __post_init__(self) -> None:
        # JSON brings lists; keep tuples (hashable, compared as the defaults).
        self.directions_deg = tuple(self.directions_deg)
        if not self.directions_deg:
            raise ValueError("directions_deg must name at least one direction")
        if self.estimate not in self.ESTIMATES:
            raise ValueError(f"estimate must be one of {', '.join(self.ESTIMATES)}, "
                             f"not {self.estimate!r}")
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
    halves_px, shared_px : float
        What went into it (below); for the hints.
    """

    reprojection_px: float
    position_m: float
    rotation_deg: float
    splits: int = 0
    #: The split halves' own figure (pixels of the photo): the test a pose
    #: must pass; NaN when not computed.
    halves_px: float = float("nan")
    #: The synthetic light's shared part of ``reprojection_px`` (pixels of the photo).
    shared_px: float = 0.0
    #: Expected error of an estimated focal length (``fx``, pixels): the
    #: bootstrap's spread × its gain; None when the focal length was known.
    focal_px: float | None = None
    #: What the estimate rests on: ``""`` the photo's matches (split halves,
    #: resampling), ``"control points"`` the picked pairs' geometry and click
    #: noise (:func:`~napari_imgreg.registration.manual.pair_uncertainty`).
    basis: str = ""

    def to_dict(self) -> dict:
        """The RESULT.json fields (JSON-ready: infinite becomes None): the three
        of the contract, ``focal_px`` when the focal length was estimated, and
        ``basis`` when the estimate is not the photo's matches'."""
        def num(v: float, nd: int):
            return round(float(v), nd) if np.isfinite(v) else None
        out = {"reprojection_px": num(self.reprojection_px, 3),
               "position_m": num(self.position_m, 4),
               "rotation_deg": num(self.rotation_deg, 4)}
        if self.focal_px is not None:
            out["focal_px"] = num(self.focal_px, 2)
        if self.basis:
            out["basis"] = self.basis
        return out

    @classmethod
    def from_dict(cls, d: dict | None) -> Uncertainty | None:
        if not d:
            return None
        def val(k):
            v = d.get(k)
            return float("inf") if v is None else float(v)
        focal = val("focal_px") if "focal_px" in d else None
        return cls(val("reprojection_px"), val("position_m"), val("rotation_deg"),
                   focal_px=focal, basis=str(d.get("basis") or ""))

    def is_small(self, image_width: int) -> bool:
        """Below :data:`UNCERTAIN_PX` at 1632 px width (scaled to ``image_width``)."""
        return bool(self.reprojection_px < UNCERTAIN_PX * image_width / 1632.0)

    def halves_disagree(self, image_width: int) -> bool:
        """The split halves' own figure reaches :data:`UNCERTAIN_PX` (scaled)."""
        return bool(self.halves_px >= UNCERTAIN_PX * image_width / 1632.0)

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
    shading_share: float = 0.0,
    rng_seed: int = 0,
) -> Uncertainty:
    """The expected error of ``pose``, tested by spatially separate halves (module docstring).

    *The halves' figure.* For each direction, the correspondences are split
    at the median of their image coordinate along it; a pose is solved from
    each half (RANSAC EPnP, ``robust``) and the two are compared at
    ``eval_points``. The same splits of simulated matches (the pose's exact
    projections of its inliers plus Gaussian noise of their spread) say how
    far apart noise alone puts the halves; the excess, in quadrature, is the
    bias. The spread term is the larger of the full pose's noise error (the
    simulated full solve against ``pose``) and, with ``params.support``, the
    support term (:func:`support_term`: the median held-out residual of one
    half's inliers under the other half's pose, propagated through the
    pose's geometry to ``eval_points``). The figure is the spread term and
    ``gain`` × half the worst excess over the directions, with ``floor_px``,
    added in quadrature; position and rotation likewise (without the floor).

    *The estimate* (``params.estimate == "bootstrap"``): ``bootstrap_gain`` ×
    the block bootstrap (:func:`bootstrap_term`) and ``shared_gain`` ×
    ``√shading_share`` × the median held-out residual (the synthetic light's
    error, shared by every match), with ``floor_px``, in quadrature. Metres
    and degrees: the bootstrap's, but at least what that image error means
    for the pose's geometry (:func:`support_term` per pixel), and for the
    centre at least half the halves' figure (the line of sight's freedom).
    When the halves' figure reaches :data:`UNCERTAIN_PX`, each of the three
    numbers is at least the halves'.

    Parameters
    ----------
    intrinsics : Intrinsics
        The photo's camera, full resolution.
    pose : Pose
        The pose to judge (``cam_from_world``), solved from these correspondences.
        The fields of ``intrinsics.estimated`` (a focal length estimated with
        the pose) are re-solved with it in every bootstrap draw; the halves
        hold them fixed.
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
    shading_share : float
        The share of the matched render's fine contrast drawn by synthetic
        light, [0, 1] (:attr:`~napari_imgreg.render.RenderResult.shading_share`;
        0 for a render in the model's own colours).
    rng_seed : int
        Seed of the halves' RANSAC, the simulated noise and the bootstrap's
        draws (reproducible).

    Returns
    -------
    Uncertainty
        Pixels of this photo, metres, degrees. Infinite when fewer than
        ``2 * min_half`` correspondences are given or no split can be solved:
        nothing independent supports the pose.
    """
    params = params or UncertaintyParams()
    robust = (pose_params or PoseParams()) if params.robust else None
    # The halves and the geometry hold the camera fixed; only the bootstrap
    # re-solves what was estimated.
    free = tuple(intrinsics.estimated)
    camera = intrinsics
    intrinsics = with_known_focal(intrinsics)
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
    cell_px = params.cell_fraction * intrinsics.width
    # The support term per pixel of keypoint error (it scales with the error):
    # the halves' spread below, and the estimate's geometry after.
    per_px = support_term(intrinsics, pose, X[inl], u[inl], E, 1.0, cell_px)
    if params.support and held_out:
        sigma_cv = float(np.median(held_out)) / 1.1774
        spread = np.maximum(noise, per_px * sigma_cv if np.isfinite(sigma_cv)
                            else np.full(3, np.inf))
    px, m, deg = np.sqrt(spread**2 + (g * bias) ** 2)
    halves = np.array([np.hypot(px, floor), m, deg])
    if params.estimate == "halves":
        return Uncertainty(*map(float, halves), splits, halves_px=float(halves[0]))
    # The estimate: the block bootstrap, and the synthetic light's shared error.
    boot = params.bootstrap_gain * bootstrap_term(camera, pose, X[inl], u[inl], E, cell_px,
                                                  params.bootstrap_samples, rng_seed)
    focal_px = float(boot[3]) if free else None
    held_px = float(np.median(held_out)) if held_out else float(np.median(fit[inl]))
    shared_px = params.shared_gain * float(np.sqrt(np.clip(shading_share, 0.0, 1.0))) * held_px
    px = float(np.sqrt(boot[0] ** 2 + shared_px**2 + floor**2))
    # Metres and degrees: at least what this image error means for this
    # geometry (how the matches turn a pixel into a turn and a step, as in
    # the support term) — an error the draws do not see (the shared part, a
    # bias along the weakly held directions) moves the camera so too. The
    # centre's step along the line of sight barely moves the image, and a
    # bias in the model's depth (relief it lacks lifts every match off the
    # rock) makes it; the halves, each extrapolating, see that freedom: half
    # their figure is a floor of the centre's error.
    geometric = (px * per_px[1:] / per_px[0] if np.isfinite(per_px).all() and per_px[0] > 0
                 else np.full(2, np.inf))
    m = max(boot[1], geometric[0], 0.5 * halves[1])
    deg = max(boot[2], geometric[1])
    est = np.array([px, m, deg])
    if halves[0] >= UNCERTAIN_PX * scale:
        # The halves see a bias: the estimate is at least what they say.
        est = np.maximum(est, halves)
    return Uncertainty(*map(float, est), splits, halves_px=float(halves[0]),
                       shared_px=float(shared_px), focal_px=focal_px)


def bootstrap_term(intrinsics: Intrinsics, pose: Pose, X: np.ndarray, u: np.ndarray,
                   E: np.ndarray, cell_px: float, samples: int = 40,
                   rng_seed: int = 0) -> np.ndarray:
    """How far the pose moves when whole neighbourhoods of matches are drawn anew.

    A block bootstrap: the matches are grouped in ``cell_px`` squares of the
    photo (neighbours share their shading, relief and matching error, so a
    cell is one observation); ``samples`` times, as many cells as there are
    are drawn with replacement and the pose is re-solved from their matches
    (least squares from ``pose``; with the fields of ``intrinsics.estimated``
    re-solved too). The spread of the re-solved cameras is the error of a
    pose built from that many independent cells.

    Parameters
    ----------
    intrinsics, pose : the photo's camera and the pose.
    X : (N, 3) array
        The pose's inlier 3D points, model frame, metres.
    u : (N, 2) array
        Their pixels in the photo.
    E : (M, 3) array
        Model points over the whole frame.
    cell_px : float
        Side of a cell, pixels.
    samples : int
        Draws.
    rng_seed : int
        Seed of the draws.

    Returns
    -------
    (4,) array
        Median over ``E`` of the RMS image distance (px) between the re-solved
        cameras and the given one, RMS camera-centre distance (m), RMS
        rotation (degrees), RMS change of ``fx`` (px; 0 when it is not
        estimated); infinite when fewer than 2 cells or 5 draws can be solved.
    """
    cells = _cell_labels(u, cell_px)
    n_cells = int(cells.max()) + 1 if len(cells) else 0
    if n_cells < 2 or len(E) == 0:
        return np.full(4, np.inf)
    members = [np.flatnonzero(cells == c) for c in range(n_cells)]
    rng = np.random.default_rng(rng_seed)
    base = pose.project(intrinsics, E)
    fixed = with_known_focal(intrinsics)
    image, centre, turn, focal = [], [], [], []
    for _ in range(samples):
        idx = np.concatenate([members[c] for c in rng.integers(0, n_cells, n_cells)])
        if len(idx) < 6:
            continue
        if intrinsics.estimated:
            p, cam = _solve_camera(intrinsics, X[idx], u[idx], pose)
        else:
            p, cam = _solve(fixed, X[idx], u[idx], pose, None), fixed
        if p is None:
            continue
        image.append(np.linalg.norm(p.project(cam, E) - base, axis=1))
        centre.append(float(np.linalg.norm(p.center - pose.center)))
        turn.append(_rotation_deg(p, pose))
        focal.append(cam.fx - intrinsics.fx)
    if len(image) < 5:
        return np.full(4, np.inf)
    rms = np.sqrt(np.mean(np.square(image), axis=0))
    rms = rms[np.isfinite(rms)]
    if len(rms) == 0:
        return np.full(4, np.inf)
    return np.array([float(np.median(rms)), float(np.sqrt(np.mean(np.square(centre)))),
                     float(np.sqrt(np.mean(np.square(turn)))),
                     float(np.sqrt(np.mean(np.square(focal))))])


def _cell_labels(u: np.ndarray, cell_px: float) -> np.ndarray:
    """(N,) int: which ``cell_px`` square of the photo each pixel of ``u`` falls in,
    numbered 0 … cells − 1."""
    return np.unique(np.floor(u / max(cell_px, 1e-6)).astype(np.int64), axis=0,
                     return_inverse=True)[1].ravel()


def _solve_camera(intr: Intrinsics, X: np.ndarray, u: np.ndarray,
                  start: Pose) -> tuple[Pose | None, Intrinsics]:
    """Pose and the fields of ``intr.estimated`` together, least squares from
    ``start`` and ``intr`` (a linear loss: every drawn match counts fully, as
    in :func:`_solve`)."""
    free = intr.estimated
    square = "cx" not in free and abs(intr.fx - intr.fy) <= 1e-9 * intr.fx
    k1 = float(intr.dist_coeffs[0]) if len(intr.dist_coeffs) else 0.0
    try:
        pose, (fx, fy), (cx, cy), k1 = refine_camera(
            X, u, start, (intr.fx, intr.fy), (intr.cx, intr.cy), k1,
            estimate_k1="dist" in free, free_principal_point="cx" in free,
            square_pixels=square, loss_scale_px=1e6)
    except (ValueError, np.linalg.LinAlgError):
        return None, intr
    dist = intr.dist
    if "dist" in free:
        dist = (k1, *intr.dist_coeffs[1:])
    try:
        cam = replace(intr, fx=fx, fy=fy, cx=cx, cy=cy, dist=dist)
    except ValueError:  # an implausible camera (FieldValueError)
        return None, intr
    return pose, cam


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
    cells = int(_cell_labels(u, cell_px).max()) + 1
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
