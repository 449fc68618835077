"""How well a drawing defines a plane, and the uncertainty of every measurement.

Two questions are answered here, from the 3D points of a projected feature,
the centre of the camera it was drawn from and the expected 3D error of its
points (``properties.camera_position``, ``properties.sigma_m`` and
``properties.uncertainty`` of the projected GeoJSON):

1. **Does the drawing determine a plane?** Every point of a line drawn on a
   photo lies on a ray through the camera centre ``C``. A line drawn straight
   on the photo therefore lies in one plane through ``C`` — the *viewing
   plane* — whatever the rock does: its best-fit "plane" is the viewing plane.
   A trace defines a plane only where its points leave the best plane through
   ``C`` by clearly more than their own expected error
   (:func:`viewing_plane`, test ``spread ≥ min_view_spread × σ``), and where
   the fitted plane does not contain the viewing rays (its angle to them at
   least ``min_ray_angle_deg``). Traces of one contact drawn on several
   photos are judged together: their points must leave the best plane through
   *each* camera.

2. **How wrong is each number?** A Monte Carlo over the error sources
   (:func:`monte_carlo`): the registered pose (a rigid rotation about the
   camera centre and a shift, from RESULT.json's ``uncertainty``), the hand's
   noise at the drawn vertices (default ±1.5 px) and the pose's reprojection
   error, both turned into metres at each point's range and obliquity, and
   the model's resolution (a fraction of its edge length, correlated over one
   edge). Each sample moves the points, refits line and plane, and the
   spread of the refitted angles about the nominal ones is the σ reported.
   The sample count (default 200) was chosen from a measured trade-off
   (``docs/interpretation.md``): the σ estimate's own relative error is
   about ``1/sqrt(2 N)``, 5 % at 200 samples, for ~15 ms per trace.

All lengths in metres (model frame), angles in degrees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

__all__ = [
    "UncertaintyParams",
    "PoseUncertainty",
    "ErrorModel",
    "DEFAULT_UNCERTAINTY",
    "viewing_plane",
    "view_geometry",
    "point_sigma",
    "monte_carlo",
    "angle_sigmas",
]


@dataclass(frozen=True)
class UncertaintyParams:
    """Settings of the error propagation.

    Attributes
    ----------
    drawing_px : float
        Standard deviation of the hand's placement of each drawn vertex,
        pixels of the photo (default 1.5; range 0–20).
    samples : int
        Monte Carlo samples per feature (default 200; range 20–5000).
    seed : int
        Seed of the Monte Carlo (results are reproducible).
    mesh_error_fraction : float
        The model's own error, as a fraction of its median edge length
        (default 0.1; range 0–1): a mesh that approximates the rock with
        triangles of edge ``h`` is taken to be off by ``0.1 h`` (1σ),
        correlated over one edge.
    max_obliquity_gain : float
        Cap of the ``1 / cos(incidence)`` factor by which an image error
        grows where the ray grazes the surface (default 4; range 1–20).
    """

    drawing_px: float = 1.5
    samples: int = 200
    seed: int = 0
    mesh_error_fraction: float = 0.1
    max_obliquity_gain: float = 4.0

    def __post_init__(self) -> None:
        checks = (
            ("drawing_px", self.drawing_px, 0.0, 20.0),
            ("samples", self.samples, 20, 5000),
            ("mesh_error_fraction", self.mesh_error_fraction, 0.0, 1.0),
            ("max_obliquity_gain", self.max_obliquity_gain, 1.0, 20.0),
        )
        for name, value, lo, hi in checks:
            if not (isinstance(value, (int, float)) and math.isfinite(value) and lo <= value <= hi):
                raise ValueError(f"{name} must be in [{lo}, {hi}], not {value!r}")


DEFAULT_UNCERTAINTY = UncertaintyParams()


@dataclass(frozen=True)
class PoseUncertainty:
    """Expected error of a registered pose (RESULT.json ``uncertainty``).

    Attributes
    ----------
    reprojection_px : float
        Expected image displacement of model points, pixels of the photo.
    position_m : float
        Expected camera-centre error, metres.
    rotation_deg : float
        Expected rotation error, degrees.
    source : {"result", "default"}
        Read from the result, or derived from its reprojection error.
    """

    reprojection_px: float
    position_m: float
    rotation_deg: float
    source: str = "default"

    @classmethod
    def from_estimate(cls, estimate: Any, status: str, metrics: dict | None,
                      focal_px: float) -> PoseUncertainty:
        """As :meth:`from_result`, of a registration held in memory: its
        ``uncertainty`` (an object with ``reprojection_px``, ``position_m``,
        ``rotation_deg``; None when not estimated), ``status`` and ``metrics``."""
        data: dict[str, Any] = {"pose": {}, "status": status, "metrics": metrics or {}}
        if estimate is not None:
            data["uncertainty"] = {k: getattr(estimate, k)
                                   for k in ("reprojection_px", "position_m", "rotation_deg")}
        return cls.from_result(data, focal_px)

    @classmethod
    def from_result(cls, data: Any, focal_px: float, range_m: float | None = None) -> PoseUncertainty:
        """The result's ``uncertainty`` block, or a documented default.

        Without the block (results written before it existed, or a sensor
        record), the default is derived from the result's mean reprojection
        error ``e`` (``metrics.reprojection_error_px``, 2 px when absent):
        ``reprojection_px = max(e, 1)``, ``rotation_deg`` = that many pixels
        seen from the camera (``reprojection_px / focal_px`` radians) and
        ``position_m`` = the same angle at the scene's range (100 m when not
        known). A sensor record (no registered pose) gets GNSS/compass-sized
        errors: 5 px is not enough, so 50 px, 5 m and 3°; so does a failed
        registration, whose pose is its prior's (``source``
        ``"default (not registered)"``).
        """
        if isinstance(data, dict) and data.get("status") == "failed":
            # A failed result carries its prior's pose (contract §4).
            return cls(50.0, 5.0, 3.0, source="default (not registered)")
        block = data.get("uncertainty") if isinstance(data, dict) else None
        if isinstance(block, dict):
            try:
                values = [float(block[k]) for k in ("reprojection_px", "position_m", "rotation_deg")]
            except (KeyError, TypeError, ValueError):
                values = []
            if values and all(math.isfinite(v) and v >= 0 for v in values):
                return cls(*values, source="result")
        if not isinstance(data, dict) or "pose" not in data or data.get("status") not in (
                "registered", "failed"):
            return cls(50.0, 5.0, 3.0, source="default (sensor prior)")

        metrics = data.get("metrics") if isinstance(data.get("metrics"), dict) else {}
        e = metrics.get("reprojection_error_px")
        e = float(e) if isinstance(e, (int, float)) and math.isfinite(e) else 2.0
        rep = max(e, 1.0)
        angle = rep / max(float(focal_px), 1.0)
        return cls(rep, angle * (range_m or 100.0), math.degrees(angle), source="default")


@dataclass
class ErrorModel:
    """The expected error of one projected feature's points.

    Attributes
    ----------
    camera_position : (3,) array
        Centre of the camera the feature was drawn from, metres.
    relative_m : float
        Expected error of a point relative to the others (drawing, pose
        reprojection and mesh, at the feature's median range), metres, 1σ.
    mesh_m : float
        Of which the model's resolution, metres (correlated over
        ``mesh_edge_m``).
    mesh_edge_m : float
        Median edge length of the faces under the feature, metres.
    n_vertices : int
        Drawn vertices (the hand's noise is independent at each of them).
    rotation_deg, position_m : float
        The pose's rigid error (1σ).
    view_m : float
        Expected distance by which an error moves a point off its viewing
        plane: the image error's footprint at the median range (``range ×
        px / focal``, no obliquity gain: sliding along the surface stays
        near the plane) with the mesh error in quadrature, metres. NaN:
        use ``relative_m``.
    along_ray_m : float
        RMS over the points of the slide along the ray an image error causes
        where the surface is oblique (``range × px / focal × tan(incidence)``,
        the gain capped), metres: the depth error. NaN (files written before
        it existed): ``sqrt(relative_m² − view_m²)``, from the median point.
    """

    camera_position: np.ndarray
    relative_m: float
    mesh_m: float = 0.0
    mesh_edge_m: float = 0.0
    n_vertices: int = 2
    rotation_deg: float = 0.0
    position_m: float = 0.0
    view_m: float = math.nan
    along_ray_m: float = math.nan
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def view_sigma_m(self) -> float:
        """:attr:`view_m`, or :attr:`relative_m` when unknown."""
        return self.view_m if math.isfinite(self.view_m) else self.relative_m

    def to_properties(self) -> dict[str, Any]:
        """The ``properties.uncertainty`` block of the projected GeoJSON."""
        out = {
            "relative_m": round(float(self.relative_m), 5),
            "mesh_m": round(float(self.mesh_m), 5),
            "mesh_edge_m": round(float(self.mesh_edge_m), 4),
            "n_vertices": int(self.n_vertices),
            "rotation_deg": round(float(self.rotation_deg), 6),
            "position_m": round(float(self.position_m), 5),
        }
        if math.isfinite(self.view_m):
            out["view_m"] = round(float(self.view_m), 5)
        if math.isfinite(self.along_ray_m):
            out["along_ray_m"] = round(float(self.along_ray_m), 5)
        out.update(self.extra)
        return out

    @classmethod
    def from_properties(cls, props: dict[str, Any]) -> ErrorModel | None:
        """Read back :meth:`to_properties` (None without ``camera_position``).

        A file that has ``camera_position`` and ``sigma_m`` but no
        ``uncertainty`` block (written by another tool) is taken as
        ``sigma_m`` of independent error at two control points.
        """
        cam = props.get("camera_position")
        try:
            c = np.asarray(cam, np.float64).reshape(3)
        except (TypeError, ValueError):
            return None
        if not np.isfinite(c).all():
            return None
        block = props.get("uncertainty") if isinstance(props.get("uncertainty"), dict) else {}

        def num(value: Any, default: float) -> float:
            try:
                v = float(value)
            except (TypeError, ValueError):
                return default
            return v if math.isfinite(v) and v >= 0 else default

        sigma = num(props.get("sigma_m"), math.nan)
        rel = num(block.get("relative_m"), sigma)
        if not math.isfinite(rel):
            return None
        return cls(
            camera_position=c, relative_m=rel, mesh_m=num(block.get("mesh_m"), 0.0),
            mesh_edge_m=num(block.get("mesh_edge_m"), 0.0),
            n_vertices=max(2, int(num(block.get("n_vertices"), 2))),
            rotation_deg=num(block.get("rotation_deg"), 0.0),
            position_m=num(block.get("position_m"), 0.0),
            view_m=num(block.get("view_m"), math.nan),
            along_ray_m=num(block.get("along_ray_m"), math.nan),
        )


# ------------------------------------------------------------------ geometry
def viewing_plane(points: np.ndarray, camera: np.ndarray) -> tuple[np.ndarray, float]:
    """The plane through the camera centre closest to the points.

    Parameters
    ----------
    points : (N, 3) array
        Metres.
    camera : (3,) array
        Camera centre, metres.

    Returns
    -------
    normal : (3,) array
        Unit normal of the best plane through ``camera`` (least squares).
    spread_m : float
        RMS distance of the points to it, metres: 0 for a line drawn straight
        on the photo and projected without error.

    Examples
    --------
    >>> pts = np.array([[0, 10, 0], [5, 10, 5], [-4, 12, -4.0]])  # in the plane z = x
    >>> n, s = viewing_plane(pts, np.zeros(3))
    >>> s < 1e-9
    True
    """
    v = np.asarray(points, np.float64).reshape(-1, 3) - np.asarray(camera, np.float64)
    _, s, vt = np.linalg.svd(v, full_matrices=False)
    normal = vt[-1] if len(vt) == 3 else np.cross(vt[0], vt[-1])
    spread = float(np.sqrt(np.mean((v @ normal) ** 2))) if len(v) else 0.0
    return normal, spread


def view_geometry(
    points_per_view: Sequence[np.ndarray], cameras: Sequence[np.ndarray], plane_normal: np.ndarray
) -> tuple[float, float]:
    """How far a plane and its points are from every view's viewing plane.

    Parameters
    ----------
    points_per_view : list of (Ni, 3) arrays
        The points, grouped by the photo they were drawn on.
    cameras : list of (3,) arrays
        The photos' camera centres.
    plane_normal : (3,) array
        Normal of the plane fitted to all points.

    Returns
    -------
    spread_m : float
        Over the cameras, the smallest RMS distance of *all* points to the
        best plane through that camera (see :func:`viewing_plane`).
    ray_angle_deg : float
        Over the views, the smallest angle between the fitted plane and the
        rays to that view's points (mean of ``asin |n · ray|``).
    """
    n = np.asarray(plane_normal, np.float64)
    n = n / np.linalg.norm(n)
    allpts = np.concatenate([np.asarray(p, np.float64).reshape(-1, 3) for p in points_per_view])
    spread = math.inf
    angle = math.inf
    for pts, cam in zip(points_per_view, cameras):
        spread = min(spread, viewing_plane(allpts, cam)[1])
        rays = np.asarray(pts, np.float64) - np.asarray(cam, np.float64)
        rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
        angle = min(angle, math.degrees(float(np.mean(np.arcsin(np.clip(np.abs(rays @ n), 0, 1))))))
    return spread, angle


def point_sigma(
    range_m: np.ndarray,
    cos_incidence: np.ndarray,
    focal_px: float,
    image_px: float,
    mesh_m: float,
    max_gain: float = 4.0,
) -> np.ndarray:
    """Expected 3D error (1σ) of projected points from an image error.

    An image error of ``image_px`` pixels moves a ray by ``image_px /
    focal_px`` radians: ``range × image_px / focal_px`` metres across the
    ray, stretched by ``1 / cos(incidence)`` (capped at ``max_gain``) as the
    hit slides along an oblique surface; the mesh's own error adds in
    quadrature.

    Parameters
    ----------
    range_m, cos_incidence : (N,) arrays
        Ray length to each hit, metres; |cos| of the angle between the ray
        and the surface normal.
    focal_px : float
    image_px : float
    mesh_m : float

    Returns
    -------
    (N,) array, metres.

    Examples
    --------
    >>> float(point_sigma(np.array([100.0]), np.array([1.0]), 1000.0, 1.5, 0.0)[0])
    0.15
    """
    gain = 1.0 / np.maximum(np.abs(cos_incidence), 1.0 / max_gain)
    lateral = np.asarray(range_m, np.float64) * image_px / float(focal_px) * gain
    return np.sqrt(lateral**2 + mesh_m**2)


# --------------------------------------------------------------- Monte Carlo
def _rotation(rng: np.random.Generator, sigma_deg: float) -> np.ndarray:
    """A random rotation matrix whose angle has RMS ``sigma_deg``."""
    w = rng.normal(0.0, math.radians(sigma_deg) / math.sqrt(3.0), 3)
    theta = float(np.linalg.norm(w))
    if theta < 1e-15:
        return np.eye(3)
    k = w / theta
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(theta) * K + (1 - math.cos(theta)) * K @ K


def _interpolation_matrix(arc: np.ndarray, n_control: int) -> np.ndarray:
    """(N, C) weights that interpolate ``C`` control values, spread evenly
    along the arc length, linearly at the N points."""
    n = len(arc)
    n_control = int(max(2, min(n_control, max(n, 2))))
    span = arc[-1] - arc[0] if n else 0.0
    t = (arc - arc[0]) / span * (n_control - 1) if span > 0 else np.linspace(0, n_control - 1, n)
    k = np.clip(np.floor(t).astype(int), 0, n_control - 2)
    f = t - k
    W = np.zeros((n, n_control))
    W[np.arange(n), k] = 1.0 - f
    W[np.arange(n), k + 1] = f
    return W


def _arc(points: np.ndarray) -> np.ndarray:
    if len(points) < 2:
        return np.zeros(len(points))
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def _image_error(
    rng: np.random.Generator,
    K: int,
    pts: np.ndarray,
    arc: np.ndarray,
    W: np.ndarray,
    camera: np.ndarray,
    model: ErrorModel,
    normal: np.ndarray | None,
    max_gain: float,
) -> np.ndarray:
    """(K, C, 3) 3D errors at the C control points from an image error there.

    Across the ray: isotropic, per axis the image error's footprint (the
    model's ``view_m`` without the mesh part, which :func:`monte_carlo`
    adds separately). Along it: the slide that keeps the point on the
    surface (see :func:`monte_carlo`).
    """
    C = W.shape[1]
    # The control points' positions and rays (nearest point along the arc).
    t_ctrl = np.linspace(arc[0], arc[-1], C) if arc[-1] > arc[0] else np.full(C, arc[0])
    idx = np.clip(np.searchsorted(arc, t_ctrl), 0, len(pts) - 1)
    rays = pts[idx] - camera
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
    helper = np.where(np.abs(rays[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    e1 = np.cross(rays, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(rays, e1)
    across = math.sqrt(max(model.view_sigma_m**2 - model.mesh_m**2, 0.0))
    a = rng.normal(0.0, across, (K, C, 2))
    delta = a[..., :1] * e1 + a[..., 1:] * e2
    # The slide's RMS from the points' own obliquity: their mean square (the
    # fit feels the steep stretches' large slides), else from the median point.
    along = (model.along_ray_m if math.isfinite(model.along_ray_m)
             else math.sqrt(max(model.relative_m**2 - model.view_sigma_m**2, 0.0)))
    slide = np.zeros((K, C))
    n = None if normal is None else np.asarray(normal, np.float64)
    if n is not None and np.isfinite(n).all() and np.linalg.norm(n) > 0:
        # The part the mean surface normal explains is correlated with the
        # error across the ray; the rest (the local relief's own tilt) is not.
        n = n / np.linalg.norm(n)
        cos = rays @ n
        cos = np.where(np.abs(cos) < 1.0 / max_gain, np.copysign(1.0 / max_gain, cos), cos)
        slide = -(delta @ n) / cos
        explained = across**2 * (1.0 - np.clip(rays @ n, -1, 1) ** 2) / cos**2
        rest = np.sqrt(np.clip(along**2 - explained, 0.0, None))
    else:
        rest = np.full(C, along)
    slide = slide + rng.normal(0.0, 1.0, (K, C)) * rest
    return delta + slide[..., None] * rays


def monte_carlo(
    parts_per_view: Sequence[Sequence[np.ndarray]],
    models: Sequence[ErrorModel],
    params: UncertaintyParams = DEFAULT_UNCERTAINTY,
    bootstrap: bool = False,
    surface_normals: Sequence[np.ndarray | None] | None = None,
) -> list[list[np.ndarray]]:
    """Perturbed copies of a feature's points, one list of views per sample.

    Per sample and view: a rigid rotation about the camera centre (RMS angle
    ``rotation_deg``) and shift (RMS ``position_m``); the drawing's and
    reprojection error at ``n_vertices`` control points along the trace,
    independent between them and linear in between (a straight stroke
    between two vertices stays straight); the mesh's error (RMS ``mesh_m``),
    independent every ``mesh_edge_m``.

    The image error is modelled as it arises: at each control point the ray
    turns by an isotropic image error (``view_m`` across the ray per axis:
    ``range × px / focal``, so the error *off the viewing plane* is exactly
    the hand's), and the hit slides along the ray to stay on the surface
    (``t = −(δ·n) / (r·n)``, capped at ``max_obliquity_gain``, with ``n``
    the feature's mean surface normal). Without a surface normal the slide
    is drawn independently with the RMS the obliquity adds,
    ``sqrt(relative_m² − view_m²)``. (Issue 14: an isotropic 3D error of
    RMS ``relative_m`` put only ``1/√3`` of the hand's error off the
    viewing plane, and the dips of nearly-viewing-plane traces came out
    overconfident.)

    Parameters
    ----------
    parts_per_view : list (views) of lists of (Mi, 3) arrays
        The feature's parts, grouped by the photo each was drawn on.
    models : list of ErrorModel
        One per view.
    params : UncertaintyParams
    bootstrap : bool
        Facets: resample the points with replacement (the fit's own scatter)
        plus independent mesh noise, instead of the drawn-vertex noise.
    surface_normals : list of (3,) arrays or None, optional
        One per view: the mean surface normal along the feature there.

    Returns
    -------
    list (``params.samples``) of lists (views) of (Ni, 3) arrays
        Each view's parts concatenated, perturbed.
    """
    rng = np.random.default_rng(params.seed)
    K = params.samples
    per_view = []
    normals = list(surface_normals) if surface_normals is not None else [None] * len(models)
    for parts, model, normal in zip(parts_per_view, models, normals):
        parts = [np.asarray(p, np.float64).reshape(-1, 3) for p in parts if len(p)]
        pts = np.concatenate(parts) if parts else np.zeros((0, 3))
        c = np.asarray(model.camera_position, np.float64)
        Rs = np.stack([_rotation(rng, model.rotation_deg) for _ in range(K)])
        shift = rng.normal(0.0, model.position_m / math.sqrt(3.0), (K, 1, 3))
        q = (pts - c) @ np.transpose(Rs, (0, 2, 1)) + c + shift
        if bootstrap:
            idx = rng.integers(0, len(pts), (K, len(pts)))
            q = np.take_along_axis(q, idx[:, :, None], axis=1)
            q += rng.normal(0.0, model.mesh_m / math.sqrt(3.0), q.shape)
        elif len(pts):
            # Parts are laid end to end along one arc (the gaps carry no noise knots).
            offsets = np.cumsum([0.0] + [float(_arc(p)[-1]) if len(p) > 1 else 0.0 for p in parts])
            arc = np.concatenate([_arc(p) + offsets[k] for k, p in enumerate(parts)])
            W = _interpolation_matrix(arc, model.n_vertices)
            q += W @ _image_error(rng, K, pts, arc, W, c, model, normal,
                                  params.max_obliquity_gain)
            if model.mesh_m > 0:
                n_mesh = (int(math.ceil(offsets[-1] / model.mesh_edge_m)) + 1
                          if model.mesh_edge_m > 0 else len(pts))
                Wm = _interpolation_matrix(arc, n_mesh)
                q += Wm @ rng.normal(0.0, model.mesh_m / math.sqrt(3.0), (K, Wm.shape[1], 3))
        per_view.append(q)
    return [[v[k] for v in per_view] for k in range(K)]


def three_point_samples(
    points: np.ndarray,
    model: ErrorModel,
    params: UncertaintyParams = DEFAULT_UNCERTAINTY,
    surface_normal: np.ndarray | None = None,
) -> list[np.ndarray]:
    """Perturbed copies of a 3-point plane's three surface points.

    As :func:`monte_carlo` does for a trace, with the clicks as the control
    points: per sample one rigid rotation about the camera centre and one
    shift (the pose's error, shared by the three points), and at each click
    its own image error (independent between the clicks: three separate
    clicks, not one stroke) turned into a 3D error across the ray plus the
    slide along it that keeps the point on the surface; the mesh's error,
    independent per point.

    Parameters
    ----------
    points : (3, 3) array
        The surface points under the clicks, metres.
    model : ErrorModel
        The photo's (camera centre, pose error, pixel noise at the range).
    params : UncertaintyParams
    surface_normal : (3,) array, optional
        The surface's mean normal there (else the slide is drawn independently).

    Returns
    -------
    list (``params.samples``) of (3, 3) arrays
    """
    rng = np.random.default_rng(params.seed)
    K = params.samples
    pts = np.asarray(points, np.float64).reshape(3, 3)
    c = np.asarray(model.camera_position, np.float64)
    Rs = np.stack([_rotation(rng, model.rotation_deg) for _ in range(K)])
    shift = rng.normal(0.0, model.position_m / math.sqrt(3.0), (K, 1, 3))
    q = (pts - c) @ np.transpose(Rs, (0, 2, 1)) + c + shift
    q += _image_error(rng, K, pts, np.arange(3.0), np.eye(3), c, model, surface_normal,
                      params.max_obliquity_gain)
    if model.mesh_m > 0:
        q += rng.normal(0.0, model.mesh_m / math.sqrt(3.0), q.shape)
    return list(q)

def _wrapped(diff: np.ndarray, period: float) -> np.ndarray:
    return (np.asarray(diff) + period / 2) % period - period / 2


def angle_sigmas(
    nominal: tuple[float, float], samples: np.ndarray, axial_direction: bool = False
) -> tuple[float, float]:
    """RMS deviation of sampled (inclination, azimuth) pairs from the nominal.

    Parameters
    ----------
    nominal : (inclination_deg, azimuth_deg)
        Dip and dip direction, or plunge and trend.
    samples : (K, 2) array
        The Monte Carlo's values (rows with NaN are dropped).
    axial_direction : bool
        The azimuth is only defined modulo 180° (a horizontal line's trend).

    Returns
    -------
    inclination_sigma_deg, azimuth_sigma_deg : float
        The azimuth's σ is capped at 180° (undefined direction: say so by a
        large number rather than pretend).

    Examples
    --------
    >>> s = np.array([[10.0, 359.0], [12.0, 1.0]])
    >>> angle_sigmas((11.0, 0.0), s)
    (1.0, 1.0)
    """
    s = np.asarray(samples, np.float64).reshape(-1, 2)
    s = s[np.isfinite(s).all(axis=1)]
    if len(s) == 0:
        return math.nan, math.nan
    d_inc = s[:, 0] - nominal[0]
    d_az = _wrapped(s[:, 1] - nominal[1], 360.0)
    if axial_direction:
        d_az = _wrapped(d_az, 180.0)
    return (float(np.sqrt(np.mean(d_inc**2))),
            float(min(180.0, np.sqrt(np.mean(d_az**2)))))
