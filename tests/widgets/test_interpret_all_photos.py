"""Project onto the model, in the workbench, projects every photo's drawings:
those of the photo on screen (its interpretation layer, with the edits made
there) and the workspace's saved drawings of the photos not shown (a reopened
workspace shows only the current photo's layer). The status line says how many
photos and traces were projected, and which photos' projection is out of date.

Run in a real napari viewer under Xvfb.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from napari_imgreg.interpret.project import Interpretation
from napari_imgreg.widgets._layers import napari_from_pixels
from napari_imgreg.widgets.interpret_widget import INTERP_KEY

from ._workbench import LOAD_S, idle as _idle, registered_on_truth, save_and_reopen




def _lines(n: int, tag: str) -> list[Interpretation]:
    return [Interpretation("LineString",
                           [[250.0 + 120 * k, 300.0], [300.0 + 120 * k, 500.0]],
                           {"label": ("sandstone", "fault")[k % 2], "comment": f"{tag} {k}"})
            for k in range(n)]


def test_a_reopened_workspace_projects_the_photos_not_shown_too(workbench, qtbot, tmp_path):
    wb = workbench
    wb.scene_panel.sample_button.click()
    qtbot.waitUntil(lambda: wb.controller.current is not None, timeout=LOAD_S)
    _idle(wb, qtbot)
    ctrl, ws = wb.controller, wb.controller.workspace
    one, two = ws.photos[0], ws.photos[1]
    for k in (1, 0):  # each registered while current; IMG_0001 is current at the end
        ctrl.select_photo(k)
        _idle(wb, qtbot)
        ws.record_registration(registered_on_truth(ws.photos[k]))
    assert ws.current is one
    ws.set_interpretations(_lines(3, "one"), one)
    ws.set_interpretations(_lines(4, "two"), two)
    ws.project_interpretations()  # the backend: both photos
    assert Counter(f.source for f in ws.features_3d) == {"IMG_0001.jpg": 3, "IMG_0002.jpg": 4}
    # IMG_0002 drawn on after that projection: its projection is out of date.
    ws.set_interpretations(_lines(5, "two"), two)
    assert ws.projection_out_of_date() == [two]
    # Reopened: only IMG_0001 (the current photo) is shown, with its layer.
    ws = save_and_reopen(wb, qtbot, tmp_path / "campaign")
    iw = wb.interpret_widget
    one, two = ws.photos[0], ws.photos[1]
    assert ws.current is one
    assert len(one.interpretations) == 3 and len(two.interpretations) == 5
    layers = [lay for lay in wb.viewer.layers if INTERP_KEY in lay.metadata]
    assert [lay.metadata[INTERP_KEY] for lay in layers] == ["IMG_0001"]
    # The saved projection is shown, naming the photo it is out of date for.
    assert "IMG_0002.jpg" in iw.status_label.text()
    assert "IMG_0001.jpg" not in iw.status_label.text()

    # One more line drawn on screen on IMG_0001: 4 there, 5 saved on IMG_0002.
    layer = layers[0]
    layer.add(napari_from_pixels(np.array([[700.0, 150.0], [740.0, 450.0]])), shape_type="path")
    assert len(one.interpretations) == 4
    assert "IMG_0001.jpg" in iw.status_label.text()  # now out of date too

    with qtbot.waitSignal(iw.projection_done, timeout=60_000) as blocker:
        assert iw.project() is not None
    qtbot.waitUntil(lambda: iw.project_button.isEnabled(), timeout=10_000)
    by_photo = Counter(f.source for f in blocker.args[0])
    assert by_photo == {"IMG_0001.jpg": 4, "IMG_0002.jpg": 5}
    # Recorded in the workspace (and so saved), nothing left out of date.
    assert Counter(f.source for f in ws.features_3d) == by_photo
    assert ws.projection_out_of_date() == []
    text = iw.status_label.text()
    assert "9 trace(s) from 2 photo(s)" in text, text
    # The saved drawings of IMG_0002 are untouched (not replaced by a layer's).
    assert [i.properties.get("comment") for i in two.interpretations] == [
        f"two {k}" for k in range(5)]

    # A pose moved after the projection: the status line names its photo.
    ctrl.nudge("turn right 1", d_trend=1.0)
    qtbot.waitUntil(lambda: "IMG_0001.jpg" in iw.status_label.text(), timeout=5_000)
    assert [ps.name for ps in ws.projection_out_of_date()] == ["IMG_0001.jpg"]
    ctrl.undo()
    _idle(wb, qtbot)
    assert ws.projection_out_of_date() == []

    # An edit after the projection names the photo it makes out of date.
    layer.selected_data = {0}
    layer.remove_selected()
    assert len(one.interpretations) == 3
    text = iw.status_label.text()
    assert "IMG_0001.jpg" in text and "IMG_0002.jpg" not in text, text
