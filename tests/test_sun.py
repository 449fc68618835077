"""Sun position, capture time, grid north and relighting.

Modules: ``solar``, ``io.exif`` and ``registration.stages.relight``.
"""

from __future__ import annotations

import io
import math
from datetime import datetime, timedelta, timezone

import numpy as np
import pytest

from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.geo import Georef
from napari_imgreg.io.exif import capture_time_from_exif, read_capture_time
from napari_imgreg.registration.stages.relight import (
    GREY_ALBEDO,
    estimate_sun_from_photo,
    relight,
    render_sunlit,
    shadow_mask,
)
from napari_imgreg.render import render
from napari_imgreg.scene import Scene
from napari_imgreg.solar import (
    SunPosition,
    meridian_convergence_deg,
    sun_direction_local,
    sun_for_photo,
    sun_position,
    sun_positions,
    sun_vector_enu,
)

UTC = timezone.utc


def _grid_azimuth(v: np.ndarray) -> float:
    """Azimuth (deg, clockwise from +Y) of a vector's horizontal part."""
    return math.degrees(math.atan2(v[0], v[1])) % 360.0


# ---------------------------------------------------------------------------
# solar position against published values
# ---------------------------------------------------------------------------


def test_spa_report_example():
    # Reda & Andreas, NREL/TP-560-34302 (2003, rev. 2008), Table A4.1 input and
    # A5.1 output: 2003-10-17 12:30:30 local (UTC-7), lat 39.742476,
    # lon -105.1786, 1830.14 m, 820 mbar, 11 °C, ΔT = 67 s:
    # topocentric zenith 50.11162°, topocentric azimuth 194.34024°.
    when = datetime(2003, 10, 17, 12, 30, 30, tzinfo=timezone(timedelta(hours=-7)))
    sun = sun_position(
        when, 39.742476, -105.1786, 1830.14, pressure_pa=82000.0, temperature_c=11.0, delta_t_s=67.0
    )
    assert abs(sun.zenith_deg - 50.11162) < 1e-3
    assert abs(sun.azimuth_deg - 194.34024) < 1e-3
    assert sun.elevation_deg == pytest.approx(90.0 - sun.zenith_deg)
    assert sun.when == when and sun.is_up
    # Default weather and ΔT move it by far less than 0.1°.
    plain = sun_position(when, 39.742476, -105.1786, 1830.14)
    assert abs(plain.zenith_deg - 50.11162) < 0.01
    assert abs(plain.azimuth_deg - 194.34024) < 0.01


# At the North Pole the sun's elevation is its declination (less ~0.0024° of
# parallax). Instants of the equinoxes and solstices: USNO "Earth's Seasons"
# tables (2023: Dec 22 03:27 UT; 2024: Mar 20 03:06, Jun 20 20:51 UT).
# Declination there: 0 at the equinox, ±ε at the solstices, with the mean
# obliquity ε = 23°26'21.4" − 46.8"/century (IAU 2006) = 23.4362° in 2024
# (nutation adds at most ±0.003°).
@pytest.mark.parametrize(
    "when, declination",
    [
        (datetime(2024, 3, 20, 3, 6, tzinfo=UTC), 0.0),
        (datetime(2024, 6, 20, 20, 51, tzinfo=UTC), 23.4362),
        (datetime(2023, 12, 22, 3, 27, tzinfo=UTC), -23.4362),
    ],
)
def test_pole_elevation_is_declination_at_equinox_and_solstices(when, declination):
    sun = sun_position(when, 90.0, 0.0)
    assert abs(sun.geometric_elevation_deg - declination) < 0.01


