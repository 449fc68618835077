"""A generated layered cliff: geometry, geology, texture and the written model.

The surface is ONE regular grid parameterised by ``(x, s)``: ``x`` runs along
the cliff (east), ``s`` is the arc length along a smooth 2-D profile in the YZ
plane (ground apron → talus → cliff face → top edge → plateau). Every grid
point is pushed along the profile normal by relief (real DEM undulation on
the ground and plateau, multi-scale gullies and buttresses on the face) and
then by differential erosion (sandstone beds stand proud of the mudstone).

Ground truth is exact: bedding is a set of parallel planes
``h = n_bed · (X − X0) = const`` (the hanging wall of a normal fault shifted
in ``h``), and the texture is coloured from the final 3-D position of every
texel, so the traces written to ``truth_lines.geojson`` are where those planes
really meet the written mesh.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from .._atomic import atomic_path, atomic_write
from .noise import (
    Lattice,
    dem_relief,
    rng_for,
    sample_detail,
    separable_sample,
    smooth_lattice,
    smoothstep,
)
from .photo import sun_vector

__all__ = [
    "OutcropSpec",
    "Geology",
    "Outcrop",
    "SIZES",
    "build_outcrop",
    "plane_normal",
    "dip_from_normal",
    "write_model",
]

#: Named scene sizes.
SIZES = ("small", "large")

# Random stream ids (see noise.rng_for): one per component.
_S_GEOMETRY, _S_GEOLOGY, _S_TEXTURE = 1, 2, 3

# Base colours (sRGB 0-255).
SANDSTONE_RGB = (200.0, 170.0, 120.0)
MUDSTONE_RGB = (110.0, 105.0, 100.0)
VEGETATION_RGB = (112.0, 112.0, 66.0)
SCREE_RGB = (150.0, 138.0, 118.0)


@dataclass(frozen=True)
class OutcropSpec:
    """Everything that defines a sample outcrop scene (lengths in metres).

    Use :meth:`for_size` for the named sizes and :func:`dataclasses.replace`
    to vary them (other seeds, more photos, other light).
    """

    # --- geometry
    width_m: float = 220.0
    """Extent along the cliff (x), centred on 0. Wider than the face a
    photo needs, so that frames turned ±25° from north stay on the model."""
    cliff_height_m: float = 40.0
    face_angle_deg: float = 76.0
    """Mean steepness of the face."""
    apron_length_m: float = 140.0
    """Ground in front of the face (toward −Y): the cameras stand on it."""
    talus_length_m: float = 12.0
    plateau_length_m: float = 60.0
    bay_depth_m: float = 22.0
    """The cliff's ends come this far forward (a gentle bay, like Mam Tor's)."""
    grid: tuple[int, int] = (256, 250)
    """Grid vertices (along x, along s)."""
    ground_relief_m: float = 1.2
    """Std of the (real-DEM) undulation of ground and plateau."""
    top_line_relief_m: float = 2.5
    """Std of the variation of the cliff-top height along the cliff."""
    face_relief_m: float = 1.6
    """Std of gullies and buttresses on the face."""
    erosion_relief_m: float = 0.45
    """Sandstone stands out this much from the recessed mudstone."""
    # --- geology
    bedding_dip_deg: float = 12.0
    bedding_dip_direction_deg: float = 200.0
    bedding_reference: tuple[float, float, float] = (0.0, 0.0, 0.0)
    sandstone_thickness_m: tuple[float, float] = (2.0, 5.0)
    mudstone_thickness_m: tuple[float, float] = (0.5, 2.0)
    fault_dip_deg: float = 65.0
    fault_dip_direction_deg: float = 100.0
    fault_throw_m: float = 4.0
    fault_point: tuple[float, float, float] = (18.0, 0.0, 25.0)
    # --- texture and model
    texture_size: int = 2048
    texture_jpeg_quality: int = 92
    survey_sun_azimuth_deg: float = 150.0
    survey_sun_elevation_deg: float = 40.0
    survey_ambient: float = 0.35
    # --- photos
    n_photos: int = 3
    photo_size: tuple[int, int] = (1024, 768)
    focal_length_mm: float = 4.25
    sensor_size_mm: tuple[float, float] = (5.6, 4.2)
    camera_make: str = "napari-imgreg"
    camera_model: str = "SynthPhone 26mm"
    camera_distance_m: tuple[float, float] = (80.0, 120.0)
    trend_range_deg: float = 25.0
    plunge_range_deg: tuple[float, float] = (-12.0, -3.0)
    roll_range_deg: float = 3.0
    height_above_ground_m: float = 1.6
    condition_strength: tuple[float, float] = (0.35, 0.9)
    """Range of :meth:`PhotoConditions.from_rng` strengths drawn per photo."""
    supersample: float = 1.5
    """Photos are rendered at this factor and area-averaged (anti-aliasing)."""
    n_check_points: int = 30
    photo_year: int = 2024
    """Photos are dated in this year, at the instant their sun stood where it is."""
    # --- prior (what the phone logs)
    sigma_position_m: float = 5.0
    sigma_altitude_m: float = 2.0
    """Noise of the prior altitude, which is the DEM height + eye height."""
    sigma_heading_deg: float = 5.0
    sigma_tilt_deg: float = 2.0
    # --- georeference
    crs: str = "EPSG:32630"
    origin: tuple[float, float, float] = (579000.0, 5912000.0, 350.0)
    dem_cell_m: float = 5.0

    @classmethod
    def for_size(cls, size: str = "small", **overrides: Any) -> OutcropSpec:
        """The named scene size with optional overrides.

        ``"small"`` (tests, demo): ≈128 k triangles, 2048² texture, three
        1024 × 768 photos. ``"large"`` (benchmarks): ≈1.2 M triangles, 4096²
        texture, five 1632 × 1224 photos.
        """
        if size == "small":
            base = cls()
        elif size == "large":
            base = cls(grid=(775, 775), texture_size=4096, n_photos=5, photo_size=(1632, 1224))
        else:
            raise ValueError(f"size must be one of {SIZES}, not {size!r}")
        return replace(base, **overrides) if overrides else base

    @property
    def n_triangles(self) -> int:
        """Triangles of the mesh: two per grid cell."""
        nx, ns = self.grid
        return 2 * (nx - 1) * (ns - 1)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (tuples become lists)."""
        return json.loads(json.dumps(asdict(self)))


