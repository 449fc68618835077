"""The Manual tab's pairs in napari: deleting, a new reference, the result's
expected error (the full solve from the truth: test_workbench.py)."""

from __future__ import annotations

import numpy as np

from napari_imgreg.sample import load_truth
from napari_imgreg.widgets._layers import napari_from_pixels

from ._workbench import LOAD_S, idle as _idle, reference_and_truth_pairs


def test_pairs_stay_matched_through_deletes_and_a_new_reference(workbench, qtbot):
    wb = workbench
    ctrl, ps, photo_px, ref_px = reference_and_truth_pairs(wb, qtbot)
    truth = load_truth(ps.photo.path)
    panel = wb.manual_panel
    rng = np.random.default_rng(0)
    P = photo_px + rng.normal(0, 1.0, (8, 2))  # clicks, about a pixel off
    R = ref_px + rng.normal(0, 1.0, (8, 2))

    panel.pick_button.click()
    photo_layer, ref_layer = ctrl.pair_layers()
    for k in range(3):
        photo_layer.add(napari_from_pixels(P[k]))
        ref_layer.add(napari_from_pixels(R[k]))
    photo_layer.add(napari_from_pixels(P[3]))  # waits for its partner
    # Deleting reference point 2 deletes photo point 2: pairs 1 and 3 stay, in order.
    ref_layer.selected_data = {1}
    ref_layer.remove_selected()
    np.testing.assert_allclose(ctrl.workspace.pairs()[0], P[[0, 2]])
    np.testing.assert_allclose(ctrl.workspace.pairs()[1], R[[0, 2]])
    np.testing.assert_allclose(ps.photo_points_px[2], P[3])  # still waiting
    assert list(photo_layer.features["pair"]) == [1, 2, 3]
    assert panel.table.rowCount() == 3
    assert panel.table.item(2, 1).text() == f"{P[3, 0]:.1f}, {P[3, 1]:.1f}"
    assert panel.table.item(2, 2).text() == "click the reference"
    ref_layer.add(napari_from_pixels(R[3]))
    for k in range(4, 8):
        photo_layer.add(napari_from_pixels(P[k]))
        ref_layer.add(napari_from_pixels(R[k]))
    assert len(ctrl.workspace.pairs()[0]) == 7
    # A mis-click on the photo, then Delete at once (napari selects each added
    # point): the reference layer now active must have nothing selected, or
    # pair 7 goes and the mis-click stays (before: it did).
    from napari.layers.points._points_key_bindings import delete_selected_points

    photo_layer.add(napari_from_pixels([900.0, 700.0]))
    assert wb.viewer.layers.selection.active is ref_layer
    delete_selected_points(ref_layer)
    np.testing.assert_allclose(ctrl.workspace.pairs()[1][-1], R[7])
    photo_layer.selected_data = {7}  # the mis-click, selected where it is
    delete_selected_points(photo_layer)
    assert len(ps.photo_points_px) == len(ps.reference_points_px) == 7

    with qtbot.waitSignal(ctrl.manual_finished, timeout=60_000) as solved:
        panel.solve_button.click()
    _idle(wb, qtbot)
    sol = solved.args[0]
    assert sol.ok
    assert sol.pose.rotation_error_deg(truth.pose) < 0.5
    # The label gives the pose's expected error, not only the pairs' RMS.
    assert "Expected error" in panel.result_label.text()
    assert f"{sol.uncertainty.position_m:.2f} m" in panel.result_label.text()

    # A new reference drops its picks; the photo's stay and show where they are.
    with qtbot.waitSignal(ctrl.reference_ready, timeout=20_000):
        panel.ref_pose_button.click()
    _idle(wb, qtbot)
    assert len(ps.reference_points_px) == 0 and len(ps.photo_points_px) == 7
    assert panel.table.rowCount() == 7
    kept = ps.photo_points_px
    for i in range(7):
        assert panel.table.item(i, 1).text() == f"{kept[i, 0]:.1f}, {kept[i, 1]:.1f}"
        assert panel.table.item(i, 2).text() == "click the reference"
    assert len(ref_layer.data) == 0 and len(photo_layer.data) == 7


def test_ctrl_v_on_a_pair_layer_pastes_no_pick(workbench, qtbot):
    """napari's paste adds points without telling anyone (no data event): on
    the pair layers it is refused, so the picks and the pairs never part."""
    wb = workbench
    ctrl = wb.controller
    wb.scene_panel.sample_button.click()
    qtbot.waitUntil(lambda: ctrl.current is not None, timeout=LOAD_S)
    _idle(wb, qtbot)
    wb.show_tab("Manual")
    with qtbot.waitSignal(ctrl.reference_ready, timeout=20_000):
        wb.manual_panel.ref_pose_button.click()
    _idle(wb, qtbot)
    for k in range(3):
        ctrl.workspace.add_pair([100.0 + 50 * k, 200.0], [110.0 + 50 * k, 210.0])
    photo, _ = ctrl.pair_layers()
    ctrl.viewer.layers.selection.active = photo
    photo.mode = "select"
    photo.selected_data = {1}
    photo._copy_data()
    with qtbot.waitSignal(ctrl.status, timeout=2_000) as said:
        ctrl.viewer.window._qt_viewer._key_map_handler.press_key("Control-V")
    assert "not pasted" in said.args[0]
    assert len(photo.data) == 3 and len(ctrl.workspace.current.photo_points_px) == 3
    assert wb.manual_panel.table.rowCount() == 3
