"""Windows and macOS behaviour, emulated on Linux.

CI runs on Linux only. These tests put one platform rule at a time in
place, through the module-level flag or helper the code consults (never by
changing the ``os`` module globally), and check the tool still does its job.
"""

from __future__ import annotations

import errno
import fcntl
import os
from pathlib import Path

import numpy as np
import pytest

from napari_imgreg import _atomic, _platform
from napari_imgreg._atomic import atomic_write


@pytest.fixture
def windows_fsync(monkeypatch):
    """Windows' ``os.fsync`` (FlushFileBuffers): EBADF on a handle opened
    without write access; the code takes its Windows path."""
    real_fsync = os.fsync
    flushed = []

    def fsync(fd):
        if fcntl.fcntl(fd, fcntl.F_GETFL) & os.O_ACCMODE == os.O_RDONLY:
            raise OSError(errno.EBADF, "Bad file descriptor")
        flushed.append(fd)
        real_fsync(fd)

    monkeypatch.setattr(_platform, "WINDOWS", True)
    monkeypatch.setattr(os, "fsync", fsync)
    return flushed


def test_atomic_write_flushes_through_a_writable_handle_on_windows(tmp_path, windows_fsync):
    path = tmp_path / "traces.geojson"
    with atomic_write(path, encoding="utf-8") as fh:
        fh.write('{"label": "grès"}')
    assert path.read_text(encoding="utf-8") == '{"label": "grès"}'
    assert windows_fsync, "the file was not flushed"
    assert [p.name for p in tmp_path.iterdir()] == ["traces.geojson"]


def test_read_only_output_is_flushed_before_it_gets_its_mode(tmp_path, windows_fsync):
    # The new file takes the replaced one's mode; flushing after that would
    # need a writable handle on a read-only file.
    path = tmp_path / "measurements.csv"
    path.write_text("old", encoding="utf-8")
    path.chmod(0o444)
    calls = []
    real_open = os.open

    def open_checking_mode(file, flags, *args, **kwargs):
        if flags & os.O_ACCMODE == os.O_RDWR and not flags & os.O_CREAT:  # not mkstemp's
            calls.append(os.stat(file).st_mode & 0o777)
        return real_open(file, flags, *args, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(_atomic.os, "open", open_checking_mode)
        with atomic_write(path, encoding="utf-8") as fh:
            fh.write("new")
    assert path.read_text(encoding="utf-8") == "new"
    assert os.stat(path).st_mode & 0o777 == 0o444
    assert calls == [0o600], "flushed after the chmod (or not through a writable handle)"


def test_linux_still_flushes_read_only(monkeypatch):
    monkeypatch.setattr(_platform, "WINDOWS", False)
    assert _atomic._flush_open_flags() == os.O_RDONLY


def test_gis_export_replaces_its_files_on_windows(tmp_path, windows_fsync):
    """The shapefile set is flushed by :func:`fsync_file` before its renames."""

    from napari_imgreg.interpret.files import read_gis_layers, write_features_gis
    from napari_imgreg.interpret.project import Feature3D

    pytest.importorskip("pyogrio", reason="pyogrio (GDAL) not installed")
    feature = Feature3D("t1", "trace", [np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0]])],
                        {"label": "Störung", "source": "IMG_1.jpg"})
    write_features_gis(tmp_path / "map.shp", [feature])
    assert windows_fsync
    _, fields, _ = read_gis_layers(tmp_path / "map.shp")["traces"]
    assert list(fields["label"]) == ["Störung"]


# ------------------------------------------------- a file open in another program
def test_output_open_in_excel_is_one_line_saying_to_close_it(tmp_path, monkeypatch):
    """Windows refuses to replace a file another program holds open."""
    from napari_imgreg.interpret.files import write_measurements_csv

    path = tmp_path / "measurements.csv"
    path.write_text("open in Excel\n", encoding="utf-8")

    def replace_refused(src, dst):
        raise PermissionError(errno.EACCES, "Access is denied", os.fspath(src), None, os.fspath(dst))

    monkeypatch.setattr(_platform, "WINDOWS", True)
    monkeypatch.setattr(_atomic.os, "replace", replace_refused)
    with pytest.raises(_atomic.OutputError) as caught:
        write_measurements_csv(path, [])
    message = str(caught.value)
    assert "\n" not in message and message.startswith(f"{path}: cannot write")
    assert "open in another program" in message and "close it" in message
    assert path.read_text(encoding="utf-8") == "open in Excel\n"
    assert [p.name for p in tmp_path.iterdir()] == ["measurements.csv"]


