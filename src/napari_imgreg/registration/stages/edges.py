"""Structure edges of renders and photos, and camera pose by chamfer alignment.

Keypoint matching needs the photo and the render to *look* alike; edges of
structure need much less. The skyline and the occluding contours of a render
are where the photo's sky ends and where near rock hides far rock, under any
sun; creases and strata contacts follow. This module extracts

* the **structure edges of a render** (:func:`render_edges`): depth
  discontinuities (skyline against the empty sky, occluding contours between
  surfaces), normal discontinuities (creases) and, when the render has colour,
  strong albedo edges — each pixel lifted to 3D through the render's ``xyz``
  map on the *near* side of a depth edge, where the 3D point belongs to the
  surface that draws the contour;
* the **edges of a photo** (:func:`photo_edges`): Canny on a blurred grey image
  with thresholds from the image's own gradient percentiles (so they adapt to
  light and exposure), the skyline of the bright low-texture sky at the top
  (:func:`detect_skyline`), their orientations and distance transforms;

and registers the photo by **chamfer alignment** (:func:`align_edges`):

1. *Turn.* A rotation of the camera about its centre moves every image point
   by a homography, so the render's 3D edge points are re-projected, not
   re-rendered: a grid of heading, tilt and roll offsets about the start is
   scored at a small size (truncated mean distance to the photo's edges) and
   the best few are polished on a finer grid and by least squares on the
   distance field.
2. *Step.* A sideways step and a turn look alike from afar; the parallax of
   near edges against far ones tells them apart. A pattern search over
   horizontal steps turns the camera to fit after each step, on a fresh
   render.
3. *Refine.* At finer sizes, closest-edge rounds (each projected edge point
   paired with the nearest photo edge pixel of its orientation through the
   distance transform's labels, point-to-line distances under a Cauchy loss,
   a weak prior on the position) refine all six degrees of freedom,
   re-rendering between rounds: a contour of a rounded surface slides over it
   as the camera moves. The last round's pairs are returned as 2D–3D
   correspondences for the quality metrics.

:func:`edge_score` measures how much better than chance a pose's structure
edges land on the photo's edges, to verify a pose however it was found.

The edge-map idea adapts the wireframe-to-Canny matching of Morago et al.,
who render depth and normal discontinuities of lidar scans of rock cuts, to
natural outcrops, where the skyline carries most of the structure.

References
----------
B. Morago, G. Bui, T. Le, N. H. Maerz, Y. Duan, "Photograph-LIDAR
registration methodology for rock discontinuity measurement", IEEE
Geoscience and Remote Sensing Letters.
H. G. Barrow, J. M. Tenenbaum, R. C. Bolles, H. C. Wolf, "Parametric
correspondence and chamfer matching: two new techniques for image
matching", IJCAI 1977.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, ClassVar

import cv2
import numpy as np
from scipy import ndimage
from scipy.optimize import least_squares

from ...camera import Intrinsics, Pose, match_scale, pixels_to_full
from ...validate import StageParams
from .pyramid import (
    PyramidLevel,
    RenderFn,
    as_render_fn,
    check_ranges,
    level_widths,
    resize_to,
    sample_bilinear,
    scene_renderer,
    with_keywords,
)
from ...render import RenderResult
from ...scene import Scene

__all__ = [
    "SKYLINE",
    "OCCLUDING",
    "CREASE",
    "ALBEDO",
    "MODEL_BORDER",
    "EDGE_KINDS",
    "DEFAULT_KIND_WEIGHTS",
    "REFERENCE_WIDTH",
    "EdgeParams",
    "EdgeSet",
    "PhotoEdges",
    "EdgeCorrespondences",
    "EdgeAlignment",
    "EdgeAgreement",
    "render_edges",
    "canny_edges",
    "detect_skyline",
    "line_segments",
    "photo_edges",
    "chamfer_distances",
    "align_edges",
    "edge_agreement",
    "edge_score",
]

# ------------------------------------------------------------ edge kinds
#: The surface against the sky (misses connected to the top of the render).
SKYLINE = 1
#: Near surface in front of a farther one (a depth jump on the surface).
OCCLUDING = 2
#: Normal discontinuity without a depth jump.
CREASE = 3
#: Strong colour edge of the texture (strata contacts, staining).
ALBEDO = 4
#: The surface against a hole or the edge of the model (not in the photo).
MODEL_BORDER = 5
EDGE_KINDS = {
    SKYLINE: "skyline",
    OCCLUDING: "occluding",
    CREASE: "crease",
    ALBEDO: "albedo",
    MODEL_BORDER: "model_border",
}
#: Default weight of each kind in chamfer scores. The skyline is the same
#: under any light and never repeats (strata do: a pose one bed too high fits
#: their edges nearly as well); a contour between two stretches of the same
#: ground, a crease and a colour edge may or may not show in the photo. The
#: model's own border is not in the photo at all.
DEFAULT_KIND_WEIGHTS = {SKYLINE: 2.0, OCCLUDING: 0.5, CREASE: 0.5, ALBEDO: 0.5, MODEL_BORDER: 0.0}

#: Distances are reported in pixels at this image width (the benchmarks'
#: photo width), whatever size the alignment ran at.
REFERENCE_WIDTH = 1632

#: Scale of the Cauchy loss of the pose refinement, px at the reference width.
_ROBUST_REF_PX = 4.0

#: Orientation bins of the oriented distance transforms over [0, π).
_ORIENTATION_BINS = 8


# ================================================================ edge sets
@dataclass
class EdgeSet:
    """Structure edge points of a render.

    Attributes
    ----------
    points_px : (N, 2) float64 array
        Pixel positions (x, y) in the render.
    xyz : (N, 3) float64 array
        Model-frame points behind them, metres (the near surface at depth
        edges).
    kind : (N,) uint8 array
        :data:`SKYLINE`, :data:`OCCLUDING`, :data:`CREASE`, :data:`ALBEDO` or
        :data:`MODEL_BORDER`.
    weight : (N,) float32 array
        Weight in chamfer scores (:data:`DEFAULT_KIND_WEIGHTS` by default).
    orientation : (N,) float32 array
        Direction of the edge's normal in the image, radians in [0, π)
        (0: a vertical edge, brightness changing along x).
    image_size : (int, int)
        (width, height) of the render.
    """

    points_px: np.ndarray
    xyz: np.ndarray
    kind: np.ndarray
    weight: np.ndarray
    orientation: np.ndarray
    image_size: tuple[int, int]

    def __len__(self) -> int:
        return len(self.kind)

    def select(self, keep: np.ndarray) -> EdgeSet:
        """The subset where ``keep`` (bool mask or indices) selects."""
        return EdgeSet(
            self.points_px[keep], self.xyz[keep], self.kind[keep], self.weight[keep],
            self.orientation[keep], self.image_size,
        )

    def counts(self) -> dict[str, int]:
        """Number of points of each kind, by name."""
        return {name: int((self.kind == k).sum()) for k, name in EDGE_KINDS.items()}

    def thinned(self, max_points: int) -> EdgeSet:
        """At most ``max_points``, the most telling kinds first.

        Skyline and occluding contours (few, and the same under any light)
        are kept up to half the budget; creases and albedo edges share the
        rest. Within a kind, points are decimated evenly along the raster
        order (deterministic, and spread over the image).
        """
        if len(self) <= max_points:
            return self
        keep = np.zeros(len(self), bool)
        budget = max_points
        groups = [np.isin(self.kind, (SKYLINE, OCCLUDING)), self.kind == CREASE,
                  self.kind == ALBEDO, self.kind == MODEL_BORDER]
        idx = [np.flatnonzero(g) for g in groups]
        first = min(len(idx[0]), max_points // 2)
        keep[_even_subset(idx[0], first)] = True
        budget -= first
        # Creases and albedo: half each, what one does not use goes to the other.
        n_crease = min(len(idx[1]), max(budget // 2, budget - len(idx[2])))
        keep[_even_subset(idx[1], n_crease)] = True
        budget -= n_crease
        n_albedo = min(len(idx[2]), budget)
        keep[_even_subset(idx[2], n_albedo)] = True
        budget -= n_albedo
        keep[_even_subset(idx[3], budget)] = True
        return self.select(keep)


def _even_subset(idx: np.ndarray, k: int) -> np.ndarray:
    """``k`` of ``idx`` spread evenly (all when there are fewer)."""
    if k <= 0:
        return idx[:0]
    if len(idx) <= k:
        return idx
    return idx[np.linspace(0, len(idx) - 1, k).round().astype(int)]


def render_edges(
    rendered: RenderResult,
    *,
    depth_jump: float = 0.05,
    slope_factor: float = 3.0,
    crease_deg: float = 35.0,
    albedo: bool | None = None,
    albedo_percentile: float = 90.0,
    min_facing: float = 0.25,
    weights: dict[int, float] | None = None,
    border_px: int = 2,
    max_points: int | None = None,
) -> EdgeSet:
    """Structure edges of a render, lifted to 3D.

    Parameters
    ----------
    rendered : RenderResult
        Any render (colour or shaded).
    depth_jump : float
        Relative depth jump that makes an occluding edge: the far side is at
        least ``1 + depth_jump`` times as deep as the near side. Measured on
        inverse depth, which is linear across a plane, so a grazing ground
        plane whose depth grows fast from pixel to pixel is no edge: the jump
        must also exceed ``slope_factor`` times the steps beside it.
    slope_factor : float
        See ``depth_jump``.
    crease_deg : float
        Angle between the surface normals on either side of a crease, degrees.
    albedo : bool, optional
        Include colour edges; by default only when the render has colour
        (a grey shaded render's edges are its light's, not the rock's).
    albedo_percentile : float
        Colour edges are Canny edges whose upper threshold is this percentile
        of the gradient magnitude over the surface.
    min_facing : float
        Colour edges only where the surface faces the camera at least this
        much (cosine of the angle between normal and line of sight): texture
        seen at a grazing angle is smeared differently from every viewpoint.
    weights : dict, optional
        Weight per kind (:data:`DEFAULT_KIND_WEIGHTS`).
    border_px : int
        Ignore edges this close to the image frame (the frame cuts the
        surface; that is not an edge of the rock).
    max_points : int, optional
        Thin to at most this many points (:meth:`EdgeSet.thinned`).

    Returns
    -------
    EdgeSet
        Points at pixel centres of the render (at a depth edge: the near-side
        pixel, so its ``xyz`` is on the occluding surface).
    """
    h, w = rendered.shape
    mask = rendered.mask
    weights = {**DEFAULT_KIND_WEIGHTS, **(weights or {})}
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_depth = np.where(mask, np.float32(1.0) / rendered.depth, np.float32(0.0))
    inv_depth = np.nan_to_num(inv_depth, nan=0.0, posinf=0.0)

    # Misses connected to the top of the image are sky; others are holes in
    # the model or beyond its edges.
    _, miss_labels = cv2.connectedComponents((~mask).astype(np.uint8), connectivity=4)
    sky_labels = np.unique(miss_labels[0][~mask[0]])
    sky = np.isin(miss_labels, sky_labels) & ~mask

    kind = np.zeros((h, w), np.uint8)
    far_is_miss = np.zeros((h, w), bool)
    far_is_sky = np.zeros((h, w), bool)
    for axis in (0, 1):
        near, far_miss, far_sky = _depth_edges_along(inv_depth, mask, sky, axis, depth_jump,
                                                     slope_factor)
        kind[near] = OCCLUDING
        far_is_miss |= far_miss
        far_is_sky |= far_sky
    kind[far_is_miss] = MODEL_BORDER
    kind[far_is_sky] = SKYLINE  # sky wins over a model border at the same pixel

    # Creases: Canny on the normal field (3 channels; Canny keeps the channel
    # with the strongest change), away from depth edges, whose normals jump too.
    depth_edge = kind > 0
    near_depth_edge = cv2.dilate(depth_edge.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    inner = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    crease = _crease_edges(rendered.normal, crease_deg) & inner & ~near_depth_edge
    kind[crease] = CREASE

    if albedo is None:
        rgb = rendered.rgb[mask]
        albedo = bool(len(rgb)) and bool(
            (np.abs(rgb[:, 0].astype(int) - rgb[:, 1]) > 2).mean() > 0.05
            or (np.abs(rgb[:, 1].astype(int) - rgb[:, 2]) > 2).mean() > 0.05
        )
    albedo_orientation = None
    if albedo:
        gray = cv2.cvtColor(rendered.rgb, cv2.COLOR_RGB2GRAY)
        colour_edges, albedo_orientation = canny_edges(
            gray, sigma=_edge_sigma(w), high_percentile=albedo_percentile, mask=inner
        )
        near_crease = cv2.dilate(crease.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        rows, cols = np.nonzero(colour_edges & inner & ~near_depth_edge & ~near_crease)
        # Texture seen at a grazing angle (the ground before the camera) is
        # smeared differently in every view: its edges move with the camera.
        facing = _facing(rendered, rows, cols) >= min_facing
        kind[rows[facing], cols[facing]] = ALBEDO

    if border_px > 0:
        kind[:border_px] = 0
        kind[-border_px:] = 0
        kind[:, :border_px] = 0
        kind[:, -border_px:] = 0
    kind[~mask] = 0

    rows, cols = np.nonzero(kind)
    k = kind[rows, cols]
    xyz = rendered.xyz[rows, cols].astype(np.float64)
    finite = np.isfinite(xyz).all(axis=1)
    rows, cols, k, xyz = rows[finite], cols[finite], k[finite], xyz[finite]
    orientation = _curve_normal_orientation(kind > 0, rows, cols)
    if albedo_orientation is not None:
        # Colour edges carry their own gradient direction, better than the
        # shape of a short curve.
        is_alb = k == ALBEDO
        orientation[is_alb] = albedo_orientation[rows[is_alb], cols[is_alb]]
    wt = np.array([weights.get(int(i), 0.0) for i in range(256)], np.float32)[k]
    edges = EdgeSet(
        points_px=np.stack([cols, rows], axis=1).astype(np.float64),
        xyz=xyz,
        kind=k.astype(np.uint8),
        weight=wt,
        orientation=orientation.astype(np.float32),
        image_size=(w, h),
    )
    if max_points is not None:
        edges = edges.thinned(max_points)
    return edges


def _facing(rendered: RenderResult, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Cosine between the surface normal and the direction to the camera at
    the given pixels, (N,)."""
    to_camera = rendered.cam_from_world.center - rendered.xyz[rows, cols].astype(np.float64)
    norm = np.linalg.norm(to_camera, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.einsum("nk,nk->n", rendered.normal[rows, cols], to_camera) / norm
    return np.nan_to_num(cos, nan=0.0)


def _depth_edges_along(
    inv_depth: np.ndarray, mask: np.ndarray, sky: np.ndarray, axis: int,
    depth_jump: float, slope_factor: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Near-side pixels of inverse-depth jumps between neighbours along ``axis``.

    Returns three (H, W) bool maps: near-side pixels of all jumps, of jumps
    to a miss, of jumps to the sky.
    """
    g = inv_depth if axis == 1 else inv_depth.T
    m = mask if axis == 1 else mask.T
    s = sky if axis == 1 else sky.T
    step = np.diff(g, axis=1)  # step[:, i] = g[:, i+1] - g[:, i]
    # The steps on either side predict a smooth surface's step here.
    padded = np.pad(np.abs(step), ((0, 0), (1, 1)), mode="edge")
    beside = 0.5 * (padded[:, :-2] + padded[:, 2:])
    a, b = g[:, :-1], g[:, 1:]
    nearer = np.maximum(a, b)
    jump = (np.abs(step) > slope_factor * beside + depth_jump * nearer) & (nearer > 0)
    a_near = jump & (a > b)  # pixel i is the near side
    b_near = jump & (b > a)  # pixel i+1 is
    near = np.zeros(g.shape, bool)
    near[:, :-1] |= a_near
    near[:, 1:] |= b_near
    far_miss = np.zeros(g.shape, bool)
    far_miss[:, :-1] |= a_near & ~m[:, 1:]
    far_miss[:, 1:] |= b_near & ~m[:, :-1]
    far_sky = np.zeros(g.shape, bool)
    far_sky[:, :-1] |= a_near & s[:, 1:]
    far_sky[:, 1:] |= b_near & s[:, :-1]
    if axis == 0:
        near, far_miss, far_sky = near.T, far_miss.T, far_sky.T
    return near, far_miss, far_sky


def _crease_edges(normal: np.ndarray, crease_deg: float, sigma: float = 1.0) -> np.ndarray:
    """Thin lines where the (smoothed) normal field turns by ``crease_deg`` or more."""
    n = cv2.GaussianBlur(normal.astype(np.float32), (0, 0), sigma)
    # A normal step of |Δn| = 2 sin(α/2) blurred by a Gaussian of width σ has
    # a peak derivative of |Δn| / (σ √(2π)); Sobel scales a derivative by 8.
    # Canny takes int16 derivatives: scale the unit normals by 1000.
    scale = 1000.0
    dn = 2.0 * math.sin(math.radians(crease_deg) / 2.0)
    high = 8.0 * scale * dn / (sigma * math.sqrt(2 * math.pi))
    high *= 0.5  # one channel sees only part of the turn (≥ 1/√3 of it)
    dx = cv2.Sobel(n * scale, cv2.CV_32F, 1, 0, ksize=3)
    dy = cv2.Sobel(n * scale, cv2.CV_32F, 0, 1, ksize=3)
    dx = np.clip(dx, -32767, 32767).astype(np.int16)
    dy = np.clip(dy, -32767, 32767).astype(np.int16)
    return cv2.Canny(dx, dy, 0.5 * high, high, L2gradient=True) > 0


def _curve_normal_orientation(edge_map: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                              sigma: float = 1.5) -> np.ndarray:
    """Direction of the normal of the edge curves through given pixels, [0, π).

    From the structure tensor of the blurred edge map: across a thin curve
    the map changes most along the curve's normal.
    """
    e = cv2.GaussianBlur(edge_map.astype(np.float32), (0, 0), sigma)
    gx = cv2.Sobel(e, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(e, cv2.CV_32F, 0, 1, ksize=3)
    jxx = cv2.GaussianBlur(gx * gx, (0, 0), sigma)
    jyy = cv2.GaussianBlur(gy * gy, (0, 0), sigma)
    jxy = cv2.GaussianBlur(gx * gy, (0, 0), sigma)
    angle = 0.5 * np.arctan2(2.0 * jxy[rows, cols], jxx[rows, cols] - jyy[rows, cols])
    return np.mod(angle, np.pi)


def _edge_sigma(width: int) -> float:
    """Gaussian blur before Canny, pixels: 2 px at 768 px width, never below 1."""
    return max(1.0, 2.0 * width / 768.0)


# =============================================================== photo edges
def canny_edges(
    gray: np.ndarray,
    sigma: float = 2.0,
    high_percentile: float = 85.0,
    low_ratio: float = 0.4,
    mask: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Canny edges with thresholds from the image's own gradient distribution.

    Parameters
    ----------
    gray : (H, W) uint8 array
    sigma : float
        Gaussian blur before differentiation, pixels (suppresses grain and
        fine texture: what is left are the contacts and outlines).
    high_percentile : float
        Upper hysteresis threshold: this percentile of the gradient magnitude
        (over ``mask``), so a dim or flat-lit photo gets as many edges as a
        contrasty one.
    low_ratio : float
        Lower threshold as a fraction of the upper.
    mask : (H, W) bool array, optional
        Pixels whose gradients set the thresholds.

    Returns
    -------
    edges : (H, W) bool array
    orientation : (H, W) float32 array
        Gradient direction (the edge normal), radians in [0, π).
    """
    g = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), sigma) if sigma > 0 else gray.astype(
        np.float32)
    dx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
    dy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    mag = cv2.magnitude(dx, dy)
    sel = mag[mask] if mask is not None else mag
    high = float(np.percentile(sel, high_percentile)) if sel.size else 0.0
    high = max(high, 2.0)  # a flat image has no edges, not rounding noise
    # Canny wants int16 derivatives; scale so the strongest fit.
    k = min(1.0, 32000.0 / max(float(mag.max()), 1e-6))
    edges = cv2.Canny(
        (dx * k).astype(np.int16), (dy * k).astype(np.int16),
        low_ratio * high * k, high * k, L2gradient=True,
    ) > 0
    orientation = np.mod(np.arctan2(dy, dx), np.pi).astype(np.float32)
    return edges, orientation


def detect_skyline(
    photo_rgb: np.ndarray,
    work_width: int = 256,
    min_columns: float = 0.15,
) -> tuple[np.ndarray, np.ndarray]:
    """The sky of a photo and the row where it ends in every column.

    A pixel looks like sky when it is smooth and either clearly blue or
    bright and neutral (cloud, overcast). Each column's skyline is the row
    that best splits it into sky-like above and not below (the maximum of the
    cumulative sky evidence from the top, so a cloud or a bird does not end
    the sky), found on a small copy, then snapped to the strongest downward
    change of brightness or blueness within a few pixels at full resolution.

    Parameters
    ----------
    photo_rgb : (H, W, 3) uint8 array
    work_width : int
        Width at which sky-likeness is judged (speed and robustness).
    min_columns : float
        Fraction of the columns that must show sky; below it no skyline is
        reported.

    Returns
    -------
    skyline : (W,) float32 array
        Row of the first non-sky pixel per column; NaN where the column shows
        no sky.
    sky : (H, W) bool array
        Pixels above the skyline.
    """
    h, w = photo_rgb.shape[:2]
    s = match_scale(w, work_width)
    small = photo_rgb if s == 1.0 else cv2.resize(
        photo_rgb, (max(8, round(w * s)), max(8, round(h * s))), interpolation=cv2.INTER_AREA)
    sh, sw = small.shape[:2]
    rgb = small.astype(np.float32)
    gray = rgb.mean(axis=2)
    mean = cv2.blur(gray, (5, 5))
    std = np.sqrt(np.maximum(cv2.blur(gray * gray, (5, 5)) - mean * mean, 0.0))
    blueness = rgb[..., 2] - rgb[..., 0]
    # Cloud rims are textured at this size, rock more so.
    smooth = std <= max(16.0, float(np.median(std)))
    bright = mean >= np.percentile(mean, 70)
    sky_like = smooth & ((blueness >= 20) | ((blueness >= -5) & bright))
    # Per column: the row r maximising (sky-like above r) - (not sky-like above r).
    evidence = np.cumsum(np.where(sky_like, 1.0, -1.0), axis=0)
    evidence = np.vstack([np.zeros((1, sw)), evidence])  # row r: evidence of rows < r
    split = np.argmax(evidence, axis=0)  # rows of sky from the top
    # A cloud resting on the skyline can drag single columns up or down.
    split = ndimage.median_filter(split, size=5, mode="nearest")
    purity = evidence[split, np.arange(sw)] / np.maximum(split, 1)
    # Sky needs ground below it: an image that is all smooth and bright
    # (a blank, a wall of fog) has no skyline.
    has_sky_small = ((split >= max(2, round(0.02 * sh))) & (split <= sh - 2)
                     & (purity >= 0.5))
    if has_sky_small.mean() < min_columns:
        return np.full(w, np.nan, np.float32), np.zeros((h, w), bool)
    # Up to full resolution; snap to the strongest change (sky above, ground
    # below) within the uncertainty of the small image.
    col_small = np.clip((np.arange(w) + 0.5) * sw / w - 0.5, 0, sw - 1)
    rough = np.interp(col_small, np.arange(sw), split.astype(np.float64)) / s
    has_sky = np.interp(col_small, np.arange(sw), has_sky_small.astype(np.float64)) > 0.5
    full = photo_rgb.astype(np.float32)
    change = np.zeros((h, w), np.float32)
    for channel in (full.mean(axis=2), full[..., 2] - full[..., 0]):
        # Smoothed down the column only: mixing in the neighbouring columns
        # would pull the change up a steep skyline.
        blurred = cv2.GaussianBlur(channel, (1, 5), sigmaX=0.0, sigmaY=1.0)
        change[1:] += np.abs(np.diff(blurred, axis=0))  # row r: between r-1 and r
    # The texture window (5 px) rims the sky with ~2 px judged "not smooth",
    # so the rough skyline sits high: search mostly below it.
    above, below = math.ceil(2.0 / s) + 1, math.ceil(5.0 / s) + 1
    rows = np.arange(h)[:, None]
    offset = rows - rough[None, :]
    window = (offset >= -above) & (offset <= below) & (rows > 0)
    # The strongest change is from the last sky pixel to the first ground one.
    snapped = np.argmax(np.where(window, change, -1.0), axis=0).astype(np.float64)
    skyline = np.where(has_sky, snapped, np.nan)
    finite = np.isfinite(skyline)
    if finite.any():
        # A median of three neighbouring columns removes single-column spikes.
        filled = np.interp(np.arange(w), np.flatnonzero(finite), skyline[finite])
        skyline = np.where(finite, ndimage.median_filter(filled, size=3, mode="nearest"), np.nan)
    sky = rows < np.where(finite, skyline, 0.0)[None, :]
    return skyline.astype(np.float32), sky


def line_segments(gray: np.ndarray, min_length_px: float = 20.0) -> np.ndarray:
    """Straight segments of a grey image (OpenCV's LSD detector).

    Parameters
    ----------
    gray : (H, W) uint8 array
    min_length_px : float
        Shorter segments are dropped.

    Returns
    -------
    (M, 4) float32 array
        Segments ``x1, y1, x2, y2`` in pixels; empty when the installed
        OpenCV has no LSD.
    """
    try:
        lsd = cv2.createLineSegmentDetector()
        lines = lsd.detect(gray)[0]
    except (cv2.error, AttributeError):  # removed from some OpenCV 4.x builds
        return np.zeros((0, 4), np.float32)
    if lines is None:
        return np.zeros((0, 4), np.float32)
    lines = lines.reshape(-1, 4)
    length = np.hypot(lines[:, 2] - lines[:, 0], lines[:, 3] - lines[:, 1])
    return lines[length >= min_length_px].astype(np.float32)


@dataclass
class PhotoEdges:
    """A photo's edges, their orientations and distance transforms.

    Attributes
    ----------
    edges : (H, W) bool array
        Canny edges and the skyline.
    orientation : (H, W) float32 array
        Edge normal direction, radians in [0, π) (meaningful on edges).
    oriented_distance : (B, H, W) float32 array
        Distance (px) to the nearest edge pixel whose orientation is within
        about ±1.5 bins of bin ``b`` (B = 8 bins over [0, π)).
    distance : (H, W) float32 array
        Distance to the nearest edge pixel of any orientation, px.
    skyline : (W,) float32 array
        Row of the first non-sky pixel per column; NaN without sky.
    sky : (H, W) bool array
    sky_distance : (H, W) float32 array or None
        Distance to the skyline, px (None when no skyline was found).
    sky_edge : (H, W) bool array
        The first ground pixels next to the sky.
    """

    edges: np.ndarray
    orientation: np.ndarray
    oriented_distance: np.ndarray
    distance: np.ndarray
    skyline: np.ndarray
    sky: np.ndarray
    sky_distance: np.ndarray | None
    sky_edge: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width)."""
        return self.edges.shape

    @property
    def has_skyline(self) -> bool:
        return self.sky_distance is not None


def photo_edges(
    photo: np.ndarray,
    *,
    sigma: float | None = None,
    high_percentile: float = 85.0,
    low_ratio: float = 0.4,
    skyline: bool = True,
    lines: bool = False,
) -> PhotoEdges:
    """Edges of a photo for chamfer matching.

    Parameters
    ----------
    photo : (H, W, 3) or (H, W) uint8 array
        RGB (the skyline needs colour) or grey.
    sigma : float, optional
        Blur before Canny, pixels (default: 2 px at 768 px width, scaled).
    high_percentile, low_ratio : float
        Canny thresholds from the gradient distribution (:func:`canny_edges`).
    skyline : bool
        Find the skyline (:func:`detect_skyline`) and add it to the edges.
    lines : bool
        Add LSD line segments (:func:`line_segments`) of at least 3 % of the
        width: long straight contacts that Canny breaks up.

    Returns
    -------
    PhotoEdges
    """
    h, w = photo.shape[:2]
    gray = photo if photo.ndim == 2 else cv2.cvtColor(photo, cv2.COLOR_RGB2GRAY)
    sigma = _edge_sigma(w) if sigma is None else sigma
    sky_line = np.full(w, np.nan, np.float32)
    sky = np.zeros((h, w), bool)
    if skyline and photo.ndim == 3:
        sky_line, sky = detect_skyline(photo)
    edges, orientation = canny_edges(gray, sigma, high_percentile, low_ratio,
                                     mask=~sky if sky.any() else None)
    edges[sky] = False  # cloud outlines are not the model's
    if lines:
        seg = line_segments(gray, min_length_px=0.03 * w)
        canvas = np.zeros((h, w), np.int32)  # segment index + 1
        for i, (x1, y1, x2, y2) in enumerate(seg):
            cv2.line(canvas, (int(round(x1)), int(round(y1))), (int(round(x2)), int(round(y2))),
                     i + 1, 1)
        extra = (canvas > 0) & ~edges & ~sky
        # A segment's normal is its direction turned by 90°.
        seg_normal = np.mod(np.arctan2(seg[:, 3] - seg[:, 1], seg[:, 2] - seg[:, 0]) + np.pi / 2,
                            np.pi)
        orientation[extra] = seg_normal[canvas[extra] - 1]
        edges |= extra
    sky_distance = None
    sky_edge = np.zeros((h, w), bool)
    if sky.any():
        # The first ground pixels next to the sky, also along the vertical
        # steps of the skyline (the side of a pinnacle, a box).
        cross = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8)
        sky_edge = ~sky & (cv2.dilate(sky.astype(np.uint8), cross) > 0)
        sky_distance = _distance_to(sky_edge)
        sky_orient = _curve_normal_orientation(sky_edge, *np.nonzero(sky_edge))
        orientation = orientation.copy()
        orientation[sky_edge] = sky_orient
        edges |= sky_edge
    oriented = _oriented_distances(edges, orientation)
    return PhotoEdges(
        edges=edges,
        orientation=orientation,
        oriented_distance=oriented,
        distance=_distance_to(edges),
        skyline=sky_line,
        sky=sky,
        sky_distance=sky_distance,
        sky_edge=sky_edge,
    )


def _distance_to(edge_map: np.ndarray) -> np.ndarray:
    """Euclidean distance (px) from every pixel to the nearest True pixel."""
    if not edge_map.any():
        return np.full(edge_map.shape, 1e4, np.float32)
    src = np.where(edge_map, 0, 255).astype(np.uint8)
    return cv2.distanceTransform(src, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def _orientation_bin(angle: np.ndarray) -> np.ndarray:
    return (np.mod(angle, np.pi) / np.pi * _ORIENTATION_BINS).astype(int) % _ORIENTATION_BINS


def _oriented_distances(edges: np.ndarray, orientation: np.ndarray) -> np.ndarray:
    """One distance transform per orientation bin, (B, H, W) float32.

    Bin ``b`` holds the edge pixels of bins b-1, b and b+1 (orientations
    modulo π), so a render edge matches photo edges within ~±34° of it.
    """
    bins = np.where(edges, _orientation_bin(orientation), -1)
    out = np.empty((_ORIENTATION_BINS, *edges.shape), np.float32)
    for b in range(_ORIENTATION_BINS):
        near = np.isin(bins, [(b - 1) % _ORIENTATION_BINS, b, (b + 1) % _ORIENTATION_BINS])
        out[b] = _distance_to(near)
    return out


# ============================================================ chamfer sampling
class _Chamfer:
    """Truncated (oriented) distance fields of one photo size, for sampling.

    Skyline points of the render read the distance to the photo's skyline
    when it has one (layer B), all others the distance to photo edges of
    their own orientation (layers 0..B-1).
    """

    def __init__(self, pe: PhotoEdges, truncate_px: float, oriented: bool = True,
                 smooth: float = 1.0) -> None:
        self.pe = pe
        self.truncate = float(truncate_px)
        self.oriented = oriented
        layers = list(pe.oriented_distance) if oriented else [pe.distance]
        self.sky_layer = None
        if pe.sky_distance is not None:
            self.sky_layer = len(layers)
            layers.append(pe.sky_distance)
        stack = np.minimum(np.stack(layers), self.truncate).astype(np.float32)
        if smooth > 0:
            # Smooth the kink on the edge and the ridges between edges: a
            # smoother field gives the optimiser usable gradients.
            for i in range(len(stack)):
                stack[i] = cv2.GaussianBlur(stack[i], (0, 0), smooth)
        self.stack = stack
        self._labels: dict = {}

    def _edge_mask(self, layer: int) -> np.ndarray:
        pe = self.pe
        if layer == self.sky_layer:
            return pe.sky_edge
        if not self.oriented:
            return pe.edges
        bins = np.where(pe.edges, _orientation_bin(pe.orientation), -1)
        return np.isin(bins, [(layer + k) % _ORIENTATION_BINS for k in (-1, 0, 1)])

    def nearest(self, layer: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                   np.ndarray]:
        """The nearest photo edge pixel of each point's layer.

        Returns
        -------
        q : (N, 2) float64 array
            Edge pixel (x, y); NaN for points outside the image.
        normal : (N, 2) float64 array
            The photo edge's unit normal there.
        distance : (N,) float64 array
            ``|uv - q|`` (inf outside).
        """
        h, w = self.pe.shape
        n = len(uv)
        q = np.full((n, 2), np.nan)
        inside = np.isfinite(uv).all(axis=1)
        inside &= (uv[:, 0] > -0.5) & (uv[:, 1] > -0.5)
        inside &= (uv[:, 0] < w - 0.5) & (uv[:, 1] < h - 0.5)
        cols = np.where(inside, np.rint(uv[:, 0]), 0).astype(int)
        rows = np.where(inside, np.rint(uv[:, 1]), 0).astype(int)
        for b in np.unique(layer[inside]):
            if b not in self._labels:
                mask = self._edge_mask(int(b))
                if not mask.any():
                    self._labels[b] = None
                else:
                    src = np.where(mask, 0, 255).astype(np.uint8)
                    _, labels = cv2.distanceTransformWithLabels(
                        src, cv2.DIST_L2, cv2.DIST_MASK_5, labelType=cv2.DIST_LABEL_PIXEL)
                    ys, xs = np.nonzero(mask)  # labels number them in raster order
                    self._labels[b] = (labels, np.stack([xs, ys], axis=1).astype(np.float64))
            if self._labels[b] is None:
                continue
            labels, coords = self._labels[b]
            sel = inside & (layer == b)
            q[sel] = coords[labels[rows[sel], cols[sel]] - 1]
        ok = np.isfinite(q[:, 0])
        theta = np.zeros(n)
        theta[ok] = self.pe.orientation[q[ok, 1].astype(int), q[ok, 0].astype(int)]
        normal = np.stack([np.cos(theta), np.sin(theta)], axis=1)
        distance = np.where(ok, np.linalg.norm(np.nan_to_num(uv - q), axis=1), np.inf)
        return q, normal, distance

    def layers_for(self, kind: np.ndarray, orientation: np.ndarray) -> np.ndarray:
        layer = _orientation_bin(orientation) if self.oriented else np.zeros(len(kind), int)
        if self.sky_layer is not None:
            layer = np.where(kind == SKYLINE, self.sky_layer, layer)
        return layer

    def sample(self, layer: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Truncated distances at positions ``uv`` (N, 2) on the given layers (N,)."""
        return sample_bilinear(self.stack, uv[..., 0], uv[..., 1], layer=layer,
                               outside=self.truncate)


