"""Control-point files and ``register --pairs``: known answers from a synthetic
camera and from the sample's true pose, bad files refused in one line (exit 2)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.errors import InputError
from napari_imgreg.io.control_points import read_control_points, write_control_points
from napari_imgreg.registration.manual import MIN_PAIRS, registers, solve_manual
from napari_imgreg.sample import load_truth

# The conftest wall (wall.obj): 40 m × 20 m in the plane y = 0, seen from the south.
WALL_INTR = Intrinsics(1632, 1224, 1300.0, 1300.0, 815.5, 611.5)
WALL_TRUTH = Pose.from_attitude(5.0, -3.0, 1.5, np.array([19.0, -30.0, 10.0]))


def _wall_points(n: int, rng) -> np.ndarray:
    """Points on the wall (y = 0) with a few off it (targets on poles): not all coplanar."""
    pts = np.c_[rng.uniform(8, 32, n), np.zeros(n), rng.uniform(3, 17, n)]
    pts[::3, 1] = -rng.uniform(1, 4, len(pts[::3]))
    return pts


def _record(path, intr: Intrinsics, pose: Pose):
    """A sensor record near (not at) ``pose``: 3 m and 4° off."""
    trend, plunge, roll = pose.attitude
    c = pose.center + [3.0, -2.0, 0.5]
    path.write_text(json.dumps({
        "camera": {"width": intr.width, "height": intr.height, "fx": intr.fx, "fy": intr.fy,
                   "cx": intr.cx, "cy": intr.cy},
        "position": {"x": c[0], "y": c[1], "z": c[2]},
        "orientation": {"trend_deg": trend + 4.0, "plunge_deg": plunge - 2.0,
                        "roll_deg": roll}}))
    return path


@pytest.fixture
def wall_photo(tmp_path):
    """A photo file of the wall camera's size and its sensor record."""
    photo = tmp_path / "IMG_0001.png"
    Image.fromarray(np.full((WALL_INTR.height, WALL_INTR.width, 3), 90, np.uint8)).save(photo)
    return photo, _record(tmp_path / "IMG_0001.json", WALL_INTR, WALL_TRUTH)


def _register_from_pairs(run_cli, mesh, photo, record, tmp_path, photo_px, xyz, *options):
    """``register --pairs`` on the wall with these pairs (``photo_px`` None:
    their exact projection by the true pose): (run, RESULT.json dict, pose)."""
    px = WALL_TRUTH.project(WALL_INTR, xyz) if photo_px is None else photo_px
    pairs = tmp_path / "pairs.csv"
    write_control_points(pairs, px, xyz)
    out = tmp_path / "R.json"
    run = run_cli(["register", mesh, photo, "--prior", record, "--pairs", pairs, *options,
                   "--out", out], max_seconds=None)
    return (run, *_result(out))


def _result(path) -> tuple[dict, Pose]:
    data = json.loads(path.read_text())
    return data, Pose.from_dict(data["pose"])


# ------------------------------------------------------------------ file
def test_written_pairs_read_back_with_their_names(tmp_path):
    rng = np.random.default_rng(0)
    px, xyz = rng.uniform(0, 600, (5, 2)), rng.uniform(-50, 50, (5, 3))
    path = tmp_path / "pairs.csv"
    write_control_points(path, px, xyz, [f"GCP{k}" for k in range(5)])
    cp = read_control_points(path, min_pairs=MIN_PAIRS)
    np.testing.assert_allclose(cp.photo_px, px, atol=1e-6)
    np.testing.assert_allclose(cp.model_xyz(None), xyz, atol=1e-6)
    assert cp.names == [f"GCP{k}" for k in range(5)] and cp.rows == [2, 3, 4, 5, 6]
    assert cp.frame == "model"


