"""Output files the user audit broke: a symlinked output, a shapefile set
with a folder in its way, a batch whose summary cannot be written, a refused
rename, and a truncated DEM's tifffile log lines. Each must end in the file
written whole, or one error line naming the file and exit code 2."""

from __future__ import annotations

import json
import logging
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from napari_imgreg import _atomic
from napari_imgreg._atomic import OutputError, atomic_path
from napari_imgreg.cli._common import write_json, write_npy
from napari_imgreg.errors import InputError

SRC = Path(__file__).resolve().parents[1] / "src"


@pytest.fixture
def wall(wall_and_record):
    """The shared wall and a sensor record facing it (conftest ``wall_and_record``)."""
    return wall_and_record


def _hidden(folder: Path) -> list[str]:
    """Left-over temporary files (hidden names) in ``folder``."""
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


# ------------------------------------------------------- 1. symlinked outputs
def test_temporary_file_takes_the_suffix_of_the_name_given(tmp_path):
    (tmp_path / "tnpy").write_text("x")
    link = tmp_path / "d.npy"
    link.symlink_to("tnpy")
    with atomic_path(link) as tmp:
        # Beside the link's target, with the extension the caller chose.
        assert tmp.parent == tmp_path and tmp.name.startswith(".tnpy.")
        assert tmp.suffix == ".npy"
        tmp.write_bytes(b"new")
    assert link.is_symlink() and (tmp_path / "tnpy").read_bytes() == b"new"


def test_npy_through_a_link_to_a_target_without_suffix(tmp_path):
    target = tmp_path / "tnpy"
    target.write_text("x\n")
    link = tmp_path / "d.npy"
    link.symlink_to(target.name)
    write_npy(link, np.arange(6.0).reshape(2, 3))
    assert link.is_symlink() and os.readlink(link) == "tnpy"
    np.testing.assert_array_equal(np.load(target), np.arange(6.0).reshape(2, 3))
    assert _hidden(tmp_path) == []  # no stray ".tnpy.XXXX.npy"


def test_npy_with_an_upper_case_suffix_is_the_file_named(tmp_path):
    # np.save given a name appends ".npy" to any name not ending in it exactly.
    path = tmp_path / "D.NPY"
    write_npy(path, np.ones(3))
    np.testing.assert_array_equal(np.load(path), np.ones(3))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["D.NPY"]


def test_render_writes_through_links_to_targets_without_suffix(wall, tmp_path, run_cli):
    mesh, prior = wall
    (tmp_path / "tpng").write_text("y\n")
    (tmp_path / "tnpy").write_text("x\n")
    (tmp_path / "out.png").symlink_to("tpng")
    (tmp_path / "d.npy").symlink_to("tnpy")
    run = run_cli(["render", mesh, prior, "--out", tmp_path / "out.png",
                   "--depth", tmp_path / "d.npy"])
    assert run.code == 0, run.err
    assert (tmp_path / "out.png").is_symlink() and (tmp_path / "d.npy").is_symlink()
    with Image.open(tmp_path / "tpng") as im:
        assert im.format == "PNG" and im.size == (160, 120)
    assert np.load(tmp_path / "tnpy").shape == (120, 160)
    assert _hidden(tmp_path) == []


def test_image_with_an_extension_opencv_cannot_write_is_one_error(tmp_path):
    from napari_imgreg.io.photos import save_image

    with pytest.raises(InputError, match=r"x\.xyz: cannot write image"):
        save_image(tmp_path / "x.xyz", np.zeros((4, 4, 3), np.uint8))
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------ 2. shapefile sets, all or nothing
def _features():
    from napari_imgreg.interpret.project import Feature3D

    line = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.5], [2.0, 0.0, 1.0]])
    return [Feature3D("f1", "trace", [line], {"label": "fault", "source": "IMG_0001.jpg"})]


def _set_bytes(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}


def test_shapefile_set_lists_every_file():
    from napari_imgreg.interpret.files import gis_output_files

    names = [p.name for p in gis_output_files("shp/L.shp")]
    assert "L.shp" in names and "L.dbf" in names and "L_measurements.dbf" in names
    assert "L_cameras.shx" in names and len(names) == 20
    assert gis_output_files("a.gpkg") == [Path("a.gpkg")]


