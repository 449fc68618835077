"""Splat renderer of a point cloud: the point-cloud counterpart of :mod:`render`.

Each point is drawn as a *surfel*: a disc of radius ``splat_scale × spacing``
(its local point spacing, :attr:`CloudScene.spacing`) in the plane of its PCA
normal. A pixel is covered by a surfel when the pixel's ray meets the disc,
and the depth written into the z-buffer is that of the ray–disc intersection,
so a cloud sampled from a plane renders the plane's exact depth whatever the
sampling; every point also covers the pixel it falls in (``min_radius_px``).
An optional second pass blends the colours of the surfels that lie on the
front surface (weights falling off to the disc's rim), and hole filling
closes the pixels that no surfel reached, or that see a farther surface
through a gap of the front one, wherever at least ``fill_min_neighbours`` of
the 8 neighbours lie on one surface; it never fills across a depth jump.

The engine is numba (chosen by measurement, ``docs/benchmarks.md``, section
``bench_cloud_render``: on 5 M points the vectorised-NumPy projection alone
took 1.72 s where the numba kernel projects in 0.32 s, and NumPy's
``np.minimum.at`` z-buffer of one pixel per point 0.46 s, with neither
splats nor filling). The kernels are compiled once per install (~7 s of
CPU) and then loaded from numba's on-disk cache. They run on
``NAPARI_IMGREG_THREADS`` Python threads (all cores by default; a batch
worker pins 1): the projection over blocks of points, the z-buffer over bands
of rows cut at equal shares of the splat work (each pixel belongs to one band
and sees the points in index order, so the image does not depend on the
threads), hole filling over its candidate pixels, which after the first pass
are only those around the pixels the previous pass filled.

A cloud of ``LodParams.min_points`` points or more is drawn through its level
of detail (:class:`~napari_imgreg.cloud.CloudLevelOfDetail`) unless a render
asks for ``detail="full"``: only the blocks in view, each at the coarsest
level whose surfels are still about a pixel.

This module imports nothing above :mod:`camera` and :mod:`validate`:
:func:`splat_cloud` returns the fields of a
:class:`~napari_imgreg.render.RenderResult` as a dict, and ``render()``
wraps them, so that :mod:`render` can dispatch here without an import cycle.
"""

from __future__ import annotations

import functools
import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numba import njit

from .camera import Intrinsics, Pose, scaled_size
from .errors import InputError
from .validate import FieldValueError, check_number, check_render_size

if TYPE_CHECKING:
    from .cloud import CloudScene

__all__ = ["CLOUD_RENDER_MODES", "SplatParams", "splat_cloud", "splat_depth"]

#: The modes of :func:`napari_imgreg.render.render`, with the same meaning.
CLOUD_RENDER_MODES = ("auto", "color", "shaded", "color_shaded", "normal")

# Grey of a cloud without intensity or colour (the mesh renderer's grey).
_GREY = 180
# The finish kernel's id_map when point indices are the scene's own.
_NO_ID_MAP = np.empty(0, np.int32)


@dataclass(frozen=True)
class SplatParams:
    """How points become surfaces in a splat render.

    Attributes
    ----------
    splat_scale : float
        Disc radius over the point's local spacing (distance to its k-th
        neighbour, :class:`~napari_imgreg.cloud.CloudParams`), in (0, 5].
        0.75 covers a uniform random sampling to ~99 %; hole filling closes
        the rest. Larger values close more gaps but blur silhouettes.
    min_radius_px : float
        Every point covers the pixels within this many pixels of where it
        projects, in [0.5, 4]. 0.75 px covers the pixel it falls in wherever
        in the pixel it falls; 1 px widens every silhouette by a pixel.
    max_radius_px : float
        Cap of a splat's screen radius, pixels, in [1, 256] (a point right in
        front of the camera would otherwise cover the whole image).
    grazing_cos : float
        A surfel seen more edge-on than this cosine between its normal and
        the pixel's ray covers only its ``min_radius_px`` pixels, in [0, 1).
    blend : bool
        Blend the colours of the front surfels (smooth intensity images);
        False: each pixel takes its nearest surfel's colour.
    blend_min_radius_px : float
        Blend only when the visible splats' median screen radius is at least
        this, pixels, in [0, 64]: with about one point per pixel the nearest
        surfel's colour is the same image, and the blend pass costs more than
        the z-buffer (0.7 s of 1.6 s at 5 M points).
    blend_depth_tol : float
        Surfels within this fraction of the front depth (or their own radius,
        whichever is larger) are on the front surface, in [0, 0.5].
    fill_passes : int
        Hole-filling passes, each closing gaps one pixel deeper, in [0, 16].
    fill_min_neighbours : int
        A pixel is filled when at least this many of its 8 neighbours lie on
        one surface in front of it, in [5, 8] (5 of 8 always includes two
        opposite neighbours, so a straight silhouette never grows).
    fill_depth_tol : float
        Neighbours within this fraction of the nearest one's depth are on one
        surface; a pixel farther than that behind them is a gap, in (0, 0.5].
    near_m : float
        Points nearer than this to the camera plane are not drawn, metres.
    """

    splat_scale: float = 0.75
    min_radius_px: float = 0.75
    max_radius_px: float = 48.0
    grazing_cos: float = 0.1
    blend: bool = True
    blend_min_radius_px: float = 1.5
    blend_depth_tol: float = 0.01
    fill_passes: int = 3
    fill_min_neighbours: int = 5
    fill_depth_tol: float = 0.02
    near_m: float = 0.01

    def __post_init__(self) -> None:
        check_number(self.splat_scale, "splat_scale", 0.0, 5.0, low_open=True)
        check_number(self.min_radius_px, "min_radius_px", 0.5, 4.0)
        check_number(self.max_radius_px, "max_radius_px", 1.0, 256.0)
        check_number(self.grazing_cos, "grazing_cos", 0.0, 0.999)
        check_number(self.blend_min_radius_px, "blend_min_radius_px", 0.0, 64.0)
        check_number(self.blend_depth_tol, "blend_depth_tol", 0.0, 0.5)
        check_number(self.fill_passes, "fill_passes", 0, 16, integer=True)
        check_number(self.fill_min_neighbours, "fill_min_neighbours", 5, 8, integer=True)
        check_number(self.fill_depth_tol, "fill_depth_tol", 0.0, 0.5, low_open=True)
        check_number(self.near_m, "near_m", 0.0, 1e3, low_open=True)


