"""Known-answer tests for :mod:`napari_imgreg.io.meshes` and ``Scene.load``."""

from __future__ import annotations

import json
import logging
import struct

import numpy as np
import pytest
import trimesh
from PIL import Image

from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.errors import InputError
from napari_imgreg.io.meshes import load_mesh
from napari_imgreg.render import render
from napari_imgreg.scene import Scene

# A small pyramid-on-a-square with a UV seam: vertex 0 (the apex) carries two
# different texture coordinates, so loaders must split it.
POS = np.array(
    [[0.5, 0.5, 1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]]
)
TEX_UV = np.array([[0.5, 1.0], [0.1, 0.2], [0.9, 0.2], [0.9, 0.8], [0.1, 0.8], [0.25, 0.75]])
# faces as (position index, uv index) per corner
FACES_P = np.array([[1, 2, 0], [2, 3, 0], [3, 4, 0], [4, 1, 0], [1, 3, 2], [1, 4, 3]])
FACES_T = np.array([[1, 2, 0], [2, 3, 0], [3, 4, 5], [4, 1, 5], [1, 3, 2], [1, 4, 3]])


def make_texture(h=12, w=20, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def corner_positions(data):
    return np.asarray(data.vertices)[np.asarray(data.faces)]


def corner_uvs(data):
    return np.asarray(data.uv)[np.asarray(data.faces)]


def write_obj(folder, texture=True, image_name="rock.png", kd="0.5 0.5 0.5", faces_t=FACES_T):
    obj = folder / "outcrop.obj"
    lines = ["mtllib outcrop.mtl", "o outcrop"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in POS]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in TEX_UV]
    lines += ["usemtl rock"]
    lines += [
        "f " + " ".join(f"{p + 1}/{t + 1}" for p, t in zip(fp, ft))
        for fp, ft in zip(FACES_P, faces_t)
    ]
    obj.write_text("\n".join(lines) + "\n")
    mtl = ["newmtl rock", f"Kd {kd}", "Ka 0 0 0"]
    if texture:
        mtl.append(f"map_Kd {image_name}")
    (folder / "outcrop.mtl").write_text("\n".join(mtl) + "\n")
    return obj


# ---------------------------------------------------------------------------
# round trips
# ---------------------------------------------------------------------------


def test_obj_mtl_png_round_trip(tmp_path):
    tex = make_texture()
    Image.fromarray(tex).save(tmp_path / "rock.png")
    obj = write_obj(tmp_path, faces_t=FACES_P)  # one UV per position: no seam
    data = load_mesh(obj)
    assert data.warnings == []
    assert data.vertices.dtype == np.float64 and data.faces.dtype == np.int32
    assert data.faces.shape == (6, 3)
    np.testing.assert_allclose(corner_positions(data), POS[FACES_P], atol=1e-6)
    np.testing.assert_allclose(corner_uvs(data), TEX_UV[FACES_P], atol=1e-6)
    assert data.uv.shape == (len(data.vertices), 2)
    np.testing.assert_array_equal(data.texture, tex)
    assert data.texture.dtype == np.uint8 and data.texture.flags.c_contiguous
    assert data.vertex_colors is None
    scene = Scene.load(obj)
    assert scene.name == "outcrop" and scene.has_texture and scene.warnings == []
    np.testing.assert_array_equal(scene.texture, tex)
    np.testing.assert_allclose(scene.vertices[scene.faces], POS[FACES_P], atol=1e-6)


def test_obj_uv_seam_keeps_per_corner_uvs(tmp_path):
    # Photogrammetry OBJs (Metashape, RealityCapture) have texture atlases:
    # every vertex on a chart border has different `vt`s in different faces.
    Image.fromarray(make_texture()).save(tmp_path / "rock.png")
    obj = write_obj(tmp_path)  # the apex has vt 1 in two faces, vt 6 in two others
    data = load_mesh(obj)
    np.testing.assert_allclose(corner_positions(data), POS[FACES_P], atol=1e-6)
    np.testing.assert_allclose(corner_uvs(data), TEX_UV[FACES_T], atol=1e-6)


def test_obj_exported_by_trimesh_round_trip(tmp_path):
    tex = make_texture(8, 16, seed=3)
    V = np.array([[0, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0], [1, 0.5, 1.5]], float)
    F = np.array([[0, 1, 2], [0, 2, 3], [0, 1, 4]])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0.5, 0.5]])
    mesh = trimesh.Trimesh(
        V, F, visual=trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(tex)), process=False
    )
    mesh.export(tmp_path / "m.obj")
    data = load_mesh(tmp_path / "m.obj")
    np.testing.assert_allclose(corner_positions(data), V[F], atol=1e-6)
    np.testing.assert_allclose(corner_uvs(data), uv[F], atol=1e-6)
    np.testing.assert_array_equal(data.texture, tex)


