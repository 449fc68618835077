"""Traces that snap to contacts: a least-cost path on the photo between clicks.

The user clicks the start and the end of a contact (and optionally waypoints
where it is ambiguous); between consecutive clicks the trace follows the path
of least accumulated cost through a cost image computed from the photo, as
qCompass does in CloudCompare (Thiele et al. 2017). The path is found by
scikit-image's :func:`skimage.graph.route_through_array` (Dijkstra with
geometric, 8-connected steps) in a window around the clicks, then thinned to
the vertices a drawn line would have and refined to sub-pixel positions on
the edge it follows.

Cost functions (``SnapParams.cost``), as in qCompass:

``"gradient"``
    Low on strong edges: bed boundaries, fault traces seen as a change of
    tone (the default). With ``oriented`` (default) only the edge running
    along the clicked segment with the polarity found under the clicks
    (darker on the same side) counts, so the trace neither jumps to the other
    side of a thin bed nor follows cross-cutting joints. On a colour photo
    the edge is also *trained* on the clicked contact (below).
``"colour_edge"``
    Low on any colour boundary (the largest gradient over the colour
    channels), unoriented.
``"darkness"``
    Low on dark pixels: open fractures, shadowed partings, coal seams.
``"brightness"``
    Low on bright pixels: veins, light-coloured partings.
``"colour"``
    Low where the colour is like that under the clicks: follow a thin band of
    one colour (a qCompass "RGB" cost).

Trained colour step (oriented ``"gradient"``, ``SnapParams.colour_weight``),
after the on-the-fly training of intelligent scissors (Mortensen & Barrett
1998): beds differ in colour as well as in tone, and the light changes
tone far more than colour. The step of the log chromaticity (``log R/G``, ``log B/G``)
across the clicked segment, read where the polarity is read, is the
contact's signature; pixels where the chromaticity steps the same way are
made cheaper, in proportion to that step. A shadow or a lit ledge beside the
contact (every channel scaled alike), mottling inside a bed (one colour on
both sides) and the other side of a thin bed (another colour pair, the
opposite step) do not carry it, so the trace keeps to the clicked contact
where its tone fades. The colour chooses the route; the luminance edge, a
JPEG's sharper channel, then places the trace on it (within one pixel, to
sub-pixel). Where the two beds are of one colour (or the photo is grey)
there is nothing to train on and the trace is the luminance's alone. On the
snapping benchmark (``benchmarks/bench_snap.py``) the share of traces that
follow another edge fell from 15 to 10 % (small scene) and from 21 to 13 %
(large); a penalty on the colours *beside* the edge (each side's colour at
±1.5–4 px against those under the clicks, as intelligent scissors compare
profiles) made it worse (16–23 %): a bed's colour varies along it more than
its step does.

Following the model (``snap_trace(..., reference=...)``,
``SnapParams.model_reach_px``): a registered pose is off by a fraction of a
pixel, so a line exactly on the photo's contact is projected that far beside
the model's. Given the model's own colours rendered from that pose
(:func:`model_reference`), which show its contact displaced by the same
error, the finished trace is moved onto that contact (within 1.5 px, where
the render steps the way the photo does) and is projected onto the contact
as the model has it. On the snapping benchmark it takes the snapped traces
from 1.62× to 1.02× (small scene) and from 1.22× to 0.56× (large) the
perfect drawing's 3D error, with the registered poses.

Coordinates are ``[col, row]`` pixels with pixel centres at integers (the
interpretation files' convention).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

__all__ = ["COSTS", "SnapParams", "cost_image", "model_reference", "snap_path", "snap_trace"]

#: The selectable cost functions (see the module docstring).
COSTS = ("gradient", "colour_edge", "darkness", "brightness", "colour")


@dataclass(frozen=True)
class SnapParams:
    """Settings of the least-cost trace.

    Attributes
    ----------
    cost : {"gradient", "darkness", "brightness", "colour"}
        What the trace follows (module docstring). Default ``"gradient"``.
    smoothing_px : float
        Gaussian σ (pixels, 0–10) applied before the cost, so texture and
        JPEG noise do not pull the trace. Default 0.7.
    contrast : float
        Exponent (1–10) applied to the normalised cost: higher makes the trace
        keep to the strongest feature even at the price of a detour. Default 3.
    floor : float
        Smallest cost of a pixel (0.001–0.5), relative to the largest; keeps
        a short path through a weak stretch cheaper than a long detour.
        Default 0.02.
    margin_px : int
        The search window is the clicks' bounding box grown by this many
        pixels (10–500); the trace never leaves it. Default 60.
    snap_radius_px : int
        Each click is first moved to the lowest-cost pixel within this radius
        (0–10; 0 keeps the clicks where they are). Default 3.
    simplify_px : float
        Douglas–Peucker tolerance (pixels, 0–3) that thins the pixel chain to
        a polyline's vertices; 0 keeps every pixel. Default 0.2.
    subpixel : bool
        Move each vertex across the path to the edge's sub-pixel peak (the
        edge costs only). Default True.
    oriented : bool
        ``"gradient"``: count only the edge along each clicked segment with the
        clicks' polarity (module docstring). Default True.
    saturation : float
        Oriented ``"gradient"``: an edge as strong as this fraction (0.1–2) of
        the edge under the clicks costs the minimum, so a stronger parallel
        edge nearby does not pull the trace off its contact. Default 0.7.
    stiffness : float
        Extra cost (0–1) of running ``corridor_px`` away from the straight
        line between two clicks, growing with the square of the distance (up
        to 4× at twice the corridor): a weak contact is not abandoned for a
        strong edge further away. 0 turns it off. Default 0.2.
    corridor_px : float
        See ``stiffness`` (1–200 px). Default 10.
    polarity_px : float
        Oriented ``"gradient"``: Gaussian σ (pixels, 0.5–10) of the derivative
        that reads the contact's polarity under the clicks. A click is off its
        contact by a hand's ±1.5 px; read at the cost's fine scale, the rock's
        mottling there can flip the sign and send the trace along the other
        side of a thin bed. Default 1.5 (on the snapping benchmark: traces
        more than 1.5 px off their contact 23.1 → 20.8 % of the small scene's,
        25.8 → 24.5 % of the large scene's).
    refine_reach_px : float
        ``"gradient"`` cost: the finished trace is moved across itself, by at
        most this many pixels (0–3; 0: not), onto the steepest step of the
        luminance itself — read at 1/8 px on the unsmoothed photo, the
        shifts then smoothed along the trace (:func:`_refine_across`). The
        smoothed gradient's peak, which places the path, lies 0.2–0.3 px to
        one side of a contact whose surroundings differ on its two sides.
        Default 1 (on the snapping benchmark: snapped/perfect 1.81 → 1.62 on
        the small scene, 1.34 → 1.22 on the large).
    colour_weight : float
        Oriented ``"gradient"`` on a colour photo: weight (0–5) of the colour
        step trained under the clicks (module docstring, "Trained colour
        step") against the luminance edge, each scaled by its strength under
        the clicks; 0 traces on the luminance alone (as before). Default 1
        (on the snapping benchmark: traces more than 1.5 px off their contact
        15 → 10 % of the small scene's, 21 → 13 % of the large scene's;
        0.75 and 1.5 did no better).
    model_reach_px : float
        With a ``reference`` (:func:`snap_trace`: the model rendered from the
        photo's registered pose), the finished trace is moved across itself
        by at most this many pixels (0–3; 0: not) onto the step the model's
        own colours show there — where the model shows the same contact
        (same polarity, consistent along the trace; :func:`_follow_model`).
        The projected line then lies on the contact as the model has it
        instead of carrying the registration's error (~0.5 px). Default 1.5
        (on the snapping benchmark: snapped/perfect 1.62 → 1.02 on the
        small scene, 1.22 → 0.56 on the large, registered poses).
    """

    cost: str = "gradient"
    smoothing_px: float = 0.7
    contrast: float = 3.0
    floor: float = 0.02
    margin_px: int = 60
    snap_radius_px: int = 3
    simplify_px: float = 0.2
    subpixel: bool = True
    oriented: bool = True
    saturation: float = 0.7
    stiffness: float = 0.2
    corridor_px: float = 10.0
    polarity_px: float = 1.5
    colour_weight: float = 1.0
    refine_reach_px: float = 1.0
    model_reach_px: float = 1.5

    def __post_init__(self) -> None:
        if self.cost not in COSTS:
            raise ValueError(f"snap cost must be one of {', '.join(COSTS)}, got {self.cost!r}")
        for name, lo, hi in (("smoothing_px", 0, 10), ("contrast", 1, 10), ("floor", 1e-3, 0.5),
                             ("margin_px", 10, 500), ("snap_radius_px", 0, 10),
                             ("simplify_px", 0, 3), ("saturation", 0.1, 2),
                             ("stiffness", 0, 1), ("corridor_px", 1, 200),
                             ("polarity_px", 0.5, 10), ("colour_weight", 0, 5),
                             ("refine_reach_px", 0, 3), ("model_reach_px", 0, 3)):
            value = getattr(self, name)
            if not lo <= value <= hi:
                raise ValueError(f"snap {name} must be in [{lo}, {hi}], got {value}")


def _gray(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image, np.float64)
    if img.ndim == 3:
        img = img[..., :3].mean(axis=2)
    return img


def _unit(image: np.ndarray) -> np.ndarray:
    """Scale to [0, 1] from the image's dtype (uint8/uint16) or its own range."""
    img = np.asarray(image)
    if img.dtype == np.uint8:
        return img.astype(np.float64) / 255.0
    if img.dtype == np.uint16:
        return img.astype(np.float64) / 65535.0
    img = img.astype(np.float64)
    lo, hi = np.nanmin(img), np.nanmax(img)
    return (img - lo) / (hi - lo) if hi > lo else np.zeros_like(img)


def _luminance_derivatives(image: np.ndarray, smoothing_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian derivatives (d/dcol, d/drow) of the luminance, ``[0, 1]`` units per pixel."""
    v = _gray(_unit(image))
    sigma = max(smoothing_px, 0.5)
    return (ndimage.gaussian_filter(v, sigma, order=(0, 1)),
            ndimage.gaussian_filter(v, sigma, order=(1, 0)))


def edge_strength(
    image: np.ndarray,
    smoothing_px: float = 1.0,
    kind: str = "gradient",
    normal: np.ndarray | None = None,
    polarity: float = 1.0,
) -> np.ndarray:
    """How strongly each pixel lies on an edge.

    Parameters
    ----------
    image : (H, W) or (H, W, C) array
    smoothing_px : float
        Gaussian σ of the derivative filter, pixels.
    kind : {"gradient", "colour_edge"}
        Luminance gradient, or the largest gradient over the CIELAB colour
        channels a*, b* (scaled to ``[0, 1]`` per 100 units).
    normal : (2,) array, optional
        ``[col, row]`` unit vector: with it (``"gradient"`` only) the signed
        derivative of luminance along ``normal`` times ``polarity``, clipped at
        0 — the edge that runs across ``normal`` and brightens towards it.
    polarity : {1, -1}

    Returns
    -------
    (H, W) float64 array, ≥ 0, image units (``[0, 1]`` scale) per pixel.
    """
    sigma = max(smoothing_px, 0.5)
    if kind == "colour_edge":
        img = _unit(image)
        if img.ndim == 2:
            return ndimage.gaussian_gradient_magnitude(img, sigma)
        from skimage.color import rgb2lab

        lab = rgb2lab(img[..., :3]) / 100.0
        return np.maximum(ndimage.gaussian_gradient_magnitude(lab[..., 1], sigma),
                          ndimage.gaussian_gradient_magnitude(lab[..., 2], sigma))
    gx, gy = _luminance_derivatives(image, smoothing_px)
    if normal is None:
        return np.hypot(gx, gy)
    return np.clip(polarity * (gx * normal[0] + gy * normal[1]), 0, None)


def cost_image(
    image: np.ndarray,
    params: SnapParams = SnapParams(),
    reference_colours: np.ndarray | None = None,
    normal: np.ndarray | None = None,
    polarity: float = 1.0,
) -> np.ndarray:
    """The per-pixel cost a snapped trace minimises.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array
        The photo (uint8, uint16 or float).
    params : SnapParams
    reference_colours : (K, C) array, optional
        For ``cost="colour"``: the colours (same scale as ``image``) the trace
        should stay on; default the image's median colour.
    normal, polarity :
        For an oriented ``"gradient"`` cost, see :func:`edge_strength`.

    Returns
    -------
    (H, W) float64 array in ``[params.floor, 1]``: low where the trace should run.
    """
    if params.cost in ("gradient", "colour_edge"):
        g = edge_strength(image, params.smoothing_px, params.cost,
                          normal if params.cost == "gradient" else None, polarity)
        scale = np.percentile(g, 99.5)
        raw = 1.0 - np.clip(g / scale, 0, 1) if scale > 0 else np.ones_like(g)
    else:
        img = _unit(image)
        if params.smoothing_px > 0:
            sig = (params.smoothing_px,) * 2 + ((0,) if img.ndim == 3 else ())
            img = ndimage.gaussian_filter(img, sig)
        if params.cost in ("darkness", "brightness"):
            v = _gray(img)
            raw = v if params.cost == "darkness" else 1.0 - v
        else:  # colour: distance to the nearest reference colour
            pix = img if img.ndim == 3 else img[..., None]
            if reference_colours is None:
                ref = np.median(pix.reshape(-1, pix.shape[-1]), axis=0)[None]
            else:
                ref = _unit_like(np.asarray(reference_colours), image).reshape(-1, pix.shape[-1])
            d = np.min(np.linalg.norm(pix[..., None, :] - ref[None, None], axis=-1), axis=-1)
            raw = np.clip(d / (np.sqrt(pix.shape[-1]) * 0.5), 0, 1)
    cost = raw ** params.contrast
    return params.floor + (1.0 - params.floor) * cost


def _unit_like(values: np.ndarray, image: np.ndarray) -> np.ndarray:
    if np.asarray(image).dtype == np.uint8:
        return values.astype(np.float64) / 255.0
    if np.asarray(image).dtype == np.uint16:
        return values.astype(np.float64) / 65535.0
    return values.astype(np.float64)


def _snap_click(cost: np.ndarray, rc: np.ndarray, radius: int) -> np.ndarray:
    """The lowest-cost pixel within ``radius`` of ``rc`` (row, col ints)."""
    if radius <= 0:
        return rc
    h, w = cost.shape
    r0, r1 = max(rc[0] - radius, 0), min(rc[0] + radius + 1, h)
    c0, c1 = max(rc[1] - radius, 0), min(rc[1] + radius + 1, w)
    win = cost[r0:r1, c0:c1]
    rr, cc = np.mgrid[r0:r1, c0:c1]
    inside = (rr - rc[0]) ** 2 + (cc - rc[1]) ** 2 <= radius ** 2
    k = np.argmin(np.where(inside, win, np.inf))
    return np.array([rr.ravel()[k], cc.ravel()[k]])


def _subpixel(strength: np.ndarray, px: np.ndarray, reach: float = 1.5) -> np.ndarray:
    """Move each vertex along the path's normal to the parabolic peak of ``strength``.

    ``px`` is (N, 2) ``[col, row]``; the ends keep their places along the path
    but move across it too. Shifts are bounded by ``reach`` pixels.
    """
    if len(px) < 2:
        return px
    tang = np.gradient(px, axis=0)
    norm = np.linalg.norm(tang, axis=1, keepdims=True)
    tang = tang / np.where(norm > 0, norm, 1)
    normal = np.stack([-tang[:, 1], tang[:, 0]], axis=1)
    offsets = np.array([-1.0, 0.0, 1.0])
    samples = px[:, None, :] + offsets[None, :, None] * normal[:, None, :]
    vals = ndimage.map_coordinates(
        strength, [samples[..., 1].ravel(), samples[..., 0].ravel()], order=1, mode="nearest"
    ).reshape(len(px), 3)
    # Walk uphill up to `reach` px, then fit a parabola through three samples.
    out = px.copy()
    for i in range(len(px)):
        centre, v = 0.0, vals[i]
        for _ in range(int(np.ceil(reach))):
            if v[1] >= v[0] and v[1] >= v[2]:
                break
            centre += -1.0 if v[0] > v[2] else 1.0
            if abs(centre) > reach:
                break
            pts = px[i] + (centre + offsets)[:, None] * normal[i]
            v = ndimage.map_coordinates(strength, [pts[:, 1], pts[:, 0]], order=1,
                                        mode="nearest")
        denom = v[0] - 2 * v[1] + v[2]
        delta = 0.5 * (v[0] - v[2]) / denom if denom < 0 else 0.0
        shift = float(np.clip(centre + np.clip(delta, -0.5, 0.5), -reach, reach))
        out[i] = px[i] + shift * normal[i]
    return out


def snap_path(
    cost: np.ndarray,
    clicks: np.ndarray,
    params: SnapParams = SnapParams(),
    strength: np.ndarray | None = None,
) -> np.ndarray:
    """The least-cost trace through the clicked points, in order.

    Parameters
    ----------
    cost : (H, W) array
        From :func:`cost_image` (positive).
    clicks : (K, 2) array, K ≥ 2
        Start, optional waypoints and end, ``[col, row]`` pixels.
    params : SnapParams
    strength : (H, W) array, optional
        Edge strength for the sub-pixel refinement (``edge_strength``);
        without it the vertices stay on pixel centres.

    Returns
    -------
    (N, 2) float64 array of ``[col, row]`` vertices, from the first click to
    the last (clicks moved by at most ``snap_radius_px``).

    Raises
    ------
    ValueError
        Fewer than two clicks, or a click outside the image.
    """
    from skimage.graph import route_through_array
    from skimage.measure import approximate_polygon

    cost = np.asarray(cost, np.float64)
    clicks = np.asarray(clicks, np.float64).reshape(-1, 2)
    if len(clicks) < 2:
        raise ValueError("snapping needs at least two clicks (start and end)")
    h, w = cost.shape
    rc = np.round(clicks[:, ::-1]).astype(int)
    if (rc < 0).any() or (rc[:, 0] >= h).any() or (rc[:, 1] >= w).any():
        raise ValueError("a snapping click lies outside the photo")
    rc = np.array([_snap_click(cost, p, params.snap_radius_px) for p in rc])
    # One window around all clicks keeps Dijkstra local (fast on big photos).
    m = params.margin_px
    r0, c0 = max(rc[:, 0].min() - m, 0), max(rc[:, 1].min() - m, 0)
    r1, c1 = min(rc[:, 0].max() + m + 1, h), min(rc[:, 1].max() + m + 1, w)
    win = cost[r0:r1, c0:c1]
    chain = [rc[:1] - (r0, c0)]
    for a, b in zip(rc[:-1], rc[1:]):
        if np.array_equal(a, b):
            continue
        path, _ = route_through_array(win, tuple(a - (r0, c0)), tuple(b - (r0, c0)),
                                      fully_connected=True, geometric=True)
        chain.append(np.asarray(path)[1:])
    pix = np.concatenate(chain) + (r0, c0)
    px = pix[:, ::-1].astype(np.float64)  # [col, row]
    if params.subpixel and strength is not None and params.cost in ("gradient", "colour_edge"):
        px = _subpixel(np.asarray(strength, np.float64), px)
        # Smooth the sub-pixel jitter along the path (3-tap), ends kept.
        if len(px) > 2:
            px[1:-1] = (px[:-2] + 2 * px[1:-1] + px[2:]) / 4
    if params.simplify_px > 0 and len(px) > 2:
        keep_ends = approximate_polygon(px, tolerance=params.simplify_px)
        px = keep_ends
    return px


def snap_trace(image: np.ndarray, clicks: np.ndarray, params: SnapParams = SnapParams(),
               reference: np.ndarray | None = None) -> np.ndarray:
    """:func:`snap_path` on ``image``'s cost (computed in a window around the clicks).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array
    clicks : (K, 2) array of ``[col, row]``, K ≥ 2
    reference : (H, W) or (H, W, 3) array, optional
        The model's own colours (or intensity) rendered from the photo's
        registered pose, the photo's size (:func:`model_reference`). The
        oriented ``"gradient"`` trace found on the photo is then moved, by
        at most ``params.model_reach_px``, onto the contact where the model
        shows it (:func:`_follow_model`); where it shows no such step the
        trace stays where the photo put it.

    Returns
    -------
    (N, 2) float64 array of ``[col, row]`` vertices.
    """
    img = np.asarray(image)
    clicks = np.asarray(clicks, np.float64).reshape(-1, 2)
    if len(clicks) < 2:
        raise ValueError("snapping needs at least two clicks (start and end)")
    h, w = img.shape[:2]
    pad = params.margin_px + params.snap_radius_px + int(4 * params.smoothing_px) + 4
    c0 = int(max(np.floor(clicks[:, 0].min()) - pad, 0))
    r0 = int(max(np.floor(clicks[:, 1].min()) - pad, 0))
    c1 = int(min(np.ceil(clicks[:, 0].max()) + pad + 1, w))
    r1 = int(min(np.ceil(clicks[:, 1].max()) + pad + 1, h))
    if c1 <= c0 or r1 <= r0:
        raise ValueError("a snapping click lies outside the photo")
    sub = img[r0:r1, c0:c1]
    local_clicks = clicks - (c0, r0)
    if params.cost == "gradient" and params.oriented:
        px = _snap_oriented(sub, local_clicks, params)
        lum = _gray(_unit(sub))
        if params.subpixel and params.refine_reach_px > 0:
            px = _refine_across(lum, px, params)
        if reference is not None and params.subpixel and params.model_reach_px > 0:
            ref = np.asarray(reference)
            if ref.shape[:2] != (h, w):
                raise ValueError(f"the model's render is {ref.shape[1]}×{ref.shape[0]} px, "
                                 f"the photo {w}×{h} px")
            px = _follow_model(lum, _gray(_unit(ref[r0:r1, c0:c1])), px, params)
        px = px + (c0, r0)
    else:
        ref = None
        if params.cost == "colour":
            rc = np.clip(np.round(clicks[:, ::-1]).astype(int), 0, [h - 1, w - 1])
            ref = img[rc[:, 0], rc[:, 1]].reshape(len(rc), -1)
        cost = cost_image(sub, params, reference_colours=ref)
        strength = (edge_strength(sub, params.smoothing_px, params.cost)
                    if params.cost in ("gradient", "colour_edge") else None)
        px = snap_path(cost, local_clicks, params, strength=strength) + (c0, r0)
    # The sub-pixel refinement may push a vertex on the border past it.
    return np.clip(px, 0, [w - 1, h - 1])


def model_reference(scene, intrinsics, cam_from_world) -> np.ndarray | None:
    """The model's own colours seen from a photo's registered pose, for
    :func:`snap_trace`'s ``reference``.

    Parameters
    ----------
    scene : Scene or CloudScene
    intrinsics : Intrinsics
        The photo's camera (the render is the photo's size).
    cam_from_world : Pose
        The photo's registered pose.

    Returns
    -------
    (H, W, 3) uint8 array, or None
        The texture or vertex colours (a cloud's colour or intensity),
        unshaded; None for a model without any (an untextured mesh, a cloud
        of bare points): its shading is no contact to follow.
    """
    from ..render import render
    from ..scene import has_appearance

    if not has_appearance(scene):
        return None
    return render(scene, intrinsics, cam_from_world, mode="color").rgb


#: σ (pixels along the trace) of the smoothing of :func:`_refine_across`'s shifts.
REFINE_ALONG_PX = 4.0

#: Step (pixels) at which :func:`_refine_across` reads the luminance across the trace.
REFINE_STEP_PX = 0.125

#: A point whose luminance step is weaker than this share of the trace's
#: median step is not moved by :func:`_refine_across`.
REFINE_MIN_STEP = 0.5


def _resample(px: np.ndarray, spacing: float = 1.0) -> np.ndarray:
    """The polyline ``px`` with a vertex every ``spacing`` pixels (ends kept).

    Evenly along its length, unlike ``project.densify`` (every vertex kept,
    segments split at most ``step`` apart): :func:`_refine_across` smooths
    along the samples, in pixels. With ``densify`` the snapping benchmark
    gave 1.63 and 1.24 instead of 1.62 and 1.22.
    """
    seg = np.linalg.norm(np.diff(px, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return px.copy()
    at = np.linspace(0.0, s[-1], max(int(np.ceil(s[-1] / spacing)) + 1, 2))
    return np.stack([np.interp(at, s, px[:, 0]), np.interp(at, s, px[:, 1])], axis=1)


def _resampled_with_normals(px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The polyline every pixel (:func:`_resample`) and its unit left-hand
    normals (``[-dy, dx]``), each (N, 2)."""
    pts = _resample(np.asarray(px, np.float64))
    tangent = np.gradient(pts, axis=0) if len(pts) > 1 else np.zeros_like(pts)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-9)
    return pts, np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)


def _refine_across(lum: np.ndarray, px: np.ndarray, params: SnapParams,
                   reach: float | None = None, polarity: float | None = None) -> np.ndarray:
    """Move a finished trace across itself onto the steepest step of ``lum``.

    The trace is resampled every pixel; at each point the luminance is read
    across it every :data:`REFINE_STEP_PX` (cubic, unsmoothed), its slope
    taken with the polarity the trace has, and the point moved to the
    slope's parabolic peak within ``params.refine_reach_px`` — unless the
    peak is at the reach's edge or weaker than :data:`REFINE_MIN_STEP` of the
    trace's median (no step of its own there: the point stays). The shifts are
    smoothed along the trace (a median of 5, then a Gaussian of σ
    :data:`REFINE_ALONG_PX`): a contact bends smoothly, the read is noisy.
    Then thinned again by ``params.simplify_px``.

    Why: the path is placed on the peak of the luminance's *smoothed*
    gradient, and where what lies beside a contact differs on its two sides
    (a bed's grain, the light on a ledge) smoothing moves that peak off the
    contact — on the sample photos 0.2–0.3 px, mostly to one side. The
    unsmoothed slope is unbiased but noisy; the smoothing along the trace
    takes the noise out.

    Parameters
    ----------
    lum : (H, W) array
        The photo's luminance (``[0, 1]``).
    px : (N, 2) array
        The trace, ``[col, row]``.
    params : SnapParams
    reach : float, optional
        How far (pixels) a point may move; default ``params.refine_reach_px``.
    polarity : {1, -1}, optional
        Which way the luminance steps across the trace (along its left-hand
        normal, ``[-dy, dx]``); default: the sign of the median slope at the
        trace.

    Returns
    -------
    (M, 2) array
    """
    from skimage.measure import approximate_polygon

    pts, normal = _resampled_with_normals(px)
    if len(pts) < 4:
        return px
    reach, step = (params.refine_reach_px if reach is None else reach), REFINE_STEP_PX
    offsets = np.arange(-reach - 1.0, reach + 1.0 + 1e-9, step)
    across = pts[:, None, :] + offsets[None, :, None] * normal[:, None, :]
    values = ndimage.map_coordinates(lum, [across[..., 1].ravel(), across[..., 0].ravel()],
                                     order=3, mode="nearest").reshape(len(pts), len(offsets))
    slope = np.gradient(values, step, axis=1)
    centre = len(offsets) // 2
    if polarity is None:  # the trace's polarity: darker on the normal's side
        polarity = 1.0 if np.median(slope[:, centre]) >= 0 else -1.0
    slope = slope * polarity
    inside = np.abs(offsets) <= reach + 1e-9
    k = np.clip(np.argmax(np.where(inside[None, :], slope, -np.inf), axis=1), 1, len(offsets) - 2)
    i = np.arange(len(pts))
    a, b, c = slope[i, k - 1], slope[i, k], slope[i, k + 1]
    denom = a - 2 * b + c
    delta = np.where(denom < 0, 0.5 * (a - c) / np.where(denom < 0, denom, 1.0), 0.0)
    shift = offsets[k] + np.clip(delta, -0.5, 0.5) * step
    # No step of its own there (a stretch where only the colour changes, a
    # fading contact), or the steepest step at the edge of the reach (another
    # edge beside): the point stays where the path put it.
    peak = slope[i, k]
    keep = (np.abs(offsets[k]) < reach - step / 2) & (peak >= REFINE_MIN_STEP * np.median(peak))
    shift = np.where(keep, shift, 0.0)
    shift = ndimage.gaussian_filter1d(ndimage.median_filter(shift, 5, mode="nearest"),
                                      REFINE_ALONG_PX, mode="nearest")
    out = pts + shift[:, None] * normal
    if params.simplify_px > 0 and len(out) > 2:
        out = approximate_polygon(out, tolerance=params.simplify_px)
    return out


#: :func:`_follow_model`: the model's render is followed only where, along
#: the trace, at least this share of its points step the same way as the photo.
MODEL_MIN_AGREEMENT = 0.8


def _side_steps(lum: np.ndarray, px: np.ndarray, reach: float) -> np.ndarray:
    """The luminance step across a trace at each of its points (every pixel).

    The mean of ``lum`` from ``reach`` to ``reach + 1`` pixels along the
    left-hand normal (``[-dy, dx]``) minus that on the other side (bilinear);
    (N,) array, ``[0, 1]`` units. Its sign is the trace's polarity there.
    """
    pts, normal = _resampled_with_normals(px)
    if len(pts) < 2:
        return np.zeros(0)
    offsets = np.linspace(reach, reach + 1.0, 5)
    side = []
    for sign in (1.0, -1.0):
        at = pts[:, None, :] + sign * offsets[None, :, None] * normal[:, None, :]
        side.append(ndimage.map_coordinates(lum, [at[..., 1].ravel(), at[..., 0].ravel()],
                                            order=1, mode="nearest")
                    .reshape(len(pts), len(offsets)).mean(axis=1))
    return side[0] - side[1]


def _follow_model(photo_lum: np.ndarray, model_lum: np.ndarray, px: np.ndarray,
                  params: SnapParams) -> np.ndarray:
    """Move a finished trace onto the contact where the model's render shows it.

    The photo's registered pose is off by a fraction of a pixel (its
    ``uncertainty``), so a line placed exactly on the photo's contact is
    projected that far beside the model's contact. The model rendered from
    that same pose shows its own contact shifted by the same error; moving the
    trace onto it (:func:`_refine_across` on the render's luminance, at most
    ``params.model_reach_px``) puts the projected line on the contact as the
    model has it. Only where the render steps the way the photo does along
    the trace (same polarity on at least :data:`MODEL_MIN_AGREEMENT` of the
    points, both read just beyond the reach): an intensity or a texture that
    does not show the contact, or shows another contact there (the other
    side of a bed), leaves the trace where the photo put it; so does a point
    whose steepest step lies at the reach's edge. A render of grey shading
    passes this test on a third of the snapping benchmark's traces (the
    photo's own shading agrees with it), which is why :func:`model_reference`
    gives no render of an untextured model.

    Parameters
    ----------
    photo_lum, model_lum : (H, W) arrays
        Luminance (``[0, 1]``) of the photo and of the render, same window.
    px : (N, 2) array
        The trace, ``[col, row]`` in that window.
    params : SnapParams

    Returns
    -------
    (M, 2) array
    """
    reach = params.model_reach_px
    photo_steps = _side_steps(photo_lum, px, reach)
    model_steps = _side_steps(model_lum, px, reach)
    if len(photo_steps) < 4:
        return px
    polarity = 1.0 if np.median(photo_steps) >= 0 else -1.0
    if np.mean(np.sign(model_steps) == polarity) < MODEL_MIN_AGREEMENT:
        return px
    return _refine_across(model_lum, px, params, reach=reach, polarity=polarity)


#: Pixels along the clicked segment, inward from each click, over which the
#: contact's polarity is read (:func:`_polarity`).
POLARITY_REACH_PX = 8

#: A polarity read weaker than this fraction of the window's strong edges
#: (99th percentile of the gradient) is not trusted (:func:`_polarity`).
WEAK_POLARITY = 0.2


def _reading_points(clicks: np.ndarray) -> np.ndarray:
    """``[col, row]`` points on the segment between the two clicks, from each
    click :data:`POLARITY_REACH_PX` pixels inward, one per pixel."""
    a, b = clicks[0], clicks[-1]
    length = float(np.linalg.norm(b - a))
    along = (b - a) / max(length, 1e-9)
    steps = np.arange(min(POLARITY_REACH_PX, max(int(length / 2), 1)), dtype=np.float64)
    return np.concatenate([a + steps[:, None] * along, b - steps[:, None] * along])


def _read(field: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """``field`` at the ``[col, row]`` points ``pts`` (bilinear)."""
    return ndimage.map_coordinates(field, [pts[:, 1], pts[:, 0]], order=1, mode="nearest")


def _polarity(gx: np.ndarray, gy: np.ndarray, normal: np.ndarray,
              clicks: np.ndarray) -> tuple[float, bool]:
    """Whether the luminance rises along ``normal`` on the clicked contact (+1) or falls (-1),
    and whether the reading is clear.

    Read on the segment between the two clicks, from each click
    :data:`POLARITY_REACH_PX` pixels inward (bilinear), not only at the
    clicks: a contact often fades where its visible stretch ends — where the
    clicks are — and the strongest edge nearby may be the other side of a
    thin bed, with the opposite polarity. The reading is clear when the mean
    derivative there is at least :data:`WEAK_POLARITY` of the window's strong
    edges.
    """
    v = _read(gx * normal[0] + gy * normal[1], _reading_points(clicks))
    mean = float(v.mean())
    strong = float(np.percentile(np.hypot(gx, gy), 99))
    return (1.0 if mean >= 0 else -1.0), abs(mean) >= WEAK_POLARITY * strong


#: Gaussian σ (pixels) of the derivative that reads colour steps: JPEG keeps
#: colour at half the resolution of luminance (:func:`_colour_step`).
COLOUR_SIGMA_PX = 1.5

#: A colour step under the clicks weaker than this fraction of the window's
#: strong colour steps (99th percentile) is not trained on (:func:`_colour_step`).
WEAK_COLOUR = 0.2

#: Added to each linear channel (``[0, 1]`` scale, about 8 of 255) before its
#: logarithm, so the chromaticity of dark, noisy pixels does not swing.
CHROMA_OFFSET = 8.0 / 255.0


def _chroma_derivatives(image: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Gaussian derivatives (d/dcol, d/drow), each (H, W, 2), of the log
    chromaticity ``log(R/G), log(B/G)`` (:data:`COLOUR_SIGMA_PX`); ``None``
    for a grey image.

    The log chromaticity does not change where only the light does (a shadow,
    a lit ledge, the shading of relief: every channel scaled alike), so its
    steps are the rock's colour changing.
    """
    img = _unit(image)
    if img.ndim != 3 or img.shape[2] < 3:
        return None
    lg = np.log(img[..., :3] + CHROMA_OFFSET)
    chroma = (lg[..., 0] - lg[..., 1], lg[..., 2] - lg[..., 1])
    return tuple(np.stack([ndimage.gaussian_filter(c, COLOUR_SIGMA_PX, order=order) for c in chroma], -1)
                 for order in ((0, 1), (1, 0)))


def _colour_step(cx: np.ndarray, cy: np.ndarray, normal: np.ndarray,
                 clicks: np.ndarray) -> np.ndarray | None:
    """The trained colour edge of one clicked segment: at each pixel, how much
    the chromaticity steps along ``normal`` as it does on the clicked contact.

    The step under the clicks (the mean chromaticity derivative along
    ``normal`` at :func:`_reading_points`, a 2-vector) is the training; each
    pixel's own step is projected on its direction and clipped at 0. ``None``
    when the trained step is weaker than :data:`WEAK_COLOUR` of the window's
    strong colour steps (a contact between beds of one colour: nothing to
    train on).
    """
    d = cx * normal[0] + cy * normal[1]
    pts = _reading_points(clicks)
    ref = np.array([_read(d[..., k], pts).mean() for k in range(d.shape[-1])])
    size = float(np.linalg.norm(ref))
    if size == 0 or size < WEAK_COLOUR * float(np.percentile(np.linalg.norm(d, axis=-1), 99)):
        return None
    return np.clip(d @ (ref / size), 0, None)


def _chord_penalty(shape: tuple[int, int], a: np.ndarray, b: np.ndarray,
                   corridor_px: float) -> np.ndarray:
    """``min((d / corridor)², 4)``, d the distance (px) of each pixel from segment a–b."""
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]]
    p = np.stack([cols, rows], axis=-1).astype(np.float64) - a
    t = b - a
    u = np.clip((p @ t) / max(float(t @ t), 1e-12), 0, 1)
    d = np.linalg.norm(p - u[..., None] * t, axis=-1)
    return np.minimum((d / corridor_px) ** 2, 4.0)


def _window_max(values: np.ndarray, click: np.ndarray, radius: int) -> float:
    c, r = np.round(click).astype(int)
    h, w = values.shape
    win = values[max(r - radius, 0):min(r + radius + 1, h), max(c - radius, 0):min(c + radius + 1, w)]
    return float(win.max()) if win.size else 0.0


def _path_length(px: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(px, axis=0), axis=1).sum())


def _edge_cost(strength: np.ndarray, a: np.ndarray, b: np.ndarray,
               params: SnapParams, chord: np.ndarray | None = None) -> np.ndarray:
    """The cost of an edge-strength image, saturated at the strength under the
    clicks; ``chord``: :func:`_chord_penalty` if already computed."""
    # Saturate at the contact's own strength (under the clicks): a stronger
    # parallel edge nearby (skyline, vegetation) is then no cheaper.
    at_clicks = [_window_max(strength, p, params.snap_radius_px + 1) for p in (a, b)]
    scale = max(params.saturation * float(np.mean(at_clicks)),
                0.05 * float(np.percentile(strength, 99.5)))
    raw = 1.0 - np.clip(strength / scale, 0, 1) if scale > 0 else np.ones_like(strength)
    cost = params.floor + (1.0 - params.floor) * raw ** params.contrast
    if params.stiffness > 0:
        if chord is None:
            chord = _chord_penalty(cost.shape, a, b, params.corridor_px)
        cost = cost + params.stiffness * chord
    return cost


def _at_clicks(strength: np.ndarray, a: np.ndarray, b: np.ndarray, params: SnapParams) -> float:
    """An edge's strength under the clicks (the mean of the largest within
    ``snap_radius_px + 1`` of each), at least 5 % of the window's strong edges."""
    r = params.snap_radius_px + 1
    return max(float(np.mean([_window_max(strength, p, r) for p in (a, b)])),
               0.05 * float(np.percentile(strength, 99.5)), 1e-12)


def _oriented_piece(gx: np.ndarray, gy: np.ndarray, a: np.ndarray, b: np.ndarray,
                    normal: np.ndarray, sign: float, params: SnapParams,
                    colour: np.ndarray | None = None) -> np.ndarray:
    """The least-cost path from ``a`` to ``b`` along the edge across ``normal`` with ``sign``.

    With ``colour`` (:func:`_colour_step`) and ``params.colour_weight`` the
    path is found in two passes. The first routes on the luminance edge plus
    ``colour_weight`` times the trained colour edge, each scaled by its
    strength under the clicks: it chooses *which* edge. The second traces
    again, kept to that route's pixels and their eight neighbours, on the
    luminance edge plus :data:`COLOUR_IN_PLACING` of the colour term, and
    refines to sub-pixel on the same: the luminance, sharper in a JPEG, says
    *where* the edge runs, the colour only where the luminance shows none.
    """
    strength = np.clip(sign * (gx * normal[0] + gy * normal[1]), 0, None)
    if colour is None or params.colour_weight == 0:
        return snap_path(_edge_cost(strength, a, b, params), np.stack([a, b]), params,
                         strength=strength)
    lum = strength / _at_clicks(strength, a, b, params)
    col = colour / _at_clicks(colour, a, b, params)
    chord = (_chord_penalty(strength.shape, a, b, params.corridor_px)
             if params.stiffness > 0 else None)
    guide = _edge_cost(lum + params.colour_weight * col, a, b, params, chord)
    route = snap_path(guide, np.stack([a, b]), replace(params, subpixel=False, simplify_px=0.0))
    on = np.zeros(strength.shape, bool)
    rc = np.round(route[:, ::-1]).astype(int)
    on[rc[:, 0], rc[:, 1]] = True
    near = ndimage.binary_dilation(on, np.ones((3, 3), bool))
    place = lum + COLOUR_IN_PLACING * params.colour_weight * col
    cost = _edge_cost(place, a, b, params, chord) + ~near  # +1 per pixel off the route's band
    return snap_path(cost, np.stack([a, b]), params, strength=place)


#: Share of ``colour_weight`` the trained colour edge keeps in the second,
#: placing pass of :func:`_oriented_piece` (and its sub-pixel refinement).
COLOUR_IN_PLACING = 0.25


def _snap_oriented(image: np.ndarray, clicks: np.ndarray, params: SnapParams) -> np.ndarray:
    """Segment by segment: the edge across each segment's normal with the clicks' polarity."""
    gx, gy = _luminance_derivatives(image, params.smoothing_px)
    pol_gx, pol_gy = (_luminance_derivatives(image, params.polarity_px)
                      if params.polarity_px != params.smoothing_px else (gx, gy))
    chroma = _chroma_derivatives(image) if params.colour_weight > 0 else None
    pieces: list[np.ndarray] = []
    for a, b in zip(clicks[:-1], clicks[1:]):
        if pieces:  # continue from where the last piece ended (its sub-pixel
            # refinement may have put it past the border)
            a = np.clip(pieces[-1][-1], 0, [image.shape[1] - 1, image.shape[0] - 1])
        t = b - a
        n = np.linalg.norm(t)
        if n == 0:
            continue
        normal = np.array([-t[1], t[0]]) / n
        sign, clear = _polarity(pol_gx, pol_gy, normal, np.stack([a, b]))
        colour = _colour_step(*chroma, normal, np.stack([a, b])) if chroma is not None else None
        if clear:
            piece = _oriented_piece(gx, gy, a, b, normal, sign, params, colour)
        else:
            # Unclear at the clicks: trace both polarities and keep the
            # straighter path — a contact runs smoothly from click to click,
            # the edge of the wrong polarity makes it wander.
            piece = min((_oriented_piece(gx, gy, a, b, normal, sg, params, colour)
                         for sg in (1.0, -1.0)), key=_path_length)
        piece = piece if not pieces else piece[1:]
        if len(piece):
            pieces.append(piece)
    if not pieces:
        return clicks[:1].astype(np.float64)
    return np.concatenate(pieces)
