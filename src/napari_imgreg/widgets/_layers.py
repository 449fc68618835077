"""Layer data for napari, built without importing napari.

The one place where the package's axis orders meet napari's:

* 3D: the model frame is (x east, y north, z up). napari draws its data axes
  (0, 1, 2) towards the viewer, down and right (a right-handed frame), so the
  plain reversal (z, y, x) would show every outcrop mirrored. The cyclic
  order (z, x, y) keeps handedness: napari axis 0 is height, 1 east, 2 north.
* 2D: image features are pixel (x = column, y = row); napari is (row, col).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from napari_imgreg.scene import Scene

__all__ = [
    "napari_from_world",
    "world_from_napari",
    "napari_from_pixels",
    "pixels_from_napari",
    "surface_layer_data",
    "NAPARI_AXIS_LABELS",
]

LayerDataTuple = tuple[Any, dict[str, Any], str]


NAPARI_AXIS_LABELS = ("z (up)", "x (east)", "y (north)")


def napari_from_world(xyz: np.ndarray) -> np.ndarray:
    """Model-frame points (..., 3) as (x, y, z) to napari data order (z, x, y)."""
    return np.asarray(xyz)[..., [2, 0, 1]]


def world_from_napari(zxy: np.ndarray) -> np.ndarray:
    """napari data coordinates (..., 3) as (z, x, y) to model-frame (x, y, z)."""
    return np.asarray(zxy)[..., [1, 2, 0]]


def napari_from_pixels(xy: np.ndarray) -> np.ndarray:
    """Pixel coordinates (N, 2) as (x, y) to napari (row, col)."""
    return np.asarray(xy)[..., ::-1]


def pixels_from_napari(rowcol: np.ndarray) -> np.ndarray:
    """napari (row, col) coordinates (N, 2) to pixel (x, y)."""
    return np.asarray(rowcol)[..., ::-1]


def surface_layer_data(scene: Scene, name: str | None = None) -> LayerDataTuple:
    """A napari Surface ``LayerDataTuple`` showing the scene as it is coloured.

    A textured scene keeps its texture and texture coordinates (napari
    multiplies the texture by white vertex colours, i.e. shows it unaltered);
    a vertex-coloured scene keeps its colours; otherwise the surface is grey
    with smooth shading.
    """
    data = (napari_from_world(scene.vertices).astype(np.float32), scene.faces)
    kwargs: dict[str, Any] = {
        "name": name or scene.name,
        "metadata": {"imgreg_scene": scene},
        "axis_labels": NAPARI_AXIS_LABELS,
    }
    if scene.has_texture:
        kwargs.update(texture=scene.texture, texcoords=scene.uv, shading="none")
    elif scene.vertex_colors is not None:
        kwargs.update(vertex_colors=scene.vertex_colors / 255.0, shading="none")
    else:
        kwargs.update(shading="smooth")
    return (data, kwargs, "surface")
