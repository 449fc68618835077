"""The photos table on its own: numbers sort as numbers, missing ones after
them; a row per photo follows the workspace; thumbnails are the photos."""

from __future__ import annotations

import math

import numpy as np
import pytest
from qtpy.QtCore import Qt

from napari_imgreg.registration.params import RegistrationParams
from napari_imgreg.registration.pipeline import Registration, Trial
from napari_imgreg.sample import sample_scene
from napari_imgreg.widgets._controller import WorkbenchController
from napari_imgreg.widgets._photos_table import (
    COLUMNS,
    THUMBNAIL_WIDTH,
    TIME_COLUMN,
    PhotosTable,
    _thumbnail,
)
from napari_imgreg.workspace import Workspace, read_photos, read_scene


def _registration(ps, q: float, secs: float) -> Registration:
    grade = "excellent" if q >= 1.2 else "good" if q >= 0.6 else "fair" if q >= 0 else "poor"
    trial = Trial(index=0, params=RegistrationParams(), metrics={}, q=q, grade=grade, hints=[],
                  pose=ps.pose, start_pose=ps.pose, rounds=1, converged=True, verified=True,
                  residual_flow_px=0.5)
    return Registration(status="registered", photo=ps.name, intrinsics=ps.intrinsics,
                        pose=ps.pose, prior=ps.prior, metrics={}, q=q, grade=grade, hints=[],
                        trials=[trial], timings_s={"total": secs}, best_trial=0)


@pytest.fixture
def table(make_napari_viewer):
    folder = sample_scene("small")
    scene, terrain = read_scene(folder / "outcrop.obj", dem=folder / "dem.tif")
    loaded, _ = read_photos(sorted(folder.glob("IMG_*.jpg")), scene)
    ws = Workspace()
    ws.load_scene(scene, terrain, {"mesh": folder / "outcrop.obj"})
    ctrl = WorkbenchController(make_napari_viewer(), workspace=ws)
    widget = PhotosTable(ctrl)
    ctrl.attach(widget)
    ws.add_loaded_photos(loaded)
    yield widget
    ctrl.shutdown()


def _column(table, col):
    return [table.table.item(r, col).text() for r in range(table.table.rowCount())]


def test_rows_follow_the_workspace_and_sort_by_number(table):
    ws = table.ws
    assert table.table.columnCount() == len(COLUMNS)
    assert _column(table, 1) == ["● IMG_0001.jpg", "● IMG_0002.jpg", "● IMG_0003.jpg"]
    first, _second, third = ws.photos
    # Q 10-ish apart as text would sort "10" before "9": these sort as numbers.
    ws.record_registration(_registration(first, 1.25, 9.0), "Auto", first)
    ws.record_registration(_registration(third, -0.3, 10.5), "Auto", third)
    assert _column(table, 4) == ["1.25", "—", "-0.30"]
    assert _column(table, TIME_COLUMN) == ["9.0", "—", "10.5"]
    assert _column(table, 3) == ["excellent", "—", "poor"]
    table.table.sortItems(TIME_COLUMN, Qt.SortOrder.AscendingOrder)
    assert _column(table, TIME_COLUMN) == ["9.0", "10.5", "—"]
    table.table.sortItems(4, Qt.SortOrder.AscendingOrder)
    assert _column(table, 4) == ["-0.30", "1.25", "—"]
    table.table.sortItems(3, Qt.SortOrder.AscendingOrder)  # best grade first
    assert _column(table, 3) == ["excellent", "poor", "—"]
    table.table.sortItems(2, Qt.SortOrder.AscendingOrder)  # the ones needing work first
    assert _column(table, 2)[0] == "not registered"
    # The rows still name their photos after sorting.
    for row in range(3):
        index = table.photo_index_at(row)
        assert table.table.item(row, 1).text().endswith(ws.photos[index].name)
    assert table.row_of(ws.current_index) is not None
    assert table.table.item(table.row_of(ws.current_index), 1).isSelected()


@pytest.mark.parametrize("from_file", [False, True])
def test_a_thumbnail_is_the_photo_made_small(tmp_path, from_file):
    """Of a photo in memory, and of one read from a file without keeping its pixels."""
    from napari_imgreg.io.photos import Photo, load_photo, save_image

    image = np.zeros((300, 400, 3), np.uint8)
    image[:, :200] = (255, 0, 0)
    photo = Photo(image)
    if from_file:
        save_image(tmp_path / "p.png", image)
        photo = load_photo(tmp_path / "p.png")
    pixmap = _thumbnail(photo)
    assert not photo.from_file or not photo.decoded
    assert pixmap.width() == THUMBNAIL_WIDTH
    assert pixmap.height() == round(300 * THUMBNAIL_WIDTH / 400)
    qimage = pixmap.toImage()
    left, right = qimage.pixelColor(2, 2), qimage.pixelColor(THUMBNAIL_WIDTH - 3, 2)
    assert (left.red(), left.green(), left.blue()) == (255, 0, 0)
    assert (right.red(), right.green(), right.blue()) == (0, 0, 0)
    assert not math.isnan(pixmap.height())


