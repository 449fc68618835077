"""Synthetic field photographs of a scene: light, weather, optics and sensor.

A photo is rendered from the *albedo* texture (what the rock is, not how it
was lit on the survey day) and lit by its own sun: Lambert shading with cast
shadows traced by Embree, a sky with clouds where no surface is hit, wet
rock, then the camera: white balance, exposure, tone curve, vignetting, lens
blur, sensor noise and JPEG compression. :class:`PhotoConditions` holds all
of it, so a benchmark can dial difficulty with one ``strength``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from typing import Any, Callable

import cv2
import numpy as np
from scipy import ndimage

from ..camera import Intrinsics, Pose, rotation_from_attitude
from ..render import render
from ..scene import Scene
from .noise import Lattice, rng_for, smooth_lattice, smoothstep

__all__ = [
    "CONDITION_PRESETS",
    "PhotoConditions",
    "sun_vector",
    "synthesize_photo",
    "camera_intrinsics",
    "sample_poses",
    "select_check_points",
    "view_fractions",
    "make_exif",
    "vertex_normals_of",
]

_SRGB_GAMMA = 2.2


def sun_vector(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit vector toward the sun (ENU) from azimuth (clockwise from north) and elevation."""
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.sin(a) * math.cos(e), math.cos(a) * math.cos(e), math.sin(e)])


