"""A workspace on disk: saved as it changes, reopened equal, migrated, crash-safe.

The workspace is the sample's (as in tests/test_workspace.py); each test saves
it into a workspace folder, changes it, and reads the folder back — field by
field, through the files a crash leaves, and from a version-0 manifest.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from napari_imgreg.errors import InputError
from napari_imgreg.geo import Georef
from napari_imgreg.interpret.project import Interpretation
from napari_imgreg.io import workspace_files as wsfiles
from napari_imgreg.registration.manual import ManualSolution
from napari_imgreg.sample import load_truth, sample_scene
from napari_imgreg.workspace import Workspace, read_photos, read_scene

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def sample():
    folder = sample_scene("small")
    scene, terrain = read_scene(folder / "outcrop.obj", dem=folder / "dem.tif")
    loaded, errors = read_photos(sorted(folder.glob("IMG_*.jpg")), scene)
    assert not errors
    return folder, scene, terrain, loaded


def _keypoints_only(params):
    for name in ("sun_relight", "area_match", "edge_align", "dense_refine"):
        setattr(params, name, False)
    return params


@pytest.fixture
def ws(sample):
    folder, scene, terrain, loaded = sample
    cv2.setRNGSeed(0)
    ws = Workspace()
    ws.load_scene(scene, terrain, {"mesh": folder / "outcrop.obj", "dem": folder / "dem.tif"})
    ws.add_loaded_photos(loaded)
    _keypoints_only(ws.params)
    return ws


def _bed_pixels(ps, min_px=150.0):
    """A true bed boundary in the photo, pixels (from the sample's truth)."""
    truth = load_truth(ps.photo.path.parent)
    pt = truth.photos[ps.name]
    for feat in truth.lines["features"]:
        xyz = np.asarray(feat["geometry"]["coordinates"])
        px = pt.pose.project(pt.intrinsics, xyz)
        ok = np.isfinite(px).all(1) & (px > 5).all(1) & (px[:, 0] < pt.intrinsics.width - 5)
        ok &= px[:, 1] < pt.intrinsics.height - 5
        if ok.all() and np.linalg.norm(np.diff(px, axis=0), axis=1).sum() > min_px:
            return px
    raise AssertionError("no bed boundary in view")


def _json(data):
    return json.loads(wsfiles.json_text(data))


def _same_pose(a, b):
    assert (a is None) == (b is None)
    if a is not None:
        np.testing.assert_array_equal(a.R, b.R)
        np.testing.assert_array_equal(a.t, b.t)


def assert_same_workspace(a: Workspace, b: Workspace) -> None:
    """Every saved field of two workspaces, photo by photo."""
    assert {k: str(v) for k, v in a.scene_files.items()} == b.scene_files
    assert a.params.to_dict() == b.params.to_dict()
    assert a.current_index == b.current_index
    assert [ps.photo.path for ps in a.photos] == [ps.photo.path for ps in b.photos]
    for pa, pb in zip(a.photos, b.photos):
        assert pa.record_path == pb.record_path
        assert pa.intrinsics == pb.intrinsics
        assert _json(pa.prior.pose.to_dict()) == _json(pb.prior.pose.to_dict())
        assert pa.prior.sigma == pb.prior.sigma and pa.prior.assumptions == pb.prior.assumptions
        assert pa.prior.intrinsics == pb.prior.intrinsics
        np.testing.assert_array_equal(pa.prior.sun, pb.prior.sun)
        # The pose and its undo/redo stacks, exactly.
        _same_pose(pa.pose, pb.pose)
        assert pa.history.label == pb.history.label
        for sa, sb in ((pa.history._undo, pb.history._undo), (pa.history._redo, pb.history._redo)):
            assert [lab for _, lab in sa] == [lab for _, lab in sb]
            for (qa, _), (qb, _) in zip(sa, sb):
                _same_pose(qa, qb)
        assert pa.runs == pb.runs and pa.selected_trial == pb.selected_trial
        assert [(r.run, r.kind, r.label) for r in pa.trials] == [(r.run, r.kind, r.label)
                                                                  for r in pb.trials]
        for ra, rb in zip(pa.trials, pb.trials):
            assert _json(ra.trial.to_dict()) == _json(rb.trial.to_dict())
            _same_pose(ra.trial.start_pose, rb.trial.start_pose)
            ca, cb = ra.trial.correspondences, rb.trial.correspondences
            assert (ca is None) == (cb is None)
            if ca is not None:
                for name in ("photo_points", "render_points", "feature_inlier", "lifted",
                             "pose_inlier"):
                    np.testing.assert_array_equal(getattr(ca, name), getattr(cb, name))
        assert (pa.registration is None) == (pb.registration is None)
        if pa.registration is not None:
            assert _json(pa.registration.to_dict()) == _json(pb.registration.to_dict())
            # Its trials are the photo's trial records, as in the live session.
            ids = {id(r.trial) for r in pb.trials}
            assert all(id(t) in ids for t in pb.registration.trials)
            assert pb.registration.assumptions == pa.registration.assumptions
        np.testing.assert_array_equal(pa.photo_points_px, pb.photo_points_px)
        np.testing.assert_array_equal(pa.reference_points_px, pb.reference_points_px)
        assert pa.reference_source == pb.reference_source
        assert (pa.reference is None) == (pb.reference is None)
        if pa.reference is not None:
            _same_pose(pa.reference.cam_from_world, pb.reference.cam_from_world)
            np.testing.assert_array_equal(pa.reference.rgb, pb.reference.rgb)  # rendered again
        np.testing.assert_array_equal(pa.sun_override, pb.sun_override)
        assert pa.sun_override_source == pb.sun_override_source
        assert (pa.manual_solution is None) == (pb.manual_solution is None)
        if pa.manual_solution is not None:
            ma, mb = pa.manual_solution, pb.manual_solution
            assert (ma.ok, ma.method, ma.focal_solved, ma.intrinsics) == (
                mb.ok, mb.method, mb.focal_solved, mb.intrinsics)
            _same_pose(ma.pose, mb.pose)
            np.testing.assert_array_equal(ma.errors_px, mb.errors_px)
            np.testing.assert_array_equal(ma.inliers, mb.inliers)
        # Drawings: at the pixel GeoJSON's precision (1/1000 px).
        assert [(i.geometry, i.properties) for i in pa.interpretations] == [
            (i.geometry, i.properties) for i in pb.interpretations]
        for ia, ib in zip(pa.interpretations, pb.interpretations):
            np.testing.assert_allclose(ia.pixels, ib.pixels, atol=5e-4)
    # 3D features at LINES3D.geojson's precision (0.1 mm); measurements exactly.
    assert [(f.id, f.kind, f.label, f.source) for f in a.features_3d] == [
        (f.id, f.kind, f.label, f.source) for f in b.features_3d]
    for fa, fb in zip(a.features_3d, b.features_3d):
        assert len(fa.parts) == len(fb.parts)
        for qa, qb in zip(fa.parts, fb.parts):
            np.testing.assert_allclose(qa, qb, atol=5e-5)
    assert len(a.measurements) == len(b.measurements)
    for ma, mb in zip(a.measurements, b.measurements):
        da, db = vars(ma).copy(), vars(mb).copy()
        np.testing.assert_array_equal(da.pop("centroid"), db.pop("centroid"))
        assert da == db


# ------------------------------------------------------------- round trip
def test_a_saved_workspace_reopens_equal_field_by_field(ws, sample, tmp_path):
    folder = tmp_path / "campaign.imgreg"
    assert ws.save(folder) == folder / "workspace.json"
    assert ws.folder == folder
    failures = []
    ws.autosave_failed.connect(failures.append)

    # Photo 1: registered, nudged, one nudge undone (a redo waiting), drawn on, projected.
    reg = ws.register(auto=False)
    assert reg.trials and reg.trials[0].correspondences is not None
    ws.nudge("turn right 1", d_trend=1.0)
    ws.nudge("look down 0.5", d_plunge=0.5)
    ws.undo()
    ps = ws.current
    ws.add_interpretation(Interpretation("LineString", _bed_pixels(ps), {"label": "sandstone"}))
    ws.add_interpretation(Interpretation("Polygon", [[300, 300], [380, 300], [380, 360]],
                                         {"label": "facet", "color": "#123456"}))
    ws.project_interpretations()
    assert ws.features_3d and ws.measurements
    # Photo 2: a reference render, control points, the sun by hand, a manual solution.
    ws.select_photo(1)
    ws.make_reference()
    ws.set_pair_points([[10.5, 20.25], [30.0, 40.0], [50.0, 60.0]], [[1.0, 2.0], [3.0, 4.5]])
    ws.set_sun_angles(120.0, 30.0)
    ws.current.manual_solution = ManualSolution(
        ok=True, pose=ws.current.pose, intrinsics=ws.current.intrinsics,
        errors_px=np.array([0.5, np.nan]), inliers=np.array([True, False]), threshold_px=4.0,
        method="pnp")
    ws.nudge("forward 2", forward=2.0)  # an event: the photo (and its solution) are saved
    assert failures == []

    files = sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())
    assert files == sorted([
        "workspace.json", "workspace.lock", "LINES3D.geojson", "MEASUREMENTS.csv", "measurements.json",
        *(f"photos/IMG_000{k}/{name}" for k in (1, 2, 3)
          for name in ("photo.json", "trials.json", "LINES.geojson")),
        "photos/IMG_0001/RESULT.json", "photos/IMG_0001/correspondences.npz"])
    manifest = json.loads((folder / "workspace.json").read_text())
    assert manifest["format"] == "napari-imgreg workspace" and manifest["version"] == 1
    assert manifest["scene"]["mesh"]["path"] == os.path.relpath(
        sample[0] / "outcrop.obj", folder)  # relative where it can be
    assert manifest["current"] == "IMG_0002" and len(manifest["photos"]) == 3
    # RESULT.json is the registration's own (docs/formats.md §4).
    result = json.loads((folder / "photos/IMG_0001/RESULT.json").read_text())
    assert result == _json(reg.to_dict())

    # Reopened from the files alone (the scene read again from its paths).
    again = Workspace.open(folder, autosave=False)  # read-only: ws still saves there
    assert again.open_problems == [] and again.folder is None
    assert_same_workspace(ws, again)
    # ... and from the scene in memory, equal again, and saving there in its turn.
    ws.detach()
    again = Workspace.open(folder, scene=ws.scene, terrain=ws.terrain)
    assert again.folder == folder
    assert_same_workspace(ws, again)
    # The reopened workspace goes on where the first left off: a redo, then saved.
    again.select_photo(0)
    assert again.redo() and again.current.history.label == "look down 0.5"
    third = Workspace.open(folder, scene=ws.scene, terrain=ws.terrain, autosave=False)
    assert third.photos[0].history.label == "look down 0.5"
    assert third.current_index == 0


