"""Register many photos of one scene at once, on a Dask distributed cluster.

The command line's ``batch`` and ``workspace register`` hand their photos to
:class:`PhotoRunner`: by default a local cluster of worker processes on this
machine, or the workers of an existing scheduler (a lab server, SLURM through
dask-jobqueue, Kubernetes through dask-kubernetes; ``docs/batch.md``).

- **One scene per worker.** A worker loads the scene and builds its ray
  engine once, at its first photo, and keeps it (:func:`cached_scene`, keyed
  by the scene files' paths, sizes and modification times), so a photo task
  costs only its own registration.
- **Photos are tasks.** Each task reads its photo and sensor record, builds
  the prior, registers and (``batch``) writes its RESULT.json atomically
  from the worker that ran it; the client only collects the small outcome
  and writes the summary.
- **A worker that dies** (killed, out of memory, a crash in a native
  library) has its photo rescheduled on another worker by the scheduler; a
  photo that has been on ``allowed_failures + 1`` dying workers is given up
  and reported (Dask's ``KilledWorker``), not retried forever; two photos
  given up while in flight together are each tried once more alone first
  (one may only have waited behind the other). Errors raised
  *by* a photo (bad input, a failed registration) are deterministic and are
  returned as the photo's outcome, never retried.
- **Threads are pinned** per worker to ``threads_per_worker``: OpenCV
  (``cv2.setNumThreads``), the package's ray-cast pool
  (``NAPARI_IMGREG_THREADS``) and BLAS/OpenMP (``OMP_NUM_THREADS`` and
  friends, set before a local worker process starts), so N workers × M
  threads never ask for more than N × M cores. Embree's own thread pool is
  used only while the ray engine's BVH is built, once per worker.

``workers=0`` runs the same tasks one after the other in this process,
without Dask: for a scene too large to load once per worker, for a debugger,
or where worker processes cannot start.
"""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import functools
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .._allocator import allocator_environment, tune_allocator
from .._atomic import OutputError, atomic_write
from .._json import dumps as strict_dumps
from ..errors import InputError, input_error
from ..io.photos import Photo, load_photo
from ..prior import check_photo_size, prior_for_photo
from ..scene import Scene
from . import pipeline

try:  # the plugin class must live at module level to be sent to workers by reference
    from distributed.diagnostics.plugin import WorkerPlugin
except ImportError:  # pragma: no cover - distributed is a dependency
    WorkerPlugin = object  # type: ignore[misc,assignment]

__all__ = [
    "ClusterParams", "SceneSpec", "PhotoRunner", "cached_scene", "register_photo_file",
    "check_photo_size",
    "register_prior", "default_workers", "worker_environment", "available_cores", "THREAD_ENV_VARS",
]

log = logging.getLogger(__name__)

#: Environment variables that size the native thread pools of a worker
#: process (BLAS, OpenMP, OpenCV's parallel backend, our ray casts).
THREAD_ENV_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                   "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS", "OPENCV_FOR_THREADS_NUM",
                   "NAPARI_IMGREG_THREADS")


def available_cores() -> int:
    """The cores this process may use (CPU affinity and cgroup quota included)."""
    try:
        from dask.system import CPU_COUNT

        return max(1, int(CPU_COUNT))
    except ImportError:  # pragma: no cover - dask is a dependency
        return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
                   else os.cpu_count() or 1)