# ---------------------------------------------------------------- conditions
@dataclass(frozen=True)
class PhotoConditions:
    """Light, weather and camera conditions of one synthetic photo.

    Attributes
    ----------
    sun_azimuth_deg, sun_elevation_deg : float
        Where the sun is (azimuth clockwise from north).
    ambient : float
        Share of the light that is diffuse sky light, in [0, 1]:
        ``shade = ambient + (1 - ambient) * max(0, n · sun) * lit``.
    shadows : bool
        Trace cast shadows.
    sun_color, sky_color : (3,) floats
        Linear RGB tints of direct sun and of the ambient sky light.
    wet_fraction : float
        Share of the rock surface that is wet (patches and seepage streaks).
    wet_darkening : float
        Wet rock reflects this fraction of the dry rock's light (0.5–0.7).
    white_balance : (3,) floats
        Per-channel gains of the camera's (imperfect) white balance.
    exposure : float
        Exposure bias relative to the camera's auto-exposure.
    gamma : float
        Encoding gamma of the tone curve.
    contrast : float
        Strength of the S-shaped tone curve, in [0, 1].
    noise_sigma : float
        Sensor noise standard deviation at mid-grey, 8-bit levels.
    blur_sigma : float
        Lens and demosaicing blur, pixels.
    vignetting : float
        Light fall-off in the image corners (fraction).
    jpeg_quality : int
        JPEG quality, 1–100.
    cloud_cover : float
        Fraction of the sky with clouds.
    haze : float
        Aerial perspective per 100 m of distance.
    seed : int
        Seeds the wet patches, clouds and sensor noise.
    """

    sun_azimuth_deg: float = 150.0
    sun_elevation_deg: float = 40.0
    ambient: float = 0.35
    shadows: bool = True
    sun_color: tuple[float, float, float] = (1.0, 0.97, 0.92)
    sky_color: tuple[float, float, float] = (0.86, 0.92, 1.0)
    wet_fraction: float = 0.0
    wet_darkening: float = 0.6
    white_balance: tuple[float, float, float] = (1.0, 1.0, 1.0)
    exposure: float = 1.0
    gamma: float = 2.2
    contrast: float = 0.25
    noise_sigma: float = 1.0
    blur_sigma: float = 0.6
    vignetting: float = 0.1
    jpeg_quality: int = 90
    cloud_cover: float = 0.3
    haze: float = 0.02
    seed: int = 0

    @classmethod
    def same_light(
        cls, survey_sun: tuple[float, float] = (150.0, 40.0), ambient: float = 0.35, seed: int = 0
    ) -> PhotoConditions:
        """The survey day's light and mild camera effects (the easy case)."""
        return cls(sun_azimuth_deg=survey_sun[0], sun_elevation_deg=survey_sun[1], ambient=ambient,
                   seed=seed)

    @classmethod
    def from_rng(
        cls,
        rng: np.random.Generator,
        strength: float = 0.5,
        survey_sun: tuple[float, float] = (150.0, 40.0),
        survey_ambient: float = 0.35,
    ) -> PhotoConditions:
        """Random conditions whose departure from the survey day grows with ``strength``.

        Parameters
        ----------
        rng : Generator
            Random stream.
        strength : float
            0: the survey sun and mild camera effects ("same_light"); 1: a
            raking, low sun from the east or west, wet rock, a badly balanced,
            noisy, more compressed image ("changed_light").
        survey_sun : (azimuth_deg, elevation_deg)
            The sun the model's texture was baked with.
        survey_ambient : float
            The survey's ambient share.
        """
        k = float(np.clip(strength, 0.0, 1.0))
        # Raking light skims a south-facing face: sun in the east or the west.
        raking_az = (95.0 if rng.random() < 0.5 else 265.0) + rng.uniform(-10.0, 10.0)
        d_az = (raking_az - survey_sun[0] + 180.0) % 360.0 - 180.0
        az = (survey_sun[0] + k * d_az + rng.uniform(-5.0, 5.0) * k) % 360.0
        el = survey_sun[1] + k * (rng.uniform(8.0, 22.0) - survey_sun[1])
        warm = k * rng.uniform(0.0, 1.0)  # low sun is warmer
        wb = np.exp(k * rng.normal(0.0, 0.06, 3))
        wb /= wb[1]
        return cls(
            sun_azimuth_deg=float(az),
            sun_elevation_deg=float(el),
            ambient=float(np.clip(survey_ambient + k * rng.uniform(-0.15, 0.05), 0.15, 0.6)),
            shadows=True,
            sun_color=(1.0, float(0.97 - 0.08 * warm), float(0.92 - 0.2 * warm)),
            sky_color=(0.86, 0.92, 1.0),
            wet_fraction=float(k * rng.uniform(0.1, 0.35)) if rng.random() < 0.3 + 0.7 * k else 0.0,
            wet_darkening=float(rng.uniform(0.5, 0.7)),
            white_balance=tuple(float(g) for g in wb),
            exposure=float(math.exp(k * np.clip(rng.normal(0.0, 0.25), -0.5, 0.5))),
            gamma=float(_SRGB_GAMMA * (1.0 + k * rng.uniform(-0.1, 0.1))),
            contrast=float(0.25 + k * rng.uniform(-0.1, 0.15)),
            noise_sigma=float(0.8 + k * rng.uniform(0.5, 2.5)),
            blur_sigma=float(0.6 + k * rng.uniform(0.0, 0.4)),
            vignetting=float(0.08 + k * rng.uniform(0.05, 0.25)),
            jpeg_quality=int(round(90 - k * rng.uniform(3.0, 10.0))),
            cloud_cover=float(rng.uniform(0.1, 0.6)),
            haze=float(0.015 + 0.02 * rng.random()),
            seed=int(rng.integers(0, 2**31 - 1)),
        )

    @classmethod
    def changed_light(
        cls,
        rng: np.random.Generator,
        survey_sun: tuple[float, float] = (150.0, 40.0),
        survey_ambient: float = 0.35,
    ) -> PhotoConditions:
        """A raking, low sun, wet rock and a worse camera (the hard case)."""
        return cls.from_rng(rng, 1.0, survey_sun, survey_ambient)

    @classmethod
    def preset(
        cls,
        name: str,
        rng: np.random.Generator | None = None,
        survey_sun: tuple[float, float] = (150.0, 40.0),
        survey_ambient: float = 0.35,
    ) -> PhotoConditions:
        """Conditions by name: one of :data:`CONDITION_PRESETS`.

        ``"same_light"`` is the survey day; ``"mild"``, ``"moderate"`` and
        ``"changed_light"`` are :meth:`from_rng` at strength 0.3, 0.6 and 1.
        """
        if name not in CONDITION_PRESETS:
            raise ValueError(f"conditions preset must be one of {tuple(CONDITION_PRESETS)}, not {name!r}")
        rng = rng if rng is not None else np.random.default_rng(0)
        strength = CONDITION_PRESETS[name]
        if strength == 0.0:
            return cls.same_light(survey_sun, survey_ambient, seed=int(rng.integers(0, 2**31 - 1)))
        return cls.from_rng(rng, strength, survey_sun, survey_ambient)

    @property
    def sun(self) -> np.ndarray:
        """Unit vector toward the sun, (3,)."""
        return sun_vector(self.sun_azimuth_deg, self.sun_elevation_deg)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        for key in ("sun_color", "sky_color", "white_balance"):
            d[key] = list(d[key])
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PhotoConditions:
        kw = {k: v for k, v in d.items() if k in cls.__dataclass_fields__}
        for key in ("sun_color", "sky_color", "white_balance"):
            if key in kw:
                kw[key] = tuple(kw[key])
        return cls(**kw)


