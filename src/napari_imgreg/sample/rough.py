"""A rough true surface under another sun, and the smoother model a user has of it.

The sample generator's photos are rendered from the same mesh the user
registers against, so nothing in them is finer than the model. Real cliffs
are rough at every scale: sandstone beds stand tens of centimetres to a metre
proud of the mudstones, gullies cut the face, the rock has grain. A
photogrammetric model keeps the broad form and bakes the rest into its texture
under the survey day's (high, diffuse) light; under a low sun on another day
that relief throws shading and shadows that move keypoints off the rock (a
*bias*, not noise). This module makes that case from a generated scene
(:func:`napari_imgreg.sample.generate_outcrop`):

* :func:`rough_displacement` — the sub-model relief, metres along the surface
  normal of every grid vertex: beds standing proud (:attr:`RoughSpec.bed_relief_m`),
  gullies, face roughness;
* :func:`build_rough_scene` — writes the user's model (the relief smoothed to
  :attr:`RoughSpec.model_resolution_m`, as a decimated photogrammetric model
  keeps it, the same ≈ 1.2 M-triangle grid) with a texture baked from the true
  surface under the diffuse survey light, and keeps the true surface for the
  photos;
* :class:`RoughScene` ``.photo`` — a photo of the true surface (bump-mapped
  grain, relief shading and cast shadows of the photo's sun, phone effects),
  :func:`rough_conditions` the low, oblique sun and phone of a changed-light
  photo, :func:`frame_check_points` check points over the whole frame (near
  ground included) on the true surface, and :func:`capture_time` the EXIF time
  where that sun is possible at the site (None where it is not).

Nothing here changes the generator's own outputs.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from .._atomic import atomic_path, atomic_write
from ..camera import Intrinsics, Pose
from ..render import render
from .noise import rng_for, separable_sample, smoothstep
from .outcrop import plane_normal
from .photo import (
    PhotoConditions,
    sun_vector,
    synthesize_photo,
    vertex_normals_of,
)
from ..scene import Scene

__all__ = [
    "ROUGH_VERSION",
    "RoughScene",
    "RoughSpec",
    "build_rough_scene",
    "capture_time",
    "frame_check_points",
    "micro_shading",
    "relief_normals",
    "rough_conditions",
    "rough_displacement",
]

#: Bump when what :func:`build_rough_scene` writes changes (cache key).
ROUGH_VERSION = "2"  # 2: harsher changed light (model 1.5 m, sun 10–25°, grain, phone)

#: Random streams of this module (see :func:`napari_imgreg.sample.noise.rng_for`).
_S_GRAIN, _S_BEDS, _S_GULLIES, _S_ROUGH, _S_LIGHT = 8100, 8200, 8300, 8400, 8500


@dataclass(frozen=True)
class RoughSpec:
    """The sub-model relief of the true surface, the user's model and the changed light.

    Lengths in metres, angles in degrees.

    Attributes
    ----------
    bed_relief_m : (float, float)
        Each sandstone bed stands proud of the mudstones by an amount drawn
        in this range. Default (0.4, 1.2).
    bed_thickness_m : (float, float)
        Thickness of each bed (sandstone and mudstone alternate). Default (1.0, 4.0).
    bed_edge_m : float
        Rounding of a bed's edge (its contacts). Default 0.25.
    bedding_dip_deg, bedding_dip_direction_deg : float
        Attitude of the bedding (the generator's default). Default 12, 200.
    n_gullies : int
        Gullies cut down the face. Default 12.
    gully_depth_m, gully_width_m : (float, float)
        Depth and half-width of each gully. Defaults (0.8, 2.0), (0.8, 2.5).
    roughness_m : float
        RMS of the face's roughness at 0.4–1.5 m (ground: a third). Default 0.2.
    grain_rms_slope : float
        RMS slope of the bump-mapped grain below the grid (per texel). Default 0.45.
    model_resolution_m : float
        The user's model keeps relief only above this scale (Gaussian sigma of
        the smoothing of the relief): what a decimated photogrammetric model
        resolves. Default 1.5.
    survey_sun_azimuth_deg, survey_sun_elevation_deg, survey_ambient : float
        The survey day's light the model's texture is baked under: high and
        diffuse. Defaults 170, 60, 0.75.
    sun_elevation_deg : (float, float)
        The photos' sun: elevation range. Default (10, 25): a low sun, whose
        shading of the unresolved relief moves keypoints most.
    sun_oblique_deg : (float, float)
        ... and how far its azimuth is from the face's outward direction
        (east or west, drawn), raking the face. Default (45, 80).
    phone_strength : float
        Strength of the phone's effects (exposure, gamma, white balance,
        vignetting, noise, blur, JPEG; :meth:`PhotoConditions.from_rng`), [0, 1].
        Default 0.9.
    photo_ambient : float
        Sky light of the photos' day (lower: harder shadows). Default 0.25.
    check_grid : (int, int)
        Check points on a grid of this many columns and rows over the whole
        frame, where the true surface is hit. Default (12, 9).
    exif_max_miss_deg : float
        A photo gets an EXIF capture time when an instant of the year puts the
        sun within this of the photo's sun (it is then moved there); otherwise
        none. Default 0.5.
    """

    bed_relief_m: tuple[float, float] = (0.4, 1.2)
    bed_thickness_m: tuple[float, float] = (1.0, 4.0)
    bed_edge_m: float = 0.25
    bedding_dip_deg: float = 12.0
    bedding_dip_direction_deg: float = 200.0
    n_gullies: int = 12
    gully_depth_m: tuple[float, float] = (0.8, 2.0)
    gully_width_m: tuple[float, float] = (0.8, 2.5)
    roughness_m: float = 0.2
    grain_rms_slope: float = 0.45
    model_resolution_m: float = 1.5
    survey_sun_azimuth_deg: float = 170.0
    survey_sun_elevation_deg: float = 60.0
    survey_ambient: float = 0.75
    sun_elevation_deg: tuple[float, float] = (10.0, 25.0)
    sun_oblique_deg: tuple[float, float] = (45.0, 80.0)
    phone_strength: float = 0.9
    photo_ambient: float = 0.25
    check_grid: tuple[int, int] = (12, 9)
    exif_max_miss_deg: float = 0.5

    def __post_init__(self) -> None:
        for name in ("bed_relief_m", "bed_thickness_m", "gully_depth_m", "gully_width_m",
                     "sun_elevation_deg", "sun_oblique_deg"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise ValueError(f"{name} must be a range 0 <= low <= high, not {(lo, hi)}")
        if self.model_resolution_m <= 0 or self.bed_edge_m <= 0:
            raise ValueError("model_resolution_m and bed_edge_m must be positive")
        if not 0 <= self.phone_strength <= 1:
            raise ValueError(f"phone_strength must be in [0, 1], not {self.phone_strength}")

    def to_dict(self) -> dict[str, Any]:
        return json.loads(json.dumps(asdict(self)))


# ------------------------------------------------------------ grain (texels)
def relief_normals(scene: Scene, grid: tuple[int, int], texture_size: int, seed: int,
                   rms_slope: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Per-texel normals of the mesh and of the rock's micro-relief, (T, T, 3) float32 each.

    The generated mesh resolves relief down to its grid (≈ 0.3 m); real rock
    is rough at every scale below that, and its shading changes with the sun.
    A self-similar height field (Gaussian-filtered noise at 4, 11, 27 and 65
    cm) is scaled to an RMS slope of ``rms_slope`` and perturbs the mesh
    normal of every texel (bump mapping in the grid's tangent frame).

    Parameters
    ----------
    scene : Scene
        A generated grid mesh (vertices in grid order, ``grid`` = (nx, ns)).
    grid : (int, int)
    texture_size : int
        T, texels per side.
    seed : int
    rms_slope : float
        RMS slope of the micro-relief (dimensionless).

    Returns
    -------
    n, n2 : (T, T, 3) float32 arrays
        Unit normals without and with the micro-relief.
    """
    nx, ns = grid
    T = texture_size
    X = scene.vertices.reshape(ns, nx, 3)
    vn = vertex_normals_of(scene).reshape(ns, nx, 3)
    ri = (1.0 - (np.arange(T) + 0.5) / T) * (ns - 1)  # v = 0 is the texture's bottom row
    ci = (np.arange(T) + 0.5) / T * (nx - 1)
    n = separable_sample(vn, ri, ci)
    n /= np.linalg.norm(n, axis=-1, keepdims=True) + 1e-9
    du = separable_sample(np.gradient(X, axis=1), ri, ci) * ((nx - 1) / T)  # metres per texel
    dv = -separable_sample(np.gradient(X, axis=0), ri, ci) * ((ns - 1) / T)  # down the texture
    lu = np.linalg.norm(du, axis=-1)
    lv = np.linalg.norm(dv, axis=-1)
    du /= lu[..., None] + 1e-9
    dv /= lv[..., None] + 1e-9
    rng = rng_for(seed, _S_GRAIN)
    h = np.zeros((T, T), np.float32)
    for sigma, amp in ((0.8, 0.25), (2.0, 0.5), (5.0, 1.0), (12.0, 1.2)):
        w = ndimage.gaussian_filter(rng.standard_normal((T, T), dtype=np.float32), sigma, mode="wrap")
        h += amp * sigma * w / w.std()
    gy, gx = np.gradient(h)
    sx = gx / np.maximum(lu, 1e-4)
    sy = gy / np.maximum(lv, 1e-4)
    k = rms_slope / float(np.sqrt(np.mean(sx * sx + sy * sy)))
    n2 = n - k * (sx[..., None] * du + sy[..., None] * dv)
    n2 /= np.linalg.norm(n2, axis=-1, keepdims=True)
    return n.astype(np.float32), n2.astype(np.float32)