@pytest.mark.parametrize("windows", [True, False])
def test_a_rename_refused_for_a_moment_is_tried_again_on_windows(tmp_path, monkeypatch, windows):
    """A virus scanner or the search indexer opening the new file for a
    moment: Windows refuses the rename; it is tried again."""
    path = tmp_path / "traces.geojson"
    refusals = []
    real_replace = os.replace

    def replace(src, dst):
        if len(refusals) < 2:
            refusals.append(dst)
            raise PermissionError(errno.EACCES, "Access is denied")
        real_replace(src, dst)

    monkeypatch.setattr(_platform, "WINDOWS", windows)
    monkeypatch.setattr(_atomic.os, "replace", replace)
    if windows:
        with atomic_write(path, encoding="utf-8") as fh:
            fh.write("{}")
        assert path.read_text(encoding="utf-8") == "{}" and len(refusals) == 2
    else:  # POSIX renames do not fail so: no waiting
        with pytest.raises(_atomic.OutputError):
            with atomic_write(path, encoding="utf-8") as fh:
                fh.write("{}")
        assert len(refusals) == 1
    assert [p.name for p in tmp_path.iterdir()] == (["traces.geojson"] if windows else [])


def test_refused_replace_off_windows_keeps_the_system_reason(tmp_path, monkeypatch):
    path = tmp_path / "out.json"
    path.write_text("{}", encoding="utf-8")

    def replace_refused(src, dst):
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(_platform, "WINDOWS", False)
    monkeypatch.setattr(_atomic.os, "replace", replace_refused)
    with pytest.raises(_atomic.OutputError, match=r"cannot write \(Permission denied\)$"):
        with atomic_write(path, encoding="utf-8") as fh:
            fh.write("{}")


def test_cli_names_the_held_file_in_one_line(tmp_path, monkeypatch, run_cli):
    table = tmp_path / "cams.csv"
    table.write_text("photo,trend_deg,plunge_deg,roll_deg\na,10,5,0\nb,100,3,1\nc,200,8,-1\n",
                     encoding="utf-8")
    phone = tmp_path / "phone.csv"
    phone.write_bytes(table.read_bytes())
    out = tmp_path / "orientation.json"
    out.write_text("{}", encoding="utf-8")

    def replace_refused(src, dst):
        raise PermissionError(errno.EACCES, "Access is denied")

    monkeypatch.setattr(_platform, "WINDOWS", True)
    monkeypatch.setattr(_atomic.os, "replace", replace_refused)
    run = run_cli(["orient", table, phone, "--out", out])
    assert run.code == 2 and "Traceback" not in run.err
    assert run.line.startswith(f"napari-imgreg orient: error: {out}: cannot write (it is open in "
                               "another program"), run.err


# ------------------------------------------------------- text files and the locale
def run_in_legacy_locale(code: str, *args: str, io_encoding: str | None = None):
    """Run ``python -c code`` where the locale's encoding is not UTF-8.

    Windows' default text encoding is the ANSI code page (cp1252 in Western
    Europe), not UTF-8. Here the C locale without UTF-8 coercion gives ASCII,
    stricter still: a text file opened without ``encoding=`` fails on the
    first non-ASCII character, and PEP 597's EncodingWarning, raised as an
    error for this package's modules, names the call.
    """
    import subprocess
    import sys

    src = Path(__file__).resolve().parents[1] / "src"
    env = {**os.environ, "LC_ALL": "C", "LANG": "C", "PYTHONCOERCECLOCALE": "0", "PYTHONUTF8": "0",
           "PYTHONPATH": os.pathsep.join([str(src), os.environ.get("PYTHONPATH", "")])}
    env.pop("PYTHONIOENCODING", None)
    if io_encoding:
        env["PYTHONIOENCODING"] = io_encoding
    prelude = ("import warnings; warnings.filterwarnings('error', category=EncodingWarning, "
               "module=r'napari_imgreg(\\.|$)')\n")
    return subprocess.run(
        [sys.executable, "-X", "warn_default_encoding", "-c", prelude + code, *args],
        env=env, capture_output=True, timeout=300, encoding="utf-8", errors="replace")


