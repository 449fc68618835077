"""The generated sample outcrop: files, determinism and ground truth."""

from __future__ import annotations

import hashlib
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from napari_imgreg import Scene, render
from napari_imgreg.geo import DEM, Georef
from napari_imgreg.sample import (
    CACHE_MANIFEST,
    GENERATOR_VERSION,
    OutcropSpec,
    PhotoConditions,
    PhotoTruth,
    SceneTruth,
    dip_from_normal,
    generate_outcrop,
    load_truth,
    sample_scene,
)

SMALL = OutcropSpec.for_size("small")
# A coarse grid, tiny texture and photos: cheap to make twice.
CHEAP = OutcropSpec.for_size(
    "small", grid=(96, 90), texture_size=256, photo_size=(192, 144), n_photos=2, supersample=1,
    n_check_points=8,
)


@pytest.fixture(scope="session")
def small() -> Path:
    """The small scene (the cached one the other tests use; read only)."""
    return sample_scene("small")


@pytest.fixture(scope="session")
def cheap_pair(tmp_path_factory) -> tuple[Path, Path]:
    a = generate_outcrop(tmp_path_factory.mktemp("cheap_a"), "small", seed=0, spec=CHEAP)
    b = generate_outcrop(tmp_path_factory.mktemp("cheap_b"), "small", seed=0, spec=CHEAP)
    return a, b


def _obj_vertices(path: Path) -> np.ndarray:
    lines = [ln for ln in path.read_text().splitlines() if ln.startswith("v ")]
    return np.array([[float(v) for v in ln.split()[1:4]] for ln in lines])


def _vertex_hash(path: Path) -> str:
    return hashlib.sha256(_obj_vertices(path).tobytes()).hexdigest()


