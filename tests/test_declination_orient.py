"""``orient --declination auto``: the WMM declination at the georeferenced origin.

Known answer: a generated survey (the rotation is known exactly) whose
phone logged magnetic headings at 13° S, 59° W in early July 2027, where
NOAA's WMM2025 test values give a declination of −17.49° (2027.5, 0 km;
WMM2025_TEST_VALUES.txt, see tests/test_declination.py). The phone's
magnetic trend is the true trend − (−17.49°); orienting with ``auto`` must
give the true rotation back.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import ExifTags, Image

from napari_imgreg.errors import InputError
from napari_imgreg.geo import Georef
from napari_imgreg.io.orientation_tables import (
    OrientationTable,
    read_orientation_table,
    write_orientation_csv,
)
from napari_imgreg.orient import orient, rotation_error_deg, survey_date
from napari_imgreg.sample.survey import simulate_survey

NOAA_DECLINATION = -17.49
# UTM 21S coordinates of 13° S, 59° W: the model origin is the site.
SITE_GEOREF = Georef("EPSG:32721", [283_077.411822, 8_562_012.355651, 0.0])
DAYS = ["2027-07-01", "2027-07-02", "2027-07-02T16:05:00-04:00", "2027-07-03"]


@pytest.fixture(scope="module")
def survey():
    return simulate_survey(np.random.default_rng(7))


def _magnetic_table(survey) -> OrientationTable:
    att = survey.measured.attitudes
    return OrientationTable.from_attitudes(
        survey.measured.photos, att[:, 0] - NOAA_DECLINATION, att[:, 1], att[:, 2])


def _write_tables(folder, survey, *, times=True, georef=True):
    """ESTIMATED and MEASURED CSVs (the latter magnetic, with a time column)."""
    folder.mkdir(exist_ok=True)
    estimated, measured = folder / "cameras.csv", folder / "phone.csv"
    write_orientation_csv(estimated, survey.estimated)
    write_orientation_csv(measured, _magnetic_table(survey))
    if times:
        lines = measured.read_text().splitlines()
        lines = [lines[0] + ",time"] + [f"{line},{DAYS[i % len(DAYS)]}"
                                        for i, line in enumerate(lines[1:])]
        measured.write_text("\n".join(lines) + "\n")
    if georef:
        SITE_GEOREF.save(folder / "georef.json")
    return estimated, measured


def test_auto_declination_gives_the_true_rotation_back(tmp_path, survey):
    estimated, measured = _write_tables(tmp_path, survey)
    table = read_orientation_table(measured)
    assert table.capture_dates[2].isoformat() == "2027-07-02"
    magnetic = orient(read_orientation_table(estimated), table)
    assert rotation_error_deg(magnetic.rotation, survey.rotation) > 15.0
    result = orient(read_orientation_table(estimated), table, declination_deg="auto",
                    georef=tmp_path / "georef.json")
    assert result.inputs["declination_deg"] == pytest.approx(NOAA_DECLINATION, abs=0.05)
    assert rotation_error_deg(result.rotation, survey.rotation) < 0.05
    block = result.inputs["declination"]
    assert block["model"] == "WMM2025" and block["date"] == "2027-07-02"
    assert block["source"] == "World Magnetic Model"
    assert block["latitude_deg"] == pytest.approx(-13.0, abs=1e-5)
    assert block["longitude_deg"] == pytest.approx(-59.0, abs=1e-5)
    assert "median of 51 capture dates in the MEASURED table's time column, over 3 days" \
        == block["date_from"]
    assert block["georef"].endswith("georef.json")
    assert any(n.startswith("declination -17.5° (WMM2025, 2027-07-02) added to the measured "
                            "trends: World Magnetic Model at 13.0000° S, 59.0000° W")
               for n in result.notes)


def test_a_given_declination_is_recorded_as_given(survey):
    result = orient(survey.estimated, _magnetic_table(survey), declination_deg=-17.49)
    assert result.inputs["declination_deg"] == -17.49
    assert result.inputs["declination"] == {"declination_deg": -17.49, "source": "given"}
    assert rotation_error_deg(result.rotation, survey.rotation) < 1e-6


def test_auto_needs_a_site_and_dates(survey):
    with pytest.raises(InputError, match="needs the site: the model's georef.json"):
        orient(survey.estimated, survey.measured, declination_deg="auto")
    with pytest.raises(InputError, match="no capture dates for an automatic declination"):
        orient(survey.estimated, survey.measured, declination_deg="auto", georef=SITE_GEOREF)
    with pytest.raises(ValueError, match="degrees or 'auto'"):
        orient(survey.estimated, survey.measured, declination_deg="automatic")


def _jpeg(path, taken=None, direction=None, ref="M", lat_lon=None):
    exif = Image.Exif()
    if taken is not None:
        exif.get_ifd(ExifTags.IFD.Exif)[ExifTags.Base.DateTimeOriginal] = taken
    gps = exif.get_ifd(ExifTags.IFD.GPSInfo) if direction is not None or lat_lon else None
    if direction is not None:
        gps[ExifTags.GPS.GPSImgDirectionRef] = ref
        gps[ExifTags.GPS.GPSImgDirection] = direction
    if lat_lon is not None:
        (lat, lon) = lat_lon
        gps[ExifTags.GPS.GPSLatitudeRef] = "S" if lat < 0 else "N"
        gps[ExifTags.GPS.GPSLatitude] = (abs(lat), 0.0, 0.0)
        gps[ExifTags.GPS.GPSLongitudeRef] = "W" if lon < 0 else "E"
        gps[ExifTags.GPS.GPSLongitude] = (abs(lon), 0.0, 0.0)
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(path, exif=exif)


def test_without_a_time_column_the_photos_exif_dates_the_survey(tmp_path, survey):
    _, measured = _write_tables(tmp_path, survey, times=False)
    table = read_orientation_table(measured)
    assert table.capture_dates is None
    # Some of the photos beside the table, by name (one with another case and suffix).
    _jpeg(tmp_path / table.photos[0], "2027:07:01 10:00:00")
    _jpeg(tmp_path / table.photos[1], "2027:07:05 10:00:00")
    stem = table.photos[2].rsplit(".", 1)[0].upper()
    _jpeg(tmp_path / f"{stem}.JPEG", "2027:07:02 18:00:00")
    day, source = survey_date(table)
    assert day.isoformat() == "2027-07-02"
    assert source == f"median of 3 capture dates in EXIF DateTimeOriginal of the photos in " \
                     f"{tmp_path}, over 5 days"


def test_without_a_georef_the_photos_gps_places_the_site(tmp_path, survey):
    """A photogrammetry model without a georeference (what orient is for): the
    MEASURED photos' own GPS places the site."""
    estimated, measured = _write_tables(tmp_path, survey, times=False, georef=False)
    table = read_orientation_table(measured)
    for k, name in enumerate(table.photos[:5]):
        # A few metres apart (1e-5° ≈ 1 m); one phone without a fix (0, 0) is not a site.
        where = (0.0, 0.0) if k == 4 else (-13.0 + 1e-5 * k, -59.0 - 1e-5 * k)
        _jpeg(tmp_path / name, f"2027:07:0{1 + k % 3} 10:00:00", lat_lon=where)
    result = orient(read_orientation_table(estimated), table, declination_deg="auto")
    assert result.inputs["declination_deg"] == pytest.approx(NOAA_DECLINATION, abs=0.05)
    assert rotation_error_deg(result.rotation, survey.rotation) < 0.05
    block = result.inputs["declination"]
    assert block["georef"] is None
    assert block["place"] == f"the median GPS position of 4 photos in {tmp_path}"
    assert block["latitude_deg"] == pytest.approx(-13.0, abs=1e-4)
    assert any("the median GPS position of 4 photos" in n for n in result.notes)


