"""Known-answer tests for :mod:`napari_imgreg.geo` (georeference and DEMs)."""

from __future__ import annotations

import json
import math

import numpy as np
import pyproj
import pytest
import tifffile

from napari_imgreg.geo import DEM, GeoError, Georef, camera_altitude

# ---------------------------------------------------------------------------
# fixtures / helpers
# ---------------------------------------------------------------------------

A, B, C = 250.0, 0.01, -0.02  # plane h = A + B*E + C*N


def plane_dem() -> DEM:
    """7 x 9 DEM sampling an inclined plane, 5 m x 4 m pixels."""
    x0, y0, dx, dy = 1000.0, 2000.0, 5.0, 4.0
    rows, cols = 7, 9
    e = x0 + np.arange(cols) * dx
    n = y0 - np.arange(rows) * dy
    E, N = np.meshgrid(e, n)
    return DEM.from_array(A + B * E + C * N, x0, y0, dx, dy, source="plane.tif")


def square_dem(heights) -> DEM:
    """2 x 2 DEM: centres at E in {0, 10}, N in {10 (row 0), 0 (row 1)}."""
    return DEM.from_array(np.array(heights, float), 0.0, 10.0, 10.0, 10.0, source="sq.tif")


# ---------------------------------------------------------------------------
# bilinear interpolation
# ---------------------------------------------------------------------------


def test_bilinear_reproduces_plane_at_interior_points():
    dem = plane_dem()
    rng = np.random.default_rng(0)
    xmin, xmax, ymin, ymax = dem.extent
    e = rng.uniform(xmin, xmax, 200)
    n = rng.uniform(ymin, ymax, 200)
    got = dem.height_at(e, n)
    assert got.shape == (200,)
    np.testing.assert_allclose(got, A + B * e + C * n, rtol=0, atol=1e-9)
    # scalar in, float out
    h = dem.height_at(1012.3, 1987.6)
    assert isinstance(h, float)
    assert abs(h - (A + B * 1012.3 + C * 1987.6)) <= 1e-9


def test_bilinear_at_pixel_centres_returns_stored_values():
    dem = plane_dem()
    E, N = dem.grid()
    assert E.shape == N.shape == dem.heights.shape
    np.testing.assert_array_equal(dem.height_at(E, N), dem.heights)


def test_extent_and_grid_geometry():
    dem = plane_dem()
    assert dem.extent == (1000.0, 1040.0, 1976.0, 2000.0)
    E, N = dem.grid()
    assert E[0, 0] == 1000.0 and N[0, 0] == 2000.0  # top-left centre
    assert N[1, 0] == 1996.0  # rows go south


def test_bilinear_hand_computed_2x2():
    dem = square_dem([[10, 20], [30, 40]])
    # c = 0.25, r = 0.5: north 12.5, south 32.5 -> 22.5
    assert dem.height_at(2.5, 5.0) == pytest.approx(22.5, abs=1e-12)
    # c = 0.4, r = 0.1: north 14, south 34 -> 16
    assert dem.height_at(4.0, 9.0) == pytest.approx(16.0, abs=1e-12)
    # corners
    assert dem.height_at(0.0, 10.0) == 10.0
    assert dem.height_at(10.0, 0.0) == 40.0


def test_half_pixel_margin_is_clamped():
    dem = square_dem([[10, 20], [30, 40]])
    # 5 m (half a pixel) west of the west centres: clamped onto column 0.
    assert dem.height_at(-5.0, 5.0) == pytest.approx(20.0)
    assert dem.height_at(15.0, 15.0) == pytest.approx(20.0)  # NE corner margin
    with pytest.raises(GeoError, match="outside"):
        dem.height_at(-5.1, 5.0)


def test_nodata_one_neighbour_renormalised():
    dem = square_dem([[10, np.nan], [30, 40]])
    # weights at c=.25, r=.5: NW .375, NE .125 (NaN), SW .375, SE .125
    expected = (0.375 * 10 + 0.375 * 30 + 0.125 * 40) / 0.875  # = 22.857142...
    assert dem.height_at(2.5, 5.0) == pytest.approx(expected, abs=1e-12)
    assert expected == pytest.approx(160 / 7)


def test_nodata_all_neighbours_raises():
    dem = square_dem([[np.nan, np.nan], [np.nan, np.nan]])
    with pytest.raises(GeoError, match="nodata") as ei:
        dem.height_at(5.0, 5.0)
    assert "sq.tif" in str(ei.value)
    # exactly on a nodata centre: the valid neighbours have zero weight
    dem2 = square_dem([[np.nan, 20], [30, 40]])
    with pytest.raises(GeoError, match="nodata"):
        dem2.height_at(0.0, 10.0)


