"""The workbench's state, without Qt or napari: a :class:`Workspace`.

A workspace holds what a registration session works on — the scene (with its
DEM and georeference), the photos with their priors, poses and pose
histories, the trials of every registration and the one selected, the
registration parameters, the control-point pairs of manual registration and
its solution, the sun of each photo, and the interpretations drawn on the
photos with their projections onto the model. Every method that changes it
emits a `psygnal <https://psygnal.readthedocs.io>`_ event (``pose_changed``,
``trials_changed``, ...), so views can follow it; the napari workbench
(:mod:`napari_imgreg.widgets.workbench`) is one such view, a script or a test
another.

Long computations stay out of the model. For each (a registration, a
reference render, manual solving and scoring, reading the sun from a photo,
projecting interpretations) the workspace hands out a :class:`Job`: a
function, or a generator function yielding
:class:`~napari_imgreg.registration.pipeline.Progress`, that any thread may
run, and the ``apply`` that records its result (call it where the workspace
lives, e.g. in the GUI thread). Each ``*_job`` method has a blocking
counterpart that runs the job at once (:meth:`Workspace.register`,
:meth:`Workspace.solve_manual`, ...).

The state is plain dataclasses with ``to_dict`` (what a saved workspace will
hold); saving and reopening are not here yet.

Examples
--------
>>> from napari_imgreg.sample import sample_scene            # doctest: +SKIP
>>> ws = Workspace()                                          # doctest: +SKIP
>>> folder = sample_scene("small")                            # doctest: +SKIP
>>> ws.open_scene(folder / "outcrop.obj", dem=folder / "dem.tif")  # doctest: +SKIP
>>> ws.add_photos(sorted(folder.glob("IMG_*.jpg")))           # doctest: +SKIP
>>> ws.pose_changed.connect(print)                            # doctest: +SKIP
>>> ws.nudge("turn right 1", d_trend=1.0)                     # doctest: +SKIP
turn right 1
>>> reg = ws.register(auto=True)                              # doctest: +SKIP
"""

from __future__ import annotations

import inspect
import math
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
from psygnal import Signal

from napari_imgreg import adjust
from napari_imgreg.camera import Intrinsics, Pose, match_scale
from napari_imgreg.errors import InputError
from napari_imgreg.geo import DEM, Georef
from napari_imgreg.interpret.project import (
    Feature3D,
    Interpretation,
    merge_interpretations,
    project_interpretations,
)
from napari_imgreg.interpret.structural import Measurement
from napari_imgreg.io.photos import Photo, load_photo
from napari_imgreg.prior import Prior, prior_for_photo, save_pose_to_record
from napari_imgreg.registration import manual, pipeline
from napari_imgreg.registration.features import FeatureParams
from napari_imgreg.registration.params import RegistrationParams
from napari_imgreg.registration.pipeline import Registration, Trial
from napari_imgreg.registration.quality import RuleHit, evaluate_rules
from napari_imgreg.registration.stages.relight import SunEstimate, estimate_sun_from_photo
from napari_imgreg.render import RenderResult, render
from napari_imgreg.scene import Scene
from napari_imgreg.solar import meridian_convergence_deg, sun_vector_enu

__all__ = [
    "Workspace",
    "PhotoState",
    "TrialRecord",
    "Job",
    "WorkbenchError",
    "one_line",
    "read_scene",
    "read_photos",
    "project_interpretation_sets",
    "SUN_ESTIMATE_WIDTH",
    "RUN_SETTINGS",
]

#: Width (pixels) at which the sun is read from a photo (its shading is broad).
SUN_ESTIMATE_WIDTH = 1024
#: Parameters that Run and Auto decide, kept when a trial's parameters are restored.
RUN_SETTINGS = ("auto_adapt", "max_trials", "search_prior", "n_search", "verify")
#: Height of the camera above the terrain when it is unknown (outside the DEM), metres.
_DEFAULT_HEIGHT_M = 1.6


class WorkbenchError(Exception):
    """An error already worded for the user (one line)."""


def one_line(exc: BaseException) -> str:
    """The first line of an error's message, naming its type unless it is bad input."""
    text = str(exc).strip()
    first = text.splitlines()[0] if text else ""
    if isinstance(exc, (InputError, WorkbenchError)):
        return first or type(exc).__name__
    return f"{type(exc).__name__}: {first}" if first else type(exc).__name__


def _moved(old: str, new: str) -> None:
    warnings.warn(f"PhotoState.{old} (napari (row, col)) is deprecated since napari-imgreg 0.2: "
                  f"use PhotoState.{new}, pixel (x, y)", DeprecationWarning, stacklevel=3)


# ------------------------------------------------------------------ state
@dataclass(eq=False)
class TrialRecord:
    """A trial in the photo's history: from which run, by which action.

    Attributes
    ----------
    trial : Trial
    run : int
        The photo's run that made it (1, 2, ...; manual trials carry the
        number of the last automatic run).
    kind : {"Run", "Auto", "Manual"}
    """

    trial: Trial
    run: int
    kind: str

    @property
    def label(self) -> str:
        t = self.trial
        if self.kind == "Manual":
            return "manual pairs"
        light = ", sun-lit render" if self.sunlit and t.origin != "sun-lit render" else ""
        area = getattr(t, "matcher", "keypoints") == "area"
        what = "blocks by correlation" if area else t.params.features.name
        return f"{self.kind} {self.run}: {what} ({t.origin}{light})"

    @property
    def sunlit(self) -> bool:
        """Matched against a render relit for the photo's sun."""
        return getattr(self.trial, "render_mode", "plain") == "sunlit"

    def to_dict(self) -> dict:
        return {"run": self.run, "kind": self.kind, "trial": self.trial.to_dict()}


