"""The Manual tab's Save pairs… and Load pairs…: a round trip through the CSV,
and loaded pairs whose model points the reference does not show still solving."""

from __future__ import annotations

import numpy as np

from napari_imgreg.io.control_points import read_control_points, write_control_points
from napari_imgreg.sample import load_truth
from napari_imgreg.widgets._layers import pixels_from_napari

from ._workbench import idle, load_sample

_DIALOGS = "napari_imgreg.widgets._panels.QFileDialog"


def _with_reference(wb, qtbot):
    ctrl = load_sample(wb, qtbot)
    wb.show_tab("Manual")
    with qtbot.waitSignal(ctrl.reference_ready, timeout=20_000):
        wb.manual_panel.ref_pose_button.click()
    idle(wb, qtbot)
    return ctrl, ctrl.current


def test_saved_pairs_load_back_into_the_table_and_layers(workbench, qtbot, monkeypatch, tmp_path):
    wb = workbench
    ctrl, ps = _with_reference(wb, qtbot)
    panel = wb.manual_panel
    truth = load_truth(ps.photo.path)
    ref = ps.reference
    ref_px = ref.cam_from_world.project(ref.intrinsics, truth.check_xyz)
    photo_px = truth.pose.project(truth.intrinsics, truth.check_xyz)
    _, valid = ref.lift(ref_px)
    idx = np.flatnonzero(valid)[:6]
    for k in idx:
        ctrl.workspace.add_pair(photo_px[k], ref_px[k])
    picked_xyz, _ = ctrl.workspace.pair_points_3d()
    assert panel.save_pairs_button.isEnabled()

    path = tmp_path / "IMG_0001.pairs.csv"
    monkeypatch.setattr(f"{_DIALOGS}.getSaveFileName", lambda *a, **k: (str(path), ""))
    panel.save_pairs_button.click()
    saved = read_control_points(path)
    np.testing.assert_allclose(saved.photo_px, photo_px[idx], atol=1e-5)
    np.testing.assert_allclose(saved.xyz, picked_xyz, atol=1e-5)
    assert saved.names == [""] * 6  # clicked pairs have no names

    panel.clear_button.click()
    assert panel.table.rowCount() == 0
    monkeypatch.setattr(f"{_DIALOGS}.getOpenFileName", lambda *a, **k: (str(path), ""))
    panel.load_pairs_button.click()
    photo_layer, ref_layer = ctrl.pair_layers()
    np.testing.assert_allclose(ctrl.workspace.pairs()[0], photo_px[idx], atol=1e-5)
    np.testing.assert_allclose(ctrl.workspace.pair_points_3d()[0], picked_xyz, atol=1e-5)
    # Shown as clicked pairs are: on both images, numbered, in the table.
    np.testing.assert_allclose(pixels_from_napari(np.asarray(photo_layer.data)), photo_px[idx],
                               atol=1e-5)
    np.testing.assert_allclose(pixels_from_napari(np.asarray(ref_layer.data)), ref_px[idx],
                               atol=0.05)
    assert list(ref_layer.features["pair"]) == [1, 2, 3, 4, 5, 6]
    assert panel.table.rowCount() == 6 and panel.table.item(0, 3).text() == "✓ from file"
    assert panel.table.item(0, 0).text() == "1"

    # Dragging a loaded pair's photo point keeps its model point; deleting a
    # pair keeps the others'.
    moved = np.asarray(photo_layer.data).copy()
    moved[0] += 2.0
    photo_layer.data = moved
    assert ctrl.workspace.pairs_with_own_point().all()
    photo_layer.selected_data = {2}
    photo_layer.remove_selected()
    np.testing.assert_allclose(ctrl.workspace.pair_points_3d()[0],
                               np.delete(picked_xyz, 2, axis=0), atol=1e-5)

    # A pair is named by double-clicking its number; the name is saved with it.
    monkeypatch.setattr("napari_imgreg.widgets._panels.QInputDialog.getText",
                        lambda *a, **k: ("GCP7", True))
    panel.table.cellDoubleClicked.emit(1, 0)
    assert panel.table.item(1, 0).text() == "2 GCP7"
    panel.rename_pair(0, "GCP7")  # another pair's name: refused, said
    assert ctrl.workspace.pair_names()[:2] == ["", "GCP7"]
    panel.save_pairs_button.click()
    assert read_control_points(path).names == ["", "GCP7", "", "", ""]


