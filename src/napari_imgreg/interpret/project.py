"""Interpretations drawn on a registered photo, projected onto the surface in 3D.

A line drawn on the photo is densified to about one sample per pixel and one
ray is cast through each sample with the registered camera (its distortion
honoured), through the scene's one ray engine. The hits form the 3D trace, so
it follows the relief. Where a ray misses (sky, a hole in the model) or the
surface seen jumps in depth between neighbouring samples (an occluding ridge,
an overhang), the line is split there: the parts are never bridged.

A polygon becomes its projected ring plus the *surface patch*: the visible
faces inside it, found by one ray per pixel inside the polygon; the facet's
plane is fitted to the patch's surface points.

On a point cloud (a :class:`~napari_imgreg.cloud.CloudScene`) the same
features are read from the photo's splat render instead of cast ray by ray:
lines through its per-pixel depth, split where the range jumps by more than
a few point spacings (the gap rule of :mod:`napari_imgreg.interpret.on_cloud`),
and facets from the cloud's own points inside the polygon that the render's
z-buffer sees. Everything after (σ, ``camera_position``, ``measure``, the
exports) is the same for both kinds of scene.

Lines from several registered photos merge into one set, each feature keeping
``properties.source`` (the photo it was drawn on), ``properties.camera_position``
(the photo's camera centre) and ``properties.sigma_m`` (the expected 3D error
of its points from the pose, the drawing and the mesh; see
:mod:`napari_imgreg.interpret.uncertainty`).

The work is bounded by the photo: a drawn line is clipped to the image (a
vertex far outside it is refused), and no line is sampled more finely than
``MIN_STEP_PX`` (so a line has at most its clipped length / step samples).

Frames: pixels are (x = column, y = row), pixel centres at integers (contract
§1); 3D points are in the local model frame, metres.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace
from typing import Any, Iterable, Sequence

import numpy as np

from ..camera import Intrinsics, Pose, as_points
from ..scene import Scene
from ..errors import InputError
from .on_cloud import (
    CloudProjectionParams,
    CloudView,
    cloud_breaks,
    cloud_hits,
    cloud_patch,
    cloud_view,
)
from .structural import (
    DEFAULT_THRESHOLDS,
    FitThresholds,
    Measurement,
    measure_facet,
    measure_three_point,
    measure_traces,
)
from .uncertainty import (
    DEFAULT_UNCERTAINTY,
    ErrorModel,
    PoseUncertainty,
    UncertaintyParams,
    point_sigma,
)

__all__ = [
    "LABEL_COLORS",
    "ProjectionParams",
    "Interpretation",
    "Feature3D",
    "ProjectedLine",
    "densify",
    "project_polyline",
    "surface_patch",
    "project_interpretations",
    "merge_interpretations",
    "measure_features",
    "label_color",
    "check_drawing",
    "MIN_STEP_PX",
    "MAX_OUTSIDE",
]

#: Finest sample spacing along a drawn line, pixels: a line across the whole
#: photo then has at most diagonal / 0.05 samples (≈ 40 000 for a 1632 px photo).
MIN_STEP_PX = 0.05
#: A drawn vertex may lie at most this many photo diagonals outside the image
#: (a line that starts just off the photo is clipped; 1e9 px is refused).
MAX_OUTSIDE = 1.0

#: Colours of the standard label classes (Kehl et al., Fig. 8); others get one
#: from :data:`_EXTRA_COLORS` by name.
LABEL_COLORS: dict[str, str] = {
    "sandstone": "#ffd400",
    "mudstone": "#8c8c8c",
    "fault": "#e31a1c",
}
_EXTRA_COLORS = ("#1f78b4", "#33a02c", "#ff7f00", "#6a3d9a", "#b15928", "#a6cee3", "#fb9a99")


def label_color(label: str, color: str | None = None) -> str:
    """The colour of a label: the feature's own (when matplotlib reads it as a
    colour: a hand-edited file's ``"color": 5`` is not), the standard one, or
    a stable pick."""
    if color:
        from matplotlib.colors import is_color_like

        if isinstance(color, str) and is_color_like(color):
            return color
    if label in LABEL_COLORS:
        return LABEL_COLORS[label]
    # Stable across runs (str hash is salted per process).
    k = sum(label.encode("utf-8")) % len(_EXTRA_COLORS)
    return _EXTRA_COLORS[k]


@dataclass(frozen=True)
class ProjectionParams:
    """How lines are sampled and where they are split.

    Attributes
    ----------
    step_px : float
        Sample spacing along each image segment, pixels (about one per pixel).
    grazing_deg : float
        Split between two samples when the 3D step between their hits lies
        within this angle of the viewing ray: the surface would have to be
        seen that obliquely to be continuous, so it is an occlusion edge or an
        overhang.
    jump_ratio : float
        Also split where the depth step exceeds this many pixel footprints
        *and* ``jump_contrast`` times the median step of the neighbouring
        samples: an isolated jump, not a steep but continuous surface.
    jump_contrast : float
    jump_window : int
        Neighbours on each side for that median.
    min_part_points : int
        Parts with fewer samples are dropped (a lone hit is not a line).
    patch_max_points : int
        Surface points kept per facet patch (an even subsample) for its plane.
    cloud : CloudProjectionParams
        On a point cloud: the gap rule that splits lines (in place of the
        jump test above; ``grazing_deg`` caps its oblique allowance) and the
        visibility test of facet points.
    """

    step_px: float = 1.0  # range MIN_STEP_PX–100
    grazing_deg: float = 5.0
    jump_ratio: float = 3.0
    jump_contrast: float = 8.0
    jump_window: int = 5
    min_part_points: int = 2
    patch_max_points: int = 20_000
    cloud: CloudProjectionParams = field(default_factory=CloudProjectionParams)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.step_px) and MIN_STEP_PX <= self.step_px <= 100.0):
            raise InputError(f"step must be in [{MIN_STEP_PX}, 100] pixels, not {self.step_px!r}")
        if not (math.isfinite(self.grazing_deg) and 0.0 <= self.grazing_deg < 90.0):
            raise InputError(f"grazing angle must be in [0, 90) degrees, not {self.grazing_deg!r}")


@dataclass
class Interpretation:
    """One feature drawn on a photo.

    Attributes
    ----------
    geometry : {"LineString", "Polygon"}
    pixels : (N, 2) float array
        Vertices as pixel (x = column, y = row). A polygon's ring is given
        open (the first vertex is not repeated).
    properties : dict
        At least ``label``; ``color`` optional; others are carried through.
    """

    geometry: str
    pixels: np.ndarray
    properties: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.geometry not in ("LineString", "Polygon"):
            raise ValueError(f"geometry must be LineString or Polygon, not {self.geometry!r}")
        px = as_points(self.pixels, 2, "pixels of a drawing")
        if self.geometry == "Polygon" and len(px) > 1 and np.array_equal(px[0], px[-1]):
            px = px[:-1]
        self.pixels = px
        self.properties = dict(self.properties)
        self.properties.setdefault("label", "unlabelled")

    @property
    def label(self) -> str:
        return str(self.properties.get("label", "unlabelled"))

    @property
    def color(self) -> str:
        return label_color(self.label, self.properties.get("color"))


@dataclass
class Feature3D:
    """An interpretation on the surface in 3D.

    Attributes
    ----------
    id : str
    kind : {"trace", "facet"}
        A projected line, or a projected polygon.
    parts : list of (Mi, 3) float arrays
        Continuous pieces on the surface, metres. A trace split at gaps and
        occlusions has several; a facet's are the pieces of its ring.
    properties : dict
        ``label``, ``color``, ``source`` and the 2D feature's other properties.
    ring_complete : bool
        Facets: the whole ring is on the surface (one closed part).
    patch_points : (K, 3) array or None
        Facets: surface points inside the polygon (subsampled), metres.
    patch_faces : (F,) int array or None
        Facets: indices of the visible faces inside the polygon (on a point
        cloud: of the visible cloud points, all of them).
    surface_normal : (3,) array or None
        Mean surface normal under the feature, turned toward the camera.
    samples : int
        Rays cast along the line or ring.
    missed : int
        Of them, rays that met no surface or fell in dropped pieces.
    """

    id: str
    kind: str
    parts: list[np.ndarray]
    properties: dict[str, Any]
    ring_complete: bool = False
    patch_points: np.ndarray | None = None
    patch_faces: np.ndarray | None = None
    surface_normal: np.ndarray | None = None
    samples: int = 0
    missed: int = 0

    @property
    def label(self) -> str:
        return str(self.properties.get("label", "unlabelled"))

    @property
    def source(self) -> str:
        return str(self.properties.get("source", ""))

    @property
    def color(self) -> str:
        return label_color(self.label, self.properties.get("color"))

    @property
    def points(self) -> np.ndarray:
        """All part vertices, (N, 3) metres."""
        if not self.parts:
            return np.zeros((0, 3))
        return np.concatenate(self.parts)

    @property
    def n_points(self) -> int:
        return sum(len(p) for p in self.parts)

    @property
    def length_m(self) -> float:
        """Summed length of the parts, metres."""
        return float(sum(np.linalg.norm(np.diff(p, axis=0), axis=1).sum() for p in self.parts))

    @property
    def error_model(self) -> ErrorModel | None:
        """Camera centre and expected point error, from the properties (None
        for files written without ``camera_position``)."""
        return ErrorModel.from_properties(self.properties)

    @property
    def contact(self) -> str:
        """The contact this trace belongs to: ``properties.contact`` of the
        drawing, empty when not given (an ``id`` is not a contact)."""
        return str(self.properties.get("contact") or "")

    def measure(
        self,
        thresholds: FitThresholds = DEFAULT_THRESHOLDS,
        uncertainty: UncertaintyParams = DEFAULT_UNCERTAINTY,
    ) -> Measurement:
        """The feature's contract §6 measurement (see :mod:`napari_imgreg.interpret.structural`)."""
        color = label_color(self.label, self.properties["color"]) \
            if self.properties.get("color") else None
        model = self.error_model
        if self.kind == "facet":
            pts = self.patch_points if self.patch_points is not None and len(self.patch_points) else self.points
            m = measure_facet(pts, self.id, self.label, self.source, thresholds, model, uncertainty)
        elif self.properties.get("measure") == "three_point":
            # The plane through the surface points under the three clicks
            # (``three_point_xyz``, in the frame of the coordinates), not the
            # fit of the drawn polyline.
            m = measure_three_point(self.properties.get("three_point_xyz"),
                                    None if model is None else model.camera_position,
                                    self.id, self.label, self.source, model, uncertainty,
                                    self.surface_normal)
            if "three_point_xyz" not in self.properties:
                m.note = ("no plane: the file has no three_point_xyz for this 3-point plane "
                          "(written before they were kept: re-run `project`)")
                if self.n_points:
                    m.centroid, m.n_points = self.points.mean(axis=0), self.n_points
        else:
            m = measure_traces(
                [self.parts], self.id, self.label, [self.source], self.surface_normal,
                thresholds, [model] if model is not None else None, uncertainty,
            )
        m.color = color
        # The geologist's own words travel with the numbers (the CSV, the GIS layer).
        m.comment = str(self.properties.get("comment") or "")
        m.above = str(self.properties.get("above") or "")
        m.below = str(self.properties.get("below") or "")
        return m


