"""The workbench's pages: scene and photos, pose and DEM map, filters,
registration, manual control points.

Each page is a view of the workbench's :class:`~napari_imgreg.workspace.Workspace`
(``self.ws``): it shows its state and follows its changes through the
signals of the shared :class:`WorkbenchController`, and acts through the
controller, which runs the jobs, draws the layers and words the errors.
"""

from __future__ import annotations

import html
import math
import re
from dataclasses import replace
from datetime import datetime
from pathlib import Path
from typing import Callable

import matplotlib
import numpy as np
from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from qtpy.QtCore import Qt
from qtpy.QtGui import QColor
from qtpy.QtWidgets import (
    QAbstractItemView,
    QButtonGroup,
    QCheckBox,
    QComboBox,
    QDoubleSpinBox,
    QFileDialog,
    QFormLayout,
    QGridLayout,
    QGroupBox,
    QHBoxLayout,
    QInputDialog,
    QLabel,
    QLineEdit,
    QListWidget,
    QProgressBar,
    QPushButton,
    QRadioButton,
    QSpinBox,
    QTableWidget,
    QTableWidgetItem,
    QTabWidget,
    QVBoxLayout,
    QWidget,
)
from superqt import QLabeledDoubleSlider, QLabeledSlider

from ..camera import Pose
from ..registration.features import DESCRIPTORS, DETECTORS, PRESETS, available
from ..registration.filters import FilterParams
from ..io.photos import PHOTO_SUFFIXES
from ..registration.manual import MIN_PAIRS, MIN_PAIRS_FOCAL
from ..registration.params import RegistrationParams
from ..scene import has_colours, size_text
from ..registration.pose import PoseParams
from ..registration.features import FeatureParams
from ..validate import param_range
from ..workspace import WorkbenchError, one_line
from ..errors import InputError
from ._controller import (CORRESPONDENCE_COLORS, PAIR_COLORS, WorkbenchController,
                          outcome_text)
from ._shortcuts import key_of

__all__ = ["ScenePanel", "PosePanel", "FiltersPanel", "RegisterPanel", "SunBox", "ManualPanel",
           "TerrainMapCanvas", "sun_source_text"]

_MESH_FILTER = "Models (*.obj *.ply *.glb *.gltf *.tif *.tiff *.asc);;All files (*)"
_DEM_FILTER = "DEM (*.tif *.tiff *.asc);;All files (*)"
_PHOTO_FILTER = "Photos (" + " ".join(f"*{s}" for s in PHOTO_SUFFIXES) + ");;All files (*)"
_PAIRS_FILTER = "Control points (*.csv);;All files (*)"


def _hint(text: str) -> QLabel:
    label = QLabel(text)
    label.setWordWrap(True)
    label.setStyleSheet("color: #9e9e9e; font-size: 11px;")
    return label


#: The camera solvers offered (``PoseParams.solver``): value, label, tooltip.
SOLVER_CHOICES = (
    ("auto", "Auto",
     "EPnP with the photo's camera when its focal length is known (record or EXIF); "
     "otherwise P4Pf, estimating the focal length with the pose."),
    ("epnp", "EPnP: camera as given",
     "Never change the camera: the record's focal length, or the assumed one."),
    ("p4pf", "P4Pf: estimate focal",
     "Estimate the focal length with the pose (square pixels, principal point at the "
     "centre), then refine both together. For a photo whose focal length is unknown or "
     "suspect (a cropped or zoomed photo)."),
    ("dlt", "DLT: whole camera",
     "Seed 003's six-point DLT: focal lengths and principal point estimated too. Needs "
     "matched 3D points off one plane; falls back to P4Pf on a planar face."),
)


def _spin(lo: float, hi: float, decimals: int = 2, step: float = 1.0,
          suffix: str = "") -> QDoubleSpinBox:
    box = QDoubleSpinBox()
    box.setRange(lo, hi)
    box.setDecimals(decimals)
    box.setSingleStep(step)
    box.setKeyboardTracking(False)  # valueChanged on Enter / arrows, not per keystroke
    if suffix:
        box.setSuffix(suffix)
    return box


def _declared_range(box, settings, name: str) -> None:
    """Give a spin box (or slider) the declared range of a parameter
    (``RANGES`` of its dataclass, :func:`~napari_imgreg.validate.param_range`):
    the GUI offers exactly what a ``--params`` file may hold."""
    bounds = param_range(settings, name)
    if bounds is None:
        return
    lo, hi = bounds
    if isinstance(box, (QSpinBox, QLabeledSlider)) and not isinstance(box, QLabeledDoubleSlider):
        box.setRange(int(math.ceil(lo)), int(min(math.floor(hi), 2**31 - 1)))
    else:
        box.setRange(float(lo), float(hi))


#: What a preset of the Register tab sets: the feature settings the tab shows.
#: The others (upright, root_sift, invariant_channel, grid, guided matching)
#: are the registration's defaults for every detector: a preset keeps them.
PRESET_FIELDS = ("detector", "descriptor", "max_features", "threshold_scale", "ratio",
                 "symmetric", "geometric_model", "geometric_threshold_px")


def preset_features(name: str, current: FeatureParams) -> FeatureParams:
    """``current`` with the shown settings of preset ``name`` (the others kept)."""
    chosen = PRESETS[name]
    return replace(current, **{field: getattr(chosen, field) for field in PRESET_FIELDS})


def preset_name(features: FeatureParams) -> str:
    """The preset whose shown settings ``features`` has ("" for none: custom)."""
    return next((name for name, p in PRESETS.items()
                 if all(getattr(p, f) == getattr(features, f) for f in PRESET_FIELDS)), "")


def _set_quietly(widget, value) -> None:
    widget.blockSignals(True)
    try:
        if isinstance(widget, QCheckBox):
            widget.setChecked(bool(value))
        elif isinstance(widget, QComboBox):
            i = widget.findData(value)
            if i < 0:
                i = widget.findText(str(value))
            widget.setCurrentIndex(max(i, 0))
        else:
            widget.setValue(value)
    finally:
        widget.blockSignals(False)


def _with_browse(edit: QLineEdit, choose: Callable[[], str]) -> QWidget:
    row = QWidget()
    box = QHBoxLayout(row)
    box.setContentsMargins(0, 0, 0, 0)
    box.addWidget(edit, 1)
    button = QPushButton("…")
    button.setFixedWidth(28)
    box.addWidget(button)

    def browse() -> None:
        path = choose()
        if path:
            edit.setText(path)

    button.clicked.connect(browse)
    return row