def test_loaded_pairs_off_the_reference_keep_their_points_and_solve(
        workbench, qtbot, monkeypatch, tmp_path):
    wb = workbench
    ctrl, ps = _with_reference(wb, qtbot)
    panel = wb.manual_panel
    truth = load_truth(ps.photo.path)
    ref = ps.reference
    # Targets on 1.5 m poles in front of the rock: in the photo, not on the model.
    toward = truth.pose.center - truth.check_xyz
    xyz = truth.check_xyz + 1.5 * toward / np.linalg.norm(toward, axis=1, keepdims=True)
    photo_px = truth.pose.project(truth.intrinsics, xyz)
    inside = np.all((photo_px > 5) & (photo_px < np.array(ps.size) - 5), axis=1)
    xyz, photo_px = xyz[inside][:10], photo_px[inside][:10]
    path = tmp_path / "targets.csv"
    write_control_points(path, photo_px, xyz, [f"T{k + 1}" for k in range(len(xyz))])
    monkeypatch.setattr(f"{_DIALOGS}.getOpenFileName", lambda *a, **k: (str(path), ""))
    panel.load_pairs_button.click()
    assert panel.table.rowCount() == 10
    assert panel.table.item(0, 0).text() == "1 T1"  # the table names the surveyed targets
    lifted, on_model = ref.lift(ref.cam_from_world.project(ref.intrinsics, xyz))
    assert not np.allclose(lifted[on_model], xyz[on_model], atol=0.5)  # not the model's points
    np.testing.assert_allclose(ctrl.workspace.pair_points_3d()[0], xyz, atol=1e-5)
    # A new reference keeps them.
    with qtbot.waitSignal(ctrl.reference_ready, timeout=20_000):
        panel.ref_pose_button.click()
    idle(wb, qtbot)
    assert len(ctrl.workspace.pairs()[0]) == 10
    with qtbot.waitSignal(ctrl.manual_finished, timeout=60_000) as solved:
        panel.solve_button.click()
    idle(wb, qtbot)
    sol = solved.args[0]
    assert sol.ok and sol.pose.rotation_error_deg(truth.pose) < 0.01
    assert np.linalg.norm(sol.pose.center - truth.pose.center) < 0.01


def test_a_loaded_point_out_of_the_references_view_is_said_so(workbench, qtbot, monkeypatch,
                                                             tmp_path):
    """A target the reference cannot show reads "out of its view", not the
    made-up pixel it is parked at."""
    wb = workbench
    ctrl, ps = _with_reference(wb, qtbot)
    truth = load_truth(ps.photo.path)
    xyz = truth.check_xyz[:6].copy()
    xyz[5] = truth.pose.center + [0.0, 0.0, 30.0]  # above the camera: behind the reference's view
    photo_px = np.clip(truth.pose.project(truth.intrinsics, xyz), 10, np.array(ps.size) - 10)
    path = tmp_path / "pairs.csv"
    write_control_points(path, photo_px, xyz)
    monkeypatch.setattr(f"{_DIALOGS}.getOpenFileName", lambda *a, **k: (str(path), ""))
    wb.manual_panel.load_pairs_button.click()
    table = wb.manual_panel.table
    assert table.rowCount() == 6
    assert table.item(5, 2).text() == "out of its view"
    assert table.item(0, 2).text() != "out of its view"

    # The sample's pairs of another photo, loaded on this one: said.
    warnings = []
    monkeypatch.setattr(ctrl, "notify_warning", warnings.append)
    other = tmp_path / "IMG_0002.pairs.csv"
    other.write_bytes(path.read_bytes())
    monkeypatch.setattr(f"{_DIALOGS}.getOpenFileName", lambda *a, **k: (str(other), ""))
    wb.manual_panel.load_pairs_button.click()
    assert warnings and warnings[0].startswith("IMG_0002.pairs.csv is named for IMG_0002.jpg, "
                                               f"not for {ps.name}")


def test_a_bad_file_is_one_notification_and_keeps_the_pairs(workbench, qtbot, monkeypatch,
                                                            tmp_path):
    wb = workbench
    ctrl, ps = _with_reference(wb, qtbot)
    ctrl.workspace.add_pair([100.0, 100.0], [120.0, 110.0])
    errors = []
    monkeypatch.setattr(ctrl, "notify_error", errors.append)
    path = tmp_path / "bad.csv"
    path.write_text("photo_x,photo_y,x,y,z\n1,2,3,4,5\n1,oops,3,4,5\n")
    monkeypatch.setattr(f"{_DIALOGS}.getOpenFileName", lambda *a, **k: (str(path), ""))
    wb.manual_panel.load_pairs_button.click()
    assert errors == [f"{path}: row 3: photo_y is not a number ('oops')"]
    assert len(ctrl.workspace.pairs()[0]) == 1
