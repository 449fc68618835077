"""A campaign's workspace over days of work: the folder moved, files
replaced on disk under the same name after the photos were registered on them."""

from __future__ import annotations

import shutil

import pytest

from napari_imgreg.errors import InputError
from napari_imgreg.io import workspace_files as wsfiles
from napari_imgreg.registration.params import RegistrationParams
from napari_imgreg.registration.pipeline import Registration, Trial
from napari_imgreg.sample import sample_scene
from napari_imgreg.workspace import Workspace


def _registration(ps) -> Registration:
    """A registered result at the photo's prior pose (what was registered
    does not matter here, only that it was)."""
    trial = Trial(index=0, params=RegistrationParams(), metrics={"inliers_3d": 100}, q=0.8,
                  grade="good", hints=[], pose=ps.pose, start_pose=ps.pose, rounds=1,
                  converged=True, verified=True, residual_flow_px=0.5)
    return Registration(status="registered", photo=ps.name, intrinsics=ps.intrinsics,
                        pose=ps.pose, prior=ps.prior, metrics=trial.metrics, q=0.8, grade="good",
                        hints=[], trials=[trial], timings_s={"total": 1.0}, best_trial=0)


@pytest.fixture
def scene_dir(tmp_path):
    src = sample_scene("small")
    out = tmp_path / "scene"
    shutil.copytree(src, out, ignore=shutil.ignore_patterns("IMG_0003.*", "truth*", "orient"))
    return out


def _campaign(scene_dir, folder, photos=None) -> Workspace:
    """A workspace of the scene and its photos (default: all), saved to ``folder``."""
    ws = Workspace()
    ws.open_scene(scene_dir / "outcrop.obj", dem=scene_dir / "dem.tif")
    ws.add_photos(photos if photos is not None else sorted(scene_dir.glob("IMG_*.jpg")))
    ws.save(folder)
    return ws


def test_a_model_or_photo_replaced_after_registering_is_said_on_opening(scene_dir, tmp_path):
    folder = tmp_path / "campaign.imgreg"
    ws = _campaign(scene_dir, folder)
    for ps in ws.photos:
        ws.record_registration(_registration(ps), "Auto", ps, pose_if_not_current=True)
    ws.detach()
    again = Workspace.open(folder, autosave=False)
    assert again.open_problems == [] and again.open_warnings == []
    assert again.photos[0].registered_on["model"] == wsfiles.file_fingerprint(
        scene_dir / "outcrop.obj")

    # Days later: the model re-exported under the same name, and a photo
    # overwritten by another one of the same name.
    with open(scene_dir / "outcrop.obj", "a") as fh:
        fh.write("# re-exported\n")
    shutil.copy(scene_dir / "IMG_0001.jpg", scene_dir / "IMG_0002.jpg")
    reopened = Workspace.open(folder)
    assert len(reopened.photos) == 2  # opened all the same, nothing of them lost
    model, photo = reopened.open_warnings
    assert model.startswith("the model outcrop.obj has changed since 2 photo(s) were "
                            "registered on it (IMG_0001.jpg, IMG_0002.jpg; ")
    assert "register them again" in model
    assert photo.startswith("IMG_0002.jpg: the photo file ") and "register it again" in photo
    assert reopened.open_problems == reopened.open_warnings

    # Registered again: that photo is no longer said to be on the old model.
    ps = reopened.photos[0]
    reopened.record_registration(_registration(ps), "Auto", ps)
    reopened.detach()
    last = Workspace.open(folder, autosave=False)
    assert len(last.open_warnings) == 2
    assert "since 1 photo(s) were registered on it (IMG_0002.jpg; " in last.open_warnings[0]