def test_crs_coordinates_are_taken_into_the_model_frame_by_the_georeference(tmp_path):
    from napari_imgreg.geo import Georef

    georef = Georef("EPSG:32630", np.array([579000.0, 5912000.0, 350.0]))
    local = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [-7.0, 8.0, 9.0], [10.0, 0.5, 1.0]])
    enh = georef.local_to_crs(local)
    path = tmp_path / "gnss.csv"
    path.write_text("# GNSS targets\nname;photo_x;photo_y;easting;northing;elevation\n" + "".join(
        f"T{k};{10 * k};{20 + k};{e:.4f};{n:.4f};{h:.4f}\n" for k, (e, n, h) in enumerate(enh)))
    cp = read_control_points(path)
    assert cp.frame == "crs"
    np.testing.assert_allclose(cp.model_xyz(georef), local, atol=1e-4)
    with pytest.raises(InputError, match="gnss.csv: points are given as easting,northing"):
        cp.model_xyz(None)


def test_latitude_longitude_are_projected_and_the_elevation_kept(tmp_path):
    """WGS84 degrees through the georeference's CRS: the known answer is the
    projection pyproj gives for the same points the other way round."""
    from napari_imgreg.geo import Georef

    georef = Georef("EPSG:32630", np.array([579000.0, 5912000.0, 350.0]))
    local = np.array([[1.0, 2.0, 3.0], [40.0, 5.0, 6.0], [-70.0, 80.0, 9.0], [10.0, -50.5, 1.0]])
    lat, lon, elevation = georef.local_to_geodetic(local)
    path = tmp_path / "gnss.csv"
    path.write_text("Name,Photo_X,Photo_Y,Latitude,Longitude,Elevation\n" + "".join(
        f"T{k},{10 * k},{20 + k},{la:.9f},{lo:.9f},{h:.4f}\n"
        for k, (la, lo, h) in enumerate(zip(lat, lon, elevation))))
    cp = read_control_points(path)
    assert cp.frame == "geodetic" and cp.names == ["T0", "T1", "T2", "T3"]
    # 1e-9 degrees is 0.1 mm.
    np.testing.assert_allclose(cp.model_xyz(georef), local, atol=1e-3)
    with pytest.raises(InputError, match="gnss.csv: points are given as "
                                         "latitude,longitude,elevation but the model has no"):
        cp.model_xyz(None)


def test_latitude_and_longitude_under_another_header_are_refused(tmp_path):
    rows = "".join(f"{100 * k},{50 + 40 * k},{53.3512 + 1e-4 * k:.6f},{-1.8132 - 2e-4 * k:.6f},"
                   f"{390 + k}\n" for k in range(5))
    for header in ("photo_x,photo_y,x,y,z\n", "photo_x,photo_y,easting,northing,elevation\n"):
        path = tmp_path / "degrees.csv"
        path.write_text(header + rows)
        cp = read_control_points(path)
        with pytest.raises(InputError, match=r"degrees.csv: the control points' (x,y|easting,"
                                             r"northing) span only 0.0004 × 0.0008: are they "
                                             r"latitude and longitude\? Give those as latitude,"):
            cp.check_not_degrees()
    path.write_text(header + "".join(f"{100 * k},{50 + 40 * k},{3 + k},{-2 - k},{9}\n"
                                     for k in range(5)))
    read_control_points(path).check_not_degrees()  # metres: 4 m apart


