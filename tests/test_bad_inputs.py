"""Issue 15, the inputs: every bad input of the command line gets exit code 2
and one line on stderr naming the file (or option) and the field, before any
long work; nothing hangs, nothing allocates without bound."""

from __future__ import annotations

import json
import math
import os
import struct
import sys
import zlib

import numpy as np
import pytest
from PIL import Image

AS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0


@pytest.fixture
def wall(wall_mesh):
    """The shared textured wall (conftest ``wall_mesh``); records face it."""
    return wall_mesh


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
def test_bad_camera_block_is_one_line_exit_2(wall, tmp_path, run_cli, camera, needle, command):
    record = _write_record(tmp_path, _record(**camera))
    if command == "render":
        argv = ["render", wall, record, "--out", tmp_path / "r.png"]
    else:
        photo = tmp_path / "IMG_0001.png"
        Image.fromarray(np.full((120, 160, 3), 90, np.uint8)).save(photo)
        argv = ["register", wall, photo, "--prior", record, "--out", tmp_path / "R.json"]
    run = run_cli(argv)
    line = run.line
    assert run.code == 2
    assert str(record) in line and needle in line, line


def test_fx_zero_does_not_hang_the_ray_caster(wall, tmp_path, run_cli):
    # Before issue 15: > 300 s in Embree with infinite ray directions.
    record = _write_record(tmp_path, _record(fx=0, fy=0))
    run = run_cli(["render", wall, record, "--out", tmp_path / "r.png"])
    assert run.code == 2 and "field 'camera.fx'" in run.line


@pytest.mark.parametrize("block, field, value, needle", [
    ("orientation", "trend_deg", 2**63, "field 'orientation.trend_deg' must be within"),
    ("orientation", "plunge_deg", 91.0, "field 'orientation.plunge_deg' must be within [-90, 90]"),
    ("position", "x", 10**400, "field 'position.x' must be within"),
    ("position", "z", float("inf"), "field 'position.z' must be a finite number"),
    ("sigma", "angles_deg", -1.0, "field 'sigma.angles_deg' must be within [0, 180]"),
])
def test_record_numbers_out_of_range(wall, tmp_path, run_cli, block, field, value, needle):
    data = _record()
    data.setdefault(block, {})[field] = value
    record = _write_record(tmp_path, data)
    run = run_cli(["render", wall, record, "--out", tmp_path / "r.png"])
    line = run.line
    assert run.code == 2 and str(record) in line and needle in line, line


@pytest.mark.parametrize("position, needle", [
    ({"lat": 95.0, "lon": 7.0}, "field 'position.lat' must be within [-90, 90], got 95.0"),
    ({"lat": 46.0, "lon": float("nan")}, "field 'position.lon' must be a finite number"),
])
def test_lat_lon_errors_name_the_record(wall, tmp_path, run_cli, position, needle):
    (tmp_path / "georef.json").write_text(json.dumps(
        {"crs": "EPSG:32632", "origin": [500000.0, 5100000.0, 0.0]}))
    data = _record()
    data["position"] = {**position, "alt": 100.0}
    record = _write_record(tmp_path, data)
    run = run_cli(["render", wall, record, "--out", tmp_path / "r.png",
                              "--georef", tmp_path / "georef.json"])
    line = run.line
    assert run.code == 2 and str(record) in line and needle in line, line


def test_result_json_with_nan_translation_or_fx_0(wall, tmp_path, run_cli):
    R = np.eye(3)[[0, 2, 1]] * [1, -1, 1]
    for name, camera, t in [("nan_t", {"fx": 50.0}, [float("nan"), 0.0, 30.0]),
                            ("fx0", {"fx": 0.0}, [0.0, 0.0, 30.0])]:
        cam = {"width": 80, "height": 60, "fy": 50.0, "cx": 39.5, "cy": 29.5, **camera}
        result = tmp_path / f"{name}.result.json"
        result.write_text(json.dumps({"camera": cam, "pose": {"R": R.tolist(), "t": t}},
                                     allow_nan=True))
        run = run_cli(["render", wall, result, "--out", tmp_path / "r.png"])
        line = run.line
        assert run.code == 2 and str(result) in line
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


def test_decompression_bomb_is_refused_before_decoding(wall, tmp_path, run_cli):
    photo = tmp_path / "IMG_0001.png"
    _png_header_only(photo, 60000, 60000)
    record = _write_record(tmp_path, _record())
    run = run_cli(["register", wall, photo, "--prior", record,
                              "--out", tmp_path / "R.json"])
    line = run.line
    assert run.code == 2 and str(photo) in line and "3,600 MP" in line and "limit is 160 MP" in line


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
def test_params_out_of_range(wall, tmp_path, run_cli, params, needle):
    record = _write_record(tmp_path, _record())
    photo = tmp_path / "IMG_0001.png"
    Image.fromarray(np.full((120, 160, 3), 90, np.uint8)).save(photo)
    params_path = tmp_path / "params.json"
    params_path.write_text(json.dumps(params, allow_nan=True))
    run = run_cli(["register", wall, photo, "--prior", record,
                              "--params", params_path, "--out", tmp_path / "R.json"])
    line = run.line
    assert run.code == 2 and str(params_path) in line and needle in line, line


# ------------------------------------------------------------------ options
@pytest.mark.parametrize("scale, needle", [
    ("nan", "--scale must be a finite number, got nan"),
    ("100", "--scale must be within (0, 8], got 100.0"),
    ("0", "--scale must be within (0, 8], got 0.0"),
])
def test_render_scale(wall, tmp_path, run_cli, scale, needle):
    record = _write_record(tmp_path, _record())
    run = run_cli(["render", wall, record, "--out", tmp_path / "r.png",
                              "--scale", scale])
    assert run.code == 2 and needle in run.line


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
def test_orient_declination(tmp_path, run_cli, value, needle):
    table = tmp_path / "cams.csv"
    table.write_text("photo,trend_deg,plunge_deg,roll_deg\na,10,5,0\nb,100,3,1\nc,200,8,-1\n")
    run = run_cli(["orient", table, table, "--out", tmp_path / "o.json",
                              "--declination", value])
    assert run.code == 2 and needle in run.line