def test_legacy_locale_is_emulated():
    run = run_in_legacy_locale("import locale; print(locale.getpreferredencoding(False))")
    assert run.returncode == 0, run.stderr
    assert "utf" not in run.stdout.lower(), run.stdout


def test_orientation_table_with_accented_photo_names_in_a_legacy_locale(tmp_path):
    code = '''
import sys
import numpy as np
from napari_imgreg.io.orientation_tables import (
    OrientationTable, read_orientation_csv, write_orientation_csv)
photos = ["gr\\u00e8s_01.jpg", "St\\u00f6rung\\u2192IMG_2.jpg", "\\u03c3-IMG_3.jpg"]
table = OrientationTable(photos, np.tile(np.eye(3), (3, 1, 1)), np.zeros(3))
write_orientation_csv(sys.argv[1], table)
assert read_orientation_csv(sys.argv[1]).photos == photos
'''
    path = tmp_path / "cams.csv"
    run = run_in_legacy_locale(code, str(path))
    assert run.returncode == 0, run.stderr
    text = path.read_bytes().decode("utf-8")
    assert "grès_01.jpg" in text and "\r\r" not in text  # newline="": one CRLF per row


def test_mesh_companions_and_batch_textures_read_utf8_materials(tmp_path):
    """An OBJ's material file is UTF-8 (what Metashape and CloudCompare
    write), read as such whatever the locale. (File names stay ASCII here:
    an ASCII locale cannot name the others, which Windows can.)"""
    (tmp_path / "model.mtl").write_text("# mat\u00e9riau gr\u00e8s\nnewmtl m\nmap_Kd texture_0.jpg\n",
                                        encoding="utf-8")
    (tmp_path / "texture_0.jpg").write_bytes(b"\xff\xd8\xff")
    (tmp_path / "model.obj").write_text("mtllib model.mtl\nv 0 0 0\n", encoding="utf-8")
    code = '''
import sys
from pathlib import Path
from napari_imgreg.io.meshes import _companions
from napari_imgreg.cli.batch import _textures_named_by
folder = Path(sys.argv[1])
names = [p.name for p in _companions(folder / "model.obj")]
assert names == ["model.obj", "model.mtl", "texture_0.jpg"], names
assert "texture_0.jpg" in _textures_named_by([folder / "model.obj"], folder)
'''
    run = run_in_legacy_locale(code, str(tmp_path))
    assert run.returncode == 0, run.stderr


