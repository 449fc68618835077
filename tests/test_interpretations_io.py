"""Interpretation files and the ``project`` / ``measure`` commands."""

from __future__ import annotations

import argparse
import csv
import json
import sys

import numpy as np
import pytest
import trimesh
from interp_scenes import camera, true_trace, wall_scene

from napari_imgreg.errors import InputError
from napari_imgreg.geo import Georef
from napari_imgreg.interpret.project import Interpretation, measure_features, project_interpretations
from napari_imgreg.interpret.files import (
    MEASUREMENT_COLUMNS,
    export_features,
    features_to_geojson,
    read_features_geojson,
    read_interpretations,
    write_features_geojson,
    write_interpretations,
    write_measurements_csv,
)

GEOREF = Georef("EPSG:32630", np.array([579000.0, 5912000.0, 350.0]))


def run_cli(argv: list[str]) -> int:
    """``napari-imgreg project|measure`` as the main command runs them."""
    from napari_imgreg.cli.interpret import add_parsers

    parser = argparse.ArgumentParser(prog="napari-imgreg")
    add_parsers(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except InputError as exc:  # what cli.main does with bad input
        print(f"napari-imgreg {args.command}: error: {exc}", file=sys.stderr)
        return 2


@pytest.fixture(scope="module")
def projected():
    """A bed trace (split by a slot), an occluded line and a facet, projected."""
    wall, X = wall_scene(hole_x=(10.0, 13.0))
    intr, pose = camera()
    (trace,) = [t for t in true_trace(X, 12.0, 200.0) if len(t) > 20]
    items = [
        Interpretation("LineString", pose.project(intr, trace), {"label": "sandstone", "bed": 3}),
        Interpretation("Polygon", np.array([[500.0, 450], [700, 450], [700, 600], [500, 600]]),
                       {"label": "mudstone"}),
        Interpretation("LineString", np.array([[10.0, 5.0], [300.0, 5.0]]), {"label": "fault"}),
    ]
    features = project_interpretations(wall, intr, pose, items, source="IMG_0007.jpg")
    return wall, X, intr, pose, items, features


def test_pixel_geojson_round_trip(tmp_path, projected):
    *_, items, _ = projected
    path = tmp_path / "lines.geojson"
    write_interpretations(path, items)
    doc = json.loads(path.read_text())
    assert doc["type"] == "FeatureCollection"
    poly = doc["features"][1]["geometry"]
    assert poly["type"] == "Polygon" and poly["coordinates"][0][0] == poly["coordinates"][0][-1]
    back = read_interpretations(path)
    assert [b.geometry for b in back] == ["LineString", "Polygon", "LineString"]
    for a, b in zip(items, back):
        assert np.allclose(a.pixels, b.pixels, atol=1e-3)
        assert b.label == a.label and b.properties["color"] == a.color
    assert back[0].properties["bed"] == 3


@pytest.mark.parametrize("content,problem", [
    ("{not json", "invalid JSON"),
    ('{"type": "Feature"}', "geometry"),
    ('[1, 2]', "not a GeoJSON FeatureCollection"),
    ('{"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {},'
     ' "geometry": {"type": "Point", "coordinates": [1, 2]}}]}', "feature 1: geometry 'Point'"),
    ('{"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {},'
     ' "geometry": {"type": "LineString", "coordinates": [[1, 2, 3], [4, 5, 6]]}}]}',
     "pixel [col, row]"),
    ('{"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {},'
     ' "geometry": {"type": "LineString", "coordinates": [[1, 2]]}}]}', "at least 2"),
])
def test_bad_pixel_geojson_is_one_clear_error(tmp_path, content, problem):
    path = tmp_path / "bad.geojson"
    path.write_text(content)
    if problem == "geometry":  # a Feature without geometry is skipped, not an error
        assert read_interpretations(path) == []
        return
    with pytest.raises(InputError) as err:
        read_interpretations(path)
    message = str(err.value)
    assert str(path) in message and problem in message and "\n" not in message


def test_3d_geojson_structure_and_round_trip(tmp_path, projected):
    *_, features = projected
    doc = features_to_geojson(features)
    trace, facet, sky = doc["features"]
    assert trace["geometry"]["type"] == "MultiLineString"  # split at the slot, never bridged
    assert trace["properties"]["source"] == "IMG_0007.jpg"
    assert trace["properties"]["label"] == "sandstone" and trace["properties"]["bed"] == 3
    assert trace["properties"]["n_parts"] == 2
    assert facet["geometry"]["type"] == "Polygon" and facet["properties"]["kind"] == "facet"
    assert len(facet["properties"]["patch_points"]) > 100
    assert sky["geometry"] is None  # wholly off the surface: kept, without geometry
    assert doc["napari_imgreg"]["frame"] == "local"
    path = tmp_path / "lines3d.geojson"
    write_features_geojson(path, features)
    back, frame = read_features_geojson(path)
    assert frame == {"frame": "local"}
    assert [f.kind for f in back] == ["trace", "facet", "trace"]
    for a, b in zip(features, back):
        assert len(a.parts) == len(b.parts)
        for pa, pb in zip(a.parts, b.parts):
            np.testing.assert_allclose(pb[: len(pa)], pa, atol=1e-4)
    # Measuring from the file gives what measuring in memory gives.
    for ma, mb in zip(measure_features(features), measure_features(back)):
        assert (ma.dip_deg is None) == (mb.dip_deg is None)
        if ma.dip_deg is not None:
            assert mb.dip_deg == pytest.approx(ma.dip_deg, abs=0.05)


def test_georeferenced_export_equals_local_plus_origin(tmp_path, projected):
    *_, features = projected
    local_path, geo_path = tmp_path / "local.geojson", tmp_path / "geo.geojson"
    write_features_geojson(local_path, features, GEOREF)
    write_features_geojson(geo_path, features, GEOREF, georeferenced=True)
    local, geo = json.loads(local_path.read_text()), json.loads(geo_path.read_text())
    assert geo["crs"]["properties"]["name"] == "urn:ogc:def:crs:EPSG::32630"
    assert geo["napari_imgreg"] == {"frame": "crs", "crs": "EPSG:32630",
                                    "origin": [579000.0, 5912000.0, 350.0]}
    assert local["napari_imgreg"]["frame"] == "local"
    # A local-frame file names a local engineering CRS, so GDAL never reads it as WGS84.
    assert local["crs"]["properties"]["name"].startswith("ENGCRS[")
    for fl, fg in zip(local["features"], geo["features"]):
        if fl["geometry"] is None:
            assert fg["geometry"] is None
            continue
        a = np.concatenate([np.asarray(p).reshape(-1, 3) for p in fl["geometry"]["coordinates"]])
        b = np.concatenate([np.asarray(p).reshape(-1, 3) for p in fg["geometry"]["coordinates"]])
        np.testing.assert_allclose(b, a + GEOREF.origin, atol=1e-4)
    with pytest.raises(InputError, match="georeference"):
        features_to_geojson(features, None, georeferenced=True)


def test_exported_geojson_opens_with_standard_readers(tmp_path, projected):
    *_, features = projected
    path = tmp_path / "lines3d.geojson"
    write_features_geojson(path, features, GEOREF, georeferenced=True)
    doc = json.load(open(path, encoding="utf-8"))  # plain json: valid GeoJSON text
    coords = doc["features"][0]["geometry"]["coordinates"]
    assert all(len(p) == 3 for part in coords for p in part)  # Z intact
    z = np.array([p[2] for part in coords for p in part])
    assert np.all(z > 350.0) and np.ptp(z) > 1.0
    shapely = pytest.importorskip("shapely", reason="shapely not installed: json check only")
    from shapely.geometry import shape

    geom = shape(doc["features"][0]["geometry"])
    assert geom.has_z and geom.geom_type == "MultiLineString"


def test_exported_geojson_opens_with_gdal(tmp_path, projected):
    pyogrio = pytest.importorskip("pyogrio", reason="pyogrio (GDAL) not installed")
    from pyogrio.raw import read as read_raw

    *_, features = projected
    path = tmp_path / "lines3d.geojson"
    write_features_geojson(path, features, GEOREF, georeferenced=True)
    info = pyogrio.read_info(path)
    assert info["crs"] == "EPSG:32630"
    # Mixed geometry types make the layer "Unknown": check each geometry's Z.
    shapely = pytest.importorskip("shapely")
    _, _, geoms, _ = read_raw(path)
    assert all(shapely.from_wkb(g).has_z for g in geoms if g is not None)


def test_csv_obj_ply_exports(tmp_path, projected):
    *_, features = projected
    n_vertices = sum(len(p) for f in features for p in f.parts)
    export_features(tmp_path / "v.csv", features, GEOREF, georeferenced=True)
    rows = list(csv.DictReader(open(tmp_path / "v.csv")))
    assert len(rows) == n_vertices and rows[0]["source"] == "IMG_0007.jpg"
    assert float(rows[0]["x"]) == pytest.approx(features[0].parts[0][0, 0] + 579000.0, abs=1e-3)

    export_features(tmp_path / "l.obj", features)
    text = (tmp_path / "l.obj").read_text().splitlines()
    assert sum(line.startswith("v ") for line in text) == n_vertices
    assert sum(line.startswith("l ") for line in text) == 3  # two trace parts + facet ring
    assert any(line.startswith("o ") and "sandstone" in line for line in text)

    export_features(tmp_path / "l.ply", features)
    ply = (tmp_path / "l.ply").read_text().splitlines()
    assert f"element vertex {n_vertices}" in ply
    n_edges = sum(len(p) - 1 for f in features for p in f.parts)
    assert f"element edge {n_edges}" in ply
    body = ply[ply.index("end_header") + 1:]
    assert len(body) == n_vertices + n_edges
    r, g, b = map(int, body[0].split()[3:6])
    assert (r, g, b) == (255, 212, 0)  # sandstone yellow
    cloud = trimesh.load(tmp_path / "l.ply", process=False)  # a standard PLY reader
    assert len(cloud.vertices) == n_vertices

    with pytest.raises(InputError, match="unknown format"):
        export_features(tmp_path / "l.txt", features)


def test_measurements_csv_has_contract_columns_and_empty_cells(tmp_path, projected):
    *_, features = projected
    ms = measure_features(features)
    path = tmp_path / "m.csv"
    write_measurements_csv(path, ms)
    lines = path.read_text().splitlines()
    assert lines[0].split(",")[:13] == [
        "id", "label", "kind", "x", "y", "z", "n_points", "dip_deg", "dip_direction_deg",
        "plunge_deg", "trend_deg", "rms_m", "planarity"]
    assert tuple(lines[0].split(",")) == MEASUREMENT_COLUMNS
    rows = list(csv.DictReader(open(path)))
    # Contract §6: one row per feature, the one off the surface too (empty, with its note).
    trace, facet, off = rows
    assert off["n_points"] == "0" and off["note"]
    assert all(off[k] == "" for k in ("x", "y", "z", "dip_deg", "dip_direction_deg",
                                      "plunge_deg", "trend_deg", "rms_m", "planarity"))
    assert trace["kind"] == "trace" and trace["plunge_deg"] != "" and trace["dip_deg"] != ""
    assert float(trace["dip_deg"]) == pytest.approx(12.0, abs=0.5)
    assert facet["kind"] == "facet" and facet["plunge_deg"] == "" and facet["trend_deg"] == ""
    assert "nan" not in path.read_text().lower()


# ---------------------------------------------------------------- commands
@pytest.fixture
def files(tmp_path, projected):
    wall, X, intr, pose, items, _ = projected
    mesh = trimesh.Trimesh(wall.vertices, wall.faces, process=False)
    mesh_path = tmp_path / "wall.ply"
    mesh.export(mesh_path)
    GEOREF.save(tmp_path / "georef.json")
    result = {"status": "registered", "photo": "IMG_0007.jpg", "camera": intr.to_dict(),
              "pose": pose.to_dict()}
    result_path = tmp_path / "IMG_0007.result.json"
    result_path.write_text(json.dumps(result))
    lines_path = tmp_path / "IMG_0007.lines.geojson"
    write_interpretations(lines_path, items)
    return tmp_path, mesh_path, result_path, lines_path


def test_project_and_measure_commands(files, capsys):
    tmp, mesh, result, lines = files
    out = tmp / "lines3d.geojson"
    assert run_cli(["project", str(result), str(mesh), str(lines), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "IMG_0007.jpg: 3 feature(s)" in printed and "split" in printed
    doc = json.loads(out.read_text())
    assert [f["properties"]["source"] for f in doc["features"]] == ["IMG_0007.jpg"] * 3

    geo = tmp / "lines3d_geo.geojson"
    assert run_cli(["project", str(result), str(mesh), str(lines), "--out", str(geo),
                    "--georeferenced"]) == 0
    a = np.asarray(json.loads(out.read_text())["features"][0]["geometry"]["coordinates"][0])
    b = np.asarray(json.loads(geo.read_text())["features"][0]["geometry"]["coordinates"][0])
    np.testing.assert_allclose(b, a + GEOREF.origin, atol=1e-4)

    csv_path, net = tmp / "MEASUREMENTS.csv", tmp / "net.png"
    assert run_cli(["measure", str(geo), "--out", str(csv_path), "--stereonet", str(net)]) == 0
    printed = capsys.readouterr().out
    assert "3 feature(s) measured" in printed and "sandstone: 1 plane(s)" in printed
    assert "1 off the surface" in printed
    rows = list(csv.DictReader(open(csv_path)))
    assert float(rows[0]["x"]) > 500000  # centroids in the file's (CRS) frame
    assert float(rows[0]["dip_deg"]) == pytest.approx(12.0, abs=0.5)
    assert net.stat().st_size > 10_000

    # Two photos merge into one set, the source recorded per feature.
    merged = tmp / "merged.geojson"
    assert run_cli(["project", str(result), str(mesh), str(lines), "--also", str(result),
                    str(lines), "--out", str(merged)]) == 0
    ids = [f["id"] for f in json.loads(merged.read_text())["features"]]
    assert len(ids) == 6 and len(set(ids)) == 6


@pytest.mark.parametrize("case", ["missing_lines", "pixel_file_to_measure", "bad_out",
                                  "georef_missing", "bad_stereonet"])
def test_commands_bad_input_exit_2_with_one_line(files, capsys, case):
    tmp, mesh, result, lines = files
    if case == "missing_lines":
        argv = ["project", str(result), str(mesh), str(tmp / "nope.geojson"), "--out", "o.geojson"]
        expect = "nope.geojson: no such file"
    elif case == "pixel_file_to_measure":
        argv = ["measure", str(lines), "--out", str(tmp / "m.csv")]
        expect = "project it first"
    elif case == "bad_out":
        argv = ["project", str(result), str(mesh), str(lines), "--out", str(tmp / "o.txt")]
        expect = "output must be one of"
    elif case == "georef_missing":
        (tmp / "georef.json").unlink()
        argv = ["project", str(result), str(mesh), str(lines), "--out", str(tmp / "o.geojson"),
                "--georeferenced"]
        expect = "needs a georeference"
    else:
        argv = ["measure", str(lines), "--out", str(tmp / "m.csv"), "--stereonet", "x.bmp"]
        expect = "stereonet must be"
    assert run_cli(argv) == 2
    err = capsys.readouterr().err.strip()
    assert expect in err and len(err.splitlines()) == 1


def test_project_onto_a_dem_surface(tmp_path, capsys):
    """MESH may be a DEM: the surface is triangulated from it (Scene.from_dem)."""
    from napari_imgreg import Intrinsics, Pose
    from napari_imgreg.geo import DEM

    # A hillside rising 0.5 m per m to the north, in a CRS frame near the georef origin.
    E = 579000.0 + np.arange(0, 101) * 2.0
    N = 5912000.0 + np.arange(100, -1, -1) * 2.0  # row 0 is north
    heights = np.repeat((350.0 + 0.5 * (N - 5912000.0))[:, None], len(E), axis=1)
    dem = DEM(heights, E[0], N[0], 2.0, 2.0, crs="EPSG:32630")
    dem.save_asc(tmp_path / "hill.asc")
    GEOREF.save(tmp_path / "georef.json")
    intr = Intrinsics(800, 600, 700.0, 700.0, 399.5, 299.5)
    pose = Pose.from_attitude(0.0, 20.0, 0.0, np.array([100.0, -40.0, 60.0]))  # local frame
    result = tmp_path / "r.json"
    result.write_text(json.dumps({"status": "registered", "photo": "IMG_9.jpg",
                                  "camera": intr.to_dict(), "pose": pose.to_dict()}))
    lines = tmp_path / "l.geojson"
    write_interpretations(lines, [Interpretation(
        "LineString", np.array([[100.0, 300.0], [700.0, 350.0]]), {"label": "fault"})])
    out = tmp_path / "o.geojson"
    assert run_cli(["project", str(result), str(tmp_path / "hill.asc"), str(lines),
                    "--out", str(out)]) == 0
    (f,), frame = read_features_geojson(out)
    assert frame["crs"] == "EPSG:32630" and len(f.parts) == 1
    pts = f.parts[0]
    # On the hillside: z_local = 0.5 * y_local (origin height 350 m, origin northing 5912000).
    np.testing.assert_allclose(pts[:, 2], 0.5 * pts[:, 1], atol=1e-3)


# ------------------------------------------------------------ GIS frames and formats
def test_local_geojson_names_its_frame_so_gdal_never_reads_wgs84(tmp_path, projected):
    pyogrio = pytest.importorskip("pyogrio", reason="pyogrio (GDAL) not installed")
    *_, features = projected
    for georef in (None, GEOREF):
        path = tmp_path / f"local_{georef is not None}.geojson"
        write_features_geojson(path, features, georef, georeferenced=False)
        crs = pyogrio.read_info(path)["crs"]
        assert crs and "LOCAL_CS" in crs and "4326" not in crs and "4979" not in crs
        doc = json.loads(path.read_text())
        assert doc["napari_imgreg"]["frame"] == "local"
    assert "579000.000" in crs  # the origin is named in the datum
    geo = tmp_path / "geo.geojson"
    write_features_geojson(geo, features, GEOREF, georeferenced=True)
    assert pyogrio.read_info(geo)["crs"] == "EPSG:32630"
    # A file without the member (before this version) is what GDAL takes for WGS84:
    doc = json.loads(geo.read_text())
    del doc["crs"]
    old = tmp_path / "old.geojson"
    old.write_text(json.dumps(doc))
    assert "4326" in pyogrio.read_info(old)["crs"] or "4979" in pyogrio.read_info(old)["crs"]


def _wkb_points(wkb: bytes) -> np.ndarray:
    shapely = pytest.importorskip("shapely")
    return np.asarray(shapely.get_coordinates(shapely.from_wkb(wkb), include_z=True))


@pytest.mark.parametrize("suffix", [".gpkg", ".shp"])
def test_gis_export_keeps_z_crs_and_every_attribute(tmp_path, projected, suffix):
    pytest.importorskip("pyogrio", reason="pyogrio (GDAL) not installed")
    from napari_imgreg.interpret.files import GIS_LAYERS, read_gis_layers

    *_, features = projected
    measurements = measure_features(features)
    path = tmp_path / f"lines3d{suffix}"
    export_features(path, features, GEOREF, measurements=measurements)
    layers = read_gis_layers(path)
    assert set(layers) == set(GIS_LAYERS)
    for _, _, crs in layers.values():
        assert crs == "EPSG:32630"
    # traces: the geometry, in the CRS, with Z, and their properties
    geoms, data, _ = layers["traces"]
    traces = [f for f in features if f.kind == "trace"]
    assert len(geoms) == len(traces)
    for f, wkb, fid in zip(traces, geoms, data["id"]):
        assert fid == f.id
        if not f.parts:
            assert wkb is None
            continue
        pts = _wkb_points(wkb)
        np.testing.assert_allclose(pts, np.concatenate(f.parts) + GEOREF.origin, atol=1e-6)
    bed = list(data["id"]).index(traces[0].id)
    assert data["label"][bed] == "sandstone" and data["source"][bed] == "IMG_0007.jpg"
    assert int(data["bed"][bed]) == 3 and int(data["n_parts"][bed]) == len(traces[0].parts)
    assert float(data["length_m"][bed]) == pytest.approx(traces[0].length_m, abs=1e-4)
    normal_col = "surface_normal" if suffix == ".gpkg" else "surf_norm"
    np.testing.assert_allclose(json.loads(data[normal_col][bed]), traces[0].surface_normal,
                               atol=1e-6)
    # The camera centre in the layer's frame, like the geometry (contract §5).
    cam_col = "camera_position" if suffix == ".gpkg" else "cam_pos"
    np.testing.assert_allclose(json.loads(data[cam_col][bed]),
                               np.asarray(traces[0].properties["camera_position"])
                               + GEOREF.origin, atol=1e-4)
    # facets: a 3D polygon
    geoms, data, _ = layers["facets"]
    (facet,) = [f for f in features if f.kind == "facet"]
    assert data["label"][0] == "mudstone"
    if facet.ring_complete:
        pts = _wkb_points(geoms[0])
        assert np.ptp(pts[:, 2]) > 0.1 and np.all(pts[:, 0] > 500000)
    # measurements: every field, undefined as null, at the centroid
    geoms, data, _ = layers["measurements"]
    assert len(geoms) == len(measurements)
    names = {"dip_direction_deg": "dip_dir", "dip_deg": "dip"} if suffix == ".shp" else {}
    assert any(m.n_points == 0 for m in measurements)  # the feature off the surface has its row
    for k, m in enumerate(measurements):
        if m.n_points == 0:
            assert geoms[k] is None
        else:
            np.testing.assert_allclose(_wkb_points(geoms[k])[0], m.centroid + GEOREF.origin,
                                       atol=1e-6)
        dip = data[names.get("dip_deg", "dip_deg")][k]
        if m.dip_deg is None:
            assert dip is None or np.isnan(dip)
        else:
            assert float(dip) == pytest.approx(m.dip_deg, abs=1e-9)
        assert data["id"][k] == m.id and (data["note"][k] or "") == m.note
        # Empty text is null too, as the numbers: what a GIS's IS NULL finds.
        for name in ("note", "comment", "above", "below"):
            assert data[name][k] is None if getattr(m, name) == "" else data[name][k]


def test_geopackage_in_local_frame_without_georef_and_camera_layer(tmp_path, projected):
    pyogrio = pytest.importorskip("pyogrio", reason="pyogrio (GDAL) not installed")
    from napari_imgreg.interpret.files import read_gis_layers, write_features_gis

    *_, _intr, pose, _, features = projected
    path = tmp_path / "local.gpkg"
    path.write_text("an older file")  # replaced only when the new one is complete
    write_features_gis(path, features, None, cameras={"IMG_0007.jpg": pose.center})
    layers = read_gis_layers(path)
    assert all("LOCAL_CS" in crs for _, _, crs in layers.values())
    geoms, data, _ = layers["cameras"]
    names = list(data["photo"])
    assert "IMG_0007.jpg" in names
    k = names.index("IMG_0007.jpg")
    np.testing.assert_allclose(_wkb_points(geoms[k])[0], pose.center, atol=1e-9)
    info = pyogrio.read_info(path, layer="traces")
    assert info["geometry_type"] == "MultiLineString Z"
    assert info["layer_metadata"]["napari_imgreg_frame"] == "local"


def test_project_command_writes_geopackage_and_shapefile(files, capsys):
    pytest.importorskip("pyogrio", reason="pyogrio (GDAL) not installed")
    from napari_imgreg.interpret.files import read_gis_layers

    tmp, mesh, result, lines = files
    for name in ("lines3d.gpkg", "lines3d.shp"):
        out = tmp / name
        assert run_cli(["project", str(result), str(mesh), str(lines), "--out", str(out)]) == 0
        layers = read_gis_layers(out)
        geoms, data, crs = layers["traces"]
        assert crs == "EPSG:32630" and len(geoms) == 2  # georef.json beside the mesh
        assert _wkb_points(next(g for g in geoms if g is not None))[0, 0] > 500000
    assert (tmp / "lines3d_measurements.shp").exists() and (tmp / "lines3d.prj").exists()


def test_a_shapefile_leaves_text_it_cannot_hold_empty_and_says_so(tmp_path, projected):
    """dBASE text holds 254 characters: a longer value would be cut into
    broken JSON, so it is left empty with a note; the GeoPackage keeps it."""
    pytest.importorskip("pyogrio", reason="pyogrio (GDAL) not installed")
    from dataclasses import replace

    from napari_imgreg.interpret.files import read_gis_layers

    *_, features = projected
    long_note = "laminated, " * 30  # 330 characters
    features = [replace(features[0], properties={**features[0].properties,
                                                 "comment": long_note}), *features[1:]]
    notes = export_features(tmp_path / "l.shp", features, GEOREF)
    # The trace's note, and its measurement's (the measurements carry it too).
    assert len(notes) == 2 and "traces: comment of 1 feature(s)" in notes[0]
    assert "measurements: comment of 1 feature(s)" in notes[1]
    _, data, _ = read_gis_layers(tmp_path / "l.shp")["traces"]
    assert data["comment"][0] is None
    for text in data["uncertaint"]:
        assert text is None or json.loads(text)  # never a cut, broken JSON
    assert export_features(tmp_path / "l.gpkg", features, GEOREF) == []
    _, data, _ = read_gis_layers(tmp_path / "l.gpkg")["traces"]
    assert data["comment"][0] == long_note


def test_the_drawings_note_and_units_reach_the_measurements(projected, tmp_path):
    """A note and the units above and below, set on a drawing, are in its
    MEASUREMENTS.csv row (and so the GIS measurements layer)."""
    from dataclasses import replace

    from napari_imgreg.interpret.project import measure_features

    *_, features = projected
    first = replace(features[0], properties={**features[0].properties, "comment": "offset 2 m",
                                             "above": "Unit B", "below": "Unit A"})
    measurements = measure_features([first, *features[1:]])
    path = tmp_path / "m.csv"
    write_measurements_csv(path, measurements)
    import csv

    rows = list(csv.DictReader(path.open(encoding="utf-8")))
    assert (rows[0]["comment"], rows[0]["above"], rows[0]["below"]) == (
        "offset 2 m", "Unit B", "Unit A")
    assert rows[1]["comment"] == ""


def test_measure_says_which_north_its_azimuths_are_from(tmp_path, projected, capsys):
    """Azimuths are measured from the model's +Y, the grid north of a
    georeferenced model's CRS; ``measure`` says how far that lies from true
    north (the meridian convergence, PROJ's value at the features), and that
    a model without a georeference has no known north."""
    import pyproj

    from napari_imgreg.interpret.files import azimuth_reference

    *_, features = projected
    centroid = np.concatenate([f.points for f in features if f.n_points]).mean(axis=0)
    lon, lat = pyproj.Transformer.from_crs("EPSG:32630", "EPSG:4326", always_xy=True).transform(
        *(centroid + GEOREF.origin)[:2])
    gamma = pyproj.Proj("EPSG:32630").get_factors(lon, lat).meridian_convergence
    assert 0.9 < gamma < 1.0  # east of zone 30's central meridian: grid north clockwise
    for georeferenced in (False, True):
        path = tmp_path / f"lines_{georeferenced}.geojson"
        write_features_geojson(path, features, GEOREF, georeferenced=georeferenced)
        assert run_cli(["measure", str(path), "--out", str(tmp_path / "m.csv"),
                        "--samples", "20"]) == 0
        out = capsys.readouterr().out
        assert (f"from grid north of EPSG:32630, {gamma:.2f}° clockwise of true north here "
                f"(true azimuth = grid azimuth + {gamma:.2f}°)") in out
    write_features_geojson(tmp_path / "bare.geojson", features)
    assert run_cli(["measure", str(tmp_path / "bare.geojson"), "--out", str(tmp_path / "m.csv"),
                    "--samples", "20"]) == 0
    assert "model frame's +Y axis (no georeference" in capsys.readouterr().out
    # West of the central meridian, grid north lies anticlockwise of true north.
    west = azimuth_reference({"frame": "local", "crs": "EPSG:32630", "origin": [300000.0,
                                                                              5912000.0, 0.0]},
                             np.zeros((1, 3)))
    assert "anticlockwise of true north" in west and "grid azimuth − " in west


@pytest.mark.parametrize("props, expect", [
    ({"surface_normal": "up"}, "properties.surface_normal must be [x, y, z]"),
    ({"surface_normal": [0, 1]}, "properties.surface_normal must be [x, y, z]"),
    # A 3-point plane with a camera or points that are not numbers: no plane, said so.
    ({"camera_position": "x", "measure": "three_point",
      "three_point_xyz": [[0, 0, "q"], [1], [2]]}, None),
    # Not a colour: the label's own on the stereonet (was matplotlib's ValueError).
    ({"color": 5}, None),
    ({"color": "notacolour"}, None),
])
def test_measure_hand_edited_properties_are_one_line_or_no_plane(tmp_path, capsys, props,
                                                                expect):
    """A hand-edited 3D file's odd property is one error line naming the file
    and feature (exit 2), or measured without a plane; never a traceback."""
    path = tmp_path / "l3d.geojson"
    path.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "id": "a", "properties": {"label": "x", "source": "p.jpg", **props},
         "geometry": {"type": "LineString",
                      "coordinates": [[0, 0, 10], [1, 0, 10], [1, 1, 9], [0, 1, 9], [0, 2, 8]]}}]}))
    code = run_cli(["measure", str(path), "--out", str(tmp_path / "m.csv"), "--samples", "20",
                    "--stereonet", str(tmp_path / "net.png")])
    out, err = capsys.readouterr()
    err = err.strip()
    if expect:
        assert code == 2 and f"l3d.geojson: feature 1: {expect}" in err
        assert len(err.splitlines()) == 1 and not (tmp_path / "m.csv").exists()
    else:
        assert code == 0 and not err and (tmp_path / "net.png").stat().st_size > 1000
        if props.get("measure") == "three_point":  # the summary counts why
            assert "1: 3-point plane: not three clicked points on the surface" in out
        (row,) = csv.DictReader((tmp_path / "m.csv").open())
        assert row["dip_deg"] == "" and row["note"].startswith("no plane")
