"""The Orient widget's *Auto (WMM)* declination (run under Xvfb).

The known answer is tests/test_declination_orient.py's: a survey whose phone
logged magnetic headings at 13° S, 59° W in early July 2027, where NOAA's
WMM2025 test values give a declination of −17.49°.
"""

from __future__ import annotations

import numpy as np
import pytest

from napari_imgreg.geo import Georef
from napari_imgreg.io.orientation_tables import OrientationTable, write_orientation_csv
from napari_imgreg.orient import rotation_error_deg
from napari_imgreg.sample.survey import simulate_survey

NOAA_DECLINATION = -17.49
SITE_GEOREF = Georef("EPSG:32721", [283_077.411822, 8_562_012.355651, 0.0])


@pytest.fixture
def magnetic_tables(tmp_path):
    survey = simulate_survey(np.random.default_rng(7))
    att = survey.measured.attitudes
    magnetic = OrientationTable.from_attitudes(
        survey.measured.photos, att[:, 0] - NOAA_DECLINATION, att[:, 1], att[:, 2])
    est, meas = tmp_path / "estimated.csv", tmp_path / "measured.csv"
    write_orientation_csv(est, survey.estimated)
    write_orientation_csv(meas, magnetic)
    lines = meas.read_text().splitlines()
    meas.write_text("\n".join([lines[0] + ",time"] + [f"{line},2027-07-02"
                                                     for line in lines[1:]]) + "\n")
    return est, meas, survey


@pytest.fixture
def widget(orient_widget):
    return orient_widget


def test_auto_declination_is_computed_in_the_backend(widget, magnetic_tables, tmp_path, qtbot):
    est, meas, survey = magnetic_tables
    SITE_GEOREF.save(tmp_path / "georef.json")  # beside the estimated table: found
    widget.set_tables(est, meas)
    widget.declination_auto.setChecked(True)
    assert not widget.declination_spin.isEnabled() and widget.georef_edit.isEnabled()
    with qtbot.waitSignal(widget.orientation_done, timeout=15000) as blocker:
        assert widget.run() is not None
    result = blocker.args[0]
    assert rotation_error_deg(result.rotation, survey.rotation) < 0.05
    assert result.inputs["declination"]["model"] == "WMM2025"
    assert widget.declination_spin.value() == pytest.approx(-17.5, abs=0.05)
    assert "declination -17.5° (WMM2025, 2027-07-02)" in widget.summary_label.text()

    # Unticked, the spin box is the input again (and 0 gives the magnetic rotation).
    widget.declination_auto.setChecked(False)
    widget.declination_spin.setValue(0.0)
    qtbot.waitUntil(lambda: widget.run_button.isEnabled(), timeout=5000)
    with qtbot.waitSignal(widget.orientation_done, timeout=15000) as blocker:
        widget.run()
    qtbot.waitUntil(lambda: widget.run_button.isEnabled(), timeout=5000)
    assert rotation_error_deg(blocker.args[0].rotation, survey.rotation) > 15.0


def test_auto_without_a_georef_or_gps_says_so(widget, magnetic_tables, qtbot):
    est, meas, _ = magnetic_tables
    widget.set_tables(est, meas)
    widget.declination_auto.setChecked(True)
    with qtbot.waitSignal(widget.orientation_failed, timeout=15000) as blocker:
        widget.run()
    assert "needs the site: the model's georef.json" in blocker.args[0]
    assert widget.run_button.isEnabled()


def test_auto_with_a_georef_chosen_elsewhere(widget, magnetic_tables, tmp_path, qtbot):
    est, meas, survey = magnetic_tables
    other = tmp_path / "site" / "model_georef.json"
    other.parent.mkdir()
    SITE_GEOREF.save(other)
    widget.set_tables(est, meas)
    widget.declination_auto.setChecked(True)
    widget.georef_edit.setText(str(other))
    with qtbot.waitSignal(widget.orientation_done, timeout=15000) as blocker:
        widget.run()
    # The worker has finished before the widget goes (a running one would outlive it).
    qtbot.waitUntil(lambda: widget.run_button.isEnabled(), timeout=5000)
    assert blocker.args[0].inputs["declination"]["georef"] == str(other)
