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

The state is plain dataclasses. :meth:`Workspace.save` writes it into a
workspace folder (``campaign.imgreg/``, see docs/formats.md "Workspace
folder" and :mod:`napari_imgreg.io.workspace_files`) and binds the workspace
to it: from then on every change is saved atomically as its event is emitted
(each photo into its own files, the manifest last), so a crash loses at most
the action in progress. :meth:`Workspace.open` reads a folder back into an
equal state and keeps saving it.

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

import gc
import hashlib
import inspect
import math
import os
import weakref
import warnings
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Callable, Iterator

import cv2
import numpy as np
from psygnal import Signal

from . import adjust
from ._atomic import OutputError
from .camera import Intrinsics, Pose, match_scale
from .errors import InputError, input_error
from .geo import DEM, Georef
from .interpret import files as interpret_files
from .interpret.project import (
    Feature3D,
    Interpretation,
    check_drawing,
    label_color,
    measure_features,
    merge_interpretations,
    project_interpretations,
)
from .interpret.structural import Measurement
from .io import workspace_files as wsfiles
from .io.exif import exif_orientation
from .io.control_points import read_control_points, write_control_points
from .io.photos import Photo, load_photo
from .io.records import Sigma
from .prior import Prior, prior_for_photo, save_pose_to_record
from .registration import manual, pipeline
from .registration.features import FeatureParams
from .registration.params import RegistrationParams
from .registration.pipeline import Registration, Trial
from .registration.quality import RuleHit, evaluate_rules
from .registration.result_file import (
    pose_or_none,
    registration_from_dict,
    stored_number,
    trial_from_dict,
)
from .registration.round import Correspondences
from .registration.stages.relight import SunEstimate, estimate_sun_from_photo
from .interpret.uncertainty import PoseUncertainty
from .registration.uncertainty import Uncertainty
from .render import RenderResult, render
from .scene import Scene
from .solar import meridian_convergence_deg, sun_vector_enu

__all__ = [
    "Workspace",
    "PhotoState",
    "TrialRecord",
    "Job",
    "SaveAs",
    "PhotoSummary",
    "BatchStep",
    "BatchSummary",
    "PHOTO_STATUSES",
    "WorkbenchError",
    "one_line",
    "read_scene",
    "read_photos",
    "project_interpretation_sets",
    "check_drawings",
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
    if isinstance(exc, (InputError, WorkbenchError, OutputError)):  # already say what
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
    pair_points_xyz : (N, 3) float array
        The model point (model frame, metres) of each photo pick that
        carries its own, loaded from a control-point file
        (:meth:`Workspace.load_pairs`); NaN rows take theirs from the
        reference pick. Aligned with ``photo_points_px``.
    pair_names : list of str
        Each photo pick's name from a control-point file (``"GCP12"``; ""
        for a clicked one), kept when the pairs are saved again. Aligned
        with ``photo_points_px``.
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
    accepted : bool
        The user accepted its current pose (:meth:`Workspace.accept`): it no
        longer needs attention until the pose changes again.
    registered_on : dict or None
        ``{"photo": ..., "model": ...}``: fingerprints
        (:func:`~napari_imgreg.io.workspace_files.file_fingerprint`) of the
        photo file and the model at its last registration (automatic or
        manual); None before any. A file replaced since (a re-exported model,
        another photo under the same name) is reported when the workspace is opened.
    error : str
        Why its registration in the last Register all raised instead of
        ending (a photo that cannot be read, too little memory); "" once a
        registration of it is recorded. Kept for the session, not saved.
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
    pair_points_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    pair_names: list[str] = field(default_factory=list)
    selected_trial: int | None = None
    runs: int = 0
    sun_override: np.ndarray | None = None
    sun_override_source: str = ""
    sun_estimate: SunEstimate | None = None
    interpretations: list[Interpretation] = field(default_factory=list)
    accepted: bool = False
    registered_on: dict | None = None
    error: str = ""
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
                      "xyz": _xyz_to_list(self.pair_points_xyz),
                      "names": list(self.pair_names),
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


#: What :meth:`Workspace.photo_status` says of a photo.
PHOTO_STATUSES = ("not registered", "failed", "registered", "accepted")
#: Grades a registered photo needs to need no attention.
GOOD_GRADES = ("excellent", "good")
#: A registered photo whose estimated reprojection error is above this (pixels) needs attention.
ATTENTION_REPROJECTION_PX = 5.0


@dataclass
class PhotoSummary:
    """One row of the photos table.

    Attributes
    ----------
    name : str
    status : str
        One of :data:`PHOTO_STATUSES`.
    grade : str
        Of its last registration (or selected trial); "" before any.
    q : float
        Its Q, in [-1.9, 1.9]; NaN before any.
    reprojection_px : float
        ``uncertainty.reprojection_px`` of its last registration, pixels
        (NaN: not estimated).
    time_s : float
        Its last registration's total time, seconds (NaN: none).
    attention : bool
        :meth:`Workspace.needs_attention`.
    drawn : int
        Features drawn on the photo.
    mapped : int
        Of the last projection, the features that came from this photo.
    mapped_out_of_date : bool
        Its drawings, camera or pose changed since that projection
        (:meth:`Workspace.projection_out_of_date`).
    """

    name: str
    status: str
    grade: str
    q: float
    reprojection_px: float
    time_s: float
    attention: bool
    drawn: int = 0
    mapped: int = 0
    mapped_out_of_date: bool = False


@dataclass
class BatchStep:
    """One photo's end in a Register all (yielded by its job's ``run``).

    Attributes
    ----------
    photo : PhotoState
    registration : Registration or None
        None when it raised (``error`` says why).
    error : str
    kind : str
        "Auto" or "Run".
    index, total : int
        Its place in the batch (from 0) and the batch's size.
    """

    photo: PhotoState
    registration: Registration | None
    error: str
    kind: str
    index: int
    total: int


@dataclass
class BatchSummary:
    """The end of a Register all.

    Attributes
    ----------
    total : int
        Photos it set out to register.
    skipped : int
        Photos left alone (registered or accepted already).
    done : int
        Photos it finished (registered or not).
    registered : int
    failed : list of str
        One line per photo that did not register.
    cancelled : bool
    """

    total: int = 0
    skipped: int = 0
    done: int = 0
    registered: int = 0
    failed: list[str] = field(default_factory=list)
    cancelled: bool = False


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
        scene = Scene.from_dem(path, georef=georef or None)
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
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]  # one photo, not a photo per character of its name
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
    scene: Scene,
    jobs: list[tuple[Intrinsics, Pose, list[Interpretation], str]
               | tuple[Intrinsics, Pose, list[Interpretation], str, PoseUncertainty | None]],
) -> tuple[list[Feature3D], list[Measurement]]:
    """Project each photo's interpretations onto the scene; one merged set.

    Parameters
    ----------
    scene : Scene
    jobs : list of (Intrinsics, Pose, list of Interpretation, str[, PoseUncertainty])
        Per photo: its camera, its pose, what was drawn on it, its name, and
        optionally its pose's expected error (the σ of what is projected;
        default :func:`~napari_imgreg.interpret.project.project_interpretations`'s).

    Returns
    -------
    features : list of Feature3D
    measurements : list of Measurement
        As ``measure`` writes them: one per feature that reached the surface,
        then one per contact drawn on two or more photos (``contact:<id>``).
    """
    for job in jobs:  # every photo's drawings, before any ray: the error names the photo
        check_drawings(job[2], job[0], job[3])
    sets = [project_interpretations(scene, job[0], job[1], job[2], source=job[3],
                                    pose_uncertainty=job[4] if len(job) > 4 else None)
            for job in jobs]
    features = merge_interpretations(*sets)
    return features, measure_features(features)


def check_drawings(items: list[Interpretation], intrinsics: Intrinsics, photo: str) -> None:
    """Refuse drawings that cannot be projected from a photo, naming it.

    What projecting them checks (:func:`~napari_imgreg.interpret.project.check_drawing`),
    done where they are set, so that a bad drawing is refused before it is
    saved instead of blocking every later projection.

    Parameters
    ----------
    items : list of Interpretation
    intrinsics : Intrinsics
        The photo's camera (its size).
    photo : str
        The photo's name, for the message.

    Raises
    ------
    InputError
        A vertex is not finite or lies far outside the photo (one line:
        ``feature <n> on <photo>: ...``).
    """
    for k, item in enumerate(items):
        check_drawing(item.pixels, intrinsics.width, intrinsics.height,
                      f"feature {k + 1} on {photo}")