def default_workers(threads_per_worker: int, n_tasks: int | None = None) -> int:
    """Worker processes of a local cluster: one per ``threads_per_worker`` cores,
    never more than there are photos to register (each worker loads the scene)."""
    n = max(1, available_cores() // max(1, threads_per_worker))
    return max(1, min(n, n_tasks)) if n_tasks else n


@dataclass
class ClusterParams:
    """Where and how wide the photos are registered.

    Attributes
    ----------
    workers : int or None
        Local cluster: worker processes. ``None`` (default): one per core
        divided by ``threads_per_worker``, at most one per photo to register.
        ``0``: no cluster, the photos one after the other in this process.
        Range 0-1024; ignored with ``scheduler``.
    threads_per_worker : int or None
        Local cluster: threads of each worker, and the size of its OpenCV,
        BLAS and ray-cast pools. ``None`` (default): 1 — registration is
        mostly Python-level work between native calls, so processes scale
        better than threads. Range 1-256; with ``scheduler`` the workers'
        own ``--nthreads`` applies (their pools are pinned to it).
    scheduler : str or None
        Address of a running Dask scheduler (``tcp://host:8786``) or a
        scheduler file (``scheduler.json``); ``None``: a local cluster.
    allowed_failures : int
        How many dying workers a photo may take with it before it is given up
        and reported (Dask's ``distributed.scheduler.allowed-failures``;
        applied to local clusters, an existing scheduler keeps its own).
        Range 0-100; default 2: a photo is tried on at most three workers.
    processes : bool
        Local cluster: workers as processes (default). ``False``: threads of
        this process (no start-up cost, but one GIL; for tests and
        debugging).
    connect_timeout_s : float
        How long to wait for ``scheduler`` to answer, and for Dask's client to
        reconnect when the connection drops mid-run, seconds (default 30;
        ``--connect-timeout``).
    """

    workers: int | None = None
    threads_per_worker: int | None = None
    scheduler: str | None = None
    allowed_failures: int = 2
    processes: bool = True
    connect_timeout_s: float = 30.0

    def __post_init__(self) -> None:
        if self.workers is not None and not 0 <= int(self.workers) <= 1024:
            raise ValueError(f"workers must be 0-1024, not {self.workers}")
        if self.threads_per_worker is not None and not 1 <= int(self.threads_per_worker) <= 256:
            raise ValueError(f"threads_per_worker must be 1-256, not {self.threads_per_worker}")
        if not 0 <= int(self.allowed_failures) <= 100:
            raise ValueError(f"allowed_failures must be 0-100, not {self.allowed_failures}")
        if not 0 < float(self.connect_timeout_s) <= 3600:  # also refuses nan
            raise ValueError(f"connect_timeout_s must be in (0, 3600], not {self.connect_timeout_s}")

    @property
    def in_process(self) -> bool:
        """No Dask at all: ``workers == 0`` without a scheduler."""
        return self.scheduler is None and self.workers == 0

    def local_shape(self, n_tasks: int | None = None) -> tuple[int, int]:
        """``(workers, threads_per_worker)`` of the local cluster to start."""
        threads = int(self.threads_per_worker or 1)
        workers = int(self.workers) if self.workers else default_workers(threads, n_tasks)
        if n_tasks:  # a worker without a photo only holds a copy of the scene
            workers = min(workers, int(n_tasks))
        return workers, threads


# ------------------------------------------------------------------ scene
def _stamp(path: str | None) -> tuple | None:
    if path is None:
        return None
    p = Path(path)
    try:
        st = p.stat()
    except OSError:
        return (str(p), None, None)
    return (str(p.resolve()), st.st_size, st.st_mtime_ns)


@dataclass(frozen=True)
class SceneSpec:
    """The scene's files, by path: what a worker needs to load it.

    Attributes
    ----------
    mesh : str
    dem, georef : str or None
    """

    mesh: str
    dem: str | None = None
    georef: str | None = None

    def key(self) -> tuple:
        """Paths, sizes and modification times: a changed file is a new scene."""
        return (_stamp(self.mesh), _stamp(self.dem), _stamp(self.georef))

    def load(self) -> Scene:
        """The scene with its ray engine built."""
        scene = Scene.load(self.mesh, georef=self.georef, dem=self.dem)
        scene.build_engine()
        return scene


#: This process's scene: ``(key, Scene)``; one at a time (a scene can be GBs).
_SCENE: list[tuple[tuple, Scene]] = []
_SCENE_LOCK = threading.Lock()


def cached_scene(spec: SceneSpec, scene: Scene | None = None) -> Scene:
    """The scene of ``spec``, loaded (and its engine built) once per process.

    Parameters
    ----------
    spec : SceneSpec
    scene : Scene, optional
        Already loaded from ``spec``: keep it as the cached one (the client's
        own scene when the photos run in this process).
    """
    key = spec.key()
    with _SCENE_LOCK:  # threads of one worker wait for one load
        if _SCENE and _SCENE[0][0] == key:
            return _SCENE[0][1]
        _SCENE.clear()  # the old scene goes before the new one loads
        if scene is None:
            t0 = time.perf_counter()
            scene = spec.load()
            log.info("scene %s loaded in %.1f s", spec.mesh, time.perf_counter() - t0)
        else:
            scene.build_engine()
        _SCENE.append((key, scene))
        return scene


# ------------------------------------------------------------------ tasks
def _write_json(path: Path, data: Any) -> None:
    text = strict_dumps(data, indent=2) + "\n"  # serialised first: a bad value writes nothing
    with atomic_write(path, encoding="utf-8") as fh:
        fh.write(text)


#: The stop event of the batch run whose task runs in this thread (see :func:`_run_task`).
_RUN_STOP = threading.local()


def _run_task(stop_name: str, fn: Callable, *args: Any) -> Any:
    """Run a batch task on a worker, where :func:`stop_requested` can see its run's
    stop event (set when the command is interrupted: a remote cluster does not
    stop the photos it is running)."""
    _RUN_STOP.name = stop_name
    try:
        return fn(*args)
    finally:
        _RUN_STOP.name = None


def stop_requested() -> bool:
    """Whether the batch run of the task in this thread was interrupted (False
    outside a Dask task, or when the scheduler cannot be asked)."""
    name = getattr(_RUN_STOP, "name", None)
    if not name:
        return False
    try:
        from distributed import Event

        return bool(Event(name).is_set())
    except Exception:  # noqa: BLE001 - no scheduler to ask: write, as without the check
        return False


#: Photo tasks running in this process now, in any thread (see :class:`_NoFinalizingMidPhoto`).
_PHOTOS_RUNNING = [0]
_PHOTOS_RUNNING_LOCK = threading.Lock()


def _counted_as_running(task: Callable) -> Callable:
    """Count ``task`` in :data:`_PHOTOS_RUNNING` while it runs (a photo task)."""

    @functools.wraps(task)
    def counted(*args: Any, **kwargs: Any) -> Any:
        with _PHOTOS_RUNNING_LOCK:
            _PHOTOS_RUNNING[0] += 1
        try:
            return task(*args, **kwargs)
        finally:
            with _PHOTOS_RUNNING_LOCK:
                _PHOTOS_RUNNING[0] -= 1

    return counted


@_counted_as_running
def register_photo_file(
    scene_spec: SceneSpec,
    photo_path: str,
    result_path: str,
    params: Any,
    on_progress: Callable | None = None,
) -> dict[str, Any]:
    """Register one photo file and write its RESULT.json: a ``batch`` task.

    Parameters
    ----------
    scene_spec : SceneSpec
        The scene (loaded once per worker, :func:`cached_scene`).
    photo_path : str
        The photo; its sensor record ``PHOTO.json`` beside it, else EXIF.
    result_path : str
        Where its RESULT.json goes (written atomically, by this process).
    params : RegistrationParams
    on_progress : callable, optional
        Progress within the photo (in-process runs only).

    Returns
    -------
    dict
        ``photo`` (file name), ``status`` (``registered``, ``failed``,
        ``bad_input``, ``error``), ``error`` (one line, empty when none),
        ``seconds`` (the photo's own, without a first scene load), and when
        it registered or failed: ``result`` (the RESULT.json dict),
        ``hints``, ``assumptions``, ``scene_load_s`` (0 when the worker had
        the scene already) and ``pid`` (of the process that ran it).
    """
    t0 = time.perf_counter()
    photo_path_ = Path(photo_path)
    name = photo_path_.name
    try:
        scene = cached_scene(scene_spec)
        # A worker's first photo also loads the scene: not the photo's time.
        scene_s, t0 = time.perf_counter() - t0, time.perf_counter()
        photo = load_photo(photo_path_)
        prior = prior_for_photo(photo, scene)
        check_photo_size(photo, prior)
        # Looked up at call time: a test may stand in for the pipeline.
        reg = pipeline.register(scene, photo.image, prior, params, name, on_progress=on_progress)
    except InputError as exc:
        return {"photo": name, "status": "bad_input", "error": _one_line(exc),
                "seconds": time.perf_counter() - t0}
    except Exception as exc:  # noqa: BLE001 - one photo's crash is its outcome, not the batch's
        return {"photo": name, "status": "error",
                "error": f"{photo_path_}: {type(exc).__name__}: {_one_line(exc)}",
                "seconds": time.perf_counter() - t0}
    result = reg.to_dict()
    if stop_requested():
        # The batch was interrupted while this photo ran on a cluster that goes
        # on: the summary has been written without it, so the folder must be too.
        return {"photo": name, "status": "error", "error": "interrupted: result not written",
                "seconds": time.perf_counter() - t0}
    try:
        _write_json(Path(result_path), result)
    except OutputError as exc:  # refused (an immutable file): this photo's outcome, not the batch's
        return {"photo": name, "status": "bad_input", "error": _one_line(exc),
                "seconds": time.perf_counter() - t0}
    return {"photo": name, "status": reg.status, "error": "", "result": result,
            "hints": list(reg.hints), "assumptions": list(reg.assumptions),
            "seconds": time.perf_counter() - t0, "scene_load_s": scene_s, "pid": os.getpid()}


@_counted_as_running
def register_prior(scene_spec: SceneSpec, image: Any, prior: Any, params: Any,
                   name: str) -> Any:
    """Register an image from a given prior: a ``workspace register`` task.

    ``image``: an RGB array, or a :class:`~napari_imgreg.io.photos.Photo` read
    from a file, which is sent without its pixels and decoded here (the
    client does not hold every photo of the campaign decoded at once).

    Returns the :class:`~napari_imgreg.registration.pipeline.Registration`
    (pickled back to the client, which records it in the workspace).
    """
    scene = cached_scene(scene_spec)
    if isinstance(image, Photo):
        photo, image = image, image.image
        photo.release()  # the array is held here until the photo is done
    return pipeline.register(scene, image, prior, params, name)


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text or type(exc).__name__


# ----------------------------------------------------------------- runner
class _PinThreads(WorkerPlugin):
    """A Dask worker plugin: size every native thread pool of the worker to
    its thread count (or ``threads``), before its first photo."""

    name = "napari-imgreg-pin-threads"

    def __init__(self, threads: int | None = None) -> None:
        self.threads = threads

    def setup(self, worker) -> None:
        n = int(self.threads or worker.state.nthreads or 1)
        pin_threads(n)


class _IgnoreInterrupt(WorkerPlugin):
    """A Dask worker plugin for the worker processes of our local cluster:
    ignore SIGINT, which a terminal's Ctrl-C sends to them too (this process
    handles it). They are started with SIGINT blocked
    (:func:`_interrupt_kept_from_workers`); this also covers one whose
    spawning thread had it unblocked."""

    name = "napari-imgreg-ignore-interrupt"

    def setup(self, worker) -> None:  # noqa: ARG002 - the plugin interface
        # A worker process runs its event loop, and this, in its main thread; a
        # worker thread of this process (processes=False) is left alone.
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)


