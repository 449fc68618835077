"""The functions a script calls first: register, render, project, measure, orient.

Each accepts what a user has at hand — file paths or the loaded objects — and
returns the package's own result types. They are thin: the work is done by
the stage packages (``registration``, ``interpret``, ``orient``), which the
command line and the napari widgets call too.

Examples
--------
>>> import napari_imgreg as ir                                    # doctest: +SKIP
>>> scene = ir.Scene.load("outcrop.obj", dem="dem.tif")
>>> result = ir.register(scene, "IMG_0001.jpg")                   # IMG_0001.json beside it
>>> result.status, result.grade_info().grade
>>> lines3d = ir.project(scene, result, "IMG_0001.lines.geojson")
>>> for m in ir.measure(lines3d):
...     print(m.kind, m.dip_deg, m.dip_direction_deg)
"""

from __future__ import annotations

import os
from typing import Callable, Sequence

from .camera import Intrinsics, Pose
from .interpret.files import read_interpretations
from .interpret.project import (
    Feature3D,
    Interpretation,
    ProjectionParams,
    measure_features,
    project_interpretations,
)
from .interpret.structural import DEFAULT_THRESHOLDS, FitThresholds, Measurement
from .io.photos import Photo, load_photo
from .orient import OrientationResult, orient
from .prior import Prior, prior_for_photo
from .registration.params import RegistrationParams
from .registration.pipeline import Progress, Registration
from .registration.pipeline import register as _register
from .scene import Scene

__all__ = ["register", "project", "measure", "orient"]

PathLike = str | os.PathLike


def register(
    scene: Scene | PathLike,
    photo: Photo | PathLike,
    prior: Prior | PathLike | None = None,
    params: RegistrationParams | None = None,
    on_progress: Callable[[Progress], None] | None = None,
) -> Registration:
    """Register one photo to the scene automatically.

    Parameters
    ----------
    scene : Scene or path
        The model (a mesh file: ``georef.json`` and ``dem.tif`` beside it are
        used, see :meth:`Scene.load`).
    photo : Photo or path
        The photograph (JPEG, PNG, TIFF or HEIC/HEIF).
    prior : Prior or path, optional
        The sensor prior, or the path of a sensor record; default: the
        ``.json`` sensor record beside the photo, completed from its EXIF.
    params : RegistrationParams, optional
        Default: the full automatic pipeline for the scene
        (:meth:`RegistrationParams.for_scene`: ``RegistrationParams()`` on a
        mesh, :meth:`RegistrationParams.for_cloud` on a point cloud).
    on_progress : callable, optional
        Called with a :class:`Progress` after every step.

    Returns
    -------
    Registration
        Its ``status`` is ``"registered"`` only when the pose was verified;
        ``to_dict()`` is the RESULT.json of ``docs/formats.md``.
    """
    if not isinstance(scene, Scene):
        scene = Scene.load(scene)
    if not isinstance(photo, Photo):
        photo = load_photo(photo)
    if not isinstance(prior, Prior):
        prior = prior_for_photo(photo, scene, record_path=prior)
    name = photo.path.name if photo.path is not None else ""
    return _register(scene, photo.image, prior, params, photo_name=name, on_progress=on_progress)


def project(
    scene: Scene | PathLike,
    registration: Registration | tuple[Intrinsics, Pose],
    interpretations: Sequence[Interpretation] | PathLike,
    source: str = "",
    params: ProjectionParams | None = None,
) -> list[Feature3D]:
    """Map the lines and polygons drawn on a registered photo onto the model.

    Parameters
    ----------
    scene : Scene or path
    registration : Registration or (Intrinsics, Pose)
        The photo's registered camera (``cam_from_world``).
    interpretations : sequence of Interpretation, or path
        What was drawn, in photo pixels (a lines GeoJSON, see
        ``docs/formats.md``).
    source : str
        The photo's name, kept in every feature's properties.
    params : ProjectionParams, optional

    Returns
    -------
    list of Feature3D
        Model-frame polylines/patches, split at gaps and occlusions.
    """
    if not isinstance(scene, Scene):
        scene = Scene.load(scene)
    if isinstance(registration, Registration):
        intrinsics, pose = registration.intrinsics, registration.pose
        source = source or registration.photo
    else:
        intrinsics, pose = registration
    if not isinstance(interpretations, (list, tuple)):
        interpretations = read_interpretations(interpretations)
    return project_interpretations(scene, intrinsics, pose, interpretations, source=source,
                                   params=params or ProjectionParams())


def measure(
    features: Sequence[Feature3D], thresholds: FitThresholds = DEFAULT_THRESHOLDS
) -> list[Measurement]:
    """Plunge/trend of traces and dip/dip direction of facets (see :mod:`interpret.structural`)."""
    return measure_features(features, thresholds)


# ``orient`` is re-exported as it is: it already takes tables or file rows.
OrientationResult = OrientationResult
