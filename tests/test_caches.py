"""Caches that verify: the parsed-mesh cache (content key, checks on read,
rebuild, eviction by size) and the sample-scene cache (a content manifest;
a truncated OBJ or a missing texture is rebuilt, not trusted)."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from napari_imgreg.io import meshes


# ------------------------------------------------------------- mesh cache
def _make_obj(path: Path, n: int = 4, seed: int = 0) -> Path:
    """A textured grid mesh of n×n vertices (different seeds: different content)."""
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float))
    v = np.stack([xs.ravel(), ys.ravel(), rng.uniform(0, 0.1, n * n)], axis=1)
    f = []
    for r in range(n - 1):
        for c in range(n - 1):
            i = r * n + c
            f += [[i, i + 1, i + n + 1], [i, i + n + 1, i + n]]
    uv = v[:, :2] / (n - 1)
    tex = Image.fromarray(rng.integers(0, 255, (8, 8, 3), dtype=np.uint8))
    trimesh.Trimesh(v, np.array(f), visual=trimesh.visual.TextureVisuals(uv=uv, image=tex),
                    process=False).export(path)
    return path


@pytest.fixture
def cache_env(tmp_path, monkeypatch):
    monkeypatch.setenv("NAPARI_IMGREG_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("NAPARI_IMGREG_MESH_CACHE_MB", raising=False)
    monkeypatch.setattr(meshes, "_CACHE_MIN_BYTES", 0)
    return tmp_path


def _entries():
    return sorted(meshes.mesh_cache_dir().glob("*.npz"))


def _rewrite_entry(entry: Path, **changes) -> None:
    with np.load(entry, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays.update(changes)
    with open(entry, "wb") as fh:
        np.savez(fh, **arrays)


def test_touching_the_mesh_does_not_add_a_copy(cache_env):
    obj = _make_obj(cache_env / "m.obj")
    first = meshes.load_mesh(obj)
    for k in range(3):
        for p in cache_env.glob("m*"):
            os.utime(p, ns=(time.time_ns() + (k + 1) * 10**9,) * 2)
        np.testing.assert_array_equal(meshes.load_mesh(obj).vertices, first.vertices)
    assert len(_entries()) == 1


def test_changed_content_is_a_new_key(cache_env):
    obj = _make_obj(cache_env / "m.obj", seed=0)
    meshes.load_mesh(obj)
    _make_obj(obj, seed=1)
    meshes.load_mesh(obj)
    assert len(_entries()) == 2


@pytest.mark.parametrize("damage, why", [
    ("faces_out_of_range", "face indices"),
    ("negative_faces", "face indices"),
    ("nan_vertices", "NaN"),
    ("wrong_vertex_shape", "vertices have shape"),
    ("uv_short", "texture coordinates"),
    ("texture_2d", "texture of shape"),
    ("wrong_key", "key"),
    ("no_faces", "no faces"),
])
def test_a_well_formed_but_wrong_entry_is_rebuilt(cache_env, monkeypatch, caplog, damage, why):
    obj = _make_obj(cache_env / "m.obj")
    first = meshes.load_mesh(obj)
    (entry,) = _entries()
    with np.load(entry) as z:
        v, f = z["vertices"], z["faces"]
    change = {
        "faces_out_of_range": {"faces": f + len(v)},
        "negative_faces": {"faces": f - len(v)},
        "nan_vertices": {"vertices": np.where(np.arange(v.size).reshape(v.shape) == 4, np.nan, v)},
        "wrong_vertex_shape": {"vertices": v[:, :2].copy()},
        "uv_short": {"uv": np.zeros((2, 2), np.float32)},
        "texture_2d": {"texture": np.zeros((4, 4), np.uint8)},
        "wrong_key": {"key": np.array("0" * 40)},
        "no_faces": {"faces": np.zeros((0, 3), np.int32)},
    }[damage]
    _rewrite_entry(entry, **change)
    parsed = []
    real_parse = meshes._parse
    monkeypatch.setattr(meshes, "_parse", lambda p: parsed.append(p) or real_parse(p))
    with caplog.at_level("WARNING", logger=meshes.__name__):
        again = meshes.load_mesh(obj)
    assert parsed == [obj]  # rebuilt from the file
    assert any(why in r.getMessage() and "rebuilding" in r.getMessage() for r in caplog.records)
    for name in ("vertices", "faces", "uv", "texture"):
        np.testing.assert_array_equal(getattr(again, name), getattr(first, name))
    # The rebuilt entry is sound: the next load is a hit again.
    monkeypatch.setattr(meshes, "_parse", lambda p: pytest.fail("parsed a third time"))
    np.testing.assert_array_equal(meshes.load_mesh(obj).faces, first.faces)


def test_cache_evicts_least_recently_used_beyond_its_limit(cache_env, monkeypatch):
    objs = [_make_obj(cache_env / f"m{k}.obj", n=30, seed=k) for k in range(4)]
    meshes.load_mesh(objs[0])
    one = _entries()[0].stat().st_size
    # Room for about two and a half entries.
    monkeypatch.setenv("NAPARI_IMGREG_MESH_CACHE_MB", str(2.5 * one / 2**20))
    meshes.load_mesh(objs[1])
    time.sleep(0.02)
    meshes.load_mesh(objs[0])  # a hit: m0 is now the most recently used
    time.sleep(0.02)
    meshes.load_mesh(objs[2])  # over the limit: m1, the least recent, goes
    keys = {p.stem for p in _entries()}
    assert keys == {meshes._cache_key(objs[0]), meshes._cache_key(objs[2])}
    total = sum(p.stat().st_size for p in _entries())
    assert total <= meshes.mesh_cache_limit_bytes()


def test_entry_larger_than_the_limit_and_limit_zero_are_not_cached(cache_env, monkeypatch):
    obj = _make_obj(cache_env / "m.obj", n=20)
    monkeypatch.setenv("NAPARI_IMGREG_MESH_CACHE_MB", "0.0001")
    meshes.load_mesh(obj)
    assert _entries() == []
    monkeypatch.setenv("NAPARI_IMGREG_MESH_CACHE_MB", "0")
    meshes.load_mesh(obj)
    assert not meshes.mesh_cache_dir().exists() or _entries() == []


def test_cache_limit_setting(monkeypatch):
    monkeypatch.delenv("NAPARI_IMGREG_MESH_CACHE_MB", raising=False)
    assert meshes.mesh_cache_limit_bytes() == meshes.MESH_CACHE_LIMIT_BYTES == 2 * 1024**3
    monkeypatch.setenv("NAPARI_IMGREG_MESH_CACHE_MB", "100")
    assert meshes.mesh_cache_limit_bytes() == 100 * 2**20
    for bad in ("lots", "nan", "-5"):
        monkeypatch.setenv("NAPARI_IMGREG_MESH_CACHE_MB", bad)
        assert meshes.mesh_cache_limit_bytes() == meshes.MESH_CACHE_LIMIT_BYTES


def test_check_mesh_arrays_known_answers():
    v = np.zeros((3, 3))
    f = np.array([[0, 1, 2]])
    assert meshes.check_mesh_arrays(v, f) is None
    assert "span 1..3" in meshes.check_mesh_arrays(v, f + 1)
    assert "NaN" in meshes.check_mesh_arrays(np.full((3, 3), np.inf), f)
    assert "integers" in meshes.check_mesh_arrays(v, f.astype(float))
    assert "vertex colours" in meshes.check_mesh_arrays(v, f, vertex_colors=np.zeros((2, 3), np.uint8))
    assert meshes.check_mesh_arrays(v, f, uv=np.zeros((3, 2), np.float32),
                                    texture=np.zeros((2, 2, 3), np.uint8)) is None


# ------------------------------------------------------------ sample cache
@pytest.fixture
def fake_sample(tmp_path, monkeypatch):
    """sample_scene with a generator that writes a tiny, complete scene quickly."""
    import napari_imgreg.sample as sample

    calls = []
    obj_text = "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"

    def generate(out_dir, size="small", seed=0, spec=None):
        out = Path(out_dir)
        calls.append(out)
        (out / "m.obj").write_text(obj_text)
        (out / "m.mtl").write_text("newmtl a\nmap_Kd tex.png\n")
        Image.new("RGB", (4, 4), (200, 100, 50)).save(out / "tex.png")
        (out / "scene.json").write_text(json.dumps({
            "files": {"mesh": "m.obj", "material": "m.mtl", "texture": "tex.png"},
            "photos": [], "n_vertices": 3, "n_triangles": 1}))
        return out

    monkeypatch.setenv("NAPARI_IMGREG_CACHE", str(tmp_path))
    monkeypatch.setattr(sample, "generate_outcrop", generate)
    return sample, calls, obj_text


def test_sound_sample_cache_is_used(fake_sample):
    sample, calls, _ = fake_sample
    first = sample.sample_scene("small")
    assert sample.sample_scene("small") == first and len(calls) == 1
    assert (first / sample.CACHE_MANIFEST).is_file()


@pytest.mark.parametrize("damage", ["truncate_obj", "delete_texture", "change_texture",
                                    "delete_manifest_entry", "garble_manifest", "garble_scene"])
def test_damaged_sample_cache_is_rebuilt(fake_sample, caplog, damage):
    sample, calls, obj_text = fake_sample
    folder = sample.sample_scene("small")
    if damage == "truncate_obj":
        (folder / "m.obj").write_text(obj_text[:-12])
    elif damage == "delete_texture":
        (folder / "tex.png").unlink()
    elif damage == "change_texture":  # same size, other bytes
        data = bytearray((folder / "tex.png").read_bytes())
        data[-20] ^= 0xFF
        (folder / "tex.png").write_bytes(bytes(data))
    elif damage == "delete_manifest_entry":
        (folder / "m.mtl").unlink()
    elif damage == "garble_manifest":
        (folder / sample.CACHE_MANIFEST).write_text("{")
    elif damage == "garble_scene":
        (folder / "scene.json").write_text("")
    assert sample.verify_sample_scene(folder) is not None
    with caplog.at_level("WARNING"):
        again = sample.sample_scene("small")
    assert again == folder and len(calls) == 2
    assert any("generating it again" in r.getMessage() for r in caplog.records)
    assert (folder / "m.obj").read_text() == obj_text and (folder / "tex.png").is_file()
    assert sample.verify_sample_scene(folder) is None
    # Nothing left beside the entry (no stale or temporary folders).
    assert [p.name for p in folder.parent.iterdir()] == [folder.name]


def test_legacy_sample_cache_is_checked_by_structure(fake_sample):
    sample, calls, obj_text = fake_sample
    folder = sample.sample_scene("small")
    (folder / sample.CACHE_MANIFEST).unlink()  # as cached by an older version
    assert sample.sample_scene("small") == folder and len(calls) == 1  # whole: adopted
    assert (folder / sample.CACHE_MANIFEST).is_file()
    (folder / sample.CACHE_MANIFEST).unlink()
    (folder / "m.obj").write_text(obj_text.rsplit("f ", 1)[0])  # lost its last triangle
    assert "truncated" in sample.verify_sample_scene(folder)
    sample.sample_scene("small")
    assert len(calls) == 2


def test_real_sample_scene_verifies():
    from napari_imgreg.sample import sample_scene, verify_sample_scene

    assert verify_sample_scene(sample_scene("small")) is None
