"""Point-cloud readers and writers (io/pointclouds.py): round trips of every
format, one-line errors for bad files, the LAS CRS rule, voxel decimation."""

from __future__ import annotations

import numpy as np
import pytest

from napari_imgreg.errors import InputError
from napari_imgreg.geo import Georef
from napari_imgreg.io.pointclouds import (
    PointCloud,
    PointCloudParams,
    is_point_cloud_file,
    read_point_cloud,
    write_point_cloud,
)

FORMATS = [".las", ".laz", ".e57", ".ply", ".pts", ".xyz"]
# xyz resolution of each format as written: LAS 0.1 mm integers, text 0.1 mm
# decimals, E57 float32 around the scan's centre, PLY double.
XYZ_TOL = {".las": 5.1e-5, ".laz": 5.1e-5, ".pts": 5.1e-5, ".xyz": 5.1e-5, ".e57": 1e-5, ".ply": 1e-12}
# intensity resolution: LAS 16-bit, PTS −2048…2047, XYZ 6 decimals, floats
INTENSITY_TOL = {".las": 1 / 65535, ".laz": 1 / 65535, ".pts": 1 / 4095, ".xyz": 1e-6, ".e57": 1e-6,
                 ".ply": 1e-6}


@pytest.fixture(scope="module")
def cloud() -> PointCloud:
    """2000 points of a 30 × 6 m cliff; intensity with 1 % at 0 and 1 % at 1,
    so that its 0.5th/99.5th percentiles are exactly 0 and 1 and the reader's
    normalisation is the identity."""
    rng = np.random.default_rng(3)
    n = 2000
    xyz = np.column_stack([rng.uniform(0, 30, n), rng.normal(0, 0.3, n), rng.uniform(0, 6, n)])
    intensity = rng.uniform(0, 1, n).astype(np.float32)
    intensity[:20], intensity[20:40] = 0.0, 1.0
    rgb = rng.integers(0, 256, (n, 3)).astype(np.uint8)
    return PointCloud(xyz, intensity, rgb)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return tmp_path_factory.mktemp("clouds")


@pytest.fixture(scope="module")
def written(cloud, folder):
    paths = {}
    for suffix in FORMATS:
        paths[suffix] = write_point_cloud(folder / f"cloud{suffix}", cloud)
    return paths


@pytest.mark.parametrize("suffix", FORMATS)
def test_round_trip(cloud, written, suffix):
    back = read_point_cloud(written[suffix])
    assert len(back) == len(cloud) and back.n_points_file == len(cloud)
    assert back.xyz.dtype == np.float64
    np.testing.assert_allclose(back.xyz, cloud.xyz, rtol=0, atol=XYZ_TOL[suffix])
    assert back.intensity is not None and back.intensity.dtype == np.float32
    np.testing.assert_allclose(back.intensity, cloud.intensity, rtol=0, atol=INTENSITY_TOL[suffix] * 0.51)
    assert back.intensity.min() == 0.0 and back.intensity.max() == 1.0
    np.testing.assert_array_equal(back.rgb, cloud.rgb)
    assert back.origin_subtracted is None and back.voxel_m is None
    assert any("model frame" in note for note in back.notes)
    assert back.source == written[suffix]


def test_without_intensity_or_colour(folder):
    xyz = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [4.0, 5.0, 6.5]])
    for suffix in FORMATS:
        back = read_point_cloud(write_point_cloud(folder / f"bare{suffix}", PointCloud(xyz)))
        np.testing.assert_allclose(back.xyz, xyz, atol=XYZ_TOL[suffix])
        assert back.intensity is None and back.rgb is None, suffix