# --------------------------------------------------------------- orientation
def plane_normal(dip_deg: float, dip_direction_deg: float) -> np.ndarray:
    """Upward unit normal of a plane from dip and dip direction.

    The normal leans toward the dip direction (azimuth of steepest descent,
    clockwise from north = +Y), by the dip angle from vertical.
    """
    d, a = math.radians(dip_deg), math.radians(dip_direction_deg)
    return np.array([math.sin(d) * math.sin(a), math.sin(d) * math.cos(a), math.cos(d)])


def dip_from_normal(normal: np.ndarray) -> tuple[float, float]:
    """(dip_deg, dip_direction_deg) of a plane from any normal (either sign)."""
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    if n[2] < 0:
        n = -n
    dip = math.degrees(math.acos(float(np.clip(n[2], -1.0, 1.0))))
    ddir = math.degrees(math.atan2(n[0], n[1])) % 360.0
    return dip, ddir


# ------------------------------------------------------------------- profile
@dataclass
class Profile:
    """The smooth cross-section (YZ plane) the surface is swept from.

    Attributes
    ----------
    s : (K,) array
        Arc length of the dense polyline, metres (0 at the south end).
    y, z : (K,) arrays
        Polyline coordinates, metres.
    knots : dict
        Arc lengths of landmarks: ``talus`` (start of the talus slope),
        ``foot``, ``top`` (top edge of the face) and ``end``.
    """

    s: np.ndarray
    y: np.ndarray
    z: np.ndarray
    knots: dict[str, float]

    @classmethod
    def build(cls, spec: OutcropSpec, step: float = 0.05) -> Profile:
        H = spec.cliff_height_m
        run = H / math.tan(math.radians(spec.face_angle_deg))
        y_foot = -run / 2.0  # the face's mid-height sits at y = 0
        talus_rise = spec.talus_length_m * math.tan(math.radians(30.0))
        z_ground_end = 1.5  # the apron climbs gently toward the cliff
        z_foot = z_ground_end + talus_rise
        pts = np.array(
            [
                [y_foot - spec.talus_length_m - spec.apron_length_m, 0.0],
                [y_foot - spec.talus_length_m, z_ground_end],
                [y_foot, z_foot],
                [y_foot + run, z_foot + H],
                [y_foot + run + spec.plateau_length_m, z_foot + H + 0.05 * spec.plateau_length_m],
            ]
        )
        # Dense polyline, extended straight at both ends so smoothing keeps them straight.
        seg = np.diff(pts, axis=0)
        lengths = np.hypot(seg[:, 0], seg[:, 1])
        pieces = []
        for k in range(len(seg)):
            n = max(2, int(np.ceil(lengths[k] / step)))
            f = np.arange(n)[:, None] / n
            pieces.append(pts[k] + f * seg[k])
        pieces.append(pts[-1:])
        poly = np.concatenate(pieces)
        pad = 400
        d0 = (poly[1] - poly[0]) * np.arange(pad, 0, -1)[:, None]
        d1 = (poly[-1] - poly[-2]) * np.arange(1, pad + 1)[:, None]
        poly = np.concatenate([poly[0] - d0, poly, poly[-1] + d1])
        # Round the corners (~2 m radius): cliff edges are never sharp.
        poly = ndimage.gaussian_filter1d(poly, 2.0 / step, axis=0, mode="nearest")[pad:-pad]
        s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poly, axis=0).T))])

        def arc_at(y: float) -> float:
            return float(np.interp(y, poly[:, 0], s))

        knots = {
            "talus": arc_at(y_foot - spec.talus_length_m),
            "foot": arc_at(y_foot),
            "top": arc_at(y_foot + run),
            "end": float(s[-1]),
        }
        return cls(s, poly[:, 0], poly[:, 1], knots)

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(y, z, n_y, n_z) at arc lengths ``s``; the normal points to open air."""
        y = np.interp(s, self.s, self.y)
        z = np.interp(s, self.s, self.z)
        ty = np.gradient(self.y, self.s)
        tz = np.gradient(self.z, self.s)
        t_y = np.interp(s, self.s, ty)
        t_z = np.interp(s, self.s, tz)
        norm = np.hypot(t_y, t_z)
        return y, z, -t_z / norm, t_y / norm

    def s_of_t(self, t: np.ndarray) -> np.ndarray:
        """Arc length for grid parameter ``t`` in [0, 1].

        Rows (and texture rows) are spent where they matter: half on the
        cliff face, the rest on the talus, the apron and the plateau.
        """
        k = self.knots
        t_knots = [0.0, 0.22, 0.30, 0.82, 1.0]
        s_knots = [0.0, k["talus"], k["foot"] - 1.0, k["top"] + 4.0, k["end"]]
        return np.interp(t, t_knots, s_knots)


# ------------------------------------------------------------------- geology
def _hash(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Deterministic pseudo-random value in [0, 1) per integer pair (a, b)."""
    v = np.sin(np.asarray(a, np.float64) * 12.9898 + np.asarray(b, np.float64) * 78.233) * 43758.5453
    return v - np.floor(v)