def test_outside_raises_naming_file_and_extent():
    dem = plane_dem()
    with pytest.raises(GeoError) as ei:
        dem.height_at(5000.0, 1990.0)
    msg = str(ei.value)
    assert "plane.tif" in msg and "outside" in msg
    assert "E=5000" in msg and "1000.0–1040.0" in msg


def test_non_strict_returns_nan_vectorised():
    dem = square_dem([[np.nan, np.nan], [30, 40]])
    e = np.array([[5.0, 100.0], [0.0, 5.0]])
    n = np.array([[0.0, 0.0], [10.0, 5.0]])
    got = dem.height_at(e, n, strict=False)
    assert got.shape == (2, 2)
    assert got[0, 0] == pytest.approx(35.0)
    assert math.isnan(got[0, 1])  # outside
    assert math.isnan(got[1, 0])  # nodata
    assert got[1, 1] == pytest.approx(35.0)  # NaN row dropped, renormalised


def test_single_row_and_column_dem():
    row = DEM.from_array([[1.0, 3.0]], 0.0, 0.0, 2.0, 2.0)
    assert row.height_at(1.0, 0.5) == pytest.approx(2.0)
    col = DEM.from_array([[1.0], [3.0]], 0.0, 0.0, 2.0, 2.0)
    assert col.height_at(0.3, -1.0) == pytest.approx(2.0)


def test_camera_altitude():
    dem = square_dem([[10, 20], [30, 40]])
    assert camera_altitude(dem, 2.5, 5.0) == pytest.approx(22.5 + 1.6)
    assert camera_altitude(dem, 2.5, 5.0, height_above_ground_m=0.0) == pytest.approx(22.5)
    with pytest.raises(GeoError):
        camera_altitude(dem, 1e6, 0.0)


def test_from_array_validation():
    with pytest.raises(GeoError, match="positive"):
        DEM.from_array(np.zeros((2, 2)), 0, 0, 0.0, 1.0)
    with pytest.raises(GeoError, match="2D"):
        DEM.from_array(np.zeros(4), 0, 0, 1.0, 1.0)


# ---------------------------------------------------------------------------
# GeoTIFF
# ---------------------------------------------------------------------------


def test_geotiff_round_trip(tmp_path):
    h = np.arange(20, dtype=np.float64).reshape(4, 5) * 0.25 + 300.0  # float32-exact
    h[1, 2] = np.nan
    # awkward values: corner = centre - half pixel is not exact in binary
    dem = DEM.from_array(h, 500000.1, 5900000.3, 0.3, 0.7, crs="EPSG:32630")
    path = tmp_path / "dem.tif"
    dem.save_geotiff(path)
    back = DEM.load(path)
    assert (back.x0, back.y0, back.dx, back.dy) == (dem.x0, dem.y0, dem.dx, dem.dy)
    assert back.crs == "EPSG:32630"
    assert back.source == "dem.tif"
    np.testing.assert_array_equal(back.heights, h)  # NaN positions equal too
    assert back == dem
    assert back.extent == dem.extent
    assert not list(tmp_path.glob(".*tmp"))  # no temp file left behind


def test_geotiff_round_trip_geometry_exact_many(tmp_path):
    rng = np.random.default_rng(1)
    path = tmp_path / "d.tif"
    for _ in range(20):
        dem = DEM.from_array(
            rng.normal(size=(3, 4)).astype(np.float32),
            float(rng.uniform(-1e6, 1e6)),
            float(rng.uniform(-1e7, 1e7)),
            float(rng.uniform(0.01, 50)),
            float(rng.uniform(0.01, 50)),
        )
        dem.save_geotiff(path)
        back = DEM.load(path)
        assert (back.x0, back.y0, back.dx, back.dy) == (dem.x0, dem.y0, dem.dx, dem.dy)
        assert back.crs is None


def test_geotiff_tags_written(tmp_path):
    path = tmp_path / "dem.tif"
    dem = DEM.from_array([[1, np.nan], [3, 4]], 100.0, 200.0, 10.0, 10.0, crs="EPSG:27700")
    dem.save_geotiff(path)
    with tifffile.TiffFile(path) as tf:
        page = tf.pages[0]
        tags = {t.code: t.value for t in page.tags}
        data = page.asarray()
    assert data.dtype == np.float32 and data[0, 1] == -9999.0
    assert tags[33550] == (10.0, 10.0, 0.0)
    assert tags[33922] == (0.0, 0.0, 0.0, 95.0, 205.0, 0.0)  # PixelIsArea corner
    gk = tags[34735]
    keys = {gk[i]: gk[i + 3] for i in range(4, len(gk), 4)}
    assert keys == {1024: 1, 1025: 1, 3072: 27700}
    assert tags[42113].strip("\x00") == "-9999"