# ----------------------------------------------------------------- kernels
def _threads() -> int:
    env = os.environ.get("NAPARI_IMGREG_THREADS")
    return max(1, int(env)) if env else max(1, os.cpu_count() or 1)


# Plain (not ``parallel=True``) kernels that release the GIL, run on a few
# Python threads over blocks of points or bands of rows: numba's parallel
# mode took ~17 s of CPU to compile these, the plain ones ~3 s (compiled once
# per install, then loaded from numba's on-disk cache).
@njit(cache=True, nogil=True, error_model="numpy")
def _project_kernel(lo, hi, xyz, radius, R, t, fx, fy, cx, cy, dist, fov, fold_r2, width,
                    height, near, min_r, max_r, out_u, out_v, out_z, out_r, vis,
                    row_work):  # pragma: no cover
    # Camera-frame depth, distorted pixel position and screen radius of
    # points lo..hi; the indices of those that can touch the image go to
    # vis[lo:lo + count], in order, and count is returned.
    # row_work (height,) adds each point's splat work (pixels of its box,
    # plus two for its set-up) to the rows it covers: the bands of the
    # z-buffer are cut at equal shares of it.
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    # Without distortion the polynomial is the identity to the last bit.
    distorted = k1 != 0.0 or k2 != 0.0 or p1 != 0.0 or p2 != 0.0 or k3 != 0.0
    fmax = max(fx, fy)
    count = 0
    for i in range(lo, hi):
        X = np.float64(xyz[i, 0])
        Y = np.float64(xyz[i, 1])
        Z = np.float64(xyz[i, 2])
        z = R[2, 0] * X + R[2, 1] * Y + R[2, 2] * Z + t[2]
        if z <= near:
            continue
        x = (R[0, 0] * X + R[0, 1] * Y + R[0, 2] * Z + t[0]) / z
        y = (R[1, 0] * X + R[1, 1] * Y + R[1, 2] * Z + t[1]) / z
        rw = np.float64(radius[i])
        # Disc radius in normalised units, seen from its nearest side.
        rn = rw / max(z - rw, near)
        if x + rn < fov[0] or x - rn > fov[1] or y + rn < fov[2] or y - rn > fov[3]:
            continue  # outside the field of view (also where a polynomial folds)
        xd, yd, mag = x, y, 1.0
        if distorted:
            r2 = x * x + y * y
            if r2 >= fold_r2:
                continue  # beyond where the lens polynomial folds back
            radial = 1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
            xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
            yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
            # Bound of the distortion's local magnification (its derivative).
            mag = (1.0 + 3.0 * abs(k1) * r2 + 5.0 * abs(k2) * r2 * r2
                   + 7.0 * abs(k3) * r2 * r2 * r2 + 6.0 * (abs(p1) + abs(p2)) * math.sqrt(r2))
        u = fx * xd + cx
        v = fy * yd + cy
        r = min(max(rn * fmax * mag, min_r), max_r)
        if u + r < -0.5 or u - r > width - 0.5 or v + r < -0.5 or v - r > height - 0.5:
            continue
        out_u[i] = u
        out_v[i] = v
        out_z[i] = z
        out_r[i] = r
        vis[lo + count] = i
        count += 1
        y0 = max(math.ceil(v - r), 0)
        y1 = min(math.floor(v + r), height - 1)
        cols = min(math.floor(u + r), width - 1) - max(math.ceil(u - r), 0) + 3
        for yy in range(y0, y1 + 1):
            row_work[yy] += cols
    return count