def test_folder_in_a_shapefile_set_is_refused_before_anything_is_replaced(tmp_path):
    pytest.importorskip("pyogrio")
    from napari_imgreg.interpret.files import write_features_gis

    path = tmp_path / "L.shp"
    write_features_gis(path, _features())
    (tmp_path / "L_measurements.dbf").unlink()
    (tmp_path / "L_measurements.dbf").mkdir()
    before = _set_bytes(tmp_path)
    with pytest.raises(InputError, match=r"L_measurements\.dbf: cannot write here: it is a folder"):
        write_features_gis(path, _features() * 2)
    assert _set_bytes(tmp_path) == before and _hidden(tmp_path) == []


def test_a_rename_refused_half_way_puts_the_set_back(tmp_path, monkeypatch):
    pytest.importorskip("pyogrio")
    from napari_imgreg.interpret import files

    path = tmp_path / "L.shp"
    files.write_features_gis(path, _features())
    before = _set_bytes(tmp_path)
    real_replace, calls = os.replace, []

    def replace(src, dst):
        calls.append(Path(dst).name)
        if len(calls) == 7:  # an immutable file in the middle of the set
            raise PermissionError(1, "Operation not permitted", os.fspath(src), None,
                                  os.fspath(dst))
        return real_replace(src, dst)

    monkeypatch.setattr(files.os, "replace", replace)
    with pytest.raises(OutputError, match=r"cannot write \(Operation not permitted\)"):
        files.write_features_gis(path, _features() * 2)
    assert len(calls) > 7  # the six replaced files were put back
    assert _set_bytes(tmp_path) == before and _hidden(tmp_path) == []


def test_project_refuses_the_folder_before_the_mesh_loads(wall, tmp_path, run_cli):
    pytest.importorskip("pyogrio")
    from napari_imgreg import Intrinsics, Pose
    from napari_imgreg.interpret.files import write_interpretations
    from napari_imgreg.interpret.project import Interpretation

    mesh, _ = wall
    intr = Intrinsics(160, 120, 100.0, 100.0, 79.5, 59.5)
    pose = Pose.from_attitude(0.0, 0.0, 0.0, [20.0, -30.0, 10.0])
    result = tmp_path / "RESULT.json"
    result.write_text(json.dumps({"status": "registered", "camera": intr.to_dict(),
                                  "pose": pose.to_dict()}))
    lines = tmp_path / "lines.geojson"
    write_interpretations(lines, [Interpretation(
        "LineString", np.array([[40.0, 60.0], [120.0, 70.0]]), {"label": "fault"})])
    out = tmp_path / "shp" / "L.shp"
    assert run_cli(["project", result, mesh, lines, "--out", out]).code == 0
    (out.parent / "L_measurements.dbf").unlink()
    (out.parent / "L_measurements.dbf").mkdir()
    before = _set_bytes(out.parent)
    run = run_cli(["project", result, mesh, lines, "--out", out])
    assert run.code == 2
    assert "L_measurements.dbf: cannot write here: it is a folder" in run.line
    assert run.out == ""  # refused before any feature was projected
    assert _set_bytes(out.parent) == before and _hidden(out.parent) == []


# --------------------------------- 3. outputs that cannot be written, up front
@pytest.mark.parametrize("blocked", ["summary.csv", "summary.json", "IMG_0002.result.json"])
def test_batch_refuses_a_folder_in_the_way_before_registering(tmp_path, monkeypatch, run_cli,
                                                             blocked):
    from test_cli_batch import _make_scene

    def must_not_run(*args, **kwargs):
        raise AssertionError("registered a photo")

    monkeypatch.setattr("napari_imgreg.registration.pipeline.register", must_not_run)
    monkeypatch.setattr("napari_imgreg.scene.Scene.load", must_not_run)
    scene = _make_scene(tmp_path / "scene", ["IMG_0001", "IMG_0002"])
    (tmp_path / "res" / blocked).mkdir(parents=True)
    run = run_cli(["batch", scene, "--out", tmp_path / "res", "--workers", 0])
    assert run.code == 2
    assert run.line.endswith(f"res/{blocked}: cannot write here: it is a folder, not a file")
    assert sorted(p.name for p in (tmp_path / "res").iterdir()) == [blocked]