# ---------------------------------------------------------------- sampling
def check_drawing(pixels: np.ndarray, width: int, height: int, where: str = "") -> np.ndarray:
    """Refuse vertices that are not finite or lie far outside the photo.

    Parameters
    ----------
    pixels : (N, 2) array
        Vertices (x, y), pixels.
    width, height : int
        The photo's size.
    where : str
        Names the feature in the message.

    Returns
    -------
    (N, 2) array
        The vertices, as float64.

    Raises
    ------
    InputError
        A NaN/inf coordinate, or one more than :data:`MAX_OUTSIDE` photo
        diagonals outside the image: sampling it would be unbounded work.
    """
    p = np.asarray(pixels, np.float64).reshape(-1, 2)
    prefix = f"{where}: " if where else ""
    if not np.isfinite(p).all():
        raise InputError(f"{prefix}a vertex coordinate is not a finite number")
    diag = math.hypot(width, height)
    margin = MAX_OUTSIDE * diag
    out = (p[:, 0] < -margin) | (p[:, 0] > width + margin) | (p[:, 1] < -margin) | (p[:, 1] > height + margin)
    if out.any():
        k = int(np.flatnonzero(out)[0])
        raise InputError(
            f"{prefix}vertex {k + 1} at ({p[k, 0]:.6g}, {p[k, 1]:.6g}) px is far outside the "
            f"{width}×{height} photo (more than {MAX_OUTSIDE:g} diagonal beyond its edge)")
    return p


