"""An OBJ opened in napari (dropped, File > Open, ``viewer.open``) goes to
napari-imgreg's textured reader, not napari's built-in grey sheet.

napari builtins also claims ``*.obj``; napari then takes the reader
preference (``settings.plugins.extension2reader``), which
:func:`napari_imgreg._reader.prefer_imgreg_reader` saves when the plugin is
activated. A drop and File > Open go through ``QtViewer._qt_open``, which
calls ``viewer.open(paths, plugin=None)`` and shows the "Choose reader"
dialog only on ``MultipleReaderError``. (A script's bare ``viewer.open(path)``
is napari's builtins by definition in napari 0.9: its ``plugin`` defaults to
"napari".) Runs in a real viewer (under Xvfb).
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from PIL import Image

from napari_imgreg._reader import PLUGIN_NAME, prefer_imgreg_reader

pytestmark = pytest.mark.gui


@pytest.fixture
def viewer(make_napari_viewer):
    return make_napari_viewer()


@pytest.fixture
def settings(viewer, monkeypatch):
    """napari's settings with no reader preferences, never written to disk
    (after the viewer: making one resets the settings)."""
    from napari.settings import get_settings

    s = get_settings()
    monkeypatch.setattr(type(s), "_maybe_save", lambda self: None)
    before = dict(s.plugins.extension2reader)
    s.plugins.extension2reader = {}
    yield s
    s.plugins.extension2reader = before


def _textured_obj(tmp_path):
    vertices = np.array([[0, 0, 0], [40, 0, 0], [40, 0, 20], [0, 0, 20]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    texture = np.full((32, 64, 3), 200, np.uint8)
    texture[:16, :32] = (255, 0, 0)
    mesh = trimesh.Trimesh(vertices, faces, process=False, visual=trimesh.visual.TextureVisuals(
        uv=uv, image=Image.fromarray(texture)))
    path = tmp_path / "wall.obj"
    mesh.export(path)
    return path


def _assert_ours(layers):
    (layer,) = layers
    assert type(layer).__name__ == "Surface"
    assert layer.metadata.get("imgreg_scene") is not None  # what the workbench offers as the model
    assert layer.texture is not None and layer.texcoords is not None


def test_without_a_preference_napari_cannot_choose(viewer, settings, tmp_path):
    """The reported problem: two readers claim .obj and none is preferred."""
    from napari.errors import MultipleReaderError
    from napari.plugins._npe2 import get_readers

    path = _textured_obj(tmp_path)
    assert {PLUGIN_NAME, "napari"} <= set(get_readers(str(path)))
    with pytest.raises(MultipleReaderError):
        viewer.open(path, plugin=None)


def test_preference_makes_viewer_open_pick_imgreg(viewer, settings, tmp_path):
    from napari.plugins.utils import get_preferred_reader

    path = _textured_obj(tmp_path)
    added = prefer_imgreg_reader()
    assert "*.obj" in added and "*.OBJ" in added
    # .ply/.glb/.gltf: no other installed reader claims them, nothing to prefer.
    assert "*.ply" not in added
    assert get_preferred_reader(str(path)) == PLUGIN_NAME
    _assert_ours(viewer.open(path, plugin=None))  # no plugin chosen: the preference decides


def test_drop_opens_without_the_choose_reader_dialog(viewer, settings, tmp_path, monkeypatch):
    """The GUI path of a dropped file (QtViewer._qt_open): no dialog, our layer."""
    from napari._qt.dialogs import qt_reader_dialog

    def no_dialog(*args, **kwargs):
        raise AssertionError("the Choose reader dialog was shown")

    monkeypatch.setattr(qt_reader_dialog.QtReaderDialog, "get_user_choices", no_dialog)
    path = _textured_obj(tmp_path)
    prefer_imgreg_reader()
    viewer.window._qt_viewer._qt_open([str(path)], stack=False)
    _assert_ours(list(viewer.layers))


def test_activation_hook_is_in_the_manifest_and_sets_the_preference(settings):
    from npe2 import PluginManager
    from npe2._plugin_manager import _call_python_name  # how npe2 calls on_activate

    manifest = PluginManager.instance().get_manifest(PLUGIN_NAME)
    assert manifest.on_activate == "napari_imgreg._reader:on_activate"
    _call_python_name(manifest.on_activate, args=(None,))
    assert settings.plugins.extension2reader.get("*.obj") == PLUGIN_NAME


def test_a_users_own_choice_is_kept(settings):
    settings.plugins.extension2reader = {"*.obj": "napari"}
    added = prefer_imgreg_reader()
    assert "*.obj" not in added
    assert settings.plugins.extension2reader["*.obj"] == "napari"
    assert prefer_imgreg_reader() == []  # idempotent


def test_the_choose_reader_dialog_preselects_napari_imgreg(tmp_path):
    """With no preference saved, the dialog lists the readers sorted by display
    name and preselects the first: ours must sort before "napari builtins"."""
    from napari.plugins import _npe2

    readers = _npe2.get_readers(str(tmp_path / "model.obj"))
    assert PLUGIN_NAME in readers and len(readers) >= 2  # napari builtins claims it too
    assert sorted(readers.values())[0] == readers[PLUGIN_NAME]
