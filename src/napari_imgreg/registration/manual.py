"""Manual control-point registration and the workbench's interactive pose tools.

When the automatic registration cannot match the photo to the render (extreme
light, a prior that is far off), the geologist picks the same points on the
photo and on a *reference render* of the model (Kehl et al. 2018, "Creating
Reference Images for Manual Registration"). The reference render's ``xyz`` map
lifts its picks to 3D, so each pair becomes a 2D–3D correspondence and the
photo's pose follows by PnP (:func:`solve_manual`); with six or more pairs the
focal length can be solved too. The result is scored with the same seven
metrics as an automatic trial (:func:`score_pose`).

The rest of the module is the arithmetic behind the workbench's pose editing
(nudges, moving the camera on the DEM map, undo), the terrain map, the
conversion between a 3D viewer camera and a photogrammetric camera, and the
camera frusta drawn in 3D. Nothing here imports Qt or napari.

Conventions are the package's: pixels (x = column, y = row) with the first
pixel's centre at (0, 0); the model frame is local ENU metres; poses are
``cam_from_world`` (:class:`~napari_imgreg.camera.Pose`).
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.errors import InputError, input_error
from napari_imgreg.registration.pose import PoseParams, estimate_pose, reprojection_errors

__all__ = [
    "MIN_PAIRS",
    "MIN_PAIRS_FOCAL",
    "nudge_pose",
    "pose_at_ground",
    "height_above_ground",
    "turn_toward",
    "PoseHistory",
    "TerrainMap",
    "terrain_map",
    "camera_from_view",
    "view_from_camera",
    "frustum_segments",
    "filtered_for_matching",
    "reduce_for_matching",
    "ManualSolution",
    "solve_manual",
    "score_pose",
    "metric_trend",
    "save_pose_to_record",
]

#: Pairs needed for a pose (EPnP's minimum).
MIN_PAIRS = 4
#: Pairs needed to solve the focal length as well.
MIN_PAIRS_FOCAL = 6


# ============================================================== pose editing
def nudge_pose(
    pose: Pose,
    d_trend: float = 0.0,
    d_plunge: float = 0.0,
    d_roll: float = 0.0,
    forward: float = 0.0,
    right: float = 0.0,
    up: float = 0.0,
) -> Pose:
    """A pose turned and moved by small amounts, as a geologist thinks of it.

    Parameters
    ----------
    pose : Pose
        The pose to change.
    d_trend, d_plunge, d_roll : float
        Added to the trend, plunge and roll, degrees (contract §2: trend
        clockwise from north, plunge positive downward). The plunge is kept
        within [-90, 90].
    forward, right, up : float
        Camera movement, metres: ``forward`` horizontally along the trend,
        ``right`` horizontally to the photographer's right, ``up`` vertically.

    Returns
    -------
    Pose
    """
    trend, plunge, roll = pose.attitude
    t = math.radians(trend)
    ahead = np.array([math.sin(t), math.cos(t), 0.0])
    side = np.array([math.cos(t), -math.sin(t), 0.0])
    center = pose.center + forward * ahead + right * side + np.array([0.0, 0.0, up])
    new_plunge = float(np.clip(plunge + d_plunge, -90.0, 90.0))
    return Pose.from_attitude(trend + d_trend, new_plunge, roll + d_roll, center)


def height_above_ground(
    pose: Pose, terrain_height: Callable[[float, float], float]
) -> float | None:
    """Height of the camera above the terrain, metres (None outside the terrain).

    Parameters
    ----------
    pose : Pose
    terrain_height : callable
        ``f(x, y) -> z`` in the local frame, e.g. :meth:`Scene.terrain_height`.
    """
    x, y, z = pose.center
    try:
        return float(z - terrain_height(float(x), float(y)))
    except (InputError, ValueError):
        return None


def pose_at_ground(
    pose: Pose,
    x: float,
    y: float,
    height: float,
    terrain_height: Callable[[float, float], float],
) -> Pose:
    """The pose moved to (x, y) at ``height`` metres above the terrain, same attitude.

    This is what a click on the DEM map does: the camera moves laterally and
    its altitude follows the DEM.

    Raises
    ------
    InputError or ValueError
        (From ``terrain_height``) the point lies outside the DEM or the model.
    """
    z = float(terrain_height(float(x), float(y))) + float(height)
    return pose.with_center(np.array([x, y, z], np.float64))


def turn_toward(pose: Pose, x: float, y: float) -> Pose:
    """The pose turned (trend only) to look toward the map point (x, y)."""
    c = pose.center
    dx, dy = float(x - c[0]), float(y - c[1])
    if math.hypot(dx, dy) < 1e-9:
        return pose
    _, plunge, roll = pose.attitude
    trend = math.degrees(math.atan2(dx, dy)) % 360.0
    return Pose.from_attitude(trend, plunge, roll, c)


class PoseHistory:
    """Undo and redo of pose edits.

    ``push`` records an edit (the previous pose can be restored by
    :meth:`undo`); ``replace`` continues the current edit without a new undo
    step (the intermediate positions of a drag on the map).

    Parameters
    ----------
    pose : Pose
        The starting pose.
    limit : int
        Undo steps kept.

    Examples
    --------
    >>> import numpy as np
    >>> from napari_imgreg.camera import Pose
    >>> h = PoseHistory(Pose.from_attitude(0, 0, 0, np.zeros(3)))
    >>> h.push(Pose.from_attitude(10, 0, 0, np.zeros(3)), "trend +10°")
    >>> round(h.undo().attitude[0], 6)
    0.0
    >>> round(h.redo().attitude[0], 6)
    10.0
    """

    def __init__(self, pose: Pose, limit: int = 200) -> None:
        self._current = pose
        self._current_label = "start"
        self._undo: list[tuple[Pose, str]] = []
        self._redo: list[tuple[Pose, str]] = []
        self.limit = int(limit)

    @property
    def current(self) -> Pose:
        return self._current

    @property
    def label(self) -> str:
        """What made the current pose ("prior", "trend +1°", "trial 2", ...)."""
        return self._current_label

    @property
    def can_undo(self) -> bool:
        return bool(self._undo)

    @property
    def can_redo(self) -> bool:
        return bool(self._redo)

    @property
    def undo_label(self) -> str:
        """The edit :meth:`undo` would take back ("" when none)."""
        return self._current_label if self._undo else ""

    def push(self, pose: Pose, label: str = "") -> None:
        """Make ``pose`` current as a new edit."""
        self._undo.append((self._current, self._current_label))
        del self._undo[: -self.limit]
        self._redo.clear()
        self._current, self._current_label = pose, label

    def replace(self, pose: Pose) -> None:
        """Change the current pose within the same edit (no new undo step)."""
        self._current = pose

    def undo(self) -> Pose | None:
        """Go back one edit; returns the restored pose (None when nothing to undo)."""
        if not self._undo:
            return None
        self._redo.append((self._current, self._current_label))
        self._current, self._current_label = self._undo.pop()
        return self._current

    def redo(self) -> Pose | None:
        """Re-apply the last undone edit; returns it (None when nothing to redo)."""
        if not self._redo:
            return None
        self._undo.append((self._current, self._current_label))
        self._current, self._current_label = self._redo.pop()
        return self._current

    def __len__(self) -> int:
        return len(self._undo)


# =============================================================== terrain map
@dataclass
class TerrainMap:
    """A north-up height raster in the local frame, for the repositioning map.

    Attributes
    ----------
    heights : (rows, cols) float array
        Heights, metres (local frame); NaN where unknown. Row 0 is the north row.
    extent : (4,) tuple
        ``(xmin, xmax, ymin, ymax)`` of the pixel centres, local metres.
    source : str
        ``"DEM"`` or ``"model"``.
    """

    heights: np.ndarray
    extent: tuple[float, float, float, float]
    source: str

    @property
    def spacing(self) -> tuple[float, float]:
        """(dx, dy) pixel spacing, metres."""
        rows, cols = self.heights.shape
        xmin, xmax, ymin, ymax = self.extent
        return (xmax - xmin) / max(cols - 1, 1), (ymax - ymin) / max(rows - 1, 1)

    @property
    def image_extent(self) -> tuple[float, float, float, float]:
        """``(left, right, bottom, top)`` of the pixel *edges* (for ``imshow``)."""
        dx, dy = self.spacing
        xmin, xmax, ymin, ymax = self.extent
        return xmin - dx / 2, xmax + dx / 2, ymin - dy / 2, ymax + dy / 2

    def hillshade(self, azimuth_deg: float = 315.0, altitude_deg: float = 45.0) -> np.ndarray:
        """Shaded relief in [0, 1] (NaN where the heights are), light from ``azimuth_deg``.

        Returns
        -------
        (rows, cols) float array
        """
        z = self.heights
        dx, dy = self.spacing
        filled = np.where(np.isfinite(z), z, np.nanmean(z) if np.isfinite(z).any() else 0.0)
        # Rows run south: d/dy (north) is minus the row gradient.
        dz_row, dz_col = np.gradient(filled, dy or 1.0, dx or 1.0)
        dzdx, dzdy = dz_col, -dz_row
        az, alt = math.radians(azimuth_deg), math.radians(altitude_deg)
        light = np.array(
            [math.sin(az) * math.cos(alt), math.cos(az) * math.cos(alt), math.sin(alt)])
        normal = np.stack([-dzdx, -dzdy, np.ones_like(filled)], axis=-1)
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        shade = np.clip(normal @ light, 0.0, 1.0)
        return np.where(np.isfinite(z), shade, np.nan)


def terrain_map(scene, max_cells: int = 400) -> TerrainMap:
    """The terrain under the scene as a height raster for the map.

    The scene's DEM when it has one (in the local frame: the georeference's
    origin subtracted), otherwise the model's own top surface sampled by
    vertical rays on a grid of at most ``max_cells`` along its longer side.

    Parameters
    ----------
    scene : Scene
    max_cells : int
        Largest raster side; a larger DEM is subsampled.

    Returns
    -------
    TerrainMap
    """
    if scene.dem is not None:
        dem = scene.dem
        origin = scene.georef.origin if scene.georef is not None else np.zeros(3)
        stride = max(1, int(math.ceil(max(dem.heights.shape) / max_cells)))
        h = dem.heights[::stride, ::stride] - origin[2]
        xmin = dem.x0 - origin[0]
        ymax = dem.y0 - origin[1]
        rows, cols = h.shape
        xmax = xmin + (cols - 1) * dem.dx * stride
        ymin = ymax - (rows - 1) * dem.dy * stride
        return TerrainMap(np.asarray(h, np.float64), (xmin, xmax, ymin, ymax), "DEM")
    (x0, y0, z0), (x1, y1, z1) = scene.bounds
    size = max(x1 - x0, y1 - y0, 1e-6)
    step = size / max(2, max_cells - 1)
    xs = np.arange(x0, x1 + step / 2, step)
    ys = np.arange(y1, y0 - step / 2, -step)  # north row first
    X, Y = np.meshgrid(xs, ys)
    top = z1 + 10.0
    origins = np.stack([X.ravel(), Y.ravel(), np.full(X.size, top)], axis=1)
    dirs = np.tile(np.array([[0.0, 0.0, -1.0]]), (X.size, 1))
    hits = scene.cast_rays(origins, dirs)
    z = np.where(hits.hit, top - hits.distance, np.nan).reshape(X.shape)
    return TerrainMap(z.astype(np.float64), (xs[0], xs[-1], ys[-1], ys[0]), "model")


# ============================================== viewer camera <-> photo camera
def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, np.float64).reshape(3)
    n = np.linalg.norm(v)
    if n == 0:
        raise ValueError("zero-length direction")
    return v / n


def camera_from_view(
    center: np.ndarray,
    view_direction: np.ndarray,
    up_direction: np.ndarray,
    visible_height: float,
    width: int,
    height: int,
    fov_deg: float | None = None,
    intrinsics: Intrinsics | None = None,
) -> tuple[Intrinsics, Pose]:
    """A pinhole camera that sees what a 3D viewer shows.

    A 3D viewer (napari, vispy) orbits a ``center`` point: it looks along
    ``view_direction``, ``up_direction`` points up on the canvas and
    ``visible_height`` world units span the canvas height at the centre. This
    places a pinhole camera of ``width`` × ``height`` pixels so that it frames
    the centre the same way, for the reference render of a manual
    registration.

    Parameters
    ----------
    center : (3,) array
        The point the view orbits, model frame (metres).
    view_direction, up_direction : (3,) arrays
        Model-frame directions (need not be unit or orthogonal; ``up`` is
        made orthogonal to ``view``).
    visible_height : float
        World extent across the image height at the centre, metres.
    width, height : int
        Size of the camera image, pixels.
    fov_deg : float, optional
        Vertical field of view (a perspective viewer). When None or 0 (an
        orthographic viewer) the focal length of ``intrinsics`` is used, or
        a 50° vertical field of view without it.
    intrinsics : Intrinsics, optional
        A camera whose focal length (scaled to ``height``) to use.

    Returns
    -------
    intrinsics : Intrinsics
        Square pixels, principal point at the image centre.
    pose : Pose
        ``cam_from_world``; the camera sits ``distance`` in front of the
        centre, where the visible height at the centre is ``visible_height``.
    """
    z = _unit(view_direction)
    up = np.asarray(up_direction, np.float64).reshape(3)
    up = up - (up @ z) * z
    y = -_unit(up)  # image rows run down the canvas
    x = np.cross(y, z)
    R = np.stack([x, y, z])
    if fov_deg:
        f = (height / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    elif intrinsics is not None:
        f = intrinsics.fy * height / intrinsics.height
    else:
        f = (height / 2.0) / math.tan(math.radians(25.0))
    distance = float(visible_height) * f / height
    cam_center = np.asarray(center, np.float64).reshape(3) - distance * z
    intr = Intrinsics(int(width), int(height), f, f, (width - 1) / 2.0, (height - 1) / 2.0)
    return intr, Pose.from_center(R, cam_center)


def view_from_camera(
    intrinsics: Intrinsics, pose: Pose, distance: float, canvas_px: float
) -> dict:
    """The 3D-viewer camera that looks from a photo's pose (inverse of :func:`camera_from_view`).

    Parameters
    ----------
    intrinsics : Intrinsics
    pose : Pose
    distance : float
        How far in front of the camera the viewer's orbit centre is, metres
        (e.g. the depth at the image centre).
    canvas_px : float
        The viewer canvas' smaller side, pixels.

    Returns
    -------
    dict
        ``center`` (3,) model-frame point, ``view_direction`` and
        ``up_direction`` (3,) model-frame unit vectors, ``zoom`` (canvas
        pixels per metre at the centre) and ``fov_deg`` (vertical field of
        view).
    """
    z = pose.view_direction
    up = -pose.R[1]
    visible = distance * intrinsics.height / intrinsics.fy
    fov = 2.0 * math.degrees(math.atan2(intrinsics.height / 2.0, intrinsics.fy))
    return {
        "center": pose.center + distance * z,
        "view_direction": z,
        "up_direction": up,
        "zoom": float(canvas_px) / visible,
        "fov_deg": fov,
    }


def frustum_segments(intrinsics: Intrinsics, pose: Pose, depth: float) -> np.ndarray:
    """Line segments of a camera's view pyramid, for drawing cameras in 3D.

    Parameters
    ----------
    intrinsics : Intrinsics
    pose : Pose
    depth : float
        Distance of the pyramid's base along the view direction, metres.

    Returns
    -------
    (8, 2, 3) array
        Start and end points (model frame): four edges from the centre to the
        image corners at ``depth``, then the four sides of the base.
    """
    w, h = intrinsics.width, intrinsics.height
    corners_px = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
    cam = intrinsics.unproject(corners_px, np.full(4, float(depth)))
    corners = pose.inverse_transform(cam)
    c = pose.center
    segs = [(c, corners[k]) for k in range(4)]
    segs += [(corners[k], corners[(k + 1) % 4]) for k in range(4)]
    return np.array(segs, np.float64)


# ===================================================== manual registration
@dataclass
class ManualSolution:
    """A pose solved from manually picked pairs.

    Attributes
    ----------
    ok : bool
    pose : Pose or None
        ``cam_from_world`` of the photo; None when ``ok`` is False.
    intrinsics : Intrinsics
        The photo's camera (with the solved focal length when
        ``focal_solved``).
    errors_px : (N,) float array
        Reprojection error of every pair under the pose, photo pixels (NaN
        without a pose or for a pair without a 3D point).
    inliers : (N,) bool array
        Pairs that agree with the pose (error below the threshold).
    threshold_px : float
        The agreement threshold used.
    focal_solved : bool
    method : str
        ``"ransac-epnp"`` (six or more pairs) or ``"pnp"`` (all pairs).
    reason : str
        Why it failed ("" when ok).
    """

    ok: bool
    pose: Pose | None
    intrinsics: Intrinsics
    errors_px: np.ndarray
    inliers: np.ndarray
    threshold_px: float
    focal_solved: bool = False
    method: str = ""
    reason: str = ""

    @property
    def rms_px(self) -> float:
        """RMS reprojection error of the inliers, pixels (NaN without)."""
        if not self.ok or not self.inliers.any():
            return float("nan")
        return float(np.sqrt(np.mean(self.errors_px[self.inliers] ** 2)))

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


def _pnp_candidates(
    intr: Intrinsics, p3: np.ndarray, p2: np.ndarray, initial: Pose | None
) -> list[Pose]:
    """Poses from several PnP solvers on all points (3D points already centred)."""
    K, dist = intr.K, intr.dist_coeffs
    out: list[Pose] = []
    flags = [cv2.SOLVEPNP_EPNP, cv2.SOLVEPNP_SQPNP]
    for flag in flags:
        try:
            ok, rvec, tvec = cv2.solvePnP(p3, p2, K, dist, flags=flag)
        except cv2.error:
            continue
        if ok:
            out.append(Pose.from_rvec_tvec(rvec, tvec))
    if initial is not None:
        rvec0 = initial.rvec.reshape(3, 1).copy()
        tvec0 = initial.t.reshape(3, 1).copy()
        try:
            ok, rvec, tvec = cv2.solvePnP(
                p3, p2, K, dist, rvec0, tvec0, useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE
            )
        except cv2.error:
            ok = False
        if ok:
            out.append(Pose.from_rvec_tvec(rvec, tvec))
    refined = []
    for pose in out:
        try:
            rvec, tvec = cv2.solvePnPRefineLM(
                p3, p2, K, dist, pose.rvec.reshape(3, 1).copy(), pose.t.reshape(3, 1).copy()
            )
            refined.append(Pose.from_rvec_tvec(rvec, tvec))
        except cv2.error:
            refined.append(pose)
    return refined


def _best_pose(intr: Intrinsics, p3: np.ndarray, p2: np.ndarray, poses: list[Pose]) -> Pose | None:
    best, best_rms = None, np.inf
    for pose in poses:
        if not (pose.transform(p3)[:, 2] > 0).all():
            continue  # cheirality: every picked point in front of the camera
        err = reprojection_errors(intr, pose, p3, p2)
        rms = float(np.sqrt(np.mean(err**2)))
        if rms < best_rms:
            best, best_rms = pose, rms
    return best


def _with_focal(intr: Intrinsics, f: float) -> Intrinsics:
    fy = f * intr.fy / intr.fx
    return Intrinsics(intr.width, intr.height, f, fy, intr.cx, intr.cy, intr.dist)


def _solve_focal(
    intr: Intrinsics, p3: np.ndarray, p2: np.ndarray, pose: Pose
) -> tuple[Intrinsics, Pose]:
    """Focal length and pose together: a coarse focal search, then joint least squares."""
    from scipy.optimize import least_squares

    f0 = intr.fx
    best = (np.inf, f0, pose)
    for f in f0 * np.geomspace(0.5, 2.0, 25):
        cand = _with_focal(intr, f)
        p = _best_pose(cand, p3, p2, _pnp_candidates(cand, p3, p2, pose))
        if p is None:
            continue
        rms = float(np.sqrt(np.mean(reprojection_errors(cand, p, p3, p2) ** 2)))
        if rms < best[0]:
            best = (rms, f, p)
    _, f_start, p_start = best

    def residuals(v: np.ndarray) -> np.ndarray:
        cand = _with_focal(intr, f0 * math.exp(v[6]))
        proj, _ = cv2.projectPoints(p3, v[:3], v[3:6], cand.K, cand.dist_coeffs)
        return (proj.reshape(-1, 2) - p2).ravel()

    v0 = np.concatenate([p_start.rvec, p_start.t, [math.log(f_start / f0)]])
    sol = least_squares(residuals, v0, method="lm", x_scale="jac")
    f = f0 * math.exp(sol.x[6])
    return _with_focal(intr, f), Pose.from_rvec_tvec(sol.x[:3], sol.x[3:6])


def solve_manual(
    intrinsics: Intrinsics,
    photo_points: np.ndarray,
    points_3d: np.ndarray,
    initial: Pose | None = None,
    solve_focal: bool = False,
    threshold_px: float | None = None,
) -> ManualSolution:
    """The photo's pose from manually picked 2D–3D pairs.

    With six or more pairs, RANSAC EPnP with refinement
    (:func:`napari_imgreg.registration.pose.estimate_pose`) sets a mis-picked pair aside;
    with four or five, every pair is used: EPnP, SQPnP and (from ``initial``)
    iterative PnP, each refined by Levenberg–Marquardt, the one with the
    smallest RMS error that keeps all points in front of the camera wins.
    With ``solve_focal`` and six or more agreeing pairs, the focal length
    (square pixels, principal point fixed) is solved with the pose: a
    search over 0.5–2× the current focal length, then joint least squares.

    Parameters
    ----------
    intrinsics : Intrinsics
        The photo's camera.
    photo_points : (N, 2) array
        Picked pixels (x, y) in the photo.
    points_3d : (N, 3) array
        The same points on the model (model frame, metres), e.g. lifted
        through a reference render's ``xyz`` map; rows with NaN are ignored.
    initial : Pose, optional
        A pose near the answer (the prior), used as one more starting point.
    solve_focal : bool
        Also solve the focal length (needs :data:`MIN_PAIRS_FOCAL` pairs).
    threshold_px : float, optional
        A pair agrees with the pose within this many pixels; default 0.8 % of
        the photo width, at least 8 px.

    Returns
    -------
    ManualSolution
        ``ok`` False with a ``reason`` when the pairs do not determine a
        pose (too few, degenerate); never raises for that.

    Notes
    -----
    PnP is degenerate when the points are (nearly) collinear; spread the
    picks over the photo. Solving the focal length needs depth variety:
    with all points on one plane seen square-on, focal length and distance
    trade off.

    Examples
    --------
    >>> import numpy as np
    >>> from napari_imgreg.camera import Intrinsics, Pose
    >>> rng = np.random.default_rng(0)
    >>> intr = Intrinsics(1000, 750, 800.0, 800.0, 499.5, 374.5)
    >>> truth = Pose.from_attitude(10.0, 5.0, 1.0, np.array([0.0, -50.0, 2.0]))
    >>> pts = np.c_[rng.uniform(-20, 20, 8), rng.uniform(-5, 5, 8), rng.uniform(-5, 15, 8)]
    >>> sol = solve_manual(intr, truth.project(intr, pts), pts)
    >>> sol.ok, sol.pose.rotation_error_deg(truth) < 1e-4, sol.rms_px < 1e-6
    (True, True, True)
    """
    p2 = np.asarray(photo_points, np.float64).reshape(-1, 2)
    p3 = np.asarray(points_3d, np.float64).reshape(-1, 3)
    if len(p2) != len(p3):
        raise ValueError(f"{len(p2)} photo points but {len(p3)} 3D points")
    n = len(p2)
    thr = float(threshold_px) if threshold_px else max(8.0, 0.008 * intrinsics.width)
    valid = np.isfinite(p2).all(axis=1) & np.isfinite(p3).all(axis=1)
    nan = np.full(n, np.nan)

    def fail(reason: str) -> ManualSolution:
        return ManualSolution(False, None, intrinsics, nan.copy(), np.zeros(n, bool), thr,
                              reason=reason)

    m = int(valid.sum())
    if m < MIN_PAIRS:
        missing = n - m
        extra = f" ({missing} without a 3D point)" if missing else ""
        return fail(f"{m} usable pairs{extra}: need at least {MIN_PAIRS}")
    q2, q3 = p2[valid], p3[valid]
    centre = q3.mean(axis=0)
    c3 = q3 - centre
    if np.linalg.svd(c3, compute_uv=False)[1] < 1e-6 * max(1.0, np.abs(c3).max()):
        return fail("the picked points are (nearly) on a line: spread them over the photo")

    def uncentre(p: Pose) -> Pose:
        return Pose(p.R, p.t - p.R @ centre)

    def centred(p: Pose) -> Pose:
        return Pose(p.R, p.t + p.R @ centre)

    init_c = centred(initial) if initial is not None else None
    pose_c, method = None, ""
    sel = np.ones(m, bool)
    if m >= 6:
        est = estimate_pose(
            intrinsics, c3, q2,
            PoseParams(reprojection_error_px=thr, iterations=2000, confidence=0.999, refine=True),
        )
        if est.ok:
            pose_c, method, sel = est.pose, "ransac-epnp", est.inliers
    if pose_c is None:
        pose_c = _best_pose(intrinsics, c3, q2, _pnp_candidates(intrinsics, c3, q2, init_c))
        method = "pnp"
        if pose_c is None:
            return fail("no pose keeps all picked points in front of the camera")
    intr = intrinsics
    focal_solved = False
    if solve_focal:
        if int(sel.sum()) < MIN_PAIRS_FOCAL:
            pass  # not enough agreeing pairs: keep the focal length (caller sees focal_solved)
        else:
            intr, pose_c = _solve_focal(intrinsics, c3[sel], q2[sel], pose_c)
            focal_solved = True
    pose = uncentre(pose_c)
    errors = nan.copy()
    errors[valid] = reprojection_errors(intr, pose, q3, q2)
    inliers = np.zeros(n, bool)
    inliers[valid] = errors[valid] < thr
    if not (pose.transform(q3[inliers[valid]])[:, 2] > 0).all():
        return fail("the pose puts picked points behind the camera")
    if inliers.sum() < MIN_PAIRS:
        return fail(f"only {int(inliers.sum())} pairs agree with any pose within {thr:.0f} px")
    return ManualSolution(True, pose, intr, errors, inliers, thr, focal_solved, method)


# ============================================================ filter preview
def reduce_for_matching(
    image: np.ndarray, match_width: int, mask: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """An image (and its mask) at the registration's matching width.

    A wider image is reduced by area averaging, as
    :func:`napari_imgreg.registration.pipeline.register_photo` reduces the photo; a
    narrower one is returned as it is (never enlarged).

    Parameters
    ----------
    image : (H, W, 3) or (H, W) uint8 array
    match_width : int
        ``RegistrationParams.match_width``, pixels.
    mask : (H, W) bool array, optional
        Reduced by nearest neighbour.

    Returns
    -------
    image : (h, w[, 3]) uint8 array
        ``w = min(W, match_width)``.
    mask : (h, w) bool array or None
    """
    h, w = image.shape[:2]
    scale = min(1.0, match_width / w)
    if scale < 1.0:
        size = (int(round(w * scale)), int(round(h * scale)))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        if mask is not None:
            mask = cv2.resize(mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    return image, mask


def filtered_for_matching(
    image: np.ndarray, params, match_width: int, mask: np.ndarray | None = None
) -> np.ndarray:
    """The grey image the feature detector reads, for previewing filters.

    The registration matches at ``match_width`` pixels: the image is first
    reduced (:func:`reduce_for_matching`), then filtered — so a Wallis window
    of 41 pixels means 41 pixels at the matching resolution, as in the
    registration.

    Parameters
    ----------
    image : (H, W, 3) or (H, W) uint8 array
        The photo or a render.
    params : FilterParams
    match_width : int
        Matching width, pixels (``RegistrationParams.match_width``).
    mask : (H, W) bool array, optional
        Valid pixels (a render's surface), reduced with the image.

    Returns
    -------
    (h, w) uint8 array
        At ``min(W, match_width)`` pixels wide.
    """
    from napari_imgreg.registration.filters import apply_filters

    small, small_mask = reduce_for_matching(image, match_width, mask)
    return apply_filters(small, params, mask=small_mask)


# ================================================================ scoring
def score_pose(
    scene,
    photo_rgb: np.ndarray,
    intrinsics: Intrinsics,
    pose: Pose,
    params=None,
    origin: str = "manual",
    cancelled: Callable[[], bool] | None = None,
):
    """Score a given pose with the seven metrics of an automatic trial.

    The model is rendered from ``pose``, photo and render are filtered,
    matched and verified exactly as in a registration round, and the matched
    render keypoints are lifted to 3D; but instead of estimating a pose, the
    *given* pose is tested: a 3D inlier is a correspondence whose 3D point
    projects within ``params.pose.reprojection_error_px`` of its photo
    keypoint, and the reprojection error is their mean. The pose is
    *verified* as in :func:`napari_imgreg.registration.pipeline.register_photo`: enough
    3D inliers and photo and render keypoints coincide (small residual flow);
    an unverified pose is graded "fair" at best.

    Parameters
    ----------
    scene : Scene
    photo_rgb : (H, W, 3) uint8 array
    intrinsics : Intrinsics
        The photo's camera.
    pose : Pose
        The pose to score.
    params : RegistrationParams, optional
        Filters, features, matching width and PnP threshold.
    origin : str
        Stored in the returned trial (``"manual"``).
    cancelled : callable, optional
        Polled between steps; raises :class:`napari_imgreg.registration.pipeline.Cancelled`.

    Returns
    -------
    napari_imgreg.registration.pipeline.Trial
        With ``pose`` set to the given pose, ``rounds`` 0 and the
        correspondences for drawing.
    """
    from napari_imgreg.registration.features import detect_and_describe, match_features
    from napari_imgreg.registration.filters import apply_filters
    from napari_imgreg.registration.params import RegistrationParams
    from napari_imgreg.registration.pipeline import (
        MIN_VERIFIED_INLIERS,
        VERIFY_FLOW_PX,
        Cancelled,
        Correspondences,
        Trial,
    )
    from napari_imgreg.registration.quality import REFERENCE_WIDTH_PX, evaluate_rules, grade_of, quality_q
    from napari_imgreg.render import render

    def check() -> None:
        if cancelled is not None and cancelled():
            raise Cancelled()

    t_start = time.perf_counter()
    params = (params or RegistrationParams()).copy()
    w, h = intrinsics.width, intrinsics.height
    if photo_rgb.shape[:2] != (h, w):
        raise ValueError(
            f"photo is {photo_rgb.shape[1]}×{photo_rgb.shape[0]} but the camera is {w}×{h}")
    scale = min(1.0, params.match_width / w)
    if scale < 1.0:
        size = (int(round(w * scale)), int(round(h * scale)))
        small = cv2.resize(photo_rgb, size, interpolation=cv2.INTER_AREA)
    else:
        small = photo_rgb
    rendered = render(scene, intrinsics, pose, scale=scale)
    check()
    photo_feats = detect_and_describe(apply_filters(small, params.photo_filters), params.features,
                                      color=small)
    check()
    mask = cv2.erode(rendered.mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    gray = apply_filters(rendered.rgb, params.render_filters, mask=rendered.mask)
    render_feats = detect_and_describe(gray, params.features, mask=mask, color=rendered.rgb)
    matches = match_features(photo_feats, render_feats, params.features)
    check()
    if len(matches):
        pp_small = photo_feats.points[matches.idx_a].astype(np.float64)
        rp_small = render_feats.points[matches.idx_b].astype(np.float64)
    else:
        pp_small = rp_small = np.zeros((0, 2))
    inl = matches.inlier
    xyz, lifted = rendered.lift(rp_small)
    lifted &= inl
    sx, sy = rendered.intrinsics.width / w, rendered.intrinsics.height / h

    def to_full(p: np.ndarray) -> np.ndarray:
        return np.stack([(p[:, 0] + 0.5) / sx - 0.5, (p[:, 1] + 0.5) / sy - 0.5], axis=1)

    photo_pts, render_pts = to_full(pp_small), to_full(rp_small)
    err = np.full(len(matches), np.inf)
    if lifted.any():
        err[lifted] = reprojection_errors(intrinsics, pose, xyz[lifted], photo_pts[lifted])
    pose_inlier = lifted & (err < params.pose.reprojection_error_px)
    n_put, n_inl = len(matches), int(inl.sum())
    n_3d, n_pose = int(lifted.sum()), int(pose_inlier.sum())
    flow = (
        float(np.median(np.linalg.norm(photo_pts[pose_inlier] - render_pts[pose_inlier], axis=1)))
        if n_pose >= 3 else float("inf")
    )
    metrics = {
        "points_photo": len(photo_feats),
        "points_render": len(render_feats),
        "putative_matches": n_put,
        "feature_inliers": n_inl,
        "correspondences_3d": n_3d,
        "inlier_ratio_2d": round(n_inl / n_put, 4) if n_put else 0.0,
        "inliers_3d": n_pose,
        "inlier_ratio_3d": round(n_pose / n_3d, 4) if n_3d else 0.0,
        "reprojection_error_px": round(float(err[pose_inlier].mean()), 4) if n_pose else None,
        "render_coverage": round(rendered.coverage, 4),
        "residual_flow_px": round(flow, 3) if math.isfinite(flow) else None,
    }
    verified = n_pose >= MIN_VERIFIED_INLIERS and flow <= VERIFY_FLOW_PX * w / REFERENCE_WIDTH_PX
    q = quality_q(metrics, w)
    grade = grade_of(q, pose_found=True)
    if not verified and grade.name in ("excellent", "good"):
        grade = grade_of(min(q, 0.59))
    hits = evaluate_rules(metrics, params, w)
    hints = [hit.hint for hit in hits]
    if not verified:
        hints.append(
            f"Photo and render from this pose disagree (residual flow "
            f"{flow:.1f} px, {n_pose} 3D inliers): pose not verified."
        )
    return Trial(
        index=-1,
        params=params,
        metrics=metrics,
        q=q,
        grade=grade.name,
        hints=hints,
        pose=pose,
        start_pose=pose,
        rounds=0,
        converged=True,
        verified=bool(verified),
        residual_flow_px=flow,
        origin=origin,
        seconds=time.perf_counter() - t_start,
        correspondences=Correspondences(photo_pts, render_pts, inl, lifted, pose_inlier),
    )


def metric_trend(metric, value: float | None, previous: float | None) -> int:
    """Whether a metric got better (+1), worse (−1) or stayed (0) since the previous trial.

    Parameters
    ----------
    metric : napari_imgreg.registration.quality.Metric
        Knows whether lower is better (the reprojection error).
    value, previous : float or None
        A missing (None/NaN) value is the worst possible.
    """
    def known(v) -> bool:
        return v is not None and v == v

    if not known(value) and not known(previous):
        return 0
    if not known(previous):
        return 1
    if not known(value):
        return -1
    if math.isclose(float(value), float(previous), rel_tol=1e-9, abs_tol=1e-12):
        return 0
    up = float(value) > float(previous)
    return (-1 if up else 1) if metric.lower_is_better else (1 if up else -1)


# ============================================================== sidecar I/O
def save_pose_to_record(
    path: str | os.PathLike, pose: Pose, camera: Intrinsics | None = None
) -> dict:
    """Write a pose into a sensor record (``PHOTO.json``) atomically.

    The record's ``position`` becomes the local ``{"x", "y", "z"}`` of the
    camera centre and its ``orientation`` the pose's trend, plunge and roll
    (contract §3); every other field (``sigma``, unknown extras) is kept. A
    missing file is created. With ``camera``, the ``camera`` block is
    replaced by its pixel form (a solved focal length).

    Parameters
    ----------
    path : path-like
        The sidecar JSON beside the photo.
    pose : Pose
    camera : Intrinsics, optional

    Returns
    -------
    dict
        What was written.

    Raises
    ------
    InputError
        The existing file is not a JSON object.
    """
    from napari_imgreg._atomic import atomic_write

    path = Path(path)
    data: dict = {}
    if path.exists():
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise input_error(path, f"cannot read the sensor record ({exc})") from None
        if not isinstance(data, dict):
            raise input_error(path, "a sensor record must be a JSON object")
    trend, plunge, roll = pose.attitude
    x, y, z = (float(v) for v in pose.center)
    data["position"] = {"x": x, "y": y, "z": z}
    data["orientation"] = {"trend_deg": trend, "plunge_deg": plunge, "roll_deg": roll}
    if camera is not None:
        data["camera"] = camera.to_dict()
    with atomic_write(path, encoding="utf-8") as fh:
        json.dump(data, fh, indent=1)
        fh.write("\n")
    return data