def _clip_segments(p: np.ndarray, width: int, height: int) -> list[np.ndarray]:
    """The polyline's pieces inside the image rectangle [-0.5, w-0.5]×[-0.5, h-0.5]
    (Liang–Barsky per segment; consecutive inside pieces are joined)."""
    lo = np.array([-0.5, -0.5])
    hi = np.array([width - 0.5, height - 0.5])
    pieces: list[list[np.ndarray]] = []
    current: list[np.ndarray] = []
    for a, b in zip(p[:-1], p[1:]):
        d = b - a
        t0, t1 = 0.0, 1.0
        ok = True
        for k in range(2):
            for q, r in ((-d[k], a[k] - lo[k]), (d[k], hi[k] - a[k])):
                if q == 0:
                    if r < 0:
                        ok = False
                else:
                    t = r / q
                    if q < 0:
                        t0 = max(t0, t)
                    else:
                        t1 = min(t1, t)
        if not ok or t0 > t1:
            if current:
                pieces.append(current)
                current = []
            continue
        ca, cb = a + t0 * d, a + t1 * d
        if current and np.allclose(current[-1], ca):
            current.append(cb)
        else:
            if current:
                pieces.append(current)
            current = [ca, cb]
        if t1 < 1.0:
            pieces.append(current)
            current = []
    if current:
        pieces.append(current)
    return [np.array(c) for c in pieces]


