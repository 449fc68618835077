"""The registration workbench: napari docks for the whole photo-to-model workflow.

Two docks share one :class:`~._controller.WorkbenchController` per viewer, and
through it one :class:`~napari_imgreg.workspace.Workspace` (the Qt-free state
they show: ``workbench.controller.workspace``):

* **Registration workbench** (tabs): *Scene* (model, DEM, georeference,
  photos with their sensor records, 2D/3D views), *Pose* (values, nudges, the
  DEM map, undo, save to the sensor record), *Filters* (gamma, Wallis,
  brightness/contrast, CLAHE for photo and render, live preview), *Register*
  (detector–descriptor, parameters, the stages for another light, the
  photo's sun with a sun-lit preview, Run / Auto / Cancel, correspondences,
  render over the photo), *Manual* (reference render, paired control points,
  solve) and *Interpret* (a place for the interpretation tools).
* **Registration quality** (under the canvas): the seven metrics, Q and grade,
  hints, suggested parameters and the trial history.

Above the tabs, the workspace bar opens and saves a workspace folder
(``campaign.imgreg/``, see docs/workspace.md); once saved or opened, every
change is saved there as it happens (through the workspace's own autosave).
The *Photos* tab is the campaign's table (:mod:`._photos_table`) with
Register all; the keyboard shortcuts are :mod:`._shortcuts`'. The same
open/save are in napari's File menu (File → IO utilities), and dropping a
``*.imgreg`` folder onto napari opens it here (:func:`get_workspace_reader`).

The canvas shows the photo on the left and the render from the current pose
on the right (2D), or the textured model with the cameras (3D).

>>> from napari_imgreg.widgets.workbench import Workbench   # doctest: +SKIP
>>> workbench = Workbench.add_to_viewer(viewer)              # doctest: +SKIP
>>> workbench.controller.open_sample()                       # doctest: +SKIP
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

from pathlib import Path

from qtpy.QtCore import Qt, QTimer
from qtpy.QtWidgets import (
    QFileDialog,
    QHBoxLayout,
    QLabel,
    QMainWindow,
    QPushButton,
    QScrollArea,
    QTabWidget,
    QVBoxLayout,
    QWidget,
)

from ._reader_preferences import prefer_imgreg_reader, prefer_workspace_reader
from ..io import workspace_files as wsfiles
from . import _shortcuts
from ._controller import WorkbenchController, controller_for, real_viewer
from ._panels import FiltersPanel, ManualPanel, PosePanel, RegisterPanel, ScenePanel
from ._photos_table import PhotosTable
from ._quality import QualityPanel
from .interpret_widget import InterpretWidget

if TYPE_CHECKING:
    import napari

__all__ = ["Workbench", "QualityDock", "WORKBENCH_NAME", "QUALITY_NAME", "PLUGIN_NAME",
           "PLUGIN_DISPLAY_NAME", "plugin_dock_names", "INTERPRET_TAB",
           "PHOTOS_TAB", "workbench_for", "get_workspace_reader", "open_workspace_dialog",
           "save_workspace_dialog"]

#: The plugin's name and display name in napari (napari.yaml's ``name`` and
#: ``display_name``; a test checks they agree).
PLUGIN_NAME = "napari-imgreg"
PLUGIN_DISPLAY_NAME = "Outcrop registration: napari-imgreg"


def plugin_dock_names(display_name: str) -> tuple[str, str, str]:
    """The names a dock of the widget ``display_name`` goes by, most likely first.

    napari names a dock opened from the Plugins menu "<widget> (<plugin's
    display name>)", one opened by ``viewer.window.add_plugin_dock_widget``
    "<widget> (<plugin name>)" (``napari.plugins.menu_item_template`` either
    way), and 0.2 docked ours under the bare name.
    """
    return (f"{display_name} ({PLUGIN_DISPLAY_NAME})", f"{display_name} ({PLUGIN_NAME})",
            display_name)


#: Dock names: the Plugins menu's, so the menu shows our docks as open (and
#: toggles them) instead of docking second ones. :func:`_find_dock` finds a
#: dock under any of its :func:`plugin_dock_names`.
WORKBENCH_NAME = plugin_dock_names("Registration workbench")[0]
QUALITY_NAME = plugin_dock_names("Registration quality")[0]
INTERPRET_TAB = "Interpret"
PHOTOS_TAB = "Photos"


def _scrolled(widget: QWidget) -> QScrollArea:
    """A page that scrolls down, never sideways (it follows the dock's width)."""
    area = QScrollArea()
    area.setWidgetResizable(True)
    area.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
    area.setWidget(widget)
    return area


#: The Register tab's widgets pinned under its scrolling page (always in view).
REGISTER_PINNED = ("run_button", "auto_button", "cancel_button", "progress", "status_label")


class _PageWithFooter(QWidget):
    """A scrolling page (:func:`_scrolled`) above a footer that does not
    scroll: on a short screen the Register tab's Run / Auto / Cancel and its
    progress stay in view under the parameters. Answers ``widget()`` (the
    panel) and ``ensureWidgetVisible`` as the plain page does."""

    def __init__(self, widget: QWidget, footer: QWidget) -> None:
        super().__init__()
        self.scroll = _scrolled(widget)
        self.footer = footer
        layout = QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.setSpacing(0)
        layout.addWidget(self.scroll, 1)
        layout.addWidget(footer)

    def widget(self) -> QWidget:
        return self.scroll.widget()

    def ensureWidgetVisible(self, child: QWidget, xmargin: int = 50,  # noqa: N802 (Qt)
                            ymargin: int = 50) -> None:
        self.scroll.ensureWidgetVisible(child, xmargin, ymargin)


def _pinned(panel: QWidget, names: tuple[str, ...]) -> QWidget:
    """The panel's page with its widgets ``names`` moved to a footer that stays
    in view (buttons side by side, the rest under them); a plain scrolling
    page when the panel has none of them."""
    widgets = [w for name in names if isinstance(w := getattr(panel, name, None), QWidget)]
    if not widgets:
        return _scrolled(panel)
    footer = QWidget()
    layout = QVBoxLayout(footer)
    layout.setContentsMargins(6, 4, 6, 4)
    layout.setSpacing(3)
    row = QHBoxLayout()
    for w in widgets:  # adding a widget to this layout takes it out of the panel's
        if isinstance(w, QPushButton):
            row.addWidget(w)
    layout.addLayout(row)
    for w in widgets:
        if not isinstance(w, QPushButton):
            layout.addWidget(w)
    return _PageWithFooter(panel, footer)


class Workbench(QWidget):
    """The tabbed workbench dock (see the module docstring).

    Parameters
    ----------
    napari_viewer : napari.viewer.Viewer
    dock_quality : bool
        Dock the quality panel too when the workbench is shown (as opening
        it from the Plugins menu does).
    """

    def __init__(self, napari_viewer: napari.viewer.Viewer, dock_quality: bool = True,
                 parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.viewer = napari_viewer
        self.controller: WorkbenchController = controller_for(napari_viewer)
        self.scene_panel = ScenePanel(self.controller)
        self.pose_panel = PosePanel(self.controller)
        self.filters_panel = FiltersPanel(self.controller)
        self.register_panel = RegisterPanel(self.controller)
        self.manual_panel = ManualPanel(self.controller)
        self.photos_table = PhotosTable(self.controller)
        self.interpret_placeholder = QLabel(
            "Interpretation tools (draw traces and polygons on the registered photo, "
            "project them onto the model, measure) dock here when installed.")
        self.interpret_placeholder.setWordWrap(True)
        self.tabs = QTabWidget()
        for panel, name in ((self.scene_panel, "Scene"), (self.photos_table, PHOTOS_TAB),
                            (self.pose_panel, "Pose"),
                            (self.filters_panel, "Filters"), (self.register_panel, "Register"),
                            (self.manual_panel, "Manual"),
                            (self.interpret_placeholder, INTERPRET_TAB)):
            # Run / Auto stay in view under the Register tab's long parameters.
            page = (_pinned(panel, REGISTER_PINNED) if panel is self.register_panel
                    else _scrolled(panel))
            self.tabs.addTab(page, name)
        self.status_label = QLabel("")
        self.status_label.setWordWrap(True)
        self.status_label.setStyleSheet("color: #bdbdbd; font-size: 11px;")
        # The workspace bar: where the work is saved.
        self.open_workspace_button = QPushButton("Open workspace…")
        self.open_workspace_button.setToolTip(
            "Open a workspace folder (*.imgreg): the model, the photos and everything done to "
            "them. Dropping the folder onto napari does the same.")
        self.save_workspace_button = QPushButton("Save workspace as…")
        self.save_workspace_button.setToolTip(
            "Save everything into a new workspace folder (*.imgreg); from then on every change "
            "is saved there as it happens")
        self.workspace_label = QLabel("")
        self.workspace_label.setWordWrap(True)
        self.workspace_label.setStyleSheet("font-size: 11px;")
        bar = QHBoxLayout()
        bar.addWidget(self.open_workspace_button)
        bar.addWidget(self.save_workspace_button)
        self.keys_label = QLabel("Keys: " + _shortcuts.help_text(
            ("turn left", "turn right", "run", "accept", "next", "attention", "undo"))
            + " … (all: hover here)")
        self.keys_label.setWordWrap(True)
        self.keys_label.setStyleSheet("color: #9e9e9e; font-size: 10px;")
        self.keys_label.setToolTip("<b>Keyboard shortcuts</b> (click the canvas first)<br>"
                                   + _shortcuts.help_text(sep="<br>"))
        layout = QVBoxLayout(self)
        layout.setContentsMargins(2, 2, 2, 2)
        layout.addLayout(bar)
        layout.addWidget(self.workspace_label)
        layout.addWidget(self.tabs, 1)
        layout.addWidget(self.keys_label)
        layout.addWidget(self.status_label)
        self.quality: QualityPanel | None = None
        self.interpret_widget: QWidget | None = None
        self.controller.status.connect(self.status_label.setText)
        self.controller.workspace_folder_changed.connect(self._show_folder)
        self.open_workspace_button.clicked.connect(lambda: open_workspace_dialog(self.viewer, self))
        self.save_workspace_button.clicked.connect(lambda: save_workspace_dialog(self.viewer, self))
        self._show_folder()
        #: Keys another binding of this viewer holds already (not bound here).
        self.keys_not_bound = _shortcuts.install(napari_viewer, self)
        prefer_workspace_reader()
        prefer_imgreg_reader()  # the demo docks us without npe2's activation hook
        self.destroyed.connect(lambda *_: _uninstall_quietly(napari_viewer))
        self.controller.attach(self)
        self._try_interpret_widget()
        if dock_quality:
            QTimer.singleShot(0, self._dock_quality)

    # ----------------------------------------------------------- docking
    @classmethod
    def add_to_viewer(cls, viewer: napari.viewer.Viewer) -> Workbench:
        """Dock the workbench (right) and the quality panel (under the canvas).

        Named as the Plugins menu names them, so the menu shows them docked
        (and toggles them) rather than docking second ones. A viewer with a
        workbench docked already gets that one back.
        """
        existing = _find_dock(viewer, WORKBENCH_NAME, Workbench)
        if isinstance(existing, Workbench):
            existing._dock_quality()
            return existing
        workbench = cls(viewer, dock_quality=False)
        real_viewer(viewer).window.add_dock_widget(workbench, name=WORKBENCH_NAME, area="right")
        workbench._dock_quality()
        return workbench

    def _dock_quality(self):
        """Dock the quality panel under the canvas; returns its dock (None if it was there)."""
        if self.quality is not None:
            return None
        existing = _find_dock(self.viewer, QUALITY_NAME, QualityDock)
        if existing is not None:
            self.quality = existing.panel if isinstance(existing, QualityDock) else existing
            return None
        dock = QualityDock(self.viewer)
        self.quality = dock.panel
        # Under the canvas, where the side-by-side photo and render leave room; the
        # workbench keeps the right column's full height.
        qdock = real_viewer(self.viewer).window.add_dock_widget(dock, name=QUALITY_NAME,
                                                                 area="bottom")
        _side_columns_full_height(qdock)
        QTimer.singleShot(0, lambda: _grow(qdock, 0.4))
        return qdock

    def add_tab(self, widget: QWidget, name: str) -> None:
        """Add a page (e.g. the interpretation tools); replaces the placeholder of
        the same name."""
        for i in range(self.tabs.count()):
            if self.tabs.tabText(i) == name:
                self.tabs.removeTab(i)
                break
        self.tabs.addTab(_scrolled(widget), name)

    def _try_interpret_widget(self) -> None:
        """Dock the interpretation tools in their tab; what is drawn on the
        workbench's photos is kept in its workspace."""
        try:
            widget = InterpretWidget(self.viewer, workspace=self.controller.workspace)
        except Exception as exc:  # pragma: no cover - the other widget's problem, not ours
            logging.getLogger(__name__).warning("interpretation tools not docked: %s", exc)
            return
        self.add_tab(widget, INTERPRET_TAB)
        self.interpret_widget = widget
        self.controller.photo_changed.connect(self._interpret_follows_photo)
        self._interpret_follows_photo()

    def _interpret_follows_photo(self) -> None:
        """The interpretation tools work on the photo chosen here."""
        combo = getattr(getattr(self, "interpret_widget", None), "photo_combo", None)
        layer = self.controller.photo_layer()
        if combo is None or layer is None:
            return
        i = combo.findText(layer.name)
        if i >= 0:
            combo.setCurrentIndex(i)

    def _show_folder(self) -> None:
        folder = self.controller.workspace_folder
        if folder is None:
            self.workspace_label.setText(
                "<span style='color:#ffb74d'>Not saved</span>: Save workspace as… keeps the "
                "photos, poses, trials, control points and drawings (then saved as you work).")
        else:
            self.workspace_label.setText(
                f"<span style='color:#91cf60'>Workspace</span> <b>{folder.name}</b> "
                f"({folder.parent}): every change is saved as it happens.")

    def show_tab(self, name: str) -> None:
        for i in range(self.tabs.count()):
            if self.tabs.tabText(i) == name:
                self.tabs.setCurrentIndex(i)
                return
        raise KeyError(name)


class QualityDock(QWidget):
    """The quality panel as a dock of its own (shares the viewer's controller)."""

    def __init__(self, napari_viewer: napari.viewer.Viewer, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.viewer = napari_viewer
        self.controller = controller_for(napari_viewer)
        self.controller.attach(self)
        self.panel = QualityPanel(self.controller)
        layout = QVBoxLayout(self)
        layout.setContentsMargins(2, 2, 2, 2)
        layout.addWidget(_scrolled(self.panel))


def _uninstall_quietly(viewer) -> None:
    try:
        _shortcuts.uninstall(viewer)
    except (RuntimeError, AttributeError, TypeError):  # pragma: no cover - viewer gone
        pass


# ---------------------------------------------- opening and saving workspaces
def workbench_for(viewer: napari.viewer.Viewer) -> Workbench:
    """The viewer's workbench dock (docked, with its quality panel, when there is none)."""
    existing = _find_dock(viewer, WORKBENCH_NAME, Workbench)
    if isinstance(existing, Workbench):
        return existing
    return Workbench.add_to_viewer(viewer)


def open_workspace_dialog(viewer: napari.viewer.Viewer | None = None,
                          parent: QWidget | None = None) -> None:
    """Ask for a workspace folder (``*.imgreg``) and open it in the workbench.

    The File menu's "Open workspace…" (File → IO utilities); without a
    viewer, napari's current one.
    """
    viewer = viewer if viewer is not None else _current_viewer()
    wb = workbench_for(viewer)
    folder = QFileDialog.getExistingDirectory(parent or wb, "Open workspace (a *.imgreg folder)")
    if folder:
        if not wsfiles.is_workspace(folder):
            wb.controller.notify_error(f"{folder}: no workspace.json: not a workspace folder")
            return
        wb.controller.open_workspace(folder)


def save_workspace_dialog(viewer: napari.viewer.Viewer | None = None,
                          parent: QWidget | None = None) -> None:
    """Ask for a new workspace folder and save the workbench's workspace into it.

    The File menu's "Save workspace as…"; ``.imgreg`` is added to the name.
    """
    viewer = viewer if viewer is not None else _current_viewer()
    wb = workbench_for(viewer)
    start = str(wb.controller.workspace_folder or Path.home() / "campaign.imgreg")
    folder, _ = QFileDialog.getSaveFileName(parent or wb, "Save workspace as (a new folder)",
                                            start, "Workspace folder (*.imgreg)")
    if folder:
        wb.controller.save_workspace(folder)


def menu_open_workspace() -> None:
    """File → IO utilities → Open workspace (napari's current viewer)."""
    open_workspace_dialog(_current_viewer())


def menu_save_workspace() -> None:
    """File → IO utilities → Save workspace as (napari's current viewer)."""
    save_workspace_dialog(_current_viewer())


def _current_viewer():
    import napari

    viewer = napari.current_viewer()
    if viewer is None:  # pragma: no cover - napari's menus always have one
        raise RuntimeError("no napari viewer")
    return viewer


#: The pattern of workspace folders in napari's reader preferences (napari
#: matches a folder with its trailing separator).
def get_workspace_reader(path):
    """napari reader contribution: a ``*.imgreg`` workspace folder opens in the workbench.

    Returns None for anything else (napari then offers other readers).
    The reader docks the workbench if needed, starts opening the workspace
    there (in a worker) and gives napari no layer of its own: the workbench
    makes them.
    """
    if isinstance(path, (list, tuple)):
        if len(path) != 1:
            return None
        path = path[0]
    folder = Path(str(path))
    if folder.suffix != ".imgreg" or not wsfiles.is_workspace(folder):
        return None

    def read(_path):
        workbench_for(_current_viewer()).controller.open_workspace(folder)
        return [(None,)]  # napari's "read, no layer" sentinel

    return read


def _main_window(dock):
    """The QMainWindow holding a dock (its Qt parent; napari keeps its own reference private)."""
    window = dock.parentWidget() if dock is not None else None
    return window if isinstance(window, QMainWindow) else None


def _side_columns_full_height(dock) -> None:
    """Let both side dock columns run down past the bottom docks: the right one
    (the workbench) and the left one (napari's layer controls and layer list),
    so a bottom dock (the quality panel) sits under the canvas only. Spanning
    the left column too, it left a laptop screen's layer list one row high."""
    window = _main_window(dock)
    if window is not None:
        window.setCorner(Qt.Corner.BottomRightCorner, Qt.DockWidgetArea.RightDockWidgetArea)
        window.setCorner(Qt.Corner.BottomLeftCorner, Qt.DockWidgetArea.LeftDockWidgetArea)


_right_column_full_height = _side_columns_full_height  # the 0.2 name


def _grow(dock, fraction: float) -> None:
    """Give a bottom dock ``fraction`` of the height it shares with the canvas."""
    try:
        window = _main_window(dock)
        if window is None:
            return
        height = window.centralWidget().height() + dock.height()
        window.resizeDocks([dock], [int(height * fraction)], Qt.Orientation.Vertical)
    except (TypeError, RuntimeError):  # pragma: no cover - layout is cosmetic; dock gone
        pass


def _find_dock(viewer: napari.viewer.Viewer, name: str, kind: type | None = None):
    """The viewer's dock widget called ``name`` under any of the names napari
    gives it (:func:`plugin_dock_names`), else any docked widget of type
    ``kind``; None when there is none."""
    # Through the viewer itself: a plugin's proxy of it would hand back our
    # own widgets proxied too (their module's name starts with "napari").
    docks = getattr(real_viewer(viewer).window, "dock_widgets", None)
    if docks is None or not hasattr(docks, "get"):
        return None
    bare = name
    for suffix in (f" ({PLUGIN_DISPLAY_NAME})", f" ({PLUGIN_NAME})"):
        if bare.endswith(suffix):
            bare = bare[: -len(suffix)]
    try:
        for candidate in plugin_dock_names(bare):
            widget = docks.get(candidate)
            if widget is not None and (kind is None or isinstance(widget, kind)):
                return widget
        if kind is not None:
            for widget in docks.values():
                if isinstance(widget, kind):
                    return widget
    except Exception:  # pragma: no cover - a window being torn down
        return None
    return None