def _write_raw_geotiff(path, data, *, raster_type, tiepoint=None, scale=None,
                       transform=None, nodata=None, epsg=32630):
    extratags = []
    if scale is not None:
        extratags.append((33550, "d", 3, scale, True))
    if tiepoint is not None:
        extratags.append((33922, "d", 6, tiepoint, True))
    if transform is not None:
        extratags.append((34264, "d", 16, transform, True))
    keys = (1, 1, 0, 3, 1024, 0, 1, 1, 1025, 0, 1, raster_type, 3072, 0, 1, epsg)
    extratags.append((34735, "H", len(keys), keys, True))
    if nodata is not None:
        extratags.append((42113, "s", 0, nodata, True))
    tifffile.imwrite(path, data, metadata=None, extratags=extratags)


def test_geotiff_pixel_is_point(tmp_path):
    path = tmp_path / "pt.tif"
    data = np.array([[1, 2, 3], [4, 5, 6]], dtype=np.int16)
    _write_raw_geotiff(path, data, raster_type=2, scale=(2.0, 3.0, 0.0),
                       tiepoint=(0, 0, 0, 100.0, 50.0, 0), nodata="5")
    dem = DEM.load(path)
    assert (dem.x0, dem.y0, dem.dx, dem.dy) == (100.0, 50.0, 2.0, 3.0)
    assert dem.heights.dtype == np.float64
    assert np.isnan(dem.heights[1, 1]) and dem.heights[1, 2] == 6.0


def test_geotiff_pixel_is_area_and_gdal_float32_nodata(tmp_path):
    path = tmp_path / "area.tif"
    nd = np.finfo(np.float32).min  # GDAL's usual float32 nodata
    data = np.array([[1, nd], [3, 4]], dtype=np.float32)
    _write_raw_geotiff(path, data, raster_type=1, scale=(2.0, 2.0, 0.0),
                       tiepoint=(0, 0, 0, 100.0, 50.0, 0), nodata=repr(float(nd)))
    dem = DEM.load(path)
    assert (dem.x0, dem.y0) == (101.0, 49.0)  # corner + half pixel
    assert np.isnan(dem.heights[0, 1])


def test_geotiff_model_transformation(tmp_path):
    path = tmp_path / "mt.tif"
    data = np.ones((2, 3), np.float32)
    m = (2.0, 0, 0, 100.0, 0, -3.0, 0, 50.0, 0, 0, 0, 0, 0, 0, 0, 1)
    _write_raw_geotiff(path, data, raster_type=1, transform=m)
    dem = DEM.load(path)
    assert (dem.x0, dem.y0, dem.dx, dem.dy) == (101.0, 48.5, 2.0, 3.0)
    rot = (2.0, 0.5, 0, 100.0, 0.5, -3.0, 0, 50.0, 0, 0, 0, 0, 0, 0, 0, 1)
    _write_raw_geotiff(path, data, raster_type=1, transform=rot)
    with pytest.raises(GeoError, match="north-up") as ei:
        DEM.load(path)
    assert "mt.tif" in str(ei.value)


def test_geotiff_multiband_takes_first_band(tmp_path):
    path = tmp_path / "rgb.tif"
    data = np.zeros((2, 3, 3), np.uint8)
    data[..., 0] = 7
    data[..., 1] = 9
    _write_raw_geotiff(path, data, raster_type=1, scale=(1.0, 1.0, 0.0),
                       tiepoint=(0, 0, 0, 0.0, 0.0, 0))
    dem = DEM.load(path)
    assert dem.heights.shape == (2, 3) and np.all(dem.heights == 7)


def test_plain_tiff_without_georeferencing(tmp_path):
    path = tmp_path / "plain.tif"
    tifffile.imwrite(path, np.zeros((2, 2), np.float32))
    with pytest.raises(GeoError, match="georeferencing") as ei:
        DEM.load(path)
    assert "plain.tif" in str(ei.value)


# ---------------------------------------------------------------------------
# ESRI ASCII grid
# ---------------------------------------------------------------------------