def chamfer_distances(
    pe: PhotoEdges,
    points_px: np.ndarray,
    kind: np.ndarray,
    orientation: np.ndarray,
    truncate_px: float = 1e4,
    oriented: bool = True,
) -> np.ndarray:
    """Distance from each point to the nearest photo edge of its orientation, px.

    Parameters
    ----------
    pe : PhotoEdges
    points_px : (N, 2) array
        Positions (x, y) in the photo-edge image.
    kind, orientation : (N,) arrays
        From an :class:`EdgeSet`; skyline points are measured to the photo's
        skyline when it has one.
    truncate_px : float
        Cap (also returned for points outside the image).
    oriented : bool
        Measure to edges of similar orientation only.

    Returns
    -------
    (N,) float64 array
    """
    ch = _Chamfer(pe, truncate_px, oriented, smooth=0.0)
    return ch.sample(ch.layers_for(kind, orientation), np.asarray(points_px, np.float64))


# ============================================================== alignment
@dataclass
class EdgeCorrespondences:
    """2D–3D correspondences from edge alignment (photo pixels at full size).

    Attributes
    ----------
    photo_points : (M, 2) float64 array
        Nearest photo edge pixel to each projected edge point, (x, y).
    xyz : (M, 3) float64 array
        The render edge points, model frame, metres.
    kind : (M,) uint8 array
    distance_px : (M,) float64 array
        Distance between the projection and the photo point at full size.
    """

    photo_points: np.ndarray
    xyz: np.ndarray
    kind: np.ndarray
    distance_px: np.ndarray

    def __len__(self) -> int:
        return len(self.kind)


