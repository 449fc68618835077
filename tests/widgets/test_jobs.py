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


_ENDS_MID_JOB = '''
import time
from qtpy.QtWidgets import QApplication
app = QApplication.instance() or QApplication([])
from napari_imgreg.registration.pipeline import Cancelled
from napari_imgreg.widgets._jobs import JobRunner

runner = JobRunner()
cancelled = runner.cancel_token("registration")

def job():
    for k in range(1000):  # 20 s unless cancelled
        if cancelled():
            raise Cancelled
        time.sleep(0.02)
        yield k

runner.start("registration", job, on_returned=lambda value: None)
end = time.time() + 0.5
while time.time() < end:
    app.processEvents()
    time.sleep(0.01)
print("running at exit:", runner.is_running("registration"), flush=True)
'''


def test_a_script_that_ends_while_a_job_runs_exits_cleanly(tmp_path):
    """A script or notebook ending while a registration ran went straight to
    Python's finalization: the worker's Qt signals were deleted under its
    thread ("GeneratorWorkerSignals has been deleted"; in napari's window the
    process aborted). Now the job is cancelled and waited for at exit."""
    import os
    import subprocess
    import sys
    import time

    script = tmp_path / "ends_mid_job.py"
    script.write_text(_ENDS_MID_JOB, encoding="utf-8")
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    t0 = time.monotonic()
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          env=env, timeout=120)
    assert "running at exit: True" in done.stdout
    assert done.returncode == 0, done.stderr
    assert "has been deleted" not in done.stderr, done.stderr
    assert time.monotonic() - t0 < 15  # cancelled, not run to its end


def test_held_results_come_in_their_order_when_the_hold_ends(qtbot):
    """While a job that reads the whole workspace runs (a save), the other
    jobs' progress, results and failures wait; the holding job's do not."""
    from napari_imgreg.widgets._jobs import hold_results, results_held

    jobs = JobRunner()
    seen = []
    ran = {"held": threading.Event(), "fails": threading.Event()}

    def steps():
        try:
            yield "step"
            return "result"
        finally:
            ran["held"].set()

    def fails():
        ran["fails"].set()
        raise OSError("disk gone")

    release = hold_results()
    assert results_held()
    # One after the other (is_running is False too before a worker starts),
    # with time for each one's signals to reach the GUI thread.
    jobs.start("held", steps, on_yielded=seen.append, on_returned=seen.append)
    qtbot.waitUntil(ran["held"].is_set, timeout=5000)
    qtbot.wait(100)
    jobs.start("fails", fails, on_returned=seen.append, on_failed=seen.append, notify=False)
    qtbot.waitUntil(ran["fails"].is_set, timeout=5000)
    qtbot.wait(100)
    holder = []
    jobs.start("holder", lambda: "saved", on_returned=holder.append, held=False)
    qtbot.waitUntil(lambda: holder == ["saved"], timeout=5000)
    qtbot.wait(100)
    assert seen == [] and jobs.busy  # delivered to the GUI thread, and kept
    release()
    release()  # a second release is nothing
    assert not results_held()
    assert seen == ["step", "result", "OSError: disk gone"]
    qtbot.waitUntil(lambda: not jobs.busy, timeout=5000)
