"""Layer data and cameras for napari, built without importing napari.

The one place where the package's axis orders and cameras meet napari's:

* 3D: the model frame is (x east, y north, z up). napari draws its data axes
  (0, 1, 2) towards the viewer, down and right (a right-handed frame), so the
  plain reversal (z, y, x) would show every outcrop mirrored. The cyclic
  order (z, x, y) keeps handedness: napari axis 0 is height, 1 east, 2 north.
* 2D: image features are pixel (x = column, y = row); napari is (row, col).
* Cameras: a 3D viewer orbits a centre point along a view direction
  (:func:`camera_from_view`, :func:`view_from_camera`); a photo's camera is a
  pinhole with a ``cam_from_world`` pose, drawn as its view pyramid
  (:func:`frustum_segments`).
"""

from __future__ import annotations

import contextlib
import math
from typing import Any

import numpy as np

from ..camera import Intrinsics, Pose
from ..scene import Scene

__all__ = [
    "napari_from_world",
    "world_from_napari",
    "napari_from_pixels",
    "pixels_from_napari",
    "surface_layer_data",
    "camera_from_view",
    "view_from_camera",
    "frustum_segments",
    "NAPARI_AXIS_LABELS",
    "only_height_slider",
    "viewer_camera",
    "layers_batched",
    "remove_layers",
    "fit_camera_2d",
    "INTERPRETATION_OF",
    "REDUCED_BY",
    "photo_pixel_frame",
]

LayerDataTuple = tuple[Any, dict[str, Any], str]


NAPARI_AXIS_LABELS = ("z (up)", "x (east)", "y (north)")


def viewer_camera(viewer):
    """The viewer's camera model (``viewer.scene.camera`` from napari 0.9 on,
    where ``viewer.camera`` is deprecated)."""
    scene = getattr(viewer, "scene", None)
    if scene is not None and hasattr(scene, "camera"):
        return scene.camera
    return viewer.camera


#: The layer lists (by id) within a batch of :func:`layers_batched` now.
_IN_BATCH: set[int] = set()


@contextlib.contextmanager
def layers_batched(viewer):
    """A context in which the viewer's layers change as one batch
    (``viewer.layers.batched_update``; a napari without it: no batch).

    napari collects garbage (``gc.collect``, 0.2–0.5 s with a campaign in
    memory) after each layer removed, except within a batch, which does it
    once at its end (even when no layer was removed: enter one only for
    removals). napari's batches do not nest (the inner one's end ends the
    batch): within one, this adds none.
    """
    layers = viewer.layers
    batched = getattr(layers, "batched_update", None)
    if not callable(batched) or id(layers) in _IN_BATCH:
        yield
        return
    _IN_BATCH.add(id(layers))
    try:
        with batched():
            yield
    finally:
        _IN_BATCH.discard(id(layers))


def remove_layers(viewer, layers) -> None:
    """Remove ``layers`` (those still in the viewer), several as one batch
    (see :func:`layers_batched`)."""
    layers = [layer for layer in layers if layer in viewer.layers]
    with layers_batched(viewer) if len(layers) > 1 else contextlib.nullcontext():
        for layer in layers:
            viewer.layers.remove(layer)


def fit_camera_2d(camera, lo, hi, canvas_hw) -> None:
    """Centre a 2D view on the (row, col) box ``lo``–``hi`` and zoom it to fill
    95 % of the canvas.

    Parameters
    ----------
    camera : napari camera
        Its ``center`` keeps a leading (not displayed) coordinate if it has one.
    lo, hi : (2,) arrays
        The box's corners, world (row, col).
    canvas_hw : (int, int)
        The canvas' height and width, pixels.
    """
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    mid = (lo + hi) / 2.0
    centre = tuple(camera.center)
    camera.center = (centre[0], *mid) if len(centre) == 3 else tuple(mid)
    camera.zoom = 0.95 * min(canvas_hw[0] / max(hi[0] - lo[0], 1.0),
                             canvas_hw[1] / max(hi[1] - lo[1], 1.0))