def test_each_change_writes_only_its_photo_and_the_manifest_last(ws, tmp_path, monkeypatch):
    folder = tmp_path / "w.imgreg"
    ws.save(folder)
    written = []
    real = wsfiles.write_text
    monkeypatch.setattr(wsfiles, "write_text",
                        lambda path, text: (written.append(Path(path).relative_to(folder)
                                                           .as_posix()), real(path, text)))
    ws.nudge("turn left 1", d_trend=-1.0)
    assert written == ["photos/IMG_0001/photo.json"]  # one small file, no other photo's
    written.clear()
    ws.set_sun_angles(90.0, 20.0)
    assert written == ["photos/IMG_0001/photo.json"]
    written.clear()
    ws.select_photo(2)  # the manifest only
    assert written == ["workspace.json"]
    written.clear()
    ws.add_interpretation(Interpretation("LineString", [[10, 10], [200, 50]], {"label": "fault"}),
                          ps=ws.photos[1])
    assert written == []  # only the photo's pixel GeoJSON, written by interpret.files
    assert json.loads((folder / "photos/IMG_0002/LINES.geojson").read_text())["features"]
    written.clear()
    # A new photo: its files first, the manifest naming it last.
    sample_folder = ws.photos[0].photo.path.parent
    for name in ("IMG_0002.jpg", "IMG_0002.json"):
        shutil.copy(sample_folder / name, tmp_path / f"copy_{name}")
    ws.add_photo(tmp_path / "copy_IMG_0002.jpg")
    assert written[-1] == "workspace.json"
    assert "photos/copy_IMG_0002/photo.json" in written[:-1]
    assert not any(p.name.startswith(".") for p in folder.rglob("*"))  # no temporary left