#: Named condition strengths for :meth:`PhotoConditions.preset`.
CONDITION_PRESETS: dict[str, float] = {
    "same_light": 0.0,
    "mild": 0.3,
    "moderate": 0.6,
    "changed_light": 1.0,
}


def camera_intrinsics(width: int, height: int, focal_length_mm: float,
                      sensor_size_mm: tuple[float, float]) -> Intrinsics:
    """Pinhole intrinsics of the phone camera (principal point at the centre)."""
    return Intrinsics.from_focal_length_mm(width, height, focal_length_mm, *sensor_size_mm)


# ------------------------------------------------------------------- optics
def _world_rays(intr: Intrinsics, pose: Pose) -> np.ndarray:
    """Unit world directions of every pixel centre, (H, W, 3) float32 (no distortion)."""
    xn = ((np.arange(intr.width) - intr.cx) / intr.fx).astype(np.float32)
    yn = ((np.arange(intr.height) - intr.cy) / intr.fy).astype(np.float32)
    R = pose.R.astype(np.float32)
    # d_world = R.T @ (xn, yn, 1): separable in rows and columns.
    d = xn[None, :, None] * R[0] + yn[:, None, None] * R[1] + R[2]
    return _unit(d)


def _unit(v: np.ndarray) -> np.ndarray:
    """Vectors along the last axis scaled to unit length (float32, fast)."""
    length = np.sqrt(np.einsum("...i,...i->...", v, v))
    return v / np.maximum(length, 1e-12)[..., None]


def _face_table(scene: Scene, vertex_normals: np.ndarray) -> np.ndarray:
    """Per-face data for barycentric interpolation, (F, 22) float32.

    Columns: v0 (3), e0 = v1 − v0 (3), e1 = v2 − v0 (3), e0·e0, e0·e1, e1·e1,
    1 / (Gram determinant), then the three vertex normals (9). One gather of
    this table per pixel is much faster than gathering each piece.
    """
    tri = scene.vertices[scene.faces]
    e0 = tri[:, 1] - tri[:, 0]
    e1 = tri[:, 2] - tri[:, 0]
    d00 = np.einsum("ij,ij->i", e0, e0)
    d01 = np.einsum("ij,ij->i", e0, e1)
    d11 = np.einsum("ij,ij->i", e1, e1)
    inv = 1.0 / np.maximum(d00 * d11 - d01 * d01, 1e-18)
    vn = vertex_normals[scene.faces].reshape(-1, 9)
    table = np.column_stack([tri[:, 0], e0, e1, d00, d01, d11, inv, vn])
    return np.ascontiguousarray(table, dtype=np.float32)