@dataclass
class Geology:
    """Planar layer-cake stratigraphy cut by one planar normal fault.

    Attributes
    ----------
    bed_normal : (3,) array
        Upward unit normal of bedding.
    reference : (3,) array
        ``X0``: where ``h = 0``, metres.
    boundaries : (B,) array
        Ascending bed-boundary ``h`` values, metres.
    lithology : (B + 1,) int array
        0 sandstone, 1 mudstone, for the bed below boundary 0, between
        boundaries, and above the last.
    bed_tint : (B + 1, 3) float array
        Per-bed colour multiplier (beds differ slightly, as in nature).
    fault_point, fault_normal : (3,) arrays
        A point on the fault plane and its upward unit normal; the hanging
        wall is where ``fault_normal · (X − fault_point) > 0``.
    slip : (3,) array
        Displacement of the hanging wall (down-dip), metres.
    h_shift : float
        ``h`` added in the hanging wall (``−n_bed · slip``; > 0 for a
        normal fault: younger beds are brought down).
    """

    bed_normal: np.ndarray
    reference: np.ndarray
    boundaries: np.ndarray
    lithology: np.ndarray
    bed_tint: np.ndarray
    fault_point: np.ndarray
    fault_normal: np.ndarray
    slip: np.ndarray
    h_shift: float
    joint_spacing: np.ndarray
    joint_offset: np.ndarray
    spec: OutcropSpec = field(repr=False)

    @classmethod
    def build(cls, spec: OutcropSpec, h_range: tuple[float, float], rng: np.random.Generator) -> Geology:
        n_bed = plane_normal(spec.bedding_dip_deg, spec.bedding_dip_direction_deg)
        n_f = plane_normal(spec.fault_dip_deg, spec.fault_dip_direction_deg)
        fd, fa = math.radians(spec.fault_dip_deg), math.radians(spec.fault_dip_direction_deg)
        down_dip = np.array([math.cos(fd) * math.sin(fa), math.cos(fd) * math.cos(fa), -math.sin(fd)])
        slip = down_dip * spec.fault_throw_m / math.sin(fd)
        h_shift = float(-n_bed @ slip)
        lo, hi = h_range[0] - 5.0, h_range[1] + h_shift + 5.0
        bounds, lith = [], []
        h = lo
        kind = int(rng.integers(2))
        while h < hi:
            lith.append(kind)
            t_lo, t_hi = spec.sandstone_thickness_m if kind == 0 else spec.mudstone_thickness_m
            h += float(rng.uniform(t_lo, t_hi))
            bounds.append(h)
            kind = 1 - kind
        lith.append(kind)
        lith_a = np.array(lith, np.int8)
        tint = np.empty((len(lith_a), 3))
        for i, k in enumerate(lith_a):
            if k == 0:  # sandstone: buff to orange to pale grey
                warm = rng.uniform(-1.0, 1.0)
                tint[i] = rng.uniform(0.88, 1.08) * np.array([1.0 + 0.05 * warm, 1.0, 1.0 - 0.12 * warm])
            else:  # mudstone: darker or lighter grey, a little green or purple
                hue = rng.uniform(-1.0, 1.0)
                tint[i] = rng.uniform(0.8, 1.12) * np.array([1.0 + 0.04 * hue, 1.0, 1.0 - 0.03 * hue])
        # Vertical joints cut each bed into blocks (wider in sandstone).
        spacing = np.where(lith_a == 0, rng.uniform(1.6, 4.5, len(lith_a)), rng.uniform(0.7, 1.4, len(lith_a)))
        offset = rng.uniform(0.0, 10.0, len(lith_a))
        return cls(
            bed_normal=n_bed,
            reference=np.asarray(spec.bedding_reference, np.float64),
            boundaries=np.array(bounds),
            lithology=lith_a,
            bed_tint=tint,
            fault_point=np.asarray(spec.fault_point, np.float64),
            fault_normal=n_f,
            slip=slip,
            h_shift=h_shift,
            joint_spacing=spacing,
            joint_offset=offset,
            spec=spec,
        )

    def fault_distance(self, X: np.ndarray) -> np.ndarray:
        """Signed distance to the fault plane (> 0 in the hanging wall), metres."""
        return (np.asarray(X) - self.fault_point) @ self.fault_normal

    def h_raw(self, X: np.ndarray) -> np.ndarray:
        """Distance along the bedding normal from ``X0`` (no fault), metres."""
        return (np.asarray(X) - self.reference) @ self.bed_normal

    def h_strat(self, X: np.ndarray) -> np.ndarray:
        """Stratigraphic height, with the hanging wall shifted, metres."""
        X = np.asarray(X)
        return self.h_raw(X) + self.h_shift * (self.fault_distance(X) > 0)

    def bed_index(self, h: np.ndarray) -> np.ndarray:
        """Index of the bed holding stratigraphic height ``h``."""
        return np.searchsorted(self.boundaries, h)

    def contact_distance(self, h: np.ndarray, bed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Stratigraphic distance (m) to the bed's base and to its top."""
        b = self.boundaries
        base = np.where(bed > 0, h - b[np.clip(bed - 1, 0, len(b) - 1)], np.inf)
        top = np.where(bed < len(b), b[np.clip(bed, 0, len(b) - 1)] - h, np.inf)
        return base, top

    def blocks(self, xw: np.ndarray, bed: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Joint blocks from the (warped) along-cliff coordinate ``xw``.

        Returns
        -------
        value : array in [0, 1)
            A random value per block.
        distance : array
            Distance to the nearest joint, metres.
        opening : array in [0, 1]
            How open (eroded, dark) that joint is; many joints are tight.
        """
        sp = self.joint_spacing[bed]
        a = (xw + self.joint_offset[bed]) / sp
        # A monotone wobble makes block widths irregular (0.5–1.5 x spacing).
        q = a + 0.3 * np.sin(2.0 * np.pi * a / 2.7 + bed)
        block = np.floor(q)
        f = q - block
        opening = smoothstep((_hash(bed + 0.5, np.round(q)) - 0.35) / 0.5)
        return _hash(bed, block), np.minimum(f, 1.0 - f) * sp, opening

    def to_dict(self) -> dict[str, Any]:
        spec = self.spec
        beds = []
        edges = np.concatenate([[-np.inf], self.boundaries, [np.inf]])
        for i, k in enumerate(self.lithology):
            base = np.array(SANDSTONE_RGB if k == 0 else MUDSTONE_RGB) * self.bed_tint[i]
            beds.append(
                {
                    "index": i,
                    "lithology": "sandstone" if k == 0 else "mudstone",
                    "h_bottom": None if not np.isfinite(edges[i]) else float(edges[i]),
                    "h_top": None if not np.isfinite(edges[i + 1]) else float(edges[i + 1]),
                    "color": [int(round(c)) for c in np.clip(base, 0, 255)],
                }
            )
        return {
            "frame": "local ENU metres (+X east, +Y north, +Z up); see georef.json",
            "bedding": {
                "dip_deg": spec.bedding_dip_deg,
                "dip_direction_deg": spec.bedding_dip_direction_deg,
                "normal": self.bed_normal.tolist(),
                "reference_point": self.reference.tolist(),
                "stratigraphic_height": "h = normal . (X - reference_point), "
                "plus fault.h_shift in the hanging wall",
            },
            "boundaries_h": self.boundaries.tolist(),
            "beds": beds,
            "fault": {
                "kind": "normal",
                "point": self.fault_point.tolist(),
                "normal": self.fault_normal.tolist(),
                "dip_deg": spec.fault_dip_deg,
                "dip_direction_deg": spec.fault_dip_direction_deg,
                "throw_m": spec.fault_throw_m,
                "slip_vector": self.slip.tolist(),
                "h_shift": self.h_shift,
                "hanging_wall": "normal . (X - point) > 0",
            },
            "lithology_colors": {
                "sandstone": list(SANDSTONE_RGB),
                "mudstone": list(MUDSTONE_RGB),
                "vegetation": list(VEGETATION_RGB),
                "scree": list(SCREE_RGB),
            },
        }


# ------------------------------------------------------------------ outcrop
@dataclass
class Outcrop:
    """A generated outcrop held in memory.

    Attributes
    ----------
    spec : OutcropSpec
    seed : int
    x : (nx,) array
        Grid x positions, metres.
    t : (ns,) array
        Grid parameter along the profile, [0, 1].
    s : (ns,) array
        Arc length of each grid row, metres.
    X : (ns, nx, 3) array
        Grid vertex positions, metres (row = along the profile).
    normals : (ns, nx, 3) array
        Outward unit vertex normals.
    rock : (ns, nx) array
        Rock exposure weight in [0, 1] (0 = vegetation / soil).
    geology : Geology
    profile : Profile
    joint_warp : Lattice
        Waviness of the joints (shared by geometry and texture).
    albedo, texture : (T, T, 3) uint8 arrays
        Reflectance, and reflectance × survey-day shading (the model's texture).
    """

    spec: OutcropSpec
    seed: int
    x: np.ndarray
    t: np.ndarray
    s: np.ndarray
    X: np.ndarray
    normals: np.ndarray
    rock: np.ndarray
    geology: Geology
    profile: Profile
    joint_warp: Lattice
    albedo: np.ndarray | None = None
    texture: np.ndarray | None = None

    @property
    def vertices(self) -> np.ndarray:
        """(V, 3) float64, row-major over the grid."""
        return self.X.reshape(-1, 3)

    @property
    def vertex_normals(self) -> np.ndarray:
        return self.normals.reshape(-1, 3)

    @property
    def faces(self) -> np.ndarray:
        """(F, 3) int32: two counter-clockwise triangles per cell (normals outward)."""
        ns, nx = self.X.shape[:2]
        idx = np.arange(ns * nx, dtype=np.int32).reshape(ns, nx)
        a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
        c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
        # (x, s) is right-handed with the outward normal: (a, b, d), (a, d, c).
        tri = np.empty((2 * len(a), 3), np.int32)
        tri[0::2] = np.stack([a, b, d], 1)
        tri[1::2] = np.stack([a, d, c], 1)
        return tri

    @property
    def uv(self) -> np.ndarray:
        """(V, 2) float64 texture coordinates: the grid parameters in [0, 1]."""
        ns, nx = self.X.shape[:2]
        u, v = np.meshgrid(np.linspace(0.0, 1.0, nx), self.t)
        return np.stack([u.ravel(), v.ravel()], axis=1)

    @property
    def face_rock(self) -> np.ndarray:
        """(F,) rock weight per triangle."""
        return self.rock.reshape(-1)[self.faces].mean(axis=1)

    def scene(self, texture: str = "albedo"):
        """A :class:`~napari_imgreg.Scene` of the mesh with the albedo or model texture."""
        from ..scene import Scene

        tex = self.albedo if texture == "albedo" else self.texture
        return Scene(self.vertices, self.faces, self.uv, tex, name=f"outcrop-{texture}")


def _joint_coordinate(x: np.ndarray, z: np.ndarray, warp: np.ndarray) -> np.ndarray:
    """Along-cliff coordinate in which joints are straight: slightly inclined
    and wavy, as real joints are."""
    return x + 0.12 * z + 0.7 * warp


def _grid_normals(X: np.ndarray) -> np.ndarray:
    """Outward unit normals of a grid surface, (ns, nx, 3)."""
    d_s = np.gradient(X, axis=0)
    d_x = np.gradient(X, axis=1)
    n = np.cross(d_x, d_s)
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)


def _weights(s: np.ndarray, knots: dict[str, float]) -> dict[str, np.ndarray]:
    """Smooth zone weights along the profile: face, ground, plateau, 'above foot'."""
    face = smoothstep((s - knots["foot"] + 1.5) / 3.0) * smoothstep((knots["top"] + 1.5 - s) / 3.0)
    ground = smoothstep((knots["foot"] - 2.0 - s) / 6.0)
    plateau = smoothstep((s - knots["top"] - 1.0) / 5.0)
    above = smoothstep((s - knots["foot"]) / (knots["top"] - knots["foot"]))
    return {"face": face, "ground": ground, "plateau": plateau, "above": above}


def _relief_of_beds(h: np.ndarray, xw: np.ndarray, geo: Geology, groove_m: float) -> np.ndarray:
    """Relief from differential erosion and jointing, metres per metre of
    ``erosion_relief_m`` (roughly in [-0.5, 0.8]).

    Sandstone stands proud (+0.5), rounded off over 0.4 m toward its
    contacts; mudstone is recessed (−0.5), rounded over 0.25 m. Sandstone
    joint blocks stand out or sit back by up to ±0.35 and joints are eroded
    into grooves ``groove_m`` wide.
    """
    bed = geo.bed_index(h)
    base, top = geo.contact_distance(h, bed)
    dist = np.minimum(base, top)
    sand = geo.lithology[bed] == 0
    edge = np.sqrt(smoothstep(dist / 0.4))
    value, jdist, opening = geo.blocks(xw, bed)
    block = 0.7 * (value - 0.5) - 0.45 * opening * np.exp(-((jdist / groove_m) ** 2))
    return np.where(sand, edge * (0.5 + block), -0.5 * smoothstep(dist / 0.25))


def build_geometry(spec: OutcropSpec, seed: int) -> Outcrop:
    """Grid geometry, geology and rock mask of the outcrop (no texture yet)."""
    rng = rng_for(seed, _S_GEOMETRY)
    profile = Profile.build(spec)
    nx, ns = spec.grid
    x = np.linspace(-spec.width_m / 2, spec.width_m / 2, nx)
    t = np.linspace(0.0, 1.0, ns)
    s = profile.s_of_t(t)
    py, pz, ny, nz = profile.at(s)
    w = _weights(s, profile.knots)
    xr, sr = (x[0], x[-1]), (0.0, profile.knots["end"])

    # Real terrain undulation (ground and plateau) and the cliff-top line.
    relief = dem_relief(rng)
    n = relief.shape[0]
    lat = Lattice(relief, xr[0], sr[0], max(xr[1] - xr[0], sr[1] - sr[0]) / (n - 1))
    terrain = lat.grid(x, s) * spec.ground_relief_m
    terrain *= (w["ground"] * (0.3 + 0.7 * smoothstep((profile.knots["talus"] - s) / 15.0)))[:, None] + w[
        "plateau"
    ][:, None]
    top_line = dem_relief(rng)[relief.shape[0] // 2]
    top_line = np.interp(np.linspace(0, 1, nx), np.linspace(0, 1, len(top_line)), top_line)
    top_line = (top_line - top_line.mean()) / max(top_line.std(), 1e-6) * spec.top_line_relief_m

    # Face relief: buttresses (broad), gullies (long down the face, incised:
    # the negative tail is deepened), roughness.
    face = np.zeros((ns, nx))
    for sigma, amp in (((14.0, 14.0), 0.5), ((3.5, 12.0), 0.6), ((1.5, 2.5), 0.25), ((0.6, 0.6), 0.08)):
        nf = smooth_lattice(rng, xr, sr, sigma).grid(x, s)
        face += amp * (nf - 1.5 * np.maximum(-nf - 0.6, 0.0))
    face *= spec.face_relief_m * w["face"][:, None]
    joint_warp = smooth_lattice(rng, xr, sr, (3.0, 3.0))
    # Shallow wave of the cliff line in plan (a few metres).
    plan = smooth_lattice(rng, xr, (0.0, 1.0), (30.0, 30.0)).grid(x, np.zeros(1))[0] * 2.0

    bay = -spec.bay_depth_m * (2.0 * x / spec.width_m) ** 2
    X = np.empty((ns, nx, 3))
    X[..., 0] = x[None, :]
    X[..., 1] = py[:, None] + bay[None, :] + plan[None, :] * w["above"][:, None] ** 0.3 * (1 - w["plateau"][:, None])
    X[..., 2] = pz[:, None] + top_line[None, :] * w["above"][:, None]
    N2 = np.stack([np.zeros_like(ny), ny, nz], axis=1)  # profile normal, (ns, 3)

    geo_rng = rng_for(seed, _S_GEOLOGY)
    # Geology needs the h range: compute it on the undisplaced surface (+ margin).
    h_tmp = (X - np.asarray(spec.bedding_reference)) @ plane_normal(
        spec.bedding_dip_deg, spec.bedding_dip_direction_deg
    )
    geology = Geology.build(spec, (float(h_tmp.min()) - 10, float(h_tmp.max()) + 10), geo_rng)

    # A fault zone erodes into a gully.
    fd = geology.fault_distance(X)
    face -= 1.2 * np.exp(-((fd / 2.0) ** 2)) * w["face"][:, None]
    X += N2[:, None, :] * (terrain + face)[..., None]

    # Differential erosion, displaced within the bedding plane so h (and so
    # the lithology at every point) is unchanged by it.
    h = geology.h_strat(X)
    d = N2 - (N2 @ geology.bed_normal)[:, None] * geology.bed_normal
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    modulation = 1.0 + 0.3 * smooth_lattice(rng, xr, sr, (20.0, 10.0)).grid(x, s)
    xw = _joint_coordinate(x[None, :], X[..., 2], joint_warp.grid(x, s))
    groove = max(0.25, 0.8 * (x[1] - x[0]))  # narrower than the grid would alias
    ero = spec.erosion_relief_m * _relief_of_beds(h, xw, geology, groove) * modulation
    X += d[:, None, :] * (ero * w["face"][:, None])[..., None]

    normals = _grid_normals(X)
    steep = 1.0 - normals[..., 2]
    rock_noise = smooth_lattice(rng, xr, sr, (3.0, 3.0)).grid(x, s)
    rock = smoothstep((steep - 0.32 + 0.12 * rock_noise) / 0.12)
    zone = smoothstep((s - profile.knots["foot"] + 4.0) / 3.0) * smoothstep((profile.knots["top"] + 12.0 - s) / 4.0)
    rock *= zone[:, None]
    return Outcrop(spec, seed, x, t, s, X, normals, rock, geology, profile, joint_warp)


# ------------------------------------------------------------------- texture
def _texture_rows(outcrop: Outcrop, r0: int, r1: int, fields: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Albedo and survey texture of texture rows ``r0:r1`` (sRGB uint8).

    Each texel is mapped to its grid parameters, then to its 3-D point and
    normal (bilinear on the grid), so its lithology is the one at its true
    position.
    """
    spec, geo = outcrop.spec, outcrop.geology
    T = spec.texture_size
    ns, nx = outcrop.X.shape[:2]
    rows = np.arange(r0, r1)
    v = 1.0 - (rows + 0.5) / T  # OpenGL: v = 0 at the bottom row
    u = (np.arange(T) + 0.5) / T
    ri, ci = v * (ns - 1), u * (nx - 1)
    X = separable_sample(outcrop.X - fields["center"], ri, ci).astype(np.float64) + fields["center"]
    nrm = separable_sample(outcrop.normals, ri, ci)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=-1, keepdims=True), 1e-6)
    x = np.interp(ci, np.arange(nx), outcrop.x).astype(np.float32)[None, :]
    s = np.interp(ri, np.arange(ns), outcrop.s).astype(np.float32)[:, None]
    shape = (len(rows), T)
    xx = np.broadcast_to(x, shape)
    ss = np.broadcast_to(s, shape)
    z = X[..., 2].astype(np.float32)
    rng = rng_for(outcrop.seed, _S_TEXTURE, 1000 + r0)
    lat = fields["lattices"]
    knots = outcrop.profile.knots
    rot, off = fields["rot"], fields["off"]

    def L(name: str) -> np.ndarray:
        la: Lattice = lat[name]
        return separable_sample(la.data, la.rows(s[:, 0]), la.cols(x[0]))

    def mix(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
        return a + (b - a) * w[..., None]

    # ---- lithology, bed contacts and joint blocks at the texel's 3-D point
    h = geo.h_strat(X)
    bed = geo.bed_index(h)
    sand = geo.lithology[bed] == 0
    base_d, top_d = geo.contact_distance(h, bed)
    xw = _joint_coordinate(xx, z, L("joint_warp"))
    bval, jdist, jopen = (a.astype(np.float32) for a in geo.blocks(xw, bed))
    tint = geo.bed_tint[bed].astype(np.float32)
    fine = ndimage.gaussian_filter(rng.standard_normal(shape, dtype=np.float32), 0.7)
    colour = L("colour")

    # Real photographic detail (scikit-image's gravel, brick): grain, blockiness.
    g1 = sample_detail("gravel", xx, z, 7.0, 17.0 + rot[0], off[0])
    g2 = sample_detail("gravel", xx, z, 2.2, -41.0 + rot[1], off[1])
    br = sample_detail("brick", z * 1.4, xw, 6.0, 90.0 + rot[2], off[2])
    lam = np.sin(2 * np.pi * (h / np.where(sand, 0.3, 0.12) + 2.0 * L("joint_warp"))).astype(np.float32)

    # ---- sandstone: per-bed tint, per-block tone, iron staining, varnish, joints
    sand_col = np.float32(SANDSTONE_RGB) * tint
    sand_col = mix(sand_col, np.float32([176, 122, 74]) * tint, 0.5 * smoothstep((L("stain") - 0.6) / 0.9))
    sand_col = mix(sand_col, np.float32([172, 168, 150]), 0.35 * smoothstep((L("bleach") - 0.5) / 0.8))
    scar = smoothstep((bval - 0.86) / 0.05)  # fresh rockfall scars: paler, unweathered
    varnish = 0.32 * smoothstep((L("varnish") - 0.3) / 0.9) * (1.0 - scar)
    sand_lum = (0.14 * g1 + 0.09 * g2 + 0.06 * np.minimum(br, 1.0) + 0.035 * lam
                + 0.22 * (bval - 0.5) + 0.06 * colour + 0.1 * scar)
    sand_lum += np.log(1.0 - varnish)
    sand_lum += np.log(1.0 - 0.4 * jopen * np.exp(-((jdist / (0.04 + 0.06 * jopen)) ** 2)))

    # ---- mudstone: grey, fissile, partly under debris, stained below sandstone
    mud_col = np.float32(MUDSTONE_RGB) * tint
    mud_col = mix(mud_col, np.float32([128, 116, 100]) * tint, 0.6 * smoothstep(L("stain") * 0.7 + 0.5))
    mud_col = mix(mud_col, np.float32(SCREE_RGB), 0.45 * smoothstep((L("debris") + 0.2) / 1.2))
    seep = np.exp(-np.clip(top_d, 0.0, None) / 0.3).astype(np.float32)
    mud_lum = (0.12 * g2 + 0.07 * g1 + 0.08 * lam + 0.1 * colour + 0.08 * (bval - 0.5)
               + np.log(1.0 - 0.2 * jopen * np.exp(-((jdist / 0.04) ** 2))) + np.log(1.0 - 0.25 * seep))
    rock_col = np.where(sand[..., None], sand_col, mud_col)
    rock_lum = np.where(sand, sand_lum, mud_lum) + 0.05 * fine
    # Weathering streaks hang below ledges, in patches.
    streak = np.maximum(L("streak"), 0.0) * smoothstep(L("colour2") + 0.3)
    rock_lum += np.log(1.0 - 0.16 * np.clip(streak, 0.0, 2.0) / 2.0 * 2.0)
    rock_col = rock_col * np.exp(rock_lum)[..., None]
    lichen = 0.4 * smoothstep((L("lichen") - 1.9) / 0.5)
    rock_col = mix(rock_col, np.float32([170, 172, 150]), lichen)

    # ---- vegetation (real grass photo) and scree
    grass = sample_detail("grass", xx, ss, 3.5, 23.0 + rot[3], off[3])
    grass2 = sample_detail("grass", xx, ss, 11.0, -62.0 + rot[4], off[4])
    veg = mix(np.float32(VEGETATION_RGB), np.float32([146, 130, 84]), smoothstep(0.5 + 0.4 * L("veg")))
    veg = mix(veg, np.float32([78, 92, 48]), 0.5 * smoothstep(L("veg2") - 0.5))
    veg *= np.exp(0.2 * grass + 0.12 * grass2 + 0.05 * fine)[..., None]
    scree_col = mix(np.float32(SCREE_RGB), np.float32([180, 160, 125]), smoothstep(L("colour2")))
    scree_col *= np.exp(0.3 * g2 + 0.18 * g1 + 0.08 * colour)[..., None]
    # Fallen blocks on the talus: a jittered grid of boulders, 0.4-1.6 m across.
    cell = 2.5
    bx, by = np.floor(xx / cell), np.floor(ss / cell)
    cx = (bx + 0.2 + 0.6 * _hash(bx, by + 7.0)) * cell
    cy = (by + 0.2 + 0.6 * _hash(bx + 3.0, by)) * cell
    radius = 0.2 + 0.6 * _hash(bx + 11.0, by + 5.0)
    boulder = (_hash(bx + 1.0, by + 2.0) > 0.55) * smoothstep((radius - np.hypot(xx - cx, ss - cy)) / 0.12)
    boulder_col = np.where((_hash(bx, by) > 0.35)[..., None], np.float32(SANDSTONE_RGB), np.float32(MUDSTONE_RGB))
    scree_col = mix(scree_col, boulder_col * np.exp(0.2 * g1)[..., None], boulder.astype(np.float32))

    # ---- which surface: steep is bare rock, gentle is vegetated; talus at the foot
    steep = 1.0 - nrm[..., 2]
    rock_w = smoothstep((steep - 0.32 + 0.12 * (L("rock") + 0.3 * fine)) / 0.1)
    # Bare rock only in the cliff zone (the ground's DEM relief is grassed over).
    rock_w *= smoothstep((s - knots["foot"] + 4.0) / 3.0) * smoothstep((knots["top"] + 12.0 - s) / 4.0)
    talus = smoothstep((s - knots["talus"] + 4.0) / 5.0) * smoothstep((knots["foot"] + 2.0 - s) / 1.5)
    talus = np.broadcast_to(talus, shape) * smoothstep(0.45 + 0.5 * L("veg") + 0.3 * fine)
    col = mix(veg, scree_col, talus)
    col = mix(col, rock_col, rock_w)
    albedo = np.clip(col + 0.5, 0, 255).astype(np.uint8)

    # ---- the model texture: albedo x survey-day shading
    amb = spec.survey_ambient
    shade = amb + (1.0 - amb) * np.clip(nrm @ fields["sun"], 0.0, None)
    model = np.clip(col * shade[..., None] + 0.5, 0, 255).astype(np.uint8)
    return albedo, model


def build_texture(outcrop: Outcrop, chunk: int = 256) -> None:
    """Compute ``outcrop.albedo`` and ``outcrop.texture`` (in place)."""
    from concurrent.futures import ThreadPoolExecutor

    from ..scene import ray_threads

    spec = outcrop.spec
    rng = rng_for(outcrop.seed, _S_TEXTURE)
    xr = (float(outcrop.x[0]), float(outcrop.x[-1]))
    sr = (0.0, float(outcrop.s[-1]))
    lat = {
        "colour": smooth_lattice(rng, xr, sr, (10.0, 6.0)),
        "colour2": smooth_lattice(rng, xr, sr, (4.0, 4.0)),
        "stain": smooth_lattice(rng, xr, sr, (5.0, 3.0)),
        "bleach": smooth_lattice(rng, xr, sr, (18.0, 12.0)),
        "varnish": smooth_lattice(rng, xr, sr, (2.0, 7.0), cells_per_sigma=2.0),
        "debris": smooth_lattice(rng, xr, sr, (3.0, 1.0), cells_per_sigma=2.0),
        "streak": smooth_lattice(rng, xr, sr, (0.35, 6.0), cells_per_sigma=2.0),
        "lichen": smooth_lattice(rng, xr, sr, (0.4, 0.4), cells_per_sigma=2.0),
        "veg": smooth_lattice(rng, xr, sr, (6.0, 6.0)),
        "veg2": smooth_lattice(rng, xr, sr, (1.0, 1.0)),
        "rock": smooth_lattice(rng, xr, sr, (2.0, 2.0)),
        "joint_warp": outcrop.joint_warp,
    }
    fields = {
        "lattices": lat,
        "center": outcrop.X.reshape(-1, 3).mean(axis=0),
        "rot": rng.uniform(-10.0, 10.0, 5),
        "off": [tuple(rng.uniform(0, 512, 2)) for _ in range(5)],
        "sun": sun_vector(spec.survey_sun_azimuth_deg, spec.survey_sun_elevation_deg).astype(np.float32),
    }
    T = spec.texture_size
    albedo = np.empty((T, T, 3), np.uint8)
    model = np.empty((T, T, 3), np.uint8)

    def work(r0: int) -> None:
        r1 = min(T, r0 + chunk)
        a, m = _texture_rows(outcrop, r0, r1, fields)
        albedo[r0:r1] = a
        model[r0:r1] = m

    with ThreadPoolExecutor(ray_threads()) as pool:
        list(pool.map(work, range(0, T, chunk)))
    outcrop.albedo, outcrop.texture = albedo, model


def build_outcrop(spec: OutcropSpec, seed: int = 0, texture: bool = True) -> Outcrop:
    """Geometry, geology and (optionally) texture of a sample outcrop."""
    outcrop = build_geometry(spec, seed)
    if texture:
        build_texture(outcrop)
    return outcrop


# ----------------------------------------------------------------- writing
def _format_rows(prefix: str, fmt: str, arr: np.ndarray) -> str:
    """Rows of numbers as OBJ lines, formatted in one C-level call (fast)."""
    line = prefix + " " + " ".join([fmt] * arr.shape[1]) + "\n"
    return (line * len(arr)) % tuple(arr.ravel().tolist())


def write_model(outcrop: Outcrop, out_dir: Path, name: str = "outcrop") -> dict[str, str]:
    """Write the OBJ + MTL + texture JPEG and the albedo PNG.

    Written in the order texture, material, mesh (each atomically), so a
    reader never sees an OBJ whose texture is not there yet.

    Returns
    -------
    dict
        File names written, by role.
    """
    from PIL import Image

    spec = outcrop.spec
    tex_name, mtl_name, obj_name = f"{name}_texture.jpg", f"{name}.mtl", f"{name}.obj"
    with atomic_path(out_dir / tex_name) as tmp:
        Image.fromarray(outcrop.texture).save(tmp, format="JPEG", quality=spec.texture_jpeg_quality)
    with atomic_path(out_dir / "albedo.png") as tmp:
        Image.fromarray(outcrop.albedo).save(tmp, format="PNG", compress_level=1)
    with atomic_write(out_dir / mtl_name, encoding="ascii") as fh:
        fh.write(
            f"# napari-imgreg sample outcrop\nnewmtl {name}\nKa 1.000 1.000 1.000\n"
            f"Kd 1.000 1.000 1.000\nKs 0.000 0.000 0.000\nd 1.0\nillum 1\nmap_Kd {tex_name}\n"
        )
    f1 = outcrop.faces.astype(np.int64) + 1
    corner = np.repeat(f1, 2, axis=1)  # "v/vt": vertex and UV share their index
    with atomic_write(out_dir / obj_name, encoding="ascii") as fh:
        fh.write(
            f"# napari-imgreg sample outcrop (seed {outcrop.seed}), local ENU metres\n"
            f"mtllib {mtl_name}\no {name}\n"
        )
        fh.write(_format_rows("v", "%.4f", outcrop.vertices))
        fh.write(_format_rows("vt", "%.6f", outcrop.uv))
        fh.write(f"usemtl {name}\n")
        fh.write(_format_faces(corner))
    return {"mesh": obj_name, "material": mtl_name, "texture": tex_name, "albedo": "albedo.png"}


def _format_faces(corner: np.ndarray) -> str:
    line = "f %d/%d %d/%d %d/%d\n"
    return (line * len(corner)) % tuple(corner.ravel().tolist())


def quantize_vertices(outcrop: Outcrop, decimals: int = 4) -> None:
    """Round vertices to what the OBJ stores, so in-memory truth = file truth."""
    outcrop.X = np.round(outcrop.X, decimals)