def _resolved(path: Path | None) -> Path | None:
    """``path`` made absolute with links resolved (None stays None)."""
    return None if path is None else Path(path).resolve()


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
    folder : Path or None
        The workspace folder it is saved into as it changes (:meth:`save`,
        :meth:`open`); None: not saved.
    open_problems : list of str
        What :meth:`open` could not restore, one line each.
    drawn_not_opened : dict of str to str
        The photos :meth:`open` could not read that were drawn on or have
        projected features, by file name: the line of ``open_problems``
        saying why. :meth:`projection_job` refuses while there are any.
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
    #: A photo was accepted, or its accepted pose changed (the photo).
    accepted_changed = Signal(object)
    #: Saving into the workspace folder failed (one line: the file and why);
    #: the state in memory is intact and the next change tries again.
    autosave_failed = Signal(str)

    def __init__(self, params: RegistrationParams | None = None) -> None:
        self.scene: Scene | None = None
        self.terrain: adjust.TerrainMap | None = None
        self.scene_files: dict[str, str] = {}
        self.photos: list[PhotoState] = []
        self.current: PhotoState | None = None
        self.params = params if params is not None else RegistrationParams()
        self.features_3d: list[Feature3D] = []
        self.measurements: list[Measurement] = []
        #: What could not be restored when the workspace was opened (one line each).
        self.open_problems: list[str] = []
        #: Photos not opened whose drawings a projection now would drop.
        self.drawn_not_opened: dict[str, str] = {}
        self._store: _FolderStore | None = None
        #: The folder names of the photos read by :meth:`open` (kept without autosave too).
        self._opened_keys: dict[PhotoState, str] = {}
        #: The lines of ``open_problems`` that are warnings: everything was opened,
        #: but a file changed since the work on it was done.
        self.open_warnings: list[str] = []
        #: The model file's fingerprint when it was loaded (what registrations are made on).
        self._mesh_fingerprint: dict | None = None
        #: Per photo, :func:`_projection_input` of what the last projection was made from.
        self._projected_from: dict[PhotoState, str] | None = None
        #: (features_3d, its length, features per source photo): see _mapped_by_source.
        self._mapped_counted: tuple | None = None

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
        own = RegistrationParams.for_scene(scene)
        if self.params.is_scene_default() and self.params != own:
            # Untouched defaults follow the model: a point cloud's differ.
            self.params = own
            self.params_changed.emit()
        self.terrain = terrain if terrain is not None else adjust.terrain_map(scene)
        self.scene_files = {k: str(v or "") for k, v in (files or {}).items()}
        self._mesh_fingerprint = wsfiles.file_fingerprint(self.scene_files.get("mesh"))
        self.photos, self.current = [], None
        self.features_3d, self.measurements = [], []
        self._projected_from = None
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
        # Resolved: the same file given by a relative and an absolute path,
        # or through a link, is one photo.
        known = {_resolved(ps.photo.path) for ps in self.photos}
        added = []
        for photo, prior in loaded:
            if _resolved(photo.path) in known:
                continue
            history = adjust.PoseHistory(prior.pose)
            history._current_label = "prior"
            ps = PhotoState(photo=photo, prior=prior, record_path=photo.sidecar,
                            intrinsics=prior.intrinsics, history=history)
            self.photos.append(ps)
            known.add(_resolved(photo.path))
            added.append(ps)
        self.photos_changed.emit()
        if self.current is None and self.photos:
            self.select_photo(0)
        return added

    def add_photos(self, paths) -> list[str]:
        """Read and add photos (a path or a list of paths; blocking); returns the
        errors, one line each."""
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
        return (next((ps for ps in self.photos if ps.photo.path == path), None)
                or next((ps for ps in self.photos
                         if _resolved(ps.photo.path) == _resolved(path)), None))

    def photo_key(self, ps: PhotoState) -> str | None:
        """The photo's folder name in the workspace folder (``photos/<key>/``),
        unique where file names are not (two ``IMG_0001.jpg`` of two cameras);
        None for a photo not saved in a folder."""
        if self._store is not None and ps in self._store.keys:
            return self._store.keys[ps]
        return self._opened_keys.get(ps)

    def select_photo(self, index: int) -> None:
        """Make photo ``index`` current (out of range: nothing happens)."""
        if not 0 <= index < len(self.photos):
            return
        previous, self.current = self.current, self.photos[index]
        # Only the current photo keeps its decoded pixels: the one left lets
        # them go (a photo read from a file decodes again when next shown).
        self.current.photo.keep_decoded = True
        if previous is not None and previous is not self.current:
            previous.photo.keep_decoded = False
            previous.photo.release()
        self.photo_changed.emit()

    @property
    def current_index(self) -> int | None:
        return self.photos.index(self.current) if self.current in self.photos else None

    # --------------------------------------------------------------- pose
    def _push(self, pose: Pose, label: str, why: str) -> None:
        self.current.history.push(pose, label)
        self._pose_edited_by_hand(self.current)
        self.pose_changed.emit(why)

    def _pose_edited_by_hand(self, ps: PhotoState) -> None:
        """A pose the user had accepted changed: it needs a look again."""
        if ps.accepted:
            ps.accepted = False
            self.accepted_changed.emit(ps)

    def set_pose(self, pose: Pose, label: str, continuing: bool = False) -> None:
        """Change the current photo's pose: an undoable edit named ``label``,
        or (``continuing``) the same edit going on (a drag)."""
        ps = self.current
        if ps is None:
            return
        if continuing:
            ps.history.replace(pose)
            self._pose_edited_by_hand(ps)
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
            self._pose_edited_by_hand(self.current)
            self.pose_changed.emit("undo")
            return True
        return False

    def redo(self) -> bool:
        """Re-apply the last undone pose edit; False when there is none."""
        if self.current is not None and self.current.history.redo() is not None:
            self._pose_edited_by_hand(self.current)
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
        # The record is marked as describing the photo as shown, so for an
        # EXIF-turned photo the sensor-frame camera block must be replaced too
        # (left as it is, an off-centre principal point would read mirrored).
        turned = (exif_orientation(ps.photo.exif) or 1) != 1
        camera = ps.intrinsics if turned or ps.intrinsics != ps.prior.intrinsics else None
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
                            ps: PhotoState | None = None,
                            pose_if_not_current: bool = False) -> Registration:
        """Record a registration of a photo: its trials join the photo's history
        (the best one selected) and, if it registered and the photo is still
        current, its pose becomes the current pose (an undoable edit).

        ``pose_if_not_current``: the registered pose becomes the photo's pose
        (an undoable edit of its history) even when another photo is current
        (Register all: the user looks at one photo while the others register).
        """
        ps = ps if ps is not None else self.current
        ps.runs += 1
        ps.registration = reg
        ps.error = ""
        if reg.registered:
            ps.registered_on = self._fingerprints_now(ps)
        first = len(ps.trials)
        for t in reg.trials:
            ps.trials.append(TrialRecord(t, ps.runs, kind))
        best = first + next((k for k, t in enumerate(reg.trials) if t.index == reg.best_trial), 0)
        label = f"{kind} {ps.runs} ({reg.grade})"
        if reg.registered and reg.intrinsics != ps.intrinsics:
            # The focal length was estimated (a record without one): the pose
            # belongs to that camera, and so must the overlays and projections.
            ps.intrinsics = reg.intrinsics
        if reg.registered and ps is self.current:
            self._push(reg.pose, label, "registration")
        elif reg.registered and pose_if_not_current:
            ps.history.push(reg.pose, label)
            self._pose_edited_by_hand(ps)
        ps.selected_trial = best
        self.trials_changed.emit()
        if ps is self.current:
            self.select_trial(best)
        else:  # registered in the background: only the current photo keeps its pixels
            ps.photo.release()
        return reg

    def _fingerprints_now(self, ps: PhotoState) -> dict:
        """What ``ps.registered_on`` records: the photo file and the model as they are now."""
        return {"photo": wsfiles.file_fingerprint(ps.photo.path), "model": self._mesh_fingerprint}

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
        """The first rule that fires for a trial (default: the selected one), or
        None (always for a manual pose the photo's matches verify)."""
        ps = self.current
        if ps is None or not ps.trials:
            return None
        index = ps.selected_trial if index is None else index
        if index is None:
            return None
        trial = ps.trials[index].trial
        if trial.origin == "manual" and trial.verified:
            # As its hints (manual.score_pose): the next step from a manual
            # pose the photo confirms is a Run from it, not other matching.
            return None
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
        """Set the current photo's reference render; its picks on the old one go.

        Pairs with their own model point (loaded from a file) stay complete:
        they come first, their points shown where they project in the new
        reference; the photo picks of the others wait for new partners.
        """
        ps = self.current
        if ps is None:
            return
        ps.reference, ps.reference_source = reference, source
        xyz = self._pair_xyz(ps)
        own = np.isfinite(xyz).all(axis=1)
        order = np.r_[np.flatnonzero(own), np.flatnonzero(~own)]
        ps.photo_points_px = np.asarray(ps.photo_points_px, float)[order].reshape(-1, 2)
        ps.pair_points_xyz = xyz[order]
        names = self._pair_names(ps)
        ps.pair_names = [names[k] for k in order]
        ps.reference_points_px = _reference_pixels(reference, xyz[own])
        self.reference_changed.emit()
        self.pairs_changed.emit()

    def set_pair_points(self, photo_px: np.ndarray, reference_px: np.ndarray) -> None:
        """Set the current photo's picks (as a view edited them): photo pixels
        (N, 2) and reference pixels (M, 2), (x, y), pair k = point k of each.

        A pair loaded with its own model point keeps it through the edit
        (points added, deleted or dragged on the photo) unless its reference
        point was dragged: it then takes the model point under it. Its name
        stays either way (the same target, picked better).
        """
        ps = self.current
        if ps is None:
            return
        photo = np.asarray(photo_px, float).reshape(-1, 2).copy()
        ref = np.asarray(reference_px, float).reshape(-1, 2).copy()
        rows = _carried_rows(ps.photo_points_px, photo)
        xyz = _rows_of(self._pair_xyz(ps), rows, np.full(3, np.nan))
        m = min(len(ref), len(ps.reference_points_px), len(photo))
        if len(photo) >= len(ps.photo_points_px) and m:
            dragged = np.abs(ref[:m] - ps.reference_points_px[:m]).max(axis=1) > _SAME_PICK_PX
            xyz[:m][dragged] = np.nan
        names = [str(v) for v in _rows_of(np.array(self._pair_names(ps), object), rows, "")]
        ps.photo_points_px, ps.reference_points_px = photo, ref
        ps.pair_points_xyz, ps.pair_names = xyz, names
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
        photo, ref, xyz = ps.photo_points_px, ps.reference_points_px, self._pair_xyz(ps)
        names = self._pair_names(ps)
        if index < len(photo):
            photo, xyz = np.delete(photo, index, axis=0), np.delete(xyz, index, axis=0)
            names = names[:index] + names[index + 1:]
        if index < len(ref):
            ref = np.delete(ref, index, axis=0)
        ps.photo_points_px, ps.reference_points_px, ps.pair_points_xyz = photo, ref, xyz
        ps.pair_names = names
        self.pairs_changed.emit()

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
        """3D points of the complete pairs (N, 3), metres, and whether each has one:
        a pair's own (loaded from a file), else the one under its reference pick."""
        ps = ps if ps is not None else self.current
        _, ref_px = self.pairs(ps)
        if ps is None or ps.reference is None or not len(ref_px):
            return np.full((len(ref_px), 3), np.nan), np.zeros(len(ref_px), bool)
        xyz, valid = ps.reference.lift(ref_px)
        own_xyz = self._pair_xyz(ps)[:len(ref_px)]
        own = np.isfinite(own_xyz).all(axis=1)
        xyz[own], valid = own_xyz[own], valid | own
        return xyz, valid

    def pairs_with_own_point(self, ps: PhotoState | None = None) -> np.ndarray:
        """(N,) bool, one per photo pick: the pair carries its own model point
        (loaded from a file), not the one under its reference pick."""
        ps = ps if ps is not None else self.current
        if ps is None:
            return np.zeros(0, bool)
        return np.isfinite(self._pair_xyz(ps)).all(axis=1)

    @staticmethod
    def _pair_xyz(ps: PhotoState) -> np.ndarray:
        """``ps.pair_points_xyz`` aligned with its photo picks (NaN-padded: a
        workspace saved before pairs carried points has none)."""
        n = len(ps.photo_points_px)
        xyz = np.asarray(ps.pair_points_xyz, float).reshape(-1, 3)[:n]
        return np.vstack([xyz, np.full((n - len(xyz), 3), np.nan)])

    @staticmethod
    def _pair_names(ps: PhotoState) -> list[str]:
        """``ps.pair_names`` aligned with its photo picks ("" for none)."""
        n = len(ps.photo_points_px)
        names = [str(name) for name in ps.pair_names][:n]
        return names + [""] * (n - len(names))

    def rename_pair(self, index: int, name: str) -> None:
        """Name pair ``index`` of the current photo (``GCP12``; "" removes the
        name). The name is saved with the pairs and written by :meth:`save_pairs`.

        Raises
        ------
        WorkbenchError
            No such pair, a name with a line break, or one another pair has
            (a control-point file names each target once).
        """
        ps = self.current
        names = self._pair_names(ps) if ps is not None else []
        if not 0 <= index < len(names):
            raise WorkbenchError(f"There is no pair {index + 1}.")
        name = str(name).strip()
        if "\n" in name or "\r" in name:
            raise WorkbenchError("A pair's name is one line.")
        if name and name in names and names.index(name) != index:
            raise WorkbenchError(f"Pair {names.index(name) + 1} is named {name!r} already.")
        names[index] = name
        ps.pair_names = names
        self.pairs_changed.emit()

    def pair_names(self, ps: PhotoState | None = None) -> list[str]:
        """Each photo pick's name from a control-point file ("" for a clicked one)."""
        ps = ps if ps is not None else self.current
        return [] if ps is None else self._pair_names(ps)

    def load_pairs(self, path: str | os.PathLike) -> int:
        """Replace the current photo's pairs by those of a control-point file.

        Each pair keeps its model point (``x,y,z``, or the CRS's ``easting,
        northing, elevation`` or WGS84 ``latitude, longitude, elevation``
        through the scene's georeference), whether or
        not the reference render shows it; its reference point is where that
        model point projects in the reference. Returns the number of pairs.

        Raises
        ------
        WorkbenchError
            No photo, or no reference render to show the pairs on.
        InputError
            A bad file (:func:`~napari_imgreg.io.control_points.read_control_points`),
            or a photo pixel outside the photo.
        """
        ps, scene = self._photo_and_scene()
        if ps.reference is None:
            raise WorkbenchError("Make a reference render first: loaded pairs are shown on it.")
        points = read_control_points(path)
        points.check_inside(*ps.size)
        xyz = points.model_points_for(scene)
        ps.photo_points_px = points.photo_px.copy()
        ps.pair_points_xyz = xyz
        ps.pair_names = list(points.names)
        ps.reference_points_px = _reference_pixels(ps.reference, xyz)
        self.pairs_changed.emit()
        return len(points)

    def save_pairs(self, path: str | os.PathLike) -> tuple[int, int]:
        """Write the current photo's complete pairs with a model point to a
        control-point file (``x,y,z``, model frame; atomically).

        Returns
        -------
        written, left_out : int
            Pairs written, and complete pairs left out for want of a model
            point (a reference pick off the model).

        Raises
        ------
        WorkbenchError
            No photo, or no pair with a model point.
        """
        ps = self.current
        if ps is None:
            raise WorkbenchError("Load a scene and a photo first.")
        photo_px, _ = self.pairs(ps)
        xyz, valid = self.pair_points_3d(ps)
        if not valid.any():
            raise WorkbenchError("No pair with a point on the model to save.")
        # Names loaded from a file go back out; clicked pairs have none (their
        # numbers in the table change as pairs are deleted: no name to keep).
        names = self._pair_names(ps)
        labels = [names[k] for k in np.flatnonzero(valid)]
        write_control_points(path, photo_px[valid], xyz[valid],
                             labels if any(labels) else None)
        return int(valid.sum()), int((~valid).sum())

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
        ps.registered_on = self._fingerprints_now(ps)
        if trial is not None:
            manual.adopt_pair_uncertainty(trial, solution)
            manual.note_record_offset(trial, ps.prior)
        ps.trials.append(TrialRecord(trial, ps.runs, "Manual"))
        ps.selected_trial = len(ps.trials) - 1
        if ps is self.current:
            self._push(solution.pose, f"manual ({solution.n_inliers} pairs)", "manual")
        self.trials_changed.emit()
        if ps is self.current:
            self.select_trial(ps.selected_trial)
        return solution

    def manual_solution_of_pairs(self, ps: PhotoState | None = None
                                 ) -> manual.ManualSolution | None:
        """The photo's manual solution when it was solved from the pairs it has
        now (its residuals are then theirs to show), else None: pairs edited,
        loaded or cleared since, or no reference render to put them in 3D.

        A pose's pairs are told by their reprojection errors: under the
        solution's camera and pose, each complete pair errs by what the
        solution recorded for it.
        """
        ps = ps if ps is not None else self.current
        sol = ps.manual_solution if ps is not None else None
        if sol is None:
            return None
        photo_px, _ = self.pairs(ps)
        errors = np.asarray(sol.errors_px, float).reshape(-1)
        if len(errors) != len(photo_px) or not len(photo_px):
            return None
        if not sol.ok or sol.pose is None:  # no pose to check against: as many pairs
            return sol
        xyz, valid = self.pair_points_3d(ps)
        if not valid.any():
            return None
        with np.errstate(invalid="ignore"):
            now = np.full(len(photo_px), np.nan)
            now[valid] = np.linalg.norm(
                sol.pose.project(sol.intrinsics, xyz[valid]) - photo_px[valid], axis=1)
        same_nan = np.array_equal(np.isnan(now), np.isnan(errors))
        both = np.isfinite(now) & np.isfinite(errors)
        close = np.allclose(now[both], errors[both], rtol=1e-3, atol=_SAME_RESIDUAL_PX)
        return sol if same_nan and close else None

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

    def unopened_drawings(self) -> str | None:
        """Why a projection must wait, or None: a photo drawn on (or with
        projected features) could not be opened (:attr:`drawn_not_opened`),
        and a projection now would drop its features from the one saved."""
        if not self.drawn_not_opened:
            return None
        name, problem = next(iter(self.drawn_not_opened.items()))
        more = len(self.drawn_not_opened) - 1
        return (f"{name} could not be opened ({problem})"
                + (f", nor {more} other photo(s) drawn on" if more else "")
                + ": a projection now would leave its drawings out"
                + ("; the saved projection is kept" if self.features_3d else "")
                + ". Mend or restore its files, then project again.")

    def projection_job(self) -> Job:
        """Project every photo's interpretations onto the scene, each from its
        current camera and pose; ``apply`` records the features and their
        measurements.

        Raises
        ------
        WorkbenchError
            No scene, nothing drawn, or a photo drawn on could not be opened
            (:attr:`drawn_not_opened`): its features would be dropped from
            the projection saved, so the last one is kept instead.
        """
        scene = self.require_scene()
        unopened = self.unopened_drawings()
        if unopened:
            raise WorkbenchError(unopened)
        drawn = [ps for ps in self.photos if ps.interpretations]
        jobs = [(ps.intrinsics, ps.pose, list(ps.interpretations), ps.name,
                 self.pose_uncertainty(ps)) for ps in drawn]
        if not jobs:
            raise WorkbenchError("Nothing to project: draw on a photo first.")
        # What it is made from, as the job starts (edits while it runs make it out of date).
        projected_from = self.projection_inputs(drawn)
        return Job("projection", lambda: project_interpretation_sets(scene, jobs),
                   lambda value: self.record_projection(*value, projected_from=projected_from),
                   "Projecting interpretations")

    def pose_uncertainty(self, ps: PhotoState) -> PoseUncertainty:
        """The expected error of the photo's current pose, for what is projected from it.

        The estimate of the registration or trial whose pose it is
        (RESULT.json ``uncertainty``); for a manual solve, the pairs' own
        (:func:`~napari_imgreg.registration.manual.pair_uncertainty`); for a
        registration without an estimate, the default derived from its reprojection error;
        for a pose no check verified (a failed registration or trial) or no
        solve produced (the prior, or moved by hand since), the sensor prior's
        default (50 px, 5 m, 3°).
        """
        pose, fx = ps.pose, ps.intrinsics.fx

        def same(other: Pose | None) -> bool:
            return _same_pose(other, pose)

        def of(unc: Uncertainty | None, status: str, metrics: dict) -> PoseUncertainty:
            return PoseUncertainty.from_estimate(unc, status, metrics, fx)

        reg = ps.registration
        if reg is not None and same(reg.pose):
            return of(reg.uncertainty, reg.status, reg.metrics)
        order = ([ps.selected_trial] if ps.selected_trial is not None else []) + list(
            range(len(ps.trials)))
        for k in order:
            if 0 <= k < len(ps.trials) and same(ps.trials[k].trial.pose):
                t = ps.trials[k].trial
                # A manual pose no match verifies has the pairs' own estimate.
                by_pairs = t.uncertainty is not None and t.uncertainty.basis == "control points"
                return of(t.uncertainty, "registered" if t.verified or by_pairs else "failed",
                          t.metrics)
        sol = ps.manual_solution
        if sol is not None and sol.ok and same(sol.pose):
            if sol.uncertainty is not None:
                return of(sol.uncertainty, "registered", {})
            errors = np.asarray(sol.errors_px, np.float64)
            errors = errors[np.asarray(sol.inliers, bool) & np.isfinite(errors)]
            rms = float(np.sqrt(np.mean(errors ** 2))) if errors.size else 2.0
            return of(None, "registered", {"reprojection_error_px": rms})
        return PoseUncertainty.from_result(None, fx)

    def project_interpretations(self) -> list[Feature3D]:
        """Project the interpretations (blocking); see :meth:`projection_job`."""
        return self.projection_job()()

    def record_projection(self, features: list[Feature3D], measurements: list[Measurement],
                          projected_from: dict[PhotoState, str] | None = None) -> list[Feature3D]:
        """Record projected interpretations and their measurements.

        ``projected_from``: per photo projected, :func:`_projection_input` of
        its drawings, camera and pose as the projection started
        (:meth:`projection_job` passes it), so that
        :meth:`projection_out_of_date` can tell. By default, the photos named
        as the features' sources, as they are now.
        """
        self.features_3d, self.measurements = list(features), list(measurements)
        if projected_from is None:
            sources = {f.source for f in self.features_3d}
            projected_from = {ps: _projection_input(ps) for ps in self.photos
                              if ps.interpretations and ps.name in sources}
        self._projected_from = dict(projected_from)
        self.projection_changed.emit()
        return self.features_3d

    def projection_inputs(self, photos: list[PhotoState] | None = None) -> dict[PhotoState, str]:
        """What each photo's projection is made from now (default: every photo
        drawn on), for :meth:`record_projection`'s ``projected_from``: taken
        as a projection starts, so that edits while it runs make it out of date."""
        photos = [ps for ps in self.photos if ps.interpretations] if photos is None else photos
        return {ps: _projection_input(ps) for ps in photos}

    @property
    def projection_inputs_known(self) -> bool:
        """It is known what the last projection was made from (not so for one
        saved before napari-imgreg recorded it): :meth:`projection_out_of_date` can tell."""
        return self._projected_from is not None

    def projection_out_of_date(self) -> list[PhotoState]:
        """The photos whose drawings, camera or pose changed since the last
        projection (drawn on since, or no longer drawn on): what it shows, and
        an export writes, is not what they hold now. Empty when nothing was
        projected, or when it is not known what from (a workspace projected
        before napari-imgreg recorded it)."""
        return [ps for ps in self.photos if self.projection_out_of_date_for(ps)]

    def projection_out_of_date_for(self, ps: PhotoState) -> bool:
        """Whether ``ps`` is among :meth:`projection_out_of_date`."""
        before = self._projected_from
        if not (self.features_3d or self.measurements) or before is None:
            return False
        return bool((ps.interpretations or ps in before)
                    and before.get(ps) != _projection_input(ps))

    # -------------------------------------------------------------- saving
    # ------------------------------------------------------- the campaign
    def photo_status(self, ps: PhotoState) -> str:
        """Where a photo stands: one of :data:`PHOTO_STATUSES`.

        "accepted" (the user accepted its pose), "registered" (the last
        automatic registration verified its pose, or the photo has a manual
        pose whose pairs' expected error is small), "failed" (it was tried
        and did not), "not registered" (never tried).
        """
        if ps.accepted:
            return "accepted"
        reg = ps.registration
        sol = ps.manual_solution
        # A manual pose registers a photo when its pairs' expected error is
        # small, and (after a failed automatic registration, the reason to
        # pick pairs) while the photo has that pose.
        manual_ok = (sol is not None and manual.registers(sol)
                     and (reg is None or _same_pose(sol.pose, ps.pose)))
        if (reg is not None and reg.registered) or manual_ok:
            return "registered"
        if reg is not None or ps.manual_solution is not None or ps.runs or ps.error:
            return "failed"
        return "not registered"

    def photo_summary(self, ps: PhotoState) -> PhotoSummary:
        """What the photos table shows of a photo (see :class:`PhotoSummary`)."""
        reg = ps.registration
        rec = ps.trials[ps.selected_trial] if (ps.selected_trial is not None
                                               and 0 <= ps.selected_trial < len(ps.trials)) else None
        grade, q = "", math.nan
        if reg is not None:
            grade, q = reg.grade, float(reg.q)
        elif rec is not None:
            grade, q = rec.trial.grade, float(rec.trial.q)
        unc = getattr(reg, "uncertainty", None) if reg is not None else None
        reproj = float(unc.reprojection_px) if unc is not None else math.nan
        secs = float(reg.timings_s.get("total", math.nan)) if reg is not None else math.nan
        mapped = self._mapped_by_source().get(ps.name, 0)
        return PhotoSummary(name=ps.name, status=self.photo_status(ps), grade=grade, q=q,
                            reprojection_px=reproj, time_s=secs,
                            attention=self.needs_attention(ps),
                            drawn=len(ps.interpretations), mapped=mapped,
                            mapped_out_of_date=self.projection_out_of_date_for(ps))

    def _mapped_by_source(self) -> dict[str, int]:
        """How many features of the last projection came from each photo (by
        name), counted once per projection: the photos table asks for every
        photo, and counting for each grew with photos × features."""
        features = self.features_3d
        counted = self._mapped_counted
        if counted is None or counted[0] is not features or counted[1] != len(features):
            counts: dict[str, int] = {}
            for f in features:
                counts[f.source] = counts.get(f.source, 0) + 1
            # The list itself is held (its id could be reused by a new one).
            self._mapped_counted = counted = (features, len(features), counts)
        return counted[2]

    def needs_attention(self, ps: PhotoState) -> bool:
        """True while a photo waits for the user: not accepted and not
        registered at grade good or better (never tried, failed, poor or
        fair, or an uncertainty above ``ATTENTION_REPROJECTION_PX``)."""
        if ps.accepted:
            return False
        reg = ps.registration
        if reg is None or not reg.registered:
            return True
        if reg.grade not in GOOD_GRADES:
            return True
        unc = getattr(reg, "uncertainty", None)
        return bool(unc is not None and np.isfinite(unc.reprojection_px)
                    and unc.reprojection_px > ATTENTION_REPROJECTION_PX)

    def next_needing_attention(self, after: int | None = None) -> int | None:
        """The index of the next photo that needs attention after photo
        ``after`` (default: the current one), going round; the photo itself
        last. None when none does."""
        n = len(self.photos)
        if not n:
            return None
        start = self.current_index if after is None else after
        start = -1 if start is None else start
        for step in range(1, n + 1):
            k = (start + step) % n
            if self.needs_attention(self.photos[k]):
                return k
        return None

    def select_next(self, step: int = 1) -> None:
        """Make the next (``step`` 1) or previous (-1) photo current, going round."""
        if not self.photos:
            return
        k = self.current_index
        self.select_photo(0 if k is None else (k + step) % len(self.photos))

    def accept(self, ps: PhotoState | None = None) -> bool:
        """The user accepts the photo's current pose (default: the current
        photo's); it no longer needs attention until its pose changes.
        False without a photo."""
        ps = ps if ps is not None else self.current
        if ps is None:
            return False
        if not ps.accepted:
            ps.accepted = True
            self.accepted_changed.emit(ps)
        return True

    def photos_to_register(self, redo: bool = False) -> list[PhotoState]:
        """The photos Register all works on: those not yet registered (never
        tried, or tried and failed), in order; ``redo`` every photo not accepted."""
        if redo:
            return [ps for ps in self.photos if not ps.accepted]
        return [ps for ps in self.photos if self.photo_status(ps) in ("not registered", "failed")]

    def register_all_job(self, auto: bool = True, redo: bool = False,
                         cancelled: Callable[[], bool] | None = None) -> Job:
        """Register every photo still to register (:meth:`photos_to_register`),
        one after the other, each from its own current pose.

        The job's ``run`` is a generator: it yields
        :class:`~napari_imgreg.registration.pipeline.Progress` (``fraction``
        over the whole batch) and, as each photo ends, a :class:`BatchStep`
        to record where the workspace lives (:meth:`record_batch_step`), so
        each finished photo is recorded and saved before the next one starts.
        Cancelling (``cancelled()`` true) stops within the running photo's
        registration; photos already recorded stay recorded, the running one
        is left as it was, and a new Register all resumes with the rest. It
        returns a :class:`BatchSummary`; ``apply`` returns it unchanged.

        Raises
        ------
        WorkbenchError
            No scene, or feature parameters that do not make a detector.
        """
        scene = self.require_scene()
        try:
            FeatureParams.from_dict(self.params.features.to_dict())
        except (KeyError, ValueError, TypeError) as exc:
            raise WorkbenchError(one_line(exc)) from exc
        todo = self.photos_to_register(redo)
        params = self.params.copy()
        params.auto_adapt = auto
        if not auto:
            params.search_prior = False
            params.max_trials = 1
        # Captured now: the GUI may edit the photos while the batch runs. The
        # pixels are decoded in the worker, one photo at a time: a photo that
        # is not current lets them go when it is done.
        work = [(ps, ps.photo, self.registration_prior(ps)) for ps in todo]
        kind = "Auto" if auto else "Run"
        is_cancelled = cancelled or (lambda: False)

        def run():
            summary = BatchSummary(total=len(work), skipped=len(self.photos) - len(work))
            for k, (ps, photo, prior) in enumerate(work):
                if is_cancelled():
                    summary.cancelled = True
                    return summary
                share = 1.0 / max(len(work), 1)
                try:
                    image = photo.image
                except Exception as exc:  # noqa: BLE001 - e.g. its file is gone since it was read
                    image, reg, error = None, None, one_line(exc)
                if image is not None:
                    steps = pipeline.register_photo(scene, image, prior, params,
                                                    photo_name=ps.name, cancelled=cancelled)
                try:
                    if image is not None:
                        while True:
                            progress = next(steps)
                            yield pipeline.Progress(
                                "register all", (k + float(progress.fraction)) * share,
                                f"{ps.name} ({k + 1}/{len(work)}): {progress.message}")
                except StopIteration as stop:
                    reg, error = stop.value, ""
                except pipeline.Cancelled:
                    summary.cancelled = True
                    return summary
                except Exception as exc:  # noqa: BLE001 - one bad photo does not stop the batch
                    reg, error = None, one_line(exc)
                finally:
                    steps = image = None
                    if ps is not self.current:
                        photo.release()
                summary.done += 1
                if reg is not None and reg.registered:
                    summary.registered += 1
                else:
                    summary.failed.append(f"{ps.name}: {error or 'not registered'}")
                yield BatchStep(ps, reg, error, kind, k, len(work))
            return summary

        return Job("register all", run, lambda summary: summary,
                   f"Registering {len(work)} photo(s)", None)

    def record_batch_step(self, step: BatchStep) -> None:
        """Record one photo's registration of a Register all (its pose becomes
        the photo's when it registered, even when it is not current)."""
        if step.photo not in self.photos:
            return
        if step.registration is not None:
            self.record_registration(step.registration, step.kind, step.photo,
                                     pose_if_not_current=True)
        else:  # it raised: tried and not registered, and why
            step.photo.error = step.error or "its registration stopped with an error"
            self.trials_changed.emit()

    def register_all(self, auto: bool = True, redo: bool = False,
                     cancelled: Callable[[], bool] | None = None,
                     on_progress: Callable | None = None) -> BatchSummary:
        """Register every photo still to register (blocking); see :meth:`register_all_job`."""
        job = self.register_all_job(auto, redo, cancelled)
        steps = job.run()
        try:
            while True:
                item = next(steps)
                if isinstance(item, BatchStep):
                    self.record_batch_step(item)
                elif on_progress is not None:
                    on_progress(item)
        except StopIteration as stop:
            return stop.value
        except pipeline.Cancelled:
            return BatchSummary(cancelled=True)

    def adopt(self, other: Workspace) -> None:
        """Take over the state of another workspace (one just opened from a
        folder, e.g. in a worker), and its folder binding: this workspace is
        then saved there, its views see the new state through its events.

        Whatever folder this workspace was saved into is released first (its
        files stay as they are); ``other`` is left empty and unbound.
        """
        self.detach()
        store, other._store = other._store, None
        if store is not None:
            store.disconnect()
        self.scene, self.terrain = other.scene, other.terrain
        self.scene_files = dict(other.scene_files)
        self.params = other.params
        self.photos, self.current = list(other.photos), None
        self.features_3d, self.measurements = other.features_3d, other.measurements
        self._projected_from = other._projected_from
        self.open_problems = list(other.open_problems)
        self.drawn_not_opened = dict(other.drawn_not_opened)
        self.open_warnings = list(other.open_warnings)
        self._opened_keys = dict(other._opened_keys)
        self._mesh_fingerprint = other._mesh_fingerprint
        current = other.current_index
        other.photos, other.current, other.scene = [], None, None
        # The views follow the events; the folder is bound after them, so that
        # they write nothing (it holds this very state already).
        if self.scene is not None:
            self.scene_changed.emit()
        self.params_changed.emit()
        self.photos_changed.emit()
        if self.photos:
            self.select_photo(current if current is not None else 0)
        self.projection_changed.emit()
        if store is not None:
            store.ws = self
            self._store = store
            store.connect()

    def to_dict(self) -> dict:
        """What a saved workspace will hold (JSON-ready; images and the model
        are referred to by path)."""
        return {
            "scene": dict(self.scene_files),
            "params": self.params.to_dict(),
            "photos": [ps.to_dict() for ps in self.photos],
            "current": self.current_index,
        }

    @property
    def folder(self) -> Path | None:
        """The workspace folder this workspace is saved into (None: not saved)."""
        return None if self._store is None else self._store.folder

    def save(self, folder: str | Path) -> Path:
        """Write the whole workspace into ``folder`` and keep it saved there.

        From then on every change is written as its event is emitted (see
        the module docstring). Saving into another folder later moves the
        binding there ("save as") once that folder is complete; the old
        folder stays as it was, and stays bound when the save fails. Saving
        into the folder it is bound to writes what changed.

        Parameters
        ----------
        folder : path-like
            A new or empty folder, or an existing workspace folder
            (conventionally named ``*.imgreg``).

        Returns
        -------
        Path
            The manifest written.

        Raises
        ------
        InputError
            ``folder`` is a file, or a non-empty folder that is not a workspace.
        OSError
            It cannot be written (nothing already saved there is lost, and
            the workspace stays saved where it was).

        See Also
        --------
        begin_save : the same in steps, for writing in a worker thread.
        """
        folder = Path(folder)
        if self._is_own_folder(folder):
            # Saved there already: what changed is written, nothing is moved.
            self._store.save_all()
            return wsfiles.manifest_path(folder)
        # The old folder stays bound until the new one is complete, so a
        # failure leaves the workspace saved where it was.
        saving = self._save_as(folder)
        saving.write()
        return saving.finish()

    def _is_own_folder(self, folder: Path) -> bool:
        return self.folder is not None and Path(os.path.abspath(folder)) == self.folder

    def begin_save(self, folder: str | Path) -> SaveAs:
        """Start a "save as" whose writing may run in another thread (the
        workbench's worker): :meth:`save` in steps.

        The folder is checked and locked here; the workspace stays saved
        where it was (if anywhere) until :meth:`SaveAs.finish` binds it to
        ``folder``, so a save that fails or is abandoned leaves it as it was.

        Parameters
        ----------
        folder : path-like
            As for :meth:`save`, but not the folder the workspace is saved
            into already (it is saved there as it changes).

        Returns
        -------
        SaveAs
            Call its :meth:`~SaveAs.write` (any thread; the workspace must
            not be edited meanwhile), then :meth:`~SaveAs.finish` or
            :meth:`~SaveAs.abandon` where the workspace lives.

        Raises
        ------
        InputError
            As for :meth:`save`; or ``folder`` is the workspace's own folder,
            or another live workspace of this session saves into it.
        OSError
            The folder cannot be made or locked.
        """
        folder = Path(folder)
        if self._is_own_folder(folder):
            raise input_error(folder, "is where this workspace is saved already: every "
                                      "change is saved there as it happens")
        return self._save_as(folder)

    def _save_as(self, folder: Path) -> SaveAs:
        if folder.exists() and not folder.is_dir():
            raise input_error(folder, "is a file, not a workspace folder")
        if (folder.is_dir() and any(folder.iterdir()) and not wsfiles.is_workspace(folder)):
            raise input_error(
                folder, "is not empty and holds no workspace.json: choose a new folder")
        store = _FolderStore(self, folder)
        store.lock()
        return SaveAs(self, store, folder)

    def flush_manifest(self) -> None:
        """Write the manifest (the parameters edited in place) into the workspace
        folder; nothing happens when it is not saved. A failure is reported
        through ``autosave_failed``."""
        if self._store is not None:
            self._store._guarded(self._store.save_manifest)

    def flush(self) -> None:
        """Write what changed without an event (the parameters edited in place)
        into the workspace folder; nothing happens when it is not saved."""
        if self._store is not None:
            self._store.save_all()

    def detach(self) -> None:
        """Stop saving into the workspace folder (the files stay as they are)
        and let another session open it."""
        if self._store is not None:
            self._store.disconnect()
            self._store.unlock()
            self._store = None

    @classmethod
    def open(cls, folder: str | Path, scene: Scene | None = None,
             terrain: adjust.TerrainMap | None = None, autosave: bool = True) -> Workspace:
        """Read a workspace folder back: scene, photos and everything done to them.

        Parameters
        ----------
        folder : path-like
            Holding ``workspace.json`` (version 1, or version 0, which is
            migrated and written back as version 1 with the old manifest kept
            as ``workspace.v0.json``).
        scene : Scene, optional
            The scene already read (it is not read again); by default the
            manifest's mesh, DEM and georeference are read.
        terrain : TerrainMap, optional
        autosave : bool
            Keep saving changes into ``folder`` (default).

        Returns
        -------
        Workspace
            Photos that could not be read again (moved, corrupt files) are
            listed in ``open_problems``, one line each, and kept in the
            manifest (their files are not touched), so nothing saved is lost.

        Raises
        ------
        InputError
            No workspace there, a corrupt manifest, a version this
            napari-imgreg does not read (one line naming the file and the
            version), a scene file that cannot be read, or (``autosave``)
            another live session saving into the folder (its
            ``workspace.lock``; open it with ``autosave=False`` to read it).
        """
        return _open_workspace(cls, Path(folder), scene, terrain, autosave)