def densify(pixels: np.ndarray, step_px: float = 1.0, closed: bool = False) -> np.ndarray:
    """Samples along a polyline about ``step_px`` apart, every vertex kept.

    Parameters
    ----------
    pixels : (N, 2) array
        Vertices (x, y), pixels.
    step_px : float
    closed : bool
        Also sample the segment from the last vertex back to the first (and
        end on the first vertex again).

    Returns
    -------
    (M, 2) array
    """
    p = np.asarray(pixels, np.float64).reshape(-1, 2)
    if closed and len(p) > 2:
        p = np.vstack([p, p[:1]])
    if len(p) < 2:
        return p.copy()
    seg = np.diff(p, axis=0)
    n = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / step_px).astype(int))
    t = np.concatenate([np.arange(k) / k for k in n])
    start = np.repeat(np.arange(len(seg)), n)
    out = p[start] + t[:, None] * seg[start]
    return np.vstack([out, p[-1:]])


@dataclass
class ProjectedLine:
    """The hits of a densified image polyline.

    Attributes
    ----------
    pixels : (M, 2) array
        The samples (x, y).
    points : (M, 3) array
        Surface points, NaN for misses; metres.
    distance : (M,) array
        Ray length to the hit, metres (inf for misses).
    face_id : (M,) int array
        Hit triangle, -1 for a miss.
    part : (M,) int array
        Index of the continuous part each sample belongs to, -1 where the
        sample is off the surface or in a dropped piece.
    normals : (M, 3) array
        Face normals at the hits, turned toward the camera (0 for misses).
    """

    pixels: np.ndarray
    points: np.ndarray
    distance: np.ndarray
    face_id: np.ndarray
    part: np.ndarray
    normals: np.ndarray

    @property
    def parts(self) -> list[np.ndarray]:
        """The 3D parts, each (Mi, 3), in order."""
        return [self.points[self.part == k] for k in range(int(self.part.max(initial=-1)) + 1)]


def _breaks(
    directions: np.ndarray, distance: np.ndarray, hit: np.ndarray, params: ProjectionParams
) -> np.ndarray:
    """(M - 1,) bool: is there a depth discontinuity between samples i and i+1?"""
    r = np.where(hit, distance, 0.0)  # misses are inf: keep them out of the arithmetic
    r0, r1 = r[:-1], r[1:]
    d0, d1 = directions[:-1], directions[1:]
    both = hit[:-1] & hit[1:]
    # Lateral spacing of the two hits (the pixel footprint), from the angle
    # between their rays; the depth step against it is cot(step-to-ray angle).
    cos_a = np.clip(np.einsum("ij,ij->i", d0, d1), -1.0, 1.0)
    angle = np.arccos(cos_a)
    r_mean = np.where(both, (r0 + r1) / 2.0, 0.0)
    lateral = np.maximum(r_mean * angle, 1e-9)
    ratio = np.where(both, np.abs(r1 - r0) / lateral, 0.0)
    breaks = ratio > 1.0 / math.tan(math.radians(params.grazing_deg))
    if len(ratio) > 2 and params.jump_contrast > 0:
        w = params.jump_window
        padded = np.pad(np.where(both, ratio, np.nan), w, mode="constant", constant_values=np.nan)
        windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * w + 1).copy()
        windows[:, w] = np.nan  # the step itself is not its own neighbour
        with warnings.catch_warnings():  # all-NaN windows (off the surface) are expected
            warnings.simplefilter("ignore", RuntimeWarning)
            local = np.nanmedian(windows, axis=1)
        local = np.where(np.isfinite(local), local, 0.0)
        breaks |= (ratio > params.jump_ratio) & (ratio > params.jump_contrast * local)
    return breaks & both


