"""Hand corrections of a pose: nudges, moves on the terrain map, undo and redo.

The arithmetic behind the workbench's pose editing, kept free of Qt and
napari so that a script or a test can drive it: :func:`nudge_pose` turns and
moves a camera as a geologist thinks of it (trend, plunge, roll; forward,
right, up), :func:`pose_at_ground` and :func:`turn_toward` are what a click
on the map does, :class:`PoseHistory` undoes and redoes edits, and
:func:`terrain_map` is the hillshaded height raster the map shows.

Conventions are the package's: the model frame is local ENU metres (x east,
y north, z up); poses are ``cam_from_world``
(:class:`~napari_imgreg.camera.Pose`); attitudes follow contract §2 (trend
clockwise from north, plunge positive downward).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .camera import Pose
from .errors import InputError
from .scene import Scene

__all__ = [
    "nudge_pose",
    "pose_at_ground",
    "height_above_ground",
    "turn_toward",
    "PoseHistory",
    "TerrainMap",
    "terrain_map",
]


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
        """(dx, dy) pixel spacing, metres. A raster one row or column wide
        (a model flat in plan, such as a vertical wall seen from above) has
        square pixels: the other axis's spacing (else its map has no height)."""
        rows, cols = self.heights.shape
        xmin, xmax, ymin, ymax = self.extent
        dx = (xmax - xmin) / (cols - 1) if cols > 1 else 0.0
        dy = (ymax - ymin) / (rows - 1) if rows > 1 else 0.0
        return (dx or dy or 1.0), (dy or dx or 1.0)

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
        # Rows run south: d/dy (north) is minus the row gradient. A map one
        # cell deep (a thin wall seen from above) is flat along that axis.
        dz_row = (np.gradient(filled, dy or 1.0, axis=0) if filled.shape[0] > 1
                  else np.zeros_like(filled))
        dz_col = (np.gradient(filled, dx or 1.0, axis=1) if filled.shape[1] > 1
                  else np.zeros_like(filled))
        dzdx, dzdy = dz_col, -dz_row
        az, alt = math.radians(azimuth_deg), math.radians(altitude_deg)
        light = np.array(
            [math.sin(az) * math.cos(alt), math.cos(az) * math.cos(alt), math.sin(alt)])
        normal = np.stack([-dzdx, -dzdy, np.ones_like(filled)], axis=-1)
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        shade = np.clip(normal @ light, 0.0, 1.0)
        return np.where(np.isfinite(z), shade, np.nan)


def terrain_map(scene: Scene, max_cells: int = 400) -> TerrainMap:
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
    if getattr(scene, "is_cloud", False):  # the highest point per cell (no rays needed)
        z = np.asarray(scene.height_grid(xs, ys), np.float64)
        return TerrainMap(z, (xs[0], xs[-1], ys[-1], ys[0]), "model")
    X, Y = np.meshgrid(xs, ys)
    top = z1 + 10.0
    origins = np.stack([X.ravel(), Y.ravel(), np.full(X.size, top)], axis=1)
    dirs = np.tile(np.array([[0.0, 0.0, -1.0]]), (X.size, 1))
    hits = scene.cast_rays(origins, dirs)
    z = np.where(hits.hit, top - hits.distance, np.nan).reshape(X.shape)
    return TerrainMap(z.astype(np.float64), (xs[0], xs[-1], ys[-1], ys[0]), "model")