def micro_shading(n: np.ndarray, n2: np.ndarray, sun: np.ndarray, ambient: float) -> np.ndarray:
    """Lambert shading of the micro-relief relative to the mesh's own, (T, T), in [0.2, 4]."""
    sun = np.asarray(sun, np.float32)
    s0 = ambient + (1.0 - ambient) * np.clip(n @ sun, 0.0, None)
    s1 = ambient + (1.0 - ambient) * np.clip(n2 @ sun, 0.0, None)
    return np.clip(s1 / np.maximum(s0, 1e-3), 0.2, 4.0)


# --------------------------------------------------------- relief (vertices)
def _grid_spacing(X: np.ndarray) -> tuple[float, float]:
    """Median vertex spacing along the grid's rows and columns, metres."""
    ds = float(np.median(np.linalg.norm(np.diff(X, axis=0), axis=-1)))
    dx = float(np.median(np.linalg.norm(np.diff(X, axis=1), axis=-1)))
    return ds, dx


def face_weight(normals: np.ndarray) -> np.ndarray:
    """How much of a vertex is cliff face (1) rather than ground (0), from its normal's steepness."""
    return smoothstep((0.8 - normals[..., 2]) / 0.25)


def rough_displacement(X: np.ndarray, normals: np.ndarray, spec: RoughSpec, seed: int
                       ) -> np.ndarray:
    """The sub-model relief of a grid surface, metres along each vertex's outward normal.

    Parameters
    ----------
    X : (ns, nx, 3) array
        Grid vertices, model frame, metres (rows up the profile, columns along x).
    normals : (ns, nx, 3) array
        Their unit outward normals.
    spec : RoughSpec
    seed : int

    Returns
    -------
    (ns, nx) float array
        Beds standing proud (sandstone +``bed_relief_m``, mudstone 0, edges
        rounded over ``bed_edge_m``) and gullies (negative), on the face only;
        roughness on the face and, a third as strong, on the ground.
    """
    ns, nx = X.shape[:2]
    face = face_weight(normals)
    ds, dx = _grid_spacing(X)
    # Beds: alternating sandstone (proud) and mudstone along the bedding normal.
    h = X @ plane_normal(spec.bedding_dip_deg, spec.bedding_dip_direction_deg)
    rng = rng_for(seed, _S_BEDS)
    lo, hi = float(h.min()) - 1.0, float(h.max()) + 1.0
    tops, amps = [lo], []
    while tops[-1] < hi:
        tops.append(tops[-1] + rng.uniform(*spec.bed_thickness_m))
    tops = np.array(tops)
    amps = rng.uniform(*spec.bed_relief_m, size=len(tops))
    amps[1::2] = 0.0  # every other bed is recessed mudstone
    k = np.clip(np.searchsorted(tops, h) - 1, 0, len(tops) - 2)
    dist = np.minimum(h - tops[k], tops[k + 1] - h)
    beds = amps[k] * np.sqrt(smoothstep(dist / spec.bed_edge_m))
    # Gullies: troughs down the face with a slight meander.
    g_rng = rng_for(seed, _S_GULLIES)
    x = X[..., 0]
    gullies = np.zeros((ns, nx))
    x_lo, x_hi = np.percentile(x, [10, 90])
    for _ in range(spec.n_gullies):
        x0 = g_rng.uniform(x_lo, x_hi)
        depth = g_rng.uniform(*spec.gully_depth_m)
        width = g_rng.uniform(*spec.gully_width_m)
        phase = g_rng.uniform(0, 2 * np.pi)
        xc = x0 + 1.5 * np.sin(X[..., 2] / 7.0 + phase)
        gullies -= depth * np.exp(-(((x - xc) / width) ** 2))
    # Roughness at 0.4-1.5 m.
    r_rng = rng_for(seed, _S_ROUGH)
    rough = np.zeros((ns, nx))
    for scale, amp in ((0.4, 0.5), (0.8, 0.8), (1.5, 1.0)):
        w = ndimage.gaussian_filter(r_rng.standard_normal((ns, nx)), (scale / ds, scale / dx))
        rough += amp * w / (w.std() + 1e-12)
    rough *= spec.roughness_m / (rough.std() + 1e-12)
    return face * (beds + gullies) + (face + (1.0 - face) / 3.0) * rough


