"""A photo whose file became unreadable after the workspace opened it is shown
as a grey stand-in of its size, with one error notification, not a traceback."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from napari_imgreg.io.photos import load_photo, save_image
from napari_imgreg.widgets._controller import _Layers


def test_an_unreadable_photo_is_a_grey_stand_in_of_its_size(make_napari_viewer, tmp_path):
    path = tmp_path / "IMG_0001.png"
    save_image(path, np.full((30, 40, 3), 200, np.uint8))
    photo = load_photo(path)  # the header only
    path.write_bytes(b"not an image any more")
    viewer = make_napari_viewer()
    layers = _Layers(viewer)
    layers.show_photo(SimpleNamespace(photo=photo))
    layer = viewer.layers["IMG_0001"]
    assert layer.data.shape == (30, 40, 3) and (layer.data == 96).all()
    assert (layers.width, layers.height) == (40, 30)
