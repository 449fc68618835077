"""napari integration: manifest, reader, sample data, and what the canvas shows.

Runs in a real napari viewer (napari needs an X server: `make test` runs the
suite under Xvfb).
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from PIL import Image

from napari_imgreg import Scene
from napari_imgreg.widgets._layers import napari_from_world, surface_layer_data, world_from_napari
from napari_imgreg._reader import get_reader


def _marked_wall(tmp_path):
    """A 40 × 20 m wall in the plane y = 0 facing south; its texture's top-left
    quadrant is red, so a mirrored or flipped display is easy to spot."""
    vertices = np.array([[0, 0, 0], [40, 0, 0], [40, 0, 20], [0, 0, 20]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    texture = np.full((64, 128, 3), 200, np.uint8)
    texture[:32, :64] = (255, 0, 0)
    mesh = trimesh.Trimesh(
        vertices, faces, process=False,
        visual=trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(texture)),
    )
    path = tmp_path / "wall.obj"
    mesh.export(path)
    return path


def test_manifest_is_valid():
    from npe2 import PluginManifest

    manifest = PluginManifest.from_distribution("napari-imgreg")
    assert manifest.name == "napari-imgreg"
    keys = {s.key for s in manifest.contributions.sample_data}
    assert {"outcrop_model", "outcrop_photo"} <= keys


def test_axis_conversion_round_trips():
    xyz = np.random.default_rng(0).normal(size=(10, 3))
    np.testing.assert_array_equal(world_from_napari(napari_from_world(xyz)), xyz)
    # napari axis 0 is height, and the permutation is cyclic (keeps handedness).
    assert napari_from_world(np.array([1.0, 2.0, 3.0])).tolist() == [3.0, 1.0, 2.0]
    perm = np.eye(3)[[2, 0, 1]]
    assert np.linalg.det(perm) == pytest.approx(1.0)


def test_reader_only_claims_meshes(tmp_path):
    assert get_reader(str(tmp_path / "photo.jpg")) is None
    assert get_reader([str(tmp_path / "a.obj"), str(tmp_path / "b.obj")]) is None
    path = _marked_wall(tmp_path)
    reader = get_reader(str(path))
    assert callable(reader)
    (data, kwargs, kind), = reader(str(path))
    assert kind == "surface"
    assert kwargs["texture"].shape == (64, 128, 3)
    assert kwargs["texcoords"].shape == (4, 2)


@pytest.mark.parametrize("suffix", [".laz", ".e57", ".xyz"])
def test_reader_opens_a_lidar_scan_as_points(tmp_path, suffix):
    """napari.yaml lists the point-cloud formats: the reader must claim them."""
    from napari_imgreg.io.pointclouds import PointCloud, write_point_cloud

    rng = np.random.default_rng(2)
    xyz = np.column_stack([rng.uniform(0, 20, 5000), np.zeros(5000), rng.uniform(0, 10, 5000)])
    path = write_point_cloud(tmp_path / f"scan{suffix}",
                             PointCloud(xyz, intensity=rng.random(5000).astype(np.float32)))
    reader = get_reader(str(path))
    assert callable(reader)
    (data, kwargs, kind), = reader(str(path))
    assert kind == "points" and len(data) == 5000


# napari's 3D reset divides by the extent along each axis, and this test's wall
# is perfectly flat (no extent along y); a real outcrop model has relief.
@pytest.mark.filterwarnings("ignore:divide by zero encountered in divide:RuntimeWarning")
def test_opened_mesh_is_displayed_unmirrored(make_napari_viewer, tmp_path):
    """Seen from the south, looking north with z up, the red quadrant must be at
    the top left, exactly where our own renderer puts it."""
    viewer = make_napari_viewer(show=True)
    layers = viewer.open(str(_marked_wall(tmp_path)), plugin="napari-imgreg")
    assert layers[0].__class__.__name__ == "Surface"
    viewer.dims.ndisplay = 3
    viewer.reset_view()
    viewer.scene.camera.set_view_direction(
        view_direction=tuple(napari_from_world(np.array([0.0, 1.0, 0.0]))),
        up_direction=tuple(napari_from_world(np.array([0.0, 0.0, 1.0]))),
    )
    shot = viewer.screenshot(canvas_only=True)[..., :3].astype(int)
    red = (shot[..., 0] > 200) & (shot[..., 1] < 80) & (shot[..., 2] < 80)
    assert red.sum() > 100, "texture not shown"
    rows, cols = np.nonzero(red)
    wall = shot.sum(axis=2) > 60
    wall_rows, wall_cols = np.nonzero(wall)
    assert rows.mean() < wall_rows.mean(), "texture upside down"
    assert cols.mean() < wall_cols.mean(), "model mirrored"


def test_surface_layer_data_colour_modes():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    f = np.array([[0, 1, 2]])
    _, kw, _ = surface_layer_data(Scene(v, f, vertex_colors=np.full((3, 3), 255, np.uint8)))
    assert kw["vertex_colors"].max() == pytest.approx(1.0)
    _, kw, _ = surface_layer_data(Scene(v, f))
    assert "texture" not in kw and "vertex_colors" not in kw


@pytest.mark.slow
def test_sample_data_open_in_napari(make_napari_viewer):
    viewer = make_napari_viewer()
    viewer.open_sample("napari-imgreg", "outcrop_model")
    surface = viewer.layers[-1]
    assert surface.__class__.__name__ == "Surface"
    assert surface.texture is not None and len(surface.data[1]) > 10_000
    viewer.open_sample("napari-imgreg", "outcrop_photo")
    photo, render = viewer.layers[-2], viewer.layers[-1]
    assert photo.rgb and render.rgb
    assert photo.data.shape == render.data.shape
    # The render from the prior shows the outcrop: most of it is surface, not sky.
    assert (np.asarray(render.data).sum(axis=2) > 0).mean() > 0.3


# ------------------------------------------- plugin docks share one workbench
def _pump(qtbot, ms=50):
    qtbot.wait(ms)


def test_the_manifest_names_agree_with_the_dock_names():
    """The docks are named as napari's Plugins menu names them (its display name)."""
    from npe2 import PluginManifest

    from napari_imgreg.widgets import workbench as wbmod

    manifest = PluginManifest.from_distribution("napari-imgreg")
    assert manifest.name == wbmod.PLUGIN_NAME
    assert manifest.display_name == wbmod.PLUGIN_DISPLAY_NAME
    names = {w.display_name for w in manifest.contributions.widgets}
    assert {"Registration workbench", "Registration quality", "Campaign view"} <= names
    from napari.plugins import menu_item_template

    assert wbmod.WORKBENCH_NAME == menu_item_template.format(manifest.display_name,
                                                             "Registration workbench")
    assert menu_item_template.format(manifest.name, "Registration quality") in \
        wbmod.plugin_dock_names("Registration quality")