def project_polyline(
    scene: Scene,
    intrinsics: Intrinsics,
    pose: Pose,
    pixels: np.ndarray,
    closed: bool = False,
    params: ProjectionParams = ProjectionParams(),
    view: CloudView | None = None,
) -> ProjectedLine:
    """Cast an image polyline onto the surface, split where it leaves it.

    Parameters
    ----------
    scene : Scene or CloudScene
        A mesh's ray engine (built once, reused) does the casting; a cloud's
        samples are read from ``view`` (module docstring).
    intrinsics : Intrinsics
        The photo's camera (at the photo's resolution).
    pose : Pose
        ``cam_from_world`` of the photo (the registration's).
    pixels : (N, 2) array
        Vertices (x = column, y = row).
    closed : bool
        A polygon's ring.
    params : ProjectionParams
    view : CloudView, optional
        On a cloud: the photo's render (:func:`~napari_imgreg.interpret.on_cloud.cloud_view`),
        shared by the features of one photo; rendered here when None.

    Returns
    -------
    ProjectedLine
        On a cloud ``face_id`` holds the index of the point hit.
    """
    p = check_drawing(pixels, intrinsics.width, intrinsics.height)
    if closed and len(p) > 2:
        p = np.vstack([p, p[:1]])
    inside = ((p[:, 0] >= -0.5) & (p[:, 0] <= intrinsics.width - 0.5)
              & (p[:, 1] >= -0.5) & (p[:, 1] <= intrinsics.height - 0.5))
    if len(p) >= 2 and not inside.all():
        # Off-image stretches have no rays: clip, and keep the pieces apart
        # (NaN samples between them become misses, which split the line).
        pieces = _clip_segments(p, intrinsics.width, intrinsics.height)
        gap = np.full((1, 2), np.nan)
        chunks = []
        for piece in pieces:
            chunks += [densify(piece, params.step_px), gap]
        samples = np.vstack(chunks[:-1]) if chunks else np.zeros((0, 2))
    else:
        samples = densify(p, params.step_px, False)
    if len(samples) == 0:
        empty = np.zeros((0, 3))
        return ProjectedLine(samples, empty, np.zeros(0), np.zeros(0, int), np.zeros(0, int), empty)
    if getattr(scene, "is_cloud", False):
        if view is None or not view.matches(intrinsics, pose):
            view = cloud_view(scene, intrinsics, pose, params.cloud)
        ch = cloud_hits(scene, view, samples)
        points, distance, face_id, normals = ch.points, ch.distance, ch.point_id, ch.normals
        hit = ch.hit
        cut = cloud_breaks(scene, ch, params.cloud, params.grazing_deg)
    else:
        finite = np.isfinite(samples).all(axis=1)
        origin, directions = pose.rays(intrinsics, np.where(finite[:, None], samples, 0.0))
        hits = scene.cast_rays(origin, directions)
        hits.distance[~finite] = np.inf
        hits.face_id[~finite] = -1
        points = scene.surface_points(hits)
        hit = hits.hit
        distance = hits.distance.astype(np.float64)
        face_id = hits.face_id.copy()
        normals = np.zeros((len(samples), 3))
        if hit.any():
            n = scene.face_array("normals")[hits.face_id[hit]].astype(np.float64)
            flip = np.einsum("ij,ij->i", n, directions[hit]) > 0
            n[flip] *= -1
            normals[hit] = n
        cut = _breaks(directions, distance, hit, params)
    # Runs of hit samples not interrupted by a break form the parts.
    starts = np.concatenate([[True], cut | ~hit[:-1]]) & hit
    run = np.cumsum(starts) - 1
    run = np.where(hit, run, -1)
    part = np.full(len(samples), -1)
    k = 0
    for r in range(int(run.max(initial=-1)) + 1):
        sel = run == r
        if sel.sum() >= params.min_part_points:
            part[sel] = k
            k += 1
    return ProjectedLine(samples, points, distance, face_id, part, normals)


