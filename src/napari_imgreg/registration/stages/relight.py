"""Relighting: the model as the photo's sun would light it, and that sun read back.

A photo taken under a low morning sun and a model textured on a cloudy noon
do not look alike: shadows, and faces lit or in shade, differ. This stage
relights a render for the photo's sun (a direction from
:mod:`napari_imgreg.solar`), cast shadows included, so that the render looks
like the photo; and, given a render aligned with a photo, estimates which sun
explains the photo's light and shade.

Shading model (the one the sample generator uses, so that a relit render of
the sample approximates its photos)::

    shade = ambient + (1 - ambient) * max(0, n · s) * lit

with ``n`` the unit surface normal, ``s`` the unit vector toward the sun and
``lit`` 0 in cast shadow. Colours are ``albedo * shade ** (1 / gamma)``.

Frames: the local frame is metres ENU (+X east, +Y grid north, +Z up);
azimuths are degrees clockwise from north, elevations degrees above the
horizon.

This module is backend only: no Qt or napari imports.
"""

from __future__ import annotations

import math
import time
import weakref
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ...camera import Intrinsics, Pose
from ..filters import masked_gaussian
from ...render import RenderResult, render
from ...scene import Scene, has_appearance, ray_threads
from ...solar import sun_vector_enu

__all__ = [
    "shadow_mask",
    "smooth_normals",
    "relight",
    "render_sunlit",
    "render_unlit_and_sunlit",
    "shading_share",
    "estimate_sun_from_photo",
    "SunEstimate",
    "GREY_ALBEDO",
]

#: Constant albedo of untextured, uncoloured meshes (render.py's grey).
GREY_ALBEDO = 180.0

# Correlation tolerance, per unit of unexplained variance, of the suns
# counted in an estimate's spread.
_SPREAD_TOLERANCE = 0.1

# Rec. 709 luma weights.
_LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)


# ---------------------------------------------------------------------------
# shadows and relighting
# ---------------------------------------------------------------------------


def _unit(v: npt.ArrayLike, name: str = "sun_dir") -> np.ndarray:
    a = np.asarray(v, np.float64).reshape(-1)
    norm = float(np.linalg.norm(a)) if a.shape == (3,) else 0.0
    if not math.isfinite(norm) or norm == 0.0:
        raise ValueError(f"{name} must be a non-zero (3,) vector, got {v!r}")
    return a / norm


def _occluded_toward(
    scene: Scene, points: np.ndarray, normals: np.ndarray, sun: np.ndarray, offset: np.ndarray
) -> np.ndarray:
    """(N,) bool: the ray toward the sun from each point, lifted ``offset`` metres
    along its normal, hits the surface."""
    origins = points + offset[:, None].astype(np.float32) * normals
    directions = np.broadcast_to(sun.astype(np.float32), origins.shape)
    return scene.cast_rays(origins, directions).hit


def _shadow_offset(scene: Scene, depth: np.ndarray | None, n: int) -> np.ndarray:
    """Lift (m) of shadow-ray origins off the surface: 1 cm + 1e-4 × depth.

    Grows with distance because a hit point's float32 error and the facets
    within one pixel's footprint do.
    """
    if depth is not None:
        return (0.01 + 1e-4 * np.nan_to_num(depth, nan=0.0)).astype(np.float32)
    size = float(np.linalg.norm(np.ptp(scene.bounds, axis=0)))
    return np.full(n, 0.01 + 1e-4 * size, np.float32)