def write_ascii_ply(path, V, F, colours):
    header = [
        "ply", "format ascii 1.0", f"element vertex {len(V)}",
        "property float x", "property float y", "property float z",
        "property uchar red", "property uchar green", "property uchar blue",
        f"element face {len(F)}", "property list uchar int vertex_indices", "end_header",
    ]
    body = [f"{x} {y} {z} {r} {g} {b}" for (x, y, z), (r, g, b) in zip(V, colours)]
    body += [f"3 {a} {b} {c}" for a, b, c in F]
    path.write_text("\n".join(header + body) + "\n")


@pytest.mark.parametrize("encoding", ["ascii-by-hand", "binary-trimesh"])
def test_ply_vertex_colours_round_trip(tmp_path, encoding):
    rng = np.random.default_rng(5)
    V = np.array([[0.25, -1.5, 3.0], [10.0, 0.0, 2.0], [4.0, 7.5, -1.0], [-3.0, 2.0, 0.5]])
    F = np.array([[0, 1, 2], [0, 2, 3], [1, 3, 2]])
    colours = rng.integers(0, 256, (4, 3), dtype=np.uint8)
    path = tmp_path / "cloud.ply"
    if encoding == "ascii-by-hand":
        write_ascii_ply(path, V, F, colours)
    else:
        trimesh.Trimesh(V, F, vertex_colors=colours, process=False).export(path)
    data = load_mesh(path)
    np.testing.assert_allclose(data.vertices, V, atol=1e-6)
    np.testing.assert_array_equal(data.faces, F)
    np.testing.assert_array_equal(data.vertex_colors, colours)
    assert data.uv is None and data.texture is None
    scene = Scene.load(path)
    assert not scene.has_texture
    np.testing.assert_array_equal(scene.vertex_colors, colours)


def test_glb_texture_round_trip(tmp_path):
    tex = make_texture(16, 24, seed=9)
    V = np.array([[0, 0, 0], [3, 0, 0], [3, 0, 2], [0, 0, 2]], float)
    F = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0.1, 0.15], [0.85, 0.15], [0.85, 0.95], [0.1, 0.95]])
    mesh = trimesh.Trimesh(
        V, F, visual=trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(tex)), process=False
    )
    path = tmp_path / "wall.glb"
    mesh.export(path)
    data = load_mesh(path)
    np.testing.assert_allclose(corner_positions(data), V[F], atol=1e-6)
    # UVs come back in the OpenGL convention (v = 0 at the image bottom)
    np.testing.assert_allclose(corner_uvs(data), uv[F], atol=1e-6)
    np.testing.assert_array_equal(data.texture, tex)


def test_glb_node_transform_is_applied(tmp_path):
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    mesh = trimesh.Trimesh(V, [[0, 1, 2]], vertex_colors=[[10, 20, 30]] * 3, process=False)
    scene = trimesh.Scene()
    T = trimesh.transformations.translation_matrix([100.0, -50.0, 7.0])
    scene.add_geometry(mesh, transform=T)
    path = tmp_path / "moved.glb"
    scene.export(path)
    data = load_mesh(path)
    np.testing.assert_allclose(corner_positions(data)[0], V + [100.0, -50.0, 7.0], atol=1e-5)


@pytest.mark.parametrize("fmt", ["obj", "glb"])
def test_loaded_texture_renders_right_way_up(tmp_path, fmt):
    """End to end: texture top half red, bottom half blue, on a vertical wall
    with v = 1 at its top: the rendered top is red."""
    tex = np.zeros((32, 32, 3), np.uint8)
    tex[:16] = [250, 10, 10]
    tex[16:] = [10, 10, 250]
    V = np.array([[-10, 20, -10], [10, 20, -10], [10, 20, 10], [-10, 20, 10]], float)
    F = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    mesh = trimesh.Trimesh(
        V, F, visual=trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(tex)), process=False
    )
    path = tmp_path / f"wall.{fmt}"
    mesh.export(path)
    scene = Scene.load(path)
    intr = Intrinsics(80, 60, 120.0, 120.0, 39.5, 29.5)
    res = render(scene, intr, Pose.from_attitude(0.0, 0.0, 0.0, [0.0, 0.0, 0.0]))
    assert res.mask.all()
    np.testing.assert_array_equal(res.rgb[5, 40], [250, 10, 10])
    np.testing.assert_array_equal(res.rgb[55, 40], [10, 10, 250])


# ---------------------------------------------------------------------------
# missing texture
# ---------------------------------------------------------------------------


def test_obj_with_missing_texture_image(tmp_path, caplog):
    obj = write_obj(tmp_path, image_name="gone.png")
    with caplog.at_level(logging.WARNING):
        data = load_mesh(obj)
    assert data.texture is None and data.uv is None
    assert data.warnings and any("texture" in w for w in data.warnings)
    assert any("texture" in r.getMessage() and "outcrop.obj" in r.getMessage() for r in caplog.records)
    np.testing.assert_allclose(corner_positions(data), POS[FACES_P], atol=1e-6)
    # falls back to a flat (material) colour or none: grey either way
    if data.vertex_colors is not None:
        assert data.vertex_colors.shape == (len(data.vertices), 3)
        assert (data.vertex_colors == data.vertex_colors[0]).all()
        assert len(set(data.vertex_colors[0].tolist())) == 1  # Kd 0.5 0.5 0.5 -> grey
    scene = Scene.load(obj)
    assert not scene.has_texture
    assert scene.warnings == data.warnings
    res = render(scene, Intrinsics(40, 30, 30.0, 30.0, 19.5, 14.5),
                 Pose.from_attitude(0.0, 89.0, 0.0, [0.5, 0.5, 5.0]))
    assert res.mask.any()
    hit = res.rgb[res.mask].astype(int)
    assert (hit[:, 0] == hit[:, 1]).all() and (hit[:, 1] == hit[:, 2]).all()  # grey


