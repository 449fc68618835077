"""The photos table of the workbench: every photo of the workspace, where it stands.

One row per photo: a thumbnail, its name, its status (not registered,
failed, registered, accepted), the grade and Q of its last registration, the
expected reprojection error of its pose (``uncertainty.reprojection_px`` of
RESULT.json, pixels), and how long its registration took. Click a header to
sort; click a row to work on that photo. Rows that need attention
(:meth:`~napari_imgreg.workspace.Workspace.needs_attention`) are marked, and
"Next needing attention" (key N over the canvas) goes to the next one.

Above it, **Register all** registers every photo not registered yet in the
background (the one job runner of :mod:`._jobs`), with a progress bar and
Cancel; each finished photo is recorded (and saved, in a saved workspace)
before the next starts, so a cancelled batch resumes where it stopped.
"""

from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import fields

import cv2
import numpy as np
from qtpy.QtCore import QSize, Qt
from qtpy.QtGui import QColor, QIcon, QImage, QPixmap
from qtpy.QtWidgets import (
    QAbstractItemView,
    QCheckBox,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QProgressBar,
    QPushButton,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from ..registration.quality import GRADES
from ..workspace import PhotoState, PhotoSummary
from ._signals import follow_while_alive
from ._controller import WorkbenchController
from ._shortcuts import key_of

__all__ = ["PhotosTable", "COLUMNS", "THUMBNAIL_WIDTH", "STATUS_COLORS"]

#: The table's columns, left to right.
#: "time" last: in a narrow dock the table scrolls sideways, and the time
#: is what the user needs least.
COLUMNS = ("", "photo", "status", "grade", "Q", "± px", "lines", "time")
TIME_COLUMN = COLUMNS.index("time")
LINES_COLUMN = COLUMNS.index("lines")
#: Thumbnail width, pixels.
THUMBNAIL_WIDTH = 52  # with the six columns, fits the workbench's ~480 px
#: Text colour of each status.
STATUS_COLORS = {"not registered": "#bdbdbd", "failed": "#ff6e6e", "registered": "#91cf60",
                 "accepted": "#4fc3f7"}
_GRADE_COLORS = {g.name: g.color for g in GRADES}
_GRADE_RANK = {g.name: k for k, g in enumerate(GRADES)}
#: Sort order of the statuses (ascending: the ones needing work first).
_STATUS_ORDER = {"not registered": 0, "failed": 1, "registered": 2, "accepted": 3}
#: The role holding an item's sort key (numbers sort as numbers, missing ones last).
SORT_ROLE = Qt.ItemDataRole.UserRole + 1
#: The role holding the photo's index in the workspace (column 1).
PHOTO_ROLE = Qt.ItemDataRole.UserRole + 2


class _Item(QTableWidgetItem):
    """A cell that sorts by its sort key, not its text."""

    def __lt__(self, other: QTableWidgetItem) -> bool:
        a, b = self.data(SORT_ROLE), other.data(SORT_ROLE)
        if a is None or b is None:
            return super().__lt__(other)
        return a < b


def _number_key(value: float) -> float:
    # Missing values (—) sort after every number in ascending order, first in descending.
    return value if math.isfinite(value) else float("inf")


def _show_lines(item: QTableWidgetItem, s) -> None:
    """Fill a "lines" cell from the photo's :class:`PhotoSummary`."""
    item.setText(_lines_text(s))
    item.setData(SORT_ROLE, s.drawn)
    item.setToolTip(f"{s.drawn} drawn on the photo; {s.mapped} mapped onto the model by the "
                    "last projection"
                    + (" (its drawings or pose changed since)" if s.mapped_out_of_date else ""))


def _lines_text(s) -> str:
    """The photos table's "lines" cell: how many features are drawn on the
    photo, and whether the last projection mapped them as they are now."""
    if not s.drawn and not s.mapped:
        return "—"
    if s.mapped_out_of_date:
        return f"{s.drawn} · out of date"
    if s.drawn and not s.mapped:
        return f"{s.drawn} · not mapped"
    return f"{s.drawn} ✓"


def _thumbnail(photo) -> QPixmap:
    """A small RGB copy of a photo as a pixmap (a JPEG decoded at a reduced
    scale, its full pixels not kept: a campaign's photos are not all decoded)."""
    small = np.ascontiguousarray(photo.thumbnail(THUMBNAIL_WIDTH), dtype=np.uint8)
    th, tw = small.shape[:2]
    qimage = QImage(small.data, tw, th, 3 * tw, QImage.Format.Format_RGB888)
    return QPixmap.fromImage(qimage.copy())  # copy: the array is freed


def _row_shown(s: PhotoSummary, ps: PhotoState) -> tuple:
    """What a row shows, comparable: the photo (by identity: a new photo may
    reuse an old one's id) and its cells' content (a missing number, NaN, as
    None: NaN equals nothing)."""
    values = tuple(None if isinstance(v, float) and math.isnan(v) else v
                   for v in vars(s).values())
    return _Identity(ps), values + (ps.error,)


#: The fields of a PhotoSummary that the "lines" cell shows.
_LINES_FIELDS = ("drawn", "mapped", "mapped_out_of_date")


def _but_lines(shown: tuple | None) -> tuple | None:
    """What :func:`_row_shown` says of a row but its "lines" cell."""
    if shown is None:
        return None
    photo, values = shown
    names = [f.name for f in fields(PhotoSummary)]
    kept = tuple(v for name, v in zip(names, values) if name not in _LINES_FIELDS)
    return photo, kept + values[len(names):]  # (and what follows the summary: its error)


class _Identity:
    """Equal to another only when holding the same object."""

    __slots__ = ("obj",)

    def __init__(self, obj) -> None:
        self.obj = obj

    def __eq__(self, other) -> bool:
        return isinstance(other, _Identity) and other.obj is self.obj


class PhotosTable(QWidget):
    """The photos of the workspace with their status, and Register all (see the
    module docstring)."""

    def __init__(self, controller: WorkbenchController, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.ctrl = controller
        self.ws = controller.workspace  # the state shown here
        controller.thumbnail_width = THUMBNAIL_WIDTH  # made ahead when a workspace opens
        self._thumbs: dict[int, QPixmap] = {}
        self._filling = False
        #: What each row shows, by workspace index (see refresh).
        self._shown: list[tuple | None] = []

        self.register_all_button = QPushButton("Register all")
        self.register_all_button.setToolTip(
            "Register every photo not registered yet (Auto: trials adapted by the rules), one "
            "after the other, in the background. Registered and accepted photos are skipped, "
            "so after Cancel it resumes with the rest.")
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.setEnabled(False)
        self.cancel_button.setToolTip("Stop within the running photo; finished photos stay")
        self.redo_check = QCheckBox("redo registered")
        self.redo_check.setToolTip("Register the registered photos again too (not the accepted)")
        self.attention_button = QPushButton(f"Next needing attention ({key_of('attention')})")
        self.attention_button.setToolTip(
            "The next photo not registered, failed, graded fair or poor, or with a large "
            "expected error — and not accepted")
        self.accept_button = QPushButton(f"Accept pose ({key_of('accept')})")
        self.accept_button.setToolTip(
            "Accept the current photo's pose as it is (it no longer needs attention until "
            "the pose changes), then go to the next photo needing attention")
        top = QHBoxLayout()
        for w in (self.register_all_button, self.cancel_button, self.redo_check):
            top.addWidget(w)
        top.addStretch(1)
        second = QHBoxLayout()
        second.addWidget(self.attention_button)
        second.addWidget(self.accept_button)
        second.addStretch(1)
        self.progress = QProgressBar()
        self.progress.setRange(0, 100)
        self.progress.setValue(0)
        self.progress.setFormat("Register all: %p%")
        self.progress.setVisible(False)
        self.progress_label = QLabel("")
        self.progress_label.setWordWrap(True)
        self.progress_label.setStyleSheet("color: #bdbdbd; font-size: 11px;")

        self.table = QTableWidget(0, len(COLUMNS))
        self.table.setHorizontalHeaderLabels(list(COLUMNS))
        self.table.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        self.table.setSelectionMode(QAbstractItemView.SelectionMode.SingleSelection)
        self.table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.setIconSize(QSize(THUMBNAIL_WIDTH, THUMBNAIL_WIDTH))
        self.table.verticalHeader().setVisible(False)
        self.table.setWordWrap(False)
        self.table.setTextElideMode(Qt.TextElideMode.ElideMiddle)
        self.table.setSortingEnabled(True)
        # In the workspace's order until a header is clicked (Qt starts descending).
        self.table.sortItems(0, Qt.SortOrder.AscendingOrder)
        self.table.setMinimumHeight(220)
        header = self.table.horizontalHeader()
        header.setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)
        header.setMinimumSectionSize(28)
        for k, tip in ((2, "not registered, failed, registered, or accepted by you"),
                       (3, "grade of the last registration"),
                       (4, "quality Q of the last registration, −1.9 … 1.9"),
                       (5, ("expected reprojection error of the pose, pixels "
                            "(RESULT.json uncertainty.reprojection_px)")),
                       (TIME_COLUMN, "time of the last registration, seconds"),
                       (LINES_COLUMN, ("features drawn on the photo; ✓: all mapped onto the model by "
                            "the last projection, 'not mapped' or 'out of date': Project "
                            "(Interpret tab) again"))):
            self.table.horizontalHeaderItem(k).setToolTip(tip)
        self.summary_label = QLabel("")
        self.summary_label.setWordWrap(True)

        layout = QVBoxLayout(self)
        layout.addLayout(top)
        layout.addWidget(self.progress)
        layout.addWidget(self.progress_label)
        layout.addWidget(self.table, 1)
        layout.addWidget(self.summary_label)
        layout.addLayout(second)

        self.register_all_button.clicked.connect(
            lambda: controller.register_all(auto=True, redo=self.redo_check.isChecked()))
        self.cancel_button.clicked.connect(controller.cancel_register_all)
        self.attention_button.clicked.connect(controller.next_needing_attention)
        self.accept_button.clicked.connect(controller.accept)
        self.table.itemSelectionChanged.connect(self._row_chosen)
        for signal in (controller.photos_changed, controller.trials_changed,
                       controller.scene_changed):
            signal.connect(self.refresh)
        controller.accepted_changed.connect(lambda _ps: self.refresh())
        self._follow_drawings()
        controller.photo_changed.connect(self._select_current)
        controller.batch_started.connect(self._batch_started)
        controller.batch_progress.connect(self._batch_progress)
        controller.batch_finished.connect(self._batch_finished)
        controller.busy_changed.connect(self._busy)
        self.refresh()

    def _follow_drawings(self) -> None:
        """Keep the "lines" column current as drawings and projections change
        (released with the widget: the workspace may outlive it)."""
        ws = self.ws
        follow_while_alive(self, [(ws.interpretations_changed, self._lines_changed),
                                  (ws.projection_changed, self.refresh),
                                  # a pose edit puts the photo's mapped lines out of date
                                  (ws.pose_changed, self._current_lines_changed)])

    def _current_lines_changed(self, *_args) -> None:
        self._lines_changed(self.ws.current)

    def _lines_changed(self, ps: PhotoState | None = None) -> None:
        """Only that photo's "lines" cell (a line drawn, a pose nudged or
        dragged: these come often, and each cell digests its photo's drawings)."""
        if ps is None or ps not in self.ws.photos:
            return
        row = self.row_of(self.ws.photos.index(ps))
        item = None if row is None else self.table.item(row, LINES_COLUMN)
        if item is not None:
            s = self.ws.photo_summary(ps)
            _show_lines(item, s)
            index = self.ws.photos.index(ps)
            shown = _row_shown(s, ps)
            # The row is up to date if nothing but its lines cell changed; else
            # the next refresh fills it.
            if index < len(self._shown) and _but_lines(self._shown[index]) == _but_lines(shown):
                self._shown[index] = shown

    # ------------------------------------------------------------- rows
    def thumbnail(self, ps: PhotoState) -> QPixmap:
        key = id(ps)
        if key not in self._thumbs:
            self._thumbs[key] = _thumbnail(ps.photo)
        return self._thumbs[key]

    def refresh(self) -> None:
        """Bring the rows up to date with the workspace (keeping the sort order).

        Only the rows whose photo, or what they show of it, changed are filled
        again: a switch of photo or one photo's registration (which refresh
        the table) costs a row, not the whole campaign's.
        """
        photos = self.ws.photos
        live = {id(ps) for ps in photos}
        self._thumbs = {k: v for k, v in self._thumbs.items() if k in live}
        summaries = [self.ws.photo_summary(ps) for ps in photos]
        shown = [_row_shown(s, ps) for ps, s in zip(photos, summaries)]
        rows = self._rows_by_index() if len(self._shown) == len(photos) else None
        with self._rows_changing():
            if rows is None or len(rows) != len(photos):
                # Photos added or removed: every row (in the workspace's order, sorted after).
                self.table.setRowCount(len(photos))
                rows = {index: index for index in range(len(photos))}
                self._shown = [None] * len(photos)
            for index, (ps, s) in enumerate(zip(photos, summaries)):
                if self._shown[index] != shown[index]:
                    self._fill(rows[index], index, ps, s)
                    self._shown[index] = shown[index]
        self._select_current()
        self._summarise()

    @contextmanager
    def _rows_changing(self):
        """Cells set in bulk: sorting off (rows move while filled otherwise),
        and the columns sized to their contents once at the end (sized at
        every cell set, each set measured its whole column: a fill of the
        table grew with the square of its rows, 12 s for 300 photos)."""
        header = self.table.horizontalHeader()
        sorting = self.table.isSortingEnabled()
        self._filling = True
        self.table.setSortingEnabled(False)
        header.setSectionResizeMode(QHeaderView.ResizeMode.Interactive)
        try:
            yield
        finally:
            self.table.resizeColumnsToContents()
            header.setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)
            self.table.setSortingEnabled(sorting)
            self._filling = False

    def _rows_by_index(self) -> dict[int, int]:
        """The table row of each workspace photo index, as the rows are sorted now."""
        rows = {}
        for row in range(self.table.rowCount()):
            index = self.photo_index_at(row)
            if index is not None:
                rows[index] = row
        return rows

    def _fill(self, row: int, index: int, ps: PhotoState, s: PhotoSummary | None = None) -> None:
        """Fill table row ``row`` with photo ``index`` (``s``: its summary, if known)."""
        s = self.ws.photo_summary(ps) if s is None else s
        thumb = _Item()
        thumb.setIcon(QIcon(self.thumbnail(ps)))
        thumb.setData(SORT_ROLE, index)
        thumb.setSizeHint(QSize(THUMBNAIL_WIDTH + 8, THUMBNAIL_WIDTH * 3 // 4 + 6))
        name = _Item(("● " if s.attention else "") + s.name)
        name.setData(SORT_ROLE, s.name)
        name.setData(PHOTO_ROLE, index)
        name.setToolTip(s.name + (" — needs attention" if s.attention else ""))
        status = _Item(s.status)
        status.setData(SORT_ROLE, _STATUS_ORDER.get(s.status, 0))
        status.setForeground(QColor(STATUS_COLORS.get(s.status, "#ffffff")))
        if ps.error:  # Register all could not register it: why
            status.setToolTip(f"Register all stopped on this photo: {ps.error}")
        grade = _Item(s.grade or "—")
        grade.setData(SORT_ROLE, _GRADE_RANK.get(s.grade, len(GRADES)))  # best first
        if s.grade in _GRADE_COLORS:
            grade.setForeground(QColor(_GRADE_COLORS[s.grade]))
        q = _Item("—" if not math.isfinite(s.q) else f"{s.q:.2f}")
        q.setData(SORT_ROLE, _number_key(s.q))
        unc = _Item("—" if not math.isfinite(s.reprojection_px) else f"{s.reprojection_px:.1f}")
        unc.setData(SORT_ROLE, _number_key(s.reprojection_px))
        secs = _Item("—" if not math.isfinite(s.time_s) else f"{s.time_s:.1f}")
        secs.setData(SORT_ROLE, _number_key(s.time_s))
        lines = _Item()
        _show_lines(lines, s)
        for col, item in enumerate((thumb, name, status, grade, q, unc, lines, secs)):
            if col >= 2:
                item.setTextAlignment(int(Qt.AlignmentFlag.AlignCenter))
            self.table.setItem(row, col, item)
        self.table.setRowHeight(row, THUMBNAIL_WIDTH * 3 // 4 + 6)

    def photo_index_at(self, row: int) -> int | None:
        """The workspace index of the photo shown in table row ``row``."""
        item = self.table.item(row, 1)
        return None if item is None else int(item.data(PHOTO_ROLE))

    def row_of(self, index: int) -> int | None:
        """The table row showing workspace photo ``index``."""
        for row in range(self.table.rowCount()):
            if self.photo_index_at(row) == index:
                return row
        return None

    def _summarise(self) -> None:
        counts: dict[str, int] = {}
        for ps in self.ws.photos:
            status = self.ws.photo_status(ps)
            counts[status] = counts.get(status, 0) + 1
        attention = sum(self.ws.needs_attention(ps) for ps in self.ws.photos)
        parts = [f"{n} {name}" for name, n in counts.items()]
        self.summary_label.setText(
            (", ".join(parts) + f"; {attention} need attention (●)") if parts
            else "No photos yet: add photos in the Scene tab, or open a workspace.")

    def _select_current(self) -> None:
        k = self.ws.current_index
        row = self.row_of(k) if k is not None else None
        self._filling = True
        try:
            if row is None:
                self.table.clearSelection()
            else:
                self.table.selectRow(row)
                self.table.scrollToItem(self.table.item(row, 1))
        finally:
            self._filling = False

    def _row_chosen(self) -> None:
        if self._filling:
            return
        rows = {i.row() for i in self.table.selectedItems()}
        if len(rows) != 1:
            return
        index = self.photo_index_at(rows.pop())
        if index is not None and index != self.ws.current_index:
            self.ctrl.select_photo(index)

    # ----------------------------------------------------------- batch
    def _batch_started(self, todo: int) -> None:
        self.progress.setVisible(True)
        self.progress.setValue(0)
        self.progress_label.setText(f"{todo} photo(s) to register…")

    def _batch_progress(self, fraction: float, message: str) -> None:
        self.progress.setValue(int(round(100 * fraction)))
        self.progress_label.setText(message)

    def _batch_finished(self, summary) -> None:
        if summary is None:
            self.progress_label.setText("Register all failed: see the status line")
        else:
            if summary.failed:
                self.progress_label.setText(
                    self.progress_label.text() + "<br>Not registered: "
                    + "; ".join(summary.failed[:6]) + (" …" if len(summary.failed) > 6 else ""))
        self.refresh()

    def _busy(self) -> None:
        running = self.ctrl.is_running("register all")
        self.register_all_button.setEnabled(not running)
        self.cancel_button.setEnabled(running)