@njit(cache=True, nogil=True, error_model="numpy")
def _surfel_hit(i, xyz, normals, R, t, dx, dy, rw2, grazing):  # pragma: no cover
    """Where the pixel ray (dx, dy, 1) meets surfel i's tangent plane:
    (depth, squared distance from the point over rw2), depth -1 when edge-on."""
    X = np.float64(xyz[i, 0])
    Y = np.float64(xyz[i, 1])
    Z = np.float64(xyz[i, 2])
    nX = np.float64(normals[i, 0])
    nY = np.float64(normals[i, 1])
    nZ = np.float64(normals[i, 2])
    px = R[0, 0] * X + R[0, 1] * Y + R[0, 2] * Z + t[0]
    py = R[1, 0] * X + R[1, 1] * Y + R[1, 2] * Z + t[1]
    pz = R[2, 0] * X + R[2, 1] * Y + R[2, 2] * Z + t[2]
    nx = R[0, 0] * nX + R[0, 1] * nY + R[0, 2] * nZ
    ny = R[1, 0] * nX + R[1, 1] * nY + R[1, 2] * nZ
    nz = R[2, 0] * nX + R[2, 1] * nY + R[2, 2] * nZ
    den = nx * dx + ny * dy + nz
    if abs(den) <= grazing * math.sqrt(dx * dx + dy * dy + 1.0):
        return -1.0, np.inf
    zs = (nx * px + ny * py + nz * pz) / den
    qx = dx * zs - px
    qy = dy * zs - py
    qz = zs - pz
    return zs, (qx * qx + qy * qy + qz * qz) / rw2


@njit(cache=True, nogil=True, error_model="numpy")
def _splat_kernel(y_lo, y_hi, vis, xyz, normals, radius, colors, R, t, u, v, z, rad, rays,
                  min_r, grazing, blend_tol, zbuf, ids, csum, wsum, do_depth,
                  do_blend):  # pragma: no cover
    # Rows y_lo..y_hi-1 of the z-buffer (do_depth: emptied here first) or of
    # the colour sums (do_blend): each thread owns a band of rows, so no two
    # write a pixel, and each pixel sees the points in index order whatever
    # the bands.
    width = zbuf.shape[1]
    min_r2 = min_r * min_r
    if do_depth:
        for yy in range(y_lo, y_hi):
            for xx in range(width):
                zbuf[yy, xx] = np.inf
                ids[yy, xx] = -1
    for j in range(vis.shape[0]):
        i = vis[j]
        r = rad[i]
        vc = v[i]
        y0 = max(math.ceil(vc - r), y_lo)
        y1 = min(math.floor(vc + r), y_hi - 1)
        if y0 > y1:
            continue
        uc = u[i]
        x0 = max(math.ceil(uc - r), 0)
        x1 = min(math.floor(uc + r), width - 1)
        rw = np.float64(radius[i])
        inv_rw2 = 1.0 / (rw * rw)
        zp = np.float64(z[i])
        # The surfel in the camera frame, once per point.
        X = np.float64(xyz[i, 0])
        Y = np.float64(xyz[i, 1])
        Z = np.float64(xyz[i, 2])
        nX = np.float64(normals[i, 0])
        nY = np.float64(normals[i, 1])
        nZ = np.float64(normals[i, 2])
        px = R[0, 0] * X + R[0, 1] * Y + R[0, 2] * Z + t[0]
        py = R[1, 0] * X + R[1, 1] * Y + R[1, 2] * Z + t[1]
        nx = R[0, 0] * nX + R[0, 1] * nY + R[0, 2] * nZ
        ny = R[1, 0] * nX + R[1, 1] * nY + R[1, 2] * nZ
        nz = R[2, 0] * nX + R[2, 1] * nY + R[2, 2] * nZ
        npd = nx * px + ny * py + nz * zp
        for yy in range(y0, y1 + 1):
            for xx in range(x0, x1 + 1):
                if do_blend and not zbuf[yy, xx] < np.inf:
                    continue
                dx = rays[yy, xx, 0]
                dy = rays[yy, xx, 1]
                den = nx * dx + ny * dy + nz
                s2 = np.inf
                zs = -1.0
                if den * den > grazing * grazing * (dx * dx + dy * dy + 1.0):
                    zs = npd / den
                    qx = dx * zs - px
                    qy = dy * zs - py
                    qz = zs - zp
                    s2 = (qx * qx + qy * qy + qz * qz) * inv_rw2
                if s2 > 1.0:
                    # Outside the disc: only the pixel the point falls in.
                    s2 = ((xx - uc) ** 2 + (yy - vc) ** 2) / min_r2
                    if s2 > 1.0:
                        continue
                    if zs <= 0.0 or abs(zs - zp) > rw:
                        zs = zp
                if zs <= 0.0:
                    continue
                if do_depth:
                    if zs < zbuf[yy, xx]:
                        zbuf[yy, xx] = zs
                        ids[yy, xx] = i
                else:
                    front = zbuf[yy, xx]
                    if zs > front + max(blend_tol * front, rw):
                        continue
                    w = 1.0 - 0.9 * s2
                    wsum[yy, xx] += w
                    for c in range(3):
                        csum[yy, xx, c] += w * colors[i, c]


