"""Issue 15, the inputs: every bad input of the command line gets exit code 2
and one line on stderr naming the file (or option) and the field, before any
long work; nothing hangs, nothing allocates without bound."""

from __future__ import annotations

import json
import os
import struct
import time
import zlib

import numpy as np
import pytest
import trimesh
from PIL import Image

from napari_imgreg.cli import main

AS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0


@pytest.fixture
def wall(tmp_path):
    """A textured 40 m × 20 m wall in the plane y = 0 and a record facing it."""
    vertices = np.array([[0, 0, 0], [40, 0, 0], [40, 0, 20], [0, 0, 20]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    texture = np.zeros((64, 128, 3), np.uint8)
    texture[..., 0] = np.linspace(0, 255, 128)[None, :]
    texture[..., 1] = 120
    mesh = trimesh.Trimesh(
        vertices, faces, process=False,
        visual=trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(texture)),
    )
    mesh_path = tmp_path / "wall.obj"
    mesh.export(mesh_path)
    return mesh_path


def _record(**camera) -> dict:
    cam = {"width": 160, "height": 120, "fx": 100.0, "fy": 100.0, "cx": 79.5, "cy": 59.5}
    cam.update(camera)
    return {
        "camera": {k: v for k, v in cam.items() if v is not None},
        "position": {"x": 20.0, "y": -30.0, "z": 10.0},
        "orientation": {"trend_deg": 0.0, "plunge_deg": 0.0, "roll_deg": 0.0},
    }


def _write_record(tmp_path, data, name="IMG_0001.json"):
    path = tmp_path / name
    # allow_nan: the file a careless tool writes (NaN is not JSON, Python reads it).
    path.write_text(json.dumps(data, allow_nan=True))
    return path


def _run(capsys, argv) -> tuple[int, str]:
    t0 = time.perf_counter()
    code = main([str(a) for a in argv])
    elapsed = time.perf_counter() - t0
    err = capsys.readouterr().err
    assert elapsed < 30, f"took {elapsed:.0f} s"  # refused at the boundary, not after work
    return code, err


def _one_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


# ------------------------------------------------------------------ records
@pytest.mark.parametrize("camera, needle", [
    ({"width": 0}, "field 'camera.width' must be within [1, 65535], got 0"),
    ({"width": -1024}, "field 'camera.width' must be within [1, 65535], got -1024"),
    ({"width": 1e12}, "field 'camera.width' must be within [1, 65535]"),
    ({"height": None}, "field 'camera.height' is missing"),
    ({"fx": -100.0}, "field 'camera.fx' must be positive, got -100.0"),
    ({"fx": 0}, "field 'camera.fx' must be positive, got 0"),
    ({"fy": float("nan")}, "field 'camera.fy'"),
    ({"dist": [float("nan"), 0, 0, 0, 0]}, "field 'camera.dist' must be finite numbers"),
    ({"dist": [0.1, 0, 0, 0, 0, 0, 0, 0]}, "field 'camera.dist' has 8 coefficients"),
    ({"width": 2**63}, "field 'camera.width' must be within [1, 65535], got 9223372036854775808"),
])
@pytest.mark.parametrize("command", ["render", "register"])
def test_bad_camera_block_is_one_line_exit_2(wall, tmp_path, capsys, camera, needle, command):
    record = _write_record(tmp_path, _record(**camera))
    if command == "render":
        argv = ["render", wall, record, "--out", tmp_path / "r.png"]
    else:
        photo = tmp_path / "IMG_0001.png"
        Image.fromarray(np.full((120, 160, 3), 90, np.uint8)).save(photo)
        argv = ["register", wall, photo, "--prior", record, "--out", tmp_path / "R.json"]
    code, err = _run(capsys, argv)
    line = _one_line(err)
    assert code == 2
    assert str(record) in line and needle in line, line


def test_fx_zero_does_not_hang_the_ray_caster(wall, tmp_path, capsys):
    # Before issue 15: > 300 s in Embree with infinite ray directions.
    record = _write_record(tmp_path, _record(fx=0, fy=0))
    code, err = _run(capsys, ["render", wall, record, "--out", tmp_path / "r.png"])
    assert code == 2 and "field 'camera.fx'" in _one_line(err)


@pytest.mark.parametrize("block, field, value, needle", [
    ("orientation", "trend_deg", 2**63, "field 'orientation.trend_deg' must be within"),
    ("orientation", "plunge_deg", 91.0, "field 'orientation.plunge_deg' must be within [-90, 90]"),
    ("position", "x", 10**400, "field 'position.x' must be within"),
    ("position", "z", float("inf"), "field 'position.z' must be a finite number"),
    ("sigma", "angles_deg", -1.0, "field 'sigma.angles_deg' must be within [0, 180]"),
])
def test_record_numbers_out_of_range(wall, tmp_path, capsys, block, field, value, needle):
    data = _record()
    data.setdefault(block, {})[field] = value
    record = _write_record(tmp_path, data)
    code, err = _run(capsys, ["render", wall, record, "--out", tmp_path / "r.png"])
    line = _one_line(err)
    assert code == 2 and str(record) in line and needle in line, line


@pytest.mark.parametrize("position, needle", [
    ({"lat": 95.0, "lon": 7.0}, "field 'position.lat' must be within [-90, 90], got 95.0"),
    ({"lat": 46.0, "lon": float("nan")}, "field 'position.lon' must be a finite number"),
])
def test_lat_lon_errors_name_the_record(wall, tmp_path, capsys, position, needle):
    (tmp_path / "georef.json").write_text(json.dumps(
        {"crs": "EPSG:32632", "origin": [500000.0, 5100000.0, 0.0]}))
    data = _record()
    data["position"] = {**position, "alt": 100.0}
    record = _write_record(tmp_path, data)
    code, err = _run(capsys, ["render", wall, record, "--out", tmp_path / "r.png",
                              "--georef", tmp_path / "georef.json"])
    line = _one_line(err)
    assert code == 2 and str(record) in line and needle in line, line


def test_result_json_with_nan_translation_or_fx_0(wall, tmp_path, capsys):
    R = np.eye(3)[[0, 2, 1]] * [1, -1, 1]
    for name, camera, t in [("nan_t", {"fx": 50.0}, [float("nan"), 0.0, 30.0]),
                            ("fx0", {"fx": 0.0}, [0.0, 0.0, 30.0])]:
        cam = {"width": 80, "height": 60, "fy": 50.0, "cx": 39.5, "cy": 29.5, **camera}
        result = tmp_path / f"{name}.result.json"
        result.write_text(json.dumps({"camera": cam, "pose": {"R": R.tolist(), "t": t}},
                                     allow_nan=True))
        code, err = _run(capsys, ["render", wall, result, "--out", tmp_path / "r.png"])
        line = _one_line(err)
        assert code == 2 and str(result) in line
        assert ("field 'pose.t'" if name == "nan_t" else "field 'camera.fx'") in line, line


# ------------------------------------------------------------------- photos
def _png_header_only(path, width, height):
    """A PNG whose header claims ``width`` × ``height`` (a decompression bomb)."""
    def chunk(kind, data):
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr)
                     + chunk(b"IDAT", zlib.compress(b"\x00" * 64)) + chunk(b"IEND", b""))