def test_autosave_failure_is_one_line_and_loses_nothing(ws, tmp_path, monkeypatch):
    folder = tmp_path / "w.imgreg"
    ws.save(folder)
    before = (folder / "photos/IMG_0001/photo.json").read_text()
    messages = []
    ws.autosave_failed.connect(messages.append)

    def full(path, text):
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr(wsfiles, "write_text", full)
    ws.nudge("turn left 3", d_trend=-3.0)  # the edit itself goes through
    assert ws.current.history.label == "turn left 3"
    assert len(messages) == 1 and "No space left" in messages[0] and "\n" not in messages[0]
    assert (folder / "photos/IMG_0001/photo.json").read_text() == before
    monkeypatch.undo()
    ws.nudge("turn left 1", d_trend=-1.0)  # the next change saves both
    reopened = Workspace.open(folder, scene=ws.scene, terrain=ws.terrain, autosave=False)
    assert reopened.photos[0].history.label == "turn left 1"
    assert [lab for _, lab in reopened.photos[0].history._undo][-1] == "turn left 3"


# ---------------------------------------------------------- bad workspaces
@pytest.mark.parametrize("version, words", [
    (2, "workspace version 2 is newer than this napari-imgreg reads (up to 1)"),
    ("1.0", "workspace version '1.0' is not known"),
    (-1, "workspace version -1 is not known"),
])
def test_an_unknown_version_is_refused_in_one_line(tmp_path, version, words):
    folder = tmp_path / "new.imgreg"
    folder.mkdir()
    doc = {"format": "napari-imgreg workspace", "version": version, "photos": []}
    (folder / "workspace.json").write_text(json.dumps(doc))
    with pytest.raises(InputError) as info:
        Workspace.open(folder)
    message = str(info.value)
    assert message.startswith(str(folder / "workspace.json") + ": ") and words in message
    assert "\n" not in message
    assert json.loads((folder / "workspace.json").read_text()) == doc  # untouched
    assert sorted(p.name for p in folder.iterdir()) == ["workspace.json"]


def test_not_a_workspace(tmp_path, ws):
    with pytest.raises(InputError, match="no such file: not a napari-imgreg workspace"):
        Workspace.open(tmp_path)
    (tmp_path / "workspace.json").write_text('{"format": "something else", "version": 1}')
    with pytest.raises(InputError, match="format 'something else'"):
        Workspace.open(tmp_path)
    (tmp_path / "workspace.json").write_text("{not json")
    with pytest.raises(InputError, match="invalid JSON at line 1"):
        Workspace.open(tmp_path)
    # Saving into a folder that holds other things is refused (nothing written).
    other = tmp_path / "photos_of_mine"
    other.mkdir()
    (other / "IMG_9.jpg").write_bytes(b"")
    with pytest.raises(InputError, match="not empty and holds no workspace.json"):
        ws.save(other)
    assert [p.name for p in other.iterdir()] == ["IMG_9.jpg"] and ws.folder is None


def test_a_photo_that_moved_is_reported_and_kept(ws, sample, tmp_path):
    src = sample[0]
    photos = tmp_path / "photos_in"
    photos.mkdir()
    for name in ("IMG_0002.jpg", "IMG_0002.json"):
        shutil.copy(src / name, photos / name)
    ws.add_photo(photos / "IMG_0002.jpg")  # a copy we can take away
    folder = tmp_path / "w.imgreg"
    ws.save(folder)
    ws.detach()
    (photos / "IMG_0002.jpg").rename(tmp_path / "elsewhere.jpg")
    again = Workspace.open(folder, scene=ws.scene, terrain=ws.terrain)
    assert len(again.photos) == 3 and len(again.open_problems) == 1
    problem = again.open_problems[0]
    assert "IMG_0002.jpg: no such file" in problem and "\n" not in problem
    again.nudge("turn right 1", d_trend=1.0)
    again.select_photo(1)  # the manifest is written again: the missing photo stays in it
    manifest = json.loads((folder / "workspace.json").read_text())
    assert len(manifest["photos"]) == 4
    (tmp_path / "elsewhere.jpg").rename(photos / "IMG_0002.jpg")
    assert len(Workspace.open(folder, scene=ws.scene, terrain=ws.terrain,
                              autosave=False).photos) == 4