@dataclass
class EdgeAlignment:
    """Outcome of :func:`align_edges`.

    Attributes
    ----------
    ok : bool
    pose : Pose
        The aligned ``cam_from_world`` (the start pose when not ok).
    start_pose : Pose
    score : float
        Weighted truncated mean chamfer distance of the edge points, px at
        :data:`REFERENCE_WIDTH` width (lower is better).
    start_score : float
        The same for the start pose.
    inlier_fraction : float
        Weighted fraction of edge points within ``inlier_px`` of a photo edge.
    n_edge_points : int
        Edge points used at the finest level.
    history : list of dict
        One entry per stage: ``stage``, ``width``, ``score`` (px at the
        reference width), ``inlier_fraction``, ``rotation_deg`` and
        ``shift_m`` from the start, ``pose``, ``seconds``.
    seconds : float
    reason : str
        Why it failed ("" when ok).
    correspondences : EdgeCorrespondences or None
        Edge points within ``inlier_px`` of a photo edge of similar
        orientation under the final pose, paired with its nearest pixel (the
        pairs of a last closest-edge round).
    agreement : float
        Edge score of the final pose (:func:`edge_agreement`).
    """

    ok: bool
    pose: Pose
    start_pose: Pose
    score: float
    start_score: float
    inlier_fraction: float
    n_edge_points: int
    history: list[dict] = field(default_factory=list)
    seconds: float = 0.0
    reason: str = ""
    correspondences: EdgeCorrespondences | None = None
    agreement: float = float("nan")