ASC_BODY = "1 2 3\n4 -9999 6\n"


@pytest.mark.parametrize(
    "header",
    [
        "ncols 3\nnrows 2\nxllcorner 100\nyllcorner 200\ncellsize 10\nNODATA_value -9999\n",
        "NCOLS 3\nNROWS 2\nXLLCENTER 105\nYLLCENTER 205\nCELLSIZE 10\nnodata_value -9999\n",
    ],
    ids=["corner", "centre"],
)
def test_asc_reading(tmp_path, header):
    path = tmp_path / "g.asc"
    path.write_text(header + ASC_BODY)
    dem = DEM.load(path)
    # lower-left cell centre (105, 205); top row is 10 m further north
    assert (dem.x0, dem.y0, dem.dx, dem.dy) == (105.0, 215.0, 10.0, 10.0)
    assert dem.crs is None and dem.source == "g.asc"
    np.testing.assert_array_equal(dem.heights[0], [1, 2, 3])  # file row 0 = north
    assert dem.height_at(105.0, 215.0) == 1.0
    assert dem.height_at(105.0, 205.0) == 4.0
    assert np.isnan(dem.heights[1, 1])


def test_asc_round_trip_with_prj(tmp_path):
    h = np.array([[1.5, np.nan], [3.25, 4.0], [5.0, 6.0]])
    dem = DEM.from_array(h, 500000.1, 5900000.3, 0.3, 0.7, crs="EPSG:32630")
    path = tmp_path / "out.asc"
    dem.save_asc(path)
    assert (tmp_path / "out.prj").is_file()
    back = DEM.load(path)
    assert back == dem


@pytest.mark.parametrize(
    "text, problem",
    [
        (
            "ncols 3\nnrows two\nxllcorner 0\nyllcorner 0\ncellsize 1\n1 2 3\n4 5 6\n",
            "not a number",
        ),
        ("ncols 3\nnrows 2\nxllcorner 0\nyllcorner 0\n1 2 3\n4 5 6\n", "cellsize"),
        ("ncols 3\nnrows 2\nyllcorner 0\ncellsize 1\n1 2 3\n4 5 6\n", "xllcorner"),
        ("ncols 3\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 1\n1 2 3\n4 5\n", "5 values"),
        ("ncols 3\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 1\n1 2 3\n4 x 6\n", "non-numeric"),
        ("colour blue\n1 2\n", "header"),
    ],
)
def test_asc_bad_input(tmp_path, text, problem):
    path = tmp_path / "bad.asc"
    path.write_text(text)
    with pytest.raises(GeoError, match=problem) as ei:
        DEM.load(path)
    assert "bad.asc" in str(ei.value)


# ---------------------------------------------------------------------------
# DEM bad input
# ---------------------------------------------------------------------------


def test_dem_missing_file(tmp_path):
    with pytest.raises(GeoError, match="not found") as ei:
        DEM.load(tmp_path / "nope.tif")
    assert "nope.tif" in str(ei.value)


def test_dem_unknown_extension(tmp_path):
    path = tmp_path / "dem.xyz"
    path.write_text("1 2 3\n")
    with pytest.raises(GeoError, match="unknown DEM file type") as ei:
        DEM.load(path)
    assert "dem.xyz" in str(ei.value)


RANDOM_BYTES = np.random.default_rng(2).integers(0, 256, 4096, dtype=np.uint8).tobytes()


@pytest.mark.parametrize("content", [b"", RANDOM_BYTES, b"II*\x00" + RANDOM_BYTES])
def test_dem_corrupt_tif(tmp_path, content):
    path = tmp_path / "corrupt.tif"
    path.write_bytes(content)
    with pytest.raises(GeoError) as ei:
        DEM.load(path)
    assert "corrupt.tif" in str(ei.value)


# ---------------------------------------------------------------------------
# Georef
# ---------------------------------------------------------------------------

ORIGIN = [587000.0, 5911000.0, 300.0]


def test_georef_save_load_round_trip(tmp_path):
    g = Georef("EPSG:32630", np.array(ORIGIN))
    path = tmp_path / "georef.json"
    g.save(path)
    assert json.loads(path.read_text()) == {"crs": "EPSG:32630", "origin": ORIGIN}
    back = Georef.load(path)
    assert back == g
    assert back.origin.dtype == np.float64 and back.origin.shape == (3,)
    assert Georef.from_dict(g.to_dict()) == g
    assert not list(tmp_path.glob(".*tmp"))


