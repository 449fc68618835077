"""The workbench's defaults and messages, decided without a viewer: the
filters' defaults (one source for a new session and Reset), the hint that
names the user's own settings before the photo, the outcome's words, the
control-point reader's messages for a GeoJSON or a long header, the model
formats a DSM-taking reader lists, the manual hint's and the automatic
declination's GUI wording, and the georef.json one folder up."""

from __future__ import annotations

import json
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from napari_imgreg.errors import InputError
from napari_imgreg.registration.filters import FilterParams
from napari_imgreg.registration.params import RegistrationParams


# ------------------------------------------------------------ 1. filters' defaults
def test_reset_filters_are_a_new_sessions_on_both_sides():
    new = RegistrationParams()
    assert new.photo_filters.wallis and new.render_filters.wallis  # a session starts with Wallis
    for which in ("photo", "render"):
        fresh = RegistrationParams.default_filters(which)
        assert fresh == getattr(new, f"{which}_filters")
        assert fresh != FilterParams()  # not the bare dataclass' (Wallis off)
    # A point cloud's (gradient and Wallis) for a point-cloud scene.
    cloud = SimpleNamespace(is_cloud=True)
    assert RegistrationParams.default_filters("photo", cloud) == \
        RegistrationParams.for_cloud().photo_filters
    # A fresh copy: editing it leaves the defaults alone.
    fresh = RegistrationParams.default_filters("render")
    fresh.wallis = False
    assert RegistrationParams().render_filters.wallis
    with pytest.raises(ValueError):
        RegistrationParams.default_filters("both")


# ------------------------------------------------------- 2. the user's settings first
def _trial(params, photo=48, render=295):
    metrics = {"points_photo": photo, "points_render": render, "feature_inliers": 11,
               "inliers_3d": 11, "inlier_ratio_2d": 1.0, "inlier_ratio_3d": 1.0}
    return SimpleNamespace(metrics=metrics, pose=None, origin="prior", verified=False,
                           correspondences=None, intrinsics=None, matcher="keypoints",
                           params=params, hints=[])


def _diagnose(params):
    from napari_imgreg.camera import Intrinsics, Pose
    from napari_imgreg.io.records import Sigma
    from napari_imgreg.prior import Prior
    from napari_imgreg.registration.explain import diagnose

    cam = Intrinsics(1024, 768, 777.0, 777.0, 511.5, 383.5)
    prior = Prior(cam, Pose.from_attitude(343.0, -4.0, 0.0, np.array([12.0, -80.0, 1.7])),
                  sigma=Sigma())
    photo = np.clip(np.random.default_rng(0).normal(120, 30, (768, 1024, 3)), 0, 255)
    t = _trial(params)
    return diagnose([t], t, "failed", prior, cam, photo.astype(np.uint8))


def test_a_raised_threshold_is_named_before_the_photo_is_blamed():
    params = RegistrationParams()
    params.features = replace(params.features, threshold_scale=3.0)
    first = _diagnose(params)[0]
    assert "(48 against 295)" in first
    threshold = first.index("threshold is ×3 (default ×1)")
    assert threshold < first.index("probably blurred")
    # With the defaults the photo is blamed as before.
    plain = _diagnose(RegistrationParams())[0]
    assert "probably blurred" in plain and "default" not in plain


def test_the_photos_own_filters_are_named_too():
    from napari_imgreg.registration.explain import fewer_points_settings

    params = RegistrationParams()
    params.photo_filters = FilterParams()  # Wallis off on the photo only (the old Reset)
    assert fewer_points_settings(params) == [
        "the photo's filters differ from the defaults (Wallis filter off)"]
    assert "Wallis filter off" in _diagnose(params)[0]
    assert fewer_points_settings(RegistrationParams.for_cloud()) == []
    assert fewer_points_settings(None) == []


def test_outcome_words_do_not_contradict_the_grade():
    from napari_imgreg.widgets._controller import outcome_text

    assert outcome_text("failed", "fair", 0.4) == \
        "not registered — best trial fair (uncertain), Q = 0.40"
    assert outcome_text("failed", "failed", -1.2) == "not registered — best trial failed, Q = -1.20"
    assert outcome_text("registered", "good", 0.9) == "registered — grade good, Q = 0.90"
    assert outcome_text("failed", "poor", -0.1, rich=True).startswith("<b>not registered</b>")
    for status, grade in (("failed", "fair"), ("failed", "poor"), ("registered", "excellent")):
        text = outcome_text(status, grade, 0.0)
        assert not text.startswith("failed") and grade in text