def test_obj_without_colours_warns(tmp_path):
    path = tmp_path / "plain.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    data = load_mesh(path)
    np.testing.assert_allclose(data.vertices, [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    np.testing.assert_array_equal(data.faces, [[0, 1, 2]])
    assert data.texture is None and data.vertex_colors is None
    assert data.warnings


# ---------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------


def _assert_input_error(path, loader=load_mesh):
    with pytest.raises(InputError) as info:
        loader(path)
    msg = str(info.value)
    assert path.name in msg
    assert "\n" not in msg and "\r" not in msg
    assert isinstance(info.value, ValueError)
    return msg


def test_missing_file(tmp_path):
    msg = _assert_input_error(tmp_path / "nowhere.obj")
    assert "no such file" in msg
    _assert_input_error(tmp_path / "nowhere.ply", loader=Scene.load)


def test_folder_is_not_a_mesh(tmp_path):
    folder = tmp_path / "model.obj"
    folder.mkdir()
    _assert_input_error(folder)


def test_unknown_extension(tmp_path):
    path = tmp_path / "mesh.xyz"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")  # valid OBJ text, wrong name
    _assert_input_error(path)
    _assert_input_error(path, loader=Scene.load)


def _good_bytes(fmt):
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    F = np.array([[0, 1, 2], [0, 2, 3]])
    mesh = trimesh.Trimesh(V, F, vertex_colors=np.full((4, 3), 200, np.uint8), process=False)
    out = mesh.export(file_type=fmt)
    return out.encode() if isinstance(out, str) else out


@pytest.mark.parametrize(
    "name, make",
    [
        ("random.ply", lambda: np.random.default_rng(0).bytes(500)),
        ("random.obj", lambda: np.random.default_rng(1).bytes(500)),
        ("random.glb", lambda: np.random.default_rng(2).bytes(500)),
        ("truncated.ply", lambda: _good_bytes("ply")[:-20]),
        ("half.ply", lambda: _good_bytes("ply")[: len(_good_bytes("ply")) // 2]),
        ("flipped.ply", lambda: _good_bytes("ply")[:60] + bytes(b ^ 0xFF for b in _good_bytes("ply")[60:])),
        ("half.glb", lambda: _good_bytes("glb")[: len(_good_bytes("glb")) // 2]),
        ("badjson.glb", lambda: _good_bytes("glb")[:20] + bytes(b ^ 0x5A for b in _good_bytes("glb")[20:])),
        ("badindex.obj", lambda: b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n"),
        ("nan.obj", lambda: b"v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n"),
        ("badindex.ply", lambda: (
            b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            b"property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
            b"end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 9\n")),
        ("empty.obj", lambda: b""),
        ("comments.obj", lambda: b"# only a comment\n"),
        ("points.obj", lambda: b"v 0 0 0\nv 1 0 0\nv 0 1 0\n"),
        ("empty.ply", lambda: b""),
        ("empty.glb", lambda: b""),
    ],
)
def test_corrupt_or_empty_files(tmp_path, name, make):
    path = tmp_path / name
    path.write_bytes(make())
    _assert_input_error(path)


def _glb_with_out_of_range_index(colours: bool) -> bytes:
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    F = np.array([[0, 1, 2], [0, 2, 3]])
    kw = {"vertex_colors": np.full((4, 3), 200, np.uint8)} if colours else {}
    glb = bytearray(trimesh.Trimesh(V, F, process=False, **kw).export(file_type="glb"))
    json_len = struct.unpack_from("<I", glb, 12)[0]
    gltf = json.loads(glb[20 : 20 + json_len])
    acc = gltf["accessors"][gltf["meshes"][0]["primitives"][0]["indices"]]
    assert acc["componentType"] == 5125  # uint32
    view = gltf["bufferViews"][acc["bufferView"]]
    start = 20 + json_len + 8 + view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    struct.pack_into("<I", glb, start + 4 * 4, 1000)  # 5th index -> vertex 1000 of 4
    return bytes(glb)


def test_glb_index_out_of_range(tmp_path):
    path = tmp_path / "badindex.glb"
    path.write_bytes(_glb_with_out_of_range_index(colours=False))
    _assert_input_error(path)


def test_glb_with_vertex_colours_index_out_of_range(tmp_path):
    path = tmp_path / "badindex_coloured.glb"
    path.write_bytes(_glb_with_out_of_range_index(colours=True))
    _assert_input_error(path)