def test_lines_column_follows_drawings_projection_and_pose(table):
    """The table says which photos are drawn on and whether the last
    projection mapped their drawings as they are now (it had no column for
    them: the Interpret tab alone showed them, one photo at a time)."""
    from napari_imgreg.interpret.project import Interpretation
    from napari_imgreg.widgets._photos_table import LINES_COLUMN

    ws = table.ws
    first = ws.photos[0]
    ws.record_registration(_registration(first, 1.25, 2.0), "Auto", first)
    assert _column(table, LINES_COLUMN) == ["—", "—", "—"]
    line = np.array([[300.0, 300.0], [500.0, 320.0], [700.0, 310.0]])
    ws.add_interpretation(Interpretation("LineString", line, {"label": "bed"}), first)
    assert _column(table, LINES_COLUMN)[0] == "1 · not mapped"
    ws.project_interpretations()
    assert _column(table, LINES_COLUMN) == ["1 ✓", "—", "—"]
    assert ws.current is first
    ws.nudge(d_trend=0.5)
    assert table.table.item(table.row_of(0), LINES_COLUMN).text() == "1 · out of date"
    assert "1 mapped onto the model" in table.table.item(table.row_of(0), LINES_COLUMN).toolTip()


def test_a_photo_register_all_could_not_register_says_why(table):
    from napari_imgreg.workspace import BatchStep

    ws = table.ws
    second = ws.photos[1]
    ws.record_batch_step(BatchStep(photo=second, registration=None,
                                   error="IMG_0002.jpg: cannot be read", kind="Auto",
                                   index=1, total=3))
    row = table.row_of(1)
    assert table.table.item(row, 2).text() == "failed"
    assert "cannot be read" in table.table.item(row, 2).toolTip()


def test_one_photos_change_fills_its_row_only(table, monkeypatch):
    """A registration recorded (a step of Register all), or a switch of photo,
    refreshes the table: only the rows that show something new are filled
    again (filling every row grew with the campaign, on the GUI thread)."""
    from qtpy.QtWidgets import QHeaderView

    ws = table.ws
    filled = []
    fill = table._fill
    monkeypatch.setattr(table, "_fill", lambda row, index, ps, s=None: (
        filled.append(index), fill(row, index, ps, s)))
    table.table.sortItems(2, Qt.SortOrder.DescendingOrder)  # rows not in the photos' order
    second = ws.photos[1]
    ws.record_registration(_registration(second, 0.8, 3.0), "Auto", second,
                           pose_if_not_current=True)
    assert filled == [1]
    assert table.table.item(table.row_of(1), 3).text() == "good"
    assert table.table.item(table.row_of(1), 2).text() == "registered"
    filled.clear()
    ws.select_photo(2)
    table.refresh()
    assert filled == []
    assert table.table.item(table.row_of(2), 1).isSelected()
    # Columns are sized to their contents again after a fill.
    header = table.table.horizontalHeader()
    assert all(header.sectionResizeMode(k) == QHeaderView.ResizeMode.ResizeToContents
               for k in range(len(COLUMNS)))
    # A photo added: every row.
    third_again = read_photos([ws.photos[2].photo.path.with_name("IMG_0001.jpg")], ws.scene)[0]
    ws.photos.clear()
    ws.add_loaded_photos(third_again)
    assert filled == [0]
    assert _column(table, 1) == ["● IMG_0001.jpg"]


def test_opening_a_workspace_makes_the_thumbnails_in_its_worker(tmp_path, monkeypatch, qapp):
    """The worker that opens a workspace makes the table's thumbnails: the GUI
    thread decodes none of them (hundreds took it seconds)."""
    from napari_imgreg.io import photos as photos_module
    from napari_imgreg.widgets._controller import _open_workspace_warm

    folder = sample_scene("small")
    ws = Workspace()
    ws.open_scene(folder / "outcrop.obj", dem=folder / "dem.tif")
    ws.add_photos(sorted(folder.glob("IMG_*.jpg")))
    ws.save(tmp_path / "campaign.imgreg")
    ws.detach()
    opened = _open_workspace_warm(tmp_path / "campaign.imgreg", THUMBNAIL_WIDTH)
    opened.detach()

    def no_decoding(*args, **kwargs):
        raise AssertionError("a photo decoded on the GUI thread")

    monkeypatch.setattr(photos_module, "_read_rgb", no_decoding)
    for ps in opened.photos:
        assert _thumbnail(ps.photo).width() == THUMBNAIL_WIDTH
        assert not ps.photo.decoded


def test_several_layers_removed_in_one_batch(make_napari_viewer):
    """napari collects garbage once per batch of removals, not once per layer;
    a batch within a batch adds none (napari's do not nest)."""
    from napari_imgreg.widgets._layers import layers_batched, remove_layers

    viewer = make_napari_viewer()
    layers = [viewer.add_points(np.zeros((1, 2)), name=f"p{k}") for k in range(5)]
    ends = []
    viewer.layers.events.end_batch.connect(lambda event: ends.append(event))
    remove_layers(viewer, layers[:2])
    assert len(ends) == 1 and [layer.name for layer in viewer.layers] == ["p2", "p3", "p4"]
    with layers_batched(viewer):
        remove_layers(viewer, layers[2:4])
        assert not ends[1:]  # the inner removals did not end the batch
    assert len(ends) == 2 and [layer.name for layer in viewer.layers] == ["p4"]
    remove_layers(viewer, [layers[4], layers[0]])  # one still there: no batch
    assert len(ends) == 2 and len(viewer.layers) == 0