class _NoFinalizingMidPhoto(WorkerPlugin):
    """A Dask worker plugin: a worker process that exits while one of its
    threads is still registering a photo ends at once (``os._exit``), without
    the interpreter's finalization.

    Closing a worker waits for its running tasks only so long (Dask's close
    timeout), and a photo takes seconds: at an interrupt the worker's process
    can reach its exit with the photo's thread still inside OpenCV. When that
    thread leaves the OpenCV call, Python (3.11–3.13) ends it with
    ``pthread_exit`` because the interpreter is finalizing; the unwinding
    reaches OpenCV's GIL guard, a C++ destructor, and the C++ runtime aborts
    the process: ``terminate called without an active exception`` on the
    command's stderr, which the workers share. Exiting before finalization
    begins (from ``atexit``, when the other threads still run as usual) leaves
    that thread nothing to unwind. A worker with no photo running exits as
    it always did.
    """

    name = "napari-imgreg-no-finalizing-mid-photo"

    def setup(self, worker) -> None:  # noqa: ARG002 - the plugin interface
        # One handler per process, however often the plugin is registered.
        atexit.unregister(_exit_at_once_if_mid_photo)
        atexit.register(_exit_at_once_if_mid_photo)


def _exit_at_once_if_mid_photo() -> None:
    """``atexit``: end this process now if a photo task is still running in
    one of its threads (:class:`_NoFinalizingMidPhoto`)."""
    if _PHOTOS_RUNNING[0] == 0:
        return
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(0)  # the worker was exiting anyway


