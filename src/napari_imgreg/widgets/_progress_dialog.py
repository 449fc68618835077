"""A window-modal progress dialog for work that must not be disturbed: the
workbench's *Save workspace as…* while its worker writes the workspace.

Shown over the viewer's window, it blocks the window's input (the docks, the
canvas, the keyboard shortcuts) while the window keeps repainting; it has no
Cancel and cannot be closed by the user (Escape, the close button), and goes
when the work is done.

Not a :class:`~qtpy.QtWidgets.QProgressDialog`: a modal one processes the
pending events inside each ``setValue``, which would deliver the job's
return in the middle of its own progress update.
"""

from __future__ import annotations

from qtpy.QtCore import Qt
from qtpy.QtWidgets import QDialog, QLabel, QProgressBar, QVBoxLayout, QWidget

__all__ = ["ModalProgress"]


class ModalProgress(QDialog):
    """A progress bar and a line saying what is done, modal to ``parent``'s window.

    Parameters
    ----------
    parent : QWidget or None
        A widget of the window to block (its window is the dialog's parent);
        None: the dialog blocks every window of the application.
    title : str
    text : str
        The first line shown.
    total : int
        Steps of the bar (0: a busy bar).
    hint : str
        A line under the bar (why the window waits).
    """

    def __init__(self, parent: QWidget | None, title: str, text: str, total: int,
                 hint: str = "") -> None:
        window = parent.window() if parent is not None else None
        super().__init__(window)
        self.setWindowTitle(title)
        self.setWindowModality(Qt.WindowModal if window is not None else Qt.ApplicationModal)
        # No close button in the title bar (where the window manager honours it).
        self.setWindowFlags((self.windowFlags() | Qt.CustomizeWindowHint | Qt.WindowTitleHint)
                            & ~Qt.WindowCloseButtonHint & ~Qt.WindowContextHelpButtonHint)
        self.label = QLabel(text)
        self.label.setWordWrap(True)
        self.bar = QProgressBar()
        self.bar.setRange(0, max(int(total), 0))
        self.bar.setValue(0)
        layout = QVBoxLayout(self)
        layout.addWidget(self.label)
        layout.addWidget(self.bar)
        if hint:
            self.hint = QLabel(hint)
            self.hint.setWordWrap(True)
            self.hint.setStyleSheet("color: #9e9e9e; font-size: 11px;")
            layout.addWidget(self.hint)
        self.setMinimumWidth(420)
        self._finished = False

    def set_progress(self, done: int, text: str | None = None) -> None:
        """Move the bar to ``done`` steps (and say ``text``)."""
        self.bar.setValue(int(done))
        if text is not None:
            self.label.setText(text)

    def finish(self) -> None:
        """The work is done: the dialog goes."""
        self._finished = True
        self.close()
        self.deleteLater()

    # The user cannot dismiss it: the work it shows goes on regardless.
    def reject(self) -> None:  # Escape
        if self._finished:
            super().reject()

    def closeEvent(self, event) -> None:
        if self._finished:
            super().closeEvent(event)
        else:
            event.ignore()
