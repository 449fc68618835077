"""Orient a photogrammetry model from the camera attitudes a phone recorded.

A structure-from-motion model built without ground control sits in an
arbitrary frame. Each photo's camera has, in that frame, an estimated view
direction ξ (camera z) and image long axis ρ (camera x); the phone measured
the same two vectors in the true-north frame (trend, plunge, roll, contract
§2). The rotation ``Q`` (``world_from_model``) that best carries the
estimated vectors onto the measured ones orients the model, and what
remains per photo — Δξ and Δρ — reveals sensor errors and model distortion
(Tavani, Corradetti et al., 2019, "Smartphone: an alternative to ground control
points for orienting virtual outcrop models and assessing their quality",
Geosphere 15(6), 2043, doi:10.1130/GES02167.1).

Three estimators are computed side by side:

``paper``
    The paper's method: J vectors join measured and estimated ξ and ρ; the
    rotation axis is the eigenvector of the smallest eigenvalue of their
    orientation tensor; the angle is found by a residual-sum-of-squares
    search about that axis in 0.1° steps.
``lsq``
    The closed-form least-squares rotation over all ξ and ρ pairs (Wahba's
    problem, solved by SVD in :meth:`scipy.spatial.transform.Rotation.align_vectors`),
    optionally weighted per photo.
``robust``
    Least squares after setting aside photos whose attitude disagrees
    grossly with the rest (a 20° compass error): every photo alone defines a
    rotation; the one with the least median residual seeds an iteratively
    trimmed least-squares fit.

Diagnostics follow the paper: per-photo Δξ and Δρ, their mean absolute
values, and the best-fit slopes and R² of Δξ against the position along the
survey path and against the measured trend, read as quality flags
(mean < 2°, |slope vs path| < 3, |slope vs trend| ≤ 0.1).

The package, in the order the data flows:

* :mod:`~napari_imgreg.orient.estimate` — J vectors, orientation tensor,
  rotation axis and angle, the three estimators (:class:`RotationEstimate`).
* :mod:`~napari_imgreg.orient.diagnostics` — residual angles, survey path
  position, trend unwrapping, line fits, the paper's quality flags and
  thresholds (units and sign conventions are defined there).
* :mod:`~napari_imgreg.orient.result` — :func:`orient`, :func:`orient_files`,
  :class:`OrientationResult` and ORIENTATION.json (:func:`save_orientation`).
* :mod:`~napari_imgreg.orient.apply` — rotate points, cameras and mesh or
  point cloud files.
* :mod:`~napari_imgreg.orient.plots` — the Δξ/Δρ residual plots (matplotlib).
* :mod:`~napari_imgreg.orient.declination` — the survey's magnetic
  declination (World Magnetic Model) for ``declination_deg="auto"``.

A generated survey with a known answer is in :mod:`napari_imgreg.sample.survey`
(``SimulatedSurvey``, ``simulate_survey``; importing them from here still
works, with a DeprecationWarning).
"""

from __future__ import annotations

import inspect
import sys
import types

from .._deprecated import forward_moved_names
from .apply import (
    MESH_OUT_SUFFIXES,
    apply_to_mesh_file,
    rotate_cameras,
    rotate_points,
)
from .diagnostics import (
    DISTORTED_RESIDUAL_DEG,
    MEAN_RESIDUAL_MAX_DEG,
    MIN_SLOPE_PHOTOS,
    NARROW_TREND_SPAN_DEG,
    PATH_SLOPE_MAX,
    STEEP_VIEW_PLUNGE_DEG,
    TREND_SLOPE_MAX,
    LinearFit,
    QualityFlag,
    fit_line,
    quality_flags,
    residual_angles,
    survey_path_position,
    unwrap_trend,
)
from .estimate import (
    METHODS,
    PAPER_STEP_DEG,
    RotationEstimate,
    angle_by_rss_search,
    estimate_rotation_lsq,
    estimate_rotation_paper,
    estimate_rotation_robust,
    j_vectors,
    lower_hemisphere_axis,
    orientation_tensor,
    rotation_axis_from_j,
    rotation_error_deg,
)
from .declination import SurveyDeclination, default_georef_path, survey_date, survey_declination
from .plots import draw_residual_plots, save_residual_plots
from .result import OrientationResult, orient, orient_files, save_orientation

__all__ = [
    "METHODS",
    "PAPER_STEP_DEG",
    "MEAN_RESIDUAL_MAX_DEG",
    "DISTORTED_RESIDUAL_DEG",
    "PATH_SLOPE_MAX",
    "TREND_SLOPE_MAX",
    "MIN_SLOPE_PHOTOS",
    "NARROW_TREND_SPAN_DEG",
    "STEEP_VIEW_PLUNGE_DEG",
    "RotationEstimate",
    "LinearFit",
    "QualityFlag",
    "OrientationResult",
    "j_vectors",
    "orientation_tensor",
    "rotation_axis_from_j",
    "angle_by_rss_search",
    "estimate_rotation_paper",
    "estimate_rotation_lsq",
    "estimate_rotation_robust",
    "residual_angles",
    "survey_path_position",
    "unwrap_trend",
    "fit_line",
    "quality_flags",
    "orient",
    "orient_files",
    "rotate_points",
    "rotate_cameras",
    "apply_to_mesh_file",
    "MESH_OUT_SUFFIXES",
    "draw_residual_plots",
    "save_residual_plots",
    "save_orientation",
    "rotation_error_deg",
    "lower_hemisphere_axis",
    "SurveyDeclination",
    "survey_date",
    "survey_declination",
    "default_georef_path",
]

#: Names that left ``orient`` in 0.2 -> their new module. Looked up by name
#: (a string, not an import): orient and sample are sibling layers.
_MOVED = {
    "SimulatedSurvey": "napari_imgreg.sample.survey",
    "simulate_survey": "napari_imgreg.sample.survey",
}
__getattr__ = forward_moved_names(__name__, _MOVED)




def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_MOVED))


class _OrientPackage(types.ModuleType):
    """This package, callable as :func:`orient`.

    ``napari_imgreg.orient`` is a package *and* the top-level function a
    script calls (``napari_imgreg.orient(estimated, measured)``). Python binds
    a subpackage over a same-named attribute of its parent once it is
    imported, so the package itself forwards a call to the function: both
    spellings then work whatever was imported first.
    """

    def __call__(self, *args, **kwargs) -> OrientationResult:
        return orient(*args, **kwargs)


# help(napari_imgreg.orient) and a notebook's ``?`` show the function's parameters.
_signature = inspect.signature(orient)
_OrientPackage.__call__.__signature__ = _signature.replace(parameters=[
    inspect.Parameter("self", inspect.Parameter.POSITIONAL_ONLY),
    *_signature.parameters.values()])
__doc__ = __doc__ + "\n\nCalled as a function, this package is :func:`orient`:\n\n" + (
    inspect.cleandoc(orient.__doc__ or ""))
sys.modules[__name__].__class__ = _OrientPackage
