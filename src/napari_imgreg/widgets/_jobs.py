"""One runner for the widgets' long jobs: napari thread workers, progress,
cancellation and errors in one place.

Every dock runs its jobs (scene and photo loading, renders, filters,
registration, manual solving, the sun, projecting interpretations, orienting
a model) through a :class:`JobRunner`: the job runs in a napari thread worker
(with a progress bar in napari's activity dock when asked), its result comes
back in the GUI thread, a cancelled job returns None, and an error becomes a
one-line message (:func:`~napari_imgreg.workspace.one_line`) for the dock to
show — never a traceback thrown at the user — and a napari notification, so
that a failure is seen even when the status line is out of sight.

Workers run functions, or generator functions that yield progress (as
:func:`~napari_imgreg.registration.pipeline.register_photo` does): napari
wraps those in a worker that can be stopped between two yields.

While a worker reads the whole workspace (the workbench's *Save workspace
as…*), :func:`hold_results` keeps every other job's results, progress and
failures from reaching the GUI thread, where they would edit the workspace
under the worker; they are delivered in order when the hold ends.
"""

from __future__ import annotations

import atexit
import functools
import inspect
import logging
import threading
import weakref
from typing import Any, Callable

from qtpy.QtCore import QObject, QThreadPool, Signal

from ..errors import InputError
from ..registration.pipeline import Cancelled
from ..workspace import WorkbenchError, one_line

__all__ = ["JobRunner", "CANCELLED", "guarded", "in_python_thread", "enough_worker_threads",
           "hold_results", "results_held"]

log = logging.getLogger(__name__)

#: What a cancelled job returns inside the worker (its handler receives None).
CANCELLED = object()


#: Every live runner (see :func:`_finish_jobs_at_exit`).
_RUNNERS: "weakref.WeakSet[JobRunner]" = weakref.WeakSet()

#: How long the interpreter's exit waits for cancelled jobs to stop, ms.
EXIT_WAIT_MS = 15_000

#: What jobs delivered to the GUI thread while held (see hold_results), in order.
_HELD: list[Callable[[], None]] = []
#: The holds in force.
_HOLDS = [0]


def hold_results() -> Callable[[], None]:
    """Hold back what every runner's jobs deliver to the GUI thread (results,
    progress, failures, ends) until the returned ``release`` is called.

    For a job that reads the whole workspace in its worker (a *Save workspace
    as…*): a registration that ends meanwhile must not edit the workspace
    under it. Its result is recorded when the hold ends, in the order the
    jobs delivered theirs. Jobs started with ``held=False`` (the one that
    holds) are never held. Holds nest; ``release`` may be called more than
    once (only the first counts).
    """
    _HOLDS[0] += 1
    released = []

    def release() -> None:
        if released:
            return
        released.append(True)
        _HOLDS[0] -= 1
        # Delivered one by one: one that starts another hold leaves the rest to it.
        while _HELD and not _HOLDS[0]:
            deliver = _HELD.pop(0)
            try:
                deliver()
            except Exception:  # noqa: BLE001 - as a Qt slot's error: the others still come
                log.exception("a held job result raised")

    return release


def results_held() -> bool:
    """Whether jobs' results are held (see :func:`hold_results`)."""
    return _HOLDS[0] > 0


def _holdable(callback: Callable) -> Callable:
    """``callback``, kept for later while results are held."""

    def deliver(*args) -> None:
        if _HOLDS[0]:
            _HELD.append(functools.partial(callback, *args))
        else:
            callback(*args)

    return deliver


@atexit.register
def _finish_jobs_at_exit() -> None:
    """Cancel every job and wait for its thread before Python finalizes.

    napari's own application waits for its workers when it quits, but a
    script or a notebook that ends while a registration runs went straight
    to finalization: the worker's Qt signals were deleted under the running
    thread, which then raised in Qt's thread ("wrapped C/C++ object of type
    GeneratorWorkerSignals has been deleted") and the process aborted. The
    jobs poll their cancel token between steps, so this waits a fraction of
    a second.
    """
    runners = [r for r in list(_RUNNERS) if r._workers]
    if not runners:
        return
    for runner in runners:
        runner.shutdown()
    QThreadPool.globalInstance().waitForDone(EXIT_WAIT_MS)