def test_local_crs_offsets():
    g = Georef("EPSG:32630", np.array(ORIGIN))
    local = np.array([[1.0, 2.0, 3.0], [-10.0, 0.5, 0.0]])
    np.testing.assert_array_equal(g.local_to_crs(local), local + ORIGIN)
    np.testing.assert_array_equal(g.local_to_crs(local[0]), local[0] + ORIGIN)
    assert g.local_to_crs(local[0]).shape == (3,)
    np.testing.assert_array_equal(g.crs_to_local(g.local_to_crs(local)), local)


def test_geodetic_central_meridian_equator():
    g = Georef("EPSG:32630", np.zeros(3))
    p = g.geodetic_to_local(0.0, -3.0, 12.0)
    assert p.shape == (3,)
    assert p[0] == pytest.approx(500000.0, abs=1e-6)
    assert p[1] == pytest.approx(0.0, abs=1e-6)
    assert p[2] == 12.0


def test_geodetic_mam_tor_against_pyproj():
    g = Georef("EPSG:32630", np.array(ORIGIN))
    lat, lon = 53.35, -1.81
    tr = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:32630", always_xy=True)
    e, n = tr.transform(lon, lat)
    p = g.geodetic_to_local(lat, lon)
    assert p[0] == pytest.approx(e - ORIGIN[0], abs=1e-9)
    assert p[1] == pytest.approx(n - ORIGIN[1], abs=1e-9)
    assert math.isnan(p[2])  # no altitude: caller fills it from the DEM
    # sanity: Mam Tor is ~580 km E in UTM 30N
    assert 570000 < e < 590000


def test_geodetic_round_trip_arrays():
    g = Georef("EPSG:32630", np.array(ORIGIN))
    local = np.array([[0.0, 0.0, 0.0], [123.4, -567.8, 90.1], [-2000.0, 3000.0, -50.0]])
    lat, lon, alt = g.local_to_geodetic(local)
    assert lat.shape == lon.shape == alt.shape == (3,)
    back = g.geodetic_to_local(lat, lon, alt)
    assert back.shape == (3, 3)
    assert np.max(np.abs(back - local)) < 1e-3
    lat0, lon0, alt0 = g.local_to_geodetic(local[1])
    assert isinstance(lat0, float)
    np.testing.assert_allclose(g.geodetic_to_local(lat0, lon0, alt0), local[1], atol=1e-3)


def test_geodetic_bad_latitude():
    g = Georef("EPSG:32630", np.zeros(3))
    with pytest.raises(GeoError, match="latitude"):
        g.geodetic_to_local(153.35, -1.81)  # lat/lon swapped


def test_georef_missing_file(tmp_path):
    with pytest.raises(GeoError, match="not found") as ei:
        Georef.load(tmp_path / "georef.json")
    assert "georef.json" in str(ei.value)


@pytest.mark.parametrize(
    "text, problem",
    [
        ("{not json", "invalid JSON"),
        ('{"crs": "EPSG:32630"}', "'origin'"),
        ('{"origin": [1, 2, 3]}', "'crs'"),
        ('{"crs": "EPSG:32630", "origin": [1, 2]}', "'origin' must be a list of 3 numbers"),
        ('{"crs": "EPSG:32630", "origin": [1, "2", 3]}', "'origin' must be a list of 3 numbers"),
        ('{"crs": "EPSG:999999", "origin": [1, 2, 3]}', "not a valid CRS"),
        ('{"crs": 32630, "origin": [1, 2, 3]}', "'crs'"),
        ('{"crs": "EPSG:4326", "origin": [1, 2, 3]}', "not a projected CRS"),
        ('[1, 2, 3]', "JSON object"),
    ],
)
def test_georef_bad_input(tmp_path, text, problem):
    path = tmp_path / "georef.json"
    path.write_text(text)
    with pytest.raises(GeoError, match=problem) as ei:
        Georef.load(path)
    assert "georef.json" in str(ei.value)


# ---------------------------------------------------------------------------
# package integration
# ---------------------------------------------------------------------------


def test_geo_error_is_the_package_input_error():
    from napari_imgreg.errors import InputError

    assert issubclass(GeoError, InputError) and issubclass(GeoError, ValueError)


