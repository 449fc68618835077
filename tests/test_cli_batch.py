"""``napari-imgreg batch``: a scene folder in, one RESULT.json per photo and a summary out."""

from __future__ import annotations

import contextlib
import csv
import io
import json
import shutil

import numpy as np
import pytest
from PIL import Image

from napari_imgreg import Pose
from napari_imgreg.cli import main
from napari_imgreg.cli.batch import SUMMARY_COLUMNS
from napari_imgreg.sample import load_truth, sample_scene

#: The sample scene's model files (the texture is named by outcrop.mtl).
SCENE_FILES = ("outcrop.obj", "outcrop.mtl", "outcrop_texture.jpg", "dem.tif", "georef.json")
RESULT_KEYS = {"status", "photo", "camera", "pose", "metrics", "quality", "trials", "timings_s"}


def _make_scene(folder, photos):
    """Copy the small sample's model and some photos (+ records, truth) into ``folder``."""
    src = sample_scene("small")
    folder.mkdir(parents=True, exist_ok=True)
    for name in SCENE_FILES:
        shutil.copy2(src / name, folder / name)
    for stem in photos:
        for suffix in (".jpg", ".json", ".truth.json"):
            shutil.copy2(src / f"{stem}{suffix}", folder / f"{stem}{suffix}")
    return folder


def _run(argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in argv])
    return code, out.getvalue(), err.getvalue()