def _refuse_renames(monkeypatch):
    def replace(src, dst):
        raise PermissionError(1, "Operation not permitted", os.fspath(src), None, os.fspath(dst))

    monkeypatch.setattr(_atomic.os, "replace", replace)


def test_refused_rename_of_an_output_is_one_line_naming_it(wall, tmp_path, monkeypatch, run_cli):
    mesh, prior = wall
    out = tmp_path / "r.png"
    out.write_bytes(b"old")
    _refuse_renames(monkeypatch)  # as for an immutable file (chattr +i)
    run = run_cli(["render", mesh, prior, "--out", out])
    assert run.code == 2
    assert run.line == f"napari-imgreg render: error: {out}: cannot write (Operation not permitted)"
    assert out.read_bytes() == b"old" and _hidden(tmp_path) == []


def test_a_full_disk_is_one_line_naming_the_output(wall, tmp_path, monkeypatch, run_cli):
    """No space left while writing: the system's error names no file; the
    command's line names the output, exit 2, the earlier file kept."""
    import errno

    mesh, prior = wall
    out = tmp_path / "r.png"
    out.write_bytes(b"old")

    def disk_full(path):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(_atomic, "fsync_file", disk_full)
    run = run_cli(["render", mesh, prior, "--out", out])
    assert run.code == 2
    assert run.line == f"napari-imgreg render: error: {out}: cannot write (No space left on device)"
    assert out.read_bytes() == b"old" and _hidden(tmp_path) == []


def test_output_error_is_an_os_error_and_one_line(tmp_path, monkeypatch):
    import pickle

    _refuse_renames(monkeypatch)
    with pytest.raises(OSError) as caught:
        write_json(tmp_path / "a.json", {"a": 1})
    error = caught.value
    assert isinstance(error, OutputError) and error.errno == 1
    assert str(error) == f"{tmp_path / 'a.json'}: cannot write (Operation not permitted)"
    # A batch worker sends it to the client.
    again = pickle.loads(pickle.dumps(error))
    assert type(again) is OutputError and str(again) == str(error) and again.errno == 1


