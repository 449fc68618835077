"""The thread-worker runner behind every dock (run under Xvfb)."""

from __future__ import annotations

import threading

from qtpy.QtWidgets import QWidget

from napari_imgreg.widgets._jobs import JobRunner


def test_a_job_ending_after_its_dock_was_deleted_raises_nothing(qtbot):
    """A dock deleted (napari closing, a test's teardown) while its job runs:
    the job's end emitted on the deleted runner and raised RuntimeError in a
    Qt slot ("wrapped C/C++ object of type JobRunner has been deleted"); the
    job is now asked to stop and its end is silent."""
    dock = QWidget()
    jobs = JobRunner(dock)
    release = threading.Event()
    cancelled = jobs.cancel_token("slow")
    seen = []

    def slow():
        release.wait(5.0)
        return cancelled()

    worker = jobs.start("slow", slow, on_returned=seen.append)
    finished = []
    worker.finished.connect(lambda: finished.append(True))
    with qtbot.waitSignal(jobs.destroyed, timeout=5000):
        dock.deleteLater()
    assert cancelled()  # told to stop with its dock
    release.set()
    qtbot.waitUntil(lambda: bool(finished), timeout=5000)
    qtbot.wait(50)
    assert seen == []  # a result for a dock that is gone is not handed on
