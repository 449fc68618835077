"""*Save workspace as…* in the workbench writes in a worker: the window keeps
answering behind a modal progress dialog, what running jobs deliver meanwhile
is recorded once the folder is complete (and so saved there), and a failure
is one line that leaves the workspace saved where it was.

The writing is slowed down (a pause per photo, in whatever thread writes) so
that the save lasts long enough to see all this on any machine.
"""

from __future__ import annotations

import json
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from qtpy.QtCore import QTimer
from qtpy.QtWidgets import QApplication

from napari_imgreg import workspace as workspace_module
from napari_imgreg.io import workspace_files as wsfiles
from napari_imgreg.registration import pipeline
from napari_imgreg.registration.pipeline import Cancelled, Progress
from napari_imgreg.widgets._progress_dialog import ModalProgress
from napari_imgreg.workspace import Workspace

from ._workbench import LOAD_S, idle, load_sample, registered_on_truth, wait_saved

pytestmark = pytest.mark.gui


def _slow_writing(monkeypatch, ctrl, pause_s: float) -> list[bool]:
    """Each photo's files written ``pause_s`` slower; returns, for each photo
    written while the save runs, whether the GUI thread wrote it."""
    on_gui_thread: list[bool] = []
    save_photo = workspace_module._FolderStore.save_photo

    def slow_save_photo(self, ps, *args, **kwargs):
        if ctrl.saving:
            on_gui_thread.append(threading.current_thread() is threading.main_thread())
            time.sleep(pause_s)
        return save_photo(self, ps, *args, **kwargs)

    monkeypatch.setattr(workspace_module._FolderStore, "save_photo", slow_save_photo)
    return on_gui_thread


def _more_photos(ctrl, qtbot, tmp_path, n: int) -> None:
    """Add ``n`` copies of the sample's photos (each with its own sensor record)."""
    source = sorted(Path(ctrl.photos[0].photo.path).parent.glob("IMG_*.jpg"))
    extra = tmp_path / "more"
    extra.mkdir()
    paths = []
    for k in range(n):
        photo = source[k % len(source)]
        copy = extra / f"COPY_{k:03d}.jpg"
        try:
            copy.hardlink_to(photo)
        except OSError:
            shutil.copyfile(photo, copy)
        shutil.copyfile(photo.with_suffix(".json"), copy.with_suffix(".json"))
        paths.append(copy)
    before = len(ctrl.photos)
    ctrl.add_photos(paths)
    qtbot.waitUntil(lambda: len(ctrl.photos) == before + n, timeout=LOAD_S)


def _heartbeat() -> tuple[QTimer, list[float]]:
    beats: list[float] = []
    timer = QTimer()
    timer.setInterval(10)
    timer.timeout.connect(lambda: beats.append(time.perf_counter()))
    timer.start()
    return timer, beats


def _tree(folder: Path) -> dict[str, bytes]:
    """The files of a workspace folder (its lock left out, the manifest
    without the time it was saved)."""
    files = {}
    for path in sorted(folder.rglob("*")):
        if path.is_file() and path.name != wsfiles.LOCK:
            data = path.read_bytes()
            if path.name == "workspace.json":
                doc = json.loads(data)
                doc.pop("saved", None)
                data = json.dumps(doc, sort_keys=True).encode()
            files[str(path.relative_to(folder))] = data
    return files


def _stand_in_registration(monkeypatch, ctrl, delay_s: float, ended: threading.Event) -> None:
    """The pipeline replaced: the photo "registers" on its prior pose after ``delay_s``."""

    def register_photo(scene, image, prior, params, photo_name="", cancelled=None):
        for k in range(4):
            if cancelled is not None and cancelled():
                raise Cancelled()
            time.sleep(delay_s / 4)
            yield Progress("match", (k + 1) / 5, f"step {k + 1}")
        ps = next(p for p in ctrl.photos if p.name == photo_name)
        ended.set()
        return registered_on_truth(ps, pose=ps.prior.pose)

    monkeypatch.setattr(pipeline, "register_photo", register_photo)