# ============================================================ workspace folder
# The conversion between the state above and the plain dicts of a workspace
# folder (docs/formats.md "Workspace folder"); the files themselves are
# io.workspace_files' (JSON, arrays) and interpret.files' (GeoJSON, CSV).
_CORRESPONDENCE_ARRAYS = ("photo_points", "render_points", "feature_inlier", "lifted",
                          "pose_inlier", "xyz")


def _history_to_dict(history: adjust.PoseHistory) -> dict:
    # adjust.PoseHistory has no accessor for its stacks: read them here, and
    # rebuild them through its public edits (_history_from_dict).
    # The stacks keep R and t only: the attitude of 200 poses is slow to compute
    # at every edit, and Pose.from_dict reads R and t.
    return {"current": history.current.to_dict(), "label": history.label,
            "undo": [{"pose": _pose_rt(p), "label": lab} for p, lab in history._undo],
            "redo": [{"pose": _pose_rt(p), "label": lab} for p, lab in history._redo],
            "limit": history.limit}


def _pose_rt(pose: Pose) -> dict:
    return {"R": pose.R.tolist(), "t": pose.t.tolist()}


def _history_from_dict(d: dict, default: Pose) -> adjust.PoseHistory:
    """A pose history with its undo and redo stacks as saved (``redo``'s last
    entry is the next redo)."""
    undo = [(Pose.from_dict(e["pose"]), str(e.get("label", ""))) for e in d.get("undo") or []]
    redo = [(Pose.from_dict(e["pose"]), str(e.get("label", ""))) for e in d.get("redo") or []]
    current = pose_or_none(d.get("current")) or default
    limit = int(d.get("limit", 200))
    # Push the undo stack, the current pose and the redo stack (next redo
    # first), then undo back to the current pose: the stacks come out as saved.
    chain = undo + [(current, str(d.get("label", "prior")))] + redo[::-1]
    history = adjust.PoseHistory(chain[0][0], limit=max(limit, len(chain)))
    history._current_label = chain[0][1]
    for pose, label in chain[1:]:
        history.push(pose, label)
    for _ in redo:
        history.undo()
    history.limit = limit
    return history