def test_heights_in_another_datum_are_refused(tmp_path):
    """Points tens of metres straight above the surface (ellipsoidal heights)
    are refused; a target on a pole, or on the ground beside the model, is not."""
    rng = np.random.default_rng(4)
    surface = np.c_[rng.uniform(0, 100, 20000), rng.uniform(0, 100, 20000), np.zeros(20000)]
    on = np.c_[rng.uniform(10, 90, 6), rng.uniform(10, 90, 6), rng.uniform(0, 3, 6)]
    path = tmp_path / "pairs.csv"
    write_control_points(path, rng.uniform(0, 600, (6, 2)), on)
    cp = read_control_points(path)
    cp.check_heights(on, surface)  # on the surface, or up to 3 m above it
    cp.check_heights(on + [150.0, 0.0, 0.0], surface)  # beside the model: far sideways
    with pytest.raises(InputError, match=r"pairs.csv: the control points lie a median 4[7-9] m "
                                         r"above the model's surface \(6 of 6\): is their height "
                                         r"in another system \(GNSS ellipsoidal heights\)\? "
                                         r"The z column must be in the model's vertical datum"):
        cp.check_heights(on + [0.0, 0.0, 47.0], surface)
    cp.check_heights(on + [0.0, 0.0, 9.0], surface)  # within 10 m: not refused
    corners = np.array([[0.0, 0, 0], [100, 0, 0], [0, 100, 0], [100, 100, 0]])
    cp.check_heights(on + [0.0, 0.0, 47.0], corners)  # too sparse to stand for the surface


GOOD = "photo_x,photo_y,x,y,z\n1,2,3,4,5\n6,7,8,9,10\n11,12,13,14,15\n16,17,18,19,20\n"


@pytest.mark.parametrize("text, needle", [
    ("", "empty file"),
    ("photo_x,x,y,z\n1,2,3,4\n", "missing column photo_y"),
    ("photo_x,photo_y,x,y\n1,2,3,4\n", "missing column z"),
    ("photo_x,photo_y\n1,2\n", "missing columns x, y, z"),
    ("photo_x,photo_y,render_x,render_y\n1,2,3,4\n", "render_x,render_y (pixels of a render) "
                                                     "are not read"),
    ("photo_x,photo_y,x,y,z,easting,northing,elevation\n1,2,3,4,5,6,7,8\n",
     "both x,y,z and easting,northing,elevation"),
    ("photo_x,photo_y,easting,northing\n1,2,3,4\n", "missing column elevation"),
    ("photo_x,photo_y,latitude,longitude,ellipsoidal_height\n1,2,3,4,5\n",
     "latitude,longitude need an elevation column: the height in the model's vertical datum"),
    ("photo_x,photo_y,latitude,longitude,elevation\n1,2,579012.5,5911859.5,381\n",
     "row 2: latitude 579012 is outside [-90, 90] (latitude,longitude are WGS84 degrees; map "
     "coordinates go in easting,northing,elevation)"),
    ("photo_x,photo_y,latitude,longitude,elevation\n1,2,53.3,-181.5,381\n",
     "row 2: longitude -181.5 is outside [-180, 180]"),
    (GOOD + "21,22,abc,24,25\n", "row 6: x is not a number ('abc')"),
    (GOOD + "21,22,23,nan,25\n", "row 6: y is not a finite number ('nan')"),
    (GOOD + "21,22,23,24\n", "row 6: z is empty"),
    (GOOD + "6,7,8,9,10\n", "row 6: repeats row 3"),
    ("photo_x,photo_y,x,y,z,name\n1,2,3,4,5,A\n6,7,8,9,10,A\n", "row 3: name 'A' appears twice "
                                                               "(first at row 2)"),
    ("photo_x,photo_y,x,y,z\n1,2,3,4,5\n6,7,8,9,10\n11,12,13,14,15\n", "3 pairs: need at least 4"),
    ("photo_x,photo_y,x,y,z\n", "no pairs after the header: need at least 4"),
])
def test_a_bad_file_is_one_line_naming_the_row(tmp_path, text, needle):
    path = tmp_path / "pairs.csv"
    path.write_text(text)
    with pytest.raises(InputError) as info:
        read_control_points(path, min_pairs=MIN_PAIRS)
    message = str(info.value)
    assert "\n" not in message and message.startswith(f"{path}: ") and needle in message, message


def test_a_photo_pixel_outside_the_photo_is_refused(tmp_path):
    path = tmp_path / "pairs.csv"
    path.write_text(GOOD.replace("16,17", "699.5,17"))
    cp = read_control_points(path)
    cp.check_inside(700, 480)  # the last pixel's edge
    with pytest.raises(InputError, match=r"row 5: photo pixel \(699.5, 17\) is outside the "
                                         r"640×480 photo"):
        cp.check_inside(640, 480)