def _summary(out):
    with open(out / "summary.csv", newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    header, body = rows[0], rows[1:]
    assert tuple(header) == SUMMARY_COLUMNS
    return [dict(zip(header, r)) for r in body], json.loads((out / "summary.json").read_text())


def _fake_registration(prior, name, status="failed"):
    """A quick stand-in for pipeline.register (no matching)."""
    from napari_imgreg.registration.pipeline import Registration

    return Registration(
        status=status, photo=name, intrinsics=prior.intrinsics, pose=prior.pose, prior=prior,
        metrics={}, q=-1.0, grade="failed", hints=["fake"], trials=[], timings_s={"total": 0.0},
    )


def _assert_at_truth(result_file, photo):
    result = json.loads(result_file.read_text())
    assert RESULT_KEYS <= set(result)
    assert result["status"] == "registered" and result["photo"] == photo.name
    truth = load_truth(photo).pose
    pose = Pose.from_dict(result["pose"])
    assert pose.rotation_error_deg(truth) < 0.2
    assert np.linalg.norm(pose.center - truth.center) < 1.0
    return result


@pytest.fixture(scope="module")
def batch_run(tmp_path_factory):
    """One real batch over two sample photos (shared: registration takes seconds)."""
    root = tmp_path_factory.mktemp("batch")
    scene = _make_scene(root / "scene", ["IMG_0001", "IMG_0003"])
    out = root / "results"
    code, stdout, stderr = _run(["batch", scene, "--out", out])
    return scene, out, code, stdout, stderr


def test_batch_registers_every_photo(batch_run):
    scene, out, code, stdout, stderr = batch_run
    assert code == 0, stdout + stderr
    assert stderr == ""
    # One RESULT.json per photo — the texture and the truth files are not photos.
    assert sorted(p.name for p in out.glob("*.result.json")) == [
        "IMG_0001.result.json", "IMG_0003.result.json"]
    for name in ("IMG_0001", "IMG_0003"):
        _assert_at_truth(out / f"{name}.result.json", scene / f"{name}.jpg")
    rows, summary = _summary(out)
    assert [r["photo"] for r in rows] == ["IMG_0001.jpg", "IMG_0003.jpg"]
    for row in rows:
        assert row["status"] == "registered" and row["error"] == ""
        result = json.loads((out / row["photo"].replace(".jpg", ".result.json")).read_text())
        assert float(row["Q"]) == pytest.approx(result["quality"]["Q"], abs=1e-3)
        assert row["grade"] == result["quality"]["grade"]
        assert int(row["n_trials"]) == len(result["trials"])
        xyz = [float(row[k]) for k in ("x", "y", "z")]
        assert np.allclose(xyz, result["pose"]["position"], atol=1e-3)
        assert float(row["trend_deg"]) == pytest.approx(result["pose"]["trend_deg"], abs=1e-3)
        assert float(row["seconds"]) > 0
    assert summary["complete"] and not summary["interrupted"]
    assert summary["n_photos"] == 2 and summary["counts"]["registered"] == 2
    assert "IMG_0003.jpg: REGISTERED" in stdout and "2 registered, 0 failed" in stdout
    assert "outcrop_texture.jpg" in stdout  # said to be a texture, not a photo
    assert not list(out.glob(".*"))  # no temporary files left


def test_skip_existing_keeps_done_photos(batch_run, tmp_path, monkeypatch):
    _, done, *_ = batch_run
    scene = batch_run[0]
    out = tmp_path / "results"
    shutil.copytree(done, out)
    kept = (out / "IMG_0001.result.json").read_bytes()
    (out / "IMG_0003.result.json").unlink()
    calls = []

    def fake_register(scene_, image, prior, params=None, photo_name="", on_progress=None):
        calls.append(photo_name)
        return _fake_registration(prior, photo_name)

    monkeypatch.setattr("napari_imgreg.registration.pipeline.register", fake_register)
    # In this process (--workers 0): the stand-in is not in worker processes.
    code, stdout, stderr = _run(["batch", scene, "--out", out, "--skip-existing", "--workers", 0])
    # Only the photo without a result is redone; the fake marks it failed: exit 1.
    assert calls == ["IMG_0003.jpg"]
    assert code == 1 and stderr == ""
    assert (out / "IMG_0001.result.json").read_bytes() == kept
    assert json.loads((out / "IMG_0003.result.json").read_text())["status"] == "failed"
    rows, summary = _summary(out)
    assert [(r["photo"], r["status"]) for r in rows] == [
        ("IMG_0001.jpg", "registered"), ("IMG_0003.jpg", "failed")]
    assert summary["counts"]["skipped"] == 1
    assert "IMG_0001.jpg: skipped" in stdout

    # Everything done: nothing is registered again.
    calls.clear()
    code, stdout, _ = _run(["batch", scene, "--out", out, "--skip-existing", "--workers", 0])
    assert calls == [] and code == 1 and stdout.count("skipped") == 2


def test_bad_photos_do_not_stop_the_batch(tmp_path):
    scene = _make_scene(tmp_path / "scene", ["IMG_0002"])
    (scene / "IMG_0000.jpg").write_bytes(b"\xff\xd8 this is not a JPEG \x00\x13\x37" * 20)
    # A photo without a sensor record and without EXIF (upper-case extension).
    Image.open(scene / "IMG_0002.jpg").save(scene / "IMG_0004.PNG")
    # A photo whose record has a wrong field.
    shutil.copy2(scene / "IMG_0002.jpg", scene / "IMG_0005.jpg")
    record = json.loads((scene / "IMG_0002.json").read_text())
    record["orientation"]["trend_deg"] = "north"
    (scene / "IMG_0005.json").write_text(json.dumps(record))
    out = tmp_path / "results"

    # In this process, so that the error lines come in the photos' order (a
    # cluster isolates bad photos the same way: tests/test_distributed.py).
    code, stdout, stderr = _run(["batch", scene, "--out", out, "--workers", 0])
    assert code == 2
    lines = stderr.strip().splitlines()
    assert len(lines) == 3
    assert sum("IMG_0000.jpg" in line for line in lines) == 1
    assert "IMG_0000.jpg" in lines[0] and "cannot read image" in lines[0]
    assert "IMG_0004.PNG" in lines[1] and "no sensor record" in lines[1]
    assert "IMG_0005.json" in lines[2] and "orientation.trend_deg" in lines[2]
    # The good photo after the corrupt one is registered.
    _assert_at_truth(out / "IMG_0002.result.json", scene / "IMG_0002.jpg")
    assert sorted(p.name for p in out.glob("*.result.json")) == ["IMG_0002.result.json"]
    rows, summary = _summary(out)
    by_photo = {r["photo"]: r for r in rows}
    assert list(by_photo) == ["IMG_0000.jpg", "IMG_0002.jpg", "IMG_0004.PNG", "IMG_0005.jpg"]
    assert by_photo["IMG_0002.jpg"]["status"] == "registered"
    for name, line in zip(("IMG_0000.jpg", "IMG_0004.PNG", "IMG_0005.jpg"), lines):
        assert by_photo[name]["status"] == "bad_input"
        assert by_photo[name]["error"] and by_photo[name]["error"] in line
    assert summary["complete"] and summary["counts"]["bad_input"] == 3
    assert "1 registered, 0 failed, 3 bad input" in stdout


def _tiny_obj(path):
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 0 1\nf 1 2 3\n")


@pytest.mark.parametrize(
    "case, needle",
    [
        ("missing", "scene: no such folder"),
        ("no_mesh", "no model in the folder"),
        ("two_meshes", "several models (a.obj, b.ply): choose one with --mesh"),
        ("corrupt_mesh", "broken.obj"),
        ("no_photos", "no photos in the folder"),
        # A campaign kept by day: the photos were not found, and nothing said why.
        ("photos_in_subfolders", "no photos in the folder (expected JPEG, PNG, TIFF or HEIC "
                                 "files); there are photos in its subfolders (day1/, day2/), "
                                 "not read: only the folder itself is"),
        ("bad_params", "params.json: invalid JSON"),
    ],
)
def test_bad_scene_is_exit_2_and_writes_nothing(tmp_path, case, needle):
    scene = tmp_path / "scene"
    extra = []
    if case != "missing":
        scene.mkdir()
        if case == "photos_in_subfolders":
            for day in ("day1", "day2"):
                (scene / day).mkdir()
                Image.new("RGB", (32, 24)).save(scene / day / "IMG_0001.jpg")
            (scene / ".thumbs").mkdir()  # hidden: not named
            Image.new("RGB", (32, 24)).save(scene / ".thumbs" / "IMG_0001.jpg")
        elif case != "no_photos":
            Image.new("RGB", (32, 24)).save(scene / "IMG_0001.jpg")
        if case == "two_meshes":
            _tiny_obj(scene / "a.obj")
            (scene / "b.ply").write_text("ply\n")
        elif case == "corrupt_mesh":
            (scene / "broken.obj").write_bytes(b"v 1 2\nf 1 2 9\n\x00\xff garbage")
        elif case in ("no_photos", "photos_in_subfolders", "bad_params"):
            _tiny_obj(scene / "a.obj")
        if case == "bad_params":
            (tmp_path / "params.json").write_text("{ oops")
            extra = ["--params", tmp_path / "params.json"]
    out = tmp_path / "results"
    code, stdout, stderr = _run(["batch", scene, "--out", out, *extra])
    assert code == 2
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], stderr
    assert not out.exists()