def surface_patch(
    scene: Scene,
    intrinsics: Intrinsics,
    pose: Pose,
    ring_pixels: np.ndarray,
    max_points: int = 20_000,
    view: CloudView | None = None,
    params: ProjectionParams = ProjectionParams(),
) -> tuple[np.ndarray, np.ndarray]:
    """Visible surface inside an image polygon: one ray per pixel centre inside.

    On a cloud: the cloud's own points whose pixel is inside the polygon and
    that the photo's z-buffer sees
    (:func:`~napari_imgreg.interpret.on_cloud.cloud_patch`).

    Parameters
    ----------
    ring_pixels : (N, 2) array
        The polygon (x, y), open or closed.
    max_points : int
        Points returned at most (an even subsample); all faces are returned.
    view : CloudView, optional
        On a cloud: the photo's render (made here when None).
    params : ProjectionParams
        On a cloud: ``cloud.visible_spacings`` and ``grazing_deg``.

    Returns
    -------
    points : (K, 3) array
        Surface points, metres.
    faces : (F,) int array
        Unique indices of the faces seen inside the polygon (on a cloud: of
        the points, all of them).
    """
    from skimage.draw import polygon

    if getattr(scene, "is_cloud", False):
        if view is None or not view.matches(intrinsics, pose):
            view = cloud_view(scene, intrinsics, pose, params.cloud)
        return cloud_patch(scene, view, ring_pixels, params.cloud, params.grazing_deg,
                           max_points)
    ring = np.asarray(ring_pixels, np.float64).reshape(-1, 2)
    if len(ring) < 3:
        return np.zeros((0, 3)), np.zeros(0, int)
    rows, cols = polygon(ring[:, 1], ring[:, 0], shape=(intrinsics.height, intrinsics.width))
    if len(rows) == 0:
        return np.zeros((0, 3)), np.zeros(0, int)
    pix = np.stack([cols, rows], axis=1).astype(np.float64)
    origin, directions = pose.rays(intrinsics, pix)
    hits = scene.cast_rays(origin, directions)
    ok = hits.hit
    faces = np.unique(hits.face_id[ok])
    pts = scene.surface_points(hits)[ok]
    if len(pts) > max_points:
        pts = pts[np.linspace(0, len(pts) - 1, max_points).astype(int)]
    return pts, faces


def _along_ray_rms(range_m: np.ndarray, cos_incidence: np.ndarray, focal_px: float,
                   image_px: float, max_gain: float) -> float:
    """RMS (metres) of the slide along the ray by which an image error of
    ``image_px`` moves hits on an oblique surface: ``range × px / focal ×
    tan(incidence)``, the incidence capped where ``1/cos`` reaches ``max_gain``."""
    cos = np.clip(np.abs(cos_incidence), 1.0 / max_gain, 1.0)
    tan = np.sqrt(1.0 - cos**2) / cos
    return float(np.sqrt(np.mean((range_m * image_px / focal_px * tan) ** 2)))


# -------------------------------------------------------------- projection
def _three_point_xyz(scene: Scene, intrinsics: Intrinsics, pose: Pose,
                     item: Interpretation, view: CloudView | None) -> list | None:
    """The surface points under a 3-point plane's three clicks
    (``properties.three_point_px``, else its three vertices), (3, 3) as
    lists, metres, local frame; None when a click misses the surface (or
    there are not three clicks)."""
    px = None
    for candidate in (item.properties.get("three_point_px"), item.pixels):
        try:  # a hand-edited file's clicks may be anything
            px = np.asarray(candidate, np.float64)
        except (TypeError, ValueError):
            continue
        if px.shape == (3, 2) and np.isfinite(px).all() and np.all(
                (px >= -0.5) & (px <= np.array([intrinsics.width, intrinsics.height]) - 0.5)):
            break  # three clicks on the photo
    else:
        return None
    if getattr(scene, "is_cloud", False):
        ch = cloud_hits(scene, view, px)
        hit, points = ch.hit, ch.points
    else:
        origin, directions = pose.rays(intrinsics, px)
        hits = scene.cast_rays(origin, directions)
        hit, points = hits.hit, scene.surface_points(hits)
    if not np.all(hit):
        return None
    return np.round(np.asarray(points, np.float64), 4).tolist()