@njit(cache=True, nogil=True, error_model="numpy")
def _fill_kernel(lo, hi, cand, zbuf, ids, csum, wsum, xyz, normals, R, t, rays, min_nb, tol,
                 grazing, do_colour, znew, idnew, cnew, wnew):  # pragma: no cover
    # One hole-filling pass over the candidate pixels cand[lo:hi] (flat
    # indices; see the module docstring). The new values go to *new (idnew
    # -1: unchanged), applied after the pass, so every pixel of a pass sees
    # the same image. Neighbours beyond the image border count as empty: a
    # border pixel is filled only when all its 5 neighbours lie on one surface.
    height, width = zbuf.shape
    for j in range(lo, hi):
        idnew[j] = -1
        yy = cand[j] // width
        xx = cand[j] % width
        ya, yb = max(yy - 1, 0), min(yy + 1, height - 1)
        xa, xb = max(xx - 1, 0), min(xx + 1, width - 1)
        zmin = np.inf
        ymin = -1
        xmin = -1
        for y2 in range(ya, yb + 1):
            for x2 in range(xa, xb + 1):
                zn = zbuf[y2, x2]
                if (x2 != xx or y2 != yy) and zn < zmin:
                    zmin = zn
                    ymin = y2
                    xmin = x2
        if ymin < 0:
            continue
        limit = zmin * (1.0 + tol)
        if zbuf[yy, xx] <= limit:
            continue  # on the front surface already (or nearer)
        count = 0
        zmax = zmin
        zsum = 0.0
        for y2 in range(ya, yb + 1):
            for x2 in range(xa, xb + 1):
                zn = zbuf[y2, x2]
                if (x2 != xx or y2 != yy) and zn <= limit:
                    count += 1
                    zmax = max(zmax, zn)
                    zsum += zn
        n_nb = (yb - ya + 1) * (xb - xa + 1) - 1
        if count < min(min_nb, n_nb):
            continue
        i = ids[ymin, xmin]
        zs, _ = _surfel_hit(i, xyz, normals, R, t, rays[yy, xx, 0], rays[yy, xx, 1], 1.0,
                            grazing)
        if not (zmin * (1.0 - tol) <= zs <= zmax * (1.0 + tol)):
            zs = zsum / count  # the tangent plane does not reach here
        znew[j] = zs
        idnew[j] = i
        if not do_colour:
            continue
        wnew[j] = 0.0
        for c in range(3):
            cnew[j, c] = 0.0
        for y2 in range(ya, yb + 1):
            for x2 in range(xa, xb + 1):
                if (x2 != xx or y2 != yy) and zbuf[y2, x2] <= limit:
                    wnew[j] += wsum[y2, x2]
                    for c in range(3):
                        cnew[j, c] += csum[y2, x2, c]


@njit(cache=True, nogil=True, error_model="numpy")
def _is_fill_candidate(zbuf, yy, xx, grow):  # pragma: no cover
    # Empty, or behind its nearest 3 × 3 neighbour by more than the
    # tolerance: in float32, the image clipped at 3e38 (the border
    # replicated), as an OpenCV min filter of the float32 image decides it.
    height, width = zbuf.shape
    z = np.float32(min(zbuf[yy, xx], 3e38))
    nearest = z
    for y2 in range(max(yy - 1, 0), min(yy + 1, height - 1) + 1):
        for x2 in range(max(xx - 1, 0), min(xx + 1, width - 1) + 1):
            nearest = min(nearest, np.float32(min(zbuf[y2, x2], 3e38)))
    return z > nearest * grow


@njit(cache=True, nogil=True, error_model="numpy")
def _fill_candidates_rows(y_lo, y_hi, zbuf, grow, flags):  # pragma: no cover
    # The first pass's candidates, rows y_lo..y_hi-1.
    for yy in range(y_lo, y_hi):
        for xx in range(zbuf.shape[1]):
            flags[yy, xx] = _is_fill_candidate(zbuf, yy, xx, grow)


@njit(cache=True, nogil=True, error_model="numpy")
def _fill_candidates_near(changed, zbuf, grow, stamp, pass_no, out):  # pragma: no cover
    # A later pass's candidates: only a pixel whose 3 × 3 neighbourhood the
    # previous pass changed can decide otherwise than it did then (the
    # others would repeat their answer), so only those are tested.
    height, width = zbuf.shape
    n = 0
    for j in range(changed.shape[0]):
        yy = changed[j] // width
        xx = changed[j] % width
        for y2 in range(max(yy - 1, 0), min(yy + 1, height - 1) + 1):
            for x2 in range(max(xx - 1, 0), min(xx + 1, width - 1) + 1):
                q = y2 * width + x2
                if stamp[q] == pass_no:
                    continue
                stamp[q] = pass_no
                if _is_fill_candidate(zbuf, y2, x2, grow):
                    out[n] = q
                    n += 1
    return n