@dataclass(eq=False)
class PhotoState:
    """One photo of the workspace and everything done to it.

    Attributes
    ----------
    photo : Photo
    prior : Prior
        From its sensor record and metadata.
    record_path : Path
        The sidecar JSON the pose is saved to.
    intrinsics : Intrinsics
        The camera used now (the prior's, or with a solved focal length).
    history : PoseHistory
        The current pose and its undo/redo.
    trials : list of TrialRecord
    registration : Registration or None
        The last automatic registration.
    manual_solution : ManualSolution or None
        The last manual solve.
    reference : RenderResult or None
        The reference render of the manual registration.
    reference_source : {"", "pose", "view"}
        Rendered from the pose at the time, or from a 3D view.
    photo_points_px : (N, 2) float array
        Control points picked on the photo, pixel (x, y).
    reference_points_px : (M, 2) float array
        Control points picked on the reference render, its pixel (x, y).
        Point k of each list make pair k; the longer list has at most one
        point waiting for its partner.
    selected_trial : int or None
        Index into ``trials`` of the trial shown.
    runs : int
        Automatic registrations run so far.
    sun_override : (3,) float array or None
        The photo's sun set by hand or read from the photo (unit vector
        toward it, local frame); None: the prior's.
    sun_override_source : str
    sun_estimate : SunEstimate or None
        The last sun read from the photo.
    interpretations : list of Interpretation
        Features drawn on the photo, pixels.
    """

    photo: Photo
    prior: Prior
    record_path: Path
    intrinsics: Intrinsics
    history: adjust.PoseHistory
    trials: list[TrialRecord] = field(default_factory=list)
    registration: Registration | None = None
    manual_solution: manual.ManualSolution | None = None
    reference: RenderResult | None = None
    reference_source: str = ""
    photo_points_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    reference_points_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    selected_trial: int | None = None
    runs: int = 0
    sun_override: np.ndarray | None = None
    sun_override_source: str = ""
    sun_estimate: SunEstimate | None = None
    interpretations: list[Interpretation] = field(default_factory=list)
    _convergence: float | None = None

    @property
    def sun(self) -> np.ndarray | None:
        """Toward the sun at capture, local frame: set by hand or read from the
        photo (``sun_override``), else the prior's (None: unknown)."""
        return self.sun_override if self.sun_override is not None else self.prior.sun

    @property
    def sun_source(self) -> str:
        return self.sun_override_source if self.sun_override is not None else self.prior.sun_source

    @property
    def name(self) -> str:
        return self.photo.path.name if self.photo.path is not None else "photo"

    @property
    def pose(self) -> Pose:
        return self.history.current

    @property
    def size(self) -> tuple[int, int]:
        return self.intrinsics.width, self.intrinsics.height

    # The picks as napari layer data, (row, col): what 0.1 kept here.
    @property
    def pairs_photo(self) -> np.ndarray:
        """Deprecated: :attr:`photo_points_px` as napari's (row, col)."""
        _moved("pairs_photo", "photo_points_px")
        return np.asarray(self.photo_points_px)[..., ::-1]

    @pairs_photo.setter
    def pairs_photo(self, rowcol: np.ndarray) -> None:
        _moved("pairs_photo", "photo_points_px")
        self.photo_points_px = np.asarray(rowcol, float).reshape(-1, 2)[..., ::-1]

    @property
    def pairs_reference(self) -> np.ndarray:
        """Deprecated: :attr:`reference_points_px` as napari's (row, col)."""
        _moved("pairs_reference", "reference_points_px")
        return np.asarray(self.reference_points_px)[..., ::-1]

    @pairs_reference.setter
    def pairs_reference(self, rowcol: np.ndarray) -> None:
        _moved("pairs_reference", "reference_points_px")
        self.reference_points_px = np.asarray(rowcol, float).reshape(-1, 2)[..., ::-1]

    def to_dict(self) -> dict:
        """What a saved workspace keeps of the photo (images and renders are
        not kept: they are read or rendered again)."""
        return {
            "photo": str(self.photo.path),
            "record": str(self.record_path),
            "camera": self.intrinsics.to_dict(),
            "pose": self.pose.to_dict(),
            "pose_label": self.history.label,
            "runs": self.runs,
            "trials": [rec.to_dict() for rec in self.trials],
            "selected_trial": self.selected_trial,
            "pairs": {"photo_px": np.asarray(self.photo_points_px).tolist(),
                      "reference_px": np.asarray(self.reference_points_px).tolist(),
                      "reference_source": self.reference_source,
                      "reference_pose": (None if self.reference is None
                                         else self.reference.cam_from_world.to_dict())},
            "sun": None if self.sun_override is None else {
                "direction": np.asarray(self.sun_override, float).tolist(),
                "source": self.sun_override_source},
            "interpretations": [
                {"geometry": item.geometry, "pixels": np.asarray(item.pixels).tolist(),
                 "properties": dict(item.properties)} for item in self.interpretations],
        }


