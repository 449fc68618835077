"""The metrics panel: seven metrics coloured superior/normal/inferior with trend
arrows, Q and the five-grade banner, the rules' hint and suggested
adaptation, and the trial history (Kehl et al. 2018, Figs. 5 and 6)."""

from __future__ import annotations

import html

import numpy as np
from qtpy.QtCore import Qt
from qtpy.QtGui import QColor
from qtpy.QtWidgets import (
    QAbstractItemView,
    QBoxLayout,
    QGroupBox,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QPushButton,
    QScrollArea,
    QSizePolicy,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from ..registration.quality import (
    GRADES,
    METRICS,
    REFERENCE_WIDTH_PX,
    classify,
    grade_of,
    metric_trend,
)
from ..registration.manual import gui_hint
from ..registration.uncertainty import UNCERTAIN_PX
from ._controller import WorkbenchController

__all__ = ["QualityPanel", "uncertainty_text", "CLASS_COLORS", "TREND_ARROWS", "HISTORY_COLUMNS", "SUNLIT_MARK",
           "origin_text"]

#: Backgrounds of a metric's class: superior (+1), normal (0), inferior (−1).
CLASS_COLORS = {1: "#2e7d32", 0: "#8d8d3a", -1: "#c62828"}
CLASS_NAMES = {1: "superior", 0: "normal", -1: "inferior"}
#: Compact metric names for the table (the full label is the tooltip).
SHORT_LABELS = {
    "points_photo": "points, photo", "points_render": "points, render",
    "feature_inliers": "feature inliers", "correspondences_3d": "in 3D",
    "inlier_ratio_2d": "inlier ratio 2D", "inliers_3d": "3D inliers",
    "inlier_ratio_3d": "inlier ratio 3D", "reprojection_error_px": "reproj. error",
}
#: Arrow and colour of a metric's trend against the previous trial.
TREND_ARROWS = {1: ("▲", "#00e676"), -1: ("▼", "#ff5252"), 0: ("=", "#bdbdbd")}
#: Height of a metric's row, pixels: the eight rows and the header fit a
#: bottom dock of 1600 × 1000 px (with the banner, error and legend above).
METRIC_ROW_PX = 20
#: Lines of hints shown at most before they scroll: the suggestion, its
#: button and the Trials list stay in view under them.
HINT_LINES = 7

#: Why an unverified pose reads no better than fair (the legend's tooltip).
CAP_NOTE = ("Only a verified pose can be good or excellent: an unverified one is graded at most "
            "fair (keypoints) or poor (blocks, edges, MI).")

#: Trial history columns.
#: The trial's run number is in its name and its grade is the colour of its Q cell
#: (the legend's colours, the grade in the tooltip): the name keeps the width.
HISTORY_COLUMNS = ("trial", "from", "Q", "3D", "error", "✓")
#: Marks, in the "from" column, a trial matched against a render relit for the photo's sun.
SUNLIT_MARK = "☀"
#: Marks, in the "from" column, a trial that matched render blocks by correlation.
AREA_MARK = "▦"
#: What each origin of a trial means (the "from" column's tooltip).
ORIGINS = {
    "prior": "matched from the start pose (the prior, or the pose you set)",
    "search": "matched from the best of the starts tried within the prior's uncertainty",
    "sun-lit render": "matched against the model relit for the photo's sun",
    "area matching": "blocks of the render found in the photo by correlation",
    "edges": "pose found by aligning the model's edges with the photo's, then matched",
    "mutual information": "pose refined by mutual information of photo and render, then matched",
    "manual": "pose solved from your control-point pairs, then scored",
}


def origin_text(rec) -> tuple[str, str]:
    """A trial's "from" cell and its tooltip: where its pose came from, ▦ when
    it matched render blocks by correlation, ☀ when it was matched against a
    render relit for the photo's sun."""
    t = rec.trial
    origin = "manual" if rec.kind == "Manual" else t.origin
    tip = ORIGINS.get(origin, f"matched from the pose of {origin}")
    cell = origin
    if getattr(t, "matcher", "keypoints") == "area" and origin != "area matching":
        cell += f" {AREA_MARK}"
        tip += "; blocks of the render found in the photo by correlation"
    if getattr(t, "render_mode", "plain") != "sunlit":
        return cell, tip + "; render as textured"
    tip += "; render relit for the photo's sun, cast shadows included"
    return (cell if origin == "sun-lit render" else f"{cell} {SUNLIT_MARK}"), tip


def uncertainty_text(unc, width: int, verified: bool = False) -> str:
    """The quality panel's line for a trial's error estimate (rich text).

    Green when the estimate is below :data:`UNCERTAIN_PX` (scaled to the
    photo's ``width``), red when it is not, grey when it was not estimated.
    ``verified``: the photo's matches confirmed the pose (said of an
    estimate from control points, which the matches did not make).
    """
    if unc is None:
        return ("<span style='color:#aaa'>Expected error: not estimated "
                "(no pose, or a pose scored as it is)</span>")
    if not np.isfinite(unc.reprojection_px) and getattr(unc, "basis", "") == "control points":
        return ("<span style='color:#ff8a80'>Expected error: unbounded — the control points do "
                "not fix the pose</span>")
    if not np.isfinite(unc.reprojection_px):
        return ("<span style='color:#ff8a80'>Expected error: unknown — too few matches on "
                "separate halves of the photo to check the pose independently</span>")
    colour = "#b9f6ca" if unc.is_small(width) else "#ff8a80"
    if getattr(unc, "basis", "") == "control points":
        why = ("from the control points' spread and click noise; the photo's matches confirm "
               "the pose" if verified else "from the control points' spread and click noise: "
               "the photo's matches did not confirm the pose")
    elif unc.halves_disagree(width):
        why = "the photo's halves disagree: the matches share a bias"
    elif unc.shared_px > 0 and unc.shared_px >= 0.5 * unc.reprojection_px:
        why = (f"≈ {unc.shared_px:.1f} px of it from the render's synthetic light, "
               "which no check can see")
    else:
        why = "independent check: areas of the photo resampled, halves compared"
    return (f"<span style='color:{colour}'>Expected error ≈ {unc.reprojection_px:.1f} px · "
            f"camera ≈ {unc.position_m:.2f} m · {unc.rotation_deg:.2f}° ({why})</span>")


def _grade_range(k: int) -> str:
    """The Q range of grade ``k``, short enough for the legend chips."""
    g = GRADES[k]
    if k == 0:
        return f"≥ {g.q_min:g}"
    upper = GRADES[k - 1].q_min
    if g.q_min == float("-inf"):
        return f"< {upper:g}"
    return f"{g.q_min:g} … {upper:g}"


def _fmt(key: str, value) -> str:
    if value is None or value != value:
        return "—"
    if key.startswith("inlier_ratio"):
        return f"{value:.2f}"
    if key == "reprojection_error_px":
        return f"{value:.2f} px"
    return f"{int(value):,}"


class QualityPanel(QWidget):
    """How good the selected trial is, why, what to change, and every trial so far."""

    def __init__(self, controller: WorkbenchController, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.ctrl = controller
        self.ws = controller.workspace  # the state shown here
        self.banner = QLabel("No trial yet: Run or Auto (Register tab), or solve manual pairs.")
        self.banner.setWordWrap(True)
        self.banner.setAlignment(Qt.AlignCenter)
        self.banner.setMinimumHeight(48)
        self._style_banner(None)
        legend = QHBoxLayout()
        legend.setSpacing(2)
        self.legend_labels: list[QLabel] = []
        for k, g in enumerate(GRADES):
            rng = html.escape(f"Q {_grade_range(k)}")
            chip = QLabel(f"{g.name}<br><span style='font-size:9px'>{rng}</span>")
            chip.setAlignment(Qt.AlignCenter)
            chip.setToolTip(g.text)
            chip.setProperty("grade", g.name)
            chip.setStyleSheet(f"background:{g.color}; color:#111; padding:2px; border-radius:3px;")
            legend.addWidget(chip, 1)
            self.legend_labels.append(chip)

        self.table = QTableWidget(len(METRICS), 4)
        self.table.setHorizontalHeaderLabels(["metric", "value", "", "inferior | superior"])
        self.table.setWordWrap(False)
        self.table.verticalHeader().setMinimumSectionSize(METRIC_ROW_PX)
        self.table.verticalHeader().setDefaultSectionSize(METRIC_ROW_PX)
        self.table.verticalHeader().setVisible(False)
        self.table.setEditTriggers(QAbstractItemView.NoEditTriggers)
        self.table.setSelectionMode(QAbstractItemView.NoSelection)
        self.table.horizontalHeader().setSectionResizeMode(0, QHeaderView.Stretch)
        for c in (1, 2, 3):
            self.table.horizontalHeader().setSectionResizeMode(c, QHeaderView.ResizeToContents)
        for r, m in enumerate(METRICS):
            item = QTableWidgetItem(SHORT_LABELS.get(m.key, m.label))
            item.setToolTip(f"{m.label}; weight {m.weight:g}")
            self.table.setItem(r, 0, item)
        self.table.setVerticalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.table.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self._fit_table()

        # The pose's independent error estimate (RESULT.json "uncertainty"):
        # what the geologist may expect, not a fit residual.
        self.uncertainty_label = QLabel("")
        self.uncertainty_label.setWordWrap(True)
        self.uncertainty_label.setToolTip(
            "Expected error of this pose, not the fit residual: poses re-solved from areas of "
            "the photo drawn again at random, tested against poses from separate halves, and "
            "the share of a relit render's light that no check can see. Median pixels at "
            "model points over the whole frame, camera centre in metres, rotation in degrees. "
            f"{UNCERTAIN_PX:g} px or more (at {REFERENCE_WIDTH_PX} px width): not verified, "
            "graded at most fair.")
        self.hint_label = QLabel("")
        self.hint_label.setWordWrap(True)
        self.hint_label.setTextInteractionFlags(Qt.TextSelectableByMouse)
        self.hint_label.setStyleSheet(
            "background:#1b5e20; color:#e8f5e9; padding:6px; border-radius:4px;")
        self.adapt_label = QLabel("")
        self.adapt_label.setWordWrap(True)
        for label in (self.hint_label, self.adapt_label):  # escaped HTML, never guessed
            label.setTextFormat(Qt.TextFormat.RichText)
        self.adapt_label.setStyleSheet(
            "background:#006064; color:#e0f7fa; padding:6px; border-radius:4px;")
        # The hints and the suggestion scroll within a bounded height: long
        # hints never push the button and the Trials list out of the dock.
        hints = QWidget()
        hints_layout = QVBoxLayout(hints)
        hints_layout.setContentsMargins(0, 0, 0, 0)
        hints_layout.setSpacing(4)
        hints_layout.addWidget(self.hint_label)
        hints_layout.addWidget(self.adapt_label)
        self.hint_scroll = QScrollArea()
        self.hint_scroll.setWidgetResizable(True)
        self.hint_scroll.setFrameShape(QScrollArea.Shape.NoFrame)
        self.hint_scroll.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.hint_scroll.setSizePolicy(QSizePolicy.Policy.Preferred, QSizePolicy.Policy.Fixed)
        self.hint_scroll.setWidget(hints)
        self.apply_button = QPushButton("Apply suggested parameters")
        self.apply_button.setEnabled(False)

        self.history = QTableWidget(0, len(HISTORY_COLUMNS))
        self.history.setHorizontalHeaderLabels(list(HISTORY_COLUMNS))
        for column, tip in (
                ("from", "Where the trial's pose came from: the start pose, a search, a sun-lit "
                         "render, edge alignment or mutual information; "
                         f"{SUNLIT_MARK}: matched against the model relit for the photo's sun"),
                ("Q", "quality Q of the trial, coloured by its grade (the legend's colours)"),
                ("3D", "3D inliers: correspondences on the model that agree with the pose"),
                ("error", "reprojection error of the inliers, pixels"),
                ("✓", "verified: an independent check agrees with the pose")):
            self.history.horizontalHeaderItem(HISTORY_COLUMNS.index(column)).setToolTip(tip)
        self.history.verticalHeader().setVisible(False)
        self.history.setEditTriggers(QAbstractItemView.NoEditTriggers)
        self.history.setSelectionBehavior(QAbstractItemView.SelectRows)
        self.history.setSelectionMode(QAbstractItemView.SingleSelection)
        # The name and the origin share what the numbers leave and wrap onto a
        # second line in a narrow dock ("Auto 1:" / "SIFT–SIFT"), never cut.
        self.history.setWordWrap(True)
        self.history.horizontalHeader().sectionResized.connect(
            lambda *_: self.history.resizeRowsToContents())
        self.history.setMinimumHeight(90)
        # Its height is what the dock leaves (its size hint, ~ 200 px, would
        # make the panel taller than a bottom dock and scroll it).
        self.history.setSizePolicy(QSizePolicy.Policy.Expanding, QSizePolicy.Policy.Ignored)
        self.restore_button = QPushButton("Restore trial (pose and parameters)")
        self.restore_button.setEnabled(False)

        # Two columns when the dock is wide (under the canvas), one when narrow (a side).
        left, right = QWidget(), QWidget()
        ll, rl = QVBoxLayout(left), QVBoxLayout(right)
        for lay in (ll, rl):
            lay.setContentsMargins(0, 0, 0, 0)
        ll.addWidget(self.banner)
        ll.addWidget(self.uncertainty_label)
        ll.addLayout(legend)
        # On the chips and the banner, not a line of its own: the metrics'
        # eight rows keep the room (the banner says when a grade is capped).
        for widget in (*self.legend_labels, self.banner):
            widget.setToolTip((widget.toolTip() + "\n" if widget.toolTip() else "")
                              + CAP_NOTE)
        ll.addWidget(self.table)
        ll.addStretch(1)
        rl.addWidget(self.hint_scroll)
        rl.addWidget(self.apply_button)
        hist_box = QGroupBox("Trials")
        hl = QVBoxLayout(hist_box)
        hl.addWidget(self.history, 1)
        hl.addWidget(self.restore_button)
        rl.addWidget(hist_box, 1)
        self._columns = QBoxLayout(QBoxLayout.Direction.TopToBottom, self)
        # Equal halves: between napari's layer list and the workbench the dock
        # is ~700 px wide, and the metrics' names need ~330 px to be read.
        self._columns.addWidget(left, 1)
        self._columns.addWidget(right, 1)
        self.hint_label.hide()
        self.adapt_label.hide()
        self._fit_hints()

        self.apply_button.clicked.connect(lambda: controller.apply_suggestion())
        self.restore_button.clicked.connect(self.restore_selected)
        self.history.itemSelectionChanged.connect(self._row_chosen)
        self.history.itemDoubleClicked.connect(lambda _item: self.restore_selected())
        controller.trials_changed.connect(self.refresh_history)
        controller.trial_selected.connect(self.show_trial)
        controller.photo_changed.connect(self._photo_changed)
        self.refresh_history()

    def resizeEvent(self, event) -> None:  # noqa: N802 (Qt)
        wide = self.width() >= 700
        self._columns.setDirection(QBoxLayout.Direction.LeftToRight if wide
                                   else QBoxLayout.Direction.TopToBottom)
        super().resizeEvent(event)
        self._fit_table()
        self._fit_hints()

    def showEvent(self, event) -> None:  # noqa: N802 (Qt)
        super().showEvent(event)
        self._fit_table()

    def _fit_table(self) -> None:
        """The metrics' table exactly as high as its header and eight rows (the
        header's height is known once styled: measured again when shown)."""
        header = self.table.horizontalHeader()
        head = max(header.height() if header.isVisible() else 0, header.sizeHint().height())
        height = self.table.verticalHeader().length() + head + 2 * self.table.frameWidth()
        if self.table.height() != height or self.table.minimumHeight() != height:
            self.table.setFixedHeight(height)

    def _fit_hints(self) -> None:
        """Size the hints' scroll area to its text, up to :data:`HINT_LINES` lines."""
        labels = [w for w in (self.hint_label, self.adapt_label) if not w.isHidden()]
        if not labels:
            self.hint_scroll.hide()
            return
        self.hint_scroll.show()
        width = max(self.hint_scroll.viewport().width(), 100)
        spacing = self.hint_scroll.widget().layout().spacing()
        needed = sum(w.heightForWidth(width) for w in labels) + spacing * (len(labels) - 1)
        cap = HINT_LINES * self.fontMetrics().lineSpacing() + 12
        self.hint_scroll.setFixedHeight(max(1, min(needed, cap)))

    # ------------------------------------------------------------ history
    def refresh_history(self) -> None:
        ps = self.ws.current
        records = ps.trials if ps is not None else []
        self.history.blockSignals(True)
        self.history.setRowCount(len(records))
        q_col = HISTORY_COLUMNS.index("Q")
        for r, rec in enumerate(records):
            t = rec.trial
            err = t.metrics.get("reprojection_error_px")
            origin, origin_tip = origin_text(rec)
            what = ("blocks" if getattr(t, "matcher", "keypoints") == "area"
                    else t.params.features.name)
            name = rec.label if rec.kind == "Manual" else f"{rec.kind} {rec.run}: {what}"
            cells = [name, origin, f"{t.q:.2f}",
                     str(t.metrics.get("inliers_3d", 0)),
                     f"{err:.2f}" if err is not None else "—",
                     "✓" if t.verified else ""]
            tips = {0: f"trial {r + 1}: {rec.label}", 1: origin_tip, q_col: f"{t.grade} (Q = {t.q:.2f})"}
            for c, text in enumerate(cells):
                item = QTableWidgetItem(text)
                if c == q_col:
                    g = next(g for g in GRADES if g.name == t.grade)
                    item.setBackground(QColor(g.color))
                    item.setForeground(QColor("#111111"))
                if c in tips:
                    item.setToolTip(tips[c])
                self.history.setItem(r, c, item)
        self.history.resizeColumnsToContents()
        for column in (0, 1):
            self.history.horizontalHeader().setSectionResizeMode(column, QHeaderView.Stretch)
        self.history.resizeRowsToContents()
        if ps is not None and ps.selected_trial is not None and ps.selected_trial < len(records):
            self.history.selectRow(ps.selected_trial)
        self.history.blockSignals(False)
        self.restore_button.setEnabled(bool(records) and self._selected_row() is not None)
        if not records:
            self.show_trial(None)

    def _selected_row(self) -> int | None:
        rows = self.history.selectionModel().selectedRows() if self.history.selectionModel() else []
        return rows[0].row() if rows else None

    def _row_chosen(self) -> None:
        row = self._selected_row()
        self.restore_button.setEnabled(row is not None)
        if row is not None:
            self.ctrl.select_trial(row)

    def restore_selected(self) -> None:
        row = self._selected_row()
        if row is not None:
            self.ctrl.restore_trial(row)

    def _photo_changed(self) -> None:
        self.refresh_history()
        ps = self.ws.current
        if ps is None or ps.selected_trial is None:
            self.show_trial(None)

    # ------------------------------------------------------------ a trial
    def _style_banner(self, grade) -> None:
        if grade is None:
            self.banner.setStyleSheet("background:#424242; color:#eeeeee; padding:6px; "
                                      "border-radius:4px; font-size:13px;")
        else:
            self.banner.setStyleSheet(f"background:{grade.color}; color:#111111; padding:6px; "
                                      "border-radius:4px; font-size:15px; font-weight:bold;")

    def show_trial(self, index: int | None) -> None:
        """Show a trial of the current photo (None: nothing yet)."""
        ps = self.ws.current
        if ps is None or index is None or not 0 <= index < len(ps.trials):
            self._style_banner(None)
            self.banner.setText("No trial yet: Run or Auto (Register tab), or solve manual pairs.")
            for r in range(len(METRICS)):
                for c in (1, 2, 3):
                    self.table.setItem(r, c, QTableWidgetItem(""))
            self.hint_label.hide()
            self.adapt_label.hide()
            self._fit_hints()
            self.uncertainty_label.hide()
            self.apply_button.setEnabled(False)
            for chip in self.legend_labels:
                chip.setText(chip.text().replace("<b>", "").replace("</b>", ""))
            return
        rec = ps.trials[index]
        t = rec.trial
        prev = ps.trials[index - 1].trial if index > 0 else None
        width = ps.intrinsics.width
        grade = next(g for g in GRADES if g.name == t.grade)
        self._style_banner(grade)
        verified = "verified" if t.verified else "not verified"
        # An unverified pose is graded below what its Q alone would give:
        # say so, or "FAIR · Q = 1.60" contradicts the legend's Q ranges.
        by_q = grade_of(t.q, t.pose is not None)
        capped = (f" (Q alone: {by_q.name}; capped, {verified})"
                  if by_q.name != grade.name and grade.name != "failed" else "")
        self.banner.setText(f"{grade.name.upper()} · Q = {t.q:.2f}{capped} — {grade.text}"
                            "<br><span style='font-size:11px; font-weight:normal'>"
                            f"trial {index + 1}: "
                            f"{html.escape(rec.label)}, {verified}</span>")
        for chip, g in zip(self.legend_labels, GRADES):
            chip.setStyleSheet(f"background:{g.color}; color:#111; padding:2px; border-radius:3px;"
                               + (" border:3px solid white;" if g is grade else ""))
        self.uncertainty_label.setText(uncertainty_text(
            getattr(t, "uncertainty", None), width, verified=bool(getattr(t, "verified", False))))
        self.uncertainty_label.show()
        for r, m in enumerate(METRICS):
            value = t.metrics.get(m.key)
            cls = classify(m, value, width)
            item = QTableWidgetItem(_fmt(m.key, value))
            item.setBackground(QColor(CLASS_COLORS[cls]))
            item.setForeground(QColor("#ffffff"))
            item.setToolTip(CLASS_NAMES[cls])
            item.setData(Qt.UserRole, cls)
            self.table.setItem(r, 1, item)
            if prev is None:
                arrow = QTableWidgetItem("")
                arrow.setData(Qt.UserRole, None)
            else:
                trend = metric_trend(m, value, prev.metrics.get(m.key))
                symbol, colour = TREND_ARROWS[trend]
                arrow = QTableWidgetItem(symbol)
                arrow.setForeground(QColor(colour))
                arrow.setToolTip(f"previous trial: {_fmt(m.key, prev.metrics.get(m.key))}")
                arrow.setData(Qt.UserRole, trend)
            arrow.setTextAlignment(Qt.AlignCenter)
            self.table.setItem(r, 2, arrow)
            s = width / REFERENCE_WIDTH_PX if m.scales_with_width else 1.0
            lo, hi = m.inferior * s, m.superior * s
            if m.lower_is_better:
                # As many decimals as the value (.2f): "1.27 px" against "> 1.3" misreads.
                limits = f"> {lo:.2f} | ≤ {hi:.2f}"
            elif m.key.startswith("inlier_ratio"):
                limits = f"< {lo:g} | ≥ {hi:g}"
            else:
                limits = f"< {lo:,.0f} | ≥ {hi:,.0f}"
            self.table.setItem(r, 3, QTableWidgetItem(limits))
        if t.hints:
            self.hint_label.setText("<br>".join(f"• {html.escape(gui_hint(h))}"
                                                for h in t.hints))
            self.hint_label.show()
        else:
            self.hint_label.hide()
        hit = self.ws.suggestion(index)
        if hit is not None:
            self.adapt_label.setText(f"Suggested for the next trial (rule {hit.rule}): "
                                     f"{html.escape(hit.adaptation)}")
            self.adapt_label.show()
        else:
            self.adapt_label.hide()
        self._fit_hints()
        self.hint_scroll.verticalScrollBar().setValue(0)  # the first hint, the likely cause
        self.apply_button.setEnabled(hit is not None)
        self.history.blockSignals(True)
        self.history.selectRow(index)
        self.history.blockSignals(False)
        self.restore_button.setEnabled(True)

    # ------------------------------------------------------ for tests
    def metric_cell(self, key: str, column: int = 1) -> QTableWidgetItem:
        row = next(r for r, m in enumerate(METRICS) if m.key == key)
        return self.table.item(row, column)