def test_orient_about_cameras_without_centres_names_the_option(tmp_path, run_cli):
    table = tmp_path / "cams.csv"
    table.write_text("photo,trend_deg,plunge_deg,roll_deg\na,10,5,0\nb,100,3,1\nc,200,8,-1\n")
    phone = tmp_path / "phone.csv"
    phone.write_bytes(table.read_bytes())
    run = run_cli(["orient", table, phone, "--out", tmp_path / "o.json", "--about", "cameras"])
    line = run.line
    assert run.code == 2 and str(table) in line and "use --about origin" in line, line
    assert not (tmp_path / "o.json").exists()


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
def test_unwritable_file_output(wall, tmp_path, run_cli, case, command):
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
    run = run_cli(argv)
    line = run.line
    assert run.code == 2 and str(out) in line and "cannot write here" in line, line


@pytest.mark.parametrize("case", ["inside a file", "a file as folder", "under /proc",
                                  "read-only"])
@pytest.mark.parametrize("command", ["sample", "demo", "batch"])
def test_unwritable_folder_output(tmp_path, run_cli, case, command):
    cases = _bad_outputs(tmp_path)
    if case not in cases:
        pytest.skip("running as root: a read-only folder is writable")
    out = cases[case][1]
    # batch: checked before its scene folder is even looked at (here: none).
    scene = [tmp_path / "no_scene"] if command == "batch" else []
    run = run_cli([command, *scene, "--out", out])
    line = run.line
    assert run.code == 2 and str(out) in line, line
    assert "cannot write here" in line or "exists and is not a folder" in line, line


def test_register_checks_its_output_before_registering(wall, tmp_path, run_cli):
    """The output is checked first: even the scene is not loaded (a missing
    mesh would be reported otherwise)."""
    photo = tmp_path / "IMG_0001.png"
    Image.fromarray(np.full((120, 160, 3), 90, np.uint8)).save(photo)
    run = run_cli(["register", tmp_path / "missing.obj", photo,
                              "--out", "/proc/x/RESULT.json"])
    assert run.code == 2 and "cannot write here" in run.line


def test_sample_seed_range(tmp_path, run_cli):
    run = run_cli(["sample", "--out", tmp_path / "s", "--seed", "-1"])
    assert run.code == 2 and "--seed must be within [0, 4294967295], got -1" in run.line


@pytest.mark.parametrize("command", ["register", "batch"])
def test_record_of_another_aspect_ratio_is_one_line_quoting_its_size(wall, tmp_path, run_cli,
                                                                     command):
    """A 320×120 camera block for a 160×120 photo is not a resized photo: one
    line naming the record and quoting its own size (not 160×60, the block
    scaled to the photo's width), before the registration."""
    scene = tmp_path / "scene"
    scene.mkdir()
    photo = scene / "IMG_0001.png"
    Image.fromarray(np.full((120, 160, 3), 90, np.uint8)).save(photo)
    record = _write_record(scene, _record(width=320, height=120))
    if command == "register":
        argv = ["register", wall, photo, "--prior", record, "--out", tmp_path / "R.json"]
    else:
        argv = ["batch", scene, "--mesh", wall, "--out", tmp_path / "results", "--workers", 0]
    run = run_cli(argv)
    line = run.line
    assert run.code == 2 and str(record) in line, line
    assert "the camera is 320×120 px but the photo is 160×120 px" in line, line
    assert "160×60" not in line


def test_register_missing_prior_is_not_replaced_by_exif(wall, tmp_path, run_cli):
    photo = tmp_path / "IMG_0001.png"
    Image.fromarray(np.full((120, 160, 3), 90, np.uint8)).save(photo)
    run = run_cli(["register", wall, photo, "--prior", tmp_path / "nope.json",
                              "--out", tmp_path / "R.json"])
    assert run.code == 2 and "nope.json: no such file" in run.line


@pytest.mark.parametrize("case", ["inside a file", "a folder", "under /proc", "read-only"])
@pytest.mark.parametrize("command", ["project", "measure"])
def test_unwritable_output_of_project_and_measure_is_found_first(tmp_path, run_cli, case,
                                                                 command):
    """Checked before anything is read: the inputs here do not even exist."""
    cases = _bad_outputs(tmp_path)
    if case not in cases:
        pytest.skip("running as root: a read-only folder is writable")
    out = str(cases[case][0])
    if case == "a folder":
        out = str(tmp_path / ("a_folder.geojson" if command == "project" else "a_folder.csv"))
        os.makedirs(out)
    if command == "project":
        out = out.replace(".png", ".geojson")
        argv = ["project", tmp_path / "R.json", tmp_path / "m.obj", tmp_path / "l.geojson",
                "--out", out]
    else:
        out = out.replace(".png", ".csv")
        argv = ["measure", tmp_path / "l3d.geojson", "--out", out]
    run = run_cli(argv)
    line = run.line
    assert run.code == 2 and out in line and "cannot write here" in line, line


@pytest.mark.parametrize("case", ["inside a file", "under /proc", "read-only"])
@pytest.mark.parametrize("action", ["create", "add", "register", "lines", "project",
                                    "export --out", "export --measurements"])
def test_unwritable_workspace_output_is_found_first(tmp_path, run_cli, case, action):
    """``workspace``: what a sub-command writes (the workspace folder it saves
    into; export's ``--out`` and ``--measurements``) is checked before anything
    is read: the scene, photos, lines and workspace here do not even exist."""
    cases = _bad_outputs(tmp_path)
    if case not in cases:
        pytest.skip("running as root: a read-only folder is writable")
    command, _, flag = action.partition(" ")
    missing = tmp_path / "missing"
    if command == "export":
        outs = {"--out": str(tmp_path / "l3d.geojson"), "--measurements": str(tmp_path / "m.csv")}
        bad = outs[flag] = str(cases[case][0]).replace(
            ".png", ".geojson" if flag == "--out" else ".csv")
        argv = ["workspace", "export", missing / "campaign.imgreg",
                "--out", outs["--out"], "--measurements", outs["--measurements"]]
    else:
        # A new folder for create; for the others, a workspace folder that
        # cannot be saved into (read-only: the folder itself).
        bad = str(cases[case][1])
        if case == "read-only" and command != "create":
            bad = str(tmp_path / "read_only")
        rest = {"create": [missing / "scene"], "add": [missing / "IMG_0001.jpg"],
                "register": [], "lines": ["IMG_0001.jpg", missing / "l.geojson"],
                "project": []}[command]
        argv = ["workspace", command, bad, *rest]
    run = run_cli(argv)
    line = run.line
    assert run.code == 2 and bad in line and "cannot write here" in line, line
    assert len(run.err.strip().splitlines()) == 1, run.err