# ------------------------------------------------------------------ the console
def run_cli_process(*args: str, io_encoding: str):
    """``python -m napari_imgreg ARGS`` whose stdout and stderr are in
    ``io_encoding``: on Windows, output redirected to a file or a pipe is in
    the ANSI code page (cp1252), a console window's (cp437, cp850) for some
    programs."""
    import subprocess
    import sys

    src = Path(__file__).resolve().parents[1] / "src"
    env = {**os.environ, "PYTHONIOENCODING": io_encoding,
           "PYTHONPATH": os.pathsep.join([str(src), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-m", "napari_imgreg", *args], env=env,
                          capture_output=True, timeout=300)


@pytest.mark.parametrize("io_encoding", ["cp1252", "cp437"])
def test_help_with_greek_letters_prints_in_a_code_page(io_encoding):
    run = run_cli_process("measure", "--help", io_encoding=io_encoding)
    assert run.returncode == 0 and b"Traceback" not in run.stderr, run.stderr
    out = run.stdout.decode(io_encoding)
    assert "--max-dip-sigma" in out
    # What the code page lacks is escaped; what it has is printed as is.
    assert ("\\u03c3" in out) == (io_encoding == "cp1252") and "\\u03bb" in out


def test_summary_is_printed_whole_in_a_code_page(tmp_path):
    """``orient``'s summary has Δξ/Δρ and the output's name: a code page
    without them used to end the summary there, silently (exit code 0)."""
    table = tmp_path / "cams.csv"
    table.write_text("photo,trend_deg,plunge_deg,roll_deg\na,10,5,0\nb,100,3,1\nc,200,8,-1\n",
                     encoding="utf-8")
    phone = tmp_path / "phone.csv"
    phone.write_bytes(table.read_bytes())
    out = tmp_path / "Störung→orientation.json"
    run = run_cli_process("orient", str(table), str(phone), "--out", str(out), io_encoding="cp1252")
    assert run.returncode == 0 and b"Traceback" not in run.stderr, run.stderr
    text = run.stdout.decode("cp1252")
    assert "mean |\\u0394\\u03be|" in text and "rotation 0.00° clockwise" in text
    assert text.rstrip().endswith("Störung\\u2192orientation.json"), text
    assert out.exists()


def test_console_left_alone_when_it_is_utf8(capsys):
    import sys

    from napari_imgreg._platform import tolerant_console

    before = sys.stdout.errors
    with tolerant_console():
        assert sys.stdout.errors == before


# ------------------------------------------------------------------ the caches
@pytest.mark.parametrize("system, expected", [
    ("win32", ("AppData", "Local", "napari-imgreg", "Cache")),
    ("darwin", ("Library", "Caches", "napari-imgreg")),
    ("linux", (".cache", "napari-imgreg")),
])
def test_caches_live_in_the_systems_user_cache_folder(monkeypatch, tmp_path, system, expected):
    """platformdirs decides the folder from ``sys.platform``: each system's is
    asked for by giving platformdirs that system's name."""
    import importlib

    import platformdirs

    from napari_imgreg.io.meshes import mesh_cache_dir
    from napari_imgreg.sample import cache_dir

    monkeypatch.delenv("NAPARI_IMGREG_CACHE", raising=False)
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setenv("LOCALAPPDATA", str(tmp_path / "AppData" / "Local"))
    monkeypatch.setattr("sys.platform", system)
    try:
        importlib.reload(platformdirs)  # it picks its class for sys.platform on import
        if system == "win32":  # asks Windows' shell folders API, absent here
            monkeypatch.setattr("platformdirs.windows.get_win_folder",
                                lambda csidl: os.environ["LOCALAPPDATA"])
        root = cache_dir()
    finally:
        monkeypatch.undo()
        importlib.reload(platformdirs)
    assert root.parts[-len(expected):] == expected and root.is_relative_to(tmp_path), root
    assert mesh_cache_dir().name == "meshes"


def test_cache_override_is_kept(monkeypatch, tmp_path):
    from napari_imgreg.io.meshes import mesh_cache_dir
    from napari_imgreg.sample import cache_dir

    monkeypatch.setenv("NAPARI_IMGREG_CACHE", str(tmp_path / "c"))
    assert cache_dir() == tmp_path / "c" and mesh_cache_dir() == tmp_path / "c" / "meshes"


# ------------------------------------------------------------ names for files
@pytest.mark.parametrize("text, expected", [
    ("IMG_0001", "IMG_0001"),
    ("grès Störung", "grès Störung"),
    ('a<b>c:d"e/f\\g|h?i*j', "a_b_c_d_e_f_g_h_i_j"),
    ("IMG.", "IMG"),
    ("IMG. . ", "IMG"),
    ("CON", "CON_"),
    ("con.backup", "con_.backup"),
    ("Com1", "Com1_"),
    ("LPT9", "LPT9_"),
    ("CONSOLE", "CONSOLE"),
    (".", "photo"),
    ("..", "photo"),
    ("", "photo"),
    ("x" * 300, "x" * 100),
])
def test_portable_name(text, expected):
    from napari_imgreg._platform import portable_name

    assert portable_name(text, fallback="photo") == expected


def test_photo_folders_are_names_windows_accepts_inside_photos():
    from napari_imgreg.io.workspace_files import photo_key

    taken: set[str] = set()
    keys = [photo_key(name, taken) for name in
            ["CON.jpg", "aux.JPG", "IMG..jpg", "IMG.jpg", "..jpg", "...jpg", "IMG_1.jpg", "img_1.JPG"]]
    assert keys == ["CON_", "aux_", "IMG", "IMG_2", "photo", "photo_2", "IMG_1", "img_1_2"]


def test_workspace_photos_with_awkward_names_get_folders_inside_photos(tmp_path, run_cli):
    """A photo named ``...jpg`` used to get the folder ``photos/..``: its
    files went into the workspace's own folder; ``CON.jpg`` a folder Windows
    cannot make."""
    import shutil

    from napari_imgreg.io import workspace_files as wsfiles
    from napari_imgreg.sample import sample_scene
    from napari_imgreg.workspace import Workspace

    src = sample_scene("small")
    photos = tmp_path / "photos in"
    photos.mkdir()
    for name in (".", "..", "CON", "IMG."):
        for suffix in (".jpg", ".json"):
            shutil.copy(src / f"IMG_0002{suffix}", photos / f"{name}{suffix}")
    folder = tmp_path / "campaign.imgreg"
    assert run_cli(["workspace", "create", folder, src, "--no-photos"]).code == 0
    before = sorted(p.name for p in folder.iterdir())
    added = run_cli(["workspace", "add", folder, *sorted(photos.glob("*.jpg"))])
    assert added.code == 0, added.err
    assert sorted(p.name for p in folder.iterdir()) == sorted([*before, wsfiles.PHOTOS_DIR])
    keys = sorted(p.name for p in (folder / wsfiles.PHOTOS_DIR).iterdir())
    assert keys == ["CON_", "IMG", "photo", "photo_2"]
    opened = Workspace.open(folder, autosave=False)
    assert sorted(opened.photo_key(ps) for ps in opened.photos) == keys


# ------------------------------------------------- worker processes by spawn
@pytest.mark.slow
def test_batch_on_two_spawned_worker_processes(tmp_path):
    """Windows and macOS start processes by spawn: a worker imports the
    package afresh and gets everything by pickle. Dask uses spawn on every
    system unless configured otherwise; here it is asked for explicitly,
    with ``python -m napari_imgreg`` (whose ``__main__`` a spawned worker
    must not run again)."""
    import csv
    import shutil
    import subprocess
    import sys

    from napari_imgreg.sample import sample_scene

    scene = tmp_path / "scene"
    shutil.copytree(sample_scene("small"), scene,
                    ignore=shutil.ignore_patterns("IMG_0003.*", "orient"))
    src = Path(__file__).resolve().parents[1] / "src"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(src), os.environ.get("PYTHONPATH", "")]),
           "DASK_DISTRIBUTED__WORKER__MULTIPROCESSING_METHOD": "spawn"}
    run = subprocess.run(
        [sys.executable, "-m", "napari_imgreg", "batch", str(scene), "--out", str(tmp_path / "out"),
         "--workers", "2"], env=env, capture_output=True, text=True, encoding="utf-8", timeout=900)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "2 worker process(es)" in run.stdout
    with open(tmp_path / "out" / "summary.csv", newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert sorted((r["photo"], r["status"]) for r in rows) == [
        ("IMG_0001.jpg", "registered"), ("IMG_0002.jpg", "registered")]


def test_batch_goes_on_while_its_summary_is_open_in_excel(tmp_path, monkeypatch):
    """On Windows a summary.csv open in Excel cannot be replaced: it used to
    end the batch after the photo being recorded; now the photos go on and
    the summary is written once it is closed."""
    from test_cli_batch import _fake_registration, _make_scene, _run, _summary

    scene = _make_scene(tmp_path / "scene", ["IMG_0001", "IMG_0002", "IMG_0003"])
    out = tmp_path / "results"
    real_replace = os.replace

    def replace(src, dst):  # held open while the first photo is recorded
        if Path(dst).name == "summary.csv" and len(list(out.glob("*.result.json"))) < 2:
            raise PermissionError(errno.EACCES, "Access is denied")
        real_replace(src, dst)

    def fake_register(scene_, image, prior, params=None, photo_name="", on_progress=None):
        return _fake_registration(prior, photo_name)

    monkeypatch.setattr("napari_imgreg.registration.pipeline.register", fake_register)
    monkeypatch.setattr(_platform, "WINDOWS", True)
    monkeypatch.setattr(_atomic.os, "replace", replace)
    code, stdout, stderr = _run(["batch", scene, "--out", out, "--workers", 0])
    assert code == 1 and stderr == "", stdout + stderr  # the stand-in fails every photo
    assert stdout.count("summary.csv: cannot write") == 1, stdout
    assert "the photos go on and the summary is updated once it is closed" in stdout
    assert sorted(p.name for p in out.glob("*.result.json")) == [
        "IMG_0001.result.json", "IMG_0002.result.json", "IMG_0003.result.json"]
    rows, summary = _summary(out)
    assert [r["photo"] for r in rows] == ["IMG_0001.jpg", "IMG_0002.jpg", "IMG_0003.jpg"]
    assert summary["complete"]


def test_batch_summary_refused_off_windows_still_stops(tmp_path, monkeypatch):
    from test_cli_batch import _fake_registration, _make_scene, _run

    scene = _make_scene(tmp_path / "scene", ["IMG_0001", "IMG_0002"])
    real_replace = os.replace

    def replace(src, dst):
        if Path(dst).name == "summary.csv":
            raise PermissionError(errno.EACCES, "Permission denied")
        real_replace(src, dst)

    monkeypatch.setattr("napari_imgreg.registration.pipeline.register",
                        lambda scene_, image, prior, params=None, photo_name="", on_progress=None:
                        _fake_registration(prior, photo_name))
    monkeypatch.setattr(_platform, "WINDOWS", False)
    monkeypatch.setattr(_atomic.os, "replace", replace)
    code, stdout, stderr = _run(["batch", scene, "--out", tmp_path / "out", "--workers", 0])
    assert code == 2 and "summary.csv: cannot write (Permission denied)" in stderr


# ------------------------------------------------ tables saved by a spreadsheet
def test_orientation_table_from_a_decimal_comma_spreadsheet(tmp_path):
    """Excel where the decimal separator is a comma (de, fr, it, es...)
    separates fields with semicolons and writes 12,5."""
    from napari_imgreg.io.orientation_tables import read_orientation_csv

    path = tmp_path / "phone.csv"
    path.write_bytes("\ufeffphoto;trend_deg;plunge_deg;roll_deg;x;y;z\r\n"
                     "Störung_1,2.jpg;12,5;-3,25;0;1,5e3;0;0\r\n"
                     "IMG_2.jpg;100;3;1;-,5;0;0\r\n".encode("utf-8"))
    table = read_orientation_csv(path)
    assert table.photos == ["Störung_1,2.jpg", "IMG_2.jpg"]
    assert table.trend_deg.tolist() == [12.5, 100.0]
    assert table.positions[:, 0].tolist() == [1500.0, -0.5]


def test_comma_separated_table_keeps_refusing_a_decimal_comma(tmp_path):
    from napari_imgreg.errors import InputError
    from napari_imgreg.io.orientation_tables import read_orientation_csv

    path = tmp_path / "phone.csv"
    path.write_text('photo,trend_deg,plunge_deg,roll_deg\na.jpg,"12,5",0,0\n', encoding="utf-8")
    with pytest.raises(InputError, match=r"row 2: trend_deg is not a number \('12,5'\)"):
        read_orientation_csv(path)


def test_control_points_saved_in_the_windows_code_page_say_how_to_save_them(tmp_path):
    from napari_imgreg.errors import InputError
    from napari_imgreg.io.control_points import read_control_points

    path = tmp_path / "pairs.csv"
    path.write_bytes("photo_x,photo_y,x,y,z,name\n10,20,1,2,3,Störung\n".encode("cp1252"))
    with pytest.raises(InputError) as caught:
        read_control_points(path)
    assert str(caught.value) == (f"{path}: line 2: not UTF-8 text; save the table as UTF-8 "
                                 "(Excel: 'CSV UTF-8')")


def test_shapefile_set_named_with_brackets_is_written(tmp_path):
    """A name like ``map[v2].shp`` was taken as a glob pattern: nothing was written."""
    pytest.importorskip("pyogrio", reason="pyogrio (GDAL) not installed")

    from napari_imgreg.interpret.files import gis_output_files, write_features_gis
    from napari_imgreg.interpret.project import Feature3D

    feature = Feature3D("t1", "trace", [np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0]])],
                        {"label": "grès"})
    path = tmp_path / "map[v2] (grès).shp"
    write_features_gis(path, [feature])
    assert (tmp_path / "map[v2] (grès).shp").is_file()
    assert {p.name for p in tmp_path.iterdir()} >= {
        p.name for p in gis_output_files(path) if p.name.startswith("map[v2] (grès).")}