def test_save_as_writes_in_a_worker_and_the_window_keeps_answering(workbench, qtbot, tmp_path,
                                                                   monkeypatch):
    wb = workbench
    ctrl = load_sample(wb, qtbot)
    _more_photos(ctrl, qtbot, tmp_path, 27)
    idle(wb, qtbot)
    ws = ctrl.workspace
    ws.record_registration(registered_on_truth(ws.photos[1]), "Auto", ws.photos[1],
                           pose_if_not_current=True)
    reference = tmp_path / "reference.imgreg"
    ws.save(reference)  # the Python API's save, for comparison (and a binding to move)
    on_gui_thread = _slow_writing(monkeypatch, ctrl, pause_s=0.04)  # 1.2 s of pauses
    timer, beats = _heartbeat()
    t0 = time.perf_counter()
    assert ctrl.save_workspace(tmp_path / "campaign") == tmp_path / "campaign.imgreg" / \
        "workspace.json"
    assert ctrl.saving and ctrl.busy
    qtbot.waitUntil(lambda: len(on_gui_thread) >= 5, timeout=30_000)
    dialog = QApplication.activeModalWidget()
    assert isinstance(dialog, ModalProgress) and dialog.isVisible()
    assert dialog.parent() is wb.window()  # modal to the viewer's window
    assert "of 30 photo(s) written" in dialog.label.text() and dialog.bar.maximum() == 30
    wait_saved(wb, qtbot)
    t1 = time.perf_counter()
    timer.stop()
    points = [t0] + [b for b in beats if t0 < b < t1] + [t1]
    longest = max(b - a for a, b in zip(points, points[1:]))
    assert len(on_gui_thread) == 30 and not any(on_gui_thread)  # every photo in the worker
    assert t1 - t0 > 1.2 and longest < 0.5, (t1 - t0, longest)
    assert QApplication.activeModalWidget() is None
    assert wb.status_label.text() == ("saved campaign.imgreg: every change is now saved "
                                      "there as it happens")
    folder = tmp_path / "campaign.imgreg"
    assert ctrl.workspace_folder == folder.resolve() and "campaign.imgreg" in \
        wb.workspace_label.text()
    assert not (reference / wsfiles.LOCK).exists()  # the old folder let go
    # The folder is what the API writes, file for file.
    assert _tree(folder) == _tree(reference)
    back = Workspace.open(folder, scene=ws.scene, terrain=ws.terrain, autosave=False)
    assert not back.open_problems
    assert [p.name for p in back.photos] == [p.name for p in ws.photos]
    assert back.photo_status(back.photos[1]) == "registered"
    # ... and the workspace goes on saving there.
    ctrl.nudge("turn right 1", d_trend=1.0)
    pose = ctrl.current.pose
    back = Workspace.open(folder, scene=ws.scene, terrain=ws.terrain, autosave=False)
    assert np.allclose(back.current.pose.R, pose.R)
    idle(wb, qtbot)


@pytest.mark.parametrize("job", ["registration", "register all"])
def test_a_registration_ending_during_the_save_is_recorded_after_it_and_saved_there(
        workbench, qtbot, tmp_path, monkeypatch, job):
    wb = workbench
    ctrl = load_sample(wb, qtbot)
    ws = ctrl.workspace
    ended = threading.Event()
    _stand_in_registration(monkeypatch, ctrl, delay_s=0.3, ended=ended)
    written = _slow_writing(monkeypatch, ctrl, pause_s=0.8)  # about 2.5 s
    ps = ctrl.current
    if job == "registration":
        ctrl.run_registration(auto=False)
    else:
        ctrl.register_all(auto=False)
    ctrl.save_workspace(tmp_path / "campaign")
    qtbot.waitUntil(ended.is_set, timeout=20_000)
    qtbot.wait(300)  # its result has reached the GUI thread: it waits there
    assert ctrl.saving and ps.registration is None and ps.trials == []
    # A programmatic edit (a script's, past the modal dialog) of a photo
    # written already (the third one is being written): written again when
    # the save finishes.
    qtbot.waitUntil(lambda: len(written) >= 3, timeout=20_000)
    other = ws.photos[1]
    ws.set_sun(np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81]), "a script",
               ps=other)
    assert ctrl.saving
    wait_saved(wb, qtbot)
    qtbot.waitUntil(lambda: not ctrl.is_running(job), timeout=20_000)
    idle(wb, qtbot)
    registered = ws.photos if job == "register all" else [ps]
    assert all(p.registration is not None for p in registered)
    folder = tmp_path / "campaign.imgreg"
    assert ctrl.workspace_folder == folder.resolve()
    back = Workspace.open(folder, scene=ws.scene, terrain=ws.terrain, autosave=False)
    for p in registered:
        again = back.photos[ws.photos.index(p)]
        assert back.photo_status(again) == "registered" and len(again.trials) == 1
        assert np.allclose(again.pose.R, p.pose.R) and np.allclose(again.pose.t, p.pose.t)
    again = back.photos[1]
    assert again.sun_override_source == "a script"
    assert np.allclose(again.sun_override, other.sun_override)