def only_height_slider(axis_labels, displayed, nsteps, visible_ndims) -> bool:
    """Whether the one slider napari would show under the canvas is the
    model's height axis and moves nothing on it.

    napari gives every axis not displayed a slider when it has more than one
    step; with the model (3D, :data:`NAPARI_AXIS_LABELS`) among the layers, the
    2D view of the photos gets one for the model's height in metres, though
    the 3D layers are hidden there. A visible layer of three or more axes (a
    user's image stack) keeps its slider, and so do more axes: False then.

    Parameters
    ----------
    axis_labels : sequence of str
        ``viewer.dims.axis_labels``.
    displayed : sequence of int
        ``viewer.dims.displayed``: the axes on the canvas.
    nsteps : sequence of int
        ``viewer.dims.nsteps``.
    visible_ndims : iterable of int
        The number of axes of each visible layer.
    """
    sliders = [axis for axis, n in enumerate(nsteps) if axis not in displayed and n > 1]
    return (tuple(axis_labels) == NAPARI_AXIS_LABELS and sliders == [0]
            and all(ndim <= 2 for ndim in visible_ndims))


#: Metadata key of an interpretation Shapes layer: the name of the photo layer
#: it is drawn on (made by the interpretation dock, followed by the workbench).
INTERPRETATION_OF = "imgreg_interpretation_of"
#: Photo layer metadata key: the layer holds every this-many-th pixel of its
#: photo, scaled up to the photo's extent (a workbench photo not shown); 0 or
#: absent: all of them.
REDUCED_BY = "imgreg_reduced_by"
#: Model layer metadata key: True on the workbench's own model, the one its
#: photos are registered to (the Orient dock does not rotate it).
WORKBENCH_MODEL = "imgreg_workbench_model"


def photo_pixel_frame(photo_layer) -> tuple[np.ndarray, np.ndarray]:
    """Where a photo's own pixels lie on the canvas: (row, col) scale and
    translation, whether its layer holds all of them or a reduced copy
    (:data:`REDUCED_BY`). Layers drawn over the photo take these."""
    scale = np.asarray(photo_layer.scale[-2:], float)
    reduced_by = float(photo_layer.metadata.get(REDUCED_BY) or 0)
    if reduced_by > 0:
        scale = scale / reduced_by
    return scale, np.asarray(photo_layer.translate[-2:], float)


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


#: Points of a cloud shown in 3D at most (a decimated display copy; the
#: stages use every point). ~0.5 s to upload on Mesa's software GL.
DISPLAY_CLOUD_POINTS = 400_000


def cloud_layer_data(scene, name: str | None = None,
                     max_points: int = DISPLAY_CLOUD_POINTS) -> LayerDataTuple:
    """A napari Points ``LayerDataTuple`` showing a lidar cloud: every k-th point
    (at most ``max_points``), coloured by its RGB or by intensity (grey), sized
    by the cloud's median point spacing. The stages keep every point."""
    n = scene.n_points
    step = max(1, int(np.ceil(n / max_points)))
    keep = np.arange(0, n, step)
    xyz = scene.xyz[keep]
    if scene.vertex_colors is not None:
        colors = scene.vertex_colors[keep] / 255.0
    elif scene.intensity is not None:
        grey = np.clip(scene.intensity[keep], 0, 1)
        colors = np.repeat(grey[:, None], 3, axis=1)
    else:
        colors = np.full((len(keep), 3), 0.7)
    colors = np.column_stack([colors, np.ones(len(keep))]).astype(np.float32)
    spacing = float(np.median(scene.spacing[keep])) if len(keep) else 0.1
    kwargs: dict[str, Any] = {
        "name": name or scene.name,
        "metadata": {"imgreg_scene": scene},
        "axis_labels": NAPARI_AXIS_LABELS,
        "face_color": colors, "border_width": 0, "size": max(spacing * 1.5 * np.sqrt(step), 1e-3),
        "shading": "none", "ndim": 3,
    }
    return (napari_from_world(xyz).astype(np.float32), kwargs, "points")


# ============================================== viewer camera <-> photo camera
def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, np.float64).reshape(3)
    n = np.linalg.norm(v)
    if n == 0:
        raise ValueError("zero-length direction")
    return v / n


