"""The registration workbench docked in a test viewer, left idle and detached."""

from __future__ import annotations

import pytest


@pytest.fixture
def workbench(make_napari_viewer, qtbot):
    from napari_imgreg.widgets.workbench import Workbench

    viewer = make_napari_viewer()
    wb = Workbench.add_to_viewer(viewer)
    yield wb
    wb.controller.cancel_register_all()
    qtbot.waitUntil(lambda: not wb.controller.busy, timeout=30_000)
    wb.controller.workspace.detach()


@pytest.fixture
def orient_widget(make_napari_viewer):
    """The Orient model dock in a test viewer."""
    from napari_imgreg.widgets.orient_widget import OrientWidget

    viewer = make_napari_viewer()
    widget = OrientWidget(viewer)
    viewer.window.add_dock_widget(widget, name="Orient model")
    return widget