def _smooth_normals(table: np.ndarray, face: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """Per-point normals interpolated from vertex normals (Phong), (N, 3) float32.

    Barycentric coordinates are recovered from the hit point, so no extra
    ray cast is needed; smooth normals avoid the faceted look of flat shading.

    Parameters
    ----------
    table : (F, 22) float32 array
        From :func:`_face_table`.
    face : (N,) int array
        The face each point lies on.
    xyz : (N, 3) array
        The points, metres.
    """
    out = np.empty((len(face), 3), np.float32)
    step = 1 << 20  # chunks bound the memory of the gathered table
    for lo in range(0, len(face), step):
        t = np.take(table, face[lo : lo + step], axis=0)
        p = xyz[lo : lo + step].astype(np.float32) - t[:, 0:3]
        d20 = np.einsum("ij,ij->i", p, t[:, 3:6])
        d21 = np.einsum("ij,ij->i", p, t[:, 6:9])
        b1 = np.clip((t[:, 11] * d20 - t[:, 10] * d21) * t[:, 12], 0.0, 1.0)
        b2 = np.clip((t[:, 9] * d21 - t[:, 10] * d20) * t[:, 12], 0.0, 1.0)
        b0 = 1.0 - b1 - b2
        n = b0[:, None] * t[:, 13:16] + b1[:, None] * t[:, 16:19] + b2[:, None] * t[:, 19:22]
        out[lo : lo + step] = _unit(n)
    return out


def vertex_normals_of(scene: Scene) -> np.ndarray:
    """Area-weighted outward vertex normals of a scene's mesh, (V, 3)."""
    fn = scene.face_array("normals").astype(np.float64)
    tri = scene.vertices[scene.faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    vn = np.zeros_like(scene.vertices)
    for k in range(3):
        np.add.at(vn, scene.faces[:, k], fn * area[:, None])
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)


_LINEAR_LUT = ((np.arange(256, dtype=np.float64) / 255.0) ** _SRGB_GAMMA).astype(np.float32)


def _to_linear(rgb_u8: np.ndarray) -> np.ndarray:
    """8-bit sRGB-ish values to linear light (a table: no per-pixel pow)."""
    return _LINEAR_LUT[rgb_u8]


def _sky(dirs: np.ndarray, cond: PhotoConditions, clouds: Lattice) -> np.ndarray:
    """Linear RGB of the sky seen along unit directions (..., 3)."""
    el = np.arcsin(np.clip(dirs[..., 2], -1.0, 1.0))
    up = np.clip(el, 0.0, None)
    zenith = np.float32([0.16, 0.30, 0.62])
    horizon = np.float32([0.70, 0.77, 0.86])
    f = (1.0 - np.exp(-up / 0.32))[..., None]
    sky = horizon * (1.0 - f) + zenith * f
    # Brighter around the sun.
    cos_sun = np.clip(dirs @ cond.sun.astype(np.float32), -1.0, 1.0)
    sky = sky + (0.35 * np.exp((cos_sun - 1.0) / 0.08))[..., None] * np.float32([1.0, 0.95, 0.85])
    # Clouds on a plane 1.5 km up: perspective makes them flatten toward the horizon.
    dz = np.maximum(dirs[..., 2], 0.02)
    px = (dirs[..., 0] / dz * 1500.0 - clouds.x0) / clouds.cell
    py = (dirs[..., 1] / dz * 1500.0 - clouds.s0) / clouds.cell
    n = clouds.data.shape[0]
    px = np.abs(np.mod(px, 2 * (n - 1)) - (n - 1)).astype(np.float32)
    py = np.abs(np.mod(py, 2 * (n - 1)) - (n - 1)).astype(np.float32)
    c = cv2.remap(clouds.data, px, py, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    thresh = 1.5 - 2.6 * cond.cloud_cover
    cover = smoothstep((c - thresh) / 1.4) ** 1.5 * smoothstep(up / 0.08)
    # Thick cloud is grey underneath, thin cloud bright.
    belly = 1.0 - 0.35 * smoothstep((c - thresh - 0.6) / 1.5)
    cloud_col = belly[..., None] * np.float32([0.95, 0.95, 0.97])
    sky = sky * (1.0 - cover[..., None]) + cloud_col * cover[..., None]
    # Below the horizon (beyond the model's edge): hazy distant land.
    land = np.float32([0.22, 0.24, 0.20])
    below = smoothstep(-el / 0.01)[..., None]
    return (sky * (1.0 - below) + land * below).astype(np.float32)


def synthesize_photo(
    scene: Scene,
    intrinsics: Intrinsics,
    pose: Pose,
    conditions: PhotoConditions,
    vertex_normals: np.ndarray | None = None,
    supersample: float = 1.5,
) -> np.ndarray:
    """A photo-like image of an albedo-textured scene under given conditions.

    Parameters
    ----------
    scene : Scene
        The mesh textured with its ALBEDO (reflectance) image.
    intrinsics : Intrinsics
        The camera.
    pose : Pose
        ``cam_from_world`` of the photo.
    conditions : PhotoConditions
        Light, weather and camera.
    vertex_normals : (V, 3) array, optional
        Outward vertex normals for smooth shading (computed when not given).
    supersample : float
        Render at this factor and area-average: each photo pixel integrates
        its footprint, like a real sensor (no texture aliasing). 1.5 is
        nearly as clean as 2 at half the cost.

    Returns
    -------
    (H, W, 3) uint8 array
        The photo before JPEG compression (sRGB).
    """
    cond = conditions
    rng = rng_for(cond.seed, 7)
    if vertex_normals is None:
        vertex_normals = vertex_normals_of(scene)
    res = render(scene, intrinsics, pose, scale=float(supersample), mode="color")
    h, w = res.shape
    mask = res.mask
    face = res.face_id[mask]
    xyz = res.xyz[mask]
    sun = cond.sun.astype(np.float32)

    n_s = _smooth_normals(_face_table(scene, vertex_normals), face, xyz)
    n_geo = res.normal[mask]
    cos_i = np.clip(n_s @ sun, 0.0, None)
    lit = (n_geo @ sun > 0.0).astype(np.float32)  # the facet itself faces the sun
    if cond.shadows:
        idx = np.flatnonzero((cos_i > 0) & (lit > 0))
        if len(idx):
            origin = xyz[idx] + 0.04 * n_geo[idx] + 0.02 * sun
            hits = scene.cast_rays(origin, np.broadcast_to(sun, (len(idx), 3)))
            lit[idx[hits.hit]] = 0.0
    # Penumbra: the sun's disc and the mesh's facets soften shadow edges.
    # (normalised by the blurred mask, so the sky does not darken the skyline).
    lit_img = np.zeros((h, w), np.float32)
    lit_img[mask] = lit
    lit_img = cv2.GaussianBlur(lit_img, (0, 0), 0.8 * supersample)
    weight = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), 0.8 * supersample)
    lit = lit_img[mask] / np.maximum(weight[mask], 1e-3)

    amb = cond.ambient
    sky_light = np.float32(cond.sky_color) * (0.8 + 0.2 * np.clip(n_s[:, 2:3], 0.0, 1.0))
    irradiance = amb * sky_light + (1.0 - amb) * (cos_i * lit)[:, None] * np.float32(cond.sun_color)
    albedo = _to_linear(res.rgb[mask])

    albedo = _foreground_detail(albedo, res.xyz, mask, n_s, pose.center)
    if cond.wet_fraction > 0:
        albedo = _wet(albedo, xyz, n_s, cond, rng, scene.bounds)
    radiance = albedo * irradiance

    # Aerial perspective: distant surfaces fade toward the horizon sky.
    rel = xyz - pose.center.astype(np.float32)
    dist = np.sqrt(np.einsum("ij,ij->i", rel, rel))
    fade = (1.0 - np.exp(-cond.haze * dist / 100.0))[:, None]
    radiance = radiance * (1.0 - fade) + fade * np.float32([0.62, 0.68, 0.78]) * 0.8

    # Fractal clouds: octaves of smooth noise on one lattice.
    clouds = smooth_lattice(rng, (0.0, 4000.0), (0.0, 4000.0), (160.0, 160.0), cells_per_sigma=16.0)
    for sigma, amp in ((50.0, 0.5), (16.0, 0.25), (5.0, 0.12)):
        white = rng.standard_normal(clouds.data.shape, dtype=np.float32)
        octave = ndimage.gaussian_filter(white, sigma / clouds.cell, mode="wrap")
        clouds.data += amp * octave / max(float(octave.std()), 1e-9)
    # Area-average the surface to photo pixels; the smooth sky fills the
    # uncovered share of each pixel (so the skyline is anti-aliased too).
    size = (intrinsics.width, intrinsics.height)
    img = np.zeros((h, w, 3), np.float32)
    img[mask] = radiance
    img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    cover = cv2.resize(mask.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    img += (1.0 - cover)[..., None] * _sky(_world_rays(intrinsics, pose), cond, clouds)
    return _camera(img, intrinsics, cond, rng)


def _foreground_detail(albedo: np.ndarray, xyz_img: np.ndarray, mask: np.ndarray,
                       n: np.ndarray, center: np.ndarray) -> np.ndarray:
    """Grass detail on near, gentle ground, finer than the model's texture.

    Close to the camera the photo resolves far more than the model's texture
    holds, as with real photos of a photogrammetric model's site.
    """
    from .noise import sample_detail

    xyz = xyz_img[mask]
    dist = np.sqrt(np.einsum("ij,ij->i", xyz - center.astype(np.float32), xyz - center.astype(np.float32)))
    w = smoothstep((110.0 - dist) / 80.0) * smoothstep((n[:, 2] - 0.75) / 0.15)
    sel = np.flatnonzero(w > 0.01)
    if len(sel) == 0:
        return albedo
    x, y = xyz[sel, 0], xyz[sel, 1]
    g = (0.22 * sample_detail("grass", x, y, 2.9, 12.0, (40.0, 300.0))
         + 0.22 * sample_detail("grass", x, y, 0.9, 31.0)
         + 0.16 * sample_detail("grass", x, y, 0.31, -53.0, (200.0, 70.0)))
    out = albedo.copy()
    out[sel] *= np.exp(w[sel] * g)[:, None]
    return out


def _wet(albedo: np.ndarray, xyz: np.ndarray, n: np.ndarray, cond: PhotoConditions,
         rng: np.random.Generator, bounds: np.ndarray) -> np.ndarray:
    """Darken (and saturate) wet patches and seepage streaks on steep rock.

    The patterns live on the surface (in x and z over the model's ``bounds``),
    so they do not depend on the image resolution.
    """
    from scipy.special import ndtri

    lo, hi = bounds
    xr, zr = (float(lo[0]), float(hi[0])), (float(lo[2]), float(hi[2]))
    patches = smooth_lattice(rng, xr, zr, (5.0, 3.0))
    streaks = smooth_lattice(rng, xr, zr, (0.5, 6.0), cells_per_sigma=2.0)
    field = 0.6 * patches.at(xyz[:, 0], xyz[:, 2]) + 0.8 * streaks.at(xyz[:, 0], xyz[:, 2])
    field /= math.hypot(0.6, 0.8)
    thresh = float(ndtri(1.0 - cond.wet_fraction))
    wet = smoothstep((field - thresh) / 0.35) * smoothstep((0.75 - n[:, 2]) / 0.2)
    wet = wet[:, None].astype(np.float32)
    lum = albedo @ np.float32([0.2126, 0.7152, 0.0722])
    sat = lum[:, None] + (albedo - lum[:, None]) * (1.0 + 0.35 * wet)
    return np.clip(sat, 0.0, None) * (1.0 - wet * (1.0 - cond.wet_darkening))


def _camera(img: np.ndarray, intr: Intrinsics, cond: PhotoConditions,
            rng: np.random.Generator) -> np.ndarray:
    """Linear radiance → 8-bit sRGB through a phone camera's pipeline."""
    h, w = img.shape[:2]
    # Vignetting (optics, before the sensor).
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    r2 = ((xx - intr.cx) ** 2 + (yy - intr.cy) ** 2) / (intr.cx**2 + intr.cy**2)
    img = img * (1.0 - cond.vignetting * r2)[..., None]
    if cond.blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), cond.blur_sigma)
    img = img * np.float32(cond.white_balance)
    # Auto-exposure: the scene's log-average luminance to a mid-tone.
    lum = img @ np.float32([0.2126, 0.7152, 0.0722])
    key = float(np.exp(np.mean(np.log(lum + 1e-4))))
    img = img * (0.2 / max(key, 1e-4) * cond.exposure)
    # Tone curve: soft shoulder (highlights roll off), gamma, gentle S-curve.
    img = img / (1.0 + 0.35 * img)
    img = np.clip(img * 1.35, 0.0, 1.0) ** (1.0 / cond.gamma)
    img = img + cond.contrast * (smoothstep(img) - img)
    out = img * 255.0
    # Sensor noise: photon noise grows with signal; a little chroma noise.
    sigma = cond.noise_sigma * np.sqrt(0.35 + out / 128.0)
    noise = rng.standard_normal(out.shape, dtype=np.float32)
    noise = 0.8 * noise + 0.2 * noise.mean(axis=2, keepdims=True)
    out = out + sigma * noise
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


