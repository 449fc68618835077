"""napari reader: open a textured outcrop mesh as a Surface layer."""

from __future__ import annotations

import os
from pathlib import Path

from .widgets._layers import surface_layer_data
from .io.meshes import MESH_SUFFIXES

__all__ = ["get_reader"]

_READABLE = tuple(s for s in MESH_SUFFIXES if s in (".obj", ".ply", ".glb", ".gltf"))


def get_reader(path: str | os.PathLike | list):
    """Return a reader for OBJ/PLY/GLB/GLTF meshes, else None (npe2 contract)."""
    if isinstance(path, list):
        if len(path) != 1:
            return None
        path = path[0]
    if Path(path).suffix.lower() not in _READABLE:
        return None
    return read_mesh_layers


def read_mesh_layers(path: str | os.PathLike | list) -> list:
    """Layer data for one mesh file (a georef.json beside it is attached)."""
    from .scene import Scene

    if isinstance(path, list):
        path = path[0]
    scene = Scene.load(path)
    return [surface_layer_data(scene)]