def smoothed(displacement: np.ndarray, X: np.ndarray, resolution_m: float) -> np.ndarray:
    """The relief a model of resolution ``resolution_m`` keeps (Gaussian of that sigma on the grid)."""
    ds, dx = _grid_spacing(X)
    return ndimage.gaussian_filter(displacement, (resolution_m / ds, resolution_m / dx),
                                   mode="nearest")


def _grid_normals(X: np.ndarray) -> np.ndarray:
    """Unit normals of a grid surface, oriented like its rows × columns cross product."""
    du = np.gradient(X, axis=1)
    dv = np.gradient(X, axis=0)
    n = np.cross(du, dv)
    return n / (np.linalg.norm(n, axis=-1, keepdims=True) + 1e-12)


def _oriented_normals(scene: Scene, grid: tuple[int, int]) -> np.ndarray:
    """Outward grid normals (ns, nx, 3): as the mesh's vertex normals point."""
    nx, ns = grid
    X = scene.vertices.reshape(ns, nx, 3).astype(np.float64)
    n = _grid_normals(X)
    ref = vertex_normals_of(scene).reshape(ns, nx, 3)
    if np.mean(np.sum(n * ref, axis=-1)) < 0:
        n = -n
    return n


def _write_obj_vertices(src: Path, dst: Path, vertices: np.ndarray) -> None:
    """``src``'s OBJ with its ``v`` lines replaced by ``vertices`` (same order), all else kept."""
    lines = src.read_bytes().split(b"\n")
    v_idx = [i for i, line in enumerate(lines) if line.startswith(b"v ")]
    if len(v_idx) != len(vertices):
        raise ValueError(f"{src}: {len(v_idx)} vertices, not {len(vertices)}")
    for i, p in zip(v_idx, vertices):
        lines[i] = b"v %.4f %.4f %.4f" % (p[0], p[1], p[2])
    with atomic_path(dst) as tmp:
        Path(tmp).write_bytes(b"\n".join(lines))