# --------------------------------------------------------------- viewpoints
def view_fractions(scene: Scene, intr: Intrinsics, pose: Pose, face_rock: np.ndarray,
                   scale: float = 0.125) -> dict[str, float]:
    """Shares of a quick low-resolution view: rock, ground/vegetation, sky, void.

    ``void`` is a ray that points below the horizon yet misses the model
    (the view runs off the model's edge).
    """
    res = render(scene, intr, pose, scale=scale, mode="shaded")
    dirs = _world_rays(res.intrinsics, pose)
    hit = res.mask
    rock = np.zeros_like(hit)
    rock[hit] = face_rock[res.face_id[hit]] > 0.5
    miss = ~hit
    n = float(hit.size)
    return {
        "rock": float(rock.sum() / n),
        "ground": float((hit & ~rock).sum() / n),
        "sky": float((miss & (dirs[..., 2] >= -0.005)).sum() / n),
        "void": float((miss & (dirs[..., 2] < -0.005)).sum() / n),
        "min_depth": float(np.nanmin(res.depth)) if hit.any() else float("nan"),
    }


def sample_poses(
    scene: Scene,
    intr: Intrinsics,
    face_line: Callable[[float], float],
    ground_y_min: Callable[[float], float],
    face_rock: np.ndarray,
    n: int,
    rng: np.random.Generator,
    x_half: float,
    distance_m: tuple[float, float] = (80.0, 120.0),
    trend_range_deg: float = 25.0,
    plunge_range_deg: tuple[float, float] = (-12.0, -3.0),
    roll_range_deg: float = 3.0,
    height_above_ground_m: float = 1.6,
    max_tries: int = 100,
) -> list[tuple[Pose, dict[str, float]]]:
    """Camera poses of a geologist on the ground apron photographing the face.

    Each pose aims at a point of the face (spread along it across the
    photos) from 80–120 m, turned by up to ±25° from north, looking slightly
    up; a quick low-resolution view checks that the frame shows mostly rock,
    some sky and some ground, and does not run off the model.

    Parameters
    ----------
    face_line : callable
        ``y = face_line(x)``: the face's mid-height line in plan.
    ground_y_min : callable
        ``y_min = ground_y_min(x)``: the apron's southern edge.
    x_half : float
        Half the model's extent along x.

    Returns
    -------
    list of (Pose, view fractions)
    """
    out = []
    top = float(scene.bounds[1, 2]) + 10.0
    for k in range(n):
        best, best_score, n_ok = None, -np.inf, 0
        lo, hi = -0.45 + 0.9 * k / n, -0.45 + 0.9 * (k + 1) / n
        for _ in range(max_tries):
            xa = rng.uniform(lo, hi) * x_half
            trend = rng.uniform(-trend_range_deg, trend_range_deg)
            dist = rng.uniform(*distance_m)
            plunge = rng.uniform(*plunge_range_deg)
            roll = rng.uniform(-roll_range_deg, roll_range_deg)
            t = math.radians(trend)
            xc = xa - dist * math.sin(t)
            yc = face_line(xa) - dist * math.cos(t)
            if abs(xc) > x_half - 8.0 or yc < ground_y_min(xc) + 8.0:
                continue
            hits = scene.cast_rays(np.array([[xc, yc, top]]), np.array([[0.0, 0.0, -1.0]]))
            if not hits.hit[0]:
                continue
            zc = top - float(hits.distance[0]) + height_above_ground_m
            pose = Pose.from_center(rotation_from_attitude(trend % 360.0, plunge, roll),
                                    np.array([xc, yc, zc]))
            f = view_fractions(scene, intr, pose, face_rock)
            ok = (f["rock"] >= 0.33 and 0.04 <= f["sky"] <= 0.4 and f["ground"] >= 0.03
                  and f["void"] <= 0.002 and f["min_depth"] > 2.0)
            # Prefer frames filled with rock, with a little sky.
            score = f["rock"] - 10.0 * f["void"] - 0.5 * max(0.0, f["sky"] - 0.3) + (1.0 if ok else 0.0)
            if score > best_score:
                best, best_score = (pose, f), score
            n_ok += ok
            if n_ok >= 8:  # the best of a few good frames
                break
        if best is None:
            raise RuntimeError("no camera position found on the ground apron")
        out.append(best)
    return out