def test_a_folder_that_takes_no_file_names_the_output(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    with pytest.raises(OutputError, match=r"a_file/out\.json: cannot write \(a file is in the way of its folder\)"):
        write_json(blocker / "out.json", {})
    with pytest.raises(OutputError, match=r"a_file/sub/out\.json: cannot write \(a file is in"):
        write_json(blocker / "sub" / "out.json", {})
    assert blocker.read_text() == "not a folder"


def test_an_os_error_naming_a_file_is_one_line(monkeypatch, run_cli):
    from napari_imgreg.cli import render

    def refused(args):
        raise PermissionError(13, "Permission denied", "/somewhere/out.png")

    monkeypatch.setattr(render, "run", refused)
    run = run_cli(["render", "m.obj", "p.json", "--out", "out.png"])
    assert run.code == 2
    assert run.line == "napari-imgreg render: error: /somewhere/out.png: Permission denied"


def test_a_result_that_cannot_be_written_is_that_photos_outcome(tmp_path, monkeypatch):
    from test_cli_batch import _fake_registration

    from napari_imgreg import Intrinsics, Pose
    from napari_imgreg.prior import Prior
    from napari_imgreg.registration import batch

    prior = Prior(Intrinsics(160, 120, 100.0, 100.0, 79.5, 59.5),
                  Pose.from_attitude(0.0, 0.0, 0.0, [0.0, 0.0, 0.0]))
    monkeypatch.setattr("napari_imgreg.registration.pipeline.register",
                        lambda scene, image, prior, params=None, photo_name="", on_progress=None:
                        _fake_registration(prior, photo_name, status="registered"))
    monkeypatch.setattr(batch, "cached_scene", lambda spec, scene=None: None)
    monkeypatch.setattr(batch, "prior_for_photo", lambda photo, scene: prior)
    monkeypatch.setattr(batch, "check_photo_size", lambda photo, prior: None)
    photo = tmp_path / "IMG_0001.jpg"
    Image.new("RGB", (160, 120)).save(photo)
    _refuse_renames(monkeypatch)
    out = tmp_path / "IMG_0001.result.json"
    outcome = batch.register_photo_file(batch.SceneSpec("m.obj", None, None), str(photo),
                                        str(out), None)
    assert outcome["status"] == "bad_input"
    assert outcome["error"] == f"{out}: cannot write (Operation not permitted)"
    assert not out.exists() and _hidden(tmp_path) == []


# ------------------------------------------------- 4. tifffile's own log lines
def _truncated_dem(folder: Path) -> Path:
    from napari_imgreg.io.rasters import write_dem_geotiff

    whole = folder / "dem.tif"
    write_dem_geotiff(whole, np.zeros((20, 30)), 0.0, 0.0, 1.0, 1.0, "EPSG:32630")
    cut = folder / "t.tif"
    cut.write_bytes(whole.read_bytes()[:300])  # tags that point past the end
    return cut


def test_reading_a_truncated_dem_logs_no_tifffile_warnings(tmp_path, caplog):
    from napari_imgreg.io.rasters import GeoError, read_geotiff

    cut = _truncated_dem(tmp_path)
    with caplog.at_level(logging.DEBUG):
        with pytest.raises(GeoError, match="t.tif"):
            read_geotiff(cut)
    assert not [r for r in caplog.records if r.name == "tifffile"]
    # Kept as our debug records, for whoever turns them on.
    assert any(r.levelno == logging.DEBUG and "TiffFileError" in r.getMessage()
               for r in caplog.records if r.name == "napari_imgreg.io.rasters")
    # Outside the reader tifffile logs as before.
    import tifffile

    with caplog.at_level(logging.WARNING):
        with pytest.raises(Exception):
            with tifffile.TiffFile(cut) as tf:
                tf.pages[0].asarray()
    assert [r for r in caplog.records if r.name == "tifffile"]


def test_render_with_a_truncated_dem_prints_only_our_line(wall, tmp_path):
    mesh, prior = wall
    cut = _truncated_dem(tmp_path)
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    proc = subprocess.run([sys.executable, "-m", "napari_imgreg", "render", str(mesh),
                           str(prior), "--out", str(tmp_path / "r.png"), "--dem", str(cut)],
                          env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == [
        f"napari-imgreg render: error: {cut}: its image data runs past the end of the file "
        "(truncated or corrupt)"]


def test_a_dem_whose_size_needs_more_strips_than_it_lists_is_refused_at_once(tmp_path):
    """One byte of a 3×4 DEM flipped (found by the readers' fuzz): its height
    read 16.5 million rows, of which the file held one strip; tifffile filled
    the rest with zeros, and the DEM loaded as 66 million cells of height 0
    after 20 s. Now: one line, before decoding."""
    import time

    import tifffile

    from napari_imgreg.geo import DEM
    from napari_imgreg.io.rasters import GeoError, write_dem_geotiff

    whole = tmp_path / "dem.tif"
    write_dem_geotiff(whole, np.arange(12.0).reshape(3, 4), 500000.0, 5000030.0, 10.0, 10.0,
                      "EPSG:32632")
    data = bytearray(whole.read_bytes())
    with tifffile.TiffFile(whole) as tf:
        length_tag = tf.pages[0].tags["ImageLength"]
        assert length_tag.dtype in (3, 4)  # SHORT or LONG, its value inline
        at = length_tag.valueoffset
        strips = math.ceil(60000 / tf.pages[0].rowsperstrip)
    data[at:at + 2] = (60000).to_bytes(2, "little")  # 60000 rows, the strip list unchanged
    bad = tmp_path / "bad.tif"
    bad.write_bytes(bytes(data))
    t0 = time.perf_counter()
    with pytest.raises(GeoError) as exc:
        DEM.load(bad)
    assert time.perf_counter() - t0 < 2.0
    assert str(exc.value) == (f"{bad}: its size (4×60000) needs {strips:,} strips or tiles of "
                              "image data and the file lists 1 (truncated or corrupt)")