def test_result_names_are_unique_ignoring_case():
    """IMG_0001.JPG and IMG_0001.jpg (two cameras) got IMG_0001.JPG.result.json
    and IMG_0001.jpg.result.json: one file on a case-insensitive results disk."""
    from pathlib import Path

    from napari_imgreg.cli.batch import _result_names

    photos = [Path("s/IMG_0001.JPG"), Path("s/IMG_0001.jpg"), Path("s/IMG_0001.png"),
              Path("s/IMG_0002.jpg")]
    names = list(_result_names(photos).values())
    assert names == ["IMG_0001.JPG.result.json", "IMG_0001.jpg.2.result.json",
                     "IMG_0001.png.result.json", "IMG_0002.result.json"]
    assert len({n.lower() for n in names}) == len(names)


def test_photos_sharing_a_sensor_record_are_warned_of(tmp_path, monkeypatch):
    """IMG_0001.jpg and IMG_0001.png (two cameras) both took IMG_0001.json
    without a word: one of them with another camera's focal length."""
    scene = _make_scene(tmp_path / "scene", ["IMG_0001"])
    Image.open(scene / "IMG_0001.jpg").save(scene / "IMG_0001.png")

    def registered(scene_, image, prior, params=None, photo_name="", on_progress=None):
        return _fake_registration(prior, photo_name, status="registered")

    monkeypatch.setattr("napari_imgreg.registration.pipeline.register", registered)
    code, stdout, _ = _run(["batch", scene, "--out", tmp_path / "results", "--workers", 0])
    assert code == 0
    assert ("  warning: 2 photos share the sensor record IMG_0001.json (IMG_0001.jpg, "
            "IMG_0001.png): each is registered from it") in stdout


def test_photos_in_subfolders_are_said_to_be_left_out(tmp_path):
    """Photos in a subfolder beside those of the folder were left out in silence."""
    from napari_imgreg.cli.batch import find_scene_files

    scene = tmp_path / "scene"
    (scene / "day2" / "cam_b").mkdir(parents=True)
    _tiny_obj(scene / "a.obj")
    Image.new("RGB", (32, 24)).save(scene / "IMG_0001.jpg")
    for name in ("IMG_0001.jpg", "IMG_0002.JPG"):
        Image.new("RGB", (32, 24)).save(scene / "day2" / "cam_b" / name)
    files = find_scene_files(scene)
    assert [p.name for p in files.photos] == ["IMG_0001.jpg"]
    assert files.ignored["day2/"] == "a subfolder with 2 photo(s): only the folder itself is read"