@njit(cache=True, nogil=True, error_model="numpy")
def _finish_kernel(y_lo, y_hi, zbuf, ids, csum, wsum, normals, colors, id_map, R, center, rays,
                   mode, light, ambient, grey, bg, use_blend, rgb, xyz_out, depth, normal_out,
                   face_id):  # pragma: no cover
    # Per-pixel outputs in the RenderResult conventions, rows y_lo..y_hi-1;
    # face_id through id_map (a level-of-detail sub-cloud's scene indices)
    # unless it is empty.
    width = zbuf.shape[1]
    mapped = id_map.shape[0] > 0
    for yy in range(y_lo, y_hi):
        for xx in range(width):
            i = ids[yy, xx]
            zs = zbuf[yy, xx]
            if i < 0 or not zs < np.inf or not rays[yy, xx, 0] == rays[yy, xx, 0]:
                # (empty, or a pixel no ray reaches: NaN, see pixel_rays)
                face_id[yy, xx] = -1
                depth[yy, xx] = np.nan
                for c in range(3):
                    xyz_out[yy, xx, c] = np.nan
                    normal_out[yy, xx, c] = 0.0
                    rgb[yy, xx, c] = bg[c]
                continue
            face_id[yy, xx] = id_map[i] if mapped else i
            depth[yy, xx] = zs
            dx = rays[yy, xx, 0]
            dy = rays[yy, xx, 1]
            # World direction of the pixel ray (z = 1 in camera): R.T @ d.
            wx = R[0, 0] * dx + R[1, 0] * dy + R[2, 0]
            wy = R[0, 1] * dx + R[1, 1] * dy + R[2, 1]
            wz = R[0, 2] * dx + R[1, 2] * dy + R[2, 2]
            xyz_out[yy, xx, 0] = center[0] + wx * zs
            xyz_out[yy, xx, 1] = center[1] + wy * zs
            xyz_out[yy, xx, 2] = center[2] + wz * zs
            n0 = np.float64(normals[i, 0])
            n1 = np.float64(normals[i, 1])
            n2 = np.float64(normals[i, 2])
            if n0 * wx + n1 * wy + n2 * wz > 0.0:  # turn toward the camera
                n0, n1, n2 = -n0, -n1, -n2
            normal_out[yy, xx, 0] = n0
            normal_out[yy, xx, 1] = n1
            normal_out[yy, xx, 2] = n2
            if mode == 0 and not use_blend:
                # The point's own colour (what the general branch below
                # computes, float round trip included, for a uint8).
                for c in range(3):
                    rgb[yy, xx, c] = colors[i, c]
                continue
            shade = ambient + (1.0 - ambient) * max(n0 * light[0] + n1 * light[1] + n2 * light[2],
                                                    0.0)
            for c in range(3):
                if mode == 3:  # the normal map
                    nc = n0 if c == 0 else (n1 if c == 1 else n2)
                    val = nc * 127.5 + 127.5
                elif mode == 1:  # grey Lambert shading
                    val = grey * shade
                else:
                    val = np.float64(colors[i, c])
                    if use_blend:
                        w = wsum[yy, xx]
                        if w > 0.0:
                            val = csum[yy, xx, c] / w
                    if mode == 2:
                        val *= shade
                rgb[yy, xx, c] = np.uint8(min(max(val + 0.5, 0.0), 255.0))


def _run_blocks(kernel, n: int, n_threads: int, *args, bounds=None) -> None:
    """Run ``kernel(lo, hi, *args)`` over [0, n) in ``n_threads`` blocks
    (or the blocks between consecutive ``bounds``)."""
    if bounds is None:
        if n_threads <= 1 or n < 2:
            kernel(0, n, *args)
            return
        bounds = np.linspace(0, n, n_threads + 1).astype(int)
    if len(bounds) <= 2:
        kernel(int(bounds[0]), int(bounds[-1]), *args)
        return
    with ThreadPoolExecutor(len(bounds) - 1) as pool:
        list(pool.map(lambda b: kernel(int(bounds[b]), int(bounds[b + 1]), *args),
                      range(len(bounds) - 1)))


def _balanced_bands(work: np.ndarray, n_bands: int) -> np.ndarray:
    """Row bounds (n_bands + 1,) cutting rows at equal shares of ``work``."""
    height = len(work)
    if n_bands <= 1 or height < 2:
        return np.array([0, height])
    cum = np.cumsum(work)
    if cum[-1] <= 0:
        return np.linspace(0, height, n_bands + 1).astype(int)
    cuts = np.searchsorted(cum, cum[-1] * np.arange(1, n_bands) / n_bands) + 1
    return np.unique(np.r_[0, np.clip(cuts, 1, height - 1), height])


@functools.lru_cache(maxsize=8)
def pixel_rays(intrinsics: Intrinsics) -> np.ndarray:
    """Undistorted normalised ray (x, y) of every pixel centre, (H, W, 2) float64.

    The ray through pixel (col, row) is ``(x, y, 1)`` in the camera frame
    (z = 1, not unit length); NaN for a pixel that no ray reaches, beyond
    where the distortion polynomial folds back (:func:`unfolded_rays`).
    Cached: a registration renders the same camera many times.
    """
    w, h = intrinsics.width, intrinsics.height
    if intrinsics.has_distortion:
        cols, rows = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        pixels = np.stack([cols.ravel(), rows.ravel()], axis=1)
        d = intrinsics.normalized_rays(pixels)
        d[~unfolded_rays(intrinsics, pixels, d)] = np.nan
        out = np.ascontiguousarray(d[:, :2].reshape(h, w, 2))
    else:
        out = np.empty((h, w, 2))
        out[..., 0] = ((np.arange(w) - intrinsics.cx) / intrinsics.fx)[None, :]
        out[..., 1] = ((np.arange(h) - intrinsics.cy) / intrinsics.fy)[:, None]
    out.setflags(write=False)
    return out


def fold_radius2(dist: np.ndarray) -> float:
    """Squared normalised radius where the radial distortion first folds
    back (``d r_distorted / d r`` reaches 0), ``inf`` where it never does.

    Beyond it the OpenCV polynomial maps farther rays nearer the image centre:
    the pixels there see the same rays twice, or none.
    """
    k1, k2, _, _, k3 = (float(c) for c in np.asarray(dist, np.float64)[:5])
    # d/dr [r (1 + k1 r² + k2 r⁴ + k3 r⁶)] = 1 + 3 k1 s + 5 k2 s² + 7 k3 s³, s = r².
    roots = np.roots([7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0])
    real = [r.real for r in roots if abs(r.imag) <= 1e-9 * max(1.0, abs(r)) and r.real > 0]
    return float(min(real)) if real else math.inf


