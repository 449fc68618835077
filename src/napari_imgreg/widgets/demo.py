"""``napari-imgreg demo --gui``: napari with the sample scene in the workbench."""

from __future__ import annotations

from pathlib import Path


def open_demo(folder: Path) -> None:  # pragma: no cover - interactive
    """Open napari with the sample scene and its photos loaded in the workbench."""
    import napari

    from .workbench import Workbench

    viewer = napari.Viewer(title="napari-imgreg demo")
    # The workbench, the canvas and the quality dock need the whole screen
    # (napari opens at about two thirds of it).
    viewer.window._qt_window.showMaximized()
    workbench = Workbench.add_to_viewer(viewer)
    workbench.controller.open_scene(
        folder / "outcrop.obj", dem=folder / "dem.tif", photos=sorted(folder.glob("IMG_*.jpg"))
    )
    napari.run()
