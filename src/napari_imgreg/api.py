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
>>> result.status, result.grade, result.uncertainty.reprojection_px
>>> lines3d = ir.project(scene, result, "IMG_0001.lines.geojson")
>>> for m in ir.measure(lines3d):
...     print(m.kind, m.dip_deg, m.dip_sigma_deg, m.plunge_deg, m.trend_deg)
>>> again = ir.load_registration("IMG_0001.result.json")          # a RESULT.json read back
"""

from __future__ import annotations

import os
import warnings
from typing import Callable, Sequence

import numpy as np

from .camera import Intrinsics, Pose, check_pose
from .errors import input_error
from .interpret.files import read_features_geojson, read_interpretations
from .interpret.project import (
    Feature3D,
    Interpretation,
    ProjectionParams,
    measure_features,
    project_interpretations,
)
from .interpret.structural import DEFAULT_THRESHOLDS, FitThresholds, Measurement
from .interpret.uncertainty import DEFAULT_UNCERTAINTY, PoseUncertainty, UncertaintyParams
from .io.photos import Photo, load_photo
from .orient import OrientationResult, orient
from .prior import Prior, check_photo_size, load_camera_and_pose, prior_for_photo
from .registration.params import RegistrationParams
from .registration.pipeline import Progress, Registration
from .registration.pipeline import register as _register
from .scene import Scene

__all__ = ["register", "project", "measure", "orient"]

PathLike = str | os.PathLike


def _scene(scene) -> Scene:
    if isinstance(scene, (str, os.PathLike)):
        return Scene.load(scene)
    # By type: asking for ``engine`` would build the ray engine here.
    if not (isinstance(scene, Scene) or getattr(scene, "is_cloud", False)):
        raise TypeError(f"scene must be a Scene or the path of a model, not "
                        f"{type(scene).__name__}")
    return scene


def register(
    scene: Scene | PathLike,
    photo: Photo | np.ndarray | PathLike,
    prior: Prior | Registration | tuple[Intrinsics, Pose] | PathLike | None = None,
    params: RegistrationParams | dict | None = None,
    on_progress: Callable[[Progress], None] | None = None,
) -> Registration:
    """Register one photo to the scene automatically.

    Parameters
    ----------
    scene : Scene or path
        The model (a mesh or point cloud file: ``georef.json`` and
        ``dem.tif`` beside it are used, see :meth:`Scene.load`).
    photo : Photo, (H, W, 3) uint8 array, or path
        The photograph (JPEG, PNG, TIFF or HEIC/HEIF). An array has no EXIF
        and no sensor record beside it: give ``prior``.
    prior : Prior, Registration, (Intrinsics, Pose) or path, optional
        Where to start: the sensor prior; an earlier registration or a camera
        and pose (a start pose with the default sensor sigma); or the path of
        a sensor record or of an earlier RESULT.json of the photo. Default:
        the ``.json`` sensor record beside the photo, completed from its EXIF.
    params : RegistrationParams or dict, optional
        Default: the full automatic pipeline for the scene
        (:meth:`RegistrationParams.for_scene`: ``RegistrationParams()`` on a
        mesh, :meth:`RegistrationParams.for_cloud` on a point cloud). A dict
        is any subset of the parameters file (``docs/formats.md``).
    on_progress : callable, optional
        Called with a :class:`Progress` after every step.

    Returns
    -------
    Registration
        Its ``status`` is ``"registered"`` only when the pose was verified;
        ``uncertainty`` is its expected error; ``to_dict()`` is the
        RESULT.json of ``docs/formats.md``.

    Raises
    ------
    InputError
        A missing or bad file, an image that is not 8-bit RGB, a start pose
        that is not a camera.
    """
    scene = _scene(scene)
    if isinstance(photo, np.ndarray):
        photo = Photo(photo)
    elif isinstance(photo, (str, os.PathLike)):
        photo = load_photo(photo)
    elif not isinstance(photo, Photo):
        raise TypeError(f"photo must be a Photo, an image array or a path, not "
                        f"{type(photo).__name__}")
    if isinstance(params, dict):
        params = RegistrationParams.from_dict(params)
    elif params is not None and not isinstance(params, RegistrationParams):
        raise TypeError(f"params must be RegistrationParams or a dict, not "
                        f"{type(params).__name__}")
    if isinstance(prior, Registration):
        prior = Prior(prior.intrinsics, prior.pose,
                      assumptions=[f"start pose from the registration of {prior.photo}"],
                      sun=prior.prior.sun, sun_source=prior.prior.sun_source)
    elif isinstance(prior, tuple):
        intrinsics, pose = _camera_tuple(prior)
        prior = Prior(intrinsics, pose, assumptions=["start pose given by the script"])
    elif prior is None or isinstance(prior, (str, os.PathLike)):
        if prior is None and photo.path is None:
            raise input_error(None, "a photo given as an array needs a prior (a Prior, a "
                              "camera and pose, or a sensor record path)")
        record = prior
        prior = prior_for_photo(photo, scene, record_path=record)
        check_photo_size(photo, prior, record)  # as the command line: naming the record
    elif not isinstance(prior, Prior):
        raise TypeError(f"prior must be a Prior, Registration, (Intrinsics, Pose) or a path, "
                        f"not {type(prior).__name__}")
    check_pose(prior.pose, "prior pose")
    if photo.size != (prior.intrinsics.width, prior.intrinsics.height):  # a camera given
        raise input_error(photo.path, f"the photo is {photo.size[0]}×{photo.size[1]}; its "
                          f"camera is {prior.intrinsics.width}×{prior.intrinsics.height}")
    name = photo.path.name if photo.path is not None else ""
    return _register(scene, photo.image, prior, params, photo_name=name, on_progress=on_progress)


def _camera_tuple(value) -> tuple[Intrinsics, Pose]:
    if (len(value) != 2 or not isinstance(value[0], Intrinsics)
            or not isinstance(value[1], Pose)):
        raise TypeError("a camera must be given as (Intrinsics, Pose)")
    return value[0], value[1]


def project(
    scene: Scene | PathLike,
    registration: Registration | Prior | tuple[Intrinsics, Pose] | PathLike,
    interpretations: Sequence[Interpretation] | PathLike,
    source: str = "",
    params: ProjectionParams | None = None,
    pose_uncertainty: PoseUncertainty | None = None,
    uncertainty: UncertaintyParams | None = None,
) -> list[Feature3D]:
    """Map the lines and polygons drawn on a registered photo onto the model.

    Parameters
    ----------
    scene : Scene or path
    registration : Registration, Prior, (Intrinsics, Pose), or path
        The photo's camera (``cam_from_world``): a registration (its
        ``uncertainty`` and ``status`` give the pose error of every sigma),
        a sensor prior (its pose, with a sensor-sized error: 50 px, 5 m, 3°),
        a camera and pose (with ``pose_uncertainty``, else a 1 px default), or
        the path of a RESULT.json or sensor record (as ``napari-imgreg
        project`` reads it).
    interpretations : sequence of Interpretation, or path
        What was drawn, in photo pixels (a lines GeoJSON, see
        ``docs/formats.md``).
    source : str
        The photo's name, kept in every feature's ``photo`` property (default:
        the registration's photo).
    params : ProjectionParams, optional
        Sampling step along the drawing (px), grazing-angle limit, and the
        point-cloud gap rule; default ``ProjectionParams()``.
    pose_uncertainty : PoseUncertainty, optional
        Overrides the pose error taken from ``registration``.
    uncertainty : UncertaintyParams, optional
        The drawing's pixel noise and the Monte Carlo draws of the sigmas.

    Returns
    -------
    list of Feature3D
        Model-frame polylines/patches, split at gaps and occlusions; a
        feature that misses the surface has no parts (and a note).
    """
    scene = _scene(scene)
    unc = pose_uncertainty
    if isinstance(registration, Registration):
        intrinsics, pose = registration.intrinsics, registration.pose
        source = source or registration.photo
        unc = unc or PoseUncertainty.from_estimate(registration.uncertainty, registration.status,
                                                   registration.metrics, intrinsics.fx)
    elif isinstance(registration, Prior):
        intrinsics, pose = registration.intrinsics, registration.pose
        unc = unc or PoseUncertainty.from_result({}, intrinsics.fx)  # the sensor prior's
    elif isinstance(registration, (str, os.PathLike)):
        from .io.records import read_json

        intrinsics, pose, _, _ = load_camera_and_pose(
            registration, scene.georef, scene.dem, scene.terrain_height,
            model_bounds=scene.bounds)
        data = read_json(registration)
        source = source or str(data.get("photo") or "")
        unc = unc or PoseUncertainty.from_result(data, intrinsics.fx)
    elif isinstance(registration, tuple):
        intrinsics, pose = _camera_tuple(registration)
    else:
        raise TypeError(f"registration must be a Registration, Prior, (Intrinsics, Pose) or a "
                        f"path, not {type(registration).__name__}")
    check_pose(pose, "pose")
    if isinstance(interpretations, (str, os.PathLike)):
        interpretations = read_interpretations(interpretations)
    else:
        interpretations = list(interpretations)
        if not all(isinstance(i, Interpretation) for i in interpretations):
            raise TypeError("interpretations must be Interpretation objects or the path of a "
                            "lines GeoJSON")
    features = project_interpretations(scene, intrinsics, pose, interpretations, source=source,
                                       params=params or ProjectionParams(), pose_uncertainty=unc,
                                       uncertainty=uncertainty or DEFAULT_UNCERTAINTY)
    if features and not any(f.parts for f in features):
        warnings.warn("no drawn feature reached the model's surface: is the camera in the "
                      "model's frame (the georef.json beside the model)?", stacklevel=2)
    return features


def measure(
    features: Sequence[Feature3D] | PathLike, thresholds: FitThresholds = DEFAULT_THRESHOLDS
) -> list[Measurement]:
    """Plunge/trend of every trace, dip/dip direction where the drawing defines a plane.

    Parameters
    ----------
    features : sequence of Feature3D, or path
        Projected features (:func:`project`), or the path of a projected
        lines GeoJSON (``napari-imgreg project`` output, local frame).
    thresholds : FitThresholds
        When a trace's points define a plane (see ``docs/interpretation.md``).

    Returns
    -------
    list of Measurement
        One per feature, and one combined ``contact:<id>`` row per contact
        traced on several photos. A trace's plane is reported only when it
        is determined: otherwise ``dip_deg`` is None and ``note`` says why
        (most straight traces seen head-on lie in their viewing plane). Every
        number has its ``*_sigma_deg`` from the pose, drawing and model errors.
    """
    if isinstance(features, (str, os.PathLike)):
        features, _ = read_features_geojson(features)
    return measure_features(features, thresholds)


# ``orient`` is re-exported as it is: it already takes tables or file rows.
OrientationResult = OrientationResult