def test_decompression_bomb_is_refused_before_decoding(wall, tmp_path, capsys):
    photo = tmp_path / "IMG_0001.png"
    _png_header_only(photo, 60000, 60000)
    record = _write_record(tmp_path, _record())
    code, err = _run(capsys, ["register", wall, photo, "--prior", record,
                              "--out", tmp_path / "R.json"])
    line = _one_line(err)
    assert code == 2 and str(photo) in line and "3,600 MP" in line and "limit is 160 MP" in line


def test_photo_over_our_limit_but_under_pillows(tmp_path):
    """Between 160 MP and Pillow's own 179 MP our check answers, from the header."""
    from napari_imgreg.errors import InputError
    from napari_imgreg.io.photos import load_photo

    photo = tmp_path / "big.png"
    _png_header_only(photo, 13000, 13000)  # 169 MP
    with pytest.raises(InputError, match=r"big.png: image is 13000×13000 px \(169 MP\); "
                                         r"the limit is 160 MP"):
        load_photo(photo)


# --------------------------------------------------------------- parameters
@pytest.mark.parametrize("params, needle", [
    ({"max_trials": 0}, "field 'max_trials' must be within [1, 50], got 0"),
    ({"max_iterations": 0}, "field 'max_iterations' must be within [1, 50], got 0"),
    ({"match_width": 0}, "field 'match_width' must be within [64, 16384], got 0"),
    ({"features": {"ratio": float("nan")}}, "field 'features.ratio' must be within"),
    ({"pose": {"iterations": 0}}, "field 'pose.iterations' must be within"),
])
def test_params_out_of_range(wall, tmp_path, capsys, params, needle):
    record = _write_record(tmp_path, _record())
    photo = tmp_path / "IMG_0001.png"
    Image.fromarray(np.full((120, 160, 3), 90, np.uint8)).save(photo)
    params_path = tmp_path / "params.json"
    params_path.write_text(json.dumps(params, allow_nan=True))
    code, err = _run(capsys, ["register", wall, photo, "--prior", record,
                              "--params", params_path, "--out", tmp_path / "R.json"])
    line = _one_line(err)
    assert code == 2 and str(params_path) in line and needle in line, line


