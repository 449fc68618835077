"""Orientation tables: CSV, Metashape XML, COLMAP images.txt, photo metadata.

Round trips build estimated orientations by rotating true attitudes, write
them in each format, read them back and recover the rotation.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from PIL import ExifTags, Image
from scipy.spatial.transform import Rotation

from napari_imgreg.camera import rotation_from_attitude
from napari_imgreg.errors import InputError
from napari_imgreg.io.exif import attitude_from_dji_gimbal
from napari_imgreg.io.orientation_tables import (
    OrientationTable,
    pair_tables,
    read_colmap_images,
    read_metashape_xml,
    read_orientation_csv,
    read_orientation_table,
    read_photo_attitudes,
    write_orientation_csv,
)
from napari_imgreg.orient import orient, rotation_error_deg
from napari_imgreg.sample.survey import simulate_survey


@pytest.fixture
def survey():
    """Noise-free survey: 51 photos, a random true rotation, model cameras with centres."""
    return simulate_survey(np.random.default_rng(7), noise_deg=0.0)


# ------------------------------------------------------------ writers (test-only)
def write_metashape_xml(
    path, table: OrientationTable, chunk_rotation, chunk_translation, chunk_scale,
    unaligned=("IMG_9999",), component=False,
):
    """Metashape cameras.xml: camera transforms are camera-to-chunk; the chunk
    transform maps chunk to model coordinates (X = s R x + t). PhotoScan writes
    it under <chunk>, Metashape 1.6+ under <components><component>."""
    cameras = []
    for i, (label, R) in enumerate(zip(table.photos, table.cam_from_world)):
        world_from_cam = R.T
        chunk_from_cam = chunk_rotation.T @ world_from_cam
        centre_chunk = chunk_rotation.T @ (table.positions[i] - chunk_translation) / chunk_scale
        M = np.eye(4)
        M[:3, :3] = chunk_from_cam
        M[:3, 3] = centre_chunk
        numbers = " ".join(f"{v:.17g}" for v in M.ravel())
        stem = label.rsplit(".", 1)[0]  # Metashape labels drop the extension
        cameras.append(
            f'<camera id="{i}" sensor_id="0" component_id="0" label="{stem}">'
            f"<transform>{numbers}</transform></camera>"
        )
    half = len(cameras) // 2
    missing = "".join(
        f'<camera id="{1000 + k}" sensor_id="0" label="{u}"/>' for k, u in enumerate(unaligned)
    )
    rot = " ".join(f"{v:.17g}" for v in chunk_rotation.ravel())
    tr = " ".join(f"{v:.17g}" for v in chunk_translation)
    transform = (
        f'<transform><rotation locked="false">{rot}</rotation><translation>{tr}</translation>'
        f"<scale>{chunk_scale:.17g}</scale></transform>"
    )
    if component:
        transform = (
            '<components next_id="1" active_id="0"><component id="0" label="Component 1">'
            f"{transform}</component></components>"
        )
    path.write_text(
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        '<document version="1.5.0"><chunk label="Chunk 1" enabled="true">'
        '<sensors next_id="1"><sensor id="0" label="phone" type="frame"/></sensors>'
        f'<cameras next_id="{len(cameras)}">{"".join(cameras[:half])}'
        f'<group id="0" label="second half" type="folder">{"".join(cameras[half:])}</group>'
        f"{missing}</cameras>{transform}</chunk></document>\n"
    )


def write_colmap_images(path, table: OrientationTable):
    lines = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
        f"# Number of images: {len(table)}, mean observations per image: 2",
    ]
    for i, (name, R) in enumerate(zip(table.photos, table.cam_from_world), start=1):
        q = Rotation.from_matrix(R).as_quat(scalar_first=True)
        t = -R @ table.positions[i - 1]
        numbers = " ".join(f"{v:.17g}" for v in [*q, *t])
        lines.append(f"{i} {numbers} 1 {name}")
        lines.append("" if i % 2 else "12.5 30.25 -1 100.0 8.0 17")  # empty POINTS2D lines happen
    path.write_text("\n".join(lines) + "\n")


def _save_jpeg(path, xmp: str | None = None, gps_direction: float | None = None, ref: str = "T"):
    image = Image.new("RGB", (16, 12), (120, 90, 60))
    kwargs = {}
    if xmp is not None:
        kwargs["xmp"] = xmp.encode()
    if gps_direction is not None:
        exif = Image.Exif()
        exif[ExifTags.IFD.GPSInfo] = {
            ExifTags.GPS.GPSImgDirectionRef: ref,
            ExifTags.GPS.GPSImgDirection: gps_direction,
        }
        kwargs["exif"] = exif
    image.save(path, "JPEG", **kwargs)


def _dji_xmp(yaw: float, pitch: float, roll: float, element_form: bool = False) -> str:
    ns = 'rdf:about="" xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/"'
    if element_form:
        body = (f"<drone-dji:GimbalYawDegree>{yaw:+.2f}</drone-dji:GimbalYawDegree>"
                f"<drone-dji:GimbalPitchDegree>{pitch:+.2f}</drone-dji:GimbalPitchDegree>"
                f"<drone-dji:GimbalRollDegree>{roll:+.2f}</drone-dji:GimbalRollDegree>")
        desc = f"<rdf:Description {ns}>{body}</rdf:Description>"
    else:
        desc = (f"<rdf:Description {ns} "
                f'drone-dji:GimbalRollDegree="{roll:+.2f}" drone-dji:GimbalYawDegree="{yaw:+.2f}" '
                f'drone-dji:GimbalPitchDegree="{pitch:+.2f}"/>')
    rdf = "http://www.w3.org/1999/02/22-rdf-syntax-ns#"
    return (f'<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="{rdf}">'
            f"{desc}</rdf:RDF></x:xmpmeta>")


# ------------------------------------------------------------------- round trips
def test_csv_round_trip_recovers_rotation(survey, tmp_path):
    est_path, meas_path = tmp_path / "estimated.csv", tmp_path / "measured.csv"
    write_orientation_csv(est_path, survey.estimated)
    write_orientation_csv(meas_path, survey.measured)
    estimated = read_orientation_table(est_path)
    measured = read_orientation_table(meas_path)
    assert estimated.kind == "csv"
    assert estimated.positions is not None and measured.positions is None
    np.testing.assert_allclose(estimated.cam_from_world, survey.estimated.cam_from_world, atol=1e-8)
    np.testing.assert_allclose(estimated.positions, survey.estimated.positions, rtol=1e-9)
    result = orient(estimated, measured, method="lsq")
    assert rotation_error_deg(result.rotation, survey.rotation) < 1e-5
    assert measured.capture_dates is None  # no time column written without dates


def test_csv_writes_capture_days_as_a_time_column(survey, tmp_path):
    from dataclasses import replace
    from datetime import date

    days = [date(2026, 6, 12)] * (len(survey.measured) - 1) + [None]
    path = tmp_path / "phone.csv"
    write_orientation_csv(path, replace(survey.measured, capture_dates=days))
    assert path.read_text().splitlines()[0].endswith(",time")
    assert read_orientation_table(path).capture_dates == days


@pytest.mark.parametrize("component", [False, True], ids=["chunk", "component"])
def test_metashape_xml_round_trip_with_chunk_transform(survey, tmp_path, component):
    chunk_R = Rotation.from_euler("zyx", [33.0, -12.0, 71.0], degrees=True).as_matrix()
    chunk_t, chunk_s = np.array([12.0, -40.0, 3.5]), 2.5
    path = tmp_path / "cameras.xml"
    write_metashape_xml(path, survey.estimated, chunk_R, chunk_t, chunk_s, component=component)
    table = read_orientation_table(path)
    assert table.kind == "metashape"
    assert len(table) == len(survey.estimated)  # grouped cameras found, unaligned one skipped
    assert any("not aligned" in note for note in table.notes)
    # Labels are extension-less; the chunk transform puts them back in the model frame.
    order = [survey.estimated.photos.index(f"{p}.jpg") for p in table.photos]
    expected = survey.estimated.cam_from_world[order]
    np.testing.assert_allclose(table.cam_from_world, expected, atol=1e-9)
    np.testing.assert_allclose(table.positions, survey.estimated.positions[order], atol=1e-6)
    result = orient(table, survey.measured)
    assert result.inputs["n_photos"] == 51  # IMG_0001 pairs with IMG_0001.jpg
    assert rotation_error_deg(result.rotation, survey.rotation) < 1e-6


def test_metashape_geocentric_chunk_is_not_applied(survey, tmp_path):
    path = tmp_path / "cameras.xml"
    write_metashape_xml(path, survey.estimated, np.eye(3), np.array([4.5e6, 1.1e6, 4.3e6]), 1.0)
    table = read_metashape_xml(path)
    assert any("geocentric" in note for note in table.notes)
    # Orientations stay in the chunk frame, here equal to the model frame (identity rotation).
    order = [survey.estimated.photos.index(f"{p}.jpg") for p in table.photos]
    expected = survey.estimated.cam_from_world[order]
    np.testing.assert_allclose(table.cam_from_world, expected, atol=1e-9)
    forced = read_metashape_xml(path, chunk_transform=True)
    np.testing.assert_allclose(forced.positions, survey.estimated.positions[order], atol=1e-6)


def test_applying_a_geocentric_chunks_rotation_to_a_mesh_warns(survey, tmp_path, run_cli):
    """The rotation is of the chunk's internal frame: right for a mesh exported in
    local coordinates only, which the command cannot tell, so it says so."""
    import trimesh

    xml = tmp_path / "cameras.xml"
    write_metashape_xml(xml, survey.estimated, np.eye(3), np.array([4.5e6, 1.1e6, 4.3e6]), 1.0)
    measured = tmp_path / "phone.csv"
    write_orientation_csv(measured, survey.measured)
    trimesh.creation.box().export(tmp_path / "model.ply")
    run = run_cli(["orient", xml, measured, "--out", tmp_path / "o.json",
                   "--apply", tmp_path / "model.ply", "--mesh-out", tmp_path / "turned.ply"])
    assert run.code == 0 and (tmp_path / "turned.ply").exists()
    assert "warning:" in run.err and "referenced to a CRS" in run.err and "local" in run.err


def test_colmap_round_trip(survey, tmp_path):
    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    write_colmap_images(sparse / "images.txt", survey.estimated)
    table = read_orientation_table(sparse)  # the model folder works as well as the file
    assert table.kind == "colmap" and table.photos == survey.estimated.photos
    np.testing.assert_allclose(table.cam_from_world, survey.estimated.cam_from_world, atol=1e-9)
    np.testing.assert_allclose(table.positions, survey.estimated.positions, atol=1e-6)
    result = orient(table, survey.measured)
    assert rotation_error_deg(result.rotation, survey.rotation) < 1e-6


def test_colmap_images_without_points_lines_keep_every_image(survey, tmp_path):
    """Some tools write images.txt with no POINTS2D lines: every image line is read
    (skipping the line after each blindly had lost every second image)."""
    images = tmp_path / "images.txt"
    write_colmap_images(images, survey.estimated)
    kept = [line for line in images.read_text().splitlines()
            if line.startswith("#") or len(line.split()) == 10]
    images.write_text("\n".join(kept) + "\n")
    table = read_colmap_images(images)
    assert table.photos == survey.estimated.photos
    np.testing.assert_allclose(table.cam_from_world, survey.estimated.cam_from_world, atol=1e-9)


def test_dji_gimbal_angles_match_aerospace_euler_convention():
    """DJI yaw/pitch/roll are NED Z-Y-X angles of a body frame (x forward, y right,
    z down); the camera's ξ is body x and ρ is body y. Checked independently with scipy."""
    ned_to_enu = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1]], float)
    rng = np.random.default_rng(3)
    cases = [(30, -90 + 1e-3, 0), (-120, -35, 4), (175, 10, -20), *rng.uniform(-80, 80, (5, 3))]
    for yaw, pitch, roll in cases:
        body = Rotation.from_euler("ZYX", [yaw, pitch, roll], degrees=True).as_matrix()
        xi = ned_to_enu @ body[:, 0]
        rho = ned_to_enu @ body[:, 1]
        R = rotation_from_attitude(*attitude_from_dji_gimbal(yaw, pitch, roll))
        np.testing.assert_allclose(R[2], xi, atol=1e-9)
        np.testing.assert_allclose(R[0], rho, atol=1e-9)