def test_workspace_photos_not_added_are_one_error_line(wall, tmp_path, run_cli):
    """A scene folder with a corrupt photo: the workspace is made with the
    others, each photo not added is listed, and stderr holds one error line."""
    import shutil

    scene = tmp_path / "scene"
    scene.mkdir()
    for f in wall.parent.iterdir():  # the mesh with its material and texture
        if f.is_file():
            shutil.copy(f, scene / f.name)
    (scene / "IMG_0001.jpg").write_bytes(b"not a jpeg")
    run = run_cli(["workspace", "create", tmp_path / "w.imgreg", scene])
    assert run.code == 2 and "IMG_0001.jpg" in run.line and "not added" in run.line, run.err
    assert run.line.startswith("napari-imgreg workspace create: error: ")
    assert len(run.err.strip().splitlines()) == 1, run.err
    assert "1 could not be read" in run.out


def test_workspace_create_names_the_folder_as_the_workbench_does(wall, tmp_path, run_cli):
    """``workspace create w5`` makes ``w5.imgreg`` (napari opens only ``*.imgreg``
    folders as workspaces), and later actions' errors name their action."""
    import shutil

    scene = tmp_path / "scene"
    scene.mkdir()
    for f in wall.parent.iterdir():
        if f.is_file():
            shutil.copy(f, scene / f.name)
    Image.fromarray(np.full((120, 160, 3), 90, np.uint8)).save(scene / "IMG_0001.png")
    run = run_cli(["workspace", "create", tmp_path / "w5", scene, "--no-photos"])
    assert run.code == 0, run.err
    assert (tmp_path / "w5.imgreg" / "workspace.json").is_file()
    assert not (tmp_path / "w5").exists() and f"{tmp_path / 'w5.imgreg'}:" in run.out
    run = run_cli(["workspace", "add", tmp_path / "w5.imgreg", tmp_path / "nope.jpg"])
    assert run.code == 2
    assert run.line.startswith("napari-imgreg workspace add: error: "), run.line


@pytest.mark.parametrize("measurements, needle", [
    ("m.txt", "m.txt: output must be a .csv file"),
    ("l3d.csv", "refusing to write --out and --measurements to one file"),
])
def test_workspace_export_measurements_must_be_another_csv(tmp_path, run_cli, measurements,
                                                          needle):
    """Refused as ``measure`` refuses it, before the workspace (here: none) is read."""
    run = run_cli(["workspace", "export", tmp_path / "campaign.imgreg", "--out",
                   tmp_path / "l3d.csv", "--measurements", tmp_path / measurements])
    line = run.line
    assert run.code == 2 and needle in line, line
    assert line.startswith("napari-imgreg workspace export: error: "), line


def test_unknown_option_shows_the_usage_of_its_command(capsys):
    from napari_imgreg.cli import main

    for argv, usage in ((["measure", "x.geojson", "--out", "m.csv", "--colour", "red"],
                         "usage: napari-imgreg measure "),
                        (["workspace", "add", "w.imgreg", "a.jpg", "--force"],
                         "usage: napari-imgreg workspace add ")):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        err = capsys.readouterr().err
        assert exc.value.code == 2 and err.startswith(usage), err
        unknown = argv[-2:] if argv[0] == "measure" else argv[-1:]
        assert f"error: unrecognized arguments: {' '.join(unknown)}" in err


# ------------------------------------------------- EXIF orientation, attitude
def _sensor_record(tmp_path, roll=2.0, **extra):
    from napari_imgreg.io.records import parse_sensor_record

    data = {"camera": {"width": 160, "height": 120, "fx": 110.0, "fy": 112.0, "cx": 80.3,
                       "cy": 58.9, "dist": [0.01, 0.0, 0.002, -0.001, 0.0]},
            "position": {"x": 1.0, "y": 2.0, "z": 3.0},
            "orientation": {"trend_deg": 40.0, "plunge_deg": 5.0, "roll_deg": roll}, **extra}
    if roll is None:
        del data["orientation"]["roll_deg"]
    return parse_sensor_record(data, tmp_path / "IMG_0001.json")


def test_exif_orientation_3_turns_camera_and_attitude_by_half_a_turn(tmp_path):
    """A photo taken upside down is stored as the sensor saw it and shown
    turned 180°: its landscape record is the sensor's, so the camera
    (principal point, tangential distortion) and the pose are turned."""
    from napari_imgreg.prior import prior_from_record

    record = _sensor_record(tmp_path)
    sensor = prior_from_record(record, image_size=(160, 120))
    prior = prior_from_record(record, image_size=(160, 120), exif_orientation=3)
    assert prior.intrinsics == sensor.intrinsics.rotated(2)
    assert prior.intrinsics.cx == pytest.approx(159 - 80.3)
    assert prior.intrinsics.cy == pytest.approx(119 - 58.9)
    assert prior.intrinsics.dist == pytest.approx((0.01, 0.0, -0.002, 0.001, 0.0))
    assert np.allclose(prior.pose.R, sensor.pose.rotated(2).R)
    assert np.allclose(prior.pose.center, sensor.pose.center)
    trend, plunge, roll = prior.pose.attitude
    assert (trend, plunge) == pytest.approx((40.0, 5.0)) and roll == pytest.approx(-178.0)
    assert any("turned +180°" in note for note in prior.assumptions)


def test_exif_orientation_3_resized_photo(tmp_path):
    from napari_imgreg.prior import prior_from_record

    record = _sensor_record(tmp_path)
    prior = prior_from_record(record, image_size=(80, 60), exif_orientation=3)
    half = prior_from_record(record, image_size=(160, 120)).intrinsics.rotated(2).scaled(0.5)
    assert prior.intrinsics == half


def test_image_frame_shown_is_not_turned(tmp_path):
    """A record of the photo as shown (as napari-imgreg saves a pose) is used as it is."""
    from napari_imgreg.prior import prior_from_record

    record = _sensor_record(tmp_path, image_frame="shown")
    plain = prior_from_record(record, image_size=(160, 120))
    prior = prior_from_record(record, image_size=(160, 120), exif_orientation=3)
    assert prior.intrinsics == plain.intrinsics
    assert np.allclose(prior.pose.R, plain.pose.R)