# --------------------------------------------------------------- migration
def test_a_version_0_workspace_is_migrated(ws, sample, tmp_path):
    """The single-file state of before (Workspace.to_dict(), no format or version)."""
    folder = tmp_path / "old.imgreg"
    folder.mkdir()
    src = sample[0]
    ps = ws.photos[1]
    pose = ps.pose.to_dict()
    old = {
        "scene": {"mesh": str(src / "outcrop.obj"), "dem": str(src / "dem.tif")},
        "params": {"match_width": 640, "max_trials": 3},
        "photos": [
            {"photo": str(src / "IMG_0001.jpg"), "record": str(src / "IMG_0001.json"),
             "camera": ws.photos[0].intrinsics.to_dict(), "pose": ws.photos[0].pose.to_dict(),
             "pose_label": "prior", "runs": 0, "trials": [], "selected_trial": None,
             "pairs": {"photo_px": [], "reference_px": [], "reference_source": "",
                       "reference_pose": None},
             "sun": None, "interpretations": []},
            {"photo": str(src / "IMG_0002.jpg"), "record": str(src / "IMG_0002.json"),
             "camera": ps.intrinsics.to_dict(), "pose": pose, "pose_label": "turned by hand",
             "runs": 1, "selected_trial": 0,
             "trials": [{"run": 1, "kind": "Run", "trial": {
                 "index": 0, "origin": "prior", "params": {"match_width": 640}, "metrics": {
                     "inliers_3d": 120}, "Q": 0.9, "grade": "good", "hints": [], "rounds": 2,
                 "converged": True, "verified": True, "residual_flow_px": 0.8,
                 "adaptation": "", "pose": pose, "seconds": 3.2}}],
             "pairs": {"photo_px": [[10.0, 20.0]], "reference_px": [], "reference_source": "",
                       "reference_pose": None},
             "sun": {"direction": [0.0, 0.6, 0.8], "source": "hand setting"},
             "interpretations": [{"geometry": "LineString", "pixels": [[1.0, 2.0], [300.0, 400.0]],
                                  "properties": {"label": "fault"}}]},
        ],
        "current": 1,
    }
    (folder / "workspace.json").write_text(json.dumps(old))
    again = Workspace.open(folder)
    assert again.open_problems == []
    assert again.params.match_width == 640 and again.params.max_trials == 3
    assert again.current_index == 1 and again.scene_files["mesh"] == str(src / "outcrop.obj")
    p2 = again.current
    _same_pose(p2.pose, ps.pose)
    assert p2.history.label == "turned by hand" and not p2.history.can_undo
    assert p2.runs == 1 and p2.selected_trial == 0 and p2.trials[0].label.startswith("Run 1")
    t = p2.trials[0].trial
    assert t.q == 0.9 and t.grade == "good" and t.params.match_width == 640 and t.seconds == 3.2
    _same_pose(t.start_pose, p2.prior.pose)  # version 0 had no start pose
    np.testing.assert_array_equal(p2.photo_points_px, [[10.0, 20.0]])
    np.testing.assert_array_equal(p2.sun_override, [0.0, 0.6, 0.8])
    assert [(i.geometry, i.label) for i in p2.interpretations] == [("LineString", "fault")]
    # The prior is rebuilt from the sensor record, as the photo was first read.
    _same_pose(p2.prior.pose, ps.prior.pose)
    # Written back as version 1, the old file kept beside it.
    assert json.loads((folder / "workspace.v0.json").read_text()) == old
    manifest = json.loads((folder / "workspace.json").read_text())
    assert manifest["version"] == 1 and manifest["current"] == "IMG_0002"
    assert (folder / "photos/IMG_0002/trials.json").exists()
    assert_same_workspace(again, Workspace.open(folder, scene=again.scene, terrain=again.terrain,
                                                autosave=False))