def test_a_file_fingerprint_ignores_dates_and_sees_content(tmp_path):
    a, b = tmp_path / "a.bin", tmp_path / "b.bin"
    a.write_bytes(bytes(range(256)) * 1000)
    shutil.copyfile(a, b)  # a copy (new dates): the same file
    assert wsfiles.file_fingerprint(a) == wsfiles.file_fingerprint(b)
    b.write_bytes(bytes(range(256)) * 999 + bytes(reversed(range(256))))  # its end edited
    assert wsfiles.fingerprint_difference(wsfiles.file_fingerprint(a),
                                          wsfiles.file_fingerprint(b)) == "same size, other content"
    assert wsfiles.file_fingerprint(tmp_path / "missing") is None
    assert wsfiles.fingerprint_difference(None, wsfiles.file_fingerprint(a)) == ""


def test_a_workspace_moved_with_or_without_its_model(scene_dir, tmp_path):
    folder = tmp_path / "campaign.imgreg"
    ws = _campaign(scene_dir, folder, [scene_dir / "IMG_0001.jpg"])
    ws.detach()
    # The whole campaign (workspace and data) moved elsewhere: the relative paths find it.
    moved = tmp_path / "elsewhere"
    moved.mkdir()
    shutil.move(folder, moved / "renamed.imgreg")
    shutil.move(scene_dir, moved / "scene")
    opened = Workspace.open(moved / "renamed.imgreg", autosave=False)
    assert [ps.photo.path for ps in opened.photos] == [moved / "scene" / "IMG_0001.jpg"]
    # The workspace copied without its model: one line saying where it was looked for.
    alone = tmp_path / "alone"
    alone.mkdir()
    shutil.copytree(moved / "renamed.imgreg", alone / "campaign.imgreg")
    shutil.move(moved / "scene", tmp_path / "gone")
    with pytest.raises(InputError, match=r"workspace.json: the mesh file is not found \(looked "
                                         r"for .*alone/scene/outcrop.obj and .*/scene/"
                                         r"outcrop.obj\): put it back there, or set "
                                         r"scene.mesh.path in this file$"):
        Workspace.open(alone / "campaign.imgreg", autosave=False)


def test_a_projection_older_than_the_drawings_or_poses_is_said(scene_dir, tmp_path, capsys):
    from napari_imgreg.interpret.project import Interpretation

    folder = tmp_path / "campaign.imgreg"
    ws = _campaign(scene_dir, folder)
    first, second = ws.photos
    line = Interpretation("LineString", [[200.0, 300.0], [700.0, 330.0]], {"label": "sandstone"})
    ws.add_interpretation(line, ps=first)
    assert ws.projection_out_of_date() == []  # nothing projected yet
    ws.project_interpretations()
    assert ws.projection_out_of_date() == []
    ws.nudge("turn right 1", d_trend=1.0)  # the first photo's pose, after it was projected
    assert ws.projection_out_of_date() == [first]
    ws.undo()
    assert ws.projection_out_of_date() == []
    ws.add_interpretation(line, ps=second)  # drawn since
    assert ws.projection_out_of_date() == [second]
    ws.detach()
    # Said after reopening, by info and by export (which still writes the last projection).
    from napari_imgreg.cli import main

    reopened = Workspace.open(folder, autosave=False)
    assert reopened.projection_out_of_date() == [reopened.photos[1]]
    capsys.readouterr()
    assert main(["workspace", "export", str(folder), "--out", str(tmp_path / "l.geojson")]) == 0
    assert ("note: the projection is older than the drawings or poses of 1 photo(s) "
            "(IMG_0002.jpg): run 'workspace project'") in capsys.readouterr().out
    # A projection recorded without saying what from (the Interpret tab's) is
    # taken to be of the photos its features name: here the first only.
    again = Workspace.open(folder)
    features = [f for f in again.features_3d if f.source == "IMG_0001.jpg"]
    again.record_projection(features, again.measurements)
    assert again.projection_out_of_date() == [again.photos[1]]
    again.project_interpretations()
    assert again.projection_out_of_date() == []
    again.detach()