def guarded(fn: Callable) -> Callable:
    """Wrap a job for a worker: cancellation returns :data:`CANCELLED`, errors
    become a :class:`WorkbenchError` of one line (the original as its cause)."""
    if inspect.isgeneratorfunction(fn):

        @functools.wraps(fn)
        def gen(*args, **kwargs):
            try:
                return (yield from fn(*args, **kwargs))
            except Cancelled:
                return CANCELLED
            except Exception as exc:
                raise WorkbenchError(one_line(exc)) from exc

        return gen

    @functools.wraps(fn)
    def func(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except Cancelled:
            return CANCELLED
        except Exception as exc:
            raise WorkbenchError(one_line(exc)) from exc

    return func


def enough_worker_threads(n: int = 6) -> None:
    """Let napari's worker pool run a registration, a render and a filter at once.

    napari's workers share Qt's global thread pool, sized to the CPU count: on
    a two-core laptop a registration and a full render would hold the pool
    and a filter preview would wait for them. The jobs spend their time in
    NumPy, OpenCV and Embree, which release the GIL.
    """
    pool = QThreadPool.globalInstance()
    if pool.maxThreadCount() < n:
        pool.setMaxThreadCount(n)


def in_python_thread(fn: Callable, *args, **kwargs):
    """Run ``fn`` in a short-lived Python thread and wait for it.

    For jobs that may touch pyproj (georeference, DEM, geodetic priors):
    pyproj 3.7 keeps per-thread PROJ contexts that can be freed under Qt's
    worker threads, which Python did not create, and the next use crashes
    the process (pyproj issues 1509 and 1622). A thread Python starts and
    ends owns its context for its whole life.
    """
    box: dict[str, Any] = {}

    def run() -> None:
        try:
            box["value"] = fn(*args, **kwargs)
        except BaseException as exc:  # re-raised in the worker
            box["error"] = exc

    thread = threading.Thread(target=run, name="napari-imgreg-io", daemon=True)
    thread.start()
    thread.join()
    if "error" in box:
        raise box["error"]
    return box.get("value")


def _log_failure(job: str, msg: str, exc: BaseException) -> None:
    """Bad input is the user's to fix (debug log); anything else is a bug (its traceback)."""
    cause = exc.__cause__ if isinstance(exc, WorkbenchError) and exc.__cause__ else exc
    if isinstance(cause, (InputError, WorkbenchError)):
        log.debug("%s failed: %s", job, msg, exc_info=exc)
    else:
        log.error("%s failed: %s", job, msg, exc_info=cause)


class JobRunner(QObject):
    """Runs named jobs in napari thread workers, one at a time per name.

    Signals
    -------
    busy_changed()
        A job started or ended.
    status(str)
        "job: cancelled", "job failed: message".
    failed(str, str)
        A job failed: its name and the one-line message (also raised as a
        napari error notification, unless the job was started with
        ``notify=False``).
    """

    busy_changed = Signal()
    status = Signal(str)
    failed = Signal(str, str)

    def __init__(self, parent: QObject | None = None) -> None:
        super().__init__(parent)
        self._workers: dict[str, Any] = {}
        self._pending: dict[str, Callable[[], None]] = {}
        self._cancel: dict[str, threading.Event] = {}
        self._closed = False
        # Its Qt object deleted with its dock (napari closing, a test's
        # teardown) while a worker still runs: nothing may be emitted then.
        self._deleted = False
        # (Not a bound method: Qt drops an object's own slots before it
        # tells of its destruction.)
        self.destroyed.connect(lambda *_args, runner=self: runner._on_destroyed())
        self._notified: dict[str, str] = {}  # per job: the failure last notified
        enough_worker_threads()
        _RUNNERS.add(self)

    def _on_destroyed(self, *_args) -> None:
        self._deleted = True
        self._closed = True
        self._pending.clear()
        for event in self._cancel.values():
            event.set()
        for worker in list(self._workers.values()):
            worker.quit()

    def _emit(self, signal_name: str, *args) -> None:
        """Emit one of this runner's signals, unless its Qt object is gone (a
        worker finishing after its dock was deleted raised RuntimeError in a
        Qt slot: "wrapped C/C++ object of type JobRunner has been deleted")."""
        if self._deleted:
            return
        try:
            getattr(self, signal_name).emit(*args)
        except RuntimeError:
            self._deleted = True

    # -------------------------------------------------------------- state
    @property
    def busy(self) -> bool:
        """True while any job runs or waits its turn."""
        return bool(self._workers) or bool(self._pending)

    def is_running(self, job: str) -> bool:
        return job in self._workers

    @property
    def closed(self) -> bool:
        return self._closed

    def worker(self, job: str):
        """The napari worker running ``job`` (None when it is not running)."""
        return self._workers.get(job)

    # ------------------------------------------------------------- cancel
    def cancel_token(self, job: str) -> Callable[[], bool]:
        """A fresh "cancelled?" callable for a job about to start (polled by
        the backend between steps); :meth:`cancel` sets it."""
        event = threading.Event()
        if self._closed:
            event.set()
        self._cancel[job] = event
        return event.is_set

    def cancel(self, *jobs: str) -> None:
        """Ask jobs (all without names) to stop at their next step."""
        for name in jobs or tuple(self._cancel):
            if (event := self._cancel.get(name)) is not None:
                event.set()

    # ---------------------------------------------------------------- run
    def defer(self, job: str, request: Callable[[], None]) -> bool:
        """While ``job`` runs, keep ``request`` to be made when it has finished
        (the first one waiting is kept); returns False when ``job`` is idle."""
        if job not in self._workers:
            return False
        self._pending.setdefault(job, request)
        return True

    def start(self, job: str, fn: Callable, *args, on_returned: Callable[[Any], None],
              on_yielded: Callable[[Any], None] | None = None,
              on_failed: Callable[[str], None] | None = None,
              on_finished: Callable[[], None] | None = None,
              progress: dict | None = None, notify: bool = True, held: bool = True,
              **kwargs):
        """Run ``fn(*args, **kwargs)`` in a napari thread worker named ``job``.

        Parameters
        ----------
        job : str
            Its name: in messages, for :meth:`is_running` and :meth:`cancel`.
        fn : callable
            A function, or a generator function yielding progress.
        on_returned : callable
            Called with the result in the GUI thread (None when cancelled).
        on_yielded : callable, optional
            Called with each yielded value. A value with a ``fraction``
            (and a ``message``) also moves the progress bar.
        on_failed : callable, optional
            Called with the one-line message when ``fn`` raised.
        on_finished : callable, optional
            Called when the job is over, whatever its outcome.
        progress : dict, optional
            napari's ``_progress`` (``{"desc": ..., "total": ...}``): a
            progress bar in the activity dock.
        notify : bool
            Raise a napari notification when it fails (False: ``on_failed``
            notifies itself).
        held : bool
            Its results, progress and failure wait while :func:`hold_results`
            holds (default); False for the job that holds them.

        Returns
        -------
        worker
            The started napari worker.
        """
        # napari is imported when a job starts: its import is slow and warns
        # (pydantic) where the widget modules are merely imported.
        from napari.qt.threading import create_worker

        def release() -> None:
            # The job is over once it has returned or failed: its result
            # handlers may start the next job of the same name.
            if self._workers.get(job) is worker:
                del self._workers[job]
                self._emit("busy_changed")

        def returned(value):
            release()
            if self._closed:
                return
            self._notified.pop(job, None)
            if value is CANCELLED:
                self._emit("status", f"{job}: cancelled")
                on_returned(None)
                return
            on_returned(value)

        def errored(exc):
            release()
            msg = one_line(exc)
            _log_failure(job, msg, exc)
            if not self._closed:
                self._emit("status", f"{job} failed: {msg}")
                if notify:
                    self._notify_failure(job, f"{job} failed: {msg}")
                self._emit("failed", job, msg)
                if on_failed is not None:
                    on_failed(msg)

        def yielded(value):
            if on_yielded is not None and not self._closed:
                on_yielded(value)
            # The bar last: its update may process pending events, the job's
            # return among them, which must not be followed by a stale progress.
            pbar = getattr(worker, "pbar", None)
            fraction = getattr(value, "fraction", None)
            if pbar is not None and fraction is not None:
                pbar.n = int(round(100 * fraction))
                pbar.set_description(f"{(progress or {}).get('desc', job)}: "
                                     f"{getattr(value, 'message', '')}")
                pbar.update(0)

        def finished():
            release()
            self._emit("busy_changed")
            if on_finished is not None and not self._closed:
                on_finished()
            if job not in self._workers:
                pending = self._pending.pop(job, None)
                if pending is not None and not self._closed:
                    pending()

        def aborted():
            returned(CANCELLED)

        connect = {"returned": returned, "errored": errored, "finished": finished}
        if inspect.isgeneratorfunction(fn):
            connect["yielded"] = yielded
            connect["aborted"] = aborted  # quit() between two yields
        if held:
            connect = {name: _holdable(callback) for name, callback in connect.items()}
        extra = {"_progress": progress} if progress else {}
        worker = create_worker(guarded(fn), *args, _connect=connect, _start_thread=False,
                               **extra, **kwargs)
        self._workers[job] = worker
        self._emit("busy_changed")
        worker.start()
        return worker

    def _notify_failure(self, job: str, message: str) -> None:
        """An error notification, once while a job repeats the same failure
        (a render asked for at each nudge must not pile them up)."""
        if self._notified.get(job) == message:
            return
        self._notified[job] = message
        # napari is imported when needed: its import is slow and warns (pydantic).
        from napari.utils.notifications import show_error

        show_error(message)

    def shutdown(self) -> None:
        """Cancel and quit every job; later results are ignored."""
        if self._closed:
            return
        self._closed = True
        self.cancel()
        self._pending.clear()
        for worker in list(self._workers.values()):
            worker.quit()