def project_interpretations(
    scene: Scene,
    intrinsics: Intrinsics,
    pose: Pose,
    interpretations: Sequence[Interpretation],
    source: str = "",
    params: ProjectionParams = ProjectionParams(),
    id_prefix: str | None = None,
    pose_uncertainty: PoseUncertainty | None = None,
    uncertainty: UncertaintyParams = DEFAULT_UNCERTAINTY,
) -> list[Feature3D]:
    """Project the features drawn on one registered photo onto the surface.

    Parameters
    ----------
    scene : Scene
    intrinsics : Intrinsics
    pose : Pose
        The photo's registered ``cam_from_world``.
    interpretations : list of Interpretation
    source : str
        The photo's name, recorded as ``properties.source``.
    params : ProjectionParams
    id_prefix : str, optional
        Feature ids are ``"<prefix>:<n>"`` (default: the source's stem), or
        the 2D feature's ``properties.id`` when it has one (also kept as
        ``properties.contact``, which joins the traces of one contact drawn
        on several photos).
    pose_uncertainty : PoseUncertainty, optional
        The pose's expected error (RESULT.json ``uncertainty``); default
        :meth:`PoseUncertainty.from_result` of an empty result (1 px).
    uncertainty : UncertaintyParams
        The drawing's pixel noise and the mesh-error fraction.

    Returns
    -------
    list of Feature3D
        One per interpretation, in order (a feature wholly off the surface
        has no parts). Each carries ``properties.camera_position``
        (the camera centre, metres), ``properties.sigma_m`` (median expected
        3D error of its points, metres, 1σ, pose position included) and
        ``properties.uncertainty`` (the error model ``measure`` propagates).

    Raises
    ------
    InputError
        A drawn vertex is not finite or lies far outside the photo.
    """
    if scene._engine is None:
        scene.build_engine()
    prefix = id_prefix if id_prefix is not None else (source.rsplit(".", 1)[0] or "f")
    for k, item in enumerate(interpretations):  # refuse bad vertices before any ray
        check_drawing(item.pixels, intrinsics.width, intrinsics.height, f"feature {k + 1}")
    center = pose.center
    if pose_uncertainty is None:
        pose_uncertainty = PoseUncertainty.from_result({"pose": {}, "status": "registered",
                                                       "metrics": {"reprojection_error_px": 1.0}},
                                                      intrinsics.fx)
    focal = float((intrinsics.fx + intrinsics.fy) / 2.0)
    image_px = math.hypot(uncertainty.drawing_px, pose_uncertainty.reprojection_px)
    # A cloud: one render of the photo's camera serves all its features.
    view = (cloud_view(scene, intrinsics, pose, params.cloud)
            if getattr(scene, "is_cloud", False) and len(interpretations) else None)
    out = []
    for k, item in enumerate(interpretations):
        closed = item.geometry == "Polygon"
        line = project_polyline(scene, intrinsics, pose, item.pixels, closed, params, view)
        props = dict(item.properties)
        props["label"] = item.label
        props.setdefault("color", item.color)
        if source:
            props["source"] = source
        # Only an explicit contact joins traces of several photos: ids are often
        # a per-file count (line1, line2, ...), and the same id on two photos
        # would measure unrelated contacts together.
        user_id = props.pop("id", None)
        fid = str(user_id or f"{prefix}:{k + 1}")
        props["camera_position"] = [round(float(v), 4) for v in center]
        if props.get("measure") == "three_point":
            props["three_point_xyz"] = _three_point_xyz(scene, intrinsics, pose, item, view)
        on_pts = line.part >= 0
        if on_pts.any():
            hits = line.points[on_pts]
            rng = np.linalg.norm(hits - center, axis=1)
            rays = (hits - center) / np.maximum(rng[:, None], 1e-12)
            cos_inc = np.abs(np.einsum("ij,ij->i", rays, line.normals[on_pts]))
            if getattr(scene, "is_cloud", False):  # the cloud's point spacing there
                edge_m = float(np.median(scene.spacing[line.face_id[on_pts]]))
            else:
                tri = scene.vertices[scene.faces[line.face_id[on_pts]]]
                edges = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2)
                edge_m = float(np.median(edges))
            mesh_m = uncertainty.mesh_error_fraction * edge_m
            rel = point_sigma(rng, cos_inc, focal, image_px, mesh_m, uncertainty.max_obliquity_gain)
            relative = float(np.median(rel))
            model = ErrorModel(
                camera_position=center, relative_m=relative, mesh_m=mesh_m, mesh_edge_m=edge_m,
                n_vertices=len(item.pixels), rotation_deg=pose_uncertainty.rotation_deg,
                position_m=pose_uncertainty.position_m,
                view_m=float(math.hypot(np.median(rng) * image_px / focal, mesh_m)),
                along_ray_m=_along_ray_rms(rng, cos_inc, focal, image_px,
                                           uncertainty.max_obliquity_gain),
                extra={"drawing_px": uncertainty.drawing_px,
                       "reprojection_px": round(pose_uncertainty.reprojection_px, 4),
                       "pose_uncertainty": pose_uncertainty.source},
            )
            props["sigma_m"] = round(math.hypot(relative, pose_uncertainty.position_m), 5)
            props["uncertainty"] = model.to_properties()
        parts = line.parts
        on = line.part >= 0
        normal = None
        if on.any():
            nsum = line.normals[on].sum(axis=0)
            if np.linalg.norm(nsum) > 0:
                normal = nsum / np.linalg.norm(nsum)
        feature = Feature3D(
            id=fid,
            kind="facet" if closed else "trace",
            parts=parts,
            properties=props,
            surface_normal=normal,
            samples=len(line.pixels),
            missed=int((~on).sum()),
        )
        if closed:
            # The ring is whole when every sample is in the one part (the
            # closing sample repeats the first, so the part closes on itself).
            feature.ring_complete = len(parts) == 1 and bool(on.all())
            pts, faces = surface_patch(
                scene, intrinsics, pose, item.pixels, params.patch_max_points, view, params
            )
            feature.patch_points, feature.patch_faces = pts, faces
        out.append(feature)
    return out