def test_photo_metadata_dji_xmp_and_exif_direction(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    _save_jpeg(folder / "DJI_0001.JPG", xmp=_dji_xmp(-92.5, -30.0, 1.5))
    _save_jpeg(folder / "DJI_0002.JPG", xmp=_dji_xmp(181.0, 5.0, -2.0, element_form=True))
    _save_jpeg(folder / "PHONE_0003.jpg", gps_direction=247.25, ref="M")
    _save_jpeg(folder / "PLAIN_0004.jpg")
    table = read_orientation_table(folder)
    assert table.kind == "photos"
    assert table.photos == ["DJI_0001.JPG", "DJI_0002.JPG", "PHONE_0003.jpg"]
    att = table.attitudes
    np.testing.assert_allclose(att[0], [267.5, 30.0, 1.5], atol=1e-9)
    np.testing.assert_allclose(att[1], [181.0, -5.0, -2.0], atol=1e-9)
    assert att[2, 0] == pytest.approx(247.25) and np.isnan(att[2, 1:]).all()
    assert table.complete.tolist() == [True, True, False]
    notes = " ".join(table.notes)
    assert "compass direction" in notes and "magnetic" in notes and "without attitude" in notes


def test_trend_only_photos_are_left_out_of_the_pairing(tmp_path):
    measured = OrientationTable.from_attitudes(
        ["a", "b", "c"], [10, 20, 30], [5, np.nan, 0], [0, 0, 0]
    )
    estimated = OrientationTable.from_attitudes(["a", "b", "c"], [40, 50, 60], [5, 6, 0], [0, 0, 0])
    paired = pair_tables(estimated, measured)
    assert paired.photos == ["a", "c"]
    assert any("incomplete" in n for n in paired.notes)
    with pytest.raises(InputError, match="full attitude"):
        pair_tables(estimated, measured, min_photos=3)


def test_csv_with_semicolons_comments_and_extra_columns(tmp_path):
    path = tmp_path / "phone.csv"
    path.write_text(
        "# exported from the field app\n"
        "photo;trend_deg;plunge_deg;roll_deg;note\n"
        "IMG_1.jpg;350.5;12;-3;left end\n\n"
        "IMG_2.jpg;10.0;-4.5;2;\n"
    )
    table = read_orientation_csv(path)
    np.testing.assert_allclose(table.attitudes, [[350.5, 12, -3], [10, -4.5, 2]], atol=1e-9)


# ----------------------------------------------------------------------- errors
@pytest.mark.parametrize(
    "content, message",
    [
        ("photo,trend_deg,plunge_deg\nIMG_1,1,2\n", "missing column roll_deg"),
        (
            "photo,trend_deg,plunge_deg,roll_deg\nIMG_1,1,2,3\nIMG_2,abc,2,3\n",
            r"row 3: trend_deg is not a number \('abc'\)",
        ),
        ("photo,trend_deg,plunge_deg,roll_deg\nIMG_1,1,95,3\n", "row 2: plunge_deg must be in"),
        ("photo,trend_deg,plunge_deg,roll_deg\nIMG_1,1,2,3\nIMG_1,1,2,3\n", "appears twice"),
        ("photo,trend_deg,plunge_deg,roll_deg\nIMG_1,nan,2,3\n", "not a finite number"),
        ("photo,trend_deg,plunge_deg,roll_deg,x,y\nIMG_1,1,2,3,4,5\n", "not all of x, y, z"),
        ("photo,trend_deg,plunge_deg,roll_deg\n", "no data rows"),
        ("", "empty file"),
    ],
)
def test_bad_csv_is_one_clear_error_naming_the_file(tmp_path, content, message):
    path = tmp_path / "table.csv"
    path.write_text(content)
    with pytest.raises(InputError, match=message) as info:
        read_orientation_table(path)
    assert str(info.value).startswith(str(path)) and "\n" not in str(info.value)


def test_no_photos_in_common(tmp_path):
    a = OrientationTable.from_attitudes(
        ["IMG_1.jpg", "IMG_2.jpg"], [1, 2], [0, 0], [0, 0], source=tmp_path / "m.csv"
    )
    b = OrientationTable.from_attitudes(
        ["DSC_1.jpg", "DSC_2.jpg"], [1, 2], [0, 0], [0, 0], source=tmp_path / "e.csv"
    )
    with pytest.raises(InputError, match="no photos in common") as info:
        pair_tables(b, a)
    assert "m.csv" in str(info.value) and "e.csv" in str(info.value)


def test_bad_xml_colmap_and_formats(tmp_path):
    bad_xml = tmp_path / "cameras.xml"
    bad_xml.write_text("<document><chunk><cameras><camera label='a'>")
    with pytest.raises(InputError, match="not valid XML"):
        read_orientation_table(bad_xml)
    no_transform = tmp_path / "empty.xml"
    no_transform.write_text(
        "<document><chunk><cameras><camera label='a'/></cameras></chunk></document>"
    )
    with pytest.raises(InputError, match="no aligned camera"):
        read_orientation_table(no_transform)
    short = tmp_path / "short.xml"
    short.write_text(
        "<document><chunk><cameras><camera label='a'><transform>1 0 0</transform></camera>"
        "</cameras></chunk></document>"
    )
    with pytest.raises(InputError, match="'a': <transform> must hold 16 numbers"):
        read_orientation_table(short)
    scaled = tmp_path / "scaled.xml"
    scaled.write_text(
        "<document><chunk><cameras><camera label='a'>"
        "<transform>2 0 0 0 0 2 0 0 0 0 2 0 0 0 0 1</transform>"
        "</camera></cameras></chunk></document>"
    )
    with pytest.raises(InputError, match="not a rotation"):
        read_orientation_table(scaled)

    images = tmp_path / "images.txt"
    images.write_text("# comment\n1 1 0 0 0 0 0 0 1\n\n")
    with pytest.raises(InputError, match="line 2: expected IMAGE_ID"):
        read_orientation_table(images)
    images.write_text("1 1 0 0 x 0 0 0 1 a.jpg\n\n")
    with pytest.raises(InputError, match="line 1: QW..TZ must be numbers"):
        read_colmap_images(images)
    binary = tmp_path / "binary_model"
    binary.mkdir()
    (binary / "images.bin").write_bytes(b"\0")
    with pytest.raises(InputError, match="model_converter"):
        read_orientation_table(binary)
    with pytest.raises(InputError, match="unknown orientation table format"):
        (tmp_path / "t.json").write_text("{}")
        read_orientation_table(tmp_path / "t.json")
    with pytest.raises(InputError, match="no such file"):
        read_orientation_table(tmp_path / "missing.csv")
    plain = tmp_path / "plain"
    plain.mkdir()
    _save_jpeg(plain / "a.jpg")
    with pytest.raises(InputError, match="no photo carries camera attitude"):
        read_photo_attitudes([plain / "a.jpg"], source=plain)


def test_pairing_by_name_ignores_folder_extension_and_case():
    measured = OrientationTable.from_attitudes(
        ["field/IMG_0001.JPG", "IMG_0002.jpg", "IMG_0003.jpg"], [1, 2, 3], [0, 0, 0], [0, 0, 0]
    )
    estimated = OrientationTable.from_attitudes(
        ["img_0001", "IMG_0002.jpg", "other"], [4, 5, 6], [0, 0, 0], [0, 0, 0]
    )
    paired = pair_tables(estimated, measured)
    assert paired.photos == ["field/IMG_0001.JPG", "IMG_0002.jpg"]
    assert paired.capture_order.tolist() == [0, 1]
    assert any("not in the estimated table" in n for n in paired.notes)
    assert math.isclose(paired.estimated[0][2] @ rotation_from_attitude(4, 0, 0)[2], 1.0)


def test_photo_metadata_of_a_heic_phone_photo(tmp_path):
    from pillow_heif import register_heif_opener

    register_heif_opener()
    folder = tmp_path / "photos"
    folder.mkdir()
    exif = Image.Exif()
    exif[ExifTags.IFD.GPSInfo] = {ExifTags.GPS.GPSImgDirectionRef: "T",
                                  ExifTags.GPS.GPSImgDirection: 123.5}
    Image.new("RGB", (16, 12), (120, 90, 60)).save(folder / "IMG_0007.HEIC", exif=exif.tobytes())
    table = read_orientation_table(folder)
    assert table.photos == ["IMG_0007.HEIC"]
    assert table.attitudes[0, 0] == pytest.approx(123.5) and np.isnan(table.attitudes[0, 1:]).all()