# ------------------------------------------------------ dependencies per system
def test_e57_without_pye57_is_one_line(tmp_path, monkeypatch):
    """Intel Macs get no pye57 (no wheel): an E57 is then refused in words."""
    import sys

    from napari_imgreg.errors import InputError
    from napari_imgreg.io.pointclouds import read_point_cloud

    pye57 = pytest.importorskip("pye57")
    path = tmp_path / "scan.e57"
    e57 = pye57.E57(str(path), mode="w")
    e57.write_scan_raw({"cartesianX": np.zeros(3), "cartesianY": np.arange(3.0),
                        "cartesianZ": np.ones(3)})
    e57.close()
    monkeypatch.setitem(sys.modules, "pye57", None)  # import pye57 -> ImportError
    with pytest.raises(InputError, match=r"scan\.e57: reading E57 needs pye57, which is not "
                                         r"installed .* convert the scan to LAZ"):
        read_point_cloud(path)


def test_pye57_is_left_out_only_on_intel_macs():
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+

    from packaging.requirements import Requirement

    pyproject = Path(__file__).resolve().parents[1] / "pyproject.toml"
    deps = tomllib.loads(pyproject.read_text(encoding="utf-8"))["project"]["dependencies"]
    (pye57,) = [Requirement(d) for d in deps if d.startswith("pye57")]

    def installed(sys_platform, machine):
        return pye57.marker.evaluate({"sys_platform": sys_platform, "platform_machine": machine})

    assert installed("darwin", "arm64") and installed("win32", "AMD64")
    assert installed("linux", "x86_64") and not installed("darwin", "x86_64")