def test_interrupted_batch_keeps_finished_results(tmp_path, monkeypatch):
    scene = _make_scene(tmp_path / "scene", ["IMG_0001", "IMG_0002"])
    out = tmp_path / "results"

    def fake_register(scene_, image, prior, params=None, photo_name="", on_progress=None):
        if photo_name == "IMG_0002.jpg":
            raise KeyboardInterrupt
        return _fake_registration(prior, photo_name, status="registered")

    monkeypatch.setattr("napari_imgreg.registration.pipeline.register", fake_register)
    code, stdout, stderr = _run(["batch", scene, "--out", out, "--workers", 0])
    assert code == 130 and "interrupted" in stderr
    assert [p.name for p in out.glob("*.result.json")] == ["IMG_0001.result.json"]
    rows, summary = _summary(out)
    assert [r["photo"] for r in rows] == ["IMG_0001.jpg"]
    assert summary["interrupted"] and not summary["complete"] and summary["n_photos"] == 2
    assert not list(out.glob(".*"))
    assert "--skip-existing" in stdout


def test_interrupted_rerun_lists_every_result_in_the_folder(tmp_path, monkeypatch):
    """Run again into a complete results folder and interrupted: the summary
    lists the result a worker wrote before this process heard of it, and the
    earlier run's result not yet replaced; the run said at its start that the
    earlier results would be replaced."""
    from napari_imgreg.cli._common import write_json

    scene = _make_scene(tmp_path / "scene", ["IMG_0001", "IMG_0002", "IMG_0003"])
    out = tmp_path / "results"

    def registered(scene_, image, prior, params=None, photo_name="", on_progress=None):
        return _fake_registration(prior, photo_name, status="registered")

    monkeypatch.setattr("napari_imgreg.registration.pipeline.register", registered)
    code, stdout, _ = _run(["batch", scene, "--out", out, "--workers", 0])
    assert code == 0 and "earlier run" not in stdout
    assert "registering 3 photo(s) in this process" in stdout  # --workers 0
    earlier_third = (out / "IMG_0003.result.json").read_bytes()

    def interrupted_at_the_second(scene_, image, prior, params=None, photo_name="",
                                  on_progress=None):
        reg = _fake_registration(prior, photo_name, status="registered")
        if photo_name == "IMG_0002.jpg":
            # As a worker does: its result written, the interrupt before it is collected.
            write_json(out / "IMG_0002.result.json", reg.to_dict())
            raise KeyboardInterrupt
        return reg

    monkeypatch.setattr("napari_imgreg.registration.pipeline.register",
                        interrupted_at_the_second)
    code, stdout, stderr = _run(["batch", scene, "--out", out, "--workers", 0])
    assert code == 130
    (start,) = [line for line in stdout.splitlines() if "of an earlier run" in line]
    assert "holds 3 result(s) of an earlier run: they will be replaced" in start
    assert "--skip-existing" in start
    rows, summary = _summary(out)
    assert [r["photo"] for r in rows] == ["IMG_0001.jpg", "IMG_0002.jpg", "IMG_0003.jpg"]
    assert [r["skipped"] for r in summary["photos"]] == [False, False, True]
    assert summary["n_done"] == 3 and summary["interrupted"] and not summary["complete"]
    assert (out / "IMG_0003.result.json").read_bytes() == earlier_third
    assert "interrupted after 3 of 3 photos (1 of them an earlier run's result" in stdout


def _registering(calls: list):
    """A fake ``pipeline.register`` that registers every photo and notes its name."""
    def registered(scene_, image, prior, params=None, photo_name="", on_progress=None):
        calls.append(photo_name)
        return _fake_registration(prior, photo_name, status="registered")

    return registered

