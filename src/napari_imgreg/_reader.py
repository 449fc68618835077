"""napari reader: open a textured outcrop mesh as a Surface layer.

napari's own ``builtins`` plugin also claims ``*.obj``: with two readers and
no saved preference, napari raises ``MultipleReaderError`` from
``viewer.open(path)`` and a dropped file gets the "Choose reader" dialog,
which preselects the first reader in alphabetical order of display names
("napari builtins": an untextured grey sheet the workbench cannot use). The
supported way to choose is napari's reader preference,
``settings.plugins.extension2reader`` (Preferences > Plugins > File readers):
once it names a plugin for a pattern, napari opens matching files with it and
shows no dialog. :func:`prefer_imgreg_reader` saves that preference for the
mesh patterns another installed reader also claims — never over a choice the
user made — and runs when napari activates the plugin (the manifest's
``on_activate``: the first use of any of its commands, e.g. docking the
workbench or loading the sample).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from .widgets._layers import cloud_layer_data, surface_layer_data
from .widgets._reader_preferences import (
    _READABLE,
    PLUGIN_NAME,
    prefer_imgreg_reader,
    prefer_workspace_reader,
)

__all__ = ["PLUGIN_NAME", "get_reader", "on_activate", "prefer_imgreg_reader"]

log = logging.getLogger(__name__)

def on_activate(context=None) -> None:
    """npe2 activation hook (napari.yaml ``on_activate``): prefer our mesh
    reader and our reader of ``*.imgreg`` workspace folders."""
    try:
        prefer_imgreg_reader()
        prefer_workspace_reader()
    except Exception as exc:  # noqa: BLE001  # pragma: no cover - a preference never blocks the plugin
        log.warning("napari-imgreg: reader preference not saved: %s", exc)


def get_reader(path: str | os.PathLike | list):
    """Return a reader for OBJ/PLY/GLB/GLTF meshes and LAS/LAZ/E57/PTS/XYZ (or
    vertex-only PLY) point clouds, else None (npe2 contract)."""
    if isinstance(path, list):
        if len(path) != 1:
            return None
        path = path[0]
    if Path(path).suffix.lower() not in _READABLE:
        return None
    return read_mesh_layers


def read_mesh_layers(path: str | os.PathLike | list) -> list:
    """Layer data for one mesh or point-cloud file (a georef.json beside it is
    attached): a Surface layer, or a Points layer of the (decimated) cloud."""
    from .scene import Scene

    if isinstance(path, list):
        path = path[0]
    scene = Scene.load(path)
    if getattr(scene, "is_cloud", False):
        scene.build_engine()  # the spacing that sizes the points
        return [cloud_layer_data(scene)]
    return [surface_layer_data(scene)]
