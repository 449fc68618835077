"""Property-based tests of every reader: any file gives a value or one
``InputError`` (exit 2 on the command line), never another exception, and
each call stays within a time and a memory bound (see hypothesis_bounds).

Each suite starts from a valid document and mutates it (values replaced by
hostile numbers, strings, nested junk; fields deleted or added), or writes
arbitrary text/bytes, so the examples reach past the first check.
"""

from __future__ import annotations

import atexit
import shutil
import json
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from hypothesis_bounds import SUITE, call_bounded, json_values, mutated, nasty_numbers

pytestmark = pytest.mark.filterwarnings("ignore")

_TMP = Path(tempfile.mkdtemp(prefix="imgreg-hypothesis-"))
atexit.register(shutil.rmtree, _TMP, True)  # the scratch folder goes with the run


def _file(name: str, content: str | bytes) -> Path:
    """Write one example's file (the same path each time: no clutter)."""
    path = _TMP / name
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content, encoding="utf-8", errors="surrogatepass")
    return path


def _json_text(data) -> str:
    """As a careless writer would: NaN and Infinity allowed."""
    return json.dumps(data, allow_nan=True)


# ------------------------------------------------------------ sensor record
RECORD = {
    "camera": {"width": 1024, "height": 768, "focal_length_mm": 4.25,
               "sensor_width_mm": 5.6, "sensor_height_mm": 4.2},
    "position": {"x": -20.8, "y": -81.5, "z": 2.2},
    "orientation": {"trend_deg": 345.4, "plunge_deg": -4.5, "roll_deg": -4.5},
    "sigma": {"position_m": 5.0, "altitude_m": 2.0, "angles_deg": 5.0},
    "time": "2025-06-01T10:00:00+02:00",
}
RECORD_PIXELS = {**RECORD, "camera": {"width": 1024, "height": 768, "fx": 800.0, "fy": 800.0,
                                      "cx": 511.5, "cy": 383.5, "dist": [0.01, -0.02, 0, 0, 0]},
                 "position": {"lat": 45.1, "lon": 7.2, "alt": 300.0}}


@SUITE
@given(st.one_of(mutated(RECORD), mutated(RECORD_PIXELS)))
def test_sensor_record(data):
    from napari_imgreg.io.records import load_sensor_record

    call_bounded(load_sensor_record, _file("rec.json", _json_text(data)))


@SUITE
@given(st.one_of(st.text(max_size=200), st.binary(max_size=200).map(bytes)))
def test_sensor_record_arbitrary_text(content):
    from napari_imgreg.io.records import load_sensor_record

    call_bounded(load_sensor_record, _file("raw.json", content))


# ------------------------------------------------------------------ params
def _default_params() -> dict:
    from napari_imgreg.registration.params import RegistrationParams

    return json.loads(json.dumps(RegistrationParams().to_dict()))



@SUITE
@given(st.data())
def test_params(data):
    from napari_imgreg.registration.params import load_params

    doc = data.draw(mutated(_default_params(), max_changes=4))
    call_bounded(load_params, _file("params.json", _json_text(doc)))


def test_params_with_a_null_descriptor_is_one_clear_error():
    """Found by the suite above: it was an AttributeError traceback."""
    from napari_imgreg.errors import InputError
    from napari_imgreg.registration.params import load_params

    with pytest.raises(InputError, match="descriptor"):
        load_params(_file("params.json", '{"features": {"descriptor": null}}'))


@SUITE
@given(st.dictionaries(st.sampled_from(["max_trials", "max_iterations", "match_width",
                                        "n_search", "converged_deg", "converged_m",
                                        "auto_adapt", "features", "pose", "area", "edges"]),
                       json_values, max_size=4))
def test_params_top_level_values(doc):
    from napari_imgreg.registration.params import load_params

    call_bounded(load_params, _file("params.json", _json_text(doc)))


# ------------------------------------------------------------ lines GeoJSON
LINES = {
    "type": "FeatureCollection",
    "features": [
        {"type": "Feature", "geometry": {"type": "LineString",
                                         "coordinates": [[10.0, 20.0], [30.5, 40.0], [50, 45]]},
         "properties": {"label": "bedding", "color": "#ff0000"}},
        {"type": "Feature", "geometry": {"type": "Polygon",
                                         "coordinates": [[[1, 1], [9, 1], [9, 9], [1, 1]]]},
         "properties": {"label": "unit"}},
    ],
}



@pytest.mark.parametrize("gtype, coordinates", [("Polygon", True), ("Polygon", {"": None}),
                                                ("MultiLineString", 3), ("MultiPolygon", [1])])
def test_lines_with_non_array_coordinates_are_one_clear_error(gtype, coordinates):
    """Found by the suite above: they were TypeError/KeyError tracebacks."""
    from napari_imgreg.errors import InputError
    from napari_imgreg.interpret.files import read_interpretations

    doc = {"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {},
           "geometry": {"type": gtype, "coordinates": coordinates}}]}
    with pytest.raises(InputError, match="feature 1"):
        read_interpretations(_file("lines.geojson", json.dumps(doc)))