# --------------------------------------------------------- the command
def test_register_from_exact_pairs_recovers_the_true_pose(wall_mesh, wall_photo, tmp_path,
                                                          run_cli):
    photo, record = wall_photo
    rng = np.random.default_rng(1)
    xyz = _wall_points(10, rng)
    run, result, pose = _register_from_pairs(run_cli, wall_mesh, photo, record, tmp_path,
                                             None, xyz)
    assert pose.rotation_error_deg(WALL_TRUTH) < 0.01
    assert np.linalg.norm(pose.center - WALL_TRUTH.center) < 0.01
    # Ten exact pairs: the expected error is the click noise's alone, small.
    assert result["status"] == "registered" and run.code == 0, run.out
    assert result["uncertainty"]["basis"] == "control points"
    assert result["metrics"]["control_points"] == 10
    assert result["metrics"]["control_point_inliers"] == 10
    assert len(result["trials"]) == 1 and result["trials"][0]["origin"] == "manual"
    assert result["best_trial"] == 0 and "estimated" not in result["camera"]
    assert "REGISTERED" in run.out and "control points: 10 of 10 agree" in run.out
    # The file is the same contract as an automatic result's.
    from napari_imgreg.registration.result_file import load_registration

    assert load_registration(tmp_path / "R.json").status == "registered"


def test_noisy_pairs_give_an_error_within_twice_the_reported_uncertainty(
        wall_mesh, wall_photo, tmp_path, run_cli):
    photo, record = wall_photo
    rng = np.random.default_rng(2)
    xyz = _wall_points(12, rng)
    clicked = WALL_TRUTH.project(WALL_INTR, xyz) + rng.normal(0, 1.5, (12, 2))
    _, result, pose = _register_from_pairs(run_cli, wall_mesh, photo, record, tmp_path,
                                           clicked, xyz)
    unc = result["uncertainty"]
    rotation = pose.rotation_error_deg(WALL_TRUTH)
    position = np.linalg.norm(pose.center - WALL_TRUTH.center)
    assert 0 < rotation <= 2 * unc["rotation_deg"], (rotation, unc)
    assert 0 < position <= 2 * unc["position_m"], (position, unc)


def test_the_focal_length_is_solved_and_marked_estimated(wall_mesh, tmp_path, run_cli):
    # The record's focal length 30 % short; the pairs fix the true one.
    photo = tmp_path / "IMG_0002.png"
    Image.fromarray(np.full((WALL_INTR.height, WALL_INTR.width, 3), 90, np.uint8)).save(photo)
    wrong = Intrinsics(1632, 1224, 910.0, 910.0, 815.5, 611.5)
    record = _record(tmp_path / "IMG_0002.json", wrong, WALL_TRUTH)
    rng = np.random.default_rng(3)
    xyz = _wall_points(12, rng)
    run, result, pose = _register_from_pairs(run_cli, wall_mesh, photo, record, tmp_path,
                                             None, xyz, "--solve-focal")
    assert result["camera"]["estimated"] == ["fx", "fy"]
    assert result["camera"]["fx"] == pytest.approx(WALL_INTR.fx, rel=1e-4)
    assert "focal_px" in result["uncertainty"]
    assert pose.rotation_error_deg(WALL_TRUTH) < 0.01
    assert "focal length solved" in run.out


