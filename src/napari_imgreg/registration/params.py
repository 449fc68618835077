"""All registration parameters in one object.

The GUI, the command line's ``--params`` file and the automatic adaptation
all edit the same :class:`RegistrationParams`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, fields, replace
from typing import ClassVar

from ..errors import input_error
from ..io.records import read_json
from .features import FeatureParams
from .filters import FilterParams
from .lidar_views import LidarViewParams
from .pose import PoseParams
from .stages.area import AreaParams
from .stages.dense import DenseParams
from .stages.edges import EdgeParams
from .uncertainty import UncertaintyParams
from ..validate import FieldValueError, check_ranges

__all__ = ["RegistrationParams", "load_params"]


def _registration_features() -> FeatureParams:
    """The registration's feature settings: SIFT, upright RootSIFT descriptors,
    and the illumination-invariant channel for matching from a distant start.

    Why (registration benchmark, changed-light photos, see
    ``docs/benchmarks.md``): relief shading under another sun turns the
    estimated keypoint orientations and changes the luminance pattern;
    upright descriptors doubled the correct matches, the invariant channel
    tripled them from the prior's render. (Guided matching, which compares
    descriptors only near the same place, found more matches but let in
    many wrong neighbours: first-trial successes fell from 15 to 9 of 16, so
    it stays off.)
    """
    return FeatureParams(upright=True, root_sift=True, invariant_channel=True)


def _registration_dense() -> DenseParams:
    """The registration's MI settings: the refinement's own, stopped after 6 s.

    MI refinement is one stage among several, and keypoints are matched
    again from its pose: 6 s of it is what the registration can spend (the
    refinement's own limit, 10 s, suits a direct call).
    """
    return DenseParams(max_seconds=6.0)


def _registration_filters() -> FilterParams:
    """The filters a registration applies to each image by default: Wallis.

    It pulls the photo's and the render's local contrast together, and near
    the right pose it doubled the correct matches on changed-light photos
    (first-trial successes 18 → 22 of 24 in the registration benchmark) at
    no cost on same-light ones. The one place these defaults are made: a new
    session's parameters and the workbench's Reset
    (:meth:`RegistrationParams.default_filters`) both come from here.
    """
    return FilterParams(wallis=True)


@dataclass
class RegistrationParams:
    """Parameters of one registration trial and of the search around it.

    Attributes
    ----------
    photo_filters, render_filters : FilterParams
        Filters for the photo and for the render, separately.
    features : FeatureParams
    pose : PoseParams
    match_width : int
        Photo and render are matched at this width (pixels, 64–16384; the
        photo's own when smaller). Poses are always solved at full resolution.
    max_iterations : int
        Render → match → pose rounds per trial (1–50): each round re-renders
        from the last estimate, which matches the photo far better than the
        prior.
    converged_deg, converged_m : float
        A trial stops iterating when the pose moves less than this (0–10°,
        0–100 m).
    auto_adapt : bool
        After a trial, apply the adaptation of the first rule that fires and
        run another trial.
    max_trials : int
        Trials at most (including the first), 1–50.
    search_prior : bool
        When no trial registers, try perturbed priors within the sensor
        record's ``sigma`` at reduced resolution.
    n_search : int
        Perturbed priors to try, 0–1000.
    verify : bool
        Call a pose registered only when verified (converged, and the photo
        and the final render agree). Off, a pose with 7 or more 3D inliers is
        taken as registered, as a plain SIFT + EPnP pipeline does (the
        benchmark's baseline).
    sun_relight : bool
        When the photo's sun is known (capture time, sensor record) and the
        model's texture sun too (``survey.json``) or the model is untextured,
        match against renders relit for the photo's sun with cast shadows.
    edge_align : bool
        When keypoints do not verify, align the model's structure edges
        (skyline, occluding contours, creases, strata contacts) to the
        photo's edges, then match keypoints again from there.
    dense_refine : bool
        When keypoints do not verify, refine the best pose by maximising the
        mutual information of photo and render, then match again.
    area_match : bool
        When keypoints do not verify, match blocks of the (sun-lit) render in
        the photo by correlation (area-based matching) from the best pose so
        far and from each stage's pose: what registers a bare mesh's shading
        to a photo of coloured rock. A textured model under a known sun has
        both its relit render and its texture as it is matched, and the one
        whose pose fits its blocks better kept. Also refines a verified keypoint pose
        whose error estimate is 0.5 px or more (at 1632 px width) by one
        area-matching trial from it, kept when its estimate is smaller.
    area : AreaParams
        Settings of the area-based matching.
    edges : EdgeParams
        Settings of the edge alignment (the start's position uncertainty and
        search range come from the prior's ``sigma``).
    dense : DenseParams
        Settings of the MI refinement (here stopped after 6 s, not 10 s).
    uncertainty : UncertaintyParams
        Settings of the pose's independent error estimate (split-half
        cross-validation), which a verified pose must keep small.
    lidar_views : bool
        On a point-cloud scene, add the matches of seed 003's reflectivity
        and wireframe view pairs (:mod:`~napari_imgreg.registration.lidar_views`)
        to each keypoint round. Default False: on the benchmark's generated
        scans they added 2–3 matches per round, none correct, for 4–5 s.
    lidar : LidarViewParams
        Settings of those views.
    seed : int
        Seed of every random draw of a registration (OpenCV's RNG for FLANN,
        USAC and RANSAC at the start of each round, the perturbed priors, the
        error estimate's simulated matches), [0, 2³¹ − 1]: the same photo,
        model and parameters give the same result whatever ran before.
        Default 0.
    """

    # Wallis on both images by default (_registration_filters says why).
    photo_filters: FilterParams = field(default_factory=_registration_filters)
    render_filters: FilterParams = field(default_factory=_registration_filters)
    features: FeatureParams = field(default_factory=lambda: _registration_features())
    pose: PoseParams = field(default_factory=PoseParams)
    # 768 px: as many correct matches across light as 1024 px (the micro-relief
    # shading that defeats matching is finer than a pixel there) in half the
    # time; poses are still solved at full resolution.
    match_width: int = 768
    max_iterations: int = 4
    converged_deg: float = 0.05
    converged_m: float = 0.05
    auto_adapt: bool = True
    max_trials: int = 4
    search_prior: bool = True
    n_search: int = 12
    verify: bool = True
    # Illumination-robust stages (used when keypoints on the plain render do
    # not verify; an untextured model is lit by the photo's sun from the start).
    sun_relight: bool = True
    edge_align: bool = True
    dense_refine: bool = True
    area_match: bool = True
    area: AreaParams = field(default_factory=AreaParams)
    edges: EdgeParams = field(default_factory=EdgeParams)
    dense: DenseParams = field(default_factory=_registration_dense)
    uncertainty: UncertaintyParams = field(default_factory=UncertaintyParams)
    lidar_views: bool = False
    lidar: LidarViewParams = field(default_factory=LidarViewParams)
    seed: int = 0

    #: Inclusive valid range of each numeric field, used alike by ``--params``
    #: files, the GUI and code (:func:`~napari_imgreg.validate.param_range`);
    #: each nested stage dataclass declares its own. Zero trials, rounds or
    #: widths would register nothing (or divide by zero).
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "match_width": (64, 16384),
        "max_iterations": (1, 50),
        "converged_deg": (0.0, 10.0),
        "converged_m": (0.0, 100.0),
        "max_trials": (1, 50),
        "n_search": (0, 1000),
        "seed": (0, 2**31 - 1),
    }

    def __post_init__(self) -> None:
        check_ranges(self)

    @classmethod
    def baseline(cls) -> RegistrationParams:
        """The plain pipeline the benchmark compares against: SIFT, ratio test,
        EPnP, no filters, no re-rendering, no adaptation, no search, no
        verification."""
        return cls(
            photo_filters=FilterParams(),
            render_filters=FilterParams(),
            features=FeatureParams("SIFT", "SIFT", symmetric=False, geometric_model="none"),
            match_width=1024,
            max_iterations=1,
            auto_adapt=False,
            max_trials=1,
            search_prior=False,
            verify=False,
            sun_relight=False,
            edge_align=False,
            dense_refine=False,
            area_match=False,
        )

    @classmethod
    def baseline_cloud(cls) -> RegistrationParams:
        """The plain baseline on a lidar scan (issue 16): :meth:`baseline` on
        the gradient magnitude of the photo and of the intensity render
        (seed 003's reflectivity view against the photo's gradient; SIFT,
        ratio test, EPnP, one round)."""
        params = cls.baseline()
        params.photo_filters = FilterParams(gradient=True)
        params.render_filters = FilterParams(gradient=True)
        return params

    @classmethod
    def for_cloud(cls) -> RegistrationParams:
        """The automatic pipeline's settings for a lidar scan's intensity renders.

        The default pipeline (:class:`RegistrationParams`) with keypoints
        matched on the gradient magnitude of both images (then Wallis, as by
        default) instead of their grey levels: a scan's intensity is the
        rock's reflectance at the laser's wavelength (sandstone bright,
        mudstone dark, under no sun), a photo's luminance is the visible
        albedo under the day's light, and what they share is where either
        changes — bed contacts, stains, the skyline, ledges — not the grey
        levels themselves. The illumination-invariant channel is off: a grey
        render has no chromaticity.

        One keypoint trial, no adapted trials and no search of the prior's
        uncertainty (which are keypoint trials too): in the cloud benchmark
        (``benchmarks/bench_register_cloud.py``, ``docs/benchmarks.md``)
        SIFT found at most one correct match per photo even when rendered
        from the *true* camera, on grey levels or gradients alike, so those
        trials only cost time (≈ 30 s of 80 s per photo); the pipeline goes
        on to the stages that register these renders (area matching, edges,
        mutual information).

        Area matching runs at the photo's full width up to 1632 px (the
        default's 1024): the splat render's relit intensity correlates with
        the photo at only r ≈ 0.5, and finer blocks average more of it. On
        the cloud benchmark's 16 photos (``benchmarks/bench_register_cloud.py``,
        both light tiers, from the sensor priors) the median check-point
        error went from 1.71 to 1.07 px, all 16 registered either way.

        The command line, batches and the workbench use these settings for
        a point cloud unless given others (:meth:`for_scene`).
        """
        params = cls()
        params.photo_filters = replace(_registration_filters(), gradient=True)
        params.render_filters = replace(_registration_filters(), gradient=True)
        params.features = replace(params.features, invariant_channel=False)
        params.max_trials = 1
        params.search_prior = False
        params.area = replace(params.area, width=1632)
        return params

    @classmethod
    def for_scene(cls, scene: object | None) -> RegistrationParams:
        """The default settings for a scene: :meth:`for_cloud` for a point
        cloud (a scene with a true ``is_cloud``), else the defaults."""
        return cls.for_cloud() if bool(getattr(scene, "is_cloud", False)) else cls()

    @classmethod
    def default_filters(cls, which: str, scene: object | None = None) -> FilterParams:
        """A fresh copy of the filters a new session starts with on ``scene``
        for one image: what the workbench's Reset returns to.

        Parameters
        ----------
        which : {"photo", "render"}
        scene : Scene, optional
            A point cloud's defaults differ (:meth:`for_scene`).
        """
        if which not in ("photo", "render"):
            raise ValueError(f"which must be 'photo' or 'render', got {which!r}")
        own = cls.for_scene(scene)
        return replace(own.photo_filters if which == "photo" else own.render_filters)

    def is_scene_default(self) -> bool:
        """True when these are one of the untouched per-scene defaults
        (:meth:`for_scene` of a mesh or of a cloud)."""
        return self in (type(self)(), type(self).for_cloud())

    def copy(self) -> RegistrationParams:
        return replace(
            self,
            photo_filters=replace(self.photo_filters),
            render_filters=replace(self.render_filters),
            features=replace(self.features),
            pose=replace(self.pose),
            area=replace(self.area),
            edges=replace(self.edges),
            dense=replace(self.dense),
            uncertainty=replace(self.uncertainty),
            lidar=replace(self.lidar),
        )

    def to_dict(self) -> dict:
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            out[f.name] = value.to_dict() if hasattr(value, "to_dict") else value
        return out

    @classmethod
    def from_dict(cls, d: dict, source: str | os.PathLike | None = None,
                  base: RegistrationParams | None = None) -> RegistrationParams:
        """Parameters from a (partial) dict; missing fields keep their defaults
        (those of ``base`` when given, e.g. :meth:`for_scene`).

        Raises
        ------
        InputError
            Unknown or ill-typed fields, or values outside their declared
            range (``RANGES`` of each dataclass: ``max_trials`` 0 is refused),
            naming ``source`` and the field.
        """
        nested = {
            "photo_filters": FilterParams,
            "render_filters": FilterParams,
            "features": FeatureParams,
            "pose": PoseParams,
            "area": AreaParams,
            "edges": EdgeParams,
            "dense": DenseParams,
            "uncertainty": UncertaintyParams,
            "lidar": LidarViewParams,
        }
        names = {f.name for f in fields(cls)}
        defaults = base.copy() if base is not None else cls()
        kwargs = {f.name: getattr(defaults, f.name) for f in fields(cls)} if base is not None else {}
        for key, value in d.items():
            if key not in names:
                raise input_error(source, f"unknown parameter '{key}'")
            if key in nested:
                if not isinstance(value, dict):
                    raise input_error(source, f"field '{key}' must be an object")
                # Missing nested fields keep the registration's defaults
                # (which differ from the stage's own for the features and MI).
                within = getattr(defaults, key).to_dict()
                try:
                    kwargs[key] = nested[key].from_dict({**within, **value})
                except FieldValueError as exc:
                    raise input_error(source, exc.within(key)) from None
                except (KeyError, TypeError, ValueError) as exc:
                    raise input_error(source, f"field '{key}': {exc}") from None
            else:
                kwargs[key] = value
        try:
            params = cls(**kwargs)
        except (TypeError, ValueError) as exc:  # FieldValueError: "field 'max_trials' ..."
            raise input_error(source, str(exc)) from None
        _check_types(params, source)
        return params


def _check_types(obj, source, section: str = "") -> None:
    """InputError when a field's value does not have its default's type."""
    defaults = type(obj)()
    for f in fields(obj):
        value, default = getattr(obj, f.name), getattr(defaults, f.name)
        name = f"{section}{f.name}"
        if hasattr(default, "to_dict"):
            _check_types(value, source, f"{name}.")
        elif isinstance(default, bool):
            if not isinstance(value, bool):
                raise input_error(source, f"field '{name}' must be true or false, got {value!r}")
        elif isinstance(default, int):
            if isinstance(value, bool) or not isinstance(value, int):
                raise input_error(source, f"field '{name}' must be an integer, got {value!r}")
        elif isinstance(default, float):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise input_error(source, f"field '{name}' must be a number, got {value!r}")
        elif isinstance(default, str):
            if not isinstance(value, str):
                raise input_error(source, f"field '{name}' must be a string, got {value!r}")
        elif isinstance(default, tuple):
            _check_tuple(value, default, f, name, source)


def _check_tuple(value, default: tuple, f, name: str, source) -> None:
    """InputError unless ``value`` is a tuple like ``default``: as long (unless
    the field is annotated ``tuple[..., ...]``), of numbers when the default
    holds floats, else of positive integers."""
    any_length = "..." in str(f.type)
    numbers = any(isinstance(v, float) for v in default)
    size = "" if any_length else f"{len(default)} "
    what = f"{size}numbers" if numbers else f"{size}positive integers"
    if not isinstance(value, tuple) or (not any_length and len(value) != len(default)) or not all(
        not isinstance(v, bool) and (isinstance(v, (int, float)) if numbers
                                     else isinstance(v, int) and v > 0)
        for v in value
    ):
        shown = list(value) if isinstance(value, (tuple, list)) else value
        raise input_error(source, f"field '{name}' must be {what}, got {shown!r}")


def load_params(path: str | os.PathLike,
                base: RegistrationParams | None = None) -> RegistrationParams:
    """Read a ``--params`` JSON file (any subset of the fields; the others
    from ``base``, by default :class:`RegistrationParams`' defaults)."""
    data = read_json(path)
    if not isinstance(data, dict):
        raise input_error(path, "parameters must be a JSON object")
    return RegistrationParams.from_dict(data, path, base=base)