def test_a_photo_missing_for_a_while_keeps_its_place_in_the_campaign(scene_dir, tmp_path):
    folder = tmp_path / "campaign.imgreg"
    ws = _campaign(scene_dir, folder)
    ws.detach()
    (scene_dir / "IMG_0001.jpg").rename(tmp_path / "IMG_0001.jpg")  # on a disk not mounted today
    today = Workspace.open(folder)
    assert [ps.name for ps in today.photos] == ["IMG_0002.jpg"]
    today.nudge("turn right 1", d_trend=1.0)
    today.select_photo(0)  # the manifest is written again, the missing photo kept in it
    today.detach()
    (tmp_path / "IMG_0001.jpg").rename(scene_dir / "IMG_0001.jpg")
    back = Workspace.open(folder, autosave=False)
    assert [ps.name for ps in back.photos] == ["IMG_0001.jpg", "IMG_0002.jpg"]  # in its order
    assert back.current is back.photos[1]  # and the photo worked on stays current


def test_register_with_a_photo_that_cannot_be_opened_is_not_a_success(scene_dir, tmp_path,
                                                                        capsys):
    """`workspace register` with one photo unreadable registered the others
    and exited 0, as if the campaign were done."""
    from napari_imgreg.cli import main

    folder = tmp_path / "campaign.imgreg"
    ws = _campaign(scene_dir, folder)
    ws.select_photo(1)
    ws.record_registration(_registration(ws.current), "Auto")  # the other one is done
    ws.detach()
    (scene_dir / "IMG_0001.jpg").write_bytes(b"\xff\xd8 not a whole JPEG")
    assert main(["workspace", "register", str(folder)]) == 2
    out, err = capsys.readouterr()
    assert "not opened: IMG_0001: " in out and "0 photo(s) to register (1 already done)" in out
    (line,) = err.splitlines()
    assert line.startswith("napari-imgreg workspace register: error: not registered, could not "
                           "be opened: IMG_0001: ")
    # Asked for the photos that open, it is their outcome alone.
    assert main(["workspace", "register", str(folder), "--photo", "IMG_0002.jpg"]) == 0


def test_what_a_full_disk_kept_from_being_saved_is_saved_by_the_next_change(scene_dir, tmp_path,
                                                                            monkeypatch):
    import errno

    from napari_imgreg import _atomic
    from napari_imgreg.interpret.project import Interpretation

    folder = tmp_path / "campaign.imgreg"
    ws = _campaign(scene_dir, folder)
    messages = []
    ws.autosave_failed.connect(messages.append)

    def disk_full(path):
        raise OSError(errno.ENOSPC, "No space left on device")  # as write() says it: no file

    monkeypatch.setattr(_atomic, "fsync_file", disk_full)
    second = ws.photos[1]
    line = Interpretation("LineString", [[200.0, 300.0], [700.0, 330.0]], {"label": "sandstone"})
    ws.add_interpretation(line, ps=second)  # drawn on a photo not shown: its save fails
    # The file it was writing named (a full disk's own error names none).
    assert messages == [f"{folder / 'photos' / 'IMG_0002' / 'LINES.geojson'}: cannot write "
                        "(No space left on device)"], messages
    assert not (folder / "photos" / "IMG_0002" / "LINES.geojson").read_text().count("sandstone")
    features = ws.project_interpretations()  # and its projection: not saved either
    assert not (folder / "LINES3D.geojson").exists()
    monkeypatch.undo()
    ws.nudge("turn right 1", d_trend=1.0)  # the next change, on another photo
    ws.detach()
    reopened = Workspace.open(folder, autosave=False)
    assert [len(ps.interpretations) for ps in reopened.photos] == [0, 1]
    assert reopened.photos[0].history.label == "turn right 1"
    assert len(reopened.features_3d) == len(features) == 1  # and the manifest names it
    assert reopened.projection_out_of_date() == []
    assert not list(folder.rglob(".*"))  # no temporary file left behind