@dataclass
class Job:
    """A long computation of the workspace, to run in a worker.

    Attributes
    ----------
    name : str
        What it does ("registration", "manual", "reference", "sun", "projection").
    run : callable
        Takes no argument; a function returning the result, or a generator
        function that yields :class:`~napari_imgreg.registration.pipeline.Progress`
        and returns it. It reads only what was captured when the job was made.
    apply : callable
        ``apply(result)`` records the result in the workspace (emitting its
        events) and returns what the blocking method returns. Call it where
        the workspace lives.
    description : str
        For a progress bar ("Registering IMG_0001.jpg").
    photo : PhotoState or None
        The photo it works on.
    """

    name: str
    run: Callable[[], Any]
    apply: Callable[[Any], Any]
    description: str = ""
    photo: PhotoState | None = None

    @property
    def yields_progress(self) -> bool:
        return inspect.isgeneratorfunction(self.run)

    def __call__(self, on_progress: Callable | None = None) -> Any:
        """Run and apply at once (blocking)."""
        result = (pipeline.run_to_end(self.run(), on_progress) if self.yields_progress
                  else self.run())
        return self.apply(result)


# ------------------------------------------------------- pure functions
def read_scene(mesh: str | Path, dem: str | Path | None = None,
               georef: str | Path | None = None) -> tuple[Scene, adjust.TerrainMap]:
    """Load a model with its engine built, and its terrain map.

    Parameters
    ----------
    mesh : path-like
        A textured mesh (OBJ, PLY, GLB) or a DSM (GeoTIFF or ``.asc``).
    dem : path-like, optional
        A DEM for camera altitudes.
    georef : path-like, optional
        ``georef.json`` (else the one beside the mesh, if any).

    Returns
    -------
    scene : Scene
    terrain : TerrainMap
        The DEM (or the model's top surface) for the repositioning map.
    """
    path = Path(mesh)
    if path.suffix.lower() in (".tif", ".tiff", ".asc"):
        scene = Scene.from_dem(path, georef=Georef.load(georef) if georef else None)
        if dem:
            scene.dem = DEM.load(dem)
    else:
        scene = Scene.load(path, georef=georef or None, dem=dem or None)
    scene.build_engine()
    return scene, adjust.terrain_map(scene)


def read_photos(paths, scene: Scene) -> tuple[list[tuple[Photo, Prior]], list[str]]:
    """Load photos and their priors (sensor record, else EXIF/XMP).

    One bad photo does not stop the others: its error is returned in words.

    Returns
    -------
    loaded : list of (Photo, Prior)
    errors : list of str
        One line per photo that could not be read.
    """
    loaded, errors = [], []
    for p in paths:
        try:
            photo = load_photo(Path(p))
            prior = prior_for_photo(photo, scene)
        except Exception as exc:  # one bad photo does not stop the others
            errors.append(one_line(exc))
            continue
        loaded.append((photo, prior))
    return loaded, errors


def project_interpretation_sets(
    scene: Scene, jobs: list[tuple[Intrinsics, Pose, list[Interpretation], str]]
) -> tuple[list[Feature3D], list[Measurement]]:
    """Project each photo's interpretations onto the scene; one merged set.

    Parameters
    ----------
    scene : Scene
    jobs : list of (Intrinsics, Pose, list of Interpretation, str)
        Per photo: its camera, its pose, what was drawn on it, its name.

    Returns
    -------
    features : list of Feature3D
    measurements : list of Measurement
        Of the features that reached the surface.
    """
    sets = [project_interpretations(scene, intr, pose, items, source=source)
            for intr, pose, items, source in jobs]
    features = merge_interpretations(*sets)
    measurements = [f.measure() for f in features if f.n_points or (
        f.patch_points is not None and len(f.patch_points))]
    return features, measurements


def _unit(direction) -> np.ndarray:
    d = np.asarray(direction, float).reshape(3)
    return d / np.linalg.norm(d)