def build_rough_scene(scene_dir: str | Path, out_dir: str | Path, spec: RoughSpec | None = None
                      ) -> Path:
    """The user's model of a rough outcrop, and its true surface, from a generated scene.

    Parameters
    ----------
    scene_dir : path
        A folder of :func:`napari_imgreg.sample.generate_outcrop` (``scene.json``,
        the OBJ, ``albedo.png``, ``georef.json``, ``dem.tif``).
    out_dir : path
        Written: ``outcrop.obj`` / ``.mtl`` / ``outcrop_texture.jpg`` (the
        user's model: relief smoothed to ``model_resolution_m``, texture baked
        from the true surface under the diffuse survey light), ``true_vertices.npy``
        (the true surface, same faces and texture coordinates), ``albedo.png``,
        ``georef.json``, ``dem.tif``, ``survey.json`` (the survey light),
        ``scene.json`` (with ``rough``: the spec and relief statistics).
    spec : RoughSpec, optional

    Returns
    -------
    Path
        ``out_dir``.
    """
    from PIL import Image

    from ..geo import Georef
    from . import write_survey

    spec = spec or RoughSpec()
    scene_dir, out_dir = Path(scene_dir), Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    manifest = json.loads((scene_dir / "scene.json").read_text(encoding="utf-8"))
    grid = tuple(manifest["grid"])
    nx, ns = grid
    seed = int(manifest["seed"])
    base = Scene.load(scene_dir / manifest["files"]["mesh"], cache=False)
    X = base.vertices.reshape(ns, nx, 3).astype(np.float64)
    normals = _oriented_normals(base, grid)
    d_true = rough_displacement(X, normals, spec, seed)
    d_model = smoothed(d_true, X, spec.model_resolution_m)
    true_v = (X + normals * d_true[..., None]).reshape(-1, 3)
    model_v = (X + normals * d_model[..., None]).reshape(-1, 3)
    np.save(out_dir / "true_vertices.npy", true_v.astype(np.float64))
    for name in ("albedo", "georef", "dem", "material"):
        shutil.copyfile(scene_dir / manifest["files"][name], out_dir / manifest["files"][name])
    _write_obj_vertices(scene_dir / manifest["files"]["mesh"], out_dir / manifest["files"]["mesh"],
                        model_v)
    # The texture: the true surface's look under the survey's diffuse light
    # (what the photogrammetry photographed), albedo × shading with its grain.
    albedo = np.asarray(Image.open(scene_dir / manifest["files"]["albedo"]).convert("RGB"))
    true_scene = Scene(true_v, base.faces, base.uv, albedo, name="true surface")
    _, n2 = relief_normals(true_scene, grid, manifest["texture_size"], seed, spec.grain_rms_slope)
    sun = sun_vector(spec.survey_sun_azimuth_deg, spec.survey_sun_elevation_deg)
    a = spec.survey_ambient
    shade = a + (1.0 - a) * np.clip(n2 @ sun.astype(np.float32), 0.0, None)
    tex = np.clip(albedo * shade[..., None] + 0.5, 0, 255).astype(np.uint8)
    with atomic_path(out_dir / manifest["files"]["texture"]) as p:
        Image.fromarray(tex).save(p, format="JPEG",
                                  quality=int(manifest["spec"]["texture_jpeg_quality"]))
    georef = Georef.load(out_dir / manifest["files"]["georef"])
    write_survey(out_dir, georef, sun, X.reshape(-1, 3).mean(axis=0))
    face = face_weight(normals) > 0.5
    out = dict(manifest)
    out["photos"] = []
    out["survey_sun"] = {"azimuth_deg": spec.survey_sun_azimuth_deg,
                         "elevation_deg": spec.survey_sun_elevation_deg, "ambient": a}
    out["rough"] = {
        "version": ROUGH_VERSION, "spec": spec.to_dict(), "source": scene_dir.name,
        "face_relief_rms_m": round(float(np.std(d_true[face])), 4),
        "relief_not_in_model_rms_m": round(float(np.std((d_true - d_model)[face])), 4),
        "true_surface": "true_vertices.npy",
    }
    out.pop("size", None)
    with atomic_write(out_dir / "scene.json", encoding="utf-8") as fh:
        json.dump(out, fh, indent=1)
    return out_dir