@SUITE
@given(st.one_of(mutated(LINES, max_changes=4), json_values))
def test_lines_geojson(doc):
    from napari_imgreg.interpret.files import read_interpretations

    call_bounded(read_interpretations, _file("lines.geojson", _json_text(doc)))


@SUITE
@given(st.lists(st.lists(nasty_numbers, min_size=2, max_size=3), min_size=0, max_size=6))
def test_lines_geojson_coordinates(coords):
    from napari_imgreg.interpret.files import read_interpretations

    doc = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "geometry": {"type": "LineString", "coordinates": coords},
         "properties": {}}]}
    call_bounded(read_interpretations, _file("lines.geojson", _json_text(doc)))


# -------------------------------------------------------------- RESULT.json
def _result_doc() -> dict:
    from napari_imgreg.camera import Intrinsics, Pose
    from napari_imgreg.prior import Prior
    from napari_imgreg.registration.pipeline import Registration

    intr = Intrinsics(640, 480, 500.0, 500.0, 319.5, 239.5)
    pose = Pose.from_attitude(10.0, 5.0, 0.0, [0.0, -50.0, 2.0])
    reg = Registration(status="registered", photo="a.jpg", intrinsics=intr, pose=pose,
                       prior=Prior(intrinsics=intr, pose=pose), metrics={"inliers_3d": 40},
                       q=0.7, grade="good", hints=[], trials=[], timings_s={"total": 1.0})
    return json.loads(json.dumps(reg.to_dict()))


@SUITE
@given(st.data())
def test_result_json(data):
    from napari_imgreg.prior import load_camera_and_pose

    doc = data.draw(mutated(_result_doc(), max_changes=3))
    call_bounded(load_camera_and_pose, _file("RESULT.json", _json_text(doc)))


# -------------------------------------------------------- orientation tables
_CSV_HEADER = "photo,trend_deg,plunge_deg,roll_deg,x,y,z"
_CSV_ROWS = ["IMG_1.jpg,10,5,0,1,2,3", "IMG_2.jpg,120.5,-3,2,4,5,6", "IMG_3.jpg,359,0,0,,,"]
_cells = st.one_of(nasty_numbers.map(str), st.text(max_size=8), st.just(""))


@SUITE
@given(st.lists(st.tuples(st.integers(0, 3), st.integers(0, 7), _cells), max_size=6),
       st.booleans())
def test_orientation_csv(edits, drop_header):
    from napari_imgreg.io.orientation_tables import read_orientation_table

    lines = [_CSV_HEADER.split(",")] + [r.split(",") for r in _CSV_ROWS]
    for row, col, value in edits:
        cells = lines[row]
        if col < len(cells):
            cells[col] = value.replace("\n", " ")
        else:
            cells.append(value)
    if drop_header:
        lines = lines[1:]
    text = "\n".join(",".join(c) for c in lines) + "\n"
    call_bounded(read_orientation_table, _file("table.csv", text))


_COLMAP = ("# Image list\n"
           "1 0.99 0.01 0.1 0.0 1.0 2.0 3.0 1 IMG_1.jpg\n\n"
           "2 0.98 0.0 0.2 0.01 4.0 5.0 6.0 1 IMG_2.jpg\n\n")
_XML = ('<?xml version="1.0"?><document><chunk><cameras>'
        '<camera id="0" label="IMG_1"><transform>1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1</transform>'
        '</camera></cameras></chunk></document>')


@SUITE
@given(st.sampled_from(["images.txt", "cameras.xml"]),
       st.lists(st.tuples(st.integers(0, 400), st.text(max_size=6)), max_size=4))
def test_orientation_colmap_and_metashape(name, edits):
    from napari_imgreg.io.orientation_tables import read_orientation_table

    text = _COLMAP if name == "images.txt" else _XML
    for pos, insert in edits:
        pos = min(pos, len(text))
        text = text[:pos] + insert + text[pos + len(insert):]
    call_bounded(read_orientation_table, _file(name, text))


# ----------------------------------------------------------- DEM and georef
GEOREF = {"crs": "EPSG:32632", "origin": [500000.0, 5000000.0, 300.0]}


@SUITE
@given(st.one_of(mutated(GEOREF), json_values))
def test_georef(doc):
    from napari_imgreg.geo import Georef

    call_bounded(Georef.load, _file("georef.json", _json_text(doc)))


_ASC_HEADER = [("ncols", 4), ("nrows", 3), ("xllcorner", 500000.0), ("yllcorner", 5000000.0),
               ("cellsize", 10.0), ("NODATA_value", -9999)]


