"""napari's slider bar under the canvas, hidden while it holds only the
model's height in the 2D view of a photo.

With the model (3D) among the layers, napari gives the 2D view of the
photos a slider for the model's height in metres, which moves nothing the
user sees there (:func:`~napari_imgreg.widgets._layers.only_height_slider`).
napari has no public switch for the bar, and its window's attributes are
private (napari warns a plugin off them): the bar is found as a Qt child
(class ``QtDims``) of the main window that holds one of our docks. A viewer
without a window, or a napari whose bar is another class, keeps its bar as
it is.
"""

from __future__ import annotations

from ._layers import only_height_slider

__all__ = ["HeightSliderHider"]

#: The viewer's events after which the bar is checked again.
_DIMS_EVENTS = ("ndisplay", "range", "axis_labels")
_LAYERS_EVENTS = ("inserted", "removed")


class HeightSliderHider:
    """Keeps a viewer's slider bar hidden while its one slider is the model's
    height and no visible layer has more than two axes.

    Parameters
    ----------
    viewer : napari.Viewer
    anchor : QWidget, optional
        A dock of ours in the viewer's window (settable later: a dock is in
        the window only once it is added).
    """

    def __init__(self, viewer, anchor=None) -> None:
        self.viewer = viewer
        self.anchor = anchor
        self._bar = None
        for name in _DIMS_EVENTS:
            getattr(viewer.dims.events, name).connect(self.update)
        for name in _LAYERS_EVENTS:
            getattr(viewer.layers.events, name).connect(self.update)
        self.update()

    def update(self, event=None) -> None:
        """Check again (also after changing layers' visibility, which napari
        tells the bar nothing of)."""
        dims = self.viewer.dims
        visible_ndims = [layer.ndim for layer in self.viewer.layers if layer.visible]
        self.set_visible(not only_height_slider(dims.axis_labels, dims.displayed, dims.nsteps,
                                                visible_ndims))

    def bar(self):
        """napari's slider bar in the anchor's window (None: not found)."""
        if self._bar is not None or self.anchor is None:
            return self._bar
        from qtpy.QtWidgets import QWidget

        try:
            window = self.anchor.window()
            bars = [w for w in window.findChildren(QWidget) if type(w).__name__ == "QtDims"]
        except RuntimeError:  # deleted
            return None
        if len(bars) == 1:
            self._bar = bars[0]
        return self._bar

    def set_visible(self, visible: bool) -> None:
        try:
            bar = self.bar()
            if bar is not None and bar.isHidden() == visible:
                bar.setVisible(visible)
        except RuntimeError:  # the window is closing: its widgets are deleted
            self._bar = None

    def release(self) -> None:
        """Stop following the viewer and show its bar again."""
        try:
            for name in _DIMS_EVENTS:
                getattr(self.viewer.dims.events, name).disconnect(self.update)
            for name in _LAYERS_EVENTS:
                getattr(self.viewer.layers.events, name).disconnect(self.update)
        except (TypeError, ValueError, RuntimeError):  # pragma: no cover
            pass
        self.set_visible(True)
