"""Generated terrestrial laser scans of the sample outcrops (issue 16's reference data).

A terrestrial laser scanner (TLS) on a tripod in front of the cliff sweeps its
beam over a regular azimuth × elevation grid and records, for every return,
the range and the strength of the echo. :func:`simulate_scan` does that on a
scene's *true surface* (the rock the photos are rendered from, not the user's
smoothed model): one ray per grid direction, the first hit found with the
scene's Embree engine, in chunks of ``ScanSpec.chunk_rays`` rays.

* **Range**: the exact hit distance plus Gaussian noise of
  ``range_noise_m`` (5 mm), along the ray.
* **Intensity** (no colour: a scanner sees no RGB)::

      I = ρ(surface at the hit) · T(hit) · |cos θ| · f(R) · (1 + σ_I · ε),  clipped to [0, 1]

  ρ is the reflectance of the rock type at the hit (the bed of ``geology.json``
  holding the hit point: sandstone brighter than mudstone, each bed varied by
  ``bed_reflectance_variation``), blended with the cover's reflectance
  (vegetation, scree) where the surface is not bare rock; T the surface's
  *texture* within a bed (below); θ the incidence
  angle between the beam and the surface normal; ``f(R) = min(1, (R_ref / R)^p)``
  a range falloff (``falloff_reference_m``, ``falloff_exponent``); ε standard
  normal, σ_I = ``intensity_noise`` (2 %). The photo's colours are never used.
* **Texture within a bed**: real TLS intensity is not flat inside a bed:
  grain size and sorting, weathering rinds, moisture (water absorbs strongly
  at 1550 nm), oxide and varnish stains and lichen vary it over centimetres
  to metres — intensity is used to tell rock types apart only after
  averaging over that scatter (Franceschi et al. 2009, *Discrimination
  between marls and limestones using intensity data from terrestrial laser
  scanner*, ISPRS J. Photogramm. 64) — and this texture is what seed 003's
  reflectivity view matches. ``T = exp(σ_T · z)``, a log-normal
  factor (geometric mean 1) of a unit-variance field
  ``z = c · a + sqrt(1 − c²) · g`` on the true surface:

  - ``g``: multi-scale 3-D value noise at the hit point, one octave per
    ``texture_scales_m`` (0.15, 0.5, 1.5, 5 m lattice cells, each randomly
    rotated and offset), equal variance per octave (self-similar: as much
    contrast at 0.15 m as at 5 m);
  - ``a``: the visible albedo's log luminance at the hit, standardised per bed
    (and over the cover), i.e. its pattern *within* the bed — dark stains,
    seeps and lichen are dark at 1550 nm too — when an albedo texture is
    given (``albedo=`` / the generated scene's ``albedo.png``); c =
    ``texture_albedo_correlation`` (0.5: a quarter of the texture's variance
    is shared with what the eye sees, the rest is the scanner's own);
  - σ_T = ``texture_amplitude`` (0.15: a 15 % log-std within a bed, a quarter
    of the sandstone/mudstone log contrast ln(0.55/0.30) = 0.61, so the rock
    types still separate by intensity as in the studies above).

  ``texture_amplitude = 0`` gives the flat beds of scan version 1.
* Rays that miss (sky) or fall outside ``[min_range_m, max_range_m]`` return
  nothing and are dropped.

:func:`write_scan` writes ``scan.laz`` (LAS 1.4, point format 6: no colour;
coordinates in the georeference's projected CRS, i.e. local + ``georef.json``
origin, with its CRS record, so a reader subtracts the origin again; intensity
as uint16 ``round(I · 65535)``; ``point_source_id`` = station index + 1) and
``scan.json`` (stations, angular step, FOV, noise, intensity model, N).

:func:`scan_outcrop` scans a generated :class:`~napari_imgreg.sample.outcrop.Outcrop`
in memory (``generate_outcrop(..., scan=ScanSpec())``); :func:`scan_scene_folder`
scans a generated scene folder on disk, the plain model or a rough scene's
true surface (:mod:`napari_imgreg.sample.rough`), rebuilding the generator's
rock/cover mask from ``scene.json``'s spec and seed.

The default reflectances are typical of a 1550 nm scanner (the common TLS
wavelength: Riegl VZ, Leica P50/RTC360, Faro); seed 003's Leica C10 and
ScanStation II work at 532 nm, where vegetation is darker still.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Mapping, NamedTuple

import numpy as np

from numba import njit

from .._atomic import atomic_path, atomic_write
from .._json import dump as strict_json_dump
from .noise import rng_for, smoothstep

__all__ = [
    "SCAN_VERSION",
    "DEFAULT_REFLECTANCE",
    "ScanSpec",
    "SAMPLE_SCAN_SPEC",
    "ScanPoints",
    "SurfaceCover",
    "Strata",
    "station_positions",
    "simulate_scan",
    "write_scan",
    "cover_from_outcrop",
    "scan_outcrop",
    "scan_scene_folder",
    "intensity_by_surface",
    "VisibleAlbedo",
    "texture_field",
    "value_noise",
]

#: Bump when what :func:`simulate_scan` / :func:`write_scan` produce changes (cache key).
SCAN_VERSION = "2"  # 2: within-bed texture of the intensity (ScanSpec.texture_*)

#: Random streams of this module (see :func:`napari_imgreg.sample.noise.rng_for`).
_S_SCAN = 8600

#: Reflectance at the scanner's wavelength (1550 nm typical), per surface kind.
#: Sandstone (quartz, little clay) is brighter than mudstone (clay, organic
#: matter, moisture); vegetation is dark at 1550 nm (leaf water absorbs).
DEFAULT_REFLECTANCE: dict[str, float] = {
    "sandstone": 0.55,
    "mudstone": 0.30,
    "scree": 0.42,
    "vegetation": 0.28,
}


@dataclass(frozen=True)
class ScanSpec:
    """A terrestrial laser survey of a cliff: stations, scan grid, intensity and noise.

    Lengths in metres, angles in degrees unless named otherwise; azimuths are
    grid azimuths, clockwise from +Y (north).

    Attributes
    ----------
    n_stations : int
        Scanner stations. Default 2, range 1–16.
    station_spacing_m : float
        Distance between neighbouring stations, along the cliff (perpendicular
        to ``facing_azimuth_deg``), centred on ``target_xy``. Default 50.
    standoff_m : float
        Horizontal distance of the stations from ``target_xy`` toward the
        viewer: a typical TLS range to a cliff (30–80 m). Default 55.
    target_xy : (float, float)
        A point on the face line the stations look at; the generator's face
        has its mid-height at (0, 0). Default (0, 0).
    facing_azimuth_deg : float
        Direction the scanners look (the generator's cliff faces south, so
        they look north: 0). Default 0.
    stations_xy : tuple of (float, float), optional
        Explicit station positions (x, y), overriding the placement above.
    tripod_height_m : float
        The scanner's optical centre above the ground under it (found by a
        vertical ray on the scanned surface). Default 1.7, range 0–10.
    step_mrad : float
        Angular step of the scan grid in azimuth and elevation, milliradians
        (1 mrad: 5 cm point spacing at 50 m). Default 1.0, range 0.05–100.
    azimuth_half_width_deg : float
        The scan window spans ``facing ± azimuth_half_width_deg``. Default 65
        (covers the face to ≈ 118 m either side of a station 55 m from it),
        range (0, 180].
    elevation_range_deg : (float, float)
        Lowest and highest beam elevation. Default (−15, 45): from the ground
        ≈ 6 m in front of the tripod to above the cliff top. Range [−90, 90].
    min_range_m, max_range_m : float
        Returns nearer or farther than these are dropped (the scanner's
        blind zone and its range at the rock's reflectance). Defaults 1.5, 300.
    reflectance : dict of str to float
        ρ per surface kind, in (0, 1]: every lithology of the geology
        (``sandstone``, ``mudstone``) and the covers ``scree`` and
        ``vegetation``. Default :data:`DEFAULT_REFLECTANCE`.
    bed_reflectance_variation : float
        Relative standard deviation of each bed's reflectance about its rock
        type's (beds of one rock type differ in grain size, clay and
        moisture; clipped at 3 sigma). 0 gives every bed its rock type's
        exact ρ. Default 0.05, range [0, 0.3].
    texture_amplitude : float
        σ_T, the standard deviation of the natural log of the within-bed
        texture factor T (see the module's docstring). Default 0.15, range
        [0, 1]; 0 switches the texture off.
    texture_scales_m : tuple of float
        Lattice cells of the texture's value-noise octaves, metres, each in
        [0.01, 100]. Default (0.15, 0.5, 1.5, 5.0).
    texture_albedo_correlation : float
        c: correlation of the texture's field with the visible albedo's
        within-bed log luminance, where an albedo is given. Default 0.5, range [0, 1].
    falloff_reference_m, falloff_exponent : float
        Range falloff ``f(R) = min(1, (R_ref / R)^p)``. The physical echo of
        an extended target falls as ``1 / R²``; recorded TLS intensities are
        gain-controlled and compressed, and fall far less: default p = 1
        (f = 0.36 at 55 m), ``R_ref`` = 20 m (nearer returns saturate the
        gain control). p = 0 switches the falloff off. Ranges R_ref > 0, p in [0, 4].
    intensity_noise : float
        Relative Gaussian noise of the intensity (σ_I). Default 0.02, range [0, 0.5].
    range_noise_m : float
        Gaussian range noise along the beam. Default 0.005, range [0, 1].
    seed : int
        All noise derives from it (independent streams per station and per
        quantity, so the result does not depend on ``chunk_rays``).
    chunk_rays : int
        Rays cast per call to the ray engine (bounds memory: ≈ 100 bytes a
        ray). Default 1 000 000.
    """

    n_stations: int = 2
    station_spacing_m: float = 50.0
    standoff_m: float = 55.0
    target_xy: tuple[float, float] = (0.0, 0.0)
    facing_azimuth_deg: float = 0.0
    stations_xy: tuple[tuple[float, float], ...] | None = None
    tripod_height_m: float = 1.7
    step_mrad: float = 1.0
    azimuth_half_width_deg: float = 65.0
    elevation_range_deg: tuple[float, float] = (-15.0, 45.0)
    min_range_m: float = 1.5
    max_range_m: float = 300.0
    reflectance: Mapping[str, float] = field(default_factory=lambda: dict(DEFAULT_REFLECTANCE))
    bed_reflectance_variation: float = 0.05
    texture_amplitude: float = 0.15
    texture_scales_m: tuple[float, ...] = (0.15, 0.5, 1.5, 5.0)
    texture_albedo_correlation: float = 0.5
    falloff_reference_m: float = 20.0
    falloff_exponent: float = 1.0
    intensity_noise: float = 0.02
    range_noise_m: float = 0.005
    seed: int = 0
    chunk_rays: int = 1_000_000

    def __post_init__(self) -> None:
        def need(ok: bool, what: str) -> None:
            if not ok:
                raise ValueError(f"ScanSpec: {what}")

        need(1 <= int(self.n_stations) <= 16, f"n_stations must be 1-16, not {self.n_stations}")
        if self.stations_xy is not None:
            need(len(self.stations_xy) >= 1 and all(len(p) == 2 for p in self.stations_xy),
                 "stations_xy must be a non-empty list of (x, y)")
        need(0.0 <= self.tripod_height_m <= 10.0,
             f"tripod_height_m must be 0-10 m, not {self.tripod_height_m}")
        need(0.05 <= self.step_mrad <= 100.0, f"step_mrad must be 0.05-100, not {self.step_mrad}")
        need(0.0 < self.azimuth_half_width_deg <= 180.0,
             f"azimuth_half_width_deg must be in (0, 180], not {self.azimuth_half_width_deg}")
        lo, hi = self.elevation_range_deg
        need(-90.0 <= lo < hi <= 90.0,
             f"elevation_range_deg must be -90 <= low < high <= 90, not {(lo, hi)}")
        need(0.0 <= self.min_range_m < self.max_range_m,
             f"need 0 <= min_range_m < max_range_m, not {self.min_range_m}, {self.max_range_m}")
        for kind in ("scree", "vegetation"):
            need(kind in self.reflectance, f"reflectance has no {kind!r}")
        for kind, rho in self.reflectance.items():
            need(0.0 < float(rho) <= 1.0, f"reflectance[{kind!r}] must be in (0, 1], not {rho}")
        need(0.0 <= self.bed_reflectance_variation <= 0.3,
             f"bed_reflectance_variation must be 0-0.3, not {self.bed_reflectance_variation}")
        need(0.0 <= self.texture_amplitude <= 1.0,
             f"texture_amplitude must be 0-1, not {self.texture_amplitude}")
        need(len(self.texture_scales_m) >= 1 and all(0.01 <= float(v) <= 100.0
                                                     for v in self.texture_scales_m),
             f"texture_scales_m must be 1 or more cells of 0.01-100 m, not {self.texture_scales_m}")
        need(0.0 <= self.texture_albedo_correlation <= 1.0,
             f"texture_albedo_correlation must be 0-1, not {self.texture_albedo_correlation}")
        need(self.falloff_reference_m > 0.0, "falloff_reference_m must be positive")
        need(0.0 <= self.falloff_exponent <= 4.0,
             f"falloff_exponent must be 0-4, not {self.falloff_exponent}")
        need(0.0 <= self.intensity_noise <= 0.5,
             f"intensity_noise must be 0-0.5, not {self.intensity_noise}")
        need(0.0 <= self.range_noise_m <= 1.0, f"range_noise_m must be 0-1 m, not {self.range_noise_m}")
        need(int(self.chunk_rays) >= 1000, f"chunk_rays must be >= 1000, not {self.chunk_rays}")

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (tuples become lists)."""
        d = asdict(self)
        d["reflectance"] = {k: float(v) for k, v in self.reflectance.items()}
        return json.loads(json.dumps(d))

    def falloff(self, range_m: np.ndarray) -> np.ndarray:
        """``f(R) = min(1, (R_ref / R)^p)``, dimensionless, for ranges in metres."""
        r = np.maximum(np.asarray(range_m, np.float64), 1e-6)
        return np.minimum(1.0, (self.falloff_reference_m / r) ** self.falloff_exponent)

    def scan_angles(self) -> tuple[np.ndarray, np.ndarray]:
        """The scan grid's azimuths and elevations, radians, (C,) and (R,).

        Cell centres of the window at ``step_mrad``, so that the grid is
        symmetric about the facing direction.
        """
        step = self.step_mrad * 1e-3
        half = math.radians(self.azimuth_half_width_deg)
        n_az = max(1, int(round(2.0 * half / step)))
        az = math.radians(self.facing_azimuth_deg) + (np.arange(n_az) - (n_az - 1) / 2.0) * step
        lo, hi = (math.radians(v) for v in self.elevation_range_deg)
        n_el = max(1, int(round((hi - lo) / step)))
        el = lo + (np.arange(n_el) + 0.5) * (hi - lo) / n_el
        return az, el


class ScanPoints(NamedTuple):
    """The returns of a simulated scan (unpacks as ``xyz, intensity, station``).

    Attributes
    ----------
    xyz : (N, 3) float64 array
        Points, model frame metres.
    intensity : (N,) float32 array
        Recorded intensity in [0, 1].
    station : (N,) uint8 array
        Index of the station that measured each point.
    """

    xyz: np.ndarray
    intensity: np.ndarray
    station: np.ndarray


@dataclass
class SurfaceCover:
    """What covers the surface at each vertex: bare rock or vegetation/scree.

    Attributes
    ----------
    rock_weight : (V,) float array
        1 where the rock is bare, 0 where covered; interpolated at each hit.
    cover_reflectance : (V,) float array
        Reflectance of the cover where it is not bare rock.
    """

    rock_weight: np.ndarray
    cover_reflectance: np.ndarray


@dataclass
class VisibleAlbedo:
    """The surface's visible albedo, for the part of the intensity's texture
    it shares (:attr:`ScanSpec.texture_albedo_correlation`).

    Attributes
    ----------
    uv : (V, 2) float array
        Texture coordinates per vertex of the scanned surface (OpenGL: v = 0
        at the image's bottom row).
    log_luminance : (T_h, T_w) float32 array
        Natural log of the albedo's linear luminance per texel.
    """

    uv: np.ndarray
    log_luminance: np.ndarray

    @classmethod
    def from_rgb(cls, uv: np.ndarray, rgb: np.ndarray) -> VisibleAlbedo:
        """From an sRGB albedo image (H, W, 3) uint8 and per-vertex ``uv``."""
        c = np.asarray(rgb, np.float32)[..., :3] / 255.0
        lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
        lum = lin @ np.array([0.2126, 0.7152, 0.0722], np.float32)  # Rec. 709 luminance
        return cls(np.asarray(uv, np.float64), np.log(lum + 1e-3).astype(np.float32))

    def at(self, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """(N,) log luminance at hits on ``faces`` (N, 3) with barycentrics (N, 3)."""
        from scipy import ndimage

        uv = np.einsum("nk,nkj->nj", bary, self.uv[faces])
        th, tw = self.log_luminance.shape
        rows = (1.0 - uv[:, 1]) * th - 0.5
        cols = uv[:, 0] * tw - 0.5
        return ndimage.map_coordinates(self.log_luminance, [rows, cols], order=1, mode="nearest")


# ------------------------------------------------------- within-bed texture
@njit(cache=True, nogil=True)
def _value_noise_kernel(p, rot, offset, out):  # pragma: no cover - compiled
    """3-D value noise at points ``p`` (N, 3) in lattice units after ``p @ rot.T + offset``:
    corner values uniform in [-1, 1] by an integer hash, quintic interpolation."""
    n = p.shape[0]
    for i in range(n):
        q0 = rot[0, 0] * p[i, 0] + rot[0, 1] * p[i, 1] + rot[0, 2] * p[i, 2] + offset[0]
        q1 = rot[1, 0] * p[i, 0] + rot[1, 1] * p[i, 1] + rot[1, 2] * p[i, 2] + offset[1]
        q2 = rot[2, 0] * p[i, 0] + rot[2, 1] * p[i, 1] + rot[2, 2] * p[i, 2] + offset[2]
        f0, f1, f2 = math.floor(q0), math.floor(q1), math.floor(q2)
        t0, t1, t2 = q0 - f0, q1 - f1, q2 - f2
        w0 = t0 * t0 * t0 * (t0 * (t0 * 6.0 - 15.0) + 10.0)
        w1 = t1 * t1 * t1 * (t1 * (t1 * 6.0 - 15.0) + 10.0)
        w2 = t2 * t2 * t2 * (t2 * (t2 * 6.0 - 15.0) + 10.0)
        i0, i1, i2 = np.int64(f0), np.int64(f1), np.int64(f2)
        acc = 0.0
        for c in range(8):
            a, b, d = c & 1, (c >> 1) & 1, (c >> 2) & 1
            h = np.uint64((i0 + a) * 73856093) ^ np.uint64((i1 + b) * 19349663) \
                ^ np.uint64((i2 + d) * 83492791)
            # splitmix64 finaliser: a well-mixed 64-bit value per lattice point
            h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
            h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
            h = h ^ (h >> np.uint64(31))
            v = (h >> np.uint64(11)) * (1.0 / 9007199254740992.0) * 2.0 - 1.0
            wa = w0 if a else 1.0 - w0
            wb = w1 if b else 1.0 - w1
            wd = w2 if d else 1.0 - w2
            acc += wa * wb * wd * v
        out[i] = acc


def _noise_norm() -> float:
    """1 / the standard deviation of :func:`value_noise`'s raw output over
    uniformly placed points: corner values of variance 1/3 weighted by the
    quintic fade, ``E[w² + (1 − w)²]`` per axis (= 181/231 by integration)."""
    e_axis = 181.0 / 231.0
    return 1.0 / math.sqrt((1.0 / 3.0) * e_axis ** 3)


def value_noise(xyz: np.ndarray, cell_m: float, rotation: np.ndarray | None = None,
                offset: np.ndarray | None = None) -> np.ndarray:
    """Smooth 3-D value noise of unit variance at points, lattice cell ``cell_m``.

    Parameters
    ----------
    xyz : (N, 3) array
        Points, metres.
    cell_m : float
        Lattice spacing, metres: values decorrelate over about one cell.
    rotation : (3, 3) array, optional
        Rotation of the lattice (default identity).
    offset : (3,) array, optional
        Offset of the lattice, in cells.

    Returns
    -------
    (N,) float64 array
        Mean 0 and standard deviation 1 over uniformly placed points
        (normalised analytically, see :func:`_noise_norm`); values in about ±3.
    """
    p = np.ascontiguousarray(np.asarray(xyz, np.float64) / float(cell_m))
    rot = np.eye(3) if rotation is None else np.ascontiguousarray(rotation, np.float64)
    off = np.zeros(3) if offset is None else np.ascontiguousarray(offset, np.float64)
    out = np.empty(len(p), np.float64)
    _value_noise_kernel(p, rot, off, out)
    return out * _noise_norm()


def texture_field(xyz: np.ndarray, spec: ScanSpec) -> np.ndarray:
    """The texture's own multi-scale field ``g`` (N,): unit variance, mean 0.

    The sum of one :func:`value_noise` octave per ``spec.texture_scales_m``
    (each lattice randomly rotated and offset from ``spec.seed``), equal
    variance each, divided by √(octaves). A property of the surface: the same
    point gets the same value from every station.
    """
    rng = rng_for(spec.seed, _S_SCAN, 777)
    g = np.zeros(len(xyz), np.float64)
    for cell in spec.texture_scales_m:
        q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
        g += value_noise(xyz, float(cell), q, rng.uniform(0.0, 1000.0, 3))
    return g / math.sqrt(len(spec.texture_scales_m))


def _standardised_by_group(a: np.ndarray, group: np.ndarray) -> np.ndarray:
    """``a`` minus its group's mean, over its group's standard deviation."""
    out = np.zeros(len(a), np.float64)
    if not len(a):
        return out
    inv = np.unique(group, return_inverse=True)[1].reshape(-1)
    n = np.bincount(inv).astype(np.float64)
    mean = np.bincount(inv, a) / n
    var = np.bincount(inv, a * a) / n - mean ** 2
    sd = np.sqrt(np.maximum(var, 0.0))
    ok = sd[inv] > 1e-9
    out[ok] = (a[ok] - mean[inv][ok]) / sd[inv][ok]
    return out


class Strata:
    """The rock type at any point, from a geology description (``geology.json``).

    Stratigraphic height ``h = n · (X − X0)`` (plus the fault's ``h_shift``
    in the hanging wall); the bed holding ``h`` is found among the ascending
    ``boundaries_h``, its lithology among ``beds``.

    Parameters
    ----------
    geology : dict, path or :class:`~napari_imgreg.sample.outcrop.Geology`
        ``geology.json``'s content (``bedding.normal``, ``bedding.reference_point``,
        ``boundaries_h``, ``beds[i].lithology``, optional ``fault.point``,
        ``fault.normal``, ``fault.h_shift``), its path, or the generator's object.
    """

    def __init__(self, geology: Any) -> None:
        if isinstance(geology, (str, os.PathLike)):
            geology = json.loads(Path(geology).read_text(encoding="utf-8"))
        if hasattr(geology, "to_dict"):
            geology = geology.to_dict()
        try:
            bed = geology["bedding"]
            self.normal = np.asarray(bed["normal"], np.float64)
            self.reference = np.asarray(bed.get("reference_point", (0.0, 0.0, 0.0)), np.float64)
            self.boundaries = np.asarray(geology.get("boundaries_h", []), np.float64)
            self.lithology = [str(b["lithology"]) for b in geology["beds"]]
            fault = geology.get("fault") or {}
            self.fault_point = np.asarray(fault.get("point", (0.0, 0.0, 0.0)), np.float64)
            self.fault_normal = np.asarray(fault.get("normal", (0.0, 0.0, 1.0)), np.float64)
            self.h_shift = float(fault.get("h_shift", 0.0))
        except (KeyError, TypeError) as exc:
            raise ValueError(f"geology: missing or malformed field {exc}") from None
        if len(self.lithology) != len(self.boundaries) + 1:
            raise ValueError(f"geology: {len(self.lithology)} beds for {len(self.boundaries)} "
                             "boundaries (need one more bed than boundaries)")
        if np.any(np.diff(self.boundaries) <= 0):
            raise ValueError("geology: boundaries_h must ascend")

    def h_strat(self, xyz: np.ndarray) -> np.ndarray:
        """Stratigraphic height of points (N, 3), metres (hanging wall shifted)."""
        xyz = np.asarray(xyz, np.float64)
        h = (xyz - self.reference) @ self.normal
        if self.h_shift:
            h = h + self.h_shift * (((xyz - self.fault_point) @ self.fault_normal) > 0)
        return h

    def bed_at(self, xyz: np.ndarray) -> np.ndarray:
        """(N,) index of the bed holding each point."""
        return np.searchsorted(self.boundaries, self.h_strat(xyz))


# -------------------------------------------------------------- stations
def _ground_z(scene, xy: np.ndarray) -> np.ndarray:
    """Height of the highest surface under each (x, y), by vertical rays (NaN off it)."""
    top = float(scene.bounds[1, 2]) + 10.0
    origins = np.column_stack([xy, np.full(len(xy), top)])
    hits = scene.cast_rays(origins, np.tile([0.0, 0.0, -1.0], (len(xy), 1)))
    return np.where(hits.hit, top - hits.distance.astype(np.float64), np.nan)


def station_positions(scene, spec: ScanSpec) -> np.ndarray:
    """The scanners' optical centres, (S, 3) model-frame metres.

    ``spec.stations_xy`` when given, else ``n_stations`` along a line
    ``standoff_m`` in front of ``target_xy`` (against ``facing_azimuth_deg``),
    ``station_spacing_m`` apart; each ``tripod_height_m`` above the ground
    (the scanned surface) under it.

    Raises
    ------
    ValueError
        A station is off the surface (no ground under it).
    """
    if spec.stations_xy is not None:
        xy = np.asarray(spec.stations_xy, np.float64).reshape(-1, 2)
    else:
        a = math.radians(spec.facing_azimuth_deg)
        forward = np.array([math.sin(a), math.cos(a)])
        right = np.array([math.cos(a), -math.sin(a)])
        along = (np.arange(spec.n_stations) - (spec.n_stations - 1) / 2.0) * spec.station_spacing_m
        xy = np.asarray(spec.target_xy, np.float64) - spec.standoff_m * forward + along[:, None] * right
    z = _ground_z(scene, xy)
    bad = ~np.isfinite(z)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise ValueError(f"scan station {k} at ({xy[k, 0]:.1f}, {xy[k, 1]:.1f}) has no ground "
                         f"under it on {scene.name!r}")
    return np.column_stack([xy, z + spec.tripod_height_m])


# -------------------------------------------------------------- scanning
def _bed_reflectance(strata: Strata, spec: ScanSpec) -> np.ndarray:
    """(B,) reflectance of each bed: its rock type's, varied per bed."""
    missing = sorted({k for k in strata.lithology if k not in spec.reflectance})
    if missing:
        raise ValueError(f"ScanSpec.reflectance has no value for lithology {', '.join(missing)}")
    rho = np.array([float(spec.reflectance[k]) for k in strata.lithology])
    sigma = spec.bed_reflectance_variation
    if sigma > 0:
        eps = np.clip(rng_for(spec.seed, _S_SCAN, 999).standard_normal(len(rho)), -3.0, 3.0)
        rho = rho * (1.0 + sigma * eps)
    return np.clip(rho, 1e-3, 1.0)


def _steepness_cover(normals: np.ndarray, spec: ScanSpec) -> tuple[np.ndarray, np.ndarray]:
    """Without a cover mask: steep surface is bare rock, gentle is vegetated
    (the generator's rule: rock where ``1 − n_z`` exceeds ≈ 0.32)."""
    w = smoothstep((1.0 - np.abs(normals[:, 2]) - 0.32) / 0.12)
    return w, np.full(len(w), float(spec.reflectance["vegetation"]))


def simulate_scan(true_scene, geology: Any, spec: ScanSpec | None = None, *,
                  cover: SurfaceCover | None = None,
                  stations: np.ndarray | None = None,
                  labels: dict[str, np.ndarray] | None = None,
                  albedo: VisibleAlbedo | None = None) -> ScanPoints:
    """Scan a surface from each station on a regular azimuth/elevation grid.

    Parameters
    ----------
    true_scene : Scene
        The surface the scanner sees (the true surface, not the user's model);
        its ray engine is built on first use.
    geology : dict, path or Geology
        The rock types (see :class:`Strata`).
    spec : ScanSpec, optional
        Default ``ScanSpec()``.
    cover : SurfaceCover, optional
        Per-vertex bare-rock weight and cover reflectance (the generator's
        mask, :func:`cover_from_outcrop`). Without it, the surface is bare
        rock where steep and vegetated where gentle (from the hit's normal).
    stations : (S, 3) array, optional
        Optical centres; default :func:`station_positions`.
    labels : dict, optional
        If given, filled with what each point hit (the truth, not stored in
        the scan): ``"bed"`` (N,) int32 bed index, ``"rock_weight"`` (N,)
        float32 bare-rock weight, ``"cos_incidence"`` (N,) float32,
        ``"texture"`` (N,) float32 the within-bed texture factor T.
    albedo : VisibleAlbedo, optional
        The surface's visible albedo (uv per vertex of ``true_scene``): the
        texture's field shares ``spec.texture_albedo_correlation`` with its
        within-bed log luminance. Without it the texture is the scanner's own
        field alone.

    Returns
    -------
    ScanPoints
        ``xyz`` (N, 3) float64 model-frame metres, ``intensity`` (N,) float32
        in [0, 1], ``station`` (N,) uint8; station by station, each in scan
        order (azimuth columns, elevation within a column). Misses dropped.
    """
    spec = spec or ScanSpec()
    strata = geology if isinstance(geology, Strata) else Strata(geology)
    bed_rho = _bed_reflectance(strata, spec)
    if stations is None:
        stations = station_positions(true_scene, spec)
    stations = np.asarray(stations, np.float64).reshape(-1, 3)
    if len(stations) > 255:
        raise ValueError("at most 255 stations (station index is uint8)")
    nv = len(true_scene.vertices)
    if cover is not None:
        if len(cover.rock_weight) != nv or len(cover.cover_reflectance) != nv:
            raise ValueError(f"cover has {len(cover.rock_weight)} vertices, the scene {nv}")
    textured = spec.texture_amplitude > 0.0
    use_albedo = textured and albedo is not None and spec.texture_albedo_correlation > 0.0
    if use_albedo and len(albedo.uv) != nv:
        raise ValueError(f"albedo has uv for {len(albedo.uv)} vertices, the scene {nv}")
    faces = true_scene.faces
    corner_normals = true_scene.face_array("vertex_normals")  # (F, 3, 3) smooth normals
    az, el = spec.scan_angles()
    cos_el, sin_el = np.cos(el), np.sin(el)
    n_el = len(el)
    cols_per_chunk = max(1, int(spec.chunk_rays) // n_el)
    out_xyz, out_int, out_st, out_bed, out_w, out_cos = [], [], [], [], [], []
    out_g, out_a, out_group = [], [], []
    for k, origin in enumerate(stations):
        rng_range = rng_for(spec.seed, _S_SCAN, k, 0)
        rng_int = rng_for(spec.seed, _S_SCAN, k, 1)
        for c0 in range(0, len(az), cols_per_chunk):
            a = az[c0:c0 + cols_per_chunk]
            # Azimuth-major (a scanner sweeps vertical profiles as it turns).
            d = np.empty((len(a), n_el, 3), np.float64)
            d[..., 0] = np.sin(a)[:, None] * cos_el[None, :]
            d[..., 1] = np.cos(a)[:, None] * cos_el[None, :]
            d[..., 2] = sin_el[None, :]
            d = d.reshape(-1, 3)
            hits = true_scene.cast_rays(origin, d, max_distance=spec.max_range_m)
            t = hits.distance.astype(np.float64)
            ok = hits.hit & (t >= spec.min_range_m) & (t <= spec.max_range_m)
            if not ok.any():
                continue
            d, t = d[ok], t[ok]
            fid = hits.face_id[ok]
            u = hits.bary_u[ok].astype(np.float64)[:, None]
            v = hits.bary_v[ok].astype(np.float64)[:, None]
            w0 = 1.0 - u - v
            tri = true_scene.vertices[faces[fid]]
            exact = w0 * tri[:, 0] + u * tri[:, 1] + v * tri[:, 2]
            cn = corner_normals[fid].astype(np.float64)
            n = w0 * cn[:, 0] + u * cn[:, 1] + v * cn[:, 2]
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            cos_inc = np.abs(np.einsum("ij,ij->i", n, d))
            if cover is None:
                w_rock, rho_cover = _steepness_cover(n, spec)
            else:
                fv = faces[fid]
                wts = np.concatenate([w0, u, v], axis=1)
                w_rock = np.einsum("ij,ij->i", np.asarray(cover.rock_weight, np.float64)[fv], wts)
                rho_cover = np.einsum("ij,ij->i",
                                      np.asarray(cover.cover_reflectance, np.float64)[fv], wts)
            bed = strata.bed_at(exact)
            rho = w_rock * bed_rho[bed] + (1.0 - w_rock) * rho_cover
            r_meas = t + spec.range_noise_m * rng_range.standard_normal(len(t))
            xyz = origin + d * r_meas[:, None]
            inten = rho * cos_inc * spec.falloff(t)
            inten *= 1.0 + spec.intensity_noise * rng_int.standard_normal(len(t))
            if textured:
                # The texture is the surface's: at the exact hit, whichever station.
                out_g.append(texture_field(exact, spec))
                if use_albedo:
                    out_a.append(albedo.at(faces[fid], np.concatenate([w0, u, v], axis=1)))
                    out_group.append(np.where(w_rock >= 0.5, bed, -1))
            out_xyz.append(xyz)
            out_int.append(inten if textured else np.clip(inten, 0.0, 1.0).astype(np.float32))
            out_st.append(np.full(len(t), k, np.uint8))
            if labels is not None:
                out_bed.append(bed.astype(np.int32))
                out_w.append(np.asarray(w_rock, np.float32))
                out_cos.append(cos_inc.astype(np.float32))
    texture = None
    if textured and out_int:
        # T = exp(σ_T z), z = c a + sqrt(1 - c²) g: the albedo's within-bed
        # pattern (standardised per bed and over the cover) and the scanner's own field.
        z = np.concatenate(out_g)
        if use_albedo:
            c = spec.texture_albedo_correlation
            a = _standardised_by_group(np.concatenate(out_a).astype(np.float64),
                                       np.concatenate(out_group))
            z = c * a + math.sqrt(1.0 - c * c) * z
        texture = np.exp(spec.texture_amplitude * z)
        sizes = np.cumsum([len(x) for x in out_int])[:-1]
        out_int = [np.clip(i * tex, 0.0, 1.0).astype(np.float32)
                   for i, tex in zip(out_int, np.split(texture, sizes))]
    if labels is not None:
        labels["texture"] = (np.ones(sum(len(x) for x in out_int), np.float32) if texture is None
                             else texture.astype(np.float32))
        labels["bed"] = np.concatenate(out_bed) if out_bed else np.empty(0, np.int32)
        labels["rock_weight"] = np.concatenate(out_w) if out_w else np.empty(0, np.float32)
        labels["cos_incidence"] = np.concatenate(out_cos) if out_cos else np.empty(0, np.float32)
    if not out_xyz:
        return ScanPoints(np.empty((0, 3)), np.empty(0, np.float32), np.empty(0, np.uint8))
    return ScanPoints(np.concatenate(out_xyz), np.concatenate(out_int), np.concatenate(out_st))


# --------------------------------------------------------------- writing
#: LAS coordinate resolution: 1 mm (the range noise is 5 mm).
LAS_SCALE_M = 0.001


def write_scan(folder: str | os.PathLike, scan: ScanPoints, spec: ScanSpec,
               stations: np.ndarray, georef=None, *, name: str = "scan",
               info: Mapping[str, Any] | None = None) -> Path:
    """Write a scan as ``<name>.laz`` and its description ``<name>.json``.

    Parameters
    ----------
    folder : path-like
        Created if needed; files are written atomically (LAZ first, the JSON
        last, so a JSON beside a LAZ means the LAZ is complete).
    scan : ScanPoints
        From :func:`simulate_scan` (model frame).
    spec : ScanSpec
        What made it (recorded in the JSON).
    stations : (S, 3) array
        The stations' optical centres, model frame.
    georef : Georef, optional
        With one, coordinates are written in its projected CRS (local +
        origin) and the LAS carries its CRS record (an OGC WKT VLR); without,
        they are model-frame coordinates and there is no CRS record.
    name : str
        File stem. Default ``"scan"``.
    info : dict, optional
        More to record in the JSON (e.g. which surface was scanned).

    Returns
    -------
    Path
        The LAZ file. Its format: LAS 1.4, point format 6 (no colour),
        scale 1 mm, ``intensity`` = ``round(I · 65535)``, ``point_source_id``
        = station index + 1, one return per pulse, class 0 (never classified).
    """
    import laspy

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    xyz = np.asarray(scan.xyz, np.float64)
    stations = np.asarray(stations, np.float64).reshape(-1, 3)
    origin = np.zeros(3) if georef is None else np.asarray(georef.origin, np.float64)
    world = xyz + origin
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.full(3, LAS_SCALE_M)
    header.offsets = np.floor(world.min(axis=0)) if len(world) else origin
    header.system_identifier = "napari-imgreg generated TLS"
    header.generating_software = "napari-imgreg sample.scan"
    crs_text = None
    if georef is not None:
        import pyproj

        crs = pyproj.CRS.from_user_input(georef.crs)
        header.add_crs(crs)
        crs_text = georef.crs
    las = laspy.LasData(header)
    las.x, las.y, las.z = world[:, 0], world[:, 1], world[:, 2]
    las.intensity = np.round(np.clip(scan.intensity, 0.0, 1.0) * 65535.0).astype(np.uint16)
    las.point_source_id = np.asarray(scan.station, np.uint16) + 1
    las.return_number = np.ones(len(xyz), np.uint8)
    las.number_of_returns = np.ones(len(xyz), np.uint8)
    laz = folder / f"{name}.laz"
    with atomic_path(laz) as tmp:
        las.write(str(tmp), do_compress=True)
    az, el = spec.scan_angles()
    counts = np.bincount(np.asarray(scan.station, np.int64), minlength=len(stations))
    doc = {
        "format": "napari-imgreg generated terrestrial laser scan",
        "scan_version": SCAN_VERSION,
        "file": laz.name,
        "n_points": int(len(xyz)),
        "coordinates": ("projected CRS (model frame + georef origin)" if georef is not None
                        else "model frame (no georeference)"),
        "crs": crs_text,
        "georef_origin": None if georef is None else [float(v) for v in origin],
        "las": {"version": "1.4", "point_format": 6, "scale_m": LAS_SCALE_M,
                "offset": [float(v) for v in header.offsets],
                "intensity": "uint16 = round(intensity * 65535), intensity in [0, 1]",
                "point_source_id": "station index + 1", "colour": None},
        "step_mrad": spec.step_mrad,
        "grid": {"azimuths": int(len(az)), "elevations": int(len(el)),
                 "azimuth_range_deg": [round(math.degrees(float(az[0])), 4),
                                       round(math.degrees(float(az[-1])), 4)],
                 "elevation_range_deg": [round(math.degrees(float(el[0])), 4),
                                         round(math.degrees(float(el[-1])), 4)]},
        "stations": [
            {"index": k, "point_source_id": k + 1,
             "position": [round(float(v), 4) for v in p],
             "position_crs": [round(float(v), 4) for v in p + origin],
             "tripod_height_m": spec.tripod_height_m,
             "rays": int(len(az) * len(el)), "points": int(counts[k])}
            for k, p in enumerate(stations)
        ],
        "noise": {"range_m": spec.range_noise_m, "intensity_relative": spec.intensity_noise},
        "intensity_model": ("reflectance(rock type or cover at the hit) * texture(hit) * "
                            "|cos(incidence)| * min(1, (falloff_reference_m / range)^falloff_exponent) * "
                            "(1 + intensity_noise * N(0, 1)), clipped to [0, 1]"),
        "texture_model": {
            "factor": "exp(texture_amplitude * z), z = c * a + sqrt(1 - c^2) * g",
            "g": "3-D value noise at the hit, one octave per texture_scales_m (lattice cell, m), "
                 "equal variance each, unit variance in all",
            "a": "visible albedo's log luminance at the hit, standardised per bed (and over the "
                 "cover); absent (c = 0) without an albedo",
            "texture_amplitude": spec.texture_amplitude,
            "texture_scales_m": [float(v) for v in spec.texture_scales_m],
            "c": spec.texture_albedo_correlation,
        },
        "spec": spec.to_dict(),
    }
    if info:
        doc.update(dict(info))
    with atomic_write(folder / f"{name}.json", encoding="utf-8") as fh:
        strict_json_dump(doc, fh, indent=1)
        fh.write("\n")
    return laz


# ------------------------------------------------ the generator's outcrops
def cover_from_outcrop(outcrop, spec: ScanSpec) -> SurfaceCover:
    """The generator's surface cover per grid vertex.

    Bare rock where the generator exposes it (``outcrop.rock``, the mask its
    texture and photos use); elsewhere scree on the talus slope at the foot
    of the cliff (the texture's talus band, at its mean strength) and
    vegetation on the ground and the plateau.
    """
    knots = outcrop.profile.knots
    s = np.asarray(outcrop.s, np.float64)
    # The texture's talus band; its patchy vegetation averages about 0.6.
    talus = 0.6 * smoothstep((s - knots["talus"] + 4.0) / 5.0) * smoothstep((knots["foot"] + 2.0 - s) / 1.5)
    rho = talus * spec.reflectance["scree"] + (1.0 - talus) * spec.reflectance["vegetation"]
    nx = outcrop.X.shape[1]
    return SurfaceCover(np.asarray(outcrop.rock, np.float64).reshape(-1),
                        np.repeat(rho, nx).astype(np.float64))


def scan_outcrop(outcrop, scene, georef, folder: str | os.PathLike, spec: ScanSpec | None = None,
                 *, name: str = "scan") -> dict[str, str]:
    """Scan a generated outcrop held in memory and write ``scan.laz`` / ``scan.json``.

    Parameters
    ----------
    outcrop : Outcrop
        From :func:`~napari_imgreg.sample.outcrop.build_geometry`.
    scene : Scene
        Its surface (vertices in grid order).
    georef : Georef or None
    folder : path-like
    spec : ScanSpec, optional

    Returns
    -------
    dict
        ``{"scan": "scan.laz", "scan_info": "scan.json"}`` (for ``scene.json``'s files).
    """
    spec = spec or ScanSpec()
    t0 = time.perf_counter()
    stations = station_positions(scene, spec)
    strata = Strata(outcrop.geology)
    labels: dict[str, np.ndarray] = {}
    albedo = (VisibleAlbedo.from_rgb(outcrop.uv, outcrop.albedo)
              if getattr(outcrop, "albedo", None) is not None else None)
    pts = simulate_scan(scene, strata, spec, cover=cover_from_outcrop(outcrop, spec),
                        stations=stations, labels=labels, albedo=albedo)
    t_sim = time.perf_counter() - t0
    laz = write_scan(folder, pts, spec, stations, georef, name=name,
                     info={"surface": scene.name, "cover": "the generator's rock mask; scree on "
                           "the talus; vegetation elsewhere",
                           "texture_albedo": "the generator's albedo" if albedo is not None else None,
                           "intensity_by_surface": intensity_by_surface(pts, labels, strata),
                           "timings_s": {"simulate": round(t_sim, 2)}})
    return {"scan": laz.name, "scan_info": f"{name}.json"}


def intensity_by_surface(scan: ScanPoints, labels: Mapping[str, np.ndarray],
                         strata: Strata) -> dict[str, Any]:
    """Median intensity and point count per surface kind: bare rock (weight
    > 0.9) by lithology, and the cover (weight < 0.1), overall and at near-normal
    incidence (cos > 0.9, where the rock types compare directly)."""
    lith = np.array(strata.lithology, dtype=object)[labels["bed"]]
    w = labels["rock_weight"]
    normal = labels["cos_incidence"] > 0.9
    kinds = {name: (w > 0.9) & (lith == name) for name in sorted(set(strata.lithology))}
    kinds["cover"] = w < 0.1
    out: dict[str, Any] = {}
    for name, sel in kinds.items():
        near = sel & normal
        out[name] = {
            "points": int(sel.sum()),
            "median": round(float(np.median(scan.intensity[sel])), 4) if sel.any() else None,
            "median_near_normal": round(float(np.median(scan.intensity[near])), 4) if near.any() else None,
        }
    return out


def _outcrop_spec(manifest: Mapping[str, Any]):
    from .outcrop import OutcropSpec

    d = dict(manifest["spec"])
    fields = OutcropSpec.__dataclass_fields__
    kw = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items() if k in fields}
    return OutcropSpec(**kw)


#: The scan ``napari-imgreg sample --scan`` writes beside the sample: the
#: default survey at a 2 mrad step (10 cm at 50 m; about 0.9 M points and
#: 4 MB of LAZ for the small sample, in ~3 s).
SAMPLE_SCAN_SPEC = ScanSpec(step_mrad=2.0)

def scan_scene_folder(folder: str | os.PathLike, spec: ScanSpec | None = None,
                      out_dir: str | os.PathLike | None = None, *,
                      geology: str | os.PathLike | None = None,
                      name: str = "scan") -> Path:
    """Scan a generated scene folder's true surface and write the scan.

    Parameters
    ----------
    folder : path-like
        A :func:`~napari_imgreg.sample.generate_outcrop` folder (the model is
        the true surface), or a :func:`~napari_imgreg.sample.rough.build_rough_scene`
        folder (its ``true_vertices.npy`` is; the model is the user's
        smoothed one).
    spec : ScanSpec, optional
    out_dir : path-like, optional
        Where to write (default ``folder``).
    geology : path-like, optional
        ``geology.json``; default the folder's, or that of the scene a rough
        folder was made from (``../../<rough.source>``, as the benchmark keeps them).
    name : str

    Returns
    -------
    Path
        The LAZ file written.

    Raises
    ------
    InputError
        A needed file is missing.
    """
    from ..errors import input_error
    from ..geo import Georef
    from ..scene import Scene
    from .outcrop import build_geometry

    spec = spec or ScanSpec()
    folder = Path(folder)
    out_dir = Path(out_dir) if out_dir is not None else folder
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    try:
        manifest = json.loads((folder / "scene.json").read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise input_error(folder / "scene.json", "no such file (not a generated scene folder)") from None
    files = manifest["files"]
    rough = manifest.get("rough")
    if geology is None:
        candidates = [folder / files.get("geology", "geology.json")]
        if rough:
            candidates.append(folder.parent.parent / rough.get("source", "") / "geology.json")
            candidates.append(folder.parent.parent / "geology.json")
        geology = next((p for p in candidates if p.is_file()), candidates[0])
    if not Path(geology).is_file():
        raise input_error(geology, "no such file (the scan needs the beds' rock types)")
    model = Scene.load(folder / files["mesh"], cache=False)
    if rough:
        true_v = np.load(folder / rough["true_surface"])
        scene = Scene(true_v, model.faces, name="true surface (rough)")
        surface = f"true surface ({rough['true_surface']})"
    else:
        scene = Scene(model.vertices, model.faces, name="true surface (model)")
        surface = f"the model ({files['mesh']}): the photos' own surface"
    georef_path = folder / files.get("georef", "georef.json")
    georef = Georef.load(georef_path) if georef_path.is_file() else None
    timings["load"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    outcrop = build_geometry(_outcrop_spec(manifest), int(manifest["seed"]))
    grid_v = outcrop.X.reshape(-1, 3)
    cover = None
    cover_note = "steep surface bare rock, gentle vegetated (no generator mask)"
    if len(grid_v) == len(scene.vertices):
        # The rebuilt grid is the file's (a 4-decimal OBJ); a rough surface is
        # the same grid with its sub-model relief (metres) added.
        gap = float(np.abs(grid_v - scene.vertices).max())
        if gap < (5.0 if rough else 0.01):
            cover = cover_from_outcrop(outcrop, spec)
            cover_note = "the generator's rock mask; scree on the talus; vegetation elsewhere"
    timings["cover"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    scene.build_engine()
    stations = station_positions(scene, spec)
    strata = Strata(geology)
    labels: dict[str, np.ndarray] = {}
    # The visible albedo the photos are rendered from (its within-bed pattern
    # is partly shared by the intensity's texture); the model's uv are the
    # true surface's (a rough scene keeps the grid and its texture coordinates).
    albedo, albedo_note = None, None
    albedo_path = folder / files.get("albedo", "albedo.png")
    if albedo_path.is_file() and model.uv is not None and len(model.uv) == len(scene.vertices):
        from PIL import Image

        with Image.open(albedo_path) as im:
            albedo = VisibleAlbedo.from_rgb(model.uv, np.asarray(im.convert("RGB")))
        albedo_note = albedo_path.name
    pts = simulate_scan(scene, strata, spec, cover=cover, stations=stations, labels=labels,
                        albedo=albedo)
    timings["simulate"] = time.perf_counter() - t0
    info = {"surface": surface, "source_folder": folder.name, "cover": cover_note,
            "texture_albedo": albedo_note,
            "geology": Path(geology).name, "seed_scene": int(manifest["seed"]),
            "intensity_by_surface": intensity_by_surface(pts, labels, strata),
            "timings_s": {k: round(v, 2) for k, v in timings.items()}}
    return write_scan(out_dir, pts, spec, stations, georef, name=name, info=info)