def test_noon_elevation_at_the_solstice_vectorised():
    # Highest sun of the June 2024 solstice day at 40° N: 90 − (40 − ε), due
    # south (a day sampled each minute through the vectorised call).
    import pandas as pd

    times = pd.date_range("2024-06-20 10:00", periods=240, freq="1min", tz="UTC")
    track = sun_positions(times, 40.0, -3.0)
    assert len(track) == 240
    k = int(np.argmax(track.geometric_elevation_deg))
    assert abs(track.geometric_elevation_deg[k] - (90.0 - 40.0 + 23.4362)) < 0.01
    assert abs(track.azimuth_deg[k] - 180.0) < 1.0
    one = track[k]
    assert isinstance(one, SunPosition) and one.azimuth_deg == track.azimuth_deg[k]
    np.testing.assert_allclose(
        track.direction_true()[k], sun_vector_enu(one.azimuth_deg, one.elevation_deg)
    )


def test_naive_time_is_refused():
    with pytest.raises(ValueError, match="time zone"):
        sun_position(datetime(2024, 6, 20, 12, 0), 40.0, -3.0)
    with pytest.raises(ValueError, match="time zone"):
        mixed = [datetime(2024, 6, 20, 12, 0, tzinfo=UTC), datetime(2024, 6, 20, 13)]
        sun_positions(mixed, 40.0, -3.0)


# ---------------------------------------------------------------------------
# capture time from EXIF
# ---------------------------------------------------------------------------


def test_capture_time_with_offset():
    exif = {"DateTimeOriginal": "2024:06:15 09:30:12", "OffsetTimeOriginal": "+02:00"}
    when = capture_time_from_exif(exif)
    assert when == datetime(2024, 6, 15, 7, 30, 12, tzinfo=UTC)
    assert when.utcoffset() == timedelta(hours=2)
    info = read_capture_time(exif)
    assert info.source == "DateTimeOriginal+OffsetTimeOriginal" and info.notes == ()
    # bytes with NUL padding and sub-seconds, negative offset
    exif = {
        "DateTimeOriginal": b"2003:10:17 12:30:30\x00",
        "SubsecTimeOriginal": "25",
        "OffsetTimeOriginal": b"-07:00\x00",
    }
    assert capture_time_from_exif(exif) == datetime(2003, 10, 17, 19, 30, 30, 250000, tzinfo=UTC)


def test_capture_time_gps_fallback():
    from PIL.TiffImagePlugin import IFDRational

    stamp = (IFDRational(7), IFDRational(30), IFDRational(51, 10))  # 07:30:05.1
    gps = {"GPSDateStamp": "2024:06:15", "GPSTimeStamp": stamp}
    exif = {"DateTimeOriginal": "2024:06:15 09:30:12", "GPSInfo": gps}
    info = read_capture_time(exif)
    assert info.when == datetime(2024, 6, 15, 7, 30, 5, 100000, tzinfo=UTC)
    assert info.source == "GPSDateStamp+GPSTimeStamp"
    assert any("GPS" in n for n in info.notes)


def test_capture_time_naive_or_missing():
    exif = {"DateTimeOriginal": "2024:06:15 09:30:12", "GPSInfo": 1234}  # empty GPS IFD: its offset
    info = read_capture_time(exif)
    assert info.when is None and "no time zone" in info.notes[0]
    assert capture_time_from_exif(exif) is None
    # An explicit zone is used, and said to be assumed (summer time in Madrid).
    info = read_capture_time(exif, assume_time_zone="Europe/Madrid")
    assert info.when == datetime(2024, 6, 15, 7, 30, 12, tzinfo=UTC)
    assert "assumed" in info.notes[0] and "+02:00" in info.notes[0]
    assert capture_time_from_exif(exif, "+01:00") == datetime(2024, 6, 15, 8, 30, 12, tzinfo=UTC)
    assert capture_time_from_exif({}) is None
    assert capture_time_from_exif({"DateTimeOriginal": "    :  :     :  :  "}) is None
    with pytest.raises(ValueError, match="time zone"):
        read_capture_time(exif, assume_time_zone="Mars/Olympus")