def _prior_to_dict(prior: Prior) -> dict:
    return {"camera": prior.intrinsics.to_dict(), "pose": prior.pose.to_dict(),
            "sigma": prior.sigma.to_dict(), "assumptions": list(prior.assumptions),
            "sun": None if prior.sun is None else np.asarray(prior.sun, float).tolist(),
            "sun_source": prior.sun_source}


def _prior_from_dict(d: dict) -> Prior:
    return Prior(intrinsics=Intrinsics.from_dict(d["camera"]), pose=Pose.from_dict(d["pose"]),
                 sigma=Sigma(**{k: float(v) for k, v in (d.get("sigma") or {}).items()}),
                 assumptions=[str(a) for a in d.get("assumptions") or []],
                 sun=None if d.get("sun") is None else np.asarray(d["sun"], float),
                 sun_source=str(d.get("sun_source", "")))


def _trial_to_dict(trial: Trial) -> dict:
    """RESULT.json's trial, plus its start pose and unrounded time."""
    d = trial.to_dict()
    d["start_pose"] = trial.start_pose.to_dict()
    d["seconds"] = float(trial.seconds)
    return d


def _correspondence_arrays(trials: list[TrialRecord]) -> dict[str, np.ndarray]:
    out = {}
    for k, rec in enumerate(trials):
        corr = rec.trial.correspondences
        if corr is None:
            continue
        for name in _CORRESPONDENCE_ARRAYS:
            value = getattr(corr, name)
            if value is not None:
                out[f"{k}.{name}"] = np.asarray(value)
    return out


