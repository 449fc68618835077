"""Atomic writes: all or nothing, with ordinary file permissions."""

import os

import pytest

from napari_imgreg._atomic import atomic_write, umask


def test_new_file_gets_umask_mode(tmp_path):
    path = tmp_path / "out.json"
    with atomic_write(path) as fh:
        fh.write("{}")
    assert path.read_text() == "{}"
    assert os.stat(path).st_mode & 0o777 == 0o666 & ~umask()


def test_replaced_file_keeps_its_mode(tmp_path):
    path = tmp_path / "out.json"
    path.write_text("old")
    path.chmod(0o640)
    with atomic_write(path) as fh:
        fh.write("new")
    assert path.read_text() == "new" and os.stat(path).st_mode & 0o777 == 0o640


def test_failure_leaves_old_file_and_no_temporary(tmp_path):
    path = tmp_path / "out.json"
    path.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_write(path) as fh:
            fh.write("half")
            raise RuntimeError("disk full")
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.json"]