@dataclass
class EdgeParams(StageParams):
    """Settings of edge alignment (:func:`align_edges`), each with its valid range ``[low, high]``.

    Attributes
    ----------
    levels : tuple of int
        Image widths, px, coarse to fine (capped at the photo's), each in
        [64, 16384]. The rotation and position searches run at the first, the
        6-DoF refinement at the others (at the first when it is the only one).
    search_rotation_deg : (yaw, pitch, roll)
        Half-ranges of the rotation search about the start, degrees, each in
        [0, 45] (yaw about the image's vertical, pitch about its horizontal,
        roll about the view direction).
    search_step_deg : float
        Grid step of the rotation search, degrees, [0.05, 10].
    keep : int
        Distinct best rotations refined at the first level, [1, 20].
    truncate_px : float
        Distances are capped at this, px at :data:`REFERENCE_WIDTH`, [2, 400]:
        an edge point farther from every photo edge is an outlier, whatever
        the distance.
    inlier_px : float
        An edge point within this of a photo edge (px at the reference width)
        is an inlier, [0.1, 100].
    max_points : int
        Edge points per level (:meth:`EdgeSet.thinned`; half at the first
        level, which is searched over many poses), [100, 1 000 000].
    max_rounds : int
        Re-render and refine rounds per level while the pose still moves the
        edge points by more than a pixel, [0, 50].
    oriented : bool
        Oriented chamfer: match edges of similar direction only.
    min_inlier_fraction : float
        Below this weighted inlier fraction the alignment is reported as
        failed, [0, 1].
    min_agreement : float
        Below this edge score (:func:`edge_agreement`: agreement above
        chance, about 0.45–0.6 for right poses of the sample, ≤ 0.2 for poses
        a degree or more off) the alignment is reported as failed, [−1, 1].
    min_step_m : float
        Smallest step of the position search, metres, [0.01, 100].
    kind_weights : dict of str to float
        Weights in chamfer scores that replace :data:`DEFAULT_KIND_WEIGHTS`,
        by kind name (``skyline``, ``occluding``, ``crease``, ``albedo``,
        ``model_border``), each in [0, 100]; 0 leaves a kind out.
    """

    KIND: ClassVar[str] = "edges"

    levels: tuple[int, ...] = (320, 768)
    search_rotation_deg: tuple[float, float, float] = (12.0, 6.0, 4.0)
    search_step_deg: float = 1.0
    keep: int = 3
    truncate_px: float = 40.0
    inlier_px: float = 4.0
    max_points: int = 3000
    max_rounds: int = 3
    oriented: bool = True
    min_inlier_fraction: float = 0.3
    min_agreement: float = 0.25
    min_step_m: float = 0.6
    kind_weights: dict[str, float] = field(default_factory=dict)

    #: Inclusive valid range of each numeric field (every element of a tuple).
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "levels": (64, 16384),
        "search_rotation_deg": (0.0, 45.0),
        "search_step_deg": (0.05, 10.0),
        "keep": (1, 20),
        "truncate_px": (2.0, 400.0),
        "inlier_px": (0.1, 100.0),
        "max_points": (100, 1_000_000),
        "max_rounds": (0, 50),
        "min_inlier_fraction": (0.0, 1.0),
        "min_agreement": (-1.0, 1.0),
        "min_step_m": (0.01, 100.0),
    }

    def __post_init__(self) -> None:
        # JSON brings lists; keep tuples (hashable, compared as the defaults).
        self.levels = tuple(self.levels)
        self.search_rotation_deg = tuple(self.search_rotation_deg)
        if not self.levels:
            raise ValueError("levels must name at least one width")
        if len(self.search_rotation_deg) != 3:
            raise ValueError("search_rotation_deg must be 3 numbers (yaw, pitch, roll), not "
                             f"{list(self.search_rotation_deg)!r}")
        if any(isinstance(w, bool) or not isinstance(w, int) for w in self.levels):
            raise ValueError(f"levels must be integers (px), not {list(self.levels)!r}")
        check_ranges(self)
        self.search_rotation_deg = tuple(float(v) for v in self.search_rotation_deg)
        if not isinstance(self.kind_weights, dict):
            raise ValueError(f"kind_weights must be an object, not {self.kind_weights!r}")
        self.kind_weights = dict(self.kind_weights)  # a copy per instance
        known = set(EDGE_KINDS.values())
        for name, weight in self.kind_weights.items():
            if name not in known:
                raise ValueError(f"unknown edge kind {name!r} in kind_weights; choose from "
                                 f"{', '.join(EDGE_KINDS.values())}")
            if isinstance(weight, bool) or not isinstance(weight, (int, float)) \
                    or not 0.0 <= weight <= 100.0:
                raise ValueError(f"kind_weights[{name!r}] must be within [0, 100], not {weight!r}")

    def weights_by_kind(self) -> dict[int, float]:
        """:attr:`kind_weights` keyed by the kind constants (:data:`SKYLINE`, ...)."""
        code = {name: kind for kind, name in EDGE_KINDS.items()}
        return {code[name]: float(weight) for name, weight in self.kind_weights.items()}