def _correspondences_of(arrays: dict[str, np.ndarray], k: int) -> Correspondences | None:
    if f"{k}.photo_points" not in arrays:
        return None
    return Correspondences(**{name: arrays.get(f"{k}.{name}") for name in _CORRESPONDENCE_ARRAYS})


def _manual_to_dict(sol: manual.ManualSolution) -> dict:
    return {"ok": bool(sol.ok), "pose": None if sol.pose is None else sol.pose.to_dict(),
            "camera": sol.intrinsics.to_dict(),
            "errors_px": np.asarray(sol.errors_px, float).tolist(),
            "inliers": np.asarray(sol.inliers, bool).tolist(),
            "threshold_px": float(sol.threshold_px), "focal_solved": bool(sol.focal_solved),
            "method": sol.method, "reason": sol.reason,
            "uncertainty": None if sol.uncertainty is None else sol.uncertainty.to_dict(),
            "warning": sol.warning}


def _manual_from_dict(d: dict) -> manual.ManualSolution:
    return manual.ManualSolution(
        ok=bool(d["ok"]), pose=pose_or_none(d.get("pose")),
        intrinsics=Intrinsics.from_dict(d["camera"]),
        errors_px=np.array([stored_number(v) for v in d.get("errors_px") or []], float),
        inliers=np.array(d.get("inliers") or [], bool),
        threshold_px=float(d.get("threshold_px", 0.0)),
        focal_solved=bool(d.get("focal_solved", False)),
        method=str(d.get("method", "")), reason=str(d.get("reason", "")),
        uncertainty=(Uncertainty.from_dict({"basis": "control points", **d["uncertainty"]})
                     if isinstance(d.get("uncertainty"), dict) else None),
        warning=str(d.get("warning") or ""))


def _xyz_to_list(xyz: np.ndarray) -> list:
    """Pairs' own model points for JSON: NaN (none) as null."""
    return [[None if not math.isfinite(v) else float(v) for v in row]
            for row in np.asarray(xyz, float).reshape(-1, 3)]


def _reference_pixels(reference: RenderResult, xyz: np.ndarray) -> np.ndarray:
    """Where model points (N, 3) show in a reference render, its pixels (N, 2).

    A point behind its camera has no such pixel: it is put just off the
    render's top-left corner (a pick must have a place), and the pair keeps
    its own model point.
    """
    px = reference.cam_from_world.project(reference.intrinsics, np.reshape(xyz, (-1, 3)))
    px[~np.isfinite(px).all(axis=1)] = -1.0
    return px.reshape(-1, 2)


#: Pixels within which a pick is the same pick after a view's edit.
_SAME_PICK_PX = 0.01
#: Pixels within which a pair's reprojection error is the one its manual
#: solution recorded (a reference rendered again lifts the same points).
_SAME_RESIDUAL_PX = 0.02


def _carried_rows(old_photo: np.ndarray, photo: np.ndarray) -> np.ndarray:
    """Which old photo pick each pick is after a view's edit, (N,) int (-1: new).

    An edit adds points at the end, deletes a pair, or drags one point: the
    same count or more keeps the picks in place (the added ones new); fewer
    follows the picks that remain, in order (a subsequence of the old ones).
    """
    n, n_old = len(photo), len(old_photo)
    rows = np.full(n, -1)
    if n >= n_old:
        rows[:n_old] = np.arange(n_old)
        return rows
    i = 0
    for j in range(n):
        while i < n_old and np.abs(old_photo[i] - photo[j]).max() > _SAME_PICK_PX:
            i += 1
        if i == n_old:
            break
        rows[j] = i
        i += 1
    return rows


def _rows_of(values: np.ndarray, rows: np.ndarray, missing) -> np.ndarray:
    """``values[rows]``, with ``missing`` where a row is -1 (a new pick)."""
    out = np.empty((len(rows), *np.shape(values)[1:]), dtype=np.asarray(values).dtype)
    out[...] = missing
    kept = rows >= 0
    out[kept] = np.asarray(values)[rows[kept]]
    return out