class RoughScene:
    """The true surface of a :func:`build_rough_scene` folder, for photos and check points."""

    def __init__(self, folder: str | Path) -> None:
        from PIL import Image

        from ..geo import Georef

        folder = Path(folder)
        self.folder = folder
        self.manifest = json.loads((folder / "scene.json").read_text(encoding="utf-8"))
        m = self.manifest
        self.spec = RoughSpec(**{k: tuple(v) if isinstance(v, list) else v
                                 for k, v in m["rough"]["spec"].items()})
        model = Scene.load(folder / m["files"]["mesh"], cache=False)
        self.albedo = np.asarray(Image.open(folder / m["files"]["albedo"]).convert("RGB"))
        true_v = np.load(folder / m["rough"]["true_surface"])
        self.scene = Scene(true_v, model.faces, model.uv, self.albedo, name="true surface")
        self.scene.build_engine()
        self.vertex_normals = vertex_normals_of(self.scene)
        self.n, self.n2 = relief_normals(self.scene, tuple(m["grid"]), m["texture_size"],
                                         int(m["seed"]), self.spec.grain_rms_slope)
        self.georef = Georef.load(folder / m["files"]["georef"])
        s = m["survey_sun"]
        self.survey = (s["azimuth_deg"], s["elevation_deg"])

    def photo(self, intrinsics: Intrinsics, pose: Pose, cond: PhotoConditions,
              supersample: float = 1.5) -> np.ndarray:
        """The photo (H, W, 3) uint8 of the true surface under ``cond``: grain, relief
        shading and cast shadows of its sun, the phone's effects (before JPEG)."""
        import copy

        m = micro_shading(self.n, self.n2, cond.sun, cond.ambient)
        scene = copy.copy(self.scene)  # shares the ray engine; own texture
        scene.texture = np.clip(self.albedo * m[..., None] + 0.5, 0, 255).astype(np.uint8)
        return synthesize_photo(scene, intrinsics, pose, cond, self.vertex_normals, supersample)