def test_image_frame_stored_turns_the_attitude_of_a_portrait_block(tmp_path):
    """``image_frame: "stored"`` says the attitude is the sensor's even when the
    camera block is already of the shown size."""
    from napari_imgreg.io.records import parse_sensor_record
    from napari_imgreg.prior import prior_from_record

    data = {"camera": {"width": 120, "height": 160, "fx": 110.0},
            "position": {"x": 1.0, "y": 2.0, "z": 3.0},
            "orientation": {"trend_deg": 40.0, "plunge_deg": 5.0, "roll_deg": 88.0}}
    plain = prior_from_record(parse_sensor_record(data), image_size=(120, 160),
                              exif_orientation=6)
    stored = prior_from_record(parse_sensor_record({**data, "image_frame": "stored"}),
                               image_size=(120, 160), exif_orientation=6)
    assert plain.pose.attitude[2] == pytest.approx(88.0)
    assert np.allclose(stored.pose.R, plain.pose.rotated(1).R)
    assert stored.pose.attitude[2] == pytest.approx(-2.0, abs=1e-6)  # roll − 90°


@pytest.mark.parametrize("orientation", [3, 6])
def test_a_roll_the_record_lacks_is_the_shown_photos(tmp_path, orientation):
    """A record without roll (a compass app): the shown photo is taken as level,
    not the sensor (which would tilt the shown photo by 90° or 180°)."""
    from napari_imgreg.prior import prior_from_record

    record = _sensor_record(tmp_path, roll=None)
    size = (160, 120) if orientation == 3 else (120, 160)
    prior = prior_from_record(record, image_size=size, exif_orientation=orientation)
    trend, plunge, roll = prior.pose.attitude
    assert (trend, plunge, roll) == pytest.approx((40.0, 5.0, 0.0), abs=1e-6)
    assert "roll assumed 0° (level photo as shown)" in prior.assumptions


def test_bad_image_frame_is_one_line(wall, tmp_path, run_cli):
    data = {**_record(), "image_frame": "sideways"}
    record = _write_record(tmp_path, data)
    run = run_cli(["render", wall, record, "--out", tmp_path / "r.png"])
    line = run.line
    assert run.code == 2 and str(record) in line
    assert "field 'image_frame' must be one of 'stored', 'shown', got 'sideways'" in line


def _oriented_photo(path, stored: np.ndarray, orientation: int, base_exif=None):
    im = Image.fromarray(stored)
    exif = base_exif if base_exif is not None else Image.Exif()
    exif[0x0112] = orientation
    im.save(path, exif=exif, quality=95)
    return path


@pytest.mark.parametrize("orientation", [2, 4, 5, 7])
def test_mirrored_exif_orientation_is_refused_with_the_fix(wall, tmp_path, run_cli, orientation):
    """A mirror image has no camera pose: one line naming the photo, the tag and
    how to fix it, whatever the record's camera block (here the photo's own size)."""
    stored = np.full((120, 160, 3), 90, np.uint8)
    photo = _oriented_photo(tmp_path / "IMG_0001.jpg", stored, orientation)
    shown = (120, 160) if orientation in (5, 7) else (160, 120)
    record = _write_record(tmp_path, _record(width=shown[0], height=shown[1]))
    run = run_cli(["register", wall, photo, "--prior", record,
                              "--out", tmp_path / "R.json"])
    line = run.line
    assert run.code == 2 and str(photo) in line, line
    assert f"EXIF orientation {orientation} mirrors it" in line
    assert "exiftool -n -Orientation=1" in line and not (tmp_path / "R.json").exists()


def test_mirrored_photo_still_loads_for_viewing(tmp_path):
    """Only registration refuses a mirrored photo: it is read and shown as its
    EXIF says (mirrored), e.g. to draw on it."""
    from napari_imgreg.io.photos import load_photo

    stored = np.zeros((30, 40, 3), np.uint8)
    stored[0, 0] = 255
    photo = load_photo(_oriented_photo(tmp_path / "m.png", stored, 2))
    assert photo.size == (40, 30) and photo.image[0, 39].min() == 255


def test_exif_camera_of_a_portrait_photo_is_the_sensors_turned(tmp_path):
    """EXIF focal-plane resolution and ExifImageWidth are the stored image's:
    a portrait photo (orientation 6) gets the sensor's camera turned, not one
    scaled by the aspect ratio."""
    from PIL import ExifTags
    from PIL.TiffImagePlugin import IFDRational

    from napari_imgreg.camera import Intrinsics
    from napari_imgreg.io.exif import record_from_exif
    from napari_imgreg.io.photos import load_photo

    exif = Image.Exif()
    sub = exif.get_ifd(ExifTags.IFD.Exif)
    sub[ExifTags.Base.FocalLength] = IFDRational(425, 100)  # 4.25 mm
    sub[ExifTags.Base.FocalPlaneXResolution] = IFDRational(160 * 10, 56)  # 5.6 mm wide sensor
    sub[ExifTags.Base.FocalPlaneResolutionUnit] = 4  # mm
    sub[ExifTags.Base.ExifImageWidth] = 160
    sub[ExifTags.Base.ExifImageHeight] = 120
    path = _oriented_photo(tmp_path / "p.jpg", np.full((120, 160, 3), 90, np.uint8), 6, exif)
    photo = load_photo(path)
    assert photo.size == (120, 160)
    camera = Intrinsics.from_dict(record_from_exif(photo)[0].camera)
    f = 4.25 * 160 / 5.6
    assert camera == Intrinsics(120, 160, f, f, 59.5, 79.5, estimated=("fx", "fy"))


def test_landscape_block_without_focal_and_exif_focal_turns_the_attitude(tmp_path):
    """The common phone case: a record giving only the sensor's size and the
    attitude, the focal length in the EXIF, the photo portrait (orientation 6)."""
    from PIL import ExifTags

    from napari_imgreg.io.photos import load_photo
    from napari_imgreg.prior import prior_for_photo

    exif = Image.Exif()
    exif.get_ifd(ExifTags.IFD.Exif)[ExifTags.Base.FocalLengthIn35mmFilm] = 28
    path = _oriented_photo(tmp_path / "IMG_0001.jpg", np.full((120, 160, 3), 90, np.uint8), 6,
                           exif)
    data = _record()
    data["camera"] = {"width": 1600, "height": 1200}  # the sensor, before a resize
    data["orientation"]["roll_deg"] = 90.0  # the phone held upright
    _write_record(tmp_path, data)
    prior = prior_for_photo(load_photo(path))
    assert (prior.intrinsics.width, prior.intrinsics.height) == (120, 160)
    assert prior.pose.attitude[2] == pytest.approx(0.0, abs=1e-6)  # level as shown
    assert "focal length from EXIF" in prior.assumptions


