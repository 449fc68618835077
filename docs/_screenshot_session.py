"""The napari session both screenshot scripts drive (user guide, workspace).

Imported by ``docs/user_guide_screenshots.py`` and
``docs/workspace_screenshots.py`` (run as scripts, so this folder is on
``sys.path``). Needs a display: run under ``xvfb-run``.
"""

from __future__ import annotations

import time


def event_pumps(app, wait_timeout_s: float = 120.0):
    """``pump(seconds)`` and ``wait(cond, timeout=wait_timeout_s)`` on ``app``
    (see :func:`open_workbench`)."""

    def pump(seconds: float = 0.3) -> None:
        end = time.time() + seconds
        while time.time() < end:
            app.processEvents()
            time.sleep(0.01)

    def wait(cond, timeout: float = wait_timeout_s) -> None:
        end = time.time() + timeout
        while not cond():
            app.processEvents()
            time.sleep(0.01)
            if time.time() > end:
                raise TimeoutError
        pump(0.5)

    return pump, wait


def open_workbench(wait_timeout_s: float = 120.0):
    """A 1600×1000 napari window with the workbench docked.

    Returns
    -------
    app, viewer, workbench, pump, wait
        ``pump(seconds)`` processes Qt events for that long; ``wait(cond,
        timeout=wait_timeout_s)`` processes them until ``cond()`` is true
        (TimeoutError beyond), then half a second more for the repaint.
    """
    import napari
    from qtpy.QtWidgets import QApplication

    from napari_imgreg.widgets.workbench import Workbench

    app = QApplication.instance() or QApplication([])
    pump, wait = event_pumps(app, wait_timeout_s)

    viewer = napari.Viewer(title="napari-imgreg", show=True)
    viewer.window._qt_window.resize(1600, 1000)
    pump(0.5)
    return app, viewer, Workbench.add_to_viewer(viewer), pump, wait


def quality_height(viewer, height: int) -> None:
    """Give the Registration quality dock (under the canvas) ``height`` pixels.

    Its default share of the window's height shows the banner, the legend and
    only the first metric rows; a screenshot about the quality panel wants
    them all. The photo and the render, side by side, keep their size (the
    canvas is wider than it is tall).
    """
    from qtpy.QtCore import Qt
    from qtpy.QtWidgets import QDockWidget

    window = viewer.window._qt_window
    for dock in window.findChildren(QDockWidget):
        if dock.windowTitle().startswith("Registration quality"):
            window.resizeDocks([dock], [height], Qt.Orientation.Vertical)
            return
    raise LookupError("no Registration quality dock")