# ------------------------------------------------- 4. a GeoJSON, a long header
def test_a_geojson_given_as_pairs_is_named_in_one_short_line(tmp_path):
    from napari_imgreg.io.control_points import read_control_points

    features = [{"type": "Feature", "geometry": {"type": "LineString",
                                                 "coordinates": [[float(i), 2.0], [3.0, 4.0]]},
                 "properties": {"id": f"line{i}", "label": "mudstone"}} for i in range(20)]
    path = tmp_path / "IMG_0001.lines.geojson"
    path.write_text(json.dumps({"type": "FeatureCollection", "features": features}))
    with pytest.raises(InputError) as err:
        read_control_points(path)
    assert str(err.value) == f"{path}: a GeoJSON file, not a CSV table"
    other = tmp_path / "pairs.csv"
    other.write_text('  [{"photo_x": 1}]')
    with pytest.raises(InputError, match="a JSON file, not a CSV table$"):
        read_control_points(other)


def test_a_missing_column_quotes_a_short_header(tmp_path):
    from napari_imgreg.io._table_csv import HEADER_EXCERPT_CHARS, header_excerpt
    from napari_imgreg.io.control_points import read_control_points
    from napari_imgreg.io.orientation_tables import read_orientation_table

    names = [f"column_number_{i}" for i in range(60)]
    for path, read in ((tmp_path / "pairs.csv", read_control_points),
                       (tmp_path / "phone.csv", read_orientation_table)):
        path.write_text(",".join(names) + "\n" + ",".join("1" * 60) + "\n")
        with pytest.raises(InputError) as err:
            read(path)
        message = str(err.value)
        assert "missing column" in message and "column_number_0,column_number_1" in message
        quoted = message.split("header is: ", 1)[1].split(";", 1)[0]
        assert len(quoted) <= HEADER_EXCERPT_CHARS and quoted.endswith("…")
    assert header_excerpt(["photo_x", "x"]) == "photo_x,x"


# ------------------------------------------------------------ 5. model formats
def test_the_model_field_lists_a_dsm_too(tmp_path):
    from napari_imgreg.io.meshes import check_model_suffix, load_mesh

    photo = tmp_path / "IMG_0001.jpg"
    photo.write_bytes(b"\xff\xd8\xff")
    with pytest.raises(InputError) as err:
        check_model_suffix(photo, dsm=True)
    assert "a mesh: .obj" in str(err.value) and "a point cloud: .las" in str(err.value)
    assert "a DSM: .tif, .tiff, .asc" in str(err.value)
    # A mesh reader that takes no DSM does not offer one.
    with pytest.raises(InputError) as err:
        load_mesh(photo)
    assert "not a model format" in str(err.value) and "DSM" not in str(err.value)
    for ok in ("dsm.tif", "dem.asc", "outcrop.obj", "scan.laz", "missing.xyz"):
        target = tmp_path / ok
        if ok != "missing.xyz":
            target.write_bytes(b"")
        check_model_suffix(target, dsm=True)  # taken (or left to the reader)


# --------------------------------------------------------- 7. the manual hint
def test_the_manual_hint_keeps_the_cli_wording_and_the_gui_gets_its_own():
    from napari_imgreg.registration.manual import RUN_FROM_IT, RUN_FROM_IT_GUI, gui_hint

    hint = (f"115 of the photo's features agree with this pose: one Run from it {RUN_FROM_IT} "
            "refines it with them, from the clicks' pixel or two to a few tenths of a pixel.")
    # What RESULT.json and the command line keep (unchanged wording).
    assert "(the workbench's Run, or register --prior with this result)" in hint
    shown = gui_hint(hint)
    assert "--prior" not in shown and "register " not in shown
    assert RUN_FROM_IT_GUI in shown and shown.startswith("115 of the photo's features")
    assert gui_hint("Too few salient points.") == "Too few salient points."


# -------------------------------------------------- 8. the declination's inputs
def test_the_declination_message_has_gui_words_and_the_cli_keeps_its_own(tmp_path):
    from napari_imgreg.io.orientation_tables import read_orientation_table
    from napari_imgreg.orient.declination import gui_wording, survey_site

    table = tmp_path / "phone.csv"
    table.write_text("photo,trend_deg,plunge_deg,roll_deg\nA.jpg,10,-5,0\n")
    measured = read_orientation_table(table)  # no georef, no photos with GPS beside it
    with pytest.raises(InputError) as err:
        survey_site(measured)
    cli = str(err.value)
    assert "give --georef FILE, or the declination as a number (--declination DEG)" in cli
    gui = gui_wording(cli)
    assert "--" not in gui
    assert "Georef field" in gui and "untick Auto (WMM)" in gui and "Declination box" in gui
    assert gui_wording("no capture dates: give it as a number (--declination DEG)") == \
        "no capture dates: give it as a number (untick Auto (WMM) and type it in the " \
        "Declination box)"