@pytest.mark.parametrize("edit", [
    lambda state: state.update(history="x"),  # used to stop the opening with a traceback
    lambda state: state.update(registration=[1]),
    lambda state: state.update(runs="many"),
])
def test_a_hand_edited_photo_state_is_one_line_and_the_rest_opens(scene_dir, tmp_path, edit):
    import json

    folder = tmp_path / "campaign.imgreg"
    ws = _campaign(scene_dir, folder)
    ws.detach()
    state_file = folder / "photos" / "IMG_0001" / "photo.json"
    state = json.loads(state_file.read_text())
    edit(state)
    state_file.write_text(json.dumps(state))
    opened = Workspace.open(folder)
    assert [ps.name for ps in opened.photos] == ["IMG_0002.jpg"]
    (problem,) = opened.open_problems
    assert problem.startswith(f"IMG_0001: {folder / 'photos' / 'IMG_0001'}: a file there holds a "
                              "field this napari-imgreg cannot read (")
    assert "\n" not in problem
    opened.nudge("turn right 1", d_trend=1.0)
    opened.detach()
    assert json.loads(state_file.read_text()) == state  # kept as it was, to be mended


@pytest.mark.parametrize("written, accepted", [(True, True), ("no", False), ("false", False),
                                               (1, False), (False, False)])
def test_only_a_json_true_accepts_a_pose(scene_dir, tmp_path, written, accepted):
    """A hand-written "no" is a non-empty string: read as truthy it accepted the pose."""
    import json

    folder = tmp_path / "campaign.imgreg"
    ws = _campaign(scene_dir, folder)
    ws.detach()
    state_file = folder / "photos" / "IMG_0001" / "photo.json"
    state = json.loads(state_file.read_text())
    state["accepted"] = written
    state_file.write_text(json.dumps(state))
    opened = Workspace.open(folder, autosave=False)
    assert opened.photos[0].accepted is accepted


# ------------------------------------------------------- save as, in steps
def _disk_full_under(folder, monkeypatch):
    """Writes of the workspace's text files under ``folder`` fail as on a full
    disk; returns the real writer, to put back."""
    write_text = wsfiles.write_text

    def disk_full(path, text, *args, **kwargs):
        if str(folder) in str(path):
            raise OSError(28, "No space left on device", str(path))
        return write_text(path, text, *args, **kwargs)

    monkeypatch.setattr(wsfiles, "write_text", disk_full)
    return write_text


def _pose_equal(a, b) -> bool:
    import numpy as np

    return np.allclose(a.R, b.R) and np.allclose(a.t, b.t)


def test_a_save_as_in_steps_keeps_the_old_folder_until_it_is_finished(scene_dir, tmp_path):
    old, new = tmp_path / "old.imgreg", tmp_path / "new.imgreg"
    ws = _campaign(scene_dir, old)
    saving = ws.begin_save(new)
    assert saving.total == 2 and saving.folder == new
    assert (new / wsfiles.LOCK).exists()  # taken at once: nobody else saves there meanwhile
    progress = list(saving.steps())
    assert progress == [(1, 2), (2, 2)]
    # Written, not yet bound: the workspace is still saved where it was.
    assert ws.folder == old and (old / wsfiles.LOCK).exists()
    assert not saving.edited_meanwhile
    assert saving.finish() == new / "workspace.json"
    assert ws.folder == new and not (old / wsfiles.LOCK).exists()
    ws.nudge("turn right 1", d_trend=1.0)  # saved in the new folder from now on
    pose = ws.current.pose
    ws.detach()
    back = Workspace.open(new, autosave=False)
    assert [p.name for p in back.photos] == [p.name for p in ws.photos]
    assert _pose_equal(back.current.pose, pose)
    assert not _pose_equal(Workspace.open(old, autosave=False).current.pose, pose)