# ====================================================================== scene
class ScenePanel(QWidget):
    """Open the model (mesh or DSM), DEM and georeference; add photos; switch 2D/3D."""

    def __init__(self, controller: WorkbenchController, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.ctrl = controller
        self.ws = controller.workspace  # the state shown here
        self.mesh_edit = QLineEdit()
        self.mesh_edit.setPlaceholderText("textured mesh (OBJ, PLY, GLB) or a DSM (GeoTIFF, .asc)")
        self.dem_edit = QLineEdit()
        self.dem_edit.setPlaceholderText("optional: DEM for camera altitudes")
        self.georef_edit = QLineEdit()
        self.georef_edit.setPlaceholderText("optional: georef.json (found beside the mesh)")
        self.open_button = QPushButton("Open model")
        self.sample_button = QPushButton("Sample outcrop")
        self.sample_button.setToolTip("The generated sample cliff with its DEM and three photos")
        self.scene_label = QLabel("No model yet.")
        self.scene_label.setWordWrap(True)
        # Busy while a model, the sample or photos load (the first sample takes ~30 s).
        self.loading_bar = QProgressBar()
        self.loading_bar.setRange(0, 0)
        self.loading_bar.setTextVisible(False)
        self.loading_bar.setMaximumHeight(8)
        self.loading_bar.setVisible(False)
        self.loading_label = _hint("")
        self.loading_label.setVisible(False)
        for edit in (self.mesh_edit, self.dem_edit, self.georef_edit):
            edit.setMinimumWidth(120)

        form = QFormLayout()
        form.addRow("Model", _with_browse(self.mesh_edit,
                                          lambda: self._file("Model", _MESH_FILTER)))
        form.addRow("DEM", _with_browse(self.dem_edit, lambda: self._file("DEM", _DEM_FILTER)))
        form.addRow("Georef", _with_browse(self.georef_edit,
                                           lambda: self._file("Georeference", "JSON (*.json)")))
        buttons = QHBoxLayout()
        buttons.addWidget(self.open_button)
        buttons.addWidget(self.sample_button)

        self.photo_list = QListWidget()
        self.photo_list.setMinimumHeight(60)
        self.photo_list.setMaximumHeight(110)
        self.add_photos_button = QPushButton("Add photos…")
        self.add_folder_button = QPushButton("Add folder…")
        photo_buttons = QHBoxLayout()
        photo_buttons.addWidget(self.add_photos_button)
        photo_buttons.addWidget(self.add_folder_button)
        self.prior_label = QLabel()
        self.prior_label.setWordWrap(True)
        self.prior_label.setTextInteractionFlags(Qt.TextSelectableByMouse)

        self.view_2d_button = QPushButton("2D: photo | render")
        self.view_3d_button = QPushButton("3D: model and cameras")
        self.view_pose_button = QPushButton("3D, seen from the photo's pose")
        view_row = QGridLayout()
        view_row.addWidget(self.view_2d_button, 0, 0)
        view_row.addWidget(self.view_3d_button, 0, 1)
        view_row.addWidget(self.view_pose_button, 1, 0, 1, 2)

        layout = QVBoxLayout(self)
        model_box = QGroupBox("Model")
        model_layout = QVBoxLayout(model_box)
        model_layout.addLayout(form)
        model_layout.addLayout(buttons)
        model_layout.addWidget(self.scene_label)
        model_layout.addWidget(self.loading_bar)
        model_layout.addWidget(self.loading_label)
        photo_box = QGroupBox("Photos")
        photo_layout = QVBoxLayout(photo_box)
        photo_layout.addWidget(_hint("Each photo's prior comes from its sensor record (the .json "
                                     "beside it), else from its EXIF/XMP."))
        photo_layout.addWidget(self.photo_list)
        photo_layout.addLayout(photo_buttons)
        photo_layout.addWidget(self.prior_label)
        view_box = QGroupBox("View")
        view_layout = QVBoxLayout(view_box)
        view_layout.addLayout(view_row)
        view_layout.addWidget(_hint(
            "2D: the photo (left) and the render from the current pose (right). "
            "3D: the textured model with every photo's camera and view frustum."))
        layout.addWidget(model_box)
        layout.addWidget(photo_box)
        layout.addWidget(view_box)
        layout.addStretch(1)

        self.open_button.clicked.connect(self.open_model)
        self.sample_button.clicked.connect(controller.open_sample)
        self.add_photos_button.clicked.connect(self._add_photos_dialog)
        self.add_folder_button.clicked.connect(self._add_folder_dialog)
        self.photo_list.currentRowChanged.connect(self._photo_chosen)
        self.view_2d_button.clicked.connect(controller.show_2d)
        self.view_3d_button.clicked.connect(lambda: controller.show_3d())
        self.view_pose_button.clicked.connect(lambda: controller.show_3d(from_pose=True))
        controller.scene_changed.connect(self._scene_changed)
        controller.photos_changed.connect(self._photos_changed)
        controller.photo_changed.connect(self._photo_changed)
        controller.loading.connect(self._loading)
        self._scene_changed()

    def _loading(self, message: str) -> None:
        """Say what is loading, with a busy bar; "" when it is over."""
        self.loading_bar.setVisible(bool(message))
        self.loading_label.setVisible(bool(message))
        self.loading_label.setText(message[:1].upper() + message[1:])
        for button in (self.open_button, self.sample_button):
            button.setEnabled(not message)

    def _file(self, title: str, filt: str) -> str:
        path, _ = QFileDialog.getOpenFileName(self, title, "", filt)
        return path

    def open_model(self) -> None:
        mesh = self.mesh_edit.text().strip()
        if not mesh:
            self.ctrl.notify_error("Choose a model file first.")
            return
        self.ctrl.open_scene(mesh, self.dem_edit.text().strip() or None,
                             self.georef_edit.text().strip() or None)

    def _add_photos_dialog(self) -> None:
        paths, _ = QFileDialog.getOpenFileNames(self, "Photos", "", _PHOTO_FILTER)
        if paths:
            self.ctrl.add_photos(paths)

    def _add_folder_dialog(self) -> None:
        folder = QFileDialog.getExistingDirectory(self, "Folder of photos")
        if folder:
            paths = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in PHOTO_SUFFIXES)
            self.ctrl.add_photos(paths)

    def _photo_chosen(self, row: int) -> None:
        current = self.ws.current
        if row >= 0 and (current is None or self.ws.photos.index(current) != row):
            self.ctrl.select_photo(row)

    def _scene_changed(self) -> None:
        scene = self.ws.scene
        if scene is None:
            self.scene_label.setText("No model yet: open one, or try the sample outcrop.")
            return
        files = dict(self.ws.scene_files)
        mesh = Path(files.get("mesh") or "")
        if (scene.georef is not None and not files.get("georef") and mesh.name
                and mesh.suffix.lower() not in (".tif", ".tiff", ".asc")):
            # Not given: the mesh reader took the georef.json beside the mesh.
            beside = mesh.parent / "georef.json"
            if beside.exists():
                files["georef"] = str(beside)
        for edit, key in ((self.mesh_edit, "mesh"), (self.dem_edit, "dem"),
                          (self.georef_edit, "georef")):
            if files.get(key):
                edit.setText(files[key])
        lo, hi = scene.bounds
        if getattr(scene, "is_cloud", False):  # a scan has no texture to miss
            looks = ("RGB colour" if scene.vertex_colors is not None else
                     "intensity" if scene.has_intensity else "no intensity or colour: shaded")
        else:
            looks = "textured" if scene.has_texture else "no texture"
        parts = [f"<b>{scene.name}</b>: {size_text(scene)}", looks,
                 f"{hi[0] - lo[0]:.0f} × {hi[1] - lo[1]:.0f} × {hi[2] - lo[2]:.0f} m"]
        if scene.georef is not None:
            parts.append(f"georeferenced ({scene.georef.crs})")
        if scene.dem is not None:
            parts.append(f"DEM {scene.dem.heights.shape[1]}×{scene.dem.heights.shape[0]} "
                         f"at {scene.dem.dx:g} m")
        else:
            parts.append("no DEM: altitudes from the model surface")
        # The reader's notes (a cloud's CRS rule, decimation) stay in view: the
        # status line that also shows them is overwritten by the next message.
        notes = "".join(f"<li>{html.escape(n)}</li>" for n in scene.warnings)
        self.scene_label.setText(", ".join(parts) + (f"<br>Assumed:<ul>{notes}</ul>" if notes else ""))

    def _photos_changed(self) -> None:
        self.photo_list.blockSignals(True)
        self.photo_list.clear()
        for ps in self.ws.photos:
            self.photo_list.addItem(ps.name)
        if self.ws.current in self.ws.photos:
            self.photo_list.setCurrentRow(self.ws.photos.index(self.ws.current))
        self.photo_list.blockSignals(False)

    def _photo_changed(self) -> None:
        ps = self.ws.current
        if ps is None:
            self.prior_label.setText("")
            return
        self._photos_changed()
        w, h = ps.size
        notes = "".join(f"<li>{n}</li>" for n in ps.prior.assumptions) or "<li>none</li>"
        s = ps.prior.sigma
        record = ps.record_path.name if ps.record_path.exists() else "none (EXIF/XMP)"
        self.prior_label.setText(
            f"<b>{ps.name}</b>: {w}×{h} px, focal {ps.intrinsics.fx:.0f} px "
            f"({ps.intrinsics.hfov_deg:.0f}° wide); sensor record: {record}; "
            f"σ {s.position_m:g} m, {s.altitude_m:g} m alt., {s.angles_deg:g}°"
            f"<br>Assumed:<ul style='margin:0'>{notes}</ul>")


# ======================================================================= map
_BG, _FG = "#262930", "#d0d3d8"  # napari's dark theme


def _land_colormap():
    terrain = matplotlib.colormaps["terrain"]
    return ListedColormap(terrain(np.linspace(0.25, 0.95, 256)), name="land")


_LAND = _land_colormap()
class TerrainMapCanvas(FigureCanvasQTAgg):
    """The DEM as a map with the cameras: click or drag to move the current
    camera (its altitude follows the DEM), Shift-click to turn it toward a
    point, wheel to zoom."""

    def __init__(self, controller: WorkbenchController) -> None:
        self.figure = Figure(figsize=(4.0, 3.6), layout="constrained", facecolor=_BG)
        super().__init__(self.figure)
        self.ctrl = controller
        self.ws = controller.workspace  # the state shown here
        self.ax = self.figure.add_subplot(111)
        self.ax.set_aspect("equal")
        self._dragging = False
        self._artists: dict = {}
        self._extent = None
        self._background = None
        self.mpl_connect("draw_event", self._on_draw)
        self.setMinimumHeight(300)
        self.mpl_connect("button_press_event", self._press)
        self.mpl_connect("motion_notify_event", self._motion)
        self.mpl_connect("button_release_event", self._release)
        self.mpl_connect("scroll_event", self._scroll)

    def set_terrain(self) -> None:
        ax = self.ax
        ax.clear()
        self._artists = {}
        self._background = None
        tmap, scene = self.ws.terrain, self.ws.scene
        if tmap is None or scene is None:
            self.draw_idle()
            return
        ext = tmap.image_extent
        ax.set_facecolor("#1e1f24")
        ax.imshow(tmap.hillshade(), cmap="gray", extent=ext, origin="upper", vmin=0, vmax=1,
                  interpolation="bilinear")
        ax.imshow(tmap.heights, cmap=_LAND, extent=ext, origin="upper", alpha=0.35,
                  interpolation="bilinear")
        lo, hi = scene.bounds
        ax.plot([lo[0], hi[0], hi[0], lo[0], lo[0]], [lo[1], lo[1], hi[1], hi[1], lo[1]],
                ls="--", lw=0.8, color="#e0e0e0", label="model")
        ax.set_xlabel("x east (m)", fontsize=8, color=_FG)
        ax.set_ylabel("y north (m)", fontsize=8, color=_FG)
        ax.tick_params(labelsize=7, colors=_FG)
        for spine in ax.spines.values():
            spine.set_color("#5a5f6a")
        ax.set_title(f"{tmap.source} (dashed: the model) — click or drag: move; "
                     "Shift-click: turn",
                     fontsize=8, color=_FG)
        self._extent = ext
        self._make_camera_artists()
        self.fit()

    def fit(self) -> None:
        """Show the terrain and every camera."""
        if self._extent is None:
            return
        left, right, bottom, top = self._extent
        xs, ys = [left, right], [bottom, top]
        for ps in self.ws.photos:
            xs.append(ps.pose.center[0])
            ys.append(ps.pose.center[1])
        pad = 0.03 * max(max(xs) - min(xs), max(ys) - min(ys))
        xlim, ylim = (min(xs) - pad, max(xs) + pad), (min(ys) - pad, max(ys) + pad)
        if not (np.allclose(self.ax.get_xlim(), xlim) and np.allclose(self.ax.get_ylim(), ylim)):
            # A full redraw costs ~0.1 s: only when the view moves, not on every photo switch.
            self.ax.set_xlim(*xlim)
            self.ax.set_ylim(*ylim)
            self._background = None
        self.update_cameras()

    def draw_idle(self) -> None:
        """Redraw soon; a hidden map (another tab) redraws when it is shown."""
        if not self.isVisible():
            self._stale = True
            return
        super().draw_idle()

    def showEvent(self, event) -> None:  # noqa: N802 (Qt)
        super().showEvent(event)
        if getattr(self, "_stale", False):
            self._stale = False
            super().draw_idle()

    def _make_camera_artists(self) -> None:
        ax = self.ax
        kw = {"animated": True}  # drawn by blitting: a pose change costs milliseconds
        (others,) = ax.plot([], [], "o", ms=4, color="#fdd835", mec="black", mew=0.5, **kw)
        (prior,) = ax.plot([], [], "o", ms=8, mfc="none", mec="white", mew=1.5, **kw)
        (wedge,) = ax.fill([0, 0], [0, 0], color="#ff1744", alpha=0.2, lw=1.0, ec="#ff1744", **kw)
        (axis,) = ax.plot([], [], color="#ff1744", lw=1.5, **kw)
        (camera,) = ax.plot([], [], "o", ms=8, color="#ff1744", mec="white", mew=1.2, **kw)
        self._artists = {"others": others, "prior": prior, "wedge": wedge, "axis": axis,
                         "camera": camera}

    def _on_draw(self, event=None) -> None:
        self._background = self.copy_from_bbox(self.figure.bbox)
        for artist in self._artists.values():
            self.ax.draw_artist(artist)

    def update_cameras(self) -> None:
        """Move the camera markers and the view wedge to the current poses."""
        ps = self.ws.current
        if self._extent is None or not self._artists:
            return
        a = self._artists
        if ps is None:
            for artist in a.values():
                artist.set_visible(False)
        else:
            for artist in a.values():
                artist.set_visible(True)
            others = np.array([p.pose.center[:2] for p in self.ws.photos
                               if p is not ps]).reshape(-1, 2)
            a["others"].set_data(others[:, 0], others[:, 1])
            pc = ps.prior.pose.center
            a["prior"].set_data([pc[0]], [pc[1]])
            c = ps.pose.center
            trend = math.radians(ps.pose.attitude[0])
            half = math.atan2(ps.intrinsics.width / 2.0, ps.intrinsics.fx)
            left, right, bottom, top = self._extent
            length = 0.35 * max(right - left, top - bottom)
            wedge = [c[:2]]
            for ang in np.linspace(trend - half, trend + half, 12):
                wedge.append(c[:2] + length * np.array([math.sin(ang), math.cos(ang)]))
            a["wedge"].set_xy(np.array(wedge + [c[:2]]))
            tip = c[:2] + 0.6 * length * np.array([math.sin(trend), math.cos(trend)])
            a["axis"].set_data([c[0], tip[0]], [c[1], tip[1]])
            a["camera"].set_data([c[0]], [c[1]])
        if self._background is None:
            self.draw_idle()
            return
        self.restore_region(self._background)
        for artist in a.values():
            self.ax.draw_artist(artist)
        # Paint from the updated buffer at the next event-loop turn (blit() would
        # repaint synchronously and hold up the render that follows the edit).
        self.update()

    # -- mouse
    def _inside(self, event) -> bool:
        return event.inaxes is self.ax and event.xdata is not None

    def _press(self, event) -> None:
        if not self._inside(event) or event.button != 1:
            return
        if _shift(event):
            self.ctrl.turn_toward(event.xdata, event.ydata)
            return
        if self.ctrl.move_on_map(event.xdata, event.ydata):
            self._dragging = True

    def _motion(self, event) -> None:
        if self._dragging and self._inside(event):
            self.ctrl.move_on_map(event.xdata, event.ydata, continuing=True)

    def _release(self, event) -> None:
        if self._dragging:
            self._dragging = False
            self.ctrl.finish_drag()

    def _scroll(self, event) -> None:
        if not self._inside(event):
            return
        factor = 0.8 if event.button == "up" else 1.25
        x, y = event.xdata, event.ydata
        x0, x1 = self.ax.get_xlim()
        y0, y1 = self.ax.get_ylim()
        self.ax.set_xlim(x + (x0 - x) * factor, x + (x1 - x) * factor)
        self.ax.set_ylim(y + (y0 - y) * factor, y + (y1 - y) * factor)
        self._background = None
        self.draw_idle()