def test_the_sample_photo_registers_from_its_check_points(tmp_path, run_cli):
    """The sample's true pose from pairs on its textured model, scored verified."""
    from napari_imgreg.sample import load_truth, sample_scene

    folder = sample_scene("small")
    truth = load_truth(folder / "IMG_0002.jpg")
    photo_px = truth.pose.project(truth.intrinsics, truth.check_xyz)
    # Given as a GNSS survey would give them: in the georeference's CRS.
    from napari_imgreg.geo import Georef

    enh = Georef.load(folder / "georef.json").local_to_crs(truth.check_xyz)
    pairs = tmp_path / "gnss.csv"
    pairs.write_text("photo_x,photo_y,easting,northing,elevation\n" + "".join(
        f"{x:.4f},{y:.4f},{e:.4f},{n:.4f},{h:.4f}\n" for (x, y), (e, n, h) in zip(photo_px, enh)))
    out = tmp_path / "R.json"
    run = run_cli(["register", folder / "outcrop.obj", folder / "IMG_0002.jpg",
                   "--dem", folder / "dem.tif", "--pairs", pairs, "--out", out],
                  max_seconds=None)
    result, pose = _result(out)
    assert run.code == 0 and result["status"] == "registered", run.out
    assert pose.rotation_error_deg(truth.pose) < 0.01
    assert np.linalg.norm(pose.center - truth.pose.center) < 0.01
    assert result["trials"][0]["verified"] and result["quality"]["grade"] in ("excellent", "good")
    # The photo's matches agree with the pose: the hint says how to refine it with them.
    assert "one Run from it" in result["quality"]["hints"][0]
    # and gives no advice meant for an automatic trial (stricter matching, ...).
    assert len(result["quality"]["hints"]) == 1, result["quality"]["hints"]



def test_another_photos_pairs_are_named_and_their_pose_called_into_question(tmp_path, run_cli):
    """IMG_0001's surveyed pairs given for IMG_0002: they solve IMG_0001's pose
    (24 m from IMG_0002's record) and agree with themselves perfectly. The
    command line warns by the file's name, and the result's first hint says
    the pose is far from the record and unconfirmed by the photo."""
    from napari_imgreg.sample import sample_scene

    folder = sample_scene("small")
    out = tmp_path / "R.json"
    run = run_cli(["register", folder / "outcrop.obj", folder / "IMG_0002.jpg",
                   "--dem", folder / "dem.tif", "--pairs", folder / "IMG_0001.pairs.csv",
                   "--out", out], max_seconds=None)
    assert run.out.startswith("warning: IMG_0001.pairs.csv is named for IMG_0001.jpg, "
                              "not for IMG_0002.jpg"), run.out
    result, _ = _result(out)
    first = result["quality"]["hints"][0]
    assert first.startswith("The control points' pose differs from the photo's sensor record "
                            "in the camera position by 2"), first
    assert "check that the pairs are this photo's" in first
    # Its own pairs: no such warning or hint.
    run = run_cli(["register", folder / "outcrop.obj", folder / "IMG_0002.jpg",
                   "--dem", folder / "dem.tif", "--pairs", folder / "IMG_0002.pairs.csv",
                   "--out", out], max_seconds=None)
    assert "warning" not in run.out and "sensor record" not in run.out

def test_pairs_in_one_corner_are_uncertain_and_never_graded_good(tmp_path, run_cli):
    """Exact pairs bunched in a corner of the photo: the photo's matches agree
    with the pose, but the pairs' expected error is large, so the result is
    not registered and its grade is not good or excellent (issue 13)."""
    from napari_imgreg.sample import sample_scene

    folder = sample_scene("small")
    truth = load_truth(folder / "IMG_0002.jpg")
    photo_px = truth.pose.project(truth.intrinsics, truth.check_xyz)
    corner = np.argsort(np.hypot(*photo_px.T))[:6]
    pairs = tmp_path / "corner.csv"
    write_control_points(pairs, photo_px[corner], truth.check_xyz[corner])
    out = tmp_path / "R.json"
    run = run_cli(["register", folder / "outcrop.obj", folder / "IMG_0002.jpg",
                   "--dem", folder / "dem.tif", "--pairs", pairs, "--out", out],
                  max_seconds=None)
    result, _ = _result(out)
    limit = 4.0 * truth.intrinsics.width / 1632.0
    assert result["uncertainty"]["basis"] == "control points"
    assert result["uncertainty"]["reprojection_px"] >= limit
    assert run.code == 1 and result["status"] == "failed"
    assert result["quality"]["grade"] not in ("good", "excellent"), result["quality"]
    assert "leave the pose uncertain" in result["quality"]["hints"][0]