def test_saved_pose_of_a_turned_photo_is_read_back_unchanged(tmp_path):
    """save_pose_to_record writes the pose of the photo as shown, with
    ``image_frame: "shown"``: the next prior is that pose, not turned again."""
    from napari_imgreg.io.photos import load_photo
    from napari_imgreg.prior import prior_for_photo, save_pose_to_record

    path = _oriented_photo(tmp_path / "IMG_0001.jpg", np.full((120, 160, 3), 90, np.uint8), 3)
    record = _write_record(tmp_path, _record(cx=70.0))
    first = prior_for_photo(load_photo(path))
    saved = save_pose_to_record(record, first.pose)
    assert saved["image_frame"] == "shown"
    again = prior_for_photo(load_photo(path))
    assert np.allclose(again.pose.R, first.pose.R) and np.allclose(again.pose.t, first.pose.t)


@pytest.mark.slow
def test_photo_turned_180_with_its_landscape_record_registers(tmp_path):
    """End to end on the sample: a photo stored as the sample's (the sensor's
    image) with EXIF orientation 3, as a phone held upside down stores it, and
    its landscape sensor record registers at the true pose turned 180°."""
    from napari_imgreg import Scene
    from napari_imgreg.io.photos import load_photo
    from napari_imgreg.prior import prior_for_photo
    from napari_imgreg.registration.pipeline import register
    from napari_imgreg.sample import load_truth, sample_scene

    folder = sample_scene("small")
    scene = Scene.load(folder / "outcrop.obj", dem=folder / "dem.tif")
    with Image.open(folder / "IMG_0001.jpg") as im:
        stored, exif = np.asarray(im.convert("RGB")), im.getexif()
    photo_path = _oriented_photo(tmp_path / "IMG_0001.jpg", stored, 3, exif)
    (tmp_path / "IMG_0001.json").write_text((folder / "IMG_0001.json").read_text())
    photo = load_photo(photo_path)
    assert np.array_equal(photo.image[0, 0], np.asarray(Image.open(photo_path))[-1, -1])
    prior = prior_for_photo(photo, scene)
    turned_truth = load_truth(folder / "IMG_0001.jpg").pose.rotated(2)
    assert (prior.intrinsics.width, prior.intrinsics.height) == photo.size
    reg = register(scene, photo.image, prior, photo_name=photo_path.name)
    assert reg.status == "registered"
    assert reg.pose.rotation_error_deg(turned_truth) < 0.2
    assert np.linalg.norm(reg.pose.center - turned_truth.center) < 0.3


# ------------------------------------------------ attitude from the metadata
def _metadata_photo(tmp_path, *, xmp=None, direction=None, lat=None, alt=None):
    """A 160 × 120 JPEG with DJI XMP gimbal angles and/or GPS tags."""
    from PIL import ExifTags
    from PIL.TiffImagePlugin import IFDRational

    exif = Image.Exif()
    gps = exif.get_ifd(ExifTags.IFD.GPSInfo)
    if direction is not None:
        gps[ExifTags.GPS.GPSImgDirectionRef] = "T"
        gps[ExifTags.GPS.GPSImgDirection] = direction
    if lat is not None:
        gps[ExifTags.GPS.GPSLatitudeRef] = "N"
        gps[ExifTags.GPS.GPSLatitude] = lat
        gps[ExifTags.GPS.GPSLongitudeRef] = "E"
        gps[ExifTags.GPS.GPSLongitude] = (IFDRational(7, 1), IFDRational(0, 1), IFDRational(0, 1))
    if alt is not None:
        gps[ExifTags.GPS.GPSAltitudeRef] = b"\x00"
        gps[ExifTags.GPS.GPSAltitude] = alt
    path = tmp_path / "DJI_0001.jpg"
    kwargs = {"exif": exif} if (direction is not None or lat is not None) else {}
    if xmp is not None:
        kwargs["xmp"] = xmp
    Image.fromarray(np.full((120, 160, 3), 90, np.uint8)).save(path, **kwargs)
    return path


def _dji_xmp(yaw, pitch, roll) -> bytes:
    return ('<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF '
            'xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#"><rdf:Description '
            'xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/" '
            f'drone-dji:GimbalRollDegree="{roll}" drone-dji:GimbalYawDegree="{yaw}" '
            f'drone-dji:GimbalPitchDegree="{pitch}"/></rdf:RDF></x:xmpmeta>').encode()


@pytest.mark.parametrize("angles, needle", [
    ((10.0, -135.0, 0.0), ("field 'XMP drone-dji:GimbalPitchDegree' must be within [-90, 90], "
                           "got -135.0")),
    (("nan", -30.0, 0.0), "field 'XMP drone-dji:GimbalYawDegree' must be a finite number, got nan"),
    ((10.0, -30.0, "1e400"), "field 'XMP drone-dji:GimbalRollDegree' must be a finite number"),
    ((10.0, -30.0, "left"), "field 'XMP drone-dji:GimbalRollDegree' must be a number, got 'left'"),
    ((725.0, -30.0, 0.0), "field 'XMP drone-dji:GimbalYawDegree' must be within [-360, 360]"),
])
def test_dji_gimbal_angles_are_range_checked(wall, tmp_path, run_cli, angles, needle):
    """A record without attitude takes the drone's gimbal angles: a corrupt one
    is one line naming the photo and the XMP field, not a silent nonsense pose."""
    photo = _metadata_photo(tmp_path, xmp=_dji_xmp(*angles))
    data = _record()
    del data["orientation"]
    record = _write_record(tmp_path, data, "DJI_0001.json")
    run = run_cli(["register", wall, photo, "--prior", record,
                              "--out", tmp_path / "R.json"])
    line = run.line
    assert run.code == 2 and str(photo) in line and needle in line, line


def test_bad_gimbal_angles_are_ignored_when_the_record_gives_the_attitude(tmp_path):
    """Only what the record lacks is read from the metadata."""
    from napari_imgreg.io.photos import load_photo
    from napari_imgreg.prior import prior_for_photo

    photo = _metadata_photo(tmp_path, xmp=_dji_xmp(10.0, -135.0, 0.0))
    _write_record(tmp_path, _record(), "DJI_0001.json")
    prior = prior_for_photo(load_photo(photo))
    assert prior.pose.attitude == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)