def test_georef_json_is_found_beside_then_one_folder_up(tmp_path):
    from napari_imgreg.orient.declination import default_georef_path, georef_found_above

    scene = tmp_path / "S"
    tables = scene / "orient"
    tables.mkdir(parents=True)
    estimated = tables / "cameras.xml"
    estimated.write_text("<document/>")
    assert default_georef_path(estimated) is None
    above = scene / "georef.json"
    above.write_text("{}")
    assert default_georef_path(estimated) == above
    assert georef_found_above(above, estimated)
    beside = tables / "georef.json"
    beside.write_text("{}")
    assert default_georef_path(estimated) == beside  # beside first
    assert not georef_found_above(beside, estimated)
    # Beside any of the files before one folder up from the first.
    mesh_dir = tmp_path / "mesh"
    mesh_dir.mkdir()
    beside.unlink()
    other = mesh_dir / "georef.json"
    other.write_text("{}")
    assert default_georef_path(estimated, mesh_dir / "model.obj") == other
    assert default_georef_path(None, "", estimated) == above
    assert not georef_found_above(None, estimated)


def test_orient_cli_keeps_its_words_and_notes_a_georef_found_above(tmp_path, run_cli,
                                                                   dated_orient_tables):
    from napari_imgreg.geo import Georef

    est, meas = dated_orient_tables
    folder = est.parent
    argv = ["orient", est, meas, "--declination", "auto", "--out", tmp_path / "o.json"]
    run = run_cli(argv)
    assert run.code == 2
    assert run.line.endswith("give --georef FILE, or the declination as a number "
                             "(--declination DEG)")
    georef = folder.parent / "georef.json"
    Georef("EPSG:32721", [283_077.411822, 8_562_012.355651, 0.0]).save(georef)
    run = run_cli(argv)
    assert run.code == 0, run.err
    assert f"note: {georef} was found one folder up from the tables" in run.out
    assert json.loads((tmp_path / "o.json").read_text())["inputs"]["declination"]["georef"] \
        == str(georef)


def test_the_command_line_says_a_failed_photo_is_not_graded_as_registered(capsys):
    """`register` printed "FAILED — grade fair": a grade that reads like a
    verdict on a photo that has none. It now names the best trial's grade."""
    from pathlib import Path

    from napari_imgreg.camera import Pose
    from napari_imgreg.cli.register import _print_summary
    from napari_imgreg.registration.quality import outcome_words

    pose = Pose.from_attitude(0.0, 0.0, 0.0, np.array([0.0, -50.0, 2.0]))
    reg = SimpleNamespace(status="failed", grade="fair", q=0.41, pose=pose, metrics={},
                          trials=[1, 2], timings_s={"total": 3.0}, hints=[])
    _print_summary(reg, SimpleNamespace(pose=pose), Path("IMG_0009.jpg"), [])
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith("IMG_0009.jpg: FAILED — best trial fair (uncertain) (Q = +0.41)")
    assert outcome_words("failed", "excellent") == "best trial excellent (not verified)"
    assert outcome_words("registered", "excellent") == "grade excellent"


def test_fit_camera_2d_centres_the_box_and_fills_the_canvas():
    """The view the workbench and the Interpret dock frame a photo with: a
    1024 × 768 photo on a 600 × 800 canvas is limited by its height."""
    from napari_imgreg.widgets._layers import fit_camera_2d

    cam = SimpleNamespace(center=(5.0, 0.0, 0.0), zoom=1.0)
    fit_camera_2d(cam, (-0.5, -0.5), (767.5, 1023.5), (600, 800))
    assert cam.center == (5.0, 383.5, 511.5)  # the slice coordinate kept
    assert cam.zoom == pytest.approx(0.95 * 600 / 768)
    cam = SimpleNamespace(center=(0.0, 0.0), zoom=1.0)
    fit_camera_2d(cam, (0.0, 0.0), (100.0, 1000.0), (600, 800))
    assert cam.center == (50.0, 500.0) and cam.zoom == pytest.approx(0.95 * 800 / 1000)