def worker_environment(threads: int, dask_environment: dict | None = None) -> dict:
    """The environment a local worker process starts with.

    Parameters
    ----------
    threads : int
        The worker's threads: every native pool of :data:`THREAD_ENV_VARS`.
    dask_environment : dict, optional
        Dask's own pre-spawn environment, kept except where replaced here.

    Returns
    -------
    dict of str to str
        Dask's variables, the thread counts and the allocator settings of
        :mod:`napari_imgreg._allocator`, which replace Dask's
        ``MALLOC_TRIM_THRESHOLD_=65536``: that value made every freed image
        buffer a fresh zero-filled mapping (twice the page faults, about 30 %
        of a worker's CPU time in the kernel on the 12-photo campaign).
    """
    env = {str(k): str(v) for k, v in (dask_environment or {}).items()}
    env.update({name: str(threads) for name in THREAD_ENV_VARS})
    env.update(allocator_environment())
    return env


def pin_threads(n: int) -> None:
    """Size this process's OpenCV and ray-cast pools to ``n`` threads (BLAS
    and OpenMP read their variables at start-up: set for local workers before
    they start, see :class:`PhotoRunner`)."""
    os.environ["NAPARI_IMGREG_THREADS"] = str(n)  # read at each large ray cast
    tune_allocator()  # an existing cluster's workers too (local ones start tuned)
    try:
        import cv2

        cv2.setNumThreads(n)
    except ImportError:  # pragma: no cover - a core dependency
        pass


class TaskLost(Exception):
    """A photo's task gave up: its workers kept dying, or the cluster went away."""


class SchedulerLost(InputError):
    """The scheduler went away during the run (stopped, restarted, its job
    ended, the network cut): the photos not finished cannot be run. One line
    naming the scheduler, as for one that never answered."""


class _GivenUp:
    """Dask gave a task up after its workers died (before its solo retry)."""

    def __init__(self, message: str) -> None:
        self.message = message