@pytest.mark.parametrize("tags, needle", [
    ({"direction": float("nan")}, "field 'EXIF GPSImgDirection' must be a finite number"),
    ({"direction": 1e6}, "field 'EXIF GPSImgDirection' must be within [-720, 720]"),
    ({"lat": (95.0, 0.0, 0.0)}, "field 'EXIF GPSLatitude' must be within [-90, 90], got 95.0"),
    ({"lat": (float("nan"), 0.0, 0.0)}, "field 'EXIF GPSLatitude' must be three finite numbers"),
])
def test_exif_attitude_and_position_are_range_checked(tmp_path, tags, needle):
    from PIL.TiffImagePlugin import IFDRational

    from napari_imgreg.errors import InputError
    from napari_imgreg.io.exif import record_from_exif
    from napari_imgreg.io.photos import load_photo

    def rational(x):
        return IFDRational(0, 0) if math.isnan(x) else IFDRational(int(x * 100), 100)

    kwargs = {k: (tuple(rational(v) for v in val) if isinstance(val, tuple) else rational(val))
              for k, val in tags.items()}
    if "lat" in kwargs:
        kwargs["direction"] = IFDRational(1000, 100)
    photo = load_photo(_metadata_photo(tmp_path, **kwargs))
    with pytest.raises(InputError) as err:
        record_from_exif(photo)
    message = str(err.value)
    assert message.startswith(str(photo.path)) and needle in message and "\n" not in message


def test_unknown_gps_altitude_is_taken_from_the_dem(tmp_path):
    """0/0, some phones' "no vertical fix": the altitude is left to the DEM, with a note."""
    from PIL.TiffImagePlugin import IFDRational

    from napari_imgreg.io.exif import record_from_exif
    from napari_imgreg.io.photos import load_photo

    photo = load_photo(_metadata_photo(
        tmp_path, lat=(IFDRational(46, 1), IFDRational(0, 1), IFDRational(0, 1)),
        alt=IFDRational(0, 0), direction=IFDRational(10, 1)))
    record, notes = record_from_exif(photo)
    assert record.position == {"lat": 46.0, "lon": 7.0}
    assert "position from EXIF GPS (GPSAltitude unknown, 0/0: ignored)" in notes


# ----------------------------------------------------- results read by project
@pytest.mark.parametrize("camera, t, needle", [
    ({"fx": 50.0}, [float("nan"), 0.0, 30.0], "field 'pose.t' must be 3 finite numbers"),
    ({"fx": 0.0}, [0.0, 0.0, 30.0], "field 'camera.fx'"),
])
def test_project_refuses_a_result_with_nan_translation_or_fx_0(wall, tmp_path, run_cli,
                                                               camera, t, needle):
    """Before issue 15 ``project`` wrote an empty file with exit 0."""
    R = np.eye(3)[[0, 2, 1]] * [1, -1, 1]
    cam = {"width": 80, "height": 60, "fy": 50.0, "cx": 39.5, "cy": 29.5, **camera}
    result = tmp_path / "IMG_0001.result.json"
    result.write_text(json.dumps({"status": "registered", "photo": "IMG_0001.jpg",
                                  "camera": cam, "pose": {"R": R.tolist(), "t": t}},
                                 allow_nan=True))
    lines = tmp_path / "lines.geojson"
    lines.write_text(json.dumps({"type": "FeatureCollection", "features": [{
        "type": "Feature", "properties": {"label": "bed"},
        "geometry": {"type": "LineString", "coordinates": [[10, 20], [60, 30]]}}]}))
    out = tmp_path / "lines3d.geojson"
    run = run_cli(["project", result, wall, lines, "--out", out])
    line = run.line
    assert run.code == 2 and str(result) in line and needle in line, line
    assert not out.exists()


# ------------------------------------------- turned photos on the command line
@pytest.mark.parametrize("orientation, shown", [(3, (160, 120)), (6, (120, 160)),
                                                (8, (120, 160))])
def test_register_a_turned_photo_with_its_landscape_record(wall, tmp_path, run_cli,
                                                           orientation, shown):
    """Before issue 15 a portrait photo with its landscape record was a
    traceback: now the camera and attitude are turned with the pixels (the
    flat-textured wall does not register: exit 1, a result written)."""
    from napari_imgreg.camera import Intrinsics, Pose

    photo = _oriented_photo(tmp_path / "IMG_0001.jpg", np.full((120, 160, 3), 90, np.uint8),
                            orientation)
    record = _write_record(tmp_path, _record())
    params = tmp_path / "params.json"
    params.write_text(json.dumps({"max_trials": 1}))
    out = tmp_path / "R.json"
    run = run_cli(["register", wall, photo, "--prior", record, "--params", params,
                   "--out", out], max_seconds=120)
    assert run.code in (0, 1) and "Traceback" not in run.err, run.err
    result = json.loads(out.read_text())
    camera = Intrinsics.from_dict(result["camera"])
    assert (camera.width, camera.height) == shown
    turns = {3: 2, 6: 1, 8: -1}[orientation]
    sensor = Pose.from_attitude(0.0, 0.0, 0.0, [20.0, -30.0, 10.0]).rotated(turns)
    assert Pose.from_dict(result["prior"]["pose"]).rotation_error_deg(sensor) < 1e-6
    assert any("turned" in note for note in result["prior"]["assumptions"])


@pytest.mark.parametrize("coords, needle", [
    ([[0, 0], [1e308, 5.0]], "far outside"),
    ([[0, 0], [1e9, 1e9]], "far outside"),
])
def test_project_refuses_unbounded_line_coordinates(wall, tmp_path, run_cli, coords, needle):
    """Before issue 15: a traceback (1e308) or a process killed at 22 GB (1e9)."""
    from napari_imgreg.camera import Intrinsics, Pose

    intr = Intrinsics(160, 120, 100.0, 100.0, 79.5, 59.5)
    pose = Pose.from_attitude(0.0, 0.0, 0.0, [20.0, -30.0, 10.0])
    result = tmp_path / "IMG_0001.result.json"
    result.write_text(json.dumps({"status": "registered", "photo": "IMG_0001.jpg",
                                  "camera": intr.to_dict(), "pose": pose.to_dict()}))
    lines = tmp_path / "lines.geojson"
    lines.write_text(json.dumps({"type": "FeatureCollection", "features": [{
        "type": "Feature", "properties": {"label": "bed"},
        "geometry": {"type": "LineString", "coordinates": coords}}]}))
    run = run_cli(["project", result, wall, lines, "--out", tmp_path / "l3d.geojson"])
    line = run.line
    assert run.code == 2 and str(lines) in line and needle in line, line
    assert line.count("160×120") == 1, line  # the photo's size, said once