def test_an_edit_made_while_a_save_as_writes_is_in_the_folder_when_it_finishes(scene_dir,
                                                                                 tmp_path):
    """The workbench keeps the workspace still while its worker writes; an
    edit that happens all the same is written when the save finishes."""
    old, new = tmp_path / "old.imgreg", tmp_path / "new.imgreg"
    ws = _campaign(scene_dir, old)
    saving = ws.begin_save(new)
    steps = saving.steps()
    next(steps)  # the first photo written
    ws.nudge("turn right 2", d_trend=2.0)  # the current (first) photo, written already
    ws.record_registration(_registration(ws.photos[1]), "Auto", ws.photos[1],
                           pose_if_not_current=True)
    for _ in steps:
        pass
    assert saving.edited_meanwhile
    saving.finish()
    pose = ws.current.pose
    ws.detach()
    back = Workspace.open(new, autosave=False)
    assert _pose_equal(back.current.pose, pose)
    assert back.current.history.label == "turn right 2"
    assert back.photo_status(back.photos[1]) == "registered"


def test_a_failed_or_abandoned_save_as_leaves_the_workspace_saved_where_it_was(
        scene_dir, tmp_path, monkeypatch):
    old, new = tmp_path / "old.imgreg", tmp_path / "new.imgreg"
    ws = _campaign(scene_dir, old)
    with pytest.raises(InputError, match="saved already"):
        ws.begin_save(old)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="not empty"):
        ws.begin_save(tmp_path / "full")

    write_text = _disk_full_under(new, monkeypatch)
    saving = ws.begin_save(new)
    with pytest.raises(OSError, match="No space"):
        saving.write()
    assert ws.folder == old and (old / wsfiles.LOCK).exists()
    assert not (new / wsfiles.LOCK).exists()  # let go: another save may take it
    with pytest.raises(RuntimeError):
        saving.finish()
    monkeypatch.setattr(wsfiles, "write_text", write_text)

    saving = ws.begin_save(new)  # abandoned halfway (the workbench closing)
    next(saving.steps())
    saving.abandon()
    assert ws.folder == old and not (new / wsfiles.LOCK).exists()
    ws.nudge("look up 1", d_plunge=-1.0)  # still saved into the old folder
    pose = ws.current.pose
    ws.detach()
    assert _pose_equal(Workspace.open(old, autosave=False).current.pose, pose)


def test_save_into_its_own_folder_writes_what_changed_and_moves_nothing(scene_dir, tmp_path):
    """``ws.save(ws.folder)`` made a second set of photo folders (IMG_0001_2, ...)
    beside the first, which stayed as orphans."""
    folder = tmp_path / "campaign.imgreg"
    ws = _campaign(scene_dir, folder)
    photo_dirs = sorted(p.name for p in (folder / wsfiles.PHOTOS_DIR).iterdir())
    assert ws.save(folder) == folder / "workspace.json"
    assert ws.folder == folder and (folder / wsfiles.LOCK).exists()
    assert sorted(p.name for p in (folder / wsfiles.PHOTOS_DIR).iterdir()) == photo_dirs
    ws.nudge("turn left 1", d_trend=-1.0)  # still autosaved there
    pose = ws.current.pose
    ws.detach()
    assert _pose_equal(Workspace.open(folder, autosave=False).current.pose, pose)


def test_a_failed_save_leaves_the_workspace_saved_where_it_was(scene_dir, tmp_path, monkeypatch):
    """The API's save detached first: a save that failed left the workspace
    saved nowhere, silently."""
    old, new = tmp_path / "old.imgreg", tmp_path / "new.imgreg"
    ws = _campaign(scene_dir, old)
    write_text = _disk_full_under(new, monkeypatch)
    with pytest.raises(OSError, match="No space"):
        ws.save(new)
    assert ws.folder == old and (old / wsfiles.LOCK).exists()
    assert not (new / wsfiles.LOCK).exists()
    monkeypatch.setattr(wsfiles, "write_text", write_text)
    ws.nudge("look down 1", d_plunge=1.0)
    pose = ws.current.pose
    assert ws.save(new) == new / "workspace.json" and ws.folder == new
    assert not (old / wsfiles.LOCK).exists()
    ws.detach()
    assert _pose_equal(Workspace.open(old, autosave=False).current.pose, pose)
    assert _pose_equal(Workspace.open(new, autosave=False).current.pose, pose)