def test_skip_existing_never_keeps_a_result_of_another_model(tmp_path, monkeypatch):
    """The model re-exported, the batch run again into the same folder and
    interrupted, then resumed: --skip-existing kept the earlier model's poses
    as if they were of the new one. Now each is registered again, and the
    interrupted run's summary names them (``stale_results``) instead of
    listing them as its own."""
    scene = _make_scene(tmp_path / "scene", ["IMG_0001", "IMG_0002", "IMG_0003"])
    out = tmp_path / "results"
    calls = []
    registered = _registering(calls)
    monkeypatch.setattr("napari_imgreg.registration.pipeline.register", registered)
    assert _run(["batch", scene, "--out", out, "--workers", 0])[0] == 0
    with open(scene / "outcrop.obj", "a", encoding="utf-8") as fh:
        fh.write("# re-exported\n")  # another model under the same name

    def interrupted_at_the_second(scene_, image, prior, params=None, photo_name="",
                                  on_progress=None):
        if photo_name == "IMG_0002.jpg":
            raise KeyboardInterrupt
        return registered(scene_, image, prior, params, photo_name)

    monkeypatch.setattr("napari_imgreg.registration.pipeline.register",
                        interrupted_at_the_second)
    code, stdout, _ = _run(["batch", scene, "--out", out, "--workers", 0])
    assert code == 130
    assert "holds 3 result(s) registered on another model (outcrop.obj: " in stdout
    rows, summary = _summary(out)
    assert [r["photo"] for r in rows] == ["IMG_0001.jpg"]  # the only one of this model
    assert summary["stale_results"] == ["IMG_0002.result.json", "IMG_0003.result.json"]

    monkeypatch.setattr("napari_imgreg.registration.pipeline.register", registered)
    calls.clear()
    code, stdout, _ = _run(["batch", scene, "--out", out, "--workers", 0, "--skip-existing"])
    assert code == 0
    assert calls == ["IMG_0002.jpg", "IMG_0003.jpg"]
    assert "IMG_0003.jpg: existing result registered on another model: redoing it" in stdout
    rows, summary = _summary(out)
    assert summary["complete"] and summary["stale_results"] == []
    assert summary["counts"] == {"registered": 3, "failed": 0, "bad_input": 0, "error": 0,
                                 "skipped": 1}
    # Resumed with the same model, nothing is redone.
    calls.clear()
    assert _run(["batch", scene, "--out", out, "--workers", 0, "--skip-existing"])[0] == 0
    assert calls == []


def test_skip_existing_redoes_a_photo_replaced_under_its_name(tmp_path, monkeypatch):
    """A photo re-exported (cropped, retouched) under its name kept the result
    of its earlier version with --skip-existing."""
    scene = _make_scene(tmp_path / "scene", ["IMG_0001", "IMG_0002"])
    out = tmp_path / "results"
    calls = []
    registered = _registering(calls)
    monkeypatch.setattr("napari_imgreg.registration.pipeline.register", registered)
    assert _run(["batch", scene, "--out", out, "--workers", 0])[0] == 0
    Image.open(scene / "IMG_0002.jpg").save(scene / "IMG_0002.jpg", quality=70)  # re-exported
    calls.clear()
    code, stdout, _ = _run(["batch", scene, "--out", out, "--workers", 0, "--skip-existing"])
    assert code == 0 and calls == ["IMG_0002.jpg"]
    assert "IMG_0002.jpg: the photo has changed since its existing result (" in stdout
    _, summary = _summary(out)
    assert [r["skipped"] for r in summary["photos"]] == [True, False]
    assert all(r["photo_fingerprint"]["size"] == (scene / r["photo"]).stat().st_size
               for r in summary["photos"])
    calls.clear()  # as it is now, nothing to redo
    assert _run(["batch", scene, "--out", out, "--workers", 0, "--skip-existing"])[0] == 0
    assert calls == []


def test_one_batch_writes_into_a_results_folder_at_a_time(tmp_path, monkeypatch):
    """Two batches into one folder each rewrote the summary with only their
    own rows and replaced each other's results: the second is now refused
    in one line, before its scene loads, and the folder is left as it was."""
    import os
    import socket
    import subprocess
    import sys

    scene = _make_scene(tmp_path / "scene", ["IMG_0001"])
    out = tmp_path / "results"

    def registered(scene_, image, prior, params=None, photo_name="", on_progress=None):
        return _fake_registration(prior, photo_name, status="registered")

    monkeypatch.setattr("napari_imgreg.registration.pipeline.register", registered)
    assert _run(["batch", scene, "--out", out, "--workers", 0])[0] == 0
    assert not (out / "batch.lock").exists()  # given back at the end
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (out / "batch.lock").write_text(json.dumps(
            {"pid": other.pid, "host": socket.gethostname(), "since": "2026-12-05T08:00:00Z",
             "token": "theirs"}))
        code, stdout, stderr = _run(["batch", scene, "--out", out, "--workers", 0])
    finally:
        other.kill()
        other.wait(30)
    assert code == 2 and stdout == ""
    assert stderr.strip() == (f"napari-imgreg batch: error: {out}: another napari-imgreg batch "
                              f"(pid {other.pid}, since 2026-12-05T08:00:00Z) writes its results "
                              "here: let it end or stop it, or delete batch.lock if no batch runs")
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.name != "batch.lock"} == before
    # Its process gone (killed, a power cut): the lock is taken over.
    code, stdout, stderr = _run(["batch", scene, "--out", out, "--workers", 0, "--skip-existing"])
    assert code == 0, stderr
    assert sorted(os.listdir(out)) == sorted(before)


def test_batch_help(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["batch", "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    assert "SCENE_DIR" in text and "--skip-existing" in text
