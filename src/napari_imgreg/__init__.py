"""napari-imgreg: register field photographs to textured 3D outcrop models.

Public API (backend, no Qt):

* :class:`Scene` — a textured mesh with its ray engine, georeference and DEM.
* :func:`render` — colour and per-pixel 3D coordinates from a camera pose.
* :class:`Intrinsics`, :class:`Pose` — the camera model and ``cam_from_world``.
"""

from __future__ import annotations

__version__ = "0.1.0"

from napari_imgreg import _deprecated

_deprecated.install()  # old flat module paths keep working, with a warning

from napari_imgreg.camera import Intrinsics, Pose, attitude_from_rotation, rotation_from_attitude
from napari_imgreg.errors import InputError
from napari_imgreg.render import RenderResult, render
from napari_imgreg.scene import Scene

__all__ = [
    "Intrinsics",
    "InputError",
    "Pose",
    "RenderResult",
    "Scene",
    "attitude_from_rotation",
    "render",
    "rotation_from_attitude",
]