# ------------------------------------------------------------ determinism
def test_same_seed_same_geometry_and_records(cheap_pair, small):
    from napari_imgreg.sample.outcrop import build_geometry, quantize_vertices

    a, b = cheap_pair
    assert not list(a.glob(".*")), "temporary files left behind"
    assert _vertex_hash(a / "outcrop.obj") == _vertex_hash(b / "outcrop.obj")
    # The written small model is the generator's geometry for seed 0.
    g = build_geometry(SMALL, 0)
    quantize_vertices(g)
    np.testing.assert_array_equal(_obj_vertices(small / "outcrop.obj"), g.vertices)
    for name in ("IMG_0001.json", "IMG_0002.json", "IMG_0001.truth.json", "geology.json",
                 "truth_lines.geojson", "scene.json"):
        assert (a / name).read_text() == (b / name).read_text(), name
    assert (a / "IMG_0001.jpg").read_bytes() == (b / "IMG_0001.jpg").read_bytes()
    for name in ("IMG_0001.lines.geojson", "IMG_0002.lines.geojson", "orient/cameras.xml",
                 "orient/phone.csv", "orient/model.obj", "orient/truth.json"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


def test_other_seed_other_geometry(tmp_path):
    from napari_imgreg.sample.outcrop import build_geometry

    g0 = build_geometry(CHEAP, 0)
    g1 = build_geometry(CHEAP, 1)
    assert g0.X.shape == g1.X.shape
    assert not np.allclose(g0.X, g1.X)
    assert not np.array_equal(g0.geology.boundaries[:5], g1.geology.boundaries[:5])


# ---------------------------------------------------------------- the model
def test_manifest_lists_the_files(small):
    m = json.loads((small / "scene.json").read_text())
    assert m["seed"] == 0 and m["size"] == "small"
    assert m["generator_version"] == GENERATOR_VERSION
    for name in m["files"].values():
        assert (small / name).is_file(), name
    assert len(m["photos"]) == SMALL.n_photos
    for ph in m["photos"]:
        for name in ph.values():
            assert (small / name).is_file(), name
        assert ph["drawing"] == ph["image"].replace(".jpg", ".lines.geojson")
        assert ph["pairs"] == ph["image"].replace(".jpg", ".pairs.csv")
    assert m["examples"]["orient"] == {"estimated": "orient/cameras.xml",
                                       "measured": "orient/phone.csv",
                                       "model": "orient/model.obj", "truth": "orient/truth.json"}
    for name in m["examples"]["orient"].values():
        assert (small / name).is_file(), name
    assert m["survey_sun"]["azimuth_deg"] == SMALL.survey_sun_azimuth_deg
    assert [p.name for p in small.glob(".*")] == [CACHE_MANIFEST], "temporary files left behind"


def test_obj_reloads_with_texture(small):
    scene = Scene.load(small / "outcrop.obj")
    assert scene.has_texture and scene.uv is not None
    assert scene.texture.shape == (SMALL.texture_size, SMALL.texture_size, 3)
    assert 100_000 <= scene.n_faces <= 150_000
    assert scene.n_faces == json.loads((small / "scene.json").read_text())["n_triangles"]
    assert scene.uv.min() >= 0.0 and scene.uv.max() <= 1.0
    assert scene.georef is not None and scene.georef.crs == "EPSG:32630"
    # Normals point to the open air: the winding is consistent, the apron's
    # faces look up, the cliff's look south (toward the cameras).
    import trimesh

    assert trimesh.Trimesh(scene.vertices, scene.faces, process=False).is_winding_consistent
    n = scene.face_array("normals")
    centre = scene.vertices[scene.faces].mean(axis=1)
    assert (n[centre[:, 1] < -60.0, 2] > 0.8).all()
    steep = np.abs(n[:, 2]) < 0.5
    assert n[steep, 1].mean() < -0.7
    # The texture is the model's: a render sees rock colours, not a flat grey.
    t = load_truth(small / "IMG_0001.jpg")
    r = render(scene, t.intrinsics, t.pose, scale=0.25)
    assert r.coverage > 0.6
    assert r.rgb[r.mask].std() > 15


def test_georef_and_dem_cover_the_cameras(small):
    georef = Georef.load(small / "georef.json")
    assert georef.crs == "EPSG:32630"
    np.testing.assert_allclose(georef.origin, SMALL.origin)
    dem = DEM.load(small / "dem.tif")
    assert dem.crs == "EPSG:32630"
    assert dem.dx == pytest.approx(SMALL.dem_cell_m)
    for ph in sorted(small.glob("IMG_*.truth.json")):
        t = load_truth(ph)
        c = t.pose.center
        ground = dem.height_at(c[0] + georef.origin[0], c[1] + georef.origin[1])
        assert np.isfinite(ground)
        # The camera stands at eye height above the (gentle) apron.
        assert abs(c[2] + georef.origin[2] - SMALL.height_above_ground_m - ground) < 1.0
        p = t.prior["position"]
        assert np.isfinite(dem.height_at(p[0] + georef.origin[0], p[1] + georef.origin[1]))


# ------------------------------------------------------------ ground truth
def test_check_points_project_to_their_pixels(small):
    scene = Scene.load(small / "outcrop.obj")
    for ph in sorted(small.glob("IMG_*.jpg")):
        t = load_truth(ph)
        assert len(t.check_xyz) >= 20
        assert t.check_surface.count("rock") >= len(t.check_xyz) // 2
        uv = t.pose.project(t.intrinsics, t.check_xyz)
        assert np.abs(uv - t.check_pixels).max() < 0.01
        inside = ((t.check_pixels >= 0) & (t.check_pixels <= [t.intrinsics.width - 1,
                                                                t.intrinsics.height - 1]))
        assert inside.all()
        r = render(scene, t.intrinsics, t.pose)
        ij = np.round(t.check_pixels).astype(int)
        seen = r.xyz[ij[:, 1], ij[:, 0]]
        assert r.mask[ij[:, 1], ij[:, 0]].all()
        assert np.linalg.norm(seen - t.check_xyz, axis=1).max() < 0.05


def _fit_plane(points: np.ndarray) -> tuple[float, float, float]:
    """(dip, dip direction, rms) of the least-squares plane through points."""
    c = points.mean(axis=0)
    _, s, vt = np.linalg.svd(points - c, full_matrices=False)
    dip, ddir = dip_from_normal(vt[2])
    return dip, ddir, float(s[2] / math.sqrt(len(points)))


def _angle_diff(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def test_bedding_recovered_from_a_bed_boundary_trace(small):
    lines = json.loads((small / "truth_lines.geojson").read_text())
    assert lines["type"] == "FeatureCollection"
    groups: dict[tuple, list] = {}
    for f in lines["features"]:
        assert f["geometry"]["type"] == "LineString"
        p = f["properties"]
        if p["label"] == "bed_boundary":
            assert {p["below"], p["above"]} == {"sandstone", "mudstone"}
            groups.setdefault((p["boundary_index"], p["block"]), []).extend(f["geometry"]["coordinates"])
    assert len(groups) >= 6
    key = max(groups, key=lambda k: len(groups[k]))
    pts = np.array(groups[key])
    # The trace must be 3-D (relief, the bay), not a line: the plane is defined.
    assert np.ptp(pts[:, 1]) > 5.0
    dip, ddir, rms = _fit_plane(pts)
    assert dip == pytest.approx(SMALL.bedding_dip_deg, abs=1.0)
    assert _angle_diff(ddir, SMALL.bedding_dip_direction_deg) < 1.0
    geology = json.loads((small / "geology.json").read_text())
    assert geology["bedding"]["dip_deg"] == SMALL.bedding_dip_deg
    assert geology["bedding"]["dip_direction_deg"] == SMALL.bedding_dip_direction_deg
    h = np.array(geology["boundaries_h"])
    assert np.all(np.diff(h) > 0)


def test_fault_trace_lies_on_the_fault_plane(small):
    geology = json.loads((small / "geology.json").read_text())
    fault = geology["fault"]
    lines = json.loads((small / "truth_lines.geojson").read_text())
    pts = np.concatenate([f["geometry"]["coordinates"] for f in lines["features"]
                          if f["properties"]["label"] == "fault"])
    dist = (pts - np.array(fault["point"])) @ np.array(fault["normal"])
    assert np.abs(dist).max() < 1e-3
    assert fault["throw_m"] == SMALL.fault_throw_m
    assert geology["fault"]["h_shift"] > 0  # a normal fault brings younger beds down


def test_prior_is_noisy_but_sane(small):
    for ph in sorted(small.glob("IMG_*.jpg")):
        t = load_truth(ph)
        rec = json.loads(ph.with_suffix(".json").read_text())
        assert set(rec) == {"camera", "position", "orientation", "sigma"}
        assert set(rec["camera"]) == {"width", "height", "focal_length_mm",
                                      "sensor_width_mm", "sensor_height_mm"}
        prior_c = np.array([rec["position"][k] for k in "xyz"])
        o = rec["orientation"]
        from napari_imgreg import Pose

        prior = Pose.from_attitude(o["trend_deg"], o["plunge_deg"], o["roll_deg"], prior_c)
        err_pos = np.linalg.norm(prior_c - t.pose.center)
        err_rot = t.pose.rotation_error_deg(prior)
        assert 0.01 < err_pos < 25.0
        assert 0.01 < err_rot < 20.0
        # The truth is a geologist's photo: looking north-ish and slightly up.
        trend, plunge, roll = t.pose.attitude
        assert _angle_diff(trend, 0.0) <= SMALL.trend_range_deg + 1e-6
        assert SMALL.plunge_range_deg[0] - 1e-6 <= plunge <= SMALL.plunge_range_deg[1] + 1e-6
        assert abs(roll) <= SMALL.roll_range_deg + 1e-6
        assert 60.0 <= -t.pose.center[1] <= 160.0


def test_photos_have_phone_exif(small):
    from PIL import Image
    from PIL.ExifTags import IFD

    georef = Georef.load(small / "georef.json")
    for ph in sorted(small.glob("IMG_*.jpg")):
        t = load_truth(ph)
        with Image.open(ph) as im:
            assert im.size == SMALL.photo_size
            exif = im.getexif()
            sub = exif.get_ifd(IFD.Exif)
            gps = exif.get_ifd(IFD.GPSInfo)
            pixels = np.asarray(im.convert("RGB"))
        assert exif[271] == SMALL.camera_make
        assert float(sub[37386]) == pytest.approx(SMALL.focal_length_mm)
        assert sub[41989] == 26
        assert 60.0 < t.intrinsics.hfov_deg < 70.0

        def deg(v):
            return float(v[0]) + float(v[1]) / 60 + float(v[2]) / 3600

        lat = deg(gps[2]) * (1 if gps[1] == "N" else -1)
        lon = deg(gps[4]) * (1 if gps[3] == "E" else -1)
        local = georef.geodetic_to_local(lat, lon, float(gps[6]))
        np.testing.assert_allclose(local, t.prior["position"], atol=0.05)
        # A photo: sky at the top, varied colours, not saturated.
        top = pixels[:20].reshape(-1, 3).astype(float).mean(axis=0)
        assert top[2] > top[0]
        assert pixels.std() > 20 and (pixels == 255).mean() < 0.05


def test_exif_capture_time_gives_the_sun_the_photo_is_lit_by(small):
    from napari_imgreg.io.photos import load_photo
    from napari_imgreg.solar import sun_for_photo

    georef = Georef.load(small / "georef.json")
    for ph in sorted(small.glob("IMG_*.jpg")):
        t = load_truth(ph)
        direction, sun, notes = sun_for_photo(load_photo(ph).exif, georef, t.pose.center)
        assert sun is not None and sun.is_up and not notes  # offset and GPS time agree
        angle = np.degrees(np.arccos(np.clip(direction @ t.conditions.sun, -1.0, 1.0)))
        assert angle < 0.01


@pytest.mark.parametrize("azimuth, elevation", [(150.0, 40.0), (80.0, 15.0), (275.0, 12.0)])
def test_time_for_sun_finds_the_instant_of_a_reachable_sun(azimuth, elevation):
    from napari_imgreg.sample.photo import sun_vector
    from napari_imgreg.sample.suntime import time_for_sun
    from napari_imgreg.solar import sun_direction_local, sun_position

    georef = Georef("EPSG:32630", np.array([579000.0, 5912000.0, 350.0]))
    center = np.array([10.0, -90.0, 2.0])
    found = time_for_sun(sun_vector(azimuth, elevation), georef, center)
    assert found.miss_deg < 0.2
    assert found.azimuth_deg == pytest.approx(azimuth, abs=0.3)
    assert found.elevation_deg == pytest.approx(elevation, abs=0.3)
    # Independently: the sun at that instant is where it says.
    lat, lon, alt = georef.local_to_geodetic(center)
    again = sun_direction_local(sun_position(found.when, lat, lon, alt), georef, center)
    np.testing.assert_allclose(again, found.direction, atol=1e-6)
    assert found.when.utcoffset().total_seconds() == 0  # 1.8° W: nautical zone UTC+0


def test_load_truth_of_a_folder(small):
    truth = load_truth(small)
    assert isinstance(truth, SceneTruth)
    assert set(truth.photos) == {f"IMG_{k:04d}.jpg" for k in range(1, SMALL.n_photos + 1)}
    assert isinstance(truth.photos["IMG_0001.jpg"], PhotoTruth)
    assert truth.mesh.is_file()
    assert truth.geology["bedding"]["dip_deg"] == SMALL.bedding_dip_deg
    assert isinstance(load_truth(small / "IMG_0002.truth.json"), PhotoTruth)


# ------------------------------------------------------- example drawings
def _true_trace_pixels(truth_feature: dict, photo: PhotoTruth) -> np.ndarray:
    """A true 3D trace projected into a photo with its true pose, every 5 cm."""
    from napari_imgreg.sample.drawing import densify_polyline

    xyz = densify_polyline(np.asarray(truth_feature["geometry"]["coordinates"]), 20.0)
    return photo.pose.project(photo.intrinsics, xyz)


def test_each_photo_has_a_drawing_of_the_contacts_it_sees(small):
    """IMG_xxxx.lines.geojson is pixel GeoJSON the interpretation tools read:
    the true bed boundaries (labelled by the bed above) and the fault, as a
    geologist draws them: simplified, within a hand's wobble of the truth."""
    from napari_imgreg.interpret.files import read_interpretations

    truth = load_truth(small)
    for name, photo in truth.photos.items():
        drawn = read_interpretations(small / name.replace(".jpg", ".lines.geojson"))
        assert len(drawn) >= 20, name
        assert {d.label for d in drawn} == {"sandstone", "mudstone", "fault"}, name
        ids = [d.properties["id"] for d in drawn]
        assert len(set(ids)) == len(ids)
        n_vertices = []
        for d in drawn:
            assert d.geometry == "LineString"
            feature = truth.lines["features"][d.properties["truth"]]
            true_label = feature["properties"]["label"]
            assert (d.label == "fault") == (true_label == "fault")
            if d.label != "fault":
                assert d.label == feature["properties"]["above"] == d.properties["above"]
                assert d.properties["below"] == feature["properties"]["below"]
            # Every drawn vertex lies near the true trace's projection: the
            # 2 px simplification plus the ±1.5 px wobble (5 σ).
            true_px = _true_trace_pixels(feature, photo)
            gap = np.linalg.norm(d.pixels[:, None] - true_px[None], axis=2).min(axis=1)
            assert gap.max() < 2.0 + 5 * 1.5 * math.sqrt(2), (name, d.properties["id"])
            inside = (d.pixels > -8).all() and (d.pixels[:, 0] < photo.intrinsics.width + 8).all()
            assert inside and (d.pixels[:, 1] < photo.intrinsics.height + 8).all()
            n_vertices.append(len(d.pixels))
        # Simplified: many contacts look straight (2 vertices), some are bent.
        assert sum(n == 2 for n in n_vertices) >= len(drawn) // 4
        assert max(n_vertices) >= 4


def test_the_example_drawing_maps_onto_the_true_traces(small):
    """Projected with the photo's true pose, IMG_0002's drawing lies on the
    true traces (within the hand's wobble at ~90 m) and gives the bedding."""
    from scipy.spatial import cKDTree

    from napari_imgreg.interpret.files import read_interpretations
    from napari_imgreg.interpret.project import project_interpretations
    from napari_imgreg.sample.drawing import densify_polyline

    truth = load_truth(small)
    photo = truth.photos["IMG_0002.jpg"]
    scene = Scene.load(small / "outcrop.obj", cache=False)
    drawn = read_interpretations(small / "IMG_0002.lines.geojson")
    features = project_interpretations(scene, photo.intrinsics, photo.pose, drawn,
                                       source="IMG_0002.jpg")
    assert len(features) == len(drawn)
    distances = []
    for item, feature in zip(drawn, features):
        true_xyz = densify_polyline(
            np.asarray(truth.lines["features"][item.properties["truth"]]["geometry"]
                       ["coordinates"]), 50.0)
        for part in feature.parts:
            distances.append(cKDTree(true_xyz).query(part)[0])
    distances = np.concatenate(distances)
    assert np.median(distances) < 0.15 and np.percentile(distances, 95) < 0.6


def test_cli_sample_writes_the_drawings_and_the_orientation_example(tmp_path, monkeypatch,
                                                                     run_cli, no_sample_cache):
    """`napari-imgreg sample` writes what the docs run: the drawings beside
    the photos and orient/; written again, the user's files in orient/ stay."""
    import napari_imgreg.sample as sample

    def generate(out_dir, size="small", seed=0, spec=None):
        out = Path(out_dir)
        (out / "scene.json").write_text(json.dumps(
            {"generator": "napari_imgreg.sample", "size": size, "seed": seed}))
        (out / "IMG_0001.lines.geojson").write_text('{"type": "FeatureCollection"}')
        (out / "orient").mkdir()
        (out / "orient" / "cameras.xml").write_text(f"<document seed='{seed}'/>")
        return out

    monkeypatch.setattr(sample, "generate_outcrop", generate)
    out = tmp_path / "scene"
    assert run_cli(["sample", "--out", out]).code == 0
    assert (out / "IMG_0001.lines.geojson").is_file()
    assert (out / "orient" / "cameras.xml").is_file()
    (out / "orient" / "ORIENTATION.json").write_text("mine")
    assert run_cli(["sample", "--out", out]).code == 0
    assert (out / "orient" / "ORIENTATION.json").read_text() == "mine"
    # A file of the sample's that the user changed is not overwritten: refused.
    (out / "orient" / "cameras.xml").write_text("edited")
    run = run_cli(["sample", "--out", out])
    assert run.code == 2 and "orient/cameras.xml changed since the sample wrote it: " \
                              "refusing to overwrite your edits" in run.line, run.line
    assert (out / "orient" / "cameras.xml").read_text() == "edited"
    # Moved away, it is written again.
    (out / "orient" / "cameras.xml").rename(tmp_path / "my_cameras.xml")
    assert run_cli(["sample", "--out", out]).code == 0
    assert (out / "orient" / "cameras.xml").read_text() == "<document seed='0'/>"
    assert (out / "orient" / "ORIENTATION.json").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["my_cameras.xml", "scene"]


def test_a_copy_without_a_manifest_is_compared_with_the_fresh_scene(tmp_path):
    """A copy written before the manifest was kept: its files are compared with
    the new generation's; the one the user changed is named, new files are not."""
    from napari_imgreg.sample import _edited_sample_files

    old, fresh = tmp_path / "old", tmp_path / "fresh"
    for folder in (old, fresh):
        (folder / "orient").mkdir(parents=True)
        (folder / "IMG_0001.json").write_text('{"trend_deg": 345.3}')
        (folder / "orient" / "phone.csv").write_text("photo,trend_deg\n")
    (fresh / "IMG_0001.pairs.csv").write_text("name\n")  # new in this version
    assert _edited_sample_files(old, fresh) == []
    (old / "IMG_0001.json").write_text('{"trend_deg": 340.0}')
    assert _edited_sample_files(old, fresh) == ["IMG_0001.json"]
    assert _edited_sample_files(old) == []  # nothing to judge by


def test_the_cache_manifest_covers_the_files_of_sub_folders(tmp_path):
    """A cached scene's orient/ files are hashed too: a changed or missing one
    makes the cache entry fail its check (and be generated again)."""
    from napari_imgreg.sample import CACHE_MANIFEST, verify_sample_scene, write_cache_manifest

    (tmp_path / "scene.json").write_text(json.dumps(
        {"files": {"mesh": "m.obj"}, "photos": [{"drawing": "IMG_0001.lines.geojson"}],
         "examples": {"orient": {"estimated": "orient/cameras.xml"}}}))
    (tmp_path / "m.obj").write_text("v 0 0 0\n")
    (tmp_path / "IMG_0001.lines.geojson").write_text("{}")
    (tmp_path / "orient").mkdir()
    (tmp_path / "orient" / "cameras.xml").write_text("<document/>")
    manifest = write_cache_manifest(tmp_path)
    assert "orient/cameras.xml" in manifest["files"] and CACHE_MANIFEST not in manifest["files"]
    assert verify_sample_scene(tmp_path) is None
    (tmp_path / "orient" / "cameras.xml").write_text("<documenT/>")  # same size
    assert "orient/cameras.xml changed" in verify_sample_scene(tmp_path)
    (tmp_path / "orient" / "cameras.xml").unlink()
    assert "orient/cameras.xml is missing" in verify_sample_scene(tmp_path)


def test_the_orientation_example_is_oriented_by_orient(small):
    """orient/ holds the paper's 51-photo survey: orient recovers the rotation
    of truth.json, and model.obj is the wall in the model's frame."""
    from napari_imgreg.io.orientation_tables import read_orientation_table
    from napari_imgreg.orient import orient, rotation_error_deg

    folder = small / "orient"
    truth = json.loads((folder / "truth.json").read_text())
    estimated = read_orientation_table(folder / "cameras.xml")
    measured = read_orientation_table(folder / "phone.csv")
    assert len(estimated) == len(measured) == truth["n_photos"] == 51
    result = orient(estimated, measured)
    true_rotation = np.array(truth["world_from_model"])
    assert rotation_error_deg(result.rotation, true_rotation) < 1.0
    # The model: in world axes it is a wall ~27 m high (times the model's scale).
    wall = Scene.load(folder / "model.obj", cache=False).vertices.astype(np.float64)
    world = (wall - truth["model_offset"]) @ true_rotation.T / truth["model_scale"]
    assert np.ptp(world[:, 2]) == pytest.approx(27.0, abs=0.5)
    assert np.ptp(wall[:, 2]) / truth["model_scale"] > 40.0  # tilted in the model frame


# ------------------------------------------------------------- conditions
def test_conditions_strength_controls_the_light():
    rng = np.random.default_rng(0)
    same = PhotoConditions.from_rng(rng, 0.0)
    assert same.sun_azimuth_deg == pytest.approx(150.0, abs=1e-9)
    assert same.sun_elevation_deg == pytest.approx(40.0)
    assert same.wet_fraction == 0.0 or same.wet_fraction < 1e-9
    hard = [PhotoConditions.from_rng(np.random.default_rng(k), 1.0) for k in range(20)]
    for c in hard:
        # Raking: the sun skims the south-facing face from the east or west.
        assert 8.0 <= c.sun_elevation_deg <= 22.0
        assert min(_angle_diff(c.sun_azimuth_deg, 95.0), _angle_diff(c.sun_azimuth_deg, 265.0)) <= 15.0
        assert 80 <= c.jpeg_quality <= 90
    assert any(c.wet_fraction > 0 for c in hard)
    assert PhotoConditions.from_dict(hard[0].to_dict()) == hard[0]


# ------------------------------------------------------------------ cache
def test_sample_scene_caches_atomically(tmp_path, monkeypatch):
    import napari_imgreg.sample as sample

    calls = []

    def fake_generate(out_dir, size="small", seed=0, spec=None):
        calls.append(Path(out_dir))
        (Path(out_dir) / "scene.json").write_text("{}")
        return Path(out_dir)

    monkeypatch.setenv("NAPARI_IMGREG_CACHE", str(tmp_path))
    monkeypatch.setattr(sample, "generate_outcrop", fake_generate)
    first = sample_scene("small")
    assert first == tmp_path / f"outcrop-small-seed0-v{GENERATOR_VERSION}"
    assert (first / "scene.json").is_file()
    # Generated in a temporary folder beside the cache entry, then renamed.
    assert calls[0].parent == tmp_path and calls[0] != first
    assert sample_scene("small") == first
    assert len(calls) == 1
    assert [p.name for p in tmp_path.iterdir()] == [first.name]
    with pytest.raises(ValueError):
        sample_scene("huge")


def test_sample_scene_leaves_nothing_when_generation_fails(tmp_path, monkeypatch):
    import napari_imgreg.sample as sample

    def failing(out_dir, size="small", seed=0, spec=None):
        (Path(out_dir) / "outcrop.obj").write_text("half")
        raise RuntimeError("disk full")

    monkeypatch.setenv("NAPARI_IMGREG_CACHE", str(tmp_path))
    monkeypatch.setattr(sample, "generate_outcrop", failing)
    with pytest.raises(RuntimeError):
        sample_scene("small", seed=3)
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------- napari-imgreg sample
def _fake_outcrop(calls, interrupt=False):
    """A stand-in for generate_outcrop: a scene.json and a mesh, in no time."""

    def generate(out_dir, size="small", seed=0, spec=None):
        calls.append(Path(out_dir))
        (Path(out_dir) / "outcrop.obj").write_text("v 0 0 0\n")
        if interrupt:
            raise KeyboardInterrupt
        (Path(out_dir) / "scene.json").write_text(json.dumps(
            {"generator": "napari_imgreg.sample", "size": size, "seed": seed}))
        return Path(out_dir)

    return generate


def test_cli_sample_copies_the_cached_scene(tmp_path, monkeypatch, run_cli, small):
    """With the scene in the cache, `sample --out` copies it (the generation
    is deterministic) instead of generating it again: the same files, in a
    second instead of about twenty."""
    import napari_imgreg.sample as sample

    monkeypatch.setattr(sample, "generate_outcrop", lambda *a, **k: pytest.fail("generated"))
    out = tmp_path / "scene"
    run = run_cli(["sample", "--out", out])
    assert run.code == 0, run.err
    assert run.out.startswith(f"copying the small sample outcrop (seed 0) from the cache {small}")
    cached = sorted(p.relative_to(small) for p in small.rglob("*") if p.is_file())
    assert sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file()) == cached
    for rel in cached:
        if rel.name != CACHE_MANIFEST:
            assert (out / rel).read_bytes() == (small / rel).read_bytes(), rel
    assert sample.verify_sample_scene(out) is None  # its own manifest, for the next run
    assert [p.name for p in tmp_path.iterdir()] == ["scene"]
    # A damaged cache is not copied: the scene is generated.
    calls = []
    monkeypatch.setenv("NAPARI_IMGREG_CACHE", str(tmp_path / "cache"))
    damaged = tmp_path / "cache" / small.name
    shutil.copytree(small, damaged)
    (damaged / "outcrop.obj").write_text("v 0 0 0\n")
    monkeypatch.setattr(sample, "generate_outcrop", _fake_outcrop(calls))
    run = run_cli(["sample", "--out", tmp_path / "again"])
    assert run.code == 0 and run.out.startswith("generating the small sample outcrop") and calls


def test_cli_sample_refuses_a_folder_of_other_files(tmp_path, monkeypatch, run_cli,
                                                    no_sample_cache):
    import napari_imgreg.sample as sample

    calls = []
    monkeypatch.setattr(sample, "generate_outcrop", _fake_outcrop(calls))
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "outcrop.obj").write_text("my edited mesh")
    run = run_cli(["sample", "--out", folder])
    line = run.line
    assert run.code == 2 and str(folder) in line and "is not empty" in line, line
    assert run.out == "" and calls == []  # refused before the progress line and the work
    assert (folder / "outcrop.obj").read_text() == "my edited mesh"
    # Another seed's scene is not this one either.
    (folder / "outcrop.obj").unlink()
    (folder / "scene.json").write_text(json.dumps(
        {"generator": "napari_imgreg.sample", "size": "small", "seed": 1}))
    assert run_cli(["sample", "--out", folder]).code == 2 and calls == []