def rough_conditions(rng: np.random.Generator, spec: RoughSpec, survey_sun: tuple[float, float],
                     face_azimuth_deg: float = 180.0) -> PhotoConditions:
    """A changed-light photo's conditions: a low sun raking the face obliquely
    (``spec.sun_elevation_deg``, ``spec.sun_oblique_deg`` from the face's
    outward azimuth, east or west) and the phone's effects at ``spec.phone_strength``."""
    cond = PhotoConditions.from_rng(rng, spec.phone_strength, survey_sun, spec.survey_ambient)
    side = 1.0 if rng.random() < 0.5 else -1.0
    az = (face_azimuth_deg + side * rng.uniform(*spec.sun_oblique_deg)) % 360.0
    el = rng.uniform(*spec.sun_elevation_deg)
    return replace(cond, sun_azimuth_deg=float(az), sun_elevation_deg=float(el),
                   ambient=spec.photo_ambient, shadows=True)


def survey_conditions(rng: np.random.Generator, spec: RoughSpec) -> PhotoConditions:
    """A photo under the survey day's light (the texture's), mild phone effects."""
    cond = PhotoConditions.from_rng(rng, 0.0, (spec.survey_sun_azimuth_deg,
                                               spec.survey_sun_elevation_deg), spec.survey_ambient)
    return replace(cond, ambient=spec.survey_ambient)


def capture_time(cond: PhotoConditions, georef, center: np.ndarray, spec: RoughSpec,
                 year: int = 2024):
    """The instant the photo's sun is possible at the site, or None.

    Returns
    -------
    (PhotoConditions, SunTime or None)
        With an instant whose sun is within ``spec.exif_max_miss_deg`` of
        ``cond``'s: the conditions moved onto that sun, and the instant. Else
        ``cond`` unchanged and None (the photo then carries no capture time).
    """
    from .suntime import time_for_sun

    st = time_for_sun(cond.sun, georef, center, year)
    if st.miss_deg > spec.exif_max_miss_deg:
        return cond, None
    return replace(cond, sun_azimuth_deg=st.azimuth_deg, sun_elevation_deg=st.elevation_deg), st


def frame_check_points(scene: Scene, intrinsics: Intrinsics, pose: Pose,
                       grid: tuple[int, int] = (12, 9)) -> list[dict[str, Any]]:
    """Check points on a regular grid over the whole frame, where ``scene`` is hit.

    Parameters
    ----------
    scene : Scene
        The true surface.
    intrinsics, pose : the photo's true camera.
    grid : (int, int)
        Columns and rows of the grid (cell centres).

    Returns
    -------
    list of dict
        ``xyz`` (model frame, metres), ``pixel`` (its exact projection),
        ``surface`` ("ground" or "rock" from the normal), ``distance_m``: the
        truth file's ``check_points`` entries.
    """
    scale = min(1.0, 816.0 / intrinsics.width)
    r = render(scene, intrinsics, pose, scale=scale)
    h, w = r.mask.shape
    cols, rows = grid
    out = []
    for j in range(rows):
        for i in range(cols):
            x = int((i + 0.5) / cols * w)
            y = int((j + 0.5) / rows * h)
            if not r.mask[y, x]:
                continue
            xyz = r.xyz[y, x].astype(np.float64)
            pix = pose.project(intrinsics, xyz[None])[0]
            nz = float(r.normal[y, x, 2])
            out.append({"xyz": xyz.tolist(), "pixel": pix.tolist(),
                        "surface": "ground" if nz > 0.8 else "rock",
                        "distance_m": float(np.linalg.norm(xyz - pose.center))})
    return out