def test_a_folder_of_photos_keeps_dates_and_heading_references(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    _jpeg(folder / "A.jpg", "2026:06:01 09:00:00", direction=10.0, ref="M")
    _jpeg(folder / "B.jpg", "2026:06:03 09:00:00", direction=20.0, ref="T")
    _jpeg(folder / "C.jpg", None, direction=30.0, ref="M")
    table = read_orientation_table(folder)
    assert table.heading_references == ["magnetic", "true", "magnetic"]
    assert [d and d.isoformat() for d in table.capture_dates] == ["2026-06-01", "2026-06-03",
                                                                  None]
    assert "2 photo(s) give magnetic, not true, north (EXIF GPSImgDirectionRef M)" in table.notes
    day, source = survey_date(table)
    assert day.isoformat() == "2026-06-01"  # the lower middle of two
    assert source == "median of 2 capture dates in the photos' EXIF, over 3 days"


def test_a_bad_time_cell_names_the_row(tmp_path):
    table = tmp_path / "phone.csv"
    table.write_text("photo,trend_deg,plunge_deg,roll_deg,time\na,10,5,0,2026-06-01\n"
                     "b,20,5,0,yesterday\n")
    with pytest.raises(InputError, match=r"phone.csv: row 3: time is not a date \('yesterday'"):
        read_orientation_table(table)
    table.write_text("photo,trend_deg,plunge_deg,roll_deg,time\na,10,5,0,2026:06:01 10:00:00\n"
                     "b,20,5,0,\n")
    assert [d and d.isoformat() for d in read_orientation_table(table).capture_dates] == [
        "2026-06-01", None]


# ------------------------------------------------------------------ command line
def test_cli_auto_writes_the_declination_and_its_source(tmp_path, survey, run_cli):
    estimated, measured = _write_tables(tmp_path, survey)
    out = tmp_path / "ORIENTATION.json"
    run = run_cli(["orient", estimated, measured, "--out", out, "--declination", "auto"],
                  max_seconds=None)
    assert run.code == 0, run.err
    assert "note: declination -17.5° (WMM2025, 2027-07-02) added" in run.out
    inputs = json.loads(out.read_text())["inputs"]
    assert inputs["declination_deg"] == pytest.approx(NOAA_DECLINATION, abs=0.05)
    assert inputs["declination"]["model"] == "WMM2025"
    assert inputs["declination"]["date"] == "2027-07-02"


def test_cli_numeric_declination_is_unchanged(tmp_path, survey, run_cli):
    estimated, measured = _write_tables(tmp_path, survey, times=False, georef=False)
    out = tmp_path / "o.json"
    run = run_cli(["orient", estimated, measured, "--out", out, "--declination", "-17.49"],
                  max_seconds=None)
    assert run.code == 0, run.err
    data = json.loads(out.read_text())
    assert data["inputs"]["declination_deg"] == -17.49
    assert data["inputs"]["declination"] == {"declination_deg": -17.49, "source": "given"}
    assert "declination" not in " ".join(data["notes"])


def test_cli_auto_without_a_georef_or_gps_is_one_line(tmp_path, survey, run_cli):
    estimated, measured = _write_tables(tmp_path, survey, georef=False)
    run = run_cli(["orient", estimated, measured, "--out", tmp_path / "o.json",
                   "--declination", "auto"])
    assert run.code == 2
    assert f"{measured}: an automatic declination needs the site: the model's georef.json" \
        in run.line
    assert not (tmp_path / "o.json").exists()


def test_cli_auto_without_dates_asks_for_a_number(tmp_path, survey, run_cli):
    estimated, measured = _write_tables(tmp_path, survey, times=False)
    run = run_cli(["orient", estimated, measured, "--out", tmp_path / "o.json",
                   "--declination", "auto"])
    assert run.code == 2
    assert f"{measured}: no capture dates" in run.line and "--declination DEG" in run.line


def test_cli_auto_with_a_date_past_the_models(tmp_path, survey, run_cli):
    estimated, measured = _write_tables(tmp_path, survey)
    measured.write_text(measured.read_text().replace("2027-07", "2035-07"))
    georef = tmp_path / "elsewhere.json"
    SITE_GEOREF.save(georef)
    run = run_cli(["orient", estimated, measured, "--out", tmp_path / "o.json",
                   "--declination", "auto", "--georef", georef])
    assert run.code == 2
    assert run.line.endswith(f"{georef}: magnetic declination: 2035-07-02 is past the newest "
                             "World Magnetic Model installed (WMM2025, valid to 2030.0; used 1 "
                             "year beyond): update pygeomag or give the declination as a number "
                             "(--declination DEG)")


def test_cli_declination_that_is_neither_a_number_nor_auto(tmp_path, run_cli, capsys):
    table = tmp_path / "cams.csv"
    table.write_text("photo,trend_deg,plunge_deg,roll_deg\na,10,5,0\nb,100,3,1\nc,200,8,-1\n")
    with pytest.raises(SystemExit) as stop:  # argparse's usage error, as for any bad option
        run_cli(["orient", table, table, "--out", tmp_path / "o.json", "--declination", "east"])
    assert stop.value.code == 2
    assert "expected degrees east (e.g. 3.0) or 'auto', got 'east'" in capsys.readouterr().err


@pytest.mark.parametrize("argv, needle", [
    (["--declination", "3", "--georef", "g.json"], "--georef is read only with --declination"),
    (["--declination", "auto", "--georef", "missing.json"], "missing.json: no such file"),
])
def test_cli_declination_options_are_checked(tmp_path, survey, run_cli, argv, needle):
    estimated, measured = _write_tables(tmp_path, survey)
    (tmp_path / "g.json").write_text("{}")
    argv = [a if not a.endswith(".json") else tmp_path / a for a in argv]
    run = run_cli(["orient", estimated, measured, "--out", tmp_path / "o.json", *argv])
    assert run.code == 2 and needle in run.err
