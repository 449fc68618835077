"""The workbench's Qt wiring: one controller per napari viewer.

The workbench's state — the scene, the photos with their priors, pose
histories and trials, the registration parameters, the control points, the
suns and interpretations — is a Qt-free :class:`~napari_imgreg.workspace.Workspace`
(``controller.workspace``). The controller builds it, follows its events, and
does what needs Qt and napari:

* it owns the napari layers that show the workspace (:class:`_Layers`): the
  photo beside the render of its pose, filtered previews, correspondences,
  the reference render and the pairs, and in 3D the model with the cameras;
* it runs every long job (scene and photo loading, renders, filters over
  full images, registration, manual solving and scoring, reading the sun)
  through one :class:`~napari_imgreg.widgets._jobs.JobRunner`, so the viewer
  never freezes, and turns errors into one-line napari notifications;
* it relays the workspace's events as Qt signals to the docks, after it has
  brought its layers up to date.

It orchestrates only: rendering, filtering, registration and manual solving
are the backend's (:mod:`~napari_imgreg.render`, :mod:`~napari_imgreg.registration.filters`,
:mod:`~napari_imgreg.registration.pipeline`, :mod:`~napari_imgreg.registration.manual`),
the state and its rules the workspace's.
"""

from __future__ import annotations

import logging
import os
import threading
import time
import weakref
from contextlib import nullcontext
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import cv2
import numpy as np
from matplotlib.colors import to_rgba
from qtpy.QtCore import QObject, QTimer, Signal

from .._allocator import tune_allocator
from .._deprecated import forward_moved_names
from ..adjust import TerrainMap
from ..camera import Intrinsics, Pose, match_scale
from ..errors import InputError
from ..io.meshes import check_model_suffix
from ..prior import Prior
from ..registration.filters import apply_filters, reduce_for_matching
from ..registration.params import RegistrationParams
from ..registration.quality import outcome_words
from ..scene import size_text
from ..registration.pipeline import Trial
from ..registration.stages.relight import render_sunlit
from ..render import RenderResult, render
from ..sample import sample_scene
from ._jobs import JobRunner, hold_results, in_python_thread
from ._dims_bar import HeightSliderHider
from ._layers import (
    INTERPRETATION_OF,
    REDUCED_BY,
    WORKBENCH_MODEL,
    camera_from_view,
    cloud_layer_data,
    fit_camera_2d,
    frustum_segments,
    layers_batched,
    napari_from_pixels,
    napari_from_world,
    pixels_from_napari,
    remove_layers,
    surface_layer_data,
    view_from_camera,
    viewer_camera,
    world_from_napari,
)
from ..workspace import (
    BatchStep,
    BatchSummary,
    Job,
    PhotoState,
    SaveAs,
    WorkbenchError,
    Workspace,
    one_line,
    read_photos,
    read_scene,
)

if TYPE_CHECKING:
    import napari

    from ..scene import Scene

__all__ = [
    "WorkbenchController",
    "PhotoState",
    "WorkbenchError",
    "controller_for",
    "real_viewer",
    "warm_napari",
    "overview_direction",
    "outcome_text",
    "one_line",
    "PREVIEW_WIDTH",
    "RENDER_NAMES",
    "PAIR_COLORS",
    "CORRESPONDENCE_COLORS",
]

log = logging.getLogger(__name__)

#: Names that moved to the workspace in 0.2 (PhotoState, WorkbenchError and
#: one_line are used here, so still imported); the old path warns.
_MOVED = {"TrialRecord": "napari_imgreg.workspace", "SUN_ESTIMATE_WIDTH": "napari_imgreg.workspace"}


__getattr__ = forward_moved_names(__name__, _MOVED)


#: Camera markers and view frusta in the 3D view, as fractions of the model's diagonal.
CAMERA_MARKER, CAMERA_FRUSTUM = 0.012, 0.035
#: Cameras in the 3D view: the photos' (and their frusta), and the current photo's.
#: Cyan and magenta: no interpretation label's colour
#: (:data:`~napari_imgreg.interpret.project.LABEL_COLORS` and the picks after
#: them), so cameras are not taken for mapped lines.
CAMERA_COLOR, CURRENT_CAMERA_COLOR = "#00e5ff", "#ff40ff"
#: "3D, seen from the photo's pose": cameras nearer the viewpoint than this
#: fraction of the distance to the outcrop are left out (up close their
#: frusta fill the view as thick bars).
NEAR_CAMERA_HIDE = 0.5
#: "3D: model and cameras": looking this far down (degrees) toward the outcrop,
#: along the cameras' mean heading.
OVERVIEW_DIP_DEG = 30.0
#: Width (pixels) of the reduced render shown while the pose is being edited.
PREVIEW_WIDTH = 400
#: Idle time after the last pose edit before the full-resolution render, ms.
FULL_RENDER_DELAY_MS = 350
#: Idle time after the last parameter edit before it is saved into the workspace folder, ms.
PARAMS_SAVE_DELAY_MS = 500
#: Render layer names: as textured, and relit for the photo's sun.
RENDER_NAMES = {"plain": "render", "sunlit": "render (sun-lit)"}
#: Correspondence lines drawn at most (an even sample of them).
MAX_LINES = 300
#: Gap between the photo and the render on the canvas, as a fraction of the width.
GAP = 0.04
#: Pair colours of the manual control points (matched on photo and reference).
PAIR_COLORS = (
    "#e6194b", "#3cb44b", "#ffe119", "#4363d8", "#f58231", "#911eb4", "#46f0f0",
    "#f032e6", "#bcf60c", "#fabebe", "#008080", "#e6beff", "#9a6324", "#fffac8",
    "#800000", "#aaffc3", "#808000", "#ffd8b1", "#000075", "#ffffff",
)
#: Correspondence line colours: agree with the pose, pass the 2D check only, rejected.
CORRESPONDENCE_COLORS = {
    "pose inlier": "#00e676", "feature inlier": "#ffd600", "outlier": "#ff1744",
}


_CONTROLLERS: weakref.WeakValueDictionary[int, WorkbenchController] = weakref.WeakValueDictionary()


def real_viewer(viewer: napari.viewer.Viewer) -> napari.viewer.Viewer:
    """The viewer itself behind napari's proxies.

    napari hands each plugin widget (Plugins menu, ``add_plugin_dock_widget``,
    app-model providers) a new ``PublicOnlyProxy`` of the viewer — a
    ``wrapt.ObjectProxy`` whose ``__wrapped__`` is the viewer — so two docks of
    one viewer hold two different objects. Anything keyed by the viewer (the
    controller below) keys the object behind them.
    """
    try:
        from wrapt import ObjectProxy  # napari's own dependency (its proxies are wrapt's)
    except ImportError:  # pragma: no cover - napari without wrapt has no proxies
        return viewer
    seen = 0
    while isinstance(viewer, ObjectProxy) and seen < 8:
        viewer = viewer.__wrapped__
        seen += 1
    return viewer


def controller_for(viewer: napari.viewer.Viewer) -> WorkbenchController:
    """The viewer's workbench controller (created on first use).

    Every workbench dock of a viewer, and any dock that wants the current
    photo, pose or registration (e.g. an interpretation widget), shares it —
    whichever proxy of the viewer napari handed the dock (see :func:`real_viewer`).
    """
    viewer = real_viewer(viewer)
    ctrl = _CONTROLLERS.get(id(viewer))
    if ctrl is None or ctrl.viewer is not viewer or ctrl.closed:
        ctrl = WorkbenchController(viewer)
        _CONTROLLERS[id(viewer)] = ctrl
    return ctrl


def warm_napari() -> None:
    """Do napari's one-time lazy set-ups in the calling (worker) thread.

    The first layer napari makes builds pint's unit registry (~0.5 s), the
    first Points or Shapes layer imports pandas (~0.2 s) and the first Shapes
    layer (the interpretation tools make one per photo) compiles numba's
    triangulation (~0.5 s); left to the GUI thread they freeze the
    window when a workspace, a model or the sample is opened. Each is done
    once per process and is skipped when done already; a failure only costs
    the time back in the GUI thread.
    """
    try:  # imported by the first Points/Shapes layer's features (~0.2 s)
        import pandas  # noqa: F401
        import napari.components.histogram  # noqa: F401
    except Exception as exc:  # pragma: no cover - napari internals moved
        log.debug("pandas not imported ahead: %s", exc)
    try:
        from napari.utils._units import get_unit_registry

        registry = get_unit_registry()  # pint's ApplicationRegistry
        inner = registry.get() if hasattr(registry, "get") else registry
        if type(inner).__name__ == "LazyRegistry":  # not built yet: built by its first use
            registry.Unit("pixel")
    except Exception as exc:  # pragma: no cover - napari internals moved
        log.debug("pint registry not warmed: %s", exc)
    try:
        from napari.layers.shapes import _accelerated_triangulate_dispatch as tri

        tri.warmup_numba_cache()
    except Exception as exc:  # pragma: no cover - napari internals moved; no numba
        log.debug("numba triangulation not warmed: %s", exc)


def _open_workspace_warm(folder: Path, thumbnail_width: int | None = None) -> Workspace:
    """Open a workspace folder, then warm napari for showing it and make the
    photos' thumbnails ``thumbnail_width`` pixels wide (worker thread: for
    hundreds of photos they took seconds of the GUI thread)."""
    opened = Workspace.open(folder)
    warm_napari()
    for ps in opened.photos if thumbnail_width else ():
        try:
            ps.photo.thumbnail(thumbnail_width)  # kept by the photo
        except Exception:  # noqa: BLE001 - met again where the table makes it, as before
            pass
    return opened


def _read_scene_warm(mesh, *args):
    check_model_suffix(mesh, dsm=True)  # what the Model field takes, a DSM too
    value = read_scene(mesh, *args)
    warm_napari()
    return value