def _rotation_grid(half_range_deg: tuple[float, float, float], step_deg: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame rotations over a yaw × pitch × roll grid, smallest first.

    Returns
    -------
    rotations : (C, 3, 3) array
        To be applied on the left of a world-to-camera rotation.
    angles_deg : (C, 3) array
        (yaw, pitch, roll) of each.
    """
    axes = []
    for half in half_range_deg:
        n = int(math.floor(half / step_deg + 1e-9))
        axes.append(np.arange(-n, n + 1) * step_deg)
    yaw, pitch, roll = np.meshgrid(*axes, indexing="ij")
    angles = np.radians(np.stack([yaw.ravel(), pitch.ravel(), roll.ravel()], axis=1))
    order = np.argsort(np.abs(angles).sum(axis=1), kind="stable")
    angles = angles[order]
    # Camera axes: yaw turns about y (down), pitch about x (right), roll about z.
    rots = []
    for a_yaw, a_pitch, a_roll in angles:
        ry = cv2.Rodrigues(np.array([0.0, a_yaw, 0.0]))[0]
        rx = cv2.Rodrigues(np.array([a_pitch, 0.0, 0.0]))[0]
        rz = cv2.Rodrigues(np.array([0.0, 0.0, a_roll]))[0]
        rots.append(rz @ rx @ ry)
    return np.array(rots), np.degrees(angles)


class _Level(PyramidLevel):
    """One image size of an alignment: scaled camera, photo edges, chamfer fields."""

    def __init__(self, intrinsics: Intrinsics, photo_rgb: np.ndarray, width: int,
                 truncate_ref_px: float, oriented: bool) -> None:
        scale = match_scale(intrinsics.width, width)
        super().__init__(intrinsics, scale)
        self.to_ref = REFERENCE_WIDTH / self.intr.width  # level px -> reference px
        small = self.resize(photo_rgb)
        self.photo = small
        self.edges = photo_edges(small)
        self.truncate = max(2.0, truncate_ref_px / self.to_ref)
        self.robust = max(1.0, _ROBUST_REF_PX / self.to_ref)
        self.chamfer = _Chamfer(self.edges, self.truncate, oriented)


def _weighted_score(d: np.ndarray, weight: np.ndarray) -> float:
    return float(np.sum(d * weight) / max(float(weight.sum()), 1e-9))


def _score_pose(level: _Level, es: EdgeSet, pose: Pose, layer: np.ndarray,
                inlier_px_level: float) -> tuple[float, float]:
    """(weighted truncated mean distance in level px, weighted inlier fraction)."""
    uv = pose.project(level.intr, es.xyz)
    d = level.chamfer.sample(layer, uv)
    w = es.weight.astype(np.float64)
    return _weighted_score(d, w), _weighted_score((d <= inlier_px_level).astype(float), w)


def _score_poses(level: _Level, es: EdgeSet, layer: np.ndarray, rotations: np.ndarray,
                 centres: np.ndarray) -> np.ndarray:
    """Weighted truncated mean chamfer distance (level px) of many poses, (C,).

    The render's 3D edge points are re-projected under every pose: exact for
    a rotation about the rendering camera's centre (image points move by a
    homography), so a whole grid of turns costs no render. Points that leave
    the photo count as the truncation distance.
    """
    w = es.weight.astype(np.float64)
    wsum = max(float(w.sum()), 1e-9)
    n = len(es)
    scores = np.empty(len(rotations))
    chunk = max(1, 400_000 // max(n, 1))
    # Relative to the points' centroid: float32 keeps sub-millimetre detail.
    origin = es.xyz.mean(axis=0)
    pts = (es.xyz - origin).astype(np.float32)
    rots32 = rotations.astype(np.float32)
    shift32 = (centres - origin).astype(np.float32)
    for lo in range(0, len(rotations), chunk):
        hi = min(lo + chunk, len(rotations))
        # R (X - C) = R X' - R C' for X' = X - origin, C' = C - origin.
        pc = np.matmul(rots32[lo:hi], pts.T)  # (C, 3, N), batched BLAS
        pc -= np.matmul(rots32[lo:hi], shift32[lo:hi, :, None])
        uv = level.intr.project(pc.transpose(0, 2, 1).reshape(-1, 3))
        d = level.chamfer.sample(np.broadcast_to(layer, (hi - lo, n)).ravel(), uv)
        scores[lo:hi] = (d.reshape(hi - lo, n) @ w) / wsum
    return scores


def _union(a: EdgeSet, b: EdgeSet) -> EdgeSet:
    """Both sets' points in one (the image positions are those of their renders)."""
    return EdgeSet(
        np.concatenate([a.points_px, b.points_px]), np.concatenate([a.xyz, b.xyz]),
        np.concatenate([a.kind, b.kind]), np.concatenate([a.weight, b.weight]),
        np.concatenate([a.orientation, b.orientation]), a.image_size,
    )