def merge_interpretations(*sets: Iterable[Feature3D]) -> list[Feature3D]:
    """One interpretation set from several photos' projections.

    Features keep their ``properties.source``; an id already used by an
    earlier feature is made unique by prefixing the source.
    """
    seen: set[str] = set()
    out = []
    for features in sets:
        for f in features:
            fid = f.id
            if fid in seen:
                fid = f"{f.source or 'photo'}:{fid}"
                n = 2
                while fid in seen:
                    fid = f"{f.source or 'photo'}:{f.id}#{n}"
                    n += 1
                f = replace(f, id=fid)
            seen.add(fid)
            out.append(f)
    return out


def measure_features(
    features: Sequence[Feature3D],
    thresholds: FitThresholds = DEFAULT_THRESHOLDS,
    uncertainty: UncertaintyParams = DEFAULT_UNCERTAINTY,
    combine: bool = True,
) -> list[Measurement]:
    """Contract §6 measurements of projected features (those with points).

    Parameters
    ----------
    features : list of Feature3D
    thresholds : FitThresholds
    uncertainty : UncertaintyParams
        Monte Carlo settings for the σ columns.
    combine : bool
        Traces of one contact (same ``properties.contact`` and label) drawn on
        two or more photos also get one combined row, id ``contact:<name>``:
        the plane their points define together (reported where they leave
        every camera's viewing plane), even when each alone is too straight.

    Returns
    -------
    list of Measurement
        One per feature, in order (contract §6: a feature that missed the
        surface gets its row too, empty but for its note), then the
        combined rows.
    """
    measured = list(features)
    out = [f.measure(thresholds, uncertainty) for f in measured]
    if not combine:
        return out
    groups: dict[tuple[str, str], list[Feature3D]] = {}
    for f in measured:
        if f.kind == "trace" and f.contact and f.n_points:
            groups.setdefault((f.label, f.contact), []).append(f)
    for (label, contact), members in groups.items():
        if len({f.source for f in members}) < 2:
            continue
        models = [f.error_model for f in members]
        m = measure_traces(
            [f.parts for f in members], f"contact:{contact}", label,
            [f.source for f in members], None, thresholds,
            models if all(md is not None for md in models) else None, uncertainty,
        )
        m.color = members[0].properties.get("color")
        out.append(m)
    return out