# ------------------------------------------------ secondary outputs, stdout, links
@pytest.mark.parametrize("case", ["inside a file", "under /proc"])
@pytest.mark.parametrize("option", ["render --depth", "render --xyz", "orient --mesh-out",
                                    "orient --plots"])
def test_unwritable_secondary_output_is_found_first(wall, tmp_path, run_cli, case, option):
    """Every output a command writes is checked before the work, not only
    ``--out``: render's ``--depth``/``--xyz``, orient's ``--mesh-out``/``--plots``."""
    (tmp_path / "a_file.txt").write_text("x")
    command, flag = option.split()
    base = tmp_path / "a_file.txt" if case == "inside a file" else "/proc"
    bad = f"{base}/napari-imgreg-{flag.strip('-')}" + (
        ".npy" if command == "render" else "" if flag == "--plots" else ".ply")
    if command == "render":
        argv = ["render", wall, _write_record(tmp_path, _record()), "--out", tmp_path / "r.png",
                flag, bad]
    else:
        table = tmp_path / "cams.csv"
        table.write_text("photo,trend_deg,plunge_deg,roll_deg\na,10,5,0\nb,100,3,1\nc,200,8,-1\n")
        argv = ["orient", table, table, "--out", tmp_path / "o.json", flag, bad]
        if flag == "--mesh-out":
            argv += ["--apply", wall]
    run = run_cli(argv)
    line = run.line
    assert run.code == 2 and bad in line and "cannot write here" in line, line
    assert not (tmp_path / "r.png").exists() and not (tmp_path / "o.json").exists()


def test_closed_stdout_after_a_successful_render(wall, tmp_path):
    """A reader that has gone (``render … | head -0``): the image is written,
    the summary lines are dropped, exit 0 and no traceback."""
    import io

    from napari_imgreg.cli import main

    record = _write_record(tmp_path, _record())
    closed = io.TextIOWrapper(io.BytesIO())
    closed.close()
    saved = sys.stdout
    sys.stdout = closed
    try:
        code = main(["render", str(wall), str(record), "--out", str(tmp_path / "r.png")])
    finally:
        sys.stdout = saved
    assert code == 0 and (tmp_path / "r.png").stat().st_size > 0


def test_symlinked_out_of_a_command_is_followed(wall, tmp_path, run_cli):
    """``render --out LINK``: the file the link points to gets the image, the link stays."""
    store = tmp_path / "store"
    store.mkdir()
    target = store / "render.png"
    target.write_bytes(b"old")
    link = tmp_path / "render.png"
    link.symlink_to(target)
    run = run_cli(["render", wall, _write_record(tmp_path, _record()), "--out", link])
    assert run.code == 0, run.err
    assert link.is_symlink() and os.readlink(link) == str(target)
    assert Image.open(target).size == (160, 120)


def test_render_of_a_tiny_point_cloud_is_one_line(tmp_path, run_cli):
    cloud = tmp_path / "tiny.xyz"
    cloud.write_text("0 10 0\n1 10 0\n0 10 1\n")
    run = run_cli(["render", cloud, _write_record(tmp_path, _record()), "--out", tmp_path / "r.png"])
    assert run.code == 2 and str(cloud) in run.line and "16 points" in run.line


# ------------------------------------------------ outputs that are the inputs
def _lines_file(tmp_path):
    lines = tmp_path / "L.geojson"
    lines.write_text(json.dumps({"type": "FeatureCollection", "features": [{
        "type": "Feature", "properties": {"label": "bed"},
        "geometry": {"type": "LineString", "coordinates": [[10, 10], [100, 50]]}}]}))
    return lines


@pytest.mark.parametrize("spelling", ["same path", "symlink"])
@pytest.mark.parametrize("case", ["project --out LINES", "register --out PRIOR",
                                  "render --depth = --xyz", "orient --mesh-out APPLY"])
def test_an_output_that_is_an_input_is_refused_before_any_work(wall, tmp_path, run_cli, case,
                                                                spelling):
    """A command never writes over its own input (the hand-drawn lines, the
    sensor record), nor two outputs into one file: one line, exit 2, every
    file as it was, whether the output names the input or a link to it."""
    record = _write_record(tmp_path, _record())

    def alias(path):
        if spelling == "same path":
            return path
        link = tmp_path / f"link{path.suffix}"
        link.symlink_to(path)
        return link

    if case == "project --out LINES":
        kept = _lines_file(tmp_path)
        argv = ["project", record, wall, kept, "--out", alias(kept)]
        needle = "refusing to overwrite the input lines; choose another name"
    elif case == "register --out PRIOR":
        photo = tmp_path / "IMG_0001.png"
        Image.fromarray(np.full((120, 160, 3), 90, np.uint8)).save(photo)
        kept = record
        argv = ["register", wall, photo, "--prior", record, "--out", alias(record)]
        needle = "refusing to overwrite the input sensor record; choose another name"
    elif case == "render --depth = --xyz":
        kept = tmp_path / "a.npy"
        np.save(kept, np.zeros(3))
        argv = ["render", wall, record, "--out", tmp_path / "r.png", "--depth", kept,
                "--xyz", alias(kept)]
        needle = "refusing to write --depth and --xyz to one file; choose another name"
    else:
        table = tmp_path / "cams.csv"
        table.write_text("photo,trend_deg,plunge_deg,roll_deg\na,10,5,0\nb,100,3,1\nc,200,8,-1\n")
        kept = wall
        argv = ["orient", table, table, "--out", tmp_path / "o.json", "--apply", wall,
                "--mesh-out", alias(wall)]
        needle = "refusing to overwrite the input mesh; choose another name"
    before = kept.read_bytes()
    run = run_cli(argv)
    line = run.line
    assert run.code == 2 and needle in line, line
    assert kept.read_bytes() == before
    assert not (tmp_path / "r.png").exists() and not (tmp_path / "o.json").exists()