def test_read_geotiff_rgb_and_bottom_up(tmp_path):
    from napari_imgreg.io.rasters import read_geotiff

    path = tmp_path / "ortho.tif"
    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    _write_raw_geotiff(path, rgb, raster_type=1, scale=(0.5, 0.5, 0.0),
                       tiepoint=(0, 0, 0, 10.0, 20.0, 0))
    r = read_geotiff(path)
    assert r.data.shape == (2, 3, 3) and r.data.dtype == np.uint8
    assert (r.x0, r.y0, r.dx, r.dy) == (10.25, 19.75, 0.5, 0.5)
    assert r.crs == "EPSG:32630" and r.nodata is None

    # negative y scale: file rows run north; the DEM comes back north-up
    path2 = tmp_path / "bottomup.tif"
    data = np.array([[1.0, 2.0], [3.0, 4.0]], np.float32)  # file row 0 = SOUTH
    _write_raw_geotiff(path2, data, raster_type=1, scale=(1.0, -1.0, 0.0),
                       tiepoint=(0, 0, 0, 0.0, 0.0, 0))
    dem = DEM.load(path2)
    assert (dem.x0, dem.y0, dem.dy) == (0.5, 1.5, 1.0)
    np.testing.assert_array_equal(dem.heights, [[3.0, 4.0], [1.0, 2.0]])
    assert dem.height_at(0.5, 0.5) == 1.0


@pytest.mark.parametrize("suffix", [".tif", ".asc"])
def test_raster_files_are_plain_arrays_that_dem_builds_on(tmp_path, suffix):
    # io.rasters reads and writes plain grids; DEM.load/save are thin on top.
    from napari_imgreg.io import rasters

    dem = plane_dem()
    dem.heights[2, 3] = np.nan
    dem = DEM.from_array(dem.heights, dem.x0, dem.y0, dem.dx, dem.dy, crs="EPSG:32630")
    path = tmp_path / f"plain{suffix}"
    write = rasters.write_dem_geotiff if suffix == ".tif" else rasters.write_dem_asc
    write(path, dem.heights.tolist(), np.float64(dem.x0), dem.y0, dem.dx, dem.dy, dem.crs)
    grid = rasters.read_dem_raster(path)
    assert isinstance(grid, rasters.GeoRaster) and grid.nodata is None
    assert grid.data.dtype == np.float64 and np.isnan(grid.data[2, 3])
    geometry = (dem.x0, dem.y0, dem.dx, dem.dy, dem.crs)
    assert (grid.x0, grid.y0, grid.dx, grid.dy, grid.crs) == geometry
    expected = dem.heights.astype(np.float32) if suffix == ".tif" else dem.heights
    np.testing.assert_array_equal(grid.data, expected)
    saved = tmp_path / f"saved{suffix}"
    (dem.save_geotiff if suffix == ".tif" else dem.save_asc)(saved)
    assert saved.read_bytes() == path.read_bytes()
    assert DEM.load(path) == DEM(grid.data, grid.x0, grid.y0, grid.dx, grid.dy, crs=grid.crs)
    assert rasters.GeoError is GeoError


def test_a_raster_larger_than_the_limit_is_refused_before_decoding(tmp_path, monkeypatch):
    from napari_imgreg.io import rasters

    dem = DEM.from_array(np.zeros((4, 5)), 0.0, 100.0, 10.0, 10.0, crs="EPSG:32630")
    path = tmp_path / "dem.tif"
    dem.save_geotiff(path)
    monkeypatch.setattr(rasters, "MAX_RASTER_CELLS", 19)
    with pytest.raises(rasters.GeoError, match=r"dem.tif: 5×4 cells is more than 19"):
        DEM.load(path)


@pytest.mark.parametrize("origin", [[53.35, -1.81, 350.0], [-1.81, 53.35, 350.0]])
def test_an_origin_in_degrees_is_refused(origin):
    """Latitude and longitude written as the origin: read as UTM metres they
    lie outside the zone, on the equator. One line saying what was expected."""
    with pytest.raises(GeoError) as err:
        Georef.from_dict({"crs": "EPSG:32630", "origin": origin}, source="georef.json")
    message = str(err.value)
    assert "\n" not in message and message.startswith("georef.json: field 'origin' [")
    assert "looks like latitude and longitude, not EPSG:32630's easting and northing" in message


@pytest.mark.parametrize("crs, origin", [
    ("EPSG:32630", [579000.0, 5912000.0, 350.0]),
    ("EPSG:32630", [0.0, 0.0, 0.0]),      # a model already in map coordinates
    ("EPSG:27700", [10.0, 20.0, 0.0]),    # near the British grid's false origin: inside its area
])
def test_an_origin_the_crs_is_used_for_is_accepted(crs, origin):
    assert Georef.from_dict({"crs": crs, "origin": origin}).crs == crs