def _widened(intrinsics: Intrinsics, margin_x_deg: float, margin_y_deg: float) -> Intrinsics:
    """The camera with its image extended by the given angles on every side."""
    half_x = math.atan2(intrinsics.width / 2.0, intrinsics.fx) + math.radians(margin_x_deg)
    half_y = math.atan2(intrinsics.height / 2.0, intrinsics.fy) + math.radians(margin_y_deg)
    pad_x = int(math.ceil(intrinsics.fx * math.tan(min(half_x, 1.4)) - intrinsics.width / 2.0))
    pad_y = int(math.ceil(intrinsics.fy * math.tan(min(half_y, 1.4)) - intrinsics.height / 2.0))
    return Intrinsics(intrinsics.width + 2 * pad_x, intrinsics.height + 2 * pad_y,
                      intrinsics.fx, intrinsics.fy, intrinsics.cx + pad_x, intrinsics.cy + pad_y,
                      intrinsics.dist)


def _best_distinct(scores: np.ndarray, rotations: np.ndarray, centres: np.ndarray, keep: int,
                   min_angle_deg: float, min_step_m: float) -> list[int]:
    """Indices of the ``keep`` best poses, each differing from the better ones
    by at least ``min_angle_deg`` or ``min_step_m``."""
    chosen: list[int] = []
    for i in np.argsort(scores, kind="stable"):
        if all(math.degrees(_angle_between(rotations[i], rotations[j])) > min_angle_deg
               or np.linalg.norm(centres[i] - centres[j]) > min_step_m for j in chosen):
            chosen.append(int(i))
        if len(chosen) >= keep:
            break
    return chosen


def _search_turns(level: _Level, es: EdgeSet, layer: np.ndarray, pose: Pose,
                  half_range_deg: tuple[float, float, float], step_deg: float, keep: int
                  ) -> tuple[list[np.ndarray], float]:
    """The ``keep`` best distinct camera rotations about ``pose``'s centre.

    Coarse to fine: a grid of twice ``step_deg`` over the whole range, a grid
    of ``step_deg`` about its best few, a grid of a quarter step about the
    ``keep`` best of those. Scores are truncated chamfer means of the
    re-projected edge points (:func:`_score_poses`).

    Returns
    -------
    rotations : list of (3, 3) arrays
        World-to-camera rotations, best first.
    score : float
        The best's score on the step grid, level px.
    """
    centre = pose.center

    def scored(rotations: np.ndarray) -> np.ndarray:
        centres = np.repeat(centre[None], len(rotations), axis=0)
        return _score_poses(level, es, layer, rotations, centres)

    coarse_grid, _ = _rotation_grid(half_range_deg, 2.0 * step_deg)
    rots = coarse_grid @ pose.R
    s = scored(rots)
    none = np.zeros((len(rots), 3))
    first = _best_distinct(s, rots, none, max(8, 3 * keep), 2.0 * step_deg, 0.0)
    local, _ = _rotation_grid((step_deg,) * 3, step_deg)
    rots = np.concatenate([local @ rots[i] for i in first])
    s = scored(rots)
    chosen = _best_distinct(s, rots, np.zeros((len(rots), 3)), keep, 2.0 * step_deg, 0.0)
    fine, _ = _rotation_grid((step_deg / 2.0,) * 3, step_deg / 4.0)
    seeds = []
    for i in chosen:
        r_fine = fine @ rots[i]
        seeds.append(r_fine[int(np.argmin(scored(r_fine)))])
    return seeds, float(s[chosen[0]])


def _turn_toward(anchor: np.ndarray, old_centre: np.ndarray, new_centre: np.ndarray
                 ) -> np.ndarray:
    """World rotation Q with Q (anchor - new) ∥ (anchor - old): a camera that
    steps from ``old_centre`` to ``new_centre`` with rotation ``R @ Q`` still
    sees ``anchor`` where it did."""
    u = anchor - old_centre
    v = anchor - new_centre
    u, v = u / np.linalg.norm(u), v / np.linalg.norm(v)
    axis = np.cross(v, u)
    s = float(np.linalg.norm(axis))
    if s < 1e-12:
        return np.eye(3)
    return cv2.Rodrigues(axis / s * math.atan2(s, float(v @ u)))[0]


def _angle_between(a: np.ndarray, b: np.ndarray) -> float:
    c = (np.trace(a @ b.T) - 1.0) / 2.0
    return math.acos(float(np.clip(c, -1.0, 1.0)))


def _refine_turn(level: _Level, es: EdgeSet, pose: Pose, layer: np.ndarray, *,
                 robust_px: float = 2.0, max_nfev: int = 60, restarts: int = 4) -> Pose:
    """The camera turn (about its centre) minimising the chamfer distances.

    Residuals are the (smoothed, truncated) distance-field values at the
    projected points times the square roots of the points' weights, under a
    Cauchy loss of scale ``robust_px`` (pixels of this level); points beyond
    the truncation have zero gradient and neither pull nor push. Unlike the
    pairing of :func:`_refine_icp`, the field needs no pairs, which at the
    coarse level (where every edge has a wrong neighbour within reach) is
    the more robust choice.
    """
    if len(es) < 6:
        return pose
    R0, c0 = pose.R, pose.center
    sw = np.sqrt(es.weight.astype(np.float64))

    def pose_of(x: np.ndarray) -> Pose:
        return Pose.from_center(cv2.Rodrigues(np.radians(x))[0] @ R0, c0)

    def residuals(x: np.ndarray) -> np.ndarray:
        uv = level.intr.project(pose_of(x).transform(es.xyz))
        return level.chamfer.sample(layer, uv) * sw

    # The field is piecewise bilinear: across its kinks a trust-region step
    # fails and the region shrinks until the solver stops, often short of the
    # minimum. Restarting from there (a fresh region) continues the descent.
    # Difference steps of 1e-3 degree: far below a pixel, far above rounding.
    x = np.zeros(3)
    for _ in range(restarts):
        res = least_squares(residuals, x, method="trf", loss="cauchy", f_scale=robust_px,
                            diff_step=1e-3, ftol=1e-10, xtol=1e-6, max_nfev=max_nfev)
        moved = float(np.max(np.abs(res.x - x)))
        x = res.x
        if moved < 1e-3:
            break
    return pose_of(x)


