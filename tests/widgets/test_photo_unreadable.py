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


def test_a_hidden_photo_lets_its_pixels_go_and_gets_them_back(make_napari_viewer, tmp_path):
    """One layer per photo visited: hidden, it keeps a 1/16 copy at the same
    extent (a campaign's photos would all stay in memory), shown again, all."""
    photos = []
    for k, size in enumerate([(320, 480), (240, 320)]):
        path = tmp_path / f"IMG_000{k + 1}.png"
        save_image(path, np.full((*size, 3), 60 * (k + 1), np.uint8))
        photos.append(SimpleNamespace(photo=load_photo(path)))
    viewer = make_napari_viewer()
    layers = _Layers(viewer)
    layers.show_photo(photos[0])
    layers.show_photo(photos[1])
    first = viewer.layers["IMG_0001"]
    assert not first.visible and first.data.shape == (20, 30, 3)
    assert tuple(first.scale) == (16.0, 16.0)
    assert viewer.layers["IMG_0002"].data.shape == (240, 320, 3)
    layers.show_photo(photos[0])
    assert first.visible and first.data.shape == (320, 480, 3) and tuple(first.scale) == (1, 1)
    assert (first.data == 60).all() and viewer.layers["IMG_0002"].data.shape == (15, 20, 3)