def test_pairs_on_a_line_fail_with_the_reason_exit_1(wall_mesh, wall_photo, tmp_path, run_cli):
    photo, record = wall_photo
    xyz = np.c_[np.linspace(5, 35, 6), np.zeros(6), np.full(6, 10.0)]
    run, result, _ = _register_from_pairs(run_cli, wall_mesh, photo, record, tmp_path, None, xyz)
    assert run.code == 1 and result["status"] == "failed" and result["trials"] == []
    assert "on a line" in result["quality"]["hints"][0]


@pytest.mark.parametrize("case, needle", [
    ("missing", "pairs.csv: no such file"),
    ("few", "pairs.csv: 3 pairs: need at least 4"),
    ("nan", "pairs.csv: row 3: photo_y is not a finite number"),
    ("outside", "pairs.csv: row 2: photo pixel (1700, 10) is outside the 1632×1224 photo"),
    ("focal", "pairs.csv: 5 pairs: --solve-focal needs at least 6"),
    ("focal_alone", "--solve-focal needs --pairs"),
    ("crs", "pairs.csv: points are given as easting,northing,elevation but the model has no "
            "georeference"),
    ("out_is_pairs", "refusing to overwrite the input control points"),
])
def test_bad_pairs_are_one_line_exit_2(wall_mesh, wall_photo, tmp_path, run_cli, case, needle):
    photo, record = wall_photo
    pairs = tmp_path / "pairs.csv"
    rows = [f"{10 + 40 * k},{10 + 30 * k},{5 + k},0,{3 + 2 * k}" for k in range(5)]
    texts = {
        "few": rows[:3], "nan": [rows[0], "1,nan,2,3,4", *rows[2:]],
        "outside": ["1700,10,1,0,1", *rows[1:]], "focal": rows,
    }
    header = "photo_x,photo_y,x,y,z\n"
    if case == "crs":
        pairs.write_text("photo_x,photo_y,easting,northing,elevation\n" + "\n".join(rows) + "\n")
    elif case in texts:
        pairs.write_text(header + "\n".join(texts[case]) + "\n")
    elif case != "missing":
        pairs.write_text(header + "\n".join(rows) + "\n")
    out = pairs if case == "out_is_pairs" else tmp_path / "R.json"
    argv = ["register", wall_mesh, photo, "--prior", record, "--out", out]
    if case != "focal_alone":
        argv += ["--pairs", pairs]
    if case in ("focal", "focal_alone"):
        argv += ["--solve-focal"]
    run = run_cli(argv)
    assert run.code == 2 and needle in run.line, run.err
    assert case == "out_is_pairs" or not (tmp_path / "R.json").exists()


def test_registers_is_the_rule_the_workspace_applies():
    rng = np.random.default_rng(4)
    xyz = _wall_points(8, rng)
    good = solve_manual(WALL_INTR, WALL_TRUTH.project(WALL_INTR, xyz), xyz)
    assert good.ok and registers(good)
    # Four pairs close together, clicked 3 px off: solved, but it does not fix the pose.
    near = xyz[:4] * 0.05 + [19, 0, 9]
    loose = solve_manual(WALL_INTR, WALL_TRUTH.project(WALL_INTR, near)
                         + rng.normal(0, 3, (4, 2)), near)
    assert not registers(loose)