# ------------------------------------------------------ a crash mid-save
_CHILD = textwrap.dedent('''
    """Build a workspace, register and interpret two photos, then block inside
    one atomic write (its temporary file complete, not yet renamed)."""
    import contextlib, json, os, sys, time
    from pathlib import Path
    import cv2
    import numpy as np
    from napari_imgreg.io import workspace_files as wsfiles
    from napari_imgreg.interpret.project import Interpretation
    from napari_imgreg.sample import sample_scene
    from napari_imgreg.workspace import Workspace

    folder, block_on, stage = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
    real = wsfiles.atomic_write
    armed = []

    @contextlib.contextmanager
    def blocking_write(path, *args, **kwargs):
        with real(path, *args, **kwargs) as fh:
            yield fh
            if armed and Path(path).name == block_on:
                fh.flush()
                os.fsync(fh.fileno())
                (folder.parent / "blocked").write_text(str(path))
                time.sleep(600)  # SIGKILL arrives here

    wsfiles.atomic_write = blocking_write

    def summary(ws):
        return {ps.name: {"pose": ps.pose.to_dict(), "label": ps.history.label,
                          "trials": len(ps.trials), "drawn": len(ps.interpretations),
                          "status": None if ps.registration is None else ps.registration.status}
                for ps in ws.photos}

    cv2.setRNGSeed(0)
    if stage == "first":
        src = sample_scene("small")
        ws = Workspace()
        for name in ("sun_relight", "area_match", "edge_align", "dense_refine"):
            setattr(ws.params, name, False)
        ws.save(folder)
        ws.open_scene(src / "outcrop.obj", dem=src / "dem.tif")
        ws.add_photos([src / "IMG_0001.jpg", src / "IMG_0002.jpg"])
        for k in range(2):
            ws.select_photo(k)
            ws.register(auto=False)
            ws.add_interpretation(Interpretation(
                "LineString", [[200.0 + 40 * k, 300.0], [700.0, 330.0 + 20 * k]],
                {"label": "sandstone"}))
        ws.project_interpretations()
        action = lambda: ws.nudge("turn right 5", d_trend=5.0)  # photo.json blocks
    else:
        ws = Workspace.open(folder)
        src = sample_scene("small")
        action = lambda: ws.add_photos([src / "IMG_0003.jpg"])  # the manifest blocks
    (folder.parent / "expected.json").write_text(json.dumps(
        {"photos": summary(ws), "features": len(ws.features_3d)}))
    armed.append(True)
    action()
    (folder.parent / "not_blocked").write_text("the write did not block")
''')