def test_docks_opened_through_the_plugin_api_share_one_controller(make_napari_viewer, qtbot,
                                                                   tmp_path, monkeypatch):
    """napari hands every plugin dock a new proxy of the viewer: the workbench,
    the quality dock, the campaign view, the File menu and a dropped workspace
    folder must all reach the same controller and workspace anyway."""
    from napari.utils._proxies import PublicOnlyProxy

    from napari_imgreg.widgets import workbench as wbmod
    from napari_imgreg.widgets._controller import controller_for, real_viewer
    from napari_imgreg.widgets.campaign import CampaignView
    from napari_imgreg.widgets.workbench import QualityDock, Workbench, workbench_for

    viewer = make_napari_viewer()
    _, wb = viewer.window.add_plugin_dock_widget("napari-imgreg", "Registration workbench")
    assert isinstance(wb, Workbench)
    assert isinstance(wb.viewer, PublicOnlyProxy)  # the proxy is involved
    qtbot.waitUntil(lambda: wb.quality is not None, timeout=5000)
    ctrl = wb.controller
    assert real_viewer(wb.viewer) is viewer and ctrl.viewer is viewer
    assert controller_for(viewer) is ctrl
    assert controller_for(PublicOnlyProxy(viewer)) is ctrl

    _, campaign = viewer.window.add_plugin_dock_widget("napari-imgreg", "Campaign view")
    assert isinstance(campaign, CampaignView)
    assert campaign.workspace is ctrl.workspace
    _, quality = viewer.window.add_plugin_dock_widget("napari-imgreg", "Registration quality")
    assert isinstance(quality, QualityDock) and quality.controller is ctrl

    # The File menu and the workspace reader find the docked workbench, under
    # whichever name napari gave it, through the viewer or a proxy of it.
    docks = set(viewer.window.dock_widgets)
    assert workbench_for(viewer) is wb
    assert workbench_for(PublicOnlyProxy(viewer)) is wb
    monkeypatch.setattr(wbmod, "_current_viewer", lambda: viewer)
    monkeypatch.setattr(wbmod.QFileDialog, "getExistingDirectory", lambda *a, **k: "")
    wbmod.menu_open_workspace()
    opened = []
    monkeypatch.setattr(ctrl, "open_workspace", opened.append)
    folder = tmp_path / "campaign.imgreg"
    folder.mkdir()
    (folder / "workspace.json").write_text("{}")
    reader = wbmod.get_workspace_reader(str(folder))
    assert reader is not None and reader(str(folder)) == [(None,)]
    assert opened == [folder]
    assert set(viewer.window.dock_widgets) == docks  # no second workbench