def _same_pose(a: Pose | None, b: Pose | None) -> bool:
    """The same pose to a nanoradian and a micrometre (an edit changes it more)."""
    return (a is not None and b is not None
            and np.allclose(a.R, b.R, rtol=0, atol=1e-9) and np.allclose(a.t, b.t, rtol=0, atol=1e-6))


def _sun_estimate_to_dict(est: SunEstimate) -> dict:
    return {f.name: (np.asarray(getattr(est, f.name), float).tolist() if f.name == "direction"
                     else float(getattr(est, f.name))) for f in fields(SunEstimate)}


def _sun_estimate_from_dict(d: dict) -> SunEstimate:
    return SunEstimate(**{f.name: (np.asarray(d[f.name], float) if f.name == "direction"
                                   else stored_number(d.get(f.name))) for f in fields(SunEstimate)})


def _measurement_to_dict(m: Measurement) -> dict:
    return {f.name: (np.asarray(getattr(m, f.name), float).tolist()
                     if isinstance(getattr(m, f.name), np.ndarray) else getattr(m, f.name))
            for f in fields(Measurement)}


def _measurement_from_dict(d: dict) -> Measurement:
    names = {f.name for f in fields(Measurement)}
    kwargs = {k: v for k, v in d.items() if k in names}
    kwargs["centroid"] = np.asarray(d.get("centroid") or [math.nan] * 3, float)
    return Measurement(**kwargs)


def _registration_from_dict(result: dict, extra: dict, ps: PhotoState,
                            source) -> Registration:
    """The photo's last registration from its RESULT.json; its trials are the
    same objects as the photo's trial records when ``extra`` says which."""
    links = extra.get("trials")
    trials = None
    if (isinstance(links, list) and len(links) == len(result.get("trials") or [])
            and all(isinstance(i, int) and 0 <= i < len(ps.trials) for i in links)):
        trials = [ps.trials[i].trial for i in links]
    reg = registration_from_dict(result, ps.prior, source, trials=trials,
                                 assumptions=extra.get("assumptions") or [],
                                 timings_s=extra.get("timings_s"))
    if not reg.photo:
        reg.photo = ps.name
    return reg


def _photo_doc(ps: PhotoState, folder: Path, has_matches: bool) -> dict:
    """A photo's ``photo.json``: everything of it but its trials, result and drawings."""
    reg = ps.registration
    registration = None
    if reg is not None:
        ids = {id(rec.trial): k for k, rec in enumerate(ps.trials)}
        registration = {"result": wsfiles.PHOTO_RESULT,
                        "trials": [ids.get(id(t)) for t in reg.trials],
                        "assumptions": list(reg.assumptions),
                        "timings_s": dict(reg.timings_s)}
    ref = ps.reference
    return {
        "photo": wsfiles.file_ref(ps.photo.path, folder),
        "record": wsfiles.file_ref(ps.record_path, folder),
        "camera": ps.intrinsics.to_dict(),
        "prior": _prior_to_dict(ps.prior),
        "history": _history_to_dict(ps.history),
        "runs": ps.runs,
        "selected_trial": ps.selected_trial,
        "pairs": {"photo_px": np.asarray(ps.photo_points_px, float).tolist(),
                  "reference_px": np.asarray(ps.reference_points_px, float).tolist(),
                  "xyz": _xyz_to_list(ps.pair_points_xyz),
                  "names": list(ps.pair_names),
                  "reference_source": ps.reference_source,
                  "reference_pose": None if ref is None else ref.cam_from_world.to_dict(),
                  "reference_camera": None if ref is None else ref.intrinsics.to_dict()},
        "sun": None if ps.sun_override is None else {
            "direction": np.asarray(ps.sun_override, float).tolist(),
            "source": ps.sun_override_source},
        "sun_estimate": None if ps.sun_estimate is None else _sun_estimate_to_dict(ps.sun_estimate),
        "manual_solution": (None if ps.manual_solution is None
                            else _manual_to_dict(ps.manual_solution)),
        "registration": registration,
        "accepted": bool(ps.accepted),
        "registered_on": ps.registered_on,
        "files": {"trials": wsfiles.PHOTO_TRIALS, "lines": wsfiles.PHOTO_LINES,
                  "correspondences": wsfiles.PHOTO_MATCHES if has_matches else None},
    }


def _fingerprint(ps: PhotoState) -> tuple:
    """What changes when a photo's trials, registration or camera change."""
    return (ps.runs, len(ps.trials), ps.selected_trial, id(ps.registration),
            id(ps.manual_solution), id(ps.intrinsics))


class _FolderStore:
    """Keeps a workspace saved in its folder: each event writes what it changed.

    Every file is written atomically and only when its content changed, so a
    nudge rewrites one small ``photo.json`` and nothing of the other photos;
    the manifest is written after the files it names.
    """

    def __init__(self, ws: Workspace | None, folder: Path, keys: dict | None = None,
                 unavailable: list[dict] | None = None) -> None:
        self.folder = Path(os.path.abspath(folder))
        self._written: dict[Path, str] = {}
        self._manifest_text = ""
        self.bind(ws, keys, unavailable)
        #: Photos written whole by this store (a reopened photo is, at its first change).
        self._saved_once: set[str] = set()
        self._connected: list[tuple[Any, Callable]] = []
        self._release: weakref.finalize | None = None
        #: What a failed save left unwritten (photos, "projection", "manifest"):
        #: the next change writes it first, whichever photo that change is of.
        self._unsaved: dict[Any, None] = {}

    def bind(self, ws: Workspace | None, keys: dict | None = None,
             unavailable: list[dict] | None = None) -> None:
        """The workspace saved, its photos' folder names, the entries kept for
        photos that could not be read."""
        self.ws = ws
        self.keys: dict[PhotoState, str] = dict(keys or {})
        #: The photo folder names in use (see _key); None: not listed yet.
        self._taken: set[str] | None = None
        #: Manifest entries of photos that could not be read when opened: kept.
        self.unavailable: list[dict] = list(unavailable or [])
        #: Their places in the manifest's list (kept there: the campaign keeps its order).
        self.unavailable_at: list[int] = []
        self.fingerprints: dict[PhotoState, tuple] = {ps: _fingerprint(ps) for ps in self.keys}

    # --------------------------------------------------------------- lock
    def lock(self) -> None:
        """Take the folder's lock: one session saves into a folder at a time
        (a second one would overwrite the first's photos with its own)."""
        key = str(self.folder)
        if _BOUND.get(key) not in (None, self):
            gc.collect()  # a workspace nobody holds any more may still be bound
            if _BOUND.get(key) not in (None, self):
                raise input_error(self.folder, "is already open in this session (another "
                                               "Workspace saves into it): detach it first")
        self.folder.mkdir(parents=True, exist_ok=True)
        token = wsfiles.acquire_lock(self.folder, own_stale=True)
        _BOUND[key] = self
        # Released by detach, or when the workspace is collected or Python exits.
        self._release = weakref.finalize(self, wsfiles.release_lock, self.folder, token)

    def unlock(self) -> None:
        if self._release is not None:
            self._release()
            self._release = None
        if _BOUND.get(str(self.folder)) is self:
            del _BOUND[str(self.folder)]

    # ------------------------------------------------------------- events
    def connect(self) -> None:
        for signal, slot in self.signals():
            signal.connect(slot)
            self._connected.append((signal, slot))

    def disconnect(self) -> None:
        for signal, slot in self._connected:
            signal.disconnect(slot)
        self._connected.clear()

    def _guarded(self, action: Callable[[], None]) -> None:
        # An autosave that fails (disk full, folder gone) must not break the
        # edit that triggered it: it is said in one line, the next change retries.
        failed = None
        # What earlier saves left unwritten first; the change's own save even if that fails
        # (each save marks what it did not finish, for the next change to write).
        for step in (self._save_unsaved, action):
            try:
                step()
            except (OSError, InputError, TypeError, ValueError) as exc:
                failed = failed or exc
        if failed is not None:
            # The manifest is written after the files it names: it waited too.
            self._unsaved["manifest"] = None
            message = one_line(failed)
            if isinstance(failed, OSError) and not failed.filename \
                    and not isinstance(failed, OutputError):  # which names its file
                message = f"{self.folder}: {message}"
            self.ws.autosave_failed.emit(message)

    def _save_unsaved(self) -> None:
        """Write what earlier saves failed to write (a drawing on another photo
        than the next change's, a projection), before the next change's files."""
        for item in list(self._unsaved):
            if isinstance(item, PhotoState):
                if item in self.ws.photos:
                    self.save_photo(item)
                else:
                    self._unsaved.pop(item, None)
            elif item == "projection":
                self.save_projection()
        if "manifest" in self._unsaved:
            self.save_manifest()

    def _on_scene(self, *_) -> None:
        # A new scene clears the photos: their folders stay on disk, unlisted.
        self.unavailable, self.keys, self.fingerprints = [], {}, {}
        self.unavailable_at = []
        self._taken = None
        self._guarded(self.save_manifest)

    def _on_photos(self, *_) -> None:
        def save():
            for ps in self.ws.photos:
                if ps not in self.keys:
                    self.save_photo(ps)
            self.save_manifest()
        self._guarded(save)

    def _on_manifest(self, *_) -> None:
        self._guarded(self.save_manifest)

    def _on_projection(self, *_) -> None:
        def save():
            self.save_projection()
            self.save_manifest()
        self._guarded(save)

    def _on_current(self, *_) -> None:
        # A pose, a pick, a selection: the photo's photo.json only.
        if self.ws.current is not None:
            self._guarded(lambda: self.save_photo(self.ws.current, ("state",)))

    def _on_photo(self, ps=None, *_) -> None:
        # A sun (photo.json) or a drawing (LINES.geojson).
        if isinstance(ps, PhotoState):
            self._guarded(lambda: self.save_photo(ps, ("lines", "state")))

    def _on_accepted(self, ps=None, *_) -> None:
        if isinstance(ps, PhotoState):
            self._guarded(lambda: self.save_photo(ps, ("state",)))

    def _on_trials(self, *_) -> None:
        # trials_changed does not say which photo: the ones whose trials changed.
        def save():
            for ps in self.ws.photos:
                if ps is self.ws.current or self.fingerprints.get(ps) != _fingerprint(ps):
                    self.save_photo(ps)
        self._guarded(save)

    # ------------------------------------------------------------ writing
    def _key(self, ps: PhotoState) -> str:
        key = self.keys.get(ps)
        if key is None:
            if self._taken is None:
                # Listed once, then grown with each key given: listing the
                # folder for every new photo grew with the square of the photos.
                self._taken = set(self.keys.values()) | {e.get("key", "")
                                                         for e in self.unavailable}
                photos_dir = self.folder / wsfiles.PHOTOS_DIR
                if photos_dir.is_dir():  # never reuse another photo's folder, even an orphan
                    self._taken |= {p.name for p in photos_dir.iterdir()}
            key = wsfiles.photo_key(ps.photo.path or ps.name, self._taken)  # (added to it)
            self.keys[ps] = key
        return key

    def _changed(self, path: Path, text: str) -> bool:
        return self._written.get(path) != text

    def _write(self, path: Path, text: str) -> None:
        wsfiles.write_text(path, text)
        self._written[path] = text

    def save_photo(self, ps: PhotoState,
                   parts: tuple[str, ...] = ("trials", "result", "lines", "state")) -> None:
        """Write one photo's files that changed: correspondences, trials,
        RESULT.json and drawings first, its ``photo.json`` last.

        ``parts`` names the files an event can have changed (the others are
        not even serialised: a nudge must stay quick); all of them when the
        photo's trials, registration or camera changed since the last write.
        """
        self._unsaved[ps] = None  # until every file of it is written
        key = self._key(ps)
        folder = self.folder / wsfiles.PHOTOS_DIR / key
        if self.fingerprints.get(ps) != _fingerprint(ps) or key not in self._saved_once:
            parts = ("trials", "result", "lines", "state")
        has_matches = any(rec.trial.correspondences is not None for rec in ps.trials)
        if "trials" in parts:
            path = folder / wsfiles.PHOTO_TRIALS
            text = wsfiles.json_text(
                {"trials": [{"run": r.run, "kind": r.kind, "trial": _trial_to_dict(r.trial)}
                            for r in ps.trials]}, compact=True)
            if self._changed(path, text):
                if has_matches:
                    wsfiles.write_arrays(folder / wsfiles.PHOTO_MATCHES,
                                         _correspondence_arrays(ps.trials))
                self._write(path, text)
        if "result" in parts and ps.registration is not None:
            path = folder / wsfiles.PHOTO_RESULT
            text = wsfiles.json_text(ps.registration.to_dict())
            if self._changed(path, text):
                self._write(path, text)
        if "lines" in parts:
            path = folder / wsfiles.PHOTO_LINES
            text = wsfiles.json_text(
                interpret_files.interpretations_to_geojson(ps.interpretations), compact=True)
            if self._changed(path, text):
                interpret_files.write_interpretations(path, ps.interpretations)
                self._written[path] = text
        if "state" in parts:
            path = folder / wsfiles.PHOTO_STATE
            text = wsfiles.json_text(_photo_doc(ps, self.folder, has_matches), compact=True)
            if self._changed(path, text):
                self._write(path, text)
        self.fingerprints[ps] = _fingerprint(ps)
        self._saved_once.add(key)
        self._unsaved.pop(ps, None)

    def save_projection(self) -> None:
        self._unsaved["projection"] = None  # until its three files are written
        ws = self.ws
        georef = ws.scene.georef if ws.scene is not None else None
        interpret_files.write_features_geojson(self.folder / wsfiles.FEATURES_3D,
                                               ws.features_3d, georef)
        interpret_files.write_measurements_csv(self.folder / wsfiles.MEASUREMENTS,
                                               ws.measurements)
        wsfiles.write_json(self.folder / wsfiles.MEASUREMENTS_JSON,
                           {"measurements": [_measurement_to_dict(m) for m in ws.measurements]})
        self._unsaved.pop("projection", None)

    def manifest(self) -> dict:
        ws = self.ws
        entries = [{"key": self._key(ps), "photo": wsfiles.file_ref(ps.photo.path, self.folder)}
                   for ps in ws.photos]
        projected = bool(ws.features_3d or ws.measurements)
        return {
            "format": wsfiles.FORMAT,
            "version": wsfiles.VERSION,
            "software": f"napari-imgreg {_version()}",
            "scene": {name: wsfiles.file_ref(path, self.folder) if path else None
                      for name, path in ws.scene_files.items()},
            "params": ws.params.to_dict(),
            "photos": self._with_unavailable(entries),
            "current": None if ws.current is None else self._key(ws.current),
            "projection": None if not projected else {
                "features": wsfiles.FEATURES_3D, "measurements": wsfiles.MEASUREMENTS,
                "measurements_exact": wsfiles.MEASUREMENTS_JSON,
                "n_features": len(ws.features_3d), "n_measurements": len(ws.measurements),
                # Per photo key, what it was projected from (see Workspace.projection_out_of_date).
                "projected_from": None if ws._projected_from is None else {
                    self._key(ps): digest for ps, digest in ws._projected_from.items()
                    if ps in ws.photos}},
        }

    def _with_unavailable(self, entries: list[dict]) -> list[dict]:
        """The manifest's photo entries: the photos read, with those that could
        not be read back at their places (photos are only ever appended)."""
        entries = list(entries)
        if len(self.unavailable_at) != len(self.unavailable):
            return entries + self.unavailable
        for at, entry in sorted(zip(self.unavailable_at, self.unavailable), key=lambda p: p[0]):
            entries.insert(min(at, len(entries)), entry)
        return entries

    def save_manifest(self) -> None:
        """Write ``workspace.json`` (when its content changed), atomically."""
        doc = self.manifest()
        text = wsfiles.json_text(doc)
        if text != self._manifest_text:
            wsfiles.write_json(wsfiles.manifest_path(self.folder),
                               {**doc, "saved": wsfiles.utc_now()})
            self._manifest_text = text
        self._unsaved.pop("manifest", None)

    def save_all(self) -> None:
        """Every photo, the projection, then the manifest."""
        for _ in self.saving_all():
            pass

    def saving_all(self) -> Iterator[int]:
        """:meth:`save_all`, yielding the number of photos written after each."""
        photos = list(self.ws.photos)
        for done, ps in enumerate(photos, 1):
            self.save_photo(ps)
            yield done
        if self.ws.features_3d or self.ws.measurements:
            self.save_projection()
        self.save_manifest()

    def signals(self) -> list[tuple[Any, Callable]]:
        """The workspace's events and what each writes (see :meth:`connect`)."""
        ws = self.ws
        return [(ws.scene_changed, self._on_scene), (ws.photos_changed, self._on_photos),
                (ws.photo_changed, self._on_manifest), (ws.params_changed, self._on_manifest),
                (ws.projection_changed, self._on_projection),
                (ws.pose_changed, self._on_current), (ws.pairs_changed, self._on_current),
                (ws.reference_changed, self._on_current), (ws.trial_selected, self._on_current),
                (ws.sun_changed, self._on_photo), (ws.interpretations_changed, self._on_photo),
                (ws.accepted_changed, self._on_accepted), (ws.trials_changed, self._on_trials)]