def _run_until_blocked(tmp_path: Path, folder: Path, block_on: str, stage: str) -> None:
    for name in ("blocked", "not_blocked", "expected.json"):
        (tmp_path / name).unlink(missing_ok=True)
    script = tmp_path / "child.py"
    script.write_text(_CHILD)
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    child = subprocess.Popen([sys.executable, str(script), str(folder), block_on, stage],
                             env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 300
        while not (tmp_path / "blocked").exists():
            if child.poll() is not None or time.monotonic() > deadline:
                out = child.stdout.read().decode(errors="replace") if child.poll() is not None else ""
                raise AssertionError(f"the child did not block (rc {child.returncode}):\n{out}")
            time.sleep(0.2)
        os.kill(child.pid, signal.SIGKILL)  # mid-save: the temporary file is written
        child.wait(30)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait(30)
    assert child.returncode == -signal.SIGKILL


def _check_intact(folder: Path, expected: dict, scene, terrain) -> Workspace:
    manifest = json.loads((folder / "workspace.json").read_text())  # valid JSON
    assert manifest["format"] == "napari-imgreg workspace" and manifest["version"] == 1
    ws = Workspace.open(folder, scene=scene, terrain=terrain, autosave=False)
    assert ws.open_problems == []
    got = {ps.name: ps for ps in ws.photos}
    assert sorted(got) == sorted(expected["photos"])
    for name, want in expected["photos"].items():
        ps = got[name]
        assert ps.pose.to_dict() == want["pose"] and ps.history.label == want["label"]
        assert len(ps.trials) == want["trials"] and len(ps.interpretations) == want["drawn"]
        assert (None if ps.registration is None else ps.registration.status) == want["status"]
    assert len(ws.features_3d) == expected["features"]
    return ws


def test_a_process_killed_mid_save_leaves_every_completed_photo_intact(sample, tmp_path):
    _, scene, terrain, _ = sample
    folder = tmp_path / "campaign.imgreg"
    # 1. Two photos registered and interpreted, then killed inside the save of a nudge.
    _run_until_blocked(tmp_path, folder, "photo.json", "first")
    expected = json.loads((tmp_path / "expected.json").read_text())
    assert all(p["trials"] >= 1 and p["drawn"] == 1 for p in expected["photos"].values())
    assert expected["features"] == 2
    leftovers = [p for p in (folder / "photos/IMG_0002").iterdir() if p.name.startswith(".")]
    assert len(leftovers) == 1  # the complete temporary file the rename never took
    ws = _check_intact(folder, expected, scene, terrain)  # the nudge in progress is lost
    assert ws.photos[1].history.label.startswith("Run 1")

    # 2. Reopened in a new process, killed inside the manifest's save as a photo is added.
    _run_until_blocked(tmp_path, folder, "workspace.json", "second")
    expected = json.loads((tmp_path / "expected.json").read_text())
    assert (folder / "photos/IMG_0003/photo.json").exists()  # its files came first ...
    ws = _check_intact(folder, expected, scene, terrain)  # ... the manifest never named it
    assert [ps.name for ps in ws.photos] == ["IMG_0001.jpg", "IMG_0002.jpg"]
    # Adding it again now works, into a fresh folder of its own (the orphan is kept).
    ws = Workspace.open(folder, scene=scene, terrain=terrain)
    ws.add_photos([sample[0] / "IMG_0003.jpg"])
    manifest = json.loads((folder / "workspace.json").read_text())
    assert [e["key"] for e in manifest["photos"]] == ["IMG_0001", "IMG_0002", "IMG_0003_2"]


def test_an_empty_workspace_saves_and_opens(sample, tmp_path):
    folder = tmp_path / "empty.imgreg"
    ws = Workspace()
    ws.save(folder)
    ws.detach()
    again = Workspace.open(folder)
    assert again.scene is None and again.photos == [] and again.open_problems == []
    src, scene, terrain, _ = sample
    again.load_scene(scene, terrain, {"mesh": src / "outcrop.obj"})  # saved as it happens
    again.add_photos([src / "IMG_0003.jpg"])
    third = Workspace.open(folder, autosave=False)
    assert third.scene_files == {"mesh": str(src / "outcrop.obj")}
    assert [ps.name for ps in third.photos] == ["IMG_0003.jpg"]


# ------------------------------------------------------------- command line
def _cli(*argv) -> int:
    import argparse

    from napari_imgreg.cli import workspace as cli_workspace

    parser = argparse.ArgumentParser(prog="napari-imgreg")
    cli_workspace.add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args([str(a) for a in argv])
    return args.func(args)


def test_the_command_line_on_a_workspace_is_resumable(sample, tmp_path, capsys):
    src = sample[0]
    scene_dir = tmp_path / "scene"
    shutil.copytree(src, scene_dir, ignore=shutil.ignore_patterns("IMG_0003.*", "truth*"))
    params = tmp_path / "params.json"
    params.write_text(json.dumps({"sun_relight": False, "area_match": False, "edge_align": False,
                                  "dense_refine": False, "max_trials": 1}))
    folder = tmp_path / "campaign.imgreg"
    assert _cli("workspace", "create", folder, scene_dir, "--params", params) == 0
    assert "outcrop.obj and 2 photo(s)" in capsys.readouterr().out
    with pytest.raises(InputError, match="already holds a workspace"):
        _cli("workspace", "create", folder, scene_dir)

    cv2.setRNGSeed(0)
    code = _cli("workspace", "register", folder, "--photo", "IMG_0001.jpg", "--once")
    out = capsys.readouterr().out
    assert "1 photo(s) to register\n" in out and "[1/1] IMG_0001.jpg: " in out
    assert code == (0 if "IMG_0001.jpg: registered" in out else 1)
    # Resumed: the photo done is skipped.
    _cli("workspace", "register", folder, "--photo", "IMG_0001.jpg", "--once")
    assert "0 photo(s) to register (1 already done)" in capsys.readouterr().out
    with pytest.raises(InputError, match="no photo named 'IMG_9.jpg'"):
        _cli("workspace", "register", folder, "--photo", "IMG_9.jpg")

    lines = tmp_path / "lines.geojson"
    lines.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"label": "sandstone"},
         "geometry": {"type": "LineString", "coordinates": [[200, 300], [700, 330]]}}]}))
    assert _cli("workspace", "lines", folder, "IMG_0001.jpg", lines) == 0
    with pytest.raises(InputError, match="nothing projected yet"):
        _cli("workspace", "export", folder, "--out", tmp_path / "x.geojson")
    assert _cli("workspace", "project", folder) == 0
    assert "1 feature(s) projected" in capsys.readouterr().out
    out3d, meas = tmp_path / "out" / "LINES3D.geojson", tmp_path / "out" / "M.csv"
    assert _cli("workspace", "export", folder, "--out", out3d, "--measurements", meas) == 0
    assert json.loads(out3d.read_text())["features"][0]["properties"]["label"] == "sandstone"
    assert meas.read_text().startswith("id,label,kind")
    # --georeferenced: the measurements' centroids in the CRS, as the features.
    geo3d, geomeas = tmp_path / "geo" / "LINES3D.geojson", tmp_path / "geo" / "M.csv"
    assert _cli("workspace", "export", folder, "--out", geo3d, "--measurements", geomeas,
                "--georeferenced") == 0
    origin = Georef.load(scene_dir / "georef.json").origin
    local_row = next(csv.DictReader(meas.open()))
    geo_row = next(csv.DictReader(geomeas.open()))
    for k, axis in enumerate("xyz"):
        assert float(geo_row[axis]) == pytest.approx(float(local_row[axis]) + origin[k], abs=2e-4)
    assert geo_row["dip_deg"] == local_row["dip_deg"]
    assert "(local + origin)" in capsys.readouterr().out
    # One GeoPackage for the campaign: traces, facets, measurements, cameras.
    import pyogrio

    gpkg = tmp_path / "campaign.gpkg"
    assert _cli("workspace", "export", folder, "--out", gpkg) == 0
    layers = {name for name, _ in pyogrio.list_layers(gpkg)}
    assert {"traces", "measurements", "cameras"} <= layers, layers
    assert _cli("workspace", "add", folder, src / "IMG_0003.jpg") == 0
    assert _cli("workspace", "info", folder) == 0
    info = capsys.readouterr().out
    assert "3 photo(s)" in info and "IMG_0001.jpg: " in info and "IMG_0003.jpg: not registered" in info
    # Each sub-command gives the folder back when it ends (not when its
    # workspace is collected): a script can run the next one at once.
    assert not (folder / "workspace.lock").exists()


def test_create_names_the_subfolders_of_photos_it_leaves_out(sample, tmp_path, capsys):
    """A campaign kept by day: the photos of day2/ were left out in silence."""
    scene_dir = tmp_path / "scene"
    shutil.copytree(sample[0], scene_dir, ignore=shutil.ignore_patterns("IMG_0002.*", "IMG_0003.*"))
    (scene_dir / "day2").mkdir()
    for name in ("IMG_0002.jpg", "IMG_0002.json", "IMG_0003.jpg", "IMG_0003.json"):
        shutil.copy2(sample[0] / name, scene_dir / "day2" / name)
    assert _cli("workspace", "create", tmp_path / "campaign", scene_dir) == 0
    out = capsys.readouterr().out
    assert ("  not added: day2/ (a subfolder with 2 photo(s): only the folder itself is read; "
            "'workspace add' adds them)") in out
    assert "workspace with outcrop.obj and 1 photo(s)" in out