def test_capture_time_through_load_photo(tmp_path):
    # The dict shape load_photo gives (tags by name, GPS under "GPSInfo").
    from PIL import Image
    from PIL.ExifTags import GPS, IFD, Base
    from PIL.TiffImagePlugin import IFDRational

    from napari_imgreg.io.photos import load_photo

    exif = Image.Exif()
    sub = exif.get_ifd(IFD.Exif)
    sub[Base.DateTimeOriginal] = "2024:06:15 09:30:12"
    sub[Base.OffsetTimeOriginal] = "+02:00"
    gps = exif.get_ifd(IFD.GPSInfo)
    gps[GPS.GPSDateStamp] = "2024:06:15"
    gps[GPS.GPSTimeStamp] = (IFDRational(7), IFDRational(30), IFDRational(10))
    buf = io.BytesIO()
    Image.new("RGB", (8, 6), (90, 90, 90)).save(buf, "JPEG", exif=exif.tobytes())
    path = tmp_path / "IMG.jpg"
    path.write_bytes(buf.getvalue())
    photo = load_photo(path)
    info = read_capture_time(photo.exif)
    assert info.when == datetime(2024, 6, 15, 7, 30, 12, tzinfo=UTC)
    assert info.source == "DateTimeOriginal+OffsetTimeOriginal"
    # (2 s between camera clock and GPS fix: no warning)
    assert info.notes == ()
    del photo.exif["OffsetTimeOriginal"]
    assert read_capture_time(photo.exif).when == datetime(2024, 6, 15, 7, 30, 10, tzinfo=UTC)


# ---------------------------------------------------------------------------
# grid north versus true north
# ---------------------------------------------------------------------------


def _utm30_georef(lat: float, lon: float) -> Georef:
    import pyproj

    to_utm = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:32630", always_xy=True)
    e, n = to_utm.transform(lon, lat)
    return Georef("EPSG:32630", np.array([e, n, 500.0]))


@pytest.mark.parametrize("lon", [-1.0, -5.5])  # east and west of the central meridian -3°
def test_true_south_sun_in_the_grid_frame(lon):
    import pyproj

    lat = 40.0
    georef = _utm30_georef(lat, lon)
    factors = pyproj.Proj("EPSG:32630").get_factors(lon, lat)
    conv = meridian_convergence_deg(georef, np.zeros(3))
    assert conv == pytest.approx(factors.meridian_convergence, abs=1e-5)
    # γ ≈ Δλ sin φ: east of the central meridian grid north is clockwise of true north
    assert np.sign(conv) == np.sign(lon + 3.0)
    assert abs(conv - (lon + 3.0) * math.sin(math.radians(lat))) < 0.01

    noon = datetime(2024, 6, 20, 12, tzinfo=UTC)
    sun = SunPosition(noon, lat, lon, 500.0, 180.0, 30.0, 60.0, 30.0)  # due (true) south
    d = sun_direction_local(sun, georef, np.zeros(3))
    assert np.linalg.norm(d) == pytest.approx(1.0)
    assert math.degrees(math.asin(d[2])) == pytest.approx(30.0)
    assert _grid_azimuth(d) == pytest.approx(180.0 - factors.meridian_convergence, abs=1e-4)
    # Independently: a point a little to the TRUE south projects along d.
    south = georef.geodetic_to_local(lat - 0.001, lon, 500.0)
    assert _grid_azimuth(d) == pytest.approx(_grid_azimuth(south), abs=1e-3)