# ------------------------------------------------------------------- locks
def test_stale_lock_being_read_by_another_session_is_taken_a_moment_later(tmp_path, monkeypatch):
    """Windows cannot delete a file another process has open, even for a
    read: the takeover of a stale lock tries again instead of failing."""
    import json
    import socket
    import subprocess
    import sys

    from napari_imgreg.io import workspace_files as wsfiles

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait(30)
    lock = tmp_path / wsfiles.LOCK
    lock.write_text(json.dumps({"pid": dead.pid, "host": socket.gethostname(),
                                "since": "2026-12-01T08:00:00Z", "token": "stale"}),
                    encoding="utf-8")
    refusals = []
    real_unlink = Path.unlink

    def unlink(self, missing_ok=False):
        if self == lock and not refusals:
            refusals.append(self)
            raise PermissionError(13, "The process cannot access the file because it is "
                                      "being used by another process", str(self))
        real_unlink(self, missing_ok=missing_ok)

    monkeypatch.setattr(Path, "unlink", unlink)
    token = wsfiles.acquire_lock(tmp_path)
    assert refusals and json.loads(lock.read_text(encoding="utf-8"))["token"] == token


# ------------------------------------------------------------------ folders
def test_sample_into_an_empty_folder_made_beforehand_on_windows(tmp_path, monkeypatch, run_cli,
                                                                no_sample_cache):
    """Windows cannot rename a folder over another, even an empty one: the
    sample command into a folder made beforehand (in Explorer) failed there."""
    import napari_imgreg.sample as sample
    from test_sample import _fake_outcrop

    real_replace = os.replace

    def windows_replace(src, dst):
        if os.path.isdir(src) and os.path.exists(dst):
            raise PermissionError(errno.EACCES, "Access is denied", str(src), None, str(dst))
        real_replace(src, dst)

    calls: list = []
    monkeypatch.setattr(sample, "generate_outcrop", _fake_outcrop(calls))
    monkeypatch.setattr(sample.os, "replace", windows_replace)
    folder = tmp_path / "Sample outcrop"
    folder.mkdir()
    run = run_cli(["sample", "--out", folder])
    assert run.code == 0, run.err
    assert (folder / "outcrop.obj").is_file() and (folder / "scene.json").is_file()
    assert [p.name for p in tmp_path.iterdir()] == ["Sample outcrop"]  # no temporary left