def test_cli_sample_writes_the_scene_into_place_whole(tmp_path, monkeypatch, run_cli,
                                                      no_sample_cache):
    import napari_imgreg.sample as sample

    calls = []
    monkeypatch.setattr(sample, "generate_outcrop", _fake_outcrop(calls))
    out = tmp_path / "scene"
    run = run_cli(["sample", "--out", out, "--seed", "7"])
    assert run.code == 0, run.err
    assert run.out.startswith("generating the small sample outcrop (seed 7)")
    assert calls[0].parent == tmp_path and calls[0] != out  # a sibling, renamed
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]
    # Again into its own earlier scene: replaced, and a file put beside it stays.
    (out / "results.csv").write_text("mine")
    assert run_cli(["sample", "--out", out, "--seed", "7"]).code == 0
    assert (out / "results.csv").read_text() == "mine" and (out / "scene.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]


def test_cli_sample_interrupted_leaves_no_half_scene(tmp_path, monkeypatch, run_cli,
                                                     no_sample_cache):
    import napari_imgreg.sample as sample

    monkeypatch.setattr(sample, "generate_outcrop", _fake_outcrop([], interrupt=True))
    run = run_cli(["sample", "--out", tmp_path / "scene"])
    assert run.code == 130
    assert list(tmp_path.iterdir()) == []


def test_survey_json_gives_the_scene_the_texture_sun(small):
    from napari_imgreg import Scene
    from napari_imgreg.sample.photo import sun_vector

    scene = Scene.load(small / "outcrop.obj")
    manifest = json.loads((small / "scene.json").read_text())
    sun = manifest["survey_sun"]
    expected = sun_vector(sun["azimuth_deg"], sun["elevation_deg"])
    # survey.json states the true azimuth; the scene turns it to grid north.
    assert np.degrees(np.arccos(np.clip(scene.survey_sun @ expected, -1, 1))) < 0.01


# ------------------------------------------------ rough true surface (issue 13)
def _vertical_face(rows: int = 200, cols: int = 60):
    """A vertical cliff y = 0, 40 m high and 30 m wide, facing −Y (grid, normals)."""
    z = np.linspace(0.0, 40.0, rows)
    x = np.linspace(-15.0, 15.0, cols)
    X = np.stack(np.broadcast_arrays(x[None, :], np.zeros((rows, cols)), z[:, None]), axis=-1)
    normals = np.broadcast_to(np.array([0.0, -1.0, 0.0]), X.shape).copy()
    return X.astype(float), normals


def test_rough_beds_stand_proud_by_the_drawn_amounts():
    from napari_imgreg.sample.rough import RoughSpec, rough_displacement

    X, n = _vertical_face()
    spec = RoughSpec(bedding_dip_deg=0.0, n_gullies=0, roughness_m=0.0, bed_edge_m=0.05)
    d = rough_displacement(X, n, spec, seed=1)
    assert d.min() >= 0.0 and d.max() <= 1.2 + 1e-9
    per_row = d[:, 0]
    np.testing.assert_allclose(d, per_row[:, None] + 0 * d)  # horizontal beds: rows are constant
    proud = per_row[per_row > 0.05]
    assert 0.3 < proud.size / per_row.size < 0.7  # sandstone and mudstone alternate
    assert np.percentile(proud, 90) >= 0.4 and np.percentile(proud, 10) >= 0.2  # edges rounded
    assert (per_row < 1e-9).mean() > 0.2  # recessed mudstone


def test_rough_gullies_cut_into_the_face_and_roughness_has_its_rms():
    from napari_imgreg.sample.rough import RoughSpec, rough_displacement

    X, n = _vertical_face()
    gullies = rough_displacement(X, n, RoughSpec(bed_relief_m=(0.0, 0.0), roughness_m=0.0,
                                                 n_gullies=3), seed=2)
    assert gullies.max() <= 1e-12 and gullies.min() <= -0.8
    rough = rough_displacement(X, n, RoughSpec(bed_relief_m=(0.0, 0.0), n_gullies=0,
                                               roughness_m=0.15), seed=2)
    assert rough.std() == pytest.approx(0.15, rel=1e-6)
    # Ground (normal up) gets a third of the face's roughness.
    ground_n = np.broadcast_to(np.array([0.0, 0.0, 1.0]), X.shape).copy()
    flat = rough_displacement(X, ground_n, RoughSpec(n_gullies=0, roughness_m=0.15), seed=2)
    assert flat.std() == pytest.approx(0.05, rel=1e-6)


def test_model_keeps_only_the_broad_relief():
    from napari_imgreg.sample.rough import RoughSpec, rough_displacement, smoothed

    X, n = _vertical_face()
    ramp = X[..., 2] * 0.1
    np.testing.assert_allclose(smoothed(ramp, X, 1.0)[20:-20], ramp[20:-20], atol=1e-9)
    d = rough_displacement(X, n, RoughSpec(bedding_dip_deg=0.0), seed=3)
    lost = d - smoothed(d, X, 1.0)
    assert lost.std() > 0.1  # bed edges and roughness are not in the model


def test_capture_time_only_where_the_sun_is_possible():
    from napari_imgreg.sample.rough import RoughSpec, capture_time

    georef = Georef("EPSG:32630", np.array([579000.0, 5912000.0, 350.0]))
    centre = np.array([0.0, -90.0, 2.0])
    spec = RoughSpec()
    possible = PhotoConditions(sun_azimuth_deg=250.0, sun_elevation_deg=25.0)
    moved, when = capture_time(possible, georef, centre, spec)
    assert when is not None and when.miss_deg <= spec.exif_max_miss_deg
    assert moved.sun_azimuth_deg == pytest.approx(250.0, abs=0.6)
    # 53° N: the sun never stands 40° high in the north.
    impossible = PhotoConditions(sun_azimuth_deg=0.0, sun_elevation_deg=40.0)
    same, none = capture_time(impossible, georef, centre, spec)
    assert none is None and same == impossible


def test_exif_without_a_capture_time():
    from PIL import Image
    from PIL.ExifTags import IFD

    from napari_imgreg.sample.photo import make_exif

    exif = Image.Exif()
    exif.load(make_exif("m", "p", 4.25, 26, None, 53.0, -1.8, 300.0, 160, 120))
    assert 0x9003 not in exif.get_ifd(IFD.Exif) and 0x0132 not in exif
    assert exif.get_ifd(IFD.Exif)[41989] == 26


def test_rough_conditions_rake_the_face_low_and_obliquely():
    from napari_imgreg.sample.noise import rng_for
    from napari_imgreg.sample.rough import RoughSpec, rough_conditions

    spec = RoughSpec()
    for k in range(20):
        c = rough_conditions(rng_for(5, k), spec, (170.0, 60.0))
        assert 10.0 <= c.sun_elevation_deg <= 25.0  # ROUGH_VERSION 2: a low sun
        off = abs((c.sun_azimuth_deg - 180.0 + 180.0) % 360.0 - 180.0)
        assert 45.0 <= off <= 80.0
        assert c.ambient == spec.photo_ambient and c.shadows


def test_rough_tier_version_2_is_the_harsher_one():
    """The cache key moved with the harsher defaults (issue 13: before's false verdicts)."""
    from napari_imgreg.sample.rough import ROUGH_VERSION, RoughSpec

    spec = RoughSpec()
    assert ROUGH_VERSION == "2"
    assert spec.model_resolution_m == 1.5 and spec.sun_elevation_deg == (10.0, 25.0)
    assert spec.grain_rms_slope == 0.45 and spec.roughness_m == 0.2
    assert spec.phone_strength == 0.9
    assert spec.bed_relief_m == (0.4, 1.2)  # beds as the issue describes them


def test_rough_scene_model_true_surface_and_check_points_over_the_frame(cheap_pair, tmp_path):
    from napari_imgreg.sample.rough import (
        RoughScene,
        RoughSpec,
        build_rough_scene,
        frame_check_points,
    )

    folder = cheap_pair[0]
    spec = RoughSpec(check_grid=(8, 6))
    out = build_rough_scene(folder, tmp_path / "rough", spec)
    model = Scene.load(out / "outcrop.obj")
    base = Scene.load(folder / "outcrop.obj")
    assert model.faces.shape == base.faces.shape
    true_v = np.load(out / "true_vertices.npy")
    moved = np.linalg.norm(true_v - base.vertices, axis=1)
    assert moved.max() > 0.4  # beds proud, gullies
    assert np.linalg.norm(true_v - model.vertices, axis=1).mean() > 0.01  # model is smoother
    manifest = json.loads((out / "scene.json").read_text())
    assert manifest["rough"]["relief_not_in_model_rms_m"] > 0.05
    assert (out / "survey.json").is_file()
    rough = RoughScene(out)
    truth = load_truth(folder / "IMG_0001.jpg")
    cps = frame_check_points(rough.scene, truth.intrinsics, truth.pose, spec.check_grid)
    pix = np.array([c["pixel"] for c in cps])
    xyz = np.array([c["xyz"] for c in cps])
    np.testing.assert_allclose(truth.pose.project(truth.intrinsics, xyz), pix, atol=1e-6)
    w, h = truth.intrinsics.width, truth.intrinsics.height
    assert (pix[:, 1] > 0.75 * h).any()  # the near ground at the bottom of the frame
    assert pix[:, 0].min() < 0.2 * w and pix[:, 0].max() > 0.8 * w
    assert {c["surface"] for c in cps} >= {"ground"}
    img = rough.photo(truth.intrinsics, truth.pose, PhotoConditions(sun_azimuth_deg=250.0,
                                                                   sun_elevation_deg=20.0), 1.0)
    assert img.shape == (h, w, 3) and img.std() > 10


def test_truth_pairs_are_check_points_both_images_show(sample_reference):
    from napari_imgreg.sample import truth_pairs

    ws, truth = sample_reference("IMG_0002.jpg")
    ps = ws.current
    photo_px, ref_px, xyz = truth_pairs(truth, ps.reference, ps.size, n=8, margin_px=20.0)
    assert photo_px.shape == ref_px.shape == (8, 2) and xyz.shape == (8, 3)
    # Each is where the true pose puts its check point, inside the margin ...
    np.testing.assert_allclose(photo_px, truth.pose.project(truth.intrinsics, xyz), atol=1e-9)
    assert np.all(photo_px >= 20) and np.all(photo_px <= np.array(ps.size) - 21)
    # ... and the reference shows that very point (not one in front of it).
    lifted, valid = ps.reference.lift(ref_px)
    assert valid.all() and np.linalg.norm(lifted - xyz, axis=1).max() < 0.05
    with pytest.raises(ValueError, match="wanted"):
        truth_pairs(truth, ps.reference, ps.size, n=10_000)


def test_each_photo_has_control_points_a_gnss_survey_would_give(small):
    """IMG_xxxx.pairs.csv: eight check points spread over the photo, in the
    georeference's map coordinates (to the mm), clicked within a few pixels
    of where the true pose puts them."""
    from napari_imgreg.io.control_points import read_control_points

    georef = Georef.load(small / "georef.json")
    for name in ("IMG_0001", "IMG_0002", "IMG_0003"):
        pairs = read_control_points(small / f"{name}.pairs.csv", min_pairs=8)
        truth = load_truth(small / f"{name}.jpg")
        assert pairs.frame == "crs" and pairs.names == [f"GCP{k}" for k in range(1, 9)]
        xyz = pairs.model_xyz(georef)
        # Each is one of the photo's check points ...
        gap = np.linalg.norm(xyz[:, None] - np.asarray(truth.check_xyz)[None], axis=2).min(axis=1)
        assert gap.max() < 0.002
        # ... clicked ±1 px off its true pixel, and spread over the frame.
        true_px = truth.pose.project(truth.intrinsics, xyz)
        assert np.linalg.norm(pairs.photo_px - true_px, axis=1).max() < 5.0
        spread = np.ptp(pairs.photo_px, axis=0) / [truth.intrinsics.width, truth.intrinsics.height]
        assert (spread > 0.6).all(), spread


def test_sample_scan_writes_a_laser_scan_of_the_same_outcrop(tmp_path, run_cli):
    """`sample --scan`: a geologist without a scan can try the point-cloud
    path; the scan lies on the sample's model, in its frame once read."""
    from napari_imgreg import Scene
    from napari_imgreg.geo import Georef
    from napari_imgreg.io.pointclouds import read_point_cloud

    out = tmp_path / "scene"
    run = run_cli(["sample", "--out", out, "--scan"], max_seconds=None)
    assert run.code == 0 and "laser scan of it written to" in run.out, run.out
    cloud = read_point_cloud(out / "scan.laz", georef=Georef.load(out / "georef.json"))
    assert len(cloud) > 300_000 and cloud.intensity is not None and cloud.rgb is None
    assert cloud.origin_subtracted is not None  # its CRS is the georeference's
    mesh = Scene.load(out / "outcrop.obj")
    lo, hi = mesh.bounds
    inside = np.all((cloud.xyz >= lo - 1.0) & (cloud.xyz <= hi + 1.0), axis=1)
    assert inside.mean() > 0.99