class PhotoRunner:
    """Run photo tasks on a Dask cluster, or in this process (``workers=0``).

    Use as a context manager; :meth:`run` yields ``(tag, outcome)`` as tasks
    finish, where ``outcome`` is the task's return value or a
    :class:`TaskLost`.

    Parameters
    ----------
    cluster : ClusterParams
    n_tasks : int
        Photos to register (a local cluster has no more workers than that).
    """

    def __init__(self, cluster: ClusterParams, n_tasks: int) -> None:
        self.cluster = cluster
        self.n_tasks = n_tasks
        self.client = None
        self._local = None
        self._saved_env: dict[str, str | None] = {}
        self.description = "in this process"
        self.scheduler_address: str | None = None

    # -- lifetime
    def __enter__(self) -> PhotoRunner:
        if self.cluster.in_process or self.n_tasks == 0:
            return self
        try:
            self._start()
        except BaseException:
            # __exit__ is not called when __enter__ raises: a cluster half set
            # up (a Ctrl-C, a plugin that failed) is closed here.
            self.close(deliver_interrupts=False)
            raise
        return self

    def _start(self) -> None:
        """Connect to the scheduler or start the local cluster, and pin threads."""
        import dask
        from distributed import Client

        _quiet_distributed()
        if self.cluster.scheduler:
            address = self.cluster.scheduler
            timeout = f"{self.cluster.connect_timeout_s}s"
            target = _scheduler_address(address)
            self.client = _connect(Client, target, address, self.cluster.connect_timeout_s)
            self.scheduler_address = target
            self.description = self.describe_scheduler()
        else:
            from distributed import LocalCluster

            n_workers, threads = self.cluster.local_shape(self.n_tasks)
            # Set before a worker process starts (BLAS and OpenMP read them when
            # NumPy loads): Dask's pre-spawn environment, which it also sets in
            # this process, where nothing heavy runs while the cluster works.
            pre_spawn = worker_environment(
                threads, dask.config.get("distributed.nanny.pre-spawn-environ", {}))
            self._saved_env = {name: os.environ.get(name) for name in pre_spawn}
            # Dask lets a variable already in this process's environment win
            # over its pre-spawn config, and leaves its own values there after
            # a cluster closes (a MALLOC_TRIM_THRESHOLD_=65536 from an earlier
            # cluster would reach our workers): set ours, restored at close.
            os.environ.update(pre_spawn)
            with dask.config.set({
                "distributed.nanny.pre-spawn-environ": pre_spawn,
                "distributed.scheduler.allowed-failures": int(self.cluster.allowed_failures),
                # A worker holds only the photos it is running (Dask's default
                # 1.1 queues one more): a dying worker takes no innocent photo's
                # retry budget with it, and a freed thread takes the next photo.
                "distributed.scheduler.worker-saturation": 1.0,
                # Dask's statistical profiler walks every thread's stack each
                # 10 ms, taking the GIL from the registration: the dashboard's
                # profile page is not worth that on a machine with no spare core.
                "distributed.worker.profile.enabled": False,
                # Housekeeping sized for tasks of seconds, not milliseconds: the
                # system monitor's psutil reads (every 0.5 s in the scheduler,
                # each nanny and each worker) took ~7 % of a core in this
                # process alone; the nanny's memory check (0.1 s) and the event
                # loops' 20 ms tick add wake-ups that compete with two busy workers.
                "distributed.admin.system-monitor.interval": "5s",
                "distributed.admin.system-monitor.disk": False,
                "distributed.worker.memory.monitor-interval": "1s",
                "distributed.admin.tick.interval": "500ms",
            }), _interrupts_held(), _interrupt_kept_from_workers():
                for attempt in (1, 2):
                    try:
                        self._local = LocalCluster(
                            n_workers=n_workers, threads_per_worker=threads,
                            processes=self.cluster.processes,
                            # Any free port: several batches may run on one machine.
                            dashboard_address=":0",
                            # The workers' own log lines (a task cancelled at Ctrl-C, a
                            # restart): the command reports each photo in its own words.
                            silence_logs=logging.CRITICAL,
                        )
                        break
                    except AssertionError:
                        # Dask's event-loop thread gives itself 10 s to start and
                        # then fails an assert (distributed.utils.LoopRunner): seen
                        # once in CI on a loaded machine. One more try, then a line.
                        if attempt == 2:
                            raise InputError("the local Dask cluster did not start (its "
                                             "event loop took over 10 s): the machine is "
                                             "busy; try again") from None
                self.client = Client(self._local)
            kind = "process(es)" if self.cluster.processes else "thread(s) of this process"
            self.description = (f"local cluster: {n_workers} worker {kind}, "
                                f"{threads} thread(s) each")
        self.client.register_plugin(_PinThreads(None), name=_PinThreads.name)
        self.client.register_plugin(_NoFinalizingMidPhoto(), name=_NoFinalizingMidPhoto.name)
        if self._local is not None and self.cluster.processes:
            self.client.register_plugin(_IgnoreInterrupt(), name=_IgnoreInterrupt.name)

    def __exit__(self, exc_type, exc, tb) -> None:
        # Unwinding from an interrupt already: another one during the close adds nothing.
        self.close(deliver_interrupts=exc_type is None)

    def close(self, deliver_interrupts: bool = True) -> None:
        """Stop the client and the local cluster (a remote cluster stays).

        Ctrl-C and SIGTERM are held until both are closed (:func:`_interrupts_held`),
        then raised (``deliver_interrupts``) or dropped.
        """
        client, local = self.client, self._local
        self.client = self._local = None
        with _interrupts_held(deliver=deliver_interrupts):
            try:
                if client is not None:
                    client.close(timeout=10)
            except Exception:  # noqa: BLE001 - closing after an interrupt may find it half gone
                pass
            try:
                if local is not None:
                    local.close(timeout=10)
            except Exception:  # noqa: BLE001
                pass
        for name, value in self._saved_env.items():  # this process's own, as before
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
        self._saved_env = {}

    def describe_scheduler(self) -> str:
        """The existing scheduler's address (read from its file) and its workers now."""
        info = self.client.scheduler_info()
        workers = info.get("workers", {})
        threads = sum(w.get("nthreads", 0) for w in workers.values())
        given = self.cluster.scheduler
        source = "" if given == self.scheduler_address else f" (from {given})"
        return (f"scheduler {self.scheduler_address}{source}: {len(workers)} worker(s), "
                f"{threads} thread(s)")

    def wait_for_workers(self, report: Callable[[str], None] | None = None) -> None:
        """On an existing scheduler with no workers yet (a cluster job still
        queued), say so and wait for the first to join; then describe it anew."""
        if self.client is None or self._local is not None:
            return
        if sum(self.client.nthreads().values()) > 0:
            return
        if report is not None:
            report("the scheduler has no workers yet: waiting for the first to join "
                   "(Ctrl-C stops)")
        self.client.wait_for_workers(1)
        self.description = self.describe_scheduler()

    def worker_pids(self) -> dict[str, int]:
        """Worker address -> process id (local clusters and benchmarks)."""
        if self.client is None:
            return {}
        return dict(self.client.run(os.getpid))

    # -- work
    def run(self, tasks: Iterable[tuple[str, Callable, tuple]],
            report: Callable[[str], None] | None = None) -> Iterator[tuple[str, Any]]:
        """Run ``(tag, function, args)`` tasks; yield ``(tag, outcome)`` as each finishes.

        ``outcome`` is what the function returned, the exception it raised, or
        a :class:`TaskLost` when the cluster lost it (its workers kept dying).
        In this process the tasks run in order (an exception propagates); on
        a cluster in any order.
        Leaving the loop early (an interrupt) cancels what has not finished.

        When the connection to an existing scheduler drops, Dask cancels every
        task in flight and tries to reconnect for ``connect_timeout_s``; this
        says so at once through ``report`` (a line of progress), submits those
        tasks again if it reconnects, and raises :class:`SchedulerLost` if not.
        """
        if self.client is None:
            for tag, fn, args in tasks:
                yield tag, fn(*args)
            return
        from distributed import as_completed
        from distributed import wait as future_wait

        # Only as many photos in flight as the cluster has threads: a worker
        # mostly holds only what it runs, so a dying worker seldom takes a
        # queued photo's retry budget (allowed-failures) with it, and an
        # interrupt has little to cancel. Rechecked as each photo finishes
        # (workers join, leave). The photos of a dead worker go to a busy one,
        # though, which then holds two: hence the solo retry below.
        run_id = f"{os.getpid()}-{time.time_ns()}"
        stop_name = f"napari-imgreg-stop-{run_id}"
        pending = iter(enumerate(tasks))
        futures: dict[Any, tuple[str, tuple[str, Callable, tuple]]] = {}
        beside: dict[Any, set[Any]] = {}  # the futures each one was ever in flight with
        running = as_completed()

        def submit(task: tuple[str, Callable, tuple], number: str) -> Any:
            tag, fn, args = task
            # The key names the photo for the dashboard and the scheduler's log.
            key = f"napari-imgreg-photo-{Path(tag).name}-{number}-{run_id}"
            if self._local is None:  # an existing scheduler's workers go on after us
                future = self.client.submit(_run_task, stop_name, fn, *args, key=key,
                                            pure=False, retries=0)
            else:  # a local cluster is closed (its photos stopped) before the folder is read
                future = self.client.submit(fn, *args, key=key, pure=False, retries=0)
            beside[future] = set(futures)
            for other in futures:
                beside[other].add(future)
            futures[future] = (tag, task)
            return future

        def submit_next() -> bool:
            try:
                k, task = next(pending)
            except StopIteration:
                return False
            running.add(submit(task, f"{k:05d}"))
            return True

        def fill() -> None:
            while running.count() < self.slots() and submit_next():
                pass

        given_up: dict[Any, tuple[str, tuple[str, Callable, tuple], _GivenUp]] = {}
        resubmitted = 0
        try:
            fill()
            for future in running:
                if future not in futures:  # cancelled as the connection dropped, submitted again
                    continue
                tag, task = futures.pop(future)
                outcome = self._outcome(future)
                if isinstance(outcome, TaskLost) and self._scheduler_gone():
                    futures[future] = (tag, task)  # not finished: cancelled below
                    if not self._reconnected(len(futures), report):
                        raise SchedulerLost(
                            f"{self.scheduler_address or 'the local cluster'}: the scheduler "
                            "went away during the run (the connection to it was lost); the "
                            "photos finished before are kept")
                    # Dask cancelled every photo in flight when the connection dropped.
                    for lost, (_, lost_task) in list(futures.items()):
                        del futures[lost]
                        resubmitted += 1
                        running.add(submit(lost_task, f"again{resubmitted:05d}"))
                    continue
                if isinstance(outcome, _GivenUp):
                    given_up[future] = (tag, task, outcome)
                else:
                    yield tag, outcome
                fill()
            # A worker that dies takes every photo it held with it (Dask counts
            # each one's death), also one queued behind the photo that killed
            # it, which lands on a busy worker after its own worker died. So
            # photos given up together, in flight at the same time, get one
            # more chance each, alone on the cluster: the innocent register,
            # the photo that kills its worker by itself is reported. A photo
            # given up with no other given up beside it is reported at once.
            for k, (future, (tag, task, outcome)) in enumerate(given_up.items()):
                if beside[future] & given_up.keys():
                    retry = submit(task, f"retry{k}")
                    future_wait(retry)
                    futures.pop(retry)
                    outcome = self._outcome(retry, solo=True)
                yield tag, TaskLost(outcome.message) if isinstance(outcome, _GivenUp) else outcome
        except RuntimeError as exc:
            # An interrupt raised while this thread waits on a lock (as_completed's
            # condition) can leave the lock unheld, and the wait's `with` then fails
            # to release it ("cannot release un-acquired lock", a traceback and exit
            # 1 after SIGTERM): what happened is the interrupt.
            if isinstance(exc.__context__, KeyboardInterrupt):
                raise exc.__context__ from None
            raise
        finally:
            # Not with a scheduler gone: each call would wait for it (30 s each).
            if futures and self.client is not None and not self._scheduler_gone():
                try:
                    # Cancelling does not stop a photo already running: tell it
                    # not to write its result after the summary.
                    if self._local is None:
                        from distributed import Event

                        Event(stop_name, client=self.client).set()
                    self.client.cancel(list(futures))
                except Exception:  # noqa: BLE001 - the cluster may be going down
                    pass

    def _outcome(self, future, solo: bool = False) -> Any:
        """A finished future's result, its exception, a :class:`TaskLost`, or a
        :class:`_GivenUp` (Dask gave it up after its workers died)."""
        from distributed import KilledWorker

        try:
            outcome = future.result()
        except (Exception, asyncio.CancelledError) as exc:  # noqa: BLE001
            outcome = exc  # the task's own exception, or the cluster's
            if isinstance(exc, KilledWorker):
                outcome = _GivenUp(_lost_message(exc, self.cluster.allowed_failures, solo))
            elif _is_lost(exc):
                outcome = TaskLost(_lost_message(exc, self.cluster.allowed_failures))
        future.release()
        return outcome

    def _reconnected(self, n_in_flight: int, report: Callable[[str], None] | None) -> bool:
        """After the connection to the scheduler dropped: whether Dask's client
        reconnects (it tries for ``connect_timeout_s``). An existing scheduler
        may be back after a network blip or a restart; a local cluster's,
        in this process, is not. Says what it waits for, and what came of it."""
        if self._local is not None or self.client is None:
            return False
        address = self.scheduler_address
        if report is not None:
            report(f"lost the connection to the scheduler at {address}: trying to reconnect for "
                   f"up to {self.cluster.connect_timeout_s:g} s (Ctrl-C stops; the photos "
                   "finished are kept)")
        t0 = time.monotonic()
        # Dask's own deadline, and a margin in case its client never says.
        while (self.client.status in ("connecting", "newly-created")
               and time.monotonic() - t0 < self.cluster.connect_timeout_s + 10):
            time.sleep(0.1)
        if self.client.status != "running":
            return False
        if report is not None:
            report(f"reconnected to the scheduler at {address} after "
                   f"{time.monotonic() - t0:.1f} s: the {n_in_flight} photo(s) that were in "
                   "flight are registered again")
        return True

    def _scheduler_gone(self) -> bool:
        """This process's client has lost its scheduler: Dask cancels every
        future at once, tries to reconnect (``connecting``) and closes the
        client when that fails (``closed``). Either way the photos in flight
        will not come back."""
        return self.client is not None and self.client.status != "running"

    def slots(self) -> int:
        """Threads of the cluster's workers now (at least 1)."""
        try:
            return max(1, sum(self.client.nthreads().values()))
        except Exception:  # noqa: BLE001 - a scheduler gone away: the results say so
            return 1


