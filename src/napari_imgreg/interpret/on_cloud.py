"""Interpretations on a point cloud: lines through the photo's splat depth,
facets from the cloud's own points.

On a :class:`~napari_imgreg.cloud.CloudScene` the photo's camera is rendered
once (:func:`cloud_view`: the splat z-buffer of the cloud at the photo's pose
and full resolution, lens distortion included, with the index of the point
whose surfel won each pixel), and every feature drawn on that photo is read
from it — one pass over the points per photo, not one per drawn line:

* **Line samples** (:func:`cloud_hits`). A sample's exact (sub-pixel) ray is
  intersected with the tangent discs of the surfels drawn at the four pixels
  around it: the nearest disc it crosses, else the tangent plane of the
  surfel whose disc it passes nearest (within 3 radii, as the render's hole
  filling does), else the depth of its nearest pixel; so a line drawn on the
  cloud of a plane lies on that plane whatever the sampling. A sample whose
  pixels show nothing is a miss.
* **Gaps** (:func:`cloud_breaks`). The line is split at misses (sky, a hole
  the render does not close) and where the range jumps between neighbouring
  samples by more than a continuous surface of the cloud can make::

      |r1 - r0| > gap_spacings * max(s, f) + f * min(tan θ0, tan θ1, cot(grazing))

  ``s`` is the larger local point spacing of the two hit points
  (:attr:`CloudScene.spacing`), ``f`` the samples' lateral footprint (their
  mean range × the angle between their rays), ``θ`` each ray's incidence on
  its point's PCA normal. The first term is the cloud's resolution: a few
  point spacings, times the *range factor* ``max(1, f / s)`` where the
  photo's step at that range is coarser than the scan. The second is the
  step a continuous surface that oblique makes between neighbouring samples,
  capped where the mesh rule calls a surface edge-on
  (:attr:`ProjectionParams.grazing_deg`, 5°). A larger jump crosses a gap in
  the cloud (an occluding ledge, a scan shadow, the sky behind a fin), not
  the rock: the parts on either side become separate 3D segments.
* **Facets** (:func:`cloud_patch`). The points of a polygon are the cloud's
  own points whose pixel lies inside it and that the z-buffer sees: at most
  ``visible_spacings × max(s, f) + f × min(tan θ, cot(grazing))`` behind the
  front surface at their pixel (the same allowance, so a point on the far
  side of a thin fin or on a wall behind an edge is left out). The plane is
  fitted to them as to a mesh facet's surface points.

Known limits (measured on the benchmark's generated scans, true pose,
``docs/benchmarks.md``): the z-buffer keeps the *nearest* of the surfels that
overlap a pixel, so with 5 mm range noise the line points sit ~8 mm in front
of the rock (median, along the ray); and where the rock recedes nearly
edge-on to the photo and the render's hole filling closed pixels from a
surfel in front, a few samples (6 of 20 000 on one photo) take that pixel's
depth, up to ~0.8 m in front (``CloudHits.how == 2``), which can split the
line there.

Frames as in :mod:`napari_imgreg.interpret.project`: pixels (x = column,
y = row) with pixel centres at integers; 3D points in the local model frame,
metres.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..camera import Intrinsics, Pose
from ..errors import InputError
from ..render_points import SplatParams, pixel_rays, splat_depth

if TYPE_CHECKING:
    from ..cloud import CloudScene

__all__ = [
    "CloudProjectionParams",
    "CloudView",
    "CloudHits",
    "cloud_view",
    "cloud_hits",
    "cloud_breaks",
    "cloud_patch",
    "gap_allowance",
]

#: A sample's ray may meet the tangent plane of a surfel this many disc radii
#: from its point (the render fills holes that way); farther, the plane is an
#: extrapolation and the pixel's own depth is used.
_MAX_TANGENT_RADII = 3.0


@dataclass(frozen=True)
class CloudProjectionParams:
    """How drawn features are read from a cloud's splat render.

    Attributes
    ----------
    gap_spacings : float
        A range jump between neighbouring line samples splits the line when
        it exceeds this many point spacings (times the range factor, plus the
        oblique-surface allowance; module docstring), in [0.5, 100]. 4
        passes the splat surface's own steps (a fraction of a spacing) and
        5 mm range noise with a wide margin, and splits at a ledge 4 spacings
        deep (~0.5 m at 90 m from a 1 mrad scan).
    visible_spacings : float
        Facets: a point counts as visible when at most this many spacings
        (plus the oblique allowance) behind the z-buffer at its pixel, in
        [0.5, 100]. 2 keeps the points a pixel's surfel hides on the same
        surface (~1 spacing apart) and drops a surface behind.
    splat : SplatParams or None
        The render's surfels; None: the scene's own (``scene.params.splat``,
        as every other render of it).
    """

    gap_spacings: float = 4.0
    visible_spacings: float = 2.0
    splat: SplatParams | None = None

    def __post_init__(self) -> None:
        for name in ("gap_spacings", "visible_spacings"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and 0.5 <= v <= 100.0):
                raise InputError(f"{name} must be in [0.5, 100] point spacings, not {v!r}")


@dataclass
class CloudView:
    """The photo's camera rendered on the cloud: what its features are read from.

    Attributes
    ----------
    intrinsics : Intrinsics
        The photo's camera (its full resolution).
    pose : Pose
        ``cam_from_world``.
    zbuf : (H, W) float64 array
        Depth along the optical axis, metres; inf where nothing is drawn.
    ids : (H, W) int32 array
        Index of the point whose surfel won the pixel, -1 where empty.
    splat : SplatParams
        The surfels it was rendered with.
    seconds : float
        Time of the render.
    """

    intrinsics: Intrinsics
    pose: Pose
    zbuf: np.ndarray
    ids: np.ndarray
    splat: SplatParams
    seconds: float = 0.0

    def matches(self, intrinsics: Intrinsics, pose: Pose) -> bool:
        """Was this view rendered for that camera?"""
        return (self.intrinsics == intrinsics and np.array_equal(self.pose.R, pose.R)
                and np.array_equal(self.pose.t, pose.t))


@dataclass
class CloudHits:
    """Line samples read from a :class:`CloudView`.

    Attributes
    ----------
    points : (M, 3) float64 array
        Surface points, metres; NaN for misses.
    distance : (M,) float64 array
        Range from the camera centre, metres; inf for misses.
    point_id : (M,) int64 array
        The cloud point whose surfel was met, -1 for a miss.
    normals : (M, 3) float64 array
        That point's PCA normal turned toward the camera (0 for misses).
    directions : (M, 3) float64 array
        The samples' unit rays, world frame.
    how : (M,) int8 array
        How each point was found: 0 the ray crosses the surfel's disc, 1 its
        tangent plane within ``_MAX_TANGENT_RADII`` radii, 2 only the pixel's
        depth (edge-on surfels, or a pixel the render's hole filling closed
        far from its point), -1 a miss.
    """

    points: np.ndarray
    distance: np.ndarray
    point_id: np.ndarray
    normals: np.ndarray
    directions: np.ndarray
    how: np.ndarray | None = None

    @property
    def hit(self) -> np.ndarray:
        return self.point_id >= 0


def cloud_view(
    scene: CloudScene,
    intrinsics: Intrinsics,
    pose: Pose,
    params: CloudProjectionParams = CloudProjectionParams(),
) -> CloudView:
    """Render the cloud's z-buffer at the photo's camera (no colours).

    Parameters
    ----------
    scene : CloudScene
    intrinsics : Intrinsics
        The photo's camera at the photo's resolution (distortion honoured).
    pose : Pose
        ``cam_from_world``.
    params : CloudProjectionParams

    Returns
    -------
    CloudView
    """
    splat = params.splat or scene.params.splat
    t0 = time.perf_counter()
    z = splat_depth(scene, intrinsics, pose, splat)
    return CloudView(intrinsics, pose, z["zbuf"], z["ids"], splat, time.perf_counter() - t0)


def _tan_incidence(normals: np.ndarray, directions: np.ndarray, cap: float) -> np.ndarray:
    """tan of the angle between each ray and its surface normal, capped."""
    cos = np.abs(np.einsum("ij,ij->i", normals, directions))
    sin = np.sqrt(np.maximum(0.0, 1.0 - cos * cos))
    with np.errstate(divide="ignore", invalid="ignore"):
        tan = np.where(cos > 0, sin / np.maximum(cos, 1e-300), np.inf)
    return np.minimum(tan, cap)


def _grazing_cap(grazing_deg: float) -> float:
    """cot(grazing): the steepest continuous surface (tan of its incidence)."""
    return math.inf if grazing_deg <= 0.0 else 1.0 / math.tan(math.radians(grazing_deg))


def gap_allowance(
    spacing_m: np.ndarray,
    footprint_m: np.ndarray,
    tan_incidence: np.ndarray,
    spacings: float,
) -> np.ndarray:
    """The largest range step a continuous cloud surface makes, metres.

    ``spacings × max(s, f) + f × tan θ`` (module docstring), elementwise.

    Parameters
    ----------
    spacing_m : array
        Local point spacing ``s``, metres.
    footprint_m : array
        Lateral step ``f`` of the samples (or a pixel) at their range, metres.
    tan_incidence : array
        tan of the ray's incidence on the surface, already capped.
    spacings : float
        ``gap_spacings`` or ``visible_spacings``.
    """
    return spacings * np.maximum(spacing_m, footprint_m) + footprint_m * tan_incidence


def cloud_hits(scene: CloudScene, view: CloudView, samples: np.ndarray) -> CloudHits:
    """3D points of line samples, read from the view's z-buffer.

    Parameters
    ----------
    scene : CloudScene
        The cloud ``view`` was rendered from.
    view : CloudView
    samples : (M, 2) array
        Pixel positions (x, y), sub-pixel; NaN rows are misses (the gaps
        between clipped pieces of a line).

    Returns
    -------
    CloudHits
    """
    s = np.asarray(samples, np.float64).reshape(-1, 2)
    m = len(s)
    finite = np.isfinite(s).all(axis=1)
    s = np.where(finite[:, None], s, 0.0)
    intr, pose = view.intrinsics, view.pose
    origin, d = pose.rays(intr, s)
    h, w = view.zbuf.shape
    rows = np.arange(m)
    # The four pixels around each sample (pixel centres at integers).
    x0 = np.clip(np.floor(s[:, 0]).astype(np.int64), 0, max(w - 2, 0))
    y0 = np.clip(np.floor(s[:, 1]).astype(np.int64), 0, max(h - 2, 0))
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    ids = view.ids
    cand = np.stack([ids[y0, x0], ids[y0, x1], ids[y1, x0], ids[y1, x1]], axis=1).astype(np.int64)
    ok = cand >= 0
    ci = np.where(ok, cand, 0)
    p = scene.xyz[ci]  # (M, 4, 3)
    nrm = scene.normals[ci].astype(np.float64)
    radius = scene.splat_radius(view.splat.splat_scale)[ci].astype(np.float64)
    den = np.einsum("mkj,mj->mk", nrm, d)
    with np.errstate(divide="ignore", invalid="ignore"):
        th = np.einsum("mkj,mkj->mk", nrm, p - origin) / den
        q = origin + th[..., None] * d[:, None, :]
        off2 = np.einsum("mkj,mkj->mk", q - p, q - p) / (radius * radius)
    facing = ok & (np.abs(den) > view.splat.grazing_cos) & (th > 0) & np.isfinite(off2)
    disc = facing & (off2 <= 1.0)
    th_disc = np.where(disc, th, np.inf)
    best = th_disc.argmin(axis=1)
    t = th_disc[rows, best]
    pid = np.where(np.isfinite(t), cand[rows, best], -1)
    # No disc crossed (a gap of a random sampling the render filled): the
    # tangent plane of the surfel whose disc the ray passes nearest.
    near_off2 = np.where(facing, off2, np.inf)
    nearest = near_off2.argmin(axis=1)
    plane = (pid < 0) & (near_off2[rows, nearest] <= _MAX_TANGENT_RADII ** 2)
    t[plane] = th[rows, nearest][plane]
    pid[plane] = cand[rows, nearest][plane]
    # Only edge-on surfels (or a far extrapolation): the nearest pixel's depth.
    xr = np.clip(np.rint(s[:, 0]).astype(np.int64), 0, w - 1)
    yr = np.clip(np.rint(s[:, 1]).astype(np.int64), 0, h - 1)
    id_px = ids[yr, xr].astype(np.int64)
    lost = (pid < 0) & (id_px >= 0)
    if lost.any():
        z_axis = d[lost] @ pose.R[2]  # camera depth per metre along the ray
        t[lost] = view.zbuf[yr[lost], xr[lost]] / np.maximum(z_axis, 1e-12)
        pid[lost] = id_px[lost]
    pid[~finite] = -1
    how = np.where(disc.any(axis=1), 0, np.where(plane, 1, 2)).astype(np.int8)
    hit = pid >= 0
    how[~hit] = -1
    t = np.where(hit, t, np.inf)
    points = np.where(hit[:, None], origin + np.where(hit, t, 0.0)[:, None] * d, np.nan)
    normals = np.zeros((m, 3))
    if hit.any():
        n = scene.normals[pid[hit]].astype(np.float64)
        n[np.einsum("ij,ij->i", n, d[hit]) > 0] *= -1.0
        normals[hit] = n
    return CloudHits(points, t, pid, normals, d, how)


def cloud_breaks(
    scene: CloudScene,
    hits: CloudHits,
    params: CloudProjectionParams,
    grazing_deg: float,
) -> np.ndarray:
    """(M - 1,) bool: does the line cross a gap in the cloud between samples i and i+1?

    The gap rule of the module docstring, on pairs of neighbouring samples
    that both hit (a miss splits the line by itself).
    """
    hit = hits.hit
    if len(hit) < 2:
        return np.zeros(0, bool)
    both = hit[:-1] & hit[1:]
    r = np.where(hit, hits.distance, 0.0)
    d0, d1 = hits.directions[:-1], hits.directions[1:]
    angle = np.arccos(np.clip(np.einsum("ij,ij->i", d0, d1), -1.0, 1.0))
    footprint = (r[:-1] + r[1:]) / 2.0 * angle
    pid = np.where(hit, hits.point_id, 0)
    spacing = scene.spacing[pid].astype(np.float64)
    cap = _grazing_cap(grazing_deg)
    tan = _tan_incidence(hits.normals, hits.directions, cap)
    allowed = gap_allowance(np.maximum(spacing[:-1], spacing[1:]), footprint,
                            np.minimum(tan[:-1], tan[1:]), params.gap_spacings)
    return both & (np.abs(r[1:] - r[:-1]) > allowed)


def cloud_patch(
    scene: CloudScene,
    view: CloudView,
    ring_pixels: np.ndarray,
    params: CloudProjectionParams = CloudProjectionParams(),
    grazing_deg: float = 5.0,
    max_points: int = 20_000,
) -> tuple[np.ndarray, np.ndarray]:
    """The cloud's own points inside an image polygon that the photo sees.

    Parameters
    ----------
    scene : CloudScene
    view : CloudView
        The photo's render.
    ring_pixels : (N, 2) array
        The polygon (x, y), open or closed.
    params : CloudProjectionParams
        ``visible_spacings``.
    grazing_deg : float
        Caps the oblique allowance as for lines.
    max_points : int
        Points returned at most (an even subsample); all ids are returned.

    Returns
    -------
    points : (K, 3) float64 array
        Visible cloud points inside the polygon, metres.
    ids : (P,) int64 array
        Indices of all of them in the cloud (``P ≥ K``), sorted.
    """
    from skimage.draw import polygon

    empty = (np.zeros((0, 3)), np.zeros(0, np.int64))
    ring = np.asarray(ring_pixels, np.float64).reshape(-1, 2)
    intr, pose = view.intrinsics, view.pose
    h, w = view.zbuf.shape
    if len(ring) < 3:
        return empty
    rr, cc = polygon(ring[:, 1], ring[:, 0], shape=(h, w))
    seen = np.isfinite(view.zbuf[rr, cc]) & (view.ids[rr, cc] >= 0)
    rr, cc = rr[seen], cc[seen]
    if len(rr) == 0:
        return empty
    mask = np.zeros((h, w), bool)
    mask[rr, cc] = True
    # The front surface inside the polygon, from the z-buffer; only points
    # near its 3D box can be visible there.
    rays = pixel_rays(intr)[rr, cc]
    zs = view.zbuf[rr, cc]
    front = pose.inverse_transform(np.column_stack([rays * zs[:, None], zs]))
    focal = float(max(intr.fx, intr.fy))
    cap = _grazing_cap(grazing_deg)
    spacing_seen = scene.spacing[view.ids[rr, cc]].astype(np.float64)
    margin = float(gap_allowance(spacing_seen.max(), zs.max() / focal, min(cap, 1e3),
                                 params.visible_spacings)) + float(spacing_seen.max())
    lo, hi = front.min(axis=0) - margin, front.max(axis=0) + margin
    xyz = scene.xyz
    near = np.flatnonzero(((xyz >= lo) & (xyz <= hi)).all(axis=1))
    if len(near) == 0:
        return empty
    cam = pose.transform(xyz[near])
    uv = intr.project(cam)
    ok = np.isfinite(uv).all(axis=1)
    u = np.rint(np.where(ok, uv[:, 0], -1.0)).astype(np.int64)
    v = np.rint(np.where(ok, uv[:, 1], -1.0)).astype(np.int64)
    ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
    u, v = np.where(ok, u, 0), np.where(ok, v, 0)
    ok &= mask[v, u]
    z = cam[:, 2]
    footprint = z / focal
    d = xyz[near] - pose.center
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    tan = _tan_incidence(scene.normals[near].astype(np.float64), d, cap)
    allowed = gap_allowance(scene.spacing[near].astype(np.float64), footprint, tan,
                            params.visible_spacings)
    ok &= z <= view.zbuf[v, u] + allowed
    ids = near[ok]
    if len(ids) == 0:
        return empty
    pts = xyz[ids]
    if len(pts) > max_points:
        pts = pts[np.linspace(0, len(pts) - 1, max_points).astype(int)]
    return pts, ids