def test_a_failed_sub_command_gives_the_folder_back(sample, tmp_path):
    folder = tmp_path / "campaign.imgreg"
    assert _cli("workspace", "create", folder, sample[0], "--no-photos") == 0
    assert not (folder / "workspace.lock").exists()
    assert _cli("workspace", "add", folder, tmp_path / "missing.jpg") == 2
    assert not (folder / "workspace.lock").exists()
    with pytest.raises(InputError, match="no photo named"):
        _cli("workspace", "register", folder, "--photo", "IMG_9.jpg")
    assert not (folder / "workspace.lock").exists()
    Workspace.open(folder).detach()  # and it opens again in this process


#: `workspace register` whose first photo stalls (marking that it started)
#: until the process is signalled.
_STALLED_REGISTER = """
    import sys, time
    from pathlib import Path
    from napari_imgreg.cli import main
    from napari_imgreg.workspace import Workspace

    def register(self, *args, **kwargs):
        Path(sys.argv[1]).write_text("started")
        while True:
            time.sleep(0.05)

    Workspace.register = register
    sys.exit(main(sys.argv[2:]))
"""


@pytest.mark.parametrize("signum, code, words", [
    (signal.SIGTERM, 143, "terminated (SIGTERM)"),  # a job scheduler's time limit, `kill`
    (signal.SIGINT, 130, "interrupted"),
])
def test_a_signalled_workspace_register_gives_the_folder_back(sample, tmp_path, signum, code,
                                                              words):
    """SIGTERM killed `workspace register` where it stood: exit -15, no word,
    workspace.lock left behind; it now unwinds as Ctrl-C does."""
    folder = tmp_path / "campaign.imgreg"
    assert _cli("workspace", "create", folder, sample[0]) == 0
    marker = tmp_path / "started"
    child = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(_STALLED_REGISTER), str(marker), "workspace",
         "register", str(folder), "--workers", "0"],
        env={**os.environ, "PYTHONPATH": str(ROOT / "src")}, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not marker.exists():
            assert child.poll() is None and time.monotonic() < deadline, child.communicate()
            time.sleep(0.05)
        assert (folder / "workspace.lock").exists()
        child.send_signal(signum)
        stdout, stderr = child.communicate(timeout=60)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait(30)
    assert child.returncode == code, stderr
    assert stderr.strip() == words
    assert "interrupted; every photo registered so far is saved" in stdout
    assert not (folder / "workspace.lock").exists()
    Workspace.open(folder).detach()  # free for the next session


def test_one_session_saves_into_a_folder_at_a_time(ws, tmp_path):
    folder = tmp_path / "w.imgreg"
    ws.save(folder)
    lock = json.loads((folder / "workspace.lock").read_text())
    assert lock["pid"] == os.getpid()
    with pytest.raises(InputError, match="already open in this session"):
        Workspace.open(folder, scene=ws.scene, terrain=ws.terrain)
    assert len(Workspace.open(folder, scene=ws.scene, terrain=ws.terrain,
                              autosave=False).photos) == 3  # reading is always allowed
    ws.detach()
    assert not (folder / "workspace.lock").exists()

    # Another live process holds it: refused, saying which; once it is gone, taken over.
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (folder / "workspace.lock").write_text(json.dumps(
            {"pid": other.pid, "host": lock["host"], "since": "2026-12-01T08:00:00Z"}))
        with pytest.raises(InputError) as info:
            Workspace.open(folder, scene=ws.scene, terrain=ws.terrain)
        assert f"is open in another napari-imgreg (pid {other.pid}" in str(info.value)
        assert "\n" not in str(info.value)
    finally:
        other.kill()
        other.wait(30)
    again = Workspace.open(folder, scene=ws.scene, terrain=ws.terrain)  # the holder died
    assert again.folder == folder
    again.detach()
    # On another machine it cannot be checked: the line says what to do.
    (folder / "workspace.lock").write_text(json.dumps({"pid": 1, "host": "field-laptop"}))
    with pytest.raises(InputError, match="open in napari-imgreg on field-laptop .*delete "
                                         "workspace.lock if that session is gone"):
        Workspace.open(folder, scene=ws.scene, terrain=ws.terrain)


def test_a_lock_being_written_by_another_session_is_not_taken_for_a_stale_one(tmp_path):
    """Two sessions starting at once: the second found the first's lock file
    created but not yet written, took the empty file for a stale lock and
    took it over; both then saved into the folder."""
    import socket
    import threading

    folder = tmp_path / "w.imgreg"
    folder.mkdir()
    lock = folder / wsfiles.LOCK
    lock.write_text("")  # the other session's, created an instant ago
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    held = json.dumps({"pid": other.pid, "host": socket.gethostname(),
                       "since": "2026-12-05T08:00:00Z", "token": "theirs"})
    writer = threading.Timer(0.3, lock.write_text, args=(held,))
    writer.start()
    try:
        with pytest.raises(InputError,
                           match=f"is open in another napari-imgreg \\(pid {other.pid}"):
            wsfiles.acquire_lock(folder)
    finally:
        writer.join()
        other.kill()
        other.wait(30)
    assert json.loads(lock.read_text())["token"] == "theirs"
    # A lock that stays unreadable is a torn write of a session long gone: taken over.
    lock.write_text("{")
    os.utime(lock, (time.time() - 60, time.time() - 60))
    token = wsfiles.acquire_lock(folder)
    assert json.loads(lock.read_text())["token"] == token
    assert [p.name for p in folder.iterdir()] == [wsfiles.LOCK]  # no temporary file left