# ------------------------------------------------------------------ options
@pytest.mark.parametrize("scale, needle", [
    ("nan", "--scale must be a finite number, got nan"),
    ("100", "--scale must be within (0, 8], got 100.0"),
    ("0", "--scale must be within (0, 8], got 0.0"),
])
def test_render_scale(wall, tmp_path, capsys, scale, needle):
    record = _write_record(tmp_path, _record())
    code, err = _run(capsys, ["render", wall, record, "--out", tmp_path / "r.png",
                              "--scale", scale])
    assert code == 2 and needle in _one_line(err)


def test_render_size_is_bounded_in_the_library(wall):
    """``--scale 8`` of a big camera, or a script's render(scale=100): refused
    before the arrays are allocated."""
    from napari_imgreg import Intrinsics, Pose
    from napari_imgreg.errors import InputError
    from napari_imgreg.render import render
    from napari_imgreg.scene import Scene

    scene = Scene.load(wall)
    intr = Intrinsics(4000, 3000, 3000.0, 3000.0, 1999.5, 1499.5)
    pose = Pose.from_attitude(0.0, 0.0, 0.0, [20.0, -30.0, 10.0])
    with pytest.raises(InputError, match=r"render of 400000×300000 px .* exceeds the limit of "
                                         r"64 MP; reduce the scale"):
        render(scene, intr, pose, scale=100)
    with pytest.raises(InputError, match="render scale must be a finite number"):
        render(scene, intr, pose, scale=float("nan"))


@pytest.mark.parametrize("value, needle", [
    ("nan", "--declination must be a finite number, got nan"),
    ("400", "--declination must be within [-180, 180], got 400.0"),
])
def test_orient_declination(tmp_path, capsys, value, needle):
    table = tmp_path / "cams.csv"
    table.write_text("photo,trend_deg,plunge_deg,roll_deg\na,10,5,0\nb,100,3,1\nc,200,8,-1\n")
    code, err = _run(capsys, ["orient", table, table, "--out", tmp_path / "o.json",
                              "--declination", value])
    assert code == 2 and needle in _one_line(err)


# ------------------------------------------------------------- output paths
def _bad_outputs(tmp_path):
    """name -> (file output, folder output) that cannot be written."""
    a_file = tmp_path / "a_file.txt"
    a_file.write_text("x")
    a_folder = tmp_path / "a_folder.png"
    a_folder.mkdir()
    cases = {
        "inside a file": (a_file / "out.png", a_file / "out"),
        "a folder": (a_folder, None),
        "a file as folder": (None, a_file),
        "under /proc": ("/proc/napari-imgreg-out.png", "/proc/napari-imgreg-out"),
    }
    if not AS_ROOT:  # root writes into read-only folders: nothing to refuse
        ro = tmp_path / "read_only"
        ro.mkdir()
        ro.chmod(0o555)
        cases["read-only"] = (ro / "out.png", ro / "out")
    return cases


