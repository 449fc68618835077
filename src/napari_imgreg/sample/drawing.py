"""What a geologist would draw on a sample photo: the true contacts, in pixels.

The sample scene's true bed boundaries and fault (``truth_lines.geojson``)
are projected into a photo with its true pose; the stretches the camera sees
(the first surface its ray meets) are the lines a geologist can draw
(:func:`visible_stretches`). A hand draws them simplified — straight where
the contact looks straight, bent where it crosses relief — with every vertex
off by a small wobble (:func:`hand_drawn`). :func:`drawing_geojson` gives
them as the pixel GeoJSON the interpretation tools read (``IMG_0001.lines.geojson``
beside each photo of the sample), and ``benchmarks/bench_interpret.py``
measures the mapping of the same lines.

This module builds plain GeoJSON dictionaries: the interpretation package
(a sibling layer, see ``docs/architecture.md``) is not imported.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

__all__ = [
    "MIN_DRAWN_PX",
    "JITTER_PX",
    "SIMPLIFY_PX",
    "VisibleStretch",
    "densify_polyline",
    "visible_stretches",
    "hand_drawn",
    "drawing_geojson",
]

#: Visible stretches shorter than this (pixels, along the line) are not drawn.
MIN_DRAWN_PX = 30.0
#: A hand-drawn line: each vertex off by this much (σ per axis, pixels).
JITTER_PX = 1.5
#: A geologist's line is straight where the contact deviates less than this (pixels).
SIMPLIFY_PX = 2.0
#: Points per metre along the true traces when their visibility is tested.
VISIBILITY_SAMPLES_PER_M = 2.0


@dataclass
class VisibleStretch:
    """One stretch of a true trace that a photo sees.

    Attributes
    ----------
    pixels : (N, 2) array
        Where the stretch lies on the photo (column, row), exactly.
    xyz : (N, 3) array
        The same points on the true trace, local metres.
    truth_index : int
        Index of the trace in ``truth_lines.geojson``'s features.
    truth_properties : dict
        That trace's properties (``label``: ``bed_boundary`` or ``fault``;
        ``above``/``below``: the beds on either side of a bed boundary).
    """

    pixels: np.ndarray
    xyz: np.ndarray
    truth_index: int
    truth_properties: dict[str, Any]

    @property
    def label(self) -> str:
        """The label a geologist gives it: ``fault``, or a bed boundary drawn
        as the base of the bed above it (``sandstone`` or ``mudstone``)."""
        if self.truth_properties.get("label") == "fault":
            return "fault"
        return str(self.truth_properties.get("above", "sandstone"))


def densify_polyline(line: np.ndarray, per_m: float) -> np.ndarray:
    """A 3D polyline with points added so that no step exceeds ``1 / per_m`` metres.

    Parameters
    ----------
    line : (N, 3) array
        Vertices, metres.
    per_m : float
        Points per metre at least, along every segment.

    Returns
    -------
    (M, 3) array
        The original vertices and evenly spaced points between them.
    """
    line = np.asarray(line, np.float64)
    out = [line[:1]]
    for a, b in zip(line[:-1], line[1:]):
        n = max(1, int(math.ceil(np.linalg.norm(b - a) * per_m)))
        out.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.concatenate(out)


def visible_stretches(scene, intrinsics, pose, truth_lines: dict[str, Any],
                      min_length_px: float = MIN_DRAWN_PX) -> list[VisibleStretch]:
    """The stretches of the true traces a photo sees, in pixels.

    Each trace is sampled every half metre and projected with the photo's
    true pose; a point is visible when it lies inside the image and the
    camera's ray through it first meets the surface there (within 2 cm +
    0.2 % of the range). Runs of visible points are separate stretches;
    those shorter than ``min_length_px`` on the photo are left out.

    Parameters
    ----------
    scene : napari_imgreg.Scene
        The model the photo was made from (its ray engine is used).
    intrinsics : napari_imgreg.camera.Intrinsics
        The photo's true camera.
    pose : napari_imgreg.camera.Pose
        The photo's true pose.
    truth_lines : dict
        ``truth_lines.geojson``: a FeatureCollection of 3D LineStrings.
    min_length_px : float
        Shortest stretch drawn, pixels along the line.

    Returns
    -------
    list of VisibleStretch
        In the order of the truth file's features, and along each.
    """
    out = []
    for k, feat in enumerate(truth_lines["features"]):
        xyz = densify_polyline(np.asarray(feat["geometry"]["coordinates"], np.float64),
                               VISIBILITY_SAMPLES_PER_M)
        px = pose.project(intrinsics, xyz)
        inside = np.isfinite(px).all(axis=1)
        inside &= (px[:, 0] >= 0) & (px[:, 1] >= 0)
        inside &= (px[:, 0] <= intrinsics.width - 1) & (px[:, 1] <= intrinsics.height - 1)
        if inside.sum() < 2:
            continue
        # Visible: the true camera's ray through the point first meets the surface there.
        origin, directions = pose.rays(intrinsics, px[inside])
        hits = scene.cast_rays(origin, directions)
        range_m = np.linalg.norm(xyz[inside] - origin, axis=1)
        visible = np.zeros(len(xyz), bool)
        visible[np.where(inside)[0]] = hits.hit & (
            np.abs(hits.distance - range_m) < 0.02 + 0.002 * range_m)
        # Runs of visible points are drawn as separate lines.
        edges = np.flatnonzero(np.diff(np.concatenate([[0], visible.astype(int), [0]])))
        for start, stop in zip(edges[::2], edges[1::2]):
            stretch = px[start:stop]
            if len(stretch) >= 2 and \
                    np.linalg.norm(np.diff(stretch, axis=0), axis=1).sum() >= min_length_px:
                out.append(VisibleStretch(stretch, xyz[start:stop], k, dict(feat["properties"])))
    return out


def hand_drawn(pixels: np.ndarray, rng: np.random.Generator, simplify_px: float = SIMPLIFY_PX,
               jitter_px: float = JITTER_PX) -> np.ndarray:
    """A line as a hand draws it: simplified, every vertex off by a wobble.

    Parameters
    ----------
    pixels : (N, 2) array
        The exact line (column, row).
    rng : numpy.random.Generator
        The wobble's random stream.
    simplify_px : float
        Douglas–Peucker tolerance: straight where the line deviates less.
    jitter_px : float
        The wobble, σ per axis, pixels.

    Returns
    -------
    (M, 2) array
        The drawn vertices, M ≤ N (2 where the line looks straight).
    """
    from skimage.measure import approximate_polygon

    simple = approximate_polygon(np.asarray(pixels, np.float64), simplify_px)
    return simple + rng.normal(0, jitter_px, simple.shape)


def drawing_geojson(stretches: Sequence[VisibleStretch], rng: np.random.Generator,
                    simplify_px: float = SIMPLIFY_PX,
                    jitter_px: float = JITTER_PX) -> dict[str, Any]:
    """The stretches drawn by hand, as pixel GeoJSON (the interpretation format).

    Parameters
    ----------
    stretches : sequence of VisibleStretch
    rng : numpy.random.Generator
        The hand's wobble (see :func:`hand_drawn`).
    simplify_px, jitter_px : float

    Returns
    -------
    dict
        A FeatureCollection of LineStrings ``[column, row]``; properties
        ``id`` (``line1``, ``line2``, …), ``label`` (``fault``, or the bed
        above a bed boundary), ``above``/``below`` (a bed boundary's beds)
        and ``truth`` (the index of its trace in ``truth_lines.geojson``).
    """
    features = []
    for n, stretch in enumerate(stretches, start=1):
        drawn = hand_drawn(stretch.pixels, rng, simplify_px, jitter_px)
        properties: dict[str, Any] = {"id": f"line{n}", "label": stretch.label}
        if stretch.label != "fault":
            for side in ("above", "below"):
                if side in stretch.truth_properties:
                    properties[side] = stretch.truth_properties[side]
        properties["truth"] = stretch.truth_index
        features.append({
            "type": "Feature",
            "geometry": {"type": "LineString", "coordinates": np.round(drawn, 2).tolist()},
            "properties": properties,
        })
    return {"type": "FeatureCollection", "features": features}
