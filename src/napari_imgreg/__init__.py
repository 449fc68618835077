"""napari-imgreg: register field photographs to 3D outcrop models.

The functions a script calls first (backend, no Qt):

* :func:`register` — a photo + its sensor record → a verified camera pose
  (:class:`Registration`, the RESULT.json of ``docs/formats.md``).
* :func:`render` — colour and the 3D point behind every pixel from a camera pose.
* :func:`project` — lines and polygons drawn on a registered photo → the model.
* :func:`measure` — plunge/trend of traces, dip/dip direction of facets.
* :func:`orient` — orient a photogrammetry model from phone camera attitudes.
* :class:`Scene` — the model with its ray engine, georeference and DEM;
  :class:`Intrinsics`, :class:`Pose` — the camera model and ``cam_from_world``.

``docs/architecture.md`` says which package does what.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

from . import _deprecated

_deprecated.install()  # old flat module paths keep working, with a warning

from .camera import Intrinsics, Pose, attitude_from_rotation, rotation_from_attitude
from .errors import InputError
from .render import RenderResult, render
from .scene import Scene

# Loaded on first use, so that ``import napari_imgreg`` (done by napari when
# it reads the plugin manifest) does not pull in OpenCV and the pipeline.
_LAZY = {
    "register": "napari_imgreg.api",
    "project": "napari_imgreg.api",
    "measure": "napari_imgreg.api",
    "Registration": "napari_imgreg.registration.pipeline",
    "RegistrationParams": "napari_imgreg.registration.params",
    "Prior": "napari_imgreg.prior",
    "Feature3D": "napari_imgreg.interpret.project",
    "Interpretation": "napari_imgreg.interpret.project",
    "Measurement": "napari_imgreg.interpret.structural",
    "OrientationResult": "napari_imgreg.orient",
    # What a script needs beside the five functions: a campaign, a photo in
    # memory or its prior, the projection's settings and error model, and the
    # files of drawings and measurements.
    "Workspace": "napari_imgreg.workspace",
    "load_registration": "napari_imgreg.registration.result_file",
    "Photo": "napari_imgreg.io.photos",
    "load_photo": "napari_imgreg.io.photos",
    "prior_for_photo": "napari_imgreg.prior",
    "ProjectionParams": "napari_imgreg.interpret.project",
    "FitThresholds": "napari_imgreg.interpret.structural",
    "PoseUncertainty": "napari_imgreg.interpret.uncertainty",
    "UncertaintyParams": "napari_imgreg.interpret.uncertainty",
    "read_interpretations": "napari_imgreg.interpret.files",
    "export_features": "napari_imgreg.interpret.files",
    "write_measurements_csv": "napari_imgreg.interpret.files",
}


def __getattr__(name: str):
    if name == "orient":
        # The package napari_imgreg.orient, which is callable as orient():
        # Python would bind the subpackage over a function of that name.
        return importlib.import_module("napari_imgreg.orient")
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'napari_imgreg' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY) | {"orient"})


__all__ = [
    "Feature3D",
    "FitThresholds",
    "InputError",
    "Interpretation",
    "Intrinsics",
    "Measurement",
    "OrientationResult",
    "Photo",
    "Pose",
    "PoseUncertainty",
    "Prior",
    "ProjectionParams",
    "Registration",
    "RegistrationParams",
    "RenderResult",
    "Scene",
    "UncertaintyParams",
    "Workspace",
    "attitude_from_rotation",
    "export_features",
    "load_photo",
    "load_registration",
    "measure",
    "orient",
    "prior_for_photo",
    "project",
    "read_interpretations",
    "register",
    "render",
    "rotation_from_attitude",
    "write_measurements_csv",
]