def unfolded_rays(intrinsics: Intrinsics, pixels: np.ndarray, rays: np.ndarray,
                  tol_px: float = 0.5) -> np.ndarray:
    """Which undistorted rays really are those of their pixels, (N,) bool.

    False where the ray lies beyond the distortion's fold
    (:func:`fold_radius2`) or does not project back onto its pixel (within
    ``tol_px``): a camera whose distortion folds inside the image has
    pixels no ray reaches, which a render leaves empty rather than fill with
    a wrong ray.

    Parameters
    ----------
    intrinsics : Intrinsics
    pixels : (N, 2) array
        Pixel positions (x, y).
    rays : (N, 3) array
        Their rays from :meth:`Intrinsics.normalized_rays` (z = 1).
    tol_px : float
    """
    if not intrinsics.has_distortion:
        return np.ones(len(pixels), bool)
    r2 = rays[:, 0] ** 2 + rays[:, 1] ** 2
    ok = r2 < fold_radius2(intrinsics.dist_coeffs)
    back = intrinsics.project(rays)
    with np.errstate(invalid="ignore"):
        ok &= np.abs(back - pixels).max(axis=1) <= tol_px
    return ok


def _field_of_view(intrinsics: Intrinsics) -> np.ndarray:
    """(x min, x max, y min, y max) of the view in normalised coordinates,
    from the pixel rays of the image border (a distortion polynomial must
    not fold far points in), with a 2-pixel margin."""
    rays = pixel_rays(intrinsics)
    border = np.concatenate([rays[0], rays[-1], rays[:, 0], rays[:, -1]])
    if not np.isfinite(border).all():
        # A distortion folding inside the image: the bounds of the rays
        # that do reach pixels (the border's do not).
        border = rays.reshape(-1, 2)
        border = border[np.isfinite(border).all(axis=1)]
        if len(border) == 0:
            return np.zeros(4)
    margin = 2.0 / max(intrinsics.fx, intrinsics.fy)
    return np.array([border[:, 0].min() - margin, border[:, 0].max() + margin,
                     border[:, 1].min() - margin, border[:, 1].max() + margin])


class _WarmUpCloud:
    """Three points in front of a camera at the origin: enough to run every
    kernel once (each compiles, or loads from numba's cache, on first call)."""

    has_intensity = True
    vertex_colors = None

    def __init__(self) -> None:
        self.xyz32 = np.array([[0.0, 0.0, 5.0], [0.5, 0.0, 5.0], [0.0, 0.5, 5.0]], np.float32)
        self.normals = np.tile(np.array([0.0, 0.0, -1.0], np.float32), (3, 1))
        self.colors = np.full((3, 3), 128, np.uint8)

    def splat_radius(self, scale: float) -> np.ndarray:
        return np.full(3, 0.1 * scale, np.float32)


def warm_up() -> float:
    """Compile (or load) the render kernels now; returns the seconds it took."""
    t0 = time.perf_counter()
    splat_cloud(_WarmUpCloud(), Intrinsics(16, 16, 16.0, 16.0, 7.5, 7.5),
                Pose(np.eye(3), np.zeros(3)))
    return time.perf_counter() - t0


def _light_direction(R: np.ndarray) -> np.ndarray:
    """Toward a light above and to the left of the camera, world frame (as
    :func:`napari_imgreg.render._light_direction`, which this module may not
    import)."""
    return R.T @ np.array([-0.4, -0.6, -0.7])


