"""Dock widget: orient a model from phone camera attitudes (backend: :mod:`napari_imgreg.orient`).

Load the model's camera orientations (ESTIMATED) and the phone's (MEASURED),
choose the estimator and the declination (a number, or *Auto (WMM)*: the
World Magnetic Model's at the model's georeferenced origin, or the photos'
GPS position, on their capture day, computed by the backend), Run (in a napari thread worker, the viewer stays
responsive), read the rotation, the three estimators side by side, the
quality flags and the Δξ/Δρ plots, then rotate a Surface layer.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg
from matplotlib.figure import Figure
from qtpy.QtCore import Qt, Signal
from qtpy.QtWidgets import (
    QApplication,
    QCheckBox,
    QComboBox,
    QDoubleSpinBox,
    QFileDialog,
    QFormLayout,
    QHBoxLayout,
    QLabel,
    QLineEdit,
    QPushButton,
    QScrollArea,
    QTableWidget,
    QTabWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from ..scene import Scene
from ._jobs import JobRunner, in_python_thread
from ._layers import WORKBENCH_MODEL, napari_from_world, world_from_napari
from ..orient import (
    METHODS,
    OrientationResult,
    default_georef_path,
    lower_hemisphere_axis,
    draw_residual_plots,
    orient_files,
    rotate_points,
    rotation_error_deg,
    save_orientation,
)
from ..orient.declination import georef_found_above, gui_wording

if TYPE_CHECKING:
    import napari

__all__ = ["OrientWidget"]

STATUS_STYLE = {
    "pass": ("#2e7d32", "✓ pass"),
    "warn": ("#e65100", "⚠ warn"),
    "n/a": ("#757575", "– n/a"),
}
_METHOD_LABELS = {
    "robust": "robust (least squares, outliers set aside)",
    "lsq": "least squares (closed form)",
    "paper": "paper (J tensor + 0.1° search)",
}
_TABLE_FILTER = "Orientation tables (*.csv *.xml *.txt);;All files (*)"


class OrientWidget(QWidget):
    """Orient a model from camera attitudes, show diagnostics, rotate a Surface.

    Parameters
    ----------
    napari_viewer : napari.viewer.Viewer
        The viewer whose Surface layers can be rotated.
    """

    orientation_done = Signal(object)  # OrientationResult
    orientation_failed = Signal(str)
    layer_oriented = Signal(str)  # layer name

    def __init__(self, napari_viewer: napari.viewer.Viewer, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.viewer = napari_viewer
        self.result: OrientationResult | None = None
        #: Where the georef.json of the last Run was found when not chosen ("": chosen, none).
        self.georef_note = ""
        self.jobs = JobRunner(self)

        # ---- inputs
        self.estimated_edit = QLineEdit()
        self.estimated_edit.setPlaceholderText(
            "model cameras: CSV, Metashape .xml, COLMAP images.txt"
        )
        self.measured_edit = QLineEdit()
        self.measured_edit.setPlaceholderText("phone attitudes: CSV or a folder of DJI photos")
        self.method_combo = QComboBox()
        for method in ("robust", "lsq", "paper"):
            self.method_combo.addItem(_METHOD_LABELS[method], method)
        self.declination_spin = QDoubleSpinBox()
        self.declination_spin.setRange(-60.0, 60.0)
        self.declination_spin.setDecimals(1)
        self.declination_spin.setSuffix("° E")
        self.declination_spin.setToolTip(
            "Magnetic declination added to the measured trends (0 if the phone logged true north)"
        )
        self.declination_auto = QCheckBox("Auto (WMM)")
        self.declination_auto.setToolTip(
            "The World Magnetic Model's declination at the model's georeferenced origin (without "
            "a georef.json: the measured photos' GPS) on the photos' median capture day (a time "
            "column, or the photos' EXIF)"
        )
        self.georef_edit = QLineEdit()
        self.georef_edit.setPlaceholderText(
            "georef.json (optional: beside the table or a folder up, or the photos' GPS)")
        self.georef_edit.setToolTip("The model's georeference: its origin places the site "
                                    "for the automatic declination (optional: a georef.json "
                                    "beside the estimated table or one folder up, else the "
                                    "measured photos' GPS)")
        self.georef_edit.setEnabled(False)
        declination_row = QWidget()
        declination_box = QHBoxLayout(declination_row)
        declination_box.setContentsMargins(0, 0, 0, 0)
        declination_box.addWidget(self.declination_spin, 1)
        declination_box.addWidget(self.declination_auto)
        self.run_button = QPushButton("Run")
        self.run_button.setToolTip("Estimate the rotation (runs in the background)")

        form = QFormLayout()
        form.addRow("Estimated", self._with_browse(self.estimated_edit, folder=False))
        form.addRow("Measured", self._with_browse(self.measured_edit, folder=True))
        form.addRow("Estimator", self.method_combo)
        form.addRow("Declination", declination_row)
        form.addRow("Georef", self.georef_edit)

        # ---- results
        self.status_label = QLabel("Load the two tables and press Run.")
        self.status_label.setWordWrap(True)
        self.summary_label = QLabel()
        self.summary_label.setWordWrap(True)
        self.summary_label.setTextInteractionFlags(Qt.TextSelectableByMouse)
        self.estimators_table = QTableWidget(0, 5)
        self.estimators_table.setHorizontalHeaderLabels(
            ["estimator", "angle (°)", "axis plunge→trend", "RMS Δ (°)", "Δ chosen (°)"]
        )
        self.estimators_table.verticalHeader().setVisible(False)
        self.estimators_table.setEditTriggers(QTableWidget.NoEditTriggers)
        self.estimators_table.setToolTip(
            "angle: clockwise looking down the axis; "
            "RMS Δ: root mean square of all Δξ and Δρ; "
            "Δ chosen: angle between this estimator's rotation and the chosen one"
        )
        self.flag_labels: list[QLabel] = []
        self.figure = Figure(figsize=(4.5, 5.5))
        self.canvas = FigureCanvasQTAgg(self.figure)
        # Small enough to dock beside the workbench on a 1000 px screen; the
        # plots tab grows with the dock.
        self.canvas.setMinimumHeight(240)

        # Summary and flags / estimators / plots as tabs: a dock stays compact.
        summary_page = QWidget()
        summary_layout = QVBoxLayout(summary_page)
        summary_layout.addWidget(self.summary_label)
        self._flags_box = QVBoxLayout()
        summary_layout.addLayout(self._flags_box)
        summary_layout.addStretch(1)
        summary_scroll = QScrollArea()
        summary_scroll.setWidgetResizable(True)
        summary_scroll.setWidget(summary_page)
        self.tabs = QTabWidget()
        self.tabs.addTab(summary_scroll, "Result")
        self.tabs.addTab(self.estimators_table, "Estimators")
        self.tabs.addTab(self.canvas, "Δξ/Δρ plots")

        # ---- apply / save
        self.layer_combo = QComboBox()
        self.apply_button = QPushButton("Apply to layer")
        self.apply_button.setToolTip(
            "Rotate the chosen Surface layer (again from its original pose)"
        )
        self.save_button = QPushButton("Save ORIENTATION.json…")
        for button in (self.apply_button, self.save_button):
            button.setEnabled(False)
        apply_row = QHBoxLayout()
        apply_row.addWidget(self.layer_combo, 1)
        apply_row.addWidget(self.apply_button)

        layout = QVBoxLayout(self)
        layout.addLayout(form)
        layout.addWidget(self.run_button)
        layout.addWidget(self.status_label)
        layout.addWidget(self.tabs, 1)
        layout.addLayout(apply_row)
        layout.addWidget(self.save_button)

        self.run_button.clicked.connect(self.run)
        self.declination_auto.toggled.connect(self._declination_mode_changed)
        self.method_combo.currentIndexChanged.connect(self._method_changed)
        self.apply_button.clicked.connect(lambda: self.apply_to_layer())
        self.save_button.clicked.connect(self._save_dialog)
        for event in (self.viewer.layers.events.inserted, self.viewer.layers.events.removed):
            event.connect(self._refresh_layers)
        self._refresh_layers()

    # ------------------------------------------------------------ inputs
    def _with_browse(self, edit: QLineEdit, folder: bool) -> QWidget:
        row = QWidget()
        box = QHBoxLayout(row)
        box.setContentsMargins(0, 0, 0, 0)
        box.addWidget(edit, 1)
        button = QPushButton("…")
        button.setToolTip("Choose a file" + (" (Shift: a folder of photos)" if folder else ""))
        button.setFixedWidth(28)
        box.addWidget(button)

        def browse() -> None:
            if folder and QApplication.keyboardModifiers() & Qt.ShiftModifier:
                path = QFileDialog.getExistingDirectory(self, "Folder of photos")
            else:
                path, _ = QFileDialog.getOpenFileName(self, "Orientation table", "", _TABLE_FILTER)
            if path:
                edit.setText(path)

        button.clicked.connect(browse)
        return row

    def set_tables(self, estimated: str | Path, measured: str | Path) -> None:
        """Fill in the two table paths (as the file choosers would)."""
        self.estimated_edit.setText(str(estimated))
        self.measured_edit.setText(str(measured))

    @property
    def method(self) -> str:
        return self.method_combo.currentData()

    def _declination_mode_changed(self, auto: bool) -> None:
        # The spin box shows the computed value after a run; it is not an input then.
        self.declination_spin.setEnabled(not auto)
        self.georef_edit.setEnabled(auto)

    def _declination_inputs(self, estimated: str) -> dict:
        """``declination_deg`` (and ``georef``) for the backend. Without a
        georef.json the backend places the site by the measured photos' GPS."""
        self.georef_note = ""
        if not self.declination_auto.isChecked():
            return {"declination_deg": self.declination_spin.value()}
        georef = self.georef_edit.text().strip()
        if not georef:
            georef = default_georef_path(estimated)
            if georef is not None:
                where = ("one folder up from" if georef_found_above(georef, estimated)
                         else "beside")
                self.georef_note = (f"The declination's site is the origin of {georef}, found "
                                    f"{where} the estimated table (Georef chooses another).")
        return {"declination_deg": "auto", "georef": str(georef) if georef else None}

    def _method_changed(self) -> None:
        if self.result is not None and not self.jobs.is_running("orientation"):
            self.run()

    # --------------------------------------------------------------- run
    def run(self):
        """Estimate in a napari thread worker; returns the worker (started)."""
        estimated, measured = self.estimated_edit.text().strip(), self.measured_edit.text().strip()
        if not estimated or not measured:
            self._fail("Choose both tables first.")
            return None
        declination = self._declination_inputs(estimated)
        self.run_button.setEnabled(False)
        self.status_label.setText("Estimating…")
        self.status_label.setStyleSheet("")
        # Errors are shown in the widget as one line (bugs are logged with their traceback).
        # Auto reads georef.json with pyproj: in a thread Python owns (see in_python_thread).
        job = (in_python_thread, orient_files) if declination["declination_deg"] == "auto" \
            else (orient_files,)
        return self.jobs.start(
            "orientation", *job, estimated, measured, method=self.method, **declination,
            on_returned=self._on_result, on_failed=self._job_failed,
            on_finished=self._on_finished, notify=False,
        )

    def _on_finished(self) -> None:
        self.run_button.setEnabled(True)

    def _job_failed(self, message: str) -> None:
        """The Run failed: a notification and the status line, in the dock's words."""
        from napari.utils.notifications import show_error

        show_error(f"orientation failed: {gui_wording(message)}")
        self.run_button.setEnabled(True)  # the job is over (its finished signal may lag)
        self._fail(message)

    def _fail(self, message: str) -> None:
        message = gui_wording(message)  # the Georef field and the box, not --georef
        self.status_label.setText(message)
        self.status_label.setStyleSheet(f"color: {STATUS_STYLE['warn'][0]};")
        self.orientation_failed.emit(message)

    def _on_result(self, result: OrientationResult | None) -> None:
        if result is None:  # cancelled
            return
        self.result = result
        if self.declination_auto.isChecked():  # show the value the model gave
            self.declination_spin.setValue(float(result.inputs.get("declination_deg", 0.0)))
        n_warn = len(result.warnings)
        n_untested = sum(flag.status == "n/a" for flag in result.flags)
        # A flag the data cannot test is no pass: say so rather than "all flags pass".
        if n_warn:
            verdict = f", {n_warn} quality warning{'s' if n_warn > 1 else ''}"
        elif n_untested:
            verdict = f", no warning but {n_untested} flag{'s' if n_untested > 1 else ''} n/a"
        else:
            verdict = ", all flags pass"
        self.status_label.setText(f"{len(result.photos)} photos paired{verdict}."
                                  + (f" {self.georef_note}" if self.georef_note else ""))
        self.status_label.setStyleSheet("")
        self._show_summary(result)
        self._show_estimators(result)
        self._show_flags(result)
        draw_residual_plots(self.figure, result, vertical=True)
        self.canvas.draw_idle()
        self.save_button.setEnabled(True)
        self.apply_button.setEnabled(self.layer_combo.count() > 0)
        self.orientation_done.emit(result)

    # ----------------------------------------------------------- display
    def _show_summary(self, result: OrientationResult) -> None:
        trend, plunge, angle = lower_hemisphere_axis(result.axis, result.angle_deg)
        sense = "clockwise" if angle >= 0 else "anticlockwise"
        lines = [
            f"<b>Rotation {abs(angle):.2f}°</b> {sense} looking down an axis plunging "
            f"{plunge:.1f}° toward {trend:.1f}° ({html.escape(_METHOD_LABELS[result.method])}).",
            f"Mean |Δξ| {result.mean_abs_delta_xi_deg:.2f}°, mean |Δρ| "
            f"{result.mean_abs_delta_rho_deg:.2f}°.",
        ]
        if result.outliers:
            lines.append(
                f"Robust fit set aside {len(result.outliers)} photo(s): "
                + html.escape(", ".join(result.outliers[:8]))
                + (", …" if len(result.outliers) > 8 else "")
            )
        lines += [f"<i>{html.escape(note)}</i>" for note in result.notes]
        self.summary_label.setText("<br>".join(lines))

    def _show_estimators(self, result: OrientationResult) -> None:
        table = self.estimators_table
        table.setRowCount(len(METHODS))
        for row, name in enumerate(("robust", "lsq", "paper")):
            est = result.estimates[name]
            trend, plunge, angle = lower_hemisphere_axis(est.axis, est.angle_deg)
            cells = [
                name + (" ◀" if name == result.method else ""),
                f"{angle:+.2f}",
                f"{plunge:.1f} → {trend:.1f}",
                f"{est.rms_deg:.2f}",
                f"{rotation_error_deg(est.rotation, result.rotation):.2f}",
            ]
            for col, text in enumerate(cells):
                table.setItem(row, col, QTableWidgetItem(text))
        table.resizeColumnsToContents()

    def _show_flags(self, result: OrientationResult) -> None:
        for label in self.flag_labels:
            self._flags_box.removeWidget(label)
            label.deleteLater()
        self.flag_labels = []
        for flag in result.flags:
            color, badge = STATUS_STYLE[flag.status]
            label = QLabel(
                f'<span style="color:{color}; font-weight:bold">{badge}</span> '
                f"<b>{html.escape(flag.title)}</b>: {html.escape(flag.reading)}"
            )
            label.setWordWrap(True)
            label.setProperty("status", flag.status)
            label.setProperty("flag", flag.key)
            self._flags_box.addWidget(label)
            self.flag_labels.append(label)

    # ------------------------------------------------------------- apply
    def _surface_layers(self) -> list:
        """The Surface layers the result may rotate: not the workbench's model,
        whose photos are registered to it as it is (rotating it would leave
        every pose and mapped line in another frame than the model shown)."""
        from napari.layers import Surface

        return [layer for layer in self.viewer.layers if isinstance(layer, Surface)
                and not layer.metadata.get(WORKBENCH_MODEL)]

    def _refresh_layers(self, event=None) -> None:
        current = self.layer_combo.currentText()
        self.layer_combo.clear()
        names = [layer.name for layer in self._surface_layers()]
        self.layer_combo.addItems(names)
        if current in names:
            self.layer_combo.setCurrentText(current)
        self.apply_button.setEnabled(self.result is not None and bool(names))
        workbench_model = any(layer.metadata.get(WORKBENCH_MODEL) for layer in self.viewer.layers)
        self.apply_button.setToolTip(
            "Rotate the chosen Surface layer (again from its original pose)"
            + ("; the workbench's model is not offered: its photos are registered to it as it "
               "is — orient the model file (orient --apply) and make the workspace with it"
               if workbench_model else ""))

    def apply_to_layer(self, layer=None) -> None:
        """Rotate a Surface layer by the result, about the result's centre.

        The layer's original vertices are kept in its metadata
        (``imgreg_unoriented_vertices``), so applying again — e.g. after
        changing the estimator — replaces the rotation instead of adding to
        it. A scene attached by the reader (``imgreg_scene``) is rotated too.
        """
        if self.result is None:
            self._fail("Run the orientation first.")
            return
        if layer is None:
            name = self.layer_combo.currentText()
            if name not in self.viewer.layers:
                self._fail("Choose a Surface layer to rotate.")
                return
            layer = self.viewer.layers[name]
        Q, c = self.result.rotation, self.result.center
        meta = layer.metadata
        if "imgreg_unoriented_vertices" not in meta:
            meta["imgreg_unoriented_vertices"] = np.array(layer.vertices, copy=True)
        original = meta["imgreg_unoriented_vertices"]
        rotated = rotate_points(world_from_napari(original), Q, c)
        layer.vertices = napari_from_world(rotated).astype(original.dtype)

        scene = meta.get("imgreg_unoriented_scene", meta.get("imgreg_scene"))
        if scene is not None:
            meta["imgreg_unoriented_scene"] = scene
            meta["imgreg_scene"] = Scene(
                rotate_points(scene.vertices, Q, c), scene.faces, scene.uv, scene.texture,
                scene.vertex_colors, scene.georef, scene.dem, scene.name,
            )
        meta["imgreg_orientation"] = self.result.to_dict()["rotation"]
        self.status_label.setText(
            f"Rotated {layer.name!r} by {self.result.angle_deg:.2f}° ({self.result.method})."
        )
        self.status_label.setStyleSheet("")
        self.layer_oriented.emit(layer.name)

    # -------------------------------------------------------------- save
    def _save_dialog(self) -> None:
        if self.result is None:
            return
        path, _ = QFileDialog.getSaveFileName(
            self, "Save orientation", "ORIENTATION.json", "JSON (*.json)"
        )
        if path:
            try:
                save_orientation(self.result, path)
            except OSError as exc:  # a read-only folder, a full disk: say so, keep the result
                self._fail(f"Could not save {path}: {exc.strerror or exc}")
                return
            self.status_label.setText(f"Saved {path}")