#: How an unregistered photo's best grade reads beside "not registered".
def outcome_text(status: str, grade: str, q: float, rich: bool = False) -> str:
    """A registration's outcome in words whose status and grade agree.

    ``"registered — grade good, Q = 0.90"``; a photo that did not register
    says so and that its grade is its best trial's: ``"not registered — best
    trial fair (uncertain), Q = 0.40"`` (RESULT.json's ``status`` stays
    ``"failed"`` and its ``grade`` ``"fair"``: only the words shown change;
    :func:`~napari_imgreg.registration.quality.outcome_words`).
    ``rich``: the status in bold (Qt rich text).
    """
    head = "registered" if status == "registered" else "not registered"
    tail = f"{outcome_words(status, grade)}, Q = {q:.2f}"
    return f"<b>{head}</b> — {tail}" if rich else f"{head} — {tail}"


def overview_direction(poses, dip_deg: float = OVERVIEW_DIP_DEG) -> np.ndarray | None:
    """A 3D view direction (model frame, unit) facing what the cameras face:
    their mean horizontal heading, ``dip_deg`` down. An outcrop is mostly a
    steep face, edge-on from straight above. None without poses."""
    if not poses:
        return None
    heading = np.mean([np.asarray(p.view_direction, float) for p in poses], axis=0)
    heading[2] = 0.0
    norm = float(np.linalg.norm(heading))
    if norm < 1e-6:  # cameras looking down, or every way: from the south
        heading, norm = np.array([0.0, 1.0, 0.0]), 1.0
    dip = np.radians(dip_deg)
    view = heading / norm * np.cos(dip) + np.array([0.0, 0.0, -np.sin(dip)])
    return view / np.linalg.norm(view)


# ------------------------------------------------------------------ layers
#: A hidden photo layer keeps every this-many-th pixel (scaled back up), not all.
_HIDDEN_PHOTO_STEP = 16


class _Layers:
    """The napari layers of the workbench, found again if the user renamed them
    and made anew if deleted."""

    def __init__(self, viewer: napari.viewer.Viewer) -> None:
        self.viewer = viewer
        self._refs: dict[str, Any] = {}
        self.width = 0
        self.height = 0

    def get(self, key: str):
        layer = self._refs.get(key)
        if layer is not None and layer in self.viewer.layers:
            return layer
        return None

    def _put(self, key: str, layer) -> Any:
        self._refs[key] = layer
        self.order()
        return layer

    def _add(self, method: str, *args, **kwargs):
        """``viewer.add_*`` without making the new layer the active one."""
        active = self.viewer.layers.selection.active
        layer = getattr(self.viewer, method)(*args, **kwargs)
        if active is not None and active in self.viewer.layers:
            self.viewer.layers.selection.active = active
        return layer

    #: Bottom to top among the workbench's layers (other layers keep their places).
    ORDER = ("surface", "photo", "photo_filtered", "render", "render_filtered", "reference",
             "blend", "correspondences", "photo_pairs", "reference_pairs", "cameras", "frusta")

    def order(self) -> None:
        """Keep the workbench's layers stacked as :attr:`ORDER` says."""
        layers = self.viewer.layers
        mine = [layer for key in self.ORDER if (layer := self.get(key)) is not None]
        slots = sorted(layers.index(layer) for layer in mine)
        for slot, layer in zip(slots, mine):
            i = layers.index(layer)
            if i != slot:
                layers.move(i, slot)

    @property
    def offset(self) -> float:
        """Column of the right-hand image (render, reference) on the canvas."""
        return self.width * (1.0 + GAP)

    # -- 2D: photo | render side by side
    def show_photo(self, ps: PhotoState) -> None:
        """The photo's own Image layer (named after it), the others hidden.

        One layer per photo: what is drawn over a photo (the interpretation
        tools key their layers by the photo layer's name) stays with it.
        """
        try:
            image = ps.photo.image  # a photo read from a file decodes here
        except InputError as exc:
            # Its file became unreadable since it was opened: a grey stand-in of
            # its size keeps its pose, drawings and pairs where they belong.
            from napari.utils.notifications import show_error

            show_error(str(exc))
            image = np.full((ps.photo.size[1], ps.photo.size[0], 3), 96, np.uint8)
        self.height, self.width = image.shape[:2]
        key = f"photo:{ps.photo.path}"
        layer = self.get(key)
        if layer is None:
            name = ps.photo.path.stem if ps.photo.path is not None else "photo"
            layer = self._put(key, self._add("add_image", image, name=name, rgb=True,
                                             metadata={"photo_path": str(ps.photo.path)}))
        elif layer.metadata.get(REDUCED_BY):
            layer.data, layer.scale = image, (1.0, 1.0)
            layer.metadata[REDUCED_BY] = 0
        previous = self.get("photo")
        self._refs["photo"] = layer
        if previous is not None and previous is not layer:
            previous.visible = False
            # Its full pixels go (a campaign's photos, each visited once, would
            # all stay in memory): a 1/16 copy keeps its extent, and showing
            # it again puts the photo's pixels back.
            step = _HIDDEN_PHOTO_STEP
            previous.data = np.ascontiguousarray(previous.data[::step, ::step])
            previous.scale = (float(step), float(step))
            previous.metadata[REDUCED_BY] = step
        layer.visible = self.viewer.dims.ndisplay == 2
        self.order()
        for key in ("photo_filtered", "render_filtered", "correspondences"):
            if (other := self.get(key)) is not None:
                other.visible = False
        # Interpretations drawn on the other photos step back with them.
        for other in self.viewer.layers:
            owner = other.metadata.get(INTERPRETATION_OF)
            if owner is not None:
                other.visible = owner == layer.name and self.viewer.dims.ndisplay == 2

    def clear_photos(self) -> None:
        """Remove the photos' layers (a new model was opened)."""
        remove_layers(self.viewer, [self._refs.pop(key) for key in list(self._refs)
                                     if key.startswith("photo:")])
        self._refs.pop("photo", None)

    def has_photos(self) -> bool:
        """Photos are shown (their layers go when another workspace or model is opened)."""
        return any(key.startswith("photo:") and self.get(key) is not None for key in self._refs)

    def set_camera(self, ps: PhotoState) -> None:
        """Keep the photo layer's camera and pose current (read by the interpretation tools)."""
        layer = self.get("photo")
        if layer is not None:
            layer.metadata["intrinsics"] = ps.intrinsics
            layer.metadata["pose"] = ps.pose

    def image_geometry(self, rendered, right: bool = True) -> tuple[tuple, tuple]:
        """(scale, translate) that lay a reduced image (a RenderResult or an
        array) over the full-size frame of the photo."""
        h, w = rendered.shape[:2]
        sx, sy = w / max(self.width, 1), h / max(self.height, 1)
        scale = (1.0 / sy, 1.0 / sx)
        # Pixel i of the reduced image has its centre at full-size (i + 0.5) / s - 0.5.
        translate = (0.5 / sy - 0.5, 0.5 / sx - 0.5 + (self.offset if right else 0.0))
        return scale, translate

    def _show_rgb(self, key: str, name: str, image: np.ndarray, scale, translate, **kwargs):
        layer = self.get(key)
        if layer is None:
            layer = self._put(key, self._add("add_image", image, name=name, rgb=True, scale=scale,
                                             translate=translate, **kwargs))
        else:
            _set_geometry(layer, scale, translate)
            layer.data = image
        return layer

    def show_render(self, rgb: np.ndarray, blend_opacity: float, blend_visible: bool,
                    mode: str = "plain") -> None:
        """The render (at the photo's size) right of the photo, and over it for
        blending; ``mode`` "sunlit": relit for the photo's sun (named so)."""
        layer = self._show_rgb("render", RENDER_NAMES[mode], rgb, (1.0, 1.0), (0.0, self.offset))
        if getattr(self, "_render_mode", "plain") != mode:  # renamed on a change only
            layer.name = RENDER_NAMES[mode]
        self._render_mode = mode
        self._blend_rgb = rgb
        blend = self.get("blend")
        if blend is None:
            self._show_rgb("blend", "overlay render", rgb, (1.0, 1.0), (0.0, 0.0),
                           opacity=blend_opacity, visible=blend_visible)
        elif blend.visible:  # a hidden overlay is brought up to date when shown
            self._show_rgb("blend", "overlay render", rgb, (1.0, 1.0), (0.0, 0.0))

    def sync_blend(self) -> None:
        blend, rgb = self.get("blend"), getattr(self, "_blend_rgb", None)
        if blend is not None and rgb is not None and blend.data is not rgb:
            blend.data = rgb

    def show_filtered(self, which: str, gray: np.ndarray, scale, translate) -> None:
        key = f"{which}_filtered"
        layer = self.get(key)
        if layer is None:
            layer = self._put(key, self._add(
                "add_image", gray, name=f"{which} · filtered", colormap="gray",
                contrast_limits=(0, 255),
                scale=scale, translate=translate))
        else:
            _set_geometry(layer, scale, translate)
            layer.data = gray
            visible = self.viewer.dims.ndisplay == 2
            if layer.visible != visible:
                layer.visible = visible

    def hide_filtered(self) -> None:
        for key in ("photo_filtered", "render_filtered"):
            if (layer := self.get(key)) is not None:
                layer.visible = False

    def show_correspondences(self, trial: Trial | None, outliers: bool, visible: bool) -> int:
        """Lines from photo keypoints to their render matches; returns how many are drawn."""
        layer = self.get("correspondences")
        corr = trial.correspondences if trial is not None else None
        if corr is None or len(corr.photo_points) == 0:
            if layer is not None:
                layer.visible = False
            return 0
        kind = np.where(corr.pose_inlier, 0, np.where(corr.feature_inlier, 1, 2))
        keep = kind < 2 if not outliers else np.ones(len(kind), bool)
        idx = np.flatnonzero(keep)
        if len(idx) == 0:  # only outliers, not asked for: nothing to draw
            if layer is not None:
                layer.visible = False
            return 0
        if len(idx) > MAX_LINES:  # an even sample: hundreds of lines hide the images
            keep = np.zeros(len(kind), bool)
            keep[idx[np.linspace(0, len(idx) - 1, MAX_LINES).round().astype(int)]] = True
        start = napari_from_pixels(corr.photo_points[keep])
        end = napari_from_pixels(corr.render_points[keep]) + np.array([0.0, self.offset])
        vectors = np.stack([start, end - start], axis=1)
        palette = np.array([_rgba(c) for c in CORRESPONDENCE_COLORS.values()])
        colors = palette[kind[keep]]
        width = max(1.0, self.width / 700)
        if layer is None:
            layer = self._put("correspondences", self._add(
                "add_vectors", vectors, name="correspondences", edge_color=colors, edge_width=width,
                vector_style="line", visible=visible))
        elif not visible:
            # napari does not re-slice a hidden layer: new data with fewer lines
            # than its stale view would break its colours. Updated when shown.
            layer.visible = False
        else:
            layer.visible = True
            layer.data = vectors
            layer.edge_color = colors
            layer.edge_width = width
        return int(keep.sum())

    def show_reference(self, reference: RenderResult) -> None:
        scale, translate = self.image_geometry(reference, right=True)
        layer = self._show_rgb("reference", "reference render", reference.rgb, scale, translate)
        layer.visible = True

    # -- pairs
    def pair_layers(self, ref_scale, ref_translate) -> tuple[Any, Any]:
        size = max(8.0, self.width / 70)
        out = []
        for key, name, scale, translate in (
            ("photo_pairs", "photo pairs", (1.0, 1.0), (0.0, 0.0)),
            ("reference_pairs", "reference pairs", ref_scale, ref_translate),
        ):
            layer = self.get(key)
            if layer is None:
                layer = self._put(key, self._add(
                    "add_points", np.zeros((0, 2)), name=name, size=size, border_color="black",
                    border_width=0.15, scale=scale, translate=translate,
                    text={"string": "{pair}", "color": "white", "size": 11,
                          "anchor": "upper_left", "translation": (-size / 2, size / 2)},
                    features={"pair": np.zeros(0, int)},
                ))
            else:
                layer.scale, layer.translate = scale, translate
            out.append(layer)
        return out[0], out[1]

    # -- 3D
    def show_surface(self, scene: Scene) -> None:
        cloud = getattr(scene, "is_cloud", False)  # a lidar scan: a Points layer
        data, kwargs, _ = (cloud_layer_data if cloud else surface_layer_data)(
            scene, name="outcrop")
        self.remove_surface()
        kwargs["visible"] = self.viewer.dims.ndisplay == 3
        kwargs["metadata"] = {**kwargs.get("metadata", {}), WORKBENCH_MODEL: True}
        self._put("surface", self._add("add_points" if cloud else "add_surface", data, **kwargs))

    def remove_surface(self) -> None:
        """Remove the model's layer (another model is opened)."""
        old = self.get("surface")
        if old is not None:
            self.viewer.layers.remove(old)

    def show_cameras(self, centers: np.ndarray, segments: np.ndarray, current: int,
                     marker_m: float = 5.0) -> None:
        visible = self.viewer.dims.ndisplay == 3
        pts = napari_from_world(centers) if len(centers) else np.zeros((0, 3))
        colors = np.array([_rgba(CURRENT_CAMERA_COLOR) if k == current else _rgba(CAMERA_COLOR)
                           for k in range(len(pts))]).reshape(-1, 4)
        layer = self.get("cameras")
        if layer is None:
            layer = self._put("cameras", self._add(
                "add_points", pts, name="cameras", ndim=3, size=marker_m,
                face_color=colors if len(pts) else CAMERA_COLOR,
                visible=visible))
        else:
            layer.data = pts
            layer.size = marker_m
            if len(pts):
                layer.face_color = colors
        seg = (napari_from_world(segments.reshape(-1, 3)).reshape(-1, 2, 3)
               if len(segments) else None)
        frusta = self.get("frusta")
        if seg is None:
            if frusta is not None:
                frusta.data = np.zeros((0, 2, 3))
            return
        vectors = np.stack([seg[:, 0], seg[:, 1] - seg[:, 0]], axis=1)
        if frusta is None:
            self._put("frusta", self._add(
                "add_vectors", vectors, name="view frusta", ndim=3, edge_color=CAMERA_COLOR,
                edge_width=0.6,
                vector_style="line", visible=visible))
        else:
            frusta.data = vectors

    def set_mode_3d(self, three_d: bool) -> None:
        for key in ("surface", "cameras", "frusta"):
            if (layer := self.get(key)) is not None:
                layer.visible = three_d
        for key in ("photo", "render", "blend", "photo_filtered", "render_filtered",
                    "correspondences", "reference", "photo_pairs", "reference_pairs"):
            layer = self.get(key)
            if layer is None:
                continue
            if three_d:
                layer.metadata["imgreg_visible_2d"] = layer.visible
                layer.visible = False
            else:
                layer.visible = layer.metadata.pop("imgreg_visible_2d", layer.visible)

    def layers_2d(self) -> list:
        return [layer for key in ("photo", "render") if (layer := self.get(key)) is not None]

    def layers_3d(self) -> list:
        return [layer for key in ("surface", "cameras") if (layer := self.get(key)) is not None]


