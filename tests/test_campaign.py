"""The campaign view in a real napari viewer (run under Xvfb): every camera
and mapped line of a workspace in 3D, every measurement on one stereonet,
following the workspace as it changes.

The workspace is the small sample with two photos registered (their true
poses, recorded as registrations) and interpreted (true bed boundaries drawn
on them, then projected), built as tests/test_workspace.py builds one.
"""

from __future__ import annotations

import numpy as np
import pytest

from napari_imgreg.interpret.project import Interpretation
from napari_imgreg.registration.params import RegistrationParams
from napari_imgreg.registration.pipeline import Registration, Trial
from napari_imgreg.sample import load_truth, sample_scene
from napari_imgreg.widgets._controller import CAMERA_MARKER
from napari_imgreg.widgets._layers import world_from_napari
from napari_imgreg.widgets.campaign import (
    CAMPAIGN_LAYER_KEY,
    STATUS_COLORS,
    CampaignView,
    fisher_plane,
)
from napari_imgreg.workspace import Workspace, read_photos, read_scene

pytestmark = pytest.mark.gui


@pytest.fixture(scope="module")
def sample():
    folder = sample_scene("small")
    scene, terrain = read_scene(folder / "outcrop.obj", dem=folder / "dem.tif")
    loaded, errors = read_photos(sorted(folder.glob("IMG_*.jpg")), scene)
    assert not errors
    return folder, scene, terrain, loaded


def _registration(ps, pose) -> Registration:
    trial = Trial(index=0, params=RegistrationParams(), metrics={"inliers_3d": 100}, q=0.8,
                  grade="good", hints=[], pose=pose, start_pose=ps.pose, rounds=1,
                  converged=True, verified=True, residual_flow_px=0.5)
    return Registration(status="registered", photo=ps.name, intrinsics=ps.intrinsics, pose=pose,
                        prior=ps.prior, metrics=trial.metrics, q=0.8, grade="good", hints=[],
                        trials=[trial], timings_s={"total": 1.0}, best_trial=0)


def _true_beds(truth, name, n=2, min_px=120.0):
    """Up to ``n`` true bed boundaries wholly inside a photo, as its pixels."""
    pt = truth.photos[name]
    out = []
    for feat in truth.lines["features"]:
        if feat["properties"]["label"] != "bed_boundary":
            continue
        px = pt.pose.project(pt.intrinsics, np.asarray(feat["geometry"]["coordinates"]))
        ok = np.isfinite(px).all(1) & (px[:, 0] > 5) & (px[:, 1] > 5)
        ok &= (px[:, 0] < pt.intrinsics.width - 5) & (px[:, 1] < pt.intrinsics.height - 5)
        if ok.all() and np.linalg.norm(np.diff(px, axis=0), axis=1).sum() > min_px:
            out.append(px)
    return out[:n]


@pytest.fixture
def campaign(sample):
    """Three photos; two registered and interpreted, the interpretations projected."""
    folder, scene, terrain, loaded = sample
    truth = load_truth(folder)
    ws = Workspace()
    ws.load_scene(scene, terrain, {"mesh": folder / "outcrop.obj", "dem": folder / "dem.tif"})
    ws.add_loaded_photos(loaded)
    for ps in ws.photos[:2]:
        pt = truth.photos[ps.name]
        ws.record_registration(_registration(ps, pt.pose), "Auto", ps=ps, pose_if_not_current=True)
        beds = _true_beds(truth, ps.name)
        assert beds, ps.name
        for px in beds:
            ws.add_interpretation(Interpretation("LineString", px, {"label": "sandstone"}), ps)
    ws.project_interpretations()
    return ws


def _cameras_world(layer):
    return world_from_napari(np.asarray(layer.data))