def camera_from_view(
    center: np.ndarray,
    view_direction: np.ndarray,
    up_direction: np.ndarray,
    visible_height: float,
    width: int,
    height: int,
    fov_deg: float | None = None,
    intrinsics: Intrinsics | None = None,
) -> tuple[Intrinsics, Pose]:
    """A pinhole camera that sees what a 3D viewer shows.

    A 3D viewer (napari, vispy) orbits a ``center`` point: it looks along
    ``view_direction``, ``up_direction`` points up on the canvas and
    ``visible_height`` world units span the canvas height at the centre. This
    places a pinhole camera of ``width`` × ``height`` pixels so that it frames
    the centre the same way, for the reference render of a manual
    registration.

    Parameters
    ----------
    center : (3,) array
        The point the view orbits, model frame (metres).
    view_direction, up_direction : (3,) arrays
        Model-frame directions (need not be unit or orthogonal; ``up`` is
        made orthogonal to ``view``).
    visible_height : float
        World extent across the image height at the centre, metres.
    width, height : int
        Size of the camera image, pixels.
    fov_deg : float, optional
        Vertical field of view (a perspective viewer). When None or 0 (an
        orthographic viewer) the focal length of ``intrinsics`` is used, or
        a 50° vertical field of view without it.
    intrinsics : Intrinsics, optional
        A camera whose focal length (scaled to ``height``) to use.

    Returns
    -------
    intrinsics : Intrinsics
        Square pixels, principal point at the image centre.
    pose : Pose
        ``cam_from_world``; the camera sits ``distance`` in front of the
        centre, where the visible height at the centre is ``visible_height``.
    """
    z = _unit(view_direction)
    up = np.asarray(up_direction, np.float64).reshape(3)
    up = up - (up @ z) * z
    y = -_unit(up)  # image rows run down the canvas
    x = np.cross(y, z)
    R = np.stack([x, y, z])
    if fov_deg:
        f = (height / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    elif intrinsics is not None:
        f = intrinsics.fy * height / intrinsics.height
    else:
        f = (height / 2.0) / math.tan(math.radians(25.0))
    distance = float(visible_height) * f / height
    cam_center = np.asarray(center, np.float64).reshape(3) - distance * z
    intr = Intrinsics(int(width), int(height), f, f, (width - 1) / 2.0, (height - 1) / 2.0)
    return intr, Pose.from_center(R, cam_center)


def view_from_camera(
    intrinsics: Intrinsics, pose: Pose, distance: float, canvas_px: float
) -> dict:
    """The 3D-viewer camera that looks from a photo's pose (inverse of :func:`camera_from_view`).

    Parameters
    ----------
    intrinsics : Intrinsics
    pose : Pose
    distance : float
        How far in front of the camera the viewer's orbit centre is, metres
        (e.g. the depth at the image centre).
    canvas_px : float
        The viewer canvas' smaller side, pixels.

    Returns
    -------
    dict
        ``center`` (3,) model-frame point, ``view_direction`` and
        ``up_direction`` (3,) model-frame unit vectors, ``zoom`` (canvas
        pixels per metre at the centre) and ``fov_deg`` (vertical field of
        view).
    """
    z = pose.view_direction
    up = -pose.R[1]
    visible = distance * intrinsics.height / intrinsics.fy
    fov = 2.0 * math.degrees(math.atan2(intrinsics.height / 2.0, intrinsics.fy))
    return {
        "center": pose.center + distance * z,
        "view_direction": z,
        "up_direction": up,
        "zoom": float(canvas_px) / visible,
        "fov_deg": fov,
    }


def frustum_segments(intrinsics: Intrinsics, pose: Pose, depth: float) -> np.ndarray:
    """Line segments of a camera's view pyramid, for drawing cameras in 3D.

    Parameters
    ----------
    intrinsics : Intrinsics
    pose : Pose
    depth : float
        Distance of the pyramid's base along the view direction, metres.

    Returns
    -------
    (8, 2, 3) array
        Start and end points (model frame): four edges from the centre to the
        image corners at ``depth``, then the four sides of the base.
    """
    w, h = intrinsics.width, intrinsics.height
    corners_px = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
    cam = intrinsics.unproject(corners_px, np.full(4, float(depth)))
    corners = pose.inverse_transform(cam)
    c = pose.center
    segs = [(c, corners[k]) for k in range(4)]
    segs += [(corners[k], corners[(k + 1) % 4]) for k in range(4)]
    return np.array(segs, np.float64)