def test_a_failed_save_is_one_line_and_the_workspace_stays_saved_where_it_was(
        workbench, qtbot, tmp_path, monkeypatch):
    wb = workbench
    ctrl = load_sample(wb, qtbot)
    ws = ctrl.workspace
    first = tmp_path / "first.imgreg"
    ctrl.save_workspace(first)
    wait_saved(wb, qtbot)
    idle(wb, qtbot)
    messages: list[str] = []
    ctrl.status.connect(messages.append)

    def refused(target) -> str:
        messages.clear()
        assert ctrl.save_workspace(target) is None
        assert not ctrl.saving and QApplication.activeModalWidget() is None
        return messages[-1]

    # Refused before anything is written: a folder of other files, a path under a file.
    (tmp_path / "notes.imgreg").mkdir()
    (tmp_path / "notes.imgreg" / "mine.txt").write_text("mine")
    said = refused(tmp_path / "notes.imgreg")
    assert "not empty" in said and "\n" not in said
    (tmp_path / "a_file").write_text("")
    said = refused(tmp_path / "a_file" / "campaign.imgreg")
    assert "a_file" in said and "\n" not in said
    assert (tmp_path / "notes.imgreg" / "mine.txt").read_text() == "mine"

    # The disk refuses the worker's writes, while a registration ends.
    target = tmp_path / "second.imgreg"
    write_text = wsfiles.write_text

    def not_writable(path, text, *args, **kwargs):
        if str(target) in str(path):
            time.sleep(0.3)
            raise PermissionError(13, "Permission denied", str(path))
        return write_text(path, text, *args, **kwargs)

    monkeypatch.setattr(wsfiles, "write_text", not_writable)
    ended = threading.Event()
    _stand_in_registration(monkeypatch, ctrl, delay_s=0.1, ended=ended)
    ps = ctrl.current
    ctrl.run_registration(auto=False)
    messages.clear()
    assert ctrl.save_workspace(target) is not None
    wait_saved(wb, qtbot)
    qtbot.waitUntil(lambda: ps.registration is not None, timeout=10_000)  # not lost
    idle(wb, qtbot)
    failures = [m for m in messages if "Permission denied" in m]
    assert failures and "\n" not in failures[-1] and "second.imgreg" in failures[-1]
    assert not any(m.startswith("saved second") for m in messages)
    assert QApplication.activeModalWidget() is None
    assert ctrl.workspace_folder == first.resolve() and "first.imgreg" in \
        wb.workspace_label.text()
    assert (first / wsfiles.LOCK).exists() and not (target / wsfiles.LOCK).exists()
    # Still saved where it was: the registration, and an edit after the failure.
    monkeypatch.setattr(wsfiles, "write_text", write_text)
    ctrl.nudge("turn left 1", d_trend=-1.0)
    back = Workspace.open(first, scene=ws.scene, terrain=ws.terrain, autosave=False)
    again = back.photos[ws.photos.index(ps)]
    assert back.photo_status(again) == "registered"
    assert again.history.label == "turn left 1"