def _refine_icp(level: _Level, es: EdgeSet, pose: Pose, layer: np.ndarray, *,
                rotation_only: bool = False, prior_center: np.ndarray | None = None,
                sigma_m: float | None = None, robust_px: float = 2.0,
                gate_px: float | None = None, iterations: int = 10,
                max_turn_deg: float = 2.0, max_step_m: float = 2.0,
                ) -> tuple[Pose, np.ndarray, np.ndarray]:
    """Pose by iterated closest edges, point to line.

    Each round pairs every projected edge point with the nearest photo edge
    pixel of its orientation (a look-up in the distance transform's labels),
    keeps the pairs closer than a gate that shrinks from ``gate_px`` to three
    times ``robust_px``, and solves the pose minimising the distances along
    the photo edges' normals (a point may slide along its edge) under a
    Cauchy loss (scale ``robust_px``, pixels of this level). Unless
    ``rotation_only``, the camera centre moves too, held by a prior term
    ``|C - prior_center| / sigma_m`` where the edges cannot place it (far
    from the camera a sideways step and a turn look alike); the prior costs
    as much as moving every point by one pixel when the centre moves by
    ``sigma_m``. For fixed pairs the cost is smooth, which the chamfer field
    is not.

    A pose that turns more than ``max_turn_deg`` or steps more than
    ``max_step_m`` from the input is not followed: pairing runs away when
    the edges leave the camera's position undetermined.

    Returns
    -------
    pose : Pose
    photo_points : (N, 2) array
        The last round's paired photo edge pixel per edge point (NaN where
        unpaired).
    paired : (N,) bool array
    """
    gate0 = level.truncate if gate_px is None else gate_px
    gate_min = 3.0 * robust_px
    sw = np.sqrt(es.weight.astype(np.float64))
    prior = prior_center is not None and sigma_m is not None and not rotation_only
    prior_weight = math.sqrt(float(es.weight.sum())) / sigma_m if prior else 0.0
    n_params = 3 if rotation_only else 6
    first = pose
    q = np.full((len(es), 2), np.nan)
    use = np.zeros(len(es), bool)
    for it in range(iterations):
        uv = pose.project(level.intr, es.xyz)
        q, normal, dist = level.chamfer.nearest(layer, uv)
        gate = max(gate_min, gate0 * 0.6 ** it)
        use = dist <= gate
        if use.sum() < 12:
            break
        xyz, qu, nu, wu = es.xyz[use], q[use], normal[use], sw[use]
        R0, c0 = pose.R, pose.center
        n_pts = len(xyz)

        def pose_of(x: np.ndarray, R0=R0, c0=c0) -> Pose:
            centre = c0 if len(x) == 3 else c0 + x[3:6]
            return Pose.from_center(cv2.Rodrigues(np.radians(x[:3]))[0] @ R0, centre)

        def residuals(x: np.ndarray, xyz=xyz, qu=qu, nu=nu, wu=wu) -> np.ndarray:
            p = pose_of(x)
            r = np.einsum("ij,ij->i", level.intr.project(p.transform(xyz)) - qu, nu) * wu
            r = np.nan_to_num(r, nan=level.truncate)
            if prior:
                r = np.concatenate([r, prior_weight * (p.center - prior_center)])
            return r

        res = least_squares(residuals, np.zeros(n_params), method="trf",
                            loss=_cauchy_then_linear(n_pts),
                            f_scale=robust_px, diff_step=1e-4, max_nfev=50)
        new = pose_of(res.x)
        if (new.rotation_error_deg(first) > max_turn_deg
                or np.linalg.norm(new.center - first.center) > max_step_m):
            break
        shift = _median_shift(level.intr, pose, new, xyz)
        pose = new
        if shift < 0.05 and gate <= gate_min:
            break
    return pose, np.where(use[:, None], q, np.nan), use


def _cauchy_then_linear(n_robust: int):
    """A least_squares loss: Cauchy for the first ``n_robust`` residuals, plain
    squares for the rest (the prior terms)."""
    def loss(z: np.ndarray) -> np.ndarray:
        rho = np.empty((3, len(z)))
        rho[0] = np.log1p(z)
        rho[1] = 1.0 / (1.0 + z)
        rho[2] = -rho[1] ** 2
        rho[0, n_robust:] = z[n_robust:]
        rho[1, n_robust:] = 1.0
        rho[2, n_robust:] = 0.0
        return rho
    return loss


def _median_shift(intr: Intrinsics, a: Pose, b: Pose, xyz: np.ndarray) -> float:
    d = np.linalg.norm(a.project(intr, xyz) - b.project(intr, xyz), axis=1)
    d = d[np.isfinite(d)]
    return float(np.median(d)) if len(d) else float("inf")


def align_edges(
    scene: Scene,
    photo_rgb: np.ndarray,
    intrinsics: Intrinsics,
    start: Pose,
    params: EdgeParams | None = None,
    *,
    position_sigma_m: float | None = 5.0,
    search_position_m: float | None = 5.0,
    render_fn: RenderFn | None = None,
    cancelled: Callable[[], bool] | None = None,
    **deprecated_keywords,
) -> EdgeAlignment:
    """Register a photo by aligning the model's structure edges to the photo's edges.

    Parameters
    ----------
    scene : Scene
    photo_rgb : (H, W, 3) uint8 array
        The photo at the size of ``intrinsics``.
    intrinsics : Intrinsics
        The photo's camera.
    start : Pose
        The start ``cam_from_world`` (sensor prior): heading within
        ``params.search_rotation_deg``, position within a few metres.
    params : EdgeParams, optional
        The alignment's settings (default ``EdgeParams()``).
    position_sigma_m : float or None
        Uncertainty of the start's position, metres: a prior that keeps the
        camera centre near the start where the edges cannot place it (None:
        no prior). The registration passes its prior's ``sigma``.
    search_position_m : float or None
        How far from the start the camera centre is searched at the first
        level, metres (a pattern search with steps from half this down to
        ``params.min_step_m``); None or 0: rotations only.
    render_fn : RenderFn, optional
        ``render_fn(intrinsics, pose, scale) -> RenderResult`` (default
        :func:`~napari_imgreg.render.render` of ``scene`` in ``auto`` mode).
        It is called with the photo's camera or, for the first search, a copy
        widened by the search range.
    cancelled : callable, optional
        Polled between steps; when it returns True the alignment stops and
        reports ``reason="cancelled"``.
    **deprecated_keywords
        Fields of :class:`EdgeParams` as keywords, and ``weights`` (by kind
        constant), as before version 0.2 (DeprecationWarning).

    Returns
    -------
    EdgeAlignment
        Never raises for a failed alignment: ``ok`` is False and ``reason``
        says why.
    """
    t_start = time.perf_counter()
    if "weights" in deprecated_keywords:
        weights = deprecated_keywords.pop("weights") or {}
        deprecated_keywords["kind_weights"] = {EDGE_KINDS[k]: w for k, w in weights.items()}
    params = with_keywords(params or EdgeParams(), deprecated_keywords, "align_edges")
    render_fn = (scene_renderer(scene) if render_fn is None
                 else as_render_fn(render_fn, scene, "align_edges"))
    weights = params.weights_by_kind()
    history: list[dict] = []
    widths = level_widths(params.levels, intrinsics.width)

    def fail(reason: str, pose: Pose = start) -> EdgeAlignment:
        return EdgeAlignment(False, pose, start, float("nan"), float("nan"), 0.0, 0, history,
                             time.perf_counter() - t_start, reason)

    def stop() -> bool:
        return cancelled is not None and bool(cancelled())

    def record(stage: str, level: _Level, pose: Pose, score_lvl: float, frac: float,
               t0: float) -> None:
        history.append({
            "stage": stage,
            "width": level.intr.width,
            "score": score_lvl * level.to_ref,
            "inlier_fraction": frac,
            "rotation_deg": pose.rotation_error_deg(start),
            "shift_m": float(np.linalg.norm(pose.center - start.center)),
            "pose": pose,
            "seconds": time.perf_counter() - t0,
        })

    def edges_at(level: _Level, pose: Pose, margin_deg: tuple[float, float] = (0.0, 0.0)
                 ) -> tuple[EdgeSet, np.ndarray]:
        camera = _widened(intrinsics, *margin_deg) if any(margin_deg) else intrinsics
        rendered = render_fn(camera, pose, level.scale)
        # The first level is searched over many poses: half the points.
        n_points = params.max_points // 2 if level is coarse else params.max_points
        es = render_edges(rendered, weights=weights, max_points=n_points)
        es = es.select(es.weight > 0)
        return es, level.chamfer.layers_for(es.kind, es.orientation)

    def refine_rounds(level: _Level, pose: Pose, rounds: int
                      ) -> tuple[Pose, EdgeSet, np.ndarray] | None:
        """Refine in 6 DoF, re-render, again while the edge points still move.

        Each render brings its own edge points (contours slide over a rounded
        surface as the camera moves), so two poses are compared on the union
        of their renders' points: a pose is not preferred merely because its
        own render shows fewer unmatched edges. Returns the pose with its
        render's edge points and layers.
        """
        es, layer = edges_at(level, pose)
        if len(es) < 30:
            return None
        for _ in range(rounds):
            t0 = time.perf_counter()
            new, _, _ = _refine_icp(level, es, pose, layer, prior_center=start.center,
                                    sigma_m=position_sigma_m, robust_px=level.robust)
            shift = _median_shift(level.intr, pose, new, es.xyz)
            es_new, layer_new = edges_at(level, new)
            if len(es_new) < 30:
                break
            both = _union(es, es_new)
            layer_both = np.concatenate([layer, layer_new])
            s_old, _ = _score_pose(level, both, pose, layer_both, 1.0)
            s_new, frac = _score_pose(level, both, new, layer_both, params.inlier_px / level.to_ref)
            if s_new >= s_old:
                break
            pose, es, layer = new, es_new, layer_new
            record("refine", level, pose, s_new, frac, t0)
            if shift < 1.0 or stop():
                break
        return pose, es, layer

    # ---- first level: turn the camera about the start's centre
    if stop():
        return fail("cancelled")
    t0 = time.perf_counter()
    coarse = _Level(intrinsics, photo_rgb, widths[0], params.truncate_px, params.oriented)
    if not coarse.edges.edges.any():
        return fail("the photo has no edges")
    # A render wider than the photo by the search range: a turned camera
    # sees edges that the start's view does not.
    yaw_r, pitch_r, roll_r = params.search_rotation_deg
    diag = math.radians(roll_r) * 0.5 * math.hypot(intrinsics.width, intrinsics.height)
    margin = (yaw_r + math.degrees(diag / intrinsics.fx) + 1.0,
              pitch_r + math.degrees(diag / intrinsics.fy) + 1.0)
    es, layer = edges_at(coarse, start, margin)
    if len(es) < 30:
        return fail(f"the render from the start pose shows only {len(es)} structure edge points")
    seeds, best_score = _search_turns(coarse, es, layer, start, params.search_rotation_deg,
                                      params.search_step_deg, params.keep)
    record("rotation search", coarse, Pose.from_center(seeds[0], start.center), best_score,
           float("nan"), t0)
    if stop():
        return fail("cancelled")
    # Refine the turn of each seed on a fresh render from it; keep the best.
    candidates = []
    for r_seed in seeds:
        t0 = time.perf_counter()
        pose = Pose.from_center(r_seed, start.center)
        es_i, layer_i = edges_at(coarse, pose)
        if len(es_i) < 30:
            continue
        pose = _refine_turn(coarse, es_i, pose, layer_i, robust_px=coarse.robust)
        s, f = _score_pose(coarse, es_i, pose, layer_i, max(params.inlier_px / coarse.to_ref, 1.0))
        record("rotation", coarse, pose, s, f, t0)
        candidates.append((s, pose))
        if stop():
            return fail("cancelled")
    if not candidates:
        return fail("no candidate pose shows enough structure edges")
    best_score, pose = min(candidates, key=lambda c: c[0])

    # ---- where the camera stands: a pattern search over horizontal steps,
    # each scored after turning the camera to fit (a step sideways and a
    # turn look alike from afar; what tells them apart is the parallax of
    # near edges against far ones, so every step is rendered anew)
    if search_position_m:
        t0 = time.perf_counter()
        anchor = np.median(es.xyz, axis=0)
        turns, _ = _rotation_grid((1.5, 1.5, 0.0), 0.25)
        step = search_position_m / 2.0
        n_eval = 0
        while step >= params.min_step_m and n_eval < 40:
            moves = []
            for dx, dy in ((step, 0.0), (-step, 0.0), (0.0, step), (0.0, -step)):
                centre = pose.center + np.array([dx, dy, 0.0])
                if np.linalg.norm(centre[:2] - start.center[:2]) > 1.5 * search_position_m:
                    continue
                turned = Pose.from_center(pose.R @ _turn_toward(anchor, pose.center, centre),
                                          centre)
                es_i, layer_i = edges_at(coarse, turned)
                n_eval += 1
                if len(es_i) < 30:
                    continue
                # Fit the turn on a grid: one batch of re-projections.
                r_try = turns @ turned.R
                s_try = _score_poses(coarse, es_i, layer_i, r_try,
                                     np.repeat(centre[None], len(turns), axis=0))
                best_turn = int(np.argmin(s_try))
                moves.append((float(s_try[best_turn]),
                              Pose.from_center(r_try[best_turn], centre)))
            if stop():
                return fail("cancelled", pose)
            best_move = min(moves, key=lambda m: m[0]) if moves else None
            if best_move is not None and best_move[0] < best_score:
                best_score, pose = best_move
            else:
                step /= 2.0
        record("position search", coarse, pose, best_score, float("nan"), t0)

    # ---- finer levels (or the only one): 6-DoF refinement
    level = coarse
    for width in widths[1:] or widths:
        if width != widths[0]:
            level = _Level(intrinsics, photo_rgb, width, params.truncate_px, params.oriented)
        out = refine_rounds(level, pose, params.max_rounds)
        if out is None:
            return fail("the render shows too few structure edge points", pose)
        pose, es, layer = out
        if stop():
            return fail("cancelled", pose)

    # ---- scores of the result and of the start, correspondences, verdict
    inl = params.inlier_px / level.to_ref
    s, f = _score_pose(level, es, pose, layer, inl)
    es0, layer0 = edges_at(level, start)
    s0, _ = _score_pose(level, es0, start, layer0, inl)
    # The pairs of a last closest-edge round: 2D photo points for 3D points.
    uv = pose.project(level.intr, es.xyz)
    nearest, _, dist = level.chamfer.nearest(layer, uv)
    close = dist <= inl
    corr = EdgeCorrespondences(
        photo_points=pixels_to_full(nearest[close], level.scale),
        xyz=es.xyz[close],
        kind=es.kind[close],
        distance_px=dist[close] / level.scale,
    )
    score, start_score = s * level.to_ref, s0 * level.to_ref
    agreement = _agreement(level.edges, es, uv, inl).score
    ok, reason = True, ""
    if f < params.min_inlier_fraction:
        ok, reason = False, (f"only {f:.0%} of the edge points lie on photo edges "
                             f"(need {params.min_inlier_fraction:.0%})")
    elif agreement < params.min_agreement:
        ok, reason = False, (f"the edges agree little better than chance (edge score "
                             f"{agreement:.2f}, need {params.min_agreement:.2f})")
    elif score >= start_score:
        ok, reason = False, "the edges fit no better than from the start pose"
    return EdgeAlignment(ok, pose, start, score, start_score, f, len(es), history,
                         time.perf_counter() - t_start, reason, corr, agreement)