def _scheduler_address(given: str) -> str:
    """The address in a scheduler file (``dask scheduler --scheduler-file``), or
    ``given`` when it is not a file.

    Raises
    ------
    InputError
        A file that is not a scheduler file, or a ``.json`` path that does not exist.
    """
    import json

    path = Path(given)
    if not path.is_file():
        if given.endswith(".json"):
            raise input_error(given, "no such scheduler file")
        if path.exists():
            raise input_error(given, "is a folder, not a scheduler address or file")
        return given
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise input_error(given, "not a Dask scheduler file (expected the JSON that "
                                 f"'dask scheduler --scheduler-file' writes: {_one_line(exc)})"
                          ) from None
    address = data.get("address") if isinstance(data, dict) else None
    if not isinstance(address, str) or not address:
        raise input_error(given, "not a Dask scheduler file (no 'address' in it)")
    return address


def _is_lost(exc: BaseException) -> bool:
    """The cluster lost the task (its workers died, it was cancelled, the
    scheduler went away), as opposed to the task raising."""
    from concurrent.futures import CancelledError

    from distributed import KilledWorker
    from distributed.comm.core import CommClosedError

    # distributed's FutureCancelledError (its client closed: the scheduler went
    # away) is a concurrent.futures.CancelledError, not asyncio's.
    return isinstance(exc, (KilledWorker, CommClosedError, asyncio.CancelledError,
                            CancelledError))


