"""Dock widget: the whole campaign at a glance — every camera and every mapped
line in the 3D view, and every measurement on one stereonet.

A view of a :class:`~napari_imgreg.workspace.Workspace` (by default the
workbench's, :func:`~napari_imgreg.widgets._controller.controller_for`): it
follows the workspace's psygnal events (photos added, poses changed,
registrations recorded, interpretations projected, a workspace opened) and
redraws, coalesced, at most a few times a second.

In the 3D view (napari's canvas with ``ndisplay == 3``) it keeps three layers
of its own: the cameras (markers coloured by status: green accepted, blue
registered, orange failed, grey not registered), their view frusta, and the
projected lines of all photos coloured by label. Markers and frusta are
sized as fractions of the model's diagonal, as the workbench draws its
cameras (:data:`~napari_imgreg.widgets._controller.CAMERA_MARKER`), so the
outcrop stays what the view shows. The stereonet is
:func:`~napari_imgreg.interpret.structural.draw_stereonet` (poles with their
confidence cones, great circles, lineations, Fisher mean per label with its α95
cone, Kamb contours); the Fisher means are listed under it.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg
from matplotlib.figure import Figure
from qtpy.QtCore import QTimer, Signal
from qtpy.QtWidgets import (
    QCheckBox,
    QHBoxLayout,
    QLabel,
    QPushButton,
    QScrollArea,
    QVBoxLayout,
    QWidget,
)

from ..interpret.project import label_color
from ..interpret.structural import FisherMean, draw_stereonet
from ..workspace import Workspace
from ._controller import CAMERA_FRUSTUM, CAMERA_MARKER, controller_for, overview_direction
from ._layers import NAPARI_AXIS_LABELS, frustum_segments, napari_from_world

if TYPE_CHECKING:
    import napari

__all__ = ["CAMPAIGN_LAYER_KEY", "STATUS_COLORS", "CampaignView", "fisher_plane"]

#: Metadata key of the layers this view owns (value: "cameras", "frusta" or "lines").
CAMPAIGN_LAYER_KEY = "imgreg_campaign"
#: Camera marker colour per photo status (Workspace.photo_status).
STATUS_COLORS = {"accepted": "#1a9850", "registered": "#4575b4", "failed": "#f46d43",
                 "not registered": "#9e9e9e"}
#: Layer names in napari's layer list.
_NAMES = {"cameras": "campaign cameras", "frusta": "campaign frusta",
          "lines": "campaign 3D lines"}
#: Idle time after the last workspace event before the view redraws, ms (a
#: nudge held down emits dozens of pose events a second).
REDRAW_DELAY_MS = 150
#: Width of the mapped lines, as a fraction of the model's diagonal.
LINE_WIDTH = 0.0025
#: The workspace events that change what the view shows.
_EVENTS = ("scene_changed", "photos_changed", "photo_changed", "pose_changed",
           "trials_changed", "accepted_changed", "projection_changed")


def fisher_plane(mean: FisherMean) -> tuple[float, float]:
    """Dip and dip direction (degrees) of the plane whose pole is a Fisher mean pole.

    A (downward) pole of plunge p and trend t is the normal of the plane
    dipping 90° − p toward t + 180°.
    """
    return 90.0 - float(mean.plunge_deg), (float(mean.trend_deg) + 180.0) % 360.0


class CampaignView(QWidget):
    """All cameras and mapped lines in 3D and every measurement on a stereonet.

    Parameters
    ----------
    napari_viewer : napari.viewer.Viewer
    workspace : Workspace, optional
        The campaign shown; default: the viewer's workbench workspace.
    """

    #: Emitted (from any thread) by a workspace event; redraws in the GUI thread.
    _workspace_event = Signal()
    #: The view was redrawn (tests and screenshots wait for it).
    redrawn = Signal()

    def __init__(self, napari_viewer: napari.viewer.Viewer, parent: QWidget | None = None, *,
                 workspace: Workspace | None = None) -> None:
        super().__init__(parent)
        self.viewer = napari_viewer
        #: The workbench controller whose workspace this shows (None: a workspace
        #: given here). Found by the viewer behind napari's proxy, so the view
        #: opened from the Plugins menu shows the workbench's campaign; held and
        #: attached, so the workspace outlives a closed workbench while shown here.
        self.controller = None
        if workspace is None:
            self.controller = controller_for(napari_viewer)
            self.controller.attach(self)
            workspace = self.controller.workspace
        self.workspace = workspace
        #: Fisher mean pole per label of the last redraw.
        self.fisher_means: dict[str, FisherMean] = {}
        # What the lines layer and the stereonet show (the workspace replaces
        # its lists on each projection): (features, model size, parts drawn).
        self._features_drawn: tuple = (None, None, 0)
        self._measurements_drawn = None

        self.summary_label = QLabel()
        self.summary_label.setWordWrap(True)
        self.frusta_check = QCheckBox("frusta")
        self.frusta_check.setChecked(True)
        self.frusta_check.setToolTip("Draw each camera's view pyramid")
        self.show_button = QPushButton("Show campaign in 3D")
        self.show_button.setToolTip("3D canvas: the model, every camera and every mapped line")
        self.figure = Figure(figsize=(4.0, 4.4))
        self.canvas = FigureCanvasQTAgg(self.figure)
        self.canvas.setMinimumHeight(240)
        self.means_label = QLabel()
        self.means_label.setWordWrap(True)
        self.means_label.setToolTip("Fisher mean plane per label: dip/dip direction (degrees), "
                                    "number of poles, α95 cone, precision κ")

        row = QHBoxLayout()
        row.addWidget(self.show_button, 1)
        row.addWidget(self.frusta_check)
        # In a scroll area: a short dock scrolls instead of overlapping its parts.
        inner = QWidget()
        inner_layout = QVBoxLayout(inner)
        inner_layout.setContentsMargins(0, 0, 0, 0)
        inner_layout.addWidget(self.summary_label)
        inner_layout.addLayout(row)
        inner_layout.addWidget(self.canvas, 1)
        inner_layout.addWidget(self.means_label)
        scroll = QScrollArea()
        scroll.setWidgetResizable(True)
        scroll.setFrameShape(QScrollArea.NoFrame)
        scroll.setWidget(inner)
        layout = QVBoxLayout(self)
        layout.setContentsMargins(2, 2, 2, 2)
        layout.addWidget(scroll)

        self._timer = QTimer(self)
        self._timer.setSingleShot(True)
        self._timer.setInterval(REDRAW_DELAY_MS)
        self._timer.timeout.connect(self.redraw)
        self._workspace_event.connect(self._timer.start)  # queued across threads
        self._connected: list = []
        for name in _EVENTS:
            signal = getattr(self.workspace, name)
            signal.connect(self._on_event)
            self._connected.append(signal)
        self.show_button.clicked.connect(lambda: self.show_3d())
        self.frusta_check.toggled.connect(lambda _on: self.redraw())
        self.viewer.dims.events.ndisplay.connect(self._follow_ndisplay)
        self.redraw()

    # ------------------------------------------------------------- events
    def _on_event(self, *args) -> None:
        try:
            self._workspace_event.emit()
        except RuntimeError:  # the dock was deleted by Qt: stop following
            self.disconnect_workspace()

    def closeEvent(self, event) -> None:
        self.disconnect_workspace()
        super().closeEvent(event)

    def disconnect_workspace(self) -> None:
        """Stop following the workspace (the dock is closed)."""
        for signal in self._connected:
            signal.disconnect(self._on_event, missing_ok=True)
        self._connected = []
        try:
            self.viewer.dims.events.ndisplay.disconnect(self._follow_ndisplay)
        except (RuntimeError, ValueError):  # pragma: no cover - already gone
            pass

    def _follow_ndisplay(self, event=None) -> None:
        # The layers are in metres: shown with the model, hidden over the photos.
        for layer in self.layers().values():
            layer.visible = self.viewer.dims.ndisplay == 3

    # ------------------------------------------------------------- layers
    def layers(self) -> dict[str, object]:
        """This view's napari layers by role ("cameras", "frusta", "lines")."""
        return {layer.metadata[CAMPAIGN_LAYER_KEY]: layer for layer in self.viewer.layers
                if CAMPAIGN_LAYER_KEY in layer.metadata}

    def _model_size(self) -> float:
        scene = self.workspace.scene
        if scene is None:
            return 100.0
        return float(np.linalg.norm(np.diff(np.asarray(scene.bounds, float), axis=0))) or 100.0

    def _put(self, role: str, method: str, data, **kwargs):
        """Create or update one of this view's layers (without making it active)."""
        layer = self.layers().get(role)
        visible = self.viewer.dims.ndisplay == 3
        if (layer is not None and data is not None and role == "frusta"
                and len(layer.data) == len(data)):
            # Same cameras, moved or recoloured: in place (removing a layer
            # costs napari a full garbage collection, ~1 s).
            layer.data = data
            layer.edge_color = kwargs["edge_color"]
            return layer
        if layer is not None and data is not None and role == "lines":
            # A new projection: the paths replaced in place.
            layer.data = []
            layer.add_paths(data, edge_width=kwargs["edge_width"], edge_color=kwargs["edge_color"])
            layer.features = kwargs["features"]
            return layer
        if layer is not None and data is not None and role == "cameras":
            # Updated in place (a selected camera stays selected): data first,
            # then the per-point values of the new count.
            layer.data = data
            layer.size = kwargs["size"]
            layer.features = kwargs["features"]
            layer.face_color = kwargs["face_color"]
            return layer
        if layer is not None:
            # Frusta of another number of cameras: napari does not change a
            # vectors layer's row count and per-row colours safely in place.
            self.viewer.layers.remove(layer)
        if data is None:
            return None
        active = self.viewer.layers.selection.active
        layer = getattr(self.viewer, method)(
            data, name=_NAMES[role], metadata={CAMPAIGN_LAYER_KEY: role}, visible=visible,
            axis_labels=NAPARI_AXIS_LABELS, **kwargs)
        if active is not None and active in self.viewer.layers:
            self.viewer.layers.selection.active = active
        return layer

    def redraw(self) -> None:
        """Redraw the cameras, the lines, the stereonet and the summary from the workspace."""
        ws = self.workspace
        photos = list(ws.photos) if ws.scene is not None else []
        size = self._model_size()
        if photos:
            centers = napari_from_world(np.array([ps.pose.center for ps in photos]))
            colors = [STATUS_COLORS.get(ws.photo_status(ps), "#9e9e9e") for ps in photos]
            self._put("cameras", "add_points", centers, ndim=3, size=CAMERA_MARKER * size,
                      face_color=colors, border_color="white",
                      features={"photo": [ps.name for ps in photos],
                                "status": [ws.photo_status(ps) for ps in photos]})
        else:
            self._put("cameras", "add_points", None)
        if photos and self.frusta_check.isChecked():
            segs = np.concatenate([frustum_segments(ps.intrinsics, ps.pose, CAMERA_FRUSTUM * size)
                                   for ps in photos])
            seg = napari_from_world(segs.reshape(-1, 3)).reshape(-1, 2, 3)
            vectors = np.stack([seg[:, 0], seg[:, 1] - seg[:, 0]], axis=1)
            edge = [STATUS_COLORS.get(ws.photo_status(ps), "#9e9e9e")
                    for ps in photos for _ in range(8)]
            self._put("frusta", "add_vectors", vectors, ndim=3, edge_color=edge,
                      edge_width=max(CAMERA_MARKER * size / 8.0, 1e-3), vector_style="line")
        else:
            self._put("frusta", "add_vectors", None)
        n_parts = self._draw_lines(size)
        if ws.measurements is not self._measurements_drawn:
            self._draw_stereonet()
            self._measurements_drawn = ws.measurements
        self._summarise(photos, n_parts)
        self.redrawn.emit()

    def _draw_lines(self, size: float) -> int:
        """The mapped lines, remade only when the projection changed; returns their parts."""
        ws = self.workspace
        if (ws.features_3d is self._features_drawn[0] and size == self._features_drawn[1]
                and (self.layers().get("lines") is not None or not self._features_drawn[2])):
            return self._features_drawn[2]
        paths, colors, labels, sources = [], [], [], []
        for f in ws.features_3d:
            for part in f.parts:
                if len(part) >= 2:
                    paths.append(napari_from_world(np.asarray(part, float)))
                    colors.append(f.color or label_color(f.label))
                    labels.append(f.label)
                    sources.append(f.source)
        if paths:
            self._put("lines", "add_shapes", paths, shape_type="path", ndim=3, edge_color=colors,
                      edge_width=max(LINE_WIDTH * size, 0.02),
                      features={"label": labels, "photo": sources})
        else:
            self._put("lines", "add_shapes", None)
        self._features_drawn = (ws.features_3d, size, len(paths))
        return len(paths)

    def _draw_stereonet(self) -> None:
        ws = self.workspace
        self.figure.clear()
        ax = self.figure.add_axes([0.02, 0.02, 0.96, 0.9])
        colors = {m.label: m.color or label_color(m.label) for m in ws.measurements}
        n_photos = len({m.source for m in ws.measurements})
        self.fisher_means = draw_stereonet(
            ax, ws.measurements, colors,
            title=f"{len(ws.measurements)} measurement(s) from {n_photos} photo(s)")
        self.canvas.draw_idle()
        lines = []
        for label, mean in sorted(self.fisher_means.items()):
            dip, dd = fisher_plane(mean)
            a95 = ("" if mean.alpha95_deg is None or not math.isfinite(mean.alpha95_deg)
                   else f", α95 {mean.alpha95_deg:.1f}°")
            kappa = ("" if mean.kappa is None else
                     (", κ > 10⁴" if not math.isfinite(mean.kappa) or mean.kappa > 1e4
                      else f", κ {mean.kappa:.0f}"))
            lines.append(f"<b style='color:{colors.get(label, '#000')}'>{label}</b> "
                         f"{dip:.0f}/{dd:03.0f}, n {mean.n}{a95}{kappa}")
        self.means_label.setText("<br>".join(lines) if lines else
                                 "No planes measured yet: project the interpretations.")

    def _summarise(self, photos, n_parts: int) -> None:
        ws = self.workspace
        if ws.scene is None:
            self.summary_label.setText("No model yet: open a scene in the workbench.")
            return
        counts = {s: 0 for s in STATUS_COLORS}
        for ps in photos:
            counts[ws.photo_status(ps)] = counts.get(ws.photo_status(ps), 0) + 1
        status = ", ".join(f"<span style='color:{STATUS_COLORS[s]}'>{n} {s}</span>"
                           for s, n in counts.items() if n)
        self.summary_label.setText(
            f"{len(photos)} photo(s): {status or 'none'}. {len(ws.features_3d)} mapped "
            f"feature(s) in {n_parts} part(s), {len(ws.measurements)} measurement(s).")

    # ----------------------------------------------------------- 3D view
    def show_3d(self) -> None:
        """Switch to the 3D canvas and frame the model with all its cameras."""
        self.redraw()
        self.viewer.dims.ndisplay = 3
        for layer in self.viewer.layers:
            if layer.metadata.get("imgreg_scene") is not None:
                layer.visible = True
        self._follow_ndisplay()
        if self.controller is not None:
            # The workbench's own cameras (one colour) would cover these,
            # coloured by each photo's status; its 3D view shows them again.
            for key in ("cameras", "frusta"):
                if (layer := self.controller.layers.get(key)) is not None:
                    layer.visible = False
        ws = self.workspace
        if ws.scene is None:
            return
        pts = [np.asarray(ws.scene.bounds, float)]
        if ws.photos:
            pts.append(np.array([ps.pose.center for ps in ws.photos]))
        pts = np.concatenate(pts)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        scene = getattr(self.viewer, "scene", None)  # napari >= 0.9 keeps the camera there
        cam = (scene.camera if scene is not None and hasattr(scene, "camera")
               else self.viewer.camera)
        cam.center = tuple(napari_from_world((lo + hi) / 2.0))
        # Obliquely from above, facing the outcrop as the cameras do (from the
        # south without cameras), the cameras in front of it.
        view = overview_direction([ps.pose for ps in ws.photos])
        if view is None:
            view = np.array([0.0, 1.0, -0.8])
        cam.set_view_direction(tuple(napari_from_world(view)), up_direction=(1.0, 0.0, 0.0))
        px = min(getattr(getattr(self.viewer, "canvas", None), "size", (600, 600)))
        cam.zoom = 0.8 * px / max(float(np.max(hi - lo)), 1e-6)