def test_sun_for_photo(tmp_path):
    georef = _utm30_georef(40.0, -1.0)
    center = np.array([10.0, -20.0, 2.0])
    exif = {"DateTimeOriginal": "2024:06:20 18:00:00", "OffsetTimeOriginal": "+02:00"}
    d, sun, notes = sun_for_photo(exif, georef, center)
    assert notes == []
    lat, lon, alt = georef.local_to_geodetic(center)
    expected = sun_position(datetime(2024, 6, 20, 16, 0, tzinfo=UTC), lat, lon, alt)
    assert sun.azimuth_deg == pytest.approx(expected.azimuth_deg)
    np.testing.assert_allclose(d, sun_direction_local(expected, georef, center))
    assert 250 < sun.azimuth_deg < 300 and sun.is_up  # a June evening in Spain: west-north-west
    d, sun, notes = sun_for_photo({"DateTimeOriginal": "2024:06:20 18:00:00"}, georef, center)
    assert d is None and sun is None and "no time zone" in notes[0]
    # Without a georeference: the EXIF GPS position, and +Y taken as true north (said).
    gps = {"GPSLatitude": (40, 0, 0), "GPSLatitudeRef": "N",
           "GPSLongitude": (1, 0, 0), "GPSLongitudeRef": "W"}
    d, sun, notes = sun_for_photo({**exif, "GPSInfo": gps}, None, center)
    assert (sun.latitude_deg, sun.longitude_deg) == (40.0, -1.0)
    np.testing.assert_allclose(d, sun.direction_true())
    assert any("true north" in n for n in notes)


# ---------------------------------------------------------------------------
# shadows
# ---------------------------------------------------------------------------


def _box_on_plane(texture: np.ndarray | None = None) -> Scene:
    """Ground z = 0 over [-12, 12]² and a box [-1, 1]² × [0, 2], outward normals."""
    ground = np.array([[-12.0, -12, 0], [12, -12, 0], [12, 12, 0], [-12, 12, 0]])
    ground_faces = np.array([[0, 1, 2], [0, 2, 3]])
    lo, hi = np.array([-1.0, -1, 0]), np.array([1.0, 1, 2])
    corners = np.array([[(hi if (i >> k) & 1 else lo)[k] for k in range(3)] for i in range(8)])
    quads = [(0, 4, 6, 2), (1, 3, 7, 5), (0, 1, 5, 4), (2, 6, 7, 3), (4, 5, 7, 6)]
    box_faces = np.array([f for a, b, c, e in quads for f in ((a, b, c), (a, c, e))]) + 4
    return Scene(np.vstack([ground, corners]), np.vstack([ground_faces, box_faces]))


def _down_camera(height: float = 30.0, size: int = 320, f: float = 320.0):
    intr = Intrinsics(size, size, f, f, (size - 1) / 2, (size - 1) / 2)
    R = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])  # looking straight down, image up = north
    return intr, Pose.from_center(R, [0.0, 0.0, height])


