"""The parsed-mesh cache: a hit returns the same arrays; any change to the
mesh, its MTL or its texture is a miss; a damaged entry is only a miss."""

import os
import time

import numpy as np
import pytest
import trimesh
from PIL import Image

from napari_imgreg.io import meshes


@pytest.fixture
def obj(tmp_path, monkeypatch):
    monkeypatch.setenv("NAPARI_IMGREG_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(meshes, "_CACHE_MIN_BYTES", 0)
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    tex = Image.fromarray(np.arange(48, dtype=np.uint8).reshape(4, 4, 3))
    trimesh.Trimesh(v, f, visual=trimesh.visual.TextureVisuals(uv=uv, image=tex),
                    process=False).export(tmp_path / "m.obj")
    return tmp_path / "m.obj"


def _same(a, b):
    for name in ("vertices", "faces", "uv", "texture"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_second_load_comes_from_the_cache(obj, monkeypatch):
    first = meshes.load_mesh(obj)
    entries = list(meshes.mesh_cache_dir().glob("*.npz"))
    assert len(entries) == 1
    monkeypatch.setattr(meshes, "_parse", lambda p: pytest.fail("parsed again"))
    _same(meshes.load_mesh(obj), first)


def test_changed_texture_invalidates(obj):
    meshes.load_mesh(obj)
    png = next(obj.parent.glob("*.png"))
    Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(png)
    os.utime(png, ns=(time.time_ns() + 10**9,) * 2)
    assert meshes.load_mesh(obj).texture.max() == 0
    assert len(list(meshes.mesh_cache_dir().glob("*.npz"))) == 2


def test_damaged_entry_is_a_miss(obj):
    first = meshes.load_mesh(obj)
    entry = next(meshes.mesh_cache_dir().glob("*.npz"))
    entry.write_bytes(b"not a zip")
    _same(meshes.load_mesh(obj), first)


def test_cache_can_be_bypassed(obj):
    meshes.load_mesh(obj, cache=False)
    assert not meshes.mesh_cache_dir().exists()