def test_two_photos_with_one_file_name_are_told_apart_not_confused(sample, tmp_path, capsys):
    # Two cameras both name a photo IMG_0001.jpg: a command naming
    # "IMG_0001.jpg" must not pick one of them silently (it used to draw on
    # the first, replacing its drawings); the photo's folder name or its path does.
    src = sample[0]
    other = tmp_path / "camera2"
    other.mkdir()
    for suffix in (".jpg", ".json"):
        shutil.copy(src / f"IMG_0002{suffix}", other / f"IMG_0001{suffix}")
    folder = tmp_path / "campaign.imgreg"
    assert _cli("workspace", "create", folder, src, "--no-photos") == 0
    assert _cli("workspace", "add", folder, src / "IMG_0001.jpg", other / "IMG_0001.jpg") == 0
    assert _cli("workspace", "add", folder, other / "IMG_0001.jpg") == 0  # once is enough
    assert (f"already in the workspace: {other / 'IMG_0001.jpg'}\n"
            f"{folder}: 0 photo(s) added, 2 in all") in capsys.readouterr().out
    lines = tmp_path / "lines.geojson"
    lines.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"label": "sandstone"},
         "geometry": {"type": "LineString", "coordinates": [[200, 300], [700, 330]]}}]}))
    capsys.readouterr()
    with pytest.raises(InputError, match=r"2 photos are named 'IMG_0001.jpg': IMG_0001 \(.*"
                                         r"IMG_0001_2 \(.*camera2"):
        _cli("workspace", "lines", folder, "IMG_0001.jpg", lines)
    with pytest.raises(InputError, match="2 photos are named"):
        _cli("workspace", "register", folder, "--photo", "IMG_0001.jpg")
    assert _cli("workspace", "lines", folder, "IMG_0001_2", lines) == 0
    assert "IMG_0001.jpg (IMG_0001_2): 1 feature(s) drawn" in capsys.readouterr().out
    assert _cli("workspace", "lines", folder, other / "IMG_0001.jpg", lines) == 0  # by its path
    opened = Workspace.open(folder, autosave=False)
    assert [(opened.photo_key(ps), len(ps.interpretations)) for ps in opened.photos] == [
        ("IMG_0001", 0), ("IMG_0001_2", 1)]
    assert opened.photos[1].photo.path.parent == other
    capsys.readouterr()
    assert _cli("workspace", "info", folder) == 0
    info = capsys.readouterr().out
    assert "IMG_0001.jpg (IMG_0001): not registered" in info
    assert "IMG_0001.jpg (IMG_0001_2): not registered; 0 trial(s), 1 drawn" in info



_TAKEOVER_RACER = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from napari_imgreg.errors import InputError
    from napari_imgreg.io import workspace_files as wsfiles

    folder, start_at, slow = Path(sys.argv[1]), float(sys.argv[2]), sys.argv[3] == "slow"
    if slow:  # this session is slow to decide the lock it read is stale
        alive = wsfiles._process_alive
        def slow_alive(pid):
            time.sleep(1.0)
            return alive(pid)
        wsfiles._process_alive = slow_alive
    while time.time() < start_at:
        time.sleep(0.001)
    try:
        token = wsfiles.acquire_lock(folder)
    except InputError as exc:
        print("refused", exc)
        sys.exit(0)
    print("holds")
    sys.stdout.flush()
    time.sleep(2.0)  # while the other decides
    wsfiles.release_lock(folder, token)
""")


def test_two_sessions_taking_over_one_stale_lock_do_not_both_hold_it(tmp_path):
    """A session found a dead session's lock and, while it decided the lock
    was stale, another took it over; the first then deleted the other's new
    lock and made its own, and both saved into the folder. The takeover now
    deletes the stale lock only while it is still the one read, one session
    at a time."""
    import socket

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait(30)
    script = tmp_path / "racer.py"
    script.write_text(_TAKEOVER_RACER)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    folder = tmp_path / "w.imgreg"
    folder.mkdir()
    (folder / wsfiles.LOCK).write_text(json.dumps(
        {"pid": dead.pid, "host": socket.gethostname(), "since": "2026-12-01T08:00:00Z",
         "token": "stale"}))
    start_at = time.time() + 3.0  # after both have imported
    slow, quick = (subprocess.Popen([sys.executable, str(script), str(folder), str(at), mode],
                                    stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                    env=env)
                   for at, mode in ((start_at, "slow"), (start_at + 0.3, "quick")))
    slow_out, quick_out = slow.communicate(timeout=60)[0], quick.communicate(timeout=60)[0]
    assert quick_out.startswith("holds"), quick_out
    assert slow_out.startswith("refused") and f"is open in another napari-imgreg (pid {quick.pid}" \
        in slow_out, slow_out
    assert [p.name for p in folder.iterdir()] == []  # given back, nothing left beside it


def test_a_lock_holder_is_alive_while_it_runs_and_dead_once_it_ended():
    running = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        assert wsfiles._process_alive(running.pid)
        assert wsfiles._process_alive(os.getpid())
    finally:
        running.kill()
    # Killed but not yet reaped (a zombie): it holds nothing any more.
    time.sleep(0.5)
    assert not wsfiles._process_alive(running.pid)
    running.wait(30)
    assert not wsfiles._process_alive(running.pid)