def test_loaded_pairs_keep_their_points_in_a_saved_workspace(tmp_path, sample_reference):
    from napari_imgreg.workspace import Workspace

    ws, truth = sample_reference("IMG_0001.jpg")
    xyz = truth.check_xyz[:6] + [0.0, -2.0, 0.0]  # 2 m in front of the rock: off the model
    pairs = tmp_path / "pairs.csv"
    write_control_points(pairs, truth.pose.project(truth.intrinsics, xyz), xyz)
    assert ws.load_pairs(pairs) == 6
    np.testing.assert_allclose(ws.pair_points_3d()[0], xyz, atol=1e-6)
    ws.save(tmp_path / "campaign.imgreg")
    ws.detach()
    again = Workspace.open(tmp_path / "campaign.imgreg")
    try:
        np.testing.assert_allclose(again.pair_points_3d()[0], xyz, atol=1e-6)
        assert again.pairs_with_own_point().all()
        written, left_out = again.save_pairs(tmp_path / "again.csv")
        assert (written, left_out) == (6, 0)
        np.testing.assert_allclose(read_control_points(tmp_path / "again.csv").xyz, xyz,
                                   atol=1e-5)
    finally:
        again.detach()


def test_pair_names_follow_their_pairs_through_edits_and_a_saved_workspace(
        tmp_path, sample_reference):
    from napari_imgreg.workspace import Workspace

    ws, truth = sample_reference("IMG_0001.jpg")
    xyz = truth.check_xyz[:6]
    names = [f"GCP{k}" for k in (3, 5, 8, 11, 12, 20)]
    pairs = tmp_path / "pairs.csv"
    write_control_points(pairs, truth.pose.project(truth.intrinsics, xyz), xyz, names)
    ws.load_pairs(pairs)
    assert ws.pair_names() == names
    ws.remove_pair(1)  # GCP5 goes, with its name
    assert ws.pair_names() == ["GCP3", "GCP8", "GCP11", "GCP12", "GCP20"]
    photo, ref = ws.current.photo_points_px.copy(), ws.current.reference_points_px.copy()
    ref[0] += 3.0  # its reference point dragged: the model point under it, the same name
    ws.set_pair_points(photo, ref)
    assert ws.pair_names()[0] == "GCP3" and not ws.pairs_with_own_point()[0]
    ws.add_pair([100.0, 100.0], [120.0, 110.0])  # a clicked pair has no name
    assert ws.pair_names() == ["GCP3", "GCP8", "GCP11", "GCP12", "GCP20", ""]
    ws.save(tmp_path / "campaign.imgreg")
    ws.detach()
    again = Workspace.open(tmp_path / "campaign.imgreg")
    try:
        assert again.pair_names() == ["GCP3", "GCP8", "GCP11", "GCP12", "GCP20", ""]
        again.save_pairs(tmp_path / "again.csv")
        written = read_control_points(tmp_path / "again.csv").names
        # A clicked pair (the 6th, when it is on the model) has no name.
        assert written[:5] == ["GCP3", "GCP8", "GCP11", "GCP12", "GCP20"]
        assert written[5:] in ([], [""])
    finally:
        again.detach()