@SUITE
@given(st.dictionaries(st.integers(0, 5), st.one_of(nasty_numbers.map(str), st.text(max_size=6)),
                       max_size=3),
       st.lists(st.lists(st.one_of(nasty_numbers.map(str), st.just("x")), max_size=5),
                max_size=4),
       st.booleans())
def test_dem_ascii_grid(header_edits, body, keep_body):
    from napari_imgreg.geo import DEM

    header = [f"{k} {header_edits.get(i, v)}".replace("\n", " ")
              for i, (k, v) in enumerate(_ASC_HEADER)]
    rows = ["1 2 3 4", "5 6 7 8", "9 10 11 -9999"] if keep_body else [" ".join(r) for r in body]
    call_bounded(DEM.load, _file("dem.asc", "\n".join(header + rows) + "\n"))


def _valid_geotiff() -> bytes:
    from napari_imgreg.geo import DEM

    path = _TMP / "valid.tif"
    if not path.exists():
        DEM.from_array(np.arange(12, dtype=np.float64).reshape(3, 4), 500000.0, 5000030.0,
                       10.0, 10.0, crs="EPSG:32632").save_geotiff(path)
    return path.read_bytes()


@SUITE
@given(st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 255)), min_size=1, max_size=6))
@example(flips=[(117, 94)])  # a strip byte count of 1.5 GB in a 408-byte file (found by CI)
@example(flips=[(1256, 252)])  # 16.5 M rows of which one strip is listed (20 s to decode)
def test_dem_geotiff_bytes(flips):
    from napari_imgreg.geo import DEM

    data = bytearray(_valid_geotiff())
    for pos, value in flips:
        data[pos % len(data)] = value
    call_bounded(DEM.load, _file("dem.tif", bytes(data)))


# -------------------------------------------------------------- mesh headers
_PLY_PROPS = ["property float x", "property float y", "property float z"]


@SUITE
@given(st.one_of(nasty_numbers, st.text(max_size=6)), st.one_of(nasty_numbers, st.text(max_size=6)),
       st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian", "utf8"]),
       st.binary(max_size=120))
def test_ply_header(n_vertex, n_face, fmt, body):
    from napari_imgreg.io.meshes import load_mesh

    header = "\n".join(["ply", f"format {fmt} 1.0", f"element vertex {n_vertex}", *_PLY_PROPS,
                        f"element face {n_face}", "property list uchar int vertex_indices",
                        "end_header"]).replace("\r", " ") + "\n"
    if fmt == "ascii" and not body:
        body = b"0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
    call_bounded(load_mesh, _file("m.ply", header.encode("utf-8", "surrogatepass") + body),
                 cache=False)


_obj_line = st.one_of(
    st.tuples(st.just("v"), st.lists(nasty_numbers, max_size=4)).map(
        lambda t: "v " + " ".join(map(str, t[1]))),
    st.tuples(st.just("f"), st.lists(st.integers(-5, 10**12), max_size=4)).map(
        lambda t: "f " + " ".join(map(str, t[1]))),
    st.text(max_size=20).map(lambda s: s.replace("\n", " ")),
    st.sampled_from(["mtllib missing.mtl", "usemtl x", "vt 0.5 0.5", "vn 0 0 1", "o part"]),
)


@SUITE
@given(st.lists(_obj_line, max_size=12))
def test_obj_lines(lines):
    from napari_imgreg.io.meshes import load_mesh

    text = "v 0 0 0\nv 1 0 0\nv 0 1 0\n" + "\n".join(lines) + "\nf 1 2 3\n"
    call_bounded(load_mesh, _file("m.obj", text), cache=False)


def test_bounds_catch_what_they_should():
    """The bound itself works: an oversized allocation and a non-input error fail."""
    with pytest.raises(AssertionError, match="MB"):
        call_bounded(lambda: np.ones(400_000_000))  # 3.2 GB
    def spin():
        while True:
            pass

    import hypothesis_bounds

    limit, hypothesis_bounds.TIME_LIMIT_S = hypothesis_bounds.TIME_LIMIT_S, 0.3
    try:
        with pytest.raises(AssertionError, match="took .* of CPU"):
            call_bounded(spin)
    finally:
        hypothesis_bounds.TIME_LIMIT_S = limit
    import time

    wall, hypothesis_bounds.WALL_LIMIT_S = hypothesis_bounds.WALL_LIMIT_S, 0.3
    try:  # blocked without computing: the wall-clock bound
        with pytest.raises(AssertionError, match="took .* of wall time"):
            call_bounded(time.sleep, 5.0)
    finally:
        hypothesis_bounds.WALL_LIMIT_S = wall
    with pytest.raises(ZeroDivisionError):
        call_bounded(lambda: 1 / 0)
    from napari_imgreg.errors import input_error

    assert "x.json" in str(call_bounded(lambda: (_ for _ in ()).throw(input_error("x.json", "bad"))))
    assert math.isfinite(call_bounded(lambda: 1.0))
