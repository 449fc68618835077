"""Generated terrestrial laser scans (issue 16): geometry, intensity model, LAS round trip.

A tiny scene with an exactly known answer: a vertical wall (the plane y = 0,
two horizontal beds: sandstone below z = 6 m, mudstone above) standing on
flat ground (z = 0), scanned at a coarse 10 mrad step from 15 m. The tests of
the rock types, the cos law and the noise switch the within-bed texture off
(``texture_amplitude=0``, scan version 1's flat beds); the texture has its own.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from napari_imgreg.geo import Georef
from napari_imgreg.sample.scan import (
    DEFAULT_REFLECTANCE,
    ScanSpec,
    SurfaceCover,
    VisibleAlbedo,
    simulate_scan,
    station_positions,
    texture_field,
    value_noise,
    write_scan,
)
from napari_imgreg.scene import Scene

BOUNDARY_Z = 6.0
WALL_TOP = 12.0
GEOLOGY = {
    "bedding": {"normal": [0.0, 0.0, 1.0], "reference_point": [0.0, 0.0, 0.0]},
    "boundaries_h": [BOUNDARY_Z],
    "beds": [{"lithology": "sandstone"}, {"lithology": "mudstone"}],
}
STATION_XY = (0.0, -15.0)
# Coarse: ≈ 16 k rays per station; the wall spans ±69° in azimuth from it.
COARSE = dict(step_mrad=10.0, azimuth_half_width_deg=60.0, elevation_range_deg=(-10.0, 35.0),
              stations_xy=(STATION_XY,))
#: Flat beds: the within-bed texture off.
FLAT = dict(texture_amplitude=0.0)


@pytest.fixture(scope="module")
def wall() -> Scene:
    """The wall (x in ±40 m, up to 12 m) on flat ground reaching 40 m in front of it."""
    wall_v = [[-40, 0, 0], [40, 0, 0], [40, 0, WALL_TOP], [-40, 0, WALL_TOP]]
    ground_v = [[-40, -40, 0], [40, -40, 0], [40, 0, 0], [-40, 0, 0]]
    scene = Scene(np.array(wall_v + ground_v, np.float64),
                  np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]]), name="wall")
    scene.build_engine()
    return scene


def _truth(xyz: np.ndarray, origin: np.ndarray) -> dict[str, np.ndarray]:
    """Exact first hits of the rays through the scanned points (noise is along the ray)."""
    d = xyz - origin
    r = np.linalg.norm(d, axis=1)
    d = d / r[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_wall = np.where(d[:, 1] > 0, -origin[1] / d[:, 1], np.inf)
        t_ground = np.where(d[:, 2] < 0, -origin[2] / d[:, 2], np.inf)
    z_wall = origin[2] + t_wall * d[:, 2]
    on_wall = (t_wall < t_ground) & (z_wall >= 0) & (z_wall <= WALL_TOP)
    t = np.where(on_wall, t_wall, t_ground)
    hit = origin + d * t[:, None]
    cos_inc = np.where(on_wall, np.abs(d[:, 1]), np.abs(d[:, 2]))
    return {"measured": r, "range": t, "hit": hit, "on_wall": on_wall, "cos": cos_inc}


@pytest.fixture(scope="module")
def default_scan(wall):
    spec = ScanSpec(**COARSE, **FLAT, bed_reflectance_variation=0.0)
    stations = station_positions(wall, spec)
    return spec, stations, simulate_scan(wall, GEOLOGY, spec, stations=stations)


def test_stations_stand_on_the_ground_at_tripod_height(wall):
    spec = ScanSpec(standoff_m=15.0, station_spacing_m=10.0, step_mrad=10.0)
    st = station_positions(wall, spec)
    np.testing.assert_allclose(st, [[-5.0, -15.0, 1.7], [5.0, -15.0, 1.7]], atol=1e-5)
    with pytest.raises(ValueError, match="no ground"):
        station_positions(wall, ScanSpec(stations_xy=((0.0, -100.0),)))


def test_points_lie_on_the_surface_within_the_range_noise(default_scan):
    spec, stations, (xyz, intensity, station) = default_scan
    assert xyz.dtype == np.float64 and xyz.shape[1] == 3
    assert intensity.dtype == np.float32 and station.dtype == np.uint8
    assert len(xyz) == len(intensity) == len(station)
    az, el = spec.scan_angles()
    # Rays above the wall see the sky: dropped, not returned as points.
    assert 0.5 * len(az) * len(el) < len(xyz) < len(az) * len(el)
    tr = _truth(xyz, stations[0])
    assert tr["on_wall"].sum() > 3000
    residual = tr["measured"] - tr["range"]
    assert abs(residual.mean()) < 3e-4
    assert residual.std() == pytest.approx(0.005, rel=0.05)
    # Across the wall: within a few sigma of the plane.
    assert np.abs(xyz[tr["on_wall"], 1]).max() < 0.03


def test_intensity_is_reflectance_times_cos_times_falloff(wall):
    """No noise: exactly rho(rock type or cover) * |cos(incidence)| * min(1, 20 m / R)."""
    scene = wall
    spec = ScanSpec(**COARSE, **FLAT, intensity_noise=0.0, range_noise_m=0.0,
                    bed_reflectance_variation=0.0)
    stations = station_positions(scene, spec)
    xyz, intensity, _ = simulate_scan(scene, GEOLOGY, spec, stations=stations)
    tr = _truth(xyz, stations[0])
    z = tr["hit"][:, 2]
    rho = np.where(tr["on_wall"], np.where(z < BOUNDARY_Z, 0.55, 0.30), DEFAULT_REFLECTANCE["vegetation"])
    expected = rho * tr["cos"] * np.minimum(1.0, 20.0 / tr["range"])
    clear = ~(tr["on_wall"] & (np.abs(z - BOUNDARY_Z) < 1e-3))  # not on the contact itself
    np.testing.assert_allclose(intensity[clear], expected[clear], rtol=2e-5, atol=1e-6)
    # Incidence spans enough for the cos law to be tested (0.45 .. 1 on the wall).
    assert tr["cos"][tr["on_wall"]].min() < 0.5


def test_sandstone_is_brighter_than_mudstone_at_equal_incidence(default_scan):
    _, stations, (xyz, intensity, _) = default_scan
    tr = _truth(xyz, stations[0])
    z = tr["hit"][:, 2]
    ratios = []
    # Equal incidence on the wall is equal range too: the falloff cancels.
    for lo in np.arange(0.6, 0.96, 0.02):
        band = tr["on_wall"] & (tr["cos"] >= lo) & (tr["cos"] < lo + 0.02)
        sand, mud = band & (z < BOUNDARY_Z - 0.1), band & (z > BOUNDARY_Z + 0.1)
        if sand.sum() > 30 and mud.sum() > 30:
            ratios.append(intensity[sand].mean() / intensity[mud].mean())
    assert len(ratios) >= 3
    np.testing.assert_allclose(ratios, 0.55 / 0.30, rtol=0.05)


def test_intensity_noise_is_two_percent_and_falls_as_cos(default_scan):
    _, stations, (xyz, intensity, _) = default_scan
    tr = _truth(xyz, stations[0])
    w = tr["on_wall"] & (np.abs(tr["hit"][:, 2] - BOUNDARY_Z) > 0.1)
    rho = np.where(tr["hit"][w, 2] < BOUNDARY_Z, 0.55, 0.30)
    model = rho * np.minimum(1.0, 20.0 / tr["range"][w])
    ratio = intensity[w] / model  # = cos(incidence) * (1 + 0.02 * noise)
    slope = float(np.sum(ratio * tr["cos"][w]) / np.sum(tr["cos"][w] ** 2))
    assert slope == pytest.approx(1.0, abs=0.003)
    assert np.std(ratio / tr["cos"][w]) == pytest.approx(0.02, rel=0.1)


def test_cover_mask_and_bed_variation(wall):
    spec = ScanSpec(**COARSE, **FLAT, intensity_noise=0.0, range_noise_m=0.0,
                    falloff_exponent=0.0, bed_reflectance_variation=0.0)
    nv = len(wall.vertices)
    cover = SurfaceCover(np.zeros(nv), np.full(nv, 0.4))  # everything covered
    stations = station_positions(wall, spec)
    xyz, intensity, _ = simulate_scan(wall, GEOLOGY, spec, cover=cover, stations=stations)
    tr = _truth(xyz, stations[0])
    np.testing.assert_allclose(intensity, 0.4 * tr["cos"], rtol=2e-5, atol=1e-6)
    # Beds of one rock type differ, by the stated variation (here 30 %, one bed each).
    varied = ScanSpec(**COARSE, **FLAT, intensity_noise=0.0, falloff_exponent=0.0,
                      bed_reflectance_variation=0.3, seed=3)
    xyz, intensity, _ = simulate_scan(wall, GEOLOGY, varied, stations=stations)
    tr = _truth(xyz, stations[0])
    sand = tr["on_wall"] & (tr["hit"][:, 2] < BOUNDARY_Z - 0.1)
    rho = intensity[sand] / tr["cos"][sand]
    assert np.ptp(rho) < 1e-4 and abs(rho.mean() - 0.55) > 1e-3 and abs(rho.mean() / 0.55 - 1) <= 0.9


def test_same_seed_same_scan_whatever_the_chunking(wall, default_scan):
    _, stations, (xyz, intensity, station) = default_scan
    small = ScanSpec(**COARSE, **FLAT, bed_reflectance_variation=0.0, chunk_rays=1000)
    xyz2, intensity2, station2 = simulate_scan(wall, GEOLOGY, small, stations=stations)
    np.testing.assert_array_equal(xyz, xyz2)
    np.testing.assert_array_equal(intensity, intensity2)
    np.testing.assert_array_equal(station, station2)


def test_las_round_trip_keeps_points_intensity_stations_and_crs(wall, tmp_path):
    import laspy

    spec = ScanSpec(standoff_m=15.0, station_spacing_m=10.0, step_mrad=20.0,
                    elevation_range_deg=(-10.0, 35.0))
    stations = station_positions(wall, spec)
    scan = simulate_scan(wall, GEOLOGY, spec, stations=stations)
    assert set(np.unique(scan.station)) == {0, 1}
    georef = Georef("EPSG:32630", np.array([579000.0, 5912000.0, 350.0]))
    laz = write_scan(tmp_path, scan, spec, stations, georef)
    las = laspy.read(laz)
    assert las.header.version.major == 1 and las.header.version.minor == 4
    assert "red" not in las.point_format.dimension_names  # no colour
    assert las.header.parse_crs().to_epsg() == 32630
    back = np.column_stack([las.x, las.y, las.z]) - georef.origin
    np.testing.assert_allclose(back, scan.xyz, atol=0.0005 + 1e-6)  # the file's 1 mm scale
    np.testing.assert_allclose(np.asarray(las.intensity) / 65535.0, scan.intensity, atol=0.51 / 65535)
    np.testing.assert_array_equal(np.asarray(las.point_source_id), scan.station.astype(int) + 1)
    doc = json.loads((tmp_path / "scan.json").read_text())
    assert doc["n_points"] == len(scan.xyz) and doc["crs"] == "EPSG:32630"
    assert [s["points"] for s in doc["stations"]] == np.bincount(scan.station).tolist()
    np.testing.assert_allclose(doc["stations"][1]["position_crs"], stations[1] + georef.origin, atol=1e-4)
    assert doc["step_mrad"] == 20.0 and doc["noise"] == {"range_m": 0.005, "intensity_relative": 0.02}
    # Without a georeference: model-frame coordinates and no CRS record.
    laz = write_scan(tmp_path / "local", scan, spec, stations, None)
    las = laspy.read(laz)
    assert las.header.parse_crs() is None
    np.testing.assert_allclose(np.column_stack([las.x, las.y, las.z]), scan.xyz, atol=0.0005 + 1e-6)


def test_bad_specs_and_geology_are_refused(wall):
    for bad in (dict(step_mrad=0.0), dict(elevation_range_deg=(10.0, -10.0)),
                dict(reflectance={"sandstone": 0.5}), dict(intensity_noise=-0.1),
                dict(min_range_m=10.0, max_range_m=5.0)):
        with pytest.raises(ValueError, match="ScanSpec"):
            ScanSpec(**bad)
    limestone = {**GEOLOGY, "beds": [{"lithology": "sandstone"}, {"lithology": "limestone"}]}
    with pytest.raises(ValueError, match="limestone"):
        simulate_scan(wall, limestone, ScanSpec(**COARSE))
    with pytest.raises(ValueError, match="beds"):
        simulate_scan(wall, {**GEOLOGY, "boundaries_h": [2.0, 6.0]}, ScanSpec(**COARSE))
    assert math.isclose(ScanSpec().falloff(np.array([55.0]))[0], 20.0 / 55.0)



def test_scan_of_a_generated_outcrop_in_memory_and_from_its_folder(tmp_path):
    """The generator's cliff (coarse grid): stations in front of it, rock
    intensity by the beds of its geology, the same scan from memory and from
    the folder (whose rock mask is rebuilt from scene.json's spec and seed)."""
    from napari_imgreg.sample.outcrop import OutcropSpec, build_geometry, quantize_vertices
    from napari_imgreg.sample.scan import Strata, scan_outcrop, scan_scene_folder

    spec = OutcropSpec.for_size("small", grid=(96, 90), texture_size=256)
    oc = build_geometry(spec, 0)
    quantize_vertices(oc)
    scene = Scene(oc.vertices, oc.faces, name="cliff")
    georef = Georef(spec.crs, np.asarray(spec.origin, np.float64))
    scan = ScanSpec(step_mrad=25.0)
    files = scan_outcrop(oc, scene, georef, tmp_path / "mem", scan)
    assert files == {"scan": "scan.laz", "scan_info": "scan.json"}
    mem = json.loads((tmp_path / "mem" / "scan.json").read_text())
    assert [s["position"][:2] for s in mem["stations"]] == [[-25.0, -55.0], [25.0, -55.0]]
    # A folder as the generator writes it (only what the scan reads).
    folder = tmp_path / "scene"
    folder.mkdir()
    with open(folder / "outcrop.obj", "w") as fh:
        fh.writelines(f"v {x:.4f} {y:.4f} {z:.4f}\n" for x, y, z in oc.vertices)
        fh.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in oc.faces)
    (folder / "geology.json").write_text(json.dumps(oc.geology.to_dict()))
    georef.save(folder / "georef.json")
    (folder / "scene.json").write_text(json.dumps({
        "seed": 0, "spec": spec.to_dict(), "grid": list(spec.grid),
        "files": {"mesh": "outcrop.obj", "geology": "geology.json", "georef": "georef.json"}}))
    laz = scan_scene_folder(folder, scan)
    doc = json.loads(laz.with_suffix(".json").read_text())
    assert doc["n_points"] == mem["n_points"] > 2000
    assert doc["cover"].startswith("the generator's rock mask")
    import laspy

    las = laspy.read(laz)
    xyz = np.column_stack([las.x, las.y, las.z]) - georef.origin
    intensity = np.asarray(las.intensity) / 65535.0
    rock = oc.rock.reshape(-1)  # bare rock at the nearest grid vertex
    from scipy.spatial import cKDTree

    bare = rock[cKDTree(oc.vertices).query(xyz)[1]] > 0.99
    lith = np.array(Strata(folder / "geology.json").lithology)[Strata(folder / "geology.json").bed_at(xyz)]
    sand, mud = bare & (lith == "sandstone"), bare & (lith == "mudstone")
    assert sand.sum() > 100 and mud.sum() > 100
    assert np.median(intensity[sand]) > 1.3 * np.median(intensity[mud])
    by = doc["intensity_by_surface"]
    assert by["sandstone"]["median_near_normal"] > 1.3 * by["mudstone"]["median_near_normal"]
    assert by == mem["intensity_by_surface"]