# ---------------------------------------------------------------- renderer
def splat_depth(
    scene: CloudScene,
    intrinsics: Intrinsics,
    pose: Pose,
    params: SplatParams = SplatParams(),
    colors: bool = False,
) -> dict:
    """Z-buffer of the surfels (and optionally their blended colour sums).

    The low-level pass shared by :func:`splat_cloud` and the cloud's ray
    queries (:meth:`CloudScene.cast_rays`).

    Parameters
    ----------
    scene : CloudScene
        Needs ``xyz32``, ``normals``, ``splat_radius(scale)`` and, with
        ``colors``, ``colors``.
    intrinsics : Intrinsics
        The camera, at the resolution to render (distortion honoured).
    pose : Pose
        ``cam_from_world``.
    params : SplatParams
    colors : bool
        Also accumulate colours (the blend pass).

    Returns
    -------
    dict
        ``zbuf`` (H, W) float64 depth along the optical axis (inf where
        empty), ``ids`` (H, W) int32 point index (-1), ``csum`` (H, W, 3)
        float64 and ``wsum`` (H, W) float64 colour sums (where ``blended``;
        empty (0, 0, 3) and (0, 0) arrays otherwise), ``rays`` (H, W, 2) the
        pixel rays, ``n_visible`` points that touched the image, ``blended``
        (the colour sums were made: ``colors`` and splats of a median
        radius of ``blend_min_radius_px`` or more) and ``timings_s``.
    """
    n_threads = _threads()
    t0 = time.perf_counter()
    h, w = intrinsics.height, intrinsics.width
    rays = pixel_rays(intrinsics)
    xyz = scene.xyz32
    normals = scene.normals
    radius = scene.splat_radius(params.splat_scale)
    colours = scene.colors if colors else np.zeros((1, 3), np.uint8)
    n = len(xyz)
    R = np.ascontiguousarray(pose.R, np.float64)
    t = np.ascontiguousarray(pose.t, np.float64)
    fov = _field_of_view(intrinsics)
    u = np.empty(n, np.float32)
    v = np.empty(n, np.float32)
    z = np.empty(n, np.float32)
    rad = np.empty(n, np.float32)
    vis_blocks = np.empty(n, np.int64)
    point_bounds = np.linspace(0, n, (n_threads if n > 200_000 else 1) + 1).astype(int)
    row_work = np.zeros((len(point_bounds) - 1, h))
    project_args = (xyz, radius, R, t, intrinsics.fx, intrinsics.fy, intrinsics.cx,
                    intrinsics.cy, intrinsics.dist_coeffs, fov,
                    fold_radius2(intrinsics.dist_coeffs), w, h, params.near_m,
                    params.min_radius_px, params.max_radius_px, u, v, z, rad, vis_blocks)
    if len(point_bounds) == 2:
        counts = [_project_kernel(0, n, *project_args, row_work[0])]
    else:
        with ThreadPoolExecutor(len(point_bounds) - 1) as pool:
            counts = list(pool.map(lambda b: _project_kernel(int(point_bounds[b]),
                                                             int(point_bounds[b + 1]),
                                                             *project_args, row_work[b]),
                                   range(len(point_bounds) - 1)))
    if len(counts) == 1:
        vis = vis_blocks[:counts[0]]
    else:
        vis = np.concatenate([vis_blocks[lo:lo + c] for lo, c in zip(point_bounds, counts)])
    del vis_blocks
    t1 = time.perf_counter()
    blended = bool(colors and params.blend and len(vis)
                   and np.median(rad[vis[:: max(1, len(vis) // 10_000)]]) >= params.blend_min_radius_px)
    zbuf = np.empty((h, w))
    ids = np.empty((h, w), np.int32)
    # Colour sums only for the blend pass (64 MB at 1632 × 1224 otherwise zeroed for nothing).
    csum = np.zeros((h, w, 3)) if blended else np.zeros((0, 0, 3))
    wsum = np.zeros((h, w)) if blended else np.zeros((0, 0))
    # Bands of rows with equal shares of the splat work (the image of a
    # cliff is rarely spread evenly over its rows).
    bands = _balanced_bands(row_work.sum(axis=0),
                            n_threads if len(vis) * 4 > 200_000 else 1)
    splat_args = (vis, xyz, normals, radius, colours, R, t, u, v, z, rad, rays,
                  params.min_radius_px, params.grazing_cos, params.blend_depth_tol,
                  zbuf, ids, csum, wsum)
    _run_blocks(_splat_kernel, h, 0, *splat_args, True, False, bounds=bands)
    t2 = time.perf_counter()
    if blended:
        _run_blocks(_splat_kernel, h, 0, *splat_args, False, True, bounds=bands)
    t3 = time.perf_counter()
    grow = np.float32(1.0 + params.fill_depth_tol)
    flat = np.empty(0, np.int64)
    stamp = None
    for k in range(params.fill_passes):
        # Candidates: empty pixels, and pixels behind their nearest neighbour
        # by more than the tolerance; after the first pass only around the
        # pixels the previous one filled.
        if k == 0:
            flags = np.empty((h, w), np.bool_)
            _run_blocks(_fill_candidates_rows, h, n_threads if h * w > 100_000 else 1, zbuf,
                        grow, flags)
            cand = np.flatnonzero(flags)
        else:
            if stamp is None:
                stamp = np.zeros(h * w, np.uint8)
            out = np.empty(9 * len(flat), np.int64)
            cand = np.sort(out[:_fill_candidates_near(flat, zbuf, grow, stamp, k, out)])
        if len(cand) == 0:
            break
        znew = np.empty(len(cand))
        idnew = np.empty(len(cand), np.int32)
        cnew = np.empty((len(cand), 3))
        wnew = np.empty(len(cand))
        _run_blocks(_fill_kernel, len(cand), n_threads if len(cand) > 50_000 else 1, cand,
                    zbuf, ids, csum, wsum, xyz, normals, R, t, rays, params.fill_min_neighbours,
                    params.fill_depth_tol, params.grazing_cos, blended, znew, idnew, cnew, wnew)
        done = idnew >= 0
        if not done.any():
            break
        flat = cand[done]
        zbuf.reshape(-1)[flat] = znew[done]
        ids.reshape(-1)[flat] = idnew[done]
        if blended:
            csum.reshape(-1, 3)[flat] = cnew[done]
            wsum.reshape(-1)[flat] = wnew[done]
    t4 = time.perf_counter()
    return {"zbuf": zbuf, "ids": ids, "csum": csum, "wsum": wsum, "rays": rays,
            "n_visible": len(vis), "blended": blended,
            "timings_s": {"project": t1 - t0, "splat": t2 - t1, "blend": t3 - t2,
                          "fill": t4 - t3}}


def splat_cloud(
    scene: CloudScene,
    intrinsics: Intrinsics,
    cam_from_world: Pose,
    scale: float = 1.0,
    mode: str = "auto",
    background: tuple[int, int, int] = (0, 0, 0),
    light_direction: np.ndarray | None = None,
    ambient: float = 0.35,
    params: SplatParams = SplatParams(),
    detail: str | None = None,
) -> dict:
    """Render a point cloud as surfels: colour (intensity), xyz, depth, normals.

    The arguments are those of :func:`napari_imgreg.render.render`, which
    calls this for a :class:`~napari_imgreg.cloud.CloudScene` and wraps the
    result: ``RenderResult(**splat_cloud(...))``.

    Parameters
    ----------
    scene : CloudScene
    intrinsics : Intrinsics
        The camera (its distortion is honoured: the render matches the photo).
    cam_from_world : Pose
    scale : float
        Render at ``scale`` times the camera's resolution; positive.
    mode : {"auto", "color", "shaded", "color_shaded", "normal"}
        ``color``: the points' colour, or their intensity as grey (grey 180
        when they have neither); ``shaded``: grey Lambert shading of the PCA
        normals; ``color_shaded``: colour times shading; ``normal``: the
        normal map; ``auto``: ``color`` for a cloud with intensity or
        colour, ``shaded`` otherwise.
    background : (3,) ints
        RGB where no surface is seen.
    light_direction : (3,) array, optional
        Toward the light, world frame (default: over the left shoulder).
    ambient : float
        Ambient share of the shading, in [0, 1].
    params : SplatParams
    detail : {"auto", "full"}, optional
        ``"auto"``: a cloud with a level of detail
        (:attr:`CloudScene.level_of_detail`, clouds of
        ``LodParams.min_points`` points or more) is drawn through it: only
        the blocks in view, each at the coarsest level whose surfels are
        still about a pixel (``LodParams.max_radius_px``); ``"full"``: every
        point. Default: the scene's ``render_detail`` (``"auto"``).

    Returns
    -------
    dict
        The fields of :class:`~napari_imgreg.render.RenderResult`: ``rgb``
        (H, W, 3) uint8, ``xyz`` (H, W, 3) float32 (NaN where empty),
        ``depth`` (H, W) float32 (NaN), ``normal`` (H, W, 3) float32 unit,
        turned toward the camera (0 where empty), ``face_id`` (H, W) int32
        *point index* (-1), ``mask`` (H, W) bool, ``intrinsics`` (scaled),
        ``cam_from_world`` and ``timings_s`` (``select``: choosing and
        gathering the level-of-detail points, ``project``, ``splat``,
        ``blend``, ``fill``, ``finish``, ``total``).

    Raises
    ------
    InputError
        A scale that is not a positive number, or a render larger than
        :data:`~napari_imgreg.validate.MAX_RENDER_PIXELS`.
    """
    if mode not in CLOUD_RENDER_MODES:
        raise ValueError(f"mode must be one of {CLOUD_RENDER_MODES}, not {mode!r}")
    if detail is None:
        detail = getattr(scene, "render_detail", "full")
    if detail not in ("auto", "full"):
        raise ValueError(f"detail must be 'auto' or 'full', not {detail!r}")
    has_colour = scene.has_intensity or scene.vertex_colors is not None
    if mode == "auto":
        mode = "color" if has_colour else "shaded"
    try:
        scale = check_number(scale, "scale", 0.0, math.inf, low_open=True)
    except FieldValueError as exc:
        raise InputError(f"render scale {exc.problem}") from None
    check_render_size(*scaled_size(intrinsics.width, intrinsics.height, scale))
    check_number(ambient, "ambient", 0.0, 1.0)
    t0 = time.perf_counter()
    intr = intrinsics.scaled(scale)
    mode_code = {"color": 0, "shaded": 1, "color_shaded": 2, "normal": 3}[mode]
    use_colour = mode_code in (0, 2)
    source, id_map = scene, _NO_ID_MAP
    lod = getattr(scene, "level_of_detail", None) if detail == "auto" else None
    if lod is not None:
        source = lod.subcloud(np.ascontiguousarray(cam_from_world.R, np.float64),
                              np.ascontiguousarray(cam_from_world.t, np.float64),
                              _field_of_view(intr), max(intr.fx, intr.fy), params.splat_scale,
                              params.near_m, scene.params.lod.max_radius_px, _threads())
        id_map = source.ids
    t_select = time.perf_counter() - t0
    z = splat_depth(source, intr, cam_from_world, params, colors=use_colour)
    t1 = time.perf_counter()
    light = _light_direction(cam_from_world.R) if light_direction is None else light_direction
    light = np.asarray(light, np.float64).reshape(3)
    light = light / max(np.linalg.norm(light), 1e-12)
    h, w = intr.height, intr.width
    rgb = np.empty((h, w, 3), np.uint8)
    xyz = np.empty((h, w, 3), np.float32)
    depth = np.empty((h, w), np.float32)
    normal = np.empty((h, w, 3), np.float32)
    face_id = np.empty((h, w), np.int32)
    _run_blocks(_finish_kernel, h, _threads() if h * w > 100_000 else 1, z["zbuf"], z["ids"],
                z["csum"], z["wsum"], source.normals, source.colors, id_map,
                np.ascontiguousarray(cam_from_world.R, np.float64),
                np.ascontiguousarray(cam_from_world.center, np.float64), z["rays"], mode_code,
                light, float(ambient), float(_GREY),
                np.asarray(background, np.float64).reshape(3),
                bool(z["blended"]), rgb, xyz, depth, normal, face_id)
    t2 = time.perf_counter()
    timings = {"select": t_select, **z["timings_s"]}
    timings.update(finish=t2 - t1, total=t2 - t0)
    return {"rgb": rgb, "xyz": xyz, "depth": depth, "normal": normal, "face_id": face_id,
            "mask": face_id >= 0, "intrinsics": intr, "cam_from_world": cam_from_world,
            "timings_s": timings}