def test_intensity_normalised_on_robust_percentiles(folder):
    """Raw intensities 100…200 with 0.3 % specular spikes at 5000: the spikes
    clip to 1 and the bulk spans the range (0.5th–99.5th percentiles)."""
    n = 2000
    raw = np.linspace(100.0, 200.0, n)
    raw[::337] = 5000.0
    xyz = np.column_stack([np.arange(n) * 0.01, np.zeros(n), np.zeros(n)])
    path = folder / "spiky.xyz"
    np.savetxt(path, np.column_stack([xyz, raw]), fmt="%.6f")
    back = read_point_cloud(path)
    lo, hi = np.percentile(raw, [0.5, 99.5])
    np.testing.assert_allclose(back.intensity, np.clip((raw - lo) / (hi - lo), 0, 1), atol=1e-6)
    assert back.intensity_range == pytest.approx((lo, hi))
    assert (back.intensity[::337] == 1.0).all()


def test_las_colour_depth(folder):
    """LAS colours are 16-bit; a file whose colours are all ≤ 255 wrote 8-bit
    values and is taken as such, with a note."""
    import laspy

    header = laspy.LasHeader(point_format=7, version="1.4")
    header.scales = [0.001] * 3
    points = laspy.ScaleAwarePointRecord.zeros(3, header=header)
    points.x = [0.0, 1.0, 2.0]
    points.red, points.green, points.blue = [10, 200, 255], [0, 1, 2], [255, 255, 255]
    with laspy.open(folder / "rgb8.las", mode="w", header=header) as writer:
        writer.write_points(points)
    back = read_point_cloud(folder / "rgb8.las")
    np.testing.assert_array_equal(back.rgb[:, 0], [10, 200, 255])
    assert any("8-bit" in note for note in back.notes)
    points.red = [10 * 257, 200 * 257, 65535]
    with laspy.open(folder / "rgb16.las", mode="w", header=header) as writer:
        writer.write_points(points)
    np.testing.assert_array_equal(read_point_cloud(folder / "rgb16.las").rgb[:, 0], [10, 200, 255])


def test_e57_scans_merged_with_their_poses(folder):
    """Two scans, the second turned 90° about z and moved: points come back
    in the file's frame, p' = R p + t."""
    import pye57

    local = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.5], [3.0, 1.0, -1.0]])
    q90z = np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])  # w, x, y, z
    path = folder / "two_scans.e57"
    e57 = pye57.E57(str(path), mode="w")
    scan = {"cartesianX": local[:, 0], "cartesianY": local[:, 1], "cartesianZ": local[:, 2],
            "intensity": np.array([0.1, 0.5, 0.9], np.float32)}
    e57.write_scan_raw(scan, rotation=np.array([1.0, 0, 0, 0]), translation=np.zeros(3))
    e57.write_scan_raw(scan, rotation=q90z, translation=np.array([10.0, 20.0, 30.0]))
    e57.close()
    back = read_point_cloud(path)
    turned = np.column_stack([-local[:, 1], local[:, 0], local[:, 2]]) + [10.0, 20.0, 30.0]
    np.testing.assert_allclose(back.xyz, np.vstack([local, turned]), atol=1e-5)
    assert back.intensity is not None and len(back.intensity) == 6
    assert any("2 scans merged" in note for note in back.notes)


def test_e57_scan_with_no_points_is_skipped(folder):
    """libE57 fails on an empty scan's data: it is skipped with a note, and a
    file of empty scans only is "holds no points", not libE57's internal error."""
    import pye57

    class Empty(np.ndarray):  # pye57 takes min() and max() of each field for its header
        def min(self, *a, **k):
            return 0.0 if self.size == 0 else np.ndarray.min(np.asarray(self), *a, **k)

        def max(self, *a, **k):
            return 1.0 if self.size == 0 else np.ndarray.max(np.asarray(self), *a, **k)

    def empty_scan():
        return {k: np.zeros(0).view(Empty) for k in ("cartesianX", "cartesianY", "cartesianZ")}

    local = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.5], [3.0, 1.0, -1.0]])
    path = folder / "empty_then_full.e57"
    e57 = pye57.E57(str(path), mode="w")
    e57.write_scan_raw(empty_scan(), name="empty")
    e57.write_scan_raw({"cartesianX": local[:, 0], "cartesianY": local[:, 1],
                        "cartesianZ": local[:, 2]}, name="full")
    e57.close()
    back = read_point_cloud(path)
    np.testing.assert_allclose(back.xyz, local, atol=1e-5)
    assert any("scan 1 of 2 holds no points" in note for note in back.notes)
    only_empty = folder / "only_empty.e57"
    e57 = pye57.E57(str(only_empty), mode="w")
    e57.write_scan_raw(empty_scan(), name="empty")
    e57.close()
    with pytest.raises(InputError, match="holds no points"):
        read_point_cloud(only_empty)


