"""Stepping through a campaign's photos does not decode them on the GUI thread:
the photos beside the current one are decoded ahead, in the background, and a
snap on a photo whose layer keeps a reduced copy uses the photo's own pixels."""

from __future__ import annotations

import threading

import numpy as np

from ._workbench import idle, load_sample


def _decodes_by_thread(ctrl) -> list[tuple[str, bool]]:
    """Wrap each photo's decoder: record (photo name, decoded on the GUI thread)."""
    seen: list[tuple[str, bool]] = []
    main = threading.main_thread()
    for ps in ctrl.photos:
        photo = ps.photo
        decode = photo._decode

        def recording(photo=photo, decode=decode):
            seen.append((photo.path.name, threading.current_thread() is main))
            return decode()

        photo._decode = recording
    return seen


def test_the_photos_beside_the_current_one_decode_in_the_background(workbench, qtbot):
    ctrl = load_sample(workbench, qtbot)
    assert ctrl.workspace.current_index == 0
    # The next photo was decoded ahead while the first was shown.
    qtbot.waitUntil(lambda: ctrl.photos[1].photo.decoded, timeout=10_000)
    assert not ctrl.photos[2].photo.decoded  # not beside the current one
    seen = _decodes_by_thread(ctrl)
    ctrl.select_photo(1)
    idle(workbench, qtbot)
    # Photo 0 was let go when left (the workspace keeps one photo's pixels)
    # and is decoded again ahead, as is photo 2: neither on the GUI thread.
    qtbot.waitUntil(lambda: ctrl.photos[0].photo.decoded and ctrl.photos[2].photo.decoded,
                    timeout=10_000)
    assert sorted(seen) == [("IMG_0001.jpg", False), ("IMG_0003.jpg", False)]
    seen.clear()
    ctrl.select_photo(2)
    idle(workbench, qtbot)
    assert not any(on_gui for _, on_gui in seen)
    layer = ctrl.layers.get("photo")
    assert layer.data.shape == (768, 1024, 3) and tuple(layer.scale) == (1.0, 1.0)


def test_a_hidden_photo_is_drawn_and_snapped_on_at_its_own_pixels(workbench, qtbot,
                                                                   monkeypatch):
    from napari_imgreg.widgets import interpret_widget as iw

    ctrl = load_sample(workbench, qtbot)
    first = ctrl.layers.get("photo")
    ctrl.select_photo(1)
    idle(workbench, qtbot)
    assert tuple(first.scale) == (16.0, 16.0)  # hidden: a reduced copy
    widget = iw.InterpretWidget(ctrl.viewer)
    # Its interpretation layer lies over the photo's pixels, not the copy's.
    shapes = widget.new_interpretation_layer(first)
    assert tuple(shapes.scale) == (1.0, 1.0)
    shapes.add(np.array([[300.0, 200.0], [310.0, 600.0]]), shape_type="path")
    seen_shapes = []
    real = iw.snap_trace

    def spy(image, clicks, params, reference=None):
        seen_shapes.append(image.shape)
        if reference is not None:  # the model's render: the photo's own size too
            seen_shapes.append(reference.shape)
        return real(image, clicks, params, reference=reference)

    monkeypatch.setattr(iw, "snap_trace", spy)
    assert widget.snap_shape(shapes, 0)
    assert seen_shapes == [(768, 1024, 3)] and len(shapes.data[0]) > 2
    widget.close()