def shadow_mask(
    scene: Scene,
    xyz: np.ndarray,
    normal: np.ndarray,
    sun_dir: npt.ArrayLike,
    depth: np.ndarray | None = None,
    mask: np.ndarray | None = None,
) -> np.ndarray:
    """Which surface points the sun reaches (not self-shadowed, not in cast shadow).

    A point is lit when its face turns toward the sun (``n · s > 0``) and a
    ray from it toward the sun meets no surface. Faces turned away are dark
    without casting.

    Parameters
    ----------
    scene : Scene
    xyz : array, shape (..., 3)
        Surface points, local metres (a render's ``xyz``; NaN = none).
    normal : array, shape (..., 3)
        Unit geometric normals turned to the viewer (a render's ``normal``).
    sun_dir : (3,) array
        Direction toward the sun, local frame.
    depth : array, shape (...), optional
        Distance to the viewer, metres; scales the ray origins' lift off
        the surface (``1 cm + 1e-4 × depth``). Default: from the scene size.
    mask : bool array, shape (...), optional
        Points to test (default: finite ``xyz`` with a non-zero normal).

    Returns
    -------
    bool array, shape (...)
        True where lit; False in shadow and where ``mask`` is False.
    """
    s = _unit(sun_dir).astype(np.float32)
    xyz = np.asarray(xyz, np.float32)
    normal = np.asarray(normal, np.float32)
    if mask is None:
        mask = np.isfinite(xyz).all(axis=-1) & np.any(normal != 0, axis=-1)
    facing = mask & (normal @ s > 0.0)
    lit = facing.copy()
    idx = np.flatnonzero(facing)
    if len(idx):
        d = None if depth is None else np.asarray(depth).reshape(-1)[idx]
        offset = _shadow_offset(scene, d, len(idx))
        pts = np.take(xyz.reshape(-1, 3), idx, axis=0)
        nrm = np.take(normal.reshape(-1, 3), idx, axis=0)
        blocked = _occluded_toward(scene, pts, nrm, s, offset)
        lit.reshape(-1)[idx[blocked]] = False
    return lit


# Per-scene table for smooth normals: v0 (3), dual edge vectors a1, a2 (6)
# giving barycentrics as dot products, face normal (3), corner normals (9).
_SMOOTH_TABLES: "weakref.WeakKeyDictionary[Scene, dict]" = weakref.WeakKeyDictionary()


def _smooth_table(scene: Scene, crease_deg: float) -> np.ndarray:
    tables = _SMOOTH_TABLES.setdefault(scene, {})
    table = tables.get(crease_deg)
    if table is None:
        tri = scene.vertices[scene.faces]
        e0 = tri[:, 1] - tri[:, 0]
        e1 = tri[:, 2] - tri[:, 0]
        nf = np.cross(e0, e1)
        inv = 1.0 / np.maximum(np.einsum("ij,ij->i", nf, nf), 1e-30)[:, None]
        # p = v0 + b1 e0 + b2 e1 + h nf  =>  b1 = (p - v0)·a1, b2 = (p - v0)·a2.
        a1 = np.cross(e1, nf) * inv
        a2 = np.cross(nf, e0) * inv
        face_normals = scene.face_array("normals")
        corners = scene.face_array("vertex_normals").copy()  # (F, 3, 3)
        # Faces on a crease (a box's edge, a ledge) keep their flat normal:
        # averaging across a hard edge would shade the whole face wrongly.
        cos_dev = np.einsum("fkj,fj->fk", corners, face_normals).min(axis=1)
        creased = cos_dev < math.cos(math.radians(crease_deg))
        corners[creased] = face_normals[creased][:, None, :]
        table = np.column_stack(
            [tri[:, 0], a1, a2, face_normals, corners.reshape(-1, 9)]
        ).astype(np.float32)
        tables[crease_deg] = table
    return table