#: The folders saved into by a live store of this process.
_BOUND: weakref.WeakValueDictionary[str, _FolderStore] = weakref.WeakValueDictionary()


class SaveAs:
    """A "save as" of a workspace in steps (:meth:`Workspace.begin_save`):
    the folder is locked, :meth:`write` writes everything, :meth:`finish`
    binds the workspace to it (or :meth:`abandon` lets it go).

    :meth:`write` may run in a worker thread, the others where the workspace
    lives. The workspace must not be edited while :meth:`write` reads it (the
    workbench holds its window and its jobs' results meanwhile); an edit that
    happens all the same is written by :meth:`finish`, which then saves
    again every file that differs from what was written.

    Attributes
    ----------
    folder : Path
        The folder written into (absolute).
    total : int
        The photos to write.
    """

    def __init__(self, ws: Workspace, store: _FolderStore, asked: Path) -> None:
        self.ws, self._store = ws, store
        self.folder = store.folder
        self._asked = asked  # as the caller named it: the manifest returned is named so
        self.total = len(ws.photos)
        self._written = False
        self._over = False
        #: Set by an event of the workspace during the write: an edit it may have missed.
        self.edited_meanwhile = False
        self._listening = [(signal, self._on_edit) for signal, _slot in store.signals()]
        for signal, slot in self._listening:
            signal.connect(slot)

    def _on_edit(self, *_) -> None:
        self.edited_meanwhile = True

    def _stop_listening(self) -> None:
        for signal, slot in self._listening:
            signal.disconnect(slot)
        self._listening = []

    def steps(self) -> Iterator[tuple[int, int]]:
        """Write every photo, the projection, then the manifest (as
        :meth:`Workspace.save` does), yielding (photos written, total) after
        each photo. When it raises (or is not run to its end), call
        :meth:`abandon` where the workspace lives."""
        if self._over:
            raise RuntimeError("this save is over")
        for done in self._store.saving_all():
            yield done, self.total
        self._written = True

    def write(self, on_progress: Callable[[int, int], None] | None = None) -> None:
        """Run :meth:`steps` to the end, calling ``on_progress(done, total)``
        after each photo; the folder is let go when it fails."""
        try:
            for done, total in self.steps():
                if on_progress is not None:
                    on_progress(done, total)
        except BaseException:
            self.abandon()
            raise

    def finish(self) -> Path:
        """Bind the workspace to the folder written (releasing the folder it was
        saved into): every later change is saved there. Returns the manifest."""
        if not self._written or self._over:
            raise RuntimeError("finish() follows a complete write()")
        self._over = True
        self._stop_listening()
        ws, store = self.ws, self._store
        ws.detach()
        ws._store = store
        store.connect()
        if self.edited_meanwhile:
            # Something changed the workspace while the files were written (it
            # should not have): every file that differs is written again now.
            store.fingerprints.clear()
            store._guarded(store.save_all)
        return wsfiles.manifest_path(self._asked)

    def abandon(self) -> None:
        """Let the folder go (what was written stays); the workspace stays
        saved where it was. Nothing happens once finished."""
        if self._over:
            return
        self._over = True
        self._stop_listening()
        self._store.unlock()


def _version() -> str:
    from . import __version__

    return __version__


