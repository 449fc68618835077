"""Windows and macOS behaviour, emulated on Linux.

CI runs on Linux only. These tests put one platform rule at a time in
place, through the module-level flag or helper the code consults (never by
changing the ``os`` module globally), and check the tool still does its job.
"""

from __future__ import annotations

import errno
import fcntl
import os

import pytest

from napari_imgreg import _atomic
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

    monkeypatch.setattr(_atomic, "_WINDOWS", True)
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
    monkeypatch.setattr(_atomic, "_WINDOWS", False)
    assert _atomic._flush_open_flags() == os.O_RDONLY


def test_gis_export_replaces_its_files_on_windows(tmp_path, windows_fsync):
    """The shapefile set is flushed by :func:`fsync_file` before its renames."""
    import numpy as np

    from napari_imgreg.interpret.files import read_gis_layers, write_features_gis
    from napari_imgreg.interpret.project import Feature3D

    pytest.importorskip("pyogrio", reason="pyogrio (GDAL) not installed")
    feature = Feature3D("t1", "trace", [np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0]])],
                        {"label": "Störung", "source": "IMG_1.jpg"})
    write_features_gis(tmp_path / "map.shp", [feature])
    assert windows_fsync
    _, fields, _ = read_gis_layers(tmp_path / "map.shp")["traces"]
    assert list(fields["label"]) == ["Störung"]