def smooth_normals(
    scene: Scene,
    face_id: np.ndarray,
    xyz: np.ndarray,
    geo_normal: np.ndarray,
    crease_deg: float = 40.0,
) -> np.ndarray:
    """Phong normals (vertex normals interpolated) at surface points, (N, 3) float32.

    Barycentrics come from the points themselves, so no ray is cast. Each
    normal is turned to the side of ``geo_normal`` (the face normal as the
    viewer sees it). A face whose vertex normals stray more than
    ``crease_deg`` from its own normal lies on a hard edge and is shaded flat.

    Parameters
    ----------
    scene : Scene
    face_id : (N,) int array
        The face under each point.
    xyz : (N, 3) array
        The points, local metres.
    geo_normal : (N, 3) array
        Unit face normals turned to the viewer (a render's ``normal``).
    crease_deg : float
        Crease angle, degrees.
    """
    if getattr(scene, "is_cloud", False):  # a cloud's normals are smooth already (PCA)
        return np.asarray(geo_normal, np.float32).reshape(-1, 3)
    table = _smooth_table(scene, float(crease_deg))
    out = np.empty((len(face_id), 3), np.float32)

    def interpolate(lo: int, hi: int) -> None:
        t = np.take(table, face_id[lo:hi], axis=0)
        w = np.asarray(xyz[lo:hi], np.float32) - t[:, 0:3]
        b1 = np.clip(np.einsum("ij,ij->i", w, t[:, 3:6]), 0.0, 1.0)
        b2 = np.clip(np.einsum("ij,ij->i", w, t[:, 6:9]), 0.0, 1.0)
        b0 = np.clip(1.0 - b1 - b2, 0.0, 1.0)
        corner = t[:, 12:21].reshape(-1, 3, 3)
        n = np.einsum("ik,ikj->ij", np.stack([b0, b1, b2], axis=1), corner)
        # Seen from the back: flip with the face.
        back = np.einsum("ij,ij->i", t[:, 9:12], geo_normal[lo:hi]) < 0
        n[back] *= -1.0
        length = np.sqrt(np.einsum("ij,ij->i", n, n))
        bad = length < 1e-6
        n /= np.where(bad, 1.0, length)[:, None]
        n[bad] = geo_normal[lo:hi][bad]
        out[lo:hi] = n

    # Blocks bound the gathered table's memory; numpy releases the GIL on
    # them, so they run in parallel.
    bounds = list(range(0, len(face_id), 1 << 16)) + [len(face_id)]
    _run_blocks(interpolate, bounds)
    return out


def _run_blocks(work, bounds: list[int]) -> None:
    """``work(lo, hi)`` for consecutive ``bounds``, on ``ray_threads()`` threads."""
    pairs = list(zip(bounds[:-1], bounds[1:]))
    n_threads = min(ray_threads(), len(pairs))
    if n_threads <= 1:
        for lo, hi in pairs:
            work(lo, hi)
        return
    with ThreadPoolExecutor(n_threads) as pool:
        list(pool.map(lambda b: work(*b), pairs))


def _shading(cos_i: np.ndarray, lit: np.ndarray | None, ambient: float, gamma: float) -> np.ndarray:
    """``(ambient + (1 - ambient) * cos_i * lit) ** (1 / gamma)``, float32."""
    direct = cos_i if lit is None else cos_i * lit
    shade = np.float32(ambient) + np.float32(1.0 - ambient) * direct
    if gamma != 1.0:
        shade = shade ** np.float32(1.0 / gamma)
    return shade.astype(np.float32, copy=False)


def relight(
    render_result: RenderResult,
    scene: Scene,
    sun_dir: npt.ArrayLike,
    ambient: float = 0.35,
    survey_sun_dir: npt.ArrayLike | None = None,
    survey_ambient: float = 0.35,
    shadows: bool = True,
    albedo: str | np.ndarray = "auto",
    *,
    survey_shadows: bool = False,
    normals: str = "smooth",
    gamma: float = 1.0,
    survey_gamma: float | None = None,
    lowpass_sigma: float = 0.04,
    penumbra_px: float = 0.8,
    crease_deg: float = 40.0,
) -> np.ndarray:
    """A render's colours as the surface would look under another sun.

    The texture holds the survey day's light. Its albedo is estimated, then
    shaded for the new sun: ``albedo * (ambient + (1 - ambient) *
    max(0, n · s) * lit) ** (1 / gamma)``, with cast shadows traced by
    Embree (one ray per pixel that faces the sun).

    Parameters
    ----------
    render_result : RenderResult
        A ``color`` render (texture or vertex colours, unshaded).
    scene : Scene
        The scene it was rendered from (for shadow rays and vertex normals).
    sun_dir : (3,) array
        Direction toward the new sun, local frame (see
        :func:`napari_imgreg.solar.sun_direction_local`).
    ambient : float
        Share of sky light under the new sun, in [0, 1].
    survey_sun_dir : (3,) array, optional
        Direction toward the sun the texture was captured under, when known.
    survey_ambient : float
        Its ambient share.
    shadows : bool
        Trace cast shadows of the new sun.
    albedo : {"auto", "survey", "lowpass", "constant", "render"} or (H, W, 3) array
        How to remove the survey light from the render's colours:
        ``survey``: divide by the survey shading computed from the normals
        (needs ``survey_sun_dir``); ``lowpass``: divide by a mask-aware
        Gaussian low-pass of the luminance (sigma ``lowpass_sigma`` × the
        image's larger side), rescaled to its mean: broad shading goes, detail
        stays; ``constant``: a uniform grey (untextured meshes); ``render``:
        take the colours as they are; an array: the albedo itself. ``auto``:
        ``survey`` when ``survey_sun_dir`` is given, ``constant`` for a mesh
        without texture or colours, else ``lowpass``.
    survey_shadows : bool
        The texture also holds the survey sun's cast shadows (photogrammetry
        textures do; the sample's does not): divide them out too.
    normals : {"smooth", "flat"}
        Shade with vertex normals interpolated across faces (no facets) or
        with the flat face normals.
    gamma : float
        Colours are ``albedo * shade ** (1 / gamma)``: 1 multiplies the stored
        values (as the sample's texture was baked), 2.2 mimics a camera that
        shaded linear light and then encoded sRGB.
    survey_gamma : float, optional
        The same for the survey light in the texture (default: ``gamma``).
    lowpass_sigma : float
        Low-pass width as a fraction of the image's larger side.
    penumbra_px : float
        Soften shadow edges by a Gaussian of this sigma (pixels), as the
        sun's disc does; 0 for hard edges.
    crease_deg : float
        With smooth normals, faces on edges sharper than this are shaded flat.

    Returns
    -------
    (H, W, 3) uint8 array
        The relit colours; the render's background where nothing is hit.
    """
    return _relight(render_result, scene, sun_dir, ambient, survey_sun_dir, survey_ambient,
                    shadows, albedo, survey_shadows=survey_shadows, normals=normals,
                    gamma=gamma, survey_gamma=survey_gamma, lowpass_sigma=lowpass_sigma,
                    penumbra_px=penumbra_px, crease_deg=crease_deg, with_share=False)[0]