def test_the_plugins_menu_toggles_the_docked_quality_panel(make_napari_viewer, qtbot):
    """The workbench docks its quality panel under the Plugins menu's name: the
    menu's Registration quality toggles that dock instead of adding a second one;
    a campaign view from the menu shows the workbench's workspace."""
    from napari._app_model import get_app_model

    from napari_imgreg.widgets.workbench import QUALITY_NAME, WORKBENCH_NAME, Workbench

    viewer = make_napari_viewer(show=True)
    app = get_app_model()
    app.commands.execute_command("napari-imgreg.workbench").result()
    qtbot.waitUntil(lambda: QUALITY_NAME in viewer.window.dock_widgets, timeout=5000)
    wb = viewer.window.dock_widgets[WORKBENCH_NAME]
    assert isinstance(wb, Workbench)
    quality = viewer.window.dock_widgets[QUALITY_NAME]
    assert wb.quality is quality.panel
    qtbot.waitUntil(quality.isVisible, timeout=5000)
    docks = list(viewer.window.dock_widgets)
    app.commands.execute_command("napari-imgreg.quality").result()
    _pump(qtbot)
    assert list(viewer.window.dock_widgets) == docks
    assert not quality.isVisible()
    app.commands.execute_command("napari-imgreg.quality").result()
    _pump(qtbot)
    assert quality.isVisible()
    app.commands.execute_command("napari-imgreg.campaign_view").result()
    _pump(qtbot)
    campaign = [w for name, w in viewer.window.dock_widgets.items()
                if name.startswith("Campaign view")]
    assert len(campaign) == 1 and campaign[0].workspace is wb.controller.workspace
    # Workbench.add_to_viewer (scripts, the demo) gives the docked one back.
    assert Workbench.add_to_viewer(viewer) is wb


def test_the_interpret_dock_from_the_plugins_menu_stands_alone_without_a_workbench(
        make_napari_viewer):
    """Opened from the Plugins menu in a window without the workbench, the
    Interpret dock has no workspace, and no workbench controller is made for it."""
    from napari_imgreg.widgets._controller import _CONTROLLERS
    from napari_imgreg.widgets.interpret_widget import InterpretWidget

    viewer = make_napari_viewer()
    _, widget = viewer.window.add_plugin_dock_widget("napari-imgreg", "Interpret")
    assert isinstance(widget, InterpretWidget)
    assert widget.workspace is None
    assert _CONTROLLERS.get(id(viewer)) is None


def test_the_interpret_dock_from_the_plugins_menu_works_on_the_workbench_workspace(
        make_napari_viewer, qtbot):
    """Opened from the Plugins menu beside the workbench (through napari's
    plugin API, with its proxy of the viewer), the Interpret dock works on the
    workbench's workspace: it shows the drawings kept for the workspace's
    photos (the sample's example drawings here), as the photo changes."""
    from napari_imgreg.interpret.files import read_interpretations
    from napari_imgreg.widgets.interpret_widget import (
        InterpretWidget,
        interpretations_from_shapes,
    )

    viewer = make_napari_viewer()
    _, wb = viewer.window.add_plugin_dock_widget("napari-imgreg", "Registration workbench")
    ctrl = wb.controller
    try:
        wb.scene_panel.sample_button.click()
        qtbot.waitUntil(lambda: ctrl.current is not None, timeout=90_000)
        qtbot.waitUntil(lambda: not ctrl.busy, timeout=30_000)
        ws = ctrl.workspace
        drawings = {}
        for ps in ws.photos:
            path = ps.photo.path.with_name(ps.photo.path.stem + ".lines.geojson")
            drawings[ps.name] = read_interpretations(path)
            ws.set_interpretations(drawings[ps.name], ps)

        _, widget = viewer.window.add_plugin_dock_widget("napari-imgreg", "Interpret")
        assert isinstance(widget, InterpretWidget) and widget is not wb.interpret_widget
        assert widget.workspace is ws

        def shown_labels() -> list[str]:
            layer = widget.interpretation_layer(ctrl.photo_layer())
            assert layer is not None
            return [item.label for item in interpretations_from_shapes(layer)]

        for index in (0, 2):
            ctrl.select_photo(index)
            qtbot.waitUntil(lambda: not ctrl.busy, timeout=30_000)
            name = ws.current.name
            assert widget._photo_state(ctrl.photo_layer()) is ws.current
            assert shown_labels() == [item.label for item in drawings[name]], name
    finally:
        ctrl.workspace.detach()