def test_orient_reads_the_mesh_to_apply_before_writing_anything(wall, tmp_path, run_cli):
    """A bad --apply mesh leaves an earlier ORIENTATION.json as it was."""
    table = tmp_path / "cams.csv"
    table.write_text("photo,trend_deg,plunge_deg,roll_deg\na,10,5,0\nb,100,3,1\nc,200,8,-1\n")
    out = tmp_path / "o.json"
    out.write_text('{"earlier": "orientation"}\n')
    bad = tmp_path / "bad.obj"
    bad.write_text("not a mesh\n")
    phone = tmp_path / "phone.csv"
    phone.write_bytes(table.read_bytes())
    run = run_cli(["orient", table, phone, "--out", out, "--apply", bad,
                   "--mesh-out", tmp_path / "om.obj"])
    line = run.line
    assert run.code == 2 and str(bad) in line, line
    assert out.read_text() == '{"earlier": "orientation"}\n'
    assert not (tmp_path / "om.obj").exists()


def test_project_of_lines_without_features_is_bad_input(wall, tmp_path, run_cli):
    """An empty drawing gives no empty output file (``0 feature(s) ()``): one line, exit 2."""
    lines = tmp_path / "L.geojson"
    lines.write_text('{"type": "FeatureCollection", "features": []}')
    out = tmp_path / "L3D.geojson"
    run = run_cli(["project", _write_record(tmp_path, _record()), wall, lines, "--out", out])
    line = run.line
    assert run.code == 2 and str(lines) in line and "no features to project" in line, line
    assert not out.exists()


@pytest.mark.parametrize("given, needle", [
    ("lines", "is GeoJSON (a drawing or projected lines), not a sensor record"),
    ("georef", "is a georef.json, not a sensor record"),
    ("photo", "is not a JSON file: binary content (PNG), not text"),
    ("folder", "is a folder, not a JSON file"),
])
def test_another_file_given_as_the_record_is_named_for_what_it_is(wall, tmp_path, run_cli,
                                                                  given, needle):
    """A drawing, a georef.json, a photo or a folder where the sensor record
    belongs: one line saying what the file is, not a missing heading or a
    decoder's error."""
    path = {"lines": tmp_path / "IMG_0001.lines.geojson", "georef": tmp_path / "georef.json",
            "photo": tmp_path / "IMG_0002.png", "folder": tmp_path / "records"}[given]
    if given == "lines":
        path.write_text('{"type": "FeatureCollection", "features": []}')
    elif given == "georef":
        path.write_text('{"crs": "EPSG:32630", "origin": [579000, 5912000, 350]}')
    elif given == "photo":
        Image.fromarray(np.zeros((12, 16, 3), np.uint8)).save(path)
    else:
        path.mkdir()
    run = run_cli(["render", wall, path, "--out", tmp_path / "r.png"])
    assert run.code == 2 and f"{path}: {needle}" in run.line, run.line
    assert not (tmp_path / "r.png").exists()


def test_a_truncated_mesh_says_so(tmp_path, run_cli):
    """A PLY cut short (an interrupted copy): one line saying the file is
    damaged or truncated, with the reader's own words after it."""
    import trimesh

    grid = trimesh.creation.box(extents=(10.0, 10.0, 10.0)).subdivide().subdivide()
    whole = tmp_path / "whole.ply"
    grid.export(whole)
    cut = tmp_path / "cut.ply"
    cut.write_bytes(whole.read_bytes()[:len(whole.read_bytes()) // 2])
    record = _write_record(tmp_path, _record())
    run = run_cli(["render", cut, record, "--out", tmp_path / "r.png"])
    assert run.code == 2
    assert f"{cut}: cannot read mesh: damaged, truncated or not a PLY file (" in run.line, run.line


@pytest.mark.parametrize("case, needle", [
    ("degrees", "coordinates in longitude and latitude (urn:ogc:def:crs:OGC:1.3:CRS84): "
                "measure needs metres"),
    ("empty", "no features to measure (an empty FeatureCollection)"),
])
def test_measure_refuses_degrees_and_nothing(tmp_path, run_cli, case, needle):
    """Lines in longitude/latitude (a GIS's export) would fit planes to degrees
    and metres together (every trace vertical); an empty file has nothing."""
    doc = {"type": "FeatureCollection", "features": []}
    if case == "degrees":
        doc["crs"] = {"type": "name", "properties": {"name": "urn:ogc:def:crs:OGC:1.3:CRS84"}}
        doc["features"] = [{"type": "Feature", "properties": {"label": "bed"}, "geometry": {
            "type": "LineString",
            "coordinates": [[-1.8132, 53.3512, 390.1], [-1.8128, 53.3511, 391.0],
                            [-1.8125, 53.3509, 390.4]]}}]
    path = tmp_path / "lines3d.geojson"
    path.write_text(json.dumps(doc))
    run = run_cli(["measure", path, "--out", tmp_path / "m.csv"])
    assert run.code == 2 and f"{path}: {needle}" in run.line, run.line
    assert not (tmp_path / "m.csv").exists()


def test_register_writes_only_a_json_result(wall, tmp_path, run_cli):
    """RESULT.json under another suffix (x.csv) would be taken for a table."""
    record = _write_record(tmp_path, _record())
    photo = tmp_path / "IMG_0001.png"
    Image.fromarray(np.full((120, 160, 3), 90, np.uint8)).save(photo)
    run = run_cli(["register", wall, photo, "--prior", record, "--out", tmp_path / "x.csv"])
    assert run.code == 2 and "x.csv: output must be a .json file (the RESULT.json)" in run.line
    assert not (tmp_path / "x.csv").exists()


def test_text_coordinates_and_a_folder_as_dem_are_named(wall, tmp_path, run_cli):
    """"100" where a number belongs is refused, not read as 100; a folder
    given as the DEM is said to be one."""
    lines = tmp_path / "lines.geojson"
    lines.write_text(json.dumps({"type": "FeatureCollection", "features": [{
        "type": "Feature", "properties": {},
        "geometry": {"type": "LineString", "coordinates": [["100", "200"], ["300", "400"]]}}]}))
    record = _write_record(tmp_path, _record())
    run = run_cli(["project", record, wall, lines, "--out", tmp_path / "l3.geojson"])
    assert run.code == 2 and f"{lines}: feature 1: coordinates are text, not numbers" in run.line
    run = run_cli(["render", wall, record, "--out", tmp_path / "r.png", "--dem", tmp_path])
    assert run.code == 2 and f"{tmp_path}: is a folder, not a DEM file" in run.line, run.line