def _relight(render_result: RenderResult, scene: Scene, sun_dir: npt.ArrayLike,
             ambient: float = 0.35, survey_sun_dir: npt.ArrayLike | None = None,
             survey_ambient: float = 0.35, shadows: bool = True,
             albedo: str | np.ndarray = "auto", *, survey_shadows: bool = False,
             normals: str = "smooth", gamma: float = 1.0, survey_gamma: float | None = None,
             lowpass_sigma: float = 0.04, penumbra_px: float = 0.8, crease_deg: float = 40.0,
             with_share: bool = True) -> tuple[np.ndarray, float | None]:
    """:func:`relight`'s colours and the :func:`shading_share` of its light
    (None when no pixel sees the surface, or without ``with_share``)."""
    rr = render_result
    mask = rr.mask
    out = rr.rgb.copy()
    if not mask.any():
        return out, None
    if normals not in ("smooth", "flat"):
        raise ValueError(f"normals must be 'smooth' or 'flat', not {normals!r}")
    s = _unit(sun_dir).astype(np.float32)
    survey_gamma = gamma if survey_gamma is None else survey_gamma
    h, w = mask.shape

    if isinstance(albedo, str):
        mode = albedo
        if mode == "auto":
            if survey_sun_dir is not None:
                mode = "survey"
            elif not has_appearance(scene):
                mode = "constant"
            else:
                mode = "lowpass"
        if mode not in ("survey", "lowpass", "constant", "render"):
            raise ValueError(f"unknown albedo mode {albedo!r}")
        if mode == "survey" and survey_sun_dir is None:
            raise ValueError("albedo='survey' needs survey_sun_dir")
    else:
        mode = "array"
        albedo = np.asarray(albedo)
        if albedo.shape != (h, w, 3):
            raise ValueError(f"albedo array must have shape {(h, w, 3)}, got {albedo.shape}")

    # Flat indices of the surface pixels: np.take is several times faster
    # than boolean-mask indexing on these image-sized arrays.
    pix = np.flatnonzero(mask)
    face = _gather(rr.face_id, pix)
    xyz = _gather(rr.xyz, pix)
    n_geo = _gather(rr.normal, pix)
    n = smooth_normals(scene, face, xyz, n_geo, crease_deg) if normals == "smooth" else n_geo
    depth = _gather(rr.depth, pix)

    def lit_fraction(sun: np.ndarray, cast: bool) -> np.ndarray:
        """(N,) float32 in [0, 1]: 0 on faces turned away or in cast shadow."""
        lit = (n_geo @ sun > 0.0).astype(np.float32)
        if cast:
            idx = np.flatnonzero(lit)
            if len(idx):
                offset = _shadow_offset(scene, depth[idx], len(idx))
                pts, nrm = np.take(xyz, idx, axis=0), np.take(n_geo, idx, axis=0)
                lit[idx[_occluded_toward(scene, pts, nrm, sun, offset)]] = 0.0
        if penumbra_px > 0:
            lit = _gather(masked_gaussian(_scatter(lit, pix, mask.shape), mask, penumbra_px), pix)
        return lit

    # --- albedo, (N, 3) float32
    colours = _gather(rr.rgb, pix).astype(np.float32)
    if mode == "survey":
        s0 = _unit(survey_sun_dir, "survey_sun_dir").astype(np.float32)
        lit0 = lit_fraction(s0, True) if survey_shadows else None
        shade0 = _shading(np.clip(n @ s0, 0.0, None), lit0, survey_ambient, survey_gamma)
        alb = colours / np.maximum(shade0, 0.02)[:, None]
    elif mode == "lowpass":
        lum = colours @ _LUMA
        sigma = max(1.0, lowpass_sigma * max(h, w))
        broad = _gather(masked_gaussian(_scatter(lum, pix, mask.shape), mask, sigma), pix)
        alb = colours * (float(lum.mean()) / np.maximum(broad, 1.0))[:, None]
    elif mode == "constant":
        alb = np.full_like(colours, GREY_ALBEDO)
    elif mode == "render":
        alb = colours
    else:
        alb = _gather(albedo, pix).astype(np.float32)

    # --- the new light
    lit = lit_fraction(s, shadows)
    shade = _shading(np.clip(n @ s, 0.0, None), lit, ambient, gamma)
    out.reshape(-1, 3)[pix] = np.clip(alb * shade[:, None] + 0.5, 0, 255).astype(np.uint8)
    return out, (shading_share(alb @ _LUMA, shade, pix, mask) if with_share else None)