# ============================================================ verification
@dataclass
class EdgeAgreement:
    """How well a render's structure edges land on a photo's edges.

    Attributes
    ----------
    fraction : float
        Weighted fraction of edge points within ``within_px`` of a photo edge
        of similar orientation.
    chance : float
        The same fraction with the edge points shifted by 10–30 px (at the
        reference width) in eight directions: what a wrong pose scores on
        this photo's edge density.
    score : float
        ``(fraction - chance) / (1 - chance)``: 0 for chance, 1 for every
        edge point on an edge.
    n_points : int
    """

    fraction: float
    chance: float
    score: float
    n_points: int


def edge_agreement(
    source: Scene | RenderResult,
    photo: np.ndarray | PhotoEdges,
    pose: Pose | None = None,
    intrinsics: Intrinsics | None = None,
    *,
    within_px: float = 4.0,
    width: int = 768,
    kinds: tuple[int, ...] = (SKYLINE, OCCLUDING, CREASE, ALBEDO),
    render_fn: RenderFn | None = None,
) -> EdgeAgreement:
    """Agreement of a pose's structure edges with a photo's edges, against chance.

    Parameters
    ----------
    source : Scene or RenderResult
        A scene (rendered from ``pose`` with ``intrinsics`` at ``width``) or a
        render already made from the pose.
    photo : (H, W, 3) uint8 array or PhotoEdges
        The photo (any size with the camera's aspect: it is resized to the
        render), or its edges at the render's size.
    pose, intrinsics : Pose, Intrinsics
        Needed with a Scene.
    within_px : float
        Tolerance, px at :data:`REFERENCE_WIDTH` width.
    width : int
        Render width with a Scene.
    kinds : tuple of int
        Edge kinds that count.
    render_fn : RenderFn, optional
        ``render_fn(intrinsics, pose, scale) -> RenderResult`` with a Scene
        (default :func:`~napari_imgreg.render.render` in ``auto`` mode).

    Returns
    -------
    EdgeAgreement
    """
    if isinstance(source, Scene):
        if pose is None or intrinsics is None:
            raise ValueError("edge_agreement needs pose and intrinsics with a Scene")
        scale = match_scale(intrinsics.width, width)
        render_fn = (scene_renderer(source) if render_fn is None
                     else as_render_fn(render_fn, source, "edge_agreement"))
        rendered = render_fn(intrinsics, pose, scale)
    else:
        rendered = source
    h, w = rendered.shape
    if isinstance(photo, PhotoEdges):
        if photo.shape != (h, w):
            raise ValueError(f"photo edges are {photo.shape}, the render is {(h, w)}")
        pe = photo
    else:
        pe = photo_edges(resize_to(photo, (w, h)))
    es = render_edges(rendered, max_points=4000)
    es = es.select(np.isin(es.kind, kinds))
    return _agreement(pe, es, es.points_px, within_px / (REFERENCE_WIDTH / w))


def _agreement(pe: PhotoEdges, es: EdgeSet, points_px: np.ndarray, tol_px: float
               ) -> EdgeAgreement:
    """:class:`EdgeAgreement` of edge points at ``points_px`` (the photo-edge
    image's pixels), tolerance ``tol_px`` in the same pixels."""
    keep = es.weight > 0
    es, points_px = es.select(keep), points_px[keep]
    if len(es) == 0:
        return EdgeAgreement(0.0, 0.0, 0.0, 0)
    ch = _Chamfer(pe, truncate_px=4 * tol_px + 1, smooth=0.0)
    layer = ch.layers_for(es.kind, es.orientation)
    wgt = es.weight.astype(np.float64)

    def frac(uv: np.ndarray) -> float:
        return _weighted_score((ch.sample(layer, uv) <= tol_px).astype(float), wgt)

    f = frac(points_px)
    to_ref = REFERENCE_WIDTH / pe.shape[1]
    chances = [
        frac(points_px + radius / to_ref * np.array([math.cos(a), math.sin(a)]))
        for radius in (10.0, 20.0, 30.0)
        for a in np.arange(8) * np.pi / 4
    ]
    chance = float(np.mean(chances))
    score = (f - chance) / max(1.0 - chance, 1e-6)
    return EdgeAgreement(f, chance, float(score), len(es))


def edge_score(
    source: Scene | RenderResult,
    photo: np.ndarray | PhotoEdges,
    pose: Pose | None = None,
    intrinsics: Intrinsics | None = None,
    **kwargs,
) -> float:
    """Edge agreement above chance (see :func:`edge_agreement`): ≈ 0 for a wrong
    pose, toward 1 for a right one."""
    return edge_agreement(source, photo, pose, intrinsics, **kwargs).score