def _distance_to_polygon(pts: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Distance from (N, 2) points to the edges of a closed polygon (M, 2)."""
    a, b = poly, np.roll(poly, -1, axis=0)
    ab = b - a
    t = np.clip(np.einsum("nmk,mk->nm", pts[:, None] - a, ab) / (ab * ab).sum(1), 0, 1)
    closest = a + t[..., None] * ab
    return np.linalg.norm(pts[:, None] - closest, axis=-1).min(axis=1)


def test_box_shadow_on_the_ground():
    from matplotlib.path import Path as MplPath

    scene = _box_on_plane()
    intr, pose = _down_camera()
    rr = render(scene, intr, pose)
    sun = sun_vector_enu(135.0, 45.0)  # from the south-east
    lit = shadow_mask(scene, rr.xyz, rr.normal, sun, depth=rr.depth)
    assert lit.shape == rr.mask.shape and not lit[~rr.mask].any()

    # Shadow of the box: its base and its top pushed down the sun's rays to
    # the ground; a convex box casts the convex hull of the two squares.
    reach = 2.0 / sun[2] * sun[:2]
    base = np.array([[-1.0, -1], [1, -1], [1, 1], [-1, 1]])
    hull = np.array(
        [[-1.0, -1], [1, -1], [1, 1], [1, 1] - reach, [-1, 1] - reach, [-1, -1] - reach]
    )
    ground = rr.mask & (np.abs(rr.xyz[..., 2]) < 1e-3)
    pts = rr.xyz[ground][:, :2].astype(float)
    inside = MplPath(hull).contains_points(pts) & ~MplPath(base).contains_points(pts)
    footprint = 30.0 / intr.fx  # metres per pixel on the ground
    clear = _distance_to_polygon(pts, hull) > 2 * footprint
    assert (inside & clear).sum() > 300
    assert not lit[ground][inside & clear].any()
    assert lit[ground][~inside & clear].all()
    # The roof faces the sun and nothing shades it.
    roof = rr.mask & (np.abs(rr.xyz[..., 2] - 2.0) < 1e-3)
    assert roof.sum() > 300 and lit[roof].all()


def test_faces_turned_from_the_sun_are_dark():
    scene = _box_on_plane()
    sun = sun_vector_enu(135.0, 45.0)
    # Points on the four walls, with their outward normals (as a viewer outside sees them).
    s = np.linspace(-0.9, 0.9, 7)
    z = np.linspace(0.1, 1.9, 7)
    S, Z = np.meshgrid(s, z)
    walls = {
        "east": (np.stack([np.full_like(S, 1.0), S, Z], -1), [1.0, 0, 0]),
        "south": (np.stack([S, np.full_like(S, -1.0), Z], -1), [0, -1.0, 0]),
        "west": (np.stack([np.full_like(S, -1.0), S, Z], -1), [-1.0, 0, 0]),
        "north": (np.stack([S, np.full_like(S, 1.0), Z], -1), [0, 1.0, 0]),
    }
    lit = {
        k: shadow_mask(scene, p, np.broadcast_to(n, p.shape), sun) for k, (p, n) in walls.items()
    }
    assert lit["east"].all() and lit["south"].all()
    assert not lit["west"].any() and not lit["north"].any()


def test_relight_untextured_box_is_grey_times_shading():
    scene = _box_on_plane()
    intr, pose = _down_camera()
    sun = sun_vector_enu(135.0, 45.0)
    res = render_sunlit(scene, intr, pose, sun, ambient=0.3, penumbra_px=0.0)
    assert "relight" in res.timings_s
    lit = shadow_mask(scene, res.xyz, res.normal, sun, depth=res.depth)
    cos = np.clip(res.normal @ sun, 0, None)
    expected = np.floor(GREY_ALBEDO * (0.3 + 0.7 * cos * lit) + 0.5)
    assert np.abs(res.rgb[res.mask].astype(float) - expected[res.mask][:, None]).max() <= 1
    assert (res.rgb[~res.mask] == 0).all()
    assert res.rgb[res.mask & ~lit].max() == round(GREY_ALBEDO * 0.3)


def test_shading_share_known_answers():
    """The share of band-passed log contrast drawn by the light: a uniform
    albedo gives 1, a uniform light 0, and two independent fields of equal
    variance a half."""
    from napari_imgreg.registration.stages.relight import shading_share

    rng = np.random.default_rng(3)
    mask = np.ones((96, 128), bool)
    mask[:10] = False  # some sky
    pix = np.flatnonzero(mask)

    def field():
        return np.exp(0.3 * rng.standard_normal(len(pix))).astype(np.float32)

    assert shading_share(np.full(len(pix), 150.0, np.float32), field(), pix, mask) == pytest.approx(1.0)
    assert shading_share(150.0 * field(), np.full(len(pix), 0.8, np.float32), pix, mask) == pytest.approx(0.0, abs=1e-9)
    half = [shading_share(150.0 * field(), field(), pix, mask) for _ in range(5)]
    assert np.mean(half) == pytest.approx(0.5, abs=0.05)


def test_relit_render_says_how_much_of_it_is_synthetic_light():
    """render_sunlit's ``shading_share``: 1 on an untextured mesh, whose every
    edge the light draws; below a half on a textured one whose pattern carries
    the detail; a plain render has none."""
    survey = sun_vector_enu(160.0, 40.0)
    textured = _panels(lambda k, pat: pat * (0.35 + 0.65 * max(0.0, float(_PANEL_NORMALS[k] @ survey))))
    intr, pose = _panel_camera()
    new = sun_vector_enu(230.0, 25.0)
    lit = render_sunlit(textured, intr, pose, new, survey_sun_dir=survey)
    assert 0.0 < lit.shading_share < 0.5
    bare = render_sunlit(_box_on_plane(), *_down_camera(), sun_vector_enu(135.0, 45.0))
    assert bare.shading_share == pytest.approx(1.0)
    assert render(textured, intr, pose).shading_share is None


# ---------------------------------------------------------------------------
# relighting a textured render
# ---------------------------------------------------------------------------

# Unit normals of three panels: (facing azimuth, tilt from horizontal).
_PANEL_NORMALS = [
    sun_vector_enu(a, 90.0 - tilt) for a, tilt in ((150.0, 35.0), (200.0, 50.0), (250.0, 25.0))
]


def _panels(texture_of_panel) -> Scene:
    """Three separate tilted square panels side by side, each with its own texture region.

    ``texture_of_panel(k, tile) -> tile`` fills panel k's (64, 64, 3) texture tile.
    """
    verts, faces, uvs = [], [], []
    tiles = []
    rng = np.random.default_rng(5)
    base = rng.uniform(60, 200, (8, 8, 3))
    import cv2

    pattern = cv2.resize(base, (64, 64), interpolation=cv2.INTER_CUBIC).clip(40, 220)
    for k, n in enumerate(_PANEL_NORMALS):
        n = n / np.linalg.norm(n)
        a = np.cross([0.0, 0.0, 1.0], n)
        a /= np.linalg.norm(a)
        b = np.cross(n, a)
        c = np.array([-6.0 + 6.0 * k, 0.0, 2.0])
        st = np.array([[-1.0, -1], [1, -1], [1, 1], [-1, 1]])
        verts.append(c + 2.4 * (st[:, :1] * a + st[:, 1:] * b))
        faces.append(np.array([[0, 1, 2], [0, 2, 3]]) + 4 * k)
        # Tile k spans u in [k/3, (k+1)/3], inset by two texels (no bleeding).
        u0, u1 = (k * 64 + 2) / 192, ((k + 1) * 64 - 2) / 192
        u = np.where(st[:, 0] < 0, u0, u1)
        uvs.append(np.column_stack([u, np.where(st[:, 1] < 0, 2 / 64, 62 / 64)]))
        tiles.append(texture_of_panel(k, pattern))
    texture = np.clip(np.concatenate(tiles, axis=1) + 0.5, 0, 255).astype(np.uint8)
    return Scene(np.vstack(verts), np.vstack(faces), np.vstack(uvs), texture)


def _panel_camera():
    intr = Intrinsics(256, 112, 300.0, 300.0, 127.5, 55.5)
    return intr, Pose.from_attitude(0.0, 5.0, 0.0, [0.0, -16.0, 3.0])


def test_relight_with_known_survey_sun():
    survey, s_amb = sun_vector_enu(160.0, 40.0), 0.35

    def survey_shade(k):
        n = _PANEL_NORMALS[k]
        return s_amb + (1 - s_amb) * max(0.0, float(n @ survey))

    baked = _panels(lambda k, pat: pat * survey_shade(k))
    albedo = _panels(lambda k, pat: pat)
    intr, pose = _panel_camera()
    rr = render(baked, intr, pose, mode="color")
    ra = render(albedo, intr, pose, mode="color")
    assert rr.coverage > 0.3
    panel = rr.face_id // 2
    mask = rr.mask

    # The survey sun reproduces the render.
    known = dict(survey_sun_dir=survey, survey_ambient=s_amb)
    same = relight(rr, baked, survey, s_amb, penumbra_px=0, **known)
    assert np.abs(same[mask].astype(int) - rr.rgb[mask]).max() <= 2
    assert (same[~mask] == rr.rgb[~mask]).all()

    # Another sun: albedo times the new shading (and its cast shadows, if any).
    new, amb = sun_vector_enu(230.0, 25.0), 0.25
    out = relight(rr, baked, new, amb, penumbra_px=0, **known)
    cos = np.array([max(0.0, float(n @ new)) for n in _PANEL_NORMALS])
    assert cos.max() > 1.5 * cos.min() > 0.6  # the panels are lit differently
    lit = shadow_mask(baked, rr.xyz, rr.normal, new, depth=rr.depth)
    shade = amb + (1 - amb) * cos[panel] * lit
    expected = ra.rgb.astype(float) * shade[..., None]
    assert np.abs(out[mask] - expected[mask]).max() <= 3
    assert np.abs(out[mask] - expected[mask]).mean() < 0.8

    # Flat and smooth normals agree on planar panels; gamma brightens the shade.
    flat = relight(rr, baked, new, amb, penumbra_px=0, normals="flat", **known)
    assert np.abs(flat.astype(int) - out).max() <= 1
    soft = relight(rr, baked, new, amb, gamma=2.2, survey_gamma=1.0, **known)
    assert soft[mask].mean() > out[mask].mean()


def test_relight_lowpass_albedo_flattens_survey_shading():
    # Without the survey sun, a low-pass of the luminance stands in for the
    # survey shading: the panels' brightness ratios shrink toward 1.
    survey = sun_vector_enu(160.0, 40.0)
    def survey_lit(k, pat):
        shade = 0.35 + 0.65 * max(0.0, float(_PANEL_NORMALS[k] @ survey))
        return np.full_like(pat, 150.0) * shade

    baked = _panels(survey_lit)
    intr, pose = _panel_camera()
    rr = render(baked, intr, pose, mode="color")
    overhead = np.array([0.0, 0.0, 1.0])
    out = relight(rr, baked, overhead, ambient=1.0, shadows=False, lowpass_sigma=0.01)
    panel = rr.face_id // 2
    inner = rr.mask & (np.abs(np.gradient(panel.astype(float), axis=1)) == 0)

    def spread(img):
        means = [img[inner & (panel == k)].mean() for k in range(3)]
        return max(means) / min(means)

    assert spread(out) < 1.1 < spread(rr.rgb)


def test_estimate_sun_from_a_synthetic_photo():
    # A corrugated ground lit by a known sun; the estimate finds it back.
    n = 60
    x, y = np.meshgrid(np.linspace(-15, 15, n), np.linspace(-15, 15, n))
    z = 1.2 * np.sin(x / 2.0) + 0.8 * np.cos(y / 1.7) + 0.5 * np.sin((x + y) / 3.1)
    V = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    idx = np.arange(n * n).reshape(n, n)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)])
    scene = Scene(V, F)
    intr, pose = _down_camera(height=35.0, size=200, f=180.0)
    rr = render(scene, intr, pose, mode="color")
    sun = sun_vector_enu(230.0, 35.0)
    photo = relight(rr, scene, sun, ambient=0.3, albedo="constant")
    est = estimate_sun_from_photo(photo, rr, scene, ambient=0.3)
    angle = math.degrees(math.acos(np.clip(est.direction @ sun, -1, 1)))
    assert angle < 3.0
    assert est.correlation > 0.95 and 0.3 < est.confidence <= 1.0
    # Noise, or one flat face (any sun on a cone lights it alike): no confidence.
    noise = np.random.default_rng(1).integers(0, 256, photo.shape).astype(np.uint8)
    assert estimate_sun_from_photo(noise, rr, scene).confidence < 0.05
    square = np.array([[-15.0, -15, 0], [15, -15, 0], [15, 15, 0], [-15, 15, 0]])
    flat = Scene(square, np.array([[0, 1, 2], [0, 2, 3]]))
    rf = render(flat, intr, pose, mode="color")
    lit_flat = relight(rf, flat, sun, ambient=0.3, albedo="constant")
    assert estimate_sun_from_photo(lit_flat, rf, flat).confidence < 0.05


# ------------------------------------------------------ the sun of a record
def test_sun_of_a_record_is_one_reading_for_prior_and_survey(tmp_path):
    """A record's ``time`` and its ``sun`` block give one sun, the one pvlib
    computes for that instant and place, in the prior and in ``survey.json``."""
    import json
    from types import SimpleNamespace

    import pandas as pd
    import pyproj
    from pvlib import atmosphere, solarposition

    from napari_imgreg.io.photos import Photo
    from napari_imgreg.io.records import parse_sensor_record
    from napari_imgreg.prior import prior_for_photo
    from napari_imgreg.scene import read_survey_sun
    from napari_imgreg.solar import sun_from_record

    georef = Georef(crs="EPSG:32630", origin=np.array([440000.0, 4470000.0, 600.0]))
    where = np.array([350.0, -120.0, 12.0])  # local metres, central Spain
    when = "2024-06-15T08:30:00+02:00"

    # Known answer, without napari_imgreg: pvlib's SPA at the point's WGS84
    # position (delta T estimated for the date, as solar does), turned from
    # true to grid north by PROJ's meridian convergence.
    e, n, h = where + georef.origin
    to_wgs84 = pyproj.Transformer.from_crs("EPSG:32630", "EPSG:4326", always_xy=True)
    lon, lat = to_wgs84.transform(e, n)
    spa = solarposition.spa_python(pd.DatetimeIndex([pd.Timestamp(when)]), lat, lon, altitude=h,
                                   pressure=atmosphere.alt2pres(h), temperature=12.0, delta_t=None)
    azimuth_true = float(spa["azimuth"].iloc[0])
    elevation = float(spa["apparent_elevation"].iloc[0])
    convergence = pyproj.Proj("EPSG:32630").get_factors(lon, lat).meridian_convergence
    a, el = math.radians(azimuth_true - convergence), math.radians(elevation)
    expected = np.array([math.sin(a) * math.cos(el), math.cos(a) * math.cos(el), math.sin(el)])
    assert 60.0 < azimuth_true < 90.0 and 10.0 < elevation < 25.0  # an early June morning

    def angle_deg(v):
        return math.degrees(math.acos(np.clip(np.asarray(v) @ expected, -1.0, 1.0)))

    by_time = sun_from_record(parse_sensor_record({"time": when}), georef, where)
    by_sun = sun_from_record(
        parse_sensor_record({"sun": {"azimuth_deg": azimuth_true, "elevation_deg": elevation}}),
        georef, where,
    )
    assert angle_deg(by_time) < 1e-5 and angle_deg(by_sun) < 1e-5
    np.testing.assert_allclose(by_time, by_sun, atol=1e-12)
    assert sun_from_record(parse_sensor_record({}), georef, where) is None
    with pytest.raises(ValueError, match="georeference"):
        sun_from_record(parse_sensor_record({"time": when}), None, where)

    # The same vectors reach the prior of a photo (seen from its centre) ...
    photo = Photo(np.zeros((30, 40, 3), np.uint8), {}, tmp_path / "IMG_0001.jpg")
    scene = SimpleNamespace(georef=georef, dem=None, terrain_height=None)
    base = {"camera": {"width": 40, "height": 30, "fx": 35.0},
            "position": dict(zip("xyz", where.tolist())),
            "orientation": {"trend_deg": 80.0, "plunge_deg": 0.0, "roll_deg": 0.0}}
    sun_block = {"sun": {"azimuth_deg": azimuth_true, "elevation_deg": elevation}}
    for block, vector in (({"time": when}, by_time), (sun_block, by_sun)):
        photo.sidecar.write_text(json.dumps({**base, **block}))
        prior = prior_for_photo(photo, scene)
        np.testing.assert_allclose(prior.pose.center, where, atol=1e-9)
        np.testing.assert_allclose(prior.sun, vector, atol=1e-12)
        # ... and the survey sun of a model's texture.
        survey = tmp_path / "survey.json"
        survey.write_text(json.dumps(block))
        np.testing.assert_allclose(read_survey_sun(survey, georef, where), vector, atol=1e-12)
    assert prior.sun_source == "sensor record sun"