def _set_geometry(layer, scale, translate) -> None:
    """Set a layer's scale and translate only when they change (each set
    makes napari recompute the scene's extent)."""
    if not np.allclose(layer.scale, scale):
        layer.scale = scale
    if not np.allclose(layer.translate, translate):
        layer.translate = translate


def _rgba(color: str) -> np.ndarray:
    return np.array(to_rgba(color), np.float32)


@dataclass
class _SaveProgress:
    """A step of a save in its worker (as :class:`~napari_imgreg.registration.pipeline.Progress`)."""

    done: int
    total: int

    @property
    def fraction(self) -> float:
        return self.done / max(self.total, 1)

    @property
    def message(self) -> str:
        return (f"{self.done} of {self.total} photo(s) written"
                + ("; writing the manifest…" if self.done >= self.total else "…"))


@dataclass
class _SaveInProgress:
    """A save of :meth:`WorkbenchController.save_workspace` under way."""

    steps: SaveAs
    dialog: Any  # ModalProgress
    release: Callable[[], None]  # ends the hold of the jobs' results


# -------------------------------------------------------------- controller
class WorkbenchController(QObject):
    """The workbench's Qt side for one viewer: it builds the :class:`Workspace`,
    shows it in napari layers, runs its jobs and relays its events (see the
    module docstring).

    The workspace's state is reachable here too (``scene``, ``photos``,
    ``current``, ``params``, ...) and its editing methods are wrapped, so a
    dock calls one object; an error worded for the user becomes a napari
    notification instead of an exception.
    """

    scene_changed = Signal()
    photos_changed = Signal()
    photo_changed = Signal()
    pose_changed = Signal(str)  # what changed it
    params_changed = Signal()
    trials_changed = Signal()
    trial_selected = Signal(int)
    render_shown = Signal(str)  # "preview" or "full"
    filters_shown = Signal(str)  # "photo" or "render"
    registration_started = Signal(str)  # "Run" or "Auto"
    registration_progress = Signal(float, str)
    registration_finished = Signal(object)  # Registration, or None when cancelled/failed
    reference_ready = Signal()
    pairs_changed = Signal()
    manual_finished = Signal(object)  # ManualSolution or None
    sun_changed = Signal()  # the current photo's sun or the sun-lit preview changed
    sun_estimated = Signal(object)  # SunEstimate, or None when it failed
    busy_changed = Signal()
    status = Signal(str)
    failed = Signal(str, str)  # job, one-line message
    accepted_changed = Signal(object)  # the photo accepted (or no longer)
    batch_started = Signal(int)  # Register all: photos to register
    batch_progress = Signal(float, str)  # fraction of the whole batch, message
    batch_photo_done = Signal(object)  # BatchStep, recorded
    batch_finished = Signal(object)  # BatchSummary (None when it failed)
    loading = Signal(str)  # what is being loaded ("" when done): the Scene tab's busy bar
    workspace_folder_changed = Signal()  # saved into, opened from, or released a folder

    def __init__(self, viewer: napari.viewer.Viewer, workspace: Workspace | None = None) -> None:
        super().__init__()
        # napari's process registers here too: keep its image buffers (see
        # _allocator; NAPARI_IMGREG_MALLOC=default opts out).
        tune_allocator()
        # The viewer itself, not a plugin proxy of it: the docks find this
        # controller by it, and its layers are added and looked up unproxied.
        viewer = real_viewer(viewer)
        self.viewer = viewer
        #: The state the docks show and edit (Qt-free).
        self.workspace = workspace if workspace is not None else Workspace()
        # A workspace made here is released (its folder's lock) with the docks;
        # a script's own one is left as it is.
        self._owns_workspace = workspace is None
        #: Every long job runs here.
        self.jobs = JobRunner(self)
        self.layers = _Layers(viewer)
        self.filter_preview = False
        self.show_outliers = False
        self.show_correspondences = True
        self.blend_opacity = 0.5
        self.blend_visible = False
        self.last_render: RenderResult | None = None
        #: Show the render relit for the photo's sun (when one is known).
        self.sun_preview = False
        #: What the shown render is: ("plain",) or ("sunlit", sun direction).
        self.shown_look: tuple = ()
        self._shown_full_pose: Pose | None = None
        self._closed = False
        self._docks = 0  # docks using this controller (see attach)
        #: A dock of ours in the viewer's window: the window a modal dialog blocks.
        self._window_anchor = None
        #: The save in progress (see save_workspace): its steps, dialog and hold.
        self._saving: _SaveInProgress | None = None
        self._pairs_busy = False  # the pair layers are being written: not an edit
        self._pairs_from_layers = False  # the workspace takes an edit of the pair layers
        self.latency: dict[str, float] = {}
        self._cameras_dirty = True
        self._surface_pending = False  # the model's layer is to be made (see _on_scene_changed)
        #: Seen from a pose: (viewpoint, radius) of the cameras left out (see fly_to_pose).
        self._hide_near: tuple[np.ndarray, float] | None = None
        self._reduced: dict[str, tuple] = {}  # filter preview: images at the match width
        #: The photo decoding ahead (see _prefetch_neighbours), when one runs.
        self._prefetching: threading.Thread | None = None
        self._asked: dict[str, float] = {}  # time of the latest request per job
        #: Width (pixels) of the photos' thumbnails a dock shows (the photos
        #: table): made in the worker that opens a workspace. None: none shown.
        self.thumbnail_width: int | None = None
        self._full_timer = QTimer(self)
        self._full_timer.setSingleShot(True)
        self._full_timer.setInterval(FULL_RENDER_DELAY_MS)
        self._full_timer.timeout.connect(lambda: self.request_render(full=True))
        # Parameters are edited in place by the docks: saved once the edits pause.
        self._params_timer = QTimer(self)
        self._params_timer.setSingleShot(True)
        self._params_timer.setInterval(PARAMS_SAVE_DELAY_MS)
        self._params_timer.timeout.connect(self._save_params)
        viewer.dims.events.ndisplay.connect(self._on_ndisplay)
        self._dims_bar = HeightSliderHider(viewer)
        self.jobs.busy_changed.connect(self.busy_changed.emit)
        self.jobs.status.connect(self.status.emit)
        self.jobs.failed.connect(self.failed.emit)
        ws = self.workspace
        self._followed = [
            (ws.scene_changed, self._on_scene_changed),
            (ws.photos_changed, self._on_photos_changed),
            (ws.photo_changed, self._on_photo_changed),
            (ws.pose_changed, self._pose_edited),
            (ws.params_changed, self._on_params_changed),
            (ws.trials_changed, self._on_trials_changed),
            (ws.trial_selected, self._on_trial_selected),
            (ws.reference_changed, self._on_reference_changed),
            (ws.pairs_changed, self._on_pairs_changed),
            (ws.sun_changed, self._on_sun_changed),
            (ws.accepted_changed, self.accepted_changed.emit),
            (ws.autosave_failed, self._on_autosave_failed),
        ]
        for event, handler in self._followed:
            event.connect(handler)

    # ------------------------------------------------------ the workspace
    @property
    def scene(self) -> Scene | None:
        return self.workspace.scene

    @property
    def scene_files(self) -> dict[str, str]:
        return self.workspace.scene_files

    @property
    def terrain(self) -> TerrainMap | None:
        return self.workspace.terrain

    @property
    def photos(self) -> list[PhotoState]:
        return self.workspace.photos

    @property
    def current(self) -> PhotoState | None:
        return self.workspace.current

    @property
    def params(self) -> RegistrationParams:
        return self.workspace.params

    @params.setter
    def params(self, params: RegistrationParams) -> None:
        self.workspace.set_params(params)

    # Workspace events: bring the layers up to date, then tell the docks.
    def _on_scene_changed(self) -> None:
        self.layers.clear_photos()
        if self.viewer.dims.ndisplay == 3:
            self.layers.show_surface(self.scene)
        else:
            # The old model goes now, with the photos' layers (in one batch,
            # when a workspace is opened over another); the new one is made later.
            self.layers.remove_surface()
            # Hidden in 2D: made on the event loop's next turn, after the
            # photo is shown — a workspace opening then freezes the window
            # twice briefly instead of once for both (busy until it is made).
            if not self._surface_pending:
                QTimer.singleShot(0, self._show_pending_surface)
            self._surface_pending = True
        self.scene_changed.emit()

    def _show_pending_surface(self) -> None:
        if not self._surface_pending:
            return
        self._surface_pending = False
        if not self._closed and self.scene is not None:
            self.layers.show_surface(self.scene)

    def _on_photos_changed(self) -> None:
        self.photos_changed.emit()
        self._update_cameras()

    def _on_photo_changed(self) -> None:
        """Show the new current photo, its pose's render, its pairs and trials."""
        ps = self.current
        self.layers.show_photo(ps)
        self.layers.set_camera(ps)
        self._shown_full_pose = None
        self.last_render = None
        if ps.reference is not None:
            # Made when missing: a workspace just opened brings its reference
            # (rendered again from its saved camera as it was read, in the worker).
            self.layers.show_reference(ps.reference)
        elif (ref := self.layers.get("reference")) is not None:
            ref.visible = False
        self._write_pair_layers()
        self._restyle_pairs()
        self.pairs_changed.emit()
        self.photo_changed.emit()
        self.pose_changed.emit("photo")
        self.trials_changed.emit()
        if ps.selected_trial is not None:
            self.select_trial(ps.selected_trial)
        else:
            self.layers.show_correspondences(None, False, False)
        self.request_render(full=False)  # quick first look (and warms the preview camera)
        self.request_render(full=True)
        self._update_cameras()
        if self.viewer.dims.ndisplay == 2:
            self.fit_2d()
        self._prefetch_neighbours()

    def _prefetch_neighbours(self) -> None:
        """Decode the photos before and after the current one in a background
        thread: stepping through the list then shows the next photo without
        decoding it on the GUI thread (0.1–0.3 s for a 12–20 MP JPEG).

        They count towards :data:`~napari_imgreg.io.photos.MAX_DECODED` (two),
        so at most the current photo and these two keep full pixels.
        """
        k = self.workspace.current_index
        if k is None or self._closed:
            return
        ahead = [self.photos[j].photo for j in (k + 1, k - 1) if 0 <= j < len(self.photos)]
        ahead = [photo for photo in ahead if photo.from_file and not photo.decoded]
        running = self._prefetching
        if not ahead or (running is not None and running.is_alive()):
            return  # one at a time: a quick run through the list leaves no queue behind

        def decode() -> None:
            for photo in ahead:
                if self._closed or self.current is None or self.current.photo is photo:
                    return  # shown meanwhile: show_photo decodes it (the photo's lock)
                try:
                    photo.image
                except InputError:
                    pass  # said when the photo is shown (a grey stand-in there)

        # A plain daemon thread, not a job: it is not work the user waits for
        # (no busy state, no progress bar), and a decode needs no cancel.
        self._prefetching = threading.Thread(target=decode, name="imgreg-prefetch", daemon=True)
        self._prefetching.start()

    def _on_params_changed(self) -> None:
        self.params_changed.emit()

    def _on_trials_changed(self) -> None:
        self.trials_changed.emit()

    def _on_trial_selected(self, index: int) -> None:
        self.redraw_correspondences()
        self.trial_selected.emit(index)

    def _on_reference_changed(self) -> None:
        ps = self.current
        if ps is None or ps.reference is None:
            return
        self.layers.show_reference(ps.reference)
        self.reference_ready.emit()

    def _on_pairs_changed(self) -> None:
        if not self._pairs_from_layers:  # an edit of the layers is shown already
            self._write_pair_layers()
        self._restyle_pairs()
        self.pairs_changed.emit()

    def _on_sun_changed(self, ps: PhotoState) -> None:
        if ps is self.current:
            self._sun_edited()

    # ------------------------------------------------------------ workers
    @property
    def busy(self) -> bool:
        """True while any job runs or waits (a render, a filter, a registration...)."""
        return self.jobs.busy or self._full_timer.isActive() or self._surface_pending

    def is_running(self, job: str) -> bool:
        return self.jobs.is_running(job)

    def _start(self, job: str, fn: Callable, *args, on_returned: Callable,
               on_yielded: Callable | None = None, progress: dict | None = None,
               on_failed: Callable | None = None, **kwargs):
        """Run ``fn`` in a napari thread worker named ``job`` (see :class:`JobRunner`)."""
        return self.jobs.start(job, fn, *args, on_returned=on_returned, on_yielded=on_yielded,
                               on_failed=on_failed, progress=progress, **kwargs)

    def _job(self, make: Callable[[], Job]) -> Job | None:
        """A workspace job, or None after telling the user why there is none."""
        try:
            return make()
        except WorkbenchError as exc:
            self.notify_error(str(exc))
            return None

    def notify_error(self, message: str) -> None:
        """Say what went wrong: in the status line and as a napari notification."""
        # napari is imported when needed: its import warns (pydantic) and is slow.
        from napari.utils.notifications import show_error

        self.status.emit(message)
        show_error(message)

    _notify_error = notify_error  # the 0.1 name

    def notify_warning(self, message: str) -> None:
        """Say what may be wrong: in the status line and as a napari warning."""
        from napari.utils.notifications import show_warning

        self.status.emit(message)
        show_warning(message)

    @property
    def closed(self) -> bool:
        return self._closed

    def attach(self, widget: QObject) -> None:
        """A dock uses this controller; when the last one is gone, it shuts down."""
        self._docks += 1
        widget.destroyed.connect(self._detach)
        if self._window_anchor is None and hasattr(widget, "window"):
            self._window_anchor = widget
            widget.destroyed.connect(self._forget_anchor)
        if self._dims_bar.anchor is None and hasattr(widget, "window"):
            self._dims_bar.anchor = widget

    def _forget_anchor(self, *_args) -> None:
        self._window_anchor = None

    def _detach(self, *_args) -> None:
        self._docks -= 1
        if self._docks <= 0:
            self.shutdown()

    def shutdown(self) -> None:
        """Stop timers and ignore late results (no dock shows this controller any more)."""
        if self._closed:
            return
        self._closed = True
        self._full_timer.stop()
        if self._params_timer.isActive():
            self._params_timer.stop()
            self._save_params()
        self.jobs.shutdown()
        if self._saving is not None:  # its worker stops at its next photo
            self._end_save(None)
        for event, handler in self._followed:  # the workspace may live on (a script's)
            event.disconnect(handler)
        if self._owns_workspace:
            # Everything is saved already; the folder may be opened again.
            self.workspace.detach()
        try:
            self.viewer.dims.events.ndisplay.disconnect(self._on_ndisplay)
        except (TypeError, ValueError, RuntimeError):  # pragma: no cover
            pass
        self._dims_bar.release()

    # -------------------------------------------------------------- scene
    def open_scene(self, mesh: str | Path, dem: str | Path | None = None,
                   georef: str | Path | None = None, photos: list | None = None) -> None:
        """Load a mesh (or a DSM as GeoTIFF/.asc), optionally a DEM and georeference,
        in a worker; then add ``photos``."""

        def done(value):
            if value is None:
                self.loading.emit("")
                return
            scene, terrain = value
            self.workspace.load_scene(scene, terrain,
                                      {"mesh": mesh, "dem": dem, "georef": georef})
            if not photos:
                self.loading.emit("")
            self.status.emit(f"opened {scene.name}: {size_text(scene)}"
                             + (", DEM" if scene.dem is not None else "")
                             + (f", {scene.georef.crs}" if scene.georef is not None else ""))
            for w in scene.warnings:
                self.status.emit(w)
            if photos:
                self.add_photos(photos)

        message = f"opening {Path(mesh).name} (reading the model, building its ray engine)…"
        self.status.emit(message)
        self.loading.emit(message)
        # pyproj is touched (georeference, DEM): in a thread Python owns.
        self._start("open scene", in_python_thread, _read_scene_warm, mesh, dem, georef,
                    on_returned=done, on_failed=lambda msg: self.loading.emit(""),
                    progress={"desc": f"Opening {Path(mesh).name}", "total": 0})

    def open_sample(self) -> None:
        """The generated sample outcrop with its DEM and its photos."""

        def done(folder):
            if folder is None:
                self.loading.emit("")
                return
            self.open_scene(folder / "outcrop.obj", dem=folder / "dem.tif",
                            photos=sorted(folder.glob("IMG_*.jpg")))

        message = ("generating the sample outcrop (the first time takes about half a "
                   "minute; later it is read back)…")
        self.status.emit(message)
        self.loading.emit(message)
        # total 0: napari shows a busy (indeterminate) bar in its activity dock.
        self._start("sample", in_python_thread, sample_scene, "small", on_returned=done,
                    on_failed=lambda msg: self.loading.emit(""),
                    progress={"desc": "Sample scene", "total": 0})

    # ----------------------------------------------------------- workspace
    @property
    def workspace_folder(self) -> Path | None:
        """The folder the workspace is saved into as it changes (None: not saved)."""
        return self.workspace.folder

    def _on_autosave_failed(self, message: str) -> None:
        self.notify_error(f"autosave failed (the work in the window is intact; the next "
                          f"change tries again): {message}")

    def params_edited(self) -> None:
        """A dock edited the parameters in place: saved once the edits pause."""
        if self.workspace.folder is not None:
            self._params_timer.start()

    def _save_params(self) -> None:
        self.workspace.flush_manifest()

    def save_workspace(self, folder: str | Path) -> Path | None:
        """Save the whole workspace into ``folder`` (a new ``*.imgreg`` folder)
        and keep saving every change there.

        The files are written in a worker, behind a dialog modal to the
        viewer's window that shows the photos written; meanwhile the window
        takes no input and what running jobs deliver (a registration's
        result, Register all's steps) waits (:func:`~._jobs.hold_results`):
        it is recorded once the folder is complete, and so saved there. When
        it is done, the status line says so and ``workspace_folder_changed``
        is emitted. A failure is one line (:meth:`notify_error`), and the
        workspace stays saved where it was.

        Parameters
        ----------
        folder : path-like
            ``.imgreg`` is added to a name without it (unless it is a
            workspace folder already).

        Returns
        -------
        Path or None
            The manifest the save writes (it exists once the save is done,
            see :attr:`saving`); None when the save could not start.
        """
        folder = Path(folder)
        if folder.suffix != ".imgreg" and not (folder / "workspace.json").exists():
            folder = folder.with_name(folder.name + ".imgreg")
        manifest = folder / "workspace.json"
        if self._saving is not None:
            self.notify_error(f"{self._saving.steps.folder.name} is being saved: wait for it.")
            return None
        if self.workspace.folder == Path(os.path.abspath(folder)):
            self.status.emit(f"{folder.name} is where the workspace is saved already: every "
                             "change is saved there as it happens")
            return manifest
        # A parameter edit waiting for its autosave goes where it was made.
        if self._params_timer.isActive():
            self._params_timer.stop()
            self._save_params()
        try:
            steps = self.workspace.begin_save(folder)
        except (InputError, OSError) as exc:
            self.notify_error(one_line(exc))
            return None
        from ._progress_dialog import ModalProgress  # Qt widgets: imported when needed

        total = steps.total
        dialog = ModalProgress(
            self._window_anchor, "Save workspace as",
            f"Saving {folder.name}: 0 of {total} photo(s) written…", total,
            hint="The window waits until the folder is complete; running jobs go on, and "
                 "what they find is recorded (and saved there) then.")
        self._saving = _SaveInProgress(steps, dialog, hold_results())
        dialog.show()
        self.status.emit(f"saving {folder.name}: {total} photo(s)…")

        def write():
            for done, total in steps.steps():
                yield _SaveProgress(done, total)
            return steps.folder  # (None would say it was cancelled)

        def written(progress):
            if self._saving is not None and self._saving.steps is steps:
                dialog.set_progress(progress.done, f"Saving {folder.name}: {progress.message}")

        # Not held: it is the job the others wait for.
        self._start("save workspace", write, held=False, notify=False,
                    on_returned=lambda value: self._end_save(
                        steps, finished=value is not None),
                    on_yielded=written,
                    on_failed=lambda message: self._end_save(steps, error=message))
        return manifest

    @property
    def saving(self) -> bool:
        """True while :meth:`save_workspace` writes a folder."""
        return self._saving is not None

    def _end_save(self, steps: SaveAs | None, finished: bool = False, error: str = "") -> None:
        """The end of a save: bind the workspace to its folder (``finished``) or
        let the folder go, close its dialog, deliver the jobs' results held."""
        saving = self._saving
        if saving is None or (steps is not None and saving.steps is not steps):
            return
        self._saving = None
        finished = finished and not self._closed
        try:
            try:
                if finished:
                    saving.steps.finish()
                else:
                    saving.steps.abandon()
            finally:
                saving.dialog.finish()
            if finished:
                self.status.emit(f"saved {saving.steps.folder.name}: every change is now saved "
                                 "there as it happens")
                self.workspace_folder_changed.emit()
            elif error:
                self.notify_error(error)
        finally:
            # Last: what they record is saved in the folder just written.
            saving.release()

    def open_workspace(self, folder: str | Path) -> None:
        """Open a workspace folder in a worker (its model, photos, poses,
        trials, control points and drawings), then show it here and keep
        saving it as it changes."""
        folder = Path(folder)
        if self.workspace.folder is not None and self.workspace.folder == folder.resolve():
            self.status.emit(f"{folder.name} is open already")
            return
        if self.is_running("register all"):
            self.notify_error("Cancel Register all before opening another workspace.")
            return

        def done(opened):
            self.loading.emit("")
            if opened is None:
                return
            self.jobs.cancel("registration", "manual", "sun", "reference")
            # The old workspace's layers (its photos, projections, model) go as one batch.
            with layers_batched(self.viewer) if self.layers.has_photos() else nullcontext():
                self.workspace.adopt(opened)
            ws = self.workspace
            self.status.emit(f"opened {folder.name}: {len(ws.photos)} photo(s), "
                             f"{sum(ws.photo_status(p) in ('registered', 'accepted') for p in ws.photos)}"
                             " registered; every change is saved there as it happens")
            for problem in ws.open_problems:
                if problem in ws.open_warnings:  # opened, but a file changed since its work
                    from napari.utils.notifications import show_warning

                    show_warning(f"{folder.name}: {problem}")
                else:
                    self.notify_error(f"{folder.name}: {problem}")
            self.workspace_folder_changed.emit()

        message = f"opening the workspace {folder.name} (model, photos, their work)…"
        self.status.emit(message)
        self.loading.emit(message)
        # pyproj is touched (georeference, DEM): in a thread Python owns.
        self._start("open workspace", in_python_thread, _open_workspace_warm, folder,
                    self.thumbnail_width,
                    on_returned=done, on_failed=lambda msg: self.loading.emit(""),
                    progress={"desc": f"Opening {folder.name}", "total": 0})

    # ------------------------------------------------------------- campaign
    def select_next(self, step: int = 1) -> None:
        """The next (``step`` 1) or previous (-1) photo, going round."""
        self.workspace.select_next(step)

    def next_needing_attention(self) -> int | None:
        """Go to the next photo that needs attention (see
        :meth:`~napari_imgreg.workspace.Workspace.needs_attention`); returns its index."""
        k = self.workspace.next_needing_attention()
        if k is None:
            self.status.emit("no photo needs attention: every photo is registered "
                             "(good or better) or accepted")
            return None
        ps = self.photos[k]
        if ps is not self.current:
            self.select_photo(k)
        self.status.emit(f"{ps.name}: {self.workspace.photo_status(ps)}"
                         + (f" ({ps.registration.grade})" if ps.registration else "")
                         + " — needs attention")
        return k

    def accept(self) -> None:
        """Accept the current photo's pose and go to the next photo needing attention."""
        ps = self.current
        if not self.workspace.accept():
            self.notify_error("Load a scene and a photo first.")
            return
        self.status.emit(f"{ps.name}: pose accepted")
        k = self.workspace.next_needing_attention()
        if k is not None and self.photos[k] is not ps:
            self.select_photo(k)

    def register_all(self, auto: bool = True, redo: bool = False) -> None:
        """Register every photo not yet registered, one after the other, in a
        background worker (progress, Cancel; a new Register all resumes)."""
        if self.is_running("register all"):
            return
        if self.is_running("registration"):
            self.notify_error("A registration is running: wait for it, or cancel it.")
            return
        cancelled = self.jobs.cancel_token("register all")
        job = self._job(lambda: self.workspace.register_all_job(auto, redo, cancelled=cancelled))
        if job is None:
            return
        todo = len(self.workspace.photos_to_register(redo))
        if todo == 0:
            self.status.emit("Register all: every photo is registered already")
            self.batch_finished.emit(BatchSummary(skipped=len(self.photos)))
            return

        def yielded(item):
            if isinstance(item, BatchStep):
                self.workspace.record_batch_step(item)
                reg = item.registration
                what = (outcome_text(reg.status, reg.grade, reg.q) if reg is not None
                        else f"failed: {item.error}")
                self.status.emit(f"{item.photo.name} ({item.index + 1}/{item.total}): {what}")
                self.batch_photo_done.emit(item)
            else:
                self.batch_progress.emit(float(item.fraction), item.message)

        def done(summary):
            if summary is None:  # cancelled before the first yield
                summary = BatchSummary(total=todo, cancelled=True)
            said = (f"Register all {'cancelled' if summary.cancelled else 'done'}: "
                    f"{summary.registered} of {summary.done} registered"
                    + (f", {summary.skipped} skipped (done before)" if summary.skipped else "")
                    + (f"; {summary.total - summary.done} left: Register all resumes"
                       if summary.cancelled else ""))
            self.status.emit(said)
            self.batch_progress.emit(summary.done / max(summary.total, 1), said)
            self.batch_finished.emit(summary)

        self.batch_started.emit(todo)
        self.status.emit(f"Register all: {todo} photo(s) to register…")
        self._start("register all", job.run, on_returned=done, on_yielded=yielded,
                    on_failed=lambda msg: self.batch_finished.emit(None),
                    progress={"total": 100, "desc": job.description})

    def cancel_register_all(self) -> None:
        """Stop Register all within the running photo (the finished ones stay)."""
        if self.is_running("register all"):
            self.jobs.cancel("register all")
            self.status.emit("cancelling Register all…")

    # ------------------------------------------------------------- photos
    def add_photos(self, paths: list) -> None:
        """Load photos and their priors (sensor record, else EXIF/XMP) in a worker."""
        try:
            scene = self.workspace.require_scene()
        except WorkbenchError as exc:
            self.notify_error(str(exc))
            return
        paths = [Path(p) for p in paths]

        def done(value):
            self.loading.emit("")
            if value is None:
                return
            loaded, errors = value
            self.workspace.add_loaded_photos(loaded)
            self.status.emit(f"{len(loaded)} photo(s) loaded")
            for msg in errors:
                self.notify_error(msg)

        message = f"loading {len(paths)} photo(s) and their priors…"
        self.status.emit(message)
        self.loading.emit(message)
        self._start("load photos", in_python_thread, read_photos, paths, scene,
                    on_returned=done, on_failed=lambda msg: self.loading.emit(""),
                    progress={"desc": f"Loading {len(paths)} photo(s)", "total": 0})

    def select_photo(self, index: int) -> None:
        """Make a photo current: show it, its pose's render, its pairs and trials."""
        self.workspace.select_photo(index)

    def photo_layer(self):
        """The current photo's Image layer (None before a photo is shown)."""
        return self.layers.get("photo")

    # --------------------------------------------------------------- pose
    def set_pose(self, pose: Pose, label: str, continuing: bool = False) -> None:
        """Change the current photo's pose (an undoable edit unless ``continuing``)."""
        self.workspace.set_pose(pose, label, continuing=continuing)

    def nudge(self, label: str = "nudge", **amounts: float) -> None:
        """Turn/move the camera by small amounts (see :func:`~napari_imgreg.adjust.nudge_pose`)."""
        self.workspace.nudge(label, **amounts)

    def move_on_map(self, x: float, y: float, continuing: bool = False,
                    height: float | None = None) -> bool:
        """Move the camera to map point (x, y), keeping its height above the terrain."""
        try:
            return self.workspace.move_on_map(x, y, continuing=continuing, height=height)
        except WorkbenchError as exc:
            self.notify_error(str(exc))
            return False

    def turn_toward(self, x: float, y: float) -> None:
        self.workspace.turn_toward(x, y)

    def height_above_ground(self) -> float | None:
        return self.workspace.height_above_ground()

    def finish_drag(self) -> None:
        """A drag ended: render at full resolution now."""
        self._full_timer.stop()
        self.request_render(full=True)

    def undo(self) -> None:
        self.workspace.undo()

    def redo(self) -> None:
        self.workspace.redo()

    def reset_to_prior(self) -> None:
        self.workspace.reset_to_prior()

    def _pose_edited(self, label: str) -> None:
        """The current pose changed: the reduced render now, the full one when
        the edits stop; the cameras are redrawn in 3D, not on every nudge."""
        if self.current is not None:
            self.layers.set_camera(self.current)
        self.request_render(full=False)
        self._full_timer.start()
        self._cameras_dirty = True
        self.pose_changed.emit(label)

    def save_record(self) -> Path | None:
        """Save the current pose (and a solved camera) into the photo's sensor record."""
        try:
            path = self.workspace.save_record()
        except (InputError, OSError) as exc:
            self.notify_error(one_line(exc))
            return None
        if path is not None:
            self.status.emit(f"pose saved to {path.name}")
        return path

    # ------------------------------------------------------------- render
    def request_render(self, full: bool, since: float | None = None) -> None:
        """Render the current pose in a worker, reduced (``full=False``, shown at
        the photo's size) or at full resolution; a request made while one runs
        waits, and a newer one replaces it."""
        ps, scene = self.current, self.scene
        if ps is None or scene is None or self._closed:
            return
        job = "render" if full else "preview"
        self._asked[job] = time.perf_counter()
        if self.jobs.defer(job, lambda t=time.perf_counter(): self.request_render(full, t)):
            return
        pose, intr = ps.pose, ps.intrinsics
        scale = 1.0 if full else match_scale(intr.width, PREVIEW_WIDTH)
        t0 = since if since is not None else time.perf_counter()
        look = self.render_look(ps)

        def job_fn():
            if look[0] == "sunlit":
                # As the pipeline renders for sun-lit matching (a view: no shading share).
                result = render_sunlit(scene, intr, pose, np.asarray(look[1]), scale=scale,
                                       survey_sun_dir=scene.survey_sun, with_share=False)
            else:
                result = render(scene, intr, pose, scale=scale)
            rgb = result.rgb
            if scale < 1.0:  # shown at the photo's size: the layers keep their geometry
                rgb = cv2.resize(rgb, (intr.width, intr.height), interpolation=cv2.INTER_LINEAR)
            return result, rgb

        def done(value):
            if value is None or self.current is not ps or look != self.render_look(ps):
                return  # another photo, or the light changed: its own render follows
            result, rgb = value
            current = ps.pose
            if full:
                if result.cam_from_world is not current:
                    return  # the pose moved on; its own full render follows
                self._shown_full_pose = current
                self.last_render = result
            elif self._shown_full_pose is current:
                return  # the full render of this pose is already shown
            self.layers.show_render(rgb, self.blend_opacity, self.blend_visible, mode=look[0])
            self.shown_look = look
            # Shown this long after the latest edit (t0: the oldest one served).
            self.latency[job] = time.perf_counter() - max(t0, self._asked.get(job, t0))
            if full:
                if self.filter_preview:
                    self.request_filter_preview("render", result)
                if self._cameras_dirty and self.viewer.dims.ndisplay == 3:
                    self._update_cameras()
            self.render_shown.emit("full" if full else "preview")

        self._start(job, job_fn, on_returned=done)

    # ------------------------------------------------------------ filters
    def set_filter_preview(self, on: bool) -> None:
        self.filter_preview = bool(on)
        if on:
            self.request_filter_preview("photo")
            self.request_filter_preview("render")
        else:
            self.layers.hide_filtered()

    def request_filter_preview(self, which: str, rendered: RenderResult | None = None,
                               since: float | None = None) -> None:
        """Filter the photo or the shown render (full image) in a worker and show it."""
        ps = self.current
        if ps is None or not self.filter_preview or self._closed:
            return
        job = f"filter {which}"
        self._asked[job] = time.perf_counter()
        if self.jobs.defer(job, lambda t=time.perf_counter(): self.request_filter_preview(
                which, since=t)):
            return
        photo = ps.photo
        if which == "photo":
            # The photo's pixels are read in the worker: a photo not decoded
            # yet decodes there, not on the GUI thread.
            image, mask = None, None
            params = replace(self.params.photo_filters)
        else:
            rendered = rendered or self.last_render
            if rendered is None:
                return
            image, mask = rendered.rgb, rendered.mask
            params = replace(self.params.render_filters)
        width = self.params.match_width
        t0 = since if since is not None else time.perf_counter()
        cache = self._reduced

        def job_fn():
            source = photo.image if which == "photo" else image
            # The reduced image does not change while a slider moves: reduce once.
            key = (which, id(source), width)
            if cache.get(which, (None,))[0] != key:
                cache[which] = (key, *reduce_for_matching(source, width, mask))
            _, small, small_mask = cache[which]
            return apply_filters(small, params, mask=small_mask)

        def done(gray):
            if gray is None or self.current is not ps or not self.filter_preview:
                return
            geometry = self.layers.image_geometry(gray, right=which != "photo")
            self.layers.show_filtered(which, gray, *geometry)
            # Shown this long after the latest edit (t0: the oldest one served).
            self.latency[job] = time.perf_counter() - max(t0, self._asked.get(job, t0))
            self.filters_shown.emit(which)

        self._start(job, job_fn, on_returned=done)

    def filters_edited(self, which: str) -> None:
        """The photo's or the render's filter parameters changed."""
        if self.filter_preview:
            self.request_filter_preview(which)

    # ------------------------------------------------------- registration
    def run_registration(self, auto: bool) -> None:
        """Register the current photo from its current pose: one trial (Run) or
        trials adapted by the rules (Auto), in a worker with progress and Cancel."""
        if self.is_running("registration"):
            return
        if self.is_running("register all"):
            self.notify_error("Register all is running: wait for it, or cancel it.")
            return
        cancelled = self.jobs.cancel_token("registration")
        job = self._job(lambda: self.workspace.registration_job(auto, cancelled=cancelled))
        if job is None:
            return
        ps, kind = job.photo, "Auto" if auto else "Run"

        def progress(p):
            self.registration_progress.emit(float(p.fraction), p.message)

        def done(reg):
            if reg is None:
                self.registration_progress.emit(0.0, "cancelled")
                self.registration_finished.emit(None)
                return
            if reg.registered and ps is self.current:
                self.set_blend(visible=True)  # the docks see it with the new pose
            job.apply(reg)
            secs = reg.timings_s.get("total", 0.0)
            self.status.emit(f"{ps.name}: {outcome_text(reg.status, reg.grade, reg.q)}, "
                             f"after {len(reg.trials)} trial(s) in {secs:.1f} s")
            self.registration_progress.emit(1.0, outcome_text(reg.status, reg.grade, reg.q))
            self.registration_finished.emit(reg)

        self.registration_started.emit(kind)
        self.status.emit(f"{kind}: registering {ps.name}…")
        self._start("registration", job.run, on_returned=done, on_yielded=progress,
                    on_failed=lambda msg: self.registration_finished.emit(None),
                    progress={"total": 100, "desc": job.description})

    def registration_prior(self, ps: PhotoState | None = None) -> Prior:
        """The prior a registration of the photo starts from (see
        :meth:`Workspace.registration_prior`)."""
        return self.workspace.registration_prior(ps)

    def cancel_registration(self) -> None:
        """Stop the running registration (or manual scoring) at its next step."""
        self.jobs.cancel("registration", "manual")  # polled by the pipeline between steps
        self.status.emit("cancelling…")

    # -------------------------------------------------------------- trials
    def select_trial(self, index: int) -> None:
        """Show a trial's metrics and correspondences (does not change the pose)."""
        self.workspace.select_trial(index)

    def redraw_correspondences(self) -> None:
        rec = self.workspace.selected_trial()
        if rec is not None:
            self.layers.show_correspondences(rec.trial, self.show_outliers,
                                             self.show_correspondences)

    def restore_trial(self, index: int) -> None:
        """Go back to a trial: its pose (or its start when it found none) and its parameters."""
        rec = self.workspace.restore_trial(index)
        if rec is not None:
            self.status.emit(f"restored trial {index + 1} ({rec.label})")

    def _keep_run_settings(self, params: RegistrationParams) -> RegistrationParams:
        return self.workspace.keep_run_settings(params)

    def suggestion(self, index: int | None = None):
        """The first rule that fires for a trial (default: the selected one), or None."""
        return self.workspace.suggestion(index)

    def apply_suggestion(self, index: int | None = None) -> bool:
        """Take the selected trial's parameters with the rule's adaptation applied."""
        hit = self.workspace.apply_suggestion(index)
        if hit is None:
            return False
        self.status.emit(f"parameters adapted (rule {hit.rule}): {hit.adaptation}")
        return True

    # ----------------------------------------------------------------- sun
    def render_look(self, ps: PhotoState | None = None) -> tuple:
        """How the render of the photo is lit: ("sunlit", its sun as a tuple)
        with the sun-lit preview on and a sun known, else ("plain",)."""
        ps = ps if ps is not None else self.current
        sun = ps.sun if ps is not None and self.sun_preview else None
        return ("plain",) if sun is None else ("sunlit", tuple(float(v) for v in sun))

    def convergence_deg(self, ps: PhotoState | None = None) -> float:
        """Meridian convergence at the photo's prior camera, degrees (see
        :meth:`Workspace.convergence_deg`)."""
        return self.workspace.convergence_deg(ps)

    def sun_angles(self, ps: PhotoState | None = None) -> tuple[float, float] | None:
        """The photo's sun as (azimuth from TRUE north, elevation), degrees; None: unknown."""
        return self.workspace.sun_angles(ps)

    def set_sun(self, direction, source: str = "hand setting") -> None:
        """Override the current photo's sun (unit vector toward it, local frame)."""
        self.workspace.set_sun(direction, source)

    def set_sun_angles(self, azimuth_true_deg: float, elevation_deg: float,
                       source: str = "hand setting") -> None:
        """Set the current photo's sun by its azimuth from TRUE north and its elevation."""
        self.workspace.set_sun_angles(azimuth_true_deg, elevation_deg, source)

    def reset_sun(self) -> None:
        """Back to the prior's sun (capture time or sensor record)."""
        self.workspace.reset_sun()

    def set_sun_preview(self, on: bool) -> None:
        """Show the render relit for the photo's sun instead of as textured."""
        on = bool(on)
        if on == self.sun_preview:
            return
        self.sun_preview = on
        self.sun_changed.emit()
        if self.current is not None and self.current.sun is None and on:
            self.status.emit("sun-lit preview: this photo's sun is unknown; set it, or read "
                             "it from the photo")
        self._shown_full_pose = None
        self.request_render(full=False)
        self.request_render(full=True)

    def _sun_edited(self) -> None:
        self.sun_changed.emit()
        if self.sun_preview:  # relit quickly, then at full resolution when the edits stop
            self._shown_full_pose = None
            self.request_render(full=False)
            self._full_timer.start()

    def estimate_sun(self) -> None:
        """Read the current photo's sun from its light and shade against a render
        from the current pose (in a worker); the result becomes its sun."""
        if self.is_running("sun"):
            return
        job = self._job(self.workspace.sun_estimate_job)
        if job is None:
            return
        ps = job.photo

        def done(est):
            if est is None:
                self.sun_estimated.emit(None)
                return
            job.apply(est)
            az, el = self.sun_angles(ps)
            weak = ("; low confidence: the pose may be off or the light flat — compare the "
                    "sun-lit preview with the photo" if est.confidence < 0.3 else "")
            self.status.emit(f"{ps.name}: sun read from the photo: azimuth {az:.1f}° (true), "
                             f"elevation {el:.1f}°, ±{est.spread_deg:.0f}°{weak}")
            self.sun_estimated.emit(est)

        self._start("sun", job.run, on_returned=done,
                    on_failed=lambda m: self.sun_estimated.emit(None),
                    progress={"desc": job.description})

    # -------------------------------------------------------------- manual
    def make_reference(self, source: str = "pose") -> None:
        """Render the reference image for manual pairs: from the current pose, or
        from the current 3D view (``source="view"``) of the napari camera."""
        if self.current is None or self.scene is None:
            self.notify_error("Load a scene and a photo first.")
            return
        intr = pose = None
        if source == "view":
            if self.viewer.dims.ndisplay != 3:
                self.notify_error(
                    "Switch to the 3D view and fly to a viewpoint like the photo's first.")
                return
            intr, pose = self.camera_from_3d_view()
        job = self._job(lambda: self.workspace.reference_job(intr, pose, source))
        if job is None:
            return

        def done(result):
            if result is None or self.current is not job.photo:
                return
            if self.viewer.dims.ndisplay == 3:
                self.show_2d()
            job.apply(result)
            where = "3D view" if source == "view" else "current pose"
            kept = len(job.photo.photo_points_px)
            # The old reference's picks went; the photo's stay, waiting for partners.
            points = "point 1" if kept == 1 else f"points 1–{kept}"
            then = (f" click {points} again on the new reference, in order (the photo's "
                    "picks stay; Clear to start afresh)" if kept else
                    " pick the same points on the photo and on the reference")
            self.status.emit(f"reference rendered from the {where}:{then}")

        self._start("reference", job.run, on_returned=done, progress={"desc": job.description})

    def camera_from_3d_view(self) -> tuple[Intrinsics, Pose]:
        """The camera that sees what the 3D view shows (photo's size and focal length)."""
        ps = self.current
        cam = self.camera
        visible = self.canvas_px() / cam.zoom
        intr = ps.intrinsics
        return camera_from_view(
            world_from_napari(np.asarray(cam.center, float)),
            world_from_napari(np.asarray(cam.view_direction, float)),
            world_from_napari(np.asarray(cam.up_direction, float)),
            visible_height=visible, width=intr.width, height=intr.height,
            fov_deg=cam.perspective or None, intrinsics=intr,
        )

    def pair_layers(self):
        """The two Points layers of the control points (photo, reference), made when missing."""
        ps = self.current
        if ps is not None and ps.reference is not None:
            scale, translate = self.layers.image_geometry(ps.reference, right=True)
        else:
            scale, translate = (1.0, 1.0), (0.0, self.layers.offset)
        photo, ref = self.layers.pair_layers(scale, translate)
        for layer in (photo, ref):
            if not layer.metadata.get("imgreg_connected"):
                layer.events.data.connect(self._on_pairs_data)
                # napari's paste adds points without a data event: the picks
                # and the workspace would part. A pasted pick means nothing
                # (the same pixel again, or a photo pixel on the reference).
                from app_model.types import KeyCode, KeyMod

                layer.bind_key(KeyMod.CtrlCmd | KeyCode.KeyV, self._refuse_paste,
                               overwrite=True)
                layer.metadata["imgreg_connected"] = True
        return photo, ref

    def _refuse_paste(self, layer=None) -> None:
        """Ctrl+V on a pair layer: say how pairs are made instead of pasting."""
        self.status.emit("Pairs are not pasted: click the point on the photo, then the same "
                         "point on the reference (drag a point to move it).")

    def start_picking(self) -> None:
        """Put the photo's pair layer in add mode; clicks alternate photo → reference."""
        photo, ref = self.pair_layers()
        target = photo if len(photo.data) <= len(ref.data) else ref
        target.selected_data = set()  # Delete must not take a pair picked earlier
        self.viewer.layers.selection.active = target
        target.mode = "add"

    def pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """Complete pairs: photo pixels (N, 2) and reference pixels (N, 2), (x, y)."""
        return self.workspace.pairs()

    def pair_points_3d(self) -> tuple[np.ndarray, np.ndarray]:
        """3D points under the reference picks (N, 3) and whether each has one."""
        return self.workspace.pair_points_3d()

    def delete_pair(self, index: int) -> None:
        self.workspace.remove_pair(index)

    def clear_pairs(self) -> None:
        self.workspace.clear_pairs()

    def _on_pairs_data(self, event) -> None:
        """A pair layer was edited in the viewer: keep pairs matched, tell the workspace."""
        # napari is imported here, when a layer already exists.
        from napari.layers.base._base_constants import ActionType

        if self._pairs_busy:
            return
        action = getattr(event, "action", None)
        if action not in (ActionType.ADDED, ActionType.REMOVED, ActionType.CHANGED):
            return
        photo, ref = self.pair_layers()
        source = event.source
        other = ref if source is photo else photo
        self._pairs_busy = True
        try:
            if action == ActionType.REMOVED:
                # Deleting a point deletes its pair, so numbering stays matched.
                idx = [i for i in (event.data_indices or ()) if 0 <= i < len(other.data)]
                if idx:
                    other.data = np.delete(np.asarray(other.data), idx, axis=0)
            elif action == ActionType.ADDED and source.mode == "add":
                # Alternate: the next click goes to the image that lacks its partner.
                if len(photo.data) > len(ref.data):
                    nxt = ref
                elif len(ref.data) > len(photo.data):
                    nxt = photo
                else:
                    nxt = photo
                if nxt is not source:
                    # napari selects each added point, and Delete removes the
                    # active layer's selection: left selected, the partner of
                    # the last pair would go (with its pair) when the user
                    # deletes a mis-click just made on the other image.
                    nxt.selected_data = set()
                    self.viewer.layers.selection.active = nxt
                    nxt.mode = "add"
        finally:
            self._pairs_busy = False
        self._pairs_from_layers = True
        try:
            self.workspace.set_pair_points(pixels_from_napari(np.asarray(photo.data, float)),
                                           pixels_from_napari(np.asarray(ref.data, float)))
        finally:
            self._pairs_from_layers = False

    def _write_pair_layers(self) -> None:
        """Show the current photo's picks in the pair layers (made when needed)."""
        ps = self.current
        if ps is None:
            return
        if (self.layers.get("photo_pairs") is None and not len(ps.photo_points_px)
                and ps.reference is None):
            return
        photo, ref = self.pair_layers()
        self._pairs_busy = True
        try:
            photo.data = np.ascontiguousarray(napari_from_pixels(ps.photo_points_px))
            ref.data = np.ascontiguousarray(napari_from_pixels(ps.reference_points_px))
        finally:
            self._pairs_busy = False
        # Without its reference render (not made again since an older workspace
        # was opened) a reference pick has no image to sit on: kept, not drawn
        # over the render from the pose. (Hidden, not emptied: an edit of the
        # photo's picks keeps them.)
        shown = ps.reference is not None
        if self.viewer.dims.ndisplay == 3:
            ref.metadata["imgreg_visible_2d"] = shown
        elif ref.visible != shown:
            ref.visible = shown

    def _restyle_pairs(self) -> None:
        """Number and colour the picks: pair k alike on the photo and the reference."""
        if self.layers.get("photo_pairs") is None or self.layers.get("reference_pairs") is None:
            return
        photo, ref = self.pair_layers()
        self._pairs_busy = True
        try:
            for layer in (photo, ref):
                n = len(layer.data)
                numbers = np.arange(1, n + 1)
                layer.features = {"pair": numbers}
                if n:
                    layer.face_color = np.array([_rgba(PAIR_COLORS[k % len(PAIR_COLORS)])
                                                 for k in range(n)])
                layer.feature_defaults = {"pair": n + 1}
                layer.refresh_text()
        finally:
            self._pairs_busy = False

    def solve_manual(self, solve_focal: bool = False) -> None:
        """Solve the photo's pose from the pairs and score it, in a worker."""
        cancelled = self.jobs.cancel_token("manual")
        job = self._job(lambda: self.workspace.manual_job(solve_focal, cancelled=cancelled))
        if job is None:
            return
        ps = job.photo

        def done(value):
            if value is None:
                self.manual_finished.emit(None)
                return
            sol, trial = value
            if sol.ok and ps is self.current:
                self.set_blend(visible=True)  # the docks see it with the new pose
            job.apply(value)
            if not sol.ok:
                self.notify_error(f"manual registration: {sol.reason}")
                self.manual_finished.emit(sol)
                return
            focal = f", focal {sol.intrinsics.fx:.1f} px" if sol.focal_solved else ""
            self.status.emit(f"manual pose from {sol.n_inliers}/{len(sol.inliers)} pairs: RMS "
                             f"{sol.rms_px:.2f} px{focal}; {trial.grade} (Q = {trial.q:.2f})")
            self.manual_finished.emit(sol)

        self._start("manual", job.run, on_returned=done,
                    on_failed=lambda m: self.manual_finished.emit(None),
                    progress={"desc": job.description})

    # --------------------------------------------------------------- views
    @property
    def camera(self):
        """The viewer's camera model (``viewer.scene.camera`` from napari 0.9 on)."""
        return viewer_camera(self.viewer)

    def canvas_px(self) -> float:
        """The canvas' smaller side, pixels."""
        canvas = getattr(self.viewer, "canvas", None)
        size = canvas.size if canvas is not None else (600, 800)
        return float(np.min(size))

    def _on_ndisplay(self, event=None) -> None:
        three_d = self.viewer.dims.ndisplay == 3
        if three_d:
            self._show_pending_surface()
        elif self._hide_near is not None:  # back in 2D: every camera next time
            self._hide_near = None
            self._cameras_dirty = True
        if three_d and self._cameras_dirty:
            self._update_cameras()
        self.layers.set_mode_3d(three_d)

    def show_3d(self, from_pose: bool = False) -> None:
        """The model and the cameras in 3D: seen obliquely, facing the outcrop
        as the cameras do (:meth:`overview_direction`), or from the current pose."""
        if not (from_pose and self.current is not None) and self._hide_near is not None:
            self._hide_near = None  # every camera again
            self._cameras_dirty = True
        if from_pose and self.current is not None:
            self.fly_to_pose()
            return
        self.viewer.dims.ndisplay = 3
        if self.layers.layers_3d():
            if self._cameras_dirty:
                self._update_cameras()
            view = self.overview_direction()
            if view is not None:
                self.camera.set_view_direction(tuple(napari_from_world(view)),
                                               tuple(napari_from_world(np.array([0., 0., 1.]))))
            self.viewer.fit_to_view(layers=self.layers.layers_3d())

    def overview_direction(self) -> np.ndarray | None:
        """The direction (model frame, unit) "3D: model and cameras" looks in:
        the cameras' mean heading, :data:`OVERVIEW_DIP_DEG` down — facing the
        outcrop obliquely, where straight down sees a cliff edge-on. None
        without photos."""
        return overview_direction([ps.pose for ps in self.photos])

    def show_2d(self) -> None:
        if self._hide_near is not None:
            self._hide_near = None
            self._cameras_dirty = True
        self.viewer.dims.ndisplay = 2
        self.fit_2d()

    def fit_2d(self) -> None:
        """Fit the photo and the render side by side to the canvas."""
        if self.viewer.dims.ndisplay != 2 or not self.layers.width:
            return
        h, w = self.layers.height, self.layers.offset + self.layers.width
        canvas = getattr(self.viewer, "canvas", None)
        fit_camera_2d(self.camera, (-0.5, -0.5), (h - 0.5, w - 0.5),
                      canvas.size if canvas is not None else (600, 800))

    def fly_to_pose(self) -> None:
        """Set the 3D view to look from the current photo's pose."""
        ps = self.current
        if ps is None:
            return
        depth = 50.0
        if self.last_render is not None:
            d = self.last_render.depth
            if np.isfinite(d).any():
                depth = float(np.nanmedian(d))
        # Cameras about the viewpoint (its own among them) would fill the view.
        self._hide_near = (np.asarray(ps.pose.center, float), NEAR_CAMERA_HIDE * depth)
        self._cameras_dirty = True
        if self.viewer.dims.ndisplay != 3:
            self.viewer.dims.ndisplay = 3  # the cameras are drawn as it switches
        else:
            self._update_cameras()
        view = view_from_camera(ps.intrinsics, ps.pose, depth, self.canvas_px())
        cam = self.camera
        cam.perspective = view["fov_deg"]
        cam.center = tuple(napari_from_world(view["center"]))
        cam.set_view_direction(tuple(napari_from_world(view["view_direction"])),
                               tuple(napari_from_world(view["up_direction"])))
        cam.zoom = view["zoom"]

    def _update_cameras(self) -> None:
        if self.scene is None or not self.photos:
            return
        if self.viewer.dims.ndisplay != 3:
            # 3D-only layers: made or brought up to date when the 3D view is
            # shown (_on_ndisplay), not while a workspace opens in 2D.
            self._cameras_dirty = True
            return
        photos = list(self.photos)
        if self._hide_near is not None:  # seen from a pose: not those about it
            eye, radius = self._hide_near
            photos = [ps for ps in photos
                      if np.linalg.norm(np.asarray(ps.pose.center, float) - eye) > radius]
        centers = np.array([ps.pose.center for ps in photos]).reshape(-1, 3)
        size = float(np.linalg.norm(np.diff(self.scene.bounds, axis=0)))
        # Small beside the outcrop: the cameras say where the photos were
        # taken, the model stays what the 3D view shows.
        segs = (np.concatenate([frustum_segments(ps.intrinsics, ps.pose, CAMERA_FRUSTUM * size)
                                for ps in photos]) if photos else np.zeros((0, 2, 3)))
        current = photos.index(self.current) if self.current in photos else -1
        self.layers.show_cameras(centers, segs, current, marker_m=CAMERA_MARKER * size)
        self._cameras_dirty = False

    # -------------------------------------------------------------- display
    def set_blend(self, opacity: float | None = None, visible: bool | None = None) -> None:
        if opacity is not None:
            self.blend_opacity = float(opacity)
        if visible is not None:
            self.blend_visible = bool(visible)
        if (blend := self.layers.get("blend")) is not None:
            blend.opacity = self.blend_opacity
            if self.blend_visible:
                self.layers.sync_blend()
            blend.visible = self.blend_visible

    def set_correspondence_display(self, visible: bool | None = None,
                                   outliers: bool | None = None) -> None:
        if visible is not None:
            self.show_correspondences = bool(visible)
        if outliers is not None:
            self.show_outliers = bool(outliers)
        layer = self.layers.get("correspondences")
        if layer is not None and not self.show_correspondences:
            layer.visible = False
        else:
            self.redraw_correspondences()