# ------------------------------------------------------------ check points
def select_check_points(
    scene: Scene,
    intr: Intrinsics,
    pose: Pose,
    face_rock: np.ndarray,
    n: int,
    rng: np.random.Generator,
) -> list[dict[str, Any]]:
    """Surface points seen by the photo, with their exact pixel positions.

    Candidates are integer pixels spread over the frame; a candidate is kept
    when its ray hits the surface away from an occluding edge (its neighbours
    two pixels away see the surface at a similar range). The stored pixel is
    the projection of the stored point with the true pose, so the two agree to
    rounding error.
    """
    gx, gy = 12, 9
    cells = [(i, j) for j in range(gy) for i in range(gx)]
    px = []
    for i, j in cells:
        c = int(rng.uniform(i, i + 1) / gx * (intr.width - 8)) + 4
        r = int(rng.uniform(j, j + 1) / gy * (intr.height - 8)) + 4
        px.append((c, r))
    px = np.array(px, np.float64)
    offsets = np.array([[0, 0], [2, 0], [-2, 0], [0, 2], [0, -2]], np.float64)
    allpx = (px[:, None, :] + offsets[None]).reshape(-1, 2)
    origin, dirs = pose.rays(intr, allpx)
    hits = scene.cast_rays(origin, dirs)
    dist = hits.distance.reshape(len(px), 5)
    ok = np.isfinite(dist).all(axis=1)
    dist = np.where(ok[:, None], dist, 0.0)
    ok &= (np.abs(dist[:, 1:] - dist[:, :1]) < 0.04 * dist[:, :1]).all(axis=1)
    pts = scene.surface_points(hits).reshape(len(px), 5, 3)[:, 0]
    face = hits.face_id.reshape(len(px), 5)[:, 0]
    idx = np.flatnonzero(ok)
    rock = face_rock[face[idx]] > 0.5 if len(idx) else np.zeros(0, bool)
    # Mostly rock (where registration is judged), some ground.
    order = np.concatenate([rng.permutation(idx[rock]), rng.permutation(idx[~rock])])
    n_ground = min(int((~rock).sum()), max(n // 6, 1))
    chosen = list(order[: n - n_ground]) + list(rng.permutation(idx[~rock])[:n_ground])
    chosen = sorted(set(int(c) for c in chosen))[:n]
    out = []
    for c in chosen:
        p = pts[c]
        uv = pose.project(intr, p[None])[0]
        out.append({
            "xyz": [float(v) for v in p],
            "pixel": [float(uv[0]), float(uv[1])],
            "surface": "rock" if face_rock[face[c]] > 0.5 else "ground",
            "distance_m": float(np.linalg.norm(p - pose.center)),
        })
    return out


# --------------------------------------------------------------------- EXIF
def _dms(value: float):
    from PIL.TiffImagePlugin import IFDRational

    v = abs(value)
    d = int(v)
    m = int((v - d) * 60)
    s = (v - d - m / 60.0) * 3600.0
    return (IFDRational(d, 1), IFDRational(m, 1), IFDRational(int(round(s * 10000)), 10000))


def make_exif(
    make: str,
    model: str,
    focal_length_mm: float,
    focal_35mm: int,
    when: str | datetime | None,
    lat: float,
    lon: float,
    alt: float,
    width: int,
    height: int,
) -> bytes:
    """EXIF block of a phone photo (camera, focal lengths, time, GPS).

    Parameters
    ----------
    when : str or datetime or None
        ``"YYYY:MM:DD HH:MM:SS"``, or a time-zone aware datetime: then the
        Exif 2.31 ``OffsetTimeOriginal`` and the GPS time stamp (UTC) are
        written too, as phones do, so the capture instant is unambiguous.
        None: no capture time at all (``DateTime``, ``DateTimeOriginal``
        left out), for a photo whose sun no instant at the site gives.
    lat, lon : float
        WGS84 degrees.
    alt : float
        Altitude, metres.
    """
    from PIL import Image
    from PIL.ExifTags import GPS, IFD, Base
    from PIL.TiffImagePlugin import IFDRational

    aware = isinstance(when, datetime) and when.tzinfo is not None
    instant = when if isinstance(when, datetime) else None
    if isinstance(when, datetime):
        when = when.strftime("%Y:%m:%d %H:%M:%S")
    exif = Image.Exif()
    exif[Base.Make] = make
    exif[Base.Model] = model
    if when is not None:
        exif[Base.DateTime] = when
    exif[Base.Orientation] = 1
    sub = exif.get_ifd(IFD.Exif)
    sub[Base.FocalLength] = IFDRational(int(round(focal_length_mm * 100)), 100)
    sub[Base.FocalLengthIn35mmFilm] = int(focal_35mm)
    if when is not None:
        sub[Base.DateTimeOriginal] = when
    if aware:
        offset = instant.utcoffset()
        minutes = int(offset.total_seconds() // 60)
        sign = "-" if minutes < 0 else "+"
        sub[Base.OffsetTimeOriginal] = f"{sign}{abs(minutes) // 60:02d}:{abs(minutes) % 60:02d}"
    sub[Base.ExifImageWidth] = int(width)
    sub[Base.ExifImageHeight] = int(height)
    gps = exif.get_ifd(IFD.GPSInfo)
    gps[GPS.GPSVersionID] = b"\x02\x03\x00\x00"
    gps[GPS.GPSLatitudeRef] = "N" if lat >= 0 else "S"
    gps[GPS.GPSLatitude] = _dms(lat)
    gps[GPS.GPSLongitudeRef] = "E" if lon >= 0 else "W"
    gps[GPS.GPSLongitude] = _dms(lon)
    gps[GPS.GPSAltitudeRef] = b"\x00" if alt >= 0 else b"\x01"
    gps[GPS.GPSAltitude] = IFDRational(int(round(abs(alt) * 100)), 100)
    if aware:
        utc = instant.astimezone(timezone.utc)
        gps[GPS.GPSDateStamp] = utc.strftime("%Y:%m:%d")
        gps[GPS.GPSTimeStamp] = (IFDRational(utc.hour, 1), IFDRational(utc.minute, 1),
                                 IFDRational(utc.second, 1))
    return exif.tobytes()