def test_text_variants(folder):
    """PTS with several blocks (a count line each); XYZ with commas, a header
    line and comments."""
    pts = folder / "blocks.pts"
    pts.write_text("2\n0 0 0 -2048 10 20 30\n1 0 0 2047 40 50 60\n1\n2 0 0 0 70 80 90\n")
    back = read_point_cloud(pts)
    np.testing.assert_allclose(back.xyz[:, 0], [0, 1, 2])
    np.testing.assert_allclose(back.intensity, [0, 1, 2048 / 4095], atol=1e-3)
    np.testing.assert_array_equal(back.rgb[:, 2], [30, 60, 90])
    xyz = folder / "commas.xyz"
    xyz.write_text("# exported\nX,Y,Z,R,G,B\n1.5,2.5,3.5,1,2,3\n4.5,5.5,6.5,4,5,6\n")
    back = read_point_cloud(xyz)
    np.testing.assert_allclose(back.xyz, [[1.5, 2.5, 3.5], [4.5, 5.5, 6.5]])
    assert back.intensity is None
    np.testing.assert_array_equal(back.rgb, [[1, 2, 3], [4, 5, 6]])
    # CloudCompare's order: a header naming the columns, intensity last, an extra column
    named = folder / "named.xyz"
    named.write_text("//X,Y,Z,R,G,B,Intensity,Dip\n0,0,0,9,8,7,10,5\n1,1,1,6,5,4,20,5\n2,2,2,3,2,1,30,5\n")
    back = read_point_cloud(named, params=PointCloudParams(intensity_percentiles=(0, 100)))
    np.testing.assert_allclose(back.intensity, [0, 0.5, 1])
    np.testing.assert_array_equal(back.rgb[:, 0], [9, 6, 3])
    assert any("ignored" in note for note in back.notes)
    # x y z nx ny nz: normals are not colours
    normals = folder / "normals.xyz"
    normals.write_text("0 0 0 0 -0.6 0.8\n1 0 0 0 0.6 0.8\n")
    back = read_point_cloud(normals)
    assert back.rgb is None and any("normals" in note for note in back.notes)


def test_is_point_cloud_file(written, folder):
    mesh = folder / "tri.ply"
    mesh.write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
    )
    assert all(is_point_cloud_file(p) for p in written.values())
    assert not is_point_cloud_file(mesh)
    assert not is_point_cloud_file(folder / "model.obj")


# -- bad files: one line naming the file ----------------------------------------


