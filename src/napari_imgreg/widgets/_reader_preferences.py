"""Reader preferences: make napari open our files with napari-imgreg's readers.

napari's "Choose reader" dialog preselects the first compatible reader by
name ("napari builtins" sorts first), so a dropped OBJ would open as an
untextured grey sheet. Saving the plugin in napari's ``extension2reader``
preferences (never over a choice the user made) is the supported route.
"""

from __future__ import annotations

import logging

from ..io.meshes import MESH_SUFFIXES
from ..io.pointclouds import POINT_CLOUD_SUFFIXES

__all__ = ["PLUGIN_NAME", "WORKSPACE_PATTERN", "prefer_imgreg_reader",
           "prefer_workspace_reader"]

log = logging.getLogger(__name__)

#: The plugin's npe2 name (napari.yaml ``name``), as reader preferences store it.
PLUGIN_NAME = "napari-imgreg"

#: What the plugin's reader opens: meshes, and lidar point clouds (napari.yaml lists both).
_READABLE = tuple(dict.fromkeys(
    [s for s in MESH_SUFFIXES if s in (".obj", ".ply", ".glb", ".gltf")]
    + list(POINT_CLOUD_SUFFIXES)))


def _competing_readers(suffix: str) -> set[str]:
    """Other installed plugins whose readers claim a file name ending in ``suffix``."""
    from npe2 import PluginManager

    pm = PluginManager.instance()
    return {r.plugin_name for r in pm.iter_compatible_readers([f"model{suffix}"])} - {PLUGIN_NAME}


def prefer_imgreg_reader(settings=None) -> list[str]:
    """Make napari open our mesh files with this plugin's reader.

    For each mesh suffix (``.obj``, ``.ply``, ``.glb``, ``.gltf``, in lower
    and upper case: napari matches patterns case-sensitively on Linux and
    macOS) that another installed reader also claims, saves
    ``"*<suffix>": "napari-imgreg"`` in napari's reader preferences, unless
    the user has a preference for that pattern already (theirs is kept).

    Parameters
    ----------
    settings : napari.settings.NapariSettings, optional
        Default: napari's (``napari.settings.get_settings()``).

    Returns
    -------
    list of str
        The patterns newly set (empty when nothing changed).
    """
    if settings is None:
        from napari.settings import get_settings

        settings = get_settings()
    prefs = dict(settings.plugins.extension2reader)
    added = []
    for suffix in _READABLE:
        for variant in (suffix, suffix.upper()):
            pattern = "*" + variant
            if pattern in prefs or not _competing_readers(variant):
                continue
            prefs[pattern] = PLUGIN_NAME
            added.append(pattern)
    if added:
        settings.plugins.extension2reader = prefs
        log.info("napari-imgreg opens %s files from now on (napari Preferences > Plugins > "
                 "File readers to change it)", ", ".join(added))
    return added


WORKSPACE_PATTERN = "*.imgreg/"


def prefer_workspace_reader() -> bool:
    """Make napari-imgreg napari's reader of ``*.imgreg`` folders, unless the
    user chose another one (napari's builtin reader also claims folders, so
    dropping one would ask which reader to use). Returns True when set here.

    ``*.imgreg`` is napari-imgreg's own extension: no other reader reads it.
    """
    try:
        from napari.settings import get_settings

        readers = get_settings().plugins.extension2reader
        if WORKSPACE_PATTERN in readers:
            return False
        get_settings().plugins.extension2reader = {**readers,
                                                   WORKSPACE_PATTERN: "napari-imgreg"}
        return True
    except Exception as exc:  # noqa: BLE001  # pragma: no cover - napari's settings; the dialog remains
        log.debug("reader preference not set: %s", exc)
        return False