def test_campaign_view_shows_every_camera_line_and_measurement(make_napari_viewer, qtbot,
                                                                campaign):
    ws = campaign
    viewer = make_napari_viewer()
    view = CampaignView(viewer, workspace=ws)
    viewer.window.add_dock_widget(view, name="Campaign view")
    layers = view.layers()
    assert set(layers) == {"cameras", "frusta", "lines"}
    cams = layers["cameras"]
    np.testing.assert_allclose(_cameras_world(cams), [ps.pose.center for ps in ws.photos],
                               atol=1e-4)
    # Statuses: two registered, one not; colour says which.
    assert list(cams.features["status"]) == ["registered", "registered", "not registered"]
    np.testing.assert_allclose(cams.face_color[0][:3], _rgb(STATUS_COLORS["registered"]), atol=0.01)
    np.testing.assert_allclose(cams.face_color[2][:3], _rgb(STATUS_COLORS["not registered"]),
                               atol=0.01)
    # Markers scaled to the model as the workbench draws them (not metres-fixed).
    diag = float(np.linalg.norm(np.diff(ws.scene.bounds, axis=0)))
    assert cams.size[0] == pytest.approx(CAMERA_MARKER * diag, rel=1e-3)
    assert len(layers["frusta"].data) == 8 * len(ws.photos)
    # Every projected part of both photos is drawn, on the surface.
    parts = [p for f in ws.features_3d for p in f.parts if len(p) >= 2]
    lines = layers["lines"]
    assert len(lines.data) == len(parts) >= 2
    assert set(lines.features["photo"]) == {ws.photos[0].name, ws.photos[1].name}
    # The stereonet has every measurement; the Fisher mean of the bedding is the
    # sample's true bedding (12° dip) where planes were measured.
    assert f"{len(ws.measurements)} measurement(s) from 2 photo(s)" in view.figure.axes[0].get_title()
    if "sandstone" in view.fisher_means:
        dip, _ = fisher_plane(view.fisher_means["sandstone"])
        assert dip == pytest.approx(12.0, abs=6.0)
        assert "sandstone" in view.means_label.text()
    assert "3 photo(s)" in view.summary_label.text()
    # In 3D only (the layers are in metres, the photos in pixels).
    assert not cams.visible
    view.show_button.click()
    assert viewer.dims.ndisplay == 3
    assert all(layer.visible for layer in view.layers().values())
    assert view.layers()["cameras"] is cams  # updated in place, not made anew


def test_campaign_view_follows_the_workspace(make_napari_viewer, qtbot, campaign):
    ws = campaign
    viewer = make_napari_viewer()
    view = CampaignView(viewer, workspace=ws)
    viewer.window.add_dock_widget(view, name="Campaign view")
    # A photo accepted: its camera turns green.
    with qtbot.waitSignal(view.redrawn, timeout=5_000):
        ws.accept(ws.photos[0])
    cams = view.layers()["cameras"]
    assert cams.features["status"][0] == "accepted"
    np.testing.assert_allclose(cams.face_color[0][:3], _rgb(STATUS_COLORS["accepted"]), atol=0.01)
    # A pose nudged: the camera moves (many nudges, one redraw after them).
    ws.select_photo(2)
    before = _cameras_world(view.layers()["cameras"])[2].copy()
    with qtbot.waitSignal(view.redrawn, timeout=5_000):
        for _ in range(5):
            ws.nudge("forward 1 m", forward=1.0)
    after = _cameras_world(view.layers()["cameras"])[2]
    np.testing.assert_allclose(after, ws.photos[2].pose.center, atol=1e-4)
    assert np.linalg.norm(after - before) > 0.5
    # The interpretations of one photo dropped and re-projected: fewer lines, fewer poles.
    n_lines, lines_layer = len(view.layers()["lines"].data), view.layers()["lines"]
    ws.set_interpretations([], ws.photos[1])
    with qtbot.waitSignal(view.redrawn, timeout=5_000):
        ws.project_interpretations()
    lines = view.layers()["lines"]
    assert 0 < len(lines.data) < n_lines
    assert set(lines.features["photo"]) == {ws.photos[0].name}
    assert len(lines.edge_color) == len(lines.features) == len(lines.data)  # replaced in place
    assert lines is lines_layer
    # Closed: it stops following.
    view.close()
    assert not view._connected