def _lost_message(exc: BaseException, allowed_failures: int, solo: bool = False) -> str:
    if type(exc).__name__ == "KilledWorker":
        allowed = getattr(exc, "allowed_failures", allowed_failures)  # the scheduler's own
        deaths = (f"{2 * (allowed + 1)} times, {allowed + 1} of them with no other photo "
                  f"on the cluster" if solo else f"{allowed + 1} times")
        return (f"the worker registering it died {deaths} (a crash in a native library "
                f"or out of memory?); not retried")
    return f"lost by the cluster ({type(exc).__name__}: {_one_line(exc)})"


@contextlib.contextmanager
def _interrupts_held(deliver: bool = True) -> Iterator[None]:
    """Hold Ctrl-C and SIGTERM while a local cluster starts or closes; then
    raise the first that arrived (``deliver``), or drop it.

    Raised inside Dask's start or close, an interrupt left the cluster half
    made or half closed: its worker processes outlived the command, which
    waited 10 s for Dask's own timeout to exit (a SIGTERM just as the last
    photo finished). Both take seconds and have timeouts. Handlers can only
    be set in the main thread; elsewhere the block runs as it is.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    arrived: list[int] = []

    def hold(signum, frame) -> None:  # noqa: ARG001 - a signal handler's signature
        arrived.append(signum)

    previous = {}
    try:
        for signum in (signal.SIGINT, signal.SIGTERM):
            previous[signum] = signal.signal(signum, hold)
        yield
    finally:
        for signum, handler in previous.items():
            # None: a handler not set from Python, restored as the default.
            signal.signal(signum, signal.SIG_DFL if handler is None else handler)
        if arrived and deliver:
            signal.raise_signal(arrived[0])  # its handler raises here, as it would have


@contextlib.contextmanager
def _interrupt_kept_from_workers() -> Iterator[None]:
    """Block SIGINT in this thread while a local cluster starts its workers.

    A terminal's Ctrl-C goes to the whole process group: each worker process
    would print a ``KeyboardInterrupt`` traceback on its way down (Dask has no
    option against it: dask/distributed issue 1925). A blocked signal stays
    blocked in the threads started here (the cluster's event loop, and the
    threads it starts to spawn and respawn the workers) and across fork and
    exec, so the workers never receive SIGINT and this process, which handles
    it, shuts the cluster down. A Ctrl-C pressed meanwhile is held, not lost:
    it arrives when the mask is restored. (Ignoring the signal instead would
    lose it: POSIX discards an ignored signal.) :class:`_IgnoreInterrupt`
    covers a worker that is spawned unblocked anyway.
    """
    if not hasattr(signal, "pthread_sigmask"):  # Windows: no signal masks
        yield
        return
    # Started now, if not already: multiprocessing's resource tracker, when it
    # starts, unblocks SIGINT in the thread that starts it (the event loop's).
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def _connect(client_class, target: str, given: str, timeout_s: float):
    """A Client of the scheduler at ``target``, or one line naming what answers there.

    Dask's own timeout covers the connection, not its handshake: a server that
    is not a scheduler (the dashboard's web port, an SSH port) kept the command
    waiting forever or failed deep in Dask's framing (a 2.8 EiB allocation).
    The connection runs in a thread with a deadline instead.
    """
    outcome: dict = {}

    def connect() -> None:
        try:
            outcome["client"] = client_class(target, timeout=f"{timeout_s}s")
        except BaseException as exc:  # noqa: BLE001 (reported below, in one line)
            outcome["error"] = exc

    thread = threading.Thread(target=connect, name="imgreg-connect", daemon=True)
    thread.start()
    deadline_s = timeout_s + min(10.0, timeout_s)  # a scheduler's handshake takes milliseconds
    thread.join(deadline_s)
    if thread.is_alive():
        raise input_error(given, f"something answers there but not as a Dask scheduler within "
                                 f"{deadline_s:g} s (a web server? the dashboard is usually "
                                 "port 8787, the scheduler 8786)")
    error = outcome.get("error")
    if isinstance(error, (OSError, TimeoutError)):  # refused, unreachable, timed out
        raise input_error(given, f"no Dask scheduler answers there "
                                 f"({type(error).__name__}: {_one_line(error)})") from None
    if isinstance(error, MemoryError):  # Dask read another protocol's bytes as a frame size
        raise input_error(given, "not a Dask scheduler: what answers there speaks another "
                                 "protocol (an SSH or web port?)") from None
    if error is not None:  # a bad address, or a server speaking another protocol
        raise input_error(given, f"not a Dask scheduler address, or not a Dask scheduler "
                                 f"answering there ({type(error).__name__}: "
                                 f"{_one_line(error)})") from None
    return outcome["client"]


def _quiet_distributed() -> None:
    """Dask's own warnings (a worker restarted, a slow event loop) are not the
    user's business: the command reports what happened to each photo."""
    for name in ("distributed", "distributed.nanny", "distributed.scheduler",
                 "distributed.worker", "distributed.core", "distributed.comm",
                 # Its "Failed to reconnect to scheduler": the command's SchedulerLost line says it.
                 "distributed.client"):
        # CRITICAL: Dask logs a task given up after workers died at ERROR, beside
        # the command's own line for that photo.
        logging.getLogger(name).setLevel(logging.CRITICAL)