def test_workspace_pairs_registers_a_campaign_photo_from_control_points(tmp_path, run_cli):
    """``workspace pairs``: the Manual tab's Load pairs… and Solve on the command line;
    the pose and the pairs are saved in the workspace."""
    import shutil

    from napari_imgreg.sample import load_truth, sample_scene
    from napari_imgreg.workspace import Workspace

    folder = sample_scene("small")
    scene = tmp_path / "scene"
    scene.mkdir()
    for name in ("outcrop.obj", "outcrop.mtl", "outcrop_texture.jpg", "dem.tif", "georef.json",
                 "IMG_0001.jpg", "IMG_0001.json", "IMG_0002.jpg", "IMG_0002.json"):
        shutil.copy(folder / name, scene / name)
    ws_folder = tmp_path / "campaign.imgreg"
    assert run_cli(["workspace", "create", ws_folder, scene], max_seconds=None).code == 0
    truth = load_truth(folder / "IMG_0002.jpg")
    rng = np.random.default_rng(4)
    px = truth.pose.project(truth.intrinsics, truth.check_xyz)
    inside = np.flatnonzero(np.all((px > 10) & (px < [1014, 758]), axis=1))
    pick = inside[np.linspace(0, len(inside) - 1, 10).round().astype(int)]
    xyz = truth.check_xyz[pick]
    clicked = px[pick] + rng.normal(0, 1.0, (10, 2))
    pairs = tmp_path / "targets.csv"
    write_control_points(pairs, clicked, xyz, [f"T{k}" for k in range(len(xyz))])

    run = run_cli(["workspace", "pairs", ws_folder, "IMG_0002.jpg", pairs], max_seconds=None)
    assert run.code == 0, run.out + run.err
    assert "IMG_0002.jpg: registered from 10 of 10 control points" in run.out
    again = Workspace.open(ws_folder, autosave=False)
    try:
        ps = next(p for p in again.photos if p.name == "IMG_0002.jpg")
        assert again.photo_status(ps) == "registered"
        assert ps.pose.rotation_error_deg(truth.pose) < 0.1
        assert again.pair_names(ps) == [f"T{k}" for k in range(len(xyz))]
    finally:
        again.detach()
    # A bad file: one line, exit 2, nothing changed.
    bad = tmp_path / "bad.csv"
    bad.write_text("photo_x,photo_y,x,y\n1,2,3,4\n")
    run = run_cli(["workspace", "pairs", ws_folder, "IMG_0001.jpg", bad])
    assert run.code == 2 and "bad.csv: missing column z" in run.line, run.err


def test_points_far_from_the_model_are_refused_as_swapped_or_another_crs(
        tmp_path, run_cli, sample_reference):
    """Northing and easting swapped, or latitude and longitude given as easting and
    northing: thousands of km from the model, which no pose fits. One line, exit 2."""
    from napari_imgreg.geo import Georef
    from napari_imgreg.sample import sample_scene

    folder = sample_scene("small")
    ws, truth = sample_reference("IMG_0002.jpg")
    photo_px = truth.pose.project(truth.intrinsics, truth.check_xyz[:8])
    enh = Georef.load(folder / "georef.json").local_to_crs(truth.check_xyz[:8])
    swapped = tmp_path / "swapped.csv"
    swapped.write_text("photo_x,photo_y,easting,northing,elevation\n" + "".join(
        f"{x:.3f},{y:.3f},{n:.3f},{e:.3f},{h:.3f}\n" for (x, y), (e, n, h) in zip(photo_px, enh)))
    run = run_cli(["register", folder / "outcrop.obj", folder / "IMG_0002.jpg",
                   "--pairs", swapped, "--out", tmp_path / "R.json"], max_seconds=None)
    assert run.code == 2 and not (tmp_path / "R.json").exists()
    assert "swapped.csv: the control points lie a median 75" in run.line
    assert "are columns swapped, or the coordinates of another system?" in run.line
    assert "in EPSG:32630's coordinates (not latitude and longitude)" in run.line
    # Points a few metres off the model (targets on poles) are not far.
    near = tmp_path / "near.csv"
    write_control_points(near, photo_px, truth.check_xyz[:8] + [0.0, -3.0, 0.0])
    assert ws.load_pairs(near) == 8
    with pytest.raises(InputError, match="lie a median 75.. km from the model"):
        ws.load_pairs(swapped)
    # Heights in another datum (ellipsoidal, ~45 m above the model's here).
    ellipsoidal = tmp_path / "ellipsoidal.csv"
    write_control_points(ellipsoidal, photo_px, truth.check_xyz[:8] + [0.0, 0.0, 45.0])
    with pytest.raises(InputError, match=r"ellipsoidal.csv: the control points lie a median "
                                         r"\d\d m above the model's surface \(8 of 8\)"):
        ws.load_pairs(ellipsoidal)
    assert len(ws.current.photo_points_px) == 8  # the pairs stay as they were