def _bad_files(written, folder, cloud):
    def cut(suffix, fraction=0.6):
        data = written[suffix].read_bytes()
        path = folder / f"cut{suffix}"
        path.write_bytes(data[: int(len(data) * fraction)])
        return path

    def shifted(suffix):
        """Bytes inserted in the points: the chunk table offset now points at
        point data (an unchecked lazrs would allocate gigabytes and abort)."""
        data = written[suffix].read_bytes()
        path = folder / f"shifted{suffix}"
        path.write_bytes(data[: len(data) // 2] + b"\x7f" * 44 + data[len(data) // 2 :])
        return path

    def text(name, content):
        path = folder / name
        path.write_text(content)
        return path

    def patched(suffix, name, fmt, at, *values):
        """A LAS/LAZ with header fields set (at the LAS 1.4 public header's offsets)."""
        import struct

        data = bytearray(written[suffix].read_bytes())
        struct.pack_into(fmt, data, at, *values)
        path = folder / f"{name}{suffix}"
        path.write_bytes(bytes(data))
        return path

    return {
        # header fields checked against the file's size before laspy reads
        "VLR count beyond the room": (patched(".las", "vlrs", "<I", 100, 2**32 - 1), "number of VLRs"),
        "LAZ VLR count beyond the room": (patched(".laz", "vlrs", "<I", 100, 2**32 - 1), "number of VLRs"),
        "point offset beyond the file": (patched(".las", "offset", "<I", 96, 2**32 - 1),
                                         "offset to the point data"),
        "EVLR beyond the file": (patched(".las", "evlr", "<QI", 235, 0, 1), "EVLR 1 of 1"),
        "EVLRs beyond the file": (patched(".las", "evlrs", "<QI", 235, 375, 2**32 - 1), "EVLRs from byte"),
        "LAS points beyond the file": (patched(".las", "count", "<Q", 247, 10**6), "record length"),
        "LAZ count beyond its bytes": (patched(".laz", "count", "<Q", 247, 2**40), "compressed points"),
        # a scale of 0 put every point on the offset: n² normals (hours at 1 M points)
        "LAS scale factors 0": (patched(".las", "scale0", "<3d", 131, 0.0, 0.0, 0.0),
                                "scale factors are 0, 0, 0: each must be a finite number other than 0"),
        "LAZ scale factor NaN": (patched(".laz", "scalenan", "<3d", 131, 0.001, float("nan"), 0.001),
                                 "scale factors are 0.001, nan, 0.001"),
        "every point at one position": (text("one.xyz", "1 2 3\n" * 50),
                                        "all 50 points lie at one position (1.000, 2.000, 3.000): no surface"),
        "truncated LAZ": (cut(".laz"), "truncated"),
        "truncated LAS": (cut(".las"), "truncated"),
        "LAZ chunk table moved": (shifted(".laz"), "cannot read LAZ"),
        "garbage LAS": (text("garbage.las", "not a las file at all" * 20), "cannot read LAS"),
        "truncated E57": (cut(".e57"), "truncated"),
        "garbage E57": (text("garbage.e57", "hello" * 40), "not an E57 file"),
        "truncated binary PLY": (cut(".ply"), "truncated"),
        "truncated ASCII PLY": (text(
            "cut_ascii.ply",
            "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
            "end_header\n0 0 0\n1 1 1\n"), "truncated"),
        "PLY with faces": (folder / "tri.ply", "it is a mesh"),
        "truncated PTS": (text("cut.pts", "3\n0 0 0 1\n1 1 1 2\n"), "truncated"),
        "bad XYZ line": (text("bad.xyz", "0 0 0\n1 1 1\n2 x 2\n"), "line 3"),
        "NaN coordinates": (text("nan.xyz", "0 0 0\nnan 1 1\n"), "NaN"),
        "empty PTS": (text("empty.pts", "0\n"), "no points"),
        "empty LAS": (None, "no points"),
        "zero bytes": (text("zero.laz", ""), "empty"),
        "unknown suffix": (text("cloud.dat", "0 0 0\n"), "not a point cloud format"),
        "missing": (folder / "missing.las", "no such file"),
    }


def test_bad_files_one_line(written, folder, cloud):
    import laspy

    bad = _bad_files(written, folder, cloud)
    empty = folder / "empty.las"
    with laspy.open(empty, mode="w", header=laspy.LasHeader(point_format=6, version="1.4")):
        pass
    bad["empty LAS"] = (empty, "no points")
    for what, (path, words) in bad.items():
        with pytest.raises(InputError) as info:
            read_point_cloud(path)
        message = str(info.value)
        assert "\n" not in message, what
        assert message.startswith(f"{path}: "), (what, message)
        assert words in message, (what, message)


def test_e57_error_prints_nothing_else(written, folder, capfd):
    """libE57 reports its exceptions on stderr: the reader keeps them quiet,
    so the user sees our one line only."""
    path = folder / "flipped.e57"
    data = bytearray(written[".e57"].read_bytes())
    data[2000:2100] = b"\xff" * 100  # inside the XML section, after a valid physical header
    path.write_bytes(bytes(data))
    with pytest.raises(InputError):
        read_point_cloud(path)
    assert capfd.readouterr().err == ""


# -- the CRS rule -----------------------------------------------------------------

ORIGIN = np.array([579000.0, 5912000.0, 350.0])


@pytest.fixture(scope="module")
def utm_las(cloud, folder):
    """The cliff in UTM 30N map coordinates, with an EPSG:32630 record."""
    mapped = PointCloud(cloud.xyz + ORIGIN, cloud.intensity, cloud.rgb, crs_epsg=32630)
    return write_point_cloud(folder / "utm.laz", mapped)


def test_crs_matching_georef_subtracts_origin(cloud, utm_las, folder):
    back = read_point_cloud(utm_las, georef=Georef("EPSG:32630", ORIGIN))
    np.testing.assert_allclose(back.xyz, cloud.xyz, atol=5.1e-5)
    np.testing.assert_array_equal(back.origin_subtracted, ORIGIN)
    assert back.crs_epsg == 32630 and "UTM zone 30N" in back.crs_wkt
    assert any("matches georef.json" in note for note in back.notes)
    # written back, it holds map coordinates and its record again
    again = read_point_cloud(write_point_cloud(folder / "utm_again.las", back),
                             georef=Georef("EPSG:32630", ORIGIN))
    np.testing.assert_allclose(again.xyz, cloud.xyz, atol=1.1e-4)


def test_las12_with_geotiff_keys(cloud, folder):
    """The common older files: LAS 1.2, point format 3, compressed, the CRS
    as GeoTIFF keys."""
    import laspy
    import pyproj

    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales, header.offsets = [0.001] * 3, np.floor(ORIGIN)
    header.add_crs(pyproj.CRS("EPSG:32630"))
    points = laspy.ScaleAwarePointRecord.zeros(len(cloud), header=header)
    mapped = cloud.xyz + ORIGIN
    points.x, points.y, points.z = mapped[:, 0], mapped[:, 1], mapped[:, 2]
    points.intensity = np.rint(cloud.intensity * 65535).astype(np.uint16)
    path = folder / "old.laz"
    with laspy.open(path, mode="w", header=header) as writer:
        writer.write_points(points)
    back = read_point_cloud(path, georef=Georef("EPSG:32630", ORIGIN))
    np.testing.assert_allclose(back.xyz, cloud.xyz, atol=5.1e-4)
    assert back.crs_epsg == 32630 and back.origin_subtracted is not None
    np.testing.assert_allclose(back.intensity, cloud.intensity, atol=1e-4)


def test_compound_crs_matches_on_its_horizontal_part(cloud, folder):
    """UTM 30N + ODN heights in the file, UTM 30N in georef.json: a match."""
    import pyproj

    compound = pyproj.CRS("EPSG:32630+5701")
    mapped = PointCloud(cloud.xyz + ORIGIN, crs_wkt=compound.to_wkt())
    path = write_point_cloud(folder / "compound.las", mapped)
    back = read_point_cloud(path, georef=Georef("EPSG:32630", ORIGIN))
    np.testing.assert_allclose(back.xyz, cloud.xyz, atol=5.1e-5)
    assert any("horizontal CRS matches" in note for note in back.notes)


def test_crs_differing_or_absent_keeps_coordinates(cloud, utm_las, written):
    other = read_point_cloud(utm_las, georef=Georef("EPSG:32631", ORIGIN))
    np.testing.assert_allclose(other.xyz, cloud.xyz + ORIGIN, atol=5.1e-5)
    assert other.origin_subtracted is None
    assert any("differs from georef.json's EPSG:32631" in note and "model frame" in note for note in other.notes)
    assert any("look like map coordinates" in note for note in other.notes)
    no_georef = read_point_cloud(utm_las)
    assert no_georef.origin_subtracted is None
    assert any("no georef.json" in note for note in no_georef.notes)
    no_record = read_point_cloud(written[".laz"], georef=Georef("EPSG:32630", ORIGIN))
    np.testing.assert_allclose(no_record.xyz, cloud.xyz, atol=5.1e-5)
    assert no_record.origin_subtracted is None and no_record.crs_epsg is None
    assert "no CRS record: coordinates taken as the model frame" in no_record.notes


def test_a_las_in_degrees_is_refused_before_its_points_are_decoded(cloud, folder, monkeypatch):
    """From the header's bounds: a 50 M-point LAZ is not decoded for minutes first."""
    from napari_imgreg.io import pointclouds

    degrees = cloud.xyz * [1e-5, 1e-5, 1.0] + [-3.5, 53.3, 350.0]
    path = write_point_cloud(folder / "lonlat_early.laz", PointCloud(degrees, crs_epsg=4326))

    def decoded(*args, **kwargs):
        raise AssertionError("points decoded before the refusal")

    monkeypatch.setattr(pointclouds._Accumulator, "add", decoded)
    with pytest.raises(InputError, match="longitude/latitude in degrees"):
        read_point_cloud(path)


def test_a_cloud_in_degrees_is_refused_in_one_line(cloud, folder):
    """A LAS whose CRS record is geographic holds longitude/latitude: taken as
    metres it was a cliff 0.0003 units wide and 6 m high, rendered as nothing
    (\"surface covers 0 %\"). It is refused, naming the CRS to reproject to."""
    degrees = cloud.xyz * [1e-5, 1e-5, 1.0] + [-3.5, 53.3, 350.0]
    path = write_point_cloud(folder / "lonlat.las", PointCloud(degrees, cloud.intensity, crs_epsg=4326))
    with pytest.raises(InputError) as exc:
        read_point_cloud(path)
    assert str(exc.value) == (
        f"{path}: coordinates are longitude/latitude in degrees (CRS record EPSG:4326, geographic), "
        "not metres: reproject the cloud to a projected CRS such as UTM first (e.g. with PDAL or "
        "CloudCompare)")
    with pytest.raises(InputError, match="reproject the cloud to georef.json's EPSG:32630 first"):
        read_point_cloud(path, georef=Georef("EPSG:32630", ORIGIN))
    # A record that says degrees over coordinates that cannot be: the CRS rule's model frame.
    wrong = write_point_cloud(folder / "wrong_record.las", PointCloud(cloud.xyz + ORIGIN, crs_epsg=4326))
    back = read_point_cloud(wrong, georef=Georef("EPSG:32630", ORIGIN))
    assert back.origin_subtracted is None and any("differs from georef.json" in n for n in back.notes)


def test_coarse_las_scale_factors_are_said(cloud, folder):
    """A LAS stored to 1 m rounds a scan's detail away (and stacks points):
    read, with a note naming the scale factors."""
    import laspy

    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = [1.0, 1.0, 1.0], [0.0, 0.0, 0.0]
    las = laspy.LasData(header)
    las.x, las.y, las.z = cloud.xyz.T
    path = folder / "metre.las"
    las.write(path)
    back = read_point_cloud(path)
    assert "coordinates stored to 1 m (its header's scale factors 1, 1, 1): detail finer than that is lost" \
        in back.notes
    assert not any("stored to" in note for note in read_point_cloud(folder / "cloud.las").notes)


# -- decimation ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def dense_wall(folder):
    """A 20 × 5 m wall scanned at ~3 cm (120 k points) in scan-line order;
    intensity a smooth ramp along x."""
    rng = np.random.default_rng(5)
    n = 120_000
    x, z = rng.uniform(0, 20, n), rng.uniform(0, 5, n)
    order = np.lexsort((z, np.floor(x / 0.5)))  # scan columns, as a scanner writes them
    xyz = np.column_stack([x, 0.02 * np.sin(x) + rng.normal(0, 0.002, n), z])[order]
    intensity = (xyz[:, 0] / 20.0).astype(np.float32)
    intensity[:1000], intensity[1000:2000] = 0.0, 1.0  # pins the percentiles: identity normalisation
    cloud = PointCloud(xyz, intensity)
    return cloud, write_point_cloud(folder / "wall.laz", cloud)


@pytest.mark.parametrize("chunk", [8_000, 2_000_000])
def test_decimation_fits_and_keeps_bounds(dense_wall, chunk):
    cloud, path = dense_wall
    cap = 10_000
    back = read_point_cloud(path, params=PointCloudParams(max_points=cap, chunk_points=chunk))
    assert 0.85 * cap <= len(back) <= cap  # the voxel measured on the first chunk fills the cap
    assert back.n_points_file == len(cloud) and back.voxel_m is not None
    lo, hi = cloud.bounds
    blo, bhi = back.bounds
    assert (blo >= lo - 1e-4).all() and (bhi <= hi + 1e-4).all()
    assert (blo - lo < 2 * back.voxel_m).all() and (hi - bhi < 2 * back.voxel_m).all()
    assert any(note.startswith("decimated 120 k → ") and "voxel grid" in note for note in back.notes)
    # kept points are measured points (on the 0.1 mm grid of the file), not centroids
    tree_idx = np.searchsorted(np.sort(np.round(cloud.xyz[:, 0], 4)), np.round(back.xyz[:, 0], 4))
    assert (tree_idx < len(cloud)).all()
    # the ramp survives the per-voxel averaging: intensity ≈ x / 20 within a voxel's span
    inner = (back.xyz[:, 0] > 1) & (back.xyz[:, 0] < 19)
    err = np.abs(back.intensity[inner] - back.xyz[inner, 0] / 20.0)
    assert np.median(err) < back.voxel_m / 20.0


@pytest.mark.parametrize("chunk", [8_000, 2_000_000])
def test_decimation_of_a_shuffled_file_fills_the_cap_too(dense_wall, folder, chunk):
    """Points not in scan order (a shuffled or merged export): the first chunk
    is a thin sample of the whole surface, not a full-density patch."""
    cloud, _ = dense_wall
    order = np.random.default_rng(1).permutation(len(cloud.xyz))
    shuffled = write_point_cloud(folder / "wall_shuffled.laz",
                                 PointCloud(cloud.xyz[order], cloud.intensity[order]))
    cap = 10_000
    back = read_point_cloud(shuffled, params=PointCloudParams(max_points=cap, chunk_points=chunk))
    assert 0.8 * cap <= len(back) <= cap


def test_a_cloud_decimated_far_under_the_cap_is_read_again(dense_wall, folder, monkeypatch):
    """Whatever misled the first voxel (here: the first points taken for a
    full-density patch when they are a thin sample of a shuffled file), a
    result far under the cap is read again on a finer voxel."""
    import napari_imgreg.io.pointclouds as pointclouds

    cloud, _ = dense_wall
    order = np.random.default_rng(1).permutation(len(cloud.xyz))
    shuffled = write_point_cloud(folder / "wall_shuffled_again.laz",
                                 PointCloud(cloud.xyz[order], cloud.intensity[order]))
    monkeypatch.setattr(pointclouds._Accumulator, "_spans_the_file", lambda self, sample: False)
    cap = 10_000
    back = read_point_cloud(shuffled, params=PointCloudParams(max_points=cap, chunk_points=8_000))
    assert 0.8 * cap <= len(back) <= cap
    assert any(note.startswith("read twice") for note in back.notes)


def test_fixed_voxel_keeps_the_first_point_of_each_voxel(dense_wall):
    """With voxel_m and no cap, the kept points are exactly the first point
    (in file order) of each occupied voxel of the grid anchored at the bounding box."""
    _, path = dense_wall
    voxel = 0.25
    back = read_point_cloud(path, max_points=None, voxel_m=voxel)
    assert back.voxel_m == voxel
    stored = read_point_cloud(path, max_points=None).xyz  # the file's own (quantised) coordinates
    lo = stored.min(axis=0)
    cells = np.floor((stored - lo) / voxel).astype(np.int64)
    _, first = np.unique((cells[:, 0] * 1000 + cells[:, 1]) * 1000 + cells[:, 2], return_index=True)
    np.testing.assert_allclose(back.xyz, stored[np.sort(first)], atol=1e-9)


def test_in_memory_formats_decimate_too(dense_wall, folder):
    cloud, _ = dense_wall
    path = write_point_cloud(folder / "wall.ply", cloud)
    back = read_point_cloud(path, max_points=10_000)
    assert 8_500 <= len(back) <= 10_000
    assert any("decimated" in note for note in back.notes)


def test_params_are_checked():
    for bad in ({"max_points": 0}, {"voxel_m": -1.0}, {"intensity_percentiles": (60, 40)},
                {"chunk_points": 10}):
        with pytest.raises(ValueError):
            PointCloudParams(**bad)


def test_the_finer_voxel_of_a_second_read():
    from napari_imgreg.io.pointclouds import _finer_voxel

    # Kept 6.7 M of 12 M on 8.3 cm: about 5.8 cm for 9.7 M (a shuffled scan).
    assert _finer_voxel(0.0825, 6_660_000, 12_000_000, 10_000_000) == pytest.approx(0.0578,
                                                                                    abs=5e-4)
    # Nothing to find: a voxel out of range, everything kept, nothing kept.
    assert _finer_voxel(1.3e154, 2, 3, 2) is None
    assert _finer_voxel(float("inf"), 2, 300, 200) is None
    assert _finer_voxel(0.1, 300, 300, 200) is None
    assert _finer_voxel(0.1, 0, 300, 200) is None


@pytest.mark.parametrize("suffix", [".ply", ".las"])
def test_missed_returns_stacked_on_one_position_are_left_out(cloud, folder, suffix):
    """A scanner writing its missed returns at (0, 0, 0): 5000 points on one
    position. They are left out with a note (their neighbour search grew with
    the square of their number: 100,000 of them took 25 s more to load), and
    the cliff's points stay, each with its intensity and colour."""
    stacked = 5000
    xyz = np.vstack([cloud.xyz, np.zeros((stacked, 3))])
    intensity = np.concatenate([cloud.intensity, np.full(stacked, 0.5, np.float32)])
    rgb = np.vstack([cloud.rgb, np.zeros((stacked, 3), np.uint8)])
    path = write_point_cloud(folder / f"missed{suffix}", PointCloud(xyz, intensity, rgb))
    back = read_point_cloud(path)
    assert len(back) == len(cloud) and back.n_points_file == len(cloud) + stacked
    np.testing.assert_allclose(back.xyz, cloud.xyz, rtol=0, atol=XYZ_TOL[suffix])
    np.testing.assert_array_equal(back.rgb, cloud.rgb)
    assert len(back.intensity) == len(cloud)
    note = next(n for n in back.notes if "stacked" in n)
    assert note.startswith("5000 points stacked on 1 position(s) (e.g. (0.000, 0.000, 0.000)")
    assert note.endswith("a scanner's missed returns, left out")
    # 1000 on one position (a coarsely quantised scan near its scanner) stay.
    xyz = np.vstack([cloud.xyz, np.full((1000, 3), 2.0)])
    path = write_point_cloud(folder / f"dense{suffix}", PointCloud(xyz, None, None))
    back = read_point_cloud(path)
    assert len(back) == len(xyz) and not any("stacked" in n for n in back.notes)