def _shift(event) -> bool:
    """Shift held during a matplotlib mouse event (the Qt event knows best)."""
    gui = getattr(event, "guiEvent", None)
    if gui is not None and hasattr(gui, "modifiers"):
        if gui.modifiers() & Qt.KeyboardModifier.ShiftModifier:
            return True
    return "shift" in getattr(event, "modifiers", ()) or event.key == "shift"


# ======================================================================= pose
#: Nudge steps: (degrees, metres).
STEPS = {"fine": (0.1, 0.25), "normal": (1.0, 1.0), "coarse": (5.0, 5.0)}


class PosePanel(QWidget):
    """The current photo's pose: values, nudges, the DEM map, undo, save."""

    def __init__(self, controller: WorkbenchController, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.ctrl = controller
        self.ws = controller.workspace  # the state shown here
        self.title = QLabel("No photo.")
        self.undo_button = QPushButton("Undo")
        self.redo_button = QPushButton("Redo")
        self.prior_button = QPushButton("Prior")
        self.prior_button.setToolTip("Back to the pose of the sensor record (undoable)")
        top = QHBoxLayout()
        top.addWidget(self.title, 1)
        for b in (self.undo_button, self.redo_button, self.prior_button):
            top.addWidget(b)

        self.x_spin = _spin(-1e7, 1e7, 2, 0.5, " m")
        self.y_spin = _spin(-1e7, 1e7, 2, 0.5, " m")
        self.z_spin = _spin(-1e5, 1e5, 2, 0.5, " m")
        self.agl_spin = _spin(-1e4, 1e4, 2, 0.25, " m")
        self.agl_spin.setToolTip("Height above the DEM (or the model): the altitude offset")
        self.trend_spin = _spin(-720, 720, 2, 0.5, "°")
        self.trend_spin.setWrapping(True)
        self.plunge_spin = _spin(-90, 90, 2, 0.5, "°")
        self.roll_spin = _spin(-180, 180, 2, 0.5, "°")
        self.crs_label = _hint("")
        values = QGridLayout()
        values.addWidget(QLabel("x (east)"), 0, 0)
        values.addWidget(self.x_spin, 0, 1)
        values.addWidget(QLabel("y (north)"), 0, 2)
        values.addWidget(self.y_spin, 0, 3)
        values.addWidget(QLabel("z"), 1, 0)
        values.addWidget(self.z_spin, 1, 1)
        values.addWidget(QLabel("above ground"), 1, 2)
        values.addWidget(self.agl_spin, 1, 3)
        values.addWidget(QLabel("trend"), 2, 0)
        values.addWidget(self.trend_spin, 2, 1)
        values.addWidget(QLabel("plunge"), 2, 2)
        values.addWidget(self.plunge_spin, 2, 3)
        values.addWidget(QLabel("roll"), 3, 0)
        values.addWidget(self.roll_spin, 3, 1)
        values.addWidget(self.crs_label, 3, 2, 1, 2)

        # Nudges
        self.step_group = QButtonGroup(self)
        step_row = QHBoxLayout()
        step_row.addWidget(QLabel("Step"))
        for k, (name, (deg, m)) in enumerate(STEPS.items()):
            b = QRadioButton(f"{name} {deg:g}° / {m:g} m")
            b.setProperty("step", name)
            self.step_group.addButton(b, k)
            step_row.addWidget(b)
            if name == "normal":
                b.setChecked(True)
        step_row.addStretch(1)
        self.nudge_buttons: dict[str, QPushButton] = {}
        grid = QGridLayout()
        spec = [
            ("turn left", "↶ left", dict(d_trend=-1)),
            ("turn right", "right ↷", dict(d_trend=1)),
            ("look up", "look up", dict(d_plunge=-1)), ("look down", "look down", dict(d_plunge=1)),
            ("roll left", "roll ⟲", dict(d_roll=-1)), ("roll right", "roll ⟳", dict(d_roll=1)),
            ("forward", "forward", dict(forward=1)), ("back", "back", dict(forward=-1)),
            ("left", "step left", dict(right=-1)), ("right", "step right", dict(right=1)),
            ("up", "up", dict(up=1)), ("down", "down", dict(up=-1)),
        ]
        for k, (key, text, amounts) in enumerate(spec):
            b = QPushButton(text)
            b.setToolTip(f"{key} by one step (key {key_of(key)} over the canvas)")
            b.clicked.connect(lambda _=False, key=key, a=amounts: self.nudge(key, **a))
            self.nudge_buttons[key] = b
            grid.addWidget(b, k // 4, k % 4)

        self.map = TerrainMapCanvas(controller)
        self.fit_button = QPushButton("Fit map")
        self.save_button = QPushButton("Save pose to sensor record")
        self.save_button.setToolTip("Write position and attitude into the photo's .json sidecar")
        self.render_label = _hint("")
        bottom = QHBoxLayout()
        bottom.addWidget(self.fit_button)
        bottom.addStretch(1)
        bottom.addWidget(self.save_button)

        layout = QVBoxLayout(self)
        layout.addLayout(top)
        pose_box = QGroupBox("Pose (local frame)")
        pose_layout = QVBoxLayout(pose_box)
        pose_layout.addLayout(values)
        pose_layout.addLayout(step_row)
        pose_layout.addLayout(grid)
        layout.addWidget(pose_box)
        map_box = QGroupBox("DEM map")
        map_layout = QVBoxLayout(map_box)
        map_layout.addWidget(self.map, 1)
        map_layout.addLayout(bottom)
        layout.addWidget(map_box, 1)
        layout.addWidget(self.render_label)

        self.undo_button.clicked.connect(controller.undo)
        self.redo_button.clicked.connect(controller.redo)
        self.prior_button.clicked.connect(controller.reset_to_prior)
        self.fit_button.clicked.connect(self.map.fit)
        self.save_button.clicked.connect(controller.save_record)
        for name, spin in (("x", self.x_spin), ("y", self.y_spin), ("z", self.z_spin),
                           ("trend", self.trend_spin), ("plunge", self.plunge_spin),
                           ("roll", self.roll_spin)):
            spin.valueChanged.connect(lambda v, name=name: self._typed(name, v))
        self.agl_spin.valueChanged.connect(self._typed_agl)
        controller.scene_changed.connect(self.map.set_terrain)
        controller.photos_changed.connect(self.map.update_cameras)
        controller.photo_changed.connect(self._photo_changed)
        controller.pose_changed.connect(self._pose_changed)
        controller.render_shown.connect(self._render_shown)
        self._pose_changed("")

    @property
    def step(self) -> tuple[float, float]:
        button = self.step_group.checkedButton()
        return STEPS[button.property("step") if button is not None else "normal"]

    def nudge(self, key: str, **unit: float) -> None:
        """One nudge of the current step (``unit`` gives the direction of each amount)."""
        deg, m = self.step
        amounts = {k: v * (deg if k.startswith("d_") else m) for k, v in unit.items()}
        self.ctrl.nudge(f"{key} {deg if any(k.startswith('d_') for k in unit) else m:g}", **amounts)

    def _photo_changed(self) -> None:
        self.map.fit()
        self._pose_changed("photo")

    def _pose_changed(self, source: str) -> None:
        ps = self.ws.current
        enabled = ps is not None
        for w in (self.x_spin, self.y_spin, self.z_spin, self.agl_spin, self.trend_spin,
                  self.plunge_spin, self.roll_spin, self.save_button, self.prior_button,
                  *self.nudge_buttons.values()):
            w.setEnabled(enabled)
        if ps is None:
            self.undo_button.setEnabled(False)
            self.redo_button.setEnabled(False)
            return
        h = ps.history
        self.undo_button.setEnabled(h.can_undo)
        self.redo_button.setEnabled(h.can_redo)
        self.undo_button.setToolTip(f"Undo: {h.undo_label}" if h.can_undo else "")
        self.title.setText(f"<b>{ps.name}</b> — {h.label}")
        x, y, z = ps.pose.center
        trend, plunge, roll = ps.pose.attitude
        for spin, value in ((self.x_spin, x), (self.y_spin, y), (self.z_spin, z),
                            (self.trend_spin, trend), (self.plunge_spin, plunge),
                            (self.roll_spin, roll)):
            _set_quietly(spin, float(value))
        agl = self.ws.height_above_ground()
        self.agl_spin.setEnabled(agl is not None)
        if agl is not None:
            _set_quietly(self.agl_spin, agl)
        scene = self.ws.scene
        if scene is not None and scene.georef is not None:
            o = scene.georef.origin
            self.crs_label.setText(f"E {x + o[0]:,.1f}  N {y + o[1]:,.1f}  H {z + o[2]:,.1f}"
                                   f"<br>{scene.georef.crs}")
        else:
            self.crs_label.setText("")
        self.map.update_cameras()

    def _typed(self, name: str, value: float) -> None:
        """One value typed: only that component changes (the others keep full precision)."""
        ps = self.ws.current
        if ps is None:
            return
        center = ps.pose.center.copy()
        attitude = dict(zip(("trend", "plunge", "roll"), ps.pose.attitude))
        if name in ("x", "y", "z"):
            center["xyz".index(name)] = value
        else:
            attitude[name] = value
        pose = Pose.from_attitude(attitude["trend"], attitude["plunge"], attitude["roll"], center)
        self.ctrl.set_pose(pose, f"{name} typed")

    def _typed_agl(self) -> None:
        ps = self.ws.current
        if ps is None:
            return
        x, y, _ = ps.pose.center
        self.ctrl.move_on_map(x, y, height=self.agl_spin.value())

    def _render_shown(self, kind: str) -> None:
        latency = self.ctrl.latency.get("render" if kind == "full" else "preview")
        r = self.ctrl.last_render if kind == "full" else None
        size = f" {r.shape[1]}×{r.shape[0]}" if r is not None else ""
        if latency is not None:
            self.render_label.setText(f"{'full' if kind == 'full' else 'reduced'} render{size} "
                                      f"shown {latency * 1000:.0f} ms after the last edit")


# ==================================================================== filters
class FilterEditor(QWidget):
    """Sliders for one image's :class:`~napari_imgreg.registration.filters.FilterParams`."""

    #: name, label, kind, lo, hi, decimals
    FIELDS = (
        ("gamma", "gamma", "float", 0.2, 5.0, 2),
        ("brightness", "brightness", "float", -100.0, 100.0, 0),
        ("contrast", "contrast", "float", 0.2, 3.0, 2),
        ("gradient_sigma_px", "smoothing σ (px)", "float", 0.0, 10.0, 1),
        ("wallis_window", "window (px)", "int", 15, 151, 0),
        ("wallis_target_mean", "target mean", "float", 0.0, 255.0, 0),
        ("wallis_target_std", "target std", "float", 5.0, 120.0, 0),
        ("wallis_brightness", "brightness b", "float", 0.0, 1.0, 2),
        ("wallis_contrast", "contrast c", "float", 0.0, 1.0, 2),
        ("clahe_clip", "clip limit", "float", 1.0, 10.0, 1),
        ("clahe_tiles", "tiles", "int", 2, 32, 0),
    )

    def __init__(self, controller: WorkbenchController, which: str,
                 on_edit: Callable[[str], None], parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.ctrl, self.which, self.on_edit = controller, which, on_edit
        self.ws = controller.workspace
        self.widgets: dict[str, QWidget] = {}
        self.wallis_check = QCheckBox("Wallis filter (local mean and contrast)")
        self.clahe_check = QCheckBox("CLAHE (adaptive histogram equalisation)")
        self.widgets["wallis"] = self.wallis_check
        # A lidar scan's intensity and a photo share their edges, not their grey levels.
        self.gradient_check = QCheckBox("gradient magnitude (for a lidar intensity render)")
        self.gradient_check.setToolTip(
            "Match edges instead of grey levels: the image becomes the strength of its "
            "gradient. A scan's intensity is the rock's reflectance to the laser, a photo's "
            "brightness the day's light on it; where either changes (contacts, stains, ledges, "
            "the skyline) is what they share.")
        self.widgets["gradient"] = self.gradient_check
        self.widgets["clahe"] = self.clahe_check
        forms = {"basic": QFormLayout(), "gradient": QFormLayout(), "wallis": QFormLayout(),
                 "clahe": QFormLayout()}
        for name, label, kind, lo, hi, dec in self.FIELDS:
            if kind == "int":
                w = QLabeledSlider(Qt.Orientation.Horizontal)
                w.setRange(int(lo), int(hi))
                if name == "wallis_window":
                    w.setSingleStep(2)
            else:
                w = QLabeledDoubleSlider(Qt.Orientation.Horizontal)
                w.setRange(lo, hi)
                w.setDecimals(dec)
            _declared_range(w, FilterParams, name)  # FIELDS' lo/hi: where none is declared
            w.valueChanged.connect(lambda v, name=name: self._changed(name, v))
            self.widgets[name] = w
            group = (name.split("_")[0] if name.startswith(("wallis", "clahe", "gradient"))
                     else "basic")
            forms[group].addRow(label, w)
        self.wallis_check.toggled.connect(lambda v: self._changed("wallis", v))
        self.gradient_check.toggled.connect(lambda v: self._changed("gradient", v))
        self.clahe_check.toggled.connect(lambda v: self._changed("clahe", v))
        self.reset_button = QPushButton("Reset")
        self.reset_button.setToolTip("Back to the filters a new session starts with "
                                     "(the Wallis filter on)")
        self.reset_button.clicked.connect(self.reset)
        layout = QVBoxLayout(self)
        layout.addLayout(forms["basic"])
        layout.addWidget(self.gradient_check)
        layout.addLayout(forms["gradient"])
        layout.addWidget(self.wallis_check)
        layout.addLayout(forms["wallis"])
        layout.addWidget(self.clahe_check)
        layout.addLayout(forms["clahe"])
        layout.addWidget(self.reset_button, 0, Qt.AlignRight)
        self.refresh()

    @property
    def params(self):
        p = self.ws.params
        return p.photo_filters if self.which == "photo" else p.render_filters

    def refresh(self) -> None:
        p = self.params
        for name, w in self.widgets.items():
            _set_quietly(w, getattr(p, name))
        self._enable()

    def _enable(self) -> None:
        p = self.params
        for name, w in self.widgets.items():
            if name.startswith("wallis_"):
                w.setEnabled(p.wallis)
            elif name.startswith("clahe_"):
                w.setEnabled(p.clahe)
            elif name.startswith("gradient_"):
                w.setEnabled(p.gradient)

    def _changed(self, name: str, value) -> None:
        if name in ("wallis_window",):
            value = int(value) | 1
        elif name == "clahe_tiles":
            value = int(value)
        elif name in ("wallis", "clahe", "gradient"):
            value = bool(value)
        else:
            value = float(value)
        setattr(self.params, name, value)
        self._enable()
        self.ctrl.params_edited()
        self.on_edit(self.which)

    def reset(self) -> None:
        """Back to the filters a new session starts with on this model (Wallis
        on; a point cloud's gradient too): :meth:`RegistrationParams.default_filters`."""
        fresh = RegistrationParams.default_filters(self.which, self.ws.scene)
        for name in fresh.to_dict():
            setattr(self.params, name, getattr(fresh, name))
        self.refresh()
        self.ctrl.params_edited()
        self.on_edit(self.which)


class FiltersPanel(QWidget):
    """Radiometric filters for the photo and the render, with live preview."""

    def __init__(self, controller: WorkbenchController, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.ctrl = controller
        self.ws = controller.workspace  # the state shown here
        self.preview_check = QCheckBox(
            "Preview: show the filtered images (grey, as the detector sees them)")
        self.link_check = QCheckBox("Same filters for photo and render")
        self.photo_editor = FilterEditor(controller, "photo", self._edited)
        self.render_editor = FilterEditor(controller, "render", self._edited)
        self.tabs = QTabWidget()
        self.tabs.addTab(self.photo_editor, "Photo")
        self.tabs.addTab(self.render_editor, "Render")
        self.latency_label = _hint("")
        layout = QVBoxLayout(self)
        layout.addWidget(self.preview_check)
        layout.addWidget(self.link_check)
        layout.addWidget(self.tabs)
        layout.addWidget(_hint(
            "Filters act on the luminance the detector reads: gamma lifts shadows, Wallis "
            "evens out local brightness and contrast (wet rock, shade), CLAHE equalises. "
            "They are part of the registration parameters (Register tab) and of every trial."))
        layout.addWidget(self.latency_label)
        layout.addStretch(1)
        self.preview_check.toggled.connect(controller.set_filter_preview)
        controller.params_changed.connect(self.refresh)
        controller.filters_shown.connect(self._shown)

    def editor(self, which: str) -> FilterEditor:
        return self.photo_editor if which == "photo" else self.render_editor

    def _edited(self, which: str) -> None:
        if self.link_check.isChecked():
            other = "render" if which == "photo" else "photo"
            src = self.editor(which).params
            if other == "render":
                self.ws.params.render_filters = replace(src)
            else:
                self.ws.params.photo_filters = replace(src)
            self.editor(other).refresh()
            self.ctrl.filters_edited(other)
        self.ctrl.filters_edited(which)

    def refresh(self) -> None:
        self.photo_editor.refresh()
        self.render_editor.refresh()

    def _shown(self, which: str) -> None:
        latency = self.ctrl.latency.get(f"filter {which}")
        if latency is not None:
            self.latency_label.setText(
                f"{which} preview shown {latency * 1000:.0f} ms after the last change")


# =============================================================== registration
class RegisterPanel(QWidget):
    """Detector/descriptor, key parameters, Run / Auto / Cancel, display options."""

    def __init__(self, controller: WorkbenchController, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.ctrl = controller
        self.ws = controller.workspace  # the state shown here
        self.preset_combo = QComboBox()
        self.preset_combo.addItem("(custom)", "")
        default = FeatureParams()
        for name in PRESETS:
            shown = f"{name} (default)" if preset_name(default) == name else name
            self.preset_combo.addItem(shown, name)
        self.preset_combo.setToolTip(
            "Sets the detector, descriptor and matching settings below; the registration's "
            "other feature settings (upright and RootSIFT descriptors, the "
            "illumination-invariant channel) are kept")
        self.detector_combo = QComboBox()
        for name in DETECTORS:
            self.detector_combo.addItem(name, name)
        self.descriptor_combo = QComboBox()
        for name in DESCRIPTORS:
            self.descriptor_combo.addItem(name, name)
        for combo in (self.detector_combo, self.descriptor_combo):
            model = combo.model()
            for i in range(combo.count()):
                if not available(combo.itemData(i)):
                    model.item(i).setEnabled(False)
                    model.item(i).setToolTip("not in this OpenCV build")
        self.max_features_spin = QSpinBox()
        self.max_features_spin.setRange(500, 50_000)
        self.max_features_spin.setSingleStep(500)
        _declared_range(self.max_features_spin, FeatureParams, "max_features")
        self.threshold_spin = _spin(0.05, 4.0, 2, 0.1)
        self.threshold_spin.setToolTip(
            "× the detector's default threshold: < 1 finds more, weaker points")
        _declared_range(self.threshold_spin, FeatureParams, "threshold_scale")
        self.ratio_spin = _spin(0.5, 0.95, 2, 0.05)
        _declared_range(self.ratio_spin, FeatureParams, "ratio")
        self.symmetric_check = QCheckBox("mutual best matches")
        self.model_combo = QComboBox()
        for name in ("fundamental", "homography", "none"):
            self.model_combo.addItem(name, name)
        self.geom_spin = _spin(0.5, 20.0, 1, 0.5, " px")
        _declared_range(self.geom_spin, FeatureParams, "geometric_threshold_px")
        self.pnp_spin = _spin(1.0, 50.0, 1, 1.0, " px")
        _declared_range(self.pnp_spin, PoseParams, "reprojection_error_px")
        # How the camera is solved: the choice a photo without a known focal
        # length (or a suspect one) needs; the texts say what each assumes.
        self.solver_combo = QComboBox()
        for name, label, tip in SOLVER_CHOICES:
            self.solver_combo.addItem(label, name)
            self.solver_combo.setItemData(self.solver_combo.count() - 1, tip,
                                          Qt.ItemDataRole.ToolTipRole)
        self.solver_combo.setToolTip(
            "How the camera is solved from the matches. Auto estimates the focal length only "
            "when the photo's record does not give it.")
        self.k1_check = QCheckBox("k1 too")
        self.k1_check.setToolTip(
            "With an estimated focal length, also estimate the lens's radial distortion k1 "
            "(needs matches out to the photo's corners).")
        self.width_spin = QSpinBox()
        self.width_spin.setRange(256, 8192)
        self.width_spin.setSingleStep(128)
        self.width_spin.setSuffix(" px")
        _declared_range(self.width_spin, RegistrationParams, "match_width")
        self.trials_spin = QSpinBox()
        self.trials_spin.setRange(1, 12)
        _declared_range(self.trials_spin, RegistrationParams, "max_trials")
        self.search_check = QCheckBox("search the prior's uncertainty when nothing registers")
        self.verify_check = QCheckBox("verify (converged, photo and render agree)")
        # Illumination-robust stages: tried in this order when keypoints do not verify.
        self.sun_relight_check = QCheckBox("match a render lit by the photo's sun")
        self.sun_relight_check.setToolTip(
            "Relight the model for the sun of the photo (its capture time, its sensor record, "
            "or the Sun box below), cast shadows included, and match the photo against that. "
            "For photos taken under another sun than the model's texture. Needs the texture's "
            "own sun (survey.json beside the model) unless the model is untextured.")
        self.area_match_check = QCheckBox("match blocks of the render by correlation")
        self.area_match_check.setToolTip(
            "Cut the render into small blocks and find each in the photo by correlation "
            "(area-based matching), then solve the pose from them as from keypoints. It compares "
            "the layout of light and shade of the relief, not keypoint descriptors: what "
            "registers a bare (untextured) mesh lit by the photo's sun to a photo of coloured "
            "rock. With a texture and the photo's sun known, every round matches both the "
            "render relit for that sun and the texture as it is, and keeps the one the pose "
            "fits better (relit shading is wrong where the photo shows relief finer than the "
            "model's). Verified like keypoints (converged, photo and render agree). Also "
            "refines a verified keypoint pose whose expected error is 0.5 px or more, when the "
            "blocks hold it tighter.")
        self.edge_align_check = QCheckBox("align the model's edges with the photo's")
        self.edge_align_check.setToolTip(
            "Line up the skyline, ridges, overhangs and bedding contacts of the model with the "
            "edges seen in the photo, then match keypoints (and blocks) again from that pose. "
            "Edges survive a change of light that defeats keypoints.")
        self.dense_refine_check = QCheckBox("refine by mutual information")
        self.dense_refine_check.setToolTip(
            "Nudge the best pose so far until photo and render agree best as whole images "
            "(mutual information: no keypoints needed), then match keypoints (and blocks) again "
            "from there. "
            "A pose that keypoints cannot confirm is kept as a start, graded poor at best.")

        form = QFormLayout()
        form.addRow("Preset", self.preset_combo)
        det_row = QHBoxLayout()
        det_row.addWidget(self.detector_combo)
        det_row.addWidget(QLabel("–"))
        det_row.addWidget(self.descriptor_combo)
        form.addRow("Detector–descriptor", det_row)
        form.addRow("Max features", self.max_features_spin)
        form.addRow("Threshold scale", self.threshold_spin)
        ratio_row = QHBoxLayout()
        ratio_row.addWidget(self.ratio_spin)
        ratio_row.addWidget(self.symmetric_check)
        form.addRow("Ratio test", ratio_row)
        geom_row = QHBoxLayout()
        geom_row.addWidget(self.model_combo)
        geom_row.addWidget(self.geom_spin)
        form.addRow("Epipolar check", geom_row)
        form.addRow("PnP threshold", self.pnp_spin)
        solver_row = QHBoxLayout()
        solver_row.addWidget(self.solver_combo, 1)
        solver_row.addWidget(self.k1_check)
        form.addRow("Camera solver", solver_row)
        form.addRow("Match width", self.width_spin)
        form.addRow("Trials (Auto)", self.trials_spin)
        form.addRow(self.search_check)
        form.addRow(self.verify_check)

        light_box = QGroupBox("When keypoints do not verify (another light)")
        light_layout = QVBoxLayout(light_box)
        for check in (self.sun_relight_check, self.area_match_check, self.edge_align_check,
                      self.dense_refine_check):
            light_layout.addWidget(check)
        light_layout.addWidget(_hint(
            "Tried in this order after the keypoint trials, edges and MI each ending in a "
            "matching trial from the pose they found; the Trials list says which stage found "
            "each pose (▦: blocks matched by correlation)."))
        self.sun_box = SunBox(controller)

        self.run_button = QPushButton("Run")
        self.run_button.setToolTip("One trial with these parameters, from the current pose "
                                   "(then the checked stages below it if it does not verify); "
                                   f"key {key_of('run')}")
        self.auto_button = QPushButton("Auto")
        self.auto_button.setToolTip("Trials adapted by the rules until the grade is good; "
                                    f"key {key_of('auto')}")
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.setEnabled(False)
        buttons = QHBoxLayout()
        for b in (self.run_button, self.auto_button, self.cancel_button):
            buttons.addWidget(b)
        self.progress = QProgressBar()
        self.progress.setRange(0, 100)
        self.progress.setValue(0)
        self.progress.setTextVisible(True)
        self.status_label = QLabel("")
        self.status_label.setWordWrap(True)

        self.corr_check = QCheckBox("correspondences")
        self.corr_check.setChecked(controller.show_correspondences)
        self.outlier_check = QCheckBox("outliers too")
        legend = " ".join(f"<span style='color:{c}'>━ {name}</span>"
                          for name, c in CORRESPONDENCE_COLORS.items())
        self.legend_label = QLabel(legend)
        self.blend_check = QCheckBox("render over the photo")
        self.blend_slider = QLabeledDoubleSlider(Qt.Orientation.Horizontal)
        self.blend_slider.setRange(0.0, 1.0)
        self.blend_slider.setDecimals(2)
        self.blend_slider.setValue(controller.blend_opacity)
        display = QGroupBox("Display")
        dl = QVBoxLayout(display)
        row1 = QHBoxLayout()
        row1.addWidget(self.corr_check)
        row1.addWidget(self.outlier_check)
        row1.addStretch(1)
        dl.addLayout(row1)
        dl.addWidget(self.legend_label)
        row2 = QHBoxLayout()
        row2.addWidget(self.blend_check)
        row2.addWidget(self.blend_slider, 1)
        dl.addLayout(row2)

        layout = QVBoxLayout(self)
        params_box = QGroupBox("Parameters")
        params_box.setLayout(form)
        layout.addWidget(params_box)
        layout.addWidget(light_box)
        layout.addWidget(self.sun_box)
        layout.addLayout(buttons)
        layout.addWidget(self.progress)
        layout.addWidget(self.status_label)
        layout.addWidget(display)
        layout.addStretch(1)

        self.preset_combo.currentIndexChanged.connect(self._preset)
        feat = "features"
        self.detector_combo.currentIndexChanged.connect(
            lambda: self._set(feat, "detector", self.detector_combo.currentData()))
        self.descriptor_combo.currentIndexChanged.connect(
            lambda: self._set(feat, "descriptor", self.descriptor_combo.currentData()))
        self.max_features_spin.valueChanged.connect(
            lambda v: self._set(feat, "max_features", int(v)))
        self.threshold_spin.valueChanged.connect(lambda v: self._set(feat, "threshold_scale", v))
        self.ratio_spin.valueChanged.connect(lambda v: self._set("features", "ratio", v))
        self.symmetric_check.toggled.connect(lambda v: self._set("features", "symmetric", bool(v)))
        self.model_combo.currentIndexChanged.connect(
            lambda: self._set(feat, "geometric_model", self.model_combo.currentData()))
        self.geom_spin.valueChanged.connect(
            lambda v: self._set(feat, "geometric_threshold_px", v))
        self.pnp_spin.valueChanged.connect(lambda v: self._set("pose", "reprojection_error_px", v))
        self.solver_combo.currentIndexChanged.connect(
            lambda: self._set("pose", "solver", self.solver_combo.currentData()))
        self.k1_check.toggled.connect(lambda v: self._set("pose", "estimate_k1", bool(v)))
        self.width_spin.valueChanged.connect(lambda v: self._set(None, "match_width", int(v)))
        self.trials_spin.valueChanged.connect(lambda v: self._set(None, "max_trials", int(v)))
        self.search_check.toggled.connect(lambda v: self._set(None, "search_prior", bool(v)))
        self.verify_check.toggled.connect(lambda v: self._set(None, "verify", bool(v)))
        for check, name in ((self.sun_relight_check, "sun_relight"),
                            (self.area_match_check, "area_match"),
                            (self.edge_align_check, "edge_align"),
                            (self.dense_refine_check, "dense_refine")):
            check.toggled.connect(lambda v, name=name: self._set(None, name, bool(v)))
        self.run_button.clicked.connect(lambda: controller.run_registration(auto=False))
        self.auto_button.clicked.connect(lambda: controller.run_registration(auto=True))
        self.cancel_button.clicked.connect(controller.cancel_registration)
        self.corr_check.toggled.connect(lambda v: controller.set_correspondence_display(visible=v))
        self.outlier_check.toggled.connect(
            lambda v: controller.set_correspondence_display(outliers=v))
        self.blend_check.toggled.connect(lambda v: controller.set_blend(visible=v))
        self.blend_slider.valueChanged.connect(lambda v: controller.set_blend(opacity=v))
        controller.params_changed.connect(self.refresh)
        controller.registration_started.connect(self._started)
        controller.registration_progress.connect(self._progress)
        controller.registration_finished.connect(self._finished)
        controller.failed.connect(self._job_failed)
        controller.pose_changed.connect(self._sync_blend)
        controller.busy_changed.connect(self._busy)
        self._failure: str | None = None  # why the running registration failed
        self.refresh()

    def _set(self, group: str | None, name: str, value) -> None:
        target = self.ws.params if group is None else getattr(self.ws.params, group)
        setattr(target, name, value)
        self.ctrl.params_edited()
        if group == "features":
            self._match_preset()
        elif name == "sun_relight":
            self.sun_box.refresh_notes()
        elif name == "solver":
            self.k1_check.setEnabled(value != "epnp")  # EPnP estimates no camera

    def _preset(self) -> None:
        name = self.preset_combo.currentData()
        if not name:
            return
        self.ws.params.features = preset_features(name, self.ws.params.features)
        self.ctrl.params_edited()
        self.refresh()

    def _match_preset(self) -> None:
        _set_quietly(self.preset_combo, preset_name(self.ws.params.features))

    def refresh(self) -> None:
        p = self.ws.params
        f = p.features
        _set_quietly(self.detector_combo, f.detector)
        _set_quietly(self.descriptor_combo, f.descriptor)
        _set_quietly(self.max_features_spin, int(f.max_features))
        _set_quietly(self.threshold_spin, float(f.threshold_scale))
        _set_quietly(self.ratio_spin, float(f.ratio))
        _set_quietly(self.symmetric_check, f.symmetric)
        _set_quietly(self.model_combo, f.geometric_model)
        _set_quietly(self.geom_spin, float(f.geometric_threshold_px))
        _set_quietly(self.pnp_spin, float(p.pose.reprojection_error_px))
        _set_quietly(self.solver_combo, p.pose.solver)
        _set_quietly(self.k1_check, bool(p.pose.estimate_k1))
        self.k1_check.setEnabled(p.pose.solver != "epnp")
        _set_quietly(self.width_spin, int(p.match_width))
        _set_quietly(self.trials_spin, int(p.max_trials))
        _set_quietly(self.search_check, p.search_prior)
        _set_quietly(self.verify_check, p.verify)
        _set_quietly(self.sun_relight_check, p.sun_relight)
        _set_quietly(self.area_match_check, p.area_match)
        _set_quietly(self.edge_align_check, p.edge_align)
        _set_quietly(self.dense_refine_check, p.dense_refine)
        self._match_preset()
        self.sun_box.refresh_notes()

    def _started(self, kind: str) -> None:
        self._failure = None
        self.status_label.setStyleSheet("")
        self.progress.setValue(0)
        self.progress.setFormat(f"{kind}: %p%")
        self.status_label.setText(f"{kind}: starting…")

    def _progress(self, fraction: float, message: str) -> None:
        self.progress.setValue(int(round(100 * fraction)))
        self.status_label.setText(message)

    def _job_failed(self, job: str, message: str) -> None:
        # Reported before registration_finished(None), which cannot say why.
        if job == "registration":
            self._failure = message

    def _finished(self, reg) -> None:
        if reg is None:
            if self._failure:
                self.status_label.setText(f"Failed: {html.escape(self._failure)}")
                self.status_label.setStyleSheet("color: #e65100;")
            else:
                self.status_label.setText("Cancelled.")
            self._failure = None
            return
        self.progress.setValue(100)
        t = reg.timings_s.get("total", 0.0)
        self.status_label.setText(
            f"{outcome_text(reg.status, reg.grade, reg.q, rich=True)}, "
            f"{len(reg.trials)} trial(s), {t:.1f} s")

    def _busy(self) -> None:
        running = self.ctrl.is_running("registration")
        self.run_button.setEnabled(not running)
        self.auto_button.setEnabled(not running)
        self.cancel_button.setEnabled(running or self.ctrl.is_running("manual"))

    def _sync_blend(self, _source: str = "") -> None:
        _set_quietly(self.blend_check, self.ctrl.blend_visible)


# ======================================================================== sun
def sun_source_text(source: str) -> str:
    """Where a photo's sun comes from, in words for the Sun box.

    >>> sun_source_text("EXIF time 2024-08-03T07:21:40+00:00")
    'from EXIF time 2024-08-03 07:21 +00:00'
    >>> sun_source_text("unknown: no capture time")
    'unknown — no capture time'
    """
    if not source:
        return "unknown"
    if source.startswith("unknown"):
        reason = source.partition(":")[2].strip()
        return f"unknown — {reason}" if reason else "unknown"
    m = re.fullmatch(r"(EXIF time|sensor record time) (\S+)", source.strip())
    if m:
        what = "EXIF time" if m.group(1) == "EXIF time" else "the sensor record's time"
        try:
            when = datetime.fromisoformat(m.group(2))
        except ValueError:
            return f"from {what} {m.group(2)}"
        zone = f" {when.isoformat()[-6:]}" if when.utcoffset() is not None else ""
        return f"from {what} {when:%Y-%m-%d %H:%M}{zone}"
    if source == "sensor record sun":
        return "from the sensor record"
    if source == "hand setting":
        return "set by hand"
    if source.startswith("photo's shading"):
        return f"read from the {source}"
    return f"from the {source}"


class SunBox(QGroupBox):
    """The current photo's sun: where it comes from, its azimuth (true north)
    and elevation to set it by hand, reading it from the photo, and the render
    relit by it."""

    def __init__(self, controller: WorkbenchController, parent: QWidget | None = None) -> None:
        super().__init__("Sun at capture", parent)
        self.ctrl = controller
        self.ws = controller.workspace  # the state shown here
        self.source_label = QLabel("No photo.")
        self.source_label.setWordWrap(True)
        self.azimuth_spin = _spin(0.0, 360.0, 1, 1.0, "°")
        self.azimuth_spin.setWrapping(True)
        self.azimuth_spin.setToolTip(
            "Direction of the sun, degrees clockwise from true north (90° east, 180° south). "
            "Type a value or hold the arrows to swing the sun round; with the sun-lit preview on "
            "the render's shadows follow.")
        self.elevation_spin = _spin(-90.0, 90.0, 1, 1.0, "°")
        self.elevation_spin.setToolTip(
            "Height of the sun above the horizon, degrees: low sun, long shadows.")
        self.north_label = _hint("")
        self.estimate_button = QPushButton("From photo")
        self.estimate_button.setToolTip(
            "Read the sun from the photo's light and shade, against a render from the current "
            "pose (it needs a pose close to right: register first, or set the pose by hand)")
        self.reset_button = QPushButton("Reset")
        self.reset_button.setToolTip("Back to the sun of the capture time or the sensor record")
        self.preview_check = QCheckBox("Sun-lit preview")
        self.preview_check.setToolTip(
            "Show the render relit for this sun, cast shadows included, instead of the model's "
            "texture as surveyed: do its shadows fall where the photo's do?")
        self.note_label = _hint("")

        angles = QGridLayout()
        angles.addWidget(QLabel("azimuth"), 0, 0)
        angles.addWidget(self.azimuth_spin, 0, 1)
        angles.addWidget(QLabel("elevation"), 0, 2)
        angles.addWidget(self.elevation_spin, 0, 3)
        angles.setColumnStretch(1, 1)
        angles.setColumnStretch(3, 1)
        buttons = QHBoxLayout()
        buttons.addWidget(self.estimate_button)
        buttons.addWidget(self.reset_button)
        buttons.addWidget(self.preview_check)
        buttons.addStretch(1)
        layout = QVBoxLayout(self)
        layout.addWidget(self.source_label)
        layout.addLayout(angles)
        layout.addWidget(self.north_label)
        layout.addLayout(buttons)
        layout.addWidget(self.note_label)

        self.azimuth_spin.valueChanged.connect(self._typed)
        self.elevation_spin.valueChanged.connect(self._typed)
        self.estimate_button.clicked.connect(controller.estimate_sun)
        self.reset_button.clicked.connect(controller.reset_sun)
        self.preview_check.toggled.connect(controller.set_sun_preview)
        controller.sun_changed.connect(self.refresh)
        controller.photo_changed.connect(self.refresh)
        controller.scene_changed.connect(self.refresh)
        controller.busy_changed.connect(self._busy)
        self.refresh()

    def _typed(self, _value: float = 0.0) -> None:
        self.ctrl.set_sun_angles(self.azimuth_spin.value(), self.elevation_spin.value())

    def refresh(self) -> None:
        ctrl, ws, ps = self.ctrl, self.ws, self.ws.current
        _set_quietly(self.preview_check, ctrl.sun_preview)
        for w in (self.azimuth_spin, self.elevation_spin, self.estimate_button,
                  self.preview_check):
            w.setEnabled(ps is not None)
        if ps is None:
            self.source_label.setText("No photo.")
            self.reset_button.setEnabled(False)
            self.north_label.setText("")
            self.refresh_notes()
            return
        angles = ws.sun_angles()
        text = sun_source_text(ps.sun_source)
        if angles is None:
            self.source_label.setText(
                f"<b>{ps.name}</b>: sun {text}. Type its azimuth and elevation, or read it "
                "from the photo.")
            grey = "color: #8a8a8a;"
            _set_quietly(self.azimuth_spin, 180.0)  # placeholders: a sun due south, 45° high
            _set_quietly(self.elevation_spin, 45.0)
        else:
            self.source_label.setText(f"<b>{ps.name}</b>: sun {text}")
            grey = ""
            _set_quietly(self.azimuth_spin, angles[0] % 360.0)
            _set_quietly(self.elevation_spin, angles[1])
        for spin in (self.azimuth_spin, self.elevation_spin):
            spin.setStyleSheet(grey)  # greyed: a placeholder until a sun is set
        self.reset_button.setEnabled(ps.sun_override is not None)
        scene = ws.scene
        if scene is not None and scene.georef is not None:
            conv = ws.convergence_deg()
            side = "east" if conv >= 0 else "west"
            self.north_label.setText(
                f"Azimuth from true north; the model's grid north is {abs(conv):.2f}° {side} of "
                f"it here ({scene.georef.crs}).")
        else:
            self.north_label.setText("Azimuth from the model's north (no georeference: taken "
                                     "as true north).")
        self.refresh_notes()
        self._busy()

    def refresh_notes(self) -> None:
        """Say when the registration will not relight, and why."""
        ws, ps, scene = self.ws, self.ws.current, self.ws.scene
        notes = []
        if ps is not None and scene is not None:
            # A scan's intensity (or colours) hold no sun: clouds are always relit.
            textured = has_colours(scene) and not getattr(scene, "is_cloud", False)
            if not ws.params.sun_relight:
                notes.append("Sun-lit matching is off (checkbox above).")
            elif ps.sun is None:
                notes.append("Registration cannot relight until this photo's sun is known.")
            elif textured and scene.survey_sun is None:
                notes.append(
                    "The sun of the model's texture is unknown (no survey.json beside the "
                    "model): the registration will not relight, and the preview only guesses "
                    "the texture's own shading.")
        self.note_label.setText(" ".join(notes))
        self.note_label.setVisible(bool(notes))

    def _busy(self) -> None:
        running = self.ctrl.is_running("sun")
        self.estimate_button.setEnabled(self.ws.current is not None and not running)
        self.estimate_button.setText("Reading…" if running else "From photo")


# ===================================================================== manual
class ManualPanel(QWidget):
    """Reference render, paired control points, solve, per-pair residuals."""

    def __init__(self, controller: WorkbenchController, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.ctrl = controller
        self.ws = controller.workspace  # the state shown here
        self.ref_pose_button = QPushButton("Reference from the current pose")
        self.ref_view_button = QPushButton("Reference from the 3D view")
        self.ref_view_button.setToolTip(
            "Fly the 3D view (Scene tab: 3D) to a viewpoint like the photo's, then press this")
        self.fly_button = QPushButton("3D view from the current pose")
        ref_row = QGridLayout()
        ref_row.addWidget(self.ref_pose_button, 0, 0)
        ref_row.addWidget(self.ref_view_button, 0, 1)
        ref_row.addWidget(self.fly_button, 1, 0, 1, 2)
        self.reference_label = _hint("No reference render yet.")

        self.pick_button = QPushButton("Pick pairs")
        self.pick_button.setToolTip(
            "Click a point on the photo, then the same point on the reference")
        self.delete_button = QPushButton("Delete pair")
        self.clear_button = QPushButton("Clear")
        pick_row = QHBoxLayout()
        for b in (self.pick_button, self.delete_button, self.clear_button):
            pick_row.addWidget(b)
        self.save_pairs_button = QPushButton("Save pairs…")
        self.save_pairs_button.setToolTip(
            "Write the pairs to a CSV: photo pixel and model point (x, y, z) of each")
        self.load_pairs_button = QPushButton("Load pairs…")
        self.load_pairs_button.setToolTip(
            "Replace the pairs by a CSV's (saved here, clicked in another tool, or surveyed "
            "targets): photo_x, photo_y and x, y, z, easting, northing, elevation or "
            "latitude, longitude, elevation")
        file_row = QHBoxLayout()
        for b in (self.save_pairs_button, self.load_pairs_button):
            file_row.addWidget(b)
        self.table = QTableWidget(0, 5)
        self.table.setHorizontalHeaderLabels(["#", "photo (x, y)", "reference (x, y)", "on model",
                                              "residual"])
        self.table.verticalHeader().setVisible(False)
        self.table.setEditTriggers(QAbstractItemView.NoEditTriggers)
        self.table.setSelectionBehavior(QAbstractItemView.SelectRows)
        self.table.setSelectionMode(QAbstractItemView.SingleSelection)
        self.table.setMinimumHeight(180)
        self.table.cellDoubleClicked.connect(self._cell_double_clicked)
        self.focal_check = QCheckBox(f"also solve the focal length (≥ {MIN_PAIRS_FOCAL} pairs)")
        # Ticked for the user when the photo's focal length is not known (no
        # focal length in its record, or only an estimate), until they untick it.
        self._focal_choice_by_user = False
        self.focal_check.toggled.connect(self._focal_chosen)
        self.solve_button = QPushButton("Solve pose")
        self.solve_button.setEnabled(False)
        self.result_label = QLabel("")
        self.result_label.setWordWrap(True)

        layout = QVBoxLayout(self)
        ref_box = QGroupBox("1. Reference render")
        rl = QVBoxLayout(ref_box)
        rl.addLayout(ref_row)
        rl.addWidget(self.reference_label)
        pairs_box = QGroupBox("2. Pairs of control points")
        pl = QVBoxLayout(pairs_box)
        pl.addWidget(_hint(
            "Click a recognisable point on the photo (left), then the same point on the reference "
            "(right); the next click goes back to the photo. Pairs are numbered and coloured "
            "alike. "
            "Drag a point (select mode, key 3) to correct it; select it there and press "
            "Delete, or use Delete pair, to remove the pair. Save pairs… writes them to a CSV "
            "(photo pixel and model point); Load pairs… reads one, whose points keep their "
            "model coordinates, shown on the reference or not."))
        pl.addLayout(pick_row)
        pl.addLayout(file_row)
        pl.addWidget(self.table, 1)
        solve_box = QGroupBox(f"3. Solve (≥ {MIN_PAIRS} pairs)")
        sl = QVBoxLayout(solve_box)
        sl.addWidget(self.focal_check)
        sl.addWidget(self.solve_button)
        sl.addWidget(self.result_label)
        layout.addWidget(ref_box)
        layout.addWidget(pairs_box, 1)
        layout.addWidget(solve_box)

        self.ref_pose_button.clicked.connect(lambda: controller.make_reference("pose"))
        self.ref_view_button.clicked.connect(lambda: controller.make_reference("view"))
        self.fly_button.clicked.connect(lambda: controller.show_3d(from_pose=True))
        self.pick_button.clicked.connect(controller.start_picking)
        self.delete_button.clicked.connect(self.delete_selected)
        self.clear_button.clicked.connect(controller.clear_pairs)
        self.save_pairs_button.clicked.connect(self._save_pairs_dialog)
        self.load_pairs_button.clicked.connect(self._load_pairs_dialog)
        self.solve_button.clicked.connect(
            lambda: controller.solve_manual(self.focal_check.isChecked()))
        controller.pairs_changed.connect(self.refresh)
        controller.reference_ready.connect(self._reference_ready)
        controller.photo_changed.connect(self._photo_changed)
        controller.manual_finished.connect(self._solved)
        controller.busy_changed.connect(self.refresh_buttons)
        self._residuals: np.ndarray | None = None
        self.refresh()

    def _cell_double_clicked(self, row: int, column: int) -> None:
        if column == 0:
            self.rename_pair(row)

    def rename_pair(self, row: int, name: str | None = None) -> None:
        """Name pair ``row`` (asked in a dialog when ``name`` is None)."""
        names = self.ws.pair_names()
        if not 0 <= row < len(names):
            return
        if name is None:
            name, ok = QInputDialog.getText(
                self, f"Name of pair {row + 1}",
                "Name (a surveyed target's, e.g. GCP12; empty for none):", text=names[row])
            if not ok:
                return
        try:
            self.ws.rename_pair(row, name)
        except WorkbenchError as exc:
            self.ctrl.notify_error(str(exc))

    def delete_selected(self) -> None:
        rows = self.table.selectionModel().selectedRows() if self.table.selectionModel() else []
        if rows:
            self.ctrl.delete_pair(rows[0].row())

    def _pairs_file(self) -> str:
        """Where the current photo's pairs go by default: PHOTO.pairs.csv beside it."""
        ps = self.ws.current
        path = ps.photo.path if ps is not None else None
        return str(path.with_suffix(".pairs.csv")) if path is not None else "pairs.csv"

    def _save_pairs_dialog(self) -> None:
        path, _ = QFileDialog.getSaveFileName(self, "Save pairs", self._pairs_file(),
                                              _PAIRS_FILTER)
        if path:
            self.save_pairs(path)

    def _load_pairs_dialog(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Load pairs", self._pairs_file(),
                                              _PAIRS_FILTER)
        if path:
            self.load_pairs(path)

    def save_pairs(self, path: str | Path) -> None:
        """Save the pairs to a control-point CSV; a problem is one notification."""
        try:
            written, left_out = self.ws.save_pairs(path)
        except (WorkbenchError, InputError, OSError) as exc:
            self.ctrl.notify_error(f"Could not save the pairs: {one_line(exc)}")
            return
        skipped = f" ({left_out} off the model left out)" if left_out else ""
        self.ctrl.status.emit(f"saved {written} pairs to {Path(path).name}{skipped}")

    def load_pairs(self, path: str | Path) -> None:
        """Replace the pairs by a control-point CSV's; a bad file is one notification."""
        try:
            n = self.ws.load_pairs(path)
        except (WorkbenchError, InputError) as exc:
            self.ctrl.notify_error(one_line(exc))
            return
        self._residuals = None  # of the pairs before
        self.ctrl.status.emit(f"loaded {n} pairs from {Path(path).name}: each keeps its "
                              "model point, on the reference or not")
        other = self._pairs_file_of_another_photo(Path(path))
        if other is not None:
            self.ctrl.notify_warning(
                f"{Path(path).name} is named for {other}, not for {self.ws.current.name}: "
                "its pairs were probably picked on that photo. Check them before solving.")

    def _pairs_file_of_another_photo(self, path: Path) -> str | None:
        """The workspace photo a control-point file is named for
        (``IMG_0002.pairs.csv``), when that is not the current photo."""
        stem = path.name.split(".")[0].lower()
        current = self.ws.current
        if current is None or Path(current.name).stem.lower() == stem:
            return None
        return next((ps.name for ps in self.ws.photos
                     if ps is not current and Path(ps.name).stem.lower() == stem), None)

    def _photo_changed(self) -> None:
        self._focal_choice_by_user = False  # another photo: its own camera decides again
        self._reference_ready()
        # Its last solve (a workspace opened again, a photo visited again): its
        # residuals and result, while the pairs are still those it was solved from.
        sol = self.ws.manual_solution_of_pairs()
        if sol is not None:
            self._solved(sol)
        else:
            self.result_label.setText("")

    def _reference_ready(self) -> None:
        ps = self.ws.current
        if ps is not None and ps.reference is None and len(ps.photo_points_px):
            # Pairs whose reference was not saved with them (an older workspace).
            self.reference_label.setText(
                f"<span style='color:#ffb74d'>The {len(ps.photo_points_px)} pairs are kept, "
                "but not the reference render they were picked on: make a reference again "
                "(pairs loaded from a file come back on it; clicked ones are clicked again "
                "on it).</span>")
        elif ps is None or ps.reference is None:
            self.reference_label.setText("No reference render yet.")
        else:
            t, p, r = ps.reference.cam_from_world.attitude
            c = ps.reference.cam_from_world.center
            src = "the 3D view" if ps.reference_source == "view" else "the pose at the time"
            self.reference_label.setText(
                f"Reference from {src}: ({c[0]:.1f}, {c[1]:.1f}, {c[2]:.1f}) m, "
                f"trend {t:.1f}° plunge {p:.1f}° roll {r:.1f}°.")
        self._residuals = None
        self.refresh()

    def refresh(self) -> None:
        ps = self.ws.current
        # Every point picked so far on each image: one may wait for its partner
        # (all the photo's do after a new reference, which drops the old one's).
        photo_px = np.asarray(ps.photo_points_px if ps is not None else np.zeros((0, 2)), float)
        ref_px = np.asarray(ps.reference_points_px if ps is not None else np.zeros((0, 2)), float)
        n_photo, n_ref = len(photo_px), len(ref_px)
        valid = self.ws.pair_points_3d()[1]
        own = self.ws.pairs_with_own_point()
        names = self.ws.pair_names()
        n = max(n_photo, n_ref)
        self.table.setRowCount(n)
        res = self._residuals
        # A loaded pair's model point out of the reference's view has no pixel
        # there worth showing (it is put just off the render).
        if ps is not None and ps.reference is not None and n_ref:
            w, h = ps.reference.intrinsics.width, ps.reference.intrinsics.height
            off_reference = ((ref_px[:, 0] < -0.5) | (ref_px[:, 1] < -0.5)
                             | (ref_px[:, 0] > w - 0.5) | (ref_px[:, 1] > h - 0.5))
        else:
            off_reference = np.zeros(n_ref, bool)
        for i in range(n):
            items = [f"{i + 1} {names[i]}" if i < len(names) and names[i] else str(i + 1),
                     f"{photo_px[i, 0]:.1f}, {photo_px[i, 1]:.1f}" if i < n_photo else
                     "click the photo",
                     ("out of its view" if off_reference[i] else
                      f"{ref_px[i, 0]:.1f}, {ref_px[i, 1]:.1f}") if i < n_ref else
                     "click the reference",
                     ("✓ from file" if i < len(own) and own[i] else "✓" if valid[i]
                      else "no reference" if ps.reference is None
                      else "✗ off the model") if i < len(valid) else "",
                     f"{res[i]:.2f} px" if res is not None and i < len(res)
                     and np.isfinite(res[i]) else ""]
            for j, text in enumerate(items):
                item = QTableWidgetItem(text)
                if j == 0:
                    item.setBackground(_qcolor(PAIR_COLORS[i % len(PAIR_COLORS)]))
                    if i < len(names):
                        item.setToolTip("Double-click to name the pair (a surveyed target's "
                                        "name is saved with it)")
                if j == 4 and res is not None and i < len(res) and np.isfinite(res[i]):
                    sol = self.ws.current.manual_solution if self.ws.current else None
                    bad = sol is not None and not sol.inliers[i]
                    item.setForeground(_qcolor("#ff1744" if bad else "#00c853"))
                self.table.setItem(i, j, item)
        self.table.resizeColumnsToContents()
        self.refresh_buttons()

    def _focal_chosen(self, _checked: bool) -> None:
        self._focal_choice_by_user = True

    def refresh_buttons(self) -> None:
        ps = self.ws.current
        has_ref = ps is not None and ps.reference is not None
        _, valid = self.ws.pair_points_3d() if ps is not None else (None, np.zeros(0, bool))
        busy = self.ctrl.is_running("manual")
        self.solve_button.setEnabled(has_ref and int(valid.sum()) >= MIN_PAIRS and not busy)
        self.pick_button.setEnabled(has_ref)
        self.load_pairs_button.setEnabled(has_ref and not busy)
        self.save_pairs_button.setEnabled(bool(valid.any()))
        enough = int(valid.sum()) >= MIN_PAIRS_FOCAL
        self.focal_check.setEnabled(enough)
        unknown = ps is not None and not ps.intrinsics.focal_known
        if not self._focal_choice_by_user:
            _set_quietly(self.focal_check, unknown and enough)
        self.focal_check.setToolTip(
            "The photo's focal length is not known (its record gives none, or it was "
            "estimated): solving it from the pairs is recommended." if unknown else
            "The photo's focal length comes from its record; solve it only if you doubt it.")
        for b in (self.ref_pose_button, self.ref_view_button):
            b.setEnabled(ps is not None and not self.ctrl.is_running("reference"))

    def _solved(self, sol) -> None:
        if sol is None:
            self.result_label.setText("Stopped.")
            return
        if not sol.ok:
            self._residuals = None
            self.result_label.setText(f"<span style='color:#ff1744'>No pose: {sol.reason}</span>")
            self.refresh()
            return
        self._residuals = sol.errors_px
        ps = self.ws.current
        # The solve's scored trial: the latest manual one (runs may follow it).
        trial = next((rec.trial for rec in reversed(ps.trials) if rec.kind == "Manual"),
                     None) if ps is not None else None
        focal = (f"; focal length {sol.intrinsics.fx:.1f} px ({sol.intrinsics.hfov_deg:.1f}° wide)"
                 if sol.focal_solved else "")
        t, p, r = sol.pose.attitude
        c = sol.pose.center
        grade = f"; scored <b>{trial.grade}</b> (Q = {trial.q:.2f})" if trial is not None else ""
        self.result_label.setText(
            f"Pose from {sol.n_inliers} of {len(sol.inliers)} pairs, RMS {sol.rms_px:.2f} px "
            f"({sol.method}){focal}: ({c[0]:.2f}, {c[1]:.2f}, {c[2]:.2f}) m, trend {t:.2f}° "
            f"plunge {p:.2f}° roll {r:.2f}°{grade}.<br>"
            + _pairs_error_text(sol.uncertainty, sol.intrinsics.width)
            + (f"<br><span style='color:#ff8a80'>{sol.warning}.</span>"
               if getattr(sol, "warning", "") else ""))
        self.refresh()


def _pairs_error_text(unc, width: int) -> str:
    """The expected error of a pose from control points (rich text): green when
    small (:data:`~napari_imgreg.registration.uncertainty.UNCERTAIN_PX`, scaled
    to the photo's ``width``), red when not; the RMS of a few pairs is no guide."""
    if unc is None:
        return ""
    if not np.isfinite(unc.reprojection_px) or not np.isfinite(unc.position_m):
        return ("<span style='color:#ff8a80'>Expected error: unbounded — these pairs do not "
                "fix the pose (too few for an unknown focal length, or on a line): add pairs "
                "spread over the photo and over distance.</span>")
    colour = "#b9f6ca" if unc.is_small(width) else "#ff8a80"
    advice = "" if unc.is_small(width) else (
        " — add pairs spread over the photo and over distance")
    return (f"<span style='color:{colour}'>Expected error ≈ {unc.reprojection_px:.1f} px · "
            f"camera ≈ {unc.position_m:.2f} m · {unc.rotation_deg:.2f}° (from the pairs' "
            f"spread and click noise, not their RMS){advice}</span>")


def _qcolor(hex_color: str):
    return QColor(hex_color)