@pytest.mark.parametrize("case", ["inside a file", "a folder", "under /proc", "read-only"])
@pytest.mark.parametrize("command", ["render", "register", "orient"])
def test_unwritable_file_output(wall, tmp_path, capsys, case, command):
    cases = _bad_outputs(tmp_path)
    if case not in cases:
        pytest.skip("running as root: a read-only folder is writable")
    out = cases[case][0]
    record = _write_record(tmp_path, _record())
    if command == "render":
        argv = ["render", wall, record, "--out", out]
    elif command == "register":
        photo = tmp_path / "IMG_0001.png"
        Image.fromarray(np.full((120, 160, 3), 90, np.uint8)).save(photo)
        out = str(out).replace(".png", ".json")
        if case == "a folder":
            os.makedirs(out, exist_ok=True)
        argv = ["register", wall, photo, "--prior", record, "--out", out]
    else:
        table = tmp_path / "cams.csv"
        table.write_text("photo,trend_deg,plunge_deg,roll_deg\na,10,5,0\nb,100,3,1\n")
        out = str(out).replace(".png", ".json")
        if case == "a folder":
            os.makedirs(out, exist_ok=True)
        argv = ["orient", table, table, "--out", out]
    code, err = _run(capsys, argv)
    line = _one_line(err)
    assert code == 2 and str(out) in line and "cannot write here" in line, line


@pytest.mark.parametrize("case", ["inside a file", "a file as folder", "under /proc",
                                  "read-only"])
@pytest.mark.parametrize("command", ["sample", "demo"])
def test_unwritable_folder_output(tmp_path, capsys, case, command):
    cases = _bad_outputs(tmp_path)
    if case not in cases:
        pytest.skip("running as root: a read-only folder is writable")
    out = cases[case][1]
    code, err = _run(capsys, [command, "--out", out])
    line = _one_line(err)
    assert code == 2 and str(out) in line and "cannot write here" in line, line


def test_register_checks_its_output_before_registering(wall, tmp_path, capsys):
    """The output is checked first: even the scene is not loaded (a missing
    mesh would be reported otherwise)."""
    photo = tmp_path / "IMG_0001.png"
    Image.fromarray(np.full((120, 160, 3), 90, np.uint8)).save(photo)
    code, err = _run(capsys, ["register", tmp_path / "missing.obj", photo,
                              "--out", "/proc/x/RESULT.json"])
    assert code == 2 and "cannot write here" in _one_line(err)


def test_sample_seed_range(tmp_path, capsys):
    code, err = _run(capsys, ["sample", "--out", tmp_path / "s", "--seed", "-1"])
    assert code == 2 and "--seed must be within [0, 4294967295], got -1" in _one_line(err)


def test_register_missing_prior_is_not_replaced_by_exif(wall, tmp_path, capsys):
    photo = tmp_path / "IMG_0001.png"
    Image.fromarray(np.full((120, 160, 3), 90, np.uint8)).save(photo)
    code, err = _run(capsys, ["register", wall, photo, "--prior", tmp_path / "nope.json",
                              "--out", tmp_path / "R.json"])
    assert code == 2 and "nope.json: no such file" in _one_line(err)


@pytest.mark.parametrize("case", ["inside a file", "under /proc"])
@pytest.mark.parametrize("command", ["project", "measure"])
def test_unwritable_output_of_project_and_measure_is_found_first(tmp_path, capsys, case,
                                                                 command):
    """Checked before anything is read: the inputs here do not even exist."""
    out = str(_bad_outputs(tmp_path)[case][0])
    if command == "project":
        out = out.replace(".png", ".geojson")
        argv = ["project", tmp_path / "R.json", tmp_path / "m.obj", tmp_path / "l.geojson",
                "--out", out]
    else:
        out = out.replace(".png", ".csv")
        argv = ["measure", tmp_path / "l3d.geojson", "--out", out]
    code, err = _run(capsys, argv)
    line = _one_line(err)
    assert code == 2 and out in line and "cannot write here" in line, line