# ---------------------------------------------------------------- opening
def _read_photo(folder: Path, entry: dict, inline: dict | None,
                scene: Scene) -> PhotoState:
    """One photo of a workspace folder (``inline``: a migrated version-0 photo)."""
    key = str(entry.get("key", ""))
    here = folder / wsfiles.PHOTOS_DIR / key
    if inline is not None:
        state, trial_dicts, matches = inline["state"], inline["trials"], {}
        source = wsfiles.manifest_path(folder)
    else:
        if not key:
            raise input_error(wsfiles.manifest_path(folder), "a photo entry without a 'key'")
        source = here / wsfiles.PHOTO_STATE
        state = wsfiles.read_json_file(source)
        files = state.get("files") or {}
        trials_path = here / wsfiles.PHOTO_TRIALS
        trial_dicts = (wsfiles.read_json_file(trials_path).get("trials") or []
                       if trials_path.exists() else [])
        matches = (wsfiles.read_arrays(here / wsfiles.PHOTO_MATCHES)
                   if files.get("correspondences") else {})
    photo_path = wsfiles.resolve_ref(state.get("photo") or entry.get("photo"), folder)
    photo = load_photo(photo_path)
    prior = _prior_from_dict(state["prior"]) if state.get("prior") else prior_for_photo(photo, scene)
    record = wsfiles.resolve_ref(state.get("record"), folder) or photo.sidecar
    intrinsics = Intrinsics.from_dict(state["camera"]) if state.get("camera") else prior.intrinsics
    history = _history_from_dict(state.get("history") or {}, prior.pose)
    trials = []
    for k, rec in enumerate(trial_dicts):
        trial = trial_from_dict(rec["trial"], source, prior.pose, _correspondences_of(matches, k))
        trials.append(TrialRecord(trial, int(rec.get("run", 0)), str(rec.get("kind", "Run"))))
    ps = PhotoState(photo=photo, prior=prior, record_path=record, intrinsics=intrinsics,
                    history=history, trials=trials, runs=int(state.get("runs", 0)))
    selected = state.get("selected_trial")
    if isinstance(selected, int) and trials:
        ps.selected_trial = min(max(selected, 0), len(trials) - 1)
    pairs = state.get("pairs") or {}
    ps.photo_points_px = np.asarray(pairs.get("photo_px") or [], float).reshape(-1, 2)
    ps.reference_points_px = np.asarray(pairs.get("reference_px") or [], float).reshape(-1, 2)
    ps.pair_points_xyz = np.array([[math.nan if v is None else v for v in row]
                                   for row in pairs.get("xyz") or []], float).reshape(-1, 3)
    ps.pair_names = [str(name) for name in pairs.get("names") or []]
    ps.reference_source = str(pairs.get("reference_source", ""))
    if pairs.get("reference_pose"):
        # Renders are not kept: the reference is rendered again from its camera.
        camera = pairs.get("reference_camera")
        ps.reference = render(scene, Intrinsics.from_dict(camera) if camera else intrinsics,
                              Pose.from_dict(pairs["reference_pose"]))
    sun = state.get("sun")
    if sun:
        ps.sun_override = np.asarray(sun["direction"], float)
        ps.sun_override_source = str(sun.get("source", ""))
    if state.get("sun_estimate"):
        ps.sun_estimate = _sun_estimate_from_dict(state["sun_estimate"])
    if state.get("manual_solution"):
        ps.manual_solution = _manual_from_dict(state["manual_solution"])
    # Only a JSON true accepts: a hand-written "no" or "false" is a string, and truthy.
    ps.accepted = state.get("accepted", False) is True
    if isinstance(state.get("registered_on"), dict):
        ps.registered_on = state["registered_on"]
    registration = state.get("registration")
    if registration and inline is None:
        result = wsfiles.read_json_file(here / registration.get("result", wsfiles.PHOTO_RESULT))
        ps.registration = _registration_from_dict(result, registration, ps,
                                                  here / wsfiles.PHOTO_RESULT)
    if inline is not None:
        ps.interpretations = [Interpretation(i["geometry"], i["pixels"], i.get("properties") or {})
                              for i in inline["interpretations"]]
    elif (here / wsfiles.PHOTO_LINES).exists():
        ps.interpretations = interpret_files.read_interpretations(here / wsfiles.PHOTO_LINES)
        for item in ps.interpretations:
            # The GeoJSON writer fills in each label's colour: not a choice the user made.
            if item.properties.get("color") == label_color(item.label, None):
                del item.properties["color"]
    return ps


def _photo_file_name(folder: Path, entry: dict) -> str:
    """The file name of a manifest entry's photo (what its features name as
    their source), else its folder name."""
    try:
        path = wsfiles.resolve_ref(entry.get("photo"), folder)
    except InputError:
        path = None
    return path.name if path is not None else str(entry.get("key") or "photo")


def _drawn_on(folder: Path, entry: dict, inline: dict | None) -> bool:
    """Whether a photo that could not be opened holds drawings (its
    ``LINES.geojson``; ``inline``: a migrated version-0 photo's); a file that
    cannot be read counts as drawn, as it may be."""
    if inline is not None:
        return bool(inline.get("interpretations"))
    lines = folder / wsfiles.PHOTOS_DIR / str(entry.get("key", "")) / wsfiles.PHOTO_LINES
    try:
        return lines.exists() and bool(interpret_files.read_interpretations(lines))
    except (InputError, OSError):
        return True


def _changed_since_registered(ws: Workspace) -> list[str]:
    """One line per photo file, and one for the model, replaced since a photo
    was registered on it: its pose may no longer fit, and nothing else would say so."""
    lines, on_old_model, difference = [], [], ""
    for ps in ws.photos:
        saved = ps.registered_on or {}
        changed = wsfiles.fingerprint_difference(
            saved.get("photo"), wsfiles.file_fingerprint(ps.photo.path))
        if changed:
            lines.append(f"{ps.name}: the photo file {ps.photo.path} has changed since it was "
                         f"registered ({changed}): its pose may not fit it; register it again")
        model_changed = wsfiles.fingerprint_difference(saved.get("model"), ws._mesh_fingerprint)
        if model_changed:
            on_old_model.append(ps.name)
            difference = model_changed
    if on_old_model:
        names = ", ".join(on_old_model[:5]) + (", ..." if len(on_old_model) > 5 else "")
        mesh = Path(ws.scene_files.get("mesh", "")).name
        lines.insert(0, f"the model {mesh} has changed since {len(on_old_model)} photo(s) were "
                        f"registered on it ({names}; {difference}): their poses, and what was "
                        "projected with them, may not fit it; register them again (Register "
                        "all with 'redo registered', or 'workspace register --redo')")
    return lines


#: Drawing properties left out of :func:`_projection_input`: how a line is shown,
#: not what it measures.
_NOT_PROJECTED = frozenset({"color"})


def _projection_input(ps: PhotoState) -> str:
    """A digest of what a photo's projection is made from: its drawings, its
    camera and its pose (equal digests: projecting it again gives the same).

    A drawing counts as it is saved (``LINES.geojson``), so that a workspace
    opened again matches what it recorded: its kind, its pixels to the saved
    precision (a line drawn in napari has more digits), and its properties
    but the colour. The label, note, units, contact and id all reach the
    projected features and measurements (the label and contact choose which
    traces are measured together); the colour only shows them, and is no
    stable part of a drawing either: napari's layer gives every line its
    label's colour, the saved file fills it in, reading it back drops it.
    Properties count whatever their order.
    """
    drawn = [(item.geometry,
              np.round(np.asarray(item.pixels, float), interpret_files.PIXEL_DECIMALS).tolist(),
              {k: v for k, v in sorted(item.properties.items()) if k not in _NOT_PROJECTED})
             for item in ps.interpretations]
    text = wsfiles.json_text([ps.pose.R.tolist(), ps.pose.t.tolist(), ps.intrinsics.to_dict(),
                              drawn], compact=True)
    return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()


def _open_workspace(cls, folder: Path, scene: Scene | None,
                    terrain: adjust.TerrainMap | None, autosave: bool) -> Workspace:
    folder = Path(os.path.abspath(folder))
    data, version = wsfiles.read_manifest(folder)
    store = None
    if autosave:  # refused at once when another session saves into the folder
        store = _FolderStore(None, folder)
        store.lock()
    try:
        return _read_workspace(cls, folder, data, version, scene, terrain, store)
    except BaseException:
        if store is not None:
            store.unlock()
        raise


def _read_workspace(cls, folder: Path, data: dict, version: int, scene: Scene | None,
                    terrain: adjust.TerrainMap | None, store: _FolderStore | None) -> Workspace:
    manifest_path = wsfiles.manifest_path(folder)
    migrated = None
    if version == 0:
        manifest, migrated = wsfiles.migrate_v0(data, folder)
        current = manifest.get("current")
        if isinstance(current, int) and 0 <= current < len(manifest["photos"]):
            manifest["current"] = manifest["photos"][current]["key"]
    else:
        manifest = data
    entries = manifest.get("photos")
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        raise input_error(manifest_path, "'photos' must be a list of objects")
    params = RegistrationParams.from_dict(manifest.get("params") or {}, manifest_path)
    scene_refs = manifest.get("scene") or {}
    files = {name: wsfiles.resolve_ref(ref, folder) for name, ref in scene_refs.items()}
    for name, path in files.items():
        if scene is None and path is not None and not path.exists():
            # A workspace moved or copied without its model: say where it was looked for.
            ref = scene_refs[name]
            tried = dict.fromkeys([str(path)] + ([str(ref["absolute"])] if isinstance(ref, dict)
                                                 and ref.get("absolute") else []))
            raise input_error(manifest_path, f"the {name} file is not found (looked for "
                                             f"{' and '.join(tried)}): put it back there, or "
                                             f"set scene.{name}.path in this file")
    if scene is None and files.get("mesh"):
        scene, terrain = read_scene(files["mesh"], files.get("dem"), files.get("georef"))
    elif scene is None and entries:
        raise input_error(manifest_path, "the workspace has photos but names no model (scene.mesh)")
    ws = cls(params)
    if scene is not None:  # (a workspace saved before any model was opened has none)
        ws.load_scene(scene, terrain, files)

    keys, unavailable, unavailable_at, problems, not_read = {}, [], [], [], []
    for k, entry in enumerate(entries):
        try:
            ps = _read_photo(folder, entry, None if migrated is None else migrated[k], scene)
        except (InputError, OSError, KeyError, TypeError, ValueError, AttributeError) as exc:
            name = entry.get("key") or f"photo {k + 1}"
            if isinstance(exc, (InputError, OSError)):  # they name their file
                problems.append(f"{name}: {one_line(exc)}")
            else:  # a field of the wrong type (a hand edit): say where its files are
                here = folder / wsfiles.PHOTOS_DIR / str(entry.get("key", ""))
                problems.append(f"{name}: {here}: a file there holds a field this "
                                f"napari-imgreg cannot read ({one_line(exc)})")
            unavailable.append(entry)
            unavailable_at.append(k)
            not_read.append((entry, None if migrated is None else migrated[k], problems[-1]))
            continue
        keys[ps] = str(entry.get("key", ""))
    ws.photos = list(keys)
    ws.open_warnings = _changed_since_registered(ws)
    ws._opened_keys = dict(keys)
    projection = manifest.get("projection")
    if projection:
        try:
            ws.features_3d, _ = interpret_files.read_features_geojson(
                folder / projection.get("features", wsfiles.FEATURES_3D))
            exact = wsfiles.read_json_file(
                folder / projection.get("measurements_exact", wsfiles.MEASUREMENTS_JSON))
            ws.measurements = [_measurement_from_dict(m) for m in exact.get("measurements") or []]
            projected_from = projection.get("projected_from")
            if isinstance(projected_from, dict):
                ws._projected_from = {ps: str(projected_from[key]) for ps, key in keys.items()
                                      if key in projected_from}
        except (InputError, OSError, KeyError, TypeError, ValueError) as exc:
            ws.features_3d, ws.measurements = [], []
            problems.append(f"projected interpretations: {one_line(exc)}")
    # After the projection is read: a damaged one is a problem to report too.
    ws.open_problems = problems + ws.open_warnings
    sources = {f.source for f in ws.features_3d}
    for entry, inline, problem in not_read:
        name = _photo_file_name(folder, entry)
        if name in sources or _drawn_on(folder, entry, inline):
            ws.drawn_not_opened[name] = problem
    ws.photos_changed.emit()
    current = manifest.get("current")
    index = next((i for i, ps in enumerate(ws.photos) if keys[ps] == current), 0)
    if ws.photos:
        ws.select_photo(index)

    if store is None:
        return ws
    store.bind(ws, keys, unavailable if migrated is None else [])
    store.unavailable_at = unavailable_at if migrated is None else []
    if migrated is not None:
        # The old single file is kept beside the new layout, then replaced.
        backup = folder / wsfiles.V0_BACKUP
        if not backup.exists():
            wsfiles.write_text(backup, manifest_path.read_text(encoding="utf-8"))
        store.save_all()
    ws._store = store
    store.connect()
    return ws