def _rgb(hex_color):
    from matplotlib.colors import to_rgb

    return np.array(to_rgb(hex_color))


def test_the_fisher_mean_pole_gives_its_plane():
    from napari_imgreg.interpret.structural import FisherMean

    # A pole plunging 60° toward 030° is the normal of a plane dipping 30° toward 210°.
    mean = FisherMean(np.zeros(3), 60.0, 30.0, 3, 2.9, 20.0, 5.0)
    assert fisher_plane(mean) == pytest.approx((30.0, 210.0))


def test_the_dock_is_in_the_manifest():
    from npe2 import PluginManifest

    manifest = PluginManifest.from_distribution("napari-imgreg")
    names = {w.display_name: w.command for w in manifest.contributions.widgets}
    assert names["Campaign view"] == "napari-imgreg.campaign_view"
    cmd = next(c for c in manifest.contributions.commands if c.id == "napari-imgreg.campaign_view")
    assert cmd.python_name == "napari_imgreg.widgets.campaign:CampaignView"
    assert CAMPAIGN_LAYER_KEY == "imgreg_campaign"


def _workbench_with_sample(make_napari_viewer, qtbot, sample):
    """A viewer with the workbench docked through napari's plugin API (a proxy
    of the viewer), the sample's model and photos loaded in its workspace."""
    folder, scene, terrain, loaded = sample
    viewer = make_napari_viewer()
    _, wb = viewer.window.add_plugin_dock_widget("napari-imgreg", "Registration workbench")
    ws = wb.controller.workspace
    ws.load_scene(scene, terrain, {"mesh": folder / "outcrop.obj", "dem": folder / "dem.tif"})
    ws.add_loaded_photos(loaded)
    qtbot.waitUntil(lambda: not wb.controller.busy, timeout=30_000)
    return viewer, wb


def test_the_campaign_view_from_the_plugins_menu_shows_the_workbench_campaign(
        make_napari_viewer, qtbot, sample):
    """Opened through napari's plugin API (a proxy of the viewer), the view shows
    the workspace the workbench holds, not an empty one of its own."""
    viewer, wb = _workbench_with_sample(make_napari_viewer, qtbot, sample)
    ws = wb.controller.workspace
    _, view = viewer.window.add_plugin_dock_widget("napari-imgreg", "Campaign view")
    assert view.workspace is ws
    assert "3 photo(s)" in view.summary_label.text()
    assert len(view.layers()["cameras"].data) == 3
    # The view keeps the workspace's controller alive while it is docked.
    assert view.controller is wb.controller


def test_show_campaign_in_3d_shows_its_own_cameras_and_no_photo_drawings(
        make_napari_viewer, qtbot, sample):
    """In 3D the campaign's status-coloured cameras are not covered by the
    workbench's, and a photo's drawing (in pixels) is not left floating
    beside the model; back in 2D the drawing is shown again."""
    viewer, wb = _workbench_with_sample(make_napari_viewer, qtbot, sample)
    ws = wb.controller.workspace
    ws.add_interpretation(Interpretation("LineString", [[100.0, 100.0], [400.0, 150.0]],
                                         {"label": "sandstone"}), ws.photos[0])
    drawing = wb.interpret_widget.new_interpretation_layer()
    assert drawing is not None and drawing.visible
    _, view = viewer.window.add_plugin_dock_widget("napari-imgreg", "Campaign view")
    view.show_3d()
    qtbot.waitUntil(lambda: viewer.dims.ndisplay == 3, timeout=10_000)
    assert view.layers()["cameras"].visible
    for key in ("cameras", "frusta"):
        layer = wb.controller.layers.get(key)
        assert layer is None or not layer.visible
    assert not drawing.visible
    wb.controller.show_2d()
    assert drawing.visible