# -------------------------------------------------------------- workspace
class Workspace:
    """The evented state of a registration session (see the module docstring).

    Parameters
    ----------
    params : RegistrationParams, optional
        The parameters of the next registration (defaults).

    Attributes
    ----------
    scene : Scene or None
    terrain : TerrainMap or None
        The scene's DEM (or top surface) as a map.
    scene_files : dict
        ``{"mesh", "dem", "georef"}`` paths the scene was read from.
    photos : list of PhotoState
    current : PhotoState or None
        The photo being worked on: the pose, trial, pair and sun methods
        act on it.
    params : RegistrationParams
        Edited in place by the GUI; :meth:`set_params` replaces them.
    features_3d : list of Feature3D
        The last projection of the interpretations.
    measurements : list of Measurement
        Their measurements.
    """

    #: A scene was loaded (the photos were cleared).
    scene_changed = Signal()
    #: Photos were added or removed.
    photos_changed = Signal()
    #: Another photo became current.
    photo_changed = Signal()
    #: The current photo's pose changed; the argument says what changed it
    #: ("nudge ...", "undo", "registration", "manual", "restore", ...).
    pose_changed = Signal(str)
    #: The registration parameters were replaced or adapted.
    params_changed = Signal()
    #: A photo's trials changed.
    trials_changed = Signal()
    #: A trial of the current photo was selected (its index).
    trial_selected = Signal(int)
    #: The current photo's reference render changed.
    reference_changed = Signal()
    #: The current photo's control points changed.
    pairs_changed = Signal()
    #: A photo's sun changed (the photo).
    sun_changed = Signal(object)
    #: A photo's interpretations changed (the photo).
    interpretations_changed = Signal(object)
    #: The interpretations were projected (``features_3d``, ``measurements``).
    projection_changed = Signal()

    def __init__(self, params: RegistrationParams | None = None) -> None:
        self.scene: Scene | None = None
        self.terrain: adjust.TerrainMap | None = None
        self.scene_files: dict[str, str] = {}
        self.photos: list[PhotoState] = []
        self.current: PhotoState | None = None
        self.params = params if params is not None else RegistrationParams()
        self.features_3d: list[Feature3D] = []
        self.measurements: list[Measurement] = []

    # -------------------------------------------------------------- scene
    def load_scene(self, scene: Scene, terrain: adjust.TerrainMap | None = None,
                   files: dict | None = None) -> None:
        """Make ``scene`` the workspace's model; the photos are cleared.

        Parameters
        ----------
        scene : Scene
            With its engine built (:func:`read_scene` builds it).
        terrain : TerrainMap, optional
            Computed from the scene when not given.
        files : dict, optional
            The paths it was read from (``mesh``, ``dem``, ``georef``).
        """
        self.scene = scene
        self.terrain = terrain if terrain is not None else adjust.terrain_map(scene)
        self.scene_files = {k: str(v or "") for k, v in (files or {}).items()}
        self.photos, self.current = [], None
        self.features_3d, self.measurements = [], []
        self.scene_changed.emit()
        self.photos_changed.emit()

    def open_scene(self, mesh: str | Path, dem: str | Path | None = None,
                   georef: str | Path | None = None) -> Scene:
        """Read and load a model (blocking; see :func:`read_scene`)."""
        scene, terrain = read_scene(mesh, dem, georef)
        self.load_scene(scene, terrain, {"mesh": mesh, "dem": dem, "georef": georef})
        return scene

    def require_scene(self) -> Scene:
        """The scene, or a :class:`WorkbenchError` saying to open one."""
        if self.scene is None:
            raise WorkbenchError(
                "Open a model first: the prior's altitude comes from its DEM or surface.")
        return self.scene

    def _photo_and_scene(self, ps: PhotoState | None = None) -> tuple[PhotoState, Scene]:
        ps = ps if ps is not None else self.current
        if ps is None or self.scene is None:
            raise WorkbenchError("Load a scene and a photo first.")
        return ps, self.scene

    # ------------------------------------------------------------- photos
    def add_loaded_photos(self, loaded: list[tuple[Photo, Prior]]) -> list[PhotoState]:
        """Add photos read by :func:`read_photos` (a photo already there is skipped).

        The first photo becomes current when none is.

        Returns
        -------
        list of PhotoState
            The photos added.
        """
        known = {ps.photo.path for ps in self.photos}
        added = []
        for photo, prior in loaded:
            if photo.path in known:
                continue
            history = adjust.PoseHistory(prior.pose)
            history._current_label = "prior"
            ps = PhotoState(photo=photo, prior=prior, record_path=photo.sidecar,
                            intrinsics=prior.intrinsics, history=history)
            self.photos.append(ps)
            known.add(photo.path)
            added.append(ps)
        self.photos_changed.emit()
        if self.current is None and self.photos:
            self.select_photo(0)
        return added

    def add_photos(self, paths) -> list[str]:
        """Read and add photos (blocking); returns the errors, one line each."""
        loaded, errors = read_photos(paths, self.require_scene())
        self.add_loaded_photos(loaded)
        return errors

    def add_photo(self, path: str | Path) -> PhotoState:
        """Read and add one photo (blocking); raises if it cannot be read."""
        scene = self.require_scene()
        photo = load_photo(Path(path))
        added = self.add_loaded_photos([(photo, prior_for_photo(photo, scene))])
        return added[0] if added else self.photo_at_path(photo.path)

    def photo_at_path(self, path: str | Path | None) -> PhotoState | None:
        """The photo read from ``path`` (None if not in the workspace)."""
        if path is None:
            return None
        path = Path(path)
        return next((ps for ps in self.photos if ps.photo.path == path), None)

    def select_photo(self, index: int) -> None:
        """Make photo ``index`` current (out of range: nothing happens)."""
        if not 0 <= index < len(self.photos):
            return
        self.current = self.photos[index]
        self.photo_changed.emit()

    @property
    def current_index(self) -> int | None:
        return self.photos.index(self.current) if self.current in self.photos else None

    # --------------------------------------------------------------- pose
    def _push(self, pose: Pose, label: str, why: str) -> None:
        self.current.history.push(pose, label)
        self.pose_changed.emit(why)

    def set_pose(self, pose: Pose, label: str, continuing: bool = False) -> None:
        """Change the current photo's pose: an undoable edit named ``label``,
        or (``continuing``) the same edit going on (a drag)."""
        ps = self.current
        if ps is None:
            return
        if continuing:
            ps.history.replace(pose)
            self.pose_changed.emit(label)
        else:
            self._push(pose, label, label)

    def nudge(self, label: str = "nudge", **amounts: float) -> None:
        """Turn/move the camera by small amounts (see :func:`adjust.nudge_pose`)."""
        if self.current is not None:
            self.set_pose(adjust.nudge_pose(self.current.pose, **amounts), label)

    def height_above_ground(self) -> float | None:
        """The current camera's height above the terrain, metres (None: unknown)."""
        if self.current is None or self.scene is None:
            return None
        return adjust.height_above_ground(self.current.pose, self.scene.terrain_height)

    def move_on_map(self, x: float, y: float, continuing: bool = False,
                    height: float | None = None) -> bool:
        """Move the camera to map point (x, y), keeping its height above the
        terrain (or at ``height``). False without a photo or a scene.

        Raises
        ------
        WorkbenchError
            (x, y) is outside the terrain.
        """
        ps = self.current
        if ps is None or self.scene is None:
            return False
        h = height if height is not None else self.height_above_ground()
        if h is None:
            h = _DEFAULT_HEIGHT_M
        try:
            pose = adjust.pose_at_ground(ps.pose, x, y, h, self.scene.terrain_height)
        except (InputError, ValueError) as exc:
            raise WorkbenchError(
                f"({x:.1f}, {y:.1f}) is outside the terrain: {one_line(exc)}") from exc
        self.set_pose(pose, "moved on the map", continuing=continuing)
        return True

    def turn_toward(self, x: float, y: float) -> None:
        """Turn the camera (trend only) toward map point (x, y)."""
        if self.current is not None:
            self.set_pose(adjust.turn_toward(self.current.pose, x, y), "turned on the map")

    def undo(self) -> bool:
        """Take back the last pose edit; False when there is none."""
        if self.current is not None and self.current.history.undo() is not None:
            self.pose_changed.emit("undo")
            return True
        return False

    def redo(self) -> bool:
        """Re-apply the last undone pose edit; False when there is none."""
        if self.current is not None and self.current.history.redo() is not None:
            self.pose_changed.emit("redo")
            return True
        return False

    def reset_to_prior(self) -> None:
        """Back to the prior's pose (an undoable edit)."""
        if self.current is not None:
            self.set_pose(self.current.prior.pose, "prior")

    def save_record(self) -> Path | None:
        """Save the current pose (and a solved camera) into the photo's sensor record.

        Raises
        ------
        InputError, OSError
            The record cannot be read or written.
        """
        ps = self.current
        if ps is None:
            return None
        camera = ps.intrinsics if ps.intrinsics != ps.prior.intrinsics else None
        save_pose_to_record(ps.record_path, ps.pose, camera=camera)
        return ps.record_path

    # ------------------------------------------------------------- params
    def set_params(self, params: RegistrationParams) -> None:
        """Replace the registration parameters."""
        self.params = params
        self.params_changed.emit()

    def keep_run_settings(self, params: RegistrationParams) -> RegistrationParams:
        """A trial's parameters with this session's run settings (Run/Auto decide
        those: :data:`RUN_SETTINGS`)."""
        new = params.copy()
        for name in RUN_SETTINGS:
            setattr(new, name, getattr(self.params, name))
        return new

    # ------------------------------------------------------- registration
    def registration_prior(self, ps: PhotoState | None = None) -> Prior:
        """The prior a registration of the photo starts from: its current camera
        and pose, its prior's uncertainty and notes, and its sun (the one set
        by hand or read from the photo, else the prior's)."""
        ps = ps if ps is not None else self.current
        sun = ps.sun
        return replace(ps.prior, intrinsics=ps.intrinsics, pose=ps.pose,
                       assumptions=list(ps.prior.assumptions),
                       sun=None if sun is None else np.array(sun, float),
                       sun_source=ps.sun_source)

    def registration_job(self, auto: bool,
                         cancelled: Callable[[], bool] | None = None) -> Job:
        """Register the current photo from its current pose: one trial (Run) or
        trials adapted by the rules (Auto).

        The job yields :class:`~napari_imgreg.registration.pipeline.Progress`
        and returns the Registration; its ``apply`` records it
        (:meth:`record_registration`).

        Raises
        ------
        WorkbenchError
            No scene or photo, or feature parameters that do not make a detector.
        """
        ps, scene = self._photo_and_scene()
        try:
            FeatureParams.from_dict(self.params.features.to_dict())
        except (KeyError, ValueError, TypeError) as exc:
            raise WorkbenchError(one_line(exc)) from exc
        params = self.params.copy()
        params.auto_adapt = auto
        if not auto:
            params.search_prior = False
            params.max_trials = 1
        prior = self.registration_prior(ps)
        image, name = ps.photo.image, ps.name
        kind = "Auto" if auto else "Run"

        def run():
            # Looked up when run: a test may stand in for the pipeline.
            return (yield from pipeline.register_photo(scene, image, prior, params,
                                                       photo_name=name, cancelled=cancelled))

        return Job("registration", run, lambda reg: self.record_registration(reg, kind, ps),
                   f"Registering {name}", ps)

    def register(self, auto: bool = False, on_progress: Callable | None = None) -> Registration:
        """Register the current photo (blocking); see :meth:`registration_job`."""
        return self.registration_job(auto)(on_progress)

    def record_registration(self, reg: Registration, kind: str = "Run",
                            ps: PhotoState | None = None) -> Registration:
        """Record a registration of a photo: its trials join the photo's history
        (the best one selected) and, if it registered and the photo is still
        current, its pose becomes the current pose (an undoable edit)."""
        ps = ps if ps is not None else self.current
        ps.runs += 1
        ps.registration = reg
        first = len(ps.trials)
        for t in reg.trials:
            ps.trials.append(TrialRecord(t, ps.runs, kind))
        best = first + next((k for k, t in enumerate(reg.trials) if t.index == reg.best_trial), 0)
        if reg.registered and ps is self.current:
            self._push(reg.pose, f"{kind} {ps.runs} ({reg.grade})", "registration")
        ps.selected_trial = best
        self.trials_changed.emit()
        if ps is self.current:
            self.select_trial(best)
        return reg

    def add_trial(self, trial: Trial, kind: str = "Run", run: int | None = None,
                  ps: PhotoState | None = None) -> TrialRecord:
        """Add a trial made elsewhere (e.g. read back) to a photo's history."""
        ps = ps if ps is not None else self.current
        rec = TrialRecord(trial, ps.runs if run is None else run, kind)
        ps.trials.append(rec)
        self.trials_changed.emit()
        return rec

    # -------------------------------------------------------------- trials
    def select_trial(self, index: int) -> None:
        """Select a trial of the current photo (its pose is not applied)."""
        ps = self.current
        if ps is None or not 0 <= index < len(ps.trials):
            return
        ps.selected_trial = index
        self.trial_selected.emit(index)

    def selected_trial(self) -> TrialRecord | None:
        ps = self.current
        if ps is None or ps.selected_trial is None or not ps.trials:
            return None
        return ps.trials[ps.selected_trial]

    def restore_trial(self, index: int) -> TrialRecord | None:
        """Go back to a trial: its pose (or its start when it found none) and its
        parameters (with this session's run settings); an undoable edit."""
        ps = self.current
        if ps is None or not 0 <= index < len(ps.trials):
            return None
        rec = ps.trials[index]
        self.set_params(self.keep_run_settings(rec.trial.params))
        pose = rec.trial.pose if rec.trial.pose is not None else rec.trial.start_pose
        self._push(pose, f"trial {index + 1} restored", "restore")
        self.select_trial(index)
        return rec

    def suggestion(self, index: int | None = None) -> RuleHit | None:
        """The first rule that fires for a trial (default: the selected one), or None."""
        ps = self.current
        if ps is None or not ps.trials:
            return None
        index = ps.selected_trial if index is None else index
        if index is None:
            return None
        trial = ps.trials[index].trial
        hits = evaluate_rules(trial.metrics, trial.params, ps.intrinsics.width)
        return hits[0] if hits else None

    def apply_suggestion(self, index: int | None = None) -> RuleHit | None:
        """Take the trial's parameters with the rule's adaptation applied
        (default: the selected trial); returns the rule, None when none fires."""
        ps = self.current
        hit = self.suggestion(index)
        if ps is None or hit is None:
            return None
        index = ps.selected_trial if index is None else index
        self.set_params(self.keep_run_settings(hit.apply(ps.trials[index].trial.params)))
        return hit

    # -------------------------------------------------------------- manual
    def reference_job(self, intrinsics: Intrinsics | None = None, pose: Pose | None = None,
                      source: str = "pose") -> Job:
        """Render the reference image for manual pairs, by default from the
        current pose (``source="view"``: a camera given from a 3D view)."""
        ps, scene = self._photo_and_scene()
        intr = intrinsics if intrinsics is not None else ps.intrinsics
        pose = pose if pose is not None else ps.pose

        def apply(result: RenderResult) -> RenderResult:
            if self.current is ps:  # another photo now: its own reference stays
                self.set_reference(result, source)
            return result

        return Job("reference", lambda: render(scene, intr, pose), apply, "Reference render", ps)

    def make_reference(self, intrinsics: Intrinsics | None = None, pose: Pose | None = None,
                       source: str = "pose") -> RenderResult:
        """Render and set the reference (blocking); see :meth:`reference_job`."""
        return self.reference_job(intrinsics, pose, source)()

    def set_reference(self, reference: RenderResult, source: str = "pose") -> None:
        """Set the current photo's reference render; its picks on the old one go."""
        ps = self.current
        if ps is None:
            return
        ps.reference, ps.reference_source = reference, source
        ps.reference_points_px = np.zeros((0, 2))
        self.reference_changed.emit()
        self.pairs_changed.emit()

    def set_pair_points(self, photo_px: np.ndarray, reference_px: np.ndarray) -> None:
        """Set the current photo's picks (as a view edited them): photo pixels
        (N, 2) and reference pixels (M, 2), (x, y), pair k = point k of each."""
        ps = self.current
        if ps is None:
            return
        ps.photo_points_px = np.asarray(photo_px, float).reshape(-1, 2).copy()
        ps.reference_points_px = np.asarray(reference_px, float).reshape(-1, 2).copy()
        self.pairs_changed.emit()

    def add_pair(self, photo_xy, reference_xy) -> int:
        """Add a pair: a photo pixel (x, y) and the same point on the reference;
        returns its index (a point waiting for its partner is completed first)."""
        ps = self.current
        if ps is None:
            raise WorkbenchError("Load a scene and a photo first.")
        n = min(len(ps.photo_points_px), len(ps.reference_points_px))
        photo = np.vstack([ps.photo_points_px[:n], np.reshape(photo_xy, (1, 2))])
        ref = np.vstack([ps.reference_points_px[:n], np.reshape(reference_xy, (1, 2))])
        self.set_pair_points(photo, ref)
        return n

    def remove_pair(self, index: int) -> None:
        """Remove pair ``index`` (both of its points)."""
        ps = self.current
        if ps is None:
            return
        photo, ref = ps.photo_points_px, ps.reference_points_px
        if index < len(photo):
            photo = np.delete(photo, index, axis=0)
        if index < len(ref):
            ref = np.delete(ref, index, axis=0)
        self.set_pair_points(photo, ref)

    def clear_pairs(self) -> None:
        self.set_pair_points(np.zeros((0, 2)), np.zeros((0, 2)))

    def pairs(self, ps: PhotoState | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Complete pairs: photo pixels (N, 2) and reference pixels (N, 2), (x, y)."""
        ps = ps if ps is not None else self.current
        if ps is None:
            return np.zeros((0, 2)), np.zeros((0, 2))
        n = min(len(ps.photo_points_px), len(ps.reference_points_px))
        return (np.asarray(ps.photo_points_px[:n], float),
                np.asarray(ps.reference_points_px[:n], float))

    def pair_points_3d(self, ps: PhotoState | None = None) -> tuple[np.ndarray, np.ndarray]:
        """3D points under the reference picks (N, 3), metres, and whether each has one."""
        ps = ps if ps is not None else self.current
        _, ref_px = self.pairs(ps)
        if ps is None or ps.reference is None or not len(ref_px):
            return np.full((len(ref_px), 3), np.nan), np.zeros(len(ref_px), bool)
        return ps.reference.lift(ref_px)

    def manual_job(self, solve_focal: bool = False,
                   cancelled: Callable[[], bool] | None = None) -> Job:
        """Solve the current photo's pose from its pairs and score it like a trial.

        The job returns ``(ManualSolution, Trial or None)``; its ``apply``
        records them (:meth:`record_manual`) and returns the solution.

        Raises
        ------
        WorkbenchError
            No reference render, or fewer than ``MIN_PAIRS`` pairs on the model.
        """
        ps, scene = self._photo_and_scene()
        if ps.reference is None:
            raise WorkbenchError("Make a reference render and pick pairs first.")
        photo_px, _ = self.pairs(ps)
        xyz, valid = self.pair_points_3d(ps)
        if int(valid.sum()) < manual.MIN_PAIRS:
            raise WorkbenchError(
                f"{int(valid.sum())} pairs with a 3D point: pick at least {manual.MIN_PAIRS} "
                "(the reference point must lie on the model)")
        intr, initial, image = ps.intrinsics, ps.pose, ps.photo.image
        params = self.params.copy()

        def run():
            sol = manual.solve_manual(intr, photo_px, xyz, initial=initial,
                                      solve_focal=solve_focal)
            trial = None
            if sol.ok:
                trial = manual.score_pose(scene, image, sol.intrinsics, sol.pose, params,
                                          cancelled=cancelled)
            return sol, trial

        return Job("manual", run, lambda value: self.record_manual(*value, ps=ps),
                   "Manual registration", ps)

    def solve_manual(self, solve_focal: bool = False) -> manual.ManualSolution:
        """Solve and score from the pairs (blocking); see :meth:`manual_job`."""
        return self.manual_job(solve_focal)()

    def record_manual(self, solution: manual.ManualSolution, trial: Trial | None,
                      ps: PhotoState | None = None) -> manual.ManualSolution:
        """Record a manual solution: a solved focal length becomes the photo's
        camera, the scored trial joins its history (selected) and, if the photo
        is still current, the pose becomes its current pose (undoable)."""
        ps = ps if ps is not None else self.current
        ps.manual_solution = solution
        if not solution.ok:
            return solution
        if solution.focal_solved:
            ps.intrinsics = solution.intrinsics
        ps.trials.append(TrialRecord(trial, ps.runs, "Manual"))
        ps.selected_trial = len(ps.trials) - 1
        if ps is self.current:
            self._push(solution.pose, f"manual ({solution.n_inliers} pairs)", "manual")
        self.trials_changed.emit()
        if ps is self.current:
            self.select_trial(ps.selected_trial)
        return solution

    # ----------------------------------------------------------------- sun
    def convergence_deg(self, ps: PhotoState | None = None) -> float:
        """Meridian convergence at the photo's prior camera, degrees: grid
        azimuth = true azimuth − convergence (0 without a georeference, the
        model's +Y then taken as true north)."""
        ps = ps if ps is not None else self.current
        scene = self.scene
        if ps is None or scene is None or scene.georef is None:
            return 0.0
        if ps._convergence is None:
            ps._convergence = float(meridian_convergence_deg(scene.georef, ps.prior.pose.center))
        return ps._convergence

    def sun_angles(self, ps: PhotoState | None = None) -> tuple[float, float] | None:
        """The photo's sun as (azimuth from TRUE north, elevation), degrees; None: unknown."""
        ps = ps if ps is not None else self.current
        if ps is None or ps.sun is None:
            return None
        d = _unit(ps.sun)
        grid_az = math.degrees(math.atan2(d[0], d[1]))
        elevation = math.degrees(math.asin(float(np.clip(d[2], -1.0, 1.0))))
        return (grid_az + self.convergence_deg(ps)) % 360.0, elevation

    def set_sun(self, direction, source: str = "hand setting",
                ps: PhotoState | None = None) -> None:
        """Override a photo's sun (default: the current one's; unit vector toward
        it, local frame); ``source`` completes "sun from the …" in the
        registration's notes."""
        ps = ps if ps is not None else self.current
        if ps is None:
            return
        ps.sun_override = _unit(direction)
        ps.sun_override_source = source
        self.sun_changed.emit(ps)

    def set_sun_angles(self, azimuth_true_deg: float, elevation_deg: float,
                       source: str = "hand setting") -> None:
        """Set the current photo's sun by its azimuth from TRUE north and its elevation."""
        if self.current is None:
            return
        grid = float(azimuth_true_deg) - self.convergence_deg()
        self.set_sun(sun_vector_enu(grid, float(elevation_deg)), source)

    def reset_sun(self) -> None:
        """Back to the prior's sun (capture time or sensor record)."""
        ps = self.current
        if ps is None or ps.sun_override is None:
            return
        ps.sun_override, ps.sun_override_source = None, ""
        self.sun_changed.emit(ps)

    def sun_estimate_job(self) -> Job:
        """Read the current photo's sun from its light and shade, against a render
        from its current pose; ``apply`` makes it the photo's sun."""
        ps, scene = self._photo_and_scene()
        intr, pose, image = ps.intrinsics, ps.pose, ps.photo.image
        survey = scene.survey_sun

        def run() -> SunEstimate:
            rendered = render(scene, intr, pose, scale=match_scale(intr.width, SUN_ESTIMATE_WIDTH))
            h, w = rendered.shape
            photo = image if image.shape[:2] == (h, w) else cv2.resize(
                image, (w, h), interpolation=cv2.INTER_AREA)
            return estimate_sun_from_photo(photo, rendered, scene=scene, survey_sun_dir=survey)

        return Job("sun", run, lambda est: self.record_sun_estimate(est, ps),
                   "Reading the sun from the photo", ps)

    def estimate_sun(self) -> SunEstimate:
        """Read the current photo's sun from the photo (blocking)."""
        return self.sun_estimate_job()()

    def record_sun_estimate(self, estimate: SunEstimate,
                            ps: PhotoState | None = None) -> SunEstimate:
        """The sun read from a photo becomes its sun."""
        ps = ps if ps is not None else self.current
        ps.sun_estimate = estimate
        self.set_sun(np.asarray(estimate.direction, float),
                     f"photo's shading (fit r = {estimate.correlation:.2f}, "
                     f"confidence {estimate.confidence:.2f})", ps=ps)
        return estimate

    # ------------------------------------------------------ interpretation
    def add_interpretation(self, item: Interpretation, ps: PhotoState | None = None) -> int:
        """Add a feature drawn on a photo (default: the current one); returns its index."""
        ps = ps if ps is not None else self.current
        if ps is None:
            raise WorkbenchError("Load a scene and a photo first.")
        ps.interpretations.append(item)
        self.interpretations_changed.emit(ps)
        return len(ps.interpretations) - 1

    def set_interpretations(self, items: list[Interpretation],
                            ps: PhotoState | None = None) -> None:
        """Replace what is drawn on a photo (as a drawing view holds it)."""
        ps = ps if ps is not None else self.current
        if ps is None:
            return
        ps.interpretations = list(items)
        self.interpretations_changed.emit(ps)

    def remove_interpretation(self, index: int, ps: PhotoState | None = None) -> None:
        ps = ps if ps is not None else self.current
        if ps is not None and 0 <= index < len(ps.interpretations):
            del ps.interpretations[index]
            self.interpretations_changed.emit(ps)

    def projection_job(self) -> Job:
        """Project every photo's interpretations onto the scene, each from its
        current camera and pose; ``apply`` records the features and their
        measurements.

        Raises
        ------
        WorkbenchError
            No scene, or nothing drawn.
        """
        scene = self.require_scene()
        jobs = [(ps.intrinsics, ps.pose, list(ps.interpretations), ps.name)
                for ps in self.photos if ps.interpretations]
        if not jobs:
            raise WorkbenchError("Nothing to project: draw on a photo first.")
        return Job("projection", lambda: project_interpretation_sets(scene, jobs),
                   lambda value: self.record_projection(*value), "Projecting interpretations")

    def project_interpretations(self) -> list[Feature3D]:
        """Project the interpretations (blocking); see :meth:`projection_job`."""
        return self.projection_job()()

    def record_projection(self, features: list[Feature3D],
                          measurements: list[Measurement]) -> list[Feature3D]:
        """Record projected interpretations and their measurements."""
        self.features_3d, self.measurements = list(features), list(measurements)
        self.projection_changed.emit()
        return self.features_3d

    # -------------------------------------------------------------- saving
    def to_dict(self) -> dict:
        """What a saved workspace will hold (JSON-ready; images and the model
        are referred to by path)."""
        return {
            "scene": dict(self.scene_files),
            "params": self.params.to_dict(),
            "photos": [ps.to_dict() for ps in self.photos],
            "current": self.current_index,
        }