#: Band of the contrast :func:`shading_share` compares, pixels of the render:
#: area matching's band-pass (``AreaParams``: 0.8 px inner, 6 px outer σ).
_SHARE_BAND_PX = (0.8, 6.0)
#: Renders wider than this are reduced for :func:`shading_share`.
_SHARE_WIDTH_PX = 1024


def shading_share(albedo_luma: np.ndarray, shade: np.ndarray, pix: np.ndarray,
                  mask: np.ndarray) -> float:
    """Share of a relit render's fine contrast that comes from its synthetic light.

    A relit render is ``albedo × shade``; its log is the sum of the two
    logs. Band-passed as area matching sees a render (0.8–6 px), the share
    is ``var(shade) / (var(shade) + var(albedo))`` of the logs: 1 for an
    untextured mesh (a uniform albedo, every edge drawn by the light), small
    for a texture whose own colours carry the detail. Matches on the
    synthetic part inherit what the model's light gets wrong — relief the
    model does not resolve shades and shadows the photo, not the render —
    and that error is shared by every match, so no split of the matches
    sees it (:mod:`napari_imgreg.registration.uncertainty` adds it).

    Parameters
    ----------
    albedo_luma : (N,) array
        Luminance of the albedo at the surface pixels (8-bit scale).
    shade : (N,) array
        The new light's shading factor there.
    pix : (N,) int array
        Their flat indices in the render.
    mask : (H, W) bool array
        The render's surface pixels.

    Returns
    -------
    float in [0, 1]; 0 when the render shows no contrast at all.
    """
    lo, hi = _SHARE_BAND_PX
    img = np.stack([_scatter(np.log(np.maximum(shade, 1e-3)).astype(np.float32), pix, mask.shape),
                    _scatter(np.log(np.maximum(albedo_luma, 1.0)).astype(np.float32), pix,
                             mask.shape)], axis=-1)
    region = mask
    # A ratio over the whole frame: on a render wider than 1024 px, the same
    # band on one reduced by an integer factor is as good and several times cheaper.
    factor = int(np.ceil(mask.shape[1] / _SHARE_WIDTH_PX))
    if factor > 1:
        size = (mask.shape[1] // factor, mask.shape[0] // factor)
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        region = cv2.resize(mask.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.99
        lo, hi = max(lo / factor, 0.5), hi / factor
    if not region.any():
        return 0.0
    band = (masked_gaussian(img, region, lo, reduce_wide=False)
            - masked_gaussian(img, region, hi))[region]
    v_shade, v_albedo = (float(v) for v in band.var(axis=0))
    total = v_shade + v_albedo
    return float(v_shade / total) if total > 0 else 0.0


def _gather(img: np.ndarray, pix: np.ndarray) -> np.ndarray:
    """Values of an (H, W) or (H, W, C) image at flat pixel indices: (N,) or (N, C)."""
    flat = img.reshape(img.shape[0] * img.shape[1], -1)
    out = np.take(flat, pix, axis=0)
    return out[:, 0] if img.ndim == 2 else out


def _scatter(values: np.ndarray, pix: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(N,) values at flat pixel indices → (H, W) float32 image, 0 elsewhere."""
    img = np.zeros(shape[0] * shape[1], np.float32)
    img[pix] = values
    return img.reshape(shape)


def render_sunlit(
    scene: Scene,
    intrinsics: Intrinsics,
    pose: Pose,
    sun_dir: npt.ArrayLike,
    scale: float = 1.0,
    background: tuple[int, int, int] = (0, 0, 0),
    **kw: Any,
) -> RenderResult:
    """Render a scene and relight it for a sun (see :func:`relight`).

    Parameters
    ----------
    scene, intrinsics, pose, scale, background
        As for :func:`napari_imgreg.render.render` (``pose`` is ``cam_from_world``).
    sun_dir : (3,) array
        Direction toward the sun, local frame.
    **kw
        Passed to :func:`relight` (``ambient``, ``survey_sun_dir``,
        ``shadows``, ``albedo``, ...); ``with_share=False`` skips the
        shading share (a render only to be looked at).

    Returns
    -------
    RenderResult
        ``rgb`` relit, ``shading_share`` its synthetic light's share of the
        contrast (:func:`shading_share`); ``timings_s["relight"]`` holds the
        relighting's seconds (also added to ``total``).
    """
    rr = render(scene, intrinsics, pose, scale=scale, mode="color", background=background)
    return _relit(rr, scene, sun_dir, **kw)


def render_unlit_and_sunlit(
    scene: Scene,
    intrinsics: Intrinsics,
    pose: Pose,
    sun_dir: npt.ArrayLike,
    scale: float = 1.0,
    background: tuple[int, int, int] = (0, 0, 0),
    **kw: Any,
) -> tuple[RenderResult, RenderResult]:
    """The render as it is and relit for a sun, from one ray cast.

    Area matching matches both and keeps the one whose pose fits its blocks
    better (:func:`~napari_imgreg.registration.round.score_round`, "auto").

    Parameters
    ----------
    scene, intrinsics, pose, sun_dir, scale, background, **kw
        As for :func:`render_sunlit`.

    Returns
    -------
    unlit, sunlit : RenderResult
        ``unlit`` with the model's own colours (the same geometry arrays as
        ``sunlit``), ``sunlit`` as :func:`render_sunlit` returns it.
    """
    rr = render(scene, intrinsics, pose, scale=scale, mode="color", background=background)
    unlit = replace(rr, rgb=rr.rgb.copy(), timings_s=dict(rr.timings_s))
    return unlit, _relit(rr, scene, sun_dir, **kw)


def _relit(rr: RenderResult, scene: Scene, sun_dir: npt.ArrayLike, **kw: Any) -> RenderResult:
    """``rr`` relit in place (:func:`_relight`), its relighting timed."""
    t0 = time.perf_counter()
    rr.rgb, rr.shading_share = _relight(rr, scene, sun_dir, **kw)
    dt = time.perf_counter() - t0
    rr.timings_s["relight"] = dt
    rr.timings_s["total"] = rr.timings_s.get("total", 0.0) + dt
    return rr


# ---------------------------------------------------------------------------
# the sun of a photo, from its shading
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class SunEstimate:
    """A sun direction read from a photo's shading.

    Attributes
    ----------
    direction : (3,) float64 array
        Unit vector toward the sun, local frame.
    azimuth_deg, elevation_deg : float
        The same as angles (azimuth clockwise from the local +Y).
    correlation : float
        Pearson correlation of photo luminance (albedo removed) with the
        predicted shading, in [-1, 1].
    confidence : float
        In [0, 1]: high when the correlation is strong AND the best direction
        is well separated (narrow peak); low on flat, uniformly lit views or
        overcast photos.
    spread_deg : float
        Angular radius of the sky directions that explain the photo nearly
        as well (unexplained variance at most doubled). Surfaces with a
        narrow range of normals fix the azimuth better than the elevation.
    """

    direction: np.ndarray
    azimuth_deg: float
    elevation_deg: float
    correlation: float
    confidence: float
    spread_deg: float


def estimate_sun_from_photo(
    photo_rgb: np.ndarray,
    render_result: RenderResult,
    scene: Scene | None = None,
    *,
    albedo: np.ndarray | None = None,
    survey_sun_dir: npt.ArrayLike | None = None,
    survey_ambient: float = 0.35,
    ambient: float = 0.35,
    step_deg: float = 5.0,
    min_elevation_deg: float = 2.0,
    max_points: int = 10_000,
    refine: int = 6,
    blur_px: float = 2.0,
    seed: int = 0,
) -> SunEstimate:
    """Which sun best explains a photo's light and shade, given its render.

    Grid search over the sky: for each candidate sun, the log of the Lambert
    shading ``ambient + (1 - ambient) max(0, n · s)`` of the render's normals
    is correlated with the log of the photo's luminance over the albedo's
    (exposure and tone curve become an offset and a slope). The best cell is
    refined on a grid four times finer; the best ``refine`` candidates are
    then re-scored with cast shadows (when ``scene`` is given).

    Parameters
    ----------
    photo_rgb : (H, W, 3) uint8 array
        The photo, at the render's size and aligned with it (a registered
        pose, or a close prior: both images are blurred by ``blur_px``).
    render_result : RenderResult
        Its render (normals, mask, colours).
    scene : Scene, optional
        For smooth normals and shadow rays.
    albedo : (H, W, 3) array, optional
        Reflectance under the render's pixels. Default: the render's colours
        freed of the survey shading when ``survey_sun_dir`` is given, else
        none (the photo's luminance alone; albedo contrast is then noise).
        Never the raw render: its survey light, often close to the photo's,
        would cancel the very shading sought.
    survey_sun_dir : (3,) array, optional
        The sun the texture was captured under, local frame.
    survey_ambient : float
        Its ambient share.
    ambient : float
        Ambient share assumed for the candidates.
    step_deg : float
        Coarse grid step in azimuth and elevation, degrees.
    min_elevation_deg : float
        Lowest sun considered, degrees.
    max_points : int
        Pixels sampled for the correlation.
    refine : int
        Number of best candidates re-scored with cast shadows.
    blur_px : float
        Gaussian blur of photo and albedo luminance, pixels.
    seed : int
        Pixel sampling.

    Returns
    -------
    SunEstimate
        ``confidence`` is low on overcast photos, views of one flat face
        (every sun on a cone shades it alike) and misaligned pairs.

    Raises
    ------
    ValueError
        Shapes differ, or fewer than 50 usable surface pixels.
    """
    rr = render_result
    mask = rr.mask
    if photo_rgb.shape[:2] != mask.shape:
        raise ValueError(
            f"photo shape {photo_rgb.shape[:2]} differs from the render's {mask.shape}"
        )
    # Away from silhouettes: the blurred ratio mixes sky and rock there.
    inner = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    if albedo is not None:
        alb_img = np.asarray(albedo)
    elif survey_sun_dir is not None and scene is not None:
        # The albedo relight() estimates: the render over its survey shading.
        alb_img = relight(rr, scene, survey_sun_dir, 1.0, survey_sun_dir=survey_sun_dir,
                          survey_ambient=survey_ambient, shadows=False, penumbra_px=0.0)
    else:
        alb_img = np.full(mask.shape + (3,), GREY_ALBEDO, np.float32)
    photo_lum = masked_gaussian(photo_rgb.astype(np.float32) @ _LUMA, mask, blur_px)
    alb_lum = masked_gaussian(alb_img.astype(np.float32) @ _LUMA, mask, blur_px)
    ok = inner & (alb_lum > 8.0) & (photo_lum > 1.0)
    idx = np.flatnonzero(ok)
    if len(idx) < 50:
        raise ValueError("too few surface pixels to read the sun from")
    if len(idx) > max_points:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_points, replace=False))
    y = np.log(photo_lum.reshape(-1)[idx] / alb_lum.reshape(-1)[idx]).astype(np.float32)
    y -= y.mean()
    y_norm = float(np.sqrt(y @ y))
    n_geo = rr.normal.reshape(-1, 3)[idx]
    xyz = rr.xyz.reshape(-1, 3)[idx]
    n = n_geo if scene is None else smooth_normals(scene, rr.face_id.reshape(-1)[idx], xyz, n_geo)

    def correlation(shade: np.ndarray) -> np.ndarray:
        """Pearson correlation of log shading (N, K) with ``y``, (K,)."""
        ls = np.log(shade)
        ls -= ls.mean(axis=0)
        return (y @ ls) / np.maximum(np.sqrt((ls * ls).sum(axis=0)) * y_norm, 1e-12)

    def lambert_scores(az: np.ndarray, el: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        dirs = sun_vector_enu(az, el).astype(np.float32)  # (K, 3)
        cos = np.clip(n @ dirs.T, 0.0, None) * (n_geo @ dirs.T > 0.0)
        return dirs, correlation(np.float32(ambient) + np.float32(1.0 - ambient) * cos)

    # Coarse sky grid, then a fine grid around its best cell.
    A, E = np.meshgrid(
        np.arange(0.0, 360.0, step_deg), np.arange(min_elevation_deg, 90.0, step_deg), indexing="ij"
    )
    coarse_dirs, coarse = lambert_scores(A.ravel(), E.ravel())
    k = int(np.argmax(coarse))
    fine_off = np.arange(-1.0, 1.0001, 0.25) * step_deg
    fA, fE = np.meshgrid(A.ravel()[k] + fine_off, E.ravel()[k] + fine_off, indexing="ij")
    keep = (fE.ravel() >= min_elevation_deg) & (fE.ravel() <= 90.0)
    fine_dirs, fine = lambert_scores(fA.ravel()[keep] % 360.0, fE.ravel()[keep])
    dirs = np.concatenate([coarse_dirs, fine_dirs])
    corr = np.concatenate([coarse, fine])

    best = int(np.argmax(corr))
    best_corr = float(corr[best])
    if scene is not None and refine > 0:
        depth = rr.depth.reshape(-1)[idx]
        for k in np.argsort(corr)[::-1][:refine]:
            s = dirs[k]
            lit = n_geo @ s > 0.0
            j = np.flatnonzero(lit)
            if len(j):
                offset = _shadow_offset(scene, depth[j], len(j))
                lit[j[_occluded_toward(scene, xyz[j], n_geo[j], s, offset)]] = False
            shade = ambient + (1.0 - ambient) * np.clip(n @ s, 0.0, None) * lit
            c = float(correlation(shade[:, None].astype(np.float32))[0])
            if c > best_corr or k == best:
                best, best_corr = int(k), c
    # Peak width: coarse directions whose correlation is within a tolerance
    # of the best that grows with the unexplained variance 1 - r² (noise,
    # albedo, haze make nearby suns statistically indistinguishable).
    top = float(np.clip(coarse.max(), 0.0, 1.0))
    near = coarse >= top - (_SPREAD_TOLERANCE * (1.0 - top**2) + 0.002)
    ang = np.degrees(np.arccos(np.clip(coarse_dirs[near] @ dirs[best], -1.0, 1.0)))
    spread = float(ang.max()) if len(ang) else 0.0
    confidence = float(np.clip(best_corr, 0.0, 1.0) * np.exp(-spread / 30.0))
    d = dirs[best].astype(np.float64)
    d /= np.linalg.norm(d)
    return SunEstimate(
        direction=d,
        azimuth_deg=math.degrees(math.atan2(d[0], d[1])) % 360.0,
        elevation_deg=math.degrees(math.asin(np.clip(d[2], -1.0, 1.0))),
        correlation=best_corr,
        confidence=confidence,
        spread_deg=spread,
    )