# ------------------------------------------------------ within-bed texture
def test_value_noise_has_unit_variance_and_decorrelates_over_a_cell():
    rng = np.random.default_rng(5)
    p = rng.uniform(0.0, 60.0, (200_000, 3))
    v = value_noise(p, 1.0)
    # Normalised analytically (corner variance 1/3, quintic fade): mean 0, sd 1.
    assert abs(v.mean()) < 0.02 and v.std() == pytest.approx(1.0, abs=0.02)
    near = value_noise(p + [0.03, 0.0, 0.0], 1.0)
    far = value_noise(p + [3.0, 0.0, 0.0], 1.0)
    assert np.corrcoef(v, near)[0, 1] > 0.98  # smooth within a cell
    assert abs(np.corrcoef(v, far)[0, 1]) < 0.02  # independent beyond one
    # The lattice is in metres: a 2 m cell is the 1 m cell at half the coordinates.
    np.testing.assert_allclose(value_noise(p, 2.0), value_noise(p / 2.0, 1.0))


def test_texture_factor_is_exp_of_amplitude_times_the_surface_field(wall):
    """No noise, no falloff, flat bed reflectances: I = rho * cos * exp(sigma_T g(hit)),
    the same at a point whichever chunk (or station) scans it."""
    spec = ScanSpec(**COARSE, intensity_noise=0.0, range_noise_m=0.0, falloff_exponent=0.0,
                    bed_reflectance_variation=0.0, texture_amplitude=0.2,
                    texture_scales_m=(0.3, 1.0))
    stations = station_positions(wall, spec)
    labels: dict = {}
    xyz, intensity, _ = simulate_scan(wall, GEOLOGY, spec, stations=stations, labels=labels)
    tr = _truth(xyz, stations[0])
    z = tr["hit"][:, 2]
    # Off the contact and the wall's foot and top (where float32 hit distances
    # may put a point on the other surface than the exact ray), and unclipped.
    w = tr["on_wall"] & (np.abs(z - BOUNDARY_Z) > 1e-3) & (z > 0.05) & (z < WALL_TOP - 0.05)
    w &= intensity < 1.0  # not clipped (sandstone at normal incidence and T > 1.8)
    rho = np.where(z < BOUNDARY_Z, 0.55, 0.30)
    log_t = np.log(intensity[w] / (rho[w] * tr["cos"][w]))
    # The scan's hits are float32 ray distances: a few points in 10^4 sit up to
    # ~2e-5 off (how far depends on the float order of the installed numpy).
    dev = np.abs(log_t - 0.2 * texture_field(tr["hit"][w], spec))
    assert dev.max() < 1e-4 and np.quantile(dev, 0.999) < 2e-5, (dev.max(),
                                                                 np.quantile(dev, 0.999))
    np.testing.assert_allclose(labels["texture"][w], np.exp(log_t), rtol=3e-5)
    # Unit-variance field: a 20 % log-std within each bed (2 octaves of 0.3 and 1 m on 80 x 12 m).
    for bed in (z < BOUNDARY_Z - 0.1, z > BOUNDARY_Z + 0.1):
        assert np.std(log_t[bed[w]]) == pytest.approx(0.2, rel=0.12)
        assert abs(np.mean(log_t[bed[w]])) < 0.03  # geometric mean 1: rho is kept
    chunked = simulate_scan(wall, GEOLOGY, replace(spec, chunk_rays=1000), stations=stations)
    np.testing.assert_array_equal(intensity, chunked.intensity)


