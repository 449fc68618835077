"""Dock widget: draw interpretations on registered photos, project them onto the
model in 3D, measure them (backend: :mod:`napari_imgreg.interpret.project`,
:mod:`napari_imgreg.interpret.structural`).

A *registered photo* is an Image layer whose metadata carries its camera and
pose: ``metadata["result"]`` (a RESULT.json dict), or ``metadata["intrinsics"]``
and ``metadata["pose"]`` (contract dicts or :class:`Intrinsics`/:class:`Pose`),
or ``metadata["imgreg_registration"]`` (a :class:`~napari_imgreg.registration.pipeline.Registration`).
"Attach RESULT.json…" adds one to any Image layer. The model is a Surface
layer with ``metadata["imgreg_scene"]`` (the reader and the sample data set it).

Per photo, an interpretation Shapes layer (paths, lines, polygons) is drawn
over it, one label class at a time (sandstone yellow, mudstone grey, fault
red, or your own). Lines are drawn with napari's polyline tool (a click per
vertex, double-click or Enter to finish); with *Snap to contact* the clicks
are only the start, the waypoints and the end, and the finished line is
replaced by the least-cost path along the contact
(:mod:`napari_imgreg.interpret.snap`), an ordinary editable path. Each shape
carries a label, a note and the units above and below it (edited for the
selected shapes), written to the GeoJSON properties. *Project* casts every interpretation layer onto the model in
a napari thread worker (in the workbench: every workspace photo's drawings, those
of the photos not on screen too) and shows one 3D layer per photo (togglable), coloured
by label, with the measurements table and the stereonet.

Docked in the registration workbench, the widget also keeps what is drawn on
the workbench's photos, and the last projection, in its
:class:`~napari_imgreg.workspace.Workspace`. Opened on its own (napari's
Plugins menu) in a window where the workbench is open, it works on that
workbench's workspace too (:func:`workbench_workspace`); without one it
stands alone.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg
from matplotlib.colors import to_hex
from matplotlib.figure import Figure
from qtpy.QtCore import QTimer, Signal
from qtpy.QtGui import QColor
from qtpy.QtWidgets import (
    QCheckBox,
    QComboBox,
    QFileDialog,
    QFormLayout,
    QHBoxLayout,
    QLabel,
    QLineEdit,
    QPushButton,
    QTableWidget,
    QTableWidgetItem,
    QTabWidget,
    QVBoxLayout,
    QWidget,
)

from .._atomic import atomic_path
from ..camera import Intrinsics, Pose
from ..errors import InputError
from ..interpret.files import (
    azimuth_reference,
    export_features,
    measurements_in_frame,
    read_interpretations,
    write_interpretations,
    write_measurements_csv,
)
from ..interpret.project import LABEL_COLORS, Feature3D, Interpretation, label_color
from ..interpret.snap import COSTS, SnapParams, model_reference, snap_trace
from ..interpret.uncertainty import PoseUncertainty
from ..interpret.structural import (  # the three-point plane moved there (issue 14); kept importable
    THREE_POINT_MIN_VIEW_ANGLE_DEG,  # noqa: F401
    Measurement,
    draw_stereonet,
    plane_from_three_points,
    stereonet_format,
)
from ..io.photos import load_photo
from ..io.records import read_json
from ..prior import load_camera_and_pose
from ..workspace import PhotoState, Workspace, one_line, project_interpretation_sets
from ._dims_bar import HeightSliderHider
from ._jobs import JobRunner
from ._signals import follow_while_alive
from ._layers import (
    INTERPRETATION_OF,
    REDUCED_BY,
    fit_camera_2d,
    napari_from_pixels,
    napari_from_world,
    photo_pixel_frame,
    pixels_from_napari,
    remove_layers,
    viewer_camera,
)

if TYPE_CHECKING:
    import napari

__all__ = ["InterpretWidget", "camera_of_layer", "interpretations_from_shapes",
           "is_photo_layer", "plane_from_three_points", "workbench_workspace"]

#: Metadata keys on the layers this widget makes.
INTERP_KEY = INTERPRETATION_OF  # Shapes layer: name of its photo layer
PROJECTED_KEY = "imgreg_projected_from"  # 3D layer: name of its photo layer
_GEOJSON_FILTER = "GeoJSON (*.geojson *.json);;All files (*)"
_EXPORT_FILTER = ("3D GeoJSON (*.geojson);;GeoPackage (*.gpkg);;3D shapefile (*.shp);;"
                  "CSV vertices (*.csv);;OBJ polylines (*.obj);;PLY polylines (*.ply)")
#: Per-shape text carried into the GeoJSON properties (feature column: property).
_TEXT_FEATURES = {"comment": "comment", "unit_above": "above", "unit_below": "below",
                  # the contact a trace belongs to (the same on each photo it is drawn on:
                  # measured together), and an id the drawing came with (kept as it is)
                  "contact": "contact", "drawing_id": "id"}
#: The boxes of the form, by feature column.
_EDITABLE_TEXT = ("comment", "unit_above", "unit_below", "contact")
#: Feature column of a shape's other properties (a loaded file's ``formation``,
#: ``observer``, ``truth``, ...), as JSON: kept through the layer, never shown.
_EXTRA_FEATURE = "extra_properties"
#: Properties the layer holds in columns (or its colours) of their own.
_OWN_PROPERTIES = frozenset({"label", "color", "measure", "three_point_px",
                             *_TEXT_FEATURES.values()})
#: napari's click-per-vertex line tool (napari >= 0.6; "add_path" is freehand there).
_LINE_MODE = "add_polyline"
_DRAW_HINT = ("click each vertex, double-click (or Enter) to finish the line; "
              "the polygon tool for facets")
_SNAP_HINT = ("click the start, any waypoints and the end of the contact, double-click (or "
              "Enter) on the end: the line snaps to the contact")
_THREE_POINT_HINT = ("click three points on the bed surface, double-click (or Enter) on the "
                     "third: the plane through them")
_LINE_TYPES = ("path", "line")
_POLYGON_TYPES = ("polygon", "rectangle", "ellipse")
#: Status text colour of errors and warnings.
_WARNING_COLOR = "#e65100"
#: The measurements table: angles with their 1σ (as the CSV's σ columns), then why a
#: trace has no plane (the CSV's ``note``) and the geologist's own note.
_TABLE_COLUMNS = ("id", "label", "kind", "dip", "dip dir.", "plunge", "trend", "rms (m)",
                  "planarity", "photo", "why no plane", "note")
#: The widest the "why no plane" column is drawn (its whole text is the tooltip).
_WHY_WIDTH_PX = 220



def camera_of_layer(layer) -> tuple[Intrinsics, Pose, str] | None:
    """Camera, pose and photo name of a registered photo layer (None if it is not one)."""
    meta = getattr(layer, "metadata", {}) or {}
    reg = meta.get("imgreg_registration")
    if reg is not None and hasattr(reg, "pose"):
        return reg.intrinsics, reg.pose, reg.photo or layer.name
    result = meta.get("result")
    if isinstance(result, dict) and "camera" in result and "pose" in result:
        try:
            return (Intrinsics.from_dict(result["camera"]), Pose.from_dict(result["pose"]),
                    str(result.get("photo") or layer.name))
        except (KeyError, TypeError, ValueError):
            return None
    intr, pose = meta.get("intrinsics"), meta.get("pose")
    if intr is None or pose is None:
        return None
    try:
        intr = intr if isinstance(intr, Intrinsics) else Intrinsics.from_dict(intr)
        pose = pose if isinstance(pose, Pose) else Pose.from_dict(pose)
    except (KeyError, TypeError, ValueError):
        return None
    name = Path(str(meta.get("photo_path", ""))).name or layer.name
    return intr, pose, name


def pose_uncertainty_of_layer(layer, intrinsics: Intrinsics) -> PoseUncertainty:
    """The expected error of a photo layer's pose (:func:`camera_of_layer`'s):
    its registration's or attached RESULT.json's ``uncertainty``, else the
    documented default (:meth:`PoseUncertainty.from_result`)."""
    meta = getattr(layer, "metadata", {}) or {}
    reg = meta.get("imgreg_registration")
    if reg is not None and hasattr(reg, "pose"):
        return PoseUncertainty.from_estimate(getattr(reg, "uncertainty", None),
                                             getattr(reg, "status", "registered"),
                                             getattr(reg, "metrics", {}), intrinsics.fx)
    return PoseUncertainty.from_result(meta.get("result"), intrinsics.fx)


#: Names of the workbench's Image layers that are not photos (renders, their
#: overlay, the filtered views the registration matches).
_NOT_PHOTO_NAMES = ("render", "render (sun-lit)", "overlay render", "reference render")
_NOT_PHOTO_SUFFIXES = (" · filtered", "render", "render (sun-lit)")
#: Workbench layers that cover the photo and are hidden while drawing on it.
_COVERING_NAMES = ("correspondences", "overlay render", "photo · filtered")
#: Shapes-layer modes that are not drawing or editing shapes.
_NOT_DRAWING_MODES = ("pan_zoom", "transform")
#: Metadata key: a layer this widget hid while drawing (shown again afterwards).
_HIDDEN_WHILE_DRAWING = "imgreg_hidden_while_drawing"
#: Metadata key: an interpretation layer whose photo was closed (its photo's name).
_DETACHED_KEY = "imgreg_interpretation_of_closed_photo"


def is_photo_layer(layer) -> bool:
    """Whether an Image layer is a photo to draw on.

    A layer with a camera (:func:`camera_of_layer`) or a workbench photo
    (``metadata["photo_path"]``) is; a render, the render overlay or a
    filtered view ("photo · filtered", "render · filtered") is not. Any other
    image is offered, so that a RESULT.json can be attached to it.
    """
    if (getattr(layer, "metadata", None) or {}).get("photo_path"):
        return True  # a workbench photo, whatever its file is called
    name = str(getattr(layer, "name", ""))
    return not (name in _NOT_PHOTO_NAMES or name.endswith(_NOT_PHOTO_SUFFIXES))


def interpretations_from_shapes(layer) -> list[Interpretation]:
    """The drawn shapes of an interpretation layer as pixel interpretations.

    Paths and lines become LineStrings, polygons (rectangles, ellipses)
    Polygons; ``features["label"]`` gives the label, the edge colour the colour.
    """
    features = getattr(layer, "features", {})
    labels = None
    if "label" in features:
        labels = [str(v) for v in features["label"]]
    texts = {prop: list(features[col]) for col, prop in _TEXT_FEATURES.items()
             if col in features}
    extras = list(features[_EXTRA_FEATURE]) if _EXTRA_FEATURE in features else []
    out = []
    for k, (data, kind) in enumerate(zip(layer.data, layer.shape_type)):
        px = pixels_from_napari(np.asarray(data)[:, -2:])
        label = labels[k] if labels is not None and k < len(labels) else "unlabelled"
        extra = extras[k] if k < len(extras) else ""
        props = {**(json.loads(extra) if isinstance(extra, str) and extra else {}),
                 "label": label, "color": to_hex(layer.edge_color[k])}
        for prop, values in texts.items():
            value = values[k] if k < len(values) else None
            if isinstance(value, str) and value.strip():
                props[prop] = value.strip()
        if ("measure" in features and k < len(features) and features["measure"].iloc[k] ==
                "three_point" and len(px) == 3):
            props["measure"] = "three_point"
            props["three_point_px"] = np.round(px, 3).tolist()
        if kind in _LINE_TYPES and len(px) >= 2:
            out.append(Interpretation("LineString", px, props))
        elif kind in _POLYGON_TYPES and len(px) >= 3:
            out.append(Interpretation("Polygon", px, props))
    return out


def workbench_workspace(viewer: napari.viewer.Viewer) -> Workspace | None:
    """The workspace of the registration workbench open in a viewer, if any.

    Looks the viewer's workbench controller up (whichever proxy of the viewer
    napari handed the caller, see
    :func:`~napari_imgreg.widgets._controller.real_viewer`) without making
    one: a viewer without a workbench gets None, and no controller.

    Parameters
    ----------
    viewer : napari.viewer.Viewer
        The viewer, or a plugin proxy of it.

    Returns
    -------
    Workspace or None
        ``controller.workspace`` of the viewer's open workbench controller.
    """
    from ._controller import _CONTROLLERS, real_viewer

    real = real_viewer(viewer)
    controller = _CONTROLLERS.get(id(real))
    if controller is None or controller.viewer is not real or controller.closed:
        return None
    return controller.workspace


class InterpretWidget(QWidget):
    """Draw interpretations on registered photos, project them in 3D, measure them.

    Parameters
    ----------
    napari_viewer : napari.viewer.Viewer
    workspace : Workspace, optional
        The workbench's: what is drawn on its photos, and the projection, are
        kept there too. Default: the workspace of the workbench open in
        ``napari_viewer`` (:func:`workbench_workspace`), if there is one —
        as when the widget is opened from napari's Plugins menu beside the
        workbench; else none (the widget stands alone).
    """

    projection_done = Signal(object)  # list of Feature3D
    projection_failed = Signal(str)
    #: The model's view for snapping has been rendered (emitted from its thread).
    _reference_rendered = Signal()

    def __init__(self, napari_viewer: napari.viewer.Viewer, parent: QWidget | None = None, *,
                 workspace: Workspace | None = None) -> None:
        super().__init__(parent)
        self.viewer = napari_viewer
        self.workspace = workspace if workspace is not None else workbench_workspace(napari_viewer)
        self.features: list[Feature3D] = []
        self.measurements: list[Measurement] = []
        self.jobs = JobRunner(self)
        self._labels: dict[str, str] = dict(LABEL_COLORS)
        self._count_before: dict[int, int] = {}  # shapes before the one being drawn
        self._drawing_started: set[int] = set()  # layers pressed on in a drawing mode
        self._recording = False  # this widget is recording its projection in the workspace
        #: Per workspace photo, what the running projection is made from (see :meth:`_jobs`).
        self._projected_from: dict[PhotoState, str] | None = None
        #: Photos and traces of the running projection.
        self._projected_counts = (0, 0)
        #: Says which projections are out of date once a run of pose edits pauses.
        self._pose_timer = QTimer(self)
        self._pose_timer.setSingleShot(True)
        self._pose_timer.setInterval(300)
        self._pose_timer.timeout.connect(lambda: self._say_out_of_date())
        self._pose_timer.timeout.connect(lambda: self._prepare_snap_reference())
        #: The model rendered from a photo's pose for snapping (:meth:`_snap_reference`):
        #: ``(key, image)`` of the last one, rendered once per photo and pose.
        self._reference_cache: tuple[tuple, np.ndarray | None] | None = None
        #: The thread rendering it ahead (:meth:`_prepare_snap_reference`), when one runs.
        self._reference_thread: threading.Thread | None = None
        #: Traces snapped while that view was still rendering, to follow the model
        #: once it is ready: ``(layer, index, clicks, image, snapped data)``.
        self._pending_follow: list[tuple] = []
        self._reference_rendered.connect(self._on_reference_rendered)

        # ---- inputs
        self.photo_combo = QComboBox()
        self.photo_combo.setToolTip("A photo layer with a registration (camera and pose)")
        self.surface_combo = QComboBox()
        self.surface_combo.setToolTip("The textured model the lines are projected onto")
        attach = QPushButton("Attach RESULT.json…")
        attach.setToolTip("Give the chosen Image layer the camera and pose of a registration")
        self.new_button = QPushButton("New interpretation layer")
        self.label_combo = QComboBox()
        for label in self._labels:
            self.label_combo.addItem(label)
        self.new_label_edit = QLineEdit()
        self.new_label_edit.setPlaceholderText("new label, e.g. coal")
        add_label = QPushButton("Add")
        self.snap_check = QCheckBox("Snap to contact")
        self.snap_check.setToolTip(
            "Click start, waypoints and end: the line follows the contact on the photo "
            "(least-cost path); edit it afterwards like any path")
        self.three_point_check = QCheckBox("3-point plane")
        self.three_point_check.setToolTip(
            "Click three points of one plane (a bedding surface) and double-click the third: "
            "its dip and dip direction, through the surface points under the clicks")
        self.cost_combo = QComboBox()
        self.cost_combo.addItems(list(COSTS))
        self.cost_combo.setToolTip(
            "What the snapped line follows: gradient (an edge along the clicks, with their "
            "polarity), colour_edge (any colour boundary), darkness (dark lines: fractures, "
            "partings), brightness (veins), colour (a band of the clicked colour)")
        self.follow_model_check = QCheckBox("Follow the model")
        self.follow_model_check.setChecked(True)
        self.follow_model_check.setToolTip(
            "gradient on a registered photo: the snapped line is moved (at most 1.5 px) onto "
            "the contact where the model's own colours show it from the photo's pose, so the "
            "projected line carries less of the registration's error; where the model does "
            "not show that contact (an untextured model, another edge) it stays on the photo's")
        self.comment_edit = QLineEdit()
        self.comment_edit.setPlaceholderText("note")
        self.above_edit = QLineEdit()
        self.above_edit.setPlaceholderText("unit above")
        self.below_edit = QLineEdit()
        self.below_edit.setPlaceholderText("unit below")
        self.contact_edit = QLineEdit()
        self.contact_edit.setPlaceholderText("e.g. K7")
        self.contact_edit.setToolTip(
            "The contact this trace is of: the same name on the traces of one contact drawn "
            "on several photos measures them together (a contact:<name> row), where together "
            "they define its plane")
        apply_text = QPushButton("Set on selected")
        apply_text.setToolTip("Label, note, units and contact of the selected shapes "
                              "(select tool)")
        load_button = QPushButton("Load GeoJSON…")
        save_button = QPushButton("Save GeoJSON…")
        self.project_button = QPushButton("Project onto the model")
        self.project_button.setToolTip("Cast every photo's drawings onto the model, shown "
                                       "or not (runs in the background)")

        # At most two widgets side by side: the tab must fit a 380 px dock.
        form = QFormLayout()
        form.addRow("Photo", self.photo_combo)
        form.addRow("", attach)
        form.addRow("Model", self.surface_combo)
        form.addRow("Label", self.label_combo)
        form.addRow("", _row(self.new_label_edit, add_label, stretch=(1, 0)))
        form.addRow("Lines", _row(self.snap_check, self.three_point_check))
        form.addRow("Snap cost", _row(self.cost_combo, self.follow_model_check))
        form.addRow("Note", self.comment_edit)
        form.addRow("Units", _row(self.above_edit, self.below_edit))
        form.addRow("Contact", _row(self.contact_edit, apply_text, stretch=(1, 0)))
        io_row = QHBoxLayout()
        io_row.addWidget(load_button)
        io_row.addWidget(save_button)

        # ---- results
        self.status_label = QLabel("Choose a registered photo and draw on it.")
        self.status_label.setWordWrap(True)
        #: Photos the last projection left out or projected from an unverified pose.
        self.projection_warnings: list[str] = []
        self.table = QTableWidget(0, len(_TABLE_COLUMNS))
        self.table.setHorizontalHeaderLabels(list(_TABLE_COLUMNS))
        self.table.verticalHeader().setVisible(False)
        self.table.setEditTriggers(QTableWidget.NoEditTriggers)
        self.figure = Figure(figsize=(4.5, 5.0))
        self.canvas = FigureCanvasQTAgg(self.figure)
        self.canvas.setMinimumHeight(380)
        self.tabs = QTabWidget()
        self.tabs.addTab(self.table, "Measurements")
        self.tabs.addTab(self.canvas, "Stereonet")
        # The results sit below the drawing controls: bring them into view when
        # they are asked for (a tab chosen, a projection done).
        self.tabs.currentChanged.connect(lambda _index: self._scroll_to_results())

        self.georef_check = QCheckBox("georeferenced")
        self.georef_check.setToolTip(
            "Export CRS coordinates (local + georef origin) to GeoJSON, CSV, OBJ and PLY, "
            "and the measurements' centroids; GeoPackage and shapefiles are always in the "
            "CRS when the model has one")
        export_button = QPushButton("Export 3D…")
        csv_button = QPushButton("Save measurements…")
        net_button = QPushButton("Save stereonet…")
        self.view3d_button = QPushButton("Show in 3D")
        self.view3d_button.setToolTip("3D canvas, looking at the lines from the photo")
        self._result_buttons = [export_button, csv_button, net_button, self.view3d_button]
        for b in self._result_buttons:
            b.setEnabled(False)
        out_row = QHBoxLayout()
        out_row.addWidget(export_button)
        out_row.addWidget(self.georef_check)
        out_row2 = QHBoxLayout()
        out_row2.addWidget(csv_button)
        out_row2.addWidget(net_button)

        layout = QVBoxLayout(self)
        layout.addLayout(form)
        layout.addWidget(self.new_button)
        layout.addLayout(io_row)
        layout.addWidget(self.project_button)
        layout.addWidget(self.status_label)
        layout.addWidget(self.view3d_button)
        # The exports above the results: the stereonet is tall, and buttons
        # below it were out of view in a 1000 px window.
        layout.addLayout(out_row)
        layout.addLayout(out_row2)
        layout.addWidget(self.tabs, 1)

        attach.clicked.connect(self._attach_dialog)
        self.new_button.clicked.connect(lambda: self.new_interpretation_layer())
        add_label.clicked.connect(self._add_label_clicked)
        apply_text.clicked.connect(lambda: self.set_selected_text())
        self.snap_check.toggled.connect(self._snap_toggled)
        for signal in (self.snap_check.toggled, self.follow_model_check.toggled,
                       self.cost_combo.currentTextChanged, self.photo_combo.currentTextChanged,
                       self.surface_combo.currentTextChanged):
            # Once the change has settled (a photo chosen also picks its model).
            signal.connect(lambda *_args: QTimer.singleShot(0, self._prepare_snap_reference))
        self.three_point_check.toggled.connect(self._snap_toggled)
        self.label_combo.currentTextChanged.connect(self._label_changed)
        load_button.clicked.connect(self._load_dialog)
        save_button.clicked.connect(self._save_dialog)
        self.project_button.clicked.connect(self.project)
        export_button.clicked.connect(self._export_dialog)
        csv_button.clicked.connect(self._save_csv_dialog)
        net_button.clicked.connect(self._save_stereonet_dialog)
        self.view3d_button.clicked.connect(lambda: self.show_3d())
        for event in (self.viewer.layers.events.inserted, self.viewer.layers.events.removed):
            event.connect(self._refresh_layers)
            event.connect(self._update_drawing)
        self.viewer.layers.selection.events.active.connect(self._update_drawing)
        self.viewer.dims.events.ndisplay.connect(self._update_drawing)
        self._dims_bar = HeightSliderHider(self.viewer, anchor=self)
        self.destroyed.connect(lambda *_args, bar=self._dims_bar: bar.release())
        self.viewer.dims.events.ndisplay.connect(self._interpretations_follow_ndisplay)
        self._refresh_layers()
        if self.workspace is not None:
            self._follow_workspace()
            self._current_photo_shown()
            if self.workspace.features_3d or self.workspace.measurements:
                self.show_workspace_projection()

    # ----------------------------------------------------------- layers
    def _photo_layers(self) -> list:
        from napari.layers import Image

        return [layer for layer in self.viewer.layers
                if isinstance(layer, Image) and is_photo_layer(layer)]

    def _surface_layers(self) -> list:
        from napari.layers import Surface

        return [layer for layer in self.viewer.layers if isinstance(layer, Surface)
                and layer.metadata.get("imgreg_scene") is not None]

    def _refresh_layers(self, event=None) -> None:
        for combo, layers in ((self.photo_combo, self._photo_layers()),
                              (self.surface_combo, self._surface_layers())):
            current = combo.currentText()
            combo.blockSignals(True)
            combo.clear()
            names = [layer.name for layer in layers]
            combo.addItems(names)
            if current in names:
                combo.setCurrentText(current)
            combo.blockSignals(False)

    @property
    def photo_layer(self):
        name = self.photo_combo.currentText()
        return self.viewer.layers[name] if name in self.viewer.layers else None

    @property
    def scene(self):
        name = self.surface_combo.currentText()
        if name in self.viewer.layers:
            return self.viewer.layers[name].metadata.get("imgreg_scene")
        return None

    def interpretation_layer(self, photo_layer=None, create: bool = False):
        """The interpretation Shapes layer of a photo (made when ``create``)."""
        photo_layer = photo_layer or self.photo_layer
        if photo_layer is None:
            return None
        for layer in self.viewer.layers:
            if layer.metadata.get(INTERP_KEY) == photo_layer.name:
                return layer
        return self.new_interpretation_layer(photo_layer) if create else None

    def new_interpretation_layer(self, photo_layer=None):
        """The photo's interpretation layer, selected for drawing in line mode.

        A photo has one: if it has a layer already, or a workspace photo has
        saved interpretations, that is the layer (its lines kept); otherwise
        an empty Shapes layer is added over the photo. Its data coordinates
        are the photo's pixels as napari (row, col): the layer takes the photo
        layer's scale and translation.
        """
        photo_layer = photo_layer or self.photo_layer
        if photo_layer is None:
            self._fail("Choose a photo layer first.")
            return None
        layer = self.interpretation_layer(photo_layer) or self.show_workspace_interpretations(
            photo_layer)
        new = layer is None
        if new:
            layer = self._add_interpretation_layer(photo_layer)
        self.viewer.layers.selection.active = layer
        self._draw_mode(layer, fit=new)
        layer.mode = _LINE_MODE
        self.status_label.setText(
            f"Drawing {self.current_label!r} on {photo_layer.name}: {self._drawing_hint()}.")
        self.status_label.setStyleSheet("")
        return layer

    def _add_interpretation_layer(self, photo_layer, items: list[Interpretation] = ()):
        """A Shapes layer over the photo holding ``items``, wired to this widget."""
        label = self.current_label
        pixel_scale, pixel_translate = photo_pixel_frame(photo_layer)
        layer = self.viewer.add_shapes(
            ndim=2,
            name=f"{photo_layer.name} interpretation",
            scale=pixel_scale,
            translate=pixel_translate,
            edge_width=3,
            face_color="transparent",
            features={"label": np.array([], dtype=object),
                      **{col: np.array([], dtype=object) for col in _TEXT_FEATURES}},
            feature_defaults={"label": label, **{col: "" for col in _TEXT_FEATURES}},
            metadata={INTERP_KEY: photo_layer.name},
        )
        layer.current_edge_color = self._labels[label]
        layer.current_face_color = "transparent"
        # Filled before the handlers are connected: restoring is not an edit.
        self._add_items(layer, list(items))
        layer.events.data.connect(lambda event, layer=layer: self._shapes_edited(event, layer))
        layer.events.mode.connect(self._update_drawing)
        layer.events.visible.connect(self._update_drawing)
        layer.selected_data.events.items_changed.connect(
            lambda *_, layer=layer: self._show_selected_text(layer))
        # napari calls it with the layer itself, not the proxy a plugin holds:
        # the flag is keyed by the object the data handler above sees.
        layer.mouse_drag_callbacks.append(
            lambda _layer, event, layer=layer: self._pressed_on(layer))
        return layer

    def _add_items(self, layer, items: list[Interpretation]) -> None:
        """Append pixel interpretations to an interpretation layer as shapes
        (label, colour, note, units and the 3-point mark kept)."""
        if not items:
            return
        data, types, colors = [], [], []
        columns: dict[str, list] = {"label": [], "measure": [], _EXTRA_FEATURE: [],
                                    **{col: [] for col in _TEXT_FEATURES}}
        for item in items:
            data.append(napari_from_pixels(item.pixels))
            types.append("path" if item.geometry == "LineString" else "polygon")
            colors.append(item.color)
            columns["label"].append(item.label)
            columns["measure"].append(str(item.properties.get("measure") or ""))
            extra = {k: v for k, v in item.properties.items() if k not in _OWN_PROPERTIES}
            columns[_EXTRA_FEATURE].append(json.dumps(extra, default=str) if extra else "")
            for col, prop in _TEXT_FEATURES.items():
                columns[col].append(str(item.properties.get(prop) or ""))
            if item.label not in self._labels:
                self.add_label(item.label, item.color)
        n0 = len(layer.data)
        layer.add(data, shape_type=types, edge_color=colors, face_color="transparent",
                  edge_width=3)
        features = layer.features.copy()
        for col, values in columns.items():
            if col in ("measure", _EXTRA_FEATURE) and not any(values) and col not in features:
                continue  # no 3-point planes, no other properties: no column
            if col not in features:
                features[col] = ""
            features.loc[n0:, col] = values
        layer.features = features
        self._reset_defaults(layer)

    def _pressed_on(self, layer) -> None:
        """A mouse press on the canvas in a drawing mode: the next shape that
        napari reports ADDED is one the user drew (not loaded or pasted)."""
        if str(layer.mode).startswith("add_"):
            self._drawing_started.add(id(layer))

    # ------------------------------------------------------- workspace
    def _follow_workspace(self) -> None:
        """Show the workspace's drawings and projection as it changes (the
        handlers are released with the widget: the workspace may outlive it)."""
        ws = self.workspace
        follow_while_alive(self, [
            (ws.photo_changed, self._current_photo_shown),
            (ws.scene_changed, self._photos_closed),
            (ws.projection_changed, self.show_workspace_projection),
            # a pose changed (nudged, registered): its projection may be out of date
            (ws.pose_changed, self._pose_edited)])

    def _current_photo_shown(self) -> None:
        current = self.workspace.current if self.workspace is not None else None
        if current is None:
            return
        for layer in self._photo_layers():
            if self._photo_state(layer) is current:
                self.show_workspace_interpretations(layer)

    def show_workspace_interpretations(self, photo_layer=None):
        """The interpretation layer of a workspace photo, built from what the
        workspace keeps for it (``PhotoState.interpretations``) when it has
        none yet. Returns it (None: not a workspace photo, or nothing drawn)."""
        photo_layer = photo_layer or self.photo_layer
        ps = self._photo_state(photo_layer)
        if ps is None:
            return None
        layer = self.interpretation_layer(photo_layer)
        if layer is not None or not ps.interpretations:
            return layer
        active = self.viewer.layers.selection.active
        layer = self._add_interpretation_layer(photo_layer, ps.interpretations)
        # Shown with its photo, but not made the active layer (not drawing yet).
        layer.mode = "pan_zoom"
        layer.visible = bool(photo_layer.visible)
        if active is not None and active in self.viewer.layers:
            self.viewer.layers.selection.active = active
        return layer

    def _photos_closed(self) -> None:
        """The workspace's photos were replaced (a model or workspace opened):
        interpretation layers of photo layers that are gone no longer belong
        to a photo, so that a new photo of the same name is not given them."""
        for layer in list(self.viewer.layers):
            photo_name = layer.metadata.get(INTERP_KEY)
            if photo_name is not None and photo_name not in self.viewer.layers:
                layer.metadata[_DETACHED_KEY] = layer.metadata.pop(INTERP_KEY)
                layer.name = f"{layer.name} (closed)"
                layer.visible = False

    def show_workspace_projection(self) -> None:
        """Show the workspace's projected features and measurements (table,
        stereonet, result buttons), e.g. those of a workspace just opened."""
        ws = self.workspace
        if ws is None or self._recording:
            return
        self.features, self.measurements = list(ws.features_3d), list(ws.measurements)
        self._show_table(self.measurements)
        self.draw_stereonet()
        for b in self._result_buttons:
            b.setEnabled(bool(self.features or self.measurements))
        if self.features or self.measurements:
            stale = self._out_of_date_note()
            self.status_label.setText(
                f"The workspace's last projection: {len(self.features)} feature(s), "
                f"{len(self.measurements)} measurement(s)." + (f" {stale}" if stale else ""))
            self.status_label.setStyleSheet(f"color: {_WARNING_COLOR};" if stale else "")

    def _out_of_date_note(self, edited: bool = False) -> str:
        """Which photos the shown projection is out of date for (drawn on, or
        their pose changed, since: :meth:`Workspace.projection_out_of_date`),
        as a sentence; "" when none is. Without a workspace, or one that does
        not know what its projection was made from (saved by an older
        version), an edit (``edited``) after a projection is said as such."""
        stale = ([ps.name for ps in self.workspace.projection_out_of_date()]
                 if self.workspace is not None else [])
        if not stale:
            unknown = self.workspace is None or not self.workspace.projection_inputs_known
            return ("Drawings changed since the last projection: the table, stereonet and "
                    "exports are of the earlier lines until you Project again."
                    if edited and unknown and self.features else "")
        return (f"Out of date for {', '.join(stale)} (drawn on, or the pose changed, since): "
                "the table, stereonet and exports are of the earlier lines until you "
                "Project again.")

    def _pose_edited(self, *_args) -> None:
        """A photo's pose changed: once the edits pause, say what that made out
        of date and render the model's view for snapping from the new pose."""
        if self.features or self.measurements or self.snap_check.isChecked():
            self._pose_timer.start()

    def _say_out_of_date(self, *_args, edited: bool = False) -> None:
        """The status line names the photos the shown projection is now out
        of date for (it is left as it is when none is)."""
        stale = self._out_of_date_note(edited)
        if stale:
            self.status_label.setText(stale)
            self.status_label.setStyleSheet(f"color: {_WARNING_COLOR};")

    def _photo_state(self, photo_layer) -> PhotoState | None:
        """The workspace's photo a photo layer shows (None: not one of its photos)."""
        if self.workspace is None or photo_layer is None:
            return None
        return self.workspace.photo_at_path(photo_layer.metadata.get("photo_path"))

    def _shapes_edited(self, event, layer) -> None:
        """A shape was added, removed or changed (not while it is being drawn)."""
        # napari is imported here, when a layer already exists.
        from napari.layers.base._base_constants import ActionType

        action = getattr(event, "action", None)
        # Only a shape the user has just finished drawing (a mouse press in a
        # drawing mode started it) is snapped or made a 3-point plane; shapes
        # added by code, loaded or pasted are not.
        if action == ActionType.ADDING:
            self._count_before[id(layer)] = len(layer.data)
        drawn = action == ActionType.ADDED and id(layer) in self._drawing_started
        if action == ActionType.ADDED:
            self._drawing_started.discard(id(layer))
        # napari drops a line of fewer than two vertices but still reports ADDED.
        drawn = drawn and len(layer.data) > self._count_before.get(id(layer), -1)
        if (drawn and self.three_point_check.isChecked()
                and len(layer.data) and layer.shape_type[-1] == "path"):
            index = len(layer.data) - 1
            QTimer.singleShot(0, lambda: self.mark_three_point(layer, index))
        elif (drawn and self.snap_check.isChecked()
                and layer.mode == _LINE_MODE and len(layer.data)
                and layer.shape_type[-1] == "path"):
            # The shape is still being finished: replace it once napari is done.
            index = len(layer.data) - 1
            QTimer.singleShot(0, lambda: self.snap_shape(layer, index))
        if action in (ActionType.ADDED, ActionType.REMOVED, ActionType.CHANGED):
            self._keep_in_workspace(layer)
            self._say_out_of_date(edited=True)  # the table and the exports are older

    def snap_params(self) -> SnapParams:
        """The snapping settings the widget uses (the chosen cost, whether to
        follow the model, defaults otherwise)."""
        follow = SnapParams.model_reach_px if self.follow_model_check.isChecked() else 0.0
        return SnapParams(cost=self.cost_combo.currentText() or "gradient",
                          model_reach_px=follow)

    def _registered_camera(self, photo_layer) -> tuple[Intrinsics, Pose] | None:
        """The camera and pose of a photo layer when they are a registration's
        (not a sensor prior, metres off): the workspace's photo when it is
        registered or accepted, else the layer's registration or RESULT.json."""
        ps = self._photo_state(photo_layer)
        if ps is not None:
            ws = self.workspace
            if ws.photo_status(ps) in ("registered", "accepted"):
                return ps.intrinsics, ps.pose
            return None
        meta = photo_layer.metadata or {}
        reg = meta.get("imgreg_registration")
        result = meta.get("result")
        if reg is not None and getattr(reg, "status", "registered") != "registered":
            return None
        if reg is None and isinstance(result, dict) and result.get("status") != "registered":
            return None
        cam = camera_of_layer(photo_layer)
        return None if cam is None else (cam[0], cam[1])

    def _reference_source(self, photo_layer) -> tuple | None:
        """What the model's view for following it is rendered from: ``(key,
        scene, intrinsics, pose)``, or None when snapping does not follow the
        model (unticked, another cost, no model, a photo not registered)."""
        params = self.snap_params()
        scene = self.scene
        if (params.model_reach_px <= 0 or params.cost != "gradient" or scene is None
                or photo_layer is None):
            return None
        cam = self._registered_camera(photo_layer)
        if cam is None:
            return None
        intr, pose = cam
        key = (id(scene), json.dumps(intr.to_dict(), sort_keys=True), pose.matrix.tobytes())
        return key, scene, intr, pose

    def _render_reference(self, key: tuple, scene, intr: Intrinsics, pose: Pose) -> None:
        """Render the model's own colours from a pose into the one-entry cache,
        in the reference thread (the cache is replaced in one assignment), then
        say so to the GUI thread (:meth:`_on_reference_rendered`)."""
        reference = None  # none: snapped on the photo alone
        try:
            reference = model_reference(scene, intr, pose)
        except (InputError, ValueError):
            pass
        finally:  # even after an unexpected error, so that no trace waits for ever
            self._reference_cache = (key, reference)
            try:
                self._reference_rendered.emit()  # queued to the GUI thread
            except RuntimeError:  # the widget was closed meanwhile
                pass

    def _start_reference_render(self, source: tuple | None) -> bool:
        """Render the model's view of ``source`` (:meth:`_reference_source`) in a
        background thread unless it is cached or another render runs (one at a
        time; the next starts when it ends). Returns whether it is on the way."""
        if source is None or (self._reference_cache is not None
                              and self._reference_cache[0] == source[0]):
            return False
        running = self._reference_thread
        if running is not None and running.is_alive():
            return True
        # A plain daemon thread, not a job: nothing the user waits for yet (no
        # busy state or progress bar), and a render needs no cancel.
        self._reference_thread = threading.Thread(
            target=self._render_reference, args=source, name="imgreg-snap-reference", daemon=True)
        self._reference_thread.start()
        return True

    def _prepare_snap_reference(self, *_args) -> None:
        """While snapping is on, render the model from the chosen photo's
        registered pose in a background thread, so that the first snap on a
        photo does not wait for it (0.1–0.5 s for a mesh, 1–3 s for a large
        point cloud)."""
        if self.snap_check.isChecked():
            self._start_reference_render(self._reference_source(self.photo_layer))

    def _snap_reference(self, photo_layer, image: np.ndarray) -> tuple[np.ndarray | None, bool]:
        """The model's own colours from the photo's registered pose, the
        photo's size, for following the model's contact, and whether it is
        still rendering.

        Rendered once per photo and pose (ahead, by :meth:`_prepare_snap_reference`,
        or started here), then reused. Never waits for a render: ``(None, True)``
        means the trace is snapped on the photo alone for now and should follow
        the model once the render is ready; ``(None, False)``, never followed.
        """
        source = self._reference_source(photo_layer)
        if source is None:
            return None, False
        cache = self._reference_cache
        if cache is None or cache[0] != source[0]:
            self._start_reference_render(source)
            return None, True
        reference = cache[1]
        if reference is None or reference.shape[:2] != image.shape[:2]:
            return None, False
        return reference, False

    def _on_reference_rendered(self) -> None:
        """A render of the model's view has ended (GUI thread): traces snapped
        while it was on the way now follow the model, unless they were edited
        or removed since; then the view of the photo chosen now, if that
        changed meanwhile, is rendered in turn."""
        waiting = []
        for item in self._pending_follow:
            layer, index, clicks, image, snapped = item
            if (layer not in self.viewer.layers or index >= len(layer.data)
                    or not np.array_equal(layer.data[index], snapped)
                    or layer.metadata.get(INTERP_KEY) not in self.viewer.layers):
                continue  # edited, removed, or its layer or photo closed: left as it is
            photo_layer = self.viewer.layers[layer.metadata[INTERP_KEY]]
            reference, pending = self._snap_reference(photo_layer, image)
            if pending:
                waiting.append(item)
            elif reference is not None:
                try:
                    px = snap_trace(image, clicks, self.snap_params(), reference=reference)
                except ValueError:
                    continue
                self._set_snapped(layer, index, px)
                self.status_label.setText(
                    "The model's view is ready: the line just snapped now follows the "
                    "model where it shows the contact.")
                self.status_label.setStyleSheet("")
        self._pending_follow = waiting
        self._prepare_snap_reference()

    def _set_snapped(self, layer, index: int, px: np.ndarray) -> None:
        """Put a snapped trace (pixels, (N, 2)) in place of path ``index``."""
        data = list(layer.data)
        data[index] = napari_from_pixels(px)
        features = layer.features.copy()
        layer.data = data
        layer.features = features
        self._reset_defaults(layer)
        self._keep_in_workspace(layer)

    def snap_shape(self, layer, index: int) -> bool:
        """Replace path ``index`` of an interpretation layer by its snapped trace.

        Its vertices are taken as the clicks (start, waypoints, end); the path
        becomes the least-cost trace through them on the layer's photo.
        Returns whether it was replaced.
        """
        if index >= len(layer.data) or layer.shape_type[index] not in _LINE_TYPES:
            return False
        photo_name = layer.metadata.get(INTERP_KEY)
        if photo_name not in self.viewer.layers:
            return False
        photo_layer = self.viewer.layers[photo_name]
        image = np.asarray(photo_layer.data)
        if photo_layer.metadata.get(REDUCED_BY):
            # A workbench photo not shown keeps a reduced copy: the trace is
            # snapped on the photo's own pixels.
            try:
                image = load_photo(photo_layer.metadata["photo_path"]).image
            except (InputError, KeyError) as exc:
                self._fail(f"Not snapped: the photo's pixels cannot be read ({exc}); "
                           "show the photo and snap again.")
                return False
        clicks = pixels_from_napari(np.asarray(layer.data[index])[:, -2:])
        reference, pending = self._snap_reference(photo_layer, image)
        try:
            px = snap_trace(image, clicks, self.snap_params(), reference=reference)
        except ValueError as exc:
            self._fail(f"Not snapped: {exc}.")
            return False
        self._set_snapped(layer, index, px)
        if pending:  # follows the model when its view is ready (_on_reference_rendered)
            self._pending_follow.append((layer, index, clicks, image, layer.data[index]))
        follow = ("; following the model where it shows the contact" if reference is not None
                  else "; the model's view is still rendering: the line will follow the "
                       "model's contact when it is ready" if pending else "")
        self.status_label.setText(
            f"Snapped: {len(clicks)} clicks -> {len(px)} vertices along the contact "
            f"({self.snap_params().cost}{follow}). Edit it with the vertex tools, or remove "
            "it (select tool, then Delete) and click again.")
        self.status_label.setStyleSheet("")
        return True

    def _reset_defaults(self, layer) -> None:
        """New shapes get the current label and empty notes (napari would
        otherwise take the last shape's values as the defaults)."""
        layer.feature_defaults = {**{col: "" for col in layer.features.columns},
                                  "label": self.current_label}

    def mark_three_point(self, layer, index: int) -> bool:
        """Make path ``index`` (three clicked vertices) a 3-point plane: its
        measurement is the plane through the surface points under the clicks."""
        if index >= len(layer.data) or len(layer.data[index]) != 3:
            self._fail("A 3-point plane needs exactly three clicks (double-click the third).")
            return False
        features = layer.features.copy()
        if "measure" not in features:
            features["measure"] = ""
        features.loc[index, "measure"] = "three_point"
        layer.features = features
        self._reset_defaults(layer)
        self._keep_in_workspace(layer)
        self.status_label.setText("3-point plane drawn: Project to measure it.")
        self.status_label.setStyleSheet("")
        return True

    def _drawing_hint(self) -> str:
        """What the next clicks make: a 3-point plane wins over snapping."""
        if self.three_point_check.isChecked():
            return _THREE_POINT_HINT + (" (Snap to contact is off while 3-point plane is on)"
                                        if self.snap_check.isChecked() else "")
        return _SNAP_HINT if self.snap_check.isChecked() else _DRAW_HINT

    def _snap_toggled(self, on: bool = False) -> None:
        layer = self.interpretation_layer()
        if layer is not None:
            layer.mode = _LINE_MODE
        self.status_label.setText(f"Drawing {self.current_label!r}: {self._drawing_hint()}.")
        self.status_label.setStyleSheet("")

    def _show_selected_text(self, layer) -> None:
        """One shape selected (select tool): its note and units in the boxes, to
        read or edit; otherwise the boxes are cleared (for several shapes,
        what is typed is set on all of them)."""
        if str(layer.mode) not in ("select", "direct"):
            return
        values = ("",) * len(_EDITABLE_TEXT)
        if len(layer.selected_data) == 1:
            k = next(iter(layer.selected_data))
            row = layer.features.iloc[k] if k < len(layer.features) else {}
            values = tuple(str(row.get(col, "") or "") for col in _EDITABLE_TEXT)
        for edit, value in zip(self._text_edits(), values):
            edit.setText(value)

    def _text_edits(self) -> tuple:
        """The boxes of :data:`_EDITABLE_TEXT`, in its order."""
        return (self.comment_edit, self.above_edit, self.below_edit, self.contact_edit)

    def set_selected_text(self, layer=None, comment: str | None = None,
                          above: str | None = None, below: str | None = None,
                          contact: str | None = None) -> int:
        """Set the note and the units above/below (and the chosen label) on the
        selected shapes. On one shape the boxes are its values (an emptied box
        clears one); on several, an empty box leaves each shape's value as it
        is. Returns the count."""
        layer = layer or self.interpretation_layer()
        if layer is None or not layer.selected_data:
            self._fail("Select shapes first (select tool), then set their label and notes.")
            return 0
        values = {"comment": self.comment_edit.text() if comment is None else comment,
                  "unit_above": self.above_edit.text() if above is None else above,
                  "unit_below": self.below_edit.text() if below is None else below,
                  "contact": self.contact_edit.text() if contact is None else contact}
        features = layer.features.copy()
        for col in _TEXT_FEATURES:
            if col not in features:
                features[col] = ""
        single = len(layer.selected_data) == 1
        for k in layer.selected_data:
            for col, value in values.items():
                if value.strip() or single:
                    features.loc[k, col] = value.strip()
        layer.features = features
        self._reset_defaults(layer)
        self._keep_in_workspace(layer)
        n = len(layer.selected_data)
        self.status_label.setText(f"Set note, units and contact on {n} shape(s).")
        self.status_label.setStyleSheet("")
        return n

    def _keep_in_workspace(self, layer) -> None:
        """What is drawn on a workspace photo is that photo's interpretations."""
        photo_name = layer.metadata.get(INTERP_KEY)
        if self.workspace is None or photo_name not in self.viewer.layers:
            return
        ps = self._photo_state(self.viewer.layers[photo_name])
        if ps is not None:
            self.workspace.set_interpretations(interpretations_from_shapes(layer), ps)

    def drawing_layer(self):
        """The interpretation layer being drawn or edited on, or None.

        It is drawing while it is the active layer, visible, on the 2D canvas,
        in a mode that adds or edits shapes (not pan/zoom or transform).
        """
        active = self.viewer.layers.selection.active
        if (active is None or INTERP_KEY not in active.metadata or not active.visible
                or self.viewer.dims.ndisplay != 2
                or str(getattr(active, "mode", "pan_zoom")) in _NOT_DRAWING_MODES):
            return None
        return active

    def _update_drawing(self, event=None) -> None:
        """While drawing, the drawing layer is on top and the workbench layers
        that cover the photo (correspondence lines, the render overlay, the
        filtered photo) are hidden; they come back when drawing stops."""
        layer = self.drawing_layer()
        if layer is None:
            self._show_covering_layers()
            return
        layers = self.viewer.layers
        i = layers.index(layer)
        if i != len(layers) - 1:
            layers.move(i, len(layers))
        for other in list(layers):
            if other is not layer and other.name in _COVERING_NAMES and other.visible:
                other.metadata[_HIDDEN_WHILE_DRAWING] = True
                other.visible = False

    def _interpretations_follow_ndisplay(self, event=None) -> None:
        """Drawings are in the photo's pixels: hidden on the 3D canvas (where
        they would float as stray strokes beside the model), shown again as
        they were on returning to 2D. Their 3D projections are other layers."""
        three_d = self.viewer.dims.ndisplay == 3
        if three_d:
            self._ensure_3d_layers()  # built when first needed, not at each projection
        for layer in list(self.viewer.layers):
            if INTERP_KEY not in layer.metadata:
                continue
            if three_d:
                layer.metadata.setdefault("imgreg_visible_2d", layer.visible)
                layer.visible = False
            elif "imgreg_visible_2d" in layer.metadata:
                layer.visible = layer.metadata.pop("imgreg_visible_2d")

    def _show_covering_layers(self) -> None:
        for other in list(self.viewer.layers):
            if not other.metadata.pop(_HIDDEN_WHILE_DRAWING, False):
                continue
            if self.viewer.dims.ndisplay == 3 and "imgreg_visible_2d" in other.metadata:
                # the workbench hid its 2D layers for 3D and restores them on return
                other.metadata["imgreg_visible_2d"] = True
            else:
                other.visible = True

    def _draw_mode(self, layer, fit: bool = False) -> None:
        """Drawing happens on the photo, in 2D: leave the 3D canvas, show photo and layer.

        On its own (not in the workbench, which frames its canvas itself) the
        dock also hides the model and the projected lines (metres in 3D: in
        2D a stray slice of them lay over the photo's corner; "Show in 3D"
        shows them again) and frames the photo when it leaves 3D or ``fit``
        (a new layer): the view was fitted to the model's and the photo's
        extents together, the photo small in a corner of a black canvas.
        """
        switched = self.viewer.dims.ndisplay != 2
        if switched:
            self.viewer.dims.ndisplay = 2
        photo = self.viewer.layers[layer.metadata[INTERP_KEY]]
        photo.visible = layer.visible = True
        if self.workspace is not None:
            return
        model = self.surface_combo.currentText()
        for other in list(self.viewer.layers):
            if other.visible and other.ndim > 2 and (PROJECTED_KEY in other.metadata
                                                     or other.name == model):
                other.visible = False
        if switched or fit:
            self._frame(photo)
        self._dims_bar.update()  # the model hidden: its height slider moves nothing now

    def _frame(self, photo) -> None:
        """The photo fills the 2D canvas (``viewer.fit_to_view`` takes a 2D
        layer's extent for all the viewer's axes and fails when the model
        gives it three)."""
        lo, hi = np.asarray(photo.extent.world, float)[:, -2:]
        canvas = getattr(self.viewer, "canvas", None)
        fit_camera_2d(viewer_camera(self.viewer), lo, hi,
                      canvas.size if canvas is not None else (600, 800))

    # ----------------------------------------------------------- labels
    @property
    def current_label(self) -> str:
        return self.label_combo.currentText() or "sandstone"

    def add_label(self, label: str, color: str | None = None) -> None:
        """Add a user-defined label class (colour picked if not given) and select it."""
        label = label.strip()
        if not label:
            return
        if label not in self._labels:
            self._labels[label] = label_color(label, color)
            self.label_combo.addItem(label)
        self.label_combo.setCurrentText(label)

    def _add_label_clicked(self) -> None:
        self.add_label(self.new_label_edit.text())
        self.new_label_edit.clear()

    def _label_changed(self, label: str) -> None:
        layer = self.interpretation_layer()
        if layer is None or not label:
            return
        # napari wants a default for every feature column (notes/units stay empty).
        layer.feature_defaults = {**{col: "" for col in layer.features.columns}, "label": label}
        layer.current_edge_color = self._labels.get(label, label_color(label))
        # With the select tools, changing the label relabels the selected shapes.
        # Not while drawing: napari leaves the line just drawn selected, and
        # choosing the next line's label must not relabel it.
        if layer.selected_data and str(layer.mode) in ("select", "direct"):
            features = layer.features.copy()
            for k in layer.selected_data:
                features.loc[k, "label"] = label
            layer.features = features

    # ------------------------------------------------------------- I/O
    def attach_result(self, path: str | Path, layer=None) -> str:
        """Attach a RESULT.json's camera and pose to an Image layer.

        A sensor record (``PHOTO.json``) works too, as for ``napari-imgreg
        project``: its prior pose is attached, with a warning. Returns
        ``"result"`` or ``"prior"``.
        """
        layer = layer or self.photo_layer
        scene = self.scene
        intr, pose, kind, notes = load_camera_and_pose(
            path, getattr(scene, "georef", None), getattr(scene, "dem", None),
            getattr(scene, "terrain_height", None))
        data = read_json(path)
        photo = data.get("photo") if isinstance(data, dict) else None
        if kind == "result":
            layer.metadata["result"] = data
            self.status_label.setText(f"{layer.name}: registration from {Path(path).name}.")
            self.status_label.setStyleSheet("")
            self._prepare_snap_reference()  # a registered pose: the model's view for snapping
            return kind
        # Not "registered": the pose's expected error is the sensor prior's (50 px, 5 m, 3°).
        layer.metadata["result"] = {"status": "prior", "photo": photo or layer.name,
                                    "camera": intr.to_dict(), "pose": pose.to_dict()}
        warning = (f"{layer.name}: {Path(path).name} is a sensor record, not a registration: "
                   "its lines will be projected with the PRIOR pose (metres off)"
                   + "".join(f"; {n}" for n in notes) + ".")
        self.status_label.setText(warning)
        self.status_label.setStyleSheet(f"color: {_WARNING_COLOR};")
        _notify(warning, "warning")
        return kind

    def load_geojson(self, path: str | Path, photo_layer=None):
        """Add the interpretations of a pixel GeoJSON to the photo's interpretation layer."""
        items = read_interpretations(path)
        layer = self.interpretation_layer(photo_layer, create=True)
        if layer is None:
            return None
        self._draw_mode(layer)
        self._add_items(layer, items)
        self._keep_in_workspace(layer)  # with their labels and notes, set after the add
        self.status_label.setText(f"Loaded {len(items)} interpretation(s) from {Path(path).name}.")
        return layer

    def save_geojson(self, path: str | Path, photo_layer=None) -> int:
        """Save the photo's interpretation layer as pixel GeoJSON; returns the count."""
        layer = self.interpretation_layer(photo_layer)
        items = interpretations_from_shapes(layer) if layer is not None else []
        write_interpretations(path, items)
        self.status_label.setText(f"Saved {len(items)} interpretation(s) to {Path(path).name}.")
        return len(items)

    # ---------------------------------------------------------- project
    def _jobs(self) -> list[tuple[Intrinsics, Pose, list[Interpretation], str]]:
        """What to project, one job per photo with drawings and a camera; the
        photos left out or projected from an unverified pose are listed in
        :attr:`projection_warnings` (said, never silently).

        With a workspace, every workspace photo with drawings is projected,
        shown or not (as :meth:`Workspace.projection_job`): the interpretation
        layer of a photo on screen is first kept as its drawings (its edits),
        the others are projected from what the workspace holds for them, each
        from its current camera and pose. A photo layer that is not a
        workspace photo (a RESULT.json attached) is projected from its layer.
        """
        jobs = []
        self.projection_warnings = []
        self._projected_from = None
        others = []  # layers of photos that are not workspace photos
        for layer in list(self.viewer.layers):
            photo_name = layer.metadata.get(INTERP_KEY)
            if photo_name is None or photo_name not in self.viewer.layers:
                continue
            self._assign_ids(layer, photo_name)
            if self._photo_state(self.viewer.layers[photo_name]) is not None:
                self._keep_in_workspace(layer)  # projected below, with the photos not shown
            else:
                others.append((layer, photo_name))
        ws = self.workspace
        if ws is not None:
            for ps in ws.photos:
                if not ps.interpretations:
                    continue
                unc = ws.pose_uncertainty(ps)
                status = ws.photo_status(ps)
                if status in ("not registered", "failed"):
                    self.projection_warnings.append(
                        f"{ps.name}: {status}: projected from its prior pose "
                        f"(error ≈ {unc.position_m:.0f} m, {unc.rotation_deg:.0f}°)")
                jobs.append((ps.intrinsics, ps.pose, list(ps.interpretations), ps.name, unc))
            # What each photo's projection is made from now, recorded with it
            # (Workspace.projection_out_of_date reads it).
            self._projected_from = ws.projection_inputs()
        for layer, photo_name in others:
            items = interpretations_from_shapes(layer)
            if not items:
                continue
            photo_layer = self.viewer.layers[photo_name]
            camera = camera_of_layer(photo_layer)
            if camera is None:
                self.projection_warnings.append(
                    f"{photo_name}: {len(items)} drawing(s) not projected (no registration: "
                    "Attach RESULT.json…)")
                continue
            intr, pose, source = camera
            jobs.append((intr, pose, items, source, pose_uncertainty_of_layer(photo_layer, intr)))
        return jobs

    def _assign_ids(self, layer, photo_name: str) -> None:
        """Give every shape without one a lasting id, ``<photo>:<n>`` with the next
        free ``n``: a trace keeps its id (in the table, the exports, a notebook)
        when another is deleted, instead of being renumbered by its position."""
        features = layer.features
        if len(features) == 0:
            return
        stem = Path(photo_name).stem
        ids = [str(v or "") for v in features["drawing_id"]] if "drawing_id" in features \
            else [""] * len(features)
        if all(ids):
            return
        used = [int(i.rsplit(":", 1)[1]) for i in ids
                if i.startswith(stem + ":") and i.rsplit(":", 1)[1].isdigit()]
        n = max(used, default=0)
        for k, value in enumerate(ids):
            if not value:
                n += 1
                ids[k] = f"{stem}:{n}"
        features = features.copy()
        features["drawing_id"] = ids
        layer.features = features
        self._reset_defaults(layer)  # the next shape must not inherit the last one's id

    def project(self):
        """Project every interpretation layer in a napari thread worker; returns it."""
        scene = self.scene
        if scene is None:
            self._fail("Choose the model (a Surface layer opened by napari-imgreg).")
            return None
        unopened = self.workspace.unopened_drawings() if self.workspace is not None else None
        if unopened:  # as Workspace.projection_job: the saved projection stays whole
            self._fail(unopened)
            return None
        jobs = self._jobs()
        if not jobs:
            self._fail(self._nothing_to_project())
            return None
        for warning in self.projection_warnings:
            _notify(warning, "warning")
        self.project_button.setEnabled(False)
        n = sum(len(j[2]) for j in jobs)
        self._projected_counts = (len(jobs), n)
        self.status_label.setText(f"Projecting {n} trace(s) from {len(jobs)} photo(s)…")
        self.status_label.setStyleSheet("")
        # Errors come back as one line (bugs are logged with their traceback).
        return self.jobs.start("projection", project_interpretation_sets, scene, jobs,
                               on_returned=self._on_result, on_failed=self._fail,
                               on_finished=self._on_finished, notify=False)

    def _nothing_to_project(self) -> str:
        """Why Project has nothing to do, and the next step (:meth:`_jobs`
        lists drawings on photos without a registration among its warnings)."""
        if any("not projected (no registration" in w for w in self.projection_warnings):
            return ("Nothing to project: the drawings are on photos without a registration "
                    "(register the photo in the workbench, or Attach RESULT.json…).")
        return ("Nothing to project: nothing is drawn yet. Press New interpretation layer, "
                "trace the contacts on the photo, then Project onto the model.")

    def _on_finished(self) -> None:
        self.project_button.setEnabled(True)

    def _fail(self, message: str) -> None:
        """An error: in the status line and as a napari notification (as the workbench's)."""
        self.status_label.setText(message)
        self.status_label.setStyleSheet(f"color: {_WARNING_COLOR};")
        _notify(message, "error")
        self.projection_failed.emit(message)

    def _on_result(self, result: tuple[list[Feature3D], list[Measurement]] | None) -> None:
        if result is None:  # cancelled
            return
        self.features, self.measurements = result
        if self.workspace is not None:
            self._recording = True  # shown below, not again by the workspace's event
            try:
                self.workspace.record_projection(self.features, self.measurements,
                                                 projected_from=self._projected_from)
            finally:
                self._recording = False
                self._projected_from = None
        # The 3D lines (0.5 s of layer building) wait for the 3D canvas: on the 2D
        # one, where a projection is made, they would only hold up the GUI.
        if self.viewer.dims.ndisplay == 3:
            self._show_layers(self.features)
        else:
            self._show_layers([])  # the earlier projection's go; these come in 3D
        self._show_table(self.measurements)
        self.draw_stereonet()
        QTimer.singleShot(0, self._scroll_to_results)
        n_parts = sum(len(f.parts) for f in self.features)
        split = sum(len(f.parts) > 1 for f in self.features)
        off = sum(not f.parts for f in self.features)
        planes = sum(m.has_plane for m in self.measurements)
        n_photos, n_traces = self._projected_counts
        self.status_label.setText(
            f"Projected {n_traces} trace(s) from {n_photos} photo(s): "
            f"{len(self.features)} feature(s) on the model as {n_parts} part(s)"
            + (f"; {split} split where they left the surface" if split else "")
            + (f"; {off} off the surface" if off else "")
            + f". {planes} well-posed plane(s)."
            + "".join(f"<br>⚠ {w}" for w in self.projection_warnings))
        self.status_label.setStyleSheet(f"color: {_WARNING_COLOR};"
                                        if self.projection_warnings else "")
        for b in self._result_buttons:
            b.setEnabled(True)
        self.projection_done.emit(self.features)

    # ---------------------------------------------------------- display
    def _ensure_3d_layers(self) -> None:
        """The 3D layers of the projected features whose photo has none yet (a
        projection made on the 2D canvas, or kept by the workspace)."""
        shown = {lay.metadata[PROJECTED_KEY] for lay in self.viewer.layers
                 if PROJECTED_KEY in lay.metadata}
        missing = [f for f in self.features if f.source not in shown]
        if missing and self.surface_combo.currentText() in self.viewer.layers:
            self._show_layers(missing, replace_all=False)

    def _scroll_to_results(self) -> None:
        """Scroll the dock (or the workbench tab) that holds this widget to its
        end, where the measurements and the stereonet are."""
        from qtpy.QtWidgets import QScrollArea

        area = self.parentWidget()
        while area is not None and not isinstance(area, QScrollArea):
            area = area.parentWidget()
        if area is not None:
            bar = area.verticalScrollBar()
            bar.setValue(bar.maximum())

    def _show_layers(self, features: list[Feature3D], replace_all: bool = True) -> None:
        """One 3D Shapes layer of paths per photo: a projection replaces every
        earlier one (``replace_all``), else only those of the features' photos."""
        surface = self.viewer.layers[self.surface_combo.currentText()]
        by_source: dict[str, list[Feature3D]] = {}
        for f in features:
            by_source.setdefault(f.source, []).append(f)
        # Every earlier projection goes: a photo whose lines were all deleted
        # since has no feature now, and its old 3D lines must not stay.
        remove_layers(self.viewer, [
            layer for layer in self.viewer.layers if PROJECTED_KEY in layer.metadata
            and (replace_all or layer.metadata[PROJECTED_KEY] in by_source)])
        extent = float(np.ptp(surface.vertices, axis=0).max()) if len(surface.vertices) else 100.0
        width = max(extent / 400.0, 0.05)  # visible at the whole-outcrop zoom
        for source, feats in by_source.items():
            paths, colors, labels, ids = [], [], [], []
            for f in feats:
                for part in f.parts:
                    if len(part) >= 2:
                        paths.append(napari_from_world(part))
                        colors.append(f.color)
                        labels.append(f.label)
                        ids.append(f.id)
            if not paths:
                continue
            self.viewer.add_shapes(
                paths, shape_type="path", ndim=3, edge_color=colors, edge_width=width,
                name=f"{source} 3D interpretation",
                scale=surface.scale, translate=surface.translate,
                features={"label": labels, "id": ids},
                metadata={PROJECTED_KEY: source},
                axis_labels=surface.axis_labels,
            )

    def show_3d(self, source: str | None = None) -> None:
        """Switch to the 3D canvas and look at the projected lines as the photo saw them.

        Photos and their 2D interpretation layers are hidden (they live in
        pixel units, the model in metres); the camera looks along the photo's
        view direction at the lines' centre, zoomed to their extent.
        """
        feats = [f for f in self.features if f.parts and (source is None or f.source == source)]
        if not feats:
            return
        self._ensure_3d_layers()
        pts = np.concatenate([f.points for f in feats])
        for layer in self.viewer.layers:
            if INTERP_KEY in layer.metadata or layer in self._photo_layers():
                layer.visible = False
            elif PROJECTED_KEY in layer.metadata or layer.name == self.surface_combo.currentText():
                layer.visible = True
        self.viewer.dims.ndisplay = 3
        view = np.array([0.0, 1.0, -0.3])  # north, a little down, without a photo
        name = feats[0].source
        for layer in self._photo_layers():
            camera = camera_of_layer(layer)
            if camera is not None and camera[2] == name:
                view = camera[1].view_direction
        cam = viewer_camera(self.viewer)
        cam.center = tuple(napari_from_world(pts.mean(axis=0)))
        cam.set_view_direction(tuple(napari_from_world(view)), up_direction=(1.0, 0.0, 0.0))
        extent = float(np.ptp(pts, axis=0).max()) or 10.0
        canvas = getattr(getattr(self.viewer, "canvas", None), "size", (600, 800))
        cam.zoom = 0.8 * min(canvas) / extent

    def _show_table(self, measurements: list[Measurement]) -> None:
        def fmt(v: float | None, d: int = 1) -> str:
            return "" if v is None else f"{v:.{d}f}"

        def angle(v: float | None, sigma: float | None) -> str:
            return fmt(v) + ("" if v is None or sigma is None else f" ± {sigma:.1f}")

        why = _TABLE_COLUMNS.index("why no plane")
        # Which north the azimuths are from (grid north of the model's CRS).
        georef = getattr(self.scene, "georef", None)
        frame = ({"frame": "local", "crs": georef.crs, "origin": georef.origin.tolist()}
                 if georef is not None else {"frame": "local"})
        north = azimuth_reference(frame, np.array([m.centroid for m in measurements])
                                  .reshape(-1, 3))
        for col in ("dip dir.", "trend"):
            self.table.horizontalHeaderItem(_TABLE_COLUMNS.index(col)).setToolTip(
                north[0].upper() + north[1:])
        self.table.setRowCount(len(measurements))
        for row, m in enumerate(measurements):
            note = " · ".join(t for t in (m.comment, m.above and f"above: {m.above}",
                                          m.below and f"below: {m.below}") if t)
            cells = [m.id, m.label, m.kind, angle(m.dip_deg, m.dip_sigma_deg),
                     angle(m.dip_direction_deg, m.dip_direction_sigma_deg),
                     angle(m.plunge_deg, m.plunge_sigma_deg),
                     angle(m.trend_deg, m.trend_sigma_deg), fmt(m.rms_m, 3),
                     fmt(m.planarity, 3), m.photo or m.source, m.note, note]
            for col, text in enumerate(cells):
                item = QTableWidgetItem(text)
                if col == 1:
                    item.setForeground(_qcolor(m.color or label_color(m.label)))
                if col in (why, why + 1) and text:
                    item.setToolTip(text)
                self.table.setItem(row, col, item)
        self.table.resizeColumnsToContents()
        if self.table.columnWidth(why) > _WHY_WIDTH_PX:
            self.table.setColumnWidth(why, _WHY_WIDTH_PX)

    def draw_stereonet(self) -> None:
        self.figure.clear()
        ax = self.figure.add_axes([0.02, 0.02, 0.96, 0.92])
        colors = {label: c for label, c in self._labels.items()}
        colors.update({m.label: m.color for m in self.measurements if m.color})
        draw_stereonet(ax, self.measurements, colors, title="Lower hemisphere, equal area")
        self.canvas.draw_idle()

    # ---------------------------------------------------------- exports
    def export(self, path: str | Path, georeferenced: bool | None = None) -> None:
        """Write the projected set (.geojson, .gpkg, .shp, .csv, .obj, .ply).

        GeoPackage and shapefiles are in the georeference's CRS whenever the
        model has one (the checkbox is for the others)."""
        scene = self.scene
        georef = getattr(scene, "georef", None)
        geo = self.georef_check.isChecked() if georeferenced is None else georeferenced
        if geo and georef is None and Path(path).suffix.lower() not in (".gpkg", ".shp"):
            # (the backend's wording names the command line's --georeferenced)
            raise InputError(f"{Path(path).name}: the model has no georeference (georef.json "
                             "beside the mesh): untick 'georeferenced' to export in the model's "
                             "frame")
        notes = export_features(path, self.features, georef, geo,
                                measurements=self.measurements)
        self.status_label.setText(f"Exported {len(self.features)} feature(s) to {Path(path).name}."
                                  + "".join(f"\nNote: {n}." for n in notes))

    def save_measurements(self, path: str | Path, georeferenced: bool | None = None) -> None:
        """Write MEASUREMENTS.csv; centroids in the CRS when the georeferenced
        box is ticked (or ``georeferenced``) and the model has a georeference."""
        georef = getattr(self.scene, "georef", None)
        geo = self.georef_check.isChecked() if georeferenced is None else georeferenced
        in_crs = geo and georef is not None
        write_measurements_csv(path, measurements_in_frame(self.measurements, georef.origin)
                               if in_crs else self.measurements)
        self.status_label.setText(f"Saved {len(self.measurements)} measurement(s)"
                                  + (f" ({georef.crs})." if in_crs else " (local frame)."))

    def save_stereonet(self, path: str | Path) -> None:
        """Write the stereonet as PNG, SVG or PDF (by the suffix; another is
        refused, :func:`~napari_imgreg.interpret.structural.stereonet_format`)."""
        fmt = stereonet_format(path)
        with atomic_path(path) as tmp:
            self.figure.savefig(tmp, dpi=120, format=fmt)
        self.status_label.setText(f"Saved stereonet to {Path(path).name}.")
        self.status_label.setStyleSheet("")

    # ---------------------------------------------------------- dialogs
    def _guarded(self, fn, *args) -> None:
        try:
            fn(*args)
        except InputError as exc:
            self._fail(str(exc))
        except OSError as exc:  # a file that cannot be written: the user's to fix
            self._fail(one_line(exc))

    def _attach_dialog(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Registration result", "", "JSON (*.json)")
        if path and self.photo_layer is not None:
            self._guarded(self.attach_result, path)

    def _load_dialog(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Interpretations (pixels)", "", _GEOJSON_FILTER)
        if path:
            self._guarded(self.load_geojson, path)

    def _save_dialog(self) -> None:
        path, chosen = QFileDialog.getSaveFileName(self, "Save interpretations", "lines.geojson",
                                                   _GEOJSON_FILTER)
        path = with_filter_suffix(path, chosen)
        if path:
            self._guarded(self.save_geojson, path)

    def _export_dialog(self) -> None:
        path, chosen = QFileDialog.getSaveFileName(self, "Export 3D interpretations",
                                                   "LINES3D.geojson", _EXPORT_FILTER)
        path = with_filter_suffix(path, chosen)
        if path:
            self._guarded(self.export, path)

    def _save_csv_dialog(self) -> None:
        path, chosen = QFileDialog.getSaveFileName(self, "Save measurements", "MEASUREMENTS.csv",
                                                   "CSV (*.csv)")
        path = with_filter_suffix(path, chosen)
        if path:
            self._guarded(self.save_measurements, path)

    def _save_stereonet_dialog(self) -> None:
        path, chosen = QFileDialog.getSaveFileName(self, "Save stereonet", "stereonet.png",
                                                   "PNG (*.png);;SVG (*.svg);;PDF (*.pdf)")
        path = with_filter_suffix(path, chosen)
        if path:
            self._guarded(self.save_stereonet, path)


def with_filter_suffix(path: str, chosen_filter: str) -> str:
    """``path`` as a save dialog returned it, with the chosen filter's first
    suffix added when the name was typed without one (Qt's own dialog does
    not add it): ``("net", "SVG (*.svg)") -> "net.svg"``. The suffix names the
    format the file is written in."""
    if not path or Path(path).suffix or "*." not in chosen_filter:
        return path
    return path + "." + chosen_filter.split("*.", 1)[1].split()[0].rstrip(")")


def _notify(message: str, severity: str) -> None:
    """A napari notification ("error" or "warning"), as the workbench raises."""
    # napari is imported when needed: its import is slow and warns (pydantic).
    from napari.utils.notifications import show_error, show_warning

    (show_error if severity == "error" else show_warning)(message)


def _row(*widgets: QWidget, stretch: tuple[int, ...] | None = None) -> QHBoxLayout:
    """Widgets side by side (equal shares unless ``stretch`` says otherwise)."""
    row = QHBoxLayout()
    for k, widget in enumerate(widgets):
        row.addWidget(widget, 1 if stretch is None else stretch[k])
    return row


def _qcolor(color: str) -> Any:
    return QColor(to_hex(color))
