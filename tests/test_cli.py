"""The command line: outputs, exit codes, one-line errors, atomic writes."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from napari_imgreg import Intrinsics, Pose


@pytest.fixture
def wall(wall_and_record):
    """The shared wall and a sensor record facing it (conftest ``wall_and_record``)."""
    return wall_and_record


def test_render_writes_image_and_depth(wall, tmp_path, run_cli):
    mesh, prior = wall
    out, depth = tmp_path / "render.png", tmp_path / "depth.npy"
    run = run_cli(["render", mesh, prior, "--out", out, "--depth", depth])
    assert run.code == 0
    image = np.asarray(Image.open(out))
    assert image.shape == (120, 160, 3)
    d = np.load(depth)
    # The wall is 30 m in front of a level camera: depth is 30 everywhere it is seen.
    assert np.nanmax(np.abs(d - 30.0)) < 1e-3
    assert np.isnan(d).any() and np.isfinite(d).any()
    # Colour follows the texture: red grows eastward (to the right).
    row = image[60]
    seen = np.isfinite(d[60])
    assert np.all(np.diff(row[seen, 0].astype(int)) >= -1)
    assert "rendered wall" in run.out


def test_render_from_result_json(wall, tmp_path, run_cli):
    mesh, _ = wall
    intr = Intrinsics(80, 60, 50.0, 50.0, 39.5, 29.5)
    pose = Pose.from_attitude(0.0, 0.0, 0.0, [20.0, -30.0, 10.0])
    result = tmp_path / "RESULT.json"
    result.write_text(json.dumps({"status": "registered", "camera": intr.to_dict(),
                                  "pose": pose.to_dict()}))
    out = tmp_path / "r.png"
    assert run_cli(["render", mesh, result, "--out", out]).code == 0
    assert np.asarray(Image.open(out)).shape == (60, 80, 3)


@pytest.mark.parametrize(
    "case, needle",
    [
        ("missing_mesh", "nope.obj: no such file"),
        ("corrupt_mesh", "broken.obj"),
        ("missing_prior", "nope.json: no such file"),
        ("bad_json", "IMG_0001.json: invalid JSON"),
        ("wrong_field", "field 'orientation.trend_deg' must be a number"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(wall, tmp_path, run_cli, case, needle):
    mesh, prior = wall
    if case == "missing_mesh":
        mesh = tmp_path / "nope.obj"
    elif case == "corrupt_mesh":
        mesh = tmp_path / "broken.obj"
        mesh.write_bytes(b"v 1 2\nf 1 2 9\n\x00\xff garbage")
    elif case == "missing_prior":
        prior = tmp_path / "nope.json"
    elif case == "bad_json":
        prior.write_text("{ oops")
    elif case == "wrong_field":
        data = json.loads(prior.read_text())
        data["orientation"]["trend_deg"] = "north"
        prior.write_text(json.dumps(data))
    out = tmp_path / "render.png"
    out.write_bytes(b"previous render")  # must survive a failed run untouched
    run = run_cli(["render", mesh, prior, "--out", out])
    assert run.code == 2 and needle in run.line
    assert out.read_bytes() == b"previous render"
    assert not list(tmp_path.glob(".render.png.*"))  # no temporary left behind


def test_console_script_help_and_usage_errors():
    run = subprocess.run([sys.executable, "-m", "napari_imgreg", "render", "--help"],
                         capture_output=True, text=True)
    assert run.returncode == 0 and "PRIOR_OR_RESULT.json" in run.stdout
    run = subprocess.run([sys.executable, "-m", "napari_imgreg", "render"],
                         capture_output=True, text=True)
    assert run.returncode == 2


def test_demo_registers_the_sample_photos(tmp_path, run_cli):
    from napari_imgreg.sample import load_truth, sample_scene

    out = tmp_path / "demo"
    run = run_cli(["demo", "--out", out], max_seconds=None)
    assert run.code == 0
    stdout = run.out
    folder = sample_scene("small")
    demo = json.loads((out / "demo.json").read_text())
    photos = sorted(p.name for p in folder.glob("IMG_*.jpg"))
    assert [p["photo"] for p in demo["photos"]] == photos
    for entry in demo["photos"]:
        stem = entry["photo"][: -len(".jpg")]
        reg = entry["registration"]
        assert reg["status"] == "registered" and reg["rotation_error_deg"] < 0.2
        # The written RESULT.json itself, checked against the ground truth.
        result = json.loads((out / f"{stem}.result.json").read_text())
        assert result["status"] == "registered"
        truth = load_truth(folder / entry["photo"]).pose
        pose = Pose.from_dict(result["pose"])
        assert pose.rotation_error_deg(truth) < 0.2
        assert np.linalg.norm(pose.center - truth.center) < 1.0
        # photo | render views, from the prior and from the registered pose.
        w, h = result["camera"]["width"], result["camera"]["height"]
        for view in ("prior", "registered"):
            assert Image.open(out / f"{stem}_photo_vs_{view}.jpg").size == (2 * w, h)
        assert f"{entry['photo']}: REGISTERED" in stdout
    assert "off the true pose by" in stdout
    assert f"registered {len(photos)} of {len(photos)} sample photos" in stdout


def test_commands_on_a_cloud_say_which_frame_its_points_are_in(wall, tmp_path, run_cli):
    """A lidar LAS in UTM coordinates with its CRS record and no georef.json
    is taken as the model frame, millions of metres from a camera: register,
    project and workspace create say so (and what georef.json to write), as
    render and batch do, instead of leaving only "camera is 5,940 km from the
    model" to explain a failure."""
    from napari_imgreg.io.pointclouds import PointCloud, write_point_cloud

    _, record = wall
    rng = np.random.default_rng(0)
    xyz = np.column_stack([rng.uniform(0, 40, 4000), np.zeros(4000), rng.uniform(0, 20, 4000)])
    origin = np.array([579000.0, 5912000.0, 350.0])
    folder = tmp_path / "scan"
    folder.mkdir()
    cloud = write_point_cloud(folder / "scan.las", PointCloud(
        xyz + origin, rng.uniform(0, 1, 4000).astype(np.float32), crs_epsg=32630))
    photo = folder / "IMG_0001.png"
    Image.fromarray(np.full((120, 160, 3), 90, np.uint8)).save(photo)
    (folder / "IMG_0001.json").write_text(record.read_text())
    lines = tmp_path / "L.geojson"
    lines.write_text(json.dumps({"type": "FeatureCollection", "features": [{
        "type": "Feature", "properties": {"label": "bed"},
        "geometry": {"type": "LineString", "coordinates": [[10, 10], [100, 50]]}}]}))
    said = "assumed: CRS record EPSG:32630 but no georef.json: coordinates taken as the model frame"
    fix = 'write a georef.json beside it, e.g. {"crs": "EPSG:32630", "origin": [579000, 5912000, 0]}'

    run = run_cli(["register", cloud, photo, "--out", tmp_path / "r.json"], max_seconds=None)
    assert run.code == 1 and said in run.out and fix in run.out, run.out
    run = run_cli(["project", record, cloud, lines, "--out", tmp_path / "L3D.geojson"])
    assert run.code == 0 and said in run.out and fix in run.out, run.out
    run = run_cli(["workspace", "create", tmp_path / "ws", folder, "--no-photos"])
    assert run.code == 0 and said in run.out and fix in run.out, run.out


def test_sigterm_unwinds_a_command_as_ctrl_c_but_leaves_a_gui_to_the_default(monkeypatch):
    """Every command turns SIGTERM into an interrupt (exit 143, its files and
    locks given back); not demo --gui, whose Qt event loop would hold the
    Python handler back, so that `kill` would no longer close the window."""
    import signal

    from napari_imgreg.cli import demo, main

    seen = []

    def fake_run(args):
        seen.append(signal.getsignal(signal.SIGTERM))
        if not args.gui:
            signal.raise_signal(signal.SIGTERM)
        return 0

    monkeypatch.setattr(demo, "run", fake_run)
    before = signal.getsignal(signal.SIGTERM)
    assert main(["demo", "--out", "x"]) == 143
    assert main(["demo", "--gui"]) == 0
    assert seen[0] is not before and seen[1] is before
    assert signal.getsignal(signal.SIGTERM) is before