def test_texture_shares_the_stated_correlation_with_the_albedo_within_each_bed(wall):
    """z = c a + sqrt(1 - c^2) g, a the albedo's log luminance standardised per bed:
    a bed-wide offset of the albedo does not move the bed's intensity."""
    c, sigma = 0.6, 0.15
    spec = ScanSpec(**COARSE, intensity_noise=0.0, range_noise_m=0.0, falloff_exponent=0.0,
                    bed_reflectance_variation=0.0, texture_amplitude=sigma,
                    texture_albedo_correlation=c, texture_scales_m=(0.3, 1.0))
    # uv: the wall (vertices 0-3) in the texture's upper half (u along x, v up z),
    # the ground (4-7) in its lower half.
    v = wall.vertices
    uv = np.column_stack([(v[:, 0] + 40.0) / 80.0, 0.5 + 0.5 * v[:, 2] / WALL_TOP])
    uv[4:, 1] = 0.5 * (v[4:, 1] + 40.0) / 40.0
    rows, cols = np.mgrid[0:256, 0:512]
    x_m = (cols + 0.5) / 512 * 80.0 - 40.0
    z_m = (1.0 - (rows + 0.5) / 256 - 0.5) * 2.0 * WALL_TOP
    # Stripes of a 4 m period, plus a darker mudstone bed (removed per bed).
    log_lum = (np.sin(2 * np.pi * x_m / 4.0) + np.where(z_m > BOUNDARY_Z, -0.5, 0.0)).astype(np.float32)
    albedo = VisibleAlbedo(uv, log_lum)
    stations = station_positions(wall, spec)
    xyz, intensity, _ = simulate_scan(wall, GEOLOGY, spec, stations=stations, albedo=albedo)
    tr = _truth(xyz, stations[0])
    z = tr["hit"][:, 2]
    w = tr["on_wall"] & (np.abs(z - BOUNDARY_Z) > 0.2)  # off the albedo's blended contact
    rho = np.where(z < BOUNDARY_Z, 0.55, 0.30)
    field = np.log(intensity / (rho * tr["cos"])) / sigma
    g = texture_field(tr["hit"], spec)
    for bed in (w & (z < BOUNDARY_Z), w & (z > BOUNDARY_Z)):
        a = np.sin(2 * np.pi * tr["hit"][bed, 0] / 4.0)  # the albedo pattern at the hits
        a = (a - a.mean()) / a.std()
        # Up to bilinear texture sampling of the stripes (256 texels across 40 m: < 1 %).
        np.testing.assert_allclose(field[bed], c * a + np.sqrt(1 - c * c) * g[bed], atol=0.03)
        assert np.corrcoef(field[bed], a)[0, 1] == pytest.approx(c, abs=0.08)
        assert abs(np.mean(field[bed])) < 0.1  # the offset is gone (0.8 g's mean is ±0.03)
